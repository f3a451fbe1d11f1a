"""Object transforms (``render.Transform``, ``render.scene.placement``): the rotation
against SciPy's, its derivative against central differences, a transformed object rendered
exactly as the same object with its world geometry written out, and bad input."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

import minidiff as md
import render
from render.scene.placement import SERIES_BELOW, rotation_matrix
from render.shade.surface import vertex_normals
from tests.render_helpers import random_scene

FEW = settings(max_examples=25, deadline=None)
UNIT = st.lists(st.floats(-1, 1), min_size=3, max_size=3).filter(lambda v: np.linalg.norm(v) > 1e-3)
#: rotation angles in degrees: zero, tiny, both sides of the series' switch, large, > 360
ANGLES = st.sampled_from(
    [0.0, 1e-9, 1e-4, np.degrees(SERIES_BELOW) * 0.999, np.degrees(SERIES_BELOW) * 1.001]
) | st.floats(0.0, 720.0)


def rotation_vector(axis, degrees) -> np.ndarray:
    axis = np.asarray(axis, dtype=np.float64)
    return axis / np.linalg.norm(axis) * degrees


@FEW
@given(axis=UNIT, degrees=ANGLES)
def test_rotation_vector_matches_scipy(axis, degrees):
    r = rotation_vector(axis, degrees)
    expected = Rotation.from_rotvec(np.radians(r)).as_matrix()
    assert np.abs(rotation_matrix(r).data - expected).max() < 1e-14


@FEW
@given(
    q=st.lists(st.floats(-3, 3), min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 0.1)
)
def test_quaternion_matches_scipy(q):
    q = np.array(q)
    expected = Rotation.from_quat(q[[1, 2, 3, 0]]).as_matrix()  # SciPy: (x, y, z, w)
    assert np.abs(rotation_matrix(q).data - expected).max() < 1e-14


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("rotation", [(0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0), (-2.5, 0.0, 0.0, 0.0)])
def test_an_unturned_constant_is_the_formulas_identity(rotation, dtype):
    """A constant rotation without an axis part skips the formulas (``_unturned``): the same
    matrix and dtype as they give (a differentiated copy still takes them, and gets the
    derivative that test_rotation_gradient_matches_central_differences checks)."""
    constant = rotation_matrix(md.tensor(np.array(rotation, dtype)))
    formula = rotation_matrix(md.tensor(np.array(rotation, dtype), requires_grad=True))
    assert constant.node is None and formula.node is not None
    assert constant.dtype == formula.dtype
    np.testing.assert_array_equal(constant.data, formula.data)
    np.testing.assert_array_equal(constant.data, np.eye(3))


def central_difference(f, x: np.ndarray, h: float) -> np.ndarray:
    return np.array(
        [(f(x + h * e) - f(x - h * e)) / (2 * h) for e in np.eye(len(x))], dtype=np.float64
    )


@FEW
@given(axis=UNIT, degrees=ANGLES, seed=st.integers(0, 2**31), quaternion=st.booleans())
def test_rotation_gradient_matches_central_differences(axis, degrees, seed, quaternion):
    """d sum(R * W) / d rotation, by the tape and by central differences, on both sides of
    the series' switch and at zero (where a closed form in theta would give NaN)."""
    rng = np.random.default_rng(seed)
    weights = rng.standard_normal((3, 3))
    if quaternion:
        half = np.radians(degrees) / 2
        unit = np.asarray(axis) / np.linalg.norm(axis)
        x = np.concatenate([[np.cos(half)], np.sin(half) * unit]) * rng.uniform(0.5, 2)
    else:
        x = rotation_vector(axis, degrees)
    param = md.tensor(x, requires_grad=True)
    md.sum(rotation_matrix(param) * weights).backward()
    numeric = central_difference(
        lambda v: float(np.sum(rotation_matrix(v).data * weights)), x, 1e-5
    )
    scale = np.linalg.norm(numeric) + np.linalg.norm(weights) * 1e-3
    assert np.linalg.norm(param.grad - numeric) / scale < 1e-7


def by_hand(vertices, normals, rotation_degrees, translation, scale, pivot):
    """World geometry written out with SciPy's rotation, independent of the renderer."""
    r = Rotation.from_rotvec(np.radians(rotation_degrees)).as_matrix()
    world = pivot + translation + scale * (vertices - pivot) @ r.T
    return world, None if normals is None else normals @ r.T


