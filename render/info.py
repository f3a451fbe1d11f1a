"""``RenderInfo``: the discrete decisions behind one image of the direct renderer, per ray
(constants on the tape), which ``render(scene, return_info=True)`` returns beside it."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from render.edges.shadows import ShadowPairs
from render.edges.silhouettes import EdgePairs
from render.edges.terms import EdgeDecisions


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
