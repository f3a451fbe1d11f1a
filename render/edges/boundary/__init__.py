"""Edge gradients by the boundary integral: the exact derivative of box-filtered pixels.

A pixel's value is the mean of the radiance f over its box, I = integral_pixel f(x) dx (a
pixel has area 1 in pixel units). Where f jumps along a curve that moves with a parameter
theta (an object's outline, a crease of a flat-shaded mesh), the derivative has two parts
(Reynolds transport):

    dI/dtheta = integral_pixel df/dtheta dx  +  integral_(curves in pixel) (f_- - f_+) v_n ds

The first, the *interior* term, is what the tape already gives (shading differentiated at
fixed visibility, one sample standing for its share of the pixel). The second, the
*boundary* term, is computed here: v_n is the curve's velocity along its unit normal n,
f_+ the radiance just on the side n points to, f_- just on the other.

Every discontinuity curve of primary visibility lies on the image of a mesh edge (a
silhouette, an open boundary, a crease or a seam across which the shading jumps) or of a
sphere's outline. Each is written as the zero set of a function e(x; theta) of the image
position that is smooth in theta:

* a mesh edge (v_i, v_j) seen from the eye C: e = d(x) . ((v_i - C) x (v_j - C)), zero on
  the plane through the eye and the edge, linear in the camera direction d(x);
* a sphere (centre c, radius r): e = (oc . d)^2 - |d|^2 (|oc|^2 - r^2), oc = C - c, the
  discriminant of the ray, zero on the outline, positive inside it.

On the zero set, v_n = -(de/dtheta) / |grad_x e|, with n = grad_x e / |grad_x e|. So the
boundary term of a pixel is a sum over quadrature points x_g on the curve's piece inside it:

    sum_g w_g (f_+ - f_-)(x_g) / |grad_x e(x_g)| * de(x_g; theta)/dtheta

and the renderer adds to the image the term ``c_g * (e(x_g; theta) - detach(e(x_g;
theta)))`` (c_g the constant factor): its value is exactly zero, its derivative is the
boundary term, and the tape takes it to every parameter e depends on (vertices, sphere
centres and radii, the camera's position, look-at, up and field of view) in one backward.

Which parts of an edge are visible, and what lies on either side, is not decided here by
geometry: f_+ and f_- are the radiance seen by two camera rays through x_g +- epsilon n,
shaded as any camera ray (``radiance_at``). Where the edge is hidden behind another surface
both rays see that surface and f_+ - f_- vanishes; where a flat-shaded mesh folds, the two
faces' colours differ; where the shading is smooth across an edge the difference is zero.
Every edge of every mesh is therefore a candidate; only the points of edges seen from
behind their own closed surface cost rays they did not need.

The curves are cut at pixel borders (``pixel_pieces``): within a pixel a mesh edge's image
is a straight segment and f_+ - f_- varies smoothly along it, so a fixed Gauss-Legendre rule
integrates it (``GAUSS_POINTS`` per piece). A sphere's outline is a conic: it is followed as
a polyline of short chords, and each quadrature point is moved onto the conic.

The lines where two surfaces pass through each other (the teapot's spout entering its
body) are curves too: the segment two crossing triangles share, with the edge function of
the line where their planes meet (``crossing_segments``); and where a triangle passes
through a sphere, the arc of the circle its plane cuts from the sphere that lies inside
the triangle (``sphere_cut_curves``, followed by chords as an outline is). The points of
outlines and of these arcs are tested for visibility as mesh edges' are (an occlusion ray
to the point where the curve lies; for an arc, also the sphere's far half), before the
rays either side are compared: where a triangle seems to emerge from a sphere the arc is
tangent to the outline, and within EPSILON of each other the rays alone cannot tell which
of the two is seen. Shadow borders (secondary visibility) are found in
``render.edges.shadow_boundary`` and added by the same term. Edges seen in mirrors are not
included.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numba
import numpy as np

import minidiff as md
from render.edges.boundary.occlusion import hidden_points, seen_in
from render.edges.boundary.pixels import (  # noqa: F401 (re-exported)
    GAUSS_POINTS,
    pixel_gradient,
    pixel_order,
    pixel_pieces,
    quadrature,
    split_at_crossings,
)
from render.edges.boundary.radiance import (  # noqa: F401 (re-exported)
    EPSILON,
    DirectRadiance,
    SideRadiance,
    radiance_at,
    seen_through,
    shade_seen,
)
from render.edges.geometry import as_column, dot_last, plane_normal, triangle_corners
from render.scene.camera import (
    camera_directions,
    clip_to_near,
    plain_frame,
    project,
    ray_directions,
    to_image_plane,
)
from render.scene.scene import Scene
from render.shade.hits import working_dtype
from render.trace.intersect import BLOCK, _jobs
from render.trace.primitives import first_sphere_id
from render.trace.topology import EdgeTable
from render.trace.visibility import Visibility

#: A sphere's outline is followed by chords at most this long, in pixels.
CHORD = 0.5
#: Points closer to the eye's plane than this fraction of the scene's size are clipped.
NEAR = 1e-7


@dataclass
class BoundaryPoints:
    """The quadrature points of one render's boundary term (constants, off the tape).

    coords (G, 2) float64: image-plane (x, y) of each point, on its curve.
    pixel (G,) int64: the pixel (row * W + column) whose piece of the curve it lies on.
    weight (G, 3): w_g (f_+ - f_-) / |grad_x e|, the factor of de/dtheta in the boundary term.
    mesh_edges: (mesh index, G_k rows, vertex ids i (G_k,), j (G_k,)) per mesh with points.
    sphere_points: (sphere index, G_k rows) per sphere with points.
    crossings: (rows, first (G_k,), second (G_k,)) the pairs of triangles (global ids)
        whose intersection the points lie on.
    sphere_cuts: (sphere index, G_k rows, triangle ids (G_k,)) per sphere with points on
        the curves where triangles pass through it (``sphere_cut_curves``).
    """

    coords: np.ndarray
    pixel: np.ndarray
    weight: np.ndarray
    mesh_edges: list
    sphere_points: list
    crossings: tuple
    sphere_cuts: list = field(default_factory=list)


# ---------------------------------------------------------------------------------------
# Off the tape: curves, pieces, quadrature points
# ---------------------------------------------------------------------------------------


# ---------------------------------------------------------------------------------------
# Candidates: mesh edges across which the image can jump, every sphere's outline
# ---------------------------------------------------------------------------------------


def continuous_creases(mesh, table: EdgeTable, eye: np.ndarray) -> np.ndarray:
    """(E,) bool: the edges of a smooth-shaded mesh across which the image cannot jump, so
    that they need no quadrature points: manifold edges whose two faces share the edge's
    vertex ids, wind consistently (one i -> j, the other j -> i) and lie on either side of
    the plane through the eye and the edge (not a silhouette from this eye). Normals and
    UVs are per vertex id, so both faces interpolate the same values along the edge and
    their shading agrees there exactly; both face the eye alike, so neither is flipped
    alone. (Their f_+ - f_- was zero up to rounding: dropping them changes the term by
    rounding only, and saves the rays and shading of most points of a smooth mesh.)"""
    if not mesh.smooth or table.faces.shape[1] < 2:
        return np.zeros(len(table.i), dtype=bool)
    two = (table.faces[:, 1] >= 0) & np.all(table.faces[:, 2:] < 0, axis=1)
    second = mesh.faces[np.maximum(table.faces[:, 1], 0)]  # (E, 3) vertex ids
    following = np.roll(second, -1, axis=1)  # each corner's next corner
    reversed_edge = np.any((second == table.j[:, None]) & (following == table.i[:, None]), axis=1)
    vertices = np.asarray(mesh.vertices.data, np.float64)
    a, b = vertices[table.i], vertices[table.j]
    m = np.cross(a - eye, b - eye)
    thirds = vertices[np.maximum(table.thirds[:, :2], 0)]  # (E, 2, 3)
    side = np.einsum("ekj,ej->ek", thirds - eye, m)
    return two & reversed_edge & (side[:, 0] * side[:, 1] < 0)


def _edge_curves(scene: Scene, frame, tables: list[EdgeTable], size: float, shared=None):
    """2-D segments (pixel coordinates) of every candidate edge in front of the eye, and
    per mesh the rows of its table that were kept (``continuous_creases`` are left out, and
    the rows another mesh counts: ``shared``, ``render.trace.seams.shared_edges``)."""
    camera = scene.camera
    starts, ends, kept = [], [], []
    for k, (mesh, table) in enumerate(zip(scene.meshes, tables, strict=True)):
        vertices = np.asarray(mesh.vertices.data, np.float64)
        a, b, keep = clip_to_near(vertices[table.i], vertices[table.j], frame, NEAR * size)
        if shared is None:
            keep = keep & ~continuous_creases(mesh, table, frame[3])
        else:  # a row that other meshes' faces join is no continuous crease of this one
            alone = ~np.any(shared[k].faces >= 0, axis=1)
            keep = keep & shared[k].owned & ~(continuous_creases(mesh, table, frame[3]) & alone)
        starts.append(project(a[keep], frame, camera.width, camera.height)[0])
        ends.append(project(b[keep], frame, camera.width, camera.height)[0])
        kept.append(np.flatnonzero(keep))
    return starts, ends, kept


def _edge_points(eye, directions, a, b):
    """Depth t (k,) along rays eye + t d (d with unit view-axis component) of the points
    where they pass closest to the lines through a and b (k, 3): the edge point each
    quadrature point stands for."""
    u = b - a
    w0 = eye - a
    dd = np.einsum("ij,ij->i", directions, directions)
    du = np.einsum("ij,ij->i", directions, u)
    uu = np.einsum("ij,ij->i", u, u)
    dw = np.einsum("ij,ij->i", directions, w0)
    uw = np.einsum("ij,ij->i", u, w0)
    det = dd * uu - du * du
    return (du * uw - uu * dw) / np.where(det > 0, det, 1.0)


# Intersection curves: where two triangles pass through each other (the teapot's lid sits
# in its rim, its spout and handle enter its body), the visible surface switches from one
# to the other along the segment the two share.


@numba.njit(cache=True, error_model="numpy")
def _dot(x, y):
    """x . y of two 3-vectors, summed left to right."""
    return x[0] * y[0] + x[1] * y[1] + x[2] * y[2]


@numba.njit(cache=True, error_model="numpy")
def _cross(x, y, out):
    """out = x cross y, three 3-vectors."""
    out[0] = x[1] * y[2] - x[2] * y[1]
    out[1] = x[2] * y[0] - x[0] * y[2]
    out[2] = x[0] * y[1] - x[1] * y[0]


@numba.njit(cache=True)
def _segment_of(t1, t2):
    """The segment (2, 3) where triangles t1 and t2 (3, 3) cross, and whether they do
    (coplanar or touching triangles do not count). Scalar loops and no temporaries: the
    same arithmetic as array expressions, compiled in a fraction of their time."""
    out = np.zeros((2, 3))
    n1, n2, e1, e2 = np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    d1, d2 = np.empty(3), np.empty(3)
    for c in range(3):
        e1[c], e2[c] = t1[1, c] - t1[0, c], t1[2, c] - t1[0, c]
    _cross(e1, e2, n1)
    for c in range(3):
        e1[c], e2[c] = t2[1, c] - t2[0, c], t2[2, c] - t2[0, c]
    _cross(e1, e2, n2)
    for k in range(3):  # each triangle's corners against the other's plane
        for c in range(3):
            e1[c], e2[c] = t2[k, c] - t1[0, c], t1[k, c] - t2[0, c]
        d2[k], d1[k] = _dot(n1, e1), _dot(n2, e2)
    if _one_side(d1) or _one_side(d2):
        return out, False
    u = np.empty(3)
    _cross(n1, n2, u)
    ends = np.zeros((2, 2))  # each triangle's interval along u
    points = np.zeros((2, 2, 3))
    for which in range(2):
        d = d1 if which == 0 else d2
        tri = t1 if which == 0 else t2
        m = 0
        for k in range(3):
            a, b = k, (k + 1) % 3
            if (d[a] > 0) != (d[b] > 0) and m < 2:
                f = d[a] / (d[a] - d[b])
                for c in range(3):
                    points[which, m, c] = tri[a, c] + (tri[b, c] - tri[a, c]) * f
                ends[which, m] = _dot(points[which, m], u)
                m += 1
        if m < 2:
            return out, False
        if ends[which, 0] > ends[which, 1]:
            ends[which, 0], ends[which, 1] = ends[which, 1], ends[which, 0]
            for c in range(3):
                points[which, 0, c], points[which, 1, c] = points[which, 1, c], points[which, 0, c]
    lo = 0 if ends[0, 0] >= ends[1, 0] else 1
    hi = 0 if ends[0, 1] <= ends[1, 1] else 1
    if ends[lo, 0] >= ends[hi, 1]:
        return out, False
    for c in range(3):
        out[0, c], out[1, c] = points[lo, 0, c], points[hi, 1, c]
    return out, True


@numba.njit(cache=True)
def _one_side(d):
    """Whether the three signed distances d (3,) leave a plane's one side uncrossed."""
    low, high = min(d[0], d[1], d[2]), max(d[0], d[1], d[2])
    return low >= 0 or high <= 0


