"""Knee mechanics of the bundled limb against its source model (docs/validation.md).

The bundled anatomy is derived from the Rajagopal et al. 2016 OpenSim model as shipped in pose2sim
0.10.49 (PROVENANCE.md). For every muscle crossing the knee this module measures, on the elastic
model held isometric at a list of knee angles, the muscle's length, its knee moment arm, the force
its cells pass to the bones below the knee and the torque they put about the knee axis, passive
(no activation) and active (full activation), and the same quantities on the OpenSim model
(``opensim`` package, requirements/validation.txt). ROS-free; no state is kept between calls.

Conventions: knee angle θ [deg] = flexion, 0 at full extension, positive flexing (our knee_r hinge
about +y rotates the shank backwards; OpenSim's ``knee_angle_r`` of the Rajagopal walker knee is
flexion-positive too: its hamstrings shorten as it grows, checked by ``opensim_reference``). Moment
arm r = −dL/dθ [m] (positive: the muscle flexes the knee), OpenSim's ``computeMomentArm`` sign.
Torque [N m] positive = flexing.
"""
from __future__ import annotations

import dataclasses
import io
import math
from pathlib import Path

import numpy as np

KNEE_JOINT = 'knee_r'
OSIM_COORDINATE = 'knee_angle_r'
OSIM_SIDE = '_r'
HAMSTRINGS = ('biceps_femoris_long_head', 'biceps_femoris_short_head', 'semimembranosus', 'semitendinosus')
TARGET_HAMSTRINGS = ('biceps_femoris_long_head', 'semimembranosus', 'semitendinosus')
TARGET_ANGLES = (0.0, 30.0, 60.0, 90.0)
MOMENT_ARM_TOLERANCE = 0.25
MIN_FORCE_FRACTION = 0.60
TORQUE_RANGE = (60.0, 180.0)        # N m, adult peak isometric knee flexion (docs/validation.md)
ACTIVE_GROUPINGS = ('groups', 'others')     # active_sets_of
SHAPE_PEAK_MAX_DEG = 60.0           # published curves peak at small to moderate flexion and fall with deep flexion


class ValidationError(ValueError):
    """Bad validation input (angles, settle time, missing source model): the message names it."""


_OPENSIM_ENV = ('LD_LIBRARY_PATH', 'PATH', 'SIMBODY_HOME')


def _import_opensim():
    """``import opensim`` without its side effects on this process's environment: the opensim 4.6 wheel
    rewrites LD_LIBRARY_PATH (to its own folder + PATH), PATH and SIMBODY_HOME when imported, and its
    C++ side sets them again when a model is loaded, which breaks every ROS 2 program this process
    starts afterwards (they no longer find the rcl libraries). Use it with :func:`_environment_kept`
    around all OpenSim work: the variables are put back as they were (through os.environ, i.e. putenv,
    so the C-level environment children inherit is restored too)."""
    with _environment_kept():
        import opensim
        if hasattr(opensim.Logger, 'removeFileSink'):
            opensim.Logger.removeFileSink()         # no opensim.log in the working directory
    return opensim


class _environment_kept:
    def __enter__(self):
        import os
        self.saved = {k: os.environ.get(k) for k in _OPENSIM_ENV}

    def __exit__(self, *exc):
        import os
        for k, v in self.saved.items():
            if v is None:
                os.environ[k] = ''             # putenv first: the C environment may hold it without os.environ
                del os.environ[k]
            else:
                os.environ[k] = v
        return False


def source_model_path() -> Path:
    """The OpenSim model the bundled limb is derived from (pose2sim 0.10.49, requirements/anatomy.txt)."""
    try:
        import Pose2Sim
    except ImportError:
        raise ValidationError('the source model needs pose2sim 0.10.49 (pip install --no-deps -r '
                              'requirements/anatomy.txt)') from None
    p = Path(Pose2Sim.__file__).parent / 'OpenSim_Setup' / 'Model_Pose2Sim_muscles_flex.osim'
    if not p.is_file():
        raise ValidationError(f'source model not found: {p}')
    return p


def parse_angles(spec: str) -> list:
    """'0,30,60' or 'START:STOP:STEP' (inclusive) [deg] -> sorted unique floats within 0-120 deg."""
    try:
        if ':' in spec:
            a, b, s = (float(t) for t in spec.split(':'))
            if not s > 0:
                raise ValidationError(f'--angles {spec!r}: step must be > 0')
            vals = list(np.arange(a, b + s * 1e-6, s))
        else:
            vals = [float(t) for t in spec.split(',') if t.strip()]
    except ValueError:
        raise ValidationError(f'--angles {spec!r}: expected comma-separated degrees or START:STOP:STEP') from None
    vals = sorted(set(round(float(v), 6) for v in vals))
    if len(vals) < 2:
        raise ValidationError(f'--angles {spec!r}: need at least two angles')
    if vals[0] < 0 or vals[-1] > 120 or not all(math.isfinite(v) for v in vals):
        raise ValidationError(f'--angles {spec!r}: angles must lie within 0-120 deg (the knee range)')
    return vals


# ------------------------------------------------------------------------------------- muscles
@dataclasses.dataclass(frozen=True)
class KneeMuscle:
    index: int              # muscle index in the TissueModel
    name: str
    group: str
    max_force: float        # [N] max isometric force (tissues.yaml, Rajagopal Fmax)
    opensim: tuple          # OpenSim muscle names (right side)


def knee_muscles(tm, tissue_table: dict) -> list:
    """The muscles whose origin and insertion segments lie on different sides of the knee (tissues.yaml
    origin/insertion), in table order, with their OpenSim names (``opensim_parts`` + ``_r``)."""
    j = list(tm.joint_names).index(KNEE_JOINT)
    below = set()
    for s in range(tm.n_segments):
        t = s
        while t >= 0:
            if t == int(tm.joint_child[j]):
                below.add(s)
                break
            t = int(tm.segment_parent[t])
    below |= {int(tm.joint_child[k]) for k in range(tm.n_joints) if tm.joint_driver[k] == j}   # coupled to it: the patella
    seg = {n: i for i, n in enumerate(tm.segment_names)}
    out = []
    for lab in tissue_table['labels'].values():
        if lab.get('tissue') != 'muscle' or lab['name'] not in tm.muscle_names:
            continue
        o, i = seg.get(lab['origin']['segment']), seg.get(lab['insertion']['segment'])
        if o is None or i is None or (o in below) == (i in below):
            continue
        m = tm.muscle_names.index(lab['name'])
        out.append(KneeMuscle(m, lab['name'], lab.get('group') or '', float(lab.get('max_isometric_force', float('nan'))),
                              tuple(p + OSIM_SIDE for p in lab.get('opensim_parts', ()))))
    return out


# ------------------------------------------------------------------------------------- OpenSim
def opensim_reference(osim_path, muscles: list, angles_deg: list, active_sets: dict, log_level: str = 'warn') -> dict:
    """The source model at each knee angle (other coordinates at their defaults).

    Per muscle (merged OpenSim parts: lengths and moment arms weighted by Fmax, forces summed):
    ``length`` [m] (muscle-tendon path), ``moment_arm`` [m] (``computeMomentArm`` about knee_angle_r).
    Per active set (name -> muscles fully active, all others at activation 0): per muscle ``force`` [N]
    (tendon force, fibres equilibrated, rigid tendon as the model has it; 0 where the path is shorter than
    the tendon slack length, where the rigid-tendon fibre length is meaningless: ``slack`` true),
    ``active_fraction`` (active fibre force along the tendon / Fmax), ``norm_fibre_length``, and
    ``torque`` [N m] = sum of moment arm x force over the knee muscles."""
    with _environment_kept():       # opensim's side effects on the environment undone (_import_opensim)
        return _opensim_reference(osim_path, muscles, angles_deg, active_sets, log_level)


