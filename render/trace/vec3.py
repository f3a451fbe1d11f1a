"""3-vector helpers and float64's epsilon for the hand-written Numba kernels (the
light's view, the rasteriser, the BVH's boxes, the mesh edges' sides and crossings):
written out, because NumPy's ``np.cross``, ``@`` and ``np.finfo`` compile to Numba code with
shape checks and error messages that took over a second of a cold start."""

from __future__ import annotations

import numpy as np

from minidiff.threads import jit

#: Float64's machine epsilon, a constant to the compiled code.
EPS = float(np.finfo(np.float64).eps)


@jit(cache=True)
def dot3(x, y):
    """x . y of two 3-vectors, summed left to right."""
    return x[0] * y[0] + x[1] * y[1] + x[2] * y[2]


@jit(cache=True, inline="always")
def cross(x, y):
    """x cross y of two 3-vectors (tuples or rows), a 3-tuple (``np.cross``'s arithmetic,
    term for term)."""
    return (x[1] * y[2] - x[2] * y[1], x[2] * y[0] - x[0] * y[2], x[0] * y[1] - x[1] * y[0])


@jit(cache=True, inline="always")
def sub(x, y):
    """x - y of two 3-tuples (or rows), a 3-tuple."""
    return (x[0] - y[0], x[1] - y[1], x[2] - y[2])
