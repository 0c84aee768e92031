"""Bone surface meshes: a mesh file named in the tissue table (model frame, metres), else marching
cubes (scikit-image) of the bone's label, on ``step``-voxel block means (1 = full resolution),
centred on the label, closed and outward."""
from __future__ import annotations

import math

import numpy as np
from numba import njit
from scipy import ndimage

from tissue_sim.errors import UserError

from .io import voxel_to_model


def _mc_mesh(vol, lab, bb, step):
    """Marching cubes of a bone label's 0.5 level. With ``step`` s > 1 the mask is first averaged
    over s x s x s blocks (zero-padded by at least one whole block on every side, so the surface
    is closed) and the surface is traced on the block means, placed at the block centres: a label
    edge then lands where the voxels' edge is, whatever its parity (plain marching cubes with
    ``step_size`` samples every s-th voxel and shifts or shrinks the surface by up to s - 1 voxels,
    half a slice for s = 2)."""
    from skimage import measure
    m = vol.labels[bb] == lab
    step = int(step)
    if step < 1:
        raise UserError(f'bone_mesh_step must be an integer >= 1 (voxels), got {step}')
    if min(m.shape) < 2 * step + 1:
        step = 1
    pads = [(step, step + (-n) % step) for n in m.shape]
    crop = np.pad(m, pads).astype(np.float32)
    if step > 1:
        s0, s1, s2 = (n // step for n in crop.shape)
        crop = crop.reshape(s0, step, s1, step, s2, step).mean(axis=(1, 3, 5))
    verts, faces, _, _ = measure.marching_cubes(crop, level=0.5, allow_degenerate=False)
    # block index -> voxel index: a block's centre is (step - 1) / 2 past its first voxel
    ijk = verts * step + (step - 1) / 2.0 + [b.start - step for b in bb]
    return voxel_to_model(vol.affine, ijk), faces.astype(np.int64)


def _load_mesh(path):
    import trimesh
    try:
        m = trimesh.load(str(path), force='mesh', process=True)
    except Exception as e:
        raise UserError(f'{path}: unreadable bone mesh ({type(e).__name__}: {e})') from None
    if len(m.faces) == 0:
        raise UserError(f'{path}: bone mesh has no faces')
    return np.asarray(m.vertices, float), np.asarray(m.faces, np.int64)


def winding_number(v: np.ndarray, f: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Generalised winding number of points w.r.t. a triangle mesh (1 inside, 0 outside a closed mesh): the sum of
    the triangles' solid angles (Van Oosterom and Strackee's formula) over 4 pi."""
    return _winding(np.ascontiguousarray(v, dtype=np.float64), np.ascontiguousarray(f, dtype=np.int64),
                    np.ascontiguousarray(np.reshape(pts, (-1, 3)), dtype=np.float64))


@njit(cache=True)
def _winding(v, f, pts):
    out = np.zeros(pts.shape[0])
    for p in range(pts.shape[0]):
        px, py, pz = pts[p, 0], pts[p, 1], pts[p, 2]
        s = 0.0
        for t in range(f.shape[0]):
            i, j, k = f[t, 0], f[t, 1], f[t, 2]
            ax, ay, az = v[i, 0] - px, v[i, 1] - py, v[i, 2] - pz
            bx, by, bz = v[j, 0] - px, v[j, 1] - py, v[j, 2] - pz
            cx, cy, cz = v[k, 0] - px, v[k, 1] - py, v[k, 2] - pz
            la = math.sqrt(ax * ax + ay * ay + az * az)
            lb = math.sqrt(bx * bx + by * by + bz * bz)
            lc = math.sqrt(cx * cx + cy * cy + cz * cz)
            num = ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx)
            den = (la * lb * lc + (ax * bx + ay * by + az * bz) * lc + (bx * cx + by * cy + bz * cz) * la
                   + (cx * ax + cy * ay + cz * az) * lb)
            s += math.atan2(num, den)
        out[p] = s / (2 * np.pi)
    return out


def label_inside_fraction(vol, lab, bb, v, f, n=100, seed=0) -> float:
    """Fraction of a bone label's voxels (a random sample) that lie inside its mesh: ~1 when the mesh
    and the label volume agree; near 0 for a mesh in the wrong frame or units."""
    ijk = np.argwhere(vol.labels[bb] == lab) + [b.start for b in bb]
    if len(ijk) == 0:
        return float('nan')
    rng = np.random.default_rng(seed)
    ijk = ijk[rng.choice(len(ijk), size=min(n, len(ijk)), replace=False)]
    w = winding_number(v, f, voxel_to_model(vol.affine, ijk.astype(float)))
    return float(np.mean(np.abs(w) > 0.5))


def bone_meshes(vol, tab, bone_labels, seg_names, step):
    import trimesh
    objs = ndimage.find_objects(vol.labels, max_label=max(bone_labels))
    names, segs, vs, ts, info = [], [], [], [], []
    for lab in bone_labels:
        e = tab[lab]
        if e['mesh'] is not None:
            v, f = _load_mesh(e['mesh'])
            src = str(e['mesh'])
        else:
            v, f = _mc_mesh(vol, lab, objs[lab - 1], step)
            src = f'marching cubes of label {lab} (step {step})'
        m = trimesh.Trimesh(v, f, process=True)
        if m.is_watertight and m.volume < 0:
            m.invert()
        names.append(e['name'])
        segs.append(seg_names.index(e['segment']))
        vs.append(np.asarray(m.vertices, np.float64))
        ts.append(np.asarray(m.faces, np.int32))
        inside = label_inside_fraction(vol, lab, objs[lab - 1], np.asarray(m.vertices), np.asarray(m.faces)) \
            if e['mesh'] is not None else None
        info.append({'bone': e['name'], 'segment': e['segment'], 'surface': src, 'vertices': len(m.vertices),
                     'label_inside_mesh': None if inside is None else round(inside, 3),
                     'triangles': len(m.faces), 'watertight': bool(m.is_watertight),
                     'volume_cm3': round(float(abs(m.volume)) * 1e6, 3) if m.is_watertight else None})
    vo = np.concatenate([[0], np.cumsum([len(v) for v in vs])]).astype(np.int64)
    to = np.concatenate([[0], np.cumsum([len(t) for t in ts])]).astype(np.int64)
    return (tuple(names), np.array(segs, np.int32), vo, np.concatenate(vs).reshape(-1, 3),
            to, np.concatenate(ts).reshape(-1, 3).astype(np.int32), info)
