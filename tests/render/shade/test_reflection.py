"""Mirror reflection (``render.shade.mirrors``): a closed form, gradients through bounces, the
decisions in ``RenderInfo``, and bad input."""

from __future__ import annotations

import json
import runpy
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import example, given

import minidiff as md
import render
from tests.render.test_gradients import FEW, SEEDS, assert_gradient_matches
from tests.render_helpers import QUAD_FACES, ground_quad, random_scene

MIRROR = 2  # the ground quad's two triangles come first: ids 0 and 1


def on_mirror(info) -> np.ndarray:
    """(H, W) bool: the pixel's (single) camera ray hits the mirror floor."""
    ids = info.prim_id[..., 0]
    return (ids >= 0) & (ids < MIRROR)


def mirror_material(reflectance=1.0) -> render.Material:
    """An ideal mirror: no diffuse, specular or ambient term of its own."""
    return render.Material(
        albedo=(0.0, 0.0, 0.0), specular=0.0, ambient=0.0, reflectance=reflectance
    )


def mirror_floor_scene(seed: int, reflectance=1.0, width=40, height=32) -> render.Scene:
    """``random_scene`` with its ground made an ideal mirror (y = 0)."""
    scene = random_scene(seed, lights=("point", "directional"), width=width, height=height)
    scene.objects[0].material = mirror_material(reflectance)
    return scene


def mirrored_view(scene: render.Scene) -> render.Scene:
    """The same scene without its floor, seen by the camera mirrored through y = 0."""
    flip = np.array([1.0, -1.0, 1.0])
    camera = scene.camera
    mirrored = render.Camera(
        camera.position.data * flip,
        camera.look_at.data * flip,
        up=camera.up.data * flip,
        fov=camera.fov.data,
        width=camera.width,
        height=camera.height,
    )
    return render.Scene(scene.objects[1:], scene.lights, mirrored, scene.background)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_an_ideal_mirror_shows_the_scene_from_the_mirrored_camera(seed):
    """Each mirror pixel equals the mirrored camera's pixel in the same row, mirrored column
    (a reflection swaps left and right), wherever both rays make the same decisions (the
    shadow-ray offset depends on the scene's size, which the floor changes)."""
    scene = mirror_floor_scene(seed)
    image, info = render.render(scene, return_info=True)
    seen, seen_info = render.render(mirrored_view(scene), return_info=True)
    seen, seen_ids = seen.data[:, ::-1], seen_info.prim_id[:, ::-1, 0]
    mirror = on_mirror(info)
    in_mirror = info.bounces[0][..., 0]
    same = mirror & (np.where(in_mirror >= 0, in_mirror - MIRROR, -1) == seen_ids)
    same &= (info.bounce_lit[0][..., 0] == seen_info.lit[:, :, ::-1, 0]).all(axis=0)
    assert mirror.sum() > 100 and same.sum() >= 0.97 * mirror.sum()
    assert (in_mirror[mirror] >= MIRROR).any() and (in_mirror[mirror] == -1).any()
    scale = float(seen.max())
    np.testing.assert_allclose(image.data[same], seen[same], rtol=0, atol=1e-9 * scale)
    # One reflection only: the mirror's own second bounce never happens (nothing else reflects).
    assert (info.bounces[1] == -2).all()


def test_reflectance_scales_what_the_mirror_shows():
    full = render.render(mirror_floor_scene(0)).data
    half = render.render(mirror_floor_scene(0, reflectance=0.5)).data
    rgb = render.render(mirror_floor_scene(0, reflectance=(1.0, 0.5, 0.0))).data
    _, info = render.render(mirror_floor_scene(0), return_info=True)
    mirror = on_mirror(info)
    np.testing.assert_array_equal(half[mirror], 0.5 * full[mirror])
    np.testing.assert_array_equal(rgb[mirror], full[mirror] * [1.0, 0.5, 0.0])
    np.testing.assert_array_equal(half[~mirror], full[~mirror])


