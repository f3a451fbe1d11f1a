# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # Lesson 2 — Arrays, broadcasting, and the two modes
#
# Lesson 1 differentiated scalars. A renderer works on arrays: a light position of shape
# `(3,)` is added to a `(k, 3)` array of hit points, an albedo of shape `(3,)` multiplies an
# `(H·W, 3)` image. For a function `f: ℝⁿ → ℝᵐ` with Jacobian `J` (`m × n`), automatic
# differentiation offers two products, never forming `J`:
#
# * **reverse mode**, the vector-Jacobian product (VJP): `u ↦ Jᵀu` (an output adjoint `u`
#   of shape `m` to an input adjoint of shape `n`), what `backward()` computes;
# * **forward mode**, the Jacobian-vector product (JVP): `v ↦ Jv` (an input direction `v`
#   to the output's directional derivative), what `md.jvp` and `md.tangents` compute.
#
# This lesson shows how a VJP handles broadcasting, checks that the two modes are
# transposes of each other, counts what each costs, and ends with the finite-difference
# check that both are tested against.

# %%
import time

import numpy as np
from course import figures_folder, save_and_show

import minidiff as md
from render.inverse.plot import line_figure

# This lesson's figures go to out/lessons/02_arrays_and_modes/ (or under $LESSONS_OUT).
OUT = figures_folder("02_arrays_and_modes")
rng = np.random.default_rng(2)

# %% [markdown]
# ## Broadcasting and `unbroadcast`
#
# `points + light` with `points` of shape `(k, 3)` and `light` of shape `(3,)` is NumPy
# broadcasting: `light` is used once per row, as if copied `k` times. Used `k` times, its
# adjoint collects `k` contributions (lesson 1's sum over users):
#
#     out[i, j] = points[i, j] + light[j]     ⇒     light̄[j] = Σᵢ out̄[i, j].
#
# A primitive's VJP does not know about broadcasting: `multiply`'s VJP returns `g · b` for
# `a`, an array of the *output's* shape. `backward` then sums it back to the input's shape
# with `md.unbroadcast(g, shape)`: first over the leading axes broadcasting added, then over
# the axes where the input had size 1 (kept as size 1).

# %%
k = 5
points = md.tensor(rng.normal(size=(k, 3)))
light = md.tensor([1.0, 4.0, 2.0], requires_grad=True)
scale = md.tensor(np.full((k, 1), 0.5), requires_grad=True)  # one number per row
out = (points - light) * scale  # (k, 3) - (3,) -> (k, 3); times (k, 1) -> (k, 3)
seed = rng.normal(size=(k, 3))  # an output adjoint, as a loss would send back
node = out.node  # the multiply
g_raw = node.vjp(seed)  # what the primitive returns, before unbroadcasting
print("multiply's VJP returns shapes", [g.shape for g in g_raw])
out.backward(seed)
light_by_hand = -(seed * 0.5).sum(axis=0)  # d out / d light = -scale, summed over rows
scale_by_hand = (seed * (points.data - light.data)).sum(axis=1, keepdims=True)
broadcast_error = max(
    np.abs(light.grad - light_by_hand).max(), np.abs(scale.grad - scale_by_hand).max()
)
print("unbroadcast of a (5, 3) array of ones to (3,):", md.unbroadcast(np.ones((5, 3)), (3,)))
print("and to (5, 1):", md.unbroadcast(np.ones((5, 3)), (5, 1)).ravel())
print(f"light.grad {light.grad}, scale.grad shape {scale.grad.shape}; "
      f"difference to the sums by hand {broadcast_error:.1e}")  # fmt: skip
ones_to_vector = md.unbroadcast(np.ones((5, 3)), (3,))[0]

# %% [markdown]
# The multiply's VJP hands back two `(5, 3)` arrays; `unbroadcast` turns a `(5, 3)` array of
# ones into `[5, 5, 5]` for a `(3,)` input (each entry was used `5`
# <!-- check: ones_to_vector --> times) and into `[3, 3, 3, 3, 3]` for a `(5, 1)` one. The
# gradients `backward` leaves in `light.grad` and `scale.grad` equal the sums written by
# hand to within `1e-15` <!-- check: broadcast_error < -->.
#
# ## Forward mode: tangents travel with values
#
# In forward mode every tensor carries, besides its value `x`, a *tangent* `ẋ = dx/dt`
# along a chosen input direction. Each primitive has a JVP beside its VJP
# (`minidiff/primitives.py`): for `multiply`, `(ȧ, ḃ) ↦ ȧ·b + a·ḃ`. There is no tape to
# walk back: the tangent is computed with the value, in the same pass.
#
# `md.jvp(f, primals, tangents)` returns `(f(x), J v)`; `md.tangents({t: v})` sets the
# tangent of existing tensors within a `with` block, so the result's `.tangent` is `J v`.
# Take a small function `ℝ⁶ → ℝ⁴`:
#
#     f(x) = tanh(W x) ⊙ (1 + x₀²)          (W a fixed 4 × 6 matrix).

