"""Mesh edges: silhouettes, creases, open boundaries and seams, a curve kind.

An edge (v_i, v_j) seen from the eye C lies on the zero set of

    e(x) = d(x) . m,    m = (v_i - C) x (v_j - C)

(the plane through the eye and the edge), linear in the camera direction d(x): its image
is a straight segment (``MeshEdge.curves``: every edge of every mesh that can be a jump,
clipped to the eye's near plane). At each quadrature point the edge point is where the
camera ray meets the edge; the face seen just beside the edge on either side is the
nearest there of the faces on that side (``edge_sides_kernel``), shaded at the edge point;
a side without a face (a silhouette's outside) is what a ray just beyond the edge sees.
Both sides are shaded, shadows included, by the render's ``SideRadiance``
(``_side_factors``): for the direct renderer its batched BVH queries and the camera hits'
compiled shading, the formulas written once.

Inside a mesh, an open edge along which another face's vertex lies (a T-junction) is cut
there before (``render.trace.topology.cut_at_t_junctions``): its parts are rows with a
face on each side. Edges that lie on one curve without sharing vertices otherwise (a
T-junction between two meshes; a seam whose two sides were cut differently; a gap or
overlap narrower than COINCIDENT of the scene; two faces overlapping flat) would each
count the jump that the ray beyond the other sees: the one curve twice (the translation
gradient of a plane split at a T-junction was 4.74 against 2.79). Where the ray beyond
an open edge meets such a face, one of the two edges counts the curve
(``_counted_elsewhere``); edges that share their vertices are matched across meshes
before (``render.trace.seams``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from functools import partial

import numpy as np

import minidiff as md
from minidiff.either import cross_last, dot_last
from minidiff.threads import job_count, kernel, run_jobs, share_tasks
from render.edges.boundary.curves import NEAR, CurvePoints, Curves, OnCurves, View, directions_at
from render.edges.boundary.moving import camera_moves, meshes_move
from render.edges.boundary.occlusion import SHORT, hidden_points, seen_in
from render.edges.boundary.radiance import EPSILON
from render.scene.camera import camera_directions, clip_to_near, project
from render.scene.lights import Light
from render.scene.scene import Scene
from render.trace.intersect import BLOCK, n_blocks
from render.trace.seams import SharedEdges, as_one_mesh
from render.trace.topology import SEAM_SIZE, EdgeTable
from render.trace.vec3 import cross, dot3, sub
from render.trace.visibility import blocked_past


def edge_plane(a, b, eye):
    """m (k, 3) = (a - eye) x (b - eye) of edges (a, b) (k, 3) seen from ``eye``: the edge
    function is e = d . m. Arrays, or tensors on the tape."""
    return cross_last(a - eye, b - eye)


class MeshEdge:
    """The edges of the meshes ``meshes`` (a range of indices into ``scene.meshes``: one
    mesh, or meshes that meet at T-junctions taken as one, ``render.edges.terms``) as a
    curve kind (``render.edges.boundary.curves``): ``table`` their ``EdgeTable`` (vertex
    and face ids of the meshes' vertices and faces concatenated), ``first_prim`` the global
    id of their first face, ``shared`` the faces other meshes have on their edges
    (``render.trace.seams.SharedEdges``; None: no mesh shares an edge with another).
    Labels: rows of ``table``."""

    summed, taped = 0, 1

    def __init__(
        self, meshes: range, table: EdgeTable, first_prim: int, shared: SharedEdges | None
    ) -> None:
        self.meshes, self.table, self.first_prim, self.shared = meshes, table, first_prim, shared

    def vertices(self, scene: Scene) -> np.ndarray:
        """(V, 3) float64: the meshes' vertices, concatenated (the table's vertex ids)."""
        return as_one_mesh([scene.meshes[k] for k in self.meshes])[0]

    def moves(self, scene: Scene) -> bool:
        """The camera or the meshes' vertices differentiated (``CurveKind.moves``)."""
        return camera_moves(scene) or meshes_move(scene, self.meshes)

    def curves(self, view: View) -> Curves:
        """Every edge in front of the eye that can be a jump: ``continuous_creases`` are
        left out, and the rows another mesh counts (``SharedEdges.owned``)."""
        table, frame = self.table, view.frame
        camera = view.scene.camera
        meshes = [view.scene.meshes[k] for k in self.meshes]
        vertices, faces = as_one_mesh(meshes)
        a, b, keep = clip_to_near(vertices[table.i], vertices[table.j], frame, NEAR * view.size)
        # Smooth shading is continuous across a mesh's own vertex ids only; of meshes taken
        # together, one flat among them makes every edge a possible jump (none left out).
        smooth = all(m.smooth for m in meshes)
        continuous = continuous_creases(smooth, faces, vertices, table, frame[3],
                                        view.scene.lights)  # fmt: skip
        if self.shared is None:
            keep = keep & ~continuous
        else:  # a row that other meshes' faces join is no continuous crease of this one
            alone = ~np.any(self.shared.faces >= 0, axis=1)
            keep = keep & self.shared.owned & ~(continuous & alone)
        return Curves(
            project(a[keep], frame, camera.width, camera.height)[0],
            project(b[keep], frame, camera.width, camera.height)[0],
            np.flatnonzero(keep),
        )

    def points(self, view: View, on: OnCurves) -> CurvePoints:
        """The factors of the points (``_edge_factors``)."""
        factor = _edge_factors(view, self, on)
        return CurvePoints.nonzero(on, factor, on.coords)

    def edge_function(self, scene: Scene, frame, points: CurvePoints):
        """e = d . m on the tape (``edge_plane``)."""
        meshes = [scene.meshes[k].vertices for k in self.meshes]
        vertices = md.concatenate(meshes) if len(meshes) > 1 else meshes[0]
        i, j = self.table.i[points.label], self.table.j[points.label]
        m = edge_plane(vertices[i], vertices[j], frame[3])
        e = dot_last(directions_at(scene, frame, points.coords), m)
        return e, np.arange(len(points.pixel))


