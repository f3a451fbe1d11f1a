# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # Lesson 10 — Monte Carlo: light that bounces, and gradients of noisy images
#
# Lessons 5-9 rendered *direct* light from point lights: one shadow ray per light, no
# randomness. Real light comes from areas (a window, a lamp shade) and bounces (a red wall
# tints the floor). The radiance leaving a point x towards ω_o is then an integral, the
# rendering equation:
#
#     L(x, ω_o) = L_e(x, ω_o) + ∫ f(x, ω_i, ω_o) L(y(x, ω_i), −ω_i) cos θ_i dω_i ,
#
# over the hemisphere of incoming directions ω_i, with y the surface the ray from x along
# ω_i meets and f the material (Lambert: albedo/π). L appears on both sides: light arriving
# at x left another surface, where it arrived from a third. No closed form exists for a
# real scene; a **Monte Carlo estimator** draws random directions and averages
# f L cos / p, where p is the density they were drawn with. Its expectation is the
# integral, whatever p is (as long as p > 0 where the integrand is not zero); its *noise*
# depends on p. This lesson measures that noise, shows three ways of choosing p for light
# from an area, renders a room with `render(..., integrator="path")`
# (`docs/path_tracing.md`) and differentiates it, and shows two traps of differentiating a
# noisy estimate: correlated samples and memory.

# %%
import math
import time
import tracemalloc

import numpy as np
from course import figures_folder, save_and_show
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

import minidiff as md
from minidiff import buffers
from render.inverse.plot import line_figure
from render.path import render_path, replay_gradient
from render.path.sample.emitters import polygon_irradiance
from render.path.sample.random import uniform
from render.path.sample.sampling import cosine_hemisphere
from render.scene.cornell import cornell_box

# This lesson's figures go to out/lessons/10_monte_carlo/ (or under $LESSONS_OUT).
OUT = figures_folder("10_monte_carlo")
lesson_start = time.perf_counter()

# %% [markdown]
# ## An integral by random numbers
#
# The irradiance at a point with normal `n = z` under a sky of radiance `L(ω) = cos θ`
# (bright at the zenith) is `E = ∫ L cos θ dω = ∫ cos² θ dω = 2π/3`. Two estimators, each
# the mean of `N` samples:
#
# * **uniform** directions on the hemisphere, `p = 1/(2π)`: each sample is
#   `2π cos² θ`;
# * **cosine-weighted** directions, `p = cos θ / π` (`render/path/sample/sampling.py`'s
#   `cosine_hemisphere`, Malley's method): each sample is `π cos θ`, smoother.
#
# The random numbers come from `render.path.sample.random.uniform(seed, ids, dimension)`, a hash
# of three integers: the same (seed, id, dimension) gives the same number wherever and in
# whatever order it is computed. That is how the path tracer makes the same image with any
# number of threads, and how its gradient pass can *replay* a sample exactly (below).

# %%
n_z = np.array([[0.0, 0.0, 1.0]])
exact_E = 2 * math.pi / 3


def irradiance_estimates(kind: str, n: int, repeats: int) -> np.ndarray:
    """``repeats`` independent estimates of E, each the mean of ``n`` samples."""
    ids = np.arange(n * repeats)
    u1, u2 = uniform(7, ids, 0), uniform(7, ids, 1)
    if kind == "uniform":  # z = cos(theta) uniform in [0, 1]: uniform on the hemisphere
        cos = u1
        values = 2 * math.pi * cos**2
    else:
        cos = cosine_hemisphere(u1, u2, np.repeat(n_z, len(ids), axis=0)).data[:, 2]
        values = math.pi * cos
    return values.reshape(repeats, n).mean(axis=1)


sample_counts = np.array([4, 16, 64, 256, 1024])
rms = {kind: [] for kind in ("uniform", "cosine")}
for kind in rms:
    for n in sample_counts:
        estimates = irradiance_estimates(kind, int(n), 400)
        rms[kind].append(float(np.sqrt(np.mean((estimates - exact_E) ** 2)) / exact_E))
