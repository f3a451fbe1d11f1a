"""Rays aimed at the edges and corners of closed meshes never slip between their faces.

A ray that crosses a closed mesh's surface at a point of an edge (or a vertex) must hit one
of the faces that meet there: the faces either side of an edge each test the ray against
that edge with their own arithmetic, and if both rounded it to their outside, the ray would
pass through a crack. The tracer's test (``render.trace.intersect.intersect_triangle``,
Woop, Benthin and Wald's watertight test) makes the two agree exactly; Moller-Trumbore,
which it replaced, let rays through (in one draw of this test's first version, 4 of the 66
aimed at an octahedron's edges). These draws hold the tracer
to it on convex meshes far from the origin (rounding grows with the coordinates), with
coordinates that are float64 or float32 values, and on bumpy closed meshes that need not
be convex, by the BVH and by brute force; both tests fail on Moller-Trumbore.
"""

from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from render.trace.accel import Accelerator

#: An octahedron wound outwards: every edge is shared by two faces, every corner by four.
CORNERS = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1.0]])
FACES = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5],
                  [0, 3, 5]])  # fmt: skip


def _edges_of(faces: np.ndarray) -> np.ndarray:
    """The (E, 2) corner pairs of the faces' edges, each once."""
    pairs = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return np.unique(np.sort(pairs, axis=1), axis=0)


def _hits_through_edges(corners, faces, rng, reach) -> list[tuple[bool, np.ndarray, np.ndarray]]:
    """Rays from outside through random points of the mesh's edges (a quarter of them at
    corners), each from a direction that every face at its point faces, from
    ``reach`` = (nearest, farthest) away along its direction; aimed so that t = 1 at the
    point. Their closest hits by the BVH and by brute force: [(use_bvh, prim, t)]."""
    triangles = corners[faces]
    normals = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    edges = _edges_of(faces)
    k = 300
    edge = edges[rng.integers(0, len(edges), k)]
    along = rng.random(k)
    along[: k // 4] = 0.0
    targets = corners[edge[:, 0]] + along[:, None] * (corners[edge[:, 1]] - corners[edge[:, 0]])
    directions = rng.normal(size=(k, 3))
    origins = targets - directions * rng.uniform(*reach, (k, 1))
    keep = np.zeros(k, bool)
    for i in range(k):  # the faces at the edge (at the corner) all face the ray
        meets = (faces == edge[i, 0]).any(axis=1)
        at = meets if along[i] == 0.0 else meets & (faces == edge[i, 1]).any(axis=1)
        n = normals[at]
        cosine = -(n @ directions[i]) / (np.linalg.norm(n, axis=1) * np.linalg.norm(directions[i]))
        keep[i] = np.all(cosine > 1e-3)
    assume(keep.sum() > 20)
    found = []
    for use_bvh in (True, False):
        prim, t, _, _ = Accelerator(triangles, use_bvh=use_bvh).closest_hit(
            origins[keep], targets[keep] - origins[keep]
        )
        found.append((use_bvh, prim, t))
    return found


def _rotation(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])  # fmt: skip


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**32 - 1),
    scales=st.tuples(*[st.floats(0.05, 20.0)] * 3),
    quaternion=st.tuples(*[st.floats(-1.0, 1.0)] * 4),
    distance=st.floats(0.0, 5.0),  # the mesh's offset from the origin: 10**distance
    single=st.booleans(),
)
def test_rays_through_edges_and_corners_of_a_closed_mesh_hit_it(
    seed, scales, quaternion, distance, single
):
    """Rays from outside through points of edges (anywhere along them) and corners, whose
    faces there all face the ray, hit the mesh there."""
    q = np.array(quaternion)
    assume(np.linalg.norm(q) > 0.1)
    rng = np.random.default_rng(seed)
    offset = rng.normal(size=3)
    corners = (CORNERS * np.array(scales)) @ _rotation(q).T
    corners += offset / np.linalg.norm(offset) * 10.0**distance
    if single:  # coordinates a float32 mesh file would hold
        corners = corners.astype(np.float32).astype(np.float64)
    for use_bvh, prim, t in _hits_through_edges(
        corners, FACES, rng, (2.0 * max(scales), 50.0 * max(scales))
    ):
        # The mesh is convex: the ray enters it at the target (t = 1), not through a crack
        # there to the far side.
        assert np.all(prim >= 0), (use_bvh, np.flatnonzero(prim < 0))
        np.testing.assert_allclose(t, 1.0, rtol=0, atol=1e-6, err_msg=f"use_bvh={use_bvh}")


def _midpoint(corners: list, middle: dict, i: int, j: int) -> int:
    """The index of the midpoint of corners i and j, added to ``corners`` the first time."""
    key = (min(i, j), max(i, j))
    if key not in middle:
        middle[key] = len(corners)
        corners.append((corners[i] + corners[j]) / 2)
    return middle[key]


def _subdivided(levels: int) -> tuple[np.ndarray, np.ndarray]:
    """The octahedron's faces split in four ``levels`` times, its corners pushed onto the
    unit sphere: (corners (V, 3), faces (F, 3)), wound outwards as the octahedron is."""
    corners, faces = list(CORNERS), [tuple(f) for f in FACES]
    for _ in range(levels):
        middle: dict[tuple[int, int], int] = {}
        split = []
        for a, b, c in faces:
            ab = _midpoint(corners, middle, a, b)
            bc = _midpoint(corners, middle, b, c)
            ca = _midpoint(corners, middle, c, a)
            split += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = split
    corners = np.array(corners)
    return corners / np.linalg.norm(corners, axis=1)[:, None], np.array(faces)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**32 - 1), bumps=st.floats(0.0, 0.4), distance=st.floats(0.0, 4.0))
def test_rays_through_edges_and_corners_of_a_bumpy_closed_mesh_stop_there(seed, bumps, distance):
    """A closed mesh that need not be convex (a sphere of 128 faces, each corner's radius
    drawn within ``bumps`` of 1): a ray from outside through a point of an edge, or a
    corner, whose faces there all face it crosses the surface there, so its first hit is
    there or nearer (t <= 1), never beyond through a crack."""
    rng = np.random.default_rng(seed)
    corners, faces = _subdivided(2)
    corners = corners * rng.uniform(1.0 - bumps, 1.0 + bumps, (len(corners), 1))
    offset = rng.normal(size=3)
    corners += offset / np.linalg.norm(offset) * 10.0**distance
    for use_bvh, prim, t in _hits_through_edges(corners, faces, rng, (3.0, 30.0)):
        assert np.all(prim >= 0), (use_bvh, np.flatnonzero(prim < 0))
        assert np.all(t <= 1.0 + 1e-6), (use_bvh, t[t > 1.0 + 1e-6])
