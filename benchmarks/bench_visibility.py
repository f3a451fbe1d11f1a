"""Visibility benchmark: BVH vs brute force on the Utah teapot.

Run:  python benchmarks/bench_visibility.py [--repeats 15] [--no-brute]

Workload (the reference from the project brief): the Newell teapot tessellated into 1,536
triangles, a 512x512 pinhole camera at (3, 2, 5) looking at the origin (one ray per pixel
centre), and a point light at (2, 5, 3) for the shadow rays of the camera hits.  A finer
tessellation (99,840 triangles) measures build time and primary rays on a bigger mesh.

Every time is the median over repeats, after a warm-up call (JIT compilation / cache load).
The thread count is Numba's default (set NUMBA_NUM_THREADS to change it).
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numba
import numpy as np

from render.accel import Accelerator

DATA = Path(__file__).resolve().parents[1] / "render" / "data" / "newell_teapot.json"
EYE = np.array([3.0, 2.0, 5.0])
TARGET = np.zeros(3)
UP = np.array([0.0, 1.0, 0.0])
TAN_HALF_FOV = 18.0 / 50.0  # horizontal fov = 2 atan(18/50), a 50 mm lens on 36 mm film
LIGHT = np.array([2.0, 5.0, 3.0])


def _bernstein3(t: np.ndarray) -> np.ndarray:
    """Cubic Bernstein basis at parameters t (n,) -> (n, 4)."""
    s = 1.0 - t
    return np.stack([s**3, 3 * t * s**2, 3 * t**2 * s, t**3], axis=1)


def teapot_triangles(cells_u: int = 4, cells_v: int = 6) -> np.ndarray:
    """The Newell teapot as a triangle soup (32 * cells_u * cells_v * 2, 3, 3).

    Each bicubic patch (4x4 control points, row-major) is evaluated on a
    (cells_u + 1) x (cells_v + 1) grid, u along the first control-point index, and each cell
    (i, j) becomes triangles (P[i,j], P[i+1,j+1], P[i+1,j]) and (P[i,j], P[i,j+1], P[i+1,j+1]).
    Control points (x, y, z) (z up) are placed at 0.5 * (x, z, -y) + (0, -0.5, 0) (y up).
    Pole patches give some zero-area triangles, as in the original data.

    Swap point: replace this function by ``render.teapot`` once that module exists.
    """
    data = json.loads(DATA.read_text())
    verts = np.asarray(data["vertices"], dtype=np.float64)
    verts = 0.5 * np.stack([verts[:, 0], verts[:, 2], -verts[:, 1]], axis=1)
    verts += np.array([0.0, -0.5, 0.0])
    bu = _bernstein3(np.linspace(0.0, 1.0, cells_u + 1))  # (nu+1, 4)
    bv = _bernstein3(np.linspace(0.0, 1.0, cells_v + 1))  # (nv+1, 4)
    tris = []
    for patch in data["patches"]:
        cp = verts[np.asarray(patch)].reshape(4, 4, 3)
        grid = np.einsum("ia,jb,abk->ijk", bu, bv, cp)  # (nu+1, nv+1, 3)
        p00 = grid[:-1, :-1].reshape(-1, 3)
        p10 = grid[1:, :-1].reshape(-1, 3)
        p01 = grid[:-1, 1:].reshape(-1, 3)
        p11 = grid[1:, 1:].reshape(-1, 3)
        t1 = np.stack([p00, p11, p10], axis=1)
        t2 = np.stack([p00, p01, p11], axis=1)
        # Interleave so that cell (i, j) gives triangles 2k, 2k+1.
        tris.append(np.stack([t1, t2], axis=1).reshape(-1, 3, 3))
    return np.concatenate(tris)


def camera_rays(width: int = 512, height: int = 512) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole camera rays through the pixel centres, row-major from the top-left pixel.
    Returns origins, directions (width*height, 3); directions are unit length."""
    forward = TARGET - EYE
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, UP)
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    tan_v = TAN_HALF_FOV * height / width
    x = ((np.arange(width) + 0.5) / width * 2.0 - 1.0) * TAN_HALF_FOV
    y = (1.0 - (np.arange(height) + 0.5) / height * 2.0) * tan_v
    xx, yy = np.meshgrid(x, y)  # (height, width)
    d = forward + xx[..., None] * right + yy[..., None] * up
    d = d.reshape(-1, 3)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.broadcast_to(EYE, d.shape).copy(), d


