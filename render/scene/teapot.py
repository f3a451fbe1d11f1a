"""The Newell (Utah) teapot and the paper's reference scene.

The teapot is Newell's 32 bicubic Bezier patches (public-domain data shipped in
``render/scene/data/newell_teapot.json``), tessellated exactly as described in
``docs/paper_scene.md`` so that every part of the project renders the same triangles:

* each patch is evaluated with cubic Bernstein polynomials on a regular
  (nu + 1) x (nv + 1) vertex grid ``P[i, j]`` at ``u_i = i / nu``, ``v_j = j / nv``, where u
  runs along the first index of the row-major 4x4 control grid and v along the second;
* cell (i, j) becomes the triangles ``(P[i,j], P[i+1,j+1], P[i+1,j])`` and
  ``(P[i,j], P[i,j+1], P[i+1,j+1])``; with this winding the geometric normal
  ``(b - a) x (c - a)`` points out of the body;
* vertices are *not* welded across patch borders and degenerate triangles (where a patch
  edge collapses to a point, at the lid knob and the bottom centre) are kept;
* a control point (x, y, z) (z up) is placed at ``0.5 * (x, z, -y) + (0, -0.5, 0)``
  (y up, roughly centred on the origin).

The default nu=4, nv=6 gives 32 * 4 * 6 * 2 = 1,536 triangles and 32 * 5 * 7 = 1,120
vertices.
"""

from __future__ import annotations

import json
from functools import lru_cache
from pathlib import Path

import numpy as np

from render.scene.scene import ArrayLike, Camera, Material, Mesh, PointLight, Scene

__all__ = ["teapot_geometry", "teapot", "teapot_atlas", "paper_scene", "PAPER_ALBEDO"]

_DATA = Path(__file__).parent / "data" / "newell_teapot.json"

#: Where the teapot stands: its lowest point (the bottom patches) is at y = -0.5.
GROUND_Y = -0.5

#: The paper's Lambertian teapot albedo (linear RGB).
PAPER_ALBEDO = (0.7, 0.3, 0.3)


@lru_cache(maxsize=1)
def _control_points() -> np.ndarray:
    """(32, 4, 4, 3) control points ``[patch, row, column, xyz]`` in the file's z-up frame."""
    with open(_DATA, encoding="utf-8") as f:
        data = json.load(f)
    vertices = np.asarray(data["vertices"], dtype=np.float64)  # (306, 3)
    patches = np.asarray(data["patches"], dtype=np.int64)  # (32, 16), row-major 4x4
    points = vertices[patches].reshape(len(patches), 4, 4, 3)
    points.flags.writeable = False  # cached: nobody may modify it
    return points


def _bernstein(n: int) -> np.ndarray:
    """(n + 1, 4) cubic Bernstein basis at t = 0, 1/n, ..., 1: ``B[i, k] = B_k(i / n)``."""
    return _bernstein_at(np.linspace(0.0, 1.0, n + 1))


def _bernstein_at(t: np.ndarray) -> np.ndarray:
    """(len(t), 4) cubic Bernstein basis at the parameters t: ``B[i, k] = B_k(t[i])``."""
    t = np.asarray(t, dtype=np.float64)[:, None]
    k = np.arange(4)
    binomial = np.array([1.0, 3.0, 3.0, 1.0])
    return binomial * t**k * (1.0 - t) ** (3 - k)


def _to_world(points: np.ndarray) -> np.ndarray:
    """(n, 3) points of the z-up file frame -> the y-up world frame, scaled and lowered to
    sit around the origin."""
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    return 0.5 * np.stack([x, z, -y], axis=1) + np.array([0.0, -0.5, 0.0])


