"""minidiff: a small tape-based reverse-mode autodiff over NumPy arrays, with forward mode.

Read in this order: ``tensor.py`` (the Tensor, the tape, backward, and forward mode's
tangents), ``primitives.py`` (each primitive's forward, vector-Jacobian product and
Jacobian-vector product side by side), ``functional.py`` (grad, value_and_grad, jvp,
check_grad), ``optim.py`` (SGD, Adam). ``kernels.py`` holds the NumPy kernels that make the
primitives fast on tall, thin arrays; each equals a plain NumPy expression. ``buffers.py``
gives the kernels' large outputs memory that earlier passes used and no longer refer to.

    >>> import numpy as np
    >>> import minidiff as md
    >>> x = md.tensor([1.0, 2.0, 3.0], requires_grad=True)
    >>> y = (x * x).sum()
    >>> y.backward()
    >>> x.grad
    array([2., 4., 6.])
    >>> md.jvp(lambda x: (x * x).sum(), (np.array([1.0, 2.0, 3.0]),), (np.ones(3),))[1]
    array(12.)
"""

from minidiff import buffers, jitcache, kernels, optim  # noqa: F401  (jitcache: first)
from minidiff.compiler import CompiledFunction, compile, tape_only  # noqa: A004
from minidiff.functional import check_grad, grad, jvp, numerical_grad, value_and_grad
from minidiff.primitives import (
    abs,
    add,
    broadcast_to,
    clip,
    concatenate,
    cos,
    cross,
    detach,
    divide,
    dot,
    exp,
    floor,
    getitem,
    linear,
    log,
    matmul,
    max,
    maximum,
    mean,
    mean_squared_error,
    minimum,
    multiply,
    negative,
    norm,
    normalize,
    power,
    reshape,
    scatter_add,
    sin,
    sqrt,
    stack,
    subtract,
    sum,
    tan,
    tanh,
    to_index,
    transpose,
    where,
)
from minidiff.tensor import (
    Tensor,
    as_tensor,
    detect_anomaly,
    enable_grad,
    is_grad_enabled,
    no_grad,
    tangents,
    tensor,
    unbroadcast,
)

__all__ = [
    "Tensor", "tensor", "as_tensor", "no_grad", "enable_grad", "detect_anomaly", "is_grad_enabled",
    "unbroadcast", "kernels", "buffers", "grad", "value_and_grad", "check_grad",
    "numerical_grad", "optim", "jvp", "tangents", "compile", "CompiledFunction", "tape_only",
    "add", "subtract", "multiply", "divide", "negative", "power", "matmul", "linear",
    "detach", "exp", "log", "sqrt", "sin", "cos", "tan", "tanh", "abs", "maximum", "minimum",
    "clip", "floor", "to_index",
    "where", "sum", "mean", "mean_squared_error", "max", "dot", "cross", "norm", "normalize",
    "reshape",
    "transpose", "broadcast_to", "stack", "concatenate", "getitem", "scatter_add",
]  # fmt: skip
