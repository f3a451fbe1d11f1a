"""Spheres' curves: their outlines, and the curves where triangles pass through them.

A sphere (centre c, radius r) seen from the eye has its outline on the zero set of the
discriminant of the camera ray, e = (oc . d)^2 - |d|^2 (|oc|^2 - r^2), oc = eye - c, positive
inside (``outline_function``). Where a triangle passes through a sphere the visible surface
switches from one to the other along the circle in which the triangle's plane cuts the
sphere (the part of it inside the triangle, ``sphere_cut_function``). Both are conics in the
image: they are followed as polylines of chords at most ``CHORD`` pixels long, each
quadrature point moved onto the conic by Newton steps on e, and f_+ and f_- are what two
rays ``EPSILON`` pixels either side see (``_traced_factors``), where the curve's point is
visible (an occlusion ray; for a cut, also not on the sphere's far half).
"""

from __future__ import annotations

import math

import numpy as np

import minidiff as md
from minidiff.either import as_column, dot_last
from render.edges.boundary.curves import NEAR, CurvePoints, Curves, OnCurves, View, directions_at
from render.edges.boundary.moving import camera_moves, meshes_move, spheres_move
from render.edges.boundary.occlusion import hidden_points
from render.edges.boundary.pixels import pixel_gradient
from render.edges.boundary.radiance import EPSILON
from render.edges.geometry import triangle_corners
from render.scene.camera import camera_directions, clip_to_near, project
from render.scene.scene import Scene
from render.trace.primitives import first_sphere_id

#: A sphere's outline is followed by chords at most this long, in pixels.
CHORD = 0.5


class SphereOutline:
    """The outline of sphere ``index`` as a curve kind (``render.edges.boundary.curves``).
    Labels: none (zeros)."""

    summed, taped = 1, 2

    def __init__(self, index: int) -> None:
        self.index = index

    def moves(self, scene: Scene) -> bool:
        """The camera or the sphere differentiated (``CurveKind.moves``)."""
        return camera_moves(scene) or spheres_move(scene, [self.index])

    def curves(self, view: View) -> Curves:
        """The outline as a closed polyline (``_outline_polyline``; none where it cannot be
        followed)."""
        camera = view.scene.camera
        poly = _outline_polyline(
            view.scene.spheres[self.index], view.frame, camera.width, camera.height, view.size
        )
        if poly is None:
            return Curves(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, np.int64))
        return Curves(poly[:-1], poly[1:], np.zeros(len(poly) - 1, np.int64))

    def points(self, view: View, on: OnCurves) -> CurvePoints:
        """The factors of the points, moved onto the outline (``_outline_factors``)."""
        factor, coords = _outline_factors(view, self.index, on)
        return CurvePoints.nonzero(on, factor, coords)

    def edge_function(self, scene: Scene, frame, points: CurvePoints):
        """The discriminant on the tape (``outline_function``)."""
        sphere = scene.spheres[self.index]
        oc = frame[3] - sphere.center
        kappa = outline_kappa(oc, sphere.radius)
        e = outline_function(oc, kappa, directions_at(scene, frame, points.coords))
        return e, np.arange(len(points.pixel))


