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
# Lessons 8 and 11 dealt with edges the *camera* sees: a pixel integrates over its area,
# a silhouette makes the integrand jump, and when the silhouette moves Reynolds' transport
# theorem adds a boundary term that no derivative of the samples contains. Lesson 10's
# path tracer has more integrals than the camera's. The light a floor point `x` receives
# from an area lamp is an integral over the lamp's surface,
#
#     E(x) = ∫_lamp  L_e  V(x, x')  G(x, x')  dA(x') ,        G = cos θ cos θ' / r² ,
#
# and the **visibility** `V(x, x')` is 1 where nothing lies between `x` and the lamp's
# point `x'`, 0 where something does. An occluder between them hides part of the lamp: `V`
# jumps along a curve on the lamp, the occluder's outline seen from `x`. The floor points
# that see part of the lamp make the soft shadow's penumbra. When the occluder moves, the
# curve moves, and `E(x)` changes, although nothing in the integrand but `V` depends on
# the occluder. This is **secondary visibility**: jumps seen from a shading point, not
# from the camera, and the camera may see none of them.
#
# This lesson measures what a renderer that differentiates its samples gets for a soft
# shadow (nothing), writes the boundary term at one floor point by hand (three ways),
# checks the library's estimate of it (`render/path/boundary/secondary.py`,
# `antialias="secondary"`) on a whole image against central differences and against a
# closed form, and places the method among its alternatives.

# %%
import time

import numpy as np
from course import figures_folder, save_and_show
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

import minidiff as md
import render
from render.path import render_path
from render.path.boundary.silhouettes import Curves, pick_reference
from render.path.sample.emitters import polygon_irradiance
from render.path.sample.random import uniform
from render.path.sample.tracer import PathSampler
from render.scene.camera import camera_directions, plain_frame, project
from render.scene.cornell import grid_quad
from render.scene.placement import placed

# This lesson's figures go to out/lessons/15_secondary_visibility/ (or under $LESSONS_OUT).
OUT = figures_folder("15_secondary_visibility")
lesson_start = time.perf_counter()
X, Y, Z = np.eye(3)

# %% [markdown]
# ## The scene: a square's soft shadow
#
# A white floor (albedo 0.8) at height 0; a grey square of side 0.3 hovering at height 0.5
# (the occluder; centred at x = 0.1); a square lamp of side 0.5 at height 1, facing down,
# radiance 5, centred above the origin. The lamp is wide for the occluder's height, so the
# shadow is mostly penumbra: a core about 0.1 across, where the floor sees none of the
# lamp, inside a penumbra about 1.1 across. The occluder is placed by a `Transform` whose
# `translation` is the parameter θ of this lesson.
#
# Two cameras: one from the side, to show you the scene, and the one we measure with,
# hanging *under* the occluder (at height 0.4) and looking straight down with a wide lens.
# It sees the floor and the shadow but neither the occluder nor the lamp, so no edge the
# camera sees moves with θ: all of the derivative is secondary visibility. `max_depth=2`
# is direct light only (lesson 10: a camera segment and a segment to the lamp), and
# `rr_depth=100` turns Russian roulette off.

# %%
OCCLUDER_CENTRE, OCCLUDER_HALF, OCCLUDER_HEIGHT = 0.1, 0.15, 0.5
LAMP_HALF, LAMP_HEIGHT, RADIANCE, ALBEDO = 0.25, 1.0, 5.0, 0.8
SIZE = 20  # the measuring camera's pixels per side


def shadow_scene(shift=(0.0, 0.0, 0.0), camera: render.Camera | None = None) -> render.Scene:
    """Floor, occluder (moved by ``shift``) and lamp, seen by ``camera`` (default: the
    measuring camera, under the occluder looking down; its image's right is +x)."""
    v, f = grid_quad((0, 0, 0), 1.5 * X, -1.5 * Z)  # faces up
    floor = render.Mesh(v, f, render.Material((ALBEDO,) * 3))
    v, f = grid_quad((OCCLUDER_CENTRE, OCCLUDER_HEIGHT, 0), OCCLUDER_HALF * X, OCCLUDER_HALF * Z)
    occluder = render.Mesh(v, f, render.Material((0.5, 0.5, 0.5)),
                           transform=render.Transform(translation=shift))  # fmt: skip
    v, f = grid_quad((0, LAMP_HEIGHT, 0), LAMP_HALF * X, LAMP_HALF * Z)  # faces down
    lamp = render.Mesh(v, f, render.Material((0, 0, 0), emission=(RADIANCE,) * 3))
    if camera is None:
        camera = render.Camera((0.2, 0.4, 0.0), (0.2, 0.0, 0.0), (0, 0, -1), 110.0, SIZE, SIZE)
    return render.Scene([floor, occluder, lamp], [], camera)


def render_image(scene: render.Scene, spp: int, seed: int, antialias=False) -> md.Tensor:
    """Direct light only, no Russian roulette: every seed's image is a smooth function of
    θ except where a sample's visibility flips."""
    return render_path(scene, spp=spp, max_depth=2, seed=seed, rr_depth=100, antialias=antialias)


