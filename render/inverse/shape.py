"""Shape optimisation: every vertex of a mesh a parameter, with the tools the field uses.

* ``mesh_laplacian``: the uniform (combinatorial) graph Laplacian L = D - A of a mesh's
  edges, a SciPy sparse matrix; ``laplacian_loss`` the smoothness term mean |L v|^2.
* ``LargeSteps`` (Nicolet, Jacobson and Jakob 2021, "Large Steps in Inverse Rendering of
  Geometry"): optimise u = (I + lambda L) v instead of the vertices v. A gradient step on u
  is a step on v filtered by (I + lambda L)^-1, a smoothing that suppresses the
  high-frequency part of the gradient, which is what crumples a mesh optimised vertex by
  vertex; the matrix is factorised once (SciPy's sparse LU) and each step solves with it.
  ``LargeStepsAdam`` is the optimiser they pair it with (uniform Adam on u), written as an
  optimiser of the mesh's own ``vertices`` tensor, so that ``render.optimize`` runs it
  unchanged.
* ``weld``: one vertex per distinct position (a mesh made of patches, like the teapot,
  repeats its seams' vertices; moved apart, they open cracks).
* ``subdivide`` (between coarse-to-fine stages), ``icosphere`` (the usual start), and the
  field's error measures: ``surface_distances`` (symmetric Chamfer and Hausdorff distances
  between surface samples, as a percentage of the bounding-box diagonal).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import trimesh
from scipy.sparse.linalg import splu
from scipy.spatial import cKDTree

import minidiff as md
from render.trace.topology import welded_ids

__all__ = [
    "mesh_laplacian",
    "laplacian_loss",
    "LargeSteps",
    "LargeStepsAdam",
    "weld",
    "subdivide",
    "icosphere",
    "SurfaceDistances",
    "surface_distances",
]


def mesh_edges(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """(E, 2) the mesh's undirected edges (i < j), each once. ValueError naming ``faces`` if
    an index is out of range, if a face repeats a vertex index (a degenerate face: its
    "edge" (i, i) is no edge, and its other two are one edge counted twice), or if an edge
    is shared by more than two faces (a non-manifold edge: the Laplacian and Large Steps
    assume a surface)."""
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.dtype.kind not in "iu" or not len(faces):
        raise ValueError(f"faces must be a non-empty (F, 3) integer array, got {faces.shape}")
    if faces.min() < 0 or faces.max() >= n_vertices:
        raise ValueError(f"faces: indices must lie in [0, {n_vertices}) (the vertices)")
    repeats = (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2])
    repeats |= faces[:, 2] == faces[:, 0]
    if repeats.any():
        k = int(np.argmax(repeats))
        raise ValueError(
            f"faces: face {k} {faces[k].tolist()} repeats a vertex index (a degenerate face; "
            f"{int(repeats.sum())} such faces): remove them (``weld`` does)"
        )
    pairs = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    edges, counts = np.unique(pairs, axis=0, return_counts=True)
    if counts.max() > 2:
        i, j = edges[np.argmax(counts)]
        raise ValueError(
            f"faces: the edge ({i}, {j}) is shared by {counts.max()} faces (non-manifold; "
            f"{int(np.sum(counts > 2))} such edges): a Laplacian needs a surface whose edges "
            "border one or two faces"
        )
    return edges


def mesh_laplacian(faces: np.ndarray, n_vertices: int) -> sp.csr_matrix:
    """The uniform graph Laplacian L = D - A (n_vertices, n_vertices), CSR: A the adjacency
    of the mesh's edges, D its row sums. (L v)_i = deg(i) v_i - sum of i's neighbours: zero
    where v is locally an average of its neighbours. Symmetric, positive semi-definite."""
    edges = mesh_edges(faces, n_vertices)
    i, j = np.concatenate([edges[:, 0], edges[:, 1]]), np.concatenate([edges[:, 1], edges[:, 0]])
    adjacency = sp.csr_matrix((np.ones(len(i)), (i, j)), shape=(n_vertices, n_vertices))
    degree = sp.diags(np.asarray(adjacency.sum(axis=1)).ravel())
    return sp.csr_matrix(degree - adjacency)


def laplacian_loss(laplacian: sp.spmatrix, vertices: md.Tensor) -> md.Tensor:
    """mean over vertices of |L v|^2, on the tape (a 0-d tensor): the smoothness term added
    to an image loss. ``vertices`` (V, 3); ``laplacian`` from ``mesh_laplacian``."""
    lv = md.linear(lambda x: laplacian @ x, lambda g: laplacian.T @ g, vertices)
    return md.sum(lv * lv) * (1.0 / vertices.shape[0])


#: The largest condition number of ``LargeSteps``' M = I + lam L that it accepts: solves
#: with M then lose at most ~1e10 * 2.2e-16 ~ 2e-6 of u's size (6 digits kept).
MAX_CONDITION = 1e10


class LargeSteps:
    """The Large Steps parameterisation of a mesh's vertices: u = M v, M = I + lam L.

    faces (F, 3) and n_vertices fix L (``mesh_laplacian``); ``lam`` > 0 the smoothing
    (the paper uses 10-100; larger is smoother), finite and small enough that M's condition
    number stays below ``MAX_CONDITION`` (lam <= 1e10 / (2 x the largest vertex degree),
    8e8 on an icosphere). M is symmetric positive definite, and is
    factorised once (``scipy.sparse.linalg.splu``); v = M^-1 u is then two triangular
    solves per step.
    """

    def __init__(self, faces: np.ndarray, n_vertices: int, lam: float = 20.0):
        if isinstance(lam, bool) or not isinstance(lam, int | float) or not 0 < lam < math.inf:
            raise ValueError(f"LargeSteps: lam must be a number > 0 (and finite), got {lam!r}")
        self.lam = float(lam)
        self.laplacian = mesh_laplacian(faces, n_vertices)
        # cond(M) <= 1 + lam * 2 * (the largest degree) (Gershgorin; L's smallest
        # eigenvalue is 0): a solve with M keeps about -log10(cond(M) * eps) digits. Past
        # MAX_CONDITION, v = M^-1 u would be wrong in its 6th digit, and by lam = 1e16 (on
        # an icosphere) not even its first: refused rather than silently wrong.
        largest = MAX_CONDITION / (2.0 * max(float(self.laplacian.diagonal().max()), 1.0))
        if self.lam > largest:
            raise ValueError(
                f"LargeSteps: lam must be at most {largest:.3g} for these faces (M = I + lam "
                f"L's condition number at most {MAX_CONDITION:.0e}: solves keep 6 digits), "
                f"got {lam!r}"
            )
        self.n_vertices = int(n_vertices)
        self.matrix = sp.csc_matrix(sp.identity(n_vertices) + self.lam * self.laplacian)
        self._lu = splu(self.matrix)

    def to_u(self, vertices: np.ndarray) -> np.ndarray:
        """u = M v for vertex positions (V, 3)."""
        return np.asarray(self.matrix @ self._per_vertex(vertices, "to_u", "vertices"))

    def to_vertices(self, u: np.ndarray) -> np.ndarray:
        """v = M^-1 u (V, 3)."""
        return self._lu.solve(self._per_vertex(u, "to_vertices", "u"))

    def adjoint(self, grad_vertices: np.ndarray) -> np.ndarray:
        """dL/du = M^-T dL/dv: the gradient with respect to u of a loss whose gradient with
        respect to the vertices is ``grad_vertices`` (V, 3)."""
        grad = self._per_vertex(grad_vertices, "adjoint", "grad_vertices")
        return self._lu.solve(grad, trans="T")

    def _per_vertex(self, x, method: str, name: str) -> np.ndarray:
        """``x`` as a float64 (V, 3) array, or a ValueError naming ``name``."""
        x = np.asarray(x, dtype=np.float64)
        if x.shape != (self.n_vertices, 3):
            raise ValueError(
                f"LargeSteps.{method}: {name} must have shape (V, 3) = ({self.n_vertices}, 3) "
                f"(one row per vertex), got {x.shape}"
            )
        return x

    def vertices(self, u: md.Tensor) -> md.Tensor:
        """v = M^-1 u on the tape, for pipelines that hold u as their parameter."""
        return md.linear(self.to_vertices, self.adjoint, u)


class LargeStepsAdam(md.optim.Optimizer):
    """Uniform Adam on u = (I + lam L) v, seen from outside as an optimiser of the mesh's
    ``vertices`` tensor (V, 3): ``step()`` turns the vertices' gradient into u's
    (``LargeSteps.adjoint``: the VJP of v = M^-1 u), updates u with uniform Adam
    (``md.optim.Adam(uniform=True)``) and writes M^-1 u back into the vertices. The same
    iterates as differentiating through ``LargeSteps.vertices`` on the tape, without
    changing the scene: ``render.optimize(scene, [mesh.vertices], target,
    optimizer=LargeStepsAdam(mesh.vertices, mesh.faces, lr=0.01))``.
    """

    def __init__(self, vertices: md.Tensor, faces: np.ndarray, lam: float = 20.0,
                 lr: float = 0.01, betas: tuple[float, float] = (0.9, 0.999)):  # fmt: skip
        super().__init__([vertices])
        if vertices.ndim != 2 or vertices.shape[1] != 3:
            raise ValueError(f"LargeStepsAdam: vertices must be (V, 3), got {vertices.shape}")
        self.vertices = vertices
        self.steps = LargeSteps(faces, vertices.shape[0], lam)
        self.u = md.tensor(self.steps.to_u(vertices.data), requires_grad=True)
        self.adam = md.optim.Adam([self.u], lr=lr, betas=betas, uniform=True)

    def step(self) -> None:
        if self.vertices.grad is None:
            return
        if np.shape(self.vertices.grad) != self.vertices.shape:
            raise ValueError(
                f"LargeStepsAdam: vertices.grad must have the shape of vertices "
                f"{self.vertices.shape}, got {np.shape(self.vertices.grad)}"
            )
        self.u.grad = self.steps.adjoint(self.vertices.grad)
        self.adam.step()
        self.vertices.data[...] = self.steps.to_vertices(self.u.data)


def weld(vertices: np.ndarray, faces: np.ndarray):
    """One vertex per distinct position (the renderer's own welding rule,
    ``render.trace.topology.welded_ids``): the welded (U, 3) vertices; the faces renumbered
    onto them (F', 3), without those that welding collapses (two corners on one vertex:
    they had zero area, and their edges would be shared by many faces); and ``index`` (V,),
    the welded vertex of each original one (``welded[index]`` equals ``vertices`` up to the
    welding tolerance). The vertices of a welded mesh move a patch mesh's seams together
    instead of tearing them open."""
    vertices = np.asarray(vertices, dtype=np.float64)
    index = welded_ids(vertices)
    _, first = np.unique(index, return_index=True)
    f = index[np.asarray(faces)]
    kept = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 2] != f[:, 0])
    return vertices[first], f[kept], index


def subdivide(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each triangle split into four at its edges' midpoints (trimesh): (V', 3), (4F, 3).
    The surface is unchanged; a coarse-to-fine schedule continues on the finer mesh."""
    v, f = trimesh.remesh.subdivide(np.asarray(vertices, dtype=np.float64), np.asarray(faces))
    return np.asarray(v), np.asarray(f, dtype=np.int64)


