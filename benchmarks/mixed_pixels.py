"""What the mixed-pixel search of ``antialias="boundary"`` traces (``render.edges.interior``),
and what its crease test (``past_creases``) leaves out of it.

Run:  python benchmarks/mixed_pixels.py [--out out/mixed_pixels] [--quick] [--views 80]
(the committed results in docs/edges/ were made with ``--out docs/edges``)

1. ``paper``: the paper scene at 512x512, without and with its ground: the candidates
   (``candidate_pixels``), those the crease test keeps, and the mixed pixels among
   either (a candidate is mixed if its 16 stratified samples, from a 16-spp render, do
   not all see the primitive, lit alike, that its centre sees); ``lost``: mixed
   candidates that the test leaves out.
2. ``views``: the same counts summed over random views (the camera and the light moved by
   a normal step of 1 in each coordinate) of the paper scene with and without its
   ground and of its teapot tessellated more or less finely (2-7 patches' rows and
   columns), 24x24 to 100x100.
3. ``time``: at 512x512, in turns (medians), the default boundary term's forward +
   backward of the light's position, and a plain one (no edge terms), each render with
   ``reuse_visibility=False``; and the search alone (``mixed_pixels``); each with the
   crease test and without it (the candidates as ``candidate_pixels`` finds them).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import timing

import minidiff as md
import render
from render.edges import interior
from render.scene.cache import RenderCache
from render.scene.camera import plain_frame
from render.trace.visibility import trace_visibility


def counts(scene: render.Scene) -> dict:
    """Candidates, kept candidates, mixed among each, and the mixed left out (``lost``), for
    ``scene`` at 1 spp and 16 interior samples."""
    width, height = scene.camera.width, scene.camera.height
    one = trace_visibility(scene, RenderCache(), True, 1, True)
    seen = interior.what_is_seen(one, width * height)
    found = interior.candidate_pixels(*seen, width, height, 1)
    kept = interior.past_creases(found, *seen, width, height, 1, one.primitives[0],
                                 plain_frame(scene.camera), 16)  # fmt: skip
    dense = trace_visibility(scene, RenderCache(), True, 16, True)
    prim = dense.primary.prim_id.reshape(-1, 16)
    mixed = np.any(prim != seen[0][:, None], axis=1)
    for j, mask in enumerate(dense.lit):
        lit = np.zeros(prim.size, bool)
        lit[dense.primary.hit_rays] = mask
        mixed |= np.any(lit.reshape(-1, 16) != seen[1][:, j, None], axis=1)
    mixed = np.flatnonzero(mixed)
    among, kept_mixed = np.isin(mixed, found).sum(), np.isin(mixed, kept).sum()
    return {"candidates": len(found), "kept": len(kept), "mixed_candidates": int(among),
            "mixed_kept": int(kept_mixed), "lost": int(among - kept_mixed)}  # fmt: skip


def random_views(n: int, seed: int = 0) -> list[dict]:
    """``counts`` of ``n`` random views (module docstring, 2.)."""
    rng = np.random.default_rng(seed)
    out = []
    for view in range(n):
        size = int(rng.choice([24, 48, 64, 100]))
        patches = (4, 6) if view % 2 == 0 else tuple(int(k) for k in rng.integers(2, 8, 2))
        ground = bool(rng.integers(2))
        scene = render.paper_scene(size, size, nu=patches[0], nv=patches[1], ground=ground)
        scene.camera.position.data[:] += rng.normal(size=3)
        scene.lights[0].position.data[:] += rng.normal(size=3)
        out.append({"size": size, "patches": list(patches), "ground": ground, **counts(scene)})
    return out


def times(size: int, repeats: int) -> dict:
    """(module docstring, 3.) Medians of each workload, with and without the crease test."""
    scene = render.paper_scene(size, size)
    light = scene.lights[0].position
    light.requires_grad = True
    weights = np.random.default_rng(3).uniform(0.0, 1.0, (size, size, 3))
    visibility = trace_visibility(scene, RenderCache(), True, 1, True)
    with_test = interior.past_creases

    def without_test(pixels, *args):
        return pixels

    def gradient(antialias) -> None:
        light.grad = None
        image = render.render(scene, antialias=antialias, reuse_visibility=False)
        md.sum(image * weights).backward()

    def switched(test, fn):
        def run():
            interior.past_creases = test
            try:
                fn()
            finally:
                interior.past_creases = with_test

        return run

    search = lambda: interior.mixed_pixels(scene, visibility, 1)  # noqa: E731
    fns = {
        "plain": lambda: gradient(False),
        "boundary": switched(with_test, lambda: gradient("boundary")),
        "boundary_without_test": switched(without_test, lambda: gradient("boundary")),
        "search": switched(with_test, search),
        "search_without_test": switched(without_test, search),
    }
    stats = timing.measure_interleaved(fns, repeats=repeats, warmup=2)
    out = {name: stats[name]["median_ms"] for name in fns}
    out["boundary_over_plain"] = out["boundary"] / out["plain"]
    out["boundary_without_test_over_plain"] = out["boundary_without_test"] / out["plain"]
    return out


def main(argv=None) -> None:
    parser = timing.make_parser(__doc__, Path("out/mixed_pixels"), quick="64x64, 4 views")
    parser.add_argument("--views", type=int, default=80, help="random views (default 80)")
    args = parser.parse_args(argv)
    size = 64 if args.quick else 512
    paper = {("ground" if ground else "plain"): counts(render.paper_scene(size, size,
                                                                          ground=ground))
             for ground in (False, True)}  # fmt: skip
    views = random_views(4 if args.quick else args.views)
    total = {key: int(sum(v[key] for v in views)) for key in views[0] if key not in
             ("size", "patches", "ground")}  # fmt: skip
    result = {"size": size, "paper": paper, "views": views, "views_total": total,
              "time": times(size, timing.QUICK_REPEATS if args.quick else 15)}  # fmt: skip
    result["report"] = report(result)
    timing.print_report(result["report"], timing.machine())
    timing.write_json(args.out, "mixed_pixels", result)


def report(result: dict) -> dict:
    """The report section (``timing.report_section``) of ``main``'s result."""
    paper, total, t = result["paper"]["plain"], result["views_total"], result["time"]
    rows = [
        timing.row("paper scene: candidates kept / found", f"{paper['kept']} / "
                   f"{paper['candidates']}"),
        timing.row("paper scene: mixed pixels left out / mixed", f"{paper['lost']} / "
                   f"{paper['mixed_candidates']}"),
        timing.row("random views: candidates kept / found", f"{total['kept']} / "
                   f"{total['candidates']}"),
        timing.row("random views: mixed pixels left out / mixed", f"{total['lost']} / "
                   f"{total['mixed_candidates']}"),
        timing.row("the search alone, ms: with the test / without",
                   f"{t['search']:.1f} / {t['search_without_test']:.1f}"),
        timing.target_row("boundary term f+b / plain f+b (without the test: "
                          f"{t['boundary_without_test_over_plain']:.2f}x)",
                          f"{t['boundary_over_plain']:.2f}x", t["boundary_over_plain"], 3.0,
                          "at most 3x"),
    ]  # fmt: skip
    title = f"The mixed-pixel search, {result['size']}x{result['size']}"
    return timing.report_section(title, rows, [], [])


if __name__ == "__main__":
    main()
