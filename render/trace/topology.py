"""Mesh topology for edge antialiasing (constants, off the tape): which faces share an
edge once coincident vertices are welded, which edges are silhouettes seen from the eye,
and a walk across the faces along a segment of the image.

The teapot's 32 patches share positions but not vertex ids, and some of their triangles
are degenerate: adjacency is therefore built on *welded* positions (within a tiny fraction
of the mesh's size) and skips degenerate faces. Without welding every patch seam would be a
false boundary, hence a false silhouette (a known failure of nvdiffrast's own tracker).

``walk_to_silhouette`` is written twice: in NumPy, one step for all segments at a time
(the version to read), and as a Numba kernel, one segment at a time (the version the
renderer runs); ``tests/render/edges/test_pairs.py`` checks that they agree.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from minidiff.threads import jit, job_count, kernel, run_jobs, share
from render.trace.grid import candidate_pairs, grown

# Vertices closer than this fraction of the mesh's size (its bounding box diagonal) are one
# position when welding.
_WELD_TOLERANCE = 1e-9
# A triangle whose area is below this fraction of the mesh's squared size is degenerate.
_DEGENERATE_AREA = 1e-12


@dataclass
class MeshEdges:
    """Each face's three edges grouped by the welded edge they lie on.

    edge_group (F, 3) int64: edge k of face f (corners k and k+1 mod 3) lies on welded edge
        ``edge_group[f, k]``; -1 for the edges of degenerate and repeated faces (``welding``:
        never silhouettes, and they are nobody's neighbour).
    n_groups: the number of welded edges.
    neighbour (F, 3) int64: the other face on edge k of face f when exactly two
        non-degenerate faces share it; -1 otherwise (a boundary or non-manifold edge).
    neighbour_edge (F, 3) int64: which edge of that neighbour it is.
    shared_ids (F, 3) bool: the neighbour uses the same two vertex ids on that edge, so
        per-vertex attributes (smooth normals, UVs) are continuous across it.
    welded (F, 3) int64: each corner's welded vertex id.
    table: the same edges seen from the other side: one row per welded edge, with every
        face on it (``EdgeTable``; the boundary integral's candidates).
    """

    edge_group: np.ndarray
    n_groups: int
    neighbour: np.ndarray
    neighbour_edge: np.ndarray
    shared_ids: np.ndarray
    welded: np.ndarray
    table: EdgeTable
    pieces: Pieces


@dataclass
class Pieces:
    """The faces met along an open edge at T-junctions (``cut_at_t_junctions``): where
    face f's edge k runs along the edges of several other faces, the walk across the mesh
    (``walk_to_silhouette``) steps into the one whose edge holds the crossing.

    first (F, 3) int64: the first piece of edge k of face f; -1 for an edge of one
        neighbour or none (``MeshEdges.neighbour``).
    end (m,) float64: where each piece ends along its edge (t from corner k to corner
        k + 1), increasing within an edge; the last piece of an edge ends at +inf.
    face (m,) int64: the face on the other side of the piece; -1 none (an open stretch),
        -2 more than one (a non-manifold stretch).
    edge (m,) int64: that face's edge along the piece (-1 with no face).
    """

    first: np.ndarray
    end: np.ndarray
    face: np.ndarray
    edge: np.ndarray

    def arrays(self) -> tuple:
        """(first, end, face, edge), as the walk's kernels take them."""
        return self.first, self.end, self.face, self.edge

    @staticmethod
    def none(n_faces: int) -> Pieces:
        """No T-junctions on a mesh of ``n_faces`` faces."""
        empty = np.zeros(0, np.int64)
        return Pieces(np.full((n_faces, 3), -1, np.int64), np.zeros(0), empty, empty)


@dataclass
class EdgeTable:
    """The welded edges of one mesh, one row per edge, with every face on it (degenerate
    and repeated faces left out).

    i, j (E,) int64: the edge's vertex ids (as its first face has them).
    faces (E, K) int64: the faces on the edge (local ids), -1 padding: one on an open
        boundary, two on a manifold edge, more where surfaces meet along it (a knob
        standing on a lid).
    thirds (E, K) int64: each face's vertex off the edge (-1 padding).
    """

    i: np.ndarray
    j: np.ndarray
    faces: np.ndarray
    thirds: np.ndarray


def _sorted_slots(edge_group: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The (face, edge) slots f * 3 + k of the non-degenerate edges, sorted by welded edge
    (stable), and their welded edge ids."""
    group = edge_group.reshape(-1)
    slots = np.flatnonzero(group >= 0)
    slots = slots[np.argsort(group[slots], kind="stable")]
    return slots, group[slots]


def _edge_table(faces: np.ndarray, slots: np.ndarray, g: np.ndarray) -> EdgeTable:
    """The ``EdgeTable`` of faces (F, 3) from their ``_sorted_slots`` (no rows when every
    face is degenerate)."""
    # Each run of equal welded edge ids starts a row; with no slots there is no run (the
    # leading True alone would make a row out of nothing).
    starts = np.flatnonzero(np.r_[len(g) > 0, g[1:] != g[:-1]])
    count = np.diff(np.r_[starts, len(g)])
    rank = np.arange(len(g)) - np.repeat(starts, count)
    row = np.repeat(np.arange(len(starts)), count)
    f, k = slots // 3, slots % 3
    table_faces = np.full((len(starts), int(count.max(initial=1))), -1, np.int64)
    thirds = np.full_like(table_faces, -1)
    table_faces[row, rank] = f
    thirds[row, rank] = faces[f, (k + 2) % 3]
    first = slots[starts]
    return EdgeTable(faces[first // 3, first % 3], faces[first // 3, (first % 3 + 1) % 3],
                     table_faces, thirds)  # fmt: skip


def open_rows_of(table: EdgeTable) -> np.ndarray:
    """The rows of ``table`` with one face (open edges: borders, and where meshes meet)."""
    return np.flatnonzero(np.sum(table.faces >= 0, axis=1) == 1)


def welded_ids(
    vertices: np.ndarray,
    tolerance: float | np.ndarray | None = None,
    near: np.ndarray | None = None,
) -> np.ndarray:
    """(V,) int64: each vertex's welded id, equal for vertices at the same position (within
    ``_WELD_TOLERANCE`` of the mesh's bounding-box diagonal), numbered 0..U-1. With a
    ``tolerance`` (a float, or (V,) per vertex: ``seam_reach``): equal too for two
    vertices among ``near`` (indices; None: every vertex) closer than that (than both
    vertices' tolerances), and for chains of such (the pairs a grid of boxes finds,
    ``render.trace.grid``, joined): where vertices that are one position came apart by
    more than rounding, as coordinates that went through float32 do, no cell boundary
    splits them. (Where meshes meet, at their seams and T-junctions, each side's vertices
    are on its open edges: ``near`` those, the grid holds few.)"""
    # Relative to the mesh's own size and corner, so that welding does not depend on where
    # the mesh is or how large it is.
    low = vertices.min(axis=0) if len(vertices) else np.zeros(3)
    keys = np.round((vertices - low) / weld_distance(vertices))
    ids = row_ids(keys)
    if tolerance is None or len(vertices) == 0:
        return ids
    near = np.arange(len(vertices)) if near is None else np.unique(near)
    reach = np.broadcast_to(np.asarray(tolerance, np.float64), (len(vertices),))
    lo, hi = grown(vertices[near], vertices[near], reach[near])
    found = candidate_pairs(vertices[near], lo, hi, _MOST_PAIRS)
    if found is None:  # a crowd within the tolerance (a mesh collapsed to a few points)
        return row_ids(np.round((vertices - low) / reach[near].min()))
    point, other = near[found[0]], near[found[1]]
    within = np.minimum(reach[point], reach[other])  # both ends' reach
    close = np.sum((vertices[point] - vertices[other]) ** 2, axis=1) <= within**2
    edges = (ids[point[close]], ids[other[close]])
    if np.all(edges[0] == edges[1]):  # nothing came apart: the ids as they are
        return ids
    n = int(ids.max()) + 1
    count, label = connected_components(
        coo_matrix((np.ones(len(edges[0])), edges), shape=(n, n)), directed=False
    )
    # Numbered as without a tolerance, by the key of each group's first vertex in
    # lexicographic order: where nothing came apart, the same ids (and tables).
    first = np.full(count, len(vertices))
    np.minimum.at(first, label[ids], np.arange(len(vertices)))
    return row_ids(keys[first])[label[ids]]


def row_ids(rows: np.ndarray) -> np.ndarray:
    """(n,) int64: the rank of each row of ``rows`` (n, k) among the distinct rows in
    lexicographic order, first column first: ``np.unique(rows, axis=0,
    return_inverse=True)[1]``, by one ``np.lexsort`` (NumPy's unique along an axis sorts a
    structured view of the rows, ~10 times slower on a mesh's vertices)."""
    if len(rows) == 0:
        return np.zeros(0, np.int64)
    order = np.lexsort(rows.T[::-1])  # the last key given is the primary one
    ordered = rows[order]
    new = np.r_[True, np.any(ordered[1:] != ordered[:-1], axis=1)]
    ids = np.empty(len(rows), np.int64)
    ids[order] = np.cumsum(new) - 1
    return ids


def weld_distance(vertices: np.ndarray) -> float:
    """How close two of these vertices (V, 3) must be to be one position: ``_WELD_TOLERANCE``
    of their bounding box's diagonal."""
    return _WELD_TOLERANCE * mesh_size(vertices)


def mesh_size(vertices: np.ndarray) -> float:
    """The length of the mesh's bounding-box diagonal (never zero)."""
    extent = vertices.max(axis=0) - vertices.min(axis=0)
    return max(float(np.linalg.norm(extent)), np.finfo(float).tiny)


#: Vertices of different meshes closer than this fraction of their coordinates' size are
#: one position (``seam_distance``): four float32 steps, as far as coordinates that were
#: once float32 (most mesh files) and were computed otherwise in two meshes can differ.
SEAM_GAP = 4 * float(np.finfo(np.float32).eps)
#: ... or closer than this fraction of the meshes' size (their bounding box's diagonal):
#: four times the distance within which the boundary term takes a point of an open edge to
#: lie on another face's edge (``render.edges.boundary.mesh_edge.COINCIDENT``, which
#: reads it). A seam whose sides came apart by less is welded, one row with both faces,
#: the same answer seen from either side; one that came apart by more lies outside that
#: test everywhere along it, and each side is a border. Between the two (the weld at four
#: float32 steps, the test at 1e-6), the test saw the seam closed at some of its points and
#: open at others: a box split into meshes whose seams were moved 2e-6 apart had gradients
#: 11-85 % off the one mesh's.
SEAM_SIZE = 4e-6
#: ... or closer than this fraction of the shortest open edge at either of them (a crack
#: narrow beside the edges it lies between: parts exported one by one, each tessellated
#: and rounded alone), and a vertex as close to an open edge, relative to that edge, lies
#: on it (``points_inside``). Left open, such a crack's two sides were two borders: a box
#: split into meshes whose seams were moved 1e-4 apart (3e-4 of its edges) had gradients
#: off the one mesh's by 5-77 % (24 boxes of ``benchmarks/seams.py``).
SEAM_LENGTH = 1e-3


def seam_distance(vertices: np.ndarray) -> float:
    """How close vertices of different meshes must be to be one position, and a vertex to
    an open edge to lie on it (a T-junction), for meshes whose vertices (V, 3), all of them,
    are ``vertices`` (or one mesh's, for its own T-junctions): within ``SEAM_GAP`` of their
    largest coordinate or ``SEAM_SIZE`` of their size, whichever is larger. Coarser than a
    mesh's own welding (``weld_distance``): two meshes that meet along a seam may have come
    apart by more than rounding (one of them through float32, the other not: 1.2e-8 apart
    on a box of size 0.4 at 0.7 from the origin, where their boundary terms' gradients,
    taken as two borders, were 20 % off and more), and a T-junction's vertex, rounded, is
    off the long edge's line."""
    if len(vertices) == 0:
        return np.finfo(float).tiny
    size = float(np.abs(vertices).max())
    return max(SEAM_GAP * size, SEAM_SIZE * mesh_size(vertices), np.finfo(float).tiny)


def seam_reach(vertices: np.ndarray, i: np.ndarray, j: np.ndarray, floor: float) -> np.ndarray:
    """(V,): how far each of ``vertices`` (V, 3) reaches to be one position with another
    (``welded_ids``): ``floor`` (``seam_distance``), or ``SEAM_LENGTH`` of the shortest
    open edge (ends i, j (n,)) at it, whichever is larger."""
    length = np.linalg.norm(vertices[i] - vertices[j], axis=1)
    shortest = np.full(len(vertices), np.inf)
    np.minimum.at(shortest, i, length)
    np.minimum.at(shortest, j, length)
    return np.maximum(floor, np.where(np.isfinite(shortest), SEAM_LENGTH * shortest, 0.0))


def mesh_edges(
    vertices: np.ndarray,
    faces: np.ndarray,
    tolerance: float | np.ndarray | None = None,
    near=None,
    cut: float | None = None,
) -> MeshEdges:
    """The welded edge structure of a mesh: vertices (V, 3), faces (F, 3), its table's
    open rows cut at T-junctions (``cut_at_t_junctions``, within ``cut``: by default its
    ``seam_distance``); vertices welded within ``tolerance`` (a float, or (V,): per vertex)
    of the vertices ``near`` where it is given (``welded_ids``)."""
    structure = edge_structure(faces, *welding(vertices, faces, tolerance, near))
    return cut_at_t_junctions(structure, np.asarray(vertices, np.float64), faces, cut)


def cut_at_t_junctions(
    edges: MeshEdges, vertices: np.ndarray, faces: np.ndarray, tolerance: float | None = None
) -> MeshEdges:
    """``edges`` with the open rows of its table (one face) cut where a vertex of another
    open row lies inside them (within ``tolerance``, else ``seam_distance``): a T-junction,
    where one face's edge runs along two of another's (a quad split on one side only).
    The parts join the rows of the same welded ends, so that the curve between the faces
    is one row with a face on each side, as it would be had the long edge been split
    too; elsewhere ``edges`` itself. (Uncut, each face's edge counted the jump to the other
    face as its own: the curve twice.) The faces meet across the cut too, for the walk
    (``walk_to_silhouette``): a face whose edge is one part is the neighbour of the long
    edge's face, and the long edge holds its parts' faces (``Pieces``); uncut, the walk took
    the long edge for an open one, a silhouette. Vertices (V, 3) float64, faces (F, 3)."""
    table = edges.table
    open_rows = open_rows_of(table)
    if len(open_rows) < 2:
        return edges
    ids = np.full(len(vertices), -1, np.int64)
    ids[faces] = edges.welded  # each vertex's welded id
    ends = np.unique(np.r_[table.i[open_rows], table.j[open_rows]])
    inside = points_inside(vertices, table.i[open_rows], table.j[open_rows], ends, ids,
                           tolerance or seam_distance(vertices))  # fmt: skip
    if inside is None or len(inside[0]) == 0:  # None: too many candidates to test (a soup)
        return edges
    cut, parts = _cut_table(table, open_rows, *inside, ids)
    return _joined_across(replace(edges, table=cut), faces, table, parts)


#: ``cut_at_t_junctions`` tests at most this many (point, open edge) pairs that a grid of
#: the edges' boxes leaves: a mesh of many long open edges crowding its volume (a soup of
#: disjoint triangles, where T-junctions are not to be expected) keeps its table uncut
#: rather than spend seconds (``MeshEdge``'s ``_counted_elsewhere`` still counts such
#: curves once where the ray beyond one edge meets the other's face).
_MOST_PAIRS = 1 << 22


def points_inside(vertices, i, j, points, ids, tolerance):
    """The pairs (segment (m,), point (m,), t (m,)) of segments (vertex ids i, j (n,)) and
    ``points`` (vertex ids) that lie strictly inside them, within ``tolerance`` or
    ``SEAM_LENGTH`` of the segment's length, whichever is larger: at t along the segment,
    0 < t < 1, another welded vertex than its ends; None if the candidates a grid of the
    segments' boxes leaves (``render.trace.grid``) are more than ``_MOST_PAIRS``."""
    a, b = vertices[i], vertices[j]
    p = vertices[points]
    tolerance = np.maximum(tolerance, SEAM_LENGTH * np.linalg.norm(b - a, axis=1))
    lo, hi = grown(np.minimum(a, b), np.maximum(a, b), tolerance)
    pairs = candidate_pairs(p, lo, hi, _MOST_PAIRS)
    if pairs is None:
        return None
    point, segment = pairs
    d = b[segment] - a[segment]
    length2 = np.sum(d * d, axis=1)
    off = p[point] - a[segment]
    t = np.sum(off * d, axis=1) / np.where(length2 > 0, length2, 1.0)
    miss = off - t[:, None] * d
    on = (np.sum(miss * miss, axis=1) <= tolerance[segment] ** 2) & (length2 > 0)
    pid = ids[points[point]]
    own = (pid == ids[i[segment]]) | (pid == ids[j[segment]])
    keep = on & ~own & (t > 0.0) & (t < 1.0)
    return segment[keep], points[point[keep]], t[keep]


def _cut_table(table: EdgeTable, open_rows, segment, point, t, ids):
    """``table`` with open row ``open_rows[s]`` cut at the vertices ``point`` found inside
    it (``points_inside``'s pairs), in the order of t, its parts merged with the rows of
    the same welded ends (at the first row's place, with its ends and its faces first, then
    the others' faces). Only the cut rows and those they merge with are looked at one by
    one: a large mesh with a few T-junctions keeps the rest of its table as arrays.
    Returns the new table and, for each cut row, (its row in ``table``, where its parts
    end along it (t, increasing, the last 1), their rows in the new table)."""
    order = np.lexsort((t, segment))
    segment, point, t = segment[order], point[order], t[order]
    # A position found twice inside one row (the vertices of two meshes welded as one: a
    # T-junction's vertex in each) cuts it once: else a part from one to the other, of no
    # length, was left open, a border.
    _, once = np.unique(np.stack([segment, ids[point]], axis=1), axis=0, return_index=True)
    once = np.sort(once)
    segment, point, t = segment[once], point[once], t[once]
    cut = np.unique(segment)
    sources, ranks, parts_i, parts_j, ends = [], [], [], [], []
    for s in cut:  # few: the rows with T-junctions
        r = open_rows[s]
        chain = np.r_[table.i[r], point[segment == s], table.j[r]]
        ends.append(np.r_[t[segment == s], 1.0])
        sources.append(np.full(len(chain) - 1, r))
        ranks.append(np.arange(len(chain) - 1))
        parts_i.append(chain[:-1])
        parts_j.append(chain[1:])
    kept = np.setdiff1d(np.arange(len(table.i)), open_rows[cut])
    source = np.r_[kept, *sources]
    rank = np.r_[np.zeros(len(kept), np.int64), *ranks]
    new_i = np.r_[table.i[kept], *parts_i]
    new_j = np.r_[table.j[kept], *parts_j]
    by_place = np.lexsort((rank, source))  # each row where its source row was
    source, new_i, new_j = source[by_place], new_i[by_place], new_j[by_place]
    group = row_ids(np.sort(np.stack([ids[new_i], ids[new_j]], axis=1), axis=1))
    _, head = np.unique(group, return_index=True)  # each group's first row
    heads = np.sort(head)
    final = np.empty(len(heads), np.int64)  # each group's row in the new table
    final[group[heads]] = np.arange(len(heads))
    first_part = np.searchsorted(source, open_rows[cut])  # rows sorted by source, then rank
    parts = [(open_rows[s], end, final[group[first + np.arange(len(end))]])
             for s, end, first in zip(cut, ends, first_part, strict=True)]  # fmt: skip
    faces, thirds = table.faces[source[heads]], table.thirds[source[heads]]
    merged = np.flatnonzero(np.bincount(group)[group[heads]] > 1)
    if len(merged):  # the parts that lie on another row: one row, every face
        columns = []
        for row in merged:
            members = np.flatnonzero(group == group[heads[row]])
            on = table.faces[source[members]] >= 0
            columns.append((table.faces[source[members]][on], table.thirds[source[members]][on]))
        width = max(faces.shape[1], *(len(f) for f, _ in columns))
        faces = np.pad(faces, ((0, 0), (0, width - faces.shape[1])), constant_values=-1)
        thirds = np.pad(thirds, ((0, 0), (0, width - thirds.shape[1])), constant_values=-1)
        for row, (f, third) in zip(merged, columns, strict=True):
            faces[row], thirds[row] = -1, -1
            faces[row, : len(f)], thirds[row, : len(f)] = f, third
    return EdgeTable(new_i[heads], new_j[heads], faces, thirds), parts


def _joined_across(edges: MeshEdges, faces, uncut: EdgeTable, parts) -> MeshEdges:
    """``edges`` (its table cut by ``_cut_table`` from ``uncut``, which also gave ``parts``)
    with the faces on either side of each cut edge made neighbours: a face whose whole edge
    is one part of the long edge has the long edge's face as its ``neighbour``, and the long
    edge's ``Pieces`` hold each part's face. Faces (F, 3)."""
    neighbour, neighbour_edge = edges.neighbour.copy(), edges.neighbour_edge.copy()
    first = edges.pieces.first.copy()
    ends, others, other_edges, whole = [], [], [], []
    for r, end, rows in parts:
        face = uncut.faces[r, 0]  # an open row: one face, whose edge runs i -> j
        k = _edge_index(faces[face], uncut.i[r], uncut.j[r])
        first[face, k] = len(others)  # its pieces: the next len(rows)
        ends.append(np.r_[end[:-1], np.inf])
        for row in rows:
            on = edges.table.faces[row]
            across = (on >= 0) & (on != face)
            if np.sum(across) != 1:  # -1: nothing across this part, -2: several faces
                others.append(-1 if not np.any(across) else -2)
                other_edges.append(-1)
                continue
            g = int(on[across][0])
            # g's edge along the part is the one opposite its third vertex (which may be
            # longer than the part, where g's edge is cut too)
            kg = (int(np.flatnonzero(faces[g] == edges.table.thirds[row][across][0])[0]) + 1) % 3
            others.append(g)
            other_edges.append(kg)
            whole.append((g, kg, face, k))
    for g, kg, face, k in whole:
        if neighbour[g, kg] < 0 and first[g, kg] < 0:  # a part that is g's whole edge
            neighbour[g, kg], neighbour_edge[g, kg] = face, k
    pieces = Pieces(first, np.concatenate(ends), np.array(others, np.int64),
                    np.array(other_edges, np.int64))  # fmt: skip
    return replace(edges, neighbour=neighbour, neighbour_edge=neighbour_edge, pieces=pieces)


def _edge_index(corners: np.ndarray, i: int, j: int) -> int:
    """Which edge k of a face with ``corners`` (3,) (vertex ids) runs from i to j."""
    for k in range(3):
        if corners[k] == i and corners[(k + 1) % 3] == j:
            return k
    raise AssertionError("the face has no such edge")  # the table's rows come from its faces


def welding(
    vertices: np.ndarray,
    faces: np.ndarray,
    tolerance: float | np.ndarray | None = None,
    near=None,
) -> tuple[np.ndarray, np.ndarray]:
    """All that ``mesh_edges`` needs from the vertex positions: each corner's welded vertex
    id (F, 3) int64 and which faces are degenerate (F,) bool (a welded edge, an area below
    ``_DEGENERATE_AREA`` of the mesh's squared size, or a repeat of an earlier face with
    the same welded corners in the same winding: the surface is there once, and its edges
    are open or shared as if it were listed once). While a shape moves, these rarely
    change, so the rest (``edge_structure``) can be reused."""
    scale = mesh_size(vertices)
    ids = welded_ids(vertices, tolerance, near)[faces]  # (F, 3) welded vertex ids
    corners = vertices[faces]
    area = np.linalg.norm(
        np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1
    )
    degenerate = (
        (ids[:, 0] == ids[:, 1]) | (ids[:, 1] == ids[:, 2]) | (ids[:, 2] == ids[:, 0])
    ) | (area <= _DEGENERATE_AREA * scale * scale)
    return ids, degenerate | repeated_faces(ids)


def repeated_faces(ids: np.ndarray) -> np.ndarray:
    """(F,) bool: the faces whose corners ``ids`` (F, 3) (welded vertex ids) repeat an
    earlier face's in the same cyclic order (the same triangle, wound the same way; a copy
    wound the other way is the back of a two-sided sheet, and stays)."""
    if len(ids) == 0:
        return np.zeros(0, bool)
    start = np.argmin(ids, axis=1)[:, None]  # each face read from its lowest id on
    turned = np.take_along_axis(ids, (start + np.arange(3)) % 3, axis=1)
    group = row_ids(turned)
    first = np.full(int(group.max()) + 1, len(ids))
    np.minimum.at(first, group, np.arange(len(ids)))
    return first[group] != np.arange(len(ids))


def edge_structure(faces: np.ndarray, ids: np.ndarray, degenerate: np.ndarray) -> MeshEdges:
    """``MeshEdges`` from the faces (F, 3) and their ``welding``."""
    a, b = ids, np.roll(ids, -1, axis=1)  # edge k joins corner k and corner k + 1
    pairs = np.stack([np.minimum(a, b), np.maximum(a, b)], axis=-1).reshape(-1, 2)
    group = row_ids(pairs).reshape(-1, 3)
    group[degenerate] = -1
    n_groups = int(group.max()) + 1 if group.size else 0

    # Pair up the two (face, edge) slots of each manifold welded edge.
    slots, g = _sorted_slots(group)
    count = np.bincount(g, minlength=n_groups)
    first = slots[:-1][(g[:-1] == g[1:]) & (count[g[:-1]] == 2)]
    second = slots[1:][(g[:-1] == g[1:]) & (count[g[1:]] == 2)]
    neighbour = np.full(group.size, -1, dtype=np.int64)
    neighbour_edge = np.full(group.size, -1, dtype=np.int64)
    neighbour[first], neighbour_edge[first] = second // 3, second % 3
    neighbour[second], neighbour_edge[second] = first // 3, first % 3
    neighbour, neighbour_edge = neighbour.reshape(-1, 3), neighbour_edge.reshape(-1, 3)
    # Same ids on both sides: the neighbour's edge runs the other way (b, a) if consistently
    # wound, or the same way (a, b) if not; either way the id sets agree.
    a_ids, b_ids = faces, np.roll(faces, -1, axis=1)
    f, k = np.maximum(neighbour, 0), np.maximum(neighbour_edge, 0)
    na, nb = a_ids[f, k], b_ids[f, k]
    shared = (neighbour >= 0) & (((na == b_ids) & (nb == a_ids)) | ((na == a_ids) & (nb == b_ids)))
    return MeshEdges(
        group,
        n_groups,
        neighbour,
        neighbour_edge,
        shared,
        ids,
        _edge_table(faces, slots, g),
        Pieces.none(len(faces)),
    )


def facing(vertices: np.ndarray, faces: np.ndarray, eye, directional: bool = False) -> np.ndarray:
    """(F,) bool: each face faces the viewer at ``eye`` (3,) (with ``directional``: at
    infinity, looking along ``eye``), by the side of its plane the viewer is on."""
    corners = vertices[faces]
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    if directional:
        return normal @ -np.asarray(eye, np.float64) > 0
    return np.einsum("ij,ij->i", normal, eye - corners[:, 0]) > 0


def silhouette_edges(
    edges: MeshEdges, vertices: np.ndarray, faces: np.ndarray, eye, directional: bool = False
) -> np.ndarray:
    """(F, 3) bool: edge k of face f is a silhouette seen from ``eye`` (3,): a boundary
    edge (no other non-degenerate face shares it) or one whose faces face opposite ways,
    as their positions have it, not their winding (``wound_alike``: a mesh whose faces
    are wound inconsistently, as scans and soups often are, is the same surface). With
    ``directional`` the viewer is at infinity and ``eye`` is the direction in which it
    looks (a directional light's direction of travel)."""
    front = facing(vertices, faces, eye, directional)
    valid = edges.edge_group >= 0
    groups = edges.edge_group[valid]
    forward = np.broadcast_to(front[:, None], valid.shape)[valid]
    n_front = np.bincount(groups[forward], minlength=edges.n_groups)
    n_back = np.bincount(groups[~forward], minlength=edges.n_groups)
    total = n_front + n_back
    silhouette = np.zeros(valid.shape, dtype=bool)
    silhouette[valid] = (total[groups] == 1) | ((n_front[groups] > 0) & (n_back[groups] > 0))
    # Two faces that are neighbours: the same rule from the pair itself (which also holds
    # where they meet at a T-junction, their edges on different welded ends).
    paired = edges.neighbour >= 0
    own = np.broadcast_to(front[:, None], paired.shape)
    f, k = np.nonzero(paired)
    g, kg = edges.neighbour[f, k], edges.neighbour_edge[f, k]
    alike = wound_alike(vertices, faces, f, k, g, kg)
    silhouette[paired] = (own[paired] != front[g]) == alike
    return silhouette


def wound_alike(vertices: np.ndarray, faces: np.ndarray, f, k, g, kg) -> np.ndarray:
    """Whether faces f and g (F,) of ``faces`` (vertex ids into ``vertices``), neighbours
    across f's edge k, which lies along g's edge kg, are wound alike: the edge runs one way
    in one and the other way in the other (along it, a part of the other's at a
    T-junction). Where they are not, the one's front is the other's back: they face the
    same way where ``facing`` says they do not. (Taken as winding, a mesh with faces
    flipped at random had false silhouettes everywhere: its pixel pairs blended pixels
    across them, the image 0.31 off, the gradients up to 84 %.)"""
    a, b = vertices[faces[f, k]], vertices[faces[f, (k + 1) % 3]]
    c, d = vertices[faces[g, kg]], vertices[faces[g, (kg + 1) % 3]]
    return np.einsum("ij,ij->i", b - a, d - c) < 0


def walk_to_silhouette(
    edges: MeshEdges, silhouette, vertices, faces, start, eye, d_near, d_far, max_steps=32,
    directional: bool = False, jumps=None,
):  # fmt: skip
    """Follow each segment (near sample at s = 0, far sample at s = 1) across the mesh from
    the near sample's face ``start`` (n,), face to face, until it leaves through a
    silhouette edge. Returns the face (n,), its edge (n,) (-2: none before s = 1, or a
    non-manifold edge on the way) and the crossing s* (n,).

    Seen from the eye, the segment enters a face through one edge and leaves through the
    first of the other two edge lines it crosses (a triangle is convex). At low resolution
    the face hit at the near sample is often not the one on the silhouette: this walk finds
    the one that is (nvdiffrast only looks at the face in the pixel).

    Also returns, for the crease test (``render.edges.silhouettes.edge_pairs``), the crossing of an
    edge where ``jumps`` (F, 3) bool says the colour jumps (flat shading, seams) that lies
    closest to the middle of the segment: its face, edge and s, (n,) each (edge -1: none).

    With ``directional`` the viewer is at infinity looking along ``eye`` (a directional
    light), and d_near, d_far are the segment's end *points*: an edge's plane then contains
    the edge and the viewing direction, normal (v_k+1 - v_k) x eye.
    """
    n = len(start)
    face = start.copy()
    entry = np.full(n, -1, dtype=np.int64)  # the edge the segment came in through
    s_entry = np.zeros(n)
    edge = np.full(n, -2, dtype=np.int64)
    s_out = np.full(n, np.nan)
    active = np.arange(n)
    jumps = np.zeros(silhouette.shape, bool) if jumps is None else jumps
    front = _front_if_cut(edges, vertices, faces, eye, directional)
    mid = (np.full(n, -1, np.int64), np.full(n, -1, np.int64), np.full(n, np.nan))
    for _ in range(max_steps):
        if len(active) == 0:
            break
        corners = vertices[faces[face[active]]]
        s_k = np.full((len(active), 3), np.inf)
        for k in range(3):
            if directional:
                m = np.cross(corners[:, (k + 1) % 3] - corners[:, k], eye)
                e_near = np.einsum("ij,ij->i", d_near[active] - corners[:, k], m)
                e_far = np.einsum("ij,ij->i", d_far[active] - corners[:, k], m)
            else:
                m = np.cross(corners[:, k] - eye, corners[:, (k + 1) % 3] - eye)
                e_near = np.einsum("ij,ij->i", d_near[active], m)
                e_far = np.einsum("ij,ij->i", d_far[active], m)
            with np.errstate(divide="ignore", invalid="ignore"):
                s = e_near / (e_near - e_far)
            ahead = (np.sign(e_near) != np.sign(e_far)) & (s > s_entry[active])
            s_k[:, k] = np.where(ahead & (entry[active] != k), s, np.inf)
        k = np.argmin(s_k, axis=1)
        s = s_k[np.arange(len(active)), k]
        inside = s < 1.0  # else the far sample lies on this face's side: no edge between
        here = face[active]
        nb, nb_edge = edges.neighbour[here, k], edges.neighbour_edge[here, k]
        across, jump = silhouette[here, k], jumps[here, k]
        for r in np.flatnonzero(inside & (edges.pieces.first[here, k] >= 0)):  # T-junctions
            nb[r], nb_edge[r], across[r], jump[r] = _across(
                here[r], k[r], edges.neighbour, edges.neighbour_edge, silhouette, jumps,
                *edges.pieces.arrays(), front, vertices, faces, eye, directional,
                d_near[active[r]], d_far[active[r]], s[r],
            )  # fmt: skip
        at_silhouette = inside & across
        jump &= inside & ~at_silhouette
        closer = jump & ~(np.abs(mid[2][active] - 0.5) <= np.abs(s - 0.5))
        rows = active[closer]
        mid[0][rows], mid[1][rows], mid[2][rows] = face[rows], k[closer], s[closer]
        done = active[at_silhouette]
        edge[done], s_out[done] = k[at_silhouette], s[at_silhouette]
        step = inside & ~at_silhouette & (nb >= 0)
        moving = active[step]
        entry[moving] = nb_edge[step]
        face[moving], s_entry[moving] = nb[step], s[step]
        active = moving
    return face, edge, s_out, mid


@jit(cache=True, inline="always")
def _edge_values(vertices, a, b, eye, directional, near, far):
    """The edge function of edge (a, b) at the segment's two ends, with scalars only (no
    temporaries in the walk's inner loop): e = near . m with m = (v_a - eye) x (v_b - eye)
    for a viewer at ``eye``, e = (near - v_a) . m with m = (v_b - v_a) x eye for a viewer
    looking along ``eye`` (``directional``); likewise at ``far``."""
    if directional:
        px = vertices[b, 0] - vertices[a, 0]
        py = vertices[b, 1] - vertices[a, 1]
        pz = vertices[b, 2] - vertices[a, 2]
        qx, qy, qz = eye[0], eye[1], eye[2]
        ox, oy, oz = vertices[a, 0], vertices[a, 1], vertices[a, 2]
    else:
        px, py, pz = vertices[a, 0] - eye[0], vertices[a, 1] - eye[1], vertices[a, 2] - eye[2]
        qx, qy, qz = vertices[b, 0] - eye[0], vertices[b, 1] - eye[1], vertices[b, 2] - eye[2]
        ox, oy, oz = 0.0, 0.0, 0.0
    mx = py * qz - pz * qy
    my = pz * qx - px * qz
    mz = px * qy - py * qx
    e_near = (near[0] - ox) * mx + (near[1] - oy) * my + (near[2] - oz) * mz
    e_far = (far[0] - ox) * mx + (far[1] - oy) * my + (far[2] - oz) * mz
    return e_near, e_far


def _front_if_cut(edges: MeshEdges, vertices, faces, eye, directional) -> np.ndarray:
    """``facing`` where the walk may need it (a mesh with ``Pieces``), else no faces."""
    if edges.pieces.end.size == 0:
        return np.zeros(0, bool)
    return facing(np.asarray(vertices, np.float64), faces, np.asarray(eye, np.float64), directional)


@jit(cache=True, inline="always")
def _along_edge(vertices, a, b, eye, directional, near, far, s):
    """Where, as t from v_a (0) to v_b (1), the line of edge (a, b) meets the ray of the
    segment's point at s (the ray from ``eye`` along near + s (far - near), or, with
    ``directional``, the ray through that point along ``eye``): the t that makes
    (v_a + t e - o) parallel to the ray's direction d, e = v_b - v_a, o the ray's origin."""
    px = near[0] + s * (far[0] - near[0])
    py = near[1] + s * (far[1] - near[1])
    pz = near[2] + s * (far[2] - near[2])
    ox, oy, oz, dx, dy, dz = eye[0], eye[1], eye[2], px, py, pz  # from eye through the point
    if directional:  # from the point along eye
        ox, oy, oz, dx, dy, dz = px, py, pz, eye[0], eye[1], eye[2]
    ex = vertices[b, 0] - vertices[a, 0]
    ey = vertices[b, 1] - vertices[a, 1]
    ez = vertices[b, 2] - vertices[a, 2]
    wx, wy, wz = vertices[a, 0] - ox, vertices[a, 1] - oy, vertices[a, 2] - oz
    mx, my, mz = ey * dz - ez * dy, ez * dx - ex * dz, ex * dy - ey * dx  # e x d
    nx, ny, nz = wy * dz - wz * dy, wz * dx - wx * dz, wx * dy - wy * dx  # (v_a - o) x d
    return -(nx * mx + ny * my + nz * mz) / (mx * mx + my * my + mz * mz)


@jit(cache=True)
def _across(f, k, neighbour, neighbour_edge, silhouette, jumps, first, end, piece_face,
            piece_edge, front, vertices, faces, eye, directional, near, far, s):  # fmt: skip
    """What lies across edge k of face f where the segment (near, far) crosses it at s:
    the face (-1: none), its edge, whether the edge is a silhouette there and whether the
    colour jumps. An edge with ``Pieces`` (a T-junction) answers for the piece that holds
    the crossing: a silhouette there if the face beyond faces the other way (``front``,
    ``facing``, taken with the two edges' directions for their winding: the face's own
    edge may be cut too, and its ``silhouette`` that of an open edge)."""
    p = first[f, k]
    if p < 0:
        return neighbour[f, k], neighbour_edge[f, k], silhouette[f, k], jumps[f, k]
    t = _along_edge(vertices, faces[f, k], faces[f, (k + 1) % 3], eye, directional, near, far, s)
    while t > end[p]:
        p += 1
    g, kg = piece_face[p], piece_edge[p]
    if g >= 0:
        # Wound alike, the part and the long edge run opposite ways (``wound_alike``).
        a, b = faces[f, k], faces[f, (k + 1) % 3]
        c, d = faces[g, kg], faces[g, (kg + 1) % 3]
        along = 0.0
        for x in range(3):
            along += (vertices[b, x] - vertices[a, x]) * (vertices[d, x] - vertices[c, x])
        return g, kg, (front[f] != front[g]) == (along < 0), jumps[g, kg]
    return -1, -1, g == -1, True  # open (a silhouette), or several faces (the walk stops)


@kernel
def _walk_kernel(job, n_jobs, vertices, faces, neighbour, neighbour_edge, silhouette, jumps,
                 piece_first, piece_end, piece_face, piece_edge, front, start, eye, d_near,
                 d_far, max_steps, directional, face, edge, s_out, mid_face, mid_k,
                 mid_s):  # fmt: skip
    """Job ``job`` of ``n_jobs`` (``minidiff.threads.run_jobs``) of ``walk_to_silhouette``,
    one segment at a time (same steps, same tie-breaking: the lowest edge index wins); the
    outputs (face, edge, s_out, mid_face, mid_k, mid_s) hold start, -2, nan, -1, -1, nan on
    entry."""
    first, stop = share(job, n_jobs, start.shape[0])
    for i in range(first, stop):
        f = start[i]
        entry = -1
        s_entry = 0.0
        for _ in range(max_steps):
            best_k = 0
            best_s = np.inf
            for k in range(3):
                if k == entry:
                    continue
                e_near, e_far = _edge_values(
                    vertices, faces[f, k], faces[f, (k + 1) % 3], eye, directional,
                    d_near[i], d_far[i],
                )  # fmt: skip
                if np.sign(e_near) != np.sign(e_far):
                    s = e_near / (e_near - e_far)
                    if s > s_entry and s < best_s:
                        best_k, best_s = k, s
            if not best_s < 1.0:
                break
            nb, nb_edge, at_silhouette, jump = _across(
                f, best_k, neighbour, neighbour_edge, silhouette, jumps, piece_first, piece_end,
                piece_face, piece_edge, front, vertices, faces, eye, directional, d_near[i],
                d_far[i], best_s,
            )  # fmt: skip
            if at_silhouette:
                edge[i], s_out[i] = best_k, best_s
                break
            if jump and not abs(mid_s[i] - 0.5) <= abs(best_s - 0.5):
                mid_face[i], mid_k[i], mid_s[i] = f, best_k, best_s
            if nb < 0:
                break
            entry = nb_edge
            f = nb
            s_entry = best_s
        face[i] = f


def walk_to_silhouette_fast(
    edges: MeshEdges, silhouette, vertices, faces, start, eye, d_near, d_far, max_steps=32,
    directional: bool = False, jumps=None,
):  # fmt: skip
    """``walk_to_silhouette`` (same arguments, same results) as one Numba kernel."""
    jumps = np.zeros(silhouette.shape, bool) if jumps is None else jumps
    front = _front_if_cut(edges, vertices, faces, eye, directional)
    start = np.array(start, np.int64)
    n = len(start)
    face, edge, s = start.copy(), np.full(n, -2, np.int64), np.full(n, np.nan)
    mid_face, mid_k, mid_s = np.full(n, -1, np.int64), np.full(n, -1, np.int64), np.full(n, np.nan)
    run_jobs(
        _walk_kernel, job_count(n, 256), np.ascontiguousarray(vertices, dtype=np.float64),
        faces, edges.neighbour, edges.neighbour_edge, np.ascontiguousarray(silhouette),
        np.ascontiguousarray(jumps), *edges.pieces.arrays(), front, start,
        np.asarray(eye, np.float64),
        np.ascontiguousarray(d_near, dtype=np.float64),
        np.ascontiguousarray(d_far, dtype=np.float64), max_steps, directional, face, edge, s,
        mid_face, mid_k, mid_s,
    )  # fmt: skip
    return face, edge, s, (mid_face, mid_k, mid_s)
