"""NumPy kernels: the fast ways minidiff computes a few plain-NumPy expressions.

Nothing here knows about tensors or gradients. Each function computes one ordinary NumPy
expression, named in the first line of its docstring (its *contract*), faster for the
arrays a renderer produces: tall, thin arrays such as 41,000 hit points of 3 coordinates,
and images. The tests (``tests/minidiff/test_kernels.py``) compare every kernel with its
contract; "bit for bit" means the same values (``np.array_equal``), shape and dtype, except
that a sum of zeros may be -0.0 where NumPy gives +0.0 (NumPy starts its sums from +0.0).

Why such arrays are slow in NumPy: its inner loops run along the last axis. When that
axis has length 3 (an xyz or RGB triple), a broadcast operation or a reduction over the
long axis pays a loop set-up per row of 3, and runs 3-15x slower than the same amount of
arithmetic on long rows. The kernels below write a loop over the rows out by hand
(compiled by Numba), or sum one column at a time.

Large outputs are written into arrays from ``buffers.py`` (memory an earlier pass used and
nothing refers to any more) instead of fresh ones: the values are the same, the page faults
of touching new memory on every pass are gone. The largest sums, differences and products
run NumPy's own loop on the threads of ``minidiff.threads``, each on its rows
(``_numpy_loop``): an element is one operation whichever thread computes it.

Only what measurably pays stays here: where NumPy's own operator was as fast in the
renderer (timed alone and in whole forward and backward passes), minidiff uses it.

One trick is deliberately *not* used: BLAS products such as ``ones @ rows`` for column
sums are faster in isolation, but OpenBLAS runs them on several threads whose idle
spinning afterwards halves the speed of the renderer's Numba kernels (measured: a
light-estimation iteration took 44 ms with it, 20 ms without).
"""

from __future__ import annotations

import numpy as np

from minidiff import buffers, jitcache  # noqa: F401  (jitcache: before any kernel is cached)
from minidiff.threads import jit, run_jobs, thread_count

# Below this many elements (both operands together) NumPy's own operators are fast enough:
# the compiled loops and reused memory only pay off on large arrays.
_SMALL = 8192
_FLOATS = (np.float32, np.float64)
# From this many elements of the result on, NumPy's own loop runs on the threads, each on
# its share of the rows (NumPy releases the GIL inside its loops). Measured on 2 cores: a
# (k, 3) * (k, 3) product of 3M elements 2.9 -> 1.6 ms, of 786k (a 512 x 512 image) 0.71
# -> 0.54 ms, of 300k no faster (handing a share to a thread costs ~0.1 ms).
PARALLEL_ELEMENTS = 1 << 19

# ---------------------------------------------------------------------------------------------
# Arithmetic: x + y, x - y, x * y
# ---------------------------------------------------------------------------------------------


