"""The 4-wide BVH (``render.trace.wide``) and its vector box test (``render.trace.simd``):
the collapse keeps every leaf once, under boxes that hold the binary boxes; the float32
boxes are rounded outward; the vector test is the scalar one, bit for bit; and the traversal
of a refitted tree gives brute force's hits."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from numba import njit

from render.trace.accel import Accelerator
from render.trace.bvh import build_bvh, one_leaf, primitive_bounds
from render.trace.intersect import enter_slot, make_ray
from render.trace.simd import enter4
from render.trace.wide import CHILD, WIDTH, collapse, wide_nodes
from tests.render.trace.test_accel import assert_same_hits, rays_for, soups

SETTINGS = settings(max_examples=40, deadline=None)
NO_SPHERES = (np.zeros((0, 3)), np.zeros(0))


def _tree(tris):
    lo, hi = primitive_bounds(tris, *NO_SPHERES)
    return build_bvh(lo, hi, max_leaf_size=2)


def _slot_box(boxes, w, k):
    """(low (3,), high (3,)) float64 of slot k of wide node w."""
    cols = [a * WIDTH + k for a in range(6)]
    b = boxes[w, cols].astype(np.float64)
    return b[:3], b[3:]


# Bounds a float32 rounds the wrong way near zero, at the ends of its range and beyond.
EDGES = [0.0, -0.0, 1e-320, -1e-320, 1e-46, -1e-46, 1.401298464324817e-45, 3.5e38, -3.5e38,
         3.4028235677973366e38, 1.0 + 1e-9, -1.0 - 1e-9, np.inf, -np.inf]  # fmt: skip


@settings(max_examples=100, deadline=None)
@given(
    values=st.lists(
        st.one_of(st.sampled_from(EDGES), st.floats(allow_nan=False, allow_subnormal=True)),
        min_size=6,
        max_size=48,
    )
)
def test_boxes_are_rounded_outward_to_the_nearest_float32s(values):
    # Each slot's low corner the largest float32 <= the float64 bound, its high corner the
    # smallest >= it: NumPy's nextafter is the reference (the fill steps on the bits).
    m = len(values) // 6
    bounds = np.array(values[: 6 * m], float).reshape(m, 6)
    slot_node = np.full((-(-m // WIDTH), WIDTH), -1, np.int64)
    slot_node.ravel()[:m] = np.arange(m)
    boxes = wide_nodes(bounds, slot_node, np.zeros(slot_node.shape, np.int64))
    with np.errstate(over="ignore"):  # (beyond float32's range: inf, as the fill's)
        near = bounds.astype(np.float32)
        down = np.where(near > bounds, np.nextafter(near, np.float32(-np.inf)), near)
        up = np.where(near < bounds, np.nextafter(near, np.float32(np.inf)), near)
    for n in range(m):
        w, k = divmod(n, WIDTH)
        for a in range(3):
            for got, want in ((boxes[w, a * WIDTH + k], down[n, a]),
                              (boxes[w, 3 * WIDTH + a * WIDTH + k], up[n, 3 + a])):  # fmt: skip
                assert np.float32(got).view(np.int32) == np.float32(want).view(np.int32)


@SETTINGS
@given(tris=soups(min_size=1, max_size=120))
def test_the_collapse_keeps_every_leaf_once_under_boxes_that_hold_the_binary_ones(tris):
    bounds, first, count, order, depth = _tree(tris)
    child, leaf_start, slot_node = collapse(bounds, first, count)
    boxes = wide_nodes(bounds, slot_node, child)
    # Each row: the boxes, then the children's codes as int32; 64-byte aligned.
    np.testing.assert_array_equal(boxes.view(np.int32)[:, CHILD : CHILD + WIDTH], child)
    assert boxes.shape[1] * 4 == 128 and boxes.ctypes.data % 64 == 0
    leaves = first[count > 0]
    # The leaves, numbered by first row, partition the table.
    np.testing.assert_array_equal(leaf_start, np.r_[np.sort(leaves), len(order)])
    seen_leaves, seen_nodes = [], []
    for w in range(len(child)):
        for k in range(WIDTH):
            n = slot_node[w, k]
            lo, hi = _slot_box(boxes, w, k)
            if n < 0:  # an empty slot: at +inf, never entered
                assert np.all(lo == np.inf) and np.all(hi == np.inf)
                continue
            # Rounded outward: the float32 box holds the binary node's, and is the tightest.
            assert np.all(lo <= bounds[n, :3]) and np.all(hi >= bounds[n, 3:])
            assert np.all(np.nextafter(lo.astype(np.float32), np.float32(np.inf)) > bounds[n, :3])
            assert np.all(np.nextafter(hi.astype(np.float32), np.float32(-np.inf)) < bounds[n, 3:])
            c = child[w, k]
            if c < 0:
                assert count[n] > 0 and leaf_start[~c] == first[n]
                assert leaf_start[~c + 1] - leaf_start[~c] == count[n]
                seen_leaves.append(n)
            else:
                assert count[n] == 0 and c > w  # depth-first: a child after its parent
                seen_nodes.append(c)
                # The child node's slots lie inside this slot's box.
                for j in range(WIDTH):
                    if slot_node[c, j] >= 0:
                        clo, chi = _slot_box(boxes, c, j)
                        assert np.all(clo >= lo) and np.all(chi <= hi)
    assert sorted(seen_leaves) == sorted(np.flatnonzero(count > 0))
    assert sorted(seen_nodes) == list(range(1, len(child)))
    # Depth-first: a node's subtree is the block of rows that starts at it, its children's
    # subtrees one after the other in slot order.
    size = np.ones(len(child), np.int64)
    for w in range(len(child) - 1, -1, -1):
        size[w] += sum(size[c] for c in child[w] if c > 0)
    for w in range(len(child)):
        at = w + 1
        for c in child[w]:
            if c > 0:
                assert c == at
                at += size[c]
        assert at == w + size[w]
    # Each node has at least two children unless the tree is one leaf.
    filled = (slot_node >= 0).sum(axis=1)
    assert np.all(filled >= (1 if len(bounds) == 1 else 2))


def test_brute_force_and_empty_trees():
    child, leaf_start, slot_node = collapse(*one_leaf(7)[:3])
    assert child.tolist() == [[-1, 0, 0, 0]] and leaf_start.tolist() == [0, 7]
    lo, hi = _slot_box(wide_nodes(one_leaf(7)[0], slot_node, child), 0, 0)
    assert np.all(lo == -np.inf) and np.all(hi == np.inf)
    child, leaf_start, slot_node = collapse(*one_leaf(0)[:3])
    assert child.shape == (0, WIDTH) and leaf_start.tolist() == [0]


# Not cached: Numba's cache of a test module would not notice an edit to render/ (only the
# project's own kernels get minidiff.jitcache's wider stamp).
@njit
def _both_tests(boxes, origins, directions, tmin, t_far):
    """(N, W, 4) entry distances of each ray into each slot, by enter4 and by enter_slot."""
    n, W = origins.shape[0], boxes.shape[0]
    vector = np.empty((n, W, WIDTH))
    scalar = np.empty((n, W, WIDTH))
    for i in range(n):
        ray = make_ray(origins[i], directions[i], tmin, t_far[i])
        for w in range(W):
            d = enter4(boxes, w, ray.origin, ray.inverse, ray.tmin, t_far[i])
            vector[i, w, 0], vector[i, w, 1], vector[i, w, 2], vector[i, w, 3] = d
            for k in range(WIDTH):
                scalar[i, w, k] = enter_slot(boxes, w, k, ray, t_far[i])
    return vector, scalar


coordinate = st.floats(-4, 4, allow_subnormal=False)


@SETTINGS
@given(
    tris=soups(min_size=1, max_size=60),
    origins=st.lists(st.tuples(coordinate, coordinate, coordinate), min_size=1, max_size=8),
    axis_aligned=st.booleans(),
    on_corners=st.booleans(),
    data=st.data(),
)
def test_the_vector_box_test_is_the_scalar_one(tris, origins, axis_aligned, on_corners, data):
    """Bit for bit, on random trees' boxes (with empty slots), for rays in every direction,
    axis-aligned ones among them (zero components: the inverse's 1e300), from boxes'
    corners (where a ray that leaves a box enters and leaves it at t = 0: inclusive ends),
    with finite and infinite far ends."""
    bounds, first, count, _, _ = _tree(tris)
    child, _, slot_node = collapse(bounds, first, count)
    boxes = wide_nodes(bounds, slot_node, child)
    o = np.array(origins, np.float64)
    if on_corners:
        slots = np.argwhere(~_empty_slots(boxes))
        for i, (w, k) in enumerate(slots[np.arange(len(o)) % len(slots)]):
            lo, hi = _slot_box(boxes, w, k)
            o[i] = np.where(np.arange(3) % 2 == i % 2, lo, hi)
    d = np.array(data.draw(st.lists(st.tuples(coordinate, coordinate, coordinate),
                                    min_size=len(o), max_size=len(o))), np.float64)  # fmt: skip
    if axis_aligned:
        d[:, data.draw(st.integers(0, 2))] = 0.0
    d[np.all(d == 0, axis=1)] = (0.0, 0.0, 1.0)
    t_far = np.array(data.draw(st.lists(st.sampled_from([np.inf, 0.5, 2.0]), min_size=len(o),
                                        max_size=len(o))))  # fmt: skip
    vector, scalar = _both_tests(boxes, o, d, 0.0, t_far)
    np.testing.assert_array_equal(vector, scalar)
    assert np.all(vector[:, _empty_slots(boxes)] == np.inf)


def _empty_slots(boxes):
    """(W, 4) bool: the slots whose box is empty (all corners at +inf)."""
    boxes = boxes[:, :CHILD]
    return np.stack([boxes[:, a * WIDTH : (a + 1) * WIDTH] == np.inf for a in range(6)]).all(0)


@SETTINGS
@given(tris=soups(min_size=1, max_size=80), data=st.data())
def test_a_refitted_wide_tree_answers_as_brute_force(tris, data):
    """Moved corners: the refit gathers the wide boxes from the refitted binary boxes again,
    and every ray's closest hit and any-hit are brute force's on the moved triangles."""
    built = Accelerator(tris)
    moved = tris + data.draw(st.floats(0.01, 0.5)) * np.random.default_rng(
        data.draw(st.integers(0, 99))
    ).normal(size=tris.shape)
    refit = built.refitted(moved)
    assert refit._slot_node is built._slot_node
    np.testing.assert_array_equal(refit._wide_child(), built._wide_child())
    brute = Accelerator(moved, use_bvh=False)
    o, d = data.draw(rays_for(moved, NO_SPHERES[0], 64))
    assert_same_hits(refit.closest_hit(o, d), brute.closest_hit(o, d))
    np.testing.assert_array_equal(refit.occluded(o, d, 1.0), brute.occluded(o, d, 1.0))
