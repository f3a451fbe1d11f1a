"""Camera rays: where each pixel looks.

A look-at pinhole camera is an orthonormal frame (forward, right, up) at the eye. The ray
through the point (x, y) of the image plane, with x, y in [-1, 1] from left to right and
bottom to top, has direction

    d = forward + x * tan(fov / 2) * right + y * tan(fov / 2) * (height / width) * up.

Two versions of this formula live here, for two jobs:

* ``primary_rays`` evaluates it for every pixel in Numba, on plain arrays: visibility (the
  BVH) only needs numbers, and generating 262,144 directions with NumPy temporaries would
  cost more than tracing them.
* ``ray_directions`` evaluates it on the tape for the rays that hit something, so gradients
  reach the camera's position, look_at, up and fov.

Off the tape the frame is ``plain_frame`` (float64 arrays, the one plain version every
caller uses), the directions through given image-plane points ``camera_directions``, and
the way back, from world points to the image, ``project`` (pixel coordinates and depth),
``to_image_plane`` (pixel coordinates to image-plane ones) and ``clip_to_near`` (segments
clipped to the part in front of the eye).
"""

from __future__ import annotations

import math
import threading

import numpy as np

import minidiff as md
from minidiff import buffers
from minidiff.kernels import sum_rows
from minidiff.threads import jit, job_count, kernel, run_jobs, share
from minidiff.trace import Traced
from render.scene.cache import same
from render.scene.scene import Camera, check_ray_count

#: A camera frame off the tape: (forward, right * half_width, up * half_height, eye), (3,)
#: float64 each (``plain_frame``).
PlainFrame = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def check_square(value, name: str) -> int:
    """``value`` as an int if it is a perfect square >= 1 of at most the ray limit
    (``check_ray_count``), else a ValueError naming ``name``: samples per pixel on an n x n
    grid."""
    # Type and sign first: math.isqrt would fail on them with a message that names nothing.
    valid = not isinstance(value, bool) and isinstance(value, int | np.integer) and value >= 1
    n = math.isqrt(value) if valid else 0
    if not valid or n * n != value:
        raise ValueError(
            f"render: {name} must be a perfect square (1, 4, 9, 16, ...), got {value!r}"
        )
    check_ray_count(1, 1, int(value))  # before an n x n grid is allocated
    return int(value)


def subpixel_offsets(spp: int) -> np.ndarray:
    """(spp, 2) fixed stratified sample positions inside a pixel, in [0, 1)^2.

    spp = n^2 gives the centres of an n x n grid of cells. The pattern is fixed (no random
    jitter), so the rendered image is a deterministic, differentiable function of the scene.
    """
    n = math.isqrt(check_square(spp, "spp"))
    cells = (np.arange(n) + 0.5) / n
    sx, sy = np.meshgrid(cells, cells)
    return np.stack([sx.ravel(), sy.ravel()], axis=1)


def camera_frame(camera: Camera) -> tuple[md.Tensor, md.Tensor, md.Tensor, md.Tensor]:
    """The camera's frame on the tape: (forward, right * half_width, up * half_height, eye).

    ``right`` and ``up`` come pre-scaled by the half extent of the image plane at distance
    1, so that a direction is simply forward + x * right + y * up.
    """
    eye = camera.position
    forward = md.normalize(camera.look_at - eye)
    right = md.normalize(md.cross(forward, camera.up))
    up = md.cross(right, forward)  # unit: right and forward are orthonormal
    half_width = md.tan(camera.fov * (math.pi / 360.0))  # tan(fov/2), fov in degrees
    half_height = half_width * (camera.height / camera.width)
    return forward, right * half_width, up * half_height, eye


def image_plane_coords(camera: Camera, ray_ids: np.ndarray, spp: int) -> np.ndarray:
    """(k, 2) image-plane coordinates (x, y) in [-1, 1] of the given rays.

    Ray r belongs to pixel r // spp (row-major, row 0 at the top) and sample r % spp.
    """
    return _coords_of_rays(ray_ids, camera.width, camera.height, spp)


def _coords_of_rays(ray_ids: np.ndarray, width: int, height: int, spp: int) -> np.ndarray:
    """``image_plane_coords`` of rays ``ray_ids`` (k,) of a width x height image, ``spp``
    per pixel, in one parallel pass (``_image_plane_coords``)."""
    ids = np.ascontiguousarray(ray_ids, dtype=np.int64)
    out = buffers.empty((len(ids), 2), np.float64)
    run_jobs(_image_plane_coords, job_count(len(ids), 65536), ids, width, height,
             subpixel_offsets(spp), out)  # fmt: skip
    return out


