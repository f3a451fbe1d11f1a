# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # Solutions to lesson 6 (gradients through a renderer)

# %%
import numpy as np

import minidiff as md
import render

SIZE = 64
light = md.tensor([2.0, 5.0, 3.0])
camera_position = md.tensor([3.0, 2.0, 5.0])
scene = render.paper_scene(width=SIZE, height=SIZE, ground=True, light_position=light,
                           camera_position=camera_position)  # fmt: skip
image, info = render.render(scene, return_info=True)
teapot_faces = render.teapot().num_faces
prim = info.prim_id[..., 0]

# %% [markdown]
# ## Exercise 1: the ground's albedo
#
# `I` is linear in the ground's albedo where the ground is seen and lit, so the gradient
# image is the ground's shading divided by its albedo (0.6) there; it is zero on the teapot
# and the background (they do not use that material) and in the shadow, where no light
# term is added (and there is no ambient term to scale).

# %%
G = render.gradient_image(scene, "objects[1].material.albedo", np.ones(3))
on_ground = prim >= teapot_faces
lit_ground = on_ground & info.lit[0, ..., 0]
assert np.abs(G[~on_ground]).max() == 0
assert np.abs(G[on_ground & ~info.lit[0, ..., 0]]).max() == 0
np.testing.assert_allclose(G[lit_ground], image.data[lit_ground] / 0.6, rtol=1e-12)
print(f"zero on {(~lit_ground).sum()} pixels; ground shading / 0.6 on {lit_ground.sum()}")

# %% [markdown]
# ## Exercise 2: the masked check for the camera
#
# Moving the camera moves every edge across the pixel grid. With `h = 1e-3` only a few
# samples lie that close to an edge, and here every one of them sits on an edge *between
# two of the teapot's triangles* (it sees one triangle before the move and its neighbour
# after): a flat-shaded mesh has far more interior edges than outline, so a random flip is
# far more likely there than on the silhouette. The kept pixels still agree to the `h²`
# truncation.

# %%
move_x = np.array([1.0, 0.0, 0.0])
G_camera = render.gradient_image(scene, "camera.position", move_x)
h, renders = 1e-3, []
with md.no_grad():
    for sign in (1, -1):
        camera_position.data = np.array([3.0 + sign * h, 2.0, 5.0])
        renders.append(render.render(scene, return_info=True))
    camera_position.data = np.array([3.0, 2.0, 5.0])
(plus, info_plus), (minus, info_minus) = renders
keep = np.ones((SIZE, SIZE), bool)
for other in (info_plus, info_minus):
    keep &= (other.prim_id == info.prim_id).all(-1) & (other.lit == info.lit).all(axis=(0, -1))
D = (plus.data - minus.data) / (2 * h)
masked = np.linalg.norm((D - G_camera)[keep]) / np.linalg.norm(G_camera[keep])
changed = ~keep
near_edge = changed & (info.prim_id[..., 0] != np.roll(info.prim_id[..., 0], 1, axis=1))
teapot = (info.prim_id[..., 0] >= 0) & (info.prim_id[..., 0] < teapot_faces)
between_triangles = changed & teapot
for other in (info_plus, info_minus):
    moved = other.prim_id[..., 0]
    between_triangles &= ~(moved != info.prim_id[..., 0]) | ((moved >= 0) & (moved < teapot_faces))
print(f"{changed.sum()} pixels changed decisions ({near_edge.sum()} next to a change of "
      f"primitive along the row, {between_triangles.sum()} between two teapot triangles); "
      f"masked error {masked:.1e}")  # fmt: skip
assert changed.sum() > 0 and masked < 1e-4
assert between_triangles.sum() == changed.sum()  # no flip on the outline at this h

# %% [markdown]
# ## Exercise 3: a loss gradient two ways

# %%
target_scene = render.paper_scene(width=SIZE, height=SIZE, ground=True, light_position=(2.5, 5, 3))
target = render.render(target_scene).data
light.requires_grad = True
loss = ((render.render(scene) - target) ** 2).mean()
loss.backward()
dL_dI = 2 * (image.data - target) / image.data.size
G_light = render.gradient_image(scene, "lights[0].position", move_x)
forward = float((dL_dI * G_light).sum())
print(f"dL/dx: reverse {light.grad[0]:.12e}, forward {forward:.12e}")
assert abs(light.grad[0] - forward) < 1e-12 * abs(forward)
