"""SimModel (immutable, compiled flat arrays), State (mutable), Control; compile_model/make_state/make_control.

The MuJoCo mjModel/mjData split: ``compile_model(tissue_model, params)`` turns the builder's
TissueModel plus physical parameters into the arrays the kernels read; ``make_state`` gives the
mutable simulation state at rest; ``make_control`` the per-muscle activation.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from tissue_sim.core.model import JOINT_COUPLED, JOINT_HINGE, TISSUE_MUSCLE, TissueModel
from tissue_sim.core.geometry import prism_volumes
from tissue_sim.core.solver import cells as CK, contact as CT, skeleton as SK, volume as VO
from tissue_sim.core.solver.measures import CentreLines, cell_axial_lengths, centre_lines
from tissue_sim.core.solver.params import Params


class DivergenceError(RuntimeError):
    """The simulation diverged. ``step`` (int, the step that failed), ``cell`` (int or -1),
    ``cause`` (str). The state is left at the last good step (no NaN leaves ``step``)."""

    def __init__(self, step: int, cell: int, cause: str):
        self.step, self.cell, self.cause = int(step), int(cell), str(cause)
        where = f', cell {self.cell}' if self.cell >= 0 else ''
        super().__init__(f'simulation diverged at step {self.step}{where}: {self.cause}')


def frozen(a, dtype=None):
    """A read-only, C-contiguous copy of a (as dtype): how SimModel holds its arrays, and what a kernel's caller
    hands it in place of one of them (numba compiles read-only and writable arrays as two signatures)."""
    a = np.ascontiguousarray(a if dtype is None else np.asarray(a, dtype=dtype))
    a = a.copy()
    a.flags.writeable = False
    return a


@dataclasses.dataclass(frozen=True, eq=False)
class SimModel:
    """Compiled, immutable model. Arrays are read-only, contiguous, ready for the numba kernels."""
    tissue: TissueModel
    params: Params
    n_substeps: int                 # sub-steps per step at params.dt (1 with the mass_scaled integrator)
    omega_max: float                # [rad/s] highest tissue natural frequency estimated at rest
    damp_rate: float                # [1/s] highest damping rate of a free vertex (sum b / m + velocity damping)
    # soft tissue
    rest: np.ndarray                # (V, 3) rest positions [m]
    inv_mass: np.ndarray            # (V,) 1/kg (0 for bone-attached vertices)
    mass: np.ndarray                # (V,) kg
    vertex_segment: np.ndarray      # (V,) int32, -1 free
    vertex_stiffness: np.ndarray    # (V,) [N/m] kappa_i = sum over the vertex's cells of k + k_active (+ volume stiffness)
    vertex_damping: np.ndarray      # (V,) [N s/m] sum over the vertex's cells of damp_b
    off: np.ndarray                 # (C+1,) int64
    cv: np.ndarray                  # (K,) int32
    X0: np.ndarray                  # (K, 3) rest positions relative to each cell's rest centroid [m]
    Qinv: np.ndarray                # (C, 3, 3) inverse of sum X0 X0^T (fibre-stretch estimate)
    q_tr: np.ndarray                # (C,) [m^2] tr Q, Q = sum X0 X0^T (elastic energy from moments)
    q_ff: np.ndarray                # (C,) [m^2] f^T Q f along the cell's fibre axis f
    rest_length: np.ndarray         # (C,) [m] rest distance between the bottom- and top-ring centroids (active tension)
    fibre: np.ndarray               # (C, 3)
    cell_muscle: np.ndarray         # (C,) int32
    k: np.ndarray                   # (C,) passive spring constant per cell-vertex [N/m]
    k_active: np.ndarray            # (C,) added spring constant at full activation [N/m]
    damp_b: np.ndarray              # (C,) deformation-damping coefficient [N s/m]
    rest_volume: np.ndarray         # (C,) [m^3]
    k_volume: np.ndarray            # (C,) volume penalty stiffness on det of the best-fit affine map [J] (0 = off)
    volume_cap: np.ndarray          # (C,) [1/m^2] bound on |grad det D|^2 = sum_i |cof(D) Qinv X0_i|^2 beyond which the volume
                                    # force is scaled down (kvol x the bound = implicit_volume_cap or explicit_volume_cap
                                    # x keff; 0 = none); the enclosed volume's force the same beyond |grad (V/V0)|^2 = it
    cell_sign: np.ndarray           # (C,) +1/-1 ring orientation (signed volume formula)
    k_enclosed: np.ndarray          # (C,) [J] stiffness of the volume energy on the enclosed volume (volume_measure 'enclosed':
                                    # k_volume of the muscle cells but thin ones, which the cell kernel then leaves out; 0 = off;
                                    # volume.enclosed_lanes)
    end_rings: CK.EndRings          # the muscles' end rings partly bound across a joint (end_ring_pull 'bound'; none otherwise)
    length_weight: np.ndarray       # (C,) weight of the cell's axial length in its muscle's length
    muscle_rest_length: np.ndarray  # (M,) [m] each muscle's length at rest (sum of length_weight x rest axial length)
    centre_lines: CentreLines       # each muscle's centre line, a linear map of the positions (observe's muscle_lengths
                                    # with params.length_measure 'centre_line')
    free_idx: np.ndarray            # (V - A,) int32 free vertices
    att_idx: np.ndarray             # (A,) int32 bone-attached vertices, grouped by segment (ascending vertex within)
    att_seg: np.ndarray             # (A,) int32 their segments
    via_off: np.ndarray             # (R+1,) int64 point via rings (TissueModel.via_point_*): ring r's vertices
    via_idx: np.ndarray             # (N,) int32 via_idx[via_off[r]:via_off[r + 1]]
    via_seg: np.ndarray             # (R,) int32 the segment holding ring r's centroid
    via_local: np.ndarray           # (R, 3) [m] the centroid's place in that segment's frame (its rest centroid)
    # skeleton
    seg_order: np.ndarray           # (S,) parents before children
    seg_parent: np.ndarray
    seg_joint: np.ndarray           # (S,) joint whose child is s, -1 root
    seg_mass: np.ndarray            # (S,) [kg] incl. attached vertices if params.attached_mass_to_segment
    seg_com: np.ndarray             # (S, 3) [m] rest pose
    seg_inertia: np.ndarray         # (S, 3, 3) [kg m^2] about the COM
    j_parent: np.ndarray
    j_child: np.ndarray
    j_type: np.ndarray
    j_axis: np.ndarray
    j_centre: np.ndarray
    j_rest: np.ndarray
    j_range: np.ndarray
    anc: np.ndarray                 # (J, S) bool: joint j moves segment s
    gravity: np.ndarray             # (3,)
    j_driver: np.ndarray            # (J,) int32 driving hinge of a coupled joint, -1 otherwise
    cp_off: np.ndarray              # (J+1,) int64 each coupled joint's knots in cp_x
    cp_x: np.ndarray                # (N,) [rad] knots (driver coordinate)
    cp_c: np.ndarray                # (N, SK.CHANNELS, 4) cubic coefficients per knot interval and channel (coupling_spline)
    j_sec: np.ndarray               # (J, 2, 3) secondary rotation axes of a hinge with a path (coupling_spline)
    skeleton: SK.Skeleton           # the skeleton arrays above (seg_* ... gravity) as the skeleton kernels read them
    cell_blocks: CK.CellLayout      # the cells again, as the cell kernel reads them: rings, chains, SIMD lanes (pack_cells)
    contact: CT.ContactGrids        # bone contact: a signed-distance grid per segment with bones, each free vertex's floor
                                    # (contact.build; no grid when params.bone_contact is off: stage 4 does nothing)

    def inv_denominator(self, h: float) -> np.ndarray:
        """(V,) [1/kg] factor of h f in the velocity update for sub-step length h: 1/m (explicit) or
        1/max(m_i, h^2 kappa_i / stability_limit^2, (h^2 kappa_i + 2 h b_i) / 3.8) (mass_scaled, b_i the vertex's
        summed damping coefficient); 0 for bone-attached vertices."""
        if self.params.integrator in ('explicit', 'implicit'):
            return self.inv_mass
        # selective mass scaling: a vertex whose cells' summed stiffness would exceed the explicit
        # limit at this h gets the mass that puts it at stability_limit (Gershgorin bound on omega h)
        # and, with damping rate c = b/m, (omega h)^2 + 2 c h below 95 % of the exact bound 4 (strongly
        # damped light vertices, e.g. the physical set's, need this; the paper set's barely change)
        kh2 = h * h * self.vertex_stiffness
        den = np.maximum(np.maximum(self.mass, kh2 / self.params.stability_limit ** 2),
                         (kh2 + 2.0 * h * self.vertex_damping) / 3.8)
        return frozen(np.where(self.inv_mass > 0, 1.0 / den, 0.0))

    @property
    def n_vertices(self):
        return self.rest.shape[0]

    @property
    def n_cells(self):
        return self.off.shape[0] - 1

    @property
    def n_muscles(self):
        return self.tissue.n_muscles

    @property
    def n_joints(self):
        return self.j_type.shape[0]

    @property
    def n_segments(self):
        return self.seg_mass.shape[0]


@dataclasses.dataclass(eq=False)
class State:
    """Mutable simulation state (mjData). Positions [m], velocities [m/s], joint coordinates [rad]."""
    x: np.ndarray                   # (V, 3)
    v: np.ndarray                   # (V, 3)
    f: np.ndarray                   # (V, 3) last elastic+damping forces [N]
    quat: np.ndarray                # (C, 4) per-cell rotation (x, y, z, w), warm start
    q: np.ndarray                   # (J,) joint coordinates [rad]
    qd: np.ndarray                  # (J,) [rad/s]
    seg_R: np.ndarray               # (S, 3, 3) segment rotations (act on rest coordinates)
    seg_t: np.ndarray               # (S, 3) [m]
    lam: np.ndarray                 # (M,) fibre stretch of each muscle's rest shape (1 = rest length)
    cell_energy: np.ndarray         # (C,) elastic energy per cell at the last force evaluation
    pressure: np.ndarray            # (C,) integral volume term of each muscle cell [J per unit det]
    cell_length: np.ndarray = None  # (C,) [m] axial length of each cell (ring-centroid distance) at the last force evaluation
    muscle_length: np.ndarray = None    # (M,) [m] muscle lengths at the last force evaluation (force-velocity on; -1: not yet)
    muscle_velocity: np.ndarray = None  # (M,) [m/s] lengthening velocity of each muscle, low-pass filtered (force-velocity on)
    joint_lock_torque: np.ndarray = None    # (J,) [N m] torque each joint lock applied about its axis in the last sub-step
                                    # (+ about the joint axis, the direction q grows; 0 where not locked)
    activation: np.ndarray = None   # (M,) activation state in [0, 1] (Params.activation_time > 0: it follows the commanded
                                    # excitation with first-order dynamics; otherwise it is the last command)
    contact_wrench: np.ndarray = None   # (S, 6) the contact's reaction on each segment in the last sub-step (force [N],
                                    # its moment about the world origin [N m]), applied in the next sub-step (docs/contact.md)
    step: int = 0
    time: float = 0.0               # [s]
    x_prev: np.ndarray = None       # (V, 3) [m] the positions one sub-step back (implicit_scheme 'bdf2'; internal)
    v_prev: np.ndarray = None       # (V, 3) [m/s] the velocities one sub-step back
    history_h: np.ndarray = None    # (1,) [s] the sub-step length x_prev and v_prev are back by (0: no history; a bdf2 step
                                    # then takes the past as at constant velocity, x_prev = x - h v, v_prev = v)
    x_back: np.ndarray = None       # double buffers (internal)
    v_back: np.ndarray = None
    workspace: object = dataclasses.field(default=None, repr=False)   # the step's scratch buffers (step.Workspace,
                                    # internal: made on the first step, not copied)

    def copy(self) -> 'State':
        return State(**{f.name: (getattr(self, f.name).copy() if isinstance(getattr(self, f.name), np.ndarray)
                                 else None if f.name == 'workspace' else getattr(self, f.name))
                        for f in dataclasses.fields(self)})


@dataclasses.dataclass(eq=False)
class Control:
    """What the user commands each step (mjData.ctrl): muscle activations and, optionally, joint locks."""
    activation: np.ndarray          # (M,) float64 in [0, 1]
    joint_lock: np.ndarray = None   # (J,) bool: hold hinge j at joint_target[j] (q = target, qd = 0 for a steady
                                    # target; the torque it takes: State.joint_lock_torque). None: no lock
    joint_target: np.ndarray = None     # (J,) [rad] the locked joints' coordinates (None: their rest coordinates)


# ---------------------------------------------------------------------------------------- compile
def compile_model(tm: TissueModel, params: Params | None = None) -> SimModel:
    """TissueModel + Params -> SimModel (raises ValueError naming the problem for a bad model)."""
    p = (params or Params.paper()).validate()
    tm.validate()
    V, C = tm.n_vertices, tm.n_cells
    off = np.asarray(tm.cell_offsets, np.int64)
    cv = np.asarray(tm.cell_vertices, np.int32)
    rest = np.asarray(tm.rest_positions, np.float64)
    sizes = np.diff(off)
    cell_of_k = np.repeat(np.arange(C), sizes)
    cent = np.zeros((C, 3))
    np.add.at(cent, cell_of_k, rest[cv])
    cent /= sizes[:, None]
    X0 = rest[cv] - cent[cell_of_k]
    Q = np.zeros((C, 3, 3))
    np.add.at(Q, cell_of_k, X0[:, :, None] * X0[:, None, :])
    tr = np.trace(Q, axis1=1, axis2=2)
    ev = np.linalg.eigvalsh(Q)
    flat = ev[:, 0] < 1e-9 * ev[:, 2]            # degenerate (flat) rest cell: pseudo-inverse, no volume term
    Qinv = np.linalg.inv(np.where(flat[:, None, None], np.eye(3), Q))
    if np.any(flat):
        Qinv[flat] = np.linalg.pinv(Q[flat], rcond=1e-9, hermitian=True)
    fib = np.asarray(tm.cell_fibre, np.float64)
    vol = prism_volumes(rest, off, cv)
    if np.any(vol == 0) or not np.all(np.isfinite(vol)):
        bad = int(np.flatnonzero(~(np.abs(vol) > 0))[0])
        raise ValueError(f'model {tm.name!r}: cell {bad} has zero or non-finite rest volume')
    sign = np.sign(vol)            # ring orientation of each cell (the volume formula assumes counter-clockwise)
    vol = np.abs(vol)
    muscle = tm.cell_tissue == TISSUE_MUSCLE
    # masses
    if p.mass_mode == 'uniform':
        mass = np.full(V, p.vertex_mass)
    else:
        dens = np.where(muscle, p.density_muscle, p.density_fat)
        mass = np.zeros(V)
        np.add.at(mass, cv, np.repeat(dens * vol / sizes, sizes))
        unused = mass <= 0
        mass[unused] = mass[~unused].min() if np.any(~unused) else 1.0
    # stiffness
    size = np.cbrt(vol)
    if p.stiffness_mode == 'given':
        k = np.where(muscle, p.k_muscle, p.k_fat) * tm.cell_k_scale
    else:
        k = np.where(muscle, p.youngs_muscle, p.youngs_fat) * size * 4.0 / sizes * tm.cell_k_scale
    k_active = np.zeros(C)
    alen = np.zeros(C)
    cell_axial_lengths(np.array(rest), off, cv, alen)          # (writable, as a state's x: one compiled signature)
    lines = centre_lines(tm, off, cv, rest, p.active_path_sigma)      # each muscle's centre line (measures.py)
    if p.active_length == 'path':
        alen = path_lengths(tm, rest, off, cv, alen, p.active_path_sigma, lines=lines)
    if p.specific_tension > 0 and p.min_stretch < 1:
        k_active = active_stiffness(tm, p, vol, alen, sizes)
    # damping: fraction of critical for a vertex of mean mass on one cell spring
    mcell = np.zeros(C)
    np.add.at(mcell, cell_of_k, mass[cv])
    mcell /= sizes
    zeta = np.where(muscle | (p.damping_ratio_fat < 0), p.damping_ratio, p.damping_ratio_fat)
    damp_b = 2.0 * zeta * np.sqrt((k + k_active) * mcell) if p.damping == 'deformation' else np.zeros(C)
    vel_damp = p.velocity_damping
    # volume penalty on the best-fit affine map D = A Qinv: kvol = volume_stiffness * k / sum_i |Qinv X0_i|^2
    # (its stiffness at rest is then volume_stiffness * k); fat cells the same with volume_stiffness_fat
    k_volume, volume_cap = np.zeros(C), np.zeros(C)
    vol_rel = np.where(muscle, p.volume_stiffness, p.volume_stiffness_fat)       # relative volume stiffness per cell
    if np.any(vol_rel > 0):
        g = np.einsum('kij,kj->ki', Qinv[cell_of_k], X0)
        g2 = np.bincount(cell_of_k, weights=np.sum(g * g, axis=1), minlength=C)
        k_volume = np.where(~flat, vol_rel * (k + k_active) / np.maximum(g2, 1e-300), 0.0)
        cap = p.implicit_volume_cap if p.integrator == 'implicit' else p.explicit_volume_cap
        if cap > 0:
            # the volume term's stiffness kvol |grad det D|^2 (vol_rel (k + k_active) at rest, |grad det D|^2 = g2) at most
            # cap x keff's (1 + vol_rel)(k + k_active) (docs/solver.md "The volume term's bound"); the enclosed volume's
            # |grad (V/V0)|^2 is held to the same bound (volume.enclosed_lanes)
            volume_cap = np.where(k_volume > 0, cap * g2 * (1.0 + vol_rel) / np.maximum(vol_rel, 1e-300), 0.0)
    # muscle length weights: cells of a muscle in the same slice gap share one gap length
    lw = np.zeros(C)
    for m in range(tm.n_muscles):
        cells = np.flatnonzero(tm.cell_muscle == m)
        if cells.size:
            _, inv, cnt = np.unique(tm.cell_slice[cells], return_inverse=True, return_counts=True)
            lw[cells] = 1.0 / cnt[inv]
    # skeleton
    S, J = tm.n_segments, tm.n_joints
    seg_parent = np.asarray(tm.segment_parent, np.int32)
    order, seen = [], set()
    root = int(np.flatnonzero(seg_parent == -1)[0])
    stack = [root]
    while stack:
        s = stack.pop(0)
        order.append(s)
        stack.extend(int(c) for c in np.flatnonzero(seg_parent == s))
    if len(order) != S:
        raise ValueError(f'model {tm.name!r}: the segments do not form one tree')
    seg_joint = np.full(S, -1, np.int32)
    for j in range(J):
        seg_joint[tm.joint_child[j]] = j
    if np.any((seg_joint < 0) & (seg_parent >= 0)):
        raise ValueError(f'model {tm.name!r}: a non-root segment has no joint')
    anc = np.zeros((J, S), bool)
    for s in range(S):
        t = s
        while seg_parent[t] >= 0:
            j = seg_joint[t]
            if tm.joint_type[j] == JOINT_HINGE:
                anc[j, s] = True
            t = seg_parent[t]
    seg_mass = np.array(tm.segment_mass, float)
    seg_com = np.array(tm.segment_com, float)
    seg_I = np.array(tm.segment_inertia, float)
    vs = np.asarray(tm.vertex_segment, np.int32)
    att = np.flatnonzero(vs >= 0).astype(np.int32)
    att = att[np.argsort(vs[att], kind='stable')]      # grouped by segment (skeleton_step sums each run)
    if p.attached_mass_to_segment:
        for s in range(S):
            sel = att[vs[att] == s]
            if sel.size == 0:
                continue
            mv, pv = mass[sel], rest[sel]
            mt = seg_mass[s] + mv.sum()
            com = (seg_mass[s] * seg_com[s] + (mv[:, None] * pv).sum(0)) / mt
            d = seg_com[s] - com
            I = seg_I[s] + seg_mass[s] * (d @ d * np.eye(3) - np.outer(d, d))
            r = pv - com
            I += np.einsum('i,ijk->jk', mv, (r * r).sum(1)[:, None, None] * np.eye(3) - r[:, :, None] * r[:, None, :])
            seg_mass[s], seg_com[s], seg_I[s] = mt, com, I
    inv_mass = np.where(vs >= 0, 0.0, 1.0 / mass)
    # volume_measure 'enclosed': the muscle cells' volume energy on their enclosed volume (volume.py), except thin cells
    # (tendons: rest ring radius below volume.THIN_RADIUS) and cells bound to a coupled joint's segment (the patella),
    # which keep the affine measure with fat; under the implicit integrator every cell keeps it (the enclosed energy's
    # stiffness is not in its prefactored system: its force, explicit there, diverged at 1 ms; docs/solver.md "What the
    # volume energy holds")
    k_enc = np.zeros(C)
    if p.volume_measure == 'enclosed' and p.integrator != 'implicit':
        coupled = np.zeros(S + 1, bool)                 # (index S: a free vertex, vertex_segment -1)
        coupled[np.asarray(tm.joint_child)[np.asarray(tm.joint_type) == JOINT_COUPLED]] = True
        on_coupled = np.bincount(np.repeat(np.arange(C), sizes), weights=coupled[vs[cv]], minlength=C) > 0
        k_enc = np.where(muscle & ~on_coupled & (VO.ring_radii(rest, off, cv) >= VO.THIN_RADIUS), k_volume, 0.0)
    # end_ring_pull 'bound': the end rings whose free vertices' share of the tension acts on their bound ones
    ends = CK.end_rings(tm.cell_muscle if p.end_ring_pull == 'bound' else np.full(C, -1), tm.cell_slice, off, cv, vs)
    # summed stiffness and damping of each vertex's cells (the mass_scaled integrator's masses)
    kcell = (k + k_active) * (1.0 + np.where(k_volume > 0, vol_rel, 0.0))
    kappa = np.zeros(V)
    np.add.at(kappa, cv, np.repeat(kcell, sizes))
    bsum = np.zeros(V)
    np.add.at(bsum, cv, np.repeat(damp_b, sizes))
    q_ff = np.einsum('ci,cij,cj->c', fib, Q, fib)
    sim_kw = dict(
        tissue=tm, params=p, n_substeps=1, omega_max=0.0, rest=frozen(rest), inv_mass=frozen(inv_mass),
        mass=frozen(mass), vertex_segment=frozen(vs), vertex_stiffness=frozen(kappa), vertex_damping=frozen(bsum), off=frozen(off), cv=frozen(cv), X0=frozen(X0),
        Qinv=frozen(Qinv), q_tr=frozen(tr), q_ff=frozen(q_ff), rest_length=frozen(alen), fibre=frozen(tm.cell_fibre, np.float64), cell_muscle=frozen(tm.cell_muscle, np.int32),
        k=frozen(k, np.float64), k_active=frozen(k_active), damp_b=frozen(damp_b), rest_volume=frozen(vol), k_volume=frozen(k_volume), volume_cap=frozen(volume_cap), cell_sign=frozen(sign),
        k_enclosed=frozen(k_enc), end_rings=CK.EndRings(*(frozen(a) for a in ends)),
        length_weight=frozen(lw),
        muscle_rest_length=frozen(np.bincount(tm.cell_muscle[tm.cell_muscle >= 0], weights=(lw * alen)[tm.cell_muscle >= 0],
                                               minlength=tm.n_muscles)[:tm.n_muscles]),
        centre_lines=lines,
        free_idx=frozen(np.flatnonzero(vs < 0).astype(np.int32)),
        att_idx=frozen(att), att_seg=frozen(vs[att]),
        **via_points(tm, rest),
        seg_order=frozen(np.array(order, np.int32)), seg_parent=frozen(seg_parent), seg_joint=frozen(seg_joint),
        seg_mass=frozen(seg_mass), seg_com=frozen(seg_com), seg_inertia=frozen(seg_I),
        j_parent=frozen(tm.joint_parent, np.int32), j_child=frozen(tm.joint_child, np.int32),
        j_type=frozen(tm.joint_type, np.uint8), j_axis=frozen(tm.joint_axis, np.float64),
        j_centre=frozen(tm.joint_centre, np.float64), j_rest=frozen(tm.joint_rest, np.float64),
        j_range=frozen(tm.joint_range, np.float64), anc=frozen(anc), gravity=frozen(np.array(p.gravity, float)),
        **coupling_spline(tm, p.joint_paths),
        skeleton=None,
        cell_blocks=CK.pack_cells(off, cv, X0, tm.cell_muscle, k, k_active, damp_b,
                                  np.where(k_enc > 0, 0.0, k_volume), tr, q_ff, alen, fib, Qinv,
                                  volume_cap=volume_cap))
    sim_kw['contact'] = CT.build(tm, p, rest, vs)          # bone signed-distance grids (stage 4; none when off)
    sim_kw['skeleton'] = SK.Skeleton(*(sim_kw[n] for n in SK.Skeleton._fields))
    c_max = float(np.max(bsum * inv_mass)) + p.velocity_damping if V else 0.0
    sim = SimModel(damp_rate=c_max, **sim_kw)
    w = estimate_omega_max(sim)
    n_sub = p.substeps or substeps_for(p, w, c_max, p.dt)
    return dataclasses.replace(sim, n_substeps=int(n_sub), omega_max=float(w))


def coupling_spline(tm: TissueModel, joint_paths: bool = True) -> dict:
    """The paths as the skeleton kernel reads them (j_driver, cp_off, cp_x, cp_c, j_sec): per coupled joint, and per
    hinge with a path when joint_paths (else it is a plain hinge), a cubic spline (scipy CubicSpline, not-a-knot ends)
    through the rows of its table in its coordinate (a coupled joint's driver's, a hinge's own), channels
    (skeleton.CHANNELS) angle about the joint's axis, the two secondary angles, dx, dy, dz; cp_c[i, ch] = coefficients of
    1, t, t^2, t^3 on the interval from knot i (t = coordinate - knot). A coupled joint's table (driver, angle, dx, dy,
    dz) has no secondary angles; a hinge's path (q, angle 2, angle 3, dx, dy, dz) no first angle (it is q - rest)."""
    from scipy.interpolate import CubicSpline
    J = tm.n_joints
    off, knots, coef = [0], [], []
    coff, ctab = np.asarray(tm.coupling_offsets, np.int64), np.asarray(tm.coupling_table, np.float64)
    poff, ptab = np.asarray(tm.joint_path_offsets, np.int64), np.asarray(tm.joint_path_table, np.float64)
    for j in range(J):
        rows = np.zeros((0, 1 + SK.CHANNELS))
        if tm.joint_type[j] == JOINT_COUPLED and coff[j + 1] > coff[j]:
            c = ctab[coff[j]:coff[j + 1]]
            rows = np.zeros((len(c), 1 + SK.CHANNELS))
            rows[:, :2], rows[:, 4:7] = c[:, :2], c[:, 2:5]
        elif tm.joint_type[j] == JOINT_HINGE and joint_paths and poff[j + 1] > poff[j]:
            c = ptab[poff[j]:poff[j + 1]]
            rows = np.zeros((len(c), 1 + SK.CHANNELS))
            rows[:, 0], rows[:, 2:7] = c[:, 0], c[:, 1:6]
        cc = np.zeros((len(rows), SK.CHANNELS, 4))
        if len(rows):
            cs = CubicSpline(rows[:, 0], rows[:, 1:], axis=0)
            cc[:-1] = np.transpose(cs.c[::-1], (1, 2, 0))      # (4, K-1, CH) -> (K-1, CH, power)
        knots.append(rows[:, 0])
        coef.append(cc)
        off.append(off[-1] + len(rows))
    cp_x = np.concatenate(knots) if knots else np.zeros(0)
    cp_c = np.concatenate(coef) if coef else np.zeros((0, SK.CHANNELS, 4))
    sec = np.asarray(tm.joint_path_axes, np.float64).reshape(J, 2, 3)
    return dict(j_driver=frozen(tm.joint_driver, np.int32), cp_off=frozen(np.array(off, np.int64)),
                cp_x=frozen(cp_x.astype(np.float64)), cp_c=frozen(cp_c), j_sec=frozen(sec))


