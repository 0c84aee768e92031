"""Label volume + tissue table -> TissueModel (paper section 2; docs/method.md section 1).

Pipeline: check labels against the table -> choose slices -> per slice: muscle ray polygons, fat
rays, bone pixels -> link muscle components between slices into prism chains -> fat hexahedra ->
vertex sharing between tissues -> bone attachment -> bone meshes -> surfaces -> TissueModel.
See docs/builder.md for every decision and the Table-1 counting rules.
"""
from __future__ import annotations

import math
import time

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from tissue_sim.errors import UserError
from tissue_sim.core import model as M

from tissue_sim.core import geometry
from . import contours as CT
from . import slices as S
from . import table as TB
from .io import LabelVolume, voxel_to_model
from .rays import polygon_area
from .sharing import share_groups
from tissue_sim.core.build_settings import settings_with_defaults

FALLBACK_CORE = 0.3        # contour sections' ray fallback (the foot's lowest slices): an inner point at least this x the
                           # ray's length out, so that rays missing the non-fat tissue do not meet in a fan of wedges


def uniform_runs(rings: list, thin_m2: float, tol_m: float, max_gaps: int) -> list:
    """Indices of the rings of one muscle chain to keep. An inner ring is left out when it is thin (area
    at most ``thin_m2``: a tendon) and lies on the straight prism between the kept rings on either side
    (every vertex within ``tol_m`` of the linear interpolation along the chain's axis): a thin uniform
    section is one longer cell spanning up to ``max_gaps`` slice gaps instead of one cell per gap. The
    end rings are always kept; max_gaps = 1 keeps every ring (the paper's one cell per slice gap)."""
    if max_gaps < 2 or len(rings) < 3:
        return list(range(len(rings)))
    keep = [0]
    for j in range(2, len(rings)):
        if j - keep[-1] > max_gaps:                 # a merged cell spans at most max_gaps slice gaps
            keep.append(j - 1)
            continue
        a, b = rings[keep[-1]], rings[j]
        za, zb = a[:, 2].mean(), b[:, 2].mean()
        for m in range(keep[-1] + 1, j):
            r = rings[m]
            t = (r[:, 2].mean() - za) / (zb - za) if zb != za else 0.5
            dev = np.linalg.norm((r - ((1 - t) * a + t * b))[:, :2], axis=1).max()
            if abs(polygon_area(r[:, :2])) > thin_m2 or dev > tol_m:
                keep.append(j - 1)
                break
    keep.append(len(rings) - 1)
    return keep


def cut_fragments(chains: list, ring_area, slice_z, max_share: float) -> tuple[list, list]:
    """Split one muscle's chains (lists of (slice, component)) into pieces separated by slice gaps that no
    cell spans (a break), and leave out every piece but the largest whose volume (trapezoid rule over its
    rings' areas ``ring_area(slice, component)`` [m^2]) is at most ``max_share`` of the muscle's. Returns
    (chains kept, [{'from_slice', 'to_slice', 'volume_mm3', 'share'} per piece left out]). A larger piece
    is kept: the break check then reports it."""
    if max_share <= 0 or len(chains) < 2:
        return chains, []
    def vol(ch):
        a = [ring_area(z, i) for z, i in ch]
        return sum(0.5 * (a[q] + a[q + 1]) * abs(slice_z[ch[q + 1][0]] - slice_z[ch[q][0]]) for q in range(len(ch) - 1))
    pieces = []                                         # [first gap, last gap, chains]
    for ch in sorted(chains, key=lambda c: c[0][0]):
        g0, g1 = ch[0][0], ch[-1][0] - 1
        if pieces and g0 <= pieces[-1][1] + 1:
            pieces[-1][1] = max(pieces[-1][1], g1)
            pieces[-1][2].append(ch)
        else:
            pieces.append([g0, g1, [ch]])
    if len(pieces) < 2:
        return chains, []
    vols = [sum(vol(ch) for ch in p[2]) for p in pieces]
    total = sum(vols)
    big = int(np.argmax(vols))
    dropped, cut = set(), []
    for q, (p, v) in enumerate(zip(pieces, vols)):
        if q != big and v <= max_share * total:
            cut.append({'from_slice': int(p[0]), 'to_slice': int(p[1] + 1), 'volume_mm3': round(v * 1e9, 1),
                        'share': round(v / total, 5)})
            dropped.update(id(ch) for ch in p[2])
    return [ch for ch in chains if id(ch) not in dropped], cut


PATH_FIT_MOVE = 0.5        # smooth_path moves a ring by at most this x its mean radius (a jitter, not a bend)


def smooth_path(rings: list, reach: float, moves: list | None = None) -> list:
    """The rings of one muscle chain with the slice-to-slice jitter taken out of their centroid path: each inner ring
    i is moved across its slice (x, y) onto the curve fitted by weighted least squares to the chain's ring centroids
    against z (a parabola where its window holds five rings or more, else a line), weights 1 - |z - z_i| / reach
    (0 beyond reach), by at most PATH_FIT_MOVE x the ring's mean radius (where the path bends more than the fit
    follows, the ring stays near its outline). A ring whose window holds fewer than three rings stays, and so do the
    chain's end rings (its origin and insertion) and a ring that would move less than a micrometre (round-off).
    moves: each moved ring's distance [m] is appended. The contour outlines of the finer models' slices (2.5-5 mm
    apart) wander by ~1 mm from slice to slice, so that a chain's ring-centroid distances summed exceeded its path by
    up to a quarter (the 6x limb's biceps femoris long head: 490 against 394 mm through the unrefined limb's slices)
    and a contraction first straightened the zigzag (docs/builder.md "Muscle paths")."""
    if reach <= 0 or len(rings) < 3:
        return rings
    c = np.array([r[:, :2].mean(axis=0) for r in rings])
    z = np.array([float(r[:, 2].mean()) for r in rings])
    out = list(rings)
    for i in range(1, len(rings) - 1):
        w = np.maximum(0.0, 1.0 - np.abs(z - z[i]) / reach)
        k = np.count_nonzero(w > 0)
        if k < 3:
            continue
        dz = (z - z[i]) / reach                      # the fit about z_i: its value there is the constant term
        basis = np.stack([np.ones_like(dz), dz] + ([dz * dz] if k >= 5 else []), axis=1)
        sw = np.sqrt(w)
        coef = np.linalg.lstsq(basis * sw[:, None], c * sw[:, None], rcond=None)[0]
        d = coef[0] - c[i]
        rad = float(np.mean(np.linalg.norm(rings[i][:, :2] - c[i], axis=1)))
        n = float(np.linalg.norm(d))
        if n > PATH_FIT_MOVE * rad:
            d *= PATH_FIT_MOVE * rad / n
            n = PATH_FIT_MOVE * rad
        if n < 1e-6:
            continue
        q = rings[i].copy()
        q[:, :2] += d
        out[i] = q
        if moves is not None:
            moves.append(n)
    return out


def _check_labels(vol: LabelVolume, table: dict, allow_missing: bool, warnings: list):
    lab = vol.labels
    counts = np.zeros(1, np.int64)
    for k0 in range(0, lab.shape[2], 16):           # slabs: contiguous in Fortran order, small temporaries
        c = np.bincount(lab[:, :, k0:k0 + 16].ravel(order='K'))
        if len(c) > len(counts):
            c[:len(counts)] += counts
            counts = c
        else:
            counts[:len(c)] += c
    present = set(int(x) for x in np.nonzero(counts)[0]) - {0}
    tab = table['labels']
    unknown = sorted(present - set(tab))
    if unknown:
        raise UserError(f'{vol.source}: label(s) {unknown} occur in the volume but not in the tissue table '
                        f'{table["source"]} (add them, e.g. as fat or muscle, or relabel to 0)')
    missing = sorted(set(tab) - present)
    if missing:
        desc = ', '.join(f'{m} ({tab[m]["name"]})' for m in missing)
        if not allow_missing:
            raise UserError(f'{vol.source}: missing labels: the tissue table lists {desc} but the volume has no such voxels '
                            '(use --allow-missing to build without them)')
        warnings.append(f'labels absent from the volume, skipped: {desc}')
    if not any(tab[l]['tissue'] == 'fat' for l in present):
        raise UserError(f'{vol.source}: the volume has no fat voxels (fat label of the table)')
    if not any(tab[l]['tissue'] == 'bone' for l in present):
        raise UserError(f'{vol.source}: the volume has no bone voxels')
    return present, counts


