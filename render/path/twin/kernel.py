"""The path tracer compiled: whole paths, one after the other, in one Numba kernel per batch.

``render.path.sample.tracer`` (the sampler) and ``render.path.gradient.transport`` (the
radiance on the tape) are the readable reference: a wavefront of NumPy passes, one depth at
a time. This module does the same work path by path, in parallel over pixels (on threads),
with no array between the steps: the camera ray, the BVH, the lobe and direction choices,
next-event estimation with its shadow ray, point and directional lights, multiple importance
sampling, Russian roulette, and the radiance each path carries.

It makes the same decisions as the sampler, from the same random numbers
(``render.path.sample.random``'s hash of seed, path id and dimension, inlined), and computes the
same radiance, up to the order of floating-point operations. Two uses:

* ``render_image``: the image, when nothing is differentiated (a forward render). Each
  pixel's samples are summed in sample order, so the image is the same bit for bit on any
  number of threads.
* ``sample_paths``: the sampler's ``PathBatch`` (every vertex's decisions, what the tape
  recomputes) and each path's radiance, for the gradients (``render.path.gradient.replay``).

``tests/render/path/test_kernel.py`` ties both to the reference: the same decisions, and
the radiance to rounding.
"""

from __future__ import annotations

import math

import numpy as np

from minidiff.threads import borrowing, jit, job_count, kernel, run_jobs, share
from render.path.sample import records as R
from render.path.sample.choices import MAX_SURVIVAL, MIN_SURVIVAL
from render.path.sample.random import mix, uniform_of
from render.path.sample.records import PathBatch
from render.path.sample.tracer import AREA, CAMERA, MIRROR, STOP, PathSampler
from render.path.twin.packed import Packed, applies, pack
from render.path.twin.scalar import (
    _DIRECTION,
    _EMITTER,
    _EMITTER_POINT,
    _LOBE,
    _ROULETTE,
    _brdf,
    _dim,
    _divided,
    _local,
    _look,
    _pdf,
    _placed,
    _point_on,
    _power,
    _put,
    _reintersect,
    _surface,
    _to_world,
    _unit,
)
from render.trace.intersect import BLOCK, closest_hit_one, occluded_one
from render.trace.vec3 import dot3

__all__ = ["Packed", "applies", "pack", "render_image", "sample_paths"]

#: Blocks of pixels are dealt to this many jobs (``_kernel``).
CHUNKS = 64
#: ``sample_paths`` first records this many vertices per path (at most max_depth), and
#: traces again with room for the longest path's if one had more: memory by the paths'
#: real lengths (Russian roulette ends most of them early), not by max_depth.
RECORD_ROWS = 32