@numba.njit(cache=True)
def _crossing_pairs(triangles, welded, order, low, high):
    """Every pair of triangles that cross, by a sweep along x over their bounding boxes
    (``order`` sorts them by low x); pairs sharing a (welded) corner are neighbours, not
    crossings. Returns the pairs (m, 2) and their segments (m, 2, 3)."""
    capacity, found = 64, 0
    pairs, segments = np.empty((capacity, 2), np.int64), np.empty((capacity, 2, 3))
    n = len(order)
    for a in range(n):
        i = order[a]
        for b in range(a + 1, n):
            j = order[b]
            if low[j, 0] > high[i, 0]:
                break
            if (
                low[j, 1] > high[i, 1]
                or low[i, 1] > high[j, 1]
                or low[j, 2] > high[i, 2]
                or low[i, 2] > high[j, 2]
            ):
                continue
            shared = False
            for p in range(3):
                for q in range(3):
                    if welded[i, p] == welded[j, q]:
                        shared = True
            if shared:
                continue
            seg, ok = _segment_of(triangles[i], triangles[j])
            if not ok:
                continue
            if found == capacity:  # grow by doubling (arrays and scalar loops compile fast)
                capacity *= 2
                more_pairs, more_segments = (
                    np.empty((capacity, 2), np.int64),
                    np.empty((capacity, 2, 3)),
                )
                for r in range(found):
                    more_pairs[r, 0], more_pairs[r, 1] = pairs[r, 0], pairs[r, 1]
                    for e in range(2):
                        for c in range(3):
                            more_segments[r, e, c] = segments[r, e, c]
                pairs, segments = more_pairs, more_segments
            pairs[found, 0], pairs[found, 1] = min(i, j), max(i, j)
            for e in range(2):
                for c in range(3):
                    segments[found, e, c] = seg[e, c]
            found += 1
    return pairs[:found].copy(), segments[:found].copy()


