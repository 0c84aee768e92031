"""Each muscle's musculotendon length as a polynomial of the joint angles, fitted to the OpenSim source model's
wrapped paths (the bundled limb's muscle_paths.yaml; docs/solver.md "Force-length").

The OpenSim engine (``opensim`` package, requirements/validation.txt) evaluates every right-leg muscle part's path
length L_MT (via points, wrap surfaces, the walker knee's coupled coordinates and the patella's coupling included) on a
grid of knee (knee_angle_r 0..120 deg, every 5) x ankle (ankle_angle_r -50..20 deg, every 5) angles, every other
coordinate 0 (hip 0: the bundled limb's fixed hip; fibres.py's pose). Per part a polynomial in the angles of the joints
the path crosses (a joint whose angle changes L_MT by less than 0.1 mm over its range is not crossed), of total
degree DEGREE, is fitted by least squares: multivariate polynomial regression of the musculotendon length in the
joint angles, as Menegaldo et al. 2004 (J Biomech 37:1447-1453) and OpenSim 4.5's PolynomialPathFitter
(FunctionBasedPath with MultivariatePolynomialFunction) do. Its derivative gives the moment arms r_j = -dL_MT/dq_j.

The fit is checked on the cell centres of the sampling grid (knee 2.5..117.5, ankle -47.5..17.5 deg, points not
fitted): max |Delta L_MT| [mm]; and the moment arms against -dL_MT/dq of OpenSim's path length by central differences
(+-0.05 deg, one-sided at the range's ends) on the 10-deg grid (max |Delta r| [mm]). (Not against OpenSim's computeMomentArm: for the gastrocnemii,
wrapped over the femoral condyles, it differs from -dL_MT/dq near extension, 17.8 vs -1.0 mm for the medial head at
0 deg; the path's energy-consistent moment arm is -dL_MT/dq, which the solver uses.) Both are written into the data file and printed.

Run standalone (``python tools/anatomy/paths.py [--out DIR]``) or from generate.py (``make anatomy``).
"""
from __future__ import annotations

import argparse
import itertools
import math
from pathlib import Path

import numpy as np
import yaml

import fibres

COORDINATES = (('knee_r', 'knee_angle_r', 0.0, 120.0), ('ankle_r', 'ankle_angle_r', -50.0, 20.0))   # (our joint,
# OpenSim coordinate, sampled range [deg]); both flexion/dorsiflexion-positive, 0 at the bundled limb's rest pose
STEP_DEG = 5.0
DEGREE = 5
FD_DEG = 0.05             # [deg] central-difference half step of the moment-arm check
CROSS_TOL = 1e-4           # [m] an L_MT change below this over a joint's range: the path does not cross it
OUT = fibres.SRC / 'tissue_sim' / 'data' / 'lower_limb'


def _grid(offset=0.0, step=STEP_DEG):
    axes = [np.arange(lo + offset, hi - offset + 1e-9, step) for _, _, lo, hi in COORDINATES]
    return np.array(list(itertools.product(*axes)))                       # (n, 2) [deg]


def sample(osim_path, poses_deg, arms=False):
    """{part: (Fmax, L_opt, L_TS, pennation, passive strain at Fmax)}, lengths {part: (n,)} [m] of the right leg's
    muscle parts (name without '_r') at the poses (n, 2) [deg] (every other coordinate 0); arms: also
    {part: (n, 2)} OpenSim's computeMomentArm [m] about each coordinate."""
    osm, kept = fibres._opensim()
    with kept():
        osm.Logger.setLevelString('warn')
        model = osm.Model(str(osim_path))
        state = model.initSystem()
        cs = model.getCoordinateSet()
        for c in cs:
            if not c.get_locked():
                c.setValue(state, 0.0, False)
        coords = [cs.get(n) for _, n, _, _ in COORDINATES]
        mus = model.getMuscles()
        parts = [mus.get(i) for i in range(mus.getSize()) if mus.get(i).getName().endswith('_r')]
        props = {}
        for mu in parts:
            dgf = osm.DeGrooteFregly2016Muscle.safeDownCast(mu)
            props[mu.getName()[:-2]] = (mu.getMaxIsometricForce(), mu.getOptimalFiberLength(), mu.getTendonSlackLength(),
                                        mu.getPennationAngleAtOptimalFiberLength(),
                                        dgf.get_passive_fiber_strain_at_one_norm_force() if dgf else float('nan'))
        L = {n: np.empty(len(poses_deg)) for n in props}
        R = {n: np.empty((len(poses_deg), len(coords))) for n in props} if arms else None
        for k, pose in enumerate(poses_deg):
            for c, v in zip(coords, pose):
                c.setValue(state, math.radians(v), False)
            model.assemble(state)
            model.realizePosition(state)
            for mu in parts:
                n = mu.getName()[:-2]
                L[n][k] = mu.getLength(state)
                if arms:
                    for j, c in enumerate(coords):
                        R[n][k, j] = mu.computeMomentArm(state, c)
    return props, L, R


