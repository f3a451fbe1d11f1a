"""Functions of tensors or plain arrays, so that a formula is written once for both.

Given a ``Tensor`` (either argument), each records on the tape like the primitive it names
(and inside a function ``minidiff.compile`` traces, on traced arrays, it is that primitive);
given plain arrays, it computes with NumPy (or minidiff's compiled kernels) and returns a
plain array. The renderer writes its edge functions and its lights' geometry with these, and
evaluates the same formulas on the tape (to differentiate them) and off it (to find points
and their constant factors).
"""

from __future__ import annotations

import numpy as np

from minidiff import kernels
from minidiff.primitives import cross, dot, reshape, sqrt
from minidiff.tensor import Tensor
from minidiff.trace import Traced


def _taped(*values) -> bool:
    """Whether any value is a Tensor, or a traced array inside ``minidiff.compile`` (then
    the primitives record the formula for the compiler)."""
    return any(isinstance(v, (Tensor, Traced)) for v in values)


def dot_last(a, b):
    """The dot product over the last axis: (..., n) and (..., n), broadcast -> (...). On
    plain 3-vectors minidiff's kernel (``kernels.dot_last``: NumPy's sums bit for bit)."""
    if _taped(a, b):
        return dot(a, b)
    a, b = np.asarray(a), np.asarray(b)
    if a.shape[-1] == 3 and b.shape[-1] == 3:
        return kernels.dot_last(a, b)
    return np.sum(a * b, axis=-1)


def cross_last(a, b):
    """The cross product over the last axis: (..., 3) and (..., 3), broadcast."""
    return cross(a, b) if _taped(a, b) else np.cross(a, b)


def as_column(x):
    """(k,) -> (k, 1), so that a per-point scalar scales the components of a vector."""
    return reshape(x, (-1, 1)) if _taped(x) else np.reshape(x, (-1, 1))


def square_root(x):
    """The element-wise square root."""
    return sqrt(x) if _taped(x) else np.sqrt(x)
