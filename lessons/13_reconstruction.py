# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # Lesson 13 — Reconstruction: rotations, basins, and shapes that stay surfaces
#
# Lessons 7 and 8 recovered a light, an albedo and a camera: a few numbers, started close
# to the truth. Reconstructing *geometry* — where an object is, how it is turned, what
# shape it has — meets three problems those did not:
#
# 1. **A rotation is not a vector.** Three numbers must describe it, and some ways of
#    choosing them break down at particular rotations, where gradient steps crawl.
# 2. **The basin.** An image loss is only bowl-shaped near the answer. Started farther
#    away, gradient descent settles in another valley; how wide the right valley is, and
#    how to start inside it, decides whether a fit works at all.
# 3. **A mesh has many more vertices than the images pin down.** Moved one by one by their
#    own gradients, vertices fold the surface over itself ("crumpling"); a regulariser
#    must choose among the shapes the images cannot tell apart.
#
# Each section measures one of them with the library's real code
# (`render.Transform`, `render.inverse.basin`, `render.inverse.shape`,
# `render.inverse.reconstruction`).

# %%
import time

import numpy as np
from course import figures_folder, save_and_show
from scipy.spatial.transform import Rotation

import minidiff as md
import render
from render.inverse.basin import downsample, resized
from render.inverse.optimize import optimize
from render.inverse.plot import line_figure
from render.inverse.reconstruction import (
    DENT_CENTRES,
    dented_blob,
    rotation_error_degrees,
    run_shape,
    shape_scene,
    view_cameras,
)
from render.scene.placement import rotation_matrix
from render.scene.teapot import paper_scene

# This lesson's figures go to out/lessons/13_reconstruction/ (or under $LESSONS_OUT).
OUT = figures_folder("13_reconstruction")
lesson_start = time.perf_counter()

# %% [markdown]
# ## 1. Three ways to write a rotation
#
# **Euler angles** compose three turns about fixed axes: here yaw `a` about z, then pitch
# `b` about y, then roll `c` about x, `R = R_z(a) R_y(b) R_x(c)`. A small change of the
# angles turns the object by the angular velocity
#
#     ω = ȧ e_z + ḃ R_z(a) e_y + ċ R_z(a) R_y(b) e_x = J(a, b) (ȧ, ḃ, ċ) .
#
# At pitch `b = 90°` the first and last columns of `J` are the same axis (`R_z R_y e_x =
# −e_z`): yaw and roll turn the object the same way, and one direction of turning has no
# angle left to produce it. That is **gimbal lock**. Near it, the smallest singular value
# of `J` — how much the best-placed unit change of the angles can still turn the object
# in its weakest direction — goes to zero, and a gradient step in the angles barely moves
# the rotation in that direction.


# %%
def euler_jacobian(yaw: float, pitch: float) -> np.ndarray:
    """J (3, 3): the angular velocity of R_z(yaw) R_y(pitch) R_x(roll) per unit rate of
    (yaw, pitch, roll), angles in radians (J does not depend on the roll)."""
    rz = Rotation.from_euler("Z", yaw).as_matrix()
    ry = Rotation.from_euler("Y", pitch).as_matrix()
    return np.stack([[0.0, 0.0, 1.0], rz @ [0.0, 1.0, 0.0], rz @ ry @ [1.0, 0.0, 0.0]], axis=1)


pitches = np.arange(0.0, 90.5, 1.0)
weakest = [
    np.linalg.svd(euler_jacobian(0.7, np.radians(p)), compute_uv=False).min() for p in pitches
]
weakest_at_45, weakest_at_85 = weakest[45], weakest[85]
weakest_at_90 = weakest[90]
figure = line_figure({"smallest singular value of J": (pitches, weakest)},
                     title="Euler angles: how well every direction can still be turned",
                     xlabel="pitch (degrees)", ylabel="smallest singular value")  # fmt: skip
save_and_show(figure, OUT / "gimbal_lock.png")
print(f"smallest singular value: {weakest_at_45:.4f} at 45°, {weakest_at_85:.4f} at 85°, "
      f"{weakest_at_90:.1e} at 90°")  # fmt: skip

