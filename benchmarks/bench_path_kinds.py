"""The path integrator's gradient for each kind of parameter, against the albedo's, and how
each scales with threads (issue 57's targets).

Run:  python benchmarks/bench_path_kinds.py [--out out/bench_path_kinds] [--quick]
      [--threads 1,2] [--size 32] [--spp 16] [--repeats 9]
(the committed results in docs/path_tracing/kinds/ were made with
``--out docs/path_tracing/kinds``)

The Cornell box with its blocks (a tall box and a sphere), ``size`` x ``size``, ``spp``
samples, max_depth 4. Each row is render + backward of a fixed random linear functional of
the image, one parameter differentiated, timed in turns (``timing.measure_interleaved``,
medians) on each thread count (``numba.set_num_threads``, which the compiled kernels of
``minidiff.compile`` follow too):

* ``albedo`` (the red wall's), ``light_position``, ``block_vertices``, ``sphere_centre``,
  ``camera_position``: every kind by the same route, the compiled whole paths
  (``render.path.gradient.window``: each path's reverse sweep inside one kernel) where
  they apply (here: everywhere), else the replay one depth at a time on the tape
  (``render.path.gradient.replay``); the albedo's is the yardstick of the others;
* ``light_position_secondary``: the light's position with ``antialias="secondary"``
  (the soft shadows' boundary term);
* ``light_position_tangent``: forward mode, the image and its tangent along the light's
  position (the compiled whole paths' JVP, ``window.tangent``); ``..._tangent_tape``: the
  same with ``gradient="tape"`` (the reference computing the tangents as it goes);
* ``forward``: the image alone (the compiled kernel, ``render.path.twin.kernel``);
* ``sampler``: the reference sampler's decisions for the image's paths
  (``PathSampler.sample``: the rays, and its compiled choices, ``render.path.sample.choices``),
  which the tape's gradient and the secondary term's continued paths use;
* ``wavefront``: the image's radiance without the kernel: the sampler's decisions, then
  the compiled whole paths' forward summing each path's radiance (``replay.radiance_of``).

Reported per row: the median (ms), its ratio to the albedo's on the same thread count
(target: at most 1.5), the secondary row over the plain light-position row (target: at
most 2.0), and each row's speed-up from the first thread count to the others (target:
at least 1.6 from 1 to 2).
"""

from __future__ import annotations

from pathlib import Path

import numba
import numpy as np
import timing

import minidiff as md
from render.path import render_path
from render.path.gradient.replay import radiance_of
from render.path.integrator import RR_DEPTH
from render.path.sample.tracer import PathSampler
from render.scene.camera import camera_frame
from render.scene.cornell import cornell_box
from render.scene.placement import placed

DEPTH = 4

#: The parameter each row differentiates.
PARAMETERS = {
    "albedo": lambda s: s.objects[3].material.albedo,
    "light_position": lambda s: s.objects[5].transform.translation,
    "block_vertices": lambda s: s.objects[6].vertices,
    "sphere_centre": lambda s: s.objects[7].center,
    "camera_position": lambda s: s.camera.position,
}


def _rows(size: int, spp: int) -> dict:
    """{row name: a function timing nothing, doing one render (+ backward)}."""
    weights = md.tensor(1.0 + 0.5 * np.random.default_rng(5).standard_normal((size, size, 3)))

    def gradient(name: str, antialias=False):
        scene = cornell_box(size, size, blocks=True)
        PARAMETERS[name](scene).requires_grad = True

        def run():
            image = render_path(scene, spp=spp, max_depth=DEPTH, seed=0, antialias=antialias)
            md.sum(image * weights).backward()

        return run

    def tangent(gradient: str):
        scene = cornell_box(size, size, blocks=True)
        direction = {PARAMETERS["light_position"](scene): np.array([0.3, -0.2, 0.5])}

        def run():
            with md.tangents(direction):
                render_path(scene, spp=spp, max_depth=DEPTH, seed=0, gradient=gradient)

        return run

    def forward():
        scene = cornell_box(size, size, blocks=True)
        with md.no_grad():
            render_path(scene, spp=spp, max_depth=DEPTH, seed=0)

    def sampler(radiance: bool = False):
        world = placed(cornell_box(size, size, blocks=True))
        paths = np.arange(size * size * spp, dtype=np.int64)  # pixel * spp + sample
        decisions = PathSampler(world, spp, DEPTH, RR_DEPTH, 0)
        batch = decisions.sample(paths)
        if radiance:
            radiance_of(world, camera_frame(world.camera), decisions, batch)

    rows = {name: gradient(name) for name in PARAMETERS}
    rows["light_position_secondary"] = gradient("light_position", "secondary")
    rows["light_position_tangent"] = tangent("replay")
    rows["light_position_tangent_tape"] = tangent("tape")
    rows["forward"] = forward
    rows["sampler"] = sampler
    rows["wavefront"] = lambda: sampler(radiance=True)
    return rows


def cost(size: int, spp: int, threads: list[int], repeats: int) -> list[dict]:
    """Per thread count: each row's median (ms) and its ratio to the albedo's."""
    rows = _rows(size, spp)
    default = numba.get_num_threads()
    out = []
    for n in threads:
        numba.set_num_threads(n)
        try:
            times = timing.measure_interleaved(rows, repeats, warmup=1)
        finally:
            numba.set_num_threads(default)
        row = {"threads": n} | {k: v["median_ms"] for k, v in times.items()}
        row["over_albedo"] = {k: row[k] / row["albedo"] for k in rows}
        row["secondary_over_plain"] = row["light_position_secondary"] / row["light_position"]
        row["tangent_over_tape"] = (
            row["light_position_tangent"] / row["light_position_tangent_tape"]
        )
        out.append(row)
        print(f"{n} threads: " + ", ".join(f"{k} {row[k]:.0f} ms" for k in rows), flush=True)
        ratios = ", ".join(f"{k} {v:.2f}" for k, v in row["over_albedo"].items())
        print(f"  over the albedo's: {ratios}", flush=True)
    first = out[0]
    for row in out:
        row["speedup"] = {k: first[k] / row[k] for k in rows}
    if len(out) > 1:
        print("speed-up from", first["threads"], "thread(s):",
              {k: round(v, 2) for k, v in out[-1]["speedup"].items()}, flush=True)  # fmt: skip
    return out


def main(argv=None) -> None:
    args, threads = timing.path_thread_options(
        __doc__, Path("out/bench_path_kinds"), size=32, repeats=9, argv=argv
    )
    size, spp, repeats = (8, 2, 1) if args.quick else (args.size, args.spp, args.repeats)
    result = {
        "size": size,
        "spp": spp,
        "max_depth": DEPTH,
        "cost": cost(size, spp, threads, repeats),
    }
    timing.write_json(args.out, "kinds", result)  # with the machine's description


if __name__ == "__main__":
    main()
