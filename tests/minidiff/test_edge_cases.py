"""Edge cases found by a fuzz run (issue 22): NaN/inf traps, silently wrong inputs, and
errors that must name the argument and what was expected. Each test can fail: it checks a
value or a message that the old behaviour did not give."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import minidiff as md
from minidiff.optim import Adam, box

finite = st.floats(-10.0, 10.0, allow_nan=False, allow_infinity=False)


def grad_of(f, *values):
    """Gradients of f(*leaves) (a scalar) with respect to every argument."""
    leaves = [md.tensor(v, requires_grad=True) for v in values]
    f(*leaves).backward()
    return [leaf.grad for leaf in leaves]


# ---------------------------------------------------------------------------------------------
# 1. where with NaN/inf in the unselected branch
# ---------------------------------------------------------------------------------------------


@settings(max_examples=60, deadline=None)
@given(
    cond=st.lists(st.booleans(), min_size=1, max_size=6),
    bad=st.sampled_from([np.inf, -np.inf, np.nan]),
)
def test_where_gives_exactly_zero_to_the_unselected_branch(cond, bad):
    """The upstream gradient is inf/NaN exactly where each branch is *not* selected (a
    multiply by a +-inf/NaN weight there): a 0/1 mask multiplied in would give NaN, the
    selection gives 0."""
    cond = np.array(cond)
    n = len(cond)
    a = md.tensor(np.where(cond, 1.0, bad), requires_grad=True)  # bad where unselected
    b = md.tensor(np.where(cond, bad, 2.0), requires_grad=True)
    y = md.where(cond, a, b)
    assert np.isfinite(y.data).all()
    with np.errstate(invalid="ignore"):
        (y * np.full(n, 3.0)).sum().backward()
    np.testing.assert_array_equal(a.grad, np.where(cond, 3.0, 0.0))
    np.testing.assert_array_equal(b.grad, np.where(cond, 0.0, 3.0))


def test_where_vjp_selects_rather_than_multiplies():
    """An inf in the upstream gradient where a is not selected: a's gradient there is 0."""
    cond = np.array([True, False])
    a = md.tensor([1.0, 1.0], requires_grad=True)
    w = md.tensor([2.0, np.inf])  # the loss weighs the b-side element by inf
    (md.where(cond, a, 0.0) * w).sum().backward()
    np.testing.assert_array_equal(a.grad, [2.0, 0.0])


def test_where_documented_trap_and_double_where():
    x = md.tensor([4.0, -1.0], requires_grad=True)
    with np.errstate(invalid="ignore"):
        md.where(x.data > 0, md.sqrt(x), 0.0).sum().backward()
    assert x.grad[0] == 0.25 and np.isnan(x.grad[1])  # the trap, as in JAX
    x.grad = None
    safe = md.where(x.data > 0, x, 1.0)
    md.where(x.data > 0, md.sqrt(safe), 0.0).sum().backward()
    np.testing.assert_array_equal(x.grad, [0.25, 0.0])  # the idiom in the docstring
    assert "double where" in md.where.__doc__


# ---------------------------------------------------------------------------------------------
# 2. power with a zero or negative base
# ---------------------------------------------------------------------------------------------


@settings(max_examples=80, deadline=None)
@given(b=st.integers(1, 5).map(float))
def test_power_at_zero_base_has_finite_gradients(b):
    ga, gb = grad_of(lambda x, y: (x**y).sum(), [0.0], [b])
    assert ga[0] == (1.0 if b == 1 else 0.0)  # b 0^(b-1)
    assert gb[0] == 0.0  # 0^b log 0: defined as 0 (PyTorch)


def test_power_zero_exponent_has_zero_slope_everywhere():
    ga, gb = grad_of(lambda x, y: (x**y).sum(), [0.0, -2.0, 3.0], [0.0, 0.0, 0.0])
    np.testing.assert_array_equal(ga, [0.0, 0.0, 0.0])
    assert gb[0] == 0.0 and gb[2] == np.log(3.0)