def continuous_creases(
    smooth: bool, faces: np.ndarray, vertices: np.ndarray, table: EdgeTable, eye: np.ndarray,
    lights: Sequence[Light] = (),
) -> np.ndarray:  # fmt: skip
    """(E,) bool: the edges of a smooth-shaded mesh (faces (F, 3), vertices (V, 3) float64;
    none where not ``smooth``) across which the image cannot jump, so that they need no
    quadrature points: manifold edges whose two faces share the edge's vertex ids, wind
    consistently (one i -> j, the other j -> i) and lie on either side of the plane through
    the eye and the edge (not a silhouette from this eye). Normals and UVs are per vertex
    id, so both faces interpolate the same values along the edge and their shading agrees
    there exactly; both face the eye alike, so neither is flipped alone. (Their f_+ - f_-
    was zero up to rounding: dropping them changes the term by rounding only, and saves
    the rays and shading of most points of a smooth mesh.) Nor a silhouette as seen from
    one of ``lights``: there one face shadows the other's side of the edge
    (``shadowed_sides``), which smooth normals can light while flat ones cannot."""
    if not smooth or table.faces.shape[1] < 2:
        return np.zeros(len(table.i), dtype=bool)
    second = faces[np.maximum(table.faces[:, 1], 0)]  # (E, 3) vertex ids
    following = np.roll(second, -1, axis=1)  # each corner's next corner
    reversed_edge = np.any((second == table.j[:, None]) & (following == table.i[:, None]), axis=1)
    rows = np.arange(len(table.i))
    m = edge_plane(vertices[table.i], vertices[table.j], eye)
    side = _third_sides(vertices, table, rows, m, eye)
    continuous = _two_faces(table, rows) & reversed_edge & (side[:, 0] * side[:, 1] < 0)
    for light in lights:
        continuous &= ~light_silhouettes(light, vertices, table, rows)
    return continuous


def light_silhouettes(light: Light, vertices: np.ndarray, table: EdgeTable, rows: np.ndarray
                      ) -> np.ndarray:  # fmt: skip
    """(k,) bool: which of the rows ``rows`` (k,) of ``table`` (vertices (V, 3)) have two
    faces both on one side of the plane the edge sweeps in ``light`` (``Light.edge_plane``):
    silhouettes as seen from the light."""
    m, base = light.edge_plane(vertices[table.i[rows]], vertices[table.j[rows]])
    side = _third_sides(vertices, table, rows, m, base)
    return _two_faces(table, rows) & (side[:, 0] * side[:, 1] > 0)


def _two_faces(table: EdgeTable, rows: np.ndarray) -> np.ndarray:
    """(k,) bool: which of the rows ``rows`` of ``table`` have exactly two faces."""
    if table.faces.shape[1] < 2:
        return np.zeros(len(rows), bool)
    faces = table.faces[rows]
    return (faces[:, 1] >= 0) & np.all(faces[:, 2:] < 0, axis=1)


