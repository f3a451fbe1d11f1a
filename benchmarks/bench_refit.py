"""BVH refit against build (issue 58): large meshes, and a real 300-step shape fit.

Run:  python benchmarks/bench_refit.py [--out out/bench_refit] [--quick] [--repeats 5]
      [--iters 300]
(the committed results in docs/benchmarks/refit/ were made with
``--out docs/benchmarks/refit``)

1. **Large meshes.** A bumpy sphere (a UV sphere whose radius varies by 5 % with a few
   sine waves) of 81,920 and of 1,310,720 triangles: the median time of building its
   ``Accelerator`` and of refitting it (``Accelerator.refitted``) after every corner moved
   by up to 1e-3 of the radius, in turns, the ratio (issue 58's target: refit at most 0.2
   of a build), the refit's page faults there and its time in a loop of refits alone, and
   both trees' SAH costs.
2. **A shape fit.** ``render.inverse.reconstruction.run_shape``: the dented blob from an
   icosphere of 5,120 triangles, 4 views of 64 x 64, ``--iters`` steps of Large Steps,
   pixel pairs. The triangles of every render's scene are recorded (at
   ``render.trace.visibility.updated``, where the renderer asks for its BVH), then
   replayed: a BVH built anew at every step against ``accel.updated``'s chain (refits until
   the SAH cost passes ``REBUILD_RATIO`` times the cost at the last build). Reported: the
   total time of each, the number of rebuilds, the refitted tree's SAH cost over a fresh
   build's at each step (largest and last), and the closest hits of 65,536 rays from the
   views' cameras at the last step on the chain's tree and on a fresh one (medians).
3. **A path-traced gradient with a large mesh.** The Cornell box (32 x 32) with the
   81,920-triangle bumpy sphere (radius 0.3) in it, 16 spp, depth 4: render + backward of
   the light's position, the scene's tree kept in its cache (as ``render_path`` does:
   the render and its backward share it) against a tree built at every render (a fresh
   cache each time: the render's and the backward's builds), in turns, on 1 thread and on
   all of Numba's.
"""

from __future__ import annotations

import time
from pathlib import Path

import numba
import numpy as np
import timing

import minidiff as md
from render.inverse.reconstruction import dented_blob, run_shape, view_cameras
from render.path import integrator, render_path
from render.scene.cache import RenderCache
from render.scene.camera import primary_rays
from render.scene.cornell import cornell_box
from render.scene.scene import Material, Mesh
from render.trace import visibility
from render.trace.accel import REBUILD_RATIO, Accelerator, updated


def bumpy_sphere(n_theta: int, n_phi: int) -> np.ndarray:
    """(2 n_theta n_phi, 3, 3) triangles of a sphere of radius about 1 whose radius varies
    by 5 % (three sine waves)."""
    theta = np.linspace(0.0, np.pi, n_theta + 1)
    phi = np.linspace(0.0, 2 * np.pi, n_phi + 1)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    r = 1.0 + 0.05 * np.sin(7 * t) * np.cos(5 * p) + 0.02 * np.sin(13 * p + 3 * t)
    grid = np.stack([r * np.sin(t) * np.cos(p), r * np.sin(t) * np.sin(p), r * np.cos(t)], -1)
    a, b = grid[:-1, :-1], grid[1:, :-1]
    c, d = grid[1:, 1:], grid[:-1, 1:]
    return np.concatenate([np.stack([a, b, c], -2), np.stack([a, c, d], -2)]).reshape(-1, 3, 3)


def large_meshes(repeats: int, sizes: list[tuple[int, int]]) -> list[dict]:
    rows = []
    for n_theta, n_phi in sizes:
        tris = bumpy_sphere(n_theta, n_phi)
        moved = tris + 1e-3 * np.random.default_rng(0).uniform(-1, 1, tris.shape)
        built = Accelerator(tris)
        times = timing.measure_interleaved(
            {
                "build": lambda m=moved: Accelerator(m),
                "refit": lambda b=built, m=moved: b.refitted(m),
            },  # fmt: skip
            repeats,
        )
        # Refits in a loop of their own: their arrays reuse the memory the last one freed,
        # where after a build's (interleaved above) they first take page faults.
        alone = timing.measure(lambda b=built, m=moved: b.refitted(m), repeats)
        refit, fresh = built.refitted(moved), Accelerator(moved)
        row = {
            "triangles": len(tris),
            "build_ms": times["build"]["median_ms"],
            "refit_ms": times["refit"]["median_ms"],
            "refit_over_build": times["refit"]["median_ms"] / times["build"]["median_ms"],
            "refit_alone_ms": alone["median_ms"],
            "refit_page_faults": times["refit"]["page_faults_per_pass"],
            "sah_refit": refit.sah_cost,
            "sah_fresh": fresh.sah_cost,
        }
        rows.append(row)
        print(f"{len(tris):,} triangles: build {row['build_ms']:.1f} ms, refit "
              f"{row['refit_ms']:.1f} ms ({row['refit_over_build']:.3f}; in a loop of refits "
              f"{row['refit_alone_ms']:.1f} ms); SAH refit "
              f"{refit.sah_cost:.2f}, fresh {fresh.sah_cost:.2f}", flush=True)  # fmt: skip
    return rows