@jit(cache=True, inline="always")
def pixel_xy(px, py, ox, oy, width, height):
    """Image-plane (x, y) of sub-pixel (ox, oy) of pixel (px, py), in the one order of
    operations every kernel uses."""
    return 2.0 * (px + ox) / width - 1.0, 1.0 - 2.0 * (py + oy) / height


@kernel
def _image_plane_coords(job, n_jobs, ray_ids, width, height, offsets, out):
    """Job ``job`` of ``n_jobs`` of ``_coords_of_rays``: its share of the rays."""
    spp = offsets.shape[0]
    first, stop = share(job, n_jobs, ray_ids.shape[0])
    for i in range(first, stop):
        pixel, s = divmod(ray_ids[i], spp)
        py, px = divmod(pixel, width)
        out[i, 0], out[i, 1] = pixel_xy(px, py, offsets[s, 0], offsets[s, 1], width, height)


def ray_directions(frame, coords: np.ndarray) -> md.Tensor:
    """(k, 3) unnormalised ray directions on the tape for image-plane coords (k, 2).

    x * right + y * up + forward is linear in the basis B = [right; up; forward] (3, 3):
    one tape node (``md.linear``) whose adjoint sums the rows, g -> [x^T g; y^T g; 1^T g].
    Not ``[x, y, 1] @ B``: NumPy hands a tall product to OpenBLAS, whose threads then
    spin beside Numba's and slow the kernels after them (on the teapot and its ground, a
    forward+backward took 40-45 ms with it and 33-35 ms without; with the boundary term
    113-150 against 82-86 ms). In a compiled function (``minidiff.compile``), where
    ``coords`` is traced, the formula itself is traced.
    """
    forward, right, up, _ = frame
    if isinstance(coords, Traced):
        return camera_directions(coords, right, up, forward)
    x, y = coords[:, :1], coords[:, 1:2]

    def apply(basis: np.ndarray) -> np.ndarray:
        return camera_directions(coords, *basis)

    def adjoint(g: np.ndarray) -> np.ndarray:
        return np.stack([sum_rows(x * g), sum_rows(y * g), sum_rows(g)])

    return md.linear(apply, adjoint, md.stack([right, up, forward]))


def camera_directions(coords: np.ndarray, right, up, forward) -> np.ndarray:
    """(k, 3): the unnormalised directions x right + y up + forward of the camera rays
    through image-plane points ``coords`` (k, 2), off the tape: the one order of
    operations of every caller (``ray_directions`` on the tape, the edge terms and the
    path tracer off it)."""
    if isinstance(coords, np.ndarray) and _in_double(coords, right, up, forward):
        # The formula compiled (``minidiff.compile``): one pass over the rows on the
        # threads, where NumPy took 8.3 ms for the 363k interior samples of a 512x512
        # boundary term (its temporaries).
        with md.no_grad():
            out = _compiled_directions(coords, right, up, forward)
        # (the plain function's array for an empty batch, or inside ``md.tape_only()``)
        return out.data if isinstance(out, md.Tensor) else out
    return _directions(coords, right, up, forward)


def _directions(coords, right, up, forward):
    """x right + y up + forward, on NumPy or minidiff arrays (traced ones too)."""
    return coords[:, :1] * right + coords[:, 1:] * up + forward


_compiled_directions = md.compile(_directions, shared=("right", "up", "forward"))


def _in_double(*arrays) -> bool:
    """Whether the arrays are all float64 (what a compiled function takes)."""
    return all(np.asarray(a).dtype == np.float64 for a in arrays)


@jit(cache=True, inline="always")
def pixel_ray(px, py, ox, oy, width, height, forward, right, up):
    """The direction (dx, dy, dz) of the camera ray through sub-pixel (ox, oy) of pixel
    (px, py): the module docstring's formula, in the one order of operations every kernel
    uses (so that all of them produce the same bits)."""
    x, y = pixel_xy(px, py, ox, oy, width, height)
    return (
        forward[0] + x * right[0] + y * up[0],
        forward[1] + x * right[1] + y * up[1],
        forward[2] + x * right[2] + y * up[2],
    )


