# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # Solutions to lesson 15 (secondary visibility)
#
# The lesson runs first and lends its closed form, its measurement and its helpers; the
# scene is built again with more occluders to choose from, the lamp able to move, and the
# measuring camera at 16 × 16 to keep the solutions quick.

# %%
import sys
from pathlib import Path

import numpy as np

import minidiff as md
import render
from render.path.boundary.silhouettes import Curves
from render.path.sample.tracer import PathSampler
from render.scene.camera import camera_directions, plain_frame
from render.scene.cornell import box_mesh, grid_quad
from render.scene.placement import placed

# lessons/ is this file's grandparent; in Jupyter (no __file__) the notebook's folder.
here = Path(__file__).resolve().parent if "__file__" in globals() else Path.cwd()
sys.path.insert(0, str(here.parent))  # lessons/course.py
from course import run_lesson  # noqa: E402

# The lesson's sizes, its render and measurement, its closed form and its two helpers of
# the quadrature (the lamp's part of an edge's shadow, and G).
lesson = run_lesson("15_secondary_visibility")
X, Y, Z = lesson["X"], lesson["Y"], lesson["Z"]
OCCLUDER_CENTRE, OCCLUDER_HALF, OCCLUDER_HEIGHT = (
    lesson[k] for k in ("OCCLUDER_CENTRE", "OCCLUDER_HALF", "OCCLUDER_HEIGHT")
)
LAMP_HALF, LAMP_HEIGHT, RADIANCE, ALBEDO = (
    lesson[k] for k in ("LAMP_HALF", "LAMP_HEIGHT", "RADIANCE", "ALBEDO")
)
POINT, render_image, left_mean = lesson["POINT"], lesson["render_image"], lesson["left_mean"]
irradiance, lamp_part, geometry = lesson["irradiance"], lesson["lamp_part"], lesson["geometry"]
SIZE, SEEDS = 16, range(4)


def shadow_scene(occluder: str = "square", shift=(0.0, 0.0, 0.0), lamp_shift=(0.0, 0.0, 0.0)):
    """The lesson's floor, occluder ("square", "sphere" or "box"; moved by ``shift``) and
    lamp (moved by ``lamp_shift``), seen from under the occluder."""
    v, f = grid_quad((0, 0, 0), 1.5 * X, -1.5 * Z)
    objects = [render.Mesh(v, f, render.Material((ALBEDO,) * 3))]
    grey = render.Material((0.5, 0.5, 0.5))
    place = render.Transform(translation=shift)
    if occluder == "square":
        v, f = grid_quad((OCCLUDER_CENTRE, OCCLUDER_HEIGHT, 0), OCCLUDER_HALF * X,
                         OCCLUDER_HALF * Z)  # fmt: skip
        objects.append(render.Mesh(v, f, grey, transform=place))
    elif occluder == "sphere":  # higher than the square: the camera (at 0.4) stays outside
        objects.append(render.Sphere((OCCLUDER_CENTRE + shift[0], 0.6, 0), 0.15, grey))
    else:
        objects.append(box_mesh((OCCLUDER_CENTRE, 0.55, 0), (0.2, 0.05, 0.2), grey))
    v, f = grid_quad((0, LAMP_HEIGHT, 0), LAMP_HALF * X, LAMP_HALF * Z)
    objects.append(render.Mesh(v, f, render.Material((0, 0, 0), emission=(RADIANCE,) * 3),
                               transform=render.Transform(translation=lamp_shift)))  # fmt: skip
    camera = render.Camera((0.2, 0.4, 0.0), (0.2, 0.0, 0.0), (0, 0, -1), 110.0, SIZE, SIZE)
    return render.Scene(objects, [], camera)


# %% [markdown]
# ## Exercise 1: the occluder's height, by hand
#
# The lesson's quadrature with the edges moving along y: `∂a/∂θ = ∂b/∂θ = (0, 1, 0)`.