def _third_sides(vertices, table: EdgeTable, rows: np.ndarray, m, base) -> np.ndarray:
    """(k, 2): m . (c - base) for the third vertex c of each of the first two faces of the
    rows ``rows`` of ``table``: on which side of the plane (m (k, 3), through ``base``
    (k, 3) or (3,)) through each edge they lie."""
    thirds = vertices[np.maximum(table.thirds[rows, :2], 0)]  # (k, 2, 3)
    return np.einsum("kfj,kj->kf", thirds - np.asarray(base)[..., None, :], m)


def shadowed_sides(
    lights: Sequence[Light], vertices: np.ndarray, table: EdgeTable, rows: np.ndarray,
    faces: np.ndarray,
) -> np.ndarray:  # fmt: skip
    """(k, 2, L) bool: whether the side of face ``faces[:, s]`` (k, 2) (local ids of the
    mesh's faces; -1: none) of an edge point on row ``rows`` (k,) of ``table`` lies in the
    shadow of the edge's other face for each light. On a light's silhouette edge
    (``light_silhouettes``) the face that lies behind the other's plane as seen from the
    light is shadowed by it right up to the edge: a ray to the light from a point of it
    near the edge crosses the other face (on a non-silhouette edge the crossing falls
    outside the other face). The edge point itself is no such point (every ray through it
    passes the edge's faces), so its side is shaded in this shadow, the limit from inside
    the face. Flat shading made this no matter: a face behind another from the light faces
    away from it and is dark anyway; smooth normals light it (the Blender teapot's spout,
    36 % off)."""
    out = np.zeros((len(rows), 2, len(lights)), bool)
    two = np.flatnonzero(_two_faces(table, rows))
    if len(two) == 0 or not lights:
        return out
    # What depends on the edge alone, once per edge (many points lie on each).
    named, at = np.unique(rows[two], return_inverse=True)
    faces = faces[two]
    a, b = vertices[table.i[named]], vertices[table.j[named]]
    third = vertices[table.thirds[named, :2]]  # (e, 2, 3): the two faces' third vertices
    normal = np.cross((b - a)[:, None], third - a[:, None])  # (e, 2, 3), either orientation
    # across[:, f]: how far the other face's third vertex lies off face f's plane.
    across = np.einsum("kfj,kfj->kf", normal, third[:, ::-1] - a[:, None])
    own = table.faces[named, :2][at]  # (k, 2): the edge's two faces at each point
    for j, light in enumerate(lights):
        silhouette = light_silhouettes(light, vertices, table, named)[at]
        lit_side = np.einsum("kfj,kj->kf", normal, np.broadcast_to(light.towards(a), a.shape))
        # behind[:, f]: the face other than f lies behind f's plane as the light sees it.
        behind = across * lit_side < 0
        for s in (0, 1):
            other = np.where(faces[:, s] == own[:, 0], 1, 0)  # the other face's column
            on_edge = (faces[:, s] == own[:, 0]) | (faces[:, s] == own[:, 1])
            out[two, s, j] = silhouette & on_edge & behind[at, other]
    return out


def edge_sides_kernel(
    eye, forward, right, up, vertices, i, j, own_faces, own_thirds, first_prim, shared_faces,
    shared_thirds, edges, coords, width, height,
):  # fmt: skip
    """``edge_sides`` of k points on the edges of an ``EdgeTable``: the same arithmetic, in
    scalars instead of a dozen (k, 3) temporaries.

    The table's rows: i, j (E,) the edges' vertex ids into ``vertices`` (V, 3); own_faces
    (E, K) the mesh's faces on each (local ids, -1 padding; global ids: plus
    ``first_prim``), own_thirds (E, K) their third vertices' ids; shared_faces (E, K2) the
    faces other meshes have on it (global ids) and shared_thirds (E, K2, 3) their third
    vertices' positions (K2 may be 0). The points: edges (k,) their rows, coords (k, 2)
    their image-plane points. Returns directions (k, 3), depth (k,), norm (k,), step
    (k, 2), chosen (k, 2) (``edge_sides``).

    What depends on the edge alone (its plane, |grad e|, the step, each face's side and
    normal) is computed once per edge the points lie on (``_per_edge``), then each point's
    own part (``_per_point``); both share their work out in jobs as the ray kernels share
    rays (``render.trace.intersect``: every result is the same on any number of threads).
    tests/render/edges/test_boundary.py ties it to its NumPy statement (``edge_sides``
    there)."""
    k = len(edges)
    # The edges the points lie on, each given a slot in the order the points first name it.
    named, first = np.unique(edges, return_index=True)
    rows = named[np.argsort(first)]
    slot = np.full(len(i), -1, np.int64)
    slot[rows] = np.arange(len(rows))
    n, n_faces = len(rows), own_faces.shape[1] + shared_faces.shape[1]
    u, w0, normal = np.empty((n, 3)), np.empty((n, 3)), np.empty((n, n_faces, 3))
    uu, uw, length = np.empty(n), np.empty(n), np.empty(n)
    step_e, ng = np.empty((n, 2)), np.empty((n, n_faces))
    face = np.full((n, n_faces), -1, np.int64)  # -1: none, or on neither side
    plus = np.zeros((n, n_faces), np.bool_)
    per_edge = (u, w0, normal, uu, uw, length, step_e, ng, face, plus)
    run_jobs(
        _per_edge, job_count(n, 1024), eye, right, up, vertices, i, j, own_faces, own_thirds,
        first_prim, shared_faces, shared_thirds, rows, width, height, *per_edge,
    )  # fmt: skip
    directions, depth, norm = np.empty((k, 3)), np.empty(k), np.empty(k)
    step, chosen = np.empty((k, 2)), np.full((k, 2), -1, np.int64)
    run_jobs(
        _per_point, job_count(k, 4096), forward, right, up, slot, edges, coords, *per_edge,
        directions, depth, norm, step, chosen,
    )  # fmt: skip
    return directions, depth, norm, step, chosen