def crossing_segments(triangles: np.ndarray, welded: np.ndarray):
    """Pairs of triangles (m, 2) (global ids) that pass through each other and the segment
    (m, 2, 3) they share: triangles (N, 3, 3), welded (N, 3) global welded vertex ids."""
    if len(triangles) < 2:
        return np.zeros((0, 2), np.int64), np.zeros((0, 2, 3))
    low, high = triangles.min(axis=1), triangles.max(axis=1)
    order = np.argsort(low[:, 0], kind="stable")
    return _crossing_pairs(triangles, welded, order, low, high)


def global_welded(scene: Scene, topology) -> np.ndarray:
    """(N, 3) welded vertex ids of every triangle, distinct between meshes."""
    parts, offset = [], 0
    for k, _ in enumerate(scene.meshes):
        welded = topology[k].welded
        parts.append(welded + offset)
        offset += int(welded.max()) + 1 if welded.size else 0
    return np.concatenate(parts) if parts else np.zeros((0, 3), np.int64)


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


# ---------------------------------------------------------------------------------------
# The boundary term
# ---------------------------------------------------------------------------------------


def boundary_points(
    scene: Scene,
    visibility: Visibility,
    frame,
    topology,
    crossings,
    radiance,
    extra: tuple[np.ndarray, np.ndarray] | None = None,
    shared=None,
) -> tuple[BoundaryPoints, tuple]:
    """Every quadrature point of the boundary term of edges, intersections and outlines,
    with its constant factor (see the module docstring), for one render. ``topology``:
    ``mesh_edges`` per mesh index; ``crossings``: ``crossing_segments`` of the scene's
    triangles (both depend on the geometry alone, so the caller may reuse them);
    ``radiance``: what the camera sees on either side (``DirectRadiance``).

    extra: more curves as segments (start (k, 2), end (k, 2), pixel coordinates): the
    shadow borders, cut together with the rest (``split_at_crossings``). Their quadrature
    points are returned as (segment (m,) into ``extra``, image-plane coords (m, 2),
    weight (m,), pixel (m,)) for the caller to finish.

    shared: the edges meshes share (``render.trace.seams.shared_edges``; None: none), each
    counted once, its sides chosen among every mesh's faces on it.
    """
    camera = scene.camera
    width, height = camera.width, camera.height
    plain = plain_frame(scene.camera)
    size = max(visibility.size, 1e-300)
    tables = [topology[k].table for k in range(len(scene.meshes))]
    starts, ends, kept = _edge_curves(scene, plain, tables, size, shared)
    n_edges = [len(s) for s in starts]
    pairs, segments = crossings
    a, b, keep = clip_to_near(segments[:, 0], segments[:, 1], plain, NEAR * size)
    pairs = pairs[keep]
    starts.append(project(a[keep], plain, width, height)[0])
    ends.append(project(b[keep], plain, width, height)[0])
    outlines = []
    for index, sphere in enumerate(scene.spheres):
        poly = _outline_polyline(sphere, plain, width, height, size)
        if poly is not None:
            starts.append(poly[:-1])
            ends.append(poly[1:])
            outlines.append((index, len(poly) - 1))
    spheres = [
        (np.asarray(sp.center.data, np.float64), float(sp.radius.data)) for sp in scene.spheres
    ]
    cut_start, cut_end, cut_sphere, cut_triangle = sphere_cut_curves(
        spheres, visibility.primitives[0], plain, width, height, size
    )
    starts.append(cut_start)
    ends.append(cut_end)
    n_own = sum(len(s) for s in starts)
    if extra is not None:
        starts.append(extra[0])
        ends.append(extra[1])
    p0, p1 = np.concatenate(starts), np.concatenate(ends)  # never empty: crossings come too
    pieces = split_at_crossings(p0, p1, *pixel_pieces(p0, p1, width, height))
    points, segment, weight = quadrature(p0, p1, *pieces[:3])
    pixel = np.repeat(pieces[3], GAUSS_POINTS)
    coords = to_image_plane(points, width, height)
    rows = np.flatnonzero(segment >= n_own)
    others = (segment[rows] - n_own, coords[rows], weight[rows], pixel[rows])
    factor = np.zeros((len(coords), 3))
    first, mesh_edges, sphere_points = 0, [], []
    firsts = np.cumsum([0] + [m.num_faces for m in scene.meshes])
    for index, count in enumerate(n_edges):
        rows = np.flatnonzero((segment >= first) & (segment < first + count))
        edges = kept[index][segment[rows] - first]
        table = tables[index]
        factor[rows] = _mesh_edge_factors(
            scene, visibility, frame, index, firsts[index], table, edges,
            np.take(coords, rows, axis=0), pixel[rows], weight[rows], radiance, rows,
            None if shared is None else shared[index],
        )  # fmt: skip
        mesh_edges.append((index, rows, table.i[edges], table.j[edges]))
        first += count
    rows = np.flatnonzero((segment >= first) & (segment < first + len(pairs)))
    crossing_pairs = pairs[segment[rows] - first]
    factor[rows] = _crossing_factors(
        scene, visibility, frame, crossing_pairs, coords[rows], weight[rows], radiance, rows
    )
    crossings = (rows, crossing_pairs)
    first += len(pairs)
    for index, count in outlines:
        rows = np.flatnonzero((segment >= first) & (segment < first + count))
        factor[rows], coords[rows] = _outline_factors(
            scene, visibility, frame, index, coords[rows], weight[rows], radiance, rows
        )
        sphere_points.append((index, rows))
        first += count
    rows = np.flatnonzero((segment >= first) & (segment < first + len(cut_sphere)))
    on_sphere, on_triangle = cut_sphere[segment[rows] - first], cut_triangle[segment[rows] - first]
    sphere_cuts = []
    for index in np.unique(on_sphere):
        mine = rows[on_sphere == index]
        ids = on_triangle[on_sphere == index]
        factor[mine], coords[mine] = _sphere_cut_factors(
            scene, visibility, frame, index, ids, coords[mine], weight[mine], radiance, mine
        )
        sphere_cuts.append((int(index), mine, ids))
    nonzero = np.any(factor != 0.0, axis=1)
    keep = np.flatnonzero(nonzero)
    remap = np.full(len(coords), -1)
    remap[keep] = np.arange(len(keep))
    mesh_edges = [
        (k, remap[r[nonzero[r]]], i[nonzero[r]], j[nonzero[r]]) for k, r, i, j in mesh_edges
    ]
    sphere_points = [(k, remap[r[nonzero[r]]]) for k, r in sphere_points]
    sphere_cuts = [(k, remap[r[nonzero[r]]], t[nonzero[r]]) for k, r, t in sphere_cuts]
    rows, crossing_pairs = crossings
    crossings = (remap[rows[nonzero[rows]]], crossing_pairs[nonzero[rows]])
    points = BoundaryPoints(
        np.take(coords, keep, axis=0),
        pixel[keep],
        np.take(factor, keep, axis=0),
        mesh_edges,
        sphere_points,
        crossings,
        sphere_cuts,
    )
    return points, others


