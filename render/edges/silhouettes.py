"""Silhouette edges: antialiasing on the tape, so that gradients see occlusion boundaries.

Visibility is a constant on the tape, so a pixel whose colour changes because an edge moves
across it contributes nothing to the gradient of the plain image. This module adds the
missing term the way nvdiffrast's ``antialias`` does (Laine et al. 2020, "Modular
Primitives for High-Performance Differentiable Rendering"), reformulated for rays:

1. Constants (``edge_pairs``, NumPy): every pair of horizontally or vertically adjacent
   samples whose primary hits differ, and the edge that separates them:
   * a *silhouette* of the nearer surface: a mesh boundary edge, or an edge whose two faces
     face opposite ways as seen from the eye (a sphere's outline always is). When the face
     hit at the near sample is not the one on the silhouette (faces smaller than pixels),
     ``render.trace.topology.walk_to_silhouette`` walks across the mesh, on *welded* adjacency
     (the teapot's patches share positions but not vertex ids), to the face that is;
   * else a *crease*: an edge across which the colour jumps (flat shading, or a seam of
     vertex ids for smooth normals and UVs);
   * or the line where the near face passes behind the far one (two surfaces that
     intersect, like the teapot's spout and body), when that comes first.
2. On the tape (``crossings``): where the edge crosses the segment between the two sample
   positions. With camera rays d_N (near sample) and d_F (far sample) and the edge
   (v_i, v_j) seen from the eye C, the edge function e(d) = d . ((v_i - C) x (v_j - C)) is
   linear along the segment of directions (d is affine in the image position), so the
   crossing is s* = e(d_N) / (e(d_N) - e(d_F)), in units of the sample spacing.
   For a sphere the outline is where the ray's discriminant vanishes: a quadratic in s.
3. Blend (``edge_updates``): each sample takes the other's colour in proportion to the
   area of its box on the other side of the edge (``box_coverage``: exact for a straight
   edge, its slope included; nvdiffrast uses the 1-D coverage along the pair). Each edge
   is handled by the pairs of one axis only: horizontal pairs take edges within 45
   degrees of vertical, vertical pairs the others.

The derivative of the blended colour with respect to s* is the colour difference across
the edge, so gradients reach the edge's vertices (or the sphere), the camera and, through
the colours, every shading parameter, with no hand-written backward pass.

With ``spp = n^2`` samples per pixel the samples form a regular grid n times finer than
the pixels; pairs are taken on that grid and the pixel is the mean of its blended samples.
Shadow edges reuse all of this (``render.edges.shadows``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import minidiff as md
from minidiff.either import as_column, dot_last
from render.edges.boundary.crossing import global_welded
from render.edges.geometry import (
    axis_ok,
    outline_normal,
    pair_coverages,
    plain_rays,
    plane_normal,
    sample_grid,
    sample_steps,
    slope_across,
    sphere_crossing,
    sphere_crossing_plain,
    triangle_corners,
)
from render.scene.camera import image_plane_coords, ray_directions
from render.scene.scene import Scene
from render.shade.surface import in_order
from render.trace.primitives import first_sphere_id
from render.trace.seams import WeldedMeshes, WeldedScene
from render.trace.topology import MeshEdges, silhouette_edges, walk_to_silhouette_fast

# --------------------------------------------------------------------------------------
# Pairs of samples across a silhouette (constants)
# --------------------------------------------------------------------------------------


@dataclass
class EdgePairs:
    """Adjacent samples whose hits differ across a silhouette, one row per pair.

    near, far (n,) int64: ray ids of the sample on the nearer surface and of the other one.
    prim (n,) int64: the primitive whose outline passes between them (global id,
        ``render.trace.visibility.scene_primitives``): a sphere, or the triangle owning the
        silhouette edge (on the nearer surface, not always the face hit at the sample).
    edge (n,) int64: its edge 0..2 (corners k, k + 1) for a triangle; -1 for a sphere; 3
        for the line where triangle ``prim`` passes behind triangle ``other`` (two surfaces
        that intersect, like the teapot's spout and body).
    other (n,) int64: that second triangle (-1 for the other kinds).
    horizontal (n,) bool: the samples are side by side in a row (else one above the other).
    """

    near: np.ndarray
    far: np.ndarray
    prim: np.ndarray
    edge: np.ndarray
    other: np.ndarray
    horizontal: np.ndarray


def candidate_pairs(grid: np.ndarray, prim_id: np.ndarray):
    """Adjacent samples (a, b) with different primitives, and whether the pair is
    horizontal: a (m,), b (m,), horizontal (m,) bool."""
    left, right = grid[:, :-1].ravel(), grid[:, 1:].ravel()
    top, bottom = grid[:-1, :].ravel(), grid[1:, :].ravel()
    h = prim_id[left] != prim_id[right]
    v = prim_id[top] != prim_id[bottom]
    a = np.concatenate([left[h], top[v]])
    b = np.concatenate([right[h], bottom[v]])
    horizontal = np.concatenate([np.ones(h.sum(), bool), np.zeros(v.sum(), bool)])
    return a, b, horizontal


def creases(group: WeldedMeshes, scene: Scene) -> np.ndarray:
    """(F, 3) bool: the colour may jump across edge k of face f of ``group`` (meshes welded
    as one) though it is no silhouette: where flat shading changes normal (not between two
    faces of one plane, as a face split in two has: no colour changes there) or changes
    material or way of shading (another mesh's face); where the faces do not share the
    edge's vertex ids (a seam: smooth or given normals and UVs are per vertex id, and
    every edge between two meshes is one)."""
    edges, meshes = group.edges, [scene.meshes[k] for k in group.meshes]
    seams = ~edges.shared_ids
    # Per face: flat and untextured (its colour from its own normal), and its material.
    member = np.searchsorted(group.meshes, group.face_mesh)  # each face's mesh in the group
    flat = np.array([not (m.smooth or m.normals is not None or m.material.textures)
                     for m in meshes])[member]  # fmt: skip
    looks = np.array([id(m.material) for m in meshes])[member]
    corners = group.vertices[group.faces]
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), np.finfo(float).tiny)
    nb = np.maximum(edges.neighbour, 0)
    # One plane within an angle of 2e-3 rad (a change of colour of 0.2 % at most): within
    # rounding, or tilted by a seam welded across a crack (``render.trace.topology.
    # seam_reach``: up to 1e-3 of the edges' length); whichever way the faces are wound
    # (their normals then opposite: the shading turns each to the viewer).
    cosine = np.abs(np.einsum("fkc,fc->fk", normal[nb], normal))
    same = (edges.neighbour >= 0) & (cosine > 1.0 - 2e-6)
    same &= (looks[nb] == looks[:, None]) & flat[nb]
    return np.where(flat[:, None], ~same, seams)


def edge_pairs(
    scene: Scene,
    prim_id: np.ndarray,
    depth: np.ndarray,
    spp: int,
    welded: WeldedScene,
    topology: dict[int, MeshEdges],
) -> EdgePairs:
    """Every pair of adjacent samples separated by a silhouette of the nearer primitive.

    prim_id, depth (N,): each ray's primitive (-1: none) and hit distance along the view
    axis (inf: none); welded: the meshes in groups welded as one (meshes that share edges
    or meet at T-junctions: the walk crosses from one to the other); topology:
    ``mesh_edges`` per mesh index in ``scene.meshes``.
    """
    camera = scene.camera
    grid = sample_grid(camera, spp)
    a, b, horizontal = candidate_pairs(grid, prim_id)
    a_nearer = depth[a] < depth[b]
    near, far = np.where(a_nearer, a, b), np.where(a_nearer, b, a)
    prim = prim_id[near]

    eye, d_near, d_far, to_pixels = plain_rays(camera, near, far, spp)
    edge = np.full(len(near), -2, dtype=np.int64)  # -2: not a silhouette pair
    s = np.full(len(near), np.nan)
    n_triangles = first_sphere_id(scene)
    on_mesh = np.flatnonzero((prim >= 0) & (prim < n_triangles))
    group_of, local = np.full(len(prim), -1), np.full(len(prim), -1)
    group_of[on_mesh], local[on_mesh] = welded.locate(prim[on_mesh])
    far_local = np.full(len(prim), -1)
    far_prim = prim_id[far]
    far_on = np.flatnonzero((far_prim >= 0) & (far_prim < n_triangles))
    far_group, far_local[far_on] = welded.locate(far_prim[far_on])
    far_local[far_on[far_group != group_of[far_on]]] = -1  # another group's face
    for g, group in enumerate(welded.groups):
        rows = np.flatnonzero(group_of == g)
        if len(rows) == 0:
            continue
        vertices, faces = group.vertices, group.faces
        silhouette = silhouette_edges(group.edges, vertices, faces, eye)
        face, k, s[rows], (mid_face, mid_k, mid_s) = walk_to_silhouette_fast(
            group.edges, silhouette, vertices, faces, local[rows], eye, d_near[rows],
            d_far[rows], jumps=creases(group, scene),
        )  # fmt: skip
        # Where no silhouette lies between the samples and the walk ended on the far
        # sample's face, blend across the crease crossed nearest the middle (at low
        # resolution several may lie between two samples: they move together, and one
        # crossing carries the whole colour difference).
        crease = (k < 0) & (mid_k >= 0) & (face == far_local[rows])
        face[crease], k[crease], s[rows[crease]] = mid_face[crease], mid_k[crease], mid_s[crease]
        corners = vertices[faces[face]]
        kk, r = np.maximum(k, 0), np.arange(len(rows))
        normal = np.cross(corners[r, kk] - eye, corners[r, (kk + 1) % 3] - eye)
        ok = (k >= 0) & axis_ok(normal, horizontal[rows], to_pixels)
        edge[rows] = np.where(ok, k, -2)
        prim[rows] = group.face_ids[face]
    for index, sphere in enumerate(scene.spheres):
        rows = np.flatnonzero(prim == n_triangles + index)
        if len(rows):
            s[rows] = sphere_crossing_plain(sphere, eye, d_near[rows], d_far[rows])
            normal = outline_normal(sphere.center.data, sphere.radius.data, eye,
                                     d_near[rows], d_far[rows], np.nan_to_num(s[rows]))  # fmt: skip
            ok = np.isfinite(s[rows]) & axis_ok(normal, horizontal[rows], to_pixels)
            edge[rows] = np.where(ok, -1, -2)
    other = np.full(len(near), -1, dtype=np.int64)
    if n_triangles:
        triangles = np.concatenate([m.triangles() for m in scene.meshes]).astype(np.float64)
        _intersections(
            triangles, global_welded(scene, topology), prim_id[near], prim_id[far], depth[far], eye,
            d_near, d_far, horizontal, to_pixels, prim, edge, s, other,
        )  # fmt: skip
    keep = edge >= -1
    return EdgePairs(near[keep], far[keep], prim[keep], edge[keep], other[keep], horizontal[keep])


def _intersection_normal(n1, a1, n2, a2, eye):
    """The edge function's normal m for the line where two planes (normal n, point a)
    cross, seen from the eye: the plane through the eye and that line is
    (n2 . (C - a2)) n1 . (p - a1) - (n1 . (C - a1)) n2 . (p - a2) = 0, so e(d) = m . d with
    m = (n2 . (C - a2)) n1 - (n1 . (C - a1)) n2. Tensors or arrays."""
    return as_column(dot_last(n2, eye - a2)) * n1 - as_column(dot_last(n1, eye - a1)) * n2


def _intersections(
    triangles, welded, near_prim, far_prim, far_depth, eye, d_near, d_far, horizontal,
    to_pixels, prim, edge, s, other,
):  # fmt: skip
    """Where the near sample's face dives behind the far sample's face before any
    silhouette or crease: the two planes' intersection line crosses the segment and, at the
    far sample, the near plane lies behind the far hit. Only for faces that touch nowhere
    (no welded vertex in common: neighbours meet at an edge, handled as a crease or not a
    discontinuity at all) and whose planes are not nearly parallel (their line would be
    ill-defined). Updates prim, edge (3), s and other in place for those pairs."""
    n_tri = len(triangles)
    rows = np.flatnonzero((near_prim < n_tri) & (far_prim >= 0) & (far_prim < n_tri))
    a, b = welded[near_prim[rows]], welded[far_prim[rows]]
    touching = (a[:, :, None] == b[:, None, :]).any(axis=(1, 2))
    rows = rows[~touching]
    if len(rows) == 0:
        return
    t1, t2 = triangles[near_prim[rows]], triangles[far_prim[rows]]
    n1, n2 = plane_normal(t1), plane_normal(t2)
    sin_angle = np.linalg.norm(np.cross(n1, n2), axis=1) / (
        np.linalg.norm(n1, axis=1) * np.linalg.norm(n2, axis=1)
    )
    # The near face's plane along the far sample's ray, against the far hit (same units).
    with np.errstate(divide="ignore", invalid="ignore"):
        t_plane = np.sum(n1 * (t1[:, 0] - eye), axis=1) / np.sum(n1 * d_far[rows], axis=1)
    behind = ~(t_plane > 0) | (t_plane > far_depth[rows])
    m = _intersection_normal(n1, t1[:, 0], n2, t2[:, 0], eye)
    e_near, e_far = np.sum(d_near[rows] * m, axis=1), np.sum(d_far[rows] * m, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        s_int = e_near / (e_near - e_far)
    crosses = (np.sign(e_near) != np.sign(e_far)) & (s_int > 0) & (s_int < 1)
    earlier = (edge[rows] < -1) | (s_int < s[rows] - 1e-9)
    use = behind & crosses & earlier & axis_ok(m, horizontal[rows], to_pixels)
    use &= sin_angle > 0.05
    rows = rows[use]
    prim[rows], edge[rows], s[rows], other[rows] = near_prim[rows], 3, s_int[use], far_prim[rows]


def crossings(scene: Scene, pairs: EdgePairs, frame, spp: int, dtype):
    """On the tape, per pair: s* (n,), where the edge crosses the segment from the near
    sample (s = 0) to the far one (s = 1), and its slope (n,) across the pair, |t| <= 1:
    along the edge, one sample step across the pair's axis moves the crossing by t steps
    along it."""
    camera, eye = scene.camera, frame[3]
    d_near = ray_directions(frame, image_plane_coords(camera, pairs.near, spp).astype(dtype))
    d_far = ray_directions(frame, image_plane_coords(camera, pairs.far, spp).astype(dtype))
    normals, order = [], []
    edges = np.flatnonzero((pairs.edge >= 0) & (pairs.edge < 3))
    if len(edges):  # a triangle's edge (v_k, v_k+1): m = (v_k - C) x (v_k+1 - C)
        corners = md.stack(triangle_corners(scene, pairs.prim[edges]), axis=1)  # (k, 3, 3)
        r, k = np.arange(len(edges)), pairs.edge[edges]
        normals.append(md.cross(corners[r, k] - eye, corners[r, (k + 1) % 3] - eye))
        order.append(edges)
    crossing = np.flatnonzero(pairs.edge == 3)
    if len(crossing):  # two faces' planes
        near_face, far_face = (
            triangle_corners(scene, pairs.prim[crossing]),
            triangle_corners(scene, pairs.other[crossing]),
        )
        normals.append(
            _intersection_normal(
                plane_normal(near_face), near_face[0], plane_normal(far_face), far_face[0], eye
            )
        )
        order.append(crossing)
    s_parts = []
    if normals:
        m = normals[0] if len(normals) == 1 else md.concatenate(normals)
        rows = np.concatenate(order)
        e_near, e_far = md.dot(d_near[rows], m), md.dot(d_far[rows], m)
        s_parts.append(e_near / (e_near - e_far))
    first = first_sphere_id(scene)
    for index, sphere in enumerate(scene.spheres):
        rows = np.flatnonzero((pairs.edge == -1) & (pairs.prim == first + index))
        if len(rows):
            s = sphere_crossing(sphere, eye, d_near[rows], d_far[rows])
            s_parts.append(s)
            normals.append(
                outline_normal(sphere.center, sphere.radius, eye, d_near[rows], d_far[rows], s)
            )
            order.append(rows)
    if not s_parts:
        empty = md.tensor(np.zeros(0, dtype))
        return empty, empty
    normal = in_order(normals, order)
    steps = sample_steps(camera, spp, dtype)
    return in_order(s_parts, order), slope_across(normal, frame, pairs.horizontal, steps)


def edge_updates(ray_colour: md.Tensor, pairs: EdgePairs, s: md.Tensor, slope: md.Tensor):
    """What blending the two samples of each pair by the coverage of their boxes adds to
    the samples' colours ray_colour (N, 3): (ray ids (2n,), additions (2n, 3)), or None.

    The near sample's box (centre at s = 0) shows the far colour on the far side of the
    edge, area ``box_coverage(0.5 - s*, t)``; the far sample's box (centre at s = 1) shows
    the near colour on the near side, area ``box_coverage(s* - 0.5, t)``. With |t| <= 1 the
    edge stays within the two boxes over the pair's row (or column), so each sample's box
    is accounted for exactly for a straight edge between two flat colours.
    """
    if len(pairs.near) == 0:
        return None
    change = ray_colour[pairs.far] - ray_colour[pairs.near]  # (n, 3)
    to_far, to_near = pair_coverages(s, slope)
    rays = np.concatenate([pairs.near, pairs.far])
    return rays, md.concatenate([to_far * change, to_near * (-change)])
