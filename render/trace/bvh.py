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

against C_leaf = C_isect * n_P for keeping P a leaf.  We measure costs in units of one
primitive test (C_isect = 1).  Evaluating every possible split is
expensive; *binning* evaluates only ``n_bins - 1`` candidate planes per axis, evenly spaced
over the bounds of the primitive centroids (Wald 2007), which gives nearly the same trees in
O(n) per node.

Large builds use both cores: the subtrees below the top of the tree own disjoint ranges of
``order`` and disjoint regions of the node arrays, so once the top is split they are built
side by side (:func:`build_bvh`).  The tree is the one the serial loop makes, node for node.
"""

from __future__ import annotations

import numpy as np

from minidiff.threads import jit, job_count, kernel, run_jobs, share, thread_count
from render.trace.vec3 import EPS

#: Cost of one node visit (two box tests) relative to one primitive test (the SAH unit).
C_TRAV = 1.0
#: Leaves never hold more than this many primitives unless their centroids coincide exactly
#: (duplicated triangles), in which case they are split by index. 4 since the rays walk a
#: 4-wide tree (``render.trace.wide``), whose box tests are cheaper than the binary tree's:
#: 262,144 camera rays at a bumpy sphere of 82,024 triangles in a room (a scene like
#: ``benchmarks/bench_embree.py``'s) took 41.3 ms with leaves of up to 4, 42.0 ms with 6
#: and 47.8 ms with 8, one thread.
MAX_LEAF_SIZE = 4
#: Default number of SAH bins per axis.
N_BINS = 12
#: Builds of at least this many primitives build the subtrees below the top of the tree on
#: all threads (see :func:`build_bvh`); the tree is the same either way.
PARALLEL_MIN_PRIMS = 65536
#: ... the top being split until every pending subtree has fewer than P / TASKS_PER_BUILD
#: primitives (enough tasks to share out evenly among the threads).
TASKS_PER_BUILD = 64
#: Boxes are padded by this fraction of the scene size (see :func:`primitive_bounds`).
PAD_RELATIVE = 1e-5


@jit(cache=True)
def primitive_bounds(triangles, sphere_centers, sphere_radii):
    """Padded bounding boxes of all primitives, triangles first, then spheres.

    triangles (T, 3, 3), sphere_centers (S, 3), sphere_radii (S,)  ->
    prim_min, prim_max (T + S, 3).

    Why padded: the traversal culls a node when the ray misses its box.  A hit point computed
    by the ray-triangle test carries rounding error, so a ray that the triangle test accepts
    right at an edge could, after rounding, just miss the exact box, and the BVH would then
    disagree with brute force.  Growing every box by 1e-5 of the scene size (plus a few ulps of
    the coordinates) covers that error with a wide margin and costs nothing measurable.
    """
    T = triangles.shape[0]
    S = sphere_centers.shape[0]
    prim_min = np.empty((T + S, 3))
    prim_max = np.empty((T + S, 3))
    for i in range(T + S):
        for a in range(3):
            prim_min[i, a], prim_max[i, a] = _extent(i, a, triangles, sphere_centers, sphere_radii)
    if T + S == 0:
        return prim_min, prim_max
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for i in range(T + S):
        for a in range(3):
            lo[a] = min(lo[a], prim_min[i, a])
            hi[a] = max(hi[a], prim_max[i, a])
    pad = _pad(lo, hi)
    for i in range(T + S):
        for a in range(3):
            prim_min[i, a] -= pad
            prim_max[i, a] += pad
    return prim_min, prim_max


@jit(cache=True, inline="always")
def _extent(p, a, triangles, sphere_centers, sphere_radii):
    """(low, high): primitive ``p``'s unpadded extent along axis ``a`` (ids: the triangles,
    then the spheres)."""
    n_tri = triangles.shape[0]
    if p < n_tri:
        x0, x1, x2 = triangles[p, 0, a], triangles[p, 1, a], triangles[p, 2, a]
        return min(x0, min(x1, x2)), max(x0, max(x1, x2))
    return (sphere_centers[p - n_tri, a] - sphere_radii[p - n_tri],
            sphere_centers[p - n_tri, a] + sphere_radii[p - n_tri])  # fmt: skip


@jit(cache=True)
def _pad(lo, hi):
    """How far every box grows (``primitive_bounds`` says why), for a scene whose primitives
    span ``lo`` to ``hi`` (3,): 1e-5 of its extent plus 64 ulps of its largest coordinate."""
    extent = max(hi[0] - lo[0], max(hi[1] - lo[1], hi[2] - lo[2]))
    magnitude = 0.0
    for a in range(3):
        magnitude = max(magnitude, max(abs(lo[a]), abs(hi[a])))
    return PAD_RELATIVE * extent + 64.0 * EPS * magnitude


@jit(cache=True)
def half_area(lx, ly, lz, hx, hy, hz):
    """Half the surface area of the box [lx, hx] x [ly, hy] x [lz, hz] (the factor 2 cancels
    in the SAH ratios).  An empty box (lo > hi) has area 0."""
    ex = hx - lx
    ey = hy - ly
    ez = hz - lz
    if ex < 0.0 or ey < 0.0 or ez < 0.0:
        return 0.0
    return ex * ey + ey * ez + ez * ex


@jit(cache=True)
def _set_bounds(node, first, count, order, prim_min, prim_max, node_bounds):
    """Set ``node_bounds[node]`` to the union of the boxes of ``order[first:first+count]``
    (with ``centroid`` as both ``prim_min`` and ``prim_max``: the bounds of their centroids)."""
    lx = ly = lz = np.inf
    hx = hy = hz = -np.inf
    for k in range(first, first + count):
        p = order[k]
        lx = min(lx, prim_min[p, 0])
        ly = min(ly, prim_min[p, 1])
        lz = min(lz, prim_min[p, 2])
        hx = max(hx, prim_max[p, 0])
        hy = max(hy, prim_max[p, 1])
        hz = max(hz, prim_max[p, 2])
    node_bounds[node, 0] = lx
    node_bounds[node, 1] = ly
    node_bounds[node, 2] = lz
    node_bounds[node, 3] = hx
    node_bounds[node, 4] = hy
    node_bounds[node, 5] = hz


@jit(cache=True)
def _bin_index(c, cmin, scale, n_bins):
    """Bin of centroid coordinate ``c`` along an axis binned from ``cmin`` with ``scale``
    bins per unit.  Shared by the SAH evaluation and the partition so that they agree."""
    return min(n_bins - 1, int((c - cmin) * scale))


@jit(cache=True)
def split_scratch(n_bins):
    """The scratch arrays of :func:`_find_split`, allocated once per build, not per node:
    bin counts (3, n_bins) int64, bin boxes (3, n_bins, 6), the left sweep's counts and
    areas (n_bins,), the bin scale per axis (3,), the best split's two child boxes (2, 6)
    and their centroids' bounds (2, 6), which :func:`_partition` fills."""
    return (
        np.empty((3, n_bins), np.int64),
        np.empty((3, n_bins, 6)),
        np.empty(n_bins, np.int64),
        np.empty(n_bins),
        np.empty(3),
        np.empty((2, 6)),
        np.empty((2, 6)),
    )