def _select_slices(vol: LabelVolume, s: dict) -> np.ndarray:
    dz = vol.pixel_mm[2]
    body_k = np.nonzero(vol.labels.any(axis=(0, 1)))[0]
    if len(body_k) == 0:
        raise UserError(f'{vol.source}: the label volume is empty (all 0)')
    if s['slices'] is not None:
        n = int(s['slices'])
        span = int(body_k[-1] - body_k[0])
        if n > span + 1:
            how = f' (refine {s["refine"]:g})' if s['refine'] != 1 else ''
            raise UserError(f'{vol.source}: wrong spacing: {n} slices asked for{how} but the labelled extent has only {span + 1}')
        ks = np.unique(np.round(np.linspace(body_k[0], body_k[-1], n)).astype(int))
        step = None
    elif s['slice_step'] is not None:
        step = int(s['slice_step'])
    else:
        if s['slice_mm'] < dz * (1 - 1e-6):
            raise UserError(f'wrong spacing: --slice-mm {s["slice_mm"]:g} is finer than the volume\'s slice spacing {dz:g} mm')
        step = max(1, int(round(s['slice_mm'] / dz)))
    if step is not None:
        ks = np.arange(body_k[0], body_k[-1] + 1, step)
    if len(ks) < 2:
        raise UserError(f'{vol.source}: only {len(ks)} slice(s) at a step of {step} ({step * dz:g} mm) over the '
                        f'labelled extent {(body_k[-1] - body_k[0]) * dz:g} mm; need at least 2 (use a smaller --slice-mm)')
    empty = [int(k) for k in ks if k not in set(body_k.tolist())]
    if empty:
        raise UserError(f'{vol.source}: empty slice(s) {empty[:5]} inside the labelled range {int(body_k[0])}..{int(body_k[-1])} '
                        '(the body must be labelled on every slice used)')
    if vol.affine[2, 2] < 0:
        ks = ks[::-1]
    return ks


def segment_span(parent, a: int | None, b: int | None) -> np.ndarray | None:
    """Segment indices on the tree path from segment a to segment b (inclusive); None if either is None."""
    if a is None or b is None:
        return None

    def up(x):
        out = [x]
        while parent[out[-1]] >= 0:
            out.append(int(parent[out[-1]]))
        return out
    pa, pb = up(a), up(b)
    common = next(x for x in pa if x in pb)
    return np.array(pa[:pa.index(common) + 1] + pb[:pb.index(common)], dtype=np.int64)


def _nearest_on_triangles(tri: np.ndarray, p: np.ndarray) -> np.ndarray:
    """The point of the triangles tri (T, 3, 3) nearest to p (3,) (all triangles tried: build time, few points; trimesh's
    proximity queries would need rtree)."""
    import trimesh
    cp = trimesh.triangles.closest_point(tri, np.repeat(np.asarray(p, float)[None], len(tri), axis=0))
    return cp[int(np.argmin(np.linalg.norm(cp - p, axis=1)))]


def _bind_wrapped(pos, vseg, glides, ctiss, cmus_k, verts_k, offsets_k, bseg, bvo, bverts, bto, btris,
                  reach: float = 0.1, n_samples: int = 40, near: float = 1.5e-3):
    """Bind (in place, vseg) each free vertex of a gliding muscle that a bone of a segment it passes over hides from
    the muscle: the horizontal line from the vertex towards the muscle's side of that bone (the direction from the
    bone's centroid to the muscle's, both horizontal components) meets the bone within reach [m] (winding number
    > 0.5 at one of n_samples points along it) and that lies farther than near [m] (the contact grid's spacing,
    Params.contact_grid) from the bone: nearer, the bone contact holds it on the surface it slides round. Returns how
    many were bound."""
    from .bones import winding_number
    n = 0
    for m, row in glides.items():
        cm = np.flatnonzero((ctiss == M.TISSUE_MUSCLE) & (cmus_k == m))
        vm = np.unique(np.concatenate([verts_k[offsets_k[c]:offsets_k[c + 1]] for c in cm]))
        for b in range(len(bvo) - 1):
            sg = int(bseg[b])
            if not row[sg] or bto[b + 1] == bto[b]:
                continue
            V, T = bverts[bvo[b]:bvo[b + 1]], btris[bto[b]:bto[b + 1]]
            lo, hi = V.min(0), V.max(0)
            free = vm[(vseg[vm] < 0) & (pos[vm, 2] >= lo[2]) & (pos[vm, 2] <= hi[2])]
            if not len(free):
                continue
            d = pos[vm].mean(0) - V.mean(0)
            d[2] = 0.0
            if np.linalg.norm(d) < 1e-9:
                continue
            d /= np.linalg.norm(d)
            f = (np.arange(1, n_samples + 1) / n_samples * reach)[None, :, None]
            pts = (pos[free][:, None, :] + f * d[None, None, :]).reshape(-1, 3)
            box = np.all((pts >= lo) & (pts <= hi), axis=1)
            hit = np.zeros(len(pts), bool)
            if box.any():
                hit[box] = winding_number(V, T, pts[box]) > 0.5
            for v in free[hit.reshape(len(free), n_samples).any(1)]:
                if np.linalg.norm(_nearest_on_triangles(V[T], pos[v]) - pos[v]) <= near:
                    continue                                # on the bone's surface: the contact slides it round
                vseg[v] = sg
                n += 1
    return n


def _out_of_bones(pos, free, bvo, bverts, bto, btris, clearance: float, rounds: int = 3):
    """(positions, count moved): every free vertex inside a bone mesh (winding number > 0.5) moved to its
    closest point on that mesh plus clearance [m] along the direction out of it; repeated (a vertex moved
    into a neighbouring bone is moved again), at most rounds times."""
    from .bones import winding_number
    pos = pos.copy()
    moved = set()
    for _ in range(rounds):
        any_in = False
        for b in range(len(bvo) - 1):
            V, T = bverts[bvo[b]:bvo[b + 1]], btris[bto[b]:bto[b + 1]]
            if len(T) == 0:
                continue
            P = pos[free]
            lo, hi = V.min(0), V.max(0)
            box = np.flatnonzero(np.all((P >= lo) & (P <= hi), axis=1))
            if not len(box):
                continue
            ins = box[winding_number(V, T, P[box]) > 0.5]
            tri = V[T]
            for i in ins:
                cp = _nearest_on_triangles(tri, P[i])
                d = cp - P[i]
                n = d / max(np.linalg.norm(d), 1e-12)
                pos[free[i]] = cp + clearance * n
                moved.add(int(free[i]))
                any_in = True
        if not any_in:
            break
    return pos, len(moved)