def _opensim_reference(osim_path, muscles: list, angles_deg: list, active_sets: dict, log_level: str = 'warn') -> dict:
    try:
        osim = _import_opensim()
    except ImportError:
        raise ValidationError('the OpenSim reference needs the opensim package (pip install --no-deps -r '
                              'requirements/validation.txt)') from None
    osim.Logger.setLevelString(log_level)      # not its per-load [info] lines
    model = osim.Model(str(osim_path))
    state = model.initSystem()
    coord = model.getCoordinateSet().get(OSIM_COORDINATE)
    all_m = model.getMuscles()
    names = [all_m.get(i).getName() for i in range(all_m.getSize())]
    for km in muscles:
        missing = [p for p in km.opensim if p not in names]
        if missing or not km.opensim:
            raise ValidationError(f'muscle {km.name}: OpenSim muscle(s) {missing or "(none)"} not in {osim_path}')
    A = len(angles_deg)
    ref = {'version': osim.__version__, 'model': str(osim_path), 'coordinate': OSIM_COORDINATE,
           'muscles': {km.name: {'opensim': list(km.opensim), 'length': [0.0] * A, 'moment_arm': [0.0] * A,
                                 'tendon_slack_length': 0.0, 'optimal_fibre_length': 0.0} for km in muscles},
           'active': {k: {'torque': [0.0] * A, 'muscles': {}} for k in active_sets}}
    for km in muscles:
        parts = [all_m.get(p) for p in km.opensim]
        w = np.array([p.getMaxIsometricForce() for p in parts])
        ref['muscles'][km.name]['tendon_slack_length'] = float(np.dot(w, [p.getTendonSlackLength() for p in parts]) / w.sum())
        ref['muscles'][km.name]['optimal_fibre_length'] = float(np.dot(w, [p.getOptimalFiberLength() for p in parts]) / w.sum())
    for a, deg in enumerate(angles_deg):
        coord.setValue(state, math.radians(deg))        # enforces the walker knee's coupled coordinates
        model.realizePosition(state)
        for km in muscles:
            parts = [all_m.get(p) for p in km.opensim]
            w = np.array([p.getMaxIsometricForce() for p in parts]) / sum(p.getMaxIsometricForce() for p in parts)
            r = ref['muscles'][km.name]
            r['length'][a] = float(sum(wi * p.getLength(state) for wi, p in zip(w, parts)))
            r['moment_arm'][a] = float(sum(wi * p.computeMomentArm(state, coord) for wi, p in zip(w, parts)))
        for key, active in active_sets.items():
            on = {p for km in muscles if km.name in active for p in km.opensim}
            for i in range(all_m.getSize()):
                all_m.get(i).setActivation(state, 1.0 if names[i] in on else 0.0)
            model.equilibrateMuscles(state)
            model.realizeDynamics(state)
            out = ref['active'][key]
            tau = 0.0
            for km in muscles:
                d = out['muscles'].setdefault(km.name, {'force': [0.0] * A, 'active_fraction': [0.0] * A,
                                                        'norm_fibre_length': [0.0] * A, 'slack': [False] * A})
                F = act = nfl = 0.0
                slack = False
                fmax = 0.0
                for p in km.opensim:
                    mu = all_m.get(p)
                    fmax += mu.getMaxIsometricForce()
                    if mu.getLength(state) <= mu.getTendonSlackLength():
                        slack = True
                        continue
                    F += mu.getTendonForce(state)
                    act += mu.getActiveFiberForceAlongTendon(state)
                    nfl += mu.getNormalizedFiberLength(state) * mu.getMaxIsometricForce()
                d['force'][a] = float(F)
                d['active_fraction'][a] = float(act / fmax)
                d['norm_fibre_length'][a] = float(nfl / fmax)
                d['slack'][a] = slack
                tau += ref['muscles'][km.name]['moment_arm'][a] * F
            out['torque'][a] = float(tau)
    return ref


# ------------------------------------------------------------------------------------- elastic model
def _below_knee(sim, j: int) -> np.ndarray:
    """Indices into att_idx of the bone-attached vertices that the knee moves (below it, or on a segment
    coupled to it: the patella)."""
    return np.flatnonzero(sim.anc[j][sim.att_seg] | np.isin(sim.att_seg, sim.j_child[sim.j_driver == j]))


class _Forces:
    """Static forces (zero velocity, no damping) of all cells, or of one muscle's cells only (muscle -1:
    the fat), on a state: the solver's readable force definition (``reference.cell_forces``, exact polar
    rotation) on the model with every other cell at zero stiffness (a masked cell then adds exactly nothing:
    the parts sum to the whole). Read-only use of the solver."""

    def __init__(self, sim):
        from tissue_sim.core.solver import reference
        self.R, self.sim, self.pad = reference, sim, reference.padded(sim)
        self._cells = {None: sim}

    def cells(self, muscle):
        if muscle not in self._cells:
            s = self.sim
            keep = (s.cell_muscle == muscle).astype(float)
            self._cells[muscle] = dataclasses.replace(s, k=s.k * keep, k_active=s.k_active * keep,
                                                      k_volume=s.k_volume * keep, k_enclosed=s.k_enclosed * keep,
                                                      damp_b=s.damp_b * keep)
        return self._cells[muscle]

    def __call__(self, state, act, muscle=None) -> np.ndarray:
        s = self.sim
        # (a masked cell has no volume stiffness, so its pressure does not act; vol_gain 0: none accumulates)
        f, *_ = self.R.cell_forces(self.cells(muscle), self.pad, state.x, np.zeros_like(state.x), state.lam.copy(),
                                   np.asarray(act, float), state.pressure.copy(), 0.0, s.params.volume_mode == 'actual')
        return f


def _active_tension(sim, state) -> np.ndarray:
    """(M,) [N] the active tension of each muscle (physical set; 0 without specific_tension): the solver's
    observed active force (``solver.muscle.muscle_forces``: per slice gap the sum over its cells of
    T = a' k_a n/4 max(l − lam L, 0), a' the activation x force-velocity x force-length factor, docs/solver.md;
    the median over the muscle's gaps: cells in series carry the same force)."""
    from tissue_sim.core.solver.muscle import muscle_forces
    return muscle_forces(sim, state)['active']


