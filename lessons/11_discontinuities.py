# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # Lesson 11 — Discontinuities: the theory of edges, checked against the truth
#
# Lesson 8 showed *that* a moving edge has no gradient in a plain renderer and measured the
# renderer's two edge methods against supersampled images. This lesson is the theory
# underneath, small enough to do by hand: why differentiating samples misses the edge,
# the term that is missing (Leibniz's rule in 1-D, Reynolds' transport theorem in 2-D),
# a toy edge term for a square in a pixel grid, and then how the field computes that term
# for real scenes.

# %%
import time

import numpy as np
from course import figures_folder, save_and_show
from matplotlib.figure import Figure

import minidiff as md
import render
from render.inverse import experiments

# This lesson's figures go to out/lessons/11_discontinuities/ (or under $LESSONS_OUT).
OUT = figures_folder("11_discontinuities")
lesson_start = time.perf_counter()

# %% [markdown]
# ## In one dimension: a step that moves
#
# Take `f(x) = 1 + x²` on `[0, 1]` and hide the part left of `t`:
#
#     I(t) = ∫₀¹ f(x) H(x − t) dx = ∫ₜ¹ f(x) dx ,       H the step function.
#
# By the fundamental theorem of calculus `dI/dt = −f(t)`: moving the step right by `dt`
# hides a sliver of width `dt` and height `f(t)`. At `t = 0.3`: `-1.09`
# <!-- check: exact_derivative -->.
#
# A renderer estimates `I` from samples: `I_N(t) = (1/N) Σ f(xᵢ) H(xᵢ − t)` at fixed
# points `xᵢ`. Differentiate *that* with respect to `t` and every term is zero (`H` is flat
# away from its jump, and the jump sits exactly on a sample with probability zero). The
# samples' derivative is zero for every `N`; the truth is −1.09. This is all of lesson 8 in
# one line: **the derivative of the estimate is not an estimate of the derivative** when
# the integrand jumps where the parameter moves it.

# %%
t0 = 0.3


def f(x):
    return 1 + x**2


exact_derivative = -f(t0)
samples_derivative = {}
for n in (16, 256, 4096):
    x = (np.arange(n) + 0.5) / n  # midpoints: a deterministic "sampler"
    t = md.tensor(t0, requires_grad=True)
    z = md.tensor(x) - t
    step = md.maximum(z, 0.0) / z  # H(x - t) on the tape: 1 where x > t, else 0
    estimate = md.mean(md.tensor(f(x)) * step)
    estimate.backward()
    samples_derivative[n] = float(t.grad)
print(f"dI/dt exact {exact_derivative:.4f}; derivative of the N-sample estimate:",
      {n: g for n, g in samples_derivative.items()})  # fmt: skip
largest_sample_derivative = max(abs(g) for g in samples_derivative.values())

# %% [markdown]
# The tape's derivative of the sampled estimate is `0` <!-- check: largest_sample_derivative -->
# for 16, 256 and 4,096 samples alike. The general rule (Leibniz): for
# `I(t) = ∫ₐᵇ g(x, t) dx` with `g` jumping across `x = s(t)`,
#
#     dI/dt = ∫ₐᵇ ∂g/∂t dx  +  (g(s⁻) − g(s⁺)) · ds/dt ,
#
# the interior term (what differentiating samples gives) plus a **boundary term**: the
# jump times the speed of the discontinuity. Here `g = f H`, `∂g/∂t = 0` away from the
# jump, `g(s⁻) − g(s⁺) = 0 − f(t)` and `ds/dt = 1`: `−f(t)`.
#
# ## In two dimensions: a pixel and a moving edge
#
# A pixel is the integral of the radiance over its area. When the integrand jumps across
# a curve that moves, Reynolds' transport theorem gives the 2-D version:
#
#     d/dθ ∫_pixel L dA = ∫_pixel ∂L/∂θ dA  +  ∫_{edges ∩ pixel} (L₊ − L₋) vₙ ds ,
#
# with `vₙ` the speed of the edge along its normal (towards the − side) and `L₊ − L₋` the
# jump across it. The first term is what a renderer that differentiates its samples
# computes; the second is what lesson 8's edge methods add.
#
# A toy: a white square of side `w` with lower-left corner `(x₀, y₀)` on a black plane,
# pixels the unit squares of the plane. Pixel `(i, j)`'s value is the area of the square
# inside it, `ov_x · ov_y` with `ov_x = max(0, min(x₀ + w, i + 1) − max(x₀, i))` (and
# `ov_y` likewise). Moving the square by `dx₀` moves its left and right edges; the
# boundary term in pixel `(i, j)` is the length of the right edge inside the pixel (`ov_y`
# if the right edge's `x` is in `[i, i + 1)`) minus that of the left edge, times the jump
# 1: the derivative of `ov_x · ov_y` exactly.