rms = {kind: np.array(v) for kind, v in rms.items()}
slope_uniform = float(np.polyfit(np.log(sample_counts), np.log(rms["uniform"]), 1)[0])
variance_ratio = float((rms["uniform"] / rms["cosine"]).mean() ** 2)
mean_of_estimates = float(irradiance_estimates("cosine", 64, 400).mean())
mean_relative_error = abs(mean_of_estimates / exact_E - 1)
figure = line_figure(
    {
        "uniform directions": (sample_counts, rms["uniform"]),
        "cosine-weighted directions": (sample_counts, rms["cosine"]),
        "1 / sqrt(N)": (sample_counts, rms["uniform"][0] * np.sqrt(4 / sample_counts)),
    },
    title="Irradiance under a cos-theta sky: relative RMS error of the mean of N samples",
    xlabel="samples N",
    ylabel="relative RMS error",
    logx=True,
    logy=True,
    references=("1 / sqrt(N)",),
)
save_and_show(figure, OUT / "error_vs_samples.png")
print(f"E = {exact_E:.6f}; mean of 400 cosine estimates {mean_of_estimates:.6f}")
for kind, values in rms.items():
    print(kind, " ".join(f"{v:.4f}" for v in values))

# %% [markdown]
# Both estimators are right on average (400 cosine-weighted estimates of 64 samples average
# `2.086` <!-- check: mean_of_estimates -->, within `0.005` <!-- check: mean_relative_error < -->
# of `2π/3 = 2.0944`, relative: two of their standard errors), and the error of either
# falls as `1/√N`: the fitted slope of the uniform one on log-log axes is `-0.5`
# <!-- check: slope_uniform --> (`error_vs_samples.png`). Four times the samples halve the
# noise; that is the price of Monte Carlo. What p changes is the constant: the uniform
# estimator's variance is `6.4` <!-- check: variance_ratio --> times the cosine one's,
# because cosine-weighted samples already follow one of the integrand's two cosines. **Importance
# sampling**: draw where the integrand is large.
#
# ## Light from an area: three ways to choose p
#
# A square lamp of side `2a` at height 1 above our point, facing down, radiance 1. Its
# irradiance has a closed form (Lambert's polygon formula: `E = ½ Σ γ_k n·(v_k × v_k+1)
# / |v_k × v_k+1|`, γ_k the angle the edge k subtends, v the unit vectors to the corners;
# `render.path.sample.emitters.polygon_irradiance`, which the library's tests also check its area
# lights against). Three estimators; the first two take one sample, the third two:
#
# * **BSDF sampling**: a cosine-weighted direction; it counts `π L_e` if it hits the lamp,
#   else 0. For a small lamp almost every sample misses: huge variance.
# * **Light sampling** (next-event estimation, NEE): a uniform point on the lamp, density
#   `1/A` per area; converted to directions, the sample is `L_e cos θ cos θ' A / r²`.
#   Excellent for a small lamp; for a large, near lamp `cos θ'/r²` varies wildly.
# * **Multiple importance sampling** (MIS, Veach 1995): one sample of *each* technique
#   (two samples, so it costs what two samples of one technique cost), each weighted by
#   `w_i = p_i² / (p_1² + p_2²)` (the power heuristic), both densities expressed in the
#   same measure. The weights sum to one for every direction, so the sum is unbiased, and
#   each sample is trusted where its own technique is the likelier one.
#
# A fair comparison gives every estimator the same cost: two samples. So besides one sample
# of BSDF or light sampling, the cell also takes the mean of two independent ones.


