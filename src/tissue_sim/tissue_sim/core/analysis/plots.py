"""Plots of a run's measurements (matplotlib, Agg backend: no display needed).

* ``joint_angles.png``: every joint's angle [deg] over time (knee + = flexion, ankle + = dorsiflexion),
  the frames the pictures draw marked.
* ``muscles.png``: muscle length and volume relative to frame 0 over time (hamstrings highlighted),
  with activations.
* ``fat_d_distribution.png``: the distribution of d over the fat cells at a few frames, the paper's
  definition beside the rotation-free one, and the skin-area ratio distribution.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from tissue_sim.core.analysis.measure import Measurements


def _plt():
    import matplotlib
    matplotlib.use('Agg', force=True)
    import matplotlib.pyplot as plt
    return plt


def pick_frames(times: np.ndarray, n: int = 4) -> np.ndarray:
    """n frame positions evenly spread in time from the first to the last frame (unique, sorted)."""
    if len(times) == 0:
        return np.zeros(0, np.int64)
    targets = np.linspace(times[0], times[-1], n)
    return np.unique(np.searchsorted(times, targets - 1e-9).clip(0, len(times) - 1))


def main_joint(joint_positions: np.ndarray):
    """Index of the joint that moves most over a run (largest range of its angle), or None when no
    joint moves (by more than 0.1 deg): the joint a motion is about (knee flexion: the knee; heel raise:
    the ankle)."""
    q = np.asarray(joint_positions, np.float64)
    if q.ndim != 2 or q.shape[0] == 0 or q.shape[1] == 0:
        return None
    rng = np.ptp(q, axis=0)
    j = int(np.argmax(rng))
    return j if rng[j] > np.deg2rad(0.1) else None


def pick_motion_frames(times: np.ndarray, joint_positions: np.ndarray, n: int = 4) -> np.ndarray:
    """n frame positions for the Fig. 8-9 style maps of any motion: the first frame, the extremes of
    the main joint (:func:`main_joint`: its largest and smallest angle, the one farther from the start
    first), the last frame, then frames evenly spread in time to fill n (each the farthest in time from
    those already chosen). Without a moving joint: :func:`pick_frames`. Sorted, unique."""
    F = len(times)
    if F == 0 or n < 1:
        return np.zeros(0, np.int64)
    j = main_joint(joint_positions)
    if j is None:
        return pick_frames(times, n)
    q = np.asarray(joint_positions)[:, j]
    ext = sorted({int(np.argmax(q)), int(np.argmin(q))}, key=lambda f: -abs(q[f] - q[0]))
    chosen = []
    for f in ext + [0, F - 1]:
        if f not in chosen and len(chosen) < n:
            chosen.append(f)
    rest = [int(f) for f in pick_frames(times, max(4 * n, 8)) if int(f) not in chosen]
    while len(chosen) < n and rest:
        gap = [min(abs(times[f] - times[c]) for c in chosen) for f in rest]
        chosen.append(rest.pop(int(np.argmax(gap))))
    return np.array(sorted(chosen), np.int64)


def joint_angles(m: Measurements, out: Path) -> Path:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 3.6), dpi=120)
    for j, n in enumerate(m.joint_names):
        ax.plot(m.times, np.rad2deg(m.joint_positions[:, j]), lw=2, label=n)
    for f in pick_motion_frames(m.times, m.joint_positions, 4) if m.joint_names else ():
        ax.axvline(m.times[f], color='0.5', lw=0.8, ls=':')
    ax.set_xlabel('time [s] (dotted: the frames the pictures draw)')
    ax.set_ylabel('joint angle [deg]\n(knee + = flexion, ankle + = dorsiflexion)')
    ax.set_title(f'Joint angles - {m.model_name}')
    ax.grid(alpha=0.3)
    if m.joint_names:
        ax.legend()
    fig.tight_layout()
    p = Path(out) / 'joint_angles.png'
    fig.savefig(p)
    plt.close(fig)
    return p


def muscles(m: Measurements, out: Path) -> Path:
    plt = _plt()
    fig, axs = plt.subplots(3, 1, figsize=(8, 8), dpi=110, sharex=True)
    with np.errstate(all='ignore'):
        lr = m.muscle_lengths / m.muscle_lengths[:1]
        vr = m.muscle_volumes / m.muscle_volumes[:1]
    ham = np.array([g == 'hamstrings' for g in m.muscle_groups], bool)
    cmap = plt.get_cmap('tab10')
    for k, n in enumerate(m.muscle_names):
        hi = ham[k] or len(m.muscle_names) <= 6
        kw = dict(lw=2.0, label=n, color=cmap(k % 10)) if hi else dict(lw=0.7, color='0.6', alpha=0.7)
        axs[0].plot(m.times, lr[:, k], **kw)
        axs[1].plot(m.times, (vr[:, k] - 1) * 100, **kw)
        axs[2].plot(m.times, m.activations[:, k], **kw)
    axs[0].set_ylabel('length / length at frame 0')
    axs[1].set_ylabel('volume change [%]')
    axs[2].set_ylabel('activation')
    axs[2].set_xlabel('time [s]')
    axs[0].set_title('Muscles' + (' (hamstrings coloured, others grey)' if ham.any() and len(m.muscle_names) > 6 else ''))
    for a in axs:
        a.grid(alpha=0.3)
    if len(m.muscle_names):
        axs[0].legend(fontsize=7, ncol=2)
    fig.tight_layout()
    p = Path(out) / 'muscles.png'
    fig.savefig(p)
    plt.close(fig)
    return p


def d_distribution(m: Measurements, out: Path) -> Path:
    plt = _plt()
    fig, axs = plt.subplots(1, 3, figsize=(13, 3.8), dpi=110)
    frames = pick_motion_frames(m.times, m.joint_positions, 4)
    cmap = plt.get_cmap('viridis')
    dmax = max(float(np.nanmax(m.d_paper)) if m.d_paper.size else 0.0, 1e-9) * 1000
    bins = np.linspace(0, dmax, 40)
    ar = m.area_ratio('frame0')
    for i, f in enumerate(frames):
        c = cmap(i / max(len(frames) - 1, 1))
        lab = f't = {m.times[f]:.2f} s'
        axs[0].hist(m.d_paper[f] * 1000, bins=bins, histtype='step', lw=1.8, color=c, label=lab)
        axs[1].hist(m.d_rotation_free[f] * 1000, bins=bins, histtype='step', lw=1.8, color=c, label=lab)
        a = ar[f][np.isfinite(ar[f])]
        if a.size:
            axs[2].hist(a, bins=40, histtype='step', lw=1.8, color=c, label=lab)
    axs[0].set_title('fat d, paper eq. (2) (rotation included)')
    axs[1].set_title('fat d, rotation-free (matched rest shape)')
    axs[2].set_title('skin area ratio vs frame 0')
    axs[0].set_xlabel('d [mm]')
    axs[1].set_xlabel('d [mm]')
    axs[2].set_xlabel('area / area at frame 0')
    for a in axs:
        a.set_ylabel('fat cells')
        a.grid(alpha=0.3)
        a.legend(fontsize=7)
    fig.tight_layout()
    p = Path(out) / 'fat_d_distribution.png'
    fig.savefig(p)
    plt.close(fig)
    return p


def all_plots(m: Measurements, out: Path) -> list[Path]:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    return [joint_angles(m, out), muscles(m, out), d_distribution(m, out)]
