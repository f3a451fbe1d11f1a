# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # Solutions to lesson 11 (discontinuities)

# %%
import math

import numpy as np

import minidiff as md
import render
from render.inverse import experiments

W_PIX, H_PIX = 12, 10
X0, Y0, SIDE, ANGLE = 3.3, 2.6, 5.2, math.radians(30)

# %% [markdown]
# ## Exercise 1: the edge term of a turned square
#
# The square's corners turn about its centre. Each edge is walked in `M` steps; at each
# step's midpoint the outward normal's x component `nₓ` is the speed at which the edge
# sweeps area when `x₀` grows, so `nₓ · ds` is added to the pixel the point lies in. The
# sum over one edge's steps inside a pixel is `nₓ` times the length of the edge inside the
# pixel: the boundary term of lesson 11, with a jump of 1.


# %%
def corners(x0, y0, w, angle):
    centre = np.array([x0 + w / 2, y0 + w / 2])
    square = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * w / 2  # counter-clockwise
    rotation = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    return centre + square @ rotation.T


def turned_edge_term(x0, y0, w, steps=20_000):
    image = np.zeros((H_PIX, W_PIX))
    c = corners(x0, y0, w, ANGLE)
    for k in range(4):
        a, b = c[k], c[(k + 1) % 4]
        edge = b - a
        normal_x = edge[1] / np.linalg.norm(edge)  # outward normal (ey, -ex) of a CCW polygon
        s = (np.arange(steps) + 0.5) / steps
        points = a + s[:, None] * edge
        ds = np.linalg.norm(edge) / steps
        i, j = np.floor(points[:, 0]).astype(int), np.floor(points[:, 1]).astype(int)
        np.add.at(image, (j, i), normal_x * ds)
    return image


def turned_image(x0, y0, w, samples):
    """The mean of samples x samples point samples per pixel of the turned square."""
    c = corners(x0, y0, w, ANGLE)
    offsets = (np.arange(samples) + 0.5) / samples
    j, i = np.meshgrid(np.arange(H_PIX), np.arange(W_PIX), indexing="ij")
    shape = (H_PIX, W_PIX, samples, samples)
    sx = np.broadcast_to(i[..., None, None] + offsets[None, None, :, None], shape)
    sy = np.broadcast_to(j[..., None, None] + offsets[None, None, None, :], shape)
    inside = np.ones(shape, bool)
    for k in range(4):  # a convex polygon: inside every edge's half-plane
        a, b = c[k], c[(k + 1) % 4]
        inside &= (b[0] - a[0]) * (sy - a[1]) - (b[1] - a[1]) * (sx - a[0]) >= 0
    return inside.mean(axis=(2, 3))


edge_term = turned_edge_term(X0, Y0, SIDE)
h = 0.05
truth = (turned_image(X0 + h, Y0, SIDE, 256) - turned_image(X0 - h, Y0, SIDE, 256)) / (2 * h)
relative = float(np.linalg.norm(edge_term - truth) / np.linalg.norm(truth))
print(f"turned square: edge term against supersampled differences, relative {relative:.4f}; "
      f"sum of the edge term {edge_term.sum():+.2e} (sliding sideways keeps the area)")  # fmt: skip
assert relative < 0.03 and abs(edge_term.sum()) < 1e-9

# %% [markdown]
# ## Exercise 2: finite differences of a random-point estimate
#
# With `N` random points, `I_N(t ± h)` differ only by the points between `t − h` and
# `t + h` (about `2hN` of them), each carrying `f/N`: the difference quotient is a count of
# random points divided by `2hN`, with relative noise about `1/√(2hN)`. Large `h` is
# smooth but biased by the curvature of `I`; small `h` leaves a handful of points to count
# and the noise takes over. There is no step at which both vanish unless `N` grows.

# %%
rng = np.random.default_rng(0)
x = rng.random(1000)
fx = 1 + x**2
for h in (0.1, 0.01, 0.001):
    estimate = (fx[x > 0.3 + h].sum() - fx[x > 0.3 - h].sum()) / (1000 * 2 * h)
    print(f"h = {h}: estimate {estimate:+.3f} (exact -1.090)")

# %% [markdown]
# ## Exercise 3: one sample per pixel
#
# The pairs change most: with one sample per pixel, a pair spans a whole pixel and sees
# only the edges between pixel centres; the teapot's many facet edges inside a pixel are
# missed, and the blend approximates coverage far from where the samples are. The
# boundary integral does not depend on the samples for its edges (it integrates along the
# edges themselves), so its error changes only through the interior term, and against one
# 4,096-sample truth such a change is hidden: the lesson's other five truths differ from
# this one by 0.038 to 0.085, about the boundary integral's error.

# %%
SIZE = 32
teapot = experiments.paper_scene(SIZE, SIZE)
along_x = np.array([1.0, 0.0, 0.0])
renders = []
with md.no_grad():
    for sign in (1, -1):
        moved = experiments.paper_scene(SIZE, SIZE)
        moved.camera.position.data = moved.camera.position.data + sign * 0.02 * along_x
        renders.append(render.render(moved, spp=4096).data)
truth = (renders[0] - renders[1]) / 0.04
errors = {}
for spp in (1, 16):
    for name, aa in (("pairs", True), ("boundary", "boundary")):
        g = render.gradient_image(teapot, "camera.position", along_x, antialias=aa, spp=spp)
        errors[name, spp] = float(np.linalg.norm(g - truth) / np.linalg.norm(truth))
print({f"{k[0]} at {k[1]} spp": round(v, 3) for k, v in errors.items()})
assert errors["pairs", 1] > 2 * errors["pairs", 16]
assert errors["boundary", 1] < 0.5 * errors["pairs", 1]
