"""Inverse rendering: the paper's Algorithm 1, and a flat-vector view for SciPy.

``optimize`` is gradient descent on scene parameters: render, compare with the target
(MSE on images clipped to [0, 1], the paper's Eq. 1), backpropagate, let the optimiser
(Adam by default, Eq. 2) update the parameters in place, project them if asked, repeat
until the loss is below a tolerance or the iteration budget is spent.

``FlatParameters`` exposes the same problem as a function of one float64 vector with
``value_and_grad(x)``, the interface of ``scipy.optimize.minimize(..., jac=True)``.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import minidiff as md
from render.inverse.parallel import check_jobs
from render.renderer import render
from render.scene.image import load_image, mse
from render.scene.scene import Scene


def _as_target(target) -> np.ndarray:
    """The target image as float64. Integer pixels (an 8-bit image read with PIL, say) are
    refused: compared as they are with a rendering in [0, 1] they would be 255 times too
    bright, and guessing their scale would be wrong for 16-bit files."""
    array = np.asarray(target.data if isinstance(target, md.Tensor) else target)
    if array.dtype.kind in "iub":
        raise TypeError(
            f"optimize: target has integer pixels ({array.dtype}); pass linear radiance as "
            "floats, e.g. render.load_image(path) or target / 255.0 for 8-bit values"
        )
    if array.dtype.kind not in "f":
        raise TypeError(f"optimize: target must be a float image array, got dtype {array.dtype}")
    return array.astype(np.float64)


def image_loss(image: md.Tensor, target: np.ndarray) -> md.Tensor:
    """The paper's Eq. 1: mean squared error between the rendered image, clipped to [0, 1]
    (what a camera or an 8-bit file would record), and the target. Saturated pixels pass
    no gradient, as in any renderer whose output is clipped. The target is clipped the same
    way, so a render of the true scene has zero loss."""
    return mse(md.clip(image, 0.0, 1.0), md.kernels.clip(np.asarray(target), 0.0, 1.0))


@dataclass
class History:
    """What happened during ``optimize``, one entry per iteration (per loss evaluation).

    loss[i] is the loss at the parameters params[i] (before update i); seconds[i] the wall
    time of iteration i (render + backward + update). ``converged`` is True if the loss
    fell below the tolerance; ``stalled`` if the loss stopped depending on the parameters
    (a gradient of zeros or none, e.g. nothing visible); ``iterations`` counts the
    updates made. With many views, ``views[i]`` lists the views rendered in iteration
    i (empty for one scene).
    """

    loss: list[float] = field(default_factory=list)
    params: list[list[np.ndarray]] = field(default_factory=list)
    seconds: list[float] = field(default_factory=list)
    converged: bool = False
    stalled: bool = False
    iterations: int = 0
    views: list[list[int]] = field(default_factory=list)

    def summary(self, seconds: float) -> dict:
        """What the experiments report of a run that took ``seconds``: the loss at the start
        and the end, the updates made, and the time in all and per loss evaluation."""
        return {
            "initial_loss": self.loss[0],
            "final_loss": self.loss[-1],
            "iterations": self.iterations,
            "seconds": seconds,
            "seconds_per_iteration": seconds / max(1, len(self.loss)),
        }


class _Progress:
    """One status line, refreshed at most every ``every`` seconds (quiet: nothing)."""

    def __init__(self, max_iters: int, quiet: bool, every: float = 1.0):
        self.max_iters, self.quiet, self.every = max_iters, quiet, every
        self.start = self.last = time.perf_counter()

    def update(self, it: int, loss: float, final: bool = False) -> None:
        now = time.perf_counter()
        if self.quiet or (not final and now - self.last < self.every):
            return
        self.last = now
        elapsed = now - self.start
        rate = (it + 1) / elapsed if elapsed > 0 else float("inf")
        end = "\n" if final else "\r"
        print(
            f"  iter {it:4d}/{self.max_iters}  loss {loss:.3e}  "
            f"elapsed {elapsed:6.1f} s  {rate:5.1f} it/s",
            end=end,
            file=sys.stderr,
            flush=True,
        )


def optimize(
    scene: Scene | Callable[[], md.Tensor] | Sequence[tuple[Scene, np.ndarray]],
    params: Sequence[md.Tensor],
    target: np.ndarray | str | Path | None = None,
    *,
    loss_fn: Callable[[md.Tensor, np.ndarray], md.Tensor] = image_loss,
    optimizer: md.optim.Optimizer | None = None,
    lr: float | Sequence[float] = 0.01,
    project=None,
    max_iters: int = 500,
    tol: float = 0.0,
    callback: Callable[[int, float, np.ndarray, History], bool | None] | None = None,
    quiet: bool = False,
    render_kwargs: dict | None = None,
    batch: int | None = None,
    seed: int = 0,
    jobs: int | None = 1,
) -> tuple[list[md.Tensor], History]:
    """Fit ``params`` so that the rendered image matches ``target`` (Algorithm 1).

    scene: the scene holding the parameters; or any zero-argument function returning an
        (H, W, 3) image tensor (for custom pipelines); or **many views** of one problem: a
        list of (scene, target) pairs whose scenes share the parameters (e.g.
        ``scene.with_camera(camera)`` for each camera: the same objects and lights), with
        ``target`` left out. The loss is then the mean of ``loss_fn`` over the views.
    params: leaf tensors with ``requires_grad=True`` used by the scene(s); updated in place.
    target: (H, W, 3) array of the target image, or the path of an image file (read with
        ``render.load_image``, values as stored).
    optimizer: defaults to ``Adam(params, lr, project=project)``.
    max_iters, tol: stop after ``max_iters`` updates, or as soon as the loss is < ``tol``.
    callback(it, loss, image, history): called every iteration with the rendered image
        (an ndarray, before the update; with views, the list of the images rendered in that
        iteration, in the order of ``history.views[it]``); returning True stops early.
    batch: with views, how many to render per iteration, drawn at random without
        replacement (stochastic gradient: the loss and gradient of that batch; the draws
        come from ``seed``, so a run repeats exactly). None: every view, every iteration.
    render_kwargs: keywords passed to every ``render`` of a scene (``antialias``, ``spp``,
        ...); not return_info (the loss takes the image alone) nor scene.
    jobs: with views, how many threads render the views of one iteration (1: one after
        the other; None: one per core; the backward pass is one, over the sum, in the
        calling thread). The result is the same for any ``jobs``.
    Returns (params, history). Raises ``OptimizationError`` (with ``.history``) if a step
    fails, e.g. on a NaN gradient; ValueError if a parameter is in no scene, or a target
    does not have its view's image size.
    """
    views = _views(scene, target, _checked_render_kwargs(render_kwargs))
    known = {id(t) for view in views if view.scene is not None for t in view.scene.parameters()}
    for i, p in enumerate(params):
        if known and id(p) not in known:
            raise ValueError(
                f"optimize: params[{i}] (shape {getattr(p, 'shape', '?')}) is not a "
                "parameter of the scene: optimising it would change nothing"
            )
    if isinstance(max_iters, bool) or not isinstance(max_iters, int) or max_iters < 0:
        raise ValueError(f"optimize: max_iters must be an int >= 0, got {max_iters!r}")
    draw = _batches(len(views), batch, seed)
    jobs = check_jobs(jobs, "optimize: jobs")
    params = list(params)
    opt = optimizer if optimizer is not None else md.optim.Adam(params, lr=lr, project=project)

    history = History()
    progress = _Progress(max_iters, quiet)
    single = isinstance(scene, Scene) or callable(scene)
    for it in range(max_iters + 1):
        start = time.perf_counter()
        chosen = draw()
        try:  # a failure at any step of an iteration keeps the history so far
            opt.zero_grad()
            loss, images = _mean_loss([views[i] for i in chosen], loss_fn, jobs)
            stop = _iteration(it, loss, params, opt, tol, max_iters, history)
        except (ValueError, FloatingPointError) as err:  # e.g. a NaN gradient or parameter
            raise OptimizationError(f"optimize: iteration {it}: {err}", history) from err
        if not single:
            history.views.append(chosen)
        history.seconds.append(time.perf_counter() - start)
        progress.update(it, history.loss[-1], final=stop)
        shown = images[0] if single else images
        if callback is not None and callback(it, history.loss[-1], shown, history):
            break
        if stop:
            break
    return params, history


@dataclass
class _View:
    """One image of an inverse problem: how to render it, and what it should look like."""

    render: Callable[[], md.Tensor]
    target: np.ndarray
    scene: Scene | None  # None for a custom pipeline


def _checked_render_kwargs(kwargs) -> dict:
    """``optimize``'s render_kwargs as a dict (None: empty), or a clear error for keywords
    that would make ``render`` return something other than the image tensor the loss takes
    (return_info: an (image, info) pair) or that ``optimize`` sets itself (scene)."""
    if kwargs is None:
        return {}
    if not isinstance(kwargs, Mapping):
        raise TypeError(
            f"optimize: render_kwargs must be a dict of render's keywords, got "
            f"{type(kwargs).__name__}"
        )
    if kwargs.get("return_info"):
        raise ValueError(
            "optimize: render_kwargs must not set return_info (render would return an "
            "(image, info) pair instead of the image the loss compares with the target)"
        )
    if "scene" in kwargs:
        raise ValueError("optimize: render_kwargs must not set scene (optimize passes each view's)")
    return dict(kwargs)


def _views(scene, target, kwargs: dict) -> list[_View]:
    """The views of an ``optimize`` problem, each target read and checked."""
    if isinstance(scene, Scene):
        return [_scene_view(scene, target, kwargs, "target")]
    if callable(scene):
        if kwargs:
            raise ValueError(
                "optimize: render_kwargs apply to scenes that optimize renders; a callable "
                "renders its own image (pass the keywords to render inside it)"
            )
        return [_View(scene, _checked_target(target, "target"), None)]
    if isinstance(scene, list | tuple) and not isinstance(scene, str):
        if target is not None:
            raise TypeError(
                "optimize: with a list of (scene, target) views, leave target out (each "
                "view carries its own)"
            )
        if len(scene) == 0:
            raise ValueError("optimize: the list of views is empty")
        views = []
        for i, pair in enumerate(scene):
            if not (
                isinstance(pair, tuple | list) and len(pair) == 2 and isinstance(pair[0], Scene)
            ):
                raise TypeError(
                    f"optimize: views[{i}] must be a (render.Scene, target) pair, got "
                    f"{type(pair).__name__}"
                )
            views.append(_scene_view(pair[0], pair[1], kwargs, f"views[{i}] target"))
        return views
    raise TypeError(
        "optimize: scene must be a Scene, a callable or a list of (Scene, target) views, "
        f"got {type(scene).__name__}"
    )


def _scene_view(scene: Scene, target, kwargs: dict, name: str) -> _View:
    target = _checked_target(target, name)
    size = (scene.camera.height, scene.camera.width, 3)
    if target.shape != size:
        raise ValueError(
            f"optimize: {name} has shape {target.shape} but its scene renders {size} "
            "(height, width, 3)"
        )
    return _View(lambda: render(scene, **kwargs), target, scene)


def _checked_target(target, name: str) -> np.ndarray:
    if target is None:
        raise TypeError(f"optimize: {name} is missing")
    if isinstance(target, str | Path):  # a file: read as stored (no sRGB decoding)
        target = load_image(target)
    target = _as_target(target)
    if not np.isfinite(target).all():
        raise ValueError(f"optimize: {name} contains NaN or inf")
    return target


def _batches(n: int, batch: int | None, seed: int) -> Callable[[], list[int]]:
    """A function giving the view indices of each iteration: all of them, or ``batch`` of
    them drawn without replacement from a generator seeded with ``seed``."""
    if batch is None:
        return lambda: list(range(n))
    if isinstance(batch, bool) or not isinstance(batch, int | np.integer) or not 1 <= batch <= n:
        raise ValueError(f"optimize: batch must be an int in [1, {n}] (the views), got {batch!r}")
    rng = np.random.default_rng(seed)
    return lambda: sorted(int(i) for i in rng.choice(n, size=int(batch), replace=False))


def _mean_loss(views: list[_View], loss_fn, jobs: int) -> tuple[md.Tensor, list[np.ndarray]]:
    """The mean loss over ``views`` (the loss itself for one) and their images. With jobs
    > 1 the views are rendered in threads (the tape is safe to record from several); the
    sum is formed in view order, so the result does not depend on ``jobs``."""
    if jobs > 1 and len(views) > 1:
        with ThreadPoolExecutor(min(jobs, len(views))) as pool:
            images = list(pool.map(lambda v: v.render(), views))
    else:
        images = [v.render() for v in views]
    losses = [loss_fn(image, v.target) for image, v in zip(images, views, strict=True)]
    loss = losses[0] if len(losses) == 1 else sum(losses[1:], losses[0]) * (1.0 / len(losses))
    return loss, [image.data for image in images]


def _iteration(it, loss, params, opt, tol, max_iters, history) -> bool:
    """The bookkeeping and update of one iteration of ``optimize``: record the loss and the
    parameters and (unless it is the last) step. Returns whether to stop."""
    value = loss.item()
    history.loss.append(value)
    history.params.append([p.data.copy() for p in params])
    if value < tol:
        history.converged = True
    if not loss.requires_grad:  # the loss depends on no parameter at all
        history.stalled = True
    stop = history.converged or history.stalled or it == max_iters
    if not stop:
        loss.backward()
        # Nothing in view depends on the parameters (e.g. the object left the image): the
        # renderer gives them zero gradients, and there is no gradient to follow.
        history.stalled = not any(p.grad is not None and np.any(p.grad) for p in params)
        if history.stalled:
            return True
        opt.step()
        history.iterations += 1
    return stop


class OptimizationError(RuntimeError):
    """``optimize`` stopped on an error (e.g. a NaN gradient); ``history`` holds the
    iterations made until then, so that one can see where it went wrong."""

    def __init__(self, message: str, history: History):
        super().__init__(message)
        self.history = history


class FlatParameters:
    """Scene parameters seen as one float64 vector, for optimisers such as SciPy's.

    ``value_and_grad(x)`` writes x into the parameters, renders, and returns (loss, grad)
    with grad a float64 vector of the same layout: the interface of
    ``scipy.optimize.minimize(fp.value_and_grad, fp.get(), jac=True, method="L-BFGS-B")``.
    """

    def __init__(
        self,
        loss: Callable[[], md.Tensor],
        params: Sequence[md.Tensor],
    ):
        self.loss = loss
        self.params = list(params)
        self.sizes = [p.data.size for p in self.params]
        self.evaluations = 0

    def get(self) -> np.ndarray:
        """The current parameter values, concatenated."""
        return np.concatenate([p.data.ravel() for p in self.params]).astype(np.float64)

    def set(self, x: np.ndarray) -> None:
        """Write the vector x back into the parameters (in place)."""
        x = np.asarray(x, dtype=np.float64)
        if x.shape != (sum(self.sizes),):
            raise ValueError(f"FlatParameters.set: x must have shape ({sum(self.sizes)},)")
        for p, part in zip(self.params, np.split(x, np.cumsum(self.sizes)[:-1]), strict=True):
            p.data[...] = part.reshape(p.shape)

    def value_and_grad(self, x: np.ndarray) -> tuple[float, np.ndarray]:
        """Loss and gradient at x (both float64)."""
        self.set(x)
        for p in self.params:
            p.grad = None
        value = self.loss()
        value.backward()
        self.evaluations += 1
        grads = [
            (p.grad if p.grad is not None else np.zeros_like(p.data)).ravel() for p in self.params
        ]
        return float(value.item()), np.concatenate(grads).astype(np.float64)