@kernel
def _primary_directions(job, n_jobs, width, height, offsets, forward, right, up, out):
    """Job ``job`` of ``n_jobs`` (``minidiff.threads.run_jobs``): the directions (into
    ``out`` (H * W * spp, 3)) of the camera rays of its share of the image's rows."""
    spp = offsets.shape[0]
    first, stop = share(job, n_jobs, height)
    for py in range(first, stop):
        for px in range(width):
            for s in range(spp):
                r = (py * width + px) * spp + s
                d = pixel_ray(
                    px, py, offsets[s, 0], offsets[s, 1], width, height, forward, right, up
                )
                out[r, 0], out[r, 1], out[r, 2] = d


def plain_frame(camera: Camera) -> PlainFrame:
    """The camera frame of ``camera_frame`` as plain float64 arrays (forward, right, up,
    eye), for everything computed off the tape (visibility, the edge terms); remembered
    for the last camera asked about (read-only: they may be returned again)."""
    tensors = (camera.position, camera.look_at, camera.up, camera.fov)
    key = [np.array(t.data) for t in tensors]  # copies: optimisers edit values in place
    key.append(np.array([camera.width, camera.height] + [t.data.dtype.num for t in tensors]))
    last_key, last_frame = getattr(_last_plain_frame, "entry", (None, None))
    if last_key is not None and same(key, last_key):
        return last_frame  # a render asks several times; ten tape operations each time add up
    with md.no_grad():
        frame = plain_camera(camera_frame(camera))
    for array in frame:
        array.flags.writeable = False
    _last_plain_frame.entry = (key, frame)
    return frame


def plain_camera(frame) -> PlainFrame:
    """The values of a frame on the tape (``camera_frame``) as float64 arrays (copies):
    what ``plain_frame`` returns for the frame's camera."""
    return tuple(np.array(t.data, np.float64) for t in frame)


# The last camera values plain_frame was asked about, and its answer.
# Per thread (each thread remembers its own last camera): a thread never reads another's
# entry half-written, and two threads rendering different cameras do not evict each other.
_last_plain_frame = threading.local()


def hits_along_rays(
    camera: Camera, ray_ids: np.ndarray, t: np.ndarray, spp: int
) -> tuple[np.ndarray, np.ndarray]:
    """Where the camera rays ``ray_ids`` (k,) end: points (k, 3) = eye + t[r] d_r, with the
    directions of ``primary_rays`` and t (N,) per camera ray, and their image-plane coords
    (k, 2) (as ``image_plane_coords``); one pass over the rays."""
    forward, right, up, eye = plain_frame(camera)
    ids = np.ascontiguousarray(ray_ids, dtype=np.int64)
    points = buffers.empty((len(ids), 3), np.float64)
    coords = buffers.empty((len(ids), 2), np.float64)
    offsets = subpixel_offsets(spp)
    run_jobs(_hits_along_rays, job_count(len(ids), 65536), ids, t, camera.width, camera.height,
             offsets, forward, right, up, eye, points, coords)  # fmt: skip
    return points, coords


@kernel
def _hits_along_rays(
    job, n_jobs, ray_ids, t, width, height, offsets, forward, right, up, eye, points, coords
):
    """Job ``job`` of ``n_jobs`` (``minidiff.threads.run_jobs``): its share of the rays
    (each ray's arithmetic on one thread: any thread count gives the same bits)."""
    spp = offsets.shape[0]
    first, stop = share(job, n_jobs, ray_ids.shape[0])
    for i in range(first, stop):
        r = ray_ids[i]
        pixel, s = divmod(r, spp)
        py, px = divmod(pixel, width)
        ox, oy = offsets[s, 0], offsets[s, 1]
        coords[i, 0], coords[i, 1] = pixel_xy(px, py, ox, oy, width, height)
        d = pixel_ray(px, py, ox, oy, width, height, forward, right, up)
        points[i, 0], points[i, 1], points[i, 2] = _ray_end(eye, t[r], d)


def sample_coords(pixels: np.ndarray, spp: int, width: int, height: int) -> np.ndarray:
    """Image-plane coords (m * spp, 2) of the ``spp`` samples of each of the flat pixel
    indices ``pixels`` (m,) of a width x height image, pixel by pixel (sample s of
    ``pixels[i]`` is row i * spp + s, at ``subpixel_offsets(spp)[s]``): the coords of those
    camera rays (``image_plane_coords``), the very bits of ``to_image_plane`` of the
    pixel's corner plus the offset, in one parallel pass (NumPy's temporaries took 7.9 ms
    for the 363k candidate samples of a 512x512 boundary term)."""
    rays = np.asarray(pixels, np.int64)[:, None] * spp + np.arange(spp)
    return _coords_of_rays(rays.reshape(-1), width, height, spp)


