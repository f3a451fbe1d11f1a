"""Steps 2 and 3 for every hit: its surface recomputed on the tape, then shaded.

One function shades hits, whoever traced them: ``shade_hits`` gives k hits on one object
(``render.shade.surface.Hits``) their colour from the lights and the material
(``render.shade.lighting``) and, on a reflective material, adds what the mirror rays see
(``render.shade.mirrors`` traces them; what they hit is shaded by ``shade_hits`` again, up
to ``max_bounces`` reflections).

``shade_camera_hits`` feeds it the camera rays' hits, object by object: each object's
Surface is recomputed from the camera frame and the primitive ids of step 1, or reused
from the render cache when nothing that moves it is differentiated and its values are
unchanged (e.g. while only a light or a material is optimised). A mesh the compiled shading
takes (``render.shade.compiled``: the same functions traced into one kernel, one node on
the tape) is shaded by it instead, when the caller does not need its Surface.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import minidiff as md
from minidiff import buffers
from render.scene.cache import RenderCache, surface_key
from render.scene.camera import ray_directions
from render.scene.scene import Scene
from render.shade import compiled
from render.shade.lighting import shade_surface
from render.shade.mirrors import Mirrors
from render.shade.surface import Hits, Surface, in_order, moves_surface, surface_at
from render.trace.primitives import primitive_ranges
from render.trace.visibility import Visibility


def working_dtype(scene: Scene) -> np.dtype:
    """float32 only if every parameter is float32 (constants such as pixel coordinates are
    cast to it, so that they do not promote the tape to float64)."""
    return np.result_type(*[t.dtype for t in scene.parameters()])


def shade_hits(
    scene: Scene, hits: Hits, mirrors: Mirrors | None, bounce: int
) -> tuple[md.Tensor, np.ndarray | None]:
    """The radiance (k, 3) leaving k ``hits`` towards their rays, and each hit's diffuse
    texture cell (k,) int64 (None: no diffuse texture). ``bounce`` counts the mirror
    reflections before these hits (0 for camera hits); a reflective material adds
    ``reflectance`` times what its mirror rays see while ``bounce < mirrors.max_bounces``."""
    material = hits.obj.material
    colour, cells = shade_surface(hits.surface, material, scene.lights, hits.lit)
    if mirrors is not None and material.reflective and bounce < mirrors.max_bounces:
        colour = colour + material.reflectance * mirror_radiance(scene, hits, mirrors, bounce + 1)
    return colour, cells


def mirror_radiance(scene: Scene, hits: Hits, mirrors: Mirrors, bounce: int) -> md.Tensor:
    """The radiance (k, 3) arriving at k ``hits`` along their mirror directions (the
    ``bounce``-th reflection): what each mirror ray hits, shaded by ``shade_hits``, or the
    background."""
    groups, missed = mirrors.trace(hits, bounce)
    parts, order = [], []
    for group in groups:
        parts.append(shade_hits(scene, group, mirrors, bounce)[0])
        order.append(group.rows)
    if len(missed):
        parts.append(md.broadcast_to(scene.background, (len(missed), 3)))
        order.append(missed)
    return in_order(parts, order)


@dataclass
class CameraShading:
    """The colours of the camera rays' hits: ``colour`` (k, 3) object by object (None if
    no ray hit anything), the ray each row belongs to ``rays`` (k,) int64, the texture cell
    of every ray ``texel`` (N,) int64 (-1: none; None if no ray hit a textured object), and
    per object index the ``Hits`` that were shaded (the edge terms shade some again)."""

    colour: md.Tensor | None
    rays: np.ndarray
    texel: np.ndarray | None
    hits: dict[int, Hits]


def shade_camera_hits(
    scene: Scene,
    visibility: Visibility,
    frame,
    cache: RenderCache,
    mirrors: Mirrors | None,
    surfaces: bool = True,
) -> CameraShading:
    """Steps 2 and 3 for the camera rays: every object's hits recomputed from the camera
    ``frame`` (``render.scene.camera.camera_frame``) and shaded by ``shade_hits``.

    surfaces: whether the caller needs every object's ``Hits`` with its Surface (the pixel
    pairs' shadow terms shade them again). Without, a mesh the compiled shading takes is
    shaded by it (``render.shade.compiled``: the same functions, compiled; one node on the
    tape) and left out of ``CameraShading.hits``."""
    primary = visibility.primary
    texel = None  # made when a textured object is hit (filling it costs a pass)
    colours, rays, shaded = [], [], {}
    hit_prims = md.kernels.gather_rows(primary.prim_id, primary.hit_rays)
    ranges = primitive_ranges(scene)
    for index, (obj, first, count) in enumerate(ranges):
        in_obj = object_rows(hit_prims, first, count, len(ranges))
        prims, obj_rays = pick(hit_prims, in_obj), pick(primary.hit_rays, in_obj)
        if len(prims) == 0:
            continue
        reflects = mirrors is not None and mirrors.max_bounces > 0 and obj.material.reflective
        if not surfaces and compiled.applies(scene, obj, reflects):
            colour, cells = compiled.shade_mesh(
                obj, prims - first if first else prims, frame, pick(primary.coords, in_obj),
                scene.lights, [pick(mask, in_obj) for mask in visibility.lit],
            ), None  # fmt: skip
        else:
            if isinstance(in_obj, slice):
                in_obj = np.arange(len(prims))
            hits = object_hits(scene, visibility, frame, cache, index, in_obj, prims)
            colour, cells = shade_hits(scene, hits, mirrors, 0)
            shaded[index] = hits
        if obj.material.texture is not None:
            if texel is None:
                texel = buffers.empty((primary.prim_id.size,), np.int64)  # reused memory
                texel.fill(-1)
            texel[obj_rays] = cells
        colours.append(colour)
        rays.append(obj_rays)
    if not colours:
        return CameraShading(None, np.zeros(0, np.int64), texel, shaded)
    colour = colours[0] if len(colours) == 1 else md.concatenate(colours)
    return CameraShading(colour, np.concatenate(rays), texel, shaded)


def object_rows(hit_prims: np.ndarray, first: int, count: int, n_objects: int):
    """The rows of the hits (primitive ids ``hit_prims`` (k,)) on the object whose
    primitives are [first, first + count): an index array, or ``slice(None)`` (every row,
    nothing to pick) when it is the scene's only object (``n_objects``)."""
    if n_objects == 1:
        return slice(None)
    return np.flatnonzero((hit_prims >= first) & (hit_prims < first + count))


