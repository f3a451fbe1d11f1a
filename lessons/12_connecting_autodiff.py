# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # Lesson 12 — Connecting autodiff systems: the renderer inside PyTorch and JAX
#
# A renderer is rarely the whole program: a network predicts the scene, a loss compares
# features, an optimiser from another library takes the step. Those live in PyTorch or
# JAX, which record (or trace) their own computations and cannot see inside minidiff's
# tape. What connects them is the chain rule at the boundary: if the outer program
# computes `L(y)` of the renderer's output `y = f(x)`, then
#
#     ∂L/∂x = J(x)ᵀ ∂L/∂y ,      J = ∂y/∂x ,
#
# and the outer framework already has `∂L/∂y`. So the renderer need only offer the
# **vector-Jacobian product** (VJP) `v ↦ Jᵀ v`, which is one `backward` through
# minidiff's tape with `v` as its seed, and, for forward mode, the **Jacobian-vector
# product** `t ↦ J t`, one render with tangents (lesson 2). This lesson checks that
# contract, writes a custom VJP into PyTorch by hand, and then uses the library's bridges
# (`render.torch`, `render.jax`; `docs/bridges.md` goes further). It needs the extras:
# `pip install -e ".[torch,jax]"` (the `test` extra has both).

# %%
import time

import numpy as np
from course import figures_folder, save_and_show

import minidiff as md
import render
from render.inverse.function import RenderFunction
from render.inverse.plot import line_figure

# This lesson's figures go to out/lessons/12_connecting_autodiff/ (or under $LESSONS_OUT).
OUT = figures_folder("12_connecting_autodiff")
lesson_start = time.perf_counter()
S = 32

# %% [markdown]
# ## The contract: a pullback and a push-forward
#
# `RenderFunction(scene, parameter names)` is the framework-neutral black box: `f(x)`
# renders with the parameter set to `x` (on a copy of the scene: calls are pure and
# thread-safe); `f.forward(x)` returns the image and a **pullback** `v ↦ Jᵀ v`;
# `f.jvp(x, t)` returns `J t`. The two are computed by different code (reverse and
# forward mode), so the **dot-product test** `⟨v, J t⟩ = ⟨Jᵀ v, t⟩` for random `v`, `t`
# checks them against each other.

# %%
f = RenderFunction(render.paper_scene(S, S), ["lights[0].position"])
x = np.array([2.0, 5.0, 3.0])
rng = np.random.default_rng(0)
image, pullback = f.forward(x)
v = rng.normal(size=image.shape)  # stands for dL/dimage
(vjp,) = pullback(v)  # J^T v: (3,), one backward
t = rng.normal(size=3)
_, jvp = f.jvp([x], [t])  # J t: (S, S, 3), one forward-mode render
left, right = float((v * jvp).sum()), float(vjp @ t)
dot_product_mismatch = abs(left - right) / abs(right)
print(f"<v, J t> = {left:.12e}, <J^T v, t> = {right:.12e}: relative {dot_product_mismatch:.1e}")

# %% [markdown]
# The two sides agree to `1e-12` <!-- check: dot_product_mismatch < --> (relative). The
# pullback needed one render and one backward; the full Jacobian would need three
# backwards here (one per input) and, for a 512 × 512 image and a 3,000-vertex mesh,
# 7 billion numbers.
#
# ## A custom VJP by hand, in PyTorch
#
# PyTorch's hook for a black box is `torch.autograd.Function`: a `forward` on plain
# tensors, and a `backward` that receives `∂L/∂output` and returns `∂L/∂input`. Here is the
# renderer as such a Function, in a dozen lines: the forward renders without a tape and
# saves its input; the backward renders again on minidiff's tape and pulls `∂L/∂image`
# back through it (`f.vjp`). PyTorch may call `backward` more than once for one forward
# (`retain_graph=True`, which `gradcheck` uses), so the backward must not depend on a tape
# an earlier call freed. (`render.torch` keeps the forward's tape for the first backward,
# saving a render, and adds dtype checks, batching, forward mode and `torch.func`
# support.) `torch.autograd.gradcheck` compares the backward with PyTorch's own central
# differences.

