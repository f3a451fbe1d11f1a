"""Bad input gets a clear exception of the documented type, naming the operation (and the
shapes, where shapes are the problem)."""

from __future__ import annotations

import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

import minidiff as md
from minidiff import optim


def leaf(values):
    return md.tensor(values, requires_grad=True)


def shapes_pattern(name, *shapes):
    """A regex: the operation's name, then each shape in order (e.g. 'add.*(2,).*(3,)')."""
    return re.escape(name) + "".join(".*" + re.escape(str(s)) for s in shapes)


# ---------------------------------------------------------------------------------------------
# Shape mismatches
# ---------------------------------------------------------------------------------------------

BINARY = {
    "add": md.add,
    "subtract": md.subtract,
    "multiply": md.multiply,
    "divide": md.divide,
    "power": md.power,
    "maximum": md.maximum,
    "minimum": md.minimum,
}
OPERATORS = {
    "add": lambda a, b: a + b,
    "subtract": lambda a, b: a - b,
    "multiply": lambda a, b: a * b,
    "divide": lambda a, b: a / b,
    "power": lambda a, b: a**b,
}


@pytest.mark.parametrize("name", sorted(BINARY))
def test_binary_broadcast_mismatch_names_op_and_shapes(name):
    a, b = leaf(np.ones((2, 3))), leaf(np.ones((4,)))
    with pytest.raises(ValueError, match=shapes_pattern(name, (2, 3), (4,))):
        BINARY[name](a, b)
    with pytest.raises(ValueError, match=shapes_pattern(name, (2, 3), (4,))):
        BINARY[name](a, np.ones(4))  # a plain array operand too


@pytest.mark.parametrize("name", sorted(OPERATORS))
def test_operator_broadcast_mismatch_names_op_and_shapes(name):
    a = leaf(np.ones((2, 3)))
    with pytest.raises(ValueError, match=shapes_pattern(name, (2, 3), (2,))):
        OPERATORS[name](a, np.ones(2))
    with pytest.raises(ValueError, match=shapes_pattern(name, (2,), (2, 3))):
        OPERATORS[name](np.ones(2), a)  # reflected operator: operands in written order


def test_matmul_mismatch():
    with pytest.raises(ValueError, match=shapes_pattern("matmul", (2, 3), (2, 3))):
        leaf(np.ones((2, 3))) @ leaf(np.ones((2, 3)))
    with pytest.raises(ValueError, match=shapes_pattern("matmul", (3,), (4,))):
        md.matmul(leaf(np.ones(3)), np.ones(4))


def test_where_mismatch():
    with pytest.raises(ValueError, match=shapes_pattern("where", (3,), (2,), (4,))):
        md.where(np.ones(3, bool), leaf(np.ones(2)), np.ones(4))


def test_clip_mismatch():
    with pytest.raises(ValueError, match=shapes_pattern("clip", (2,), (3,))):
        md.clip(leaf(np.ones(2)), np.zeros(3), 1.0)


def test_dot_and_cross_mismatch():
    with pytest.raises(ValueError, match=shapes_pattern("dot", (2, 3), (2, 4))):
        md.dot(leaf(np.ones((2, 3))), np.ones((2, 4)))
    with pytest.raises(ValueError, match=shapes_pattern("dot", (2, 3), (4, 3))):
        md.dot(leaf(np.ones((2, 3))), np.ones((4, 3)))
    with pytest.raises(ValueError, match=shapes_pattern("cross", (2, 2), (2, 3))):
        md.cross(leaf(np.ones((2, 2))), np.ones((2, 3)))
    with pytest.raises(ValueError, match=shapes_pattern("cross", (2, 3), (4, 3))):
        md.cross(leaf(np.ones((2, 3))), np.ones((4, 3)))


def test_shape_manipulation_mismatch():
    x = leaf(np.ones((2, 3)))
    with pytest.raises(ValueError, match=shapes_pattern("reshape", (2, 3), (4,))):
        md.reshape(x, (4,))
    with pytest.raises(ValueError, match=shapes_pattern("reshape", (2, 3), (5, 5))):
        x.reshape(5, 5)
    with pytest.raises(ValueError, match=shapes_pattern("broadcast_to", (2, 3), (4, 3, 2))):
        md.broadcast_to(x, (4, 3, 2))
    with pytest.raises(ValueError, match=shapes_pattern("broadcast_to", (2, 3), (5,))):
        md.broadcast_to(x, 5)
    with pytest.raises(ValueError, match=shapes_pattern("stack", (2, 3), (3, 2))):
        md.stack([x, np.ones((3, 2))])
    with pytest.raises(ValueError, match=shapes_pattern("concatenate", (2, 3), (2, 4))):
        md.concatenate([x, np.ones((2, 4))], axis=0)


