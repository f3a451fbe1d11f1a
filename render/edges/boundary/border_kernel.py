"""The shadow borders' quadrature points moved onto their borders in one compiled pass.

``render.edges.boundary.shadow_border`` states, in NumPy, how a quadrature point on a
border's chord is moved onto the border (``onto_border``: Newton steps on e along its
image-plane gradient, ``border_gradient``) and which factors it then needs
(``_border_factors``: |grad e| in pixels, the step one pixel along it, where the camera
sees the receiver just either side). ``border_points`` does all of that per point in one
parallel Numba pass, with the same operations in the same order (each dot product
(a0 b0 + a1 b1) + a2 b2, as minidiff's ``dot_last`` sums it; each cross product as
``np.cross`` forms it), so that it gives the NumPy statement's numbers to the last bit or
to rounding; ``tests/render/edges/test_border_kernel.py`` ties the two. The points are
shared out in blocks (``render.trace.intersect._jobs``): each writes only its own rows, so
the results do not depend on the thread count.

What is left to NumPy: which points are hidden (``hidden_points``, itself compiled) and
the radiance either side (the renderer's ``SideRadiance``).
"""

from __future__ import annotations

import numba
import numpy as np

from render.edges.boundary.radiance import EPSILON
from render.scene.lights import DirectionalLight, PointLight
from render.scene.scene import Scene
from render.trace.intersect import BLOCK, _jobs

#: The light kinds of the kernel: a point light (its position) and a directional light
#: (its direction of travel as given, not normalised: ``Light.edge_plane``, ``ray_to``).
AT_POINT, AT_INFINITY = 0, 1


def kernel_lights(scene: Scene) -> tuple[np.ndarray, np.ndarray] | None:
    """(kind (L,) int64, vector (L, 3) float64) of the scene's lights for ``border_points``
    (AT_POINT with the position, AT_INFINITY with the direction of travel), or None if one
    of them is of another class (then the NumPy statement, which asks the light itself,
    moves the points)."""
    kind, vector = np.zeros(len(scene.lights), np.int64), np.zeros((len(scene.lights), 3))
    for j, light in enumerate(scene.lights):
        if type(light) is PointLight:
            vector[j] = np.asarray(light.position.data, np.float64)
        elif type(light) is DirectionalLight:
            kind[j], vector[j] = AT_INFINITY, np.asarray(light.direction.data, np.float64)
        else:
            return None
    return kind, vector


@numba.njit(cache=True, error_model="numpy", inline="always")
def _dot(a0, a1, a2, b0, b1, b2):
    """a . b summed as minidiff's ``dot_last`` (and einsum's row loop) sums it."""
    return (a0 * b0 + a1 * b1) + a2 * b2


@numba.njit(cache=True, error_model="numpy", inline="always")
def _cross(a0, a1, a2, b0, b1, b2):
    """a x b formed as ``np.cross`` forms it."""
    return a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0


@numba.njit(cache=True, error_model="numpy")
def _receiver_hit(rec, radius, frame, x, y, direction_first, out):
    """Where the camera ray through image-plane (x, y) meets the receiver (``rec`` (2, 3):
    its normal or centre, a point on its plane; ``radius``: -1 for a triangle), as
    ``shadow_border._receiver_hits``: writes the direction d (out[0:3]), the point P
    (out[3:6]) and the receiver's normal n at P (out[6:9]); returns the depth t (NaN where
    the ray misses or runs along the plane). ``frame`` (4, 3): forward, right, up, eye.
    ``direction_first``: d summed as ``border_gradient`` sums it ((forward + x right) + y
    up), else as ``camera_directions`` does ((x right + y up) + forward). (Scalars and
    indices only: array views in this loop cost more than its arithmetic. Called, not
    inlined, six times per point: inlined, ``border_points`` compiled in ~9 s instead of
    ~5 s on a busy 2-core machine, to run ~0.2 ms faster on the teapot at 512x512.)"""
    for c in range(3):
        if direction_first:
            out[c] = (frame[0, c] + x * frame[1, c]) + y * frame[2, c]
        else:
            out[c] = (x * frame[1, c] + y * frame[2, c]) + frame[0, c]
    d0, d1, d2 = out[0], out[1], out[2]
    e0, e1, e2 = frame[3, 0], frame[3, 1], frame[3, 2]
    if radius < 0:
        t = _dot(
            rec[0, 0], rec[0, 1], rec[0, 2], rec[1, 0] - e0, rec[1, 1] - e1, rec[1, 2] - e2
        ) / _dot(rec[0, 0], rec[0, 1], rec[0, 2], d0, d1, d2)  # fmt: skip
    else:
        o0, o1, o2 = e0 - rec[0, 0], e1 - rec[0, 1], e2 - rec[0, 2]
        dd, bb = _dot(d0, d1, d2, d0, d1, d2), _dot(d0, d1, d2, o0, o1, o2)
        kappa = _dot(o0, o1, o2, o0, o1, o2) - radius * radius
        t = (-bb - np.sqrt(bb * bb - dd * kappa)) / dd
    if not np.isfinite(t):
        t = np.nan
    for c in range(3):
        out[3 + c] = frame[3, c] + t * out[c]
        out[6 + c] = rec[0, c] if radius < 0 else out[3 + c] - rec[0, c]
    return t


