"""Widening the basin: a coarse-to-fine schedule and a search stage before the gradients.

A local optimiser follows the image loss downhill from where it starts; it cannot find an
object that is not in view, and from far away it settles in whatever pose makes the
silhouettes overlap best. Two standard remedies, both explicit options here:

* ``coarse_to_fine``: optimise first against small images (each pixel of the target the
  mean of a block of the full-size one: a blurred, downsampled loss whose minimum is wider
  and smoother), then at the next size, up to the full one, continuing from where the
  previous stage ended. Each stage is a plain ``optimize``.
* ``greedy_search``: before any gradient, try random proposals around the best parameters
  so far at a low resolution and keep a proposal when it lowers the loss (NVlabs'
  nvdiffrast pose sample spends the first half of its iterations this way). Its cost is
  stated, not hidden: ``SearchResult.renders`` counts the renders, ``seconds`` their time,
  and the experiments add both to what they report.
* ``multi_start``: a few short, cheap runs of the gradients from several starts (the given
  one and turned copies of it), each at a low resolution with a cheaper edge method, and
  keep the one whose loss ends lowest. Unlike the greedy search, every candidate has
  descended before it is judged, so that a start in the right basin is compared at (near)
  its minimum, not at a proposal's raw loss.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

import minidiff as md
from render.inverse.optimize import History, image_loss, optimize
from render.renderer import render
from render.scene.scene import Camera, Scene


def resized(scene: Scene, width: int, height: int) -> Scene:
    """The same scene seen by a camera of another image size: the camera's *tensors* are
    shared (a gradient reaching the small view's camera reaches the original's), and so
    are the objects and lights (``Scene.with_camera``)."""
    c = scene.camera
    return scene.with_camera(Camera(c.position, c.look_at, c.up, c.fov, width, height))


def downsample(image: np.ndarray, factor: int) -> np.ndarray:
    """(H / factor, W / factor, C) block means of an (H, W, C) image: what a camera with
    ``factor`` times fewer pixels per side, each averaging the light over its area, records
    (a box filter). ValueError unless ``factor`` divides H and W."""
    image = np.asarray(image, dtype=np.float64)
    h, w = image.shape[:2]
    if isinstance(factor, bool) or not isinstance(factor, int | np.integer) or factor < 1:
        raise ValueError(f"downsample: factor must be an int >= 1, got {factor!r}")
    if h % factor or w % factor:
        raise ValueError(f"downsample: factor {factor} does not divide the image size {h}x{w}")
    return image.reshape(h // factor, factor, w // factor, factor, -1).mean(axis=(1, 3))


def coarse_to_fine(
    scene: Scene,
    params: Sequence[md.Tensor],
    target: np.ndarray,
    factors: Sequence[int] = (4, 2, 1),
    iters: Sequence[int] = (100, 100, 100),
    **optimize_kwargs,
) -> list[History]:
    """``optimize`` once per downsampling factor, coarsest first: stage k renders ``scene``
    at 1/factors[k] of its size (``resized``) against the block-mean target
    (``downsample``), for iters[k] iterations. Every stage gets its own optimiser state
    (Adam's moments belong to one loss). ``optimize_kwargs`` go to every stage (``lr``,
    ``render_kwargs``, ...). Returns the stages' histories."""
    if len(factors) != len(iters) or not factors:
        raise ValueError("coarse_to_fine: factors and iters must be non-empty and of one length")
    if "optimizer" in optimize_kwargs:
        raise TypeError("coarse_to_fine: each stage makes its own optimiser; pass lr instead")
    target = np.asarray(target, dtype=np.float64)
    histories = []
    for factor, n in zip(factors, iters, strict=True):
        small = downsample(target, factor)
        view = scene if factor == 1 else resized(scene, small.shape[1], small.shape[0])
        _, history = optimize(view, params, small, max_iters=n, **optimize_kwargs)
        histories.append(history)
        if history.converged:
            break
    return histories


@dataclass
class SearchResult:
    """What ``greedy_search`` did: the loss at the start and at the end (at its low
    resolution), the renders it made, their wall time, and each accepted proposal's
    render number and loss."""

    start_loss: float
    loss: float
    renders: int
    seconds: float
    accepted: list[tuple[int, float]] = field(default_factory=list)


#: propose(rng, best values, progress in [0, 1)) -> new values for the parameters
Proposal = Callable[[np.random.Generator, list[np.ndarray], float], list[np.ndarray]]


