# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # Lesson 14 — Path replay and radiative backpropagation
#
# Lesson 10 differentiated a path-traced image by putting the paths on minidiff's tape, and
# noticed that the tape's memory grows with the number of samples. This lesson takes that
# apart: why the memory grows, the adjoint idea that avoids it (radiative backpropagation,
# Nimier-David, Vicini, Zeltner, Jakob 2020; path replay backpropagation, Vicini,
# Speierer, Jakob 2021), a hand-written adjoint of a small path model checked against the
# tape, and the choice every Monte Carlo gradient makes about its samples: *attached* or
# *detached* (Zeltner, Speierer, Georgiev, Jakob 2021).

# %%
import math
import time
import tracemalloc

import numpy as np
from course import figures_folder, save_and_show
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from scipy.integrate import quad

import minidiff as md
from minidiff import buffers
from render.path import render_path
from render.path.sample.random import uniform
from render.scene.cornell import cornell_box

# This lesson's figures go to out/lessons/14_path_replay/ (or under $LESSONS_OUT).
OUT = figures_folder("14_path_replay")
lesson_start = time.perf_counter()

# %% [markdown]
# ## 1. A tape remembers every path
#
# Reverse mode needs, in its backward pass, the values of the forward pass (lesson 1: a
# node's VJP reads its inputs). For a path tracer the forward pass is every vertex of every
# path: its point, normal, material, direction, the throughput so far. A tape keeps all of
# them until `backward`, so its memory grows with pixels × samples × depth.
#
# `render_path(..., gradient="tape")` does exactly that. The library's default,
# `gradient="replay"`, renders the image with the compiled kernel and hands the tape one
# node; its backward *replays* the paths (below): it follows each path again from the
# decisions the render recorded (which primitive, which lobe, which light sample) and takes
# its derivative path by path, never holding a tape of the batch. For every kind of
# parameter (an albedo, a light's position, a vertex, the camera) that is one compiled
# function of the whole path (`render/path/gradient/window.py`: the tape's readable
# formulas for vertex `k`, called for one vertex after the other and traced by lesson 16's
# compiler), whose VJP runs each path's reverse sweep inside the kernel, in parallel over
# the paths. Where that does not apply (float32 parameters, a light whose shading does not
# compile) the replay goes one depth at a time on the tape
# (`render/path/gradient/replay.py`): *windows*, window `k` computing only what vertex `k`
# of the batch's paths adds and what its bounce multiplies by (which needs vertices
# `k − 1`, `k` and `k + 1`), taking its share of the
# gradient with its own `backward`, freed before window `k + 1` is built (section 3 says
# what it takes from the rest of the path).
#
# The tape's size depends on the parameter (a moving lamp puts the geometry of every shadow
# ray on the tape, an albedo only the shading). So compare like with like: each parameter's
# tape against its replay, the left wall's albedo and the lamp's position. The peak of NumPy's
# allocations during one gradient of the Cornell box at 16 × 16, without Russian roulette
# (so paths really are `max_depth` long):


# %%
def room_with(parameter: str) -> tuple:
    """The Cornell box at 16 × 16 and its parameter to differentiate, requiring grad: the
    left wall's albedo ("albedo") or the lamp's position ("lamp")."""
    room = cornell_box(16, 16)
    p = (
        room.objects[0].material.albedo
        if parameter == "albedo"
        else room.objects[5].transform.translation
    )
    p.requires_grad = True
    return room, p


def box_gradient_once(gradient: str, parameter: str, spp: int, max_depth: int) -> None:
    """Render the Cornell box and differentiate the mean of the squared image with respect
    to ``parameter`` (``room_with``)."""
    room, _ = room_with(parameter)
    # Off: minidiff's pool of reused arrays (a reused array is no new allocation, so the
    # peak would depend on what ran before).
    with buffers.fresh():
        image = render_path(
            room, spp=spp, max_depth=max_depth, seed=0, rr_depth=100, gradient=gradient
        )
        md.mean(image * image).backward()


