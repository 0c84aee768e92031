"""Headless pictures of a run like the paper's figures (pyvista/VTK offscreen; no display, no GPU).

Views (``kind``):

* ``limb`` (paper Fig. 6): the whole limb from the side, bones opaque ivory, muscles in red/brown
  shades (hamstrings bright red), fat/skin translucent yellow.
* ``knee`` (paper Fig. 7): the same, close up on the knee.
* ``area`` (paper Fig. 8): each fat cell's skin face coloured by its area relative to frame 0:
  white = unchanged, blue = grown, red = shrunk (log scale, symmetric).
* ``d_paper`` / ``d_rotfree`` (paper Fig. 9): fat deformation degree d per cell, white (0) -> red.

The camera looks along +y from the -y side (the lateral side of a right limb): x (forward) points
right on the picture, z up; parallel projection, one camera for all frames of a figure so they
compare. VTK uses an EGL (GPU-less capable) or OSMesa offscreen window; depth peeling stays off
(translucent meshes vanish with it on some offscreen drivers).
"""
from __future__ import annotations

import os

import numpy as np

from tissue_sim.core import measures
from tissue_sim.core.model import TISSUE_FAT
from tissue_sim.core.tissue_cdr import quat_to_matrix

IVORY = (0.93, 0.90, 0.80)
FAT_YELLOW = (1.0, 0.80, 0.20)
HAMSTRING_RED = (0.85, 0.08, 0.08)
_FLAT = dict(ambient=0.55, diffuse=0.5, specular=0.0)
_BAR = dict(color='black', n_labels=5, vertical=True, position_x=0.86, position_y=0.12, height=0.7, width=0.06,
            title_font_size=14, label_font_size=12)
KINDS = ('limb', 'knee', 'area', 'd_paper', 'd_rotfree')


def _pv():
    os.environ.setdefault('VTK_DEFAULT_OPENGL_WINDOW', 'vtkEGLRenderWindow')
    import pyvista as pv
    pv.OFF_SCREEN = True
    return pv


# ----------------------------------------------------------------------------- geometry
def posed_bones(topo, poses: np.ndarray) -> list[np.ndarray]:
    """Vertices of every bone at the given segment poses (S, 7) [m]."""
    out = []
    R = quat_to_matrix(poses[:, 3:7]) if len(poses) else np.zeros((0, 3, 3))
    for b in range(len(topo.bone_names)):
        v, _ = topo.bone_mesh(b)
        s = int(topo.bone_segment[b])
        if 0 <= s < len(poses):
            v = v.astype(np.float64) @ R[s].T + poses[s, :3]
        out.append(np.asarray(v, np.float64))
    return out


def muscle_colour(name: str, group: str, k: int) -> tuple:
    if group == 'hamstrings':
        return HAMSTRING_RED
    shades = [(0.62, 0.22, 0.18), (0.70, 0.30, 0.22), (0.55, 0.18, 0.16), (0.75, 0.38, 0.30), (0.60, 0.28, 0.25)]
    return shades[k % len(shades)]


def knee_centre(topo, poses: np.ndarray, X0: np.ndarray) -> np.ndarray:
    """Estimate of the knee centre at rest [m].

    The child segment whose pose relative to its parent turns most over the frames is the knee's;
    its centre is the point that moves the same way with both (least squares over the frames),
    regularised towards the gap between the two segments' bones (or the mesh centre).
    """
    X0 = np.asarray(X0, np.float64)
    guess = X0.mean(axis=0) if X0.size else np.zeros(3)
    parents = np.asarray(topo.segment_parent)
    if poses.ndim != 3 or poses.shape[1] == 0 or len(parents) < 2:
        return guess
    R = quat_to_matrix(poses[..., 3:7])                     # (F, S, 3, 3)
    best, child = -1.0, -1
    for s, p in enumerate(parents):
        if p < 0:
            continue
        rel = np.einsum('fji,fjk->fik', R[:, p], R[:, s])
        ang = np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1))
        rng_ = float(np.ptp(ang))
        if rng_ > best:
            best, child = rng_, s
    if child < 0:
        return guess
    p = parents[child]
    bp = [topo.bone_mesh(b)[0] for b in range(len(topo.bone_names)) if topo.bone_segment[b] == p]
    bc = [topo.bone_mesh(b)[0] for b in range(len(topo.bone_names)) if topo.bone_segment[b] == child]
    if bp and bc:
        from scipy.spatial import cKDTree
        A, B = np.concatenate(bp).astype(float), np.concatenate(bc).astype(float)
        dist, idx = cKDTree(A).query(B)
        i = int(np.argmin(dist))
        guess = 0.5 * (A[idx[i]] + B[i])
    if best < np.deg2rad(2):
        return guess
    M = (R[:, child] - R[:, p]).reshape(-1, 3)
    b = (poses[:, p, :3] - poses[:, child, :3]).reshape(-1)
    lam = 1e-3 * max(len(b), 1)
    A = np.vstack([M, np.sqrt(lam) * np.eye(3)])
    rhs = np.concatenate([b, np.sqrt(lam) * guess])
    return np.linalg.lstsq(A, rhs, rcond=None)[0]


def _faces(tri: np.ndarray) -> np.ndarray:
    n = tri.shape[1]
    return np.hstack([np.full((len(tri), 1), n, np.int64), tri]).ravel()


