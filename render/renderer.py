"""``render(scene)``: visibility with the BVH, then shading on the tape.

The pipeline, one step at a time:

1. Flatten the scene's geometry into one list of primitives (all mesh triangles, then all
   spheres) and build the accelerator over it (``render.accel``).
2. Trace one ray per pixel (or ``spp`` rays) through the BVH: which primitive does each ray
   hit? This is the only non-differentiable step; its answers are constants.
3. Trace a shadow ray from every hit point to every light: is the light visible? Also a
   constant.
4. For the rays that hit something, *recompute* the hit on the tape (``render.geometry``)
   and shade it (``render.shading``): gradients flow to every continuous parameter.
5. Put the hit colours into the image (a scatter-add) and fill the misses with the
   background.

Steps 1-3 depend only on the geometry, the camera and the lights. When those have not
changed since the previous render of the same scene (for example while only a material is
optimised), their results are reused (``reuse_visibility=True``, the default): the cache
compares the actual values, so it can never serve stale visibility. The first half of
step 4, the hit points, normals and UVs of an object (its ``Surface``), is reused the same
way when no parameter that moves them requires grad (e.g. while a light is optimised).
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass, field

import numpy as np

import minidiff as md
from render.accel import Accelerator
from render.camera import camera_frame, image_plane_coords, primary_rays, ray_directions
from render.geometry import (
    intersect_edges,
    intersect_spheres,
    toward_ray,
    vertex_normals,
)
from render.scene import DirectionalLight, Material, Mesh, PointLight, Scene, Sphere
from render.shading import column, sample_texture, shade, texel_cell

# Shadow rays start on the surface; they skip the triangle they start on and ignore hits
# closer than this fraction of the distance to the light (neighbouring triangles at a
# shared edge would otherwise shadow the start point).
_SHADOW_EPSILON = 1e-7


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


@dataclass
class _Visibility:
    """Cached results of steps 1-3, with the values they were computed from."""

    geometry_key: list = field(default_factory=list)
    accelerators: dict = field(default_factory=dict)
    primary_key: list | None = None
    primary: tuple | None = None
    shadow_keys: dict = field(default_factory=dict)
    shadows: dict = field(default_factory=dict)
    # Step 4's geometry of an object nothing differentiable moves (see ``_cached_surface``):
    # object index -> (key, Surface). Cleared with the primary hits.
    surfaces: dict = field(default_factory=dict)


_CACHE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _same(key_a: list | None, key_b: list) -> bool:
    return (
        key_a is not None
        and len(key_a) == len(key_b)
        and all(
            a.shape == b.shape and np.array_equal(a, b) for a, b in zip(key_a, key_b, strict=True)
        )
    )


def _geometry_arrays(scene: Scene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The current primitives as plain arrays: triangles (T, 3, 3), centres (S, 3), radii."""
    meshes, spheres = scene.meshes, scene.spheres
    triangles = (
        np.concatenate([m.triangles() for m in meshes]).astype(np.float64)
        if meshes
        else np.zeros((0, 3, 3))
    )
    centers = np.array([s.center.data for s in spheres], dtype=np.float64).reshape(-1, 3)
    radii = np.array([s.radius.data for s in spheres], dtype=np.float64).reshape(-1)
    return triangles, centers, radii


