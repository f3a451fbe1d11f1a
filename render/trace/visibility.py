"""Step 1, visibility: which primitive each camera ray hits, which lights each hit sees.

These are the renderer's discrete decisions. They are computed on plain arrays, with the
BVH (``render.trace.accel``) or, where that is faster and gives the same answers, by
projection (``render.trace.raster``, ``render.trace.light_view``), and are constants on the
tape: the image is differentiable for fixed visibility (``render.shade.surface`` recomputes
*where* each ray hits, differentiably).

* ``trace_primary``: one ray per pixel sample, traced through the BVH or rasterised: the
  primitive it hits (ids of ``render.trace.primitives``).
* ``shadow_rays`` / ``trace_shadows``: a ray from every hit point to a light: is it blocked?
  (Many rays towards a point light: answered in the light's view; else by the BVH.)

``trace_visibility`` runs them, reusing earlier results from a ``render.scene.cache``
``RenderCache`` when the values they depend on are unchanged; the BVH is built (and kept)
only when a ray first needs it. The ``Visibility`` it returns also answers shadow rays for
the stages that trace more rays later (mirror bounces, shadow edges).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from render.scene.cache import RenderCache, camera_key, light_key
from render.scene.camera import hits_along_rays, primary_rays
from render.scene.scene import Camera, Light, Scene
from render.trace.accel import Accelerator, updated
from render.trace.light_view import bounding_box, occluded_towards_light
from render.trace.primitives import Primitives, scene_primitives
from render.trace.raster import raster_closest_hit

#: Shadow rays skip the triangle they start on and start a little off the surface, towards
#: the light, so that rounding in the hit point cannot make a neighbouring triangle at a
#: shared edge shadow it. The offset is relative, so that a scene renders the same at any
#: scale and anywhere (issue 9): this fraction of the scene's size (its bounding box
#: diagonal), or SHADOW_ULPS units in the last place of the coordinates involved if that is
#: larger (far from the origin, where coordinates carry fewer digits).
SHADOW_EPSILON = 1e-9
SHADOW_ULPS = 1024


@dataclass
class PrimaryHits:
    """The camera rays' hits. Ray r goes through pixel r // spp, sample r % spp.

    prim_id (H * W * spp,) int64: the primitive each ray hits, -1 for the background.
    hit_rays (k,) int64: the rays that hit something (``prim_id >= 0``), in ray order.
    depth (H * W * spp,) float64: each ray's hit distance along the view axis (inf: none).
    points (k, 3) float64: where they hit (the shadow rays start there).
    coords (k, 2) float64: where they cross the image plane, x and y in [-1, 1]; the
        renderer rebuilds the differentiable rays from them.
    """

    prim_id: np.ndarray
    hit_rays: np.ndarray
    depth: np.ndarray
    points: np.ndarray
    coords: np.ndarray


def trace_primary(
    accelerator: Callable[[], Accelerator],
    camera: Camera,
    spp: int,
    primitives=None,
    raster: bool = False,
) -> PrimaryHits:
    """Trace every camera ray (``spp`` per pixel) through ``accelerator()``, or with ``raster``
    find the same hits by rasterising ``primitives`` (``render.trace.raster``: bit-identical,
    faster while there are many rays per primitive)."""
    if raster:
        prim_id, t, _, _ = raster_closest_hit(*primitives, camera, spp, with_uv=False)
    else:
        eye, directions = primary_rays(camera, spp)
        prim_id, t, _, _ = accelerator().closest_hit(
            np.broadcast_to(eye, directions.shape), directions
        )
    hit_rays = np.flatnonzero(prim_id >= 0)
    # The camera directions have unit component along the view axis: t is the depth.
    points, coords = hits_along_rays(camera, hit_rays, t, spp)
    return PrimaryHits(prim_id, hit_rays, t, points, coords)


@dataclass
class ShadowRays:
    """Rays from k surface points towards a light, as ``Accelerator.occluded`` takes them:
    blocked if a primitive other than ``ignore_prim`` is hit with 0 < t < tmax."""

    origins: np.ndarray
    directions: np.ndarray
    tmax: np.ndarray | float
    ignore_prim: np.ndarray


def shadow_offset(points: np.ndarray, scene_size: float, light_position=None) -> float:
    """How far above the surface the shadow rays start (see ``SHADOW_EPSILON``): one
    distance for all of them, from the largest coordinate involved."""
    magnitude = float(max(points.max(), -points.min())) if len(points) else 0.0  # max |x|
    if light_position is not None:
        magnitude = max(magnitude, float(np.abs(light_position).max()))
    return max(SHADOW_EPSILON * scene_size, SHADOW_ULPS * np.finfo(np.float64).eps * magnitude)


def shadow_rays(
    light: Light,
    points: np.ndarray,
    start_prim: np.ndarray,
    n_triangles: int,
    scene_size: float,
) -> ShadowRays:
    """The shadow rays from hit points (k, 3) on primitives start_prim (k,) to ``light``
    (``Light.shadow_rays``: a point light's end just before it, a directional light's never);
    ``scene_size`` is the diagonal of the geometry's bounding box."""
    offset = shadow_offset(points, scene_size, light.location())
    origins, directions, tmax = light.shadow_rays(points, offset)
    # Skip the triangle the ray starts on (a flat triangle cannot shadow its own points), but
    # not a sphere: seen from inside it does shadow itself (a light outside cannot reach the
    # inside). Starting on the outside of a sphere towards the light, its other root is
    # behind the ray, and the offset removes the start point itself.
    ignore = np.where(start_prim < n_triangles, start_prim, -1)
    return ShadowRays(origins, directions, tmax, ignore)


