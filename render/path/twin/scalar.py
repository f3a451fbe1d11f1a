"""The compiled path tracer's per-path arithmetic (Numba, one path at a time): vectors, the
sampling densities, the BRDF, the surface at a hit, the textures, and the two ray queries.
Each function is the scalar twin of a minidiff or tape function named in its docstring
(``render.path.sample.sampling``, ``render.path.sample.choices``, ``render.shade.lighting``,
``render.shade.surface``), the same formula in the same order of operations where the
order matters. (The random numbers are ``render.path.sample.random``'s own Numba hash.)

The arrays are ``render.path.twin.packed.Packed``'s (each function takes the ones it reads:
handed over one by one, not as the whole tuple, which Numba would copy at every call).
"""

from __future__ import annotations

import math

import numpy as np

from minidiff.threads import borrowing, jit
from render.path.sample.random import BOUNCE_DIMENSIONS, DIMENSIONS_PER_BOUNCE
from render.trace.vec3 import dot3


@jit(cache=True, inline="always")
def sample_rgb(texture, u, v):
    """The bilinear lookup of an (H, W, 3) texture at UV (u, v), repeating
    (``render.shade.lighting.sample_texture`` for one point): its three channels, and the
    footprint's cell. One inlined copy serves all three channels: a copy per channel made
    every kernel that inlines it compile for longer."""
    height, width = texture.shape[0], texture.shape[1]
    # The UV modulo 1 first, as ``lighting._footprint`` takes it: the cell's column is
    # then in [-1, width - 1] (-1 wraps to the last), whatever the UV's size.
    x = (u - np.floor(u)) * width - 0.5
    y = (1.0 - (v - np.floor(v))) * height - 0.5
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = x - x0, y - y0
    ix0 = int(x0) if x0 >= 0.0 else width - 1
    iy0 = int(y0) if y0 >= 0.0 else height - 1
    ix1 = int(x0) + 1 if x0 + 1.0 < width else 0
    iy1 = int(y0) + 1 if y0 + 1.0 < height else 0
    return (
        _bilinear(texture, iy0, ix0, iy1, ix1, fx, fy, 0),
        _bilinear(texture, iy0, ix0, iy1, ix1, fx, fy, 1),
        _bilinear(texture, iy0, ix0, iy1, ix1, fx, fy, 2),
        iy0 * width + ix0,
    )


@jit(cache=True, inline="always")
def _bilinear(texture, iy0, ix0, iy1, ix1, fx, fy, c):
    """Channel c of ``sample_rgb``: the four texels' weighted sum."""
    top = texture[iy0, ix0, c] * (1.0 - fx) + texture[iy0, ix1, c] * fx
    bottom = texture[iy1, ix0, c] * (1.0 - fx) + texture[iy1, ix1, c] * fx
    return top * (1.0 - fy) + bottom * fy


@jit(cache=True)
def _unit(x0, x1, x2):
    """``md.normalize`` of one 3-vector: x times 1 / |x| (the zero vector stays zero)."""
    length = math.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
    inv = 1.0 / length if length > 0 else 0.0
    return x0 * inv, x1 * inv, x2 * inv


# --- random numbers: render.path.sample.random's hash for one path and dimension -----------

_LOBE = BOUNCE_DIMENSIONS["lobe"]
_DIRECTION = BOUNCE_DIMENSIONS["direction"]
_ROULETTE = BOUNCE_DIMENSIONS["roulette"]
_EMITTER = BOUNCE_DIMENSIONS["emitter"]
_EMITTER_POINT = BOUNCE_DIMENSIONS["emitter_point"]


@jit(cache=True)
def _dim(depth, j):
    """``render.path.sample.random.bounce_dimension``."""
    return 2 + DIMENSIONS_PER_BOUNCE * (depth - 1) + j


# --- small vector helpers ----------------------------------------------------------------------


@jit(cache=True)
def _divided(x0, x1, x2):
    """x / |x| (``np.linalg.norm`` then a division, as the sampler's ``unit``)."""
    length = math.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
    if length > 0:
        return x0 / length, x1 / length, x2 / length
    return x0, x1, x2


@borrowing
def _put(records, k, row, column, x):
    """Write the 3-tuple x to records[k, row, column:column + 3]."""
    records[k, row, column] = x[0]
    records[k, row, column + 1] = x[1]
    records[k, row, column + 2] = x[2]


@borrowing
def _basis(n):
    """``render.path.sample.sampling.orthonormal_basis`` of one unit normal."""
    sign = 1.0 if n[2] >= 0 else -1.0
    a = -1.0 / (sign + n[2])
    b = n[0] * n[1] * a
    s = (1.0 + sign * n[0] ** 2 * a, sign * b, -sign * n[0])
    t = (b, sign + n[1] ** 2 * a, -n[1])
    return s, t