# %% [markdown]
# The smallest singular value falls from 1 at pitch 0 to `0.5412`
# <!-- check: weakest_at_45 --> at 45°, `0.0617` <!-- check: weakest_at_85 --> at 85°
# and to rounding error, `1e-15` <!-- check: weakest_at_90 < --> or less, at 90°
# (`gimbal_lock.png`; it is `√2 sin((90° − b)/2)`).
#
# The renderer's `render.Transform` takes the two other common choices:
#
# * a **rotation vector** `r` (axis times angle, in degrees), turned into a matrix by
#   Rodrigues' formula (`render/scene/placement.py`); its differential is the identity at
#   `r = 0` and singular only at 360°, so near the identity every direction turns alike;
# * a **unit quaternion** `q = (w, x, y, z)`, four numbers for three degrees of freedom.
#   The renderer uses `q / |q|`, so the loss does not change along `q` itself: the
#   gradient is perpendicular to `q`, and a plain gradient step (along the gradient)
#   changes `|q|` only to second order. Adam does not step along the gradient: it divides
#   each coordinate by its own running scale, so its step has a part along `q` and `|q|`
#   drifts (measured below).
#
# How much this matters for a fit: take a target rotation at pitch 85°, start 30° away
# from it about random axes, and minimise the squared difference of the matrices,
# `L = Σ (R(p) − R*)²`, with Adam (the same step size, 0.02, in radians or quaternion
# units) until the fit is within 0.1° of the target.


# %%
def euler_matrix(angles: md.Tensor) -> md.Tensor:
    """R_z(a) R_y(b) R_x(c) (3, 3) on the tape, angles (a, b, c) in radians."""
    a, b, c = angles[0], angles[1], angles[2]
    ca, sa, cb, sb, cc, sc = md.cos(a), md.sin(a), md.cos(b), md.sin(b), md.cos(c), md.sin(c)
    return md.stack([
        md.stack([ca * cb, ca * sb * sc - sa * cc, ca * sb * cc + sa * sc]),
        md.stack([sa * cb, sa * sb * sc + ca * cc, sa * sb * cc - ca * sc]),
        md.stack([-sb, cb * sc, cb * cc]),
    ])  # fmt: skip


def as_parameters(kind: str, matrix: np.ndarray) -> np.ndarray:
    """The rotation ``matrix`` written as Euler angles (radians), a rotation vector
    (radians) or a quaternion (w, x, y, z)."""
    r = Rotation.from_matrix(matrix)
    if kind == "Euler angles":
        return r.as_euler("ZYX")
    if kind == "rotation vector":
        return r.as_rotvec()
    x, y, z, w = r.as_quat()
    return np.array([w, x, y, z])


def matrix_of(kind: str, p: md.Tensor) -> md.Tensor:
    """The (3, 3) rotation of parameters ``p`` of that kind, on the tape."""
    if kind == "Euler angles":
        return euler_matrix(p)
    if kind == "rotation vector":
        return rotation_matrix(p * (180.0 / np.pi))  # render.Transform's, in degrees
    return rotation_matrix(p)  # a quaternion (w, x, y, z), normalised inside


def steps_to_fit(kind: str, target: np.ndarray, start: np.ndarray, cap: int = 1000):
    """Adam steps (lr 0.02) until R(p) is within 0.1 degrees of ``target`` (``cap`` if
    never); for a quaternion also the largest |cos| between the gradient and q, the
    change of |q| per unit of step length at each step, and |q| at the end."""
    p = md.tensor(as_parameters(kind, start), requires_grad=True)
    optimizer = md.optim.Adam([p], lr=0.02)
    along, drift = 0.0, []
    for step in range(cap):
        optimizer.zero_grad()
        m = matrix_of(kind, p)
        md.sum((m - target) ** 2).backward()
        # The angle of the rotation R R*^T between the two: its trace is 1 + 2 cos(angle).
        cosine = np.clip((np.trace(m.data @ target.T) - 1.0) / 2.0, -1.0, 1.0)
        if np.degrees(np.arccos(cosine)) < 0.1:
            return step, along, drift, np.linalg.norm(p.data)
        before = p.data.copy()
        if kind == "quaternion":
            g = p.grad
            along = max(along, abs(g @ p.data) / (np.linalg.norm(g) * np.linalg.norm(p.data)))
        optimizer.step()
        length = np.linalg.norm(p.data - before)
        if length > 0:
            drift.append(abs(np.linalg.norm(p.data) - np.linalg.norm(before)) / length)
    return cap, along, drift, np.linalg.norm(p.data)


