"""Every minidiff primitive: forward values against NumPy, and tape gradients against central
finite differences (the paper's Eq. 3 relative error), on shapes and values drawn by
hypothesis.

How a gradient is checked: for f(x, ...) with output shape S, the scalar loss is
``sum(f(x, ...) * W)`` with a fixed random W of shape S, so every output element contributes
with its own weight (a plain ``sum`` would let errors that cancel across elements hide).
``md.check_grad`` compares the tape gradient of that loss with central differences
(eps = 1e-6) in float64 and returns ||g_ad - g_fd|| / (||g_fd|| + 1e-8), which must be
below 1e-6.

Values are drawn well conditioned: away from kinks (abs, maximum, minimum, clip, max),
singularities (log, sqrt, divide, tan) and zero-length vectors (norm, normalize), with a
margin much larger than eps, so that finite differences are themselves accurate. They are
also kept away from points where the whole gradient vanishes (cos at 0, a^b at a = 1 or
b = 0): there Eq. 3 divides finite-difference rounding noise (~1e-11) by ~1e-8 and fails
although nothing is wrong.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

import minidiff as md
from minidiff.tensor import record
from tests.minidiff.test_kernels import tall_broadcast_pairs

SETTINGS = settings(max_examples=30, deadline=None)
TOL = 1e-6
EPS = 1e-6


# ---------------------------------------------------------------------------------------------
# Helpers
# ---------------------------------------------------------------------------------------------


def projected_loss(f, args, seed=0):
    """loss(*args) = sum(f(*args) * W), W a fixed random array of f's output shape."""
    with md.no_grad():
        out_shape = f(*[md.tensor(a) for a in args]).shape
    weights = np.random.default_rng(seed).normal(size=out_shape)
    return lambda *a: md.sum(f(*a) * weights)


def assert_grad_matches(f, *args, argnums=0, tol=TOL):
    """The tape gradient of sum(f(*args) * W) matches finite differences (Eq. 3 < tol)."""
    loss = projected_loss(f, args)
    rel, g_ad, g_fd = md.check_grad(loss, *args, eps=EPS, argnums=argnums)
    assert rel < tol, f"relative error {rel:.2e}\nAD:\n{g_ad}\nFD:\n{g_fd}"


def floats(lo, hi):
    # No subnormals (below 2.2e-308): their products underflow, and rounding alone then
    # breaks the checks' relative tolerances (e.g. multiply at (0, 5e-324): 0.33).
    return st.floats(lo, hi, allow_nan=False, allow_infinity=False, allow_subnormal=False)


def arrays(shape, lo=-2.0, hi=2.0):
    return hnp.arrays(np.float64, shape, elements=floats(lo, hi))


def away_from_zero(shape, lo=0.3, hi=2.0):
    """Values with lo <= |x| <= hi (either sign): no kink of abs, no pole of 1/x."""
    magnitudes = hnp.arrays(np.float64, shape, elements=floats(lo, hi))
    signs = hnp.arrays(np.float64, shape, elements=st.sampled_from([-1.0, 1.0]))
    return st.builds(np.multiply, magnitudes, signs)


def on_grid(shape, offset):
    """k/2 + offset + jitter with |jitter| <= 0.1: arrays drawn with offsets 0 and 0.25 are
    at least 0.05 apart everywhere, even after broadcasting (maximum/minimum without ties)."""
    element = st.builds(lambda k, j: 0.5 * k + offset + j, st.integers(-4, 3), floats(-0.1, 0.1))
    return hnp.arrays(np.float64, shape, elements=element)


def positive_base(shape):
    """Bases for power in [0.3, 0.8] or [1.2, 1.7]: positive (so a^b is differentiable in b)
    and away from 1, where d(a^b)/db = a^b log(a) vanishes."""
    return away_from_zero(shape, 0.2, 0.7).map(lambda v: v + 1.0)


@st.composite
def distinct(draw, shape, gap=0.3):
    """An array whose elements are pairwise at least gap - 0.2 apart (max without ties)."""
    size = int(np.prod(shape, dtype=np.int64))
    order = draw(st.permutations(range(size)))
    jitter = draw(hnp.arrays(np.float64, (size,), elements=floats(-0.1, 0.1)))
    return (gap * np.asarray(order, dtype=np.float64) - gap * size / 2 + jitter).reshape(shape)


shapes = hnp.array_shapes(min_dims=0, max_dims=3, min_side=1, max_side=4)
nonscalar_shapes = hnp.array_shapes(min_dims=1, max_dims=3, min_side=1, max_side=4)
pairs = hnp.mutually_broadcastable_shapes(num_shapes=2, min_dims=0, max_dims=3, max_side=4)


@st.composite
def axis_args(draw, ndim):
    """(axis, keepdims) for a reduction over an ndim array: None, an int (maybe negative) or
    a tuple of distinct axes (maybe negative)."""
    keepdims = draw(st.booleans())
    if ndim == 0:
        return None, keepdims
    kind = draw(st.sampled_from(["none", "int", "tuple"]))
    if kind == "none":
        return None, keepdims
    if kind == "int":
        return draw(st.integers(-ndim, ndim - 1)), keepdims
    axes = draw(st.lists(st.integers(0, ndim - 1), min_size=1, max_size=ndim, unique=True))
    negate = draw(st.lists(st.booleans(), min_size=len(axes), max_size=len(axes)))
    return tuple(a - ndim if n else a for a, n in zip(axes, negate, strict=True)), keepdims