class SphereCut:
    """The curves where triangles pass through spheres, as a curve kind
    (``render.edges.boundary.curves``). Labels: (sphere index, triangle's global id) (k, 2)."""

    summed, taped = 2, 3

    def moves(self, scene: Scene) -> bool:
        """The camera, a sphere or a mesh's vertices differentiated (``CurveKind.moves``)."""
        return camera_moves(scene) or spheres_move(scene) or meshes_move(scene)

    def curves(self, view: View) -> Curves:
        """The curves as chords (``sphere_cut_curves``)."""
        camera = view.scene.camera
        spheres = [
            (np.asarray(sp.center.data, np.float64), float(sp.radius.data))
            for sp in view.scene.spheres
        ]
        triangles, frame = view.occluders.primitives[0], view.frame
        start, end, sphere, triangle = sphere_cut_curves(
            spheres, triangles, frame, camera.width, camera.height, view.size
        )
        return Curves(start, end, np.stack([sphere, triangle], axis=1))

    def points(self, view: View, on: OnCurves) -> CurvePoints:
        """The factors of the points, moved onto the curves, sphere by sphere
        (``_sphere_cut_factors``)."""
        factor, coords = np.zeros((len(on.pixel), 3)), on.coords.copy()
        for index in np.unique(on.label[:, 0]):
            mine = np.flatnonzero(on.label[:, 0] == index)
            factor[mine], coords[mine] = _sphere_cut_factors(view, int(index), on, mine)
        return CurvePoints.nonzero(on, factor, coords)

    def edge_function(self, scene: Scene, frame, points: CurvePoints):
        """``sphere_cut_function`` on the tape, sphere by sphere."""
        parts, order = [], []
        for index in np.unique(points.label[:, 0]):
            rows = np.flatnonzero(points.label[:, 0] == index)
            sphere = scene.spheres[index]
            a, b, c = triangle_corners(scene, points.label[rows, 1])
            d = directions_at(scene, frame, points.coords[rows])
            normal = md.cross(b - a, c - a)
            parts.append(sphere_cut_function(a, normal, sphere.center, sphere.radius, frame[3], d))
            order.append(rows)
        return (md.concatenate(parts) if len(parts) > 1 else parts[0]), np.concatenate(order)


def outline_kappa(oc, radius):
    """|oc|^2 - r^2 of a sphere seen from the eye (oc = eye - centre (3,)): positive where
    the eye is outside it. Arrays, or tensors on the tape."""
    return dot_last(oc, oc) - radius * radius


def outline_function(oc, kappa, d):
    """The edge function e (k,) of a sphere's outline, the discriminant (oc . d)^2 - |d|^2
    kappa of camera rays with directions d (k, 3) (oc = eye - centre (3,), kappa =
    ``outline_kappa``): positive where the ray hits the sphere. Arrays, or tensors on the
    tape."""
    b = dot_last(d, oc)
    return b * b - dot_last(d, d) * kappa


def _outline_polyline(sphere, frame, width: int, height: int, size: float):
    """The sphere's outline as a closed polyline in pixel coordinates (n, 2): the circle of
    points where rays from the eye touch it, sampled so that chords are at most ``CHORD``
    pixels (None: the eye is inside the sphere, no part of it is in front, or it is too
    small, seen from the eye, for its outline to be found in double precision)."""
    eye = frame[3]
    centre = np.asarray(sphere.center.data, np.float64)
    r = float(sphere.radius.data)
    w = centre - eye
    dist2 = float(w @ w)
    if dist2 <= r * r:
        return None
    if r * r <= np.finfo(np.float64).eps * dist2:
        # The outline is where b^2 = |d|^2 (dist2 - r^2) (``_onto_outline``): with r^2
        # below dist2's rounding that discriminant is noise (and with r * r underflowing
        # the circle collapses to a point, Newton divides by zero). Such a sphere subtends
        # under 1.5e-8 radians: its outline's contribution (its length) is nil.
        return None
    touch = eye + w * (1.0 - r * r / dist2)  # centre of the circle of tangency
    rho = r * math.sqrt(1.0 - r * r / dist2)
    u1 = np.cross(w, [1.0, 0.0, 0.0] if abs(w[0]) < 0.9 * math.sqrt(dist2) else [0.0, 1.0, 0.0])
    u1 /= np.linalg.norm(u1)
    u2 = np.cross(w, u1) / math.sqrt(dist2)

    def circle(n):
        phi = np.linspace(0.0, 2.0 * math.pi, n + 1)
        pts = touch + rho * (np.cos(phi)[:, None] * u1 + np.sin(phi)[:, None] * u2)
        return project(pts, frame, width, height)

    px, depth = circle(64)
    if not np.all(depth > NEAR * size):
        return None  # part of the outline behind the eye: not supported (documented)
    perimeter = float(np.sum(np.linalg.norm(np.diff(px, axis=0), axis=1)))
    n = int(min(max(64, math.ceil(perimeter / CHORD)), 1 << 16))
    px, _ = circle(n)
    return px


