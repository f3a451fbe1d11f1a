"""``render.trace.outlines``: the curves that can be outlines seen from a point, found once
for the direct renderer's shadow borders and the path integrator's secondary term."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import ConvexHull

import minidiff as md
import render
from render.edges.boundary.shadow_tracing import _light_silhouettes
from render.path import render_path
from render.path.boundary.silhouettes import Curves
from render.path.sample.tracer import PathSampler
from render.scene.cornell import grid_quad
from render.scene.placement import placed
from render.trace import outlines
from render.trace.outlines import Outlines, one_sided
from render.trace.primitives import first_sphere_id, scene_primitives
from render.trace.visibility import scene_size
from tests.render.edges.test_t_junctions import boxes_in_meshes

GREY = render.Material((0.5, 0.5, 0.5))
X, Y, Z = np.eye(3)


def outlines_of(scene: render.Scene) -> Outlines:
    world = placed(scene)
    primitives = scene_primitives(world)
    return Outlines.of(world, primitives[0], scene_size(primitives))


def hull(seed: int) -> render.Mesh:
    """A closed convex mesh: the hull of 12 random points in the unit ball, every face
    wound outward (its normal away from the centroid)."""
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(12, 3))
    points /= np.linalg.norm(points, axis=1, keepdims=True) / rng.uniform(0.5, 1.0, (12, 1))
    faces = ConvexHull(points).simplices.copy()
    corners = points[faces]
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    inward = np.sum(normal * (corners.mean(axis=1) - points.mean(axis=0)), axis=1) < 0
    faces[~inward] = faces[~inward][:, [0, 2, 1]]
    return render.Mesh(points, faces, GREY)


def turning_edges(mesh: render.Mesh, facing) -> set[frozenset]:
    """The edges (as sets of their two vertex ids) between a face that ``facing`` (F,)
    says faces the light and one that faces away: the textbook rule for a closed mesh."""
    faces = np.asarray(mesh.faces)
    by_edge: dict[frozenset, list[int]] = {}
    for f, (i, j, k) in enumerate(faces):
        for edge in ((i, j), (j, k), (k, i)):
            by_edge.setdefault(frozenset(map(int, edge)), []).append(f)
    return {e for e, (f, g) in by_edge.items() if facing[f] != facing[g]}


def scene_of(mesh: render.Mesh, light: render.Light) -> render.Scene:
    camera = render.Camera((0.0, 0.0, 6.0), (0.0, 0.0, 0.0), (0, 1, 0), 40.0, 8, 8)
    return render.Scene([mesh], [light], camera)


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 2**16),
    where=st.tuples(*[st.floats(-1.0, 1.0)] * 3).filter(lambda v: np.linalg.norm(v) > 0.1),
    directional=st.booleans(),
)
def test_the_outlines_seen_from_a_light_are_the_edges_where_the_faces_turn(
    seed, where, directional
):
    """On a closed, outward-wound mesh, the edges ``one_sided`` keeps for a point light (3
    to 6 from the centre) or a distant light are those between a face turned towards the
    light and one turned away; the direct renderer's shadow borders start from exactly
    those (``_light_silhouettes``)."""
    mesh = hull(seed)
    w = np.asarray(where) / np.linalg.norm(where)
    if directional:
        light = render.DirectionalLight(-w, 1.0)
    else:
        light = render.PointLight(w * (3.0 + 3.0 * abs(where[0])), 1.0)
    corners = np.asarray(mesh.vertices.data)[np.asarray(mesh.faces)]
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    facing = np.sum(normal * light.towards(corners[:, 0]), axis=1) > 0
    want = turning_edges(mesh, facing)

    outlines = outlines_of(scene_of(mesh, light))
    m, base = light.edge_plane(outlines.a, outlines.b)
    kept = one_sided(m, base, outlines.c)[0]
    assert {frozenset(map(int, e)) for e in outlines.ends[kept]} == want
    occluder = _light_silhouettes(outlines, light, first_sphere=mesh.num_faces)[0]
    assert {frozenset(map(int, row[1:])) for row in occluder} == want


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**16), height=st.floats(2.5, 6.0))
def test_a_soft_shadows_edges_seen_from_a_point_lights_place_are_its_shadow_borders(seed, height):
    """The path integrator's curves seen from a point (``Curves.silhouettes``, the apex at
    a point light's position) are the direct renderer's shadow borders' occluder edges for
    that light: one module finds both."""
    light = render.PointLight((0.3, height, -0.2), 1.0)
    v, f = grid_quad((0.0, -1.5, 0.0), 3.0 * X, -3.0 * Z)
    floor = render.Mesh(v, f, GREY)
    scene = render.Scene([hull(seed), floor], [light], scene_of(hull(seed), light).camera)
    world = placed(scene)
    curves = Curves.of(PathSampler(world, 1, 2, 100, 0))
    angle, _ = curves.silhouettes(np.asarray(light.position.data, np.float64)[None])
    from_path = np.flatnonzero(angle[0, : curves.n_edges] > 0)
    occluder = _light_silhouettes(curves, light, first_sphere_id(world))[0]
    rows = np.column_stack([curves.edge_object, curves.ends])[from_path]
    np.testing.assert_array_equal(occluder[occluder[:, 0] >= 0], rows)


def test_a_mesh_of_lone_triangles_has_border_edges_only_and_its_soft_shadow_renders():
    """A mesh whose edges each have one face (a lone triangle: every edge a border, an
    outline from anywhere) over a floor: its three edges, the third corner on both sides.
    Until the outlines were found here, the path integrator's secondary term failed on it
    (an index past the edge table's one column)."""
    v = np.array([[-0.3, 0.5, -0.3], [0.3, 0.5, -0.3], [0.0, 0.5, 0.3]])
    triangle = render.Mesh(v, np.array([[0, 1, 2]]), GREY)
    v, f = grid_quad((0.0, 0.0, 0.0), 1.5 * X, -1.5 * Z)
    light = render.PointLight((0.0, 1.5, 0.1), 3.0)
    camera = render.Camera((0.05, 1.2, 0.05), (0.0, 0.0, 0.0), (0, 0, -1), 90.0, 8, 8)
    scene = render.Scene([triangle, render.Mesh(v, f, GREY)], [light], camera)
    outlines = outlines_of(scene)
    mine = outlines.edge_object == 0
    assert sorted(map(sorted, outlines.ends[mine].tolist())) == [[0, 1], [0, 2], [1, 2]]
    for (i, j), c in zip(outlines.ends[mine], outlines.c[mine], strict=True):
        third = v_third = np.asarray(triangle.vertices.data)[3 - i - j]
        np.testing.assert_array_equal(c, [third, v_third])

    scene.lights[0].position.requires_grad = True
    image = render_path(scene, spp=2, max_depth=2, seed=0, antialias="secondary")
    md.sum(image).backward()
    assert np.all(np.isfinite(scene.lights[0].position.grad))
    assert np.any(scene.lights[0].position.grad != 0)


def on_some_triangle(points, triangles, tolerance) -> np.ndarray:
    """NumPy statement of ``on_triangle`` for every point (k, 3) and triangle (T, 3, 3)
    pair: (k,) bool, the point within ``tolerance`` of some triangle."""
    v0, e1, e2 = (
        triangles[:, 0],
        triangles[:, 1] - triangles[:, 0],
        triangles[:, 2] - triangles[:, 0],
    )
    normal = np.cross(e1, e2)
    area = np.linalg.norm(normal, axis=1)
    d = points[:, None] - v0[None]  # (k, T, 3)
    near = np.abs(np.sum(d * normal, axis=2)) <= tolerance * area
    d11, d12, d22 = (np.sum(x * y, axis=1) for x, y in ((e1, e1), (e1, e2), (e2, e2)))
    p1, p2 = np.sum(d * e1, axis=2), np.sum(d * e2, axis=2)
    with np.errstate(divide="ignore", invalid="ignore"):
        det = d11 * d22 - d12 * d12
        u, v = (d22 * p1 - d12 * p2) / det, (d11 * p2 - d12 * p1) / det
        margin = tolerance * (np.linalg.norm(e1, axis=1) + np.linalg.norm(e2, axis=1)) / area
        inside = (u >= -margin) & (v >= -margin) & (u + v <= 1 + margin)
    return np.any((area > 0) & near & inside, axis=1)


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    n_small=st.integers(0, 300),
    n_large=st.integers(0, 3),
    tolerance=st.sampled_from([1e-9, 1e-5, 1e-2]),
)
def test_the_grid_finds_the_points_on_triangles_that_testing_every_pair_finds(
    seed, n_small, n_large, tolerance
):
    """``_touching`` (each point against the triangles listed in its grid cell, and the
    large ones) against every pair tested in NumPy: small triangles of many sizes, a few
    spanning the whole soup, degenerate ones; points on triangles, just off them by
    fractions and multiples of the tolerance, and anywhere."""
    from render.trace.outlines import CONTACT, _touching

    rng = np.random.default_rng(seed)
    centre = rng.uniform(-1, 1, (n_small, 1, 3))
    scale = 10.0 ** rng.uniform(-3, -0.5, (n_small, 1, 1))
    small = centre + scale * rng.normal(size=(n_small, 3, 3))
    large = rng.uniform(-3, 3, (n_large, 3, 3))
    triangles = np.concatenate([small, large, small[:2, [0, 0, 1]]])  # and two degenerate
    rng.shuffle(triangles)
    picked = (
        triangles[rng.integers(0, len(triangles), 200)] if len(triangles) else np.zeros((0, 3, 3))
    )
    u, v = rng.uniform(0, 1, (2, len(picked), 1))
    flip = (u + v > 1)[:, 0]
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    on = picked[:, 0] + u * (picked[:, 1] - picked[:, 0]) + v * (picked[:, 2] - picked[:, 0])
    off = rng.normal(size=on.shape) * tolerance * rng.choice([0.3, 1.0, 3.0], (len(on), 1))
    points = np.concatenate([on + off, rng.uniform(-1.5, 1.5, (100, 3))])
    size = tolerance / CONTACT
    want = on_some_triangle(points, triangles, tolerance)
    for few_pairs in (0, outlines._FEW_PAIRS):  # the grid, and pair by pair (NumPy)
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(outlines, "_FEW_PAIRS", few_pairs)
            got = _touching(points, [], triangles, np.array([0, len(triangles)]), size)
        np.testing.assert_array_equal(got, want)
    assert 0 < want.sum() < len(points) or len(triangles) == 0


