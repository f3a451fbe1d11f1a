"""Primary visibility's boundary term for the path integrator.

The camera's silhouettes, creases, the outlines of spheres and the lines where surfaces
cross move with the geometry and the camera; a pixel's integral over them has a boundary
term (``render.edges.boundary``: for every point x on an edge, the jump f_+(x) - f_-(x)
of what the camera sees on either side, times how fast the edge moves across x). The
direct renderer's jump is its own shading on either side; here it is the path-traced
radiance of the camera rays through the two sides, estimated with ``samples`` paths each.

Both sides of one quadrature point draw the same random numbers (common random numbers:
their difference has far less noise than two independent estimates), and the path ids come
after those of the image (pixel x spp + sample), so that the jumps are independent of the
image's own samples. The estimate of each jump is unbiased, so the boundary term is; it is
added to the image with value zero, as the direct renderer's is.

Secondary visibility's boundary terms (soft shadows, lights' shadows, indirect occlusion)
are ``render.path.boundary.secondary``'s.
"""

from __future__ import annotations

import numpy as np

import minidiff as md
from render.edges.boundary.occlusion import Occluders
from render.edges.boundary.radiance import first_hits
from render.edges.boundary.shadow_border import plane_depth
from render.edges.boundary.term import add_curve_terms
from render.edges.terms import primary_kinds
from render.path.gradient.replay import radiance_of
from render.path.sample.tracer import PathSampler
from render.scene.cache import cache_for
from render.scene.camera import project, to_image_plane
from render.scene.scene import Scene
from render.trace.visibility import scene_size

#: Paths traced at once when estimating jumps (bounds the memory of one estimate).
CHUNK_PATHS = 1 << 17
#: How far towards its triangle's centroid an edge point's path starts (a fraction), and
#: on an edge whose faces may have come apart across a crack (``beside`` given).
INSIDE = 1e-6
PAST_CRACK = 1e-2