@jit(cache=True)
def _find_split(first, count, order, prim_min, prim_max, centroid, area, c_trav, scratch, cb):
    """Binned SAH split search for the primitives ``order[first:first+count]``, whose
    centroids span ``cb`` (6,): (min x, y, z, max x, y, z).

    ``scratch`` comes from :func:`split_scratch`.  Returns ``(axis, split_bin, cmin, scale,
    cost)``: primitives whose centroid bin ``_bin_index(c[axis], cmin, scale)`` is
    ``< split_bin`` go left; ``cost`` is the SAH cost of that split in units of one primitive
    test; the two children's boxes are left in ``scratch[-2]``.  ``axis = -1`` if no plane
    separates the centroids (all coincide).
    """
    bins, bin_box, left_count, left_area, scale, child_box, _ = scratch
    n_bins = bins.shape[1]
    # The bins are spread over where the centroids are, not over the node's box, so that a
    # few large primitives do not squeeze all small ones into one bin.
    for a in range(3):
        scale[a] = 0.0
        if cb[3 + a] > cb[a]:
            s = n_bins / (cb[3 + a] - cb[a])
            if s < np.inf:  # an extent of a few denormals would give inf and then NaN bins
                scale[a] = s

    # One pass over the primitives fills the bins of all three axes: count and box.  A bin's
    # box is set by its first primitive, so empty bins are never initialised (most nodes are
    # small: resetting every box of every bin would cost more than filling them); the sweeps
    # below skip them.
    bins[:] = 0
    for k in range(first, first + count):
        p = order[k]
        # (the primitive's box read once into scalars, for the three axes' bins)
        x0, y0, z0 = prim_min[p, 0], prim_min[p, 1], prim_min[p, 2]
        x1, y1, z1 = prim_max[p, 0], prim_max[p, 1], prim_max[p, 2]
        for a in range(3):
            if scale[a] == 0.0:
                continue
            b = _bin_index(centroid[p, a], cb[a], scale[a], n_bins)
            if bins[a, b] == 0:
                bin_box[a, b, 0], bin_box[a, b, 1], bin_box[a, b, 2] = x0, y0, z0
                bin_box[a, b, 3], bin_box[a, b, 4], bin_box[a, b, 5] = x1, y1, z1
            else:
                bin_box[a, b, 0] = min(bin_box[a, b, 0], x0)
                bin_box[a, b, 1] = min(bin_box[a, b, 1], y0)
                bin_box[a, b, 2] = min(bin_box[a, b, 2], z0)
                bin_box[a, b, 3] = max(bin_box[a, b, 3], x1)
                bin_box[a, b, 4] = max(bin_box[a, b, 4], y1)
                bin_box[a, b, 5] = max(bin_box[a, b, 5], z1)
            bins[a, b] += 1

    best_axis = -1
    best_bin = 0
    best_cost = np.inf
    for a in range(3):
        if scale[a] == 0.0:
            continue
        # Sweep left to right: count and area of everything left of plane i, the plane
        # between bins i-1 and i.
        lx = ly = lz = np.inf
        hx = hy = hz = -np.inf
        n = 0
        for i in range(1, n_bins):
            if bins[a, i - 1] > 0:
                n += bins[a, i - 1]
                lx = min(lx, bin_box[a, i - 1, 0])
                ly = min(ly, bin_box[a, i - 1, 1])
                lz = min(lz, bin_box[a, i - 1, 2])
                hx = max(hx, bin_box[a, i - 1, 3])
                hy = max(hy, bin_box[a, i - 1, 4])
                hz = max(hz, bin_box[a, i - 1, 5])
            left_count[i] = n
            left_area[i] = half_area(lx, ly, lz, hx, hy, hz)
        # Sweep right to left, growing the right side, and evaluate each plane.
        lx = ly = lz = np.inf
        hx = hy = hz = -np.inf
        n = 0
        for i in range(n_bins - 1, 0, -1):
            if bins[a, i] > 0:
                n += bins[a, i]
                lx = min(lx, bin_box[a, i, 0])
                ly = min(ly, bin_box[a, i, 1])
                lz = min(lz, bin_box[a, i, 2])
                hx = max(hx, bin_box[a, i, 3])
                hy = max(hy, bin_box[a, i, 4])
                hz = max(hz, bin_box[a, i, 5])
            if n == 0 or left_count[i] == 0:
                continue  # not a split: one side would be empty
            # SAH: the cost of visiting this node plus testing each child's primitives,
            # weighted by the probability that a ray through the node enters that child.
            right_area = half_area(lx, ly, lz, hx, hy, hz)
            cost = c_trav + (left_count[i] * left_area[i] + n * right_area) / area
            if cost < best_cost:
                best_cost = cost
                best_axis = a
                best_bin = i
    if best_axis < 0:
        return -1, 0, 0.0, 0.0, np.inf
    # The children's boxes are the unions of their bins' boxes (exact: min and max do not
    # round), which saves a pass over the primitives per child.
    child_box[:, 0:3] = np.inf
    child_box[:, 3:6] = -np.inf
    for i in range(n_bins):
        if bins[best_axis, i] > 0:
            side = 0 if i < best_bin else 1
            for c in range(3):
                child_box[side, c] = min(child_box[side, c], bin_box[best_axis, i, c])
                child_box[side, 3 + c] = max(child_box[side, 3 + c], bin_box[best_axis, i, 3 + c])
    return best_axis, best_bin, cb[best_axis], scale[best_axis], best_cost