def ray_ends(eye: np.ndarray, directions: np.ndarray, depth: np.ndarray, rays: np.ndarray
             ) -> np.ndarray:  # fmt: skip
    """Where the camera rays ``rays`` (k,) end: points (k, 3) = eye + depth[r] directions[r]
    for r in ``rays``, from the eye (3,), every ray's direction (N, 3) and its depth (N,)
    along it (for the camera's directions, whose component along the view axis is 1, the
    depth); one parallel pass, where NumPy's gathers and temporaries took 8.5 ms for the
    180k hits among a 512x512 boundary term's interior samples."""
    rays = np.ascontiguousarray(rays, dtype=np.int64)
    directions = np.ascontiguousarray(directions, dtype=np.float64)
    out = buffers.empty((len(rays), 3), np.float64)
    run_jobs(_ray_ends, job_count(len(rays), 16384), np.ascontiguousarray(eye, np.float64),
             directions, np.ascontiguousarray(depth, np.float64), rays, out)  # fmt: skip
    return out


@kernel
def _ray_ends(job, n_jobs, eye, directions, depth, rays, out):
    """Job ``job`` of ``n_jobs`` of ``ray_ends``: its share of the rays."""
    first, stop = share(job, n_jobs, rays.shape[0])
    for i in range(first, stop):
        r = rays[i]
        out[i, 0], out[i, 1], out[i, 2] = _ray_end(eye, depth[r], directions[r])


@jit(cache=True, inline="always")
def _ray_end(eye, t, d):
    """eye + t d: where a ray from the eye (3,) along ``d`` (three numbers) ends at t."""
    return eye[0] + t * d[0], eye[1] + t * d[1], eye[2] + t * d[2]


def primary_rays(camera: Camera, spp: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """All camera rays as plain arrays: eye (3,) and directions (H * W * spp, 3).

    Ray r goes through pixel r // spp at sub-pixel sample r % spp (see ``subpixel_offsets``).
    """
    forward, right, up, eye = plain_frame(camera)
    offsets = subpixel_offsets(spp)
    width, height = camera.width, camera.height
    directions = np.empty((height * width * len(offsets), 3))
    run_jobs(_primary_directions, job_count(height, 128), width, height, offsets, forward, right,
             up, directions)  # fmt: skip
    return eye, directions


# ---------------------------------------------------------------------------------------
# World points onto the image, off the tape
# ---------------------------------------------------------------------------------------


def project(
    points: np.ndarray, frame: PlainFrame, width: int, height: int
) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (k, 2) (column, row; continuous, the image spans [0, W] x [0, H])
    and depth along the view axis (k,) of world points (k, 3)."""
    forward, right, up, eye = frame
    rel = points - eye
    depth = rel @ forward
    with np.errstate(divide="ignore", invalid="ignore"):
        x = (rel @ right) / (depth * (right @ right))
        y = (rel @ up) / (depth * (up @ up))
    return np.stack([(x + 1.0) * (width / 2.0), (1.0 - y) * (height / 2.0)], axis=1), depth


def to_image_plane(px: np.ndarray, width: int, height: int) -> np.ndarray:
    """Image-plane (x, y) in [-1, 1] of pixel coordinates (k, 2): 2 px / W - 1 and
    1 - 2 py / H."""
    # The same operations in the same order as written above, into one column buffer
    # reused: without the temporaries, 400k points take 1.8 ms instead of 4.5.
    column = 2.0 * px[:, 0]
    out = np.empty((len(px), 2), column.dtype)
    column /= width
    np.subtract(column, 1.0, out=out[:, 0])
    np.multiply(px[:, 1], 2.0, out=column)
    column /= height
    np.subtract(1.0, column, out=out[:, 1])
    return out


def clip_to_near(
    p0: np.ndarray, p1: np.ndarray, frame: PlainFrame, near: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The parts of 3-D segments p0 -> p1 (k, 3) in front of the plane at distance ``near``
    ahead of the eye: new endpoints (k, 3) each, and which segments keep a part (k,)."""
    forward, _, _, eye = frame
    z0, z1 = (p0 - eye) @ forward, (p1 - eye) @ forward
    keep = (z0 > near) | (z1 > near)
    cut = ((z0 <= near) | (z1 <= near)) & keep  # then z0 != z1
    t = np.where(cut, near - z0, 0.0) / np.where(cut, z1 - z0, 1.0)
    q = p0 + t[:, None] * (p1 - p0)
    p0 = np.where((cut & (z0 <= near))[:, None], q, p0)
    p1 = np.where((cut & (z1 <= near))[:, None], q, p1)
    return p0, p1, keep