@kernel
def _per_edge(
    job, n_jobs, eye, right, up, vertices, i, j, own_faces, own_thirds, first_prim,
    shared_faces, shared_thirds, rows, width, height, u, w0, normal, uu, uw, length, step_e,
    ng, face, plus,
):  # fmt: skip
    """Job ``job`` of ``n_jobs`` of ``edge_sides_kernel``'s first pass: per edge ``rows[e]``
    of its blocks, u = b - a, w0 = eye - a, their products, |grad e| in pixels, the step
    across the edge and each face's side and normal (``face`` -1, ``plus`` False on entry)."""
    n, n_own = rows.shape[0], own_faces.shape[1]
    n_faces = n_own + shared_faces.shape[1]
    sx, sy = 2.0 / width, -2.0 / height
    # 3-vectors as tuples (``render.trace.vec3``): no scratch arrays, no row views.
    o = (eye[0], eye[1], eye[2])
    r, w = (right[0], right[1], right[2]), (up[0], up[1], up[2])
    for block in range(job, n_blocks(n), n_jobs):
        for e in range(block * BLOCK, min(n, (block + 1) * BLOCK)):
            row = rows[e]
            a = (vertices[i[row], 0], vertices[i[row], 1], vertices[i[row], 2])
            b = (vertices[j[row], 0], vertices[j[row], 1], vertices[j[row], 2])
            ue, we = sub(b, a), sub(o, a)
            u[e, 0], u[e, 1], u[e, 2] = ue
            w0[e, 0], w0[e, 1], w0[e, 2] = we
            m = cross(sub(a, o), sub(b, o))
            uu[e], uw[e] = dot3(ue, ue), dot3(ue, we)
            # pixel_gradient of grad e = (m . right, m . up)
            gx, gy = dot3(m, r) * sx, dot3(m, w) * sy
            length[e] = math.sqrt(gx * gx + gy * gy)
            scale = length[e] if length[e] > 0 else 1.0
            step_e[e, 0], step_e[e, 1] = gx / scale * sx, gy / scale * sy
            towards = (step_e[e, 0] * r[0] + step_e[e, 1] * w[0],
                       step_e[e, 0] * r[1] + step_e[e, 1] * w[1],
                       step_e[e, 0] * r[2] + step_e[e, 1] * w[2])  # fmt: skip
            for f in range(n_faces):  # each face's side and normal
                if f < n_own:
                    if own_faces[row, f] < 0:
                        continue
                    k = own_thirds[row, f]
                    third = (vertices[k, 0], vertices[k, 1], vertices[k, 2])
                    global_id = own_faces[row, f] + first_prim
                else:
                    global_id = shared_faces[row, f - n_own]
                    if global_id < 0:
                        continue
                    third = (shared_thirds[row, f - n_own, 0], shared_thirds[row, f - n_own, 1],
                             shared_thirds[row, f - n_own, 2])  # fmt: skip
                side = (third[0] - o[0]) * m[0] + (third[1] - o[1]) * m[1]
                side = side + (third[2] - o[2]) * m[2]
                if side == 0 or side != side:
                    continue
                face[e, f], plus[e, f] = global_id, side > 0
                cut = cross(ue, sub(third, a))
                normal[e, f, 0], normal[e, f, 1], normal[e, f, 2] = cut
                ng[e, f] = dot3(cut, towards)


