"""minidiff.kernels: every kernel equals the plain NumPy expression its docstring names
(``np.array_equal``: the same values, shape and dtype; +0.0 and -0.0 count as equal), on
shapes and values drawn by hypothesis.

The renderer's golden images and gradients (tests/render/test_golden.py) depend on these being
exact: a kernel that is "close" would change the last bits of every image.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from minidiff import kernels

DTYPES = st.sampled_from([np.float32, np.float64])
#: Shapes for the element-wise kernels: small ones (0 to 3 axes) or a large one, which takes
#: the compiled loops and reused memory.
SMALL_OR_LARGE = st.one_of(
    hnp.array_shapes(min_dims=0, max_dims=3, max_side=40), st.just((30_000, 3))
)
# Each arithmetic kernel and the NumPy operator it equals.
ARITHMETIC = [
    (kernels.add, np.add),
    (kernels.subtract, np.subtract),
    (kernels.multiply, np.multiply),
]


def assert_identical(got: np.ndarray, expected: np.ndarray) -> None:
    """Same shape, same dtype, same values (NaN where NaN)."""
    assert got.shape == expected.shape, (got.shape, expected.shape)
    assert got.dtype == expected.dtype, (got.dtype, expected.dtype)
    np.testing.assert_array_equal(got, expected)


def values(rng: np.random.Generator, shape, dtype) -> np.ndarray:
    """Normal values with some exact zeros and negative zeros (sign bits must match too)."""
    x = rng.normal(size=shape)
    x[rng.uniform(size=shape) < 0.05] = 0.0
    x[rng.uniform(size=shape) < 0.05] = -0.0
    return x.astype(dtype)


# ---------------------------------------------------------------------------------------------
# add, subtract, multiply: equal x + y, x - y, x * y
# ---------------------------------------------------------------------------------------------


@st.composite
def tall_broadcast_pairs(draw):
    """Two shapes that broadcast to (..., k, n) with a short last axis n (mostly 3) and a
    large k (the compiled loops need at least 8192 elements), one of them broadcast along
    some axis. Without leading axes and with n = 3: the renderer's rows of three."""
    lead = draw(st.lists(st.integers(1, 3), max_size=1))
    k = draw(st.integers(2800, 9000))
    n = draw(st.sampled_from([3, 3, 2, 4]))
    full = (*lead, k, n)
    patterns = [
        (full, (n,)),  # (k, 3) op (3,): a point minus many points
        (full, (*lead, k, 1)),  # (k, 3) op (k, 1): an RGB colour scaled per hit
        ((*lead, k, 1), (n,)),  # (k, 1) op (3,): an outer product
        ((1, n), full),
        ((*lead, k, 1), full),
    ]
    a, b = draw(st.sampled_from(patterns))
    return (a, b) if draw(st.booleans()) else (b, a)


@settings(max_examples=40, deadline=None)
@given(
    shapes=tall_broadcast_pairs(),
    ops=st.sampled_from(ARITHMETIC),
    dtype=DTYPES,
    seed=st.integers(0, 2**16),
)
def test_arithmetic_of_tall_arrays_equals_numpy(shapes, ops, dtype, seed):
    """Bit-identical to NumPy's own broadcasting, shape and dtype included."""
    kernel, ufunc = ops
    rng = np.random.default_rng(seed)
    x = rng.uniform(0.5, 2.0, shapes[0]).astype(dtype)
    y = rng.uniform(0.5, 2.0, shapes[1]).astype(dtype)
    assert_identical(kernel(x, y), ufunc(x, y))


ROW_PATTERNS = [((9000, 3), (9000, 1)), ((9000, 1), (9000, 3)), ((3,), (9000, 3))]
ROW_PATTERNS += [((9000, 3), (1, 3)), ((9000, 1), (3,)), ((1, 3), (9000, 1))]


