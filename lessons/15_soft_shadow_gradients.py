# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # Lesson 15 — Secondary visibility: the gradient of a soft shadow
#
# Lesson 11 found the derivative that sampling misses when an edge moves across the
# *image*: the integrand over a pixel jumps where a silhouette is, the jump moves with the
# parameters, and Reynolds' transport theorem adds a boundary term along the edge. The
# same thing happens one bounce later. The light a floor point `x` receives from an area
# light is an integral over the light's surface,
#
#     E(x) = ∫_light  L_e  V(x, x')  G(x, x')  dA(x') ,
#
# with `G` the geometry term (the cosines over the squared distance) and `V(x, x')` the
# **visibility**: 1 if nothing lies between `x` and the light's point `x'`, else 0. Where
# an occluder covers part of the light, `V` jumps from 1 to 0 along a curve on the light:
# the occluder's silhouette seen from `x`. That curve makes the soft shadow (the penumbra:
# the points that see part of the light), and it moves when the light, the occluder or `x`
# moves. A path tracer that differentiates its samples (lesson 10) differentiates `G` and
# `L_e` but holds each sample's `V` fixed: it misses the motion of the curve, that is, most
# of how a soft shadow changes. This is *secondary* visibility: the jumps seen from a
# shading point, not from the camera.
#
# This lesson measures what is missed on a scene you can look at, writes the boundary term
# from a shading point, checks the library's estimate of it (`render/path/secondary.py`,
# `antialias="secondary"`) against finite differences, and compares the method with its
# alternatives.

# %%
import time

import numpy as np
from course import figures_folder, save_and_show
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

import minidiff as md
import render
from render.path import render_path
from render.path.silhouettes import Curves
from render.path.tracer import PathSampler
from render.scene.cornell import box_mesh, grid_quad
from render.scene.placement import placed

# This lesson's figures go to out/lessons/15_soft_shadow_gradients/ (or under $LESSONS_OUT).
OUT = figures_folder("15_soft_shadow_gradients")
lesson_start = time.perf_counter()
X, Y, Z = np.eye(3)

# %% [markdown]
# ## The scene: a box's soft shadow
#
# A white floor, a flat grey box hovering 0.6 above it, and a small square lamp (side 0.25,
# emission 5) at height 1, facing down. The camera hangs *under* the box, looking down at
# the floor with a wide (110°) lens: it sees the floor and the shadow, but neither the box
# nor the lamp, so nothing that moves in this lesson has an edge in the image itself. All
# the derivative comes from the shadow. `max_depth=2`: the light that reaches the floor
# directly (lesson 10's segments).


# %%
def shadow_scene(lamp_shift: float = 0.0, size: int = 24) -> render.Scene:
    """The floor, the box and the lamp (moved by ``lamp_shift`` along x), seen from under
    the box; ``size`` × ``size`` pixels."""
    v, f = grid_quad((0, 0, 0), 1.5 * X, -1.5 * Z)
    floor = render.Mesh(v, f, render.Material((0.8, 0.8, 0.8)))
    box = box_mesh((0.1, 0.6, 0.0), (0.2, 0.05, 0.2), render.Material((0.5, 0.5, 0.5)))
    v, f = grid_quad((0.0, 1.0, 0.0), 0.25 * X, 0.25 * Z)
    emitter = render.Material((0, 0, 0), emission=(5.0, 5.0, 5.0))
    lamp = render.Mesh(v, f, emitter, transform=render.Transform(translation=(lamp_shift, 0, 0)))
    camera = render.Camera((0.05, 0.35, 0.05), (0.0, 0.0, 0.0), (0, 0, -1), 110.0, size, size)
    return render.Scene([floor, box, lamp], [], camera)


def shadow_render(scene: render.Scene, spp: int, seed: int, antialias=False) -> md.Tensor:
    """The path-traced image: direct light only, no Russian roulette (rr_depth past
    max_depth), so that every seed's estimate is a smooth function of the lamp's place
    apart from the visibility jumps."""
    return render_path(scene, spp=spp, max_depth=2, seed=seed, rr_depth=100, antialias=antialias)


