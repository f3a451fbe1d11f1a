"""``render(scene)``: the pipeline, one step per module.

1. Visibility (``render.visibility``, plain arrays, constants on the tape): build the BVH
   over all primitives, trace one ray per pixel sample (which primitive does it hit?) and a
   shadow ray from every hit to every light (is the light visible?).
2. Surfaces (``render.geometry``, on the tape): for the rays that hit, *recompute* the hit
   point, normal and UV differentiably from the camera and the primitive, object by object.
3. Shading (``render.shading``, on the tape): lights and materials give each hit a colour.
4. Image: scatter the hit colours into their pixels, fill the misses with the background.

Gradients reach every continuous parameter through steps 2-4; step 1's decisions are
constants. With ``reuse_visibility=True`` (the default), step 1 and the surfaces of step 2
are reused from the previous render of the same scene when the values they depend on are
unchanged (``render.cache``), e.g. while only a material is optimised.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import minidiff as md
from render.cache import RenderCache, cache_for, surface_key
from render.camera import camera_frame, ray_directions
from render.geometry import Surface, mesh_surface, moves_surface, sphere_surface
from render.scene import Mesh, Scene
from render.shading import shade_mesh, shade_surface
from render.visibility import Visibility, primitive_ranges, trace_visibility

__all__ = ["render", "RenderInfo", "shade_mesh", "shade_surface"]


def render(
    scene: Scene,
    bvh: bool = True,
    shadows: bool = True,
    spp: int = 1,
    reuse_visibility: bool = True,
    return_info: bool = False,
) -> md.Tensor | tuple[md.Tensor, RenderInfo]:
    """Render ``scene`` to linear radiance, an (H, W, 3) ``minidiff.Tensor``.

    bvh: use the BVH (False: brute force over all primitives, same result, for ablations).
    shadows: trace shadow rays (False: every light reaches every hit point).
    spp: samples per pixel, a perfect square, on a fixed stratified pattern (deterministic,
        hence differentiable); the pixel value is their mean.
    reuse_visibility: reuse the previous render's visibility when geometry, camera and
        lights have the same values (see the module docstring).
    return_info: also return a ``RenderInfo`` with the discrete decisions.

    Every parameter of the scene that is a ``requires_grad`` tensor receives its gradient
    when the caller runs ``backward`` on a loss computed from the image.
    """
    if not isinstance(scene, Scene):
        raise TypeError(f"render: scene must be a render.Scene, got {type(scene).__name__}")
    scene.validate()
    cache = cache_for(scene, reuse_visibility)

    visibility = trace_visibility(scene, cache, bool(bvh), spp, bool(shadows))  # 1
    colour, ray_of_colour, texel = _shade_objects(scene, visibility, cache)  # 2 and 3
    image = _compose_image(scene, visibility, colour, ray_of_colour, spp)  # 4

    if not return_info:
        return image
    return image, RenderInfo.of(scene, visibility, texel, spp)


def working_dtype(scene: Scene) -> np.dtype:
    """float32 only if every parameter is float32 (constants such as pixel coordinates are
    cast to it, so that they do not promote the tape to float64)."""
    return np.result_type(*[t.dtype for t in scene.parameters()])


def _shade_objects(
    scene: Scene, visibility: Visibility, cache: RenderCache
) -> tuple[md.Tensor | None, np.ndarray, np.ndarray]:
    """Steps 2 and 3 for every object: the colours (k, 3) of all hit rays, object by object,
    the ray each colour belongs to (k,), and the texture cell of every ray (N,) (-1: none)."""
    primary, dtype = visibility.primary, working_dtype(scene)
    frame = camera_frame(scene.camera)
    eye = frame[3]
    coords = primary.coords.astype(dtype, copy=False)
    hit_prims = primary.prim_id[primary.hit_rays]

    texel = np.full(primary.prim_id.size, -1, dtype=np.int64)
    colours, rays = [], []
    for index, (obj, first, count) in enumerate(primitive_ranges(scene)):
        in_obj = np.flatnonzero((hit_prims >= first) & (hit_prims < first + count))
        if len(in_obj) == 0:
            continue

        def surface(obj=obj, first=first, in_obj=in_obj) -> Surface:
            directions = ray_directions(frame, coords[in_obj])
            if isinstance(obj, Mesh):
                return mesh_surface(obj, hit_prims[in_obj] - first, eye, directions)
            return sphere_surface(obj, eye, directions)

        hits = _reused_surface(scene, cache, visibility, index, obj, dtype, surface)
        obj_lit = [mask[in_obj].astype(dtype) for mask in visibility.lit]
        colour, texel[primary.hit_rays[in_obj]] = shade_surface(
            hits, obj.material, scene.lights, obj_lit
        )
        colours.append(colour)
        rays.append(primary.hit_rays[in_obj])
    if not colours:
        return None, np.zeros(0, np.int64), texel
    colour = colours[0] if len(colours) == 1 else md.concatenate(colours)
    return colour, np.concatenate(rays), texel


def _reused_surface(scene, cache, visibility, index, obj, dtype, compute) -> Surface:
    """The object's Surface from ``cache`` when nothing that moves it requires grad and its
    values are unchanged (e.g. while a light or a material is optimised): saves the hit
    recomputation (gathers, cross and dot products on every hit). Otherwise ``compute()``
    on the tape."""
    camera = scene.camera
    owned = moves_surface(obj)
    movers = [camera.position, camera.look_at, camera.up, camera.fov] + owned
    if md.is_grad_enabled() and any(t.requires_grad for t in movers):
        return compute()

    def untaped() -> Surface:
        with md.no_grad():
            return compute()

    key = surface_key(obj, owned, dtype) + [visibility.stamp]
    surface, _ = cache.get(("surface", index), key, untaped)
    return surface


def _compose_image(scene: Scene, visibility: Visibility, colour, ray_of_colour, spp: int):
    """Step 4: the (H, W, 3) image: each pixel the mean of its samples' colours, misses
    showing the background."""
    camera, prim_id = scene.camera, visibility.primary.prim_id
    n_pixels = camera.width * camera.height
    image = None
    if colour is not None:
        image = md.scatter_add(colour, ray_of_colour // spp, n_pixels)
        if spp > 1:
            image = image * (1.0 / spp)
    background = scene.background
    if image is None or background.requires_grad or np.any(background.data):
        misses = np.bincount(np.flatnonzero(prim_id < 0) // spp, minlength=n_pixels)
        fill = (misses / spp).astype(working_dtype(scene))[:, None] * background
        image = fill if image is None else image + fill
    return md.reshape(image, (camera.height, camera.width, 3))


@dataclass
class RenderInfo:
    """The discrete decisions behind an image (constants on the tape), per ray.

    prim_id (H, W, spp) int64: the primitive each ray hit (-1: background).
    lit (n_lights, H, W, spp) bool: light j reaches the ray's hit point unoccluded.
    texel (H, W, spp) int64: the cell of the bilinear texture lookup at the hit
        (``render.shading.texel_cell``; -1 where the hit surface is untextured or missed).
    Two renders have the same visibility where ``prim_id`` and ``lit`` agree. The image is a
    smooth function of the parameters only while all three stay the same: the tape
    gradient is the derivative for fixed decisions, so finite differences agree with it
    only where a perturbation changes none of them.
    """

    prim_id: np.ndarray
    lit: np.ndarray
    texel: np.ndarray

    @classmethod
    def of(cls, scene: Scene, visibility: Visibility, texel: np.ndarray, spp: int) -> RenderInfo:
        """The per-ray arrays of one render, shaped (H, W, spp)."""
        camera, primary = scene.camera, visibility.primary
        shape = (camera.height, camera.width, spp)
        lit = np.zeros((len(visibility.lit), primary.prim_id.size), dtype=bool)
        for j, mask in enumerate(visibility.lit):
            lit[j, primary.hit_rays] = mask
        return cls(
            primary.prim_id.reshape(shape),
            lit.reshape((len(visibility.lit),) + shape),
            texel.reshape(shape),
        )