def test_max_bounces_zero_and_zero_reflectance_are_the_plain_render():
    scene = mirror_floor_scene(1)
    off, info = render.render(scene, max_bounces=0, return_info=True)
    assert info.bounces == [] and info.bounce_lit == []
    scene.objects[0].material.reflectance = md.tensor(0.0)
    plain, info = render.render(scene, return_info=True)
    assert info.bounces == []
    np.testing.assert_array_equal(off.data, plain.data)
    assert (off.data[on_mirror(info)] == 0).all()  # a black mirror: no term of its own


def facing_mirrors(seed: int, width=36, height=30) -> render.Scene:
    """Two parallel vertical mirrors (x = -1.5 and x = 1.5, 6 units long) with a sphere and
    a pyramid between them, seen along them, so that rays bounce from one to the other;
    the floor is diffuse, the sphere reflective too."""
    scene = random_scene(seed, lights=("point",), width=width, height=height)
    rng = np.random.default_rng(seed)
    for x in (-1.5, 1.5):
        vertices = [(x, 0.0, 2.0), (x, 0.0, -4.0), (x, 2.5, -4.0), (x, 2.5, 2.0)]
        tint = rng.uniform(0.6, 0.9, 3)
        material = render.Material(albedo=0.05 * tint, reflectance=tint)
        scene.objects.append(render.Mesh(vertices, QUAD_FACES, material))
    scene.spheres[0].material.reflectance = md.tensor(0.5)
    scene.camera.position.data[:] = (0.4 + rng.uniform(-0.2, 0.2), 1.5, 3.5)
    scene.camera.look_at.data[:] = (-0.5 + rng.uniform(-0.2, 0.2), 1.0, -3.0)
    scene.camera.fov.data[...] = 60.0
    return scene


def test_facing_mirrors_bounce_twice():
    scene = facing_mirrors(0)
    _, info = render.render(scene, return_info=True)
    second = info.bounces[1]
    assert (second >= 0).sum() >= 10  # rays that hit something after two reflections
    _, once = render.render(scene, max_bounces=1, return_info=True)
    assert len(once.bounces) == 1
    np.testing.assert_array_equal(once.bounces[0], info.bounces[0])


# Every parameter type, through reflections: (scene builder, parameters).
def _materials(s):
    return [obj.material for obj in s.objects]


CASES = {
    "light_position": lambda s: [s.lights[0].position],
    "light_intensity": lambda s: [s.lights[0].intensity],
    "mirror_reflectance": lambda s: [m.reflectance for m in _materials(s)],
    "albedo": lambda s: [m.albedo for m in _materials(s)],
    "specular": lambda s: [m.specular for m in _materials(s)],
    "mirror_vertices": lambda s: [s.objects[-1].vertices, s.objects[0].vertices],
    "pyramid_vertices": lambda s: [s.objects[1].vertices],
    "sphere": lambda s: [s.spheres[0].center, s.spheres[0].radius],
    "camera": lambda s: [s.camera.position, s.camera.look_at, s.camera.fov],
    "background": lambda s: [s.background],
}


@pytest.mark.parametrize("case", list(CASES))
@FEW
@given(seed=SEEDS)
@example(seed=0)
def test_gradients_through_two_facing_mirrors(case, seed):
    scene = facing_mirrors(seed)
    assert_gradient_matches(scene, CASES[case](scene))


@pytest.mark.parametrize("case", ["light_position", "sphere", "camera", "mirror_reflectance"])
@FEW
@given(seed=SEEDS)
@example(seed=3)
def test_gradients_through_a_mirror_floor_and_a_reflective_sphere(case, seed):
    scene = mirror_floor_scene(seed, reflectance=0.7)
    scene.objects[0].material.albedo = md.tensor([0.2, 0.3, 0.1])  # part mirror, part diffuse
    scene.spheres[0].material.reflectance = md.tensor([0.6, 0.5, 0.4])
    assert_gradient_matches(scene, CASES[case](scene))


