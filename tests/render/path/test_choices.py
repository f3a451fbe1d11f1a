"""The sampler's compiled choices (``render.path.sample.choices``) and the densities they use
(``render.path.sample.sampling``): the compiled call is its formulas run primitive by primitive,
and every density is the density of the directions drawn with it."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

import minidiff as md
from render.path.integrator import _batch_paths
from render.path.sample import sampling
from render.path.sample.tracer import PathSampler
from render.scene.cornell import cornell_box
from render.scene.placement import placed
from tests.render.path.test_kernel import assert_same_decisions, small_scenes
from tests.render.path.test_replay import every_kind


def _samples(scene, spp: int, max_depth: int, rr_depth: int, seed: int, on_the_tape: bool):
    world = placed(scene)
    sampler = PathSampler(world, spp, max_depth, rr_depth, seed)
    paths = _batch_paths(world, sampler, 0, spp)
    if on_the_tape:
        with md.tape_only():
            return sampler.sample(paths)
    return sampler.sample(paths)


def _assert_same_batches(ours, reference) -> None:
    """The same decisions, and every continuous field equal to rounding: the compiled kernel
    runs each primitive's scalar form in the order the tape runs it, but the two need not
    call the same ``exp``, ``log`` or ``pow``. The compiled kernel calls the C library's;
    NumPy, on a CPU with AVX-512, its own SIMD versions, which differ in the last bit
    (``tests/render/test_golden.py`` says more). On this test's scene an Intel Xeon with
    AVX-512 gave one ``nee_weight`` of 70 one ulp apart; a CPU without it, the same bits."""
    assert_same_decisions(ours, reference)
    for mine, theirs in zip(ours.vertices, reference.vertices, strict=True):
        for name in ("emit_weight", "nee_weight", "next_pdf", "survive", "escape_dir"):
            a, b = getattr(mine, name), getattr(theirs, name)
            # A few roundings of each of tens of operations (1.1e-16 each), of the field's
            # largest value; another formula or sample moves values by far more.
            scale = float(np.max(np.abs(b), initial=0.0))
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-13 * scale, err_msg=name)


def test_the_compiled_choices_are_their_formulas_on_a_scene_of_every_kind():
    """Glossy, mirror, textured and smooth surfaces, spheres, every light kind."""
    compiled = _samples(every_kind(6), 3, 5, 2, 7, on_the_tape=False)
    reference = _samples(every_kind(6), 3, 5, 2, 7, on_the_tape=True)
    assert len(compiled.vertices) >= 3
    _assert_same_batches(compiled, reference)


@settings(max_examples=6, deadline=None)
@given(
    scene=small_scenes(),
    max_depth=st.integers(1, 5),
    rr_depth=st.integers(1, 4),
    seed=st.integers(0, 2**31 - 1),
)
def test_the_compiled_choices_are_their_formulas_on_drawn_scenes(scene, max_depth, rr_depth, seed):
    compiled = _samples(scene, 2, max_depth, rr_depth, seed, on_the_tape=False)
    reference = _samples(scene, 2, max_depth, rr_depth, seed, on_the_tape=True)
    _assert_same_batches(compiled, reference)


def test_the_cornell_box_paths_reach_every_kind_of_decision():
    batch = _samples(cornell_box(8, 8, blocks=True), 4, 6, 2, 3, on_the_tape=False)
    assert any((v.nee_prim >= 0).any() for v in batch.vertices)  # NEE saw the light
    assert any((v.survive < 1).any() for v in batch.vertices)  # Russian roulette played
    assert any((v.emit_weight < 1).any() for v in batch.vertices)  # MIS weighed emission


def _unit_rows(rng, n):
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), shininess=st.floats(0.0, 8.0))
def test_each_density_is_the_density_of_its_directions(seed, shininess):
    """Over the sphere of directions, the mean of p (uniform directions) times 4 pi is the
    share of the drawn directions where p is positive: 1 for the cosine lobe, and for the
    Blinn-Phong lobe the share of reflected directions above the surface."""
    rng = np.random.default_rng(seed)
    n = 200_000
    normal = np.tile(_unit_rows(rng, 1), (n, 1))
    view = _unit_rows(rng, 1)
    view = view * np.sign(view @ normal[0])  # the viewer on the normal's side
    view = np.tile(view, (n, 1))
    s = np.full(n, shininess)
    uniform_dirs = _unit_rows(rng, n)
    u1, u2 = rng.random(n), rng.random(n)

    drawn = sampling.cosine_hemisphere(u1, u2, normal).data
    assert np.all(drawn @ normal[0] >= -1e-12)
    mass = 4 * math.pi * sampling.cosine_pdf(normal, uniform_dirs).data.mean()
    assert abs(mass - 1.0) < 0.02, mass

    drawn = sampling.blinn_phong_lobe(u1, u2, normal, view, s).data
    above = np.mean(drawn @ normal[0] > 0)
    mass = 4 * math.pi * sampling.blinn_phong_pdf(normal, view, uniform_dirs, s).data.mean()
    assert abs(mass - above) < 0.03 * max(above, 0.1), (mass, above)
