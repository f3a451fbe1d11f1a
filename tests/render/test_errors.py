"""Bad input to ``render.render`` fails with a clear error; degenerate but legal geometry
renders with finite values and finite gradients (never NaN).

The degenerate cases run under ``minidiff.detect_anomaly()``, which raises at the first
primitive whose forward value or backward gradient is NaN or inf, naming it, so a failure
points at the operation that produced it rather than at the final image.
"""

from __future__ import annotations

import numpy as np
import pytest

import minidiff as md
import render
from tests.render_helpers import QUAD_FACES, ground_quad, random_scene

# --------------------------------------------------------------------------------------
# Clear errors
# --------------------------------------------------------------------------------------


def small_scene():
    return random_scene(0, lights=("point", "directional"), width=12, height=10)


@pytest.mark.parametrize(
    ("owner", "name"),
    [
        (lambda s: s.lights[0], "position"),
        (lambda s: s.lights[0], "intensity"),
        (lambda s: s.lights[1], "direction"),
        (lambda s: s.camera, "look_at"),
        (lambda s: s.camera, "fov"),
        (lambda s: s.objects[0], "vertices"),
        (lambda s: s.objects[0].material, "albedo"),
        (lambda s: s.spheres[0], "radius"),
        (lambda s: s, "background"),
    ],
)
def test_nan_set_in_place_is_reported_by_name(owner, name):
    """An optimiser edits ``.data`` in place, after the constructors' checks: the render
    re-validates and names the parameter."""
    scene = small_scene()
    render.render(scene)  # fine before the edit (and fills the visibility cache)
    owner(scene).__dict__[name].data.reshape(-1)[0] = np.nan
    with pytest.raises(ValueError, match=rf"\b{name}\b.*(NaN|nan)"):
        render.render(scene)


def test_inf_light_position_is_reported():
    scene = small_scene()
    scene.lights[0].position.data[1] = np.inf
    with pytest.raises(ValueError, match=r"PointLight: position .*infinite"):
        render.render(scene)


@pytest.mark.parametrize("spp", [3, 0, -1, 2, 8])
def test_spp_must_be_a_positive_perfect_square(spp):
    with pytest.raises(ValueError, match=r"spp must be a perfect square.*got " + str(spp)):
        render.render(small_scene(), spp=spp)


@pytest.mark.parametrize("spp", [4.0, "4", None, True])
def test_spp_must_be_an_int(spp):
    with pytest.raises(ValueError, match=r"spp must be a perfect square"):
        render.render(small_scene(), spp=spp)


def test_spp_may_be_a_numpy_integer():
    scene = small_scene()
    np.testing.assert_array_equal(
        render.render(scene, spp=np.int64(4)).data, render.render(scene, spp=4).data
    )


@pytest.mark.parametrize("not_a_scene", [None, "scene", [1, 2], render.Material((1, 1, 1))])
def test_not_a_scene(not_a_scene):
    with pytest.raises(TypeError, match=r"render: scene must be a render.Scene"):
        render.render(not_a_scene)


def test_textured_sphere():
    texture = np.full((2, 2, 3), 0.5)
    with pytest.raises(ValueError, match=r"Sphere: textured materials are not supported"):
        render.Sphere((0, 0, 0), 1.0, render.Material((1, 1, 1), texture=texture))
    # Given a texture after construction: the render's validation catches it.
    scene = small_scene()
    scene.spheres[0].material.texture = md.tensor(texture)
    with pytest.raises(ValueError, match=r"textured|texture"):
        render.render(scene)


def test_objects_and_lights_of_the_wrong_type():
    scene = small_scene()
    scene.objects.append("teapot")
    with pytest.raises(TypeError, match=r"objects\[3\] must be a Mesh or a Sphere"):
        render.render(scene)
    scene = small_scene()
    scene.lights.append(render.Sphere((0, 0, 0), 1.0, render.Material((1, 1, 1))))
    with pytest.raises(TypeError, match=r"lights\[2\] must be a PointLight"):
        render.render(scene)


# --------------------------------------------------------------------------------------
# Degenerate geometry: finite values and gradients
# --------------------------------------------------------------------------------------