def gradient_peak_mb(gradient: str, parameter: str, spp: int, max_depth: int) -> float:
    """The peak of traced allocations (MB) during ``box_gradient_once``."""
    tracemalloc.start()
    box_gradient_once(gradient, parameter, spp, max_depth)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return peak / 1e6


WAYS = {  # the parameter, then how its gradient is taken
    "albedo: through the tape": ("tape", "albedo"),
    "albedo: compiled replay": ("replay", "albedo"),
    "lamp's position: through the tape": ("tape", "lamp"),
    "lamp's position: compiled whole paths": ("replay", "lamp"),
}
for gradient, parameter in WAYS.values():  # first calls load kernels and fill caches
    # (the compiled replay's kernels depend on the depth: lesson 16's compiler traces
    # each once; one sample per pixel is enough to make them)
    for depth in [2, 4, 8, 16] if gradient == "replay" else [4]:
        box_gradient_once(gradient, parameter, 1, depth)
spps, depths = [4, 16, 64], [2, 4, 8, 16]
memory_by_spp = {w: [gradient_peak_mb(*WAYS[w], spp, 4) for spp in spps] for w in WAYS}
# 16 spp at max_depth 4 was measured just above: the depth sweep reuses it.
memory_by_depth = {
    w: [memory_by_spp[w][1] if d == 4 else gradient_peak_mb(*WAYS[w], 16, d) for d in depths]
    for w in WAYS
}
for name in WAYS:
    print(f"{name:38s} spp {spps}: {np.round(memory_by_spp[name], 2)} MB; "
          f"max_depth {depths}: {np.round(memory_by_depth[name], 2)} MB")  # fmt: skip
albedo_tape, compiled = "albedo: through the tape", "albedo: compiled replay"
lamp_tape, paths = "lamp's position: through the tape", "lamp's position: compiled whole paths"
tape_spp_growth = memory_by_spp[albedo_tape][2] / memory_by_spp[albedo_tape][1]
tape_depth_growth = memory_by_depth[albedo_tape][3] / memory_by_depth[albedo_tape][0]
lamp_tape_spp_growth = memory_by_spp[lamp_tape][2] / memory_by_spp[lamp_tape][1]
lamp_tape_depth_growth = memory_by_depth[lamp_tape][3] / memory_by_depth[lamp_tape][0]
paths_spp_growth = memory_by_spp[paths][2] / memory_by_spp[paths][1]
paths_depth_growth = memory_by_depth[paths][3] / memory_by_depth[paths][0]
# The two replays are one compiled function: how far apart their peaks are, at most.
replays_differ = max(
    abs(a / b - 1.0)
    for by in (memory_by_spp, memory_by_depth)
    for a, b in zip(by[compiled], by[paths], strict=True)
)
# Like with like: each parameter's tape over its replay, at each point measured.
albedo_saving_at_64 = memory_by_spp[albedo_tape][2] / memory_by_spp[compiled][2]
albedo_saving_at_depth_16 = memory_by_depth[albedo_tape][3] / memory_by_depth[compiled][3]
lamp_saving_by_spp, lamp_saving_by_depth = (
    [t / r for t, r in zip(by[lamp_tape], by[paths], strict=True)]
    for by in (memory_by_spp, memory_by_depth)
)
lamp_smallest_spp_saving = min(lamp_saving_by_spp)
lamp_saving_at_64 = lamp_saving_by_spp[2]
lamp_saving_at_depth_2 = lamp_saving_by_depth[0]
# The first depth from which the lamp's replay holds less than the tape, at 16 spp.
replay_cheaper_from_depth = next(
    d for i, d in enumerate(depths) if all(s > 1 for s in lamp_saving_by_depth[i:])
)
print(f"lamp's position, tape / compiled whole paths: spp {spps}: "
      f"{np.round(lamp_saving_by_spp, 2)}; max_depth {depths}: "
      f"{np.round(lamp_saving_by_depth, 2)}")  # fmt: skip
