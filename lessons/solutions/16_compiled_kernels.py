# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # Solutions to lesson 16 (from NumPy passes to a compiled kernel)

# %%
import math
import sys
from pathlib import Path

import numba
import numpy as np

import minidiff as md
import render
from render.shade import fused
from render.shade.adjoint_kernels import CHUNKS

# lessons/ is this file's grandparent; in Jupyter (no __file__) the notebook's folder.
here = Path(__file__).resolve().parent if "__file__" in globals() else Path.cwd()
sys.path.insert(0, str(here.parent))  # lessons/course.py
from course import run_lesson  # noqa: E402

# The lesson's timer, thread switch, fixed-chunk sum, and its real hits of a 256 x 256 view.
lesson = run_lesson("16_compiled_kernels")
median_ms, on_threads, sum_by_chunks = (
    lesson[k] for k in ("median_ms", "on_threads", "sum_by_chunks")
)
view, points, normals, lit = (lesson[k] for k in ("view", "points", "normals", "lit"))
position, intensity = lesson["position"], lesson["intensity"]
albedo_sum = (lesson["albedo"] / math.pi).sum(axis=1)  # each hit's Σρ/π
THREAD_COUNTS = sorted({1, lesson["TWO"]})


# %% [markdown]
# ## Exercise 1: the film as a kernel
#
# The passes: `np.where` writes an (N, 3) array of every sample's colour, `reshape` is a
# view, `mean(axis=1)` adds each pixel's samples in order and divides by `spp`. The
# kernel: one pixel per iteration, its samples added in order in a register, then scaled.


# %%
def film_passes(prim_id, radiance, spp, background):
    """(P, 3): each pixel the mean of its spp samples; a miss (prim_id -1) the background."""
    return np.where(prim_id[:, None] < 0, background, radiance).reshape(-1, spp, 3).mean(axis=1)


@numba.njit(parallel=True, error_model="numpy")
def film_kernel(prim_id, radiance, spp, background, out):
    """``film_passes`` written into ``out`` (P, 3): pixel p's samples summed in order,
    times 1 / spp."""
    scale = 1.0 / spp
    for p in numba.prange(out.shape[0]):
        for c in range(3):
            total = 0.0
            for s in range(spp):
                r = p * spp + s
                total += background[c] if prim_id[r] < 0 else radiance[r, c]
            out[p, c] = total * scale


rng = np.random.default_rng(16)
film_results = {}
for spp in (4, 9):
    n_pixels = 512 * 512 if spp == 4 else 64 * 64
    radiance = rng.uniform(0.0, 2.0, (n_pixels * spp, 3))
    prim_id = np.where(rng.uniform(size=n_pixels * spp) < 0.2, -1, 7)  # a fifth miss
    background = np.array([0.1, 0.2, 0.3])
    mine = np.empty((n_pixels, 3))
    film_kernel(prim_id, radiance, spp, background, mine)  # compiles on the first pass
    library = np.empty((n_pixels, 3))
    fused._film(prim_id, radiance, spp, background, numba.get_num_threads(), library)
    reference = film_passes(prim_id, radiance, spp, background)
    film_results[spp] = (
        int(np.count_nonzero(mine != reference)),
        int(np.count_nonzero(mine != library)),
        float(np.abs(mine - reference).max() / np.abs(reference).max()),
    )
    print(
        f"spp {spp}: kernel vs passes {film_results[spp][0]} values differ (largest "
        f"{film_results[spp][2]:.1e}), vs fused._film {film_results[spp][1]}"
    )

film_differ_spp4 = film_results[4][0]
film_differ_spp9 = film_results[9][0]
assert film_results[4][:2] == (0, 0)  # spp = 4: the same bits as both
assert film_results[9][1] == 0  # the library's film does what ours does
assert film_differ_spp9 > 0 and film_results[9][2] < 1e-15  # the passes round differently

# %% [markdown]
# With 4 samples per pixel the kernel gives the passes' and the library's bits (`0`
# <!-- check: film_differ_spp4 --> values differ): the sums add the samples in the same
# order, and dividing by 4 or multiplying by 1/4 are both exact (a power of two only moves
# the exponent). With 9 samples the kernel still equals `fused._film` (which also
# multiplies by `1 / spp`), but `mean` *divides* by 9, and `x · (1/9)` rounds twice where
# `x / 9` rounds once: some values differ by a unit in the last place, none by more than
# `1e-15` relative. The timings, 512 × 512 pixels with 4 samples each:

# %%
spp, n_pixels = 4, 512 * 512
radiance = rng.uniform(0.0, 2.0, (n_pixels * spp, 3))
prim_id = np.where(rng.uniform(size=n_pixels * spp) < 0.2, -1, 7)
out = np.empty((n_pixels, 3))
passes_ms = median_ms(lambda: film_passes(prim_id, radiance, spp, background), repeats=3)


def film_ms() -> float:
    return median_ms(lambda: film_kernel(prim_id, radiance, spp, background, out))


kernel_ms = {t: on_threads(t, film_ms) for t in THREAD_COUNTS}
print(f"film of {n_pixels * spp:,} samples: passes {passes_ms:.2f} ms; kernel "
      + ", ".join(f"{ms:.2f} ms on {t} thread(s) ({passes_ms / ms:.1f}x)"
                  for t, ms in kernel_ms.items()))  # fmt: skip