# ----------------------------------------------------------------------------- renderer
class LimbRenderer:
    """One offscreen plotter per view kind; meshes updated in place per frame (fast animations)."""

    def __init__(self, topo, kind: str = 'limb', size=(800, 600), fat_opacity: float = 0.28,
                 clim=None, d_max: float | None = None):
        if kind not in KINDS:
            raise ValueError(f'unknown view {kind!r}; choose from {", ".join(KINDS)}')
        pv = _pv()
        self.pv, self.topo, self.kind = pv, topo, kind
        self.size = tuple(int(v) for v in size)
        self.pl = pv.Plotter(off_screen=True, window_size=self.size)
        self.pl.set_background('white')
        self.meshes = []            # (polydata, kind, index)
        rest = np.asarray(topo.rest_positions, np.float64)
        groups = measures.surface_groups(topo)
        if kind in ('limb', 'knee'):
            for b in range(len(topo.bone_names)):
                v, t = topo.bone_mesh(b)
                if len(t) == 0:
                    continue
                pd = pv.PolyData(np.asarray(v, np.float64), _faces(np.asarray(t, np.int64)))
                self.pl.add_mesh(pd, color=IVORY, smooth_shading=True, specular=0.2, render=False)
                self.meshes.append((pd, 'bone', b))
            mnames = list(topo.muscle_names)
            for name, tri in groups.items():
                if not name.startswith('muscle/'):
                    continue
                mn = name.split('/', 1)[1]
                k = mnames.index(mn) if mn in mnames else 0
                grp = topo.muscle_groups[k] if mn in mnames else ''
                pd = pv.PolyData(rest.copy(), _faces(tri))
                self.pl.add_mesh(pd, color=muscle_colour(mn, grp, k), smooth_shading=True, render=False)
                self.meshes.append((pd, 'soft', None))
            for name, tri in groups.items():
                if name.startswith('muscle/'):
                    continue
                pd = pv.PolyData(rest.copy(), _faces(tri))
                self.pl.add_mesh(pd, color=FAT_YELLOW, opacity=fat_opacity, smooth_shading=True, render=False)
                self.meshes.append((pd, 'soft', None))
        else:
            quads = np.asarray(topo.skin_quads, np.int64)
            fat_ids, _ = measures.cells_of(topo.cell_offsets, topo.cell_vertices, topo.cell_tissue, TISSUE_FAT)
            local = np.full(topo.n_cells, -1, np.int64)
            local[fat_ids] = np.arange(fat_ids.size)
            self.quad_local = local[np.asarray(topo.skin_quad_cell, np.int64)]
            ok = self.quad_local >= 0
            self.quad_local = self.quad_local[ok]
            pd = pv.PolyData(rest.copy(), _faces(quads[ok]))
            pd.cell_data['value'] = np.zeros(int(ok.sum()))
            if kind == 'area':
                lim = np.log2(clim) if clim else np.log2(1.3)
                title = 'log2 area\nvs frame 0\nblue grown\nred shrunk'
                self.pl.add_mesh(pd, scalars='value', cmap='bwr_r', clim=(-lim, lim), show_edges=True,
                                 edge_color=(0.5, 0.5, 0.5), line_width=0.3, render=False, **_FLAT,
                                 scalar_bar_args=dict(title=title, fmt='%.2f', **_BAR))
            else:
                dm = (d_max or 1e-3) * 1000
                title = 'fat d [mm]\n(paper eq. 2)' if kind == 'd_paper' else 'fat d [mm]\n(rotation-free)'
                self.pl.add_mesh(pd, scalars='value', cmap='Reds', clim=(0, dm), show_edges=True,
                                 edge_color=(0.5, 0.5, 0.5), line_width=0.3, render=False, **_FLAT,
                                 scalar_bar_args=dict(title=title, fmt='%.1f', **_BAR))
            self.meshes.append((pd, 'soft', None))
            self.skin_pd = pd
        self.text = None

    def set_camera(self, bounds_points: np.ndarray, focus: np.ndarray | None = None, half_height: float | None = None):
        """Side view (camera on -y looking +y, z up), parallel projection fitting the points or a focus box."""
        P = np.asarray(bounds_points, np.float64)
        lo, hi = P.min(axis=0), P.max(axis=0)
        c = 0.5 * (lo + hi) if focus is None else np.asarray(focus, np.float64)
        aspect = self.size[0] / self.size[1]
        if half_height is None:
            half_height = 0.55 * max(hi[2] - lo[2], (hi[0] - lo[0]) / aspect, 1e-3)
        dist = 10 * max(np.ptp(P, axis=0).max(), 0.1)
        cam = self.pl.camera
        cam.focal_point = tuple(c)
        cam.position = (c[0], c[1] - dist, c[2])
        cam.up = (0.0, 0.0, 1.0)
        self.pl.enable_parallel_projection()
        cam.parallel_scale = half_height
        self.pl.reset_camera_clipping_range()

    def update(self, X: np.ndarray, poses: np.ndarray, values: np.ndarray | None = None, label: str = ''):
        X = np.asarray(X, np.float64)
        bones = posed_bones(self.topo, poses) if any(k == 'bone' for _, k, _ in self.meshes) else []
        for pd, k, b in self.meshes:
            if k == 'bone':
                pd.points = bones[b]
            else:
                pd.points = X
        if values is not None and self.kind not in ('limb', 'knee'):
            v = np.asarray(values, np.float64)[self.quad_local]
            if self.kind == 'area':
                with np.errstate(divide='ignore', invalid='ignore'):
                    v = np.log2(v)
                v = np.nan_to_num(v)
            else:
                v = v * 1000
            self.skin_pd.cell_data['value'] = v
        if self.text is not None:          # (render=False: the screenshot renders the frame once)
            self.pl.remove_actor(self.text, render=False)
        self.text = (self.pl.add_text(label, position='upper_left', font_size=11, color='black', render=False)
                     if label else None)

    def image(self) -> np.ndarray:
        """(H, W, 3) uint8."""
        self.pl.reset_camera_clipping_range()
        self.pl.render()                   # (the one render of the frame: screenshot reads the last one)
        return self.pl.screenshot(return_img=True)

    def close(self):
        self.pl.close()
