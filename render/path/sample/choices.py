"""What a path does at a vertex, computed by one compiled function per depth.

``render.path.sample.tracer.PathSampler`` walks a batch of paths one depth at a time. At each
depth the discrete work stays where it is done best (the random numbers' hash, picking an
emitter from its table, the BVH's rays, the lights' own shadow rays); everything continuous
in between is ``vertex_choices``, written once on minidiff arrays with the formulas of
``render.path.sample.sampling`` and compiled by ``minidiff.compile`` into one fused loop over the
paths (no array between the steps, parallel, the same bits on any number of threads):

* the vertex's geometric and shading normals, turned to face the path (two-sided);
* the multiple importance sampling (MIS) weight of the emission seen there;
* next-event estimation: a uniform point on the emitter drawn outside, its direction and
  the MIS weight of that strategy (the shadow ray is traced afterwards);
* continuation: a lobe (diffuse, Blinn-Phong or mirror) chosen by a uniform number, a
  direction drawn from it, its density, Russian roulette.

The scene is read as the path integrator's tables (``render.path.sample.tables.Tables``): the
meshes' vertices, vertex normals and faces, the spheres' centres and radii, which objects
are smooth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import minidiff as md
from render.path.sample.sampling import (
    blinn_phong_lobe,
    blinn_phong_pdf,
    cosine_hemisphere,
    cosine_pdf,
    power_heuristic,
    sphere_direction,
    triangle_point,
)
from render.path.sample.tables import Tables
from render.shade.surface import column, divided_unit, face_normals

#: Russian roulette keeps a path with probability min(MAX_SURVIVAL, throughput estimate),
#: at least MIN_SURVIVAL.
MIN_SURVIVAL, MAX_SURVIVAL = 0.05, 0.95


def _pick(condition, a, b):
    """Rows of a where ``condition`` (k,), else of b: (k, 3) vectors."""
    return md.where(column(condition), a, b)


def geometric_normal(face, sphere, on_sphere, points, vertices, faces, centers):
    """``render.shade.surface.geometric_normals`` from the tables: a triangle's unit face
    normal, a sphere's unit outward normal at ``points``."""
    face_normal = face_normals(*_corners(vertices, faces, face))
    return divided_unit(_pick(on_sphere, points - centers[sphere], face_normal))


def _corners(table, faces, face):
    """The rows of ``table`` (V, 3) at the three corners of faces ``face`` (k,)."""
    corner = faces[face]
    return table[corner[:, 0]], table[corner[:, 1]], table[corner[:, 2]]


def _lobe_pdf(probability, shininess, ns, wo, wi):
    """(k,) the density per steradian of the diffuse-or-glossy choice at directions wi."""
    return probability[:, 0] * cosine_pdf(ns, wi) + probability[:, 1] * blinn_phong_pdf(
        ns, wo, wi, shininess
    )