@pytest.mark.parametrize(
    ("call", "name", "shapes"),
    [
        (lambda a: md.normalize(a), "normalize", "()"),
        (lambda a: md.norm(a), "norm", "()"),
        (lambda a: md.dot(a, a), "dot", "() and ()"),
        (lambda a: md.dot(a, np.ones(3)), "dot", "() and (3,)"),
        (lambda a: md.dot(np.ones(3), a), "dot", "(3,) and ()"),
    ],
)
def test_vector_primitives_refuse_0d_inputs(call, name, shapes):
    """These work along a last axis; a 0-d input has none (NumPy says 'too many indices')."""
    pattern = re.escape(f"{name}: needs vectors, shape (..., n), not 0-d; got shape {shapes}")
    with pytest.raises(ValueError, match=pattern):
        call(leaf(2.0))


@pytest.mark.parametrize(
    ("shape", "axis"), [((0,), None), ((0, 3), None), ((0, 3), 0), ((2, 0), 1), ((2, 0, 3), (0, 1))]
)
def test_mean_of_no_elements(shape, axis):
    """NumPy would warn 'Mean of empty slice' and return NaN."""
    pattern = re.escape(f"mean: no elements to average (shape {shape}, axis={axis})")
    with pytest.raises(ValueError, match=pattern):
        md.mean(leaf(np.ones(shape)), axis=axis)


def test_mean_over_a_non_empty_axis_of_an_empty_array_is_fine():
    out = md.mean(leaf(np.ones((0, 3))), axis=1)  # 3 elements per (non-existent) row
    assert out.shape == (0,)


@pytest.mark.parametrize("name", ["stack", "concatenate"])
@pytest.mark.parametrize("empty", [[], (), iter([])])
def test_stack_and_concatenate_of_nothing(name, empty):
    with pytest.raises(ValueError, match=f"{name}: needs at least one tensor, got an empty"):
        getattr(md, name)(empty)


def test_scatter_add_bad_index():
    values = leaf(np.ones((3, 2)))
    with pytest.raises(ValueError, match=r"scatter_add: index must be .* length 3"):
        md.scatter_add(values, np.array([0, 1]), 4)
    with pytest.raises(ValueError, match=r"scatter_add: index must be"):
        md.scatter_add(values, np.array([0.0, 1.0, 2.0]), 4)
    with pytest.raises(ValueError, match=r"scatter_add: indices must lie in \[0, 4\)"):
        md.scatter_add(values, np.array([0, 1, 4]), 4)
    with pytest.raises(ValueError, match=r"scatter_add: indices must lie"):
        md.scatter_add(values, np.array([0, -1, 2]), 4)


@pytest.mark.parametrize(
    "index, message",
    [
        (np.array([0, 5]), "index 5 is out of bounds for axis 0 with size 4"),  # row gather
        ((0, 7), "index 7 is out of bounds for axis 1 with size 3"),  # basic indexing
        (np.array([[0, 9]]), "index 9 is out of bounds"),  # 2-D integer array
        (np.array([0.5]), "must be of integer"),  # a float index
    ],
)
def test_getitem_bad_index_names_op_and_shape(index, message):
    x = leaf(np.ones((4, 3)))
    with pytest.raises(IndexError, match=rf"getitem: .*{message}.*shape \(4, 3\)"):
        x[index]


# ---------------------------------------------------------------------------------------------
# backward
# ---------------------------------------------------------------------------------------------


def test_backward_on_non_scalar_without_seed():
    y = leaf(np.ones((2, 3))) * 2.0
    with pytest.raises(ValueError, match=r"backward: the output has shape \(2, 3\)"):
        y.backward()


def test_backward_seed_of_wrong_shape():
    y = leaf(np.ones((2, 3))) * 2.0
    with pytest.raises(ValueError, match=r"backward: seed gradient has shape \(3,\).*\(2, 3\)"):
        y.backward(np.ones(3))


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_backward_non_finite_seed(bad):
    y = leaf([1.0, 2.0]) * 2.0
    with pytest.raises(ValueError, match="backward: the seed gradient contains NaN or inf"):
        y.backward(np.array([1.0, bad]))
    z = (leaf(1.0) * 2.0).sum()
    with pytest.raises(ValueError, match="backward: the seed gradient contains NaN or inf"):
        z.backward(bad)


def test_double_backward_through_freed_tape():
    x = leaf([1.0, 2.0])
    y = md.sum(md.exp(x) * x)
    y.backward()
    with pytest.raises(RuntimeError, match=r"backward: the tape through 'sum' .* freed"):
        y.backward()