def scene_size(primitives: Primitives) -> float:
    """The diagonal of the bounding box of ``scene_primitives`` (0 for an empty scene)."""
    triangles, centers, radii = primitives
    lo, hi = [], []
    if len(triangles):
        corners_lo, corners_hi = bounding_box(triangles.reshape(-1, 3))
        lo, hi = [corners_lo], [corners_hi]
    if len(centers):
        lo.append((centers - radii[:, None]).min(axis=0))
        hi.append((centers + radii[:, None]).max(axis=0))
    if not lo:
        return 0.0
    return float(np.linalg.norm(np.max(hi, axis=0) - np.min(lo, axis=0)))


#: Shadow rays towards a point light are answered in the light's view (``render.trace.light_view``)
#: when there are at least this many per primitive, otherwise by the BVH. Measured on the
#: teapot (1,536 triangles), BVH already built, medians of 30: 2,500 rays BVH 0.43 / view
#: 0.58 ms, 10,000: 1.26 / 1.19 ms, 41,000: 4.2-6.0 / 2.3-2.7 ms; without the light's
#: view a render that rasterises its camera rays must build the BVH (1.2-1.6 ms) as well.
LIGHT_VIEW_RAYS_PER_PRIMITIVE = 4


def trace_shadows(
    accelerator: Callable[[], Accelerator],
    primitives: Primitives,
    light: Light,
    points: np.ndarray,
    start_prim: np.ndarray,
    size: float,
    bvh: bool = True,
) -> np.ndarray:
    """(k,) bool: True where ``light`` reaches the hit point (no primitive in between).

    points (k, 3) on primitives start_prim (k,) of ``primitives`` (``scene_primitives``),
    whose bounding box has the diagonal ``size`` (``scene_size``).
    With ``bvh`` and many rays towards a point light, the rays are answered in the light's
    view (``render.trace.light_view.occluded_towards_light``, the same answers), else by
    ``accelerator()`` (which builds the scene's accelerator on first use).
    """
    if len(points) == 0:
        return np.zeros(0, dtype=bool)
    n_prims = len(primitives[0]) + len(primitives[1])
    rays = shadow_rays(light, points, start_prim, len(primitives[0]), size)
    _ignore_spheres_facing(rays.ignore_prim, light, points, start_prim, primitives)
    position = light.location()  # None: a light at infinity, which has no view
    if bvh and position is not None:
        if len(points) >= LIGHT_VIEW_RAYS_PER_PRIMITIVE * n_prims:
            blocked = occluded_towards_light(
                primitives, position, rays.origins, rays.directions, rays.tmax, rays.ignore_prim
            )
            if blocked is not None:  # None: the rays fan out too widely for one view
                return ~blocked
    blocked = accelerator().occluded(
        rays.origins, rays.directions, rays.tmax, tmin=0.0, ignore_prim=rays.ignore_prim
    )
    return ~blocked