# %%
W_PIX, H_PIX = 12, 10  # the grid of pixels


def square_image(x0, y0, w, samples=None):
    """Pixel values of the square: exact areas (samples None), or the mean of a
    ``samples`` x ``samples`` grid of point samples per pixel (a supersampled render)."""
    i, j = np.meshgrid(np.arange(W_PIX), np.arange(H_PIX))  # (rows, columns)
    if samples is None:
        ov_x = np.clip(np.minimum(x0 + w, i + 1) - np.maximum(x0, i), 0, None)
        ov_y = np.clip(np.minimum(y0 + w, j + 1) - np.maximum(y0, j), 0, None)
        return ov_x * ov_y
    offsets = (np.arange(samples) + 0.5) / samples
    sx = i[..., None, None] + offsets[None, None, :, None]
    sy = j[..., None, None] + offsets[None, None, None, :]
    inside = (sx >= x0) & (sx < x0 + w) & (sy >= y0) & (sy < y0 + w)
    return inside.mean(axis=(2, 3))


def square_edge_term(x0, y0, w):
    """d(pixel values)/dx0 by the boundary term: the vertical edges' lengths in each pixel,
    + for the right edge (it uncovers black with white), - for the left."""
    i, j = np.meshgrid(np.arange(W_PIX), np.arange(H_PIX))
    ov_y = np.clip(np.minimum(y0 + w, j + 1) - np.maximum(y0, j), 0, None)
    right = (i <= x0 + w) & (x0 + w < i + 1)
    left = (i <= x0) & (x0 < i + 1)
    return ov_y * (right.astype(float) - left.astype(float))


X0, Y0, SIDE = 3.3, 2.6, 5.2
exact_fd = (square_image(X0 + 1e-4, Y0, SIDE) - square_image(X0 - 1e-4, Y0, SIDE)) / 2e-4
edge_term = square_edge_term(X0, Y0, SIDE)
toy_edge_error = float(np.abs(edge_term - exact_fd).max())
supersampled_fd = {}
for samples in (8, 64, 512):
    h = 0.25  # stays inside the pixels the edges are in (x0 = 3.3, x0 + w = 8.5)
    plus, minus = (square_image(X0 + s * h, Y0, SIDE, samples) for s in (1, -1))
    supersampled_fd[samples] = float(np.abs((plus - minus) / (2 * h) - edge_term).max())
print(f"edge term vs exact-area differences: {toy_edge_error:.1e}; vs supersampled "
      f"differences: {supersampled_fd}")  # fmt: skip
supersampled_error_512 = supersampled_fd[512]

