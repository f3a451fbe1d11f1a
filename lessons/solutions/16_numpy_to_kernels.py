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
import time

import numba
import numpy as np

import minidiff as md
from render.scene.camera import camera_directions


def median_seconds(function, repeats: int = 7) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def on_threads(function, threads):
    before = numba.get_num_threads()
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    try:
        return function()
    finally:
        numba.set_num_threads(before)


rng = np.random.default_rng(160)

# %% [markdown]
# ## Exercise 1: the camera rays' directions as a kernel
#
# `camera_directions` evaluates `coords[:, :1] * right + coords[:, 1:] * up + forward`:
# two (k, 3) products, their (k, 3) sum, then a (k, 3) sum with `forward`. Each `+` of
# NumPy rounds once, left to right, so a kernel that writes `(x * right + y * up) +
# forward` in that order gives the same bits; `forward + x * right + y * up` (the order of
# `render.scene.camera.pixel_ray`) need not.


# %%
@numba.njit(parallel=True)
def directions_kernel(coords, right, up, forward, out):
    """out[i] = coords[i, 0] * right + coords[i, 1] * up + forward, as camera_directions
    rounds it."""
    for i in numba.prange(coords.shape[0]):
        x, y = coords[i, 0], coords[i, 1]
        for c in range(3):
            out[i, c] = (x * right[c] + y * up[c]) + forward[c]


k = 1_000_000
coords = rng.uniform(-1.0, 1.0, (k, 2))
right, up, forward = (rng.normal(size=3) for _ in range(3))
out = np.empty((k, 3))
directions_kernel(coords, right, up, forward, out)  # compiles
reference = camera_directions(coords, right, up, forward)
directions_differ = int(np.count_nonzero(out != reference))
assert directions_differ == 0

numpy_seconds = median_seconds(lambda: camera_directions(coords, right, up, forward))
one_thread = on_threads(
    lambda: median_seconds(lambda: directions_kernel(coords, right, up, forward, out)), 1
)
all_threads = median_seconds(lambda: directions_kernel(coords, right, up, forward, out))
print(f"NumPy {1000 * numpy_seconds:.1f} ms; kernel {1000 * one_thread:.1f} ms on one "
      f"thread ({numpy_seconds / one_thread:.1f}x), {1000 * all_threads:.1f} ms on "
      f"{numba.get_num_threads()} ({numpy_seconds / all_threads:.1f}x)")  # fmt: skip

# %% [markdown]
# The kernel's directions are the library's bit for bit (`0`
# <!-- check: directions_differ --> values differ). Its speed-up is printed: most of it
# shows on one thread already (no temporaries: NumPy writes and reads four (k, 3) arrays,
# the kernel writes one); a second thread adds less, because the loop is limited by memory
# bandwidth, which the two cores share.
#
# ## Exercise 2: the Blinn-Phong lobe in both versions
#
# The half vector h = normalize(l + v), the lobe `specular (s + 8) / (8π) max(n · h, 0)^s`.
# NumPy's `np.power` and the kernel's `**` (which calls the C library's `pow`) are both
# accurate to about a unit in the last place, but not the *same* function: NumPy may use
# its own vectorised implementation. So values now differ, by a few units in the last place
# of the largest value at most; the library's test of its fused passes allows 8 for the
# same reason (`tests/render/shade/test_fused.py`).


# %%
def lobe_numpy(points, normals, camera, light, shininess):
    to_light = light - points
    to_light = to_light / np.linalg.norm(to_light, axis=1, keepdims=True)
    to_camera = camera - points
    to_camera = to_camera / np.linalg.norm(to_camera, axis=1, keepdims=True)
    half = to_light + to_camera
    half = half / np.linalg.norm(half, axis=1, keepdims=True)
    cos = np.maximum(np.sum(normals * half, axis=1), 0.0)
    return (shininess + 8.0) / (8.0 * math.pi) * np.power(cos, shininess)


@numba.njit(parallel=True)
def lobe_kernel(points, normals, camera, light, shininess, out):
    for i in numba.prange(points.shape[0]):
        lx, ly, lz = light[0] - points[i, 0], light[1] - points[i, 1], light[2] - points[i, 2]
        norm = math.sqrt(lx * lx + ly * ly + lz * lz)
        lx, ly, lz = lx / norm, ly / norm, lz / norm
        vx, vy, vz = camera[0] - points[i, 0], camera[1] - points[i, 1], camera[2] - points[i, 2]
        norm = math.sqrt(vx * vx + vy * vy + vz * vz)
        vx, vy, vz = vx / norm, vy / norm, vz / norm
        hx, hy, hz = lx + vx, ly + vy, lz + vz
        norm = math.sqrt(hx * hx + hy * hy + hz * hz)
        cos = (
            normals[i, 0] * (hx / norm) + normals[i, 1] * (hy / norm) + normals[i, 2] * (hz / norm)
        )
        out[i] = (shininess + 8.0) / (8.0 * math.pi) * max(cos, 0.0) ** shininess