def _grid_faces(nu: int, nv: int) -> np.ndarray:
    """(nu * nv * 2, 3) triangles of one (nu + 1) x (nv + 1) vertex grid, cell-major order."""
    index = np.arange((nu + 1) * (nv + 1)).reshape(nu + 1, nv + 1)
    p00 = index[:-1, :-1].ravel()  # P[i, j]
    p10 = index[1:, :-1].ravel()  # P[i+1, j]
    p01 = index[:-1, 1:].ravel()  # P[i, j+1]
    p11 = index[1:, 1:].ravel()  # P[i+1, j+1]
    first = np.stack([p00, p11, p10], axis=1)
    second = np.stack([p00, p01, p11], axis=1)
    # Interleave so the two triangles of a cell are consecutive: cell c -> rows 2c, 2c+1.
    return np.stack([first, second], axis=1).reshape(-1, 3)


def teapot_geometry(nu: int = 4, nv: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """Tessellate the Newell teapot into triangles (see the module docstring).

    Args:
        nu: cells per patch along u (the first control-grid index), >= 1.
        nv: cells per patch along v (the second control-grid index), >= 1.

    Returns:
        vertices: (32 * (nu + 1) * (nv + 1), 3) float64 positions, world frame (y up),
            patch-major then row-major ``P[i, j]``.
        faces: (32 * nu * nv * 2, 3) int64 vertex indices, patch-major, then cell (i, j)
            row-major, then the two triangles of the cell in the order given above.
    """
    for name, n in (("nu", nu), ("nv", nv)):
        if isinstance(n, bool) or not isinstance(n, int | np.integer):
            raise TypeError(f"teapot_geometry: {name} must be an int, got {type(n).__name__}")
        if n < 1:
            raise ValueError(f"teapot_geometry: {name} must be >= 1, got {n}")
    nu, nv = int(nu), int(nv)

    control = _control_points()  # (P, 4, 4, 3)
    bu, bv = _bernstein(nu), _bernstein(nv)  # (nu+1, 4), (nv+1, 4)
    # P[p, i, j] = sum_a sum_b Bu[i, a] Bv[j, b] C[p, a, b]: all patches at once.
    grid = np.einsum("ia,jb,pabk->pijk", bu, bv, control, optimize=True)
    n_patches = grid.shape[0]
    vertices = _to_world(grid.reshape(-1, 3))

    per_patch = (nu + 1) * (nv + 1)
    offsets = np.arange(n_patches, dtype=np.int64)[:, None, None] * per_patch
    faces = (_grid_faces(nu, nv)[None, :, :] + offsets).reshape(-1, 3)
    return np.ascontiguousarray(vertices), faces.astype(np.int64)


#: The texture atlas of ``teapot_atlas``: the 32 patches in 4 rows of 8 tiles.
ATLAS_TILES = (4, 8)


def teapot_atlas(tile: int = 16, nu: int = 4, nv: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """A texture atlas for the teapot: every Bezier patch gets its own ``tile`` x ``tile``
    block of an (4 tile, 8 tile, 3) texture, patch p in block row p // 8, column p % 8.

    Returns:
        uvs: (V, 2) texture coordinates for the vertices of ``teapot_geometry(nu, nv)``:
            the patch parameters (u, v) in [0, 1]^2 mapped linearly onto the block's texel
            centres, u along the columns, v down the rows, so that bilinear lookups stay
            inside the block (no colour bleeds from a neighbouring patch).
        points: (4 tile, 8 tile, 3) the world position on the exact Bezier surface of every
            texel centre: a function of 3-D position (a neural field, a procedural pattern)
            evaluated here is a texture the renderer samples at the hits.
    """
    if isinstance(tile, bool) or not isinstance(tile, int | np.integer) or tile < 2:
        raise ValueError(f"teapot_atlas: tile must be an int >= 2, got {tile!r}")
    vertices, _ = teapot_geometry(nu, nv)  # checks nu and nv
    rows, columns = ATLAS_TILES
    height, width = rows * tile, columns * tile
    patch = np.arange(32)
    ty, tx = patch // columns, patch % columns
    u = np.linspace(0.0, 1.0, nu + 1)
    v = np.linspace(0.0, 1.0, nv + 1)
    # Continuous texel coordinates (centres at integers, ``render.shade.lighting``).
    x = tx[:, None, None] * tile + u[None, :, None] * (tile - 1) + 0.0 * v[None, None, :]
    y = ty[:, None, None] * tile + v[None, None, :] * (tile - 1) + 0.0 * u[None, :, None]
    uvs = np.stack([(x + 0.5) / width, 1.0 - (y + 0.5) / height], axis=-1).reshape(-1, 2)
    assert len(uvs) == len(vertices)

    t = _bernstein_at(np.arange(tile) / (tile - 1))  # texel centres of a block: (tile, 4)
    grid = np.einsum("ia,jb,pabk->pijk", t, t, _control_points(), optimize=True)  # [p, u, v]
    points = np.empty((height, width, 3))
    for p in range(32):  # block rows follow v, block columns u
        block = _to_world(grid[p].reshape(-1, 3)).reshape(tile, tile, 3)
        points[ty[p] * tile : (ty[p] + 1) * tile, tx[p] * tile : (tx[p] + 1) * tile] = (
            block.transpose(1, 0, 2)
        )
    return uvs, points


def teapot(nu: int = 4, nv: int = 6, material: Material | None = None) -> Mesh:
    """The tessellated Newell teapot as a flat-shaded ``Mesh``.

    ``material`` defaults to the paper's Lambertian material, albedo (0.7, 0.3, 0.3), no
    specular and no ambient term.
    """
    vertices, faces = teapot_geometry(nu, nv)
    if material is None:
        material = Material(albedo=PAPER_ALBEDO)
    return Mesh(vertices, faces, material)


def paper_scene(
    width: int = 512,
    height: int = 512,
    light_position: ArrayLike = (2, 5, 3),
    light_intensity: ArrayLike = 100.0,
    albedo: ArrayLike = PAPER_ALBEDO,
    camera_position: ArrayLike = (3, 2, 5),
    look_at: ArrayLike = (0, 0, 0),
    nu: int = 4,
    nv: int = 6,
    ground: bool = False,
    ground_material: Material | None = None,
) -> Scene:
    """The reference scene of ``docs/paper_scene.md``: the teapot lit by one white point light.

    Camera: pinhole at ``camera_position`` looking at ``look_at``, up (0, 1, 0), a 50 mm
    lens on a 36 mm sensor (horizontal fov 39.5978 degrees), ``width`` x ``height`` pixels.
    Light: point light at ``light_position`` with radiant intensity ``light_intensity``.
    Material: Lambertian ``albedo``, no specular, no ambient. Black background.

    Continuous arguments may be ``minidiff.Tensor`` s (e.g. ``requires_grad=True`` for the
    inverse-rendering experiments); the scene keeps those very objects.

    ``ground=True`` stands the teapot on a 6 x 6 grey (albedo 0.6) square at its bottom,
    y = -0.5, so that it casts a shadow a camera can see (not part of the paper's scene);
    ``ground_material`` replaces its material (e.g. ``Material(..., reflectance=0.8)``: a
    mirror floor).
    """
    camera = Camera.from_focal_length(
        50.0, 36.0, position=camera_position, look_at=look_at, up=(0, 1, 0),
        width=width, height=height,
    )  # fmt: skip
    light = PointLight(light_position, light_intensity)
    mesh = teapot(nu, nv, material=Material(albedo=albedo))
    objects = [mesh]
    if ground:
        s, y = 3.0, GROUND_Y
        square = np.array([(-s, y, s), (s, y, s), (s, y, -s), (-s, y, -s)], dtype=np.float64)
        material = ground_material if ground_material is not None else Material((0.6,) * 3)
        objects.append(Mesh(square, [[0, 1, 2], [0, 2, 3]], material))
    return Scene(objects, [light], camera, background=(0, 0, 0))
