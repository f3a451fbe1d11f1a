# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # Lesson 16 — From NumPy passes to a compiled kernel
#
# Lessons 4-6 built the renderer as a chain of NumPy passes: every step takes whole arrays
# and returns whole arrays, and the tape records each one. That is the readable way, and it
# stays the library's reference. It is not the fast way: each pass reads its inputs from
# memory and writes a new array back, one core does all of it, and between the passes
# Python decides what to call next. This lesson takes one stage from NumPy passes to a
# compiled, parallel Numba kernel the way the library does (`render/shade/fused.py`,
# `render/shade/adjoint_kernels.py`, `docs/architecture.md`):
#
# 1. **measure first**: profile a render and find where its time goes;
# 2. write the stage as one kernel and **tie it to the plain version by a test**;
# 3. make its result **independent of the number of threads**, bit for bit;
# 4. know what compiling costs, and when to pay it.
#
# Timings in this lesson are printed, never checked: they depend on the machine. What is
# checked is what must hold everywhere: that the two versions agree, and that the bits do
# not depend on the thread count.

# %%
import cProfile
import math
import pstats
import time
import tracemalloc
from collections import defaultdict

import numba
import numpy as np
from course import figures_folder, save_and_show
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

import minidiff as md
import render

# This lesson's figures go to out/lessons/16_numpy_to_kernels/ (or under $LESSONS_OUT).
OUT = figures_folder("16_numpy_to_kernels")
lesson_start = time.perf_counter()


