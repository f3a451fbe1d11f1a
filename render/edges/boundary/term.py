"""The boundary term: every curve kind's quadrature points, and the term on the tape.

``boundary_points`` asks each curve kind (``render.edges.boundary.curves``) for its curves,
cuts them all together at pixel borders and where they cross (``render.edges.boundary.
pixels``), puts the quadrature points on the pieces and hands each kind back the points on
its own curves, for their constant factors. ``boundary_term`` then adds, for every kind, c_g
(e(x_g; theta) - detach(e(x_g; theta))) to the image: zero in value, the boundary term in
derivative. ``add_curve_terms`` does both for one render; ``curve_points`` and
``with_boundary_term`` are its two halves, for a caller that finds the points apart (the
direct renderer, on a second thread: ``render.edges.terms.boundary_points_of``).
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import partial

import numpy as np

import minidiff as md
from minidiff.threads import share_tasks
from render.edges.boundary.curves import CurveKind, CurvePoints, OnCurves, View
from render.edges.boundary.kind_points import kind_points
from render.edges.boundary.occlusion import Occluders
from render.edges.boundary.pixels import pixel_pieces, split_at_crossings
from render.edges.boundary.radiance import SideRadiance
from render.scene.camera import plain_frame
from render.scene.scene import Scene
from render.shade.hits import working_dtype


def boundary_points(view: View, kinds: Sequence[CurveKind]) -> list[CurvePoints]:
    """Each kind's quadrature points with their constant factors (``CurvePoints``, one per
    kind, in the order of ``kinds``). A point's key (its name for the ``SideRadiance``) is
    its row among all kinds' points before any are dropped: it depends on the order of
    ``kinds``, which the caller keeps fixed (``kind_points`` deals them out)."""
    camera = view.scene.camera
    width, height = camera.width, camera.height
    curves = [kind.curves(view) for kind in kinds]
    p0 = np.concatenate([np.zeros((0, 2))] + [c.start for c in curves])
    p1 = np.concatenate([np.zeros((0, 2))] + [c.end for c in curves])
    pieces = split_at_crossings(p0, p1, *pixel_pieces(p0, p1, width, height))
    counts = np.array([len(c.start) for c in curves], np.int64)
    tasks = []
    for kind, mine, (segment, coords, pixel, weight, rows) in zip(
        kinds, curves, kind_points(p0, p1, pieces, counts, width, height), strict=True
    ):
        on = OnCurves(mine.label[segment], coords, pixel, weight, rows)
        if len(rows) and kind.moves(view.scene):
            tasks.append(partial(kind.points, view, on))
        else:  # no points on this kind's curves, or a term zero in derivative
            tasks.append(partial(CurvePoints.nonzero, on, np.zeros((0, 3)), on.coords))
    # Each kind's points apart: a thread that has ended its own step may take some
    # (the direct renderer's mixed pixels' thread, ``minidiff.threads.share_tasks``).
    return share_tasks(tasks)


def boundary_term(
    scene: Scene, frame, kinds: Sequence[CurveKind], points: Sequence[CurvePoints]
) -> md.Tensor | None:
    """(H, W, 3) on the tape: zero in value, the boundary term in derivative (None when
    there are no points). ``points``: ``boundary_points`` of ``kinds``; ``frame``: the
    render's ``camera_frame``. The kinds' edge functions are recorded in the order of their
    ``taped`` rank and their terms summed in that of their ``summed`` rank (ties: in the
    order of ``kinds``; ``CurveKind`` says why two orders)."""
    on_tape = {}
    for k in sorted(range(len(kinds)), key=lambda k: kinds[k].taped):
        if len(points[k].pixel):
            on_tape[k] = kinds[k].edge_function(scene, frame, points[k])
    parts, weight, pixel = [], [], []
    for k in sorted(on_tape, key=lambda k: kinds[k].summed):
        e, rows = on_tape[k]
        parts.append(e)
        weight.append(points[k].factor[rows])
        pixel.append(points[k].pixel[rows])
    if not parts:
        return None
    dtype = working_dtype(scene)
    e = md.concatenate(parts) if len(parts) > 1 else parts[0]
    moving = e - md.tensor(e.data)  # zero, with the derivative of e
    values = md.reshape(moving, (-1, 1)) * np.concatenate(weight).astype(dtype)
    camera = scene.camera
    image = md.scatter_add(values, np.concatenate(pixel), camera.width * camera.height)
    return md.reshape(image, (camera.height, camera.width, 3))


def add_curve_terms(
    scene: Scene,
    occluders: Occluders,
    image: md.Tensor,
    frame,
    radiance: SideRadiance,
    kinds: Sequence[CurveKind],
) -> md.Tensor:
    """The image (H, W, 3) plus the boundary term of ``kinds``' curves: the same values, the
    exact edge derivative. ``occluders``: the render's geometry for occlusion rays;
    ``frame``: its ``camera_frame``; ``radiance``: what the camera sees either side of a
    curve."""
    points = curve_points(scene, occluders, radiance, kinds)
    return with_boundary_term(scene, image, frame, kinds, points)


def curve_points(
    scene: Scene, occluders: Occluders, radiance: SideRadiance, kinds: Sequence[CurveKind]
) -> list[CurvePoints]:
    """``boundary_points`` of ``kinds`` seen in the render's camera, the sides of each
    curve shaded by ``radiance`` and occluded by ``occluders`` (off the tape)."""
    view = View(scene, plain_frame(scene.camera), occluders, radiance)
    return boundary_points(view, kinds)


def with_boundary_term(
    scene: Scene, image: md.Tensor, frame, kinds: Sequence[CurveKind],
    points: Sequence[CurvePoints],
) -> md.Tensor:  # fmt: skip
    """The image (H, W, 3) plus ``boundary_term`` of ``kinds`` at their ``points``."""
    term = boundary_term(scene, frame, kinds, points)
    return image if term is None else image + term