def wrapped_points(osim_path, parts, arc_points=8):
    """{part: (n, 3) [m]} each muscle part's path in the rest pose (every coordinate 0) as OpenSim wraps it: its path
    points and, over each wrap surface, the wrapped arc (arc_points samples of PathWrapPoint.getWrapPath), in the
    femur_r frame (osim.load's frame), origin to insertion."""
    osm, kept = fibres._opensim()
    out = {}
    with kept():
        model, state = fibres.rest_pose(osm, osim_path)
        femur = model.getBodySet().get('femur_r')
        ground = model.getGround()
        mus = model.getMuscles()
        for part in parts:
            path = mus.get(part + '_r').getGeometryPath().getCurrentPath(state)
            pts = []
            for i in range(path.getSize()):
                pp = path.get(i)
                wp = osm.PathWrapPoint.safeDownCast(pp)
                if wp is not None and i + 1 < path.getSize() and osm.PathWrapPoint.safeDownCast(path.get(i + 1)):
                    arc = wp.getWrapPath(state)            # in the wrap object's body frame
                    body = wp.getParentFrame()
                    n = arc.getSize()
                    for j in np.linspace(0, n - 1, min(arc_points, n)).round().astype(int):
                        g = body.findStationLocationInGround(state, arc.get(int(j)))
                        pts.append(ground.findStationLocationInAnotherFrame(state, g, femur))
                    continue
                pts.append(ground.findStationLocationInAnotherFrame(state, pp.getLocationInGround(state), femur))
            out[part] = np.array([[v.get(k) for k in range(3)] for v in pts])
    return out


def powers(crossed):
    """Exponent rows (T, 2) of the monomials of total degree <= DEGREE in the crossed coordinates (bool (2,))."""
    rows = [e for e in itertools.product(range(DEGREE + 1), repeat=len(COORDINATES))
            if sum(e) <= DEGREE and all(c or k == 0 for c, k in zip(crossed, e))]
    return np.array(sorted(rows, key=lambda e: (sum(e), [-k for k in e])), np.int64)


def evaluate(pw, coef, q):
    """L_MT (n,) and dL/dq (n, 2) of the polynomial (exponents pw (T, 2), coefficients (T,)) at q (n, 2) [rad]."""
    L = np.zeros(len(q))
    d = np.zeros((len(q), pw.shape[1]))
    for e, c in zip(pw, coef):
        L += c * np.prod(q ** e, axis=1)
        for j in range(pw.shape[1]):
            if e[j] > 0:
                e1 = e.copy()
                e1[j] -= 1
                d[:, j] += c * e[j] * np.prod(q ** e1, axis=1)
    return L, d


def fit(osim_path):
    """The fitted paths: {part: dict(muscle fields, powers, coefficients, errors)} and a summary."""
    grid = _grid()
    props, L, _ = sample(osim_path, grid)
    check = _grid(STEP_DEG / 2)
    _, Lc, _ = sample(osim_path, check)
    coarse = _grid(step=10.0)
    Rc = {n: np.zeros((len(coarse), len(COORDINATES))) for n in props}
    for j in range(len(COORDINATES)):              # r = -dL_MT/dq by central differences of OpenSim's path length
        dq = np.zeros(len(COORDINATES))
        dq[j] = FD_DEG
        lo, hi = COORDINATES[j][2], COORDINATES[j][3]      # (one-sided at the range's ends)
        up, dn = np.minimum(coarse[:, j] + FD_DEG, hi), np.maximum(coarse[:, j] - FD_DEG, lo)
        _, Lp, _ = sample(osim_path, np.where(np.arange(len(COORDINATES)) == j, up[:, None], coarse))
        _, Lm, _ = sample(osim_path, np.where(np.arange(len(COORDINATES)) == j, dn[:, None], coarse))
        for n in props:
            Rc[n][:, j] = -(Lp[n] - Lm[n]) / np.radians(up - dn)
    q, qc, qa = np.radians(grid), np.radians(check), np.radians(coarse)
    out = {}
    for n, (fmax, lopt, lts, alpha, strain) in props.items():
        Lg = L[n].reshape([len(np.arange(lo, hi + 1e-9, STEP_DEG)) for _, _, lo, hi in COORDINATES])
        crossed = np.array([np.ptp(Lg, axis=j).max() > CROSS_TOL for j in range(len(COORDINATES))])
        pw = powers(crossed)
        A = np.stack([np.prod(q ** e, axis=1) for e in pw], 1)
        coef, *_ = np.linalg.lstsq(A, L[n], rcond=None)
        Lf, _ = evaluate(pw, coef, qc)
        _, d = evaluate(pw, coef, qa)
        err_r = np.abs(-d - Rc[n])[:, crossed] if crossed.any() else np.zeros(1)
        out[n] = dict(fmax=fmax, lopt=lopt, lts=lts, alpha=alpha, strain=strain, crossed=crossed, powers=pw, coef=coef,
                      max_dl_mm=float(np.abs(Lf - Lc[n]).max() * 1e3), max_dr_mm=float(err_r.max() * 1e3),
                      length_range_mm=float(np.ptp(L[n]) * 1e3))
    return out


