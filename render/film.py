"""Step 5, the film: the (H, W, 3) image from the samples' colours.

Ray r belongs to pixel r // spp; a pixel is the mean of its ``spp`` samples, and a sample
that hit nothing shows the scene's background. Two builders, for the two shapes the colours
arrive in: ``image_from_hits`` takes the colours of the rays that hit (k, 3), as steps 2-3
give them, and adds them straight into pixels; with edge terms the colours of all samples
(N, 3) are needed first (``render.shade.hits.sample_colours``, kept there because the
boundary mode's interior samples need it too; the edge terms blend neighbouring samples),
then ``pixel_means``.
"""

from __future__ import annotations

import numpy as np

import minidiff as md
from render.scene.scene import Scene
from render.shade.hits import working_dtype


def image_from_hits(scene: Scene, prim_id: np.ndarray, colour, rays: np.ndarray, spp: int):
    """The (H, W, 3) image: each pixel the mean of its samples' colours, misses showing the
    background. colour (k, 3) (None: nothing was hit) of the rays ``rays`` (k,); prim_id
    (N,) every ray's primitive (-1: background)."""
    camera = scene.camera
    n_pixels = camera.width * camera.height
    image = None
    if colour is not None:
        image = md.scatter_add(colour, rays // spp, n_pixels)
        if spp > 1:
            image = image * (1.0 / spp)
    background = scene.background
    if image is None or background.is_differentiated() or np.any(background.data):
        misses = np.bincount(np.flatnonzero(prim_id < 0) // spp, minlength=n_pixels)
        fill = (misses / spp).astype(working_dtype(scene))[:, None] * background
        image = fill if image is None else image + fill
    return md.reshape(image, (camera.height, camera.width, 3))


def pixel_means(scene: Scene, samples: md.Tensor, spp: int) -> md.Tensor:
    """(H, W, 3) image: the mean of each pixel's spp consecutive samples (N, 3)."""
    camera = scene.camera
    if spp > 1:
        pixel = np.arange(samples.shape[0]) // spp
        samples = md.scatter_add(samples, pixel, camera.width * camera.height) * (1.0 / spp)
    return md.reshape(samples, (camera.height, camera.width, 3))
