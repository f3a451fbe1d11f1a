"""Secondary visibility's boundary term for the path integrator: soft shadows, hard shadows
seen after a bounce, and indirect occlusion.

``render.path.transport`` writes a path in area measure: every vertex after the camera's is a
fixed place on its surface (barycentrics), so the integral over the next vertex x' of a
vertex x is over surfaces that move with the parameters, and the only discontinuities left
inside it are those of visibility V(x, x'). Where the segment x -> x' grazes an occluder's
silhouette (a mesh edge whose two faces lie on one side of the plane through x and the
edge, a mesh's border, a sphere's outline as seen from x), V jumps between 1 and 0 along a
curve on the surfaces behind, and that curve moves with the parameters. Reynolds'
transport theorem gives the derivative of the integral: the interior term the tape
computes, plus

    int_curve  (F_+ - F_-) dphi/dtheta / |grad_S phi|  dl

where phi(x') is a level set function that is zero on the curve (positive on the side
marked +), F the integrand in area measure, grad_S phi its gradient along the surface and
dl the curve's length. For a mesh edge (a, b) seen from x: phi = (x' - x) . ((a - x) x
(b - x)); for a sphere (c, r): phi = distance(c, line(x, x')) - r. Where the occluder is,
F = 0; on the other side F is the whole path through x' (``docs/path_tracing.md`` has the
derivation). Next-event estimation needs no term of its own: its point on an area light is
one more x' in the same area measure, and its MIS weight and the BSDF-sampled one sum to 1.

The estimator, per vertex x_k of a path (k >= 1; not after a mirror, see below): pick a
silhouette with probability proportional to the angle it subtends at x_k, a point m on it
uniformly, trace the ray x_k -> m (it must reach m) and on beyond m to x'; the sample is

    beta_k f_k G(x_k, x') L(x' -> x_k) |dx'/dt| / |grad_S phi| / P(curve) * sign * dphi/dtheta,

beta_k the path's weight up to x_k, L estimated by a path continued from x' (its emission
counted whole). A point light at l casts hard shadows: its NEE at x' jumps where the
segment x' -> l grazes a silhouette seen from l, a curve on the surfaces, in the integral
over x' from x_k. The same construction with l as the apex samples it; the jump is the
light's contribution at x'. Everything but dphi/dtheta is a constant computed off the tape
(``path_radiance`` under ``no_grad`` for beta_k f_k G L); phi is recomputed on the tape from
x_k, x' (their places on their surfaces), the curve and the light, so ``backward`` reaches
every parameter that moves them. Each sample's value is phi - phi = 0: the term adds
nothing to the image.

Not covered: vertices reached through a mirror (their position on the tape is a chain of
reflections), directional lights' shadows after a bounce, an environment seen past an edge
after a bounce, and occluders in contact with the surface behind them (a block standing on
the floor: its bottom edges are skipped, which is exact while the contact holds).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np

import minidiff as md
from render.path import kernel
from render.path.random import uniform
from render.path.sampling import dot, unit
from render.path.tracer import AREA, MIRROR, STOP, PathBatch, PathSampler, Vertices
from render.path.transport import path_radiance, vertex_on_tape
from render.scene.camera import ray_directions
from render.scene.lights import PointLight
from render.scene.scene import Mesh
from render.shade.surface import column, geometric_normals, in_order
from render.trace.primitives import primitive_ranges
from render.trace.topology import mesh_edges
from render.trace.visibility import shadow_offset

#: The boundary paths' seed is the render's seed XOR this (independent of the image's).
SEED_KEY = 0x5EC0_DA7A_0B0D_1E55
#: The seed of the curve choices: the boundary paths' seed XOR this times (1 + light index).
CHOICE_KEY = 0x2545_F491_4F6C_DD1D
#: Boundary paths traced together (bounds the memory of one chunk's tape).
CHUNK_PATHS = 1 << 14
#: A surface closer than this (a fraction of the scene's size) behind an edge touches it.
CONTACT = 1e-5
#: A face whose plane passes within this angle of the apex is seen edge-on: not a silhouette.
GRAZING = 1e-9


@dataclass
class Curves:
    """Where visibility can change, as plain world-space arrays: mesh edges (E of them)
    with their endpoints ``a``, ``b`` (E, 3), the third vertices ``c`` (E, 2, 3) of the
    faces on either side (a border edge: its one face twice), the owning object (E,) and
    the endpoints' vertex ids in it ``ends`` (E, 2) (coincident vertices welded, as
    ``render.trace.topology`` does; where more than two faces meet, the first two); and
    spheres (S): ``centre`` (S, 3), ``radius`` (S,), object (S,). Edges between two faces
    of one plane never are silhouettes and are left out."""

    a: np.ndarray
    b: np.ndarray
    c: np.ndarray
    edge_object: np.ndarray
    ends: np.ndarray
    centre: np.ndarray
    radius: np.ndarray
    sphere_object: np.ndarray

    @classmethod
    def of(cls, sampler: PathSampler) -> Curves:
        parts, spheres = [], []
        for o, obj in enumerate(sampler.objects):
            if not isinstance(obj, Mesh):
                spheres.append((o, obj.center.data, float(obj.radius.data)))
                continue
            vertices, faces = np.asarray(obj.vertices.data, np.float64), np.asarray(obj.faces)
            # Welded: a box whose sides have their own vertices still has shared edges.
            table = mesh_edges(vertices, faces).table
            both = np.where(table.faces[:, 1:2] >= 0, table.faces[:, :2], table.faces[:, :1])
            thirds = np.where(table.faces[:, 1:2] >= 0, table.thirds[:, :2], table.thirds[:, :1])
            tri = vertices[faces]
            normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            n1, n2 = normal[both[:, 0]], normal[both[:, 1]]
            flat = (
                (table.faces[:, 1] >= 0)
                & (
                    np.linalg.norm(np.cross(n1, n2), axis=1)
                    <= 1e-9 * np.linalg.norm(n1, axis=1) * np.linalg.norm(n2, axis=1)
                )
                & (dot(n1, n2) > 0)
            )
            keep = ~flat
            e = np.stack([table.i[keep], table.j[keep]], axis=1)
            parts.append((o, vertices, e, thirds[keep, 0], thirds[keep, 1]))
        a = [v[e[:, 0]] for _, v, e, _, _ in parts]
        b = [v[e[:, 1]] for _, v, e, _, _ in parts]
        c = [np.stack([v[t1], v[t2]], axis=1) for _, v, _, t1, t2 in parts]
        return cls(
            _rows(a, (0, 3)), _rows(b, (0, 3)), _rows(c, (0, 2, 3)),
            _rows([np.full(len(e), o) for o, _, e, _, _ in parts], (0,)).astype(np.int64),
            _rows([e for _, _, e, _, _ in parts], (0, 2)).astype(np.int64),
            np.array([s[1] for s in spheres], np.float64).reshape(-1, 3),
            np.array([s[2] for s in spheres], np.float64),
            np.array([s[0] for s in spheres], np.int64),
        )  # fmt: skip

    @property
    def n_edges(self) -> int:
        return len(self.a)

    def silhouettes(self, apex: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For apexes (n, 3): the angle (n, E + S) each curve subtends there, zero where it
        is no silhouette (edges first, then spheres), and the side (n, E) of the plane
        through apex and edge that the edge's faces lie on (+1 or -1)."""
        pa, pb = self.a[None] - apex[:, None], self.b[None] - apex[:, None]  # (n, E, 3)
        normal = np.cross(pa, pb)
        size = np.linalg.norm(normal, axis=2)
        pc = self.c[None] - apex[:, None, None]  # (n, E, 2, 3)
        side = np.einsum("neij,nej->nei", pc, normal)
        sure = np.abs(side) > GRAZING * size[..., None] * np.linalg.norm(pc, axis=3)
        silhouette = sure.all(axis=2) & (np.sign(side[..., 0]) == np.sign(side[..., 1]))
        angle = np.where(silhouette, np.arctan2(size, np.einsum("nej,nej->ne", pa, pb)), 0.0)
        distance = np.linalg.norm(self.centre[None] - apex[:, None], axis=2)  # (n, S)
        around = self.radius < distance * (1 - 1e-9)
        circle = np.where(around, 2 * np.pi * self.radius / np.maximum(distance, 1e-300), 0.0)
        return np.concatenate([angle, circle], axis=1), np.sign(side[..., 0])

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
        u1, u2 = _basis(d.reshape(-1, 3))
        u1, u2 = u1.reshape(d.shape), u2.reshape(d.shape)
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

    def point(self, apex: np.ndarray, index: np.ndarray, t: np.ndarray):
        """The point m (n, 3) at parameter t (n,) on curves ``index`` (n,) (all valid), and
        dm/dt (n, 3): along an edge from a (t = 0) to b (t = 1); around the circle where the
        cone from the apex (n, 3) touches a sphere (azimuth 2 pi t)."""
        m, tangent = np.zeros((len(index), 3)), np.zeros((len(index), 3))
        edge = index < self.n_edges
        j = index[edge]
        tangent[edge] = self.b[j] - self.a[j]
        m[edge] = self.a[j] + t[edge, None] * tangent[edge]
        ball = ~edge
        s = index[ball] - self.n_edges
        q = self.centre[s] - apex[ball]
        d2 = dot(q, q)
        r = self.radius[s]
        centre = apex[ball] + q * (1 - r * r / d2)[:, None]
        rho = r * np.sqrt(d2 - r * r) / np.sqrt(d2)
        u1, u2 = _basis(q / np.sqrt(d2)[:, None])
        tau = 2 * np.pi * t[ball]
        cos, sin = np.cos(tau)[:, None], np.sin(tau)[:, None]
        m[ball] = centre + rho[:, None] * (cos * u1 + sin * u2)
        tangent[ball] = 2 * np.pi * rho[:, None] * (cos * u2 - sin * u1)
        return m, tangent

    def gradient(self, apex, index, points) -> np.ndarray:
        """(n, 3): the gradient in x' of the curve's level set function phi (module
        docstring) at ``points`` x' (n, 3), seen from ``apex`` (n, 3)."""
        grad = np.zeros((len(index), 3))
        edge = index < self.n_edges
        j = index[edge]
        grad[edge] = np.cross(self.a[j] - apex[edge], self.b[j] - apex[edge])
        ball = ~edge
        w, q = points[ball] - apex[ball], self.centre[index[ball] - self.n_edges] - apex[ball]
        ww, wq = dot(w, w), dot(w, q)
        distance = np.linalg.norm(np.cross(w, q), axis=1) / np.sqrt(ww)
        grad[ball] = -(wq / (np.maximum(distance, 1e-300) * ww))[:, None] * (
            q - (wq / ww)[:, None] * w
        )
        return grad