@jit(cache=True, inline="always")
def _trace_path(bvh, s, seed_key, path, px, py, width, height, max_depth, rr_depth, stack,
                stack_t, keep, row, rec_i, rec_f, rec_lit):  # fmt: skip
    """The radiance of path id ``path`` through pixel (px, py) (L0, L1, L2). With ``keep``,
    its decisions are written to row ``row`` of the records
    (``render.path.sample.records``): its number of vertices n (0: the camera ray missed),
    and its first vertices, as many as the records have room for.

    Two views of each vertex, as in the reference: the sampler decides with the point its
    ray found (``point``, the direction it arrived along ``incoming``); the tape computes
    the radiance at the point it recomputes (``xt``: the same point for a vertex placed on
    its primitive, but a mirror's reflected ray starts at the surface, not ``offset`` above
    it) with directions between recomputed points (``wot``)."""
    (triangles, centers, radii, prim_object, albedo, specular, shininess,
     reflectance, emission, probability, lobe_reflectance, maps, texels, smooth, corners,
     normals, uvs, e_prims, e_cdf, e_probability, e_area, e_row_of, light_kind, light_vec,
     light_strength, light_color, forward, right, up, eye, background, offset,
     n_tri, lobe_on) = s  # fmt: skip
    key = mix(seed_key ^ np.uint64(path))
    # The camera ray (PathSampler.sample, to_image_plane, camera_directions).
    fx = px + uniform_of(key, 0)
    fy = py + uniform_of(key, 1)
    x, y = 2.0 * fx / width - 1.0, 1.0 - 2.0 * fy / height
    d = (x * right[0] + y * up[0] + forward[0], x * right[1] + y * up[1] + forward[1],
         x * right[2] + y * up[2] + forward[2])  # fmt: skip
    if keep:
        rec_f[0, row, R.COORD], rec_f[0, row, R.COORD + 1] = x, y
    prim, t, u, v = closest_hit_one(bvh, (eye[0], eye[1], eye[2]), d, 0.0, stack, stack_t)
    if prim < 0:
        if keep:
            rec_i[0, row, R.COUNT] = 0
        return background[0], background[1], background[2]
    point = (eye[0] + t * d[0], eye[1] + t * d[1], eye[2] + t * d[2])
    incoming = _divided(d[0], d[1], d[2])
    form, pdf, previous, estimate = CAMERA, 0.0, point, 1.0
    xt, ut, vt, wot = point, u, v, _unit(-d[0], -d[1], -d[2])
    beta = (1.0, 1.0, 1.0)
    L = (0.0, 0.0, 0.0)
    depth = 1
    while True:
        # Memory by the paths' real lengths, not by max_depth: the records hold the vertices
        # that fit (sample_paths traces again with deeper ones if a path had more).
        kept = keep and depth <= rec_i.shape[0]
        o, ng, ns, uv, local = _surface(
            triangles, centers, prim_object, smooth, corners, normals, uvs, prim, point, u, v
        )
        ngt, nst, uvt = ng, ns, uv
        if form == MIRROR:
            ngt, nst, uvt = _surface(
                triangles, centers, prim_object, smooth, corners, normals, uvs, prim, xt, ut, vt
            )[1:4]
        wo = (-incoming[0], -incoming[1], -incoming[2])
        side = -1.0 if dot3(ng, wo) < 0 else 1.0
        ng = (side * ng[0], side * ng[1], side * ng[2])
        ns = (side * ns[0], side * ns[1], side * ns[2])
        side_t = -1.0 if dot3(ngt, wot) < 0 else 1.0
        nst = (side_t * nst[0], side_t * nst[1], side_t * nst[2])
        # Emission seen here, MIS-weighted against NEE (PathSampler._emission_weight).
        weight = 1.0
        if e_prims.shape[0] > 0 and form == AREA:
            weight = _emission_weight(
                e_row_of, e_probability, e_area, prim, point, previous, ng, pdf
            )
        if side_t > 0:
            L = _emitted(L, beta, emission, o, weight)
        if keep:  # the path's length so far, also past the records' depth
            rec_i[0, row, R.COUNT] = depth
        if kept:
            _record_vertex(rec_i, rec_f, depth, row, prim, form, local, weight)
        if depth == max_depth:
            break
        p_d, p_g, p_m = probability[o, 0], probability[o, 1], probability[o, 2]
        kd, ks = _look(albedo, specular, maps, texels, o, uvt)
        # What the lights' terms read of the vertex and its surface.
        ignore = prim if prim < n_tri else -1
        here = (point, xt, ng, nst, wot, prim, ignore, o, depth, kept)
        look = (kd, ks, shininess[o], lobe_on[o], p_d, p_g)
        origin = (point[0] + offset * ng[0], point[1] + offset * ng[1], point[2] + offset * ng[2])
        if e_prims.shape[0] > 0:  # next-event estimation: one point on the area lights
            L = _next_event(L, beta, bvh, stack, triangles, centers, radii, prim_object,
                            emission, e_prims, e_cdf, e_probability, e_area, key, origin, ns,
                            wo, here, look, row, rec_i, rec_f)  # fmt: skip
        L = _lights(L, beta, bvh, stack, light_kind, light_vec, light_strength, light_color,
                    offset, here, look, row, rec_lit)  # fmt: skip
        # How the path goes on (PathSampler._continue).
        mirror, wi, next_pdf = _direction(key, depth, wo, ns, p_d, p_g, p_m, shininess[o])
        go = (p_d + p_g + p_m > 0) and next_pdf > 0 and dot3(ng, wi) > 0
        estimate = estimate * lobe_reflectance[o]
        survive = 1.0
        if depth >= rr_depth:
            survive = min(max(estimate, MIN_SURVIVAL), MAX_SURVIVAL)
            go = go and uniform_of(key, _dim(depth, _ROULETTE)) < survive
        wi = _divided(wi[0], wi[1], wi[2])
        if kept:
            rec_f[depth - 1, row, R.SURVIVE] = survive
            _put(rec_f, depth - 1, row, R.ESCAPE_DIR, wi)
        if not go:
            break
        scale = 1.0 / (next_pdf * survive)
        prim, t, u, v = closest_hit_one(bvh, origin, wi, 0.0, stack, stack_t)
        if kept:
            rec_i[depth - 1, row, R.NEXT] = MIRROR if mirror else AREA
            rec_f[depth - 1, row, R.NEXT_PDF] = next_pdf
            rec_i[depth - 1, row, R.ESCAPE] = prim < 0
        point_next = (origin[0] + t * wi[0], origin[1] + t * wi[1], origin[2] + t * wi[2])
        factor, x_next, ut, vt, wo_next = _segment(
            triangles, centers, radii, (reflectance[o, 0], reflectance[o, 1], reflectance[o, 2]),
            prim, mirror, scale, wi, point_next, u, v, xt, ut, vt, wot, nst, look,
        )  # fmt: skip
        beta = (beta[0] * factor[0], beta[1] * factor[1], beta[2] * factor[2])
        if prim < 0:  # the environment
            L = (L[0] + beta[0] * background[0], L[1] + beta[1] * background[1],
                 L[2] + beta[2] * background[2])  # fmt: skip
            break
        previous, point, xt, wot = point, point_next, x_next, wo_next
        incoming, form, pdf = wi, MIRROR if mirror else AREA, next_pdf
        depth += 1
    return L[0], L[1], L[2]


