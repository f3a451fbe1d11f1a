"""A 4-wide BVH with float32 boxes, collapsed from the binary SAH tree of ``render.trace.bvh``.

The traversal (``render.trace.intersect``) walks this tree; the binary tree stays the one
that is built, refitted and costed, and this one is made from it in one pass over its nodes
(:func:`collapse`), its boxes gathered from the binary boxes again after a refit
(:func:`wide_nodes`).

Why wider: a binary tree tests two boxes a node and pushes or pops about once per level; a
4-wide one tests four boxes of one node side by side (six loads of four float32, as vector
instructions: ``render.trace.simd``) and halves the levels, the pushes and the pops (Embree's
BVH4, tinybvh's BVH4_CPU: "Shallow Bounding Volume Hierarchies for Fast SIMD Ray Tracing of
Incoherent Rays", Dammertz et al. 2008).  Why float32: the boxes are half the memory (a node
is 96 bytes of boxes, where four binary children took 192), and the traversal's time is much
of it waiting for memory.  The slab test still computes in float64 (a float32 box converts
exactly), so what decides a hit is unchanged.

The layout, W nodes, one row of ``nodes`` (W, 32) float32 each: 128 bytes, two cache
lines, the array aligned to 64 bytes, so that a node's boxes and its children's codes
arrive together:

* columns ``side * 12 + axis * 4 + slot`` (0 to 23) -- the boxes: side 0 the low corner,
  1 the high; the four children's boxes side by side per coordinate. Each float32 bound is
  the float64 one rounded outward (low down, high up), so a wide box holds its binary box:
  a ray that reaches a primitive through the binary tree reaches it through this one, and
  the hits stay bit for bit brute force's (``intersect``'s module docstring).  An empty
  slot's box has both corners at +inf, which no ray enters.
* columns ``CHILD + slot`` (24 to 27), read as int32 (``nodes.view(np.int32)``) -- the
  children: ``c >= 0`` the wide node ``c``; ``c < 0`` the leaf ``~c`` (``-1 - c``).
* ``leaf_start`` (L + 1,) int64, an array of its own -- leaf ``l`` holds rows
  ``leaf_start[l] : leaf_start[l+1]`` of the leaf-ordered primitive table: the binary
  leaves' ranges partition it, so the leaves numbered by their first row need one array.

Node 0 is the root, the others in depth-first order (a node's subtree follows it in memory).
"""

from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import types
from numba.core.errors import TypingError
from numba.extending import intrinsic

from minidiff.threads import jit, job_count, kernel, run_jobs, share
from render.trace.bvh import half_area

#: Children a node of the wide tree holds at most.
WIDTH = 4
#: A node's row: the boxes (6 * WIDTH float32), then the children's codes (WIDTH int32),
#: then padding to 128 bytes.
CHILD = 6 * WIDTH
NODE_COLUMNS = 32


@jit(cache=True)
def collapse(node_bounds, node_first, node_count):
    """The 4-wide tree of a binary tree of ``build_bvh``'s form (``node_bounds`` (M, 6),
    ``node_first``, ``node_count`` (M,)): returns ``child`` (W, 4), ``leaf_start`` (L + 1,)
    and ``slot_node`` (W, 4) int64, the binary node each slot stands for (-1: empty), from
    which :func:`wide_nodes` makes the boxes.

    Each wide node takes a binary interior node's two children, then replaces the child of
    largest surface area that is not a leaf by its two children, until it holds four or only
    leaves (the greedy collapse of Wald et al. 2008 and of Embree's BVH4 builder: the boxes
    a ray is likeliest to enter are opened at once).  A tree that is one leaf becomes a root
    with that one slot.  An empty tree (M = 0) gives no node.
    """
    M = node_first.shape[0]
    # The binary leaves numbered in the order of their first rows: each leaf marked at its
    # first row, the rows then read in order (their ranges are disjoint; no sort to compile).
    is_leaf = node_count > 0
    total = n_leaves = 0
    for n in range(M):
        if is_leaf[n]:
            total += node_count[n]
            n_leaves += 1
    starting = np.full(total, -1, np.int64)  # row -> the leaf that starts there
    for n in range(M):
        if is_leaf[n]:
            starting[node_first[n]] = n
    leaf_start = np.empty(n_leaves + 1, np.int64)
    rank = np.empty(M, np.int64)  # binary leaf -> its number
    r = 0
    for row in range(total):
        if starting[row] >= 0:
            rank[starting[row]] = r
            leaf_start[r] = row
            r += 1
    leaf_start[n_leaves] = total
    # At most one wide node per binary interior node (and the root).
    size = max(1, M - n_leaves) if M else 0
    child = np.zeros((size, WIDTH), np.int64)
    slot_node = np.full((size, WIDTH), -1, np.int64)
    if M == 0:
        return child[:0], leaf_start, slot_node[:0]
    if is_leaf[0]:
        child[0, 0] = ~rank[0]
        slot_node[0, 0] = 0
        return child[:1], leaf_start, slot_node[:1]
    # A stack of binary interior nodes still to become wide nodes, each with the slot
    # (parent wide node, slot) that will point to it. A node is numbered when it is taken:
    # its subtree is numbered before its next sibling's (depth-first order).
    # (Its rows written and read element by element: a tuple assigned to a row compiles
    # Numba's shape checks, over a second of a cold start.)
    todo = np.empty((size * WIDTH + 1, 3), np.int64)
    todo[0, 0], todo[0, 1], todo[0, 2] = 0, -1, 0
    n_todo, used = 1, 0
    kids = np.empty(WIDTH, np.int64)
    while n_todo:
        n_todo -= 1
        b, parent, slot = todo[n_todo, 0], todo[n_todo, 1], todo[n_todo, 2]
        w = used
        used += 1
        if parent >= 0:
            child[parent, slot] = w
        kids[0], kids[1], n_kids = node_first[b], node_first[b] + 1, 2
        while n_kids < WIDTH:
            widest, widest_area = -1, -1.0
            for k in range(n_kids):
                if not is_leaf[kids[k]]:
                    box = node_bounds[kids[k]]
                    area = half_area(box[0], box[1], box[2], box[3], box[4], box[5])
                    if area > widest_area:
                        widest, widest_area = k, area
            if widest < 0:
                break
            opened = kids[widest]
            kids[widest] = node_first[opened]
            kids[n_kids] = node_first[opened] + 1
            n_kids += 1
        for k in range(n_kids - 1, -1, -1):  # pushed last, taken first: slot 0's subtree next
            slot_node[w, k] = kids[k]
            if is_leaf[kids[k]]:
                child[w, k] = ~rank[kids[k]]
            else:
                todo[n_todo, 0], todo[n_todo, 1], todo[n_todo, 2] = kids[k], w, k
                n_todo += 1
    return child[:used], leaf_start, slot_node[:used]


