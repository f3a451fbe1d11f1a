"""Which parameters move which curves: a curve kind's boundary term carries a derivative
only where a parameter its edge function reads is differentiated
(``render.edges.boundary.curves.CurveKind.moves``); the path integrator's secondary term
asks the same of each sample. Tested by each parameter's gradient alone and with every
other (``tests/render/edges/test_boundary.py``, ``tests/render/path/test_secondary.py``).
"""

from __future__ import annotations

import numpy as np

import minidiff as md
from render.scene.scene import Scene


def moving(*tensors: md.Tensor | None) -> bool:
    """Whether a derivative flows through any of ``tensors`` (None: none), in either mode
    (``Tensor.is_differentiated``)."""
    return any(t is not None and t.is_differentiated() for t in tensors)


def camera_moves(scene: Scene) -> bool:
    """Whether the camera's position, orientation or field of view is differentiated: then
    every curve moves in the image."""
    camera = scene.camera
    return moving(*(getattr(camera, field.name) for field in camera.FIELDS))


def objects_move(scene: Scene) -> np.ndarray:
    """(M + S,) bool: whether each mesh's vertices (in world space: a transform's
    parameters reach them too), then each sphere's centre or radius, are differentiated
    (the objects in the order of ``render.trace.primitives.scene_primitives``)."""
    meshes = [moving(mesh.vertices) for mesh in scene.meshes]
    spheres = [moving(sphere.center, sphere.radius) for sphere in scene.spheres]
    return np.array(meshes + spheres, bool)


def meshes_move(scene: Scene, meshes=None) -> bool:
    """Whether the vertices of ``scene.meshes[k]`` for k in ``meshes`` (default: all) are
    differentiated (``objects_move``)."""
    flags = objects_move(scene)[: len(scene.meshes)]
    return bool(flags.any() if meshes is None else flags[list(meshes)].any())


def spheres_move(scene: Scene, spheres=None) -> bool:
    """Whether the centre or radius of ``scene.spheres[k]`` for k in ``spheres`` (default:
    all) is differentiated (``objects_move``)."""
    flags = objects_move(scene)[len(scene.meshes) :]
    return bool(flags.any() if spheres is None else flags[list(spheres)].any())


def geometry_moves(scene: Scene) -> bool:
    """Whether anything that places a curve is differentiated: the camera, a mesh's
    vertices, a sphere, where a light is (``Light.placement``; its shadows' borders). When
    not, every kind's boundary term is zero in derivative (``CurveKind.moves``), and the
    renderer looks for no curve."""
    lights = (t for light in scene.lights for t in light.placement())
    return camera_moves(scene) or bool(objects_move(scene).any()) or moving(*lights)
