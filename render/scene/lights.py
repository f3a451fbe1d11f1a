"""Lights, and everything the renderer asks of one.

A light answers, for the stages that trace, shade and differentiate edges, in one place:

* ``towards(points)``: the vector from points to the light; ``incidence(points)``: the unit
  direction to it and the irradiance it delivers (on the tape, ``render.shade.lighting``);
* ``shadow_rays(points, offset)``: rays from points towards it and where they end
  (``render.trace.visibility``); ``shadow_ray_end``: the end of a ray along ``towards``;
  ``location()``: where it is, if it is anywhere (the shadow rays' offset, the light's view);
* ``shadow_key()``: what its shadow rays depend on (``render.scene.cache``);
  ``placement()``: the parameters that say where it is (by default all of them; its
  shadows' borders move only with them, ``render.edges.boundary.moving.geometry_moves``);
* ``pack()`` / ``shading_pack()``: its kind code and values for the hand-written kernels
  (``render.edges.boundary.shadow_tracing``, the path integrator's ``render.path.twin.packed``);
* ``edge_plane(v_i, v_j)``: the plane an occluder's edge sweeps in its light, the shadow's
  border; ``ray_to(points)``: its ray to points, for a sphere occluder; ``sphere_outline``:
  a sphere's silhouette as the light sees it (``render.edges``, ``render.path``).

The formulas that are differentiated (``towards``, ``incidence``, ``edge_plane``,
``ray_to``) are written once over both namespaces: given minidiff tensors they record on
the tape with the light's parameter tensors; given plain arrays they compute with the
parameters' values as float64 arrays. A new light type is a subclass here (its
``FIELDS`` and these methods) plus its tests; the compiled kernels switch on ``KIND``.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from typing import Any, ClassVar

import numpy as np

import minidiff as md
from minidiff import Tensor, buffers
from minidiff.either import cross_last
from minidiff.threads import job_count, kernel, run_jobs, share
from minidiff.trace import Traced
from render.scene.fields import IN_RANGE, ArrayLike, Field, HasFields, normalisable

__all__ = ["DIRECTIONAL", "POINT", "DirectionalLight", "Light", "PointLight"]

#: Values a formula is written over: minidiff tensors (on the tape) or plain arrays.
Values = Tensor | np.ndarray
#: Rays (origins (k, 3), directions (k, 3), tmax (k,) or one float for all).
Rays = tuple[np.ndarray, np.ndarray, np.ndarray | float]
#: A circle: its centre (3,) and two orthogonal radius vectors u1, u2 (3,) each.
Circle = tuple[np.ndarray, np.ndarray, np.ndarray]

#: The kind codes compiled kernels switch on (``Light.KIND``).
POINT, DIRECTIONAL = 0, 1


def _strength(name: str) -> Field:
    """A light's scalar strength field (intensity or irradiance), >= 0."""
    return Field(name, ((),), (lambda x: x >= 0.0, ">= 0"))


#: A light's (3,) linear RGB colour, multiplying its strength; white unless given.
_LIGHT_COLOR = Field("color", ((3,),))
WHITE = (1.0, 1.0, 1.0)


def _value(param: Tensor, like: Any) -> Values:
    """``param`` itself when ``like`` is a tensor (on the tape, or traced by
    ``minidiff.compile``), else its values, float64."""
    if isinstance(like, (Tensor, Traced)):
        return param
    return np.asarray(param.data, np.float64)