# %%
def lamp_estimates(half: float, n: int, technique: str, stream: int = 0) -> np.ndarray:
    """``n`` estimates of the lamp's irradiance by ``technique``: "bsdf" or "light" (one
    sample each), "mis" (one of each), "2 bsdf" or "2 light" (the mean of two). ``stream``
    picks independent random numbers (dimensions 4 * stream to 4 * stream + 3)."""
    if technique.startswith("2 "):
        one = technique[2:]
        return (lamp_estimates(half, n, one, 2) + lamp_estimates(half, n, one, 3)) / 2
    ids, d = np.arange(n), 4 * stream
    area = (2 * half) ** 2
    # Light sampling: a uniform point on the lamp (at height 1, facing down).
    point = np.stack([half * (2 * uniform(3, ids, d) - 1), half * (2 * uniform(3, ids, d + 1) - 1),
                      np.ones(n)], axis=1)  # fmt: skip
    r2 = (point**2).sum(axis=1)
    cos_here = point[:, 2] / np.sqrt(r2)  # at the point, and at the lamp (parallel planes)
    p_light = r2 / (cos_here * area)  # 1/A per area, as a density per steradian
    light_value = cos_here / p_light  # L_e cos / p, L_e = 1
    # BSDF sampling: a cosine-weighted direction; does it reach the lamp's plane inside it?
    u1, u2 = uniform(3, ids, d + 2), uniform(3, ids, d + 3)
    w = cosine_hemisphere(u1, u2, np.repeat(n_z, n, axis=0)).data
    t = 1.0 / np.maximum(w[:, 2], 1e-300)
    hits = (np.abs(w[:, 0] * t) < half) & (np.abs(w[:, 1] * t) < half)
    p_bsdf = w[:, 2] / math.pi
    bsdf_value = np.where(hits, w[:, 2] / p_bsdf, 0.0)
    if technique == "light":
        return light_value
    if technique == "bsdf":
        return bsdf_value
    # MIS: each sample weighted by its technique's share of the two densities there.
    p_bsdf_at_light = cos_here / math.pi
    p_light_at_bsdf = np.where(hits, (t**2 * (w**2).sum(1)) / (w[:, 2] * area), 0.0)
    w_light = p_light**2 / (p_light**2 + p_bsdf_at_light**2)
    w_bsdf = np.where(hits, p_bsdf**2 / (p_bsdf**2 + p_light_at_bsdf**2), 0.0)
    return w_light * light_value + w_bsdf * bsdf_value


lamp_errors = {}
TECHNIQUES = ("bsdf", "light", "2 bsdf", "2 light", "mis")
for half in (0.05, 2.0):
    corners = np.array([[-half, -half, 1], [half, -half, 1], [half, half, 1], [-half, half, 1.0]])
    exact = polygon_irradiance(np.zeros(3), n_z[0], corners)  # the closed form
    for technique in TECHNIQUES:
        samples = lamp_estimates(half, 200_000, technique)
        lamp_errors[half, technique] = (float(samples.mean() / exact - 1),
                                        float(samples.std() / exact))  # fmt: skip
    print(f"lamp half-side {half}: E = {exact:.6f}; relative bias, relative std of one estimate:")
    for technique in TECHNIQUES:
        bias, std = lamp_errors[half, technique]
        print(f"   {technique:5s} {bias:+.4f}  {std:.3f}")
small_bsdf_std = lamp_errors[0.05, "bsdf"][1]
small_light_std = lamp_errors[0.05, "light"][1]
large_bsdf_std = lamp_errors[2.0, "bsdf"][1]
large_light_std = lamp_errors[2.0, "light"][1]
large_mis_std = lamp_errors[2.0, "mis"][1]
small_mis_std = lamp_errors[0.05, "mis"][1]
large_two_bsdf_std = lamp_errors[2.0, "2 bsdf"][1]
small_two_light_std = lamp_errors[0.05, "2 light"][1]
# At equal cost (two samples), MIS's noise over the better technique's, and the worse
# technique's over the better one's, on each lamp.
mis_over_best = max(large_mis_std / large_two_bsdf_std, small_mis_std / small_two_light_std)
worst_over_best_small = lamp_errors[0.05, "2 bsdf"][1] / small_two_light_std
worst_over_best_large = lamp_errors[2.0, "2 light"][1] / large_two_bsdf_std
# Variance is the standard deviation squared: the factor in samples for the same noise.
mis_variance_over_best = mis_over_best**2
largest_bias = max(abs(b) for b, _ in lamp_errors.values())

