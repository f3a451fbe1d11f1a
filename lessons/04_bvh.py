# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # Lesson 4 — Ray-triangle intersection and the BVH
#
# Visibility is the renderer's one discrete question: *which primitive does this ray hit
# first?* This lesson answers it for one ray and one triangle (Möller–Trumbore), then for
# many rays and the teapot's 1,536 triangles, with a bounding volume hierarchy (BVH) built by
# the surface area heuristic (SAH). Read along: `render/trace/intersect.py` (the Numba kernels),
# `render/trace/bvh.py` (the builder), `render/trace/accel.py` (the `Accelerator` that ties them
# together) and `render/shade/surface.py` (the same intersection on the tape).
#
# ## Möller–Trumbore
#
# A ray `o + t·d` meets the plane of the triangle `(a, b, c)` where
# `o + t·d = a + u·e1 + v·e2`, with edges `e1 = b − a`, `e2 = c − a`. That is a 3 × 3
# linear system `[−d, e1, e2]·(t, u, v)ᵀ = o − a`, and Cramer's rule solves it with triple
# products. With `s = o − a`, `p = d × e2`, `q = s × e1`:
#
#     det = e1·p,   t = (e2·q)/det,   u = (s·p)/det,   v = (d·q)/det.
#
# The ray hits the triangle if `u ≥ 0`, `v ≥ 0`, `u + v ≤ 1` and `t > t_min`; the hit is
# `(1 − u − v)·a + u·b + v·c`. If `det ≈ 0` the ray is parallel to the plane (or the
# triangle has no area): a miss. `render.shade.surface.intersect_edges` computes exactly
# this on the minidiff tape.
#
# The tracer, `render.trace.intersect.intersect_triangle`, finds the same `t, u, v` (to
# rounding) another way, because of what rounding does at a shared edge: a ray through a
# point of the edge between two triangles gets `u` from one and `v` (or `1 − u − v`) from
# the other, each rounded its own way, and if both come out a hair negative the ray passes
# between them into a closed mesh. (On an octahedron, 4 of 66 rays aimed at edges did,
# before the tracer changed; `tests/render/trace/test_watertight.py`.) So the tracer uses
# the *watertight* test of Woop, Benthin and Wald (2013): it moves the corners into the
# ray's frame (the ray's origin at 0, its direction sheared onto the z axis) and asks on
# which side of each edge the ray passes, a 2-D cross product of the edge's two corners.
# Each corner's coordinates there depend on that corner alone, and swapping an edge's ends
# negates its cross product exactly, so two triangles sharing an edge always agree on the
# ray's side of it: one of them is hit.

# %%
import time

import numpy as np
from course import figures_folder
from PIL import Image, ImageDraw

import minidiff as md
import render
from render.scene.camera import primary_rays
from render.shade.surface import intersect_edges
from render.trace.accel import Accelerator
from render.trace.intersect import intersect_triangle, make_ray, pack_primitives

# This lesson's figures go to out/lessons/04_bvh/ (or under $LESSONS_OUT).
OUT = figures_folder("04_bvh")

# %%
a, b, c = np.array([0.0, 0.0, 0.0]), np.array([2.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])
origin, direction = np.array([0.5, 0.25, 3.0]), np.array([0.1, 0.05, -1.0])

# The Numba kernel reads a packed row per triangle: a, b, c, normal, degeneracy cut.
table = pack_primitives(np.stack([a, b, c])[None], np.zeros((0, 3)), np.zeros(0))
ray = make_ray(origin, direction, 0.0, np.inf)  # o + t d for 0 < t < inf
t_numba, u_numba, v_numba = intersect_triangle(table, 0, ray)

# The same on the tape (arrays of k = 1 ray).
t_tape, u_tape, v_tape = intersect_edges(
    md.tensor(origin), md.tensor(direction[None]), md.tensor(a[None]),
    md.tensor((b - a)[None]), md.tensor((c - a)[None]),
)  # fmt: skip
hit_t = float(t_numba)
hit_u, hit_v = float(u_numba), float(v_numba)
mt_agreement = max(abs(t_tape.data[0] - hit_t), abs(u_tape.data[0] - hit_u))
hit_point = origin + hit_t * direction
barycentric_point = (1 - hit_u - hit_v) * a + hit_u * b + hit_v * c
print(f"Numba: t = {hit_t:.6f}, u = {hit_u:.6f}, v = {hit_v:.6f}")
print(f"tape:  t = {t_tape.data[0]:.6f}, u = {u_tape.data[0]:.6f}, v = {v_tape.data[0]:.6f}")
print("o + t d =", hit_point, "  (1-u-v) a + u b + v c =", barycentric_point)

