"""Steps 2 and 3 off the tape, in one compiled pass: the colour of k camera hits on a mesh
when nothing that colour depends on is differentiated.

``shade_camera_hits`` recomputes each hit's surface (``surface_at``) and shades it
(``shade_surface``) with minidiff operations: some forty passes over (k, 3) arrays, each
writing a new one. When no parameter of the camera, the mesh, its material or the lights
is differentiated, no tape is needed, and ``shade_mesh_values`` computes the same colours
point by point in one Numba loop: the camera ray, Moller-Trumbore, the normal (flat or
interpolated), the UV and texture lookups, every light's Lambert + Blinn-Phong term, the
ambient and emitted radiance.

The arithmetic is the tape code's, operation for operation and in the same order (Numba
does not contract a * b + c into a fused multiply-add without fastmath), so the colours
are the same bit for bit, except where a Blinn-Phong lobe raises n.h to the shininess:
NumPy's vectorised ``power`` and the C library's ``pow`` that Numba calls may round the
last bit differently. ``tests/render/shade/test_compiled_shading.py`` ties the two together.

Its users: a forward render that nothing differentiates, and the edge terms, which shade
what lies on either side of an edge off the tape (``render.edges.boundary.DirectRadiance``).
Spheres, float32 scenes and materials that reflect (their mirror rays are traced by
``render.shade.mirrors``) take the tape code, values only.
"""

from __future__ import annotations

import math

import numba
import numpy as np

import minidiff as md
from render.scene.scene import Mesh, Scene
from render.shade.surface import vertex_normals
from render.trace.intersect import BLOCK, _jobs

_NO_MAP = np.zeros((0, 0, 3))  # stands for an absent texture (Numba needs an array)


def applies(scene: Scene, obj, reflects: bool) -> bool:
    """Whether ``shade_mesh_values`` gives ``obj``'s camera hits their colour: a mesh in a
    float64 scene, ``reflects`` False (no mirror ray leaves it), and, while gradients are
    enabled, nothing its colour depends on differentiated (the camera, the mesh, its
    material, the lights); and every light one the kernel shades (``compiled_shading``)."""
    if not isinstance(obj, Mesh) or reflects:
        return False
    if not all(light.compiled_shading for light in scene.lights):
        return False
    owners = [scene.camera, obj, obj.material, *scene.lights]
    depends = [t for owner in owners for t in owner.named_parameters().values()]
    if any(t.dtype != np.float64 for t in depends):
        return False
    return not (md.is_grad_enabled() and any(t.is_differentiated() for t in depends))


def shade_mesh_values(
    mesh: Mesh, faces_hit: np.ndarray, camera, coords: np.ndarray, lights, lit
) -> tuple[np.ndarray, np.ndarray]:
    """The radiance (k, 3) float64 and texture cell (k,) int64 (-1: untextured) of k camera
    rays through image-plane points ``coords`` (k, 2) that hit the mesh's faces
    ``faces_hit`` (k,) (local ids): what ``surface_at`` then ``shade_surface`` compute,
    as plain values. ``camera``: (forward, right, up, eye) float64 (3,) each (the camera
    frame's values); ``lit[j]`` (k,): 1 where light j reaches the hit."""
    forward, right, up, eye = camera
    visible = np.zeros((len(lights), len(faces_hit)))
    for j, mask in enumerate(lit):
        visible[j] = mask
    out = np.empty((len(faces_hit), 3))
    texel = np.empty(len(faces_hit), np.int64)
    _shade_kernel(
        np.ascontiguousarray(coords, np.float64), (eye, right, up, forward), mesh_pack(mesh),
        np.ascontiguousarray(faces_hit, np.int64), material_pack(mesh.material),
        lights_pack(lights), visible, numba.get_num_threads(), out, texel,
    )  # fmt: skip
    return out, texel


def mesh_pack(mesh: Mesh) -> tuple:
    """``shade_hit``'s mesh tuple of ``mesh``: (vertices (V, 3), faces (F, 3), vertex
    normals (V, 3) (its own, or computed from its vertices; (0, 3) if it is flat), UVs
    (V, 2) ((0, 2) if untextured), smooth, textured)."""
    with md.no_grad():  # the normals a smooth mesh without its own computes from its vertices
        normals = (
            np.zeros((0, 3))
            if not mesh.smooth
            else mesh.normals.data
            if mesh.normals is not None
            else vertex_normals(mesh.vertices, mesh.faces).data
        )
    textured = bool(mesh.material.textures)
    uvs = mesh.uvs.data if textured else np.zeros((0, 2))
    return mesh.vertices.data, mesh.faces, normals, uvs, mesh.smooth, textured


