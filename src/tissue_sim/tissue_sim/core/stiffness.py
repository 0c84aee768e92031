"""Knee joint stiffness under co-contraction of the hamstrings and quadriceps (ROS-free).

Antagonists that contract together stiffen a joint without moving it. Measured here the way an
isometric dynamometer with a position perturbation does it, with the solver's joint lock
(``Control.joint_lock`` / ``joint_target``, docs/solver.md "Joint lock"): for each co-contraction
level a (the hamstrings at activation a, the quadriceps at the activation that cancels their active
torque at the angle, :func:`balance`, so that the co-contraction alone does not move the knee; every
other muscle passive; the ankle held at its rest angle as a strapped foot):

1. hold the knee at ``angle`` while the activation ramps to a, settle; the isometric knee torque
   tau0 = -joint_lock_torque (positive = flexing), averaged over the last tenth of the hold;
2. move the target to ``angle + delta`` (a 50-ms ramp), settle, torque tau+; to ``angle - delta``, settle, tau-;
3. stiffness k = -(tau+ - tau-) / (2 delta) [N m/rad] (a central difference: the restoring torque
   per radian of imposed rotation; positive = the joint resists);
4. release the knee (lock off, the activation kept) and follow it for ``free_seconds``: the drift
   [deg] = the largest |q - angle| while free, and where it ends. The same with the hamstrings
   alone at a (``single``) shows what the co-contraction prevents.

Returned as a JSON-able dict (:func:`measure`); ``tissue-sim stiffness`` prints, writes and plots it.
"""
from __future__ import annotations

import math

import numpy as np

KNEE = 'knee_r'
AGONISTS = ('hamstrings', 'quadriceps')
STEP_SECONDS = 0.05      # [s] the perturbation's ramp (delta in 50 ms: an instant jump flings the tissue)