def add(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Equals ``x + y`` bit for bit, for any two broadcastable arrays (see ``_arithmetic``)."""
    return _arithmetic(_ADD, np.add, x, y)


def subtract(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Equals ``x - y`` bit for bit, for any two broadcastable arrays (see ``_arithmetic``)."""
    return _arithmetic(_SUBTRACT, np.subtract, x, y)


def multiply(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Equals ``x * y`` bit for bit, for any two broadcastable arrays (see ``_arithmetic``)."""
    return _arithmetic(_MULTIPLY, np.multiply, x, y)


def _arithmetic(code: int, ufunc, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``ufunc(x, y)`` (np.add, np.subtract or np.multiply; ``code`` names it to the compiled
    loops), bit for bit. Shapes: any two broadcastable arrays; NumPy's result shape and dtype.

    Two things make it faster than NumPy's operator, for large arrays of one float dtype:

    * Rows of three: (k, 3) op (k, 1), a colour scaled per hit; (3,) op (k, 3), one point
      minus many; (k, 1) op (3,), an outer product. NumPy runs these 3-10x slower than
      (k, 3) op (k, 3); a compiled loop makes one pass over the rows instead (k = 41k:
      ~25 us against 90-220 us).
    * Reused memory for the result (``buffers.py``): what matters for the image-sized arrays
      of a loss, which fresh would be page-faulted in again on every pass.
    """
    if x.size + y.size < _SMALL or x.dtype != y.dtype or x.dtype not in _FLOATS:
        return ufunc(x, y)  # small, or a result dtype that NumPy's promotion decides
    out = buffers.empty(np.broadcast_shapes(x.shape, y.shape), x.dtype)  # raises as ufunc
    if out.ndim != 2 or out.shape[1] != 3 or x.ndim > 2 or y.ndim > 2:
        return _numpy_loop(ufunc, x, y, out)
    # A role for each operand: 2 the full (k, 3) array, 1 a (k, 1) column, 0 a row.
    k = out.shape[0]
    roles = {(k, 3): 2, (k, 1): 1, (1, 3): 0, (3,): 0}
    role_x, role_y = roles.get(x.shape), roles.get(y.shape)
    if role_x is None or role_y is None or role_x == role_y:
        return _numpy_loop(ufunc, x, y, out)  # e.g. (k, 3) op (k, 3): NumPy's loop is fast
    # The loops take the fuller operand first; ``swap`` tells them that it came second in
    # x op y (a subtraction must keep its order).
    swap = role_y > role_x
    first, second = (y, x) if swap else (x, y)
    second = second.reshape(-1, second.shape[-1])  # (3,) -> (1, 3)
    if max(role_x, role_y) == 1:
        _outer(code, first, second, swap, out)  # (k, 1) with (1, 3)
    elif min(role_x, role_y) == 1:
        _per_row(code, first, second, swap, out)  # (k, 3) with (k, 1)
    else:
        _fixed_row(code, first, second, swap, out)  # (k, 3) with (1, 3)
    return out


def _numpy_loop(ufunc, x: np.ndarray, y: np.ndarray, out: np.ndarray) -> np.ndarray:
    """``ufunc(x, y, out=out)``, by rows (``_by_rows``): each job computes ``ufunc`` on its
    rows of the operands (an operand broadcast along the first axis is passed whole)."""
    rows = out.shape[0]

    def part(first: int, end: int) -> None:
        # an operand with the result's first axis is cut; one broadcast along it is not
        mine = [a[first:end] if a.ndim == out.ndim and a.shape[0] == rows else a for a in (x, y)]
        ufunc(*mine, out=out[first:end])

    _by_rows(rows, out.size, part)
    return out


def _by_rows(rows: int, size: int, part) -> None:
    """``part(first, end)`` over the rows [0, rows) of an array of ``size`` elements: from
    PARALLEL_ELEMENTS elements on, one contiguous share of the rows per thread
    (``minidiff.threads``; NumPy releases the GIL inside its loops, the compiled loops
    here are ``nogil``), else all of them at once. Each element is one operation on its
    own numbers, whichever share holds it: the same bits on any number of threads."""
    n_jobs = min(thread_count(), rows) if size >= PARALLEL_ELEMENTS else 1
    if n_jobs <= 1:
        part(0, rows)
        return
    run_jobs(lambda j, n: part(j * rows // n, (j + 1) * rows // n), n_jobs)


def double_in_place(x: np.ndarray) -> None:
    """``np.add(x, x, out=x)``, by rows on the threads (``_by_rows``) when x is large."""
    if x.ndim == 0:
        np.add(x, x, out=x)
        return
    _by_rows(x.shape[0], x.size, lambda a, b: np.add(x[a:b], x[a:b], out=x[a:b]))


def copy(g, dtype: np.dtype) -> np.ndarray:
    """Equals ``np.array(g, dtype=dtype)`` bit for bit: a copy that aliases nothing. A large
    array of floats is copied into reused memory (``buffers.py``), by rows on the threads
    (``_by_rows``): a gradient of a million rows of three took 3.2 ms on one thread into
    fresh memory (a leaf's first ``.grad``)."""
    dtype = np.dtype(dtype)
    large = isinstance(g, np.ndarray) and g.ndim > 0 and g.size >= PARALLEL_ELEMENTS
    if not large or dtype not in _FLOATS or g.dtype not in _FLOATS:
        return np.array(g, dtype=dtype)
    out = buffers.empty(g.shape, dtype)
    _by_rows(out.shape[0], out.size,
             lambda a, b: np.copyto(out[a:b], g[a:b], casting="unsafe"))  # fmt: skip
    return out


# The operators of the compiled loops, by code. Each is a single IEEE operation, so the
# loops give NumPy's bits. (Division is left to NumPy: its vectorised divide is faster than
# such a loop.)
_ADD, _SUBTRACT, _MULTIPLY = 0, 1, 2


@jit(cache=True, inline="always")
def _apply(code, p, q, swap):
    """p op q, or q op p if ``swap`` (the operator given by its code)."""
    if swap:
        p, q = q, p
    if code == _ADD:
        return p + q
    if code == _SUBTRACT:
        return p - q
    return p * q


@jit(cache=True)
def _per_row(code, full, column, swap, out):
    """out (k, 3) = full (k, 3) op column (k, 1), one pass over the rows."""
    for i in range(out.shape[0]):
        c = column[i, 0]
        for j in range(3):
            out[i, j] = _apply(code, full[i, j], c, swap)


@jit(cache=True)
def _fixed_row(code, full, row, swap, out):
    """out (k, 3) = full (k, 3) op row (1, 3), one pass over the rows."""
    r0, r1, r2 = row[0, 0], row[0, 1], row[0, 2]
    for i in range(out.shape[0]):
        out[i, 0] = _apply(code, full[i, 0], r0, swap)
        out[i, 1] = _apply(code, full[i, 1], r1, swap)
        out[i, 2] = _apply(code, full[i, 2], r2, swap)


@jit(cache=True)
def _outer(code, column, row, swap, out):
    """out (k, 3) = column (k, 1) op row (1, 3), one pass over the rows."""
    r0, r1, r2 = row[0, 0], row[0, 1], row[0, 2]
    for i in range(out.shape[0]):
        c = column[i, 0]
        out[i, 0] = _apply(code, c, r0, swap)
        out[i, 1] = _apply(code, c, r1, swap)
        out[i, 2] = _apply(code, c, r2, swap)


# ---------------------------------------------------------------------------------------------
# Vectors along the last axis: dot and cross products, normalize's projection
# ---------------------------------------------------------------------------------------------


def dot_last(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Equals ``np.sum(a * b, axis=-1)``: bit for bit for 3-vectors, up to rounding otherwise.

    Shapes: (..., n) and (..., n), broadcast against each other; the result is (...).
    For n = 3 (the renderer's case) three products are summed, in the order NumPy sums
    them: ~2x faster than einsum and ~5x faster than ``(a * b).sum(-1)``. Other n use
    ``np.einsum``, whose summation order may differ in the last bit.
    """
    if a.shape[-1] == 3 and b.shape[-1] == 3:
        # (a0 b0 + a1 b1) + a2 b2, into reused buffers.
        shape = np.broadcast_shapes(a.shape[:-1], b.shape[:-1])
        out = buffers.empty(shape, np.result_type(a, b))
        if _rows_of_three(a, b):
            _dot_rows(a, b, out)  # the same operations in one pass over the rows
            return out
        term = buffers.empty(shape, out.dtype)
        np.multiply(a[..., 0], b[..., 0], out=out)
        np.add(out, np.multiply(a[..., 1], b[..., 1], out=term), out=out)
        return np.add(out, np.multiply(a[..., 2], b[..., 2], out=term), out=out)
    return np.einsum("...i,...i->...", *np.broadcast_arrays(a, b))


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Equals ``np.cross(a, b)`` bit for bit, for 3-vectors along the last axis.

    Shapes: (..., 3) and (..., 3), broadcast; the result is their broadcast shape. Written
    out because ``np.cross`` first copies (and moves the axes of) its inputs.
    """
    out = buffers.empty(np.broadcast_shapes(a.shape, b.shape), np.result_type(a, b))
    if _rows_of_three(a, b):
        _cross_rows(a, b, out)  # the same operations in one pass over the rows
        return out
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    term = buffers.empty(out.shape[:-1], out.dtype)
    for j, (p, q, r, s) in enumerate(((a1, b2, a2, b1), (a2, b0, a0, b2), (a0, b1, a1, b0))):
        # out_j = p q - r s, the products formed into reused buffers
        np.multiply(p, q, out=out[..., j])
        np.subtract(out[..., j], np.multiply(r, s, out=term), out=out[..., j])
    return out


def _rows_of_three(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether a and b are both (k, 3) float arrays of one dtype, with k large enough for the
    compiled loops below to pay off (the renderer's hit points, normals and directions)."""
    return (
        a.ndim == 2
        and a.shape == b.shape
        and a.shape[1] == 3
        and a.shape[0] >= _SMALL // 6
        and a.dtype == b.dtype
        and a.dtype in _FLOATS
    )


# NumPy applies each operation of dot_last and cross3 to a whole column of a (k, 3) array, a
# strided pass over memory per operation (5 for a dot product, 9 for a cross product). These
# loops do the same operations, in the same order and precision (no fused multiply-add:
# Numba does not contract without fastmath), row by row in one pass: 3-5x faster for k = 41k.


@jit(cache=True)
def _dot_rows(a, b, out):
    for i in range(a.shape[0]):
        out[i] = a[i, 0] * b[i, 0] + a[i, 1] * b[i, 1] + a[i, 2] * b[i, 2]


@jit(cache=True)
def _cross_rows(a, b, out):
    for i in range(a.shape[0]):
        a0, a1, a2 = a[i, 0], a[i, 1], a[i, 2]
        b0, b1, b2 = b[i, 0], b[i, 1], b[i, 2]
        out[i, 0] = a1 * b2 - a2 * b1
        out[i, 1] = a2 * b0 - a0 * b2
        out[i, 2] = a0 * b1 - a1 * b0


def project_out(y: np.ndarray, g: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Equals ``(g - y * dot_last(y, g)[..., None]) * scale`` bit for bit: g without its
    component along the unit vectors y, scaled (normalize's VJP and JVP).

    Shapes: y and g (..., 3), broadcast against each other; scale broadcastable to them,
    e.g. (..., 1). For (k, 3) rows and a (k, 1) scale, one compiled pass instead of four
    (k = 41k: 2x faster than the expression with ``multiply`` and ``dot_last``).
    """
    if _rows_of_three(y, g) and scale.shape == (y.shape[0], 1) and scale.dtype == y.dtype:
        out = buffers.empty(y.shape, y.dtype)
        _project_out_rows(y, g, scale, out)
        return out
    return multiply(g - multiply(y, dot_last(y, g)[..., None]), scale)


@jit(cache=True)
def _project_out_rows(y, g, scale, out):
    for i in range(y.shape[0]):
        d = y[i, 0] * g[i, 0] + y[i, 1] * g[i, 1] + y[i, 2] * g[i, 2]  # dot_last's order
        s = scale[i, 0]
        for j in range(3):
            out[i, j] = (g[i, j] - y[i, j] * d) * s


# ---------------------------------------------------------------------------------------------
# Rows: gather and scatter
# ---------------------------------------------------------------------------------------------


def gather_rows(x: np.ndarray, index: np.ndarray) -> np.ndarray:
    """Equals ``x[index]`` bit for bit, for a 1-D integer array ``index``.

    Shapes: x (n, ...), index (k,) with values in [-n, n); the result is (k, ...).
    ``np.take`` is ~4x faster than fancy indexing for rows (measured: 41k rows of 3).
    """
    n = x.shape[0]
    if index.size and (index.min() < -n or index.max() >= n):
        bad = index.max() if index.max() >= n else index.min()
        raise IndexError(f"index {bad} is out of bounds for axis 0 with size {n}")
    out = buffers.empty(index.shape + x.shape[1:], x.dtype)
    # mode="wrap" maps [-n, 0) as Python does; it lets np.take write straight into ``out``
    # (with the default mode="raise" it buffers the result first).
    return np.take(x, index, axis=0, out=out, mode="wrap")


def scatter_add_rows(index: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """Equals ``out = np.zeros((n, ...)); np.add.at(out, index, values)``, summed in float64.

    Shapes: index (k,) integers in [0, n), values (k, ...); the result is (n, ...) of
    ``values.dtype``. Repeated indices accumulate, in the order of ``index``. The sums are
    formed in float64 and rounded to ``values.dtype`` once at the end (bit for bit equal to
    ``np.add.at`` on a float64 array, then ``astype``). Float values are added by one
    compiled loop over the rows (``np.add.at`` is unbuffered and slow; the ``np.bincount``
    per column that other dtypes use makes one pass per column).
    """
    # An explicit column count, not -1: reshape cannot infer -1 when there are no rows.
    rows = values.reshape(len(index), int(np.prod(values.shape[1:], dtype=np.int64)))
    cols = rows.shape[1]
    if values.dtype.kind == "f":
        sums = buffers.zeros((n, cols), np.float64)
        if not _add_rows_at(np.ascontiguousarray(index, np.int64), rows, sums):
            raise IndexError(f"scatter_add_rows: an index is outside [0, {n})")
        out = sums if values.dtype == np.float64 else sums.astype(values.dtype)
        return out.reshape((n,) + values.shape[1:])
    out = np.empty((n, cols), dtype=values.dtype)
    if cols <= 4:
        for j in range(cols):
            out[:, j] = np.bincount(index, weights=rows[:, j], minlength=n)
    else:  # one bincount over (row, column) pairs flattened
        flat = (index[:, None] * cols + np.arange(cols)).ravel()
        out[:] = np.bincount(flat, weights=rows.ravel(), minlength=n * cols).reshape(n, cols)
    return out.reshape((n,) + values.shape[1:])


@jit(cache=True)
def _add_rows_at(index, rows, sums):
    """sums[index[i]] += rows[i] for i in order (in float64); False if an index is outside
    sums (nothing is written past it)."""
    n = sums.shape[0]
    for i in range(index.shape[0]):
        r = index[i]
        if r < 0 or r >= n:
            return False
        for j in range(rows.shape[1]):
            sums[r, j] += rows[i, j]
    return True


# ---------------------------------------------------------------------------------------------
# The sums behind unbroadcast
# ---------------------------------------------------------------------------------------------


def sum_rows(rows: np.ndarray) -> np.ndarray:
    """Equals ``rows.sum(axis=0)`` up to rounding: the (m,) column sums of an (n, m) array.

    Bit for bit, up to 8 columns: each column summed on its own, ``[c.sum() for c in
    rows.T]`` (NumPy's pairwise summation along the column, ~15x faster than
    ``rows.sum(axis=0)`` for (41k, 3), and more accurate); beyond 8, ``rows.sum(axis=0)``.
    """
    if rows.shape[1] <= 8:
        out = np.empty(rows.shape[1], dtype=rows.dtype)
        for j in range(rows.shape[1]):
            out[j] = rows[:, j].sum()
        return out
    return rows.sum(axis=0)


def sum_leading_axes(g: np.ndarray, lead: int) -> np.ndarray:
    """Equals ``g.sum(axis=tuple(range(lead)))`` up to rounding (as ``sum_rows``).

    Shapes: g (a1, ..., a_lead, *rest) -> rest. The leading axes are flattened into rows
    and summed with ``sum_rows``.
    """
    # Both sizes explicit: reshape cannot infer a -1 next to a zero-size axis.
    n_rows = int(np.prod(g.shape[:lead], dtype=np.int64))
    rows = g.reshape(n_rows, int(np.prod(g.shape[lead:], dtype=np.int64)))
    return sum_rows(rows).reshape(g.shape[lead:])


def sum_keepdims(g: np.ndarray, axes: tuple[int, ...]) -> np.ndarray:
    """Equals ``g.sum(axis=axes, keepdims=True)`` bit for bit.

    Shapes: g of any shape, ``axes`` non-negative axes of g; the summed axes keep size 1.
    Summing (k, 3) -> (k, 1), e.g. the gradient of a per-hit scalar that scaled an RGB
    colour, is done with two additions: ``.sum(axis=-1)`` over rows of length 3 pays a
    loop set-up per row.
    """
    if axes == (g.ndim - 1,) and g.shape[-1] == 3:
        return (g[..., 0] + g[..., 1] + g[..., 2])[..., None]
    return g.sum(axis=axes, keepdims=True)


# ---------------------------------------------------------------------------------------------
# Clip: the image a loss compares
# ---------------------------------------------------------------------------------------------


def clip(x: np.ndarray, lo, hi) -> np.ndarray:
    """Equals ``np.clip(x, lo, hi)`` bit for bit (into reused memory when lo and hi are
    Python numbers or 0-d arrays of x's dtype: the result then has x's shape and dtype).

    Reused memory is the whole point: a loss clips the whole image, and a fresh image-sized
    array would be page-faulted in on every pass (measured with ``np.clip``: ~1,800 more
    faults per light-estimation iteration at 512x512)."""
    if x.dtype.kind != "f" or x.ndim == 0 or not all(_scalar_of(v, x.dtype) for v in (lo, hi)):
        return np.clip(x, lo, hi)
    out = buffers.empty(x.shape, x.dtype)
    _by_rows(x.shape[0], x.size, lambda a, b: np.clip(x[a:b], lo, hi, out=out[a:b]))
    return out


def pass_where_equal(g: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Equals ``np.where(a == b, g, 0.0)`` bit for bit (into reused memory when g, a and b
    are large float arrays of one shape and dtype): the gradient of clip, maximum and
    minimum passed where the input is what came out.

    ``np.where`` with a scalar branch runs a slow broadcast loop: on a 512x512 RGB image
    it took 1.4 ms, a third of a light-estimation step; one compiled pass takes ~0.2 ms."""
    if not (
        g.shape == a.shape == b.shape
        and g.size >= _SMALL
        and g.dtype == a.dtype == b.dtype
        and g.dtype.type in _FLOATS
    ):
        return np.where(a == b, g, 0.0)
    out = buffers.empty(g.shape, g.dtype)
    flat = [v.reshape(-1) for v in (g, a, b, out)]
    _by_rows(g.size, g.size, lambda i, j: _pass_where_equal(*(v[i:j] for v in flat)))
    return out


@jit(cache=True)
def _pass_where_equal(g, a, b, out):
    for i in range(g.shape[0]):
        out[i] = g[i] if a[i] == b[i] else 0.0


def _scalar_of(v, dtype: np.dtype) -> bool:
    """Whether v leaves np.clip's result dtype at ``dtype``: a Python int or float (NumPy
    treats those as weak), or a 0-d array of that dtype."""
    if isinstance(v, bool):
        return False
    if isinstance(v, int | float):
        return True
    return isinstance(v, np.ndarray) and v.ndim == 0 and v.dtype == dtype
