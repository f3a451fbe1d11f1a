"""Finding the shadow borders of the boundary term, off the tape: curves of secondary
visibility as image segments (``border_chords``).

A point light L casts past an occluder's silhouette *as seen from the light* a shadow whose
border, on the receiving surface, is where the light's ray to the receiver point grazes the
occluder (``render.edges.boundary.shadow_border`` writes that border's edge function e and
adds its term). Each silhouette curve of each occluder seen from the light (mesh edges whose
faces all lie on one side of the plane the edge sweeps in the light, open edges, a sphere's
circle of tangency: ``render.trace.outlines``, which finds the path integrator's soft
shadows' edges too; ``_light_silhouettes``) is followed by rays from the light that graze
it; where such a ray goes on to hit a receiver, it marks a point of the border.
Consecutive points on one receiver triangle are joined by a chord, exact while the occluder
is an edge and the receiver a triangle (the border is then straight), and at most ``CHORD``
pixels long otherwise; where the receiver changes, the curve parameter is bisected until
the gap is below ``GAP`` pixels (``bisect_chords``, one compiled pass; its plain NumPy
statement, round by round, is ``tests/render/edges/shadow_reference.py``, and a test ties
the two).

Not included: shadow borders seen in mirrors, and a receiver narrower than the spacing of
the grazing rays: they start ``SPACING`` pixels apart along the occluder's image and are
refined where the border they draw is longer than that, but a small receiver between two
rays that both miss it, or both hit the same other one, is not seen.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from minidiff.threads import borrowing, job_count, kernel, run_jobs
from render.edges.boundary.pixels import JUNCTION
from render.scene.camera import plain_camera, project
from render.scene.lights import POINT, Light
from render.scene.scene import Scene
from render.trace.intersect import BLOCK, closest_hit_one, n_blocks
from render.trace.outlines import Outlines, one_sided
from render.trace.primitives import first_sphere_id
from render.trace.visibility import Visibility

#: Where the border is curved (a sphere casts it or receives it), chords at most this long.
CHORD = 0.5
#: Grazing rays along a silhouette are at most this far apart, in image pixels, while they
#: hit the same receiver (so that a small receiver between two of them is rarely missed).
SPACING = 2.0
#: Where the receiver changes between two grazing rays, bisect until they are this close:
#: half the reach of a T-junction (``pixels.JUNCTION``), so that the curve where the
#: receiver changes (a crease of a faceted receiver) is cut where the border meets it.
GAP = JUNCTION / 2
#: Bisection rounds at most. A chord is at most SPACING = 2 pixels long at the start, so
#: after 20 halvings what is left of one whose receiver jumps (the border falls off one
#: surface onto another farther away, and the two ends never come within GAP) is ~2e-6
#: pixels of the border: dropping it changes the term by ~1e-6 of one pixel's share.
#: (30 rounds changed gradients by < 1e-7 relative on the teapot and its ground, and cost
#: 10 more rounds of grazing rays for the few dozen chords at such jumps.)
ROUNDS = 20
#: Grazing rays start this fraction of the way beyond the occluder (off its own surface).
START = 1e-7


@dataclass
class BorderChords:
    """The shadow borders of one render as image segments (off the tape): start, end (k, 2)
    pixel coordinates; per chord its light (k,) (an index into ``scene.lights``), occluder
    (k, 3) int64 ((mesh index, v_i, v_j) of an occluder edge, v_i and v_j among every
    mesh's vertices as ``Outlines.ends`` has them, or (-1, sphere index, -1) of an occluder
    sphere), receiver (k,) (the primitive, global id, the border lies on) and crack (k,)
    (the occluder edge's ``Outlines.crack``: its side samples must pass farther)."""

    start: np.ndarray
    end: np.ndarray
    light: np.ndarray
    occluder: np.ndarray
    receiver: np.ndarray
    crack: np.ndarray


# ---------------------------------------------------------------------------------------
# The silhouettes as seen from the light, as curves S(u), u in [0, 1]
# ---------------------------------------------------------------------------------------


def _light_silhouettes(outlines: Outlines, light: Light, first_sphere: int):
    """Occluder curves of one light, among the scene's ``outlines`` (``render.trace.
    outlines``: the edges whose faces lie on one side of the plane the edge sweeps in the
    light, ``Light.edge_plane``; the spheres' circles of tangency, ``Light.sphere_outline``):
    (occluder (c, 3) int64 as in ``BorderChords``, curve kind per row: 0 a segment from
    ``a`` to ``b`` (c, 3), 1 a circle centre ``a``, radius vector ``b`` and second axis
    ``axis`` (c, 3), ``own`` (c, 2) the primitives a ray grazing the curve meets only
    by rounding: an edge's two faces, a sphere's id twice, and ``crack`` (c,), an edge's
    ``Outlines.crack``, 0 for a sphere; ``first_sphere``: the first sphere's primitive
    id)."""
    m, base = light.edge_plane(outlines.a, outlines.b)
    keep = np.flatnonzero(one_sided(m, base, outlines.c)[0])
    rows = [np.stack([outlines.edge_object[keep], *outlines.ends[keep].T], axis=1)]
    a, b, axis = [outlines.a[keep]], [outlines.b[keep]], [np.zeros((len(keep), 3))]
    own, crack = [outlines.faces[keep]], [outlines.crack[keep]]
    for index, (centre, r) in enumerate(zip(outlines.centre, outlines.radius, strict=True)):
        circle = light.sphere_outline(centre, float(r))
        if circle is None:
            continue  # the light inside the sphere: everything outside is dark
        rows.append(np.array([[-1, index, -1]]))
        own.append(np.full((1, 2), first_sphere + index))
        crack.append(np.zeros(1))
        for out, x in zip((a, b, axis), circle, strict=True):
            out.append(x[None])
    occluder = np.concatenate(rows).astype(np.int64)
    kind = (occluder[:, 0] < 0).astype(np.int64)
    return (occluder, kind, np.concatenate(a), np.concatenate(b), np.concatenate(axis),
            np.concatenate(own).astype(np.int64), np.concatenate(crack))  # fmt: skip


# ---------------------------------------------------------------------------------------
# Following the border: grazing rays, bisection, chords (``bisect_chords``)
# ---------------------------------------------------------------------------------------


def _starting_chords(scene, frame, curves):
    """Where the grazing rays start: each curve at 2 points plus one per SPACING pixels of
    its image from the camera, as chords (curve (n,), u0 (n,), u1 (n,))."""
    occluder, kind, a, b, axis = curves[:5]
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
    return curve, u0, u0 + 1.0 / count[curve]


@borrowing
def _curve_point(kind, a, b, axis, cv, u):
    """The point S(u) (a 3-tuple) of curve ``cv`` (rows of kind, a, b, axis: kind 0 the
    segment from a to b; 1 the circle with centre a, radius vector b and second axis
    ``axis``) at parameter u in [0, 1]."""
    if kind[cv] == 1:
        phi = 2.0 * math.pi * u
        cos, sin = math.cos(phi), math.sin(phi)
        return (a[cv, 0] + cos * b[cv, 0] + sin * axis[cv, 0],
                a[cv, 1] + cos * b[cv, 1] + sin * axis[cv, 1],
                a[cv, 2] + cos * b[cv, 2] + sin * axis[cv, 2])  # fmt: skip
    return (a[cv, 0] + u * (b[cv, 0] - a[cv, 0]), a[cv, 1] + u * (b[cv, 1] - a[cv, 1]),
            a[cv, 2] + u * (b[cv, 2] - a[cv, 2]))  # fmt: skip


@borrowing
def _graze_one(bvh, where, point, own, cv, s, frame, width, height, size, first_sphere, stack,
               stack_t):  # fmt: skip
    """Where the light of curve ``cv`` sends the ray grazing the point s (a 3-tuple) of the
    curve on to hit: (receiver, x, y), the receiver -1 (nothing, behind the camera, or the
    sphere grazed) or its pixel position (x, y) (0, 0 for -1). ``where[cv]``: the light's
    position if ``point[cv]``, else its unit direction; ``own[cv]``: what the ray meets only
    by rounding (``_light_silhouettes``). (Scalars and tuples only: arrays allocated per
    ray cost more than the arithmetic around the trace, and cost the cold start their
    compiling.)"""
    forward, right, up, eye = frame
    # One traversal for both kinds of light (``closest_hit_one``: the one compiled copy the
    # path kernel calls too): from a light at a point the ray leaves the light towards s,
    # from a light at infinity it leaves s along the light's direction.
    w = (where[cv, 0], where[cv, 1], where[cv, 2])
    if point[cv]:
        o = w
        d = (s[0] - w[0], s[1] - w[1], s[2] - w[2])
        tmin = 1.0 + START
    else:
        o = s
        d = w
        tmin = START * size
    prim, t, _, _ = closest_hit_one(bvh, o, d, tmin, stack, stack_t)
    for _ in range(2):
        # A face of the edge grazed: the ray through the edge meets its plane nowhere else,
        # so it met the face by rounding, or across a crack where the meshes that share
        # the edge meet (float32 vertices: 1e-8 apart). The ray goes on beyond it.
        if prim < 0 or prim >= first_sphere or (prim != own[cv, 0] and prim != own[cv, 1]):
            break
        prim, t, _, _ = closest_hit_one(bvh, o, d, t, stack, stack_t)
    if prim < 0:
        return -1, 0.0, 0.0
    h0, h1, h2 = o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]
    r0, r1, r2 = h0 - eye[0], h1 - eye[1], h2 - eye[2]
    depth = r0 * forward[0] + r1 * forward[1] + r2 * forward[2]
    rr = right[0] * right[0] + right[1] * right[1] + right[2] * right[2]
    uu = up[0] * up[0] + up[1] * up[1] + up[2] * up[2]
    x = (r0 * right[0] + r1 * right[1] + r2 * right[2]) / (depth * rr)
    y = (r0 * up[0] + r1 * up[1] + r2 * up[2]) / (depth * uu)
    if not (depth > 1e-7 * size) or prim == own[cv, 0]:  # the sphere grazed
        return -1, 0.0, 0.0
    return prim, (x + 1.0) * (width / 2.0), (1.0 - y) * (height / 2.0)


