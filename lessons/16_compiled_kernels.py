# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # Lesson 16 — How a tape becomes a kernel
#
# Lessons 1-6 built the renderer from minidiff's primitives: each one a NumPy pass over
# whole arrays, recorded on a tape with its VJP and JVP beside it. That text is the
# library's mathematics and stays its reference. Run as it is, it is slow: every pass reads
# its inputs from memory and writes a new array, `backward` does the same again in reverse,
# and one core does all of it.
#
# The way out that Dr.Jit (Mitsuba 3), JAX and tinygrad take, and minidiff now too
# (`minidiff/compiler.py`, `docs/compiler.md`), is not to write the mathematics a second
# time in a faster language, but to **compile the text we have**:
#
# 1. **trace**: run the function once on stand-in arrays that record, for one element of
#    the batch, every scalar operation: a straight-line program (`minidiff/trace.py`,
#    `minidiff/ir.py`);
# 2. **generate**: write that program as one loop over the elements, and its derivative
#    programs, reverse (VJP) and forward (JVP), from each primitive's *scalar form*: the
#    same rule as its array VJP, one element at a time (`minidiff/codegen.py`);
# 3. **compile and cache**: LLVM turns the loop into machine code for this processor, which
#    is kept on disk by a hash of its text (`minidiff/backend.py`);
# 4. **one node**: on the tape the compiled function is a single recorded operation, whose
#    VJP and JVP call the generated kernels.
#
# The renderer's shading goes through it (`render/shade/compiled.py`: the readable
# `surface_at` and `shade_surface`, compiled). This lesson follows the road on a small
# function, then measures the library's own shading before and after. Timings are printed,
# never checked (they depend on the machine and on what else runs on it); what is checked
# is what must hold everywhere: agreement, bits and counts.

# %%
import contextlib
import cProfile
import inspect
import math
import pstats
import time
import tracemalloc

import numba
import numpy as np
from course import figures_folder, save_and_show
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

import minidiff as md
import render
from minidiff import backend, compiler, primitives
from render.shade import compiled

# This lesson's figures go to out/lessons/16_compiled_kernels/ (or under $LESSONS_OUT).
OUT = figures_folder("16_compiled_kernels")
lesson_start = time.perf_counter()
TWO = min(2, numba.config.NUMBA_NUM_THREADS)  # the compiled kernels' threads, at most


