"""How much of a path-traced sample is rays through the BVH, and how much is the rest?

Run:  python benchmarks/bench_path_rays.py [--out out/bench_path_rays] [--quick]
      [--threads 1,2] [--size 128] [--spp 16] [--repeats 7]
(the committed results in docs/benchmarks/path_rays/ were made with
``--out docs/benchmarks/path_rays``)

The Cornell box with its blocks, ``size`` x ``size``, ``spp`` samples, max_depth 4 (as
``bench_path_mitsuba.py``'s speed row) and 5 (issue 58's comparison), rr_depth
``integrator.RR_DEPTH``.

* **All**: the image, ``render_path`` without a tape: the hand-written kernel
  (``render.path.twin.kernel``), which traces each path's rays one after the other, between
  its shading.
* **Rays**: the very rays that kernel traces, through the same BVH, on their own. The
  reference sampler (``render.path.sample.tracer.PathSampler``) makes the kernel's
  decisions from the same random numbers (``tests/render/path/test_kernel.py``); its
  accelerator's calls are recorded (the camera rays, each depth's continuation rays, the
  shadow rays of next-event estimation where the kernel traces one: where the emitter's
  point passes its checks, ``nee_ok``), then replayed as those batches, timed.
* **Rest** = all - rays: the shading, sampling, random numbers and bookkeeping.

Batched rays are not the kernel's interleaved ones: a batch walks the tree for many rays of
one depth in a row (warmer caches, no shading between them), so "rays" is what the rays
would cost traced apart, and "rest" absorbs any difference. Reported per depth and thread
count: the three medians (ms), microseconds per sample per pixel, rays per sample, and the
rays' share of the whole.
"""

from __future__ import annotations

from pathlib import Path

import numba
import numpy as np
import timing

import minidiff as md
from render.path import render_path
from render.path.integrator import RR_DEPTH
from render.path.sample.tracer import PathSampler
from render.scene.cornell import cornell_box
from render.scene.placement import placed


class _Recorder:
    """An accelerator that records every query it answers (and answers it)."""

    def __init__(self, accelerator):
        self.accelerator = accelerator
        self.calls: list[tuple[str, tuple, dict]] = []
        self.keep: np.ndarray | None = None  # the shadow rays the kernel traces, when set

    def closest_hit(self, origins, directions, **options):
        self.calls.append(("closest_hit", (np.array(origins), np.array(directions)), options))
        return self.accelerator.closest_hit(origins, directions, **options)

    def occluded(self, origins, directions, tmax, **options):
        keep = slice(None) if self.keep is None else self.keep
        kept = {k: (v[keep] if isinstance(v, np.ndarray) else v) for k, v in options.items()}
        tmax_kept = tmax[keep] if isinstance(tmax, np.ndarray) else tmax
        self.calls.append(("occluded", (origins[keep], directions[keep], tmax_kept), kept))
        return self.accelerator.occluded(origins, directions, tmax, **options)


def recorded_rays(scene, spp: int, depth: int) -> tuple[object, list]:
    """The accelerator and the queries (name, arguments, options) of the image's paths."""
    world = placed(scene)
    sampler = PathSampler(world, spp, depth, RR_DEPTH, 0)
    recorder = _Recorder(sampler.accelerator)
    sampler.accelerator = recorder
    original = PathSampler._next_event

    def next_event(self, record, state, prims, choices):
        recorder.keep = choices.nee_ok  # the kernel traces NEE's ray only where it is ok
        try:
            original(self, record, state, prims, choices)
        finally:
            recorder.keep = None

    PathSampler._next_event = next_event
    try:
        camera = scene.camera
        sampler.sample(np.arange(camera.width * camera.height * spp, dtype=np.int64))
    finally:
        PathSampler._next_event = original
    return recorder.accelerator, recorder.calls


def split(size: int, spp: int, depth: int, threads: list[int], repeats: int) -> list[dict]:
    """Per thread count: the whole image, its rays alone, the rest (module docstring)."""
    scene = cornell_box(size, size, blocks=True)
    accelerator, calls = recorded_rays(scene, spp, depth)
    n_rays = sum(len(args[0]) for _, args, _ in calls)
    samples = size * size * spp

    def image():
        with md.no_grad():
            render_path(scene, spp=spp, max_depth=depth, seed=0)

    def rays():
        for name, args, options in calls:
            getattr(accelerator, name)(*args, **options)

    default = numba.get_num_threads()
    out = []
    for n in threads:
        numba.set_num_threads(n)
        try:
            times = timing.measure_interleaved({"all": image, "rays": rays}, repeats, warmup=1)
        finally:
            numba.set_num_threads(default)
        whole, traced = times["all"]["median_ms"], times["rays"]["median_ms"]
        row = {
            "threads": n,
            "max_depth": depth,
            "all_ms": whole,
            "rays_ms": traced,
            "rest_ms": whole - traced,
            "rays_share": traced / whole,
            "us_per_sample_per_pixel": 1e3 * whole / samples,
            "rays_us_per_sample_per_pixel": 1e3 * traced / samples,
            "rest_us_per_sample_per_pixel": 1e3 * (whole - traced) / samples,
            "rays_per_sample": n_rays / samples,
            "ns_per_ray": 1e6 * traced / n_rays,
        }
        out.append(row)
        print(f"depth {depth}, {n} threads: all {whole:.1f} ms, rays {traced:.1f} ms "
              f"({100 * row['rays_share']:.0f} %), rest {whole - traced:.1f} ms; "
              f"{row['rays_per_sample']:.2f} rays a sample, {row['ns_per_ray']:.1f} ns a ray",
              flush=True)  # fmt: skip
    return out


def main(argv=None) -> dict:
    args, threads = timing.path_thread_options(
        __doc__, Path("out/bench_path_rays"), size=128, repeats=7, argv=argv
    )
    size, spp, repeats = (8, 2, 1) if args.quick else (args.size, args.spp, args.repeats)
    depths = [4] if args.quick else [4, 5]
    result = {
        "size": size,
        "spp": spp,
        "rr_depth": RR_DEPTH,
        "rows": [row for d in depths for row in split(size, spp, d, threads, repeats)],
    }
    timing.write_json(args.out, "path_rays", result)
    return result


if __name__ == "__main__":
    main()
