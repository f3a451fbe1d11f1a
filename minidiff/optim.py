"""Gradient-descent optimisers that update tensors in place: SGD and Adam (the paper's Eq. 2).

Both take a list of leaf tensors, read each one's ``.grad`` in ``step()`` and change its
``.data`` in place (so a scene that holds the tensor sees the new value). An optional
projection per parameter runs after each step, e.g. ``box(0, 1)`` keeps colours in the RGB
cube (the paper's section 5.8).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from minidiff.tensor import Tensor

Projection = Callable[[np.ndarray], np.ndarray]


def box(lo: float | np.ndarray, hi: float | np.ndarray) -> Projection:
    """The Euclidean projection onto the box [lo, hi] (component-wise clamp).

    lo > hi in any component is refused (ValueError naming both): the box is empty, and
    np.clip would silently give hi everywhere there."""
    lo_a, hi_a = np.asarray(lo), np.asarray(hi)
    try:
        empty = np.any(lo_a > hi_a)
    except (TypeError, ValueError):
        raise ValueError(
            f"box: lo and hi must be numbers or arrays, got {lo!r} and {hi!r}"
        ) from None
    if empty:
        raise ValueError(f"box: lo must be <= hi in every component, got lo={lo!r} and hi={hi!r}")
    return lambda x: np.clip(x, lo, hi)


class Optimizer:
    """Shared bookkeeping: the parameters, per-parameter projections, and zero_grad."""

    def __init__(
        self,
        params: Sequence[Tensor],
        project: Projection | Sequence[Projection | None] | None = None,
    ):
        self.params = list(params)
        if not self.params:
            raise ValueError(f"{type(self).__name__}: params is empty")
        for i, p in enumerate(self.params):
            if not isinstance(p, Tensor) or not p.requires_grad or not p.is_leaf:
                raise TypeError(
                    f"{type(self).__name__}: params[{i}] must be a leaf Tensor with "
                    "requires_grad=True"
                )
        if project is None or callable(project):
            self.project = [project] * len(self.params)
        elif isinstance(project, list | tuple):
            self.project = list(project)
            if len(self.project) != len(self.params):
                raise ValueError(
                    f"{type(self).__name__}: {len(self.project)} projections for "
                    f"{len(self.params)} params"
                )
        else:
            raise TypeError(
                f"{type(self).__name__}: project must be a callable, a list of callables or "
                f"None, got {type(project).__name__}"
            )
        for i, f in enumerate(self.project):
            if f is not None and not callable(f):
                raise TypeError(
                    f"{type(self).__name__}: project[{i}] must be callable or None, "
                    f"got {type(f).__name__}"
                )

    def zero_grad(self) -> None:
        """Forget accumulated gradients (call before each new backward pass)."""
        for p in self.params:
            p.grad = None

    def _gradients(self) -> list[tuple[int, Tensor, np.ndarray]]:
        """(index, param, grad) for params that received a gradient. All are checked before
        any is returned, so a NaN in a later parameter cannot leave a half-applied step."""
        found = []
        for i, p in enumerate(self.params):
            if p.grad is None:
                continue
            if np.shape(p.grad) != p.shape:
                raise ValueError(
                    f"{type(self).__name__}.step: gradient of params[{i}] has shape "
                    f"{np.shape(p.grad)}, but the parameter has shape {p.shape}"
                )
            if not np.isfinite(p.grad).all():
                raise ValueError(
                    f"{type(self).__name__}.step: gradient of params[{i}] contains NaN/inf"
                )
            found.append((i, p, p.grad))
        return found

    def _per_param_lr(self, lr) -> list[float]:
        """One learning rate per parameter, each a finite number >= 0. A list is checked
        for length: passed on as is, ``[0.1, 0.2] * g`` would silently broadcast against
        the gradient's elements."""
        one = np.ndim(lr) == 0  # a number (or a string, None, ...: refused by _real)
        if one:
            lrs = [_real(self, "lr", lr)] * len(self.params)
        else:
            lrs = [_real(self, f"lr[{i}]", v) for i, v in enumerate(lr)]
        if len(lrs) != len(self.params):
            raise ValueError(
                f"{type(self).__name__}: {len(lrs)} learning rates for {len(self.params)} params"
            )
        for i, v in enumerate(lrs):
            if not (math.isfinite(v) and v >= 0):
                name = "lr" if one else f"lr[{i}]"
                raise ValueError(
                    f"{type(self).__name__}: {name} must be a finite number >= 0, got {v}"
                )
        return lrs

    def _apply_projection(self, i: int, p: Tensor) -> None:
        if self.project[i] is not None:
            projected = np.asarray(self.project[i](p.data))
            # Broadcasting a scalar or a row into the parameter would pass silently.
            if projected.shape != p.data.shape:
                raise ValueError(
                    f"{type(self).__name__}: project[{i}] must return an array of the "
                    f"parameter's shape {p.data.shape}, got {projected.shape}"
                )
            p.data[...] = projected