def _line_points(visibility, frame, camera, m, coords, directions, depth, ignore):
    """For k points on lines with the edge function e = d . m (m (k, 3), the plane through
    the eye and the line), seen along camera directions (k, 3) at ``depth`` (k,): |grad e|
    in pixel units (k,), the image-plane step one pixel along grad e (k, 2), and which
    points are ``hidden_points`` (k,) bool."""
    forward, right, up, eye = frame
    norm, step = pixel_gradient(np.stack([m @ right, m @ up], axis=1), *_size(camera))
    hidden = hidden_points(visibility, frame, camera, coords, directions, depth, norm, ignore)
    return norm, step, hidden


def edge_sides(eye, forward, right, up, vertices, i, j, faces, thirds, coords, width, height):
    """The geometry of k quadrature points on mesh edges (v_i, v_j), plainly in NumPy (the
    reference of ``edge_sides_kernel``, which computes the same in one pass).

    eye, forward, right, up (3,): the camera (``plain_camera``); vertices (V, 3); i, j
    (k,) the edges' vertex ids; faces (k, K): the faces on each edge (ids, -1 padding, as
    ``EdgeTable.faces``); thirds (k, K, 3): their corners off the edge (positions: a face
    may belong to another mesh, ``render.trace.seams``); coords (k, 2) image-plane points.

    Returns the camera directions (k, 3) through the points, the depth (k,) of the edge
    point along them (``_edge_points``), |grad e| in pixel units (k,) and the image-plane
    step (k, 2) one pixel along grad e (``pixel_gradient``), and the face (k, 2) seen
    just beside the edge on its + and - side (-1: no face on that side): the nearest
    there of the faces on that side (``_approach``)."""
    a, b = vertices[i], vertices[j]
    m = np.cross(a - eye, b - eye)
    directions = camera_directions(coords, right, up, forward)
    depth = _edge_points(eye, directions, a, b)
    norm, step = pixel_gradient(np.stack([m @ right, m @ up], axis=1), width, height)
    valid = faces >= 0
    third = thirds  # (k, K, 3)
    side = np.sign(np.einsum("nkj,nj->nk", third - eye[None], m))
    towards = step[:, :1] * right + step[:, 1:] * up  # the image step to the + side
    normals = np.cross((b - a)[:, None], third - a[:, None])  # (k, K, 3)
    rate = _approach(normals, directions[:, None], towards[:, None])  # (k, K)
    chosen = np.full((len(coords), 2), -1, np.int64)
    for column, sign in enumerate((1.0, -1.0)):
        on_side = valid & (side == sign)
        best = np.argmax(np.where(on_side, sign * rate, -np.inf), axis=1)
        has = on_side.any(axis=1)
        chosen[has, column] = faces[has, best[has]]
    return directions, depth, norm, step, chosen