def test_backward_on_a_constant():
    with pytest.raises(ValueError, match="backward: this tensor does not require grad"):
        md.tensor([1.0]).sum().backward()


# ---------------------------------------------------------------------------------------------
# Construction, NumPy interop, function transformations
# ---------------------------------------------------------------------------------------------


def test_integer_tensor_cannot_require_grad():
    with pytest.raises(TypeError, match="tensor: only floating-point tensors can require grad"):
        md.tensor([1, 2], requires_grad=True, dtype=np.int64)


NOT_FLOAT = [np.array([1, 2]), np.array([1, 2], dtype=np.uint8), np.array([True, False])]


@pytest.mark.parametrize("values", NOT_FLOAT, ids=lambda v: str(v.dtype))
def test_tensor_constructor_refuses_grad_for_integer_and_bool(values):
    """Tensor(int_array, requires_grad=True) used to truncate every gradient to 0."""
    pattern = rf"Tensor: only floating-point tensors can require grad, got dtype {values.dtype}"
    with pytest.raises(TypeError, match=pattern):
        md.Tensor(values, requires_grad=True)
    t = md.Tensor(values)  # as a constant it is fine
    with pytest.raises(TypeError, match=pattern):
        t.requires_grad = True  # ... and stays one
    assert not t.requires_grad


def test_data_of_a_tensor_that_requires_grad_stays_floating_point():
    x = leaf([1.0, 2.0])
    with pytest.raises(TypeError, match="Tensor.data: only floating-point tensors .* int64"):
        x.data = np.array([1, 2])
    np.testing.assert_array_equal(x.data, [1.0, 2.0])  # unchanged
    x.data = np.array([3.0, 4.0], dtype=np.float32)  # another float dtype is fine
    assert x.dtype == np.float32


@settings(max_examples=30, deadline=None)
@given(
    dtype=st.sampled_from(
        [np.int8, np.int16, np.int32, np.int64, np.uint16, np.uint64, np.bool_, np.complex128]
    ),
    shape=hnp.array_shapes(min_dims=0, max_dims=3, max_side=3),
)
def test_no_non_float_dtype_can_require_grad(dtype, shape):
    values = np.zeros(shape, dtype=dtype)
    with pytest.raises(TypeError, match="only floating-point tensors can require grad"):
        md.Tensor(values, requires_grad=True)
    with pytest.raises(TypeError, match="only floating-point tensors can require grad"):
        md.tensor(values, requires_grad=True, dtype=dtype)


def test_numpy_ufunc_on_tensor_is_refused():
    """np.exp(tensor) would silently drop the gradient; it is a TypeError instead."""
    with pytest.raises(TypeError):
        np.exp(leaf([1.0]))


def test_value_and_grad_needs_scalar_output():
    with pytest.raises(ValueError, match=r"value_and_grad: f must return a scalar.*\(2,\)"):
        md.grad(lambda x: x * 2.0)(np.ones(2))
    with pytest.raises(ValueError, match="value_and_grad: argnums 1 but only 1 arguments"):
        md.grad(lambda x: md.sum(x), argnums=1)(np.ones(2))


def test_anomaly_errors_name_the_primitive():
    with np.errstate(all="ignore"), md.detect_anomaly():
        with pytest.raises(FloatingPointError, match="anomaly: forward of 'log'"):
            md.log(leaf([0.0]))
        with pytest.raises(FloatingPointError, match="anomaly: forward of 'divide'"):
            leaf([1.0]) / 0.0
        y = md.sqrt(leaf([0.0, 1.0])).sum()
        with pytest.raises(FloatingPointError, match=r"anomaly: the VJP of 'sqrt'.*\(2,\)"):
            y.backward()


# ---------------------------------------------------------------------------------------------
# Optimisers
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("cls", [optim.SGD, optim.Adam])
def test_optimizer_bad_params(cls):
    name = cls.__name__
    with pytest.raises(ValueError, match=f"{name}: params is empty"):
        cls([])
    with pytest.raises(TypeError, match=rf"{name}: params\[0\] must be a leaf Tensor"):
        cls([md.tensor([1.0])])  # does not require grad
    with pytest.raises(TypeError, match=rf"{name}: params\[1\] must be a leaf Tensor"):
        cls([leaf([1.0]), leaf([1.0]) * 2.0])  # not a leaf
    with pytest.raises(TypeError, match=rf"{name}: params\[0\] must be a leaf Tensor"):
        cls([np.ones(2)])
    with pytest.raises(ValueError, match=f"{name}: 1 projections for 2 params"):
        cls([leaf([1.0]), leaf([1.0])], project=[optim.box(0, 1)])


