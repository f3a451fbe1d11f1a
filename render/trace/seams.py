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
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from render.scene.scene import Scene
from render.trace.topology import _WELD_TOLERANCE, _scale, row_ids


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
    # Welded positions across meshes: no coarser than any one mesh's own welding, so that
    # no two vertices a mesh keeps apart are merged here.
    every = np.concatenate(vertices)
    tolerance = min(_scale(v) for v in vertices) * _WELD_TOLERANCE
    # Never below the coordinates' own rounding (a mesh collapsed to a point has size ~0):
    # positions closer than that are one position anyway, and the keys stay finite.
    tolerance = max(tolerance, 4 * np.finfo(np.float64).eps * float(np.abs(every).max()))
    if tolerance == 0.0:  # every vertex at the origin
        return None
    keys = np.round((every - every.min(axis=0)) / tolerance)
    welded = row_ids(keys)
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
