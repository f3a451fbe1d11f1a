"""The quadrature points of the cut pieces, dealt out to their curve kinds.

``render.edges.boundary.term.boundary_points`` cuts every kind's segments together
(``render.edges.boundary.pixels``) and hands each kind back the quadrature points on its
own segments: ``quadrature``, the image plane's coordinates, a mask per kind, in NumPy.
(A compiled, parallel twin of this was deleted: it was no faster on the paper scene at
512x512, where the boundary term's forward and backward took 352-360 ms with the NumPy
statement and 365-374 ms with the twin.)
"""

from __future__ import annotations

import numpy as np

from render.edges.boundary.pixels import GAUSS_POINTS, quadrature
from render.scene.camera import to_image_plane


def kind_points(p0, p1, pieces, counts, width: int, height: int) -> list[tuple]:
    """Per kind (``counts`` (K,): how many of the segments p0 -> p1 (n, 2), pixel
    coordinates, are each kind's, in kind order): the quadrature points on the ``pieces``
    (segment, start, end, pixel (m,) each: ``split_at_crossings``) of its segments, as
    (its own segment index (g,), image-plane coords (g, 2), pixel (g,), weight (g,), key
    (g,): the point's row among all kinds' points), in the pieces' order."""
    at, segment, weight = quadrature(p0, p1, *pieces[:3])
    pixel = np.repeat(pieces[3], GAUSS_POINTS)
    coords = to_image_plane(at, width, height)
    owner = np.repeat(np.arange(len(counts)), counts)[segment]
    own_segment = segment - (np.cumsum(counts) - counts)[owner]
    found = []
    for k in range(len(counts)):
        rows = np.flatnonzero(owner == k)
        found.append(
            (own_segment[rows], np.take(coords, rows, axis=0), pixel[rows], weight[rows], rows)
        )
    return found
