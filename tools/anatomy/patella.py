"""The moving patella: the source model's patellofemoral path as a table in the knee angle.

The Rajagopal 2016 model (pose2sim 0.10.49, ``Model_Pose2Sim_muscles_flex.osim``) moves the patella
relative to the femur by the CustomJoint ``patellofemoral_r``: a rotation about the femur offset frame's
z axis and translations along its x and y axes, each a SimmSpline of ``knee_angle_r_beta``, which a
CoordinateCouplerConstraint sets equal to ``knee_angle_r``. This module samples that joint (osim.load
with both coordinates at the knee angle; osim.simm_spline is OpenSim's spline, checked against the
opensim engine to 1e-16 m by tests/test_patella.py) every ``STEP_DEG`` over the knee's range and writes
the patella segment and its coupled joint for joints.yaml (docs/FORMATS.md "coupled joint"):

    p -> Rot(axis, angle(theta)) (p - centre) + centre + d(theta)

for a point p of the patella at rest (knee 0), in the model frame; ``centre`` is the patella body's
origin at rest; the table rows are [knee angle deg, angle deg, dx, dy, dz m] (row 0 all zero). The
rotation axis is fixed in the femur (checked here: every sampled relative rotation is about it).

    python tools/anatomy/patella.py            # prints the table (the generator writes it)
"""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import osim  # noqa: E402

STEP_DEG = 5.0
RANGE_DEG = (0.0, 120.0)      # the knee's range in joints.yaml (Rajagopal 2016's original 0-120 deg)
JOINT = 'patellofemoral_r'
PATELLA_LABEL = 2           # generate.BONES
DRIVER = 'knee_r'
SOURCE = ('patella: segment (mass, centre of mass, inertia) = OpenSim body patella_r, and its path relative '
          'to the femur = the patellofemoral_r CustomJoint of the same model (pose2sim 0.10.49, SimmSplines of '
          'knee_angle_r_beta, coupled 1:1 to knee_angle_r by patellofemoral_knee_angle_r_con) sampled every '
          f'{STEP_DEG:g} deg over {RANGE_DEG[0]:g}-{RANGE_DEG[1]:g} deg by tools/anatomy/patella.py')

_A = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])      # OpenSim femur frame -> model frame (os_to_model)


def _pose(osim_path, deg):
    """4x4 pose of the patella body in the femur frame (OpenSim axes) at knee angle deg."""
    q = math.radians(deg)
    return osim.load(osim_path, {'knee_angle_r': q, 'knee_angle_r_beta': q})['bodies']['patella_r']['T']


def sample(osim_path, step_deg: float = STEP_DEG, range_deg=RANGE_DEG):
    """(axis (3,), centre (3,), rows (K, 5)) in the model frame; rows [knee deg, angle deg, dx, dy, dz]."""
    T0 = _pose(osim_path, 0.0)
    R0, p0 = T0[:3, :3], T0[:3, 3]
    degs = np.arange(range_deg[0], range_deg[1] + 0.5 * step_deg, step_deg)
    rv, d = [], []
    for deg in degs:
        T = _pose(osim_path, float(deg))
        Rrel = _A @ T[:3, :3] @ R0.T @ _A.T
        rv.append(Rotation.from_matrix(Rrel).as_rotvec())
        d.append(_A @ (T[:3, 3] - p0))
    rv = np.array(rv)
    axis = rv[np.argmax(np.linalg.norm(rv, axis=1))]
    axis = axis / np.linalg.norm(axis)
    ang = rv @ axis
    off = np.linalg.norm(rv - ang[:, None] * axis, axis=1).max()
    if off > 1e-9:
        raise SystemExit(f'error: {JOINT}: the patella does not rotate about one axis fixed in the femur '
                         f'(residual {off:.3g} rad)')
    axis = np.where(np.abs(axis) < 1e-12, 0.0, axis)
    rows = np.column_stack([degs, np.degrees(ang), np.array(d)])
    return axis, _A @ p0, rows


def segment(model):
    """The patella segment for joints.yaml: OpenSim body patella_r's mass, centre of mass and inertia
    (about the centre of mass) in the model frame at rest. model: osim.load() at full extension."""
    b = model['bodies']['patella_r']
    R0, p0 = b['T'][:3, :3], b['T'][:3, 3]
    Ixx, Iyy, Izz, Ixy, Ixz, Iyz = b['inertia']
    I_body = np.array([[Ixx, Ixy, Ixz], [Ixy, Iyy, Iyz], [Ixz, Iyz, Izz]])
    R = _A @ R0
    I = R @ I_body @ R.T
    com = _A @ (R0 @ b['com'] + p0)
    return {'name': 'patella', 'parent': 'thigh', 'mass': round(float(b['mass']), 5),
            'com': [round(float(v), 6) for v in com], 'length': 0.0,
            'inertia': [[round(float(v), 11) + 0.0 for v in row] for row in I]}


def joint(osim_path):
    """The coupled joint patellofemoral_r (thigh -> patella, driven by knee_r) for joints.yaml."""
    axis, centre, rows = sample(osim_path)
    return {'name': JOINT, 'type': 'coupled', 'parent': 'thigh', 'child': 'patella', 'driver': DRIVER,
            'axis': [round(float(v), 9) + 0.0 for v in axis], 'centre': [round(float(v), 6) for v in centre],
            'table_columns': ['driver_deg', 'angle_deg', 'dx', 'dy', 'dz'],
            'table': [[round(float(r[0]), 3), round(float(r[1]), 6)] + [round(float(v), 7) + 0.0 for v in r[2:]]
                      for r in rows]}


def insertion(name, default):
    """The insertion entry of tissues.yaml for muscle name: the patella segment for a muscle whose tendon
    ends on the patella (the quadriceps, muscles.TENDONS), else default. In the source model the
    quadriceps' paths run over the patella to the tibial tuberosity (the patellar ligament); here the
    tendon ends on the patella, and the patellar ligament is the coupled joint: the quadriceps pull the
    tibia through the patella's coupling Jacobian, as the source model's coupled patella does."""
    import muscles as MU
    if MU.TENDONS.get(name) == (PATELLA_LABEL,):
        return {'segment': 'patella', 'body': 'patella_r'}
    return default


def main():
    sys.path.insert(0, str(HERE))
    import generate
    path = generate.package_dir('Pose2Sim') / 'OpenSim_Setup' / 'Model_Pose2Sim_muscles_flex.osim'
    j = joint(path)
    print('axis', j['axis'], 'centre', j['centre'])
    for r in j['table']:
        print(' '.join(f'{v:10.6g}' for v in r))
    return 0


if __name__ == '__main__':
    sys.exit(main())
