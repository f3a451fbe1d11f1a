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

# %%
import numpy as np

import minidiff as md
import render
from render.path import render_path
from render.path.silhouettes import Curves
from render.path.tracer import PathSampler
from render.scene.cornell import box_mesh, grid_quad
from render.scene.placement import placed

X, Y, Z = np.eye(3)
SEEDS = range(4)


def scene(occluder: str = "box", lamp_scale: float = 1.0, sphere_x: float = 0.1):
    """Lesson 15's scene at 16 × 16: the floor, an occluder ("box" or "sphere", the
    sphere's centre at x = ``sphere_x``) and the lamp scaled by ``lamp_scale`` about its
    centre, its emission per area fixed."""
    v, f = grid_quad((0, 0, 0), 1.5 * X, -1.5 * Z)
    objects = [render.Mesh(v, f, render.Material((0.8, 0.8, 0.8)))]
    grey = render.Material((0.5, 0.5, 0.5))
    if occluder == "box":
        objects.append(box_mesh((0.1, 0.6, 0.0), (0.2, 0.05, 0.2), grey))
    else:
        objects.append(render.Sphere((sphere_x, 0.6, 0.0), 0.15, grey))
    v, f = grid_quad((0.0, 1.0, 0.0), 0.25 * X, 0.25 * Z)
    emitter = render.Material((0, 0, 0), emission=(5.0, 5.0, 5.0))
    lamp = render.Mesh(v, f, emitter, transform=render.Transform(scale=lamp_scale))
    camera = render.Camera((0.05, 0.35, 0.05), (0.0, 0.0, 0.0), (0, 0, -1), 110.0, 16, 16)
    return render.Scene([*objects, lamp], [], camera)


def image_sum(s, spp, seed, antialias=False):
    image = render_path(s, spp=spp, max_depth=2, seed=seed, rr_depth=100, antialias=antialias)
    return image.sum()


def derivatives(make, parameter, direction=1.0, spp=64):
    """(samples only, with the boundary term, central differences extrapolated to h = 0)
    of the image's sum with respect to the scalar ``make(value)`` builds its scene from,
    ``parameter(scene)`` is the tensor, ``direction`` the direction its offset t moves it
    in, ``make(t)`` the scene at offset t."""
    ours = {}
    for antialias in (False, "secondary"):
        values = []
        for seed in SEEDS:
            s = make(0.0)
            p = parameter(s)
            p.requires_grad = True
            image_sum(s, spp, seed, antialias).backward()
            values.append(float(np.sum(p.grad * direction)))
        ours[antialias] = float(np.mean(values))
    with md.no_grad():
        fd = {
            h: np.mean([
                (image_sum(make(h), 1024, seed).item() - image_sum(make(-h), 1024, seed).item())
                / (2 * h)
                for seed in SEEDS
            ])
            for h in (0.05, 0.025)
        }  # fmt: skip
    truth = float((4 * fd[0.025] - fd[0.05]) / 3)
    return ours[False], ours["secondary"], truth


# %% [markdown]
# ## Exercise 1: the lamp's size
#
# With the emission per area fixed, a larger lamp sends more light: its power grows with its
# area, on every lit point of the floor. That part of the derivative is in the interior
# term (the lamp's area, and each sample's place on it, move with the scale): the samples'
# derivative gets it. What it misses is the penumbra widening around the shadow's core.

# %%
size_plain, size_term, size_truth = derivatives(
    lambda t: scene(lamp_scale=1.0 + t), lambda s: s.objects[2].transform.scale
)
size_plain_share = size_plain / size_truth
size_term_error = abs(size_term / size_truth - 1)
print(f"lamp size: samples only {size_plain:.2f}, with the term {size_term:.2f}, "
      f"central differences {size_truth:.2f}")  # fmt: skip
assert size_term_error < 0.03 and 0.1 < size_plain_share < 0.5

# %% [markdown]
# The samples' derivative gets `0.28` <!-- check: size_plain_share --> of the truth, more
# than the 0.16 of the lamp's slide (the growth of its power is in the interior term), but
# in this scene most of the change is still the penumbra's: the box's shadow covers much of
# the view, and its penumbra widens on every side. The derivative with the term is within
# `0.03` <!-- check: size_term_error < --> of the truth. (`docs/path_tracing.md` notes
# the opposite case in the Cornell box, where the light's growth dominates and the
# camera's term alone comes within 1.3 %: a light's size is a weak test of a boundary term
# unless its power is held fixed.)
#
# ## Exercise 2: a sphere
#
# A sphere has no edges: seen from `x`, its silhouette is the circle where the cone from `x`
# touches it, and `φ(x') = distance(c, line(x, x')) − r` (negative inside the cone).
# `Curves` lists it as a centre and a radius, and `silhouettes` gives the circle's angle,
# `2π r / distance`.

# %%
sphere_plain, sphere_term, sphere_truth = derivatives(
    lambda t: scene("sphere", sphere_x=0.1 + t), lambda s: s.objects[1].center, X, spp=256
)
sphere_term_error = abs(sphere_term / sphere_truth - 1)
sphere_plain_share = sphere_plain / sphere_truth
curves = Curves.of(PathSampler(placed(scene("sphere")), 1, 2, 100, 0))
print(f"sphere's x: samples only {sphere_plain:.2f}, with the term {sphere_term:.2f}, "
      f"central differences {sphere_truth:.2f}; Curves lists spheres {curves.centre.tolist()}, "
      f"radii {curves.radius.tolist()}")  # fmt: skip
assert sphere_term_error < 0.05 and abs(sphere_plain_share) < 0.2

# %% [markdown]
# (A sphere's term is noisier than the box's, per sample: 256 samples per pixel here.)
# Nothing but the shadow depends on the sphere's place (the camera does not see it), so
# the samples' derivative gets almost nothing: `0.00` <!-- check: sphere_plain_share --> of
# the truth, while the one with the term is within `0.05` <!-- check: sphere_term_error < -->.
#
# ## Exercise 3: counting the box's silhouettes along the floor

# %%
box_curves = Curves.of(PathSampler(placed(scene()), 1, 2, 100, 0))
xs = np.linspace(0.1, 1.0, 91)
apexes = np.stack([xs, np.zeros_like(xs), np.full_like(xs, 0.05)], axis=1)
angles, _ = box_curves.silhouettes(apexes)
counts = ((angles[:, : box_curves.n_edges] > 0) & (box_curves.edge_object == 1)).sum(axis=1)
first_six = float(xs[np.argmax(counts == 6)])
at_the_side_plane = int(counts[np.argmin(np.abs(xs - 0.3))])
print("box silhouette edges at x = 0.1, 0.2, ..., 1.0:", counts[::10].tolist())
assert counts[0] == 4 and counts[-1] == 6 and set(counts[xs < 0.295]) == {4}

# %% [markdown]
# Right under the box a point sees only its bottom face: 4 silhouette edges. Once the
# point passes the plane of the box's side face, at `x = 0.1 + 0.2 = 0.3` (the box spans
# x ∈ [−0.1, 0.3]), it sees that face too and the outline is the bottom face plus one side
# (z = 0.05 keeps the point within the box's z-range, so no other side shows): 6 edges,
# from `x = 0.31` <!-- check: first_six --> on, the first point of the walk past 0.3.
# Exactly at 0.3 the side face is seen edge-on and the count is `3`
# <!-- check: at_the_side_plane -->: the edges around that face are grazing there, and
# `Curves` leaves a grazing edge out rather than decide which side its faces are on.
