"""What silhouettes and shadow edges share: the sample grid, edge functions, crossings,
coverage.

Both kinds of edge are handled the same way (``render.edges.silhouettes``,
``render.edges.shadows``): a pair of adjacent samples on the regular sample grid
(``sample_grid``) has an edge between them whose *edge function* e(d) = m . d is linear in
the camera direction d; d is affine along the pair, so the crossing is a closed form, and
the edge's slope across the pair follows from m (``grid_gradient``, ``slope_across``). A
sphere's outline is where a quadratic in the same parameter vanishes
(``sphere_crossing``). Each sample's box is then blended by the area on the far side of
the edge (``box_coverage``, ``pair_coverages``), and the blends are added to the samples'
colours in one scatter (``add_to_samples``).

Functions named ``..._plain`` or taking arrays work off the tape (to find pairs); the
others work on tensors and arrays alike (with ``minidiff.either``) or on the tape.
"""

from __future__ import annotations

import numpy as np

import minidiff as md
from minidiff.either import as_column, dot_last
from render.scene.camera import image_plane_coords, plain_frame
from render.scene.scene import Camera, Scene, Sphere
from render.shade.surface import in_order


def sample_grid(camera: Camera, spp: int) -> np.ndarray:
    """(H n, W n) int64: the ray id at each position of the regular sample grid."""
    n = int(round(spp**0.5))
    rays = np.arange(camera.height * camera.width * spp).reshape(camera.height, camera.width, n, n)
    # ray = pixel * spp + sy * n + sx (``render.scene.camera.subpixel_offsets``); grid row py n + sy
    return rays.transpose(0, 2, 1, 3).reshape(camera.height * n, camera.width * n)


def sample_steps(camera: Camera, spp: int, dtype=np.float64) -> np.ndarray:
    """(2,) one sample step in image-plane x and y: x spans [-1, 1] over W n samples, so a
    step is 2 / (W n) (likewise y with H)."""
    n = round(spp**0.5)
    return np.array([2.0 / (camera.width * n), 2.0 / (camera.height * n)], dtype=dtype)


def plain_rays(camera: Camera, near: np.ndarray, far: np.ndarray, spp: int):
    """Eye (3,), directions (n, 3) of the near and far samples (float64, off the tape), and
    the factors (2,) that turn an image-plane gradient into sample-grid units."""
    forward, right, up, eye = plain_frame(camera)
    basis = np.stack([right, up, forward])
    d_near = _homogeneous(image_plane_coords(camera, near, spp)) @ basis
    d_far = _homogeneous(image_plane_coords(camera, far, spp)) @ basis
    return eye, d_near, d_far, (right, up, sample_steps(camera, spp))


def _homogeneous(coords: np.ndarray) -> np.ndarray:
    return np.concatenate([coords, np.ones((len(coords), 1), coords.dtype)], axis=1)


def plane_normal(corners):
    """Unnormalised normals (n, 3) of triangles: (b - a) x (c - a). ``corners`` is an
    (n, 3, 3) array (n may be 0), or the tensors (a, b, c), (n, 3) each, on the tape."""
    if isinstance(corners, np.ndarray):
        return np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    a, b, c = corners
    return md.cross(b - a, c - a)


def grid_gradient(normal, right, up, to_samples):
    """(gx, gy): the gradient, in sample-grid units, of an edge function whose gradient with
    respect to the ray direction is ``normal`` (n, 3). Directions are d = forward + x right
    + y up, and one sample step is ``to_samples`` (2,) in x and in y (y grows upwards, rows
    downwards: only magnitudes are used)."""
    return dot_last(normal, right) * to_samples[0], dot_last(normal, up) * to_samples[1]


def axis_ok(normal, horizontal, to_pixels) -> np.ndarray:
    """(n,) bool: the edge is handled by pairs of this axis: horizontal pairs take edges
    within 45 degrees of vertical (|gx| >= |gy|), vertical pairs the others. Each edge is
    then blended in one direction only, and its slope across a pair is at most 1."""
    gx, gy = grid_gradient(normal, *to_pixels)
    return np.where(horizontal, np.abs(gx) >= np.abs(gy), np.abs(gy) > np.abs(gx))


def slope_across(normal, frame, horizontal: np.ndarray, steps: np.ndarray) -> md.Tensor:
    """(n,) on the tape: how far an edge with edge-function normal ``normal`` (n, 3) moves
    along each pair's axis per sample step across it (|t| <= 1 by the 45-degree rule)."""
    gx, gy = grid_gradient(normal, frame[1], frame[2], steps)
    return md.where(horizontal, gy, gx) / md.where(horizontal, gx, gy)


def outline_normal(center, radius, eye, d_near, d_far, s):
    """The gradient of a sphere's discriminant D(d) = (oc . d)^2 - |d|^2 (|oc|^2 - r^2)
    with respect to the direction, at the crossing d* = d_near + s (d_far - d_near):
    2 (oc . d*) oc - 2 (|oc|^2 - r^2) d*. Tensors or arrays."""
    oc = eye - center
    d = d_near + as_column(s) * (d_far - d_near)
    kappa = dot_last(oc, oc) - radius * radius
    return as_column(dot_last(oc, d) * 2.0) * oc - as_column(kappa * 2.0) * d


