"""The tape: what gets recorded, how gradients flow and accumulate, what is freed, dtypes, memory,
anomaly mode, and the Tensor / grad API around it."""

from __future__ import annotations

import gc
import tracemalloc

import numpy as np
import pytest

import minidiff as md
from minidiff.tensor import Node


def leaf(values, dtype=None):
    return md.tensor(values, requires_grad=True, dtype=dtype)


# ---------------------------------------------------------------------------------------------
# Gradient flow
# ---------------------------------------------------------------------------------------------


def test_gradients_accumulate_across_backward_calls():
    x = leaf([1.0, -2.0, 3.0])
    (x * x).sum().backward()
    np.testing.assert_array_equal(x.grad, [2.0, -4.0, 6.0])
    (3.0 * x).sum().backward()  # a second forward pass; its gradient adds on
    np.testing.assert_array_equal(x.grad, [5.0, -1.0, 9.0])
    x.grad = None  # what optimizer.zero_grad() does
    (x * x).sum().backward()
    np.testing.assert_array_equal(x.grad, [2.0, -4.0, 6.0])


def test_diamond_graph_sums_contributions():
    """x feeds y, and both x and y feed z: every path's contribution is added."""
    x = leaf([0.5, -1.5])
    y = md.sin(x)
    z = y * y + x * y + md.exp(x)
    z.sum().backward()
    s, c = np.sin(x.data), np.cos(x.data)
    np.testing.assert_allclose(x.grad, 2 * s * c + s + x.data * c + np.exp(x.data), rtol=1e-14)


def test_same_tensor_as_both_operands():
    x = leaf([3.0])
    (x * x * x).backward(np.array([1.0]))
    np.testing.assert_allclose(x.grad, [27.0])
    y = leaf(2.0)
    (y / y + y - y).backward()
    np.testing.assert_allclose(y.grad, 0.0, atol=1e-15)


def test_seed_scales_the_gradient_and_defaults_to_one_for_scalars():
    x = leaf([1.0, 2.0])
    (x * x).backward(np.array([10.0, -1.0]))
    np.testing.assert_array_equal(x.grad, [20.0, -4.0])
    for out_shape in [(), (1,), (1, 1)]:  # any one-element output gets the seed 1
        z = leaf(2.0)
        (z * z).reshape(out_shape).backward()
        assert z.grad == 4.0
    w = leaf([1.0, 2.0])
    w.backward(np.array([3.0, 4.0]))  # backward on a leaf itself: its grad is the seed
    np.testing.assert_array_equal(w.grad, [3.0, 4.0])


def test_leaf_grad_is_a_fresh_array():
    """.grad never aliases the seed or a VJP's array, so editing it changes nothing else."""
    x = leaf([1.0, 2.0])
    seed = np.array([1.0, 1.0])
    (x + 0.0).backward(seed)
    x.grad[0] = 99.0
    np.testing.assert_array_equal(seed, [1.0, 1.0])
    y = leaf([1.0, 2.0])
    y.backward(seed)
    assert not np.shares_memory(y.grad, seed)


# ---------------------------------------------------------------------------------------------
# The tape is freed after backward
# ---------------------------------------------------------------------------------------------


def test_second_backward_through_freed_tape_raises():
    x = leaf([1.0, 2.0])
    y = (x * x).sum()
    y.backward()
    with pytest.raises(RuntimeError, match=r"backward: the tape through 'sum'.*freed"):
        y.backward()
    np.testing.assert_array_equal(x.grad, [2.0, 4.0])  # unchanged by the failed call


def test_shared_subgraph_is_freed_by_the_first_backward():
    """Two losses sharing an intermediate: the first backward frees the shared part, so the
    second names the freed primitive instead of silently giving a partial gradient."""
    x = leaf([1.0, 2.0])
    shared = md.exp(x)
    first, second = shared.sum(), (shared * 2.0).sum()
    first.backward()
    with pytest.raises(RuntimeError, match="'exp'"):
        second.backward()


def test_recomputing_the_forward_pass_allows_another_backward():
    x = leaf([1.0, 2.0])
    for _ in range(3):
        (x * x).sum().backward()
    np.testing.assert_array_equal(x.grad, [6.0, 12.0])


