# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # Lesson 6 — Gradients through a renderer
#
# Lessons 3-5 built a renderer from camera rays, a BVH and shading. Which of its steps does
# the tape see? `render.render` (`render/renderer.py`) answers in its docstring:
#
# 1. **Visibility** (constants): which primitive each camera ray hits (`prim_id`) and
#    whether each hit sees each light (`lit`). These are discrete decisions, made in Numba
#    on plain arrays; a small move of a parameter either leaves them alone or flips them.
# 2. **Surfaces** (on the tape): for the primitive that was hit, the hit point, normal and
#    UV are *recomputed* with minidiff from the camera and the vertices
#    (`render/shade/surface.py`, lesson 4's Möller–Trumbore again, on tensors).
# 3. **Shading** (on the tape): lesson 5's formulas, on those tensors.
#
# So the image `I(θ)` is, for fixed decisions, a smooth function of every continuous
# parameter `θ`, and `backward` gives its exact derivative *for those decisions*. Where a
# move of `θ` would flip a decision (an edge, a shadow boundary) the image jumps and the
# tape knows nothing of it: lesson 8 deals with that. This lesson looks at the derivative,
# first as pictures, then checks it against finite differences the only honest way.

# %%
import time

import numpy as np
from course import figures_folder

import minidiff as md
import render

# This lesson's figures go to out/lessons/06_gradients_through_a_renderer/ (or under $LESSONS_OUT).
OUT = figures_folder("06_gradients_through_a_renderer")
SIZE = 64

# %% [markdown]
# ## The constants: `RenderInfo`
#
# `render.render(scene, return_info=True)` returns the image and a `RenderInfo` holding the
# decisions, per pixel and sample: `prim_id` (`-1` for the background), `lit` (per light)
# and `texel` (the texture cell a lookup used). The scene is the paper's teapot on a grey
# ground (`render.paper_scene(ground=True)`) at 64 × 64, with the light position a tensor.

# %%
start = time.perf_counter()
light = md.tensor([2.0, 5.0, 3.0])
scene = render.paper_scene(width=SIZE, height=SIZE, ground=True, light_position=light)
image, info = render.render(scene, return_info=True)
teapot_faces = render.teapot().num_faces  # the ground's two triangles come after these
prim = info.prim_id[..., 0]
teapot_pixels = int(((prim >= 0) & (prim < teapot_faces)).sum())
ground_pixels = int((prim >= teapot_faces).sum())
shadow_pixels = int(((prim >= 0) & ~info.lit[0, ..., 0]).sum())
print(f"prim_id {info.prim_id.shape} {info.prim_id.dtype}, lit {info.lit.shape} {info.lit.dtype}")
print(f"{teapot_pixels} teapot pixels, {ground_pixels} ground pixels, "
      f"{shadow_pixels} hits that do not see the light")  # fmt: skip
print("parameters:", ", ".join(scene.named_parameters()))

# %% [markdown]
# Of the 4,096 pixels, `639` <!-- check: teapot_pixels --> show the teapot and
# `1,862` <!-- check: ground_pixels --> the ground; `158` <!-- check: shadow_pixels --> hits
# do not see the light (the teapot's shadow on the ground, and parts of the teapot that the
# teapot itself hides from the light). Every continuous
# number of the scene is a parameter with a name (printed above): the camera's position,
# each light's position, intensity and colour, each object's vertices and material.
#
# ## Gradient images
#
# For a parameter `p` and a direction `v` in its space, the *gradient image* is
#
#     G = d I(p + t v) / dt  at t = 0,        an (H, W, 3) array,
#
# the change of every pixel when `p` moves along `v`. It is one column of the Jacobian
# `∂I/∂p`, so lesson 2 says: one forward-mode pass. `render.gradient_image(scene, name,
# direction)` runs `render.render` inside `md.tangents({p: v})`
# (`render/inverse/gradient_image.py`), and `render.write_gradient_png` draws it in diverging
# colours (red: the pixel brightens, blue: it darkens, with a scale bar).

# %%
move_x = np.array([1.0, 0.0, 0.0])
G_light = render.gradient_image(scene, "lights[0].position", move_x)
G_intensity = render.gradient_image(scene, "lights[0].intensity", 1.0)
G_albedo = render.gradient_image(scene, "objects[0].material.albedo", np.array([1.0, 0, 0]))
G_camera = render.gradient_image(scene, "camera.position", move_x)
render.save_image(np.repeat(np.repeat(image.data, 4, 0), 4, 1), OUT / "image.png", srgb=True)
render.write_gradient_png(G_light, OUT / "d_light_x.png", label="d image / d light x")
render.write_gradient_png(G_albedo, OUT / "d_albedo_red.png", label="d image / d teapot red")
render.write_gradient_png(G_camera, OUT / "d_camera_x.png", label="d image / d camera x")
# Radiance is linear in the intensity: I = intensity * G_intensity wherever the light counts.
intensity_linearity = float(np.abs(100.0 * G_intensity - image.data).max())
albedo_outside_teapot = float(np.abs(G_albedo[prim >= teapot_faces]).max())
print(f"|100 dI/dintensity - I| = {intensity_linearity:.1e}; "
      f"d(ground)/d(teapot albedo) = {albedo_outside_teapot}")  # fmt: skip