def _real(optimizer: Optimizer, name: str, value: Any) -> float:
    """``value`` as a float, if it is a real number (not a string, a bool or an array)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError(
            f"{type(optimizer).__name__}: {name} must be a real number, "
            f"got {type(value).__name__} {value!r}"
        )
    return float(value)


def _fraction(optimizer: Optimizer, name: str, value: Any) -> float:
    """A decay rate such as momentum or Adam's betas: a number in [0, 1). At 1 the running
    averages would never forget (and Adam's bias correction would divide by 1 - 1 = 0)."""
    value = _real(optimizer, name, value)
    if not 0.0 <= value < 1.0:
        raise ValueError(f"{type(optimizer).__name__}: {name} must lie in [0, 1), got {value}")
    return value


class SGD(Optimizer):
    """theta <- theta - lr * g  (with optional momentum: v <- mu v + g; theta <- theta - lr v).

    ``lr`` may be one number or one per parameter, as for Adam.
    """

    def __init__(
        self, params, lr: float | Sequence[float] = 0.01, momentum: float = 0.0, project=None
    ):
        super().__init__(params, project)
        self.lr = self._per_param_lr(lr)
        self.momentum = _fraction(self, "momentum", momentum)
        self.velocity = [np.zeros_like(p.data) for p in self.params]

    def step(self) -> None:
        """One update of every parameter that has a gradient."""
        for i, p, g in self._gradients():
            if self.momentum:
                self.velocity[i] = self.momentum * self.velocity[i] + g
                g = self.velocity[i]
            p.data -= self.lr[i] * g
            self._apply_projection(i, p)


class Adam(Optimizer):
    """Adam with bias correction, exactly the paper's Eq. 2:

        m_t = b1 m_{t-1} + (1 - b1) g          v_t = b2 v_{t-1} + (1 - b2) g^2
        m^_t = m_t / (1 - b1^t)                v^_t = v_t / (1 - b2^t)
        theta_{t+1} = theta_t - lr m^_t / (sqrt(v^_t) + eps)

    ``lr`` may be one number or one per parameter (parameters of different scales, e.g.
    a light position in metres and an intensity in hundreds, want different step sizes).

    ``uniform=True``: the denominator is the *largest* sqrt(v^) over the parameter's
    entries instead of each entry's own (Nicolet et al. 2021, "Large Steps in Inverse
    Rendering of Geometry", their uniform Adam): every entry of the parameter moves with
    the same scale, so a smooth gradient field gives a smooth update (per-entry scaling
    would re-weight the vertices of a mesh one by one and undo a smooth parameterisation).

    Huge gradients: g^2 overflows float64 for |g| > 1.3e154, and v = inf would stop the
    parameter for good (m / sqrt(inf) = 0 at every later step). So v is kept divided by
    ``scale[i]**2``, where ``scale[i]`` is a power of two (1 until a gradient above 2^500
    ~ 3e150 arrives, then raised so that g / scale stays below it): the update reads
    ``m^ / (sqrt(v^) * scale + eps)``. Powers of two rescale exactly, and with scale 1
    the arithmetic is the plain formula above, bit for bit.
    """

    def __init__(
        self,
        params,
        lr: float | Sequence[float] = 1e-3,
        betas: tuple[float, float] = (0.9, 0.999),
        eps: float = 1e-8,
        project=None,
        uniform: bool = False,
    ):
        super().__init__(params, project)
        self.lr = self._per_param_lr(lr)
        if not isinstance(uniform, bool):
            raise TypeError(f"Adam: uniform must be a bool, got {type(uniform).__name__}")
        self.uniform = uniform
        try:
            b1, b2 = betas
        except (TypeError, ValueError):
            raise TypeError(f"Adam: betas must be a pair (b1, b2), got {betas!r}") from None
        self.betas = (_fraction(self, "betas[0]", b1), _fraction(self, "betas[1]", b2))
        self.eps = _real(self, "eps", eps)
        if not (math.isfinite(self.eps) and self.eps > 0):
            raise ValueError(f"Adam: eps must be a finite number > 0, got {self.eps}")
        self.m = [np.zeros_like(p.data) for p in self.params]
        self.v = [np.zeros_like(p.data) for p in self.params]
        self.t = [0] * len(self.params)  # per parameter: a parameter may skip steps
        self.scale = [1.0] * len(self.params)  # v is stored divided by scale^2

    def step(self) -> None:
        """One Adam update of every parameter that has a gradient, then its projection."""
        b1, b2 = self.betas
        for i, p, g in self._gradients():
            self.t[i] += 1
            t = self.t[i]
            self.m[i] = b1 * self.m[i] + (1 - b1) * g
            scale = self._rescale(i, g)
            gs = g if scale == 1.0 else g / scale
            self.v[i] = b2 * self.v[i] + (1 - b2) * gs * gs
            m_hat = self.m[i] / (1 - b1**t)
            v_hat = self.v[i] / (1 - b2**t)
            root = np.sqrt(v_hat) if scale == 1.0 else np.sqrt(v_hat) * scale
            if self.uniform:
                root = np.max(root)
            p.data -= self.lr[i] * m_hat / (root + self.eps)
            self._apply_projection(i, p)

    def _rescale(self, i: int, g: np.ndarray) -> float:
        """The scale of v for params[i] after seeing g: raised (by a power of two, and v
        rescaled with it, exactly) if |g| / scale would exceed 2^500, so that the squares
        of g / scale stay far from overflow. Never lowered."""
        largest = float(np.max(np.abs(g))) if np.size(g) else 0.0
        scale = self.scale[i]
        if largest > scale * _ADAM_LIMIT:
            new = 2.0 ** (math.frexp(largest / _ADAM_LIMIT)[1])  # >= largest / limit
            self.v[i] = self.v[i] * ((scale / new) ** 2)
            self.scale[i] = scale = new
        return scale


_ADAM_LIMIT = 2.0**500  # |g / scale| stays below this: its square (2^1000) is finite
