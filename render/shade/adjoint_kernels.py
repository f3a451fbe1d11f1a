"""The compiled passes behind ``render.shade.adjoint``'s VJP.

``backward_rows`` re-evaluates every camera hit (what ``compiled.shade_hit`` computes:
the ray, Moller-Trumbore, the normal, every light's Lambert + Blinn-Phong term, the ambient
and emitted radiance) and carries its sample's gradient back by hand:

* global parameters (the camera frame, the lights, the materials: a few dozen numbers) are
  summed per chunk of hit rows, CHUNKS fixed chunks in row order, each summed in order by
  one thread; the caller adds the chunks in order, so the sums do not depend on the number
  of threads;
* what a hit gives its face's three corners (vertex positions, vertex normals) is written
  per hit; ``vertex_order`` groups those entries by vertex (a stable counting sort, so
  each vertex's entries keep the hits' order) and ``sum_by_vertex`` adds them vertex by
  vertex, in parallel over vertices: no thread adds into another's sums.

The derivation, for one hit on the ray d = x right + y up + forward from the eye E:
Moller-Trumbore solves E - a = -t d + u e1 + v e2 (e1 = b - a, e2 = c - a); with (tb, ub,
vb) the adjoints of (t, u, v), lambda = (tb (e1 x e2) + ub (d x e2) + vb (e1 x d)) / det,
det = e1 . (d x e2), and E gets lambda, a -lambda, d t lambda, e1 -u lambda, e2 -v lambda.
The unit vectors are ``md.normalize``'s: y = x / |x| passes (g - y (y . g)) / |x| back; the
clamps are ``md.maximum``'s (at a tie the gradient passes).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from render.shade.compiled import camera_hit
from render.trace.intersect import BLOCK, _jobs

#: The hit rows are summed in this many chunks (whatever the thread count).
CHUNKS = 128
#: Where the global sums sit in a row of ``backward_rows``' ``sums``: the camera frame
#: (forward, right, up, eye: FRAME numbers), then per light LIGHT_SIZE (its position or the
#: unit vector towards it (3), its strength, its colour (3)), then per mesh MATERIAL_SIZE
#: (albedo (3), specular (3), shininess, ambient (3), emission (3)).
FRAME, LIGHT_SIZE, MATERIAL_SIZE = 12, 7, 13
_INV_PI = 1.0 / math.pi


@numba.njit(cache=True, error_model="numpy", parallel=True)
def backward_rows(
    prim_id, hit_rays, coords, spp, pixels, camera, meshes, materials, lights, lit, flags,
    n_threads, sums, corner_v, corner_n,
):  # fmt: skip
    """Every hit row i (ray ``hit_rays[i]``, image-plane point ``coords[i]``, lit masks
    ``lit[:, i]``) given its pixel's gradient ``pixels`` (H * W, 3) over ``spp``, carried
    back through its shading (``_hit_adjoint``).

    camera: (eye, right, up, forward) (3,) each. meshes: (vertices (V, 3), faces (F, 3)
    global vertex ids, vertex normals (V, 3), the mesh of each face (F,), smooth per mesh
    (M,)), a face's global id being its primitive id. materials: per mesh albedo,
    specular, ambient, emission (M, 3) each, shininess (M,), lobe on (M,). lights:
    ``compiled.lights_pack``. flags: (geometry: carry the gradient back to the camera and
    the corners; shininess: compute the shininess' gradient).
    Writes ``sums`` (CHUNKS, width) (zeros on entry; the layout in FRAME, LIGHT_SIZE,
    MATERIAL_SIZE) and, unless they are empty, ``corner_v`` and ``corner_n`` (k, 3, 3):
    what hit i gives its face's corners' positions and normals."""
    k = hit_rays.shape[0]
    size = (k + CHUNKS - 1) // CHUNKS
    n_jobs = max(1, min(CHUNKS, n_threads))
    scale = 1.0 / spp
    for job in numba.prange(n_jobs):
        for chunk in range(job, CHUNKS, n_jobs):
            for i in range(chunk * size, min(k, (chunk + 1) * size)):
                r = hit_rays[i]
                p = r if spp == 1 else r // spp
                g0, g1, g2 = pixels[p, 0], pixels[p, 1], pixels[p, 2]
                if spp > 1:  # the film's 1 / spp
                    g0, g1, g2 = g0 * scale, g1 * scale, g2 * scale
                if g0 == 0.0 and g1 == 0.0 and g2 == 0.0:
                    _zero_corners(i, corner_v, corner_n)
                    continue
                _hit_adjoint(
                    coords[i, 0], coords[i, 1], i, g0, g1, g2, camera, meshes, prim_id[r],
                    materials, lights, lit, flags, sums, chunk, corner_v, corner_n,
                )  # fmt: skip


@numba.njit(cache=True, inline="always")
def _zero_corners(i, corner_v, corner_n):
    for c in range(3):
        for a in range(3):
            if corner_v.shape[0] > 0:
                corner_v[i, c, a] = 0.0
            if corner_n.shape[0] > 0:
                corner_n[i, c, a] = 0.0


@numba.njit(cache=True, inline="always")
def _unit(x0, x1, x2):
    """``md.normalize`` of one 3-vector (the zero vector stays zero) and 1 / |x| (0 there)."""
    length = math.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
    inv = 1.0 / length if length > 0 else 0.0
    return x0 * inv, x1 * inv, x2 * inv, inv


@numba.njit(cache=True, inline="always")
def _unit_adjoint(y0, y1, y2, inv, g0, g1, g2):
    """What y = x / |x| (``_unit``: y and 1 / |x|) passes back to x for y's gradient g."""
    along = y0 * g0 + y1 * g1 + y2 * g2
    return (g0 - y0 * along) * inv, (g1 - y1 * along) * inv, (g2 - y2 * along) * inv


@numba.njit(cache=True, error_model="numpy", inline="always")
def _hit_adjoint(
    x, y, i, g0, g1, g2, camera, meshes, face, materials, lights, lit, flags, sums, chunk,
    corner_v, corner_n,
):  # fmt: skip
    """Hit row i through image-plane point (x, y) on face ``face``, its radiance's gradient
    (g0, g1, g2): re-evaluated as ``compiled.shade_hit`` shades it and carried back into
    ``sums[chunk]`` and the corner rows i (``backward_rows``)."""
    eye = camera[0]
    vertices, faces, vertex_normal, mesh_of, smooth_of = meshes
    albedo, specular, ambient, emission, shininess_of, lobe_of = materials
    light_kind, light_vec, light_strength, light_color = lights
    geometry, shininess_wanted = flags
    m = mesh_of[face]
    base_m = FRAME + LIGHT_SIZE * light_kind.shape[0] + MATERIAL_SIZE * m
    # -- the forward values -------------------------------------------------------------
    (
        d0, d1, d2, ia, ib, ic, e10, e11, e12, e20, e21, e22, s0, s1, s2, p0, p1, p2,
        q0, q1, q2, inv_det, t, u, v,
    ) = camera_hit(x, y, camera, vertices, faces, face)  # fmt: skip
    c0, c1, c2 = e11 * e22 - e12 * e21, e12 * e20 - e10 * e22, e10 * e21 - e11 * e20  # e1 x e2
    nu0, nu1, nu2, inv_m = _unit(c0, c1, c2)
    flip = -1.0 if nu0 * d0 + nu1 * d1 + nu2 * d2 > 0 else 1.0
    w0 = 1.0 - u - v
    smooth = smooth_of[m]
    if smooth:
        nu0, nu1, nu2, inv_m = _unit(
            0 + w0 * vertex_normal[ia, 0] + u * vertex_normal[ib, 0] + v * vertex_normal[ic, 0],
            0 + w0 * vertex_normal[ia, 1] + u * vertex_normal[ib, 1] + v * vertex_normal[ic, 1],
            0 + w0 * vertex_normal[ia, 2] + u * vertex_normal[ib, 2] + v * vertex_normal[ic, 2],
        )
    n0, n1, n2 = nu0 * flip, nu1 * flip, nu2 * flip
    pt0, pt1, pt2 = eye[0] + t * d0, eye[1] + t * d1, eye[2] + t * d2
    a0, a1, a2 = albedo[m, 0], albedo[m, 1], albedo[m, 2]
    k0, k1, k2 = specular[m, 0], specular[m, 1], specular[m, 2]
    shininess, lobe_on = shininess_of[m], lobe_of[m]
    lobe_scale = vh0 = vh1 = vh2 = inv_view = 0.0
    if lobe_on:  # a division and a square root per hit saved without
        lobe_scale = (shininess + 8.0) / (8.0 * math.pi)
        vh0, vh1, vh2, inv_view = _unit(d0, d1, d2)  # the view is -vh
    # -- the lights, forward and back -----------------------------------------------------
    gn0 = gn1 = gn2 = 0.0  # the gradient of the facing normal n
    gp0 = gp1 = gp2 = 0.0  # of the point
    gd0 = gd1 = gd2 = 0.0  # of the ray's direction
    for j in range(light_kind.shape[0]):
        visible = lit[j, i]
        if visible == 0.0:
            continue
        base = FRAME + LIGHT_SIZE * j
        point = light_kind[j] == 0
        o0 = o1 = o2 = inv_o = distance_sq = inv_distance_sq = 0.0
        if point:
            o0, o1 = light_vec[j, 0] - pt0, light_vec[j, 1] - pt1
            o2 = light_vec[j, 2] - pt2
            distance_sq = o0 * o0 + o1 * o1 + o2 * o2
            inv_distance_sq = 1.0 / (1.0 if distance_sq == 0 else distance_sq)
            irradiance = light_strength[j] * inv_distance_sq
            l0, l1, l2, inv_o = _unit(o0, o1, o2)
        else:
            l0, l1, l2 = light_vec[j, 0], light_vec[j, 1], light_vec[j, 2]
            irradiance = light_strength[j]
        cos_raw = n0 * l0 + n1 * l1 + n2 * l2
        cos_theta = 0.0 if cos_raw < 0.0 else cos_raw
        f0, f1, f2 = a0 * _INV_PI, a1 * _INV_PI, a2 * _INV_PI
        h0 = h1 = h2 = inv_h = n_dot_h = power = lobe = 0.0
        if lobe_on:
            h0, h1, h2, inv_h = _unit(l0 + -vh0, l1 + -vh1, l2 + -vh2)
            n_dot_h = n0 * h0 + n1 * h1 + n2 * h2
            clamped = 1e-12 if n_dot_h < 1e-12 else n_dot_h
            power = clamped**shininess
            lobe = power * lobe_scale
            f0, f1, f2 = f0 + lobe * k0, f1 + lobe * k1, f2 + lobe * k2
        scalar = irradiance * cos_theta * visible
        col0, col1, col2 = light_color[j, 0], light_color[j, 1], light_color[j, 2]
        # term_c = scalar * (f_c * colour_c)
        sums[chunk, base + 4] += g0 * scalar * f0
        sums[chunk, base + 5] += g1 * scalar * f1
        sums[chunk, base + 6] += g2 * scalar * f2
        g_scalar = g0 * (f0 * col0) + g1 * (f1 * col1) + g2 * (f2 * col2)
        gf0, gf1, gf2 = g0 * scalar * col0, g1 * scalar * col1, g2 * scalar * col2
        sums[chunk, base_m + 0] += gf0 * _INV_PI
        sums[chunk, base_m + 1] += gf1 * _INV_PI
        sums[chunk, base_m + 2] += gf2 * _INV_PI
        gl0 = gl1 = gl2 = 0.0
        if lobe_on:
            sums[chunk, base_m + 3] += gf0 * lobe
            sums[chunk, base_m + 4] += gf1 * lobe
            sums[chunk, base_m + 5] += gf2 * lobe
            g_lobe = gf0 * k0 + gf1 * k1 + gf2 * k2
            g_power = g_lobe * lobe_scale
            if shininess_wanted:  # through the power and through the scale (s + 8) / (8 pi)
                clamped = 1e-12 if n_dot_h < 1e-12 else n_dot_h
                sums[chunk, base_m + 6] += g_power * power * math.log(clamped) + g_lobe * (
                    power / (8.0 * math.pi)
                )
            if n_dot_h >= 1e-12 and shininess != 0.0:  # the clamp passes its gradient
                g_ndh = g_power * shininess * (power / n_dot_h)
                gn0, gn1, gn2 = gn0 + g_ndh * h0, gn1 + g_ndh * h1, gn2 + g_ndh * h2
                gh0, gh1, gh2 = _unit_adjoint(h0, h1, h2, inv_h, g_ndh * n0, g_ndh * n1, g_ndh * n2)
                gl0, gl1, gl2 = gh0, gh1, gh2
                gv0, gv1, gv2 = _unit_adjoint(vh0, vh1, vh2, inv_view, -gh0, -gh1, -gh2)
                gd0, gd1, gd2 = gd0 + gv0, gd1 + gv1, gd2 + gv2
        g_irradiance = g_scalar * cos_theta * visible
        g_cos = g_scalar * irradiance * visible
        if cos_raw >= 0.0:  # max(n . l, 0) passes its gradient at a tie
            gn0, gn1, gn2 = gn0 + g_cos * l0, gn1 + g_cos * l1, gn2 + g_cos * l2
            gl0, gl1, gl2 = gl0 + g_cos * n0, gl1 + g_cos * n1, gl2 + g_cos * n2
        if point:
            sums[chunk, base + 3] += g_irradiance * inv_distance_sq
            g_dsq = 0.0 if distance_sq == 0 else -g_irradiance * irradiance * inv_distance_sq
            go0, go1, go2 = _unit_adjoint(l0, l1, l2, inv_o, gl0, gl1, gl2)
            go0, go1 = go0 + 2.0 * g_dsq * o0, go1 + 2.0 * g_dsq * o1
            go2 = go2 + 2.0 * g_dsq * o2
            sums[chunk, base + 0] += go0
            sums[chunk, base + 1] += go1
            sums[chunk, base + 2] += go2
            gp0, gp1, gp2 = gp0 - go0, gp1 - go1, gp2 - go2
        else:
            sums[chunk, base + 3] += g_irradiance
            sums[chunk, base + 0] += gl0
            sums[chunk, base + 1] += gl1
            sums[chunk, base + 2] += gl2
    # -- ambient and emission ------------------------------------------------------------
    front = 1.0 if flip > 0 else 0.0
    sums[chunk, base_m + 7] += g0
    sums[chunk, base_m + 8] += g1
    sums[chunk, base_m + 9] += g2
    sums[chunk, base_m + 10] += g0 * front
    sums[chunk, base_m + 11] += g1 * front
    sums[chunk, base_m + 12] += g2 * front
    if not geometry:
        return
    # -- the geometry: the point, the normal, Moller-Trumbore, the ray ------------------
    ge0, ge1, ge2 = gp0, gp1, gp2  # point = eye + t d
    g_t = gp0 * d0 + gp1 * d1 + gp2 * d2
    gd0, gd1, gd2 = gd0 + t * gp0, gd1 + t * gp1, gd2 + t * gp2
    gm0, gm1, gm2 = _unit_adjoint(nu0, nu1, nu2, inv_m, gn0 * flip, gn1 * flip, gn2 * flip)
    e1b0 = e1b1 = e1b2 = e2b0 = e2b1 = e2b2 = g_u = g_v = 0.0
    normals = corner_n.shape[0] > 0
    if smooth:  # m = (1 - u - v) na + u nb + v nc
        na0, na1, na2 = vertex_normal[ia, 0], vertex_normal[ia, 1], vertex_normal[ia, 2]
        g_u = (
            gm0 * (vertex_normal[ib, 0] - na0)
            + gm1 * (vertex_normal[ib, 1] - na1)
            + gm2 * (vertex_normal[ib, 2] - na2)
        )
        g_v = (
            gm0 * (vertex_normal[ic, 0] - na0)
            + gm1 * (vertex_normal[ic, 1] - na1)
            + gm2 * (vertex_normal[ic, 2] - na2)
        )
        if normals:
            corner_n[i, 0, 0], corner_n[i, 0, 1], corner_n[i, 0, 2] = w0 * gm0, w0 * gm1, w0 * gm2
            corner_n[i, 1, 0], corner_n[i, 1, 1], corner_n[i, 1, 2] = u * gm0, u * gm1, u * gm2
            corner_n[i, 2, 0], corner_n[i, 2, 1], corner_n[i, 2, 2] = v * gm0, v * gm1, v * gm2
    else:  # m = e1 x e2: e1 gets e2 x gm, e2 gets gm x e1
        e1b0, e1b1, e1b2 = e21 * gm2 - e22 * gm1, e22 * gm0 - e20 * gm2, e20 * gm1 - e21 * gm0
        e2b0, e2b1, e2b2 = gm1 * e12 - gm2 * e11, gm2 * e10 - gm0 * e12, gm0 * e11 - gm1 * e10
        if normals:
            for c in range(3):
                for a in range(3):
                    corner_n[i, c, a] = 0.0
    # Moller-Trumbore: lambda = (tb (e1 x e2) + ub (d x e2) + vb (e1 x d)) / det
    r0, r1, r2 = e11 * d2 - e12 * d1, e12 * d0 - e10 * d2, e10 * d1 - e11 * d0  # e1 x d
    lam0 = (g_t * c0 + g_u * p0 + g_v * r0) * inv_det
    lam1 = (g_t * c1 + g_u * p1 + g_v * r1) * inv_det
    lam2 = (g_t * c2 + g_u * p2 + g_v * r2) * inv_det
    ge0, ge1, ge2 = ge0 + lam0, ge1 + lam1, ge2 + lam2
    gd0, gd1, gd2 = gd0 + t * lam0, gd1 + t * lam1, gd2 + t * lam2
    e1b0, e1b1, e1b2 = e1b0 - u * lam0, e1b1 - u * lam1, e1b2 - u * lam2
    e2b0, e2b1, e2b2 = e2b0 - v * lam0, e2b1 - v * lam1, e2b2 - v * lam2
    if corner_v.shape[0] > 0:  # a gets -lambda - e1b - e2b, b gets e1b, c gets e2b
        corner_v[i, 0, 0] = -lam0 - e1b0 - e2b0
        corner_v[i, 0, 1] = -lam1 - e1b1 - e2b1
        corner_v[i, 0, 2] = -lam2 - e1b2 - e2b2
        corner_v[i, 1, 0], corner_v[i, 1, 1], corner_v[i, 1, 2] = e1b0, e1b1, e1b2
        corner_v[i, 2, 0], corner_v[i, 2, 1], corner_v[i, 2, 2] = e2b0, e2b1, e2b2
    # d = x right + y up + forward
    sums[chunk, 0] += gd0
    sums[chunk, 1] += gd1
    sums[chunk, 2] += gd2
    sums[chunk, 3] += x * gd0
    sums[chunk, 4] += x * gd1
    sums[chunk, 5] += x * gd2
    sums[chunk, 6] += y * gd0
    sums[chunk, 7] += y * gd1
    sums[chunk, 8] += y * gd2
    sums[chunk, 9] += ge0
    sums[chunk, 10] += ge1
    sums[chunk, 11] += ge2


#: The most (chunks x vertices) counters ``vertex_order`` keeps.
_COUNTERS = 1 << 22


@numba.njit(cache=True, error_model="numpy", parallel=True)
def vertex_order(prim_id, hit_rays, faces, n_vertices, n_threads):
    """The k hits' 3k corner entries (entry 3 i + c: corner c of hit i's face, faces (F, 3)
    global vertex ids, a hit's face being ``prim_id[hit_rays[i]]``) grouped by vertex, a
    stable counting sort: ``order`` (3k,) the entries, vertex by vertex, each vertex's in
    increasing entry (hit) order, and ``start`` (V + 1,): vertex v's run is
    order[start[v]:start[v + 1]]. Counted in up to n_threads chunks of hits; the result does
    not depend on how many."""
    k = hit_rays.shape[0]
    n_chunks = max(1, min(n_threads, _COUNTERS // max(n_vertices, 1)))
    size = (k + n_chunks - 1) // n_chunks
    counts = np.zeros((n_chunks, n_vertices), np.int64)
    for chunk in numba.prange(n_chunks):
        for i in range(chunk * size, min(k, (chunk + 1) * size)):
            face = prim_id[hit_rays[i]]
            for c in range(3):
                counts[chunk, faces[face, c]] += 1
    # Each chunk's first slot for each vertex: the vertices in order, the chunks in order.
    start = np.empty(n_vertices + 1, np.int64)
    total = 0
    for vertex in range(n_vertices):
        start[vertex] = total
        for chunk in range(n_chunks):
            count = counts[chunk, vertex]
            counts[chunk, vertex] = total
            total += count
    start[n_vertices] = total
    order = np.empty(3 * k, np.int64)
    for chunk in numba.prange(n_chunks):
        for i in range(chunk * size, min(k, (chunk + 1) * size)):
            face = prim_id[hit_rays[i]]
            for c in range(3):
                vertex = faces[face, c]
                order[counts[chunk, vertex]] = 3 * i + c
                counts[chunk, vertex] += 1
    return start, order


@numba.njit(cache=True, error_model="numpy", parallel=True)
def sum_by_vertex(start, order, corner_v, corner_n, n_threads, g_v, g_n):
    """Every vertex's gradient: its entries (``vertex_order``) of ``corner_v`` (k, 3, 3)
    summed in order into ``g_v`` (V, 3), and of ``corner_n`` into ``g_n`` (V, 3) unless
    ``corner_n`` is empty; in parallel over vertices (``_jobs``/BLOCK)."""
    n_vertices = start.shape[0] - 1
    normals = corner_n.shape[0] > 0
    n_blocks, n_jobs = _jobs(n_vertices, n_threads)
    for job in numba.prange(n_jobs):
        for block in range(job, n_blocks, n_jobs):
            for vertex in range(block * BLOCK, min(n_vertices, (block + 1) * BLOCK)):
                v0 = v1 = v2 = w0 = w1 = w2 = 0.0
                for index in range(start[vertex], start[vertex + 1]):
                    entry = order[index]
                    i, c = entry // 3, entry % 3
                    v0 += corner_v[i, c, 0]
                    v1 += corner_v[i, c, 1]
                    v2 += corner_v[i, c, 2]
                    if normals:
                        w0 += corner_n[i, c, 0]
                        w1 += corner_n[i, c, 1]
                        w2 += corner_n[i, c, 2]
                g_v[vertex, 0], g_v[vertex, 1], g_v[vertex, 2] = v0, v1, v2
                if normals:
                    g_n[vertex, 0], g_n[vertex, 1], g_n[vertex, 2] = w0, w1, w2
