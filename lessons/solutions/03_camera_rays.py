# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # Solutions to lesson 3 (camera rays)

# %%
import math

import numpy as np

import render
from render.scene.camera import camera_frame, ray_directions

# %% [markdown]
# ## Exercise 1: the vertical field of view from two rays

# %%
W, H, FOV = 8, 5, 40.0
camera = render.Camera(position=(0, 0, 5), look_at=(0, 0, 0), fov=FOV, width=W, height=H)
top, bottom = ray_directions(camera_frame(camera), np.array([[0.0, 1.0], [0.0, -1.0]])).data
measured = math.degrees(math.acos(top @ bottom / (np.linalg.norm(top) * np.linalg.norm(bottom))))
formula = math.degrees(2 * math.atan(math.tan(math.radians(FOV / 2)) * H / W))
print(f"vertical fov: from the rays {measured:.6f}, formula {formula:.6f} degrees")
assert abs(measured - formula) < 1e-9

# %% [markdown]
# ## Exercise 2: projecting a point to its pixel
#
# With `q = p − C`, the point lies on the ray `d(x, y)` with
# `x = (q·r̂) / ((q·f)·tan(fov/2))` and `y = (q·û) / ((q·f)·tan(fov/2)·H/W)`; the frame's
# scaled `right` and `up` already contain those tangents, so `x = (q·right)/|right|² / (q·f)`.
# The pixel is then `px = floor((x + 1)/2 · W)`, `py = floor((1 − y)/2 · H)`.


# %%
def project(camera, p):
    forward, right, up, eye = (t.data for t in camera_frame(camera))
    q = np.asarray(p, float) - eye
    depth = q @ forward
    x = (q @ right) / (right @ right) / depth
    y = (q @ up) / (up @ up) / depth
    return (x + 1) / 2 * camera.width, (1 - y) / 2 * camera.height  # continuous pixel coords


p = (0.7, -0.4, 1.0)
cam = render.Camera(position=(0, 0, 5), look_at=(0, 0, 0), fov=40.0, width=64, height=48)
u, v = project(cam, p)
sphere = render.Sphere(p, 0.08, render.Material((0.8, 0.8, 0.8)))
scene = render.Scene([sphere], [render.PointLight((0, 0, 5), 10.0)], cam)
_, info = render.render(scene, return_info=True)
rows, cols = np.nonzero(info.prim_id[..., 0] >= 0)
centre = (cols.mean() + 0.5, rows.mean() + 0.5)  # centre of the hit pixels, pixel units
print(f"projected to pixel coordinates ({u:.2f}, {v:.2f}); pixel ({int(u)}, {int(v)})")
print(f"the sphere's {len(rows)} hit pixels are centred at ({centre[0]:.2f}, {centre[1]:.2f})")
assert abs(centre[0] - u) < 0.5 and abs(centre[1] - v) < 0.5

# %% [markdown]
# ## Exercise 3: a 35 mm lens
#
# `fov = 2·atan(18/35) = 54.43°`. Pixel centres are `2·tan(fov/2)/W = 36/35/640` apart
# horizontally, and `2·tan(fov/2)·(H/W)/H`, the same, vertically: pixels are square.

# %%
lens = render.Camera.from_focal_length(35.0, 36.0, position=(0, 0, 5), look_at=(0, 0, 0),
                                       width=640, height=480)  # fmt: skip
fov35 = float(lens.fov.data)
_, right, up, _ = camera_frame(lens)
dx = 2 * np.linalg.norm(right.data) / lens.width
dy = 2 * np.linalg.norm(up.data) / lens.height
print(f"fov {fov35:.4f} degrees; pixel spacing {dx:.6e} (x), {dy:.6e} (y)")
assert abs(fov35 - math.degrees(2 * math.atan(18 / 35))) < 1e-9
assert abs(dx - dy) < 1e-15 and abs(dx - 36 / 35 / 640) < 1e-15