class Light(HasFields, ABC):
    """What every light answers (module docstring). Subclasses set ``KIND``,
    ``shadow_ray_end`` and ``FIELDS`` (one of them ``color``, (3,)) and implement the
    methods below."""

    #: Its code in the compiled kernels: POINT or DIRECTIONAL.
    KIND: ClassVar[int]
    #: The parameter t at which a shadow ray from ``shadow_rays`` (or one along
    #: ``towards``) reaches the light: 1.0 for a light at a point, inf for one at infinity.
    shadow_ray_end: ClassVar[float]
    #: Whether the compiled kernels shade it: ``render.shade.compiled`` traces this class's
    #: own ``incidence`` (``minidiff.compile``), the path integrator's kernel switches on
    #: ``KIND`` (``shading_pack``). A new light type starts without (the tape shades it).
    compiled_shading: ClassVar[bool] = False
    color: Tensor

    @abstractmethod
    def location(self) -> np.ndarray | None:
        """(3,) float64: where the light is; None for a light at infinity."""

    def placement(self) -> tuple[Tensor, ...]:
        """The parameters that say where the light is, not how bright: what its shadows'
        borders move with (``render.edges.boundary.moving.geometry_moves``). By default
        every parameter of the light (a new light type is right without it, if slower: a
        differentiated strength then makes its borders' points be found too)."""
        return tuple(getattr(self, field.name) for field in self.FIELDS)

    @abstractmethod
    def towards(self, points: Values) -> Values:
        """The vector (k, 3) or (3,) from points (k, 3) to the light, not normalised (a
        tensor if ``points`` is one, on the tape)."""

    @abstractmethod
    def incidence(self, points: Values) -> tuple[Tensor, Tensor]:
        """On the tape, per point (k, 3): the unit direction to the light (k, 3) or (3,) and
        the irradiance (k,) or a scalar on a surface facing it (no cosine yet), to be
        multiplied by ``color``."""

    @abstractmethod
    def shadow_rays(self, points: np.ndarray, offset: float) -> Rays:
        """Rays from points (k, 3) towards the light, each started ``offset`` towards it:
        (origins (k, 3), directions (k, 3), tmax (k,) or a float): the ray is blocked by a hit
        with 0 < t < tmax."""

    @abstractmethod
    def shadow_key(self) -> list[np.ndarray]:
        """What the light's shadow rays depend on besides the points (copies)."""

    @abstractmethod
    def pack(self, unit: bool = False) -> tuple[int, np.ndarray]:
        """(KIND, (3,) float64) for compiled kernels: a point light's position, a
        directional light's direction of travel as given (``unit``: divided by its length)."""

    def shading_pack(self) -> tuple[int, np.ndarray, float]:
        """(KIND, (3,) float64, strength) for ``render.path.twin.packed``: the position, or the
        unit vector towards the light as ``incidence`` computes it; the intensity or
        irradiance. Only for a light with ``compiled_shading`` (the others are shaded on
        the tape only)."""
        raise TypeError(f"{type(self).__name__} has no compiled shading")

    @abstractmethod
    def edge_plane(self, v_i: Values, v_j: Values) -> tuple[Values, Values]:
        """The plane an occluder's edge from v_i to v_j (k, 3) sweeps in this light, the
        border of its shadow: (m, base), e(P) = m . (P - base) is zero on it. Tensors (on the
        tape) or arrays."""

    @abstractmethod
    def ray_to(self, points: Values) -> tuple[Values, Values]:
        """The light's ray reaching points (k, 3), as (origin, direction): P lies on
        origin + t direction (for a sphere occluder's border: the ray grazes the sphere).
        Tensors (on the tape) or arrays."""

    @abstractmethod
    def sphere_outline(self, centre: np.ndarray, radius: float) -> Circle | None:
        """The outline of a sphere (centre (3,), radius) seen from the light, a circle:
        (its centre (3,), u1 (3,), u2 (3,)), its points centre + cos(phi) u1 + sin(phi) u2;
        None if the light cannot see it from outside."""

    def shadow_apex(self, centre: np.ndarray, far: float) -> Tensor:
        """Where the light casts its shadows from, (3,) on the tape: for a light at a point
        (``shadow_ray_end`` 1), that point; for one at infinity, the point ``far`` away
        from ``centre`` (3,) in its direction (its shadows' borders are those of a point
        light there, to rounding). Written with ``towards``, so every light has it; a
        light that is neither raises."""
        here = md.tensor(np.asarray(centre, np.float64))
        if self.shadow_ray_end == 1.0:
            return here + self.towards(here)
        if self.shadow_ray_end == math.inf:
            return here + md.normalize(self.towards(here)) * far
        raise TypeError(
            f"{type(self).__name__}.shadow_ray_end is {self.shadow_ray_end!r}: the path "
            "integrator's shadow borders need a light at a point (1.0) or at infinity (inf)"
        )