@kernel
def _per_point(
    job, n_jobs, forward, right, up, slot, edges, coords, u, w0, normal, uu, uw, length,
    step_e, ng, face, plus, directions, depth, norm, step, chosen,
):  # fmt: skip
    """Job ``job`` of ``n_jobs`` of ``edge_sides_kernel``'s second pass: each point's
    direction, depth, |grad e|, step and nearest face either side (``chosen`` -1 on
    entry)."""
    k, n_faces = edges.shape[0], face.shape[1]
    for block in range(job, n_blocks(k), n_jobs):
        for p in range(block * BLOCK, min(k, (block + 1) * BLOCK)):
            # Elements read one by one: row views of shared arrays would count
            # references, atomically, in every thread.
            e, x, y = slot[edges[p]], coords[p, 0], coords[p, 1]
            d0 = x * right[0] + y * up[0] + forward[0]
            d1 = x * right[1] + y * up[1] + forward[1]
            d2 = x * right[2] + y * up[2] + forward[2]
            directions[p, 0], directions[p, 1], directions[p, 2] = d0, d1, d2
            # _edge_points: the depth along d of the point nearest the line through a and b
            dd = d0 * d0 + d1 * d1 + d2 * d2
            du = d0 * u[e, 0] + d1 * u[e, 1] + d2 * u[e, 2]
            dw = d0 * w0[e, 0] + d1 * w0[e, 1] + d2 * w0[e, 2]
            det = dd * uu[e] - du * du
            depth[p] = (du * uw[e] - uu[e] * dw) / (det if det > 0 else 1.0)
            norm[p], step[p, 0], step[p, 1] = length[e], step_e[e, 0], step_e[e, 1]
            # the nearest face on either side (approach; ties go to the first, as np.argmax)
            best_plus, best_minus = -np.inf, -np.inf
            for f in range(n_faces):
                if face[e, f] < 0:
                    continue
                nd = normal[e, f, 0] * d0 + normal[e, f, 1] * d1 + normal[e, f, 2] * d2
                rate = ng[e, f] / nd if nd != 0 else ng[e, f] / np.inf
                if plus[e, f] and (chosen[p, 0] < 0 or rate > best_plus):
                    best_plus, chosen[p, 0] = rate, face[e, f]
                elif not plus[e, f] and (chosen[p, 1] < 0 or -rate > best_minus):
                    best_minus, chosen[p, 1] = -rate, face[e, f]


