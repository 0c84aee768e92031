"""The skeleton: a tree of rigid segments with hinge, fixed or coupled joints (fixed root), joint-space
dynamics (docs/solver.md "Skeleton"). numba; the model's skeleton arrays come as one ``Skeleton`` named tuple.

A coupled joint (the patellofemoral joint) has no degree of freedom: its child (a leaf segment) is posed
relative to its parent by a cubic spline of its driver hinge's coordinate (``coupled_eval``); its
coordinate q is the spline's angle. Its segment's inertia, gravity and tissue forces enter the driver's
equation through the coupling Jacobian (virtual work), see ``skeleton_step``.

A hinge may have a path (the knee: the source model's walker knee, docs/solver.md "Skeleton"): besides its
rotation q - rest about its axis, its child turns about two more axes and translates by splines of q, as an
OpenSim CustomJoint with one coordinate does. Its child's velocity per unit qd is then W x (x - P) + D with W, P,
D functions of q (``path_frame``, ``joint_motion``) instead of the plain hinge's a x (x - p)."""
from __future__ import annotations

import collections
import math

import numpy as np
from numba import njit

Skeleton = collections.namedtuple('Skeleton', 'seg_order seg_parent seg_joint seg_mass seg_com seg_inertia j_parent '
                                  'j_child j_type j_axis j_centre j_rest j_range anc gravity j_driver cp_off cp_x cp_c '
                                  'j_sec')
# j_driver (J,) int32: driving hinge of a coupled joint (-1 otherwise); cp_off (J+1,) int64: the knots in cp_x of a
# coupled joint or of a hinge with a path (none for a plain hinge); cp_x (N,) coordinates of the knots [rad] (the
# driver's, the hinge's own); cp_c (N, CHANNELS, 4): per knot interval, per channel (angle about j_axis [rad], angle
# about j_sec[j, 0], angle about j_sec[j, 1] [rad], dx, dy, dz [m]) the cubic's coefficients of 1, t, t^2, t^3 with
# t = coordinate - knot (a joint's last row unused); a hinge's angle about j_axis is q - rest (channel 0 unused), a
# coupled joint's secondary angles are 0; j_sec (J, 2, 3): the secondary rotation axes (unit, parent's rest frame)

HINGE = 1
COUPLED = 2
CHANNELS = 6            # spline channels of a path: angle about j_axis, the two secondary angles, dx, dy, dz


@njit(cache=True)
def coupled_eval(j, th, sk, out):
    """The path of joint j (a coupled joint or a hinge with a path) at coordinate th (its driver's, the hinge's own):
    out[ch, 0..2] = value, first and second derivative in th of the channels (CHANNELS: angle about j_axis, the two
    secondary angles [rad], dx, dy, dz [m]); beyond the table a straight line with the end slope."""
    o0, o1 = sk.cp_off[j], sk.cp_off[j + 1]
    x = sk.cp_x
    ext = 0.0
    if th < x[o0]:
        k, t = o0, 0.0
        ext = th - x[o0]
    elif th > x[o1 - 1]:
        k = o1 - 2
        t = x[o1 - 1] - x[k]
        ext = th - x[o1 - 1]
    else:
        k = o0
        while k < o1 - 2 and th >= x[k + 1]:
            k += 1
        t = th - x[k]
    for ch in range(CHANNELS):
        c0, c1, c2, c3 = sk.cp_c[k, ch, 0], sk.cp_c[k, ch, 1], sk.cp_c[k, ch, 2], sk.cp_c[k, ch, 3]
        v = c0 + t * (c1 + t * (c2 + t * c3))
        d1 = c1 + t * (2.0 * c2 + 3.0 * t * c3)
        d2 = 2.0 * c2 + 6.0 * t * c3
        if ext != 0.0:
            v += d1 * ext
            d2 = 0.0
        out[ch, 0] = v
        out[ch, 1] = d1
        out[ch, 2] = d2


