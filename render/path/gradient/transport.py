"""The radiance that sampled paths carry, on the tape.

``render.path.sample.tracer`` decided where every path goes; here each vertex is recomputed from
the scene's parameters and the path's contribution is written as one product per vertex,
so that a ``backward`` reaches every parameter the radiance depends on: emission, albedo,
light positions, vertex positions, the camera.

**Which quantities move, and why the densities are constants.** An estimate is f(x) / p(x)
for a sample x drawn with density p. Its derivative must be the derivative of the integral
of f, which is the integral of df/dtheta *if* the samples are expressed in coordinates
that do not move with theta; then p is the density those coordinates were drawn with, a
constant. The coordinates used here:

* the camera ray's position in its pixel (the image-plane point is fixed; the ray moves with
  the camera, and its hit is recomputed by intersecting the recorded primitive, as in the
  direct renderer): ``CAMERA`` vertices; mirror bounces likewise (``MIRROR``);
* a vertex reached by a sampled direction is recorded by its *place on its primitive*
  (barycentrics, or a direction from a sphere's centre): ``AREA`` vertices move with the
  surface. The direction was drawn with density p_w per steradian; in area measure the
  same point has density p_w |cos theta'| / r^2 (theta' at the new vertex), a constant,
  and the integrand gains the geometry factor |cos theta'| / r^2 and the area element's
  stretch (twice the triangle's area, or r^2 on a sphere), both on the tape. Written as
  ``x / detach(x)`` (value 1), they leave the value f cos / p_w unchanged and add exactly
  the derivative of the change of measure;
* next-event estimation's point on an area light is likewise a fixed place on the light,
  density P(primitive) / area (area on the tape).

Emission reached by a sampled direction and the same emission reached by NEE are then in
the same coordinates (a place on the light), so their MIS weights (constants from the
sampler) sum to one for every theta: the derivative of an area light's position or shape
is complete without a boundary term at the light's outline. What is *not* included: the
boundary terms of visibility between vertices (shadows' and indirect occlusion's edges) and
of primary visibility (the jittered camera rays' silhouettes); see ``docs/path_tracing.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

import minidiff as md
from render.path.sample.records import PathBatch
from render.path.sample.tracer import AREA, MIRROR, STOP, PathSampler
from render.scene.camera import ray_directions
from render.shade.lighting import Appearance, appearance, brdf, light_contribution
from render.shade.surface import Surface, column, in_order, surface_at, toward_ray
from render.trace.primitives import primitive_ranges


@dataclass(kw_only=True)
class Vertex(Surface):
    """k path vertices on the tape, possibly on several objects: their ``Surface`` (points,
    unit ``geometric`` and ``shading`` normals, not yet facing the viewer; ``stretch`` (k,)
    the area element's scale, 1 at vertices found by rays), the unit direction back to the
    previous vertex ``wo`` (k, 3), and the material there (``look``: albedo, specular
    (k, 3), shininess (k,)), ``reflectance`` and ``emission`` (k, 3)."""

    wo: md.Tensor
    look: Appearance
    reflectance: md.Tensor
    emission: md.Tensor

    def take(self, rows: np.ndarray) -> Vertex:
        """The vertices ``rows``."""
        look = self.look
        return Vertex(
            points=self.points[rows], geometric=self.geometric[rows],
            shading=self.shading[rows], wo=self.wo[rows], stretch=self.stretch[rows],
            look=Appearance(look.albedo[rows], look.specular[rows], look.ambient,
                            look.shininess[rows], look.texel[rows]),
            reflectance=self.reflectance[rows], emission=self.emission[rows],
        )  # fmt: skip


def path_radiance(world, frame, sampler: PathSampler, batch: PathBatch) -> md.Tensor:
    """(N, 3) the radiance each path of ``batch`` carries to the camera, on the tape."""
    n_paths = len(batch.paths)
    dtype = np.result_type(*[t.dtype for t in world.parameters()])
    parts, rows_of = [], []
    missed = np.flatnonzero(batch.missed)
    if len(missed):  # camera rays that see the environment
        parts.append(md.broadcast_to(world.background, (len(missed), 3)))
        rows_of.append(missed)
    vertices = batch.vertices
    if vertices and len(vertices[0].rows):
        first = vertices[0]
        directions = ray_directions(frame, batch.coords[first.rows].astype(dtype))
        origins = md.broadcast_to(frame[3], (len(first.rows), 3))
        vertex = vertex_on_tape(
            world, sampler, first.prim, first.local, first.form, origins, directions
        )
        throughput = None
        for depth, record in enumerate(vertices):
            following = vertices[depth + 1] if depth + 1 < len(vertices) else None
            throughput, vertex = _at_vertex(
                world, sampler, record, following, vertex, throughput, parts, rows_of, dtype
            )
            if vertex is None:
                break
    if not parts:
        return md.tensor(np.zeros((n_paths, 3), dtype))
    values = md.concatenate(parts) if len(parts) > 1 else parts[0]
    return md.scatter_add(values, np.concatenate(rows_of), n_paths)


def _times(throughput, x):
    """throughput * x, where a throughput of None stands for 1."""
    return x if throughput is None else throughput * x


def _at_vertex(world, sampler, record, following, v: Vertex, throughput, parts, rows_of, dtype):
    """Add what the paths gain at one depth's vertices (emission, NEE, lights, the
    environment after a last bounce) to ``parts``; return the throughput (k', 3) and the
    ``Vertex`` of the paths that go on (None, None when none does)."""
    side = viewer_side(v).astype(dtype)
    ns = v.shading * side  # two-sided: the shading normal faces the viewer
    look = v.look
    diffuse = look.albedo * (1.0 / math.pi)
    specular = look.specular.is_differentiated() or bool(np.any(look.specular.data))
    view = v.wo if specular else None
    rows = record.rows

    # Emission seen at this vertex (from its front only), MIS-weighted.
    if v.emission.is_differentiated() or np.any(v.emission.data):
        weight = (side[:, 0] > 0) * record.emit_weight
        parts.append(_times(throughput, v.emission * column(md.tensor(weight.astype(dtype)))))
        rows_of.append(rows)
    # Point and directional lights (their shadow rays are the sampler's).
    for j, light in enumerate(world.lights):
        lit = record.lit[j].astype(dtype)
        if lit.any():
            parts.append(
                _times(throughput, light_contribution(v.points, ns, -v.wo, look, light, lit))
            )
            rows_of.append(rows)
    # Next-event estimation on the area lights.
    nee = np.flatnonzero(record.nee_weight > 0)
    if len(nee):
        light = vertex_on_tape(world, sampler, record.nee_prim[nee], record.nee_local[nee],
                               np.full(len(nee), AREA, np.int8), None, None)  # fmt: skip
        to = light.points - v.points[nee]
        d2 = md.dot(to, to)
        wi = to / column(md.sqrt(d2))
        cos_x = md.maximum(md.dot(ns[nee], wi), 0.0)
        cos_z = md.abs(md.dot(light.geometric, wi))
        f = brdf(ns[nee], None if view is None else view[nee], wi, diffuse[nee], v.take(nee).look)
        # The point's density P / area: the area (half the stretch on a triangle, 4 pi times
        # it on a sphere) is on the tape; P is in nee_weight.
        area = light.stretch * _area_factor(sampler, record.nee_prim[nee], dtype)
        scale = cos_x * cos_z / d2 * area * record.nee_weight[nee].astype(dtype)
        parts.append(
            _times(
                None if throughput is None else throughput[nee], f * column(scale) * light.emission
            )
        )
        rows_of.append(rows[nee])

    # How the paths go on: a factor per path for its next segment.
    go = record.next != STOP
    if not go.any():
        return None, None
    scale = 1.0 / (record.next_pdf * record.survive)  # constants
    mirror = record.next == MIRROR

    def bounce_weight(wi, at):
        """f cos / (p q) at vertices ``at`` for unit directions wi (diffuse or glossy)."""
        f = brdf(ns[at], None if view is None else view[at], wi, diffuse[at], v.take(at).look)
        cos = md.maximum(md.dot(ns[at], wi), 0.0)
        return f * column(cos * scale[at].astype(dtype))

    # Paths that leave the scene see the environment (no NEE for it: weight 1).
    for kind_mask, is_mirror in ((record.escape & ~mirror, False), (record.escape & mirror, True)):
        out = np.flatnonzero(kind_mask)
        if len(out) == 0:
            continue
        if is_mirror:
            factor = v.reflectance[out] * column(md.tensor(scale[out].astype(dtype)))
        else:
            factor = bounce_weight(md.tensor(record.escape_dir[out].astype(dtype)), out)
        sub = None if throughput is None else throughput[out]
        parts.append(_times(sub, factor) * world.background)
        rows_of.append(rows[out])

    if following is None or len(following.rows) == 0:
        return None, None
    at = np.searchsorted(rows, following.rows)  # the continuing paths among these
    is_mirror = following.form == MIRROR
    nxt = next_vertex(world, sampler, v, ns, at, following)
    factors, order = [], []
    area_rows = np.flatnonzero(~is_mirror)
    if len(area_rows):
        k = at[area_rows]
        to = nxt.points[area_rows] - v.points[k]
        d2 = md.dot(to, to)
        wi = to / column(md.sqrt(d2))
        geometry = md.abs(md.dot(nxt.geometric[area_rows], wi)) / d2 * nxt.stretch[area_rows]
        change = geometry / md.tensor(geometry.data)  # value 1: the change of measure
        factors.append(bounce_weight(wi, k) * column(change))
        order.append(area_rows)
    mirror_rows = np.flatnonzero(is_mirror)
    if len(mirror_rows):
        k = at[mirror_rows]
        factors.append(v.reflectance[k] * column(md.tensor(scale[k].astype(dtype))))
        order.append(mirror_rows)
    factor = in_order(factors, order)
    return _times(None if throughput is None else throughput[at], factor), nxt


def next_vertex(world, sampler: PathSampler, v: Vertex, ns, at: np.ndarray, record) -> Vertex:
    """The vertices of ``record`` (the next depth's ``Vertices``) reached from rows ``at``
    of ``v`` (their shading normals ``ns`` (k, 3), facing the viewer): ``AREA`` ones at
    their places, ``MIRROR`` ones where the reflected rays meet their primitives."""
    # A mirror bounce's ray moves with the surface and its normal; others need no ray.
    reflected = 2.0 * column(md.dot(v.wo[at], ns[at])) * ns[at] - v.wo[at]
    return vertex_on_tape(world, sampler, record.prim, record.local, record.form, v.points[at],
                          reflected)  # fmt: skip


def viewer_side(v: Vertex) -> np.ndarray:
    """(k, 1): +1 where the geometric normal of ``v`` faces the viewer (``wo``), else -1:
    surfaces are two-sided, and their normals are turned to face the viewer."""
    with md.no_grad():
        return toward_ray(v.geometric, -v.wo).data


def _area_factor(sampler: PathSampler, prims: np.ndarray, dtype) -> np.ndarray:
    """(k,) what turns ``Vertex.stretch`` into the primitive's area: 1/2 on a triangle
    (the stretch is |(b - a) x (c - a)|), 4 pi on a sphere (the stretch is r^2)."""
    return np.where(prims < sampler.n_triangles, 0.5, 4.0 * math.pi).astype(dtype)


def vertex_on_tape(world, sampler: PathSampler, prims, local, form, origins, directions) -> Vertex:
    """k path vertices recomputed on the tape from primitives ``prims`` (k,): ``AREA`` ones
    at their coordinates ``local`` (k, 3) on the primitive, the others where the rays
    (``origins``, ``directions``: (k, 3) tensors) meet it. ``wo`` points back along the
    ray, or to ``origins`` for ``AREA`` vertices (None: no previous vertex, NEE points)."""
    objects = object_of(sampler, prims)
    owners = [obj for obj, _, _ in primitive_ranges(world)]  # this render's tensors
    parts, order = [], []
    for o in np.unique(objects):
        obj = owners[o]
        for is_area in (True, False):
            rows = np.flatnonzero((objects == o) & ((form == AREA) == is_area))
            if len(rows) == 0:
                continue
            faces = prims[rows] - sampler.first[o]
            if is_area:
                found = surface_at(obj, faces, local=local[rows])
                previous = None if origins is None else origins[rows]
                wo = _back(found.points, previous)
                stretch = found.stretch
            else:  # the normal as n / |n|, like the AREA vertices' (``surface_at``)
                found = surface_at(obj, faces, origins[rows], directions[rows], divide=True)
                wo = -md.normalize(found.directions)
                stretch = md.tensor(np.ones(len(rows), found.points.dtype))
            geometry = {"points": found.points, "geometric": found.geometric,
                        "shading": found.shading, "wo": wo, "stretch": stretch}  # fmt: skip
            parts.append(geometry | _material(obj.material, found.uv, len(rows)))
            order.append(rows)
    fields = ("points", "geometric", "shading", "wo", "stretch", "albedo", "specular", "shininess",
              "reflectance", "emission")  # fmt: skip
    joined = {name: in_order([p[name] for p in parts], order) for name in fields}
    look = Appearance(joined["albedo"], joined["specular"], md.tensor(0.0), joined["shininess"],
                      np.full(len(prims), -1, np.int64))  # fmt: skip
    return Vertex(**{name: joined[name] for name in fields[:5]}, look=look,
                  reflectance=joined["reflectance"], emission=joined["emission"])  # fmt: skip


def object_of(sampler: PathSampler, prims: np.ndarray) -> np.ndarray:
    """(k,) the index (in ``sampler.objects``) of the object owning each primitive id."""
    return np.searchsorted(sampler.first, prims, side="right") - 1


def _material(material, uv, k: int) -> dict:
    """The material at k vertices as per-vertex tensors (k, 3) (shininess (k,))."""
    look = appearance(material, uv)
    return {
        "albedo": md.broadcast_to(look.albedo, (k, 3)),
        "specular": md.broadcast_to(look.specular, (k, 3)),
        "shininess": md.broadcast_to(look.shininess, (k,)),
        "reflectance": md.broadcast_to(material.reflectance, (k, 3)),
        "emission": md.broadcast_to(material.emission, (k, 3)),
    }


def _back(points, previous):
    """The unit direction (k, 3) from ``AREA`` vertices back to the ``previous`` vertex
    (zero for NEE points, which have none and need none)."""
    if previous is not None:
        return md.normalize(previous - points)
    return md.tensor(np.zeros(points.shape, points.dtype))