# ---------------------------------------------------------------------------------------------
# The checker can fail: a primitive with a wrong VJP is caught
# ---------------------------------------------------------------------------------------------


def wrong_sin(x):
    """sin with a deliberately wrong VJP (sin instead of cos)."""
    x = md.as_tensor(x)
    return record("wrong_sin", np.sin(x.data), (x,), lambda g: (g * np.sin(x.data),))


def wrong_broadcast_multiply(a, b):
    """a * b whose VJP for b forgets to multiply by a."""
    a, b = md.as_tensor(a), md.as_tensor(b)
    return record("wrong_mul", a.data * b.data, (a, b), lambda g: (g * b.data, g))


def test_check_grad_reports_wrong_vjp():
    x = np.linspace(0.1, 1.0, 5)
    rel, g_ad, g_fd = md.check_grad(lambda x: md.sum(wrong_sin(x)), x)
    assert rel > 0.1
    np.testing.assert_allclose(g_ad, np.sin(x))
    np.testing.assert_allclose(g_fd, np.cos(x), rtol=1e-7)
    with pytest.raises(AssertionError, match="relative error"):
        assert_grad_matches(wrong_sin, x)
    with pytest.raises(AssertionError, match="relative error"):
        assert_grad_matches(
            wrong_broadcast_multiply, np.full((2, 3), 3.0), np.ones(3), argnums=(0, 1)
        )


def test_check_grad_returns_eq3_relative_error():
    x = np.array([0.3, -1.2, 2.0])
    rel, g_ad, g_fd = md.check_grad(lambda x: md.sum(wrong_sin(x) * x), x, eps=1e-6)
    expected = np.linalg.norm(g_ad - g_fd) / (np.linalg.norm(g_fd) + 1e-8)
    assert rel == pytest.approx(expected, rel=1e-12)
    # Several arguments: one relative error over all of them together, tuples of gradients.
    a, b = np.array([1.0, 2.0]), np.array([3.0, -1.0])
    rel, (ga, gb), (fa, fb) = md.check_grad(lambda a, b: md.sum(a * b * b), a, b, argnums=(0, 1))
    np.testing.assert_allclose(ga, b * b)
    np.testing.assert_allclose(gb, 2 * a * b)
    both_ad, both_fd = np.concatenate([ga, gb]), np.concatenate([fa, fb])
    expected = np.linalg.norm(both_ad - both_fd) / (np.linalg.norm(both_fd) + 1e-8)
    assert rel == pytest.approx(expected, rel=1e-9, abs=1e-15)


# ---------------------------------------------------------------------------------------------
# Elementwise unary functions
# ---------------------------------------------------------------------------------------------

# name -> (minidiff function, NumPy reference, strategy for inputs of a given shape)
UNARY = {
    "negative": (md.negative, np.negative, arrays),
    "exp": (md.exp, np.exp, arrays),
    "log": (md.log, np.log, lambda s: arrays(s, 0.1, 3.0)),
    "sqrt": (md.sqrt, np.sqrt, lambda s: arrays(s, 0.1, 3.0)),
    # sin and cos away from their stationary points (+-pi/2 and 0, pi): there the gradient
    # is ~0 and Eq. 3 would measure finite-difference rounding noise against ~0.
    "sin": (md.sin, np.sin, lambda s: arrays(s, -1.4, 1.4)),
    "cos": (md.cos, np.cos, lambda s: away_from_zero(s, 0.2, 2.9)),
    "tan": (md.tan, np.tan, lambda s: arrays(s, -1.2, 1.2)),
    "tanh": (md.tanh, np.tanh, arrays),
    "abs": (md.abs, np.abs, away_from_zero),
    "neg_operator": (lambda x: -x, np.negative, arrays),
}


@pytest.mark.parametrize("name", sorted(UNARY))
@SETTINGS
@given(data=st.data(), shape=shapes)
def test_unary(name, data, shape):
    f, ref, values = UNARY[name]
    x = data.draw(values(shape))
    out = f(md.tensor(x))
    assert isinstance(out, md.Tensor) and out.shape == np.shape(ref(x))
    np.testing.assert_allclose(out.data, ref(x), rtol=1e-14)
    assert_grad_matches(f, x)


# ---------------------------------------------------------------------------------------------
# Elementwise binary functions, with broadcasting
# ---------------------------------------------------------------------------------------------

# name -> (minidiff function, NumPy reference, strategy for a, strategy for b)
BINARY = {
    "add": (md.add, np.add, arrays, arrays),
    "subtract": (md.subtract, np.subtract, arrays, arrays),
    "multiply": (md.multiply, np.multiply, arrays, arrays),
    "divide": (md.divide, np.divide, arrays, away_from_zero),
    # Exponents keep away from 0: with b ~ 0 both partial derivatives can vanish together,
    # and Eq. 3 would then compare two numbers that are both ~0.
    "power": (
        md.power,
        np.power,
        positive_base,
        lambda s: away_from_zero(s, 0.3, 2.0),
    ),
    "maximum": (md.maximum, np.maximum, lambda s: on_grid(s, 0.25), lambda s: on_grid(s, 0.0)),
    "minimum": (md.minimum, np.minimum, lambda s: on_grid(s, 0.25), lambda s: on_grid(s, 0.0)),
    "add_operator": (lambda a, b: a + b, np.add, arrays, arrays),
    "sub_operator": (lambda a, b: a - b, np.subtract, arrays, arrays),
    "mul_operator": (lambda a, b: a * b, np.multiply, arrays, arrays),
    "div_operator": (lambda a, b: a / b, np.divide, arrays, away_from_zero),
    "pow_operator": (
        lambda a, b: a**b,
        np.power,
        positive_base,
        lambda s: away_from_zero(s, 0.3, 2.0),
    ),
}


