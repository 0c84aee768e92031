"""Cross-sections that follow the label outline (``sections: contour``; docs/builder.md "Contour sections").

A region's outline is the 0.5 iso-line of its mask (``skimage.measure.find_contours``, the curve the
ray sections also use), mapped to model-frame metres through the slice's affine and oriented
counter-clockwise seen from +z. It is resampled by arc length to ``FINE`` points per ring vertex; a
ring is every ``FINE``-th of them from a start index chosen per chain so that corresponding
vertices of neighbouring slices lie as close as possible after the two centroids are aligned
(least twist and shear). Each ring is then offset along its vertex normals until its area is the
region's target area (the chord polygon of a convex outline loses area, of a concave one gains).
With the builder setting ``fat_follow`` the fat tube's rings are placed vertex by vertex instead, each vertex near its
predecessor on the slice below (``follow_ring``, ``pair_inner`` with ``prev``; docs/builder.md "Fat tube").
"""
from __future__ import annotations

import numpy as np
from numba import njit
from scipy import ndimage
from skimage import measure

from .rays import polygon_area

FINE = 8                 # fine outline samples per ring vertex (start-index resolution 1/FINE of a vertex step)
INNER_FLOOR = 0.5        # pair_inner: least spacing of the fat layer's inner vertices, x the even spacing
ANGLE_MIN_GAP = 0.02     # fat_rings: the pairing by angle is kept where its inner points are at least this x the even
                         # spacing apart (the bundled limb's foot ring: 0.024); closer, pair_inner replaces it
INNER_NEAR = 0.1         # pair_inner: weight of the pairing lengths against the spacing's evenness
FOLLOW_NEAR = 0.5        # follow_ring, pair_inner(prev=): weight of a vertex's squared distance from its predecessor on
                         # the slice below (in even spacings) against the spacing's evenness (builder setting fat_follow)


def outline_px(mask: np.ndarray) -> np.ndarray | None:
    """Outer boundary (0.5 iso-line) of a 2-D mask in pixel (i, j) coordinates of ``mask``, closed
    polygon without the repeated point; the longest closed contour (holes are left out)."""
    cs = measure.find_contours(np.pad(mask.astype(np.float64), 1), 0.5)
    cs = [c for c in cs if len(c) >= 4 and np.allclose(c[0], c[-1])]
    if not cs:
        return None
    c = max(cs, key=lambda c: abs(polygon_area(c)))
    return c[:-1] - 1.0


def to_model_ccw(px: np.ndarray, lin: np.ndarray, off: np.ndarray) -> np.ndarray:
    """Pixel (i, j) outline -> model xy [m], counter-clockwise seen from +z."""
    xy = px @ lin.T + off
    return xy if polygon_area(xy) > 0 else xy[::-1].copy()


def resample(xy: np.ndarray, m: int) -> np.ndarray:
    """m points evenly spaced by arc length along the closed polygon xy, starting at xy[0]."""
    p = np.vstack([xy, xy[:1]])
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    t = np.arange(m) * s[-1] / m
    return np.stack([np.interp(t, s, p[:, 0]), np.interp(t, s, p[:, 1])], axis=1)


