"""``render(scene)``: the pipeline, one step per module.

1. Visibility (``render.trace.visibility``, plain arrays, constants on the tape): which primitive
   does the ray of every pixel sample hit, and does each hit see each light? Camera rays are
   rasterised or traced through the BVH, shadow rays towards a point light answered in the
   light's view or by the BVH (``render.trace.raster``: the same answers, bit for bit); the BVH
   is built only if some ray needs it.
2. Surfaces (``render.shade.surface``, on the tape): for the rays that hit, *recompute* the hit
   point, normal and UV differentiably from the camera and the primitive, object by object.
3. Shading (``render.shade.lighting``, on the tape): lights and materials give each hit a colour;
   a reflective material adds what its mirror ray sees (``render.shade.mirrors``: traced like
   step 1, recomputed like step 2, shaded like step 3, up to ``max_bounces`` times).
4. Edges (``render.edges.silhouettes`` and ``render.edges.shadows``, with
   ``antialias=True``): where a silhouette, a crease or a shadow edge passes between two
   adjacent samples, blend them by how much of each one's box the edge covers, with the
   crossing computed on the tape: gradients then see occlusion and shadow boundaries move.
5. Image: each pixel the mean of its samples, misses showing the background.

Gradients reach every continuous parameter through steps 2-5; step 1's decisions (and
which primitive each mirror ray hits) are constants. With ``reuse_visibility=True`` (the
default), step 1 and the surfaces of step 2 are reused from the previous render of the
same scene when the values they depend on are unchanged (``render.scene.cache``), e.g. while
only a material is optimised; mirror rays are traced anew on every render.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

import minidiff as md
from minidiff import buffers
from render.edges.shadows import ShadowPairs, object_index_of, shadow_crossings, shadow_updates
from render.edges.silhouettes import EdgePairs, add_to_samples, crossings, edge_updates, in_order
from render.scene.cache import RenderCache, cache_for, surface_key
from render.scene.camera import camera_frame, ray_directions, subpixel_offsets
from render.scene.scene import Mesh, Scene, check_ray_count
from render.shade.lighting import appearance, light_contribution, shade_mesh, shade_surface
from render.shade.mirrors import Bounces, reflected_radiance
from render.shade.surface import Surface, mesh_surface, moves_surface, sphere_surface
from render.trace.visibility import Visibility, primitive_ranges, scene_size, trace_visibility

__all__ = ["render", "RenderInfo", "shade_mesh", "shade_surface"]


def render(
    scene: Scene,
    bvh: bool = True,
    shadows: bool = True,
    spp: int = 1,
    reuse_visibility: bool = True,
    return_info: bool = False,
    antialias: bool = False,
    max_bounces: int = 2,
    primary: str = "auto",
) -> md.Tensor | tuple[md.Tensor, RenderInfo]:
    """Render ``scene`` to linear radiance, an (H, W, 3) ``minidiff.Tensor``.

    bvh: use the BVH (False: brute force over all primitives, same result, for ablations).
    shadows: trace shadow rays (False: every light reaches every hit point).
    spp: samples per pixel, a perfect square, on a fixed stratified pattern (deterministic,
        hence differentiable); the pixel value is their mean.
    reuse_visibility: reuse the previous render's visibility when geometry, camera and
        lights have the same values (see the module docstring).
    return_info: also return a ``RenderInfo`` with the discrete decisions.
    antialias: blend adjacent samples across silhouettes, creases and shadow edges by
        their coverage, on the tape (``render.edges.silhouettes``,
        ``render.edges.shadows``), so that moving edges have gradients. False (the
        default, the paper's renderer): every sample shows the primitive at its centre, the
        image is a step function at edges and their motion has no gradient. See the README
        for why False is the default and when to switch it on.
    max_bounces: how many mirror reflections a camera ray may take (RayTracer.jl's depth:
        the camera hit plus two reflections); 0 turns reflection off. Only hits on a
        material with a non-zero (or differentiated) ``reflectance`` spawn a mirror ray.
    primary: how the camera rays' hits are found: "bvh" traces them through the BVH,
        "raster" rasterises the primitives (``render.trace.raster``; the same hits bit for bit,
        faster while there are many rays per primitive), "auto" (default) rasterises when
        there are at least 16 camera rays per primitive (``RASTER_RAYS_PER_PRIMITIVE``).
        With ``bvh=False`` both are brute force (the ablation).

    Every parameter of the scene that is a ``requires_grad`` tensor receives its gradient
    when the caller runs ``backward`` on a loss computed from the image.
    """
    if not isinstance(scene, Scene):
        raise TypeError(f"render: scene must be a render.Scene, got {type(scene).__name__}")
    scene.validate()
    subpixel_offsets(spp)  # a clear error for a bad spp before anything else
    check_ray_count(scene.camera.width, scene.camera.height, spp)
    cache = cache_for(scene, reuse_visibility)

    antialias = _check_flag(antialias, "antialias")
    max_bounces = _check_bounces(max_bounces)
    raster = _rasterise(scene, _check_primary(primary), spp) and bool(bvh)
    visibility = trace_visibility(  # 1
        scene, cache, bool(bvh), spp, bool(shadows), antialias, raster
    )
    frame = camera_frame(scene.camera)
    bounces = _bounces(scene, visibility, bool(shadows), max_bounces)
    colour, ray_of_colour, texel, shaded = _shade_objects(  # 2, 3
        scene, visibility, frame, cache, bounces
    )
    if antialias:  # 4
        dtype = working_dtype(scene)
        samples = _sample_colours(scene, visibility, colour, ray_of_colour)
        s, slope = crossings(scene, visibility.pairs, frame, spp, dtype)
        silhouettes = edge_updates(samples, visibility.pairs, s, slope)
        shadows = _shadow_updates(scene, visibility, shaded, frame, spp)
        samples = add_to_samples(samples, [silhouettes, shadows])
        image = _pixel_means(scene, samples, spp)  # 5
    else:
        image = _compose_image(scene, visibility, colour, ray_of_colour, spp)  # 5

    if not return_info:
        return image
    return image, RenderInfo.of(scene, visibility, texel, spp, bounces)


def working_dtype(scene: Scene) -> np.dtype:
    """float32 only if every parameter is float32 (constants such as pixel coordinates are
    cast to it, so that they do not promote the tape to float64)."""
    return np.result_type(*[t.dtype for t in scene.parameters()])


def _check_primary(value) -> str:
    if value not in ("auto", "raster", "bvh"):
        raise ValueError(f'render: primary must be "auto", "raster" or "bvh", got {value!r}')
    return value


#: "auto" rasterises when rays / primitives >= RASTER_RAYS_PER_PRIMITIVE. Measured at 512x512
#: (camera-ray hits alone, medians of 9): 1,536 triangles raster 2.8 ms / BVH 9.9 ms,
#: 15,360: 10.1 / 12.1 ms, 99,840: 43.8 / 15.9 ms, 256,000: 134 / 27 ms.
RASTER_RAYS_PER_PRIMITIVE = 16


def _rasterise(scene: Scene, primary: str, spp: int) -> bool:
    """Whether to rasterise the camera rays' hits (``render(primary=...)``)."""
    if primary != "auto":
        return primary == "raster"
    rays = scene.camera.width * scene.camera.height * spp
    primitives = sum(m.num_faces for m in scene.meshes) + len(scene.spheres)
    return primitives * RASTER_RAYS_PER_PRIMITIVE <= rays


def _check_bounces(value) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 0:
        raise ValueError(f"render: max_bounces must be an integer >= 0, got {value!r}")
    return int(value)


def _bounces(scene: Scene, visibility: Visibility, shadows: bool, max_bounces: int):
    """What the mirror rays need (``render.shade.mirrors.Bounces``), or None if no hit can
    spawn one."""
    if max_bounces == 0 or not any(obj.material.reflective for obj in scene.objects):
        return None
    n_rays = visibility.primary.prim_id.size
    ids = [np.full(n_rays, -2, dtype=np.int64) for _ in range(max_bounces)]
    lit = [np.zeros((len(scene.lights), n_rays), dtype=bool) for _ in range(max_bounces)]
    size = scene_size(visibility.primitives)
    return Bounces(
        scene, visibility.accelerator, visibility.bvh, visibility.primitives, size, shadows,
        max_bounces, ids, lit,
    )  # fmt: skip


def _check_flag(value, name: str) -> bool:
    if not isinstance(value, bool | np.bool_):
        raise TypeError(f"render: {name} must be True or False, got {value!r}")
    return bool(value)


def _shade_objects(scene: Scene, visibility: Visibility, frame, cache: RenderCache, bounces):
    """Steps 2 and 3 for every object: the colours (k, 3) of all hit rays, object by object,
    the ray each colour belongs to (k,), the texture cell of every ray (N,) (-1: none; None
    if no ray hit a textured object), and per object index (in ``primitive_ranges`` order)
    its hit rays and ``Surface``. With ``bounces`` (``render.shade.mirrors.Bounces``),
    reflective objects add what their mirror rays see."""
    primary, dtype = visibility.primary, working_dtype(scene)
    eye = frame[3]
    coords = primary.coords.astype(dtype, copy=False)
    hit_prims = md.kernels.gather_rows(primary.prim_id, primary.hit_rays)

    texel = None  # made when a textured object is hit (filling it costs a pass)
    colours, rays, shaded = [], [], {}
    for index, (obj, first, count) in enumerate(primitive_ranges(scene)):
        in_obj = np.flatnonzero((hit_prims >= first) & (hit_prims < first + count))
        if len(in_obj) == 0:
            continue

        def surface(obj=obj, first=first, in_obj=in_obj) -> Surface:
            directions = ray_directions(frame, md.kernels.gather_rows(coords, in_obj))
            if isinstance(obj, Mesh):
                return mesh_surface(obj, hit_prims[in_obj] - first, eye, directions)
            return sphere_surface(obj, eye, directions)

        hits = _reused_surface(scene, cache, visibility, index, obj, dtype, surface)
        obj_lit = [_as_dtype(mask[in_obj], dtype) for mask in visibility.lit]
        colour, cells = shade_surface(hits, obj.material, scene.lights, obj_lit)
        if obj.material.texture is not None:
            if texel is None:
                texel = buffers.empty((primary.prim_id.size,), np.int64)  # reused memory
                texel.fill(-1)
            texel[primary.hit_rays[in_obj]] = cells
        if bounces is not None and obj.material.reflective:
            rays_in_obj = primary.hit_rays[in_obj]
            seen = reflected_radiance(bounces, hits, hit_prims[in_obj], rays_in_obj, 1)
            colour = colour + obj.material.reflectance * seen
        colours.append(colour)
        rays.append(primary.hit_rays[in_obj])
        shaded[index] = (primary.hit_rays[in_obj], hits)
    if not colours:
        return None, np.zeros(0, np.int64), texel, shaded
    colour = colours[0] if len(colours) == 1 else md.concatenate(colours)
    return colour, np.concatenate(rays), texel, shaded


def _as_dtype(mask: np.ndarray, dtype) -> np.ndarray:
    """``mask.astype(dtype)``, in reused memory (``minidiff.buffers``)."""
    out = buffers.empty(mask.shape, dtype)
    out[...] = mask
    return out


def _reused_surface(scene, cache, visibility, index, obj, dtype, compute) -> Surface:
    """The object's Surface from ``cache`` when nothing that moves it is differentiated
    (requires grad or carries a tangent) and its values are unchanged (e.g. while a light
    or a material is optimised): saves the hit recomputation (gathers, cross and dot
    products on every hit). Otherwise ``compute()`` on the tape."""
    camera = scene.camera
    owned = moves_surface(obj)
    movers = [camera.position, camera.look_at, camera.up, camera.fov] + owned
    if md.is_grad_enabled() and any(t.is_differentiated() for t in movers):
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
    if image is None or background.is_differentiated() or np.any(background.data):
        misses = np.bincount(np.flatnonzero(prim_id < 0) // spp, minlength=n_pixels)
        fill = (misses / spp).astype(working_dtype(scene))[:, None] * background
        image = fill if image is None else image + fill
    return md.reshape(image, (camera.height, camera.width, 3))


def _shadow_updates(scene, visibility, shaded, frame, spp):
    """Step 4 for shadows: what blending each shadow pair's light contribution across its
    edge adds to the samples (``render.edges.shadows.shadow_updates``), or None. The
    unoccluded contribution of the pair's light is shaded again at both samples, from
    their object's Surface."""
    pairs = visibility.shadow_pairs
    if pairs is None or len(pairs.lit) == 0:
        return None
    prim_id = visibility.primary.prim_id
    objects = [obj for obj, _, _ in primitive_ranges(scene)]
    owner = object_index_of(scene, prim_id[pairs.lit])  # both samples are on this object
    lit_light, dark_light, lit_points, order = [], [], [], []
    for index, (rays, surface) in shaded.items():
        obj = objects[index]
        row_of_ray = np.full(prim_id.size, -1, dtype=np.int64)
        row_of_ray[rays] = np.arange(len(rays))
        for j, light in enumerate(scene.lights):
            rows = np.flatnonzero((owner == index) & (pairs.light == j))
            if len(rows) == 0:
                continue
            lit_rows, dark_rows = row_of_ray[pairs.lit[rows]], row_of_ray[pairs.dark[rows]]
            lit_light.append(_unoccluded(surface, lit_rows, obj.material, light))
            dark_light.append(_unoccluded(surface, dark_rows, obj.material, light))
            lit_points.append(surface.points[lit_rows])
            order.append(rows)
    s, slope = shadow_crossings(
        scene, pairs, prim_id[pairs.lit], in_order(lit_points, order), frame, spp,
        working_dtype(scene),
    )  # fmt: skip
    return shadow_updates(pairs, s, slope, in_order(lit_light, order), in_order(dark_light, order))


def _unoccluded(surface: Surface, rows: np.ndarray, material, light) -> md.Tensor:
    """One light's unoccluded contribution (k, 3) at some rows of a Surface."""
    uv = surface.uv[rows] if surface.uv is not None else None
    look = appearance(material, uv, len(rows))
    return light_contribution(
        surface.points[rows], surface.normals[rows], surface.directions[rows], look, light
    )


def _sample_colours(scene: Scene, visibility: Visibility, colour, ray_of_colour) -> md.Tensor:
    """(N, 3) the colour of every ray: its hit's, or the background."""
    prim_id = visibility.primary.prim_id
    n_rays = prim_id.size
    samples = None if colour is None else md.scatter_add(colour, ray_of_colour, n_rays)
    background = scene.background
    if samples is None or background.is_differentiated() or np.any(background.data):
        misses = (prim_id < 0).astype(working_dtype(scene))[:, None]
        fill = misses * background
        samples = fill if samples is None else samples + fill
    return samples


def _pixel_means(scene: Scene, samples: md.Tensor, spp: int) -> md.Tensor:
    """(H, W, 3) image: the mean of each pixel's spp consecutive samples (N, 3)."""
    camera = scene.camera
    if spp > 1:
        pixel = np.arange(samples.shape[0]) // spp
        samples = md.scatter_add(samples, pixel, camera.width * camera.height) * (1.0 / spp)
    return md.reshape(samples, (camera.height, camera.width, 3))


@dataclass
class RenderInfo:
    """The discrete decisions behind an image (constants on the tape), per ray.

    prim_id (H, W, spp) int64: the primitive each ray hit (-1: background).
    lit (n_lights, H, W, spp) bool: light j reaches the ray's hit point unoccluded.
    texel (H, W, spp) int64: the cell of the bilinear texture lookup at the hit
        (``render.shade.lighting.texel_cell``; -1 where the hit surface is untextured or missed).
    pairs: with ``antialias=True``, the pairs of adjacent samples across a silhouette and
        the edge each one uses (``render.edges.silhouettes.EdgePairs``, ray ids r = pixel * spp +
        sample); None without.
    shadow_pairs: likewise across shadow edges (``render.edges.shadows.ShadowPairs``);
        None without antialiasing or without shadows.
    bounces: per mirror reflection b = 1, 2, ..., an (H, W, spp) int64 array: the
        primitive the ray's b-th mirror ray hit (-1: the background; -2: no such ray).
        Empty when nothing in the scene reflects (or ``max_bounces=0``).
    bounce_lit: per mirror reflection, (n_lights, H, W, spp) bool: light j reaches the
        point that mirror ray hit (False where there is none).
    Two renders have the same visibility where ``prim_id``, ``lit``, ``bounces`` and
    ``bounce_lit`` agree.
    The image is a smooth function of the parameters only while all of these stay the same: the tape
    gradient is the derivative for fixed decisions, so finite differences agree with it
    only where a perturbation changes none of them.
    """

    prim_id: np.ndarray
    lit: np.ndarray
    texel: np.ndarray
    pairs: EdgePairs | None = None
    shadow_pairs: ShadowPairs | None = None
    bounces: list[np.ndarray] = field(default_factory=list)
    bounce_lit: list[np.ndarray] = field(default_factory=list)

    @classmethod
    def of(cls, scene: Scene, visibility: Visibility, texel: np.ndarray | None, spp: int, bounces):
        """The per-ray arrays of one render, shaped (H, W, spp); texel None: no ray hit a
        textured surface."""
        camera, primary = scene.camera, visibility.primary
        if texel is None:
            texel = np.full(primary.prim_id.size, -1, dtype=np.int64)
        shape = (camera.height, camera.width, spp)
        lit = np.zeros((len(visibility.lit), primary.prim_id.size), dtype=bool)
        for j, mask in enumerate(visibility.lit):
            lit[j, primary.hit_rays] = mask
        return cls(
            primary.prim_id.reshape(shape),
            lit.reshape((len(visibility.lit),) + shape),
            texel.reshape(shape),
            visibility.pairs,
            visibility.shadow_pairs,
            [] if bounces is None else [ids.reshape(shape) for ids in bounces.hit_ids],
            [] if bounces is None else [m.reshape(lit.shape[:1] + shape) for m in bounces.lit],
        )
