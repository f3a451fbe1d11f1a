"""Path replay compiled (``render.path.twin.adjoint``, ``kernel.replay_gradient``): when only
materials, lights' strengths and colours and the environment require grad, ``backward`` on
``render_path``'s image runs the kernel's path replay instead of a tape. Its gradient must
be the tape's (``gradient="tape"``, the same seed) to rounding, for linear and non-linear
losses; ``covers`` must send everything else to the tape; its bits must not depend on the
number of threads; its memory must not grow with spp or with the paths' depth; forward mode
must be unaffected.

The tape gives None or zeros for a parameter that does not move the image (depending on
whether it entered the tape), the replay None or zeros too (a reflectance whose mirror lobe
is never picked, an albedo under a texture): both count as zero here.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tracemalloc
from pathlib import Path
from unittest import mock

import numba
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import minidiff as md
import render
from minidiff import buffers
from render.path.sample.tracer import PathSampler
from render.path.twin import adjoint, kernel
from render.scene.cornell import box_mesh, cornell_box
from render.scene.placement import placed
from tests.render.path.test_kernel import UncompiledPointLight, drawn_view
from tests.render.path.test_replay import _gradients, every_kind

#: |replay - tape| <= RTOL * max(max |tape|, FLOOR * the largest |tape| of all parameters)
#: per parameter: the same terms summed in another order (the tape per batch and per depth,
#: the kernel path by path into 64 chunks). Measured (this machine), max |difference| /
#: max |tape| per parameter: 1.7e-14 on the Cornell box, 6.4e-14 on every_kind (depths 2
#: to 8, Russian roulette), 6e-16 for the MSE loss; over 120 drawn scenes up to 1.8e-11, at
#: a shininess whose gradient is 1.2e-5 of the scene's largest (a sum of terms of both
#: signs: its rounding is that of its terms); against the scene's largest gradient every
#: difference is below 3e-16. (The kernel of 842466d, which divided by the throughput, gave
#: up to 1.4e-10 there.) Hence FLOOR.
RTOL = 1e-10
FLOOR = 1e-4
#: The names (suffixes) of the parameters the compiled replay differentiates.
COVERED = (
    ".albedo", ".specular", ".shininess", ".reflectance", ".emission", ".ambient",
    ".intensity", ".irradiance", ".color",
)  # fmt: skip


def require_covered(scene: render.Scene, skip: tuple[str, ...] = ()) -> None:
    """Every covered parameter of ``scene`` (but those named in ``skip``) requires grad,
    nothing else does."""
    for name, p in scene.named_parameters().items():
        wanted = name.endswith(COVERED) or name == "background"
        p.requires_grad = wanted and name not in skip


def worst_ratio(replayed: dict, taped: dict) -> tuple[float, int]:
    """(max over parameters of max |replay - tape| / max |tape|, how many parameters the
    image depends on), after checking every parameter agrees to RTOL (None as zeros)."""
    worst, moved = 0.0, 0
    largest = max(np.abs(g).max() for g in taped.values() if g is not None)
    for name, tape in taped.items():
        ours = replayed[name]
        if tape is None and ours is None:
            continue
        shape = (tape if tape is not None else ours).shape
        tape = np.zeros(shape) if tape is None else tape
        ours = np.zeros(shape) if ours is None else ours
        assert ours.shape == tape.shape, name
        scale = np.abs(tape).max()
        error = np.abs(ours - tape).max()
        if scale == 0:
            assert error == 0, f"{name}: {ours} where the tape has zeros"
            continue
        assert error <= RTOL * max(scale, FLOOR * largest), f"{name}: {ours} != {tape} (tape)"
        worst, moved = max(worst, error / scale), moved + 1
    return worst, moved


def replay_against_tape(scene: render.Scene, weights: np.ndarray, **options) -> tuple[float, int]:
    """``worst_ratio`` of sum(weights * image)'s gradient, by ``render_path``'s replay
    (checked to be the compiled one) against the tape's."""
    assert adjoint.covers(placed(scene))
    _, taped = _gradients(scene, weights, gradient="tape", **options)
    with mock.patch.object(kernel, "replay_gradient", wraps=kernel.replay_gradient) as spy:
        _, replayed = _gradients(scene, weights, **options)
    assert spy.call_count == 1, "the compiled path replay did not run"
    return worst_ratio(replayed, taped)