def ring_at(fine: np.ndarray, start: int, n: int) -> np.ndarray:
    m = len(fine)
    return fine[(start + (m // n) * np.arange(n)) % m]


def _candidates(fine: np.ndarray, n: int) -> np.ndarray:
    """(m, n, 2): the ring for every start index of the fine outline."""
    m = len(fine)
    return fine[(np.arange(m)[:, None] + (m // n) * np.arange(n)[None, :]) % m]


def start_costs(fine: np.ndarray, n: int, ref: np.ndarray, centred: bool = True) -> np.ndarray:
    """Sum of squared distances between each candidate ring and ``ref`` (n, 2), per start index;
    with ``centred`` both are taken about their own centroids (twist and shear only, not the
    translation of the region)."""
    R = _candidates(fine, n)
    if centred:
        R = R - R.mean(axis=1, keepdims=True)
        ref = ref - ref.mean(axis=0)
    return np.sum((R - ref[None]) ** 2, axis=(1, 2))


def anterior_start(fine: np.ndarray, n: int) -> int:
    """Start index whose point lies most nearly along +x (anterior) from the outline's centroid:
    vertex 0 of the first ring of a chain points the way ray 0 does."""
    c = fine.mean(axis=0)
    d = fine - c
    ang = np.abs(np.arctan2(d[:, 1], d[:, 0]))
    return int(np.argmin(ang + 1e-9 * np.arange(len(fine))))


def gaps(ring: np.ndarray) -> np.ndarray:
    """Edge lengths of a closed ring (n, 2): |ring[i + 1] - ring[i]|."""
    return np.linalg.norm(np.roll(ring, -1, axis=0) - ring, axis=1)


def polygon_perimeter(xy: np.ndarray) -> float:
    return float(gaps(xy).sum())


@njit(cache=True, inline='always')
def _tri2s(ax, ay, bx, by, cx, cy):
    """Twice the signed area of the triangle (a, b, c) from its coordinates (also on arrays: _tri2)."""
    return (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)


def _tri2(a, b, c):
    """Twice the signed area of triangles (a, b, c) (arrays of xy, broadcast): _tri2s on the coordinates."""
    return _tri2s.py_func(a[..., 0], a[..., 1], b[..., 0], b[..., 1], c[..., 0], c[..., 1])


def is_simple(xy: np.ndarray) -> bool:
    """True when the closed polygon has no two non-adjacent edges that intersect."""
    n = len(xy)
    a, b = xy, xy[np.r_[1:n, 0]]
    i, j = np.triu_indices(n, 2)
    keep = ~((i == 0) & (j == n - 1))
    i, j = i[keep], j[keep]
    d1 = _tri2(a[i], b[i], a[j]); d2 = _tri2(a[i], b[i], b[j])
    d3 = _tri2(a[j], b[j], a[i]); d4 = _tri2(a[j], b[j], b[i])
    return not np.any((d1 * d2 < 0) & (d3 * d4 < 0))


def match_area(ring: np.ndarray, target: float, iters: int = 4) -> np.ndarray:
    """Offset a counter-clockwise ring along its vertex (mitre) normals until its area is ``target``
    [m^2]; returns the ring unchanged when the offset would make it self-intersect."""
    r = ring.copy()
    nxt, prv = np.r_[1:len(r), 0], np.r_[len(r) - 1, 0:len(r) - 1]
    for _ in range(iters):
        a = polygon_area(r)
        e = r[nxt] - r                                         # edge i: r[i] -> r[i+1]
        L = np.linalg.norm(e, axis=1)
        if a <= 0 or np.any(L <= 0):
            return ring
        nrm = np.stack([e[:, 1], -e[:, 0]], 1) / L[:, None]     # outward normal of edge i (CCW)
        n1, n2 = nrm[prv], nrm                                   # edges before / after vertex i
        mitre = (n1 + n2) / np.maximum(1.0 + np.sum(n1 * n2, axis=1), 0.5)[:, None]
        delta = (target - a) / L.sum()
        if abs(target - a) <= 1e-4 * target:
            break
        r = r + delta * mitre
    return r if is_simple(r) and polygon_area(r) > 0 else ring


def best_ring(fine: np.ndarray, n: int, ref: np.ndarray | None, target: float | None, centred: bool = True):
    """The ring of ``n`` vertices on the fine outline: start index by least (centred) squared
    distance to ``ref`` (the ring below in the chain; None: anterior start), the first simple
    candidate in order of cost; area matched to ``target``. Returns (ring (n, 2), start) or
    (None, -1) when no start gives a simple polygon."""
    if ref is None:
        s0 = anterior_start(fine, n)
        order = np.argsort(np.abs(((np.arange(len(fine)) - s0 + len(fine) // 2) % len(fine)) - len(fine) // 2), kind='stable')
    else:
        order = np.argsort(start_costs(fine, n, ref, centred), kind='stable')
    for s in order[:len(fine) // n + 1]:
        r = ring_at(fine, int(s), n)
        if is_simple(r) and polygon_area(r) > 0:
            return (match_area(r, target) if target else r), int(s)
    return None, -1


def region_fine(mask: np.ndarray, origin_px, lin, off, n: int) -> np.ndarray | None:
    """Fine outline (FINE * n points, model xy [m], CCW) of one region mask whose pixel (0, 0) is
    full-slice pixel ``origin_px``."""
    o = outline_px(mask)
    if o is None or len(o) < 3:
        return None
    xy = to_model_ccw(o + np.asarray(origin_px, float), lin, off)
    return resample(xy, FINE * n)


def fat_outlines(sl: np.ndarray, lin, off, px_mm: float, bone_labels, fat_labels, n: int, close_mm: float = 4.0):
    """Fine outer (skin) and inner (subcutaneous fat's inner face) outlines of one slice, model xy
    [m], CCW, and the areas [m^2] they should enclose.

    Skin: the outer boundary of the body's largest component. Inner face: the outer boundary of the
    non-fat tissue (muscles, bones), closed over gaps narrower than ``2 close_mm`` and with holes
    (intermuscular fat) filled, largest component. Returns None when a boundary cannot be traced."""
    body = sl > 0
    objs = ndimage.find_objects(body.astype(np.int8))
    if not objs or objs[0] is None:
        return None
    r = max(1, int(round(close_mm / px_mm)))
    bb = tuple(slice(max(s.start - r - 2, 0), min(s.stop + r + 2, N)) for s, N in zip(objs[0], sl.shape))
    crop = sl[bb]
    bodyc = crop > 0
    lab, nl = ndimage.label(bodyc)
    if nl > 1:
        bodyc = lab == (np.argmax(np.bincount(lab.ravel())[1:]) + 1)
    bodyc = ndimage.binary_fill_holes(bodyc)
    inner = bodyc & ~np.isin(crop, fat_labels)
    if inner.any():
        # closing with a disk of radius r, by distance transforms (dilate, then erode)
        p = np.pad(inner, r + 1)
        dil = ndimage.distance_transform_edt(~p) <= r
        inner = (ndimage.distance_transform_edt(dil) > r)[r + 1:-r - 1, r + 1:-r - 1]
        inner = ndimage.binary_fill_holes(inner) & bodyc
        lab, nl = ndimage.label(inner)
        if nl > 1:
            inner = lab == (np.argmax(np.bincount(lab.ravel())[1:]) + 1)
    org = np.array([bb[0].start, bb[1].start], float)
    px_area = abs(np.linalg.det(lin))
    outer_f = region_fine(bodyc, org, lin, off, n)
    inner_f = region_fine(inner, org, lin, off, n) if inner.any() else None
    if outer_f is None:
        return None
    return {'outer': outer_f, 'inner': inner_f, 'outer_area': float(bodyc.sum()) * px_area,
            'inner_area': float(inner.sum()) * px_area if inner_f is not None else 0.0}


# ---------------------------------------------------------------------------- along the stack

def bridge_gaps(regions: list, smalls: list, labels, dropped: list) -> list:
    """Keep a muscle's small component (below ``min_area_mm2``, e.g. a thin tendon) on a slice
    between two slices where the muscle has kept components, so that its chain does not break
    there. In place on ``regions``/``dropped``; returns [(label, slice)] bridged."""
    out = []
    for lab in labels:
        pres = [zi for zi, r in enumerate(regions) if r.get(lab)]
        if len(pres) < 2:
            continue
        for zi in range(pres[0] + 1, pres[-1]):
            if not regions[zi].get(lab) and lab in smalls[zi]:
                reg = smalls[zi][lab]
                reg.small = False
                regions[zi][lab] = [reg]
                a = round(reg.area_mm2, 2)
                for q, d in enumerate(dropped):
                    if d['slice'] == zi and d['label'] == lab and d['area_mm2'] == a:
                        dropped.pop(q)
                        break
                out.append((lab, zi))
    return out


def label_slice_counts(labels: np.ndarray, wanted) -> dict:
    """{label: (K,) voxel count of the label on every volume slice k}."""
    K = labels.shape[2]
    mx = int(max(wanted)) + 1
    c = np.zeros((K, mx), np.int64)
    for k in range(K):
        b = np.bincount(labels[:, :, k].ravel(), minlength=mx)
        c[k] = b[:mx]
    return {int(l): c[:, int(l)].astype(np.float64) for l in wanted}


def glitch_substitute(counts: np.ndarray, k: int, jump: float = 2.5) -> int | None:
    """A used voxel slice k whose label area jumps by more than ``jump`` times against both
    neighbouring voxel slices (a labelling glitch: the bundled limb labels all of gastrocnemius
    medialis as lateralis on one voxel slice) is represented by the neighbouring slice whose area is
    closer to their mean; returns that slice, or None. Ends of a label (a neighbour without it) are
    never glitches."""
    if k <= 0 or k >= len(counts) - 1:
        return None
    a, own, b = counts[k - 1], counts[k], counts[k + 1]
    if a <= 0 or b <= 0:
        return None
    if own * jump < min(a, b) or own > jump * max(a, b):
        m = 0.5 * (a + b)
        return k - 1 if abs(a - m) <= abs(b - m) else k + 1
    return None


def slab_factor(counts: np.ndarray, ks, zi: int, has_prev: bool, has_next: bool, lo: float = 2 / 3, hi: float = 1.5,
                own: float | None = None) -> float:
    """Area factor of a ring on used slice ``zi`` so that the prism chain's volume (trapezoid rule
    over the used slices) equals the label's volume: the label voxels of the ring's slab (half way to
    each neighbouring ring of the chain; at a chain end, all the way to the next used slice or the
    volume's end, where the label tapers off between slices) over the ring's trapezoid weight,
    relative to the label's area on the slice itself; clamped to [lo, hi]."""
    K = len(counts)
    edges = np.arange(K + 1) - 0.5
    F = np.concatenate([[0.0], np.cumsum(counts)])
    k = float(ks[zi])
    vol = w = 0.0
    for nb, has in ((zi - 1, has_prev), (zi + 1, has_next)):
        if 0 <= nb < len(ks):
            kn = float(ks[nb])
            b = 0.5 * (k + kn) if has else kn - 0.5 * np.sign(kn - k)
            if has:
                w += 0.5 * abs(kn - k)
        else:
            b = -0.5 if (zi == 0) == (ks[-1] > ks[0]) else K - 0.5
        vol += abs(np.interp(b, edges, F) - np.interp(k, edges, F))
    own = counts[int(k)] if own is None else own
    if w <= 0 or own <= 0:
        return 1.0
    return float(np.clip(vol / (w * own), lo, hi))


def chain_rings(chains: list, regions: list, lab: int, n: int, counts: np.ndarray, ks, subst: dict | None = None) -> None:
    """Choose every contour ring of one muscle's chains (in place on the regions): start index by
    least twist and shear against the ring below, area = the region's label area times the slab
    factor (the chain keeps the label's volume); ``subst`` {slice: voxel slice} names slices whose
    section was taken from a neighbouring voxel slice (glitch_substitute)."""
    pres = {z for ch in chains for (z, _) in ch}
    for ch in chains:
        ref = None
        for z, i in ch:
            reg = regions[z][lab][i]
            if reg.fine is not None:
                k2 = (subst or {}).get(z)
                f = slab_factor(counts, ks, z, (z - 1) in pres, (z + 1) in pres, own=None if k2 is None else counts[k2])
                r, _ = best_ring(reg.fine, n, ref, reg.area_mm2 * 1e-6 * f)
                if r is not None:
                    reg.ring = np.concatenate([r, np.full((n, 1), reg.ring[0, 2])], axis=1)
                    reg.poly_area_mm2 = polygon_area(r) * 1e6
            ref = reg.ring[:, :2]


def fat_rings(fats: list, n: int, min_thickness_m: float, fallback=None, follow: bool = False) -> tuple[list, list]:
    """Fat tube rings from the slices' fine outlines (slices.fat_contours): the skin ring's start by
    least twist against the slice below, the inner ring's start by least distance to the skin ring
    of its slice (so that inner a and outer a face each other across the layer), both area-matched;
    the inner point is kept ``min_thickness_m`` inside the outer one. With ``follow`` (builder setting
    fat_follow) each ring follows its predecessor on the slice below instead where that fits: the skin ring
    by follow_ring, the inner ring by pair_inner with prev (facing the skin ring and near the inner ring below);
    the even rings above where it does not. Returns dicts like
    slices.fat_rays (inner, outer (n, 3), origin, has_bone, fat_area_mm2), and the slices whose
    outlines still gave a crossing cell: there ``fallback(slice, outer ring below)`` (the paper's
    rays, turned to the least twist against the ring below) is used when given."""
    out, ref, ref_in, f_bad = [], None, None, []
    for f in fats:
        ref_prev = ref
        if 'fine' not in f and 'outer_area' not in f:
            out.append(f)                           # ray fallback of an untraceable slice
            ref, ref_in = f['outer'][:, :2], f['inner'][:, :2]
            continue
        z = f['z']
        o = follow_ring(f['outer'], ref) if follow and ref is not None else None
        if o is not None:
            o = match_area(o, f['outer_area'])
            if not (is_simple(o) and polygon_area(o) > 0):
                o = None
        if o is None:
            o, _ = best_ring(f['outer'], n, ref, f['outer_area'])
        if o is None:
            o = ring_at(f['outer'], anterior_start(f['outer'], n), n)
        co = o.mean(axis=0)
        inn, crowded = None, False
        if f['inner'] is not None and follow and ref_in is not None:
            p = pair_inner(f['inner'], o, prev=ref_in)
            if p is not None:
                inn = _matched_if_valid(p, f['inner_area'], o)
        if f['inner'] is not None and inn is None:
            inn, _ = best_ring(f['inner'], n, o, f['inner_area'], centred=False)
            if inn is not None and not fat_quads_valid(inn, o):
                # a small inner region off the skin's centre (the foot): pair by angle about it instead, and where
                # that crosses or puts neighbouring inner points (nearly) together, along its outline (pair_inner)
                fi = f['inner']
                inn = match_area(pair_by_angle(fi, o), f['inner_area'])
                even = polygon_perimeter(fi) / n
                if not fat_quads_valid(inn, o) or gaps(inn).min() < ANGLE_MIN_GAP * even:
                    p = pair_inner(fi, o)
                    if p is not None:
                        inn = _matched_if_valid(p, f['inner_area'], o)
                    else:
                        crowded = True          # no pairing gives distinct points and valid quads: rays
        if inn is None:
            inn = co + 0.5 * (o - co)
        ci = inn.mean(axis=0)
        d = inn - o
        L = np.linalg.norm(d, axis=1)
        thin = L < min_thickness_m
        if thin.any():
            u = ci - o[thin]
            u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-12)
            inn[thin] = o[thin] + u * min_thickness_m
        ref = o
        if crowded or not fat_quads_valid(inn, o):
            f_bad.append(len(out))
            if fallback is not None:
                fb = fallback(len(out), ref_prev)
                out.append(fb)
                ref = ref_prev = fb['outer'][:, :2]
                ref_in = fb['inner'][:, :2]
                continue
        ref_prev = ref
        ref_in = inn

        def pts(xy):
            return np.concatenate([xy, np.full((n, 1), z)], axis=1)
        out.append({'origin': np.array([co[0], co[1], z]), 'inner': pts(inn), 'outer': pts(o), 'has_bone': f['has_bone'],
                    'fat_area_mm2': f['fat_area_mm2']})
    return out, f_bad


def _matched_if_valid(inner: np.ndarray, area: float, outer: np.ndarray) -> np.ndarray:
    """A paired inner ring area-matched to ``area`` (match_area) where its quads with the skin ring ``outer`` stay
    valid (fat_quads_valid), else as paired."""
    m = match_area(inner, area)
    return m if fat_quads_valid(m, outer) else inner


def pair_by_angle(fine: np.ndarray, outer: np.ndarray) -> np.ndarray:
    """For each vertex of ``outer`` (n, 2), the point of the fine inner outline ``fine`` nearest to it in angle about
    the outline's centroid (fat_rings' first pairing where the even ring would cross)."""
    c = fine.mean(axis=0)
    ang_f = np.arctan2(fine[:, 1] - c[1], fine[:, 0] - c[0])
    ang_o = np.arctan2(outer[:, 1] - c[1], outer[:, 0] - c[0])
    dif = np.abs((ang_f[None, :] - ang_o[:, None] + np.pi) % (2 * np.pi) - np.pi)
    return fine[np.argmin(dif, axis=1)]


@njit(cache=True)
def _pair_dp(I, dist, outer, g, G, even, quads=True):
    """pair_inner's (and follow_ring's) dynamic programme for one start: I (m + 1, 2) the fine points from the start
    (the last the start again), dist (m + 1, n) the weighted squared pairing lengths. Vertex k + 1 of ``outer`` pairs
    with fine point u, reached from k's t = u - dlt (g <= dlt <= G), when the quad (I[t], I[u], outer[k + 1],
    outer[k]) is a simple clockwise quad (``quads``; False: any step, outer the ring of another slice); the cost adds
    dist[u, k + 1] (the last step: u = m, the start) and (dlt / even - 1)^2. Returns (least cost at the start, inf
    when none, and the fine index of each vertex of outer). Ties go to the smaller dlt, then the smaller t (the order
    in which they are tried)."""
    m1, n = dist.shape
    m = m1 - 1
    cost = np.full(m1, np.inf)
    cost[0] = dist[0, 0]
    back = np.zeros((n, m1), dtype=np.int64)
    new = np.empty(m1)
    for k in range(n):
        obx, oby = outer[(k + 1) % n, 0], outer[(k + 1) % n, 1]
        oax, oay = outer[k, 0], outer[k, 1]
        new[:] = np.inf
        arg = back[k]
        found = False
        for t in range(m1):
            if cost[t] < np.inf:
                found = True
                break
        if not found:
            break
        last = m if k == n - 1 else m - g * (n - 1 - k)     # room left for the other steps (the last: u = m)
        for dlt in range(g, G + 1):
            for t in range(m1):
                if not cost[t] < np.inf:
                    continue
                u = t + dlt
                if (u != m) if k == n - 1 else (u > last):
                    continue
                ax, ay, bx, by = I[t, 0], I[t, 1], I[u, 0], I[u, 1]
                if quads and not (((_tri2s(ax, ay, bx, by, obx, oby) < 0) and (_tri2s(ax, ay, obx, oby, oax, oay) < 0))
                        or ((_tri2s(ax, ay, bx, by, oax, oay) < 0) and (_tri2s(bx, by, obx, oby, oax, oay) < 0))):
                    continue
                c = cost[t] + (dist[u, (k + 1) % n] if k < n - 1 else 0.0) + (dlt / even - 1.0) ** 2
                if c < new[u]:
                    new[u] = c
                    arg[u] = t
        cost[:] = new
    idx = np.zeros(n, dtype=np.int64)
    if not cost[m] < np.inf:
        return np.inf, idx
    u = m
    for k in range(n - 1, 0, -1):
        u = back[k, u]
        idx[k] = u
    return cost[m], idx


def pair_inner(fine: np.ndarray, outer: np.ndarray, floor: float = INNER_FLOOR, n_starts: int = 16,
               prev: np.ndarray | None = None) -> np.ndarray | None:
    """The fat layer's inner ring paired with the skin ring ``outer`` (n, 2, CCW) on the fine inner outline ``fine``
    (m, 2, CCW): indices in order along the outline, each step at least ``floor`` x and at most 6 x the even spacing
    m/n, every quad (inner a, inner b, outer b, outer a) a simple clockwise quad (one diagonal inside), with the least
    sum of squared deviations (in even spacings) from the even spacing plus INNER_NEAR x the squared pairing lengths
    (over the mean squared thickness), plus, with ``prev`` (n, 2: the inner ring of the slice below), FOLLOW_NEAR x
    each inner vertex's squared distance from its predecessor there (in even spacings of the outline).
    A dynamic programme over the fine points, for the ``n_starts`` starts nearest to outer[0]. None when no pairing
    gives valid quads. The floor keeps neighbouring inner vertices apart where a long skin outline faces a short inner
    one (the foot): there, pairing by nearness or by angle makes near-degenerate wedge cells."""
    d2 = np.sum((fine[:, None, :] - outer[None]) ** 2, axis=2)     # (m, n) squared pairing lengths
    d2 *= INNER_NEAR / (float(np.mean(np.min(d2, axis=0))) + 1e-24)
    if prev is not None:
        d2 += _follow_cost(fine, prev)
    return _least_pairing(fine, d2, outer, floor, n_starts, True)


def follow_ring(fine: np.ndarray, prev: np.ndarray, floor: float = INNER_FLOOR, n_starts: int = 8) -> np.ndarray | None:
    """The ring of n = len(prev) vertices on the fine outline ``fine`` (m, 2, CCW) that follows ``prev`` (n, 2: the
    ring of the slice below): indices in order along the outline, each step at least ``floor`` x and at most 6 x the
    even spacing m/n, with the least sum of FOLLOW_NEAR x each vertex's squared distance from its predecessor (in even
    spacings of the outline) plus the squared deviations of the steps from the even spacing (_pair_dp without the
    quads' test). Where an outline changes its shape between slices (the sole, the toes), an even ring from the best
    start (best_ring) moves its vertices along the outline by many spacings; this one moves each as little as the
    spacing allows. None when no pairing fits."""
    return _least_pairing(fine, _follow_cost(fine, prev), prev, floor, n_starts, False)


def _follow_cost(fine: np.ndarray, prev: np.ndarray) -> np.ndarray:
    """(m, n) FOLLOW_NEAR x the squared distances of the fine points from the vertices of the ring below, in even
    spacings of the fine outline (perimeter / n)."""
    spacing = polygon_perimeter(fine) / len(prev)
    return FOLLOW_NEAR * np.sum((fine[:, None, :] - prev[None]) ** 2, axis=2) / (spacing ** 2 + 1e-24)


def _least_pairing(fine, dist, outer, floor, n_starts, quads):
    """The least-cost pairing (_pair_dp) of the fine outline with the n vertices of ``outer`` over the ``n_starts``
    starts of least dist to outer[0]; the paired fine points (n, 2), or None when no start gives one."""
    m, n = len(fine), len(outer)
    even = m / n
    g = max(1, int(np.ceil(floor * even)))
    G = max(g, min(m // 2, int(np.ceil(6 * even))))
    if g * n > m:
        return None
    best, best_cost = None, np.inf
    for s0 in np.argsort(dist[:, 0], kind='stable')[:n_starts]:
        off = (s0 + np.arange(m + 1)) % m                           # offsets 0 .. m from the start (m: the start again)
        I, d = fine[off], dist[off]
        c, idx = _pair_dp(I, d, outer, g, G, even, quads)
        if np.isfinite(c) and c < best_cost:
            best_cost, best = c, I[idx]
    return None if best is None else best.copy()


def fat_quads_valid(inner: np.ndarray, outer: np.ndarray) -> bool:
    """Every fat quad (inner a, inner b, outer b, outer a) of one slice is clockwise (positive cell)."""
    b = np.r_[1:len(inner), 0]
    q = np.stack([inner, inner[b], outer[b], outer], axis=1)           # (n, 4, 2)
    x, y = q[..., 0], q[..., 1]
    a = 0.5 * np.sum(x * np.roll(y, -1, axis=1) - np.roll(x, -1, axis=1) * y, axis=1)
    return bool(np.all(a < 0))


def turn_rays(make, n: int, ref: np.ndarray | None, steps: int = 4) -> dict:
    """The ray fat ring ``make(angle_offset)`` (slices.fat_rays) turned to the least twist against
    ``ref``: angle offsets in ``steps`` sub-steps of the ray spacing, ray indices rolled."""
    if ref is None:
        return make(0.0)
    best, bc = None, np.inf
    for off in 2 * np.pi / n * np.arange(steps) / steps:
        f = make(off)
        o = f['outer'][:, :2]
        for r in range(n):
            c = float(np.sum(((np.roll(o, -r, axis=0) - o.mean(0)) - (ref - ref.mean(0))) ** 2))
            if c < bc:
                bc, best = c, (f, r)
    f, r = best
    return dict(f, inner=np.roll(f['inner'], -r, axis=0), outer=np.roll(f['outer'], -r, axis=0))
