"""Binned-SAH BVH construction (Numba), in flat arrays.

The tree is stored the way tinybvh / Jacco Bikker's "How to build a BVH" articles do it:

* ``node_bounds`` (M, 6) float64 -- ``(min x, min y, min z, max x, max y, max z)``,
* ``node_first`` (M,) int64 -- a leaf's first index into ``order``; an interior node's left
  child (the right child is always ``left + 1``, so siblings share a cache line pair),
* ``node_count`` (M,) int64 -- number of primitives of a leaf, 0 for an interior node,
* ``order`` (P,) int64 -- primitive ids in leaf order: leaf ``n`` holds
  ``order[node_first[n] : node_first[n] + node_count[n]]``.

Node 0 is the root.  Triangles and spheres live in the same tree: the builder only sees
primitive bounding boxes, so any primitive kind with a box can be added.

Splits are chosen with the surface area heuristic (SAH).  For a ray that hits a node, the
probability that it also hits a child is (for uniformly distributed rays) the ratio of their
surface areas, so the expected cost of splitting a node P into L and R is

    C_split = C_trav + C_isect * (A(L) * n_L + A(R) * n_R) / A(P)

against C_leaf = C_isect * n_P for keeping P a leaf.  Evaluating every possible split is
expensive; *binning* evaluates only ``n_bins - 1`` candidate planes per axis, evenly spaced
over the bounds of the primitive centroids (Wald 2007), which gives nearly the same trees in
O(n) per node.
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: Cost of one node visit (two box tests) relative to one primitive test.
C_TRAV = 1.0
#: Cost of one primitive test.
C_ISECT = 1.0
#: Leaves never hold more than this many primitives unless their centroids coincide exactly
#: (duplicated triangles), in which case they are split by index.
MAX_LEAF_SIZE = 8
#: Default number of SAH bins per axis.
N_BINS = 12
#: Boxes are padded by this fraction of the scene size (see :func:`padded_bounds`).
PAD_RELATIVE = 1e-5


def padded_bounds(prim_min: np.ndarray, prim_max: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Grow the primitive boxes (P, 3) by a small absolute margin.

    The traversal culls a node when the ray misses its box.  A hit point computed by the
    ray-triangle test carries rounding error, so a ray that the triangle test accepts right
    at an edge could, after rounding, miss the exact box, and the BVH would then disagree with
    brute force.  Padding every box by 1e-5 of the scene size (plus a few ulps of the
    coordinates) is far more than that error, and costs nothing measurable in culling.
    """
    if prim_min.shape[0] == 0:
        return prim_min.copy(), prim_max.copy()
    extent = float(np.max(prim_max.max(axis=0) - prim_min.min(axis=0)))
    magnitude = float(max(np.abs(prim_min).max(), np.abs(prim_max).max()))
    pad = PAD_RELATIVE * extent + 64.0 * np.finfo(np.float64).eps * magnitude
    return prim_min - pad, prim_max + pad


@njit(cache=True)
def _surface_area(bmin, bmax):
    """Half the surface area of a box from its min/max corners (3,) (the factor 2 cancels in
    the SAH ratios).  An empty box (min > max) has area 0."""
    ex = bmax[0] - bmin[0]
    ey = bmax[1] - bmin[1]
    ez = bmax[2] - bmin[2]
    if ex < 0.0 or ey < 0.0 or ez < 0.0:
        return 0.0
    return ex * ey + ey * ez + ez * ex


@njit(cache=True)
def _update_bounds(node, first, count, order, prim_min, prim_max, node_bounds):
    """Set ``node_bounds[node]`` to the union of the boxes of ``order[first:first+count]``."""
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for k in range(first, first + count):
        p = order[k]
        for a in range(3):
            lo[a] = min(lo[a], prim_min[p, a])
            hi[a] = max(hi[a], prim_max[p, a])
    node_bounds[node, 0:3] = lo
    node_bounds[node, 3:6] = hi


@njit(cache=True)
def _find_split(first, count, order, prim_min, prim_max, centroid, area, n_bins):
    """Binned SAH split search for the primitives ``order[first:first+count]``.

    Returns ``(axis, split_bin, cmin, scale, cost)``: primitives whose centroid falls in a bin
    ``< split_bin`` along ``axis`` go left, with ``bin = int((c - cmin) * scale)``.
    ``axis = -1`` if every centroid coincides (no plane separates them).
    ``cost`` is the SAH cost of the split (see the module docstring).
    """
    # Centroid bounds: bins are spread over where the centroids are, not the node's box,
    # so that large primitives do not squeeze all small ones into one bin.
    cmin = np.full(3, np.inf)
    cmax = np.full(3, -np.inf)
    for k in range(first, first + count):
        p = order[k]
        for a in range(3):
            cmin[a] = min(cmin[a], centroid[p, a])
            cmax[a] = max(cmax[a], centroid[p, a])

    bin_count = np.zeros((3, n_bins), np.int64)
    bin_lo = np.full((3, n_bins, 3), np.inf)
    bin_hi = np.full((3, n_bins, 3), -np.inf)
    scale = np.zeros(3)
    for a in range(3):
        if cmax[a] > cmin[a]:
            scale[a] = n_bins / (cmax[a] - cmin[a])
    # One pass over the primitives fills the bins of all three axes.
    for k in range(first, first + count):
        p = order[k]
        for a in range(3):
            if scale[a] == 0.0:
                continue
            b = min(n_bins - 1, int((centroid[p, a] - cmin[a]) * scale[a]))
            bin_count[a, b] += 1
            for c in range(3):
                bin_lo[a, b, c] = min(bin_lo[a, b, c], prim_min[p, c])
                bin_hi[a, b, c] = max(bin_hi[a, b, c], prim_max[p, c])

    best_axis = -1
    best_bin = 0
    best_cost = np.inf
    left_area = np.zeros(n_bins)
    left_count = np.zeros(n_bins, np.int64)
    lo = np.empty(3)
    hi = np.empty(3)
    for a in range(3):
        if scale[a] == 0.0:
            continue
        # Sweep left to right: area/count of everything left of plane i (between bins i-1, i).
        lo[:] = np.inf
        hi[:] = -np.inf
        n = 0
        for i in range(1, n_bins):
            n += bin_count[a, i - 1]
            for c in range(3):
                lo[c] = min(lo[c], bin_lo[a, i - 1, c])
                hi[c] = max(hi[c], bin_hi[a, i - 1, c])
            left_count[i] = n
            left_area[i] = _surface_area(lo, hi)
        # Sweep right to left and evaluate each plane.
        lo[:] = np.inf
        hi[:] = -np.inf
        n = 0
        for i in range(n_bins - 1, 0, -1):
            n += bin_count[a, i]
            for c in range(3):
                lo[c] = min(lo[c], bin_lo[a, i, c])
                hi[c] = max(hi[c], bin_hi[a, i, c])
            if n == 0 or left_count[i] == 0:
                continue  # not a split: one side would be empty
            cost = (
                C_TRAV + C_ISECT * (left_count[i] * left_area[i] + n * _surface_area(lo, hi)) / area
            )
            if cost < best_cost:
                best_cost = cost
                best_axis = a
                best_bin = i
    if best_axis < 0:
        return -1, 0, 0.0, 0.0, np.inf
    return best_axis, best_bin, cmin[best_axis], scale[best_axis], best_cost