@settings(max_examples=80, deadline=None)
@given(a=st.floats(-5.0, -0.1), b=st.integers(-3, 4).map(float))
def test_power_negative_base_integer_exponent(a, b):
    """d/da is real for an integer-valued exponent; d/db is NaN (log of a negative)."""
    with np.errstate(invalid="ignore"):
        ga, gb = grad_of(lambda x, y: (x**y).sum(), [a], [b])
    expected = 0.0 if b == 0 else b * a ** (b - 1)
    np.testing.assert_allclose(ga[0], expected, rtol=1e-12)
    assert np.isnan(gb[0])


def test_power_negative_base_fractional_exponent_is_nan_like_numpy():
    with np.errstate(invalid="ignore"):
        y = md.tensor([-2.0], requires_grad=True) ** 0.5
        y.sum().backward()
    assert np.isnan(y.data[0])


def test_power_forward_mode_agrees_at_zero_base():
    value, tangent = md.jvp(lambda x: x**2.0, (np.array([0.0, 3.0]),), (np.ones(2),))
    np.testing.assert_array_equal(tangent, [0.0, 6.0])
    _, tangent = md.jvp(
        lambda y: md.tensor([0.0, 2.0]) ** y, (np.array([2.0, 2.0]),), (np.ones(2),)
    )
    np.testing.assert_allclose(tangent, [0.0, 4.0 * np.log(2.0)])


# ---------------------------------------------------------------------------------------------
# 3. max / maximum with ties and NaN
# ---------------------------------------------------------------------------------------------


def test_maximum_tie_goes_to_a_and_minimum_too():
    ga, gb = grad_of(lambda x, y: md.maximum(x, y).sum(), [1.0], [1.0])
    assert (ga[0], gb[0]) == (1.0, 0.0)
    ga, gb = grad_of(lambda x, y: md.minimum(x, y).sum(), [1.0], [1.0])
    assert (ga[0], gb[0]) == (1.0, 0.0)


@pytest.mark.parametrize("op", [md.maximum, md.minimum])
def test_maximum_nan_propagates_and_takes_the_gradient(op):
    a = md.tensor([np.nan, 1.0, np.nan], requires_grad=True)
    b = md.tensor([1.0, np.nan, np.nan], requires_grad=True)
    y = op(a, b)
    assert np.isnan(y.data).all()  # as np.maximum / np.minimum
    y.sum().backward()
    np.testing.assert_array_equal(a.grad, [1.0, 0.0, 1.0])  # the NaN input; both: a
    np.testing.assert_array_equal(b.grad, [0.0, 1.0, 0.0])
    _, t = md.jvp(lambda u: op(u, b.data), (a.data,), (np.ones(3),))
    np.testing.assert_array_equal(t, [1.0, 0.0, 1.0])  # forward mode: the same choice


def test_max_ties_split_and_nan_takes_the_gradient():
    (g,) = grad_of(lambda x: md.max(x), [3.0, 1.0, 3.0])
    np.testing.assert_array_equal(g, [0.5, 0.0, 0.5])
    (g,) = grad_of(lambda x: md.max(x, axis=1).sum(), [[1.0, np.nan, 2.0], [np.nan, 0, np.nan]])
    np.testing.assert_array_equal(g, [[0.0, 1.0, 0.0], [0.5, 0.0, 0.5]])
    _, t = md.jvp(lambda u: md.max(u), (np.array([1.0, np.nan]),), (np.array([5.0, 7.0]),))
    assert t == 7.0


# ---------------------------------------------------------------------------------------------
# 4. float16 is refused, naming the dtype
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "make",
    [
        lambda: md.tensor(np.ones(2, np.float16)),
        lambda: md.tensor([1.0, 2.0], dtype=np.float16),
        lambda: md.tensor(np.ones(2, np.float16), requires_grad=True),
        lambda: md.exp(np.ones(2, np.float16)),
        lambda: md.tensor([1.0]) * np.ones(1, np.float16),
    ],
)
def test_float16_is_refused_naming_the_dtype(make):
    with pytest.raises(TypeError, match=r"dtype float16 is not supported.*float32 or float64"):
        make()


def test_supported_dtypes_still_work():
    assert md.tensor(np.ones(2, np.float32)).dtype == np.float32
    assert md.tensor([1, 2]).dtype == np.float64
    assert md.tensor([1, 2], dtype=np.int32).dtype == np.int32