def _visibility(scene: Scene, bvh: bool, spp: int, shadows: bool, reuse: bool):
    """Steps 1-3: the primary hit of every ray (prim_id), the rays that hit (hit_rays), their
    image-plane coordinates (coords, (k, 2) float64), per light a lit mask per hit ray, and
    the cache they came from."""
    cache = _CACHE.get(scene) if reuse else None
    if cache is None:
        cache = _Visibility()
        if reuse:
            _CACHE[scene] = cache

    geometry = list(_geometry_arrays(scene))
    if not _same(cache.geometry_key, geometry):
        cache.geometry_key = geometry
        cache.accelerators.clear()
        cache.primary_key = None
        cache.shadow_keys.clear()
    if bvh not in cache.accelerators:
        cache.accelerators[bvh] = Accelerator(*geometry, use_bvh=bvh)
    accel = cache.accelerators[bvh]

    camera = scene.camera
    camera_key = [
        np.array(x.data, dtype=np.float64)  # a copy: the optimiser edits .data in place
        for x in (camera.position, camera.look_at, camera.up, camera.fov)
    ] + [np.array([camera.width, camera.height, spp, bvh])]
    if not _same(cache.primary_key, camera_key):
        eye, directions = primary_rays(camera, spp)
        origins = np.broadcast_to(eye, directions.shape)
        prim_id, t, _, _ = accel.closest_hit(origins, directions)
        hit_rays = np.flatnonzero(prim_id >= 0)
        points = eye + t[hit_rays, None] * directions[hit_rays]  # where shadow rays start
        # Where the hit rays cross the image plane: constant while the camera is, so it is
        # cached too (step 4 rebuilds the differentiable rays from it on every render).
        coords = image_plane_coords(camera, hit_rays, spp)
        cache.primary_key, cache.primary = camera_key, (prim_id, hit_rays, points, coords)
        cache.shadow_keys.clear()
        cache.surfaces.clear()
    prim_id, hit_rays, points, coords = cache.primary

    lit = []
    for j, light in enumerate(scene.lights):
        if not shadows:
            lit.append(np.ones(len(hit_rays), dtype=bool))
            continue
        light_key = _light_key(light) + [np.array([bvh])]
        if not _same(cache.shadow_keys.get(j), light_key):
            cache.shadows[j] = _trace_shadows(accel, light, points, prim_id[hit_rays])
            cache.shadow_keys[j] = light_key
        lit.append(cache.shadows[j])
    return prim_id, hit_rays, coords, lit, cache


def _light_key(light) -> list:
    """The values the shadow rays depend on (copies, so later in-place edits are seen)."""
    if isinstance(light, PointLight):
        return [np.array(light.position.data, dtype=np.float64), np.array([0.0])]
    return [np.array(light.direction.data, dtype=np.float64), np.array([1.0])]


def _trace_shadows(accel: Accelerator, light, points: np.ndarray, start_prim: np.ndarray):
    """(k,) bool: True where the light reaches the hit point (no primitive in between)."""
    if len(points) == 0:
        return np.zeros(0, dtype=bool)
    if isinstance(light, PointLight):
        # Unnormalised direction to the light: t = 1 is the light itself.
        directions = np.asarray(light.position.data, dtype=np.float64) - points
        tmax = 1.0 - _SHADOW_EPSILON
        # A light sitting exactly on a hit point: no direction to trace; its contribution
        # is zero anyway (see shading), so call it lit.
        zero = ~directions.any(axis=1)
        directions[zero] = (0.0, 1.0, 0.0)
    elif isinstance(light, DirectionalLight):
        # Unit length: tmin is in units of the direction vector, and the user's direction
        # may have any length (with |direction| = 1e7 every nearby occluder was skipped).
        towards = -np.asarray(light.direction.data, np.float64)
        directions = np.broadcast_to(towards / np.linalg.norm(towards), points.shape)
        tmax = np.inf
    else:
        raise TypeError(f"render: unsupported light type {type(light).__name__}")
    scale = max(1.0, float(np.abs(points).max()))
    # Skip the triangle the ray starts on (a flat triangle cannot shadow its own points), but
    # not a sphere: seen from inside it does shadow itself (a light outside cannot reach the
    # inside). Starting on the outside of a sphere towards the light, its other root is
    # behind the ray, and tmin removes the start point itself.
    ignore = np.where(start_prim < accel.n_triangles, start_prim, -1)
    blocked = accel.occluded(
        points, directions, tmax, tmin=_SHADOW_EPSILON * scale, ignore_prim=ignore
    )
    return ~blocked


def _interpolate(weights, attribute, faces):
    """Barycentric interpolation of a per-vertex attribute (V, n) at k hits: (k, n)."""
    return sum(w * attribute[faces[:, i]] for i, w in enumerate(weights))


@dataclass
class Surface:
    """What shading needs to know about k hits on one object (tensors, on the tape):
    points (k, 3), unit normals facing the ray (k, 3), the camera rays' directions (k, 3)
    and, for a textured mesh, the interpolated UVs (k, 2) (else None)."""

    points: md.Tensor
    normals: md.Tensor
    directions: md.Tensor
    uv: md.Tensor | None = None


