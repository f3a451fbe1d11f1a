"""``render(scene)``: the pipeline, one step per folder, called top to bottom here.

0. Placement (``render/scene/placement.py``, on the tape): objects with a ``Transform``
   get their world-space geometry; the steps below see only world space.
1. Visibility (``render/trace/``, plain arrays, constants on the tape): which primitive
   does the ray of every pixel sample hit, and does each hit see each light? Camera rays
   are rasterised or traced through the BVH, shadow rays towards a point light answered in
   the light's view or by the BVH (the same answers, bit for bit); the BVH is built only
   if some ray needs it.
2. Surfaces (``render/shade/``, on the tape): for the rays that hit, *recompute* the hit
   point, normal and UV differentiably from the camera and the primitive, object by object.
3. Shading (``render/shade/``, on the tape): lights and materials give each hit a colour;
   a reflective material adds what its mirror ray sees (traced like step 1, recomputed
   like step 2, shaded like step 3 by the same function, up to ``max_bounces`` times).
4. Edges (``render/edges/``, with ``antialias=True``): where a silhouette, a crease or a
   shadow edge passes between two adjacent samples, blend them by how much of each one's
   box the edge covers, with the crossing computed on the tape: gradients then see
   occlusion and shadow boundaries move.
5. Image (``render/film.py``): each pixel the mean of its samples, misses showing the
   background.

Steps 2, 3 and 5 take compiled passes where they can (``render.shade.adjoint.route``):
with nothing differentiated (``render.shade.fused``), and, for meshes without textures or
mirrors whose hits move, as one tape node with a hand-written, compiled adjoint
(``render.shade.adjoint``); the taped functions are the reference they are tested against.

Gradients reach every continuous parameter through steps 2-5; step 1's decisions (and
which primitive each mirror ray hits) are constants. With ``reuse_visibility=True`` (the
default), step 1, the edge pairs and the surfaces of step 2 are reused from the previous
render of the same scene when the values they depend on are unchanged
(``render.scene.cache``), e.g. while only a material is optimised; mirror rays are traced
anew on every render. ``docs/architecture.md`` walks through the folders.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

import minidiff as md
from render.edges import terms
from render.edges.interior import INTERIOR_SAMPLES, antialias_mixed_pixels, check_interior_samples
from render.edges.shadows import ShadowPairs
from render.edges.silhouettes import EdgePairs
from render.edges.terms import EdgeDecisions, add_boundary_term, add_edge_terms, differentiated
from render.film import image_from_hits, pixel_means
from render.path.integrator import render_path
from render.scene.cache import cache_for
from render.scene.camera import camera_frame, plain_frame, subpixel_offsets
from render.scene.placement import placed
from render.scene.scene import Scene, check_ray_count
from render.shade import adjoint, fused
from render.shade.hits import sample_colours, shade_camera_hits
from render.shade.lighting import shade_mesh, shade_surface
from render.shade.mirrors import Mirrors
from render.trace.raster import rasterise_camera_rays
from render.trace.visibility import trace_visibility

__all__ = ["render", "RenderInfo", "shade_mesh", "shade_surface"]


def render(
    scene: Scene,
    bvh: bool = True,
    shadows: bool = True,
    spp: int = 1,
    reuse_visibility: bool = True,
    return_info: bool = False,
    antialias: bool | str = False,
    max_bounces: int = 2,
    primary: str = "auto",
    integrator: str = "direct",
    interior_samples: int = INTERIOR_SAMPLES,
    **path_options,
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
        their coverage, on the tape (``render/edges/``), so that moving edges have
        gradients. False (the default, the paper's renderer): every sample shows the
        primitive at its centre, the image is a step function at edges and their motion
        has no gradient. See the README for why False is the default and when to switch
        it on.
        True or "pairs": as just said. "boundary": silhouettes, creases, the lines where
        surfaces intersect and shadow borders get the exact edge derivative of
        box-filtered pixels instead (``render.edges.boundary``: the boundary integral, one
        curve kind per kind of discontinuity), and pixels whose box is mixed become the
        mean of ``interior_samples`` samples, in value and derivative
        (``render.edges.interior``; the other pixels are the plain image's).
    max_bounces: how many mirror reflections a camera ray may take (RayTracer.jl's depth:
        the camera hit plus two reflections); 0 turns reflection off. Only hits on a
        material with a non-zero (or differentiated) ``reflectance`` spawn a mirror ray.
    primary: how the camera rays' hits are found: "bvh" traces them through the BVH,
        "raster" rasterises the primitives (``render.trace.raster``; the same hits bit for
        bit, faster while there are many rays per primitive), "auto" (default) rasterises
        when there are at least 16 camera rays per primitive
        (``render.trace.raster.RASTER_RAYS_PER_PRIMITIVE``). With ``bvh=False`` both are
        brute force.
    interior_samples: with "boundary", a mixed pixel's samples, its value and interior
        term (``render.edges.interior``); at most ``spp``: its own (~3x faster at 512x512).

    integrator: "direct" (default): the renderer above, the paper's; "path": a Monte Carlo
        path tracer with area lights (emissive materials), indirect light and the
        background as a constant environment (``render.path.render_path``: ``spp`` paths
        per pixel, any integer >= 1, and its options ``max_depth``, ``seed``,
        ``rr_depth``, ``batch_spp``, ``edge_spp`` as keywords; ``antialias`` may be
        False or "boundary" (primary visibility's boundary term, ``render.path.edges``);
        the other options above belong to the direct renderer and must keep their
        defaults).

    Every parameter of the scene that is a ``requires_grad`` tensor receives its gradient
    when the caller runs ``backward`` on a loss computed from the image (zeros where the
    image cannot depend on it, whichever route computed the image).
    """
    if not isinstance(scene, Scene):
        raise TypeError(f"render: scene must be a render.Scene, got {type(scene).__name__}")
    if integrator == "path":
        _check_direct_defaults(bvh, shadows, return_info, max_bounces, primary, interior_samples)
        return render_path(scene, spp, antialias=antialias, **path_options)
    if integrator != "direct":
        raise ValueError(f'render: integrator must be "direct" or "path", got {integrator!r}')
    if path_options:
        raise TypeError(
            f'render: {", ".join(sorted(path_options))} only apply to integrator="path"'
        )
    scene.validate()
    subpixel_offsets(spp)  # a clear error for a bad spp before anything else
    check_ray_count(scene.camera.width, scene.camera.height, spp)
    antialias = _check_antialias(antialias)
    inner = check_interior_samples(interior_samples)  # a mixed pixel's interior samples
    max_bounces = _check_bounces(max_bounces)
    raster = rasterise_camera_rays(scene, primary, spp) and bool(bvh)
    cache = cache_for(scene, reuse_visibility)
    world = placed(scene)  # 0: transformed objects in world space, on the tape

    visibility = trace_visibility(world, cache, bool(bvh), spp, bool(shadows), raster)  # 1
    pairs = antialias == "pairs"  # the pairs' shadow terms shade the hits' surfaces again
    route, mirrors, edges = adjoint.route(world, pairs, max_bounces), None, None
    if route == "fused":  # 2, 3, 5 in compiled passes: nothing is differentiated, no tape
        values, texel = fused.image_values(world, visibility, plain_frame(world.camera), spp)
        image = md.Tensor(values)  # no copy
    else:
        frame = camera_frame(world.camera)
        if route == "node":  # 2, 3, 5 as one node: compiled forward, hand-written adjoint
            image, texel = adjoint.image(world, visibility, frame, spp), None
        else:
            mirrors = Mirrors.of(world, visibility, max_bounces)
            shading = shade_camera_hits(world, visibility, frame, cache, mirrors, pairs)  # 2, 3
            prim_id, texel = visibility.primary.prim_id, shading.texel
            if pairs:
                samples = sample_colours(world, prim_id, shading.colour, shading.rays)
                samples, edges = add_edge_terms(world, visibility, cache, samples, shading,
                                                frame, spp)  # 4  # fmt: skip
                image = pixel_means(world, samples, spp)  # 5
            else:
                image = image_from_hits(world, prim_id, shading.colour, shading.rays, spp)  # 5
    if antialias == "boundary":  # 4': mixed pixels from their 16 samples, on every route
        frame = camera_frame(world.camera) if route == "fused" else frame
        image = antialias_mixed_pixels(world, visibility, image, frame, spp, max_bounces, inner)
        if differentiated(scene):  # the boundary term: zero in value
            image = add_boundary_term(world, visibility, cache, image, frame, max_bounces)
    image = terms.on_every_parameter(image, scene)  # zeros for what the image cannot depend on
    if not return_info:
        return image
    return image, RenderInfo.of(world, visibility, texel, spp, mirrors, edges)