# %% [markdown]
# `d_light_x.png`: moving the light towards +x brightens the faces turned that way and
# darkens the others; the shadow is white (zero), as the light's position enters only
# through shading terms the shadowed points do not have. `d_albedo_red.png` is the teapot's
# red channel divided by its red albedo (`I` is linear in the albedo), exactly `0` <!-- check:
# albedo_outside_teapot --> on the ground. The image is linear in the light's intensity too:
# `100 · dI/dI₀` equals the image to within `1e-15` <!-- check: intensity_linearity < -->.
# `d_camera_x.png` is non-zero across the ground although nothing but the camera moves:
# the hit points slide over the ground, and their distances and angles to the light
# change. That derivative exists only because step 2 recomputes the hits on the tape.
#
# ## Forward against reverse
#
# For any loss `L = Σ w ⊙ I` (a fixed weight image `w`), reverse mode gives `∂L/∂p` and
# the dot-product identity of lesson 2 says `(∂L/∂p)·v = Σ w ⊙ G`.

# %%
w = np.random.default_rng(6).normal(size=image.shape)
light.requires_grad = True
(render.render(scene) * w).sum().backward()
reverse = float(light.grad @ move_x)
forward = float((w * G_light).sum())
light.requires_grad = False
modes_error = abs(reverse - forward) / abs(reverse)
print(f"reverse {reverse:.12f}, forward {forward:.12f}, relative difference {modes_error:.1e}")

# %% [markdown]
# The two agree to a relative `1e-12` <!-- check: modes_error < -->: the same derivative.
#
# ## The masked finite-difference check
#
# Finite differences see the real image, jumps included. Perturb the light by `±h` along
# `v`, render, and compare `D_h = (I(p + hv) − I(p − hv)) / 2h` with `G`. A pixel whose
# decisions differ between the two renders (its shadow ray now blocked, say) jumps by an
# amount of order 1, so its difference quotient is of order `1/h`: huge, and no fault of the
# tape. The check must therefore compare only the pixels whose `RenderInfo` is the same in
# every perturbed render as in the reference. With the relative `l2` error of the paper's
# Eq. 3, `‖D_h − G‖ / ‖G‖`, over all pixels and over the kept ones:


# %%
def decisions_same(a, b):
    """(H, W): the pixels whose samples hit the same primitives and see the same lights."""
    return (a.prim_id == b.prim_id).all(-1) & (a.lit == b.lit).all(axis=(0, -1))


def fd_check(h):
    with md.no_grad():
        light.data = np.array([2.0 + h, 5.0, 3.0])
        plus, info_plus = render.render(scene, return_info=True)
        light.data = np.array([2.0 - h, 5.0, 3.0])
        minus, info_minus = render.render(scene, return_info=True)
        light.data = np.array([2.0, 5.0, 3.0])
    D = (plus.data - minus.data) / (2 * h)
    keep = decisions_same(info_plus, info) & decisions_same(info_minus, info)
    unmasked = np.linalg.norm(D - G_light) / np.linalg.norm(G_light)
    masked = np.linalg.norm((D - G_light)[keep]) / np.linalg.norm(G_light[keep])
    return D, keep, float(unmasked), float(masked)


for h in (3e-2, 1e-2, 1e-3, 1e-5):
    _, keep, unmasked, masked = fd_check(h)
    print(f"h = {h:.0e}: {(~keep).sum():2d} pixels changed decisions; "
          f"error over all pixels {unmasked:.1e}, over the kept ones {masked:.1e}")  # fmt: skip
D, keep, unmasked_error, masked_error = fd_check(1e-2)
changed_pixels = int((~keep).sum())
render.write_gradient_png(D, OUT / "fd_unmasked_h1e-2.png",
                          scale=float(np.percentile(np.abs(G_light.sum(-1)), 99.5)),
                          label="central differences, h = 0.01 (same scale)")  # fmt: skip
print(f"elapsed {time.perf_counter() - start:.1f} s; figures in {OUT}")

# %% [markdown]
# With `h = 0.01`, `1` <!-- check: changed_pixels --> pixel changes its decision (a sample
# on the shadow's edge), and that one pixel makes the error over all pixels larger than
# `1` <!-- check: unmasked_error > -->: the difference quotient is wrong by more than the
# whole gradient image. Over the other 4,095 pixels the error is below `1e-5`
# <!-- check: masked_error < -->, the `h²` truncation of lesson 2. With smaller `h` no pixel
# happens to flip and both errors are small; the mask is what makes the check reliable
# for *every* `h` and scene, not only lucky ones. `fd_unmasked_h1e-2.png` shows the
# difference quotient on the gradient image's scale: one saturated pixel on the shadow's
# border. (`tests/render/test_gradients.py` runs this check on random scenes for every kind
# of parameter; `tests/render_helpers.py` holds its mask, texels included.)
#
# ## Exercises
#
# 1. Make the gradient image of the *ground's* albedo (`objects[1].material.albedo`) along
#    `(1, 1, 1)`. Which pixels are zero, and why is the teapot's shadow zero too?
# 2. Repeat the masked check for the camera position along `x` with `h = 1e-3`. How many
#    pixels change their decisions now, and where are they? (A moving camera moves every
#    edge in the image: the teapot's outline, but also the edges between its triangles.
#    Compare the primitive each flipped pixel sees before and after.) What is the masked
#    error?
# 3. Compute `∂L/∂(light position)` for `L = mean((I − T)²)` with `T` the render of the
#    light at `(2.5, 5, 3)`, by reverse mode, and check its x component against
#    `Σ (∂L/∂I) ⊙ G` with one gradient image.
#
# Solutions: `lessons/solutions/06_gradients_through_a_renderer.py`.