# %%
n, m = 6, 4
W = rng.normal(size=(m, n))
x0 = rng.normal(size=n)


def f(x):
    x = md.as_tensor(x)
    return md.tanh(md.matmul(W, x)) * (1.0 + x[0] ** 2)


v = rng.normal(size=n)
value, Jv = md.jvp(f, (x0,), (v,))
xt = md.tensor(x0)
with md.tangents({xt: v}):
    Jv_again = f(xt).tangent
print("J v by md.jvp:     ", Jv)
print("J v by md.tangents:", Jv_again)

# The whole Jacobian two ways: n forward passes (columns) or m reverse passes (rows).
J_forward = np.stack([md.jvp(f, (x0,), (e,))[1] for e in np.eye(n)], axis=1)
rows = []
for e in np.eye(m):
    xr = md.tensor(x0, requires_grad=True)
    f(xr).backward(e)  # the VJP with u = e: row of J
    rows.append(xr.grad)
J_reverse = np.stack(rows)
modes_difference = float(np.abs(J_forward - J_reverse).max())

# The dot-product identity <u, J v> = <J^T u, v>, for random u and v.
u = rng.normal(size=m)
xr = md.tensor(x0, requires_grad=True)
f(xr).backward(u)
JTu = xr.grad
lhs, rhs = float(u @ Jv), float(JTu @ v)
dot_identity_error = abs(lhs - rhs) / abs(lhs)
print(f"forward and reverse Jacobians differ by {modes_difference:.1e}")
print(f"<u, J v> = {lhs:.15f}   <J^T u, v> = {rhs:.15f}   relative {dot_identity_error:.1e}")

# %% [markdown]
# Building `J` column by column with `n = 6` JVPs and row by row with `m = 4` VJPs gives the
# same matrix to within `1e-15` <!-- check: modes_difference < -->. For random `u` and `v`,
#
#     ⟨u, J v⟩ = uᵀ J v = (Jᵀ u)ᵀ v = ⟨Jᵀ u, v⟩,
#
# and the two sides agree to a relative `1e-14` <!-- check: dot_identity_error < -->. This
# *dot-product test* is how a JVP and a VJP are checked against each other without any
# step size: `tests/minidiff/test_jvp.py` runs it on every primitive.
#
# ## What each mode costs
#
# One JVP gives one column of `J` (the derivative of all outputs along one input
# direction); one VJP gives one row (the gradient of one output with respect to all
# inputs). Each pass costs a small multiple of evaluating `f`. So the full gradient of a
# scalar loss of `n` parameters takes **one** reverse pass but `n` forward passes: this is
# why training and inverse rendering use reverse mode. Forward mode wins when there are
# few inputs and many outputs: the derivative of a whole image along *one* parameter (the
# gradient images of lesson 6) is one forward pass, but would take one reverse pass per
# pixel. Here is the scalar case, `L(x) = Σ tanh(A x)²` with `n = 200`.

# %%
n_big = 200
A = rng.normal(size=(300, n_big)) / np.sqrt(n_big)
x_big = rng.normal(size=n_big)


def loss(x):
    return (md.tanh(md.matmul(A, md.as_tensor(x))) ** 2).sum()


start = time.perf_counter()
g_reverse = md.grad(loss)(x_big)
reverse_seconds = time.perf_counter() - start
start = time.perf_counter()
g_forward = np.array([md.jvp(loss, (x_big,), (e,))[1] for e in np.eye(n_big)])
forward_seconds = time.perf_counter() - start
forward_passes = n_big
cost_ratio = forward_seconds / reverse_seconds
gradient_agreement = float(np.abs(g_forward - g_reverse).max())
print(f"reverse: 1 pass, {reverse_seconds * 1e3:.2f} ms; forward: {forward_passes} passes, "
      f"{forward_seconds * 1e3:.1f} ms ({cost_ratio:.0f} times longer); "
      f"largest difference {gradient_agreement:.1e}")  # fmt: skip