def _circle(centre: np.ndarray, radius: float, view: np.ndarray, shrink: float) -> Circle:
    """The circle where rays along ``view`` (3,) touch the sphere, ``shrink`` = r^2 / |view|^2
    of the way back along ``view`` from the centre (0: rays from infinity)."""
    dist2 = float(view @ view)
    rho = radius * math.sqrt(1.0 - shrink)
    u1 = np.cross(view, [1.0, 0, 0] if abs(view[0]) < 0.9 * math.sqrt(dist2) else [0, 1.0, 0])
    u1 *= rho / np.linalg.norm(u1)
    u2 = np.cross(view, u1) / math.sqrt(dist2)
    return centre - shrink * view, u1, u2


class PointLight(Light):
    """An isotropic point light.

    Args:
        position: (3,) position in world space.
        intensity: scalar radiant intensity I (W/sr), >= 0. The irradiance at distance r
            facing the light is ``I / r**2`` (inverse-square falloff).
        color: (3,) linear RGB multiplier of the intensity (white by default).
    """

    KIND = POINT
    shadow_ray_end = 1.0
    compiled_shading = True
    FIELDS = (Field("position", ((3,),), IN_RANGE), _strength("intensity"), _LIGHT_COLOR)

    def __init__(self, position: ArrayLike, intensity: ArrayLike, color: ArrayLike = WHITE):
        self._set_fields(position=position, intensity=intensity, color=color)
        self.validate()

    def placement(self) -> tuple[Tensor, ...]:
        return (self.position,)

    def location(self) -> np.ndarray:
        return np.asarray(self.position.data, dtype=np.float64)

    def towards(self, points: Values) -> Values:
        return _value(self.position, points) - points

    def incidence(self, points: Values) -> tuple[Tensor, Tensor]:
        offset = self.towards(points)
        # A light exactly on the surface would give 0/0: divide by 1 there instead (the
        # contribution is zero anyway, since the direction to the light is zero). Only exact
        # zeros are replaced, so that any distance, however small the scene, is used as it
        # is (a fixed floor was not scale-invariant: issue 9).
        distance_sq = md.dot(offset, offset)
        distance_sq = md.where(distance_sq == 0.0, 1.0, distance_sq)
        return md.normalize(offset), self.intensity / distance_sq

    def shadow_rays(self, points: np.ndarray, offset: float) -> Rays:
        points = np.asarray(points, np.float64)
        origins = buffers.empty(points.shape, np.float64)
        directions = buffers.empty(points.shape, np.float64)
        tmax = buffers.empty(points.shape[:1], np.float64)
        run_jobs(_point_light_rays, job_count(len(points), 65536), self.location(), points,
                 offset, origins, directions, tmax)  # fmt: skip
        return origins, directions, tmax

    def shadow_key(self) -> list[np.ndarray]:
        return [np.array(self.position.data), np.array([0.0])]

    def pack(self, unit: bool = False) -> tuple[int, np.ndarray]:
        return POINT, self.location()

    def shading_pack(self) -> tuple[int, np.ndarray, float]:
        return POINT, self.position.data, self.intensity.data

    def edge_plane(self, v_i: Values, v_j: Values) -> tuple[Values, Values]:
        position = _value(self.position, v_i)
        return cross_last(v_i - position, v_j - position), position

    def ray_to(self, points: Values) -> tuple[Values, Values]:
        position = _value(self.position, points)
        return position, points - position

    def shadow_apex(self, centre: np.ndarray, far: float) -> Tensor:
        return self.position  # the base class's formula, without its rounding

    def sphere_outline(self, centre: np.ndarray, radius: float) -> Circle | None:
        view = centre - self.location()
        dist2 = float(view @ view)
        if dist2 <= radius * radius:
            return None  # the light inside the sphere: everything outside is dark
        return _circle(centre, radius, view, radius * radius / dist2)


