# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # Solutions to lesson 4 (ray-triangle intersection and the BVH)
#
# Exercises 1 and 3 reuse the lesson's counting traversal and SAH cost: the lesson is run
# first (its figures go to its own output folder) and its functions taken from it.

# %%
import sys
from pathlib import Path

import numpy as np

import render
from render.scene.camera import primary_rays
from render.trace.accel import Accelerator
from render.trace.intersect import intersect_triangle, make_ray, pack_primitives

# lessons/ is this file's grandparent; in Jupyter (no __file__) the notebook's folder.
here = Path(__file__).resolve().parent if "__file__" in globals() else Path.cwd()
sys.path.insert(0, str(here.parent))  # lessons/course.py, lessons/exercise_checks.py
from course import run_lesson  # noqa: E402

lesson = run_lesson("04_bvh")
closest_hit_counted, sah_cost = lesson["closest_hit_counted"], lesson["sah_cost"]
triangles = lesson["triangles"]


def count_tests(acc, scene):
    """(rays that hit, triangle tests, brute-force tests / BVH tests) for a scene's view."""
    eye, directions = primary_rays(scene.camera)
    counted = np.array([closest_hit_counted(acc, eye, d) for d in directions])
    tests = int(counted[:, 2].sum())
    return int((counted[:, 0] >= 0).sum()), tests, len(directions) * acc.n_prims / tests


# %% [markdown]
# ## Exercise 1: the number of bins
#
# More candidate planes can only find splits at least as cheap at each node, but the
# differences are small here: 2 bins (every node cut through the middle of its centroids'
# extent) give an SAH cost of 20.6, 12 bins 20.1, 32 bins 19.6, and the counted tests move
# by a few percent. The teapot's triangles are small and evenly spread, so a middle split
# is nearly as good as the best one; scenes of very uneven triangle sizes need the bins.

# %%
view = render.paper_scene(width=64, height=64)
costs = {}
for bins in (2, 4, 12, 32):
    acc = Accelerator(triangles, n_bins=bins)
    costs[bins] = sah_cost(acc)
    hits, tests, saved = count_tests(acc, view)
    print(f"{bins:>2} bins: SAH cost {costs[bins]:6.2f}, {acc.n_nodes} nodes, "
          f"{tests:,} triangle tests on the 64x64 view")  # fmt: skip
assert costs[32] <= costs[2]

# %% [markdown]
# ## Exercise 2: a ray through a shared edge
#
# The square `(0,0)-(1,1)` as two triangles sharing the diagonal; the ray goes down through
# `(0.5, 0.5)`, a point of the diagonal. `u, v ≥ 0` and `u + v ≤ 1` are inclusive, so both
# triangles report the hit at the same `t`; the `(t, id)` order picks the lower id.

# %%
p0, p1, p2, p3 = (0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (1.0, 1.0, 0.0), (0.0, 1.0, 0.0)
square = np.array([[p0, p1, p2], [p0, p2, p3]])
o, d = np.array([0.5, 0.5, 1.0]), np.array([0.0, 0.0, -1.0])
table = pack_primitives(square, np.zeros((0, 3)), np.zeros(0))
both = [intersect_triangle(table, k, make_ray(o, d, 0.0, np.inf)) for k in range(2)]
print("each triangle's (t, u, v):", both)
assert both[0][0] == both[1][0] == 1.0
for order in ([0, 1], [1, 0]):
    for use_bvh in (True, False):
        ids, t, _, _ = Accelerator(square[order], use_bvh=use_bvh).closest_hit(o[None], d[None])
        print(f"triangles in order {order}, use_bvh={use_bvh}: hit id {ids[0]} at t = {t[0]}")
        assert ids[0] == 0

# %% [markdown]
# ## Exercise 3: a camera twice as far away
#
# The teapot covers about a quarter as many pixels, so about a quarter as many rays hit and
# the triangle tests shrink with them, while brute force still tests every ray against every
# triangle: the factor saved grows. Per ray that hits, the cost barely changes (the tree is
# the same; only the rays differ).

# %%
accel = Accelerator(triangles)
near = count_tests(accel, view)
far = count_tests(accel, render.paper_scene(width=64, height=64, camera_position=(6, 4, 10)))
for name, (hits, tests, saved) in (("near", near), ("far", far)):
    print(f"{name}: {hits} rays hit, {tests:,} triangle tests, {saved:.0f}x fewer than brute force")
assert far[0] < 0.4 * near[0] and far[2] > near[2]


# %% [markdown]
# ## Exercise 4: a ray-triangle intersection of your own
#
# Möller–Trumbore, vectorised: solve `o + t d = a + u (b − a) + v (c − a)` by Cramer's rule
# with `e1 = b − a`, `e2 = c − a`, `p = d × e2`, `det = e1 · p`; a ray parallel to the
# triangle's plane has `det = 0`.

# %%
from exercise_checks import check_any_hit, check_intersection  # noqa: E402


def my_intersect(o, d, a, b, c):
    e1, e2 = b - a, c - a
    p = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, p)
    safe = np.where(det != 0, det, 1.0)
    s = o - a
    u = np.einsum("ij,ij->i", s, p) / safe
    q = np.cross(s, e1)
    v = np.einsum("ij,ij->i", d, q) / safe
    t = np.einsum("ij,ij->i", e2, q) / safe
    hit = (det != 0) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    return np.where(hit, t, np.inf), np.where(hit, u, 0.0), np.where(hit, v, 0.0)


print(check_intersection(my_intersect))

# %% [markdown]
# ## Exercise 5: an any-hit walk
#
# A stack of nodes; a node whose box the ray misses before `t_max` is skipped; a leaf's
# triangles are tested until one is hit.


# %%
def my_occluded(acc, o, d, t_max):
    inverse = 1.0 / np.where(d == 0, 1e-300, d)
    ray = make_ray(o, d, 0.0, t_max)
    stack = [0]
    while stack:
        node = stack.pop()
        t1 = (acc.node_bounds[node, :3] - o) * inverse
        t2 = (acc.node_bounds[node, 3:] - o) * inverse
        if max(np.minimum(t1, t2).max(), 0.0) > min(np.maximum(t1, t2).min(), t_max):
            continue  # the ray misses this box before t_max
        first, count = acc.node_first[node], acc.node_count[node]
        if count > 0:
            for k in range(first, first + count):
                if intersect_triangle(acc.leaf_prim, k, ray)[0] < t_max:
                    return True
        else:
            stack += [first, first + 1]
    return False


print(check_any_hit(my_occluded))