def test_freed_nodes_drop_their_arrays():
    x = leaf(np.ones(1000))
    y = md.exp(x)
    node = y.node
    y.sum().backward()
    assert node.freed and node.vjp is None and node.inputs == () and node.grad is None


# ---------------------------------------------------------------------------------------------
# What is recorded: requires_grad, no_grad, detach, constants
# ---------------------------------------------------------------------------------------------


def test_constants_record_nothing_and_get_no_grad():
    c = md.tensor([1.0, 2.0])  # requires_grad=False
    arr = np.array([3.0, 4.0])
    y = md.exp(c) * arr + c
    assert not y.requires_grad and y.node is None
    x = leaf([0.5, 0.5])
    z = (x * c + arr * x + c).sum()
    z.backward()
    assert c.grad is None
    np.testing.assert_array_equal(arr, [3.0, 4.0])
    np.testing.assert_array_equal(x.grad, c.data + arr)


def test_no_grad_records_nothing():
    x = leaf([1.0, 2.0])
    assert md.is_grad_enabled()
    with md.no_grad():
        assert not md.is_grad_enabled()
        y = md.sin(x) * x + 1.0
        assert not y.requires_grad and y.node is None
        with md.no_grad():  # nesting restores the outer state
            pass
        assert not md.is_grad_enabled()
    assert md.is_grad_enabled()
    assert (x * 2.0).requires_grad
    with pytest.raises(ValueError, match="does not require grad"):
        y.sum().backward()
    assert x.grad is None


def test_no_grad_restores_state_after_an_exception():
    with pytest.raises(KeyError), md.no_grad():
        raise KeyError("boom")
    assert md.is_grad_enabled()


def test_enable_grad_records_inside_no_grad_and_restores_it():
    x = leaf([1.0, 2.0])
    with md.no_grad():
        with md.enable_grad():
            assert md.is_grad_enabled()
            loss = (md.sin(x) * x).sum()
        assert not md.is_grad_enabled()
        loss.backward()  # the tape of the enabled block, even here
    np.testing.assert_allclose(x.grad, np.cos(x.data) * x.data + np.sin(x.data))
    with pytest.raises(KeyError), md.no_grad(), md.enable_grad():
        raise KeyError("boom")
    assert md.is_grad_enabled()


def test_detach_cuts_the_tape():
    x = leaf([1.0, 2.0])
    d = x.detach()
    assert not d.requires_grad and d.node is None
    assert np.shares_memory(d.data, x.data)  # same values, no copy
    (d * x + x).sum().backward()  # d is a constant: d/dx (d x + x) = d + 1
    np.testing.assert_array_equal(x.grad, [2.0, 3.0])
    y = md.exp(leaf([0.0]))
    assert y.detach().node is None


def test_only_leaves_receive_grad():
    x = leaf([1.0, 2.0])
    y = x * 2.0
    y.sum().backward()
    assert y.grad is None
    np.testing.assert_array_equal(x.grad, [2.0, 2.0])


# ---------------------------------------------------------------------------------------------
# dtypes: float64 by default, float32 preserved end to end
# ---------------------------------------------------------------------------------------------


def test_default_dtype_is_float64():
    assert md.tensor([1, 2, 3]).dtype == np.float64
    assert md.tensor(2).dtype == np.float64
    assert md.tensor([1.0]).dtype == np.float64
    assert md.tensor(np.arange(3)).dtype == np.float64
    assert md.tensor([1, 2], dtype=np.float32).dtype == np.float32
    assert md.tensor(np.ones(2, np.float32)).dtype == np.float32
    assert md.tensor(np.ones(2, np.float32), dtype=np.float64).dtype == np.float64


def f32(*shape, lo=0.5, hi=1.5, seed=0):
    rng = np.random.default_rng(seed)
    return md.tensor(rng.uniform(lo, hi, size=shape).astype(np.float32), requires_grad=True)