def test_gradients_through_mirrors_with_antialiasing():
    scene = facing_mirrors(1)
    params = [scene.lights[0].position, scene.objects[-1].vertices, scene.spheres[0].center]
    assert_gradient_matches(scene, params, antialias=True)


def test_a_zero_reflectance_being_optimised_gets_its_gradient():
    """d image / d rho at rho = 0 is what the mirror ray sees: the ray must be traced."""
    scene = mirror_floor_scene(2)
    rho = md.tensor(0.0, requires_grad=True)
    scene.objects[0].material.reflectance = rho
    image = render.render(scene)
    image.sum().backward()
    with md.no_grad():
        scene.objects[0].material.reflectance = md.tensor(1.0)
        added = render.render(scene).data.sum() - image.data.sum()
    assert added > 0 and rho.grad == pytest.approx(added, rel=1e-9)


def test_a_mirror_inside_a_sphere():
    """Camera inside a reflective sphere: every ray hits its inside, and the mirror rays
    hit the far side again (the inside root)."""
    inside = render.Sphere((0.0, 0.0, 0.0), 3.0, render.Material((0.3, 0.4, 0.5), reflectance=0.5))
    camera = render.Camera((0.0, 0.0, 1.0), (0.0, 0.0, 0.0), width=12, height=10)
    scene = render.Scene([inside], [render.PointLight((0.5, 0.5, 0.5), 5.0)], camera)
    image, info = render.render(scene, return_info=True)
    assert (info.prim_id == 0).all() and (info.bounces[0] == 0).all()
    assert (info.bounces[1] == 0).all() and np.isfinite(image.data).all()
    assert_gradient_matches(scene, [inside.radius, scene.lights[0].position])


@pytest.mark.parametrize("bad", [-1, 1.5, True, "2", None])
def test_bad_max_bounces_is_refused(bad):
    scene = mirror_floor_scene(0, width=8, height=8)
    with pytest.raises(ValueError, match="max_bounces must be an integer >= 0"):
        render.render(scene, max_bounces=bad)


def test_reflectance_has_a_checked_shape():
    with pytest.raises(ValueError, match="reflectance"):
        render.Material((0.5, 0.5, 0.5), reflectance=(1.0, 0.5))
    quad = ground_quad(material=mirror_material())
    assert quad.material.reflective


EXAMPLE = Path(__file__).resolve().parents[3] / "examples" / "mirror_reflection.py"


def test_mirror_example_quick(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(EXAMPLE.parent))  # as `python examples/...` would
    monkeypatch.setattr(sys, "argv", [str(EXAMPLE), "--quick", "--quiet", "--out", str(tmp_path)])
    runpy.run_path(str(EXAMPLE), run_name="__main__")
    folder = tmp_path / "mirror_reflection"
    result = json.loads((folder / "mirror_reflection.json").read_text())
    (run,) = result["runs"]
    assert run["direct_teapot_rays"] == 0 and run["teapot_rays_via_mirror"] > 0
    assert run["position_error_pct"] < run["initial_position_error_pct"]
    figure = render.load_image(folder / "teapot_mirror_floor.png")
    assert figure.shape == (48, 96, 3)
    assert np.abs(figure[:, :48] - figure[:, 48:]).max() > 0.1  # the reflections show


def test_gradient_images_see_through_mirrors():
    """Forward mode (``render.gradient_image``) through reflections equals reverse mode."""
    scene = facing_mirrors(2)
    weights = np.random.default_rng(0).standard_normal((30, 36, 3))
    named = scene.named_parameters()
    for name in ("lights[0].position", "objects[3].vertices", "objects[2].center"):
        tensor = named[name]  # a mirror's vertices, the reflective sphere's centre
        direction = np.random.default_rng(1).standard_normal(tensor.shape)
        forward = float(np.sum(weights * render.gradient_image(scene, tensor, direction)))
        tensor.requires_grad, tensor.grad = True, None
        (render.render(scene) * md.tensor(weights)).sum().backward()
        reverse = float(np.sum(tensor.grad * direction))
        tensor.requires_grad = False
        assert forward == pytest.approx(reverse, rel=1e-9), name
