"""Where two surfaces pass through each other, a curve kind.

Where two triangles cross (the teapot's lid sits in its rim, its spout and handle enter its
body), the visible surface switches from one to the other along the segment the two share
(``crossing_segments``: a sweep over the triangles' boxes, in Numba). The segment lies on
the line where their planes meet, whose edge function is that of a mesh edge: e = d . m,
m = (P - eye) x (n1 x n2) (``plane_line``, for arrays and tensors). Near the segment each
side sees the triangle that is nearer there, shaded at the point.
"""

from __future__ import annotations

import numpy as np

from minidiff.either import as_column, cross_last, dot_last
from minidiff.threads import jit, job_count, kernel, run_jobs, share
from render.edges.boundary.curves import NEAR, CurvePoints, Curves, OnCurves, View, directions_at
from render.edges.boundary.mesh_edge import approach
from render.edges.boundary.moving import camera_moves, meshes_move
from render.edges.boundary.occlusion import hidden_points
from render.edges.boundary.pixels import boxes_apart, pixel_gradient
from render.edges.geometry import plane_normal, triangle_corners
from render.scene.camera import camera_directions, clip_to_near, project
from render.scene.scene import Scene
from render.trace.seams import as_one_mesh, seam_tolerances
from render.trace.topology import welded_ids
from render.trace.vec3 import cross, dot3, sub


class SurfaceCrossing:
    """The segments where triangles pass through each other, as a curve kind
    (``render.edges.boundary.curves``): ``pairs`` (m, 2) the pairs of triangles (global
    ids) and ``segments`` (m, 2, 3) the segments they share (``crossing_segments``, which
    depend on the geometry alone: the caller keeps them). Labels: pairs (k, 2)."""

    summed, taped = 3, 4

    def __init__(self, pairs: np.ndarray, segments: np.ndarray) -> None:
        self.pairs, self.segments = pairs, segments

    def moves(self, scene: Scene) -> bool:
        """The camera or some mesh's vertices differentiated (``CurveKind.moves``)."""
        return camera_moves(scene) or meshes_move(scene)

    def curves(self, view: View) -> Curves:
        """The segments in front of the eye."""
        frame, camera = view.frame, view.scene.camera
        ends = self.segments[:, 0], self.segments[:, 1]
        a, b, keep = clip_to_near(*ends, frame, NEAR * view.size)
        return Curves(
            project(a[keep], frame, camera.width, camera.height)[0],
            project(b[keep], frame, camera.width, camera.height)[0],
            self.pairs[keep],
        )

    def points(self, view: View, on: OnCurves) -> CurvePoints:
        """The factors of the points (``_crossing_factors``)."""
        return CurvePoints.nonzero(on, _crossing_factors(view, on), on.coords)

    def edge_function(self, scene: Scene, frame, points: CurvePoints):
        """e = d . m on the tape (``plane_line``)."""
        first = triangle_corners(scene, points.label[:, 0])
        second = triangle_corners(scene, points.label[:, 1])
        _, _, m = plane_line(first, second, frame[3])
        e = dot_last(directions_at(scene, frame, points.coords), m)
        return e, np.arange(len(points.pixel))


@jit(cache=True)
def _segment_of(t1, t2):
    """Where triangles t1 and t2 (each its three corners, 3-tuples) cross: (ok, a, b), the
    segment from a to b (3-tuples) they share, ok False where they do not cross (coplanar
    or touching triangles do not count). Scalars and tuples, no arrays: the same
    arithmetic as array expressions, in a fraction of the time, and compiled in a fraction
    of it too."""
    zero = (0.0, 0.0, 0.0)
    p0, p1, p2 = t1
    q0, q1, q2 = t2
    n1 = cross(sub(p1, p0), sub(p2, p0))
    n2 = cross(sub(q1, q0), sub(q2, q0))
    # each triangle's corners against the other's plane
    d2 = (dot3(n1, sub(q0, p0)), dot3(n1, sub(q1, p0)), dot3(n1, sub(q2, p0)))
    d1 = (dot3(n2, sub(p0, q0)), dot3(n2, sub(p1, q0)), dot3(n2, sub(p2, q0)))
    if _one_side(d1) or _one_side(d2):
        return False, zero, zero
    u = cross(n1, n2)
    # each triangle's interval along u: where its edges cross the other's plane
    ok1, a1, b1, s1, e1 = _interval(t1, d1, u)
    ok2, a2, b2, s2, e2 = _interval(t2, d2, u)
    if not (ok1 and ok2):
        return False, zero, zero
    start, first = (a1, s1) if s1 >= s2 else (a2, s2)
    end, last = (b1, e1) if e1 <= e2 else (b2, e2)
    if first >= last:
        return False, zero, zero
    return True, start, end


@jit(cache=True, inline="always")
def _one_side(d):
    """Whether the three signed distances d (3,) leave a plane's one side uncrossed.
    (Inlined: a function of its own cost a cold start a third of a second to compile.)"""
    return (d[0] >= 0 and d[1] >= 0 and d[2] >= 0) or (d[0] <= 0 and d[1] <= 0 and d[2] <= 0)


