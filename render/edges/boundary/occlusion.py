"""Which points of a curve the camera sees (off the tape).

A point of a curve (the point on a mesh edge, an outline or the cut of two surfaces that a
quadrature point stands for) is hidden where something lies between it and the eye: an
any-hit ray from the eye that ends just short of it (``hidden_points``), answered by the
rasteriser's tiles when there are many rays per primitive, else by the BVH.
"""

from __future__ import annotations

import numpy as np

from render.scene.scene import Scene
from render.trace.raster import OCCLUSION_RAYS_PER_PRIMITIVE, raster_occluded
from render.trace.visibility import Visibility


def hidden_points(
    visibility: Visibility,
    frame,
    camera,
    coords: np.ndarray,
    directions: np.ndarray,
    depth: np.ndarray,
    norm: np.ndarray,
    ignore: np.ndarray,
    first_try: np.ndarray | None = None,
) -> np.ndarray:
    """(k,) bool: which of k points seen along camera directions (k, 3) through image-plane
    points ``coords`` (k, 2) at ``depth`` (k,) are hidden: something other than primitive
    ``ignore`` (k,) lies in front (an any-hit ray that ends just short of the point), or
    their curve is seen edge-on (|grad e| = ``norm`` zero) or from behind. ``frame``: the
    plain camera (``render.scene.camera.plain_frame``). With many rays per primitive the
    rays are answered by the rasteriser's tiles (``raster_occluded``), else by the BVH,
    which tries
    ``first_try`` (k,), a primitive likely to lie in front of each point (``seen_in``),
    before its traversal: the same answers either way."""
    tmax = depth * (1.0 - 1e-6)
    primitives = visibility.primitives
    n_prims = len(primitives[0]) + len(primitives[1])
    if visibility.bvh and len(coords) >= OCCLUSION_RAYS_PER_PRIMITIVE * n_prims:
        blocked = raster_occluded(
            primitives, frame, camera.width, camera.height, coords, directions, tmax, ignore
        )
    else:
        blocked = visibility.accelerator().occluded(
            np.broadcast_to(frame[3], directions.shape), directions, tmax,
            tmin=0.0, ignore_prim=ignore, first_try=first_try,
        )  # fmt: skip
    return (norm <= 0) | ~(depth > 0) | blocked


def seen_in(visibility: Visibility, pixel: np.ndarray, scene: Scene) -> np.ndarray | None:
    """(k,) int64: the primitive the camera sees at the first sample of each pixel ``pixel``
    (k,) (row * W + column), -1 for none; None if the render traced no camera rays (the
    path integrator's edges). What hides a point in a pixel is most often what is seen
    there: on the teapot at 512x512 it hides 24k of the 31k hidden edge points, which then
    need no traversal of the BVH."""
    if visibility.primary is None:
        return None
    prim_id = visibility.primary.prim_id  # ray r: pixel r // spp, sample r % spp
    width, height = scene.camera.width, scene.camera.height
    return np.take(prim_id, pixel * (prim_id.size // (width * height)))
