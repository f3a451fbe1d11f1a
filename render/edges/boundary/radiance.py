"""The radiance either side of a curve: f_+ and f_- of the boundary term (off the tape).

The boundary term of a curve's point is w (f_+ - f_-) / |grad e| de/dtheta: f_+ and f_- are
what the camera sees just on either side of the curve. The curve kinds ask for them through
a ``SideRadiance``, in one of two forms: ``seen`` where the primitive seen on a side is known
(a mesh edge's face, one of two crossing triangles: shaded at the curve's point), ``along``
where it is not (a ray ``EPSILON`` pixels beside the curve, traced). The direct renderer's
is ``DirectRadiance`` (its own shading of the rays either side); the path
integrator's is ``render.path.boundary.primary.PathRadiance`` (path-traced estimates).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Protocol

import numpy as np

import minidiff as md
from render.scene.cache import RenderCache
from render.scene.camera import camera_directions, plain_frame, ray_ends
from render.scene.scene import Scene
from render.shade.hits import shade_camera_hits
from render.shade.mirrors import Mirrors
from render.trace.visibility import PrimaryHits, Visibility, hit_past

#: How far, in pixels, the two rays that see either side of a curve pass from it.
EPSILON = 1e-3


class SideRadiance(Protocol):
    """What the camera sees through image-plane points, for f_+ and f_- (float64, off the
    tape). Image-plane points are (x, y) in [-1, 1] (``render.scene.camera``).

    ``key`` (k,) int64 names the quadrature point each ray belongs to: the two sides of a
    point share it. A deterministic renderer ignores it; a Monte Carlo one draws both
    sides' random numbers from it, so that f_+ - f_- is estimated with common random
    numbers (far less noise than two independent estimates)."""

    def seen(self, coords: np.ndarray, prim_id: np.ndarray, depth: np.ndarray, key: np.ndarray,
             beside: np.ndarray | None = None, shadowed: np.ndarray | None = None,
             ) -> np.ndarray:  # fmt: skip
        """(k, 3): the radiance of camera rays through ``coords`` (k, 2) that first meet
        primitive ``prim_id`` (k,) int64 (global ids; -1: none) at ``depth`` (k,) along the
        view axis. ``beside`` (k, m) (global ids, -1 padding): for points on an edge, the
        faces on that edge, which cannot shadow them (``Visibility.lit_beside``).
        ``shadowed`` (k, L) bool: for points on an edge, whether their side (their face)
        lies in the shadow the edge's other face casts from each light
        (``mesh_edge.shadowed_sides``): the limit from inside the face."""
        ...

    def along(
        self, coords: np.ndarray, key: np.ndarray, beside: np.ndarray | None = None
    ) -> np.ndarray:
        """(k, 3): the radiance of the camera rays through ``coords`` (k, 2), their first
        hit traced (past the faces ``beside`` (k, m), as ``seen``'s: the rays just beyond
        an edge, which meet its faces only across a seam's crack)."""
        ...


def seen_through(
    scene: Scene,
    visibility: Visibility,
    coords: np.ndarray,
    prim_id: np.ndarray,
    depth: np.ndarray,
    directions: np.ndarray | None = None,
    beside: np.ndarray | None = None,
    shadowed: np.ndarray | None = None,
) -> Visibility:
    """The render's ``visibility`` with its camera rays replaced by k rays through
    image-plane points ``coords`` (k, 2) that meet primitives ``prim_id`` (k,) (-1: the
    background) at ``depth`` (k,) along the view axis: their hit points and, per light,
    which of them it reaches (shadow rays traced as the render's are; for points on an
    edge, passing the faces ``beside`` (k, m) on it: ``Visibility.lit_beside``; and dark
    where ``shadowed`` (k, L) says the edge's other face shadows their side).
    ``directions``: the rays' camera directions (k, 3) if the caller has them already."""
    forward, right, up, eye = plain_frame(scene.camera)
    hit = np.flatnonzero(prim_id >= 0)
    at = np.take(coords, hit, axis=0)  # np.take: rows gathered ~5x faster than coords[hit]
    if directions is None:
        directions = camera_directions(coords, right, up, forward)
    points = ray_ends(eye, directions, depth, hit)
    primary = PrimaryHits(prim_id, hit, depth, points, at)
    lit = [visibility.lit_towards(light, points, prim_id[hit]) for light in scene.lights]
    if beside is not None and visibility.shadows:
        lit = [visibility.lit_beside(light, points, prim_id[hit], beside[hit], mask)
               for light, mask in zip(scene.lights, lit, strict=True)]  # fmt: skip
    if shadowed is not None and visibility.shadows:
        lit = [mask & ~shadowed[hit, j] for j, mask in enumerate(lit)]
    return replace(visibility, primary=primary, lit=lit)


class DirectRadiance:
    """The direct renderer's ``SideRadiance``: its own shading of the rays either side
    (``key`` is ignored: the shading is deterministic).
    ``frame``: the render's camera frame on the tape (``render.scene.camera.camera_frame``)."""

    def __init__(self, scene: Scene, visibility: Visibility, frame, max_bounces: int) -> None:
        self.scene, self.visibility, self.frame = scene, visibility, frame
        self.max_bounces = max_bounces

    def seen(self, coords: np.ndarray, prim_id: np.ndarray, depth: np.ndarray, key: np.ndarray,
             beside: np.ndarray | None = None, shadowed: np.ndarray | None = None,
             ) -> np.ndarray:  # fmt: skip
        """``SideRadiance.seen``, off the tape: the radiance (k, 3) float64 of camera rays
        through ``coords`` (k, 2) that meet ``prim_id`` (k,) (-1: the background) at
        ``depth`` (k,), shaded as the render's camera hits are (shadows and mirror
        reflections included, by ``shade_camera_hits``; the faces ``beside`` passed, the
        sides ``shadowed`` in their edge's own shadow)."""
        scene, max_bounces = self.scene, self.max_bounces
        seen = seen_through(scene, self.visibility, coords, prim_id, depth, beside=beside,
                            shadowed=shadowed)  # fmt: skip
        out = np.empty((len(coords), 3))
        out[:] = np.asarray(scene.background.data, np.float64)
        # Values only: a reflectance that is zero adds nothing, even while it is differentiated.
        if not any(np.any(obj.material.reflectance.data) for obj in scene.objects):
            max_bounces = 0
        with md.no_grad():
            mirrors = Mirrors.of(scene, seen, max_bounces)
            shading = shade_camera_hits(
                scene, seen, self.frame, RenderCache(), mirrors, surfaces=False
            )
        if shading.colour is not None:
            out[shading.rays] = shading.colour.data
        return out

    def along(
        self, coords: np.ndarray, key: np.ndarray, beside: np.ndarray | None = None
    ) -> np.ndarray:
        """``SideRadiance.along``, off the tape: the radiance (k, 3) the camera sees through
        image-plane points ``coords`` (k, 2), each ray traced with the render's accelerator
        (past the faces ``beside``), then shaded as ``seen`` does."""
        prim_id, t = first_hits(self.scene, self.visibility.accelerator(), coords, beside)
        return self.seen(coords, prim_id, t, key)


def first_hits(scene: Scene, accelerator, coords: np.ndarray, beside=None) -> tuple:
    """(prim (k,), depth (k,)): what the camera rays through image-plane points ``coords``
    (k, 2) first meet (-1, inf: nothing), past the faces ``beside`` (k, m) where given
    (``render.trace.visibility.hit_past``)."""
    forward, right, up, eye = plain_frame(scene.camera)
    directions = camera_directions(coords, right, up, forward)
    origins = np.broadcast_to(eye, directions.shape)
    if beside is None or not np.any(beside >= 0):
        prim_id, t, _, _ = accelerator.closest_hit(origins, directions)
    else:
        prim_id, t, _, _ = hit_past(accelerator, origins, directions, beside)
    return prim_id, t
