"""The shadow border as a curve of the boundary term: its edge function e, written once for
plain arrays and for the tape, and the term (``render(antialias="boundary")``).

A shadow boundary is a discontinuity of the image like an outline (``render.edges.boundary``
explains the boundary term; ``render.edges.boundary.shadow_tracing`` finds the borders as
image chords). A point light L casts past an occluder's silhouette *as seen from the light*
a shadow whose border, on the receiving surface, is where the light's ray to the receiver
point P grazes the occluder. With P(x) the point the camera ray through image position x
meets on the receiver, the border in the image is the zero set of

* an occluder edge (v_i, v_j): e = m . (P(x) - L), m = (v_i - L) x (v_j - L) (the plane
  through the light and the edge; for a directional light travelling along w, m = (v_j -
  v_i) x w and e = m . (P(x) - v_i): ``Light.edge_plane``) (``edge_border``);
* an occluder sphere (c, r): e = (oc . u)^2 - |u|^2 (|oc|^2 - r^2), the discriminant of the
  light's ray origin + t u reaching P (``Light.ray_to``), oc = origin - c: from a point
  light origin L and u = P(x) - L, from a directional one origin P(x) and u = w
  (``sphere_border``);

smooth in every parameter: the receiver's vertices or sphere (through P: ``plane_depth``,
``sphere_depth``), the camera (through the ray), the occluder and the light. These
functions are written once, with ``minidiff.either``'s functions: on the tape they give
e(x_g; theta) (``shadow_term``); off it, traced by ``minidiff.compile`` into one parallel
pass per light (``_onto_border``), they move each quadrature point from its chord onto the
border (Newton on e) and find its factors' geometry (|grad e| in pixels, the receiver's
depth just either side). The boundary term of a pixel is then, as for outlines, the sum
over quadrature points on the border's pieces inside it of w (f_+ - f_-) / |grad_x e|
de/dtheta: f_+ and f_- are the radiance on the receiver just either side (``radiance``'s
``seen``), zero where the camera does not see the border point (``hidden_points``) or it
lies in another shadow of the same light (f_+ = f_- there). ``ShadowBorder`` is the curve
kind that hands all this to the term (``render.edges.boundary.curves``).

The compiled pass replaced a hand-written Numba twin of the same formulas (244 lines, ~15
s of compiling on a fresh install); it gives that twin's points and factors bit for bit
on the paper teapot and its ground, and its own function on the tape
(``shadow_points(..., compiled=False)``) gives them bit for bit too
(``tests/render/edges/test_border_points.py``).
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass

import numpy as np

import minidiff as md
from minidiff.either import as_column, dot_last, square_root
from render.edges.boundary.curves import CurvePoints, Curves, OnCurves, View
from render.edges.boundary.moving import geometry_moves
from render.edges.boundary.occlusion import Occluders, hidden_points, seen_in
from render.edges.boundary.pixels import pixel_step
from render.edges.boundary.radiance import EPSILON, SideRadiance
from render.edges.boundary.shadow_tracing import BorderChords, border_chords
from render.edges.geometry import plane_normal, triangle_corners
from render.scene.camera import plain_camera, ray_directions
from render.scene.lights import Light
from render.scene.scene import Scene
from render.shade.hits import working_dtype
from render.shade.surface import in_order
from render.trace.outlines import Outlines
from render.trace.primitives import first_sphere_id
from render.trace.visibility import Visibility

#: Newton steps that move a quadrature point from its chord onto the curved border.
NEWTON_STEPS = 3


@dataclass
class ShadowPoints:
    """The quadrature points of one render's shadow-border term (constants, off the tape).

    coords (G, 2), pixel (G,), weight (G, 3): as in ``BoundaryPoints``.
    light (G,) int64: the light's index in ``scene.lights``.
    receiver (G,) int64: the primitive (global id) the border lies on.
    occluder (G, 3) int64: (mesh index, v_i, v_j) of an occluder edge, or (-1, sphere
        index, -1) of an occluder sphere.
    """

    coords: np.ndarray
    pixel: np.ndarray
    weight: np.ndarray
    light: np.ndarray
    receiver: np.ndarray
    occluder: np.ndarray


# ---------------------------------------------------------------------------------------
# The edge function: arrays or tensors
# ---------------------------------------------------------------------------------------


def plane_depth(normal, corner, eye, d, dot=dot_last):
    """t (k,): where rays eye + t d (d (k, 3)) meet the planes through ``corner`` (k, 3)
    with normals ``normal`` (k, 3) (inf or NaN where a ray runs along its plane)."""
    return dot(normal, corner - eye) / dot(normal, d)


def sphere_depth(centre, radius, eye, d, dot=dot_last):
    """t (k,): where rays eye + t d (d (k, 3)) enter spheres (``centre`` (3,) or (k, 3),
    ``radius`` scalar or (k,)); NaN where they miss."""
    oc = eye - centre
    dd, bb = dot(d, d), dot(d, oc)
    kappa = dot(oc, oc) - radius * radius
    return (-bb - square_root(bb * bb - dd * kappa)) / dd


def edge_border(m, base, p):
    """e (k,) of an occluder edge's border at receiver points p (k, 3): m . (p - base), with
    m (k, 3) the normal of the plane through the light and the edge and ``base`` (3,) or
    (k, 3) a point on it (the light's position, or the edge's first corner)."""
    return dot_last(m, p - base)


def sphere_border(oc, u, radius):
    """e (k,) of an occluder sphere's border at receiver points P (k, 3): the discriminant
    (oc . u)^2 - |u|^2 (|oc|^2 - r^2) of the light's rays origin + t u that reach them, oc =
    origin - centre (``sphere_ray``), positive where the ray meets the sphere."""
    r2 = radius * radius
    ou = dot_last(u, oc)
    return ou * ou - dot_last(u, u) * (dot_last(oc, oc) - r2)


def sphere_ray(light: Light, centre, p):
    """(oc (k, 3) or (3,), u (k, 3) or (3,)): the light's rays origin + t u reaching receiver
    points p (k, 3) (``Light.ray_to``), as seen from a sphere's centre: oc = origin - centre.
    Rays from a light at infinity start at the points; from a light at a point every ray
    starts at the light, and oc is recorded on the tape before u (the order in which the
    light position's gradient has always been summed: the same bits)."""
    if light.location() is None:
        origin, u = light.ray_to(p)
        return origin - centre, u
    oc = light.ray_to(centre)[0] - centre  # the ray's origin, the light, is the same for all
    return oc, light.ray_to(p)[1]


# ---------------------------------------------------------------------------------------
# Off the tape: the points moved onto the border, their constant factors
# ---------------------------------------------------------------------------------------


def _sphere_border_gradient(oc, u, radius, at_point: bool):
    """de/dP (k, 3) of ``sphere_border``: P moves the ray's direction u = P - origin from a
    light at a point (``at_point``), the ray's origin P from a light at infinity."""
    ou = dot_last(u, oc)
    if at_point:
        kappa = dot_last(oc, oc) - radius * radius
        return as_column(2.0 * ou) * oc - as_column(2.0 * kappa) * u
    return as_column(2.0 * ou) * u - as_column(2.0 * dot_last(u, u)) * oc


def _receiver_hits(receivers, d, eye):
    """Depth t (k,), point P (k, 3) and surface normal n (k, 3) where rays eye + t d (d (k,
    3)) meet the planes of triangle receivers, or the near side of sphere receivers
    (``receivers``: ``_receiver_rows``); t is NaN where they miss or run along the plane."""
    normal_or_centre, corner, radius = receivers
    triangle = radius < 0
    t = md.where(
        triangle,
        plane_depth(normal_or_centre, corner, eye, d),
        sphere_depth(normal_or_centre, radius, eye, d),
    )
    t = md.where(md.abs(t) < np.inf, t, np.nan)  # NaN where not finite
    points = eye + as_column(t) * d
    return t, points, md.where(as_column(triangle), normal_or_centre, points - normal_or_centre)


def _border_at(frame, receivers, occluders, light, x, y):
    """e (k,), its gradient with respect to image-plane (x, y) (gx, gy: (k,) each), and the
    receiver points P (k, 3) and their depths t (k,), at image-plane points (x, y)
    (``receivers``, ``occluders``, ``light``: ``_border_rows``; ``frame``: the plain
    camera). P(d) = C + t(d) d on a surface with normal n at P has dP/dd = t (I - d n^T /
    (n . d))."""
    forward, right, up, eye = frame
    kind, m, base, size = occluders
    at_point, w = light
    d = forward + as_column(x) * right + as_column(y) * up
    t, points, normal = _receiver_hits(receivers, d, eye)
    # A sphere's border: the light's ray reaching P (``Light.ray_to``), from the light at a
    # point w towards P, or along the direction w from P for a light at infinity.
    oc, u = (w - base, points - w) if at_point else (points - base, w)
    sphere = kind == 1
    e = md.where(sphere, sphere_border(oc, u, size), edge_border(m, base, points))
    g = md.where(as_column(sphere), _sphere_border_gradient(oc, u, size, at_point), m)
    gd = as_column(t) * (g - as_column(dot_last(g, d) / dot_last(normal, d)) * normal)
    return e, dot_last(gd, right), dot_last(gd, up), points, t


@md.compile(shared=("frame", "light", "pixel"))
def _onto_border(coords, receivers, occluders, frame, light, pixel, form):
    """k points ``coords`` (k, 2) moved onto their borders and the factors' geometry there,
    in one compiled pass (``minidiff.compile``): ``form`` = (the light is at a point,
    Newton steps); ``light`` = (w,): its position or direction of travel (``_border_rows``);
    ``pixel`` (2,): (2 / W, -2 / H), pixel units per image-plane unit.

    Returns x, y (k,) the moved points; e, gx, gy (k,) there (``_border_at``); P (k, 3); t
    (k,); |grad e| in pixels (k,) (``pixel_step``); the camera direction there (k, 3)
    (``camera_directions``' order); the points ``EPSILON`` pixels either side along grad e,
    x+, y+, x-, y- (k,); and the depths (k,) at which the camera rays there meet the
    receiver, + side then - side."""
    at_point, steps = form
    light = (at_point, light[0])
    forward, right, up, eye = frame
    x, y = coords[:, 0], coords[:, 1]
    for _ in range(steps):  # Newton on e along its image-plane gradient
        e, gx, gy, _, _ = _border_at(frame, receivers, occluders, light, x, y)
        norm2 = gx * gx + gy * gy
        shift = md.where(norm2 > 0, e / md.where(norm2 > 0, norm2, 1.0), 0.0)
        x, y = x - shift * gx, y - shift * gy
    e, gx, gy, points, t = _border_at(frame, receivers, occluders, light, x, y)
    norm, step = pixel_step(md.stack([gx, gy], axis=1), pixel)
    step_x, step_y = step[:, 0], step[:, 1]
    direction = as_column(x) * right + as_column(y) * up + forward
    sides = [x + EPSILON * step_x, y + EPSILON * step_y, x - EPSILON * step_x, y - EPSILON * step_y]
    # Both sides seen on the receiver itself (the border point is seen on it): rays traced
    # there would cross any curve of primary visibility within EPSILON of the border and
    # add its jump. Where a triangle passes through a sphere, the sphere's shadow border on
    # it is tangent to the curve of the cut, and along a stretch traced rays saw the
    # triangle on one side and the sphere on the other.
    depths = [
        _receiver_hits(receivers, as_column(sx) * right + as_column(sy) * up + forward, eye)[0]
        for sx, sy in (sides[:2], sides[2:])
    ]
    return (x, y, e, gx, gy, points, t, norm, direction, *sides, *depths)


def _border_points(frame, receivers, occluders, light, coords, steps: int, pixel=(1.0, 1.0)):
    """``_onto_border`` on plain arrays, as plain arrays (its outputs, in its order)."""
    at_point, w = light
    # (Only the reference route, on the tape, computes in NumPy and could warn: the rows'
    # other kind's formula divides by zero or takes a negative square root, unused.)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = _onto_border(
            np.asarray(coords, np.float64), receivers, occluders, tuple(frame),
            (np.asarray(w, np.float64),), np.asarray(pixel, np.float64), (at_point, steps),
        )  # fmt: skip
    return [md.as_tensor(o).data for o in out]