# %%
curves = Curves.of(PathSampler(placed(shadow_scene()), 1, 2, 100, 0))
angles, faces_side = curves.silhouettes(POINT)
x = POINT[0]
height_terms = {
    int(j): lesson["edge_term"](x, curves.a[j], curves.b[j], faces_side[0, j], Y)
    for j in np.flatnonzero(curves.edge_object == 1)
}
height_by_hand = sum(height_terms.values())
height_exact = float((irradiance(POINT, (0, 1e-6, 0)) - irradiance(POINT, (0, -1e-6, 0)))[0] / 2e-6)
height_error = abs(height_by_hand / height_exact - 1)
height_edges = sum(t != 0 for t in height_terms.values())
print("each edge:", {j: round(t, 5) for j, t in height_terms.items()})
print(f"dE/d(height): boundary term {height_by_hand:.6f}, closed form {height_exact:.6f}")
assert height_error < 1e-6 and height_edges == 2 and height_by_hand > 0

# %% [markdown]
# Raising the occluder brings it closer to the lamp. Seen from `x`, a point `c` of the
# occluder lies on the lamp's plane at `x + (c − x) / height` (lamp at height 1), so its
# projection shrinks towards the point straight above `x`, and every edge's shadow moves
# across itself now. Two of them lie on the lamp (the left edge, and the edge at z = 0.15,
# whose shadow crosses the lamp at z = 0.2), so `2` <!-- check: height_edges --> edges
# contribute; the other two miss the lamp, as before. Both shadows move towards the part
# of the lamp that stays hidden, so lamp is uncovered and the derivative is positive:
# dE/dθ = `0.748` <!-- check: height_exact -->, and the boundary term gives it to
# `1e-6` <!-- check: height_error < --> (relative).
#
# ## Exercise 2: a sphere, and a box's silhouettes
#
# `Curves` lists a sphere as its centre and radius (no edges); seen from `x` its silhouette
# is the circle where the cone from `x` touches it, and `silhouettes` reports the angle
# `2π r / d`, `d` the distance from `x` to the centre.

# %%
sphere_curves = Curves.of(PathSampler(placed(shadow_scene("sphere")), 1, 2, 100, 0))
sphere_angle = float(sphere_curves.silhouettes(POINT)[0][0, sphere_curves.n_edges])
distance = np.linalg.norm(sphere_curves.centre[0] - POINT[0])
assert len(sphere_curves.radius) == 1
assert abs(sphere_angle - 2 * np.pi * 0.15 / distance) < 1e-12


def sphere_derivative(antialias, spp=64):
    """d left_mean / d(sphere's x), the mean over SEEDS (backward: the replay)."""
    values = []
    for seed in SEEDS:
        scene = shadow_scene("sphere")
        centre = scene.objects[1].center
        centre.requires_grad = True
        left_mean(render_image(scene, spp, seed, antialias)).backward()
        values.append(0.0 if centre.grad is None else float(centre.grad[0]))
    return float(np.mean(values))


sphere_plain = sphere_derivative(False, spp=16)
sphere_term = sphere_derivative("secondary")
with md.no_grad():
    h = 0.02
    sphere_truth = float(np.mean([
        (left_mean(render_image(shadow_scene("sphere", (h, 0, 0)), 512, seed).data)
         - left_mean(render_image(shadow_scene("sphere", (-h, 0, 0)), 512, seed).data)) / (2 * h)
        for seed in SEEDS
    ]))  # fmt: skip
sphere_term_error = abs(sphere_term / sphere_truth - 1)
sphere_plain_size = abs(sphere_plain)
print(f"sphere: angle {sphere_angle:.4f} rad; d left_mean / dx: samples only {sphere_plain:.2e}, "
      f"with the term {sphere_term:.4f}, central differences {sphere_truth:.4f}")  # fmt: skip
assert sphere_term_error < 0.05 and sphere_plain_size < 1e-9

box_curves = Curves.of(PathSampler(placed(shadow_scene("box")), 1, 2, 100, 0))
box_counts = {}
for name, apex in (("under", [0.1, 0.0, 0.0]), ("aside", [0.7, 0.0, 0.05])):
    angle = box_curves.silhouettes(np.array([apex]))[0][0, : box_curves.n_edges]
    box_counts[name] = int(np.sum((angle > 0) & (box_curves.edge_object == 1)))