# The tape's memory per pixel per sample, from 16 to 64 spp, scaled to 512 × 512 at 256 spp.
per_pixel_sample_mb = (memory_by_spp[albedo_tape][2] - memory_by_spp[albedo_tape][1]) / (
    16 * 16 * (64 - 16)
)
tape_at_512_gb = per_pixel_sample_mb * 512 * 512 * 256 / 1000
print(f"the tape at 512 x 512, 256 spp, max_depth 4: about {tape_at_512_gb:.0f} GB")
# Two panels, one y axis: against spp (max_depth 4) and against max_depth (16 spp).
figure = Figure(figsize=(8.0, 3.6), dpi=100, layout="constrained")
FigureCanvasAgg(figure)
panels = figure.subplots(1, 2, sharey=True)
for ax, xs, by, xlabel in (
    (panels[0], spps, memory_by_spp, "samples per pixel (max_depth 4)"),
    (panels[1], depths, memory_by_depth, "max_depth (16 samples per pixel)"),
):
    for name, (gradient, parameter) in WAYS.items():
        ax.plot(xs, by[name], marker="o", markersize=4, label=name,
                color="tab:blue" if parameter == "albedo" else "tab:orange",
                linestyle="-" if gradient == "tape" else "--")  # fmt: skip
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xticks(xs, [str(x) for x in xs])
    ax.minorticks_off()
    ax.set_xlabel(xlabel)
    ax.grid(True, color="0.9")
panels[0].set_ylabel("peak memory (MB)")
panels[1].legend(fontsize=8, frameon=False, loc="lower right", bbox_to_anchor=(1, 0.1))
figure.suptitle("Peak memory of one gradient, Cornell box 16 × 16", fontsize=10)
save_and_show(figure, OUT / "memory.png")