@md.compile(shared=("vertices", "normals", "faces", "smooth", "centers", "radii", "offset"))
def _choices(here, path, material, nee, numbers, vertices, normals, faces, smooth, centers,
             radii, offset, form):  # fmt: skip
    """The choices of k paths at their vertex (module docstring), all (k, ...) float64.

    here: (face, sphere, on a sphere, object, local (k, 3)), the vertex's primitive and its
    coordinates on it (``Tables.role``); path: (point, incoming unit direction, reached by
    a sampled direction (bool), that direction's density, previous point, Russian
    roulette's throughput estimate); material: (lobe probabilities (k, 3), shininess, mean
    reflectance); nee: (the emitter's role as ``here``'s first three, its picking
    probability, its area, whether it is another primitive than the vertex's, NEE's area
    density at the vertex's own primitive); numbers: (emitter point u1, u2, direction u1,
    u2, lobe, roulette). Shared: the ``Tables``' meshes and spheres (at least one row
    each); offset (): how far above the surface the rays start. Static form: (whether the
    scene has emitters, whether this is the last vertex (only the normal and the emission
    weight), whether Russian roulette plays here).

    Returns (ng, emit_weight (with emitters), origin) at the last vertex; else also, with
    emitters, (nee_local, nee_point, nee_ok, nee_weight), then (wi, pdf, mirror, go,
    throughput, survive (with roulette)): flags as 0.0 / 1.0."""
    has_emitters, last, roulette = form
    face, sphere, on_sphere, obj, local = here
    points, incoming, by_area, pdf, previous, throughput = path
    ng = geometric_normal(face, sphere, on_sphere, points, vertices, faces, centers)
    u, v = column(local[:, 0]), column(local[:, 1])
    na, nb, nc = _corners(normals, faces, face)
    ns = _pick(smooth[obj] & ~on_sphere, divided_unit((1.0 - u - v) * na + u * nb + v * nc), ng)
    wo = -incoming
    side = column(md.where(md.dot(ng, wo) < 0, -1.0, 1.0))  # two-sided: face the viewer
    ng, ns = side * ng, side * ns
    outputs = (ng,)
    e_face, e_sphere, e_on_sphere, e_probability, e_area, e_other, p_here = nee

    # The emission seen here, if reached by a sampled direction: MIS against NEE's density
    # of the same point, both in area measure.
    if has_emitters:
        to = points - previous
        d2 = md.dot(to, to)
        cos = md.abs(md.dot(ng, to)) / md.sqrt(md.where(d2 > 0, d2, 1.0))
        p_bsdf = pdf * cos / md.where(d2 > 0, d2, 1.0)
        weight = md.where(p_here > 0, power_heuristic(p_bsdf, p_here), 1.0)
        outputs += (md.where(by_area, weight, 1.0),)
    outputs += (points + offset * ng,)  # where rays leaving the vertex start
    if last:
        return outputs
    probability, shininess, reflectance = material
    e_u1, e_u2, u1, u2, u_lobe, u_roulette = numbers

    if has_emitters:  # a uniform point on the picked emitter, and NEE's MIS weight
        uv = triangle_point(e_u1, e_u2)
        ball = sphere_direction(e_u1, e_u2)
        e_on = column(e_on_sphere)
        nee_local = md.where(e_on, ball, md.concatenate([uv, 0.0 * uv[:, :1]], axis=1))
        a, b, c = _corners(vertices, faces, e_face)
        on_triangle = a + uv[:, 0:1] * (b - a) + uv[:, 1:2] * (c - a)
        z = md.where(e_on, centers[e_sphere] + column(radii[e_sphere]) * ball, on_triangle)
        nz = geometric_normal(e_face, e_sphere, e_on_sphere, z, vertices, faces, centers)
        to = z - points
        d2 = md.dot(to, to)
        wi = to / column(md.sqrt(md.where(d2 > 0, d2, 1.0)))
        cos_z = -md.dot(nz, wi)
        ok = (probability[:, 0] + probability[:, 1] > 0) & (cos_z > 0) & (md.dot(ng, wi) > 0)
        ok = ok & (d2 > 0) & e_other
        p_nee = e_probability / e_area
        p_bsdf = _lobe_pdf(probability, shininess, ns, wo, wi) * cos_z / md.where(d2 > 0, d2, 1.0)
        weight = power_heuristic(p_nee, p_bsdf) / e_probability
        outputs += (nee_local, z, md.where(ok, 1.0, 0.0), weight)

    # Continuation: a lobe, a direction from it, its density, Russian roulette.
    glossy = (u_lobe >= probability[:, 0]) & (u_lobe < probability[:, 0] + probability[:, 1])
    mirror = u_lobe >= probability[:, 0] + probability[:, 1]
    wi = cosine_hemisphere(u1, u2, ns)
    wi = _pick(glossy, blinn_phong_lobe(u1, u2, ns, wo, shininess), wi)
    wi = _pick(mirror, 2.0 * column(md.dot(wo, ns)) * ns - wo, wi)
    pdf = md.where(mirror, probability[:, 2], _lobe_pdf(probability, shininess, ns, wo, wi))
    lobe_sum = probability[:, 0] + probability[:, 1] + probability[:, 2]
    go = (lobe_sum > 0) & (pdf > 0) & (md.dot(ng, wi) > 0)
    throughput = throughput * reflectance
    outputs += (divided_unit(wi), pdf, md.where(mirror, 1.0, 0.0))
    if roulette:
        survive = md.clip(throughput, MIN_SURVIVAL, MAX_SURVIVAL)
        go = go & (u_roulette < survive)
        return (*outputs, md.where(go, 1.0, 0.0), throughput, survive)
    return (*outputs, md.where(go, 1.0, 0.0), throughput)