class DirectionalLight(Light):
    """A distant light (like the sun): parallel rays, no falloff.

    Args:
        direction: (3,) the direction in which the light **travels**, i.e. from the light
            towards the scene (the Mitsuba / glTF convention). A sun shining straight down
            has ``direction=(0, -1, 0)``. The vector towards the light, used for shading
            and shadow rays, is ``-direction / |direction|``. Need not be unit length, must
            not be zero.
        irradiance: scalar irradiance E (W/m^2) on a surface facing the light, >= 0.
        color: (3,) linear RGB multiplier of the irradiance (white by default).
    """

    KIND = DIRECTIONAL
    shadow_ray_end = math.inf
    compiled_shading = True
    # Shading and shadow rays divide by the direction's length: it must not underflow.
    _DIRECTION = Field("direction", ((3,),), (normalisable, "a vector of length 1e-150 to 1e150"))
    FIELDS = (_DIRECTION, _strength("irradiance"), _LIGHT_COLOR)

    def __init__(self, direction: ArrayLike, irradiance: ArrayLike, color: ArrayLike = WHITE):
        self._set_fields(direction=direction, irradiance=irradiance, color=color)
        self.validate()

    def placement(self) -> tuple[Tensor, ...]:
        return (self.direction,)

    def location(self) -> None:
        return None

    def towards(self, points: Values) -> Values:
        return -_value(self.direction, points)

    def incidence(self, points: Values) -> tuple[Tensor, Tensor]:
        return md.normalize(self.towards(points)), self.irradiance

    def shadow_rays(self, points: np.ndarray, offset: float) -> Rays:
        # Unit length: the user's direction may have any length.
        towards = -np.asarray(self.direction.data, np.float64)
        unit = towards / np.linalg.norm(towards)
        origins = points + offset * unit
        return origins, np.broadcast_to(unit, points.shape), np.inf

    def shadow_key(self) -> list[np.ndarray]:
        return [np.array(self.direction.data), np.array([1.0])]

    def pack(self, unit: bool = False) -> tuple[int, np.ndarray]:
        w = np.asarray(self.direction.data, np.float64)
        return DIRECTIONAL, (w / np.linalg.norm(w) if unit else w)

    def shading_pack(self) -> tuple[int, np.ndarray, float]:
        with md.no_grad():
            return DIRECTIONAL, md.normalize(-self.direction).data, self.irradiance.data

    def edge_plane(self, v_i: Values, v_j: Values) -> tuple[Values, Values]:
        return cross_last(v_j - v_i, _value(self.direction, v_i)), v_i

    def ray_to(self, points: Values) -> tuple[Values, Values]:
        return points, _value(self.direction, points)

    def sphere_outline(self, centre: np.ndarray, radius: float) -> Circle | None:
        return _circle(centre, radius, np.asarray(self.direction.data, np.float64), 0.0)


@kernel
def _point_light_rays(job, n_jobs, position, points, offset, origins, directions, tmax):
    """Job ``job`` of ``n_jobs`` (``minidiff.threads.run_jobs``): shadow rays towards a
    point light from its share of the points (k, 3): each starts ``offset`` towards the
    light and ends just before it (``PointLight.shadow_rays``)."""
    first, stop = share(job, n_jobs, points.shape[0])
    for i in range(first, stop):
        tx = position[0] - points[i, 0]
        ty = position[1] - points[i, 1]
        tz = position[2] - points[i, 2]
        distance = np.sqrt(tx * tx + ty * ty + tz * tz)
        if distance <= 2.0 * offset:
            # A light on (or within the offset of) the hit point: nothing can come between;
            # its contribution is zero or nearly so (see shading), so call it lit (tmax = 0).
            fraction = offset
            directions[i, 0], directions[i, 1], directions[i, 2] = 0.0, 1.0, 0.0
            tmax[i] = 0.0
        else:
            fraction = offset / distance  # of the way to the light
            tmax[i] = 1.0 - fraction / (1.0 - fraction)
        origins[i, 0] = points[i, 0] + fraction * tx
        origins[i, 1] = points[i, 1] + fraction * ty
        origins[i, 2] = points[i, 2] + fraction * tz
        if distance > 2.0 * offset:
            # Unnormalised direction to the light: t = 1 is the light itself.
            directions[i, 0] = position[0] - origins[i, 0]
            directions[i, 1] = position[1] - origins[i, 1]
            directions[i, 2] = position[2] - origins[i, 2]