def hold_sweep(sim, muscles: list, angles_deg: list, active: list, settle: float, ramp_speed: float,
               progress=None) -> dict:
    """Hold the knee at each angle in turn (ascending; the angle ramps at ramp_speed [deg/s] from the
    previous one, then is held for settle [s]), with the muscles named in ``active`` at activation 1
    (the others 0), and measure the settled state.

    The knee is held by the solver's joint lock (``Control.joint_lock`` / ``joint_target``, docs/solver.md
    "Joint lock"): inside every sub-step the knee is put on its target (qd = 0 in the hold), the tissue
    moves and the bones do not. Every other hinge (the ankle) is locked at its rest coordinate, as a
    dynamometer straps the foot and as the source model's reference has it at its default. Returns per angle: muscle lengths (all knee muscles) [m]; the isometric
    knee torque [N m] (positive = flexing): minus the torque the lock applies (``joint_lock_torque``), mean
    over the last 10 % of the hold; the same torque from the static forces of every cell on the
    bone-attached vertices below the knee (``torque_static``, zero velocity: no damping); per muscle the
    force its own cells put on those bones [N] (magnitude of the net force), their torque [N m] and the
    active tension [N] (physical set); the kinetic energy of the free tissue at the end [J]."""
    from tissue_sim.core import solver
    from tissue_sim.core.solver.muscle import tension_activation
    j = list(sim.tissue.joint_names).index(KNEE_JOINT)
    state = solver.make_state(sim)
    ctrl = solver.make_control(sim)
    ctrl.joint_lock[:] = True                 # the knee, and the other joints at rest (the foot strapped)
    ctrl.joint_target[:] = state.q
    for km in muscles:
        if km.name in active:
            ctrl.activation[km.index] = 1.0
    from tissue_sim.core.solver.measures import joint_torques
    forces = _Forces(sim)
    att = sim.att_idx[_below_knee(sim, j)]
    dt = sim.params.dt
    cur = math.degrees(state.q[j])
    res = {k: [] for k in ('length', 'torque', 'torque_static', 'muscle_force', 'muscle_torque', 'tension',
                           'kinetic_energy', 'all_lengths')}
    res['diverged'] = None
    for a_i, deg in enumerate(angles_deg):
        n_ramp = int(math.ceil(abs(deg - cur) / ramp_speed / dt))
        n_hold = max(1, int(round(settle / dt)))
        n_avg = max(1, n_hold // 10)
        try:
            for i in range(n_ramp):
                ctrl.joint_target[j] = math.radians(cur + (deg - cur) * (i + 1) / n_ramp)
                solver.step(sim, state, ctrl)
            ctrl.joint_target[j] = math.radians(deg)
            if n_hold > n_avg:
                solver.step(sim, state, ctrl, n_steps=n_hold - n_avg)
            tau = 0.0
            for _ in range(n_avg):
                solver.step(sim, state, ctrl)
                tau -= state.joint_lock_torque[j] / n_avg
        except solver.DivergenceError as e:
            # the sweep ends here: this and the later angles are NaN (no number is made up), the JSON says why
            res['diverged'] = {'at_deg': deg, 'time_s': state.time, 'error': str(e)}
            nan, nm = float('nan'), len(muscles)
            for _ in angles_deg[a_i:]:
                for k in ('torque', 'torque_static', 'kinetic_energy'):
                    res[k].append(nan)
                for k in ('length', 'muscle_force', 'muscle_torque', 'tension'):
                    res[k].append([nan] * nm)
                res['all_lengths'].append([nan] * sim.n_muscles)
            break
        cur = deg
        obs = solver.observe(sim, state)
        res['torque'].append(float(tau))
        act = tension_activation(sim, state)        # the activation the step scales the tension with
        # torques by virtual work (measures.joint_torques): the patella's forces act through its coupling
        res['torque_static'].append(float(joint_torques(sim, state, forces(state, act), att)[j]))
        mf, mt = [], []
        for km in muscles:
            fm = forces(state, act, km.index)
            mf.append(float(np.linalg.norm(fm[att].sum(0))))
            mt.append(float(joint_torques(sim, state, fm, att)[j]))
        res['muscle_force'].append(mf)
        res['muscle_torque'].append(mt)
        ten = _active_tension(sim, state)
        res['tension'].append([float(ten[km.index]) for km in muscles])
        res['length'].append([float(obs['muscle_lengths'][km.index]) for km in muscles])
        res['all_lengths'].append([float(v) for v in obs['muscle_lengths']])
        res['kinetic_energy'].append(float(obs['kinetic_energy']))
        if progress:
            progress(deg)
    return res


def excursion_moment_arm(lengths, angles_deg) -> np.ndarray:
    """r = −dL/dθ [m/rad] along axis 0 (second-order differences on the possibly uneven angle grid)."""
    return -np.gradient(np.asarray(lengths, float), np.radians(np.asarray(angles_deg, float)), axis=0)


# ------------------------------------------------------------------------------------- the whole comparison
def _inputs(angles_deg, osim_path, model) -> tuple:
    """(angles [deg] (default 0-120 every 10), the source model's path (checked), the TissueModel (default: the
    bundled limb), its knee muscles) of a comparison."""
    import yaml

    from tissue_sim.core.builder import default_inputs, default_model
    angles = list(angles_deg) if angles_deg is not None else [float(a) for a in range(0, 121, 10)]
    osim_path = Path(osim_path) if osim_path else source_model_path()
    if not osim_path.is_file():
        raise ValidationError(f'source model not found: {osim_path}')
    tm = model if model is not None else default_model()
    return angles, osim_path, tm, knee_muscles(tm, yaml.safe_load(Path(default_inputs()[1]).read_text()))


def _built_with_via_points(tm) -> bool:
    """Whether the model was built with the builder setting via_points (its meta's settings; the results say which)."""
    return bool(tm.meta.get('settings', {}).get('via_points'))


def parameter_set(params: str, overrides=()):
    """Params of the named set ('physical' or 'paper') with NAME=VALUE overrides (the command's --set; as
    Params.from_assignments); ValidationError naming a bad set or assignment."""
    from tissue_sim.core.load import load_params
    if params not in ('physical', 'paper'):
        raise ValidationError(f'--params {params!r}: expected physical or paper')
    try:
        return load_params(params, None, list(overrides))
    except ValueError as e:
        raise ValidationError(f'--set: {e}') from None


def check_grouping(grouping: str) -> None:
    """ValidationError naming a grouping active_sets_of does not know."""
    if grouping not in ACTIVE_GROUPINGS:
        raise ValidationError(f'--active-sets {grouping}: must be one of {", ".join(ACTIVE_GROUPINGS)}')


def active_sets_of(muscles: list, grouping: str = 'groups') -> dict:
    """The active sweeps (name -> knee muscles fully active in it, the others at rest): the hamstrings together (the
    torque targets' sweep), then with ``grouping`` 'groups' every other knee muscle with its anatomical group
    (tissues.yaml ``group``: the quadriceps, the triceps surae, ...), one sweep per group in table order, antagonists
    at rest; with 'others' every other knee muscle in one sweep (the co-contraction of all of them)."""
    check_grouping(grouping)
    sets = {'hamstrings': [km.name for km in muscles if km.name in HAMSTRINGS]}
    for km in muscles:
        if km.name not in HAMSTRINGS:
            key = 'others' if grouping == 'others' else (km.group or km.name)
            if key in ('passive', 'hamstrings'):        # (a group named like a sweep: its muscle's own name)
                key = km.name
            sets.setdefault(key, []).append(km.name)
    return sets


def run_sweeps(sim, muscles: list, angles: list, sweeps: dict, settle: float, ramp_speed: float, progress=None,
               jobs: int | None = None) -> dict:
    """hold_sweep for each sweep (name -> the muscles active in it), ``jobs`` at a time on threads of their own
    (realtime.map_threads; default: this process's usable CPUs): each sweep has its own state, so they give the same
    numbers as one after the other. Returns name -> hold_sweep's result, in the order of sweeps. progress(name,
    angle) is called from the sweeps' threads."""
    from tissue_sim.core.realtime import map_threads

    def one(item):
        key, act = item
        return hold_sweep(sim, muscles, angles, act, settle, ramp_speed,
                          progress=(lambda d: progress(key, d)) if progress else None)
    return dict(zip(sweeps, map_threads(one, sweeps.items(), jobs)))


def run_validation(params: str = 'physical', angles_deg=None, settle: float = 1.0, ramp_speed: float = 200.0,
                   osim_path=None, model=None, progress=None, overrides=(), grouping: str = 'groups',
                   jobs: int | None = None) -> dict:
    """Everything docs/validation.md reports, as one JSON-able dict (see ``evaluate`` for the targets); overrides:
    NAME=VALUE changes of the parameter set (parameter_set); grouping: which knee muscles contract together in the
    active sweeps (active_sets_of); jobs: how many sweeps run at once (run_sweeps)."""
    from tissue_sim.core import solver
    base = parameter_set(params, overrides)
    if not (settle > 0 and math.isfinite(settle)):
        raise ValidationError(f'--settle {settle}: must be a positive number of seconds')
    if not (ramp_speed > 0 and math.isfinite(ramp_speed)):
        raise ValidationError(f'--ramp-speed {ramp_speed}: must be a positive number of deg/s')
    check_grouping(grouping)                        # before the model is built
    angles, osim_path, tm, muscles = _inputs(angles_deg, osim_path, model)
    active_sets = active_sets_of(muscles, grouping)
    hams = active_sets['hamstrings']
    set_of = {m: key for key, ms in active_sets.items() for m in ms}
    ref = opensim_reference(osim_path, muscles, angles, active_sets)
    sim = solver.compile_model(tm, base)
    runs = run_sweeps(sim, muscles, angles, {'passive': [], **active_sets}, settle, ramp_speed, progress, jobs)
    out = {'params': params, 'overrides': list(overrides), 'angles_deg': angles, 'settle_s': settle, 'ramp_speed_deg_s': ramp_speed,
           'model': tm.name, 'via_points': _built_with_via_points(tm), 'n_substeps': sim.n_substeps, 'opensim': ref,
           'active_grouping': grouping, 'active_sets': active_sets, 'muscles': {}, 'torque': {}}
    for i, km in enumerate(muscles):
        act_key = set_of[km.name]
        ro = ref['muscles'][km.name]
        rf = ref['active'][act_key]['muscles'][km.name]
        d = {'index': km.index, 'group': km.group, 'opensim': list(km.opensim), 'max_isometric_force': km.max_force,
             'active_set': act_key,
             'opensim_length_ratio': list(np.asarray(ro['length']) / ro['length'][0]),
             'opensim_moment_arm': ro['moment_arm'],
             'opensim_excursion_moment_arm': list(excursion_moment_arm(ro['length'], angles)),
             'opensim_force': rf['force'], 'opensim_active_fraction': rf['active_fraction'],
             'opensim_norm_fibre_length': rf['norm_fibre_length'], 'opensim_slack': rf['slack']}
        for mode, key in (('passive', 'passive'), ('active', act_key)):
            r = runs[key]
            L = np.array([row[i] for row in r['length']])
            F = np.array([row[i] for row in r['muscle_force']])
            T = np.array([row[i] for row in r['muscle_torque']])
            d[f'{mode}_length'] = list(L)
            d[f'{mode}_length_ratio'] = list(L / L[0])
            d[f'{mode}_moment_arm'] = list(excursion_moment_arm(L, angles))
            d[f'{mode}_force'] = list(F)
            d[f'{mode}_torque'] = list(T)
            d[f'{mode}_force_moment_arm'] = list(np.where(F > 1e-9, T / np.where(F > 1e-9, F, 1.0), 0.0))
            d[f'{mode}_tension'] = [row[i] for row in r['tension']]
            d[f'{mode}_force_fraction'] = list(F / km.max_force)
        out['muscles'][km.name] = d
    out['torque'] = {
        'passive': runs['passive']['torque'],
        'hamstrings_active': runs['hamstrings']['torque'],
        'hamstrings_active_static': runs['hamstrings']['torque_static'],
        'hamstrings_only': [float(sum(row[i] for i, km in enumerate(muscles) if km.name in hams))
                            for row in runs['hamstrings']['muscle_torque']],
        'opensim_hamstrings_active': ref['active']['hamstrings']['torque'],
        'kinetic_energy': {k: r['kinetic_energy'] for k, r in runs.items()}}
    out['moment_arm_resolution'] = moment_arm_resolution(runs, muscles, angles, list(tm.muscle_names))
    out['diverged'] = {k: r['diverged'] for k, r in runs.items()}      # None, or where a sweep diverged (then NaN on)
    out['targets'] = evaluate(out)
    out['moment_arm_error'] = moment_arm_error(out)
    return out


def moment_arm_error(res: dict) -> dict:
    """Not a target, a summary: the mean |ours - OpenSim's computeMomentArm| [mm] of every knee muscle's moment arm,
    passive and active, at every angle sampled (a sweep that diverged: its NaN angles left out), overall and per muscle.
    One number to compare two builds or parameter sets by (docs/validation.md)."""
    per = {}
    for name, d in res['muscles'].items():
        os_ = np.asarray(d['opensim_moment_arm'], float)
        e = np.concatenate([np.abs(np.asarray(d[f'{mode}_moment_arm'], float) - os_) for mode in ('passive', 'active')])
        per[name] = e[np.isfinite(e)] * 1e3
    every = np.concatenate(list(per.values())) if per else np.zeros(0)
    return {'mean_abs_mm': float(every.mean()) if every.size else None, 'n': int(every.size),
            'per_muscle_mm': {k: float(v.mean()) if v.size else None for k, v in per.items()}}


def moment_arm_resolution(runs: dict, muscles: list, angles, names) -> dict:
    """What a moment arm measured by each sweep's holds resolves: per sweep {``value`` [m/rad], ``muscle``,
    ``angle_deg``}, the largest |-dL/dtheta| (excursion_moment_arm) of the muscles that do not cross the knee (no knee
    moment arm at all) over that sweep's angles and where it occurs. The tissue near the joint, and the tissue the
    active muscles pull on, deforms with the angle, so their lengths change a little; a knee muscle's moment arm within
    its sweep's value has no sign (evaluate)."""
    knee = {km.index for km in muscles}
    others = [m for m in range(len(names)) if m not in knee]
    out = {}
    for key, r in runs.items():
        best = {'value': 0.0, 'muscle': None, 'angle_deg': None}
        L = np.asarray(r.get('all_lengths', []), float)
        if L.ndim == 2 and L.shape[0] >= 2 and others:
            ma = np.abs(excursion_moment_arm(L[:, others], angles))
            if np.any(np.isfinite(ma)):
                a, m = np.unravel_index(np.nanargmax(ma), ma.shape)
                best = {'value': float(ma[a, m]), 'muscle': names[others[m]], 'angle_deg': angles[a]}
        out[key] = best
    return out


def _at(angles, values, deg):
    """The value at angle deg if sampled, else None."""
    for a, v in zip(angles, values):
        if abs(a - deg) < 1e-6:
            return v
    return None


def evaluate(res: dict) -> dict:
    """Pass/fail of the issue's targets, from the measured data. Each entry: pass (bool or None when the
    angles needed were not sampled) and the numbers it was decided on."""
    angles = res['angles_deg']
    mus = res['muscles']
    t = {}
    # 1. sign of every knee muscle's moment arm at every angle, passive and active; a moment arm within the holds'
    # resolution (moment_arm_resolution) has no sign; where the source model's is within it too, the sign is not decided
    reso = res.get('moment_arm_resolution', {})

    def resolution(sweep):          # per sweep (run_validation's moment_arm_resolution)
        return float(reso.get(sweep, {}).get('value', 0.0))
    bad, undecided = [], 0
    for name, d in mus.items():
        for mode in ('passive', 'active'):
            res_r = resolution('passive' if mode == 'passive' else d.get('active_set', 'hamstrings'))
            for a, ours, ref in zip(angles, d[f'{mode}_moment_arm'], d['opensim_moment_arm']):
                if abs(ref) <= res_r:
                    undecided += 1
                    continue
                sign = np.sign(ours) if abs(ours) > res_r else 0.0     # (NaN: a diverged sweep, no sign)
                if sign != np.sign(ref):
                    below = ' (within the resolution: no sign)' if abs(ours) <= res_r else ''
                    bad.append(f'{name} {mode} {a:g} deg: {ours * 1e3:+.1f}{below} vs {ref * 1e3:+.1f} mm')
    t['moment_arm_signs'] = {'pass': not bad, 'wrong': bad, 'undecided': undecided,
                             'resolution_mm': {k: resolution(k) * 1e3 for k in reso}}
    # 2. hamstrings within +-25 % at 0, 30, 60, 90 deg
    rows, ok, missing = [], True, [a for a in TARGET_ANGLES if _at(angles, angles, a) is None]
    for name in TARGET_HAMSTRINGS:
        if name not in mus:
            continue
        d = mus[name]
        for mode in ('passive', 'active'):
            for a in TARGET_ANGLES:
                ours, ref = _at(angles, d[f'{mode}_moment_arm'], a), _at(angles, d['opensim_moment_arm'], a)
                if ours is None:
                    continue
                err = (ours - ref) / abs(ref)
                good = bool(abs(err) <= MOMENT_ARM_TOLERANCE)
                ok = ok and good
                rows.append({'muscle': name, 'mode': mode, 'angle_deg': a, 'ours_mm': ours * 1e3,
                             'opensim_mm': ref * 1e3, 'rel_error': err, 'pass': good})
    t['hamstring_moment_arms'] = {'pass': ok if not missing else (False if not ok else None),
                                  'tolerance': MOMENT_ARM_TOLERANCE, 'angles_not_sampled': missing, 'rows': rows}
    # 3. each hamstring >= 60 % of Fmax near its optimal length (the sampled angle where OpenSim's
    # normalised fibre length is closest to 1), fully active, knee held there
    rows, ok = [], True
    for name in HAMSTRINGS:
        if name not in mus:
            continue
        d = mus[name]
        k = int(np.argmin(np.abs(np.asarray(d['opensim_norm_fibre_length']) - 1.0)))
        frac = d['active_force_fraction'][k]
        good = bool(frac >= MIN_FORCE_FRACTION)
        ok = ok and good
        rows.append({'muscle': name, 'angle_deg': angles[k], 'opensim_norm_fibre_length': d['opensim_norm_fibre_length'][k],
                     'force_fraction': frac, 'tension_fraction': d['active_tension'][k] / d['max_isometric_force'],
                     'opensim_active_fraction': d['opensim_active_fraction'][k], 'pass': good})
    # the paper's parameter set is dimensionless (Table 2: unit masses, k = 1e6): its forces are not newtons
    si = res.get('params') != 'paper'
    note = None if si else 'paper set: dimensionless forces, no comparison in N'
    t['hamstring_force'] = {'pass': ok if si else None, 'min_fraction': MIN_FORCE_FRACTION, 'rows': rows, 'note': note}
    # 4. peak isometric flexion torque within the adult range
    tau = np.asarray(res['torque']['hamstrings_active'])
    k = int(np.nanargmax(tau)) if np.any(np.isfinite(tau)) else 0        # (NaN: a sweep that diverged)
    t['peak_torque'] = {'pass': bool(TORQUE_RANGE[0] <= tau[k] <= TORQUE_RANGE[1]) if si else None,  # (NaN: False)
                        'range_Nm': list(TORQUE_RANGE), 'peak_Nm': float(tau[k]), 'at_deg': angles[k], 'note': note}
    # 5. shape: peak at <= 60 deg, then falling with flexion to the deepest angle sampled
    after = tau[k:]
    falling = bool(np.all(np.diff(after) <= 0)) and (len(after) < 2 or after[-1] < tau[k])
    t['torque_shape'] = {'pass': bool(angles[k] <= SHAPE_PEAK_MAX_DEG and falling and angles[k] < angles[-1]),
                         'peak_at_deg': angles[k], 'falls_after_peak': falling,
                         'ratio_last_to_peak': float(after[-1] / tau[k]) if tau[k] != 0 else None,
                         'opensim_peak_at_deg': angles[int(np.argmax(res['torque']['opensim_hamstrings_active']))]}
    return t


# ------------------------------------------------------------------------------------- outputs
def jsonable(o):
    """numpy scalars and arrays inside dicts/lists -> plain Python (json.dump's input)."""
    if isinstance(o, dict):
        return {str(k): jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple, np.ndarray)):
        return [jsonable(v) for v in o]
    if isinstance(o, np.bool_):
        return bool(o)
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    return o