def weights_for(scene: render.Scene, seed: int = 0) -> np.ndarray:
    """(H, W, 3) random weights of a linear loss: every pixel's dL/dimage differs."""
    camera = scene.camera
    return np.random.default_rng(seed).normal(size=(camera.height, camera.width, 3))


# --------------------------------------------------------------------------------------
# 1: the tape's gradient, linear loss
# --------------------------------------------------------------------------------------


def test_cornell_box_every_material_and_light_parameter():
    scene = cornell_box(8, 8)
    require_covered(scene)
    options = {"spp": 6, "max_depth": 5, "seed": 2, "batch_spp": 2}
    _, moved = replay_against_tape(scene, weights_for(scene), **options)
    assert moved >= 12  # the walls' albedos, the light's emission, ...


@pytest.mark.parametrize("max_depth, rr_depth", [(2, 1), (5, 2), (8, 2)])
def test_every_kind_of_material_light_and_environment(max_depth, rr_depth):
    """every_kind's covered parameters (not the floor's specular, under a specular
    texture), down to depth 8 with Russian roulette from depth 1 or 2."""
    scene = every_kind()
    require_covered(scene, skip=("objects[0].material.specular",))
    options = {"spp": 4, "max_depth": max_depth, "rr_depth": rr_depth, "seed": max_depth,
               "batch_spp": 2}  # fmt: skip
    _, moved = replay_against_tape(scene, weights_for(scene, max_depth), **options)
    assert moved >= 20


def _material(draw, rng: np.random.Generator) -> render.Material:
    """A drawn diffuse, glossy or mirror material; its specular, reflectance and emission
    scalars or (3,); sometimes one channel of its albedo and of its (3,) specular and
    reflectance 0 (the throughput of that channel ends there, not its derivative)."""
    kind = draw(st.sampled_from(["diffuse", "glossy", "mirror"]))
    shaped = draw(st.booleans())
    dark = draw(st.sampled_from([None, 0, 1, 2]))

    def value(low: float, high: float, zero: bool = True):
        if not shaped:
            return rng.uniform(low, high)
        values = rng.uniform(low, high, 3)
        if dark is not None and zero:
            values[dark] = 0.0
        return values

    albedo = rng.uniform(0.05, 0.9, 3)
    if dark is not None:
        albedo[dark] = 0.0
    return render.Material(
        albedo, specular=value(0.05, 0.5) if kind == "glossy" else 0.0,
        shininess=rng.uniform(1.0, 60.0),
        reflectance=value(0.2, 0.7) if kind == "mirror" else 0.0,
        emission=value(0.2, 2.0, zero=False) if draw(st.booleans()) else 0.0,
    )  # fmt: skip


