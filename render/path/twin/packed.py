"""A scene as the compiled path tracer reads it (``render.path.twin.kernel``): plain arrays.

``pack`` reads a ``PathSampler`` once: its primitives and BVH, emitters and lobe
probabilities (the sampler's own), and its ``Tables`` (``render.path.sample.tables``, the
one packing of the scene's objects that the compiled gradient and choices read too): per
object its material, smoothness and textures, every mesh's faces, vertex normals and UVs,
laid out as flat float64 / int64 arrays that Numba code indexes by object or primitive id.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from render.path.sample.tables import compiles
from render.path.sample.tracer import PathSampler
from render.scene.scene import Scene
from render.shade.lighting import term_present
from render.trace.intersect import FlatBVH
from render.trace.visibility import SHADOW_EPSILON, SHADOW_ULPS


def applies(world: Scene) -> bool:
    """Whether the kernel can trace ``world`` (``tables.compiles``)."""
    return compiles(world)


@dataclass
class Packed:
    """A scene as the kernel reads it: its BVH and plain float64 / int64 arrays (``pack``)."""

    bvh: FlatBVH
    arrays: tuple
    width: int
    height: int
    n_lights: int


def pack(sampler: PathSampler) -> Packed:
    """The plain arrays of ``sampler``'s scene: its primitives, BVH, emitters and lobes,
    and what the compiled paths read too, from the sampler's own ``Tables`` (per object
    its material, smoothness and textures; every mesh's faces, vertex normals and UVs), in
    the layout Numba code indexes by object or primitive id."""
    world = sampler.scene
    tables = sampler.tables
    triangles, centers, radii = sampler.primitives
    albedo, specular, shininess, emission, reflectance = (
        np.ascontiguousarray(m.data, np.float64) for m in tables.materials
    )
    # Whether the Blinn-Phong lobe is computed: a non-zero or differentiated specular
    # (render.path.gradient.transport computes it then; its derivative needs it when zero).
    lobe_on = np.array([term_present(obj.material.specular) for obj in sampler.objects], bool)
    maps, texels = _texture_maps(tables)
    n_vertices = 0 if tables.vertices is None else len(tables.vertices.data)
    corners = np.zeros((0, 3), np.int64) if tables.faces is None else tables.faces
    normals = np.zeros((0, 3)) if tables.normals is None else tables.normals.data
    uvs = np.zeros((n_vertices, 2)) if tables.uvs is None else tables.uvs.data
    e = sampler.emitters
    lights = world.lights
    packs = [light.shading_pack() for light in lights]
    light_kind = np.array([p[0] for p in packs], np.int64)
    light_vec = np.array([p[1] for p in packs], np.float64).reshape(-1, 3)
    light_strength = np.array([p[2] for p in packs], np.float64).reshape(-1)
    light_color = np.array([light.color.data for light in lights], np.float64).reshape(-1, 3)
    forward, right, up, eye = sampler.frame
    # The shadow rays' offset (render.trace.visibility.shadow_offset), from the largest
    # coordinate any point or point light can have.
    extent = np.abs(centers).max(initial=0.0) + radii.max(initial=0.0)
    magnitude = max(
        [np.abs(triangles).max(initial=0.0), extent]
        + [float(np.abs(light_vec[j]).max()) for j in range(len(lights)) if light_kind[j] == 0]
    )
    offset = max(SHADOW_EPSILON * sampler.size, SHADOW_ULPS * np.finfo(np.float64).eps * magnitude)
    background = np.broadcast_to(world.background.data, (3,)).astype(np.float64)
    arrays = (
        triangles, centers, radii, tables.owner.astype(np.int64),
        albedo, specular, shininess, reflectance, emission,
        sampler.lobes.probability, sampler.lobes.reflectance, maps, texels,
        tables.smooth.astype(np.bool_), corners, normals, uvs,
        e.prims, e.cdf, e.probability, e.area, e.row_of,
        light_kind, light_vec, light_strength, light_color,
        np.ascontiguousarray(forward), np.ascontiguousarray(right), np.ascontiguousarray(up),
        np.ascontiguousarray(eye), background, offset, sampler.n_triangles, lobe_on,
    )  # fmt: skip
    camera = world.camera
    return Packed(sampler.accelerator.flat_tree(), arrays, camera.width, camera.height,
                  len(lights))  # fmt: skip


def _texture_maps(tables) -> tuple[np.ndarray, np.ndarray]:
    """The textures of ``tables`` (``Tables.textures``: per kind, albedo's then the
    specular's, the texels and each object's first row, width and height) as the kernel
    reads them: maps (O, 2, 3) int64, per object and kind (first row, height, width) in
    ``texels`` (T, 3), the kinds' texels one after the other (-1: no texture)."""
    n_obj = len(tables.smooth)
    maps = np.full((n_obj, 2, 3), -1, np.int64)
    parts, n_texels = [], 0
    for kind, table in enumerate(tables.textures):
        if table is None:
            continue
        rows, first, width, height, has = table
        for o in np.flatnonzero(has):
            maps[o, kind] = (n_texels + int(first[o]), int(height[o]), int(width[o]))
        parts.append(rows.data)
        n_texels += len(rows.data)
    return maps, np.concatenate(parts) if parts else np.zeros((0, 3))