def greedy_search(
    scene: Scene,
    params: Sequence[md.Tensor],
    target: np.ndarray,
    propose: Proposal,
    renders: int = 200,
    factor: int = 4,
    seed: int = 0,
    render_kwargs: dict | None = None,
    pool: int = 1,
) -> SearchResult:
    """Greedy random search: ``renders`` proposals, each rendered at 1/``factor`` of the
    image size without a tape and compared with the block-mean target by the image loss
    (``image_loss``); a proposal that lowers the loss becomes the new best. The best values
    are written into ``params`` at the end. ``propose(rng, best, progress)`` draws a
    proposal (a list of arrays, one per parameter) around ``best``; ``progress`` runs from
    0 to 1 over the budget, so that steps can shrink. Deterministic for a given ``seed``.
    ``pool`` > 1 compares block means of ``pool`` x ``pool`` rendered pixels instead (a
    blurred loss: an object in the wrong place still overlaps the target's blurred object
    and scores better than nothing in view, which a sharp MSE does not)."""
    if isinstance(renders, bool) or not isinstance(renders, int) or renders < 0:
        raise ValueError(f"greedy_search: renders must be an int >= 0, got {renders!r}")
    params = list(params)
    small = downsample(target, factor)
    view = resized(scene, small.shape[1], small.shape[0])
    small = downsample(small, pool)
    kwargs = {k: v for k, v in (render_kwargs or {}).items() if k != "antialias"}
    rng = np.random.default_rng(seed)
    start = time.perf_counter()

    def loss_now() -> float:
        with md.no_grad():
            image = downsample(np.clip(render(view, **kwargs).data, 0.0, 1.0), pool)
            return float(image_loss(md.tensor(image), small).item())

    best = [p.data.copy() for p in params]
    best_loss = start_loss = loss_now()
    result = SearchResult(start_loss, start_loss, 1, 0.0)
    for k in range(renders):
        proposal = propose(rng, [b.copy() for b in best], k / max(renders, 1))
        for p, value in zip(params, proposal, strict=True):
            p.data[...] = value
        loss = loss_now()
        result.renders += 1
        if loss < best_loss:
            best, best_loss = [np.array(v, dtype=np.float64) for v in proposal], loss
            result.accepted.append((result.renders, loss))
    for p, value in zip(params, best, strict=True):
        p.data[...] = value
    result.loss, result.seconds = best_loss, time.perf_counter() - start
    return result


@dataclass
class MultiStartResult:
    """What ``multi_start`` did: each start's loss after its short run (at the low
    resolution), the index of the kept one, the renders made (every iteration of every
    start, plus the evaluation after the last update) and their wall time."""

    losses: list[float]
    best: int
    renders: int
    seconds: float


def multi_start(
    scene: Scene,
    params: Sequence[md.Tensor],
    target: np.ndarray,
    starts: Sequence[Sequence[np.ndarray]],
    iters: int = 40,
    factor: int = 2,
    **optimize_kwargs,
) -> MultiStartResult:
    """From each of ``starts`` (a list of values, one array per parameter), ``iters``
    iterations of ``optimize`` at 1/``factor`` of the image size against the block-mean
    target (each start with its own optimiser); the parameters end at the values the start
    with the lowest final loss reached. ``optimize_kwargs`` go to every run (``lr``,
    ``render_kwargs``: e.g. the cheaper ``antialias=True`` for this stage, ...)."""
    if isinstance(iters, bool) or not isinstance(iters, int) or iters < 0:
        raise ValueError(f"multi_start: iters must be an int >= 0, got {iters!r}")
    if not starts:
        raise ValueError("multi_start: give at least one start")
    if "optimizer" in optimize_kwargs:
        raise TypeError("multi_start: each start makes its own optimiser; pass lr instead")
    params = list(params)
    small = downsample(np.asarray(target, dtype=np.float64), factor)
    view = scene if factor == 1 else resized(scene, small.shape[1], small.shape[0])
    begin = time.perf_counter()
    losses, ends, renders = [], [], 0
    for values in starts:
        if len(values) != len(params):
            raise ValueError(f"multi_start: a start has {len(values)} values for {len(params)} "
                             "parameters")  # fmt: skip
        for p, value in zip(params, values, strict=True):
            p.data[...] = value
        _, history = optimize(view, params, small, max_iters=iters, **optimize_kwargs)
        losses.append(float(history.loss[-1]))
        ends.append([p.data.copy() for p in params])
        renders += len(history.loss)
    best = int(np.argmin(losses))
    for p, value in zip(params, ends[best], strict=True):
        p.data[...] = value
    return MultiStartResult(losses, best, renders, time.perf_counter() - begin)
