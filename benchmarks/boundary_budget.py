"""Where the default boundary term's time goes: the rays it traces beside the plain render's,
and its two halves timed alone on 1 and 2 threads (issue 57's targets: its forward+backward
at most 3x a plain one, and 1.6x faster on 2 threads than on 1).

Run:  python benchmarks/boundary_budget.py [--out DIR] [--quick] [--repeats 15] [--size 512]
(DIR: out/benchmarks by default; the committed results in docs/benchmarks/budget/ were made
with ``--out docs/benchmarks/budget``)

The paper scene at 512x512 (64x64 with ``--quick``), its light moved as in
``bench_render.loss_problem``, ``antialias="boundary"`` with its default 16 interior samples:

1. ``rays``: what the plain render traces (its camera rays, rasterised, and one shadow ray
   per hit and light) against what the boundary term adds: the candidates for mixed
   pixels that the crease test keeps (``render.edges.interior``, counted as
   ``mixed_pixels.py`` counts them), whose interior samples are traced; the mixed pixels
   among them, whose samples' hits are shadow-tested as camera hits are; and the curves'
   quadrature points whose factor is not zero (each such point's two sides are shaded: a
   shadow ray per side and light, and rays that test whether the point is seen).
2. ``time``: medians, in turns, each on 1 and 2 threads (``minidiff.threads.using_threads``):
   a plain forward+backward into every parameter, the boundary term's, and its two halves
   alone, which a render runs side by side (``minidiff.threads.beside``): the curves'
   points (``render.edges.terms.boundary_points_of``) and the mixed pixels' search
   (``render.edges.interior.mixed_pixels``). Each block of timed calls follows
   ``WARM_SECONDS`` of untimed calls of the same workload (``bench_speed.py``: a core left
   idle wakes slowly).
3. ``profiled_ms``: each half on 1 thread under ``cProfile``, its time in all and in the
   kernels that trace rays (``RAY_KERNELS``).
"""

from __future__ import annotations

import cProfile
import pstats
import time

import bench_render
import mixed_pixels as search
import numpy as np
import timing

from minidiff.threads import using_threads
from render.edges import interior
from render.edges.terms import boundary_points_of
from render.scene.cache import RenderCache
from render.scene.camera import camera_frame
from render.scene.placement import placed
from render.trace.visibility import trace_visibility

#: Untimed calls before each block of timed ones (as ``bench_speed.WARM_SECONDS``).
WARM_SECONDS = 0.3
#: Interior samples per mixed pixel: the default (``render.edges.interior``).
INTERIOR = interior.INTERIOR_SAMPLES
#: The compiled kernels that trace rays (the BVH's, the rasteriser's, the light's view's),
#: by name: ``ray_kernels`` sums their time.
RAY_KERNELS = ("closest_hit_bvh", "occluded_bvh", "_occluded_by_cell", "_raster_occluded",
               "_raster_closest_hit", "_bisect_blocks")  # fmt: skip


def rays(size: int) -> dict:
    """The rays of the plain render and those the boundary term adds (module docstring, 1)."""
    scene, _, _ = bench_render.loss_problem(size)
    world = placed(scene)
    visibility = trace_visibility(world, RenderCache(), True, 1, True)
    found = interior.mixed_pixels(world, visibility, 1, INTERIOR)
    pixels, seen = found if found is not None else (np.zeros(0, np.int64), None)
    kinds, points = boundary_points_of(world, visibility, RenderCache(),
                                       camera_frame(world.camera), 2)  # fmt: skip
    return {
        "lights": len(world.lights),
        "camera_rays": size * size,
        "hits": int(len(visibility.primary.hit_rays)),
        "candidates": search.counts(world)["kept"],  # those whose samples are traced
        "mixed": int(len(pixels)),
        "interior_samples": int(len(pixels) * INTERIOR),
        "interior_hits": 0 if seen is None else int(len(seen.primary.hit_rays)),
        "curve_points": {
            type(kind).__name__: len(on.pixel) for kind, on in zip(kinds, points, strict=True)
        },
    }


def workloads(size: int) -> dict:
    """{name: callable} of the timed workloads, each on 1 and 2 threads."""
    scene, params, target = bench_render.loss_problem(size)
    world = placed(scene)
    visibility = trace_visibility(world, RenderCache(), True, 1, True)
    frame = camera_frame(world.camera)
    plain = {
        "fb_plain": lambda: bench_render.forward_backward(scene, params, target),
        "fb_boundary": lambda: bench_render.forward_backward(
            scene, params, target, antialias="boundary", interior_samples=INTERIOR
        ),
        "points": lambda: boundary_points_of(world, visibility, RenderCache(), frame, 2),
        "mixed_pixels": lambda: interior.mixed_pixels(world, visibility, 1, INTERIOR),
    }
    out = {}
    for name, fn in plain.items():
        for threads in (1, 2):

            def on(fn=fn, threads=threads):
                with using_threads(threads):
                    fn()

            out[f"{name}_{threads}"] = on
    return out