def icosphere(subdivisions: int = 3, radius: float = 1.0, center=(0.0, 0.0, 0.0)):
    """(vertices, faces) of a geodesic sphere (trimesh): 10 * 4^s + 2 vertices (s = 3: 642,
    s = 4: 2,562), counter-clockwise seen from outside."""
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(sphere.vertices) + np.asarray(center), np.asarray(sphere.faces, np.int64)


@dataclass
class SurfaceDistances:
    """Between two surfaces, in % of the reference's bounding-box diagonal: ``chamfer``
    (the mean over both directions of the mean distance from a sample of one surface to
    the other surface) and ``hausdorff`` (the largest such distance), ``worst`` (3,) the
    sample where it is reached. With a ``region`` (a box): ``region_share``, the % of the
    Chamfer sum that samples inside the box contribute, and ``chamfer_outside``, the
    Chamfer distance of the samples outside it (NaN without a region)."""

    chamfer: float
    hausdorff: float
    worst: np.ndarray
    region_share: float = float("nan")
    chamfer_outside: float = float("nan")


def surface_distances(
    vertices: np.ndarray,
    faces: np.ndarray,
    ref_vertices: np.ndarray,
    ref_faces: np.ndarray,
    samples: int = 20_000,
    seed: int = 0,
    region: tuple[np.ndarray, np.ndarray] | None = None,
) -> SurfaceDistances:
    """Symmetric Chamfer and Hausdorff distances between a mesh and a reference mesh: from
    ``samples`` points drawn uniformly by area on each surface (trimesh, seeded) to the
    closest point of the *other surface* (not of its samples, which would add the sample
    spacing to every distance: ~0.3 % of the diagonal at 20,000 samples on a sphere); both
    as % of the reference's bounding-box diagonal (the measure of the Large Steps paper).
    ``region``: a box (lo (3,), hi (3,)) whose share of the Chamfer sum is reported (the
    teapot's handle, whose hole a sphere cannot grow)."""
    a = _surface_samples(vertices, faces, samples, seed)
    b = _surface_samples(ref_vertices, ref_faces, samples, seed + 1)
    a_to_b = distance_to_mesh(a, ref_vertices, ref_faces)
    b_to_a = distance_to_mesh(b, vertices, faces)
    scale = 100.0 / float(np.linalg.norm(np.ptp(np.asarray(ref_vertices), axis=0)))
    points, distances = np.concatenate([a, b]), np.concatenate([a_to_b, b_to_a])
    # Both sides have ``samples`` points: the mean of all is the mean of the two means.
    out = SurfaceDistances(scale * float(distances.mean()), scale * float(distances.max()),
                           points[np.argmax(distances)])  # fmt: skip
    if region is not None:
        inside = np.all((points >= region[0]) & (points <= region[1]), axis=1)
        out.region_share = 100.0 * float(distances[inside].sum() / distances.sum())
        if not np.all(inside):
            out.chamfer_outside = scale * float(distances[~inside].mean())
    return out