# Every primitive applied to float32 tensors, with Python-number constants where they fit.
FLOAT32_CASES = {
    "add": lambda a, b: a + 1,
    "radd": lambda a, b: 2.5 + a,
    "subtract": lambda a, b: a - b - 0.5,
    "rsubtract": lambda a, b: 1.0 - a,
    "multiply": lambda a, b: a * b * 3,
    "rmultiply": lambda a, b: 0.1 * a,
    "divide": lambda a, b: a / b / 2.0,
    "rdivide": lambda a, b: 1 / a,
    "negative": lambda a, b: -a,
    "power": lambda a, b: a**2 + a**0.5 + a**b,
    "rpower": lambda a, b: 2.0**a,
    "matmul": lambda a, b: a @ b.T,
    "exp": lambda a, b: md.exp(a),
    "log": lambda a, b: md.log(a),
    "sqrt": lambda a, b: md.sqrt(a),
    "sin": lambda a, b: md.sin(a),
    "cos": lambda a, b: md.cos(a),
    "tan": lambda a, b: md.tan(a),
    "tanh": lambda a, b: md.tanh(a),
    "abs": lambda a, b: md.abs(a - 1),
    "maximum": lambda a, b: md.maximum(a, 1.0) + md.maximum(0, b),
    "minimum": lambda a, b: md.minimum(a, 1) + md.minimum(b, a),
    "clip": lambda a, b: md.clip(a, 0.8, 1.2) + md.clip(b, 0, 1.0),
    "where": lambda a, b: md.where(a > 1.0, a, 0.0) + md.where(b > 1, 1.0, b),
    "sum": lambda a, b: md.sum(a, axis=1) + a.sum(),
    "mean": lambda a, b: md.mean(a, axis=(0, 1), keepdims=True) + a.mean(),
    "max": lambda a, b: md.max(a, axis=0) + a.max(),
    "dot": lambda a, b: md.dot(a, b),
    "cross": lambda a, b: md.cross(a, b),
    "norm": lambda a, b: md.norm(a, axis=1, keepdims=True) + md.norm(b, axis=0, keepdims=True),
    "normalize": lambda a, b: md.normalize(a),
    "reshape": lambda a, b: md.reshape(a, (-1,)) + b.reshape(3, 2).sum(),
    "transpose": lambda a, b: md.transpose(a, (1, 0)) + a.T,
    "broadcast_to": lambda a, b: md.broadcast_to(a, (4, 2, 3)),
    "stack": lambda a, b: md.stack([a, b], axis=-1),
    "concatenate": lambda a, b: md.concatenate([a, b], axis=0),
    "getitem": lambda a, b: a[0] + a[np.array([1, 1])] + a[a > 1.0].sum() + a[:, ::-1],
    "scatter_add": lambda a, b: md.scatter_add(a, np.array([2, 2]), 3),
}


@pytest.mark.parametrize("name", sorted(FLOAT32_CASES))
def test_float32_preserved_end_to_end(name):
    a, b = f32(2, 3), f32(2, 3, seed=1)
    out = FLOAT32_CASES[name](a, b)
    assert out.dtype == np.float32, f"{name}: forward gave {out.dtype}"
    loss = (out * out).sum() * 0.5 + 1  # a float32 loss through more Python constants
    assert loss.dtype == np.float32
    loss.backward()
    for x in (a, b):
        assert x.grad is None or x.grad.dtype == np.float32, f"{name}: grad {x.grad.dtype}"
    assert a.grad is not None


def test_float32_grad_stays_float32_when_mixed_with_float64_constants():
    """A float64 constant makes the forward result float64 (NumPy promotion), but the
    gradient of a float32 leaf is float32, also after accumulating over several calls."""
    x = f32(3)
    w = np.array([1.0, 2.0, 3.0])  # float64
    for _ in range(2):
        (x * w).sum().backward()
    assert x.grad.dtype == np.float32
    np.testing.assert_allclose(x.grad, 2 * w, rtol=1e-6)


def test_float32_seed_and_value_and_grad():
    x = f32(2)
    (x * 2).backward(np.array([1.0, 1.0]))  # a float64 seed is cast to the output's dtype
    assert x.grad.dtype == np.float32
    g = md.grad(lambda x: (x * x).sum())(np.ones(3, np.float32))
    assert g.dtype == np.float32


# ---------------------------------------------------------------------------------------------
# Memory: nothing accumulates over many iterations
# ---------------------------------------------------------------------------------------------


def live_nodes() -> int:
    gc.collect()
    return sum(1 for o in gc.get_objects() if isinstance(o, Node))