# %% [markdown]
# All ten estimators are unbiased: over 200,000 samples each mean is within `0.02`
# <!-- check: largest_bias < --> of the closed form (relative; the worst is BSDF sampling
# of the small lamp, whose mean rests on a few hundred hits). Their noise is another
# matter (the relative standard deviation of *one* estimate; N estimates divide it by √N):
#
# * small lamp (half-side 0.05): BSDF sampling `17.6` <!-- check: small_bsdf_std --> (about
#   one direction in 300 hits it), light sampling `0.002` <!-- check: small_light_std -->;
# * large lamp (half-side 2): BSDF sampling `0.45` <!-- check: large_bsdf_std -->, light
#   sampling `1.21` <!-- check: large_light_std --> (points far out on the lamp are seen at
#   a grazing angle from far away: tiny contributions, drawn as often as the bright middle);
# * MIS: `0.002` <!-- check: small_mis_std --> and `0.475` <!-- check: large_mis_std -->.
#
# But MIS spends two samples. At equal cost it is *not* the best on either lamp: two light
# samples give `0.0015` <!-- check: small_two_light_std --> on the small lamp, two BSDF
# samples `0.320` <!-- check: large_two_bsdf_std --> on the large one. MIS's standard
# deviation is up to `1.5` <!-- check: mis_over_best --> times the better technique's, so
# its variance is up to `2.2` <!-- check: mis_variance_over_best --> times as large: to
# match the better technique's noise it needs 2.2 times the samples (the error falls as
# 1/√N). What MIS buys is that it is never far from the better one. The worse technique,
# at the same cost, has more than `8000` <!-- check: worst_over_best_small > --> times the
# better one's standard deviation on the small lamp (BSDF) and `2.7`
# <!-- check: worst_over_best_large --> times on the large one (light). A renderer
# cannot choose per lamp and per pixel which technique to trust (a scene has small and large
# lamps, glossy and matte surfaces, near and far), and a wrong choice is a disaster while
# MIS costs at most 1.5 times the standard deviation here (2.2 times the samples):
# robustness, not a free lunch.
#
# The path tracer (`render/path/sample/tracer.py`) does exactly this at every bounce: one NEE
# point on the area lights and one BSDF direction, MIS-weighted with the power heuristic;
# point and directional lights, which no direction can hit, by NEE alone.
#
# ## Ending paths: Russian roulette
#
# A path could bounce forever; each bounce costs a ray and adds less light. Stopping at a
# fixed depth biases the image (the light of longer paths is lost). **Russian roulette**
# stops a path at random without bias: at a vertex, continue with probability `q` and divide
# what the rest of the path brings, `X`, by `q`; stop (count 0) otherwise. The estimate
# `X · 1{U < q} / q` has expectation `q · X / q + (1 − q) · 0 = X`, whatever `q` is.
# It is not free. The estimate is `X/q` with probability `q` and 0 otherwise, so its square
# has expectation `q · E[X²]/q² = E[X²]/q`, and its variance is `E[X²]/q − E[X]²`. For a
# constant `X`, which has no noise of its own, that is `X²/q − X² = X² (1 − q)/q`: the
# coin's noise alone. In general it is `Var X / q + E[X]² (1 − q)/q`: `X`'s own noise,
# inflated by `1/q`, plus the coin's. What it buys is the expected cost: the rest of the
# path is traced only with probability `q`. Played with the same `q` at every vertex, a
# path makes `k` more bounces with probability `q^k (1 − q)`, `q/(1 − q)` more on average:
# a path of unbounded length, with no depth limit and no bias, has a finite expected cost.
# Checked below with the library's random numbers, for `q = ¼` and two `X`: the constant 1
# (the formula: `(1 − q)/q = 3`), and `X` uniform in [0, 1) (mean ½, variance 1/12; the
# formula: `(1/12)/q + ¼ (1 − q)/q = 1.0833`):

