"""Tests of the visibility module (render.trace.bvh, render.trace.intersect, render.trace.accel).

The brute-force Accelerator (use_bvh=False) is the oracle: the BVH must return *exactly* the
same ids, t, u, v (same per-primitive arithmetic, (t, id) tie order, conservative culling).
That brute force is the BVH's own traversal on a tree of one leaf, so it is checked in turn
against closed forms and against ``brute_force_reference``, a plain Python loop over every
primitive that shares nothing with the traversal but the per-primitive test.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from render.trace.accel import Accelerator
from render.trace.bvh import MAX_LEAF_SIZE, N_BINS, _partition, build_bvh, primitive_bounds
from render.trace.intersect import intersect_prim, make_ray, pack_primitives

NO_SPHERES = (np.zeros((0, 3)), np.zeros(0))
SETTINGS = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])


# --------------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------------


def assert_same_hits(a, b):
    """Bit-identical closest_hit results."""
    for name, x, y in zip(("prim_id", "t", "u", "v"), a, b, strict=True):
        np.testing.assert_array_equal(x, y, err_msg=name)


def brute_force_reference(tris, centers, radii, o, d, tmin=0.0, tmax=np.inf, ignore=None):
    """Closest hits ``(prim_id, t, u, v)`` and any-hits (N,) bool of N rays ``o + t d``,
    ``tmin < t < tmax`` (a scalar or (N,)), against every primitive in id order, in plain
    Python over the library's per-primitive test: the nearest hit, the lowest id of equal
    ones (a later id replaces it only if strictly nearer); blocked if any primitive other
    than ``ignore[i]`` (N,) is hit."""
    table = pack_primitives(tris, centers, radii)
    tmax = np.broadcast_to(np.asarray(tmax, float), len(o))
    ignore = np.full(len(o), -1) if ignore is None else ignore
    hits = np.zeros((len(o), 4))
    hits[:, :2] = (-1, np.inf)
    blocked = np.zeros(len(o), bool)
    for i in range(len(o)):
        ray = make_ray(o[i], d[i], float(tmin), float(tmax[i]))
        for p in range(len(table)):
            t, u, v = intersect_prim(table, p, p, len(tris), ray)
            if t < min(hits[i, 1], ray.tmax):
                hits[i] = (p, t, u, v)
            blocked[i] |= t < ray.tmax and p != ignore[i]
    return (hits[:, 0].astype(np.int64), *hits[:, 1:].T), blocked


def grid_triangles(nx: int, ny: int, z: float = 0.0, size: float = 1.0) -> np.ndarray:
    """A flat nx x ny grid of unit cells at height z, each cell split into two triangles
    (p00, p11, p10) and (p00, p01, p11) -- every interior edge and vertex is shared."""
    tris = []
    for i in range(nx):
        for j in range(ny):
            p00 = np.array([i, j, 0.0]) * size
            p10 = np.array([i + 1, j, 0.0]) * size
            p01 = np.array([i, j + 1, 0.0]) * size
            p11 = np.array([i + 1, j + 1, 0.0]) * size
            tris.append([p00, p11, p10])
            tris.append([p00, p01, p11])
    t = np.array(tris)
    t[..., 2] = z
    return t


def sphere_mesh(n_theta: int, n_phi: int, radius: float = 1.0) -> np.ndarray:
    """A UV-sphere triangle mesh (with degenerate triangles at the poles)."""
    th = np.linspace(0, np.pi, n_theta + 1)
    ph = np.linspace(0, 2 * np.pi, n_phi + 1)
    p = radius * np.stack(
        [
            np.sin(th)[:, None] * np.cos(ph),
            np.sin(th)[:, None] * np.sin(ph),
            np.cos(th)[:, None] * np.ones_like(ph),
        ],
        axis=-1,
    )
    a, b, c, d = p[:-1, :-1], p[1:, :-1], p[:-1, 1:], p[1:, 1:]
    t1 = np.stack([a, d, b], axis=-2).reshape(-1, 3, 3)
    t2 = np.stack([a, c, d], axis=-2).reshape(-1, 3, 3)
    return np.concatenate([t1, t2])


# Coordinates on a coarse lattice make shared vertices/edges, coplanar and degenerate
# triangles and exact ties likely; a few arbitrary floats keep the general case covered.
coord = st.one_of(
    st.integers(-4, 4).map(lambda k: k * 0.5),
    st.floats(-2.0, 2.0, allow_nan=False, allow_infinity=False),
)
point = st.tuples(coord, coord, coord)
triangle = st.one_of(
    st.tuples(point, point, point),
    # degenerate: repeated vertex / collinear
    point.map(lambda p: (p, p, p)),
    st.tuples(point, point).map(lambda pq: (pq[0], pq[1], pq[0])),
    st.tuples(point, point).map(
        lambda pq: (pq[0], pq[1], tuple(2 * np.array(pq[1]) - np.array(pq[0])))
    ),
)


@st.composite
def soups(draw, min_size=0, max_size=40):
    """A triangle soup (T, 3, 3): random, degenerate, duplicated and grid triangles."""
    tris = draw(st.lists(triangle, min_size=min_size, max_size=max_size))
    arr = np.array(tris, dtype=np.float64).reshape(-1, 3, 3)
    if draw(st.booleans()):  # a patch of grid triangles with shared edges and vertices
        g = grid_triangles(
            draw(st.integers(1, 3)),
            draw(st.integers(1, 3)),
            z=draw(st.sampled_from([0.0, 0.5, -1.0])),
            size=0.5,
        )
        arr = np.concatenate([arr, g])
    if len(arr) and draw(st.booleans()):  # duplicates
        k = draw(st.integers(0, len(arr) - 1))
        arr = np.concatenate([arr, arr[k : k + 1].repeat(draw(st.integers(1, 12)), axis=0)])
    if len(arr) > 1 and draw(st.booleans()):
        arr = arr[draw(st.permutations(range(len(arr))))]
    return arr


@st.composite
def rays_for(draw, tris: np.ndarray, centers: np.ndarray, n: int):
    """n rays (origins, directions) aimed at features of the scene: vertices, edge midpoints,
    interior points of triangles, sphere centres/silhouettes, or random directions."""
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    origins = rng.uniform(-4, 4, size=(n, 3))
    # Lattice origins make axis-aligned and exactly-symmetric rays likely.
    lattice = rng.random(n) < 0.3
    origins[lattice] = rng.integers(-6, 7, size=(lattice.sum(), 3)) * 0.5
    targets = rng.uniform(-2, 2, size=(n, 3))
    kind = rng.integers(0, 5, size=n)
    if len(tris):
        k = rng.integers(0, len(tris), size=n)
        i = rng.integers(0, 3, size=n)
        j = (i + 1) % 3
        bary = rng.dirichlet([1, 1, 1], size=n)
        vertex = tris[k, i]
        midpoint = 0.5 * (tris[k, i] + tris[k, j])
        inside = np.einsum("nk,nkd->nd", bary, tris[k])
        targets = np.where((kind == 0)[:, None], vertex, targets)
        targets = np.where((kind == 1)[:, None], midpoint, targets)
        targets = np.where((kind == 2)[:, None], inside, targets)
    if len(centers):
        s = rng.integers(0, len(centers), size=n)
        targets = np.where((kind == 3)[:, None], centers[s], targets)
    d = targets - origins
    zero = np.all(np.abs(d) < 1e-50, axis=1)  # (nearly) zero: not a valid direction
    d[zero] = rng.normal(size=(zero.sum(), 3)) + 1e-3
    # Random lengths: directions need not be unit.
    d *= rng.choice([1.0, 0.5, 3.0], size=(n, 1))
    return origins, d


# --------------------------------------------------------------------------------------------
# Closed forms
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("use_bvh", [True, False])
def test_triangle_closed_form(use_bvh):
    # Triangle a=(0,0,0), b=(2,0,0), c=(0,2,0) in the plane z = 0; hit = (1-u-v)a + u b + v c.
    tri = np.array([[[0.0, 0, 0], [2, 0, 0], [0, 2, 0]]])
    acc = Accelerator(tri, use_bvh=use_bvh)
    o = np.array([[0.5, 1.0, 3.0], [0.5, 1.0, 3.0], [0.5, 1.0, -1.0], [3.0, 3.0, 1.0]])
    d = np.array([[0.0, 0, -1], [0.0, 0, -3], [0.0, 0, 1], [0.0, 0, -1]])
    pid, t, u, v = acc.closest_hit(o, d)
    np.testing.assert_array_equal(pid, [0, 0, 0, -1])
    np.testing.assert_allclose(t[:3], [3.0, 1.0, 1.0], rtol=1e-15)
    np.testing.assert_allclose(u[:3], 0.25, rtol=1e-15)
    np.testing.assert_allclose(v[:3], 0.5, rtol=1e-15)
    assert t[3] == np.inf and u[3] == 0 and v[3] == 0
    # tmax cuts the hit, tmin skips it.
    assert acc.closest_hit(o[:1], d[:1], tmax=2.9)[0][0] == -1
    assert acc.closest_hit(o[:1], d[:1], tmin=3.1)[0][0] == -1
    assert acc.closest_hit(o[:1], d[:1], tmax=3.0)[0][0] == -1  # t < tmax is strict


@pytest.mark.parametrize("use_bvh", [True, False])
def test_sphere_closed_form(use_bvh):
    tri = np.array([[[10.0, 0, 0], [11, 0, 0], [10, 1, 0]]])  # far away: id 0
    acc = Accelerator(
        tri, np.array([[0.0, 0, 5], [0, 0, 20]]), np.array([1.0, 2.0]), use_bvh=use_bvh
    )
    o = np.array([[0.0, 0, 0], [0, 0, 5], [0, 0, 0], [1, 0, 0], [3, 0, 0], [1, 0, 10]])
    d = np.array([[0.0, 0, 1], [0, 0, 2], [0, 0, -1], [0, 0, 1], [0, 0, 1], [0, 0, 1]])
    pid, t, u, v = acc.closest_hit(o, d)
    np.testing.assert_array_equal(pid, [1, 1, -1, 1, -1, 2])
    # From outside: the near root 5 - 1.  From the centre: the exit root, |2 d| t = 1.
    # At distance 1 from the axis: tangent at z = 5.  Sphere 2: 20 - sqrt(2^2 - 1^2) - 10.
    np.testing.assert_allclose(t[[0, 1, 3, 5]], [4.0, 0.5, 5.0, 10 - np.sqrt(3.0)], rtol=1e-14)
    assert np.all(u == 0) and np.all(v == 0)
    # tmin beyond the near root gives the far root.
    pid, t, _, _ = acc.closest_hit(o[:1], d[:1], tmin=4.5)
    assert pid[0] == 1 and t[0] == pytest.approx(6.0, rel=1e-14)


def test_spheres_only_and_list_input():
    acc = Accelerator(np.zeros((0, 3, 3)), [[0, 0, 20]], [2])
    pid, t, _, _ = acc.closest_hit([[3.0, 0, 0], [1, 0, 0]], [[0, 0, 1], [0, 0, 1]])
    np.testing.assert_array_equal(pid, [-1, 0])
    np.testing.assert_allclose(t[1], 20 - np.sqrt(3.0), rtol=1e-14)


@pytest.mark.parametrize("use_bvh", [True, False])
def test_tie_goes_to_lowest_id_on_grid(use_bvh):
    # On a flat axis-aligned grid every triangle has the same normal (0, 0, -1), so a vertical
    # ray gets exactly the same t from every triangle containing its foot point: a true tie.
    tris = grid_triangles(4, 4)
    rng = np.random.default_rng(1)
    for perm in [np.arange(len(tris)), rng.permutation(len(tris))]:
        acc = Accelerator(tris[perm], use_bvh=use_bvh)
        xs, ys = np.meshgrid(np.arange(0, 4.01, 0.5), np.arange(0, 4.01, 0.5))
        feet = np.stack([xs.ravel(), ys.ravel()], axis=1)
        o = np.concatenate([feet, np.full((len(feet), 1), 2.0)], axis=1)
        d = np.tile([0.0, 0.0, -1.0], (len(o), 1))
        pid, t, _, _ = acc.closest_hit(o, d)
        np.testing.assert_array_equal(t, 2.0)
        # Independent expectation: the lowest id among the triangles containing the foot.
        for f, got in zip(feet, pid, strict=True):
            containing = [k for k, tri in enumerate(tris[perm]) if _in_triangle_2d(f, tri[:, :2])]
            assert got == min(containing)


def _in_triangle_2d(p, tri):
    """Inclusive point-in-triangle test in 2D (exact for our lattice points)."""

    def cross(a, b, c):
        return (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])

    s = [cross(tri[i], tri[(i + 1) % 3], p) for i in range(3)]
    return all(x >= 0 for x in s) or all(x <= 0 for x in s)


def test_duplicated_triangles_hit_lowest_id():
    tri = np.array([[[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]])
    tris = np.concatenate([grid_triangles(2, 2, z=-1.0), tri.repeat(50, axis=0)])
    acc = Accelerator(tris)
    pid, t, _, _ = acc.closest_hit(np.array([[0.2, 0.2, 1.0]]), np.array([[0.0, 0, -1]]))
    assert pid[0] == 8 and t[0] == 1.0
    occ = acc.occluded(
        np.array([[0.2, 0.2, 1.0]]),
        np.array([[0.0, 0, -1]]),
        np.array([1.5]),
        ignore_prim=np.array([8]),
    )
    assert occ[0]  # the other 49 copies still shadow


# --------------------------------------------------------------------------------------------
# Robustness: degenerate triangles, grazing rays, rays on the surface, empty scenes
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("use_bvh", [True, False])
def test_degenerate_triangles_never_hit_and_no_nan(use_bvh):
    tris = np.array(
        [
            [[0.0, 0, 0], [0, 0, 0], [0, 0, 0]],  # a point
            [[0.0, 0, 0], [1, 0, 0], [2, 0, 0]],  # collinear
            [[0.0, 0, 0], [1, 1, 0], [0, 0, 0]],  # repeated vertex
            [[0.0, 0, 0], [1, 0, 0], [1e9, 1e-9, 0]],  # extreme sliver
        ]
    )
    acc = Accelerator(tris, use_bvh=use_bvh)
    rng = np.random.default_rng(0)
    o = rng.uniform(-3, 3, (500, 3))
    target = rng.choice([0.0, 0.5, 1.0], size=(500, 3)) * np.array([1, 1, 0])
    d = target - o
    d[np.all(d == 0, axis=1)] = [0, 0, 1]
    pid, t, u, v = acc.closest_hit(o, d)
    assert np.all(pid == -1) and np.all(t == np.inf)
    assert not np.isnan(u).any() and not np.isnan(v).any()
    assert not acc.occluded(o, d, np.full(500, np.inf), tmin=0.0).any()


@pytest.mark.parametrize("use_bvh", [True, False])
def test_grazing_and_surface_rays(use_bvh):
    tris = grid_triangles(3, 3)
    acc = Accelerator(tris, use_bvh=use_bvh)
    o = np.array(
        [
            [-1.0, 0.5, 0.0],  # grazing: in the plane, through the interior
            [-1.0, 1.0, 0.0],  # in the plane, along a grid line
            [0.5, 0.5, 0.0],  # starts on the surface, going up
            [0.5, 0.5, 0.0],  # starts on the surface, going down
            [0.5, 0.5, 0.0],  # starts on the surface, in the plane
            [1.0, 1.0, 0.0],  # starts on a shared vertex, going up
        ]
    )
    d = np.array([[1.0, 0, 0], [1, 0, 0], [0.1, 0.2, 1], [0.1, 0.2, -1], [1, 1, 0], [0, 0, 1]])
    for tmin in [0.0, 1e-9]:
        pid, t, u, v = acc.closest_hit(o, d, tmin=tmin)
        assert not (np.isnan(t).any() or np.isnan(u).any() or np.isnan(v).any())
        assert np.all(pid[:2] == -1)  # rays in the plane of a triangle are misses
        assert np.all(pid[4] == -1)
        assert np.all((pid == -1) | (t > tmin))
    # With the tie rule and ignore_prim, a shadow ray leaving the surface is not shadowed.
    pid, t, _, _ = acc.closest_hit(np.array([[0.5, 0.3, 1.0]]), np.array([[0.0, 0, -1]]))
    hit = np.array([[0.5, 0.3, 1.0]]) + t[:, None] * np.array([[0.0, 0, -1]])
    light = np.array([[0.7, 0.1, 3.0]])
    assert not acc.occluded(hit, light - hit, np.array([1.0]), ignore_prim=pid).any()


@pytest.mark.parametrize("use_bvh", [True, False])
def test_empty_scene_misses(use_bvh):
    acc = Accelerator(np.zeros((0, 3, 3)), use_bvh=use_bvh)
    o = np.zeros((3, 3))
    d = np.eye(3)
    pid, t, u, v = acc.closest_hit(o, d)
    np.testing.assert_array_equal(pid, -1)
    np.testing.assert_array_equal(t, np.inf)
    assert not acc.occluded(o, d, np.ones(3)).any()
    # and zero rays
    pid, t, u, v = acc.closest_hit(np.zeros((0, 3)), np.zeros((0, 3)))
    assert pid.shape == t.shape == u.shape == v.shape == (0,)
    assert acc.occluded(np.zeros((0, 3)), np.zeros((0, 3)), 1.0).shape == (0,)


# --------------------------------------------------------------------------------------------
# BVH == brute force (property tests)
# --------------------------------------------------------------------------------------------


@SETTINGS
@given(data=st.data(), tris=soups())
def test_closest_hit_bvh_equals_brute_force(data, tris):
    bvh = Accelerator(tris)
    ref = Accelerator(tris, use_bvh=False)
    o, d = data.draw(rays_for(tris, np.zeros((0, 3)), 200))
    tmin = data.draw(st.sampled_from([0.0, 1e-9, 0.5]))
    tmax = data.draw(st.sampled_from([np.inf, 3.0, 1.0]))
    got = bvh.closest_hit(o, d, tmin, tmax)
    want = ref.closest_hit(o, d, tmin, tmax)
    assert_same_hits(got, want)
    assert_same_hits(want, brute_force_reference(tris, *NO_SPHERES, o, d, tmin, tmax)[0])
    pid, t, u, v = got
    hit = pid >= 0
    assert np.all((t[hit] > tmin) & (t[hit] < tmax)) and np.all(np.isinf(t[~hit]))
    assert not (np.isnan(u).any() or np.isnan(v).any())
    # Barycentrics reproduce the hit point.
    if hit.any():
        tri = tris[pid[hit]]
        p = (
            (1 - u[hit] - v[hit])[:, None] * tri[:, 0]
            + u[hit, None] * tri[:, 1]
            + v[hit, None] * tri[:, 2]
        )
        q = o[hit] + t[hit, None] * d[hit]
        scale = 1 + np.abs(q).max(axis=1) + np.linalg.norm(d[hit], axis=1) * t[hit]
        assert np.all(np.linalg.norm(p - q, axis=1) <= 1e-6 * scale)


@SETTINGS
@given(
    data=st.data(),
    tris=soups(max_size=25),
    spheres=st.lists(st.tuples(point, st.floats(0.05, 1.5)), min_size=0, max_size=8),
)
def test_mixed_scene_and_shadows_bvh_equals_brute_force(data, tris, spheres):
    centers = np.array([s[0] for s in spheres], dtype=np.float64).reshape(-1, 3)
    radii = np.array([s[1] for s in spheres], dtype=np.float64)
    bvh = Accelerator(tris, centers, radii)
    ref = Accelerator(tris, centers, radii, use_bvh=False)
    o, d = data.draw(rays_for(tris, centers, 150))
    assert_same_hits(bvh.closest_hit(o, d), ref.closest_hit(o, d))
    assert_same_hits(ref.closest_hit(o, d), brute_force_reference(tris, centers, radii, o, d)[0])

    n = len(o)
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    tmax = rng.choice([np.inf, 1.0, 0.5, 2.0, 1 - 1e-9], size=n)
    n_prims = len(tris) + len(centers)
    ignore = rng.integers(-1, max(n_prims, 1), size=n) if n_prims else np.full(n, -1)
    tmin = data.draw(st.sampled_from([0.0, 1e-6]))
    blocked = ref.occluded(o, d, tmax, tmin=tmin, ignore_prim=ignore)
    np.testing.assert_array_equal(bvh.occluded(o, d, tmax, tmin=tmin, ignore_prim=ignore), blocked)
    reference = brute_force_reference(tris, centers, radii, o, d, tmin, tmax, ignore)[1]
    np.testing.assert_array_equal(blocked, reference)
    # A primitive to try first changes nothing, whether it blocks the ray (the closest hit,
    # the ignored one included) or not (any id, or none).
    closest = ref.closest_hit(o, d, tmin=tmin)[0]
    for first in (closest, rng.integers(-1, max(n_prims, 1), size=n) if n_prims else closest):
        for acc in (bvh, ref):
            np.testing.assert_array_equal(
                acc.occluded(o, d, tmax, tmin=tmin, ignore_prim=ignore, first_try=first),
                blocked,
            )
    # Shadow rays from the hits: consistent with closest_hit along the same segment.
    pid, t, _, _ = bvh.closest_hit(o, d)
    hit = pid >= 0
    if hit.any():
        p = o[hit] + t[hit, None] * d[hit]
        light = rng.uniform(-4, 4, size=(1, 3))
        sd = light - p
        ok = np.any(sd != 0, axis=1)
        p, sd, ign = p[ok], sd[ok], pid[hit][ok]
        occ = bvh.occluded(p, sd, np.full(len(p), 1.0), ignore_prim=ign)
        np.testing.assert_array_equal(
            occ, ref.occluded(p, sd, np.full(len(p), 1.0), ignore_prim=ign)
        )


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n_theta=st.integers(3, 30), n_phi=st.integers(3, 40))
def test_mesh_bvh_equals_brute_force(seed, n_theta, n_phi):
    # A closed mesh (up to 2,400 triangles) gives deeper trees and many shared edges.
    rng = np.random.default_rng(seed)
    tris = sphere_mesh(n_theta, n_phi) * rng.uniform(0.5, 2, size=3)
    tris = np.concatenate([tris, sphere_mesh(4, 6, 0.3) + rng.uniform(-2, 2, size=3)])
    bvh = Accelerator(tris)
    ref = Accelerator(tris, use_bvh=False)
    o = rng.normal(size=(400, 3)) * 4
    targets = tris[rng.integers(0, len(tris), 400), rng.integers(0, 3, 400)]
    targets[::2] = rng.normal(size=(200, 3))
    d = targets - o
    assert_same_hits(bvh.closest_hit(o, d), ref.closest_hit(o, d))
    tmax = rng.uniform(0, 1.5, size=400)
    np.testing.assert_array_equal(bvh.occluded(o, d, tmax), ref.occluded(o, d, tmax))


# --------------------------------------------------------------------------------------------
# Build invariants
# --------------------------------------------------------------------------------------------


@SETTINGS
@given(tris=soups(min_size=1, max_size=60))
def test_build_invariants(tris):
    acc = Accelerator(tris)
    P = len(tris)
    assert 1 <= acc.n_nodes <= 2 * P - 1
    assert sorted(acc.leaf_ids.tolist()) == list(range(P))
    leaf = acc.node_count > 0
    assert acc.node_count[leaf].sum() == P
    lo, hi = tris.min(axis=1), tris.max(axis=1)
    for n in np.flatnonzero(leaf):
        ids = acc.leaf_ids[acc.node_first[n] : acc.node_first[n] + acc.node_count[n]]
        assert np.all(acc.node_bounds[n, :3] <= lo[ids]) and np.all(
            acc.node_bounds[n, 3:] >= hi[ids]
        )
        if acc.node_count[n] > MAX_LEAF_SIZE:
            c = lo[ids] + hi[ids]
            assert np.all(c == c[0])  # only coincident centroids may exceed the leaf size
    # Interior nodes contain their children.
    for n in np.flatnonzero(~leaf):
        for c in (acc.node_first[n], acc.node_first[n] + 1):
            assert np.all(acc.node_bounds[n, :3] <= acc.node_bounds[c, :3])
            assert np.all(acc.node_bounds[n, 3:] >= acc.node_bounds[c, 3:])


def _tree_in_visit_order(bounds, first, count):
    """The tree as a list of (box, count, leaf range start) in depth-first order from the
    root: equal for two builds that made the same splits, however their nodes are numbered."""
    out, stack = [], [0]
    while stack:
        n = stack.pop()
        out.append((tuple(bounds[n]), int(count[n]), int(first[n]) if count[n] else -1))
        if count[n] == 0:
            stack += [first[n] + 1, first[n]]
    return out


@SETTINGS
@given(tris=soups(min_size=1, max_size=120), copies=st.integers(1, 20))
def test_parallel_build_makes_the_serial_tree(tris, copies):
    # Forcing the parallel path on small inputs: the top is split serially, the subtrees of
    # fewer than 2 * MAX_LEAF_SIZE primitives on the threads; duplicates (coincident
    # centroids, split by index) included.
    tris = np.concatenate([tris, np.repeat(tris[:1], copies, axis=0)])
    lo, hi = primitive_bounds(tris, np.zeros((0, 3)), np.zeros(0))
    serial = build_bvh(lo, hi, parallel_min_prims=10**9)
    parallel = build_bvh(lo, hi, parallel_min_prims=1)
    assert parallel[0].shape == serial[0].shape
    assert _tree_in_visit_order(*parallel[:3]) == _tree_in_visit_order(*serial[:3])
    assert np.array_equal(parallel[3], serial[3]) and parallel[4] == serial[4]


@SETTINGS
@given(
    centroid=st.integers(1, 200).flatmap(
        lambda n: st.lists(st.tuples(*[st.floats(-1e3, 1e3)] * 3), min_size=n, max_size=n)
    ),
    axis=st.integers(0, 2),
    split_bin=st.integers(1, N_BINS - 1),
    seed=st.integers(0, 2**16),
)
def test_partition_gives_each_side_its_centroids_bounds(centroid, axis, split_bin, seed):
    # The builder's children read the centroid bounds the partition gathered on its way
    # (a pass over their primitives saved): they must be the plain min and max.
    centroid = np.array(centroid, float)
    n = len(centroid)
    order = np.random.default_rng(seed).permutation(n).astype(np.int64)
    lo, hi = centroid[:, axis].min(), centroid[:, axis].max()
    scale = N_BINS / (hi - lo) if hi > lo else 0.0
    child_cb = np.empty((2, 6))
    first = min(3, n - 1)
    kept = order[:first].copy()
    count = n - first
    n_left = _partition(first, count, order, centroid, axis, split_bin, lo, scale, N_BINS,
                        child_cb)  # fmt: skip
    assert np.array_equal(order[:first], kept)  # only its range is reordered
    bins = np.minimum(N_BINS - 1, ((centroid[:, axis] - lo) * scale).astype(np.int64))
    left, right = order[first : first + n_left], order[first + n_left : first + count]
    assert np.all(bins[left] < split_bin) and np.all(bins[right] >= split_bin)
    for side, ids in enumerate((left, right)):
        if len(ids):
            expected = np.concatenate([centroid[ids].min(axis=0), centroid[ids].max(axis=0)])
        else:
            expected = np.array([np.inf] * 3 + [-np.inf] * 3)
        assert np.array_equal(child_cb[side], expected)


def test_parallel_build_of_a_mesh_makes_the_serial_tree():
    tris = sphere_mesh(60, 90)  # 10,800 triangles: ~100 subtrees on the threads
    lo, hi = primitive_bounds(tris, np.zeros((0, 3)), np.zeros(0))
    serial = build_bvh(lo, hi, parallel_min_prims=10**9)
    parallel = build_bvh(lo, hi, parallel_min_prims=1)
    assert _tree_in_visit_order(*parallel[:3]) == _tree_in_visit_order(*serial[:3])
    assert np.array_equal(parallel[3], serial[3]) and parallel[4] == serial[4]


def test_build_statistics_and_repr():
    acc = Accelerator(sphere_mesh(20, 40))
    assert acc.n_triangles == 1600 and acc.n_spheres == 0 and acc.n_prims == 1600
    assert acc.n_leaves >= 1600 // MAX_LEAF_SIZE and acc.depth >= 8
    assert acc.build_seconds >= 0
    assert "BVH" in repr(acc)
    assert "brute force" in repr(Accelerator(sphere_mesh(2, 3), use_bvh=False))


def test_brute_force_is_one_leaf_of_any_size_holding_every_primitive_in_id_order():
    # Far more primitives than MAX_LEAF_SIZE (and than any stack or block size) in one leaf
    # whose box is all of space: every ray tests every primitive, the ids in order.
    rng = np.random.default_rng(7)
    tris = sphere_mesh(30, 40)
    centers, radii = rng.uniform(-1.5, 1.5, (5, 3)), rng.uniform(0.1, 0.5, 5)
    brute = Accelerator(tris, centers, radii, use_bvh=False)
    P = brute.n_prims
    assert (brute.n_nodes, brute.n_leaves, brute.depth) == (1, 1, 1) and P > 100 * MAX_LEAF_SIZE
    assert brute.node_count[0] == P and brute.node_first[0] == 0
    np.testing.assert_array_equal(brute.leaf_ids, np.arange(P))
    np.testing.assert_array_equal(brute.node_bounds[0], [-np.inf] * 3 + [np.inf] * 3)
    o = rng.normal(size=(40, 3)) * 4
    d = tris[rng.integers(0, len(tris), 40), 0] - o
    d[::4] = centers[rng.integers(0, 5, 10)] - o[::4]
    want, blocked = brute_force_reference(tris, centers, radii, o, d, ignore=np.arange(40))
    assert_same_hits(brute.closest_hit(o, d), want)
    assert_same_hits(Accelerator(tris, centers, radii).closest_hit(o, d), want)
    np.testing.assert_array_equal(brute.occluded(o, d, np.inf, 0.0, np.arange(40)), blocked)
    assert (want[0] >= len(tris)).any() and 0 < blocked.sum() and (want[0] >= 0).all()


# --------------------------------------------------------------------------------------------
# Input validation
# --------------------------------------------------------------------------------------------

TRI = np.array([[[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]])


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(triangles=np.zeros((5, 3))), r"triangles must have shape \(T, 3, 3\), got \(5, 3\)"),
        (dict(triangles=np.zeros((5, 3, 2))), r"triangles must have shape \(T, 3, 3\)"),
        (dict(triangles=np.full((1, 3, 3), np.nan)), "triangles must be finite"),
        (dict(triangles=np.full((1, 3, 3), np.inf)), "triangles must be finite"),
        (dict(triangles=np.full((1, 3, 3), 1e70)), "triangles must be at most 1e.60 in magn"),
        (dict(triangles=np.array([["a", "b", "c"]] * 3)[None]), "triangles must be a real"),
        (dict(triangles=TRI, sphere_centers=np.zeros((2, 3))), "given together"),
        (
            dict(triangles=TRI, sphere_centers=np.zeros((2, 2)), sphere_radii=np.ones(2)),
            r"sphere_centers must have shape \(S, 3\)",
        ),
        (
            dict(triangles=TRI, sphere_centers=np.zeros((2, 3)), sphere_radii=np.ones(3)),
            r"sphere_radii must have shape \(S,\) = \(2,\)",
        ),
        (
            dict(triangles=TRI, sphere_centers=np.zeros((1, 3)), sphere_radii=np.array([-1.0])),
            "sphere_radii must be > 0",
        ),
        (
            dict(triangles=TRI, sphere_centers=np.zeros((1, 3)), sphere_radii=np.array([np.nan])),
            "sphere_radii must be finite",
        ),
        (
            dict(triangles=TRI, sphere_centers=np.array([[0, np.inf, 0]]), sphere_radii=np.ones(1)),
            "sphere_centers must be finite",
        ),
        (dict(triangles=TRI, n_bins=1), "n_bins"),
    ],
)
def test_bad_scene_raises(kwargs, message):
    with pytest.raises(ValueError, match=message):
        Accelerator(**kwargs)


@pytest.mark.parametrize("use_bvh", [True, False])
@pytest.mark.parametrize(
    "o, d, kwargs, message",
    [
        (np.zeros((4, 2)), np.ones((4, 3)), {}, r"origins must have shape \(N, 3\), got \(4, 2\)"),
        (np.zeros(3), np.ones(3), {}, r"origins must have shape \(N, 3\), got \(3,\)"),
        (np.zeros((4, 3)), np.ones((5, 3)), {}, "same number of rays N, got 4 and 5"),
        (np.full((2, 3), np.nan), np.ones((2, 3)), {}, "origins must be finite"),
        (
            np.zeros((2, 3)),
            np.array([[1.0, np.inf, 0], [1, 0, 0]]),
            {},
            "directions must be finite",
        ),
        (np.zeros((2, 3)), np.array([[0.0, 0, 0], [1, 0, 0]]), {}, "directions must be nonzero"),
        (np.zeros((2, 3)), np.array([[1e-70, 0, 0], [1, 0, 0]]), {}, "1 rays are zero or too"),
        (np.full((2, 3), 1e61), np.ones((2, 3)), {}, "origins must be finite and at most 1e.60"),
        (np.zeros((2, 3)), np.full((2, 3), -1e61), {}, "directions must be finite and at most"),
        (np.zeros((2, 3)), np.ones((2, 3)), dict(tmin=np.nan), "tmin must be finite"),
        (np.zeros((2, 3)), np.ones((2, 3)), dict(tmax=np.nan), "tmax must be not NaN"),
        (np.zeros((2, 3)), np.ones((2, 3)), dict(tmin="x"), "tmin must be a real scalar"),
    ],
)
def test_bad_rays_raise(use_bvh, o, d, kwargs, message):
    acc = Accelerator(TRI, use_bvh=use_bvh)
    with pytest.raises(ValueError, match=message):
        acc.closest_hit(o, d, **kwargs)
    with pytest.raises(ValueError, match=message):
        acc.occluded(o, d, **{"tmax": 1.0, **kwargs})


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(tmax=np.ones(3)), r"tmax must have shape \(N,\) = \(2,\), got \(3,\)"),
        (dict(tmax=np.array([1.0, np.nan])), "tmax must not contain NaN"),
        (dict(tmax=1.0, ignore_prim=np.zeros(3, int)), r"ignore_prim must have shape \(N,\)"),
        (dict(tmax=1.0, ignore_prim=np.zeros(2)), "ignore_prim must be an integer array"),
        (dict(tmax=1.0, ignore_prim=np.array([0, 5])), "ignore_prim values must be -1"),
        (dict(tmax=1.0, ignore_prim=np.array([0, -2])), "ignore_prim values must be -1"),
        (dict(tmax=1.0, first_try=np.zeros(3, int)), r"first_try must have shape \(N,\)"),
        (dict(tmax=1.0, first_try=np.zeros(2)), "first_try must be an integer array"),
        (dict(tmax=1.0, first_try=np.array([1, 0])), "first_try values must be -1"),
    ],
)
def test_bad_shadow_arguments_raise(kwargs, message):
    acc = Accelerator(TRI)
    with pytest.raises(ValueError, match=message):
        acc.occluded(np.zeros((2, 3)), np.ones((2, 3)), **kwargs)


def test_integer_and_noncontiguous_inputs_are_converted():
    tris = np.asfortranarray(grid_triangles(2, 2).astype(np.float32))
    acc = Accelerator(tris)
    o = np.zeros((10, 6))[:, ::2] + np.array([0.5, 0.5, 1])  # non-contiguous view
    d = np.tile(np.array([0, 0, -1]), (10, 1))  # integer directions
    pid, t, _, _ = acc.closest_hit(o, d)
    assert np.all(pid >= 0) and np.all(t == 1.0)
    # Read-only arrays are accepted too (and copied, so Numba needs no second compilation).
    o = np.ascontiguousarray(o)
    o.flags.writeable = False
    assert_same_hits(acc.closest_hit(o, d), (pid, t, *acc.closest_hit(o.copy(), d)[2:]))


@pytest.mark.parametrize("use_bvh", [True, False])
def test_broadcast_rays_equal_materialised_rays(use_bvh):
    # A shared eye (camera) or a shared direction (directional light) may be passed as
    # np.broadcast_to views; the answers must equal those for the materialised arrays.
    rng = np.random.default_rng(3)
    tris = sphere_mesh(8, 12)
    acc = Accelerator(tris, np.array([[0.0, 0.0, 1.5]]), np.array([0.4]), use_bvh=use_bvh)
    eye = np.array([0.3, -0.2, 4.0])
    d = rng.normal(size=(300, 3)) * 0.2 + np.array([0.0, 0.0, -1.0])
    o = np.broadcast_to(eye, d.shape)
    assert_same_hits(acc.closest_hit(o, d), acc.closest_hit(o.copy(), d))
    p = rng.normal(size=(300, 3)) * 2
    light_dir = np.broadcast_to(np.array([0.2, 0.3, 1.0]), p.shape)
    tmax = np.full(300, np.inf)
    np.testing.assert_array_equal(
        acc.occluded(p, light_dir, np.inf, tmin=1e-9),
        acc.occluded(p, light_dir.copy(), tmax, tmin=1e-9),
    )
    with pytest.raises(ValueError, match="origins must be finite"):
        acc.closest_hit(np.broadcast_to(np.array([np.nan, 0, 0]), d.shape), d)


@pytest.mark.parametrize("use_bvh", [True, False])
def test_blocked_past_goes_on_beyond_the_faces_it_passes(use_bvh):
    """``render.trace.visibility.blocked_past``: rays up the z axis through three stacked
    triangles (ids 0, 1, 2 at z = 1, 2, 3) are blocked by the first they do not pass,
    within tmax; ending before the first not passed, they are not."""
    from render.trace.visibility import blocked_past

    tri = np.array([[-1.0, -1.0, 0.0], [2.0, -1.0, 0.0], [-1.0, 2.0, 0.0]])
    stacked = np.stack([tri + [0.0, 0.0, z] for z in (1.0, 2.0, 3.0)])
    acc = Accelerator(stacked, use_bvh=use_bvh)
    passing = np.array([[-1, -1], [0, -1], [0, 1], [0, 1], [1, 2], [0, 2]])
    tmax = np.array([10.0, 10.0, 10.0, 2.5, 10.0, 1.5])
    origins = np.zeros((len(tmax), 3))
    directions = np.broadcast_to([0.0, 0.0, 1.0], origins.shape)
    blocked = blocked_past(acc, origins, directions, tmax, passing)
    # 0 blocks; 1 blocks past 0; 2 past 0, 1; 2 is beyond tmax 2.5; 0 blocks (passing 1, 2);
    # passing 0 and 2, 1 lies beyond tmax 1.5
    np.testing.assert_array_equal(blocked, [True, True, True, False, True, False])