def _rows(parts: list[np.ndarray], empty: tuple) -> np.ndarray:
    return np.concatenate(parts) if parts else np.zeros(empty)


def _basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (k, 3) orthogonal to the unit n (k, 3) and to each other."""
    helper = np.where(np.abs(n[:, :1]) > 0.9, [[0.0, 1.0, 0.0]], [[1.0, 0.0, 0.0]])
    u1 = unit(np.cross(n, helper))
    return u1, np.cross(n, u1)


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


@dataclass
class _Crossing:
    """Boundary samples behind curves: which are valid (n,) bool; for the valid ones (k of
    them, in order), x' on primitive ``prim`` (k,) at ``local`` (k, 3), ``points`` (k, 3),
    its geometric normal facing ``viewer`` (k, 3) and the constant weight |dx'/dt| /
    |grad_S phi| / P(curve) * sign (k,)."""

    valid: np.ndarray
    prim: np.ndarray
    local: np.ndarray
    points: np.ndarray
    normal: np.ndarray
    weight: np.ndarray
    index: np.ndarray


def _cross(sampler, curves: Curves, apex, index, probability, side, t, viewer, origin):
    """Boundary samples behind the curves ``index`` (n,) (-1: none) seen from ``apex``
    (n, 3): the point at t (n,) on the curve must be seen from the apex (rays leave from
    ``origin`` (n, 3), the apex lifted off its surface), and the first surface beyond it,
    x', must not touch the curve; its normal is turned to face ``viewer`` (n, 3).
    ``probability`` (n,): the density of the sample, P(curve) times the density of t."""
    valid = (index >= 0) & (probability > 0)
    rows = np.flatnonzero(valid)
    m, tangent = curves.point(apex[rows], index[rows], t[rows])
    to = m - origin[rows]
    seen = ~sampler.accelerator.occluded(origin[rows], to, 1.0 - 1e-7, tmin=0.0)
    direction = unit(m - apex[rows])
    size = sampler.size
    prim, far, u, v = sampler.accelerator.closest_hit(m, direction, tmin=1e-9 * size)
    ok = seen & (prim >= 0) & (far > CONTACT * size)
    rows, m, tangent, direction = rows[ok], m[ok], tangent[ok], direction[ok]
    prim, far, u, v = prim[ok], far[ok], u[ok], v[ok]
    points = m + far[:, None] * direction
    local = sampler._local(prim, points, u, v)
    normal = geometric_normals(sampler.primitives, prim, points)
    normal *= np.where(dot(normal, viewer[rows] - points) < 0, -1.0, 1.0)[:, None]
    # |dx'/dt|: x' is m projected from the apex onto the plane of x'.
    w = m - apex[rows]
    stretch = np.linalg.norm(points - apex[rows], axis=1) / np.linalg.norm(w, axis=1)
    wn = dot(w, normal)
    along = stretch * np.linalg.norm(
        tangent - (dot(tangent, normal) / np.where(wn != 0, wn, 1.0))[:, None] * w, axis=1
    )
    grad = curves.gradient(apex[rows], index[rows], points)
    across = np.linalg.norm(grad - dot(grad, normal)[:, None] * normal, axis=1)
    # Edges: F is 0 on the faces' side of phi; spheres: inside the cone (phi < 0).
    sign = np.where(index[rows] < curves.n_edges, -side[rows], 1.0)
    good = (wn != 0) & (across > 0)
    weight = np.where(good, along / np.where(good, across, 1.0), 0.0) * sign / probability[rows]
    valid = np.zeros(len(index), bool)
    valid[rows] = good
    keep = good
    return _Crossing(valid, prim[keep], local[keep], points[keep], normal[keep], weight[keep],
                     index[rows][keep])  # fmt: skip


def add_secondary_term(world, image: md.Tensor, frame, sampler: PathSampler) -> md.Tensor:
    """The image (H, W, 3) plus secondary visibility's boundary term (zero in value),
    estimated with ``sampler.spp`` boundary paths per pixel; on the tape of ``world``."""
    terms = [t for t in _chunks(world, frame, sampler) if t is not None]
    if not terms:
        return image
    camera = world.camera
    values = md.concatenate([v for v, _ in terms]) if len(terms) > 1 else terms[0][0]
    pixels = np.concatenate([p for _, p in terms])
    term = md.scatter_add(values, pixels, camera.width * camera.height) * (1.0 / sampler.spp)
    return image + md.reshape(term, image.shape)


def backpropagate_secondary(placed_world, sampler: PathSampler, d_image: np.ndarray) -> None:
    """Add d_image . d term / d p to the gradients of the parameters, ``d_image`` (H, W, 3)
    dL/dimage: one boundary chunk at a time, each on a fresh tape from ``placed_world()``
    (memory bounded by a chunk, whatever the spp)."""
    from render.scene.camera import camera_frame

    weights = d_image.reshape(-1, 3) * (1.0 / sampler.spp)
    for chunk in _paths(sampler):
        world = placed_world()
        term = _chunk(world, camera_frame(world.camera), sampler, chunk, None)
        if term is not None and term[0].requires_grad:
            values, pixels = term
            md.sum(values * weights[pixels]).backward()


def _paths(sampler: PathSampler):
    camera = sampler.scene.camera
    total = camera.width * camera.height * sampler.spp
    for start in range(0, total, CHUNK_PATHS):
        yield np.arange(start, min(start + CHUNK_PATHS, total), dtype=np.int64)


def _chunks(world, frame, sampler):
    for chunk in _paths(sampler):
        yield _chunk(world, frame, sampler, chunk, None)


def _chunk(world, frame, sampler: PathSampler, paths: np.ndarray, packed):
    """(values (M, 3) on the tape, pixel (M,)) of the boundary samples of boundary paths
    ``paths``, or None when there are none."""
    own = copy.copy(sampler)
    own.seed = (sampler.seed ^ SEED_KEY) & (2**64 - 1)
    if kernel.applies(own.scene):
        batch, _ = kernel.sample_paths(own, paths)
    else:
        batch = own.sample(paths)
    curves = Curves.of(own)
    if curves.n_edges + len(curves.radius) == 0:
        return None
    points = _points(own, batch)
    values, pixels = [], []
    for k in range(1, min(len(batch.vertices), own.max_depth - 1) + 1):
        for term in _terms_at(own, curves, batch, points, k, world, frame):
            values.append(term[0])
            pixels.append(batch.paths[term[1]] // own.spp)
    if not values:
        return None
    joined = md.concatenate(values) if len(values) > 1 else values[0]
    return joined, np.concatenate(pixels)


def _points(sampler, batch: PathBatch) -> list[np.ndarray]:
    """Each depth's vertex positions (k, 3), plain, from their places on their primitives
    (or, at camera and mirror vertices, where their rays met them: the same point)."""
    out = []
    triangles, centres, radii = sampler.primitives
    for record in batch.vertices:
        prim, local = record.prim, record.local
        p = np.zeros((len(prim), 3))
        tri = prim < sampler.n_triangles
        t = triangles[prim[tri]]
        u, v = local[tri, :1], local[tri, 1:2]
        p[tri] = (1 - u - v) * t[:, 0] + u * t[:, 1] + v * t[:, 2]
        s = prim[~tri] - sampler.n_triangles
        p[~tri] = centres[s] + radii[s, None] * local[~tri]
        out.append(p)
    return out


def _terms_at(sampler, curves, batch, points, k: int, world, frame):
    """The boundary samples at the paths' k-th vertices: behind silhouettes seen from
    them (the next segment's visibility) and, for every point light, behind silhouettes
    seen from the light (its shadow at the next vertex). Yields (values (M, 3), the
    samples' rows in the batch (M,))."""
    record = batch.vertices[k - 1]
    rows = record.rows
    eye = sampler.frame[3]
    if k == 1:
        previous = np.broadcast_to(eye, (len(rows), 3))
    else:
        before = batch.vertices[k - 2]
        previous = points[k - 2][np.searchsorted(before.rows, rows)]
    here = points[k - 1]
    normal = geometric_normals(sampler.primitives, record.prim, here)
    normal *= np.where(dot(normal, previous - here) < 0, -1.0, 1.0)[:, None]
    obj = np.searchsorted(sampler.first, record.prim, side="right") - 1
    lobes = sampler.lobes.probability[obj]
    can = (record.form != MIRROR) & (lobes[:, 0] + lobes[:, 1] > 0)
    ids = batch.paths[rows]
    origin = here + shadow_offset(here, sampler.size) * normal
    dims = 2 + 8 * (k - 1)  # bounce k's block of dimensions (render.path.random)
    seed = sampler.seed ^ CHOICE_KEY
    weights, side = curves.silhouettes(here)
    weights[~can] = 0.0

    # Two estimators of the next segment's term, for two parts of F: x''s emission, by
    # curves clipped to where their rays meet an emitter picked as NEE picks it (a soft
    # shadow's edges are mostly seen against the light); and all the rest, by whole curves.
    emitters = sampler.emitters
    if len(emitters):
        row = emitters.pick(uniform(seed, ids, dims + 2))
        target = emitters.prims[row]
        on = target < sampler.n_triangles
        triangle = sampler.primitives[0][np.where(on, target, 0)]
        lo, hi = curves.towards(here, triangle)
        lo[~on], hi[~on] = 0.0, 1.0
        clipped = np.where(weights > 0, _clipped_angle(curves, here, weights, lo, hi), 0.0)
        index, probability, faces = _choose(clipped, uniform(seed, ids, dims + 3), side)
        at, every = np.maximum(index, 0), np.arange(len(ids))
        low, high = lo[every, at], hi[every, at]
        t, density = curves.parameter(here, at, low, high, uniform(seed, ids, dims + 4))
        probability = probability * emitters.probability[row] * density
        index = np.where(high > low, index, -1)
        cross = _cross(sampler, curves, here, index, probability, faces, t, here, origin)
        sub = np.flatnonzero(cross.valid)
        keep = (dot(normal[sub], cross.points - here[sub]) > 0) & (cross.prim == target[sub])
        yield from _segment(world, frame, sampler, curves, batch, k, cross, keep, here, True)

    index, probability, faces = _choose(weights, uniform(seed, ids, dims), side)
    ones = np.ones(len(ids))
    t, density = curves.parameter(here, np.maximum(index, 0), 0 * ones, ones,
                                  uniform(seed, ids, dims + 1))  # fmt: skip
    probability = probability * density
    cross = _cross(sampler, curves, here, index, probability, faces, t, here, origin)
    front = dot(normal[cross.valid], cross.points - here[cross.valid]) > 0
    yield from _segment(world, frame, sampler, curves, batch, k, cross, front, here, False)

    # Point lights' shadows at x' seen from x_k (x' must still get the light's NEE).
    if k + 1 > sampler.max_depth - 1:
        return
    for j, light in enumerate(sampler.scene.lights):
        if not isinstance(light, PointLight):
            continue
        seed_j = sampler.seed ^ ((CHOICE_KEY * (j + 2)) & (2**64 - 1))
        u, t = uniform(seed_j, ids, dims), uniform(seed_j, ids, dims + 1)
        at = np.asarray(light.position.data, np.float64)[None]
        seen, side = curves.silhouettes(at)  # the same silhouettes for every x_k
        index, probability, side = _choose(seen, u, side)
        index = np.where(can, index, -1)
        apex = np.repeat(at, len(ids), 0)
        ones = np.ones(len(ids))
        t, density = curves.parameter(apex, np.maximum(index, 0), 0 * ones, ones, t)
        probability = probability * density
        cross = _cross(sampler, curves, apex, index, probability, side, t, here, apex)
        sub = np.flatnonzero(cross.valid)
        to = cross.points - here[sub]
        ok = (dot(normal[sub], to) > 0) & (dot(cross.normal, at - cross.points) > 0)
        ok &= ~sampler.accelerator.occluded(origin[sub], cross.points - origin[sub],
                                            1.0 - 1e-7, tmin=0.0)  # fmt: skip
        yield from _shadow(world, frame, sampler, curves, batch, k, cross, ok, here, j)


def _segment(world, frame, sampler, curves, batch, k, cross, keep, here, emission: bool):
    """The samples behind silhouettes seen from x_k that ``keep`` selects: with
    ``emission``, x''s emission alone; else the path through x' continued from there, but
    for the emission of the emitters (the other estimator's). Yields (values (M, 3), rows
    in the batch (M,))."""
    record = batch.vertices[k - 1]
    sub = np.flatnonzero(cross.valid)[keep]
    if len(sub) == 0:
        return
    hit = _take(cross, keep)
    src = record.rows[sub]
    m = len(src)
    prefix = _prefix(sampler, batch, k, src, here[sub], hit)
    if emission:
        lights = np.zeros((len(sampler.scene.lights), m), bool)
        tail = [_quiet(np.arange(m), hit.prim, hit.local, np.full(m, AREA, np.int8), lights)]
        tail[0].emit_weight[:] = 1.0
    else:
        tail = sampler.resume(batch.paths[src], k + 1, hit.prim, hit.local, hit.points, here[sub])
        tail[0].emit_weight[:] = np.where(sampler.emitters.row_of[hit.prim] >= 0, 0.0, 1.0)
    yield _value(world, frame, sampler, curves, batch, k, src, hit, prefix + tail, None), src


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


def _shadow(world, frame, sampler, curves, batch, k, cross, ok, here, j):
    """The samples on point light j's shadow border seen from x_k: the jump is the light's
    contribution at x'. Yields (values (M, 3), rows in the batch (M,))."""
    record = batch.vertices[k - 1]
    sub = np.flatnonzero(cross.valid)[ok]
    if len(sub) == 0:
        return
    hit = _take(cross, ok)
    src = record.rows[sub]
    m = len(src)
    prefix = _prefix(sampler, batch, k, src, here[sub], hit)
    lit = np.zeros((len(sampler.scene.lights), m), bool)
    lit[j] = True
    last = _quiet(np.arange(m), hit.prim, hit.local, np.full(m, AREA, np.int8), lit)
    yield _value(world, frame, sampler, curves, batch, k, src, hit, prefix + [last], j), src


def _take(cross: _Crossing, keep: np.ndarray) -> _Crossing:
    """The valid samples of ``cross`` that ``keep`` (over the valid ones) selects."""
    return _Crossing(cross.valid, cross.prim[keep], cross.local[keep], cross.points[keep],
                     cross.normal[keep], cross.weight[keep], cross.index[keep])  # fmt: skip


def _quiet(rows, prim, local, form, lit) -> Vertices:
    """A vertex record that gains nothing but from the lights ``lit`` (L, m) and stops."""
    m = len(rows)
    return Vertices(rows, prim, local, form, np.zeros(m), np.full(m, -1, np.int64),
                    np.zeros((m, 3)), np.zeros(m), lit, np.full(m, STOP, np.int8), np.ones(m),
                    np.ones(m), np.zeros(m, bool), np.zeros((m, 3)))  # fmt: skip


def _prefix(sampler, batch, k, src, here, hit: _Crossing) -> list[Vertices]:
    """The records of depths 1..k of the batch's paths ``src`` (m,), renumbered 0..m-1,
    that gain nothing on the way (their emission, NEE and lights belong to the image) and
    go on from x_k (``here`` (m, 3)) to x' (``hit``) with density 1 in area measure."""
    m = len(src)
    records = []
    for d in range(k):
        rec = batch.vertices[d]
        pos = np.searchsorted(rec.rows, src)
        out = _quiet(np.arange(m), rec.prim[pos], rec.local[pos], rec.form[pos],
                     np.zeros((len(sampler.scene.lights), m), bool))  # fmt: skip
        out.next, out.next_pdf, out.survive = rec.next[pos], rec.next_pdf[pos], rec.survive[pos]
        records.append(out)
    to = hit.points - here
    d2 = dot(to, to)
    cos = np.abs(dot(hit.normal, to)) / np.sqrt(d2)
    last = records[-1]
    # The tape's factor f cos / next_pdf times its change of measure (value 1): with
    # next_pdf = r^2 / cos', f G, the integrand in area measure.
    last.next, last.next_pdf, last.survive = np.full(m, AREA, np.int8), d2 / cos, np.ones(m)
    return records


def _value(world, frame, sampler, curves, batch, k, src, hit, records, light):
    """(m, 3) on the tape: each sample's constant F |dx'/dt| / |grad_S phi| / P * sign
    (F: the radiance of the path ``records``, computed off the tape) times phi - phi."""
    rays = PathBatch(batch.paths[src], batch.coords[src], np.zeros(len(src), bool), records)
    with md.no_grad():
        radiance = path_radiance(world, frame, sampler, rays).data
    record = batch.vertices[k - 1]
    pos = np.searchsorted(record.rows, src)
    dtype = radiance.dtype
    if light is None:  # the apex is x_k itself
        directions = ray_directions(frame, batch.coords[src].astype(dtype))
        origins = md.broadcast_to(frame[3], (len(src), 3))
        apex = vertex_on_tape(world, sampler, record.prim[pos], record.local[pos],
                              record.form[pos], origins, directions).points  # fmt: skip
    else:
        apex = md.broadcast_to(world.lights[light].position, (len(src), 3))
    far = vertex_on_tape(world, sampler, hit.prim, hit.local, np.full(len(src), AREA, np.int8),
                         None, None).points  # fmt: skip
    phi = _phi(world, curves, hit.index, apex, far)
    moved = phi - md.tensor(phi.data)  # zero, with phi's derivative
    return md.tensor(radiance * hit.weight[:, None]) * column(moved)


def _phi(world, curves: Curves, index, apex, far) -> md.Tensor:
    """(m,) on the tape: the level set function phi (module docstring) of curves ``index``
    (m,) seen from ``apex`` (m, 3), at the points ``far`` (m, 3)."""
    owners = [obj for obj, _, _ in primitive_ranges(world)]
    parts, order = [], []
    edge = index < curves.n_edges
    for o in np.unique(curves.edge_object[index[edge]]):
        rows = np.flatnonzero(edge & (curves.edge_object[np.where(edge, index, 0)] == o))
        ends = curves.ends[index[rows]]
        vertices = owners[o].vertices
        p = apex[rows]
        normal = md.cross(vertices[ends[:, 0]] - p, vertices[ends[:, 1]] - p)
        parts.append(md.dot(far[rows] - p, normal))
        order.append(rows)
    for s in np.unique(index[~edge] - curves.n_edges):
        rows = np.flatnonzero(index == curves.n_edges + s)
        sphere = owners[curves.sphere_object[s]]
        p = apex[rows]
        w, q = far[rows] - p, md.broadcast_to(sphere.center, (len(rows), 3)) - p
        across = md.cross(w, q)
        parts.append(md.sqrt(md.dot(across, across) / md.dot(w, w)) - sphere.radius)
        order.append(rows)
    return in_order(parts, order)
