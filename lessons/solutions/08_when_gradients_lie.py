# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # Solutions to lesson 8 (when gradients lie)
#
# The lesson's sliding square, repeated so that this file runs on its own.

# %%
import math

import numpy as np

import minidiff as md
import render

S = 48
base = np.array([[-0.5, -0.5, 0.0], [0.5, -0.5, 0.0], [0.5, 0.5, 0.0], [-0.5, 0.5, 0.0]])
square = render.Mesh(base, [[0, 1, 2], [0, 2, 3]], render.Material((0.8, 0.8, 0.8)))
camera = render.Camera(position=(0, 0, 3), look_at=(0, 0, 0), up=(0, 1, 0), fov=40.0,
                       width=S, height=S)  # fmt: skip
sun = render.DirectionalLight((0, 0, -1), 3.0)
scene = render.Scene([square], [sun], camera)
pixels_per_unit = S / (2 * 3 * math.tan(math.radians(20)))
along_x = np.array([1.0, 0.0, 0.0])


def square_at(t, antialias, corners=base):
    square.vertices = md.as_tensor(corners) + t
    return render.render(scene, antialias=antialias)


def fit(start, antialias, target, iters=150):
    t = md.tensor(start, requires_grad=True)
    render.optimize(lambda: square_at(t, antialias), [t], target, lr=0.01, max_iters=iters,
                    quiet=True)  # fmt: skip
    return float(np.linalg.norm(t.data))


# %% [markdown]
# ## Exercise 1: a point light close to the square
#
# The plain gradient is *still* exactly zero. Shading depends on where the hit point is in
# the world (its distance and angle to the light, the view), and sliding a plane within
# itself moves no hit point: each camera ray meets the plane `z = 0` where it did before.
# The interior of the square looks the same wherever the square is; only the edges (and
# the pixels they change) know. What would make the interior depend on `t` is something
# attached to the square, such as a texture: its UVs travel with the vertices, so each
# ray sees a different texel and the plain gradient is no longer zero. Plain Adam then
# makes progress from the texture alone (here it halves the distance in 300 steps; the
# bilinear stripes give a gradient only where the texture varies).

# %%
scene.lights = [render.PointLight((0, 0, 1), 3.0)]
t = md.tensor([0.105, 0.07, 0.0])
with md.tangents({t: along_x}):
    plain = square_at(t, False).tangent
print(f"point light: sum |dI/dt_x| (plain) = {np.abs(plain).sum()}")
assert np.abs(plain).sum() == 0.0

stripes = np.zeros((8, 8, 3))
stripes[:, ::2] = 1.0  # vertical stripes, four periods across the square
square.uvs = md.tensor([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
square.material = render.Material((0.8, 0.8, 0.8), texture=stripes)
with md.tangents({t: along_x}):
    textured = square_at(t, False).tangent
target = square_at(md.tensor(np.zeros(3)), False).data
plain_end = fit([0.05, 0.03, 0.0], False, target, iters=300)
print(f"textured: sum |dI/dt_x| (plain) = {np.abs(textured).sum():.3f}; plain Adam from "
      f"|t| = 0.058 ends at {plain_end:.1e}")  # fmt: skip
assert np.abs(textured).sum() > 1.0 and plain_end < 0.05
square.uvs, square.material, scene.lights = None, render.Material((0.8, 0.8, 0.8)), [sun]

# %% [markdown]
# ## Exercise 2: slanted edges
#
# The positive part of the gradient image is the area gained by the two leading edges,
# `c · ppu² · (cos 30° + sin 30°)` per unit. The renderer's value is close but not exact:
# each row (for the near-vertical edge, each column for the other) counts only the pairs
# whose samples straddle the edge, a count that is an integer while the true extent is
# not, and the pixels at the corners are approximated (lesson 8).

# %%
a = math.radians(30)
rotation = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
rotated = base @ rotation.T
t = md.tensor([0.105, 0.07, 0.0])
with md.tangents({t: along_x}):
    image = square_at(t, True, rotated)
c = float(image.data.max())
gained = float(image.tangent[..., 0].clip(min=0).sum())
formula = c * pixels_per_unit**2 * (math.cos(a) + math.sin(a))
print(f"positive part {gained:.3f}, formula {formula:.3f}, ratio {gained / formula:.4f}")
assert abs(gained / formula - 1) < 0.05

# %% [markdown]
# ## Exercise 3: the edge of the basin
#
# Bisection between a start that converges (0.9) and one that does not (1.1). The edge is
# where the render's square stops overlapping the target's: one square width, `t_x ≈ 1`
# (to within a pixel, `1/ppu ≈ 0.05`: overlap is decided on the pixel grid).

# %%
target = square_at(md.tensor(np.zeros(3)), False).data
low, high = 0.9, 1.1
for _ in range(8):
    middle = (low + high) / 2
    if fit([middle, 0.0, 0.0], True, target, iters=200) < 1e-2:
        low = middle
    else:
        high = middle
print(f"basin edge between {low:.4f} and {high:.4f}")
assert abs(low - 1.0) < 1.0 / pixels_per_unit