def via_points(tm: TissueModel, rest: np.ndarray) -> dict:
    """The point via rings' arrays of SimModel (via_off, via_idx, via_seg, via_local): each ring's vertices, its segment
    and its rest centroid (a segment's frame is the model frame in the rest pose; integration.hold_via_points)."""
    off, idx = np.asarray(tm.via_point_offsets, np.int64), np.asarray(tm.via_point_vertices, np.int32)
    R = off.size - 1
    local = np.array([rest[idx[off[r]:off[r + 1]]].mean(axis=0) for r in range(R)]).reshape(R, 3)
    return dict(via_off=frozen(off), via_idx=frozen(idx), via_seg=frozen(np.asarray(tm.via_point_segment, np.int32)),
                via_local=frozen(local, np.float64))


def active_stiffness(tm: TissueModel, p: Params, vol: np.ndarray, alen: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """(C,) active spring constant [N/m] per cell at full activation.

    A prism cell of axial length L whose rest shape is shortened to lam L pulls on each end ring
    with n_ring k (1 - lam) L / 2 when held at length L (each ring vertex is displaced (1 - lam) L / 2
    from its target). The cells of a muscle form chains in series, so every slice gap of the
    muscle must carry the same force F: each gap's cells share F in proportion to their cross
    section A_c = V_c / L_c, i.e. k_c = 2 F (A_c / sum A) / (n_ring (1 - lam_min) L_c).
    F = the muscle's max isometric force from the anatomy (Rajagopal's Fmax, itself 60 N/cm^2 x PCSA)
    scaled by specific_tension / 6e5, or specific_tension x the muscle's mean cross section when
    the model has no force. The thin tendon cells then carry the full force instead of limiting it."""
    C = vol.shape[0]
    k_active = np.zeros(C)
    L = np.maximum(alen, 1e-9)
    area = vol / L
    n_ring = sizes / 2
    forces = muscle_max_forces(tm, p, vol, alen)
    for m in range(tm.n_muscles):
        cells = np.flatnonzero(tm.cell_muscle == m)
        if cells.size == 0:
            continue
        _, gap = np.unique(tm.cell_slice[cells], return_inverse=True)
        share = area[cells] / np.bincount(gap, weights=area[cells])[gap]
        k_active[cells] = 2.0 * forces[m] * share / (n_ring[cells] * (1.0 - p.min_stretch) * L[cells])
    return k_active


def path_lengths(tm: TissueModel, x: np.ndarray, off: np.ndarray, cv: np.ndarray, chord_len: np.ndarray,
                 sigma: float, floor: float = 0.5, lines: CentreLines | None = None) -> np.ndarray:
    """(C,) [m] the active tension's rest length of each muscle cell along its muscle's centre line (`active_length: path`):
    the cell's ring-centroid chord projected on the tangent of the muscle's centre line at its slice gap, at least
    ``floor`` x the chord; fat cells and the cells of the slice gaps next to each of a muscle's anchored rings (its
    end rings and via rings) keep ``chord_len`` (the chain's line of pull into its attachment, which the smoothed line
    cuts short). The centre line
    (measures.centre_lines, the one the muscle length is measured along): the mean of each gap's cell centres, slice
    by slice, smoothed with a Gaussian of ``sigma`` [m], differentiated.
    Why: the rings' centroids wander sideways from slice to slice (segmentation, each ring's own polygon), more per
    length the finer the slices; a chain of cells under tension pulls those offsets straight, shortening every cell's
    chord (l / L 0.95 -> 0.92 held isometric, 1x -> 2x) and, with the tension linear in l - lam L, losing force with
    refinement. Measured along the centre line, a cell's length is what its fibres span (docs/solver.md)."""
    C = off.shape[0] - 1
    n = np.diff(off) // 2
    cell_of = np.repeat(np.arange(C), 2 * n)
    top = (np.arange(cv.shape[0]) - np.repeat(off[:-1], 2 * n)) >= np.repeat(n, 2 * n)
    sums = np.zeros((C, 2, 3))
    np.add.at(sums, (cell_of, top.astype(int)), x[cv])
    chord = (sums[:, 1] - sums[:, 0]) / n[:, None]
    lines = lines if lines is not None else centre_lines(tm, off, cv, x, sigma)   # (compile_model's, built at x)
    pts = lines.points(x)
    out = np.array(chord_len, np.float64)
    for m in range(tm.n_muscles):
        cells = np.flatnonzero(tm.cell_muscle == m)
        if cells.size == 0:
            continue
        _, gap = np.unique(tm.cell_slice[cells], return_inverse=True)
        for piece in lines.pieces(m):                       # the gaps between two anchored rings (ends, via rings)
            if piece.size < 3:
                continue                                    # gaps next to an anchored ring only
            tangent = np.gradient(pts[piece], axis=0)       # the smoothed gap points, in gap order
            tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-300)
            first = lines.gap[piece[0]]
            mine = (gap > first) & (gap < first + piece.size - 1)   # the gaps next to an anchored ring keep their
            along = np.abs(np.einsum('ij,ij->i', chord[cells[mine]], tangent[gap[mine] - first]))   # chord: there the
            out[cells[mine]] = np.maximum(along, floor * out[cells[mine]])  # chain turns into its attachment
    return out


