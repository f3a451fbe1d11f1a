"""Optimisers: SGD and Adam (the paper's Eq. 2) against hand arithmetic, convergence, box
projection, per-parameter learning rates, zero_grad."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

import minidiff as md
from minidiff import optim


def param(values, dtype=None):
    return md.tensor(values, requires_grad=True, dtype=dtype)


def quadratic_loss(theta, A, c):
    """0.5 (theta - c)^T A (theta - c); minimiser c for a positive definite A."""
    d = theta - c
    return 0.5 * md.sum(d * (d @ A))


def random_spd(rng, n):
    m = rng.normal(size=(n, n))
    return m @ m.T + n * np.eye(n)


# ---------------------------------------------------------------------------------------------
# SGD
# ---------------------------------------------------------------------------------------------


def test_sgd_step_is_theta_minus_lr_g():
    theta = param([1.0, -2.0, 0.5])
    start = theta.data.copy()
    opt = optim.SGD([theta], lr=0.1)
    (theta * theta * theta).sum().backward()  # g = 3 theta^2
    g = 3 * start**2
    tensor_object, data_object = theta, theta.data
    opt.step()
    np.testing.assert_allclose(theta.data, start - 0.1 * g, rtol=1e-15)
    assert theta is tensor_object and theta.data is data_object  # updated in place


def test_sgd_momentum():
    theta = param([1.0])
    opt = optim.SGD([theta], lr=0.5, momentum=0.9)
    expected, velocity = 1.0, 0.0
    for _ in range(3):
        opt.zero_grad()
        (theta * theta).sum().backward()
        velocity = 0.9 * velocity + 2 * expected
        expected -= 0.5 * velocity
        opt.step()
        assert theta.data[0] == pytest.approx(expected, rel=1e-15)


# ---------------------------------------------------------------------------------------------
# Adam: Eq. 2 by hand
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("lr, betas, eps", [(0.1, (0.9, 0.999), 1e-8), (0.03, (0.5, 0.8), 1e-3)])
def test_adam_first_three_steps_follow_eq2(lr, betas, eps):
    """The loss sum(theta^4 / 4 - theta) has gradient theta^3 - 1, which changes from step to
    step; the expected trajectory is computed element by element with Python floats."""
    start = [0.5, -1.0, 2.0]
    theta = param(start)
    opt = optim.Adam([theta], lr=lr, betas=betas, eps=eps)
    b1, b2 = betas
    expected = list(start)
    m = [0.0] * 3
    v = [0.0] * 3
    for t in (1, 2, 3):
        opt.zero_grad()
        (theta**4 / 4.0 - theta).sum().backward()
        for k in range(3):
            g = expected[k] ** 3 - 1.0
            m[k] = b1 * m[k] + (1.0 - b1) * g
            v[k] = b2 * v[k] + (1.0 - b2) * g * g
            m_hat = m[k] / (1.0 - b1**t)
            v_hat = v[k] / (1.0 - b2**t)
            expected[k] = expected[k] - lr * m_hat / (math.sqrt(v_hat) + eps)
        opt.step()
        np.testing.assert_allclose(theta.data, expected, rtol=1e-13, atol=1e-15)


def test_adam_first_step_moves_each_coordinate_by_lr():
    """At t = 1, m^ = g and v^ = g^2, so the step is lr * g / (|g| + eps) ~ lr * sign(g)."""
    theta = param([3.0, -4.0, 0.25])
    opt = optim.Adam([theta], lr=0.01)
    g = np.array([2.0, -5.0, 1e-3])
    (theta * g).sum().backward()
    opt.step()
    np.testing.assert_allclose(theta.data, [2.99, -3.99, 0.24], rtol=1e-6)
    np.testing.assert_allclose(
        theta.data, [3.0, -4.0, 0.25] - 0.01 * g / (np.abs(g) + 1e-8), rtol=1e-15
    )


# ---------------------------------------------------------------------------------------------
# Convergence and projection
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_adam_converges_on_convex_quadratic(seed):
    rng = np.random.default_rng(seed)
    n = 4
    A, c = random_spd(rng, n), rng.normal(size=n)
    theta = param(rng.normal(size=n) * 3)
    opt = optim.Adam([theta], lr=0.05)
    for _ in range(1500):
        opt.zero_grad()
        quadratic_loss(theta, A, c).backward()
        opt.step()
    np.testing.assert_allclose(theta.data, c, atol=1e-4)


def test_sgd_converges_on_convex_quadratic():
    rng = np.random.default_rng(3)
    A, c = random_spd(rng, 3), rng.normal(size=3)
    theta = param(np.zeros(3))
    opt = optim.SGD([theta], lr=0.5 / np.linalg.eigvalsh(A).max())
    for _ in range(500):
        opt.zero_grad()
        quadratic_loss(theta, A, c).backward()
        opt.step()
    np.testing.assert_allclose(theta.data, c, atol=1e-8)


@settings(max_examples=25, deadline=None)
@given(
    start=hnp.arrays(np.float64, 5, elements=st.floats(0.0, 1.0)),
    target=hnp.arrays(np.float64, 5, elements=st.floats(-2.0, 3.0)),
    lr=st.floats(0.01, 0.5),
    use_sgd=st.booleans(),
)
def test_box_projection_keeps_params_in_unit_box(start, target, lr, use_sgd):
    """Minimising |theta - target|^2 over [0, 1]^5: every iterate stays in the box, and the
    result is the projection of the target onto the box."""
    theta = param(start)
    cls = optim.SGD if use_sgd else optim.Adam
    opt = cls([theta], lr=lr, project=optim.box(0, 1))
    for _ in range(300):
        opt.zero_grad()
        md.sum((theta - target) ** 2).backward()
        opt.step()
        assert np.all(theta.data >= 0.0) and np.all(theta.data <= 1.0)
    np.testing.assert_allclose(theta.data, np.clip(target, 0, 1), atol=0.05)


def test_box_projection_runs_after_every_step_and_per_parameter():
    a, b = param([0.95, 0.05]), param([0.95, 0.05])
    opt = optim.Adam([a, b], lr=0.2, project=[optim.box(0, 1), None])
    (a * np.array([-1.0, 1.0]) + b * np.array([-1.0, 1.0])).sum().backward()
    opt.step()  # both move by 0.2 away from the centre; only a is projected
    np.testing.assert_allclose(a.data, [1.0, 0.0])
    np.testing.assert_allclose(b.data, [1.15, -0.15])
    box = optim.box(np.array([0.0, -1.0]), np.array([1.0, 0.0]))
    np.testing.assert_array_equal(box(np.array([2.0, 2.0])), [1.0, 0.0])


# ---------------------------------------------------------------------------------------------
# Per-parameter learning rates, zero_grad, bookkeeping
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("cls", [optim.SGD, optim.Adam])
def test_per_parameter_learning_rates(cls):
    a, b = param([1.0, 1.0]), param([1.0])
    opt = cls([a, b], lr=[0.1, 0.001])
    (a.sum() + b.sum()).backward()  # g = 1 everywhere: both SGD and Adam step by lr
    opt.step()
    np.testing.assert_allclose(a.data, [0.9, 0.9], rtol=1e-7)
    np.testing.assert_allclose(b.data, [0.999], rtol=1e-7)
    with pytest.raises(ValueError, match=f"{cls.__name__}: 3 learning rates for 2 params"):
        cls([a, b], lr=[0.1, 0.2, 0.3])


@pytest.mark.parametrize("cls", [optim.SGD, optim.Adam])
def test_zero_grad_resets_and_params_without_grad_are_skipped(cls):
    a, b = param([1.0]), param([2.0])
    opt = cls([a, b], lr=0.1)
    (a * 3.0).sum().backward()
    (a * 3.0).sum().backward()
    np.testing.assert_array_equal(a.grad, [6.0])  # accumulated until zero_grad
    assert b.grad is None
    opt.step()
    assert b.data[0] == 2.0  # no gradient, no step
    opt.zero_grad()
    assert a.grad is None and b.grad is None
    moved = a.data.copy()
    opt.step()  # nothing to do after zero_grad
    np.testing.assert_array_equal(a.data, moved)
    (a * 3.0).sum().backward()
    np.testing.assert_array_equal(a.grad, [3.0])  # starts from zero again


def test_adam_counts_steps_per_parameter():
    """A parameter that skipped a step has its own bias-correction step count."""
    a, b = param([0.0]), param([0.0])
    opt = optim.Adam([a, b], lr=0.1)
    a.sum().backward()
    opt.step()
    opt.zero_grad()
    (a.sum() + b.sum()).backward()
    opt.step()
    assert opt.t == [2, 1]
    np.testing.assert_allclose(b.data, [-0.1], rtol=1e-7)  # a first step: exactly lr


def test_adam_keeps_float32():
    theta = param(np.array([0.5, 1.5], np.float32))
    opt = optim.Adam([theta], lr=0.1, project=optim.box(0, 1))
    for _ in range(3):
        opt.zero_grad()
        ((theta - 0.3) ** 2).sum().backward()
        opt.step()
    assert theta.dtype == np.float32 and theta.grad.dtype == np.float32
    assert opt.m[0].dtype == np.float32 and opt.v[0].dtype == np.float32
