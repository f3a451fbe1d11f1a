"""The path integrator's default gradient: ``backward`` on a path-traced image replays its
samples a batch at a time (``render_path(..., gradient="replay")``) instead of keeping them
all on the tape. Its image is the compiled kernel's (``render.path.twin.kernel``), the tape's to
rounding (``IMAGE_RTOL``); its gradient is the tape's to rounding for every kind of
parameter, with the boundary term and in forward mode; its memory must not grow with spp."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

import minidiff as md
import render
from minidiff import buffers
from render.path import render_path
from render.scene.cornell import box_mesh, cornell_box

#: |kernel's image - tape's| <= IMAGE_RTOL * max |tape's| (measured: 2.4e-14).
IMAGE_RTOL = 1e-12
#: |replay - tape| <= GRAD_RTOL * max |tape| per parameter: the two sum the same terms in
#: another order (the tape adds the batches' gradients at the shared placed geometry, the
#: replay at the parameters, batch after batch). Measured: at most 2e-14 on these scenes.
GRAD_RTOL = 1e-12


def every_kind(width: int = 8) -> render.Scene:
    """The Cornell box with every kind of parameter the path integrator reads, all
    requiring grad: a textured glossy floor (uvs, texture, specular texture), a mirror back
    wall, a smooth box with vertex normals, a sphere placed by a transform, a point and a
    directional light, the environment (seen through the open front)."""
    scene = cornell_box(width, width)
    floor = scene.objects[0]
    texture = np.random.default_rng(0).uniform(0.2, 0.9, (4, 4, 3))
    floor.material = render.Material(
        (0.7, 0.7, 0.7), specular=0.3, shininess=12.0, texture=texture,
        specular_texture=np.full((2, 2, 3), 0.8),
    )  # fmt: skip
    floor.uvs = md.tensor([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    scene.objects[2].material = render.Material((0.5, 0.5, 0.5), reflectance=0.4)
    box = box_mesh((-0.35, -0.4, -0.3), (0.25, 0.6, 0.25), render.Material((0.7, 0.6, 0.5)))
    box = render.Mesh(
        box.vertices.data, box.faces, box.material, normals=_box_normals(box), smooth=True
    )
    sphere = render.Sphere(
        (0.0, 0.0, 0.0), 0.35, render.Material((0.6, 0.7, 0.8)),
        transform=render.Transform(translation=(0.4, -0.65, 0.25)),
    )  # fmt: skip
    scene.objects[6:] = [box, sphere]
    scene.lights = [
        render.PointLight((0.3, 0.6, 0.4), 2.0),
        render.DirectionalLight((0.1, -0.3, -1.0), 0.5),
    ]
    scene.background = md.tensor([0.1, 0.2, 0.3])
    scene.validate()
    for p in scene.parameters():
        p.requires_grad = True
    return scene


def _box_normals(box: render.Mesh) -> np.ndarray:
    """Per-vertex normals of ``box_mesh`` (its sides do not share vertices): the side's."""
    v, faces = box.vertices.data, box.faces
    n = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])
    normals = np.zeros_like(v)
    for corner in range(3):
        np.add.at(normals, faces[:, corner], n)
    return normals / np.linalg.norm(normals, axis=1, keepdims=True)


def _gradients(scene, weights, **options):
    """The image and every parameter's gradient of sum(weights * image), and the image."""
    for p in scene.parameters():
        p.grad = None
    image = render_path(scene, **options)
    md.sum(image * md.tensor(weights)).backward()
    return image, {name: p.grad for name, p in scene.named_parameters().items()}


def _assert_same_gradients(replayed: dict, taped: dict) -> None:
    moved = 0
    for name, tape in taped.items():
        if tape is None:  # e.g. ambient: the path integrator does not read it
            assert replayed[name] is None, name
            continue
        scale = np.abs(tape).max()
        np.testing.assert_allclose(replayed[name], tape, rtol=0, atol=GRAD_RTOL * scale,
                                   err_msg=name)  # fmt: skip
        moved += scale > 0
    assert moved >= 20  # most parameters move the image (not a test of zeros)


@pytest.mark.parametrize("antialias", [False, "boundary"])
def test_replay_gives_the_tapes_image_and_gradient_for_every_kind_of_parameter(antialias):
    scene = every_kind()
    weights = np.random.default_rng(1).normal(size=(8, 8, 3))
    options = {"spp": 6, "max_depth": 4, "seed": 3, "batch_spp": 2, "antialias": antialias,
               "edge_spp": 2}  # fmt: skip
    taped_image, taped = _gradients(scene, weights, gradient="tape", **options)
    image, replayed = _gradients(scene, weights, **options)
    assert image.node.name == "path_image"  # one node, not the samples' tape
    assert taped_image.node.name != "path_image"
    # The image itself, to rounding: the replay's render must make the sampler's choices
    # that depend on what is differentiated (a differentiated emission is an area light).
    _assert_same_image(image, taped_image)
    _assert_same_gradients(replayed, taped)


