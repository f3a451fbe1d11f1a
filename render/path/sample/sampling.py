"""Sampling: directions, points on emitters, and their densities, written once on minidiff
arrays.

These choose *where* a path goes (discrete, like visibility: constants on the tape). Every
density is the one the samples were drawn with, so that an estimate f / p is unbiased;
``render.path.gradient.transport`` recomputes f on the tape and divides by these p as constants.
The sampler (``render.path.sample.choices``) runs them inside one compiled function per vertex;
called on plain arrays they run primitive by primitive and return minidiff tensors (``.data``
for the array). Shapes: k samples per call, directions and normals (k, 3) unit vectors.

``dot`` and ``unit`` are plain helpers for the code around the sampler (shadow and
silhouette geometry off the tape).
"""

from __future__ import annotations

import math

import numpy as np

import minidiff as md
from render.shade.surface import divided_unit


def dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(k,) row-wise dot products of plain (k, 3) arrays."""
    return np.einsum("ij,ij->i", a, b)


def unit(v: np.ndarray) -> np.ndarray:
    """Plain (k, 3) rows scaled to unit length (zero rows stay zero): ``divided_unit``'s."""
    return divided_unit(v).data


def orthonormal_basis(n):
    """Two unit tangents (k, 3) completing unit normals n (k, 3) to a right-handed frame
    (Duff et al. 2017, "Building an orthonormal basis, revisited": no branch, no
    normalisation, exact at n = -z)."""
    x, y, z = n[:, 0], n[:, 1], n[:, 2]
    sign = md.where(z >= 0, 1.0, -1.0)
    a = -1.0 / (sign + z)
    b = x * y * a
    s = md.stack([1.0 + sign * x**2 * a, sign * b, -sign * x], axis=1)
    t = md.stack([b, sign + y**2 * a, -y], axis=1)
    return s, t


def to_world(local, n):
    """Local directions (k, 3) (z along the normal) in the world frame of normals n (k, 3)."""
    s, t = orthonormal_basis(n)
    return local[:, 0:1] * s + local[:, 1:2] * t + local[:, 2:3] * n


def cosine_hemisphere(u1, u2, n):
    """Directions (k, 3) around normals n (k, 3) with density cos(theta) / pi (Malley's
    method: a uniform point on the unit disc, lifted to the hemisphere)."""
    r, phi = md.sqrt(u1), 2.0 * math.pi * u2
    lift = md.sqrt(md.maximum(1.0 - u1, 0.0))
    return to_world(md.stack([r * md.cos(phi), r * md.sin(phi), lift], axis=1), n)


def cosine_pdf(n, w):
    """(k,) the density of ``cosine_hemisphere`` at directions w (k, 3), per steradian."""
    return md.maximum(md.dot(n, w), 0.0) / math.pi


def blinn_phong_lobe(u1, u2, n, view, shininess):
    """Directions (k, 3) for the Blinn-Phong lobe max(0, n.h)^s: a half vector h drawn with
    density (s + 1) / (2 pi) (n.h)^s around n, and ``view`` (k, 3, unit, towards the
    viewer) reflected about it. Directions below the surface come out as they are; their
    lobe value is zero and the caller ends such paths."""
    cos_h = u1 ** (1.0 / (shininess + 1.0))
    sin_h = md.sqrt(md.maximum(1.0 - cos_h**2, 0.0))
    phi = 2.0 * math.pi * u2
    h = to_world(md.stack([sin_h * md.cos(phi), sin_h * md.sin(phi), cos_h], axis=1), n)
    return 2.0 * md.reshape(md.dot(view, h), (-1, 1)) * h - view


def blinn_phong_pdf(n, view, w, shininess):
    """(k,) the density of ``blinn_phong_lobe`` at directions w (k, 3), per steradian: the
    half vector's density over the Jacobian 4 |view . h| of the reflection."""
    h = divided_unit(view + w)
    cos_h = md.maximum(md.dot(n, h), 0.0)
    vh = md.abs(md.dot(view, h))
    pdf_h = (shininess + 1.0) / (2.0 * math.pi) * cos_h**shininess
    seen = (vh > 0) & (md.dot(n, w) > 0)
    return md.where(seen, pdf_h / md.where(vh > 0, 4.0 * vh, 1.0), 0.0)


def triangle_point(u1, u2):
    """(k, 2) barycentrics (u, v) uniform over a triangle (point (1 - u - v) a + u b + v c;
    Turk 1990's square-root warp)."""
    root = md.sqrt(u1)
    return md.stack([u2 * root, 1.0 - root], axis=1)


def sphere_direction(u1, u2):
    """(k, 3) unit vectors uniform over the sphere (Archimedes: z uniform in [-1, 1])."""
    z = 1.0 - 2.0 * u1
    r = md.sqrt(md.maximum(1.0 - z * z, 0.0))
    phi = 2.0 * math.pi * u2
    return md.stack([r * md.cos(phi), r * md.sin(phi), z], axis=1)


def power_heuristic(p, q):
    """(k,) Veach's power heuristic (beta = 2): the weight p^2 / (p^2 + q^2) of the strategy
    with density p against one with density q (both in the same measure); 0 where both are 0."""
    p2, q2 = p * p, q * q
    total = p2 + q2
    return md.where(total > 0, p2 / md.where(total > 0, total, 1.0), 0.0)