@numba.njit(cache=True, error_model="numpy", parallel=True)
def edge_sides_kernel(
    eye, forward, right, up, vertices, i, j, faces, thirds, coords, width, height, n_threads
):
    """``edge_sides`` in one pass over the points: the same arithmetic per point, in
    scalars and four scratch 3-vectors instead of a dozen (k, 3) temporaries, the points
    shared out over ``n_threads`` (``numba.get_num_threads()``) as the ray kernels share
    rays (``render.trace.intersect._jobs``: every point's result is the same on any number
    of threads). The hot loop of the boundary term; tests/render/edges/test_boundary.py ties it to
    ``edge_sides``."""
    k, n_faces = faces.shape
    directions = np.empty((k, 3))
    depth, norm = np.empty(k), np.empty(k)
    step = np.empty((k, 2))
    chosen = np.full((k, 2), -1, np.int64)
    n_blocks, n_jobs = _jobs(k, n_threads)
    sx, sy = 2.0 / width, -2.0 / height
    for job in numba.prange(n_jobs):
        am, bm, m, u = np.empty(3), np.empty(3), np.empty(3), np.empty(3)  # per thread
        w0, towards, t, normal = np.empty(3), np.empty(3), np.empty(3), np.empty(3)
        for block in range(job, n_blocks, n_jobs):
            for p in range(block * BLOCK, min(k, (block + 1) * BLOCK)):
                a, b, d = vertices[i[p]], vertices[j[p]], directions[p]
                for c in range(3):
                    am[c], bm[c] = a[c] - eye[c], b[c] - eye[c]
                    d[c] = coords[p, 0] * right[c] + coords[p, 1] * up[c] + forward[c]
                    u[c], w0[c] = b[c] - a[c], eye[c] - a[c]
                _cross(am, bm, m)
                # _edge_points: the depth along d of the point nearest the line through a and b
                dd, du, uu, dw, uw = _dot(d, d), _dot(d, u), _dot(u, u), _dot(d, w0), _dot(u, w0)
                det = dd * uu - du * du
                depth[p] = (du * uw - uu * dw) / (det if det > 0 else 1.0)
                # pixel_gradient of grad e = (m . right, m . up)
                gx, gy = _dot(m, right) * sx, _dot(m, up) * sy
                length = math.sqrt(gx * gx + gy * gy)
                scale = length if length > 0 else 1.0
                norm[p] = length
                step[p, 0], step[p, 1] = gx / scale * sx, gy / scale * sy
                for c in range(3):
                    towards[c] = step[p, 0] * right[c] + step[p, 1] * up[c]
                # the nearest face on either side (_approach; ties go to the first, as np.argmax)
                best_plus, best_minus = -np.inf, -np.inf
                for f in range(n_faces):
                    if faces[p, f] < 0:
                        continue
                    third = thirds[p, f]
                    for c in range(3):
                        t[c] = third[c] - a[c]
                    side = (third[0] - eye[0]) * m[0] + (third[1] - eye[1]) * m[1]
                    side = side + (third[2] - eye[2]) * m[2]
                    if side == 0 or side != side:
                        continue
                    _cross(u, t, normal)
                    nd, ng = _dot(normal, d), _dot(normal, towards)
                    rate = ng / nd if nd != 0 else ng / np.inf
                    if side > 0 and (chosen[p, 0] < 0 or rate > best_plus):
                        best_plus, chosen[p, 0] = rate, faces[p, f]
                    elif side < 0 and (chosen[p, 1] < 0 or -rate > best_minus):
                        best_minus, chosen[p, 1] = -rate, faces[p, f]
    return directions, depth, norm, step, chosen