def times(size: int, repeats: int, block: int = 3) -> dict:
    """Medians (ms) of every workload, in turns, blocks of ``block`` calls after
    ``WARM_SECONDS`` of untimed calls (module docstring, 2)."""
    fns = workloads(size)
    for fn in fns.values():  # compilation, caches
        fn()
        fn()
    spent = {name: [] for name in fns}
    for _ in range(-(-repeats // block)):
        for name, fn in fns.items():
            start = time.perf_counter()
            while time.perf_counter() - start < WARM_SECONDS:
                fn()
            for _ in range(block):
                t0 = time.perf_counter()
                fn()
                spent[name].append(time.perf_counter() - t0)
    return {name: timing.summarize(t) for name, t in spent.items()}


def ray_kernels(size: int, calls: int) -> dict:
    """{half: (ms per call in all, ms per call in ``RAY_KERNELS``)} of the two halves on 1
    thread, profiled (``cProfile``: the kernels' own time, the Python around them slowed a
    little by the profiler)."""
    fns = workloads(size)
    out = {}
    for half in ("points", "mixed_pixels"):
        fn = fns[f"{half}_1"]
        fn()
        profile = cProfile.Profile()
        profile.enable()
        for _ in range(calls):
            fn()
        profile.disable()
        stats = pstats.Stats(profile).stats
        total = sum(entry[2] for entry in stats.values())
        ray = sum(entry[2] for key, entry in stats.items() if key[2] in RAY_KERNELS)
        out[half] = (1e3 * total / calls, 1e3 * ray / calls)
    return out


def run(args) -> dict:
    counted = rays(args.size)
    timed = times(args.size, args.repeats)
    profiled = ray_kernels(args.size, args.repeats)
    ms = {name: t["median_ms"] for name, t in timed.items()}
    traced = counted["candidates"] * INTERIOR
    ratios = {
        "boundary_over_plain_2": ms["fb_boundary_2"] / ms["fb_plain_2"],
        "boundary_over_plain_1": ms["fb_boundary_1"] / ms["fb_plain_1"],
        "threads_boundary": ms["fb_boundary_1"] / ms["fb_boundary_2"],
        "threads_plain": ms["fb_plain_1"] / ms["fb_plain_2"],
        "threads_points": ms["points_1"] / ms["points_2"],
        "threads_mixed_pixels": ms["mixed_pixels_1"] / ms["mixed_pixels_2"],
        "traced_samples_over_camera_rays": traced / counted["camera_rays"],
        "interior_hits_over_hits": counted["interior_hits"] / counted["hits"],
        "ray_kernels_points": profiled["points"][1] / profiled["points"][0],
        "ray_kernels_mixed_pixels": profiled["mixed_pixels"][1] / profiled["mixed_pixels"][0],
    }
    return {
        "size": args.size,
        "interior_samples_per_pixel": INTERIOR,
        "warm_seconds": WARM_SECONDS,
        "rays": counted,
        "profiled_ms": {half: {"all": a, "ray_kernels": r} for half, (a, r) in profiled.items()},
        "time": timed,
        "ratios": ratios,
        "report": report(args.size, counted, ms, ratios),
    }


def report(size: int, counted: dict, ms: dict, ratios: dict) -> dict:
    """The report section (``timing.report_section``) of ``run``'s result."""
    points = ", ".join(f"{k} {v:,}" for k, v in counted["curve_points"].items())
    rows = [
        timing.row("plain render: camera rays / hits (shadow rays per light)",
                   f"{counted['camera_rays']:,} / {counted['hits']:,}"),
        timing.row("boundary term: candidates traced / their samples",
                   f"{counted['candidates']:,} / {counted['candidates'] * INTERIOR:,}"),
        timing.row("boundary term: mixed pixels / their samples / hits among them",
                   f"{counted['mixed']:,} / {counted['interior_samples']:,} / "
                   f"{counted['interior_hits']:,}"),
        timing.row("boundary term: curve points (non-zero factor)", points),
        timing.row("f+b ms, 1 / 2 threads: plain",
                   f"{ms['fb_plain_1']:.1f} / {ms['fb_plain_2']:.1f}"),
        timing.row("f+b ms, 1 / 2 threads: boundary",
                   f"{ms['fb_boundary_1']:.1f} / {ms['fb_boundary_2']:.1f}"),
        timing.row("alone ms, 1 / 2 threads: curve points",
                   f"{ms['points_1']:.1f} / {ms['points_2']:.1f}"),
        timing.row("alone ms, 1 / 2 threads: mixed pixels' search",
                   f"{ms['mixed_pixels_1']:.1f} / {ms['mixed_pixels_2']:.1f}"),
        timing.row("profiled, 1 thread: ray kernels' share of the curve points / the search",
                   f"{ratios['ray_kernels_points']:.0%} / "
                   f"{ratios['ray_kernels_mixed_pixels']:.0%}"),
        timing.target_row("boundary f+b / plain f+b (2 threads)",
                          f"{ratios['boundary_over_plain_2']:.2f}x",
                          ratios["boundary_over_plain_2"], 3.0, "3.0x"),
        timing.row("1 -> 2 threads: boundary f+b",
                   f"{ratios['threads_boundary']:.2f}x", "at least 1.6x",
                   "met" if ratios["threads_boundary"] >= 1.6 else "not met"),
    ]  # fmt: skip
    return timing.report_section(f"The default boundary term's budget ({size}x{size})",
                                 rows, [], [])  # fmt: skip


def main(argv=None) -> dict:
    return timing.main("boundary_budget", __doc__, run, argv, repeats=15, size=(512, 64))


if __name__ == "__main__":
    main()