@jit(cache=True)
def _interval(tri, d, u):
    """Where triangle ``tri``'s edges (its corners, 3-tuples) cross a plane (the corners'
    signed distances d from it): (ok, p, q, s, e), the two points p, q in the order of
    their positions s <= e along u; ok False unless two edges cross it. The edges in turn
    (written out: a tuple indexed by a variable is slow in Numba)."""
    c0, c1, c2 = tri
    zero = (0.0, 0.0, 0.0)
    m, p, q, s, e = _edge_crossing(c0, c1, d[0], d[1], u, 0, zero, zero, 0.0, 0.0)
    m, p, q, s, e = _edge_crossing(c1, c2, d[1], d[2], u, m, p, q, s, e)
    m, p, q, s, e = _edge_crossing(c2, c0, d[2], d[0], u, m, p, q, s, e)
    if m < 2:
        return False, p, q, s, e
    if s > e:
        return True, q, p, e, s
    return True, p, q, s, e


@jit(cache=True)
def _edge_crossing(x, y, dx, dy, u, m, p, q, s, e):
    """``_interval``'s (m, p, q, s, e) extended by the edge from corner x to corner y (at
    signed distances dx, dy from the plane) if it crosses the plane and fewer than two
    edges have."""
    if (dx > 0) != (dy > 0) and m < 2:
        f = dx / (dx - dy)
        point = (x[0] + (y[0] - x[0]) * f, x[1] + (y[1] - x[1]) * f,
                 x[2] + (y[2] - x[2]) * f)  # fmt: skip
        if m == 0:
            return 1, point, q, dot3(point, u), e
        return m + 1, p, point, s, dot3(point, u)
    return m, p, q, s, e


@jit(cache=True, inline="always")
def _triangle(triangles, i):
    """Triangle i of ``triangles`` (N, 3, 3) as its three corners (3-tuples)."""
    return ((triangles[i, 0, 0], triangles[i, 0, 1], triangles[i, 0, 2]),
            (triangles[i, 1, 0], triangles[i, 1, 1], triangles[i, 1, 2]),
            (triangles[i, 2, 0], triangles[i, 2, 1], triangles[i, 2, 2]))  # fmt: skip


@kernel
def _crossing_pairs(job, n_jobs, triangles, welded, order, low, high):
    """Job ``job`` of ``n_jobs`` (``minidiff.threads.run_jobs``): every pair of triangles
    that cross whose first in ``order`` (the triangles sorted by low x) is in the job's
    share, by a sweep along x over their bounding boxes; pairs sharing a (welded) corner
    are neighbours, not crossings. Returns the pairs (m, 2) and their segments (m, 2, 3),
    in the order of the sweep (the jobs' in turn: the order of one job)."""
    capacity, found = 64, 0
    pairs, segments = np.empty((capacity, 2), np.int64), np.empty((capacity, 2, 3))
    n = len(order)
    first, stop = share(job, n_jobs, n)
    for a in range(first, stop):
        i = order[a]
        for b in range(a + 1, n):
            j = order[b]
            if low[j, 0] > high[i, 0]:
                break
            if boxes_apart(low[i, 1], high[i, 1], low[j, 1], high[j, 1],
                           low[i, 2], high[i, 2], low[j, 2], high[j, 2]):  # y, z  # fmt: skip
                continue
            shared = False
            for p in range(3):
                for q in range(3):
                    if welded[i, p] == welded[j, q]:
                        shared = True
            if shared:
                continue
            ok, seg_a, seg_b = _segment_of(_triangle(triangles, i), _triangle(triangles, j))
            if not ok:
                continue
            if found == capacity:  # grow by doubling (arrays and scalar loops compile fast)
                capacity *= 2
                more_pairs, more_segments = (
                    np.empty((capacity, 2), np.int64),
                    np.empty((capacity, 2, 3)),
                )
                for r in range(found):
                    more_pairs[r, 0], more_pairs[r, 1] = pairs[r, 0], pairs[r, 1]
                    for e in range(2):
                        for c in range(3):
                            more_segments[r, e, c] = segments[r, e, c]
                pairs, segments = more_pairs, more_segments
            pairs[found, 0], pairs[found, 1] = min(i, j), max(i, j)
            for c in range(3):
                segments[found, 0, c], segments[found, 1, c] = seg_a[c], seg_b[c]
            found += 1
    return pairs[:found].copy(), segments[:found].copy()


def crossing_segments(triangles: np.ndarray, welded: np.ndarray):
    """Pairs of triangles (m, 2) (global ids) that pass through each other and the segment
    (m, 2, 3) they share: triangles (N, 3, 3), welded (N, 3) global welded vertex ids."""
    if len(triangles) < 2:
        return np.zeros((0, 2), np.int64), np.zeros((0, 2, 3))
    low, high = triangles.min(axis=1), triangles.max(axis=1)
    order = np.argsort(low[:, 0], kind="stable")
    found = run_jobs(_crossing_pairs, job_count(len(order), 4096), triangles, welded, order,
                     low, high)  # fmt: skip
    if len(found) == 1:
        return found[0]
    return np.concatenate([p for p, _ in found]), np.concatenate([s for _, s in found])