def _sees_own_bone(p: np.ndarray, own: np.ndarray, other: np.ndarray) -> np.ndarray:
    """(n,) bool: the straight line in the slice from each point p (n, 2) to the nearest pixel of its own bone (own,
    pixel centres) does not cross another bone (other): it stays more than 0.75 pixel from every other-bone pixel,
    beyond its first 2 pixels (a point lying on the other bone starts there)."""
    if len(other) == 0:
        return np.ones(len(p), bool)
    tree_o = cKDTree(other)
    px = float(cKDTree(own).query(own[:1], k=2)[0][0, 1]) if len(own) > 1 else float(tree_o.query(other[:1], k=2)[0][0, 1])
    _, j = cKDTree(own).query(p)
    ok = np.ones(len(p), bool)
    for i, (a, b) in enumerate(zip(p, own[j])):
        n = int(np.ceil(np.linalg.norm(b - a) / (0.5 * px)))
        t = np.linspace(0.0, 1.0, n + 1)[:, None]
        q = a + t * (b - a)
        q = q[np.linalg.norm(q - a, axis=1) > 2.0 * px]
        if len(q) and tree_o.query(q)[0].min() < 0.75 * px:
            ok[i] = False
    return ok


def _muscle_span(entry, seg_names, skel) -> list:
    """The segments on the tree path between a muscle's origin and insertion segments (indices; [] without both)."""
    o, i_ = entry.get('origin'), entry.get('insertion')
    span = segment_span(skel['segment_parent'], seg_names.index(o) if o else None, seg_names.index(i_) if i_ else None)
    return [] if span is None else [int(x) for x in span]


def _section_holds(pos, polys, p, tol: float) -> bool:
    """Whether one of the ordered rings ``polys`` (vertex indices) holds the point p in its slice: p's (x, y) inside
    the polygon or within tol [m] of its outline."""
    from skimage.measure import points_in_poly
    for poly in polys:
        xy = pos[poly, :2]
        if points_in_poly(p[None, :2], xy)[0]:
            return True
        e = np.roll(xy, -1, 0) - xy
        t = np.clip(((p[:2] - xy) * e).sum(1) / np.maximum((e * e).sum(1), 1e-30), 0.0, 1.0)
        if np.min(np.linalg.norm(xy + t[:, None] * e - p[:2], axis=1)) <= tol:
            return True
    return False


def _turns_inside_out(pos, vseg, cells, verts, offsets, ring, si, skel, span) -> str | None:
    """The hinge whose range would turn a muscle cell next to ``ring`` inside out if ``ring`` were fixed to segment si:
    for each hinge with child si whose parent the muscle spans, the ring and the neighbouring cells' vertices bound to
    si turned about the hinge to each end of its range, every other vertex where it is (a free vertex is pulled along
    the muscle by its tension, not carried round by the bone). None if no cell's signed volume reaches 0."""
    from scipy.spatial.transform import Rotation
    from tissue_sim.core.geometry import prism_volumes
    rs = set(ring.tolist())
    nb = [c for c in cells if rs & set(verts[offsets[c]:offsets[c + 1]].tolist())]
    for j in range(len(skel['joint_names'])):
        if skel['joint_type'][j] != M.JOINT_HINGE or skel['joint_child'][j] != si or skel['joint_parent'][j] not in span:
            continue
        c0 = np.asarray(skel['joint_centre'][j], float)
        for ang in skel['joint_range'][j]:
            R = Rotation.from_rotvec(ang * np.asarray(skel['joint_axis'][j], float)).as_matrix()
            for c in nb:
                v = verts[offsets[c]:offsets[c + 1]]
                x = pos[v].copy()
                turn = np.isin(v, ring) | (vseg[v] == si)
                x[turn] = (x[turn] - c0) @ R.T + c0
                if prism_volumes(x, np.array([0, len(v)]), np.arange(len(v)))[0] <= 0.0:
                    return skel['joint_names'][j]
    return None