# %% [markdown]
# The edge term equals the derivative of the exact pixel areas to `1e-9`
# <!-- check: toy_edge_error < -->, and central differences of supersampled images
# approach it as the samples grow (below `0.002` <!-- check: supersampled_error_512 < -->
# with 512 × 512 samples per pixel): supersampling plus a finite step is how we measure
# the truth of a renderer, and the step must not carry an edge across a pixel's border
# (the area is only piecewise linear). Exercise 1 asks for the same term for the square
# turned by 30°, where every edge crosses pixels diagonally.
#
# ## Computing the boundary term in a renderer: the methods of the field
#
# A real image has millions of edge pieces; the jump `L₊ − L₋` is itself an integral (the
# light arriving on either side); the edge's speed comes from the geometry. The methods
# differ in how they find the edges and how they integrate along them:
#
# * **Edge sampling** (Li, Aittala, Durand, Lehtinen, SIGGRAPH Asia 2018; redner): pick
#   points on the silhouette edges at random, evaluate the jump with two rays, add the
#   term. Unbiased, but needs the edges listed and sampled well.
# * **The boundary integral, deterministic** (this library's `antialias="boundary"`,
#   `render/edges/boundary/`): every edge that can be a silhouette or crease, cut into
#   pieces per pixel, one quadrature point per piece, occlusion tested with a ray. Exact
#   for straight edges up to the quadrature; for a Monte Carlo jump, the path integrator's
#   `render/path/boundary/primary.py` (lesson 10) traces both sides.
# * **Pairs of samples** (nvdiffrast's `antialias`, Laine, Hellsten, Karras, Seol,
#   Lehtinen, Aila, SIGGRAPH Asia 2020; this library's `antialias=True`): where two
#   neighbouring samples see different surfaces, blend them by where the edge crosses the
#   segment between them. Cheap and smooth, but it sees only edges between two samples and
#   approximates each pixel's coverage along one axis.
# * **Reparameterisation** (Loubet, Holzschuch, Jakob, SIGGRAPH Asia 2019): move the
#   *samples* with the discontinuities, so that the integrand no longer jumps where the
#   parameter moves it and the ordinary derivative of the samples is right. No edges
#   listed; an approximate warp, so a small bias.
# * **Warped-area sampling** (Bangaru, Li, Durand, SIGGRAPH Asia 2020): turns the boundary
#   integral into an area integral with a smooth warp field (the divergence theorem), which
#   ordinary samples can estimate without bias.
# * **Projective sampling** (Zhang, Roussel, Jakob, SIGGRAPH Asia 2023; Mitsuba 3's
#   `projective` integrator): finds silhouette edges by projecting samples onto them and
#   samples the boundary term from those, with a guiding distribution.
# * **Smoothing: soft rasterisers** (Rhodin, Robertini, Richardt, Seidel, Theobalt, ICCV
#   2015, scenes of Gaussian blobs; SoftRas, Liu, Li, Chen, Li, ICCV 2019; DIB-R, Chen,
#   Gao, Ling, Smith, Lehtinen, Jacobson, Fidler, NeurIPS 2019): do not differentiate the
#   image, differentiate a blurred one. SoftRas makes each triangle's coverage of a pixel
#   a sigmoid of the pixel's signed (squared) distance to the triangle, with a temperature
#   σ, and blends the triangles by a softmax over depth with a second temperature; DIB-R
#   interpolates attributes exactly for the pixels a triangle covers and gives background
#   pixels a soft silhouette (a coverage that decays with the distance to the nearest
#   face). Every pixel near an edge then has a gradient, even one the edge has not reached
#   yet, so the basin of convergence is wider (lesson 13 blurs its images for the same
#   reason). The price: the image and its gradient are those of a different, blurred
#   scene, biased by an amount set by the temperatures, which must be tuned (and usually
#   lowered as a fit converges); occlusion is approximated by the softmax. The methods
#   above estimate the derivative of the image itself.
#
# The toy square, soft: each pixel's value is the square's soft coverage at the pixel's
# centre, every edge's inside test `sigmoid(e / σ)` with `e` the signed distance to that
# edge's line (positive inside) and `σ` a width in pixels, the four tests multiplied.
# Near an edge and away from the corners that is a sigmoid of the signed distance to the
# square, as in SoftRas (which divides the *squared* distance by its σ, an area; the
# idea is the same). The soft image is smooth in `x₀`, so the tape differentiates it as
# it is (`md.jvp`, forward mode: one parameter, a whole image of derivatives), and central
# differences agree. Against the exact areas and the exact edge term, for a sharp, a
# medium and a wide blur:


# %%
def relative_error(estimate: np.ndarray, truth: np.ndarray) -> float:
    """|estimate - truth| / |truth| over the whole image: the error measure from here on."""
    return float(np.linalg.norm(estimate - truth) / np.linalg.norm(truth))