with md.no_grad():
    picture = shadow_render(shadow_scene(), spp=256, seed=0).data
print(f"the floor's brightness: lit {picture.max():.3f}, in the shadow's core {picture.min():.3f}")

# %% [markdown]
# ## What differentiating the samples misses
#
# The quantity to differentiate: the image's sum (every pixel's brightness added), with
# respect to the lamp's position along x. Three numbers, each averaged over four seeds:
#
# * **the samples' derivative** (`antialias=False`): minidiff's `backward` through the
#   path tracer, `V` of every sample held fixed;
# * **with the boundary term** (`antialias="secondary"`): the same plus the library's
#   estimate of the term along the silhouettes;
# * **the truth**: central differences `(S(+h) − S(−h)) / 2h` of renders with 1,024
#   samples per pixel, the same seeds on both sides (common random numbers: the noise
#   cancels in the difference).

# %%
SEEDS = range(4)


def lamp_derivative(antialias, spp: int = 64) -> tuple[float, float]:
    """The mean over SEEDS of d(sum of the image)/d(lamp's x), and its standard error."""
    values = []
    for seed in SEEDS:
        scene = shadow_scene()
        shift = scene.objects[2].transform.translation
        shift.requires_grad = True
        shadow_render(scene, spp, seed, antialias).sum().backward()
        values.append(float(shift.grad[0]))
    return float(np.mean(values)), float(np.std(values, ddof=1) / np.sqrt(len(values)))


def central_difference(h: float, spp: int = 1024) -> tuple[float, np.ndarray]:
    """The central difference of the image's sum with step ``h`` (mean over SEEDS), and
    the per-pixel difference image (H, W)."""
    with md.no_grad():
        images = [
            (shadow_render(shadow_scene(+h), spp, seed).data
             - shadow_render(shadow_scene(-h), spp, seed).data) / (2 * h)
            for seed in SEEDS
        ]  # fmt: skip
    image = np.mean(images, axis=0).sum(-1)
    return float(image.sum()), image


samples_only, samples_only_error = lamp_derivative(False)
with_term, with_term_error = lamp_derivative("secondary")
fd_coarse, _ = central_difference(0.05)
fd_fine, derivative_image = central_difference(0.025)
# The central difference's error falls as h²: two steps give its limit (Richardson).
truth = (4 * fd_fine - fd_coarse) / 3
print(f"samples only {samples_only:.1f} ± {samples_only_error:.1f}; with the boundary term "
      f"{with_term:.1f} ± {with_term_error:.1f}")  # fmt: skip
print(f"central differences: h = 0.05 {fd_coarse:.1f}, h = 0.025 {fd_fine:.1f}, "
      f"extrapolated to h = 0: {truth:.1f}")  # fmt: skip
share_seen = samples_only / truth
term_error = abs(with_term / truth - 1)
step_bias = abs(fd_coarse / truth - 1)

# %% [markdown]
# Moving the lamp along x moves the shadow along −x, and the image's sum falls fast: the
# truth is `-351.1` <!-- check: truth -->. The samples' derivative sees only `0.16`
# <!-- check: share_seen --> of it: what it gets right is the change of `G` and of the
# lamp's angle to each point, not the penumbra sliding over the floor. With the boundary
# term the estimate is within `0.02` <!-- check: term_error < --> of the truth (relative),
# about as close as four seeds can show.
#
# The truth needed care of its own. With the step `h = 0.05` the central difference is off
# by `0.03` <!-- check: step_bias --> (relative): the lamp is 0.25 wide, so 0.05 is a
# fifth of it, and the penumbra's profile is curved on that scale. The error of a central
# difference falls as `h²`, so two steps give a better estimate than either,
# `(4 D(h/2) − D(h)) / 3` (Richardson extrapolation). Lesson 11 met the same trade: a step
# small enough for the curvature, samples enough for the noise of the smaller difference.
#
# `soft_shadow.png` shows the image and the truth's derivative per pixel. Most of it lies
# in the two penumbras, where the floor sees part of the lamp: negative (red) where the
# shadow moves in, positive (blue) at the edge of the view, where it moves out; the
# shadow's core, which sees none of the lamp, does not change.