def _ignore_spheres_facing(ignore, light, points, start_prim, primitives) -> None:
    """Let the shadow rays that start on a sphere facing the light skip that sphere (in place
    in ``ignore``). A sphere is convex: a ray leaving its surface outwards, (p - c) . l > 0
    for the direction l to the light, never meets it again. Near the terminator the offset
    along l moves the start point only offset * cos(angle) off the surface, less than the
    rounding of the hit point far from the origin; without this the ray could meet the
    sphere at t ~ 0 and shadow the point (tests/render/test_scale_invariance.py, seed 315)."""
    triangles, centers, _ = primitives
    on_sphere = np.flatnonzero(start_prim >= len(triangles))
    if len(on_sphere) == 0:
        return
    p = points[on_sphere]
    outward = p - centers[start_prim[on_sphere] - len(triangles)]
    towards = np.broadcast_to(light.towards(p), p.shape)
    facing = np.einsum("ij,ij->i", outward, towards) > 0.0
    ignore[on_sphere[facing]] = start_prim[on_sphere[facing]]


@dataclass
class Visibility:
    """Every discrete decision of one render about camera rays: their hits and, per light,
    a lit mask (k,) bool over the hit rays (all True with ``shadows=False``).

    ``stamp`` (1,) identifies the computation of ``primary``: equal stamps, equal hits (for
    the keys of the caches that build on them; ``geometry`` likewise for the primitives).
    ``primitives`` (``render.trace.primitives.scene_primitives``) are what they were traced
    with, ``size`` their bounding box's diagonal, and ``accelerator()`` gives their
    accelerator (built on its first call: a render whose camera rays are rasterised and
    whose shadows are found in the light's view needs none), for the rays that come later
    (mirror rays, the shadow edges' occluders); ``bvh`` says whether it is a BVH (False:
    brute force, the ablation) and ``shadows`` whether shadow rays are traced.
    """

    primary: PrimaryHits
    lit: list[np.ndarray]
    stamp: np.ndarray
    geometry: np.ndarray
    accelerator: Callable[[], Accelerator]
    bvh: bool
    shadows: bool
    primitives: Primitives
    size: float

    def lit_towards(self, light: Light, points, start_prim) -> np.ndarray:
        """(k,) bool: True where ``light`` reaches the points (k, 3) on primitives
        ``start_prim`` (k,) (all True without shadows); ``trace_shadows`` with this
        render's primitives and accelerator."""
        if not self.shadows:
            return np.ones(len(points), dtype=bool)
        return trace_shadows(
            self.accelerator, self.primitives, light, points, start_prim, self.size, self.bvh
        )

    def lit_beside(self, light: Light, points, start_prim, beside, lit) -> np.ndarray:
        """``lit`` (k,) bool, ``lit_towards`` of the points (k, 3) on triangles
        ``start_prim`` (k,), with those it leaves dark tested again, their shadow rays
        passing the faces ``beside`` (k, m) (global ids, -1 padding) as they pass their own:
        the faces whose edge the points lie on (the boundary term's edge points). A line
        through a point of a triangle's edge meets the triangle's plane there only, so such
        a face shadows the point only by rounding, or across the crack where two meshes
        meet whose vertices were rounded apart (through float32: ~1e-8 apart, where shadow
        rays start ``SHADOW_EPSILON`` of the scene off the surface). Left dark, one side of
        such a seam's edge points was in shadow: a box split into meshes, one of them
        rounded to float32, had translation gradients up to 28 % off the one mesh's."""
        dark = np.flatnonzero(~lit & np.any(beside >= 0, axis=1)
                              & (start_prim < len(self.primitives[0])))  # fmt: skip
        if len(dark) == 0:
            return lit
        rays = shadow_rays(light, points[dark], start_prim[dark], len(self.primitives[0]),
                           self.size)  # fmt: skip
        passing = np.column_stack([rays.ignore_prim, beside[dark]])
        tmax = np.broadcast_to(rays.tmax, (len(dark),))
        blocked = blocked_past(self.accelerator(), rays.origins, rays.directions, tmax, passing)
        out = lit.copy()
        out[dark] = ~blocked
        return out