def mesh_surface(mesh: Mesh, faces_hit, eye, directions) -> Surface:
    """Recompute the hits on one mesh's triangles on the tape.

    faces_hit (k,) local face ids from the BVH; eye (3,) and directions (k, 3) the camera
    rays (tensors).
    """
    faces = mesh.faces[faces_hit]
    a, b, c = (mesh.vertices[faces[:, i]] for i in range(3))
    e1, e2 = b - a, c - a
    # Barycentrics are needed only to interpolate vertex normals or UVs.
    interpolated = mesh.smooth or mesh.material.texture is not None
    t, u, v = intersect_edges(eye, directions, a, e1, e2, barycentrics=interpolated)
    points = eye + column(t) * directions
    normals = md.normalize(md.cross(e1, e2))
    flip = toward_ray(normals, directions)
    if interpolated:
        weights = (column(1.0 - u - v), column(u), column(v))  # of corners a, b, c
    if mesh.smooth:
        vn = mesh.normals if mesh.normals is not None else vertex_normals(mesh.vertices, mesh.faces)
        normals = md.normalize(_interpolate(weights, vn, faces))
    uv = _interpolate(weights, mesh.uvs, faces) if mesh.material.texture is not None else None
    return Surface(points, normals * flip, directions, uv)


def sphere_surface(sphere: Sphere, eye, directions) -> Surface:
    """Recompute the hits on one sphere on the tape (k rays known to hit it)."""
    if sphere.material.texture is not None:
        raise ValueError("render: spheres carry no UVs, so their material cannot have a texture")
    inside = np.linalg.norm(eye.data - sphere.center.data) < sphere.radius.data
    far_root = np.full(directions.shape[0], bool(inside))
    t = intersect_spheres(eye, directions, sphere.center, sphere.radius, far_root)
    points = eye + column(t) * directions
    normals = md.normalize(points - sphere.center)
    return Surface(points, normals * toward_ray(normals, directions), directions)


def shade_surface(
    surface: Surface, material: Material, lights, lit
) -> tuple[md.Tensor, np.ndarray]:
    """Shade k hits: the radiance (k, 3) and the texture cell of each hit (k,) int64 (-1
    when untextured). lit[j] (k,) float visibility of light j."""
    k = surface.points.shape[0]
    if material.texture is not None:
        albedo = sample_texture(material.texture, surface.uv)
        texel = texel_cell(material.texture.shape, surface.uv.data)
    else:
        albedo = material.albedo
        texel = np.full(k, -1, dtype=np.int64)
    radiance = shade(
        surface.points, surface.normals, surface.directions, albedo, material, lights, lit
    )
    return radiance, texel


def shade_mesh(mesh: Mesh, faces_hit, eye, directions, lights, lit) -> tuple[md.Tensor, np.ndarray]:
    """``mesh_surface`` then ``shade_surface``: radiance (k, 3) and texel cells (k,)."""
    return shade_surface(mesh_surface(mesh, faces_hit, eye, directions), mesh.material, lights, lit)


def _moves_surface(obj: Mesh | Sphere, camera) -> list[md.Tensor]:
    """The parameters that move an object's hit points, normals or UVs."""
    tensors = [camera.position, camera.look_at, camera.up, camera.fov]
    if isinstance(obj, Sphere):
        return tensors + [obj.center, obj.radius]
    return tensors + [t for t in (obj.vertices, obj.normals, obj.uvs) if t is not None]


