"""The scene's geometry as one list of primitives: what the tracers take, and their ids.

Every mesh triangle, in scene order, then every sphere: primitive id = position in that
list. The tracers (``render.trace.accel``, ``render.trace.raster``) answer with these ids;
the later stages map them back to objects with ``primitive_ranges`` / ``object_index_of``.
"""

from __future__ import annotations

import numpy as np

from render.scene.scene import Mesh, Scene, Sphere

#: triangles (T, 3, 3), sphere centres (S, 3), sphere radii (S,), all float64.
Primitives = tuple[np.ndarray, np.ndarray, np.ndarray]


def scene_primitives(scene: Scene) -> Primitives:
    """The current primitives as plain float64 arrays: triangles (T, 3, 3) of every mesh in
    scene order, then sphere centres (S, 3) and radii (S,). Primitive id = row, spheres
    numbered after the triangles (see ``primitive_ranges``)."""
    meshes, spheres = scene.meshes, scene.spheres
    triangles = (
        np.concatenate([m.triangles() for m in meshes]).astype(np.float64)
        if meshes
        else np.zeros((0, 3, 3))
    )
    centers = np.array([s.center.data for s in spheres], dtype=np.float64).reshape(-1, 3)
    radii = np.array([s.radius.data for s in spheres], dtype=np.float64).reshape(-1)
    return triangles, centers, radii


def primitive_ranges(scene: Scene) -> list[tuple[Mesh | Sphere, int, int]]:
    """(object, first primitive id, primitive count) per object, in the order of
    ``scene_primitives``: the triangles of every mesh, then the spheres."""
    ranges, first = [], 0
    for obj in scene.meshes + scene.spheres:
        count = obj.num_faces if isinstance(obj, Mesh) else 1
        ranges.append((obj, first, count))
        first += count
    return ranges


def first_sphere_id(scene: Scene) -> int:
    """The global primitive id of the first sphere: spheres follow all triangles, so it is
    also the number of triangles."""
    return sum(m.num_faces for m in scene.meshes)


def object_index_of(scene: Scene, prim: np.ndarray) -> np.ndarray:
    """(n,) the index in ``scene.meshes + scene.spheres`` of the object owning each
    primitive id (-1 for -1)."""
    counts = [m.num_faces for m in scene.meshes] + [1] * len(scene.spheres)
    starts = np.cumsum([0] + counts)
    return np.where(prim >= 0, np.searchsorted(starts, prim, side="right") - 1, -1)
