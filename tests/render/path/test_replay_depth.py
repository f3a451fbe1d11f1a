"""Path replay backpropagation (``render.path.gradient.replay.backpropagate_paths``): one batch's
gradient one depth at a time equals the gradient through the tape of all its depths
(``render.path.gradient.transport.path_radiance``) for every kind of parameter, through mirror
chains and Russian roulette, and its memory does not grow with ``max_depth`` while the tape's
does."""

from __future__ import annotations

import tracemalloc
from contextlib import nullcontext
from unittest import mock

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import minidiff as md
import render
from minidiff import buffers
from render.path.gradient import replay, window
from render.path.gradient.replay import backpropagate_paths
from render.path.gradient.transport import path_radiance
from render.path.sample.tables import Tables
from render.path.sample.tracer import MIRROR, PathSampler
from render.scene.camera import camera_frame
from render.scene.cornell import cornell_box
from render.scene.placement import placed
from tests.render.path.test_replay import every_kind

#: |replay - tape| <= GRAD_RTOL * max |tape| per parameter. The two sum the same terms in
#: another order, and the replay's remaining radiance is a difference divided by the
#: throughput. Measured: at most 8e-14 (every_kind, depth 8).
GRAD_RTOL = 1e-10


def _paths(scene, spp: int, max_depth: int, rr_depth: int, seed: int):
    """The sampler, a batch of every pixel's ``spp`` paths, their radiance (N, 3) and the
    weights (N, 3) of a loss sum(weights * radiance)."""
    world = placed(scene)
    sampler = PathSampler(world, spp, max_depth, rr_depth, seed)
    camera = scene.camera
    batch = sampler.sample(np.arange(camera.width * camera.height * spp, dtype=np.int64))
    with md.no_grad():
        radiance = path_radiance(world, camera_frame(world.camera), sampler, batch).data
    weights = np.random.default_rng(seed).normal(size=radiance.shape)
    return sampler, batch, radiance, weights


def _taped(scene, sampler, batch, radiance, weights) -> None:
    world = placed(scene)
    frame = camera_frame(world.camera)
    md.sum(path_radiance(world, frame, sampler, batch) * md.tensor(weights)).backward()


def _replayed(scene, sampler, batch, radiance, weights) -> None:
    world = placed(scene)
    backpropagate_paths(world, camera_frame(world.camera), sampler, batch, radiance, weights)


def _gradients(scene, way, paths) -> dict:
    for p in scene.parameters():
        p.grad = None
    way(scene, *paths)
    return {name: p.grad for name, p in scene.named_parameters().items()}


def _assert_same_gradients(scene, paths, windows: bool = False) -> int:
    """The replay's gradients against the tape's, within GRAD_RTOL of each parameter's
    largest; returns how many parameters the tape moves. None (never reached) counts as
    zero: the replay reaches a factor whose later radiance is zero, where the tape may
    not (a mirror's reflectance when nothing is seen in it). ``windows``: the replay one
    depth at a time on the tape (the route of textured scenes) rather than compiled."""
    taped = _gradients(scene, _taped, paths)
    with mock.patch.object(replay, "compiles", lambda *_: False) if windows else nullcontext():
        replayed = _gradients(scene, _replayed, paths)
    pairs = {n: (0.0 if g is None else g, 0.0 if replayed[n] is None else replayed[n])
             for n, g in taped.items() if g is not None or replayed[n] is not None}  # fmt: skip
    scales = {n: np.abs(tape).max() for n, (tape, _) in pairs.items()}
    errors = {n: np.abs(replay - tape).max() / max(scales[n], 1e-300)
              for n, (tape, replay) in pairs.items()}  # fmt: skip
    assert max(errors.values()) <= GRAD_RTOL, errors
    return sum(s > 0 for s in scales.values())


def _longest_mirror_run(batch) -> int:
    """The most ``MIRROR`` vertices in a row on any path of the batch."""
    run = np.zeros(len(batch.paths), np.int64)
    longest = 0
    for record in batch.vertices:
        mirror = record.form == MIRROR
        following = np.zeros(len(batch.paths), np.int64)
        following[record.rows[mirror]] = run[record.rows[mirror]] + 1
        run = following
        longest = max(longest, int(run.max(initial=0)))
    return longest


@pytest.mark.parametrize("max_depth", [2, 4, 8])
def test_every_kind_of_parameter_gets_the_tapes_gradient(max_depth):
    scene = every_kind()
    paths = _paths(scene, spp=4, max_depth=max_depth, rr_depth=3, seed=3)
    # Paths go past Russian roulette's first vertex (at depth 8 the last die by depth 5).
    assert len(paths[1].vertices) >= min(max_depth, 5)
    assert _assert_same_gradients(scene, paths) >= 20  # not a comparison of zeros