@jit(cache=True, inline="always")
def _emission_weight(e_row_of, e_probability, e_area, prim, point, previous, ng, pdf):
    """MIS weight of the emission seen at an ``AREA`` vertex ``point`` on ``prim``, reached
    from ``previous`` by a direction of density ``pdf``, against NEE's choice of the same
    point (``PathSampler._emission_weight``; 1 where NEE cannot pick it)."""
    r = e_row_of[prim]
    p_nee = e_probability[r] / e_area[r] if r >= 0 else 0.0
    to = (point[0] - previous[0], point[1] - previous[1], point[2] - previous[2])
    d2 = dot3(to, to)
    d2 = d2 if d2 > 0 else 1.0
    cos = abs(dot3(ng, to)) / math.sqrt(d2)
    if p_nee > 0:
        return _power(pdf * cos / d2, p_nee)
    return 1.0


@jit(cache=True, inline="always")
def _emitted(L, beta, emission, o, weight):
    """``L`` plus the emission of object ``o`` seen at a vertex with MIS weight ``weight``,
    through throughput ``beta``."""
    return (L[0] + beta[0] * (emission[o, 0] * weight), L[1] + beta[1] * (emission[o, 1] * weight),
            L[2] + beta[2] * (emission[o, 2] * weight))  # fmt: skip


@jit(cache=True, inline="always")
def _record_vertex(rec_i, rec_f, depth, row, prim, form, local, weight):
    """Vertex ``depth`` of the path of row ``row`` into the records, its NEE, lights and
    continuation as if none (what follows overwrites them)."""
    rec_i[depth - 1, row, R.PRIM] = prim
    rec_i[depth - 1, row, R.FORM] = form
    rec_i[depth - 1, row, R.NEE_PRIM] = -1
    rec_i[depth - 1, row, R.NEXT] = STOP
    _put(rec_f, depth - 1, row, R.LOCAL, local)
    rec_f[depth - 1, row, R.EMIT] = weight
    rec_f[depth - 1, row, R.NEE_WEIGHT] = 0.0
    rec_f[depth - 1, row, R.NEXT_PDF] = 1.0
    rec_f[depth - 1, row, R.SURVIVE] = 1.0
    rec_i[depth - 1, row, R.ESCAPE] = 0


