# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # Solutions to lesson 13 (reconstruction)

# %%
import numpy as np
from scipy.spatial.transform import Rotation

import minidiff as md
import render
from render.inverse.optimize import image_loss, optimize
from render.inverse.reconstruction import dented_blob, rotation_error_degrees, run_shape
from render.scene.teapot import paper_scene

# %% [markdown]
# ## Exercise 1: gimbal lock of the x-y-z order
#
# For `R = R_x(a) R_y(b) R_z(c)` a change of the angles turns the object by
# `ω = ȧ e_x + ḃ R_x(a) e_y + ċ R_x(a) R_y(b) e_z`. The third column is `R_x(a)` applied
# to `R_y(b) e_z = (sin b, 0, cos b)`, which is `e_x` when `b = 90°`: the first and third
# columns coincide. Whatever the order, the lock is at ±90° of the *middle* angle.


# %%
def xyz_jacobian(a: float, b: float) -> np.ndarray:
    rx = Rotation.from_euler("X", a).as_matrix()
    ry = Rotation.from_euler("Y", b).as_matrix()
    return np.stack([[1.0, 0.0, 0.0], rx @ [0.0, 1.0, 0.0], rx @ ry @ [0.0, 0.0, 1.0]], axis=1)


middle = np.arange(0.0, 180.5, 0.5)
weakest = [np.linalg.svd(xyz_jacobian(0.4, np.radians(b)), compute_uv=False).min() for b in middle]
lock = float(middle[int(np.argmin(weakest))])
print(f"x-y-z order: the smallest singular value is {min(weakest):.1e} at b = {lock}°")
assert lock == 90.0 and min(weakest) < 1e-12

# %% [markdown]
# ## Exercise 2: blur first, then sharpen
#
# The blur on the tape: a Gaussian kernel applied as weighted sums of shifted slices of the
# image tensor (rows, then columns), keeping only the pixels whose whole kernel lies in
# the image (no padding needed). 30 steps against blurred images, then 20 against the
# plain ones, from 70° about the vertical; 30 plain steps alone for comparison.

# %%
P = 40
scene = paper_scene(P, P)
teapot = scene.objects[0]
teapot.transform = render.Transform(pivot=teapot.vertices.data.mean(axis=0))
target = render.render(scene, spp=16).data.copy()


def blurred(image, sigma: float = 3.0):
    """A 'valid' Gaussian blur of an (H, W, 3) tensor or array (each side loses 3 sigma)."""
    radius = int(3 * sigma)
    k = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma) ** 2)
    k /= k.sum()
    h, w = image.shape[0] - 2 * radius, image.shape[1] - 2 * radius
    rows = sum(float(weight) * image[i : i + h] for i, weight in enumerate(k))
    return sum(float(weight) * rows[:, i : i + w] for i, weight in enumerate(k))


def fit(schedule) -> float:
    rotation = md.tensor([0.0, 70.0, 0.0], requires_grad=True)
    teapot.transform.rotation = rotation
    for steps, blur in schedule:
        loss = (lambda image, t: image_loss(blurred(image), blurred(t))) if blur else image_loss
        optimize(scene, [rotation], target, loss_fn=loss, lr=2.0, max_iters=steps, quiet=True,
                 render_kwargs={"antialias": "boundary"})  # fmt: skip
    return rotation_error_degrees(rotation.data)


plain_error = fit([(30, False)])
schedule_error = fit([(30, True), (20, False)])
print(f"from 70°: plain steps end {plain_error:.1f}° off, blur then plain {schedule_error:.1f}°")
# Plain gradients from 70° stop in the local minimum past the basin's edge (55°, in the
# lesson); the blurred loss's basin reaches past 70°, and the plain steps finish the fit.
assert plain_error > 90.0 and schedule_error < 10.0

# %% [markdown]
# ## Exercise 3: Large Steps' λ
#
# λ sets how strongly each step is smoothed: `(I + λL)⁻¹` damps a pattern of
# wavelength `ℓ` (in edges) by about `1 / (1 + λ (2π/ℓ)²)`. A larger λ keeps the surface
# smoother, and takes longer to carve the dents (a larger Hausdorff distance at a fixed
# budget).

# %%
blob = dented_blob(3)
for lam in (1.0, 20.0):
    run = run_shape(blob, views=4, size=24, iters=30, method="large_steps", lam=lam, lr=0.1,
                    start_subdivisions=2, antialias="pairs", held_out=1, samples=5000)  # fmt: skip
    print(f"lambda {lam:4.0f}: Chamfer {run['chamfer_percent']:.2f} %, "
          f"Hausdorff {run['hausdorff_percent']:.1f} %")  # fmt: skip
