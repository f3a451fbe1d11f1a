"""Curves cut into pixels, and the quadrature points on the pieces (off the tape).

The boundary term integrates over each curve's piece inside each pixel. The curves come as
2-D segments in pixel coordinates (column, row; the image spans [0, W] x [0, H]):
``pixel_pieces`` cuts them at pixel borders and the image's border, ``split_at_crossings``
cuts the pieces again where two pieces in one pixel cross or one ends on another, and
``quadrature`` puts Gauss-Legendre points on the parts. The cutting runs in Numba: the
teapot at 512x512 has ~52k pieces, and the pair test inside crowded pixels is quadratic.
``pixel_gradient`` turns an edge function's image-plane gradient into pixel units.

A segment lying on a pixel border (an axis-aligned edge seen by a centred camera: the
commonest test scene) is shared: the box-filtered image has only one-sided derivatives
there (moving the edge right changes the pixel on its right, moving it left the one on its
left), and the boundary term takes the symmetric one, which central differences measure:
each piece is given to both pixels beside the border with half its weight
(``border_lines``, ``border_share``), and a segment on a horizontal and a vertical border
at once (a degenerate one, at a pixel corner) to four, with a quarter.
"""

from __future__ import annotations

import math

import numpy as np

import minidiff as md
from minidiff import buffers
from minidiff.threads import jit, job_count, kernel, run_jobs
from render.trace.intersect import BLOCK, n_blocks

#: Quadrature points per piece of a curve inside one pixel (Gauss-Legendre on [0, 1]). The
#: pieces are first cut wherever another curve crosses them in the pixel
#: (``split_at_crossings``), so that along a part nothing is hidden or uncovered and no
#: shadow begins: then the midpoint is exact while the jump varies linearly along it.
#: Without the cuts, a piece partly hidden by another surface's outline or partly in
#: shadow counted all or nothing: on the paper teapot at 64x64 (translation, window check
#: against 4,096-spp renders) one uncut point per piece left 1.8 % (3.2 % with shadows),
#: two 0.35 % (0.7 %).
GAUSS_POINTS = 1
#: A piece that ends this close (pixels) before another one, its line going on to cross
#: it, counts as ending on it (a T-junction, ``split_at_crossings``). A shadow border is
#: followed until its receiver changes (``shadow_tracing.bisect_chords``): where it falls
#: onto the next face of a faceted receiver its chord stops up to ``shadow_tracing.GAP``
#: (half of this) short of the crease, and where it enters another shadow ~1e-5 pixels
#: short of that shadow's border; the crease or the border must still be cut there (on
#: one side of the junction it lies in the shadow and jumps by nothing). When this was a
#: tenth of GAP, the creases were cut only by chance: a faceted cone's shadow on another
#: (RayTracer.jl's tree) gave the receiver's translation gradient 7 % off
#: (tests/render/edges/test_shadow_edges.py).
JUNCTION = 2e-3
#: A segment both of whose ends lie this close (pixels) to the same pixel border lies on it
#: (``border_lines``): far above the rounding of projected pixel coordinates (~1e-13),
#: far below any offset a finite difference could resolve.
ON_BORDER = 1e-9
#: ``border_lines``' entry for a segment on no border along that axis.
NO_BORDER = np.iinfo(np.int64).min
#: Pieces' bounding boxes are widened by this many pixels (and JUNCTION) before the pair
#: test rejects pairs whose boxes are apart: far above the rounding of pixel coordinates
#: (~1e-13), far below any piece's length that matters, so no pair the exact test accepts
#: is rejected.
BOX_SLACK = 1e-9


@jit(cache=True)
def _clip_box(x0, y0, x1, y1, width, height):
    """Liang-Barsky: the parameter range [t0, t1] of the segment inside [0, W] x [0, H]
    (t0 > t1: none of it)."""
    t0, t1 = 0.0, 1.0
    dx, dy = x1 - x0, y1 - y0
    for p, q in ((-dx, x0), (dx, width - x0), (-dy, y0), (dy, height - y0)):
        if p == 0.0:
            if q < 0.0:
                return 1.0, 0.0
        else:
            r = q / p
            if p < 0.0:
                t0 = max(t0, r)
            else:
                t1 = min(t1, r)
    return t0, t1