# %%
figure = Figure(figsize=(7.0, 3.4), dpi=100, layout="constrained")
FigureCanvasAgg(figure)
left = figure.add_subplot(1, 2, 1)
left.imshow(np.clip(picture / picture.max(), 0, 1) ** (1 / 2.2), interpolation="nearest")
left.set_title("the floor from under the box\n(256 spp)", fontsize=10)
right = figure.add_subplot(1, 2, 2)
limit = np.abs(derivative_image).max()
shown = right.imshow(derivative_image, cmap="RdBu", vmin=-limit, vmax=limit,
                     interpolation="nearest")  # fmt: skip
right.set_title("d(pixel) / d(lamp's x), central differences\n(red: darker as the lamp moves)",
                fontsize=10)  # fmt: skip
figure.colorbar(shown, ax=right, shrink=0.8)
for ax in (left, right):
    ax.set_axis_off()
save_and_show(figure, OUT / "soft_shadow.png")

# %% [markdown]
# ## The boundary term from a shading point
#
# Fix a floor point `x`. Write the lamp's points `x'` with a **level set function** that is
# zero on the jump of `V` and changes sign across it. For a mesh edge `(a, b)` of the
# occluder, seen from `x`, it is the side of the plane through `x` and the edge:
#
#     φ(x') = (x' − x) · ((a − x) × (b − x)) .
#
# Reynolds' theorem in level-set form (lesson 11 had it for a pixel) splits the derivative
# of `E(x)` into the interior term the tape computes and
#
#     ∫_curve  (F₊ − F₋)  (∂φ/∂θ) / |∇_S φ|  dl ,
#
# an integral along the curve on the lamp, with `F₊ − F₋` the jump of the integrand (here:
# the lamp's unoccluded contribution, against zero), `∂φ/∂θ` how fast the curve's level set
# changes with the parameter at a fixed `x'`, `|∇_S φ|` its gradient along the lamp's
# surface (so that the quotient is the curve's normal speed) and `dl` length on the lamp.
#
# **Which edges?** Only the *silhouette* edges seen from `x`: those whose two faces lie on
# the same side of the plane through `x` and the edge (for a border edge, always). An edge
# between a face `x` sees and one it does not is where the box's outline is; an edge
# between two faces `x` sees is inside the outline, and `V` does not jump there.
# `render.path.silhouettes.Curves` lists the candidate edges and, for any apex, the angle
# each one subtends if it is a silhouette (0 if not):

# %%
curves = Curves.of(PathSampler(placed(shadow_scene()), 1, 2, 100, 0))
owner = {0: "floor", 1: "box", 2: "lamp"}
below = np.array([[0.1, 0.0, 0.0]])  # right under the box's centre
aside = np.array([[0.6, 0.0, 0.3]])  # off to one side
silhouette_counts = {}
for name, apex in (("below the box", below), ("aside", aside)):
    angle, _ = curves.silhouettes(apex)
    seen = angle[0, : curves.n_edges] > 0
    silhouette_counts[name] = {
        owner[o]: int(np.sum(seen & (curves.edge_object == o))) for o in owner
    }
    print(f"{name}: silhouette edges {silhouette_counts[name]}")
box_edges_listed = int(np.sum(curves.edge_object == 1))
box_silhouettes_below = silhouette_counts["below the box"]["box"]
box_silhouettes_aside = silhouette_counts["aside"]["box"]