def median_time(fn, repeats: int) -> float:
    """Median wall time of ``fn()`` in seconds over ``repeats`` calls, after one warm-up."""
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def shadow_rays(origins, directions, prim_id, t):
    """Shadow rays from the camera hits towards LIGHT: origin = hit point, direction =
    LIGHT - hit (unnormalised, so the light is at t = 1), tmax = 1 - 1e-9, ignore = hit id."""
    hit = prim_id >= 0
    p = origins[hit] + t[hit, None] * directions[hit]
    return p, LIGHT - p, np.full(p.shape[0], 1.0 - 1e-9), prim_id[hit]


def run(repeats: int, brute: bool) -> None:
    print(
        f"numba {numba.__version__}, threads: {numba.get_num_threads()}, "
        f"layer: {numba.config.THREADING_LAYER}"
    )
    origins, directions = camera_rays()
    n_rays = origins.shape[0]

    tris = teapot_triangles()
    Accelerator(tris)  # warm-up: JIT compile / cache load of the builder
    build = median_time(lambda: Accelerator(tris), repeats)
    acc = Accelerator(tris)
    print(f"\nteapot: {tris.shape[0]} triangles; {acc}")
    print(f"  build                      {build * 1e3:8.2f} ms")

    prim_id, t, u, v = acc.closest_hit(origins, directions)
    n_hit = int((prim_id >= 0).sum())
    primary = median_time(lambda: acc.closest_hit(origins, directions), repeats)
    print(f"  closest_hit BVH  {n_rays} rays {primary * 1e3:8.2f} ms   ({n_hit} hits)")

    so, sd, stmax, sign = shadow_rays(origins, directions, prim_id, t)
    occ = acc.occluded(so, sd, stmax, ignore_prim=sign)
    shadow = median_time(lambda: acc.occluded(so, sd, stmax, ignore_prim=sign), repeats)
    print(
        f"  occluded BVH     {so.shape[0]} rays  {shadow * 1e3:8.2f} ms   "
        f"({int(occ.sum())} in shadow)"
    )

    if brute:
        ref = Accelerator(tris, use_bvh=False)
        r_id, r_t, r_u, r_v = ref.closest_hit(origins, directions)
        same = (
            np.array_equal(r_id, prim_id)
            and np.array_equal(r_t, t)
            and np.array_equal(r_u, u)
            and np.array_equal(r_v, v)
        )
        bf = median_time(lambda: ref.closest_hit(origins, directions), max(1, repeats // 5))
        print(f"  closest_hit brute force    {bf * 1e3:8.2f} ms   (identical to BVH: {same})")
        r_occ = ref.occluded(so, sd, stmax, ignore_prim=sign)
        bfs = median_time(
            lambda: ref.occluded(so, sd, stmax, ignore_prim=sign), max(1, repeats // 5)
        )
        print(
            f"  occluded brute force       {bfs * 1e3:8.2f} ms   "
            f"(identical to BVH: {np.array_equal(r_occ, occ)})"
        )

    fine = teapot_triangles(26, 60)
    build_fine = median_time(lambda: Accelerator(fine), max(3, repeats // 3))
    acc_fine = Accelerator(fine)
    print(f"\nfine teapot: {fine.shape[0]} triangles; {acc_fine}")
    print(f"  build                      {build_fine * 1e3:8.2f} ms")
    fid, ft, _, _ = acc_fine.closest_hit(origins, directions)
    primary_fine = median_time(lambda: acc_fine.closest_hit(origins, directions), repeats)
    print(
        f"  closest_hit BVH  {n_rays} rays {primary_fine * 1e3:8.2f} ms   "
        f"({int((fid >= 0).sum())} hits)"
    )
    fso, fsd, fstmax, fsign = shadow_rays(origins, directions, fid, ft)
    shadow_fine = median_time(
        lambda: acc_fine.occluded(fso, fsd, fstmax, ignore_prim=fsign), repeats
    )
    print(f"  occluded BVH     {fso.shape[0]} rays  {shadow_fine * 1e3:8.2f} ms")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--no-brute", action="store_true", help="skip the brute-force runs")
    args = parser.parse_args()
    run(args.repeats, not args.no_brute)


if __name__ == "__main__":
    main()
