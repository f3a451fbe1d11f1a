"""Which points of a curve the camera sees (off the tape).

A point of a curve (the point on a mesh edge, an outline or the cut of two surfaces that a
quadrature point stands for) is hidden where something lies between it and the eye: an
any-hit ray from the eye that ends just short of it (``hidden_points``), answered by the
rasteriser's tiles when there are many rays per primitive, else by the BVH. What a render
hands the boundary term for these rays is an ``Occluders``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from render.scene.scene import Scene
from render.trace.accel import Accelerator
from render.trace.primitives import Primitives
from render.trace.raster import OCCLUSION_RAYS_PER_PRIMITIVE, raster_occluded
from render.trace.visibility import Visibility


@dataclass(frozen=True)
class Occluders:
    """What the boundary term needs of a render's geometry (plain arrays, constants).

    primitives: what the render traced (``render.trace.primitives.scene_primitives``);
    size: their bounding box's diagonal; accelerator(): their accelerator (built on first
    call); bvh: whether it is a BVH (False: brute force, and the rasteriser does not answer
    occlusion rays either); geometry: the stamp of the primitives (keys of the render
    cache); camera_prims (H * W * spp,) int64: the primitive each camera ray of the render
    sees (-1: none), or None where the render traced none (the path integrator's edges)."""

    primitives: Primitives
    size: float
    accelerator: Callable[[], Accelerator]
    bvh: bool
    geometry: np.ndarray
    camera_prims: np.ndarray | None = None

    @classmethod
    def of(cls, visibility: Visibility) -> Occluders:
        """The occluders of a render's ``Visibility`` (the direct renderer's)."""
        return cls(
            visibility.primitives,
            visibility.size,
            visibility.accelerator,
            visibility.bvh,
            visibility.geometry,
            visibility.primary.prim_id,
        )


#: ``hidden_points``' rays end this fraction of the depth short of the point.
SHORT = 1e-6


def hidden_points(
    visibility: Occluders | Visibility,
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
    tmax = depth * (1.0 - SHORT)
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


def seen_in(occluders: Occluders, pixel: np.ndarray, scene: Scene) -> np.ndarray | None:
    """(k,) int64: the primitive the camera sees at the first sample of each pixel ``pixel``
    (k,) (row * W + column), -1 for none; None if the render traced no camera rays (the
    path integrator's edges). What hides a point in a pixel is most often what is seen
    there: on the teapot at 512x512 it hides 24k of the 31k hidden edge points, which then
    need no traversal of the BVH."""
    prim_id = occluders.camera_prims  # ray r: pixel r // spp, sample r % spp
    if prim_id is None:
        return None
    width, height = scene.camera.width, scene.camera.height
    return np.take(prim_id, pixel * (prim_id.size // (width * height)))