def wide_nodes(node_bounds: np.ndarray, slot_node: np.ndarray, child: np.ndarray) -> np.ndarray:
    """The wide tree's ``nodes`` (W, 32) float32, each row 128 bytes on a 64-byte boundary
    (module docstring): slot ``(w, k)``'s box is binary node ``slot_node[w, k]``'s box of
    ``node_bounds`` (M, 6) rounded outward to float32, an empty slot's (-1) the empty box
    (both corners at +inf); columns ``CHILD``.. hold ``child`` (W, 4) as int32 bits. On all
    threads (the nodes are independent): a refit gathers them again."""
    W = slot_node.shape[0]
    # 64-byte aligned: a node is exactly two cache lines, read together.
    memory = np.empty(W * NODE_COLUMNS + 16, np.float32)
    skip = (-memory.ctypes.data % 64) // 4
    nodes = memory[skip : skip + W * NODE_COLUMNS].reshape(W, NODE_COLUMNS)
    nodes[:, CHILD + WIDTH :] = 0.0
    nodes.view(np.int32)[:, CHILD : CHILD + WIDTH] = child
    run_jobs(_fill_boxes, job_count(W, 4096), node_bounds, slot_node, nodes)
    return nodes


@kernel
def _fill_boxes(job, n_jobs, node_bounds, slot_node, boxes):
    """Job ``job`` of ``n_jobs`` (``minidiff.threads.run_jobs``) of ``wide_nodes``: the boxes
    of its share of the nodes."""
    start, stop = share(job, n_jobs, slot_node.shape[0])
    for w in range(start, stop):
        for k in range(WIDTH):
            n = slot_node[w, k]
            for a in range(3):
                if n < 0:
                    boxes[w, a * WIDTH + k] = np.inf
                    boxes[w, 3 * WIDTH + a * WIDTH + k] = np.inf
                else:
                    boxes[w, a * WIDTH + k] = _down(node_bounds[n, a])
                    boxes[w, 3 * WIDTH + a * WIDTH + k] = _up(node_bounds[n, 3 + a])


# Rounded outward by a step on the float32's bits, chosen without a branch: with
# ``np.nextafter`` (a call) behind a branch that goes either way at random, the boxes of the
# 1.3M-triangle tree took 49-58 ms on one thread, 24-28 ms this way (the same bits:
# tests/render/trace/test_wide.py); a refit gathers them again. A float32's bits, read as
# an int32, step to its neighbour away from zero by +1 and towards zero by -1 (on either
# side of zero); from a zero, the neighbour is the smallest subnormal of the wanted sign.


@jit(cache=True, inline="always")
def _down(x):
    """The largest float32 <= x (float32(x) rounds to nearest: one step down where that
    went up)."""
    y = np.float32(x)
    below = _from_bits(np.int32(-2147483647))  # 0x80000001: -(smallest subnormal), below 0
    if y != 0:
        below = _from_bits(np.int32(_bits(y) + (-1 if y > 0 else 1)))
    return below if np.float64(y) > x else y


@jit(cache=True, inline="always")
def _up(x):
    """The smallest float32 >= x."""
    y = np.float32(x)
    above = _from_bits(np.int32(1))  # the smallest subnormal, above 0
    if y != 0:
        above = _from_bits(np.int32(_bits(y) + (1 if y > 0 else -1)))
    return above if np.float64(y) < x else y


@intrinsic
def _bits(typingctx, x):
    """A float32's bits as an int32 (LLVM's bitcast: no memory, no call)."""
    if x != types.float32:
        raise TypingError(f"_bits takes a float32, got {x}")
    return types.int32(types.float32), lambda context, builder, sig, args: builder.bitcast(
        args[0], ir.IntType(32)
    )


@intrinsic
def _from_bits(typingctx, x):
    """The float32 whose bits are the int32 ``x``."""
    if x != types.int32:
        raise TypingError(f"_from_bits takes an int32, got {x}")
    return types.float32(types.int32), lambda context, builder, sig, args: builder.bitcast(
        args[0], ir.FloatType()
    )
