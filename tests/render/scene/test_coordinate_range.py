"""The supported range relative to the camera's view distance |look_at - position|
(``render.scene.scene.MAX_COORD_RELATIVE`` for coordinates, ``MAX_EXTENT_RELATIVE`` for the
geometry's extent) is checked once, by ``Scene.validate``: the rasterised and the BVH paths
refuse the same scenes with the same message, and the largest accepted scenes render the same
on both paths and as their small counterparts, shadows included. (The absolute bound
``MAX_COORD`` is tested in ``tests/render/test_errors.py``.)"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import minidiff as md
import render
from render.scene.scene import MAX_COORD_RELATIVE, MAX_EXTENT_RELATIVE
from tests.render_helpers import random_scene

QUAD = [[0, 1, 2], [0, 2, 3]]
#: The message's statement of the range, for a camera 5 units from its look-at point.
RANGE = r"x the camera's view distance \|look_at - position\| \(= 5\), i\.e\. "


def material():
    return render.Material(albedo=(0.8, 0.8, 0.8))


def camera(distance=5.0, width=12, height=10):
    return render.Camera((0, 0, distance), (0, 0, 0), width=width, height=height)


def quad(size=1.0):
    """A quad of side 2 * size around the origin in z = 0."""
    s = size
    return render.Mesh([[-s, -s, 0], [s, -s, 0], [s, s, 0], [-s, s, 0]], QUAD, material())


def render_info(scene, primary="raster"):
    with md.no_grad():
        _, info = render.render(scene, primary=primary, return_info=True)
    return info


def test_a_quad_vertex_at_1e12_seen_from_5_units_is_refused_on_both_paths():
    """The issue's case: with its shared corner at 1e12 the quad covers 18 of these 12 x 10
    pixels (counted in rational arithmetic); both paths rendered none of them, without a word.
    It is refused when built, and when made by an in-place edit (as an optimiser does) both
    paths refuse it with the same message, which states the supported range."""
    message = (
        r"^Scene: objects\[0\]\.vertices has a coordinate of magnitude 1e\+12; supported: at "
        r"most 1e\+08 " + RANGE + r"5e\+08$"
    )
    with pytest.raises(ValueError, match=message):
        far = quad()
        far.vertices.data[0] = (1e12, -1, 0)
        render.Scene([far], [render.PointLight((0, 3, 5), 30.0)], camera())
    mesh = quad()
    scene = render.Scene([mesh], [render.PointLight((0, 3, 5), 30.0)], camera())
    mesh.vertices.data[0] = (1e12, -1, 0)
    messages = []
    for primary in ("raster", "bvh"):
        with pytest.raises(ValueError, match=message) as error:
            render_info(scene, primary)
        messages.append(str(error.value))
    assert messages[0] == messages[1]


def move_camera(scene):
    scene.camera.position.data[0] += 1e10
    scene.camera.look_at.data[0] += 1e10


@pytest.mark.parametrize(
    "edit, name",
    [
        (move_camera, "camera.position"),  # the view distance stays 5
        (lambda s: s.lights[0].position.data.__setitem__(1, 1e10), r"lights\[0\]\.position"),
        (lambda s: s.objects[0].vertices.data.__setitem__((3, 2), 1e10), r"objects\[0\]\.vert"),
        (lambda s: s.objects[1].center.data.__setitem__(2, -1e10), r"objects\[1\]\.center"),
    ],
)
def test_every_coordinate_is_checked_point_lights_included(edit, name):
    scene = render.Scene(
        [quad(), render.Sphere((0, 0, -3), 1.0, material())],
        [render.PointLight((0, 3, 5), 30.0), render.DirectionalLight((0, -1e10, 0), 1.0)],
        camera(),
    )
    edit(scene)
    with pytest.raises(ValueError, match=rf"^Scene: {name}.* of magnitude 1e\+10; supported"):
        scene.validate()


@pytest.mark.parametrize("seed", [1, 4])
def test_the_largest_accepted_translation_renders_the_same_on_both_paths(seed):
    """A scene moved until its largest coordinate is MAX_COORD_RELATIVE view distances:
    accepted, seen the same on both paths and as unmoved, shadows included."""
    reference = render_info(random_scene(seed, width=14, height=12), "bvh")
    scene = random_scene(seed, width=14, height=12)
    view = float(np.linalg.norm(scene.camera.look_at.data - scene.camera.position.data))
    shift = np.array([1.0, -1.0, 1.0]) * (MAX_COORD_RELATIVE * view - 10.0)
    points = [scene.camera.position, scene.camera.look_at]
    points += [light.position for light in scene.lights if isinstance(light, render.PointLight)]
    points += [o.vertices if isinstance(o, render.Mesh) else o.center for o in scene.objects]
    for p in points:
        p.data[...] += shift
    largest = max(float(np.abs(p.data).max()) for p in points)
    assert 0.9999 * MAX_COORD_RELATIVE * view < largest <= MAX_COORD_RELATIVE * view
    raster = render_info(scene, "raster")
    np.testing.assert_array_equal(raster.prim_id, render_info(scene, "bvh").prim_id)
    np.testing.assert_array_equal(raster.prim_id, reference.prim_id)
    np.testing.assert_array_equal(raster.lit, reference.lit)


def wall_scene(reach=3.0, light=None):
    """A wall standing on a ground quad, its shadow at its foot, seen from 5 units; the
    ground's second corner is ``reach`` away along x (a long sliver beyond the image, which
    sees the same triangles for every reach)."""
    ground = quad(3.0)
    ground.vertices.data[1, 0] = reach
    wall = [[0.5, -0.5, 0], [0.5, 0.5, 0], [0.5, 0.5, 0.5], [0.5, -0.5, 0.5]]
    light = light or render.PointLight((2.5, 0, 3), 30.0)
    objects = [ground, render.Mesh(wall, QUAD, material())]
    return render.Scene(objects, [light], camera(width=48, height=40))


def test_geometry_wider_than_the_supported_extent_is_refused():
    """A ground 1e7 view distances across started the shadow rays 1e-9 of that off the
    surface, past the foot of the wall, and its shadow lost pixels there."""
    for reach in (MAX_EXTENT_RELATIVE * 5.0 * 1.01, 5e7):
        with pytest.raises(
            ValueError,
            match=r"^Scene: the geometry spans .*objects\[0\] reaches farthest\); supported: "
            r"at most 10000 " + RANGE + "50000$",
        ):
            wall_scene(reach)


def test_the_widest_accepted_geometry_renders_the_same_on_both_paths_shadows_included():
    reference = render_info(wall_scene())
    assert (~reference.lit & (reference.prim_id >= 0)[None]).any()  # there is a shadow
    scene = wall_scene(MAX_EXTENT_RELATIVE * 5.0 * 0.99)  # the diagonal a little longer
    raster = render_info(scene, "raster")
    np.testing.assert_array_equal(raster.prim_id, render_info(scene, "bvh").prim_id)
    # The same object (two triangles each: ids 0-1 the ground, 2-3 the wall) in every
    # pixel: a ray exactly through the ground's diagonal meets both of its triangles, at t
    # rounded each its own way (the watertight test's), and the long one may be the nearer.
    np.testing.assert_array_equal(raster.prim_id // 2, reference.prim_id // 2)
    np.testing.assert_array_equal(raster.lit, reference.lit)


def test_the_farthest_accepted_point_light_shades_like_a_directional_light():
    """Point lights are not exempt from the range (a light 1e12 view distances away lost
    shadows); one at its edge gives a directional light's image, shadows included."""
    towards = np.array([2.5, 0.0, 3.0]) / np.linalg.norm([2.5, 0.0, 3.0])
    with md.no_grad():
        sun = render.render(wall_scene(light=render.DirectionalLight(-towards, 1.0)))
        far = MAX_COORD_RELATIVE * 5.0 * 0.999
        image = render.render(wall_scene(light=render.PointLight(towards * far, far**2)))
    np.testing.assert_allclose(image.data, sun.data, rtol=0, atol=1e-7 * sun.data.max())


