"""Visibility queries for a scene of triangles and spheres: the public :class:`Accelerator`.

Usage::

    acc = Accelerator(triangles, sphere_centers, sphere_radii)   # builds the BVH
    prim_id, t, u, v = acc.closest_hit(origins, directions)      # camera / bounce rays
    shadowed = acc.occluded(points, light - points, tmax=1 - 1e-6,
                            ignore_prim=prim_id)                 # shadow rays

``Accelerator(..., use_bvh=False)`` tests every ray against every primitive: the same
traversal on a tree of one leaf that holds them all (``render.trace.bvh.one_leaf``).  It
answers exactly the same (bit for bit, see ``render.trace.intersect``): it is the ablation
baseline and the test oracle.

Design notes

* One BVH over all primitives: triangles and spheres are leaves of the same tree (the builder
  only needs boxes), so mixed scenes need a single traversal.
* All input checking happens here, in Python, before any Numba kernel runs: the kernels
  assume contiguous float64 arrays of the right shapes with finite, moderate values.
* A ray array in which every row is the same (``np.broadcast_to(eye, (N, 3))``, e.g. the
  camera's eye or a directional light) is passed to the kernels as its single row instead of
  being copied N times.
* An empty scene (no triangles, no spheres) is allowed: every ray misses.
"""

from __future__ import annotations

import copy
import time

import numpy as np

from minidiff.threads import job_count, kernel, run_jobs, share
from render.scene.scene import MAX_COORD
from render.trace.bvh import (
    C_TRAV,
    N_BINS,
    build_bvh,
    one_leaf,
    primitive_bounds,
    refit_bounds,
    sah_cost,
)
from render.trace.intersect import (
    RAYS_PER_JOB,
    FlatBVH,
    Rays,
    closest_hit_bvh,
    occluded_bvh,
    pack_primitives,
)
from render.trace.wide import CHILD, WIDTH, collapse, wide_nodes

#: Largest accepted magnitude of any coordinate, radius or direction component: the scene's
#: supported range (``render.scene.scene.MAX_COORD``), checked again for direct users.
#: A direction needs some component at least this large (so that |d|^2 does not underflow).
MIN_DIRECTION = 1e-60

#: Default ``tmin`` of ``occluded``, in units of the direction vector.  With the usual
#: unnormalised direction ``light - point`` this is a millionth of the light distance; together
#: with ``ignore_prim`` it removes shadow acne.  (The renderer starts its shadow rays off the
#: surface instead and passes tmin=0: see ``render.trace.visibility.shadow_rays``.)
SHADOW_TMIN = 1e-6

#: ``updated`` refits a tree while its SAH cost stays below this many times the cost it had
#: when it was built, and builds a new one beyond (primitives that moved apart from their
#: leaf-mates make its boxes overlap; see ``docs/architecture.md``).
REBUILD_RATIO = 1.5


# --------------------------------------------------------------------------------------------
# Input validation
# --------------------------------------------------------------------------------------------


def _contiguous_float64(a: np.ndarray) -> np.ndarray:
    """C-contiguous, writeable float64 (a view if ``a`` already is one).  Writeable because
    Numba types read-only arrays differently and would compile every kernel a second time."""
    out = np.ascontiguousarray(a, dtype=np.float64)
    return out if out.flags.writeable else out.copy()


def _as_real_array(name: str, x, shape_text: str) -> np.ndarray:
    """``np.asarray(x)`` (no copy) if it is a real numeric array, else ValueError."""
    try:
        a = np.asarray(x)
    except Exception as exc:  # ragged lists and the like
        raise ValueError(f"{name} must be an array of shape {shape_text}: {exc}") from None
    if not (
        np.issubdtype(a.dtype, np.floating)
        or np.issubdtype(a.dtype, np.integer)
        or a.dtype == np.bool_
    ):
        raise ValueError(f"{name} must be a real numeric array, got dtype {a.dtype}")
    return a