def table_rows(res: dict) -> list:
    """Rows of the printed table: per muscle and angle, length ratio and moment arm (ours passive, ours
    active, OpenSim), active force / Fmax (ours, OpenSim)."""
    rows = []
    for name, d in res['muscles'].items():
        for a_i, a in enumerate(res['angles_deg']):
            rows.append([name, f'{a:g}',
                         f"{d['passive_length_ratio'][a_i]:.3f}", f"{d['active_length_ratio'][a_i]:.3f}",
                         f"{d['opensim_length_ratio'][a_i]:.3f}",
                         f"{d['passive_moment_arm'][a_i] * 1e3:+.1f}", f"{d['active_moment_arm'][a_i] * 1e3:+.1f}",
                         f"{d['active_force_moment_arm'][a_i] * 1e3:+.1f}", f"{d['opensim_moment_arm'][a_i] * 1e3:+.1f}",
                         f"{d['active_force_fraction'][a_i]:.2f}", f"{d['opensim_active_fraction'][a_i]:.2f}"])
    return rows


TABLE_HEADER = ['muscle', 'deg', 'L/L0 pas', 'L/L0 act', 'L/L0 osim', 'r pas mm', 'r act mm', 'r F act mm',
                'r osim mm', 'F/Fmax', 'F/Fmax osim']