def median_seconds(function, repeats: int = 7) -> float:
    """The median wall time of ``repeats`` calls of ``function()``: the median, because a
    shared machine's timings have a long tail of interrupted runs."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return float(np.median(times))


# %% [markdown]
# ## 1. Where does a render's time go?
#
# The paper's teapot on its ground, 160 × 160, rendered so that the tape records it (the
# light's intensity requires a gradient) and differentiated, under Python's profiler
# `cProfile`. The profiler counts every Python function call and the time spent in it;
# `tottime` is the time in the function's own lines, `cumtime` includes what it called.
# Two things to know when reading it:
#
# * a compiled Numba kernel is one opaque call: its time shows up as the kernel's `tottime`,
#   with nothing inside it broken down (to look inside, time the kernel's parts yourself);
# * the profiler's own bookkeeping slows down code that makes many small calls, so the
#   shares are a guide, not a measurement. Time the stages you suspect with
#   `time.perf_counter` before and after a change, and compare medians.

# %%
scene = render.paper_scene(160, 160, ground=True)
light = scene.lights[0]


def taped_step():
    """One render recorded on the tape, and its backward (a gradient for the light's
    intensity)."""
    light.intensity.requires_grad, light.intensity.grad = True, None
    image = render.render(scene, reuse_visibility=False)
    md.mean(image * image).backward()
    light.intensity.requires_grad = False


taped_step()  # the first call compiles (or loads) the kernels: keep it out of the profile
profiler = cProfile.Profile()
profiler.enable()
for _ in range(5):
    taped_step()
profiler.disable()
stats = pstats.Stats(profiler)

# Each function's own time (tottime), summed by the folder its code lives in: the folders
# are the pipeline's steps (docs/architecture.md).
by_folder = defaultdict(float)
for (filename, _, _), (_, _, tottime, _, _) in stats.stats.items():
    path = filename.replace("\\", "/")
    folder = next(
        (part for part in ("minidiff", "render/trace", "render/shade", "render/scene",
                           "render/edges", "render/film") if f"/{part}" in path),
        "NumPy and Python's built-ins",
    )  # fmt: skip
    by_folder[folder] += tottime
profile_total = sum(by_folder.values())
for folder, seconds in sorted(by_folder.items(), key=lambda kv: -kv[1]):
    print(
        f"{folder:32s} {1000 * seconds / 5:7.2f} ms a step  {100 * seconds / profile_total:5.1f} %"
    )
print()
stats.sort_stats("tottime").print_stats(8)

# %% [markdown]
# Read the table from the top. In our runs the tape's own machinery (`minidiff`:
# recording each operation, allocating its output, calling its VJP in `backward`) and
# NumPy's array passes took more than half of the time, the geometry less: the BVH
# traversal, the rasteriser and the light's view (`render/trace`) are already compiled
# kernels, each one opaque line in the profile. Among single functions, look for the ones
# called few times with a large `tottime` (a pass over big arrays: a candidate for a
# kernel) and the ones called hundreds of times with a small `percall` (Python overhead:
# a candidate for doing less, not for compiling). A recorded render pays for generality:
# every operation is a separate pass over a whole array. When nothing needs the tape, the
# library skips it: `render.render` routes a render that nothing differentiates through
# `render.shade.fused` (two compiled passes), and one whose vertices move through one tape
# node with a hand-written compiled adjoint (`render.shade.adjoint`).


# %%
def plain_step():
    return render.render(scene, reuse_visibility=False)


def recorded_render():
    light.intensity.requires_grad = True
    image = render.render(scene, reuse_visibility=False)
    light.intensity.requires_grad = False
    return image


plain_seconds = median_seconds(plain_step)
recorded_seconds = median_seconds(recorded_render)
print(f"the same image: compiled passes {1000 * plain_seconds:.1f} ms, on the tape "
      f"{1000 * recorded_seconds:.1f} ms ({recorded_seconds / plain_seconds:.1f}x)")  # fmt: skip
# The two routes must give the same image: the library's test does this check
# (tests/render/shade/test_fused.py, test_the_paper_scene_gives_the_taped_image).
fused_differing_values = int(np.count_nonzero(plain_step().data != recorded_render().data))
print(f"values that differ between the two routes: {fused_differing_values}")

# %% [markdown]
# The two routes give the same image bit for bit here: `0`
# <!-- check: fused_differing_values --> of its `76,800` <!-- check: image_values --> values
# differ. That equality is not luck: the compiled pass does each hit's arithmetic in the
# same order as the taped functions, and `tests/render/shade/test_fused.py` holds it to
# that (on the paper scene, bit for bit; on random scenes with specular lobes and several
# samples per pixel, to 8 units in the last place of the largest value, because NumPy's
# vectorised `power` and the C library's `pow` round differently).
#
# ## 2. One stage, two ways
#
# A stage small enough to read in full: Lambert shading of `N` hit points under a point
# light, with a shadow mask. Written as NumPy passes, as the taped renderer writes it
# (`render/shade/lighting.py`):

# %%
image_values = scene.camera.height * scene.camera.width * 3


def lambert_numpy(points, normals, albedo, light_position, intensity, lit):
    """(N, 3) radiance of N hit points (N, 3) with unit ``normals`` (N, 3) and ``albedo``
    (N, 3), lit by a point light (``light_position`` (3,), ``intensity`` scalar) where
    ``lit`` (N,) is True: albedo / pi * intensity * max(n . l, 0) / r^2."""
    to_light = light_position - points  # (N, 3) new array
    r2 = np.sum(to_light * to_light, axis=1)  # (N, 3) product, then (N,)
    l = to_light / np.sqrt(r2)[:, None]  # (N,) root, then (N, 3) quotient
    cos = np.maximum(np.sum(normals * l, axis=1), 0.0)  # (N, 3) product, (N,), (N,)
    scale = intensity * cos / r2 * lit  # three (N,) arrays
    return albedo / math.pi * scale[:, None]  # (N, 3), then the (N, 3) result


@numba.njit(parallel=True, error_model="numpy")
def lambert_kernel(points, normals, albedo, light_position, intensity, lit, out):
    """``lambert_numpy``'s radiance written into ``out`` (N, 3): one pass over the hits,
    each hit's arithmetic in registers, the hits shared among the threads (prange)."""
    for i in numba.prange(points.shape[0]):
        dx = light_position[0] - points[i, 0]
        dy = light_position[1] - points[i, 1]
        dz = light_position[2] - points[i, 2]
        r2 = dx * dx + dy * dy + dz * dz
        r = math.sqrt(r2)
        cos = normals[i, 0] * (dx / r) + normals[i, 1] * (dy / r) + normals[i, 2] * (dz / r)
        scale = intensity * max(cos, 0.0) / r2 * lit[i]
        for c in range(3):
            out[i, c] = albedo[i, c] / math.pi * scale