def pick(values: np.ndarray, rows) -> np.ndarray:
    """``values[rows]`` for ``object_rows``' rows: gathered in parallel into reused memory
    (``minidiff.kernels.gather_rows``), or ``values`` itself for every row."""
    return values if isinstance(rows, slice) else md.kernels.gather_rows(values, rows)


def object_hits(
    scene: Scene, visibility: Visibility, frame, cache: RenderCache, index: int, in_obj, prims
) -> Hits:
    """The camera rays' hits ``in_obj`` (k,) (rows of ``visibility.primary.hit_rays``) on
    primitives ``prims`` (k,) (global ids) of the object at ``index`` in
    ``primitive_ranges``, its Surface computed on the tape or reused from ``cache``
    (``_reused_surface``)."""
    primary, dtype = visibility.primary, working_dtype(scene)
    obj, first, _ = primitive_ranges(scene)[index]

    def surface() -> Surface:
        coords = md.kernels.gather_rows(primary.coords.astype(dtype, copy=False), in_obj)
        return surface_at(obj, prims - first, frame[3], ray_directions(frame, coords))

    found = _reused_surface(scene, cache, visibility, index, obj, dtype, surface)
    lit = [_as_dtype(mask[in_obj], dtype) for mask in visibility.lit]
    return Hits(obj, index, found, prims, primary.hit_rays[in_obj], in_obj, lit)


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


def sample_colours(scene: Scene, prim_id: np.ndarray, colour, rays: np.ndarray) -> md.Tensor:
    """(N, 3) the colour of every ray: its hit's (``colour`` (k, 3) of the rays ``rays``
    (k,)), or the background where prim_id (N,) is -1."""
    n_rays = prim_id.size
    samples = None if colour is None else md.scatter_add(colour, rays, n_rays)
    background = scene.background
    if samples is None or background.is_differentiated() or np.any(background.data):
        misses = (prim_id < 0).astype(working_dtype(scene))[:, None]
        fill = misses * background
        samples = fill if samples is None else samples + fill
    return samples
