"""``render.shade.adjoint``: steps 2, 3 and 5 as one tape node with a hand-written adjoint.

Its gradients are tied to the tape's (``shade_camera_hits`` then ``image_from_hits``, the
reference, called directly on the same visibility) for every parameter type the node
takes: the camera (position, look_at, up, fov), every vertex of flat and smooth meshes
(with normals computed on the tape and given), the normals, point and directional lights
(position or direction, strength, colour), every material parameter and the background;
on random scenes and on the paper scene with its ground, at 1 and 4 samples per pixel.
Also: its image is the fused passes' (the same bits as a render that nothing
differentiates), ``render`` takes it where it applies and the tape elsewhere (textures,
spheres, mirrors, forward mode, pixel pairs), and its gradients do not depend on the
thread count.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import minidiff as md
import render
from render.film import image_from_hits
from render.scene.cache import cache_for
from render.scene.camera import camera_frame
from render.scene.placement import placed
from render.shade import adjoint
from render.shade.hits import shade_camera_hits
from render.trace.visibility import trace_visibility
from tests.render_helpers import count_calls, random_scene, same_bits_on_one_and_two_threads

#: Largest difference allowed, relative to the reference gradient's largest entry (seen:
#: 8e-14, on a camera position whose gradient sums terms of both signs).
TOLERANCE = 1e-10

#: Parameters the node does not take: a non-zero reflectance turns it off, UVs and
#: textures belong to textured materials.
_NOT_TAKEN = ("reflectance", "uvs", "texture")


def _differentiate_all(scene: render.Scene) -> list[str]:
    """Every parameter the node takes requires grad; their names."""
    names = []
    for name, tensor in scene.named_parameters().items():
        if not name.endswith(_NOT_TAKEN):
            tensor.requires_grad = True
            names.append(name)
    return names


def _image(scene: render.Scene, spp: int, node: bool) -> md.Tensor:
    """The image of steps 2, 3 and 5: the node's, or the reference's on the tape."""
    world = placed(scene)
    cache = cache_for(scene, False)
    visibility = trace_visibility(world, cache, True, spp, True)
    frame = camera_frame(world.camera)
    if node:
        assert adjoint.applies(world, max_bounces=2)
        return adjoint.image(world, visibility, frame, spp)
    shading = shade_camera_hits(world, visibility, frame, cache, None, surfaces=False)
    return image_from_hits(world, visibility.primary.prim_id, shading.colour, shading.rays, spp)


def _gradients(scene: render.Scene, names, weights, image_of) -> dict[str, np.ndarray]:
    """d sum(image * weights) / d p for every parameter named."""
    parameters = scene.named_parameters()
    for name in names:
        parameters[name].grad = None
    md.sum(image_of() * weights).backward()
    return {
        name: np.zeros(parameters[name].shape)
        if parameters[name].grad is None
        else parameters[name].grad.copy()
        for name in names
    }


def _largest_difference(scene: render.Scene, spp: int, names=None) -> float:
    """The node's gradients against the reference's, for every parameter named (default:
    all it takes); returns the largest difference relative to each gradient's scale, after
    checking that the images agree and every gradient is non-trivially compared."""
    names = _differentiate_all(scene) if names is None else names
    camera = scene.camera
    weights = np.random.default_rng(7).normal(size=(camera.height, camera.width, 3))
    reference = _gradients(scene, names, weights, lambda: _image(scene, spp, node=False))
    ours = _gradients(scene, names, weights, lambda: _image(scene, spp, node=True))
    worst = 0.0
    for name in names:
        scale = np.abs(reference[name]).max()
        difference = np.abs(ours[name] - reference[name]).max()
        assert ours[name].shape == reference[name].shape, name
        assert difference <= TOLERANCE * scale or scale == difference == 0.0, (
            f"{name}: {difference:.3g} of a gradient of scale {scale:.3g}"
        )
        worst = max(worst, difference / scale if scale else 0.0)
    return worst


def _given_normals(seed: int) -> render.Scene:
    """A random scene whose pyramid is smooth with normals of its own (tilted away from
    the ones its faces would give)."""
    scene = random_scene(seed, sphere=False, lights=("point", "directional"))
    pyramid = scene.objects[1]
    vertices = pyramid.vertices.data
    normals = vertices - vertices.mean(axis=0) + np.random.default_rng(seed).normal(0, 0.2, (5, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    scene.objects[1] = render.Mesh(
        vertices, pyramid.faces, pyramid.material, normals=normals, smooth=True
    )
    return scene


SCENES = {
    "flat, point light": lambda: random_scene(1, sphere=False),
    "smooth, computed normals, both lights": lambda: random_scene(
        2, sphere=False, smooth=True, lights=("point", "directional")
    ),
    "smooth, given normals": lambda: _given_normals(3),
    "directional light, no ambient background": lambda: random_scene(
        4, sphere=False, lights=("directional",), background=(0.0, 0.0, 0.0)
    ),
    "paper scene with ground": lambda: render.paper_scene(48, 48, ground=True),
}


@pytest.mark.parametrize("spp", [1, 4])
@pytest.mark.parametrize("name", list(SCENES))
def test_the_gradients_are_the_tapes(name, spp):
    assert _largest_difference(SCENES[name](), spp) < TOLERANCE


def test_emission_and_a_zero_specular_that_is_differentiated():
    """An emissive material and a specular coefficient of zero (the tape adds its lobe
    because it is differentiated) in a (3,)- and a scalar-shaped parameter."""
    scene = random_scene(5, sphere=False)
    ground, pyramid = (obj.material for obj in scene.objects)
    ground.emission = md.tensor([0.2, 0.1, 0.3])
    pyramid.specular = md.tensor(0.0)
    pyramid.ambient = md.tensor([0.05, 0.0, 0.02])
    assert _largest_difference(scene, 1) < TOLERANCE


def test_a_few_parameters_only():
    """Only a light and one mesh's vertices differentiated: the others get no gradient."""
    scene = random_scene(6, sphere=False, smooth=True)
    names = ["lights[0].intensity", "objects[1].vertices"]
    for name in names:
        scene.named_parameters()[name].requires_grad = True
    assert _largest_difference(scene, 4, names) < TOLERANCE
    assert scene.camera.position.grad is None and scene.background.grad is None


