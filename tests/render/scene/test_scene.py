"""Tests for render.scene.scene: tensor storage convention and validation."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import minidiff
from render import Camera, DirectionalLight, Material, Mesh, PointLight, Scene, Sphere, Transform

TRI_V = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
TRI_F = np.array([[0, 1, 2]])


def grey() -> Material:
    return Material((0.5, 0.5, 0.5))


def triangle(**kwargs) -> Mesh:
    return Mesh(TRI_V, TRI_F, kwargs.pop("material", grey()), **kwargs)


def camera(**kwargs) -> Camera:
    kwargs.setdefault("position", (0, 0, 5))
    kwargs.setdefault("look_at", (0, 0, 0))
    return Camera(**kwargs)


# --- storage convention ----------------------------------------------------------------


def test_parameters_become_float64_tensors():
    cam = camera()
    for t in (cam.position, cam.look_at, cam.up, cam.fov):
        assert isinstance(t, minidiff.Tensor)
        assert t.dtype == np.float64
    assert cam.fov.shape == ()
    assert cam.position.shape == (3,)
    assert isinstance(cam.width, int) and isinstance(cam.height, int)

    mesh = triangle(uvs=np.zeros((3, 2)), normals=np.tile([0.0, 0.0, 1.0], (3, 1)))
    assert isinstance(mesh.vertices, minidiff.Tensor) and mesh.vertices.shape == (3, 3)
    assert isinstance(mesh.uvs, minidiff.Tensor) and isinstance(mesh.normals, minidiff.Tensor)
    assert type(mesh.faces) is np.ndarray and mesh.faces.dtype == np.int64

    mat = Material((0.1, 0.2, 0.3), specular=(0.1, 0.1, 0.1), ambient=0.05)
    assert mat.specular.shape == (3,) and mat.ambient.shape == () and mat.shininess.shape == ()
    scene = Scene([mesh], [PointLight((0, 5, 0), 10.0)], cam)
    assert isinstance(scene.background, minidiff.Tensor) and scene.background.shape == (3,)


def test_user_tensors_are_kept_by_identity():
    pos = minidiff.tensor([1.0, 4.0, 2.0], requires_grad=True)
    intensity = minidiff.tensor(150.0, requires_grad=True)
    albedo = minidiff.tensor([0.5, 0.5, 0.5], requires_grad=True)
    verts = minidiff.tensor(TRI_V, requires_grad=True)
    light = PointLight(pos, intensity)
    mat = Material(albedo)
    mesh = Mesh(verts, TRI_F, mat)
    assert light.position is pos and light.intensity is intensity
    assert mat.albedo is albedo and mesh.vertices is verts
    cam_pos = minidiff.tensor([3.0, 2.0, 5.0], requires_grad=True)
    assert Camera.from_focal_length(50.0, position=cam_pos, look_at=(0, 0, 0)).position is cam_pos


def test_from_focal_length():
    cam = Camera.from_focal_length(50.0, 36.0, position=(3, 2, 5), look_at=(0, 0, 0))
    assert float(cam.fov.data) == pytest.approx(math.degrees(2 * math.atan(18 / 50)))
    assert float(cam.fov.data) == pytest.approx(39.5978, abs=1e-4)
    assert (cam.width, cam.height) == (512, 512)
    with pytest.raises(ValueError, match="focal_mm"):
        Camera.from_focal_length(0.0, position=(0, 0, 1), look_at=(0, 0, 0))
    with pytest.raises(TypeError, match="focal_mm"):
        Camera.from_focal_length(minidiff.tensor(50.0), position=(0, 0, 1), look_at=(0, 0, 0))


def test_mesh_triangles_and_scene_properties():
    mesh = triangle()
    tris = mesh.triangles()
    assert tris.shape == (1, 3, 3)
    np.testing.assert_array_equal(tris[0], TRI_V)
    sphere = Sphere((0, 0, 0), 1.0, grey())
    scene = Scene([mesh, sphere], [DirectionalLight((0, -1, 0), 2.0)], camera())
    assert scene.meshes == [mesh] and scene.spheres == [sphere]
    assert "Scene(1 meshes, 1 spheres, 1 lights" in repr(scene)


def test_smooth_without_normals_is_legal():
    # The renderer then computes vertex normals from the current vertices.
    assert triangle(smooth=True).smooth


def test_degenerate_triangles_are_legal():
    verts = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]])  # collinear: zero area
    Mesh(verts, [[0, 1, 2], [0, 0, 0]], grey())


def test_validate_sees_in_place_changes():
    mesh = triangle()
    scene = Scene([mesh], [], camera())
    mesh.vertices.data[0, 0] = np.nan
    with pytest.raises(ValueError, match="Mesh: vertices contains NaN"):
        scene.validate()
    mesh.vertices.data[0, 0] = 0.0
    scene.camera.fov.data[...] = 200.0
    with pytest.raises(ValueError, match=r"Camera: fov must be in \(0, 180\)"):
        scene.validate()


# --- validation errors ---------------------------------------------------------------------


@pytest.mark.parametrize(
    ("build", "error", "message"),
    [
        (lambda: Mesh(TRI_V, np.zeros((4, 4), int), grey()), ValueError,
         r"Mesh: faces must have shape \(F, 3\), got \(4, 4\)"),
        (lambda: Mesh(TRI_V, np.zeros((0, 3), int), grey()), ValueError, "faces is empty"),
        (lambda: Mesh(np.zeros((0, 3)), [[0, 1, 2]], grey()), ValueError, "vertices is empty"),
        (lambda: Mesh(TRI_V, [[0, 1, 3]], grey()), ValueError, "index vertex 3"),
        (lambda: Mesh(TRI_V, [[0, -1, 2]], grey()), ValueError, "negative index"),
        (lambda: Mesh(TRI_V, [[0.0, 1.0, 2.0]], grey()), TypeError, "faces must be an integer"),
        (lambda: Mesh(TRI_V, minidiff.tensor([[0, 1, 2]]), grey()), TypeError, "not a minidiff"),
        (lambda: Mesh(TRI_V[:, :2], TRI_F, grey()), ValueError, r"vertices must have shape \(V,"),
        (lambda: Mesh(TRI_V, TRI_F, "red"), TypeError, "Mesh: material must be a Material"),
        (lambda: triangle(normals=np.ones((2, 3))), ValueError, r"normals must have shape \(3, 3"),
        (lambda: triangle(uvs=np.ones((3, 3))), ValueError, r"uvs must have shape \(3, 2\)"),
        (lambda: triangle(smooth=1), TypeError, "smooth must be a bool"),
        (lambda: triangle(material=Material((1, 1, 1), texture=np.ones((2, 2, 3)))), ValueError,
         "texture but the mesh has no uvs"),
        (lambda: camera(fov=0.0), ValueError, r"fov must be in \(0, 180\)"),
        (lambda: camera(fov=180.0), ValueError, r"fov must be in \(0, 180\)"),
        (lambda: camera(width=0), ValueError, "width must be a positive int"),
        (lambda: camera(height=2.5), TypeError, "height must be a positive int"),
        (lambda: camera(width=True), TypeError, "width must be a positive int"),
        (lambda: camera(look_at=(0, 0, 5)), ValueError, "position and look_at must differ"),
        (lambda: camera(up=(0, 0, 2)), ValueError, "parallel to the view direction"),
        (lambda: camera(up=(0, 0, 0)), ValueError, "up must be a non-zero"),
        (lambda: camera(position=(0, 0, np.inf)), ValueError, "position contains NaN or inf"),
        (lambda: camera(position="abc"), TypeError, "Camera: position must be numeric"),
        (lambda: camera(position=(1, 2)), ValueError, r"position must have shape \(3,\)"),
        (lambda: PointLight((0, 1, 0), -1.0), ValueError, "intensity must be >= 0"),
        (lambda: PointLight((0, 1, 0), (1.0, 2.0)), ValueError, "intensity must have shape ()"),
        (lambda: DirectionalLight((0, 0, 0), 1.0), ValueError, "direction must be a vector of len"),
        (lambda: DirectionalLight((0, -1, 0), -2.0), ValueError, "irradiance must be >= 0"),
        (lambda: Material((1, 1)), ValueError, r"Material: albedo must have shape \(3,\)"),
        (lambda: Material((1, 1, 1), shininess=0.0), ValueError, "shininess must be > 0"),
        (lambda: Material((1, 1, 1), specular=(1, 1)), ValueError, r"specular must have shape"),
        (lambda: Material((1, 1, 1), texture=np.ones((4, 4))), ValueError, r"\(H, W, 3\)"),
        (lambda: Material((np.nan, 1, 1)), ValueError, "albedo contains NaN"),
        (lambda: Material(None), TypeError, "albedo must be numeric"),
        (lambda: Sphere((0, 0, 0), -1.0, grey()), ValueError, "radius must be > 0"),
        (lambda: Sphere((0, 0), 1.0, grey()), ValueError, r"center must have shape \(3,\)"),
        (lambda: Scene([triangle(), "teapot"], [], camera()), TypeError,
         r"objects\[1\] must be a Mesh or a Sphere, got str"),
        (lambda: Scene([triangle()], [grey()], camera()), TypeError, r"lights\[0\] must be"),
        (lambda: Scene(triangle(), [], camera()), TypeError, "objects must be a list"),
        (lambda: Scene([], [], "camera"), TypeError, "camera must be a Camera"),
        (lambda: Scene([], [], camera(), background=(0, 0)), ValueError, "background"),
    ],
)  # fmt: skip
def test_validation_errors(build, error, message):
    with pytest.raises(error, match=message):
        build()


def test_integer_tensor_is_rejected():
    with pytest.raises(TypeError, match="floating-point"):
        PointLight(minidiff.Tensor(np.array([0, 1, 0])), 1.0)


@settings(max_examples=40, deadline=None)
@given(shape=st.lists(st.integers(0, 4), min_size=0, max_size=3).map(tuple))
def test_random_vertex_shapes(shape):
    """Any vertex array that is not (V>=1, 3) is rejected with a message naming the argument."""
    verts = np.zeros(shape)
    if len(shape) == 2 and shape[1] == 3 and shape[0] >= 3:
        Mesh(verts, TRI_F, grey())  # valid
    else:
        with pytest.raises(ValueError, match="Mesh: "):
            Mesh(verts, TRI_F, grey())


@settings(max_examples=40, deadline=None)
@given(shape=st.lists(st.integers(0, 4), min_size=0, max_size=3).map(tuple))
def test_random_position_shapes(shape):
    if shape == (3,):
        return
    with pytest.raises(ValueError, match=r"PointLight: position must have shape \(3,\)"):
        PointLight(np.ones(shape), 1.0)


@settings(max_examples=30, deadline=None)
@given(fov=st.floats(allow_nan=True, allow_infinity=True))
def test_fov_range(fov):
    if math.isfinite(fov) and 0.0 < fov < 180.0:
        assert float(camera(fov=fov).fov.data) == fov
    else:
        with pytest.raises(ValueError, match="Camera: fov"):
            camera(fov=fov)


def test_named_parameters_name_every_parameter_once_in_parameters_order():
    shared = Material((0.5, 0.5, 0.5))
    mesh = Mesh(TRI_V, TRI_F, shared, uvs=np.zeros((3, 2)))
    sphere = Sphere((0, 0, -3), 0.5, shared)  # the same material: listed once
    scene = Scene([mesh, sphere], [PointLight((0, 1, 0), 2.0)], camera(), (0.1, 0.2, 0.3))
    named = scene.named_parameters()
    assert list(named)[:5] == [
        "camera.position", "camera.look_at", "camera.up", "camera.fov", "lights[0].position",
    ]  # fmt: skip
    assert named["objects[0].vertices"] is mesh.vertices
    assert named["objects[0].uvs"] is mesh.uvs
    assert named["objects[0].material.albedo"] is shared.albedo
    assert named["objects[1].center"] is sphere.center
    assert "objects[1].material.albedo" not in named  # shared: first name only
    assert "objects[0].normals" not in named  # unset optional fields are not parameters
    assert named["background"] is scene.background
    assert len({id(t) for t in named.values()}) == len(named)
    # parameters() walks the same owners without the names: the same tensors, in order,
    # also with a transform, a second light and a tensor shared across owners.
    mesh.transform = Transform(translation=(0.1, 0.0, 0.0))
    scene.lights.append(DirectionalLight((0, -1, 0), 1.0, color=mesh.material.albedo))
    for case in (scene, Scene([mesh, sphere], scene.lights, camera(), shared.albedo)):
        listed = case.parameters()
        assert len(listed) == len(case.named_parameters())
        assert all(a is b for a, b in zip(listed, case.named_parameters().values(), strict=True))


def test_a_named_size_must_agree_across_fields():
    with pytest.raises(ValueError, match=r"Mesh: uvs must have shape \(3, 2\), got \(4, 2\)"):
        Mesh(TRI_V, TRI_F, Material((1, 1, 1)), uvs=np.zeros((4, 2)))


@pytest.mark.parametrize(
    "build, message",
    [
        (lambda: DirectionalLight((0, -1e-300, 0), 1.0), "direction must be a vector of length"),
        (lambda: DirectionalLight((0, -1e200, 0), 1.0), "length 1e-150 to 1e150"),
        (lambda: Mesh(TRI_V, [[0, 1, 2], [0, 1]], Material((1, 1, 1))), "faces must be an"),
        (
            lambda: Mesh(TRI_V, np.array([[0, 1, 2**63 + 5]], np.uint64), Material((1, 1, 1))),
            "too large for int64",
        ),
        (
            lambda: Mesh(TRI_V, TRI_F, Material((1, 1, 1)), normals=np.zeros((3, 3)), smooth=True),
            "normals are all",
        ),
    ],
)
def test_inputs_that_gave_unclear_errors_or_silent_black(build, message):
    with pytest.raises(ValueError, match=message):
        build()