@st.composite
def small_scenes(draw) -> render.Scene:
    """A box and a sphere sharing one drawn material, more boxes and spheres of drawn
    materials, an emissive sphere, an emissive triangle seen directly, a coloured point
    light and/or directional light, a non-zero background; a camera of 8 to 12 pixels a
    side around the origin (the background fills the corners)."""
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    shared = _material(draw, rng)
    objects = [
        box_mesh(rng.uniform(-0.5, 0.5, 3), rng.uniform(0.1, 0.35, 3), shared),
        render.Sphere(rng.uniform(-0.5, 0.5, 3), rng.uniform(0.1, 0.3), shared),
    ]
    for _ in range(draw(st.integers(0, 2))):
        corner, size = rng.uniform(-0.5, 0.5, 3), rng.uniform(0.1, 0.35, 3)
        objects.append(box_mesh(corner, size, _material(draw, rng)))
    for _ in range(draw(st.integers(0, 2))):
        objects.append(
            render.Sphere(rng.uniform(-0.5, 0.5, 3), rng.uniform(0.1, 0.35), _material(draw, rng))
        )
    emission = rng.uniform(0.5, 5.0, 3) if draw(st.booleans()) else rng.uniform(0.5, 5.0)
    emitter = render.Material(rng.uniform(0.0, 0.5, 3), emission=emission)
    objects.append(render.Sphere(rng.uniform(-0.5, 0.5, 3), rng.uniform(0.1, 0.3), emitter))
    lights = []
    point, directional = draw(st.sampled_from([(True, False), (False, True), (True, True)]))
    if point:
        position, intensity = rng.uniform(-1.5, 1.5, 3), rng.uniform(0.5, 3.0)
        lights.append(render.PointLight(position, intensity, rng.uniform(0.3, 1.0, 3)))
    if directional:
        direction, irradiance = rng.normal(size=3), rng.uniform(0.2, 1.0)
        lights.append(render.DirectionalLight(direction, irradiance, rng.uniform(0.3, 1.0, 3)))
    camera, triangle = drawn_view(draw, rng)
    return render.Scene([*objects, triangle], lights, camera, background=rng.uniform(0.1, 0.8, 3))


@settings(max_examples=8, deadline=None)
@given(
    scene=small_scenes(),
    spp=st.integers(1, 4),
    max_depth=st.integers(1, 6),
    rr_depth=st.integers(1, 4),
    seed=st.integers(0, 2**31 - 1),
)
def test_drawn_scenes(scene, spp, max_depth, rr_depth, seed):
    require_covered(scene)
    options = {"spp": spp, "max_depth": max_depth, "rr_depth": rr_depth, "seed": seed,
               "batch_spp": 2}  # fmt: skip
    _, moved = replay_against_tape(scene, weights_for(scene, seed), **options)
    assert moved >= 2  # max_depth 1: the emissions seen and the background
    assert np.abs(scene.background.grad).max() > 0  # the background is seen


def test_a_zero_channel_of_an_albedo_or_a_reflectance():
    """A wall of albedo (0.6, 0, 0.3), another (0, 0.5, 0.2), a mirror of reflectance
    (0.8, 0.8, 0): the paths that bounce off them carry nothing in that channel, yet the
    image's derivative by that channel of the factor is what reaches the vertex (the tape's
    gradient is not zero there)."""
    scene = cornell_box(8, 8)
    scene.objects[3].material.albedo = md.tensor([0.6, 0.0, 0.3])
    scene.objects[4].material.albedo = md.tensor([0.0, 0.5, 0.2])
    scene.objects[2].material.reflectance = md.tensor([0.8, 0.8, 0.0])
    require_covered(scene)
    options = {"spp": 4, "max_depth": 4, "seed": 1, "batch_spp": 2}
    replay_against_tape(scene, weights_for(scene, 5), **options)


# --------------------------------------------------------------------------------------
# 2: a loss that is not linear, through render.render
# --------------------------------------------------------------------------------------


def test_mse_through_render_render():
    scene = every_kind()
    require_covered(scene, skip=("objects[0].material.specular",))
    target = np.random.default_rng(4).uniform(0.0, 0.5, (8, 8, 3))
    options = {"spp": 4, "max_depth": 4, "seed": 9, "batch_spp": 2}

    def gradients(**gradient):
        for p in scene.parameters():
            p.grad = None
        image = render.render(scene, integrator="path", **options, **gradient)
        md.mean((image - md.tensor(target)) ** 2).backward()
        return {name: p.grad for name, p in scene.named_parameters().items()}

    taped = gradients(gradient="tape")
    with mock.patch.object(kernel, "replay_gradient", wraps=kernel.replay_gradient) as spy:
        replayed = gradients()
    assert spy.call_count == 1
    _, moved = worst_ratio(replayed, taped)
    assert moved >= 20