def differentiable_parameters(scene):
    """Every continuous parameter of the scene, switched to requires_grad (grads reset)."""
    params = [scene.background]
    for c in (scene.camera,):
        params += [c.position, c.look_at, c.up, c.fov]
    for light in scene.lights:
        params += [v for v in vars(light).values() if isinstance(v, md.Tensor)]
    for obj in scene.objects:
        params += [v for v in vars(obj).values() if isinstance(v, md.Tensor)]
        params += [v for v in vars(obj.material).values() if isinstance(v, md.Tensor)]
    for p in params:
        p.requires_grad, p.grad = True, None
    return params


def assert_finite_render_and_gradients(scene, min_hits=1, **kwargs):
    """Render and backpropagate under detect_anomaly; everything must be finite."""
    params = differentiable_parameters(scene)
    weights = np.random.default_rng(0).standard_normal((scene.camera.height, scene.camera.width, 3))
    with md.detect_anomaly():
        image, info = render.render(scene, return_info=True, **kwargs)
        (image * md.tensor(weights)).sum().backward()
    assert np.isfinite(image.data).all()
    for p in params:
        assert p.grad is None or np.isfinite(p.grad).all()
    assert (info.prim_id >= 0).sum() >= min_hits  # the degenerate case was actually hit
    return image, info


def test_zero_area_triangles():
    """Collapsed triangles (repeated vertex, all three equal, collinear) next to a normal one,
    flat and smooth: they are never hit, and they add nothing (not NaN) to vertex normals."""
    vertices = [(-1, -1, 0), (1, -1, 0), (0, 1, 0), (0.5, 0.5, 0), (0.5, 0.5, 0), (2, 2, 0),
                (-1, -1, 0.0)]  # fmt: skip
    faces = [[0, 1, 2], [3, 4, 5], [0, 0, 1], [3, 3, 3], [0, 1, 6], [0, 3, 5]]
    camera = render.Camera((0.2, 0.1, 3.0), (0, 0, 0), fov=60, width=24, height=24)
    for smooth in (False, True):
        material = render.Material((0.5, 0.5, 0.5), specular=0.3, ambient=0.01)
        mesh = render.Mesh(vertices, faces, material, smooth=smooth)
        scene = render.Scene([mesh], [render.PointLight((0.5, 0.5, 2), 10.0)], camera)
        _, info = assert_finite_render_and_gradients(scene, min_hits=50)
        assert set(np.unique(info.prim_id[info.prim_id >= 0])) == {0}


@pytest.mark.parametrize("tilt", [0.0, 1e-12, 1e-9, 1e-6, 1e-3])
def test_triangle_seen_edge_on(tilt):
    """A triangle whose plane (nearly) contains the camera's central row of rays: those rays
    graze it (or lie in it). Whatever the visibility decides, no NaN."""
    vertices = [(-1, -tilt, -1), (1, -tilt, -1), (0, tilt, 1.0)]
    camera = render.Camera((0, 0, 3.0), (0, 0, 0), fov=60, width=33, height=33)
    mesh = render.Mesh(vertices, [[0, 1, 2]], render.Material((0.5, 0.5, 0.5), specular=0.3))
    floor = ground_quad(size=3.0, y=-1.0)  # something else to see
    scene = render.Scene([mesh, floor], [render.PointLight((0.5, 2, 2), 10.0)], camera)
    assert_finite_render_and_gradients(scene)


def test_point_light_exactly_on_a_hit_point():
    """The centre ray of an odd-sized image hits the plane exactly at the origin, where the
    light sits (r = 0): the clamp makes its contribution zero rather than 0/0. Elsewhere the
    light lies in the plane, so cos = 0 everywhere."""
    camera = render.Camera((0, 2.0, 0), (0, 0, 0), up=(0, 0, -1), fov=60, width=33, height=33)
    material = render.Material((0.5, 0.5, 0.5), specular=0.4)
    scene = render.Scene(
        [ground_quad(material=material)], [render.PointLight((0, 0, 0), 10)], camera
    )
    image, info = assert_finite_render_and_gradients(scene, min_hits=33 * 33)
    assert (image.data == 0).all()


