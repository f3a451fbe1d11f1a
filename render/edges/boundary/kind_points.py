"""The quadrature points of the cut pieces, dealt out to their curve kinds.

``render.edges.boundary.term.boundary_points`` cuts every kind's segments together
(``render.edges.boundary.pixels``) and hands each kind back the quadrature points on its
own segments. ``kind_points_reference`` states that in NumPy (``quadrature``, the image
plane's coordinates, a mask per kind); ``kind_points`` does it in one compiled, parallel
pass with the same operations (blocks of points as ``render.trace.intersect._jobs`` deals
rays: a count per block and kind, then each block writes its own rows, so the rows do not
depend on the thread count). ``tests/render/edges/test_border_kernel.py`` ties the two.
"""

from __future__ import annotations

import functools

import numba
import numpy as np

from render.edges.boundary.pixels import GAUSS_POINTS, border_share, quadrature
from render.scene.camera import to_image_plane
from render.trace.intersect import BLOCK, _jobs


@functools.cache
def _rule() -> tuple[np.ndarray, np.ndarray]:
    """The Gauss-Legendre nodes and weights on [0, 1] (GAUSS_POINTS,), as ``quadrature``
    forms them (once: ``leggauss`` solves an eigenproblem, ~0.5 ms a call). Read only."""
    nodes, weights = np.polynomial.legendre.leggauss(GAUSS_POINTS)
    nodes, weights = (nodes + 1.0) / 2.0, weights / 2.0
    nodes.flags.writeable = weights.flags.writeable = False
    return nodes, weights


def kind_points_reference(p0, p1, pieces, counts, width: int, height: int) -> list[tuple]:
    """Per kind (``counts`` (K,): how many of the segments p0 -> p1 (n, 2), pixel
    coordinates, are each kind's, in kind order): the quadrature points on the ``pieces``
    (segment, start, end, pixel (m,) each: ``split_at_crossings``) of its segments, as
    (its own segment index (g,), image-plane coords (g, 2), pixel (g,), weight (g,), key
    (g,): the point's row among all kinds' points), in the pieces' order."""
    at, segment, weight = quadrature(p0, p1, *pieces[:3])
    pixel = np.repeat(pieces[3], GAUSS_POINTS)
    coords = to_image_plane(at, width, height)
    owner = np.repeat(np.arange(len(counts)), counts)[segment]
    own_segment = segment - (np.cumsum(counts) - counts)[owner]
    found = []
    for k in range(len(counts)):
        rows = np.flatnonzero(owner == k)
        found.append(
            (own_segment[rows], np.take(coords, rows, axis=0), pixel[rows], weight[rows], rows)
        )
    return found


def kind_points(p0, p1, pieces, counts, width: int, height: int) -> list[tuple]:
    """``kind_points_reference``, in one compiled pass (``_kind_points``)."""
    nodes, weights = _rule()
    first = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    segment, start, end, pixel = pieces
    p0, p1 = np.ascontiguousarray(p0, np.float64), np.ascontiguousarray(p1, np.float64)
    kind_start, own, coords, pixel_out, weight, key = _kind_points(
        p0, p1, border_share(p0, p1), segment, start, end, pixel, nodes, weights, first,
        width, height, numba.get_num_threads(),
    )  # fmt: skip
    return [
        (own[a:b], coords[a:b], pixel_out[a:b], weight[a:b], key[a:b])
        for a, b in zip(kind_start[:-1], kind_start[1:], strict=True)
    ]


@numba.njit(cache=True, error_model="numpy", inline="always")
def _kind_of(s, first):
    """The kind whose segments, first[k]:first[k + 1], hold segment s."""
    k = 0
    while first[k + 1] <= s:
        k += 1
    return k


@numba.njit(cache=True, error_model="numpy", parallel=True)
def _kind_points(
    p0, p1, share, segment, start, end, pixel, nodes, weights, first, width, height, n_threads
):  # fmt: skip
    """The quadrature points (``nodes``, ``weights`` on [0, 1], times the ``share`` (n,) of
    their segment: ``border_share``) on the m pieces, grouped by
    the kind of their segment (kind k's segments: first[k]:first[k + 1]), each kind's in
    the pieces' order: (where each kind's rows start (K + 1,), own segment index, coords
    (g, 2) in the image plane, pixel, weight, key: the point's row in piece order)."""
    m, g, n_kinds = len(segment), len(nodes), len(first) - 1
    n_blocks, n_jobs = _jobs(m, n_threads)
    count = np.zeros((n_blocks + 1, n_kinds), np.int64)
    for job in numba.prange(n_jobs):
        for block in range(job, n_blocks, n_jobs):
            for i in range(block * BLOCK, min(m, (block + 1) * BLOCK)):
                count[block + 1, _kind_of(segment[i], first)] += g
    # Row of block b's first point of kind k: the kind's rows, then the blocks before b.
    kind_start = np.zeros(n_kinds + 1, np.int64)
    for k in range(n_kinds):
        total = 0
        for block in range(n_blocks + 1):
            total += count[block, k]
        kind_start[k + 1] = kind_start[k] + total
    for k in range(n_kinds):
        count[0, k] += kind_start[k]
        for block in range(1, n_blocks + 1):
            count[block, k] += count[block - 1, k]
    own = np.empty(m * g, np.int64)
    coords, weight = np.empty((m * g, 2)), np.empty(m * g)
    pixel_out, key = np.empty(m * g, np.int64), np.empty(m * g, np.int64)
    for job in numba.prange(n_jobs):
        for block in range(job, n_blocks, n_jobs):
            for i in range(block * BLOCK, min(m, (block + 1) * BLOCK)):
                s = segment[i]
                k = _kind_of(s, first)
                d0, d1 = p1[s, 0] - p0[s, 0], p1[s, 1] - p0[s, 1]
                span = end[i] - start[i]
                length = np.sqrt(d0 * d0 + d1 * d1) * span * share[s]
                for q in range(g):
                    row = count[block, k]
                    count[block, k] += 1
                    t = start[i] + span * nodes[q]
                    x, y = p0[s, 0] + t * d0, p0[s, 1] + t * d1
                    coords[row, 0] = 2.0 * x / width - 1.0
                    coords[row, 1] = 1.0 - 2.0 * y / height
                    own[row], pixel_out[row] = s - first[k], pixel[i]
                    weight[row], key[row] = length * weights[q], i * g + q
    return kind_start, own, coords, pixel_out, weight, key