def muscle_max_forces(tm: TissueModel, p: Params, vol: np.ndarray, alen: np.ndarray) -> np.ndarray:
    """(M,) [N] each muscle's maximum isometric force F as the physical set uses it (the active tension's calibration,
    the passive force-length's scale): the anatomy's Fmax x specific_tension / 6e5, or specific_tension x the
    muscle's mean cross section (volume / length) when the model has none; 0 with specific_tension 0 (the paper)."""
    forces = np.zeros(tm.n_muscles)
    L = np.maximum(alen, 1e-9)
    for m in range(tm.n_muscles):
        cells = np.flatnonzero(tm.cell_muscle == m)
        if cells.size == 0:
            continue
        fmax = float(tm.muscle_max_force[m]) if np.isfinite(tm.muscle_max_force[m]) else 0.0
        if fmax > 0:
            forces[m] = fmax * p.specific_tension / 6.0e5
        else:   # no force in the model: specific tension x mean cross section (volume / length)
            _, gap = np.unique(tm.cell_slice[cells], return_inverse=True)
            length = float(np.sum(np.bincount(gap, weights=L[cells]) / np.bincount(gap)))
            forces[m] = p.specific_tension * float(np.sum(vol[cells])) / length
    return forces


def substeps_for(p: Params, omega: float, c: float, dt: float) -> int:
    """Sub-steps per step of length dt: params.substeps if set; 1 for the mass_scaled integrator
    (the scaled masses keep omega h below stability_limit); else the explicit stability estimate."""
    if p.substeps:
        return p.substeps
    if p.integrator in ('mass_scaled', 'implicit'):
        return 1
    return stable_substeps(omega, c, dt, p.stability_limit)