def test_point_light_on_the_surface_seen_at_an_angle():
    """The light sits on a visible triangle's surface, other geometry around: finite."""
    scene = random_scene(2, lights=("point",), width=20, height=16)
    ground = scene.objects[0]
    scene.lights[0].position.data[:] = (0.3, 0.0, 0.4)  # on the ground plane y = 0
    ground.material.specular.data[...] = 0.5
    assert_finite_render_and_gradients(scene, min_hits=100)


@pytest.mark.parametrize("offset", [0.0, 1e-15, -1e-15, 1e-12, 1e-9])
def test_sphere_hit_at_a_grazing_angle(offset):
    """The centre ray of an odd-sized image is tangent to the sphere (discriminant ~0):
    the derivative of sqrt would blow up there without the renderer's clamp."""
    radius = 0.5
    camera = render.Camera((0, 0, 0), (0, 0, -1), fov=30, width=33, height=33)
    material = render.Material((0.5, 0.5, 0.5), specular=0.3, shininess=8.0)
    sphere = render.Sphere((radius * (1 + offset), 0, -5), radius, material)
    lights = [render.PointLight((0, 3, 0), 10.0), render.DirectionalLight((1, -1, -1), 1.0)]
    assert_finite_render_and_gradients(render.Scene([sphere], lights, camera), min_hits=100)


def test_sphere_grazing_random_limbs():
    """Many spheres seen at a low resolution with 4 samples: plenty of limb hits."""
    rng = np.random.default_rng(4)
    spheres = [
        render.Sphere(rng.uniform(-2, 2, 3) - (0, 0, 3), rng.uniform(0.2, 0.6),
                      render.Material(rng.uniform(0, 1, 3), specular=0.2))
        for _ in range(12)
    ]  # fmt: skip
    camera = render.Camera((0, 0, 4.0), (0, 0, -3), fov=60, width=20, height=20)
    scene = render.Scene(spheres, [render.PointLight((1, 3, 3), 20.0)], camera)
    assert_finite_render_and_gradients(scene, min_hits=100, spp=4)


@pytest.mark.parametrize(
    "normals",
    [
        [(0, 0, 1), (0, 0, 0), (0, 0, 1)],  # one zero normal
        [(0, 0, 1), (0, 0, -1), (0.3, 0, 1)],  # opposite normals cancel along an edge
    ],
    ids=["one-zero", "cancelling"],  # all zero is refused (tests/render/scene/test_scene.py)
)
def test_zero_length_vertex_normal_with_smooth_shading(normals):
    vertices = [(-1, -1, 0), (1, -1, 0), (0, 1, 0.0)]
    camera = render.Camera((0.1, 0.2, 3.0), (0, 0, 0), fov=60, width=33, height=33)
    material = render.Material((0.5, 0.5, 0.5), specular=0.3)
    mesh = render.Mesh(vertices, [[0, 1, 2]], material, normals=normals, smooth=True)
    scene = render.Scene([mesh], [render.PointLight((0.5, 0.5, 2), 10.0)], camera)
    assert_finite_render_and_gradients(scene, min_hits=100)


def test_smooth_mesh_with_an_isolated_vertex_and_degenerate_faces():
    """Computed vertex normals (smooth=True, no normals): a vertex used by no face and one
    used only by zero-area faces get the zero normal, without NaN."""
    vertices = [(-1, -1, 0), (1, -1, 0), (0, 1, 0), (5, 5, 5), (0.3, 0.3, 0)]
    faces = [[0, 1, 2], [4, 4, 0]]
    camera = render.Camera((0.1, 0.2, 3.0), (0, 0, 0), fov=60, width=24, height=24)
    mesh = render.Mesh(vertices, faces, render.Material((0.5, 0.5, 0.5)), smooth=True)
    scene = render.Scene([mesh], [render.PointLight((0.5, 0.5, 2), 10.0)], camera)
    assert_finite_render_and_gradients(scene, min_hits=50)


def test_light_and_camera_inside_a_sphere():
    """Camera inside a sphere (the far root is taken) with the light inside too."""
    camera = render.Camera((0, 0, 0.2), (0, 0, -1), fov=90, width=16, height=16)
    sphere = render.Sphere((0, 0, 0), 2.0, render.Material((0.5, 0.5, 0.5)))
    scene = render.Scene([sphere], [render.PointLight((0.3, 0.5, 0.0), 5.0)], camera)
    image, info = assert_finite_render_and_gradients(scene, min_hits=256)
    assert (image.data > 0).all()  # the inside of the sphere is lit, two-sided