@njit(cache=True)
def coupled_coordinates(q, qd, sk):
    """Set each coupled joint's coordinate (its angle) and velocity from its driver's."""
    ev = np.empty((CHANNELS, 3))
    for j in range(q.shape[0]):
        if sk.j_type[j] == COUPLED:
            d = sk.j_driver[j]
            coupled_eval(j, q[d], sk, ev)
            q[j] = ev[0, 0]
            qd[j] = ev[0, 1] * qd[d]


@njit(cache=True)
def axis_angle_mat(ax, ang, R):
    """Rotation by ang [rad] about unit axis ax (Rodrigues), written into R."""
    c, s = math.cos(ang), math.sin(ang)
    t = 1 - c
    x, y, z = ax[0], ax[1], ax[2]
    R[0, 0] = t * x * x + c; R[0, 1] = t * x * y - s * z; R[0, 2] = t * x * z + s * y
    R[1, 0] = t * x * y + s * z; R[1, 1] = t * y * y + c; R[1, 2] = t * y * z - s * x
    R[2, 0] = t * x * z - s * y; R[2, 1] = t * y * z + s * x; R[2, 2] = t * z * z + c


@njit(cache=True)
def has_path(j, sk):
    """True when hinge j has a path (its child turns about secondary axes and translates with its coordinate)."""
    return sk.j_type[j] == HINGE and sk.cp_off[j + 1] > sk.cp_off[j]


@njit(cache=True)
def path_frame(j, th, sk, ev, Rl, w1, w2):
    """Hinge j with a path at its coordinate th: ev (CHANNELS, 3) = its channels (coupled_eval), Rl (3, 3) = its child's
    rotation in the parent's rest frame, Rot(a, th - rest) Rot(b1, phi_1) Rot(b2, phi_2) (a = j_axis, b = j_sec: each
    axis taken in the frame the rotations before it have turned, as an OpenSim CustomJoint's), w1 (3,) = the child's
    angular velocity per unit rate of th and w2 (3,) = dw1/dth, both in the parent's rest frame. The child's point at
    rest X is at Rl (X - c) + c + d (c = j_centre, d = channels 3-5)."""
    coupled_eval(j, th, sk, ev)
    a, b1, b2 = sk.j_axis[j], sk.j_sec[j, 0], sk.j_sec[j, 1]
    R1 = np.empty((3, 3))
    R2 = np.empty((3, 3))
    R3 = np.empty((3, 3))
    axis_angle_mat(a, th - sk.j_rest[j], R1)
    axis_angle_mat(b1, ev[1, 0], R2)
    axis_angle_mat(b2, ev[2, 0], R3)
    R12 = np.empty((3, 3))
    for r in range(3):
        for c in range(3):
            R12[r, c] = R1[r, 0] * R2[0, c] + R1[r, 1] * R2[1, c] + R1[r, 2] * R2[2, c]
    for r in range(3):
        for c in range(3):
            Rl[r, c] = R12[r, 0] * R3[0, c] + R12[r, 1] * R3[1, c] + R12[r, 2] * R3[2, c]
    u2 = np.empty(3)
    u3 = np.empty(3)
    for r in range(3):
        u2[r] = R1[r, 0] * b1[0] + R1[r, 1] * b1[1] + R1[r, 2] * b1[2]
        u3[r] = R12[r, 0] * b2[0] + R12[r, 1] * b2[1] + R12[r, 2] * b2[2]
    f2, f3, g2, g3 = ev[1, 1], ev[2, 1], ev[1, 2], ev[2, 2]
    # w1 = a + u2 phi_1' + u3 phi_2'; w2 = a x u2 phi_1' + u2 phi_1'' + (a + u2 phi_1') x u3 phi_2' + u3 phi_2''
    v = np.empty(3)
    for r in range(3):
        w1[r] = a[r] + u2[r] * f2 + u3[r] * f3
        v[r] = a[r] + u2[r] * f2
    c1 = np.empty(3)
    c2 = np.empty(3)
    _cross(a, u2, c1)
    _cross(v, u3, c2)
    for r in range(3):
        w2[r] = c1[r] * f2 + u2[r] * g2 + c2[r] * f3 + u3[r] * g3