def _edge_factors(view: View, kind: MeshEdge, on: OnCurves) -> np.ndarray:
    """(g, 3): w (f_+ - f_-) / |grad e| for the quadrature points ``on`` the edges of
    ``kind``'s meshes (labels: rows of its table), zero where the edge point is hidden.

    The edge point is where the camera ray through the quadrature point meets the edge.
    It is visible if nothing lies in front of it (an any-hit ray that ends just short of
    it). Each face's third vertex tells on which side of the edge's image it lies. On each
    side, the face seen just beside the edge is the nearest there of the faces on that
    side (``approach``), shaded at the edge point as a camera hit on it would be; a side
    with no face (a silhouette's outside, an open boundary) is what a ray just beyond the
    edge sees. A crease has one face on each side, a silhouette both on one. The faces
    other meshes have on these edges (``kind.shared``) are candidates on either side as
    the mesh's own are. A point is hidden too by what lies in front of it closer than
    ``hidden_points`` looks (``_thin_occluder``), and an open edge's point is left to the
    edge of another face that draws the same curve (``_counted_elsewhere``). The sides
    are shaded by ``view.radiance`` (``_side_factors``)."""
    scene, table, first_prim, shared = view.scene, kind.table, kind.first_prim, kind.shared
    edges, coords, pixel, weight, keys = on.label, on.coords, on.pixel, on.weight, on.key
    camera = scene.camera
    forward, right, up, eye = view.frame
    vertices = kind.vertices(scene)
    shared_faces, shared_thirds = np.zeros((len(table.i), 0), np.int64), np.zeros((1, 0, 3))
    if shared is not None:
        shared_faces, shared_thirds = shared.faces, shared.thirds
    directions, depth, norm, step, chosen = edge_sides_kernel(
        eye, forward, right, up, vertices, table.i, table.j, table.faces, table.thirds,
        first_prim, shared_faces, np.asarray(shared_thirds, np.float64), edges,
        np.ascontiguousarray(coords), camera.width, camera.height,
    )  # fmt: skip
    ignore = table.faces[edges, 0] + first_prim
    hidden = hidden_points(
        view.occluders, view.frame, camera, coords, directions, depth, norm, ignore,
        seen_in(view.occluders, pixel, scene),
    )  # fmt: skip
    on_row = _faces_on(kind, shared_faces)  # (E, K) global ids, -1 padding
    seams = _seam_rows(kind, on_row, vertices, view.occluders.primitives[0])
    again = np.flatnonzero(hidden & (norm > 0) & (depth > 0) & seams[edges])
    if len(again):  # a face of the edge hides its point only across a seam's crack
        hidden[again] = blocked_past(
            view.occluders.accelerator(), np.broadcast_to(eye, (len(again), 3)),
            directions[again], depth[again] * (1.0 - SHORT), on_row[edges[again]],
        )  # fmt: skip
    seen = np.flatnonzero(~hidden)
    faces = on_row[edges[seen]]
    open_row = _open_rows(kind, shared_faces)
    occluder = _thin_occluder(view, directions[seen], depth[seen], faces)
    # An open edge just behind a face that draws the same curve is that curve: which of the
    # two counts it is ``_counted_elsewhere``'s choice, made as if neither hid the other.
    near = np.flatnonzero((occluder >= 0) & open_row[edges[seen]])
    points = eye + depth[seen[near], None] * directions[seen[near]]
    occluder[near[_coincident(view, kind, edges[seen[near]], points, occluder[near])]] = -1
    seen = seen[occluder < 0]
    step = _beyond_steps(view, open_row, edges, directions, depth, step, seen)
    mine = seen[open_row[edges[seen]]]  # only open boundaries can lie on another's edge
    elsewhere = _counted_elsewhere(view, kind, *(np.take(x, mine, axis=0) for x in (
        edges, coords, directions, depth, step, chosen)))  # fmt: skip
    seen = np.setdiff1d(seen, mine[elsewhere], assume_unique=True)
    coords, depth, step, chosen = (np.take(x, seen, axis=0) for x in (coords, depth, step, chosen))
    scale, keys = weight[seen] / norm[seen], keys[seen]
    out = np.zeros((len(hidden), 3))
    beside = np.where(seams[edges[seen], None], on_row[edges[seen]], -1)
    local = np.where(chosen >= 0, chosen - first_prim, -1)  # ids among the table's faces
    shadowed = shadowed_sides(scene.lights, vertices, table, edges[seen], local)
    out[seen] = _side_factors(view, coords, depth, step, chosen, keys, scale, beside, shadowed)
    return out


#: An edge point within this fraction of the scene's size of another face's plane, on an
#: edge of that face in line with its own (or on a face parallel to its own), lies on a
#: curve that face's edges draw too (module docstring: seams that do not share vertices).
#: A quarter of the distance within which meshes' seams are welded before
#: (``render.trace.topology.SEAM_SIZE``): a seam is either welded or beyond this test.
COINCIDENT = SEAM_SIZE / 4
#: The ray beyond an open boundary passes this fraction of the scene's size from the edge
#: (when nearer than ``EPSILON`` pixels): well inside ``COINCIDENT``, so a gap it crosses
#: is one that ``_counted_elsewhere`` sees as closed.
BEYOND = 1e-7
#: Something this fraction of the depth or more in front of an edge point hides it
#: (``hidden_points`` ends its rays 1e-6 short, for a whole render's occluders at once).
THIN = 1e-12


def _faces_on(kind: MeshEdge, shared_faces: np.ndarray) -> np.ndarray:
    """(E, K + K2) int64: the global ids of every face on each row of ``kind.table``, its
    mesh's then other meshes' (``shared_faces`` (E, K2)), -1 padding."""
    own = kind.table.faces
    return np.concatenate([np.where(own >= 0, own + kind.first_prim, -1), shared_faces], axis=1)


def _thin_occluder(view: View, directions, depth, faces) -> np.ndarray:
    """(n,) int64: for n edge points seen along camera directions (n, 3) at ``depth`` (n,),
    visible to ``hidden_points``, a primitive other than their edge's ``faces`` (n, K)
    that hides them after all, between THIN and 1e-6 of their depth in front of them (-1:
    none): the other side of a box thinner than a millionth of its distance (without this,
    its far edges showed through: a 1e-6 thick box translated gave 17.6 against 5.3)."""
    if len(depth) == 0:
        return np.zeros(0, np.int64)
    eye = view.frame[3]
    prim, _, _, _ = view.occluders.accelerator().closest_hit(
        np.broadcast_to(eye, directions.shape), directions, tmax=depth * (1.0 - THIN)
    )
    return np.where(np.any(faces == prim[:, None], axis=1), -1, prim)