def _hold(sim, st, ctrl, seconds: float) -> float:
    """Step ``seconds`` with the control as set; the mean isometric torque of the knee [N m] over the
    last tenth (minus the lock's torque)."""
    from tissue_sim.core import solver
    j = list(sim.tissue.joint_names).index(KNEE)
    n = max(10, int(round(seconds / sim.params.dt)))
    n_avg = max(1, n // 10)
    solver.step(sim, st, ctrl, n_steps=n - n_avg)
    tau = 0.0
    for _ in range(n_avg):
        solver.step(sim, st, ctrl)
        tau -= st.joint_lock_torque[j] / n_avg
    return float(tau)


def _move(sim, st, ctrl, j: int, target: float, seconds: float):
    """Move the locked joint j's target linearly to ``target`` [rad] over ``seconds`` (a jump would move
    the bones in one sub-step and fling the tissue)."""
    from tissue_sim.core import solver
    n = max(1, int(round(seconds / sim.params.dt)))
    q0 = float(ctrl.joint_target[j])
    for i in range(n):
        ctrl.joint_target[j] = q0 + (target - q0) * (i + 1) / n
        solver.step(sim, st, ctrl)


def level_stiffness(sim, activations: dict, angle_deg: float = 30.0, delta_deg: float = 2.0, settle: float = 0.3,
                    ramp: float = 0.3, free_seconds: float = 0.5, release: bool = True, perturb: bool = True) -> dict:
    """One activation ({selector: a}, every other muscle passive; see the module's documentation);
    DivergenceError propagates. ``perturb``: the +-delta steps and the stiffness; ``release``: the free
    knee's drift."""
    from tissue_sim.core import solver
    names = list(sim.tissue.joint_names)
    j = names.index(KNEE)
    target = np.zeros(sim.n_muscles)
    for sel, a in activations.items():
        target[solver.muscle_indices(sim, sel)] = float(a)
    st, ctrl = solver.make_state(sim), solver.make_control(sim)
    ctrl.joint_lock[:] = True                        # the knee, and the ankle at rest (the foot strapped)
    ctrl.joint_target[:] = st.q
    th = math.radians(angle_deg)
    # to the angle (the lock follows a moving target exactly) with the activation rising alongside
    n = max(1, int(round(ramp / sim.params.dt)))
    for i in range(n):
        ctrl.joint_target[j] = th * (i + 1) / n
        ctrl.activation[:] = target * (i + 1) / n
        solver.step(sim, st, ctrl)
    tau0 = _hold(sim, st, ctrl, settle)
    if not perturb:
        return {'activations': {k_: float(v) for k_, v in activations.items()}, 'torque_nm': tau0}
    d = math.radians(delta_deg)
    _move(sim, st, ctrl, j, th + d, STEP_SECONDS)
    tau_p = _hold(sim, st, ctrl, settle)
    _move(sim, st, ctrl, j, th - d, 2 * STEP_SECONDS)
    tau_m = _hold(sim, st, ctrl, settle)
    _move(sim, st, ctrl, j, th, STEP_SECONDS)
    _hold(sim, st, ctrl, settle / 2)
    k = -(tau_p - tau_m) / (2 * d)
    out = {'activations': {k_: float(v) for k_, v in activations.items()}, 'torque_nm': tau0, 'torque_plus_nm': tau_p,
           'torque_minus_nm': tau_m, 'stiffness_nm_per_rad': float(k), 'stiffness_nm_per_deg': float(k * math.pi / 180)}
    if not release:
        return out
    # release the knee: how far it drifts under this activation
    ctrl.joint_lock[j] = False
    q = []
    for _ in range(max(1, int(round(free_seconds / sim.params.dt / 10)))):
        solver.step(sim, st, ctrl, n_steps=10)
        q.append(math.degrees(st.q[j]))
    q = np.array(q)
    dq = q - angle_deg
    out.update(free_drift_max_deg=float(np.abs(dq).max()), free_final_deg=float(q[-1]))
    return out


def balance(sim, level: float, tau_ham: float, tau_passive: float, angle_deg: float = 30.0, settle: float = 0.3,
            ramp: float = 0.3, tol_nm: float = 1.0, max_iter: int = 4) -> dict:
    """The quadriceps activation b that cancels the hamstrings' active torque at the angle: the
    isometric torque with the hamstrings at ``level`` and the quadriceps at b equals the passive one
    (``tau_passive``) within ``tol_nm`` (or 5 % of the hamstrings' active torque). ``tau_ham``: the
    torque with the hamstrings alone at ``level``. Regula falsi (Illinois) between b = 0 and
    b = level (the quadriceps are the stronger group: at equal activation they extend the knee);
    torque is not linear in activation on this model (hamstrings alone at 30 deg: -1.2, +6.8, +81 N m at
    0.25, 0.5, 1), so it is solved, not scaled."""
    f0 = tau_ham - tau_passive
    tries = [(0.0, f0)]
    tol = max(tol_nm, 0.05 * abs(f0))
    if f0 <= tol or level <= 0:                       # nothing to cancel
        return {'quadriceps': 0.0, 'residual_nm': f0, 'tries': tries}
    lo, flo, hi = 0.0, f0, float(level)
    fhi = hold_torque(sim, {'hamstrings': level, 'quadriceps': hi}, angle_deg, settle, ramp) - tau_passive
    tries.append((hi, fhi))
    if fhi >= 0:                                      # the quadriceps at the same level do not cancel it
        return {'quadriceps': hi, 'residual_nm': fhi, 'tries': tries}
    best, side = (hi, fhi), 0
    for _ in range(max_iter):
        b = (lo * fhi - hi * flo) / (fhi - flo)
        fb = hold_torque(sim, {'hamstrings': level, 'quadriceps': b}, angle_deg, settle, ramp) - tau_passive
        tries.append((b, fb))
        if abs(fb) < abs(best[1]):
            best = (b, fb)
        if abs(fb) <= tol:
            break
        if fb > 0:
            lo, flo = b, fb
            if side == 1:
                fhi /= 2
            side = 1
        else:
            hi, fhi = b, fb
            if side == -1:
                flo /= 2
            side = -1
    return {'quadriceps': float(best[0]), 'residual_nm': float(best[1]), 'tries': [(float(b), float(f)) for b, f in tries]}


def hold_torque(sim, activations: dict, angle_deg: float, settle: float, ramp: float) -> float:
    """The isometric knee torque [N m] (positive = flexing) held at the angle under ``activations``."""
    return level_stiffness(sim, activations, angle_deg=angle_deg, settle=settle, ramp=ramp, release=False,
                           perturb=False)['torque_nm']


def measure(sim, levels=(0.0, 0.25, 0.5, 1.0), angle_deg: float = 30.0, delta_deg: float = 2.0, settle: float = 0.3,
            ramp: float = 0.3, free_seconds: float = 0.5, single: bool = True, progress=None,
            jobs: int | None = None) -> dict:
    """Knee stiffness at each co-contraction level a: the hamstrings at a, the quadriceps balancing them
    (:func:`balance`); with ``single`` also the figures of the hamstrings alone at a (what the
    antagonist prevents: their drift). A level that diverges gives its error instead of figures (no
    number made up). The levels are independent runs: ``jobs`` of them at a time on threads of their own
    (realtime.map_threads; default the usable CPUs), each giving what it gives alone; progress(a) is called from
    them."""
    from tissue_sim.core import solver
    from tissue_sim.core.realtime import map_threads
    kw = dict(angle_deg=angle_deg, delta_deg=delta_deg, settle=settle, ramp=ramp, free_seconds=free_seconds)
    tau_p = hold_torque(sim, {}, angle_deg, settle, ramp)

    def level(a):
        r = {'level': float(a)}
        try:
            ham = level_stiffness(sim, {'hamstrings': a}, **kw) if a > 0 else None
            bal = balance(sim, a, ham['torque_nm'], tau_p, angle_deg, settle, ramp) if a > 0 else {'quadriceps': 0.0}
            r.update(level_stiffness(sim, {'hamstrings': a, 'quadriceps': bal['quadriceps']}, **kw))
            r['balance'] = bal
            if ham is not None and single:
                r['hamstrings_only'] = {k: ham[k] for k in ('torque_nm', 'stiffness_nm_per_rad', 'free_drift_max_deg',
                                                             'free_final_deg')}
        except solver.DivergenceError as e:
            r['diverged'] = str(e)
        if progress:
            progress(a)
        return r
    rows = map_threads(level, levels, jobs)
    return {'joint': KNEE, 'angle_deg': angle_deg, 'delta_deg': delta_deg, 'settle_s': settle, 'ramp_s': ramp,
            'free_seconds': free_seconds, 'params': sim.params.preset, 'model': sim.tissue.name,
            'passive_torque_nm': tau_p, 'levels': rows,
            'published_passive_stiffness_nm_per_rad': published_passive_stiffness(angle_deg, delta_deg),
            'definitions': {
                'torque_nm': 'isometric knee torque at the angle, positive = flexing (minus the joint lock torque)',
                'stiffness_nm_per_rad': '-(torque at angle+delta - torque at angle-delta) / (2 delta)',
                'free_drift_max_deg': 'largest |knee angle - angle| within free_seconds after the lock is released, '
                                      'the activation kept'}}


def published_passive_stiffness(angle_deg: float, delta_deg: float) -> float:
    """The relaxed knee's flexion stiffness [N m/rad] at angle_deg (hip and ankle 0) from Riener & Edrich 1999's passive
    moment (validation.riener_edrich_knee; all passive structures of ten subjects), by the same central difference
    over +-delta_deg as the simulated one: the reference for level 0."""
    from tissue_sim.core.validation import riener_edrich_knee
    m = riener_edrich_knee([angle_deg + delta_deg, angle_deg - delta_deg])
    return float(-(m[0] - m[1]) / math.radians(2.0 * delta_deg))


def plot(res: dict, path) -> None:
    """Stiffness and free-knee drift against the level: co-contraction beside the hamstrings alone."""
    import matplotlib
    matplotlib.use('Agg', force=True)
    import matplotlib.pyplot as plt
    rows = [r for r in res['levels'] if 'diverged' not in r]
    a = [r['level'] for r in rows]
    single = [(r['level'], r['hamstrings_only']) for r in rows if 'stiffness_nm_per_rad' in r.get('hamstrings_only', {})]
    fig, axs = plt.subplots(1, 2, figsize=(10, 3.8), dpi=110)
    axs[0].plot(a, [r['stiffness_nm_per_rad'] for r in rows], 'o-', lw=2, label='co-contraction (quadriceps balancing)')
    axs[1].plot(a, [r['free_drift_max_deg'] for r in rows], 'o-', lw=2, label='co-contraction')
    if res.get('published_passive_stiffness_nm_per_rad') is not None:
        axs[0].plot([0.0], [res['published_passive_stiffness_nm_per_rad']], 'k*', ms=10,
                    label='relaxed knee, Riener & Edrich 1999')
    if single:
        axs[0].plot([s[0] for s in single], [s[1]['stiffness_nm_per_rad'] for s in single], 's--', label='hamstrings alone')
        axs[1].plot([s[0] for s in single], [s[1]['free_drift_max_deg'] for s in single], 's--', label='hamstrings alone')
    axs[0].set_ylabel('knee stiffness k [N m/rad]')
    axs[1].set_ylabel(f'free knee drift within {res["free_seconds"]:g} s [deg]')
    for ax in axs:
        ax.set_xlabel('hamstring activation')
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    axs[0].set_title(f'{res["joint"]} at {res["angle_deg"]:g} deg, +-{res["delta_deg"]:g} deg ({res["params"]} set)')
    axs[1].set_title('released knee, activation kept')
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
