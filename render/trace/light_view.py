"""Shadow rays towards a point light, answered in the light's view: the BVH's answers, found
primitive by primitive.

Every shadow ray towards a point light lies on a line through the light, so a primitive can
block it only if it covers the ray's direction *as seen from the light*: the camera
rasteriser's idea (``render.trace.raster``) with the light as the eye.

1. View: look from the light towards the middle of the rays' origins, with a grid of cells
   over the directions the rays take, about RAYS_PER_CELL rays per cell
   (:func:`occluded_towards_light`, :func:`_light_view`). Rays fanning out too widely for
   one view (beyond MIN_VIEW_COSINE of its axis) are left to the BVH.
2. Bin: each primitive's projected box lists it in the cells it overlaps, nearest the light
   first (``raster.screen_boxes``, ``raster.bin_to_tiles``, ``raster.nearest_depths``).
3. Test: each ray against its own cell's list with the tracer's ray-primitive function,
   skipping primitives whose projected edges rule it out and stopping at the first one
   wholly farther from the light than the ray's start: ``raster.blocked_by_list``, the
   camera rasteriser's occlusion test.

Any-hit is a yes or no, and the lists are conservative, so the answers are the BVH's (and
brute force's): ``tests/render/trace/test_light_view.py`` checks it on random soups and
spheres, shared edges and vertices, scenes far from the origin, and rendered images. Where
rounding in the directions from the light could put a point in the wrong cell (primitives or
ray origins very close to the light), the primitive is listed in every cell and the ray tested
against every primitive.
"""

from __future__ import annotations

import numpy as np

from minidiff.threads import jit, job_count, kernel, run_jobs
from render.trace.intersect import BLOCK, RAYS_PER_JOB, make_ray, n_blocks, pack_primitives
from render.trace.raster import (
    EDGE_MARGIN,
    bin_to_tiles,
    blocked_by_any,
    blocked_by_list,
    nearest_depths,
    screen_boxes,
)
from render.trace.vec3 import EPS, cross, dot3

#: Shadow rays per cell of the light's grid: fewer cells mean longer lists per ray, more
#: cells more binning per primitive.
RAYS_PER_CELL = 4

#: The light's view is used only if every ray leaves the light within ~70 degrees of the
#: view axis (the cosine of their angle is at least this); wider fans go to the BVH.
MIN_VIEW_COSINE = 0.35


