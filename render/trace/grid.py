"""Boxes in a uniform grid, looked up by points: which boxes may hold a point (plain arrays,
off the tape).

A few tests pair points with boxes of the same scene and keep the pairs whose point lies
in (or within a tolerance of) the shape inside the box: the mesh edges that rest on another
object's surface (``render.trace.outlines``), the vertices that lie inside another face's
edge (T-junctions, ``render.trace.topology``). Testing every pair costs the product of the
counts; here each point meets only the boxes listed in its cell of a grid (cells as wide as
the median box), and the few boxes too large for the grid.
"""

from __future__ import annotations

import numpy as np

#: A box spanning more grid cells than this is paired with every point instead of being
#: listed in each cell (a floor of two triangles under a fine mesh).
MOST_CELLS = 64


def grown(lo: np.ndarray, hi: np.ndarray, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """Boxes [lo, hi] (n, 3) grown by ``tolerance``, and by a margin for the rounding of
    whatever computed them and of the test that will use them (a part in 1e12 of their
    coordinates): a point the test accepts lies in its grown box."""
    reach = 1.001 * tolerance + 1e-12 * np.maximum(np.abs(lo), np.abs(hi)).max(axis=1)
    return lo - reach[:, None], hi + reach[:, None]


def boxes_at_points(points: np.ndarray, lo: np.ndarray, hi: np.ndarray):
    """For points (k, 3) and boxes [lo, hi] (n, 3) each: (starts, stops (k,), order, large):
    point i's candidates are boxes ``order[starts[i]:stops[i]]`` (those overlapping its
    cell) and ``large`` (those spanning more than ``MOST_CELLS`` cells); every box that
    holds a point is among them."""
    empty = np.zeros(len(points), np.int64)
    if len(lo) == 0 or len(points) == 0:
        return empty, empty, np.zeros(0, np.int64), np.zeros(0, np.int64)
    origin = np.minimum(lo.min(axis=0), points.min(axis=0))
    extent = np.maximum(hi.max(axis=0), points.max(axis=0)) - origin
    # Cells as wide as the median box, at most 2^20 along an axis (keys fit an int64).
    width = max(float(np.median(np.max(hi - lo, axis=1))), float(extent.max()) / 2**20, 1e-300)
    dims = np.floor(extent / width).astype(np.int64) + 1
    first_cell = np.clip(np.floor((lo - origin) / width).astype(np.int64), 0, dims - 1)
    last_cell = np.clip(np.floor((hi - origin) / width).astype(np.int64), 0, dims - 1)
    span = last_cell - first_cell + 1
    count = np.prod(span, axis=1)
    large = np.flatnonzero(count > MOST_CELLS)
    small = np.flatnonzero(count <= MOST_CELLS)
    # Every (box, cell) pair of the small boxes: cell = first corner + offset.
    box = np.repeat(small, count[small])
    k = np.arange(len(box)) - np.repeat(np.cumsum(count[small]) - count[small], count[small])
    sx, sy = span[box, 0], span[box, 1]
    cell = first_cell[box] + np.stack([k % sx, (k // sx) % sy, k // (sx * sy)], axis=1)
    key = (cell[:, 2] * dims[1] + cell[:, 1]) * dims[0] + cell[:, 0]
    sort = np.argsort(key, kind="stable")
    key, order = key[sort], box[sort]
    at = np.clip(np.floor((points - origin) / width).astype(np.int64), 0, dims - 1)
    point_key = (at[:, 2] * dims[1] + at[:, 1]) * dims[0] + at[:, 0]
    starts = np.searchsorted(key, point_key, side="left")
    stops = np.searchsorted(key, point_key, side="right")
    return starts, stops, order.astype(np.int64), large.astype(np.int64)


def candidate_pairs(points: np.ndarray, lo: np.ndarray, hi: np.ndarray, most: int):
    """(point (m,), box (m,)): every pair ``boxes_at_points`` makes candidates, each once
    (a large box with every point); None if they are more than ``most`` (long thin boxes
    crowding a volume: a soup of 30k small random triangles' edges made 32M)."""
    starts, stops, order, large = boxes_at_points(points, lo, hi)
    count = stops - starts
    if int(count.sum()) + len(large) * len(points) > most:
        return None
    point = np.repeat(np.arange(len(points)), count)
    box = order[np.repeat(starts - np.cumsum(count) + count, count) + np.arange(count.sum())]
    if len(large):
        point = np.r_[point, np.repeat(np.arange(len(points)), len(large))]
        box = np.r_[box, np.tile(large, len(points))]
    return point, box