def _sphere_quadratic(eye, center, radius, d_near, d_far):
    """Coefficients (q2, q1, q0) of the discriminant along the segment of directions
    d(s) = d_near + s (d_far - d_near): disc(s) = q2 s^2 + 2 q1 s + q0 (works on tensors
    and on arrays)."""
    oc = eye - center
    delta = d_far - d_near
    kappa = dot_last(oc, oc) - radius * radius
    b0, b1 = dot_last(d_near, oc), dot_last(delta, oc)
    a0, a1, a2 = dot_last(d_near, d_near), dot_last(d_near, delta), dot_last(delta, delta)
    return b1 * b1 - kappa * a2, b0 * b1 - kappa * a1, b0 * b0 - kappa * a0


def sphere_crossing_plain(sphere: Sphere, eye, d_near, d_far) -> np.ndarray:
    """(n,) s* where the segment leaves the sphere's outline (NaN where it does not: the far
    ray hits the sphere too, or the eye is inside it)."""
    center = np.asarray(sphere.center.data, np.float64)
    radius = float(sphere.radius.data)
    if np.linalg.norm(eye - center) <= radius:
        return np.full(len(d_near), np.nan)
    q2, q1, q0 = _sphere_quadratic(eye, center, radius, d_near, d_far)
    leaves = (q0 > 0) & (q2 + 2.0 * q1 + q0 < 0)  # hit at s = 0, miss at s = 1
    with np.errstate(divide="ignore", invalid="ignore"):
        s = q0 / (np.sqrt(np.maximum(q1 * q1 - q2 * q0, 0.0)) - q1)
    return np.where(leaves & (s > 0) & (s < 1), s, np.nan)


# --------------------------------------------------------------------------------------
# On the tape
# --------------------------------------------------------------------------------------


def sphere_crossing(sphere: Sphere, eye, d_near, d_far) -> md.Tensor:
    """s* of the sphere's outline along each segment, on the tape.

    disc(s) = q2 s^2 + 2 q1 s + q0 goes from positive (the near ray hits) to negative (the
    far ray misses), so the crossing is the root where it decreases, q2 s + q1 = -sqrt(D)
    with D = q1^2 - q2 q0: s* = (-q1 - sqrt(D)) / q2 = q0 / (sqrt(D) - q1). The second form
    stays finite when q2 is 0 (the discriminant linear in s).
    """
    q2, q1, q0 = _sphere_quadratic(eye, sphere.center, sphere.radius, d_near, d_far)
    return q0 / (md.sqrt(q1 * q1 - q2 * q0) - q1)


def triangle_corners(scene: Scene, ids: np.ndarray):
    """The corners (a, b, c), each (k, 3) on the tape, of the triangles with global ids
    ``ids`` (k,), in that order."""
    parts, order, first = [], [], 0
    for mesh in scene.meshes:
        rows = np.flatnonzero((ids >= first) & (ids < first + mesh.num_faces))
        if len(rows):
            corners = mesh.vertices[mesh.faces[ids[rows] - first].reshape(-1)]
            parts.append(md.reshape(corners, (-1, 3, 3)))
            order.append(rows)
        first += mesh.num_faces
    corners = in_order(parts, order)
    return corners[:, 0], corners[:, 1], corners[:, 2]


def box_coverage(offset: md.Tensor, slope: md.Tensor, include_zero: bool = True) -> md.Tensor:
    """The area of a unit pixel box on the positive side of a straight edge, (n,).

    In the box's frame, u along the pair's axis (box centre at u = 0) and v across it, the
    edge is u = -offset + slope * v, |slope| <= 1, and the covered part is u > that line:
    area = integral over v in [-1/2, 1/2] of max(0, offset - slope v). With h = |slope|/2:
    offset itself (clamped at 0) where |offset| >= h (the edge stays on one side of the
    box's centre line across the whole box), else the triangle (offset + h)^2 / (4 h).
    With slope 0 this is nvdiffrast's 1-D coverage; the slope makes it exact for any
    straight edge.
    The two branches meet with equal value and derivative (the area is C^1).
    """
    h = md.abs(slope) * 0.5
    corner = np.abs(offset.data) < h.data  # a constant choice of formula, like visibility
    # max(offset, 0) with the kink at 0 given to one side only (``include_zero``): an edge
    # exactly on the boundary between two boxes must move exactly one of them.
    positive = (offset.data >= 0) if include_zero else (offset.data > 0)
    straight = md.where(positive, offset, 0.0)
    triangle = (offset + h) ** 2 / (md.maximum(h, 1e-12) * 4.0)
    return md.where(corner, triangle, straight)


def pair_coverages(s: md.Tensor, slope: md.Tensor) -> tuple[md.Tensor, md.Tensor]:
    """For an edge crossing a pair at s* (sample 0 at s = 0, sample 1 at s = 1): the area
    of sample 0's box beyond the edge and of sample 1's box before it, (n, 1) each. At
    s* = 0.5 exactly the edge lies on the boxes' border: only one of them moves with it."""
    beyond = box_coverage(0.5 - s, slope)
    before = box_coverage(s - 0.5, slope, include_zero=False)
    return md.reshape(beyond, (-1, 1)), md.reshape(before, (-1, 1))


def add_to_samples(ray_colour: md.Tensor, updates: list) -> md.Tensor:
    """ray_colour (N, 3) plus every (ray ids, additions) in ``updates`` (None: nothing),
    scattered in one pass. Each pair's additions are computed from the colours before any
    blending, as in nvdiffrast."""
    updates = [u for u in updates if u is not None]
    if not updates:
        return ray_colour
    rays = np.concatenate([r for r, _ in updates])
    values = md.concatenate([v for _, v in updates]) if len(updates) > 1 else updates[0][1]
    return ray_colour + md.scatter_add(values, rays, ray_colour.shape[0])