@njit(cache=True)
def joint_motion(j, q, sk, seg_R, seg_t, ev, Rl, w1, w2, out):
    """Joint j's motion at coordinates q and the pose (seg_R, seg_t), per unit rate of its coordinate (a hinge's own,
    a coupled joint's driver's): out[0:3] = its child's angular velocity W, out[3:6] a point P and out[6:9] the
    offset rate D such that a point x of the child moves at W x (x - P) + D, out[9:12] = dW/dq and out[12:15] = dD/dq
    (the velocity-product accelerations' terms), all in the world; a plain hinge (or a fixed joint): (a, p, 0, 0, 0),
    its world axis and centre. ev, Rl, w1, w2: scratch (path_frame's)."""
    p = sk.j_parent[j]
    ax, c = sk.j_axis[j], sk.j_centre[j]
    for r in range(9, 15):
        out[r] = 0.0
    if sk.j_type[j] == COUPLED:
        coupled_eval(j, q[sk.j_driver[j]], sk, ev)
        for r in range(3):
            a = seg_R[p, r, 0] * ax[0] + seg_R[p, r, 1] * ax[1] + seg_R[p, r, 2] * ax[2]
            out[r] = a * ev[0, 1]
            out[9 + r] = a * ev[0, 2]
    elif has_path(j, sk):
        path_frame(j, q[j], sk, ev, Rl, w1, w2)
        for r in range(3):
            out[r] = seg_R[p, r, 0] * w1[0] + seg_R[p, r, 1] * w1[1] + seg_R[p, r, 2] * w1[2]
            out[9 + r] = seg_R[p, r, 0] * w2[0] + seg_R[p, r, 1] * w2[1] + seg_R[p, r, 2] * w2[2]
    else:
        for r in range(3):
            out[r] = seg_R[p, r, 0] * ax[0] + seg_R[p, r, 1] * ax[1] + seg_R[p, r, 2] * ax[2]
            out[3 + r] = seg_R[p, r, 0] * c[0] + seg_R[p, r, 1] * c[1] + seg_R[p, r, 2] * c[2] + seg_t[p, r]
            out[6 + r] = 0.0
        return
    for r in range(3):
        out[3 + r] = (seg_R[p, r, 0] * (c[0] + ev[3, 0]) + seg_R[p, r, 1] * (c[1] + ev[4, 0])
                      + seg_R[p, r, 2] * (c[2] + ev[5, 0]) + seg_t[p, r])
        out[6 + r] = seg_R[p, r, 0] * ev[3, 1] + seg_R[p, r, 1] * ev[4, 1] + seg_R[p, r, 2] * ev[5, 1]
        out[12 + r] = seg_R[p, r, 0] * ev[3, 2] + seg_R[p, r, 1] * ev[4, 2] + seg_R[p, r, 2] * ev[5, 2]