def border_gradient(frame, receivers, occluders, light, coords):
    """e (k,), its gradient with respect to image-plane (x, y) (k, 2), and the receiver
    points P (k, 3) and their depths t (k,), at image-plane points ``coords`` (k, 2)
    (``_border_at``, compiled)."""
    _, _, e, gx, gy, points, t = _border_points(frame, receivers, occluders, light, coords, 0)[:7]
    return e, np.stack([gx, gy], axis=1), points, t


def onto_border(frame, receivers, occluders, light, coords, steps: int = NEWTON_STEPS):
    """The image-plane points ``coords`` (k, 2) moved onto the border by ``steps`` Newton
    steps along grad e, and there ``border_gradient``'s e (k,), gradient (k, 2), points P
    (k, 3) and depths t (k,)."""
    out = _border_points(frame, receivers, occluders, light, coords, steps)
    x, y, e, gx, gy, points, t = out[:7]
    return np.stack([x, y], axis=1), e, np.stack([gx, gy], axis=1), points, t


def _receiver_rows(scene, visibility, receiver):
    """The receivers ``receiver`` (k,) (global primitive ids) as ``_receiver_hits`` takes
    them: plane normal or sphere centre (k, 3), a point on the plane (k, 3), radius (k,)
    (-1 for a triangle)."""
    triangles, centres, radii = visibility.primitives
    n_tri = first_sphere_id(scene)
    k = len(receiver)
    normal, corner, radius = np.zeros((k, 3)), np.zeros((k, 3)), np.full(k, -1.0)
    tri = np.flatnonzero(receiver < n_tri)
    corners = np.take(triangles, receiver[tri], axis=0)
    normal[tri], corner[tri] = plane_normal(corners), corners[:, 0]
    sph = np.flatnonzero(receiver >= n_tri)
    normal[sph], radius[sph] = centres[receiver[sph] - n_tri], radii[receiver[sph] - n_tri]
    return normal, corner, radius


