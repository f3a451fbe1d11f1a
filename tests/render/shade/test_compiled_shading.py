"""``render.shade.compiled`` is ``surface_at`` + ``shade_surface`` compiled: on random meshes
(flat, smooth, with normals of their own), materials (lobes, ambient, emission) and
lights, its forward, its gradient for every input (camera, vertices, normals, material,
lights) and its tangent equal the same functions run on the tape, to 1e-12 of each array's
scale; whole renders, differentiated or not, equal the same renders with the compiled
functions run on the tape (``minidiff.tape_only``)."""

from __future__ import annotations

import contextlib

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

import minidiff as md
import render
from render.scene.camera import camera_frame, ray_directions
from render.shade import compiled
from render.shade.lighting import shade_surface
from render.shade.surface import surface_at
from tests.render_helpers import count_calls, random_scene

RTOL = 1e-12
#: Gradients of shared parameters (the camera, materials, lights) are sums over the hits,
#: taken in another order than the tape's (NumPy's pairwise sum against the compiled
#: chunks), with cancellations: within 1e-11 of the result's scale.
GRAD_RTOL = 1e-11


def _mesh(rng, smooth: bool, normals: bool, specular: bool, emission: bool):
    vertices = rng.uniform(-1.0, 1.0, (7, 3)) + np.array([0.0, 0.0, 4.0])
    faces = np.array([rng.choice(7, 3, replace=False) for _ in range(9)])
    material = render.Material(
        rng.uniform(0.1, 0.9, 3),
        specular=rng.uniform(0.0, 0.5, 3) if specular else 0.0,
        shininess=rng.uniform(1.0, 60.0),
        ambient=rng.uniform(0.0, 0.1),
        emission=rng.uniform(0.0, 0.3, 3) if emission else 0.0,
    )
    return render.Mesh(
        vertices, faces, material, normals=rng.normal(size=(7, 3)) if normals else None,
        smooth=smooth,
    )  # fmt: skip


def _smallest_vertex_normal(mesh) -> float:
    """The shortest of the mesh's summed face normals at its vertices (before normalising)."""
    v, faces = mesh.vertices.data, mesh.faces
    n = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])
    summed = np.zeros_like(v)
    for corner in range(3):
        np.add.at(summed, faces[:, corner], n)
    return float(np.linalg.norm(summed[np.unique(faces)], axis=1).min())


def _lights(rng, kinds):
    lights = []
    for kind in kinds:
        colour = rng.uniform(0.5, 1.0, 3)
        if kind == "point":
            lights.append(render.PointLight(rng.uniform(-3, 3, 3), rng.uniform(1, 20), colour))
        else:
            lights.append(render.DirectionalLight(rng.normal(size=3), rng.uniform(0.5, 3), colour))
    return lights


def _close(actual, expected, what: str, rtol: float = RTOL) -> None:
    actual, expected = np.asarray(actual), np.asarray(expected)
    scale = max(np.abs(expected).max(initial=0.0), 1e-300)
    np.testing.assert_allclose(actual, expected, rtol=0, atol=rtol * scale, err_msg=what)


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 2**31),
    smooth=st.booleans(),
    normals=st.booleans(),
    specular=st.booleans(),
    emission=st.booleans(),
    kinds=st.lists(st.sampled_from(["point", "directional"]), max_size=3),
)
def test_shade_mesh_equals_surface_at_then_shade_surface_in_value_gradient_and_tangent(
    seed, smooth, normals, specular, emission, kinds
):
    rng = np.random.default_rng(seed)
    mesh = _mesh(rng, smooth, normals and smooth, specular, emission)
    # Faces drawn at random can cancel at a vertex (a face and its reverse): its computed
    # normal is then rounding noise, and so is its gradient, on the tape and compiled alike.
    assume(not (smooth and not normals) or _smallest_vertex_normal(mesh) > 1e-6)
    lights = _lights(rng, kinds)
    k = 40
    faces = rng.integers(0, mesh.num_faces, k)
    faces[:3] = faces[0]  # repeated faces: their vertices' gradients add up
    coords = rng.uniform(-0.4, 0.4, (k, 2))
    camera = render.Camera([0.1, -0.2, 0.0], [0.0, 0.1, 4.0], [0.0, 1.0, 0.0], 45.0, 16, 16)
    lit = [(rng.uniform(size=k) < 0.7) * 1.0 for _ in lights]
    weights = rng.normal(size=(k, 3))
    owners = [camera, mesh, mesh.material, *lights]
    params = [t for owner in owners for t in owner.named_parameters().values()]

    def taped():
        frame = camera_frame(camera)
        surface = surface_at(mesh, faces, frame[3], ray_directions(frame, coords))
        return shade_surface(surface, mesh.material, lights, lit)[0]

    def compiled_shading():
        return compiled.shade_mesh(mesh, faces, camera_frame(camera), coords, lights, lit)

    tangents = [rng.normal(size=p.shape) for p in params[:6]]  # camera, vertices, ...
    results = {}
    for name, run in (("tape", taped), ("compiled", compiled_shading)):
        for p in params:
            p.requires_grad, p.grad = True, None
        colour = run()
        md.sum(colour * weights).backward()
        grads = [None if p.grad is None else p.grad.copy() for p in params]
        for p in params:
            p.requires_grad = False
        with md.tangents(dict(zip(params[:6], tangents, strict=True))):
            tangent = run().tangent
        results[name] = (colour.data, grads, tangent)
    (value, grads, tangent), (value_c, grads_c, tangent_c) = results["tape"], results["compiled"]
    _close(value_c, value, "value")
    for p, g, g_c in zip(params, grads, grads_c, strict=True):
        if g is None or not np.any(g):
            assert g_c is None or not np.any(g_c), p
        else:
            _close(g_c, g, f"gradient of a {p.shape} parameter", GRAD_RTOL)
    _close(tangent_c, tangent, "tangent")


