"""Shadow edges: hard shadows whose boundaries move with the light, the occluder and the
receiver, on the tape.

A shadow boundary is where the plane through an occluder's silhouette edge (as seen from
the light) cuts the receiving surface. Between two adjacent samples on the same object,
one lit by a light and one not, it is found and blended exactly like a silhouette between
two samples (``render.edges.silhouettes``), but only the light's own contribution is blended:

1. Constants (``shadow_pairs``): the pairs; the occluder (the primitive that blocks the
   dark sample's shadow ray: ``Accelerator.closest_hit`` along it); its silhouette edge
   *as seen from the light* between the two shadow rays (``render.trace.topology``'s walk, with
   the light as the viewer: for a directional light the viewer is at infinity).
2. On the tape (``shadow_crossings``): the shadow plane of edge (v_i, v_j) has normal
   m = (v_i - L) x (v_j - L) for a point light L and m = (v_j - v_i) x w for a directional
   light travelling along w. Along the pair, the receiver point seen through camera
   direction d on the receiver's plane (normal n through a) is P(d) = C + (n.(a - C) /
   n.d) d, so m . (P(d) - v_i) = 0 is, times n.d, linear in d:
       M . d = 0  with  M = (m . (C - v_i)) n + (n . (a - C)) m,
   and d is affine along the pair: the crossing is s* = M.d_lit / (M.d_lit - M.d_dark),
   the same closed form as a silhouette. A sphere occluder (point lights): the light's
   ray to P(d) grazes it where a quadratic in s vanishes (``render.edges.silhouettes``'s sphere
   crossing, with the light as the eye and u(d) = (n.d)(P(d) - L), linear in d, as the
   directions).
3. Blend (``shadow_updates``): the lit sample's box loses, and the dark sample's box
   gains, the light's unoccluded contribution times the area of the box on the other side
   of the shadow edge (``render.edges.geometry.box_coverage``).

Approximations (measured in ``tests/render/edges/test_shadow_edges.py``): the receiver is
taken to be the plane of the lit sample's face (its tangent plane on a sphere), so a curved receiver
or a pair across a crease of the receiver is approximated by that plane; pairs whose two
samples hit different objects get no shadow-edge term (their silhouette term, if any,
blends the whole colour already); a sphere occluder under a directional light gets none.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import minidiff as md
from minidiff.either import as_column, dot_last
from render.edges import geometry
from render.scene.camera import image_plane_coords, ray_directions
from render.scene.lights import DIRECTIONAL
from render.scene.scene import Scene
from render.shade.hits import working_dtype
from render.shade.lighting import appearance, light_contribution
from render.shade.surface import Hits, Surface, in_order
from render.trace.accel import Accelerator
from render.trace.primitives import first_sphere_id, object_index_of, primitive_ranges
from render.trace.seams import WeldedScene
from render.trace.topology import silhouette_edges, walk_to_silhouette_fast
from render.trace.visibility import shadow_rays


@dataclass
class ShadowPairs:
    """Adjacent samples on one object, lit and not lit by one light, one row per pair.

    lit, dark (n,) int64: ray ids of the lit and of the shadowed sample.
    light (n,) int64: the light's index in ``scene.lights``.
    occluder (n,) int64: the primitive whose outline (seen from the light) casts the edge.
    edge (n,) int64: its edge 0..2 (corners k, k + 1); -1 for a sphere.
    horizontal (n,) bool: the samples are side by side in a row.
    """

    lit: np.ndarray
    dark: np.ndarray
    light: np.ndarray
    occluder: np.ndarray
    edge: np.ndarray
    horizontal: np.ndarray

    @classmethod
    def empty(cls) -> ShadowPairs:
        return cls(*(np.zeros(0, np.int64) for _ in range(5)), np.zeros(0, bool))

    @classmethod
    def concatenate(cls, parts: list[ShadowPairs]) -> ShadowPairs:
        if not parts:
            return cls.empty()
        columns = zip(*(vars(p).values() for p in parts), strict=True)
        return cls(*(np.concatenate(x) for x in columns))


def _receiver_planes(scene: Scene, prim: np.ndarray, points: np.ndarray):
    """The receiver's plane at each sample: normal (n, 3) and a point on it (n, 3): the hit
    face's plane, or a sphere's tangent plane at the hit point."""
    n_tri = first_sphere_id(scene)
    normal, anchor = np.empty((len(prim), 3)), np.array(points, dtype=np.float64)
    if n_tri:
        tri = np.concatenate([m.triangles() for m in scene.meshes]).astype(np.float64)
        on_tri = prim < n_tri
        corners = tri[prim[on_tri]]
        normal[on_tri] = geometry.plane_normal(corners)
        anchor[on_tri] = corners[:, 0]
    for index, sphere in enumerate(scene.spheres):
        on = prim == n_tri + index
        normal[on] = points[on] - np.asarray(sphere.center.data, np.float64)
    return normal, anchor


def _image_normal(m, v_i, normal, anchor, eye):
    """M = (m . (C - v_i)) n + (n . (a - C)) m: the normal, in camera-direction space, of
    the image line where the plane m . (P - v_i) = 0 cuts the receiver plane (n, a).
    Tensors or arrays, (k, 3) each."""
    return (
        as_column(dot_last(m, eye - v_i)) * normal + as_column(dot_last(normal, anchor - eye)) * m
    )


def _homogeneous_points(d, normal, anchor, eye, origin):
    """u(d) = (n . d)(C - origin) + (n . (a - C)) d = (n . d) (P(d) - origin), with P(d)
    the receiver point seen along d: linear in d. Tensors or arrays."""
    return (
        as_column(dot_last(normal, d)) * (eye - origin)
        + as_column(dot_last(normal, anchor - eye)) * d
    )


def shadow_pairs(
    scene: Scene,
    accel: Accelerator,
    primary,
    lit: list[np.ndarray],
    spp: int,
    welded: WeldedScene,
    size: float,
) -> ShadowPairs:
    """Every pair of adjacent samples on one object across a shadow edge of some light.

    primary: ``render.trace.visibility.PrimaryHits``; lit[j] (k,) bool per hit ray; welded:
    the meshes in groups welded as one (``render.trace.seams.WeldedScene``: the walk
    crosses from one mesh to another where they share edges); size: the scene's size (for
    the shadow rays' start offset).
    """
    camera, prim_id = scene.camera, primary.prim_id
    grid = geometry.sample_grid(camera, spp)
    hit_index = np.full(prim_id.size, -1, dtype=np.int64)
    hit_index[primary.hit_rays] = np.arange(len(primary.hit_rays))
    n_tri = first_sphere_id(scene)
    parts = []
    for j, light in enumerate(scene.lights):
        lit_ray = np.zeros(prim_id.size, dtype=bool)  # per ray: light j reaches its hit
        lit_ray[primary.hit_rays] = lit[j]
        lit_grid = lit_ray[grid]
        # Pairs whose shadow state differs (cheap on the whole grid), then only those few on
        # one object (both samples hit it).
        h = lit_grid[:, :-1] != lit_grid[:, 1:]
        v = lit_grid[:-1, :] != lit_grid[1:, :]
        a = np.concatenate([grid[:, :-1][h], grid[:-1, :][v]])
        b = np.concatenate([grid[:, 1:][h], grid[1:, :][v]])
        horizontal = np.concatenate([np.ones(h.sum(), bool), np.zeros(v.sum(), bool)])
        obj_a, obj_b = (
            _surface_of(scene, welded, prim_id[a]),
            _surface_of(scene, welded, prim_id[b]),
        )
        same = (obj_a == obj_b) & (obj_a >= 0)
        a, b, h = a[same], b[same], horizontal[same]
        if len(a) == 0:
            continue
        lit_id, dark_id = np.where(lit_ray[a], a, b), np.where(lit_ray[a], b, a)
        dark_points = primary.points[hit_index[dark_id]]
        rays = shadow_rays(light, dark_points, prim_id[dark_id], accel.n_triangles, size)
        tmax = light.shadow_ray_end
        blocker, _, _, _ = accel.closest_hit(rays.origins, rays.directions, 0.0, tmax)
        rows = (lit_id, dark_id, h, blocker)
        parts.append(
            _edges_of_blockers(scene, light, j, primary, hit_index, rows, n_tri, welded, spp)
        )
    return ShadowPairs.concatenate(parts)


def _surface_of(scene: Scene, welded: WeldedScene, prim: np.ndarray) -> np.ndarray:
    """(k,): which surface each primitive ``prim`` (k,) (-1: none) lies on: its meshes'
    welded group (meshes that share edges are one surface, as a multi-material file's
    are: a shadow falling across their seam has its edge like one inside a mesh; taken
    object by object, a teapot in four meshes lost the shadow edges across them, its
    pixel pairs' gradients 1.5 % off), or its sphere; -1 for none."""
    obj = object_index_of(scene, prim)
    n_meshes, n_groups = len(scene.meshes), len(welded.groups)
    out = np.where(obj >= 0, obj - n_meshes + n_groups, -1)  # spheres after the groups
    mesh = np.flatnonzero((obj >= 0) & (obj < n_meshes))
    out[mesh] = welded.group_of[obj[mesh]]
    return out


def _edges_of_blockers(
    scene, light, j, primary, hit_index, rows, n_tri, welded, spp
) -> ShadowPairs:
    """For one light j: each pair's occluder edge (seen from the light), kept where the
    shadow edge crosses the pair within the 45-degree rule. rows: (lit ray ids, dark ray
    ids, horizontal, blocker of the dark ray's shadow ray), (n,) each."""
    lit_id, dark_id, horizontal, blocker = rows
    # Where the light 'looks from': its position, or (at infinity) its direction of travel.
    kind, viewer = light.pack()
    directional = kind == DIRECTIONAL
    lit_points = primary.points[hit_index[lit_id]]
    dark_points = primary.points[hit_index[dark_id]]
    eye, d_lit, d_dark, to_pixels = geometry.plain_rays(scene.camera, lit_id, dark_id, spp)
    normal, anchor = _receiver_planes(scene, primary.prim_id[lit_id], lit_points)
    occluder = blocker.copy()
    edge = np.full(len(lit_id), -2, dtype=np.int64)
    image_normal = np.zeros((len(lit_id), 3))
    on_mesh = np.flatnonzero((blocker >= 0) & (blocker < n_tri))
    group_of, local = np.full(len(blocker), -1), np.full(len(blocker), -1)
    group_of[on_mesh], local[on_mesh] = welded.locate(blocker[on_mesh])
    for g, group in enumerate(welded.groups):
        rows = np.flatnonzero(group_of == g)
        if len(rows):
            vertices, faces = group.vertices, group.faces
            silhouette = silhouette_edges(group.edges, vertices, faces, viewer, directional)
            if directional:  # segment end points
                near, far = dark_points[rows], lit_points[rows]
            else:  # directions from the light
                near, far = dark_points[rows] - viewer, lit_points[rows] - viewer
            face, k, _, _ = walk_to_silhouette_fast(
                group.edges, silhouette, vertices, faces, local[rows], viewer, near, far,
                directional=directional,
            )  # fmt: skip
            found = k >= 0
            corners = vertices[faces[face]]
            r, kk = np.arange(len(rows)), np.maximum(k, 0)
            m, _ = light.edge_plane(corners[r, kk], corners[r, (kk + 1) % 3])
            image_normal[rows] = _image_normal(m, corners[r, kk], normal[rows], anchor[rows], eye)
            edge[rows] = np.where(found, k, -2)
            occluder[rows] = group.face_ids[face]
    s = np.full(len(lit_id), np.nan)
    triangle = edge >= 0
    e_lit = np.sum(d_lit * image_normal, axis=1)
    e_dark = np.sum(d_dark * image_normal, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        s[triangle] = (e_lit / (e_lit - e_dark))[triangle]
    for index, sphere in enumerate(scene.spheres):
        rows = np.flatnonzero(blocker == n_tri + index)
        if len(rows) == 0 or directional:
            continue
        u_dark = _homogeneous_points(d_dark[rows], normal[rows], anchor[rows], eye, viewer)
        u_lit = _homogeneous_points(d_lit[rows], normal[rows], anchor[rows], eye, viewer)
        s_dark = geometry.sphere_crossing_plain(sphere, viewer, u_dark, u_lit)
        g = geometry.outline_normal(sphere.center.data, sphere.radius.data, viewer, u_dark, u_lit,
                            np.nan_to_num(s_dark))  # fmt: skip
        image_normal[rows] = _chain_to_directions(g, normal[rows], anchor[rows], eye, viewer)
        s[rows] = 1.0 - s_dark
        edge[rows] = np.where(np.isfinite(s_dark), -1, -2)
    # The receiver's plane is an approximation: the crossing it gives may fall just outside
    # the pair although the shadow rays say the edge lies between the samples. Such pairs
    # are kept and their crossing clamped to [0, 1] on the tape (``shadow_crossings``):
    # dropping them would make the image jump when the crossing re-enters the pair.
    keep = (edge >= -1) & np.isfinite(s)
    keep &= geometry.axis_ok(image_normal, horizontal, to_pixels)
    return ShadowPairs(
        lit_id[keep], dark_id[keep], np.full(keep.sum(), j, np.int64), occluder[keep],
        edge[keep], horizontal[keep],
    )  # fmt: skip


def _chain_to_directions(g, normal, anchor, eye, origin):
    """The gradient with respect to d of a function of u(d) (``_homogeneous_points``) whose
    gradient with respect to u is g: n ((C - origin) . g) + (n . (a - C)) g."""
    return (
        as_column(dot_last(eye - origin, g)) * normal
        + as_column(dot_last(normal, anchor - eye)) * g
    )


# --------------------------------------------------------------------------------------
# On the tape
# --------------------------------------------------------------------------------------


def _receiver_planes_tape(scene: Scene, prim: np.ndarray, points: md.Tensor):
    """``_receiver_planes`` on the tape: (normal, anchor), (k, 3) each. ``points`` are the
    samples' hit points on the tape (used for spheres)."""
    n_tri = first_sphere_id(scene)
    normals, anchors, order = [], [], []
    on_tri = np.flatnonzero(prim < n_tri)
    if len(on_tri):
        corners = geometry.triangle_corners(scene, prim[on_tri])
        normals.append(geometry.plane_normal(corners))
        anchors.append(corners[0])
        order.append(on_tri)
    for index, sphere in enumerate(scene.spheres):
        on = np.flatnonzero(prim == n_tri + index)
        if len(on):
            p = points[on]
            normals.append(p - sphere.center)
            anchors.append(p)
            order.append(on)
    return in_order(normals, order), in_order(anchors, order)


def shadow_crossings(
    scene: Scene, pairs: ShadowPairs, prim_lit: np.ndarray, lit_points, frame, spp: int, dtype
):
    """On the tape, per pair: s* (n,), where the shadow edge crosses the segment from the
    lit sample (s = 0) to the dark one (s = 1), clamped to [0, 1] (see ``shadow_pairs``),
    and its slope across the pair (n,).
    prim_lit (n,): the lit samples' primitives; lit_points (n, 3): their hit points on the
    tape."""
    camera, eye = scene.camera, frame[3]
    d_lit = ray_directions(frame, image_plane_coords(camera, pairs.lit, spp).astype(dtype))
    d_dark = ray_directions(frame, image_plane_coords(camera, pairs.dark, spp).astype(dtype))
    normal, anchor = _receiver_planes_tape(scene, prim_lit, lit_points)
    s_parts, normals, order = [], [], []
    n_tri = first_sphere_id(scene)
    for j, light in enumerate(scene.lights):
        rows = np.flatnonzero((pairs.light == j) & (pairs.edge >= 0))
        if len(rows):
            corners = md.stack(geometry.triangle_corners(scene, pairs.occluder[rows]), axis=1)
            r, k = np.arange(len(rows)), pairs.edge[rows]
            v_i, v_j = corners[r, k], corners[r, (k + 1) % 3]
            m, _ = light.edge_plane(v_i, v_j)
            big_m = _image_normal(m, v_i, normal[rows], anchor[rows], eye)
            e_lit, e_dark = md.dot(d_lit[rows], big_m), md.dot(d_dark[rows], big_m)
            s_parts.append(e_lit / (e_lit - e_dark))
            normals.append(big_m)
            order.append(rows)
        for index, sphere in enumerate(scene.spheres):
            rows = np.flatnonzero(
                (pairs.light == j) & (pairs.edge == -1) & (pairs.occluder == n_tri + index)
            )
            if len(rows) == 0:
                continue
            position = light.position
            u_dark = _homogeneous_points(d_dark[rows], normal[rows], anchor[rows], eye, position)
            u_lit = _homogeneous_points(d_lit[rows], normal[rows], anchor[rows], eye, position)
            s_dark = geometry.sphere_crossing(sphere, position, u_dark, u_lit)
            g = geometry.outline_normal(
                sphere.center, sphere.radius, position, u_dark, u_lit, s_dark
            )
            s_parts.append(1.0 - s_dark)
            normals.append(_chain_to_directions(g, normal[rows], anchor[rows], eye, position))
            order.append(rows)
    s = in_order(s_parts, order)
    slope = geometry.slope_across(in_order(normals, order), frame, pairs.horizontal,
                         geometry.sample_steps(camera, spp, dtype))  # fmt: skip
    return md.clip(s, 0.0, 1.0), slope


def shadow_terms(scene: Scene, pairs: ShadowPairs, prim_id, shaded: dict[int, Hits], frame, spp):
    """What blending each shadow pair's light contribution across its edge adds to the
    samples (``shadow_updates``), or None without pairs. The unoccluded contribution of the
    pair's light is shaded again at both samples, from their object's ``Hits`` (``shaded``,
    per object index: ``render.shade.hits.CameraShading.hits``). prim_id (N,): each camera
    ray's primitive."""
    if len(pairs.lit) == 0:
        return None
    objects = [obj for obj, _, _ in primitive_ranges(scene)]
    # Each sample shaded on its own object: the two lie on one surface, but it may be two
    # meshes welded as one (``shadow_pairs``).
    owners = {"lit": object_index_of(scene, prim_id[pairs.lit]),
              "dark": object_index_of(scene, prim_id[pairs.dark])}  # fmt: skip
    light_at = {"lit": ([], []), "dark": ([], [])}  # per side: contributions, their rows
    lit_points = []
    for index, hits in shaded.items():
        obj, surface = objects[index], hits.surface
        row_of_ray = np.full(prim_id.size, -1, dtype=np.int64)
        row_of_ray[hits.rays] = np.arange(len(hits.rays))
        for j, light in enumerate(scene.lights):
            for side, rays in (("lit", pairs.lit), ("dark", pairs.dark)):
                rows = np.flatnonzero((owners[side] == index) & (pairs.light == j))
                if len(rows) == 0:
                    continue
                at = row_of_ray[rays[rows]]
                light_at[side][0].append(_unoccluded(surface, at, obj.material, light))
                light_at[side][1].append(rows)
                if side == "lit":
                    lit_points.append(surface.points[at])
    dtype = working_dtype(scene)
    lit_rows = light_at["lit"][1]
    s, slope = shadow_crossings(
        scene, pairs, prim_id[pairs.lit], in_order(lit_points, lit_rows), frame, spp, dtype
    )
    return shadow_updates(pairs, s, slope, in_order(*light_at["lit"]), in_order(*light_at["dark"]))


def _unoccluded(surface: Surface, rows: np.ndarray, material, light) -> md.Tensor:
    """One light's unoccluded contribution (k, 3) at some rows of a Surface."""
    uv = surface.uv[rows] if surface.uv is not None else None
    look = appearance(material, uv)
    return light_contribution(
        surface.points[rows], surface.normals[rows], surface.directions[rows], look, light
    )


def shadow_updates(pairs: ShadowPairs, s, slope, light_lit, light_dark):
    """What blending each pair's light contribution across its shadow edge adds to the
    samples' colours: (ray ids (2n,), additions (2n, 3)). The lit sample loses its
    unoccluded contribution light_lit (n, 3) times the area of its box in the shadow, the
    dark sample gains light_dark (n, 3) times the area of its box in the light."""
    shadowed, lighted = geometry.pair_coverages(s, slope)
    rays = np.concatenate([pairs.lit, pairs.dark])
    return rays, md.concatenate([-(shadowed * light_lit), lighted * light_dark])