@settings(max_examples=40, deadline=None)
@given(
    shapes=st.one_of(
        tall_broadcast_pairs(),
        hnp.mutually_broadcastable_shapes(num_shapes=2, min_dims=1, max_dims=3, max_side=30)
        .map(lambda b: b.input_shapes)
        .filter(lambda s: sum(np.prod(x) for x in s) >= 8192),
    ),
    ops=st.sampled_from(ARITHMETIC),
    dtype=DTYPES,
    threads=st.integers(2, 5),
    seed=st.integers(0, 2**16),
)
def test_arithmetic_split_among_threads_equals_numpy(shapes, ops, dtype, threads, seed):
    """From ``kernels.PARALLEL_ELEMENTS`` on (here lowered to 0), NumPy's loop runs on the
    threads, each on its rows of the result (an operand broadcast along the first axis
    passed whole): bit for bit NumPy's result, on any number of threads, however the
    operands broadcast."""
    from minidiff.threads import using_threads

    kernel, ufunc = ops
    rng = np.random.default_rng(seed)
    x, y = (values(rng, shape, dtype) for shape in shapes)
    saved = kernels.PARALLEL_ELEMENTS
    kernels.PARALLEL_ELEMENTS = 0
    try:
        with using_threads(threads):
            got = kernel(x, y)
    finally:
        kernels.PARALLEL_ELEMENTS = saved
    assert_identical(got, ufunc(x, y))