# %%
roulette_ids = np.arange(400_000)
q = 0.25
survives = uniform(5, roulette_ids, 1) < q  # the coin: continue with probability q
coin_only = np.where(survives, 1.0 / q, 0.0)  # X = 1
coin_variance = float(coin_only.var())
coin_variance_error = abs(coin_variance / ((1 - q) / q) - 1)
x = uniform(5, roulette_ids, 0)  # what the rest of the path would bring
with_roulette = np.where(survives, x / q, 0.0)
roulette_standard_error = with_roulette.std() / math.sqrt(len(roulette_ids))
roulette_bias_in_errors = abs(with_roulette.mean() - 0.5) / roulette_standard_error
roulette_variance = float(with_roulette.var())
roulette_variance_predicted = (1 / 12) / q + 0.5**2 * (1 - q) / q
roulette_variance_error = abs(roulette_variance / roulette_variance_predicted - 1)
roulette_variance_growth = roulette_variance / float(x.var())
traced_share = float(survives.mean())
print(f"X = 1: mean {coin_only.mean():.4f}, variance {coin_variance:.4f} (predicted "
      f"{(1 - q) / q:.4f}); X uniform: mean {with_roulette.mean():.4f} (X's: 0.5; "
      f"{roulette_bias_in_errors:.1f} standard errors off), variance {roulette_variance:.4f} "
      f"(predicted {roulette_variance_predicted:.4f}, X's own: {x.var():.4f}); paths traced "
      f"on: {traced_share:.4f}")  # fmt: skip

# %% [markdown]
# For `X = 1` the variance is `2.996` <!-- check: coin_variance --> against the formula's 3
# (relative difference below `0.005` <!-- check: coin_variance_error < -->, the Monte Carlo
# error of a variance from 400,000 samples). For `X` uniform the mean stays ½ (within `3`
# <!-- check: roulette_bias_in_errors < --> standard errors) and the variance is `1.081`
# <!-- check: roulette_variance --> against the formula's 1.0833 (below `0.005`
# <!-- check: roulette_variance_error < --> relative):
# `13.0` <!-- check: roulette_variance_growth --> times X's own, for tracing the rest of
# only `0.249` <!-- check: traced_share --> of the paths. Here that is a bad trade (13 times
# the variance for a quarter of the cost); it is a good one where `X` is small compared
# with the rest of the pixel's light, which is why roulette is switched on only deep in a
# path, and why `q` follows what the path still carries. In `render/path/twin/kernel.py` (and
# its NumPy reference, `render/path/sample/tracer.py`), from vertex `rr_depth` on (5 by default,
# as in Mitsuba 3), a path continues with probability `q` = the product of the mean
# reflectances of the surfaces it has met (an estimate of its throughput), clamped to
# [0.05, 0.95] (`MIN_SURVIVAL`, `MAX_SURVIVAL` in `tracer.py`), and what it gathers after
# that is divided by `q` (its next segment's weight is `1 / (pdf · q)`). A path that
# carries little is cut often; one that carries much rarely.
#
# ## A room rendered by paths
#
# `render.render(scene, integrator="path", spp=..., max_depth=..., seed=...)` traces `spp`
# paths per pixel: from the camera through a random point of the pixel, at every vertex NEE
# plus a BSDF direction, until `max_depth` segments (1: lamps seen directly, 2: direct
# light, 3: one bounce of indirect light, ...) or Russian roulette ends it. The Cornell box
# (`render.scene.cornell.cornell_box`): a white room, a red and a green wall, a lamp in
# the ceiling, a box and a sphere. The pixel noise, measured over independent seeds,
# follows the same `1/√N`.

# %%
room = cornell_box(12, 12)
noise = []
path_spps = np.array([4, 16, 64])
for spp in path_spps:
    with md.no_grad():
        images = np.stack([render_path(room, spp=int(spp), max_depth=4, seed=s).data
                           for s in range(6)])  # fmt: skip
    noise.append(float((images.std(axis=0, ddof=1) / images.mean(axis=0).clip(1e-3)).mean()))
noise = np.array(noise)
path_noise_slope = float(np.polyfit(np.log(path_spps), np.log(noise), 1)[0])
with md.no_grad():
    pretty = render_path(cornell_box(48, 48), spp=64, max_depth=5, seed=1).data
    direct_only = render_path(cornell_box(48, 48), spp=64, max_depth=2, seed=1).data