@settings(max_examples=20, deadline=None)
@given(boxes_in_meshes())
def test_the_outlines_ends_are_the_vertices_at_their_ends(case):
    """Every outline's ``ends`` are the rows of every mesh's vertices (mesh after mesh) at
    its ends ``a`` and ``b``, also where meshes meet at a T-junction, so that an edge is
    cut at another mesh's vertex (before, an end was counted among its first end's mesh's
    vertices: an index past them, or another mesh's vertex, once the meshes that meet were
    not neighbours in ``scene.meshes``)."""
    _, meshes = case
    v, f = grid_quad((0, 0, 0), np.array([1.5, 0, 0]), np.array([0, 0, -1.5]))
    floor = render.Mesh(v, f, render.Material((0.5, 0.5, 0.5)))
    camera = render.Camera((0.6, 1.3, 1.1), (0, 0.3, 0), (0, 1, 0), 45.0, 8, 8)
    scene = render.Scene([*meshes, floor], [], camera)
    found = outlines_of(scene)
    vertices = np.concatenate([np.asarray(m.vertices.data) for m in scene.meshes])
    assert found.n_edges > 0
    np.testing.assert_array_equal(vertices[found.ends[:, 0]], found.a)
    np.testing.assert_array_equal(vertices[found.ends[:, 1]], found.b)
