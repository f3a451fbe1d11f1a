"""Edges lying exactly on pixel borders (an axis-aligned scene seen by a centred camera):
the boundary term takes the symmetric derivative, half the jump to each pixel beside the
border (``render.edges.boundary.pixels.border_lines``), which central differences measure.

Before, a piece of curve on a border went wholly to the pixel on its right (or below): the
one-sided derivative. Measured on the scenes below (weights uniform in [0, 1]): the seam
moved along x 1.272 against the central difference's 0.667 (+91 %), the outline moved
along x and y 3.403 and 4.958 against 2.377 and 3.999; now 0.666, 2.374 and 4.004 (0.2 %).

The truth here is not the usual jittered supersampling (``render.inverse.reference``): at
256 samples per pixel its noise was 5 % on these scenes. On them the box-filtered image's
central difference can be had exactly instead: every edge that moves lies on a pixel border
and moves perpendicular to itself (the other edges slide along themselves or do not move),
the plane's shading at a fixed pixel does not change (the edges move within the plane),
and a fixed n x n grid of samples (``render(spp=n * n)``) counts the strip an edge sweeps
exactly when the edge moves by a whole number of sample spacings from a pixel border: it
then passes exactly that many columns (or rows) of samples, each 1/n of a pixel, and the
difference is the box-filtered image's, whose central difference is the mean of the two
one-sided derivatives. The moving edges' ends lie on pixel borders or half-way between
(the seam's ends at rows 4.5 and 11.5), where the grid also counts their length exactly
(the seam ending at row 4.4 was counted 0.625 pixels long by the grid: 4 % off). Along an
edge the n samples per pixel are a midpoint rule of the jump, as the one quadrature point
per pixel is. (Moving the seam along itself tilts the quads' top and bottom edges: the grid
is not exact there, and that case is left out.)
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import minidiff as md
from render import Camera, Material, Mesh, PointLight, Scene, Transform, render
from render.edges.boundary.kind_points import kind_points
from render.edges.boundary.pixels import (
    border_share,
    pixel_pieces,
    quadrature,
    split_at_crossings,
)

SIZE = 16
#: The plane z = 0 spans x, y in [-2, 2] in the image: 4 pixels per unit, the origin on a
#: pixel corner (8, 8).
FOV = 2.0 * math.degrees(math.atan(2.0 / 3.0))
PER_UNIT = SIZE / 4.0
GRID = 8  # samples per pixel along each axis of the truth's renders
RED, GREEN = Material(albedo=(0.8, 0.1, 0.1)), Material(albedo=(0.1, 0.8, 0.2))
QUAD = np.array([[0, 1, 2], [0, 2, 3]])


def _quad(x0: float, x1: float, y0: float, y1: float) -> np.ndarray:
    return np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0.0]])


def _scene(kind: str, offset: np.ndarray) -> Scene:
    """ "seam": a red and a green quad meeting along x = 0 (on the border of columns 7 and
    8), its two vertices moved by the leaf ``scene.moved`` (their value ``offset``), the
    outline off the pixel grid (x = 3.6 and 12.4, y = 4.5 and 11.5 pixels); "outline": one
    quad whose outline lies on the borders x = 4 and 12, y = 5 and 11, moved by a
    ``Transform``."""
    moved = md.tensor(np.array(offset, float), requires_grad=True)
    if kind == "seam":
        left, right = _quad(-1.1, 0, -0.875, 0.875), _quad(0, 1.1, -0.875, 0.875)
        vertices = md.tensor(np.concatenate([left, right[[1, 2]]]))
        vertices = vertices + md.reshape(moved, (1, 3)) * np.array([0, 1, 1, 0, 0, 0.0])[:, None]
        objects = [Mesh(vertices, QUAD, RED), Mesh(vertices, [[1, 4, 5], [1, 5, 2]], GREEN)]
    else:
        objects = [
            Mesh(_quad(-1, 1, -0.75, 0.75), QUAD, RED, transform=Transform(translation=moved))
        ]
    camera = Camera(position=(0, 0, 3.0), look_at=(0, 0, 0), fov=FOV, width=SIZE, height=SIZE)
    scene = Scene(objects, [PointLight((1.0, 2.0, 4.0), 40.0)], camera)
    scene.moved = moved
    return scene


def _truth(kind: str, weights: np.ndarray, direction: np.ndarray) -> float:
    """(L(h) - L(-h)) / 2h of L = sum(weights * image), the images rendered on a fixed
    GRID x GRID pattern, h one sample spacing (module docstring: exact for these scenes)."""
    h = 1.0 / (GRID * PER_UNIT)
    loss = [
        float(np.sum(weights * render(_scene(kind, s * direction), spp=GRID**2).data))
        for s in (h, -h)
    ]
    return (loss[0] - loss[1]) / (2.0 * h)


def _ours(kind: str, weights: np.ndarray, direction: np.ndarray) -> float:
    scene = _scene(kind, np.zeros(3))
    (render(scene, antialias="boundary") * weights).sum().backward()
    return float(scene.moved.grad @ direction)


@pytest.mark.parametrize("kind", ["seam", "outline"])
def test_edges_on_pixel_borders_get_the_central_difference(kind):
    """The seam moved across itself, and the outline moved along both axes of the plane:
    within 5 % of the exact central difference (measured: 0.2 %)."""
    weights = np.random.default_rng(1).uniform(0.0, 1.0, (SIZE, SIZE, 3))
    axes = [np.eye(3)[0]] if kind == "seam" else [np.eye(3)[0], np.eye(3)[1]]
    truth = [_truth(kind, weights, d) for d in axes]
    ours = [_ours(kind, weights, d) for d in axes]
    assert min(np.abs(truth)) > 0.1
    error = np.linalg.norm(np.subtract(ours, truth)) / np.linalg.norm(truth)
    assert error < 0.05, (ours, truth)


def test_a_piece_on_a_border_is_shared_by_the_pixels_beside_it():
    """A vertical segment on x = 3 gives each of its pieces to columns 2 and 3 with half the
    weight, a horizontal one on the image's top border half to row 0 alone (there is no row
    above), a degenerate one on a pixel corner a quarter to each of four; one off the grid
    keeps its whole weight in one pixel; ``kind_points`` deals each kind its pieces'
    points with those weights."""
    p0 = np.array([[3.0, 1.5], [0.5, 0.0], [5.0, 5.0], [1.2, 1.5]])
    p1 = np.array([[3.0, 3.5], [1.5, 0.0], [5.0, 5.0 + 1e-12], [1.2, 2.5]])
    width = height = 8
    segment, start, end, pixel = pixel_pieces(p0, p1, width, height)
    _, on, weight = quadrature(p0, p1, segment, start, end)
    np.testing.assert_array_equal(border_share(p0, p1), [0.5, 0.5, 0.25, 1.0])
    total = np.bincount(on, weights=weight, minlength=4)
    length = np.linalg.norm(p1 - p0, axis=1)
    np.testing.assert_allclose(total, length * [1.0, 0.5, 1.0, 1.0])
    vertical = {(int(p) // width, int(p) % width) for p in pixel[segment == 0]}
    assert vertical == {(r, c) for r in (1, 2, 3) for c in (2, 3)}
    assert sorted(pixel[segment == 1] // width) == [0, 0]
    corner = {(int(p) // width, int(p) % width) for p in pixel[segment == 2]}
    assert corner == {(4, 4), (4, 5), (5, 4), (5, 5)}
    assert set(pixel[segment == 3]) == {1 * width + 1, 2 * width + 1}
    # Dealt to two kinds (segment 0, then 1-3): each kind's own segments, their weights.
    pieces = split_at_crossings(p0, p1, segment, start, end, pixel)
    dealt = kind_points(p0, p1, pieces, np.array([1, 3]), width, height)
    assert [len(np.unique(own)) for own, *_ in dealt] == [1, 3]
    for *_, rows in dealt:  # each kind's points in the pieces' order
        assert np.all(np.diff(rows) > 0)
    np.testing.assert_allclose(np.bincount(dealt[0][0], weights=dealt[0][3]), total[:1])
    np.testing.assert_allclose(np.bincount(dealt[1][0], weights=dealt[1][3]), total[1:])
