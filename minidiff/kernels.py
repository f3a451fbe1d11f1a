"""NumPy kernels: the fast ways minidiff computes a few plain-NumPy expressions.

Nothing here knows about tensors or gradients. Each function computes one ordinary NumPy
expression, named in the first line of its docstring (its *contract*), faster for the
shapes a renderer produces: tall, thin arrays such as 41,000 hit points of 3 coordinates.
The tests (``tests/test_minidiff_kernels.py``) compare every kernel with its contract;
"bit for bit" means the same values (``np.array_equal``), shape and dtype, except that a
sum of zeros may be -0.0 where NumPy gives +0.0 (NumPy starts its sums from +0.0).

Why such arrays are slow in NumPy: its inner loops run along the last axis. When that
axis has length 3 (an xyz or RGB triple), a broadcast operation or a reduction over the
long axis pays a loop set-up per row of 3, and runs 3-15x slower than the same amount of
arithmetic on long rows. The kernels below rearrange the work into long loops (one column
at a time) or write a length-3 loop out by hand.

Large outputs are written into arrays from ``buffers.py`` (memory an earlier pass used and
nothing refers to any more) instead of fresh ones: the values are the same, the page faults
of touching new memory on every pass are gone.

One trick is deliberately *not* used: BLAS products such as ``ones @ rows`` for column
sums are faster in isolation, but OpenBLAS runs them on several threads whose idle
spinning afterwards halves the speed of the renderer's Numba kernels (measured: a
light-estimation iteration took 44 ms with it, 20 ms without).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numba
import numpy as np

from minidiff import buffers

# Below this many elements (both operands together) NumPy's own broadcasting is fast enough:
# the column-at-a-time loop only pays off on large arrays.
_SMALL = 8192


def elementwise(op: Callable, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Equals ``op(x, y)`` bit for bit, for a NumPy binary ufunc ``op`` (np.add, np.multiply, ...).

    Shapes: any two broadcastable arrays; the result has the broadcast shape and NumPy's
    result dtype. Faster when the last axis is short (2 to 4) and one operand is broadcast,
    as in (k, 3) * (3,), (k, 1) * (k, 3) or (k, 1) * (3,): those run 3-6x slower in NumPy
    than a plain (k, 3) * (k, 3) (measured for k = 41k), so we apply ``op`` to one output
    column at a time, which gives NumPy long inner loops again; for (k, 3) results of +, -
    and * a compiled loop does all three columns in one pass (``_broadcast_rows``: 45-65 us
    against 100-130 us column by column for k = 41k).
    """
    if x.size + y.size < _SMALL or op not in _FLOAT_TO_FLOAT or x.dtype != y.dtype:
        return op(x, y)  # too small to matter, or a result dtype we do not predict
    shape = np.broadcast_shapes(x.shape, y.shape)
    out = buffers.empty(shape, x.dtype)
    if x.shape == y.shape or x.size == 1 or y.size == 1:
        return op(x, y, out=out)  # NumPy's own loop is fast here
    if shape[-1:] == (3,) and len(shape) == 2 and op in _ROW_OPS and max(x.ndim, y.ndim) <= 2:
        # Rows of three, the renderer's case: one compiled pass, ~2x faster again.
        _broadcast_rows(_ROW_OPS[op], x.reshape(-1, x.shape[-1]), y.reshape(-1, y.shape[-1]), out)
        return out
    if len(shape) < 2 or not 1 < shape[-1] <= 4:
        return op(x, y, out=out)
    for j in range(shape[-1]):
        op(_last_axis_column(x, j), _last_axis_column(y, j), out=out[..., j])
    return out


# The ufuncs whose result has the dtype of two equal float operands (``out`` can be given).
_FLOAT_TO_FLOAT = {np.add, np.subtract, np.multiply, np.divide, np.maximum, np.minimum, np.power}

# The ufuncs ``_broadcast_rows`` applies, by code: single IEEE operations, so a compiled loop
# gives NumPy's bits. (Division is left to NumPy: its vectorised divide is faster than the
# loop's; maximum and minimum would need NumPy's NaN rules.)
_ROW_OPS = {np.add: 0, np.subtract: 1, np.multiply: 2}


@numba.njit(cache=True, inline="always")
def _apply(code, p, q):
    if code == 0:
        return p + q
    if code == 1:
        return p - q
    return p * q