def write(table, paths, out_dir):
    """muscle_paths.yaml: per muscle of the tissue table (its opensim_parts) each part's polynomial."""
    muscles = {}
    for lab in table['labels'].values():
        if lab.get('tissue') != 'muscle':
            continue
        entry = []
        for p in lab['opensim_parts']:
            f = paths[p]
            joints = [COORDINATES[j][0] for j in range(len(COORDINATES)) if f['crossed'][j]]
            cols = [j for j in range(len(COORDINATES)) if f['crossed'][j]]
            entry.append({'part': p, 'max_isometric_force': round(float(f['fmax']), 3),
                          'optimal_fibre_length': float(f['lopt']), 'tendon_slack_length': float(f['lts']),
                          'pennation_at_optimal_rad': float(f['alpha']),
                          'passive_strain_at_fmax': float(f['strain']),
                          'joints': joints,
                          'powers': [[int(e[j]) for j in cols] for e in f['powers']],
                          'coefficients_m': [float(c) for c in f['coef']],
                          'fit_max_error_mm': round(f['max_dl_mm'], 4),
                          'moment_arm_max_error_mm': round(f['max_dr_mm'], 4)})
        muscles[lab['name']] = entry
    errs = [(e['fit_max_error_mm'], e['moment_arm_max_error_mm']) for v in muscles.values() for e in v]
    doc = {'source': 'generated by tools/anatomy/paths.py: the musculotendon path length L_MT [m] of every OpenSim '
                     'muscle part of pose2sim 0.10.49 Model_Pose2Sim_muscles_flex.osim (Rajagopal 2016; wrapping, '
                     'walker knee and patella coupling included; every other coordinate 0) sampled every '
                     f'{STEP_DEG:g} deg over knee_angle_r 0..120 and ankle_angle_r -50..20 deg, fitted by least squares '
                     f'with a polynomial of total degree <= {DEGREE} in the angles [rad] of the joints it crosses '
                     '(Menegaldo et al. 2004 J Biomech 37:1447; OpenSim 4.5 PolynomialPathFitter): L_MT = sum_t '
                     'coefficients_m[t] prod_j q_j^powers[t][j]; q_j the joint coordinate (knee flexion, ankle '
                     'dorsiflexion positive, 0 at rest). Fit errors: fit_max_error_mm on the grid cell centres, '
                     'moment_arm_max_error_mm against -dL_MT/dq of OpenSim\'s path (central differences) on the 10-deg grid.',
           'coordinates': {j: c for j, c, _, _ in COORDINATES},
           'fit_max_error_mm': round(max(e[0] for e in errs), 4),
           'moment_arm_max_error_mm': round(max(e[1] for e in errs), 4),
           'muscles': muscles}
    with open(Path(out_dir) / 'muscle_paths.yaml', 'w') as fh:
        yaml.safe_dump(doc, fh, sort_keys=False, default_flow_style=None, width=110)
    return doc


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--out', default=str(OUT))
    ap.add_argument('--osim', default=None)
    a = ap.parse_args(argv)
    import sys
    sys.path.insert(0, str(fibres.SRC))
    from tissue_sim.core.validation import source_model_path
    osim = a.osim or source_model_path()
    table = yaml.safe_load((Path(a.out) / 'tissues.yaml').read_text())
    doc = write(table, fit(osim), a.out)
    for name, parts in doc['muscles'].items():
        for e in parts:
            print(f"{name:28s} {e['part']:12s} joints {','.join(e['joints']) or '-':14s} "
                  f"max |dL| {e['fit_max_error_mm']:.3f} mm  max |dr| {e['moment_arm_max_error_mm']:.3f} mm")
    print(f"max |dL| {doc['fit_max_error_mm']} mm, max |dr| {doc['moment_arm_max_error_mm']} mm")


if __name__ == '__main__':
    main()
