"""Edits of a mesh that keep its surface but change how it is written down: the ways mesh
files differ from the tidy meshes a renderer is usually tested on.

* ``with_t_junctions``: faces split at a point of an edge they share with another face,
  which keeps the whole edge (a quad split on one side only: a T-junction);
* ``in_meshes``: the faces dealt to several meshes (a file with several materials, read as
  one mesh per material), which then meet along seams;
* ``moved_apart``: each position moved a little, in a random direction (parts written with
  a few digits, or transformed apart: their seams come apart);
* ``through_float32``: the vertices rounded to float32 and back (a part stored in float32);
* ``wound_at_random``: faces flipped at random (scans and soups are wound inconsistently).

The boundary terms must give the same gradients on all of them as on the tidy mesh
(``tests/render/edges/test_t_junctions.py``; ``benchmarks/seams.py`` measures by how much
they do; lesson 11 shows it). ``light_and_translation`` is the comparison they share: the
gradients of one weighting of a render of the meshes over a floor (``floor_scene``).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

import minidiff as md
from render.scene.cornell import grid_quad
from render.scene.lights import PointLight
from render.scene.materials import Material
from render.scene.scene import Camera, Mesh, Scene


def with_t_junctions(mesh: Mesh, picks: list[tuple[int, float]]) -> Mesh:
    """``mesh`` with, for each (face, t) of ``picks``, that face split in two at the point
    t along its first edge that another face shares (by position): the other face keeps
    the whole edge, a T-junction. Faces are picked once each, and only if still whole."""
    v, f = np.asarray(mesh.vertices.data, float), [list(x) for x in np.asarray(mesh.faces)]
    vertices = list(v)
    done = set()
    for face, t in picks:
        face %= len(f)
        if face in done or len(f[face]) != 3:
            continue
        tri = f[face]
        for k in range(3):
            a, b, c = tri[k], tri[(k + 1) % 3], tri[(k + 2) % 3]
            others = [
                g
                for g, o in enumerate(f)
                if g != face
                and g not in done
                and sum(any(np.allclose(vertices[x], vertices[y]) for y in o) for x in (a, b)) == 2
            ]
            if others:
                vertices.append(vertices[a] + t * (vertices[b] - vertices[a]))
                m = len(vertices) - 1
                f[face] = [a, m, c]
                f.append([m, b, c])
                done.update({face, len(f) - 1, *others})
                break
    return Mesh(np.array(vertices), np.array(f), mesh.material)


def in_meshes(mesh: Mesh, owner: list[int], between: bool = False) -> list[Mesh]:
    """``mesh``'s faces dealt to meshes by ``owner`` (one index per face; each mesh keeps
    every vertex), with, if ``between``, a small triangle far off as a mesh of its own
    between the first and the others (so that meshes that meet are not neighbours in a
    scene's meshes)."""
    v, f = np.asarray(mesh.vertices.data), np.asarray(mesh.faces)
    owner = np.asarray(owner)
    out = [Mesh(v, f[owner == k], mesh.material) for k in np.unique(owner)]
    if between:
        far = np.array([[2.0, 0.1, -1.0], [2.2, 0.1, -1.0], [2.0, 0.3, -1.0]])
        out.insert(1, Mesh(far, np.array([[0, 1, 2]]), mesh.material))
    return out


def moved_apart(mesh: Mesh, distance: float, rng: np.random.Generator) -> Mesh:
    """``mesh`` with each of its positions moved by up to ``distance`` (uniformly), in a
    random direction: its vertices at one position move as one (a file writes a position
    once), so it stays whole, and its seams with other meshes come apart."""
    v = np.asarray(mesh.vertices.data, np.float64)
    _, where = np.unique(v, axis=0, return_inverse=True)
    where = where.ravel()
    away = rng.normal(size=(where.max() + 1 if len(where) else 0, 3))
    away *= (
        distance * rng.uniform(0, 1, (len(away), 1)) / np.linalg.norm(away, axis=1, keepdims=True)
    )
    return Mesh(v + away[where], mesh.faces, mesh.material)


def through_float32(mesh: Mesh) -> Mesh:
    """``mesh`` with its vertices rounded to float32 and back."""
    rounded = np.asarray(mesh.vertices.data).astype(np.float32).astype(np.float64)
    return Mesh(rounded, mesh.faces, mesh.material)


def wound_at_random(mesh: Mesh, rng: np.random.Generator, share: float = 0.5) -> Mesh:
    """``mesh`` with about ``share`` of its faces, drawn by ``rng``, wound the other way."""
    faces = np.asarray(mesh.faces).copy()
    flip = rng.random(len(faces)) < share
    faces[flip] = faces[flip][:, ::-1]
    return Mesh(np.asarray(mesh.vertices.data), faces, mesh.material)


def floor_scene(meshes: list[Mesh], size: int = 32) -> Scene:
    """``meshes`` over a grey 3 x 3 floor at y = 0 under a point light, seen from above at
    ``size`` x ``size`` (a box about (0.1, 0.6, 0) of size 0.3 fills a third of it)."""
    floor = Mesh(*grid_quad((0, 0, 0), (1.5, 0, 0), (0, 0, -1.5)), Material((0.6, 0.6, 0.6)))
    light = PointLight((0.3, 1.6, 0.2), 3.0)
    camera = Camera((0.6, 1.3, 1.1), (0.05, 0.3, 0.0), (0, 1, 0), 45.0, size, size)
    return Scene([floor, *meshes], [light], camera)


def light_and_translation(
    meshes: list[Mesh], image_of: Callable[[Scene], md.Tensor], size: int = 32
) -> np.ndarray:
    """(6,): the light's position gradient and the meshes' translation gradient (their
    vertices' gradients summed) of a fixed random weighting of ``image_of(scene)`` (H, W,
    3), the meshes over the floor (``floor_scene``). The meshes' gradients are reset first
    (a mesh may be compared more than once)."""
    scene = floor_scene(meshes, size)
    light = scene.lights[0].position
    light.requires_grad = True
    for mesh in meshes:
        mesh.vertices.requires_grad, mesh.vertices.grad = True, None
    weights = np.random.default_rng(7).uniform(0, 1, (size, size, 3))
    md.sum(image_of(scene) * weights).backward()
    return np.r_[light.grad, sum(m.vertices.grad.sum(axis=0) for m in meshes)]