@numba.njit(cache=True)
def _broadcast_rows(code, x, y, out):
    """out (k, 3) = x op y for x and y each (k, 3), (k, 1) or (1, 3), not both the same
    shape (``_ROW_OPS``). One loop per pattern, each a single pass over the rows: NumPy's
    column-at-a-time passes stride through memory three times."""
    k = out.shape[0]
    x_rows, y_rows = x.shape[0] == k, y.shape[0] == k
    x_full, y_full = x_rows and x.shape[1] == 3, y_rows and y.shape[1] == 3
    if x_full and y_rows:  # (k, 3) op (k, 1): e.g. vectors scaled per row
        for i in range(k):
            c = y[i, 0]
            for j in range(3):
                out[i, j] = _apply(code, x[i, j], c)
    elif y_full and x_rows:  # (k, 1) op (k, 3)
        for i in range(k):
            c = x[i, 0]
            for j in range(3):
                out[i, j] = _apply(code, c, y[i, j])
    elif y_full:  # (1, 3) op (k, 3): e.g. one point minus many
        x0, x1, x2 = x[0, 0], x[0, 1], x[0, 2]
        for i in range(k):
            out[i, 0] = _apply(code, x0, y[i, 0])
            out[i, 1] = _apply(code, x1, y[i, 1])
            out[i, 2] = _apply(code, x2, y[i, 2])
    elif x_full:  # (k, 3) op (1, 3)
        y0, y1, y2 = y[0, 0], y[0, 1], y[0, 2]
        for i in range(k):
            out[i, 0] = _apply(code, x[i, 0], y0)
            out[i, 1] = _apply(code, x[i, 1], y1)
            out[i, 2] = _apply(code, x[i, 2], y2)
    elif x_rows:  # (k, 1) op (1, 3): an outer product
        y0, y1, y2 = y[0, 0], y[0, 1], y[0, 2]
        for i in range(k):
            c = x[i, 0]
            out[i, 0] = _apply(code, c, y0)
            out[i, 1] = _apply(code, c, y1)
            out[i, 2] = _apply(code, c, y2)
    else:  # (1, 3) op (k, 1)
        x0, x1, x2 = x[0, 0], x[0, 1], x[0, 2]
        for i in range(k):
            c = y[i, 0]
            out[i, 0] = _apply(code, x0, c)
            out[i, 1] = _apply(code, x1, c)
            out[i, 2] = _apply(code, x2, c)


def clip(x: np.ndarray, lo, hi) -> np.ndarray:
    """Equals ``np.clip(x, lo, hi)`` bit for bit (into reused memory when lo and hi are
    Python numbers or 0-d arrays of x's dtype: the result then has x's shape and dtype)."""
    if x.dtype.kind != "f" or not all(_scalar_of(v, x.dtype) for v in (lo, hi)):
        return np.clip(x, lo, hi)
    return np.clip(x, lo, hi, out=buffers.empty(x.shape, x.dtype))


def _scalar_of(v, dtype: np.dtype) -> bool:
    """Whether v leaves np.clip's result dtype at ``dtype``: a Python int or float (NumPy
    treats those as weak), or a 0-d array of that dtype."""
    if isinstance(v, bool):
        return False
    if isinstance(v, int | float):
        return True
    return isinstance(v, np.ndarray) and v.ndim == 0 and v.dtype == dtype


