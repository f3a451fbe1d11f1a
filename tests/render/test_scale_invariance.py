"""A scene renders the same at any scale and anywhere (issue 9).

Scaling every length by s (and a point light's intensity by s^2, so that the irradiance
I / r^2 is unchanged) and translating everything by T must give the same image, shadows
included. Float64 carries about 16 digits, so a scene of size s can only be moved so far
before its own details drown in the coordinates' rounding: T is drawn up to 1e6 scene sizes
(|T| <= 1e6 s), with s from 1e-6 to 1e6. Every tolerance of the renderer is relative for
this to hold (the shadow rays' start offset, the light-distance and discriminant floors).
"""

from __future__ import annotations

import numpy as np
from hypothesis import example, given, settings
from hypothesis import strategies as st

import minidiff as md
import render
from tests.render_helpers import random_scene


def transformed(scene: render.Scene, scale: float, shift: np.ndarray) -> render.Scene:
    """The scene with every point p moved to scale * p + shift (in place, returned)."""
    for obj in scene.objects:
        if isinstance(obj, render.Mesh):
            obj.vertices.data[...] = obj.vertices.data * scale + shift
        else:
            obj.center.data[...] = obj.center.data * scale + shift
            obj.radius.data[...] = obj.radius.data * scale
    for light in scene.lights:
        if isinstance(light, render.PointLight):
            light.position.data[...] = light.position.data * scale + shift
            light.intensity.data[...] = light.intensity.data * scale**2
    camera = scene.camera
    camera.position.data[...] = camera.position.data * scale + shift
    camera.look_at.data[...] = camera.look_at.data * scale + shift
    return scene


def render_plain(scene, antialias):
    with md.no_grad():
        image, info = render.render(
            scene, reuse_visibility=False, antialias=antialias, return_info=True
        )
    return image.data, info


@settings(max_examples=25)
@given(
    seed=st.integers(0, 10_000),
    log_scale=st.floats(-6.0, 6.0),
    shift=st.tuples(*[st.floats(-1e6, 1e6)] * 3),
    lights=st.sampled_from([("point",), ("directional",), ("point", "directional")]),
    antialias=st.booleans(),
)
# A shadow ray from a sphere's terminator met the sphere itself at t ~ 0 after the move: the
# offset towards the light barely leaves a surface it grazes (visibility._ignore_spheres_facing).
@example(
    seed=315, log_scale=1.40625, shift=(0.0, 0.0, 191466.0), lights=("point",), antialias=False
)
def test_scaled_and_translated_scene_renders_the_same(seed, log_scale, shift, lights, antialias):
    reference, ref_info = render_plain(random_scene(seed, lights=lights), antialias)
    scale = 10.0**log_scale
    moved = transformed(random_scene(seed, lights=lights), scale, np.array(shift) * scale)
    image, info = render_plain(moved, antialias)
    np.testing.assert_array_equal(info.lit, ref_info.lit)  # shadows included
    np.testing.assert_array_equal(info.prim_id, ref_info.prim_id)
    assert np.abs(image - reference).max() <= 1e-6 * np.abs(reference).max()


def test_far_from_the_origin_point_light_shadows_survive():
    """The case that failed: a unit scene at x = 1e7 lost every point-light shadow."""
    reference, ref_info = render_plain(random_scene(4), False)
    assert (~ref_info.lit).any()  # the scene has shadows
    _, info = render_plain(transformed(random_scene(4), 1.0, np.array([1e7, 0, 0])), False)
    np.testing.assert_array_equal(info.lit, ref_info.lit)
