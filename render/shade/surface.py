"""Geometry on the tape: where rays meet surfaces, and their normals, recomputed differentiably.

The BVH tells us *which* primitive each ray hits; that choice is discrete and is treated
as a constant. *Where* the ray hits it is a smooth function of the ray and the primitive,
so we recompute it here with minidiff: that is what carries gradients from a pixel back to
the camera (through the ray) and to the vertex positions (through the triangle). Using the
BVH's t and barycentrics as constants instead would silently zero those gradients.

One surface interaction serves both integrators: ``surface_at`` builds a ``Surface`` (points,
normals, UVs, and either the rays that found the points or the area element of points placed
on their primitive) for meshes and spheres; the direct renderer shades it
(``render.shade.hits``, ``render.shade.mirrors``), the path integrator's vertices are
Surfaces too (``render.path.gradient.transport.Vertex``). ``geometric_normals`` is the plain normal
the tracers decide with.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import minidiff as md
from render.scene.scene import Mesh, Sphere


def column(x) -> md.Tensor:
    """(k,) -> (k, 1), so that a per-hit scalar scales the three components of a vector."""
    return md.reshape(x, (-1, 1))


def intersect_edges(origin, direction, a, e1, e2, barycentrics: bool = True):
    """Moller-Trumbore for rays known to hit their triangles, on the tape.

    origin (3,) or (k, 3); direction (k, 3); the triangle as a corner a (k, 3) and two edges
    e1 = b - a, e2 = c - a (k, 3), which the caller needs anyway for the normal. Returns
    (t, u, v), each (k,): the hit is origin + t * direction = (1 - u - v) a + u b + v c.
    With ``barycentrics=False`` only t is computed (u and v are returned as None).

    Derivation in brief: solve origin + t d = a + u e1 + v e2 with Cramer's rule; the
    determinants are triple products, written as dot(., cross(., .)).
    """
    p = md.cross(direction, e2)
    inv_det = 1.0 / md.dot(e1, p)  # non-zero: the BVH only reports non-degenerate hits
    s = origin - a
    q = md.cross(s, e1)
    t = md.dot(e2, q) * inv_det
    if not barycentrics:
        return t, None, None
    u = md.dot(s, p) * inv_det
    v = md.dot(direction, q) * inv_det
    return t, u, v


def intersect_spheres(origin, direction, center, radius, far_root: np.ndarray):
    """Ray-sphere distance on the tape for rays known to hit (k rays).

    origin (3,) or (k, 3), direction (k, 3), center (k, 3), radius (k,). ``far_root`` (k,)
    bool picks the far root (rays starting inside the sphere), as the BVH did.
    Solves |o + t d - c|^2 = r^2: t = (-b -+ sqrt(b^2 - a c')) / a.
    """
    oc = origin - center
    a = md.dot(direction, direction)
    b = md.dot(oc, direction)
    c = md.dot(oc, oc) - radius * radius
    # At a grazing hit the discriminant is ~0 and sqrt's derivative blows up; clamping keeps
    # the value (it is ~0 anyway) and gives a finite gradient. The floor is relative to b^2
    # (the discriminant's scale), so that it means the same for a sphere of any size; it
    # is a constant (detach), and never below the smallest normal number.
    b2 = b * b
    floor = md.maximum(md.detach(b2) * 1e-16, np.asarray(np.finfo(b.dtype).tiny, b.dtype))
    root = md.sqrt(md.maximum(b2 - a * c, floor))
    one = np.asarray(1.0, a.dtype)
    sign = md.where(far_root, one, -one)
    return (-b + sign * root) / a


def face_normals(a, b, c):
    """Unnormalised geometric normals (b - a) x (c - a), (k, 3); length = twice the area."""
    return md.cross(b - a, c - a)


def vertex_normals(vertices, faces: np.ndarray):
    """(V, 3) unit area-weighted vertex normals, on the tape.

    Each face adds its unnormalised normal (length proportional to its area) to its three
    corners; the sums are normalised. Vertices used by no face get the zero vector.
    """
    corners = [vertices[faces[:, i]] for i in range(3)]
    n = face_normals(*corners)
    summed = md.scatter_add(md.concatenate([n, n, n]), faces.T.ravel(), vertices.shape[0])
    return md.normalize(summed)


def geometric_normals(primitives, prims: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Plain unit geometric normals (k, 3), ``points``' dtype, of primitives ``prims`` (k,)
    (global ids into ``render.trace.primitives.scene_primitives``' (triangles, centres,
    radii)) at ``points`` (k, 3) on them: a triangle's (b - a) x (c - a), a sphere's outward
    normal; not turned to face anything (zero for a degenerate triangle)."""
    triangles, centers, _ = primitives
    n_tri = len(triangles)
    normals = np.empty_like(points)
    on_tri = prims < n_tri
    normals[on_tri] = face_normals(*np.moveaxis(triangles[prims[on_tri]], 1, 0)).data
    on_sphere = ~on_tri
    normals[on_sphere] = points[on_sphere] - centers[prims[on_sphere] - n_tri]
    return divided_unit(normals).data


def divided_unit(v):
    """Rows of ``v`` (k, 3) divided by their length (zero rows stay zero), on minidiff or
    plain arrays: the unit vectors the tracers decide with (``md.normalize``, the tape's,
    multiplies by the inverse length instead, which rounds differently)."""
    length = md.norm(v)
    return v / column(md.where(length > 0, length, 1.0))


def toward_ray(normals, directions):
    """(k, 1) constant signs that flip normals to face the incoming ray (two-sided shading),
    in the normals' dtype.

    A normal facing away from the viewer has dot(n, d) > 0. The sign is a discrete choice
    (like visibility), so it is a constant on the tape (and in a compiled function a
    comparison, which carries no derivative).
    """
    one = np.asarray(1.0, normals.dtype)
    with md.no_grad():
        away = md.dot(normals, directions) > 0.0
    return column(md.where(away, -one, one))


# --------------------------------------------------------------------------------------
# Surfaces: the points where rays meet an object (or points placed on it), on the tape
# --------------------------------------------------------------------------------------


@dataclass(kw_only=True)
class Surface:
    """k points on the surface of one object, recomputed on the tape from the primitives
    they lie on (``surface_at``): what both integrators shade.

    points (k, 3); geometric (k, 3): unit geometric normals, as the primitive orients them
    (a triangle's (b - a) x (c - a), a sphere's outward normal); shading (k, 3): unit
    shading normals, oriented as ``geometric`` (a smooth mesh's interpolated vertex
    normals, else ``geometric`` itself); uv (k, 2): a textured mesh's interpolated UVs
    (else None).

    For points found by rays: directions (k, 3), the rays' directions; normals (k, 3), the
    shading normals turned to face the rays (two-sided shading: what the direct renderer
    shades with); front (k,) 1 where the ray meets the side the geometric normal points to
    (the side an emissive material emits from), else 0 (a constant). For points placed on their
    primitive (by coordinates on it): stretch (k,), the area element's scale, dA = stretch
    du dv on a triangle (|(b - a) x (c - a)|, twice its area) and dA = stretch dw on a
    sphere (r^2, w the unit direction from its centre). The others are None."""

    points: md.Tensor
    geometric: md.Tensor
    shading: md.Tensor
    uv: md.Tensor | None = None
    directions: md.Tensor | None = None
    normals: md.Tensor | None = None
    front: md.Tensor | None = None
    stretch: md.Tensor | None = None


@dataclass
class Hits:
    """k rays' hits on one object, ready to shade: the object (``obj``, at ``index`` in
    ``render.trace.primitives.primitive_ranges``), the hits' ``Surface`` on the tape, the
    global primitive ids ``prims`` (k,) int64, the camera ray each belongs to ``rays`` (k,)
    int64, where they stand among the rays of their batch ``rows`` (k,) int64, and per light
    ``lit[j]`` (k,) float: 1 where light j reaches the hit (a constant)."""

    obj: Mesh | Sphere
    index: int
    surface: Surface
    prims: np.ndarray
    rays: np.ndarray
    rows: np.ndarray
    lit: list[np.ndarray]


def in_order(parts: list[md.Tensor], order: list[np.ndarray]) -> md.Tensor:
    """The rows of ``parts`` (computed group by group) put back in the original order:
    part i holds the rows ``order[i]`` (together a permutation of 0..n-1)."""
    joined = parts[0] if len(parts) == 1 else md.concatenate(parts)
    rows = np.concatenate(order)
    inverse = np.empty_like(rows)  # row r of the result is row inverse[r] of ``joined``
    inverse[rows] = np.arange(len(rows))  # (argsort would give the same, in n log n)
    return joined[inverse]


def interpolate(weights, attribute, corners):
    """Barycentric interpolation of a per-vertex attribute (V, n) at k hits: (k, n).
    ``corners``: the vertex ids (k,) of the hit faces' three corners."""
    return sum(w * attribute[ids] for ids, w in zip(corners, weights, strict=True))


def surface_at(
    obj: Mesh | Sphere,
    prims: np.ndarray,
    origins=None,
    directions=None,
    *,
    local: np.ndarray | None = None,
    traced_from: np.ndarray | None = None,
    far_root=None,
    divide: bool = False,
) -> Surface:
    """The ``Surface`` of k points on one object, on the tape (or plain values under
    ``md.no_grad()``): where the rays ``origins`` (3,) or (k, 3) and ``directions`` (k, 3)
    (tensors: the camera's, or rays leaving another surface) meet the object's primitives
    ``prims`` (k,) (local ids: a mesh's faces; ignored on a sphere), or, given ``local``
    (k, 3) instead of rays, at those coordinates on them ((u, v, _) barycentrics of corners
    b and c on a triangle, the unit direction from a sphere's centre).

    traced_from (k, 3): where the tracer started the rays (plain; by default ``origins``'
    values): a ray that starts inside a sphere meets its far side (a reflected ray starting
    *on* the sphere passes the side it was traced from). far_root (k,) bool: which rays meet
    a sphere's far side, given rather than found from ``traced_from`` (a compiled function,
    where the rays' values are not known). divide: a triangle's unit normal
    as n / |n| rather than ``md.normalize``'s n * (1 / |n|) (the two differ in the last
    bit; the path integrator divides, sharing |n| with ``stretch``; points placed by
    ``local`` always do).
    """
    if isinstance(obj, Mesh):
        surface = _on_mesh(obj, prims, origins, directions, local, divide)
    else:
        surface = _on_sphere(obj, origins, directions, local, traced_from, far_root)
    if directions is not None:
        flip = toward_ray(surface.geometric, directions)
        surface.directions = directions
        surface.normals = surface.shading * flip
        surface.front = md.maximum(flip[:, 0], 0.0)  # 1 or 0, in the normals' dtype
    return surface


def face_corners(table, faces) -> list:
    """The vertex ids (k,) of corners a, b and c of faces ``faces`` (k,) of the face
    ``table`` (F, 3) (traced arrays in a compiled function: a gather)."""
    if isinstance(faces, np.ndarray):  # plain arrays: column by column, in reused memory
        return [md.kernels.gather_rows(table[:, i], faces) for i in range(3)]
    rows = table[faces]
    return [rows[:, i] for i in range(3)]


def _on_mesh(mesh: Mesh, faces: np.ndarray, origins, directions, local, divide) -> Surface:
    """``surface_at`` on a mesh's faces ``faces`` (k,) (local ids)."""
    corners = face_corners(mesh.faces, faces)
    a, b, c = (mesh.vertices[ids] for ids in corners)
    e1, e2 = b - a, c - a
    # Barycentrics are needed only to interpolate vertex normals or UVs.
    textured = bool(mesh.material.textures)
    interpolated = mesh.smooth or textured
    if local is None:
        t, u, v = intersect_edges(origins, directions, a, e1, e2, barycentrics=interpolated)
        points = origins + column(t) * directions
    else:
        if isinstance(local, np.ndarray):  # else already an array of the caller's
            local = md.tensor(local.astype(a.dtype))
        u, v = local[:, 0], local[:, 1]
        points = a + column(u) * e1 + column(v) * e2
    n = md.cross(e1, e2)
    stretch = None
    if local is None and not divide:
        geometric = md.normalize(n)
    else:
        length = md.sqrt(md.dot(n, n))
        geometric = n / column(length)
        stretch = None if local is None else length
    shading = geometric
    if interpolated:
        weights = (column(1.0 - u - v), column(u), column(v))  # of corners a, b, c
    if mesh.smooth:
        vn = mesh.normals if mesh.normals is not None else vertex_normals(mesh.vertices, mesh.faces)
        shading = md.normalize(interpolate(weights, vn, corners))
    uv = interpolate(weights, mesh.uvs, corners) if textured else None
    return Surface(points=points, geometric=geometric, shading=shading, uv=uv, stretch=stretch)


def _on_sphere(sphere: Sphere, origins, directions, local, traced_from, far_root) -> Surface:
    """``surface_at`` on a sphere: its ``center`` (3,) and ``radius`` (), or per point (k, 3)
    and (k,) (a compiled function's gathers from all spheres)."""
    if sphere.material.textures:
        raise ValueError("render: spheres carry no UVs, so their material cannot have a texture")
    if local is not None:
        w = md.tensor(local.astype(sphere.center.dtype)) if isinstance(local, np.ndarray) else local
        points = sphere.center + column(sphere.radius) * w
        stretch = sphere.radius * sphere.radius  # one per point: () -> (k,)
        if stretch.ndim == 0:
            stretch = md.broadcast_to(stretch, (len(local),))
        return Surface(points=points, geometric=w, shading=w, stretch=stretch)
    if far_root is None:
        starts = origins.data if traced_from is None else traced_from
        inside = np.linalg.norm(starts - sphere.center.data, axis=-1) < sphere.radius.data
        far_root = np.broadcast_to(inside, (directions.shape[0],))
    t = intersect_spheres(origins, directions, sphere.center, sphere.radius, far_root)
    points = origins + column(t) * directions
    normals = md.normalize(points - sphere.center)
    return Surface(points=points, geometric=normals, shading=normals)


def moves_surface(obj: Mesh | Sphere) -> list[md.Tensor]:
    """The object's own parameters that move its hit points, normals or UVs (the camera's
    move them too)."""
    if isinstance(obj, Sphere):
        return [obj.center, obj.radius]
    return [t for t in (obj.vertices, obj.normals, obj.uvs) if t is not None]