def stable_substeps(omega: float, c: float, dt: float, limit: float) -> int:
    """Sub-steps so that symplectic Euler with stiffness omega^2 and damping rate c is stable with
    margin: (omega h)^2 + 2 c h <= limit^2 (the exact bound is 4)."""
    if omega <= 0 and c <= 0:
        return 1
    h = (-c + math.sqrt(c * c + omega * omega * limit * limit)) / (omega * omega) if omega > 0 else limit * limit / (2 * c)
    return max(1, math.ceil(dt / h * (1 - 1e-12)))


def estimate_omega_max(sim: SimModel, iters: int = 40) -> float:
    """Highest natural frequency [rad/s] of the free tissue at rest (power iteration on the force
    kernel linearised by finite differences, every muscle at full activation). Sets the sub-steps."""
    free = sim.inv_mass > 0
    if not np.any(free):
        return 0.0
    rng = np.random.default_rng(0)
    u = rng.standard_normal(sim.rest.shape) * free[:, None]
    f = np.zeros_like(sim.rest)
    quat = np.tile([0.0, 0.0, 0.0, 1.0], (sim.n_cells, 1))
    M = max(sim.n_muscles, 1)
    lam, act = np.ones(M), np.ones(M)
    e = np.zeros(sim.n_cells)
    scale = 1e-6 * max(np.ptp(sim.rest, axis=0).max(), 1e-3)
    par = sim.cell_blocks.par.copy()
    par[:, CK.P_B * CK.BLK:(CK.P_B + 1) * CK.BLK] = 0.0       # no damping
    par.flags.writeable = False                               # read-only as in the model: one compiled kernel
    cells = sim.cell_blocks._replace(par=par)
    work = CK.cell_work(cells)
    lam_est = 0.0
    for _ in range(iters):
        u /= np.linalg.norm(u)
        xp = sim.rest + scale * u
        quat[:] = (0.0, 0.0, 0.0, 1.0)
        CK.cell_forces(xp, xp, f, quat, cells, lam, act, sim.params.volume_mode == 'actual', 20, e,
                      np.zeros(sim.n_cells), 0.0, work, np.empty(sim.n_cells))
        y = -(f / scale) * sim.inv_mass[:, None]
        lam_est = float(np.sum(y * u))
        u = y
    return math.sqrt(max(lam_est, 0.0) * 1.05)


