# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # Solutions to lesson 2 (arrays, broadcasting, the two modes)

# %%
import numpy as np

import minidiff as md

rng = np.random.default_rng(0)

# %% [markdown]
# ## Exercise 1: a VJP with broadcasting on both sides
#
# `out[i, j] = x[j] · y[i, 0]`, shape `(4, 3)`. For an output adjoint `g` (4, 3):
# `x̄[j] = Σᵢ g[i, j] y[i, 0]` (the leading axis summed away) and
# `ȳ[i, 0] = Σⱼ g[i, j] x[j]` (the size-1 axis summed, kept).

# %%
x_data, y_data, g = rng.normal(size=3), rng.normal(size=(4, 1)), rng.normal(size=(4, 3))
x_bar = md.unbroadcast(g * y_data, (3,))
y_bar = md.unbroadcast(g * x_data[None, :], (4, 1))
x = md.tensor(x_data, requires_grad=True)
y = md.tensor(y_data, requires_grad=True)
(x[None, :] * y).backward(g)
print("x.grad", x.grad, " by hand", x_bar)
np.testing.assert_allclose(x.grad, x_bar, rtol=1e-14)
np.testing.assert_allclose(y.grad, y_bar, rtol=1e-14)
np.testing.assert_allclose(x_bar, (g * y_data).sum(axis=0), rtol=1e-14)

# %% [markdown]
# ## Exercise 2: the Jacobian of `normalize`
#
# `n = x/‖x‖`; `dn = (dx − n (n·dx))/‖x‖`, so `J = (I − n nᵀ)/‖x‖`, and `J x = 0`.

# %%
x0 = np.array([0.3, -1.2, 2.0])
J = np.stack([md.jvp(md.normalize, (x0,), (e,))[1] for e in np.eye(3)], axis=1)
n = x0 / np.linalg.norm(x0)
J_formula = (np.eye(3) - np.outer(n, n)) / np.linalg.norm(x0)
print("J by three JVPs:\n", J)
np.testing.assert_allclose(J, J_formula, atol=1e-15)
along_x = md.jvp(md.normalize, (x0,), (x0,))[1]
print("J x =", along_x)
assert np.abs(along_x).max() < 1e-15

# %% [markdown]
# ## Exercise 3: the step size in float32
#
# With `ε₃₂ ≈ 1.2e-7` the balance moves to `h ≈ ε₃₂^(1/3) ≈ 5e-3` and the best relative
# error to about `ε₃₂^(2/3) ≈ 2.4e-5`: finite differences in float32 check gradients only to
# a few digits. (The exact value is computed in float64.)

# %%
n_big = 200
A = rng.normal(size=(300, n_big)) / np.sqrt(n_big)
x_big = rng.normal(size=n_big)
direction = rng.normal(size=n_big)
direction /= np.linalg.norm(direction)


def loss(x, a):
    return (md.tanh(md.matmul(a, md.as_tensor(x))) ** 2).sum()


exact = float(md.grad(lambda x: loss(x, A))(x_big) @ direction)
A32, x32, d32 = A.astype(np.float32), x_big.astype(np.float32), direction.astype(np.float32)
steps = np.logspace(-6, -0.5, 23)
errors = []
with md.no_grad():
    for h in steps:
        h32 = np.float32(h)
        plus = loss(x32 + h32 * d32, A32).item()
        minus = loss(x32 - h32 * d32, A32).item()
        errors.append(abs((plus - minus) / (2 * float(h32)) - exact) / abs(exact))
best = int(np.argmin(errors))
print(f"float32: best step {steps[best]:.1e}, relative error {errors[best]:.1e}")
assert 1e-4 < steps[best] < 1e-1
assert 1e-7 < errors[best] < 1e-3
