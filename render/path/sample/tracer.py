"""Sampling paths, off the tape: where each path goes and with what probability.

A path starts at a random point of its pixel and bounces through the scene. At each vertex
it gets light three ways, each recorded here as discrete choices and constant weights
(``render.path.gradient.transport`` then computes the radiance they carry on the tape):

* **emission** of the surface it reached (seen directly, or reached by a sampled direction:
  then weighted by multiple importance sampling (MIS) against next-event estimation);
* **next-event estimation** (NEE): a point picked on an area light (``Emitters``), its
  shadow ray, and its MIS weight; and every point or directional light, with its shadow ray;
* **continuation**: a lobe of the material picked (diffuse, Blinn-Phong, mirror), a
  direction sampled from it, Russian roulette after ``rr_depth`` vertices, the ray traced
  with the BVH. It ends on a new vertex, leaves the scene (it then sees the environment,
  the scene's ``background``), or stops.

``max_depth`` counts segments as Mitsuba 3 does: 1 shows the emitters seen directly, 2 adds
direct lighting, 3 one bounce of indirect light, and so on.

Vertices are reached in one of three forms, which say how the tape recomputes them:
``CAMERA`` and ``MIRROR`` vertices are where a ray meets the recorded primitive (the ray
moves with the camera or the mirror, as in the direct renderer); ``AREA`` vertices, reached
by a sampled direction, are the recorded point *on* the primitive (its barycentrics), so
they move with it, and the sampled density is converted to area measure (see
``render.path.gradient.transport`` for why this keeps the derivative of area lights and of moving
geometry right).

Every random number is ``render.path.sample.random.uniform(seed, path id, dimension)``: the paths
of a batch do not depend on which other paths are in it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import minidiff as md
from render.path.sample.choices import vertex_choices
from render.path.sample.emitters import Emitters
from render.path.sample.random import bounce_dimension, uniform
from render.path.sample.records import AREA, CAMERA, MIRROR, STOP, PathBatch, Vertices
from render.path.sample.sampling import dot, unit
from render.path.sample.tables import Tables
from render.scene.cache import RenderCache
from render.scene.camera import camera_directions, plain_frame, to_image_plane
from render.scene.scene import Scene
from render.shade.surface import geometric_normals
from render.trace.accel import Accelerator
from render.trace.primitives import primitive_ranges, scene_primitives
from render.trace.visibility import (
    cached_accelerator,
    geometry_stamp,
    scene_size,
    shadow_offset,
    shadow_rays,
)

#: The largest max_depth and rr_depth: every bounce's random-number dimensions
#: (``random.bounce_dimension``) then fit in an int64.
MAX_DEPTH = 2**59


@dataclass
class _Lobes:
    """Per object (in ``primitive_ranges`` order): the probabilities of picking the
    diffuse, glossy and mirror lobes (O, 3) (each lobe's mean reflectance, normalised), the
    sum of those reflectances (O,) (at most 1: Russian roulette's throughput estimate) and
    the Blinn-Phong exponent (O,)."""

    probability: np.ndarray
    reflectance: np.ndarray
    shininess: np.ndarray

    @classmethod
    def of(cls, objects) -> _Lobes:
        weights, shininess = [], []
        for obj in objects:
            m = obj.material
            albedo = m.texture.data.mean() if m.texture is not None else m.albedo.data.mean()
            specular = float(np.mean(m.specular.data))
            if m.specular_texture is not None:
                specular *= float(m.specular_texture.data.mean())
            weights.append([albedo, specular, float(np.mean(m.reflectance.data))])
            shininess.append(float(m.shininess.data))
        w = np.maximum(np.array(weights, np.float64).reshape(-1, 3), 0.0)
        total = w.sum(axis=1)
        probability = w / np.where(total > 0, total, 1.0)[:, None]
        return cls(probability, np.minimum(total, 1.0), np.array(shininess))


class PathSampler:
    """Samples batches of paths in one scene (world space, ``render.scene.placement``):
    its primitives, BVH, emitters and materials' lobes, read once as plain arrays. With a
    ``cache`` (the scene's ``RenderCache``) the BVH is the one kept there while the
    geometry is unchanged, refitted when it moved (``visibility.cached_accelerator``);
    without, built anew."""

    def __init__(self, world: Scene, spp: int, max_depth: int, rr_depth: int, seed: int,
                 cache: RenderCache | None = None):  # fmt: skip
        self.scene, self.spp, self.max_depth, self.rr_depth, self.seed = (
            world, spp, max_depth, rr_depth, seed,
        )  # fmt: skip
        self.cache = cache  # the scene's render cache, if any (read by the boundary terms)
        self.primitives = scene_primitives(world)
        self.n_triangles = len(self.primitives[0])
        self.size = max(scene_size(self.primitives), 1e-300)
        if cache is None:
            self.accelerator = Accelerator(*self.primitives)
        else:
            geometry = geometry_stamp(cache, self.primitives)
            self.accelerator = cached_accelerator(cache, self.primitives, geometry)
        ranges = primitive_ranges(world)
        self.objects = [obj for obj, _, _ in ranges]
        self.first = np.array([first for _, first, _ in ranges], np.int64)
        self.lobes = _Lobes.of(self.objects)
        self.emitters = Emitters.of(world, self.primitives)
        self.frame = plain_frame(world.camera)
        with md.no_grad():  # the tables the compiled choices read, plain
            self.tables = Tables.of(world, self.frame, leaves=False)

    def sample(self, paths: np.ndarray) -> PathBatch:
        """The ``PathBatch`` of path ids ``paths`` (N,) int64."""
        camera = self.scene.camera
        width, height = camera.width, camera.height
        pixel = paths // self.spp
        film = np.stack(
            [
                pixel % width + uniform(self.seed, paths, 0),
                pixel // width + uniform(self.seed, paths, 1),
            ],
            axis=1,
        )
        return self.start(paths, to_image_plane(film, width, height))

    def start(
        self,
        paths: np.ndarray,
        coords: np.ndarray,
        prim: np.ndarray | None = None,
        depth: np.ndarray | None = None,
    ) -> PathBatch:
        """The ``PathBatch`` of paths ``paths`` (N,) whose camera rays pass through the
        image-plane points ``coords`` (N, 2): traced (``prim`` None), or given their first
        hit, primitive ``prim`` (N,) (-1: none) at ``depth`` (N,) along the view axis (the
        sides of an edge, ``render.path.boundary.primary``)."""
        forward, right, up, eye = self.frame
        directions = camera_directions(coords, right, up, forward)
        if prim is None:
            prim, t, u, v = self.accelerator.closest_hit(
                np.broadcast_to(eye, directions.shape), directions
            )
            rows = np.flatnonzero(prim >= 0)
            points = eye + t[rows, None] * directions[rows]
            local = self.local_coordinates(prim[rows], points, u[rows], v[rows])
        else:
            rows = np.flatnonzero(prim >= 0)
            points = eye + depth[rows, None] * directions[rows]
            local = self.local_coordinates(
                prim[rows], points, *self._barycentric(prim[rows], points)
            )
        state = _State(rows, prim[rows], local, points, unit(directions[rows]),
                       np.full(len(rows), CAMERA, np.int8), np.zeros(len(rows)), points,
                       np.ones(len(rows)))  # fmt: skip
        return PathBatch(paths, coords, prim < 0, self._walk(paths, 1, state))

    def resume(
        self, paths: np.ndarray, depth: int, prim: np.ndarray, local: np.ndarray,
        points: np.ndarray, previous: np.ndarray,
    ) -> list[Vertices]:  # fmt: skip
        """The records of depths ``depth``, ``depth + 1``, ... of paths ``paths`` (n,) that
        are at ``points`` (n, 3) on primitives ``prim`` (n,) (coordinates ``local`` (n, 3)),
        reached from ``previous`` (n, 3) as ``AREA`` vertices: the continuation of a path
        from a given point (``render.path.boundary.secondary``). The first record's ``emit_weight``
        is MIS against a direction density of 1 per steradian: the caller sets its own."""
        n = len(paths)
        state = _State(np.arange(n), prim, local, points, unit(points - previous),
                       np.full(n, AREA, np.int8), np.ones(n), previous, np.ones(n))  # fmt: skip
        return self._walk(paths, depth, state)

    def _walk(self, paths, depth: int, state: _State) -> list[Vertices]:
        """The records of ``state``'s paths from ``depth`` until they all stop."""
        vertices = []
        for k in range(depth, self.max_depth + 1):
            record, state = self._vertex(paths, k, state)
            vertices.append(record)
            if state is None:
                break
        return vertices

    # --- one depth ------------------------------------------------------------------------

    def _vertex(self, paths, depth: int, s: _State):
        """Everything that happens at the paths' ``depth``-th vertex: a ``Vertices`` record
        and the state at the next vertex (None when no path goes on). The continuous work
        is one compiled call (``render.path.sample.choices``); here are the random numbers, the
        emitter picked, and the rays."""
        n = len(s.rows)
        if n == 0:
            return Vertices.none(len(self.scene.lights)), None
        ids = paths[s.rows]
        last = depth == self.max_depth
        has_emitters = len(self.emitters) > 0
        obj = self.tables.owner[s.prim]
        material = (self.lobes.probability[obj], self.lobes.shininess[obj],
                    self.lobes.reflectance[obj])  # fmt: skip
        nee = numbers = None
        if has_emitters:
            pick = np.zeros(n, np.int64)
            if not last:
                pick = self.emitters.pick(
                    uniform(self.seed, ids, bounce_dimension(depth, "emitter"))
                )
            prims = self.emitters.prims[pick]
            nee = (prims, self.emitters.probability[pick], self.emitters.area[pick],
                   prims != s.prim, self.emitters.pdf_area(s.prim))  # fmt: skip
        if not last:
            e = bounce_dimension(depth, "emitter_point")
            d = bounce_dimension(depth, "direction")
            numbers = tuple(
                uniform(self.seed, ids, dim)
                for dim in (e, e + 1, d, d + 1, bounce_dimension(depth, "lobe"),
                            bounce_dimension(depth, "roulette"))
            )  # fmt: skip
        path = (s.points, s.incoming, s.form == AREA, s.pdf, s.previous, s.throughput)
        offset = shadow_offset(s.points, self.size)
        form = (has_emitters, last, depth >= self.rr_depth)
        c = vertex_choices(
            self.tables, (s.prim, s.local), path, material, nee, numbers, offset, form
        )
        record = Vertices(
            s.rows, s.prim, s.local, s.form, c.emit_weight,
            np.full(n, -1, np.int64), np.zeros((n, 3)), np.zeros(n),
            np.zeros((len(self.scene.lights), n), bool), np.full(n, STOP, np.int8),
            np.ones(n), np.ones(n), np.zeros(n, bool), np.zeros((n, 3)),
        )  # fmt: skip
        if last:
            return record, None
        if has_emitters:
            self._next_event(record, s, nee[0], c)
        self._lights(record, s, c.ng)
        return record, self._continue(record, s, c)

    def _next_event(self, record, s: _State, prims: np.ndarray, c) -> None:
        """NEE's shadow rays: the point drawn on an area light is seen, or its weight is 0."""
        ignore = np.where(s.prim < self.n_triangles, s.prim, -1)
        blocked = self.accelerator.occluded(
            c.origin, c.nee_point - c.origin, 1.0 - 1e-7, tmin=0.0, ignore_prim=ignore
        )
        visible = c.nee_ok & ~blocked
        record.nee_prim[:] = np.where(visible, prims, -1)
        record.nee_local[:] = c.nee_local
        record.nee_weight[:] = np.where(visible, c.nee_weight, 0.0)

    def _lights(self, record, s: _State, ng: np.ndarray) -> None:
        """Which of the scene's lights reach each vertex (from its front side)."""
        for j, light in enumerate(self.scene.lights):
            towards = np.broadcast_to(light.towards(s.points), ng.shape)
            rays = shadow_rays(light, s.points, s.prim, self.n_triangles, self.size)
            blocked = self.accelerator.occluded(
                rays.origins, rays.directions, rays.tmax, tmin=0.0, ignore_prim=rays.ignore_prim
            )
            record.lit[j] = ~blocked & (dot(ng, towards) > 0)

    def _continue(self, record, s: _State, c):
        """Trace the continuation rays of the paths that go on: the next state."""
        prim, t, u, v = self.accelerator.closest_hit(c.origin, c.wi)
        record.next[:] = np.where(c.go, np.where(c.mirror, MIRROR, AREA), STOP)
        record.next_pdf[:] = np.where(c.go, c.pdf, 1.0)
        record.survive[:] = c.survive
        record.escape[:] = c.go & (prim < 0)
        record.escape_dir = c.wi  # the compiled call's own array: nothing else writes it
        on = np.flatnonzero(c.go & (prim >= 0))
        if len(on) == 0:
            return None

        def kept(values):  # the rows of the paths that go on (np.take: see Vertices.take)
            return np.take(values, on, axis=0)

        hit, wi = kept(prim), kept(c.wi)
        points = kept(c.origin) + kept(t)[:, None] * wi
        return _State(
            kept(s.rows), hit, self.local_coordinates(hit, points, kept(u), kept(v)), points,
            wi, np.where(kept(c.mirror), MIRROR, AREA).astype(np.int8), kept(c.pdf),
            kept(s.points), kept(c.throughput),
        )  # fmt: skip

    # --- plain geometry --------------------------------------------------------------------

    def local_coordinates(self, prim, points, u, v) -> np.ndarray:
        """(k, 3) coordinates of hit points on their primitives (``Vertices.local``)."""
        local = np.zeros((len(prim), 3))
        on_tri = prim < self.n_triangles
        local[:, 0], local[:, 1] = np.where(on_tri, u, 0.0), np.where(on_tri, v, 0.0)
        on_sphere = np.flatnonzero(~on_tri)
        if len(on_sphere):
            at = np.take(points, on_sphere, axis=0)
            local[on_sphere] = geometric_normals(self.primitives, prim[on_sphere], at)
        return local

    def _barycentric(self, prim, points) -> tuple[np.ndarray, np.ndarray]:
        """(u, v) (k,) each: the barycentrics of ``points`` (k, 3) in the planes of their
        triangles ``prim`` (k,) (anything for spheres' rows: ``local_coordinates`` ignores
        them)."""
        u, v = np.zeros(len(prim)), np.zeros(len(prim))
        on_tri = np.flatnonzero(prim < self.n_triangles)
        tri = self.primitives[0][prim[on_tri]]
        e1, e2, p = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], points[on_tri] - tri[:, 0]
        d11, d12, d22 = dot(e1, e1), dot(e1, e2), dot(e2, e2)
        p1, p2 = dot(p, e1), dot(p, e2)
        det = d11 * d22 - d12 * d12
        det = np.where(det != 0, det, 1.0)
        u[on_tri], v[on_tri] = (d22 * p1 - d12 * p2) / det, (d11 * p2 - d12 * p1) / det
        return u, v


@dataclass
class _State:
    """The paths at their current vertex (k of them): rows into the batch, primitive,
    local coordinates, point (k, 3), the unit direction they arrived along (k, 3), the
    form, the density of the direction that led here (``AREA``; per steradian), the
    previous vertex (k, 3) and Russian roulette's throughput estimate (k,)."""

    rows: np.ndarray
    prim: np.ndarray
    local: np.ndarray
    points: np.ndarray
    incoming: np.ndarray
    form: np.ndarray
    pdf: np.ndarray
    previous: np.ndarray
    throughput: np.ndarray


def check_path_options(spp, max_depth, rr_depth) -> tuple[int, int, int]:
    """spp >= 1, max_depth and rr_depth in [1, MAX_DEPTH], as ints, or a clear error."""
    spp = check_count("spp", spp)
    max_depth, rr_depth = check_count("max_depth", max_depth), check_count("rr_depth", rr_depth)
    # The kernel counts depths in int64 and draws bounce k's random numbers from dimension
    # 2 + 8 (k - 1) + j: beyond MAX_DEPTH they would wrap around.
    why = {
        "max_depth": "deeper bounces would have no random numbers of their own",
        "rr_depth": "to turn Russian roulette off, any rr_depth above max_depth will do",
    }
    for name, value in (("max_depth", max_depth), ("rr_depth", rr_depth)):
        if value > MAX_DEPTH:
            raise ValueError(
                f"render: {name} must be an integer in [1, 2**59], got {value!r} ({why[name]})"
            )
    return spp, max_depth, rr_depth


def check_count(name: str, value) -> int:
    """``value`` as an int if it is an integer >= 1, else a ValueError naming ``name``."""
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
        raise ValueError(f"render: {name} must be an integer >= 1, got {value!r}")
    return int(value)