@jit(cache=True, inline="always")
def _next_event(L, beta, bvh, stack, triangles, centers, radii, prim_object, emission, e_prims,
                e_cdf, e_probability, e_area, key, origin, ns, wo, here, look, row, rec_i,
                rec_f):  # fmt: skip
    """``L`` plus next-event estimation at the vertex ``here``: one point drawn on the area
    lights (the ``e_`` arrays), its shadow ray from ``origin``, MIS against the BSDF's density
    (its shading normal ``ns`` facing ``wo``) (PathSampler._next_event), and the radiance
    it brings (transport._at_vertex, from the tape's point)."""
    point, xt, ng, nst, wot, prim, ignore, o, depth, kept = here
    kd, ks, shin, lobe, p_d, p_g = look
    n_emit = e_prims.shape[0]
    pick = np.searchsorted(e_cdf, uniform_of(key, _dim(depth, _EMITTER)) * e_cdf[-1],
                           side="right")  # fmt: skip
    pick = min(pick, n_emit - 1)
    e_prim = e_prims[pick]
    u1 = uniform_of(key, _dim(depth, _EMITTER_POINT))
    u2 = uniform_of(key, _dim(depth, _EMITTER_POINT) + 1)
    e_local, z, nz = _point_on(triangles, centers, radii, e_prim, u1, u2)
    if kept:  # recorded whether or not it is seen, as the sampler does
        _put(rec_f, depth - 1, row, R.NEE_LOCAL, e_local)
    to = (z[0] - point[0], z[1] - point[1], z[2] - point[2])
    d2 = dot3(to, to)
    root = math.sqrt(d2 if d2 > 0 else 1.0)
    wi = (to[0] / root, to[1] / root, to[2] / root)
    cos_z = -dot3(nz, wi)
    ok = (p_d + p_g > 0) and cos_z > 0 and dot3(ng, wi) > 0 and d2 > 0 and e_prim != prim
    if ok:
        to = (z[0] - origin[0], z[1] - origin[1], z[2] - origin[2])
        ok = not occluded_one(bvh, origin, to, 1.0 - 1e-7, ignore, stack)
    if not ok:
        return L
    p_nee = e_probability[pick] / e_area[pick]
    p_bsdf = _pdf(p_d, p_g, shin, ns, wo, wi) * cos_z / (d2 if d2 > 0 else 1.0)
    nee_weight = _power(p_nee, p_bsdf) / e_probability[pick]
    if kept:
        rec_i[depth - 1, row, R.NEE_PRIM] = e_prim
        rec_f[depth - 1, row, R.NEE_WEIGHT] = nee_weight
    # The radiance it brings (transport._at_vertex), from the tape's point.
    to = (z[0] - xt[0], z[1] - xt[1], z[2] - xt[2])
    d2 = dot3(to, to)
    root = math.sqrt(d2)
    wi = (to[0] / root, to[1] / root, to[2] / root)
    eo = prim_object[e_prim]
    scale = max(dot3(nst, wi), 0.0) * abs(dot3(nz, wi)) / d2 * e_area[pick]
    scale = scale * nee_weight
    f = _brdf(nst, wot, wi, kd, ks, shin, lobe)
    return (L[0] + beta[0] * (f[0] * scale * emission[eo, 0]),
            L[1] + beta[1] * (f[1] * scale * emission[eo, 1]),
            L[2] + beta[2] * (f[2] * scale * emission[eo, 2]))  # fmt: skip


