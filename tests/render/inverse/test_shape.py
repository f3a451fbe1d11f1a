"""Shape optimisation's pieces (``render.inverse.shape``): the Laplacian, Large Steps and its
optimiser, uniform Adam, subdivision, and the surface distances the experiments report."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.sparse.csgraph import connected_components

import minidiff as md
from render.inverse.shape import (
    LargeSteps,
    LargeStepsAdam,
    closest_on_triangles,
    distance_to_mesh,
    icosphere,
    laplacian_loss,
    mesh_laplacian,
    subdivide,
    surface_distances,
    weld,
)

FEW = settings(max_examples=15, deadline=None)


def test_laplacian_is_degree_minus_adjacency():
    v, f = icosphere(1)
    lap = mesh_laplacian(f, len(v)).toarray()
    dense = np.zeros_like(lap)
    for face in f:
        for i, j in ((0, 1), (1, 2), (2, 0)):
            dense[face[i], face[j]] = dense[face[j], face[i]] = -1.0
    dense[np.diag_indices_from(dense)] = -dense.sum(axis=1)
    assert np.array_equal(lap, dense)
    assert np.allclose(lap @ np.ones(len(v)), 0) and np.array_equal(lap, lap.T)


def test_non_manifold_edges_are_refused_by_name():
    faces = np.array([[0, 1, 2], [0, 1, 3], [0, 1, 4]])  # three faces on the edge (0, 1)
    with pytest.raises(ValueError, match=r"faces: the edge \(0, 1\) is shared by 3 faces"):
        mesh_laplacian(faces, 5)
    with pytest.raises(ValueError, match=r"faces: indices must lie in \[0, 4\)"):
        LargeSteps(faces, 4)
    with pytest.raises(ValueError, match="lam must be a number > 0"):
        LargeSteps(faces[:1], 3, lam=0.0)


@FEW
@given(lam=st.floats(0.1, 100.0), seed=st.integers(0, 2**31), subdivisions=st.integers(0, 1))
def test_large_steps_gradient_matches_central_differences(lam, seed, subdivisions):
    """v = M^-1 u on the tape: d loss / du against central differences, for a loss of v
    that is not linear (so that a wrong adjoint cannot pass)."""
    rng = np.random.default_rng(seed)
    v, f = icosphere(subdivisions)
    steps = LargeSteps(f, len(v), lam)
    u0 = steps.to_u(v + 0.1 * rng.standard_normal(v.shape))
    weights = rng.standard_normal(v.shape)

    def loss(u):
        x = steps.vertices(u)
        return md.sum(md.sin(x) * weights) + laplacian_loss(steps.laplacian, x)

    u = md.tensor(u0, requires_grad=True)
    loss(u).backward()
    direction = rng.standard_normal(v.shape)
    h = 1e-6
    numeric = (
        loss(md.tensor(u0 + h * direction)).item() - loss(md.tensor(u0 - h * direction)).item()
    ) / (2 * h)
    assert abs(float(np.sum(u.grad * direction)) - numeric) <= 1e-6 * max(1.0, abs(numeric))
    assert np.allclose(steps.to_vertices(steps.to_u(v)), v, atol=1e-12)


def test_uniform_adam_divides_by_the_largest_second_moment():
    x = md.tensor(np.array([1.0, 2.0, 3.0]), requires_grad=True)
    opt = md.optim.Adam([x], lr=0.1, uniform=True)
    x.grad = np.array([0.5, -2.0, 1.0])
    opt.step()
    # first step: m^ = g, sqrt(v^) = |g|, the largest |g| is 2
    assert np.allclose(x.data, [1.0, 2.0, 3.0] - 0.1 * np.array([0.5, -2.0, 1.0]) / (2.0 + 1e-8))
    with pytest.raises(TypeError, match="uniform must be a bool"):
        md.optim.Adam([x], uniform="yes")


def test_large_steps_adam_follows_the_tape_parameterisation():
    """Three steps of LargeStepsAdam on the vertices equal three steps of uniform Adam on
    u, differentiating v = M^-1 u on the tape."""
    rng = np.random.default_rng(3)
    v0, f = icosphere(1)
    target = v0 * 1.3 + 0.05 * rng.standard_normal(v0.shape)

    def loss(x):
        return md.sum((x - target) ** 2 * np.arange(1, len(v0) + 1)[:, None])

    vertices = md.tensor(v0.copy(), requires_grad=True)
    opt = LargeStepsAdam(vertices, f, lam=10.0, lr=0.05)
    steps = LargeSteps(f, len(v0), 10.0)
    u = md.tensor(steps.to_u(v0), requires_grad=True)
    reference = md.optim.Adam([u], lr=0.05, uniform=True)
    for _ in range(3):
        opt.zero_grad()
        loss(vertices).backward()
        opt.step()
        reference.zero_grad()
        loss(steps.vertices(u)).backward()
        reference.step()
    assert np.allclose(vertices.data, steps.to_vertices(u.data), rtol=0, atol=1e-12)
    assert np.abs(vertices.data - v0).max() > 0.03  # it moved (3 steps of lr 0.05)


def test_closest_points_match_a_search_over_all_triangles():
    rng = np.random.default_rng(0)
    vertices = rng.standard_normal((20, 3))
    faces = rng.integers(0, 20, (40, 3))  # overlapping, and some degenerate (repeated ids)
    faces[:3, 1] = faces[:3, 0]
    points = 1.5 * rng.standard_normal((400, 3))
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    _, expected, _ = trimesh.proximity.closest_point_naive(mesh, points)
    assert np.abs(distance_to_mesh(points, vertices, faces) - expected).max() < 1e-12
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    one = closest_on_triangles(points[:1, None], a, b, c)
    assert one.shape == (1, 40, 3)


def test_surface_distances_of_a_scaled_sphere():
    """A sphere of radius 1.01 against one of radius 1 (the same icosphere scaled): the
    vertices are 0.01 apart, the parallel facets' planes slightly less."""
    v, f = icosphere(4)
    result = surface_distances(v * 1.01, f, v, f, samples=4000)
    diagonal = np.linalg.norm(np.ptp(v, axis=0))
    assert result.chamfer == pytest.approx(100 * 0.01 / diagonal, rel=0.02)
    assert 0.99 * 100 * 0.01 / diagonal <= result.hausdorff <= (1 + 1e-9) * 100 * 0.01 / diagonal
    same = surface_distances(*subdivide(v, f), v, f, samples=4000)
    assert same.chamfer < 1e-12 and same.hausdorff < 1e-12