@settings(max_examples=5, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    spp=st.sampled_from([1, 4]),
    lights=st.sampled_from([("point",), ("directional",), ("point", "directional"), ()]),
    smooth=st.booleans(),
)
def test_drawn_scenes(seed, spp, lights, smooth):
    scene = random_scene(seed, sphere=False, lights=lights, smooth=smooth, width=20, height=16)
    assert _largest_difference(scene, spp) < TOLERANCE


@pytest.mark.parametrize("spp", [1, 4])
def test_render_takes_the_node_with_the_fused_image(monkeypatch, spp):
    """Its image is the fused passes' (a render that nothing differentiates), bit for bit;
    ``return_info`` still reports the decisions (no texture cells)."""
    scene = random_scene(8, sphere=False, smooth=True, lights=("point", "directional"))
    plain, plain_info = render.render(scene, spp=spp, reuse_visibility=False, return_info=True)
    scene.camera.position.requires_grad = True
    calls = count_calls(monkeypatch, adjoint, "image")
    image, info = render.render(scene, spp=spp, reuse_visibility=False, return_info=True)
    assert calls == [1] and image.node is not None
    np.testing.assert_array_equal(image.data, plain.data)
    np.testing.assert_array_equal(info.prim_id, plain_info.prim_id)
    np.testing.assert_array_equal(info.lit, plain_info.lit)
    assert np.all(info.texel == -1)


@pytest.mark.parametrize("antialias", [False, "boundary"])
def test_render_gradients_with_and_without_the_node(monkeypatch, antialias):
    """``render``'s gradients through the node equal those it gives on the tape (the
    boundary term's parts added on top of the node's image)."""
    scene = render.paper_scene(40, 32, ground=True)
    names = _differentiate_all(scene)
    weights = np.random.default_rng(3).normal(size=(32, 40, 3))

    def image():
        return render.render(scene, spp=4, antialias=antialias, reuse_visibility=False)

    calls = count_calls(monkeypatch, adjoint, "image")
    ours = _gradients(scene, names, weights, image)
    assert calls == [1]
    monkeypatch.setattr(adjoint, "applies", lambda *_: False)
    reference = _gradients(scene, names, weights, image)
    assert calls == [1]
    for name in names:
        scale = np.abs(reference[name]).max()
        np.testing.assert_allclose(ours[name], reference[name], rtol=0, atol=TOLERANCE * scale)