@pytest.mark.parametrize("name", sorted(BINARY))
@SETTINGS
@given(data=st.data(), shapes=pairs)
def test_binary_broadcasting(name, data, shapes):
    f, ref, a_values, b_values = BINARY[name]
    shape_a, shape_b = shapes.input_shapes
    a, b = data.draw(a_values(shape_a)), data.draw(b_values(shape_b))
    out = f(md.tensor(a), md.tensor(b))
    assert out.shape == shapes.result_shape
    np.testing.assert_allclose(out.data, ref(a, b), rtol=1e-14)
    assert_grad_matches(f, a, b, argnums=(0, 1))


@pytest.mark.parametrize("name", sorted(BINARY))
@SETTINGS
@given(data=st.data(), shape=shapes, constant_side=st.sampled_from(["left", "right"]))
def test_binary_with_constants(name, data, shape, constant_side):
    """A Python number or a plain ndarray on either side: the tensor side still gets the
    right gradient (the operators' reflected forms, e.g. 2.0 - x, go through here too)."""
    f, ref, a_values, b_values = BINARY[name]
    a, b = data.draw(a_values(shape)), data.draw(b_values(shape))
    scalar = data.draw(st.booleans())
    if constant_side == "left":
        c = float(a.flat[0]) if scalar else a
        assert_grad_matches(lambda x: f(c, x), b)
        np.testing.assert_allclose(f(c, md.tensor(b)).data, ref(c, b), rtol=1e-14)
    else:
        c = float(b.flat[0]) if scalar else b
        assert_grad_matches(lambda x: f(x, c), a)
        np.testing.assert_allclose(f(md.tensor(a), c).data, ref(a, c), rtol=1e-14)


@SETTINGS
@given(data=st.data(), shape=shapes, n=st.sampled_from([2, 3, 2.0, 3.0, -1]))
def test_power_with_integer_exponent_on_any_sign(data, shape, n):
    """x ** n for a constant integer n is differentiable also for x < 0 (no log(x) needed).
    (Values away from 0, where the gradient of x^3 vanishes and Eq. 3 would compare two
    numbers that are both ~0.)"""
    x = data.draw(away_from_zero(shape))
    assert_grad_matches(lambda x: x**n, x)


@SETTINGS
@given(x=on_grid(shapes, 0.25))
def test_clip(x):
    """clip to [-0.5, 0.5]: values are at least 0.15 away from the bounds."""
    out = md.clip(md.tensor(x), -0.5, 0.5)
    np.testing.assert_array_equal(out.data, np.clip(x, -0.5, 0.5))
    assert_grad_matches(lambda x: md.clip(x, -0.5, 0.5), x)


@SETTINGS
@given(data=st.data(), shapes=pairs)
def test_clip_with_array_bounds(data, shapes):
    """Array bounds broadcast against x: values on the k/2 grid, bounds on the k/2 + 1/4 grid."""
    shape_x, shape_lo = shapes.input_shapes
    x = data.draw(on_grid(shape_x, 0.0))
    lo = data.draw(on_grid(shape_lo, 0.25))
    hi = lo + 1.0
    np.testing.assert_array_equal(md.clip(md.tensor(x), lo, hi).data, np.clip(x, lo, hi))
    assert_grad_matches(lambda x: md.clip(x, lo, hi), x)


@SETTINGS
@given(data=st.data(), shapes=hnp.mutually_broadcastable_shapes(num_shapes=3, max_side=3))
def test_where(data, shapes):
    shape_c, shape_a, shape_b = shapes.input_shapes
    cond = data.draw(hnp.arrays(bool, shape_c))
    a, b = data.draw(arrays(shape_a)), data.draw(arrays(shape_b))
    out = md.where(cond, md.tensor(a), md.tensor(b))
    np.testing.assert_array_equal(out.data, np.where(cond, a, b))
    assert_grad_matches(lambda a, b: md.where(cond, a, b), a, b, argnums=(0, 1))
    assert_grad_matches(lambda a: md.where(cond, a, 0.0), a)


# ---------------------------------------------------------------------------------------------
# Reductions
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["sum", "mean"])
@SETTINGS
@given(data=st.data(), shape=shapes)
def test_sum_mean(name, data, shape):
    x = data.draw(arrays(shape))
    axis, keepdims = data.draw(axis_args(len(shape)))
    f = getattr(md, name)
    ref = getattr(np, name)(x, axis=axis, keepdims=keepdims)
    out = f(md.tensor(x), axis=axis, keepdims=keepdims)
    assert out.shape == np.shape(ref)
    np.testing.assert_allclose(out.data, ref, rtol=1e-13)
    assert_grad_matches(lambda x: f(x, axis=axis, keepdims=keepdims), x)
    # The method form is the same primitive.
    method = getattr(md.tensor(x), name)(axis=axis, keepdims=keepdims)
    np.testing.assert_allclose(method.data, ref, rtol=1e-13)