def test_memory_does_not_grow_over_200_iterations():
    x = leaf(np.linspace(-1, 1, 2000))
    w = np.cos(np.arange(2000.0))
    opt = md.optim.SGD([x], lr=1e-3)

    def iteration():
        opt.zero_grad()
        y = md.tanh(x * w) + md.exp(-x * x)
        loss = (md.sum(y[::2] * y[1::2]) + md.max(y)) / 7.0
        loss.backward()
        opt.step()

    for _ in range(5):  # warm-up: caches, first-time allocations
        iteration()
    nodes_before = live_nodes()
    tracemalloc.start()
    try:
        iteration()
        baseline, _ = tracemalloc.get_traced_memory()
        for _ in range(200):
            iteration()
        current, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert live_nodes() == nodes_before
    # One iteration's arrays are ~16 KB each; a leak of one per iteration would add > 3 MB.
    assert current - baseline < 200_000, f"grew by {current - baseline} bytes"
    assert peak - baseline < 2_000_000


def test_forward_passes_without_backward_are_freed():
    """No global tape: an undifferentiated forward pass goes away with its tensors."""
    x = leaf(np.ones(100))
    before = live_nodes()
    for _ in range(200):
        y = md.exp(md.sin(x) * 2.0).sum()
    assert y.node is not None
    del y
    assert live_nodes() == before


# ---------------------------------------------------------------------------------------------
# Anomaly mode
# ---------------------------------------------------------------------------------------------


def test_anomaly_mode_names_log_in_forward():
    x = leaf([1.0, 0.0])
    with np.errstate(divide="ignore"):
        assert np.isneginf(md.log(x).data[1])  # off by default: -inf passes silently
        with md.detect_anomaly(), pytest.raises(FloatingPointError, match="forward of 'log'"):
            md.log(x)


def test_anomaly_mode_names_sqrt_in_backward():
    x = leaf([4.0, 0.0])
    y = md.sqrt(x) * 3.0  # forward is finite: sqrt(0) = 0 ...
    with np.errstate(divide="ignore"), md.detect_anomaly():
        with pytest.raises(FloatingPointError, match="VJP of 'sqrt'"):
            y.sum().backward()  # ... but d sqrt / dx = inf at 0


def test_anomaly_mode_is_off_again_after_the_block():
    with md.detect_anomaly():
        pass
    x = leaf([0.0])
    with np.errstate(divide="ignore", invalid="ignore"):
        md.sqrt(x).sum().backward()
    assert np.isinf(x.grad[0])


def test_anomaly_mode_passes_finite_computations():
    x = leaf([1.0, 2.0])
    with md.detect_anomaly():
        md.sum(md.log(x) * md.sqrt(x)).backward()
    np.testing.assert_allclose(x.grad, 1 / np.sqrt(x.data) + np.log(x.data) / (2 * np.sqrt(x.data)))


# ---------------------------------------------------------------------------------------------
# The Tensor API and the function transformations
# ---------------------------------------------------------------------------------------------


def test_tensor_attributes_and_methods():
    data = np.arange(6.0).reshape(2, 3)
    t = md.tensor(data, requires_grad=True)
    data[0, 0] = 100.0  # tensor() copies
    assert t.data[0, 0] == 0.0
    assert isinstance(t.data, np.ndarray) and t.grad is None and t.requires_grad
    assert t.shape == (2, 3) and t.ndim == 2 and t.dtype == np.float64 and t.size == 6
    assert t.numpy() is t.data
    assert md.tensor([[4.5]]).item() == 4.5 and isinstance(md.tensor(2.0).item(), float)
    assert t.T.shape == (3, 2) and t.transpose().shape == (3, 2)
    assert t.transpose(1, 0).shape == (3, 2) and t.transpose((1, 0)).shape == (3, 2)
    assert t.reshape(3, 2).shape == (3, 2) and t.reshape((6,)).shape == (6,)
    assert t.sum().shape == () and t.sum(axis=0).shape == (3,)
    assert t.mean(axis=1, keepdims=True).shape == (2, 1)
    np.testing.assert_array_equal(t.max(axis=-1).data, [2.0, 5.0])
    assert "requires_grad=True" in repr(t)