@borrowing
def _to_world(l0, l1, l2, n):
    s, t = _basis(n)
    return (
        l0 * s[0] + l1 * t[0] + l2 * n[0],
        l0 * s[1] + l1 * t[1] + l2 * n[1],
        l0 * s[2] + l1 * t[2] + l2 * n[2],
    )


@jit(cache=True)
def _power(p, q):
    total = p * p + q * q
    return p * p / total if total > 0 else 0.0


@borrowing
def _glossy_pdf(n, view, w, shininess):
    """``render.path.sample.sampling.blinn_phong_pdf`` of one direction."""
    h = _divided(view[0] + w[0], view[1] + w[1], view[2] + w[2])
    cos_h = max(dot3(n, h), 0.0)
    vh = abs(dot3(view, h))
    if not (vh > 0 and dot3(n, w) > 0):
        return 0.0
    return (shininess + 1.0) / (2.0 * math.pi) * cos_h**shininess / (4.0 * vh)


@borrowing
def _pdf(p_diffuse, p_glossy, shininess, ns, wo, wi):
    """``PathSampler._pdf``: the density of the diffuse-or-glossy choice at wi (the glossy
    lobe's, and its power, only where the material has one: 0 x its finite pdf is 0)."""
    glossy = _glossy_pdf(ns, wo, wi, shininess) if p_glossy > 0 else 0.0
    return p_diffuse * (max(dot3(ns, wi), 0.0) / math.pi) + p_glossy * glossy


@borrowing
def _lobe(ns, view, wi, shininess):
    """The Blinn-Phong lobe's n.h (clamped as the tape clamps it, >= 1e-12) and
    (n.h)^shininess."""
    h = _unit(wi[0] + view[0], wi[1] + view[1], wi[2] + view[2])
    n_dot_h = max(dot3(ns, h), 1e-12)
    return n_dot_h, n_dot_h**shininess


@borrowing
def _brdf(ns, view, wi, albedo, specular, shininess, lobe_on):
    """``render.shade.lighting.brdf`` (3-tuple): albedo / pi plus the energy-normalised
    Blinn-Phong lobe specular (n + 8) / (8 pi) (n.h)^n where ``lobe_on`` (the material's
    specular is non-zero or differentiated)."""
    inv_pi = 1.0 / math.pi
    f0, f1, f2 = albedo[0] * inv_pi, albedo[1] * inv_pi, albedo[2] * inv_pi
    if lobe_on:
        power = _lobe(ns, view, wi, shininess)[1]
        lobe = power * ((shininess + 8.0) / (8.0 * math.pi))
        f0, f1, f2 = f0 + lobe * specular[0], f1 + lobe * specular[1], f2 + lobe * specular[2]
    return f0, f1, f2


@borrowing
def _surface(triangles, centers, prim_object, smooth, corners, normals, uvs, prim, point, u, v):
    """At a point on primitive ``prim`` (barycentrics u, v on a triangle): the object, the
    unit geometric normal, the shading normal and the UV, and the coordinates ``local``."""
    o = prim_object[prim]
    n_tri = triangles.shape[0]
    if prim < n_tri:
        ng = _triangle_normal(triangles, prim)
        local = (u, v, 0.0)
        ns = ng
        w0 = 1.0 - u - v
        ia, ib, ic = corners[prim, 0], corners[prim, 1], corners[prim, 2]
        if smooth[o]:
            ns = _divided(
                w0 * normals[ia, 0] + u * normals[ib, 0] + v * normals[ic, 0],
                w0 * normals[ia, 1] + u * normals[ib, 1] + v * normals[ic, 1],
                w0 * normals[ia, 2] + u * normals[ib, 2] + v * normals[ic, 2],
            )
        uv = (
            w0 * uvs[ia, 0] + u * uvs[ib, 0] + v * uvs[ic, 0],
            w0 * uvs[ia, 1] + u * uvs[ib, 1] + v * uvs[ic, 1],
        )
    else:
        k = prim - n_tri
        ng = _divided(point[0] - centers[k, 0], point[1] - centers[k, 1], point[2] - centers[k, 2])
        local, ns, uv = ng, ng, (0.0, 0.0)
    return o, ng, ns, uv, local


@borrowing
def _look(albedo, specular, maps, texels, o, uv):
    """The albedo and specular colours of object o at UV ``uv`` (its textures sampled)."""
    kd = (albedo[o, 0], albedo[o, 1], albedo[o, 2])
    ks = (specular[o, 0], specular[o, 1], specular[o, 2])
    # One loop over the two maps (0: albedo, 1: specular), so that the lookup is compiled
    # once: written out twice, this function took 1.3 s of a cold compile.
    for which in range(2):
        if maps[o, which, 0] >= 0:
            start, h, w = maps[o, which, 0], maps[o, which, 1], maps[o, which, 2]
            t = texels[start : start + h * w].reshape((h, w, 3))
            m0, m1, m2, _ = sample_rgb(t, uv[0], uv[1])
            if which == 0:
                kd = (m0, m1, m2)
            else:
                ks = (ks[0] * m0, ks[1] * m1, ks[2] * m2)
    return kd, ks