def _border_rows(scene, visibility, light, occluder, receiver):
    """Per point, what ``onto_border`` needs of its receiver and occluder (gathered once):
    receiver (plane normal or sphere centre (k, 3), a point on the plane (k, 3), radius
    (k,): -1 for a triangle) and occluder (kind (k,): 0 an edge, 1 a sphere; m (k, 3) and
    base (k, 3) of an edge's e = m . (P - base); a sphere's centre (k, 3) and radius
    (k,)), and the light's rays (whether it is at a point; its position, or its direction
    of travel: ``Light.ray_to``'s)."""
    k = len(receiver)
    normal, corner, radius = _receiver_rows(scene, visibility, receiver)
    kind, m, base, size = np.zeros(k, np.int64), np.zeros((k, 3)), np.zeros((k, 3)), np.zeros(k)
    rows = np.flatnonzero(occluder[:, 0] >= 0)
    if len(rows):  # edges: their ends among every mesh's vertices (``Outlines.ends``)
        vertices = np.concatenate([np.asarray(mesh.vertices.data, np.float64)
                                   for mesh in scene.meshes])  # fmt: skip
        vi, vj = vertices[occluder[rows, 1]], vertices[occluder[rows, 2]]
        m[rows], base[rows] = light.edge_plane(vi, vj)
    for index, sphere in enumerate(scene.spheres):
        rows = np.flatnonzero((occluder[:, 0] < 0) & (occluder[:, 1] == index))
        kind[rows], base[rows] = 1, np.asarray(sphere.center.data, np.float64)
        size[rows] = float(sphere.radius.data)
    at = light.location()
    w = at if at is not None else np.asarray(light.ray_to(np.zeros((1, 3)))[1], np.float64)
    return (normal, corner, radius), (kind, m, base, size), (at is not None, w.reshape(3))