@jit(cache=True)
def _partition(first, count, order, centroid, axis, split_bin, cmin, scale, n_bins, child_cb):
    """Reorder ``order[first:first+count]`` in place so that primitives with centroid bin
    ``< split_bin`` come first (a quicksort-style partition); returns how many went left.
    Each primitive is looked at once, and its centroid, read anyway, also goes into the
    bounds of its side's centroids: ``child_cb`` (2, 6), left and right, which the
    children's split searches read (a pass over each child's primitives saved; the same
    tree: min and max do not round). With ``_find_split`` reading each primitive's box once,
    the serial build of ``bench_embree``'s 1.3M-triangle scene took 744-782 ms against
    809-836 ms before, one thread, four runs in turns."""
    # (the bounds in scalars, not in child_cb's rows: kept in registers)
    lx = ly = lz = rx = ry = rz = np.inf
    hx = hy = hz = sx = sy = sz = -np.inf
    i = first
    j = first + count - 1
    while i <= j:
        p = order[i]
        x, y, z = centroid[p, 0], centroid[p, 1], centroid[p, 2]
        if _bin_index(centroid[p, axis], cmin, scale, n_bins) < split_bin:
            lx, ly, lz = min(lx, x), min(ly, y), min(lz, z)
            hx, hy, hz = max(hx, x), max(hy, y), max(hz, z)
            i += 1
        else:
            rx, ry, rz = min(rx, x), min(ry, y), min(rz, z)
            sx, sy, sz = max(sx, x), max(sy, y), max(sz, z)
            order[i], order[j] = order[j], p
            j -= 1
    child_cb[0, 0], child_cb[0, 1], child_cb[0, 2] = lx, ly, lz
    child_cb[0, 3], child_cb[0, 4], child_cb[0, 5] = hx, hy, hz
    child_cb[1, 0], child_cb[1, 1], child_cb[1, 2] = rx, ry, rz
    child_cb[1, 3], child_cb[1, 4], child_cb[1, 5] = sx, sy, sz
    return i - first