# %% [markdown]
# The gradient takes one backward pass, or `200` <!-- check: forward_passes --> JVPs, and the
# two agree to within `1e-14` <!-- check: gradient_agreement < -->. The run prints how much
# longer the 200 forward passes take (tens of times on the development machine; a timing,
# so not checked here); the ratio grows with `n`.
#
# ## Checking a gradient with finite differences, and the step size
#
# Both modes are exact up to rounding; finite differences are the independent referee. The
# central difference along a direction `v`,
#
#     D_h = (L(x + h v) − L(x − h v)) / 2h  =  ∇L·v + (h²/6) L'''(x)[v, v, v] + O(h⁴),
#
# has a **truncation** error `∝ h²`. But `L` is computed with a relative rounding error
# of about `ε ≈ 2.2e-16`, and the difference divides it by `2h`: a **rounding** error
# `∝ ε |L| / h`. The total is smallest where the two meet, near `h ≈ (3ε|L|/|L'''|)^(1/3)`,
# of the order `ε^(1/3) ≈ 6e-6`. The figure `fd_step.png` plots both on log-log axes
# against the exact `∇L·v` from the tape.

# %%
direction = rng.normal(size=n_big)
direction /= np.linalg.norm(direction)
exact = float(g_reverse @ direction)
steps = np.logspace(-12, -0.5, 47)
errors = []
for h in steps:
    with md.no_grad():
        d = (loss(x_big + h * direction).item() - loss(x_big - h * direction).item()) / (2 * h)
    errors.append(abs(d - exact) / abs(exact))
errors = np.array(errors)
best_h = float(steps[np.argmin(errors)])
best_error = float(errors.min())
# The slope of the error on the large-h side (truncation) and the small-h side (rounding).
big, small = steps > 1e-3, steps < 1e-8
truncation_slope = float(np.polyfit(np.log10(steps[big]), np.log10(errors[big]), 1)[0])
rounding_slope = float(np.polyfit(np.log10(steps[small]), np.log10(errors[small]), 1)[0])
figure = line_figure(
    {
        "|D_h - exact| / |exact|": (steps, errors),
        "h^2 (truncation)": (
            steps[steps > 1e-6],
            errors[-1] * (steps[steps > 1e-6] / steps[-1]) ** 2,
        ),
        "eps / h (rounding)": (steps[steps < 1e-3], 2.2e-16 / steps[steps < 1e-3]),
    },
    title="Central differences of L along v: error against the step h",
    xlabel="step h",
    ylabel="relative error",
    logx=True,
    logy=True,
    references=("h^2 (truncation)", "eps / h (rounding)"),  # guides: dashed, beneath the data
)
save_and_show(figure, OUT / "fd_step.png")
print(f"best step {best_h:.1e} with relative error {best_error:.1e}; "
      f"slopes {truncation_slope:.2f} (large h), {rounding_slope:.2f} (small h)")  # fmt: skip

# %% [markdown]
# On the large-`h` side the error falls with slope `2.0` <!-- check: truncation_slope -->
# (a tenth of the step, a hundredth of the error); below `1e-8` it *rises* as `h` shrinks,
# with a slope near −1 (noisy: rounding is not smooth). The best step here is between
# `1e-7` <!-- check: best_h > --> and `1e-4` <!-- check: best_h < -->, where the
# relative error is below `1e-9` <!-- check: best_error < -->; no step does better.
# So a finite-difference check in float64 can only say "agrees to about `1e-9`", and a
# check that fails at `1e-12` means nothing. `md.check_grad` uses `h = 1e-6`.
#
# ## Exercises
#
# 1. Write the VJP of `x ↦ x[None, :] * y` for `x` of shape `(3,)` and `y` of shape `(4, 1)`
#    by hand (the output is `(4, 3)`), including the unbroadcasting for *both* inputs, and
#    compare with `backward`.
# 2. `f(x) = x / ‖x‖` (`md.normalize`) maps `ℝ³ → ℝ³`. Compute its Jacobian with three JVPs,
#    check it against `(I − n nᵀ)/‖x‖`, and verify `J x = 0`: moving along `x` does not
#    change the direction.
# 3. Redo the step-size plot in float32 (`loss` on `x_big.astype(np.float32)` with a
#    float32 `A`). Where is the best step now, and how large is the best error? Compare with
#    `ε₃₂^(1/3)` for `ε₃₂ ≈ 1.2e-7`.
#
# Solutions: `lessons/solutions/02_arrays_and_modes.py`.

# %%
print(f"figures in {OUT}")