# %% [markdown]
# The tapes first. From 16 to 64 samples per pixel the albedo's tape grows more than `2.5`
# <!-- check: tape_spp_growth > --> times and the lamp's more than `3`
# <!-- check: lamp_tape_spp_growth > --> times (four times the paths, plus a fixed part);
# from depth 2 to 16 more than `2` <!-- check: tape_depth_growth > --> and `3`
# <!-- check: lamp_tape_depth_growth > --> times (fewer than 8: a path that leaves the box
# through its open front ends early). The lamp's tape is the larger at every point: the
# lamp's position reaches more of each path's arithmetic (every light sample's point,
# distance and cosines) than an albedo does.
#
# **The replay** is one compiled function for both parameters (their peaks differ by less
# than `0.05` <!-- check: replays_differ < --> of each other, relative). It grows less than
# `1.1` <!-- check: paths_spp_growth < --> times from 16 to 64 samples and less than `7.5`
# <!-- check: paths_depth_growth < --> times from depth 2 to 16 (the values are printed
# above; the allocator's bookkeeping moves them by a percent from run to run). It holds one
# batch of paths' *decisions* (which primitive, which lobe, which light: a few hundred
# bytes per vertex) and a few arrays per path, never the whole batch's tape: the reverse
# sweep of a path keeps its values inside the kernel, one path per thread at a time (8
# depths at a time: a deeper path's vertex 8 and throughput are handed to a second
# kernel, and their gradient back). So the
# decisions are most of the peak, and they grow with the paths' length: that is the growth
# with depth. A batch is 16 samples per pixel by default (`batch_spp`), so below 16 it
# grows with the samples like the tape, and above it stays flat. Against the lamp's own
# tape it is the smaller at every point measured: the tape holds more than `3.5`
# <!-- check: lamp_smallest_spp_saving > --> times as much at every spp, more than `12`
# <!-- check: lamp_saving_at_64 > --> times at 64, and more than `3.5`
# <!-- check: lamp_saving_at_depth_2 > --> times at depth 2, so the replay is the cheaper
# from depth `2` <!-- check: replay_cheaper_from_depth --> on. An albedo puts much less on
# its tape: at 64 samples its tape still holds more than `5`
# <!-- check: albedo_saving_at_64 > --> times the replay, but at depth 16 a little less,
# `0.9` <!-- check: albedo_saving_at_depth_16 --> times: there the decisions the replay
# reads (and its second segment's copy of the rows it needs, below depth 8) take more than
# the albedo's tape. (Before the replay was compiled from the tape's
# formulas, the albedo had a hand-written replay of its own that kept nothing per path, a
# second copy of the mathematics; and when the replay went window by window, each window a
# tape of its own spanning three vertices, the lamp's replay held more than its tape at
# depth 2.) `memory.png` shows the four against spp (left) and
# against `max_depth` (right): blue the albedo, orange the lamp, solid lines the tape,
# dashed the replay. Scaled to 512 × 512 at 256 samples, the albedo's tape would need more
# than `50` <!-- check: tape_at_512_gb > --> GB.
#
# ## 2. The adjoint idea: light going backwards
#
# A path's radiance is a sum over its vertices,
#
#     L = Σ_k β_k C_k ,     β_1 = 1,  β_{k+1} = β_k F_k ,
#
# where `C_k` is what vertex `k` adds (the lamp seen by next-event estimation, or hit by the
# sampled direction) and `F_k` the factor of the segment that leaves it (`f cos / p`: for
# Lambert sampled by its cosine, the albedo). Its derivative with respect to a parameter θ:
#
#     dL/dθ = Σ_k β_k dC_k/dθ  +  Σ_k β_k dF_k/dθ · R_k ,     R_k = C_{k+1} + F_{k+1} R_{k+1} ,
#
# `R_k` being the radiance that reaches vertex `k` from the rest of the path. Read it
# backwards, and it is light transport run in reverse: the loss's gradient with respect to a
# pixel, `δ = ∂loss/∂I`, is *emitted* by the camera as **adjoint radiance**, carried along
# the path with the throughput `β_k`, and wherever it meets a vertex whose scattering
# depends on θ it deposits `δ β_k (dC_k/dθ + dF_k/dθ R_k)`. That is **radiative
# backpropagation** (Nimier-David et al. 2020): no tape, just a second transport
# simulation. Its one difficulty is `R_k`, the radiance arriving at the vertex: radiative
# backpropagation estimated it with a new, independent path from every vertex (a cost
# quadratic in the depth). **Path replay backpropagation** (Vicini et al. 2021) instead
# traces the *same* path again, from the same random numbers (the library's counter-based
# generator, `render/path/sample/random.py`, gives every number from (seed, path, dimension), so
# a replay draws exactly what the render drew), and gets `R_k` from the path's own total:
# after subtracting what the vertices up to `k` added, what remains is `β_k F_k R_k`.
#
# ## 3. The adjoint by hand, for a small path model
#
# A model small enough to write out: a path that bounces between Lambertian surfaces with
# albedos `ρ` (one parameter per surface), each vertex adding next-event estimation
# `C_k = ρ_{s_k} g_k E` (the lamp's emission `E` times a geometry factor `g_k`), the
# segment factor `F_k = ρ_{s_k}`, and the last direction hitting the lamp with weight `w`:
# one more term `w E`. The forward pass keeps nothing but the running throughput and `L`.

# %%
# One path: the surfaces it bounces on (indices into rho), each vertex's geometry factor
# g_k, and the MIS weight of the lamp hit by its last direction.
surfaces = np.array([0, 1, 0, 2])
geometry = np.array([0.31, 0.12, 0.27, 0.05])
last_hit_weight = 0.4
rho = np.array([0.7, 0.45, 0.8])
emission = 6.0


def path_radiance(rho, emission) -> float:
    """L = sum_k beta_k C_k, by one walk along the path: O(1) memory."""
    beta, radiance = 1.0, 0.0
    for s, g in zip(surfaces, geometry, strict=True):
        radiance += beta * rho[s] * g * emission  # C_k: next-event estimation
        beta *= rho[s]  # F_k: the sampled bounce
    return radiance + beta * last_hit_weight * emission