def test_quad_textured_with_degenerate_uvs():
    """All uvs equal (the texture is sampled at one point) and uvs far outside [0, 1]."""
    texture = np.random.default_rng(1).uniform(0, 1, (3, 3, 3))
    camera = render.Camera((0, 0, 3.0), (0, 0, 0), fov=50, width=16, height=16)
    for uvs in (np.full((4, 2), 0.5), np.array([(-7, -7), (9, -7), (9, 9), (-7, 9.0)])):
        mesh = render.Mesh(
            [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)],
            QUAD_FACES,
            render.Material((1, 1, 1), texture=texture),
            uvs=uvs,
        )
        scene = render.Scene([mesh], [render.DirectionalLight((0, 0, -1), 1.0)], camera)
        assert_finite_render_and_gradients(scene, min_hits=100)


@pytest.mark.parametrize(
    "width, height, spp",
    [(2**32, 2**32, 1), (2**62 + 1, 4, 1), (2**31, 2**31, 4), (2**33, 2**31, 1), (65536, 65536, 1),
     (100_000, 100_000, 1), (32768, 32768, 4), (30_000, 30_000, 1), (8, 8, 2**62),
     (8192, 8193, 1), (4096, 4096, 9)],
)  # fmt: skip
def test_image_sizes_that_cannot_fit_fail_before_allocating(width, height, spp):
    """They crashed the interpreter (int64 overflow in a Numba kernel) or failed inside an
    allocation. Now a ValueError names width, height and spp, and nothing big is allocated."""
    import tracemalloc

    tracemalloc.start()
    try:
        with pytest.raises(ValueError, match=r"width x height x spp = .* the limit of"):
            camera = render.Camera((0, 0, 5), (0, 0, 0), width=width, height=min(height, 4))
            if height > 4 or spp > 1:  # the camera itself was fine: the render is too big
                camera.height = height
                scene = render.Scene([], [], camera)
                render.render(scene, spp=spp)
        assert tracemalloc.get_traced_memory()[1] < 50e6  # peak bytes
    finally:
        tracemalloc.stop()


@pytest.mark.parametrize("primary", ["raster", "bvh"])
@pytest.mark.parametrize(
    "change, owner",
    [
        (lambda s: s.objects[0].vertices.data.__setitem__((7, 1), 1e61), "Mesh: vertices"),
        (lambda s: s.objects[-1].radius.data.__setitem__((), 1e200), "Sphere: radius"),
        (lambda s: s.objects[-1].center.data.__setitem__(0, -1e61), "Sphere: center"),
        (lambda s: s.camera.position.data.__setitem__(2, 1e61), "Camera: position"),
        (lambda s: s.camera.look_at.data.__setitem__(0, 1e61), "Camera: look_at"),
        (lambda s: s.lights[0].position.data.__setitem__(1, 1e61), "PointLight: position"),
    ],
)
def test_coordinates_beyond_the_supported_range_are_refused_on_every_path(change, owner, primary):
    """A vertex at 1e61 rendered black on the rasterised path while the BVH refused it, and
    a sphere of radius 1e200 had no hits: the scene's validation now refuses both, the same
    on every path, naming the parameter and the range."""
    scene = render.paper_scene(width=16, height=12)
    scene.objects.append(render.Sphere((1.5, 0.5, 1.0), 0.5, render.Material((0.5,) * 3)))
    render.render(scene, primary=primary)  # fine before the change
    change(scene)
    with pytest.raises(ValueError, match=f"{owner} must be .*at most 1e60"):
        render.render(scene, primary=primary)


def test_the_largest_supported_coordinates_give_the_same_hits_on_both_paths():
    scene = render.paper_scene(width=24, height=16)
    for t in (scene.objects[0].vertices, scene.camera.position, scene.camera.look_at):
        t.data[...] = t.data * 1e59
    scene.lights[0].position.data[...] = scene.lights[0].position.data * 1e59
    _, raster = render.render(scene, primary="raster", return_info=True)
    _, bvh = render.render(scene, primary="bvh", return_info=True)
    assert (raster.prim_id >= 0).any()
    np.testing.assert_array_equal(raster.prim_id, bvh.prim_id)