def material_pack(material) -> tuple:
    """``shade_hit``'s material tuple of ``material`` (float64 values)."""
    maps = [material.texture, material.specular_texture, material.ambient_texture]
    specular, ambient, emission = (
        np.broadcast_to(t.data, (3,)).astype(np.float64)
        for t in (material.specular, material.ambient, material.emission)
    )
    return (
        *(_NO_MAP if m is None else m.data for m in maps),
        material.albedo.data, specular, ambient, float(material.shininess.data), emission,
        bool(np.any(material.specular.data)), bool(np.any(material.ambient.data)),
        material.emissive,
    )  # fmt: skip


def lights_pack(lights) -> tuple:
    """``shade_hit``'s lights tuple: per light its kind, its position or the unit vector
    towards it (``Light.shading_pack``), its strength and colour."""
    packs = [light.shading_pack() for light in lights]
    return (
        np.array([p[0] for p in packs], np.int64),
        np.array([p[1] for p in packs], np.float64).reshape(-1, 3),
        np.array([p[2] for p in packs], np.float64).reshape(-1),
        np.array([light.color.data for light in lights], np.float64).reshape(-1, 3),
    )


@numba.njit(cache=True, inline="always")
def sample_rgb(texture, u, v):
    """The bilinear lookup of an (H, W, 3) texture at UV (u, v), repeating
    (``render.shade.lighting.sample_texture`` for one point): its three channels, and the
    footprint's cell. One inlined copy serves all three channels: a copy per channel made
    every kernel that inlines ``shade_hit`` compile for longer."""
    height, width = texture.shape[0], texture.shape[1]
    x, y = u * width - 0.5, (1.0 - v) * height - 0.5
    # Floors kept as floats and wrapped before the cast (``lighting._wrapped``): Numba's
    # math.floor returns int64, which a UV of 1e100 overflows.
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = x - x0, y - y0
    ix0, iy0 = int(x0 % width), int(y0 % height)
    ix1, iy1 = (ix0 + 1) % width, (iy0 + 1) % height
    return (
        _bilinear(texture, iy0, ix0, iy1, ix1, fx, fy, 0),
        _bilinear(texture, iy0, ix0, iy1, ix1, fx, fy, 1),
        _bilinear(texture, iy0, ix0, iy1, ix1, fx, fy, 2),
        iy0 * width + ix0,
    )


@numba.njit(cache=True, inline="always")
def _bilinear(texture, iy0, ix0, iy1, ix1, fx, fy, c):
    """Channel c of ``sample_rgb``: the four texels' weighted sum."""
    top = texture[iy0, ix0, c] * (1.0 - fx) + texture[iy0, ix1, c] * fx
    bottom = texture[iy1, ix0, c] * (1.0 - fx) + texture[iy1, ix1, c] * fx
    return top * (1.0 - fy) + bottom * fy


@numba.njit(cache=True, inline="always")
def _unit(x0, x1, x2):
    """``md.normalize`` of one 3-vector: x times 1 / |x| (the zero vector stays zero)."""
    length = math.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
    inv = 1.0 / length if length > 0 else 0.0
    return x0 * inv, x1 * inv, x2 * inv