def left_mean(image):
    """The quantity we differentiate: the mean brightness of the image's left half (the
    floor at x < 0.2, the shadow's left half), all three channels."""
    return image[:, : image.shape[1] // 2].mean()


side_camera = render.Camera((1.0, 0.8, 1.4), (0.1, 0.4, 0.0), (0, 1, 0), 60.0, 96, 96)
with md.no_grad():
    overview = render_image(shadow_scene(camera=side_camera), spp=16, seed=0).data
    picture = render_image(shadow_scene(), spp=256, seed=0).data
print(f"the measuring camera's picture: mean {picture.mean():.4f}, left half "
      f"{left_mean(picture):.4f}")  # fmt: skip

# %%
figure = Figure(figsize=(7.6, 3.7), dpi=100, layout="constrained")
FigureCanvasAgg(figure)
axes = figure.subplots(1, 2)
axes[0].imshow(np.clip(3 * overview, 0, 1) ** (1 / 2.2), interpolation="nearest")
labels = {"lamp": (0.0, 1.0, 0.0), "occluder": (0.1, 0.5, 0.0), "soft shadow": (0.2, 0.0, 0.0)}
where, _ = project(np.array(list(labels.values())), plain_frame(side_camera), 96, 96)
for (name, _), (px, py) in zip(labels.items(), where, strict=True):
    axes[0].annotate(name, (px, py), (px - 45, py + 8), color="orange", fontsize=9,
                     arrowprops={"arrowstyle": "->", "color": "orange"})  # fmt: skip
axes[0].set_title("the scene from the side (16 spp)", fontsize=10)
axes[1].imshow(np.clip(picture / picture.max(), 0, 1) ** (1 / 2.2), interpolation="nearest")
axes[1].axvline(SIZE / 2 - 0.5, color="orange", lw=1)
axes[1].set_title("the measuring camera: the floor from under\nthe occluder (256 spp; "
                  "left of the line: left_mean)", fontsize=10)  # fmt: skip
for ax in axes:
    ax.set_axis_off()
save_and_show(figure, OUT / "scene.png")

# %% [markdown]
# `scene.png`: on the left the lamp, the occluder lit from above and its shadow on the
# floor; on the right what the measuring camera sees, a dark core (where the floor sees
# almost none of the lamp) fading into a wide penumbra.
#
# ## 1. What differentiating the integrand misses
#
# Differentiate `left_mean`, the mean brightness of the picture's left half, with respect
# to the occluder's x. Moving the occluder to +x moves its shadow to +x, out of the left
# half: the left half brightens, the derivative is positive.
#
# **The samples' derivative.** `backward` through the path tracer (by default a replay of
# the paths, lesson 14; the same as the tape's): the derivative of every sample, its
# visibility held as the sampler decided it.

# %%
scene = shadow_scene()
shift = scene.objects[1].transform.translation
shift.requires_grad = True
left_mean(render_image(scene, spp=64, seed=0)).backward()
interior_x = abs(float(shift.grad[0]))
print(f"the samples' derivative d left_mean / d x = {float(shift.grad[0]):.3g}")

# %% [markdown]
# **The truth**: central differences `(B(θ + h) − B(θ − h)) / 2h` of renders with 1,024
# samples per pixel, `h = 0.02`, each pair with the same seed (common random numbers: the
# noise of the two sides mostly cancels), over four seeds:

# %%
H, SEEDS, FD_SPP = 0.02, range(4), 1024
with md.no_grad():
    fd_images = [
        (render_image(shadow_scene((+H, 0, 0)), FD_SPP, seed).data
         - render_image(shadow_scene((-H, 0, 0)), FD_SPP, seed).data) / (2 * H)
        for seed in SEEDS
    ]  # fmt: skip
fd_per_seed = [float(left_mean(d)) for d in fd_images]
truth = float(np.mean(fd_per_seed))
truth_se = float(np.std(fd_per_seed, ddof=1) / np.sqrt(len(fd_per_seed)))
print(f"central differences: {truth:.4f} ± {truth_se:.4f} (seeds: {np.round(fd_per_seed, 4)})")

# %% [markdown]
# The samples' derivative is below `1e-12` <!-- check: interior_x < --> in size (rounding
# of a zero); the truth is `0.416` <!-- check: truth -->. Nothing went wrong inside the
# tape: with `max_depth=2` the occluder enters a path's contribution only through whether
# the shadow ray from the floor to the lamp is blocked, a 0 or a 1 the sampler decided off
# the tape (a path whose sampled direction meets the occluder's underside ends there and
# carries nothing: the occluder emits no light). Lesson 11's one-line argument, one bounce
# later: the derivative of the estimate is not an estimate of the derivative.
#
# ## At one floor point
#
# Take the floor point `x = (0, 0, 0.1)`, in the left penumbra. Its irradiance has a closed
# form. Seen from `x`, the occluder's square projects onto the lamp's plane as a larger
# square (scaled by height 1 over height 0.5), and the lamp's hidden part is the overlap of
# two rectangles, another rectangle. Lambert's polygon formula (lesson 10,
# `render.path.sample.emitters.polygon_irradiance`) gives the integral of `G` over each:
# `E = L_e (P(lamp) − P(overlap))`.


# %%
def rectangle(lo, hi):
    """The corners (n, 4, 3) of rectangles [lo, hi] (n, 2) in (x, z) on the lamp's plane."""
    xs = np.stack([lo[:, 0], hi[:, 0], hi[:, 0], lo[:, 0]], axis=1)
    zs = np.stack([lo[:, 1], lo[:, 1], hi[:, 1], hi[:, 1]], axis=1)
    return np.stack([xs, np.full(xs.shape, LAMP_HEIGHT), zs], axis=2)


def irradiance(points, shift=(0.0, 0.0, 0.0), lamp_x: float = 0.0):
    """E at floor points (n, 3) with the occluder moved by ``shift`` (and the lamp by
    ``lamp_x`` along x, for the exercises): the lamp's, less the part the occluder's
    square, projected from each point onto the lamp's plane, hides."""
    shift = np.asarray(shift, float)
    scale = LAMP_HEIGHT / (OCCLUDER_HEIGHT + shift[1])  # from a floor point at height 0
    xz = points[:, [0, 2]]
    centre = np.array([OCCLUDER_CENTRE + shift[0], shift[2]])
    lamp_lo = np.full(xz.shape, -LAMP_HALF) + [lamp_x, 0]
    lamp_hi = np.full(xz.shape, LAMP_HALF) + [lamp_x, 0]
    lo = np.maximum(xz + (centre - OCCLUDER_HALF - xz) * scale, lamp_lo)
    hi = np.minimum(xz + (centre + OCCLUDER_HALF - xz) * scale, lamp_hi)
    hidden = np.where(np.all(hi > lo, axis=1), polygon_irradiance(points, Y, rectangle(lo, hi)), 0)
    return RADIANCE * (polygon_irradiance(points, Y, rectangle(lamp_lo, lamp_hi)) - hidden)


POINT = np.array([[0.0, 0.0, 0.1]])
point_irradiance = float(irradiance(POINT)[0])
point_exact = float((irradiance(POINT, (1e-6, 0, 0)) - irradiance(POINT, (-1e-6, 0, 0)))[0] / 2e-6)

# A renderer's estimate: 64 fixed points on the lamp (one at random in each cell of an
# 8 x 8 grid: stratified), each seen or hidden.
cell = np.arange(64)
along_x = LAMP_HALF * ((cell % 8 + uniform(1, cell, 0)) / 4 - 1)
along_z = LAMP_HALF * ((cell // 8 + uniform(1, cell, 1)) / 4 - 1)
lamp_points = np.stack([along_x, np.full(64, LAMP_HEIGHT), along_z], axis=1)


def sampled_irradiance(theta: float) -> float:
    """The 64-sample estimate of E at POINT with the occluder moved by theta along x: the
    shadow ray to each lamp point crosses the occluder's plane inside the square or not."""
    to = lamp_points - POINT
    cross = POINT + to * (OCCLUDER_HEIGHT / to[:, 1:2])  # where it passes height 0.5
    hidden = (np.abs(cross[:, 0] - OCCLUDER_CENTRE - theta) < OCCLUDER_HALF) & (
        np.abs(cross[:, 2]) < OCCLUDER_HALF
    )
    geometry = to[:, 1] ** 2 / np.sum(to**2, axis=1) ** 2  # cos θ cos θ' / r² (parallel)
    return float(np.mean(RADIANCE * np.where(hidden, 0, geometry)) * (2 * LAMP_HALF) ** 2)


thetas = np.linspace(-0.05, 0.05, 401)
staircase = np.array([sampled_irradiance(t) for t in thetas])
smooth = np.array([irradiance(POINT, (t, 0, 0))[0] for t in thetas])
staircase_slope = (sampled_irradiance(1e-4) - sampled_irradiance(-1e-4)) / 2e-4
staircase_steps = int(np.count_nonzero(np.diff(staircase)))
print(
    f"E(x) = {point_irradiance:.4f}, dE/dθ = {point_exact:.4f}; the 64-sample estimate's "
    f"slope at θ = 0: {staircase_slope}, its steps over θ in [-0.05, 0.05]: {staircase_steps}"
)

figure = Figure(figsize=(5.6, 3.4), dpi=100, layout="constrained")
FigureCanvasAgg(figure)
ax = figure.add_subplot()
ax.plot(thetas, smooth, "k", label="E(x): Lambert's formula")
ax.plot(thetas, staircase, color="tab:red", lw=1, label="64 fixed lamp samples")
ax.set_xlabel("θ: the occluder's shift along x")
ax.set_ylabel("irradiance at x = (0, 0, 0.1)")
ax.legend(fontsize=9)
save_and_show(figure, OUT / "one_point.png")

# %% [markdown]
# At this point E = `0.4151` <!-- check: point_irradiance --> and dE/dθ = `4.1546`
# <!-- check: point_exact --> (central differences of the closed form with `h = 1e-6`;
# the closed form is smooth in θ here, so that is exact to many digits). `one_point.png`
# sets it against a renderer's estimate with 64 fixed points on the lamp: a staircase,
# `22` <!-- check: staircase_steps --> steps over the plotted range and flat between them.
# Its slope at θ = 0 is `0` <!-- check: staircase_slope -->, and so is every derivative a
# tape takes of it. Each step is one lamp sample whose shadow ray stops being blocked as
# the occluder's edge passes it. On average the steps climb with the smooth curve (their
# number per unit θ times their height is its slope), but no single estimate's derivative
# sees them: they are what the boundary term has to supply.
#
# ## 2. The boundary term from a shading point
#
# **The level set.** Fix `x`. For an edge `(a, b)` of the occluder, the points `x'` on
# the lamp whose segment to `x` grazes the edge are those on the plane through `x`, `a`
# and `b`. So the jump of `V` lies on the zero set of
#
#     φ(x') = (x' − x) · ((a − x) × (b − x)) ,
#
# positive on one side of that plane and negative on the other
# (`render/path/boundary/silhouettes.py`, `level_set`). Write the integrand as
# `F₊ H(φ) + F₋ (1 − H(φ))`, with `H` the step function and `F₊`, `F₋` the integrand on the
# two sides (here `L_e G` on the side the lamp is seen, 0 on the occluder's).
# Differentiating under the integral, `H'(φ) = δ(φ)`, and the delta function turns the area
# integral into one along the curve (lesson 11's Reynolds transport theorem in its
# level-set form):
#
#     dE/dθ = ∫_lamp ∂F/∂θ dA  +  ∫_curve (F₊ − F₋) (∂φ/∂θ) / |∇_S φ| dl .
#
# `∂φ/∂θ` is how fast φ changes at a fixed `x'` when the edge moves, `|∇_S φ|` its
# gradient along the lamp's surface (their ratio is, up to its sign, the speed at which the
# curve crosses `x'`), and `dl` length along the curve on the lamp. The first term is what
# the tape computes, here 0. The second is the whole derivative.
#
# **Which edges.** Only silhouettes seen from `x` make `V` jump: an edge whose two faces
# lie on one side of the plane through `x` and the edge (a border edge always). An edge
# between a face `x` sees and a face it does not see is on the outline; an edge between two
# faces it sees is inside the outline. `render.path.boundary.silhouettes.Curves` lists every
# candidate curve of the scene (mesh edges, spheres' outlines) and, for any *apex* (the
# point the edges are seen from: here the floor point `x`; in the renderer each path
# vertex), the angle each subtends there, 0 where it is no silhouette:

# %%
sampler = PathSampler(placed(shadow_scene()), 1, 2, 100, 0)
curves = Curves.of(sampler)
angles, faces_side = curves.silhouettes(POINT)
is_silhouette = angles[0, : curves.n_edges] > 0
names = ("floor", "occluder", "lamp")
silhouettes_seen = {name: int(np.sum(is_silhouette & (curves.edge_object == o)))
                    for o, name in enumerate(names)}  # fmt: skip
print(f"{curves.n_edges} candidate edges; silhouettes seen from x: {silhouettes_seen}")
occluder_silhouettes = silhouettes_seen["occluder"]
lamp_silhouettes = silhouettes_seen["lamp"]
floor_silhouettes = silhouettes_seen["floor"]
candidate_edges = curves.n_edges

# %% [markdown]
# Each quad is two triangles, so five edges; the diagonal lies inside a flat face and is
# left out, which leaves `Curves` `12` <!-- check: candidate_edges --> candidates here.
# Seen from `x`: the occluder's `4`
# <!-- check: occluder_silhouettes --> border edges are silhouettes; so are the lamp's
# `4` <!-- check: lamp_silhouettes --> (but the lamp's outline needs no term: behind it,
# seen from `x`, there is nothing, and the integral is over the lamp's surface, whose
# points the tape writes as fixed places on it, `docs/path_tracing.md`, "How it
# differentiates"); the floor's `0`
# <!-- check: floor_silhouettes --> are not (`x` lies in their plane: seen edge-on).
#
# **The term by quadrature.** For each occluder edge: project it from `x` onto the lamp's
# plane, keep the part over the lamp, and integrate along it with the midpoint rule.
# `∂φ/∂θ` comes from the tape in forward mode (`md.tangents`, lesson 2): φ recomputed from
# `θ`, as the library recomputes it; the rest are numbers.


# %%
def lamp_part(start, end):
    """The parameters (u0, u1) of the part of the segment start -> end (on the lamp's
    plane) that lies over the lamp (u0 >= u1: none)."""
    u0, u1 = 0.0, 1.0
    for k in (0, 2):
        d = end[k] - start[k]
        if d == 0:
            if abs(start[k]) > LAMP_HALF:
                return 1.0, 0.0
            continue
        lo, hi = sorted(((-LAMP_HALF - start[k]) / d, (LAMP_HALF - start[k]) / d))
        u0, u1 = max(u0, lo), min(u1, hi)
    return u0, u1


def geometry(x, lamp_point):
    """G = cos θ cos θ' / r² between a floor point and points on the lamp (facing)."""
    to = lamp_point - x
    return to[..., 1] ** 2 / np.sum(to**2, axis=-1) ** 2


def edge_term(x, a, b, side: float, direction) -> float:
    """The boundary term at floor point ``x`` of the occluder's edge (a, b) moving along
    ``direction`` (3,): the integral of (F₊ − F₋) ∂φ/∂θ / |∇_S φ| along the edge's shadow
    on the lamp, by the midpoint rule on 2,000 points; ``side``: the side of the plane
    through ``x`` and the edge that the edge's faces lie on (``Curves.silhouettes``)."""
    reach = (LAMP_HEIGHT - x[1]) / (OCCLUDER_HEIGHT - x[1])
    start, end = x + (a - x) * reach, x + (b - x) * reach  # the edge's shadow on the lamp
    u0, u1 = lamp_part(start, end)
    if u0 >= u1:
        return 0.0  # its shadow misses the lamp
    n = 2000
    u = u0 + (u1 - u0) * (np.arange(n) + 0.5) / n
    on_curve = start + u[:, None] * (end - start)
    dl = (u1 - u0) * np.linalg.norm(end - start) / n
    theta = md.tensor(0.0)
    with md.tangents({theta: 1.0}):
        moved_a, moved_b = md.tensor(a) + theta * direction, md.tensor(b) + theta * direction
        normal = md.cross(moved_a - md.tensor(x), moved_b - md.tensor(x))
        phi = md.sum(md.tensor(on_curve - x) * normal, axis=1)
    dphi = phi.tangent  # ∂φ/∂θ at every point of the curve
    grad = np.cross(a - x, b - x)  # ∇φ; along the lamp: drop its y part
    across = np.linalg.norm(grad - grad[1] * Y)
    # F₊ − F₋: F is 0 on the side of the plane where the edge's faces are.
    jump = -side * RADIANCE * geometry(x, on_curve)
    return float(np.sum(jump * dphi / across) * dl)


x = POINT[0]
edge_terms = {
    j: edge_term(x, curves.a[j], curves.b[j], faces_side[0, j], X)
    for j in np.flatnonzero(curves.edge_object == 1)
}
boundary_by_hand = sum(edge_terms.values())
quadrature_error = abs(boundary_by_hand / point_exact - 1)
print("each occluder edge's term:", {int(j): round(t, 6) for j, t in edge_terms.items()})
print(f"boundary term {boundary_by_hand:.8f} against dE/dθ {point_exact:.8f}")
nonzero_edges = sum(t != 0 for t in edge_terms.values())

# %% [markdown]
# The sum of the edges' terms equals the closed form's derivative to a relative
# `1e-6` <!-- check: quadrature_error < -->. Only `1` <!-- check: nonzero_edges --> of the
# four edges contributes: two edges' shadows miss the lamp altogether, and the edge along
# x has its shadow on the lamp but moves *along itself* as the occluder slides in x, so
# `∂φ/∂θ = 0` on it. Only motion across a curve changes what is hidden. (Here the formula
# reduces to what you could write at once: the left edge's shadow sweeps the lamp at speed
# 2, the scale 1 / 0.5, uncovering a strip of `L_e G` per unit length.)
#
# **The estimator.** A renderer cannot integrate along every curve at every shading point;
# `render/path/boundary/secondary.py` takes one sample per path vertex:
#
# 1. pick a silhouette with probability proportional to the angle it subtends at `x`, and a
#    point `m` on it uniformly *in that angle* (`render/path/boundary/silhouettes.py`; uniform along
#    the edge, points near an apex close to the edge would carry weights growing as one over
#    the distance);
# 2. trace the ray from `x` through `m` to the first surface beyond it, `x'` (`_cross`);
# 3. the sample is `(F₊ − F₋) |dx'/dt| / |∇_S φ| / p(curve, t) · ∂φ/∂θ`, where
#    `|dx'/dt|` converts the edge's parameter `t` into length on the surface behind
#    (`x'` is `m` projected from `x` onto the plane of `x'`), and `p` the density of the
#    draw.
#
# Here it is by hand, with `pick_reference` (the NumPy version of the library's draws, the
# one to read; the renderer runs a compiled loop that `tests/render/path/test_secondary.py`
# ties to it):

# %%
N_POINT = 4096


def boundary_samples(seed: int, triangle=None, triangle_probability: float = 1.0):
    """N_POINT one-sample estimates of the boundary term at x: whole curves, or (with
    ``triangle`` (3, 3)) only the parts of the curves whose rays meet that triangle of the
    lamp, the triangle picked with ``triangle_probability``."""
    ids = np.arange(N_POINT)
    towards = None if triangle is None else np.repeat(triangle[None], N_POINT, axis=0)
    index, density, side, t = pick_reference(curves, POINT, uniform(seed, ids, 0),
                                             uniform(seed, ids, 1), towards)  # fmt: skip
    out = np.zeros(N_POINT)
    ok = index >= 0
    index, density, side, t = index[ok], density[ok] * triangle_probability, side[ok], t[ok]
    apex = np.repeat(POINT, len(index), axis=0)
    m, tangent = curves.aim(apex, index, side, t, lift=0.0)[:2]  # the point on it, dm/dt
    w = m - apex
    beyond = apex + w * ((LAMP_HEIGHT - apex[:, 1]) / w[:, 1])[:, None]  # x', lamp's plane
    on_lamp = (w[:, 1] > 0) & np.all(np.abs(beyond[:, [0, 2]]) <= LAMP_HALF, axis=1)
    on_lamp &= curves.edge_object[index] == 1  # rays past the lamp's own edges meet nothing
    lamp_normal = np.broadcast_to(-Y, beyond.shape)
    stretch = np.linalg.norm(beyond - apex, axis=1) / np.linalg.norm(w, axis=1)
    # |dx'/dt|: dm/dt projected from the apex onto the lamp's plane, stretched by |x' - x| / |w|.
    slide = np.sum(tangent * lamp_normal, axis=1) / np.sum(w * lamp_normal, axis=1)
    along = stretch * np.linalg.norm(tangent - slide[:, None] * w, axis=1)
    grad = curves.gradient(apex, index, beyond)  # ∇φ at x'
    across = np.linalg.norm(grad - np.sum(grad * lamp_normal, axis=1)[:, None] * lamp_normal,
                            axis=1)  # fmt: skip
    a, b = curves.a[index], curves.b[index]
    dphi = np.sum((beyond - apex) * (np.cross(X, b - apex) + np.cross(a - apex, X)), axis=1)
    jump = -side * RADIANCE * geometry(apex, beyond)
    out[ok] = np.where(on_lamp, jump * along / across / density * dphi, 0.0)
    return out


whole = boundary_samples(seed=7)
whole_mean, whole_se = whole.mean(), whole.std() / np.sqrt(N_POINT)
whole_useful = float(np.mean(whole != 0))
# The library's second estimator: NEE picks a lamp triangle (by area), and the curves are
# clipped to the parts whose rays meet it.
lamp_triangles = sampler.primitives[0][sampler.emitters.prims]
chosen = (uniform(7, np.arange(N_POINT), 2) >= sampler.emitters.probability[0]).astype(int)
clipped = np.zeros(N_POINT)
for k, triangle in enumerate(lamp_triangles):
    samples = boundary_samples(8 + k, triangle, sampler.emitters.probability[k])
    clipped[chosen == k] = samples[chosen == k]
clipped_mean, clipped_se = clipped.mean(), clipped.std() / np.sqrt(N_POINT)
clipped_useful = float(np.mean(clipped != 0))
variance_ratio = whole.var() / clipped.var()
whole_z = abs(whole_mean - point_exact) / whole_se
clipped_z = abs(clipped_mean - point_exact) / clipped_se
print(
    f"whole curves: {whole_mean:.3f} ± {whole_se:.3f} ({whole_useful:.1%} of samples reach "
    f"the lamp); clipped to the lamp: {clipped_mean:.3f} ± {clipped_se:.3f} "
    f"({clipped_useful:.1%}); variance ratio {variance_ratio:.1f}; exact {point_exact:.3f}"
)

# %% [markdown]
# With `4,096` <!-- check: N_POINT --> samples, whole curves give `4.02`
# <!-- check: whole_mean --> ± `0.18` <!-- check: whole_se --> against the exact 4.155
# (within `1.0` <!-- check: whole_z < --> standard error), but only `0.10`
# <!-- check: whole_useful --> of the samples carry anything. A silhouette is picked by
# the angle it subtends at `x`, and most of that angle looks past the lamp into the dark,
# or along the lamp's own edges, behind which there is nothing. The library therefore
# splits `F` in two (`_terms_at`): the emission of `x'`, estimated on curves *clipped* to
# the parts whose rays meet a lamp triangle that next-event estimation picks, and the rest
# (light reflected at `x'`; zero here, with `max_depth=2`) on whole curves. Clipped, a
# share of `0.615` <!-- check: clipped_useful --> of the samples carry something, the
# estimate is `4.18` <!-- check: clipped_mean --> ± `0.07` <!-- check: clipped_se -->
# (within `1.0` <!-- check: clipped_z < --> standard error), and its variance is `6.7`
# <!-- check: variance_ratio --> times smaller for the same number of rays.
#
# ## What the library computes, on the whole image
#
# `render_path(..., antialias="secondary")` does this for every vertex of every path
# (`add_secondary_term`), with `F` the whole path through `x'` estimated by the path tracer
# (`replay.radiance_of`: the compiled whole path, values only), and for the shadows of
# point lights (the same construction with the light as the apex). Everything in a sample
# but `∂φ/∂θ` is a constant computed off the tape; φ is recomputed from `x`, `x'` and the
# edge's vertices (`level_set` again, compiled per sample: one node on the tape), and the
# sample is the constant times `φ − detach(φ)`: its value is zero, its derivative is the
# term. So the image does not change:

# %%
with md.no_grad():
    plain_image = render_image(shadow_scene(), 16, seed=3).data
moved = shadow_scene()
moved.objects[1].transform.translation.requires_grad = True
with_term_image = render_image(moved, 16, seed=3, antialias="secondary").data
image_change = float(np.abs(with_term_image - plain_image).max())
print(f"largest change of a pixel from adding the term: {image_change}")

# %% [markdown]
# The largest change of any pixel is `0` <!-- check: image_change -->. The derivative does
# change. Forward mode (`md.tangents` on the translation, direction +x) gives the whole
# derivative image in one pass, each seed with 64 samples per pixel; `backward` gives the
# same numbers for one scalar (checked for seed 0 below):

# %%
GRAD_SPP = 64


def derivative_image(seed: int, antialias, spp: int = GRAD_SPP) -> np.ndarray:
    """d(image)/d(occluder's x) (H, W, 3) by forward mode through the path tracer."""
    scene = shadow_scene()
    translation = scene.objects[1].transform.translation
    with md.tangents({translation: X}):
        image = render_image(scene, spp, seed, antialias)
    return np.zeros(image.shape) if image.tangent is None else image.tangent


ours_images = [derivative_image(seed, "secondary") for seed in SEEDS]
ours_per_seed = [float(left_mean(d)) for d in ours_images]
ours = float(np.mean(ours_per_seed))
ours_se = float(np.std(ours_per_seed, ddof=1) / np.sqrt(len(ours_per_seed)))
interior_image = derivative_image(0, False, spp=16)
interior_largest = float(np.abs(interior_image).max())

scene = shadow_scene()
shift = scene.objects[1].transform.translation
shift.requires_grad = True
left_mean(render_image(scene, GRAD_SPP, seed=0, antialias="secondary")).backward()
backward_vs_forward = abs(float(shift.grad[0]) / ours_per_seed[0] - 1)

# The exact derivative image: the closed form at 8 x 8 points in every pixel.
forward_axis, right_axis, up_axis, eye = plain_frame(shadow_scene().camera)
cells = (np.arange(SIZE * 8) + 0.5) / (SIZE * 8)
grid_x, grid_y = np.meshgrid(2 * cells - 1, 1 - 2 * cells)  # image-plane coordinates
directions = camera_directions(np.stack([grid_x.ravel(), grid_y.ravel()], axis=1),
                               right_axis, up_axis, forward_axis)  # fmt: skip
floor_points = eye + directions * (-eye[1] / directions[:, 1:2])


def exact_image(shift_x: float) -> np.ndarray:
    """The expected image (H, W): albedo / π times E, averaged over each pixel."""
    radiance = ALBEDO / np.pi * irradiance(floor_points, (shift_x, 0, 0))
    return radiance.reshape(SIZE, 8, SIZE, 8).mean(axis=(1, 3))


exact_derivative_image = (exact_image(1e-5) - exact_image(-1e-5)) / 2e-5
exact = float(left_mean(exact_derivative_image))
closed_form_vs_render = abs(left_mean(picture) / left_mean(exact_image(0.0)) - 1)

ours_vs_truth = abs(ours / truth - 1)
ours_vs_exact = abs(ours / exact - 1)
ours_vs_exact_percent = 100 * ours_vs_exact
ours_se_percent = 100 * ours_se / exact  # the 4-seed mean's standard error, relative
truth_vs_exact = abs(truth / exact - 1)
truth_vs_exact_percent = 100 * truth_vs_exact
truth_noise = truth_se / truth
# The step's bias alone: the closed form's own central difference with the same h = 0.02,
# no noise in it, against its derivative. What remains of the differences' error is noise.
noiseless_differences = float(left_mean((exact_image(H) - exact_image(-H)) / (2 * H)))
step_bias_percent = 100 * abs(noiseless_differences / exact - 1)
noise_part_percent = 100 * abs(truth - noiseless_differences) / exact
noise_part_in_se = abs(truth - noiseless_differences) / truth_se
print(
    f"d left_mean / d x: samples only {interior_x:.1e}; with the term {ours:.4f} ± "
    f"{ours_se:.4f}; central differences {truth:.4f} ± {truth_se:.4f}; closed form {exact:.4f}"
)
print(
    f"relative: ours vs differences {ours_vs_truth:.2%}, ours vs exact {ours_vs_exact:.2%}, "
    f"differences vs exact {truth_vs_exact:.2%}; backward vs forward {backward_vs_forward:.1e}"
)
print(
    f"ours vs exact {ours_vs_exact_percent:.3f} % (standard error {ours_se_percent:.3f} %); "
    f"differences vs exact {truth_vs_exact_percent:.3f} %: the step's bias "
    f"{step_bias_percent:.3f} % (noiseless differences {noiseless_differences:.5f}), the "
    f"rest {noise_part_percent:.3f} % "
    f"({noise_part_in_se:.2f} standard errors)"
)

# %% [markdown]
# With the boundary term, d left_mean / dx = `0.421` <!-- check: ours --> (four seeds of
# 64 samples per pixel, standard error `0.003` <!-- check: ours_se < -->), against the
# central differences' `0.416`: within `0.03` <!-- check: ours_vs_truth < --> of them
# (relative). `backward` on seed 0 agrees with forward mode to `1e-9`
# <!-- check: backward_vs_forward < -->. The tape alone gives a derivative image whose
# largest pixel is `0` <!-- check: interior_largest --> (exactly: no tangent reaches the
# image).
#
# **How good is the truth?** Central differences have two errors of their own: noise
# (their standard error over the four seeds, `0.01` <!-- check: truth_noise < --> of the
# value) and the step's bias (the penumbra's profile curves over a shift of 2h = 0.04 of
# the occluder, 0.08 of its shadow). This scene allows a third number without either: the
# closed form above at 8 × 8 points in every pixel of the measuring camera (it agrees with
# the 256-sample picture's left half to `0.005` <!-- check: closed_form_vs_render < -->),
# differentiated by central differences with `h = 1e-5`. It gives `0.4208`
# <!-- check: exact -->. The central differences are `1.1`
# <!-- check: truth_vs_exact_percent --> % off it. How much of that is the step? The same
# closed form differenced with their step, `h = 0.02`, has no noise, and differs from the
# exact value by `0.31` <!-- check: step_bias_percent --> %: that is the step's bias. The
# rest, the `0.8` <!-- check: noise_part_percent --> % between the differences and that
# noiseless version of them, is noise: `1.7` <!-- check: noise_part_in_se --> of their
# standard errors, not unusual for a mean of four seeds.
#
# The boundary term's mean over its four seeds is `0.04` <!-- check: ours_vs_exact_percent -->
# % from the exact value, and its standard error is `0.53` <!-- check: ours_se_percent -->
# %: it agrees within its noise, and an error as small as 0.04 % is partly luck (expect
# about a standard error). Even so, with 64 samples per pixel against the differences'
# 2 × 1,024, it is closer to the exact value than the reference it is usually checked
# against, whose error is mostly noise and partly its step.
# This is why the library's checks allow some percent (`tests/render/path/test_secondary.py`
# 10 %, `benchmarks/path_secondary.py` the issue's 5 %) and report the differences' own
# error beside every comparison.

# %%
panels = {
    "tape only (antialias=False)": interior_image[..., 0],
    'with the boundary term\n(antialias="secondary", 4 x 64 spp)': np.mean(ours_images, 0)[..., 0],
    "central differences\n(4 x 1,024 spp, h = 0.02)": np.mean(fd_images, 0)[..., 0],
    "closed form (Lambert)": exact_derivative_image,
}
limit = float(np.abs(exact_derivative_image).max())
figure = Figure(figsize=(9.6, 2.9), dpi=100, layout="constrained")
FigureCanvasAgg(figure)
axes = figure.subplots(1, 4)
for ax, (title, image) in zip(axes, panels.items(), strict=True):
    shown = ax.imshow(image, cmap="RdBu", vmin=-limit, vmax=limit, interpolation="nearest")
    ax.set_title(title, fontsize=9)
    ax.set_axis_off()
figure.colorbar(shown, ax=axes, shrink=0.8, label="d pixel / d occluder x")
save_and_show(figure, OUT / "gradient_images.png")

# %% [markdown]
# `gradient_images.png`: each pixel's derivative with respect to the occluder's x
# (blue: brighter as the occluder moves to +x). The tape alone sees nothing. With the term,
# the left penumbra brightens and the right one darkens, as the closed form says; the
# central differences show the same from 32 times the samples (two renders of 1,024
# samples per seed against one of 64). The core of the shadow, which sees almost none of
# the lamp, and the floor far out, which sees all of it, hardly change.
#
# ## 3. The method and its alternatives
#
# All the methods below estimate the same derivative; they differ in how they find the
# discontinuities and what they pay for it.
#
# * **Edge sampling from shading points** (Li, Aittala, Durand, Lehtinen 2018,
#   "Differentiable Monte Carlo ray tracing through edge sampling"; redner): what this
#   lesson did. At each shading point, sample a point on a silhouette seen from it and
#   evaluate the two sides. Unbiased, and the boundary is explicit. Its cost is *finding*
#   silhouettes: for every vertex the edges that are silhouettes from there (redner builds a
#   hierarchy over edges for it).
# * **Reparameterisation** (Loubet, Holzschuch, Jakob 2019) and **warped-area sampling**
#   (Bangaru, Li, Durand 2020): move the samples with the discontinuities, so that in the
#   new coordinates nothing jumps where the parameter moves it and the derivative of the
#   samples is the whole derivative. Nothing to find; the cost moves into the warp: Loubet's
#   is built from a few extra rays per sample and is only approximately aligned with the
#   edges (biased); warped-area sampling is unbiased but needs many extra rays per sample
#   for its weights.
# * **Path-space differentiable rendering** (Zhang, Miller, Yan, Gkioulekas, Zhao 2020):
#   the same boundary term written for whole paths in area measure, its boundary paths
#   built from a point on an edge outwards in both directions, so that they need not come
#   from a shading point at all. General (every discontinuity of every segment); its cost
#   is the construction of those paths, and sampling the boundary segments where they
#   matter took further work (Yan, Lassner, Budge, Dong, Zhao 2022, guiding).
# * **Projective sampling** (Zhang, Roussel, Jakob 2023; Mitsuba 3's `prb_projective`):
#   start from an ordinary sample of the integrand and project it onto a nearby boundary,
#   with guiding structures to find the boundaries that matter: no loop over edges.
#
# The library's choice is edge sampling from shading points, written in area measure as in
# path-space differentiable rendering. `docs/path_tracing.md` ("Why edge sampling, and not
# the alternatives") gives its reasons: edge sampling is "unbiased, and the boundary is
# explicit, so a student can see which edge moved which pixel"; its cost is finding
# silhouettes, and where redner builds a 6D hierarchy of edges "we loop over all curves per
# vertex in Numba, which is fine for the scenes here (tens to hundreds of edges after the
# flat and touching ones are removed) and is the first thing to replace for meshes with
# thousands of silhouette edges". Written in area measure, "the same term covers soft
# shadows, indirect occlusion and point lights' shadows, and matches the coordinates our
# tape already uses" (every vertex after the camera's is a fixed place on its surface).
# Projective sampling is "better at scale (no per-vertex loop over edges), but the
# projection and its guiding are much more machinery to read, and it estimates the same
# term". Of reparameterisation: "no silhouettes to find, but Loubet's is biased ... and
# warped-area sampling needs many extra rays per sample for its weights; their variance is
# harder to reason about than an explicit boundary sample". The same page measures the
# price: on the Cornell box the term costs 2.2 to 2.5 times the gradient without it, and
# every derivative it checks against central differences agrees within 2 %. Against
# Mitsuba 3's projective integrator on that box it reports the sphere's derivative in
# agreement and the light's position 3.7 combined errors apart (Mitsuba's high, its own
# central differences agreeing with ours), "why it is high is not established".

# %%
print(f"elapsed {time.perf_counter() - lesson_start:.1f} s; figures in {OUT}")

# %% [markdown]
# ## Exercises
#
# 1. **The occluder's height, by hand.** At the floor point `x = (0, 0, 0.1)`, compute
#    `dE/dθ` for θ the occluder's height (its translation along y) with the boundary
#    integral over the occluder's edges (now `∂a/∂θ = ∂b/∂θ = (0, 1, 0)`) and compare it
#    with central differences of `irradiance`. Which edges contribute now, and why does
#    the sign make sense?
# 2. **A sphere for the square.** Replace the square by a `render.Sphere` of radius 0.15
#    centred at (0.1, 0.6, 0) (at height 0.5 it would hold the camera). What does
#    `Curves` list for it, and what angle does it subtend at `x`? Compare
#    `d left_mean / d(sphere's x)` from the samples alone, with the boundary term and by
#    central differences. Then count the silhouette edges of a box
#    (`render.scene.cornell.box_mesh`) seen from a floor point under it and from one off to
#    the side.
# 3. **The lamp moves.** Differentiate `left_mean` with respect to the lamp's x (give the
#    lamp a `Transform`). Now the samples' derivative is not zero: what does it capture,
#    and what share of the truth (the closed form, adapted) is it? What does the boundary
#    term add?
#
# Solutions: `lessons/solutions/15_secondary_visibility.py`.