@pytest.mark.parametrize("smooth", [False, True])
def test_transformed_mesh_renders_like_its_world_copy(smooth):
    scene = random_scene(3, lights=("point", "directional"), smooth=smooth)
    mesh = scene.objects[1]
    rng = np.random.default_rng(1)
    if smooth:  # its own normals: the ones computed from the faces (they agree with the
        # winding, which decides the side shaded), perturbed
        normals = vertex_normals(mesh.vertices, mesh.faces).data
        mesh.normals = md.tensor(normals + 0.3 * rng.standard_normal(normals.shape))
    fields = (rng.uniform(-30, 30, 3), rng.uniform(-0.2, 0.2, 3), 1.15, mesh.vertices.data.mean(0))
    normals = None if mesh.normals is None else mesh.normals.data
    world, normals = by_hand(mesh.vertices.data, normals, *fields)
    copy = render.Mesh(world, mesh.faces, mesh.material, normals=normals, smooth=smooth)
    objects = [scene.objects[0], copy, scene.objects[2]]
    expected = render.render(render.Scene(objects, scene.lights, scene.camera, scene.background))
    mesh.transform = render.Transform(*fields)
    image = render.render(scene)
    assert np.abs(image.data - expected.data).max() < 1e-12
    assert np.abs(image.data - render.render(scene, reuse_visibility=False).data).max() == 0


def test_transformed_sphere_renders_like_its_world_copy():
    scene = random_scene(4)
    sphere = scene.objects[2]
    fields = ((10.0, -40.0, 5.0), (0.1, 0.05, -0.1), 0.8, sphere.center.data + (0.3, 0.0, 0.1))
    (centre,), _ = by_hand(sphere.center.data[None], None, *fields)
    copy = render.Sphere(centre, 0.8 * sphere.radius.data, sphere.material)
    expected = render.render(render.Scene(scene.objects[:2] + [copy], scene.lights, scene.camera,
                                          scene.background))  # fmt: skip
    sphere.transform = render.Transform(*fields)
    assert np.abs(render.render(scene).data - expected.data).max() < 1e-12


def test_transform_parameters_are_named_and_receive_gradients():
    scene = random_scene(5)
    scene.objects[1].transform = render.Transform(
        md.tensor([0.0, 10.0, 0.0], requires_grad=True), scale=md.tensor(1.0, requires_grad=True)
    )
    names = scene.named_parameters()
    for field in ("rotation", "translation", "scale", "pivot"):
        assert f"objects[1].transform.{field}" in names
    md.sum(render.render(scene)).backward()
    t = scene.objects[1].transform
    assert np.abs(t.rotation.grad).max() > 0 and abs(float(t.scale.grad)) > 0


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"rotation": (np.nan, 0.0, 0.0)}, "rotation contains NaN"),
        ({"rotation": (0.0, 0.0, 0.0, 0.0)}, "rotation must be a rotation vector or a non-zero"),
        ({"rotation": (1.0, 2.0)}, r"rotation must have shape \(3,\) or \(4,\)"),
        ({"scale": 0.0}, "scale must be > 0"),
        ({"translation": (0.0, np.inf, 0.0)}, "translation contains NaN"),
        ({"pivot": "centre"}, "pivot must be numeric"),
    ],
)
def test_bad_transforms_are_refused_by_name(kwargs, message):
    with pytest.raises((ValueError, TypeError), match=f"Transform: {message}"):
        render.Transform(**kwargs)


def test_bad_transform_edits_are_refused_at_render():
    scene = random_scene(6)
    scene.objects[1].transform = render.Transform((0.0, 0.0, 1.0, 0.0))
    scene.objects[1].transform.rotation.data[:] = 0.0  # an optimiser walked to zero
    with pytest.raises(ValueError, match="Transform: rotation must be"):
        render.render(scene)
    scene.objects[1].transform = "identity"
    with pytest.raises(TypeError, match="Mesh: transform must be a Transform"):
        render.render(scene)


def test_a_transform_placing_an_object_far_away_is_refused():
    scene = random_scene(7)
    scene.objects[2].transform = render.Transform(translation=(1e12, 0.0, 0.0))
    with pytest.raises(ValueError, match=r"objects\[2\] \(placed by its transform\)"):
        render.render(scene)
