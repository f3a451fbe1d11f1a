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
# Lessons 4-6 built the renderer as a chain of NumPy passes: each step takes whole arrays
# and returns whole arrays, and minidiff's tape records the ones that touch a parameter.
# That is the readable way, and it stays the library's reference. It is not the fast way:
# every pass reads its inputs from memory and writes a new array back, one core does all of
# it, and Python decides between passes what to call next. The library therefore grew
# compiled, parallel Numba kernels (Lam, Pitrou and Seibert 2015) *beside* the tape
# (`docs/architecture.md`):
#
# * `render/shade/compiled.py`: `shade_hit`, one camera hit's whole shading (the ray,
#   Möller-Trumbore, the normal, every light) as scalar arithmetic;
# * `render/shade/fused.py`: a render that nothing differentiates in two parallel passes,
#   `shade_hit` per hit, then the film per pixel;
# * `render/shade/adjoint.py` and `adjoint_kernels.py`: a render whose hits move, as one
#   tape node whose backward re-evaluates every hit and carries its gradient back by hand.
#
# This lesson walks the same road on a small scale: **measure** where a render's time goes;
# rewrite one stage as a kernel **tied to its plain version by a check**; make the kernel's
# sums **independent of the thread count**, bit for bit; know what **compiling** costs.
# Timings are printed, never checked (they depend on the machine and on what else runs on
# it); what is checked is what must hold everywhere: agreement, bits, counts and bytes.

# %%
import collections
import cProfile
import math
import pstats
import time
import tracemalloc

import numba
import numpy as np
from course import figures_folder, save_and_show
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import NullFormatter

import minidiff as md
import render
from render.scene.camera import primary_rays
from render.shade import adjoint, adjoint_kernels, compiled, fused
from render.shade.lighting import shade_surface
from render.shade.surface import surface_at

# This lesson's figures go to out/lessons/16_compiled_kernels/ (or under $LESSONS_OUT).
OUT = figures_folder("16_compiled_kernels")
lesson_start = time.perf_counter()
# Numba's parallel loops run on at most NUMBA_NUM_THREADS threads (the cores, by default).
MOST_THREADS = numba.config.NUMBA_NUM_THREADS
TWO = min(2, MOST_THREADS)