def shadow_points(
    scene: Scene,
    visibility: Visibility,
    frame,
    chords: BorderChords,
    pieces,
    radiance: SideRadiance,
    compiled: bool = True,
) -> ShadowPoints:
    """The quadrature points of the shadow borders with their constant factors
    (``BoundaryPoints``): ``pieces`` = (chord (m,), image-plane coords (m, 2), weight (m,),
    pixel (m,)) of the points on ``chords`` (cut with the other curves at pixel borders
    and crossings); ``radiance``: what the camera sees either side. The points are moved
    onto their borders, light by light, by one compiled pass each (``_onto_border``), or
    with ``compiled`` False by the same function on the tape, primitive by primitive
    (``minidiff.tape_only``: the reference); the radiance on either side is asked for all
    of them at once."""
    plain = plain_camera(frame)
    chord, coords, weight, pixel = pieces
    light, occluder = chords.light[chord], np.take(chords.occluder, chord, axis=0)
    receiver = chords.receiver[chord]
    k = len(light)
    moved, side, side_depth = coords.copy(), np.full((k, 2, 2), np.nan), np.full((k, 2), np.nan)
    t, norm, direction = np.full(k, np.nan), np.zeros(k), np.zeros((k, 3))
    camera = scene.camera
    scale = (2.0 / camera.width, -2.0 / camera.height)
    with contextlib.nullcontext() if compiled else md.tape_only():
        for j, source in enumerate(scene.lights):
            rows = np.flatnonzero(light == j)
            if len(rows) == 0:
                continue
            parts = _border_rows(
                scene, visibility, source, np.take(occluder, rows, axis=0), receiver[rows]
            )
            out = _border_points(plain, *parts, coords[rows], NEWTON_STEPS, scale)
            x, y, _, _, _, _, t[rows], norm[rows], direction[rows] = out[:9]
            moved[rows] = np.stack([x, y], axis=1)
            side[rows] = np.stack(out[9:13], axis=1).reshape(-1, 2, 2)
            side_depth[rows] = np.stack(out[13:], axis=1)
            cracked = np.flatnonzero(chords.crack[chord[rows]] > 0)
            if len(cracked):
                at = rows[cracked]
                side[at], side_depth[at] = _past_the_crack(
                    scene, plain, source, [x[cracked] for x in parts[0]], parts[2],
                    occluder[at], out, cracked, chords.crack[chord[at]],
                )  # fmt: skip
    # What hides a point is most often what the camera sees in its pixel: tried first.
    rows = np.flatnonzero(np.isfinite(t) & (t > 0) & (norm > 0))
    hidden = hidden_points(
        visibility, plain, camera, np.take(moved, rows, axis=0),
        np.take(direction, rows, axis=0), t[rows], norm[rows], receiver[rows],
        seen_in(Occluders.of(visibility), pixel[rows], scene),
    )  # fmt: skip
    rows = rows[~hidden]
    sides = np.take(side, rows, axis=0)
    both = np.concatenate([sides[:, 0], sides[:, 1]])
    depth = np.take(side_depth, rows, axis=0).T.reshape(-1)
    factor = _jumps(radiance, rows, both, receiver, depth, weight, norm, k)
    keep = np.flatnonzero(np.any(factor != 0.0, axis=1))
    return ShadowPoints(np.take(moved, keep, axis=0), pixel[keep], np.take(factor, keep, axis=0),
                        light[keep], receiver[keep], np.take(occluder, keep, axis=0))  # fmt: skip