def _as_float_array(name: str, x, shape_text: str, ndim: int, last: tuple[int, ...]) -> np.ndarray:
    """``x`` as a C-contiguous float64 array of ``ndim`` dimensions whose trailing dimensions
    are ``last``; raises ValueError naming the argument and the expected shape otherwise."""
    a = _as_real_array(name, x, shape_text)
    if a.ndim != ndim or a.shape[ndim - len(last) :] != last:
        raise ValueError(f"{name} must have shape {shape_text}, got {a.shape}")
    return _contiguous_float64(a)


def _as_ray_array(name: str, x) -> tuple[np.ndarray, int, int]:
    """A ray array (N, 3) as ``(array, step, N)`` for the kernels: ray i reads row
    ``i * step``.  A broadcast array whose rows all share memory (stride 0) becomes its single
    row (1, 3) with step 0; anything else a C-contiguous float64 copy/view with step 1."""
    a = _as_real_array(name, x, "(N, 3)")
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {a.shape}")
    n = a.shape[0]
    if n > 1 and a.strides[0] == 0:
        return _contiguous_float64(a[:1]), 0, n
    return _contiguous_float64(a), 1, n


#: A second thread checks rays from this many rows a job on: a row costs about 4 ns (500k
#: rays: 1.9 ms on one thread), starting a job on the pool some 80 us (2 threads, this
#: Xeon). At 1,024 rows a job, as the traversals have it, the secondary term's 36 checks of
#: 16k rays took 4.8 ms on 2 threads against about 0.5 ms on one.
CHECK_ROWS_PER_JOB = 1 << 16


def _count_bad_rows(a: np.ndarray) -> tuple[int, int]:
    """Of the rows of ``a`` (N, 3): how many are bad (NaN, inf or larger than MAX_COORD in
    magnitude), and how many of the others are too short to be a direction (every component
    below MIN_DIRECTION). One pass instead of several NumPy temporaries, on the pool's
    threads from ``CHECK_ROWS_PER_JOB`` rows a job."""
    counts = np.zeros((job_count(len(a), CHECK_ROWS_PER_JOB), 2), np.int64)
    run_jobs(_count_bad_share, len(counts), a, counts)
    bad, short = counts.sum(axis=0)
    return int(bad), int(short)


@kernel
def _count_bad_share(job, n_jobs, a, counts):
    """Job ``job`` of ``n_jobs`` of ``_count_bad_rows``: its share of the rows, counted into
    ``counts[job]`` (the comparisons are written so that NaN fails them)."""
    bad = 0
    short = 0
    start, stop = share(job, n_jobs, a.shape[0])
    for i in range(start, stop):
        x, y, z = abs(a[i, 0]), abs(a[i, 1]), abs(a[i, 2])
        if not (x <= MAX_COORD and y <= MAX_COORD and z <= MAX_COORD):
            bad += 1
        elif x < MIN_DIRECTION and y < MIN_DIRECTION and z < MIN_DIRECTION:
            short += 1
    counts[job, 0], counts[job, 1] = bad, short