def test_weld_joins_the_teapots_seams_and_drops_collapsed_faces():
    from render.scene.teapot import teapot_geometry

    vertices, faces = (np.asarray(a) for a in teapot_geometry()[:2])
    welded, welded_faces, index = weld(vertices, faces)
    assert len(welded) < len(vertices)  # the patches repeat their seams' vertices
    np.testing.assert_allclose(welded[index], vertices, atol=1e-9)

    # Same triangles, less the collapsed ones (the poles): their corners are unchanged.
    def area(corners):
        a, b, c = corners[:, 0], corners[:, 1], corners[:, 2]
        return np.linalg.norm(np.cross(b - a, c - a), axis=1).sum()

    np.testing.assert_allclose(area(welded[welded_faces]), area(vertices[faces]), rtol=1e-12)
    assert np.all(welded_faces != np.roll(welded_faces, 1, axis=1))  # no corner repeated

    # Unwelded, the Laplacian couples nothing across a seam: 32 separate patches.
    # Welded, the teapot is a manifold (a Laplacian accepts it) of a few connected parts.
    def parts(f, n):
        return connected_components(mesh_laplacian(f, n) != 0)[0]

    assert parts(faces, len(vertices)) == 32
    assert parts(welded_faces, len(welded)) < 8


def test_a_regions_share_of_the_chamfer_distance():
    """A sphere grown by 1 % against the unit sphere: every sample is 0.01 off, so the
    upper half-space holds half the Chamfer sum, and outside it the Chamfer is the same."""
    v, f = icosphere(4)
    upper = (np.array([-2.0, -2.0, 0.0]), np.array([2.0, 2.0, 2.0]))
    result = surface_distances(v * 1.01, f, v, f, samples=4000, region=upper)
    assert result.region_share == pytest.approx(50.0, abs=3.0)
    assert result.chamfer_outside == pytest.approx(result.chamfer, rel=0.02)
    assert np.linalg.norm(result.worst) == pytest.approx(1.0, abs=0.011)
    everything = surface_distances(v * 1.01, f, v, f, samples=4000, region=(-upper[1], upper[1]))
    assert everything.region_share == pytest.approx(100.0) and np.isnan(everything.chamfer_outside)
    assert np.isnan(surface_distances(v * 1.01, f, v, f, samples=500).region_share)
