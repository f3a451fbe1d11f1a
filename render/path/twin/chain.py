"""Path replay's bookkeeping for the compiled path tracer (``render.path.twin.kernel``): the
chain of one path's vertices, and the gradient vector its replay adds to.

A path's radiance is sum_k beta_k C_k with beta_{k+1} = beta_k F_k, so its derivative is
sum_k beta_k (dC_k + dF_k R_k), R_k = C_{k+1} + F_{k+1} R_{k+1} the radiance that reaches
vertex k from the rest of the path (``docs/path_tracing.md``). The kernel adds the dC_k
terms as it traces the path and writes each vertex's row of the chain (the layout
``_C_*``); when the path has ended, ``_replay_chain`` computes R_k and
``_factor_gradients`` adds the dF_k R_k terms to the gradient vector (the layout ``_G_*``,
which ``render.path.twin.adjoint`` maps onto the scene's parameters).
"""

from __future__ import annotations

import numpy as np

from minidiff.threads import borrowing
from render.path.twin.scalar import _brdf_adjoint

#: Path replay's gradient vector: per object (``_G_OBJECT`` entries from ``_G_OBJECT * o``)
#: albedo (3), specular (3), shininess, reflectance (3), emission (3); then per light
#: (``_G_LIGHT`` entries) its strength (intensity or irradiance) and colour (3); then the
#: environment (3).
_G_ALBEDO, _G_SPECULAR, _G_SHININESS, _G_REFLECTANCE, _G_EMISSION = 0, 3, 6, 7, 10
_G_OBJECT, _G_LIGHT = 13, 4

#: A path's chain for path replay, per vertex k: C_k (3), F_k (3), the environment seen
#: after it (3), R_k (3); and what d F_k needs: the object, whether the bounce is a
#: mirror's, the cosine over the density (a mirror: 1 / the density), the shading normal,
#: the view and the new direction (3 each), the specular colour (3), the shininess,
#: whether the lobe and a texture are on, and the throughput before the vertex (3).
_C_ADDED, _C_FACTOR, _C_ESCAPE, _C_REST = 0, 3, 6, 9
_C_OBJECT, _C_MIRROR, _C_COS, _C_NORMAL, _C_VIEW, _C_DIRECTION = 12, 13, 14, 15, 18, 21
_C_SPECULAR, _C_SHININESS, _C_LOBE, _C_TEXTURED, _C_BETA = 24, 27, 28, 29, 30
_C_FIELDS = 33


@borrowing
def _replay_chain(chain):
    """Fill chain[k, _C_REST:] with R_k = E_k + C_{k+1} + F_{k+1} R_{k+1}: the radiance
    that reaches vertex k from the rest of its path (E_k: the environment, if the path
    leaves the scene after vertex k; rows past the path's end are zero)."""
    depth = chain.shape[0]
    for k in range(depth - 1, -1, -1):
        for c in range(3):
            rest = chain[k, _C_ESCAPE + c]
            if k + 1 < depth:
                after = chain[k + 1, _C_ADDED + c]
                rest += after + chain[k + 1, _C_FACTOR + c] * chain[k + 1, _C_REST + c]
            chain[k, _C_REST + c] = rest


@borrowing
def _factor_gradients(chain, delta, grad):
    """Add each vertex's delta . beta_k dF_k R_k to ``grad``, from the chain that
    ``_trace_path`` recorded and ``_replay_chain`` completed (rows of vertices that did
    not go on hold a zero throughput and add nothing)."""
    for k in range(chain.shape[0]):
        row = chain[k]
        if row[_C_BETA] == 0.0 and row[_C_BETA + 1] == 0.0 and row[_C_BETA + 2] == 0.0:
            continue  # past the path's end (or no throughput left): nothing to add
        w = (delta[0] * row[_C_BETA] * row[_C_REST], delta[1] * row[_C_BETA + 1] * row[_C_REST + 1],
             delta[2] * row[_C_BETA + 2] * row[_C_REST + 2])  # fmt: skip
        g_object = _G_OBJECT * np.int64(row[_C_OBJECT])
        scale = row[_C_COS]
        if row[_C_MIRROR] > 0.0:
            for c in range(3):
                grad[g_object + _G_REFLECTANCE + c] += w[c] * scale
        else:
            w = (w[0] * scale, w[1] * scale, w[2] * scale)
            normal = (row[_C_NORMAL], row[_C_NORMAL + 1], row[_C_NORMAL + 2])
            view = (row[_C_VIEW], row[_C_VIEW + 1], row[_C_VIEW + 2])
            direction = (row[_C_DIRECTION], row[_C_DIRECTION + 1], row[_C_DIRECTION + 2])
            specular = (row[_C_SPECULAR], row[_C_SPECULAR + 1], row[_C_SPECULAR + 2])
            _brdf_adjoint(normal, view, direction, specular, row[_C_SHININESS],
                          row[_C_LOBE] > 0.0, row[_C_TEXTURED] > 0.0, w, grad,
                          g_object)  # fmt: skip