# %% [markdown]
# The kernel reads each sample once and writes each pixel once; the passes write and read
# back a 25 MB array of samples first. On a quiet machine the second thread roughly
# halves the kernel's time; on a busy one it may not (a parallel loop waits for its
# slowest thread). Medians, never single runs: one run can land on a moment when another
# process holds the core.
#
# ## Exercise 2: the light position's gradient as one kernel
#
# For a lit hit with `c = n · ω > 0`, its three channels' sum is
# `v = I S c / r²` with `S = Σρ/π`. With `o = p − x`, `∂r²/∂p = 2o` and
# `∂c/∂p = (n − c ω) / r` (the derivative of a unit vector, as `md.normalize`'s VJP), so
#
#     ∂v/∂p = I S ((n − c ω) / (r · r²) − 2 c o / r⁴).
#
# The hits are the lesson's (`points`, `normals`, `lit`, and `albedo_sum` from its `albedo`).


# %%
@numba.njit(parallel=True, error_model="numpy")
def position_gradient(points, normals, albedo_sum, lit, position, intensity, chunks):
    """d(sum over hits of the shading)/d(light position) (3,), summed over ``chunks`` fixed
    chunks of hits (each in order, in parallel), then the chunks in order."""
    n = points.shape[0]
    size = (n + chunks - 1) // chunks
    partial = np.zeros((chunks, 3))
    for chunk in numba.prange(chunks):
        for i in range(chunk * size, min(n, (chunk + 1) * size)):
            o0 = position[0] - points[i, 0]
            o1 = position[1] - points[i, 1]
            o2 = position[2] - points[i, 2]
            r2 = o0 * o0 + o1 * o1 + o2 * o2
            r = math.sqrt(r2)
            w0, w1, w2 = o0 / r, o1 / r, o2 / r
            c = normals[i, 0] * w0 + normals[i, 1] * w1 + normals[i, 2] * w2
            if c <= 0.0 or lit[i] == 0.0:
                continue
            k = intensity * albedo_sum[i]
            a, b = k / (r * r2), 2.0 * k * c / (r2 * r2)
            partial[chunk, 0] += a * (normals[i, 0] - c * w0) - b * o0
            partial[chunk, 1] += a * (normals[i, 1] - c * w1) - b * o1
            partial[chunk, 2] += a * (normals[i, 2] - c * w2) - b * o2
    total = np.zeros(3)
    for chunk in range(chunks):
        for a in range(3):
            total[a] += partial[chunk, a]
    return total


hit_args = (points, normals, albedo_sum, lit, position, intensity)
by_threads = [on_threads(t, lambda: position_gradient(*hit_args, CHUNKS)) for t in THREAD_COUNTS]
view.lights[0].position.requires_grad = True
md.sum(render.render(view)).backward()
tape_position_grad = view.lights[0].position.grad
view.lights[0].position.requires_grad = False
position_relative_difference = float(
    np.abs(by_threads[0] - tape_position_grad).max() / np.abs(tape_position_grad).max()
)
position_values_differ = int(np.count_nonzero(by_threads[0] != by_threads[-1]))
print(f"kernel {by_threads[0]}, tape {tape_position_grad}: relative difference "
      f"{position_relative_difference:.1e}; on {THREAD_COUNTS} threads "
      f"{position_values_differ} values differ")  # fmt: skip
assert position_relative_difference < 1e-10
assert position_values_differ == 0

# %% [markdown]
# The kernel agrees with the tape to `1e-10` <!-- check: position_relative_difference < -->
# (relative: the two evaluate the derivative in different orders, from rays whose directions
# differ in the last bits, see the lesson), and gives the same bits on one and two threads
# (`0` <!-- check: position_values_differ --> of the three values differ). The three
# sums share one loop: each hit's `o`, `r`, `ω` and `c` are computed once, in registers;
# the tape computes them as (k, 3) and (k,) arrays forward and again in the VJPs backward.
#
# ## Exercise 3: one chunk per thread

# %%
terms = rng.uniform(0.0, 1.0, 400_003)


# As many chunks as threads: the chunking, hence the bits, follows the thread count.
per_thread = [on_threads(t, lambda: sum_by_chunks(terms, numba.get_num_threads()))
              for t in THREAD_COUNTS]  # fmt: skip
one_vs_two_chunks_differ = int(sum_by_chunks(terms, 1) != sum_by_chunks(terms, 2))
assert one_vs_two_chunks_differ == 1
print(f"chunks = threads on {THREAD_COUNTS}: {[v.hex() for v in per_thread]}")
for chunks in (1, 8, CHUNKS, 8192):
    print(f"{chunks:5d} chunks: {median_ms(lambda c=chunks: sum_by_chunks(terms, c), 5):.3f} ms")

# %% [markdown]
# With one chunk per thread, one thread sums one chunk and two threads two, and a sum of
# one chunk and a sum of two chunks differ here (`1` <!-- check: one_vs_two_chunks_differ -->:
# they differ), so the result would follow the machine. A fixed count keeps the terms'
# order fixed. What the count trades: at most `chunks` threads can work at once (8 chunks
# leave a 64-core machine mostly idle, and uneven chunks leave threads waiting for the
# slowest), while every chunk costs a row of partial sums (`backward_rows` keeps `CHUNKS` ×
# a few dozen numbers, one per global parameter) and one step of the final serial sum.
# At 128 chunks both costs are small next to the work in the chunks for any sum worth
# running in parallel (the adjoint's: tens of thousands of hits, a few hundred per chunk);
# the timings above show whether 1, 8, 128 or 8,192 chunks make a difference you can
# measure on your machine for 400,000 terms.