# --------------------------------------------------------------------------------------
# 3: which scenes the compiled replay takes
# --------------------------------------------------------------------------------------


def _covered_with(name: str | None) -> bool:
    """``covers`` of every_kind with an albedo, a light's colour and the background
    requiring grad, and the parameter ``name`` too (None: nothing more)."""
    scene = every_kind(4)
    for p in scene.parameters():
        p.requires_grad = False
    parameters = scene.named_parameters()
    for wanted in ("objects[3].material.albedo", "lights[0].color", "background", name):
        if wanted is not None:
            parameters[wanted].requires_grad = True
    return adjoint.covers(placed(scene))


@pytest.mark.parametrize(
    "name",
    [
        "objects[3].material.specular", "objects[3].material.shininess",
        "objects[2].material.reflectance", "objects[5].material.emission",
        "objects[7].material.ambient", "lights[0].intensity", "lights[1].irradiance",
        "lights[1].color", "objects[0].material.albedo",  # under a texture
    ],
)  # fmt: skip
def test_covered_parameters(name):
    assert _covered_with(None)
    assert _covered_with(name)


@pytest.mark.parametrize(
    "name",
    [
        "objects[1].vertices", "objects[7].transform.translation", "objects[7].center",
        "objects[7].radius", "objects[5].transform.rotation", "camera.position",
        "lights[0].position", "lights[1].direction", "objects[0].material.texture",
        "objects[0].material.specular",  # under a specular texture
        "objects[0].uvs",
    ],
)  # fmt: skip
def test_parameters_left_to_the_tape(name):
    assert not _covered_with(name)


def test_nothing_to_differentiate_float32_and_uncompiled_lights_are_not_covered():
    scene = cornell_box(4, 4)
    assert not adjoint.covers(placed(scene))
    scene.objects[0].material.albedo = md.tensor(np.float32([0.7, 0.6, 0.5]))
    scene.objects[0].material.albedo.requires_grad = True
    assert not adjoint.covers(placed(scene))
    scene = cornell_box(4, 4)
    scene.lights = [UncompiledPointLight((0.2, 0.5, 0.3), 1.5)]
    scene.lights[0].intensity.requires_grad = True
    assert not adjoint.covers(placed(scene))
    scene.lights = [render.PointLight((0.2, 0.5, 0.3), 1.5)]
    scene.lights[0].intensity.requires_grad = True
    assert adjoint.covers(placed(scene))


def test_an_albedo_and_a_vertex_take_the_tape():
    scene = cornell_box(6, 6)
    scene.objects[4].material.albedo.requires_grad = True
    scene.objects[1].vertices.requires_grad = True
    assert not adjoint.covers(placed(scene))
    options = {"spp": 4, "max_depth": 4, "seed": 5, "batch_spp": 2}
    weights = weights_for(scene, 6)
    _, taped = _gradients(scene, weights, gradient="tape", **options)
    with mock.patch.object(kernel, "replay_gradient", wraps=kernel.replay_gradient) as spy:
        image, replayed = _gradients(scene, weights, **options)
    assert spy.call_count == 0
    assert image.node.name == "path_image"  # replayed, on the tape
    _, moved = worst_ratio(replayed, taped)
    assert moved == 2


# --------------------------------------------------------------------------------------
# 4: threads
# --------------------------------------------------------------------------------------

#: The gradient vector of every_kind at 24 x 24 (576 pixels, nine of the kernel's blocks
#: of 64) on 1 and 2 threads in one process.
_THREADS = """
import numba, numpy as np
from render.path.twin import kernel
from render.path.sample.tracer import PathSampler
from render.scene.placement import placed
from tests.render.path.test_replay import every_kind
sampler = PathSampler(placed(every_kind(24)), 2, 5, 2, 4)
d_image = np.random.default_rng(0).normal(size=(24, 24, 3))
runs = []
for n in (1, 2):
    numba.set_num_threads(n)
    assert numba.get_num_threads() == n
    runs.append(kernel.replay_gradient(sampler, d_image))
assert np.count_nonzero(runs[0]) > 30
assert np.array_equal(runs[0], runs[1]), "gradient"
print("same bits")
"""


