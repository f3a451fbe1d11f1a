# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # Lesson 3 — Camera rays
#
# A ray tracer starts by asking, for every pixel, *which ray does this pixel see?* The
# renderer's answer is a look-at pinhole camera (`render/scene/camera.py`, `render.Camera`):
#
# * an **eye** `C` (`position`), a point it looks at (`look_at`) and an approximate `up`;
# * an orthonormal **frame**: `f = normalize(look_at − C)` (forward),
#   `r = normalize(f × up)` (right), `u = r × f` (the true up);
# * a **horizontal field of view** `fov`: the image plane at distance 1 in front of the
#   eye spans `x ∈ [−1, 1]` → `[−tan(fov/2), tan(fov/2)]` horizontally and, with square
#   pixels, `tan(fov/2)·H/W` vertically.
#
# The ray through the image-plane point `(x, y)` (x to the right, y up, both in `[−1, 1]`)
# has the direction
#
#     d(x, y) = f + x·tan(fov/2)·r + y·tan(fov/2)·(H/W)·u,
#
# and pixel `(px, py)` (column, row; **row 0 at the top**) is sampled at its centre,
#
#     x = 2(px + ½)/W − 1,        y = 1 − 2(py + ½)/H.
#
# `d` is not normalised: its component along `f` is 1, so the ray parameter `t` of a hit
# `C + t·d` is the hit's depth along the view axis. This lesson evaluates these formulas with
# the library's own code and checks them number by number.

# %%
import math
from pathlib import Path

import numpy as np
from course import figures_folder
from PIL import Image, ImageDraw

import minidiff as md
import render
from render.scene.camera import (
    camera_frame,
    image_plane_coords,
    primary_rays,
    ray_directions,
    subpixel_offsets,
)

# This lesson's figures go to out/lessons/03_camera_rays/ (or under $LESSONS_OUT).
OUT = figures_folder("03_camera_rays")

# %% [markdown]
# ## The frame
#
# A tiny camera, 8 × 5 pixels, five units in front of the origin, 40° wide.
# `camera_frame` returns the frame on the tape with `right` and `up` already scaled by the
# half extents of the image plane, so that a direction is `f + x·right + y·up`.

# %%
W, H, FOV = 8, 5, 40.0
camera = render.Camera(position=(0, 0, 5), look_at=(0, 0, 0), fov=FOV, width=W, height=H)
forward, right, up, eye = camera_frame(camera)
print("eye", eye.data, " forward", forward.data)
print("right * tan(fov/2)", right.data, " up * tan(fov/2) * H/W", up.data)
half_width = float(np.linalg.norm(right.data))
half_height = float(np.linalg.norm(up.data))
vertical_fov = math.degrees(2 * math.atan(half_height))

# %% [markdown]
# The image plane reaches tan(20°) = `0.36397` <!-- check: half_width --> to either side
# and 0.36397 · 5/8 = `0.22748` <!-- check: half_height --> up and down, so the vertical
# field of view is 2·atan(0.22748) = `25.63` <!-- check: vertical_fov --> degrees: the
# `fov` argument is the horizontal one.
#
# ## Every pixel's ray
#
# `primary_rays` evaluates `d` for all pixels at once in Numba (visibility only needs
# numbers); `image_plane_coords` gives each ray's `(x, y)`. Ray `r` belongs to pixel
# `r // spp`, pixels in row-major order from the top-left.

# %%
eye_np, directions = primary_rays(camera)  # (H*W, 3)
coords = image_plane_coords(camera, np.arange(W * H), spp=1)  # (H*W, 2)
top_left_x, top_left_y = coords[0]
print("pixel (0, 0) is sampled at (x, y) =", coords[0], "; pixel (W-1, H-1) at", coords[-1])

px, py = np.arange(W * H) % W, np.arange(W * H) // W
by_formula = (
    forward.data
    + ((2 * (px + 0.5) / W - 1) * math.tan(math.radians(FOV / 2)))[:, None] * [1, 0, 0]
    + ((1 - 2 * (py + 0.5) / H) * math.tan(math.radians(FOV / 2)) * H / W)[:, None] * [0, 1, 0]
)
formula_error = float(np.abs(directions - by_formula).max())
print(f"largest difference between primary_rays and the formula: {formula_error:.1e}")