def global_welded(scene: Scene, topology) -> np.ndarray:
    """(N, 3) welded vertex ids of every triangle: each mesh's own (``topology``:
    ``mesh_edges`` per mesh index), distinct between meshes but where the ends of their
    open edges are one position (``render.trace.topology.seam_distance``: two triangles of
    two meshes that meet along a seam touch there, they do not cross, though the seam's
    two sides came apart by a float32 rounding)."""
    meshes = scene.meshes
    ids, offset = [], 0
    for k in range(len(meshes)):
        ids.append(topology[k].welded + offset)
        offset += int(topology[k].welded.max()) + 1 if topology[k].welded.size else 0
    if len(meshes) < 2:
        return ids[0] if ids else np.zeros((0, 3), np.int64)
    ids = np.concatenate(ids)
    vertices, faces = as_one_mesh(meshes)
    reach, ends = seam_tolerances(vertices, [topology[k].table for k in range(len(meshes))],
                                  [m.vertices.data for m in meshes], vertices)  # fmt: skip
    ends = np.unique(ends)
    if len(ends) == 0:
        return ids
    # Each end's welded id (any corner at that vertex has it), then the ends joined.
    corner = np.full(len(vertices), -1, np.int64)
    corner[faces.reshape(-1)] = ids.reshape(-1)
    joined = welded_ids(vertices[ends], reach[ends])
    merged = np.arange(offset)
    lowest = np.full(int(joined.max()) + 1, offset)
    np.minimum.at(lowest, joined, corner[ends])
    merged[corner[ends]] = lowest[joined]
    return merged[ids]


def plane_line(t1, t2, eye):
    """For triangles t1, t2 (k, 3, 3) (arrays, or tuples of (k, 3) tensors (a, b, c)): the
    normals n1, n2 (k, 3), and m = (P - eye) x u (k, 3) of the line where their planes meet
    (u = n1 x n2, P on the line): the line's edge function is d . m, as for a mesh edge."""
    n1, n2 = plane_normal(t1), plane_normal(t2)
    if isinstance(t1, np.ndarray):
        t1, t2 = (t1[:, 0], t1[:, 1], t1[:, 2]), (t2[:, 0], t2[:, 1], t2[:, 2])
    h1, h2 = dot_last(n1, t1[0]), dot_last(n2, t2[0])
    a11, a22, a12 = dot_last(n1, n1), dot_last(n2, n2), dot_last(n1, n2)
    det = a11 * a22 - a12 * a12
    # P = alpha n1 + beta n2 with n1 . P = h1, n2 . P = h2 (the point nearest the origin).
    alpha, beta = (h1 * a22 - h2 * a12) / det, (h2 * a11 - h1 * a12) / det
    point = as_column(alpha) * n1 + as_column(beta) * n2
    return n1, n2, cross_last(point - eye, cross_last(n1, n2))


def _crossing_factors(view: View, on: OnCurves) -> np.ndarray:
    """(g, 3): w (f_+ - f_-) / |grad e| for the quadrature points ``on`` the segments where
    the triangle pairs ``on.label`` (g, 2) cross, zero where hidden. Near the segment each
    side sees the triangle that is nearer there, shaded at the point."""
    forward, right, up, eye = view.frame
    camera, pairs, coords, weight, keys = view.scene.camera, on.label, on.coords, on.weight, on.key
    triangles = view.occluders.primitives[0]
    t1, t2 = triangles[pairs[:, 0]], triangles[pairs[:, 1]]
    n1, n2, m = plane_line(t1, t2, eye)
    directions = camera_directions(coords, right, up, forward)
    # Depth of the point: where the ray meets plane 1 (the point is on both planes).
    nd = np.einsum("ij,ij->i", n1, directions)
    depth = np.einsum("ij,ij->i", n1, t1[:, 0] - eye) / np.where(nd != 0, nd, np.inf)
    # The line's edge function d . m has the image-plane gradient (m . right, m . up).
    norm, step = pixel_gradient(np.stack([m @ right, m @ up], axis=1), camera.width, camera.height)
    hidden = hidden_points(
        view.occluders, view.frame, camera, coords, directions, depth, norm, pairs[:, 0]
    )
    seen = np.flatnonzero(~hidden)
    towards = step[seen, :1] * right + step[seen, 1:] * up  # towards the + side
    d = directions[seen]

    # Triangle 1 is the nearer on the + side if it comes nearer faster (``approach``).
    plus_first = approach(n1[seen], d, towards) > approach(n2[seen], d, towards)
    plus = np.where(plus_first, pairs[seen, 0], pairs[seen, 1])
    minus = np.where(plus_first, pairs[seen, 1], pairs[seen, 0])
    k = len(seen)
    colours = view.radiance.seen(
        np.concatenate([coords[seen], coords[seen]]),
        np.concatenate([plus, minus]),
        np.concatenate([depth[seen], depth[seen]]),
        np.concatenate([keys[seen], keys[seen]]),
    )
    out = np.zeros((len(coords), 3))
    out[seen] = (weight[seen] / norm[seen])[:, None] * (colours[:k] - colours[k:])
    return out