@jit(cache=True, inline="always")
def _lights(L, beta, bvh, stack, light_kind, light_vec, light_strength, light_color, offset,
            here, look, row, rec_lit):  # fmt: skip
    """``L`` plus the point and directional lights that reach the vertex ``here``
    (PathSampler._lights, lighting.light_contribution), their shadow rays from the sampler's
    point and their light from the tape's."""
    point, xt, ng, nst, wot, prim, ignore, o, depth, kept = here
    kd, ks, shin, lobe, _, _ = look
    for j in range(light_kind.shape[0]):
        if light_kind[j] == 0:
            tx = light_vec[j, 0] - point[0]
            ty = light_vec[j, 1] - point[1]
            tz = light_vec[j, 2] - point[2]
            distance = math.sqrt(tx * tx + ty * ty + tz * tz)
            lit = ng[0] * tx + ng[1] * ty + ng[2] * tz > 0
            if lit and distance > 2.0 * offset:
                fraction = offset / distance
                so = (point[0] + fraction * tx, point[1] + fraction * ty,
                      point[2] + fraction * tz)  # fmt: skip
                to = (light_vec[j, 0] - so[0], light_vec[j, 1] - so[1], light_vec[j, 2] - so[2])
                lit = not occluded_one(bvh, so, to, 1.0 - fraction / (1.0 - fraction), ignore,
                                       stack)  # fmt: skip
            tx = light_vec[j, 0] - xt[0]
            ty = light_vec[j, 1] - xt[1]
            tz = light_vec[j, 2] - xt[2]
            distance_sq = tx * tx + ty * ty + tz * tz
            irradiance = light_strength[j] / (1.0 if distance_sq == 0 else distance_sq)
            wl = _unit(tx, ty, tz)
        else:
            wl = (light_vec[j, 0], light_vec[j, 1], light_vec[j, 2])
            lit = dot3(ng, wl) > 0
            if lit:
                so = (point[0] + offset * wl[0], point[1] + offset * wl[1],
                      point[2] + offset * wl[2])  # fmt: skip
                lit = not occluded_one(bvh, so, wl, np.inf, ignore, stack)
            irradiance = light_strength[j]
        if kept:
            rec_lit[depth - 1, row, j] = lit
        if not lit:
            continue
        scalar = irradiance * max(dot3(nst, wl), 0.0)
        f = _brdf(nst, wot, wl, kd, ks, shin, lobe)
        L = (L[0] + beta[0] * (scalar * (f[0] * light_color[j, 0])),
             L[1] + beta[1] * (scalar * (f[1] * light_color[j, 1])),
             L[2] + beta[2] * (scalar * (f[2] * light_color[j, 2])))  # fmt: skip
    return L


@jit(cache=True, inline="always")
def _direction(key, depth, wo, ns, p_d, p_g, p_m, shin):
    """The lobe picked at vertex ``depth`` (diffuse, glossy or mirror with probabilities
    ``p_d``, ``p_g``, ``p_m``) and the direction it draws about the shading normal ``ns``
    facing ``wo``: (mirror, wi, its density) (PathSampler._continue)."""
    u1 = uniform_of(key, _dim(depth, _DIRECTION))
    u2 = uniform_of(key, _dim(depth, _DIRECTION) + 1)
    pick_lobe = uniform_of(key, _dim(depth, _LOBE))
    if pick_lobe >= p_d + p_g:  # the mirror
        c2 = 2.0 * dot3(wo, ns)
        return True, (c2 * ns[0] - wo[0], c2 * ns[1] - wo[1], c2 * ns[2] - wo[2]), p_m
    if pick_lobe >= p_d:  # glossy
        cos_h = u1 ** (1.0 / (shin + 1.0))
        sin_h = math.sqrt(max(1.0 - cos_h**2, 0.0))
        phi = 2.0 * math.pi * u2
        h = _to_world(sin_h * math.cos(phi), sin_h * math.sin(phi), cos_h, ns)
        c2 = 2.0 * dot3(wo, h)
        wi = (c2 * h[0] - wo[0], c2 * h[1] - wo[1], c2 * h[2] - wo[2])
    else:
        r, phi = math.sqrt(u1), 2.0 * math.pi * u2
        wi = _to_world(r * math.cos(phi), r * math.sin(phi),
                       math.sqrt(max(1.0 - u1, 0.0)), ns)  # fmt: skip
    return False, wi, _pdf(p_d, p_g, shin, ns, wo, wi)