rng = np.random.default_rng(16)
n_hits = 400_000
points = rng.uniform(-1.0, 1.0, (n_hits, 3))
normals = rng.normal(size=(n_hits, 3))
normals /= np.linalg.norm(normals, axis=1, keepdims=True)
albedo = rng.uniform(0.2, 0.9, (n_hits, 3))
lit = rng.uniform(size=n_hits) < 0.8
light_position, intensity = np.array([0.5, 3.0, 2.0]), 40.0
args = (points, normals, albedo, light_position, intensity, lit)

start = time.perf_counter()
radiance_kernel = np.empty((n_hits, 3))
lambert_kernel(*args, radiance_kernel)  # the first call compiles
compile_seconds = time.perf_counter() - start
radiance_numpy = lambert_numpy(*args)
scale_of_values = np.abs(radiance_numpy).max()
kernel_difference = float(np.abs(radiance_kernel - radiance_numpy).max() / scale_of_values)
kernel_differing_values = int(np.count_nonzero(radiance_kernel != radiance_numpy))
print(f"first call (compiling): {compile_seconds:.2f} s; largest difference "
      f"{kernel_difference:.1e} of the largest value; {kernel_differing_values} of "
      f"{radiance_numpy.size} values differ in any bit")  # fmt: skip

# %% [markdown]
# **The test that ties them.** The kernel is only worth having if it computes what the
# plain version computes; the plain version is the one a reader checks against the formula,
# and the tape's property tests check its derivatives. So the first thing a kernel gets is
# a test against its plain twin, on many inputs. Here the largest difference is below
# `1e-15` <!-- check: kernel_difference < --> of the largest value, and the run printed
# above found no value that differs in any bit: both versions do the same correctly
# rounded IEEE operations in the same order (`np.sum` over an axis of three adds left to
# right, as the kernel does). That is a choice, made when the kernel is written: write
# `dx * dx + (dy * dy + dz * dz)` and some values move by a unit in the last place. A test
# allows a few units in the last place of the largest value, and fails on anything more.
#
# The library's kernels are tied the same way: `tests/render/shade/test_compiled_shading.py`
# (each hit's colour against the taped `shade_mesh`), `test_fused.py` (the image),
# `test_adjoint.py` (the compiled adjoint's gradients against the tape's `backward`), and
# `tests/render/edges/test_edge_kernel.py` (the boundary term's kernel against its NumPy
# statement, which stays callable with `compiled=False`).
#
# **What the passes cost in memory.** Each NumPy line above writes a new array. `tracemalloc`
# sees NumPy's allocations:

# %%
tracemalloc.start()
lambert_numpy(*args)
_, numpy_peak = tracemalloc.get_traced_memory()
tracemalloc.stop()
out_bytes = n_hits * 3 * 8
numpy_peak_ratio = numpy_peak / out_bytes
numpy_seconds = median_seconds(lambda: lambert_numpy(*args))
kernel_seconds = median_seconds(lambda: lambert_kernel(*args, radiance_kernel))
print(f"NumPy passes: peak {numpy_peak / 1e6:.1f} MB ({numpy_peak_ratio:.2f}x the "
      f"{out_bytes / 1e6:.1f} MB result), {1000 * numpy_seconds:.1f} ms; kernel: no "
      f"temporaries, {1000 * kernel_seconds:.1f} ms on {numba.get_num_threads()} threads "
      f"({numpy_seconds / kernel_seconds:.1f}x)")  # fmt: skip

