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
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import minidiff as md
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
    (no gradient, e.g. nothing visible); ``iterations`` counts the updates made.
    """

    loss: list[float] = field(default_factory=list)
    params: list[list[np.ndarray]] = field(default_factory=list)
    seconds: list[float] = field(default_factory=list)
    converged: bool = False
    stalled: bool = False
    iterations: int = 0


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
    scene: Scene | Callable[[], md.Tensor],
    params: Sequence[md.Tensor],
    target: np.ndarray,
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
) -> tuple[list[md.Tensor], History]:
    """Fit ``params`` so that the rendered image matches ``target`` (Algorithm 1).

    scene: the scene holding the parameters, or any zero-argument function returning an
        (H, W, 3) image tensor (for custom pipelines).
    params: leaf tensors with ``requires_grad=True`` used by the scene; updated in place.
    target: (H, W, 3) array of the target image, or the path of an image file (read with
        ``render.load_image``, values as stored).
    optimizer: defaults to ``Adam(params, lr, project=project)``.
    max_iters, tol: stop after ``max_iters`` updates, or as soon as the loss is < ``tol``.
    callback(it, loss, image, history): called every iteration with the rendered image
        (an ndarray, before the update); returning True stops early.
    Returns (params, history). Raises ``OptimizationError`` (with ``.history``) if a step
    fails, e.g. on a NaN gradient; ValueError if a parameter is not in the scene.
    """
    if isinstance(target, str | Path):  # a file: read as stored (no sRGB decoding)
        target = load_image(target)
    target = _as_target(target)
    if isinstance(scene, Scene):
        known = {id(t) for t in scene.parameters()}
        for i, p in enumerate(params):
            if id(p) not in known:
                raise ValueError(
                    f"optimize: params[{i}] (shape {getattr(p, 'shape', '?')}) is not a "
                    "parameter of the scene: optimising it would change nothing"
                )
        kwargs = render_kwargs or {}
        scene_obj = scene

        def render_image() -> md.Tensor:
            return render(scene_obj, **kwargs)
    elif callable(scene):
        render_image = scene
    else:
        raise TypeError(f"optimize: scene must be a Scene or a callable, got {type(scene)}")
    if isinstance(max_iters, bool) or not isinstance(max_iters, int) or max_iters < 0:
        raise ValueError(f"optimize: max_iters must be an int >= 0, got {max_iters!r}")
    if not np.isfinite(target).all():
        raise ValueError("optimize: target contains NaN or inf")
    params = list(params)
    opt = optimizer if optimizer is not None else md.optim.Adam(params, lr=lr, project=project)

    history = History()
    progress = _Progress(max_iters, quiet)
    for it in range(max_iters + 1):
        start = time.perf_counter()
        try:  # a failure at any step of an iteration keeps the history so far
            stop, image = _iteration(it, render_image, loss_fn, target, params, opt, tol,
                                     max_iters, history)  # fmt: skip
        except (ValueError, FloatingPointError) as err:  # e.g. a NaN gradient or parameter
            raise OptimizationError(f"optimize: iteration {it}: {err}", history) from err
        history.seconds.append(time.perf_counter() - start)
        progress.update(it, history.loss[-1], final=stop)
        if callback is not None and callback(it, history.loss[-1], image, history):
            break
        if stop:
            break
    return params, history


def _iteration(it, render_image, loss_fn, target, params, opt, tol, max_iters, history):
    """One iteration of ``optimize``: render, record the loss and the parameters, and (unless
    it is the last) step. Returns whether to stop, and the rendered image (an ndarray)."""
    opt.zero_grad()
    image = render_image()
    loss = loss_fn(image, target)
    value = loss.item()
    history.loss.append(value)
    history.params.append([p.data.copy() for p in params])
    if value < tol:
        history.converged = True
    if not loss.requires_grad:
        # Nothing in view depends on the parameters (e.g. the object left the image):
        # there is no gradient to follow.
        history.stalled = True
    stop = history.converged or history.stalled or it == max_iters
    if not stop:
        loss.backward()
        opt.step()
        history.iterations += 1
    return stop, image.data


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