# ---------------------------------------------------------------------------------------------
# 5. sqrt at 0 and normalize of the zero vector
# ---------------------------------------------------------------------------------------------


def test_sqrt_at_zero_gradient_is_inf_as_in_pytorch():
    (g,) = grad_of(lambda x: md.sqrt(x).sum(), [0.0, 4.0])
    np.testing.assert_array_equal(g, [np.inf, 0.25])


@settings(max_examples=40, deadline=None)
@given(shape=st.sampled_from([(3,), (2, 3), (1, 4)]))
def test_normalize_and_norm_of_zero_vector_are_zero_not_nan(shape):
    x = md.tensor(np.zeros(shape), requires_grad=True)
    y = md.normalize(x)
    np.testing.assert_array_equal(y.data, np.zeros(shape))
    (y * np.arange(1.0, 1.0 + y.size).reshape(shape)).sum().backward()
    np.testing.assert_array_equal(x.grad, np.zeros(shape))
    _, t = md.jvp(md.normalize, (np.zeros(shape),), (np.ones(shape),))
    np.testing.assert_array_equal(t, np.zeros(shape))
    (g,) = grad_of(lambda v: md.norm(v).sum(), np.zeros(shape))
    np.testing.assert_array_equal(g, np.zeros(shape))


# ---------------------------------------------------------------------------------------------
# 6. Adam after a huge gradient
# ---------------------------------------------------------------------------------------------


def adam_reference(grads, lr=0.1, b1=0.9, b2=0.999, eps=1e-8):
    """The paper's formula in extended precision (np.longdouble reaches 1e4932 on x86)."""
    ld = np.longdouble
    theta, m, v = ld(0), ld(0), ld(0)
    out = []
    for t, g in enumerate(grads, start=1):
        g = ld(g)
        m = ld(b1) * m + (1 - ld(b1)) * g
        v = ld(b2) * v + (1 - ld(b2)) * g * g
        theta -= ld(lr) * (m / (1 - ld(b1) ** t)) / (np.sqrt(v / (1 - ld(b2) ** t)) + ld(eps))
        out.append(float(theta))
    return out


@pytest.mark.skipif(
    np.finfo(np.longdouble).maxexp <= 1024, reason="needs a longdouble wider than float64"
)
@settings(max_examples=40, deadline=None)
@given(
    huge=st.floats(1e160, 1e300),
    small=st.lists(st.floats(-1e3, 1e3).filter(lambda g: abs(g) > 1e-3), min_size=1, max_size=5),
)
def test_adam_keeps_moving_after_a_huge_gradient(huge, small):
    p = md.tensor([0.0], requires_grad=True)
    opt = Adam([p], lr=0.1)
    positions = []
    for g in [huge, *small]:
        p.grad = np.array([g])
        opt.step()
        positions.append(p.data[0])
    assert np.isfinite(opt.v[0]).all()
    np.testing.assert_allclose(positions, adam_reference([huge, *small]), rtol=1e-9)
    assert len(set(positions)) == len(positions)  # every step moved


def test_adam_plain_gradients_are_untouched_by_the_scaling():
    p = md.tensor([0.0, 1.0], requires_grad=True)
    opt = Adam([p], lr=0.1)
    p.grad = np.array([1e-3, 2.0])
    opt.step()
    assert opt.scale == [1.0]
    g = p.grad  # the plain formula, operation for operation
    m, v = 0.9 * np.zeros(2) + (1 - 0.9) * g, 0.999 * np.zeros(2) + (1 - 0.999) * g * g
    expected = np.array([0.0, 1.0]) - 0.1 * (m / (1 - 0.9**1)) / (
        np.sqrt(v / (1 - 0.999**1)) + 1e-8
    )
    np.testing.assert_array_equal(p.data, expected)


# ---------------------------------------------------------------------------------------------
# 7. an empty box
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("lo, hi", [(1.0, 0.0), (np.array([0.0, 2.0]), np.array([1.0, 1.0]))])
def test_box_with_lo_above_hi_is_refused(lo, hi):
    with pytest.raises(ValueError, match=r"box: lo must be <= hi.*lo=.*hi="):
        box(lo, hi)


