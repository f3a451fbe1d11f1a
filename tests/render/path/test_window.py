"""The compiled gradient of whole paths (``render.path.gradient.window``) against the tape.

On scenes of triangle meshes and spheres without mirrors or textures, ``backward`` on a
path-traced image takes its paths' gradient in one compiled kernel (each path's reverse
sweep over all its depths, ``window.path_terms``). Its gradient must be the
tape's (``gradient="tape"``: every path on one tape, the readable reference) for every kind
of parameter, on Hypothesis-drawn scenes: flat and smooth meshes (own normals or computed),
glossy or not, point, directional and area lights, an environment, a transform."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import minidiff as md
import render
from render.path import render_path
from render.path.gradient import window
from render.path.sample.tables import compiles
from render.path.sample.tracer import MIRROR
from render.scene.cornell import box_mesh, cornell_box

#: |compiled - tape| <= GRAD_RTOL * max |tape| per parameter (issue 57: 1e-10). The two
#: sum the same terms in another order. Measured: at most 1e-14 on these scenes.
GRAD_RTOL = 1e-10


@st.composite
def triangle_scenes(draw) -> render.Scene:
    """The Cornell box's room and light (a transformed area light) with a block that is
    flat, smooth with its own normals or smooth with computed ones; a glossy wall or none;
    0-2 point or directional lights; an environment seen through the open front or black;
    a sphere or none, glowing or not (an area light NEE samples), placed by a transform
    or not."""
    scene = cornell_box(6, 6, blocks=False)
    block = box_mesh((-0.35, -0.4, -0.3), (0.25, 0.6, 0.25), render.Material((0.7, 0.6, 0.5)))
    shading = draw(st.sampled_from(["flat", "own normals", "computed"]))
    if shading != "flat":
        normals = None
        if shading == "own normals":
            rng = np.random.default_rng(draw(st.integers(0, 9)))
            normals = 0.3 * rng.normal(size=block.vertices.shape) + 2.0 * block.vertices.data
        block = render.Mesh(block.vertices.data, block.faces, block.material, normals=normals,
                            smooth=True)  # fmt: skip
    scene.objects.append(block)
    sphere = draw(st.sampled_from(["none", "plain", "glowing", "transformed"]))
    if sphere != "none":
        glow = 2.0 if sphere == "glowing" else 0.0
        material = render.Material((0.6, 0.7, 0.8), emission=glow)
        transform = (
            render.Transform(translation=(0.1, 0.05, 0.0)) if sphere == "transformed" else None
        )
        scene.objects.append(render.Sphere((0.35, -0.65, 0.25), 0.3, material, transform=transform))
    if draw(st.booleans()):
        shininess = draw(st.sampled_from([4.0, 30.0]))
        scene.objects[2].material = render.Material((0.6,) * 3, specular=0.4, shininess=shininess)
    lights = []
    for kind in draw(st.lists(st.sampled_from(["point", "directional"]), max_size=2)):
        if kind == "point":
            lights.append(render.PointLight((0.3, 0.6, 0.4), 1.5, color=(1.0, 0.8, 0.6)))
        else:
            lights.append(render.DirectionalLight((0.1, -0.3, -1.0), 0.5))
    scene.lights = lights
    if draw(st.booleans()):
        scene.background = md.tensor([0.1, 0.2, 0.3])
    scene.validate()
    # Every parameter, but the emission of objects that do not glow: a differentiated
    # emission makes its surface an area light that NEE samples (at 6x6 and 3 spp they would
    # take most samples from the real light).
    for name, p in scene.named_parameters().items():
        glows = "emission" not in name or np.any(p.data)
        p.requires_grad = glows
    return scene


def _counting(monkeypatch) -> list:
    """A list that grows by one at each call of the compiled gradient."""
    calls, original = [], window.backpropagate
    monkeypatch.setattr(window, "backpropagate", lambda *a: calls.append(1) or original(*a))
    return calls


def _gradients(scene, weights, **options) -> dict:
    for p in scene.parameters():
        p.grad = None
    image = render_path(scene, **options)
    md.sum(image * md.tensor(weights)).backward()
    return {name: p.grad for name, p in scene.named_parameters().items()}


@settings(
    max_examples=6,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)
@given(scene=triangle_scenes(), depth=st.integers(2, 5), seed=st.integers(0, 2**32))
def test_compiled_paths_give_the_tapes_gradient_for_every_parameter(
    scene, depth, seed, monkeypatch
):
    weights = np.random.default_rng(seed % 7).normal(size=(6, 6, 3))
    options = {"spp": 3, "max_depth": depth, "seed": seed, "batch_spp": 2}
    calls = _counting(monkeypatch)
    replayed = _gradients(scene, weights, **options)
    assert calls  # the compiled route took it
    monkeypatch.undo()
    taped = _gradients(scene, weights, gradient="tape", **options)
    # A parameter whose derivative is exactly 0 on the tape (a ceiling no light reaches
    # directly) may get the rounding of terms that cancel (1e-15): its scale is then the
    # largest gradient's, times 1e-3.
    floor = 1e-3 * max(np.abs(g).max() for g in taped.values() if g is not None)
    for name, tape in taped.items():
        if tape is None:  # a parameter the path integrator does not read (ambient)
            assert replayed[name] is None or not np.any(replayed[name]), name
            continue
        scale = max(np.abs(tape).max(), floor)
        np.testing.assert_allclose(replayed[name], tape, rtol=0, atol=GRAD_RTOL * scale,
                                   err_msg=name)  # fmt: skip
    # Not a test of zeros: the area light's place moves every image (NEE).
    assert np.any(taped["objects[5].transform.translation"])


@settings(
    max_examples=4,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)
@given(scene=triangle_scenes(), depth=st.integers(2, 5), seed=st.integers(0, 2**32))
def test_compiled_paths_give_the_tapes_tangent(scene, depth, seed, monkeypatch):
    """Forward mode: the image's tangent along a random direction of every parameter at
    once, by the compiled JVP of the whole paths (``window.tangent``), is the tape's."""
    rng = np.random.default_rng(seed % 7)
    directions = {p: rng.normal(size=p.shape) for p in scene.parameters() if p.requires_grad}
    for p in scene.parameters():
        p.requires_grad = False  # tangents only
    options = {"spp": 3, "max_depth": depth, "seed": seed, "batch_spp": 2}
    calls, compiled = [], window.tangent
    monkeypatch.setattr(window, "tangent", lambda *a: calls.append(1) or compiled(*a))
    with md.tangents(directions):
        replayed = render_path(scene, **options).tangent
    assert calls  # the compiled route took it
    monkeypatch.undo()
    with md.tangents(directions):
        taped = render_path(scene, gradient="tape", **options).tangent
    scale = np.abs(taped).max()
    assert scale > 0  # the area light's place moves every image (NEE)
    np.testing.assert_allclose(replayed, taped, rtol=0, atol=GRAD_RTOL * scale)