@njit(cache=True)
def _partition(first, count, order, centroid, axis, split_bin, cmin, scale, n_bins):
    """Reorder ``order[first:first+count]`` in place so that primitives with centroid bin
    ``< split_bin`` come first; returns how many went left.  Uses exactly the binning formula
    of :func:`_find_split`, so the counts match the SAH evaluation."""
    i = first
    j = first + count - 1
    while i <= j:
        b = min(n_bins - 1, int((centroid[order[i], axis] - cmin) * scale))
        if b < split_bin:
            i += 1
        else:
            order[i], order[j] = order[j], order[i]
            j -= 1
    return i - first


@njit(cache=True)
def build_bvh(prim_min, prim_max, n_bins=N_BINS, max_leaf_size=MAX_LEAF_SIZE):
    """Build a binned-SAH BVH over P primitive boxes ``prim_min``, ``prim_max`` (P, 3).

    Returns ``(node_bounds (M, 6), node_first (M,), node_count (M,), order (P,), depth)``
    with M the number of nodes used (at most 2P - 1) and depth the number of levels.
    Subdivision is top-down with an explicit stack: a node is split at the cheapest binned SAH
    plane unless keeping it a leaf is cheaper (and it has at most ``max_leaf_size``
    primitives).  Nodes whose centroids all coincide are split in the middle of their index
    range, so leaves stay small even for duplicated primitives.
    """
    P = prim_min.shape[0]
    if P == 0:
        return (
            np.zeros((0, 6)),
            np.zeros(0, np.int64),
            np.zeros(0, np.int64),
            np.zeros(0, np.int64),
            0,
        )
    centroid = 0.5 * (prim_min + prim_max)
    max_nodes = 2 * P - 1
    node_bounds = np.empty((max_nodes, 6))
    node_first = np.zeros(max_nodes, np.int64)
    node_count = np.zeros(max_nodes, np.int64)
    order = np.arange(P)

    node_first[0] = 0
    node_count[0] = P
    _update_bounds(0, 0, P, order, prim_min, prim_max, node_bounds)
    nodes_used = 1
    depth = 1
    # Depth-first order: at most one pending sibling per level, and there are < P levels.
    stack = np.empty(P + 2, np.int64)
    stack_depth = np.empty(P + 2, np.int64)
    stack[0] = 0
    stack_depth[0] = 1
    sp = 1
    while sp > 0:
        sp -= 1
        node = stack[sp]
        level = stack_depth[sp]
        depth = max(depth, level)
        first = node_first[node]
        count = node_count[node]
        if count <= 1:
            continue
        area = _surface_area(node_bounds[node, 0:3], node_bounds[node, 3:6])
        axis, split_bin, cmin, scale, cost = _find_split(
            first, count, order, prim_min, prim_max, centroid, max(area, 1e-300), n_bins
        )
        if axis >= 0:
            if cost >= C_ISECT * count and count <= max_leaf_size:
                continue  # a leaf is cheaper than any split
            n_left = _partition(first, count, order, centroid, axis, split_bin, cmin, scale, n_bins)
        elif count > max_leaf_size:
            n_left = count // 2  # all centroids coincide: split by index
        else:
            continue
        left = nodes_used
        nodes_used += 2
        node_first[left] = first
        node_count[left] = n_left
        node_first[left + 1] = first + n_left
        node_count[left + 1] = count - n_left
        _update_bounds(left, first, n_left, order, prim_min, prim_max, node_bounds)
        _update_bounds(
            left + 1, first + n_left, count - n_left, order, prim_min, prim_max, node_bounds
        )
        node_first[node] = left
        node_count[node] = 0
        stack[sp] = left + 1
        stack_depth[sp] = level + 1
        stack[sp + 1] = left
        stack_depth[sp + 1] = level + 1
        sp += 2
    return (
        node_bounds[:nodes_used].copy(),
        node_first[:nodes_used].copy(),
        node_count[:nodes_used].copy(),
        order,
        depth,
    )