indirect_share = float(1 - direct_only.mean() / pretty.mean())
# Two labelled panels; the images are shown brightened twice and gamma-encoded for display.
room_figure = Figure(figsize=(6.4, 3.9), dpi=100, layout="constrained")
FigureCanvasAgg(room_figure)
for i, (panel, title) in enumerate([
    (direct_only, "direct light only\n(max_depth=2, 64 spp)"),
    (pretty, "direct and indirect light\n(max_depth=5, 64 spp)"),
]):  # fmt: skip
    ax = room_figure.add_subplot(1, 2, i + 1)
    ax.imshow(np.clip(2 * panel, 0, 1) ** (1 / 2.2), interpolation="nearest")
    ax.set_title(title, fontsize=10)
    ax.set_axis_off()
save_and_show(room_figure, OUT / "cornell_box.png")
print(
    "relative pixel noise at",
    list(path_spps),
    "spp:",
    noise.round(4),
    f"slope {path_noise_slope:.3f}; indirect light's share of the image {indirect_share:.3f}",
)

# %% [markdown]
# The relative pixel noise falls with slope `-0.5` <!-- check: path_noise_slope --> against
# spp. `cornell_box.png` shows the room at 64 spp with `max_depth=2` (direct light only:
# the ceiling is black, the shadows are black) and `max_depth=5` (indirect light: the
# ceiling lit by the floor, the walls' colours bleeding onto the box); indirect light is
# `0.20` <!-- check: indirect_share --> of the image's mean.
#
# ## Differentiating a noisy image
#
# The path tracer records each path's discrete choices (which surface, which lobe, lit or
# blocked) as constants and recomputes the contributions on the tape, as the direct
# renderer does with visibility (lesson 6). So `backward` gives the derivative of *this*
# estimate, itself an estimate of the derivative of the expected image. For a parameter
# that changes no choice, the emission of the lamp, the same seed on both sides of a
# central difference makes the two agree to rounding.

# %%
lamp = room.objects[5].material
lamp.emission.requires_grad = True
weights = np.random.default_rng(0).random((12, 12, 3))
md.sum(render_path(room, spp=8, max_depth=4, seed=3) * md.tensor(weights)).backward()
tape_gradient = lamp.emission.grad.copy()
lamp.emission.requires_grad, lamp.emission.grad = False, None
base = lamp.emission.data.copy()
central = np.zeros(3)
for c in range(3):
    values = []
    for sign in (1, -1):
        lamp.emission.data = base + sign * 1e-3 * np.eye(3)[c]
        with md.no_grad():
            values.append(
                float((render_path(room, spp=8, max_depth=4, seed=3).data * weights).sum())
            )
    central[c] = (values[0] - values[1]) / 2e-3
lamp.emission.data = base
emission_agreement = float(np.abs(tape_gradient - central).max() / np.abs(central).max())
print(f"d sum(W * I) / d emission: tape {tape_gradient.round(6)}, same-seed central "
      f"differences {central.round(6)}; relative difference {emission_agreement:.1e}")  # fmt: skip

