"""Two 3-vector helpers for the hand-written Numba kernels (the light's view, the mesh
edges' sides and crossings): written out, because NumPy's ``np.cross`` and ``@`` compile to
Numba code with shape checks and error messages that took over a second of a cold start."""

from __future__ import annotations

import numba


@numba.njit(cache=True, error_model="numpy")
def dot3(x, y):
    """x . y of two 3-vectors, summed left to right."""
    return x[0] * y[0] + x[1] * y[1] + x[2] * y[2]


@numba.njit(cache=True, error_model="numpy")
def cross3(x, y, out):
    """out = x cross y, three 3-vectors (``np.cross``'s arithmetic, term for term)."""
    out[0] = x[1] * y[2] - x[2] * y[1]
    out[1] = x[2] * y[0] - x[0] * y[2]
    out[2] = x[0] * y[1] - x[1] * y[0]