# %% [markdown]
# The top-left pixel is sampled at x = −1 + 1/W = `-0.875` <!-- check: top_left_x -->,
# y = 1 − 1/H = `0.8` <!-- check: top_left_y -->: half a pixel in from the corner, not at
# the corner. (A classic off-by-half bug samples at `px/W` instead of `(px + ½)/W`, which
# shifts the whole image by half a pixel.) For this camera `r = (1, 0, 0)`,
# `u = (0, 1, 0)` and `f = (0, 0, −1)`, so the formula can be written out by hand; it
# matches `primary_rays` to `1e-15` <!-- check: formula_error < -->.
#
# The rays through the pixel centres of a row do not span the full field of view: the two
# outermost centres are half a pixel in from the edges, so they are
# `2·atan((1 − 1/W)·tan(fov/2))` apart.

# %%
row = directions.reshape(H, W, 3)[H // 2]  # the middle row: y = 0 since H is odd
a, b = row[0], row[-1]
span_of_centres = math.degrees(math.acos(a @ b / (np.linalg.norm(a) * np.linalg.norm(b))))
print(f"angle between the outermost pixel-centre rays of the middle row: {span_of_centres:.4f}")

# %% [markdown]
# Measured on the rays: `35.33` <!-- check: span_of_centres --> degrees, against 40° for the
# edges of the image.
#
# ## Several samples per pixel
#
# With `spp = n²` samples, `subpixel_offsets` places them at the centres of an n × n grid
# of cells inside the pixel (a fixed pattern, no randomness: the image stays a
# deterministic, differentiable function of the scene). Their mean is the pixel centre.

# %%
offsets = subpixel_offsets(4)
print("offsets of 4 samples inside a pixel:\n", offsets)
coords4 = image_plane_coords(camera, np.arange(W * H * 4), spp=4).reshape(W * H, 4, 2)
spp_centre_error = float(np.abs(coords4.mean(axis=1) - coords).max())
print(f"mean of each pixel's 4 samples minus its centre: {spp_centre_error:.1e}")

# %% [markdown]
# The means of the four samples equal the pixel centres (largest difference below `1e-15`
# <!-- check: spp_centre_error < -->).
#
# ## The same rays on the tape
#
# For gradients the renderer rebuilds the rays that hit something with minidiff:
# `ray_directions(camera_frame(camera), coords)` is `[x, y, 1] @ [right; up; forward]`,
# one matrix product on the tape. Its values are those of `primary_rays`, and gradients
# reach `position`, `look_at`, `up` and `fov`. For the `x` component of a ray,
# `∂d_x/∂fov = x · ½ · (π/180) / cos²(fov/2)` (fov in degrees).

# %%
fov = md.tensor(FOV, requires_grad=True)
camera_t = render.Camera(position=(0, 0, 5), look_at=(0, 0, 0), fov=fov, width=W, height=H)
d_tape = ray_directions(camera_frame(camera_t), coords)
tape_vs_numba = float(np.abs(d_tape.data - directions).max())
d_tape[0, 0].backward()  # the x component of the top-left pixel's ray
dx_dfov = float(fov.grad)
dx_dfov_formula = top_left_x * 0.5 * (math.pi / 180) / math.cos(math.radians(FOV / 2)) ** 2
print(f"tape vs primary_rays {tape_vs_numba:.1e}")
print(f"d(d_x)/d(fov): tape {dx_dfov:.8f}, formula {dx_dfov_formula:.8f}")

# %% [markdown]
# The tape's rays equal the Numba rays (difference below `1e-15`
# <!-- check: tape_vs_numba < -->), and widening the view by one degree moves the top-left
# ray's `x` component by `-0.0086474` <!-- check: dx_dfov --> (the formula gives the same
# value): the ray tilts further left.
#
# ## Figures
#
# `ray_grid.png`: left, the camera seen from above — the eye, the image plane at distance 1
# with its pixel boundaries, and the rays through the pixel centres of one row; right, the
# image plane as the camera sees it — pixel boundaries, pixel centres (dots), and the four
# `spp = 4` samples of the top-left pixel (small squares). `directions.png`: the unit ray
# directions of a 96 × 64 camera as colours, `(0.5 + 0.5·d̂)` → RGB.


# %%
def draw_ray_grid(path: Path) -> None:
    img = Image.new("RGB", (900, 420), "white")
    draw = ImageDraw.Draw(img)
    hw = half_width

    # Left panel: top view, world x to the right, depth (along f) upwards.
    def top(x, depth):
        return 220 + x / (1.3 * hw) * 180, 380 - depth * 280

    draw.text((40, 10), "top view: eye, image plane at depth 1, rays of one row", fill="black")
    draw.line([top(-hw, 1), top(hw, 1)], fill="black", width=2)
    for i in range(W + 1):  # pixel boundaries on the image plane
        x = -hw + 2 * hw * i / W
        draw.line([top(x, 0.97), top(x, 1.03)], fill="black")
    for d in row:  # rays through the middle row's pixel centres, to depth 1.25
        draw.line([top(0, 0), top(d[0] * 1.25, 1.25)], fill=(31, 119, 180))
        u, v = top(d[0], 1)  # where the ray crosses the image plane
        draw.ellipse([u - 3, v - 3, u + 3, v + 3], fill=(31, 119, 180))
    for s in (-1, 1):  # the field of view
        draw.line([top(0, 0), top(s * hw * 1.25, 1.25)], fill=(214, 39, 40))
    draw.ellipse([top(0, 0)[0] - 5, top(0, 0)[1] - 5, top(0, 0)[0] + 5, top(0, 0)[1] + 5], "black")
    draw.text((top(0, 0)[0] + 8, top(0, 0)[1] - 6), "eye", fill="black")
    draw.text((top(hw, 1)[0] + 6, top(hw, 1)[1] - 6), "image plane", fill="black")
    draw.text((40, 395), "red: the field of view (x = -1, 1); blue: pixel-centre rays", "black")

    # Right panel: the image plane, x right, y up.
    def plane(x, y):
        return 480 + (x + 1) / 2 * 380, 70 + (1 - y) / 2 * 380 * H / W

    draw.text((480, 10), "image plane: pixels, centres, 4 samples of pixel (0, 0)", fill="black")
    for i in range(W + 1):
        x = -1 + 2 * i / W
        draw.line([plane(x, -1), plane(x, 1)], fill=(150, 150, 150))
    for j in range(H + 1):
        y = -1 + 2 * j / H
        draw.line([plane(-1, y), plane(1, y)], fill=(150, 150, 150))
    for x, y in coords:
        u, v = plane(x, y)
        draw.ellipse([u - 3, v - 3, u + 3, v + 3], fill=(31, 119, 180))
    for x, y in coords4[0]:
        u, v = plane(x, y)
        draw.rectangle([u - 2, v - 2, u + 2, v + 2], fill=(214, 39, 40))
    u, v = plane(-1, 1)
    draw.text((u - 30, v - 16), "(-1, 1)", fill="black")
    u, v = plane(1, -1)
    draw.text((u - 20, v + 4), "(1, -1)", fill="black")
    img.save(path)


draw_ray_grid(OUT / "ray_grid.png")
wide = render.Camera(position=(0, 0, 5), look_at=(0, 0, 0), fov=FOV, width=96, height=64)
_, d_wide = primary_rays(wide)
unit = d_wide / np.linalg.norm(d_wide, axis=1, keepdims=True)
colours = (0.5 + 0.5 * unit).reshape(64, 96, 3)
render.save_image(np.repeat(np.repeat(colours, 4, axis=0), 4, axis=1), OUT / "directions.png")
print(f"figures in {OUT}")

# %% [markdown]
# ## Exercises
#
# 1. Find the vertical field of view from rays alone: build the rays through the middle of
#    the top and bottom edges of the image (`(x, y) = (0, ±1)`) with `ray_directions` and
#    measure the angle between them. Compare with `2·atan(tan(fov/2)·H/W)`.
# 2. Write `project(camera, p)`, the pixel `(px, py)` that a world point `p` falls in (invert
#    the formula for `d`: divide the components of `p − C` along `r` and `u` by the
#    component along `f`). Check it with the renderer: render a small sphere at
#    `p = (0.7, −0.4, 1.0)` with a 64 × 48 camera and compare with the centre of the
#    sphere's hit pixels. The scene and the render (lessons 5 and 6 explain them):
#    `scene = render.Scene([render.Sphere(p, 0.08, render.Material((0.8, 0.8, 0.8)))],
#    [render.PointLight((0, 0, 5), 10.0)], camera)`, then
#    `_, info = render.render(scene, return_info=True)`: `info.prim_id` is an
#    `(H, W, spp)` array, per pixel and sample the primitive its ray hits (−1: none), so
#    `np.nonzero(info.prim_id[..., 0] >= 0)` gives the rows and columns of the hit pixels.
# 3. A 35 mm lens on a 36 mm wide sensor (`render.Camera.from_focal_length`): what is its
#    horizontal field of view, and how far apart are neighbouring pixel centres on the image
#    plane at distance 1 for a 640 × 480 image, horizontally and vertically?
#
# Solutions: `lessons/solutions/03_camera_rays.py`.
