"""The truth edge gradients are checked against: box-filtered pixels by jittered supersampling.

``render(scene, spp=n*n)`` samples every pixel on the same fixed n x n grid. That is right
for a differentiable image, but wrong for a reference of edge derivatives: an image edge
parallel to the grid (the rim of a teapot seen level) crosses the rows of samples of every
pixel along it at the same phase, so a central difference of two such renders counts whole
rows of samples at once and its error does not average out along the edge (at 64x64 the
teapot's vertical-translation derivative moved between 70.3 and 76.3 with the step h, at
1,024 and 4,096 samples). Here each of the n x n cells of each pixel gets its own uniform
jitter, drawn from a generator seeded by (seed, row): the same seed gives the same sample
positions, so the two renders of a central difference are correlated, and the error of a
counted row is random from pixel to pixel and averages out.

The rays are traced with the scene's accelerator and shaded as the renderer's camera rays
(``render.edges.boundary.DirectRadiance.along``: shadows and mirrors included), in batches.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

import minidiff as md
from render.edges.boundary.radiance import DirectRadiance
from render.renderer import render
from render.scene.cache import RenderCache
from render.scene.camera import camera_frame, subpixel_offsets, to_image_plane
from render.scene.placement import placed
from render.scene.scene import Scene
from render.trace.visibility import trace_visibility

#: Rays traced and shaded at once (bounds the memory, ~1 KiB per ray).
BATCH = 1 << 19


def supersampled_image(
    scene: Scene,
    spp: int = 1024,
    seed: int = 0,
    shadows: bool = True,
    max_bounces: int = 2,
    pixels: np.ndarray | None = None,
) -> np.ndarray:
    """The box-filtered image of ``scene``, (H, W, 3) float64 (off the tape), each pixel the
    mean of ``spp`` (a perfect square) jittered stratified samples.

    pixels: flat pixel indices (row * W + column), to compute only those: then the result
        is (k, 3) in that order. A pixel's samples do not depend on which others are asked
        for, so a difference of two calls is correlated pixel by pixel.
    """
    if not isinstance(scene, Scene):
        raise TypeError(f"supersampled_image: scene must be a render.Scene, got {scene!r}")
    scene.validate()
    with md.no_grad():  # objects with a Transform drawn where render draws them
        scene = placed(scene)
    cells = subpixel_offsets(spp)  # (spp, 2) stratum centres; a clear error for a bad spp
    n = int(round(np.sqrt(spp)))
    camera = scene.camera
    width, height = camera.width, camera.height
    whole = pixels is None
    pixels = np.arange(width * height) if whole else np.asarray(pixels)
    if (
        pixels.ndim != 1
        or pixels.dtype.kind not in "iu"
        or not np.all((pixels >= 0) & (pixels < width * height))
    ):
        raise ValueError(
            f"supersampled_image: pixels must be flat pixel indices in [0, {width * height}), "
            f"got {pixels!r}"
        )
    visibility = trace_visibility(scene, RenderCache(), True, 1, bool(shadows))
    frame = camera_frame(scene.camera)
    rows, cols = pixels // width, pixels % width
    out = np.empty((len(pixels), 3))
    per_batch = max(1, BATCH // spp)
    for lo in range(0, len(pixels), per_batch):
        hi = min(lo + per_batch, len(pixels))
        jitter = _jitter(seed, rows[lo:hi], cols[lo:hi], width, spp)  # (k, spp, 2)
        positions = cells[None] + (jitter - 0.5) / n  # inside each cell
        px = np.stack([cols[lo:hi], rows[lo:hi]], axis=1)[:, None, :] + positions
        coords = to_image_plane(px.reshape(-1, 2), width, height)
        key = np.arange(len(coords))  # DirectRadiance names points but does not use the names
        radiance = DirectRadiance(scene, visibility, frame, max_bounces).along(coords, key)
        out[lo:hi] = radiance.reshape(hi - lo, spp, 3).mean(axis=1)
    return out.reshape(height, width, 3) if whole else out


def _jitter(seed: int, rows: np.ndarray, cols: np.ndarray, width: int, spp: int) -> np.ndarray:
    """(k, spp, 2) uniform jitter in [0, 1) for the pixels (rows, cols): one stream per
    image row, seeded by (seed, row), so a pixel's jitter is the same whoever asks."""
    out = np.empty((len(rows), spp, 2))
    for row in np.unique(rows):
        mine = rows == row
        stream = np.random.default_rng([int(seed), int(row)]).random((width, spp, 2))
        out[mine] = stream[cols[mine]]
    return out


def moved_along(
    build: Callable[[], Scene], tensor_of: Callable[[Scene], md.Tensor], direction: np.ndarray
) -> Callable[[float], tuple[Scene, md.Tensor, np.ndarray]]:
    """``make_scene`` for ``window_difference`` and ``window_mean_gradient``: s -> (a fresh
    scene from ``build()`` with the tensor ``tensor_of(scene)`` moved by s * direction,
    that tensor, the direction)."""

    def make(s: float):
        scene = build()
        tensor = tensor_of(scene)
        with md.no_grad():
            tensor.data[...] = tensor.data + s * direction
        return scene, tensor, direction

    return make


def window_difference(
    make_scene: Callable[[float], tuple[Scene, md.Tensor, np.ndarray]],
    weights: np.ndarray,
    h: float,
    spp: int = 1024,
    seed: int = 0,
    shadows: bool = True,
    pixels: np.ndarray | None = None,
) -> float:
    """(L(h) - L(-h)) / 2h for L(s) = sum(weights * image(s)), the supersampled image of
    ``make_scene(s)``: the scene moved by s along a direction, with the tensor moved and
    the direction (only the scene is used here). ``pixels``: flat indices of the only
    pixels that can change (the caller's claim, e.g. around a lone object on a black
    background); the others are left out of both sides."""
    w = weights if pixels is None else weights.reshape(-1, weights.shape[-1])[pixels]
    values = [
        float(np.sum(w * supersampled_image(make_scene(s)[0], spp, seed, shadows, pixels=pixels)))
        for s in (h, -h)
    ]
    return (values[0] - values[1]) / (2.0 * h)


def window_mean_gradient(
    make_scene: Callable[[float], tuple[Scene, md.Tensor, np.ndarray]],
    weights: np.ndarray,
    h: float,
    antialias: bool | str,
    points: int = 16,
    spp: int = 1,
    shadows: bool = True,
) -> float:
    """The mean over s in [-h, h] (``points`` midpoints) of dL/ds, L(s) = sum(weights *
    render(make_scene(s))) differentiated by one backward pass. Its integral over the
    window is L(h) - L(-h): so it equals ``window_difference`` when the gradient is the
    derivative of the box-filtered image, whatever h (a large h makes the supersampled
    difference precise)."""
    total = 0.0
    for k in range(points):
        scene, tensor, direction = make_scene(-h + (k + 0.5) * 2.0 * h / points)
        tensor.requires_grad, tensor.grad = True, None
        image = render(scene, spp=spp, shadows=shadows, antialias=antialias, reuse_visibility=False)
        if image.requires_grad:  # else nothing seen depends on the tensor here: dL/ds = 0
            (image * weights).sum().backward()
            total += float(np.sum(tensor.grad * direction))
    return total / points