n = 200_000
points = rng.uniform(-1.0, 1.0, (n, 3))
normals = rng.normal(size=(n, 3))
normals /= np.linalg.norm(normals, axis=1, keepdims=True)
camera, light = np.array([0.0, 1.0, 6.0]), np.array([2.0, 4.0, 3.0])
lobe = np.empty(n)
lobe_kernel(points, normals, camera, light, 37.0, lobe)
plain = lobe_numpy(points, normals, camera, light, 37.0)
lobe_ulps = float(np.abs(lobe - plain).max() / (np.finfo(float).eps * np.abs(plain).max()))
print(f"largest difference: {lobe_ulps:.2f} units in the last place of the largest value")
assert lobe_ulps < 8

# %% [markdown]
# The largest difference is below `8` <!-- check: lobe_ulps < --> units in the last place
# of the largest value (printed above; `np.linalg.norm` also sums its squares its own way).
#
# ## Exercise 3: the intensity's gradient as a kernel, with the chunked sum
#
# `radiance_i,c = albedo_i,c / π · intensity · cos_i / r_i² · lit_i`, so
# `∂ mean(radiance) / ∂ intensity = Σ_i,c albedo_i,c / π · cos_i / r_i² · lit_i / (3N)`:
# one number summed over every hit, which is exactly where a thread-count-dependent sum
# would creep in. The kernel sums it in 128 fixed chunks.

# %%
N_CHUNKS = 128


@numba.njit(parallel=True)
def intensity_gradient(points, normals, albedo, light_position, lit):
    n = points.shape[0]
    size = (n + N_CHUNKS - 1) // N_CHUNKS
    partial = np.zeros(N_CHUNKS)
    for chunk in numba.prange(N_CHUNKS):
        total = 0.0
        for i in range(chunk * size, min(n, (chunk + 1) * size)):
            dx = light_position[0] - points[i, 0]
            dy = light_position[1] - points[i, 1]
            dz = light_position[2] - points[i, 2]
            r2 = dx * dx + dy * dy + dz * dz
            r = math.sqrt(r2)
            cos = normals[i, 0] * (dx / r) + normals[i, 1] * (dy / r) + normals[i, 2] * (dz / r)
            factor = max(cos, 0.0) / r2 * lit[i]
            for c in range(3):
                total += albedo[i, c] / math.pi * factor
        partial[chunk] = total
    total = 0.0
    for chunk in range(N_CHUNKS):
        total += partial[chunk]
    return total / (3 * n)


albedo = rng.uniform(0.2, 0.9, (n, 3))
lit = rng.uniform(size=n) < 0.8
light_position = np.array([0.5, 3.0, 2.0])

# The tape: the same shading with the intensity a minidiff leaf.
intensity = md.Tensor(np.array(40.0), requires_grad=True)
to_light = light_position - points
r2 = np.sum(to_light * to_light, axis=1)
cos = np.maximum(np.sum(normals * (to_light / np.sqrt(r2)[:, None]), axis=1), 0.0)
radiance = md.Tensor(albedo / math.pi * (cos / r2 * lit)[:, None]) * intensity
md.mean(radiance).backward()
taped = float(intensity.grad)

compiled = [
    on_threads(lambda: intensity_gradient(points, normals, albedo, light_position, lit), t)
    for t in (1, 2)
]
gradient_relative_error = abs(compiled[0] - taped) / abs(taped)
print(f"tape {taped!r}, kernel {compiled[0]!r} (relative difference "
      f"{gradient_relative_error:.1e}); 1, 2 threads: {[v.hex() for v in compiled]}")  # fmt: skip
assert gradient_relative_error < 1e-13
assert compiled[0] == compiled[1]

# %% [markdown]
# The kernel's gradient agrees with minidiff's `backward` to `1e-13`
# <!-- check: gradient_relative_error < --> relative (the sums are taken in another order:
# the tape's `mean` is NumPy's pairwise sum), and gives the same bits on one and on two
# threads.