def torque_rows(res: dict) -> list:
    t = res['torque']
    return [[f'{a:g}', f'{t["hamstrings_active"][i]:.1f}', f'{t["hamstrings_active_static"][i]:.1f}',
             f'{t["hamstrings_only"][i]:.1f}', f'{t["passive"][i]:.1f}', f'{t["opensim_hamstrings_active"][i]:.1f}']
            for i, a in enumerate(res['angles_deg'])]


TORQUE_HEADER = ['deg', 'torque (hamstrings active, -lock) N m', 'all cells, static N m', 'hamstrings\' own cells N m',
                 'passive N m', 'OpenSim N m']


def plot(res: dict, path) -> None:
    """Moment arms and length ratios (ours passive/active vs OpenSim; hamstrings, then the other knee
    muscles), the torque-angle curve and the hamstrings' force / Fmax: one PNG."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    ang = np.asarray(res['angles_deg'])
    names = list(res['muscles'])
    fig, axs = plt.subplots(2, 3, figsize=(16, 9))
    cmap = plt.get_cmap('tab10')
    for col, sel in ((0, [n for n in names if n in HAMSTRINGS]), (1, [n for n in names if n not in HAMSTRINGS])):
        for i, name in enumerate(sel):
            d = res['muscles'][name]
            c = cmap(i % 10)
            axs[0, col].plot(ang, np.asarray(d['opensim_moment_arm']) * 1e3, '-', color=c, label=name)
            axs[0, col].plot(ang, np.asarray(d['passive_moment_arm']) * 1e3, ':', color=c)
            axs[0, col].plot(ang, np.asarray(d['active_moment_arm']) * 1e3, '--', color=c)
            axs[1, col].plot(ang, d['opensim_length_ratio'], '-', color=c, label=name)
            axs[1, col].plot(ang, d['passive_length_ratio'], ':', color=c)
            axs[1, col].plot(ang, d['active_length_ratio'], '--', color=c)
            if col == 0:
                axs[1, 2].plot(ang, d['active_force_fraction'], '--o', ms=3, color=c, label=f'{name} (ours)')
                axs[1, 2].plot(ang, d['opensim_active_fraction'], '-', color=c, label=f'{name} (OpenSim)')
        what = 'hamstrings' if col == 0 else 'other knee muscles'
        axs[0, col].axhline(0, color='0.5', lw=0.6)
        axs[0, col].set(title=f'{what}: knee moment arm -dL/dθ', xlabel='knee flexion [deg]', ylabel='moment arm [mm] (+ flexes)')
        axs[1, col].set(title=f'{what}: length ratio L(θ)/L(0)', xlabel='knee flexion [deg]', ylabel='L/L0')
        axs[0, col].legend(fontsize=6, ncol=2, title='solid OpenSim, dotted ours passive, dashed ours active',
                           title_fontsize=6)
    t = res['torque']
    ax = axs[0, 2]
    if res['params'] == 'physical':
        ax.axhspan(*TORQUE_RANGE, color='0.9', label='adult peak isometric flexion (dynamometry)')
    ax.plot(ang, t['hamstrings_active'], 'o-', ms=3, label='ours: isometric torque (minus the knee lock\'s), hamstrings active')
    ax.plot(ang, t['hamstrings_only'], 's--', ms=3, label="ours: the hamstrings' own cells")
    ax.plot(ang, t['passive'], 'x:', label='ours: passive')
    ax.plot(ang, t['opensim_hamstrings_active'], 'k-', label='OpenSim (Rajagopal 2016), hamstrings active')
    ax.set(title='isometric knee-flexion torque, hamstrings fully active', xlabel='knee flexion [deg]',
           ylabel='torque [N m] (+ flexes)' + (' (paper set: dimensionless)' if res['params'] == 'paper' else ''))
    ax.legend(fontsize=6)
    axs[1, 2].axhline(MIN_FORCE_FRACTION, color='0.6', lw=0.8)
    axs[1, 2].set(title='hamstring force / Fmax, fully active', xlabel='knee flexion [deg]', ylabel='F / Fmax')
    axs[1, 2].legend(fontsize=6, ncol=2)
    fig.suptitle(f"tissue-sim validate: {res['model']}, params {res['params']}, settle {res['settle_s']:g} s")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format='png', dpi=70)
    plt.close(fig)
    from PIL import Image           # (matplotlib's own dependency) a 256-colour PNG: a quarter of the size
    Image.open(buf).convert('RGB').quantize(256).save(path, format='png', optimize=True)


# ------------------------------------------------------------------------------------- passive knee moment
ANKLE_JOINT, OSIM_ANKLE = 'ankle_r', 'ankle_angle_r'
PASSIVE_ANGLES = tuple(float(a) for a in range(0, 121, 15))
ANKLE_ANGLES = (-40.0, -30.0, -20.0, -10.0, 0.0, 10.0, 20.0)


def riener_edrich_knee(knee_deg, ankle_deg=0.0, hip_deg=0.0):
    """Passive knee moment [N m] (positive flexing; knee flexion, ankle dorsiflexion, hip flexion positive [deg]) of
    Riener & Edrich 1999 (J Biomech 32:539-544), their double-exponential fit to ten subjects:
    M = exp(1.800 - 0.0460 A - 0.0352 K + 0.0217 H) - exp(-3.971 - 0.0004 A + 0.0495 K - 0.0128 H) - 4.820
    + exp(2.220 - 0.150 K). The last term (the extension limit) with 0.150 per degree, not the 1.50 one secondary
    source prints: 1.50 would make it vanish within 2 deg of full extension (a step, not an elastic limit); both give
    10.4 N m at 0 deg."""
    k, a, h = np.asarray(knee_deg, float), float(ankle_deg), float(hip_deg)
    return (np.exp(1.800 - 0.0460 * a - 0.0352 * k + 0.0217 * h) - np.exp(-3.971 - 0.0004 * a + 0.0495 * k - 0.0128 * h)
            - 4.820 + np.exp(2.220 - 0.150 * k))


def riener_edrich_ankle(ankle_deg, knee_deg=0.0):
    """Passive ankle moment [N m] of Riener & Edrich 1999 in this project's convention (ankle dorsiflexion positive,
    moment positive dorsiflexing), from their ankle fit M = exp(2.1016 - 0.0843 A - 0.0176 K) - exp(-7.9763 + 0.1949 A
    + 0.0008 K) - 1.792 in their angle A, read as plantarflexion-positive with the moment plantarflexing-positive:
    their knee formula's ankle term (exp(... - 0.0460 A ...), the gastrocnemii's flexing moment) falls as A grows, so
    A grows as the gastrocnemii slacken, i.e. with plantarflexion. The coefficients are quoted as this project has
    them, not re-checked against the paper's text in this version (docs/solver.md "Force-length"): a secondary
    comparison; the physical set's choice rests on the knee."""
    a, k = -np.asarray(ankle_deg, float), float(knee_deg)
    return -(np.exp(2.1016 - 0.0843 * a - 0.0176 * k) - np.exp(-7.9763 + 0.1949 * a + 0.0008 * k) - 1.792)