def _onto_outline(coords, sphere, frame, steps: int = 3):
    """Image-plane points (k, 2) moved onto the sphere's outline (Newton steps on the
    discriminant along its gradient); and that gradient (k, 2) at the result."""
    # ``outline_function`` written out in matmul and einsum, and d summed forward first:
    # the shared form (np.sum's dot products, ``camera_directions``) rounds differently,
    # and the points' last bits, so every image's with a sphere, would move.
    forward, right, up, eye = frame
    oc = eye - np.asarray(sphere.center.data, np.float64)
    kappa = float(oc @ oc) - float(sphere.radius.data) ** 2
    for _ in range(steps + 1):
        d = forward + coords[:, :1] * right + coords[:, 1:] * up
        b = d @ oc
        disc = b * b - np.einsum("ij,ij->i", d, d) * kappa
        grad_d = 2.0 * b[:, None] * oc - 2.0 * kappa * d
        grad = np.stack([grad_d @ right, grad_d @ up], axis=1)
        if _ == steps:
            return coords, grad
        coords = coords - (disc / np.einsum("ij,ij->i", grad, grad))[:, None] * grad


# Where a triangle passes through a sphere the visible surface switches from one to the
# other along the circle in which the triangle's plane cuts the sphere (the part of it
# inside the triangle). Seen from the eye the circle is a conic; a ray with direction d
# meets the plane (normal n through a) at eye + (n . (a - eye) / n . d) d, and that point
# lies on the sphere (centre c, radius r) where
#     e = |(n . d) (eye - c) + (n . (a - eye)) d|^2 - r^2 (n . d)^2
# is zero (the condition times (n . d)^2: no division, smooth in every parameter).


def sphere_cut_function(a, n, centre, radius, eye, d):
    """The edge function e (k,) of the curves where triangles (a corner a (k, 3), normal n
    (k, 3)) cut a sphere (centre (3,), radius), at camera directions d (k, 3); arrays, or
    tensors on the tape."""
    nd = dot_last(n, d)
    g = as_column(nd) * (eye - centre) + as_column(dot_last(n, a - eye)) * d
    return dot_last(g, g) - radius * radius * nd * nd


def _onto_sphere_cut(coords, corners, centre, radius, frame, steps: int = 3):
    """Image-plane points (k, 2) moved onto the images of the curves where triangles
    ``corners`` (k, 3, 3) cut a sphere (Newton steps on ``sphere_cut_function`` along its
    gradient); and that gradient (k, 2) at the result."""
    # ``sphere_cut_function`` written out with einsum beside its gradient: its shared form
    # (np.sum's dot products) rounds differently and would move the points' last bits.
    forward, right, up, eye = frame
    a = corners[:, 0]
    n = np.cross(corners[:, 1] - a, corners[:, 2] - a)
    w = eye - centre
    k = np.einsum("ij,ij->i", n, a - eye)
    for step in range(steps + 1):
        d = camera_directions(coords, right, up, forward)
        nd = np.einsum("ij,ij->i", n, d)
        g = nd[:, None] * w + k[:, None] * d
        e = np.einsum("ij,ij->i", g, g) - radius * radius * nd * nd
        # d e / d d = 2 (n (w . g) + k g - r^2 (n . d) n)
        grad_d = 2.0 * ((g @ w - radius * radius * nd)[:, None] * n + k[:, None] * g)
        grad = np.stack([grad_d @ right, grad_d @ up], axis=1)
        if step == steps:
            return coords, grad
        length2 = np.einsum("ij,ij->i", grad, grad)
        coords = coords - (e / np.where(length2 > 0, length2, np.inf))[:, None] * grad


