"""The curves along which what a point sees can change, and how a point on them is drawn.

Seen from a point (the apex: a path vertex, or a point light), visibility jumps across the
silhouettes of the occluders: a mesh edge whose two faces lie on one side of the plane
through the apex and the edge (a border edge always), and the circle where the cone from
the apex touches a sphere. ``render.path.boundary.secondary`` samples a point on such a
curve for every path vertex; here is where the curves come from (``Curves.of``) and how
one is drawn:

* a curve with probability proportional to the angle it subtends at the apex (its share of
  what the apex sees), or to the angle of its part whose rays meet a given triangle (an
  emitter: ``towards``), and
* a point on it uniformly in that angle (``parameter``): drawn uniformly along the edge, a
  point near an apex close to the edge would carry a weight that grows as 1 / distance.

Which curves can be silhouettes (mesh edges welded across the meshes that share them,
the two outer faces of an edge where more meet, edges resting on another object's surface
left out) is ``render.trace.outlines``' to say, for this term and the direct renderer's
shadow borders alike: ``Curves`` are its ``Outlines`` with the draws added.

``pick_reference`` composes the NumPy steps (n x E arrays: the version to read);
``Curves.pick`` does the same per apex in one parallel Numba loop over the curves (no
n x E arrays; the version the renderer runs). ``tests/render/path/test_secondary.py``
checks that they agree.
"""

from __future__ import annotations

from dataclasses import fields
from functools import cached_property

import numpy as np

import minidiff as md
from minidiff.threads import borrowing, jit, job_count, kernel, run_jobs, share
from render.path.sample.sampling import dot, unit
from render.path.sample.tracer import PathSampler
from render.scene.scene import Mesh
from render.shade.surface import column, divided_unit
from render.trace.outlines import GRAZING, Outlines, one_sided
from render.trace.vec3 import cross, dot3, sub

#: A draw weighs the edges in runs of this many, skipping a run where bounds on its
#: faces' planes show that none is a silhouette from the apex (``Curves.clusters``).
CLUSTER = 16
#: ... by at least this fraction of the distance and the run's radius (the bounds are
#: computed otherwise than the edges' own tests, and round otherwise).
RUN_MARGIN = 1e-6


def level_set(apex, far, a, b, centre, radius, is_edge) -> md.Tensor:
    """(m,) the level set function phi (``render.path.boundary.secondary``'s docstring) at
    the points ``far`` (m, 3) of curves seen from ``apex`` (m, 3): the edge (``a``, ``b``,
    (m, 3) each) where ``is_edge`` (m,), else the sphere (``centre`` (m, 3), ``radius``
    (m,)). Each row reads both kinds' arguments, which need only be finite where unused;
    None: the scene has no such curve. The one text of phi: the boundary samples'
    derivative (compiled or on the tape) and the curves' gradient (``Curves.gradient``) both
    come from it."""
    w = far - apex
    edge = sphere = None
    if a is not None:
        edge = md.dot(w, md.cross(a - apex, b - apex))
    if centre is not None:
        across = md.cross(w, centre - apex)
        ratio = md.dot(across, across) / md.dot(w, w)
        if edge is not None:  # 1 on the edges' rows: the root's derivative at 0 is infinite
            ratio = md.where(is_edge, 1.0, ratio)
        sphere = md.sqrt(ratio) - radius
    if edge is None or sphere is None:
        return sphere if edge is None else edge
    return md.where(is_edge, edge, sphere)