def _check_direct_defaults(bvh, shadows, return_info, max_bounces, primary, interior) -> None:
    """The path integrator has its own answers to these: refuse rather than ignore them."""
    given = {"bvh": bvh is not True, "shadows": shadows is not True,
             "return_info": return_info is not False, "max_bounces": max_bounces != 2,
             "primary": primary != "auto",
             "interior_samples": interior != INTERIOR_SAMPLES}  # fmt: skip
    changed = [name for name, differs in given.items() if differs]
    if changed:
        raise ValueError(
            f'render: {", ".join(changed)} belong to integrator="direct"; the path integrator '
            "traces with the BVH, always shadows, and bounces up to its max_depth (see "
            "docs/path_tracing.md)"
        )


def _check_antialias(value) -> str | None:
    """None (no edge terms), "pairs" or "boundary"; True means "pairs"."""
    if isinstance(value, bool | np.bool_):
        return "pairs" if value else None
    if value in ("pairs", "boundary"):
        return value
    raise ValueError(f'render: antialias must be True, False, "pairs" or "boundary", got {value!r}')


def _check_bounces(value) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 0:
        raise ValueError(f"render: max_bounces must be an integer >= 0, got {value!r}")
    return int(value)


@dataclass
class RenderInfo:
    """The discrete decisions behind an image (constants on the tape), per ray.

    prim_id (H, W, spp) int64: the primitive each ray hit (-1: background).
    lit (n_lights, H, W, spp) bool: light j reaches the ray's hit point unoccluded.
    texel (H, W, spp) int64: the cell of the bilinear texture lookup at the hit
        (``render.shade.lighting.texel_cell``; -1 where the hit surface is untextured or missed).
    pairs: with ``antialias=True``, the pairs of adjacent samples across a silhouette and
        the edge each one uses (``render.edges.silhouettes.EdgePairs``, ray ids r = pixel * spp +
        sample); None without (and with ``antialias="boundary"``, which integrates them).
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
    def of(cls, scene, visibility, texel, spp: int, mirrors, edges: EdgeDecisions | None):
        """The per-ray arrays of one render (``render.trace.visibility.Visibility``; texel
        (N,), None if no ray hit a textured surface; the ``Mirrors`` or None; the edge
        pairs or None), shaped (H, W, spp)."""
        camera, primary = scene.camera, visibility.primary
        record = None if mirrors is None else mirrors.record
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
            None if edges is None else edges.silhouettes,
            None if edges is None else edges.shadows,
            [] if record is None else [ids.reshape(shape) for ids in record.hit_ids],
            [] if record is None else [m.reshape(lit.shape[:1] + shape) for m in record.lit],
        )