def test_comparisons_return_plain_boolean_arrays():
    x = md.tensor([1.0, 2.0, 3.0], requires_grad=True)
    other = md.tensor([3.0, 2.0, 1.0])
    for result, expected in [
        (x < 2.0, [True, False, False]),
        (x <= other, [True, True, False]),
        (x > np.array([0.0, 5.0, 0.0]), [True, False, True]),
        (x >= 2, [False, True, True]),
        (x == other, [False, True, False]),
        (x != 2.0, [True, False, True]),
    ]:
        assert type(result) is np.ndarray and result.dtype == bool
        np.testing.assert_array_equal(result, expected)


def test_operators_with_arrays_on_the_left_return_tensors():
    x = md.tensor([1.0, 2.0], requires_grad=True)
    a = np.array([3.0, 4.0])
    for out in (a + x, a - x, a * x, a / x, a**x, np.ones((2, 2)) @ x):
        assert isinstance(out, md.Tensor) and out.requires_grad


def test_grad_and_value_and_grad():
    def f(a, b, c):
        return md.sum(a * b) + c * 0.0

    a, b = np.array([1.0, 2.0]), np.array([3.0, 4.0])
    value, g = md.value_and_grad(f)(a, b, 5.0)
    assert value == 11.0
    np.testing.assert_array_equal(g, b)
    ga, gb = md.grad(f, argnums=(0, 1))(a, b, 5.0)
    np.testing.assert_array_equal(ga, b)
    np.testing.assert_array_equal(gb, a)
    # An argument the output does not depend on gets a zero gradient of its shape.
    (gc_,) = md.grad(lambda a, b: md.sum(a * a), argnums=(1,))(a, np.ones((2, 2)))
    np.testing.assert_array_equal(gc_, np.zeros((2, 2)))
    # Integer inputs are differentiated as float64; inputs are never modified.
    g_int = md.grad(lambda x: md.sum(x * x))(np.array([1, 2]))
    assert g_int.dtype == np.float64
    np.testing.assert_array_equal(g_int, [2.0, 4.0])
    np.testing.assert_array_equal(a, [1.0, 2.0])


def test_numerical_grad_is_central_differences():
    g = md.numerical_grad(lambda x: md.sum(x**3), [np.array([1.0, 2.0])], 0, 1e-3)
    np.testing.assert_allclose(g, [3.0 + 1e-6, 12.0 + 1e-6], rtol=1e-9)  # f''' h^2 / 6 term


def test_check_grad_calls_f_with_tensors_on_both_sides():
    """The finite-difference side sees the same kind of argument as the tape side, so f may
    use Tensor-only attributes (here ``.data``, which on an ndarray is a memoryview)."""
    seen = set()

    def f(x):
        seen.add(type(x))
        return md.sum(x * x) + 0.0 * float(x.data.sum())

    rel, g_ad, _ = md.check_grad(f, np.array([1.0, -2.0]))
    assert seen == {md.Tensor}
    assert rel < 1e-8
    np.testing.assert_allclose(g_ad, [2.0, -4.0])
    # Several checked arguments: each is a Tensor in every call; the others are as given.
    seen_pairs = set()

    def g(a, w, b):
        seen_pairs.add((type(a), type(w), type(b)))
        return md.sum(a * b * w)

    w = np.array([2.0, 3.0])
    rel, (ga, gb), _ = md.check_grad(g, np.ones(2), w, np.ones(2), argnums=(0, 2))
    assert seen_pairs == {(md.Tensor, np.ndarray, md.Tensor)}
    assert rel < 1e-8
    np.testing.assert_allclose(ga, w)


def test_zero_size_arrays():
    """Empty selections (a renderer with no hits) flow through gather, broadcasting and the
    reverse pass, giving zero gradients of the right shape."""
    x = leaf(np.ones((4, 3)))
    empty = x[np.array([], dtype=np.int64)]  # (0, 3)
    (empty * 2.0).sum().backward()
    np.testing.assert_array_equal(x.grad, np.zeros((4, 3)))
    y = leaf(np.zeros(0))
    (y + np.zeros((5, 0))).sum().backward()  # broadcast a (0,) input over 5 rows
    assert y.grad.shape == (0,)
    v = leaf(np.ones((0, 2)))
    md.scatter_add(v, np.array([], dtype=np.int64), 3).sum().backward()
    assert v.grad.shape == (0, 2)