def test_mirrors_and_textures_compile_float32_takes_the_tape():
    """A mirror bounce and a texture compile (``applies``; their gradients:
    ``test_replay.py``'s ``every_kind``); a float32 parameter is left to the tape's
    windows."""
    from render.path.sample.tracer import MIRROR, PathSampler
    from render.scene.placement import placed

    def applies(scene):
        world = placed(scene)
        batch = PathSampler(world, 1, 3, 5, 0).sample(np.arange(16, dtype=np.int64))
        return compiles(world), batch

    scene = cornell_box(4, 4, blocks=True)  # meshes and a sphere
    assert applies(scene)[0]
    scene.objects[0].material = render.Material((0.5, 0.5, 0.5), reflectance=0.5)
    compiled, batch = applies(scene)
    assert any(np.any(v.next == MIRROR) for v in batch.vertices)  # a path meets the mirror
    assert compiled and batch.meets_mirror()
    scene = cornell_box(4, 4, blocks=True)
    scene.objects[0].material = render.Material((0.5, 0.5, 0.5), texture=np.ones((2, 2, 3)))
    scene.objects[0].uvs = md.tensor([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    assert applies(scene)[0]
    scene.objects[1].material.albedo = md.tensor(np.float32([0.7, 0.6, 0.5]))
    assert not applies(scene)[0]


@pytest.mark.parametrize("threads", [1, 2])
def test_compiled_paths_do_not_depend_on_the_thread_count(threads, monkeypatch):
    """The same bits on 1 and 2 threads (``minidiff.compiler.using_threads``), with every
    kernel on the threads however small its batch (``PARALLEL_WORK``)."""
    from minidiff import compiler

    monkeypatch.setattr(compiler, "PARALLEL_WORK", 0)

    def gradient(n):
        scene = cornell_box(6, 6, blocks=True)
        light = scene.objects[5].transform.translation
        light.requires_grad = True
        with compiler.using_threads(n):
            image = render_path(scene, spp=2, max_depth=6, seed=5)
            md.sum(image * image).backward()
        return light.grad

    np.testing.assert_array_equal(gradient(threads), gradient(1))


@pytest.mark.parametrize("threads", [1, 2])
def test_compiled_tangents_do_not_depend_on_the_thread_count(threads, monkeypatch):
    """Forward mode: the same bits on 1 and 2 threads, and a float32 parameter's tangent
    taken by the tape (the compiled route declines it) equal to its tape's."""
    from minidiff import compiler

    monkeypatch.setattr(compiler, "PARALLEL_WORK", 0)

    def tangent(n, dtype=np.float64):
        scene = cornell_box(6, 6, blocks=True)
        wall = scene.objects[3].material
        wall.albedo = md.tensor(wall.albedo.data.astype(dtype))
        light = scene.objects[5].transform.translation
        directions = {wall.albedo: np.ones(3, dtype), light: np.array([0.2, -0.3, 0.1])}
        with compiler.using_threads(n), md.tangents(directions):
            return render_path(scene, spp=2, max_depth=6, seed=5).tangent

    np.testing.assert_array_equal(tangent(threads), tangent(1))
    calls, compiled = [], window.tangent
    monkeypatch.setattr(window, "tangent", lambda *a: calls.append(1) or compiled(*a))
    single = tangent(threads, np.float32)
    assert not calls and np.any(single)
    np.testing.assert_allclose(single, tangent(1), rtol=0, atol=1e-4 * np.abs(single).max())


def test_spheres_only_with_the_camera_inside_one(monkeypatch):
    """A scene without triangles, the camera inside a sphere (its rays meet the far side),
    a glowing sphere NEE samples: every gradient is the tape's."""
    scene = render.Scene(
        [
            render.Sphere((0, 0, 0), 6.0, render.Material((0.7, 0.5, 0.3), specular=0.2)),
            render.Sphere((0.5, 0.5, -1.0), 0.7, render.Material((0.2, 0.6, 0.3), emission=3.0)),
        ],
        [render.PointLight((1, 2, 1), 10.0)],
        render.Camera((0, 0, 3), (0, 0, 0), (0, 1, 0), 60.0, 8, 8),
    )
    for p in scene.parameters():
        p.requires_grad = True
    weights = np.random.default_rng(0).normal(size=(8, 8, 3))
    calls = _counting(monkeypatch)
    replayed = _gradients(scene, weights, spp=3, max_depth=4, seed=2)
    assert calls
    monkeypatch.undo()
    taped = _gradients(scene, weights, spp=3, max_depth=4, seed=2, gradient="tape")
    assert np.any(taped["objects[0].center"]) and np.any(taped["camera.position"])
    for name, tape in taped.items():
        if tape is not None:
            scale = max(np.abs(tape).max(), 1e-300)
            np.testing.assert_allclose(replayed[name], tape, rtol=0, atol=GRAD_RTOL * scale,
                                       err_msg=name)  # fmt: skip


@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(scene=triangle_scenes(), depth=st.integers(1, 5), seed=st.integers(0, 2**32),
       mirror=st.booleans())  # fmt: skip
def test_radiance_of_is_the_value_of_path_radiance(scene, depth, seed, mirror):
    """``replay.radiance_of`` (the boundary terms' constants, compiled, mirror bounces
    included) equals ``transport.path_radiance``."""
    from render.path.gradient.replay import radiance_of
    from render.path.gradient.transport import path_radiance
    from render.path.sample.tracer import PathSampler
    from render.scene.camera import camera_frame
    from render.scene.placement import placed

    if mirror:
        scene.objects[1].material = render.Material((0.5, 0.5, 0.5), reflectance=0.6)
    with md.no_grad():
        world = placed(scene)
        frame = camera_frame(world.camera)
        batch = PathSampler(world, 2, depth, 3, seed).sample(np.arange(72, dtype=np.int64))
        bounces = [np.any(v.form == MIRROR) or np.any(v.next == MIRROR) for v in batch.vertices]
        assert compiles(world) and batch.meets_mirror() == any(bounces)
        expected = path_radiance(world, frame, PathSampler(world, 2, depth, 3, seed), batch).data
    got = radiance_of(world, frame, PathSampler(world, 2, depth, 3, seed), batch)
    scale = max(np.abs(expected).max(), 1e-300)
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12 * scale)
    assert depth == 1 or np.any(expected)  # light reaches some path


def test_records_laid_out_from_a_batch_are_the_kernels():
    """``Records.of`` a batch of the reference sampler (per-depth lists) gives the layout
    the kernel writes as it traces the same paths: integers equal, floats to 1e-12 of their
    scale (the two sample the same decisions, computed in another order)."""
    from render.path.sample.records import PathBatch, Records
    from render.path.sample.tracer import PathSampler
    from render.path.twin import kernel
    from render.scene.placement import placed

    scene = cornell_box(8, 8, blocks=True)
    scene.objects[2].material = render.Material((0.5, 0.5, 0.5), reflectance=0.4)
    scene.lights = [render.PointLight((0.3, 0.6, 0.4), 1.5)]
    world = placed(scene)
    sampler = PathSampler(world, 2, 6, 3, 11)
    paths = np.arange(8 * 8 * 2, dtype=np.int64)
    traced, _ = kernel.sample_paths(sampler, paths)
    sampled = sampler.sample(paths)
    laid_out = Records.of(PathBatch(sampled.paths, sampled.coords, sampled.missed,
                                    sampled.vertices), 1)  # fmt: skip
    written = traced.records
    depth = len(laid_out.ints)
    assert depth >= 4 and np.any(written.ints[..., 3] == 2)  # deep, and a mirror bounce
    np.testing.assert_array_equal(laid_out.ints, written.ints[:depth])
    np.testing.assert_array_equal(laid_out.lit, written.lit[:depth])
    scale = np.abs(written.floats).max()
    np.testing.assert_allclose(laid_out.floats, written.floats[:depth], rtol=0, atol=1e-12 * scale)