def make_state(sim: SimModel) -> State:
    """The rest state: positions at rest, zero velocities, joints at their rest coordinates."""
    V, C, S, J = sim.n_vertices, sim.n_cells, sim.n_segments, sim.n_joints
    quat = np.zeros((C, 4))
    quat[:, 3] = 1.0
    st = State(x=sim.rest.copy(), v=np.zeros((V, 3)), f=np.zeros((V, 3)), quat=quat, q=sim.j_rest.copy(),
               qd=np.zeros(J), seg_R=np.tile(np.eye(3), (S, 1, 1)), seg_t=np.zeros((S, 3)),
               lam=np.ones(max(sim.n_muscles, 0)), cell_energy=np.zeros(C), pressure=np.zeros(C),
               cell_length=np.zeros(C), muscle_length=np.full(max(sim.n_muscles, 0), -1.0),
               muscle_velocity=np.zeros(max(sim.n_muscles, 0)), joint_lock_torque=np.zeros(J),
               activation=np.zeros(max(sim.n_muscles, 0)), contact_wrench=np.zeros((S, 6)),
               x_back=np.empty((V, 3)), v_back=np.empty((V, 3)), x_prev=np.zeros((V, 3)), v_prev=np.zeros((V, 3)),
               history_h=np.zeros(1))
    SK.coupled_coordinates(st.q, st.qd, sim.skeleton)
    return st


