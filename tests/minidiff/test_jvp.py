"""Forward mode (``md.jvp``, ``md.tangents``): every primitive's JVP, on shapes and values
drawn by hypothesis (the strategies of ``tests/minidiff/test_primitives.py``), against

- reverse mode, by the dot-product identity: for random u (of the output's shape) and v
  (one per input), <u, J v> from forward mode equals <J^T u, v> from the tape, to 1e-10
  relative to sum |u * Jv| + sum |J^T u * v| (the size of the terms being summed, so that
  cancellation cannot hide an error);
- central differences along v: (f(x + h v) - f(x - h v)) / 2h, with the Eq. 3 relative
  error below 1e-6 (h = 1e-6, float64).

Values are drawn away from kinks as in the primitive tests, where finite differences are
valid. At kinks (ties of max/maximum/minimum, clip at its bounds, abs at 0, zero vectors)
only the identity is checked: it holds there too, because the JVP and the VJP pick the same
subgradient; a JVP picking the other branch would fail it.
"""

from __future__ import annotations

import inspect

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

import minidiff as md
from minidiff import primitives
from minidiff.tensor import record
from tests.minidiff.test_primitives import (
    BINARY,
    UNARY,
    arrays,
    away_from_zero,
    axis_args,
    distinct,
    nonscalar_shapes,
    on_grid,
    pairs,
    shapes,
    wrong_sin,
)

SETTINGS = settings(max_examples=20, deadline=None)
IDENTITY_TOL = 1e-10
FD_TOL = 1e-6
H = 1e-6


# ---------------------------------------------------------------------------------------------
# The checks
# ---------------------------------------------------------------------------------------------


def dot_identity_error(f, args, seed=0):
    """|<u, J v> - <J^T u, v>| / (sum |u Jv| + sum |J^T u v|) for random u, v; also returns
    J v and v."""
    rng = np.random.default_rng(seed)
    directions = [rng.normal(size=np.shape(a)) for a in args]
    value, jv = md.jvp(f, tuple(args), tuple(directions))
    with md.no_grad():
        expected = f(*[md.tensor(a) for a in args])
    np.testing.assert_array_equal(value, expected.data)
    assert jv.shape == value.shape and jv.dtype == value.dtype
    u = rng.normal(size=value.shape)
    nums = tuple(range(len(args)))
    _, grads = md.value_and_grad(lambda *xs: md.sum(f(*xs) * u), nums)(*args)
    forward = np.sum(u * jv)
    reverse = sum(np.sum(g * v) for g, v in zip(grads, directions, strict=True))
    scale = np.sum(np.abs(u * jv)) + sum(
        np.sum(np.abs(g * v)) for g, v in zip(grads, directions, strict=True)
    )
    error = abs(forward - reverse) / scale if scale > 0 else abs(forward - reverse)
    return error, jv, directions


def assert_jvp_matches(f, *args, fd=True, seed=0):
    """The dot-product identity with reverse mode, and (if ``fd``) central differences."""
    args = [np.asarray(a, dtype=np.float64) for a in args]
    error, jv, directions = dot_identity_error(f, args, seed)
    assert error <= IDENTITY_TOL, f"<u, Jv> != <J^T u, v>: relative error {error:.2e}"
    if not fd:
        return
    with md.no_grad():
        plus = f(*[md.tensor(a + H * v) for a, v in zip(args, directions, strict=True)]).data
        minus = f(*[md.tensor(a - H * v) for a, v in zip(args, directions, strict=True)]).data
    central = (plus - minus) / (2 * H)
    rel = np.linalg.norm(jv - central) / (np.linalg.norm(central) + 1e-8)
    assert rel < FD_TOL, f"J v vs central differences: relative error {rel:.2e}\n{jv}\n{central}"


# ---------------------------------------------------------------------------------------------
# One or more cases per primitive: a strategy drawing (f, args)
# ---------------------------------------------------------------------------------------------


#: primitive name -> strategies drawing (f, args); every primitive in md.__all__ needs one.
CASES: dict[str, list] = {}


def case_of(name: str):
    """Register a composite strategy (a function of ``draw``) as a case of primitive
    ``name``."""

    def register(strategy):
        CASES.setdefault(name, []).append(strategy())
        return strategy

    return register