@jit(cache=True)
def _subdivide(root, level, next_free, tree, boxes, rule, defer_below, deferred, deferred_level):
    """Split the subtree under ``root`` (at ``level``, root = 1) until its leaves are final.

    ``tree`` = (node_bounds, node_first, node_count, order), the arrays being built;
    ``boxes`` = (prim_min, prim_max, centroid) of the primitives; ``rule`` = (n_bins,
    max_leaf_size, c_trav), the split rule.  The node ``root`` must already hold its range
    of ``order`` (``node_first``/``node_count``) and its box.  New nodes are allocated as
    pairs from ``next_free`` on.  Nodes with fewer than ``defer_below`` primitives are not
    split but appended to ``deferred`` (with their level in ``deferred_level``) for a later
    call; ``defer_below = 0`` builds everything.
    Returns ``(next_free, depth, n_deferred)``.

    Top-down with an explicit stack: a node is split at its cheapest binned-SAH plane,
    unless keeping it a leaf is cheaper and it has at most ``max_leaf_size`` primitives.  A
    node whose centroids all coincide (duplicated primitives) cannot be split by a plane; if
    it is too big it is split in the middle of its index range instead.
    """
    node_bounds, node_first, node_count, order = tree
    prim_min, prim_max, centroid = boxes
    n_bins, max_leaf_size, c_trav = rule
    scratch = split_scratch(n_bins)
    child_cb = scratch[-1]  # (_partition's)
    depth = level
    n_deferred = 0
    # Depth-first: at most one pending sibling per level, and there are fewer levels than
    # primitives. Each pending node with its centroids' bounds (``_partition`` made them).
    stack = np.empty(node_count[root] + 2, np.int64)
    stack_level = np.empty(node_count[root] + 2, np.int64)
    stack_cb = np.empty((node_count[root] + 2, 6))
    cb = np.empty((1, 6))  # the node's, copied: its stack row is overwritten by a child's
    stack[0] = root
    stack_level[0] = level
    _set_bounds(0, node_first[root], node_count[root], order, centroid, centroid, stack_cb)
    sp = 1
    while sp > 0:
        sp -= 1
        node = stack[sp]
        level = stack_level[sp]
        first = node_first[node]
        count = node_count[node]
        for j in range(6):
            cb[0, j] = stack_cb[sp, j]
        if count > 1 and count < defer_below:
            deferred[n_deferred] = node
            deferred_level[n_deferred] = level
            n_deferred += 1
            continue
        depth = max(depth, level)
        if count <= 1:
            continue
        b = node_bounds[node]
        area = max(half_area(b[0], b[1], b[2], b[3], b[4], b[5]), 1e-300)
        axis, split_bin, cmin, scale, cost = _find_split(
            first, count, order, prim_min, prim_max, centroid, area, c_trav, scratch, cb[0]
        )
        if axis >= 0:
            if cost >= count and count <= max_leaf_size:
                continue  # testing all primitives is cheaper than any split: a leaf
            n_left = _partition(
                first, count, order, centroid, axis, split_bin, cmin, scale, n_bins, child_cb
            )
        elif count > max_leaf_size:
            n_left = count // 2  # all centroids coincide: split by index
            _set_bounds(0, first, n_left, order, centroid, centroid, child_cb)
            _set_bounds(1, first + n_left, count - n_left, order, centroid, centroid, child_cb)
        else:
            continue
        # Children are allocated as a pair, so the right child is always left + 1.
        left = next_free
        next_free += 2
        node_first[left] = first
        node_count[left] = n_left
        node_first[left + 1] = first + n_left
        node_count[left + 1] = count - n_left
        if axis >= 0:
            # The boxes _find_split made from its bins, element by element (a row
            # assignment compiles Numba's shape checks: a second of a cold start).
            child_box = scratch[-2]
            for j in range(6):
                node_bounds[left, j] = child_box[0, j]
                node_bounds[left + 1, j] = child_box[1, j]
        else:
            _set_bounds(left, first, n_left, order, prim_min, prim_max, node_bounds)
            _set_bounds(
                left + 1, first + n_left, count - n_left, order, prim_min, prim_max, node_bounds
            )
        node_first[node] = left
        node_count[node] = 0
        stack[sp] = left + 1
        stack_level[sp] = level + 1
        stack[sp + 1] = left
        stack_level[sp + 1] = level + 1
        for j in range(6):
            stack_cb[sp, j] = child_cb[1, j]
            stack_cb[sp + 1, j] = child_cb[0, j]
        sp += 2
    return next_free, depth, n_deferred