@numba.njit(cache=True, error_model="numpy", inline="always")
def camera_hit(x, y, camera, vertices, faces, face):
    """The camera ray through image-plane point (x, y) and its Moller-Trumbore intersection
    with row ``face`` of a mesh (``render.scene.camera.camera_directions``, then
    ``render.shade.surface.intersect_edges``), in the tape code's order of operations:
    d (the ray's direction), (ia, ib, ic) (the face's corners), e1 = b - a, e2 = c - a,
    s = eye - a, p = d x e2, q = s x e1 (three numbers each), 1 / det, t, u, v: one flat
    tuple of 25. Shared by
    ``shade_hit`` and its adjoint (``render.shade.adjoint_kernels``), which needs the
    intermediate values too. camera: (eye, right, up, forward); vertices (V, 3), faces
    (F, 3)."""
    eye, right, up, forward = camera
    d0 = x * right[0] + y * up[0] + forward[0]
    d1 = x * right[1] + y * up[1] + forward[1]
    d2 = x * right[2] + y * up[2] + forward[2]
    # Elements read one by one: a row view of a shared array counts a reference to it, an
    # atomic operation that every thread contends for.
    ia, ib, ic = faces[face, 0], faces[face, 1], faces[face, 2]
    ax, ay, az = vertices[ia, 0], vertices[ia, 1], vertices[ia, 2]
    e10, e11, e12 = vertices[ib, 0] - ax, vertices[ib, 1] - ay, vertices[ib, 2] - az
    e20, e21, e22 = vertices[ic, 0] - ax, vertices[ic, 1] - ay, vertices[ic, 2] - az
    p0, p1, p2 = d1 * e22 - d2 * e21, d2 * e20 - d0 * e22, d0 * e21 - d1 * e20  # d x e2
    inv_det = 1.0 / (e10 * p0 + e11 * p1 + e12 * p2)
    s0, s1, s2 = eye[0] - ax, eye[1] - ay, eye[2] - az
    q0, q1, q2 = s1 * e12 - s2 * e11, s2 * e10 - s0 * e12, s0 * e11 - s1 * e10  # s x e1
    t = (e20 * q0 + e21 * q1 + e22 * q2) * inv_det
    u = (s0 * p0 + s1 * p1 + s2 * p2) * inv_det
    v = (d0 * q0 + d1 * q1 + d2 * q2) * inv_det
    # One flat tuple: unpacking nested tuples in a parallel kernel fails Numba's array
    # analysis ("Dimension mismatch").
    return (
        d0, d1, d2, ia, ib, ic, e10, e11, e12, e20, e21, e22, s0, s1, s2, p0, p1, p2,
        q0, q1, q2, inv_det, t, u, v,
    )  # fmt: skip


