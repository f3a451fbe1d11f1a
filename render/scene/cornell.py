"""A Cornell-box-like scene for the path integrator: a closed room lit by an area light.

The room is the cube [-1, 1]^3 without its front wall (the camera looks in through it): a
white floor, ceiling and back wall, a red left wall and a green right wall, an emissive
square just below the ceiling facing down, and (``blocks=True``) a tall white box and a
white sphere on the floor. Every wall is its own ``Mesh`` (its own material, so that an
experiment can differentiate one wall's albedo); ``subdivisions`` splits each wall into a
grid, so that a wall has interior vertices to move.
"""

from __future__ import annotations

import numpy as np

from render.scene.scene import Camera, Material, Mesh, Scene, Sphere, Transform

WHITE, RED, GREEN = (0.73, 0.73, 0.73), (0.63, 0.065, 0.05), (0.14, 0.45, 0.091)
#: The light's radiance (per channel) and half side, and how far below the ceiling it hangs.
LIGHT_RADIANCE = (17.0, 12.0, 4.0)
LIGHT_HALF_SIDE = 0.25
LIGHT_DROP = 0.01


def grid_quad(center, u, v, n: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """An n x n grid of squares over the parallelogram center +- u +- v: vertices
    ((n + 1)^2, 3) and faces (2 n^2, 3), wound so that every normal (b - a) x (c - a)
    points along u x v."""
    s = np.linspace(-1.0, 1.0, n + 1)
    a, b = np.meshgrid(s, s, indexing="ij")  # a along u, b along v
    vertices = np.asarray(center, float) + a.reshape(-1, 1) * u + b.reshape(-1, 1) * v
    faces = []
    for i in range(n):
        for j in range(n):
            p0, p1 = i * (n + 1) + j, (i + 1) * (n + 1) + j  # p1: one step along u
            p2, p3 = p1 + 1, p0 + 1  # one step along v
            faces += [(p0, p1, p2), (p0, p2, p3)]
    return vertices, np.array(faces, np.int64)


def box_mesh(center, half, material: Material) -> Mesh:
    """An axis-aligned box (12 triangles, normals outward)."""
    c, h = np.asarray(center, float), np.asarray(half, float)
    x, y, z = np.eye(3) * h[:, None]
    # (centre, u, v) per side, u x v along the outward normal.
    sides = [(c + y, x, -z), (c - y, x, z), (c + x, y, z), (c - x, z, y), (c + z, x, y),
             (c - z, y, x)]  # fmt: skip
    vertices, faces = [], []
    for centre, u, v in sides:
        verts, tris = grid_quad(centre, u, v)
        faces.append(tris + 4 * len(vertices))
        vertices.append(verts)
    return Mesh(np.concatenate(vertices), np.concatenate(faces), material)


def cornell_box(
    width: int = 64,
    height: int = 64,
    blocks: bool = True,
    subdivisions: int = 1,
    light_radiance=LIGHT_RADIANCE,
) -> Scene:
    """The room (see the module docstring) seen from the front. Objects, in order: floor,
    ceiling, back wall, left wall (red), right wall (green), the light (a square with a
    ``Transform``, so that its position is a parameter), then with ``blocks`` the tall box
    and the sphere."""
    x, y, z = np.eye(3)

    def wall(center, u, v, albedo):
        vertices, faces = grid_quad(center, u, v, subdivisions)
        return Mesh(vertices, faces, Material(albedo))

    objects = [
        wall(-y, x, -z, WHITE),  # floor, facing up
        wall(y, x, z, WHITE),  # ceiling, facing down
        wall(-z, x, y, WHITE),  # back wall, facing the camera
        wall(-x, y, z, RED),  # left wall, facing right
        wall(x, z, y, GREEN),  # right wall, facing left
    ]
    side = LIGHT_HALF_SIDE
    vertices, faces = grid_quad((0.0, 1.0 - LIGHT_DROP, 0.0), side * x, side * z)  # faces down
    light = Material((0.0, 0.0, 0.0), emission=light_radiance)
    objects.append(Mesh(vertices, faces, light, transform=Transform()))
    if blocks:
        objects.append(box_mesh((-0.35, -0.4, -0.3), (0.25, 0.6, 0.25), Material(WHITE)))
        objects.append(Sphere((0.4, -0.65, 0.25), 0.35, Material(WHITE)))
    camera = Camera(
        position=(0.0, 0.0, 3.9), look_at=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), fov=39.0,
        width=width, height=height,
    )  # fmt: skip
    return Scene(objects, [], camera)
