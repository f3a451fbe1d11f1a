"""Tests for render.teapot: the tessellation promised by docs/paper_scene.md."""

import json
from pathlib import Path

import numpy as np
import pytest

import minidiff
from render.scene.scene import Mesh, PointLight, Scene
from render.scene.teapot import paper_scene, teapot, teapot_geometry

DATA = Path(__file__).parents[3] / "render" / "scene" / "data" / "newell_teapot.json"


def place(p: np.ndarray) -> np.ndarray:
    """The paper's placement of z-up control points: 0.5 * (x, z, -y) + (0, -0.5, 0)."""
    return 0.5 * np.stack([p[..., 0], p[..., 2], -p[..., 1]], axis=-1) + [0.0, -0.5, 0.0]


def normals_and_centroids(vertices, faces):
    tri = vertices[faces]
    return np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), tri.mean(axis=1)


@pytest.mark.parametrize(
    ("nu", "nv", "n_faces", "n_vertices"),
    [
        (4, 6, 1536, 1120),
        (8, 13, 6656, 32 * 9 * 14),
        (1, 1, 64, 128),
        (26, 60, 99840, 32 * 27 * 61),
    ],
)
def test_counts(nu, nv, n_faces, n_vertices):
    vertices, faces = teapot_geometry(nu, nv)
    assert vertices.shape == (n_vertices, 3) and vertices.dtype == np.float64
    assert faces.shape == (n_faces, 3) and faces.dtype == np.int64
    assert faces.min() == 0 and faces.max() == n_vertices - 1


def test_patch_corners_interpolate_control_points():
    """Bezier endpoint property: each patch's grid corners are its corner control points."""
    data = json.loads(DATA.read_text())
    control = np.asarray(data["vertices"])[np.asarray(data["patches"])].reshape(32, 4, 4, 3)
    nu, nv = 4, 6
    grid = teapot_geometry(nu, nv)[0].reshape(32, nu + 1, nv + 1, 3)
    for (i, j), (a, b) in [
        ((0, 0), (0, 0)),
        ((0, nv), (0, 3)),
        ((nu, 0), (3, 0)),
        ((nu, nv), (3, 3)),
    ]:
        np.testing.assert_allclose(grid[:, i, j], place(control[:, a, b]), atol=1e-12)


def test_first_cell_winding_matches_spec():
    nv = 6
    _, faces = teapot_geometry(4, nv)
    p = lambda i, j: i * (nv + 1) + j  # noqa: E731
    np.testing.assert_array_equal(faces[0], [p(0, 0), p(1, 1), p(1, 0)])
    np.testing.assert_array_equal(faces[1], [p(0, 0), p(0, 1), p(1, 1)])
    np.testing.assert_array_equal(faces[48], faces[0] + 35)  # next patch: offset by 5 x 7


def test_normals_point_outward():
    vertices, faces = teapot_geometry()
    n, c = normals_and_centroids(vertices, faces)
    ok = np.linalg.norm(n, axis=1) > 1e-12
    patch = np.arange(len(faces)) // 48
    centre = (vertices.min(axis=0) + vertices.max(axis=0)) / 2
    outward = np.einsum("ij,ij->i", n, c - centre) > 0
    assert outward[ok].mean() > 0.75  # spout/handle/rim inner sides face the centre
    # The body (patches 4-11) is a surface of revolution about the y axis: all radial.
    body = ok & (patch >= 4) & (patch < 12)
    radial = c * [1.0, 0.0, 1.0]
    assert (np.einsum("ij,ij->i", n[body], radial[body]) > 0).all()
    # The bottom (patches 28-31) faces down.
    bottom = ok & (patch >= 28)
    assert (n[bottom, 1] < 0).all()


def test_degenerate_triangles_few_and_finite():
    vertices, faces = teapot_geometry()
    assert np.isfinite(vertices).all()
    n, _ = normals_and_centroids(vertices, faces)
    area = 0.5 * np.linalg.norm(n, axis=1)
    degenerate = area < 1e-12
    assert 0 < degenerate.sum() <= 64  # collapsed patch edges at the lid knob and bottom
    assert len(np.unique(vertices[faces[degenerate]].reshape(-1, 3), axis=0)) < 3 * 64


def test_bounding_box():
    vertices, _ = teapot_geometry()
    np.testing.assert_allclose(vertices.min(axis=0), [-1.5, -0.5, -1.0], atol=1e-9)
    # Spout tip at x = 0.5 * 3.4, lid knob at y = 0.5 * 3.15 - 0.5 (tessellated: slightly less).
    np.testing.assert_allclose(vertices.max(axis=0), [1.714, 1.075, 1.0], atol=0.01)


def test_bad_resolution():
    with pytest.raises(ValueError, match="nu must be >= 1"):
        teapot_geometry(0, 6)
    with pytest.raises(TypeError, match="nv must be an int"):
        teapot_geometry(4, 6.0)


def test_teapot_mesh_default_material():
    mesh = teapot()
    assert isinstance(mesh, Mesh) and mesh.num_faces == 1536 and not mesh.smooth
    np.testing.assert_array_equal(mesh.material.albedo.data, [0.7, 0.3, 0.3])
    assert float(mesh.material.specular.data) == 0.0 and float(mesh.material.ambient.data) == 0


def test_paper_scene():
    scene = paper_scene()
    assert isinstance(scene, Scene) and len(scene.meshes) == 1 and not scene.spheres
    cam = scene.camera
    np.testing.assert_array_equal(cam.position.data, [3, 2, 5])
    np.testing.assert_array_equal(cam.look_at.data, [0, 0, 0])
    np.testing.assert_array_equal(cam.up.data, [0, 1, 0])
    assert float(cam.fov.data) == pytest.approx(39.5978, abs=1e-4)
    assert (cam.width, cam.height) == (512, 512)
    (light,) = scene.lights
    assert isinstance(light, PointLight)
    np.testing.assert_array_equal(light.position.data, [2, 5, 3])
    assert float(light.intensity.data) == 100.0
    np.testing.assert_array_equal(light.color.data, [1, 1, 1])
    np.testing.assert_array_equal(scene.background.data, [0, 0, 0])
    assert scene.meshes[0].num_faces == 1536


def test_paper_scene_keeps_user_tensors():
    light_pos = minidiff.tensor([1.0, 4.0, 2.0], requires_grad=True)
    intensity = minidiff.tensor(150.0, requires_grad=True)
    albedo = minidiff.tensor([0.2, 0.5, 0.8], requires_grad=True)
    cam_pos = minidiff.tensor([3.5, 2.5, 5.0], requires_grad=True)
    scene = paper_scene(
        width=64, height=48, light_position=light_pos, light_intensity=intensity,
        albedo=albedo, camera_position=cam_pos, nu=8, nv=13,
    )  # fmt: skip
    assert scene.lights[0].position is light_pos and scene.lights[0].intensity is intensity
    assert scene.meshes[0].material.albedo is albedo and scene.camera.position is cam_pos
    assert (scene.camera.width, scene.camera.height) == (64, 48)
    assert scene.meshes[0].num_faces == 6656
