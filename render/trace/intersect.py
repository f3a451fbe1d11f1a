"""Per-ray intersection kernels (Numba): ray-triangle, ray-sphere, ray-box and BVH traversal.

Everything here works on flat NumPy arrays so that Numba can compile it:

* ``leaf_prim`` (P, 16) float64 -- one row per primitive, see :func:`pack_primitives`.
  Triangles and spheres share the table; a row with global id ``< n_tri`` is a triangle.
* ``boxes`` (W, 32) float32 (``child``: the same rows read as int32), ``leaf_start`` (L + 1,)
  int64 -- the 4-wide BVH (``render.trace.wide``): four children's boxes a node, each child
  a node or a leaf, a leaf a range of rows of the leaf-ordered primitive table.

A ray is ``origin + t * direction`` with ``tmin < t < tmax``: one :class:`Ray` record per ray
(:func:`make_ray`), ``Rays`` for the arrays of N rays the parallel kernels take.

Brute force is the same traversal on a tree of a single leaf that holds every primitive in id
order under a box of all space (``render.trace.bvh.one_leaf``): every ray enters the leaf
and tests every primitive.  The single most important property of this module: a BVH
returns *bit-identical* results to that brute force.  This needs three ingredients:

1. The same per-primitive function (same floating-point operations) in both paths.
2. A total order on hits: ``(t, prim_id)`` lexicographically.  A ray through an edge shared by
   two triangles may hit both at exactly the same t; brute force would keep whichever it saw
   first, the BVH whichever leaf it opened first.  With the order, both keep the lower id.
3. Conservative node culling: a node is skipped only if it *cannot* contain an accepted hit.
   The BVH boxes are padded (see ``render.trace.bvh``) by far more than the rounding error of
   a hit point, and a node whose entry distance *equals* the current best t is still opened,
   because it may hold an equal-t hit with a lower id.

(The padding argument assumes ray origins within ~1e4 scene sizes of the scene; a stress
test with origins up to 1e8 scene sizes away still found no difference.)

All functions are compiled with ``error_model="numpy"``: a division by zero gives inf/NaN
instead of raising, so no exception can be raised inside a parallel loop.  The inputs are
validated in ``render.trace.accel`` so that it does not happen in the first place.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from minidiff.threads import borrowing, inlined, jit, job_count, kernel, run_jobs, share
from render.trace.simd import enter4
from render.trace.wide import CHILD, WIDTH

#: Row width of the primitive table (16 float64 = two 64-byte cache lines).
PRIM_WIDTH = 16

#: A triangle is a miss for a ray when |d . n| <= DEGENERATE_TOL * |d| * |e1| * |e2|, i.e.
#: when sin(angle between the edges) * cos(angle between ray and normal) is below the
#: tolerance. This catches zero-area triangles (sin ~ 0) and rays in the triangle's plane
#: (cos ~ 0), the two cases where the division by the determinant would blow up (or give
#: 0/0 = NaN).  It also bounds the rounding error of an accepted hit point to about 1e-9 of
#: the ray length, far below the BVH box padding, which is what makes BVH == brute force
#: exact.
DEGENERATE_TOL = 1e-7

#: Rays are dealt to the threads in blocks of this many consecutive rays (see the kernels).
BLOCK = 64

#: A second thread is used from this many rays a job on: starting a job on the pool costs
#: about 46 us (``minidiff.threads``), a thousand rays through the BVH some 100 us.
RAYS_PER_JOB = 1024


class FlatBVH(NamedTuple):
    """A BVH flattened for the kernels, passed as one argument (``closest_hit_ray(bvh, ...)``).

    boxes (W, 32) float32 and child, the same memory as int32, and leaf_start (L + 1,): the
    4-wide tree (see ``render.trace.wide``: a row's columns ``CHILD``.. are its children);
    leaf_prim (P, 16) / leaf_ids (P,): the primitive table and the global ids in leaf order;
    n_tri: ids below it are triangles; stack_size: the traversal stack's length, 3 per
    level of the binary tree it was collapsed from, plus 2 (near-first traversal pushes at
    most three nodes per level, and a wide level is at least one binary level).
    """

    boxes: np.ndarray
    child: np.ndarray
    leaf_start: np.ndarray
    leaf_prim: np.ndarray
    leaf_ids: np.ndarray
    n_tri: int
    stack_size: int


class Ray(NamedTuple):
    """One ray ``origin + t * direction``, ``tmin < t < tmax``, with what its tests reuse.

    origin, direction: (x, y, z) floats (the direction of any nonzero length: t is in its
    units); inverse: 1 / direction for the slab test (:func:`safe_inverse`); length:
    |direction| (the triangle test's tolerance scales with it); axes (kx, ky, kz), shear
    (sx, sy, sz) and the origin's coordinates in that order: the frame of the watertight
    triangle test (:func:`intersect_triangle`).  Made by :func:`make_ray`.
    """

    origin: tuple[float, float, float]
    direction: tuple[float, float, float]
    inverse: tuple[float, float, float]
    length: float
    tmin: float
    tmax: float
    axes: tuple[int, int, int]
    shear: tuple[float, float, float]
    axis_origin: tuple[float, float, float]


class Rays(NamedTuple):
    """N rays for the parallel kernels: ray i is ``origins[i * o_step] + t *
    directions[i * d_step]`` with ``tmin < t < tmax[i * t_step]`` (:func:`ray_at`).

    origins, directions (N, 3) or (1, 3) float64, tmax (N,) or (1,) float64, each with its
    step 1 or 0: a value shared by all rays (a camera's eye, a directional light, one
    tmax) is passed as its single row instead of a copy per ray.
    """

    origins: np.ndarray
    directions: np.ndarray
    o_step: int
    d_step: int
    tmin: float
    tmax: np.ndarray
    t_step: int


# --------------------------------------------------------------------------------------------
# Primitive table
# --------------------------------------------------------------------------------------------


def pack_primitives(
    triangles: np.ndarray,
    sphere_centers: np.ndarray,
    sphere_radii: np.ndarray,
    order: np.ndarray | None = None,
) -> np.ndarray:
    """Precompute the per-primitive data used by the intersection tests.

    triangles (T, 3, 3), sphere_centers (S, 3), sphere_radii (S,)  ->  prim_data (T+S, 16),
    row ``k`` for primitive ``order[k]`` (ids: triangles ``0..T-1``, then the spheres; by
    default in id order).  A BVH passes its leaf order, so that a leaf's rows are contiguous.

    Triangle row: ``a[0:3], b[3:6], c[6:9], n[9:12], cut[12]``: the corners as given (the
    watertight test needs each corner's own coordinates: a + (b - a) need not be b), the
    geometric normal ``n = (b - a) x (c - a)`` and ``cut = DEGENERATE_TOL*|b - a|*|c - a|``
    (``inf`` for a degenerate triangle, so that it can never be hit).
    Sphere row: ``centre[0:3], radius[3], radius**2[4]``. A test reads one 128-byte row.
    """
    if order is None:
        order = np.arange(len(triangles) + len(sphere_centers))
    data = np.zeros((len(order), PRIM_WIDTH))
    n_jobs = job_count(len(order), 16384)
    run_jobs(_pack_rows, n_jobs, triangles, sphere_centers, sphere_radii, order, data)
    return data


@kernel
def _pack_rows(job, n_jobs, triangles, sphere_centers, sphere_radii, order, data):
    """Job ``job`` of ``n_jobs`` of the loop of :func:`pack_primitives`: its share of the
    rows of ``data`` (rows are independent)."""
    T = triangles.shape[0]
    start, stop = share(job, n_jobs, order.shape[0])
    for i in range(start, stop):
        p = order[i]
        if p >= T:
            s = p - T
            # Element by element: a slice assignment compiles Numba's shape checks (over a
            # second of a cold start).
            for a in range(3):
                data[i, a] = sphere_centers[s, a]
            data[i, 3] = sphere_radii[s]
            data[i, 4] = sphere_radii[s] * sphere_radii[s]
            continue
        for a in range(3):
            data[i, a] = triangles[p, 0, a]
            data[i, 3 + a] = triangles[p, 1, a]
            data[i, 6 + a] = triangles[p, 2, a]
        e1x, e1y, e1z = data[i, 3] - data[i, 0], data[i, 4] - data[i, 1], data[i, 5] - data[i, 2]
        e2x, e2y, e2z = data[i, 6] - data[i, 0], data[i, 7] - data[i, 1], data[i, 8] - data[i, 2]
        nx = e1y * e2z - e1z * e2y
        ny = e1z * e2x - e1x * e2z
        nz = e1x * e2y - e1y * e2x
        data[i, 9] = nx
        data[i, 10] = ny
        data[i, 11] = nz
        cut = DEGENERATE_TOL * np.sqrt(
            (e1x * e1x + e1y * e1y + e1z * e1z) * (e2x * e2x + e2y * e2y + e2z * e2z)
        )
        # |n| / (|e1| |e2|) is the sine of the angle between the edges; below the tolerance
        # the triangle is a sliver or a point and no ray can pass the det test reliably.
        if np.sqrt(nx * nx + ny * ny + nz * nz) <= cut:
            cut = np.inf
        data[i, 12] = cut


# --------------------------------------------------------------------------------------------
# Rays
# --------------------------------------------------------------------------------------------


@jit(cache=True, inline="always")
def safe_inverse(d):
    """1/d for the slab test, with exact zeros replaced by a tiny positive number: then
    ``(bound - origin) * inv`` is huge (or +-inf) or exactly 0, never ``0 * inf = NaN``."""
    if d == 0.0:
        d = 1e-300
    return 1.0 / d


@inlined
def make_ray(origin, direction, tmin, tmax):
    """The :class:`Ray` ``origin + t * direction``, ``tmin < t < tmax``; origin and direction
    are 3-tuples of floats (every caller passes tuples, so it is compiled once)."""
    dx, dy, dz = direction[0], direction[1], direction[2]
    ox, oy, oz = origin[0], origin[1], origin[2]
    # The watertight test's frame: z along the direction's largest component, x and y the
    # other two in turn (swapped where that component is negative, to keep the winding).
    # Written out: a tuple indexed by a variable is slow in Numba.
    if abs(dx) >= abs(dy) and abs(dx) >= abs(dz):
        axes, (a, b, c), (oa, ob, oc) = (1, 2, 0), (dy, dz, dx), (oy, oz, ox)
    elif abs(dy) >= abs(dz):
        axes, (a, b, c), (oa, ob, oc) = (2, 0, 1), (dz, dx, dy), (oz, ox, oy)
    else:
        axes, (a, b, c), (oa, ob, oc) = (0, 1, 2), (dx, dy, dz), (ox, oy, oz)
    if c < 0.0:
        axes, a, b, oa, ob = (axes[1], axes[0], axes[2]), b, a, ob, oa
    return Ray(
        (ox, oy, oz),
        (dx, dy, dz),
        (safe_inverse(dx), safe_inverse(dy), safe_inverse(dz)),
        np.sqrt(dx * dx + dy * dy + dz * dz),
        tmin,
        tmax,
        axes,
        (a / c, b / c, 1.0 / c),
        (oa, ob, oc),
    )


@inlined
def ray_at(rays, i):
    """Ray ``i`` of ``rays`` (a :class:`Rays`) as a :class:`Ray`. (Elements read one by one
    into tuples: ``make_ray`` is compiled for tuples only, and no row view is made.)"""
    o, d = i * rays.o_step, i * rays.d_step
    return make_ray(
        (rays.origins[o, 0], rays.origins[o, 1], rays.origins[o, 2]),
        (rays.directions[d, 0], rays.directions[d, 1], rays.directions[d, 2]),
        rays.tmin,
        rays.tmax[i * rays.t_step],
    )


# --------------------------------------------------------------------------------------------
# Ray-primitive tests (scalar; shared by the traversal, the rasteriser and the light's view)
# --------------------------------------------------------------------------------------------


@jit(cache=True, inline="always")
def intersect_triangle(prim, k, ray):
    """Watertight test of ``ray`` (a :class:`Ray`) against row ``k`` of ``prim`` (P, 16)
    (Woop, Benthin and Wald 2013, "Watertight Ray/Triangle Intersection").

    Returns ``(t, u, v)`` with ``t > ray.tmin``; ``t = inf`` for a miss (the caller compares
    t with its own upper bound).  The hit point is ``(1-u-v)*a + u*b + v*c``.

    The corners are moved into the ray's frame (``make_ray``: origin at the ray's, the
    direction sheared onto the z axis), where the ray is the point (0, 0) and its side of
    each edge is a 2-D cross product of the edge's two corners: ``e_u``, ``e_v``, ``e_w``
    for the edges b-c, c-a and a-b. A corner's coordinates there depend on that corner
    alone, and an edge's product with its ends swapped is exactly the negative (``x*y -
    z*w = -(z*w - x*y)`` in floating point), so two triangles sharing an edge always agree
    on which side of it the ray passes: a ray through a closed mesh's edge or corner hits
    a face there, never slips between them (``tests/render/trace/test_watertight.py``;
    Moller-Trumbore, which this replaced, let 4 of 66 such rays through an octahedron's
    edges). The sides are inclusive (0 is inside; either winding is a face) and the (t,
    id) order picks one where several are hit.

    Misses: rays within DEGENERATE_TOL of the triangle's plane (relative to its edges,
    by the normal ``n``: where t's rounding would be unbounded, which is what keeps the
    BVH's answers equal to brute force's) and degenerate triangles (``cut = inf``)."""
    kx, ky, kz = ray.axes
    sx, sy, sz = ray.shear
    ox, oy, oz = ray.axis_origin  # (a tuple indexed by a variable is slow in Numba)
    az, bz, cz = prim[k, kz] - oz, prim[k, 3 + kz] - oz, prim[k, 6 + kz] - oz
    bx = (prim[k, 3 + kx] - ox) - sx * bz
    by = (prim[k, 3 + ky] - oy) - sy * bz
    cx = (prim[k, 6 + kx] - ox) - sx * cz
    cy = (prim[k, 6 + ky] - oy) - sy * cz
    e_u = cx * by - cy * bx
    ax = (prim[k, kx] - ox) - sx * az
    ay = (prim[k, ky] - oy) - sy * az
    e_v = ax * cy - ay * cx
    # Sides of opposite signs: outside (most rays leave here, before the third side).
    if (e_u < 0.0 and e_v > 0.0) or (e_u > 0.0 and e_v < 0.0):
        return np.inf, 0.0, 0.0
    e_w = bx * ay - by * ax
    if (e_u < 0.0 or e_v < 0.0 or e_w < 0.0) and (e_u > 0.0 or e_v > 0.0 or e_w > 0.0):
        return np.inf, 0.0, 0.0
    dx, dy, dz = ray.direction
    if abs(dx * prim[k, 9] + dy * prim[k, 10] + dz * prim[k, 11]) <= ray.length * prim[k, 12]:
        return np.inf, 0.0, 0.0
    det = e_u + e_v + e_w
    if det == 0.0:
        return np.inf, 0.0, 0.0
    inv = 1.0 / det
    t = (e_u * (sz * az) + e_v * (sz * bz) + e_w * (sz * cz)) * inv
    if not t > ray.tmin:
        return np.inf, 0.0, 0.0
    return t, e_v * inv, e_w * inv


@jit(cache=True, inline="always")
def intersect_sphere(prim, k, ray):
    """Ray-sphere test of ``ray`` against row ``k`` of ``prim``; returns the nearest root
    ``t > ray.tmin`` (``inf`` for a miss).

    Solves |o + t d - c|^2 = r^2, i.e. a t^2 - 2 b t + c0 = 0 with a = d.d, b = -(o-c).d,
    c0 = |o-c|^2 - r^2.  Two numerically careful choices ("Precision Improvements for
    Ray/Sphere Intersection", Ray Tracing Gems ch. 7):
    the discriminant b^2 - a c0 is computed as a (r^2 - |l|^2) with l the perpendicular from the
    centre to the ray (no catastrophic cancellation for small spheres far away), and the roots
    as c0/q and q/a with q = b + sign(b) sqrt(disc) (no cancellation between b and sqrt(disc)).
    """
    ox, oy, oz = ray.origin
    dx, dy, dz = ray.direction
    fx = ox - prim[k, 0]
    fy = oy - prim[k, 1]
    fz = oz - prim[k, 2]
    a = dx * dx + dy * dy + dz * dz
    b = -(fx * dx + fy * dy + fz * dz)
    s = b / a
    lx = fx + s * dx
    ly = fy + s * dy
    lz = fz + s * dz
    disc = a * (prim[k, 4] - (lx * lx + ly * ly + lz * lz))
    if disc < 0.0:
        return np.inf
    c0 = fx * fx + fy * fy + fz * fz - prim[k, 4]
    q = b + np.copysign(np.sqrt(disc), b)
    if q == 0.0:
        # b == 0 and disc == 0: a tangent ray whose origin is the touching point.
        t0 = 0.0
        t1 = 0.0
    else:
        t0 = c0 / q
        t1 = q / a
        if t0 > t1:
            t0, t1 = t1, t0
    if t0 > ray.tmin:
        return t0
    if t1 > ray.tmin:
        return t1
    return np.inf


@inlined
def intersect_prim(prim, k, pid, n_tri, ray):
    """Test of ``ray`` against row ``k`` of ``prim``, primitive ``pid``: a triangle if
    ``pid < n_tri``, else a sphere.  Returns ``(t, u, v)`` with ``t = inf`` for a miss
    (u = v = 0 for spheres)."""
    if pid < n_tri:
        return intersect_triangle(prim, k, ray)
    return intersect_sphere(prim, k, ray), 0.0, 0.0


@jit(cache=True, inline="always")
def enter_slot(boxes, w, k, ray, t_far):
    """Slab test of ``ray`` against slot ``k`` of wide node ``w`` of ``boxes`` (W, 32)
    (``render.trace.wide``): the plain version of ``render.trace.simd.enter4``, which tests
    the four slots at once with the same arithmetic (``tests/render/trace/test_wide.py``).

    Returns the entry distance ``max(tmin, t_enter)`` if the ray overlaps the box somewhere in
    ``[ray.tmin, t_far]`` (both ends inclusive, see the tie rule), else ``inf`` (an empty
    slot's box, both corners at +inf, is always missed). The slab distances are ``(plane -
    origin) / d``, computed with the ray's inverse direction (a product is much cheaper than
    a division) in float64, from the float32 planes.
    """
    ox, oy, oz = ray.origin
    ix, iy, iz = ray.inverse
    x0 = (boxes[w, k] - ox) * ix
    x1 = (boxes[w, 3 * WIDTH + k] - ox) * ix
    y0 = (boxes[w, WIDTH + k] - oy) * iy
    y1 = (boxes[w, 4 * WIDTH + k] - oy) * iy
    z0 = (boxes[w, 2 * WIDTH + k] - oz) * iz
    z1 = (boxes[w, 5 * WIDTH + k] - oz) * iz
    t_enter = max(max(min(x0, x1), min(y0, y1)), max(min(z0, z1), ray.tmin))
    t_leave = min(min(max(x0, x1), max(y0, y1)), min(max(z0, z1), t_far))
    if t_enter <= t_leave:
        return t_enter
    return np.inf


# --------------------------------------------------------------------------------------------
# Single-ray traversal
# --------------------------------------------------------------------------------------------
# The per-ray functions are inlined into the parallel kernels: as a real call, passing five
# arrays (each a struct of pointer, shape, strides, ...) per ray cost about 30% of the
# traversal time; still 8% (the 1.3M-triangle mesh's camera rays) and 18% of the path kernel
# with the call compiled without reference counts (a ``borrowing`` function). Inlined by
# Numba (``inline="always"``), each kernel typed and compiled its own copy of the traversal
# (1.8-2.1 s of a cold start each); ``inlined`` (``minidiff.threads``) compiles the
# traversals, the ray-primitive test and ``make_ray`` once, and LLVM inlines that code into
# each kernel: the same speed (the 1.3M mesh's camera, random, shadow and segment rays 61,
# 41, 43, 21 ms either way), a cold first boundary gradient 28.1 -> 21.8 s.


@jit(cache=True, inline="always")
def _pop(stack, stack_t, sp, best_t):
    """Pop the most recently pushed node that can still hold an accepted hit (entry distance
    ``<= best_t``; equal is kept for the tie rule).  Returns ``(code, sp)`` (a child code of
    ``render.trace.wide``); ``sp = -1`` when the stack runs empty."""
    while sp > 0:
        sp -= 1
        if stack_t[sp] <= best_t:
            return stack[sp], sp
    return 0, -1


@jit(cache=True, inline="always")
def _next(stack, sp):
    """Pop the most recently pushed node: ``(code, sp)``, ``sp = -1`` when the stack is
    empty."""
    if sp == 0:
        return 0, -1
    return stack[sp - 1], sp - 1


@jit(cache=True, inline="always")
def _push_if(stack, sp, code, entry):
    """Push ``code`` if its box was entered (``entry`` finite); returns the new ``sp``."""
    if entry != np.inf:
        stack[sp] = code
        return sp + 1
    return sp


@jit(cache=True, inline="always")
def _leaf_rows(bvh, code):
    """Rows ``start:stop`` of the leaf-ordered table that the leaf of child code ``code`` (<
    0) holds."""
    return bvh.leaf_start[~code], bvh.leaf_start[~code + 1]


# Both leaf loops are inlined into the traversal. The binary tree's traversal called the
# closest-hit loop as a function of its own: inlined there, brute force's one long leaf ran
# at 85 ms when the kernel was compiled in the process but at 135 ms when it was loaded
# from Numba's cache. With the 4-wide tree, inlined, the closest hits of the 82k-triangle
# scene's camera rays take 30.6 ms against 41.9 ms as a call (and 30.8 ms loaded from the
# cache), brute force's the same either way (1,920 triangles, 16,384 rays: 205 ms), and
# compiling the renderer's kernels (``tests/warm_kernels.py`` in one process) 84 s against
# 76 s.


@jit(cache=True, inline="always")
def _closest_in_leaf(table, ids, n_tri, start, stop, ray, best):
    """``best`` = (prim_id, t, u, v) updated with the hits of ``ray`` on rows ``start:stop``
    of ``table`` (primitives ``ids[start:stop]``), in the (t, id) order."""
    best_id, best_t, best_u, best_v = best
    for k in range(start, stop):
        pid = ids[k]
        t, u, v = intersect_prim(table, k, pid, n_tri, ray)
        # Lexicographic (t, id) order: an exact tie goes to the lower id.  best_id starts at
        # -1, so a hit exactly at tmax is never accepted.
        if t < best_t or (t == best_t and pid < best_id):
            best_id = pid
            best_t = t
            best_u = u
            best_v = v
    return best_id, best_t, best_u, best_v


@jit(cache=True, inline="always")
def _blocked_in_leaf(table, ids, n_tri, start, stop, ray, ignore):
    """Whether ``ray`` hits one of the primitives ``ids[start:stop]`` (rows ``start:stop`` of
    ``table``) other than ``ignore`` before ``ray.tmax``."""
    for k in range(start, stop):
        pid = ids[k]
        if pid != ignore and intersect_prim(table, k, pid, n_tri, ray)[0] < ray.tmax:
            return True
    return False


@inlined
def meets_before_end(table, k, pid, n_tri, ray):
    """Whether row ``k`` of ``table`` (primitive ``pid``) meets ``ray`` before its tmax,
    where a kernel tests one primitive outside its main loop (``occluded_bvh``'s hint, the
    rasterised tests' rays that no list covers)."""
    return intersect_prim(table, k, pid, n_tri, ray)[0] < ray.tmax


@inlined
def closest_hit_ray(bvh, ray, stack, stack_t):
    """Closest hit of ``ray`` (a :class:`Ray`) in ``bvh`` (a :class:`FlatBVH`): returns
    ``(prim_id, t, u, v)``, ``(-1, inf, 0, 0)`` for a miss.  ``stack`` int64 and ``stack_t``
    float64 (``bvh.stack_size``,) are scratch space supplied by the caller (allocating them
    per ray would dominate the cost).

    Iterative traversal, near child first: at a node all four children's boxes are tested,
    sorted by entry distance (five compare-exchanges), the farther ones that were hit are
    pushed with their entry distances and the nearest is taken next. Visiting near boxes
    first finds a close hit early, which shrinks ``best_t`` and lets us skip the far boxes
    when they are popped (their entry distance is then > best_t).
    """
    # -1 as an int64, not the literal -1: the leaf loop compiles for one type of ``best``
    # (the literal gave it a second signature, a second compile of the same code).
    best = (np.int64(-1), ray.tmax, 0.0, 0.0)
    if bvh.child.shape[0] == 0:
        return -1, np.inf, 0.0, 0.0
    boxes, child = bvh.boxes, bvh.child
    code = 0
    sp = 0
    while sp >= 0:
        if code < 0:
            start, stop = _leaf_rows(bvh, code)
            best = _closest_in_leaf(bvh.leaf_prim, bvh.leaf_ids, bvh.n_tri, start, stop, ray, best)
            code, sp = _pop(stack, stack_t, sp, best[1])
            continue
        w = code
        d0, d1, d2, d3 = enter4(boxes, w, ray.origin, ray.inverse, ray.tmin, best[1])
        c0, c1 = child[w, CHILD], child[w, CHILD + 1]
        c2, c3 = child[w, CHILD + 2], child[w, CHILD + 3]
        # Sort the four (entry, child) pairs by entry; misses (inf) go last.
        if d1 < d0:
            d0, d1, c0, c1 = d1, d0, c1, c0
        if d3 < d2:
            d2, d3, c2, c3 = d3, d2, c3, c2
        if d2 < d0:
            d0, d2, c0, c2 = d2, d0, c2, c0
        if d3 < d1:
            d1, d3, c1, c3 = d3, d1, c3, c1
        if d2 < d1:
            d1, d2, c1, c2 = d2, d1, c2, c1
        if d0 == np.inf:  # every child missed
            code, sp = _pop(stack, stack_t, sp, best[1])
            continue
        if d3 != np.inf:
            stack[sp], stack_t[sp] = c3, d3
            sp += 1
        if d2 != np.inf:
            stack[sp], stack_t[sp] = c2, d2
            sp += 1
        if d1 != np.inf:
            stack[sp], stack_t[sp] = c1, d1
            sp += 1
        code = c0
    if best[0] < 0:
        return -1, np.inf, 0.0, 0.0
    return best


@inlined
def occluded_ray(bvh, ray, ignore, stack):
    """Any-hit query of a shadow ``ray`` in ``bvh``: True if some primitive other than
    ``ignore`` is hit with ``ray.tmin < t < ray.tmax``.  Stops at the first such hit.  Same
    structure as :func:`closest_hit_ray` but without near-first ordering: most shadow rays
    are *not* blocked and must visit every overlapping node anyway, so sorting the children
    costs more than the earlier exit saves (measured on the binary tree, and on this one:
    ``benchmarks/bench_embree.py``'s shadow rays at 1.3M triangles took 48.5 ms sorted
    against 40.2 ms, one thread; pushing the leaf children last, to test them first, the
    children stored and pushed in the order of their centres along one axis, pushes
    without branches or looping over a mask of the entered slots, and a prefetch of each
    pushed node were slower too: docs/benchmarks.md,
    "BVH against Embree").  ``stack`` (``bvh.stack_size``,) int64 is scratch space."""
    if bvh.child.shape[0] == 0:
        return False
    code = 0
    sp = 0
    while sp >= 0:
        if code < 0:
            start, stop = _leaf_rows(bvh, code)
            if _blocked_in_leaf(bvh.leaf_prim, bvh.leaf_ids, bvh.n_tri, start, stop, ray, ignore):
                return True
        else:
            d0, d1, d2, d3 = enter4(bvh.boxes, code, ray.origin, ray.inverse, ray.tmin, ray.tmax)
            # (written out: a tuple indexed by a variable is slow in Numba)
            sp = _push_if(stack, sp, bvh.child[code, CHILD], d0)
            sp = _push_if(stack, sp, bvh.child[code, CHILD + 1], d1)
            sp = _push_if(stack, sp, bvh.child[code, CHILD + 2], d2)
            sp = _push_if(stack, sp, bvh.child[code, CHILD + 3], d3)
        code, sp = _next(stack, sp)
    return False


@borrowing
def closest_hit_one(bvh, origin, direction, tmin, stack, stack_t):
    """:func:`closest_hit_ray` of the ray ``origin + t direction``, ``t > tmin`` (origin and
    direction (x, y, z) floats): (prim, t, u, v). For kernels that trace a ray among other
    work (the path kernel, the shadow borders' chords): a call, not inlined into them:
    inlined (``inlined``), the path kernel's cold first gradient took 17.0 s against 14.7 s
    and its forward ran no faster (107.6 against 111.1 ms, Cornell box 128x128, 16 spp)."""
    return closest_hit_ray(bvh, make_ray(origin, direction, tmin, np.inf), stack, stack_t)


@borrowing
def occluded_one(bvh, origin, direction, tmax, ignore, stack):
    """:func:`occluded_ray` of the ray ``origin + t direction``, ``0 < t < tmax``, ignoring
    primitive ``ignore``; one compiled copy, as :func:`closest_hit_one`."""
    return occluded_ray(bvh, make_ray(origin, direction, 0.0, tmax), ignore, stack)


# --------------------------------------------------------------------------------------------
# Parallel kernels over ray arrays
# --------------------------------------------------------------------------------------------
# Jobs run on the threads of ``minidiff.threads`` (``threads.run_jobs(kernel, n_jobs, ...)``
# calls ``kernel(job, n_jobs, ...)`` once per job; ``threads.job_count(N, BLOCK)`` jobs:
# one per thread). Job j takes blocks j, j + n_jobs, j + 2 n_jobs, ... of BLOCK consecutive
# rays, in order.  The interleave shares the image out evenly (a contiguous split would give
# one thread all the sky and the other all the teapot), and walking each thread's rays in
# order keeps consecutive rays alike, whose branches go the same way: brute force on every
# 16th camera ray of the teapot (1 thread) took 98 ms when the blocks were dealt to 64 jobs
# (a jump of 64 blocks after each), 76 ms in order; the BVH's camera rays 12.0 against
# 10.4 ms, its shadow rays 4.8 against 4.0 ms (the same per-ray code, dealt either way).
# Each job allocates its traversal stack once.


@jit(cache=True, inline="always")
def n_blocks(n_rays):
    """How many blocks of BLOCK rays N rays make."""
    return (n_rays + BLOCK - 1) // BLOCK


@kernel
def closest_hit_bvh(job, n_jobs, bvh, rays, out_id, out_t, out_u, out_v):
    """Job ``job`` of ``n_jobs`` (``minidiff.threads.run_jobs``) of the closest hits of N
    rays (a :class:`Rays`) in ``bvh`` (a :class:`FlatBVH`): written to out_id (N,) int64,
    out_t, out_u, out_v (N,) float64 (see :func:`closest_hit_ray`)."""
    n = out_id.shape[0]
    stack = np.empty(bvh.stack_size, np.int64)
    stack_t = np.empty(bvh.stack_size, np.float64)
    for b in range(job, n_blocks(n), n_jobs):
        for i in range(b * BLOCK, min(n, (b + 1) * BLOCK)):
            out_id[i], out_t[i], out_u[i], out_v[i] = closest_hit_ray(
                bvh, ray_at(rays, i), stack, stack_t
            )


@kernel
def occluded_bvh(job, n_jobs, bvh, rays, ignore, first_row, out):
    """Job ``job`` of ``n_jobs`` of the any-hit of N shadow rays (a :class:`Rays`) in
    ``bvh`` (a :class:`FlatBVH`), each ignoring primitive ``ignore[i]`` (N,) int64 (-1:
    none): written to out (N,) bool (see :func:`occluded_ray`).

    ``first_row`` (N,) int64, or empty: a row of the leaf table to test before the
    traversal (-1: none). A ray that primitive blocks is blocked, and needs no traversal;
    the answer is the traversal's, which would test that primitive too (its leaf's box
    holds it)."""
    n = out.shape[0]
    hinted = first_row.shape[0] > 0
    stack = np.empty(bvh.stack_size, np.int64)
    for b in range(job, n_blocks(n), n_jobs):
        for i in range(b * BLOCK, min(n, (b + 1) * BLOCK)):
            ray = ray_at(rays, i)
            k = first_row[i] if hinted else -1
            if (
                k >= 0
                and bvh.leaf_ids[k] != ignore[i]
                and meets_before_end(bvh.leaf_prim, k, bvh.leaf_ids[k], bvh.n_tri, ray)
            ):
                out[i] = True
            else:
                out[i] = occluded_ray(bvh, ray, ignore[i], stack)