def _seam_rows(kind: MeshEdge, on_row: np.ndarray, vertices, triangles) -> np.ndarray:
    """(E,) bool: the rows of ``kind.table`` whose faces may have come apart along them:
    those with a face (``on_row`` (E, K), global ids: ``_faces_on``; ``triangles`` (T, 3,
    3) every face's corners) whose corners are not both the row's ends (``vertices`` (V,
    3): the meshes', ``as_one_mesh``) at the same positions: meshes welded across a crack
    (within ``seam_distance``), or the long edge of a T-junction, whose vertex was rounded
    off its line. A ray through an edge point meets the planes of the edge's faces there
    only, but across such a crack it may meet another face of the edge: the visibility
    tests of these rows' points pass the row's faces (``blocked_past``)."""
    table = kind.table
    a, b = vertices[table.i][:, None], vertices[table.j][:, None]
    apart = np.zeros(len(table.i), bool)
    for column in on_row.T:
        corners = triangles[np.maximum(column, 0)]  # (E, 3, 3)
        ends = np.any(np.all(corners == a, axis=2), axis=1) & np.any(
            np.all(corners == b, axis=2), axis=1
        )
        apart |= (column >= 0) & ~ends
    return apart


def _open_rows(kind: MeshEdge, shared_faces: np.ndarray) -> np.ndarray:
    """(E,) bool: the rows of ``kind.table`` with one face in all (open boundaries)."""
    return np.sum(_faces_on(kind, shared_faces) >= 0, axis=1) == 1


def _beyond_steps(view: View, open_row, edges, directions, depth, step, seen) -> np.ndarray:
    """``step`` (k, 2), with the points ``seen`` (n,) on open rows (``open_row`` (E,) bool;
    ``edges`` (k,) the points' rows) shortened so that the ray ``EPSILON`` steps beyond
    the edge passes BEYOND times the scene's size from the edge point (directions (k, 3),
    depth (k,)), where ``EPSILON`` pixels would pass farther: a gap narrower than that
    between two meshes' edges is crossed, and the two edges seen as one curve."""
    right, up = view.frame[1], view.frame[2]
    rows = seen[open_row[edges[seen]]]
    moved = EPSILON * np.linalg.norm(step[rows, :1] * right + step[rows, 1:] * up, axis=1)
    world = np.abs(depth[rows]) * moved  # how far the beyond ray passes from the point
    out = step.copy()
    factor = np.minimum(1.0, BEYOND * view.size / np.maximum(world, 1e-300))
    out[rows] = step[rows] * factor[:, None]
    return out


def _counted_elsewhere(view: View, kind: MeshEdge, rows, coords, directions, depth, step,
                       chosen) -> np.ndarray:  # fmt: skip
    """(n,) bool: which of n visible points on open boundary rows of ``kind.table`` (rows
    (n,), image-plane coords (n, 2), camera directions (n, 3), depth (n,), ``step`` (n, 2)
    and ``chosen`` (n, 2) of ``edge_sides_kernel``) another edge counts instead.

    The ray just beyond the edge meets a face q that is ``_coincident`` with the edge: q's
    edge sees this edge's face beyond it in turn, and both would count the one jump in the
    image. The edge whose face has the lower global id keeps it (the same choice seen from
    either side), with q as what lies beyond."""
    if len(rows) == 0:
        return np.zeros(0, bool)
    forward, right, up, eye = view.frame
    side = np.where(chosen[:, 0] < 0, 1.0, -1.0)  # towards the side without a face
    beyond = camera_directions(coords + EPSILON * side[:, None] * step, right, up, forward)
    q, _, _, _ = view.occluders.accelerator().closest_hit(
        np.broadcast_to(eye, beyond.shape), beyond
    )
    own = kind.table.faces[rows, 0] + kind.first_prim
    return _coincident(view, kind, rows, eye + depth[:, None] * directions, q) & (q < own)