def test_segments_hand_their_last_vertex_on(monkeypatch):
    """The compiled replay takes ``window.SEGMENT`` depths at a time, each segment handing
    its last vertex and throughput to the next and getting their gradient back: with
    segments of 2 depths (small kernels, quick to compile) paths of 5 vertices run through
    a first, a middle and a last segment, every kind of parameter (textures, a mirror,
    lights) against the tape."""

    monkeypatch.setattr(window, "SEGMENT", 2)
    scene = every_kind()
    paths = _paths(scene, spp=2, max_depth=5, rr_depth=100, seed=3)
    assert len(paths[1].vertices) == 5
    assert _assert_same_gradients(scene, paths) >= 20


def _tangents(scene, paths, compiled: bool) -> np.ndarray:
    """The tangent (N, 3) of the paths' radiance along a random direction of every
    parameter at once: the compiled JVP of the whole paths, or the tape's forward mode."""
    sampler, batch = paths[:2]
    rng = np.random.default_rng(11)
    directions = {p: rng.normal(size=p.shape) for p in scene.parameters()}
    with md.tangents(directions):
        world = placed(scene)
        frame = camera_frame(world.camera)
        if compiled:
            return window.tangent(Tables.of(world, frame, leaves=False), batch)
        return path_radiance(world, frame, sampler, batch).tangent


@pytest.mark.parametrize("segment", [2, window.SEGMENT])
def test_forward_mode_compiled_paths_are_the_tapes(segment, monkeypatch):
    """The tangent of each path's radiance by the compiled JVP (``window.tangent``), every
    kind of parameter moving at once (textures, a mirror, lights, the environment), equals
    the tape's forward mode: in one segment, and in segments of 2 depths that hand their
    last vertex on with its tangent."""
    monkeypatch.setattr(window, "SEGMENT", segment)
    scene = every_kind()
    for p in scene.parameters():
        p.requires_grad = False  # tangents only: nothing recorded
    paths = _paths(scene, spp=2, max_depth=5, rr_depth=100, seed=3)
    assert len(paths[1].vertices) == 5
    tape = _tangents(scene, paths, compiled=False)
    compiled = _tangents(scene, paths, compiled=True)
    scale = np.abs(tape).max()
    assert scale > 0 and np.all(np.isfinite(compiled))
    np.testing.assert_allclose(compiled, tape, rtol=0, atol=GRAD_RTOL * scale)


def _differentiate(scene: render.Scene) -> render.Scene:
    """Every parameter of the Cornell box requires grad but the emission of the surfaces
    that do not emit (a differentiated emission makes its surface a light that NEE picks:
    the light would then rarely be picked, and most gradients would be zero at 6x6)."""
    for name, p in scene.named_parameters().items():
        p.requires_grad = "emission" not in name or bool(np.any(p.data))
    return scene


def _mirrored(kind: str, reflectance: float, albedo: float, shift) -> render.Scene:
    """A 6x6 Cornell box with mirrors (``_differentiate``d): ``"facing"``, the side walls
    (two facing mirrors, also diffuse by ``albedo``); ``"sphere"``, a pure mirror sphere
    placed by a transform (moved by ``shift``); ``"both"``."""
    scene = cornell_box(6, 6)
    if kind in ("facing", "both"):
        for i, tint in ((3, (albedo, 0.1, 0.1)), (4, (0.1, albedo, 0.1))):
            scene.objects[i].material = render.Material(tint, reflectance=reflectance)
    if kind in ("sphere", "both"):
        scene.objects[7] = render.Sphere(
            (0.0, 0.0, 0.0), 0.3, render.Material((0.0, 0.0, 0.0), reflectance=reflectance),
            transform=render.Transform(translation=(0.3 + shift[0], -0.6, 0.2 + shift[1])),
        )  # fmt: skip
    scene.validate()
    return _differentiate(scene)


@settings(max_examples=6, deadline=None)
@given(
    kind=st.sampled_from(["facing", "sphere", "both"]),
    reflectance=st.floats(0.5, 0.95),
    albedo=st.floats(0.05, 0.6),
    shift=st.tuples(st.floats(-0.1, 0.1), st.floats(-0.1, 0.1)),
    max_depth=st.integers(2, 6),
    rr_depth=st.integers(1, 3),
    seed=st.integers(0, 2**16),
    windows=st.booleans(),
)
def test_mirror_scenes_get_the_tapes_gradient(
    kind, reflectance, albedo, shift, max_depth, rr_depth, seed, windows
):
    scene = _mirrored(kind, reflectance, albedo, shift)
    paths = _paths(scene, spp=2, max_depth=max_depth, rr_depth=rr_depth, seed=seed)
    assert _assert_same_gradients(scene, paths, windows) >= 15