def opensim_passive_moments(osim_path, knee_deg, ankle_deg) -> dict:
    """The source model with every right-leg muscle's passive fibre force switched on (DeGrooteFregly2016Muscle
    ignore_passive_fiber_force false; its own curve and strains: 0.7 or 0.6 at Fmax), zero activation, fibres
    equilibrated, every other coordinate 0: per pose (knee_deg[i], ankle_deg[i]) the knee and ankle moments [N m]
    sum over the muscles of tendon force x computeMomentArm (positive: flexing the knee, dorsiflexing the ankle)."""
    with _environment_kept():
        try:
            osim = _import_opensim()
        except ImportError:
            raise ValidationError('the OpenSim reference needs the opensim package (pip install --no-deps -r '
                                  'requirements/validation.txt)') from None
        osim.Logger.setLevelString('warn')
        model = osim.Model(str(osim_path))
        mus = model.getMuscles()
        right = [i for i in range(mus.getSize()) if mus.get(i).getName().endswith(OSIM_SIDE)]
        for i in right:
            osim.DeGrooteFregly2016Muscle.safeDownCast(mus.get(i)).set_ignore_passive_fiber_force(False)
        state = model.initSystem()
        cs = model.getCoordinateSet()
        for c in cs:
            if not c.get_locked():
                c.setValue(state, 0.0, False)
        knee, ankle = cs.get(OSIM_COORDINATE), cs.get(OSIM_ANKLE)
        out = {'version': osim.__version__, 'knee_Nm': [], 'ankle_Nm': []}
        for kd, ad in zip(knee_deg, ankle_deg):
            knee.setValue(state, math.radians(kd), False)
            ankle.setValue(state, math.radians(ad), False)
            model.assemble(state)
            for i in range(mus.getSize()):
                mus.get(i).setActivation(state, 0.0)
            model.equilibrateMuscles(state)
            model.realizeDynamics(state)
            tk = ta = 0.0
            for i in right:
                mu = mus.get(i)
                F = mu.getTendonForce(state)
                if F != 0.0:
                    tk += F * mu.computeMomentArm(state, knee)
                    ta += F * mu.computeMomentArm(state, ankle)
            out['knee_Nm'].append(float(tk))
            out['ankle_Nm'].append(float(ta))
    return out


PASSIVE_VARIANTS = {'thelen (k 5, eps0 0.6)': dict(fl_passive_curve='thelen', fl_passive_shape=5.0, fl_passive_strain=0.6),
                    'degroote (k 4, eps0 0.7)': dict(fl_passive_curve='degroote', fl_passive_shape=4.0,
                                                     fl_passive_strain=0.7)}


