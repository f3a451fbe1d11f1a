"""What secondary visibility's boundary term costs, and how the path integrator scales with
threads.

Run:  python benchmarks/bench_secondary.py [--out out/bench_secondary] [--quick]
      [--threads 1,2]
(the committed results in docs/path_tracing/secondary/ were made with
``--out docs/path_tracing/secondary``)

The Cornell box with its blocks seen from a camera that sees the floor and the blocks'
soft shadows but not the light (``benchmarks/path_gradients.py``'s ``scene_for``), max_depth
4, no Russian roulette before depth 100. For each number of Numba threads, timed in turns
(``timing.measure_interleaved``, medians):

* ``forward``: the image alone (the compiled kernel);
* ``plain``: render + backward of a fixed random linear functional of the image for the
  light's position (the replay on the tape), without edge terms;
* ``secondary``: the same with ``antialias="secondary"``;
* ``boundary``: with ``antialias="boundary"`` (the camera's term too).

The issue's target is the term's own cost, (secondary - plain) / plain, at most 3.
``variance`` (on the default thread count): the light position's directional derivative
over seeds with the term, its standard deviation, the time per gradient, and their
product's square (variance x time: what a fixed error bar costs).
"""

from __future__ import annotations

from pathlib import Path

import numba
import numpy as np
import timing
from path_gradients import DIRECTIONS, scene_for

import minidiff as md
from render.path import render_path

DEPTH = 4


def _problem(size: int, spp: int):
    weights = 1.0 + 0.5 * np.random.default_rng(5).standard_normal((size, size, 3))

    def gradient(antialias, seed=0):
        scene = scene_for(True, False)
        scene.camera.width = scene.camera.height = size
        p = scene.objects[5].transform.translation
        p.requires_grad = True
        image = render_path(scene, spp=spp, max_depth=DEPTH, seed=seed, rr_depth=100,
                            antialias=antialias)  # fmt: skip
        md.sum(image * md.tensor(weights)).backward()
        return float(p.grad @ DIRECTIONS["light_position"])

    def forward():
        scene = scene_for(True, False)
        scene.camera.width = scene.camera.height = size
        with md.no_grad():
            render_path(scene, spp=spp, max_depth=DEPTH, seed=0, rr_depth=100)

    return gradient, forward


def cost(size: int, spp: int, threads: list[int], repeats: int) -> list[dict]:
    """Per thread count: medians (ms) of forward, plain, secondary, boundary; ratios."""
    gradient, forward = _problem(size, spp)
    default = numba.get_num_threads()
    rows = []
    for n in threads:
        numba.set_num_threads(n)
        try:
            times = timing.measure_interleaved(
                {
                    "forward": forward,
                    "plain": lambda: gradient(False),
                    "secondary": lambda: gradient("secondary"),
                    "boundary": lambda: gradient("boundary"),
                },
                repeats,
                warmup=1,
            )
        finally:
            numba.set_num_threads(default)
        row = {"threads": n} | {k: v["median_ms"] for k, v in times.items()}
        row["secondary_over_plain"] = row["secondary"] / row["plain"]
        row["term_over_plain"] = (row["secondary"] - row["plain"]) / row["plain"]
        row["boundary_over_plain"] = row["boundary"] / row["plain"]
        rows.append(row)
        print(
            f"{n:2d} threads: forward {row['forward']:.0f} ms, plain {row['plain']:.0f} ms, "
            f"secondary {row['secondary']:.0f} ms, boundary {row['boundary']:.0f} ms; the "
            f"term {row['term_over_plain']:.2f}x plain",
            flush=True,
        )
    first = rows[0]
    for row in rows:
        for name in ("forward", "plain", "secondary"):
            row[f"{name}_speedup_over_{first['threads']}_thread"] = first[name] / row[name]
    return rows


def variance(size: int, spp: int, seeds: int) -> dict:
    """The light position's directional derivative with the term, over seeds."""
    gradient, _ = _problem(size, spp)
    values, times = [], []
    for seed in range(seeds):
        t = timing.time.perf_counter()
        values.append(gradient("secondary", seed))
        times.append(timing.time.perf_counter() - t)
    values = np.array(values)
    out = {
        "seeds": seeds,
        "mean": values.mean(),
        "std": values.std(ddof=1),
        "standard_error": values.std(ddof=1) / np.sqrt(seeds),
        "seconds_per_gradient": float(np.median(times)),
    }
    out["variance_times_seconds"] = out["std"] ** 2 * out["seconds_per_gradient"]
    print(out, flush=True)
    return out


def main(argv=None) -> None:
    args, threads = timing.path_thread_options(
        __doc__, Path("out/bench_secondary"), size=64, repeats=7, argv=argv
    )
    size, spp, repeats, seeds = (
        (16, 2, 2, 3) if args.quick else (args.size, args.spp, args.repeats, 16)
    )
    timed = cost(size, spp, threads, repeats)
    result = {"size": size, "spp": spp, "max_depth": DEPTH, "cost": timed}
    result["variance"] = variance(size, spp, seeds)
    timing.write_json(args.out, "cost", result)  # with the machine's description


if __name__ == "__main__":
    main()
