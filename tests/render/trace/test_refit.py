"""Refitting the BVH to moved primitives (``Accelerator.refitted``, ``accel.updated``): the
same topology with new boxes answers every ray as brute force does, bit for bit; its boxes
are the build's for the same primitives; a tree whose SAH cost grew too much is built anew;
and a render of moved vertices, which refits the cached tree, is the render without the
cache."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import minidiff as md
import render
from minidiff.threads import using_threads
from render.scene.cache import cache_for
from render.trace.accel import REBUILD_RATIO, Accelerator, updated
from render.trace.bvh import build_bvh, primitive_bounds, refit_bounds, sah_cost
from tests.render.trace.test_accel import assert_same_hits, rays_for, soups, sphere_mesh

SETTINGS = settings(max_examples=40, deadline=None)
NO_SPHERES = (np.zeros((0, 3)), np.zeros(0))


def _spheres(draw) -> tuple[np.ndarray, np.ndarray]:
    n = draw(st.integers(0, 5))
    centers = np.array(draw(st.lists(st.tuples(*[st.floats(-3, 3)] * 3), min_size=n,
                                     max_size=n)), np.float64).reshape(-1, 3)  # fmt: skip
    radii = np.array(draw(st.lists(st.floats(0.05, 1.0), min_size=n, max_size=n)), np.float64)
    return centers, radii


@SETTINGS
@given(data=st.data(), tris=soups(min_size=1, max_size=80), parallel=st.booleans())
def test_refit_to_the_same_primitives_gives_the_builds_boxes(data, tris, parallel):
    """Unions of the same boxes, grouped otherwise: the same bits, for the serial build's
    numbering and the parallel build's (children after parents either way)."""
    centers, radii = _spheres(data.draw)
    lo, hi = primitive_bounds(tris, centers, radii)
    bounds, first, count, order, _ = build_bvh(lo, hi, parallel_min_prims=1 if parallel else 10**9)
    np.testing.assert_array_equal(refit_bounds(first, count, order, tris, centers, radii), bounds)


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_a_large_refit_gives_the_builds_boxes_on_any_number_of_threads(threads):
    """A mesh of 12,800 triangles (over 16,384 nodes: the leaves' boxes are shared out
    among the threads), jittered: the same boxes as the build over the jittered corners."""
    tris = sphere_mesh(80, 80) + 1e-3 * np.random.default_rng(1).normal(size=(12800, 3, 3))
    lo, hi = primitive_bounds(tris, *NO_SPHERES)
    bounds, first, count, order, _ = build_bvh(lo, hi)
    with using_threads(threads):
        refit = refit_bounds(first, count, order, tris, *NO_SPHERES)
    np.testing.assert_array_equal(refit, bounds)


@SETTINGS
@given(data=st.data(), tris=soups(min_size=1, max_size=40),
       scale=st.sampled_from([1e-6, 1e-2, 0.3, 3.0]))  # fmt: skip
def test_a_refitted_tree_answers_as_brute_force(data, tris, scale):
    """Every corner and sphere moved (a little or far, so that leaves overlap): closest hits
    and shadow rays as brute force gives them, bit for bit; every box holds its primitives
    and its children."""
    centers, radii = _spheres(data.draw)
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    built = Accelerator(tris, centers, radii)
    moved = tris + scale * rng.normal(size=tris.shape)
    moved_centers = centers + scale * rng.normal(size=centers.shape)
    refit = built.refitted(moved, moved_centers, radii)
    assert refit.refits == 1 and refit.built_cost == built.sah_cost
    assert refit.node_first is built.node_first and refit.leaf_ids is built.leaf_ids
    brute = Accelerator(moved, moved_centers, radii, use_bvh=False)
    o, d = data.draw(rays_for(moved, moved_centers, 150))
    assert_same_hits(refit.closest_hit(o, d), brute.closest_hit(o, d))
    tmax = rng.choice([np.inf, 1.0, 0.5], size=len(o))
    np.testing.assert_array_equal(refit.occluded(o, d, tmax), brute.occluded(o, d, tmax))
    lo, hi = primitive_bounds(moved, moved_centers, radii)
    for n in range(refit.n_nodes):
        box = refit.node_bounds[n]
        if refit.node_count[n]:
            ids = refit.leaf_ids[refit.node_first[n] : refit.node_first[n] + refit.node_count[n]]
            assert np.all(box[:3] <= lo[ids]) and np.all(box[3:] >= hi[ids])
        else:
            for c in (refit.node_first[n], refit.node_first[n] + 1):
                child = refit.node_bounds[c]
                assert np.all(box[:3] <= child[:3]) and np.all(box[3:] >= child[3:])
    # The tree it was refitted from still answers for the primitives it was built over.
    np.testing.assert_array_equal(built.node_bounds, Accelerator(tris, centers, radii).node_bounds)


def test_sah_cost_of_a_small_tree():
    """A root box 2 x 1 x 1 (half area 5) over two unit cubes (3 each), one primitive per
    leaf: 1 * 5/5 + 1 * 3/5 + 1 * 3/5 = 2.2; an empty tree costs 0."""
    bounds = np.array([[0, 0, 0, 2, 1, 1], [0, 0, 0, 1, 1, 1], [1, 0, 0, 2, 1, 1]], float)
    first, count = np.array([1, 0, 1]), np.array([0, 1, 1])
    assert sah_cost(bounds, first, count, 1.0) == pytest.approx(2.2, rel=1e-15)
    assert sah_cost(np.zeros((0, 6)), np.zeros(0, np.int64), np.zeros(0, np.int64), 1.0) == 0.0