def run_passive_validation(params: str = 'physical', angles_deg=None, settle: float = 0.5, ramp_speed: float = 200.0,
                           osim_path=None, model=None, progress=None, overrides=()) -> dict:
    """The passive knee moment of the whole model (tissue + passive fibre force; no activation, knee held by the joint
    lock at each angle, ankle at 0, hip 0 as the bundled limb has it) against the source model with its passive
    fibre force on (opensim_passive_moments) and against Riener & Edrich 1999 (riener_edrich_knee). Measured: the
    total moment = minus the lock's torque (hold_sweep); the passive fibres' part = muscle.passive_state at the angle
    (it depends on the joint angles only), the tissue's part = the rest. The other passive curves
    (PASSIVE_VARIANTS) are reported as tissue + their fibre moment. Also the ankle at knee 0: the fibres' moment
    against OpenSim's (the tissue's ankle moment is not measured here). overrides: as run_validation's."""
    from tissue_sim.core import solver
    from tissue_sim.core.builder import default_model
    from tissue_sim.core.solver.muscle import passive_state
    base = parameter_set(params, overrides)
    if not (settle > 0 and math.isfinite(settle)):
        raise ValidationError(f'--settle {settle}: must be a positive number of seconds')
    angles = list(angles_deg) if angles_deg is not None else list(PASSIVE_ANGLES)
    osim_path = Path(osim_path) if osim_path else source_model_path()
    if not osim_path.is_file():
        raise ValidationError(f'source model not found: {osim_path}')
    tm = model if model is not None else default_model()
    sim = solver.compile_model(tm, base)
    j, ja = list(tm.joint_names).index(KNEE_JOINT), list(tm.joint_names).index(ANKLE_JOINT)
    run = hold_sweep(sim, [], angles, [], settle, ramp_speed, progress=(lambda d: progress('passive', d)) if progress else None)
    total = np.asarray(run['torque'], float)

    def fibres(p, knee, ankle, joint):
        s = sim if p is None else solver.compile_model(tm, dataclasses.replace(base, **p))
        out = []
        for kd, ad in zip(knee, ankle):
            q = np.array(s.j_rest, float)
            q[j], q[ja] = math.radians(kd), math.radians(ad)
            out.append(float(passive_state(s, q)[0][joint]) if s.params.passive_force_length
                       and s.params.specific_tension > 0 else 0.0)
        return np.array(out)

    own = fibres(None, angles, [0.0] * len(angles), j)
    tissue = total - own
    variants = {}
    on = dict(passive_force_length=True)
    for name, kw in PASSIVE_VARIANTS.items():
        variants[name] = {'fibres_Nm': list(fibres({**on, **kw}, angles, [0.0] * len(angles), j)),
                          'ankle_fibres_Nm': list(fibres({**on, **kw}, [0.0] * len(ANKLE_ANGLES), ANKLE_ANGLES, ja))}
        variants[name]['total_Nm'] = list(tissue + np.asarray(variants[name]['fibres_Nm']))
    ref = opensim_passive_moments(osim_path, angles, [0.0] * len(angles))
    ank = opensim_passive_moments(osim_path, [0.0] * len(ANKLE_ANGLES), ANKLE_ANGLES)
    re = riener_edrich_knee(np.asarray(angles))
    out = {'params': params, 'overrides': list(overrides), 'angles_deg': angles, 'settle_s': settle, 'model': tm.name,
           'via_points': _built_with_via_points(tm),
           'passive_force_length': bool(sim.params.passive_force_length),
           'passive_curve': dict(curve=sim.params.fl_passive_curve, k=sim.params.fl_passive_shape,
                                 eps0=sim.params.fl_passive_strain),
           'total_Nm': list(total), 'fibres_Nm': list(own), 'tissue_Nm': list(tissue), 'variants': variants,
           'opensim': ref, 'riener_edrich_Nm': list(re), 'diverged': run['diverged'],
           'ankle': {'angles_deg': list(ANKLE_ANGLES), 'opensim_Nm': ank['ankle_Nm'],
                     'fibres_Nm': list(fibres(None, [0.0] * len(ANKLE_ANGLES), ANKLE_ANGLES, ja)),
                     'riener_edrich_Nm': list(riener_edrich_ankle(np.asarray(ANKLE_ANGLES)))}}
    out['rms_vs_riener_edrich_Nm'], out['rms_vs_opensim_Nm'] = {}, {}
    if params == 'paper':             # dimensionless (Table 2: unit masses, k = 1e6): not comparable in N m
        return out
    for key, v in [('ours', total)] + [(k, np.asarray(d['total_Nm'])) for k, d in variants.items()]:
        out.setdefault('rms_vs_riener_edrich_Nm', {})[key] = float(np.sqrt(np.mean((v - re) ** 2)))
        out.setdefault('rms_vs_opensim_Nm', {})[key] = float(np.sqrt(np.mean((v - np.asarray(ref['knee_Nm'])) ** 2)))
    return out


def passive_rows(res: dict) -> tuple:
    """(header, rows) of the printed passive-moment table."""
    names = list(res['variants'])
    header = ['knee °', 'ours total', 'tissue', 'fibres'] + [f'total {n.split()[0]}' for n in names] + \
             ['OpenSim (passive on)', 'Riener & Edrich']
    rows = []
    for i, a in enumerate(res['angles_deg']):
        rows.append([f'{a:g}', f'{res["total_Nm"][i]:.1f}', f'{res["tissue_Nm"][i]:.1f}', f'{res["fibres_Nm"][i]:.1f}']
                    + [f'{res["variants"][n]["total_Nm"][i]:.1f}' for n in names]
                    + [f'{res["opensim"]["knee_Nm"][i]:.1f}', f'{res["riener_edrich_Nm"][i]:.1f}'])
    return header, rows