def _surface_samples(vertices, faces, count: int, seed: int) -> np.ndarray:
    mesh = trimesh.Trimesh(np.asarray(vertices), np.asarray(faces), process=False)
    points, _ = trimesh.sample.sample_surface(mesh, count, seed=seed)
    return np.asarray(points)


#: How many triangles (those with the nearest centroids) ``distance_to_mesh`` tries first.
CANDIDATES = 32


def distance_to_mesh(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(N,) the exact distance from each point (N, 3) to the closest point of the mesh's
    triangles. The triangles tried for a point are those with the k nearest centroids (a
    k-d tree, SciPy); the answer d is certain once the k-th nearest centroid is farther
    than d + R (R: the largest distance from a triangle's centroid to its corners, so no
    untried triangle can come nearer than d); points not yet certain are tried again with
    twice the k, up to all triangles."""
    points = np.asarray(points, dtype=np.float64)
    triangles = _even_triangles(np.asarray(vertices, dtype=np.float64), np.asarray(faces))
    centroids = triangles.mean(axis=1)
    reach = float(np.sqrt(np.max(np.sum((triangles - centroids[:, None]) ** 2, axis=-1))))
    tree, out = cKDTree(centroids), np.empty(len(points))
    todo, k = np.arange(len(points)), CANDIDATES
    while len(todo):
        k = min(k, len(triangles))
        centre_distance, near = tree.query(points[todo], k=k)
        near, centre_distance = near.reshape(len(todo), k), centre_distance.reshape(len(todo), k)
        corners = triangles[near]  # (n, k, 3, 3)
        closest = closest_on_triangles(points[todo, None, :], *np.moveaxis(corners, 2, 0))
        found = np.sqrt(np.min(np.sum((closest - points[todo, None, :]) ** 2, axis=-1), axis=1))
        certain = (centre_distance[:, -1] > found + reach) | (k == len(triangles))
        out[todo[certain]] = found[certain]
        todo, k = todo[~certain], 2 * k
    return out


def _even_triangles(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(T, 3, 3) the mesh's triangles, the long ones split (trimesh) until no edge is
    longer than the median edge: the same surface, but no triangle reaching far from
    its centroid, which would make ``distance_to_mesh``'s certainty test try them all (the
    teapot's slivers at its poles did: 3 s per call instead of 0.1)."""
    triangles = vertices[faces]
    edges = np.linalg.norm(triangles - np.roll(triangles, 1, axis=1), axis=-1)
    longest = float(np.median(edges))
    if longest > 0 and edges.max() > longest:
        vertices, faces = trimesh.remesh.subdivide_to_size(vertices, faces, max_edge=longest)
        triangles = np.asarray(vertices)[np.asarray(faces)]
    return triangles


def closest_on_triangles(p, a, b, c) -> np.ndarray:
    """The closest point to p on each triangle (a, b, c), arrays of 3-vectors broadcast
    together: Ericson, *Real-Time Collision Detection*, 5.1.5, vectorised. The point lies
    in one of seven Voronoi regions of the triangle (three corners, three edges, the
    face); each region's test and answer is written as an array, and the first region
    that holds wins (the face, tested last, is the default)."""

    def dot(x, y):
        return np.sum(x * y, axis=-1)

    ab, ac, ap, bp, cp = b - a, c - a, p - a, p - b, p - c
    d1, d2, d3, d4, d5, d6 = (
        dot(ab, ap),
        dot(ac, ap),
        dot(ab, bp),
        dot(ac, bp),
        dot(ab, cp),
        dot(ac, cp),
    )
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):  # only in regions not chosen
        total = va + vb + vc
        face = a + ab * (vb / total)[..., None] + ac * (vc / total)[..., None]
        on_ab = a + ab * (d1 / (d1 - d3))[..., None]
        on_ac = a + ac * (d2 / (d2 - d6))[..., None]
        on_bc = b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)))[..., None]
    regions = [  # in Ericson's order: the first that holds is the answer
        (d1 <= 0) & (d2 <= 0), (d3 >= 0) & (d4 <= d3), (vc <= 0) & (d1 >= 0) & (d3 <= 0),
        (d6 >= 0) & (d5 <= d6), (vb <= 0) & (d2 >= 0) & (d6 <= 0),
        (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0),
    ]  # fmt: skip
    answers = [a, b, on_ab, c, on_ac, on_bc]
    out = np.broadcast_to(face, np.broadcast_shapes(face.shape, a.shape)).copy()
    for region, answer in reversed(list(zip(regions, answers, strict=True))):
        out = np.where(region[..., None], np.broadcast_to(answer, out.shape), out)
    # A degenerate (zero-area) triangle is a segment or a point: the closest of its edges'.
    flat = ~np.isfinite(out).all(axis=-1)
    if flat.any():  # (only those entries: a mesh may have thousands of points x candidates)
        q, x, y, z = (np.broadcast_to(v, out.shape)[flat] for v in (p, a, b, c))
        edges = [_closest_on_segment(q, u, w) for u, w in ((x, y), (y, z), (z, x))]
        best = np.argmin([np.sum((e - q) ** 2, axis=-1) for e in edges], axis=0)
        out[flat] = np.choose(best[:, None], edges)
    return out


def _closest_on_segment(p, a, b) -> np.ndarray:
    """The closest point to p on the segment from a to b (a point if a = b), broadcast."""
    ab = b - a
    length2 = np.sum(ab * ab, axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(length2 > 0, np.sum((p - a) * ab, axis=-1) / length2, 0.0)
    return a + ab * np.clip(t, 0.0, 1.0)[..., None]