def _mesh_edge_factors(
    scene, visibility, frame, index, first_prim, table, edges, coords, pixel, weight, radiance,
    keys, shared=None,
) -> np.ndarray:  # fmt: skip
    """(k, 3): w (f_+ - f_-) / |grad e| for k quadrature points on the edges ``edges``
    (rows of ``table``) of mesh ``index``, zero where the edge point is hidden; ``pixel``
    (k,): the pixel each point lies in; ``keys`` (k,): the points' names for ``radiance``
    (``DirectRadiance``).

    The edge point is where the camera ray through the quadrature point meets the edge.
    It is visible if nothing lies in front of it (an any-hit ray that ends just short of
    it). Each face's third vertex tells on which side of the edge's image it lies. On each
    side, the face seen just beside the edge is the nearest there of the faces on that
    side (``_approach``), shaded at the edge point as a camera hit on it would be; a side
    with no face (a silhouette's outside, an open boundary) is what a ray just beyond the
    edge sees. A crease has one face on each side, a silhouette both on one. ``shared``:
    the faces other meshes have on these edges (``render.trace.seams.SharedEdges``),
    candidates on either side as the mesh's own are; None: no other mesh's."""
    forward, right, up, eye = plain_frame(scene.camera)
    vertices = np.asarray(scene.meshes[index].vertices.data, np.float64)
    own = np.take(table.faces, edges, axis=0)
    faces = np.where(own >= 0, own + first_prim, -1)  # global primitive ids
    thirds = np.take(vertices, np.maximum(np.take(table.thirds, edges, axis=0), 0), axis=0)
    if shared is not None and shared.faces.shape[1]:
        faces = np.concatenate([faces, np.take(shared.faces, edges, axis=0)], axis=1)
        thirds = np.concatenate([thirds, np.take(shared.thirds, edges, axis=0)], axis=1)
    directions, depth, norm, step, chosen = edge_sides_kernel(
        eye, forward, right, up, vertices, table.i[edges], table.j[edges], faces, thirds,
        np.ascontiguousarray(coords), *_size(scene.camera), numba.get_num_threads(),
    )  # fmt: skip
    ignore = table.faces[edges, 0] + first_prim
    hidden = hidden_points(
        visibility, (forward, right, up, eye), scene.camera, coords, directions, depth, norm,
        ignore, seen_in(visibility, pixel, scene),
    )  # fmt: skip
    seen = np.flatnonzero(~hidden)
    n = len(seen)
    coords, depth, step, chosen = (np.take(x, seen, axis=0) for x in (coords, depth, step, chosen))
    keys = np.concatenate([keys[seen], keys[seen]])  # per row of ``colour`` below
    # Both sides at once: one shading pass for the sides with a face (shaded at the edge
    # point), one for the sides without (what a ray just beyond the edge sees).
    face = np.concatenate([chosen[:, 0], chosen[:, 1]])  # rows: the + sides, then the -
    both = np.concatenate([coords, coords])
    faced, beyond = np.flatnonzero(face >= 0), np.flatnonzero(face < 0)
    colour = np.empty((2 * n, 3))
    colour[faced] = radiance.seen(
        np.take(both, faced, axis=0), face[faced],
        np.concatenate([depth, depth])[faced], keys[faced],
    )  # fmt: skip
    offset = EPSILON * np.concatenate([step, -step])
    colour[beyond] = radiance.along(np.take(both + offset, beyond, axis=0), keys[beyond])
    out = np.zeros((len(hidden), 3))
    out[seen] = (weight[seen] / norm[seen])[:, None] * (colour[:n] - colour[n:])
    return out