# %% [markdown]
# At its peak the NumPy version holds `5.0` <!-- check: numpy_peak_ratio --> times the
# result's bytes in arrays: the result and the temporaries alive at the same time (the
# (N, 3) ones cost as much as the result each); it writes more than that in all, since each
# temporary is freed and another one allocated.
# The kernel writes the result and nothing else: each hit's intermediate numbers live in
# the processor's registers. That is where most of the speed-up printed above comes from
# — memory traffic, not arithmetic — and why it shows even on one thread. The threads add
# what they can on top: `prange` hands each thread a share of the hits, and since every
# hit's result depends only on its own inputs, the shares need no coordination.
#
# ## 3. Results that do not depend on the thread count
#
# Shading writes one result per hit. A *gradient* is different: many hits add into the same
# number (a light's intensity gets a contribution from every pixel it lights). Floating-point
# addition is not associative: `(a + b) + c` and `a + (b + c)` can differ in the last bit.
# So a sum's bits depend on the order of its terms. Sum 200 arrays of 10,000 numbers each
# in order, and again as two halves added at the end, which is what two threads do:


# %%
@numba.njit
def sum_in_order(x, start, stop):
    """x[start] + x[start + 1] + ... + x[stop - 1], left to right."""
    total = 0.0
    for i in range(start, stop):
        total += x[i]
    return total


arrays = rng.uniform(-1.0, 1.0, (200, 10_000))
halves_differ = sum(
    sum_in_order(x, 0, 10_000) != sum_in_order(x, 0, 5_000) + sum_in_order(x, 5_000, 10_000)
    for x in arrays
)
print(f"{halves_differ} of {len(arrays)} sums change their last bits when split in two")

# %% [markdown]
# `194` <!-- check: halves_differ --> of the 200 sums change. A `prange` loop with a
# `+=` reduction lets each thread sum its own share and then adds the shares: its result
# depends on how many threads there are (and, with dynamic scheduling, on which thread
# took which share). A gradient that changes with the machine's core count makes tests
# flaky and runs irreproducible, and the guide of this project forbids it.
#
# The cure the library uses (`render/shade/adjoint_kernels.py`): cut the terms into a
# fixed number of chunks that does not depend on the threads (128 there), sum each chunk
# in order, in parallel, and add the chunks' sums in order at the end. The threads decide
# only *who* sums a chunk, never *which* terms or in what order.

# %%
N_CHUNKS = 128


@numba.njit(parallel=True)
def sum_by_threads(x):
    """A prange reduction: each thread's share summed, then the shares added."""
    total = 0.0
    for i in numba.prange(x.shape[0]):
        total += x[i]
    return total


@numba.njit(parallel=True)
def sum_by_chunks(x):
    """The sum of x (n,) over N_CHUNKS fixed chunks: each chunk in order (in parallel),
    then the chunks' sums in order. The same bits on any number of threads."""
    n = x.shape[0]
    size = (n + N_CHUNKS - 1) // N_CHUNKS
    partial = np.zeros(N_CHUNKS)
    for c in numba.prange(N_CHUNKS):
        total = 0.0
        for i in range(c * size, min(n, (c + 1) * size)):
            total += x[i]
        partial[c] = total
    total = 0.0
    for c in range(N_CHUNKS):
        total += partial[c]
    return total


def on_threads(function, threads):
    """``function()`` run with Numba's parallel loops on ``threads`` threads (at most the
    number Numba started with); the count is restored afterwards."""
    before = numba.get_num_threads()
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    try:
        return function()
    finally:
        numba.set_num_threads(before)


big = rng.uniform(-1.0, 1.0, 1_000_003)
thread_counts = sorted({1, min(2, numba.config.NUMBA_NUM_THREADS), numba.get_num_threads()})
by_threads = [on_threads(lambda: sum_by_threads(big), t) for t in thread_counts]
by_chunks = [on_threads(lambda: sum_by_chunks(big), t) for t in thread_counts]
chunked_bits_differ = sum(value != by_chunks[0] for value in by_chunks)
print(f"threads {thread_counts}: prange reduction {[v.hex() for v in by_threads]}")
print(f"                 fixed chunks     {[v.hex() for v in by_chunks]}")

