"""The one surface interaction (``render.shade.surface.surface_at``): the same point found by a
ray and placed by its coordinates on the primitive is the same ``Surface``; what each form
adds (the normals facing the rays, the area element) is what it says."""

from __future__ import annotations

import numpy as np
import pytest

import minidiff as md
from render.scene.scene import Material, Mesh, Sphere
from render.shade.surface import geometric_normals, surface_at

RNG_SEED = 4


def _mesh(rng: np.random.Generator, smooth: bool, textured: bool) -> Mesh:
    """Four random triangles (corners within the unit cube), random vertex normals and UVs."""
    vertices = rng.uniform(-1.0, 1.0, (12, 3))
    normals = rng.standard_normal((12, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    texture = rng.uniform(0.0, 1.0, (4, 4, 3)) if textured else None
    return Mesh(vertices, np.arange(12).reshape(4, 3), Material((0.5, 0.5, 0.5), texture=texture),
                normals=normals, uvs=rng.uniform(0.0, 1.0, (12, 2)), smooth=smooth)  # fmt: skip


def _rays_to(points: np.ndarray, rng: np.random.Generator):
    """Origins (k, 3) off to one side and directions (k, 3) of rays through ``points``."""
    origins = points + rng.uniform(1.0, 2.0, (len(points), 1)) * rng.standard_normal(points.shape)
    return md.tensor(origins), md.tensor(points - origins)


@pytest.mark.parametrize("smooth, textured", [(False, False), (True, False), (True, True)])
def test_a_point_found_by_a_ray_is_the_point_placed_on_the_triangle(smooth, textured):
    rng = np.random.default_rng(RNG_SEED)
    mesh = _mesh(rng, smooth, textured)
    faces = np.array([0, 1, 2, 3, 3, 1])
    u = rng.uniform(0.05, 0.5, len(faces))
    v = rng.uniform(0.05, 0.45, len(faces))
    local = np.stack([u, v, np.zeros_like(u)], axis=1)
    placed = surface_at(mesh, faces, local=local)
    origins, directions = _rays_to(placed.points.data, rng)
    for divide in (False, True):
        found = surface_at(mesh, faces, origins, directions, divide=divide)
        np.testing.assert_allclose(found.points.data, placed.points.data, atol=1e-12)
        np.testing.assert_allclose(found.geometric.data, placed.geometric.data, atol=1e-15)
        np.testing.assert_allclose(found.shading.data, placed.shading.data, atol=1e-12)
        if textured:
            np.testing.assert_allclose(found.uv.data, placed.uv.data, atol=1e-12)
        assert found.stretch is None and found.directions is directions
    corners = mesh.vertices.data[mesh.faces[faces]]
    twice_area = np.linalg.norm(
        np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1
    )
    np.testing.assert_allclose(placed.stretch.data, twice_area, rtol=1e-14)
    assert placed.normals is None and placed.directions is None and placed.front is None
    if not smooth:
        assert placed.shading is placed.geometric


def test_normals_face_the_rays_and_front_says_which_side_they_meet():
    rng = np.random.default_rng(RNG_SEED + 1)
    mesh = _mesh(rng, smooth=False, textured=False)
    faces = np.repeat(np.arange(4), 8)
    local = np.concatenate([rng.uniform(0.1, 0.4, (len(faces), 2)), np.zeros((32, 1))], axis=1)
    points = surface_at(mesh, faces, local=local).points.data
    origins, directions = _rays_to(points, rng)
    found = surface_at(mesh, faces, origins, directions)
    cos = np.sum(found.normals.data * directions.data, axis=1)
    assert np.all(cos < 0)  # towards where the ray came from
    meets_front = np.sum(found.geometric.data * directions.data, axis=1) < 0
    np.testing.assert_array_equal(found.front.data, meets_front * 1.0)
    assert meets_front.any() and not meets_front.all()  # both sides were met


def test_a_point_placed_on_a_triangle_moves_with_its_corners():
    """d point / d corner = the corner's barycentric weight (1 - u - v, u, v)."""
    rng = np.random.default_rng(RNG_SEED + 2)
    mesh = _mesh(rng, smooth=False, textured=False)
    mesh.vertices.requires_grad = True
    u, v = 0.2, 0.3
    placed = surface_at(mesh, np.array([1]), local=np.array([[u, v, 0.0]]))
    md.sum(placed.points).backward()
    expected = np.zeros((12, 3))
    expected[3:6] = np.array([1.0 - u - v, u, v])[:, None]
    np.testing.assert_allclose(mesh.vertices.grad, expected, atol=1e-15)


def test_a_sphere_point_by_ray_and_by_direction_from_the_centre():
    rng = np.random.default_rng(RNG_SEED + 3)
    sphere = Sphere((0.3, -0.2, 0.5), 0.7, Material((0.5, 0.5, 0.5)))
    w = rng.standard_normal((16, 3))
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    placed = surface_at(sphere, np.zeros(16, np.int64), local=w)
    np.testing.assert_allclose(placed.stretch.data, np.full(16, 0.49), rtol=1e-15)
    # From outside, aimed at the point from the side it faces: the near root.
    origins = md.tensor(placed.points.data + rng.uniform(0.5, 2.0, (16, 1)) * w)
    directions = md.tensor(placed.points.data - origins.data)
    found = surface_at(sphere, np.zeros(16, np.int64), origins, directions)
    np.testing.assert_allclose(found.points.data, placed.points.data, atol=1e-12)
    np.testing.assert_allclose(found.geometric.data, w, atol=1e-12)
    assert np.all(found.front.data == 1.0)
    # From the centre (inside): the far root, met from the back.
    centre = md.tensor(np.broadcast_to(sphere.center.data, (16, 3)).copy())
    inside = surface_at(sphere, np.zeros(16, np.int64), centre, md.tensor(w))
    np.testing.assert_allclose(inside.points.data, placed.points.data, atol=1e-12)
    assert np.all(inside.front.data == 0.0)


def test_plain_geometric_normals_are_the_taped_ones():
    rng = np.random.default_rng(RNG_SEED + 4)
    mesh = _mesh(rng, smooth=False, textured=False)
    sphere = Sphere((0.1, 0.2, 0.3), 0.5, Material((0.5, 0.5, 0.5)))
    faces = np.array([0, 2, 3])
    local = np.array([[0.2, 0.3, 0.0], [0.1, 0.1, 0.0], [0.5, 0.2, 0.0]])
    on_mesh = surface_at(mesh, faces, local=local)
    on_sphere = surface_at(sphere, np.zeros(2, np.int64), local=np.eye(3)[:2])
    primitives = (
        mesh.vertices.data[mesh.faces],
        sphere.center.data[None],
        sphere.radius.data[None],
    )
    prims = np.array([0, 2, 3, 4, 4])  # the triangles' global ids, then the sphere's
    points = np.concatenate([on_mesh.points.data, on_sphere.points.data])
    plain = geometric_normals(primitives, prims, points)
    np.testing.assert_array_equal(plain[:3], on_mesh.geometric.data)  # n / |n|, as placed
    np.testing.assert_allclose(plain[3:], np.eye(3)[:2], atol=1e-15)