def test_where_the_node_does_not_apply(monkeypatch):
    """Textures, spheres, mirrors, pixel pairs and forward-mode tangents take the tape."""
    calls = count_calls(monkeypatch, adjoint, "image")
    textured = random_scene(0, sphere=False, texture=True)
    spheres = random_scene(0)
    mirror = random_scene(1, sphere=False)
    mirror.objects[0].material.reflectance = md.tensor(0.5)
    for scene in (textured, spheres, mirror):
        scene.lights[0].position.requires_grad = True
        assert not adjoint.applies(placed(scene), max_bounces=2)
        assert render.render(scene, reuse_visibility=False).node is not None
    assert adjoint.applies(mirror, max_bounces=0)  # no mirror ray leaves it then
    plain = random_scene(2, sphere=False)
    plain.lights[0].position.requires_grad = True
    render.render(plain, reuse_visibility=False, antialias=True)
    assert calls == []
    plain.lights[0].position.requires_grad = False
    with md.tangents({plain.lights[0].intensity: np.array(1.0)}):
        assert not adjoint.applies(plain, max_bounces=2)
        image = render.render(plain, reuse_visibility=False)
    assert calls == [] and image.tangent is not None
    render.render(plain, reuse_visibility=False)  # nothing differentiated: the fused passes
    assert calls == []
    # Only a light moves: the tape, which reuses the hits' surfaces from the render cache.
    plain.lights[0].position.requires_grad = True
    assert adjoint.route(placed(plain), pairs=False, max_bounces=2) == "tape"
    render.render(plain, reuse_visibility=False)
    assert calls == []
    plain.meshes[0].vertices.requires_grad = True  # the hits move: the node
    render.render(plain, reuse_visibility=False)
    assert calls == [1]


_THREADS = """
import numpy as np, render, minidiff as md
scene = render.paper_scene(64, 48, ground=True)
params = [scene.camera.position, scene.lights[0].position, scene.lights[0].intensity,
          scene.meshes[0].vertices, scene.meshes[1].vertices, scene.background,
          scene.meshes[0].material.albedo]
for p in params:
    p.requires_grad = True
weights = np.random.default_rng(0).normal(size=(48, 64, 3))
def run():
    for p in params:
        p.grad = None
    md.sum(render.render(scene, spp=4, reuse_visibility=False) * weights).backward()
    return [p.grad.copy() for p in params]
"""


@pytest.mark.new_processes
def test_the_same_gradients_on_one_and_two_threads():
    same_bits_on_one_and_two_threads(_THREADS)


def test_what_no_ray_hits_gets_a_zero_gradient():
    """As on the tape: a camera that sees nothing, a mesh that no ray hits and a shininess
    without a lobe get zero gradients (``render`` ties the image to every parameter that
    requires grad, whichever route computed it)."""
    position = md.tensor([3.0, 2.0, 5.0], requires_grad=True)
    away = render.paper_scene(16, 16, camera_position=position, look_at=(3.0, 2.0, 10.0))
    assert adjoint.applies(away, max_bounces=2)
    md.sum(render.render(away, reuse_visibility=False)).backward()
    np.testing.assert_array_equal(position.grad, np.zeros(3))
    scene = random_scene(9, sphere=False)
    hidden = random_scene(10, sphere=False).objects[1]
    hidden.vertices = md.tensor(hidden.vertices.data + [0.0, 0.0, 50.0])  # behind the camera
    scene.objects.append(hidden)
    scene.objects[0].material.specular = md.tensor(0.0)
    shininess = scene.objects[0].material.shininess
    for tensor in (hidden.vertices, hidden.material.albedo, shininess):
        tensor.requires_grad = True
    scene.lights[0].intensity.requires_grad = True
    md.sum(render.render(scene, reuse_visibility=False)).backward()
    for tensor in (hidden.vertices, hidden.material.albedo, shininess):
        np.testing.assert_array_equal(tensor.grad, np.zeros(tensor.shape))
    assert np.abs(scene.lights[0].intensity.grad).max() > 0