@borrowing
def _point_on(triangles, centers, radii, prim, u1, u2):
    """NEE's point on an emitter (``render.path.sample.choices``) for one primitive: local, point,
    unit normal (a uniform point by Turk's square-root warp on a triangle, by Archimedes on
    a sphere)."""
    if prim < triangles.shape[0]:
        root = math.sqrt(u1)
        local = (u2 * root, 1.0 - root, 0.0)
        normal = _triangle_normal(triangles, prim)
    else:
        z = 1.0 - 2.0 * u1
        r = math.sqrt(max(1.0 - z * z, 0.0))
        phi = 2.0 * math.pi * u2
        local = (r * math.cos(phi), r * math.sin(phi), z)
        normal = local
    return local, _placed(triangles, centers, radii, prim, local), normal


@borrowing
def _triangle_normal(triangles, prim):
    """The unit normal (b - a) x (c - a) / |.| of triangle ``prim``."""
    a, b, c = triangles[prim, 0], triangles[prim, 1], triangles[prim, 2]
    e1 = (b[0] - a[0], b[1] - a[1], b[2] - a[2])
    e2 = (c[0] - a[0], c[1] - a[1], c[2] - a[2])
    return _divided(
        e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0]
    )


@borrowing
def _reintersect(triangles, centers, radii, prim, o, d):
    """Where the ray o + t d meets primitive ``prim`` as the tape finds it
    (``surface_at`` from rays: the triangle's plane, or the sphere's root on the far side
    of the ray's start when it starts inside): the point and its barycentrics (u, v)."""
    n_tri = triangles.shape[0]
    if prim < n_tri:
        a, b, c = triangles[prim, 0], triangles[prim, 1], triangles[prim, 2]
        e1 = (b[0] - a[0], b[1] - a[1], b[2] - a[2])
        e2 = (c[0] - a[0], c[1] - a[1], c[2] - a[2])
        p = (d[1] * e2[2] - d[2] * e2[1], d[2] * e2[0] - d[0] * e2[2], d[0] * e2[1] - d[1] * e2[0])
        inv_det = 1.0 / dot3(e1, p)
        q0 = (o[0] - a[0], o[1] - a[1], o[2] - a[2])
        q = (q0[1] * e1[2] - q0[2] * e1[1], q0[2] * e1[0] - q0[0] * e1[2],
             q0[0] * e1[1] - q0[1] * e1[0])  # fmt: skip
        t = dot3(e2, q) * inv_det
        u, v = dot3(q0, p) * inv_det, dot3(d, q) * inv_det
    else:
        k = prim - n_tri
        oc = (o[0] - centers[k, 0], o[1] - centers[k, 1], o[2] - centers[k, 2])
        a2, b2 = dot3(d, d), dot3(oc, d)
        c2 = dot3(oc, oc) - radii[k] * radii[k]
        root = math.sqrt(max(b2 * b2 - a2 * c2, max(b2 * b2 * 1e-16, 2.2250738585072014e-308)))
        sign = 1.0 if math.sqrt(dot3(oc, oc)) < radii[k] else -1.0
        t = (-b2 + sign * root) / a2
        u = v = 0.0
    return (o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]), u, v


@borrowing
def _local(triangles, centers, prim, point, u, v):
    """``PathSampler.local_coordinates``: (u, v, 0) on a triangle, the unit direction from
    a sphere's centre."""
    if prim < triangles.shape[0]:
        return (u, v, 0.0)
    k = prim - triangles.shape[0]
    return _divided(point[0] - centers[k, 0], point[1] - centers[k, 1], point[2] - centers[k, 2])


@borrowing
def _placed(triangles, centers, radii, prim, local):
    """The point at coordinates ``local`` on primitive ``prim`` (``surface_at(local=)``)."""
    n_tri = triangles.shape[0]
    if prim < n_tri:
        a, b, c = triangles[prim, 0], triangles[prim, 1], triangles[prim, 2]
        u, v = local[0], local[1]
        return (a[0] + u * (b[0] - a[0]) + v * (c[0] - a[0]),
                a[1] + u * (b[1] - a[1]) + v * (c[1] - a[1]),
                a[2] + u * (b[2] - a[2]) + v * (c[2] - a[2]))  # fmt: skip
    k = prim - n_tri
    return (centers[k, 0] + radii[k] * local[0], centers[k, 1] + radii[k] * local[1],
            centers[k, 2] + radii[k] * local[2])  # fmt: skip