def _cached_surface(cache: _Visibility, index: int, obj, camera, dtype, compute) -> Surface:
    """The object's Surface, reused from the previous render when nothing that moves it
    requires grad and its values are unchanged (e.g. while a light or a material is
    optimised); otherwise ``compute()`` on the tape. Saves the hit recomputation
    (gathers, cross and dot products on every hit) in each such iteration."""
    tensors = _moves_surface(obj, camera)
    if any(t.requires_grad for t in tensors) and md.is_grad_enabled():
        return compute()
    # The camera and the vertices are in the primary key (``cache.surfaces`` is cleared
    # when it changes); normals and UVs are not, so they are compared here.
    # The object itself, its switches and the working dtype change the result too.
    switches = [id(obj), np.dtype(dtype).num]
    if isinstance(obj, Mesh):
        switches += [obj.smooth, obj.material.texture is not None, obj.normals is not None]
    key = [np.array(t.data) for t in tensors[4:]] + [np.array(switches, dtype=np.int64)]
    entry = cache.surfaces.get(index)
    if entry is not None and _same(entry[0], key):
        return entry[1]
    with md.no_grad():
        surface = compute()
    cache.surfaces[index] = (key, surface)
    return surface


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
    return_info: also return a ``RenderInfo`` with the visibility decisions.

    Every parameter of the scene that is a ``requires_grad`` tensor receives its gradient
    when the caller runs ``backward`` on a loss computed from the image.
    """
    if not isinstance(scene, Scene):
        raise TypeError(f"render: scene must be a render.Scene, got {type(scene).__name__}")
    scene.validate()
    camera, lights = scene.camera, scene.lights
    prim_id, hit_rays, coords, lit, cache = _visibility(
        scene, bool(bvh), spp, bool(shadows), reuse_visibility
    )
    n_pixels = camera.width * camera.height

    # The working precision: float32 only if every parameter is float32 (constants such as
    # pixel coordinates are cast to it, so that they do not promote the tape to float64).
    dtype = np.result_type(*[t.dtype for t in scene.parameters()])
    frame = camera_frame(camera)
    eye = frame[3]
    coords = coords.astype(dtype, copy=False)
    hit_prims = prim_id[hit_rays]

    texel = np.full(prim_id.size, -1, dtype=np.int64)  # per ray, for RenderInfo
    colours, pixels = [], []
    for index, (obj, first, count) in enumerate(_primitive_ranges(scene)):
        in_obj = np.flatnonzero((hit_prims >= first) & (hit_prims < first + count))
        if len(in_obj) == 0:
            continue

        def compute(obj=obj, first=first, in_obj=in_obj) -> Surface:
            directions = ray_directions(frame, coords[in_obj])
            if isinstance(obj, Mesh):
                return mesh_surface(obj, hit_prims[in_obj] - first, eye, directions)
            return sphere_surface(obj, eye, directions)

        surface = _cached_surface(cache, index, obj, camera, dtype, compute)
        obj_lit = [m[in_obj].astype(dtype) for m in lit]
        colour, texel[hit_rays[in_obj]] = shade_surface(surface, obj.material, lights, obj_lit)
        colours.append(colour)
        pixels.append(hit_rays[in_obj] // spp)

    image = None
    if colours:
        colour = colours[0] if len(colours) == 1 else md.concatenate(colours)
        image = md.scatter_add(colour, np.concatenate(pixels), n_pixels)
        if spp > 1:
            image = image * (1.0 / spp)
    background = scene.background
    if image is None or background.requires_grad or np.any(background.data):
        misses = np.bincount(np.flatnonzero(prim_id < 0) // spp, minlength=n_pixels)
        fill = (misses / spp).astype(dtype)[:, None] * background
        image = fill if image is None else image + fill
    image = md.reshape(image, (camera.height, camera.width, 3))
    if not return_info:
        return image
    shape = (camera.height, camera.width, spp)
    lit_full = np.zeros((len(lights), prim_id.size), dtype=bool)
    for j, m in enumerate(lit):
        lit_full[j, hit_rays] = m
    return image, RenderInfo(
        prim_id.reshape(shape), lit_full.reshape((len(lights),) + shape), texel.reshape(shape)
    )


def _primitive_ranges(scene: Scene) -> list[tuple[Mesh | Sphere, int, int]]:
    """(object, first primitive id, primitive count) per object, in the accelerator's order:
    the triangles of every mesh, then the spheres (see ``_geometry_arrays``)."""
    ranges, first = [], 0
    for obj in scene.meshes + scene.spheres:
        count = obj.num_faces if isinstance(obj, Mesh) else 1
        ranges.append((obj, first, count))
        first += count
    return ranges
