"""``render.gradient_image`` (forward mode through the renderer) and ``write_gradient_png``.

For each kind of parameter (light position and intensity, albedo, camera position, a mesh's
vertices, a sphere's centre), on small random scenes (``render_helpers.random_scene``,
24 x 24), with antialias False and True:

- against central differences of ``render.render`` along the same direction (fourth order,
  (4 D(h) - D(2h)) / 3, h = 1e-6 relative), over the pixels whose discrete decisions no
  perturbed render changes (``render_helpers._same_visibility``, the mask of
  ``tests/render/test_gradients.py``; see there for why); Eq. 3 relative error below 1e-5;
- against reverse mode: sum((dL/dI) * gradient image) equals dL/dtheta . direction from
  ``backward`` for L = sum(I * W), W a random image, to 1e-9 relative, over every parameter
  of the scene (no mask needed: both are the derivative for fixed decisions).
"""

from __future__ import annotations

import runpy
import sys
from pathlib import Path

import numba
import numpy as np
import pytest
from PIL import Image

import minidiff as md
import render
from render.scene.image import diverging_colours
from tests.render_helpers import _same_visibility, random_scene

SIZE = 24
FD_TOLERANCE = 1e-5
IDENTITY_TOLERANCE = 1e-9


@pytest.fixture(autouse=True, scope="module")
def one_numba_thread():
    """Tiny renders: a parallel Numba launch costs more than the work (as in
    tests/render/test_gradients.py). Same results."""
    previous = numba.get_num_threads()
    numba.set_num_threads(1)
    yield
    numba.set_num_threads(previous)


def scene_for(seed, **options):
    return random_scene(seed, width=SIZE, height=SIZE, **options)


def unit_direction(shape, seed):
    d = np.random.default_rng(seed).standard_normal(shape)
    return d / np.linalg.norm(d)


def central_difference_image(scene, parameter, direction, **render_kwargs):
    """(4 D(h) - D(2h)) / 3 of the rendered image along ``direction`` and the (H, W) mask
    of pixels whose decisions no perturbed render changes."""
    with md.no_grad():
        _, reference = render.render(scene, return_info=True, **render_kwargs)
    base = parameter.data.copy()
    h = 1e-6 * max(1.0, float(np.abs(base).max()))
    same = np.ones((SIZE, SIZE), dtype=bool)
    quotients = []
    try:
        for m in (1, 2):
            images = []
            for sign in (1.0, -1.0):
                parameter.data = base + sign * m * h * direction
                with md.no_grad():
                    image, info = render.render(scene, return_info=True, **render_kwargs)
                same &= _same_visibility(info, reference)
                images.append(image.data)
            quotients.append((images[0] - images[1]) / (2 * m * h))
    finally:
        parameter.data = base
    return (4.0 * quotients[0] - quotients[1]) / 3.0, same


# name -> (random_scene options, parameter name in scene.named_parameters())
PARAMETERS = {
    "light_position": ({}, "lights[0].position"),
    "light_intensity": ({}, "lights[0].intensity"),
    "albedo": ({}, "objects[0].material.albedo"),
    "camera_position": ({}, "camera.position"),
    "mesh_vertices": ({}, "objects[1].vertices"),
    "sphere_center": ({}, "objects[2].center"),
}


@pytest.mark.parametrize("antialias", [False, True])
@pytest.mark.parametrize("case", sorted(PARAMETERS))
@pytest.mark.parametrize("seed", [0, 7])
def test_gradient_image_matches_finite_differences(case, antialias, seed):
    options, name = PARAMETERS[case]
    scene = scene_for(seed, **options)
    parameter = scene.named_parameters()[name]
    direction = unit_direction(parameter.shape, seed)
    image = render.gradient_image(scene, name, direction, antialias=antialias)
    fd, same = central_difference_image(scene, parameter, direction, antialias=antialias)
    assert image.shape == (SIZE, SIZE, 3) and image.dtype == np.float64
    assert same.sum() >= 0.9 * same.size, f"only {same.sum()}/{same.size} pixels compared"
    ad, fd = image[same], fd[same]
    assert np.linalg.norm(fd) > 1e-3, "the parameter should visibly change the image"
    rel = np.linalg.norm(ad - fd) / (np.linalg.norm(fd) + 1e-8)
    assert rel < FD_TOLERANCE, f"relative error {rel:.2e}"


