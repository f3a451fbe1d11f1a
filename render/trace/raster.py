"""Camera-ray visibility by rasterisation: the BVH's answers, found triangle by triangle.

Every camera ray of a pinhole camera starts at the eye, so the nearest primitive along each
one can be found the other way round: for each primitive, list the samples whose rays may
cross it, and test only those. This is the paper's own future-work item ("rasterization for
primary visibility and ray tracing for secondary effects").

1. Project: each primitive's bounding box on the screen, in pixels (a triangle's three
   corners; a sphere's eight box corners): the pixels with a sample inside it, widened by
   a hundredth of a pixel (far more than rounding), and a triangle's three edges as lines
   on the screen. A primitive reaching behind the eye's plane gets the whole screen and no
   edges (a projection would be meaningless).
2. Bin: the screen is cut into TILE x TILE pixel tiles; each tile lists the primitives
   whose box overlaps it, nearest first (a counting pass, a prefix sum, a filling pass).
3. Test: tiles in parallel (no two threads ever write the same sample); in each, every
   listed primitive is tested against the rays of the samples in its box that lie within
   its edges (give or take the hundredth of a pixel) and that have not already hit
   something wholly in front of it, with *the same* ray-primitive function the tracer uses
   (``render.trace.intersect.intersect_prim``); each ray keeps the smallest (t, id), lower id
   first on a tie, as the BVH does.

Step 3 is the brute-force tracer restricted to candidates, and the candidates are
conservative (a ray outside a triangle's projected edges cannot hit it, nor can one that
already hit something nearer than all of it win against that), so the ids, t, u and v
are bit-identical to ``Accelerator.closest_hit`` (``tests/render/trace/test_raster.py`` checks it on
random triangle soups, shared edges and vertices, spheres, and the teapot).

Any-hit camera rays through arbitrary image-plane points (the boundary term asks whether
anything lies in front of an edge point) are answered the same way (``raster_occluded``):
each ray scans its tile's list, nearest first, until a primitive lies wholly beyond its
end. The shadow rays towards a point light are answered the same way, seen from the light:
``render.trace.light_view`` (it shares ``screen_boxes``, ``bin_to_tiles``, ``nearest_depths``,
``may_see`` and ``wholly_beyond`` with this module).
"""

from __future__ import annotations

import numpy as np

from minidiff import buffers
from minidiff.threads import inlined, jit, job_count, kernel, run_jobs
from render.scene.camera import pixel_ray, plain_frame, subpixel_offsets
from render.scene.scene import Camera
from render.trace.intersect import (
    BLOCK,
    RAYS_PER_JOB,
    intersect_prim,
    make_ray,
    meets_before_end,
    n_blocks,
    pack_primitives,
)
from render.trace.vec3 import EPS, dot3

#: Side of a binning tile, in pixels.
TILE = 16

#: The boundary term asks ``raster_occluded`` rather than the BVH when it has at least this
#: many rays per primitive (binning costs per primitive, the BVH per ray). Measured on the
#: teapot's edge points (any-hit alone, medians of 9, BVH / raster): 1,536 triangles at
#: 512x512, 55k rays: 4.1 / 2.3 ms; 6,144 at 512x512, 141k: 13.9 / 7.3 ms; 24,576 at
#: 256x256, 316k: 48 / 38 ms; 24,576 at 128x128, 275k (11 per triangle): 45 / 70 ms.
OCCLUSION_RAYS_PER_PRIMITIVE = 16
#: ``raster_occluded``'s tiles, in pixels: smaller than the camera rays' (a ray scans a
#: shorter list; 4, 6, 8 and 12 took 2.3, 2.4, 2.5 and 2.7 ms on the 55k rays above).
OCCLUSION_TILE = 4