# %%
try:
    import torch
except ImportError:  # pragma: no cover - the lesson says what to install
    torch = None
    print('PyTorch is not installed: pip install -e ".[torch]" to run the rest')

if torch is not None:

    class RenderLight(torch.autograd.Function):
        """image = render(scene with the light at ``position``); VJP by minidiff."""

        @staticmethod
        def forward(ctx, position):
            ctx.save_for_backward(position)
            return torch.from_numpy(f8(position.detach().numpy()))  # no tape

        @staticmethod
        def backward(ctx, grad_image):
            (position,) = ctx.saved_tensors
            (grad_position,) = f8.vjp([position.detach().numpy()], grad_image.numpy())
            return torch.from_numpy(grad_position)

    position = torch.tensor([2.0, 5.0, 3.0], dtype=torch.float64, requires_grad=True)
    # gradcheck probes every output element: keep the image small (8 x 8).
    f8 = RenderFunction(render.paper_scene(8, 8), ["lights[0].position"])
    gradcheck_passed = bool(torch.autograd.gradcheck(RenderLight.apply, (position,), eps=1e-6,
                                                     atol=1e-7, rtol=1e-5))  # fmt: skip
    print(f"gradcheck: {gradcheck_passed}")

# %% [markdown]
# `gradcheck` passes (`1` <!-- check: gradcheck_passed --> = True): PyTorch's finite
# differences of our forward agree with our backward. Two rules made it work: the forward
# takes and returns plain tensors (PyTorch records the Function itself, not what happens
# inside), and everything the backward needs is saved on `ctx` by *this* call, so two
# calls never mix their values.
#
# ## The library's bridges
#
# `render.torch.function(scene, names, **render_options)` and `render.jax.function(...)`
# are those Functions, written once for any scene and any parameters. Their gradients
# must be minidiff's own, whatever framework asks.

# %%
scene = render.paper_scene(S, S)
target = render.render(render.paper_scene(S, S, light_position=(2.5, 4.5, 3.5))).data
start = np.array([2.0, 5.0, 3.0])
light = md.tensor(start, requires_grad=True)
native_scene = render.paper_scene(S, S, light_position=light)
md.mean((render.render(native_scene) - md.tensor(target)) ** 2).backward()
native = light.grad.copy()
bridge_errors = {}
if torch is not None:
    import render.torch as render_torch

    g = render_torch.function(scene, ["lights[0].position"])
    p = torch.tensor(start, requires_grad=True)
    ((g(p) - torch.from_numpy(target)) ** 2).mean().backward()
    bridge_errors["torch"] = float(np.abs(p.grad.numpy() - native).max() / np.abs(native).max())
try:
    import jax
    import jax.numpy as jnp

    import render.jax as render_jax
except ImportError:  # pragma: no cover
    jax = None
    print('JAX is not installed: pip install -e ".[jax]" for its part')
if jax is not None:
    jax.config.update("jax_enable_x64", True)  # the scene is float64: say so to JAX
    h = render_jax.function(scene, ["lights[0].position"])
    jax_grad = jax.grad(lambda q: jnp.mean((h(q) - target) ** 2))(jnp.array(start))
    bridge_errors["jax"] = float(np.abs(np.asarray(jax_grad) - native).max() / np.abs(native).max())
print("largest relative difference to minidiff's gradient:", bridge_errors)
largest_bridge_error = max(bridge_errors.values())

# %% [markdown]
# PyTorch's and JAX's gradients equal minidiff's to `1e-12`
# <!-- check: largest_bridge_error < --> (relative): the same tape, reached from three
# frameworks. One difference shows in the code: JAX never records, it *traces* a function
# into a program, so `render.jax` hands JAX a `pure_callback` for the render and a
# `custom_vjp` rule for its gradient; JAX's residuals must be arrays, so its backward
# renders again (two renders and one backward per gradient, against PyTorch's one and one).
#
# ## Optimising with another library's optimiser
#
# The light, fitted by `torch.optim.Adam` through the bridge:

