"""The picture set of a run: paper-like figures at chosen times, side-by-side panels, an animation.

Files (in ``out``): ``<view>_f<frame>.png`` per chosen frame for each view of
:mod:`~tissue_sim.core.analysis.render` (limb, knee, area, d_paper, d_rotfree), ``<view>_panel.png``
(the chosen frames side by side, like the paper's figure rows) and ``animation.gif`` (or ``.mp4``).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from tissue_sim.core import runio
from tissue_sim.core.analysis import measure, render
from tissue_sim.core.analysis.plots import pick_frames, pick_motion_frames


def frames_at_times(times: np.ndarray, wanted) -> np.ndarray:
    """Indices of the frames nearest to the wanted times [s] (error if outside the run)."""
    out = []
    for w in wanted:
        if w < times[0] - 1e-9 or w > times[-1] + 1e-6:
            raise runio.RunError(f'time {w} s is outside the run ({times[0]:.3f} .. {times[-1]:.3f} s)')
        out.append(int(np.argmin(np.abs(times - w))))
    return np.array(sorted(set(out)), np.int64)


def render_run(run: runio.Run, out, measures: measure.Measurements | None = None, times=None, n_frames: int = 4,
               size=(800, 600), views=render.KINDS, animation: str | None = 'gif', anim_frames: int = 48,
               anim_size=(480, 360), progress=None) -> list[Path]:
    """Render the figure set of a loaded run into ``out``; returns the files written.

    Frames: ``times`` [s], else ``n_frames`` picked by :func:`~tissue_sim.core.analysis.plots.pick_motion_frames`
    (the start, the extremes of the joint that moves most, the end: any motion, knee or ankle); the
    close-up view centres on the joint that turns most (``render.knee_centre``).

    ``measures``: the run's :class:`~tissue_sim.core.analysis.measure.Measurements` when already
    computed (``analyze``); the frames drawn that it lacks (or all, if None) are measured here."""
    import imageio.v3 as iio
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    topo = run.model
    t_all, poses_all, jn, jp_all = run.times, run.segment_poses, run.joint_names, run.joint_positions
    chosen = frames_at_times(t_all, times) if times else pick_motion_frames(t_all, run.joint_positions, n_frames)
    anim = pick_frames(t_all, min(anim_frames, len(t_all))) if animation else np.zeros(0, np.int64)
    need = sorted(set(chosen.tolist()) | set(anim.tolist()) | {0})
    m, row = measure.rows_for(run, set(chosen.tolist()) | {0}, measures)
    area0 = m.skin_area[row[0]]
    vals = {}
    for f in chosen:
        k = row[int(f)]
        with np.errstate(divide='ignore', invalid='ignore'):
            vals[int(f)] = {'area': np.where(area0 > 0, m.skin_area[k] / area0, 1.0), 'd_paper': m.d_paper[k],
                            'd_rotfree': m.d_rotation_free[k]}
    bones_all = [np.concatenate(render.posed_bones(topo, poses_all[f])) for f in need if len(topo.bone_names)]
    pts = np.concatenate([run.frames[need].reshape(-1, 3).astype(np.float64)] + bones_all)
    knee = render.knee_centre(topo, poses_all, topo.rest_positions)
    height = float(np.ptp(pts[:, 2]))
    moving = [j for j in range(len(jn)) if np.ptp(jp_all[:, j]) > np.deg2rad(0.1)] if len(jn) else []

    def label(f):                       # every joint that moves in the run (all of them when none does)
        s = f't = {t_all[f]:.2f} s'
        for j in moving or range(len(jn)):
            s += f'   {jn[j]} {np.rad2deg(jp_all[f, j]):.0f} deg'
        return s

    files = []
    for view in views:
        dmax = None
        if view in ('d_paper', 'd_rotfree'):
            dmax = max(float(max(v[view].max() for v in vals.values())), 1e-6) if vals else 1e-3
        clim = None
        if view == 'area' and vals:
            r = np.concatenate([v['area'][m.skin_area_rest > 0] for v in vals.values()])
            r = r[np.isfinite(r) & (r > 0)]
            lim = float(np.percentile(np.abs(np.log2(r)), 99)) if r.size else 0.0
            clim = 2 ** max(lim, np.log2(1.05))
        vsize = size
        if view != 'knee':                  # tall narrow limbs: narrower pictures (size is the maximum)
            ext = np.ptp(pts, axis=0)
            w = int(min(size[0], max(360, size[1] * 1.3 * ext[0] / max(ext[2], 1e-9) + 220)))
            vsize = (w, size[1])
        rd = render.LimbRenderer(topo, view, size=vsize, clim=clim, d_max=dmax)
        if view == 'knee':
            rd.set_camera(pts, focus=knee, half_height=max(0.18 * height, 0.8 * float(np.ptp(topo.rest_positions[:, 0])), 0.05))
        else:
            rd.set_camera(pts)
        imgs = []
        for f in chosen:
            f = int(f)
            v = vals[f]['area' if view == 'area' else view] if view in ('area', 'd_paper', 'd_rotfree') else None
            rd.update(run.frames[f], poses_all[f], v, label(f))
            img = rd.image()
            p = out / f'{view}_f{int(run.frame_index[f]):05d}.png'
            iio.imwrite(p, img)
            files.append(p)
            imgs.append(img)
            if progress:
                progress()
        rd.close()
        if len(imgs) > 1:
            sep = np.full((imgs[0].shape[0], 6, 3), 255, np.uint8)
            panel = np.concatenate(sum(([im, sep] for im in imgs), [])[:-1], axis=1)
            p = out / f'{view}_panel.png'
            iio.imwrite(p, panel)
            files.append(p)
    if animation and len(anim):
        rd = render.LimbRenderer(topo, 'limb', size=anim_size)
        rd.set_camera(pts)
        imgs = []
        for f in anim:
            f = int(f)
            rd.update(run.frames[f], poses_all[f], None, label(f))
            imgs.append(rd.image())
            if progress:
                progress()
        rd.close()
        span = max(t_all[anim[-1]] - t_all[anim[0]], 1e-6)
        fps = float(np.clip((len(anim) - 1) / span, 4, 30))
        if animation == 'mp4':
            p = out / 'animation.mp4'
            _mp4(p, imgs, fps)
        else:
            p = out / 'animation.gif'
            iio.imwrite(p, np.stack(imgs), duration=1000.0 / fps, loop=0)
        files.append(p)
    return files


def _mp4(path: Path, imgs, fps: float):
    import imageio.v2 as iio2
    with iio2.get_writer(path, fps=fps, codec='libx264', quality=7, macro_block_size=8) as w:
        for im in imgs:
            w.append_data(im)