def anchor_muscle_ends(vslice, slice_z, verts, offsets, ctiss, cmus, mlabels, tab, seg_names, bonepix,
                       vseg, warnings, pos, allowed, vias: bool = False, via_m: float = 0.003, skel=None,
                       point_rings: list | None = None, point_names=None) -> dict:
    """Fix each muscle's proximal end ring to its origin segment and its distal end ring to its
    insertion segment (the tissue table's ``origin``/``insertion``; the paper takes muscle
    attachments from anatomy atlases, section 4.2), in place on ``vseg``.

    The end rings are the muscle's ring vertices on its highest (proximal, +z) and lowest slice.
    The whole ring is fixed, vertices shared (2.4) with the fat or with other muscles included: the
    active tension pulls on every ring vertex, and a shared vertex left free is pulled along the
    muscle by it (held only by its soft neighbours), so the muscle shortens inside and its cells lose
    their tension. Two guards: a shared vertex is not fixed to a segment outside the origin-insertion
    span of any muscle using it (``allowed``, (V, n_segments): nothing of a muscle is bound across a
    joint it does not cross), nor where another muscle's end ring claims it for a different segment.
    Where bones of other segments share the ring's slice, a ring vertex is fixed when the straight line to its
    own segment's bone crosses no other bone (``_sees_own_bone``): a ring wrapped round the femur beside the
    patella would swing its far side through the femur in flexion. Why not "only where nearer to the segment's bone
    than to any other": the vastus lateralis' insertion ring lies on the femur above the patella, and that rule fixes
    3 of its 11 vertices (the muscle then passes 27-59 N of its 5,149 N to the knee); all 11 see the patella, and,
    moving with it, they go at most 3.5 mm into the femur over 0-120 deg (docs/builder.md).
    With ``vias``, the ring on the muscle's slice nearest each of its via points (tissues.yaml ``via_points``: where
    the source model holds the path to a bone between its ends) is fixed to the via point's segment by the same
    rules, where that ring's section holds the via point (inside it or within ``via_m`` of its outline: the muscle lies
    where the source path runs); a via point beyond the muscle's slices (on a tendon the labels do not reach) or off
    the section, or whose ring fixed would turn a neighbouring cell inside out within the range of a joint the muscle
    crosses (``skel``), is skipped and listed (``vias_beyond_slices``, ``vias_off_section``, ``vias_inside_out``;
    docs/builder.md "Via points"). With ``point_rings`` (a list), a ring that fails only the inside-out test becomes
    a point via instead: (muscle index, the ring's vertices, segment index) is appended to it and the via point listed
    under ``vias_point`` (the solver holds the ring's centroid at its rest place in that segment's frame and lets the ring
    turn: a tendon passing a bone-fixed point, as the source model's path at its via point); ``point_names`` (a set of
    muscle names; None: every muscle) limits that to the muscles named.
    A ring is fixed only where a bone of that segment is present on the ring's slice, i.e. the
    ring lies along that bone: a ring across a joint from its bone (a belly ending above the
    patella, a calf muscle ending far above the foot) would become a rigid lever through the
    joint, so it is left free and a warning says so. Returns {muscle: {end: [segment, n_vertices]}}, end 'origin',
    'insertion' or 'via k' (k the via point's index)."""
    out = {}
    up = slice_z[-1] >= slice_z[0]
    proposals = {}                                   # vertex -> {muscle: segment}
    rings = []
    for m, lab in enumerate(mlabels):
        cells = np.flatnonzero((ctiss == M.TISSUE_MUSCLE) & (cmus == m))
        if cells.size == 0:
            continue
        vs = np.unique(np.concatenate([verts[offsets[c]:offsets[c + 1]] for c in cells]))
        zs = vslice[vs]
        ends = [('origin', zs.max() if up else zs.min(), tab[lab].get('origin')),
                ('insertion', zs.min() if up else zs.max(), tab[lab].get('insertion'))]
        if vias:
            polys = [p_ for c in cells for v_ in [verts[offsets[c]:offsets[c + 1]]]
                     for p_ in (v_[:len(v_) // 2], v_[len(v_) // 2:])]
            zu = np.unique(zs)
            lo, hi = sorted((slice_z[zu.min()], slice_z[zu.max()]))
            span = _muscle_span(tab[lab], seg_names, skel) if skel is not None else []
            for k, (seg, at) in enumerate(tab[lab].get('via_points', [])):
                zi = zu[np.argmin(np.abs(slice_z[zu] - at[2]))]
                if not lo <= at[2] <= hi:      # on a tendon beyond the labelled muscle (the ankle's retinacula)
                    out.setdefault(tab[lab]['name'], {}).setdefault('vias_beyond_slices', []).append(k)
                elif not _section_holds(pos, [p_ for p_ in polys if vslice[p_[0]] == zi], at, via_m):
                    out.setdefault(tab[lab]['name'], {}).setdefault('vias_off_section', []).append(k)
                elif all((zi, seg) != (z_, s_) for _, z_, s_ in ends):
                    if skel is not None and _turns_inside_out(pos, vseg, cells, verts, offsets, vs[zs == zi],
                                                              seg_names.index(seg), skel, span):
                        if point_rings is not None and (point_names is None or tab[lab]['name'] in point_names):
                            point_rings.append((m, vs[zs == zi], seg_names.index(seg)))
                            out.setdefault(tab[lab]['name'], {}).setdefault('vias_point', []).append(k)
                        else:
                            out.setdefault(tab[lab]['name'], {}).setdefault('vias_inside_out', []).append(k)
                    else:
                        ends.append((f'via {k}', zi, seg))
        for end, zi, seg in ends:
            if seg is None:
                continue
            ring = vs[zs == zi]
            bxy, blab = bonepix[zi]
            if any(tab[int(l)]['segment'] == seg for l in np.unique(blab)):
                si = seg_names.index(seg)
                mine = np.array([tab[int(l)]['segment'] == seg for l in blab])
                if not mine.all():
                    ring = ring[_sees_own_bone(pos[ring, :2], bxy[mine], bxy[~mine])]
                for v in ring.tolist():
                    proposals.setdefault(v, {})[m] = si
                rings.append((m, lab, end, seg, si, ring))
            else:
                warnings.append(f'muscle {tab[lab]["name"]}: no {seg} bone on the slice of its {end} ring '
                                f'(slice {int(zi)}, z {slice_z[zi]:.3f} m): left unanchored')
    for m, lab, end, seg, si, ring in rings:
        fix = [v for v in ring.tolist() if allowed[v, si] and all(s_ == si for s_ in proposals[v].values())]
        vseg[fix] = si
        out.setdefault(tab[lab]['name'], {})[end] = [seg, len(fix)]
        if len(fix) < len(ring):
            warnings.append(f'muscle {tab[lab]["name"]}: {len(ring) - len(fix)} of the {len(ring)} vertices of its {end} '
                            f'ring are shared with a muscle that does not span {seg} (or ends on another segment): '
                            f'left to their own binding')
    return out


def _wrap_arrays(tab, mlabels, seg_names) -> dict:
    """The TissueModel's wrap_* fields from the table's wrap_surfaces of the model's muscles (mlabels, in muscle order):
    one surface per name, in the order they first appear, with the geometry of its first entry; its muscles those that
    list it (their segments checked by load_tissue_table). UserError where two entries of one name differ."""
    surf, users = {}, {}
    for m, lab in enumerate(mlabels):
        for e in tab[lab].get('wrap_surfaces', []):
            q = np.zeros(3) if e['quadrant'] is None else e['quadrant']
            row = np.concatenate([e['centre'], e['axis'], q, [e['radius'], e['length']]])
            seg = seg_names.index(e['segment'])
            if e['name'] in surf:
                if surf[e['name']][0] != seg or np.max(np.abs(surf[e['name']][1] - row)) > 1e-9:
                    raise UserError(f'label {lab} ({tab[lab]["name"]}): wrap surface {e["name"]!r} differs from the one '
                                    f'of that name another muscle lists (segment or geometry)')
            else:
                surf[e['name']] = (seg, row)
            if m not in users.setdefault(e['name'], []):
                users[e['name']].append(m)
    names = list(surf)
    return {'wrap_names': tuple(names), 'wrap_segment': np.array([surf[n][0] for n in names], np.int32),
            'wrap_geometry': np.array([surf[n][1] for n in names], np.float64).reshape(-1, 11),
            'wrap_muscle_offsets': np.concatenate([[0], np.cumsum([len(users[n]) for n in names])]).astype(np.int64),
            'wrap_muscles': np.array([m for n in names for m in users[n]], np.int32)}


def build(vol: LabelVolume, table: dict, settings: dict | None = None, progress=None) -> tuple[M.TissueModel, dict]:
    """Build the TissueModel. ``progress(step_name, fraction)`` is called as the build advances."""
    t0 = time.perf_counter()
    s = settings_with_defaults(settings or {})
    prog = progress or (lambda *_: None)
    warnings: list[str] = []
    tab = table['labels']
    skel = table['skeleton']
    present, counts = _check_labels(vol, table, s['allow_missing'], warnings)
    muscle_labels = sorted(l for l in present if tab[l]['tissue'] == 'muscle')
    bone_labels = sorted(l for l in present if tab[l]['tissue'] == 'bone')
    fat_labels = sorted(l for l in present if tab[l]['tissue'] == 'fat')
    ks = _select_slices(vol, s)
    Z = len(ks)
    px_area_mm2 = vol.pixel_mm[0] * vol.pixel_mm[1]
    px_mm = max(vol.pixel_mm[0], vol.pixel_mm[1])
    attach_m = (px_mm if s['attach_mm'] is None else s['attach_mm']) / 1000.0
    prog('slices', 0.0)

    # ---------------------------------------------------------------- per slice
    geoms, regions, smalls, fats, bonepix, dropped, slice_counts = [], [], [], [], [], [], []
    maxlab = max(tab) + 1
    vox_counts = CT.label_slice_counts(vol.labels, muscle_labels) if s['sections'] == 'contour' and muscle_labels else {}
    substituted = {}                     # (label, slice index) -> the neighbouring voxel slice used instead
    for zi, k in enumerate(ks):
        sl = vol.labels[:, :, k]
        slice_counts.append(np.bincount(sl.ravel(), minlength=maxlab))
        g = S.slice_geom(vol.affine, int(k))
        geoms.append(g)
        regs, drop, sm = S.muscle_regions(sl, g, muscle_labels, s['muscle_rays'], s['min_area_mm2'], s['ray_hit'], 0.0,
                                            s['ray_origin'], s['sections'])
        for lab in muscle_labels if vox_counts else ():
            k2 = CT.glitch_substitute(vox_counts[lab], int(k))
            if k2 is None:
                continue
            r2, d2, s2 = S.muscle_regions(vol.labels[:, :, k2], g, [lab], s['muscle_rays'], s['min_area_mm2'], s['ray_hit'],
                                          0.0, s['ray_origin'], s['sections'])
            regs.pop(lab, None); sm.pop(lab, None)
            drop = [d for d in drop if d[0] != lab] + d2
            regs.update(r2); sm.update(s2)
            substituted[(lab, zi)] = k2
            slice_counts[-1][lab] = vox_counts[lab][k2]
            warnings.append(f'muscle {tab[lab]["name"]}: its area on slice {zi} (k={int(k)}, {int(vox_counts[lab][k])} voxels) '
                            f'jumps against both neighbouring voxel slices: the section of k={k2} '
                            f'({int(vox_counts[lab][k2])} voxels) is used (a labelling glitch)')
        regions.append(regs)
        smalls.append(sm)
        dropped += [{'slice': zi, 'label': l, 'name': tab[l]['name'], 'area_mm2': round(a, 2), 'reason': r} for l, a, r in drop]
        f = None
        if s['sections'] == 'contour':
            f = S.fat_contours(sl, g, bone_labels, fat_labels, s['fat_rays'])
        if f is None:
            f = S.fat_rays(sl, g, bone_labels, fat_labels, s['fat_rays'], s['min_fat_mm'] / 1000.0, 0.0)
        if not f['has_bone'] and s['sections'] == 'rays':
            warnings.append(f'slice {zi} (k={int(k)}) has no bone: fat rays start at the body centroid')
        fats.append(f)
        bonepix.append(S.bone_pixels(sl, g, bone_labels))
        prog('slices', (zi + 1) / Z)
    slice_z = np.array([g.z for g in geoms])
    if np.any(np.diff(slice_z) <= 0):
        raise UserError(f'{vol.source}: inconsistent slices: slice heights are not strictly monotonic')

    # ---------------------------------------------------------------- muscle chains
    n = s['muscle_rays']
    muscle_names, muscle_groups, mforce, mfibre, mscale, muscle_labels_used = [], [], [], [], [], []
    mrest = []
    pos_l, tis_l, ring_l, sl_l = [], [], [], []           # provisional vertices
    cells_m = []                                            # (muscle, slice, bottom ids, top ids)
    chains_m = []                                           # (muscle, [ring id arrays])
    ring_counter = [0]
    nv = [0]

    def new_ring(p, tissue, zi):
        ids = np.arange(nv[0], nv[0] + len(p))
        nv[0] += len(p)
        pos_l.append(p); tis_l.append(np.full(len(p), tissue)); ring_l.append(np.full(len(p), ring_counter[0]))
        sl_l.append(np.full(len(p), zi))
        ring_counter[0] += 1
        return ids

    area_rows = []
    not_represented = []                 # contour regions with a hole or without a simple ring (reported)
    single = []
    breaks = []
    path_moves = []                      # [m] each ring smooth_path moved (reported)
    fragments = []                       # small pieces of a muscle cut off by slices without its label (left out)
    bridged = CT.bridge_gaps(regions, smalls, muscle_labels, dropped)
    for lab in muscle_labels:
        mi = len(muscle_names)
        links = {}            # (zi, idx) -> idx on zi+1
        for zi in range(Z - 1):
            a, b = regions[zi].get(lab, []), regions[zi + 1].get(lab, [])
            if not a or not b:
                continue
            ov = np.array([[ra.overlap(rb) for rb in b] for ra in a], dtype=float)
            used_a, used_b = set(), set()
            for flat in np.argsort(-ov, axis=None):
                i, j = np.unravel_index(flat, ov.shape)
                if ov[i, j] <= 0:
                    break
                if i in used_a or j in used_b:
                    continue
                links[(zi, i)] = j; used_a.add(i); used_b.add(j)
            for i, ra in enumerate(a):       # no overlap: nearest centroid within the equivalent radius
                if i in used_a:
                    continue
                best, bd = None, np.inf
                for j, rb in enumerate(b):
                    if j in used_b:
                        continue
                    dpx = np.linalg.norm(ra.centroid_px() - rb.centroid_px())
                    req = math.sqrt(max(ra.mask.sum(), rb.mask.sum()) / math.pi)
                    if dpx < req and dpx < bd:
                        best, bd = j, dpx
                if best is not None:
                    links[(zi, i)] = best; used_b.add(best); used_a.add(i)
            if not used_a:
                # the muscle is on both slices but no component overlaps or lies near (a thin tendon
                # beside its belly): link the nearest pair, so the muscle stays one chain
                d = np.array([[np.linalg.norm(ra.centroid_px() - rb.centroid_px()) for rb in b] for ra in a])
                i, j = np.unravel_index(np.argmin(d), d.shape)
                links[(zi, int(i))] = int(j)
        linked_to = {(zi + 1, j) for (zi, _), j in links.items()}
        ring_ids = {}
        chains = []
        for zi in range(Z):
            for i, reg in enumerate(regions[zi].get(lab, [])):
                if (zi, i) in linked_to:
                    continue                                   # not a chain start
                if (zi, i) not in links:
                    single.append({'slice': zi, 'label': lab, 'name': tab[lab]['name'], 'area_mm2': round(reg.area_mm2, 2),
                                   'reason': 'present on one used slice only (no cell)'})
                    continue
                chain, z, ii = [], zi, i
                while True:
                    chain.append((z, ii))
                    if (z, ii) not in links:
                        break
                    ii = links[(z, ii)]; z += 1
                chains.append(chain)
        chains, cut = cut_fragments(chains, lambda z, ii: abs(polygon_area(regions[z][lab][ii].ring[:, :2])), slice_z,
                                    s['max_fragment'])
        for f in cut:
            f.update(muscle=tab[lab]['name'], label=lab)
            fragments.append(f)
            warnings.append(f'muscle {tab[lab]["name"]}: a fragment on slices {f["from_slice"]}-{f["to_slice"]} '
                            f'({f["volume_mm3"]:.0f} mm^3, {100 * f["share"]:.2f} % of the muscle) is cut off from the muscle '
                            f'by slices without its label: left out (max_fragment {s["max_fragment"]:g})')
        if not chains:
            warnings.append(f'muscle {tab[lab]["name"]} (label {lab}) gives no cell at this slice spacing: left out of the model')
            continue
        covered = sorted({z for ch in chains for (z, _) in ch[:-1]})
        z = covered[0]
        while z < covered[-1]:
            if z in covered:
                z += 1
                continue
            z1 = next(c for c in covered if c > z)
            absent = [q for q in range(z + 1, z1) if not regions[q].get(lab)]
            breaks.append({'muscle': tab[lab]['name'], 'label': lab, 'from_slice': z, 'to_slice': z1,
                           'reason': f'label absent on slice(s) {absent}' if absent else 'no cell links the slices'})
            z = z1
        if s['sections'] == 'contour':
            CT.chain_rings(chains, regions, lab, n, vox_counts[lab], ks, {z: k2 for (l, z), k2 in substituted.items() if l == lab})
        muscle_names.append(tab[lab]['name']); muscle_groups.append(tab[lab]['group']); muscle_labels_used.append(lab)
        mforce.append(tab[lab]['max_isometric_force']); mfibre.append(tab[lab]['optimal_fibre_length'])
        mrest.append(tab[lab]['rest_fibre_length'])
        mscale.append(tab[lab]['stiffness_scale'])
        biggest = max(abs(polygon_area(regions[z][lab][ii].ring[:, :2])) for ch in chains for (z, ii) in ch)
        for chain in chains:
            rings = [regions[z][lab][ii].ring for (z, ii) in chain]
            chain = [chain[q] for q in uniform_runs(rings, s['tendon_frac'] * biggest, s['merge_tol'] * math.sqrt(biggest / math.pi),
                                                    s['merge_gaps'])]
            rids = []
            rings = smooth_path([regions[z][lab][ii].ring for (z, ii) in chain], s['path_smooth_mm'] / 1000.0, path_moves)
            for (z, ii), ring in zip(chain, rings):
                rids.append(new_ring(ring, mi, z))
            cids = []
            for c in range(len(chain) - 1):
                cids.append(len(cells_m))
                cells_m.append((mi, chain[c][0], rids[c], rids[c + 1]))
            chains_m.append((mi, rids, cids))
        for zi in range(Z):
            rs = regions[zi].get(lab, [])
            if rs:
                area_rows.append({'muscle': tab[lab]['name'], 'slice': zi,
                                  'label_mm2': round(float(slice_counts[zi][lab]) * px_area_mm2, 2),
                                  'polygon_mm2': round(sum(r.poly_area_mm2 for r in rs), 2),
                                  'sections': sorted({r.origin_kind for r in rs})})
                for r in rs:
                    if s['sections'] == 'contour' and r.origin_kind != 'contour':
                        not_represented.append({'muscle': tab[lab]['name'], 'slice': zi, 'area_mm2': round(r.area_mm2, 1),
                                                'how': r.origin_kind})
    if breaks and not s['allow_broken']:
        b = breaks[0]
        more = f' (and {len(breaks) - 1} more break(s))' if len(breaks) > 1 else ''
        raise UserError(f'{vol.source}: muscle {b["muscle"]} (label {b["label"]}) breaks between slices {b["from_slice"]} and '
                        f'{b["to_slice"]}: {b["reason"]}{more} (use --allow-broken-muscles to build it in pieces)')
    for b in breaks:
        warnings.append(f'muscle {b["muscle"]} breaks between slices {b["from_slice"]} and {b["to_slice"]} ({b["reason"]}): '
                        'built in pieces (allow_broken)')
    prog('chains', 1.0)

    # ---------------------------------------------------------------- fat tube
    nf = s['fat_rays']
    if s['sections'] == 'contour':
        def fallback(zi, ref):          # contour rings that cross: the paper's rays on that slice, least twist (core)
            return CT.turn_rays(lambda off: S.fat_rays(vol.labels[:, :, ks[zi]], geoms[zi], bone_labels, fat_labels, nf,
                                                       s['min_fat_mm'] / 1000.0, off, FALLBACK_CORE), nf, ref)
        fats, bad = CT.fat_rings(fats, nf, s['min_fat_mm'] / 1000.0, fallback, s['fat_follow'])
        for zi in bad:
            warnings.append(f'slice {zi}: the fat layer\'s outlines give crossing cells: rays used on this slice')
    fat_ring = []
    for zi in range(Z):
        fat_ring.append(new_ring(np.concatenate([fats[zi]['inner'], fats[zi]['outer']]), -1, zi))
    cells_f = []
    for zi in range(Z - 1):
        lo, hi = fat_ring[zi], fat_ring[zi + 1]
        for a in range(nf):
            b = (a + 1) % nf
            q = [a, b, nf + b, nf + a]                  # inner a, inner b, outer b, outer a
            cells_f.append((zi, lo[q], hi[q]))

    pos0 = np.concatenate(pos_l)
    tis0 = np.concatenate(tis_l)
    ring0 = np.concatenate(ring_l)
    sl0 = np.concatenate(sl_l)
    C_m, C_f = len(cells_m), len(cells_f)
    sizes = np.array([2 * n] * C_m + [8] * C_f, dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    verts0 = np.concatenate([np.concatenate([c[2], c[3]]) for c in cells_m] + [np.concatenate([c[1], c[2]]) for c in cells_f])
    flip = np.array([False] * C_m + [True] * C_f)
    min_vol = s['min_cell_volume_mm3'] * 1e-9

    # ---------------------------------------------------------------- vertex sharing (guarded)
    eligible = np.ones(len(pos0), bool)
    vol_pre = geometry.prism_volumes(pos0, offsets, verts0, flip)
    bad_pre = np.nonzero(vol_pre < min_vol)[0]
    for it in range(6):
        rep = share_groups(pos0, tis0, ring0, sl0, s['share_mm'] / 1000.0, eligible)
        uniq, inv = np.unique(rep, return_inverse=True)
        cnt = np.bincount(inv)
        pos = np.zeros((len(uniq), 3))
        np.add.at(pos, inv, pos0)
        pos /= cnt[:, None]
        verts = inv[verts0]
        vols = geometry.prism_volumes(pos, offsets, verts, flip)
        bad = np.setdiff1d(np.nonzero(vols < min_vol)[0], bad_pre)
        if len(bad) == 0:
            break
        # un-share every group that touches a cell the merge made degenerate, then redo
        for c in bad:
            groups = inv[verts0[offsets[c]:offsets[c + 1]]]
            eligible[np.isin(inv, groups) & (cnt[inv] > 1)] = False
    shared_group = cnt > 1
    n_unshared = int(np.count_nonzero(~eligible))

    # ---------------------------------------------------------------- degenerate cells: drop
    keep = vols >= min_vol
    dropped_cells = [{'cell': int(c), 'tissue': 'muscle' if c < C_m else 'fat',
                      'muscle': muscle_names[cells_m[c][0]] if c < C_m else '',
                      'volume_mm3': round(float(vols[c]) * 1e9, 4)} for c in np.nonzero(~keep)[0]]
    cell_slice_all = np.array([c[1] for c in cells_m] + [c[0] for c in cells_f], dtype=np.int32)
    cell_tissue_all = np.array([M.TISSUE_MUSCLE] * C_m + [M.TISSUE_FAT] * C_f, dtype=np.uint8)
    cell_muscle_all = np.array([c[0] for c in cells_m] + [-1] * C_f, dtype=np.int32)
    fat_scale = tab[fat_labels[0]]['stiffness_scale']
    k_all = np.array([mscale[c[0]] for c in cells_m] + [fat_scale] * C_f, dtype=np.float64)
    kc = np.nonzero(keep)[0]
    sizes_k = sizes[kc]
    offsets_k = np.concatenate([[0], np.cumsum(sizes_k)])
    verts_k = np.concatenate([verts[offsets[c]:offsets[c + 1]] for c in kc]) if len(kc) else np.zeros(0, np.int64)
    # drop vertices no kept cell uses
    used = np.zeros(len(pos), bool); used[verts_k] = True
    remap = np.cumsum(used) - 1
    pos = pos[used]; verts_k = remap[verts_k]
    shared_group = shared_group[used]
    vslice = np.zeros(len(uniq), np.int64); vslice[inv] = sl0
    vslice = vslice[used]
    V = len(pos)
    C = len(kc)
    ctiss = cell_tissue_all[kc]

    # ---------------------------------------------------------------- flags
    flags = np.zeros(V, np.uint8)
    cv_t = np.repeat(ctiss, sizes_k)
    flags[verts_k[cv_t == M.TISSUE_MUSCLE]] |= M.VF_MUSCLE
    flags[verts_k[cv_t == M.TISSUE_FAT]] |= M.VF_FAT
    flags[shared_group] |= M.VF_SHARED

    # ---------------------------------------------------------------- bone attachment
    # A vertex is fixed to the nearest bone within attach_m whose segment lies on the path between
    # the origin and insertion segments of every muscle using the vertex: nothing of a muscle is
    # bound across a joint it does not cross (the fat, and muscles without origin/insertion, any).
    # With bind_passed_over off, a segment strictly between a muscle's origin and insertion (the shank
    # for the gastrocnemii) is one it glides over: its vertices are not bound to that bone by
    # proximity, and by an end ring only where a muscle arising from that bone shares them (the
    # soleus's origin ring beside the gastrocnemius lateralis; not the insertion rings of the tendons
    # beside the medialis, which pinned its belly to the tibia: docs/anatomy.md, the gastrocnemii).
    seg_names = skel['segment_names']
    nseg = len(seg_names)
    cmus_k = cell_muscle_all[kc]
    allowed = np.ones((V, nseg), bool)
    passed = np.zeros((V, nseg), bool)               # a muscle using the vertex passes over the segment
    arises = np.zeros((V, nseg), bool)               # a muscle using the vertex arises from the segment
    glides = {}                                      # muscle -> the segments it passes over (bind_passed_over off)
    for m, lab in enumerate(muscle_labels_used):
        o, i_ = tab[lab].get('origin'), tab[lab].get('insertion')
        span = _muscle_span(tab[lab], seg_names, skel)
        if not span:
            continue
        row = np.zeros(nseg, bool); row[span] = True
        cm = np.flatnonzero((ctiss == M.TISSUE_MUSCLE) & (cmus_k == m))
        vm = np.unique(np.concatenate([verts_k[offsets_k[c]:offsets_k[c + 1]] for c in cm]))
        allowed[vm] &= row
        # an end ring that anchor_muscle_ends fixes (its segment's bone on its slice) and the ring next to it are
        # bound to that segment or left free, never by proximity to another bone: the end cell does not straddle
        # a joint (the vastus medialis' end cell between its patella ring and 5 femur-bound vertices 17 mm above
        # inverted when the knee flexed; docs/builder.md)
        zs, up = vslice[vm], slice_z[-1] >= slice_z[0]
        for seg, zi, step in ((o, zs.max() if up else zs.min(), -1 if up else 1), (i_, zs.min() if up else zs.max(), 1 if up else -1)):
            if seg is not None and any(tab[int(l)]['segment'] == seg for l in np.unique(bonepix[zi][1])):
                own = np.zeros(nseg, bool); own[seg_names.index(seg)] = True
                allowed[vm[(zs == zi) | (zs == zi + step)]] &= own
        if not s['bind_passed_over']:
            row[[seg_names.index(o), seg_names.index(i_)]] = False
            passed[vm] |= row
            arises[vm, seg_names.index(o)] = True
            glides[m] = row
    vseg = np.full(V, -1, np.int32)
    refused = 0
    bone_touch = {}
    for zi in range(Z):
        bxy, blab = bonepix[zi]
        on = np.nonzero(vslice == zi)[0]
        if len(bxy) == 0 or len(on) == 0:
            continue
        bseg_px = np.array([seg_names.index(tab[int(l)]['segment']) for l in blab])
        D = np.full((len(on), nseg), np.inf)
        for sg in np.unique(bseg_px):
            d, _ = cKDTree(bxy[bseg_px == sg]).query(pos[on, :2])
            D[:, sg] = np.maximum(d - 0.5 * px_mm / 1000.0, 0.0)
        near = D.min(axis=1) <= attach_m + 1e-12
        D[~(allowed & ~passed)[on]] = np.inf
        best = np.argmin(D, axis=1)
        hit = D[np.arange(len(on)), best] <= attach_m + 1e-12
        refused += int(np.count_nonzero(near & ~hit))
        vseg[on[hit]] = best[hit]
        if hit.any():                                    # which bone each attached vertex touches
            ok = np.isin(bseg_px, best[hit])
            _, j = cKDTree(bxy[ok]).query(pos[on[hit], :2])
            for l in blab[ok][j]:
                bone_touch[tab[int(l)]['name']] = bone_touch.get(tab[int(l)]['name'], 0) + 1

    # ---------------------------------------------------------------- muscle origins and insertions
    point_rings = [] if s['point_vias'] else None
    point_names = set(s['point_vias']) if isinstance(s['point_vias'], list) else None
    anchors = anchor_muscle_ends(vslice, slice_z, verts_k, offsets_k, ctiss, cmus_k, muscle_labels_used,
                                 tab, seg_names, bonepix, vseg, warnings, pos,
                                 allowed if s['unshare_passed_over'] else allowed & ~(passed & ~arises),
                                 vias=s['via_points'], via_m=float(s['via_mm']) * 1e-3, skel=skel,
                                 point_rings=point_rings, point_names=point_names) if s['anchor_muscles'] else {}
    point_rings = point_rings or []

    # ---------------------------------------------------------------- gliding muscles: their own vertices
    # With unshare_passed_over (and bind_passed_over off), every end ring is anchored, and a vertex bound to
    # a segment that a muscle using it passes over (an origin or insertion ring on that bone, shared with a
    # gastrocnemius beside it) is split: the passing muscle's cells get a free copy at the same place, the
    # ring keeps its anchor. The gastrocnemii lie in their own compartment and glide over the shank's
    # muscles; one such shared vertex bound to the tibia pinned the medialis' cells below the knee, and
    # left free, the hamstrings' insertion rings lost their anchor there (docs/anatomy.md, the gastrocnemii).
    # A point via ring's vertices count as held by its segment here: a gliding muscle sharing one gets its own copy
    # (the gastrocnemius medialis beside semitendinosus' ring on the 3x limb was dragged by the ring's projection).
    held = vseg.copy()
    for _, ring, sg in point_rings:
        held[ring[held[ring] < 0]] = sg
    split = {}                                       # (muscle, vertex) -> its own vertex
    if not s['bind_passed_over'] and s['unshare_passed_over'] and glides:
        cmv = np.repeat(np.where(ctiss == M.TISSUE_MUSCLE, cmus_k, -1), sizes_k)
        for e in np.flatnonzero(cmv >= 0):
            m, v = int(cmv[e]), int(verts_k[e])
            if held[v] >= 0 and m in glides and glides[m][held[v]]:
                verts_k[e] = split.setdefault((m, v), V + len(split))
        if split:
            old = np.array([v for _, v in split], np.int64)
            pos = np.concatenate([pos, pos[old]])
            vseg = np.concatenate([vseg, np.full(len(old), -1, vseg.dtype)])
            flags = np.concatenate([flags, np.full(len(old), M.VF_MUSCLE, flags.dtype)])
            V = len(pos)

    # ---------------------------------------------------------------- cells: fibres
    P = [pos[verts_k[offsets_k[c]:offsets_k[c + 1]]] for c in range(C)]
    fib = np.array([p[len(p) // 2:].mean(0) - p[:len(p) // 2].mean(0) for p in P]).reshape(C, 3)
    fib /= np.linalg.norm(fib, axis=1, keepdims=True)

    # ---------------------------------------------------------------- skin quads and surfaces
    quads, qcell = [], []
    for c in range(C):
        if ctiss[c] == M.TISSUE_FAT:
            v = verts_k[offsets_k[c]:offsets_k[c] + 8]
            quads.append([v[3], v[2], v[6], v[7]])          # outer a bot, outer b bot, outer b top, outer a top
            qcell.append(c)
    quads = np.array(quads, np.int32).reshape(-1, 4)
    qcell = np.array(qcell, np.int32)
    flags[quads.ravel()] |= M.VF_SKIN
    finv = remap[inv]                                     # provisional vertex -> final vertex
    groups, gnames = [], []

    def add(tris, name):
        if len(tris):
            if name not in gnames:
                gnames.append(name)
            groups.append((np.asarray(tris, np.int32), gnames.index(name)))

    def own(mi, ring):                                   # a gliding muscle's ring: its own (split) vertices
        return np.array([split.get((mi, int(v)), int(v)) for v in ring]) if split else ring

    for mi, rids, cids in chains_m:
        # a chain is split into runs of kept cells (a dropped degenerate cell opens it)
        run = []
        for ci, cid in enumerate(cids + [None]):
            if cid is not None and keep[cid]:
                if not run:
                    run.append(own(mi, finv[rids[ci]]))
                run.append(own(mi, finv[rids[ci + 1]]))
            elif run:
                add(geometry.chain_surface(run, pos), f'muscle/{muscle_names[mi]}')
                run = []
    if len(quads):
        add(np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]]), 'skin')
        inner = []
        for c in range(C):
            if ctiss[c] == M.TISSUE_FAT:
                v = verts_k[offsets_k[c]:offsets_k[c] + 8]
                inner += [[v[0], v[4], v[5]], [v[0], v[5], v[1]]]      # faces the limb axis
        add(inner, 'fat/inner')
        caps = []
        cs_k = cell_slice_all[kc]
        for c in range(C):
            if ctiss[c] != M.TISSUE_FAT:
                continue
            v = verts_k[offsets_k[c]:offsets_k[c] + 8]
            if cs_k[c] == 0:                                            # bottom ring is clockwise: faces down
                caps += [[v[0], v[1], v[2]], [v[0], v[2], v[3]]]
            if cs_k[c] == Z - 2:                                        # top ring reversed: faces up
                caps += [[v[7], v[6], v[5]], [v[7], v[5], v[4]]]
        add(caps, 'fat/caps')
    surf_t = np.concatenate([g[0] for g in groups]) if groups else np.zeros((0, 3), np.int32)
    surf_g = np.concatenate([np.full(len(g[0]), g[1], np.int32) for g in groups]) if groups else np.zeros(0, np.int32)
    prog('cells', 1.0)

    # ---------------------------------------------------------------- bones
    from .bones import bone_meshes
    bnames, bseg, bvo, bverts, bto, btris, bone_info = bone_meshes(vol, tab, bone_labels, seg_names, s['bone_mesh_step'])
    for b in bone_info:
        if b['label_inside_mesh'] is not None and b['label_inside_mesh'] < 0.5:
            warnings.append(f'bone {b["bone"]}: only {100 * b["label_inside_mesh"]:.0f} % of its label voxels lie inside its '
                            f'mesh ({b["surface"]}): check that the mesh is in the model frame, in metres')
    prog('bones', 1.0)

    # ---------------------------------------------------------------- free vertices out of the bones
    # The label volume's soft tissue and the bone meshes come from different sources, so a few free vertices
    # lie inside a bone at rest (17 of the gastrocnemii in the tibia's top, up to 1.6 mm deep on the bundled
    # limb). The bone contact keeps a free vertex no deeper than it lies at rest, so such a vertex could stay
    # or go deeper than the 1-mm criterion; it is moved out along its closest-point direction to bone_clearance_mm
    # from the surface (docs/builder.md "Free vertices inside a bone").
    n_moved_out = 0
    if s['bone_clearance_mm'] is not None and len(bnames):
        pos, n_moved_out = _out_of_bones(pos, np.flatnonzero(vseg < 0), bvo, bverts, bto, btris,
                                         float(s['bone_clearance_mm']) * 1e-3)
        if n_moved_out:
            P = [pos[verts_k[offsets_k[c]:offsets_k[c + 1]]] for c in range(C)]
            fib = np.array([p[len(p) // 2:].mean(0) - p[:len(p) // 2].mean(0) for p in P]).reshape(C, 3)
            fib /= np.linalg.norm(fib, axis=1, keepdims=True)

    # ---------------------------------------------------------------- gliding muscles wrapped round a bone
    # A muscle glides over a bone it passes over on its own side of it. Where its section wraps round that
    # bone (the bone lies between one of its vertices and the muscle's side of it), that part cannot glide:
    # left free, it is dragged across the bone by the rest of the muscle. Such a vertex is bound to the bone's
    # segment (docs/builder.md "Gliding muscles wrapped round a bone").
    n_wrapped = 0
    if glides and len(bnames):
        n_wrapped = _bind_wrapped(pos, vseg, glides, ctiss, cmus_k, verts_k, offsets_k, bseg, bvo, bverts, bto, btris)

    cell_vol = vols[kc]
    wraps = _wrap_arrays(tab, muscle_labels_used, skel['segment_names'])
    tm = M.TissueModel(
        name=table['name'],
        rest_positions=pos, vertex_segment=vseg, vertex_flags=flags,
        cell_offsets=offsets_k.astype(np.int64), cell_vertices=verts_k.astype(np.int32),
        via_point_offsets=np.concatenate([[0], np.cumsum([len(r) for _, r, _ in point_rings])]).astype(np.int64),
        via_point_vertices=(np.concatenate([r for _, r, _ in point_rings]) if point_rings else np.zeros(0)).astype(np.int32),
        via_point_segment=np.array([sg for _, _, sg in point_rings], np.int32),
        via_point_muscle=np.array([m for m, _, _ in point_rings], np.int32),
        **wraps,
        cell_tissue=ctiss, cell_muscle=cell_muscle_all[kc], cell_fibre=fib,
        cell_slice=cell_slice_all[kc], cell_k_scale=k_all[kc],
        skin_quads=quads, skin_quad_cell=qcell,
        surface_triangles=surf_t.reshape(-1, 3), surface_group=surf_g, surface_group_names=tuple(gnames),
        muscle_names=tuple(muscle_names), muscle_groups=tuple(muscle_groups),
        muscle_max_force=np.array(mforce, np.float64), muscle_fibre_length=np.array(mfibre, np.float64),
        muscle_rest_fibre_length=np.array(mrest, np.float64),
        **dict(zip(('path_muscle', 'path_data', 'path_powers', 'path_coef'),
                   TB.path_arrays(table.get('muscle_paths', {}), muscle_names, len(skel['joint_names'])))),
        bone_names=bnames, bone_segment=bseg, bone_vertex_offsets=bvo, bone_vertices=bverts,
        bone_triangle_offsets=bto, bone_triangles=btris,
        segment_names=skel['segment_names'], segment_parent=skel['segment_parent'],
        segment_mass=skel['segment_mass'], segment_com=skel['segment_com'], segment_inertia=skel['segment_inertia'],
        joint_names=skel['joint_names'], joint_type=skel['joint_type'], joint_parent=skel['joint_parent'],
        joint_child=skel['joint_child'], joint_axis=skel['joint_axis'], joint_centre=skel['joint_centre'],
        joint_range=skel['joint_range'], joint_rest=skel['joint_rest'],
        joint_driver=skel['joint_driver'], coupling_offsets=skel['coupling_offsets'],
        coupling_table=skel['coupling_table'], joint_path_offsets=skel['joint_path_offsets'],
        joint_path_table=skel['joint_path_table'], joint_path_axes=skel['joint_path_axes'],
        slice_z=slice_z,
        meta={'builder': 'tissue_sim.core.builder', 'source': vol.source, 'tissue_table': table['source'],
              'joints_source': skel.get('source', ''), 'root_joint': skel.get('root_joint'),
              'settings': {k: v for k, v in s.items()}, 'units': 'SI (m, kg, s, rad), model frame REP-103',
              'slice_k': [int(k) for k in ks], 'voxel_mm': [round(x, 6) for x in vol.pixel_mm],
              'attach_mm': attach_m * 1000.0, 'anchors': anchors},
    ).validate()
    build_s = time.perf_counter() - t0
    from .quality import quality_report
    vox_m3 = float(np.prod(vol.pixel_mm)) * 1e-9
    label_vol = {tab[l]['name']: float(counts[l]) * vox_m3 for l in muscle_labels}
    label_vol['fat'] = float(sum(counts[l] for l in fat_labels)) * vox_m3
    checks = {'label_volume_m3': label_vol, 'breaks': breaks, 'fragments': fragments, 'bridged': [[tab[l]['name'], z] for l, z in bridged],
              'bone_touch': {tab[l]['name']: bone_touch.get(tab[l]['name'], 0) for l in bone_labels},
              'refused_across_joint': refused,
              'moved_out_of_bones': n_moved_out, 'wrapped_bound': n_wrapped, 'shear_limit': s['shear_limit'], 'not_represented': not_represented}
    report = quality_report(tm, checks=checks, cell_vol=cell_vol, area_rows=area_rows, fats=fats, dropped=dropped + single,
                            dropped_cells=dropped_cells, warnings=warnings, n_unshared=n_unshared,
                            n_before_sharing=len(pos0), bone_info=bone_info, build_s=build_s)
    report['path_smoothing'] = {'reach_mm': s['path_smooth_mm'], 'rings_moved': len(path_moves),
                                'median_mm': round(float(np.median(path_moves)) * 1000, 3) if path_moves else 0.0,
                                'max_mm': round(float(np.max(path_moves)) * 1000, 3) if path_moves else 0.0}
    return tm, report