def soft_square_image(x0, y0, w, sigma):
    """A soft coverage of the square at each pixel's centre: every edge's inside test a
    sigmoid of the signed distance to that edge's line (in pixels) over sigma, the four
    multiplied. A tensor function of x0."""
    cx, cy = np.meshgrid(np.arange(W_PIX) + 0.5, np.arange(H_PIX) + 0.5)

    def inside(distance):  # sigmoid(distance / sigma), 1/2 on the edge
        return 0.5 + 0.5 * md.tanh(distance / (2 * sigma))

    across = inside(md.tensor(cx) - x0) * inside(x0 + w - md.tensor(cx))
    along = inside(md.tensor(cy - y0)) * inside(md.tensor(y0 + w - cy))
    return across * along


exact_image = square_image(X0, Y0, SIDE)
FAR = (5, 1)  # a pixel 1.8 pixels left of the square: its true derivative is 0
soft, soft_gradients = {}, {}
for sigma in (0.05, 0.2, 1.0):
    image, gradient = md.jvp(lambda x0, s=sigma: soft_square_image(x0, Y0, SIDE, s), (X0,), (1.0,))
    soft_gradients[sigma] = gradient
    soft[sigma] = {
        "image bias": relative_error(image, exact_image),
        "gradient error": relative_error(gradient, edge_term),
        "pixels with a gradient": int((np.abs(gradient) > 1e-3).sum()),
        "gradient 1.8 px out": float(gradient[FAR]),
    }
    print(f"sigma {sigma}:", {k: round(v, 5) for k, v in soft[sigma].items()})
with md.no_grad():  # the soft image is smooth: central differences agree with the tape
    plus, minus = (soft_square_image(X0 + s, Y0, SIDE, 0.2).data for s in (1e-6, -1e-6))
soft_tape_vs_differences = float(np.abs((plus - minus) / 2e-6 - soft_gradients[0.2]).max())
edge_term_pixels = int((edge_term != 0).sum())
soft_sharp_error = soft[0.05]["gradient error"]
soft_medium_error = soft[0.2]["gradient error"]
soft_wide_error = soft[1.0]["gradient error"]
soft_wide_bias = soft[1.0]["image bias"]
soft_wide_pixels = soft[1.0]["pixels with a gradient"]
soft_wide_far = soft[1.0]["gradient 1.8 px out"]
soft_medium_far = soft[0.2]["gradient 1.8 px out"]

# %% [markdown]
# The tape and central differences of the soft image agree to `1e-6`
# <!-- check: soft_tape_vs_differences < -->: nothing jumps any more. The exact edge term
# is nonzero in `12` <!-- check: edge_term_pixels --> pixels, the ones the square's left
# and right edges cross. With `σ = 1` pixel the soft gradient is above 10⁻³ in every one
# of the `120` <!-- check: soft_wide_pixels --> pixels, and a pixel 1.8 pixels outside
# the square, which the edge has not reached, gets `-0.10` <!-- check: soft_wide_far -->
# (the true image's derivative there: 0): an optimiser there is told which way to move.
# The price is bias: the soft image is `0.44` <!-- check: soft_wide_bias --> off the true
# areas (relative, over the image) and its gradient `0.845` <!-- check: soft_wide_error -->
# off the exact edge term. Lower the temperature and the gradient first improves, `0.19`
# <!-- check: soft_medium_error --> at `σ = 0.2` (where the far pixel gets only `-0.0006`
# <!-- check: soft_medium_far -->), then gets worse again, `3.0`
# <!-- check: soft_sharp_error --> at `σ = 0.05`: a near-step sampled at pixel centres.
# Column 8's centres lie on the right edge (`x₀ + w = 8.5`), where the sigmoid's slope
# is `1/(4σ) = 5` against the edge term's 1; column 3's centres lie 0.2 inside the left
# edge, where it is almost flat (−0.35 against −1). The plain renderer's problem comes
# back. So σ is tuned, a compromise between reach and bias, and the gradient is never
# the true image's.
#
# ## The methods on a real scene, and how exact the truth is
#
# On the teapot, the camera's x position, 32 × 32 pixels, each method rendering 16 samples
# per pixel (4 × 4, so that the interior term, too, is an average over the pixel rather
# than its centre's value), against central differences of 4,096-sample renders (a
# stratified 64 × 64 grid per pixel) with a step of about a seventh of a pixel:

# %%
SIZE = 32
teapot = experiments.paper_scene(SIZE, SIZE)
along_x = np.array([1.0, 0.0, 0.0])
method_gradients = {
    name: render.gradient_image(teapot, "camera.position", along_x, antialias=aa, spp=16)
    for name, aa in (("plain", False), ("pairs", True), ("boundary", "boundary"))
}


def supersampled_truth(spp: int, step: float) -> np.ndarray:
    """Central differences of two ``spp``-sample renders, the camera moved by ± ``step``."""
    renders = []
    with md.no_grad():
        for sign in (1, -1):
            moved = experiments.paper_scene(SIZE, SIZE)
            moved.camera.position.data = moved.camera.position.data + sign * step * along_x
            renders.append(render.render(moved, spp=spp).data)
    return (renders[0] - renders[1]) / (2 * step)


# a pixel is about 0.14 units wide at the teapot: a step of 0.02 is nine sample spacings
teapot_truth = supersampled_truth(4096, 0.02)
method_errors = {name: relative_error(g, teapot_truth) for name, g in method_gradients.items()}
plain_teapot_error = method_errors["plain"]
pairs_teapot_error = method_errors["pairs"]
boundary_teapot_error = method_errors["boundary"]
print({name: round(e, 4) for name, e in method_errors.items()})

# %% [markdown]
# Relative to the truth (over the whole gradient image), the plain renderer is off by
# `0.9` <!-- check: plain_teapot_error > --> or more (it has only the interior term), the
# pixel pairs by `0.26` <!-- check: pairs_teapot_error -->, the boundary integral by just
# under `0.045` <!-- check: boundary_teapot_error < -->.
#
# How good is that 0.045? The truth is an estimate too: a regular grid of samples counts
# an edge's coverage in steps of one sample spacing, and the step moves the edges by only
# nine spacings. Another grid (63², 60² or 70² samples per pixel) or another step
# gives another truth, with errors of its own. Five more of them:

# %%
# (samples per pixel, step): grids of 63², 64², 63², 70², 60² and steps of 0.015 to 0.025
other_samplings = ((3969, 0.02), (4096, 0.015), (3969, 0.025), (4900, 0.02), (3600, 0.02))
other_truths = [supersampled_truth(spp, other_step) for spp, other_step in other_samplings]
truths_disagree = [relative_error(t, teapot_truth) for t in other_truths]
truth_spread_low, truth_spread_high = min(truths_disagree), max(truths_disagree)
boundary_against_others = [relative_error(method_gradients["boundary"], t) for t in other_truths]
pairs_against_others = [relative_error(method_gradients["pairs"], t) for t in other_truths]
boundary_error_low, boundary_error_high = min(boundary_against_others), max(boundary_against_others)
pairs_error_low = min(pairs_against_others)
print(f"the other truths differ from ours by {np.round(truths_disagree, 4)}; against them "
      f"the boundary integral is off by {np.round(boundary_against_others, 4)}, the pairs "
      f"by {np.round(pairs_against_others, 4)}")  # fmt: skip

# The six truths' mean: a better truth, if their errors are independent (its noise about
# 1/sqrt(6) of one truth's). Each truth against it, and the boundary integral with 16 and
# with 64 samples per pixel.
all_truths = [teapot_truth, *other_truths]
mean_truth = np.mean(all_truths, axis=0)
truths_from_mean = [relative_error(t, mean_truth) for t in all_truths]
truth_from_mean_low, truth_from_mean_high = min(truths_from_mean), max(truths_from_mean)
boundary_64 = render.gradient_image(teapot, "camera.position", along_x, antialias="boundary",
                                    spp=64)  # fmt: skip
boundary_64_error = relative_error(boundary_64, teapot_truth)
boundary_from_mean = relative_error(method_gradients["boundary"], mean_truth)
boundary_64_from_mean = relative_error(boundary_64, mean_truth)
pairs_from_mean = relative_error(method_gradients["pairs"], mean_truth)
print(f"each truth from the six's mean: {np.round(truths_from_mean, 4)}; the boundary "
      f"integral at 16 spp {boundary_from_mean:.4f}, at 64 spp {boundary_64_from_mean:.4f} "
      f"(from our truth: {boundary_64_error:.4f}); the pairs {pairs_from_mean:.4f}")  # fmt: skip

