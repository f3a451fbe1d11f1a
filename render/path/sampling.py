"""Sampling in plain NumPy: directions, points on emitters, and their densities.

These choose *where* a path goes (discrete, like visibility: constants on the tape). Every
density is the one the samples were drawn with, so that an estimate f / p is unbiased;
``render.path.transport`` recomputes f on the tape and divides by these p as constants.
Shapes: k samples per call, directions and normals (k, 3) unit vectors.
"""

from __future__ import annotations

import math

import numpy as np


def dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(k,) row-wise dot products of (k, 3) arrays."""
    return np.einsum("ij,ij->i", a, b)


def unit(v: np.ndarray) -> np.ndarray:
    """(k, 3) rows scaled to unit length (zero rows stay zero)."""
    n = np.linalg.norm(v, axis=1, keepdims=True)
    return v / np.where(n > 0, n, 1.0)


def orthonormal_basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents (k, 3) completing unit normals n (k, 3) to a right-handed frame
    (Duff et al. 2017, "Building an orthonormal basis, revisited": no branch, no
    normalisation, exact at n = -z)."""
    sign = np.where(n[:, 2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    s = np.stack([1.0 + sign * n[:, 0] ** 2 * a, sign * b, -sign * n[:, 0]], axis=1)
    t = np.stack([b, sign + n[:, 1] ** 2 * a, -n[:, 1]], axis=1)
    return s, t


def to_world(local: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Local directions (k, 3) (z along the normal) in the world frame of normals n (k, 3)."""
    s, t = orthonormal_basis(n)
    return local[:, :1] * s + local[:, 1:2] * t + local[:, 2:] * n


def cosine_hemisphere(u1: np.ndarray, u2: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Directions (k, 3) around normals n (k, 3) with density cos(theta) / pi (Malley's
    method: a uniform point on the unit disc, lifted to the hemisphere)."""
    r, phi = np.sqrt(u1), 2.0 * math.pi * u2
    local = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(1.0 - u1, 0.0))], 1)
    return to_world(local, n)


def cosine_pdf(n: np.ndarray, w: np.ndarray) -> np.ndarray:
    """(k,) the density of ``cosine_hemisphere`` at directions w (k, 3), per steradian."""
    return np.maximum(dot(n, w), 0.0) / math.pi


def blinn_phong_lobe(
    u1: np.ndarray, u2: np.ndarray, n: np.ndarray, view: np.ndarray, shininess: np.ndarray
) -> np.ndarray:
    """Directions (k, 3) for the Blinn-Phong lobe max(0, n.h)^s: a half vector h drawn with
    density (s + 1) / (2 pi) (n.h)^s around n, and ``view`` (k, 3, unit, towards the
    viewer) reflected about it. Directions below the surface come out as they are; their
    lobe value is zero and the caller ends such paths."""
    cos_h = u1 ** (1.0 / (shininess + 1.0))
    sin_h = np.sqrt(np.maximum(1.0 - cos_h**2, 0.0))
    phi = 2.0 * math.pi * u2
    h = to_world(np.stack([sin_h * np.cos(phi), sin_h * np.sin(phi), cos_h], 1), n)
    return 2.0 * dot(view, h)[:, None] * h - view


def blinn_phong_pdf(
    n: np.ndarray, view: np.ndarray, w: np.ndarray, shininess: np.ndarray
) -> np.ndarray:
    """(k,) the density of ``blinn_phong_lobe`` at directions w (k, 3), per steradian: the
    half vector's density over the Jacobian 4 |view . h| of the reflection."""
    h = unit(view + w)
    cos_h = np.maximum(dot(n, h), 0.0)
    vh = np.abs(dot(view, h))
    pdf_h = (shininess + 1.0) / (2.0 * math.pi) * cos_h**shininess
    return np.where((vh > 0) & (dot(n, w) > 0), pdf_h / np.where(vh > 0, 4.0 * vh, 1.0), 0.0)


def triangle_point(u1: np.ndarray, u2: np.ndarray) -> np.ndarray:
    """(k, 2) barycentrics (u, v) uniform over a triangle (point (1 - u - v) a + u b + v c;
    Turk 1990's square-root warp)."""
    root = np.sqrt(u1)
    return np.stack([u2 * root, 1.0 - root], axis=1)


def sphere_direction(u1: np.ndarray, u2: np.ndarray) -> np.ndarray:
    """(k, 3) unit vectors uniform over the sphere (Archimedes: z uniform in [-1, 1])."""
    z = 1.0 - 2.0 * u1
    r = np.sqrt(np.maximum(1.0 - z * z, 0.0))
    phi = 2.0 * math.pi * u2
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def power_heuristic(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(k,) Veach's power heuristic (beta = 2): the weight p^2 / (p^2 + q^2) of the strategy
    with density p against one with density q (both in the same measure); 0 where both are 0."""
    p2, q2 = p * p, q * q
    total = p2 + q2
    return np.where(total > 0, p2 / np.where(total > 0, total, 1.0), 0.0)