@pytest.mark.parametrize("ops", ARITHMETIC)
@pytest.mark.parametrize("shapes", ROW_PATTERNS)
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_arithmetic_rows_of_three_keep_every_bit(ops, shapes, dtype):
    """The compiled (k, 3) loops on special values too: signed zeros, infinities, NaN,
    subnormals and huge values (their overflow to inf), against NumPy bit for bit."""
    kernel, ufunc = ops
    rng = np.random.default_rng(7)
    info = np.finfo(dtype)
    special = np.array(
        [0.0, -0.0, np.inf, -np.inf, np.nan, info.smallest_subnormal, info.max, -1.5], dtype
    )

    def draw(shape):
        x = rng.uniform(-3, 3, shape).astype(dtype)
        x.flat[rng.integers(0, x.size, x.size // 4)] = rng.choice(special, x.size // 4)
        return x

    x, y = draw(shapes[0]), draw(shapes[1])
    with np.errstate(all="ignore"):
        got, want = kernel(x, y), ufunc(x, y)
    assert got.shape == want.shape and got.dtype == want.dtype
    assert np.array_equal(got.view(np.uint8), want.view(np.uint8))  # NaN and -0.0 included


@settings(max_examples=40, deadline=None)
@given(
    shapes=hnp.mutually_broadcastable_shapes(num_shapes=2, max_dims=3, max_side=5),
    ops=st.sampled_from(ARITHMETIC),
    dtypes=st.tuples(DTYPES, DTYPES),
    seed=st.integers(0, 2**16),
)
def test_arithmetic_of_small_and_mixed_dtypes_equals_numpy(shapes, ops, dtypes, seed):
    """NumPy's own operator (small arrays) and mixed float32/float64 operands."""
    kernel, ufunc = ops
    rng = np.random.default_rng(seed)
    x = rng.uniform(0.5, 2.0, shapes.input_shapes[0]).astype(dtypes[0])
    y = rng.uniform(0.5, 2.0, shapes.input_shapes[1]).astype(dtypes[1])
    assert_identical(np.asarray(kernel(x, y)), np.asarray(ufunc(x, y)))


# ---------------------------------------------------------------------------------------------
# dot_last, cross3, gather_rows
# ---------------------------------------------------------------------------------------------

TALL_PAIRS = [((4000, 3), (4000, 3)), ((4000, 3), (3,)), ((3,), (50, 3)), ((2, 7, 3), (7, 3))]


@settings(max_examples=40, deadline=None)
@given(shapes=st.sampled_from(TALL_PAIRS), dtype=DTYPES, seed=st.integers(0, 2**16))
def test_dot_last_of_3_vectors_equals_numpy_sum(shapes, dtype, seed):
    rng = np.random.default_rng(seed)
    a, b = values(rng, shapes[0], dtype), values(rng, shapes[1], dtype)
    assert_identical(kernels.dot_last(a, b), np.sum(a * b, axis=-1))


@settings(max_examples=30, deadline=None)
@given(
    n=st.integers(1, 9).filter(lambda n: n != 3),
    rows=st.integers(0, 20),
    seed=st.integers(0, 2**16),
)
def test_dot_last_of_other_lengths_equals_numpy_sum_up_to_rounding(n, rows, seed):
    rng = np.random.default_rng(seed)
    a, b = values(rng, (rows, n), np.float64), values(rng, (n,), np.float64)
    got = kernels.dot_last(a, b)
    assert got.shape == (rows,)
    np.testing.assert_allclose(got, np.sum(a * b, axis=-1), rtol=1e-13, atol=1e-13)


@settings(max_examples=40, deadline=None)
@given(
    rows=st.sampled_from([4000, 1500, 7]),
    scale_shape=st.sampled_from(["column", "scalar"]),
    dtype=DTYPES,
    seed=st.integers(0, 2**16),
)
def test_project_out_equals_its_numpy_expression(rows, scale_shape, dtype, seed):
    """The compiled pass ((k, 3) rows, (k, 1) scale) and the fallback (small k, other
    scales) against the plain expression, bit for bit."""
    rng = np.random.default_rng(seed)
    y, g = values(rng, (rows, 3), dtype), values(rng, (rows, 3), dtype)
    scale = values(rng, (rows, 1) if scale_shape == "column" else (), dtype)
    along = y * np.sum(y * g, axis=-1)[..., None]
    assert_identical(kernels.project_out(y, g, scale), (g - along) * scale)


@settings(max_examples=40, deadline=None)
@given(shapes=st.sampled_from(TALL_PAIRS), dtype=DTYPES, seed=st.integers(0, 2**16))
def test_cross3_equals_numpy_cross(shapes, dtype, seed):
    rng = np.random.default_rng(seed)
    a, b = values(rng, shapes[0], dtype), values(rng, shapes[1], dtype)
    assert_identical(kernels.cross3(a, b), np.cross(a, b))


@settings(max_examples=30, deadline=None)
@given(
    n=st.integers(1, 50),
    trailing=hnp.array_shapes(min_dims=0, max_dims=2, max_side=4),
    k=st.integers(0, 100),
    seed=st.integers(0, 2**16),
)
def test_gather_rows_equals_fancy_indexing(n, trailing, k, seed):
    rng = np.random.default_rng(seed)
    x = values(rng, (n, *trailing), np.float64)
    index = rng.integers(-n, n, size=k)
    assert_identical(kernels.gather_rows(x, index), x[index])


@pytest.mark.parametrize(
    "dtypes", [(np.float32, np.float32), (np.float64, np.float64), (np.float32, np.float64)]
)
def test_dot_and_cross_of_strided_rows_equal_numpy(dtypes):
    # Views with row and column strides (the compiled row loops take any strides) and a
    # mixed pair (NumPy's column path).
    rng = np.random.default_rng(5)
    a = values(rng, (8000, 5), dtypes[0])[::2, 1:4]
    b = values(rng, (4000, 3), dtypes[1])[::-1]
    assert_identical(kernels.dot_last(a, b), np.sum(a * b, axis=-1))
    assert_identical(kernels.cross3(a, b), np.cross(a, b))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_large_gathers_and_products_equal_numpy(dtype):
    # Large enough for reused output arrays (minidiff.buffers); two calls, the first result
    # kept, so the second cannot write into it.
    rng = np.random.default_rng(3)
    x = values(rng, (30_000, 3), dtype)
    index = rng.integers(-30_000, 30_000, size=40_000)
    first = kernels.gather_rows(x, index)
    assert_identical(kernels.gather_rows(x, index[::-1]), x[index[::-1]])
    assert_identical(first, x[index])
    first = kernels.multiply(x, x)
    assert_identical(kernels.multiply(x[::-1], x), x[::-1] * x)
    assert_identical(first, x * x)


@settings(max_examples=40, deadline=None)
@given(
    shape=SMALL_OR_LARGE,
    dtype=st.sampled_from([np.float32, np.float64, np.int64]),
    bounds=st.sampled_from([(0.0, 1.0), (0, 1), (-0.5, 0.25), ("a0", "a1"), ("v", "v")]),
    seed=st.integers(0, 2**16),
)
def test_clip_equals_numpy(shape, dtype, bounds, seed):
    # Bounds: Python floats or ints, 0-d arrays of x's dtype ("a0", "a1"), or arrays that
    # broadcast against x ("v").
    rng = np.random.default_rng(seed)
    x = values(rng, shape, np.float64) * 2
    x = x.astype(dtype) if dtype != np.int64 else np.round(x * 10).astype(np.int64)
    if bounds == ("a0", "a1"):
        lo, hi = np.array(-0.5, dtype=x.dtype), np.array(0.5, dtype=x.dtype)
    elif bounds == ("v", "v"):
        lo, hi = -np.abs(values(rng, shape[-1:], np.float64)), np.ones(shape[-1:])
    else:
        lo, hi = bounds
    first = kernels.clip(x, lo, hi)
    assert_identical(kernels.clip(x[::-1] if x.ndim else x, lo, hi),
                     np.clip(x[::-1] if x.ndim else x, lo, hi))  # fmt: skip
    assert_identical(first, np.clip(x, lo, hi))


@settings(max_examples=40, deadline=None)
@given(
    shape=SMALL_OR_LARGE,
    dtype=DTYPES,
    strided=st.booleans(),
    seed=st.integers(0, 2**16),
)
def test_pass_where_equal_equals_numpy(shape, dtype, strided, seed):
    # a == b where a is b clipped (the clip VJP), with NaN (never equal) and -0.0 == 0.0
    # among the values.
    rng = np.random.default_rng(seed)
    b = (values(rng, shape, np.float64) * 2).astype(dtype)
    if b.size:
        b.reshape(-1)[:: max(1, b.size // 7)] = np.nan
        b.reshape(-1)[1 :: max(1, b.size // 5)] = -0.0
    a = np.clip(b, np.asarray(-0.5, dtype), np.asarray(0.5, dtype))
    g = (values(rng, shape, np.float64) * 3).astype(dtype)
    if strided and b.ndim:
        a, b, g = a[::-1], b[::-1], g[::-1]
    first = kernels.pass_where_equal(g, a, b)
    assert_identical(kernels.pass_where_equal(g, a, b), np.where(a == b, g, 0.0))
    assert_identical(first, np.where(a == b, g, 0.0))


@pytest.mark.parametrize("bad", [5, -6, 100])
def test_gather_rows_out_of_range_raises(bad):
    with pytest.raises(IndexError, match=f"index {bad} is out of bounds for axis 0 with size 5"):
        kernels.gather_rows(np.zeros((5, 3)), np.array([0, bad]))


# ---------------------------------------------------------------------------------------------
# scatter_add_rows: equals np.add.at in float64, rounded once
# ---------------------------------------------------------------------------------------------


@settings(max_examples=40, deadline=None)
@given(
    n=st.integers(1, 30),
    trailing=hnp.array_shapes(min_dims=0, max_dims=2, max_side=4),  # both paths: <= 4, > 4
    k=st.integers(0, 200),
    dtype=DTYPES,
    seed=st.integers(0, 2**16),
)
def test_scatter_add_rows_equals_add_at_in_float64(n, trailing, k, dtype, seed):
    rng = np.random.default_rng(seed)
    index = rng.integers(0, n, size=k)  # with repeats
    v = values(rng, (k, *trailing), dtype)
    expected = np.zeros((n, *trailing))
    np.add.at(expected, index, v.astype(np.float64))
    assert_identical(kernels.scatter_add_rows(index, v, n), expected.astype(dtype))


@settings(max_examples=40, deadline=None)
@given(
    n=st.integers(1, 300),
    trailing=hnp.array_shapes(min_dims=0, max_dims=2, max_side=4),
    fraction=st.floats(0.0, 1.0),
    dtype=DTYPES,
    seed=st.integers(0, 2**16),
)
def test_scatter_add_rows_with_distinct_indices_is_add_at_bit_for_bit(
    n, trailing, fraction, dtype, seed
):
    """No index repeats (a renderer putting each hit's colour into its pixel): the same bits
    as np.add.at from zeros, sign of zero included (0.0 + -0.0 = +0.0)."""
    rng = np.random.default_rng(seed)
    index = rng.permutation(n)[: int(fraction * n)]
    v = values(rng, (len(index), *trailing), dtype)
    expected = np.zeros((n, *trailing))
    np.add.at(expected, index, v.astype(np.float64))
    got = kernels.scatter_add_rows(index, v, n)
    assert_identical(got, expected.astype(dtype))
    np.testing.assert_array_equal(np.signbit(got), np.signbit(expected.astype(dtype)))


def test_scatter_add_rows_of_other_dtypes_and_bad_indices():
    index = np.array([2, 0, 2])
    ints = np.array([[1, 2], [3, 4], [5, 6]])
    expected = np.zeros((3, 2), np.int64)
    np.add.at(expected, index, ints)
    assert_identical(kernels.scatter_add_rows(index, ints, 3), expected)  # bincount path
    for bad in ([0, 3, 1], [0, -1, 1]):
        with pytest.raises(IndexError, match=r"outside \[0, 3\)"):
            kernels.scatter_add_rows(np.array(bad), np.ones((3, 2)), 3)


# ---------------------------------------------------------------------------------------------
# The sums behind unbroadcast
# ---------------------------------------------------------------------------------------------


@settings(max_examples=40, deadline=None)
@given(
    rows=st.integers(0, 30000), cols=st.integers(1, 12), dtype=DTYPES, seed=st.integers(0, 2**16)
)
def test_sum_rows_equals_column_sums(rows, cols, dtype, seed):
    """Bit for bit: each column summed on its own up to 8 columns, rows.sum(axis=0) beyond;
    and always rows.sum(axis=0) up to rounding."""
    r = values(np.random.default_rng(seed), (rows, cols), dtype)
    got = kernels.sum_rows(r)
    if cols <= 8:
        assert_identical(got, np.array([column.sum() for column in r.T], dtype=dtype))
    else:
        assert_identical(got, r.sum(axis=0))
    tol = 1e-4 if dtype == np.float32 else 1e-11
    np.testing.assert_allclose(got, r.sum(axis=0), rtol=tol, atol=tol * max(1, rows) ** 0.5)


@settings(max_examples=30, deadline=None)
@given(shape=hnp.array_shapes(min_dims=1, max_dims=4, min_side=0, max_side=6), data=st.data())
def test_sum_leading_axes_equals_numpy_sum(shape, data):
    lead = data.draw(st.integers(1, len(shape)))
    g = values(np.random.default_rng(0), shape, np.float64)
    got = kernels.sum_leading_axes(g, lead)
    expected = g.sum(axis=tuple(range(lead)))
    assert got.shape == expected.shape and got.dtype == expected.dtype
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-12)


@settings(max_examples=40, deadline=None)
@given(
    shape=hnp.array_shapes(min_dims=1, max_dims=3, min_side=1, max_side=5),
    last3=st.booleans(),
    data=st.data(),
    dtype=DTYPES,
)
def test_sum_keepdims_equals_numpy_sum(shape, last3, data, dtype):
    if last3:  # the written-out (k, 3) -> (k, 1) case, with many rows
        shape = (*shape[:-1], 5000, 3)
    ndim = len(shape)
    axes = tuple(sorted(data.draw(st.sets(st.integers(0, ndim - 1), min_size=1))))
    if last3 and data.draw(st.booleans()):
        axes = (ndim - 1,)
    g = values(np.random.default_rng(1), shape, dtype)
    assert_identical(kernels.sum_keepdims(g, axes), g.sum(axis=axes, keepdims=True))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_sum_keepdims_last3_differs_from_numpy_only_in_the_sign_of_zero(dtype):
    """The one difference the contract allows: NumPy starts a sum from +0.0, so three
    negative zeros sum to +0.0 there and to -0.0 here. Equal values all the same."""
    g = np.array([[-0.0, -0.0, -0.0], [0.0, -0.0, -0.0], [1.0, -1.0, -0.0]], dtype=dtype)
    got = kernels.sum_keepdims(g, (1,))
    expected = g.sum(axis=1, keepdims=True)
    assert_identical(got, expected)
    np.testing.assert_array_equal(np.signbit(got), [[True], [False], [False]])
    np.testing.assert_array_equal(np.signbit(expected), [[False], [False], [False]])


@settings(max_examples=40, deadline=None)
@given(
    shape=hnp.array_shapes(min_dims=1, max_dims=3, max_side=40),
    source=st.sampled_from([np.float32, np.float64, np.int64]),
    target=st.sampled_from([np.float32, np.float64]),
    threads=st.integers(1, 5),
    reversed_rows=st.booleans(),
    seed=st.integers(0, 2**16),
)
def test_copy_equals_numpys_copy_and_aliases_nothing(
    shape, source, target, threads, reversed_rows, seed
):
    """``kernels.copy`` (a leaf's first ``.grad``): ``np.array(g, dtype)`` bit for bit
    (signs of zeros, NaN, a cast down to float32 included), from any view, with its rows
    split among any number of threads (``PARALLEL_ELEMENTS`` lowered to 0), never sharing
    memory with ``g``."""
    from minidiff.threads import using_threads

    rng = np.random.default_rng(seed)
    g = values(rng, shape, source)
    if np.dtype(source).kind == "f" and g.size:
        g.flat[rng.integers(0, g.size)] = np.nan
    if reversed_rows:
        g = g[::-1]
    saved = kernels.PARALLEL_ELEMENTS
    kernels.PARALLEL_ELEMENTS = 0
    try:
        with using_threads(threads):
            got = kernels.copy(g, target)
    finally:
        kernels.PARALLEL_ELEMENTS = saved
    want = np.array(g, dtype=target)
    assert got.shape == want.shape and got.dtype == want.dtype
    assert got.tobytes() == want.tobytes()  # every bit, the signs of zeros and NaN's too
    assert not np.shares_memory(got, g)


@settings(max_examples=40, deadline=None)
@given(
    shape=SMALL_OR_LARGE,
    dtype=DTYPES,
    threads=st.integers(2, 5),
    seed=st.integers(0, 2**16),
)
def test_clip_its_gradient_and_doubling_split_among_threads_equal_numpy(
    shape, dtype, threads, seed
):
    """From ``kernels.PARALLEL_ELEMENTS`` on (here lowered to 0) the loss's clip, the
    clip's VJP and the squared error's doubling run by rows on the threads
    (``kernels._by_rows``): NumPy's bits (signs of zeros and NaN included) on any number
    of threads."""
    from minidiff.threads import using_threads

    rng = np.random.default_rng(seed)
    x = np.asarray(values(rng, shape, np.float64) * 2, dtype)
    if x.size:
        x.reshape(-1)[:: max(1, x.size // 7)] = np.nan
    g = np.asarray(values(rng, shape, np.float64) * 3, dtype)
    saved = kernels.PARALLEL_ELEMENTS
    kernels.PARALLEL_ELEMENTS = 0
    try:
        with using_threads(threads):
            clipped = kernels.clip(x, -0.5, 0.5)
            passed = kernels.pass_where_equal(g, clipped, x)
            doubled = g.copy()
            kernels.double_in_place(doubled)
    finally:
        kernels.PARALLEL_ELEMENTS = saved
    want = np.clip(x, -0.5, 0.5)
    for got, expected in ((clipped, want), (passed, np.where(want == x, g, 0.0)),
                          (doubled, g + g)):  # fmt: skip
        assert got.shape == expected.shape and got.dtype == expected.dtype
        assert got.tobytes() == expected.tobytes()