target_rotation = Rotation.from_euler("ZYX", np.radians([40.0, 85.0, 10.0])).as_matrix()
kinds = ("Euler angles", "rotation vector", "quaternion")


def fit_from_random_starts(seed: int) -> tuple[dict, float, list, list]:
    """Steps to fit from three starts 30 degrees away about random axes (``seed``), per
    kind; and the quaternion's largest |cos(gradient, q)|, |q|'s change per unit step
    and its final |q| (``steps_to_fit``)."""
    steps = {kind: [] for kind in kinds}
    largest, drifts, norms = 0.0, [], []
    for axis in np.random.default_rng(seed).normal(size=(3, 3)):
        turn = Rotation.from_rotvec(np.radians(30.0) * axis / np.linalg.norm(axis)).as_matrix()
        for kind in kinds:
            n, along, drift, norm = steps_to_fit(kind, target_rotation, turn @ target_rotation)
            steps[kind].append(n)
            if kind == "quaternion":
                largest, drifts, norms = max(largest, along), drifts + drift, norms + [norm]
    return steps, largest, drifts, norms


steps, largest_cosine, q_drift, q_norms = fit_from_random_starts(13)
euler_steps = int(np.median(steps["Euler angles"]))
rotvec_steps = int(np.median(steps["rotation vector"]))
quaternion_steps = int(np.median(steps["quaternion"]))
# Four more sets of three starts: how much slower Euler angles are varies with the starts.
runs = [steps] + [fit_from_random_starts(seed)[0] for seed in (14, 15, 16, 17)]
n_starts = 3 * len(runs)
euler_capped = sum(n >= 1000 for run in runs for n in run["Euler angles"])
medians = [(np.median(run["Euler angles"]), np.median(run["rotation vector"])) for run in runs]
slowdowns = [euler / rotvec for euler, rotvec in medians if euler < 1000]
slowdown_low, slowdown_high = min(slowdowns), max(slowdowns)
rotvec_most = max(n for run in runs for n in run["rotation vector"])
drift_median = float(np.median(q_drift))
q_norm_farthest = float(max(q_norms, key=lambda n: abs(n - 1.0)))
for kind in kinds:
    print(f"{kind:16s} steps to 0.1°: {[n for run in runs for n in run[kind]]}")
print(f"largest |cos(gradient, q)|: {largest_cosine:.1e}")
print(f"Adam on q: median |d|q|| / |step| {drift_median:.3f}, final |q| {q_norms}")

# %% [markdown]
# Median over three starts: the rotation vector needs `68` <!-- check: rotvec_steps -->
# steps, the quaternion `85` <!-- check: quaternion_steps -->, Euler angles `670`
# <!-- check: euler_steps --> — from the same starts, because near pitch 85° one
# direction of turning needs large, slow changes of two angles that nearly cancel. How
# many times slower depends on the starts. Over `15` <!-- check: n_starts --> starts (five
# sets of three random axes) the rotation vector always fitted within `109`
# <!-- check: rotvec_most --> steps, while Euler angles had not fitted after 1,000 steps
# from `4` <!-- check: euler_capped --> of them; in the sets whose median Euler fit
# finished, the medians were `5.8` <!-- check: slowdown_low --> to `9.9`
# <!-- check: slowdown_high --> times the rotation vector's.
#
# The quaternion's gradient was perpendicular to `q` throughout: the largest |cosine|
# between them was below `1e-15` <!-- check: largest_cosine < -->. Its steps were not:
# per unit of step length, `|q|` changed by `0.27` <!-- check: drift_median --> (median over
# the steps of the first three fits), far from second order, and one fit ended at `|q|` = `1.25`
# <!-- check: q_norm_farthest -->. The fit does not care (the renderer divides by `|q|`),
# but a quaternion optimised with Adam is no longer a unit quaternion: normalise it before
# you use it elsewhere.
#
# So: a rotation vector about a pivot (what `render.Transform` takes, and what
# `render.inverse.reconstruction.run_pose` fits) when the rotation to find is moderate; a
# quaternion when it can be anything; Euler angles only when the pitch stays far from 90°.
#
# ## 2. The basin of a pose
#
# The teapot of the paper's scene, turned about the vertical axis through its centre by
# an angle `θ`; the target is `θ = 0`. The image loss of every `θ` in 5° steps (64 × 64,
# 16 samples per pixel so that each render is close to the box-filtered image the
# gradients describe):