#: Where the occluder edge's faces came apart (``Outlines.crack``), a border's side samples
#: pass the edge this many times the crack's width away, at most ``MOST_SIDE`` pixels from
#: the border (each side of a crack wider than that is a border of its own, in the image).
PAST_CRACK = 4.0
MOST_SIDE = 0.25


def _past_the_crack(scene, frame, source, receivers, light, occluder, out, rows, crack):
    """The side samples (n, 2, 2) and their depths (n, 2) of the border points ``rows``
    (n,) of ``out`` (``_border_points``' outputs; ``receivers``, ``light``: their rows of
    ``_border_rows``; ``occluder`` (n, 3) their edges, the shadow cast by ``source``),
    moved from ``EPSILON`` pixels to as far as the light's rays through them pass
    ``PAST_CRACK`` times the edge's ``crack`` (n,) from it. The rays through the samples
    ``EPSILON`` pixels either side pass the edge by a fraction of that width: across such
    a crack, the lit side's ray met the other mesh's face, and the jump was lost (a box in
    meshes whose seams were moved 1e-4 apart had its light's gradient 30 % off)."""
    forward, right, up, eye = frame
    x, y, points, norm = out[0][rows], out[1][rows], out[5][rows], out[7][rows]
    at_point, w = light
    vertices = np.concatenate([np.asarray(m.vertices.data, np.float64) for m in scene.meshes])
    a, b = vertices[occluder[:, 1]], vertices[occluder[:, 2]]
    light_plane = source.edge_plane(a, b)[0]
    ratio = np.ones(len(rows))
    if at_point:  # where the ray from the light to P passes the edge's line, along it
        u, v, w0 = points - w, b - a, w - a
        uu, uv, vv = np.sum(u * u, 1), np.sum(u * v, 1), np.sum(v * v, 1)
        ud, vd = np.sum(u * w0, 1), np.sum(v * w0, 1)
        ratio = np.clip((uv * vd - vv * ud) / np.maximum(uu * vv - uv * uv, 1e-300), 1e-3, 1.0)
    # e = m . (P - base): a pixel moves the sample norm / |m| off the plane through light
    # and edge on the receiver, and ``ratio`` of that where its ray passes the edge.
    per_pixel = norm / np.maximum(np.linalg.norm(light_plane, axis=1), 1e-300) * ratio
    reach = PAST_CRACK * crack / np.maximum(per_pixel, 1e-300)
    far = np.clip(reach, EPSILON, MOST_SIDE)
    step = np.stack([out[9][rows] - x, out[10][rows] - y], axis=1) / EPSILON
    sides = np.stack([np.stack([x, y], 1) + far[:, None] * step,
                      np.stack([x, y], 1) - far[:, None] * step], axis=1)  # fmt: skip
    normal, corner, radius = receivers
    depths = []
    for k in range(2):
        d = forward + sides[:, k, :1] * right + sides[:, k, 1:] * up
        depths.append(np.where(radius < 0, plane_depth(normal, corner, eye, d), np.nan))
    return sides, np.stack(depths, axis=1)