# %% [markdown]
# They agree to `1e-8` <!-- check: emission_agreement < --> (relative). A light's position
# or a vertex would move choices too (a shadow's edge, a silhouette): lesson 8's problem
# again, now also in the shadows of area lights; `docs/path_tracing.md` measures what the
# missing boundary terms cost and how `antialias="boundary"` restores the camera's.
#
# ## Trap 1: the same samples in the image and in its gradient
#
# For a loss that is not linear in the image, `L = Σ (I − T)²`, the gradient is
# `2 Σ (I − T) ∂I/∂θ`. If `I` and `∂I/∂θ` come from the *same* samples, they are
# correlated, and the expectation of their product is not the product of expectations: for
# an emission scale `k` (so `∂I/∂k = I/k`) the gradient's mean is off by `2 Σ Var(I) / k`,
# always upward. `render.path.replay_gradient` therefore renders the image with `seed` and
# replays the paths for the gradient with `seed_grad`; left out, `seed_grad` is `seed + 1`
# (`render/path/integrator.py`). One more is enough because no number comes from a running
# generator: each is a hash of (seed, path id, dimension) (`render/path/sample/random.py`:
# SplitMix64's finaliser applied to the seed, then again after the path id and the
# dimension are folded in). A seed one higher changes the key from the first step, so the
# same path ids draw an unrelated stream, not a shifted copy of the old one; the cell below
# measures it. `seed_grad=seed` is allowed: it gives the correlated gradient, measured
# below, and it is what `render_path`'s own backward computes (its replay uses the image's
# seed, so that it equals the tape's gradient: the derivative of *this* estimate).
#
# Mitsuba 3's `mi.render` does it differently: its `seed_grad` defaults to 0, which means
# "derive one from `seed`", by a hash (`mi.sample_tea_32(seed, 1)`), and it raises an
# error when `seed_grad == seed`. Both decorrelate for the same reason: the gradient's
# random numbers come from a stream unrelated to the image's, ours because our generator
# is keyed by the seed, Mitsuba's because its sampler is seeded with a hashed value.

# %%
stream_ids = np.arange(200_000)
stream_correlation = max(
    abs(float(np.corrcoef(uniform(s, stream_ids, d), uniform(s + 1, stream_ids, d))[0, 1]))
    for s in (0, 3) for d in (0, 1)
)  # fmt: skip
print(f"largest |correlation| of seed s and s + 1 on the same path ids: {stream_correlation:.4f}")

# %% [markdown]
# The numbers that seeds `s` and `s + 1` give the same 200,000 path ids correlate by at most
# `0.01` <!-- check: stream_correlation < --> (four pairs of streams; independent streams
# would give about `1/√200000 ≈ 0.002`). Now the gradients, over 60 seeds at 1 spp (even
# seeds, so that no run's gradient seed is another run's image seed), with the target the
# expected image (so the true gradient is zero), once with `seed_grad=seed` and once with
# the default:

# %%
small = cornell_box(12, 12)
with md.no_grad():
    expected = render_path(small, spp=1024, max_depth=3, seed=99).data


def seed_gradient(seed: int, seed_grad: int | None) -> float:
    emission = small.objects[5].material.emission
    emission.requires_grad, emission.grad = True, None
    replay_gradient(small, lambda image: md.sum((image - md.tensor(expected)) ** 2), spp=1,
                    max_depth=3, seed=seed, seed_grad=seed_grad)  # fmt: skip
    grad = float(emission.grad.sum())
    emission.requires_grad, emission.grad = False, None
    return grad


gradient_seeds = range(0, 120, 2)
correlated = np.array([seed_gradient(s, s) for s in gradient_seeds])
decorrelated = np.array([seed_gradient(s, None) for s in gradient_seeds])  # seed + 1
correlated_mean = float(correlated.mean())
correlated_error = float(correlated.std() / math.sqrt(len(correlated)))
decorrelated_mean = float(decorrelated.mean())
decorrelated_error = float(decorrelated.std() / math.sqrt(len(decorrelated)))
bias_in_errors = float((correlated_mean - decorrelated_mean)
                       / math.hypot(correlated_error, decorrelated_error))  # fmt: skip
decorrelated_in_errors = abs(decorrelated_mean) / decorrelated_error
print(f"correlated {correlated_mean:.3f} ± {correlated_error:.3f}; decorrelated "
      f"{decorrelated_mean:.3f} ± {decorrelated_error:.3f}")  # fmt: skip

# %% [markdown]
# The decorrelated mean is zero within its error (`|mean|` below `3`
# <!-- check: decorrelated_in_errors < --> standard errors); the correlated one sits more
# than `5` <!-- check: bias_in_errors > --> standard errors above it. An optimiser fed the
# correlated gradient would settle where the image is too dark, by an amount that shrinks
# only as the spp grows.

