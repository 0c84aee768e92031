#!/usr/bin/env python3
"""Pictures of the bundled limb for docs/anatomy.md (matplotlib slices, pyvista 3D view).

    python tools/anatomy/pictures.py [--data DIR] [--out docs/img]
"""
from __future__ import annotations

import argparse
import os
from pathlib import Path

import matplotlib

matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402
import nibabel as nib  # noqa: E402
import numpy as np  # noqa: E402
import yaml  # noqa: E402
from matplotlib.colors import ListedColormap  # noqa: E402
from matplotlib.patches import Patch  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]


def colours(table):
    cmap = plt.get_cmap('tab20')
    cmap2 = plt.get_cmap('tab20b')
    lut = np.ones((256, 3))
    i = 0
    for lbl, t in sorted(table.items()):
        if t['tissue'] == 'bone':
            lut[lbl] = (0.93, 0.91, 0.82)
        elif t['tissue'] == 'fat':
            lut[lbl] = (1.0, 0.85, 0.45)
        else:
            lut[lbl] = (cmap if i < 20 else cmap2)(i % 20)[:3]
            i += 1
    lut[0] = (1, 1, 1)
    return lut


def slices_figure(lab, affine, table, out):
    lut = colours(table)
    S = affine[2, 3] + affine[2, 2] * np.arange(lab.shape[2])
    picks = [('hip (top of stack)', S.max() - 5), ('mid-thigh', -200.0), ('knee', -410.0), ('mid-shank', -620.0)]
    fig, axes = plt.subplots(1, 4, figsize=(16, 5.2))
    used = set()
    for ax, (title, s) in zip(axes, picks):
        k = int(np.argmin(np.abs(S - s)))
        sl = lab[:, :, k]
        used |= set(np.unique(sl).tolist())
        # display: anterior up, patient's right on the left of the image (radiological: viewed from below)
        img = lut[sl.T[::-1, :]]
        ext = [affine[0, 3], affine[0, 3] + lab.shape[0], affine[1, 3], affine[1, 3] + lab.shape[1]]
        ax.imshow(img, extent=ext, interpolation='nearest')
        ax.set_title(f'{title}: S = {S[k]:.1f} mm')
        ax.set_xlabel('R (mm)')
        ax.set_ylabel('A (mm)')
    handles = [Patch(color=lut[lbl], label=table[lbl]['name']) for lbl in sorted(used) if lbl in table]
    fig.legend(handles=handles, loc='lower center', ncol=8, fontsize=7, frameon=False)
    fig.tight_layout(rect=(0, 0.16, 1, 1))
    fig.savefig(out, dpi=110)
    plt.close(fig)


def coronal_figure(lab, affine, table, out):
    lut = colours(table)
    fig, axes = plt.subplots(1, 2, figsize=(9, 10))
    hip_i = int(round(-affine[0, 3]))
    hip_j = int(round(-affine[1, 3]))
    ext_c = [affine[0, 3], affine[0, 3] + lab.shape[0], affine[2, 3], affine[2, 3] + affine[2, 2] * lab.shape[2]]
    ext_s = [affine[1, 3], affine[1, 3] + lab.shape[1], affine[2, 3], affine[2, 3] + affine[2, 2] * lab.shape[2]]
    j = min(max(hip_j - 10, 0), lab.shape[1] - 1)
    axes[0].imshow(lut[lab[:, j, :].T[::-1]], extent=ext_c, aspect='auto', interpolation='nearest')
    axes[0].set_title(f'coronal, A = {affine[1, 3] + j:.0f} mm')
    axes[0].set_xlabel('R (mm)')
    axes[0].set_ylabel('S (mm)')
    i = min(max(hip_i, 0), lab.shape[0] - 1)
    axes[1].imshow(lut[lab[i, :, :].T[::-1]], extent=ext_s, aspect='auto', interpolation='nearest')
    axes[1].set_title(f'sagittal, R = {affine[0, 3] + i:.0f} mm')
    axes[1].set_xlabel('A (mm)')
    fig.tight_layout()
    fig.savefig(out, dpi=90)
    plt.close(fig)


def view3d(data, lab, affine, table, out):
    os.environ.setdefault('VTK_DEFAULT_OPENGL_WINDOW', 'vtkEGLRenderWindow')
    import pyvista as pv
    from skimage import measure

    lut = colours(table)
    pl = pv.Plotter(off_screen=True, window_size=(800, 1300))
    for lbl, t in sorted(table.items()):
        if t['tissue'] == 'bone':
            mesh = pv.read(str(data / t['mesh']))
            mesh.points = np.c_[-mesh.points[:, 1], mesh.points[:, 0], mesh.points[:, 2]] * 1000.0
            pl.add_mesh(mesh, color=lut[lbl], smooth_shading=True)
        elif t['tissue'] == 'muscle':
            m = np.pad(lab == lbl, 1)
            if m.sum() < 10:
                continue
            v, f, _, _ = measure.marching_cubes(m.astype(np.float32), 0.5, step_size=2)
            v = (v - 1) @ np.diag(np.diag(affine)[:3]) + affine[:3, 3]
            faces = np.c_[np.full(len(f), 3), f].ravel()
            pl.add_mesh(pv.PolyData(v, faces).smooth(n_iter=30), color=lut[lbl], opacity=1.0,
                        smooth_shading=True)
    pl.set_background('white')
    pl.view_vector((1.0, 1.6, 0.35), viewup=(0, 0, 1))   # from antero-lateral, slightly above
    pl.reset_camera()
    pl.camera.zoom(1.5)
    pl.screenshot(str(out))
    pl.close()


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument('--data', type=Path, default=ROOT / 'src/tissue_sim/tissue_sim/data/lower_limb')
    ap.add_argument('--out', type=Path, default=ROOT / 'docs/img')
    ap.add_argument('--no-3d', action='store_true')
    a = ap.parse_args(argv)
    a.out.mkdir(parents=True, exist_ok=True)
    img = nib.load(a.data / 'labels.nii.gz')
    lab = np.asarray(img.dataobj)
    table = yaml.safe_load(open(a.data / 'tissues.yaml'))['labels']
    slices_figure(lab, img.affine, table, a.out / 'anatomy_slices.png')
    coronal_figure(lab, img.affine, table, a.out / 'anatomy_coronal.png')
    if not a.no_3d:
        view3d(a.data, lab, img.affine, table, a.out / 'anatomy_3d.png')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
