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
  plain arrays with the scene's accelerator (``trace_bounce``);
* where it hits is recomputed on the tape (``render.shade.surface``) from the differentiable
  hit point and mirror direction, so gradients reach the mirror's geometry and the camera
  (through p and n), the reflected object and its material, the lights, and rho.

Self-intersection: the traced ray starts a little off the mirror, along its geometric
normal, by the shadow rays' scale-relative offset (``render.trace.visibility.shadow_offset``), so
rounding cannot make it hit the face it leaves, even at grazing angles. The tape starts it
at p itself (the offset is not part of the model).

Not modelled: silhouettes and shadow edges seen *in* a mirror get no edge term (with
``antialias=True`` only camera-ray pairs are blended), and a mirror's own edge is blended as
any silhouette.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

import minidiff as md
from render.edges.silhouettes import in_order
from render.scene.scene import Mesh, Scene
from render.shade.lighting import shade_surface
from render.shade.surface import Surface, mesh_surface, sphere_surface
from render.trace.accel import Accelerator
from render.trace.visibility import primitive_ranges, shadow_offset, trace_shadows


def reflect(directions, normals) -> md.Tensor:
    """Mirror directions r = d - 2 (d . n) n (k, 3), on the tape: directions (k, 3) of any
    length (|r| = |d|), normals (k, 3) unit."""
    return directions - md.reshape(2.0 * md.dot(directions, normals), (-1, 1)) * normals


@dataclass
class Bounces:
    """What every bounce needs: the scene, the accelerator its visibility was traced with
    (``accelerator()``, built on first use; ``bvh`` False if it is brute force), the
    primitives (``render.trace.visibility.scene_primitives``: triangles (T, 3, 3), sphere
    centres (S, 3), radii (S,)),
    the scene's size (for the offsets), whether shadows are traced, the number of
    reflections allowed, and the decisions made, per bounce and camera ray: the primitive
    its mirror ray hit (``hit_ids[b]`` (N,): -2 no such ray, -1 the background) and which
    lights reach that hit (``lit[b]`` (n_lights, N) bool)."""

    scene: Scene
    accelerator: Callable[[], Accelerator]
    bvh: bool
    primitives: tuple[np.ndarray, np.ndarray, np.ndarray]
    size: float
    shadows: bool
    max_bounces: int
    hit_ids: list[np.ndarray]
    lit: list[np.ndarray]


def geometric_normals(bounces: Bounces, prims: np.ndarray, points: np.ndarray, incoming):
    """(k, 3) plain unit normals of the primitives ``prims`` (k,) at ``points`` (k, 3),
    facing the ``incoming`` directions (k, 3): the side the mirror ray leaves from."""
    triangles, centers, _ = bounces.primitives
    n_tri = len(triangles)
    normals = np.empty_like(points)
    on_triangle = prims < n_tri
    a, b, c = np.moveaxis(triangles[prims[on_triangle]], 1, 0)
    normals[on_triangle] = np.cross(b - a, c - a)
    on_sphere = ~on_triangle
    normals[on_sphere] = points[on_sphere] - centers[prims[on_sphere] - n_tri]
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    facing_away = np.einsum("ij,ij->i", normals, incoming) > 0
    normals[facing_away] *= -1.0
    return normals


def trace_bounce(bounces: Bounces, points: np.ndarray, normals: np.ndarray, directions):
    """Trace k mirror rays on plain arrays: from ``points`` (k, 3), lifted off the surface
    along the unit ``normals`` (k, 3), along ``directions`` (k, 3). Returns the primitive
    each hits (k,) int64 (-1: none), the ray origins used (k, 3) and the hit points (k, 3)
    (NaN where missed)."""
    origins = points + shadow_offset(points, bounces.size) * normals
    prim, t, _, _ = bounces.accelerator().closest_hit(origins, directions)
    hits = origins + np.where(prim >= 0, t, np.nan)[:, None] * directions
    return prim, origins, hits


def reflected_radiance(
    bounces: Bounces, surface: Surface, prims: np.ndarray, rays: np.ndarray, bounce: int
) -> md.Tensor:
    """The radiance (k, 3) arriving along the mirror directions at k hits of ``surface``
    (on primitives ``prims`` (k,), reached by camera rays ``rays`` (k,)): the colour of
    what each mirror ray hits, shaded like a camera hit (with its own reflection while
    ``bounce < max_bounces``), or the background. ``bounce`` counts from 1."""
    scene = bounces.scene
    mirrored = reflect(surface.directions, surface.normals)
    points, plain_directions = surface.points.data, mirrored.data
    lift = geometric_normals(bounces, prims, points, surface.directions.data)
    prim, origins, hit_points = trace_bounce(bounces, points, lift, plain_directions)
    bounces.hit_ids[bounce - 1][rays] = prim

    parts, order = [], []
    for obj, first, count in primitive_ranges(scene):
        rows = np.flatnonzero((prim >= first) & (prim < first + count))
        if len(rows) == 0:
            continue
        start, along = surface.points[rows], mirrored[rows]
        if isinstance(obj, Mesh):
            hits = mesh_surface(obj, prim[rows] - first, start, along)
        else:  # which root the tracer took follows from where its ray started
            inside = np.linalg.norm(origins[rows] - obj.center.data, axis=1) < obj.radius.data
            hits = sphere_surface(obj, start, along, inside)
        lit = _lit(bounces, hit_points[rows], prim[rows])
        bounces.lit[bounce - 1][:, rays[rows]] = lit
        lit = [mask.astype(hits.points.dtype) for mask in lit]
        colour, _ = shade_surface(hits, obj.material, scene.lights, lit)
        if bounce < bounces.max_bounces and obj.material.reflective:
            further = reflected_radiance(bounces, hits, prim[rows], rays[rows], bounce + 1)
            colour = colour + obj.material.reflectance * further
        parts.append(colour)
        order.append(rows)
    missed = np.flatnonzero(prim < 0)
    if len(missed):
        parts.append(md.broadcast_to(scene.background, (len(missed), 3)))
        order.append(missed)
    return in_order(parts, order)


def _lit(bounces: Bounces, points: np.ndarray, prims: np.ndarray) -> np.ndarray:
    """(n_lights, k) bool: which lights reach the hit points, as for camera hits."""
    lights = bounces.scene.lights
    if not bounces.shadows:
        return np.ones((len(lights), len(points)), dtype=bool)
    masks = [
        trace_shadows(
            bounces.accelerator,
            bounces.primitives,
            light,
            points,
            prims,
            bounces.size,
            bounces.bvh,
        )
        for light in lights
    ]
    return np.array(masks, dtype=bool).reshape(len(lights), len(points))