def path_adjoint(rho, emission, delta: float) -> tuple[np.ndarray, float]:
    """d(delta * L)/d(rho) and d(delta * L)/d(emission) by replay: walk the path again,
    carrying the throughput forwards and the radiance still to come, L minus what the
    vertices so far added (Vicini et al. 2021)."""
    total = path_radiance(rho, emission)  # the render gives L; the replay needs only it
    d_rho, d_emission = np.zeros_like(rho), 0.0
    beta, remaining = 1.0, total
    for s, g in zip(surfaces, geometry, strict=True):
        c = rho[s] * g * emission
        remaining -= beta * c  # now beta_k F_k R_k: what reaches vertex k from later on
        d_rho[s] += delta * beta * g * emission  # beta_k dC_k/d rho
        d_emission += delta * beta * rho[s] * g  # beta_k dC_k/dE
        d_rho[s] += delta * remaining / rho[s]  # beta_k dF_k/d rho R_k, dF/d rho = 1
        beta *= rho[s]
    d_emission += delta * beta * last_hit_weight
    return d_rho, d_emission


# The same path on minidiff's tape, for reference.
rho_leaf = md.Tensor(rho.copy(), requires_grad=True)
emission_leaf = md.Tensor(np.array(emission), requires_grad=True)
beta, taped = md.Tensor(np.array(1.0)), md.Tensor(np.array(0.0))
for s, g in zip(surfaces, geometry, strict=True):
    taped = taped + beta * rho_leaf[s] * g * emission_leaf
    beta = beta * rho_leaf[s]
taped = taped + beta * last_hit_weight * emission_leaf
delta = 0.8  # the loss's derivative with respect to this path's pixel
(delta * taped).backward()
by_hand_rho, by_hand_emission = path_adjoint(rho, emission, delta)
replay_difference = max(
    np.abs(by_hand_rho - rho_leaf.grad).max() / np.abs(rho_leaf.grad).max(),
    abs(by_hand_emission - float(emission_leaf.grad)) / abs(float(emission_leaf.grad)),
)
print(f"L = {path_radiance(rho, emission):.6f}; by hand d/d rho {by_hand_rho.round(6)}, "
      f"d/dE {by_hand_emission:.6f}; tape {rho_leaf.grad.round(6)}, "
      f"{float(emission_leaf.grad):.6f}; relative difference {replay_difference:.1e}")  # fmt: skip

# %% [markdown]
# The hand-written adjoint gives the tape's gradient to `1e-14`
# <!-- check: replay_difference < --> relative, with two walks along the path and a
# handful of numbers in memory, where the tape recorded every product. Surface 0 is visited
# twice: its derivative collects both visits' shares, as a tape's would.
#
# The library does the same on real scenes, and its tests hold it to the tape
# (`tests/render/path/test_replay.py`, `test_window.py`). Here, the left wall's albedo
# and the lamp's position on the Cornell box, by the tape and by the default replay:


# %%
def box_gradient(gradient: str, parameter: str) -> np.ndarray:
    room, p = room_with(parameter)
    image = render_path(room, spp=8, max_depth=4, seed=3, gradient=gradient)
    md.mean(image * image).backward()
    return p.grad


library_replay_difference = max(
    float(np.abs(box_gradient("replay", name) - box_gradient("tape", name)).max()
          / np.abs(box_gradient("tape", name)).max())
    for name in ("albedo", "lamp")
)  # fmt: skip
print(f"replay against the tape, Cornell box: {library_replay_difference:.1e} (relative)")

# %% [markdown]
# They agree to `1e-12` <!-- check: library_replay_difference < --> (relative). One
# detail differs from the hand-written replay above: dividing `remaining` by `ρ` fails
# where a channel's albedo is 0 (a pure red wall has no green). The library's compiled
# replay never divides: its reverse sweep is reverse mode through the path's product of
# factors, which gets `R_k` by the recursion `R_k = C_{k+1} + F_{k+1} R_{k+1}` (Exercise
# 1 writes it by hand) from the values it holds for the one path being replayed; the
# replay by windows on the tape divides, and where a
# factor is 0 it gathers `R_k` from the later windows and builds that window again at the
# end (`docs/path_tracing.md`, `render/path/gradient/replay.py`). Mitsuba's `prb`
# divides and takes the inverse of a zero as 0, which drops that term. Exercise 1 asks
# why that matters.
#
# ## 4. Attached or detached samples
#
# Every estimate here is `f(x) / p(x)` for a sample `x` drawn with density `p`. When the
# density depends on θ (a glossy lobe sampled by its own shape, whose exponent is being
# fitted), there are two consistent ways to differentiate, and one tempting wrong one.
# Take `I(θ) = ∫₀¹ (θ + 1) x^θ cos x dx`, sampled by the lobe itself,
# `p_θ(x) = (θ + 1) x^θ`, `x = u^(1/(θ+1))` for uniform `u`:
#
# * **attached**: the sample moves with θ (`x(u, θ)`), and the estimate `f/p = cos x(u, θ)`
#   is differentiated through the sampling map: `−sin x · ∂x/∂θ`;
# * **detached**: the sample is a fixed number, `p` a constant; the derivative is
#   `(∂f/∂θ)(x) / p(x) = cos x · (1/(θ+1) + ln x)`;
# * **wrong**: the sample fixed *and* `p` differentiated with `f`: `f/p = cos x` does not
#   depend on θ at all, and the gradient is zero.

