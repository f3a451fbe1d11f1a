"""How long the compiled paths' gradient (``render.path.gradient.window``) takes to compile,
by the number of depths of the paths.

Run:  python benchmarks/bench_path_compile.py [--out out/bench_path_compile] [--quick]

The Cornell box with its blocks at 16x16, 4 spp, no Russian roulette (so every batch
reaches ``max_depth``), the light's position differentiated. For each ``max_depth`` in
increasing order, in one process with an empty minidiff cache of its own (a temporary
folder): the first gradient (which traces ``path_terms`` for the segments of that many
depths that the depths before did not need, ``window.SEGMENT`` depths at most each,
generates their VJPs and compiles them with LLVM) and the second (the kernels in memory);
the difference is the compile latency. Numba's kernels are compiled (or loaded) before the first
measurement. Then, at the last of those depths, the box's last mesh given 1, 2, 3
vertices more (copies of its first, which no face uses: the same image): the first and
second gradient at each length, where a kernel compiled for one length of the path tables
serves every other (``minidiff.codegen``: a table's row count is read when the kernel
runs), so only the trace is made again. (``main`` called inside a process that has
compiled these kernels already, as the smoke test does with ``--quick``, measures
whatever its cache holds.) Writes
``bench_path_compile.json``; the committed one is regenerated with ``--out
docs/path_tracing``.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

DEPTHS = (2, 4, 8, 16, 32)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("out/bench_path_compile"))
    parser.add_argument("--quick", action="store_true", help="max_depth 2 only")
    args = parser.parse_args(argv)
    import numpy as np

    import minidiff as md
    from render.inverse.jsonio import write_json
    from render.path import render_path
    from render.scene.cornell import cornell_box

    scene = cornell_box(16, 16, blocks=True)
    light = scene.objects[5].transform.translation
    light.requires_grad = True

    def gradient(depth: int) -> float:
        light.grad = None
        start = time.perf_counter()
        image = render_path(scene, spp=4, max_depth=depth, seed=0, rr_depth=100)
        md.sum(image * image).backward()
        return time.perf_counter() - start

    with md.no_grad():  # Numba's kernels (the image's), compiled or loaded from its cache
        render_path(scene, spp=1, max_depth=2, seed=0)
    rows = []
    for depth in (2,) if args.quick else DEPTHS:
        first, second = gradient(depth), gradient(depth)
        rows.append({"max_depth": depth, "first_s": first, "second_s": second,
                     "compile_s": first - second})  # fmt: skip
        print(f"max_depth {depth:2d}: first {first:.2f} s, then {second:.3f} s", flush=True)
    lengths = []
    mesh = scene.meshes[-1]
    vertices = np.asarray(mesh.vertices.data)
    for extra in (1, 2, 3):
        mesh.vertices = md.tensor(np.concatenate([vertices, np.repeat(vertices[:1], extra, 0)]))
        first, second = gradient(depth), gradient(depth)
        lengths.append({"extra_vertices": extra, "vertices": len(vertices) + extra,
                        "first_s": first, "second_s": second})  # fmt: skip
        print(f"{extra} more vertices: first {first:.3f} s, then {second:.3f} s", flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    write_json(args.out / "bench_path_compile.json",
               {"size": 16, "spp": 4, "runs": rows, "longer_mesh": lengths})  # fmt: skip


if __name__ == "__main__":
    os.environ["MINIDIFF_CACHE_DIR"] = tempfile.mkdtemp()  # empty, before minidiff is imported
    main()