def _assert_same_image(image, taped_image):
    """The kernel's image against the tape's: the same paths, the radiance summed in
    another order (one path at a time, against the tape's scatter-add)."""
    scale = np.abs(taped_image.data).max()
    assert scale > 0
    np.testing.assert_allclose(image.data, taped_image.data, rtol=0, atol=IMAGE_RTOL * scale)


def test_the_differentiated_image_does_not_depend_on_batch_spp():
    """With gradients, the image is the kernel's whatever ``batch_spp`` (one batch or
    several): the same bits, and the bits of the render without gradients."""
    scene = every_kind()
    images = [render_path(scene, spp=4, max_depth=3, batch_spp=b) for b in (1, 4, 8)]
    assert all(image.node.name == "path_image" for image in images)
    with md.no_grad():
        plain = render_path(scene, spp=4, max_depth=3, batch_spp=2)
    assert plain.node is None
    for image in images:
        np.testing.assert_array_equal(image.data, plain.data)
    # Forward mode alone: the image is summed from the paths its tangent traced, the same
    # bits as the plain render's (of a scene whose emissions are not differentiated now).
    for p in scene.parameters():
        p.requires_grad = False
    plain = render_path(scene, spp=4, max_depth=3)
    light = scene.objects[5].transform.translation
    for b in (1, 4, 8):
        with md.tangents({light: np.ones(3)}):
            image = render_path(scene, spp=4, max_depth=3, batch_spp=b)
        assert np.any(image.tangent)
        np.testing.assert_array_equal(image.data, plain.data)


@pytest.mark.parametrize("antialias", [False, "boundary"])
def test_forward_mode_through_the_replayed_image(antialias, monkeypatch):
    """Tangents on some parameters while others require grad: the image's tangent (the
    compiled JVP of the whole paths, ``window.tangent``, plus the edge terms' own) and the
    gradients are the tape's."""
    from render.path.gradient import window

    scene = every_kind()
    light = scene.objects[5].transform.translation
    albedo = scene.objects[3].material.albedo
    albedo.requires_grad = False  # a tangent only
    weights = np.random.default_rng(2).normal(size=(8, 8, 3))
    directions = {light: [0.3, -0.2, 0.5], albedo: [1.0, 0.0, 0.5]}
    options = {"spp": 4, "max_depth": 3, "seed": 7, "batch_spp": 2, "antialias": antialias,
               "edge_spp": 2}  # fmt: skip
    with md.tangents(directions):
        taped_image, taped = _gradients(scene, weights, gradient="tape", **options)
    calls, compiled = [], window.tangent
    monkeypatch.setattr(window, "tangent", lambda *a: calls.append(1) or compiled(*a))
    with md.tangents(directions):
        image, replayed = _gradients(scene, weights, **options)
    assert image.node.name == "path_image"
    assert len(calls) == 2  # the compiled route, a batch of 2 samples at a time
    _assert_same_image(image, taped_image)
    tangent = taped_image.tangent
    assert np.abs(tangent).max() > 0
    np.testing.assert_allclose(image.tangent, tangent, rtol=0, atol=1e-13 * np.abs(tangent).max())
    assert replayed["objects[3].material.albedo"] is None
    _assert_same_gradients(replayed, taped)


def test_a_computed_parameter_passes_its_gradient_on():
    """A parameter that is not a leaf (computed on the tape from another tensor) gets its
    gradient from the replay's node, and the tape carries it on to that tensor."""

    def gradient(**options):
        scene = cornell_box(6, 6)
        base = md.tensor([0.5, 0.1, 0.1], requires_grad=True)
        scene.objects[3].material.albedo = base * 1.5
        image = render_path(scene, spp=4, max_depth=3, seed=2, batch_spp=1, **options)
        md.sum(image).backward()
        return base.grad

    taped = gradient(gradient="tape")
    assert np.abs(taped).min() > 0
    np.testing.assert_allclose(gradient(), taped, rtol=GRAD_RTOL)


def test_backward_under_no_grad_and_after_the_parameters_changed():
    """The replay records its batches even when ``backward`` runs under ``no_grad()``, and
    differentiates the image that was rendered even if a parameter changed since (it
    renders a copy of the parameters' values at the time of the render)."""
    scene = cornell_box(6, 6)
    light = scene.objects[5].transform.translation
    light.requires_grad = True
    weights = np.random.default_rng(3).normal(size=(6, 6, 3))
    options = {"spp": 4, "max_depth": 3, "seed": 1, "batch_spp": 2}
    _, reference = _gradients(scene, weights, **options)
    light.grad = None
    loss = md.sum(render_path(scene, **options) * md.tensor(weights))
    with md.no_grad():
        loss.backward()
    np.testing.assert_array_equal(light.grad, reference["objects[5].transform.translation"])
    light.grad = None
    loss = md.sum(render_path(scene, **options) * md.tensor(weights))
    light.data[1] -= 0.1
    loss.backward()
    np.testing.assert_array_equal(light.grad, reference["objects[5].transform.translation"])