def unary_case(name):
    f, _, values = UNARY[name]
    return shapes.flatmap(values).map(lambda x: (f, [x]))


def binary_case(name):
    f, _, a_values, b_values = BINARY[name]

    @st.composite
    def draw(draw):
        shape_a, shape_b = draw(pairs).input_shapes
        return f, [draw(a_values(shape_a)), draw(b_values(shape_b))]

    return draw()


def binary_with_constant_case(name):
    """One operand a constant (Python number or array): it has no tangent (None)."""
    f, _, a_values, b_values = BINARY[name]

    @st.composite
    def draw(draw):
        shape_a, shape_b = draw(pairs).input_shapes
        a, b = draw(a_values(shape_a)), draw(b_values(shape_b))
        if draw(st.booleans()):
            c = float(b.flat[0]) if draw(st.booleans()) else b
            return (lambda x: f(x, c)), [a]
        c = float(a.flat[0]) if draw(st.booleans()) else a
        return (lambda x: f(c, x)), [b]

    return draw()


@case_of("matmul")
@st.composite
def matmul_case(draw):
    signature = hnp.mutually_broadcastable_shapes(
        signature=np.matmul.signature, max_dims=2, min_side=1, max_side=3
    )
    shape_a, shape_b = draw(signature).input_shapes
    return md.matmul, [draw(arrays(shape_a)), draw(arrays(shape_b))]


@case_of("clip")
@st.composite
def clip_case(draw):
    shape_x, shape_lo = draw(pairs).input_shapes
    x, lo = draw(on_grid(shape_x, 0.0)), draw(on_grid(shape_lo, 0.25))
    return (lambda x: md.clip(x, lo, lo + 1.0)), [x]


@case_of("where")
@st.composite
def where_case(draw):
    shape_c, shape_a, shape_b = draw(
        hnp.mutually_broadcastable_shapes(num_shapes=3, max_side=3)
    ).input_shapes
    cond = draw(hnp.arrays(bool, shape_c))
    return (lambda a, b: md.where(cond, a, b)), [draw(arrays(shape_a)), draw(arrays(shape_b))]


def reduction_case(name):
    @st.composite
    def draw(draw):
        shape = draw(shapes)
        x = draw(distinct(shape) if name == "max" else arrays(shape))
        axis, keepdims = draw(axis_args(len(shape)))
        fn = getattr(md, name)
        return (lambda x: fn(x, axis=axis, keepdims=keepdims)), [x]

    return draw()


@case_of("dot")
@st.composite
def dot_case(draw):
    batch = draw(hnp.mutually_broadcastable_shapes(num_shapes=2, max_dims=2, max_side=3))
    n = draw(st.integers(1, 4))
    shape_a, shape_b = (s + (n,) for s in batch.input_shapes)
    return md.dot, [draw(arrays(shape_a)), draw(arrays(shape_b))]


@case_of("mean_squared_error")
@st.composite
def mean_squared_error_case(draw):
    shape = draw(hnp.array_shapes(min_dims=1, max_dims=3, max_side=4))
    return md.mean_squared_error, [draw(arrays(shape)), draw(arrays(shape))]


@case_of("cross")
@st.composite
def cross_case(draw):
    batch = draw(hnp.mutually_broadcastable_shapes(num_shapes=2, max_dims=2))
    shape_a, shape_b = (s + (3,) for s in batch.input_shapes)
    return md.cross, [draw(arrays(shape_a)), draw(arrays(shape_b))]


@case_of("norm")
@st.composite
def norm_case(draw):
    shape = draw(nonscalar_shapes)
    axis = draw(st.integers(-len(shape), len(shape) - 1))
    keepdims = draw(st.booleans())
    return (lambda x: md.norm(x, axis=axis, keepdims=keepdims)), [draw(away_from_zero(shape))]


@case_of("normalize")
@st.composite
def normalize_case(draw):
    # At least 2 components: a 1-vector normalises to its sign, whose derivative is 0 up to
    # rounding, and the relative checks would compare rounding noise with rounding noise.
    shape = draw(nonscalar_shapes)
    shape = shape[:-1] + (max(shape[-1], 2),)
    return md.normalize, [draw(away_from_zero(shape))]


