"""Mesh edges' factors: both sides of every visible edge point found and their shadow rays
traced in one compiled pass, their radiance shaded by the compiled shading, the factor
written.

``render.edges.boundary.mesh_edge._edge_factors`` states the factor of a mesh edge's
quadrature point, w (f_+ - f_-) / |grad e|, with NumPy passes and the renderer's general
shading (``DirectRadiance``: ``seen_through`` -> shadow rays per light, ``Mirrors``,
``shade_camera_hits``). For the common scene, ``side_factors`` computes the same numbers
in two steps: the discrete work in one parallel Numba function (``side_hits_kernel``: per
side, the hit (the face at the edge point, or the closest hit of the ray ``EPSILON``
pixels beside the edge) and the shadow ray towards each light
(``render.trace.visibility.shadow_rays``' offset and ignored primitive, answered by the
BVH's any-hit traversal: the render's answers)), then the colour of every side's hit by
the camera hits' own compiled shading (``render.shade.compiled.shade_mesh``, the readable
formulas traced), mesh by mesh.

It applies (``pack_scene`` returns a ``PackedScene``) where the reference would shade every
mesh hit with the compiled shading: a ``DirectRadiance``, every light one that
``Light.compiled_shading`` covers, and every mesh one ``render.shade.compiled.applies``
takes (float64, untextured, no mirror rays leaving it). Spheres may be in the scene: they
block rays; a side whose ray beside the edge hits one is left to the reference
(``needs_reference``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

import minidiff as md
from render.edges.boundary.radiance import EPSILON, DirectRadiance
from render.scene.lights import POINT
from render.scene.scene import Mesh, Scene
from render.shade import compiled
from render.trace.intersect import (
    BLOCK,
    FlatBVH,
    _jobs,
    closest_hit_ray,
    intersect_prim,
    make_ray,
    occluded_call,
)
from render.trace.primitives import primitive_ranges
from render.trace.visibility import SHADOW_EPSILON, SHADOW_ULPS, Visibility

#: ``shadow_offset``'s SHADOW_ULPS units in the last place, per unit of magnitude.
_ULP_SCALE = SHADOW_ULPS * np.finfo(np.float64).eps


@dataclass
class PackedScene:
    """What ``side_factors`` reads of a render: ``bvh`` its accelerator's tree, ``rows``
    (P,) the row of each primitive in the tree's leaf table; ``shadow`` (kind (L,) int64,
    vector (L, 3): a point light's position or the unit direction of a directional light's
    shadow rays, whether shadow rays are traced at all, the scene-size part of the shadow
    offset); the ``scene`` (its meshes and lights shade the sides) and its ``background``
    (3,)."""

    bvh: FlatBVH
    rows: np.ndarray
    shadow: tuple
    scene: Scene
    background: np.ndarray


def pack_scene(scene: Scene, radiance) -> PackedScene | None:
    """The render's scene as ``side_factors`` reads it, or None where it does not apply
    (the module docstring): the reference computes the factors then."""
    if type(radiance) is not DirectRadiance or not scene.meshes:
        return None
    # As DirectRadiance.seen decides: mirror rays only where some reflectance is not zero.
    bounces = radiance.max_bounces
    if not any(np.any(obj.material.reflectance.data) for obj in scene.objects):
        bounces = 0
    for mesh in scene.meshes:
        reflects = bounces > 0 and mesh.material.reflective
        if not compiled.applies(scene, mesh, reflects):
            return None
    background = np.broadcast_to(np.asarray(scene.background.data, np.float64), (3,))
    visibility: Visibility = radiance.visibility
    bvh = visibility.accelerator().flat_tree()
    rows = np.empty(len(bvh.leaf_ids), np.int64)
    rows[bvh.leaf_ids] = np.arange(len(bvh.leaf_ids))
    shadow = _pack_shadows(scene, visibility)
    return PackedScene(bvh, rows, shadow, scene, np.ascontiguousarray(background))


def _pack_shadows(scene: Scene, visibility: Visibility) -> tuple:
    """``PackedScene.shadow``: per light its kind and its position (a point light) or the
    unit direction its shadow rays take (``Light.shadow_rays``' own), whether shadows are
    traced, and SHADOW_EPSILON times the scene's size."""
    kinds = np.array([light.KIND for light in scene.lights], np.int64)
    vectors = np.zeros((len(scene.lights), 3))
    for j, light in enumerate(scene.lights):
        location = light.location()
        if location is not None:
            vectors[j] = location
        else:  # the light's own shadow ray from the origin: its unit direction
            vectors[j] = np.asarray(light.shadow_rays(np.zeros((1, 3)), 0.0)[1])[0]
    return kinds, vectors, bool(visibility.shadows), SHADOW_EPSILON * visibility.size


def side_factors(
    packed: PackedScene, frame, coords, depth, step, chosen, scale
) -> tuple[np.ndarray, np.ndarray]:
    """The factors (n, 3) of n visible edge points, and which of them ``needs_reference``
    (n,) bool (a side's ray hit a sphere: their factors are left zero). ``frame`` (forward,
    right, up, eye); coords (n, 2) image-plane points on the edges, depth (n,) the edge
    point's depth, step (n, 2) the image-plane step from the edge towards its + side,
    chosen (n, 2) the face seen on the + and - side (global ids, -1: none), scale (n,)
    w / |grad e|."""
    n, n_lights = len(coords), len(packed.scene.lights)
    needs_reference = np.zeros(n, np.bool_)
    if not n:
        return np.zeros((0, 3)), needs_reference
    forward, right, up, eye = (np.asarray(getattr(t, "data", t), np.float64) for t in frame)
    # Side s of point p is row s * n + p (+ side 0, - side 1).
    xy, prim, lit = np.empty((2 * n, 2)), np.empty(2 * n, np.int64), np.ones((2 * n, n_lights))
    side_hits_kernel(
        packed.bvh, packed.rows, (eye, right, up, forward), packed.shadow,
        np.ascontiguousarray(coords, np.float64), np.ascontiguousarray(depth, np.float64),
        np.ascontiguousarray(step, np.float64), np.ascontiguousarray(chosen, np.int64),
        numba.get_num_threads(), xy, prim, lit, needs_reference,
    )  # fmt: skip
    colour = np.empty((2 * n, 3))
    colour[...] = packed.background
    shaded = (prim >= 0) & ~np.concatenate([needs_reference, needs_reference])
    with md.no_grad():
        for obj, first, count in primitive_ranges(packed.scene):
            rows = np.flatnonzero(shaded & (prim >= first) & (prim < first + count))
            if len(rows) and isinstance(obj, Mesh):
                masks = [lit[rows, j] for j in range(n_lights)]
                colour[rows] = compiled.shade_mesh(
                    obj, prim[rows] - first, (forward, right, up, eye), xy[rows],
                    packed.scene.lights, masks,
                ).data  # fmt: skip
    out = np.asarray(scale, np.float64)[:, None] * (colour[:n] - colour[n:])
    out[needs_reference] = 0.0
    return out, needs_reference


@numba.njit(cache=True, error_model="numpy", inline="always")
def _magnitude(points, hit, group):
    """max |x| over the coordinates of the points (2n, 3) whose ``hit`` (2n,) is ``group``
    (``render.trace.visibility.shadow_offset``'s magnitude; 0 for none). A maximum is the
    same in any order."""
    top = 0.0
    for s in range(points.shape[0]):
        if hit[s] == group:
            for c in range(3):
                top = max(top, abs(points[s, c]))
    return top


@numba.njit(cache=True, error_model="numpy", inline="always")
def _shadow_ray(kind, vector, offset, point):
    """The shadow ray from ``point`` (3,) towards a light of ``kind`` (``vector``: its
    position, or its shadow rays' unit direction), started ``offset`` towards it: the ray
    ``Light.shadow_rays`` makes, with ``trace_shadows``' tmin 0."""
    p0, p1, p2 = point[0], point[1], point[2]
    if kind == POINT:  # render.scene.lights._point_light_rays, one ray
        tx, ty, tz = vector[0] - p0, vector[1] - p1, vector[2] - p2
        distance = np.sqrt(tx * tx + ty * ty + tz * tz)
        if distance <= 2.0 * offset:  # the light within the offset: tmax 0, never blocked
            origin = (p0 + offset * tx, p1 + offset * ty, p2 + offset * tz)
            return make_ray(origin, (0.0, 1.0, 0.0), 0.0, 0.0)
        fraction = offset / distance
        tmax = 1.0 - fraction / (1.0 - fraction)
        o0, o1, o2 = p0 + fraction * tx, p1 + fraction * ty, p2 + fraction * tz
        return make_ray((o0, o1, o2), (vector[0] - o0, vector[1] - o1, vector[2] - o2), 0.0, tmax)
    # DirectionalLight.shadow_rays: points + offset * unit, never ending
    origin = (p0 + offset * vector[0], p1 + offset * vector[1], p2 + offset * vector[2])
    return make_ray(origin, (vector[0], vector[1], vector[2]), 0.0, np.inf)


@numba.njit(cache=True, error_model="numpy", inline="always")
def _blocks(bvh, rows, prim, ray):
    """Whether triangle ``prim`` (row ``rows[prim]`` of the leaf table) blocks ``ray``: the
    test the any-hit traversal makes of it."""
    return intersect_prim(bvh.leaf_prim, rows[prim], prim, bvh.n_tri, ray)[0] < ray.tmax


# A function of its own, not inlined (twice) into the kernel, and its traversals calls: the
# kernel compiled for three minutes with them inlined (render.trace.intersect.occluded_call).
@numba.njit(cache=True, error_model="numpy")
def _lit(bvh, rows, shadow, offsets, group, point, plus, minus, stack, lit):
    """``lit`` (L, 2) = 1.0 where light j reaches ``point`` (3,) from the + and the - side,
    0.0 where a primitive blocks its shadow ray (``shadow_rays``, answered as
    ``occluded_ray`` answers it). ``plus`` and ``minus``: the triangle each side sees (its
    ray skips it), -1 for a side not at this point (its row is left as it was).

    A point seen on both sides (a crease) has one shadow ray per light, skipping either
    face: one traversal that skips ``plus`` answers the + side; the - side is blocked by
    ``plus`` itself, or, if the traversal found a blocker, by it unless that was ``minus``
    (a second traversal only when ``minus`` blocks the ray)."""
    kinds, vectors, traced = shadow[0], shadow[1], shadow[2]
    for j in range(kinds.shape[0]):
        if not traced:
            lit[j, 0] = lit[j, 1] = 1.0
            continue
        ray = _shadow_ray(kinds[j], vectors[j], offsets[group, j], point)
        if plus < 0:
            lit[j, 1] = 0.0 if occluded_call(bvh, ray, minus, stack) else 1.0
            continue
        blocked = occluded_call(bvh, ray, plus, stack)
        lit[j, 0] = 0.0 if blocked else 1.0
        if minus >= 0:
            if not blocked:
                blocked = _blocks(bvh, rows, plus, ray)
            elif _blocks(bvh, rows, minus, ray):
                blocked = occluded_call(bvh, ray, minus, stack)
            lit[j, 1] = 0.0 if blocked else 1.0


@numba.njit(cache=True, error_model="numpy", parallel=True)
def side_hits_kernel(
    bvh, rows, camera, shadow, coords, depth, step, chosen, n_threads, xy, prim, lit_out,
    needs_reference,
):  # fmt: skip
    """``side_factors``' discrete work, points shared out over ``n_threads`` as the ray
    kernels share rays (``render.trace.intersect._jobs``). Side s of point p is row
    s * n + p (+ side 0, - side 1) of ``xy`` (2n, 2) (its image-plane point), ``prim``
    (2n,) (the primitive it sees, -1: none) and ``lit_out`` (2n, L) (1.0 where light j
    reaches its point). Two passes, as the reference's two batches of rays need: the first
    finds every side's hit (the face at the edge point, or the closest hit of the camera
    ray ``EPSILON`` pixels beside the edge) and its point; then the shadow offset of each
    batch (``shadow_offset``: faced sides, then the sides traced beside the edge) from the
    largest coordinate among its points; the second traces the shadow rays."""
    eye, right, up, forward = camera
    n = coords.shape[0]
    n_tri = bvh.n_tri
    points = np.zeros((2 * n, 3))
    group = np.full(2 * n, -1, np.int64)  # 0: seen at the edge point, 1: traced beside it
    n_blocks, n_jobs = _jobs(n, n_threads)
    for job in numba.prange(n_jobs):
        stack = np.empty(bvh.stack_size, np.int64)
        stack_t = np.empty(bvh.stack_size, np.float64)
        for block in range(job, n_blocks, n_jobs):
            for p in range(block * BLOCK, min(n, (block + 1) * BLOCK)):
                for side in range(2):
                    s = side * n + p
                    x, y, t, face = coords[p, 0], coords[p, 1], depth[p], chosen[p, side]
                    if face < 0:  # the ray beside the edge: its closest hit
                        dx, dy = EPSILON * step[p, 0], EPSILON * step[p, 1]
                        x, y = (x + dx, y + dy) if side == 0 else (x + -dx, y + -dy)
                    d0 = x * right[0] + y * up[0] + forward[0]
                    d1 = x * right[1] + y * up[1] + forward[1]
                    d2 = x * right[2] + y * up[2] + forward[2]
                    if face < 0:
                        ray = make_ray(eye, (d0, d1, d2), 0.0, np.inf)
                        face, t = closest_hit_ray(bvh, ray, stack, stack_t)[:2]
                    xy[s, 0], xy[s, 1], prim[s] = x, y, face
                    if face >= 0:
                        group[s] = 0 if chosen[p, side] >= 0 else 1
                        points[s, 0] = eye[0] + t * d0
                        points[s, 1] = eye[1] + t * d1
                        points[s, 2] = eye[2] + t * d2
                    if face >= n_tri:
                        needs_reference[p] = True  # a sphere: shaded by the reference
    # The shadow offset per batch and light (render.trace.visibility.shadow_offset).
    kinds, vectors, epsilon_size = shadow[0], shadow[1], shadow[3]
    offsets = np.empty((2, kinds.shape[0]))
    for g in range(2):
        top = _magnitude(points, group, g)
        for j in range(kinds.shape[0]):
            magnitude = top
            if kinds[j] == POINT:
                for c in range(3):
                    magnitude = max(magnitude, abs(vectors[j, c]))
            offsets[g, j] = max(epsilon_size, _ULP_SCALE * magnitude)
    for job in numba.prange(n_jobs):
        stack = np.empty(bvh.stack_size, np.int64)
        lit = np.empty((kinds.shape[0], 2))  # per light, the two sides
        for block in range(job, n_blocks, n_jobs):
            for p in range(block * BLOCK, min(n, (block + 1) * BLOCK)):
                if needs_reference[p]:
                    continue
                # The faced sides share the edge point: their shadow rays are traced together.
                plus, minus = chosen[p, 0], chosen[p, 1]
                if plus >= 0 or minus >= 0:
                    s = p if plus >= 0 else n + p
                    _lit(bvh, rows, shadow, offsets, 0, points[s], plus, minus, stack, lit)
                for side in range(2):
                    s = side * n + p
                    f = prim[s]
                    if f < 0:
                        continue
                    if chosen[p, side] < 0:  # traced beside the edge: a point of its own
                        plus, minus = (f, -1) if side == 0 else (-1, f)
                        _lit(bvh, rows, shadow, offsets, 1, points[s], plus, minus, stack, lit)
                    for j in range(kinds.shape[0]):
                        lit_out[s, j] = lit[j, side]
