"""Function transformations over plain arrays: grad, value_and_grad (reverse mode), jvp
(forward mode), and a gradient checker."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from minidiff.tensor import Tensor, as_tangent, no_grad, tangents, tensor


def _argnums_tuple(argnums: int | Sequence[int]) -> tuple[int, ...]:
    return (argnums,) if isinstance(argnums, int) else tuple(argnums)


def value_and_grad(f: Callable[..., Any], argnums: int | Sequence[int] = 0) -> Callable:
    """Turn a scalar function f(*args) into one returning (value, gradient).

    The arguments at ``argnums`` (arrays, numbers or tensors) are copied into fresh leaf
    tensors that require grad; the gradient is returned as ndarray(s) of their shapes
    (a tuple when ``argnums`` is a tuple). An output that does not depend on an argument
    gives a zero gradient for it.
    """
    nums = _argnums_tuple(argnums)

    def wrapped(*args):
        args = list(args)
        leaves = []
        for i in nums:
            if i >= len(args):
                raise ValueError(f"value_and_grad: argnums {i} but only {len(args)} arguments")
            leaf = tensor(args[i], requires_grad=True)
            args[i] = leaf
            leaves.append(leaf)
        out = f(*args)
        _check_scalar("value_and_grad", out)
        if isinstance(out, Tensor):
            if out.requires_grad:
                out.backward()
            value = out.item()
        else:
            value = float(np.asarray(out))
        grads = tuple(
            leaf.grad if leaf.grad is not None else np.zeros_like(leaf.data) for leaf in leaves
        )
        return value, (grads[0] if isinstance(argnums, int) else grads)

    return wrapped


def _check_scalar(where: str, out: Any) -> None:
    """A gradient is of a scalar function: refuse anything but one real number, naming
    what f returned (a vector's gradient is a Jacobian: use ``jvp`` or ``backward(seed)``)."""
    try:
        array = np.asarray(out._data if isinstance(out, Tensor) else out)
    except Exception:  # noqa: BLE001 - whatever it was, it is not a number
        array = np.asarray(None)
    if array.dtype.kind not in "biuf":
        raise TypeError(
            f"{where}: f must return a scalar (a one-element Tensor or a real number), "
            f"got {type(out).__name__}"
        )
    if array.size != 1:
        raise ValueError(
            f"{where}: f must return a scalar (a one-element Tensor or a real number), got "
            f"{type(out).__name__} of shape {array.shape}; for a vector-valued f use jvp, "
            "or backward(seed) with a seed of that shape"
        )


def grad(f: Callable[..., Any], argnums: int | Sequence[int] = 0) -> Callable:
    """Turn a scalar function f(*args) into one returning its gradient (see value_and_grad)."""
    vg = value_and_grad(f, argnums)
    return lambda *args: vg(*args)[1]


def jvp(
    f: Callable[..., Any], primals: Sequence[Any], tangents_in: Sequence[Any]
) -> tuple[np.ndarray, np.ndarray]:
    """Forward mode: the value of ``f(*primals)`` and its directional derivative along
    ``tangents_in``, ``J_f(primals) @ tangents_in``, in one pass.

    primals: the arguments (arrays, numbers or tensors), each copied into a fresh leaf
    tensor (it need not require grad). tangents_in: one direction per primal, of the
    primal's shape (integer or floating-point values, converted to the primal's dtype).
    f returns a Tensor (or an array or number, which does not depend on the primals).
    Returns ``(value, tangent)``, two ndarrays of the output's shape; the tangent is zeros
    where the output does not depend on the primals.

        >>> md.jvp(lambda x: x * x, (np.array([1.0, 3.0]),), (np.array([1.0, 0.0]),))
        (array([1., 9.]), array([2., 0.]))
    """
    if not isinstance(primals, (tuple, list)) or not isinstance(tangents_in, (tuple, list)):
        raise TypeError(
            "jvp: primals and tangents must be tuples or lists (one entry per argument of f), "
            f"got {type(primals).__name__} and {type(tangents_in).__name__}"
        )
    if len(primals) != len(tangents_in):
        raise ValueError(
            f"jvp: {len(primals)} primals but {len(tangents_in)} tangents; give one tangent "
            "per primal"
        )
    leaves = [tensor(p) for p in primals]
    directions = {
        leaf: as_tangent("jvp", f"tangent {i}", leaf, t)
        for i, (leaf, t) in enumerate(zip(leaves, tangents_in, strict=True))
    }
    with tangents(directions):
        out = f(*leaves)
    if isinstance(out, Tensor):
        value = np.array(out.data)
        t = out.tangent
        return value, (np.zeros_like(value) if t is None else np.array(t))
    value = np.asarray(out)
    return value, np.zeros(value.shape, dtype=np.result_type(value.dtype, np.float64))


def numerical_grad(f: Callable[..., Any], args: Sequence[Any], argnum: int, eps: float):
    """Central finite differences of a scalar f w.r.t. args[argnum]: (f(x+h) - f(x-h)) / 2h,
    one element at a time. Runs under no_grad (nothing is recorded).

    f receives the perturbed argument as a (constant) Tensor, as it does under
    value_and_grad, and every other argument as given, so that a function using
    Tensor-only methods (``.numpy()``) or ``.data`` means the same on both sides of a check."""
    args = list(args)
    x = args[argnum]
    x = np.array(x.data if isinstance(x, Tensor) else x, dtype=np.float64)
    g = np.zeros_like(x)
    flat, gflat = x.reshape(-1), g.reshape(-1)
    with no_grad():
        for k in range(flat.size):
            saved = flat[k]
            flat[k] = saved + eps
            f_plus = f(*args[:argnum], Tensor(x.copy()), *args[argnum + 1 :])
            _check_scalar("numerical_grad", f_plus)
            flat[k] = saved - eps
            f_minus = f(*args[:argnum], Tensor(x.copy()), *args[argnum + 1 :])
            f_plus, f_minus = float(np.asarray(f_plus)), float(np.asarray(f_minus))
            flat[k] = saved
            gflat[k] = (f_plus - f_minus) / (2 * eps)
    return g


def check_grad(
    f: Callable[..., Any],
    *args: Any,
    eps: float = 1e-6,
    argnums: int | Sequence[int] = 0,
) -> tuple[float, Any, Any]:
    """Compare the tape gradient of a scalar f with central finite differences.

    Returns ``(rel_error, g_ad, g_fd)`` with the paper's Eq. 3 relative l2 error
    ``||g_ad - g_fd|| / (||g_fd|| + 1e-8)`` over all checked arguments together. With a
    tuple ``argnums``, g_ad and g_fd are tuples of arrays. Use float64 inputs: in float32 the
    finite differences themselves are only good to ~1e-3.
    """
    nums = _argnums_tuple(argnums)
    args64 = [
        np.asarray(a.data if isinstance(a, Tensor) else a, dtype=np.float64) if i in nums else a
        for i, a in enumerate(args)
    ]
    _, g_ad = value_and_grad(f, nums)(*args64)
    # The checked arguments as constant Tensors: f sees a Tensor for each of them in every
    # evaluation, as value_and_grad gives it.
    args_fd = [Tensor(a) if i in nums else a for i, a in enumerate(args64)]
    g_fd = tuple(numerical_grad(f, args_fd, i, eps) for i in nums)
    ad = np.concatenate([np.ravel(g) for g in g_ad])
    fd = np.concatenate([np.ravel(g) for g in g_fd])
    rel = float(np.linalg.norm(ad - fd) / (np.linalg.norm(fd) + 1e-8))
    if isinstance(argnums, int):
        return rel, g_ad[0], g_fd[0]
    return rel, g_ad, g_fd