@kernel
def _subdivide_in_parallel(
    job, n_jobs, tasks, task_level, task_worker, task_free, task_end, task_depth, tree, boxes,
    rule,
):  # fmt: skip
    """Job ``job`` of ``n_jobs`` (``minidiff.threads.run_jobs``) of building the subtrees
    under the nodes ``tasks`` at once, one ``_subdivide`` each.

    They are independent: each owns its range of ``order`` and allocates its nodes from its
    own region ``task_free[i]`` on; ``task_end[i]`` and ``task_depth[i]`` receive where the
    region's used part ends and the subtree's depth.  Job ``w`` builds the tasks with
    ``task_worker == w`` (a static schedule of unequal tasks would leave a core idle).
    """
    unused = np.empty(0, np.int64)
    for i in range(tasks.shape[0]):
        if task_worker[i] == job:
            task_end[i], task_depth[i], _ = _subdivide(
                tasks[i], task_level[i], task_free[i], tree, boxes, rule, 0, unused, unused
            )


@jit(cache=True)
def _close_gaps(nodes_used, tasks, task_free, task_end, node_bounds, node_first, node_count):
    """Move the subtrees' regions down to follow each other from ``nodes_used`` on, shifting
    the child links of their interior nodes (and of their roots, which live above) by as much.
    Returns the number of nodes in use."""
    for i in range(tasks.shape[0]):
        shift = nodes_used - task_free[i]
        for n in range(task_free[i], task_end[i]):
            node_bounds[n + shift] = node_bounds[n]
            node_first[n + shift] = node_first[n] + (shift if node_count[n] == 0 else 0)
            node_count[n + shift] = node_count[n]
        if node_count[tasks[i]] == 0:
            node_first[tasks[i]] += shift
        nodes_used += task_end[i] - task_free[i]
    return nodes_used


def deal_out(sizes: np.ndarray, n_workers: int) -> np.ndarray:
    """Assign jobs of the given sizes (n,) to ``n_workers``: largest first, each to the worker
    with the least work so far (the LPT rule).  Returns each job's worker (n,) int64."""
    load = np.zeros(n_workers, np.int64)
    worker = np.empty(len(sizes), np.int64)
    for job in np.argsort(-np.asarray(sizes), kind="stable"):
        worker[job] = np.argmin(load)
        load[worker[job]] += sizes[job]
    return worker