box_under, box_aside = box_counts["under"], box_counts["aside"]
box_edges = int(np.sum(box_curves.edge_object == 1))
print(f"the box's {box_edges} edges; silhouettes:", box_counts)
assert box_under == 4 and box_aside == 6 and box_edges == 12

# %% [markdown]
# The sphere subtends `1.53` <!-- check: sphere_angle --> radians of silhouette at `x`
# (its circle's angular length). Nothing but the shadow depends on the sphere's place, so
# the samples' derivative is below `1e-9` <!-- check: sphere_plain_size < --> in size,
# while with the boundary term the derivative is within `0.05`
# <!-- check: sphere_term_error < --> of central differences (4 × 512 samples per pixel,
# h = 0.02; the sphere's term is noisier than the square's).
#
# A box has `12` <!-- check: box_edges --> edges once the diagonals of its flat faces
# are left out. From right under it a floor point sees only the bottom face, and the
# outline is that face's border: `4` <!-- check: box_under --> edges. From a point off to
# one side (x = 0.7, within the box's z-range) it sees the bottom and the side facing it:
# the outline is a hexagon, `6` <!-- check: box_aside --> edges. The edge the two seen faces
# share is not one of them (both its faces are seen, it lies inside the outline), and
# neither are the edges between two hidden faces.
#
# ## Exercise 3: the lamp moves
#
# Now `G` depends on the parameter (the lamp's points move away from or towards each floor
# point), so the samples' derivative is not zero. The closed form adapts: move the lamp's
# rectangle (the occluder's projection does not change).

# %%
forward_axis, right_axis, up_axis, eye = plain_frame(shadow_scene().camera)
cells = (np.arange(SIZE * 8) + 0.5) / (SIZE * 8)
grid_x, grid_y = np.meshgrid(2 * cells - 1, 1 - 2 * cells)
directions = camera_directions(np.stack([grid_x.ravel(), grid_y.ravel()], axis=1),
                               right_axis, up_axis, forward_axis)  # fmt: skip
floor_points = eye + directions * (-eye[1] / directions[:, 1:2])


def exact_left_mean(lamp_x: float) -> float:
    radiance = ALBEDO / np.pi * irradiance(floor_points, lamp_x=lamp_x)
    return float(left_mean(radiance.reshape(SIZE, 8, SIZE, 8).mean(axis=(1, 3))))


lamp_exact = (exact_left_mean(1e-5) - exact_left_mean(-1e-5)) / 2e-5


def lamp_derivative(antialias, spp=32):
    values = []
    for seed in SEEDS:
        scene = shadow_scene()
        shift = scene.objects[2].transform.translation
        shift.requires_grad = True
        left_mean(render_image(scene, spp, seed, antialias)).backward()
        values.append(float(shift.grad[0]))
    return float(np.mean(values))


lamp_plain = lamp_derivative(False)
lamp_term = lamp_derivative("secondary")
lamp_plain_share = lamp_plain / lamp_exact
lamp_term_error = abs(lamp_term / lamp_exact - 1)
print(f"lamp's x: samples only {lamp_plain:.4f}, with the term {lamp_term:.4f}, "
      f"closed form {lamp_exact:.4f}")  # fmt: skip
assert lamp_term_error < 0.03 and abs(lamp_plain_share) < 0.5

# %% [markdown]
# The closed form gives d left_mean / d(lamp's x) = `-0.2567` <!-- check: lamp_exact -->:
# moving the lamp to +x moves the shadow to −x, into the left half, and moves the lamp
# away from most of the left half's floor. The samples' derivative gets `0.18`
# <!-- check: lamp_plain_share --> of it: the second part, the change of `G` (the
# distances and angles to the lamp's points), which is real; it misses the larger part,
# the shadow's penumbra sliding across the floor. With the boundary term the estimate is
# within `0.03` <!-- check: lamp_term_error < --> of the closed form.
# (`docs/path_tracing.md` finds the same in the Cornell box: with the blocks' soft shadows
# in view, the light position's derivative is 92 % missed without the term.)
