"""The path integrator: memory of its two gradients against spp, and its time per sample.

Run:  python benchmarks/bench_path.py [--out out/bench_path] [--quick] [--part memory|speed]

* Memory: the peak of Python's traced allocations (``tracemalloc``; NumPy reports its
  arrays to it) during one gradient of an image loss on the Cornell box at 32x32, max_depth
  4, for the gradient through the tape (render, loss, backward: the tape holds every path
  until the backward) and the replay gradient (``render.path.replay_gradient``, batches of
  16 samples), from 16 to 1,024 spp. The tape's peak is measured up to 256 spp and its
  growth per sample reported; the replay's at every spp.
* Time: one render of the Cornell box at 128x128, max_depth 4, 16 spp, without a tape, and
  one tape gradient; medians of 5 after a warm-up, as microseconds per sample per pixel.
  The comparison with Mitsuba 3 is ``benchmarks/bench_path_mitsuba.py``.

Writes ``bench_path.json`` to ``out/bench_path/`` (git-ignored scratch) unless ``--out`` is
given; the committed results are regenerated with ``--out docs/path_tracing``.
"""

from __future__ import annotations

import json
import time
import tracemalloc
from pathlib import Path

import numpy as np
import timing

import minidiff as md
from minidiff import buffers
from render.inverse.jsonio import write_json
from render.path import render_path, replay_gradient
from render.scene.cornell import cornell_box

DEPTH = 4


def _problem(size: int):
    """The Cornell box with the light's position and the walls' albedos differentiated, and
    an MSE loss against a target rendered with the light elsewhere."""
    target = render_path(cornell_box(size, size), spp=16, max_depth=DEPTH, seed=1).data
    scene = cornell_box(size, size)
    scene.objects[5].transform.translation.data = np.array([0.1, -0.05, 0.1])
    params = [scene.objects[5].transform.translation] + [
        scene.objects[i].material.albedo for i in range(5)
    ]
    for p in params:
        p.requires_grad = True

    def loss(image):
        return md.mean((image - md.tensor(target)) ** 2)

    return scene, params, loss


def peak_mb(fn) -> float:
    """Peak traced allocation during ``fn()``, in MB (above what was allocated before), with
    minidiff's pool of reusable buffers emptied first."""
    buffers.clear()
    tracemalloc.start()
    tracemalloc.reset_peak()
    base = tracemalloc.get_traced_memory()[0]
    fn()
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return (peak - base) / 1e6


def memory(size: int, tape_spps, replay_spps) -> dict:
    scene, params, loss = _problem(size)

    def tape(spp):
        for p in params:
            p.grad = None
        loss(render_path(scene, spp=spp, max_depth=DEPTH, seed=0, gradient="tape")).backward()

    def replay(spp):
        for p in params:
            p.grad = None
        replay_gradient(scene, loss, spp=spp, max_depth=DEPTH, seed=0, batch_spp=16)

    out = {}
    # With minidiff's pool of reusable buffers (default, at most 512 MiB: a cache whose
    # arrays outlive the pass) and without it (what the gradient itself needs). A path
    # tracer's arrays change shape from batch to batch, so the pool fills with shapes that
    # are not asked for again until it reaches its cap.
    default_max = buffers.max_bytes()
    for pool, max_bytes in (("pool", default_max), ("no_pool", 0)):
        buffers.set_max_bytes(max_bytes)
        try:
            row = {"tape": {}, "replay": {}}
            for spp in tape_spps:
                row["tape"][spp] = peak_mb(lambda s=spp: tape(s))
                print(f"{pool:8s} tape   {spp:5d} spp: {row['tape'][spp]:8.1f} MB", flush=True)
            for spp in replay_spps:
                row["replay"][spp] = peak_mb(lambda s=spp: replay(s))
                print(f"{pool:8s} replay {spp:5d} spp: {row['replay'][spp]:8.1f} MB", flush=True)
        finally:
            buffers.set_max_bytes(default_max)
        spps = sorted(row["tape"])
        row["tape_mb_per_spp"] = (row["tape"][spps[-1]] - row["tape"][spps[0]]) / (
            spps[-1] - spps[0]
        )
        values = list(row["replay"].values())
        row["replay_max_over_min"] = max(values) / min(values)
        out[pool] = row
    return out


def speed(size: int, spp: int, repeats: int) -> dict:
    scene, params, loss = _problem(size)

    def forward():
        with md.no_grad():
            render_path(scene, spp=spp, max_depth=DEPTH, seed=0)

    def gradient():
        for p in params:
            p.grad = None
        loss(render_path(scene, spp=spp, max_depth=DEPTH, seed=0, gradient="tape")).backward()

    out = {}
    for name, fn in (("forward", forward), ("tape_gradient", gradient)):
        fn()  # warm-up: Numba compiles, the BVH code loads
        times = []
        for _ in range(repeats):
            start = time.perf_counter()
            fn()
            times.append(time.perf_counter() - start)
        median = float(np.median(times))
        out[name] = {
            "median_s": median,
            "us_per_sample_per_pixel": median / (size * size * spp) * 1e6,
        }
        print(f"{name}: {median:.2f} s, {out[name]['us_per_sample_per_pixel']:.2f} us/sample/pixel")
    return out


def main(argv=None) -> None:
    parser = timing.make_parser(
        __doc__, out=Path("out/bench_path"), quick="memory at 16x16, speed at 32x32: a smoke run"
    )
    parser.add_argument(
        "--part", choices=("both", "memory", "speed"), default="both",
        help="measure one part only, keeping the other's results from bench_path.json",
    )  # fmt: skip
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "bench_path.json"
    result = json.loads(path.read_text()) if path.exists() and args.part != "both" else {}
    if args.part in ("both", "memory"):
        result["memory"] = (
            memory(16, (4, 8), (4, 8, 16))
            if args.quick
            else memory(32, (16, 64, 256), (16, 64, 256, 1024))
        )
    if args.part in ("both", "speed"):
        result["speed"] = speed(32, 4, 2) if args.quick else speed(128, 16, 5)
    write_json(path, result)


if __name__ == "__main__":
    main()