#: Rows of chords each block of starting chords (BLOCK of them, ``bisect_chords``) may
#: write at first: this many per starting chord in it, and SPARE_ROWS more (measured on the
#: teapot and its ground, 32x32 to 512x512: at most 6.5 chords per starting chord beyond 64
#: at 512x512, 17 at 32x32). A block that needs more makes the whole pass run again with
#: four times the room.
CHORDS_PER_START = 8
SPARE_ROWS = 1024


def bisect_chords(
    bvh, curves, where, point, own, start, frame, width, height, size, first_sphere,
    room: int = 0,
):  # fmt: skip
    """The border's chords, bisected: each starting chord (``start`` = curve (n,), u0 (n,),
    u1 (n,)) followed depth first, one grazing ray at a time (traced in ``bvh``): a chord
    over one receiver longer than SPACING (CHORD where a sphere casts or receives) is
    halved, and one whose ends see different receivers is halved until they are GAP apart,
    ROUNDS times at most. ``curves`` = (kind, a, b, axis) per curve; ``where``
    (c, 3), ``point`` (c,) and ``own`` (c, 2) per curve. Returns the chords (x0 (m, 2), x1
    (m, 2), curve (m,), receiver (m,)). ``tests/render/edges/shadow_reference.py`` states
    the same bisection round by round in NumPy, and test_shadow_edges.py ties the two.

    The starting chords are cut into blocks of BLOCK, dealt to the jobs in turn as
    ``render.trace.intersect`` deals rays (the work per chord varies: a chord over a busy
    receiver is cut many times); each block writes its chords to its own ``room`` rows of
    shared arrays, and the blocks are read back in block order: the same rows in the same
    order on any number of threads. ``room``: rows per block at first; 0 sizes them from
    ``n`` (a positive value, for the tests, forces that many)."""
    n = len(start[0])
    blocks = max(1, -(-n // BLOCK))
    # The frame's vectors as tuples of floats: the kernels read them without reference
    # counts, and compile no array arguments for them.
    axes = tuple((float(v[0]), float(v[1]), float(v[2])) for v in frame)
    if room <= 0:
        room = CHORDS_PER_START * min(n, BLOCK) + SPARE_ROWS
    while True:
        out = (np.empty((blocks * room, 2)), np.empty((blocks * room, 2)),
               np.empty(blocks * room, np.int64), np.empty(blocks * room, np.int64))  # fmt: skip
        count = np.empty(blocks, np.int64)
        run_jobs(
            _bisect_blocks, job_count(n, BLOCK), bvh, curves, where, point, own, start, axes,
            width, height, size, first_sphere, out, room, count,
        )  # fmt: skip
        if np.all(count >= 0):
            break
        room *= 4  # some block ran out of rows: again, with more (the same chords)
    # Each block's first count[block] rows, block after block.
    total = int(count.sum())
    keep = np.repeat(np.arange(blocks) * room - (np.cumsum(count) - count), count) + np.arange(
        total
    )
    return tuple(x[keep] for x in out)


@kernel
def _bisect_blocks(
    job, n_jobs, bvh, curves, where, point, own, start, frame, width, height, size,
    first_sphere, out, room, count,
):  # fmt: skip
    """Job ``job`` of ``n_jobs`` (``minidiff.threads.run_jobs``) of ``bisect_chords``: its
    blocks of starting chords, block ``k``'s chords written to rows k * room, ... of ``out``
    and their number to ``count[k]`` (-1 if they need more than ``room`` rows)."""
    n = start[0].shape[0]
    # The job's scratch: the traversal's stack, and the pending intervals (u0, u1, receiver
    # and pixel at either end, round).
    scratch = (np.empty(bvh.stack_size, np.int64), np.empty(bvh.stack_size),
               np.empty((2 * ROUNDS + 4, 2)), np.empty((2 * ROUNDS + 4, 2), np.int64),
               np.empty((2 * ROUNDS + 4, 4)), np.empty(2 * ROUNDS + 4, np.int64))  # fmt: skip
    for block in range(job, max(1, n_blocks(n)), n_jobs):
        count[block] = _bisect_block(
            bvh, curves, where, point, own, start, block * BLOCK, min(n, (block + 1) * BLOCK),
            frame, width, height, size, first_sphere, out, block * room, room, scratch,
        )  # fmt: skip


@borrowing
def _bisect_block(
    bvh, curves, where, point, own, start, first, last, frame, width, height, size,
    first_sphere, out, offset, room, scratch,
):  # fmt: skip
    """``bisect_chords`` for the starting chords first..last - 1: their chords written to
    rows offset, offset + 1, ... of ``out`` = (x0, x1, curve, receiver). Returns how many,
    or -1 if they need more than ``room`` rows. (Without reference counts: its scratch
    comes from ``_bisect_blocks``.)"""
    x0s, x1s, curve_out, receiver_out = out
    kind, a, b, axis = curves
    curve0, u0s, u1s = start
    stack, stack_t, todo_u, todo_p, todo_x, todo_r = scratch
    m = 0
    for k in range(first, last):
        cv = curve0[k]
        curved_curve = kind[cv] == 1
        s = _curve_point(kind, a, b, axis, cv, u0s[k])
        p_a, xa0, xa1 = _graze_one(bvh, where, point, own, cv, s, frame, width, height, size,
                                   first_sphere, stack, stack_t)  # fmt: skip
        s = _curve_point(kind, a, b, axis, cv, u1s[k])
        p_b, xb0, xb1 = _graze_one(bvh, where, point, own, cv, s, frame, width, height, size,
                                   first_sphere, stack, stack_t)  # fmt: skip
        todo_u[0, 0], todo_u[0, 1] = u0s[k], u1s[k]
        todo_p[0, 0], todo_p[0, 1] = p_a, p_b
        todo_x[0, 0], todo_x[0, 1], todo_x[0, 2], todo_x[0, 3] = xa0, xa1, xb0, xb1
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
                pm, xm0, xm1 = _graze_one(bvh, where, point, own, cv,
                                          _curve_point(kind, a, b, axis, cv, mid), frame,
                                          width, height, size, first_sphere, stack,
                                          stack_t)  # fmt: skip
                # the upper half first on the stack, so the lower one is taken next
                todo_u[n, 0], todo_u[n, 1] = mid, hi
                todo_p[n, 0], todo_p[n, 1] = pm, p1
                todo_x[n, 0], todo_x[n, 1], todo_x[n, 2], todo_x[n, 3] = xm0, xm1, x10, x11
                todo_r[n] = rounds + 1
                todo_u[n + 1, 0], todo_u[n + 1, 1] = lo, mid
                todo_p[n + 1, 0], todo_p[n + 1, 1] = p0, pm
                todo_x[n + 1, 0], todo_x[n + 1, 1] = x00, x01
                todo_x[n + 1, 2], todo_x[n + 1, 3] = xm0, xm1
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


def border_chords(scene: Scene, visibility: Visibility, frame, outlines: Outlines) -> BorderChords:
    """The chords of every light's shadow borders (module docstring); ``outlines``: the
    scene's curves that can be outlines (``render.trace.outlines.Outlines``). None of them
    without shadows."""
    plain = plain_camera(frame)
    size = max(visibility.size, 1e-300)
    parts = []
    for j, light in enumerate(scene.lights if visibility.shadows else []):
        curves = _light_silhouettes(outlines, light, first_sphere_id(scene))
        parts.append((*curves, np.full(len(curves[0]), j)))
    if parts:
        *curves, light = (np.concatenate(p) for p in zip(*parts, strict=True))
    if not parts or len(light) == 0:
        empty = np.zeros(0, np.int64)
        return BorderChords(np.zeros((0, 2)), np.zeros((0, 2)), empty,
                            np.zeros((0, 3), np.int64), empty, np.zeros(0))  # fmt: skip
    start = _starting_chords(scene, plain, curves)
    # The kernel's grazing rays: from a point light's position, or along a light's unit
    # direction of travel.
    kinds, towards = zip(*(x.pack(unit=True) for x in scene.lights), strict=True)
    point, towards = np.array(kinds) == POINT, np.array(towards)
    camera = scene.camera
    x0, x1, curve, receiver = bisect_chords(
        visibility.accelerator().flat_tree(), tuple(curves[1:5]), towards[light], point[light],
        curves[5], start, plain, camera.width, camera.height, size, first_sphere_id(scene),
    )  # fmt: skip
    return BorderChords(x0, x1, light[curve], curves[0][curve], receiver, curves[6][curve])