def _coincident(view: View, kind: MeshEdge, rows, point, q) -> np.ndarray:
    """(n,) bool: whether face q (n,) (global ids; -1 or a sphere: no) draws the same curve
    as the open edges ``rows`` (n,) of ``kind.table`` at their points ``point`` (n, 3): the
    point lies on q's plane (within COINCIDENT times the scene's size) and either one of
    q's edges lies on the edge's line (a T-junction, a seam whose vertices do not coincide,
    a gap or overlap narrower than that) or q is parallel to the edge's own face (a flat
    overlap: each edge lies inside the other's face)."""
    triangles = view.occluders.primitives[0]
    own = kind.table.faces[rows, 0] + kind.first_prim
    if len(triangles) == 0 or len(rows) == 0:
        return np.zeros(len(rows), bool)
    tri = triangles[np.clip(q, 0, len(triangles) - 1)]  # (n, 3, 3)
    tolerance = COINCIDENT * view.size
    normal = _unit(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]))
    on_q = np.abs(np.sum((point - tri[:, 0]) * normal, axis=1)) <= tolerance
    face = triangles[own]
    face_normal = _unit(np.cross(face[:, 1] - face[:, 0], face[:, 2] - face[:, 0]))
    parallel = np.linalg.norm(np.cross(face_normal, normal), axis=1) <= COINCIDENT
    vertices = kind.vertices(view.scene)
    a, b = vertices[kind.table.i[rows]], vertices[kind.table.j[rows]]
    u = _unit(b - a)[:, None]
    off = tri - a[:, None]  # (n, 3, 3): q's corners from a
    off_line = np.linalg.norm(off - np.sum(off * u, axis=2, keepdims=True) * u, axis=2)
    near = off_line <= tolerance  # (n, 3): which corners of q lie on the edge's line
    in_line = np.any(near & np.roll(near, -1, axis=1), axis=1)  # two corners: one of q's edges
    q_face = (q >= 0) & (q < len(triangles)) & (q != own)
    return q_face & on_q & (in_line | parallel)


def _unit(v: np.ndarray) -> np.ndarray:
    """Rows of ``v`` (n, 3) scaled to length 1 (zero rows stay zero)."""
    length = np.linalg.norm(v, axis=1, keepdims=True)
    return v / np.where(length > 0, length, 1.0)


def _side_factors(view: View, coords, depth, step, chosen, keys, scale, faces, shadowed
                  ) -> np.ndarray:  # fmt: skip
    """(n, 3): ``scale`` (n,) times f_+ - f_- of n visible edge points through image-plane
    points ``coords`` (n, 2) at ``depth`` (n,), the faces ``chosen`` (n, 2) seen either
    side (-1: none, then the ray ``EPSILON`` pixels along ``step`` (n, 2) beside the
    edge), shaded by ``view.radiance`` (``keys`` (n,) its names of the points; ``faces``
    (n, K) the faces on each point's edge where they may have come apart, which the rays
    of its sides pass: ``_seam_rows``; ``shadowed`` (n, 2, L) the sides in their edge's
    own shadow: ``shadowed_sides``)."""
    n = len(coords)
    keys = np.concatenate([keys, keys])  # per row of ``colour`` below
    # Both sides at once: one shading pass for the sides with a face (shaded at the edge
    # point), one for the sides without (what a ray just beyond the edge sees).
    face = np.concatenate([chosen[:, 0], chosen[:, 1]])  # rows: the + sides, then the -
    both = np.concatenate([coords, coords])
    faced, beyond = np.flatnonzero(face >= 0), np.flatnonzero(face < 0)
    sides = np.concatenate([faces, faces])
    offset = EPSILON * np.concatenate([step, -step])
    colour = np.empty((2 * n, 3))
    colour[faced], colour[beyond] = share_tasks([  # two independent passes (share_tasks)
        partial(view.radiance.seen, np.take(both, faced, axis=0), face[faced],
                np.concatenate([depth, depth])[faced], keys[faced],
                beside=np.take(sides, faced, axis=0),
                shadowed=np.concatenate([shadowed[:, 0], shadowed[:, 1]])[faced]),
        partial(view.radiance.along, np.take(both + offset, beyond, axis=0), keys[beyond],
                beside=np.take(sides, beyond, axis=0)),
    ])  # fmt: skip
    return scale[:, None] * (colour[:n] - colour[n:])


def approach(normals, directions, towards):
    """How fast planes through a point come nearer as the ray moves into one side: a plane
    with normal n through the point at depth t has depth t (n . d) / (n . (d + s g)) along
    the ray moved by s towards g, so the larger (n . g) / (n . d), the nearer it comes.
    Arrays broadcast over leading axes; the last is xyz."""
    nd = np.sum(normals * directions, axis=-1)
    ng = np.sum(normals * towards, axis=-1)
    return ng / np.where(nd != 0, nd, np.inf)
