"""Edges that several meshes share (constants, off the tape): one curve, counted once.

A file with several materials is read as several meshes (``load_mesh``: one per material),
which meet along seams: the red and the green half of a model share the vertices of the
line between them. Each mesh's own table (``render.trace.topology.EdgeTable``) sees such a
seam as an open boundary, with a face on one side and nothing on the other. Left so, the
boundary integral would count the seam once from each mesh, each time with the jump from
its face to whatever lies beyond it: twice the true term (or, for two meshes that do not
move alike, the sum of two wrong ones).

The image jumps across a curve by what the nearest surfaces on its two sides show,
whichever objects they belong to. So edges are matched across meshes by position (the
vertices welded as within a mesh, at the finest of the meshes' welding tolerances), the
first mesh in ``scene.meshes`` that has an edge keeps it, and the faces the other meshes
have on it join its row: the edge's sides are then chosen among all of them, and the
later meshes drop their copies of the row.

Where meshes must be taken as one instead (the outlines, drawn edge by edge; the pixel
pairs' walk from face to face), ``welded_groups`` joins the meshes that share an edge or
meet at a T-junction (``t_junction_pairs``: a vertex of one inside an open edge of the
other) and welds each group as one mesh (``as_one_mesh``, ``WeldedMeshes``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from render.scene.scene import Mesh, Scene
from render.trace.topology import (
    MeshEdges,
    mesh_edges,
    open_rows_of,
    points_inside,
    row_ids,
    seam_distance,
    seam_reach,
    welded_ids,
)


@dataclass
class SharedEdges:
    """What other meshes add to one mesh's ``EdgeTable`` (E rows).

    owned (E,) bool: the mesh counts the row's edge (False: a mesh earlier in
        ``scene.meshes`` has the same edge and counts it, with this mesh's faces).
    faces (E, M) int64: global primitive ids of the faces that later meshes have on the
        edge (-1 padding; M may be 0).
    thirds (E, M, 3) float64: those faces' corners off the edge (positions: the vertices
        belong to other meshes).
    """

    owned: np.ndarray
    faces: np.ndarray
    thirds: np.ndarray


def shared_edges(scene: Scene, topology) -> list[SharedEdges] | None:
    """``SharedEdges`` per mesh index of ``scene.meshes`` (``topology``: ``mesh_edges`` per
    mesh index, from the same vertex values), or None when no two meshes share an edge
    (then each mesh's table is the whole truth)."""
    meshes = scene.meshes
    vertices = [np.asarray(m.vertices.data, np.float64) for m in meshes]
    tables = [topology[k].table for k in range(len(meshes))]
    return shared_between(vertices, tables, [m.num_faces for m in meshes])


def shared_between(vertices: list, tables: list, n_faces: list) -> list[SharedEdges] | None:
    """``shared_edges`` of meshes given by their vertices (V_k, 3) float64, their tables
    (``EdgeTable``) and their numbers of faces (their faces' global ids follow one another
    in this order): one ``SharedEdges`` per mesh, or None."""
    if len(tables) < 2:
        return None
    every = np.concatenate(vertices)
    welded = welded_ids(every, *seam_tolerances(every, tables, vertices, every))
    starts = np.cumsum([0] + [len(v) for v in vertices])
    ends = [
        np.sort(np.stack([welded[t.i + s], welded[t.j + s]], axis=1), axis=1)
        for t, s in zip(tables, starts, strict=False)
    ]
    mesh = np.concatenate([np.full(len(t.i), k) for k, t in enumerate(tables)])
    row = np.concatenate([np.arange(len(t.i)) for t in tables])
    group = row_ids(np.concatenate(ends))
    order = np.lexsort((row, mesh, group))  # by edge, then mesh, then row
    g = group[order]
    first = np.r_[True, g[1:] != g[:-1]]
    if first.all():
        return None
    owner = order[np.maximum.accumulate(np.where(first, np.arange(len(g)), 0))]
    copies = order[~first]  # rows that join their edge's owner
    owner = owner[~first]
    firsts = np.cumsum([0, *n_faces])

    # One entry per (copy row, face on it): the owner it joins, its global id, its third.
    join, face, third = [], [], []
    for k, table in enumerate(tables):
        mine = np.flatnonzero(mesh[copies] == k)
        if len(mine) == 0:
            continue
        local = row[copies[mine]]
        f, t = table.faces[local], table.thirds[local]
        valid = f >= 0
        join.append(np.broadcast_to(owner[mine][:, None], f.shape)[valid])
        face.append(f[valid] + firsts[k])
        third.append(vertices[k][t[valid]])
    join, face, third = np.concatenate(join), np.concatenate(face), np.concatenate(third)
    by_owner = np.argsort(join, kind="stable")
    join, face, third = join[by_owner], face[by_owner], third[by_owner]
    start = np.flatnonzero(np.r_[True, join[1:] != join[:-1]])
    count = np.diff(np.r_[start, len(join)])
    rank = np.arange(len(join)) - np.repeat(start, count)
    width = int(count.max())

    out, offset = [], 0
    for k, table in enumerate(tables):
        n = len(table.i)
        owned = np.ones(n, bool)
        owned[row[copies[mesh[copies] == k]]] = False
        faces = np.full((n, width), -1, np.int64)
        thirds = np.zeros((n, width, 3))
        here = (join >= offset) & (join < offset + n)
        faces[join[here] - offset, rank[here]] = face[here]
        thirds[join[here] - offset, rank[here]] = third[here]
        out.append(SharedEdges(owned, faces, thirds))
        offset += n
    return out


def welded_groups(meshes: list[Mesh], topology, shared, first) -> list[tuple[list[int], MeshEdges]]:
    """The meshes (indices) in groups that are welded into one: meshes that share an edge
    (``shared``: ``render.trace.seams.shared_edges`` of the meshes' ``topology``; ``first``
    (M + 1,): each mesh's first global face id) or meet at a T-junction (a vertex of one
    inside an open edge of the other: a fin tessellated otherwise than the plate it hangs
    from, ``t_junction_pairs``), and the meshes joined to those, and so on; each group (in
    the order of its first mesh) with its welded ``MeshEdges``, the group's meshes taken as
    one (their vertices, then their faces, concatenated; the table cut at its T-junctions,
    ``render.trace.topology.cut_at_t_junctions``)."""
    parent = list(range(len(meshes)))

    def root(k: int) -> int:
        while parent[k] != k:
            k = parent[k]
        return k

    def join(k: int, o: int) -> None:
        low, high = sorted((root(k), root(o)))
        parent[high] = low

    for k, joined in enumerate(shared or []):
        faces = joined.faces[joined.faces >= 0]  # other meshes' faces on mesh k's edges
        for o in np.unique(np.searchsorted(first, faces, side="right") - 1):
            join(k, int(o))
    for k, o in t_junction_pairs(meshes, topology):
        join(k, o)
    groups: dict[int, list[int]] = {}
    for k in range(len(meshes)):
        groups.setdefault(root(k), []).append(k)
    return [
        (group, topology[group[0]] if len(group) == 1 else edges_as_one(meshes, group, topology))
        for group in sorted(groups.values())
    ]


def edges_as_one(meshes: list[Mesh], members, topology) -> MeshEdges:
    """The ``MeshEdges`` of the meshes ``members`` (indices into ``meshes``; ``topology``:
    each mesh's ``mesh_edges``) taken as one (``as_one_mesh``): welded within
    ``seam_distance`` (of all ``meshes``) where their open edges end, cut at their
    T-junctions."""
    vertices, faces = as_one_mesh([meshes[o] for o in members])
    every = as_one_mesh(meshes)[0]
    reach, near = seam_tolerances(vertices, [topology[o].table for o in members],
                                  [meshes[o].vertices.data for o in members], every)  # fmt: skip
    return mesh_edges(vertices, faces, reach, near, seam_distance(every))


def t_junction_pairs(meshes: list[Mesh], topology) -> set[tuple[int, int]]:
    """The pairs of meshes (indices) where a vertex of one lies inside an open edge of the
    other (``render.trace.topology``'s test, on every mesh's open edges at once)."""
    if len(meshes) < 2:
        return set()
    vertices, _ = as_one_mesh(meshes)
    offsets = np.cumsum([0] + [len(m.vertices.data) for m in meshes])
    i, j = open_rows_ends([edges.table for edges in topology], [m.vertices.data for m in meshes])
    if len(i) < 2:
        return set()
    floor = seam_distance(vertices)
    ends = np.unique(np.r_[i, j])
    reach = seam_reach(vertices, i, j, floor)
    found = points_inside(vertices, i, j, ends, welded_ids(vertices, reach, ends), floor)
    if found is None:
        return set()
    segment, point, _ = found
    edge_mesh = np.searchsorted(offsets, i[segment], side="right") - 1
    point_mesh = np.searchsorted(offsets, point, side="right") - 1
    return {(int(a), int(b)) for a, b in zip(edge_mesh, point_mesh, strict=True) if a != b}


def open_rows_ends(tables: list, vertices: list) -> tuple[np.ndarray, np.ndarray]:
    """The ends (i (n,), j (n,)) of the open rows (one face) of meshes' ``tables``
    (``EdgeTable``), as ids among their ``vertices`` (V_k, 3) concatenated: where meshes
    can meet."""
    offsets = np.cumsum([0] + [len(v) for v in vertices])
    i, j = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    for table, offset in zip(tables, offsets, strict=False):
        rows = open_rows_of(table)
        i.append(table.i[rows] + offset)
        j.append(table.j[rows] + offset)
    return np.concatenate(i), np.concatenate(j)


def seam_tolerances(vertices: np.ndarray, tables: list, parts: list, every: np.ndarray):
    """For meshes taken as one, their vertices (V, 3) ``vertices`` (the meshes' ``parts``
    (V_k, 3) concatenated) with their ``tables``: each vertex's ``seam_reach`` (V,) (its
    floor the ``seam_distance`` of ``every``, all the scene's meshes' vertices), and the
    ends of the open rows (ids among ``vertices``), where meshes can meet."""
    i, j = open_rows_ends(tables, parts)
    return seam_reach(vertices, i, j, seam_distance(every)), np.r_[i, j]


def as_one_mesh(meshes: list[Mesh]) -> tuple[np.ndarray, np.ndarray]:
    """The vertices (V, 3) float64 and faces (F, 3) of ``meshes`` taken as one mesh (their
    vertices, then their faces, concatenated)."""
    offsets = np.cumsum([0] + [len(m.vertices.data) for m in meshes])
    vertices = np.concatenate([np.asarray(m.vertices.data, np.float64) for m in meshes])
    faces = [np.asarray(m.faces) + s for m, s in zip(meshes, offsets[:-1], strict=True)]
    return vertices, np.concatenate(faces)


@dataclass
class WeldedMeshes:
    """The meshes of one ``welded_groups`` group taken as one, for a walk across their
    faces: their indices in ``scene.meshes`` (``meshes``), their ``MeshEdges``, vertices
    (V, 3) float64 and faces (F, 3) (``as_one_mesh``), and per face its global primitive id
    ``face_ids`` (F,) and its mesh ``face_mesh`` (F,) (an index into ``scene.meshes``)."""

    meshes: list[int]
    edges: MeshEdges
    vertices: np.ndarray
    faces: np.ndarray
    face_ids: np.ndarray
    face_mesh: np.ndarray


@dataclass
class WeldedScene:
    """A scene's meshes in ``WeldedMeshes`` groups, and where each mesh's faces are in its
    group: ``group_of`` (M,) its group, ``offset`` (M,) the group-local id of its first
    face, ``first`` (M + 1,) the global id of its first face (the meshes' faces come first
    among the primitives, mesh after mesh)."""

    groups: list[WeldedMeshes]
    group_of: np.ndarray
    offset: np.ndarray
    first: np.ndarray

    @classmethod
    def of(cls, scene: Scene, topology, shared) -> WeldedScene:
        """The groups of ``scene``'s meshes (``topology``: ``mesh_edges`` per mesh index;
        ``shared``: their ``shared_edges``)."""
        meshes = scene.meshes
        first = np.cumsum([0] + [m.num_faces for m in meshes])
        group_of = np.zeros(len(meshes), np.int64)
        offset = np.zeros(len(meshes), np.int64)
        groups = []
        topology = [topology[k] for k in range(len(meshes))]
        for g, (members, edges) in enumerate(welded_groups(meshes, topology, shared, first)):
            vertices, faces = as_one_mesh([meshes[k] for k in members])
            counts = [meshes[k].num_faces for k in members]
            group_of[members] = g
            offset[members] = np.cumsum([0, *counts[:-1]])
            face_ids = np.concatenate([np.arange(first[k], first[k + 1]) for k in members])
            face_mesh = np.repeat(np.asarray(members, np.int64), counts)
            groups.append(WeldedMeshes(members, edges, vertices, faces, face_ids, face_mesh))
        return cls(groups, group_of, offset, first)

    def locate(self, prim: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For triangles ``prim`` (n,) (global ids below ``first[-1]``): their groups (n,)
        and their ids in them (n,)."""
        mesh = np.searchsorted(self.first, prim, side="right") - 1
        return self.group_of[mesh], prim - self.first[mesh] + self.offset[mesh]