@case_of("reshape")
@st.composite
def reshape_case(draw):
    shape = draw(shapes)
    size = int(np.prod(shape, dtype=np.int64))
    target = draw(st.sampled_from([(size,), (-1,), shape[::-1], shape + (1,), (1, -1)]))
    return (lambda x: md.reshape(x, target)), [draw(arrays(shape))]


@case_of("transpose")
@st.composite
def transpose_case(draw):
    shape = draw(shapes)
    axes = tuple(draw(st.permutations(range(len(shape)))))
    axes = None if draw(st.booleans()) else axes
    return (lambda x: md.transpose(x, axes)), [draw(arrays(shape))]


@case_of("broadcast_to")
@st.composite
def broadcast_to_case(draw):
    target = draw(shapes)
    ndim = draw(st.integers(0, len(target)))
    shrink = draw(st.lists(st.booleans(), min_size=ndim, max_size=ndim))
    trailing = target[len(target) - ndim :]
    shape = tuple(1 if s else n for n, s in zip(trailing, shrink, strict=True))
    return (lambda x: md.broadcast_to(x, target)), [draw(arrays(shape))]


@case_of("stack")
@st.composite
def stack_case(draw):
    shape, count = draw(shapes), draw(st.integers(1, 3))
    axis = draw(st.integers(-len(shape) - 1, len(shape)))
    xs = [draw(arrays(shape)) for _ in range(count)]
    constant = draw(arrays(shape))  # a constant among the tensors: its tangent is zero
    return (lambda *xs: md.stack([*xs, constant], axis=axis)), xs


@case_of("concatenate")
@st.composite
def concatenate_case(draw):
    shape, count = draw(nonscalar_shapes), draw(st.integers(1, 3))
    axis = draw(st.integers(-len(shape), len(shape) - 1))
    positive = axis % len(shape)
    pieces = [
        shape[:positive] + (draw(st.integers(1, 3)),) + shape[positive + 1 :]
        for _ in range(count + 1)
    ]
    xs = [draw(arrays(s)) for s in pieces[:-1]]
    constant = draw(arrays(pieces[-1]))
    return (lambda *xs: md.concatenate([constant, *xs], axis=axis)), xs


@case_of("getitem")
@st.composite
def getitem_case(draw):
    shape = draw(nonscalar_shapes)
    x = draw(on_grid(shape, 0.0))
    n = shape[0]
    kind = draw(st.sampled_from(["basic", "rows", "arrays", "mask", "computed_mask"]))
    if kind == "basic":
        index = draw(hnp.basic_indices(shape, allow_newaxis=True))
    elif kind == "rows":  # the renderer's gather, repeats and negative indices
        index = draw(hnp.arrays(np.int64, st.integers(1, 8), elements=st.integers(-n, n - 1)))
    elif kind == "arrays":
        result = hnp.array_shapes(max_dims=2, max_side=4)
        index = draw(hnp.integer_array_indices(shape, result_shape=result))
    elif kind == "mask":
        index = draw(hnp.arrays(bool, shape[: draw(st.integers(1, len(shape)))]))
    else:  # grid values stay 0.15 away from the threshold: h v cannot change the mask
        return (lambda x: x[x > 0.25]), [x]
    return (lambda x: x[index]), [x]


@case_of("scatter_add")
@st.composite
def scatter_add_case(draw):
    trailing = draw(hnp.array_shapes(min_dims=0, max_dims=2, max_side=4))
    k, size = draw(st.integers(1, 8)), draw(st.integers(1, 5))
    index = draw(hnp.arrays(np.int64, (k,), elements=st.integers(0, size - 1)))
    return (lambda v: md.scatter_add(v, index, size)), [draw(arrays((k,) + trailing))]


@case_of("linear")
@st.composite
def linear_case(draw):
    """A dense matrix, or the inverse of a prefactored sparse one (``linear``'s two uses)."""
    from tests.minidiff.test_primitives import linear_operator

    apply, adjoint, n_in = draw(linear_operator())
    columns = draw(st.sampled_from([(), (1,), (3,)]))
    return (lambda x: md.linear(apply, adjoint, x)), [draw(arrays((n_in,) + columns))]


UNARY_PRIMITIVES = ["negative", "exp", "log", "sqrt", "sin", "cos", "tan", "tanh", "abs"]
BINARY_PRIMITIVES = ["add", "subtract", "multiply", "divide", "power", "maximum", "minimum"]

