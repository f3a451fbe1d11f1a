"""``render.shade.fused``: a render that nothing differentiates, shaded by the compiled
shading and averaged into pixels off the tape, gives the taped pipeline's image (the same
functions run on the tape, ``minidiff.tape_only``; to rounding: a pixel's samples are
summed in another order), and the same bits on any number of threads."""

from __future__ import annotations

import numpy as np
import pytest

import minidiff as md
import render
from render.shade import fused
from tests.render_helpers import count_calls, random_scene, same_bits_on_one_and_two_threads


def _taped(scene, **options):
    """The same render on the tape: a light's intensity requires grad (the image's values
    do not depend on that), the compiled functions run on the tape."""
    light = scene.lights[0]
    strength = light.intensity if isinstance(light, render.PointLight) else light.irradiance
    strength.requires_grad = True
    with md.tape_only():
        image, info = render.render(scene, reuse_visibility=False, return_info=True, **options)
    assert image.node is not None  # the tape code ran
    strength.requires_grad = False
    return image.data, info


@pytest.mark.parametrize("spp", [1, 4])
@pytest.mark.parametrize(
    "options",
    [
        dict(lights=("point", "directional"), smooth=True, sphere=False),
        dict(lights=("directional",), sphere=False, background=(0.3, 0.2, 0.1)),
        dict(lights=("point", "point"), sphere=False, pyramid=True),
    ],
)
def test_the_fused_passes_give_the_taped_image(monkeypatch, options, spp):
    scene = random_scene(3, **options)
    calls = count_calls(monkeypatch, fused, "image_values")
    plain, info = render.render(scene, spp=spp, reuse_visibility=False, return_info=True)
    assert calls, "the fused passes did not run"
    taped, taped_info = _taped(scene, spp=spp)
    # A few ulps of the largest value: the Blinn-Phong lobes' powers (NumPy's vectorised
    # power against LLVM's pow) and, with spp > 1, the order of the sums.
    scale = np.abs(taped).max()
    np.testing.assert_allclose(plain.data, taped, rtol=0, atol=8 * np.finfo(float).eps * scale)
    np.testing.assert_array_equal(info.texel, taped_info.texel)
    np.testing.assert_array_equal(info.prim_id, taped_info.prim_id)


def test_the_paper_scene_gives_the_taped_image(monkeypatch):
    """Lambertian, one sample per pixel: nothing rounds differently, the same bits."""
    scene = render.paper_scene(40, 40, ground=True)
    calls = count_calls(monkeypatch, fused, "image_values")
    plain = render.render(scene, reuse_visibility=False)
    assert calls
    np.testing.assert_array_equal(plain.data, _taped(scene)[0])


def test_where_the_fused_passes_do_not_apply(monkeypatch):
    """Spheres, mirrors, textures, pixel pairs and differentiated renders take the taped
    path (whose meshes the compiled shading shades too, as one node:
    ``test_compiled_shading.py``)."""
    calls = count_calls(monkeypatch, fused, "image_values")
    render.render(random_scene(0), reuse_visibility=False)  # a sphere
    mirror = random_scene(1, sphere=False)
    mirror.objects[0].material.reflectance = md.tensor(0.5)
    render.render(mirror, reuse_visibility=False)
    plain = random_scene(2, sphere=False)
    render.render(plain, reuse_visibility=False, antialias=True)
    textured = random_scene(2, sphere=False, texture=True)
    render.render(textured, reuse_visibility=False)
    plain.lights[0].color.requires_grad = True
    render.render(plain, reuse_visibility=False)
    plain.lights[0].color.requires_grad = False
    assert calls == []
    render.render(plain, reuse_visibility=False)
    assert calls == [1]
    assert not fused.applies(random_scene(0), max_bounces=2)
    assert fused.applies(mirror, max_bounces=0)  # no mirror ray leaves it then


_THREADS = """
import render
scene = render.paper_scene(64, 48, ground=True)
def run():
    return [render.render(scene, spp=4, reuse_visibility=False).data.copy()]
"""


@pytest.mark.new_processes
def test_the_same_bits_on_one_and_two_threads():
    same_bits_on_one_and_two_threads(_THREADS)