def record_fit(iters: int, size: int) -> list[np.ndarray]:
    """The triangles of every render of a shape fit, in order (``visibility.updated``
    wrapped for the run)."""
    seen = []
    original = visibility.updated

    def recording(previous, triangles, *rest, **options):
        seen.append(np.array(triangles))
        return original(previous, triangles, *rest, **options)

    visibility.updated = recording
    try:
        run_shape(dented_blob(5), views=4, size=size, iters=iters, batch=4, antialias="pairs",
                  held_out=1, samples=2000)  # fmt: skip
    finally:
        visibility.updated = original
    return seen


def replay(steps: list[np.ndarray], size: int, repeats: int) -> dict:
    """Each recorded step built anew against ``updated``'s chain, timed step by step."""
    build_s = chain_s = 0.0
    chain, rebuilds, ratios = None, 0, []
    for tris in steps:
        t0 = time.perf_counter()
        fresh = Accelerator(tris)
        t1 = time.perf_counter()
        chain = updated(chain, tris)
        t2 = time.perf_counter()
        build_s, chain_s = build_s + t1 - t0, chain_s + t2 - t1
        rebuilds += chain.refits == 0
        ratios.append(chain.sah_cost / fresh.sah_cost)
    camera = view_cameras(1, 256)[0]
    origins, directions = primary_rays(camera)[:2]
    origins = np.broadcast_to(np.asarray(origins, float), np.shape(directions))
    fresh = Accelerator(steps[-1])
    rays = timing.measure_interleaved(
        {"chain": lambda: chain.closest_hit(origins, directions),
         "fresh": lambda: fresh.closest_hit(origins, directions)}, repeats)  # fmt: skip
    return {
        "renders": len(steps),
        "triangles": len(steps[-1]),
        "build_every_step_s": build_s,
        "updated_s": chain_s,
        "builds": int(rebuilds),
        "sah_over_fresh_max": max(ratios),
        "sah_over_fresh_last": ratios[-1],
        "rays": len(directions),
        "closest_hit_chain_ms": rays["chain"]["median_ms"],
        "closest_hit_fresh_ms": rays["fresh"]["median_ms"],
    }


def path_gradient(repeats: int, n_theta: int, n_phi: int) -> list[dict]:
    """Part 3: the light-position gradient with the scene's tree kept, and built anew."""
    corners = (0.3 * bumpy_sphere(n_theta, n_phi)).reshape(-1, 3) + [0.0, -0.5, 0.0]
    scene = cornell_box(32, 32)
    scene.objects.append(Mesh(corners, np.arange(len(corners)).reshape(-1, 3),
                              Material((0.6, 0.6, 0.6))))  # fmt: skip
    light = scene.objects[5].transform.translation
    light.requires_grad = True
    weights = md.tensor(np.random.default_rng(0).normal(size=(32, 32, 3)))

    def step() -> None:
        light.grad = None
        md.sum(render_path(scene, spp=16, max_depth=4, seed=0) * weights).backward()

    def built_every_time() -> None:
        kept = integrator.cache_for
        integrator.cache_for = lambda scene, reuse: RenderCache()
        try:
            step()
        finally:
            integrator.cache_for = kept

    rows, default = [], numba.get_num_threads()
    for threads in sorted({1, default}):
        numba.set_num_threads(threads)
        try:
            times = timing.measure_interleaved({"kept": step, "built": built_every_time}, repeats)
        finally:
            numba.set_num_threads(default)
        rows.append({"threads": threads, "triangles": len(corners) // 3,
                     "kept_ms": times["kept"]["median_ms"],
                     "built_ms": times["built"]["median_ms"]})  # fmt: skip
        kept, built = times["kept"]["median_ms"], times["built"]["median_ms"]
        print(f"path gradient, {threads} thread(s): tree kept {kept:.1f} ms, built at every "
              f"render {built:.1f} ms", flush=True)  # fmt: skip
    return rows


def main(argv=None) -> None:
    parser = timing.make_parser(__doc__, out=Path("out/bench_refit"))
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--iters", type=int, default=300)
    args = parser.parse_args(argv)
    quick = args.quick
    repeats = timing.QUICK_REPEATS if quick else args.repeats
    sizes = [(32, 64)] if quick else [(128, 320), (512, 1280)]
    meshes = large_meshes(repeats, sizes)
    steps = record_fit(3 if quick else args.iters, 32 if quick else 64)
    fit = replay(steps, 64, repeats)
    print(f"shape fit: {fit['renders']} renders of {fit['triangles']:,} triangles; built every "
          f"step {fit['build_every_step_s']:.3f} s, updated {fit['updated_s']:.3f} s with "
          f"{fit['builds']} builds; SAH over a fresh tree's: at most "
          f"{fit['sah_over_fresh_max']:.3f}, last {fit['sah_over_fresh_last']:.3f}; "
          f"{fit['rays']:,} camera rays {fit['closest_hit_chain_ms']:.2f} ms on the chain's "
          f"tree, {fit['closest_hit_fresh_ms']:.2f} ms on a fresh one", flush=True)  # fmt: skip
    path = path_gradient(repeats, *((8, 16) if quick else (128, 320)))
    timing.write_json(args.out, "refit", {"rebuild_ratio": REBUILD_RATIO, "meshes": meshes,
                                          "shape_fit": fit, "path_gradient": path})  # fmt: skip


if __name__ == "__main__":
    main()
