"""``minidiff.either``: one formula for tensors and arrays. On plain arrays each function
equals its NumPy formula bit for bit; given a tensor on either side it records on the tape
(the primitives themselves are tested against central differences in test_primitives.py)
with the same values."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

import minidiff as md
from minidiff.either import as_column, cross_last, dot_last, square_root

VALUES = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False)


@st.composite
def vector_pairs(draw, last=3):
    rows = draw(st.integers(0, 6))
    shape = (rows, last) if draw(st.booleans()) else (last,)
    other = (rows, last) if draw(st.booleans()) else (last,)
    return draw(arrays(np.float64, shape, elements=VALUES)), draw(
        arrays(np.float64, other, elements=VALUES)
    )


@settings(max_examples=40)
@given(pair=st.one_of(vector_pairs(3), vector_pairs(5)))
def test_plain_arrays_give_numpys_bits(pair):
    a, b = pair
    assert not isinstance(dot_last(a, b), md.Tensor)
    np.testing.assert_array_equal(dot_last(a, b), np.sum(a * b, axis=-1))
    if a.shape[-1] == 3:
        np.testing.assert_array_equal(cross_last(a, b), np.cross(a, b))
    np.testing.assert_array_equal(as_column(a[..., 0]), np.reshape(a[..., 0], (-1, 1)))
    np.testing.assert_array_equal(square_root(np.abs(a)), np.sqrt(np.abs(a)))


@settings(max_examples=20)
@given(pair=vector_pairs(3))
def test_a_tensor_on_either_side_records_on_the_tape(pair):
    a, b = pair
    for left, right in (
        (md.tensor(a, requires_grad=True), b),
        (a, md.tensor(b, requires_grad=True)),
    ):
        for f, plain in ((dot_last, dot_last(a, b)), (cross_last, cross_last(a, b))):
            out = f(left, right)
            assert isinstance(out, md.Tensor) and out.requires_grad
            np.testing.assert_allclose(out.data, plain, rtol=1e-12, atol=1e-9)
    t = md.tensor(np.abs(a) + 1.0, requires_grad=True)
    md.sum(square_root(t) * as_column(t[..., 0]) if t.data.ndim == 2 else square_root(t)).backward()
    assert t.grad is not None


@md.compile(shared=("axis",))
def _either_formula(a, b, axis):
    """A formula written with ``either``'s functions only: rows a, b (k, 3), ``axis`` (3,)."""
    c = cross_last(a, b)
    return as_column(square_root(dot_last(c, c))) * axis + as_column(dot_last(a, axis) * b[:, 0])


@settings(max_examples=20, deadline=None)
@given(
    rows=st.integers(1, 7),
    seed=st.integers(0, 2**32 - 1),
)
def test_a_formula_written_with_either_compiles_to_its_plain_values(rows, seed):
    """Inside ``minidiff.compile`` the functions are the primitives they name (traced
    arrays count as tensors): the compiled formula gives what it gives on plain arrays,
    bit for bit, and its gradient is the tape's."""
    rng = np.random.default_rng(seed)
    a, b, axis = rng.normal(size=(rows, 3)), rng.normal(size=(rows, 3)), rng.normal(size=3)
    plain = _either_formula.function(a, b, axis)
    np.testing.assert_array_equal(md.as_tensor(_either_formula(a, b, axis)).data,
                                  md.as_tensor(plain).data)  # fmt: skip
    grads = []
    for run in (_either_formula, _either_formula.function):
        ta = md.tensor(a, requires_grad=True)
        md.sum(run(ta, b, axis)).backward()
        grads.append(ta.grad)
    np.testing.assert_allclose(grads[0], grads[1], rtol=1e-12, atol=1e-12)
