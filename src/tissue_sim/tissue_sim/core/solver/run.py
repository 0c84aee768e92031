"""Observations and headless runs: observe(), simulate() (activation timelines: tissue_sim.core.activation)."""
from __future__ import annotations

from typing import Iterator

import numpy as np
from scipy.spatial.transform import Rotation

from tissue_sim.core.activation import timeline_function
from tissue_sim.core.solver.measures import cell_axial_lengths, cell_volumes, kinetic_energy, skeleton_energy
from tissue_sim.core.solver.model import SimModel, State, make_state
from tissue_sim.core.solver.muscle import muscle_forces
from tissue_sim.core.solver.step import _run


def observe(sim: SimModel, state: State) -> dict:
    """Outputs of the current state.

    joint_positions (J,) [rad], joint_velocities (J,) [rad/s], muscle_lengths (M,) [m] (per muscle, with
    params.length_measure 'centre_line' the length of its centre line, measures.centre_lines; 'chord': the sum over
    slice gaps of the mean distance between its cells' bottom- and top-ring centroids),
    muscle_volumes (M,) [m^3] (sum of its cells' volumes, divergence theorem on the triangulated
    prism surface), muscle_stretch (M,) (contraction state lambda), kinetic_energy [J] (free
    vertices), elastic_energy [J] (sum 0.5 k |G - x|^2 at the last force evaluation),
    skeleton_energy [J] (segments' kinetic + gravitational potential), joint_lock_torque (J,) [N m] (the
    torque each joint lock applied in the last sub-step about the joint axis, + in the direction q grows; in
    a static hold it balances the tissue's and gravity's torque: the isometric joint torque is its negative;
    0 where no lock),
    segment_poses (S, 7) x y z qx qy qz qw (the transform from rest to current pose), time [s], step;
    activations (M,) the activation state (the commands with instant activation, Params.activation_time 0),
    muscle_forces (M,) [N] each muscle's force, active tension + passive fibre force (muscle_active_forces,
    muscle_passive_forces; 0 in the paper set: muscle.muscle_forces), fibre_lengths (M,) normalised fibre lengths,
    passive_energy [J] of the passive fibre force (0 when off)."""
    M = sim.n_muscles
    mus = sim.cell_muscle
    sel = mus >= 0
    mv = np.bincount(mus[sel], weights=cell_volumes(sim, state.x, 'muscle'), minlength=M)
    if sim.params.length_measure == 'centre_line':
        ml = sim.centre_lines.lengths(state.x, M)
    else:
        alen = np.empty(sim.n_cells)
        cell_axial_lengths(state.x, sim.off, sim.cv, alen)
        ml = np.bincount(mus[sel], weights=(alen * sim.length_weight)[sel], minlength=M)
    ke = kinetic_energy(sim, state)
    mf = muscle_forces(sim, state)
    return dict(time=state.time, skeleton_energy=skeleton_energy(sim, state), step=state.step, joint_positions=state.q.copy(), joint_velocities=state.qd.copy(),
                joint_lock_torque=(state.joint_lock_torque.copy() if state.joint_lock_torque is not None
                                   else np.zeros(sim.n_joints)),
                muscle_lengths=ml, muscle_volumes=mv, muscle_stretch=state.lam.copy(), kinetic_energy=ke,
                elastic_energy=float(state.cell_energy.sum()),
                segment_poses=np.concatenate([state.seg_t, Rotation.from_matrix(state.seg_R).as_quat()], axis=1),
                activations=(state.activation.copy() if state.activation is not None else np.zeros(M)),
                muscle_forces=mf['total'], muscle_active_forces=mf['active'], muscle_passive_forces=mf['passive'],
                fibre_lengths=mf['fibre_length'], passive_energy=mf['passive_energy'])




def simulate(sim: SimModel, duration: float, timeline=None, dt: float | None = None, every: int = 1,
             state: State | None = None, output: str = 'state') -> Iterator[tuple]:
    """Run headless for ``duration`` s; yield (t, snapshot) at t = 0 and every ``every`` steps.

    Snapshot: a State copy (output='state') or observe()'s dict (output='obs'). Activation is
    sampled at the start of every step. ``state`` (modified in place) continues a run. Raises
    DivergenceError like step()."""
    dt = sim.params.dt if dt is None else float(dt)
    if not (duration >= 0 and dt > 0 and every >= 1):
        raise ValueError('simulate: need duration >= 0, dt > 0, every >= 1')
    if output not in ('state', 'obs'):
        raise ValueError("simulate: output must be 'state' or 'obs'")
    fn = timeline_function(sim, timeline)
    st = make_state(sim) if state is None else state
    snap = (lambda s: s.copy()) if output == 'state' else (lambda s: observe(sim, s))
    n_total = int(round(duration / dt))
    t0 = st.time
    yield st.time, snap(st)
    done = 0
    while done < n_total:
        n = min(every, n_total - done)
        acts = np.stack([fn(t0 + (done + i) * dt) for i in range(n)])
        _run(sim, st, acts, dt)
        done += n
        yield st.time, snap(st)
