# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # Solutions to lesson 16 (how a tape becomes a kernel)

# %%
import numpy as np

import minidiff as md

rng = np.random.default_rng(160)
n = 10_000
points = md.tensor(rng.uniform(-1.0, 1.0, (n, 3)))
normals = md.tensor(rng.normal(size=(n, 3)))
normals = md.tensor(normals.data / np.linalg.norm(normals.data, axis=1, keepdims=True))


def relative_difference(a, b) -> float:
    """max |a - b| over max |b|: how far ``a`` is from ``b``, relative to ``b``'s scale."""
    return float(np.abs(np.asarray(a) - np.asarray(b)).max() / np.abs(np.asarray(b)).max())


# %% [markdown]
# ## Exercise 1: a directional light
#
# The direction of travel `w` is shared; `normalize(-w)` is the same for every hit, and
# the program computes it per element (a few operations; LLVM may hoist them out of the
# loop). Its gradient is a sum over the hits, in fixed chunks.


# %%
def lambert_directional(normals, direction, irradiance):
    """Radiance (k,) of k hits with unit normals (k, 3) under a directional light that
    travels along ``direction`` (3,) with ``irradiance`` (), albedo 1."""
    towards = md.normalize(-direction)
    return irradiance * md.maximum(md.dot(normals, towards), 0.0) / np.pi


compiled_directional = md.compile(lambert_directional, shared=("direction", "irradiance"))
direction = md.tensor([0.3, -1.0, 0.2], requires_grad=True)
irradiance = md.tensor(2.0)
results = []
for function in (compiled_directional, lambert_directional):
    direction.grad = None
    radiance = function(normals, direction, irradiance)
    md.sum(radiance * radiance).backward()
    results.append((radiance.data, direction.grad.copy()))
directional_value = relative_difference(results[0][0], results[1][0])
directional_gradient = relative_difference(results[0][1], results[1][1])
print(f"value within {directional_value:.1e}, gradient within {directional_gradient:.1e}")
assert directional_value < 1e-12 and directional_gradient < 1e-12

# %% [markdown]
# The value agrees to `1e-12` <!-- check: directional_value < --> and the gradient with
# respect to `w` to `1e-12` <!-- check: directional_gradient < --> of their scale.
#
# ## Exercise 2: one trace, or one per length
#
# Reading `points.shape[0]` tells the compiler that the program may depend on the batch
# length (here it does: the scale), so it keeps one trace per length.


# %%
def mean_height_reads_length(points):
    """Each point's height over the batch length (a made-up use of the length)."""
    return points[:, 1] * (1.0 / points.shape[0])


def height(points):
    return points[:, 1] * 1.0


per_length = md.compile(mean_height_reads_length)
independent = md.compile(height)
for k in (10, 20, 30):
    per_length(points[:k])
    independent(points[:k])
traces_reading_length = len(per_length._traces)
traces_not_reading = len(independent._traces)
print(f"reads the length: {traces_reading_length} traces; does not: {traces_not_reading}")

# %% [markdown]
# `3` <!-- check: traces_reading_length --> traces for three lengths when the function reads
# the length, `1` <!-- check: traces_not_reading --> when it does not. (A function that
# needs the length should take it as a shared argument instead, a number like any other.)
#
# ## Exercise 3: the clamp, written to compile


# %%
def lambert(points, normals, light, intensity):
    offset = light - points
    distance_sq = md.dot(offset, offset)
    cosine = md.maximum(md.dot(normals, md.normalize(offset)), 0.0)
    return intensity * cosine / (np.pi * distance_sq)


def clamped(points, normals, light, intensity):
    """``lambert`` clamped to at most 1: the choice made per element by md.where."""
    value = lambert(points, normals, light, intensity)
    return md.where(value > 1.0, 1.0, value)


compiled_clamped = md.compile(clamped, shared=("light", "intensity"))
light = md.tensor([0.2, 0.6, 0.4], requires_grad=True)
intensity = md.tensor(3.0, requires_grad=True)
results = []
for function in (compiled_clamped, clamped):
    light.grad = intensity.grad = None
    radiance = function(points, normals, light, intensity)
    md.sum(radiance).backward()
    results.append((radiance.data, light.grad.copy(), np.array(intensity.grad)))
clamped_share = float(np.mean(results[1][0] == 1.0))
clamp_difference = max(relative_difference(a, b) for a, b in zip(*results, strict=True))
print(f"{100 * clamped_share:.1f} % of the hits clamped; compiled against tape within "
      f"{clamp_difference:.1e}")  # fmt: skip
assert clamp_difference < 1e-12

# %% [markdown]
# A share of the hits is clamped (more than `0` <!-- check: clamped_share > -->; printed),
# and the compiled value and gradients agree with the tape's within `1e-12`
# <!-- check: clamp_difference < -->: where a hit is clamped, its gradient is exactly zero
# in both (the select passes the cotangent to the constant 1.0).