def sphere_cut_curves(spheres, triangles: np.ndarray, frame, width: int, height: int, size):
    """The curves where triangles pass through spheres, as 2-D chords in pixel coordinates:
    start (k, 2), end (k, 2), the sphere's index (k,) and the triangle's global id (k,).
    ``spheres``: (centre (3,), radius) per sphere; ``triangles`` (N, 3, 3). Each curve is
    the circle in which the triangle's plane cuts the sphere, followed by chords of at most
    ``CHORD`` pixels and clipped to the triangle and to the eye's near plane."""
    starts, ends, which, ids = [np.zeros((0, 2))], [np.zeros((0, 2))], [], []
    if len(triangles) == 0:
        return starts[0], ends[0], np.zeros(0, np.int64), np.zeros(0, np.int64)
    a = triangles[:, 0]
    normal = np.cross(triangles[:, 1] - a, triangles[:, 2] - a)
    area2 = np.linalg.norm(normal, axis=1)
    unit = normal / np.where(area2 > 0, area2, 1.0)[:, None]
    low, high = triangles.min(axis=1), triangles.max(axis=1)
    for index, (centre, radius) in enumerate(spheres):
        dist = np.einsum("ij,ij->i", unit, centre - a)
        near = (
            (area2 > 0)
            & (np.abs(dist) < radius)
            & np.all(low <= centre + radius, axis=1)
            & np.all(high >= centre - radius, axis=1)
        )
        for t in np.flatnonzero(near):
            rho2 = radius * radius - dist[t] * dist[t]
            if rho2 <= np.finfo(np.float64).eps * radius * radius:
                continue  # the plane touches the sphere: no curve of any length
            n = unit[t]
            u1 = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
            u1 /= np.linalg.norm(u1)
            u2 = np.cross(n, u1)
            middle, rho = centre - dist[t] * n, math.sqrt(rho2)

            def circle(m, middle=middle, rho=rho, u1=u1, u2=u2):
                phi = np.linspace(0.0, 2.0 * math.pi, m + 1)
                return middle + rho * (np.cos(phi)[:, None] * u1 + np.sin(phi)[:, None] * u2)

            rough = circle(64)
            px, depth = project(rough, frame, width, height)
            if np.all(depth > NEAR * size):
                perimeter = float(np.sum(np.linalg.norm(np.diff(px, axis=0), axis=1)))
                m = int(min(max(64, math.ceil(perimeter / CHORD)), 1 << 16))
            else:  # partly behind the eye: the chords are clipped below
                m = 1 << 10
            points = circle(m)
            p0, p1 = points[:-1], points[1:]
            t0, t1 = np.zeros(m), np.ones(m)
            corners = triangles[t]
            for i in range(3):  # clip each chord to the triangle's three half-planes
                v, w, third = corners[i], corners[(i + 1) % 3], corners[(i + 2) % 3]
                inward = np.cross(n, w - v)
                inward = inward if inward @ (third - v) >= 0 else -inward
                s0, s1 = (p0 - v) @ inward, (p1 - v) @ inward
                cut = np.where(s0 != s1, s0 / np.where(s0 != s1, s0 - s1, 1.0), 0.0)
                t0 = np.where(s0 < 0, np.where(s1 > s0, np.maximum(t0, cut), 2.0), t0)
                t1 = np.where(s1 < 0, np.where(s0 > s1, np.minimum(t1, cut), -1.0), t1)
            keep = np.flatnonzero(t0 < t1)
            if len(keep) == 0:
                continue
            delta = p1[keep] - p0[keep]
            q0, q1 = p0[keep] + t0[keep, None] * delta, p0[keep] + t1[keep, None] * delta
            q0, q1, front = clip_to_near(q0, q1, frame, NEAR * size)
            starts.append(project(q0[front], frame, width, height)[0])
            ends.append(project(q1[front], frame, width, height)[0])
            which.append(np.full(int(front.sum()), index))
            ids.append(np.full(int(front.sum()), t))
    return (
        np.concatenate(starts),
        np.concatenate(ends),
        np.concatenate(which or [np.zeros(0, np.int64)]).astype(np.int64),
        np.concatenate(ids or [np.zeros(0, np.int64)]).astype(np.int64),
    )


