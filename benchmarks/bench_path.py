"""The path integrator: memory of its gradients against spp and depth, and its time per
sample.

Run:  python benchmarks/bench_path.py [--out out/bench_path] [--quick] [--part memory|speed]

* Memory: the peak of Python's traced allocations (``tracemalloc``; NumPy reports its
  arrays to it) during one gradient of an image loss on the Cornell box at 32x32, max_depth
  4, for three ways: through the tape (render, loss, backward: the tape holds every path
  until the backward), and the replay (``render.path.replay_gradient``, batches of 16
  samples: the compiled whole paths, ``render.path.gradient.window``) with the light's
  position and five albedos differentiated, and with the five albedos alone, from 16 to
  1,024 spp; then both replays from max_depth 2 to 8 at 64 spp (``rr_depth`` 100: paths go
  deep). The tape's peak is measured up to 256 spp and its growth per sample reported.
* Time: the Cornell box at 128x128, max_depth 4, 16 spp, medians after a warm-up, as
  microseconds per sample per pixel, timed in turns: a render that nothing differentiates
  (the compiled kernel) on 2 and on 1 Numba threads, the same render on the tape (the
  readable reference, ``gradient="tape"``), and render + backward of an MSE three ways:
  the five albedos (replay), the light's position and the albedos (replay), and through
  the tape. The comparison with Mitsuba 3 is
  ``benchmarks/bench_path_mitsuba.py``.

Writes ``bench_path.json`` to ``out/bench_path/`` (git-ignored scratch) unless ``--out`` is
given; the committed results are regenerated with ``--out docs/path_tracing``.
"""

from __future__ import annotations

import json
import tracemalloc
from pathlib import Path

import numba
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


def memory(size: int, tape_spps, replay_spps, depths, depth_spp: int) -> dict:
    scene, params, loss = _problem(size)

    def tape(spp):
        for p in params:
            p.grad = None
        loss(render_path(scene, spp=spp, max_depth=DEPTH, seed=0, gradient="tape")).backward()

    def replay(spp, depth=DEPTH, rr_depth=5, moving=params):
        for p in params:
            p.grad, p.requires_grad = None, any(p is q for q in moving)
        replay_gradient(scene, loss, spp=spp, max_depth=depth, seed=0, batch_spp=16,
                        rr_depth=rr_depth)  # fmt: skip
        for p in params:
            p.requires_grad = True

    albedos = params[1:]  # the albedos alone: no geometry moves

    out = {}
    # With minidiff's pool of reusable buffers (default, at most 512 MiB: a cache whose
    # arrays outlive the pass) and without it (what the gradient itself needs). A path
    # tracer's arrays change shape from batch to batch, so the pool fills with shapes that
    # are not asked for again until it reaches its cap.
    default_max = buffers.max_bytes()
    for pool, max_bytes in (("pool", default_max), ("no_pool", 0)):
        buffers.set_max_bytes(max_bytes)
        try:
            row = {"tape": {}, "replay": {}, "compiled": {}, "replay_depth": {},
                   "compiled_depth": {}}  # fmt: skip
            for spp in tape_spps:
                row["tape"][spp] = peak_mb(lambda s=spp: tape(s))
                print(f"{pool:8s} tape   {spp:5d} spp: {row['tape'][spp]:8.1f} MB", flush=True)
            for spp in replay_spps:
                row["replay"][spp] = peak_mb(lambda s=spp: replay(s))
                row["compiled"][spp] = peak_mb(lambda s=spp: replay(s, moving=albedos))
                print(f"{pool:8s} replay {spp:5d} spp: {row['replay'][spp]:8.1f} MB, compiled "
                      f"{row['compiled'][spp]:8.2f} MB", flush=True)  # fmt: skip
            for depth in depths:
                row["replay_depth"][depth] = peak_mb(lambda d=depth: replay(depth_spp, d, 100))
                row["compiled_depth"][depth] = peak_mb(
                    lambda d=depth: replay(depth_spp, d, 100, albedos)
                )
                replayed, compiled = row["replay_depth"][depth], row["compiled_depth"][depth]
                print(f"{pool:8s} max_depth {depth}: replay {replayed:8.1f} MB, compiled "
                      f"{compiled:8.2f} MB", flush=True)  # fmt: skip
        finally:
            buffers.set_max_bytes(default_max)
        spps = sorted(row["tape"])
        row["tape_mb_per_spp"] = (row["tape"][spps[-1]] - row["tape"][spps[0]]) / (
            spps[-1] - spps[0]
        )
        for name in ("replay", "compiled", "replay_depth", "compiled_depth"):
            values = list(row[name].values())
            row[f"{name}_max_over_min"] = max(values) / min(values)
        out[pool] = row
    return out


def speed(size: int, spp: int, repeats: int) -> dict:
    """Microseconds per sample per pixel of the renders and gradients in the docstring,
    timed in turns (``timing.measure_interleaved``), and their ratios."""
    scene, params, loss = _problem(size)
    threads = numba.get_num_threads()

    def render(gradient="replay"):
        return render_path(scene, spp=spp, max_depth=DEPTH, seed=0, gradient=gradient)

    def forward(n_threads):
        def run():
            numba.set_num_threads(n_threads)
            try:
                with md.no_grad():
                    render()
            finally:
                numba.set_num_threads(threads)

        return run

    def gradient(moving, way="replay"):
        def run():
            for p in params:
                p.grad, p.requires_grad = None, any(p is q for q in moving)
            loss(render(way)).backward()
            for p in params:
                p.requires_grad = True

        return run

    def taped_forward():
        render("tape")  # the parameters require grad: the image is computed on the tape

    fns = {
        "forward": forward(threads),
        "forward_1_thread": forward(1),
        "forward_on_tape": taped_forward,
        "gradient_albedos": gradient(params[1:]),
        "gradient_all": gradient(params),
        "gradient_tape": gradient(params, "tape"),
    }
    times = timing.measure_interleaved(fns, repeats, warmup=1)
    out = {"size": size, "spp": spp, "max_depth": DEPTH, "threads": threads}
    for name, t in times.items():
        out[name] = t | {"us_per_sample_per_pixel": t["median_ms"] * 1e3 / (size * size * spp)}
        per = out[name]["us_per_sample_per_pixel"]
        print(f"{name}: {t['median_ms']:.0f} ms, {per:.3f} us/sample/pixel", flush=True)
    base = out["forward"]["median_ms"]
    out["ratios"] = {
        "threads_speedup": out["forward_1_thread"]["median_ms"] / base,
        "tape_forward_over_forward": out["forward_on_tape"]["median_ms"] / base,
        "gradient_albedos_over_forward": out["gradient_albedos"]["median_ms"] / base,
        "gradient_all_over_forward": out["gradient_all"]["median_ms"] / base,
        "gradient_tape_over_forward": out["gradient_tape"]["median_ms"] / base,
    }
    print(out["ratios"])
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
            memory(16, (4, 8), (4, 8, 16), (2, 4), 4)
            if args.quick
            else memory(32, (16, 64, 256), (16, 64, 256, 1024), (2, 4, 8), 64)
        )
    if args.part in ("both", "speed"):
        result["speed"] = speed(32, 4, 2) if args.quick else speed(128, 16, 9)
    write_json(path, result)


if __name__ == "__main__":
    main()
