"""Camera-ray visibility by rasterisation: the BVH's answers, found triangle by triangle.

Every camera ray of a pinhole camera starts at the eye, so the nearest primitive along each
one can be found the other way round: for each primitive, list the samples whose rays may
cross it, and test only those. This is the paper's own future-work item ("rasterization for
primary visibility and ray tracing for secondary effects").

1. Project: each primitive's bounding box on the screen, in pixels (a triangle's three
   corners; a sphere's eight box corners): the pixels with a sample inside it, widened by
   a hundredth of a pixel (far more than rounding). A primitive reaching behind the eye's
   plane gets the whole screen (a projection would be meaningless).
2. Bin: the screen is cut into TILE x TILE pixel tiles; each tile lists the primitives
   whose box overlaps it, in increasing id (a counting pass, a prefix sum, a filling pass).
3. Test: tiles in parallel (no two threads ever write the same sample); in each, every
   listed primitive is tested against the rays of the samples in its box with *the same*
   ray-primitive function the tracer uses (``render.intersect.intersect_prim``), and each
   ray keeps the smallest (t, id), lower id first on a tie, as the BVH does.

Step 3 is the brute-force tracer restricted to candidates, and the boxes are conservative
(a ray outside a triangle's projected box cannot hit it), so the ids, t, u and
v are bit-identical to ``Accelerator.closest_hit`` (``tests/test_raster.py`` checks it on
random triangle soups, shared edges and vertices, spheres, and the teapot).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from minidiff import buffers
from render.camera import pixel_ray, plain_frame, subpixel_offsets
from render.intersect import intersect_prim, pack_primitives
from render.scene import Camera

#: Side of a binning tile, in pixels.
TILE = 16


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
) -> np.ndarray:
    """(P, 4) int64 pixel boxes (x0, y0, x1, y1), inclusive and clipped to the image, of
    every primitive (triangles, then spheres): the pixels whose samples' rays may hit it.

    ``right`` and ``up`` are the camera frame's pre-scaled vectors (a ray is forward +
    x right + y up, x and y in [-1, 1] across the image; ``render.camera``); offsets
    (spp, 2) the samples' positions in their pixel (``render.camera.subpixel_offsets``).
    """
    # The corners whose projections bound each primitive's: (P, n, 3).
    tri = triangles.reshape(-1, 3, 3)
    lo, hi = centers - radii[:, None], centers + radii[:, None]
    pick = np.array([[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)], dtype=bool)
    sphere_corners = np.where(pick[None], hi[:, None], lo[:, None])
    n_tri = len(tri)
    boxes = np.empty((n_tri + len(centers), 4), dtype=np.int64)
    for rows, corners in ((slice(0, n_tri), tri), (slice(n_tri, None), sphere_corners)):
        if len(corners):
            boxes[rows] = _project_boxes(corners, eye, forward, right, up, width, height, offsets)
    return boxes


def _project_boxes(corners, eye, forward, right, up, width, height, offsets) -> np.ndarray:
    """Pixel boxes of point sets (P, n, 3) (see ``screen_boxes``)."""
    q = corners - eye
    depth = q @ forward
    # Image-plane x, y of a point: q = s (forward + x right + y up), right and up orthogonal
    # to forward, so x = (q . right) / (|right|^2 depth).
    with np.errstate(divide="ignore", invalid="ignore"):
        x = (q @ right) / (right @ right * depth)
        y = (q @ up) / (up @ up * depth)
    # Continuous pixel coordinates: the sample at offset (ox, oy) of pixel (px, py) sits at
    # X = px + ox, Y = py + oy. A sample in [X0, X1] belongs to a pixel from
    # floor(X0 - max ox) to floor(X1 - min ox); the margin covers rounding many times over.
    margin = 0.01
    px, py = (x + 1.0) * (width / 2.0), (1.0 - y) * (height / 2.0)
    o_lo, o_hi = offsets.min(axis=0) - margin, offsets.max(axis=0) + margin
    behind = (depth <= 0).any(axis=1) | ~np.isfinite(px).all(axis=1) | ~np.isfinite(py).all(axis=1)
    with np.errstate(invalid="ignore"):
        box = np.stack(
            [
                np.floor(px.min(axis=1) - o_hi[0]),
                np.floor(py.min(axis=1) - o_hi[1]),
                np.floor(px.max(axis=1) - o_lo[0]),
                np.floor(py.max(axis=1) - o_lo[1]),
            ],
            axis=1,
        )
    box[behind] = (0, 0, width - 1, height - 1)
    limit = np.array([width - 1, height - 1, width - 1, height - 1], dtype=np.float64)
    return np.clip(np.nan_to_num(box), 0, limit).astype(np.int64)


@njit(cache=True)
def bin_to_tiles(boxes, tiles_x, tiles_y):
    """Per tile (row-major), the ids of the primitives whose box overlaps it, in increasing
    order: CSR arrays (start (n_tiles + 1,), ids)."""
    n_tiles = tiles_x * tiles_y
    counts = np.zeros(n_tiles + 1, np.int64)
    for p in range(boxes.shape[0]):
        for ty in range(boxes[p, 1] // TILE, boxes[p, 3] // TILE + 1):
            for tx in range(boxes[p, 0] // TILE, boxes[p, 2] // TILE + 1):
                counts[ty * tiles_x + tx + 1] += 1
    start = np.cumsum(counts)
    fill = start[:-1].copy()
    ids = np.empty(start[-1], np.int64)
    for p in range(boxes.shape[0]):  # in id order, so each tile's list is sorted
        for ty in range(boxes[p, 1] // TILE, boxes[p, 3] // TILE + 1):
            for tx in range(boxes[p, 0] // TILE, boxes[p, 2] // TILE + 1):
                t = ty * tiles_x + tx
                ids[fill[t]] = p
                fill[t] += 1
    return start, ids


@njit(cache=True, parallel=True, error_model="numpy")
def _raster_closest_hit(
    prim_data, n_tri, boxes, start, ids, tiles_x, width, height, offsets, eye, forward, right,
    up, out_id, out_t, out_u, out_v, with_uv,
):  # fmt: skip
    """Step 3 of the module docstring; ray r = (py * width + px) * spp + sample, its
    direction made on the spot (``render.camera.pixel_ray``, the tracer's very bits)."""
    spp = offsets.shape[0]
    out_id[:] = -1
    out_t[:] = np.inf
    if with_uv:
        out_u[:] = 0.0
        out_v[:] = 0.0
    ox, oy, oz = eye[0], eye[1], eye[2]
    n_tiles = start.shape[0] - 1
    # Tiles dealt round-robin to jobs: prange splits its range in contiguous parts, which
    # would give one thread the sky and the other the object.
    n_jobs = min(n_tiles, 64)
    for job in prange(n_jobs):
        for tile in range(job, n_tiles, n_jobs):
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
                        for s in range(spp):
                            r = (py * width + px) * spp + s
                            dx, dy, dz = pixel_ray(
                                px, py, offsets[s, 0], offsets[s, 1], width, height, forward,
                                right, up,
                            )  # fmt: skip
                            dlen = np.sqrt(dx * dx + dy * dy + dz * dz)
                            t, u, v = intersect_prim(
                                prim_data, pid, pid, n_tri, ox, oy, oz, dx, dy, dz, dlen, 0.0
                            )
                            # The BVH's order: (t, id); a miss is t = inf and never accepted.
                            best = out_t[r]
                            if t < best or (t == best and pid < out_id[r]):
                                out_id[r] = pid
                                out_t[r] = t
                                if with_uv:
                                    out_u[r] = u
                                    out_v[r] = v


def raster_closest_hit(
    triangles: np.ndarray,
    centers: np.ndarray,
    radii: np.ndarray,
    camera: Camera,
    spp: int = 1,
    with_uv: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """The nearest hit of every camera ray of ``camera`` (``spp`` per pixel), like
    ``Accelerator.closest_hit`` of ``render.camera.primary_rays``: (prim_id, t, u, v),
    each (H * W * spp,); u and v are None with ``with_uv=False`` (the renderer does not
    need them).

    triangles (T, 3, 3), centers (S, 3), radii (S,): the scene's primitives
    (``render.visibility.scene_primitives``).
    """
    forward, right, up, eye = plain_frame(camera)
    width, height = camera.width, camera.height
    offsets = subpixel_offsets(spp)
    boxes = screen_boxes(triangles, centers, radii, eye, forward, right, up, width, height, offsets)
    tiles_x, tiles_y = -(-width // TILE), -(-height // TILE)
    start, ids = bin_to_tiles(boxes, tiles_x, tiles_y)
    prim_data = pack_primitives(
        np.ascontiguousarray(triangles, np.float64).reshape(-1, 3, 3),
        np.ascontiguousarray(centers, np.float64).reshape(-1, 3),
        np.ascontiguousarray(radii, np.float64).reshape(-1),
    )
    n = width * height * spp
    # Reused memory (minidiff.buffers): fresh 2 MB arrays per render cost page faults.
    out_id, out_t = buffers.empty((n,), np.int64), buffers.empty((n,), np.float64)
    out_u, out_v = (np.empty(n), np.empty(n)) if with_uv else (np.empty(1), np.empty(1))
    _raster_closest_hit(
        prim_data, len(triangles), boxes, start, ids, tiles_x, width, height, offsets, eye,
        forward, right, up, out_id, out_t, out_u, out_v, with_uv,
    )  # fmt: skip
    if not with_uv:
        return out_id, out_t, None, None
    return out_id, out_t, out_u, out_v