@SETTINGS
@given(data=st.data(), shape=shapes)
def test_max(data, shape):
    x = data.draw(distinct(shape))
    axis, keepdims = data.draw(axis_args(len(shape)))
    ref = np.max(x, axis=axis, keepdims=keepdims)
    out = md.max(md.tensor(x), axis=axis, keepdims=keepdims)
    np.testing.assert_array_equal(out.data, ref)
    assert out.shape == np.shape(ref)
    assert_grad_matches(lambda x: md.max(x, axis=axis, keepdims=keepdims), x)
    assert_grad_matches(lambda x: x.max(axis=axis, keepdims=keepdims), x)


def test_max_ties_split_the_gradient():
    """The documented subgradient: tied maxima share the gradient equally."""
    x = md.tensor([[1.0, 3.0, 3.0], [2.0, 0.0, 2.0]], requires_grad=True)
    md.max(x, axis=1).backward(np.array([1.0, 4.0]))
    np.testing.assert_allclose(x.grad, [[0.0, 0.5, 0.5], [2.0, 0.0, 2.0]])
    y = md.tensor([5.0, 5.0, 5.0, 1.0], requires_grad=True)
    md.max(y).backward()
    np.testing.assert_allclose(y.grad, [1 / 3, 1 / 3, 1 / 3, 0.0])


def test_kink_subgradients():
    """The documented choices at kinks: abs'(0) = 0, maximum/minimum ties go to a, clip has
    slope 1 on its bounds."""
    x = md.tensor([0.0, 1.0], requires_grad=True)
    md.abs(x).sum().backward()
    np.testing.assert_array_equal(x.grad, [0.0, 1.0])
    a, b = md.tensor([1.0], requires_grad=True), md.tensor([1.0], requires_grad=True)
    (md.maximum(a, b) + 2 * md.minimum(a, b)).sum().backward()
    np.testing.assert_array_equal(a.grad, [3.0])
    np.testing.assert_array_equal(b.grad, [0.0])
    c = md.tensor([-1.0, 0.0, 0.5, 1.0, 2.0], requires_grad=True)
    md.clip(c, 0.0, 1.0).sum().backward()
    np.testing.assert_array_equal(c.grad, [0.0, 1.0, 1.0, 1.0, 0.0])


# ---------------------------------------------------------------------------------------------
# Vector algebra along the last axis
# ---------------------------------------------------------------------------------------------


@SETTINGS
@given(
    data=st.data(),
    batch=hnp.mutually_broadcastable_shapes(num_shapes=2, max_dims=2, max_side=3),
    n=st.integers(1, 4),
)
def test_dot(data, batch, n):
    shape_a, shape_b = (s + (n,) for s in batch.input_shapes)
    a, b = data.draw(arrays(shape_a)), data.draw(arrays(shape_b))
    out = md.dot(md.tensor(a), md.tensor(b))
    np.testing.assert_allclose(out.data, np.sum(a * b, axis=-1), rtol=1e-12, atol=1e-14)
    assert_grad_matches(md.dot, a, b, argnums=(0, 1))


@SETTINGS
@given(data=st.data(), shape=hnp.array_shapes(min_dims=1, max_dims=3, max_side=5))
def test_mean_squared_error(data, shape):
    """The fused loss: the same bits as mean((a - b) * (a - b)) in value and gradient, and
    the gradient against central differences."""
    a, b = data.draw(arrays(shape)), data.draw(arrays(shape))
    x, y = md.tensor(a, requires_grad=True), md.tensor(a, requires_grad=True)
    fused = md.mean_squared_error(x, b)
    composed = ((y - b) * (y - b)).mean()
    fused.backward()
    composed.backward()
    assert fused.item() == composed.item()
    np.testing.assert_array_equal(x.grad, y.grad)
    assert_grad_matches(md.mean_squared_error, a, b, argnums=(0, 1))


def test_mean_squared_error_refuses_mismatched_or_empty_arrays():
    with pytest.raises(ValueError, match="shapes differ"):
        md.mean_squared_error(np.zeros((2, 3)), np.zeros(3))
    with pytest.raises(ValueError, match="no elements"):
        md.mean_squared_error(np.zeros(0), np.zeros(0))


@SETTINGS
@given(data=st.data(), batch=hnp.mutually_broadcastable_shapes(num_shapes=2, max_dims=2))
def test_cross(data, batch):
    shape_a, shape_b = (s + (3,) for s in batch.input_shapes)
    a, b = data.draw(arrays(shape_a)), data.draw(arrays(shape_b))
    out = md.cross(md.tensor(a), md.tensor(b))
    np.testing.assert_allclose(out.data, np.cross(a, b), rtol=1e-12, atol=1e-14)
    assert_grad_matches(md.cross, a, b, argnums=(0, 1))


@SETTINGS
@given(data=st.data(), shape=nonscalar_shapes, keepdims=st.booleans())
def test_norm(data, shape, keepdims):
    x = data.draw(away_from_zero(shape))  # every vector has length >= 0.3
    axis = data.draw(st.integers(-len(shape), len(shape) - 1))
    out = md.norm(md.tensor(x), axis=axis, keepdims=keepdims)
    ref = np.linalg.norm(x, axis=axis, keepdims=keepdims)
    np.testing.assert_allclose(out.data, ref, rtol=1e-14)
    assert_grad_matches(lambda x: md.norm(x, axis=axis, keepdims=keepdims), x)


