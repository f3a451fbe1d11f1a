"""Dense meshes: the edge terms where a mesh has many faces per pixel or per path vertex.

Run:  python benchmarks/bench_dense.py [--out out/bench_dense] [--quick]
(the committed results in docs/benchmarks/dense/ were made with
``--out docs/benchmarks/dense``)

Two cases, each a UV sphere of ``4 n^2`` flat faces (``uv_sphere``):

* ``secondary``: the path integrator's secondary-visibility term (the Cornell box without
  its blocks, the sphere in it, 16x16 pixels, 4 spp, max_depth 3, the light's position
  differentiated): render + backward with the term, with it but no run of edges skipped
  (``Curves.clusters`` told that no run may be: every edge tested at every vertex, as
  before runs were skipped), and without the term; timed in turns
  (``timing.measure_interleaved``, medians).
* ``direct``: the direct renderer's boundary term (``antialias="boundary"``) of the
  sphere over a floor at 128 x 128, its vertices moved before each render as in a shape
  fit (every table of the geometry made anew): one render + backward each, the time and
  the boundary term's pieces and their most in one pixel. At 360k faces the split at
  crossings once asked for a table of every pair of pieces in a pixel (32 GiB) and failed.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import timing

import minidiff as md
import render
from render.path import render_path
from render.path.boundary import silhouettes
from render.scene.cornell import cornell_box

GREY = render.Material((0.6, 0.6, 0.6))


def uv_sphere(n: int, radius: float = 1.0, centre=(0.0, 0.0, 0.0)):
    """A UV sphere: (n + 1) x 2n vertices, 4 n^2 faces wound outward (flat-shaded)."""
    around = np.linspace(0, 2 * np.pi, 2 * n, endpoint=False)
    theta, phi = np.meshgrid(np.linspace(0, np.pi, n + 1), around, indexing="ij")
    v = np.stack([np.sin(theta) * np.cos(phi), np.cos(theta), np.sin(theta) * np.sin(phi)], -1)
    v = v.reshape(-1, 3) * radius + np.asarray(centre)
    idx = np.arange(len(v)).reshape(n + 1, 2 * n)
    a, b = idx[:-1], np.roll(idx[:-1], -1, 1)
    c, d = idx[1:], np.roll(idx[1:], -1, 1)
    faces = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3),
                            np.stack([b, c, d], -1).reshape(-1, 3)])  # fmt: skip
    return v, faces


def secondary_rows(n: int, repeats: int) -> dict:
    """The secondary term's three rows for a sphere of 4 n^2 faces (module docstring)."""
    scene = cornell_box(16, 16, blocks=False)
    v, f = uv_sphere(n, 0.2, (0.0, -0.1, 0.0))
    scene.objects.append(render.Mesh(v, f, GREY))
    light = scene.objects[5].transform.translation
    light.requires_grad = True

    def gradient(antialias, skip=True):
        def run():
            light.grad = None
            clusters = silhouettes.Curves.clusters
            if not skip:  # every run kept: each edge tested at every vertex
                silhouettes.Curves.clusters = property(
                    lambda self: (clusters.func(self)[0], np.zeros_like(clusters.func(self)[1]))
                )
            try:
                image = render_path(scene, spp=4, max_depth=3, seed=0, antialias=antialias)
                md.sum(image).backward()
            finally:
                silhouettes.Curves.clusters = clusters

        return run

    rows = {
        "secondary": gradient("secondary"),
        "secondary_every_edge": gradient("secondary", skip=False),
        "plain": gradient(False),
    }
    times = timing.measure_interleaved(rows, repeats, warmup=1)
    out = {"faces": len(f), **{k: v["median_ms"] for k, v in times.items()}}
    out["every_edge_over_skipping"] = out["secondary_every_edge"] / out["secondary"]
    return out


def direct_row(n: int) -> dict:
    """The direct renderer's boundary term on a sphere of 4 n^2 faces at 128 x 128."""
    import render.edges.boundary.term as term

    v, f = uv_sphere(n, 1.0, (0.0, 1.2, 0.0))
    floor = render.Mesh(np.array([[-3, 0, -3], [3, 0, -3], [3, 0, 3], [-3, 0, 3.0]]),
                        np.array([[0, 2, 1], [0, 3, 2]]), GREY)  # fmt: skip
    camera = render.Camera((0, 3, 6), (0, 1, 0), (0, 1, 0), 45.0, 128, 128)
    scene = render.Scene([floor, render.Mesh(v, f, GREY)], [render.PointLight((1, 5, 1), 20.0)],
                         camera)  # fmt: skip
    vertices = scene.objects[1].vertices
    vertices.requires_grad = True
    seen = {}
    split = term.split_at_crossings

    def spy(p0, p1, segment, start, end, pixel):
        seen["pieces"] = len(pixel)
        seen["most_in_a_pixel"] = int(np.bincount(pixel).max()) if len(pixel) else 0
        return split(p0, p1, segment, start, end, pixel)

    def run() -> float:
        vertices.data[:, 0] += 1e-5  # moved: the geometry's tables made anew
        vertices.grad = None
        start = time.perf_counter()
        image = render.render(scene, antialias="boundary")
        md.sum(image).backward()
        return time.perf_counter() - start

    term.split_at_crossings = spy
    try:
        run()  # compiles
        seconds = [run() for _ in range(2)]
    finally:
        term.split_at_crossings = split
    return {"faces": len(f), "f_b_ms": 1000 * float(np.median(seconds)), **seen}


def main(argv=None) -> None:
    parser = timing.make_parser(__doc__, out=Path("out/bench_dense"))
    args = parser.parse_args(argv)
    sizes, direct, repeats = ((10,), (30,), 1) if args.quick else ((60, 120), (100, 300), 5)
    result = {
        "secondary": [secondary_rows(n, repeats) for n in sizes],
        "direct": [direct_row(n) for n in direct],
    }
    for row in result["secondary"]:
        print(f"secondary, {row['faces']} faces: {row['secondary']:.0f} ms (every edge tested: "
              f"{row['secondary_every_edge']:.0f} ms; without the term {row['plain']:.0f} ms)",
              flush=True)  # fmt: skip
    for row in result["direct"]:
        print(f"direct boundary f+b, {row['faces']} faces at 128x128: {row['f_b_ms']:.0f} ms "
              f"({row['pieces']} pieces, at most {row['most_in_a_pixel']} in a pixel)",
              flush=True)  # fmt: skip
    timing.write_json(args.out, "bench_dense", result)


if __name__ == "__main__":
    main()
