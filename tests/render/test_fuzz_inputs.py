"""Extreme and bad scene values, drawn by Hypothesis: every render either refuses the scene
with a clear error (naming the class or ``render`` and what was expected), or gives a finite
image (non-negative without antialiasing) whose gradients are finite.

This is the property behind the hand cases in ``tests/render/test_errors.py`` and
``tests/minidiff/test_edge_cases.py``: no crash, no NaN or inf, no raw NumPy or Python error.
"""

from __future__ import annotations

import numpy as np
from hypothesis import example, given, settings
from hypothesis import strategies as st

import minidiff as md
import render

#: Values a user might type or an optimiser might produce: ordinary, tiny, huge, zero,
#: negative, not finite.
EXTREME = st.one_of(
    st.floats(-10.0, 10.0),
    st.sampled_from([0.0, -0.0, 1e-300, -1e-300, 1e-12, 1e12, -1e12, 1e61, 1e200, -1e200]),
    st.sampled_from([np.inf, -np.inf, np.nan]),
)
VECTOR = st.tuples(EXTREME, EXTREME, EXTREME)

#: A clear error names the object or function that refused the value.
OWNERS = ("Camera", "PointLight", "DirectionalLight", "Sphere", "Mesh", "Material", "Scene",
          "render")  # fmt: skip


def build_and_render(field: str, value) -> None:
    """The paper scene (plus a sphere) at 16 x 12 with one value replaced; render it with
    every parameter differentiated and check the outcome."""
    try:
        scene = render.paper_scene(width=16, height=12)
        scene.objects.append(render.Sphere((1.5, 0.5, 1.0), 0.5, render.Material((0.5,) * 3)))
        camera, light = scene.camera, scene.lights[0]
        sphere, teapot = scene.objects[-1], scene.objects[0]
        if field == "vertex":
            vertices = teapot.vertices.data.copy()
            vertices[7] = value
            teapot.vertices = md.tensor(vertices)
        else:
            owner, name = {
                "camera.position": (camera, "position"),
                "camera.look_at": (camera, "look_at"),
                "camera.fov": (camera, "fov"),
                "light.position": (light, "position"),
                "light.intensity": (light, "intensity"),
                "sphere.center": (sphere, "center"),
                "sphere.radius": (sphere, "radius"),
                "albedo": (teapot.material, "albedo"),
            }[field]
            setattr(owner, name, md.tensor(value))
        for p in scene.parameters():
            p.requires_grad = True
        for antialias in (False, True):
            image = render.render(scene, antialias=antialias, reuse_visibility=False)
            image.sum().backward()
            assert np.isfinite(image.data).all(), field
            # The pixel-pair blends of antialias=True can undershoot 0 slightly where several
            # pairs overlap one sample (found here: -0.0018 with the camera at (6, 7, 1));
            # the exact boundary term of issue 23 replaces them. Plain renders never do.
            # A negative albedo is rendered as given (the image is linear in it, as an
            # optimiser stepping through it needs): only other fields must keep it >= 0.
            assert antialias or field == "albedo" or (image.data >= 0).all(), field
            for p in scene.parameters():
                assert p.grad is None or np.isfinite(p.grad).all(), (field, p.shape)
                p.grad = None
    except (ValueError, TypeError) as error:
        assert str(error).startswith(OWNERS), f"{field}={value!r}: unclear error {error!r}"


@settings(max_examples=60, deadline=None)
@given(
    field=st.sampled_from(
        ["camera.position", "camera.look_at", "light.position", "sphere.center", "albedo", "vertex"]
    ),  # fmt: skip
    value=VECTOR,
)
def test_extreme_vectors_are_refused_clearly_or_render_finite(field, value):
    build_and_render(field, np.array(value))


@settings(max_examples=40, deadline=None)
@given(field=st.sampled_from(["camera.fov", "light.intensity", "sphere.radius"]), value=EXTREME)
# A sphere this large shadows only itself near the teapot: shadow pairs with no triangle
# receiver crashed (an IndexError in plane_normal of no triangles).
@example(field="sphere.radius", value=2.0)
def test_extreme_scalars_are_refused_clearly_or_render_finite(field, value):
    build_and_render(field, np.array(value))