# %%
S = 64
pose_scene = paper_scene(S, S)
teapot = pose_scene.objects[0]
teapot.transform = render.Transform(pivot=teapot.vertices.data.mean(axis=0))
pose_target = render.render(pose_scene, spp=16).data.copy()


def turned(theta: float, scene=pose_scene, spp: int = 16) -> np.ndarray:
    """The image with the teapot turned by ``theta`` degrees about the vertical."""
    teapot.transform.rotation = md.tensor([0.0, float(theta), 0.0])
    with md.no_grad():
        return render.render(scene, spp=spp).data.copy()


def blur(image: np.ndarray, sigma: float) -> np.ndarray:
    """A Gaussian blur of an (H, W, 3) image (a separable kernel, edges clamped)."""
    radius = int(3 * sigma)
    k = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma) ** 2)
    k /= k.sum()
    padded = np.pad(image, ((radius, radius), (radius, radius), (0, 0)), mode="edge")
    rows = sum(w * padded[i : i + image.shape[0]] for i, w in enumerate(k))
    return sum(w * rows[:, i : i + image.shape[1]] for i, w in enumerate(k))


def basin(losses: np.ndarray, angles: np.ndarray) -> tuple[float, float]:
    """The interval of angles around 0 over which the loss only falls towards 0."""
    i = j = int(np.argmin(np.abs(angles)))
    while j + 1 < len(losses) and losses[j + 1] > losses[j]:
        j += 1
    while i > 0 and losses[i - 1] > losses[i]:
        i -= 1
    return float(angles[i]), float(angles[j])


angles = np.arange(-180.0, 180.1, 5.0)
images = [turned(a) for a in angles]
landscapes = {
    "64 x 64": lambda image: image,
    "blurred (sigma 4 px)": lambda image: blur(image, 4.0),
    "16 x 16 block means": lambda image: downsample(image, 4),
}
curves, basins, minima = {}, {}, {}
for name, prepare in landscapes.items():
    reference = prepare(pose_target)
    losses = np.array([np.mean((prepare(image) - reference) ** 2) for image in images])
    curves[name] = (angles, losses / losses.max())
    basins[name] = basin(losses, angles)
    lower = (losses[1:-1] < losses[:-2]) & (losses[1:-1] < losses[2:])  # a local minimum
    minima[name] = int(np.sum(lower & (angles[1:-1] != 0.0)))  # other than the answer's
basin_low, basin_high = basins["64 x 64"]
blurred_low, blurred_high = basins["blurred (sigma 4 px)"]
minima_full, minima_coarse = minima["64 x 64"], minima["16 x 16 block means"]
figure = line_figure(curves, title="Image loss against the teapot's turn (target: 0)",
                     xlabel="turn about the vertical (degrees)",
                     ylabel="loss / its largest value")  # fmt: skip
save_and_show(figure, OUT / "basin.png")
for name in landscapes:
    print(f"{name:22s} basin {basins[name]}, {minima[name]} other local minima")

# %% [markdown]
# At 64 × 64 the loss falls all the way to the answer only from turns between
# `-60` <!-- check: basin_low --> and `55` <!-- check: basin_high --> degrees
# (`basin.png`); outside, it has `6` <!-- check: minima_full --> other local minima (the
# spout and handle trade places near ±180°; from the side, a quarter turn shows a
# similar outline). Two common ways to widen the basin:
#
# * **Blur** (or coarse-to-fine): compare blurred images, so that a teapot in the wrong
#   pose still overlaps the target's blurred one. Here it widens the basin on one side
#   and narrows it a little on the other, to `-55` <!-- check: blurred_low --> … `75`
#   <!-- check: blurred_high --> degrees: blur helps, but not by much.
# * **Coarser images** are not the same thing: the 16 × 16 block means have `10`
#   <!-- check: minima_coarse --> other local minima, more than the full image — with fewer
#   pixels, each one's flips between teapot and background dominate the loss. (This is
#   why `render.inverse.basin.greedy_search`'s default compares 64-pixel images, and its
#   `pool` option blurs.)
#
# Now gradients, with the boundary integral of lesson 11 (`antialias="boundary"`) so
# that the silhouettes' motion is in them. The rotation vector (three numbers, degrees)
# is the parameter, Adam's step is 2° per iteration.

