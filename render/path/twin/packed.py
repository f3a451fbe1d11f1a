"""A scene as the compiled path tracer reads it (``render.path.twin.kernel``): plain arrays.

``pack`` reads a ``PathSampler``'s world once: its primitives and BVH, emitters and lobe
probabilities (the sampler's own), and per object its material, smooth normals, UVs and
textures, concatenated into flat float64 / int64 arrays that Numba code indexes by object
or primitive id.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from render.path.sample.tables import compiles
from render.path.sample.tracer import PathSampler
from render.scene.scene import Mesh, Scene
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
    """The plain arrays of ``sampler``'s scene (its primitives, BVH, emitters, lobes), and
    per object its material, smooth normals, UVs and textures, concatenated."""
    world = sampler.scene
    objects = sampler.objects
    n_obj = len(objects)
    triangles, centers, radii = sampler.primitives
    counts = np.diff(np.append(sampler.first, sampler.n_triangles + len(centers)))
    prim_object = np.repeat(np.arange(n_obj, dtype=np.int64), counts)
    albedo, specular, reflectance, emission = (np.zeros((n_obj, 3)) for _ in range(4))
    shininess = np.zeros(n_obj)
    # Whether the Blinn-Phong lobe is computed: a non-zero or differentiated specular
    # (render.path.gradient.transport computes it then; its derivative needs it when zero).
    lobe_on = np.zeros(n_obj, np.bool_)
    maps = np.full((n_obj, 2, 3), -1, np.int64)  # (offset, height, width) of map_Kd, map_Ks
    texels, n_texels = [], 0
    smooth = np.zeros(n_obj, np.bool_)
    corners = np.zeros((sampler.n_triangles, 3), np.int64)  # global vertex ids
    uvs, n_vertices = [], 0
    # The vertex normals of every mesh (a smooth mesh's own; a flat one's are never read).
    tables = sampler.tables
    normals = np.zeros((0, 3)) if tables.normals is None else tables.normals.data
    for o, obj in enumerate(objects):
        m = obj.material
        albedo[o] = np.broadcast_to(m.albedo.data, (3,))
        specular[o] = np.broadcast_to(m.specular.data, (3,))
        reflectance[o] = np.broadcast_to(m.reflectance.data, (3,))
        emission[o] = np.broadcast_to(m.emission.data, (3,))
        shininess[o] = float(m.shininess.data)
        lobe_on[o] = m.specular.is_differentiated() or bool(np.any(m.specular.data))
        for k, texture in enumerate((m.texture, m.specular_texture)):
            if texture is not None:
                h, w = texture.shape[:2]
                maps[o, k] = (n_texels, h, w)
                texels.append(texture.data.reshape(-1, 3))
                n_texels += h * w
        if isinstance(obj, Mesh):
            first = sampler.first[o]
            corners[first : first + obj.num_faces] = obj.faces + n_vertices
            count = obj.vertices.shape[0]
            if obj.smooth:
                smooth[o] = True
            uvs.append(obj.uvs.data if obj.uvs is not None else np.zeros((count, 2)))
            n_vertices += count
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
        triangles, centers, radii, prim_object,
        albedo, specular, shininess, reflectance, emission,
        sampler.lobes.probability, sampler.lobes.reflectance, maps,
        np.concatenate(texels) if texels else np.zeros((0, 3)), smooth, corners,
        normals,
        np.concatenate(uvs) if uvs else np.zeros((0, 2)),
        e.prims, e.cdf, e.probability, e.area, e.row_of,
        light_kind, light_vec, light_strength, light_color,
        np.ascontiguousarray(forward), np.ascontiguousarray(right), np.ascontiguousarray(up),
        np.ascontiguousarray(eye), background, offset, sampler.n_triangles, lobe_on,
    )  # fmt: skip
    camera = world.camera
    return Packed(sampler.accelerator.flat_tree(), arrays, camera.width, camera.height,
                  len(lights))  # fmt: skip