def _outline_factors(view: View, index: int, on: OnCurves) -> tuple[np.ndarray, np.ndarray]:
    """(g, 3) w (f_+ - f_-) / |grad e| for the quadrature points ``on`` the outline of
    sphere ``index``, and the points moved onto the outline (g, 2). The outline of a sphere
    is smooth: f_+ and f_- are what two rays just inside and just outside it see, where the
    point at which the ray touches the sphere is visible (``hidden_points``, the sphere
    itself ignored). The test matters where another curve runs within the rays' EPSILON of
    the outline: where a triangle passing through the sphere seems to emerge from it, the
    curve of the cut is tangent to the outline, and there the rays alone saw the same
    jump across both (counting it twice)."""
    scene, plain = view.scene, view.frame
    sphere = scene.spheres[index]
    coords, grad = _onto_outline(on.coords, sphere, plain)
    forward, right, up, eye = plain
    directions = camera_directions(coords, right, up, forward)
    dd = np.einsum("ij,ij->i", directions, directions)
    depth = (directions @ (np.asarray(sphere.center.data, np.float64) - eye)) / dd
    ignore = np.full(len(coords), first_sphere_id(scene) + index)
    hidden = np.zeros(len(coords), dtype=bool)
    factor = _traced_factors(
        view, coords, directions, depth, grad, on.weight, on.key, ignore, hidden
    )
    return factor, coords


def _sphere_cut_factors(
    view: View, index: int, on: OnCurves, rows: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(k, 3) w (f_+ - f_-) / |grad e| for the k quadrature points ``rows`` of ``on`` (on
    the curves where triangles cut sphere ``index``; labels (sphere, triangle)), and the
    points moved onto those curves (k, 2). A point is hidden where it lies on the sphere's
    far half (the sphere itself is in front) or something else is in front of it
    (``hidden_points``); where it is visible f_+ and f_- are what two rays either side see
    (the triangle on one, the sphere on the other)."""
    scene, plain = view.scene, view.frame
    forward, right, up, eye = plain
    sphere = scene.spheres[index]
    centre, radius = np.asarray(sphere.center.data, np.float64), float(sphere.radius.data)
    corners = view.occluders.primitives[0][on.label[rows, 1]]
    coords, grad = _onto_sphere_cut(on.coords[rows], corners, centre, radius, plain)
    directions = camera_directions(coords, right, up, forward)
    n = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    nd = np.einsum("ij,ij->i", n, directions)
    depth = np.einsum("ij,ij->i", n, corners[:, 0] - eye) / np.where(nd != 0, nd, np.inf)
    point = eye + depth[:, None] * directions
    far = np.einsum("ij,ij->i", point - centre, eye - point) <= 0
    ignore = np.full(len(coords), first_sphere_id(scene) + index)
    factor = _traced_factors(
        view, coords, directions, depth, grad, on.weight[rows], on.key[rows], ignore, far
    )
    return factor, coords


def _traced_factors(view: View, coords, directions, depth, grad, weight, keys, ignore, hidden):
    """(k, 3) w (f_+ - f_-) / |grad e| for k points ``coords`` (k, 2) on a curve whose edge
    function has image-plane gradient ``grad`` (k, 2) there, zero where the curve's point
    (along camera ``directions`` (k, 3) at ``depth`` (k,)) is ``hidden`` (k,) already or
    ``hidden_points`` (primitive ``ignore`` (k,) not counted), else f_+ and f_- traced by
    rays ``EPSILON`` pixels either side (``keys`` (k,): the points' names, ``weight``
    (k,): the rule's weights)."""
    camera = view.scene.camera
    norm, step = pixel_gradient(grad, camera.width, camera.height)
    hidden = hidden | hidden_points(
        view.occluders, view.frame, camera, coords, directions, depth, norm, ignore
    )
    seen = np.flatnonzero(~hidden)
    at, step, keys = coords[seen], step[seen], keys[seen]
    both = np.concatenate([at + EPSILON * step, at - EPSILON * step])
    f = view.radiance.along(both, np.concatenate([keys, keys]))
    jump = np.zeros((len(coords), 3))
    jump[seen] = f[: len(seen)] - f[len(seen) :]
    factor = np.where(norm > 0, weight / np.where(norm > 0, norm, 1.0), 0.0)
    return factor[:, None] * jump
