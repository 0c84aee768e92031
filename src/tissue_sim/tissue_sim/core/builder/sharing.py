"""Vertex sharing between tissues (paper section 2.4).

On each slice, vertices of *different tissues* (two different muscles, or a muscle and the fat)
closer than a threshold are grouped and replaced by one shared vertex at the group's centroid.
Grouping is single-linkage (union-find over close pairs, nearest pairs first) with one guard: a
group never takes two vertices of the same ring (polygon of one muscle component, or the fat ring
of the slice), so no cell gets a repeated vertex. All vertices of a slice share its z, so merged
vertices stay on the slice plane.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def share_groups(pos: np.ndarray, tissue: np.ndarray, ring: np.ndarray, slice_id: np.ndarray, radius: float,
                 eligible: np.ndarray | None = None) -> np.ndarray:
    """Group representative per vertex (index of a vertex in the same group; itself if unmerged).

    pos (V, 3) [m]; tissue (V,) int (muscle index, or -1 for fat): only different tissues merge;
    ring (V,) int: vertices of one ring never merge together; slice_id (V,): merges stay within a slice;
    eligible (V,) bool: vertices that may be merged at all (default all).
    """
    V = len(pos)
    parent = np.arange(V)
    if radius <= 0 or V == 0:
        return parent
    # pairs within the radius, only on the same slice (z equal) and of different tissues
    tree = cKDTree(pos)
    pairs = tree.query_pairs(radius, output_type='ndarray')
    if len(pairs) == 0:
        return parent
    a, b = pairs[:, 0], pairs[:, 1]
    keep = (slice_id[a] == slice_id[b]) & (tissue[a] != tissue[b])
    if eligible is not None:
        keep &= eligible[a] & eligible[b]
    a, b = a[keep], b[keep]
    d = np.linalg.norm(pos[a] - pos[b], axis=1)
    order = np.argsort(d, kind='stable')
    members = {}

    def find(x):
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    for i in order:
        ra, rb = find(a[i]), find(b[i])
        if ra == rb:
            continue
        ma = members.get(ra, [ra])
        mb = members.get(rb, [rb])
        rings_a = {int(ring[v]) for v in ma}
        if any(int(ring[v]) in rings_a for v in mb):
            continue
        parent[rb] = ra
        members[ra] = ma + mb
        members.pop(rb, None)
    return np.array([find(v) for v in range(V)])