@njit(cache=True)
def forward_kinematics(q, sk, seg_R, seg_t):
    """Pose (R_s, t_s) of every non-root segment from the joint coordinates q; a point p_rest of
    segment s is at R_s p_rest + t_s. Joint j rotates its child by q_j - rest_j about its rest axis
    through its rest centre (a hinge with a path, a coupled joint: by its path's rotations and offset, path_frame),
    then the parent's pose applies. sk.seg_order lists parents first."""
    seg_order, seg_joint, j_parent, j_axis, j_centre, j_rest = sk.seg_order, sk.seg_joint, sk.j_parent, sk.j_axis, sk.j_centre, sk.j_rest
    Rj = np.empty((3, 3))
    ev = np.empty((CHANNELS, 3))
    w1 = np.empty(3)
    w2 = np.empty(3)
    for s in seg_order:
        j = np.int64(seg_joint[s])      # (int64 as the other callers' j: one compiled signature of each callee)
        if j < 0:
            continue
        p = j_parent[j]
        ox = oy = oz = 0.0
        if sk.j_type[j] == COUPLED:       # coupled: angle and offset d from the driver's coordinate
            coupled_eval(j, q[sk.j_driver[j]], sk, ev)
            axis_angle_mat(j_axis[j], ev[0, 0], Rj)
            ox, oy, oz = ev[3, 0], ev[4, 0], ev[5, 0]
        elif has_path(j, sk):             # a hinge with a path: three rotations and an offset from its coordinate
            path_frame(j, q[j], sk, ev, Rj, w1, w2)
            ox, oy, oz = ev[3, 0], ev[4, 0], ev[5, 0]
        else:
            axis_angle_mat(j_axis[j], q[j] - j_rest[j], Rj)
        cx, cy, cz = j_centre[j, 0], j_centre[j, 1], j_centre[j, 2]
        # local transform: x -> Rj (x - c) + c + o ; world: R_p (Rj (x - c) + c + o) + t_p
        lx = cx + ox - (Rj[0, 0] * cx + Rj[0, 1] * cy + Rj[0, 2] * cz)
        ly = cy + oy - (Rj[1, 0] * cx + Rj[1, 1] * cy + Rj[1, 2] * cz)
        lz = cz + oz - (Rj[2, 0] * cx + Rj[2, 1] * cy + Rj[2, 2] * cz)
        for r in range(3):
            for c in range(3):
                seg_R[s, r, c] = seg_R[p, r, 0] * Rj[0, c] + seg_R[p, r, 1] * Rj[1, c] + seg_R[p, r, 2] * Rj[2, c]
            seg_t[s, r] = seg_R[p, r, 0] * lx + seg_R[p, r, 1] * ly + seg_R[p, r, 2] * lz + seg_t[p, r]


@njit(cache=True)
def _cross(a, b, out):
    out[0] = a[1] * b[2] - a[2] * b[1]
    out[1] = a[2] * b[0] - a[0] * b[2]
    out[2] = a[0] * b[1] - a[1] * b[0]