def hit_past(accelerator: Accelerator, origins, directions, passing, tmax=np.inf) -> tuple:
    """The closest hits (prim (k,), t (k,), u (k,), v (k,): ``Accelerator.closest_hit``'s)
    of the rays ``origins + t directions`` (k, 3), 0 < t < ``tmax`` (k,) or a float, past
    the primitives ``passing`` (k, m) (global ids, -1 padding): a ray that meets one goes
    on beyond it (one more closest hit than the faces to pass, at most; a ray that meets
    only such faces meets nothing). For rays through an edge point, which meet the planes
    of the edge's faces there only, but across a seam's crack may meet a face of the edge
    (``render.trace.topology.seam_distance``)."""
    origins = np.array(origins, np.float64)
    tmax = np.array(np.broadcast_to(tmax, (len(origins),)), np.float64)
    prim, t, u, v = accelerator.closest_hit(origins, directions, 0.0, tmax)
    travelled = np.zeros(len(origins))
    todo = np.arange(len(origins))
    for _ in range(passing.shape[1]):
        passed = (prim[todo] >= 0) & np.any(prim[todo, None] == passing[todo], axis=1)
        todo = todo[passed]
        if len(todo) == 0:
            break
        # On from where it met the face (the direction keeps its length).
        step = t[todo]
        travelled[todo] += step
        origins[todo] += step[:, None] * directions[todo]
        tmax[todo] -= step
        # From the face met, the ray meets it again by rounding: it goes on from a
        # billionth of its direction's length beyond.
        prim[todo], t[todo], u[todo], v[todo] = accelerator.closest_hit(
            origins[todo], directions[todo], 1e-9, tmax[todo]
        )
    else:
        last = todo[(prim[todo] >= 0) & np.any(prim[todo, None] == passing[todo], axis=1)]
        prim[last], t[last] = -1, np.inf
    return prim, np.where(prim >= 0, travelled + t, np.inf), u, v


def blocked_past(accelerator: Accelerator, origins, directions, tmax, passing) -> np.ndarray:
    """(k,) bool: whether the rays ``origins + t directions`` (k, 3), 0 < t < ``tmax`` (k,),
    meet a primitive other than those ``passing`` (k, m) (``hit_past``)."""
    return hit_past(accelerator, origins, directions, passing, tmax)[0] >= 0


def geometry_stamp(cache: RenderCache, primitives: Primitives) -> np.ndarray:
    """The stamp of ``primitives`` (``scene_primitives``) in ``cache``: the same while they
    keep their values, a new one when they change."""
    return cache.get("geometry", list(primitives), lambda: None)[1]


def cached_accelerator(
    cache: RenderCache, primitives: Primitives, geometry: np.ndarray, bvh: bool = True
) -> Accelerator:
    """The accelerator of ``primitives`` (whose stamp is ``geometry``), kept in ``cache``
    while they keep their values: the last one refitted to moved primitives, or built anew
    (``accel.updated``). The direct renderer and the path integrator share it."""
    slot = ("accelerator", bvh)
    previous = cache.latest(slot)
    return cache.get(slot, [geometry], lambda: updated(previous, *primitives, use_bvh=bvh))[0]


def trace_visibility(
    scene: Scene, cache: RenderCache, bvh: bool, spp: int, shadows: bool, raster: bool = False
) -> Visibility:
    """Step 1: camera rays (traced, or with ``raster`` rasterised) and shadow rays of
    ``scene``, each reused from ``cache`` while the values it depends on are unchanged (a
    later stage depends on the earlier). The accelerator is built only when a ray needs it."""
    primitives = scene_primitives(scene)
    geometry = geometry_stamp(cache, primitives)
    size = scene_size(primitives)

    def accelerator() -> Accelerator:
        """The scene's accelerator, made when first needed (``cached_accelerator``)."""
        return cached_accelerator(cache, primitives, geometry, bvh)

    primary, traced = cache.get(
        "primary",
        camera_key(scene.camera, spp, bvh) + [geometry, np.array([raster])],
        lambda: trace_primary(accelerator, scene.camera, spp, primitives, raster),
    )
    visibility = Visibility(
        primary, [], traced, geometry, accelerator, bvh, shadows, primitives, size
    )
    start_prim = primary.prim_id[primary.hit_rays]
    for j, light in enumerate(scene.lights):
        if not shadows:
            visibility.lit.append(np.ones(len(primary.hit_rays), dtype=bool))
            continue
        mask, _ = cache.get(
            ("shadows", j),
            light_key(light) + [traced],
            lambda light=light: visibility.lit_towards(light, primary.points, start_prim),
        )
        visibility.lit.append(mask)
    return visibility