def reset(sim: SimModel, state: State) -> State:
    """Put state back to rest in place (keeps its arrays); returns it."""
    fresh = make_state(sim)
    for f in dataclasses.fields(State):
        a, b = getattr(state, f.name), getattr(fresh, f.name)
        if isinstance(a, np.ndarray) and a.shape == b.shape:
            a[...] = b
        else:
            setattr(state, f.name, b)
    return state


def set_joint_positions(sim: SimModel, state: State, q, qd=None) -> State:
    """Pose the skeleton at joint coordinates q [rad] (and velocities qd), moving bone-attached
    vertices with their segments; free vertices stay where they are. A coupled joint's entry is
    replaced by its driver's spline value (it has no freedom). Returns state."""
    q = np.asarray(q, np.float64)
    if q.shape != (sim.n_joints,) or not np.all(np.isfinite(q)):
        raise ValueError(f'q must be {sim.n_joints} finite joint coordinates')
    state.q[:] = q
    state.qd[:] = 0.0 if qd is None else qd
    SK.coupled_coordinates(state.q, state.qd, sim.skeleton)     # a coupled joint follows its driver
    SK.forward_kinematics(state.q, sim.skeleton, state.seg_R, state.seg_t)
    a, s = sim.att_idx, sim.att_seg
    state.x[a] = np.einsum('aij,aj->ai', state.seg_R[s], sim.rest[a]) + state.seg_t[s]
    state.muscle_length[:] = -1.0        # a jump, not a motion: the force-velocity estimate starts again
    state.muscle_velocity[:] = 0.0
    if state.contact_wrench is not None:
        state.contact_wrench[:] = 0.0    # (the last sub-step's contact reaction belongs to the old pose)
    if state.history_h is not None:
        state.history_h[:] = 0.0         # (BDF2 starts again: the last sub-step is not this pose's past)
    return state


def make_control(sim: SimModel) -> Control:
    return Control(activation=np.zeros(sim.n_muscles), joint_lock=np.zeros(sim.n_joints, bool),
                   joint_target=sim.j_rest.copy())


def muscle_indices(sim: SimModel, name: str) -> list:
    """Indices of a muscle selector (a muscle, a name prefix, a group or 'all'; see core/activation.py);
    KeyError (UnknownMuscle) naming the choices."""
    from tissue_sim.core.activation import Muscles
    return Muscles.of(sim).indices(name)