@numba.njit(cache=True, error_model="numpy", inline="always")
def shade_hit(x, y, camera, mesh, face, material, lights, lit, i, out, r):
    """The radiance of one camera ray through image-plane point (x, y) that hits row
    ``face`` of ``mesh``: what ``surface_at`` then ``shade_surface`` compute for one hit,
    in the tape code's order of operations. Written into row r of ``out`` (n, 3); returns
    the hit's texture cell (-1: untextured). Arrays and a row rather than row views: each
    view counts a reference to its array, atomically, which threads then contend for.

    camera: (eye, right, up, forward), float64 (3,) each (the camera frame's values).
    mesh: (vertices (V, 3) float64, faces (F, 3) int64, vertex normals (V, 3) (read only
        if smooth), UVs (V, 2) (read only if textured), smooth, textured).
    material: (albedo map, specular map, ambient map: (H, W, 3) float64 each, (0, 0, 3)
        for none; albedo (3,), specular (3,), ambient (3,), shininess (float), emission
        (3,); specular_on, ambient_on, emissive: whether those terms are added).
    lights: (kind (L,) int64, vector (L, 3): a point light's position or the unit vector
        towards a directional light, strength (L,), colour (L, 3)) (``Light.shading_pack``).
    lit: (L, k) float64; column i: 1 where light j reaches the hit, 0 where it does not."""
    eye = camera[0]
    vertices, faces, vertex_normal, uvs, smooth, textured = mesh
    albedo_map, specular_map, ambient_map = material[0], material[1], material[2]
    albedo, specular, ambient, shininess, emission = material[3:8]
    specular_on, ambient_on, emissive = material[8], material[9], material[10]
    light_kind, light_vec, light_strength, light_color = lights
    (
        d0, d1, d2, ia, ib, ic, e10, e11, e12, e20, e21, e22, _, _, _, _, _, _,
        _, _, _, _, t, u, v,
    ) = camera_hit(x, y, camera, vertices, faces, face)  # fmt: skip
    # The normal, facing the ray (surface_at, toward_ray).
    n0, n1, n2 = _unit(e11 * e22 - e12 * e21, e12 * e20 - e10 * e22, e10 * e21 - e11 * e20)
    flip = -1.0 if n0 * d0 + n1 * d1 + n2 * d2 > 0 else 1.0
    w0 = 1.0 - u - v
    if smooth:
        normal = vertex_normal
        n0, n1, n2 = _unit(
            0 + w0 * normal[ia, 0] + u * normal[ib, 0] + v * normal[ic, 0],
            0 + w0 * normal[ia, 1] + u * normal[ib, 1] + v * normal[ic, 1],
            0 + w0 * normal[ia, 2] + u * normal[ib, 2] + v * normal[ic, 2],
        )
    n0, n1, n2 = n0 * flip, n1 * flip, n2 * flip
    # The material at the hit (render.shade.lighting.appearance). Each map's test sits
    # outside the loop over channels and the values stay in scalars: a branch inside the
    # loop, and rows of a scratch array, made this pass ~2x slower.
    texel = -1
    uu = vv = 0.0
    if textured:
        uu = 0 + w0 * uvs[ia, 0] + u * uvs[ib, 0] + v * uvs[ic, 0]
        vv = 0 + w0 * uvs[ia, 1] + u * uvs[ib, 1] + v * uvs[ic, 1]
    if albedo_map.shape[0] > 0:
        a0, a1, a2, texel = sample_rgb(albedo_map, uu, vv)
    else:
        a0, a1, a2 = albedo[0], albedo[1], albedo[2]
    k0, k1, k2 = specular[0], specular[1], specular[2]
    if specular_map.shape[0] > 0:
        m0, m1, m2, _ = sample_rgb(specular_map, uu, vv)
        k0, k1, k2 = specular[0] * m0, specular[1] * m1, specular[2] * m2
    # The lights (render.shade.lighting.shade), summed in the tape's order.
    lobe_scale = (shininess + 8.0) / (8.0 * math.pi)
    point = (eye[0] + t * d0, eye[1] + t * d1, eye[2] + t * d2)
    r0 = r1 = r2 = 0.0
    for j in range(light_kind.shape[0]):
        if light_kind[j] == 0:  # a point light
            o0 = light_vec[j, 0] - point[0]
            o1 = light_vec[j, 1] - point[1]
            o2 = light_vec[j, 2] - point[2]
            distance_sq = o0 * o0 + o1 * o1 + o2 * o2
            irradiance = light_strength[j] / (1.0 if distance_sq == 0 else distance_sq)
            l0, l1, l2 = _unit(o0, o1, o2)
        else:  # a directional light: light_vec holds the unit vector to it
            l0, l1, l2 = light_vec[j, 0], light_vec[j, 1], light_vec[j, 2]
            irradiance = light_strength[j]
        cos_theta = n0 * l0 + n1 * l1 + n2 * l2
        cos_theta = 0.0 if cos_theta < 0.0 else cos_theta
        f0, f1, f2 = a0 * (1.0 / math.pi), a1 * (1.0 / math.pi), a2 * (1.0 / math.pi)
        if specular_on:
            view = _unit(d0, d1, d2)
            h0, h1, h2 = _unit(l0 + -view[0], l1 + -view[1], l2 + -view[2])
            n_dot_h = n0 * h0 + n1 * h1 + n2 * h2
            n_dot_h = 1e-12 if n_dot_h < 1e-12 else n_dot_h
            lobe = n_dot_h**shininess * lobe_scale
            f0, f1, f2 = f0 + lobe * k0, f1 + lobe * k1, f2 + lobe * k2
        scalar = irradiance * cos_theta * lit[j, i]
        t0 = scalar * (f0 * light_color[j, 0])
        t1 = scalar * (f1 * light_color[j, 1])
        t2 = scalar * (f2 * light_color[j, 2])
        r0, r1, r2 = (t0, t1, t2) if j == 0 else (r0 + t0, r1 + t1, r2 + t2)
    if ambient_on:
        if ambient_map.shape[0] > 0:
            m0, m1, m2, _ = sample_rgb(ambient_map, uu, vv)
            r0, r1, r2 = r0 + ambient[0] * m0, r1 + ambient[1] * m1, r2 + ambient[2] * m2
        else:
            r0, r1, r2 = r0 + ambient[0], r1 + ambient[1], r2 + ambient[2]
    if emissive:
        front = 1.0 if flip > 0 else 0.0
        r0, r1, r2 = r0 + front * emission[0], r1 + front * emission[1], r2 + front * emission[2]
    out[r, 0], out[r, 1], out[r, 2] = r0, r1, r2
    return texel


@numba.njit(cache=True, error_model="numpy", parallel=True)
def _shade_kernel(
    coords, camera, mesh, faces_hit, material, lights, visible, n_threads, out, texel
):
    """``shade_mesh_values``' loop: ``shade_hit`` of every hit p, in parallel over
    ``n_threads`` (``render.trace.intersect._jobs``); ``visible`` (L, k) the lit masks."""
    k = faces_hit.shape[0]
    n_blocks, n_jobs = _jobs(k, n_threads)
    for job in numba.prange(n_jobs):
        for block in range(job, n_blocks, n_jobs):
            for p in range(block * BLOCK, min(k, (block + 1) * BLOCK)):
                texel[p] = shade_hit(
                    coords[p, 0], coords[p, 1], camera, mesh, faces_hit[p], material, lights,
                    visible, p, out, p,
                )  # fmt: skip