def _peak_mb(scene, gradient: str, spp: int) -> float:
    """Peak traced allocation (MB) of one render and its backward."""
    buffers.clear()
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        image = render_path(scene, spp=spp, max_depth=3, seed=0, batch_spp=2, gradient=gradient)
        md.sum(image).backward()
        return (tracemalloc.get_traced_memory()[1] - base) / 1e6
    finally:
        tracemalloc.stop()


def test_memory_does_not_grow_with_spp():
    """4x more samples: the tape's peak grows with them, the replay's stays that of one
    batch (measured at 16x16, batches of 2: replay 1.11 and 1.18 MB at 4 and 16 spp, tape
    5.9 and 23 MB). Not smaller: with compiled windows a batch of 8x8 paths holds so little
    that what the interpreter holds between calls until its next garbage collection is a
    fifth of it."""
    scene = cornell_box(16, 16)
    for p in scene.parameters():
        p.requires_grad = True
    _peak_mb(scene, "replay", 4)  # first-call allocations (compiled code, caches) not counted
    replay = [_peak_mb(scene, "replay", spp) for spp in (4, 16)]
    tape = [_peak_mb(scene, "tape", spp) for spp in (4, 16)]
    assert tape[1] > 3 * tape[0]  # the measurement sees the tape grow
    assert replay[1] < 1.25 * replay[0]
    assert replay[1] < tape[1] / 4


def _tangent_peak_mb(scene, directions, spp: int) -> float:
    """Peak traced allocation (MB) of one render's tangent (forward mode)."""
    buffers.clear()
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        with md.tangents(directions):
            image = render_path(scene, spp=spp, max_depth=3, seed=0, batch_spp=2)
        assert np.any(image.tangent)
        return (tracemalloc.get_traced_memory()[1] - base) / 1e6
    finally:
        tracemalloc.stop()


def test_forward_mode_memory_does_not_grow_with_spp():
    """The tangent of a 4x larger spp: the compiled paths' tangents are summed into the
    image a batch at a time, nothing kept (measured at 16x16, batches of 2: 0.69 and 0.70
    MB at 4 and 16 spp, 0.73 at 64)."""
    scene = cornell_box(16, 16)
    directions = {p: np.ones(p.shape) for p in scene.parameters()}
    _tangent_peak_mb(scene, directions, 4)  # first-call allocations not counted
    peaks = [_tangent_peak_mb(scene, directions, spp) for spp in (4, 16)]
    assert peaks[1] < 1.25 * peaks[0]


def test_bad_gradient_option_is_named():
    with pytest.raises(ValueError, match='gradient must be "replay" or "tape"'):
        render.render(cornell_box(4, 4), integrator="path", gradient="adjoint")


def test_the_replay_on_the_tape_takes_a_batch_in_chunks_of_paths(monkeypatch):
    """A batch's paths replayed a few at a time (``REPLAY_PATHS``, so that a large image's
    batch does not hold millions of paths at once) give the tape's gradient."""
    from render.path import integrator

    scene = every_kind()
    weights = np.random.default_rng(4).normal(size=(8, 8, 3))
    options = {"spp": 4, "max_depth": 3, "seed": 5, "batch_spp": 2}
    _, taped = _gradients(scene, weights, gradient="tape", **options)
    monkeypatch.setattr(integrator, "REPLAY_PATHS", 37)  # 128 paths a batch: 4 chunks
    _, chunked = _gradients(scene, weights, **options)
    _assert_same_gradients(chunked, taped)


@pytest.mark.parametrize("replay_paths", [2**17, 37])
def test_an_image_replayed_in_one_go_traces_its_paths_once(monkeypatch, replay_paths):
    """One batch of at most ``REPLAY_PATHS`` paths: the records the render makes serve its
    ``backward`` (``integrator._KeptPaths``), so the kernel traces the paths once, not
    twice; a batch taken in chunks keeps nothing and traces them again. Either way the
    image is the plain render's, bit for bit, and the gradient is the tape's."""
    from render.path import integrator
    from render.path.twin import kernel

    scene = every_kind()
    weights = np.random.default_rng(6).normal(size=(8, 8, 3))
    options = {"spp": 4, "max_depth": 3, "seed": 5, "batch_spp": 4}
    taped_image, taped = _gradients(scene, weights, gradient="tape", **options)
    with md.no_grad():
        plain = render_path(scene, **options)
    monkeypatch.setattr(integrator, "REPLAY_PATHS", replay_paths)
    runs = []  # the kernel's runs: the image's, then the replay's chunks'
    run = kernel._run
    monkeypatch.setattr(kernel, "_run", lambda *a, **k: runs.append(k.get("paths")) or run(*a, **k))
    image, replayed = _gradients(scene, weights, **options)
    np.testing.assert_array_equal(image.data, plain.data)
    _assert_same_image(image, taped_image)
    _assert_same_gradients(replayed, taped)
    traced = [None if paths is None else len(paths) for paths in runs]
    assert traced == ([8 * 8 * 4] if replay_paths == 2**17 else [None] + [37] * 6 + [34])