# %% [markdown]
# The five other truths differ from ours by `0.038` <!-- check: truth_spread_low --> to
# just under `0.085` <!-- check: truth_spread_high < -->: **the truth's own uncertainty is
# as large as the boundary integral's error**. Against the five, the boundary integral is
# off by `0.036` <!-- check: boundary_error_low --> to just under `0.070`
# <!-- check: boundary_error_high < -->, no more than the truths are off one another: it
# agrees with the truth to within the truth's own uncertainty, and its 0.045 measures the
# reference as much as the method. The pixel pairs, `0.25`
# <!-- check: pairs_error_low > --> or more off every truth, are far outside that
# uncertainty: their error is their own, and so is the plain renderer's.
#
# Two consequences. More samples for the method cannot show more than the truth can: with
# 64 samples per pixel the boundary integral is still more than `0.034`
# <!-- check: boundary_64_error > --> off our truth. A better truth can show more. The six
# truths' mean has about 1/√6 of one truth's noise (if their errors are independent);
# each truth is `0.026` <!-- check: truth_from_mean_low --> to `0.059`
# <!-- check: truth_from_mean_high --> off that mean (though each is a sixth of it),
# the boundary integral `0.029` <!-- check: boundary_from_mean --> with 16 samples, about
# as close as the best single truth, and about `0.02` <!-- check: boundary_64_from_mean -->
# with 64, closer than any 4,096-sample truth. The pairs stay `0.26`
# <!-- check: pairs_from_mean --> off. So the 0.045 above is mostly the reference's
# error. What is the method's own, at 16 samples, is mostly the interior term's (sampled,
# not integrated: it shrinks with 64 samples), and at 64 samples it is below what these
# truths can resolve.
#
# At this size the teapot is 20-odd pixels wide and dozens of its facet edges cross every
# pixel: pairs of samples see few of them. With one sample per pixel the pairs do far
# worse (exercise 3). The README measures the same comparison at 128 × 128 and 512 × 512.
# `teapot_row.png` shows two rows of the gradient image, the truth as black dots on top
# and the six truths' range as a grey band. In the middle row the truths agree and the
# boundary integral runs through the dots; in row 10 the truths spread by about as much
# as the boundary integral misses them, while the pairs miss by far more in many pixels
# and the plain renderer sees a fraction of the derivative.