class Curves(Outlines):
    """The scene's ``Outlines`` (``render.trace.outlines``: mesh edges ``a``, ``b`` (E, 3)
    with their faces' third corners ``c`` (E, 2, 3), owner and vertex ids; spheres
    ``centre`` (S, 3), ``radius`` (S,)) and how a point on one seen from a path vertex is
    drawn (the module docstring)."""

    @classmethod
    def of(cls, sampler: PathSampler) -> Curves:
        """The curves of the sampler's scene (world space)."""
        found = Outlines.of(sampler.scene, sampler.primitives[0], sampler.size)
        # The edges in the order of their midpoints along a Morton curve, so that runs of
        # consecutive edges lie near each other (``clusters``; positions only: the meshes
        # of a split mesh give its curves in the same order).
        order = np.argsort(_morton(0.5 * (found.a + found.b)), kind="stable")
        edge_fields = ("a", "b", "c", "edge_object", "ends", "faces", "crack")
        return cls(**{
            f.name: getattr(found, f.name)[order] if f.name in edge_fields
            else getattr(found, f.name) for f in fields(Outlines)
        })  # fmt: skip

    @classmethod
    def kept(cls, sampler: PathSampler) -> Curves:
        """``Curves.of(sampler)``, kept in the sampler's render cache while the scene's
        objects keep their shapes (every mesh's vertices and faces, every sphere's centre
        and radius: all the curves are made of): a fit of materials or lights finds them
        again at every step. Read-only, as everything in the cache."""
        if sampler.cache is None:
            return cls.of(sampler)
        key = []
        for obj in sampler.objects:
            shape = (obj.vertices, obj.faces) if isinstance(obj, Mesh) else (obj.center, obj.radius)
            key.extend(np.array(getattr(part, "data", part)) for part in shape)
        return sampler.cache.get("silhouette curves", key, lambda: cls.of(sampler))[0]

    def silhouettes(self, apex: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For apexes (n, 3): the angle (n, E + S) each curve subtends there, zero where it
        is no silhouette (edges first, then spheres), and the side (n, E) of the plane
        through apex and edge that the edge's faces lie on (+1 or -1)."""
        pa, pb = self.a[None] - apex[:, None], self.b[None] - apex[:, None]  # (n, E, 3)
        normal = np.cross(pa, pb)
        silhouette, side = one_sided(normal, apex[:, None], self.c)
        size = np.linalg.norm(normal, axis=2)
        angle = np.where(silhouette, np.arctan2(size, np.einsum("nej,nej->ne", pa, pb)), 0.0)
        distance = np.linalg.norm(self.centre[None] - apex[:, None], axis=2)  # (n, S)
        around = self.radius < distance * (1 - 1e-9)
        circle = np.where(around, 2 * np.pi * self.radius / np.maximum(distance, 1e-300), 0.0)
        return np.concatenate([angle, circle], axis=1), side

    def towards(self, apex: np.ndarray, triangle: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The parameters (lo, hi) (n, E + S) of the part of each curve through which rays
        from the apexes (n, 3) meet the triangle (n, 3, 3) (lo = hi: none): on an edge, the
        rays in the plane through apex and edge that cross the triangle; on a sphere's
        circle, the azimuths (about the axis apex -> centre, which rays from the apex keep)
        that the triangle spans, as an arc that may run past 1 (the circle is periodic)."""
        pa, e = self.a[None] - apex[:, None], (self.b - self.a)[None]  # (n, E, 3)
        normal = np.cross(pa, self.b[None] - apex[:, None])
        v = triangle[:, None] - apex[:, None, None]  # (n, 1, 3, 3)
        dist = np.einsum("nvk,nek->nev", v[:, 0], normal)  # (n, E, 3)
        ts = []
        for i, j in ((0, 1), (1, 2), (2, 0)):
            crosses = dist[..., i] * dist[..., j] < 0
            f = dist[..., i] / np.where(crosses, dist[..., i] - dist[..., j], 1.0)
            q = v[:, :, i] + f[..., None] * (v[:, :, j] - v[:, :, i])  # from the apex
            # Where apex + mu q meets a + t e: t = ((-pa) x q) . (e x q) / |e x q|^2.
            exq = np.cross(e, q)
            t = np.einsum("nek,nek->ne", np.cross(-pa, q), exq) / np.maximum(
                np.einsum("nek,nek->ne", exq, exq), 1e-300
            )
            ts.append(np.where(crosses, t, np.nan))
        ts = np.stack(ts, axis=2)
        two = np.sum(~np.isnan(ts), axis=2) >= 2
        edge_lo = np.where(two, np.clip(np.nanmin(np.where(two[..., None], ts, 0), 2), 0, 1), 0)
        edge_hi = np.where(two, np.clip(np.nanmax(np.where(two[..., None], ts, 0), 2), 0, 1), 0)
        q = self.centre[None] - apex[:, None]  # (n, S, 3)
        d = q / np.maximum(np.linalg.norm(q, axis=2, keepdims=True), 1e-300)
        u1, u2 = (x.data.reshape(d.shape) for x in basis(d.reshape(-1, 3)))
        azimuth = np.arctan2(np.einsum("nsk,nvk->nsv", u2, v[:, 0]),
                             np.einsum("nsk,nvk->nsv", u1, v[:, 0]))  # fmt: skip
        azimuth = np.sort(azimuth, axis=2)
        gaps = np.diff(np.concatenate([azimuth, azimuth[..., :1] + 2 * np.pi], axis=2), axis=2)
        widest = np.argmax(gaps, axis=2)
        start = np.take_along_axis(azimuth, ((widest + 1) % 3)[..., None], axis=2)[..., 0]
        width = 2 * np.pi - np.take_along_axis(gaps, widest[..., None], axis=2)[..., 0]
        whole = np.take_along_axis(gaps, widest[..., None], axis=2)[..., 0] <= np.pi
        sphere_lo = np.where(whole, 0.0, np.mod(start, 2 * np.pi) / (2 * np.pi))
        sphere_hi = np.where(whole, 1.0, sphere_lo + width / (2 * np.pi))
        lo = np.concatenate([edge_lo, sphere_lo], axis=1)
        return lo, np.concatenate([edge_hi, sphere_hi], axis=1)

    @cached_property
    def clusters(self) -> tuple[np.ndarray, np.ndarray]:
        """Bounds that let a draw skip runs of ``CLUSTER`` consecutive edges none of which
        is a silhouette from its apex (``_hidden_run``; ``of`` orders the edges along a
        Morton curve, so that a run's lie near each other). Per run (K,), the edges' planes
        through a and its faces' third corners, each turned so that a point on its
        positive side (of both an edge's) makes the edge no silhouette (side_k(p) =
        -n_k . (p - a), n_k = (b - a) x (c_k - a)); as a cone of their unit normals (axis
        (K, 3), the cosine and sine of its half-angle) and a sphere about their points a
        (centre (K, 3), radius): ``bounds`` (K, 9) = axis, cos, sin, centre, radius, and
        whether a run may be skipped at all (K,) bool (not where a face is degenerate or
        the cone is a quarter turn wide or more). From most apexes most runs of a dense
        mesh are skipped."""
        n_runs = -(-self.n_edges // CLUSTER)
        bounds, usable = np.zeros((n_runs, 9)), np.zeros(n_runs, bool)
        if n_runs == 0:
            return bounds, usable
        a, b = self.a, self.b
        normals = np.stack([np.cross(b - a, self.c[:, 0] - a),
                            -np.cross(b - a, self.c[:, 1] - a)], axis=1)  # fmt: skip
        length = np.linalg.norm(normals, axis=2)
        ok = np.all(length > 0, axis=1)
        unit_normals = normals / np.where(length > 0, length, 1.0)[..., None]
        pad = n_runs * CLUSTER - self.n_edges  # the last run's missing edges: its first's
        idx = np.r_[np.arange(self.n_edges), np.full(pad, (n_runs - 1) * CLUSTER)]
        m = unit_normals[idx].reshape(n_runs, 2 * CLUSTER, 3)
        points = a[idx].reshape(n_runs, CLUSTER, 3)
        axis = m.sum(axis=1)
        size = np.linalg.norm(axis, axis=1)
        axis = axis / np.where(size > 0, size, 1.0)[:, None]
        cos = np.min(np.einsum("kij,kj->ki", m, axis), axis=1)
        centre = points.mean(axis=1)
        radius = np.max(np.linalg.norm(points - centre[:, None], axis=2), axis=1)
        usable = ok[idx].reshape(n_runs, CLUSTER).all(axis=1) & (size > 0) & (cos > 0)
        cos = np.clip(cos, -1.0, 1.0)
        bounds = np.concatenate([axis, cos[:, None], np.sqrt(1.0 - cos * cos)[:, None],
                                 centre, radius[:, None]], axis=1)  # fmt: skip
        return np.ascontiguousarray(bounds), usable

    def pick(self, apex, whole, towards=None):
        """``pick_reference`` computed per apex in one compiled loop over the curves:
        ``whole`` = (u_curve, u_point, active) for a draw from whole curves, ``towards`` =
        (triangles, u_curve, u_point, active) for one from their parts towards triangles
        (or None); returns each draw's (index, density, side, t) (None for no ``towards``)."""
        n = len(whole[0])
        clip = towards is not None
        tri = np.zeros((1, 3, 3)) if not clip else np.ascontiguousarray(towards[0], float)
        second = towards[1:] if clip else (np.zeros(n), np.zeros(n), np.zeros(n, bool))
        u_curve = np.stack([whole[0], second[0]]).astype(float)
        u_point = np.stack([whole[1], second[1]]).astype(float)
        active = np.stack([whole[2], second[2]]).astype(bool)
        out = np.empty((2, 4, n))
        run_jobs(_pick, job_count(n, 256), np.ascontiguousarray(apex, float), self.a, self.b,
                 self.c, self.centre, self.radius, *self.clusters, tri, clip, active, u_curve,
                 u_point, GRAZING, out)  # fmt: skip
        draws = [(o[0].astype(np.int64), o[1], o[2], o[3]) for o in out]
        return draws[0], draws[1] if clip else None

    def parameter(self, apex, index, lo, hi, u) -> tuple[np.ndarray, np.ndarray]:
        """A parameter t (n,) in lo..hi (n,) on each curve ``index`` (n,), and its density
        (n,) per unit t: uniform in the angle seen from the apex (n, 3), so that the
        weights stay bounded where an apex is close to an edge (uniform in t, the points
        near it would carry weights that grow as 1 / distance). Spheres' circles: uniform
        in azimuth, which is the same."""
        t, density = lo + u * (hi - lo), 1.0 / np.where(hi > lo, hi - lo, 1.0)
        edge = np.flatnonzero(index < self.n_edges)
        if len(edge) == 0:
            return t, density
        j, p = index[edge], apex[edge]
        e = self.b[j] - self.a[j]
        start = unit(self.a[j] + lo[edge, None] * e - p)
        end = unit(self.a[j] + hi[edge, None] * e - p)
        total = np.arctan2(np.linalg.norm(np.cross(start, end), axis=1), dot(start, end))
        towards = unit(end - dot(end, start)[:, None] * start)
        psi = (u[edge] * total)[:, None]
        d = np.cos(psi) * start + np.sin(psi) * towards
        exd = np.cross(e, d)
        t[edge] = dot(np.cross(p - self.a[j], d), exd) / np.maximum(dot(exd, exd), 1e-300)
        w = self.a[j] + t[edge, None] * e - p
        # dpsi/dt = |w x e| / |w|^2, over the total angle.
        rate = np.linalg.norm(np.cross(w, e), axis=1) / dot(w, w)
        density[edge] = rate / np.where(total > 0, total, 1.0)
        return t, density

    def rows(self, index: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Of curves ``index`` (n,) (all valid): each one's row in the edges' table, in the
        spheres' table (0 in the rows of the other kind: a harmless row, never selected),
        and which are edges (n,) bool (``padded``'s tables)."""
        is_edge = index < self.n_edges
        return np.where(is_edge, index, 0), np.where(is_edge, 0, index - self.n_edges), is_edge

    @property
    def padded(self) -> tuple:
        """(a, b, centre, radius) with one harmless row where the scene has no edge or no
        sphere: the tables the compiled functions below gather from."""
        a, b = (self.a, self.b) if self.n_edges else (np.zeros((1, 3)), np.ones((1, 3)))
        if len(self.radius):
            return a, b, self.centre, self.radius
        return a, b, np.zeros((1, 3)), np.ones(1)

    def aim(self, apex, index, side, t, lift: float) -> tuple[np.ndarray, ...]:
        """For curves ``index`` (n,) (all valid) seen from ``apex`` (n, 3): the point m at
        parameter t (n,), dm/dt, m lifted by ``lift`` towards the side the occluder does not
        hide (edges: faces on ``side`` (n,) of the plane through apex and edge) and the unit
        direction from the apex to m, each (n, 3): ``_aim``, compiled."""
        found = _aim(np.ascontiguousarray(apex, np.float64), np.asarray(t, np.float64),
                     np.asarray(side, np.float64), *self.rows(index),
                     np.asarray(lift, np.float64), *self.padded)  # fmt: skip
        return tuple(x.data for x in found)

    def gradient(self, apex, index, points) -> np.ndarray:
        """(n, 3): the gradient in x' of the level set function phi of curves ``index`` (n,)
        seen from ``apex`` (n, 3) at ``points`` x' (n, 3): ``level_set``'s own derivative
        (the compiled VJP of ``_level_set_of``, off the caller's tape)."""
        with md.enable_grad():  # its own tape, also inside a caller's no_grad()
            x = md.tensor(np.asarray(points, np.float64), requires_grad=True)
            phi = _level_set_of(np.ascontiguousarray(apex, np.float64), x, *self.rows(index),
                                *self.padded)  # fmt: skip
            phi.backward(np.ones(phi.shape))
        return x.grad


def curve_points(apex, t, a, b, centre, radius, is_edge):
    """The point m (n, 3) at parameter t (n,) on each row's curve seen from ``apex`` (n, 3),
    and dm/dt (n, 3): along the edge (``a``, ``b`` (n, 3)) from a (t = 0) to b (t = 1)
    where ``is_edge`` (n,), else around the circle where the cone from the apex touches the
    sphere (``centre`` (n, 3), ``radius`` (n,)) (azimuth 2 pi t, about the axis apex ->
    centre, from ``basis``'s first vector). Minidiff arrays; each row reads both kinds'
    arguments, which need only be finite where unused."""
    e = b - a
    q = centre - apex
    d2 = md.dot(q, q)
    rho = radius * md.sqrt(d2 - radius * radius) / md.sqrt(d2)
    middle = apex + q * column(1.0 - radius * radius / d2)
    u1, u2 = basis(q / column(md.sqrt(d2)))
    tau = 2.0 * np.pi * t
    cos, sin = column(md.cos(tau)), column(md.sin(tau))
    edge = column(is_edge)
    m = md.where(edge, a + column(t) * e, middle + column(rho) * (cos * u1 + sin * u2))
    tangent = md.where(edge, e, column(2.0 * np.pi * rho) * (cos * u2 - sin * u1))
    return m, tangent


def away_from_occluder(apex, side, m, a, b, centre, is_edge):
    """(n, 3) unit vectors from the curve points m (n, 3) towards the side that the
    occluder does not hide: across the plane through apex and edge, away from the edge's
    faces (on ``side`` (n,) of it), where ``is_edge``; else out of the sphere."""
    across = column(-side) * divided_unit(md.cross(a - apex, b - apex))
    return md.where(column(is_edge), across, divided_unit(m - centre))


def basis(n):
    """Two unit vectors (k, 3) orthogonal to the unit n (k, 3) and to each other (the
    azimuths' axes of ``curve_points``, and of the pick kernel's ``_axes``)."""
    helper = md.where(column(md.abs(n[:, 0]) > 0.9), np.array([0.0, 1.0, 0.0]),
                      np.array([1.0, 0.0, 0.0]))  # fmt: skip
    u1 = divided_unit(md.cross(n, helper))
    return u1, md.cross(n, u1)


@md.compile(shared=("lift", "a", "b", "centre", "radius"))
def _aim(apex, t, side, edge, ball, is_edge, lift, a, b, centre, radius):
    """``Curves.aim`` for rows of curves: ``edge``, ``ball``, ``is_edge`` (``Curves.rows``)
    into the tables a, b, centre, radius (``Curves.padded``)."""
    ends, sphere = (a[edge], b[edge]), (centre[ball], radius[ball])
    m, tangent = curve_points(apex, t, *ends, *sphere, is_edge)
    off = m + lift * away_from_occluder(apex, side, m, *ends, sphere[0], is_edge)
    # The rays pass a hair off the occluder, on the side that is not hidden: a ray through
    # the very point m could meet the sphere it touches or the faces at the edge again.
    return m, tangent, off, divided_unit(m - apex)


@md.compile(shared=("a", "b", "centre", "radius"))
def _level_set_of(apex, far, edge, ball, is_edge, a, b, centre, radius):
    """``level_set`` of rows of curves (``Curves.rows`` into ``Curves.padded``)."""
    return level_set(apex, far, a[edge], b[edge], centre[ball], radius[ball], is_edge)


def _choose(weights: np.ndarray, u: np.ndarray, side: np.ndarray):
    """A curve per row, picked with probability proportional to ``weights`` (n or 1,
    E + S) by uniforms u (n,): its index (n,) (-1: none had weight), the probability (n,)
    and, for edges, the side its faces lie on (``side`` (n or 1, E); 0 for spheres)."""
    n = len(u)
    if weights.shape[1] == 0:
        return np.full(n, -1), np.zeros(n), np.zeros(n)
    cdf = np.cumsum(weights, axis=1)
    total = np.broadcast_to(cdf[:, -1], (n,))
    index = np.minimum((cdf < (u * total)[:, None]).sum(axis=1), weights.shape[1] - 1)
    rows = np.zeros(n, np.int64) if len(weights) == 1 else np.arange(n)
    chosen = weights[rows, index]
    ok = (total > 0) & (chosen > 0)
    probability = np.where(ok, chosen / np.where(total > 0, total, 1.0), 0.0)
    edges = side.shape[1]
    faces = np.where(index < edges, side[rows, np.minimum(index, max(edges - 1, 0))], 0.0)
    return np.where(ok, index, -1), probability, faces if edges else np.zeros(n)


def _clipped_angle(curves: Curves, apex, weights, lo, hi) -> np.ndarray:
    """(n, E + S): the angle that the part lo..hi of each curve subtends at the apexes
    (n, 3), given the whole curves' angles ``weights`` (n, E + S)."""
    e = curves.n_edges
    a, ab = curves.a[None], (curves.b - curves.a)[None]
    start = a + lo[:, :e, None] * ab - apex[:, None]
    end = a + hi[:, :e, None] * ab - apex[:, None]
    edges = np.arctan2(np.linalg.norm(np.cross(start, end), axis=2),
                       np.einsum("nek,nek->ne", start, end))  # fmt: skip
    spheres = weights[:, e:] * (hi[:, e:] - lo[:, e:])
    return np.concatenate([edges, spheres], axis=1)


def pick_reference(curves: Curves, apex, u_curve, u_point, triangle=None, active=None):
    """For apexes (n, 3) (or one, (1, 3)), a curve each and a point on it, from uniforms
    ``u_curve`` and ``u_point`` (n,): the curve's index (n,) (-1: none; only rows
    ``active`` (n,) bool), the sample's density (n,) (P(curve) times the density of t),
    the side (n,) the edge's faces lie on, and t (n,). With ``triangle`` (n, 3, 3), only
    the curves' parts whose rays meet it (``towards``). NumPy, n x (E + S) arrays."""
    n = len(u_curve)
    weights, side = curves.silhouettes(apex)
    weights = np.array(np.broadcast_to(weights, (n, weights.shape[1])))
    side = np.broadcast_to(side, (n, side.shape[1]))
    if active is not None:
        weights[~active] = 0.0
    lo, hi = np.zeros(weights.shape), np.ones(weights.shape)
    if triangle is not None:
        lo, hi = curves.towards(np.broadcast_to(apex, (n, 3)), triangle)
        angles = _clipped_angle(curves, np.broadcast_to(apex, (n, 3)), weights, lo, hi)
        weights = np.where(weights > 0, angles, 0.0)
    index, probability, faces = _choose(weights, u_curve, side)
    at, rows = np.maximum(index, 0), np.arange(n)
    low, high = lo[rows, at], hi[rows, at]
    t, density = curves.parameter(np.broadcast_to(apex, (n, 3)), at, low, high, u_point)
    index = np.where((high > low) & (index >= 0), index, -1)
    return index, np.where(index >= 0, probability * density, 0.0), faces, t


@jit(cache=True, inline="always")
def _norm(a):
    return np.sqrt(dot3(a, a))


# The draws' helpers: those run per curve and apex are inlined by Numba (``_edge``,
# ``_whole``, ``_clipped``, ``_edge_towards``: as calls, the Cornell box's draws took a
# fifth to a third longer); the others are plain calls, which LLVM inlines by itself
# (Numba's inlining of them doubled the kernel's cold compile, 4 -> 9 s, for no speed).
@jit(cache=True, inline="always")
def _edge(p, a, b, c0, c1, grazing):
    """An edge seen from p: (the angle it subtends, 0 if no silhouette; its faces' side)."""
    pa, pb = sub(a, p), sub(b, p)
    normal = cross(pa, pb)
    d0, d1 = sub(c0, p), sub(c1, p)
    s0, s1 = dot3(d0, normal), dot3(d1, normal)
    # Most edges of a closed mesh are not silhouettes: their faces' far corners lie on
    # opposite sides. Tested first, it spares them the three square roots below (either
    # test alone gives 0; NaN fails both).
    if np.sign(s0) != np.sign(s1):
        return 0.0, 0.0
    size = _norm(normal)
    if not (abs(s0) > grazing * size * _norm(d0) and abs(s1) > grazing * size * _norm(d1)):
        return 0.0, 0.0
    return np.arctan2(size, dot3(pa, pb)), np.sign(s0)


@jit(cache=True, inline="always")
def _edge_towards(p, a, b, tri):
    """(lo, hi): the part of edge a -> b through which rays from p meet the triangle ``tri``
    (its three corners) (``Curves.towards``); lo = hi = 0 if none."""
    e, pa = sub(b, a), sub(a, p)
    normal = cross(pa, sub(b, p))
    v0, v1, v2 = sub(tri[0], p), sub(tri[1], p), sub(tri[2], p)
    # The triangle's sides in turn (written out: a tuple indexed by a variable is slow).
    lo, hi, found = _side_crossing(v0, v1, normal, e, pa, 0.0, 0.0, 0)
    lo, hi, found = _side_crossing(v1, v2, normal, e, pa, lo, hi, found)
    lo, hi, found = _side_crossing(v2, v0, normal, e, pa, lo, hi, found)
    if found < 2:
        return 0.0, 0.0
    return min(max(lo, 0.0), 1.0), min(max(hi, 0.0), 1.0)


@jit(cache=True)
def _side_crossing(vi, vj, normal, e, pa, lo, hi, found):
    """``_edge_towards``'s (lo, hi, found) extended by the triangle's side vi -> vj (corners
    from p), if the plane through p and the edge (``normal``) crosses it: the parameter t
    on the edge a + t e where the ray from p through the crossing meets it."""
    di, dj = dot3(vi, normal), dot3(vj, normal)
    if not di * dj < 0:
        return lo, hi, found
    f = di / (di - dj)
    q = (vi[0] + f * (vj[0] - vi[0]), vi[1] + f * (vj[1] - vi[1]), vi[2] + f * (vj[2] - vi[2]))
    exq = cross(e, q)
    t = dot3(cross((-pa[0], -pa[1], -pa[2]), q), exq) / max(dot3(exq, exq), 1e-300)
    if found == 0:
        return t, t, 1
    return min(lo, t), max(hi, t), found + 1


@jit(cache=True)
def _axes(n):
    """``basis`` for one unit vector."""
    helper = (0.0, 1.0, 0.0) if abs(n[0]) > 0.9 else (1.0, 0.0, 0.0)
    u1 = cross(n, helper)
    length = _norm(u1)
    u1 = (u1[0] / length, u1[1] / length, u1[2] / length)
    return u1, cross(n, u1)


@jit(cache=True)
def _sphere_towards(p, centre, tri):
    """(lo, hi): the azimuths (over 2 pi) about p -> centre that the triangle ``tri`` (its
    three corners) spans."""
    q = sub(centre, p)
    length = max(_norm(q), 1e-300)
    u1, u2 = _axes((q[0] / length, q[1] / length, q[2] / length))
    v0, v1, v2 = sub(tri[0], p), sub(tri[1], p), sub(tri[2], p)
    z0 = np.arctan2(dot3(u2, v0), dot3(u1, v0))
    z1 = np.arctan2(dot3(u2, v1), dot3(u1, v1))
    z2 = np.arctan2(dot3(u2, v2), dot3(u1, v2))
    z0, z1 = _in_order(z0, z1)  # sorted as np.sort sorts (NaN last)
    z1, z2 = _in_order(z1, z2)
    z0, z1 = _in_order(z0, z1)
    # The widest gap between neighbours (the first of equal ones) and the azimuth after it.
    widest, start = z1 - z0, z1
    if z2 - z1 > widest:
        widest, start = z2 - z1, z2
    if z0 + 2 * np.pi - z2 > widest:
        widest, start = z0 + 2 * np.pi - z2, z0
    if widest <= np.pi:
        return 0.0, 1.0
    lo = np.mod(start, 2 * np.pi) / (2 * np.pi)
    return lo, lo + (2 * np.pi - widest) / (2 * np.pi)


@jit(cache=True)
def _in_order(x, y):
    """(x, y) in ascending order, NaN after every number (np.sort's order)."""
    if y < x or (x != x and y == y):
        return y, x
    return x, y


@borrowing
def _curve(p, j, a, b, c, centre, radius, tri, clip, grazing):
    """Curve j seen from p: (weight, side, lo, hi) as ``pick_reference`` has them."""
    weight, side = _whole(p, j, a, b, c, centre, radius, grazing)
    if weight == 0.0 or not clip:
        return weight, side, 0.0, 1.0
    return _clipped(p, j, a, b, centre, weight, side, tri)


@jit(cache=True, inline="always")
def _whole(p, j, a, b, c, centre, radius, grazing):
    """Curve j seen from p, whole: (weight, side): an edge's angle if it is a silhouette
    (``_edge``), a sphere's outline's 2 pi r / distance unless p is inside; 0 else."""
    n_edges = a.shape[0]
    if j < n_edges:
        return _edge(p, a[j], b[j], c[j, 0], c[j, 1], grazing)
    s = j - n_edges
    distance = _norm(sub(centre[s], p))
    if not radius[s] < distance * (1 - 1e-9):
        return 0.0, 0.0
    return 2 * np.pi * radius[s] / max(distance, 1e-300), 0.0


@jit(cache=True, inline="always")
def _clipped(p, j, a, b, centre, weight, side, tri):
    """Curve j seen from p, whose whole weight ``weight`` (> 0) and side are known: (its
    weight, side, lo, hi) clipped to the part whose rays meet triangle ``tri``, as
    ``_curve(..., clip=True)`` gives them (the same operations)."""
    n_edges = a.shape[0]
    if j < n_edges:
        lo, hi = _edge_towards(p, a[j], b[j], tri)
        if hi == lo:  # no ray through the edge meets the triangle (most edges): angle 0
            return 0.0, side, lo, hi
        e = sub(b[j], a[j])
        start = (a[j][0] + lo * e[0] - p[0], a[j][1] + lo * e[1] - p[1],
                 a[j][2] + lo * e[2] - p[2])  # fmt: skip
        end = (a[j][0] + hi * e[0] - p[0], a[j][1] + hi * e[1] - p[1], a[j][2] + hi * e[2] - p[2])
        return np.arctan2(_norm(cross(start, end)), dot3(start, end)), side, lo, hi
    lo, hi = _sphere_towards(p, centre[j - n_edges], tri)
    return weight * (hi - lo), 0.0, lo, hi


@kernel
def _pick(
    job, n_jobs, apex, a, b, c, centre, radius, bounds, usable, tri, clip, active, u_curve,
    u_point, grazing, out,
):  # fmt: skip
    """Job ``job`` of ``n_jobs`` (``minidiff.threads.run_jobs``): for its share of the
    draws, ``pick_reference`` per apex (row i of ``apex``, or row 0 if it has one), twice:
    ``out[0]`` from whole curves (rows ``active[0]``, uniforms ``u_curve[0]``,
    ``u_point[0]``) and, with ``clip``, ``out[1]`` from the curves' parts towards the
    triangles ``tri`` (rows ``active[1]``, the uniforms' row 1). out (2, 4, n): index,
    density, side, t. One pass over the curves serves both (their silhouette tests)."""
    first, stop = share(job, n_jobs, u_curve.shape[1])
    weights = np.zeros((2, a.shape[0] + centre.shape[0]))  # one apex's weights, filled anew
    totals = np.zeros((2, len(usable) + 1))  # and their sums, run by run (the spheres last)
    for i in range(first, stop):
        _pick_one(i, apex, a, b, c, centre, radius, bounds, usable, tri, clip, active, u_curve,
                  u_point, grazing, weights, totals, out)  # fmt: skip


@borrowing
def _pick_one(i, apex, a, b, c, centre, radius, bounds, usable, tri, clip, active, u_curve,
              u_point, grazing, weights, totals, out):  # fmt: skip
    """``_pick``'s draw i, its curves' ``weights`` (2, count) and their sums by runs of
    ``CLUSTER`` edges, ``totals`` (2, runs + 1) (the spheres last), as room (compiled
    without reference counts: its loop over the curves takes a view of each one's row).
    A run that ``_hidden_run`` shows holds no silhouette (``Curves.clusters``) gets a zero
    sum, its weights neither tested nor written (``_draw`` does not read them): a dense
    mesh's draw costs its runs and the few edges near its silhouettes, not every edge."""
    for s in range(2):
        out[s, 0, i], out[s, 1, i], out[s, 2, i], out[s, 3, i] = -1.0, 0.0, 0.0, 0.0
    count = weights.shape[1]
    if count == 0:
        return
    each_apex, each_tri = int(apex.shape[0] > 1), int(tri.shape[0] > 1)  # else row 0 for all
    row, r = i * each_apex, i * each_tri
    p = (apex[row, 0], apex[row, 1], apex[row, 2])
    triangle = ((tri[r, 0, 0], tri[r, 0, 1], tri[r, 0, 2]),
                (tri[r, 1, 0], tri[r, 1, 1], tri[r, 1, 2]),
                (tri[r, 2, 0], tri[r, 2, 1], tri[r, 2, 2]))  # fmt: skip
    n_runs = len(usable)
    for k in range(n_runs + 1):
        first, stop = _run(k, n_runs, a.shape[0], count)
        totals[0, k] = totals[1, k] = 0.0
        if k < n_runs and usable[k] and _hidden_run(p, bounds, k):
            continue
        for j in range(first, stop):
            _weigh_curve(i, j, p, a, b, c, centre, radius, triangle, clip, active, grazing,
                         weights)  # fmt: skip
            totals[0, k] += weights[0, j]
            totals[1, k] += weights[1, j]
    for s in range(2 if clip else 1):
        _draw(p, weights[s], totals[s], u_curve[s, i], u_point[s, i], a, b, c, centre, radius,
              triangle, s == 1, grazing, out[s, :, i])  # fmt: skip


@jit(cache=True, inline="always")
def _run(k, n_runs, n_edges, count):
    """Curves first..stop-1 of run k: ``CLUSTER`` edges, the last run's the rest; run
    ``n_runs``, the spheres."""
    if k == n_runs:
        return n_edges, count
    return k * CLUSTER, min(n_edges, (k + 1) * CLUSTER)


@jit(cache=True, inline="always")
def _weigh_curve(i, j, p, a, b, c, centre, radius, triangle, clip, active, grazing, weights):
    """Curve j's weights for draw i from p: whole (row 0) and towards the triangle (row 1)."""
    weight, side = _whole(p, j, a, b, c, centre, radius, grazing)
    weights[0, j] = weight if active[0, i] else 0.0
    weights[1, j] = 0.0
    if clip and active[1, i] and weight > 0:  # the part towards the triangle
        weights[1, j] = _clipped(p, j, a, b, centre, weight, side, triangle)[0]


def _morton(points: np.ndarray) -> np.ndarray:
    """(n,) int64: the Morton codes of ``points`` (n, 3), 21 bits a coordinate over their
    bounding box: points near each other mostly get codes near each other."""
    low, high = points.min(axis=0), points.max(axis=0)
    cells = np.floor((points - low) / np.where(high > low, high - low, 1.0) * 2097151.0)
    code = np.zeros(len(points), np.int64)
    for axis in range(3):
        x = np.clip(cells[:, axis], 0, 2097151).astype(np.int64)
        for bit in range(21):
            code |= ((x >> bit) & 1) << (3 * bit + axis)
    return code


@jit(cache=True, inline="always")
def _hidden_run(p, bounds, k):
    """Whether p lies on the positive side of every plane of run k (``Curves.clusters``),
    or on the negative side of every one, by a margin: then none of its edges has both
    faces on one side of the plane through p and the edge, and none is a silhouette. With
    w = p - centre, each plane's m . (p - x) is within radius of m . w, and m . w, the
    angle between m and w within the cone's half-angle theta of phi (the axis's to w), is
    at least |w| cos(phi + theta) and at most |w| cos(phi - theta) (where phi - theta >=
    0; these bounds only decide where phi + theta or phi - theta lies past a quarter
    turn)."""
    w = (p[0] - bounds[k, 5], p[1] - bounds[k, 6], p[2] - bounds[k, 7])
    d = _norm(w)
    radius = bounds[k, 8]
    if not d > radius:  # p within the sphere: no bound
        return False
    cos_phi = (w[0] * bounds[k, 0] + w[1] * bounds[k, 1] + w[2] * bounds[k, 2]) / d
    cos_phi = min(1.0, max(-1.0, cos_phi))
    sin_phi = np.sqrt(1.0 - cos_phi * cos_phi)
    cos_t, sin_t = bounds[k, 3], bounds[k, 4]
    margin = RUN_MARGIN * (d + radius)
    low = d * (cos_phi * cos_t - sin_phi * sin_t)  # |w| cos(phi + theta)
    if low - radius > margin and cos_phi * cos_t - sin_phi * sin_t > 0:
        return True
    high = d * (cos_phi * cos_t + sin_phi * sin_t)  # |w| cos(phi - theta)
    return high + radius < -margin and cos_phi < 0


@borrowing
def _draw(p, weights, totals, u_curve, u_point, a, b, c, centre, radius, triangle, clip,
          grazing, out):  # fmt: skip
    """One curve drawn by its ``weights`` (count,), summed by runs in ``totals`` (runs +
    1,) (``_pick_one``: a run summed to zero holds no weight, and its weights are not
    read), and a point on it, into out (4,): the run where the running sum of the runs
    reaches u_curve times their total, then the curve in it where the running sum of its
    weights does (or its last curve with weight, should rounding leave that sum short)."""
    total = 0.0
    for k in range(len(totals)):
        total += totals[k]
    if not total > 0:
        return
    target, running, run = u_curve * total, 0.0, len(totals) - 1
    for k in range(len(totals)):
        if totals[k] > 0 and not running + totals[k] < target:
            run = k
            break
        running += totals[k]
    while not totals[run] > 0:  # rounding left the target past the last run with weight
        run -= 1
    first, stop = _run(run, len(totals) - 1, a.shape[0], len(weights))
    chosen = first
    for j in range(first, stop):
        if weights[j] > 0:
            chosen = j
            running += weights[j]
            if not running < target:
                break
    weight, faces, lo, hi = _curve(p, chosen, a, b, c, centre, radius, triangle, clip, grazing)
    if not (weight > 0 and hi > lo):
        return
    probability = weight / total
    if chosen >= a.shape[0]:  # uniform in azimuth
        out[0], out[1], out[2] = chosen, probability / (hi - lo), 0.0
        out[3] = lo + u_point * (hi - lo)
        return
    e = sub(b[chosen], a[chosen])
    start = (a[chosen][0] + lo * e[0] - p[0], a[chosen][1] + lo * e[1] - p[1],
             a[chosen][2] + lo * e[2] - p[2])  # fmt: skip
    end = (a[chosen][0] + hi * e[0] - p[0], a[chosen][1] + hi * e[1] - p[1],
           a[chosen][2] + hi * e[2] - p[2])  # fmt: skip
    ls, le = _norm(start), _norm(end)
    start = (start[0] / ls, start[1] / ls, start[2] / ls)
    end = (end[0] / le, end[1] / le, end[2] / le)
    angle = np.arctan2(_norm(cross(start, end)), dot3(start, end))
    c_ = dot3(end, start)
    tw = (end[0] - c_ * start[0], end[1] - c_ * start[1], end[2] - c_ * start[2])
    lt = _norm(tw)
    tw = (tw[0] / lt, tw[1] / lt, tw[2] / lt)
    psi = u_point * angle
    d = (np.cos(psi) * start[0] + np.sin(psi) * tw[0],
         np.cos(psi) * start[1] + np.sin(psi) * tw[1],
         np.cos(psi) * start[2] + np.sin(psi) * tw[2])  # fmt: skip
    exd = cross(e, d)
    ti = dot3(cross(sub(p, a[chosen]), d), exd) / max(dot3(exd, exd), 1e-300)
    w = (a[chosen][0] + ti * e[0] - p[0], a[chosen][1] + ti * e[1] - p[1],
         a[chosen][2] + ti * e[2] - p[2])  # fmt: skip
    rate = _norm(cross(w, e)) / dot3(w, w)  # dpsi / dt
    density = probability * rate / (angle if angle > 0 else 1.0)
    if np.isfinite(density) and density > 0 and np.isfinite(ti):  # else an edge seen end-on
        out[0], out[1], out[2], out[3] = chosen, density, faces, ti
