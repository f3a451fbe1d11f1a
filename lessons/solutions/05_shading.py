# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # Solutions to lesson 5 (shading)

# %%
import math

import numpy as np

import render
from render.scene.camera import primary_rays

ALBEDO, N = 0.6, 33
camera = render.Camera(position=(0, 3, 0), look_at=(0, 0, 0), up=(0, 0, -1), fov=60.0,
                       width=N, height=N)  # fmt: skip
s = 4.0
plane = render.Mesh([(-s, 0, s), (s, 0, s), (s, 0, -s), (-s, 0, -s)], [[0, 1, 2], [0, 2, 3]],
                    render.Material((ALBEDO,) * 3))  # fmt: skip

# %% [markdown]
# ## Exercise 1: a directional light
#
# The light travels at 60° from the normal: `direction = −(sin 60°, cos 60°, 0)` (it goes
# *down* towards the plane). Every point sees the same `l` and the same `E`, so the plane is
# one constant colour, `E · albedo/π · cos 60° = 2 · 0.6/π · 0.5 = 0.19099`.

# %%
theta = math.radians(60)
sun = render.DirectionalLight((-math.sin(theta), -math.cos(theta), 0.0), 2.0)
image = render.render(render.Scene([plane], [sun], camera)).data
expected = 2.0 * ALBEDO / math.pi * math.cos(theta)
print(f"every pixel {image[..., 0].min():.6f} .. {image[..., 0].max():.6f}, formula {expected:.6f}")
np.testing.assert_allclose(image, expected, rtol=1e-13)

# %% [markdown]
# ## Exercise 2: where is the plane brightest?
#
# With the light at `(x_L, h, 0)`, `L ∝ cos θ / r² = h / r³`, and `r` is smallest directly
# under the light, where `cos θ = 1` as well: both factors peak at the same point, `x = 1`.

# %%
light = render.PointLight((1.0, 2.0, 0.0), 10.0)
image = render.render(render.Scene([plane], [light], camera)).data[..., 0]
row, col = np.unravel_index(np.argmax(image), image.shape)
eye, directions = primary_rays(camera)
d = directions[row * N + col]
brightest = eye + (-eye[1] / d[1]) * d
pixel_size = 2 * 3 * math.tan(math.radians(30)) / N  # on the plane
print(f"brightest pixel ({col}, {row}) sees the plane at {brightest.round(3)}")
assert abs(brightest[0] - 1.0) < pixel_size and abs(brightest[2]) < pixel_size

# %% [markdown]
# ## Exercise 3: the Blinn-Phong normalisation
#
# Light along the normal, view at angle `θ` from it: the half vector is at `θ/2`, so
# `f_s = (m + 8)/(8π) cos^m(θ/2)`, and the reflected fraction (for light along `n`, the
# cosine that weights it is the view's, `cos θ`, by reciprocity) is
# `2π ∫₀^{π/2} f_s cos θ sin θ dθ`. It is not exactly 1 but close: 1.024, 1.075 and 1.018
# for `m = 1, 10, 100`. `(m + 8)/(8π)` is a cheap approximation of the exact factor, good to
# about 8 % here: the lobe reflects a little more than it receives, never wildly so.

# %%
theta = np.linspace(0, math.pi / 2, 200_001)
for m in (1, 10, 100):
    integrand = (m + 8) / (8 * math.pi) * np.cos(theta / 2) ** m * np.cos(theta) * np.sin(theta)
    fraction = 2 * math.pi * np.sum((integrand[1:] + integrand[:-1]) / 2 * np.diff(theta))
    print(f"m = {m:>3}: reflected fraction {fraction:.4f}")
    assert 1.0 < fraction < 1.08


# %% [markdown]
# ## Exercise 4: a Lambert shader on the tape
#
# Everything is a minidiff operation on tensors, so `backward` reaches the light's
# position, the albedo and the intensity through it.

# %%
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import minidiff as md  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # lessons/: exercise_checks
from exercise_checks import check_lambert  # noqa: E402


def my_lambert(points, normals, albedo, light_position, intensity):
    to_light = light_position - points  # (k, 3)
    r2 = md.sum(to_light * to_light, axis=1, keepdims=True)  # (k, 1)
    cos = md.maximum(md.sum(normals * to_light, axis=1, keepdims=True) / md.sqrt(r2), 0.0)
    return albedo * (1 / math.pi) * intensity * cos / r2


print(check_lambert(my_lambert))