@settings(max_examples=20, deadline=None)
@given(
    log_scale=st.floats(-6.0, 6.0),
    log_ratio=st.floats(0.0, 12.0),
    corner=st.integers(0, 3),
    axis=st.integers(0, 2),
    sign=st.sampled_from([-1.0, 1.0]),
)
def test_scenes_are_accepted_exactly_within_the_range_and_then_seen_the_same(
    log_scale, log_ratio, corner, axis, sign
):
    """A quad seen from 5 scale units with one corner log_ratio decades of view distances
    away: refused beyond MAX_COORD_RELATIVE or MAX_EXTENT_RELATIVE, else the same hits on both
    paths."""
    scale = 10.0**log_scale
    mesh = quad(size=scale)
    mesh.vertices.data[corner, axis] = sign * 10.0**log_ratio * 5.0 * scale
    scene_camera = camera(5.0 * scale)
    view = float(np.linalg.norm(scene_camera.look_at.data - scene_camera.position.data))
    light = render.PointLight(np.array([0, 3, 5]) * scale, 30.0 * scale**2)
    largest = float(np.abs(mesh.vertices.data).max())
    extent = float(np.linalg.norm(np.ptp(mesh.vertices.data, axis=0)))
    if largest > MAX_COORD_RELATIVE * view or extent > MAX_EXTENT_RELATIVE * view:
        with pytest.raises(ValueError, match=r"objects\[0\]\.vertices has a coord|geometry spans"):
            render.Scene([mesh], [light], scene_camera)
        return
    scene = render.Scene([mesh], [light], scene_camera)
    raster, bvh = render_info(scene, "raster"), render_info(scene, "bvh")
    np.testing.assert_array_equal(raster.prim_id, bvh.prim_id)