@jit(cache=True)
def _crossings(a0, a1, t0, t1, out):
    """The parameters t in (t0, t1) where a0 + t (a1 - a0) crosses an integer, in
    increasing order, written to ``out``; returns how many."""
    n = 0
    d = a1 - a0
    if d == 0.0:
        return 0
    lo, hi = a0 + t0 * d, a0 + t1 * d
    step = 1 if hi > lo else -1
    k = math.floor(lo) + 1 if step > 0 else math.ceil(lo) - 1
    while (k < hi) if step > 0 else (k > hi):
        out[n] = (k - a0) / d
        n += 1
        k += step
    return n


def border_lines(p0: np.ndarray, p1: np.ndarray) -> np.ndarray:
    """Per segment p0 -> p1 (k, 2) (pixel coordinates), the pixel border it lies on along
    each axis: (k, 2) int64, column x = border[:, 0] (a vertical border) and row y =
    border[:, 1] (a horizontal one), ``NO_BORDER`` where it lies on none (both ends within
    ``ON_BORDER`` of the same integer)."""
    line = np.rint(p0)
    on = (np.abs(p0 - line) <= ON_BORDER) & (np.abs(p1 - line) <= ON_BORDER)
    return np.where(on, line, NO_BORDER).astype(np.int64)


def border_share(p0: np.ndarray, p1: np.ndarray) -> np.ndarray:
    """Per segment p0 -> p1 (k, 2), the share (k,) of each pixel its pieces are given to: 1,
    1/2 on a pixel border (the pixels either side each get half), 1/4 on two (a corner)."""
    return np.prod(np.where(border_lines(p0, p1) == NO_BORDER, 1.0, 0.5), axis=1)


@jit(cache=True)
def _cells(c, border):
    """The pixel cells, along one axis, of a piece whose midpoint has coordinate ``c``: the
    two cells beside ``border`` if the piece's segment lies on it (``border_lines``), else
    the cell holding ``c`` (twice). Cells outside the image are skipped by the caller."""
    if border != NO_BORDER:
        return border - 1, border
    cell = math.floor(c)
    return cell, cell


@jit(cache=True)
def _count_pieces(p0, p1, border, width, height):
    n = 0
    for s in range(p0.shape[0]):
        t0, t1 = _clip_box(p0[s, 0], p0[s, 1], p1[s, 0], p1[s, 1], width, height)
        if t0 >= t1:
            continue
        ax, ay = p0[s, 0] + t0 * (p1[s, 0] - p0[s, 0]), p0[s, 1] + t0 * (p1[s, 1] - p0[s, 1])
        bx, by = p0[s, 0] + t1 * (p1[s, 0] - p0[s, 0]), p0[s, 1] + t1 * (p1[s, 1] - p0[s, 1])
        copies = (1 + (border[s, 0] != NO_BORDER)) * (1 + (border[s, 1] != NO_BORDER))
        pieces = abs(math.floor(bx) - math.floor(ax)) + abs(math.floor(by) - math.floor(ay)) + 1
        n += copies * pieces
    return n


@jit(cache=True)
def _fill_pieces(p0, p1, border, width, height, segment, start, end, pixel):
    xs = np.empty(width + 2)
    ys = np.empty(height + 2)
    n = 0
    for s in range(p0.shape[0]):
        t0, t1 = _clip_box(p0[s, 0], p0[s, 1], p1[s, 0], p1[s, 1], width, height)
        if t0 >= t1:
            continue
        nx = _crossings(p0[s, 0], p1[s, 0], t0, t1, xs)
        ny = _crossings(p0[s, 1], p1[s, 1], t0, t1, ys)
        i = j = 0
        a = t0
        while True:  # merge the two sorted lists of crossings
            if i < nx and (j >= ny or xs[i] <= ys[j]):
                b = xs[i]
                i += 1
            elif j < ny:
                b = ys[j]
                j += 1
            else:
                b = t1
            if b > a:
                m = 0.5 * (a + b)
                cx = p0[s, 0] + m * (p1[s, 0] - p0[s, 0])
                cy = p0[s, 1] + m * (p1[s, 1] - p0[s, 1])
                col0, col1 = _cells(cx, border[s, 0])
                row0, row1 = _cells(cy, border[s, 1])
                for row in range(row0, row1 + 1):
                    for col in range(col0, col1 + 1):
                        if 0 <= col < width and 0 <= row < height:
                            segment[n], start[n], end[n] = s, a, b
                            pixel[n] = row * width + col
                            n += 1
            a = b
            if b >= t1:
                break
    return n


