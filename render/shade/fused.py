"""Steps 2, 3 and 5 in two compiled passes, for a render that nothing differentiates.

``shade_camera_hits`` then ``image_from_hits`` shade the camera hits object by object and
average them into pixels with a dozen NumPy passes between the compiled shading and the
film: gathering each object's hits, their image-plane points and lit masks, scattering the
colours into pixels, counting the misses. When no tape is needed and every object is a
mesh that ``render.shade.compiled`` shades (``applies``), ``image_values`` does the same
in two parallel passes over plain arrays:

1. ``_shade_rays``: every hit row (in parallel), on the mesh its primitive belongs to
   (one call per mesh), shaded by ``compiled.shade_hit`` into a per-ray buffer;
2. ``_film``: every pixel (in parallel) the mean of its samples, the background where a
   sample hit nothing.

Every ray's and pixel's arithmetic is done by one thread, in a fixed order, so the image
does not depend on the number of threads. It equals the taped pipeline's to rounding (the
same per-hit arithmetic as ``compiled.shade_mesh_values``; a pixel's samples are summed in
sample order rather than in the tape's scatter order, which only matters for spp > 1);
``tests/render/shade/test_fused.py`` ties the two together.
"""

from __future__ import annotations

import numba
import numpy as np

from minidiff import buffers
from render.scene.scene import Scene
from render.shade import compiled
from render.trace.intersect import BLOCK, _jobs
from render.trace.primitives import primitive_ranges
from render.trace.visibility import Visibility


def applies(scene: Scene, max_bounces: int) -> bool:
    """Whether ``image_values`` renders ``scene``: every object a mesh that
    ``compiled.applies`` to (float64, lights it shades, nothing differentiated while
    gradients are enabled, no mirror ray leaving it with ``max_bounces``)."""
    if scene.spheres:
        return False
    return all(
        compiled.applies(scene, mesh, max_bounces > 0 and mesh.material.reflective)
        for mesh in scene.meshes
    )


def image_values(
    scene: Scene, visibility: Visibility, camera: tuple, spp: int
) -> tuple[np.ndarray, np.ndarray | None]:
    """The (H, W, 3) float64 image of ``scene`` from its ``visibility`` (camera rays
    ``spp`` per pixel, their hits and lit masks), and the texture cell (N,) int64 of every
    ray (-1: none; None if no ray hit a textured mesh). ``camera``: (forward, right, up,
    eye) float64 (3,) each, the camera frame's values. Only where ``applies``."""
    primary = visibility.primary
    n_rays = primary.prim_id.size
    radiance = buffers.empty((n_rays, 3), np.float64)
    lit = np.empty((len(visibility.lit), len(primary.hit_rays)))
    for j, mask in enumerate(visibility.lit):
        lit[j] = mask
    texel = None
    forward, right, up, eye = camera
    threads = numba.get_num_threads()
    lights = compiled.lights_pack(scene.lights)
    for obj, first, count in primitive_ranges(scene):
        textured = obj.material.texture is not None
        if textured and texel is None:
            texel = np.full(n_rays, -1, np.int64)
        _shade_rays(
            primary.prim_id, primary.hit_rays, primary.coords, first, count,
            (eye, right, up, forward), compiled.mesh_pack(obj),
            compiled.material_pack(obj.material), lights, lit, threads, radiance,
            texel if textured else np.empty(0, np.int64),
        )  # fmt: skip
    # Reused memory (minidiff.buffers): a fresh 512x512 image costs ~1.5 ms of page faults.
    image = buffers.empty((scene.camera.height, scene.camera.width, 3), np.float64)
    background = np.broadcast_to(np.asarray(scene.background.data, np.float64), (3,))
    _film(primary.prim_id, radiance, spp, np.ascontiguousarray(background), threads,
          image.reshape(-1, 3))  # fmt: skip
    return image, texel


@numba.njit(cache=True, error_model="numpy", parallel=True)
def _shade_rays(
    prim_id, hit_rays, coords, first, count, camera, mesh, material, lights, lit, n_threads,
    radiance, texel,
):  # fmt: skip
    """``compiled.shade_hit`` of every hit row i whose primitive lies in [first, first +
    count) (one mesh), written to row ``hit_rays[i]`` of ``radiance`` (N, 3) (and of
    ``texel`` (N,) unless it is empty); ``lit`` (L, k) the lit masks of the k hit rows."""
    k = hit_rays.shape[0]
    n_blocks, n_jobs = _jobs(k, n_threads)
    for job in numba.prange(n_jobs):
        for block in range(job, n_blocks, n_jobs):
            for i in range(block * BLOCK, min(k, (block + 1) * BLOCK)):
                r = hit_rays[i]
                face = prim_id[r] - first
                if face < 0 or face >= count:
                    continue
                cell = compiled.shade_hit(
                    coords[i, 0], coords[i, 1], camera, mesh, face, material, lights,
                    lit, i, radiance, r,
                )  # fmt: skip
                if texel.shape[0] > 0:
                    texel[r] = cell


@numba.njit(cache=True, error_model="numpy", parallel=True)
def _film(prim_id, radiance, spp, background, n_threads, image):
    """Every pixel (row of ``image`` (H * W, 3)) the mean of its ``spp`` samples' radiance
    (N, 3), ``background`` (3,) where a sample's ``prim_id`` (N,) is -1: the samples summed
    in order, times 1 / spp."""
    n = image.shape[0]
    scale = 1.0 / spp
    n_blocks, n_jobs = _jobs(n, n_threads)
    for job in numba.prange(n_jobs):
        for block in range(job, n_blocks, n_jobs):
            for p in range(block * BLOCK, min(n, (block + 1) * BLOCK)):
                for c in range(3):
                    total = 0.0
                    for s in range(spp):
                        r = p * spp + s
                        value = background[c] if prim_id[r] < 0 else radiance[r, c]
                        total = value if s == 0 else total + value
                    image[p, c] = total if spp == 1 else total * scale