@numba.njit(cache=True, error_model="numpy", inline="always")
def _border_gradient(rec, radius, occ, kind, size, light_kind, frame, x, y, scratch, grad):
    """``shadow_border.border_gradient`` at one image-plane point (x, y): returns e and
    the depth t, writes grad e (2,) to ``grad`` (and d, P, n to ``scratch`` (9,)).
    ``rec``, ``radius``: the receiver (``_receiver_hit``); ``occ`` (3, 3): the occluder's
    m, base (as ``_border_rows``: an edge's plane e = m . (P - base), ``kind`` 0; a
    sphere's centre and radius ``size``, ``kind`` 1) and the light's vector
    (``light_kind`` AT_POINT: its position, AT_INFINITY: its direction of travel)."""
    t = _receiver_hit(rec, radius, frame, x, y, True, scratch)
    d0, d1, d2 = scratch[0], scratch[1], scratch[2]
    p0, p1, p2 = scratch[3], scratch[4], scratch[5]
    n0, n1, n2 = scratch[6], scratch[7], scratch[8]
    b0, b1, b2 = occ[1, 0], occ[1, 1], occ[1, 2]
    if kind == 0:
        g0, g1, g2 = occ[0, 0], occ[0, 1], occ[0, 2]
        e = _dot(g0, g1, g2, p0 - b0, p1 - b1, p2 - b2)
    else:  # sphere_ray, sphere_border, _sphere_border_gradient
        w0, w1, w2 = occ[2, 0], occ[2, 1], occ[2, 2]
        if light_kind == AT_POINT:
            o0, o1, o2 = w0 - b0, w1 - b1, w2 - b2
            u0, u1, u2 = p0 - w0, p1 - w1, p2 - w2
        else:
            o0, o1, o2 = p0 - b0, p1 - b1, p2 - b2
            u0, u1, u2 = w0, w1, w2
        ou = _dot(u0, u1, u2, o0, o1, o2)
        uu = _dot(u0, u1, u2, u0, u1, u2)
        e = ou * ou - uu * (_dot(o0, o1, o2, o0, o1, o2) - size * size)
        if light_kind == AT_POINT:
            kappa = _dot(o0, o1, o2, o0, o1, o2) - size * size
            a, b = 2.0 * ou, 2.0 * kappa
            g0, g1, g2 = a * o0 - b * u0, a * o1 - b * u1, a * o2 - b * u2
        else:
            a, b = 2.0 * ou, 2.0 * uu
            g0, g1, g2 = a * u0 - b * o0, a * u1 - b * o1, a * u2 - b * o2
    q = _dot(g0, g1, g2, d0, d1, d2) / _dot(n0, n1, n2, d0, d1, d2)
    gd0, gd1, gd2 = t * (g0 - q * n0), t * (g1 - q * n1), t * (g2 - q * n2)
    grad[0] = _dot(gd0, gd1, gd2, frame[1, 0], frame[1, 1], frame[1, 2])
    grad[1] = _dot(gd0, gd1, gd2, frame[2, 0], frame[2, 1], frame[2, 2])
    return e, t


@numba.njit(cache=True, error_model="numpy", inline="always")
def _point_rows(i, light, occluder, receiver, lights, meshes, spheres, prims, rec, occ):
    """Point i's receiver (``rec`` (2, 3): normal or centre, corner) and occluder (``occ``
    (3, 3): m, base, the light's vector), as ``shadow_border._border_rows`` gathers them;
    returns (receiver radius, occluder kind, occluder radius, light kind)."""
    light_kind, light_vector = lights
    vertices, first_vertex = meshes
    centres, radii = spheres
    triangles, prim_centres, prim_radii = prims
    j, r = light[i], receiver[i]
    for c in range(3):
        occ[2, c] = light_vector[j, c]
    n_tri = triangles.shape[0]
    if r < n_tri:
        a0, a1, a2 = triangles[r, 0, 0], triangles[r, 0, 1], triangles[r, 0, 2]
        rec[0, 0], rec[0, 1], rec[0, 2] = _cross(
            triangles[r, 1, 0] - a0, triangles[r, 1, 1] - a1, triangles[r, 1, 2] - a2,
            triangles[r, 2, 0] - a0, triangles[r, 2, 1] - a1, triangles[r, 2, 2] - a2,
        )  # fmt: skip
        rec[1, 0], rec[1, 1], rec[1, 2] = a0, a1, a2
        radius = -1.0
    else:
        for c in range(3):
            rec[0, c], rec[1, c] = prim_centres[r - n_tri, c], 0.0
        radius = prim_radii[r - n_tri]
    mesh = occluder[i, 0]
    if mesh < 0:  # a sphere: its centre and radius
        s = occluder[i, 1]
        for c in range(3):
            occ[0, c], occ[1, c] = 0.0, centres[s, c]
        return radius, 1, radii[s], light_kind[j]
    vi, vj = first_vertex[mesh] + occluder[i, 1], first_vertex[mesh] + occluder[i, 2]
    w0, w1, w2 = occ[2, 0], occ[2, 1], occ[2, 2]
    if light_kind[j] == AT_POINT:  # PointLight.edge_plane
        occ[0, 0], occ[0, 1], occ[0, 2] = _cross(
            vertices[vi, 0] - w0, vertices[vi, 1] - w1, vertices[vi, 2] - w2,
            vertices[vj, 0] - w0, vertices[vj, 1] - w1, vertices[vj, 2] - w2,
        )  # fmt: skip
        for c in range(3):
            occ[1, c] = occ[2, c]
    else:  # DirectionalLight.edge_plane
        occ[0, 0], occ[0, 1], occ[0, 2] = _cross(
            vertices[vj, 0] - vertices[vi, 0], vertices[vj, 1] - vertices[vi, 1],
            vertices[vj, 2] - vertices[vi, 2], w0, w1, w2,
        )  # fmt: skip
        for c in range(3):
            occ[1, c] = vertices[vi, c]
    return radius, 0, 0.0, light_kind[j]


