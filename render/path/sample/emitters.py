"""Area lights: the emissive triangles and spheres of a scene, and how one is picked.

Next-event estimation picks one emissive primitive with probability proportional to its
area (``Emitters.pick``), then a uniform point on it (``render.path.sample.choices``, with
``render.path.sample.sampling``'s ``triangle_point`` and ``sphere_direction``): the density of a
point is P(primitive) / area in area measure (``pdf_area``), the same everywhere on the
emitters, which keeps the weights of multiple importance sampling simple. The point is
recorded by its coordinates on its primitive (barycentrics (u, v) on a triangle, the unit
direction from a sphere's centre), so that on the tape it moves with the primitive
(``render.path.gradient.transport``).

``polygon_irradiance`` is the closed form the estimators are checked against: the
irradiance a flat polygon of uniform radiance gives a point (Lambert's formula).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from render.scene.scene import Mesh, Scene
from render.trace.primitives import primitive_ranges


@dataclass
class Emitters:
    """The emissive primitives of a scene (plain arrays, off the tape).

    prims (E,) int64: their global primitive ids (``render.trace.primitives``);
    probability (E,): the chance next-event estimation picks each (area / total area);
    cdf (E,): its running sum; row_of (P,) int64: the row of each primitive id in
    ``prims`` (-1: not emissive); area (E,): each one's area."""

    prims: np.ndarray
    probability: np.ndarray
    cdf: np.ndarray
    row_of: np.ndarray
    area: np.ndarray

    @classmethod
    def of(cls, scene: Scene, primitives) -> Emitters:
        """The emitters of a scene in world space, with its ``scene_primitives``. An
        emissive object whose area is zero is an error (it cannot emit)."""
        triangles, centers, radii = primitives
        n_prims = len(triangles) + len(centers)
        prims, areas = [], []
        for index, (obj, first, count) in enumerate(primitive_ranges(scene)):
            if not obj.material.emissive:
                continue
            if isinstance(obj, Mesh):
                tri = triangles[first : first + count]
                area = 0.5 * np.linalg.norm(
                    np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1
                )
            else:
                area = np.array([4.0 * math.pi * radii[first - len(triangles)] ** 2])
            if not area.sum() > 0:
                name = scene.objects.index(obj) if obj in scene.objects else index
                raise ValueError(
                    f"render: objects[{name}] is emissive but has zero area, so it cannot emit"
                )
            prims.append(np.arange(first, first + count)[area > 0])
            areas.append(area[area > 0])
        prims = np.concatenate(prims) if prims else np.zeros(0, np.int64)
        area = np.concatenate(areas) if areas else np.zeros(0)
        probability = area / area.sum() if len(area) else area
        row_of = np.full(n_prims, -1, np.int64)
        row_of[prims] = np.arange(len(prims))
        return cls(prims, probability, np.cumsum(probability), row_of, area)

    def __len__(self) -> int:
        return len(self.prims)

    def pick(self, u: np.ndarray) -> np.ndarray:
        """(k,) rows into ``prims`` for uniform numbers u (k,): by area."""
        return np.minimum(np.searchsorted(self.cdf, u * self.cdf[-1], side="right"), len(self) - 1)

    def pdf_area(self, prims: np.ndarray) -> np.ndarray:
        """(k,) the area density of next-event estimation at a point on primitives ``prims``
        (k,): P(primitive) / its area, 0 for primitives that do not emit."""
        rows = self.row_of[np.maximum(prims, 0)]
        ok = (prims >= 0) & (rows >= 0)
        safe = np.maximum(rows, 0)
        return np.where(ok, self.probability[safe] / self.area[safe], 0.0)


def polygon_irradiance(points, normals, corners, radiance: float = 1.0):
    """The irradiance at ``points`` (n, 3) with unit ``normals`` (n, 3) or one (3,), from
    flat polygons ``corners`` (n, k, 3) or one (k, 3) of uniform ``radiance``, each wholly
    in front of its point: (n,), or a float for one point (3,). Lambert's formula:
    E = L/2 |sum over edges of gamma_e n . u_e|, gamma_e the angle the edge subtends at the
    point and u_e the unit normal of the plane through the point and the edge."""
    one = np.ndim(points) == 1
    points = np.atleast_2d(np.asarray(points, np.float64))
    corners = np.asarray(corners, np.float64)
    if corners.ndim == 2:
        corners = np.broadcast_to(corners, (len(points), *corners.shape))
    normals = np.broadcast_to(np.asarray(normals, np.float64), points.shape)
    v = corners - points[:, None]
    v = v / np.linalg.norm(v, axis=2, keepdims=True)
    w = np.roll(v, -1, axis=1)  # each edge's second corner
    cross = np.cross(v, w)
    length = np.linalg.norm(cross, axis=2)
    gamma = np.arctan2(length, np.sum(v * w, axis=2))
    along = np.einsum("nkj,nj->nk", cross, normals) / np.where(length > 0, length, 1.0)
    irradiance = 0.5 * radiance * np.abs(np.sum(gamma * along, axis=1))
    return float(irradiance[0]) if one else irradiance