def where(condition: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Equals ``np.where(condition, a, b)`` bit for bit, for arrays a and b (into reused
    memory when the result is a large float array: b copied, then a where the condition
    holds)."""
    dtype = np.result_type(a, b)
    shape = np.broadcast_shapes(condition.shape, a.shape, b.shape)
    if dtype.kind != "f" or math.prod(shape) < _SMALL:
        return np.where(condition, a, b)
    out = buffers.empty(shape, dtype)
    np.copyto(out, b)
    np.copyto(out, a, where=condition)
    return out


def zeros_like(x: np.ndarray) -> np.ndarray:
    """Equals ``np.zeros_like(x)`` (into reused memory for large arrays)."""
    return buffers.zeros(x.shape, x.dtype)


def negative(x: np.ndarray) -> np.ndarray:
    """Equals ``-x`` bit for bit (into reused memory for large float arrays)."""
    if x.dtype.kind != "f" or x.size < _SMALL:
        return -x
    return np.negative(x, out=buffers.empty(x.shape, x.dtype))


def _last_axis_column(x: np.ndarray, j: int) -> np.ndarray:
    """Column j of x along the last axis, or its only column if x is broadcast there."""
    if x.ndim == 0:
        return x
    return x[..., j] if x.shape[-1] > 1 else x[..., 0]


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
        and a.dtype in (np.float32, np.float64)
    )


# NumPy applies each operation of dot_last and cross3 to a whole column of a (k, 3) array, a
# strided pass over memory per operation (5 for a dot product, 9 for a cross product). These
# loops do the same operations, in the same order and precision (no fused multiply-add:
# Numba does not contract without fastmath), row by row in one pass: 3-5x faster for k = 41k.


@numba.njit(cache=True)
def _dot_rows(a, b, out):
    for i in range(a.shape[0]):
        out[i] = a[i, 0] * b[i, 0] + a[i, 1] * b[i, 1] + a[i, 2] * b[i, 2]


@numba.njit(cache=True)
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
    e.g. (..., 1). For (k, 3) rows and a (k, 1) scale, one compiled pass instead of four.
    """
    if _rows_of_three(y, g) and scale.shape == (y.shape[0], 1) and scale.dtype == y.dtype:
        out = buffers.empty(y.shape, y.dtype)
        _project_out_rows(y, g, scale, out)
        return out
    along = elementwise(np.multiply, y, dot_last(y, g)[..., None])
    return elementwise(np.multiply, elementwise(np.subtract, g, along), scale)


@numba.njit(cache=True)
def _project_out_rows(y, g, scale, out):
    for i in range(y.shape[0]):
        d = y[i, 0] * g[i, 0] + y[i, 1] * g[i, 1] + y[i, 2] * g[i, 2]  # dot_last's order
        s = scale[i, 0]
        for j in range(3):
            out[i, j] = (g[i, j] - y[i, j] * d) * s


def dot_vjp(g: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Equals ``(g[..., None] * b, g[..., None] * a)`` bit for bit: both gradients of a dot
    product a . b along the last axis, for the upstream gradient g (...).

    For (k,) g and (k, 3) rows a and b, one compiled pass makes both.
    """
    if _rows_of_three(a, b) and g.shape == a.shape[:1] and g.dtype == a.dtype:
        out_a, out_b = buffers.empty(a.shape, a.dtype), buffers.empty(a.shape, a.dtype)
        _dot_vjp_rows(g, a, b, out_a, out_b)
        return out_a, out_b
    g = g[..., None]
    return elementwise(np.multiply, g, b), elementwise(np.multiply, g, a)


@numba.njit(cache=True)
def _dot_vjp_rows(g, a, b, out_a, out_b):
    for i in range(g.shape[0]):
        c = g[i]
        for j in range(3):
            out_a[i, j] = c * b[i, j]
            out_b[i, j] = c * a[i, j]


def cross_vjp(g: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Equals ``(cross3(b, g), cross3(g, a))`` bit for bit: both gradients of a x b for the
    upstream gradient g (..., 3). For (k, 3) rows, one compiled pass makes both."""
    if _rows_of_three(a, b) and g.shape == a.shape and g.dtype == a.dtype:
        out_a, out_b = buffers.empty(a.shape, a.dtype), buffers.empty(a.shape, a.dtype)
        _cross_vjp_rows(g, a, b, out_a, out_b)
        return out_a, out_b
    return cross3(b, g), cross3(g, a)


@numba.njit(cache=True)
def _cross_vjp_rows(g, a, b, out_a, out_b):
    for i in range(g.shape[0]):
        a0, a1, a2 = a[i, 0], a[i, 1], a[i, 2]
        b0, b1, b2 = b[i, 0], b[i, 1], b[i, 2]
        g0, g1, g2 = g[i, 0], g[i, 1], g[i, 2]
        out_a[i, 0] = b1 * g2 - b2 * g1  # b x g
        out_a[i, 1] = b2 * g0 - b0 * g2
        out_a[i, 2] = b0 * g1 - b1 * g0
        out_b[i, 0] = g1 * a2 - g2 * a1  # g x a
        out_b[i, 1] = g2 * a0 - g0 * a2
        out_b[i, 2] = g0 * a1 - g1 * a0


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


def matmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Equals ``a @ b`` bit for bit (NumPy's matmul, into a reused array for 2-D operands)."""
    if a.ndim != 2 or b.ndim != 2 or a.shape[1] != b.shape[0]:
        return a @ b
    return np.matmul(a, b, out=buffers.empty((a.shape[0], b.shape[1]), np.result_type(a, b)))


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


@numba.njit(cache=True)
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