def test_box_with_equal_bounds_is_a_point():
    np.testing.assert_array_equal(box(0.5, 0.5)(np.array([0.0, 1.0])), [0.5, 0.5])


# ---------------------------------------------------------------------------------------------
# 8. complex tensors cannot require grad
# ---------------------------------------------------------------------------------------------


def test_complex_requires_grad_is_refused():
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no ComplexWarning on the way
        with pytest.raises(TypeError, match=r"complex tensor \(dtype complex128\) cannot"):
            md.tensor(np.array([1 + 2j]), requires_grad=True)
        c = md.tensor(np.array([1 + 2j]))  # a constant keeps its imaginary part
    assert c.dtype == np.complex128 and c.data[0] == 1 + 2j
    with pytest.raises(TypeError, match="complex"):
        c.requires_grad = True


# ---------------------------------------------------------------------------------------------
# 9. in-place edits of saved constants and computed tensors
# ---------------------------------------------------------------------------------------------


def test_in_place_edit_of_a_saved_constant_is_caught():
    x = md.tensor(3.0, requires_grad=True)
    c = md.tensor(2.0)
    y = x * c
    c.data[...] = 50
    with pytest.raises(RuntimeError, match=r"'multiply' needs the values of its input 1"):
        y.backward()


def test_in_place_edit_of_a_saved_computed_tensor_is_the_documented_gap():
    """Tensor.data: writes into tensors computed on the tape are not seen (watching them
    cost ~5 ms of a 10 ms render step); if this starts raising, update the docs."""
    x = md.tensor([0.5], requires_grad=True)
    s = md.sin(x)
    y = s * s
    s.data[...] = 3.0
    y.backward()
    np.testing.assert_allclose(x.grad, [2 * 3.0 * np.cos(0.5)])  # the edited value


# ---------------------------------------------------------------------------------------------
# 10-13. errors that name the argument and what was expected
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "f, kind, what",
    [
        (lambda x: x * 2.0, ValueError, r"got Tensor of shape \(3,\)"),
        (lambda x: np.ones(3), ValueError, r"got ndarray of shape \(3,\)"),
        (lambda x: "loss", TypeError, "got str"),
        (lambda x: None, TypeError, "got NoneType"),
    ],
)
def test_grad_of_a_non_scalar_function_names_what_it_returned(f, kind, what):
    with pytest.raises(kind, match=r"f must return a scalar.*" + what):
        md.grad(f)(np.ones(3))
    with pytest.raises(kind, match=r"numerical_grad: f must return a scalar.*" + what):
        md.numerical_grad(f, [np.ones(3)], 0, 1e-6)


@pytest.mark.parametrize("cls", [Adam, md.optim.SGD])
def test_wrong_shape_gradient_names_the_parameter_and_both_shapes(cls):
    a = md.tensor([1.0], requires_grad=True)
    b = md.tensor(np.ones((2, 3)), requires_grad=True)
    opt = cls([a, b], lr=0.1)
    a.grad, b.grad = np.ones(1), np.ones(3)  # would broadcast silently
    with pytest.raises(ValueError, match=r"params\[1\] has shape \(3,\).*shape \(2, 3\)"):
        opt.step()
    assert a.data[0] == 1.0  # nothing half-applied


@pytest.mark.parametrize(
    "data, shown", [("abc", "str 'abc'"), (None, "NoneType"), ([1.0, "x"], "list"), ({}, "dict")]
)
def test_tensor_of_non_numbers_is_a_type_error_naming_it(data, shown):
    with pytest.raises(
        TypeError, match=r"tensor: cannot make a tensor of " + shown + r".*expected"
    ):
        md.tensor(data)


def test_bool_of_a_tensor():
    assert bool(md.tensor([2.0])) and not bool(md.tensor(0.0))
    assert not md.tensor([[0.0]])
    with pytest.raises(ValueError, match=r"minidiff: the truth value of a Tensor of shape \(2,\)"):
        bool(md.tensor([1.0, 0.0]))
    with pytest.raises(ValueError, match="minidiff"):
        if md.tensor([1.0, 2.0]):  # formerly silently true
            pass