def _check_rays(origins, directions, tmin, tmax) -> tuple[Rays, int]:
    """Validate and convert the rays: origins and directions (N, 3) each, finite, moderate,
    directions nonzero; tmin a finite scalar; tmax a scalar or (N,), not NaN.  Returns
    ``(rays, N)``, the rays as the kernels take them (a ``Rays`` record)."""
    o, o_step, n = _as_ray_array("origins", origins)
    d, d_step, n_d = _as_ray_array("directions", directions)
    if n != n_d:
        raise ValueError(
            f"origins and directions must have the same number of rays N, got {n} and {n_d}"
        )
    if n > 0:
        bad_o = _count_bad_rows(o)[0]
        bad_d, short_d = _count_bad_rows(d)
        if bad_o:
            raise ValueError(
                f"origins must be finite and at most {MAX_COORD:g} in magnitude; "
                f"{bad_o * (n if o_step == 0 else 1)} rays are not"
            )
        if bad_d:
            raise ValueError(
                f"directions must be finite and at most {MAX_COORD:g} in magnitude; "
                f"{bad_d * (n if d_step == 0 else 1)} rays are not"
            )
        if short_d:
            raise ValueError(
                f"directions must be nonzero (some component >= {MIN_DIRECTION:g} in "
                f"magnitude); {short_d * (n if d_step == 0 else 1)} rays are zero or too short"
            )
    tmin = _check_scalar("tmin", tmin, allow_inf=False)
    if np.ndim(tmax) == 0:
        tmax_arr = np.array([_check_scalar("tmax", tmax, allow_inf=True)])
        t_step = 0
    else:
        tmax_arr = _as_float_array("tmax", tmax, f"(N,) = ({n},)", 1, ())
        if tmax_arr.shape[0] != n:
            raise ValueError(f"tmax must have shape (N,) = ({n},), got {tmax_arr.shape}")
        if np.isnan(tmax_arr).any():
            raise ValueError("tmax must not contain NaN")
        t_step = 1
    return Rays(o, d, o_step, d_step, tmin, tmax_arr, t_step), n


def _check_coordinates(name: str, a: np.ndarray) -> None:
    """Finite values of magnitude at most MAX_COORD, else ValueError. From the smallest and
    the largest value (NumPy's reductions: no temporary array; a NaN or an infinity shows
    in one of them), not from ``np.abs(a)`` (94 MB for 1.3M triangles)."""
    if a.size == 0:
        return
    low, high = float(a.min()), float(a.max())
    if not (np.isfinite(low) and np.isfinite(high)):
        raise ValueError(f"{name} must be finite (found NaN or inf)")
    if max(-low, high) > MAX_COORD:
        raise ValueError(
            f"{name} must be at most {MAX_COORD:g} in magnitude, got {max(-low, high):g}"
        )


def _check_scalar(name: str, x, allow_inf: bool) -> float:
    """A real scalar (NaN never allowed, +-inf only if ``allow_inf``)."""
    if isinstance(x, str | bytes):
        raise ValueError(f"{name} must be a real scalar, got {x!r}")
    try:
        f = float(x)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a real scalar, got {x!r}") from None
    if np.isnan(f) or (np.isinf(f) and not allow_inf):
        raise ValueError(f"{name} must be {'not NaN' if allow_inf else 'finite'}, got {f}")
    return f


def _checked_primitives(triangles, sphere_centers, sphere_radii):
    """(triangles (T, 3, 3), centres (S, 3), radii (S,)) as contiguous float64 arrays, each
    checked (finite, at most MAX_COORD, radii > 0), else a ValueError naming it."""
    tri = _as_float_array("triangles", triangles, "(T, 3, 3)", 3, (3, 3))
    if (sphere_centers is None) != (sphere_radii is None):
        raise ValueError("sphere_centers and sphere_radii must be given together")
    if sphere_centers is None:
        centers = np.zeros((0, 3))
        radii = np.zeros(0)
    else:
        centers = _as_float_array("sphere_centers", sphere_centers, "(S, 3)", 2, (3,))
        radii = _as_float_array("sphere_radii", sphere_radii, "(S,)", 1, ())
        if radii.shape[0] != centers.shape[0]:
            raise ValueError(
                f"sphere_radii must have shape (S,) = ({centers.shape[0]},) to match "
                f"sphere_centers, got {radii.shape}"
            )
    _check_coordinates("triangles", tri)
    _check_coordinates("sphere_centers", centers)
    _check_coordinates("sphere_radii", radii)
    if not (radii > 0).all():
        raise ValueError("sphere_radii must be > 0")
    return tri, centers, radii


# --------------------------------------------------------------------------------------------
# The accelerator
# --------------------------------------------------------------------------------------------