@jit(cache=True, inline="always")
def _segment(triangles, centers, radii, reflectance, prim, mirror, scale, wi, point_next, u, v,
             xt, ut, vt, wot, nst, look):  # fmt: skip
    """The segment from the tape's point ``xt`` to the next vertex, which the ray ``wi``
    found at ``point_next`` on ``prim`` (barycentrics u, v; -1: none): (F_k, the tape's
    next point and its (ut, vt), the direction back from it). A mirror's reflected ray starts
    at the surface (the object's ``reflectance``); another lobe's next vertex is placed on
    its primitive, the direction between the two points (``look``: the BRDF's arguments)."""
    kd, ks, shin, lobe, _, _ = look
    x_next, wo_next = xt, wot  # (both read only when a vertex follows)
    if mirror:
        factor = (reflectance[0] * scale, reflectance[1] * scale, reflectance[2] * scale)
        c2 = 2.0 * dot3(wot, nst)  # the tape's reflected ray, from its own point
        reflected = (c2 * nst[0] - wot[0], c2 * nst[1] - wot[1], c2 * nst[2] - wot[2])
        if prim >= 0:
            x_next, ut, vt = _reintersect(triangles, centers, radii, prim, xt, reflected)
        wo_next = _unit(-reflected[0], -reflected[1], -reflected[2])
        return factor, x_next, ut, vt, wo_next
    wn = wi  # the direction sampled; to a new vertex, the one between the points
    if prim >= 0:
        x_next = _placed(triangles, centers, radii, prim,
                         _local(triangles, centers, prim, point_next, u, v))  # fmt: skip
        to = (x_next[0] - xt[0], x_next[1] - xt[1], x_next[2] - xt[2])
        root = math.sqrt(dot3(to, to))
        wn = (to[0] / root, to[1] / root, to[2] / root)
        wo_next = _unit(-wn[0], -wn[1], -wn[2])
    cos = max(dot3(nst, wn), 0.0) * scale
    f = _brdf(nst, wot, wn, kd, ks, shin, lobe)
    return (f[0] * cos, f[1] * cos, f[2] * cos), x_next, ut, vt, wo_next


@jit(cache=True, inline="always")
def _clear_rows(rec_i, rec_f, rec_lit, row):
    """Zero path ``row``'s records at every depth (a path writes only the fields its
    vertices have): here, on the threads, rather than a serial ``np.zeros`` of them all."""
    for depth in range(rec_i.shape[0]):
        for k in range(rec_i.shape[2]):
            rec_i[depth, row, k] = 0
        for k in range(rec_f.shape[2]):
            rec_f[depth, row, k] = 0.0
        for k in range(rec_lit.shape[2]):
            rec_lit[depth, row, k] = False


@borrowing
def _trace_block(bvh, s, seed_key, spp, width, height, max_depth, rr_depth, start, stop, paths,
                 stack, stack_t, out, radiance, rec_i, rec_f, rec_lit):  # fmt: skip
    """Items start..stop-1, one of two ways:

    * pixels (``paths`` empty): each pixel's mean over its spp paths, summed in sample
      order, into ``out`` (H, W, 3);
    * paths ``paths[i]``: their radiance into ``radiance`` (N, 3) and their records.

    One call per block of items, so that the scene's arrays are handed over once per block,
    not once per path."""
    image = paths.shape[0] == 0
    for i in range(start, stop):
        if not image:
            _clear_rows(rec_i, rec_f, rec_lit, i)
        count = spp if image else 1
        total = (0.0, 0.0, 0.0)
        for sample in range(count):
            path = i * spp + sample if image else paths[i]
            pixel = path // spp
            L = _trace_path(
                bvh, s, seed_key, path, pixel % width, pixel // width, width, height, max_depth,
                rr_depth, stack, stack_t, not image, i, rec_i, rec_f, rec_lit,
            )  # fmt: skip
            total = L if sample == 0 else (total[0] + L[0], total[1] + L[1], total[2] + L[2])
        if image:
            inv = 1.0 / spp
            x, y = i % width, i // width
            out[y, x, 0] = total[0] * inv
            out[y, x, 1] = total[1] * inv
            out[y, x, 2] = total[2] * inv
        else:
            radiance[i, 0], radiance[i, 1], radiance[i, 2] = total