BAD_LR = [
    (float("nan"), ValueError, r"lr must be a finite number >= 0, got nan"),
    (float("inf"), ValueError, r"lr must be a finite number >= 0, got inf"),
    (-0.1, ValueError, r"lr must be a finite number >= 0, got -0.1"),
    ("0.1", TypeError, r"lr must be a real number, got str '0.1'"),
    (None, TypeError, r"lr must be a real number, got NoneType"),
    (True, TypeError, r"lr must be a real number, got bool"),
    ([0.1, "x"], TypeError, r"lr\[1\] must be a real number, got str"),
    ([0.1, -1.0], ValueError, r"lr\[1\] must be a finite number >= 0, got -1.0"),
]


@pytest.mark.parametrize("cls", [optim.SGD, optim.Adam])
@pytest.mark.parametrize(("lr", "error", "message"), BAD_LR)
def test_optimizer_bad_learning_rate(cls, lr, error, message):
    with pytest.raises(error, match=f"{cls.__name__}: {message}"):
        cls([leaf([1.0]), leaf([2.0])], lr=lr)


@pytest.mark.parametrize(
    ("kwargs", "error", "message"),
    [
        ({"betas": (1, 1)}, ValueError, r"betas\[0\] must lie in \[0, 1\), got 1.0"),
        ({"betas": (0.9, 1.0)}, ValueError, r"betas\[1\] must lie in \[0, 1\), got 1.0"),
        ({"betas": (-0.1, 0.9)}, ValueError, r"betas\[0\] must lie in \[0, 1\), got -0.1"),
        ({"betas": (0.9, float("nan"))}, ValueError, r"betas\[1\] must lie in \[0, 1\)"),
        ({"betas": (0.9, "0.99")}, TypeError, r"betas\[1\] must be a real number"),
        ({"betas": 0.9}, TypeError, r"betas must be a pair \(b1, b2\), got 0.9"),
        ({"betas": (0.9, 0.99, 0.1)}, TypeError, r"betas must be a pair"),
        ({"eps": 0.0}, ValueError, r"eps must be a finite number > 0, got 0.0"),
        ({"eps": -1e-8}, ValueError, r"eps must be a finite number > 0"),
        ({"eps": float("inf")}, ValueError, r"eps must be a finite number > 0, got inf"),
        ({"eps": float("nan")}, ValueError, r"eps must be a finite number > 0, got nan"),
        ({"eps": "1e-8"}, TypeError, r"eps must be a real number, got str"),
    ],
)
def test_adam_bad_betas_and_eps(kwargs, error, message):
    with pytest.raises(error, match=f"Adam: {message}"):
        optim.Adam([leaf([1.0])], **kwargs)


@pytest.mark.parametrize(
    ("momentum", "error"),
    [(1.0, ValueError), (-0.5, ValueError), (float("nan"), ValueError), ("0.9", TypeError)],
)
def test_sgd_bad_momentum(momentum, error):
    with pytest.raises(error, match="SGD: momentum must"):
        optim.SGD([leaf([1.0])], momentum=momentum)


@settings(max_examples=60, deadline=None)
@given(
    lr=st.floats(0.0, 10.0),
    b1=st.floats(0.0, 1.0, exclude_max=True),
    b2=st.floats(0.0, 1.0, exclude_max=True),
    eps=st.floats(1e-12, 1.0),
    g=st.floats(-1e3, 1e3),
)
def test_adam_step_is_finite_for_every_accepted_setting(lr, b1, b2, eps, g):
    """What the checks let through never produces NaN parameters (the failure they prevent)."""
    x = leaf([1.0])
    opt = optim.Adam([x], lr=lr, betas=(b1, b2), eps=eps)
    for _ in range(3):
        x.grad = np.array([g])
        opt.step()
    assert np.isfinite(x.data).all()


@pytest.mark.parametrize("cls", [optim.SGD, optim.Adam])
def test_optimizer_refuses_non_finite_gradient(cls):
    x, y = leaf([1.0, 2.0]), leaf([3.0])
    opt = cls([x, y])
    x.grad = np.array([1.0, 1.0])
    y.grad = np.array([np.nan])
    with pytest.raises(ValueError, match=rf"{cls.__name__}.step: gradient of params\[1\]"):
        opt.step()
    # Nothing was changed, not even the parameter before the bad one.
    np.testing.assert_array_equal(x.data, [1.0, 2.0])
    np.testing.assert_array_equal(y.data, [3.0])