# %% [markdown]
# The box has `12` <!-- check: box_edges_listed --> edges (its faces' diagonals are left
# out: they lie inside flat faces and are never silhouettes). From the point right under
# it, `4` <!-- check: box_silhouettes_below --> are silhouettes: the point sees only the
# bottom face, and its outline is the bottom face's border. From the point aside, `6`
# <!-- check: box_silhouettes_aside --> are: it sees the bottom and two sides, and the
# outline is a hexagon. The lamp's four border edges are silhouettes from every floor point
# (its outline needs no term, though: the lamp's area moves with it, which the interior term
# already differentiates; the library leaves them to the integral). The floor's own edges
# lie in the plane of `x`: grazing, never silhouettes of anything `x` can see behind.
#
# **The estimator** (`render/path/secondary.py`, one sample per path vertex): pick a
# silhouette with probability proportional to the angle it subtends at `x`, a point `m` on
# it uniformly in that angle, trace the ray from `x` through `m` to the first surface
# beyond, `x'`; the sample is the path's throughput times the unoccluded contribution of
# `x'`, times `|dx'/dt| / |∇_S φ|` (the curve's length on the surface per unit of the edge
# parameter, over the level set's gradient), divided by the probability of the draw, times
# `∂φ/∂θ` — the only factor on the tape, recomputed from `x`, `x'` and the edge's vertices
# so that `backward` reaches every parameter that moves any of them. Its *value* is
# `φ − φ = 0`: the image does not change, only its gradient. Picking by angle matters: a
# point uniform along an edge that passes close to `x` would carry a weight growing as one
# over the distance, and a single such sample could hold most of a seed's gradient
# (`docs/path_tracing.md`).
#
# ## The method against its alternatives
#
# * **Edge sampling from shading points** (Li, Aittala, Durand, Lehtinen 2018, redner),
#   written in area measure as in path-space differentiable rendering (Zhang, Wu, Zhao
#   2020): what the library does. Unbiased; the boundary is explicit, so one can see which
#   edge moved which pixel; one term covers soft shadows, indirect occlusion and the hard
#   shadows of point lights (the same construction with the light as the apex). Its cost is
#   *finding* silhouettes: redner builds a hierarchy over edges; the library loops over all
#   candidate curves per vertex in Numba, fine for tens to hundreds of edges and the first
#   thing to replace for meshes with thousands.
# * **Projective sampling** (Zhang, Roussel, Jakob 2023; Mitsuba 3's `prb_projective`):
#   start from an ordinary sample of the integrand and project it onto a nearby boundary,
#   with guiding structures to find the boundaries that matter. Better at scale (no loop
#   over edges per vertex), but much more machinery to read, for the same term.
# * **Reparameterisation** (Loubet, Holzschuch, Jakob 2019) and **warped-area sampling**
#   (Bangaru, Li, Durand 2020): move the samples with the discontinuities so that no
#   boundary term is needed. Nothing to find, but Loubet's warp is only approximately
#   aligned with the edges (a bias) and warped-area sampling spends many extra rays per
#   sample on its weights.
#
# `docs/path_tracing.md` gives these reasons at length, and checks the term on the Cornell
# box against central differences (light position, sphere centre, a box's corner, a point
# light's shadows seen after a bounce: all within 2 %) and against Mitsuba 3's projective
# integrator.

# %%
print(f"elapsed {time.perf_counter() - lesson_start:.1f} s; figures in {OUT}")

# %% [markdown]
# ## Exercises
#
# 1. **The lamp's size.** Make the lamp's `Transform` scale (`transform.scale`) the
#    parameter, with its emission fixed (so a larger lamp gives more light). Compare the
#    samples' derivative, the one with the term, and central differences. What share of
#    the truth does the samples' derivative get now, and why more than when the lamp
#    slides? (What does a larger lamp change besides its penumbra?)
# 2. **A sphere for the box.** Replace the box by a `render.Sphere` of radius 0.15 at the
#    same place and differentiate the image's sum with respect to the sphere's centre
#    along x. A sphere has no edges: what is its silhouette seen from `x`, and what does
#    `Curves` list for it?
# 3. **Counting silhouettes.** Walk a point along the floor from under the box's centre
#    outwards (x from 0.1 to 1.0, z = 0.05) and plot the number of the box's silhouette
#    edges against x. Where does it change from 4 to 6, and why there?
#
# Solutions: `lessons/solutions/15_soft_shadow_gradients.py`.