# %% [markdown]
# The chunked sum gives the same bits on every thread count tried (`0`
# <!-- check: chunked_bits_differ --> of them differ; the counts are printed above, as many
# as this machine has, at most two here and one under the test suite, which gives each of
# its worker processes one Numba thread). The `prange` reduction's bits (printed in hex)
# may or may not change from one thread to two on your machine; the point is that nothing
# promises they will not. The library checks this property for every parallel kernel that
# sums: `tests/render_helpers.py`'s `same_bits_on_one_and_two_threads` runs a script in a
# new process on one and then two threads and fails unless every array is identical (used
# by the tests of `fused`, `adjoint`, the edge and border kernels and the path tracer's
# secondary term). Results that hold on any thread count also make the *speed* safe to
# chase: a kernel can be re-blocked or re-scheduled without anyone's gradient changing.
#
# ## 4. What compiling costs
#
# The first call of `lambert_kernel` above took `compile_seconds` (printed): Numba
# translated the Python to LLVM and LLVM to machine code. The library's kernels carry
# `cache=True`, which saves the machine code under `__pycache__` beside the module, so only
# the first run on a machine pays; a kernel defined in a notebook cell has no file to cache
# beside, which is why this lesson's kernels compile on every run. Two lessons the library
# learned the hard way (`docs/architecture.md`):
#
# * compile time grows with the code a kernel inlines. A BVH traversal inlined six times
#   into one kernel took three minutes of CPU to compile; called as a function of its own,
#   compiled once, 29 s, for a 0.7 ms cost at run time;
# * Numba's cache checks only the kernel's own module: after editing a function that other
#   modules inline, delete their cached `.nbi`/`.nbc` files.

# %%
labels = ["render, tape", "render, compiled", "Lambert, NumPy", "Lambert, kernel"]
millis = [1000 * s for s in (recorded_seconds, plain_seconds, numpy_seconds, kernel_seconds)]
figure = Figure(figsize=(6.4, 3.2), dpi=100, layout="constrained")
FigureCanvasAgg(figure)
ax = figure.add_subplot()
ax.barh(labels, millis, color=["0.6", "tab:blue", "0.6", "tab:blue"])
ax.set_xlabel("median time (ms), this machine")
ax.set_title("The paper scene at 160 × 160, and Lambert shading of 400,000 hits",
             fontsize=10, loc="left")  # fmt: skip
save_and_show(figure, OUT / "stage_times.png")
print(f"elapsed {time.perf_counter() - lesson_start:.1f} s; figures in {OUT}")

# %% [markdown]
# `stage_times.png` shows the medians measured above, on whatever machine ran the lesson.
#
# ## Exercises
#
# 1. **Speed up one stage and measure it.** `render.scene.camera.camera_directions(coords,
#    right, up, forward)` computes the camera rays' directions `x·right + y·up + forward`
#    in NumPy passes. Write it as a parallel kernel, tie it to the library's function by a
#    check (same bits, or how many units in the last place and why), and measure the
#    speed-up for a million rays with `median_seconds` on one thread and on all of them.
# 2. Add the energy-normalised Blinn-Phong lobe (lesson 5) to `lambert_numpy` and
#    `lambert_kernel` (a camera position, the half vector, `specular · (s + 8) / (8π) ·
#    max(n · h, 0)^s`) and check them against each other. Why do some values now differ by
#    more than one unit in the last place (compare `np.power` with `**` in a kernel)?
# 3. Make the gradient of `md.mean(lambert(...))` with respect to `intensity` a kernel: the
#    sum over hits of `∂radiance/∂intensity`, with the thread-count-independent chunked
#    sum, and check it against minidiff's `backward` through a taped version of
#    `lambert_numpy`.
#
# Solutions: `lessons/solutions/16_numpy_to_kernels.py`.
