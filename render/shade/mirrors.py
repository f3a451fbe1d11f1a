"""Mirror reflection: at a hit on a reflective material, trace the mirror ray and add what it
sees.

A material with reflectance rho (a scalar or RGB) adds, at each of its hits,

    rho * L(p, r),   r = d - 2 (d . n) n,

the radiance arriving at the hit point p from the mirror direction r of the incoming
direction d about the (shading) normal n, which faces the incoming ray. L is computed like
a camera hit's colour: direct light with shadows, plus the hit's own reflection, up to
``max_bounces`` reflections in all (RayTracer.jl's depth is 2); a reflected ray that
leaves the scene sees the background.

As for camera rays, the decisions are constants and the rest is on the tape:

* which primitive the mirror ray hits, and which lights reach that hit, are traced on
  plain arrays with the scene's accelerator (``Mirrors.trace``), and recorded;
* where it hits is recomputed on the tape (``render.shade.surface``) from the differentiable
  hit point and mirror direction, so gradients reach the mirror's geometry and the camera
  (through p and n), the reflected object and its material, the lights, and rho.

What a mirror ray hits is then shaded like a camera hit, by the same function
(``render.shade.hits.shade_hits``), which calls back here for the next bounce.

Self-intersection: the traced ray starts a little off the mirror, along its geometric
normal, by the shadow rays' scale-relative offset
(``render.trace.visibility.shadow_offset``), so rounding cannot make it hit the face it
leaves, even at grazing angles. The tape starts it at p itself (the offset is not part of
the model).

Not modelled: silhouettes and shadow edges seen *in* a mirror get no edge term (with
``antialias=True`` only camera-ray pairs are blended), and a mirror's own edge is blended as
any silhouette.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

import minidiff as md
from render.scene.scene import Scene
from render.shade.surface import Hits, Surface, geometric_normals, surface_at
from render.trace.primitives import primitive_ranges
from render.trace.visibility import Visibility, shadow_offset


def reflect(directions, normals) -> md.Tensor:
    """Mirror directions r = d - 2 (d . n) n (k, 3), on the tape: directions (k, 3) of any
    length (|r| = |d|), normals (k, 3) unit."""
    return directions - md.reshape(2.0 * md.dot(directions, normals), (-1, 1)) * normals


@dataclass
class BounceRecord:
    """The decisions made for the mirror rays, per bounce b = 1, 2, ... and camera ray:
    the primitive its b-th mirror ray hit (``hit_ids[b - 1]`` (N,) int64: -2 no such ray,
    -1 the background) and which lights reach that hit (``lit[b - 1]`` (n_lights, N)
    bool)."""

    hit_ids: list[np.ndarray]
    lit: list[np.ndarray]

    @classmethod
    def empty(cls, max_bounces: int, n_lights: int, n_rays: int) -> BounceRecord:
        return cls(
            [np.full(n_rays, -2, dtype=np.int64) for _ in range(max_bounces)],
            [np.zeros((n_lights, n_rays), dtype=bool) for _ in range(max_bounces)],
        )


class Mirrors:
    """Traces the mirror rays of one render: the scene, its visibility (primitives,
    accelerator, shadow rays) and ``max_bounces`` are fixed at creation; each ``trace``
    writes its decisions into ``record`` (a ``BounceRecord``)."""

    def __init__(self, scene: Scene, visibility: Visibility, max_bounces: int) -> None:
        self.scene = scene
        self.visibility = visibility
        self.max_bounces = max_bounces
        n_rays = visibility.primary.prim_id.size
        self.record = BounceRecord.empty(max_bounces, len(scene.lights), n_rays)

    @classmethod
    def of(cls, scene: Scene, visibility: Visibility, max_bounces: int) -> Mirrors | None:
        """The render's mirror tracer, or None if no hit can spawn a mirror ray."""
        if max_bounces == 0 or not any(obj.material.reflective for obj in scene.objects):
            return None
        return cls(scene, visibility, max_bounces)

    def trace(self, hits: Hits, bounce: int) -> tuple[Iterator[Hits], np.ndarray]:
        """The mirror rays leaving k ``hits`` (bounce ``bounce``, counting from 1): what
        each ray hits, object by object, as ``Hits`` whose rows index the k rays (each
        object's Surface is recomputed on the tape when the iterator reaches it), and the
        rows (m,) of the rays that miss everything."""
        surface = hits.surface
        mirrored = reflect(surface.directions, surface.normals)
        points, plain_directions = surface.points.data, mirrored.data
        lift = self._geometric_normals(hits.prims, points, surface.directions.data)
        prim, origins, hit_points = self._closest_hits(points, lift, plain_directions)
        self.record.hit_ids[bounce - 1][hits.rays] = prim
        groups = self._hit_groups(surface, mirrored, prim, origins, hit_points, hits.rays, bounce)
        return groups, np.flatnonzero(prim < 0)

    def _hit_groups(self, surface: Surface, mirrored, prim, origins, hit_points, rays, bounce):
        for index, (obj, first, count) in enumerate(primitive_ranges(self.scene)):
            rows = np.flatnonzero((prim >= first) & (prim < first + count))
            if len(rows) == 0:
                continue
            start, along = surface.points[rows], mirrored[rows]
            # A sphere's root is the one the tracer took: from where its ray started.
            found = surface_at(obj, prim[rows] - first, start, along, traced_from=origins[rows])
            lit = self._lit(hit_points[rows], prim[rows])
            self.record.lit[bounce - 1][:, rays[rows]] = lit
            lit = [mask.astype(found.points.dtype) for mask in lit]
            yield Hits(obj, index, found, prim[rows], rays[rows], rows, lit)

    def _geometric_normals(self, prims: np.ndarray, points: np.ndarray, incoming):
        """(k, 3) plain unit normals of the primitives ``prims`` (k,) at ``points`` (k, 3),
        facing the ``incoming`` directions (k, 3): the side the mirror ray leaves from."""
        normals = geometric_normals(self.visibility.primitives, prims, points)
        facing_away = np.einsum("ij,ij->i", normals, incoming) > 0
        normals[facing_away] *= -1.0
        return normals

    def _closest_hits(self, points: np.ndarray, normals: np.ndarray, directions):
        """Trace k mirror rays on plain arrays: from ``points`` (k, 3), lifted off the
        surface along the unit ``normals`` (k, 3), along ``directions`` (k, 3). Returns the
        primitive each hits (k,) int64 (-1: none), the ray origins used (k, 3) and the hit
        points (k, 3) (NaN where missed)."""
        origins = points + shadow_offset(points, self.visibility.size) * normals
        prim, t, _, _ = self.visibility.accelerator().closest_hit(origins, directions)
        hits = origins + np.where(prim >= 0, t, np.nan)[:, None] * directions
        return prim, origins, hits

    def _lit(self, points: np.ndarray, prims: np.ndarray) -> np.ndarray:
        """(n_lights, k) bool: which lights reach the hit points, as for camera hits."""
        lights = self.scene.lights
        masks = [self.visibility.lit_towards(light, points, prims) for light in lights]
        return np.array(masks, dtype=bool).reshape(len(lights), len(points))