# %%
P = 40
fit_scene = resized(pose_scene, P, P)
teapot.transform.rotation = md.tensor([0.0, 0.0, 0.0])
fit_target = render.render(fit_scene, spp=16).data.copy()


def descend(start, iters: int = 50) -> tuple[float, float]:
    """Adam on the rotation vector from ``start`` (degrees); returns the rotation error
    (degrees) at the end and the seconds it took."""
    rotation = md.tensor(np.asarray(start, dtype=float), requires_grad=True)
    teapot.transform.rotation = rotation
    begin = time.perf_counter()
    optimize(fit_scene, [rotation], fit_target, lr=2.0, max_iters=iters, quiet=True,
             render_kwargs={"antialias": "boundary"})  # fmt: skip
    return rotation_error_degrees(rotation.data), time.perf_counter() - begin


near_error, near_seconds = descend([15.0, 25.0, 10.0])
far_error, far_seconds = descend([0.0, 120.0, 0.0], iters=30)
print(f"from 30° about a tilted axis: {near_error:.2f}° off after 50 steps ({near_seconds:.1f} s)")
print(f"from 120° about the vertical: {far_error:.1f}° off after 30 steps ({far_seconds:.1f} s)")

# %% [markdown]
# Started 30° away (about a tilted axis), the fit ends within `3` <!-- check: near_error < -->
# degrees of the truth after 50 steps (40 × 40 pixels); started 120° away it stays more
# than `100` <!-- check: far_error > --> degrees off, in the local minimum the landscape
# showed. Gradients cannot cross a ridge. (The last digits of such runs are chaotic: a
# change in the last bits of the renderer's arithmetic, another processor or another
# version of the edge code, moves them by tenths of a degree here: 1.4-1.9° and
# 117-121° were measured on the way; the printout above says what this run gave.)
#
# **Search** can: before any gradient, try the candidates the landscape suggests and
# start from the best. About one axis a grid of 24 turns, compared at 16 × 16 (4 samples
# per pixel), costs 24 tiny renders:

# %%
small_scene = resized(pose_scene, 16, 16)
teapot.transform.rotation = md.tensor([0.0, 0.0, 0.0])
small_target = render.render(small_scene, spp=4).data.copy()
begin = time.perf_counter()
grid = np.arange(-180.0, 180.0, 15.0)
grid_losses = [np.mean((turned(a, small_scene, spp=4) - small_target) ** 2) for a in grid]
search_best = float(grid[int(np.argmin(grid_losses))])
search_seconds = time.perf_counter() - begin
searched_error, _ = descend([0.0, search_best, 0.0], iters=20)
print(f"search: best of {len(grid)} turns is {search_best:.0f}° ({search_seconds:.2f} s); "
      f"20 steps from there end {searched_error:.2f}° off")  # fmt: skip

