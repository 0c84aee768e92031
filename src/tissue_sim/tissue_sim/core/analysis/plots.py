"""Plots of a run's measurements (matplotlib, Agg backend: no display needed).

* ``joint_angles.png``: every joint's angle [deg] over time (the knee in the paper's experiment).
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


def joint_angles(m: Measurements, out: Path) -> Path:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 3.6), dpi=120)
    for j, n in enumerate(m.joint_names):
        ax.plot(m.times, np.rad2deg(m.joint_positions[:, j]), lw=2, label=n)
    ax.set_xlabel('time [s]')
    ax.set_ylabel('joint angle [deg] (knee: + = flexion)')
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
    frames = pick_frames(m.times, 4)
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