def median_ms(function, repeats: int = 5) -> float:
    """The median wall time of ``repeats`` calls of ``function()``, in milliseconds: the
    median, because a shared machine's timings have a long tail of interrupted runs."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return 1000 * float(np.median(times))


# %% [markdown]
# ## 1. A function, traced
#
# Lambert shading under a point light, written with minidiff as in lesson 5. `points` and
# `normals` have one row per hit: they are *batched*. The light's position and intensity
# are the same for every hit: they are *shared*, and `md.compile` is told so by name.


# %%
def lambert(points, normals, light, intensity):
    """Radiance (k,) of k hits (points, unit normals: (k, 3)) under a point light at
    ``light`` (3,) of ``intensity`` (), with albedo 1."""
    offset = light - points
    distance_sq = md.dot(offset, offset)
    cosine = md.maximum(md.dot(normals, md.normalize(offset)), 0.0)
    return intensity * cosine / (math.pi * distance_sq)


compiled_lambert = md.compile(lambert, shared=("light", "intensity"))

rng = np.random.default_rng(16)
n = 1_000_000
points = md.tensor(rng.uniform(-1.0, 1.0, (n, 3)))
normals = md.tensor(rng.normal(size=(n, 3)))
normals = md.tensor(normals.data / np.linalg.norm(normals.data, axis=1, keepdims=True))
light = md.tensor([0.5, 2.0, 1.0], requires_grad=True)
intensity = md.tensor(10.0, requires_grad=True)

program = compiled_lambert.trace(points, normals, light, intensity)
lines = program.graph.nodes
operations = {}
for node in lines:
    operations[node.op] = operations.get(node.op, 0) + 1
program_lines = len(lines)
print(f"{program_lines} lines for one element:", dict(sorted(operations.items())))
for index, node in enumerate(lines[:8]):
    print(f"  v{index} = {node.op} {' '.join(f'v{a}' for a in node.args)} {node.attrs or ''}")

# %% [markdown]
# One element's program has `49` <!-- check: program_lines --> lines (the counts by
# operation are printed): `load`s of the element's six numbers, `uniform`s for the four
# shared ones, constants, and the arithmetic, every vector operation taken apart into its
# lanes (`md.dot` of two 3-vectors is three products and two sums, in NumPy's order); the
# comparisons and `select`s are `md.maximum`'s and `md.normalize`'s own rules (a NaN
# passes through a maximum; a zero vector normalises to zero). It holds no loop and no
# branch, and its length does not depend on `n`: the same program
# serves every batch length. Nothing about derivatives is in it yet, except that every
# line made by a differentiable primitive remembers its inputs and its *slopes*: for each
# input a function `d -> d * dy/dx` written with the same scalar operations. They come
# from the primitive's scalar form, which sits beside its array form in
# `minidiff/primitives.py`:

# %%
print(inspect.getsource(primitives._divide_scalar))
print(inspect.getsource(primitives.divide).split("\n\n")[0])

# %% [markdown]
# The scalar form says `d/da = d / b` and `d/db = -(d / b) y`: exactly the products the
# array VJP below it computes (`ga = g / b`, `-ga * out`). That is the whole trick: the
# rule is written once per primitive, and everything above minidiff (the renderer) is
# written once, on arrays.
#
# ## 2. One loop, three modes
#
# The code generator writes the program as a loop over elements in LLVM's language, in
# three modes: **forward** (the program), **VJP** (the program, then the lines backwards
# through the slopes, from the output's cotangent to each input's gradient) and **JVP**
# (the program with a tangent beside every line). A gradient with respect to a shared
# input is a sum over the elements; the VJP sums it in fixed chunks of `CHUNK` elements,
# each in order, then the chunks in order, so the bits do not depend on how many threads
# share the chunks.

# %%
forward_ir = compiled_lambert.source(points, normals, light, intensity)
vjp_ir = compiled_lambert.source(points, normals, light, intensity, mode="vjp")
print(f"LLVM IR: forward {len(forward_ir.splitlines())} lines, VJP {len(vjp_ir.splitlines())}")
print("\n".join(line for line in forward_ir.splitlines() if "fdiv" in line or "sqrt" in line))


def taped_step(function):
    """Value and gradients of sum(radiance) with respect to the light and the intensity."""
    light.grad = intensity.grad = None
    radiance = function(points, normals, light, intensity)
    md.sum(radiance).backward()
    return radiance.data, light.grad.copy(), np.array(intensity.grad)


start = time.perf_counter()
compiled_values = taped_step(compiled_lambert)  # traced already; generates and compiles
first_call_s = time.perf_counter() - start
tape_values = taped_step(lambert)
worst = 0.0
for a, b in zip(compiled_values, tape_values, strict=True):
    worst = max(worst, float(np.abs(a - b).max() / np.abs(b).max()))
compiled_vs_tape = worst
with md.tangents({light: np.array([1.0, 0.0, 0.0])}):
    tangent_c = compiled_lambert(points, normals, light, intensity).tangent
    tangent_t = lambert(points, normals, light, intensity).tangent
tangent_vs_tape = float(np.abs(tangent_c - tangent_t).max() / np.abs(tangent_t).max())
print(f"first compiled step {first_call_s:.2f} s (kernels generated, compiled or fetched); "
      f"compiled against tape: value and gradients within {compiled_vs_tape:.1e}, "
      f"tangent within {tangent_vs_tape:.1e}")  # fmt: skip

# %% [markdown]
# The compiled function's value and gradients agree with the tape's to within `1e-12`
# <!-- check: compiled_vs_tape < --> of each array's largest value, and its tangent to
# within `1e-12` <!-- check: tangent_vs_tape < -->: the same rules, applied in the same
# order, differ only in the order of the long sums (the tape adds a million terms
# pairwise, NumPy's way; the kernel in chunks).
#
# **Threads.** The same step on one and on two threads:

# %%
runs = []
for threads in sorted({1, TWO}):
    with compiler.using_threads(threads):
        runs.append(taped_step(compiled_lambert))
thread_values_differ = sum(
    int(np.count_nonzero(a != b)) for a, b in zip(runs[0], runs[-1], strict=True)
)
print(f"threads {sorted({1, TWO})}: {thread_values_differ} values differ")

# %% [markdown]
# `0` <!-- check: thread_values_differ --> values differ. `using_threads` sets the count
# for this thread only (a context variable): no switch that one thread flips for another.
#
# **Time and memory.** Each primitive on the tape writes an array of `n` rows forward, and
# its VJP writes more backward; the compiled step writes its output and the gradients.
# Measured with `tracemalloc`, which sees NumPy's allocations:


# %%
def peak_mb(function) -> float:
    tracemalloc.start()
    taped_step(function)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return peak / 2**20


tape_ms = median_ms(lambda: taped_step(lambert))
kernel_ms = {t: 0.0 for t in sorted({1, TWO})}
for threads in kernel_ms:
    with compiler.using_threads(threads):
        kernel_ms[threads] = median_ms(lambda: taped_step(compiled_lambert))
tape_peak, compiled_peak = peak_mb(lambert), peak_mb(compiled_lambert)
compiled_uses_less_memory = compiled_peak < tape_peak
print(f"{n:,} hits, forward + backward: tape {tape_ms:.0f} ms, compiled "
      + ", ".join(f"{ms:.0f} ms on {t} thread(s)" for t, ms in kernel_ms.items())
      + f"; peak memory: tape {tape_peak:.0f} MB, compiled {compiled_peak:.0f} MB")  # fmt: skip

# %% [markdown]
# The compiled step's peak is the smaller (`True` <!-- check: compiled_uses_less_memory -->;
# both printed): it keeps the output and one row of gradient per chunk, where the tape keeps
# every intermediate array for the VJPs. The times are printed; on our 2-core machine the
# compiled step was about three times faster on one thread, and a second thread added
# another half.
#
# **Tables.** A shared array indexed by an integer array (a *table*: a mesh's vertices
# read at each hit's corners, a material per object) is *gathered*, and the VJP of a
# gather adds each element's gradient into the row it read: a scatter-add, where two
# elements may add to the same row at once. A small table (up to `codegen.PARTIAL_LIMIT`
# numbers) gets these sums inside the kernel, into its own copy of the table per group of
# consecutive chunks (at most `codegen.PARTIAL_GROUPS`; a thread runs whole groups), the
# groups' copies added in order afterwards; a larger one has every element's contribution
# written out, then added into the table in element order by a second kernel. Either way
# each row's sum is made in an order fixed by the elements alone:


# %%
@md.compile(shared=("albedos",))
def tinted(radiance, objects, albedos):
    """Radiance (k, 3): each hit's (k,) brightness times its object's albedo, a row of
    the (objects, 3) table ``albedos`` gathered at ``objects`` (k,)."""
    return radiance[:, None] * albedos[objects]


brightness = lambert(points, normals, light, intensity).data
objects = rng.integers(0, 8, n)  # eight objects
albedos = md.tensor(rng.uniform(0.2, 0.8, (8, 3)), requires_grad=True)
table_grads = []
for function, threads in [(tinted, t) for t in sorted({1, TWO})] + [(tinted.function, 1)]:
    with compiler.using_threads(threads):
        albedos.grad = None
        md.sum(function(brightness, objects, albedos)).backward()
        table_grads.append(albedos.grad.copy())
table_vs_tape = float(
    np.abs(table_grads[0] - table_grads[-1]).max() / np.abs(table_grads[-1]).max()
)
table_threads_differ = int(np.count_nonzero(table_grads[0] != table_grads[-2]))
print(
    f"the albedos' gradient: within {table_vs_tape:.1e} of the tape's; "
    f"{table_threads_differ} numbers differ between {sorted({1, TWO})} threads"
)

# %% [markdown]
# The table's gradient is the tape's to within `1e-12` <!-- check: table_vs_tape < -->
# (the tape adds each row's terms as NumPy's `add.at` does, in element order; the
# kernel by groups), and `0` <!-- check: table_threads_differ --> of its numbers differ
# between thread counts.
#
# ## 3. What the compiler refuses
#
# A trace has no values: it records one element's arithmetic for every element. So Python
# control flow on a traced value, a NumPy function called on one, or `.data` cannot be
# traced; the compiler refuses them when it traces, naming the operation and what to write
# instead.


# %%
def clamped_badly(points, normals, light, intensity):
    value = lambert(points, normals, light, intensity)
    if value > 1.0:  # a Python branch on a traced value: which element's value?
        return value * 0.0 + 1.0
    return value


try:
    md.compile(clamped_badly, shared=("light", "intensity"))(points, normals, light, intensity)
    refused = ""
except md.trace.CompileError as error:
    refused = str(error)
print("refused:", refused)

# %% [markdown]
# The message says what to do: `md.where(value > 1.0, 1.0, value)` makes the choice per
# element, inside the program (a comparison and a select: no branch). Exercise 3 writes it.
#
# ## 4. The cache
#
# Tracing is Python (milliseconds for a small function), and LLVM compiles the text to
# machine code (a fraction of a second). The machine code is kept in memory for the
# process (any function that traces to the same program gets it) and on disk
# (`~/.cache/minidiff/kernels`, or `$MINIDIFF_CACHE_DIR`), keyed by a hash of the traced
# program, of minidiff's code that turns a program into LLVM text (an edit there is a new
# key), LLVM's version and the CPU: the next process, or another function that traces to
# the same program, loads the machine code instead of writing the text and compiling it.

# %%
timings = {}
for label in ("a new CompiledFunction (trace, then the kernel from memory)", "a repeat call"):
    fresh = md.compile(lambert, shared=("light", "intensity"))
    if label == "a repeat call":
        fresh(points[:10], normals[:10], light, intensity)
    start = time.perf_counter()
    fresh(points[:10], normals[:10], light, intensity)
    timings[label] = 1000 * (time.perf_counter() - start)
cached_files = len(list(backend.cache_dir().glob("*.o")))
for label, ms in timings.items():
    print(f"{label}: {ms:.1f} ms")
print(f"{cached_files} kernels in {backend.cache_dir()}")

# %% [markdown]
# ## 5. The library's shading, before and after
#
# The renderer's steps 2 and 3 (lesson 6) recompute each camera hit's surface and shade
# it: `surface_at` (the ray, Möller-Trumbore, the normal) then `shade_surface` (every
# light, the BRDF, the ambient and emitted terms). `render/shade/compiled.py` runs exactly
# those functions through `md.compile` for each mesh (the camera frame, vertices, normals,
# material and lights shared; each hit's image-plane point, face and shadow verdicts
# batched). `md.tape_only()` runs every compiled function's plain text on the tape instead,
# in this thread only: the reference, and the "before".
#
# One optimisation step (render, loss, backward) of the paper's teapot at 128 × 128 with
# its vertices differentiated, under Python's profiler on one thread: the stage table gives
# each pipeline step's cumulative time (its `cumtime`: the time in the function and in
# everything it called).

# %%
scene = render.paper_scene(128, 128, ground=True)
vertices = scene.meshes[0].vertices
vertices.requires_grad = True

STAGES = {
    ("visibility.py", "trace_visibility"): "1 visibility",
    ("hits.py", "shade_camera_hits"): "2-3 surfaces and shading",
    ("film.py", "image_from_hits"): "5 film",
    ("tensor.py", "backward"): "backward",
}


def step():
    vertices.grad = None
    image = render.render(scene, reuse_visibility=False)
    md.mean(image * image).backward()
    return image.data, vertices.grad.copy()


def profile(context) -> dict:
    """Milliseconds per step and stage of three steps under cProfile, on one thread."""
    with compiler.using_threads(1), context():
        numba.set_num_threads(1)
        step()  # loads the kernels, fills the caches
        profiler = cProfile.Profile()
        profiler.enable()
        for _ in range(3):
            step()
        profiler.disable()
        numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
    stats = pstats.Stats(profiler).strip_dirs()
    table = {"total": 1000 * stats.total_tt / 3}
    for (filename, _, function), (_, _, _, cumtime, _) in stats.stats.items():
        if (filename, function) in STAGES:
            table[STAGES[filename, function]] = 1000 * cumtime / 3
    return table


before, after = profile(md.tape_only), profile(contextlib.nullcontext)  # tape, then compiled
for stage in ["total", *STAGES.values()]:
    print(
        f"  {stage:26s} tape {before.get(stage, 0):7.1f} ms, compiled {after.get(stage, 0):7.1f} ms"
    )
with md.tape_only():
    image_tape, grad_tape = step()
image_compiled, grad_compiled = step()
render_vs_tape = max(
    float(np.abs(image_compiled - image_tape).max() / np.abs(image_tape).max()),
    float(np.abs(grad_compiled - grad_tape).max() / np.abs(grad_tape).max()),
)
print(f"image and vertex gradient, compiled against tape: within {render_vs_tape:.1e}")

# %% [markdown]
# The table (this machine's numbers) shows where the compiled shading changes the step:
# the surfaces-and-shading stage and `backward` shrink, visibility (already compiled, by
# hand: it is discrete work, a BVH and a rasteriser) does not. The image and the vertices'
# gradient agree with the tape's to within `1e-11` <!-- check: render_vs_tape < -->.
#
# The profiler's own numbers deserve a word: it counts every Python-level call, so the
# tape (many small calls) is slowed by it more than the compiled step (few big ones); a
# compiled kernel is *one* opaque call, its whole time its `tottime`. The shares are a
# guide; `docs/benchmarks/` has the plain timings.
#
# How many kernels did the library compile for this scene? One trace per kind of mesh,
# material and lights (the teapot and its ground here), each with the modes it was asked
# for:

# %%
kinds = len(compiled._shade._traces)
kernels = sum(len(trace.kernels) for trace in compiled._shade._traces.values())
print(f"{kinds} traces of the shading, {kernels} kernels")

# %% [markdown]
# ## The measurements in one figure

# %%
figure = Figure(figsize=(10, 3.6), dpi=100, layout="constrained")
FigureCanvasAgg(figure)
left, right = figure.subplots(1, 2)
labels = ["tape"] + [f"compiled, {t} thread{'s' if t > 1 else ''}" for t in kernel_ms]
left.barh(
    labels, [tape_ms, *kernel_ms.values()], color=["tab:gray"] + ["tab:blue"] * len(kernel_ms)
)
left.set_xlabel("median ms, forward + backward")
left.set_title(f"lambert on {n:,} hits", fontsize=10)
stages = list(STAGES.values())
rows = np.arange(len(stages))
right.barh(rows - 0.2, [before.get(s, 0) for s in stages], 0.4, color="tab:gray", label="tape")
right.barh(rows + 0.2, [after.get(s, 0) for s in stages], 0.4, color="tab:blue", label="compiled")
right.set_yticks(rows, stages)
right.set_xlabel("ms per step (one thread, under cProfile)")
right.set_title("the paper scene, 128 × 128, vertices moving", fontsize=10)
right.legend(fontsize=8)
save_and_show(figure, OUT / "tape_and_kernel.png")
print(f"elapsed {time.perf_counter() - lesson_start:.1f} s; figures in {OUT}")

# %% [markdown]
# `tape_and_kernel.png`: on the left the small function's step, on the right the paper
# scene's stages, this machine's numbers (run it again on yours; they will differ, the
# checks above will not).
#
# ## Exercises
#
# 1. **A directional light.** Write `lambert` for a directional light (a direction of
#    travel `w` (3,), shared; the unit vector towards the light `normalize(-w)`; no
#    falloff), compile it, and check its value and its gradient with respect to `w`
#    against the tape's to 1e-12.
# 2. **One trace, or one per length.** A traced function that reads a batched array's
#    length (`points.shape[0]`) may depend on it, so the compiler keeps one trace per
#    length. Write such a function, call it with three lengths and count its traces
#    (`CompiledFunction._traces`); then write it without reading the length and count
#    again.
# 3. **The clamp, written to compile.** Write `clamped_badly` with `md.where`, compile it,
#    and check its value and gradients against the tape.
#
# Solutions: `lessons/solutions/16_compiled_kernels.py`.