def pixel_pieces(p0: np.ndarray, p1: np.ndarray, width: int, height: int):
    """Cut 2-D segments p0 -> p1 (k, 2), in pixel coordinates, at pixel borders and at the
    image's border: per piece its segment (m,) int64, parameter range [start, end] (m,)
    each along the segment, and pixel (m,) int64 (row * W + column). A segment lying on a
    pixel border gives each piece to both pixels beside it, in two rows (four at a corner;
    ``border_share`` is the weight of each)."""
    p0, p1 = np.ascontiguousarray(p0, np.float64), np.ascontiguousarray(p1, np.float64)
    border = border_lines(p0, p1)
    bound = _count_pieces(p0, p1, border, width, height)
    segment, pixel = np.empty(bound, np.int64), np.empty(bound, np.int64)
    start, end = np.empty(bound), np.empty(bound)
    n = _fill_pieces(p0, p1, border, width, height, segment, start, end, pixel)
    return segment[:n], start[:n], end[:n], pixel[:n]


@jit(cache=True)
def _piece_geometry(p0, p1, segment, start, end, order, lo, hi, out):
    """Rows lo..hi - 1 of the pieces' geometry, in ``order``: each piece's start a, its
    extent b (the piece is a -> a + b), its bounding box widened by BOX_SLACK and how far
    (as a fraction of b) beyond its ends another piece's line still counts as reaching it,
    as rows (ax, ay, bx, by, x0, x1, y0, y1, reach) of ``out`` (k, 9), read contiguously by
    ``_split_group``'s pair loop."""
    for x in range(lo, hi):
        i = order[x]
        s = segment[i]
        dx, dy = p1[s, 0] - p0[s, 0], p1[s, 1] - p0[s, 1]
        ax, ay = p0[s, 0] + start[i] * dx, p0[s, 1] + start[i] * dy
        bx, by = p0[s, 0] + end[i] * dx - ax, p0[s, 1] + end[i] * dy - ay
        out[x, 0], out[x, 1], out[x, 2], out[x, 3] = ax, ay, bx, by
        slack = BOX_SLACK + JUNCTION
        out[x, 4], out[x, 5] = min(ax, ax + bx) - slack, max(ax, ax + bx) + slack
        out[x, 6], out[x, 7] = min(ay, ay + by) - slack, max(ay, ay + by) + slack
        # Another piece's end counts as on this one when it stops within JUNCTION pixels.
        out[x, 8] = max(1e-12, JUNCTION / math.sqrt(bx * bx + by * by))


@jit(cache=True, inline="always")
def boxes_apart(ax0, ax1, bx0, bx1, ay0, ay1, by0, by1):
    """Whether two axis-aligned boxes, [ax0, ax1] x [ay0, ay1] and [bx0, bx1] x [by0, by1],
    are apart along x or y."""
    return bx0 > ax1 or ax0 > bx1 or by0 > ay1 or ay0 > by1


#: ``_sort_cuts`` sorts this many cuts or fewer by insertion.
FEW_CUTS = 24