@SETTINGS
@given(data=st.data(), shape=nonscalar_shapes)
def test_normalize(data, shape):
    # At least 2 components: a 1-vector normalises to its sign, whose gradient is exactly 0.
    shape = shape[:-1] + (max(shape[-1], 2),)
    x = data.draw(away_from_zero(shape))
    out = md.normalize(md.tensor(x))
    ref = x / np.linalg.norm(x, axis=-1, keepdims=True)
    np.testing.assert_allclose(out.data, ref, rtol=1e-14)
    assert_grad_matches(md.normalize, x)


def test_norm_and_normalize_of_zero_vector_are_finite():
    x = md.tensor(np.zeros((2, 3)), requires_grad=True)
    (md.norm(x).sum() + md.normalize(x).sum()).backward()
    np.testing.assert_array_equal(x.grad, np.zeros((2, 3)))


# ---------------------------------------------------------------------------------------------
# Matrix product
# ---------------------------------------------------------------------------------------------


@SETTINGS
@given(
    data=st.data(),
    shapes=hnp.mutually_broadcastable_shapes(
        signature=np.matmul.signature, max_dims=2, min_side=1, max_side=3
    ),
)
def test_matmul(data, shapes):
    """1-D and 2-D operands and broadcast batches, as drawn from NumPy's gufunc signature
    (n?,k),(k,m?)->(n?,m?)."""
    shape_a, shape_b = shapes.input_shapes
    a, b = data.draw(arrays(shape_a)), data.draw(arrays(shape_b))
    out = md.tensor(a) @ md.tensor(b)
    np.testing.assert_allclose(out.data, a @ b, rtol=1e-12, atol=1e-14)
    assert out.shape == shapes.result_shape
    assert_grad_matches(md.matmul, a, b, argnums=(0, 1))
    assert_grad_matches(lambda a: a @ b, a)  # constant ndarray on the right ...
    assert_grad_matches(lambda b: a @ b, b)  # ... and on the left (__rmatmul__)


@st.composite
def linear_operator(draw):
    """(apply, adjoint, input size) of a random linear map: a dense (m, n) matrix, or the
    inverse of a sparse diagonally dominant (n, n) one through SciPy's LU factorisation."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    n = draw(st.integers(1, 6))
    rng = np.random.default_rng(draw(st.integers(0, 2**31)))
    if draw(st.booleans()):
        a = rng.normal(size=(draw(st.integers(1, 6)), n))
        return (lambda x: a @ x), (lambda g: a.T @ g), n
    m = sp.random(n, n, density=0.4, random_state=rng) + sp.eye(n) * (n + 1.0)
    lu = splu(sp.csc_matrix(m))
    return lu.solve, (lambda g: lu.solve(g, trans="T")), n


@settings(max_examples=25, deadline=None)
@given(operator=linear_operator(), columns=st.sampled_from([(), (1,), (3,)]), data=st.data())
def test_linear(operator, columns, data):
    """A constant linear map A: the VJP is A^T g (checked against central differences, for
    a dense A and for the inverse of a sparse LU factorisation)."""
    apply, adjoint, n = operator
    x = data.draw(arrays((n,) + columns))
    np.testing.assert_allclose(md.linear(apply, adjoint, x).data, apply(x), rtol=1e-12)
    assert_grad_matches(lambda x: md.linear(apply, adjoint, x), x)


@pytest.mark.parametrize(
    "shape_a, shape_b",
    [((3,), (3,)), ((3,), (3, 2)), ((2, 3), (3,)), ((2, 3), (3, 4)), ((5, 2, 3), (3,))],
)
def test_matmul_vector_cases(shape_a, shape_b):
    rng = np.random.default_rng(1)
    a, b = rng.normal(size=shape_a), rng.normal(size=shape_b)
    assert_grad_matches(md.matmul, a, b, argnums=(0, 1))


# ---------------------------------------------------------------------------------------------
# Shape manipulation
# ---------------------------------------------------------------------------------------------


@SETTINGS
@given(data=st.data(), shape=shapes)
def test_reshape(data, shape):
    x = data.draw(arrays(shape))
    size = x.size
    target = data.draw(
        st.sampled_from([(size,), (-1,), shape[::-1], shape + (1,), (1,) + shape, (1, -1)])
    )
    np.testing.assert_array_equal(md.reshape(md.tensor(x), target).data, x.reshape(target))
    assert_grad_matches(lambda x: md.reshape(x, target), x)
    assert_grad_matches(lambda x: x.reshape(*target), x)
    assert_grad_matches(lambda x: x.reshape(target), x)


@SETTINGS
@given(data=st.data(), shape=shapes)
def test_transpose(data, shape):
    x = data.draw(arrays(shape))
    ndim = len(shape)
    perm = data.draw(st.permutations(range(ndim)))
    negate = data.draw(st.lists(st.booleans(), min_size=ndim, max_size=ndim))
    axes = tuple(a - ndim if n else a for a, n in zip(perm, negate, strict=True))
    out = md.transpose(md.tensor(x), axes)
    np.testing.assert_array_equal(out.data, np.transpose(x, axes))
    assert_grad_matches(lambda x: md.transpose(x, axes), x)
    assert_grad_matches(lambda x: x.transpose(*axes), x)
    assert_grad_matches(lambda x: md.transpose(x), x)
    assert_grad_matches(lambda x: x.T, x)


@SETTINGS
@given(data=st.data(), target=shapes)
def test_broadcast_to(data, target):
    # An input shape that broadcasts *to* target: some trailing axes of target, each either
    # kept or shrunk to 1.
    ndim = data.draw(st.integers(0, len(target)))
    trailing = target[len(target) - ndim :]
    shrink = data.draw(st.lists(st.booleans(), min_size=ndim, max_size=ndim))
    shape = tuple(1 if s else n for n, s in zip(trailing, shrink, strict=True))
    x = data.draw(arrays(shape))
    out = md.broadcast_to(md.tensor(x), target)
    np.testing.assert_array_equal(out.data, np.broadcast_to(x, target))
    assert_grad_matches(lambda x: md.broadcast_to(x, target), x)


@SETTINGS
@given(data=st.data(), shape=shapes, count=st.integers(1, 3))
def test_stack(data, shape, count):
    xs = [data.draw(arrays(shape)) for _ in range(count)]
    axis = data.draw(st.integers(-len(shape) - 1, len(shape)))
    out = md.stack([md.tensor(x) for x in xs], axis=axis)
    np.testing.assert_array_equal(out.data, np.stack(xs, axis=axis))
    assert_grad_matches(lambda *xs: md.stack(xs, axis=axis), *xs, argnums=tuple(range(count)))
    # A mix of tensors and constant arrays.
    assert_grad_matches(lambda x: md.stack([x, xs[0] * 2.0], axis=axis), xs[-1])


@SETTINGS
@given(data=st.data(), shape=nonscalar_shapes, count=st.integers(1, 3))
def test_concatenate(data, shape, count):
    axis = data.draw(st.integers(-len(shape), len(shape) - 1))
    lengths = data.draw(st.lists(st.integers(1, 3), min_size=count, max_size=count))
    positive = axis % len(shape)
    shapes_ = [shape[:positive] + (n,) + shape[positive + 1 :] for n in lengths]
    xs = [data.draw(arrays(s)) for s in shapes_]
    out = md.concatenate([md.tensor(x) for x in xs], axis=axis)
    np.testing.assert_array_equal(out.data, np.concatenate(xs, axis=axis))
    assert_grad_matches(lambda *xs: md.concatenate(xs, axis=axis), *xs, argnums=tuple(range(count)))


# ---------------------------------------------------------------------------------------------
# Indexing: gather (x[index]) and scatter_add
# ---------------------------------------------------------------------------------------------


def check_index(x, index):
    """Forward equals NumPy's, gradient matches finite differences."""
    out = md.tensor(x)[index]
    np.testing.assert_array_equal(out.data, x[index])
    assert_grad_matches(lambda x: x[index], x)