for _name in UNARY_PRIMITIVES:
    CASES[_name] = [unary_case(_name)]
CASES["negative"].append(unary_case("neg_operator"))
for _name in BINARY_PRIMITIVES:
    CASES[_name] = [binary_case(_name), binary_with_constant_case(_name)]
for _name, _op in [("add", "add"), ("subtract", "sub"), ("multiply", "mul"), ("divide", "div")]:
    CASES[_name].append(binary_case(_op + "_operator"))
CASES["power"].append(binary_case("pow_operator"))
for _name in ("sum", "mean", "max"):
    CASES[_name] = [reduction_case(_name)]

# detach, floor and to_index are left out: their outputs are constants, without a tangent
# (their own tests below).
CONSTANT_OUTPUTS = ("detach", "floor", "to_index")
PRIMITIVES = sorted(
    name
    for name in md.__all__
    if inspect.isfunction(getattr(md, name))
    and getattr(md, name).__module__ == primitives.__name__
    and name not in CONSTANT_OUTPUTS
)


def test_detach_carries_no_tangent():
    """detach's output is a constant: no tangent (zero), and x * detach(x)'s tangent is
    detach(x) t."""
    x = md.tensor([1.5, -2.0])
    with md.tangents({x: np.array([1.0, 3.0])}):
        held = md.detach(x)
        product = x * held
    assert held.tangent is None
    np.testing.assert_array_equal(product.tangent, [1.5, -6.0])


def test_floor_and_to_index_carry_no_tangent():
    """floor (a step) and to_index (an index) are constants: x - floor(x)'s tangent is
    x's, and to_index gives a plain integer array."""
    x = md.tensor([1.5, -2.25])
    with md.tangents({x: np.array([1.0, 3.0])}):
        cell = md.floor(x)
        fraction = x - cell
        index = md.to_index(cell)
    assert cell.tangent is None
    np.testing.assert_array_equal(fraction.tangent, [1.0, 3.0])
    assert isinstance(index, np.ndarray) and index.dtype == np.int64
    np.testing.assert_array_equal(index, [1, -3])


def test_every_exported_primitive_has_a_jvp_case():
    """A new primitive in md.__all__ fails here until its JVP is tested (and the test below
    fails if it has no JVP: record refuses tangents then)."""
    assert len(PRIMITIVES) >= 33
    missing = sorted(set(PRIMITIVES) - set(CASES))
    assert not missing, f"primitives without a JVP test case: {missing}"


@pytest.mark.parametrize("name", PRIMITIVES)
@settings(max_examples=3, deadline=None)
@given(data=st.data())
def test_every_exported_primitive_propagates_a_tangent(name, data):
    """Each primitive, given tangents on all inputs, gives its output a tangent of the
    output's shape (a primitive recorded without ``jvp=`` raises NotImplementedError here),
    and its source passes a JVP to ``record`` (or lets ``_elementwise`` pass it)."""
    source = inspect.getsource(getattr(md, name))
    assert "jvp=" in source or "return _elementwise(" in source
    f, args = data.draw(CASES[name][0])
    xs = [md.tensor(a) for a in args]
    with md.tangents({x: np.ones(x.shape) for x in xs}):
        out = f(*xs)
    assert out.tangent is not None and out.tangent.shape == out.shape


CASE_IDS = [(name, i) for name in sorted(CASES) for i in range(len(CASES[name]))]


@pytest.mark.parametrize("name, i", CASE_IDS)
@SETTINGS
@given(data=st.data(), seed=st.integers(0, 2**16))
def test_jvp(name, i, data, seed):
    f, args = data.draw(CASES[name][i])
    assert_jvp_matches(f, *args, seed=seed)


# ---------------------------------------------------------------------------------------------
# The checker can fail
# ---------------------------------------------------------------------------------------------


def sin_with_wrong_jvp(x):
    """sin whose VJP is right and whose JVP uses sin instead of cos."""
    x = md.as_tensor(x)
    return record(
        "sin_wrong_jvp",
        np.sin(x.data),
        (x,),
        lambda g: (g * np.cos(x.data),),
        jvp=lambda t: t * np.sin(x.data),
    )