@pytest.mark.parametrize("seed", range(2))
@pytest.mark.parametrize(
    "options",
    [
        dict(lights=("point", "directional"), smooth=True, sphere=False),
        dict(lights=("directional",)),
        dict(lights=("point",), smooth=True, sphere=False),
    ],
)
def test_renders_equal_the_same_renders_on_the_tape(monkeypatch, seed, options):
    """Differentiated (every parameter) or not: the image and every gradient equal those of
    the renderer with the compiled shading run on the tape."""
    scene = random_scene(seed, **options)
    calls = count_calls(monkeypatch, md.compiler.CompiledFunction, "_forward")  # kernels run
    with md.tape_only():
        plain = render.render(scene, reuse_visibility=False)
    assert calls == [], "tape_only still ran the compiled shading"
    now = render.render(scene, reuse_visibility=False)
    assert calls, "the compiled shading did not run"
    _close(now.data, plain.data, "image")
    params = scene.parameters()
    grads = {}
    for name, context in (("tape", md.tape_only), ("compiled", contextlib.nullcontext)):
        for p in params:
            p.requires_grad, p.grad = True, None
        with context():
            image = render.render(scene, reuse_visibility=False)
        md.sum(image * image).backward()
        grads[name] = [p.grad.copy() for p in params]
    for p, g, g_c in zip(params, grads["tape"], grads["compiled"], strict=True):
        _close(g_c, g, f"gradient of a {p.shape} parameter", GRAD_RTOL)


def test_applies_to_untextured_float64_meshes_that_send_no_mirror_rays():
    scene = random_scene(0)  # a ground quad, a pyramid, a sphere
    quad, _, sphere = scene.objects
    assert compiled.applies(scene, quad, reflects=False)
    assert not compiled.applies(scene, quad, reflects=True)  # mirror rays: the tape code
    assert not compiled.applies(scene, sphere, reflects=False)
    quad.vertices.requires_grad = True  # differentiated: compiled, one node on the tape
    assert compiled.applies(scene, quad, reflects=False)
    textured = random_scene(0, texture=True)
    assert not compiled.applies(textured, textured.objects[0], reflects=False)
    single = random_scene(0)
    single.objects[0].vertices = md.tensor(single.objects[0].vertices.data.astype(np.float32))
    assert not compiled.applies(single, single.objects[0], reflects=False)


def test_one_trace_per_kind_of_mesh_material_and_lights():
    """A new batch length, new values, another mesh of the same kind: no new trace; a
    lobe switched on, or another light, makes one."""
    scene = random_scene(5, lights=("point",), sphere=False)
    compiled._shade._traces.clear()  # (other tests in this process traced other kinds)
    render.render(scene, reuse_visibility=False)
    before = len(compiled._shade._traces)
    scene.camera.position.data[...] += 0.01
    scene.lights[0].intensity.data[...] *= 2.0
    render.render(scene, reuse_visibility=False)
    assert len(compiled._shade._traces) == before
    scene.lights.append(render.DirectionalLight((0.0, -1.0, 0.2), 1.0))
    render.render(scene, reuse_visibility=False)
    assert len(compiled._shade._traces) > before