@SETTINGS
@given(data=st.data(), shape=nonscalar_shapes)
def test_getitem_basic(data, shape):
    """Integers, slices (negative steps included), Ellipsis and None."""
    x = data.draw(arrays(shape))
    index = data.draw(hnp.basic_indices(shape, allow_newaxis=True))
    check_index(x, index)


@SETTINGS
@given(data=st.data(), shape=nonscalar_shapes)
def test_getitem_row_gather(data, shape):
    """x[int_array] with a 1-D array, repeated and negative indices (the renderer's gather)."""
    x = data.draw(arrays(shape))
    n = shape[0]
    index = data.draw(hnp.arrays(np.int64, st.integers(1, 8), elements=st.integers(-n, n - 1)))
    check_index(x, index)
    check_index(x, index.tolist())  # a list is an integer-array index too


@SETTINGS
@given(data=st.data(), shape=nonscalar_shapes)
def test_getitem_integer_arrays(data, shape):
    """Tuples of integer arrays over several axes (any result shape, repeats likely)."""
    x = data.draw(arrays(shape))
    index = data.draw(
        hnp.integer_array_indices(shape, result_shape=hnp.array_shapes(max_dims=2, max_side=4))
    )
    check_index(x, index)


@SETTINGS
@given(data=st.data(), shape=hnp.array_shapes(min_dims=2, max_dims=3, max_side=4))
def test_getitem_mixed_tuple(data, shape):
    """A slice on the first axis and an integer array (with repeats) on the last."""
    x = data.draw(arrays(shape))
    m = shape[-1]
    cols = data.draw(hnp.arrays(np.int64, st.integers(1, 5), elements=st.integers(-m, m - 1)))
    step = data.draw(st.sampled_from([1, 2, -1]))
    check_index(x, (slice(None, None, step), ..., cols))


@SETTINGS
@given(data=st.data(), shape=nonscalar_shapes)
def test_getitem_boolean_mask(data, shape):
    x = data.draw(on_grid(shape, 0.0))
    k = data.draw(st.integers(1, len(shape)))
    mask = data.draw(hnp.arrays(bool, shape[:k]))  # a mask over the leading k axes
    check_index(x, mask)
    check_index(x, (mask,) + (slice(None, None, -1),) * (len(shape) - k))
    # A mask computed from the tensor itself by a comparison (a plain boolean ndarray); the
    # grid values keep 0.15 away from the threshold, so finite differences keep the mask.
    assert_grad_matches(lambda x: x[x > 0.25], x)