class PathRadiance:
    """What the camera sees through image-plane points, by path tracing: the path
    integrator's ``render.edges.boundary.radiance.SideRadiance``.

    world: the scene in world space; frame: its camera frame; sampler: the render's
    ``PathSampler`` (its BVH, emitters, seed, max_depth); samples: paths per side of each
    point; first_id: the path id of key 0's first sample (ids ``first_id + key * samples +
    s``, s < samples)."""

    def __init__(self, world: Scene, frame, sampler: PathSampler, samples: int, first_id: int):
        self.world, self.frame, self.sampler = world, frame, sampler
        self.samples, self.first_id = samples, first_id

    def seen(self, coords: np.ndarray, prim_id: np.ndarray, depth: np.ndarray, key: np.ndarray,
             beside: np.ndarray | None = None, shadowed: np.ndarray | None = None,
             ) -> np.ndarray:  # fmt: skip
        """(k, 3): the mean radiance of ``samples`` paths per camera ray through ``coords``
        (k, 2) that first meets primitive ``prim_id`` (k,) (-1: none) at ``depth`` (k,).
        The paths start inside their triangles (``_inside``), off the faces of the edge,
        and farther in on the edges whose faces ``beside`` (k, m) may have come apart;
        from there their shadow rays find the edge's own shadow themselves (``shadowed``
        is not needed)."""
        cracked = np.zeros(len(coords), bool) if beside is None else np.any(beside >= 0, axis=1)
        coords, depth = self._inside(coords, prim_id, depth, cracked)
        return self._estimate(coords, key, prim_id, depth)

    def _inside(self, coords, prim, depth, cracked) -> tuple[np.ndarray, np.ndarray]:
        """The image-plane points (k, 2) and depths (k,) of the edge points moved
        ``INSIDE`` of the way towards their triangles' centroids (``PAST_CRACK`` where
        ``cracked`` (k,), and onto the triangle's plane). An edge point is exactly on its
        triangle's border: where two walls meet, a path bouncing off it would start on the
        other wall (a zero-length segment); just inside, it is the limit f_+ or f_- is.
        Across a crack (meshes welded within ``seam_distance``), the other face may
        overhang the triangle near the edge, and the edge point lies off the triangle's
        plane: a path started there was in that face's shadow (a box in meshes moved 4e-6
        apart had its translation's gradient 9 % off the one box's, 17 standard errors)."""
        forward, right, up, eye = self.sampler.frame
        coords, depth = coords.copy(), depth.copy()
        rows = np.flatnonzero((prim >= 0) & (prim < self.sampler.n_triangles))
        points = eye + depth[rows, None] * (
            coords[rows, :1] * right + coords[rows, 1:] * up + forward
        )
        triangles = self.sampler.primitives[0][prim[rows]]
        centroid = triangles.mean(axis=1)
        fraction = np.where(cracked[rows], PAST_CRACK, INSIDE)[:, None]
        camera = self.world.camera
        px, depth[rows] = project(
            points + fraction * (centroid - points), (forward, right, up, eye), camera.width,
            camera.height,
        )  # fmt: skip
        coords[rows] = to_image_plane(px, camera.width, camera.height)
        far = np.flatnonzero(cracked[rows])
        if len(far):  # the depth of the triangle's plane there
            tri, at = triangles[far], rows[far]
            d = forward + coords[at, :1] * right + coords[at, 1:] * up
            normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            depth[at] = plane_depth(normal, tri[:, 0], eye, d)
        return coords, depth

    def along(
        self, coords: np.ndarray, key: np.ndarray, beside: np.ndarray | None = None
    ) -> np.ndarray:
        """(k, 3): the mean radiance of ``samples`` paths per camera ray through ``coords``
        (k, 2), its first hit traced (past the faces ``beside``, where given, as
        ``render.edges.boundary.radiance.first_hits`` traces them)."""
        if beside is None or not np.any(beside >= 0):
            return self._estimate(coords, key)
        prim, depth = first_hits(self.world, self.sampler.accelerator, coords, beside)
        return self._estimate(coords, key, prim, depth)

    def _estimate(self, coords, key, prim=None, depth=None) -> np.ndarray:
        n = self.samples
        out = np.zeros((len(coords), 3))
        step = max(1, CHUNK_PATHS // n)
        for start in range(0, len(coords), step):
            rows = slice(start, start + step)
            k = len(coords[rows])
            paths = (self.first_id + key[rows, None] * n + np.arange(n)[None, :]).ravel()
            given = () if prim is None else (np.repeat(prim[rows], n), np.repeat(depth[rows], n))
            batch = self.sampler.start(paths, np.repeat(coords[rows], n, axis=0), *given)
            radiance = radiance_of(self.world, self.frame, self.sampler, batch)
            out[rows] = radiance.reshape(k, n, 3).mean(axis=1)
        return out


def add_path_boundary_term(
    scene: Scene, world: Scene, image: md.Tensor, frame, sampler: PathSampler, samples: int
) -> md.Tensor:
    """The image (H, W, 3) plus the boundary term of primary visibility (zero in value),
    its jumps estimated with ``samples`` paths per side. ``scene``: the user's scene (its
    render cache keeps the mesh topology); ``world``: it placed in world space, on the tape,
    with ``frame`` its camera frame; ``sampler``: the render's."""
    cache = cache_for(scene, True)
    primitives = sampler.primitives
    _, geometry = cache.get("geometry", list(primitives), lambda: None)  # its stamp
    # The sampler's primitives and BVH answer the occlusion rays; no camera ray was traced
    # for the edges (no ``camera_prims``).
    accelerator = sampler.accelerator
    occluders = Occluders(primitives, scene_size(primitives), lambda: accelerator, True, geometry)
    camera = world.camera
    first_id = camera.width * camera.height * sampler.spp  # after the image's path ids
    radiance = PathRadiance(world, frame, sampler, samples, first_id)
    kinds = primary_kinds(world, occluders, cache)
    return add_curve_terms(world, occluders, image, frame, radiance, kinds)