def plot_passive(res: dict, path) -> None:
    """The passive knee moment against the angle: ours (total, tissue, each curve's total), OpenSim, Riener & Edrich;
    and the ankle fibres' moment at knee 0 against OpenSim's."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4.2))
    a = res['angles_deg']
    ax.plot(a, res['total_Nm'], 'o-', label=f'ours, total ({res["passive_curve"]["curve"]}'
            + ('' if res['passive_force_length'] else ', fibres off') + ')')
    ax.plot(a, res['tissue_Nm'], 'x:', label='ours, tissue only')
    for n, d in res['variants'].items():
        ax.plot(a, d['total_Nm'], '--', label=f'ours, tissue + fibres {n}')
    ax.plot(a, res['opensim']['knee_Nm'], 's-', color='k', label='OpenSim source model, passive on (DeGroote-Fregly)')
    ax.plot(a, res['riener_edrich_Nm'], 'd-', color='tab:red', label='Riener & Edrich 1999')
    ax.axhline(0, color='0.7', lw=0.5)
    ax.set_xlabel('knee flexion [deg]'); ax.set_ylabel('passive knee moment [N m] (+ flexing)')
    ax.legend(fontsize=7); ax.set_title('passive knee moment, hip 0, ankle 0')
    b = res['ankle']
    bx.plot(b['angles_deg'], b['fibres_Nm'], 'o-', label=f'ours, fibres ({res["passive_curve"]["curve"]}, eps0 '
            f'{res["passive_curve"]["eps0"]:g})')
    for n, d in res['variants'].items():
        bx.plot(b['angles_deg'], d['ankle_fibres_Nm'], '--', label=f'ours, fibres {n}')
    bx.plot(b['angles_deg'], b['opensim_Nm'], 's-', color='k', label='OpenSim, passive on')
    bx.plot(b['angles_deg'], b['riener_edrich_Nm'], 'd-', color='tab:red', label='Riener & Edrich 1999 (ankle fit)')
    bx.set_ylim(-150.0, 100.0)                      # (the uncalibrated curves leave it: thousands of N m)
    bx.set_xlabel('ankle dorsiflexion [deg]'); bx.set_ylabel('passive ankle moment [N m] (+ dorsiflexing)')
    bx.legend(fontsize=7); bx.set_title('passive fibres at the ankle, knee 0')
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ------------------------------------------------------------------------------------- the knee's kinematics
WALKER_KNEE = 'walker_knee_r'
WALKER_SECONDARY = ('rotation2', 'rotation3', 'translation1', 'translation2', 'translation3')


def hinge_source_model(osim_path, centre_model, out_path) -> Path:
    """Write a copy of the source model whose walker knee is the plain hinge the paper set uses: its secondary
    rotations and translations (WALKER_SECONDARY) constant 0, rotation1 (knee_angle_r about the walker frame's x axis,
    the bundled knee's axis) about centre_model (model frame, m: the bundled knee's hinge centre), both of the joint's
    offset frames moved there (the tibia's rest pose unchanged: the two frames are aligned at 0)."""
    import xml.etree.ElementTree as ET
    tree = ET.parse(osim_path)
    joint = next((j for j in tree.getroot().iter('CustomJoint') if j.get('name') == WALKER_KNEE), None)
    if joint is None:
        raise ValidationError(f'{osim_path}: no CustomJoint {WALKER_KNEE!r}')
    for ta in joint.iter('TransformAxis'):
        if ta.get('name') in WALKER_SECONDARY:
            for fn in [c for c in ta if c.tag not in ('coordinates', 'axis')]:
                ta.remove(fn)
            const = ET.SubElement(ta, 'Constant', name='function')
            ET.SubElement(const, 'value').text = '0'
            ta.find('coordinates').text = ''
    c = np.asarray(centre_model, float)
    c_os = np.array([c[0], c[2], -c[1]])              # model (x ant, y left, z up) -> OpenSim femur (x ant, y up, z right)
    frames = {f.get('name'): f for f in joint.iter('PhysicalOffsetFrame')}
    parent = frames[joint.find('socket_parent_frame').text.strip()]
    delta = c_os - np.array([float(v) for v in parent.find('translation').text.split()])
    for f in frames.values():
        t = f.find('translation')
        t.text = ' '.join(repr(float(v)) for v in np.array([float(v) for v in t.text.split()]) + delta)
    tree.write(out_path)
    return Path(out_path)


def unwrapped_source_model(osim_path, muscles: list, out_path) -> Path:
    """Write a copy of the source model whose knee muscles (their OpenSim parts) have no wrap objects: each path its
    points alone, straight between them, as our chains are before the tissue round them shapes them."""
    import xml.etree.ElementTree as ET
    tree = ET.parse(osim_path)
    parts = {p for km in muscles for p in km.opensim}
    for el in tree.getroot().iter():
        if el.get('name') in parts:
            for objects in el.iterfind('.//PathWrapSet/objects'):
                for w in list(objects):
                    objects.remove(w)
    tree.write(out_path)
    return Path(out_path)


def run_kinematics(angles_deg=None, osim_path=None, model=None) -> dict:
    """What the knee's kinematics alone do to the moment arms (docs/validation.md "The knee's kinematics"): the source
    model's own muscle paths (wrapping included) evaluated with its walker knee and with the walker knee replaced by
    the plain hinge of the paper set (``hinge_source_model``): per knee muscle the moment arm (computeMomentArm) with
    each; the angles where the hinge changes its sign; the target hamstrings' (hinge - walker) / |walker| at the issue's
    angles. Beside them the walker knee with the knee muscles' wrap objects removed (``unwrapped_source_model``) and
    the angles where that changes the sign: what the source model's wrap surfaces alone decide. No elastic model is
    run."""
    import tempfile
    angles, osim_path, tm, muscles = _inputs(angles_deg, osim_path, model)
    j = list(tm.joint_names).index(KNEE_JOINT)
    with tempfile.TemporaryDirectory() as tmp:
        hinge = hinge_source_model(osim_path, tm.joint_centre[j], Path(tmp) / 'hinge.osim')
        unwrapped = unwrapped_source_model(osim_path, muscles, Path(tmp) / 'unwrapped.osim')
        walker_ref = opensim_reference(osim_path, muscles, angles, {})
        hinge_ref = opensim_reference(hinge, muscles, angles, {}, log_level='error')   # (its bone meshes are not found
                                                                                       # from the temporary folder)
        bare_ref = opensim_reference(unwrapped, muscles, angles, {}, log_level='error')
    out = {'angles_deg': angles, 'osim': str(osim_path), 'hinge_centre_m': [float(v) for v in tm.joint_centre[j]],
           'hinge_axis': [float(v) for v in tm.joint_axis[j]], 'muscles': {}, 'sign_changes': [], 'hamstrings': [],
           'wrap_sign_changes': []}
    for km in muscles:
        w = np.asarray(walker_ref['muscles'][km.name]['moment_arm'])
        h = np.asarray(hinge_ref['muscles'][km.name]['moment_arm'])
        u = np.asarray(bare_ref['muscles'][km.name]['moment_arm'])
        out['muscles'][km.name] = {'walker_moment_arm': list(w), 'hinge_moment_arm': list(h),
                                   'unwrapped_moment_arm': list(u)}
        for a, x, y, z in zip(angles, w, h, u):
            if np.sign(x) != np.sign(y):
                out['sign_changes'].append({'muscle': km.name, 'angle_deg': a, 'walker_mm': x * 1e3, 'hinge_mm': y * 1e3})
            if np.sign(x) != np.sign(z):
                out['wrap_sign_changes'].append({'muscle': km.name, 'angle_deg': a, 'walker_mm': x * 1e3,
                                                 'unwrapped_mm': z * 1e3})
        if km.name in TARGET_HAMSTRINGS:
            for a in TARGET_ANGLES:
                x, y = _at(angles, w, a), _at(angles, h, a)
                if x is not None:
                    out['hamstrings'].append({'muscle': km.name, 'angle_deg': a, 'walker_mm': x * 1e3, 'hinge_mm': y * 1e3,
                                              'rel_difference': (y - x) / abs(x),
                                              'within_tolerance': bool(abs(y - x) <= MOMENT_ARM_TOLERANCE * abs(x))})
    return out


def plot_kinematics(res: dict, path) -> None:
    """Moment arms of the knee muscles in the source model, walker knee (solid) against the plain hinge (dashed) and
    the walker knee without the wrap objects (dotted)."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.8))
    for k, (name, d) in enumerate(res['muscles'].items()):
        ax = axes[0] if name in HAMSTRINGS else axes[1]
        c = f'C{k % 10}'
        ax.plot(res['angles_deg'], np.asarray(d['walker_moment_arm']) * 1e3, '-', color=c, label=name)
        ax.plot(res['angles_deg'], np.asarray(d['hinge_moment_arm']) * 1e3, '--', color=c)
        ax.plot(res['angles_deg'], np.asarray(d['unwrapped_moment_arm']) * 1e3, ':', color=c)
    for ax, title in zip(axes, ('hamstrings', 'the other knee muscles')):
        ax.axhline(0.0, color='k', lw=0.5)
        ax.set_xlabel('knee flexion [deg]'); ax.set_ylabel('moment arm [mm] (+ flexor)')
        ax.set_title(f'source model, {title}: walker knee (solid), plain hinge (dashed), no wrap objects (dotted)',
                     fontsize=8)
        ax.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
