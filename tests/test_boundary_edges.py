"""render(antialias="boundary"): the boundary integral along edges and outlines
(``render.edges.boundary``), checked against what it estimates: central differences of
supersampled renders (1,024 samples per pixel), for a weighted image loss.

Bound: 5 % relative l2 error of the gradient. What limits it besides the method: the
interior term at one sample per pixel (a pixel cut by an edge counts the shading
derivative of whichever surface its centre sees) and the reference's own error (a
1,024-sample staircase, differenced over +-h).
"""

from __future__ import annotations

import numpy as np
import pytest

import minidiff as md
from render import Camera, Material, Mesh, PointLight, Scene, Sphere, render
from render.edges.boundary import pixel_pieces

SIZE = 32
FLAT = Material(albedo=(0.0, 0.0, 0.0), ambient=1.0)  # one colour: the edges alone
LIT = Material(albedo=(0.6, 0.5, 0.4))


def _weights(size: int = SIZE) -> np.ndarray:
    return np.random.default_rng(1).uniform(0.0, 1.0, (size, size, 3))


def _uv_sphere(n: int) -> tuple[np.ndarray, np.ndarray]:
    """A closed triangulated sphere of radius 0.8: n rings, 2n segments."""
    theta = np.linspace(0.0, np.pi, n + 1)[1:-1]
    phi = np.linspace(0.0, 2.0 * np.pi, 2 * n, endpoint=False)
    ring = np.stack(
        [np.outer(np.sin(theta), np.cos(phi)), np.outer(np.cos(theta), np.ones_like(phi)),
         np.outer(np.sin(theta), np.sin(phi))], axis=-1,
    ).reshape(-1, 3)  # fmt: skip
    vertices = np.concatenate([[[0.0, 1.0, 0.0]], ring, [[0.0, -1.0, 0.0]]]) * 0.8
    m, last = 2 * n, len(ring) + 1
    faces = [[0, 1 + (j + 1) % m, 1 + j] for j in range(m)]
    for i in range(n - 2):
        for j in range(m):
            a, b = 1 + i * m + j, 1 + i * m + (j + 1) % m
            faces += [[a, b, b + m], [a, b + m, a + m]]
    base = 1 + (n - 2) * m
    faces += [[last, base + j, base + (j + 1) % m] for j in range(m)]
    return vertices, np.array(faces)


def _scene(kind: str, offset, material: Material) -> Scene:
    camera = Camera(position=(0.3, 0.5, 4.0), look_at=(0, 0, 0), width=SIZE, height=SIZE)
    light = PointLight((1.0, 2.0, 5.0), 30.0)
    if kind == "triangle":
        vertices = np.array([[-1.0, -0.7, 0.0], [1.2, -0.5, 0.0], [0.1, 0.9, 0.2]])
        objects = [Mesh(vertices + offset, [[0, 1, 2]], material)]
    elif kind == "sphere":
        objects = [Sphere(np.array([0.1, 0.2, 0.0]) + offset, 0.8, material)]
    elif kind == "mesh sphere":
        vertices, faces = _uv_sphere(12)
        objects = [Mesh(vertices + offset, faces, material)]
    else:  # a triangle in front of a sphere: T-junctions where their outlines cross
        vertices = np.array([[-1.2, -0.9, 0.6], [0.4, -0.6, 0.6], [-0.3, 0.5, 0.7]])
        objects = [
            Mesh(vertices + offset, [[0, 1, 2]], Material(albedo=(0.2, 0.6, 0.3))),
            Sphere(np.array([0.2, 0.1, -0.3]), 0.8, material),
        ]
    return Scene(objects, [light], camera)


def _moved(scene: Scene) -> md.Tensor:
    obj = scene.objects[0]
    return obj.vertices if isinstance(obj, Mesh) else obj.center


def _loss(kind, offset, material, spp, weights) -> float:
    with md.no_grad():
        image = render(_scene(kind, offset, material), spp=spp, reuse_visibility=False)
    return float(np.sum(weights * image.data))


def _supersampled_gradient(kind, material, h=0.01, spp=1024) -> np.ndarray:
    weights = _weights()
    return np.array([
        (_loss(kind, h * e, material, spp, weights) - _loss(kind, -h * e, material, spp, weights))
        / (2.0 * h)
        for e in np.eye(3)
    ])  # fmt: skip


def _boundary_gradient(kind, material, antialias="boundary") -> np.ndarray:
    scene = _scene(kind, np.zeros(3), material)
    moved = _moved(scene)
    moved.requires_grad = True
    image = render(scene, antialias=antialias, reuse_visibility=False)
    (image * _weights()).sum().backward()
    return moved.grad if moved.grad.ndim == 1 else moved.grad.sum(axis=0)


@pytest.mark.parametrize(
    "kind, material",
    [("triangle", FLAT), ("triangle", LIT), ("sphere", FLAT), ("mesh sphere", FLAT),
     ("overlap", FLAT), ("overlap", LIT)],
)  # fmt: skip
def test_translation_gradient_matches_supersampled_differences(kind, material):
    truth = _supersampled_gradient(kind, material)
    ours = _boundary_gradient(kind, material)
    error = np.linalg.norm(ours - truth) / np.linalg.norm(truth)
    assert error < 0.05, (kind, ours, truth, error)
    # The boundary term is what makes the difference: without it the error is large.
    plain = _boundary_gradient(kind, material, antialias=False)
    assert np.linalg.norm(plain - truth) / np.linalg.norm(truth) > 3 * error


def test_boundary_term_leaves_the_image_unchanged():
    """Zero in value: without shadows (whose edges are still blended by pixel pairs) the
    image is the plain one, bit for bit."""
    scene = _scene("overlap", np.zeros(3), LIT)
    with md.no_grad():
        plain = render(scene, reuse_visibility=False, shadows=False).data
    scene.objects[0].vertices.requires_grad = True
    image, info = render(scene, antialias="boundary", shadows=False, return_info=True)
    np.testing.assert_array_equal(image.data, plain)
    assert info.pairs is None  # no silhouette pairs were blended: the integral took them


def test_pixel_pieces_cover_a_segment_once():
    """A segment cut at pixel borders: the pieces' lengths add up to its length inside
    the image, each piece lies in the pixel it names, and parts outside are dropped."""
    rng = np.random.default_rng(3)
    p0 = rng.uniform(-3.0, 11.0, (200, 2))
    p1 = rng.uniform(-3.0, 11.0, (200, 2))
    segment, start, end, pixel = pixel_pieces(p0, p1, 8, 6)
    mid = p0[segment] + ((start + end) / 2)[:, None] * (p1 - p0)[segment]
    assert np.all(np.floor(mid[:, 1]) * 8 + np.floor(mid[:, 0]) == pixel)
    for s in range(0, 200, 17):  # against fine sampling of the segment
        t = (np.arange(200_000) + 0.5) / 200_000
        pts = p0[s] + t[:, None] * (p1[s] - p0[s])
        inside = (pts[:, 0] >= 0) & (pts[:, 0] <= 8) & (pts[:, 1] >= 0) & (pts[:, 1] <= 6)
        assert np.sum(end[segment == s] - start[segment == s]) == pytest.approx(
            inside.mean(), abs=1e-4
        )


def test_antialias_refuses_an_unknown_method():
    with pytest.raises(ValueError, match='antialias must be True, False, "pairs" or "boundary"'):
        render(_scene("triangle", np.zeros(3), FLAT), antialias="exact")