def reverse_mode_directional(scene, parameter, weights, direction, **render_kwargs):
    """dL/dtheta . direction for L = sum(render(scene) * weights), by backward."""
    saved = parameter.requires_grad
    parameter.requires_grad, parameter.grad = True, None
    try:
        image = render.render(scene, **render_kwargs)
        if not image.requires_grad:  # the image does not depend on the parameter
            return 0.0
        (image * weights).sum().backward()
        return float(np.sum(parameter.grad * direction))
    finally:
        parameter.requires_grad, parameter.grad = saved, None


@pytest.mark.parametrize("antialias", [False, True])
@pytest.mark.parametrize("seed", [3, 11])
def test_gradient_image_agrees_with_reverse_mode(antialias, seed):
    """Every parameter of a scene with a black background, no ambient and no specular on
    the ground: the renderer skips work on such constants, and must not when they carry a
    tangent (the background, ambient and specular images are not zero)."""
    scene = scene_for(seed, background=(0.0, 0.0, 0.0))
    ground = scene.objects[0].material
    ground.ambient = md.tensor(0.0)
    ground.specular = md.tensor(0.0)
    render.render(scene, antialias=antialias)  # fill the caches (the surface cache too)
    weights = np.random.default_rng(seed).standard_normal((SIZE, SIZE, 3))
    nonzero = []
    for name, parameter in scene.named_parameters().items():
        direction = unit_direction(parameter.shape, seed + 1)
        image = render.gradient_image(scene, parameter, direction, antialias=antialias)
        forward = float(np.sum(weights * image))
        reverse = reverse_mode_directional(
            scene, parameter, weights, direction, antialias=antialias
        )
        scale = max(abs(reverse), 1e-12)
        assert abs(forward - reverse) <= IDENTITY_TOLERANCE * scale, (name, forward, reverse)
        if abs(reverse) > 1e-6:
            nonzero.append(name)
    for name in ("background", "objects[0].material.ambient", "objects[0].material.specular"):
        assert name in nonzero, f"{name}: the gradient image should not vanish"
    assert len(nonzero) >= 15


def test_one_image_per_component():
    """direction=None stacks the partial derivatives; they combine linearly to any
    direction's image."""
    scene = scene_for(5)
    position = scene.lights[0].position
    images = render.gradient_image(scene, position)
    assert images.shape == (3, SIZE, SIZE, 3)
    d = np.array([0.3, -1.0, 2.0])
    along = render.gradient_image(scene, position, d)
    np.testing.assert_allclose(np.tensordot(d, images, axes=1), along, rtol=1e-12, atol=1e-14)
    np.testing.assert_array_equal(images[1], render.gradient_image(scene, position, [0, 1, 0]))
    intensity = render.gradient_image(scene, "lights[0].intensity")
    assert intensity.shape == (SIZE, SIZE, 3)  # a 0-d parameter: one image
    # The image is linear in a point light's radiant intensity I: image(I) = image(0) +
    # I * d image / dI exactly.
    light = scene.lights[0]
    value = float(light.intensity.data)
    with md.no_grad():
        full = render.render(scene).data
        light.intensity.data = np.array(0.0)
        dark = render.render(scene).data
        light.intensity.data = np.array(value)
    assert np.abs(intensity).max() > 1e-3
    np.testing.assert_allclose(dark + value * intensity, full, rtol=1e-12, atol=1e-14)