@njit(cache=True)
def skeleton_step(h, q, qd, f, x, sk, att_idx, att_seg, joint_damping, limit_wh, limit_zeta, seg_R, seg_t, work,
                  lock, target, lock_tau, tau_ext, wext):
    """One step of the skeleton (a tree of rigid segments, hinge, fixed or coupled joints, fixed root).

    tau_j = a_j . sum over attached vertices of segments below joint j of (x - p_j) x f (the
    tissue's reaction on the bone), plus tau_ext[j] [N m] (J,): torques given in joint space (the passive fibre force,
    muscle.passive_torques; a coupled joint's entry is not used), plus the wrench wext (S, 6) on each segment (force
    [N], its moment about the world origin [N m]: the contact's reaction, State.contact_wrench). Joint-space mass
    matrix M from segment masses/inertias by Jacobians; bias (Coriolis, centrifugal, gravity) by recursive Newton-Euler with qdd = 0;
    range limits as an implicit stiff, critically damped end stop (no jolt). Symplectic Euler:
    qd += h qdd, q += h qd; then forward kinematics. Returns False if qdd is not finite.

    Joint lock (docs/solver.md "Joint lock"): a hinge j with lock[j] is driven to target[j] within the step
    (its qdd is prescribed so that qd = (target - q) / h and q = target after it: a steady target holds it
    with qd = 0); the other joints move under the lock's reaction. lock_tau[j] [N m] is the torque the lock
    applies about the joint axis (positive about +axis, the direction q grows): tau_lock = M_j. qdd - rhs_j,
    i.e. in a static hold minus the tissue's torque plus the gravity torque on the segments below. 0 for a
    joint not locked. work: (J, 8 + J) scratch.

    A coupled joint (docs/solver.md "Coupled joints") has no equation of its own: its child's tissue wrench,
    Newton-Euler wrench (inertia, gravity) and mass enter its driver's row through the coupling Jacobian;
    after the step its coordinate follows the driver's (coupled_coordinates)."""
    seg_order, seg_parent, seg_joint, seg_mass, seg_com, seg_inertia, j_parent, j_child, j_type, j_axis, j_centre, \
        j_rest, j_range, anc, gravity, j_driver, cp_off, cp_x, cp_c, j_sec = sk
    S = seg_mass.shape[0]
    J = q.shape[0]
    # world axes and centres of the joints, world COM and inertia of the segments (current pose)
    a = work[0:J, 0:3]
    pj = work[0:J, 3:6]
    com = np.empty((S, 3))
    Iw = np.empty((S, 3, 3))
    for j in range(J):
        p = j_parent[j]
        for r in range(3):
            a[j, r] = seg_R[p, r, 0] * j_axis[j, 0] + seg_R[p, r, 1] * j_axis[j, 1] + seg_R[p, r, 2] * j_axis[j, 2]
            pj[j, r] = (seg_R[p, r, 0] * j_centre[j, 0] + seg_R[p, r, 1] * j_centre[j, 1]
                        + seg_R[p, r, 2] * j_centre[j, 2] + seg_t[p, r])
    for s in range(S):
        for r in range(3):
            com[s, r] = seg_R[s, r, 0] * seg_com[s, 0] + seg_R[s, r, 1] * seg_com[s, 1] + seg_R[s, r, 2] * seg_com[s, 2] + seg_t[s, r]
        for r in range(3):
            for c in range(3):
                acc = 0.0
                for k in range(3):
                    for l in range(3):
                        acc += seg_R[s, r, k] * seg_inertia[s, k, l] * seg_R[s, c, l]
                Iw[s, r, c] = acc
    # every joint's motion at the current pose (joint_motion): per unit rate of its coordinate (a coupled joint's
    # driver's) the child's angular velocity W, the point P and offset rate D of its velocity W x (x - P) + D, and
    # their rates A phi'' and R_p d'' for the velocity-product accelerations; jw[j] = (W, P, D): (a, p, 0) for a
    # plain hinge
    cw = np.zeros((J, 15))
    ev = np.empty((CHANNELS, 3))
    Rl = np.empty((3, 3))
    w1 = np.empty(3)
    w2 = np.empty(3)
    pathed = np.zeros(J, np.bool_)
    for j in range(J):
        joint_motion(j, q, sk, seg_R, seg_t, ev, Rl, w1, w2, cw[j])
        pathed[j] = has_path(j, sk)
    jw = cw[:, 0:9]
    # tissue wrench per segment (force, moment about the world origin), summed up the tree
    Fs = np.zeros((S, 3))
    Ns = np.zeros((S, 3))
    # (summed in registers over each run of one segment: compile_model sorts the list by segment)
    k = 0
    while k < att_idx.shape[0]:
        s = att_seg[k]
        f0 = f1 = f2 = n0 = n1 = n2 = 0.0
        while k < att_idx.shape[0] and att_seg[k] == s:
            i = att_idx[k]
            f0 += f[i, 0]; f1 += f[i, 1]; f2 += f[i, 2]
            n0 += x[i, 1] * f[i, 2] - x[i, 2] * f[i, 1]
            n1 += x[i, 2] * f[i, 0] - x[i, 0] * f[i, 2]
            n2 += x[i, 0] * f[i, 1] - x[i, 1] * f[i, 0]
            k += 1
        Fs[s, 0] += f0; Fs[s, 1] += f1; Fs[s, 2] += f2
        Ns[s, 0] += n0; Ns[s, 1] += n1; Ns[s, 2] += n2
    for s in range(S):
        for r in range(3):
            Fs[s, r] += wext[s, r]
            Ns[s, r] += wext[s, 3 + r]
    # recursive Newton-Euler, qdd = 0, base acceleration -g (gravity), forward pass
    w = np.zeros((S, 3))
    al = np.zeros((S, 3))
    acom = np.zeros((S, 3))
    tmp = np.empty(3)
    tmp2 = np.empty(3)
    vk = np.empty(3)
    d = np.empty(3)
    acc_p = np.empty(3)
    Iwv = np.empty(3)
    Ial = np.empty(3)
    for s in seg_order:
        j = seg_joint[s]
        if j < 0:
            for r in range(3):
                acom[s, r] = -gravity[r]
            continue
        p = j_parent[j]
        if j_type[j] == COUPLED or pathed[j]:
            # w = w_p + W qd, alpha = alpha_p + w_p x W qd + A phi'' qd^2; COM: the parent's material point there,
            # + 2 w_p x v_rel + a_rel (v_rel = (W x r + D) qd, a_rel = (A phi'' x r + W x (W x r) + R_p d'') qd^2)
            th = qd[j_driver[j]] if j_type[j] == COUPLED else qd[j]
            for r in range(3):
                tmp[r] = cw[j, r] * th                                # W qd
                w[s, r] = w[p, r] + tmp[r]
            _cross(w[p], tmp, tmp2)
            for r in range(3):
                al[s, r] = al[p, r] + tmp2[r] + cw[j, 9 + r] * th * th
                d[r] = com[s, r] - com[p, r]
            _cross(al[p], d, tmp); _cross(w[p], d, tmp2)
            for r in range(3):
                acc_p[r] = acom[p, r] + tmp[r]
            _cross(w[p], tmp2, tmp)
            for r in range(3):
                acc_p[r] += tmp[r]
                d[r] = com[s, r] - cw[j, 3 + r]                       # r = com - P
            _cross(cw[j, 0:3], d, tmp)                                # W x r
            for r in range(3):
                vk[r] = (tmp[r] + cw[j, 6 + r]) * th                  # v_rel
            _cross(w[p], vk, tmp2)
            for r in range(3):
                acc_p[r] += 2.0 * tmp2[r]
            _cross(cw[j, 0:3], tmp, tmp2)                             # W x (W x r)
            _cross(cw[j, 9:12], d, tmp)                               # A phi'' x r
            for r in range(3):
                acom[s, r] = acc_p[r] + (tmp[r] + tmp2[r] + cw[j, 12 + r]) * th * th
            continue
        wq = qd[j] if j_type[j] == 1 else 0.0
        for r in range(3):
            w[s, r] = w[p, r] + a[j, r] * wq
        # alpha_s = alpha_p + w_p x (a_j qd_j)
        _cross(w[p], a[j], tmp)
        for r in range(3):
            al[s, r] = al[p, r] + tmp[r] * wq
        # acceleration of the joint point on the parent, then of the child's COM
        for r in range(3):
            d[r] = pj[j, r] - com[p, r]
        _cross(al[p], d, tmp); _cross(w[p], d, tmp2)
        for r in range(3):
            acc_p[r] = acom[p, r] + tmp[r]
        _cross(w[p], tmp2, tmp)
        for r in range(3):
            acc_p[r] += tmp[r]
            d[r] = com[s, r] - pj[j, r]
        _cross(al[s], d, tmp); _cross(w[s], d, tmp2)
        for r in range(3):
            acom[s, r] = acc_p[r] + tmp[r]
        _cross(w[s], tmp2, tmp)
        for r in range(3):
            acom[s, r] += tmp[r]
    # backward pass: wrench (force, moment about the world origin) each subtree needs
    Fb = np.zeros((S, 3))
    Nb = np.zeros((S, 3))
    for kk in range(seg_order.shape[0] - 1, -1, -1):
        s = seg_order[kk]
        for r in range(3):
            Fb[s, r] += seg_mass[s] * acom[s, r]
        for r in range(3):
            Iwv[r] = Iw[s, r, 0] * w[s, 0] + Iw[s, r, 1] * w[s, 1] + Iw[s, r, 2] * w[s, 2]
            Ial[r] = Iw[s, r, 0] * al[s, 0] + Iw[s, r, 1] * al[s, 1] + Iw[s, r, 2] * al[s, 2]
        _cross(w[s], Iwv, tmp)
        for r in range(3):
            tmp2[r] = seg_mass[s] * acom[s, r]
        _cross(com[s], tmp2, Iwv)
        for r in range(3):
            Nb[s, r] += Ial[r] + tmp[r] + Iwv[r]
        ps = seg_parent[s]
        if ps >= 0:
            for r in range(3):
                Fb[ps, r] += Fb[s, r]; Nb[ps, r] += Nb[s, r]
                Fs[ps, r] += Fs[s, r]; Ns[ps, r] += Ns[s, r]
    # joint-space equations M qdd = tau - bias
    M = work[0:J, 6:6 + J]
    rhs = work[0:J, 6 + J]
    for j in range(J):
        c = j_child[j]
        # moment about P_j: W . (N - P_j x F) + D . F (a plain hinge: a . (N - p_j x F))
        _cross(jw[j, 3:6], Fs[c], tmp)
        _cross(jw[j, 3:6], Fb[c], tmp2)
        tau = 0.0
        bias = 0.0
        for r in range(3):
            tau += jw[j, r] * (Ns[c, r] - tmp[r]) + jw[j, 6 + r] * Fs[c, r]
            bias += jw[j, r] * (Nb[c, r] - tmp2[r]) + jw[j, 6 + r] * Fb[c, r]
        rhs[j] = tau + tau_ext[j] - bias - joint_damping * qd[j]   # viscous joint damping, implicit (M += h c below)
        for k in range(J):
            acc = 0.0
            for s in range(S):
                if anc[j, s] and anc[k, s]:
                    for r in range(3):
                        d0 = com[s, r] - jw[j, 3 + r]
                        tmp[r] = d0
                    _cross(jw[j, 0:3], tmp, tmp2)      # J_v column of j at COM of s: W x (com - P) + D
                    for r in range(3):
                        tmp2[r] += jw[j, 6 + r]
                        tmp[r] = com[s, r] - jw[k, 3 + r]
                    _cross(jw[k, 0:3], tmp, vk)
                    for r in range(3):
                        vk[r] += jw[k, 6 + r]
                    acc += seg_mass[s] * (tmp2[0] * vk[0] + tmp2[1] * vk[1] + tmp2[2] * vk[2])
                    for r in range(3):
                        acc += jw[j, r] * (Iw[s, r, 0] * jw[k, 0] + Iw[s, r, 1] * jw[k, 1] + Iw[s, r, 2] * jw[k, 2])
            M[j, k] = acc
    # coupled joints: the child's tissue wrench, inertia and gravity on the driver d by virtual work:
    # tau_d += W . (N - P x F) + D . F (tissue), bias likewise; M: the coupling column J_d += (W x (com - P) + D, W)
    for j in range(J):
        if j_type[j] != COUPLED:
            continue
        c = j_child[j]
        dr = j_driver[j]
        tau = 0.0
        bias = 0.0
        _cross(cw[j, 3:6], Fs[c], tmp)
        _cross(cw[j, 3:6], Fb[c], tmp2)
        for r in range(3):
            tau += cw[j, r] * (Ns[c, r] - tmp[r]) + cw[j, 6 + r] * Fs[c, r]
            bias += cw[j, r] * (Nb[c, r] - tmp2[r]) + cw[j, 6 + r] * Fb[c, r]
        rhs[dr] += tau - bias
        for r in range(3):
            d[r] = com[c, r] - cw[j, 3 + r]
        _cross(cw[j, 0:3], d, tmp)
        for r in range(3):
            tmp[r] += cw[j, 6 + r]                                    # V: velocity of the COM per unit qd_d
            Iwv[r] = Iw[c, r, 0] * cw[j, 0] + Iw[c, r, 1] * cw[j, 1] + Iw[c, r, 2] * cw[j, 2]   # I W
        acc = 0.0
        for r in range(3):
            acc += seg_mass[c] * tmp[r] * tmp[r] + cw[j, r] * Iwv[r]
        M[dr, dr] += acc
        for k in range(J):                                            # cross terms with the hinges that move c
            if not anc[k, c]:
                continue
            for r in range(3):
                d[r] = com[c, r] - jw[k, 3 + r]
            _cross(jw[k, 0:3], d, vk)
            acc = 0.0
            for r in range(3):
                acc += seg_mass[c] * tmp[r] * (vk[r] + jw[k, 6 + r]) + Iwv[r] * jw[k, r]
            M[dr, k] += acc
            M[k, dr] += acc
    # --- joint lock (begin): save the locked rows (the lock torque is M_j. qdd - rhs_j), prescribe their qdd
    n_lock = 0
    for j in range(J):
        lock_tau[j] = 0.0
        if lock[j] and j_type[j] == 1:
            n_lock += 1
    if n_lock > 0:
        row = np.empty((J, J + 1))
        for j in range(J):
            if lock[j] and j_type[j] == 1:
                for k in range(J):
                    row[j, k] = M[j, k]
                row[j, J] = rhs[j]
        for j in range(J):
            if lock[j] and j_type[j] == 1:
                qddl = ((target[j] - q[j]) / h - qd[j]) / h
                for k in range(J):
                    if k != j:
                        rhs[k] -= M[k, j] * qddl
                        M[k, j] = 0.0
                        M[j, k] = 0.0
                M[j, j] = 1.0
                rhs[j] = qddl
    # --- joint lock (end)
    for j in range(J):
        if lock[j] and j_type[j] == 1:           # locked: prescribed above (no damping, no end stop)
            continue
        if j_type[j] != 1:                       # fixed joint: no motion
            for k in range(J):
                M[j, k] = 0.0
                M[k, j] = 0.0
            M[j, j] = 1.0
            rhs[j] = 0.0
            continue
        # end stop: implicit spring-damper on the predicted coordinate (stiffness from the joint's inertia)
        mjj = M[j, j]
        M[j, j] += h * joint_damping
        wl = limit_wh / h
        kl = mjj * wl * wl
        bl = 2.0 * limit_zeta * mjj * wl
        qp = q[j] + h * qd[j]
        pen = 0.0
        if qp > j_range[j, 1]:
            pen = qp - j_range[j, 1]
        elif qp < j_range[j, 0]:
            pen = qp - j_range[j, 0]
        if pen != 0.0:
            M[j, j] += h * h * kl + h * bl
            rhs[j] += -kl * pen - bl * qd[j]
    # solve (Gaussian elimination with partial pivoting; J is small)
    qdd = work[0:J, 7 + J]
    for i in range(J):
        piv = i
        for r in range(i + 1, J):
            if abs(M[r, i]) > abs(M[piv, i]):
                piv = r
        if piv != i:
            for c in range(J):
                t_ = M[i, c]; M[i, c] = M[piv, c]; M[piv, c] = t_
            t_ = rhs[i]; rhs[i] = rhs[piv]; rhs[piv] = t_
        for r in range(i + 1, J):
            fac = M[r, i] / M[i, i]
            for c in range(i, J):
                M[r, c] -= fac * M[i, c]
            rhs[r] -= fac * rhs[i]
    for i in range(J - 1, -1, -1):
        acc = rhs[i]
        for c in range(i + 1, J):
            acc -= M[i, c] * qdd[c]
        qdd[i] = acc / M[i, i]
    for j in range(J):
        if not math.isfinite(qdd[j]):
            return False
    for j in range(J):
        if j_type[j] == 1:
            qd[j] += h * qdd[j]
            q[j] += h * qd[j]
    if n_lock > 0:                               # --- joint lock (begin): its torque; the coordinate exactly on target
        for j in range(J):
            if lock[j] and j_type[j] == 1:
                acc = -row[j, J]
                for k in range(J):
                    acc += row[j, k] * qdd[k]
                lock_tau[j] = acc
                q[j] = target[j]
    # --- joint lock (end)
    coupled_coordinates(q, qd, sk)
    forward_kinematics(q, sk, seg_R, seg_t)
    return True


def joint_jacobians(q, sk, seg_R, seg_t):
    """(W, P, D), each (J, 3), in the world at the pose (seg_R, seg_t) of coordinates q: the velocity of a point x of
    joint j's child per unit rate of its coordinate (a hinge's own; a coupled joint's driver's, j_driver) is
    W[j] x (x - P[j]) + D[j], its angular velocity W[j] (joint_motion, as skeleton_step uses it; a plain hinge: its
    world axis, centre and 0). For measures (measures.joint_torques, skeleton_energy)."""
    J = len(q)
    out = np.zeros((J, 15))
    ev, Rl, w1, w2 = np.empty((CHANNELS, 3)), np.empty((3, 3)), np.empty(3), np.empty(3)
    for j in range(J):
        joint_motion(j, np.asarray(q, np.float64), sk, seg_R, seg_t, ev, Rl, w1, w2, out[j])
    return out[:, 0:3], out[:, 3:6], out[:, 6:9]