@numba.njit(cache=True, error_model="numpy", parallel=True)
def border_points(
    coords, light, occluder, receiver, lights, meshes, spheres, prims, frame, width, height,
    steps, n_threads, out,
):  # fmt: skip
    """The k points ``coords`` (k, 2) (image plane) on their chords moved onto their
    borders (``onto_border``'s ``steps`` Newton steps) and their factors' geometry
    (``_border_factors``), per point i: its ``light`` (k,), ``occluder`` (k, 3) and
    ``receiver`` (k,) as in ``ShadowPoints``; ``lights`` = ``kernel_lights``; ``meshes`` =
    (every mesh's vertices, concatenated (V, 3) float64, the first row of each mesh (M,));
    ``spheres`` = (centres (S, 3), radii (S,)) of the scene's spheres; ``prims``: the
    render's primitives (``Visibility.primitives``); ``frame`` (4, 3): the plain camera's
    forward, right, up and eye.

    Writes ``out`` = (moved (k, 2), grad e (k, 2), depth t (k,), |grad e| in pixels (k,),
    camera direction at the moved point (k, 3) as ``camera_directions`` sums it, the points
    EPSILON pixels either side along grad e (k, 2, 2): [:, 0] the + side, [:, 1] the -
    side, and the depths (k, 2) at which the camera rays there meet the receiver)."""
    moved, grad, depth, norm, direction, side, side_depth = out
    sx, sy = 2.0 / width, -2.0 / height
    n_blocks, n_jobs = _jobs(len(light), n_threads)
    for job in numba.prange(n_jobs):
        rec, occ = np.empty((2, 3)), np.empty((3, 3))
        scratch, g = np.empty(9), np.empty(2)
        for block in range(job, n_blocks, n_jobs):
            for i in range(block * BLOCK, min(len(light), (block + 1) * BLOCK)):
                radius, kind, size, light_kind = _point_rows(
                    i, light, occluder, receiver, lights, meshes, spheres, prims, rec, occ
                )
                x, y = coords[i, 0], coords[i, 1]
                for _ in range(steps):
                    e, _t = _border_gradient(
                        rec, radius, occ, kind, size, light_kind, frame, x, y, scratch, g
                    )
                    norm2 = g[0] * g[0] + g[1] * g[1]
                    shift = e / norm2 if norm2 > 0 else 0.0
                    x, y = x - shift * g[0], y - shift * g[1]
                e, t = _border_gradient(
                    rec, radius, occ, kind, size, light_kind, frame, x, y, scratch, g
                )
                moved[i, 0], moved[i, 1], grad[i, 0], grad[i, 1] = x, y, g[0], g[1]
                depth[i] = t
                # pixel_gradient: |grad e| in pixels and the image-plane step of one pixel
                px, py = g[0] * sx, g[1] * sy
                length = np.sqrt(px * px + py * py)
                norm[i] = length
                scale = length if length > 0 else 1.0
                step_x, step_y = (px / scale) * sx, (py / scale) * sy
                for c in range(3):
                    direction[i, c] = (x * frame[1, c] + y * frame[2, c]) + frame[0, c]
                for s in range(2):
                    sign = 1.0 if s == 0 else -1.0
                    at_x = x + sign * (EPSILON * step_x)
                    at_y = y + sign * (EPSILON * step_y)
                    side[i, s, 0], side[i, s, 1] = at_x, at_y
                    side_depth[i, s] = _receiver_hit(rec, radius, frame, at_x, at_y, False, scratch)