# %% [markdown]
# The grid's best turn is `0` <!-- check: search_best --> degrees, and twenty gradient
# steps from there end within `3` <!-- check: searched_error < --> degrees of the truth
# (Adam's 2° steps keep circling the minimum, which at one sample per pixel against a
# 16-sample target is not exactly the truth; fewer or smaller steps settle closer). In three
# dimensions a grid is 24³ renders; `render.inverse.basin.greedy_search` draws random
# proposals around the best so far instead (`reconstruction.pose_proposal`: early on a
# uniformly random rotation half the time, later small turns), and `run_pose` with a
# `search` races the start and the search's best before committing. By default
# `run_pose` does something cheaper that works better from 30-45°: a multi-start stage
# (`basin.multi_start`) runs the start and six copies turned 30° about ±x, ±y, ±z for 40
# low-resolution iterations each and goes on from the lowest loss. The reconstruction
# experiments (`examples/pose_estimation.py`, docs/reconstruction/) measure how far each
# widens the basin for random axes.
#
# ## 3. Shape from views: crumpling, a Laplacian, Large Steps
#
# Now the shape itself: a blob with three dents (`reconstruction.dented_blob`) seen by 4
# cameras at 24 × 24 under four coloured lights (`shape_scene`), fitted from an icosphere
# of 162 vertices whose positions are the parameters. Three ways to take a step, each 30
# iterations at the same step size (0.1):
#
# * **none**: Adam on each vertex's own gradient;
# * **Laplacian**: the same, with `10⁻³ · ‖L v‖²` (mean over the vertices) added to the
#   loss (`shape.laplacian_loss`). `L = D − A` is the mesh's graph Laplacian
#   (`shape.mesh_laplacian`: `A` the adjacency, `D` the degrees): row i of `L v` is
#   `deg(i) · (v_i − mean of its neighbours)`, and an icosphere's degrees are 5 and 6, so
#   `‖L v‖²` is about 36 times the sum of squared "vertex minus the mean of its neighbours",
#   and a weight or a λ written for that normalised Laplacian is about 36 (weight) or 6 (λ)
#   times the one here;
# * **Large Steps** (Nicolet et al. 2021, `shape.LargeStepsAdam`, λ = 4): optimise
#   `u = M v`, `M = I + λL`, instead of `v`. Since `v = M⁻¹ u` and `M` is symmetric, the
#   gradient with respect to `u` is `M⁻¹ g` (`g` the vertices' gradient), and a plain
#   gradient step `Δu = −η M⁻¹ g` moves the vertices by `Δv = M⁻¹ Δu = −η (I + λL)⁻² g`:
#   the gradient filtered twice by a low-pass filter on the mesh. That is the paper's
#   argument: `(I + λL)⁻²` damps the gradient's rough (high-frequency) components, which
#   make a mesh crumple, much as a second-order step would whose Hessian is `(I + λL)²`,
#   so each step is smooth however large. It needs Adam with one second-moment scale for
#   all of `u` (`md.optim.Adam(uniform=True)`, which `LargeStepsAdam` uses): Adam's usual
#   per-coordinate scale would rescale each vertex's step on its own and undo the
#   filtering.
#
# A surface that crumples folds over itself: on this star-shaped blob every face should
# face outwards, so the faces whose normal points towards the centre count the folds.
# The edges are pixel pairs (`antialias="pairs"`): on a crumpled mesh the boundary
# integral's pieces multiply (many short silhouettes in each pixel) and so does its cost.