def _jumps(radiance, rows, both, receiver, depth, weight, norm, k) -> np.ndarray:
    """(k, 3): w (f_+ - f_-) / |grad e| at the points ``rows`` (n,) of k, zero elsewhere:
    f_+ and f_- are the radiance at image-plane points ``both`` (2n, 2) (the + sides of
    ``rows``, then their - sides), each seen on its point's ``receiver`` (k,) at ``depth``
    (2n,) (NaN or <= 0: beside a sphere receiver's outline, then traced); ``weight`` (k,),
    ``norm`` (k,): the points' weights and |grad e| in pixels."""
    keys = np.concatenate([rows, rows])
    on = np.concatenate([receiver[rows], receiver[rows]])
    found = np.isfinite(depth) & (depth > 0)
    f = np.empty((len(both), 3))
    inside, outside = np.flatnonzero(found), np.flatnonzero(~found)
    f[inside] = radiance.seen(
        np.take(both, inside, axis=0), on[inside], depth[inside], keys[inside]
    )
    if len(outside):  # a side ray beside a sphere receiver's outline: what is seen there
        f[outside] = radiance.along(np.take(both, outside, axis=0), keys[outside])
    out = np.zeros((k, 3))
    out[rows] = (weight[rows] / norm[rows])[:, None] * (f[: len(rows)] - f[len(rows) :])
    return out


# ---------------------------------------------------------------------------------------
# On the tape
# ---------------------------------------------------------------------------------------


def _receiver_points_tape(scene: Scene, d: md.Tensor, eye, receiver: np.ndarray) -> md.Tensor:
    """P (k, 3) on the tape: where rays eye + t d meet their receivers (the triangle's
    plane, or a sphere's near side)."""
    n_tri = first_sphere_id(scene)
    parts, order = [], []
    tri = np.flatnonzero(receiver < n_tri)
    if len(tri):
        a, b, c = triangle_corners(scene, receiver[tri])
        n = md.cross(b - a, c - a)
        dt = d[tri]
        parts.append(eye + as_column(plane_depth(n, a, eye, dt)) * dt)
        order.append(tri)
    for index, sphere in enumerate(scene.spheres):
        rows = np.flatnonzero(receiver == n_tri + index)
        if len(rows) == 0:
            continue
        dt = d[rows]
        parts.append(eye + as_column(sphere_depth(sphere.center, sphere.radius, eye, dt)) * dt)
        order.append(rows)
    return in_order(parts, order)


