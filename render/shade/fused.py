"""Steps 2, 3 and 5 without the tape, for a render that nothing differentiates.

``shade_camera_hits`` then ``image_from_hits`` shade the camera hits object by object and
average them into pixels with a dozen NumPy passes between the shading and the film:
gathering each object's hits, their image-plane points and lit masks, scattering the
colours into pixels, counting the misses. When nothing is differentiated and every object
is a mesh the compiled shading takes (``applies``), ``image_values`` does the same in
fewer passes over plain arrays:

1. every mesh's hits shaded by ``shade_camera_hits``, whose meshes all take the compiled
   shading here (``render.shade.compiled.shade_mesh``), copied into a per-ray buffer;
2. ``_film``: every pixel (in parallel) the mean of its samples, the background where a
   sample hit nothing.

Every ray's and pixel's arithmetic is done by one thread, in a fixed order, so the image
does not depend on the number of threads. It equals the taped pipeline's to rounding (a
pixel's samples are summed in sample order rather than in the tape's scatter order, which
only matters for spp > 1); ``tests/render/shade/test_fused.py`` ties the two together.
"""

from __future__ import annotations

import numpy as np

import minidiff as md
from minidiff import buffers
from minidiff.threads import job_count, kernel, run_jobs, share
from render.scene.cache import RenderCache
from render.scene.scene import Scene
from render.shade import compiled
from render.shade.hits import shade_camera_hits
from render.trace.visibility import Visibility


def applies(scene: Scene, max_bounces: int) -> bool:
    """Whether ``image_values`` renders ``scene``: nothing differentiated (no parameter
    requires grad while gradients are enabled, none carries a tangent), and every object a
    mesh that ``compiled.applies`` to (float64, untextured, lights it shades, no mirror ray
    leaving it with ``max_bounces``)."""
    grad = md.is_grad_enabled()
    if any(p.tangent is not None or (grad and p.requires_grad) for p in scene.parameters()):
        return False
    if scene.spheres:
        return False
    return all(
        compiled.applies(scene, mesh, max_bounces > 0 and mesh.material.reflective)
        for mesh in scene.meshes
    )


def image_values(scene: Scene, visibility: Visibility, camera: tuple, spp: int) -> np.ndarray:
    """The (H, W, 3) float64 image of ``scene`` from its ``visibility`` (camera rays
    ``spp`` per pixel, their hits and lit masks). ``camera``: (forward, right, up, eye)
    float64 (3,) each, the camera frame's values. Only where ``applies``."""
    primary = visibility.primary
    with md.no_grad():  # every mesh shaded by the compiled shading (``applies``)
        shading = shade_camera_hits(scene, visibility, camera, RenderCache(), None, False)
    radiance = buffers.empty((primary.prim_id.size, 3), np.float64)
    if shading.colour is not None:
        radiance[shading.rays] = shading.colour.data
    # Reused memory (minidiff.buffers): a fresh 512x512 image costs ~1.5 ms of page faults.
    image = buffers.empty((scene.camera.height, scene.camera.width, 3), np.float64)
    background = np.broadcast_to(np.asarray(scene.background.data, np.float64), (3,))
    pixels = image.reshape(-1, 3)
    run_jobs(_film, job_count(len(pixels), 65536), primary.prim_id, radiance, spp,
             np.ascontiguousarray(background), pixels)  # fmt: skip
    return image


@kernel
def _film(job, n_jobs, prim_id, radiance, spp, background, image):
    """Job ``job`` of ``n_jobs`` (``minidiff.threads.run_jobs``): each pixel of its
    contiguous share (rows of ``image`` (H * W, 3)) the mean of its ``spp`` samples'
    radiance (N, 3), ``background`` (3,) where a sample's ``prim_id`` (N,) is -1: the
    samples summed in order, times 1 / spp. (Every pixel costs the same: a contiguous share
    streams through memory, where blocks dealt in turn took 0.79 against 0.53 ms at 512x512
    on 2 threads.)"""
    scale = 1.0 / spp
    first, stop = share(job, n_jobs, image.shape[0])
    for p in range(first, stop):
        for c in range(3):
            total = 0.0
            for s in range(spp):
                r = p * spp + s
                value = background[c] if prim_id[r] < 0 else radiance[r, c]
                total = value if s == 0 else total + value
            image[p, c] = total if spp == 1 else total * scale