def screen_boxes(
    triangles: np.ndarray,
    centers: np.ndarray,
    radii: np.ndarray,
    eye: np.ndarray,
    forward: np.ndarray,
    right: np.ndarray,
    up: np.ndarray,
    width: int,
    height: int,
    offsets: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Where each primitive (triangles, then spheres) may be seen: (boxes, edges).

    boxes (P, 4) int64: pixel boxes (x0, y0, x1, y1), inclusive and clipped to the image,
    holding every pixel whose samples' rays may hit the primitive. edges (P, 3, 3): three
    lines (a, b, c) per primitive such that a sample at continuous pixel position (X, Y)
    (pixel px + its offset) can only see the primitive if a X + b Y + c >= -EDGE_MARGIN for
    all three: a triangle's edges, in pixels from each edge, positive inside; (0, 0, 1),
    always true, where that test would not be safe (spheres, triangles reaching behind the
    eye's plane or seen edge-on).

    ``right`` and ``up`` are the camera frame's pre-scaled vectors (a ray is forward +
    x right + y up, x and y in [-1, 1] across the image; ``render.scene.camera``); offsets
    (spp, 2) the samples' positions in their pixel (``render.scene.camera.subpixel_offsets``).
    """
    # The corners whose projections bound each primitive's: (P, n, 3).
    tri = triangles.reshape(-1, 3, 3)
    lo, hi = centers - radii[:, None], centers + radii[:, None]
    pick = np.array([[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)], dtype=bool)
    sphere_corners = np.where(pick[None], hi[:, None], lo[:, None])
    n_tri = len(tri)
    boxes = np.empty((n_tri + len(centers), 4), dtype=np.int64)
    edges = np.zeros((n_tri + len(centers), 3, 3))
    edges[:, :, 2] = 1.0
    for rows, corners in ((slice(0, n_tri), tri), (slice(n_tri, None), sphere_corners)):
        if len(corners):
            _project(corners, eye, forward, right, up, width, height, offsets, boxes[rows],
                     edges[rows])  # fmt: skip
    return boxes, edges


#: How far outside a triangle's projected edges (in pixels) a sample may lie and still be
#: tested: rounding in the projection and in the ray-triangle test is many orders smaller.
EDGE_MARGIN = 0.01


@jit(cache=True)
def _project(corners, eye, forward, right, up, width, height, offsets, boxes, edges):
    """Fill ``boxes`` (and, for triangles, ``edges``) of point sets (P, n, 3) (see
    ``screen_boxes``). Serial: in parallel blocks it took twice as long on the teapot's
    1,536 triangles (0.3 against 0.15 ms: waking the threads costs more than the work)."""
    # Continuous pixel coordinates: the sample at offset (ox, oy) of pixel (px, py) sits at
    # X = px + ox, Y = py + oy. A sample in [X0, X1] belongs to a pixel from
    # floor(X0 - max ox) to floor(X1 - min ox); the margin covers rounding many times over.
    # (Loops and ``dot3`` rather than ``.min()`` and ``@``: NumPy's functions compiled for
    # Numba cost a cold start tenths of a second each.)
    lo_ox = lo_oy = np.inf
    hi_ox = hi_oy = -np.inf
    for k in range(offsets.shape[0]):
        lo_ox, hi_ox = min(lo_ox, offsets[k, 0]), max(hi_ox, offsets[k, 0])
        lo_oy, hi_oy = min(lo_oy, offsets[k, 1]), max(hi_oy, offsets[k, 1])
    lo_ox, lo_oy = lo_ox - EDGE_MARGIN, lo_oy - EDGE_MARGIN
    hi_ox, hi_oy = hi_ox + EDGE_MARGIN, hi_oy + EDGE_MARGIN
    over_rr, over_uu = 1.0 / dot3(right, right), 1.0 / dot3(up, up)
    n = corners.shape[1]
    xs, ys = np.empty(n), np.empty(n)
    for p in range(corners.shape[0]):
        behind = False
        x_lo = y_lo = np.inf
        x_hi = y_hi = -np.inf
        for k in range(n):
            qx = corners[p, k, 0] - eye[0]
            qy = corners[p, k, 1] - eye[1]
            qz = corners[p, k, 2] - eye[2]
            depth = qx * forward[0] + qy * forward[1] + qz * forward[2]
            # Image-plane x, y of a point: q = s (forward + x right + y up), right and up
            # orthogonal to forward, so x = (q . right) / (|right|^2 depth).
            inverse = 1.0 / depth
            x = (qx * right[0] + qy * right[1] + qz * right[2]) * inverse * over_rr
            y = (qx * up[0] + qy * up[1] + qz * up[2]) * inverse * over_uu
            xs[k], ys[k] = (x + 1.0) * (width / 2.0), (1.0 - y) * (height / 2.0)
            if not (depth > 0.0 and np.isfinite(xs[k]) and np.isfinite(ys[k])):
                behind = True  # a projection would be meaningless: the whole screen
            x_lo, x_hi = min(x_lo, xs[k]), max(x_hi, xs[k])
            y_lo, y_hi = min(y_lo, ys[k]), max(y_hi, ys[k])
        if behind:
            boxes[p, 0], boxes[p, 1], boxes[p, 2], boxes[p, 3] = 0, 0, width - 1, height - 1
            continue
        boxes[p, 0] = _pixel_in(np.floor(x_lo - hi_ox), width)
        boxes[p, 1] = _pixel_in(np.floor(y_lo - hi_oy), height)
        boxes[p, 2] = _pixel_in(np.floor(x_hi - lo_ox), width)
        boxes[p, 3] = _pixel_in(np.floor(y_hi - lo_oy), height)
        if n == 3:
            _triangle_edges(xs, ys, edges[p])


@jit(cache=True)
def _triangle_edges(xs, ys, out):
    """The edge lines (a, b, c) of the projected triangle (xs, ys) (3,), as signed distances
    in pixels, positive inside (``screen_boxes``); left as they are (always true) if rounding
    could flip a sign: the triangle is (nearly) edge-on, or its corners are so far out that
    the distances would lose more than a thousandth of a pixel."""
    reach = 1.0  # bounds every |difference| below
    for k in range(3):
        reach = max(reach, 2.0 * abs(xs[k]) + 1.0, 2.0 * abs(ys[k]) + 1.0)
    rounding = 8.0 * EPS * reach * reach  # of a cross product below
    area = (xs[1] - xs[0]) * (ys[2] - ys[0]) - (xs[2] - xs[0]) * (ys[1] - ys[0])
    if abs(area) <= 64.0 * rounding:
        return
    shortest = np.inf
    for k in range(3):
        j = (k + 1) % 3
        shortest = min(shortest, (xs[j] - xs[k]) ** 2 + (ys[j] - ys[k]) ** 2)
    if rounding > 1e-3 * np.sqrt(shortest):
        return
    side = 1.0 if area > 0 else -1.0
    for k in range(3):
        j = (k + 1) % 3
        dx, dy = xs[j] - xs[k], ys[j] - ys[k]
        scale = side / np.sqrt(dx * dx + dy * dy)
        # Distance of (X, Y) from the edge k -> j, positive on the triangle's side.
        a, b = -dy * scale, dx * scale
        out[k, 0], out[k, 1], out[k, 2] = a, b, -(a * xs[k] + b * ys[k])


@jit(cache=True, inline="always")
def _pixel_in(value, n):
    """A whole number of pixels clipped to [0, n - 1] (clipped as a float: it may be huge)."""
    return int(min(max(value, 0.0), n - 1.0))


@jit(cache=True)
def bin_to_tiles(boxes, tiles_x, tiles_y, tile, order):
    """Per tile of ``tile`` x ``tile`` pixels (row-major), the ids of the primitives whose
    box overlaps it, in the order of ``order`` (a permutation of the ids): CSR arrays
    (start (n_tiles + 1,), ids)."""
    n_tiles = tiles_x * tiles_y
    counts = np.zeros(n_tiles + 1, np.int64)
    for p in range(boxes.shape[0]):
        for ty in range(boxes[p, 1] // tile, boxes[p, 3] // tile + 1):
            for tx in range(boxes[p, 0] // tile, boxes[p, 2] // tile + 1):
                counts[ty * tiles_x + tx + 1] += 1
    start = counts  # summed in place (a loop: np.cumsum compiles a second function)
    for t in range(1, n_tiles + 1):
        start[t] += start[t - 1]
    fill = start[:-1].copy()
    ids = np.empty(start[-1], np.int64)
    for p in order:
        for ty in range(boxes[p, 1] // tile, boxes[p, 3] // tile + 1):
            for tx in range(boxes[p, 0] // tile, boxes[p, 2] // tile + 1):
                t = ty * tiles_x + tx
                ids[fill[t]] = p
                fill[t] += 1
    return start, ids


@kernel
def _raster_closest_hit(
    job, n_jobs, prim_data, n_tri, boxes, edges, near, rounding, start, ids, tiles_x, width,
    height, offsets, eye, forward, right, up, out_id, out_t, out_u, out_v, with_uv, slot,
    given, busy,
):  # fmt: skip
    """Step 3 of the module docstring for job ``job`` of ``n_jobs``
    (``minidiff.threads.run_jobs``); ray r = (py * width + px) * spp + sample, its
    direction made on the spot (``render.scene.camera.pixel_ray``, the tracer's very bits).
    out_id, out_t (and out_u, out_v if ``with_uv``) hold -1, inf (and 0) on entry.

    Some pixels only, when ``slot`` (H W,) int64 is not empty: pixel p's samples are rays
    r = slot[p] * spp + sample (none where slot[p] < 0), their directions ``given`` (rows
    r, (k, 3)); ``busy`` (n_tiles,) bool says which tiles hold such a pixel."""
    spp = offsets.shape[0]
    n_tiles = start.shape[0] - 1
    some = slot.shape[0] > 0
    origin = (eye[0], eye[1], eye[2])  # a tuple, as every caller of make_ray passes
    # The samples' box in their pixel: its corners are samples (an n x n grid), so a
    # pixel whose box misses a primitive's edges has no sample that passes them.
    box_x0, box_y0, box_x1, box_y1 = np.inf, np.inf, -np.inf, -np.inf
    for s in range(spp):
        box_x0, box_x1 = min(box_x0, offsets[s, 0]), max(box_x1, offsets[s, 0])
        box_y0, box_y1 = min(box_y0, offsets[s, 1]), max(box_y1, offsets[s, 1])
    # Tiles dealt round-robin to jobs: contiguous parts would give one thread the sky and
    # the other the object.
    for tile in range(job, n_tiles, n_jobs):
        if some and not busy[tile]:
            continue
        tx0 = (tile % tiles_x) * TILE
        ty0 = (tile // tiles_x) * TILE
        for j in range(start[tile], start[tile + 1]):
            pid = ids[j]
            x0 = max(boxes[pid, 0], tx0)
            x1 = min(boxes[pid, 2], tx0 + TILE - 1, width - 1)
            y0 = max(boxes[pid, 1], ty0)
            y1 = min(boxes[pid, 3], ty0 + TILE - 1, height - 1)
            for py in range(y0, y1 + 1):
                for px in range(x0, x1 + 1):
                    first = (py * width + px) * spp
                    if some:
                        if slot[py * width + px] < 0:
                            continue
                        first = slot[py * width + px] * spp
                    if spp > 1 and not box_may_see(edges, pid, px + box_x0, py + box_y0,
                                                   px + box_x1, py + box_y1):  # fmt: skip
                        continue
                    for s in range(spp):
                        if not may_see(edges, pid, px + offsets[s, 0], py + offsets[s, 1]):
                            continue
                        r = first + s
                        if wholly_beyond(near[pid], out_t[r], rounding):
                            continue  # wholly behind what the ray already hit
                        if some:
                            direction = (given[r, 0], given[r, 1], given[r, 2])
                        else:
                            direction = pixel_ray(
                                px, py, offsets[s, 0], offsets[s, 1], width, height, forward,
                                right, up,
                            )  # fmt: skip
                        ray = make_ray(origin, direction, 0.0, np.inf)
                        t, u, v = intersect_prim(prim_data, pid, pid, n_tri, ray)
                        # The BVH's order: (t, id); a miss is t = inf and never accepted.
                        best = out_t[r]
                        if t < best or (t == best and pid < out_id[r]):
                            out_id[r] = pid
                            out_t[r] = t
                            if with_uv:
                                out_u[r] = u
                                out_v[r] = v


@jit(cache=True, inline="always")
def wholly_beyond(near, depth, rounding):
    """Whether a primitive whose nearest depth (along the view axis) is ``near`` lies wholly
    beyond ``depth`` >= 0, with room for the rounding of both: a relative millionth plus
    ``rounding`` (absolute), many times what either can be off by."""
    return near > depth * (1.0 + 1e-6) + rounding


@jit(cache=True, inline="always")
def may_see(edges, pid, x, y):
    """Whether a sample at continuous pixel position (x, y) passes primitive ``pid``'s three
    edge tests (``screen_boxes``). (Elements read one by one: a row view ``edges[pid]``
    would count references, atomically, on every test.)"""
    for k in range(3):
        if edges[pid, k, 0] * x + edges[pid, k, 1] * y + edges[pid, k, 2] < -EDGE_MARGIN:
            return False
    return True


@jit(cache=True, inline="always")
def box_may_see(edges, pid, x0, y0, x1, y1):
    """Whether a sample at one of the corners of the box [x0, x1] x [y0, y1] of continuous
    pixel positions may pass primitive ``pid``'s three edge tests: False only where every
    sample whose position is a corner, or within the box, fails ``may_see`` (each edge's
    largest over the box is at a corner, and rounding keeps that order)."""
    for k in range(3):
        a, b = edges[pid, k, 0], edges[pid, k, 1]
        x, y = (x1 if a > 0.0 else x0), (y1 if b > 0.0 else y0)
        if a * x + b * y + edges[pid, k, 2] < -EDGE_MARGIN:
            return False
    return True


@inlined
def blocked_by_list(prim_data, n_tri, ids, first, last, near, edges, depth, rounding, x, y,
                    ray, ignore):  # fmt: skip
    """Whether ``ray`` (its end at most ``depth`` along the view axis, its sample at
    continuous position (x, y) of the view) is blocked by one of the primitives ``ids[first
    : last]`` of a cell's list, nearest first (``bin_to_tiles``), other than ``ignore``:
    tested up to the first primitive wholly beyond ``depth``, those whose ``edges`` rule
    out (x, y) skipped. The camera's occlusion test and the light's view share it."""
    for j in range(first, last):
        pid = ids[j]
        if wholly_beyond(near[pid], depth, rounding):
            return False  # this one and the rest lie wholly beyond the ray's end
        if pid == ignore or not may_see(edges, pid, x, y):
            continue
        if intersect_prim(prim_data, pid, pid, n_tri, ray)[0] < ray.tmax:
            return True
    return False


@inlined
def blocked_by_any(prim_data, n_tri, ray, ignore):
    """Whether ``ray`` is blocked by any primitive of ``prim_data`` (in id order) other than
    ``ignore``: for rays no cell's list covers (few: those outside the image, or starting
    very close to a light)."""
    for pid in range(prim_data.shape[0]):
        if pid != ignore and meets_before_end(prim_data, pid, pid, n_tri, ray):
            return True
    return False


#: ``render(primary="auto")`` rasterises when rays / primitives >= RASTER_RAYS_PER_PRIMITIVE.
#: Measured at 512x512 (camera-ray hits alone, medians of 9): 1,536 triangles raster 2.8 ms /
#: BVH 9.9 ms, 15,360: 10.1 / 12.1 ms, 99,840: 43.8 / 15.9 ms, 256,000: 134 / 27 ms.
RASTER_RAYS_PER_PRIMITIVE = 16


def rasterise_camera_rays(scene, primary: str, spp: int) -> bool:
    """Whether a render rasterises its camera rays' hits (``render(primary=...)``: "raster",
    "bvh", or "auto": when there are at least RASTER_RAYS_PER_PRIMITIVE rays per
    primitive)."""
    if primary not in ("auto", "raster", "bvh"):
        raise ValueError(f'render: primary must be "auto", "raster" or "bvh", got {primary!r}')
    if primary != "auto":
        return primary == "raster"
    rays = scene.camera.width * scene.camera.height * spp
    primitives = sum(m.num_faces for m in scene.meshes) + len(scene.spheres)
    return primitives * RASTER_RAYS_PER_PRIMITIVE <= rays


def raster_closest_hit(
    triangles: np.ndarray,
    centers: np.ndarray,
    radii: np.ndarray,
    camera: Camera,
    spp: int = 1,
    with_uv: bool = True,
    pixels: np.ndarray | None = None,
    directions: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """The nearest hit of every camera ray of ``camera`` (``spp`` per pixel), like
    ``Accelerator.closest_hit`` of ``render.scene.camera.primary_rays``: (prim_id, t, u, v),
    each (H * W * spp,); u and v are None with ``with_uv=False`` (the renderer does not
    need them).

    triangles (T, 3, 3), centers (S, 3), radii (S,): the scene's primitives
    (``render.trace.visibility.scene_primitives``).

    Or the hits of the ``spp`` samples of some pixels only: ``pixels`` (m,) distinct flat
    pixel indices, ``directions`` (m * spp, 3) their rays' directions from the eye, pixel
    by pixel (sample s of ``pixels[i]`` is row i * spp + s, through its sub-pixel offset
    ``subpixel_offsets(spp)[s]``): each (m * spp,), the hits ``Accelerator.closest_hit``
    finds for those rays (the mixed pixels' samples, ``render.edges.interior``).
    """
    forward, right, up, eye = plain_frame(camera)
    width, height = camera.width, camera.height
    offsets = subpixel_offsets(spp)
    triangles = np.ascontiguousarray(triangles, np.float64).reshape(-1, 3, 3)
    centers = np.ascontiguousarray(centers, np.float64).reshape(-1, 3)
    radii = np.ascontiguousarray(radii, np.float64).reshape(-1)
    primitives = (triangles, centers, radii)
    boxes, edges, near, rounding, start, ids, tiles_x = _binned(
        primitives, (forward, right, up, eye), width, height, offsets, TILE
    )
    prim_data = pack_primitives(triangles, centers, radii)
    slot, given, busy = _some_pixels(pixels, directions, width, height, spp, tiles_x,
                                     len(start) - 1)  # fmt: skip
    n = width * height * spp if pixels is None else len(given)
    # Reused memory (minidiff.buffers): fresh 2 MB arrays per render cost page faults.
    out_id, out_t = buffers.empty((n,), np.int64), buffers.empty((n,), np.float64)
    out_u, out_v = (np.zeros(n), np.zeros(n)) if with_uv else (np.empty(1), np.empty(1))
    out_id.fill(-1)
    out_t.fill(np.inf)
    run_jobs(
        _raster_closest_hit, job_count(len(start) - 1, 16), prim_data, len(triangles), boxes,
        edges, near, rounding, start, ids, tiles_x, width, height, offsets, eye, forward,
        right, up, out_id, out_t, out_u, out_v, with_uv, slot, given, busy,
    )  # fmt: skip
    if not with_uv:
        return out_id, out_t, None, None
    return out_id, out_t, out_u, out_v


def _some_pixels(
    pixels, directions, width: int, height: int, spp: int, tiles_x: int, n_tiles: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``_raster_closest_hit``'s (slot, given, busy) for the samples of ``pixels`` (empty
    arrays: every pixel), checked."""
    if (pixels is None) != (directions is None):
        raise ValueError("pixels and directions must be given together (or neither)")
    if pixels is None:
        empty = np.zeros(0, np.int64)
        return empty, np.zeros((0, 3)), np.zeros(0, np.bool_)
    pixels = np.asarray(pixels)
    if pixels.ndim != 1 or not np.issubdtype(pixels.dtype, np.integer):
        raise ValueError(f"pixels must be a (m,) integer array, got {pixels.dtype} {pixels.shape}")
    if len(pixels) and (pixels.min() < 0 or pixels.max() >= width * height):
        raise ValueError(f"pixels must be flat pixel indices in [0, {width * height - 1}]")
    given = np.ascontiguousarray(directions, np.float64)
    if given.shape != (len(pixels) * spp, 3):
        raise ValueError(
            f"directions must have shape (m * spp, 3) = ({len(pixels) * spp}, 3), got {given.shape}"
        )
    slot = np.full(width * height, -1, np.int64)
    slot[pixels] = np.arange(len(pixels))
    if np.count_nonzero(slot >= 0) != len(pixels):
        raise ValueError("pixels must be distinct")
    busy = np.zeros(n_tiles, np.bool_)
    busy[(pixels // width // TILE) * tiles_x + (pixels % width) // TILE] = True
    return slot, given, busy


def _binned(primitives, frame, width: int, height: int, offsets: np.ndarray, tile: int):
    """Steps 1 and 2 of the module docstring for samples at ``offsets`` (n, 2) in their
    pixels and tiles of ``tile`` pixels: (boxes, edges, near, rounding, start, ids,
    tiles_x), each tile's list (CSR ``start``, ``ids``) nearest first."""
    triangles, centers, radii = primitives
    forward, right, up, eye = frame
    boxes, edges = screen_boxes(
        triangles, centers, radii, eye, forward, right, up, width, height, offsets
    )
    # Each tile's list nearest first: a primitive wholly behind a sample's hit so far (or
    # a ray's end) is skipped. A hit's t is its depth (the directions have unit component
    # along forward), never less than its primitive's nearest depth but for rounding
    # (``wholly_beyond``).
    near = nearest_depths(triangles, centers, radii, eye, forward)
    extent = max(
        np.abs(triangles).max(initial=0.0), (np.abs(centers) + radii[:, None]).max(initial=0.0)
    )
    rounding = 64.0 * np.finfo(np.float64).eps * (np.abs(eye).max() + extent)
    tiles_x, tiles_y = -(-width // tile), -(-height // tile)
    start, ids = bin_to_tiles(boxes, tiles_x, tiles_y, tile, np.argsort(near, kind="stable"))
    return boxes, edges, near, rounding, start, ids, tiles_x


def raster_occluded(
    primitives: tuple[np.ndarray, np.ndarray, np.ndarray],
    frame: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    width: int,
    height: int,
    coords: np.ndarray,
    directions: np.ndarray,
    tmax: np.ndarray,
    ignore: np.ndarray,
) -> np.ndarray:
    """(k,) bool: ``Accelerator.occluded(eye, directions, tmax, tmin=0, ignore_prim=ignore)``
    for k camera rays through image-plane points ``coords`` (k, 2) anywhere in the image
    (``directions`` (k, 3) = ``camera_directions(coords, ...)``, tmax (k,), ignore (k,)
    int64, -1: none), found as ``raster_closest_hit`` finds hits: the primitives binned in
    the camera's tiles nearest first, each ray tested against its tile's list with the
    tracer's ray-primitive function up to the first primitive wholly beyond its end. The
    same answers as the BVH's (``tests/render/trace/test_raster.py``).

    primitives: ``scene_primitives``; frame: the camera's (forward, right, up, eye)
    (``plain_frame``) of a ``width`` x ``height`` image."""
    forward, right, up, eye = frame
    triangles, centers, radii = primitives
    # A point may lie anywhere in its pixel: boxes for offsets from 0 to 1.
    anywhere = np.array([[0.0, 0.0], [1.0, 1.0]])
    tile = OCCLUSION_TILE
    _, edges, near, rounding, start, ids, tiles_x = _binned(
        primitives, frame, width, height, anywhere, tile
    )
    out = np.zeros(len(coords), np.bool_)
    run_jobs(
        _raster_occluded, job_count(len(out), RAYS_PER_JOB),
        pack_primitives(triangles, centers, radii), len(triangles), edges, near, rounding,
        start, ids, tile, tiles_x, width, height, eye, forward, np.ascontiguousarray(coords),
        np.ascontiguousarray(directions), tmax, ignore, out,
    )  # fmt: skip
    return out


@kernel
def _raster_occluded(
    job, n_jobs, prim_data, n_tri, edges, near, rounding, start, ids, tile_size, tiles_x,
    width, height, eye, forward, coords, directions, tmax, ignore, out,
):  # fmt: skip
    """``raster_occluded``'s test for job ``job`` of ``n_jobs``, rays dealt as the tracer's
    kernels deal them (``render.trace.intersect``): each against its tile's list, or
    against every primitive if it lies outside the image (no tile holds what it may
    meet)."""
    for block in range(job, n_blocks(out.shape[0]), n_jobs):
        for i in range(block * BLOCK, min(out.shape[0], (block + 1) * BLOCK)):
            out[i] = _occluded_in_tile(
                prim_data, n_tri, edges, near, rounding, start, ids, tile_size, tiles_x,
                width, height, eye, forward, coords, directions, tmax, ignore, i,
            )  # fmt: skip


@jit(cache=True, inline="always")
def _occluded_in_tile(
    prim_data, n_tri, edges, near, rounding, start, ids, tile_size, tiles_x, width, height,
    eye, forward, coords, directions, tmax, ignore, i,
):  # fmt: skip
    """Whether camera ray i of ``_raster_occluded`` is blocked."""
    # The ray's continuous pixel position (``render.scene.camera.pixel_xy`` inverted).
    x, y = (coords[i, 0] + 1.0) * (width / 2.0), (1.0 - coords[i, 1]) * (height / 2.0)
    inside = -EDGE_MARGIN <= x <= width + EDGE_MARGIN
    inside = inside and -EDGE_MARGIN <= y <= height + EDGE_MARGIN
    tile = (_pixel_in(np.floor(y), height) // tile_size) * tiles_x
    tile += _pixel_in(np.floor(x), width) // tile_size
    d = (directions[i, 0], directions[i, 1], directions[i, 2])
    ray = make_ray((eye[0], eye[1], eye[2]), d, 0.0, tmax[i])
    if not inside:
        return blocked_by_any(prim_data, n_tri, ray, ignore[i])
    depth = tmax[i] * (d[0] * forward[0] + d[1] * forward[1] + d[2] * forward[2])
    return blocked_by_list(prim_data, n_tri, ids, start[tile], start[tile + 1], near, edges,
                           depth, rounding, x, y, ray, ignore[i])  # fmt: skip


@jit(cache=True)
def nearest_depths(triangles, centers, radii, eye, forward):
    """(P,) each primitive's smallest depth along ``forward`` from the point ``eye`` (a camera's
    eye or a light; triangles: their nearest corner; spheres: centre depth - radius)."""
    near = np.empty(triangles.shape[0] + centers.shape[0])
    for p in range(triangles.shape[0]):
        near[p] = np.inf
        for k in range(3):
            depth = 0.0
            for a in range(3):
                depth += (triangles[p, k, a] - eye[a]) * forward[a]
            near[p] = min(near[p], depth)
    for s in range(centers.shape[0]):
        depth = 0.0
        for a in range(3):
            depth += (centers[s, a] - eye[a]) * forward[a]
        near[triangles.shape[0] + s] = depth - radii[s]
    return near
