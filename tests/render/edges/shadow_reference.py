"""Plain NumPy statements of compiled shadow-border code, for the tests that tie the two.

``border_chords`` is ``render.edges.boundary.shadow_tracing.bisect_chords`` round by round:
every pending chord of every curve is halved at once, its grazing rays traced in one call
per kind of light (``graze``), where the kernel follows each starting chord depth first,
one ray at a time. Both must find the same chords (in another order).
"""

from __future__ import annotations

import math

import numpy as np

from render.edges.boundary.shadow_tracing import CHORD, GAP, ROUNDS, SPACING, START
from render.scene.camera import project


def curve_points(kind, a, b, axis, u):
    """Points S(u) (k, 3) of curves (rows of kind, a, b, axis: a segment from a to b, or a
    circle with centre a, radius vector b and second axis ``axis``) at parameters u (k,)."""
    phi = 2.0 * math.pi * u[:, None]
    circle = a + np.cos(phi) * b + np.sin(phi) * axis
    return np.where(kind[:, None] == 1, circle, a + u[:, None] * (b - a))


def graze(visibility, where, point, s, own, frame, width, height, size, first_sphere):
    """Where the light's rays grazing the points s (k, 3) go on to hit: receiver (k,) (-1:
    nothing, behind the camera, or the sphere grazed) and its pixel position (k, 2). Per
    point its light: ``where`` (k, 3), a position where ``point`` (k,), else a unit
    direction, and ``own`` (k, 2), what it meets only by rounding: a ray that meets a face
    of the edge grazed goes on beyond it (twice at most), one that meets the sphere grazed
    counts as meeting nothing. The rays from point lights are traced in one call, the
    others in another; those that go on, one at a time."""
    prim, hit = np.full(len(s), -1), np.zeros_like(s)
    accelerator = visibility.accelerator()
    for rows in (np.flatnonzero(point), np.flatnonzero(~point)):
        if len(rows) == 0:
            continue
        at, w = np.take(s, rows, axis=0), np.take(where, rows, axis=0)
        if point[rows[0]]:  # from the light through the point, on beyond it
            o, d, tmin = w, at - w, 1.0 + START
        else:  # from the point along the light's (unit) direction
            o, d, tmin = at, w, START * size
        p, t, _, _ = accelerator.closest_hit(o, d, tmin=tmin)
        for _ in range(2):
            again = np.flatnonzero((p >= 0) & (p < first_sphere)
                                   & np.any(p[:, None] == own[rows], axis=1))  # fmt: skip
            for r in again:
                p[r : r + 1], t[r : r + 1], _, _ = accelerator.closest_hit(
                    o[r : r + 1], d[r : r + 1], tmin=float(t[r]))  # fmt: skip
        hit[rows] = o + np.where(p >= 0, t, 0.0)[:, None] * d
        prim[rows] = p
    px, depth = project(np.where(prim[:, None] >= 0, hit, s), frame, width, height)
    prim = np.where((prim >= 0) & (depth > 1e-7 * size) & (prim != own[:, 0]), prim, -1)
    return prim, np.where(prim[:, None] >= 0, px, 0.0)


def border_chords(visibility, curves, where, point, own, start, frame, width, height, size,
                  first_sphere):  # fmt: skip
    """``bisect_chords``' chords (x0 (m, 2), x1 (m, 2), curve (m,), receiver (m,)), found
    round by round; the same arguments but ``visibility`` for the kernel's tree."""
    kind, a, b, axis = curves
    curve, u0, u1 = start

    def sample(c, u):
        s = curve_points(*(np.take(x, c, axis=0) for x in (kind, a, b, axis)), u)
        return graze(
            visibility, where[c], point[c], s, own[c], frame, width, height, size, first_sphere
        )

    p0, x0 = sample(curve, u0)
    p1, x1 = sample(curve, u1)
    chords = []
    for rounds in range(ROUNDS + 1):
        both = (p0 >= 0) & (p1 >= 0)
        length = np.where(both, np.linalg.norm(x1 - x0, axis=1), 0.0)
        curved = (kind[curve] == 1) | (p0 >= first_sphere)  # a sphere casts or receives
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
