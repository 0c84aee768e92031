"""Analytic phantoms for the model builder (and tiny models for other tests).

Geometry is defined in the model frame (x anterior, y left, z up; mm here) and rasterised into a
label volume with a NIfTI-style affine (voxel -> RAS mm). Stable API for other engineers:

    make_phantom(kind) -> (labels (I, J, K) int16, affine (4, 4), table dict)
    make_phantom_model(kind='column', **builder_settings) -> TissueModel (built by the real builder;
        slice_mm=25 unless a slice setting is given: 9 slices)
    write_phantom(kind, folder, fmt='nii'|'npz'|'png') -> (labels_path, tissues_yaml_path)

Kinds:
  column     bone (two segments 'upper'/'lower' meeting at z = 12.5 mm, hinge 'knee' about +y there),
             muscle 'flexor' (label 11, hamstrings) disc r 25 at x = -35, muscle 'extensor' (12) disc r 25
             at x = +35, both touching the bone (r 10 at the axis); fat fills the body (r 70). z in [-100, 100].
  tapered    column whose flexor is a cone: r = 25 (60 - z) / 160 mm for z < 60 (ends between slices).
  two_bones  two bones in every slice: 'tibia' (r 12 at (10, -15)) on segment 'upper' and 'fibula'
             (r 6 at (-5, 25)) on segment 'lower'; one muscle disc r 20 at (-40, 0); fat r 70.
  split      column whose flexor is one disc below z = 0 and two discs (r 12 at y = +-14) above.
  cshape     column whose flexor is a C-shaped (non-convex) annulus sector around the bone.
  tendon     column whose flexor becomes a thin tendon (r 4 mm) beside its belly above z = 0, with no
             overlap between them on neighbouring slices (semitendinosus in the bundled limb)
  gap        column whose flexor is absent between z = -10 and z = 10 (a real break of the label)
  fragment   column whose flexor is absent between z = -60 and z = -40 and below it only a thin disc (r 4 mm):
             a small piece cut off from the belly (< 1 % of the muscle's volume)
  limb       a synthetic lower limb of the paper's size (hip at z = 0 down to z = -1125 mm; 6 bones,
             28 muscles on thigh and shank, fat), 1.5 mm pixels, 2.5 mm slices: benchmark input
             used by bench/build.py while the bundled anatomy is absent (make_limb_phantom()).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

VOX = (1.0, 1.0, 5.0)           # mm
HALF = 80                       # in-plane half-width [voxels]
Z0, Z1 = -100.0, 100.0          # mm
R_BODY, R_BONE, R_MUS, X_MUS = 70.0, 10.0, 25.0, 35.0
KNEE_Z = 12.5                   # mm


def _grid():
    I = J = 2 * HALF + 1
    K = int(round((Z1 - Z0) / VOX[2])) + 1
    affine = np.array([[-VOX[0], 0, 0, HALF * VOX[0]],
                       [0, -VOX[1], 0, HALF * VOX[1]],
                       [0, 0, VOX[2], Z0],
                       [0, 0, 0, 1.0]])
    i, j, k = np.meshgrid(np.arange(I), np.arange(J), np.arange(K), indexing='ij')
    ras = np.stack([i, j, k], -1) @ affine[:3, :3].T + affine[:3, 3]
    x, y, z = ras[..., 1], -ras[..., 0], ras[..., 2]      # model frame, mm
    return (I, J, K), affine, x, y, z


def _joints():
    return {
        'source': 'phantom',
        'segments': [
            {'name': 'upper', 'parent': None, 'mass': 8.0, 'com': [0.0, 0.0, 0.06], 'inertia': [0.1, 0.1, 0.02]},
            {'name': 'lower', 'parent': 'upper', 'mass': 3.0, 'com': [0.0, 0.0, -0.05], 'inertia': [0.03, 0.03, 0.005]},
        ],
        'joints': [{'name': 'knee', 'type': 'hinge', 'parent': 'upper', 'child': 'lower', 'axis': [0, 1, 0],
                    'centre': [0.0, 0.0, KNEE_Z / 1000.0], 'range_deg': [0, 120], 'rest_deg': 0}],
    }


def _table(kind):
    labels = {
        1: {'name': 'upper_bone', 'tissue': 'bone', 'segment': 'upper'},
        2: {'name': 'lower_bone', 'tissue': 'bone', 'segment': 'lower'},
        11: {'name': 'flexor', 'tissue': 'muscle', 'group': 'hamstrings', 'max_isometric_force': 1000.0,
             'optimal_fibre_length': 0.1},
        12: {'name': 'extensor', 'tissue': 'muscle', 'group': 'quadriceps', 'stiffness_scale': 2.0},
        40: {'name': 'fat', 'tissue': 'fat'},
    }
    if kind == 'two_bones':
        labels = {1: {'name': 'tibia', 'tissue': 'bone', 'segment': 'upper'},
                  2: {'name': 'fibula', 'tissue': 'bone', 'segment': 'lower'},
                  11: {'name': 'flexor', 'tissue': 'muscle', 'group': 'hamstrings'},
                  40: {'name': 'fat', 'tissue': 'fat'}}
    return {'name': f'phantom_{kind}', 'joints': _joints(), 'labels': labels}


def make_phantom(kind: str = 'column'):
    """(labels (I, J, K) int16, affine (4, 4), tissue-table dict with inline joints)."""
    shape, affine, x, y, z = _grid()
    lab = np.zeros(shape, np.int16)
    r = np.hypot(x, y)
    lab[r <= R_BODY] = 40
    if kind == 'two_bones':
        lab[np.hypot(x + 40, y) <= 20] = 11
        lab[np.hypot(x - 10, y + 15) <= 12] = 1
        lab[np.hypot(x + 5, y - 25) <= 6] = 2
        return lab, affine, _table(kind)
    bone = r <= R_BONE
    lab[bone & (z >= KNEE_Z)] = 1
    lab[bone & (z < KNEE_Z)] = 2
    lab[np.hypot(x - X_MUS, y) <= R_MUS] = 12
    flex = np.hypot(x + X_MUS, y) <= R_MUS
    if kind == 'tapered':
        flex = (np.hypot(x + X_MUS, y) <= R_MUS * (60.0 - z) / 160.0) & (z < 60.0)
    elif kind == 'split':
        flex = np.where(z < 0, flex, (np.hypot(x + X_MUS, y - 14) <= 12) | (np.hypot(x + X_MUS, y + 14) <= 12))
    elif kind == 'cshape':
        ang = np.degrees(np.arctan2(y, x))
        flex = (r > R_BONE) & (r <= 40.0) & (np.abs(ang) > 100.0)          # C open towards +x, around the bone
        lab[np.hypot(x - X_MUS, y) <= R_MUS] = 40
        lab[(np.hypot(x - X_MUS - 8, y) <= 17)] = 12
    elif kind == 'tendon':
        flex = np.where(z < 0, flex, np.hypot(x + X_MUS, y - 32) <= 4)
    elif kind == 'gap':
        flex = flex & (np.abs(z) > 10)
    elif kind == 'fragment':
        flex = np.where(z < -60, np.hypot(x + X_MUS, y) <= 4, flex) & ~((z >= -60) & (z < -40))
    elif kind != 'column':
        raise ValueError(f'unknown phantom kind {kind!r} (column, tapered, two_bones, split, cshape, tendon, gap, fragment)')
    lab[flex & ~bone] = 11
    return lab, affine, _table(kind)


def make_phantom_model(kind: str = 'column', **settings):
    """TissueModel of a phantom, built by tissue_sim.core.builder with default settings unless given."""
    from tissue_sim.core.builder import build_model
    lab, aff, table = make_phantom(kind)
    if not any(settings.get(k) is not None for k in ('slices', 'slice_mm', 'slice_step')):
        settings['slice_mm'] = 25.0          # 9 slices over the 200-mm phantom
    tm, _ = build_model((lab, aff), table, **settings)
    return tm


def write_phantom(kind: str, folder, fmt: str = 'nii'):
    """Write a phantom as files (labels + tissues.yaml + joints.yaml); returns (labels_path, table_path)."""
    import yaml
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    lab, aff, table = make_phantom(kind)
    (folder / 'joints.yaml').write_text(yaml.safe_dump(table['joints'], sort_keys=False))
    t = dict(table, joints='joints.yaml')
    (folder / 'tissues.yaml').write_text(yaml.safe_dump(t, sort_keys=False))
    if fmt == 'nii':
        import nibabel as nib
        p = folder / 'labels.nii.gz'
        nib.save(nib.Nifti1Image(lab, aff), str(p))
    elif fmt == 'npz':
        p = folder / 'labels.npz'
        np.savez_compressed(p, labels=lab, affine=aff)
    elif fmt == 'png':
        import imageio.v3 as iio
        p = folder / 'slices'
        p.mkdir(exist_ok=True)
        for k in range(lab.shape[2]):
            iio.imwrite(p / f'slice_{k:04d}.png', lab[:, :, k].T.astype(np.uint8))
        # PNG convention: columns to the patient's left (R decreases), rows posterior (A decreases)
        (p / 'spacing.yaml').write_text(yaml.safe_dump({'pixel_mm': [VOX[0], VOX[1]], 'slice_mm': VOX[2],
                                                        'origin_mm': [float(aff[0, 3]), float(aff[1, 3]), float(aff[2, 3])]}))
    else:
        raise ValueError(fmt)
    return p, folder / 'tissues.yaml'


def make_hard_phantom(rotated: bool = True):
    """(labels, affine, table) of a phantom with every shape the ray sections get wrong, on an awkward
    grid: anisotropic voxels (0.9 x 1.3 x 5 mm), an in-plane rotation of 25 degrees, a flipped voxel
    axis and slices stored superior-first (``rotated=False``: the same anatomy on a plain axis-aligned
    grid of the same voxel size). Model frame mm, z in [-100, 100], knee at z = 12.5:

      skin      bumpy: r = 75 + 5 sin(6 theta) + 3 sin(z / 15)
      bones     'upper' r 10 at the axis above the knee; below it two bones, 'tibia' r 7 at (3, -3) and
                'fibula' r 4 at (-3, 5) (one bone becoming two), both on segment 'lower'
      wrap      (11, hamstrings, origin upper, insertion lower) an annulus r 13..32 about the axis
                except the anterior 120 degrees: wrapped around three sides of the bone(s)
      crescent  (12) inside the circle r 20 about (48, 0), outside the circle r 16 about (58, 0)
      split     (13) a disc r 12 about (0, -50) below z = 0, two discs r 7 about (+-10, -50) above
      short     (14) a disc r 10 about (0, 52) for z <= 37 (ends between two 25-mm slices)
      fat       (40) the rest of the body
    """
    sx, sy, sz = 0.9, 1.3, 5.0
    I, J, K = 230, 160, 41
    th = np.radians(25.0) if rotated else 0.0
    rot = np.array([[np.cos(th), -np.sin(th), 0], [np.sin(th), np.cos(th), 0], [0, 0, 1.0]])
    flip = np.diag([-1.0, 1.0, -1.0]) if rotated else np.eye(3)       # i axis and slice order reversed
    A = rot @ np.diag([sx, sy, sz]) @ flip
    centre = np.array([(I - 1) / 2, (J - 1) / 2, 0.0 if rotated else K - 1.0])
    t = np.array([0.0, 0.0, 100.0]) - A @ centre                       # voxel centre -> RAS (0, 0, 100 or -100 + ...)
    if not rotated:
        t[2] = 100.0 - A[2, 2] * (K - 1)
    affine = np.eye(4)
    affine[:3, :3], affine[:3, 3] = A, t
    i, j, k = np.meshgrid(np.arange(I), np.arange(J), np.arange(K), indexing='ij')
    ras = np.stack([i, j, k], -1) @ A.T + t
    x, y, z = ras[..., 1], -ras[..., 0], ras[..., 2]
    r, ang = np.hypot(x, y), np.arctan2(y, x)
    lab = np.zeros((I, J, K), np.int16)
    lab[r <= 75 + 5 * np.sin(6 * ang) + 3 * np.sin(z / 15)] = 40
    up = z >= KNEE_Z
    bone = np.zeros_like(lab)
    bone[up & (r <= 10)] = 1
    bone[~up & (np.hypot(x - 3, y + 3) <= 7)] = 2
    bone[~up & (np.hypot(x + 3, y - 5) <= 4)] = 3
    lab[(r > 13) & (r <= 32) & (np.abs(np.degrees(ang)) > 60)] = 11
    cres = (np.hypot(x - 48, y) <= 20) & (np.hypot(x - 58, y) > 16)
    lab[cres & (lab == 40)] = 12
    split = np.where(z < 0, np.hypot(x, y + 50) <= 12, (np.hypot(x - 10, y + 50) <= 7) | (np.hypot(x + 10, y + 50) <= 7))
    lab[split] = 13
    lab[(np.hypot(x, y - 52) <= 10) & (z <= 37)] = 14
    lab[bone > 0] = bone[bone > 0]
    joints = _joints()
    joints['segments'][0]['com'] = [0.0, 0.0, 0.06]
    labels = {1: {'name': 'upper_bone', 'tissue': 'bone', 'segment': 'upper'},
              2: {'name': 'tibia', 'tissue': 'bone', 'segment': 'lower'},
              3: {'name': 'fibula', 'tissue': 'bone', 'segment': 'lower'},
              11: {'name': 'wrap', 'tissue': 'muscle', 'group': 'hamstrings', 'origin': 'upper', 'insertion': 'lower'},
              12: {'name': 'crescent', 'tissue': 'muscle', 'group': 'quadriceps'},
              13: {'name': 'split', 'tissue': 'muscle'},
              14: {'name': 'short', 'tissue': 'muscle'},
              40: {'name': 'fat', 'tissue': 'fat'}}
    return lab, affine, {'name': 'phantom_hard', 'joints': joints, 'labels': labels}


def make_limb_phantom():
    """(labels, affine, table) of the synthetic 'limb' (see the module docstring); ~30 M voxels."""
    px, dz = 1.5, 2.5
    half = 70
    zlo, zhi = -1125.0, 0.0
    K = int(round((zhi - zlo) / dz)) + 1
    affine = np.array([[-px, 0, 0, half * px], [0, -px, 0, half * px], [0, 0, dz, zlo], [0, 0, 0, 1.0]])
    n = 2 * half + 1
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing='ij')
    x = (half - j) * px          # A
    y = (i - half) * px          # -R
    lab = np.zeros((n, n, K), np.int16)
    bones = {1: ('femur', 'thigh'), 2: ('patella', 'shank'), 3: ('tibia', 'shank'), 4: ('fibula', 'shank'),
             5: ('talus', 'foot'), 6: ('calcaneus', 'foot')}
    labels = {b: {'name': nm, 'tissue': 'bone', 'segment': sg} for b, (nm, sg) in bones.items()}
    labels[90] = {'name': 'subcutaneous_fat', 'tissue': 'fat'}
    muscles = []
    for m in range(14):                                   # thigh
        a = 2 * np.pi * m / 14
        muscles.append((f'thigh_{m:02d}', 48 * np.cos(a), 48 * np.sin(a), 14.0, -440 + (m % 3) * 25.0, -30 - (m % 4) * 30.0,
                        'hamstrings' if m in (6, 7, 8) else ''))
    for m in range(12):                                   # shank
        a = 2 * np.pi * (m + 0.5) / 12
        muscles.append((f'shank_{m:02d}', 5 + 33 * np.cos(a), -8 + 33 * np.sin(a), 10.0, -860 + (m % 3) * 30.0, -480.0, ''))
    muscles.append(('gastrocnemius_lat', -48, -16, 12.0, -760, -470, ''))
    muscles.append(('gastrocnemius_med', -48, 16, 12.0, -760, -470, ''))
    for m, mu in enumerate(muscles):
        labels[10 + m] = {'name': mu[0], 'tissue': 'muscle', 'group': mu[6]}
    for k in range(K):
        z = zlo + k * dz
        if z > -455:
            rb = 85 - 30 * (-z) / 455
        elif z > -880:
            rb = 55 - 20 * (-455 - z) / 425
        else:
            rb = 40
        sl = np.where(np.hypot(x, y) <= rb, 90, 0).astype(np.int16)
        for m, (nm, cx, cy, r, z0, z1, _) in enumerate(muscles):
            if z0 <= z <= z1:
                sl[np.hypot(x - cx, y - cy) <= r * min(1.0, 0.4 + 0.6 * min(z - z0, z1 - z) / 60.0)] = 10 + m
        if -450 <= z <= -20:
            sl[np.hypot(x - 5, y) <= 14] = 1
        if -470 <= z <= -420:
            sl[np.hypot(x - 45, y) <= 10] = 2
        if -880 <= z < -450:
            sl[np.hypot(x - 10, y) <= 15] = 3
        if -860 <= z <= -470:
            sl[np.hypot(x + 10, y + 25) <= 7] = 4
        if -900 <= z < -880:
            sl[np.hypot(x - 5, y) <= 18] = 5
        if z < -900:
            sl[np.hypot(x + 10, y) <= 22] = 6
        lab[:, :, k] = sl
    joints = {
        'source': 'synthetic limb phantom',
        'segments': [
            {'name': 'thigh', 'parent': None, 'mass': 10.4, 'com': [0.0, 0.0, -0.19], 'inertia': [0.18, 0.18, 0.04]},
            {'name': 'shank', 'parent': 'thigh', 'mass': 3.4, 'com': [0.0, 0.0, -0.64], 'inertia': [0.05, 0.05, 0.006]},
            {'name': 'foot', 'parent': 'shank', 'mass': 1.1, 'com': [0.03, 0.0, -1.0], 'inertia': [0.004, 0.004, 0.001]},
        ],
        'joints': [
            {'name': 'knee_r', 'type': 'hinge', 'parent': 'thigh', 'child': 'shank', 'axis': [0, 1, 0],
             'centre': [0.0, 0.0, -0.455], 'range_deg': [0, 120], 'rest_deg': 0},
            {'name': 'ankle_r', 'type': 'fixed', 'parent': 'shank', 'child': 'foot', 'centre': [0.0, 0.0, -0.885]},
        ],
    }
    return lab, affine, {'name': 'limb_phantom', 'joints': joints, 'labels': labels}