@pytest.mark.parametrize("windows", [False, True])
def test_a_run_of_mirrors_is_rebuilt_from_its_start(windows):
    """Facing mirrors that reflect almost everything: paths bounce between them several
    times in a row (the compiled path follows them; each window on the tape must rebuild
    the run from its first vertex)."""
    scene = _mirrored("facing", 0.95, 0.05, (0.0, 0.0))
    paths = _paths(scene, spp=4, max_depth=8, rr_depth=8, seed=5)
    assert _longest_mirror_run(paths[1]) >= 3
    assert _assert_same_gradients(scene, paths, windows) >= 15


@pytest.mark.parametrize("windows", [False, True])
def test_a_zero_channel_of_the_throughput_keeps_its_derivative(windows):
    """A red wall with no green or blue, a green one with no red and a zero specular: the
    paths' throughput is zero in those channels after a bounce there, but the derivative
    of the albedo's zero channels (and of the specular) is not (the light that arrives
    there, window ``_Pending``)."""
    scene = cornell_box(6, 6)
    scene.objects[3].material = render.Material((0.6, 0.0, 0.0))
    scene.objects[4].material = render.Material((0.0, 0.5, 0.2), specular=0.0, shininess=5.0)
    _differentiate(scene)
    paths = _paths(scene, spp=4, max_depth=5, rr_depth=3, seed=1)
    assert _assert_same_gradients(scene, paths, windows) >= 15
    grad = _gradients(scene, _replayed, paths)["objects[3].material.albedo"]
    assert np.all(grad[1:] != 0)  # the zero channels do move the image


def _peak_mb(way, scene, paths) -> float:
    """Peak traced allocation (MB) of one batch's backward pass, from its placement on
    (minidiff's buffers fresh, as ``render_path``'s are)."""
    buffers.clear()
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        with buffers.fresh():
            way(scene, *paths)
        return (tracemalloc.get_traced_memory()[1] - base) / 1e6
    finally:
        tracemalloc.stop()


def test_memory_does_not_grow_with_max_depth(monkeypatch):
    """Cornell box 16x16, 4 spp, no Russian roulette before depth 100, max_depth 2 and 8.
    The tape's peak grows with the vertices it holds. The replay's windows on the tape
    (the route of mirrors and textures) peak at their largest window (the first ones,
    which hold the most paths), the same at any depth. The compiled route (its reverse
    sweep path by path inside the kernel, ``window.SEGMENT`` depths at a time) holds no
    tape: its peak is the batch's dense records (``render.path.sample.records``, the
    batch's own size, made here from the sampler's per-depth lists), the later segments'
    rows of them (the paths that reach them: at most the records again) and a few (N, 3)
    arrays. The 10 % (25 % for the compiled route's few arrays) leave room for the
    allocator. Measured: tape 3.59, 11.28 MB; windows 4.05, 4.04 MB; compiled 0.51, 2.29
    MB of which the records 0.35, 1.38 MB."""
    from render.path.sample.records import Records

    scene = cornell_box(16, 16)
    for p in scene.parameters():
        p.requires_grad = True
    shallow, deep = (_paths(scene, 4, depth, 100, 0) for depth in (2, 8))
    for paths in (shallow, deep):  # first-call allocations (caches, kernels) not counted
        _peak_mb(_replayed, scene, paths)
    compiled = [_peak_mb(_replayed, scene, paths) for paths in (shallow, deep)]
    held = []
    for _, batch, _, _ in (shallow, deep):
        records = Records.of(batch, 0)
        held.append((records.ints.nbytes + records.floats.nbytes + records.lit.nbytes) / 1e6)
    tape = [_peak_mb(_taped, scene, paths) for paths in (shallow, deep)]
    monkeypatch.setattr(replay, "compiles", lambda *_: False)
    _peak_mb(_replayed, scene, shallow)
    windows = [_peak_mb(_replayed, scene, paths) for paths in (shallow, deep)]
    assert tape[1] > 2 * tape[0]  # the measurement sees the tape grow with depth
    assert windows[1] < 1.1 * windows[0]
    assert windows[1] < tape[1] / 2
    assert held[1] > 3 * held[0]  # the records grow with depth ...
    # ... and nothing else but the segments' rows of them
    assert compiled[1] - 2 * held[1] < 1.25 * (compiled[0] - held[0])
    assert compiled[1] < tape[1] / 4