# %%
columns = np.arange(SIZE)
figure = Figure(figsize=(9.6, 3.8), dpi=100, layout="constrained")
# Two rows: the middle one, and row 10, across the body, where the truths visibly differ.
for ax, row in zip(figure.subplots(1, 2), (SIZE // 2, 10), strict=True):
    row_truths = np.stack([t[row].sum(-1) for t in all_truths])  # sum of RGB
    ax.fill_between(columns, row_truths.min(0), row_truths.max(0), color="0.75", zorder=0,
                    label="range of the six truths")  # fmt: skip
    for name, label in (("plain", "plain renderer"), ("pairs", "pixel pairs"),
                        ("boundary", "boundary integral")):  # fmt: skip
        ax.plot(columns, method_gradients[name][row].sum(-1), "--", marker=".",
                linewidth=1, markersize=4, label=label)  # fmt: skip
    # the truth last, on top: the boundary integral's line would hide a line beneath it
    ax.plot(columns, teapot_truth[row].sum(-1), "o", color="black", markersize=5, zorder=5,
            label="truth (4,096-sample differences)")  # fmt: skip
    ax.set_title(f"row {row}: d image / d camera x (sum of RGB)", fontsize=10, loc="left")
    ax.set_xlabel("pixel column")
    ax.grid(alpha=0.3)
figure.axes[0].set_ylabel("derivative")
figure.axes[0].legend(fontsize=8)
save_and_show(figure, OUT / "teapot_row.png")

# %% [markdown]
# ## Meshes as files have them
#
# Every edge above belongs to a tidy mesh: one list of vertices, each position once, faces
# wound alike. Files are not so tidy. A model with several materials is read as one mesh
# per material (`render.load_mesh`), which meet along seams; a part stored or moved in
# float32 comes apart from its neighbour by a rounding; parts exported one by one come
# apart by more; scans are wound at random. Each is the same surface, so the image and
# its gradient must be the same: the test that found most of the renderer's edge defects
# (a seam counted as two borders, a shadow ray stopped by the face across a crack, a
# flipped face taken for a silhouette). `render.scene.surgery` writes a mesh those ways.
# Here a box over a floor, its faces dealt to three meshes, is compared with the tidy box
# (the boundary term, the light's and the box's translation gradients):


# %%
from render.scene.cornell import box_mesh  # noqa: E402
from render.scene.surgery import (  # noqa: E402
    in_meshes,
    light_and_translation,
    moved_apart,
    through_float32,
    wound_at_random,
)

tidy = box_mesh((0.1, 0.6, 0.0), (0.15, 0.1, 0.12), render.Material((0.6, 0.6, 0.6)))


def seam_gradients(meshes: list) -> np.ndarray:
    """The light's position gradient and the meshes' translation gradient of a fixed
    weighting of the boundary term's render of the meshes over a floor at 32 x 32."""
    return light_and_translation(
        meshes, lambda scene: render.render(scene, antialias="boundary", interior_samples=1)
    )


rng = np.random.default_rng(3)
parts = in_meshes(tidy, rng.integers(0, 3, len(tidy.faces)).tolist())
written = {
    "three meshes": parts,
    "the last through float32": [*parts[:-1], through_float32(parts[-1])],
    "the last moved up to 1e-4": [*parts[:-1], moved_apart(parts[-1], 1e-4, rng)],
    "wound at random": [wound_at_random(tidy, rng)],
    "the last moved up to 1e-3": [*parts[:-1], moved_apart(parts[-1], 1e-3, rng)],
}
reference = seam_gradients([tidy])
seam_errors = {
    name: float(np.abs(seam_gradients(meshes) - reference).max() / np.abs(reference).max())
    for name, meshes in written.items()
}
seam_error_largest = max(e for name, e in seam_errors.items() if "1e-3" not in name)
seam_error_apart = seam_errors["the last moved up to 1e-3"]
print({name: f"{e:.1e}" for name, e in seam_errors.items()})
print(f"elapsed {time.perf_counter() - lesson_start:.1f} s; figures in {OUT}")

# %% [markdown]
# The first four agree with the tidy box to less than `0.001`
# <!-- check: seam_error_largest < --> of the largest gradient. Where two meshes' open
# edges end within a thousandth of those edges (or four float32 steps, or 4e-6 of the
# scene) they are welded into one curve with a face on each side
# (`render.trace.topology.seam_reach`), and the rays that test or shade a point of such an
# edge pass the faces on it, which a line through the edge meets nowhere else. The last
# box's seams came apart by up to 1e-3, three thousandths of its edges: two borders with a
# crack between, a hundredth of a pixel wide, and the gradients are `0.01`
# <!-- check: seam_error_apart > --> or more off. The image hardly changes; the estimate
# of its derivative does, because each side's jump is evaluated inside the crack. Weld
# such seams before rendering.

# %% [markdown]
# ## Exercises
#
# 1. **A toy edge term of your own.** Turn the square by 30° about its centre. Write
#    `turned_edge_term(x0, y0, w)`, the derivative of every pixel's covered area with
#    respect to `x0`: walk along each of the four edges in small steps `ds`, and add
#    `jump · vₙ · ds` to the pixel each step lies in, where `vₙ = n · (1, 0)` is the
#    edge's outward normal's x component (the area grows where the edge moves outwards)
#    and the jump is 1. Check it against central differences of supersampled images
#    (`h = 0.05`, 256 × 256 samples per pixel).
# 2. In the 1-D example, replace the midpoints by `N` uniform random points and estimate
#    `dI/dt` by central differences of `I_N` with step `h`. For `N = 1000`, how does the
#    error behave for `h = 0.1, 0.01, 0.001`, and why does it grow for small `h`?
# 3. Redo the teapot comparison with one sample per pixel (`spp=1`) for the three
#    methods. Which one changes most, and why?
#
# Solutions: `lessons/solutions/11_discontinuities.py`.
