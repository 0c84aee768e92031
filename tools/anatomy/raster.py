"""Slice closed triangle meshes with planes and fill the cross-sections on a pixel grid.

Pure numpy: a plane cuts each triangle that straddles it in one segment; the segments of a
closed surface form closed loops, filled by the even-odd rule along pixel rows (crossing
parity, half-open at pixel centres).  Meshes that are not perfectly closed are filled along
rows and along columns and the two results intersected, which removes the streaks a gap
leaves in one direction.
"""
from __future__ import annotations

import numpy as np


def plane_segments(tri, normal, offset):
    """Segments where the plane normal . p = offset cuts triangles tri (m, 3, 3).

    Returns (n, 2, 3) segment end points (the plane's intersections with two triangle edges).
    """
    s = tri @ np.asarray(normal, float) - offset
    s = np.where(s == 0.0, 1e-12, s)  # a vertex exactly on the plane counts as above it
    pos = s > 0
    cross = pos.any(1) & ~pos.all(1)
    tri, s, pos = tri[cross], s[cross], pos[cross]
    # the odd vertex out (alone on its side) is the apex of both cut edges
    odd = np.where(pos.sum(1) == 1, np.argmax(pos, 1), np.argmax(~pos, 1))
    idx = np.arange(len(tri))
    a = tri[idx, odd]
    sa = s[idx, odd]
    out = []
    for k in (1, 2):
        o = (odd + k) % 3
        b = tri[idx, o]
        sb = s[idx, o]
        t = sa / (sa - sb)
        out.append(a + t[:, None] * (b - a))
    return np.stack(out, 1)


def _parity_fill(seg2, shape):
    """Even-odd fill of 2D segments (n, 2, 2) given in pixel coordinates (row, col)."""
    H, W = shape
    cnt = np.zeros((H, W + 1), np.int32)
    r0, c0 = seg2[:, 0, 0], seg2[:, 0, 1]
    r1, c1 = seg2[:, 1, 0], seg2[:, 1, 1]
    lo = np.minimum(r0, r1)
    hi = np.maximum(r0, r1)
    first = np.ceil(lo).astype(int)
    last = np.ceil(hi).astype(int) - 1  # rows j with lo <= j < hi
    n = np.maximum(last - first + 1, 0)
    if n.sum() == 0:
        return np.zeros(shape, bool)
    sid = np.repeat(np.arange(len(seg2)), n)
    j = np.repeat(first, n) + (np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n))
    dr = r1[sid] - r0[sid]
    c = c0[sid] + (j - r0[sid]) * (c1[sid] - c0[sid]) / dr
    ok = (j >= 0) & (j < H)
    j, c = j[ok], c[ok]
    col = np.clip(np.ceil(c).astype(int), 0, W)
    np.add.at(cnt, (j, col), 1)
    return (np.cumsum(cnt, 1)[:, :W] % 2).astype(bool)


def fill_segments(seg2, shape, robust=False):
    """Fill the loops formed by 2D segments (n, 2, 2) in pixel coordinates (row, col)."""
    rows = _parity_fill(seg2, shape)
    if not robust:
        return rows
    cols = _parity_fill(seg2[:, :, ::-1], shape[::-1]).T
    return rows & cols