# %%
if torch is not None:
    p = torch.tensor(start, requires_grad=True)
    adam = torch.optim.Adam([p], lr=0.05)
    fit_losses = []
    for _ in range(150):
        adam.zero_grad()
        loss = ((g(p) - torch.from_numpy(target)) ** 2).mean()
        loss.backward()
        adam.step()
        fit_losses.append(loss.item())
    torch_fit_error = float(np.linalg.norm(p.detach().numpy() - [2.5, 4.5, 3.5]))
    torch_loss_drop = fit_losses[0] / fit_losses[-1]
    # Adam's ringing: the steps where the loss is a local maximum of the curve, and how far
    # it climbs back after its first minimum.
    fl = np.asarray(fit_losses)
    loss_peaks = [i for i in range(1, len(fl) - 1) if fl[i - 1] < fl[i] >= fl[i + 1]]
    first_minimum = int(np.argmax(np.diff(fl) > 0))
    rebound = fl[loss_peaks[0]] / fl[first_minimum]
    n_loss_peaks = len(loss_peaks)
    print(f"loss minimum at step {first_minimum}, peaks at steps {loss_peaks}, first "
          f"rebound x{rebound:.0f}")  # fmt: skip
    print(f"after 150 PyTorch Adam steps: light {p.detach().numpy().round(4)}, distance to "
          f"the truth {torch_fit_error:.4f}, loss / {torch_loss_drop:.0f}")  # fmt: skip
    figure = line_figure({"loss": (np.arange(len(fit_losses)), fit_losses)},
                         title="The light fitted by torch.optim.Adam through render.torch",
                         xlabel="step", ylabel="image MSE", logy=True)  # fmt: skip
    save_and_show(figure, OUT / "torch_fit.png")
print(f"elapsed {time.perf_counter() - lesson_start:.1f} s; figures in {OUT}")

# %% [markdown]
# From `0.87` away (`|(2, 5, 3) − (2.5, 4.5, 3.5)|`) the light ends within `0.01`
# <!-- check: torch_fit_error < --> of the truth, the loss divided by more than `1000`
# <!-- check: torch_loss_drop > --> (`torch_fit.png`): PyTorch's optimiser, minidiff's
# derivative.
#
# The curve in `torch_fit.png` is not a steady fall: it *rings*. The loss reaches a first
# minimum at step `11` <!-- check: first_minimum -->, then climbs more than `100`
# <!-- check: rebound > --> times higher, and it swings up and down with `8`
# <!-- check: n_loss_peaks --> peaks, each lower than the one before, 22 steps apart at
# first and 14 by the end. That is Adam, not the renderer: its first moment (β₁ = 0.9) is
# momentum, which carries the light past the truth, and its step is about `lr` whatever the
# gradient's size, so near the minimum it overshoots and swings back. A smaller `lr`, a
# decaying one (`torch.optim.lr_scheduler`) or a smaller β₁ damps the ringing; plain
# gradient descent with a small enough step falls without it, but far more slowly.
#
# ## Exercises
#
# 1. Add forward mode to `RenderLight`: a `jvp` static method (PyTorch calls it with
#    `ctx` and the input's tangent) that returns `J t` from `f.jvp` (save the input for it
#    with `ctx.save_for_forward`); check it against the dot-product test, pushing the
#    tangent through with `torch.autograd.forward_ad` (`make_dual`, `unpack_dual`).
#    Not with `torch.func.jvp`: its transforms accept only a Function written with a
#    separate `setup_context` static method, and even then, inside `jvp` the tangent and
#    the saved input are wrapped tensors whose `.numpy()` fails ("Cannot access data
#    pointer of Tensor that doesn't have storage", PyTorch 2.13), while `f.jvp` needs NumPy
#    arrays.
# 2. With `render.jax.function`, take `jax.jit(jax.grad(...))` of the loss above and
#    `jax.vmap` the image over three light positions. Is `vmap` faster than three calls,
#    per render? Why not (see the README's "What to know")?
#
# Solutions: `lessons/solutions/12_connecting_autodiff.py`.
