"""Shadow edges by the boundary integral: the exact derivative where a hard shadow's border
moves (``render(antialias="boundary")``).

A shadow boundary is a discontinuity of the image like an outline (``render.edges.boundary``
explains the boundary term; this module supplies its curves of secondary visibility). A
point light L casts past an occluder's silhouette *as seen from the light* a shadow whose
border, on the receiving surface, is where the light's ray to the receiver point P grazes
the occluder. With P(x) the point the camera ray through image position x meets on the
receiver, the border in the image is the zero set of

* an occluder edge (v_i, v_j): e = m . (P(x) - L), m = (v_i - L) x (v_j - L) (the plane
  through the light and the edge; for a directional light travelling along w, m = (v_j -
  v_i) x w and e = m . (P(x) - v_i));
* an occluder sphere (c, r): e = (oc . u)^2 - |u|^2 (|oc|^2 - r^2), the discriminant of the
  light's ray: oc = L - c, u = P(x) - L (directional: oc = P(x) - c, u = w);

smooth in every parameter: the receiver's vertices or sphere (through P), the camera (through
the ray), the occluder and the light. The boundary term of a pixel is then, as for outlines,
the sum over quadrature points on the border's pieces inside it of w (f_+ - f_-) / |grad_x
e| de/dtheta, and ``shadow_term`` adds c (e - detach(e)) to the image.

Finding the border (off the tape): each silhouette curve of each occluder seen from the
light (mesh edges whose faces do not all face the light, open edges, a sphere's circle of
tangency) is followed by rays from the light that graze it; where such a ray goes on to hit
a receiver, it marks a point of the border. Consecutive points on one receiver triangle are
joined by a chord, exact while the occluder is an edge and the receiver a triangle (the
border is then straight), and at most ``CHORD`` pixels long otherwise; where the receiver
changes, the curve parameter is bisected until the gap is below ``GAP`` pixels. The chords
are cut at pixel borders like outlines (``pixel_pieces``), each quadrature point moved onto
the exact border (Newton on e), and f_+ and f_- are the radiance seen by two camera rays
just either side (``radiance_at``): a border hidden from the camera, or lying in another
shadow of the same light, has f_+ = f_- there and adds nothing.

Not included: shadow borders seen in mirrors, and a receiver narrower than the spacing of
the grazing rays: they start ``SPACING`` pixels apart along the occluder's image and are
refined where the border they draw is longer than that, but a small receiver between two
rays that both miss it, or both hit the same other one, is not seen.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

import minidiff as md
from render.edges.boundary.occlusion import hidden_points as _hidden
from render.edges.boundary.pixels import pixel_gradient as _pixel_gradient
from render.edges.boundary.radiance import EPSILON
from render.edges.geometry import as_column, dot_last, plane_normal, triangle_corners
from render.scene.camera import camera_directions, plain_camera, project, ray_directions
from render.scene.scene import PointLight, Scene
from render.shade.hits import working_dtype
from render.shade.surface import in_order
from render.trace.intersect import closest_hit_ray, make_ray
from render.trace.primitives import first_sphere_id
from render.trace.visibility import Visibility

#: Where the border is curved (a sphere casts it or receives it), chords at most this long.
CHORD = 0.5
#: Grazing rays along a silhouette are at most this far apart, in image pixels, while they
#: hit the same receiver (so that a small receiver between two of them is rarely missed).
SPACING = 2.0
#: Where the receiver changes between two grazing rays, bisect until they are this close.
GAP = 1e-3
#: Bisection rounds at most. A chord is at most SPACING = 2 pixels long at the start, so
#: after 20 halvings what is left of one whose receiver jumps (the border falls off one
#: surface onto another farther away, and the two ends never come within GAP) is ~2e-6
#: pixels of the border: dropping it changes the term by ~1e-6 of one pixel's share.
#: (30 rounds changed gradients by < 1e-7 relative on the teapot and its ground, and cost
#: 10 more rounds of grazing rays for the few dozen chords at such jumps.)
ROUNDS = 20
#: Grazing rays start this fraction of the way beyond the occluder (off its own surface).
START = 1e-7
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
# The silhouettes as seen from the light, as curves S(u), u in [0, 1]
# ---------------------------------------------------------------------------------------


def _edge_faces(scene: Scene, topology, shared=None) -> list[tuple]:
    """Per mesh, for every face on every welded edge (``EdgeTable.faces``, (E, K), then the
    faces other meshes have on it, ``render.trace.seams.SharedEdges.faces``, when
    ``shared`` is given): its normal (E, K', 3), first corner (E, K', 3) and whether the
    slot holds a face (E, K') bool; the same for every light, so computed once per
    render."""
    out = []
    if shared is not None:
        every = [np.asarray(m.vertices.data, np.float64)[m.faces] for m in scene.meshes]
        triangles = np.concatenate(every)  # (N, 3, 3), by global primitive id
    for k, mesh in enumerate(scene.meshes):
        vertices = np.asarray(mesh.vertices.data, np.float64)
        faces = topology[k].table.faces
        tri = vertices[mesh.faces[np.maximum(faces, 0)]]  # (E, K, 3, 3)
        valid = faces >= 0
        if shared is not None:
            tri = np.concatenate([tri, triangles[np.maximum(shared[k].faces, 0)]], axis=1)
            valid = np.concatenate([valid, shared[k].faces >= 0], axis=1)
        normal = np.cross(tri[..., 1, :] - tri[..., 0, :], tri[..., 2, :] - tri[..., 0, :])
        out.append((normal, tri[..., 0, :], valid))
    return out


def _light_silhouettes(scene: Scene, topology, light, edge_faces, shared=None):
    """Occluder curves of one light: (occluder (c, 3) int64 as in ``ShadowPoints``, curve
    kind per row: 0 a segment from ``a`` to ``b`` (c, 3), 1 a circle centre ``a``, radius
    vector ``b`` and second axis ``axis`` (c, 3)). ``edge_faces``: ``_edge_faces``;
    ``shared``: the edges meshes share (``render.trace.seams.shared_edges``, None: none),
    each an occluder's silhouette once, judged by every mesh's faces on it."""
    rows, a, b, axis = [], [], [], []
    point = isinstance(light, PointLight)
    where = np.asarray(light.position.data if point else light.direction.data, np.float64)
    for k, mesh in enumerate(scene.meshes):
        table = topology[k].table
        vertices = np.asarray(mesh.vertices.data, np.float64)
        normal, corner, valid = edge_faces[k]
        towards = (where - corner) if point else -where
        facing = np.sign(np.sum(normal * towards, axis=-1))
        lit = np.any(valid & (facing > 0), axis=1)
        dark = np.any(valid & (facing < 0), axis=1)
        keep = (lit & dark) | (valid.sum(axis=1) == 1)
        if shared is not None:
            joined = np.any(shared[k].faces >= 0, axis=1)
            own = vertices[np.maximum(table.thirds, 0)]
            thirds = np.concatenate([own, shared[k].thirds], axis=1)
            one_side = _one_sided(vertices[table.i], vertices[table.j], thirds, valid, where, point)
            # Where faces of several meshes meet, their windings need not agree (two
            # coincident copies, a seam between differently wound parts): the edge is an
            # outline seen from the light where all their third corners lie on one side
            # of the plane through the light and the edge.
            keep = np.where(joined, one_side, keep) & shared[k].owned
        keep = np.flatnonzero(keep)
        rows.append(np.stack([np.full(len(keep), k), table.i[keep], table.j[keep]], axis=1))
        a.append(vertices[table.i[keep]])
        b.append(vertices[table.j[keep]])
        axis.append(np.zeros((len(keep), 3)))
    for index, sphere in enumerate(scene.spheres):
        centre, r = np.asarray(sphere.center.data, np.float64), float(sphere.radius.data)
        view = (centre - where) if point else where
        dist2 = float(view @ view)
        if point and dist2 <= r * r:
            continue  # the light inside the sphere: everything outside is dark
        shrink = r * r / dist2 if point else 0.0
        rho = r * math.sqrt(1.0 - shrink)
        u1 = np.cross(view, [1.0, 0, 0] if abs(view[0]) < 0.9 * math.sqrt(dist2) else [0, 1.0, 0])
        u1 *= rho / np.linalg.norm(u1)
        u2 = np.cross(view, u1) / math.sqrt(dist2)
        rows.append(np.array([[-1, index, -1]]))
        a.append((centre - shrink * view)[None])
        b.append(u1[None])
        axis.append(u2[None])
    occluder = np.concatenate(rows) if rows else np.zeros((0, 3), np.int64)
    kind = (occluder[:, 0] < 0).astype(np.int64)
    cat = (lambda x: np.concatenate(x)) if rows else (lambda x: np.zeros((0, 3)))
    return occluder, kind, cat(a), cat(b), cat(axis)


def _one_sided(a, b, thirds, valid, where, point: bool) -> np.ndarray:
    """(E,) bool: edges (a, b) (E, 3) whose faces' third corners ``thirds`` (E, K, 3) (where
    ``valid`` (E, K)) all lie on one side of the plane through the light and the edge
    (``where``: a point light's position, or a directional light's direction)."""
    m = np.cross(a - where, b - where) if point else np.cross(b - a, where)
    side = np.einsum("ekj,ej->ek", thirds - a[:, None], m)
    plus = np.any(valid & (side > 0), axis=1)
    minus = np.any(valid & (side < 0), axis=1)
    return ~(plus & minus)


def _curve_points(kind, a, b, axis, u):
    """Points S(u) (k, 3) of curves (rows of kind, a, b, axis) at parameters u (k,)."""
    phi = 2.0 * math.pi * u[:, None]
    circle = a + np.cos(phi) * b + np.sin(phi) * axis
    return np.where(kind[:, None] == 1, circle, a + u[:, None] * (b - a))


# ---------------------------------------------------------------------------------------
# Following the border: grazing rays, bisection, chords
# ---------------------------------------------------------------------------------------


def _graze(visibility, lights, light, frame, size, camera, s, own):
    """Where the light's rays grazing the points s (k, 3) go on to hit: receiver (k,)
    (-1: nothing, behind the camera, or ``own`` (k,), the sphere grazed, which a ray
    touching it meets again only by rounding), its image position (k, 2) in pixels.
    ``light`` (k,): each point's light, an index into ``lights``. The rays of all point
    lights are traced in one call, those of all directional lights in another."""
    prim, hit = np.full(len(s), -1), np.zeros_like(s)
    point = np.array([isinstance(x, PointLight) for x in lights])
    towards = np.array([_towards(x) for x in lights])
    for rows in (np.flatnonzero(point[light]), np.flatnonzero(~point[light])):
        if len(rows) == 0:
            continue
        at = np.take(s, rows, axis=0)
        where = np.take(towards, light[rows], axis=0)
        if point[light[rows[0]]]:  # from the light through the point, on beyond it
            p, t, _, _ = visibility.accelerator().closest_hit(where, at - where, tmin=1.0 + START)
            hit[rows] = where + np.where(p >= 0, t, 0.0)[:, None] * (at - where)
        else:  # from the point along the light's (unit) direction
            p, t, _, _ = visibility.accelerator().closest_hit(at, where, tmin=START * size)
            hit[rows] = at + np.where(p >= 0, t, 0.0)[:, None] * where
        prim[rows] = p
    px, depth = project(np.where(prim[:, None] >= 0, hit, s), frame, camera.width, camera.height)
    prim = np.where((prim >= 0) & (depth > 1e-7 * size) & (prim != own), prim, -1)
    return prim, np.where(prim[:, None] >= 0, px, 0.0)


def _starting_chords(scene, frame, curves):
    """Where the grazing rays start: each curve at 2 points plus one per SPACING pixels of
    its image from the camera, as chords (curve (n,), u0 (n,), u1 (n,)); and per curve
    the sphere a ray grazing it must not count as its receiver (``own`` (c,), -2: none)."""
    occluder, kind, a, b, axis = curves
    camera = scene.camera
    ends = np.concatenate([a, np.where(kind[:, None] == 1, a + b, b)])
    px, depth = project(ends, frame, camera.width, camera.height)
    ok = (depth[: len(a)] > 0) & (depth[len(a) :] > 0)
    span = np.where(ok, np.linalg.norm(px[: len(a)] - px[len(a) :], axis=1), 0.0)
    span = np.where(kind == 1, 2.0 * math.pi * span, span)
    count = np.clip(np.ceil(span / SPACING), 4 * kind + 1, 4096).astype(np.int64)
    curve = np.repeat(np.arange(len(a)), count)
    first = np.repeat(np.cumsum(count) - count, count)
    u0 = (np.arange(len(curve)) - first) / count[curve]
    own = np.where(kind == 1, first_sphere_id(scene) + occluder[:, 1], -2)
    return (curve, u0, u0 + 1.0 / count[curve]), own


def _border_chords(scene, visibility, frame, size, curves, light):
    """Chords of the border in the image: start, end (m, 2) pixels, and per chord its curve
    (m,) and receiver (m,). ``curves``: every light's (``_light_silhouettes``, joined),
    ``light`` (c,) the light of each curve: all lights are followed together, one round of
    grazing rays for all of them. (The plain statement of ``bisect_chords``, which the
    renderer runs.)"""
    occluder, kind, a, b, axis = curves
    camera = scene.camera
    (curve, u0, u1), own = _starting_chords(scene, frame, curves)

    def sample(c, u):
        rows = (np.take(x, c, axis=0) for x in (kind, a, b, axis))  # faster than x[c]
        s = _curve_points(*rows, u)
        return _graze(visibility, scene.lights, light[c], frame, size, camera, s, own[c])

    p0, x0 = sample(curve, u0)
    p1, x1 = sample(curve, u1)
    chords = []
    for rounds in range(ROUNDS + 1):
        both = (p0 >= 0) & (p1 >= 0)
        length = np.where(both, np.linalg.norm(x1 - x0, axis=1), 0.0)
        curved = (kind[curve] == 1) | (p0 >= first_sphere_id(scene))  # a sphere casts or receives
        long = (p0 == p1) & both & (length > np.where(curved, CHORD, SPACING))
        change = (p0 != p1) & ~(both & (length < GAP))  # bisect towards where it changes
        split = (long | change) & (rounds < ROUNDS)
        done = ~split & (p0 == p1) & (p0 >= 0)
        chords.append((x0[done], x1[done], curve[done], p0[done]))
        if not split.any():
            break
        c, lo, hi = curve[split], u0[split], u1[split]
        mid = 0.5 * (lo + hi)
        pm, xm = sample(c, mid)
        curve = np.concatenate([c, c])
        u0, u1 = np.concatenate([lo, mid]), np.concatenate([mid, hi])
        p0, p1 = np.concatenate([p0[split], pm]), np.concatenate([pm, p1[split]])
        x0, x1 = np.concatenate([x0[split], xm]), np.concatenate([xm, x1[split]])
    return tuple(np.concatenate(part) for part in zip(*chords, strict=True))


@numba.njit(cache=True, error_model="numpy")
def _curve_point(kind, a, b, axis, u, out):
    """``_curve_points`` of one curve at parameter u, into out (3,)."""
    if kind == 1:
        phi = 2.0 * math.pi * u
        cos, sin = math.cos(phi), math.sin(phi)
        for c in range(3):
            out[c] = a[c] + cos * b[c] + sin * axis[c]
    else:
        for c in range(3):
            out[c] = a[c] + u * (b[c] - a[c])


@numba.njit(cache=True, error_model="numpy")
def _graze_one(bvh, where, point, s, own, frame, width, height, size, stack, stack_t, px):
    """``_graze`` of one point s (3,) of a curve of light ``where`` (a position if
    ``point``, else a unit direction): the receiver (-1: none) and its pixel position,
    written to px (2,)."""
    forward, right, up, eye = frame
    hit = np.empty(3)
    if point:
        d = np.empty(3)
        for c in range(3):
            d[c] = s[c] - where[c]
        prim, t, _, _ = closest_hit_ray(
            bvh, make_ray(where, d, 1.0 + START, np.inf), stack, stack_t
        )
        for c in range(3):
            hit[c] = where[c] + (t if prim >= 0 else 0.0) * d[c]
    else:
        ray = make_ray(s, where, START * size, np.inf)
        prim, t, _, _ = closest_hit_ray(bvh, ray, stack, stack_t)
        for c in range(3):
            hit[c] = s[c] + (t if prim >= 0 else 0.0) * where[c]
    if prim < 0:
        px[0] = px[1] = 0.0
        return -1
    rel = hit - eye
    depth = rel[0] * forward[0] + rel[1] * forward[1] + rel[2] * forward[2]
    rr = right[0] * right[0] + right[1] * right[1] + right[2] * right[2]
    uu = up[0] * up[0] + up[1] * up[1] + up[2] * up[2]
    x = (rel[0] * right[0] + rel[1] * right[1] + rel[2] * right[2]) / (depth * rr)
    y = (rel[0] * up[0] + rel[1] * up[1] + rel[2] * up[2]) / (depth * uu)
    if not (depth > 1e-7 * size) or prim == own:
        px[0] = px[1] = 0.0
        return -1
    px[0], px[1] = (x + 1.0) * (width / 2.0), (1.0 - y) * (height / 2.0)
    return prim


#: ``bisect_chords`` deals the starting chords to threads in this many blocks per thread
#: (the work per chord varies: a chord over a busy receiver is cut many times).
BLOCKS_PER_THREAD = 8
#: Rows of chords each block may write at first: this many per starting chord in it, and
#: SPARE_ROWS more (measured on the teapot and its ground, 32x32 to 512x512: at most 6.5
#: chords per starting chord beyond 64 at 512x512, 17 at 32x32, where blocks are short).
#: A block that needs more makes the whole pass run again with four times the room.
CHORDS_PER_START = 8
SPARE_ROWS = 1024


@numba.njit(cache=True, error_model="numpy", parallel=True)
def bisect_chords(
    bvh, curves, where, point, own, start, frame, width, height, size, first_sphere, n_threads,
    room,
):  # fmt: skip
    """``_border_chords``' bisection in one pass: each starting chord (``start`` = curve
    (n,), u0 (n,), u1 (n,)) followed depth first, the same tests and the same grazing rays
    (traced one by one in ``bvh``). ``curves`` = (kind, a, b, axis) per curve; ``where``
    (c, 3), ``point`` (c,) and ``own`` (c,) per curve. Returns the chords (x0 (m, 2), x1
    (m, 2), curve (m,), receiver (m,)): the same set as ``_border_chords``, in another
    order. tests/render/edges/test_shadow_edges.py ties the two.

    The starting chords are cut into blocks, dealt to ``n_threads`` threads
    (``numba.get_num_threads()``) in turn; each block writes its chords to its own rows of
    shared arrays (arrays, not a list of parts: Numba does not support lists written in a
    prange), and the blocks are read back in block order: the same rows in the same order
    on any number of threads."""
    n = len(start[0])
    n_blocks = max(1, min(n, BLOCKS_PER_THREAD * n_threads))
    bounds = (np.arange(n_blocks + 1) * n) // n_blocks
    n_jobs = min(n_blocks, max(1, n_threads))
    # ``room``: rows per block at first; 0 (the renderer) sizes them from ``n``, a positive
    # value (the tests) forces that many. A required argument: a default would make Numba
    # compile a second signature (the call with it omitted), ~5 s more on every fresh install.
    if room <= 0:
        room = CHORDS_PER_START * ((n + n_blocks - 1) // n_blocks) + SPARE_ROWS
    while True:
        x0s, x1s = np.empty((n_blocks * room, 2)), np.empty((n_blocks * room, 2))
        curve_out = np.empty(n_blocks * room, np.int64)
        receiver_out = np.empty(n_blocks * room, np.int64)
        count = np.empty(n_blocks, np.int64)
        for job in numba.prange(n_jobs):
            for block in range(job, n_blocks, n_jobs):
                count[block] = _bisect_block(
                    bvh, curves, where, point, own, start, bounds[block], bounds[block + 1],
                    frame, width, height, size, first_sphere,
                    (x0s, x1s, curve_out, receiver_out), block * room, room,
                )  # fmt: skip
        if np.all(count >= 0):
            break
        room *= 4  # some block ran out of rows: again, with more (the same chords)
    keep = np.empty(np.sum(count), np.int64)
    m = 0
    for block in range(n_blocks):
        keep[m : m + count[block]] = np.arange(block * room, block * room + count[block])
        m += count[block]
    return x0s[keep], x1s[keep], curve_out[keep], receiver_out[keep]


@numba.njit(cache=True, error_model="numpy")
def _bisect_block(
    bvh, curves, where, point, own, start, first, last, frame, width, height, size,
    first_sphere, out, offset, room,
):  # fmt: skip
    """``bisect_chords`` for the starting chords first..last - 1: their chords written to
    rows offset, offset + 1, ... of ``out`` = (x0, x1, curve, receiver). Returns how many,
    or -1 if they need more than ``room`` rows."""
    x0s, x1s, curve_out, receiver_out = out
    kind, a, b, axis = curves
    curve0, u0s, u1s = start
    stack = np.empty(bvh.stack_size, np.int64)
    stack_t = np.empty(bvh.stack_size)
    m = 0
    # A pending interval: (u0, u1, receiver and pixel at either end, its round).
    todo_u = np.empty((2 * ROUNDS + 4, 2))
    todo_p = np.empty((2 * ROUNDS + 4, 2), np.int64)
    todo_x = np.empty((2 * ROUNDS + 4, 4))
    todo_r = np.empty(2 * ROUNDS + 4, np.int64)
    s, px = np.empty(3), np.empty(2)
    for k in range(first, last):
        cv = curve0[k]
        curved_curve = kind[cv] == 1
        _curve_point(kind[cv], a[cv], b[cv], axis[cv], u0s[k], s)
        p_a = _graze_one(
            bvh, where[cv], point[cv], s, own[cv], frame, width, height, size, stack, stack_t, px
        )
        xa0, xa1 = px[0], px[1]
        _curve_point(kind[cv], a[cv], b[cv], axis[cv], u1s[k], s)
        p_b = _graze_one(
            bvh, where[cv], point[cv], s, own[cv], frame, width, height, size, stack, stack_t, px
        )
        todo_u[0, 0], todo_u[0, 1] = u0s[k], u1s[k]
        todo_p[0, 0], todo_p[0, 1] = p_a, p_b
        todo_x[0, 0], todo_x[0, 1], todo_x[0, 2], todo_x[0, 3] = xa0, xa1, px[0], px[1]
        todo_r[0] = 0
        n = 1
        while n > 0:
            n -= 1
            lo, hi = todo_u[n, 0], todo_u[n, 1]
            p0, p1 = todo_p[n, 0], todo_p[n, 1]
            x00, x01, x10, x11 = todo_x[n, 0], todo_x[n, 1], todo_x[n, 2], todo_x[n, 3]
            rounds = todo_r[n]
            both = p0 >= 0 and p1 >= 0
            length = math.sqrt((x10 - x00) ** 2 + (x11 - x01) ** 2) if both else 0.0
            curved = curved_curve or p0 >= first_sphere
            long = p0 == p1 and both and length > (CHORD if curved else SPACING)
            change = p0 != p1 and not (both and length < GAP)
            if (long or change) and rounds < ROUNDS:
                mid = 0.5 * (lo + hi)
                _curve_point(kind[cv], a[cv], b[cv], axis[cv], mid, s)
                pm = _graze_one(bvh, where[cv], point[cv], s, own[cv], frame, width, height,
                                size, stack, stack_t, px)  # fmt: skip
                # the upper half first on the stack, so the lower one is taken next
                todo_u[n, 0], todo_u[n, 1] = mid, hi
                todo_p[n, 0], todo_p[n, 1] = pm, p1
                todo_x[n, 0], todo_x[n, 1], todo_x[n, 2], todo_x[n, 3] = px[0], px[1], x10, x11
                todo_r[n] = rounds + 1
                todo_u[n + 1, 0], todo_u[n + 1, 1] = lo, mid
                todo_p[n + 1, 0], todo_p[n + 1, 1] = p0, pm
                todo_x[n + 1, 0], todo_x[n + 1, 1] = x00, x01
                todo_x[n + 1, 2], todo_x[n + 1, 3] = px[0], px[1]
                todo_r[n + 1] = rounds + 1
                n += 2
                continue
            if p0 == p1 and p0 >= 0:
                if m == room:
                    return -1
                r = offset + m
                x0s[r, 0], x0s[r, 1], x1s[r, 0], x1s[r, 1] = x00, x01, x10, x11
                curve_out[r], receiver_out[r] = cv, p0
                m += 1
    return m


# ---------------------------------------------------------------------------------------
# The edge function e(x) and its image gradient, off the tape
# ---------------------------------------------------------------------------------------


def _receiver_hits(receivers, directions, eye):
    """Depth t (k,), point P (k, 3) and surface normal n (k, 3) where rays eye + t d meet
    the planes of triangle receivers, or the near side of sphere receivers (``receivers``:
    ``_border_rows``)."""
    normal_or_centre, corner, radius = receivers
    t = np.full(len(radius), np.nan)
    normal = normal_or_centre.copy()
    tri, sph = np.flatnonzero(radius < 0), np.flatnonzero(radius >= 0)
    n, d = normal[tri], directions[tri]
    nd = np.einsum("ij,ij->i", n, d)
    t[tri] = np.einsum("ij,ij->i", n, corner[tri] - eye) / np.where(nd != 0, nd, np.nan)
    centre, r = normal_or_centre[sph], radius[sph]
    oc = eye - centre
    d = directions[sph]
    dd, bb = np.einsum("ij,ij->i", d, d), np.einsum("ij,ij->i", d, oc)
    disc = bb * bb - dd * (np.einsum("ij,ij->i", oc, oc) - r * r)
    t[sph] = np.where(disc >= 0, -bb - np.sqrt(np.maximum(disc, 0.0)), np.nan) / dd
    points = eye + t[:, None] * directions
    normal[sph] = points[sph] - centre
    return t, points, normal


def _border_function(occluders, light, points):
    """e (k,) and de/dP (k, 3) of the border (module docstring) at receiver points (k, 3)
    (``occluders``, ``light``: ``_border_rows``)."""
    kind, m, base, size = occluders
    where, point = light
    e, grad = np.einsum("ij,ij->i", m, points - base), m.copy()  # the edges' rows
    rows = np.flatnonzero(kind == 1)  # the spheres'
    c, r = base[rows], size[rows]
    if point:
        oc, u = where - c, points[rows] - where
        kappa = np.einsum("ij,ij->i", oc, oc) - r * r
        ou = np.einsum("ij,ij->i", u, oc)
        e[rows] = ou * ou - np.einsum("ij,ij->i", u, u) * kappa
        grad[rows] = 2.0 * ou[:, None] * oc - 2.0 * kappa[:, None] * u
    else:
        oc = points[rows] - c
        ow = oc @ where
        e[rows] = ow * ow - float(where @ where) * (np.einsum("ij,ij->i", oc, oc) - r * r)
        grad[rows] = 2.0 * ow[:, None] * where - 2.0 * float(where @ where) * oc
    return e, grad


def _border_gradient(frame, receivers, occluders, light, coords):
    """e (k,), its gradient with respect to image-plane (x, y) (k, 2), and the receiver
    points P (k, 3) and their depths (k,), at image-plane points (k, 2) (``receivers``,
    ``occluders``, ``light``: ``_border_rows``).
    P(d) = C + t(d) d on a surface with normal n at P has dP/dd = t (I - d n^T / (n . d))."""
    forward, right, up, eye = frame
    d = coords @ np.stack([right, up]) + forward  # x right + y up + forward
    t, points, normal = _receiver_hits(receivers, d, eye)
    e, g = _border_function(occluders, light, points)
    nd = np.einsum("ij,ij->i", normal, d)
    gd = t[:, None] * (g - (np.einsum("ij,ij->i", g, d) / nd)[:, None] * normal)
    return e, np.stack([gd @ right, gd @ up], axis=1), points, t


def _onto_border(frame, receivers, occluders, light, coords, steps=NEWTON_STEPS):
    """Image-plane points (k, 2) moved onto the border by Newton steps along grad e. (With
    ``_border_gradient``, the plain statement of ``border_newton``.)"""
    for _ in range(steps):
        e, grad = _border_gradient(frame, receivers, occluders, light, coords)[:2]
        norm2 = np.einsum("ij,ij->i", grad, grad)
        step = np.where(norm2 > 0, e / np.where(norm2 > 0, norm2, 1.0), 0.0)
        coords = coords - step[:, None] * grad
    return coords


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
    """Per point, what ``border_newton`` needs of its receiver and occluder (gathered once):
    receiver (plane normal or sphere centre (k, 3), a point on the plane (k, 3), radius
    (k,): -1 for a triangle) and occluder (kind (k,): 0 an edge, 1 a sphere; m (k, 3) and
    base (k, 3) of an edge's e = m . (P - base); a sphere's centre (k, 3) and radius
    (k,)), and the light (where (3,): position or direction; whether it is a point light)."""
    k = len(receiver)
    normal, corner, radius = _receiver_rows(scene, visibility, receiver)
    point = isinstance(light, PointLight)
    where = np.asarray(light.position.data if point else light.direction.data, np.float64)
    kind, m, base, size = np.zeros(k, np.int64), np.zeros((k, 3)), np.zeros((k, 3)), np.zeros(k)
    for index, mesh in enumerate(scene.meshes):
        rows = np.flatnonzero(occluder[:, 0] == index)
        vertices = np.asarray(mesh.vertices.data, np.float64)
        vi, vj = vertices[occluder[rows, 1]], vertices[occluder[rows, 2]]
        m[rows] = np.cross(vi - where, vj - where) if point else np.cross(vj - vi, where)
        base[rows] = where if point else vi
    for index, sphere in enumerate(scene.spheres):
        rows = np.flatnonzero((occluder[:, 0] < 0) & (occluder[:, 1] == index))
        kind[rows], base[rows] = 1, np.asarray(sphere.center.data, np.float64)
        size[rows] = float(sphere.radius.data)
    return (normal, corner, radius), (kind, m, base, size), (where, point)


@numba.njit(cache=True, error_model="numpy")
def border_newton(forward, right, up, eye, receivers, occluders, light, coords, steps):
    """``_onto_border`` and then ``_border_gradient`` in one pass over the points (the same
    arithmetic per point, in scalars): the points (k, 2) moved onto the border by ``steps``
    Newton steps along grad e, and there e (k,), its image-plane gradient (k, 2), the
    receiver points P (k, 3) and their depths t (k,). ``receivers``, ``occluders``,
    ``light``: ``_border_rows``. tests/render/edges/test_shadow_edges.py ties it to the
    NumPy functions."""
    normal, corner, radius = receivers
    kind, m, base, size = occluders
    where, point = light
    k = len(coords)
    moved, grad2 = coords.copy(), np.zeros((k, 2))
    e_out, points, depth = np.zeros(k), np.zeros((k, 3)), np.zeros(k)
    d, p, n, g, u = np.empty(3), np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    ww = where[0] * where[0] + where[1] * where[1] + where[2] * where[2]
    for i in range(k):
        for step in range(steps + 1):
            x, y = moved[i, 0], moved[i, 1]
            for c in range(3):
                d[c] = forward[c] + x * right[c] + y * up[c]
            # _receiver_hits: the depth t, the point P and the normal n there
            if radius[i] < 0:  # a triangle's plane
                for c in range(3):
                    n[c], u[c] = normal[i, c], corner[i, c] - eye[c]
                nd = n[0] * d[0] + n[1] * d[1] + n[2] * d[2]
                t = (n[0] * u[0] + n[1] * u[1] + n[2] * u[2]) / nd if nd != 0 else np.nan
                for c in range(3):
                    p[c] = eye[c] + t * d[c]
            else:  # a sphere's near side
                for c in range(3):
                    u[c] = eye[c] - normal[i, c]  # oc
                dd = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
                bb = d[0] * u[0] + d[1] * u[1] + d[2] * u[2]
                disc = bb * bb - dd * (u[0] * u[0] + u[1] * u[1] + u[2] * u[2] - radius[i] ** 2)
                t = (-bb - math.sqrt(max(disc, 0.0)) if disc >= 0 else np.nan) / dd
                for c in range(3):
                    p[c] = eye[c] + t * d[c]
                    n[c] = p[c] - normal[i, c]
            # _border_function: e and de/dP
            if kind[i] == 0:
                e = 0.0
                for c in range(3):
                    e += m[i, c] * (p[c] - base[i, c])
                    g[c] = m[i, c]
            elif point:
                for c in range(3):
                    n_oc = where[c] - base[i, c]
                    u[c] = p[c] - where[c]
                    g[c] = n_oc  # oc, for now
                kappa = g[0] * g[0] + g[1] * g[1] + g[2] * g[2] - size[i] ** 2
                ou = u[0] * g[0] + u[1] * g[1] + u[2] * g[2]
                e = ou * ou - (u[0] * u[0] + u[1] * u[1] + u[2] * u[2]) * kappa
                for c in range(3):
                    g[c] = 2.0 * ou * g[c] - 2.0 * kappa * u[c]
            else:
                for c in range(3):
                    u[c] = p[c] - base[i, c]  # oc
                ow = u[0] * where[0] + u[1] * where[1] + u[2] * where[2]
                e = ow * ow - ww * (u[0] * u[0] + u[1] * u[1] + u[2] * u[2] - size[i] ** 2)
                for c in range(3):
                    g[c] = 2.0 * ow * where[c] - 2.0 * ww * u[c]
            # the image-plane gradient: dP/dd = t (I - d n^T / (n . d))
            nd = n[0] * d[0] + n[1] * d[1] + n[2] * d[2]
            gd_scale = (g[0] * d[0] + g[1] * d[1] + g[2] * d[2]) / nd
            for c in range(3):
                u[c] = t * (g[c] - gd_scale * n[c])
            gx = u[0] * right[0] + u[1] * right[1] + u[2] * right[2]
            gy = u[0] * up[0] + u[1] * up[1] + u[2] * up[2]
            if step == steps:
                e_out[i], grad2[i, 0], grad2[i, 1], depth[i] = e, gx, gy, t
                for c in range(3):
                    points[i, c] = p[c]
                break
            norm2 = gx * gx + gy * gy
            shift = e / norm2 if norm2 > 0 else 0.0
            moved[i, 0], moved[i, 1] = x - shift * gx, y - shift * gy
    return moved, e_out, grad2, points, depth


# ---------------------------------------------------------------------------------------
# The points and the term
# ---------------------------------------------------------------------------------------


@dataclass
class BorderChords:
    """The shadow borders of one render as image segments (off the tape): start, end (k, 2)
    pixel coordinates; per chord its light (k,), occluder (k, 3) (as in ``ShadowPoints``)
    and receiver (k,)."""

    start: np.ndarray
    end: np.ndarray
    light: np.ndarray
    occluder: np.ndarray
    receiver: np.ndarray


def border_chords(
    scene: Scene, visibility: Visibility, frame, topology, shared=None
) -> BorderChords:
    """The chords of every light's shadow borders (module docstring); ``topology``:
    ``mesh_edges`` per mesh; ``shared``: the edges meshes share
    (``render.trace.seams.shared_edges``, None: none). None of them without shadows."""
    plain = plain_camera(frame)
    size = max(visibility.size, 1e-300)
    parts = []
    edge_faces = (
        _edge_faces(scene, topology, shared) if visibility.shadows and scene.lights else None
    )
    for j, light in enumerate(scene.lights if visibility.shadows else []):
        curves = _light_silhouettes(scene, topology, light, edge_faces, shared)
        parts.append((*curves, np.full(len(curves[0]), j)))
    if parts:
        *curves, light = (np.concatenate(p) for p in zip(*parts, strict=True))
    if not parts or len(light) == 0:
        empty = np.zeros(0, np.int64)
        return BorderChords(np.zeros((0, 2)), np.zeros((0, 2)), empty,
                            np.zeros((0, 3), np.int64), empty)  # fmt: skip
    start, own = _starting_chords(scene, plain, curves)
    towards = np.array([_towards(x) for x in scene.lights])
    point = np.array([isinstance(x, PointLight) for x in scene.lights])
    camera = scene.camera
    x0, x1, curve, receiver = bisect_chords(
        visibility.accelerator().flat_tree(), tuple(curves[1:]), towards[light], point[light],
        own, start, plain, camera.width, camera.height, size, first_sphere_id(scene),
        numba.get_num_threads(), 0,
    )  # fmt: skip
    return BorderChords(x0, x1, light[curve], curves[0][curve], receiver)


def _towards(light) -> np.ndarray:
    """(3,): a point light's position, or a directional light's unit direction."""
    if isinstance(light, PointLight):
        return np.asarray(light.position.data, np.float64)
    w = np.asarray(light.direction.data, np.float64)
    return w / np.linalg.norm(w)


def shadow_points(
    scene: Scene, visibility: Visibility, frame, chords: BorderChords, pieces, radiance
) -> ShadowPoints:
    """The quadrature points of the shadow borders with their constant factors
    (``BoundaryPoints``): ``pieces`` = (chord (m,), image-plane coords (m, 2), weight (m,),
    pixel (m,)) of the points on ``chords`` (``boundary_points``' extra curves);
    ``radiance``: what the camera sees either side (``boundary.DirectRadiance``). The
    points are moved onto their light's border light by light, and the radiance on either
    side is asked for all of them at once."""
    plain = plain_camera(frame)
    chord, coords, weight, pixel = pieces
    light, occluder = chords.light[chord], np.take(chords.occluder, chord, axis=0)
    receiver = chords.receiver[chord]
    moved, t = coords.copy(), np.full(len(chord), np.nan)
    grad = np.zeros((len(chord), 2))
    for j, source in enumerate(scene.lights):
        rows = np.flatnonzero(light == j)
        if len(rows) == 0:
            continue
        rows_of = _border_rows(scene, visibility, source, np.take(occluder, rows, axis=0),
                               receiver[rows])  # fmt: skip
        moved[rows], _, grad[rows], _, t[rows] = border_newton(
            *plain, *rows_of, np.ascontiguousarray(coords[rows]), NEWTON_STEPS
        )
    factor = _border_factors(scene, visibility, plain, receiver, moved, grad, t, weight, radiance)
    keep = np.flatnonzero(np.any(factor != 0.0, axis=1))
    return ShadowPoints(np.take(moved, keep, axis=0), pixel[keep], np.take(factor, keep, axis=0),
                        light[keep], receiver[keep], np.take(occluder, keep, axis=0))  # fmt: skip


def _border_factors(
    scene, visibility, frame, receiver, coords, grad, t, weight, radiance
) -> np.ndarray:
    """(k, 3): w (f_+ - f_-) / |grad e| at k points ``coords`` (k, 2) on the borders, where
    e has the image-plane gradient ``grad`` (k, 2) and the camera ray meets the
    ``receiver`` (k,) at depth ``t`` (k,) (``_border_gradient``); zero where the camera
    does not see the receiver there or the border is degenerate."""
    forward, right, up, eye = frame
    norm, step = _pixel_gradient(grad, scene.camera.width, scene.camera.height)
    seen = np.isfinite(t) & (t > 0) & (norm > 0)
    rows = np.flatnonzero(seen)
    at = np.take(coords, rows, axis=0)
    hidden = _hidden(
        visibility, frame, scene.camera, at, camera_directions(at, right, up, forward), t[rows],
        norm[rows], receiver[rows],
    )  # fmt: skip
    rows, at = rows[~hidden], at[~hidden]
    shift = EPSILON * np.take(step, rows, axis=0)
    both = np.concatenate([at + shift, at - shift])
    keys = np.concatenate([rows, rows])
    # Both sides shaded on the receiver itself (the border point is seen on it): rays
    # traced there would cross any curve of primary visibility within EPSILON of the
    # border and add its jump. Where a triangle passes through a sphere, the sphere's
    # shadow border on it is tangent to the curve of the cut, and along a stretch the
    # traced rays saw the triangle on one side and the sphere on the other.
    on = np.concatenate([receiver[rows], receiver[rows]])
    depth, _, _ = _receiver_hits(
        _receiver_rows(scene, visibility, on), camera_directions(both, right, up, forward), eye
    )
    found = np.isfinite(depth) & (depth > 0)
    f = np.empty((len(both), 3))
    inside, outside = np.flatnonzero(found), np.flatnonzero(~found)
    f[inside] = radiance.seen(
        np.take(both, inside, axis=0), on[inside], depth[inside], keys[inside]
    )
    if len(outside):  # a side ray beside a sphere receiver's outline: what is seen there
        f[outside] = radiance.along(np.take(both, outside, axis=0), keys[outside])
    out = np.zeros((len(coords), 3))
    out[rows] = (weight[rows] / norm[rows])[:, None] * (f[: len(rows)] - f[len(rows) :])
    return out


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
        t = dot_last(n, a - eye) / dot_last(n, dt)
        parts.append(eye + as_column(t) * dt)
        order.append(tri)
    for index, sphere in enumerate(scene.spheres):
        rows = np.flatnonzero(receiver == n_tri + index)
        if len(rows) == 0:
            continue
        dt = d[rows]
        oc = eye - sphere.center
        dd, bb = dot_last(dt, dt), dot_last(dt, oc)
        kappa = md.dot(oc, oc) - sphere.radius * sphere.radius
        t = (-bb - md.sqrt(bb * bb - dd * kappa)) / dd
        parts.append(eye + as_column(t) * dt)
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
        point = isinstance(light, PointLight)
        where = light.position if point else light.direction
        for k, mesh in enumerate(scene.meshes):
            rows = np.flatnonzero(mine & (points.occluder[:, 0] == k))
            if len(rows) == 0:
                continue
            p = _receiver_points_tape(scene, d[rows], eye, points.receiver[rows])
            vi = mesh.vertices[points.occluder[rows, 1]]
            vj = mesh.vertices[points.occluder[rows, 2]]
            if point:
                m = md.cross(vi - where, vj - where)
                parts.append(md.dot(m, p - where))
            else:
                m = md.cross(vj - vi, where)
                parts.append(md.dot(m, p - vi))
            order.append(rows)
        for index, sphere in enumerate(scene.spheres):
            on = (points.occluder[:, 0] < 0) & (points.occluder[:, 1] == index)
            rows = np.flatnonzero(mine & on)
            if len(rows) == 0:
                continue
            p = _receiver_points_tape(scene, d[rows], eye, points.receiver[rows])
            r2 = sphere.radius * sphere.radius
            if point:
                oc, u = where - sphere.center, p - where
                ou = md.dot(u, oc)
                parts.append(ou * ou - md.dot(u, u) * (md.dot(oc, oc) - r2))
            else:
                oc = p - sphere.center
                ow = md.dot(oc, where)
                parts.append(ow * ow - md.dot(where, where) * (md.dot(oc, oc) - r2))
            order.append(rows)
    if not parts:
        return None
    return (md.concatenate(parts) if len(parts) > 1 else parts[0]), np.concatenate(order)