# %%
theta = 3.0
exact_derivative = quad(lambda x: x**theta * math.cos(x) * (1 + (theta + 1) * math.log(x)), 0, 1)[0]
u = uniform(14, np.arange(200_000), 0)
x = u ** (1 / (theta + 1))
attached = (
    -np.sin(x) * x * np.log(u) * (-1 / (theta + 1) ** 2)
)  # d x / d theta = x ln u (-1/(θ+1)²)
detached = np.cos(x) * (1 / (theta + 1) + np.log(x))
sample_errors = {}
for name, estimate in (("attached", attached), ("detached", detached)):
    standard_error = estimate.std() / math.sqrt(len(estimate))
    sample_errors[name] = abs(estimate.mean() - exact_derivative) / standard_error
    print(f"{name}: {estimate.mean():.5f} ± {standard_error:.5f} (exact {exact_derivative:.5f}), "
          f"std of one sample {estimate.std():.4f}")  # fmt: skip
worst_in_errors = max(sample_errors.values())
variance_ratio = float(detached.var() / attached.var())

# %% [markdown]
# Both agree with the exact derivative, `-0.02526` <!-- check: exact_derivative -->, to
# within `3` <!-- check: worst_in_errors < --> standard errors. Their noise differs a lot:
# here the detached estimate's variance is more than `100` <!-- check: variance_ratio > -->
# times the attached one's (`ln x` is large where the lobe puts few samples). That is not a
# rule: it depends on the integrand, and attached sampling has its own costs (the sampling
# map must be differentiable, and the samples move, so visibility can change under them).
# The wrong one gives 0.
#
# The library is **detached**: `render/path/gradient/transport.py` writes every sampled vertex as a
# fixed place on its surface and every density as a constant, and differentiates `f`,
# the cosines and the change of measure. A material's lobe then moves under its fixed
# samples, and the direction's *density* never needs a derivative. Mitsuba's `prb` is
# detached too; attached sampling is what you need for ideal mirrors and glass, whose
# `f` is a delta function and cannot be differentiated at a fixed direction (the library
# follows mirrors' reflected rays instead: they are deterministic).

# %%
print(f"elapsed {time.perf_counter() - lesson_start:.1f} s; figures in {OUT}")

# %% [markdown]
# ## Exercises
#
# 1. **A wall with no green.** Set `rho[1] = 0` in the path model. What does
#    `path_adjoint` return for `d/d rho[1]`, and what does the tape? Write
#    `path_adjoint_recursive`, which keeps `(C_k, F_k)` for each vertex of the path and
#    computes `R_k` backwards by `R_k = C_{k+1} + F_{k+1} R_{k+1}`; check it against the tape
#    with and without the zero.
# 2. **A moving lamp.** Let the geometry factors depend on the lamp's distance `d`,
#    `g_k = a_k / d²`, and add `d/dd` to the hand-written adjoint (only the `C_k` depend on
#    `d`). Check against the tape.
# 3. **Memory at depth.** Extend the depth sweep of section 1 to `max_depth` 32 for the
#    tape and the lamp's compiled replay. Which one grows, by how much, and what grows in the
#    replay (see `docs/path_tracing.md`)?
#
# Solutions: `lessons/solutions/14_path_replay.py`.