# %% [markdown]
# The ray from `(0.5, 0.25, 3)` along `(0.1, 0.05, −1)` meets the triangle's plane `z = 0`
# at `t = 3` <!-- check: hit_t --> (three steps of `d`, whose `z` component is −1), at
# `(0.8, 0.4, 0)`: `u = 0.4` <!-- check: hit_u -->, `v = 0.4` <!-- check: hit_v -->. The
# Numba kernel and the tape agree to `1e-15` <!-- check: mt_agreement < -->. (The renderer
# finds *which* triangle without the tape, then recomputes *where* on the tape, so that
# gradients reach the camera and the vertices: the tracer's `t, u, v` would be constants.
# Which triangle: by default camera rays are not traced through the BVH at all but
# *rasterised* — each triangle lists the pixels its screen box covers and tests only their
# rays, with this same intersection function (`render/trace/raster.py`; the same hits bit
# for bit, faster while there are many rays per triangle) — and shadow rays towards a point
# light are answered the same way from the light's side (`render/trace/light_view.py`).
# The BVH below answers every other ray: mirror and path-traced rays, edge and shadow
# border rays, and everything when `render(..., primary="bvh")`.)
#
# ## A BVH over the teapot
#
# Testing every ray against every triangle costs `rays × triangles` tests. A BVH is a
# binary tree of axis-aligned boxes: each node's box bounds all the triangles below it, the
# leaves hold a few triangles each. A ray that misses a box skips its whole subtree.
#
# How to split a node? The **surface area heuristic**: for rays that pass through a node's
# box `P`, the chance of also passing through a child box `L` is about `A(L)/A(P)` (ratio of
# surface areas, exact for uniformly distributed rays). So the expected cost of a split is
#
#     C_split = C_trav + (A(L)·n_L + A(R)·n_R) / A(P),    against    C_leaf = n_P,
#
# in units of one triangle test (`render/trace/bvh.py` uses `C_trav = 1`). The builder evaluates
# 11 candidate planes per axis (12 bins over the triangles' centroids), takes the cheapest
# and stops when a leaf is cheaper (and holds at most 4 triangles).

# %%
vertices, faces = render.teapot_geometry()
triangles = vertices[faces]  # (1536, 3, 3)
accel = Accelerator(triangles)
print(accel)
n_triangles, n_nodes, n_leaves, depth = len(triangles), accel.n_nodes, accel.n_leaves, accel.depth


def half_area(bounds):
    e = bounds[..., 3:] - bounds[..., :3]
    return e[..., 0] * e[..., 1] + e[..., 1] * e[..., 2] + e[..., 2] * e[..., 0]


def sah_cost(acc, c_trav=1.0):
    """Expected cost of the tree for a ray through the root box, in triangle tests:
    C_trav per interior node visited plus n per leaf visited, each weighted by its area."""
    area = half_area(acc.node_bounds) / half_area(acc.node_bounds[0])
    leaf = acc.node_count > 0
    return float(c_trav * area[~leaf].sum() + (acc.node_count[leaf] * area[leaf]).sum())


tree_cost = sah_cost(accel)
leaf_sizes = accel.node_count[accel.node_count > 0]
print(f"SAH cost {tree_cost:.2f} triangle tests per ray, against {n_triangles} for one leaf")
print(f"leaf sizes: mean {leaf_sizes.mean():.2f}, largest {leaf_sizes.max()}")

# %% [markdown]
# The teapot's `1,536` <!-- check: n_triangles --> triangles make a tree of `1,499`
# <!-- check: n_nodes --> nodes, `750` <!-- check: n_leaves --> of them leaves, `13`
# <!-- check: depth --> levels deep. Its SAH cost is `20.11` <!-- check: tree_cost -->
# tests (box visits and triangle tests) per ray that enters the root box, against 1,536
# for a single leaf.
#
# ## Traversal, counted
#
# A walk of the tree for one ray: at an interior node it tests both children's boxes (the
# slab test: intersect the ray's `t` intervals between the pairs of planes of the box),
# descends into the nearer one and pushes the farther one with its entry distance; a
# popped node whose entry distance is beyond the best hit so far is skipped. Below is that
# walk in plain Python, counting box and triangle tests, with the library's triangle test
# on the library's tree. It must find the same triangle as `Accelerator.closest_hit` for
# every ray. (The library's own walk, `render.trace.intersect.closest_hit_ray`, does the
# same on a 4-wide tree collapsed from this one, `render/trace/wide.py`: four boxes a node,
# tested at once with vector instructions, half the levels.)