def test_getitem_repeated_indices_accumulate():
    x = md.tensor([1.0, 2.0, 3.0], requires_grad=True)
    x[np.array([0, 0, 2, -1, 0])].backward(np.array([1.0, 2.0, 3.0, 4.0, 5.0]))
    np.testing.assert_array_equal(x.grad, [8.0, 0.0, 7.0])
    y = md.tensor(np.zeros((2, 2)), requires_grad=True)
    y[[0, 0, 1], [1, 1, -1]].sum().backward()
    np.testing.assert_array_equal(y.grad, [[0.0, 2.0], [0.0, 1.0]])


@pytest.mark.parametrize("cols", [1, 3, 7])  # both code paths of the row scatter (<= 4, > 4)
def test_getitem_row_gather_wide_rows(cols):
    rng = np.random.default_rng(2)
    x = rng.normal(size=(5, cols))
    check_index(x, np.array([4, 0, 0, -1, 2, 2, 2]))
    check_index(x, np.array([], dtype=np.int64))  # no rows selected: zero gradient


@SETTINGS
@given(
    data=st.data(),
    trailing=hnp.array_shapes(min_dims=0, max_dims=2, max_side=4),
    k=st.integers(1, 8),
    size=st.integers(1, 5),
)
def test_scatter_add(data, trailing, k, size):
    values = data.draw(arrays((k,) + trailing))
    index = data.draw(hnp.arrays(np.int64, (k,), elements=st.integers(0, size - 1)))
    expected = np.zeros((size,) + trailing)
    np.add.at(expected, index, values)
    out = md.scatter_add(md.tensor(values), index, size)
    np.testing.assert_allclose(out.data, expected, rtol=1e-14, atol=1e-14)
    assert_grad_matches(lambda v: md.scatter_add(v, index, size), values)


# ---------------------------------------------------------------------------------------------
# Composite functions
# ---------------------------------------------------------------------------------------------

# Unary steps that keep values bounded and smooth for inputs in roughly [-5, 5].
SMOOTH_UNARY = {
    "sin": md.sin,
    "cos": md.cos,
    "tanh": md.tanh,
    "exp_sin": lambda v: md.exp(md.sin(v)),
    "log1p_sq": lambda v: md.log(1.0 + v * v),
    "sqrt1p_sq": lambda v: md.sqrt(v**2 + 1.0),
    "half_square": lambda v: 0.5 * v * v,
    "neg": lambda v: -v,
    "normalize": lambda v: md.normalize(md.stack([v, 1.0 + 0 * v], axis=-1))[..., 0],
}
# Binary steps; the divisor 2 + cos(b) stays in [1, 3].
SMOOTH_BINARY = {
    "add": lambda a, b: a + b,
    "sub": lambda a, b: a - b,
    "mul": lambda a, b: a * b,
    "div": lambda a, b: a / (2.0 + md.cos(b)),
    "pow": lambda a, b: (1.5 + md.sin(a)) ** md.tanh(b),
    "rsub_const": lambda a, b: 1.0 - a * 0.5 + b,
}


@st.composite
def programs(draw):
    """Input shapes (mutually broadcastable) and a list of steps; each step applies a unary op
    to one earlier value or a binary op to two earlier values, so values are reused (diamonds).
    """
    shapes = draw(hnp.mutually_broadcastable_shapes(num_shapes=3, max_dims=3, max_side=3))
    steps = []
    for i in range(draw(st.integers(1, 6))):
        n_values = 3 + i
        if draw(st.booleans()):
            steps.append(
                (
                    "u",
                    draw(st.sampled_from(sorted(SMOOTH_UNARY))),
                    draw(st.integers(0, n_values - 1)),
                    None,
                )
            )
        else:
            steps.append(
                (
                    "b",
                    draw(st.sampled_from(sorted(SMOOTH_BINARY))),
                    draw(st.integers(0, n_values - 1)),
                    draw(st.integers(0, n_values - 1)),
                )
            )
    return shapes.input_shapes, steps


def run_program(steps, *inputs):
    values = list(inputs)
    for kind, name, i, j in steps:
        if kind == "u":
            values.append(SMOOTH_UNARY[name](values[i]))
        else:
            values.append(SMOOTH_BINARY[name](values[i], values[j]))
    # Every value feeds the output (each broadcast to the common shape, then summed), so
    # every input matters even if the last step ignores it.
    out = values[-1]
    for v in values[:-1]:
        out = out + 0.5 * v
    return out


@settings(max_examples=40, deadline=None)
@given(data=st.data(), program=programs())
def test_random_compositions(data, program):
    shapes_, steps = program
    inputs = [data.draw(arrays(s)) for s in shapes_]
    assert_grad_matches(lambda *xs: run_program(steps, *xs), *inputs, argnums=(0, 1, 2))