def median_ms(function, repeats: int = 7) -> float:
    """The median wall time of ``repeats`` calls of ``function()``, in milliseconds: the
    median, because a shared machine's timings have a long tail of interrupted runs."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return 1000 * float(np.median(times))


def on_threads(threads: int, function):
    """``function()`` with Numba's parallel loops on ``threads`` threads; the count before
    is restored afterwards."""
    before = numba.get_num_threads()
    numba.set_num_threads(threads)
    try:
        return function()
    finally:
        numba.set_num_threads(before)


# %% [markdown]
# ## 1. Where does a render's time go?
#
# Measure before you optimise. The paper's teapot on its ground, 128 × 128, with the light's
# *position* differentiated: the library's router (`render.shade.adjoint.route`) sends a
# render where only lights or materials move to the tape, so every shading operation that
# depends on the light is a recorded NumPy pass, and `backward` runs each one's VJP. One
# optimisation step (render, loss, backward) under Python's profiler, `cProfile`:
#
# * it counts every Python-level call; **`ncalls`** is how often a function ran,
#   **`tottime`** the time in its own lines, **`cumtime`** that plus everything it called;
# * a compiled Numba kernel is *one* opaque call: its whole time is its `tottime`, nothing
#   inside it is broken down (to look inside, time the kernel's parts yourself);
# * the profiler's bookkeeping slows down code that makes many small calls more than code
#   that makes few big ones, so its shares are a guide; confirm with `time.perf_counter`.
#
# The profile runs on **one thread**. A profile of a parallel program mixes work with
# waiting: on a busy machine a parallel loop ends when its slowest thread ends, and a thread
# the operating system has descheduled makes the others wait. Work first, scaling later.

# %%
scene = render.paper_scene(128, 128, ground=True)
light = scene.lights[0]
light.position.requires_grad = True
route_light = adjoint.route(scene, pairs=False, max_bounces=2)


def taped_step():
    """One optimisation step on the tape: render, loss, backward."""
    light.position.grad = None
    image = render.render(scene, reuse_visibility=False)  # every step traced anew
    md.mean(image * image).backward()


# Each pipeline step (docs/architecture.md) is one function: its cumtime is the step's time.
STAGES = {
    ("visibility.py", "trace_visibility"): "1 visibility (Numba kernels)",
    ("hits.py", "shade_camera_hits"): "2-3 surfaces, shading (tape)",
    ("film.py", "image_from_hits"): "5 film (tape)",
    ("tensor.py", "backward"): "backward (the tape's VJPs)",
}
STEPS = 3


def profile_steps() -> pstats.Stats:
    taped_step()  # the first call loads (or compiles) the kernels and fills the caches
    profiler = cProfile.Profile()
    profiler.enable()
    for _ in range(STEPS):
        taped_step()
    profiler.disable()
    return pstats.Stats(profiler).strip_dirs()


stats = on_threads(1, profile_steps)
stage_ms = {}
for (filename, _, function), (_, _, _, cumtime, _) in stats.stats.items():
    if (filename, function) in STAGES:
        stage_ms[STAGES[filename, function]] = 1000 * cumtime / STEPS
profile_ms = 1000 * stats.total_tt / STEPS
stage_ms["everything else"] = profile_ms - sum(stage_ms.values())
# Every minidiff primitive, on the tape or not, passes its result through `record`.
primitive_calls = sum(
    ncalls for (filename, _, function), (_, ncalls, *_) in stats.stats.items()
    if (filename, function) == ("tensor.py", "record")
) // STEPS  # fmt: skip
print(f"route: {route_light}; one step, one thread, under the profiler: {profile_ms:.1f} ms")
for stage, ms in sorted(stage_ms.items(), key=lambda kv: -kv[1]):
    print(f"  {stage:32s} {ms:7.2f} ms  {100 * ms / profile_ms:5.1f} %")
slowest_stage = max(stage_ms, key=stage_ms.get)
print(f"the slowest stage here: {slowest_stage}")
stats.sort_stats("tottime").print_stats(10)

# %% [markdown]
# Read the stage table first, then the functions. The stage table (printed above, this
# machine's numbers) shows how the step's time divides between the compiled visibility and
# the tape's passes (the shading forward and the VJPs in `backward`); on our runs each was a
# sizeable share, the film a few per cent at most. In the function table look for two
# patterns:
#
# * few calls with a large `tottime` and a large `percall`: a big pass over arrays or a
#   Numba kernel (names such as `closest_hit_bvh`, `_hits_along_rays`: the BVH and the
#   rasteriser). A NumPy pass there is a candidate for a kernel;
# * many calls with a tiny `percall` (minidiff's `record`, `_arithmetic`, NumPy's
#   `reduce`): Python's overhead per operation. Compiling does not help one call; doing
#   fewer of them does, and that is what a fused kernel does.
#
# How many operations does the tape hold? A tensor's `node` names the operation that made
# it and the tensors it read (`node.inputs`); walking back from the loss visits every
# recorded operation once. Some are *views*: a `reshape` returns the same memory seen with
# another shape, and writes no array.


# %%
def tape_nodes(output: md.Tensor) -> tuple[collections.Counter, collections.Counter]:
    """The operations on the tape that ``output`` depends on, counted by name, and those
    of them whose result is a view of an input (it shares the input's memory)."""
    names, views, seen, stack = collections.Counter(), collections.Counter(), set(), [output]
    while stack:
        tensor = stack.pop()
        node = tensor.node
        if node is None or id(node) in seen:
            continue
        seen.add(id(node))
        names[node.name] += 1
        if any(np.may_share_memory(tensor.data, x.data) for x in node.inputs):
            views[node.name] += 1
        stack.extend(node.inputs)
    return names, views


image = render.render(scene, reuse_visibility=False)
light_nodes, light_views = tape_nodes(md.mean(image * image))
taped_image = image.data.copy()
taped_nodes = sum(light_nodes.values())
taped_views = sum(light_views.values())
print(f"light moves: {taped_nodes} nodes on the tape: {dict(light_nodes)}; views: "
      f"{dict(light_views)}; minidiff primitives called per step: {primitive_calls}")  # fmt: skip

# The teapot's vertices move instead: the router takes one node with a compiled adjoint.
light.position.requires_grad = False
vertices = scene.meshes[0].vertices
vertices.requires_grad = True
route_vertices = adjoint.route(scene, pairs=False, max_bounces=2)
image = render.render(scene, reuse_visibility=False)
vertex_nodes = tape_nodes(md.mean(image * image))[0]
node_passes = sum(vertex_nodes.values())
print(f"vertices move (route {route_vertices!r}): {node_passes} nodes: {dict(vertex_nodes)}")
vertices.requires_grad = False

# Nothing differentiated: steps 2, 3 and 5 in fused.py's two compiled passes, no tape.
route_plain = adjoint.route(scene, pairs=False, max_bounces=2)
plain_image = render.render(scene, reuse_visibility=False).data
fused_values_differ = int(np.count_nonzero(plain_image != taped_image))
image_values = plain_image.size
print(f"route {route_plain!r}: {fused_values_differ} of {plain_image.size} values differ "
      f"from the taped image")  # fmt: skip

# %% [markdown]
# With the light differentiated, the loss depends on `27` <!-- check: taped_nodes --> tape
# nodes, recorded operations. `3` <!-- check: taped_views --> of them are `reshape`s, views
# that write no array; each of the others writes one array forward, and `backward` runs
# every node's VJP, which writes the gradients of its inputs. The tape is not all of the
# NumPy work, though: the profile counts `81` <!-- check: primitive_calls --> calls of
# minidiff's primitives per step (every primitive passes its result through `record`, whose
# `ncalls` that is), because the operations that touch no parameter, such as the hits'
# surfaces, run through the same primitives without a node, and some primitives are
# several NumPy operations inside (`normalize`, `cross`). When the teapot's vertices move,
# the router picks `"node"`, and the whole of steps 2, 3 and 5 is one recorded operation,
# `shaded_image`: the loss depends on `3` <!-- check: node_passes --> nodes (that node,
# `image * image`, `mean`). Its forward is
# `fused.image_values`, its backward `adjoint_kernels.backward_rows`: every hit re-evaluated
# and its gradient carried back by a hand-written adjoint of the whole routine, instead of a
# tape of its operations (the idea of lesson 14's compiled replay, applied to shading).
#
# With nothing differentiated the render takes the fused passes, and `0`
# <!-- check: fused_values_differ --> of the `49,152` <!-- check: image_values --> values
# differ from the taped image: the compiled code does each hit's arithmetic in the tape's
# order, operation for operation, so the bits agree. The library holds itself to that in
# `tests/render/shade/test_fused.py` (`test_the_paper_scene_gives_the_taped_image`: the same
# bits; `test_the_fused_passes_give_the_taped_image`: random scenes with specular lobes and
# several samples per pixel, to 8 units in the last place of the largest value),
# `test_compiled_shading.py` (each hit's colour against the taped `shade_mesh`) and
# `test_adjoint.py` (the node's gradients against the tape's `backward`, for every kind of
# parameter). Where can the last bits differ, then? Measured, three candidates:


# %%
@numba.njit
def numba_power(x, exponent):
    """x ** exponent (n,) element by element, as the compiled shading computes a lobe."""
    out = np.empty_like(x)
    for i in range(x.shape[0]):
        out[i] = x[i] ** exponent
    return out


@numba.njit
def multiply_add(a, b, c):
    return a * b + c


@numba.njit(fastmath=True)
def multiply_add_fast(a, b, c):
    return a * b + c


bases = np.random.default_rng(0).uniform(0.0, 1.0, 100_000)
square_values_differ = int(np.count_nonzero(np.power(bases, 2.0) != numba_power(bases, 2.0)))
power_values_differ = int(np.count_nonzero(np.power(bases, 7.3) != numba_power(bases, 7.3)))
# (1 + 2^-30)² = 1 + 2^-29 + 2^-60: rounded, the 2^-60 is lost, unless a fused
# multiply-add keeps the exact product until the addition.
near_one = 1.0 + 2.0**-30
fused_multiply_adds = int(multiply_add(near_one, near_one, -(1.0 + 2.0**-29)) != 0.0)
fastmath_result = multiply_add_fast(near_one, near_one, -(1.0 + 2.0**-29))
# Several samples per pixel: the film sums a pixel's samples in its own order.
small = render.paper_scene(48, 48, ground=True)
small.background = md.tensor([0.3, 0.3, 0.3])  # (black would add zeros: no rounding)
fused_spp4 = render.render(small, spp=4, reuse_visibility=False).data
small.lights[0].intensity.requires_grad = True  # the tape's code (the values do not change)
taped_spp4 = render.render(small, spp=4, reuse_visibility=False).data
spp4_values_differ = int(np.count_nonzero(fused_spp4 != taped_spp4))
spp4_largest_ulps = float(
    np.abs(fused_spp4 - taped_spp4).max() / (np.finfo(float).eps * np.abs(taped_spp4).max())
)
avx512 = bool(np._core._multiarray_umath.__cpu_features__.get("AVX512_SKX"))
print(f"of {len(bases):,} bases: x ** 2.0 differs in {square_values_differ}, x ** 7.3 in "
      f"{power_values_differ} (NumPy against Numba; AVX-512 here: {avx512}); a * b + c fused: "
      f"{fused_multiply_adds} (with fastmath: {fastmath_result!r}); 4 spp: "
      f"{spp4_values_differ} values differ, at most {spp4_largest_ulps:.2f} ulp of the "
      f"largest")  # fmt: skip

# %% [markdown]
# * **Powers.** A specular lobe is `cos^shininess`. NumPy computes `x ** 2.0` as `x · x`,
#   the compiled code calls the C library's `pow`, and the two round differently: here
#   `x ** 2.0` differs in more than `50` <!-- check: square_values_differ > --> of 100,000
#   random bases (printed). For other exponents NumPy calls the same C `pow`, and on a processor
#   without AVX-512 (such as the one printed above) the bits agree; with AVX-512, NumPy's
#   `power`, `exp`, `log` and friends run its own vectorised (SVML) routines, which round
#   differently from the C library.
# * **Fused multiply-add.** A processor's FMA instruction computes `a · b + c` with one
#   rounding instead of two. Numba does not contract `a * b + c` into one unless `fastmath`
#   allows it: `(1 + 2⁻³⁰)² − (1 + 2⁻²⁹)` is `0` in plain Numba, as in NumPy
#   (`0` <!-- check: fused_multiply_adds --> fused), while the `fastmath` version
#   may keep the `2⁻⁶⁰` (printed). The library's kernels do not set `fastmath`.
# * **The order of a sum.** With several samples per pixel the compiled film adds a
#   pixel's samples, the background's among them, in one loop and scales the total once;
#   the tape's film (`render/film.py`) scales the sum of the hits, then adds the
#   background times the share of samples that missed. Where a pixel's samples both hit
#   and miss, the roundings differ: at 4 samples per pixel `41`
#   <!-- check: spp4_values_differ --> of the values of the paper scene differ (48 × 48,
#   a grey background, no specular lobe), all by less than `1`
#   <!-- check: spp4_largest_ulps < --> unit in the last place of the largest value. In
#   the test's random scenes this is the difference that shows at 4 samples, with their
#   lobes or without; at one sample their images are the same bits.
#
# ## 2. One stage, two ways
#
# The stage: Lambert shading under a point light with a shadow factor, the only term the
# paper scene has (`render/shade/lighting.py`). For a hit at `x` with unit normal `n`
# (facing the ray), albedo `ρ`, a light of intensity `I` at `p`, and `lit` 1 or 0 (the
# shadow ray's verdict):
#
#     L = ρ/π · I · max(n · ω, 0) / r² · lit,   with o = p − x, r² = o · o, ω = o / r.
#
# The hits are real: the camera hits of a 256 × 256 render, their surfaces recomputed by
# the library's `surface_at` (off the tape) from the rays of `primary_rays`, and the shadow
# verdicts from `RenderInfo.lit`.

# %%
view = render.paper_scene(256, 256, ground=True)
view_image, info = render.render(view, return_info=True)
eye, directions = primary_rays(view.camera)
prim_id, lit_ray = info.prim_id.reshape(-1), info.lit[0].reshape(-1)
firsts = np.cumsum([0] + [mesh.num_faces for mesh in view.meshes])
rays, points, normals, albedo, lit, library_colour = [], [], [], [], [], []
with md.no_grad():
    for mesh, first, stop in zip(view.meshes, firsts[:-1], firsts[1:], strict=True):
        on_mesh = np.flatnonzero((prim_id >= first) & (prim_id < stop))
        surface = surface_at(mesh, prim_id[on_mesh] - first, md.tensor(eye),
                             md.tensor(directions[on_mesh]))  # fmt: skip
        mask = lit_ray[on_mesh].astype(np.float64)
        rays.append(on_mesh)
        points.append(surface.points.data)
        normals.append(surface.normals.data)
        albedo.append(np.broadcast_to(mesh.material.albedo.data, (len(on_mesh), 3)))
        lit.append(mask)
        # The library's taped shading of the same hits (values only, under no_grad).
        library_colour.append(shade_surface(surface, mesh.material, view.lights, [mask])[0].data)
rays, points, normals, albedo, lit, library_colour = (
    np.concatenate(parts) for parts in (rays, points, normals, albedo, lit, library_colour)
)
position = view.lights[0].position.data
intensity = float(view.lights[0].intensity.data)
n_hits = len(rays)
print(f"{n_hits} hits on {len(view.meshes)} meshes; {int(lit.sum())} of them lit")

# %% [markdown]
# **The NumPy passes**, in the order of operations of the library's taped code. Every line
# writes a new array; `new` keeps them in a list so that we can count them.


# %%
def lambert_passes(points, normals, albedo, position, intensity, lit, keep=None, clock=None):
    """(k, 3) radiance of k hits (points, unit normals facing the rays, albedo: (k, 3);
    lit (k,) 1.0 or 0.0) under a point light at ``position`` (3,) of ``intensity``, as
    NumPy passes. Each array a pass writes is appended to ``keep`` (a list) if given, and
    the time it was done to ``clock`` (a list)."""

    def new(array):
        if keep is not None:
            keep.append(array)
        if clock is not None:
            clock.append(time.perf_counter())
        return array

    offset = new(position - points)  # (k, 3)
    distance_sq = new(np.sum(new(offset * offset), axis=1))  # (k, 3), then (k,)
    irradiance = new(intensity / distance_sq)  # (k,)
    inverse = new(1.0 / new(np.sqrt(distance_sq)))  # (k,), (k,)
    towards = new(offset * inverse[:, None])  # (k, 3): a view costs nothing, a product does
    cosine = new(np.maximum(new(np.sum(new(normals * towards), axis=1)), 0.0))
    scalar = new(new(irradiance * cosine) * lit)  # (k,), (k,)
    return new(scalar[:, None] * new(albedo * (1.0 / math.pi)))  # (k, 3), (k, 3)


# %% [markdown]
# **The kernel.** One loop over the hits; each hit's intermediate numbers are scalars that
# live in the processor's registers, and `numba.prange` shares the hits among the threads.
# Every hit writes only its own row, so the threads need no coordination. The arithmetic is
# written in the same order as the passes: `o0 * o0 + o1 * o1 + o2 * o2` adds left to right
# as `np.sum` over an axis of three does, and Numba does not fuse `a * b + c` into one
# rounding (a fused multiply-add) unless `fastmath` allows it. `error_model="numpy"` makes a
# division by zero give `inf` as in NumPy instead of raising (the library's kernels set it:
# raising needs a check on every division).


# %%
@numba.njit(parallel=True, error_model="numpy")
def lambert_kernel(points, normals, albedo, position, intensity, lit, out):
    """``lambert_passes``' radiance written into ``out`` (k, 3), one hit per iteration."""
    for i in numba.prange(points.shape[0]):
        o0 = position[0] - points[i, 0]
        o1 = position[1] - points[i, 1]
        o2 = position[2] - points[i, 2]
        distance_sq = o0 * o0 + o1 * o1 + o2 * o2
        irradiance = intensity / distance_sq
        inverse = 1.0 / math.sqrt(distance_sq)
        cosine = (normals[i, 0] * (o0 * inverse) + normals[i, 1] * (o1 * inverse)
                  + normals[i, 2] * (o2 * inverse))  # fmt: skip
        scalar = irradiance * max(cosine, 0.0) * lit[i]
        for c in range(3):
            out[i, c] = scalar * (albedo[i, c] * (1.0 / math.pi))


args = (points, normals, albedo, position, intensity, lit)
kernel_radiance = np.empty((n_hits, 3))
start = time.perf_counter()
lambert_kernel(*args, kernel_radiance)  # the first call compiles
first_call_s = time.perf_counter() - start
start = time.perf_counter()
lambert_kernel(*args, kernel_radiance)
second_call_ms = 1000 * (time.perf_counter() - start)

passes = []
passes_radiance = lambert_passes(*args, keep=passes)
largest = np.abs(passes_radiance).max()
kernel_relative_difference = float(np.abs(kernel_radiance - passes_radiance).max() / largest)
kernel_values_differ = int(np.count_nonzero(kernel_radiance != passes_radiance))
library_values_differ = int(np.count_nonzero(passes_radiance != library_colour))
# Against the rendered image: its rays' directions come from another formula (see below).
image_relative_difference = float(
    np.abs(kernel_radiance - view_image.data.reshape(-1, 3)[rays]).max() / largest
)
print(f"kernel's first call {first_call_s:.2f} s (compiling), second {second_call_ms:.2f} ms")
print(
    f"kernel vs passes: largest difference {kernel_relative_difference:.1e} of the "
    f"largest value, {kernel_values_differ} values differ; passes vs shade_surface: "
    f"{library_values_differ} differ; kernel vs the image {image_relative_difference:.1e}"
)

# %% [markdown]
# **The check that ties them.** The kernel is worth having only if it computes what the
# plain version computes, and the plain version is the one a reader checks against the
# formula (and the tape's tests check its derivatives). So the first thing a kernel gets is
# a check against its plain twin. Here the largest difference is below `1e-12`
# <!-- check: kernel_relative_difference < --> of the largest value, and in fact `0`
# <!-- check: kernel_values_differ --> of the values differ in any bit: both do the same
# correctly rounded IEEE operations in the same order. The passes in turn give the
# library's taped `shade_surface` bit for bit (`0` <!-- check: library_values_differ -->
# values differ). Against the rendered image the kernel is within `1e-12`
# <!-- check: image_relative_difference < --> but not always the same bits: the renderer
# builds each camera ray's direction as `x·right + y·up + forward` from the hit's
# image-plane point, `primary_rays` by another formula that rounds differently, so the
# *inputs* differ in their last bits, not the shading. Write `dx * dx + (dy * dy + dz * dz)`
# in the kernel and some values move by a unit in the last place too; that is why a test
# that allows no difference states the order of operations it relies on, and one that
# allows a few units in the last place says where they come from.
#
# **What the passes cost in memory.** The passes wrote these arrays:

# %%
numpy_passes = len(passes)
result_bytes = passes_radiance.nbytes
temporary_bytes = sum(a.nbytes for a in passes) - result_bytes
temporary_bytes_per_hit = temporary_bytes // n_hits
result_bytes_per_hit = result_bytes // n_hits
wide_temporaries = sum(a.ndim == 2 for a in passes) - 1  # (k, 3), less the result
narrow_temporaries = sum(a.ndim == 1 for a in passes)  # (k,)
written_bytes_per_hit = temporary_bytes_per_hit + result_bytes_per_hit
tracemalloc.start()
lambert_passes(*args)
numpy_peak = tracemalloc.get_traced_memory()[1]
tracemalloc.stop()
tracemalloc.start()
lambert_kernel(*args, kernel_radiance)
kernel_peak = tracemalloc.get_traced_memory()[1]
tracemalloc.stop()
peak_over_result = numpy_peak / result_bytes
print(
    f"{numpy_passes} arrays written: {temporary_bytes / 1e6:.2f} MB of temporaries "
    f"({temporary_bytes_per_hit} bytes a hit) besides the {result_bytes / 1e6:.2f} MB "
    f"result; peak {numpy_peak / 1e6:.2f} MB; during the kernel's call {kernel_peak} bytes"
)
numpy_ms = median_ms(lambda: lambert_passes(*args))
# A profile of the passes: each pass's time, from the clock `new` keeps (medians of 15).
PASS_NAMES = ("position - points", "offset * offset", "np.sum(axis=1)", "intensity / r²",
              "sqrt", "1 / sqrt", "offset * inverse", "normals * towards", "np.sum(axis=1) ",
              "maximum", "irradiance * cosine", "* lit", "albedo / π",
              "scalar * (albedo / π)")  # fmt: skip
clocks = []
for _ in range(15):
    clock = [time.perf_counter()]
    lambert_passes(*args, clock=clock)
    clocks.append(np.diff(clock))
pass_ms = dict(zip(PASS_NAMES, 1000 * np.median(clocks, axis=0), strict=True))
sums_share = (pass_ms["np.sum(axis=1)"] + pass_ms["np.sum(axis=1) "]) / sum(pass_ms.values())
for name, ms in pass_ms.items():
    print(f"  {name:24s} {ms:6.3f} ms")
print(f"the two sums over an axis of three: {sums_share:.0%} of the passes' time")
# The same sum written as three columns: the same additions in the same order.
offset = position - points
columns_sum = (
    offset[:, 0] * offset[:, 0] + offset[:, 1] * offset[:, 1] + offset[:, 2] * offset[:, 2]
)
columns_values_differ = int(np.count_nonzero(columns_sum != np.sum(offset * offset, axis=1)))
axis_sum_ms = median_ms(lambda: np.sum(offset * offset, axis=1))
columns_sum_ms = median_ms(
    lambda: offset[:, 0] * offset[:, 0] + offset[:, 1] * offset[:, 1] + offset[:, 2] * offset[:, 2]
)
print(f"r² by np.sum(axis=1) {axis_sum_ms:.3f} ms, by columns {columns_sum_ms:.3f} ms "
      f"({columns_values_differ} values differ)")  # fmt: skip
numpy_peak_mb = numpy_peak / 1e6
kernel_ms = {t: on_threads(t, lambda: median_ms(lambda: lambert_kernel(*args, kernel_radiance)))
             for t in sorted({1, TWO})}  # fmt: skip
print(
    f"medians: NumPy passes {numpy_ms:.2f} ms; kernel "
    + ", ".join(f"{ms:.3f} ms on {t} thread(s)" for t, ms in kernel_ms.items())
)

# %% [markdown]
# The passes write `14` <!-- check: numpy_passes --> arrays: the result and `184`
# <!-- check: temporary_bytes_per_hit --> bytes of temporaries per hit, more than seven
# times the result's `24` <!-- check: result_bytes_per_hit --> (`5`
# <!-- check: wide_temporaries --> (k, 3) arrays of 24 bytes a hit, `8`
# <!-- check: narrow_temporaries --> (k,) arrays of 8). Each one is written to memory and
# read back by the next pass. Not all are alive at once: the peak of what the passes hold,
# measured by `tracemalloc`, is more than `5` <!-- check: peak_over_result > --> times the
# result's bytes (printed above), because each temporary is freed as soon as nothing refers
# to it. The kernel
# allocates no array at all: `tracemalloc` sees less than `1000`
# <!-- check: kernel_peak < --> bytes during its call (the call's own small Python
# objects); it writes the result, which the caller allocated, and nothing else.
#
# Where does the passes' time go? The profile of the passes (printed above: each pass's
# median, from the clock `new` keeps) answers it, and a common guess does not. The guess is
# memory traffic: `208` <!-- check: written_bytes_per_hit --> bytes written per hit and
# read back, against a few dozen operations, a pass that runs at the speed of memory (the
# roofline model, Williams, Waterman and Patterson 2009). But what the passes hold at once
# peaks under `6` <!-- check: numpy_peak_mb < --> MB, which fits in the last-level cache
# of a current processor (tens of MB; `lscpu` shows yours): the arrays never leave the
# cache, and main memory's bandwidth is not what limits them. The profile shows instead
# that a pass's cost follows *how* NumPy runs it. On the machine this lesson was written
# on, the two `np.sum(..., axis=1)`, 2 passes of 14, took a large share of the time
# (printed above for yours): NumPy reduces each row of three separately, with a loop set
# up per row, where an elementwise pass runs one loop over the whole array. Written as
# three columns, `o0·o0 + o1·o1 + o2·o2`, the same sum was several times faster there
# (both printed) and gives the same bits (`0`
# <!-- check: columns_values_differ --> values differ: the same additions in the same
# order). The other large shares are the (k, 3) passes, each allocating a fresh array and
# writing it once; the (k,) passes on narrow arrays cost little. The kernel avoids all of
# it: no reduction over a short axis, no array allocated, one call instead of fourteen.
#
# A second thread adds what it can on top. On a machine whose cores are busy with other
# work it may add nothing, or cost far more than it brings: a parallel loop ends when its
# slowest thread ends, and a thread waiting for a core that another process holds keeps
# everyone waiting (compare the two kernel timings printed above; on a quiet machine with a
# free core the second is the smaller).
#
# ## 3. Results that do not depend on the thread count
#
# Shading writes one result per hit. A *gradient* is a sum: the light's intensity gets a
# contribution from every hit it lights. The shading is linear in `I`, so the derivative of
# a hit's three channels' sum with respect to `I` is that sum evaluated at `I = 1`, and
# `∂(Σ image)/∂I` is the sum of those over the hits. Floating-point addition is not
# associative (Goldberg 1991): `(a + b) + c` and `a + (b + c)` can differ in the last bit,
# so a sum's bits depend on the order of its terms. Two ways to sum in parallel:
#
# * a `prange` loop with `total += x[i]`: Numba gives each thread a share of the terms and
#   adds the threads' partial sums at the end. *How many shares* depends on the thread count;
# * a fixed number of chunks, as `adjoint_kernels.backward_rows` sums its global gradients:
#   `CHUNKS` (`128` <!-- check: CHUNKS -->) contiguous chunks whatever the thread count,
#   each summed in order by one thread, then the chunks' sums added in order. The threads
#   decide only *who* sums a chunk, never which terms or in what order.


# %%
@numba.njit(parallel=True)
def sum_by_threads(x):
    """A prange reduction: each thread sums its share, then the shares are added."""
    total = 0.0
    for i in numba.prange(x.shape[0]):
        total += x[i]
    return total


@numba.njit(parallel=True)
def sum_by_chunks(x, chunks):
    """The sum of x (n,) over ``chunks`` fixed contiguous chunks: each chunk summed in order
    (the chunks in parallel), then the chunks' sums added in order."""
    n = x.shape[0]
    size = (n + chunks - 1) // chunks
    partial = np.zeros(chunks)
    for c in numba.prange(chunks):
        total = 0.0
        for i in range(c * size, min(n, (c + 1) * size)):
            total += x[i]
        partial[c] = total
    total = 0.0
    for c in range(chunks):
        total += partial[c]
    return total


def differing_bits(a: float, b: float) -> int:
    """How many of the 64 bits of two float64 numbers differ."""
    return bin(int(np.float64(a).view(np.int64) ^ np.float64(b).view(np.int64))).count("1")


CHUNKS = adjoint_kernels.CHUNKS
terms = lambert_passes(points, normals, albedo, position, 1.0, lit).sum(axis=1)  # d/dI per hit
thread_counts = sorted({1, TWO})
by_threads = [on_threads(t, lambda: sum_by_threads(terms)) for t in thread_counts]
by_chunks = [on_threads(t, lambda: sum_by_chunks(terms, CHUNKS)) for t in thread_counts]
chunked_bits_differ = differing_bits(by_chunks[0], by_chunks[-1])
prange_bits_differ = differing_bits(by_threads[0], by_threads[-1])
print(f"threads {thread_counts}: prange reduction {[v.hex() for v in by_threads]} "
      f"({prange_bits_differ} bits differ); {CHUNKS} chunks {[v.hex() for v in by_chunks]} "
      f"({chunked_bits_differ} bits differ)")  # fmt: skip

# The number of chunks, unlike the number of threads, does change the bits:
by_chunk_count = [sum_by_chunks(terms, chunks) for chunks in range(1, 9)]
distinct_sums = len(set(by_chunk_count))
print(f"1 to 8 chunks give {distinct_sums} different sums:",
      sorted({v.hex() for v in by_chunk_count}))  # fmt: skip

# The tape's gradient of the same sum (the tape sums in yet another order).
view.lights[0].intensity.requires_grad = True
md.sum(render.render(view)).backward()
tape_gradient = float(view.lights[0].intensity.grad)
view.lights[0].intensity.requires_grad = False
chunked_vs_tape = abs(by_chunks[0] - tape_gradient) / abs(tape_gradient)
print(f"d(sum of the image)/dI: chunked {by_chunks[0]:.12f}, tape {tape_gradient:.12f}")

# %% [markdown]
# The chunked sum gives the same bits on one and on two threads: `0`
# <!-- check: chunked_bits_differ --> of its 64 bits differ (the thread counts tried are
# printed; two when the machine has two cores). The `prange` reduction's bits (printed in
# hex, and how many differ) *may* change between one and two threads on your machine, or
# not: nothing promises either, and that is the problem. Splitting the same terms into 1,
# 2, ..., 8 chunks gives more than `1` <!-- check: distinct_sums > --> different sum (the
# run prints how many: 6 or 7 on the machines we tried, as the terms' last bits depend on
# NumPy's build and the CPU), so an order that follows the thread count gives bits that
# follow it too. All of them are right to
# rounding: the chunked sum is within `1e-12` <!-- check: chunked_vs_tape < --> of the
# tape's gradient `∂(Σ image)/∂I`, whose VJPs compute the same terms and add them in yet
# another order.
#
# Why insist on the same bits, when the difference is a rounding error? Because a result
# that moves with the core count makes a test flaky (pass on the laptop, fail on a 64-core
# CI runner), makes two runs of an optimisation drift apart after a few hundred steps (a last
# bit that changes an Adam step changes every later one), and hides real bugs behind "just
# rounding". The project's guide asks for *thread-count-independent results*: every
# parallel kernel that sums uses fixed chunks, or gives every output to one thread
# (`adjoint_kernels.sum_by_vertex` sums each vertex's entries in parallel over vertices;
# `fused._film` sums each pixel's samples by one thread). The reproducible-summation
# literature (Demmel and Nguyen 2015) goes further, with sums whose bits do not depend on
# the order at all; fixed chunks are the cheap version, enough when the *terms'* order is
# fixed. The tests hold the library to it: `tests/render_helpers.py`'s
# `same_bits_on_one_and_two_threads` runs a script in a new process with two Numba threads
# allowed, calls its `run()` on one and then two threads, and fails unless every array is
# identical (`tests/render/shade/test_fused.py`, `test_adjoint.py`, the edge and border
# kernels' tests, and the path tracer's `test_kernel.py`, `test_adjoint.py` and
# `test_secondary.py` use it). The same check on the library, in this process:


# %%
def node_gradients():
    """The image and the gradients of a render whose teapot moves (the "node" route) and
    whose light's intensity is differentiated."""
    small = render.paper_scene(96, 96, ground=True)
    small.meshes[0].vertices.requires_grad = True
    small.lights[0].intensity.requires_grad = True
    image = render.render(small)
    md.mean(image * image).backward()
    return [image.data, small.meshes[0].vertices.grad, small.lights[0].intensity.grad]


runs = [on_threads(t, node_gradients) for t in thread_counts]
node_values_differ = sum(
    int(np.count_nonzero(a != b)) for a, b in zip(runs[0], runs[-1], strict=True)
)
print(f"the node's image and gradients on {thread_counts} threads: "
      f"{node_values_differ} values differ")  # fmt: skip

# %% [markdown]
# `0` <!-- check: node_values_differ --> values differ between one and two threads: the
# image (`fused._shade_rays` and `fused._film`), the vertices' gradients (per-hit corner
# entries summed vertex by vertex) and the intensity's (128 chunks).
#
# ## 4. What compiling costs
#
# The kernel's first call above took `first_call_s` (printed: about a second here); its
# later calls, the medians of section 2. On the first call Numba infers the types of the
# arguments, translates the function to LLVM's intermediate language, and LLVM compiles
# that to machine code for this processor; the machine code is kept for the rest of the
# process, one version per combination of argument types (call it with float32 arrays and it
# compiles again).
#
# **Caching.** `@numba.njit(cache=True)` also writes the machine code to disk, in
# `__pycache__` beside the module (`.nbi` index and `.nbc` data files), so that the next
# process loads it instead of compiling. Every compiled function of the library carries it;
# checked here for `render/shade`:

# %%
library_functions = {
    f"{module.__name__.split('.')[-1]}.{name}": function
    for module in (compiled, fused, adjoint_kernels)
    for name, function in vars(module).items()
    if isinstance(function, numba.core.registry.CPUDispatcher)
    and function.__module__ == module.__name__
}
uncached = [name for name, f in library_functions.items() if not f._cache.__class__.__name__
            .startswith("FunctionCache")]  # fmt: skip
uncached_count = len(uncached)
inlined = [name for name, f in library_functions.items() if f.targetoptions.get("inline")]
print(f"{len(library_functions)} compiled functions in render/shade; without cache=True: "
      f"{uncached}; inlined into their callers: {inlined}")  # fmt: skip

# %% [markdown]
# `0` <!-- check: uncached_count --> of them compile on every run. This lesson's own kernels
# do not use `cache=True`: Numba finds a function's cache through the file it is defined
# in, and a lesson run as a notebook has no file of its own. Outside IPython, which Numba
# handles with a cache of its own keyed on the cell, such a function fails at its first
# call ("cannot cache function ...: no locator available"); and a cache kept for cells
# that change from one run to the next buys little. A small kernel compiles in about a
# second; a lesson can pay that.
#
# **Inlining.** `inline="always"` (the functions listed above: `shade_hit`, `camera_hit`,
# the adjoint's `_hit_adjoint`, ...) pastes a function's body into every caller at the
# level of Numba's own representation, before LLVM sees it: no call, and LLVM optimises
# the caller and the callee together. Its price is compile time, which grows faster than
# the code inlined. `docs/architecture.md` records the lesson: the boundary term's
# `edge_kernel.side_factors_kernel` traces a few shadow rays among other work, and with six
# inlined copies of the BVH traversal it took three minutes to compile on a fresh clone;
# calling one compiled traversal (`intersect.occluded_call`) instead, under half a
# minute. So the library inlines the
# traversal only into kernels that are mostly traversal (`trace/intersect.py`'s ray
# kernels), and calls it from the rest.
#
# **A stale cache.** Numba decides whether a cached kernel is still valid by *its own*
# source file's modification time and size and its own bytecode. A kernel calls other compiled
# functions (`fused._shade_rays` calls `compiled.shade_hit`), and their machine code is
# part of the kernel's, inlined or not; an edit to the module that defines them changes
# nothing Numba checks, so the next run loads the old machine code. The library therefore
# keys its kernels' cache on the sources of the `render` and `minidiff` packages: an edit
# to any of them makes every cached kernel compile again.
#
# ## The measurements in one figure

# %%
figure = Figure(figsize=(10, 3.6), dpi=100, layout="constrained")
FigureCanvasAgg(figure)
left, right = figure.subplots(1, 2, width_ratios=[1.3, 1])
names = sorted(stage_ms, key=stage_ms.get)
left.barh(names, [stage_ms[n] for n in names], color="tab:gray")
left.set_xlabel("ms per step (one thread, under cProfile)")
left.set_title(f"A taped step, 128 × 128, light moving ({taped_nodes} tape nodes)", fontsize=10)
labels = ["NumPy passes"] + [f"kernel, {t} thread{'s' if t > 1 else ''}" for t in kernel_ms]
colours = ["tab:gray"] + ["tab:blue"] * len(kernel_ms)
values = [numpy_ms, *kernel_ms.values()]
right.barh(labels, values, color=colours)
right.set_xscale("log")
right.xaxis.set_minor_formatter(NullFormatter())  # decades only: no crowded labels
right.set_xlim(min(values) / 3, max(values) * 6)
for row, ms in enumerate(values):
    right.text(ms * 1.1, row, f"{ms:.2f} ms", va="center", fontsize=9)
right.set_xlabel("median ms (log scale)")
right.set_title(f"Lambert shading of {n_hits:,} hits", fontsize=10)
save_and_show(figure, OUT / "where_time_goes.png")
print(f"elapsed {time.perf_counter() - lesson_start:.1f} s; figures in {OUT}")

# %% [markdown]
# `where_time_goes.png`: on the left the profile's stages, on the right the shading stage's
# medians, this machine's numbers (run it again on yours; they will differ, the checks
# above will not).
#
# ## Exercises
#
# 1. **Speed up one stage and measure it.** The film (step 5, `render/film.py`) as NumPy
#    passes: with `spp` samples per pixel, ray `r` in pixel `r // spp`, sample radiance
#    `radiance` (N, 3) and `prim_id` (N,) (-1: a miss, which shows the `background` (3,)),
#    `np.where(prim_id[:, None] < 0, background, radiance).reshape(-1, spp, 3).mean(axis=1)`.
#    Write it as a `prange` kernel over pixels, check it against the passes and against the
#    library's own `fused._film` (how many values differ, and why), and measure the
#    speed-up at 512 × 512 with 4 samples per pixel with `median_ms`, on one thread and on
#    two.
# 2. **A gradient as a thread-independent kernel.** Write the gradient of `Σ image` with
#    respect to the light's *position* (three sums over the hits) as one kernel: each hit's
#    derivative of `I max(n·ω, 0) lit Σρ/π / r²` in registers, summed over `CHUNKS` fixed
#    chunks. Check it against the tape's `light.position.grad` and check that it gives the
#    same bits on one and two threads.
# 3. **Why not one chunk per thread?** Replace the fixed `CHUNKS` by the thread count
#    (`sum_by_chunks(terms, numba.get_num_threads())`) and show that the sum's bits then
#    follow the thread count. What do more chunks cost, and what do they buy (time 1, 8, 128
#    and 8,192 chunks)?
#
# Solutions: `lessons/solutions/16_compiled_kernels.py`.
