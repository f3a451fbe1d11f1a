"""The curves whose outline can be seen from a point: the one place they are found.

Seen from a point (the apex: a point light, a path vertex) or from a direction (a distant
light), visibility jumps across the outlines of the occluders: a mesh edge whose faces
all lie on one side of the plane through the apex and the edge (a border edge always),
and the circle where the cone from the apex touches a sphere. Two parts of the renderer
ask for them: the direct renderer's shadow borders (``render.edges.boundary.
shadow_tracing``: the outlines seen from each light, followed by grazing rays) and the
path integrator's secondary visibility (``render.path.boundary.silhouettes``: an outline
seen from each path vertex, drawn at random). Both take the scene's candidate curves from
``Outlines.of`` and decide which are outlines from where they look with ``one_sided``, so
that a shadow border and a soft shadow's edge come from the same edges, chosen by the same
rules:

* Meshes that share an edge (a multi-material file read as one mesh per material, walls
  meeting at a corner), or meet at a T-junction (a vertex of one inside an open edge of
  the other: a fin tessellated otherwise than the plate it hangs from), are welded into
  one (``render.trace.seams.welded_groups``: ``shared_edges`` finds the first,
  ``t_junction_pairs`` the second; the group welded and its open edges cut at
  T-junctions by ``render.trace.topology``), so that such an
  edge has a face of each mesh and is an outline where both lie on one side of the plane
  through apex and edge, as in one mesh. Taken mesh by mesh, it is a border of each (an
  outline from everywhere, counted twice), or, at a T-junction, it rests on the other's
  face (and the rule below drops it: an L whose fin's top edge was split lost its
  corner). The rule is the faces' positions, not their winding: two coincident copies, or
  parts wound differently, still agree.
* Where more than two faces meet at an edge, the two that bound the others around it
  decide (``_outer_faces``), and an edge whose faces span more than a half turn never is
  one; nor is an edge between two faces of one plane.
* Edges that rest on another object's surface without being one of its edges (a box
  standing on the floor, a fin standing on a plate inside it) are left out. A ray from
  the apex that grazes such an edge meets that surface at the edge itself, unless it runs
  in the surface's plane: the curve where visibility changes behind the edge is the edge,
  whether the edge is convex (the box's: nothing shows between box and floor) or concave
  (the fin's: its two sides see the plate on their own sides), so its shadow has no border
  of its own on that surface. What this leaves out (by this argument, not measured) is
  the contact line's own motion along the surface: a box sliding on the floor covers floor
  in front of it that a point off the floor's plane saw. While the line stays in place on
  the surface (the light moving, the occluder's other edges), nothing is missed; for a box
  lifted off the floor, the derivative given is the one-sided one of pressing it in. An
  edge lying along another object's edge with no vertex of either inside the other (the
  same segment, its ends not welded: a gap wider than the welding's tolerance) is left
  out too, though it may be an outline: a case not handled.

Everything here is discrete (which curves, on plain float64 arrays, off the tape); the
edge functions the boundary terms differentiate are their modules' own.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from minidiff.threads import jit, job_count, kernel, run_jobs, share
from render.scene.scene import Mesh, Scene
from render.trace.grid import boxes_at_points, grown
from render.trace.seams import as_one_mesh, shared_edges, welded_groups
from render.trace.topology import EdgeTable, MeshEdges, mesh_edges, seam_distance
from render.trace.vec3 import cross, dot3, sub

#: A face whose plane passes within this angle of the apex is seen edge-on: not an outline.
GRAZING = 1e-9
#: A surface closer than this (a fraction of the scene's size) to an edge touches it.
CONTACT = 1e-5


@dataclass
class Outlines:
    """The curves that can be outlines, as plain world-space arrays: mesh edges (E of them)
    with their endpoints ``a``, ``b`` (E, 3), the third vertices ``c`` (E, 2, 3) of the
    faces on either side (a border edge: its one face twice), the owning object (E,) (an
    index into ``scene.meshes``, which are the scene's first objects: its first end's
    mesh) and the endpoints' vertex ids ``ends`` (E, 2) among every mesh's vertices, mesh
    after mesh in ``scene.meshes``' order (the part of an edge cut at a T-junction between
    two meshes ends at a vertex of the other; coincident vertices welded across the meshes that
    share edges: an edge two meshes share is one edge, its object the first of them; where
    more than two faces meet, the two that bound the others around the edge), the faces
    ``faces`` (E, 2) whose third corners ``c`` are (global primitive ids: a ray through the
    edge meets them nowhere else), and how far from the edge's ends their sides may lie,
    ``crack`` (E,) (0 where they share its ends; a seam welded across a crack,
    ``render.trace.topology.seam_reach``); and spheres (S): ``centre`` (S, 3), ``radius``
    (S,), object (S,) (an index into the scene's objects, meshes first). Left out: the
    edges the module docstring says never are outlines, or whose shadow has no border of
    its own."""

    a: np.ndarray
    b: np.ndarray
    c: np.ndarray
    edge_object: np.ndarray
    ends: np.ndarray
    faces: np.ndarray
    crack: np.ndarray
    centre: np.ndarray
    radius: np.ndarray
    sphere_object: np.ndarray

    @classmethod
    def of(cls, world: Scene, triangles: np.ndarray, size: float, tables=None) -> Outlines:
        """The candidate curves of ``world`` (world space, ``render.scene.placement``),
        whose triangles (T, 3, 3) are ``triangles`` (``render.trace.primitives.
        scene_primitives``) and whose size is ``size`` (``scene_size``). ``tables``: the
        meshes' ``mesh_edges`` per mesh index and their ``shared_edges``, where the caller
        has them; else computed here."""
        meshes = world.meshes
        topology, shared = tables if tables is not None else _tables(world)
        first = np.cumsum([0] + [m.num_faces for m in meshes])
        parts = [
            _group_edges(meshes, group, welded, triangles, first, size)
            for group, welded in welded_groups(meshes, topology, shared, first)
        ]
        spheres = world.spheres
        return cls(
            _rows([p[0] for p in parts], (0, 3)), _rows([p[1] for p in parts], (0, 3)),
            _rows([p[2] for p in parts], (0, 2, 3)),
            _rows([p[3] for p in parts], (0,)).astype(np.int64),
            _rows([p[4] for p in parts], (0, 2)).astype(np.int64),
            _rows([p[5] for p in parts], (0, 2)).astype(np.int64),
            _rows([p[6] for p in parts], (0,)),
            np.array([s.center.data for s in spheres], np.float64).reshape(-1, 3),
            np.array([float(s.radius.data) for s in spheres], np.float64),
            np.arange(len(meshes), len(meshes) + len(spheres), dtype=np.int64),
        )  # fmt: skip

    @property
    def n_edges(self) -> int:
        return len(self.a)


def one_sided(m: np.ndarray, base: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Which edges are outlines seen through the planes e(P) = m . (P - base) through each
    edge and the apex (``m``, ``base`` (..., E, 3) or broadcasting to it: for an apex p,
    m = (a - p) x (b - p) and base = p; for a light, its ``edge_plane``): those whose faces'
    third corners ``c`` (E, 2, 3) both lie on one side of the plane, neither within
    ``GRAZING`` of it; (..., E) bool, and the side they lie on (..., E) (+1 or -1)."""
    pc = c - base[..., None, :]  # (..., E, 2, 3)
    side = np.einsum("...ij,...j->...i", pc, m)
    size = np.linalg.norm(m, axis=-1)
    sure = np.abs(side) > GRAZING * size[..., None] * np.linalg.norm(pc, axis=-1)
    outline = sure.all(axis=-1) & (np.sign(side[..., 0]) == np.sign(side[..., 1]))
    return outline, np.sign(side[..., 0])


def _tables(world: Scene) -> tuple[list[MeshEdges], list | None]:
    """Each mesh's ``mesh_edges`` (cut at T-junctions within the meshes' ``seam_distance``)
    and the edges meshes share (``shared_edges``)."""
    cut = seam_distance(as_one_mesh(world.meshes)[0]) if world.meshes else None
    topology = [mesh_edges(*as_one_mesh([mesh]), cut=cut) for mesh in world.meshes]
    return topology, shared_edges(world, topology)


def _group_edges(meshes: list[Mesh], group: list[int], edges: MeshEdges, triangles, first, size):
    """The edge arrays (a, b, c, object, ends, faces, crack: ``Outlines``) of the meshes ``group``
    (indices) welded as one, with ``edges`` their ``MeshEdges``: every welded edge but the
    flat ones and those that rest on another object's surface (``_touching``)."""
    members = [meshes[o] for o in group]
    vertices, faces = as_one_mesh(members)
    table = edges.table
    pick, fenced = _outer_faces(vertices, table)
    both = np.take_along_axis(table.faces, pick, axis=1)
    thirds = np.take_along_axis(table.thirds, pick, axis=1)
    tri = vertices[faces]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n1, n2 = normal[both[:, 0]], normal[both[:, 1]]
    flat = (
        (np.sum(table.faces >= 0, axis=1) >= 2)
        & (
            np.linalg.norm(np.cross(n1, n2), axis=1)
            <= 1e-9 * np.linalg.norm(n1, axis=1) * np.linalg.norm(n2, axis=1)
        )
        & (np.sum(n1 * n2, axis=1) > 0)
    )
    middle = 0.5 * (vertices[table.i] + vertices[table.j])
    keep = ~flat & ~fenced & ~_touching(middle, group, triangles, first, size)
    i, j = table.i[keep], table.j[keep]
    # The ends as ids among every mesh's vertices: a part of an edge cut at a T-junction
    # between two meshes ends at the other mesh's vertex.
    offsets = np.cumsum([0] + [len(m.vertices.data) for m in members])
    start = np.cumsum([0] + [len(m.vertices.data) for m in meshes])[np.asarray(group)]
    member = np.searchsorted(offsets, np.stack([i, j], axis=1), side="right") - 1
    ends = start[member] + np.stack([i, j], axis=1) - offsets[member]
    c = np.stack([vertices[thirds[keep, 0]], vertices[thirds[keep, 1]]], axis=1)
    face_ids = np.concatenate([np.arange(first[k], first[k + 1]) for k in group])
    owner = np.asarray(group, np.int64)[member[:, 0]]
    crack = _crack(vertices[i], vertices[j], vertices[faces[both[keep]]])
    return vertices[i], vertices[j], c, owner, ends, face_ids[both[keep]], crack


def _crack(a: np.ndarray, b: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """(E,): the largest distance from an edge's ends ``a``, ``b`` (E, 3) to the sides of
    its faces (``corners`` (E, 2, 3, 3)): 0 where both faces have the edge (a T-junction's
    part lies on the long edge's side), the width of the crack where meshes welded across
    one come apart (``render.trace.topology.seam_reach``)."""
    start, end = corners, np.roll(corners, -1, axis=2)  # (E, 2, 3, 3): each face's sides
    side = end - start
    length2 = np.maximum(np.sum(side * side, axis=-1), np.finfo(float).tiny)
    worst = np.zeros(len(a))
    for p in (a, b):
        off = p[:, None, None] - start
        t = np.clip(np.sum(off * side, axis=-1) / length2, 0.0, 1.0)
        gap = np.linalg.norm(off - t[..., None] * side, axis=-1)  # (E, 2, 3)
        worst = np.maximum(worst, gap.min(axis=2).max(axis=1))
    return worst


def _outer_faces(vertices: np.ndarray, table: EdgeTable) -> tuple[np.ndarray, np.ndarray]:
    """Which two of each edge's faces (columns of ``table.faces``, (E, 2); a border edge:
    its one face twice) decide whether it is an outline, and which edges never are (E,)
    bool. An edge is an outline where all its faces lie on one side of the plane through
    apex and edge. With two faces, those; where more meet (a fin standing on a plate's
    edge between two of the plate's faces, a box on a floor whose grid runs along its
    bottom edges), the faces' half-planes around the edge lie on one side of such a plane
    only if they fit in a half turn: then the two that bound them decide it; if not (the
    largest angle between neighbours around the edge is at most a half turn), it never
    is one."""
    count = np.sum(table.faces >= 0, axis=1)
    pick = np.where(count[:, None] >= 2, [[0, 1]], [[0, 0]])
    fenced = np.zeros(len(count), bool)
    for row in np.flatnonzero(count > 2):  # few: non-manifold edges
        a, b = vertices[table.i[row]], vertices[table.j[row]]
        axis = (b - a) / np.linalg.norm(b - a)
        w = vertices[table.thirds[row, : count[row]]] - a
        w -= np.outer(w @ axis, axis)  # each face's direction away from the edge
        angle = np.arctan2(np.cross(w[0], w) @ axis, w @ w[0])
        order = np.argsort(angle)
        gaps = np.diff(np.r_[angle[order], angle[order[0]] + 2 * np.pi])
        widest = int(np.argmax(gaps))
        fenced[row] = gaps[widest] <= np.pi * (1 + 1e-9)
        pick[row] = order[(widest + 1) % len(order)], order[widest]
    return pick, fenced


def _touching(points: np.ndarray, owners: list[int], triangles, first, size) -> np.ndarray:
    """(k,) bool: which ``points`` (k, 3) of the meshes ``owners`` lie on a triangle of
    another object (within ``CONTACT`` of the scene's ``size``: ``on_triangle``);
    ``triangles`` (T, 3, 3): every mesh's, ``first`` (M + 1,): each mesh's first row
    there. Few pairs of points and triangles (a teapot's edges against a floor's two
    triangles) are tested pair by pair in NumPy (``on_triangles``); more, each point
    against the triangles whose box, grown by the tolerance, overlaps its cell of a grid
    (``_cells``), and against the few triangles too large for the grid (``_touch``): the
    same answers, at a cost that grows with the points and the triangles, not their
    product (two meshes of 20k triangles: 1.7 s tested pairwise)."""
    other = np.ones(len(triangles), bool)
    for owner in owners:
        other[first[owner] : first[owner + 1]] = False
    triangles = np.ascontiguousarray(triangles[other], np.float64)
    tolerance = CONTACT * size
    points = np.ascontiguousarray(points, np.float64)
    if len(points) * len(triangles) <= _FEW_PAIRS:
        return on_triangles(points, triangles, tolerance)
    starts, stops, order, large = _cells(points, triangles, tolerance)
    out = np.zeros(len(points), bool)
    run_jobs(_touch, job_count(len(points), 256), points, triangles, starts, stops, order,
             large, tolerance, out)  # fmt: skip
    return out


#: Points and triangles this few in pairs are tested pair by pair: the grid costs more
#: (and its kernel seconds of a cold start).
_FEW_PAIRS = 1 << 18


def on_triangles(points: np.ndarray, triangles: np.ndarray, tolerance: float) -> np.ndarray:
    """(k,) bool: whether each of ``points`` (k, 3) is ``on_triangle`` of some triangle
    of ``triangles`` (T, 3, 3), every pair tested (the same arithmetic, in NumPy), 4,096
    points at a time. A sliver's det may be 0, or its margin and barycentrics not finite:
    comparisons with NaN are False, as in the kernel, and a zero area leaves it out."""
    out = np.zeros(len(points), bool)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        v0 = triangles[:, 0]
        e1, e2 = triangles[:, 1] - v0, triangles[:, 2] - v0
        normal = np.cross(e1, e2)
        area = np.sqrt(np.sum(normal * normal, axis=1))
        d11, d12, d22 = (np.sum(x * y, axis=1) for x, y in ((e1, e1), (e1, e2), (e2, e2)))
        det = d11 * d22 - d12 * d12
        margin = tolerance * np.sqrt(d11) / area + tolerance * np.sqrt(d22) / area
        for lo in range(0, len(points), 4096):
            d = points[lo : lo + 4096, None] - v0[None]  # (n, T, 3)
            near = np.abs(np.sum(d * normal, axis=2)) <= tolerance * area
            p1, p2 = np.sum(d * e1, axis=2), np.sum(d * e2, axis=2)
            u, v = (d22 * p1 - d12 * p2) / det, (d11 * p2 - d12 * p1) / det
            inside = (u >= -margin) & (v >= -margin) & (u + v <= 1 + margin)
            out[lo : lo + 4096] = np.any((area > 0) & near & inside, axis=1)
    return out


def _cells(points, triangles, tolerance):
    """The candidates of each point (k,) for ``_touch``: ``order[starts[i]:stops[i]]``,
    the triangles whose box (around all that ``on_triangle`` accepts for them) overlaps
    point i's cell of a uniform grid, and ``large``, those too large for it, for every
    point (``render.trace.grid``). A triangle that accepts a point has the point in its
    box, hence is among its candidates."""
    # What ``on_triangle`` accepts: within the tolerance of the plane, and barycentrics
    # u, v >= -m, u + v <= 1 + m (m in units of the triangle's sides): the triangle with
    # corners (u, v) = (-m, -m), (1 + 2m, -m), (-m, 1 + 2m), then the tolerance off it.
    v0, e1, e2 = (
        triangles[:, 0],
        triangles[:, 1] - triangles[:, 0],
        triangles[:, 2] - triangles[:, 0],
    )
    area = np.linalg.norm(np.cross(e1, e2), axis=1)
    sides = np.linalg.norm(e1, axis=1) + np.linalg.norm(e2, axis=1)
    m = np.where(area > 0, tolerance * sides / np.where(area > 0, area, 1.0), 0.0)[:, None]
    region = np.stack([v0 - m * (e1 + e2), v0 + (1 + 2 * m) * e1 - m * e2,
                       v0 - m * e1 + (1 + 2 * m) * e2], axis=1)  # fmt: skip
    lo, hi = grown(region.min(axis=1), region.max(axis=1), tolerance)
    return boxes_at_points(points, lo, hi)


@jit(cache=True, inline="always")
def _norm(a):
    return np.sqrt(dot3(a, a))


@jit(cache=True, inline="always")
def on_triangle(p, triangles, f, tolerance):
    """Point p (a 3-tuple) within ``tolerance`` of triangle ``f`` of ``triangles`` (T, 3, 3):
    of its plane, and inside it with a margin of ``tolerance`` along its sides."""
    v0 = (triangles[f, 0, 0], triangles[f, 0, 1], triangles[f, 0, 2])
    e1 = sub(triangles[f, 1], v0)
    e2 = sub(triangles[f, 2], v0)
    normal = cross(e1, e2)
    area = _norm(normal)
    if area == 0:
        return False
    d = sub(p, v0)
    if abs(dot3(d, normal)) > tolerance * area:
        return False
    # Barycentrics of p's projection, with a margin of ``tolerance`` along the sides.
    d11, d12, d22 = dot3(e1, e1), dot3(e1, e2), dot3(e2, e2)
    p1, p2 = dot3(d, e1), dot3(d, e2)
    det = d11 * d22 - d12 * d12
    u, v = (d22 * p1 - d12 * p2) / det, (d11 * p2 - d12 * p1) / det
    margin = tolerance * _norm(e1) / area + tolerance * _norm(e2) / area
    return u >= -margin and v >= -margin and u + v <= 1 + margin


@kernel
def _touch(job, n_jobs, points, triangles, starts, stops, order, large, tolerance, out):
    """Job ``job`` of ``n_jobs`` (``minidiff.threads.run_jobs``), for its share of the
    points: out[i], point i is ``on_triangle`` of one of its candidates (``_cells``)."""
    first, stop = share(job, n_jobs, len(points))
    for i in range(first, stop):
        p = (points[i, 0], points[i, 1], points[i, 2])
        found = False
        for n in range(starts[i], stops[i]):
            if on_triangle(p, triangles, order[n], tolerance):
                found = True
                break
        if not found:
            for n in range(len(large)):
                if on_triangle(p, triangles, large[n], tolerance):
                    found = True
                    break
        out[i] = found


def _rows(parts: list[np.ndarray], empty: tuple) -> np.ndarray:
    return np.concatenate(parts) if parts else np.zeros(empty)