def maximum_ties_to_b(a, b):
    """maximum whose JVP sends a tie to b (its VJP sends it to a)."""
    a, b = md.as_tensor(a), md.as_tensor(b)
    wins = a.data >= b.data
    return record(
        "max_ties_to_b",
        np.maximum(a.data, b.data),
        (a, b),
        lambda g: (np.where(wins, g, 0.0), np.where(wins, 0.0, g)),
        jvp=lambda ta, tb: np.where(a.data > b.data, ta, tb),
    )


def test_checker_finds_wrong_jvps():
    x = np.linspace(0.2, 1.2, 4)
    with pytest.raises(AssertionError, match="<u, Jv>"):
        assert_jvp_matches(sin_with_wrong_jvp, x)
    ties = np.array([1.0, 2.0, 3.0])
    with pytest.raises(AssertionError, match="<u, Jv>"):
        assert_jvp_matches(maximum_ties_to_b, ties, ties.copy(), fd=False)
    assert_jvp_matches(md.maximum, ties, ties.copy(), fd=False)  # the real one agrees


def test_primitive_without_jvp_refuses_tangents():
    with pytest.raises(NotImplementedError, match="'wrong_sin' has no JVP"):
        md.jvp(wrong_sin, (np.ones(3),), (np.ones(3),))
    # Without tangents it still works (reverse mode only).
    assert md.grad(lambda x: md.sum(wrong_sin(x)))(np.ones(3)).shape == (3,)


# ---------------------------------------------------------------------------------------------
# Kinks: the identity holds with the documented subgradients
# ---------------------------------------------------------------------------------------------


def test_kinks_agree_with_reverse_mode():
    tied = np.array([[1.0, 3.0, 3.0], [2.0, 0.0, 2.0], [4.0, 4.0, 4.0]])
    for axis in (None, 0, 1, (0, 1)):
        for keepdims in (False, True):

            def f(x, axis=axis, keepdims=keepdims):
                return md.max(x, axis=axis, keepdims=keepdims)

            assert_jvp_matches(f, tied, fd=False)
    a = np.array([1.0, 2.0, -1.0, 0.5])
    b = np.array([1.0, 3.0, -1.0, 0.0])
    assert_jvp_matches(md.maximum, a, b, fd=False)
    assert_jvp_matches(md.minimum, a, b, fd=False)
    assert_jvp_matches(lambda x: md.maximum(x, 1.0), a, fd=False)  # a constant bound
    assert_jvp_matches(lambda x: md.clip(x, -1.0, 1.0), a, fd=False)  # on both bounds
    assert_jvp_matches(md.abs, np.array([0.0, -1.0, 2.0]), fd=False)
    zero_rows = np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 2.0]])
    assert_jvp_matches(md.normalize, zero_rows, fd=False)
    assert_jvp_matches(md.norm, zero_rows, fd=False)
    # The tangent values themselves at the ties: maximum and minimum take a's, max the mean.
    _, t = md.jvp(md.maximum, (a, b), (np.ones(4), np.zeros(4)))
    np.testing.assert_array_equal(t, [1.0, 0.0, 1.0, 1.0])
    _, t = md.jvp(md.minimum, (a, b), (np.zeros(4), np.ones(4)))
    np.testing.assert_array_equal(t, [0.0, 0.0, 0.0, 1.0])
    _, t = md.jvp(lambda x: md.max(x, axis=1), (tied,), (np.arange(9.0).reshape(3, 3),))
    np.testing.assert_allclose(t, [1.5, 4.0, 7.0])


# ---------------------------------------------------------------------------------------------
# jvp and tangents: the interface
# ---------------------------------------------------------------------------------------------


def test_jvp_accepts_tensors_numbers_and_lists():
    x = md.tensor([1.0, 2.0], requires_grad=True)
    value, t = md.jvp(lambda x, s: x * s, (x, 3.0), ([1, 0], 1.0))
    np.testing.assert_array_equal(value, [3.0, 6.0])
    np.testing.assert_array_equal(t, [3.0 + 1.0, 2.0])
    assert x.tangent is None and x.grad is None  # the given tensor is copied, not touched
    # An output that does not depend on the primals: zero tangent.
    value, t = md.jvp(lambda x: np.ones(2), (x,), (np.ones(2),))
    np.testing.assert_array_equal(t, np.zeros(2))
    value, t = md.jvp(lambda x: md.tensor(np.ones(2)), (x,), (np.ones(2),))
    np.testing.assert_array_equal(t, np.zeros(2))