@jit(cache=True)
def _sort_cuts(ts, m):
    """Sort ts[:m] in place. m is small on most pieces, and Numba's ``sort`` costs ~200 ns
    even for two (10 ms of a 512x512 teapot's split): insertion below FEW_CUTS. Where
    hundreds of silhouette segments meet (the teapot's pole) a piece has hundreds of cuts:
    an O(m log m) heapsort there (Numba's ``sort`` compiles a quicksort: about a second of
    a cold start). (The cuts are numbers, never NaN: any sort gives the same array.)"""
    if m > FEW_CUTS:
        for root in range(m // 2 - 1, -1, -1):  # a max-heap of ts[:m]
            _sift_down(ts, root, m)
        for end in range(m - 1, 0, -1):  # the largest left to the end, one after another
            ts[0], ts[end] = ts[end], ts[0]
            _sift_down(ts, np.int64(0), end)  # (a literal 0: a second compile)
        return
    for k in range(1, m):
        t = ts[k]
        j = k - 1
        while j >= 0 and ts[j] > t:
            ts[j + 1] = ts[j]
            j -= 1
        ts[j + 1] = t


@jit(cache=True)
def _sift_down(ts, root, end):
    """Move ts[root] down the heap ts[:end] (children of i at 2 i + 1 and 2 i + 2) until
    neither child is larger."""
    while True:
        child = 2 * root + 1
        if child >= end:
            return
        if child + 1 < end and ts[child] < ts[child + 1]:
            child += 1
        if not ts[root] < ts[child]:
            return
        ts[root], ts[child] = ts[child], ts[root]
        root = child


@jit(cache=True)
def _room(out, base, n, end, extra):
    """A job's table with room for ``extra`` more rows: its parts are rows base..n-1 of
    ``out``, which it may fill up to row ``end``. Returns (out, base, n, end): the same
    where there is room, else a table of its own at least twice as long holding those
    rows from row 0."""
    if n + extra <= end:
        return out, base, n, end
    size = max(2 * (end - base), n - base + extra)
    bigger = np.empty((size, 4))
    for r in range(n - base):  # (a slice assignment compiles its shape checks: seconds)
        for c in range(4):
            bigger[r, c] = out[base + r, c]
    return bigger, 0, n - base, size


@jit(cache=True)
def _split_group(geometry, segment, start, end, pixel, order, lo, hi, first, out, n, limit, ts):
    """Split the pieces order[first:hi] (of the group order[lo:hi], all in one pixel) where
    another of the group crosses or touches them; append the parts (segment, start, end,
    pixel rows) to ``out`` from row n, up to row ``limit`` (``geometry``:
    ``_piece_geometry``; ``ts``: scratch, at least hi - lo long). Returns the new row count
    and the first piece whose parts did not fit (hi: all did); the caller grows ``out``
    and calls again from there. (No array is returned: Numba would count its references
    for every group.)"""
    for x in range(first, hi):
        i = order[x]
        ax, ay, bx, by = geometry[x, 0], geometry[x, 1], geometry[x, 2], geometry[x, 3]
        m = np.int64(0)  # not the literal 0: _sort_cuts would compile for both
        for y in range(lo, hi):
            if y == x:
                continue
            # Pieces whose boxes are apart cannot meet (most pairs in a crowded pixel).
            if boxes_apart(
                geometry[x, 4], geometry[x, 5], geometry[y, 4], geometry[y, 5],
                geometry[x, 6], geometry[x, 7], geometry[y, 6], geometry[y, 7],
            ):  # fmt: skip
                continue
            cx, cy, fx, fy = geometry[y, 0], geometry[y, 1], geometry[y, 2], geometry[y, 3]
            den = bx * fy - by * fx
            if den == 0.0:
                continue
            num = (cx - ax) * fy - (cy - ay) * fx
            # t = num / den outside (0, 1) for most pairs, seen without the division: signs
            # that differ give t <= 0, |num| >= |den| gives |t| >= 1 (rounding is monotonic).
            if (num < 0.0) != (den < 0.0) or abs(num) >= abs(den):
                continue
            t = num / den
            if not 1e-9 < t < 1.0 - 1e-9:
                continue  # then u is not needed
            u = ((cx - ax) * by - (cy - ay) * bx) / den
            reach = geometry[y, 8]
            if -reach <= u <= 1.0 + reach:
                ts[m] = t
                m += 1
        _sort_cuts(ts, m)
        if n + m + 1 > limit:  # m cuts make at most m + 1 parts
            return n, x
        previous = 0.0
        for k in range(m + 1):
            t = ts[k] if k < m else 1.0
            if t > previous:
                out[n, 0] = segment[i]
                out[n, 1] = start[i] + previous * (end[i] - start[i])
                out[n, 2] = start[i] + t * (end[i] - start[i])
                out[n, 3] = pixel[i]
                n += 1
            previous = t
    return n, hi


def _split_all(p0, p1, segment, start, end, pixel, order, bounds):
    """Every pixel's group of pieces split (``_split_group``): the groups (pieces
    order[bounds[g]:bounds[g + 1]]) in blocks of BLOCK, dealt to jobs as
    ``render.trace.intersect`` deals rays (the crowded pixels lie together in pixel
    order). Each job writes its groups' parts one after the other into its own stretch of
    a scratch table, twice as many rows as its pieces (most pieces are not cut), and on
    into a table of its own, grown as it fills, if they are more (a pixel of k pieces may
    have up to k * k parts, but a dense mesh's thousands of pieces in one pixel of a small
    image cross little: a table for k * k parts took tens of GB). The parts are then
    copied out in group order: the same rows, in the same order, on any number of
    threads. Returns the parts' (segment, start, end, pixel) (m,) each."""
    n_groups = len(bounds) - 1
    count, at = np.empty(n_groups, np.int64), np.empty(n_groups, np.int64)
    n_jobs = job_count(n_groups, BLOCK)
    # Each job's stretch of the scratch table: twice the pieces of the blocks dealt to it.
    firsts = np.arange(0, n_groups, BLOCK)
    pieces = bounds[np.minimum(firsts + BLOCK, n_groups)] - bounds[firsts]
    stretch = np.zeros(n_jobs + 1, np.int64)
    np.add.at(stretch, np.arange(len(firsts)) % n_jobs + 1, 2 * pieces + 16)
    stretch = np.cumsum(stretch)
    # From minidiff's pool, its rows rounded up to a power of two, so that the next
    # render, whose count differs a little, reuses it instead of touching fresh pages.
    scratch = buffers.empty((1 << int(stretch[-1]).bit_length(), 4), np.float64)
    widest = int(np.diff(bounds).max(initial=0))
    geometry = np.empty((len(order), 9))
    tables = run_jobs(
        _split_groups, n_jobs, p0, p1, segment, start, end, pixel, order, bounds, scratch,
        stretch, widest, geometry, count, at,
    )  # fmt: skip
    # Group g's parts are rows at[g], ..., at[g] + count[g] - 1 of its job's table (the
    # job of its block), which starts at row offset[job] of ``joined``: the scratch table
    # itself where every job's parts fit in their stretches (the common case), else the
    # tables joined.
    if all(np.may_share_memory(t, scratch) for t, _, _ in tables):  # (a grown one is apart)
        joined, offset = scratch, stretch
    else:
        joined = np.concatenate([t[base:row] for t, base, row in tables])
        offset = np.cumsum([0] + [row - base for _, base, row in tables])
    first = offset[(np.arange(n_groups) // BLOCK) % n_jobs] + at
    rows = np.repeat(first - (np.cumsum(count) - count), count) + np.arange(int(count.sum()))
    columns = np.ascontiguousarray(joined[rows].T)  # each returned array contiguous, as before
    return columns[0].astype(np.int64), columns[1], columns[2], columns[3].astype(np.int64)


@kernel
def _split_groups(
    job, n_jobs, p0, p1, segment, start, end, pixel, order, bounds, scratch, stretch, widest,
    geometry, count, at,
):  # fmt: skip
    """Job ``job`` of ``n_jobs`` (``minidiff.threads.run_jobs``) of ``_split_all``: its
    blocks of groups split, their parts written from row ``stretch[job]`` of ``scratch``
    on (or into a table of its own once that stretch is full); returns that table and the
    rows it filled, (table, first, stop); group g's first row among them to at[g], its
    number of parts to count[g]."""
    n_groups = bounds.shape[0] - 1
    ts = np.empty(widest + 1)
    out, base, limit = scratch, stretch[job], stretch[job + 1]
    row = base
    for b in range(job, n_blocks(n_groups), n_jobs):
        for g in range(b * BLOCK, min(n_groups, (b + 1) * BLOCK)):
            lo, hi = bounds[g], bounds[g + 1]
            at[g] = row - base
            if hi - lo == 1:  # nothing to cut: the common case
                if row + 1 > limit:
                    out, base, row, limit = _room(out, base, row, limit, 1)
                i = order[lo]
                out[row, 0], out[row, 1], out[row, 2] = segment[i], start[i], end[i]
                out[row, 3] = pixel[i]
                row += 1
            else:
                _piece_geometry(p0, p1, segment, start, end, order, lo, hi, geometry)
                x = lo
                while True:
                    row, x = _split_group(geometry, segment, start, end, pixel, order, lo, hi,
                                          x, out, row, limit, ts)  # fmt: skip
                    if x == hi:
                        break
                    out, base, row, limit = _room(out, base, row, limit, hi - lo)
            count[g] = row - base - at[g]
    return out, base, row


def pixel_order(pixel: np.ndarray) -> np.ndarray:
    """``np.argsort(pixel, kind="stable")`` for pixel ids (k,) int64 >= 0: each pair (id,
    position) packed into one int64 and sorted by NumPy's fastest sort (vectorised on x86;
    the stable argsort takes ~6x as long on the teapot's 52k pieces at 512x512). Unique
    keys, so the order is the stable one; ids or positions too large to pack fall back.
    (``_counting_order`` gives the same order; this is its reference.)"""
    n = len(pixel)
    if n == 0 or n >= 1 << 32 or pixel.max() >= 1 << 31:
        return np.argsort(pixel, kind="stable")
    return np.sort((pixel << 32) | np.arange(n)) & 0xFFFFFFFF


#: ``split_at_crossings`` orders the pieces by a counting sort while the pixel ids span at
#: most this many per piece (the teapot at 512x512: ~5), else by ``pixel_order``: a counting
#: sort's table of every pixel of a large image would cost more than sorting few pieces.
COUNTING_SPAN = 16


@jit(cache=True)
def _counting_order(pixel, n_pixels):
    """``pixel_order``'s order of pixel ids (k,) int64 in [0, n_pixels), by a counting
    sort (stable; several times faster than NumPy's sort on the teapot's pieces)."""
    where = np.zeros(n_pixels + 1, np.int64)
    for i in range(len(pixel)):
        where[pixel[i] + 1] += 1
    for p in range(n_pixels):
        where[p + 1] += where[p]
    order = np.empty(len(pixel), np.int64)
    for i in range(len(pixel)):
        order[where[pixel[i]]] = i
        where[pixel[i]] += 1
    return order


@jit(cache=True)
def _pixel_groups(pixel, order):
    """The pieces (pixel ids (k,), k > 0, in ``order``, by pixel) grouped: ``bounds``
    (n + 1,) where each of the n occupied pixels' group starts in ``order``."""
    n_groups = 1
    for x in range(1, len(pixel)):
        n_groups += pixel[order[x]] != pixel[order[x - 1]]
    bounds = np.empty(n_groups + 1, np.int64)
    bounds[0] = 0
    g = 0
    for x in range(1, len(pixel) + 1):
        if x == len(pixel) or pixel[order[x]] != pixel[order[x - 1]]:
            g += 1
            bounds[g] = x
    return bounds


def split_at_crossings(p0, p1, segment, start, end, pixel):
    """The pieces (``pixel_pieces``' arrays) cut where two pieces in the same pixel cross,
    or where one ends on another (a T-junction): along each part the set of curves beside
    it does not change, so what is seen on either side changes smoothly, and one
    quadrature point stands for the part. Same arrays, more rows."""
    if len(pixel) == 0:  # nothing in view (the group bounds below assume one piece at least)
        return segment, start, end, pixel
    n_pixels = int(pixel.max()) + 1
    if n_pixels <= COUNTING_SPAN * len(pixel):
        order = _counting_order(pixel, n_pixels)
    else:
        order = pixel_order(pixel)
    bounds = _pixel_groups(pixel, order)
    return _split_all(
        np.ascontiguousarray(p0, np.float64), np.ascontiguousarray(p1, np.float64), segment,
        start, end, pixel, order, bounds,
    )  # fmt: skip


def quadrature(p0, p1, segment, start, end):
    """Gauss-Legendre points on the pieces: positions (m * GAUSS_POINTS, 2), their segment,
    and weights (the rule's weight times the piece's length, in pixels, times its
    segment's ``border_share``)."""
    nodes, weights = np.polynomial.legendre.leggauss(GAUSS_POINTS)
    nodes, weights = (nodes + 1.0) / 2.0, weights / 2.0
    t = start[:, None] + (end - start)[:, None] * nodes[None, :]  # (m, g)
    first = np.take(p0, segment, axis=0)  # np.take: a faster gather than p0[segment]
    delta = np.take(p1, segment, axis=0) - first
    length = np.sqrt(np.einsum("ij,ij->i", delta, delta)) * (end - start)
    length = length * border_share(p0, p1)[segment]
    points = first[:, None, :] + t[..., None] * delta[:, None, :]
    return (
        points.reshape(-1, 2),
        np.repeat(segment, GAUSS_POINTS),
        (length[:, None] * weights[None, :]).reshape(-1),
    )


def pixel_step(grad, scale):
    """A gradient (k, 2) with respect to the image-plane (x, y) in pixel units, ``scale``
    (2,) = (2 / W, -2 / H) (x = 2 px / W - 1, y = 1 - 2 py / H): its length in pixel units
    (k,), and the image-plane step (k, 2) that moves a point one pixel along it. On minidiff
    arrays (traced inside ``minidiff.compile`` too); plain arrays give tensors."""
    grad_px = grad * scale
    norm = md.norm(grad_px)
    unit = grad_px / md.reshape(md.where(norm > 0, norm, 1.0), (-1, 1))
    return norm, unit * scale


def pixel_gradient(grad: np.ndarray, width: int, height: int):
    """``pixel_step`` of a plain gradient (k, 2) for a W x H image, as plain arrays."""
    norm, step = pixel_step(grad, np.array([2.0 / width, -2.0 / height]))
    return norm.data, step.data
