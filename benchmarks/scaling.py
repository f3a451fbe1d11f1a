"""Scaling: how forward and forward+backward time, and the tape's memory, grow.

Run:  python benchmarks/scaling.py [--out DIR] [--quick]

Two series on the paper scene (``docs/paper_scene.md``), both with the BVH:

* pixels: 64^2, 128^2, 256^2, 512^2, 1024^2 with the 1,536-triangle teapot;
* triangles: the teapot tessellated 4x6, 8x13, 12x20, 18x40, 26x60 cells per patch
  (1,536 to 99,840 triangles) at 512^2.

Per point: the forward render of the plain scene (``render(scene, reuse_visibility=False)``,
no tape) and forward+backward of the paper's loss w.r.t. all parameters (light, albedo,
camera, all vertices; ``bench_render.forward_backward``), medians after a warm-up; and the
peak memory of one forward+backward (tracemalloc: the NumPy arrays alive at once, i.e. the
tape and its temporaries; and the process's peak RSS).

And one large mesh (not with --quick): the teapot tessellated 80 x 200 cells per patch,
1,024,000 triangles: BVH build time (target <= 1 s), a forward render at 512x512, and the
memory per triangle (the accelerator's arrays; the process's peak RSS growth).

Fitted: the exponent b of t = a n^b (least squares on log-log) over all points and over
the upper half (where fixed per-render costs matter less). b = 1 is linear scaling; for
triangles, a BVH should give b well below 1 for ray casting (logarithmic traversal), while
the build (n log n) and the per-vertex work of the backward pass grow about linearly.
"""

from __future__ import annotations

import resource

import timing
from bench_render import forward_backward, loss_problem

from render import render
from render.inverse.plot import line_plot
from render.scene.teapot import paper_scene, teapot
from render.trace.accel import Accelerator
from render.trace.primitives import scene_primitives

# The quantities fitted (and plotted) per point.
FITTED = {
    "forward": lambda p: p["forward"]["median_ms"],
    "forward_backward": lambda p: p["forward_backward"]["median_ms"],
    "tape_memory": lambda p: p["memory_forward_backward"]["tracemalloc_peak_mb"],
}


def main(argv=None) -> dict:
    return timing.main("scaling", __doc__, run, argv)


def run(args) -> dict:
    """Both series, the fitted exponents, the million-triangle mesh (not with --quick), the
    plots and the report."""
    if args.quick:
        sizes, tess, size_tri, repeats = [16, 32, 64], [(2, 3), (4, 6), (8, 13)], 64, 2
    else:
        sizes = [64, 128, 256, 512, 1024]
        tess = [(4, 6), (8, 13), (12, 20), (18, 40), (26, 60)]
        size_tri, repeats = 512, 7
    # Fewer runs at 1024^2, where one forward+backward takes seconds.
    pixels = [point(size, 4, 6, repeats if size < 1024 else max(2, repeats - 2)) for size in sizes]
    triangles = [point(size_tri, nu, nv, repeats) for nu, nv in tess]
    result = {
        "pixels": pixels,
        "triangles": triangles,
        "triangle_series_size": size_tri,
        "repeats": repeats,
        "exponents_pixels": exponents(pixels, "pixels"),
        "exponents_triangles": exponents(triangles, "triangles"),
        "million": None if args.quick else million(),
    }
    result["report"] = report(result, plots(result, args.out))
    return result


def point(size: int, nu: int, nv: int, repeats: int) -> dict:
    """One point of a series: the teapot tessellated nu x nv at ``size``^2."""
    plain = paper_scene(size, size, nu=nu, nv=nv)
    scene, params, target = loss_problem(size, nu, nv)
    p = {
        "size": size,
        "pixels": size * size,
        "triangles": plain.meshes[0].num_faces,
        "vertices": plain.meshes[0].num_vertices,
        "forward": timing.measure(lambda: render(plain, reuse_visibility=False), repeats),
        "forward_backward": timing.measure(
            lambda: forward_backward(scene, params, target), repeats
        ),
        "memory_forward_backward": timing.measure_memory(
            lambda: forward_backward(scene, params, target)
        ),
    }
    print(
        f"{size:5d}^2 {p['triangles']:7,d} tri  forward {timing.ms(p['forward'])}  "
        f"f+b {timing.ms(p['forward_backward'])}",
        flush=True,
    )
    return p


