# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # Solutions to lesson 14 (path replay)

# %%
import sys
from pathlib import Path

import numpy as np

import minidiff as md

# lessons/ is this file's grandparent; in Jupyter (no __file__) the notebook's folder.
here = Path(__file__).resolve().parent if "__file__" in globals() else Path.cwd()
sys.path.insert(0, str(here.parent))  # lessons/course.py
from course import run_lesson  # noqa: E402

# The lesson's path model (its surfaces, geometry factors, last hit's weight, emission and
# the pixel's delta) and its memory measurement.
lesson = run_lesson("14_path_replay")
surfaces, geometry = lesson["surfaces"], lesson["geometry"]
last_hit_weight, emission, delta = lesson["last_hit_weight"], lesson["emission"], lesson["delta"]
gradient_peak_mb = lesson["gradient_peak_mb"]
box_gradient_once = lesson["box_gradient_once"]


def taped_gradient(rho, emission, distance=None):
    """d(delta * L)/d(rho), d/dE (and d/d distance, with g_k = geometry_k / distance²) by
    minidiff's tape."""
    rho_leaf = md.Tensor(np.array(rho, float), requires_grad=True)
    e_leaf = md.Tensor(np.array(emission), requires_grad=True)
    d_leaf = md.Tensor(np.array(1.0 if distance is None else distance), requires_grad=True)
    beta, total = md.Tensor(np.array(1.0)), md.Tensor(np.array(0.0))
    for s, g in zip(surfaces, geometry, strict=True):
        g_k = g / (d_leaf * d_leaf) if distance is not None else g
        total = total + beta * rho_leaf[s] * g_k * e_leaf
        beta = beta * rho_leaf[s]
    (delta * (total + beta * last_hit_weight * e_leaf)).backward()
    return rho_leaf.grad, float(e_leaf.grad), float(d_leaf.grad if distance is not None else 0)


# %% [markdown]
# ## Exercise 1: a wall with no green
#
# With `rho[1] = 0` the lesson's `path_adjoint` divides `remaining` by zero: the vertex's
# share `β_k dF_k/dρ R_k` becomes `0/0`. Yet `R_1` (what reaches vertex 1 from later on)
# is not zero, and neither is the derivative: making that wall a little green would let
# light through. Keeping `(C_k, F_k)` per vertex (a few numbers for each vertex of the one
# path being replayed) and running the recursion backwards needs no division.


# %%
def path_adjoint_recursive(rho, emission, delta):
    c = [rho[s] * g * emission for s, g in zip(surfaces, geometry, strict=True)]
    f = [rho[s] for s in surfaces]
    n = len(surfaces)
    remaining = [0.0] * n  # R_k
    after = last_hit_weight * emission  # what the last direction brings
    for k in range(n - 1, -1, -1):
        remaining[k] = after
        after = c[k] + f[k] * after
    d_rho, d_emission, beta = np.zeros_like(rho), 0.0, 1.0
    for k, (s, g) in enumerate(zip(surfaces, geometry, strict=True)):
        d_rho[s] += delta * beta * (g * emission + remaining[k])  # dC/d rho + dF/d rho R_k
        d_emission += delta * beta * rho[s] * g
        beta *= rho[s]
    return d_rho, d_emission + delta * beta * last_hit_weight


for rho in (np.array([0.7, 0.45, 0.8]), np.array([0.7, 0.0, 0.8])):
    by_hand, by_hand_e = path_adjoint_recursive(rho, emission, delta)
    tape_rho, tape_e, _ = taped_gradient(rho, emission)
    recursion_difference = max(
        np.abs(by_hand - tape_rho).max() / np.abs(tape_rho).max(), abs(by_hand_e - tape_e) / tape_e
    )
    print(f"rho {rho}: recursion {by_hand.round(6)}, tape {tape_rho.round(6)}")
    assert recursion_difference < 1e-14
zero_albedo_gradient = float(by_hand[1])

# %% [markdown]
# With the zero the tape and the recursion agree (to `1e-14` <!-- check:
# recursion_difference < --> relative): `d/d rho[1]` is `1.88496` <!-- check:
# zero_albedo_gradient -->, not zero and not `nan` (it does not depend on `rho[1]` itself:
# the vertices before it set its throughput, the ones after it its `R_k`), while `d/d
# rho[2]` is 0: no light reaches surface 2's vertex through a black wall. This is the case
# `docs/path_tracing.md` describes for the library's compiled replay: an albedo
# `(0.6, 0, 0)` still learns its green.
#
# ## Exercise 2: a moving lamp
#
# With `g_k = a_k / d²`, only the `C_k` depend on `d`: `dC_k/dd = −2 C_k / d`. The replay
# adds `δ β_k dC_k/dd` at each vertex.


# %%
def distance_derivative(rho, emission, distance, delta):
    beta, total = 1.0, 0.0
    for s, a in zip(surfaces, geometry, strict=True):
        total += delta * beta * rho[s] * a * emission * (-2 / distance**3)
        beta *= rho[s]
    return total


rho = np.array([0.7, 0.45, 0.8])
by_hand_d = distance_derivative(rho, emission, 1.3, delta)
tape_d = taped_gradient(rho, emission, distance=1.3)[2]
distance_difference = abs(by_hand_d - tape_d) / abs(tape_d)
print(f"d/d distance: by hand {by_hand_d:.6f}, tape {tape_d:.6f}")
assert distance_difference < 1e-14

# %% [markdown]
# They agree to `1e-14` <!-- check: distance_difference < --> relative.
#
# ## Exercise 3: memory at depth 32
#
# Like with like: the tape and the compiled replay of whole paths, both for the lamp's
# position (the replay is what the library runs for it). The replay's kernel is compiled
# once per depth (lesson 16), so a first call at each depth comes before the measurement.


# %%
for depth in (2, 32):
    box_gradient_once("replay", "lamp", 1, depth)
tape = {d: gradient_peak_mb("tape", "lamp", 16, d) for d in (2, 32)}
paths = {d: gradient_peak_mb("replay", "lamp", 16, d) for d in (2, 32)}
tape_growth_32 = tape[32] / tape[2]
paths_growth_32 = paths[32] / paths[2]
tape_over_paths_32 = tape[32] / paths[32]
print(f"depth 2 -> 32: tape {tape[2]:.1f} -> {tape[32]:.1f} MB, compiled replay "
      f"{paths[2]:.1f} -> {paths[32]:.1f} MB")  # fmt: skip

# %% [markdown]
# From depth 2 to 32 the tape grows more than `3.5` <!-- check: tape_growth_32 > --> times,
# and the compiled replay more than `4.5` <!-- check: paths_growth_32 > --> times
# (printed above); at depth 32 the tape still holds more than `1.2`
# <!-- check: tape_over_paths_32 > --> times as much. What grows in the replay is the
# batch's *records*: every vertex's decisions (primitive, lobe, light sample) for all the
# batch's paths, which the replay reads and which are kept for the whole batch
# (`docs/path_tracing.md`); the kernel itself keeps one path's values per thread while it
# runs that path's reverse sweep, whatever the number of paths. So the replay is flat in
# the number of samples, not in depth; a replay flat in both would have to trace each path
# again while it takes its derivative, keeping no records (Exercise 1's recursion, on the
# fly). (Many paths leave the open box long before depth 32, so nothing grows
# sixteen-fold.)