def _approach(normals, directions, towards):
    """How fast planes through a point come nearer as the ray moves into one side: a plane
    with normal n through the point at depth t has depth t (n . d) / (n . (d + s g)) along
    the ray moved by s towards g, so the larger (n . g) / (n . d), the nearer it comes.
    Arrays broadcast over leading axes; the last is xyz."""
    nd = np.sum(normals * directions, axis=-1)
    ng = np.sum(normals * towards, axis=-1)
    return ng / np.where(nd != 0, nd, np.inf)


def _plane_line(t1, t2, eye):
    """For triangles t1, t2 (k, 3, 3) (arrays, or tuples of (k, 3) tensors (a, b, c)): the
    normals n1, n2 (k, 3), and m = (P - eye) x u (k, 3) of the line where their planes meet
    (u = n1 x n2, P on the line): the line's edge function is d . m, as for a mesh edge."""
    n1, n2 = plane_normal(t1), plane_normal(t2)
    if isinstance(t1, np.ndarray):
        t1, t2 = (t1[:, 0], t1[:, 1], t1[:, 2]), (t2[:, 0], t2[:, 1], t2[:, 2])
    h1, h2 = dot_last(n1, t1[0]), dot_last(n2, t2[0])
    a11, a22, a12 = dot_last(n1, n1), dot_last(n2, n2), dot_last(n1, n2)
    det = a11 * a22 - a12 * a12
    # P = alpha n1 + beta n2 with n1 . P = h1, n2 . P = h2 (the point nearest the origin).
    alpha, beta = (h1 * a22 - h2 * a12) / det, (h2 * a11 - h1 * a12) / det
    point = as_column(alpha) * n1 + as_column(beta) * n2
    cross = md.cross if isinstance(point, md.Tensor) else np.cross
    return n1, n2, cross(point - eye, cross(n1, n2))


def _crossing_factors(scene, visibility, frame, pairs, coords, weight, radiance, keys):
    """(k, 3): w (f_+ - f_-) / |grad e| for k quadrature points on the segments where the
    triangle pairs ``pairs`` (k, 2) cross, zero where hidden. Near the segment each side
    sees the triangle that is nearer there, shaded at the point."""
    forward, right, up, eye = plain_frame(scene.camera)
    camera = scene.camera
    triangles = visibility.primitives[0]
    t1, t2 = triangles[pairs[:, 0]], triangles[pairs[:, 1]]
    n1, n2, m = _plane_line(t1, t2, eye)
    directions = camera_directions(coords, right, up, forward)
    # Depth of the point: where the ray meets plane 1 (the point is on both planes).
    nd = np.einsum("ij,ij->i", n1, directions)
    depth = np.einsum("ij,ij->i", n1, t1[:, 0] - eye) / np.where(nd != 0, nd, np.inf)
    norm, step, hidden = _line_points(
        visibility, (forward, right, up, eye), camera, m, coords, directions, depth, pairs[:, 0]
    )
    seen = np.flatnonzero(~hidden)
    towards = step[seen, :1] * right + step[seen, 1:] * up  # towards the + side
    d = directions[seen]

    # Triangle 1 is the nearer on the + side if it comes nearer faster (``_approach``).
    plus_first = _approach(n1[seen], d, towards) > _approach(n2[seen], d, towards)
    plus = np.where(plus_first, pairs[seen, 0], pairs[seen, 1])
    minus = np.where(plus_first, pairs[seen, 1], pairs[seen, 0])
    k = len(seen)
    colours = radiance.seen(
        np.concatenate([coords[seen], coords[seen]]),
        np.concatenate([plus, minus]),
        np.concatenate([depth[seen], depth[seen]]),
        np.concatenate([keys[seen], keys[seen]]),
    )
    out = np.zeros((len(coords), 3))
    out[seen] = (weight[seen] / norm[seen])[:, None] * (colours[:k] - colours[k:])
    return out


def _size(camera) -> tuple[int, int]:
    """(width, height) of the camera's image, in pixels."""
    return camera.width, camera.height


def _outline_factors(scene, visibility, frame, index, coords, weight, radiance, keys):
    """(k, 3) w (f_+ - f_-) / |grad e| for k quadrature points on the outline of sphere
    ``index``, and the points moved onto the outline (k, 2). The outline of a sphere is
    smooth: f_+ and f_- are what two rays just inside and just outside it see, where the
    point at which the ray touches the sphere is visible (``hidden_points``, the sphere itself
    ignored). The test matters where another curve runs within the rays' EPSILON of the
    outline: where a triangle passing through the sphere seems to emerge from it, the
    curve of the cut is tangent to the outline, and there the rays alone saw the same
    jump across both (counting it twice)."""
    plain = plain_frame(scene.camera)
    sphere = scene.spheres[index]
    coords, grad = _onto_outline(coords, sphere, plain)
    forward, right, up, eye = plain
    directions = camera_directions(coords, right, up, forward)
    dd = np.einsum("ij,ij->i", directions, directions)
    depth = (directions @ (np.asarray(sphere.center.data, np.float64) - eye)) / dd
    ignore = np.full(len(coords), first_sphere_id(scene) + index)
    return _traced_factors(
        scene.camera, visibility, plain, coords, directions, depth, grad, weight, radiance,
        keys, ignore, np.zeros(len(coords), dtype=bool),
    )  # fmt: skip