@dataclass
class Choices:
    """``_choices``' outputs for k paths, as plain arrays: ng (k, 3) the facing geometric
    normal; emit_weight (k,); origin (k, 3) where rays leaving the vertex start; NEE:
    nee_local (k, 3), nee_point (k, 3), nee_ok (k,) bool (before its shadow ray),
    nee_weight (k,); continuation: wi (k, 3) unit, pdf (k,), mirror (k,) bool, go (k,) bool
    (before its ray), throughput (k,), survive (k,). Fields a vertex does not compute are
    None (NEE without emitters, continuation at the last vertex); emit_weight and survive
    are ones where they do not apply."""

    ng: np.ndarray
    emit_weight: np.ndarray
    origin: np.ndarray
    nee_local: np.ndarray | None = None
    nee_point: np.ndarray | None = None
    nee_ok: np.ndarray | None = None
    nee_weight: np.ndarray | None = None
    wi: np.ndarray | None = None
    pdf: np.ndarray | None = None
    mirror: np.ndarray | None = None
    go: np.ndarray | None = None
    throughput: np.ndarray | None = None
    survive: np.ndarray | None = None


def vertex_choices(tables: Tables, here, path, material, nee, numbers, offset: float,
                   form: tuple) -> Choices:  # fmt: skip
    """``_choices`` on plain arrays (its arguments, but ``here`` = (primitive ids (k,),
    local (k, 3)) and ``nee`` = (the emitters' primitive ids, picking probabilities,
    areas, whether each is another primitive than the vertex's, NEE's area density at the
    vertex's own primitive), or None without emitters; ``numbers`` None at the last
    vertex); ``tables`` plain (built under ``no_grad``)."""
    has_emitters, last, roulette = form
    prims, local = here
    n = len(prims)
    ones = np.ones(n)
    if nee is None:
        nee = (prims, ones, ones, np.zeros(n, bool), ones)
    e_prims, *rest = nee
    path = tuple(np.asarray(x, np.float64) if x.dtype.kind == "f" else x for x in path)
    here = padded_role(tables, prims, np.asarray(local, np.float64))
    data = [md.as_tensor(out).data for out in _choices(  # plain in, plain out (tape_only)
        here, path, material, (*padded_role(tables, e_prims)[:3], *rest),
        numbers if numbers is not None else (ones,) * 6, *padded_tables(tables),
        np.asarray(offset, np.float64), form,
    )]  # fmt: skip
    ng, emit_weight = data.pop(0), (data.pop(0) if has_emitters else ones)
    found = Choices(ng, emit_weight, data.pop(0))
    if last:
        return found
    if has_emitters:
        found.nee_local, found.nee_point = data.pop(0), data.pop(0)
        found.nee_ok, found.nee_weight = data.pop(0) > 0, data.pop(0)
    found.wi, found.pdf, found.mirror = data.pop(0), data.pop(0), data.pop(0) > 0
    found.go, found.throughput = data.pop(0) > 0, data.pop(0)
    found.survive = data.pop(0) if roulette else ones
    return found


def padded_role(tables: Tables, prims: np.ndarray, local: np.ndarray | None = None) -> tuple:
    """``Tables.role`` with a row 0 where the scene has no face or no sphere (``padded_tables``)."""
    face, sphere, on_sphere, obj, local = tables.role(prims, local)
    zero = np.zeros(len(prims), np.int64)
    return (zero if face is None else face, zero if sphere is None else sphere, on_sphere, obj,
            local)  # fmt: skip


def padded_tables(tables: Tables) -> tuple:
    """The tables ``_choices`` reads, plain, with one harmless row where the scene has no
    mesh or no sphere: (vertices, normals, faces, smooth, centres, radii)."""
    none = tables.faces is None
    vertices = np.zeros((1, 3)) if none else tables.vertices.data
    normals = np.zeros((1, 3)) if none else tables.normals.data
    faces = np.zeros((1, 3), np.int64) if none else tables.faces
    centers = np.zeros((1, 3)) if tables.centers is None else tables.centers.data
    radii = np.ones(1) if tables.radii is None else tables.radii.data
    floats = (np.asarray(x, np.float64) for x in (vertices, normals, centers, radii))
    vertices, normals, centers, radii = floats  # a float32 scene's, in double precision
    return vertices, normals, faces, tables.smooth, centers, radii