class Accelerator:
    """Visibility for a set of triangles (T, 3, 3) and spheres (centres (S, 3), radii (S,)).

    Primitive ids: triangles are 0..T-1 in the given order, spheres are T..T+S-1.

    ``use_bvh=False`` gives the brute-force baseline (same results, bit for bit): a tree of
    one leaf holding every primitive, which every ray enters.  ``n_bins`` is the number of
    SAH bins per axis used by the builder.

    The tree (attributes): the binary tree that is built, refitted and costed,
    ``node_bounds``, ``node_first``, ``node_count`` (``render.trace.bvh``); the 4-wide tree
    collapsed from it that rays traverse, ``wide_nodes``, ``leaf_start``
    (``render.trace.wide``); ``leaf_ids`` and ``leaf_prim`` (``render.trace.intersect``).
    Build statistics: ``n_triangles``, ``n_spheres``, ``n_prims``, ``n_nodes``, ``n_leaves``
    (of the binary tree), ``depth`` (its levels, root = 1; 0 for an empty scene),
    ``build_seconds`` (wall time of ``__init__``, or of ``refitted``; the first build in a
    process also loads the compiled kernels), ``use_bvh``; ``sah_cost`` (the tree's SAH cost,
    ``render.trace.bvh.sah_cost``), ``built_cost`` (its cost when its topology was built) and
    ``refits`` (how many times it was refitted since).
    """

    def __init__(
        self,
        triangles: np.ndarray,
        sphere_centers: np.ndarray | None = None,
        sphere_radii: np.ndarray | None = None,
        use_bvh: bool = True,
        n_bins: int = N_BINS,
    ) -> None:
        t0 = time.perf_counter()
        tri, centers, radii = _checked_primitives(triangles, sphere_centers, sphere_radii)
        if isinstance(n_bins, bool) or not isinstance(n_bins, int | np.integer) or n_bins < 2:
            raise ValueError(f"n_bins must be an integer >= 2, got {n_bins!r}")

        self.use_bvh = bool(use_bvh)
        self.n_triangles = tri.shape[0]
        self.n_spheres = centers.shape[0]
        self.n_prims = self.n_triangles + self.n_spheres
        if self.use_bvh:
            prim_min, prim_max = primitive_bounds(tri, centers, radii)
            tree = build_bvh(prim_min, prim_max, int(n_bins))
        else:
            tree = one_leaf(self.n_prims)
        self.node_bounds, self.node_first, self.node_count, order, depth = tree
        # The primitive table in leaf order: a leaf's primitives are contiguous in memory.
        self.leaf_ids = order
        # Primitive id -> its row in that table (``occluded``'s first_try); id -1 -> -1.
        self._leaf_row = np.full(self.n_prims + 1, -1, np.int64)
        self._leaf_row[order] = np.arange(len(order))
        self.leaf_prim = pack_primitives(tri, centers, radii, order)
        self.depth = int(depth)
        child, self.leaf_start, self._slot_node = collapse(
            self.node_bounds, self.node_first, self.node_count
        )
        self.wide_nodes = wide_nodes(self.node_bounds, self._slot_node, child)
        self.n_nodes = int(self.node_bounds.shape[0])
        self.n_leaves = int(np.count_nonzero(self.node_count))
        self.sah_cost = self.built_cost = self._cost()
        self.refits = 0
        self.build_seconds = time.perf_counter() - t0

    def _wide_child(self) -> np.ndarray:
        """(W, 4) int32: the wide tree's child codes, read from its nodes' rows."""
        return self.wide_nodes.view(np.int32)[:, CHILD : CHILD + WIDTH]

    def _cost(self) -> float:
        """The tree's SAH cost (0 for brute force: one leaf, which every ray enters)."""
        if not self.use_bvh:
            return 0.0
        return float(sah_cost(self.node_bounds, self.node_first, self.node_count, C_TRAV))

    def refitted(
        self,
        triangles: np.ndarray,
        sphere_centers: np.ndarray | None = None,
        sphere_radii: np.ndarray | None = None,
    ) -> Accelerator:
        """This tree over moved primitives: an Accelerator for ``triangles`` (T, 3, 3) and
        spheres (the same T and S as this one's) with this tree's topology and leaf order
        and new boxes (``render.trace.bvh.refit_bounds``: each node's, over its primitives'
        new places). This one is not changed (the render cache shares it read-only).

        Its rays get the same answers as from a tree built anew, and as from brute force,
        bit for bit: a box only decides which primitives a ray tests, and each box still
        holds its primitives. What moving costs is speed: primitives that drift apart from
        their leaf-mates stretch the boxes, and ``sah_cost`` grows over ``built_cost``
        (``updated`` builds anew beyond ``REBUILD_RATIO``)."""
        tri, centers, radii = _checked_primitives(triangles, sphere_centers, sphere_radii)
        if (len(tri), len(centers)) != (self.n_triangles, self.n_spheres):
            raise ValueError(
                f"refitted: the tree holds {self.n_triangles} triangles and {self.n_spheres} "
                f"spheres, got {len(tri)} and {len(centers)}: build a new Accelerator"
            )
        return self._refit(tri, centers, radii)

    def _refit(self, tri: np.ndarray, centers: np.ndarray, radii: np.ndarray) -> Accelerator:
        """``refitted`` for checked arrays of this tree's counts."""
        t0 = time.perf_counter()
        out = copy.copy(self)  # the topology's arrays shared: nobody writes into them
        if self.use_bvh:
            out.node_bounds = refit_bounds(self.node_first, self.node_count, self.leaf_ids,
                                           tri, centers, radii)  # fmt: skip
            out.wide_nodes = wide_nodes(out.node_bounds, self._slot_node, self._wide_child())
        out.leaf_prim = pack_primitives(tri, centers, radii, self.leaf_ids)
        out.sah_cost = out._cost()
        out.refits = self.refits + 1
        out.build_seconds = time.perf_counter() - t0
        return out

    def __repr__(self) -> str:
        kind = (
            f"BVH: {self.n_nodes} nodes, {self.n_leaves} leaves, depth {self.depth}"
            if self.use_bvh
            else "brute force"
        )
        made = f"refitted ({self.refits})" if self.refits else "built"
        return (
            f"Accelerator({self.n_triangles} triangles, {self.n_spheres} spheres, {kind}, "
            f"{made} in {self.build_seconds * 1e3:.1f} ms)"
        )

    # ----------------------------------------------------------------------------------------

    def flat_tree(self) -> FlatBVH:
        """The flat tree for Numba code that traces rays itself, one at a time
        (``intersect.closest_hit_ray``): no checks, the caller's rays must be finite."""
        return self._tree()

    def _tree(self) -> FlatBVH:
        """The flat tree as the traversal kernels take it (one argument)."""
        return FlatBVH(
            self.wide_nodes,
            self.wide_nodes.view(np.int32),
            self.leaf_start,
            self.leaf_prim,
            self.leaf_ids,
            self.n_triangles,
            3 * self.depth + 2,
        )

    def closest_hit(
        self,
        origins: np.ndarray,
        directions: np.ndarray,
        tmin: float = 0.0,
        tmax: np.ndarray | float = np.inf,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Closest hit along each ray ``origins[i] + t * directions[i]``, ``tmin < t < tmax``.

        origins, directions: (N, 3); directions need not be unit length (t is in units of the
        direction vector); tmax a scalar or (N,).  Returns ``prim_id`` (N,) int64 (-1 for a
        miss), ``t`` (N,) float64 (inf for a miss), ``u``, ``v`` (N,) float64 barycentrics:
        for triangle ``(a, b, c)`` the hit is ``(1-u-v)*a + u*b + v*c``; for spheres and
        misses ``u = v = 0``.

        Ties are broken by the order (t, prim_id): of two hits at exactly the same t (a ray
        through a shared edge or vertex) the lower id wins, with or without the BVH.
        """
        rays, n = _check_rays(origins, directions, tmin, tmax)
        out_id = np.empty(n, np.int64)
        out_t = np.empty(n)
        out_u = np.empty(n)
        out_v = np.empty(n)
        if n:
            jobs = job_count(n, RAYS_PER_JOB)
            run_jobs(closest_hit_bvh, jobs, self._tree(), rays, out_id, out_t, out_u, out_v)
        return out_id, out_t, out_u, out_v

    def _prim_ids(self, name: str, values, n: int) -> np.ndarray:
        """``values`` checked as (N,) integer primitive ids or -1: an int64 copy."""
        ids = np.asarray(values)
        if ids.shape != (n,):
            raise ValueError(f"{name} must have shape (N,) = ({n},), got {ids.shape}")
        if not np.issubdtype(ids.dtype, np.integer):
            raise ValueError(f"{name} must be an integer array, got dtype {ids.dtype}")
        ids = np.array(ids, dtype=np.int64, order="C")  # a copy: writeable
        if n and (ids.min() < -1 or ids.max() >= self.n_prims):
            raise ValueError(
                f"{name} values must be -1 (none) or primitive ids in [0, {self.n_prims - 1}]"
            )
        return ids

    def occluded(
        self,
        origins: np.ndarray,
        directions: np.ndarray,
        tmax: np.ndarray | float,
        tmin: float = SHADOW_TMIN,
        ignore_prim: np.ndarray | None = None,
        first_try: np.ndarray | None = None,
    ) -> np.ndarray:
        """Any-hit shadow rays: (N,) bool, True if some primitive other than ``ignore_prim[i]``
        is hit with ``tmin < t < tmax[i]``.

        origins, directions (N, 3); tmax (N,) or a scalar (e.g. ``1 - 1e-6`` with the
        unnormalised direction ``light - origin``); ignore_prim (N,) integer ids, -1 = none
        (typically the ``prim_id`` the shadow ray starts on: a flat triangle cannot shadow
        itself, so skipping it removes self-intersection acne).

        first_try (N,) integer ids, -1 = none: a primitive likely to block each ray, tested
        before the traversal (e.g. the one the camera sees in front of a point). Only the
        time changes: a ray it blocks needs no traversal, and the answer is the same.
        """
        rays, n = _check_rays(origins, directions, tmin, tmax)
        ignore = (
            np.full(n, -1, np.int64)
            if ignore_prim is None
            else self._prim_ids("ignore_prim", ignore_prim, n)
        )
        first_row = np.zeros(0, np.int64)
        if first_try is not None:
            first_row = self._leaf_row[self._prim_ids("first_try", first_try, n)]
        out = np.empty(n, np.bool_)
        if n:
            jobs = job_count(n, RAYS_PER_JOB)
            run_jobs(occluded_bvh, jobs, self._tree(), rays, ignore, first_row, out)
        return out


def updated(
    previous: Accelerator | None,
    triangles: np.ndarray,
    sphere_centers: np.ndarray | None = None,
    sphere_radii: np.ndarray | None = None,
    use_bvh: bool = True,
) -> Accelerator:
    """An Accelerator for these primitives: ``previous`` refitted (``Accelerator.refitted``)
    if it holds as many triangles and spheres, with the same ``use_bvh``, and the refitted
    tree's SAH cost stays within ``REBUILD_RATIO`` of the cost ``previous``'s topology had
    when it was built; else a new one. The answers are the same either way (bit for bit);
    for loops that move vertices (shape and pose fits), a refit is a fraction of a build."""
    tri, centers, radii = _checked_primitives(triangles, sphere_centers, sphere_radii)
    if (
        previous is not None
        and previous.use_bvh == bool(use_bvh)
        and (previous.n_triangles, previous.n_spheres) == (len(tri), len(centers))
    ):
        refit = previous._refit(tri, centers, radii)
        if refit.sah_cost <= REBUILD_RATIO * refit.built_cost:
            return refit
    return Accelerator(tri, centers, radii, use_bvh=use_bvh)
