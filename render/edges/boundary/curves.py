"""What a curve kind is: the interface between the boundary term and each kind of curve.

A curve kind (``MeshEdge``, ``SurfaceCrossing``, ``SphereOutline``, ``SphereCut``, the
shadow borders) owns three things, and ``render.edges.boundary.term`` asks each in turn:

1. ``curves``: where its curves lie in the image, as 2-D segments in pixel coordinates, each
   with a label the kind reads back (an edge's row, a pair of triangles, ...);
2. ``points``: given the quadrature points on its segments, their constant factor w (f_+ -
   f_-) / |grad_x e| (off the tape: occlusion, the radiance either side), the points moved
   onto the exact curve where the segments are chords of it;
3. ``edge_function``: its edge function e at those points on the tape, written once for
   arrays and tensors where the plain code evaluates it too;

and ``moves``: whether e can carry a derivative at all (some parameter it reads is
differentiated). Where it cannot, the kind's term is zero in value and derivative both, and
its points' factors, the costly part (occlusion, the radiance either side), are not
computed: a light's or a material's gradient needs no mesh edge's.

The term cuts every kind's segments together (so that a piece of one curve is cut where
another crosses it) and hands each kind back only its own points.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

import minidiff as md
from render.edges.boundary.occlusion import Occluders
from render.edges.boundary.radiance import SideRadiance
from render.scene.camera import PlainFrame, ray_directions
from render.scene.scene import Scene
from render.shade.hits import working_dtype

#: Points closer to the eye's plane than this fraction of the scene's size are clipped.
NEAR = 1e-7


@dataclass(frozen=True)
class View:
    """What every curve kind needs of one render (off the tape): the scene, its camera
    frame as plain arrays, the occluders of its occlusion rays, and the radiance either side
    of a curve (``SideRadiance``)."""

    scene: Scene
    frame: PlainFrame
    occluders: Occluders
    radiance: SideRadiance

    @property
    def size(self) -> float:
        """The scene's size (its bounding box's diagonal, > 0): ``NEAR`` is a fraction of it."""
        return max(self.occluders.size, 1e-300)


@dataclass
class Curves:
    """One kind's curves as k 2-D segments: start (k, 2), end (k, 2) in pixel coordinates
    (column, row; the image spans [0, W] x [0, H]), and label (k, ...): what the kind needs
    to know of each segment's curve."""

    start: np.ndarray
    end: np.ndarray
    label: np.ndarray


@dataclass
class OnCurves:
    """g quadrature points on one kind's segments: label (g, ...) (their segments'),
    image-plane coords (g, 2), pixel (g,) (row * W + column), weight (g,) (the rule's weight
    times the piece's length, in pixels) and key (g,) int64 (a name per point, unique in
    the render, for ``SideRadiance``)."""

    label: np.ndarray
    coords: np.ndarray
    pixel: np.ndarray
    weight: np.ndarray
    key: np.ndarray


@dataclass
class CurvePoints:
    """One kind's quadrature points with a non-zero factor (constants): image-plane coords
    (g, 2) on the curve, pixel (g,), factor (g, 3) (w (f_+ - f_-) / |grad_x e|), label
    (g, ...) as in ``Curves``."""

    coords: np.ndarray
    pixel: np.ndarray
    factor: np.ndarray
    label: np.ndarray

    @classmethod
    def nonzero(cls, on: OnCurves, factor: np.ndarray, coords: np.ndarray) -> CurvePoints:
        """The points of ``on`` whose ``factor`` (g, 3) is not zero, at ``coords`` (g, 2)."""
        keep = np.flatnonzero(np.any(factor != 0.0, axis=1))
        return cls(
            np.take(coords, keep, axis=0),
            on.pixel[keep],
            np.take(factor, keep, axis=0),
            on.label[keep],
        )


class CurveKind(Protocol):
    """A kind of curve along which the image jumps (the module docstring).

    ``taped`` and ``summed`` rank the kinds for ``render.edges.boundary.term.boundary_term``:
    the order in which their edge functions are recorded on the tape, and the order in which
    their terms are added to the image. Floating-point sums depend on the order of their
    terms: the gradients' on the first (the backward pass adds each kind's share into the
    same parameters), the image's on the second, so both are kept as they have always been
    (taped: shadow borders 0, mesh edges 1, outlines 2, sphere cuts 3, surface crossings 4;
    summed: mesh edges 0, outlines 1, sphere cuts 2, surface crossings 3, shadow borders 4),
    and every image and gradient keeps its last bits. A new kind takes the next rank in both.
    """

    taped: int
    summed: int

    def moves(self, scene: Scene) -> bool:
        """Whether a parameter its edge function reads is differentiated, in the render's
        ``scene`` (its objects placed in world space, on the tape;
        ``render.edges.boundary.moving``)."""
        ...

    def curves(self, view: View) -> Curves:
        """Its curves in view, as segments."""
        ...

    def points(self, view: View, on: OnCurves) -> CurvePoints:
        """The factors of the quadrature points ``on`` its curves."""
        ...

    def edge_function(
        self, scene: Scene, frame, points: CurvePoints
    ) -> tuple[md.Tensor, np.ndarray]:
        """Its edge function e (g,) at ``points`` on the tape (``frame``: the render's
        ``camera_frame``), and the rows (g,) of ``points`` each value belongs to (a kind
        that evaluates its points in groups returns them in its groups' order)."""
        ...


def directions_at(scene: Scene, frame, coords: np.ndarray) -> md.Tensor:
    """(g, 3) the camera directions through image-plane points (g, 2) on the tape, in the
    scene's working precision."""
    return ray_directions(frame, coords.astype(working_dtype(scene)))