def test_gradient_image_leaves_the_scene_alone():
    scene = scene_for(2)
    vertices = scene.objects[1].vertices
    before = vertices.data.copy()
    render.gradient_image(scene, vertices, np.ones(vertices.shape), antialias=True)
    np.testing.assert_array_equal(vertices.data, before)
    assert vertices.tangent is None and not vertices.requires_grad and vertices.grad is None


def test_gradient_image_refuses_bad_arguments():
    scene = scene_for(2)
    with pytest.raises(ValueError, match="no parameter 'lights\\[3\\].position'.*camera.position"):
        render.gradient_image(scene, "lights[3].position")
    with pytest.raises(ValueError, match="not one of the scene's parameters"):
        render.gradient_image(scene, md.tensor([1.0, 2.0, 3.0]))
    with pytest.raises(TypeError, match="parameter must be a minidiff Tensor"):
        render.gradient_image(scene, 3)
    with pytest.raises(ValueError, match=r"direction \(for camera.position\) has shape \(2,\), "):
        render.gradient_image(scene, "camera.position", np.ones(2))
    with pytest.raises(ValueError, match=r"expected \(3,\)"):
        render.gradient_image(scene, "camera.position", np.ones(2))
    with pytest.raises(TypeError, match="return_info"):
        render.gradient_image(scene, "camera.position", np.ones(3), return_info=True)
    with pytest.raises(TypeError, match="render.Scene"):
        render.gradient_image("scene", "camera.position")


def test_write_gradient_png(tmp_path):
    """Zero is white, positive red, negative blue, symmetric around zero; the file has the
    (enlarged) picture on top and a scale bar below."""
    channel = np.zeros((8, 16))
    channel[:, :4] = -2.0
    channel[:, 12:] = 2.0
    path = render.write_gradient_png(channel, tmp_path / "g.png", scale=2.0, label="test")
    pixels = np.asarray(Image.open(path).convert("RGB"))
    factor = 256 // 16
    assert pixels.shape[1] == 256 and pixels.shape[0] > 8 * factor  # the bar is below
    top = pixels[: 8 * factor]
    np.testing.assert_array_equal(top[0, 8 * factor], [255, 255, 255])  # zero: white
    red, blue = top[0, -1].astype(int), top[0, 0].astype(int)
    assert red[0] > red[2] + 100 and blue[2] > blue[0] + 100
    np.testing.assert_array_equal(diverging_colours(np.array([0.0]), 1.0), [[255, 255, 255]])
    # An (H, W, 3) image: its channels are summed; an automatic scale; a clear error for bad
    # input.
    rgb = np.stack([channel, np.zeros_like(channel), channel], axis=-1)
    assert render.write_gradient_png(rgb, tmp_path / "rgb.png").exists()
    with pytest.raises(ValueError, match=r"shape \(H, W, 3\) or \(H, W\)"):
        render.write_gradient_png(np.zeros((4, 4, 2)), tmp_path / "bad.png")
    with pytest.raises(ValueError, match="NaN or inf"):
        render.write_gradient_png(np.full((4, 4), np.nan), tmp_path / "bad.png")
    with pytest.raises(ValueError, match="scale must be a positive number"):
        render.write_gradient_png(channel, tmp_path / "bad.png", scale=0.0)
    with pytest.raises(ValueError, match="must end in .png"):
        render.write_gradient_png(channel, tmp_path / "bad.jpg")


EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "gradient_images.py"


def test_gradient_images_example_runs(tmp_path, monkeypatch):
    """``examples/gradient_images.py`` at 24 x 24 writes the render and five gradient PNGs."""
    monkeypatch.setattr(sys, "argv", [str(EXAMPLE), "--size", "24", "--out", str(tmp_path)])
    runpy.run_path(str(EXAMPLE), run_name="__main__")
    stems = ["render", "light_x", "light_intensity", "albedo_red", "camera_x", "teapot_x"]
    for stem in stems:
        with Image.open(tmp_path / "gradient_images" / f"{stem}.png") as image:
            assert image.width >= 24