def occluded_towards_light(
    primitives: tuple[np.ndarray, np.ndarray, np.ndarray],
    light: np.ndarray,
    origins: np.ndarray,
    directions: np.ndarray,
    tmax: np.ndarray,
    ignore: np.ndarray,
) -> np.ndarray | None:
    """(N,) bool: ``Accelerator.occluded(origins, directions, tmax, tmin=0, ignore)`` for
    shadow rays towards the point ``light`` (3,), found by binning the primitives in the
    light's view; None if the rays fan out too widely for one view (use the BVH then).

    primitives: ``(triangles (T, 3, 3), centres (S, 3), radii (S,))``; origins and
    directions (N, 3) with every ray's line through the light: ``directions = light -
    origins`` and 0 <= tmax (N,) < 1, as ``render.trace.visibility.shadow_rays`` makes them
    (tmax = 0: the light is at the ray's start, nothing is between).
    """
    out = np.zeros(len(origins), np.bool_)
    if len(origins) == 0:
        return out
    fits, forward, right, up, spread = _light_view(light, origins, MIN_VIEW_COSINE)
    if not fits:
        return None
    # Cells: about RAYS_PER_CELL rays each, about square (right and up are the half extents).
    n_cells = max(1, len(origins) // RAYS_PER_CELL)
    half_x, half_y = np.sqrt(right @ right), np.sqrt(up @ up)
    width = int(np.clip(np.sqrt(n_cells * half_x / half_y), 1, 4096))
    height = int(np.clip(n_cells // width, 1, 4096))
    # Directions from the light are only as exact as the points are far from it: closer
    # than ``close``, rounding may move a point by more than half the margin of a cell.
    # Primitives that come that close are listed in every cell, and rays that start that
    # close are tested against every primitive.
    cell = min(2.0 * half_x / width, 2.0 * half_y / height)  # in tangents
    close = spread / (0.5 * EDGE_MARGIN * cell)
    triangles, centers, radii = primitives
    view = (light, forward, right, up, width, height)
    boxes, edges = screen_boxes(triangles, centers, radii, *view, np.zeros((1, 2)))
    near = nearest_depths(triangles, centers, radii, light, forward)
    boxes[near <= close] = (0, 0, width - 1, height - 1)
    edges[near <= close] = ((0.0, 0.0, 1.0),) * 3  # no edge test for them either
    # Each cell's list nearest first, so that a ray can stop at the first primitive that is
    # wholly farther from the light than the ray's start.
    start, ids = bin_to_tiles(boxes, width, height, 1, np.argsort(near, kind="stable"))
    prim_data = pack_primitives(triangles, centers, radii)
    run_jobs(_occluded_by_cell, job_count(len(out), RAYS_PER_JOB), prim_data, len(triangles), start,
             ids, near, edges, view, close, origins, directions, tmax, ignore, out)  # fmt: skip
    return out


@jit(cache=True)
def _light_view(light, origins, min_cosine):
    """The light's view of the rays: (fits, forward, right, up, spread); fits is False if
    the rays fan out wider than ``min_cosine`` allows.

    forward points from the light to the middle of the rays' origins' bounding box; right
    and up are perpendicular to it, scaled so that every origin's image-plane position
    (``render.scene.camera``) is within [-1, 1]: the box's corners are (a cone around forward is
    convex, and a box's projection is that of its corners). spread / depth bounds how far
    (in image-plane units, tangents) rounding can move the image of a point at that depth
    from the light: the image of a ray's origin, or of the end of its segment near the
    light (its direction is light - origin rounded).

    Written with scalars and ``render.trace.vec3`` (not ``@``, ``np.abs(...).max()``): the
    same work, a fraction of the cold compile (1.46 s before, most of it NumPy's
    functions compiled for Numba).
    """
    lo, hi = bounding_box(origins)
    mid = ((lo[0] + hi[0]) / 2.0 - light[0], (lo[1] + hi[1]) / 2.0 - light[1],
           (lo[2] + hi[2]) / 2.0 - light[2])  # fmt: skip
    length = np.sqrt(dot3(mid, mid))
    forward = (mid[0] / length, mid[1] / length, mid[2] / length)
    # Any unit vector perpendicular to forward, then the third axis.
    helper = (1.0, 0.0, 0.0) if abs(forward[0]) < 0.9 else (0.0, 1.0, 0.0)
    side = _unit(cross(forward, helper))
    upward = cross(side, forward)
    # False if the box's middle is the light
    fits = np.isfinite(forward[0]) and np.isfinite(forward[1]) and np.isfinite(forward[2])
    reach_x = reach_y = 0.0
    size = max(abs(light[0]), abs(light[1]), abs(light[2]))
    for k in range(8):
        corner = (
            (hi[0] if k & 1 else lo[0]) - light[0],
            (hi[1] if k >> 1 & 1 else lo[1]) - light[1],
            (hi[2] if k >> 2 & 1 else lo[2]) - light[2],
        )
        depth = dot3(corner, forward)
        fits &= depth >= min_cosine * np.sqrt(dot3(corner, corner))
        reach_x = max(reach_x, abs(dot3(corner, side)) / depth)
        reach_y = max(reach_y, abs(dot3(corner, upward)) / depth)
    # A little room so that the outermost rays fall inside the grid.
    reach_x = reach_x * (1.0 + 1e-6) + 1e-12
    reach_y = reach_y * (1.0 + 1e-6) + 1e-12
    # A few ulps of the coordinates involved, at most, moved over the depth.
    far = max(abs(lo[0]), abs(lo[1]), abs(lo[2]), abs(hi[0]), abs(hi[1]), abs(hi[2]))
    spread = 8.0 * EPS * (size + far) * (1.0 + reach_x + reach_y)
    right = np.array([side[0] * reach_x, side[1] * reach_x, side[2] * reach_x])
    up = np.array([upward[0] * reach_y, upward[1] * reach_y, upward[2] * reach_y])
    return fits, np.array([forward[0], forward[1], forward[2]]), right, up, spread


@jit(cache=True, inline="always")
def _unit(x):
    """The 3-tuple x divided by its length."""
    length = np.sqrt(x[0] * x[0] + x[1] * x[1] + x[2] * x[2])
    return (x[0] / length, x[1] / length, x[2] / length)


@jit(cache=True)
def bounding_box(points):
    """The bounding box (lo (3,), hi (3,)) of points (N, 3), N >= 1, in one pass (NumPy's
    min(axis=0) pays a loop set-up per row of 3)."""
    # Six scalars, not two arrays: LLVM keeps them in registers (array elements it must
    # load and store each time, as the arrays might overlap ``points``).
    x0 = x1 = points[0, 0]
    y0 = y1 = points[0, 1]
    z0 = z1 = points[0, 2]
    for i in range(1, points.shape[0]):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        x0, x1 = min(x0, x), max(x1, x)
        y0, y1 = min(y0, y), max(y1, y)
        z0, z1 = min(z0, z), max(z1, z)
    return np.array([x0, y0, z0]), np.array([x1, y1, z1])


@kernel
def _occluded_by_cell(job, n_jobs, prim_data, n_tri, start, ids, near, edges, view, close,
                      origins, directions, tmax, ignore, out):  # fmt: skip
    """Job ``job`` of ``n_jobs`` (``minidiff.threads.run_jobs``): any-hit of its rays
    against the list of its cell of the light's ``view`` (tmin = 0, as the shadow rays),
    nearest first, up to the first primitive wholly beyond the ray's start, skipping those
    whose ``edges`` rule it out; against every primitive if the ray starts within depth
    ``close`` of the light."""
    light, forward, right, up, width, height = view
    rr, uu = dot3(right, right), dot3(up, up)
    eps = EPS
    light_size = max(abs(light[0]), abs(light[1]), abs(light[2]))
    # Blocks of rays dealt round-robin to the jobs (``render.trace.intersect``): contiguous
    # halves gave one thread the shadowed rows of the image and the other the lit ones.
    for block in range(job, n_blocks(out.shape[0]), n_jobs):
        for i in range(block * BLOCK, min(out.shape[0], (block + 1) * BLOCK)):
            _occluded_ray(prim_data, n_tri, start, ids, near, edges, view, close, origins,
                          directions, tmax, ignore, out, i, rr, uu, eps, light_size)  # fmt: skip


@jit(cache=True, inline="always")
def _occluded_ray(prim_data, n_tri, start, ids, near, edges, view, close, origins, directions,
                  tmax, ignore, out, i, rr, uu, eps, light_size):  # fmt: skip
    """``_occluded_by_cell`` for ray i."""
    light, forward, right, up, width, height = view
    if tmax[i] > 0.0:  # else the light is at the ray's start: nothing between
        ox, oy, oz = origins[i, 0], origins[i, 1], origins[i, 2]
        wx, wy, wz = ox - light[0], oy - light[1], oz - light[2]
        # The ray's cell: its origin's position as raster._project computes it for points.
        depth = wx * forward[0] + wy * forward[1] + wz * forward[2]
        x = (wx * right[0] + wy * right[1] + wz * right[2]) / (rr * depth)
        y = (wx * up[0] + wy * up[1] + wz * up[2]) / (uu * depth)
        px, py = (x + 1.0) * (width / 2.0), (1.0 - y) * (height / 2.0)  # in cells
        cx = min(max(int(np.floor(px)), 0), width - 1)
        cy = min(max(int(np.floor(py)), 0), height - 1)
        c = cy * width + cx
        # The segment's points are no deeper than its start (exactly: (1 - t) times its
        # depth), so primitives wholly beyond that depth cannot block it.
        rounding = 64.0 * eps * (light_size + max(abs(ox), abs(oy), abs(oz)))
        origin = (origins[i, 0], origins[i, 1], origins[i, 2])
        ray = make_ray(origin, (directions[i, 0], directions[i, 1], directions[i, 2]), 0.0, tmax[i])
        if depth <= close:  # rounding could put the ray in the wrong cell: test them all
            out[i] = blocked_by_any(prim_data, n_tri, ray, ignore[i])
        else:
            out[i] = blocked_by_list(prim_data, n_tri, ids, start[c], start[c + 1], near, edges,
                                     depth, rounding, px, py, ray, ignore[i])  # fmt: skip