@SETTINGS
@given(data=st.data(), n=st.integers(1, 5), k=st.integers(1, 8))
def test_composite_gather_mask_where(data, n, k):
    """A renderer-like pattern: gather vertex rows with repeated indices, shade with dot and
    normalize, mask with where, reduce with max and mean, scatter back."""
    vertices = data.draw(away_from_zero((n, 3)))
    light = data.draw(arrays((3,), 3.0, 4.0))  # outside the vertices' [-2, 2] box
    index = data.draw(hnp.arrays(np.int64, (k,), elements=st.integers(-n, n - 1)))
    mask = data.draw(hnp.arrays(bool, (k,)))

    def shade(vertices, light):
        rows = vertices[index]  # (k, 3), rows repeat
        to_light = light - rows
        cos = md.dot(md.normalize(rows), md.normalize(to_light))
        r2 = md.dot(to_light, to_light)
        lit = md.where(mask, cos / r2, 0.1 * md.tanh(cos))
        rows_index = np.where(index < 0, index + n, index)
        image = md.scatter_add(lit, rows_index, n)
        # A term whose gradient never vanishes (|rows| >= 0.3, light >= 3): the shading terms
        # alone have exactly zero gradient when all rows are collinear with the light.
        flux = md.scatter_add(md.sum(rows * light, axis=1), rows_index, n)
        return md.stack([image, md.mean(lit) + flux, md.exp(-r2).sum() + image], axis=1)

    assert_grad_matches(shade, vertices, light, argnums=(0, 1))


@SETTINGS
@given(data=st.data(), rows=st.integers(1, 4), cols=st.integers(1, 4))
def test_composite_broadcast_back_to_size_one_axes(data, rows, cols):
    """(rows, 1) and (1, cols) operands broadcast to (rows, cols); their gradients are summed
    back over the size-1 axes, also through reductions with keepdims."""
    a = data.draw(arrays((rows, 1)))
    b = data.draw(arrays((1, cols)))
    c = data.draw(arrays(()))

    def f(a, b, c):
        grid = md.sin(a * b) + c * a - b / (2.0 + md.cos(c))
        centred = grid - md.mean(grid, axis=1, keepdims=True)
        return md.sum(centred * centred, axis=0, keepdims=True) + md.tanh(grid).T.sum(axis=1)

    assert_grad_matches(f, a, b, c, argnums=(0, 1, 2))


# ---------------------------------------------------------------------------------------------
# Tall, thin arrays: gradients through the compiled row loops (minidiff.kernels; their
# values are compared with NumPy in tests/minidiff/test_kernels.py)
# ---------------------------------------------------------------------------------------------


@settings(max_examples=10, deadline=None)
@given(shapes=tall_broadcast_pairs(), seed=st.integers(0, 2**16))
def test_tall_broadcast_gradients(shapes, seed):
    """Gradients through the fast path (forward, VJPs and the column sums of unbroadcast),
    checked as directional derivatives: for random directions (dx, dy), the tape's
    <grad, d> equals the central difference of the loss along d (all elements at once:
    element-wise finite differences of 10^4 inputs would take too long)."""
    rng = np.random.default_rng(seed)
    x0 = rng.uniform(0.5, 2.0, shapes[0])
    y0 = rng.uniform(0.5, 2.0, shapes[1])
    weights = rng.normal(size=np.broadcast_shapes(*shapes))

    def loss(x, y):
        return md.sum((x * y + x / y - (y - x)) * weights)  # no kinks: FD is exact

    x, y = md.tensor(x0, requires_grad=True), md.tensor(y0, requires_grad=True)
    loss(x, y).backward()
    dx, dy = rng.normal(size=x0.shape), rng.normal(size=y0.shape)
    h = 1e-6
    with md.no_grad():
        plus = loss(md.tensor(x0 + h * dx), md.tensor(y0 + h * dy)).item()
        minus = loss(md.tensor(x0 - h * dx), md.tensor(y0 - h * dy)).item()
    fd = (plus - minus) / (2 * h)
    ad = float(np.sum(x.grad * dx) + np.sum(y.grad * dy))
    assert abs(ad - fd) <= 1e-6 * max(1.0, abs(fd)), (ad, fd)


# ---------------------------------------------------------------------------------------------
# floor: a step, its derivative 0 between the steps
# ---------------------------------------------------------------------------------------------


@SETTINGS
@given(data=st.data(), shape=shapes)
def test_floor_is_a_step_whose_derivative_is_zero_between_steps(data, shape):
    """floor(x) is NumPy's; away from the integers (where central differences see no
    step) the derivative of x * floor(x) is floor(x), the step contributing nothing."""
    whole = data.draw(hnp.arrays(np.float64, shape, elements=st.integers(-5, 5).map(float)))
    part = data.draw(hnp.arrays(np.float64, shape, elements=floats(0.05, 0.95)))
    x = whole + part
    np.testing.assert_array_equal(md.floor(x).data, np.floor(x))
    assert not md.floor(md.tensor(x, requires_grad=True)).requires_grad
    assert_grad_matches(lambda y: y * md.floor(y), x)


# ---------------------------------------------------------------------------------------------
# detach: a value without a derivative
# ---------------------------------------------------------------------------------------------


@SETTINGS
@given(data=st.data(), shape=shapes)
def test_detach_keeps_the_value_and_drops_the_derivative(data, shape):
    """x * detach(x) has x's square as value and derivative detach(x) (not 2x): central
    differences of the same product with the detached factor held fixed."""
    x = data.draw(away_from_zero(shape))
    t = md.tensor(x, requires_grad=True)
    held = md.detach(t)
    assert not held.requires_grad
    np.testing.assert_array_equal(held.data, x)
    out = md.sum(t * held)
    out.backward()
    np.testing.assert_allclose(t.grad, x, rtol=1e-14)
    assert_grad_matches(lambda y: y * md.tensor(x), x)