# %%
def box_entry(bounds, o, inverse, t_max):
    """Slab test: the distance at which the ray enters the box, or inf if it misses it
    before t_max."""
    t1, t2 = (bounds[:3] - o) * inverse, (bounds[3:] - o) * inverse
    t_in, t_out = max(np.minimum(t1, t2).max(), 0.0), min(np.maximum(t1, t2).min(), t_max)
    return t_in if t_in <= t_out else np.inf


def closest_hit_counted(acc, o, d):
    """(triangle id or -1, box tests, triangle tests) for one ray."""
    bounds, first, count = acc.node_bounds, acc.node_first, acc.node_count
    inverse = 1.0 / np.where(d == 0, 1e-300, d)
    ray = make_ray(o, d, 0.0, np.inf)
    best, best_t, boxes, tests = -1, np.inf, 1, 0
    if box_entry(bounds[0], o, inverse, best_t) == np.inf:
        return best, boxes, tests
    stack = [(0, 0.0)]  # (node, entry distance)
    while stack:
        node, entry = stack.pop()
        if entry > best_t:
            continue  # a closer hit was found since this node was pushed
        if count[node] > 0:  # a leaf: test its triangles
            for k in range(first[node], first[node] + count[node]):
                tests += 1
                t, _, _ = intersect_triangle(acc.leaf_prim, k, ray)
                pid = acc.leaf_ids[k]
                if t < best_t or (t == best_t and pid < best):  # ties: the lower id wins
                    best, best_t = pid, t
        else:  # both children's boxes; the nearer one is popped first
            left = first[node]
            entries = [(box_entry(bounds[ch], o, inverse, best_t), ch) for ch in (left, left + 1)]
            boxes += 2
            for t_in, child in sorted(entries, reverse=True):
                if t_in < np.inf:
                    stack.append((child, t_in))
    return best, boxes, tests


scene = render.paper_scene(width=64, height=64)
eye, directions = primary_rays(scene.camera)
start = time.perf_counter()
counted = np.array([closest_hit_counted(accel, eye, d) for d in directions])
print(f"Python traversal of {len(directions)} rays: {time.perf_counter() - start:.2f} s")
prim_id, _, _, _ = accel.closest_hit(np.broadcast_to(eye, directions.shape), directions)
same_hits = bool((counted[:, 0] == prim_id).all())
n_rays, rays_hitting = len(directions), int((prim_id >= 0).sum())
bvh_triangle_tests, bvh_box_tests = int(counted[:, 2].sum()), int(counted[:, 1].sum())
brute_triangle_tests = n_rays * n_triangles
tests_saved_factor = round(brute_triangle_tests / bvh_triangle_tests)
tests_per_hit_ray = counted[prim_id >= 0, 2].mean()
rays_missing_root = int((counted[:, 1] == 1).sum())  # one box test: the root's
rays_without_tests = int((counted[:, 2] == 0).sum())
print(f"same hits as Accelerator.closest_hit: {same_hits}; {rays_hitting} rays hit the teapot")
print(f"triangle tests: BVH {bvh_triangle_tests:,}, brute force {brute_triangle_tests:,} "
      f"({tests_saved_factor:.0f}x fewer); box tests {bvh_box_tests:,}")  # fmt: skip
print(f"a ray that hits the teapot tests {tests_per_hit_ray:.1f} triangles on average")

# %% [markdown]
# On the paper's view at 64 × 64 pixels (`4,096` <!-- check: n_rays --> rays, `639`
# <!-- check: rays_hitting --> of which hit the teapot), the walk finds the same triangle as
# the Numba BVH for every ray and needs `3,377` <!-- check: bvh_triangle_tests --> triangle
# tests in all, against `6,291,456` <!-- check: brute_triangle_tests --> for brute force:
# `1863` <!-- check: tests_saved_factor --> times fewer, for `34,652`
# <!-- check: bvh_box_tests --> box tests. A ray that hits the teapot tests `3.9`
# <!-- check: tests_per_hit_ray --> triangles on average. Most rays test none at all
# (`3,326` <!-- check: rays_without_tests -->): `2,404` <!-- check: rays_missing_root -->
# miss the root box, the others enter some boxes but no leaf's box. The SAH cost (20) is
# an estimate for rays spread evenly through the root box that visit every leaf they pass
# through; a closest-hit search visits the near leaves first and stops early.
#
# In wall time (Numba, both cores; the numbers vary with the machine and its load), with
# identical answers, bit for bit:

# %%
big = render.paper_scene(width=128, height=128)
eye_big, dirs_big = primary_rays(big.camera)
origins_big = np.broadcast_to(eye_big, dirs_big.shape)
brute = Accelerator(triangles, use_bvh=False)
seconds = {}
for name, acc in (("BVH", accel), ("brute force", brute)):
    times = []
    for _ in range(3):  # the best of three: the first call may load compiled code
        start = time.perf_counter()
        ids, *_ = acc.closest_hit(origins_big, dirs_big)
        times.append(time.perf_counter() - start)
    seconds[name] = min(times)
    print(f"{name:>12}: {len(dirs_big)} rays in {seconds[name] * 1e3:.1f} ms")
bvh_equals_brute = bool((accel.closest_hit(origins_big, dirs_big)[0] == ids).all())
print("identical hits:", bvh_equals_brute)

# %% [markdown]
# ## Figure: the top of the tree
#
# `bvh_levels.png` draws the teapot's triangles seen from the front (projected onto the
# `x–y` plane) and, in four panels, the boxes of the nodes at depth 0 (the root), 1, 2 and
# 3, projected the same way.


# %%
def nodes_by_depth(acc, levels):
    found, frontier = [], [0]
    for _ in range(levels):
        found.append(frontier)
        frontier = [ch for n in frontier if acc.node_count[n] == 0 for ch in (acc.node_first[n],
                    acc.node_first[n] + 1)]  # fmt: skip
    return found


def draw_levels(acc, path, levels=4, width=420):
    lo, hi = acc.node_bounds[0, :2], acc.node_bounds[0, 3:5]
    scale = (width - 40) / (hi[0] - lo[0])
    panel = (width, int(scale * (hi[1] - lo[1])) + 50)
    img = Image.new("RGB", (2 * panel[0], 2 * panel[1]), "white")
    draw = ImageDraw.Draw(img)
    colours = [(214, 39, 40), (31, 119, 180), (44, 160, 44), (255, 127, 14), (148, 103, 189)]
    for level, nodes in enumerate(nodes_by_depth(acc, levels)):
        ox, oy = (level % 2) * panel[0] + 20, (level // 2) * panel[1] + 30

        def xy(p, ox=ox, oy=oy):
            return ox + (p[0] - lo[0]) * scale, oy + (hi[1] - p[1]) * scale

        for tri in triangles:
            draw.polygon([xy(p) for p in tri], outline=(200, 200, 200))
        for i, n in enumerate(nodes):
            box = acc.node_bounds[n]
            (x0, y1), (x1, y0) = xy(box[:2]), xy(box[3:5])
            draw.rectangle([x0, y0, x1, y1], outline=colours[i % len(colours)], width=2)
        draw.text((ox, oy - 22), f"depth {level}: {len(nodes)} boxes", fill="black")
    img.save(path)


draw_levels(accel, OUT / "bvh_levels.png")
print(f"figures in {OUT}")

# %% [markdown]
# ## Exercises
#
# 1. The builder's only knob in `Accelerator` is `n_bins`, the number of candidate planes
#    per axis (plus one). Build the teapot's BVH with 2, 4, 12 and 32 bins and compare the
#    SAH cost and the counted triangle tests of the 64 × 64 paper view.
# 2. Edges are inclusive: a ray through the shared diagonal of a square made of two
#    triangles hits both. Show it with `intersect_triangle`, then show that
#    `Accelerator.closest_hit` returns the lower id (with and without the BVH) — and still
#    the lower id when the two triangles are listed in the other order.
# 3. Move the paper camera twice as far from the teapot (`camera_position=(6, 4, 10)`).
#    How do the number of rays that hit, the triangle tests and the factor saved over brute
#    force change? Why?
#
# Two you build yourself, checked against the library by `lessons/exercise_checks.py`
# (`from exercise_checks import ...` works from a lesson or a notebook in `lessons/`):
#
# 4. **A ray-triangle intersection.** Write `my_intersect(o, d, a, b, c)` for k rays and k
#    triangles at once, in NumPy, from the Möller–Trumbore derivation at the top of this
#    lesson: return `(t, u, v)`, with `t = inf` where the ray misses (parallel, outside the
#    triangle, or behind the origin). Run `check_intersection(my_intersect)`: 2,000 random
#    rays and triangles against `intersect_triangle`.
# 5. **A shadow ray through the BVH.** Write `my_occluded(acc, o, d, t_max)`: walk the
#    library's tree (the layout `closest_hit_counted` above uses) and return True as soon
#    as any triangle is hit at `0 < t < t_max`. An any-hit walk needs no ordering of the
#    children and may stop at the first hit. Run `check_any_hit(my_occluded)`: 400 rays
#    through the teapot against `Accelerator.occluded`.
#
# Solutions: `lessons/solutions/04_bvh.py`.