def test_jvp_keeps_float32():
    x = np.array([1.0, 2.0], dtype=np.float32)
    value, t = md.jvp(lambda x: md.exp(x) * 2.0, (x,), (np.ones(2),))
    assert value.dtype == np.float32 and t.dtype == np.float32
    np.testing.assert_allclose(t, 2 * np.exp(x), rtol=1e-6)


def test_jvp_refuses_bad_tangents():
    x = np.ones((2, 3))
    with pytest.raises(ValueError, match=r"tangent 1 has shape \(3,\), expected \(2, 3\)"):
        md.jvp(md.add, (x, x), (x, np.ones(3)))
    with pytest.raises(ValueError, match=r"tangent 0 must be a real number array of shape"):
        md.jvp(md.exp, (x,), (np.ones((2, 3), dtype=complex),))
    with pytest.raises(ValueError, match=r"tangent 0 .*got dtype bool"):
        md.jvp(md.exp, (x,), (np.ones((2, 3), dtype=bool),))
    with pytest.raises(ValueError, match="2 primals but 1 tangents"):
        md.jvp(md.add, (x, x), (x,))
    with pytest.raises(TypeError, match="tuples or lists"):
        md.jvp(md.exp, x, x)
    with pytest.raises(ValueError, match=r"has shape \(2,\), expected \(3,\)"):
        with md.tangents({md.tensor(np.ones(3)): np.ones(2)}):
            pass
    with pytest.raises(ValueError, match="only floating-point tensors can have tangents"):
        with md.tangents({md.Tensor(np.arange(3)): np.ones(3)}):
            pass
    with pytest.raises(TypeError, match="keys must be minidiff Tensors"):
        with md.tangents({"x": np.ones(3)}):
            pass


def test_tangents_context_restores_and_nests():
    x = md.tensor([1.0, 2.0])
    with md.tangents({x: [1.0, 0.0]}):
        with md.tangents({x: [0.0, 1.0]}):
            np.testing.assert_array_equal((x * x).tangent, [0.0, 4.0])
        np.testing.assert_array_equal((x * x).tangent, [2.0, 0.0])
        y = x * 3.0
    assert x.tangent is None
    np.testing.assert_array_equal(y.tangent, [3.0, 0.0])  # computed tangents stay
    with pytest.raises(RuntimeError), md.tangents({x: [1.0, 1.0]}):
        raise RuntimeError("inside")
    assert x.tangent is None  # restored on errors too


def test_forward_and_reverse_coexist():
    """A parameter with a tangent on the tape: backward gives the same gradient as without
    the tangent, and the output's tangent is the JVP."""
    rng = np.random.default_rng(3)
    x0, v = rng.normal(size=(4, 3)), rng.normal(size=(4, 3))
    light = np.array([3.0, 4.0, 5.0])

    def f(x):
        return md.sum(md.normalize(x) * md.tanh(md.dot(x, light))[:, None] ** 2)

    plain = md.tensor(x0, requires_grad=True)
    f(plain).backward()
    both = md.tensor(x0, requires_grad=True)
    with md.tangents({both: v}):
        out = f(both)
    out.backward()
    np.testing.assert_array_equal(both.grad, plain.grad)
    np.testing.assert_allclose(out.tangent, np.sum(plain.grad * v), rtol=1e-12)


def test_no_grad_and_detach_stop_tangents():
    """What reverse mode treats as a constant, forward mode does too."""
    x = md.tensor([1.0, 2.0])
    with md.tangents({x: [1.0, 1.0]}):
        assert (x * 2.0).tangent is not None
        assert (x.detach() * 2.0).tangent is None
        assert x.is_differentiated() and not x.detach().is_differentiated()
        with md.no_grad():
            assert (x * 2.0).tangent is None
    assert not x.is_differentiated()
    assert md.tensor(1.0, requires_grad=True).is_differentiated()


def test_anomaly_mode_checks_tangents():
    x = md.tensor([0.0, 1.0])
    with md.detect_anomaly(), md.tangents({x: [1.0, 1.0]}), np.errstate(divide="ignore"):
        with pytest.raises(FloatingPointError, match="JVP of 'sqrt'"):
            md.sqrt(x)