def shadow_term(scene: Scene, points: ShadowPoints, frame) -> tuple[md.Tensor, np.ndarray] | None:
    """e(x_g; theta) (G',) on the tape for the points that have one, and those rows (G',):
    the caller adds weight * (e - detach(e)) to the image (None: no points)."""
    if len(points.pixel) == 0:
        return None
    eye = frame[3]
    d = ray_directions(frame, points.coords.astype(working_dtype(scene)))
    parts, order = [], []
    for j, light in enumerate(scene.lights):
        mine = points.light == j
        if not mine.any():
            continue
        rows = np.flatnonzero(mine & (points.occluder[:, 0] >= 0))
        if len(rows):  # edges: their ends among every mesh's vertices (``Outlines.ends``)
            meshes = scene.meshes
            vertices = (md.concatenate([mesh.vertices for mesh in meshes])
                        if len(meshes) > 1 else meshes[0].vertices)  # fmt: skip
            p = _receiver_points_tape(scene, d[rows], eye, points.receiver[rows])
            vi = vertices[points.occluder[rows, 1]]
            vj = vertices[points.occluder[rows, 2]]
            parts.append(edge_border(*light.edge_plane(vi, vj), p))
            order.append(rows)
        for index, sphere in enumerate(scene.spheres):
            on = (points.occluder[:, 0] < 0) & (points.occluder[:, 1] == index)
            rows = np.flatnonzero(mine & on)
            if len(rows) == 0:
                continue
            p = _receiver_points_tape(scene, d[rows], eye, points.receiver[rows])
            parts.append(sphere_border(*sphere_ray(light, sphere.center, p), sphere.radius))
            order.append(rows)
    if not parts:
        return None
    return (md.concatenate(parts) if len(parts) > 1 else parts[0]), np.concatenate(order)


class ShadowBorder:
    """The shadow borders of the scene's lights as a curve kind of the boundary term
    (``render.edges.boundary.curves.CurveKind``): its curves are the chords
    ``border_chords`` finds, its points those ``shadow_points`` moves onto the borders and
    weighs, its edge function ``shadow_term``. It keeps the chords and the points of the
    render it is asked about, for that render's later steps. Labels: chord ids.

    ``visibility``, ``frame``: the render's; ``outlines``: the scene's curves that can be
    outlines (``render.trace.outlines.Outlines``)."""

    summed, taped = 4, 0

    def __init__(self, visibility: Visibility, frame, outlines: Outlines) -> None:
        self.visibility, self.frame, self.outlines = visibility, frame, outlines

    def moves(self, scene: Scene) -> bool:
        """Anything that places a curve differentiated: where a light is, the occluders,
        the receivers, the camera (``geometry_moves``; ``CurveKind.moves``)."""
        return geometry_moves(scene)

    def curves(self, view: View) -> Curves:
        """The chords of every light's shadow borders."""
        self.chords = border_chords(view.scene, self.visibility, self.frame, self.outlines)
        return Curves(self.chords.start, self.chords.end, np.arange(len(self.chords.start)))

    def points(self, view: View, on: OnCurves) -> CurvePoints:
        """The points moved onto the borders, with their factors."""
        pieces = (on.label, on.coords, on.weight, on.pixel)
        self.borders = shadow_points(
            view.scene, self.visibility, self.frame, self.chords, pieces, view.radiance
        )
        found = self.borders
        return CurvePoints(found.coords, found.pixel, found.weight, np.arange(len(found.pixel)))

    def edge_function(self, scene: Scene, frame, points: CurvePoints):
        """The borders' edge function on the tape, light by light and occluder by occluder."""
        return shadow_term(scene, self.borders, frame)