def exponents(points: list[dict], key: str) -> dict:
    """Fitted exponents of forward, forward+backward and tape memory vs ``key``."""
    x = [p[key] for p in points]
    upper = points[len(points) // 2 :]
    xu = [p[key] for p in upper]
    out = {}
    for name, get in FITTED.items():
        out[name] = timing.fit_power_law(x, [get(p) for p in points])
        out[name + "_upper"] = timing.fit_power_law(xu, [get(p) for p in upper])
    return out


def million(repeats: int = 3) -> dict:
    """The 1,024,000-triangle teapot: BVH build, forward render, memory per triangle."""
    rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    scene = paper_scene(512, 512)
    scene.objects[0] = teapot(80, 200)
    primitives = scene_primitives(scene)
    n = scene.meshes[0].num_faces
    build = timing.measure(lambda: Accelerator(*primitives), repeats, warmup=1)
    accel = Accelerator(*primitives)
    arrays = (accel.leaf_prim, accel.node_bounds, accel.node_first)
    arrays += (accel.node_count, accel.leaf_ids)
    accel_bytes = sum(a.nbytes for a in arrays)
    forward = timing.measure(lambda: render(scene, reuse_visibility=False), repeats, warmup=1)
    rss_after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return {
        "triangles": n,
        "build": build,
        "forward": forward,
        "accelerator_bytes_per_triangle": accel_bytes / n,
        "peak_rss_growth_bytes_per_triangle": (rss_after - rss_before) * 2**20 / n,
    }


def plots(r: dict, out) -> list:
    """Times (and the tape's memory) against pixels and against triangles, log-log."""
    times = {"forward": FITTED["forward"], "forward+backward": FITTED["forward_backward"]}
    tape = {"tape peak MB (tracemalloc)": FITTED["tape_memory"]}
    log = {"logx": True, "logy": True}
    return [
        line_plot(
            timing.series(r["pixels"], "pixels", times | tape),
            out / "scaling_pixels.png",
            title="Scaling with pixels (1,536 triangles): ms, and MB for the tape",
            xlabel="pixels",
            ylabel="ms / MB",
            **log,
        ),
        line_plot(
            timing.series(r["triangles"], "triangles", times),
            out / "scaling_triangles.png",
            title=f"Scaling with triangles at {r['triangle_series_size']}^2 (BVH)",
            xlabel="triangles",
            ylabel="ms",
            **log,
        ),
    ]


def report(r: dict, plots: list) -> dict:
    """Rows: the fitted exponents, every point, the million-triangle mesh."""
    rows = []
    for label in ("pixels", "triangles"):
        fit = r[f"exponents_{label}"]
        for name in FITTED:
            rows.append(
                timing.row(
                    f"exponent of {name.replace('_', ' ')} vs {label} (all / upper half)",
                    f"{fit[name]:.2f} / {fit[name + '_upper']:.2f}",
                )
            )
    for p in r["pixels"] + r["triangles"]:
        rows.append(
            timing.row(
                f"{p['size']}^2, {p['triangles']:,} tri: forward / f+b / tape peak / "
                "page faults per f+b",
                f"{p['forward']['median_ms']:.1f} / {p['forward_backward']['median_ms']:.1f} ms / "
                f"{p['memory_forward_backward']['tracemalloc_peak_mb']:.0f} MB / "
                f"{p['forward_backward']['page_faults_per_pass']:.0f}",
            )
        )
    if r["million"] is not None:
        rows += million_rows(r["million"])
    notes = [
        f"Medians of {r['repeats']} runs after a warm-up. Exponent b of t ~ n^b by least "
        "squares on log-log; 'upper half' fits the larger half of the points only.",
        "Tape peak = tracemalloc peak of one forward+backward (NumPy arrays alive at once). "
        "Page faults: minor faults per forward+backward (fresh 4 KiB pages): with glibc's "
        "default allocator, arrays above its mmap threshold (128 KiB at first, adapted as the "
        "process runs) are mapped and unmapped on every pass.",
    ]
    return timing.report_section("Scaling (scaling.py)", rows, notes, [p.name for p in plots])


def million_rows(m: dict) -> list:
    """Report rows of ``million()``."""
    return [
        timing.target_row(
            f"BVH build, {m['triangles']:,} triangles",
            timing.ms(m["build"]),
            m["build"]["median_ms"],
            1000.0,
            "target <= 1 s",
        ),
        timing.row(
            f"forward render at 512x512, {m['triangles']:,} triangles", timing.ms(m["forward"])
        ),
        timing.row(
            "memory per triangle: accelerator arrays / peak RSS growth of the process",
            f"{m['accelerator_bytes_per_triangle']:.0f} / "
            f"{m['peak_rss_growth_bytes_per_triangle']:.0f} bytes",
        ),
    ]


if __name__ == "__main__":
    main()