def _sphere_cut_factors(scene, visibility, frame, index, ids, coords, weight, radiance, keys):
    """(k, 3) w (f_+ - f_-) / |grad e| for k quadrature points on the curves where the
    triangles ``ids`` (k,) (global ids) cut sphere ``index``, and the points moved onto
    those curves (k, 2). A point is hidden where it lies on the sphere's far half (the
    sphere itself is in front) or something else is in front of it (``hidden_points``); where
    it is visible f_+ and f_- are what two rays either side see (the triangle on one, the
    sphere on the other)."""
    plain = plain_frame(scene.camera)
    forward, right, up, eye = plain
    sphere = scene.spheres[index]
    centre, radius = np.asarray(sphere.center.data, np.float64), float(sphere.radius.data)
    corners = visibility.primitives[0][ids]
    coords, grad = _onto_sphere_cut(coords, corners, centre, radius, plain)
    directions = camera_directions(coords, right, up, forward)
    n = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    nd = np.einsum("ij,ij->i", n, directions)
    depth = np.einsum("ij,ij->i", n, corners[:, 0] - eye) / np.where(nd != 0, nd, np.inf)
    point = eye + depth[:, None] * directions
    far = np.einsum("ij,ij->i", point - centre, eye - point) <= 0
    ignore = np.full(len(coords), first_sphere_id(scene) + index)
    return _traced_factors(
        scene.camera, visibility, plain, coords, directions, depth, grad, weight, radiance,
        keys, ignore, far,
    )  # fmt: skip


def _traced_factors(
    camera, visibility, frame, coords, directions, depth, grad, weight, radiance, keys, ignore,
    hidden,
):  # fmt: skip
    """(k, 3) w (f_+ - f_-) / |grad e| for k points ``coords`` (k, 2) on a curve whose edge
    function has image-plane gradient ``grad`` (k, 2) there, zero where the curve's point
    (along camera ``directions`` (k, 3) at ``depth`` (k,)) is ``hidden`` (k,) already or
    ``hidden_points`` (primitive ``ignore`` (k,) not counted), else f_+ and f_- traced by rays
    ``EPSILON`` pixels either side; and the points."""
    norm, step = pixel_gradient(grad, *_size(camera))
    hidden = hidden | hidden_points(
        visibility, frame, camera, coords, directions, depth, norm, ignore
    )
    seen = np.flatnonzero(~hidden)
    at, step, keys = coords[seen], step[seen], keys[seen]
    both = np.concatenate([at + EPSILON * step, at - EPSILON * step])
    f = radiance.along(both, np.concatenate([keys, keys]))
    jump = np.zeros((len(coords), 3))
    jump[seen] = f[: len(seen)] - f[len(seen) :]
    factor = np.where(norm > 0, weight / np.where(norm > 0, norm, 1.0), 0.0)
    return factor[:, None] * jump, coords


def boundary_term(
    scene: Scene, points: BoundaryPoints, frame, shadows: tuple | None = None
) -> md.Tensor | None:
    """(H, W, 3) on the tape: zero in value, the boundary term in derivative (None when
    there are no points). ``shadows``: the shadow borders' (e (G',) on the tape, weight
    (G', 3), pixel (G',)) (``render.edges.shadow_boundary.shadow_term``), or None."""
    dtype = working_dtype(scene)
    eye = frame[3]
    parts, order = [], []
    for index, rows, i, j in points.mesh_edges:
        if len(rows) == 0:
            continue
        vertices = scene.meshes[index].vertices
        m = md.cross(vertices[i] - eye, vertices[j] - eye)
        d = ray_directions(frame, points.coords[rows].astype(dtype))
        parts.append(md.dot(d, m))
        order.append(rows)
    for index, rows in points.sphere_points:
        if len(rows) == 0:
            continue
        sphere = scene.spheres[index]
        oc = eye - sphere.center
        kappa = md.dot(oc, oc) - sphere.radius * sphere.radius
        d = ray_directions(frame, points.coords[rows].astype(dtype))
        b = md.dot(d, oc)
        parts.append(b * b - md.dot(d, d) * kappa)
        order.append(rows)
    for index, rows, ids in points.sphere_cuts:
        if len(rows) == 0:
            continue
        sphere = scene.spheres[index]
        a, b, c = triangle_corners(scene, ids)
        d = ray_directions(frame, points.coords[rows].astype(dtype))
        parts.append(
            sphere_cut_function(a, md.cross(b - a, c - a), sphere.center, sphere.radius, eye, d)
        )
        order.append(rows)
    rows, pairs = points.crossings
    if len(rows):
        first = triangle_corners(scene, pairs[:, 0])
        second = triangle_corners(scene, pairs[:, 1])
        _, _, m = _plane_line(first, second, eye)
        d = ray_directions(frame, points.coords[rows].astype(dtype))
        parts.append(md.dot(d, m))
        order.append(rows)
    weight = [points.weight[np.concatenate(order)]] if order else []
    pixel = [points.pixel[np.concatenate(order)]] if order else []
    if shadows is not None:
        parts.append(shadows[0])
        weight.append(shadows[1])
        pixel.append(shadows[2])
    if not parts:
        return None
    e = md.concatenate(parts) if len(parts) > 1 else parts[0]
    moving = e - md.tensor(e.data)  # zero, with the derivative of e
    values = md.reshape(moving, (-1, 1)) * np.concatenate(weight).astype(dtype)
    camera = scene.camera
    image = md.scatter_add(values, np.concatenate(pixel), camera.width * camera.height)
    return md.reshape(image, (camera.height, camera.width, 3))
