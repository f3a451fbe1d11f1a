# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # Solutions to lesson 12 (connecting autodiff systems)

# %%
import time

import jax
import jax.numpy as jnp
import numpy as np
import torch
import torch.autograd.forward_ad as fwad

import render
import render.jax as render_jax
from render.inverse.function import RenderFunction

f8 = RenderFunction(render.paper_scene(8, 8), ["lights[0].position"])

# %% [markdown]
# ## Exercise 1: forward mode in the Function
#
# PyTorch's forward-mode AD (`torch.autograd.forward_ad`) calls a Function's `jvp` with
# the input's tangent; the inputs it needs are saved with `ctx.save_for_forward`. The
# dot-product test ties it to the backward. (`torch.func.jvp` refuses this Function: the
# `torch.func` transforms need `setup_context`, and even with it the tangent and saved
# input reaching `jvp` are wrapped tensors whose `.numpy()` fails, so a `jvp` that calls
# NumPy stays with `forward_ad`.)


# %%
class RenderLight(torch.autograd.Function):
    @staticmethod
    def forward(ctx, position):
        ctx.save_for_backward(position)
        ctx.save_for_forward(position)
        return torch.from_numpy(f8(position.detach().numpy()))

    @staticmethod
    def backward(ctx, grad_image):
        (position,) = ctx.saved_tensors
        return torch.from_numpy(f8.vjp([position.detach().numpy()], grad_image.numpy())[0])

    @staticmethod
    def jvp(ctx, tangent):
        (position,) = ctx.saved_tensors
        return torch.from_numpy(f8.jvp([position.detach().numpy()], [tangent.numpy()])[1])


rng = np.random.default_rng(1)
position = torch.tensor([2.0, 5.0, 3.0], dtype=torch.float64)
t = torch.from_numpy(rng.normal(size=3))
with fwad.dual_level():
    jt = fwad.unpack_dual(RenderLight.apply(fwad.make_dual(position, t))).tangent
v = torch.from_numpy(rng.normal(size=(8, 8, 3)))
p = position.clone().requires_grad_(True)
(RenderLight.apply(p) * v).sum().backward()
left, right = float((v * jt).sum()), float(p.grad @ t)
print(f"<v, J t> = {left:.12e}, <J^T v, t> = {right:.12e}")
assert abs(left - right) < 1e-12 * abs(right)

# %% [markdown]
# ## Exercise 2: jit, grad and vmap in JAX
#
# `jax.jit(jax.grad(...))` works: the render is a `pure_callback` inside the compiled
# program, its gradient the `custom_vjp` rule. `vmap` renders the batch one element after
# the other (`vmap_method="sequential"`): the callback runs NumPy and Numba, which JAX
# cannot batch, so nothing is gained *per render* over a loop (a loop of separate calls
# pays JAX's dispatch for each call on top, so it may even be slower); the times are
# printed, not asserted: timings are noisy.

# %%
jax.config.update("jax_enable_x64", True)
scene = render.paper_scene(32, 32)
target = render.render(render.paper_scene(32, 32, light_position=(2.5, 4.5, 3.5))).data
h = render_jax.function(scene, ["lights[0].position"])
grad = jax.jit(jax.grad(lambda q: jnp.mean((h(q) - target) ** 2)))
g = grad(jnp.array([2.0, 5.0, 3.0]))
lights = jnp.array([[2.0, 5.0, 3.0], [1.0, 6.0, 2.0], [3.0, 4.0, 4.0]])
batched = jax.vmap(h)(lights)
start = time.perf_counter()
batched = jax.vmap(h)(lights).block_until_ready()
vmap_seconds = time.perf_counter() - start
start = time.perf_counter()
looped = jnp.stack([h(q) for q in lights]).block_until_ready()
loop_seconds = time.perf_counter() - start
print(f"jit(grad): {np.asarray(g)}; vmap {vmap_seconds * 1e3:.1f} ms, "
      f"loop {loop_seconds * 1e3:.1f} ms")  # fmt: skip
assert np.array_equal(np.asarray(batched), np.asarray(looped))  # the same renders, bit for bit
assert np.all(np.isfinite(np.asarray(g))) and np.abs(np.asarray(g)).max() > 0