@pytest.mark.new_processes
def test_the_same_bits_on_one_and_two_threads():
    """In a new process (a pytest-xdist worker is limited to one Numba thread)."""
    env = {**os.environ, "NUMBA_NUM_THREADS": "2"}
    done = subprocess.run(
        [sys.executable, "-c", _THREADS], env=env, capture_output=True, text=True,
        timeout=300, cwd=Path(__file__).parents[3],  # the repository: imports tests.
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "same bits"


# --------------------------------------------------------------------------------------
# 5: memory
# --------------------------------------------------------------------------------------


def _peak_kb(scene: render.Scene, spp: int, max_depth: int) -> float:
    """Peak traced allocation (KB) of ``adjoint.backpropagate`` of the Cornell box."""
    world = placed(scene)
    sampler = PathSampler(world, spp, max_depth, 100, 0)
    d_image = weights_for(scene)
    for p in scene.parameters():
        p.grad = None
    buffers.clear()
    with buffers.fresh():
        tracemalloc.start()
        try:
            base = tracemalloc.get_traced_memory()[0]
            adjoint.backpropagate(world, sampler, d_image)
            return (tracemalloc.get_traced_memory()[1] - base) / 1e3
        finally:
            tracemalloc.stop()


def test_memory_does_not_grow_with_spp_or_depth():
    """16x more samples, 4x deeper paths: about the same peak, on one Numba thread (each
    thread replays one path at a time). Measured (this machine): 20.8 KB at max_depth 2
    and 21.4 KB at 8, the same at spp 4 and 64 (to 0.03 KB): the packed scene, the
    gradient chunks (16 x 16 pixels are 4 blocks of 64: 4 x 107 floats, 3.4 KB), the
    d_image copy (6 KB) and the chain of the path being replayed (12 floats per vertex:
    what grows with max_depth). A per-path array of colours would add 16 x 16 x 64 x 3 x
    8 B = 393 KB at spp 64; 10 % (2 KB) leaves room for the chain and Python's own small
    allocations."""
    scene = cornell_box(16, 16)
    require_covered(scene)
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        _peak_kb(scene, 4, 2)  # first-call allocations (compiled code, caches) not counted
        peaks = {(spp, depth): _peak_kb(scene, spp, depth) for spp in (4, 64) for depth in (2, 8)}
    finally:
        numba.set_num_threads(threads)
    low = min(peaks.values())
    assert low > 0
    assert max(peaks.values()) < 1.1 * low, peaks


# --------------------------------------------------------------------------------------
# 6: forward mode
# --------------------------------------------------------------------------------------


def test_forward_mode_is_unaffected():
    """A tangent on an albedo while the other covered parameters require grad: the image's
    tangent is the tape's, and so are the gradients (by the compiled replay)."""
    scene = cornell_box(8, 8)
    require_covered(scene)
    albedo = scene.objects[3].material.albedo
    albedo.requires_grad = False  # a tangent only
    weights = weights_for(scene, 7)
    options = {"spp": 4, "max_depth": 4, "seed": 7, "batch_spp": 2}
    with md.tangents({albedo: [1.0, 0.0, 0.5]}):
        taped_image, taped = _gradients(scene, weights, gradient="tape", **options)
    with mock.patch.object(kernel, "replay_gradient", wraps=kernel.replay_gradient) as spy:
        with md.tangents({albedo: [1.0, 0.0, 0.5]}):
            image, replayed = _gradients(scene, weights, **options)
    assert spy.call_count == 1
    tangent = taped_image.tangent
    assert np.abs(tangent).max() > 0
    np.testing.assert_allclose(image.tangent, tangent, rtol=0, atol=RTOL * np.abs(tangent).max())
    assert replayed["objects[3].material.albedo"] is None
    worst_ratio(replayed, taped)