@kernel
def _kernel(worker, n_workers, bvh, s, seed, spp, width, height, max_depth, rr_depth, paths,
            out, radiance, rec_i, rec_f, rec_lit):  # fmt: skip
    """``_trace_block`` over every pixel (``paths`` empty) or every path of ``paths``, in
    blocks of BLOCK dealt to min(blocks, CHUNKS) jobs: job j takes blocks j, j + jobs, ...;
    ``worker`` of ``n_workers`` (``minidiff.threads.run_jobs``) runs a contiguous run of
    jobs, so each thread's blocks are spread over the whole image (with one job per thread,
    the left and the right halves of a 128-pixel-wide image went to different threads,
    which take different times)."""
    n = width * height if paths.shape[0] == 0 else paths.shape[0]
    n_blocks = (n + BLOCK - 1) // BLOCK
    n_jobs = np.int64(min(n_blocks, CHUNKS))
    seed_key = mix(np.uint64(seed))
    first, stop = share(worker, n_workers, n_jobs)
    stack, stack_t = np.empty(bvh.stack_size, np.int64), np.empty(bvh.stack_size, np.float64)
    for job in range(first, stop):
        for b in range(job, n_blocks, n_jobs):
            _trace_block(bvh, s, seed_key, spp, width, height, max_depth, rr_depth, b * BLOCK,
                         min(n, (b + 1) * BLOCK), paths, stack, stack_t, out, radiance, rec_i,
                         rec_f, rec_lit)  # fmt: skip


def _run(packed: Packed, sampler: PathSampler, paths=None, out=None, radiance=None,
         records=None) -> None:  # fmt: skip
    """``_kernel`` with empty arrays for what this call does not use."""
    none_i = np.zeros((1, 0, R.I_FIELDS), np.int64)
    none_f, none_lit = np.zeros((1, 0, R.F_FIELDS)), np.zeros((1, 0, 1), bool)
    rec_i, rec_f, rec_lit = records or (none_i, none_f, none_lit)
    n = packed.width * packed.height if paths is None else len(paths)
    run_jobs(_kernel, job_count(min(-(-n // BLOCK), CHUNKS)), packed.bvh, packed.arrays,
             np.uint64(sampler.seed), sampler.spp, packed.width, packed.height,
             sampler.max_depth, sampler.rr_depth,
             np.zeros(0, np.int64) if paths is None else paths,
             np.zeros((0, 0, 3)) if out is None else out,
             np.zeros((0, 3)) if radiance is None else radiance, rec_i, rec_f,
             rec_lit)  # fmt: skip


def render_image(sampler: PathSampler, packed: Packed | None = None) -> np.ndarray:
    """The (H, W, 3) float64 image of ``sampler``'s scene: its spp paths per pixel, traced
    by the kernel (the same seed, the same image bit for bit on any number of threads)."""
    packed = pack(sampler) if packed is None else packed
    out = np.empty((packed.height, packed.width, 3))
    _run(packed, sampler, out=out)
    return out


def sample_paths(
    sampler: PathSampler, paths: np.ndarray, packed: Packed | None = None
) -> tuple[PathBatch, np.ndarray]:
    """The ``PathBatch`` of path ids ``paths`` (N,) int64, as ``sampler.sample(paths)``
    makes it, and each path's radiance (N, 3) float64, traced by the kernel."""
    packed = pack(sampler) if packed is None else packed
    n, depth = len(paths), min(sampler.max_depth, RECORD_ROWS)
    radiance = np.empty((n, 3))
    paths = np.ascontiguousarray(paths, np.int64)
    if n == 0:
        return PathBatch(paths, np.zeros((0, 2)), np.zeros(0, bool), []), radiance
    while True:
        records = R.Records.empty(depth, n, packed.n_lights, zeroed=False)  # (_clear_rows)
        _run(packed, sampler, paths=paths, radiance=radiance,
             records=(records.ints, records.floats, records.lit))  # fmt: skip
        count = records.count
        if count.max() <= depth:
            break
        depth = int(count.max())  # the same paths again, with room for every vertex
    coords = records.floats[0, :, R.COORD : R.COORD + 2].copy()
    return PathBatch(paths, coords, count == 0, records=records), radiance