def test_updated_refits_until_the_cost_grows_past_the_ratio():
    tris = sphere_mesh(20, 30)
    rng = np.random.default_rng(3)
    built = updated(None, tris)
    assert built.refits == 0
    jittered = updated(built, tris + 1e-3 * rng.normal(size=tris.shape))
    assert jittered.refits == 1 and jittered.node_first is built.node_first
    assert jittered.sah_cost <= REBUILD_RATIO * built.sah_cost
    # Corners thrown across the scene: the old leaves would span it, a new tree is built.
    scrambled = tris[rng.permutation(len(tris))].reshape(-1, 3)[rng.permutation(3 * len(tris))]
    rebuilt = updated(jittered, scrambled.reshape(tris.shape))
    assert rebuilt.refits == 0 and rebuilt.node_first is not built.node_first
    # ... because the refit would have cost more than REBUILD_RATIO times the build's.
    refit = jittered.refitted(scrambled.reshape(tris.shape))
    assert refit.sah_cost > REBUILD_RATIO * refit.built_cost
    # Another count of primitives, or brute force asked for: built anew.
    assert updated(built, tris[:-1]).refits == 0
    assert not updated(built, tris, use_bvh=False).use_bvh
    brute = updated(updated(None, tris, use_bvh=False), tris + 1.0, use_bvh=False)
    assert brute.refits == 1 and not brute.use_bvh  # one leaf: always refitted


def test_refitted_refuses_other_primitives_by_name():
    acc = Accelerator(sphere_mesh(4, 6))
    with pytest.raises(ValueError, match="refitted: the tree holds 48 triangles and 0 spheres"):
        acc.refitted(sphere_mesh(4, 5))
    with pytest.raises(ValueError, match="triangles must be finite"):
        acc.refitted(np.full((48, 3, 3), np.nan))


def test_a_render_of_moved_vertices_refits_the_cached_tree_and_is_the_fresh_render():
    """Two renders of a shape step (vertices moved in place, as an optimiser does): the
    second refits the tree the first built, and its image and vertex gradient are those of
    a render without the cache, bit for bit."""
    scene = render.paper_scene(width=24, height=20)
    teapot = scene.objects[0]
    teapot.vertices = md.tensor(teapot.vertices.data, requires_grad=True)
    render.render(scene, primary="bvh").sum().backward()
    rng = np.random.default_rng(0)
    teapot.vertices.data += 2e-3 * rng.normal(size=teapot.vertices.shape)
    results = []
    for reuse in (True, False):
        teapot.vertices.grad = None
        image = render.render(scene, primary="bvh", reuse_visibility=reuse)
        image.sum().backward()
        results.append((image.data, teapot.vertices.grad))
    assert cache_for(scene, True).latest(("accelerator", True)).refits == 1
    for cached, fresh in zip(*results, strict=True):
        np.testing.assert_array_equal(cached, fresh)


def test_bench_refit_quick(tmp_path, load_script):
    """The benchmark runs (tiny sizes) and reports finite times and costs."""
    load_script("benchmarks/bench_refit.py").main(["--quick", "--out", str(tmp_path)])
    data = json.loads((tmp_path / "refit.json").read_text(encoding="utf-8"))
    assert data["meshes"][0]["refit_ms"] > 0 and data["meshes"][0]["sah_refit"] > 0
    assert data["shape_fit"]["renders"] > 0 and data["shape_fit"]["sah_over_fresh_max"] > 0


def test_the_path_integrator_keeps_the_scenes_tree_and_refits_it(monkeypatch):
    """Path-traced gradient steps: the render and its backward share the scene's cached
    tree (one build for both), the next step's moved vertices refit it, and image and
    gradient are those of the same scene rendered with a cache of its own, bit for bit."""
    from render.path import render_path
    from render.scene.cornell import cornell_box

    builds = []
    build = Accelerator.__init__
    monkeypatch.setattr(Accelerator, "__init__", lambda self, *a, **k: builds.append(1)
                        or build(self, *a, **k))  # fmt: skip

    def step(scene, shift):
        block = scene.objects[6]
        block.vertices = md.tensor(block.vertices.data + shift, requires_grad=True)
        image = render_path(scene, spp=2, max_depth=3, seed=4)
        md.sum(image * image).backward()
        return image.data, block.vertices.grad

    scene = cornell_box(8, 8, blocks=True)
    cache = cache_for(scene, True)
    first = step(scene, 0.0)
    assert len(builds) == 1 and cache.latest(("accelerator", True)).refits == 0
    moved = step(scene, 1e-3)
    assert len(builds) == 1 and cache.latest(("accelerator", True)).refits == 1
    for ours, theirs in zip(moved, step(cornell_box(8, 8, blocks=True), 1e-3), strict=True):
        np.testing.assert_array_equal(ours, theirs)
    assert len(builds) == 2  # the other scene's cache built its own
    assert not np.array_equal(first[0], moved[0])  # the block moved in the image
