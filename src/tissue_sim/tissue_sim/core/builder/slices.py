"""Per-slice extraction: muscle/bone regions -> ray polygons, fat rays, bone pixels for attachment.

All coordinates returned are model frame metres (REP-103: x anterior, y left, z superior).
"""
from __future__ import annotations

import dataclasses

import numpy as np
from scipy import ndimage

from . import contours, rays
from .io import voxel_to_model


@dataclasses.dataclass
class Region:
    """One connected component of one label on one slice."""
    label: int
    bbox: tuple            # (slice_i, slice_j) in full-slice pixel indices
    mask: np.ndarray       # bool crop (the component only)
    area_mm2: float        # label area (pixel count x pixel area)
    origin_kind: str = ''
    ring: np.ndarray | None = None     # (n, 3) model-frame polygon vertices, CCW from +z
    poly_area_mm2: float = 0.0
    fine: np.ndarray | None = None     # contour sections: (FINE n, 2) outline, model xy [m], CCW
    small: bool = False                # below min_area_mm2 (kept only to bridge a muscle's gap)

    def overlap(self, other: 'Region') -> int:
        si = (max(self.bbox[0].start, other.bbox[0].start), min(self.bbox[0].stop, other.bbox[0].stop))
        sj = (max(self.bbox[1].start, other.bbox[1].start), min(self.bbox[1].stop, other.bbox[1].stop))
        if si[0] >= si[1] or sj[0] >= sj[1]:
            return 0
        a = self.mask[si[0] - self.bbox[0].start:si[1] - self.bbox[0].start, sj[0] - self.bbox[1].start:sj[1] - self.bbox[1].start]
        b = other.mask[si[0] - other.bbox[0].start:si[1] - other.bbox[0].start, sj[0] - other.bbox[1].start:sj[1] - other.bbox[1].start]
        return int(np.count_nonzero(a & b))

    def centroid_px(self) -> np.ndarray:
        ij = np.argwhere(self.mask).mean(axis=0)
        return ij + [self.bbox[0].start, self.bbox[1].start]


@dataclasses.dataclass
class SliceGeom:
    k: int
    z: float                       # [m]
    lin: np.ndarray                # (2, 2) voxel (i, j) -> model (x, y) metres
    off: np.ndarray                # (2,) model xy of voxel (0, 0) on this slice

    def to_model(self, ij: np.ndarray) -> np.ndarray:
        xy = np.asarray(ij, float) @ self.lin.T + self.off
        return np.concatenate([xy, np.full(xy.shape[:-1] + (1,), self.z)], axis=-1)

    def to_pixel(self, xy: np.ndarray) -> np.ndarray:
        return (np.asarray(xy, float)[..., :2] - self.off) @ np.linalg.inv(self.lin).T


def slice_geom(affine: np.ndarray, k: int) -> SliceGeom:
    o = voxel_to_model(affine, np.array([0.0, 0.0, float(k)]))
    ei = voxel_to_model(affine, np.array([1.0, 0.0, float(k)])) - o
    ej = voxel_to_model(affine, np.array([0.0, 1.0, float(k)])) - o
    lin = np.array([[ei[0], ej[0]], [ei[1], ej[1]]])
    return SliceGeom(k=k, z=float(o[2]), lin=lin, off=o[:2])


def _pad_bbox(bb, shape, pad=2):
    return tuple(slice(max(s.start - pad, 0), min(s.stop + pad, n)) for s, n in zip(bb, shape))