# %%
def folded_faces(vertices: np.ndarray, faces: np.ndarray) -> int:
    """Faces whose normal points towards the mesh's centre (a star-shaped surface has
    none: each one is a fold)."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    outward = (a + b + c) / 3.0 - vertices.mean(axis=0)
    return int(np.sum(np.einsum("ij,ij->i", np.cross(b - a, c - a), outward) < 0))


blob = dented_blob(3)
shape_runs = {
    method: run_shape(blob, views=4, size=24, iters=30, method=method, start_subdivisions=2,
                      lr=0.1, antialias="pairs", held_out=1, batch=4, samples=5000)
    for method in ("none", "laplacian", "large_steps")
}  # fmt: skip


def dent_depth(vertices: np.ndarray) -> float:
    """How deep the three dents are, averaged: per dent centre c_k
    (``reconstruction.DENT_CENTRES``), the mean radius of the vertices 35 to 50 degrees
    from c_k (the rim around the dent) minus the radius of the vertex nearest to c_k."""
    radius = np.linalg.norm(vertices, axis=1)
    directions = vertices / radius[:, None]
    depths = []
    for c in DENT_CENTRES:
        cos = directions @ c
        rim = (cos < np.cos(np.radians(35.0))) & (cos > np.cos(np.radians(50.0)))
        depths.append(radius[rim].mean() - radius[np.argmax(cos)])
    return float(np.mean(depths))


folds = {m: folded_faces(*r["mesh"]) for m, r in shape_runs.items()}
dent_target = dent_depth(blob[0])
dents = {m: 100.0 * dent_depth(r["mesh"][0]) / dent_target for m, r in shape_runs.items()}
dents_laplacian, dents_large = dents["laplacian"], dents["large_steps"]
chamfer = {m: r["chamfer_percent"] for m, r in shape_runs.items()}
folds_none, folds_laplacian, folds_large = folds["none"], folds["laplacian"], folds["large_steps"]
chamfer_none, chamfer_laplacian = chamfer["none"], chamfer["laplacian"]
chamfer_large = chamfer["large_steps"]
n_faces = len(shape_runs["none"]["mesh"][1])
for method, run in shape_runs.items():
    print(f"{method:12s} Chamfer {run['chamfer_percent']:.2f} %, "
          f"{folds[method]} of {n_faces} faces folded, dents {dents[method]:.0f} % deep, "
          f"{run['seconds']:.1f} s")  # fmt: skip

# A held-out view of the target and of each result, larger than the fitting views.
show_camera = view_cameras(5, 96, seed=1)[4]
with md.no_grad():
    pictures = [render.render(shape_scene(*blob).with_camera(show_camera)).data]
    pictures += [render.render(shape_scene(*r["mesh"]).with_camera(show_camera)).data
                 for r in shape_runs.values()]  # fmt: skip
render.save_image(np.clip(np.concatenate(pictures, axis=1), 0, 1), OUT / "shapes.png", srgb=True)

# %% [markdown]
# | step | folded faces (of `320` <!-- check: n_faces -->) | Chamfer distance (% of the size) |
# |---|---|---|
# | none | `109` <!-- check: folds_none --> | `2.6` <!-- check: chamfer_none --> |
# | Laplacian | `11` <!-- check: folds_laplacian --> | `1.32` <!-- check: chamfer_laplacian --> |
# | Large Steps | `0` <!-- check: folds_large --> | `0.60` <!-- check: chamfer_large --> |
#
# (`shapes.png`: the target, then the three results, from a view none of the fits saw.)
# The dents' depth (`dent_depth` above: the rim's radius minus the centre's, averaged over
# the three dents) as a share of the target's: the Laplacian fit `80.4`
# <!-- check: dents_laplacian --> %, the Large Steps fit `34.3` <!-- check: dents_large --> %.
# Without a regulariser a third of the surface is folded: each vertex followed its own
# pixels' gradient, and neighbouring vertices, pulled by different pixels, crossed. The
# Laplacian penalty, at this small weight, holds most neighbours together (a few folds
# remain, and the surface is rough) and leaves the image free to carve the dents: most of
# their depth is there, and the dent in `shapes.png` shows. A larger weight would hold the
# surface smoother and the dents shallower; the weight trades one against the other.
# Large Steps smooths the *steps*, not the shape: no fold, and the closest surface overall,
# but after 30 steps it has carved only about a third of the dents' depth, and its dent
# in `shapes.png` is hardly visible. A dent is a rough (high-frequency) feature, exactly
# what `(I + λL)⁻²` damps, so it comes last; more iterations, or a smaller λ (exercise
# 3), deepen it. Neither method is "the" answer: read the figure and the numbers together.
#
# ## What to take away
#
# * Parameterise rotations with a rotation vector or a quaternion; Euler angles have a
#   pitch where gradient steps crawl.
# * A pose fit works only inside its basin; blur widens it a little, a coarse search
#   over the ridges a lot, and the search's cost is renders you can count.
# * A mesh fitted to images needs its steps (or its shape) smoothed; Large Steps lets
#   steps stay large without crumpling, at the price of fine detail coming last.
#
# ## Exercises
#
# 1. Gimbal lock elsewhere: compose the turns in the order x, then y, then z (`R = R_x(a)
#    R_y(b) R_z(c)`), write its `J` and find the pitch at which its smallest singular
#    value is zero.
# 2. The blurred loss as the loss of the descent: fit from 70° about the vertical,
#    comparing images blurred by σ = 4 px for 30 steps, then the plain images for 20 (a
#    coarse-to-fine schedule by blur). Does it reach the answer that plain gradients from
#    70° miss? (Blur the rendered image on the tape with a convolution written as sums of
#    shifted slices, as `blur` above does.)
# 3. Large Steps' λ: run the shape fit with λ = 1 and λ = 20 (`run_shape(..., lam=...)`)
#    and compare the Chamfer distance and the dents (the Hausdorff distance,
#    `hausdorff_percent`). What does a larger λ cost?

# %%
lesson_seconds = time.perf_counter() - lesson_start
print(f"lesson ran in {lesson_seconds:.1f} s")