def build_bvh(
    prim_min: np.ndarray,
    prim_max: np.ndarray,
    n_bins: int = N_BINS,
    max_leaf_size: int = MAX_LEAF_SIZE,
    c_trav: float = C_TRAV,
    parallel_min_prims: int = PARALLEL_MIN_PRIMS,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """Build a binned-SAH BVH over P primitive boxes ``prim_min``, ``prim_max`` (P, 3).

    Returns ``(node_bounds (M, 6), node_first (M,), node_count (M,), order (P,), depth)``
    with M the number of nodes (at most 2P - 1) and depth the number of levels (root = 1).

    With at least ``parallel_min_prims`` primitives the top of the tree is split first, down
    to subtrees of fewer than P / ``TASKS_PER_BUILD`` (at least ``2 * max_leaf_size``)
    primitives, and those are then built on all threads.  Every node is split by the same
    rule either way, so the tree is the same; only the numbering of its nodes differs (each
    subtree's nodes are contiguous).
    """
    P = prim_min.shape[0]
    if P == 0:
        empty = np.zeros(0, np.int64)
        return np.zeros((0, 6)), empty, empty.copy(), empty.copy(), 0
    centroid = 0.5 * (prim_min + prim_max)
    max_nodes = 2 * P - 1
    node_bounds = np.empty((max_nodes, 6))
    node_first = np.zeros(max_nodes, np.int64)
    node_count = np.zeros(max_nodes, np.int64)
    order = np.arange(P)
    node_count[0] = P
    _set_bounds(0, 0, P, order, prim_min, prim_max, node_bounds)
    defer_below = max(P // TASKS_PER_BUILD, 2 * max_leaf_size) if P >= parallel_min_prims else 0
    tasks = np.empty(P if defer_below else 0, np.int64)
    task_level = np.empty_like(tasks)
    tree = (node_bounds, node_first, node_count, order)
    boxes = (prim_min, prim_max, centroid)
    rule = (n_bins, max_leaf_size, float(c_trav))
    nodes_used, depth, n_tasks = _subdivide(
        0, 1, 1, tree, boxes, rule, defer_below, tasks, task_level
    )
    if n_tasks:
        tasks = tasks[:n_tasks]
        # A subtree of n primitives has at most 2n - 1 nodes, its root already allocated.
        region = 2 * node_count[tasks] - 2
        task_free = nodes_used + np.cumsum(region) - region
        task_end = np.empty(n_tasks, np.int64)
        task_depth = np.empty(n_tasks, np.int64)
        workers = deal_out(node_count[tasks], thread_count())
        run_jobs(
            _subdivide_in_parallel,
            int(workers.max()) + 1,
            tasks,
            task_level[:n_tasks],
            workers,
            task_free,
            task_end,
            task_depth,
            tree,
            boxes,
            rule,
        )
        depth = max(depth, int(task_depth.max()))
        nodes_used = _close_gaps(
            nodes_used, tasks, task_free, task_end, node_bounds, node_first, node_count
        )
    # Cut the arrays to the nodes used in place (realloc: no copy of what is kept; a copy
    # of the 1M-triangle tree's nodes took ~55 ms). Nothing else refers to them: ``tree``
    # holds these very arrays, not views.
    node_bounds.resize((nodes_used, 6), refcheck=False)
    node_first.resize(nodes_used, refcheck=False)
    node_count.resize(nodes_used, refcheck=False)
    return node_bounds, node_first, node_count, order, int(depth)


def refit_bounds(node_first, node_count, order, triangles, sphere_centers, sphere_radii):
    """The node boxes of a tree of ``build_bvh``'s form (``node_first``, ``node_count``,
    ``order`` (P,)) over the primitives triangles (T, 3, 3), spheres (S, 3), (S,) (T + S =
    P): each leaf's box the union of its primitives' (straight from their corners and
    spheres; ``_leaf_boxes``, on all threads), all grown by ``primitive_bounds``' pad, then
    each interior node's the union of its two children's (``_pad_and_join``). Returns
    node_bounds (M, 6): the boxes ``build_bvh`` gives these nodes over ``primitive_bounds``
    of the same primitives, bit for bit, on any number of threads (min and max are exact,
    and a rounded subtraction of the same pad keeps their order)."""
    node_bounds = np.empty((node_first.shape[0], 6))
    jobs = job_count(node_first.shape[0], 16384)
    spans = np.empty((jobs, 6))
    run_jobs(_leaf_boxes, jobs, node_first, node_count, order, triangles, sphere_centers,
             sphere_radii, node_bounds, spans)  # fmt: skip
    _pad_and_join(node_first, node_count, node_bounds, spans)
    return node_bounds


@kernel
def _leaf_boxes(job, n_jobs, node_first, node_count, order, triangles, sphere_centers,
                sphere_radii, node_bounds, spans):  # fmt: skip
    """Job ``job`` of ``n_jobs`` (``minidiff.threads.run_jobs``) of ``refit_bounds``: the
    unpadded boxes of the leaves among its share of the nodes, and their union in
    ``spans[job]`` (6,)."""
    span = spans[job]
    span[:3], span[3:] = np.inf, -np.inf
    start, stop = share(job, n_jobs, node_first.shape[0])
    for node in range(start, stop):
        if node_count[node] == 0:
            continue
        box = node_bounds[node]
        box[:3], box[3:] = np.inf, -np.inf
        for k in range(node_first[node], node_first[node] + node_count[node]):
            for a in range(3):
                low, high = _extent(order[k], a, triangles, sphere_centers, sphere_radii)
                box[a], box[3 + a] = min(box[a], low), max(box[3 + a], high)
        for a in range(3):
            span[a], span[3 + a] = min(span[a], box[a]), max(span[3 + a], box[3 + a])


@jit(cache=True)
def _pad_and_join(node_first, node_count, node_bounds, spans):
    """``refit_bounds``' second pass: every leaf's box grown by the pad of the scene's span
    (the union of ``spans`` (jobs, 6)), then each interior node's box the union of its
    children's, from the last node to the root."""
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for job in range(spans.shape[0]):
        for a in range(3):
            lo[a], hi[a] = min(lo[a], spans[job, a]), max(hi[a], spans[job, 3 + a])
    pad = _pad(lo, hi)
    for node in range(node_first.shape[0] - 1, -1, -1):
        box = node_bounds[node]
        if node_count[node] > 0:
            for a in range(3):
                box[a] -= pad
                box[3 + a] += pad
        else:
            left = node_first[node]
            for a in range(3):
                box[a] = min(node_bounds[left, a], node_bounds[left + 1, a])
                box[3 + a] = max(node_bounds[left, 3 + a], node_bounds[left + 1, 3 + a])


@jit(cache=True)
def sah_cost(node_bounds, node_first, node_count, c_trav):
    """The tree's SAH cost, in primitive tests: the expected work of a ray through the root
    box, sum over interior nodes of ``c_trav`` A(node) / A(root) plus over leaves of their
    primitive count times A(leaf) / A(root) (A: surface area). 0 for an empty tree or a
    root without area (one flat primitive)."""
    if node_first.shape[0] == 0:
        return 0.0
    root = node_bounds[0]
    area = half_area(root[0], root[1], root[2], root[3], root[4], root[5])
    if not area > 0.0:
        return 0.0
    total = 0.0
    for node in range(node_first.shape[0]):
        b = node_bounds[node]
        share = half_area(b[0], b[1], b[2], b[3], b[4], b[5]) / area
        total += share * (node_count[node] if node_count[node] > 0 else c_trav)
    return total


def one_leaf(n_prims: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """Brute force as a tree: a single leaf holding all ``n_prims`` primitives in id order,
    under a box of all space, in the form :func:`build_bvh` returns.

    The traversal's slab test passes every ray through an infinite box (its slab distances
    are -inf and +inf, never NaN: an inverse direction is never 0), so every ray whose
    interval ``tmin <= tmax`` is not empty tests every primitive, in id order.  No primitive
    (``n_prims = 0``): no node, as ``build_bvh`` gives.
    """
    if n_prims == 0:
        return build_bvh(np.zeros((0, 3)), np.zeros((0, 3)))
    space = np.array([[-np.inf, -np.inf, -np.inf, np.inf, np.inf, np.inf]])
    count = np.array([n_prims], np.int64)
    return space, np.zeros(1, np.int64), count, np.arange(n_prims, dtype=np.int64), 1