def muscle_regions(sl: np.ndarray, geom: SliceGeom, labels: list[int], n_rays: int, min_area_mm2: float,
                   ray_hit: str, angle_offset: float, origin_mode: str = 'best', sections: str = 'contour'):
    """Cross-section polygons of every component of every muscle label on one slice.

    ``sections``: 'contour' (the traced outline resampled by arc length; the ring's start index is
    chosen later along each chain, docs/builder.md) or 'rays' (the paper's half-lines). A contour
    region whose outline gives no simple polygon falls back to rays (``origin_kind`` says so).
    Returns ({label: [Region, ...] (largest first)}, dropped, small) where dropped lists
    (label, area_mm2, reason) for components below ``min_area_mm2`` or without a valid polygon,
    and small = {label: Region} the largest dropped small component of a label that has no kept
    component on this slice (used to bridge a thin tendon between two slices of its muscle).
    """
    px_area = abs(np.linalg.det(geom.lin)) * 1e6                 # mm^2 per pixel
    objs = ndimage.find_objects(sl)
    dirs = rays.pixel_directions(rays.ray_angles(n_rays, angle_offset), geom.lin)
    u = np.stack([np.cos(rays.ray_angles(n_rays, angle_offset)), np.sin(rays.ray_angles(n_rays, angle_offset))], 1)
    out, dropped, small = {}, [], {}
    for lab in labels:
        if lab > len(objs) or objs[lab - 1] is None:
            continue
        bb = _pad_bbox(objs[lab - 1], sl.shape)
        crop = sl[bb] == lab
        comp, ncomp = ndimage.label(crop)
        sizes = np.bincount(comp.ravel())[1:]
        cobjs = ndimage.find_objects(comp)
        regs = []
        for rank, ci in enumerate(np.argsort(-sizes)):
            area = float(sizes[ci]) * px_area
            is_small = area < min_area_mm2
            if is_small:
                dropped.append((lab, area, f'component below {min_area_mm2:g} mm^2'))
                if rank > 0 or sizes[ci] < 2:
                    continue
            sub = _pad_bbox(cobjs[ci], comp.shape)
            mm = comp[sub] == ci + 1
            full_bb = (slice(bb[0].start + sub[0].start, bb[0].start + sub[0].stop),
                       slice(bb[1].start + sub[1].start, bb[1].start + sub[1].stop))
            reg = Region(lab, full_bb, mm, area, small=is_small)
            if sections == 'contour':
                reg.fine = contours.region_fine(mm, (full_bb[0].start, full_bb[1].start), geom.lin, geom.off, n_rays)
                r2 = None
                if reg.fine is not None:
                    r2, _ = contours.best_ring(reg.fine, n_rays, None, None)    # provisional: chosen along the chain
                if r2 is not None:
                    # the outline is the outer boundary: a region enclosing a hole (another tissue)
                    # keeps its area on the ring, not its hole (reported)
                    hole = rays.polygon_area(reg.fine) * 1e6 > 1.1 * area
                    reg.origin_kind = 'contour (encloses a hole)' if hole else 'contour'
                    reg.ring = np.concatenate([r2, np.full((n_rays, 1), geom.z)], axis=1)
                    reg.poly_area_mm2 = rays.polygon_area(r2) * 1e6
                    (small.__setitem__(lab, reg) if is_small else regs.append(reg))
                    continue
                reg.fine = None                       # not representable as a simple contour ring: rays
            if origin_mode == 'best':
                origin, reg.origin_kind, d = rays.best_origin(mm, dirs, ray_hit, px_area_m2=px_area * 1e-6)
            else:
                origin, reg.origin_kind = rays.ray_origin(mm)
                d = rays.cast(mm.astype(np.float64), origin, dirs, ray_hit)
            if not np.all(np.isfinite(d)) or np.min(d) <= 0:
                dropped.append((lab, area, 'no polygon (ray casting failed)'))
                continue
            o_model = geom.to_model(origin + [full_bb[0].start, full_bb[1].start])
            ring = np.empty((n_rays, 3))
            ring[:, :2] = o_model[:2] + d[:, None] * u
            ring[:, 2] = geom.z
            reg.ring = ring
            reg.poly_area_mm2 = rays.polygon_area(ring[:, :2]) * 1e6
            if sections == 'contour':
                reg.origin_kind = 'rays (no simple contour ring)'
            (small.__setitem__(lab, reg) if is_small else regs.append(reg))
        if regs:
            out[lab] = regs
            small.pop(lab, None)
    return out, dropped, small


def fat_rays(sl: np.ndarray, geom: SliceGeom, bone_labels: list[int], fat_labels: list[int], n_rays: int,
             min_thickness_m: float, angle_offset: float, core: float = 0.05) -> dict:
    """Fat tube rays of one slice (paper section 2.3): from the centroid of the bone region(s), the
    outer (skin) point is the farthest exit from the body, the inner point the farthest exit from
    the non-fat tissue (muscle, bone); inner is kept at least ``min_thickness_m`` inside outer and
    at least ``core`` x the ray's length out from the origin (rays that miss the non-fat tissue)."""
    body = sl > 0
    bb = _pad_bbox(ndimage.find_objects(body.astype(np.int8))[0], sl.shape, 3)
    crop = sl[bb]
    bodyc = crop > 0
    bone = np.isin(crop, bone_labels)
    fat = np.isin(crop, fat_labels)
    origin = np.argwhere(bone if bone.any() else bodyc).mean(axis=0)
    ang = rays.ray_angles(n_rays, angle_offset)
    dirs = rays.pixel_directions(ang, geom.lin)
    u = np.stack([np.cos(ang), np.sin(ang)], 1)
    outer = rays.cast(bodyc.astype(np.float64), origin, dirs, 'last')
    inner = rays.cast((bodyc & ~fat).astype(np.float64), origin, dirs, 'last')
    inner = np.where(np.isfinite(inner), inner, 0.0)
    outer = np.where(np.isfinite(outer), outer, min_thickness_m)
    inner = np.clip(inner, core * outer, np.maximum(outer - min_thickness_m, core * outer))
    o_model = geom.to_model(origin + [bb[0].start, bb[1].start])
    def pts(d):
        p = np.empty((n_rays, 3))
        p[:, :2] = o_model[:2] + d[:, None] * u
        p[:, 2] = geom.z
        return p
    return {'origin': o_model, 'inner': pts(inner), 'outer': pts(outer), 'has_bone': bool(bone.any()),
            'fat_area_mm2': float(np.count_nonzero(fat)) * abs(np.linalg.det(geom.lin)) * 1e6}


def fat_contours(sl: np.ndarray, geom: SliceGeom, bone_labels: list[int], fat_labels: list[int], n: int) -> dict | None:
    """Fat tube outlines of one slice (``sections: contour``): the fine skin outline and the fine
    outline of the fat layer's inner face (contours.fat_outlines); the rings are chosen along the
    stack by the assembler. None when the body has no traceable outline."""
    px_mm = float(np.sqrt(abs(np.linalg.det(geom.lin)))) * 1000.0
    f = contours.fat_outlines(sl, geom.lin, geom.off, px_mm, bone_labels, fat_labels, n)
    if f is None:
        return None
    fat = np.isin(sl, fat_labels)
    f.update(has_bone=bool(np.isin(sl, bone_labels).any()),
             fat_area_mm2=float(np.count_nonzero(fat)) * abs(np.linalg.det(geom.lin)) * 1e6, z=geom.z)
    return f


def bone_pixels(sl: np.ndarray, geom: SliceGeom, bone_labels: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """Model-frame xy [m] of the centres of all bone pixels on a slice, and their labels."""
    m = np.isin(sl, bone_labels)
    ij = np.argwhere(m)
    return geom.to_model(ij)[:, :2], sl[m]
