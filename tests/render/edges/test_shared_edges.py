"""Edges that two meshes share (a multi-material file's seams) are counted once by the
boundary integral (``render.trace.seams``), checked against what it estimates: finite
differences of supersampled, box-filtered renders (``render.inverse.reference``, as in
tests/render/edges/test_boundary.py).

Before the seams were matched across meshes, each mesh counted the edge with the jump
from its own face to what lies beyond it: measured on these scenes, 15 % off on x for two
quads under one ``Transform`` and twice the truth for two coincident meshes.
"""

from __future__ import annotations

import numpy as np
import pytest

import minidiff as md
from render import Camera, Material, Mesh, PointLight, Scene, Transform
from render.inverse.reference import window_difference, window_mean_gradient
from render.trace.seams import shared_edges
from render.trace.topology import mesh_edges

SIZE = 24
RED, GREEN = Material(albedo=(0.8, 0.1, 0.1)), Material(albedo=(0.1, 0.8, 0.2))
QUAD = np.array([[0, 1, 2], [0, 2, 3]])
GROUND = Mesh(
    np.array([[-4, -1.5, -4], [4, -1.5, -4], [4, -1.5, 4], [-4, -1.5, 4.0]]),
    QUAD[:, ::-1],
    Material(albedo=(0.6, 0.6, 0.6)),
)


def _halves(folded: bool) -> tuple[np.ndarray, np.ndarray]:
    """Two unit quads side by side, meeting along x = 0 (the right one folded back)."""
    left = np.array([[-1.0, -0.7, 0], [0, -0.7, 0], [0, 0.7, 0], [-1, 0.7, 0]])
    right = np.array([[0, -0.7, 0], [1.0, -0.7, 0], [1, 0.7, 0], [0, 0.7, 0]])
    if folded:
        right[[1, 2], 2] = 0.6
    return left, right


def _scene(how: str, folded: bool, same: bool, ground: bool, t: np.ndarray) -> Scene:
    """The two halves as two meshes, both moved by the leaf tensor ``scene.moved`` (its
    value ``t``): under one ``Transform``, as two vertex tensors, as one vertex tensor the
    two meshes index ("welded": the seam's vertices are the same ids), or one half twice
    (two coincident meshes)."""
    left, right = _halves(folded)
    moved = md.tensor(np.array(t, float), requires_grad=True)
    second = RED if same else GREEN
    if how == "transform":
        place = Transform(translation=moved)
        objects = [
            Mesh(left, QUAD, RED, transform=place),
            Mesh(right, QUAD, second, transform=place),
        ]
    elif how == "separate":
        objects = [
            Mesh(md.tensor(left) + moved, QUAD, RED),
            Mesh(md.tensor(right) + moved, QUAD, second),
        ]
    elif how == "welded":
        vertices = md.tensor(np.concatenate([left, right])) + moved
        objects = [Mesh(vertices, QUAD, RED), Mesh(vertices, QUAD + 4, second)]
    elif how == "seam":  # moved: the seam's two vertices alone (both meshes index them)
        vertices = md.tensor(np.concatenate([left, right[[1, 2]]]))
        vertices = vertices + md.reshape(moved, (1, 3)) * np.array([0, 1, 1, 0, 0, 0.0])[:, None]
        objects = [Mesh(vertices, QUAD, RED), Mesh(vertices, [[1, 4, 5], [1, 5, 2]], second)]
    else:  # coincident
        objects = [
            Mesh(md.tensor(left) + moved, QUAD, RED),
            Mesh(md.tensor(left) + moved, QUAD, RED),
        ]
    camera = Camera(position=(0.3, 0.4, 3.0), look_at=(0, 0, 0), width=SIZE, height=SIZE)
    scene = Scene(
        objects + ([GROUND] if ground else []), [PointLight((1.0, 4.0, 2.0), 40.0)], camera
    )
    scene.moved = moved
    return scene


@pytest.mark.parametrize(
    "how, folded, same, ground",
    [
        ("transform", False, False, False),  # the case: one Transform, red | green
        ("separate", True, False, True),  # unwelded, folded, casting a shadow on the ground
        ("welded", True, True, True),  # one vertex tensor, one material
        ("seam", False, False, False),  # only the shared edge moves
        ("coincident", False, True, True),  # two copies of one mesh
    ],
)
def test_a_shared_edge_is_counted_once(how, folded, same, ground):
    weights = np.random.default_rng(1).uniform(0.0, 1.0, (SIZE, SIZE, 3))
    truth, ours = [], []
    for axis in range(3):
        direction = np.eye(3)[axis]

        def make(s, direction=direction):
            scene = _scene(how, folded, same, ground, s * direction)
            return scene, scene.moved, direction

        truth.append(window_difference(make, weights, 0.02, 256))
        ours.append(window_mean_gradient(make, weights, 0.02, "boundary", 8))
    error = np.linalg.norm(np.subtract(ours, truth)) / np.linalg.norm(truth)
    assert error < 0.05, (ours, truth)


def test_shared_edges_match_rows_across_meshes_by_position():
    """The seam's row is kept by the first mesh, which gains the second's faces on it (as
    global primitive ids, with their third corners); the second drops its copy; a lone
    mesh, or meshes that share no edge, need no table."""
    scene = _scene("separate", True, False, True, np.zeros(3))
    topology = {
        k: mesh_edges(np.asarray(m.vertices.data), m.faces) for k, m in enumerate(scene.meshes)
    }
    shared = shared_edges(scene, topology)
    first, second, ground = shared
    seam = np.flatnonzero(np.any(first.faces >= 0, axis=1))
    assert len(seam) == 1 and first.owned.all() and ground.owned.all()
    table = topology[0].table
    assert {int(table.i[seam[0]]), int(table.j[seam[0]])} == {1, 2}
    assert first.faces[seam[0], 0] in (2, 3)  # a face of the second mesh: ids 2 and 3
    np.testing.assert_array_equal(first.thirds[seam[0], 0], [1.0, 0.7, 0.6])
    assert (~second.owned).sum() == 1 and not np.any(second.faces >= 0)
    alone = Scene([scene.meshes[0], GROUND], scene.lights, scene.camera)
    assert shared_edges(alone, {0: topology[0], 1: topology[2]}) is None