# %% [markdown]
# ## Trap 2: a tape that remembers every sample
#
# Rendering on the tape and calling `backward` keeps every vertex of every path until the
# backward: memory grows with spp × depth. **Replay** (`replay_gradient`; the structure of
# radiative backpropagation, Nimier-David et al. 2020) renders the image without a tape,
# computes `∂L/∂I` once, then renders the samples again in batches with the *same* random
# numbers (the counter-based generator of the first section makes that exact), each batch
# on its own short tape, and back-propagates that batch's share of `∂L/∂I` before dropping
# it. The peak memory is one batch's. `render_path` does this by itself when a parameter
# requires grad (its default `gradient="replay"`): the image it returns is one tape node
# whose backward replays the batches. Below, `gradient="tape"` keeps every path on the tape
# instead, to show what replay saves.

# %%
mem_room = cornell_box(16, 16)
mem_room.objects[3].material.albedo.requires_grad = True
with md.no_grad():
    mem_target = render_path(mem_room, spp=4, max_depth=3, seed=5).data


def mem_loss(image):
    return md.mean((image - md.tensor(mem_target)) ** 2)


def peak_mb(fn) -> float:
    """The peak of the memory NumPy allocates while ``fn()`` runs, in MB. The renderer's
    pool of reused arrays (``minidiff.buffers``) is off inside (``fresh``): an array the
    pool hands back again is not a new allocation, so with it on the peak would depend on
    what ran before."""
    tracemalloc.start()
    with buffers.fresh():
        fn()
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return peak / 1e6


memory = {}
for spp in (16, 64):
    memory["tape", spp] = peak_mb(
        lambda s=spp: mem_loss(
            render_path(mem_room, spp=s, max_depth=3, gradient="tape")
        ).backward()
    )
    memory["replay", spp] = peak_mb(
        lambda s=spp: replay_gradient(mem_room, mem_loss, spp=s, max_depth=3, batch_spp=16)
    )
tape_added = memory["tape", 64] - memory["tape", 16]  # MB
replay_growth = memory["replay", 64] / memory["replay", 16]
print({f"{k[0]} {k[1]} spp": round(v, 1) for k, v in memory.items()})
print(f"elapsed {time.perf_counter() - lesson_start:.1f} s; figures in {OUT}")

# %% [markdown]
# From 16 to 64 spp the tape's peak grows by more than `5` <!-- check: tape_added > --> MB
# (printed above: three more batches of 16 samples on the tape, each about 2.5 MB for this
# 16x16 image, over a part that does not grow with spp), the replay's less than `1.1`
# <!-- check: replay_growth < --> times. Each batch still holds all the vertices of its
# paths, so this replay's memory still grows with `max_depth`; lesson 14 takes replay
# further, to a compiled adjoint that walks each path again vertex by vertex and keeps a
# few numbers per vertex (Vicini et al. 2021).
#
# ## Exercises
#
# 1. A *uniform* sky (`L = 1`): compute the relative standard deviation of one
#    cosine-weighted sample of `E = π` and of one uniform sample. Why is one of them zero?
# 2. From the room's noise at 16 spp (above), predict the spp needed for a relative pixel
#    noise of 5 %, render it with 6 seeds, and measure.
# 3. Replace the power heuristic in `lamp_estimates` by the *balance* heuristic
#    `w_i = p_i / (p_1 + p_2)`. Is it still unbiased? Compare its noise with the power
#    heuristic's for both lamps.
# 4. **Variance reduction for a gradient.** A pixel's value `I(θ) = ∫₀¹ e^(θx) dx` and its
#    derivative `I'(θ) = ∫₀¹ x e^(θx) dx`, estimated at `θ = 1.5` as the mean of
#    `x e^(θx)` over uniform `x` (`render.path.sample.random.uniform`). At equal cost (the same
#    number of evaluations of the integrand), reduce its variance (a) with *antithetic*
#    pairs, `x` and `1 − x`, whose terms move in opposite directions; (b) with a *control
#    variate*, a function `g` close to the integrand whose mean you know (its Taylor
#    polynomial `x + θx²`, mean `½ + θ/3`): `x e^(θx) − c (g(x) − E[g])`, with `c` the
#    regression coefficient. Check both against the closed form and measure the factors.
#
# Solutions: `lessons/solutions/10_monte_carlo.py`.
