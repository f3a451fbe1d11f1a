"""``render.torch``: the renderer as a PyTorch function (optional extra ``torch``).

    import torch, render, render.torch
    scene = render.paper_scene(64, 64)
    f = render.torch.function(scene, ["lights[0].position"])
    position = torch.tensor([2.0, 5.0, 3.0], dtype=torch.float64, requires_grad=True)
    loss = ((f(position) - target) ** 2).mean()
    loss.backward()                       # position.grad: through minidiff's tape

How two autodiff systems meet: ``_Render`` is a ``torch.autograd.Function`` whose forward
renders with ``render.inverse.function.RenderFunction`` (one render recorded on minidiff's
tape) and whose backward is that render's pullback (one minidiff ``backward``): PyTorch
sees one operation with a hand-written derivative, like any of its own. Its ``jvp`` is
minidiff's forward mode, so ``torch.func.jvp`` and ``torch.autograd.forward_ad`` work too;
``forward`` and ``setup_context`` are kept apart, as ``torch.func`` requires.

* **Differentiable once**: the backward is NumPy code, invisible to PyTorch, so a second
  derivative raises an error (``_FirstOrder``), in reverse or forward mode
  (``torch.func.hessian``). This is stated by the pullback being an
  ``autograd.Function`` whose own backward raises, not by ``@once_differentiable``: under
  ``torch.func.grad(torch.func.grad(f))`` that decorator turns the second derivative into
  a silent zero (measured with PyTorch 2.13), while the explicit error reaches both.
* **dtypes**: tensors come and go in the function's dtype (``f.dtype``, float64 unless the
  scene is float32); a floating-point tensor of another dtype is an error naming its
  parameter, never a silent cast. Integer and boolean tensors are constants (no gradient).
* **Batches loop**: a value with one leading dimension more than its parameter is a batch
  of B values; the scene is rendered B times, one after the other, and the images stacked
  (B, ...). Unbatched values are shared by the whole batch. A scalar parameter given shape
  (1,) is refused: one value, or a batch of one? ``torch.func.vmap`` does the same loop,
  and so do the derivatives' own operations under it: ``torch.func.jacrev``, ``jacfwd``
  and ``vmap(grad(f))`` work (one pullback, or one forward-mode render, per row).
* **CPU**: tensors on another device are copied to the CPU and the image is returned on
  the device of the first value.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

import minidiff as md
from render.inverse.function import RenderFunction
from render.scene.scene import Scene

__all__ = ["function", "TorchRenderFunction"]


def function(
    scene: Scene | Sequence[Scene],
    parameters: str | md.Tensor | Sequence[str | md.Tensor],
    **render_kwargs: Any,
) -> TorchRenderFunction:
    """``render(scene, **render_kwargs)`` as a PyTorch function of the ``parameters``
    (names such as ``"camera.position"``, or the scene's tensors), in that order; see
    ``render.inverse.function.RenderFunction`` for views and ``render_kwargs``."""
    return TorchRenderFunction(RenderFunction(scene, parameters, **render_kwargs))


class TorchRenderFunction:
    """Call with one torch tensor per parameter; returns the image as a torch tensor,
    (H, W, 3), (V, H, W, 3) for views, with a leading (B,) for a batch. ``core`` is the
    ``RenderFunction``; ``names``, ``shapes``, ``dtype`` are its."""

    def __init__(self, core: RenderFunction) -> None:
        self.core = core
        self.names, self.shapes = core.names, core.shapes
        self.dtype = _TORCH_DTYPES[np.dtype(core.dtype)]

    def __repr__(self) -> str:
        return f"render.torch.{self.core!r}"

    def __call__(self, *values: torch.Tensor) -> torch.Tensor:
        where = "render.torch"
        if len(values) != len(self.names):
            raise TypeError(
                f"{where}: expected {len(self.names)} tensors ({', '.join(self.names)}), got "
                f"{len(values)}"
            )
        batch = None
        for name, shape, value in zip(self.names, self.shapes, values, strict=True):
            if not isinstance(value, torch.Tensor):
                raise TypeError(
                    f"{where}: {name} must be a torch.Tensor, got {type(value).__name__}"
                )
            if value.dtype.is_floating_point and value.dtype != self.dtype:
                raise TypeError(
                    f"{where}: {name} is {value.dtype} but this function computes in "
                    f"{self.dtype}; convert it explicitly (e.g. .to({self.dtype}))"
                )
            if value.dim() == len(shape) + 1 and tuple(value.shape[1:]) == shape:
                if shape == () and value.shape[0] == 1:
                    raise ValueError(
                        f"{where}: {name} is a scalar parameter but was given shape (1,): one "
                        "value (pass a 0-d tensor, x.reshape(())) or a batch of one (its "
                        "image would get a leading 1)? Ambiguous, so refused; for a batch of "
                        "one use torch.func.vmap"
                    )
                if batch is not None and value.shape[0] != batch:
                    raise ValueError(
                        f"{where}: {name} has a batch of {value.shape[0]}, another value {batch}"
                    )
                batch = value.shape[0]
            elif tuple(value.shape) != shape:
                raise ValueError(
                    f"{where}: {name} must have shape {shape} (or (B, *{shape}) for a batch), "
                    f"got {tuple(value.shape)}"
                )
        # Record minidiff's tape only if PyTorch will ask for a backward pass.
        record = torch.is_grad_enabled() and any(v.requires_grad for v in values)
        if batch is None:
            return _Render.apply(self.core, record, *values)[0]
        images = []
        for b in range(batch):  # a loop: the renderer draws one scene at a time
            one = [
                v[b] if tuple(v.shape) != s else v for v, s in zip(values, self.shapes, strict=True)
            ]
            images.append(_Render.apply(self.core, record, *one)[0])
        return torch.stack(images)


_TORCH_DTYPES = {np.dtype(np.float32): torch.float32, np.dtype(np.float64): torch.float64}


def _numpy(value: torch.Tensor) -> np.ndarray:
    return value.detach().cpu().numpy()


class _Pullback:
    """Carries the pullback of one forward from ``forward`` to ``backward`` (an output
    that is not a tensor: PyTorch passes it through untouched)."""

    def __init__(self, pullback=None) -> None:
        self.pullback = pullback


class _Render(torch.autograd.Function):
    """One render: inputs (core, record, *values), outputs (image, _Pullback); ``record``
    says whether to keep minidiff's tape for a backward pass."""

    @staticmethod
    def forward(core: RenderFunction, record: bool, *values: torch.Tensor):
        arrays = [_numpy(v) for v in values]
        device = values[0].device
        if record and any(a.dtype.kind == "f" for a in arrays):
            # Keep this render's tape for the backward pass: no second render.
            image, pullback = core.forward(*arrays)
            return torch.from_numpy(image).to(device), _Pullback(pullback)
        # No input asks for a gradient here (or a torch.func transform hides it): render
        # without a tape; a backward that comes anyway renders again on the tape.
        return torch.from_numpy(core(*arrays)).to(device), _Pullback()

    @staticmethod
    def setup_context(ctx, inputs, output) -> None:
        core, _, *values = inputs
        ctx.core, ctx.pullback = core, output[1].pullback
        ctx.save_for_backward(*values)
        ctx.save_for_forward(*values)

    @staticmethod
    def backward(ctx, d_image: torch.Tensor, _d_pullback: Any):
        values = ctx.saved_tensors
        holder, ctx.pullback = _Pullback(ctx.pullback), None  # the tape is used once
        grads = _Pull.apply(ctx.core, holder, d_image, *values)
        differentiable = [v.dtype.is_floating_point for v in values]
        return (None, None) + tuple(
            g if d else None for g, d in zip(grads, differentiable, strict=True)
        )

    @staticmethod
    def jvp(ctx, _d_core: Any, _d_record: Any, *tangents: torch.Tensor | None):
        return _Push.apply(ctx.core, len(tangents), *ctx.saved_tensors, *tangents), None

    @staticmethod
    def vmap(info, in_dims, core: RenderFunction, record: bool, *values: torch.Tensor):
        """``torch.func.vmap``: one render per batch element, stacked."""
        images = []
        for b in range(info.batch_size):
            one = [
                v if d is None else v.select(d, b) for v, d in zip(values, in_dims[2:], strict=True)
            ]
            images.append(_Render.apply(core, record, *one)[0])
        return (torch.stack(images), _Pullback()), (0, None)


SECOND_DERIVATIVES = (
    "render.torch: the renderer's derivative is not differentiable again (it is minidiff's "
    "tape, which PyTorch cannot see): no second derivatives (torch.func.hessian, grad of "
    "grad, jvp of grad); differentiate the renderer once"
)


class _FirstOrder(torch.autograd.Function):
    """What ``_Pull`` and ``_Push`` share: nothing to save, and no derivative of their own
    (the renderer is differentiated once, by minidiff)."""

    @staticmethod
    def setup_context(ctx, inputs, output) -> None:
        pass

    @staticmethod
    def backward(ctx, *_grads):
        raise RuntimeError(SECOND_DERIVATIVES)

    @staticmethod
    def jvp(ctx, *_tangents):
        """Forward mode over a derivative (``torch.func.hessian``, ``jacfwd(jacrev(f))``,
        ``jvp(grad(f))``): refused like reverse mode over it, not with PyTorch's "You must
        implement the jvp function"."""
        raise RuntimeError(SECOND_DERIVATIVES)


class _Pull(_FirstOrder):
    """The pullback as a PyTorch operation, (core, holder, d_image, *values) -> one
    gradient per value (zeros for integer values): its NumPy work must run inside a
    ``forward``, where ``torch.func`` hands over plain tensors."""

    @staticmethod
    def forward(core: RenderFunction, holder: _Pullback, d_image, *values):
        d = _numpy(d_image.contiguous())
        arrays = [_numpy(v) for v in values]
        grads = core.vjp(arrays, d) if holder.pullback is None else holder.pullback(d)
        return tuple(
            torch.zeros(v.shape, dtype=d_image.dtype, device=v.device) if g is None
            else torch.from_numpy(np.asarray(g)).to(v.device)
            for g, v in zip(grads, values, strict=True)
        )  # fmt: skip

    @staticmethod
    def vmap(info, in_dims, core: RenderFunction, holder: _Pullback, d_image, *values):
        """``torch.func.vmap`` (``jacrev``, ``vmap(grad(f))``): one pullback per batch
        element, stacked. The forward's tape (``holder``) serves the first element when
        the values are not batched (then it was recorded for them); every other element
        renders again on a tape of its own (a tape is used once)."""
        shared = all(d is None for d in in_dims[3:])
        per_element = []
        for b in range(info.batch_size):
            d = d_image if in_dims[2] is None else d_image.select(in_dims[2], b)
            one = _element(values, in_dims[3:], b)
            tape = holder if b == 0 and shared else _Pullback()
            per_element.append(_Pull.apply(core, tape, d, *one))
        grads = tuple(torch.stack(g) for g in zip(*per_element, strict=True))
        return grads, (0,) * len(grads)


class _Push(_FirstOrder):
    """The Jacobian-vector product as a PyTorch operation, (core, n, *values, *tangents) ->
    the image's tangent (minidiff's forward mode)."""

    @staticmethod
    def forward(core: RenderFunction, n: int, *values_and_tangents):
        values, tangents = values_and_tangents[:n], values_and_tangents[n:]
        moves = [None if t is None else _numpy(t) for t in tangents]
        _, d_image = core.jvp([_numpy(v) for v in values], moves)
        return torch.from_numpy(d_image).to(values[0].device)

    @staticmethod
    def vmap(info, in_dims, core: RenderFunction, n: int, *values_and_tangents):
        """``torch.func.vmap`` (``jacfwd``, ``vmap(jvp(f))``): one Jacobian-vector product
        per batch element, stacked."""
        tangents = [
            _Push.apply(core, n, *_element(values_and_tangents, in_dims[2:], b))
            for b in range(info.batch_size)
        ]
        return torch.stack(tangents), 0


def _element(values, dims, b: int) -> list:
    """Element ``b`` of a vmapped batch: each value at index b along its batch dimension
    (``dims``: one per value, None where the value is shared by the whole batch)."""
    return [
        v if d is None or v is None else v.select(d, b) for v, d in zip(values, dims, strict=True)
    ]
