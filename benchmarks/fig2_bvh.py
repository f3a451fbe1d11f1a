"""Figure 2: forward render time and peak memory with and without the BVH.

Run:  python benchmarks/fig2_bvh.py [--out DIR] [--quick]

Two series on the paper scene (``docs/paper_scene.md``):

1. Resolution: the 1,536-triangle teapot at 64^2, 128^2, 256^2, 512^2 and 1024^2 pixels.
   Each point is a full forward render, ``render(scene, bvh=..., reuse_visibility=False)``
   (BVH build, camera rays, shadow rays, shading; no parameter requires a gradient), the
   median of several renders after a warm-up, and the peak memory of one more render:
   the process's peak resident memory (what the paper's "total resident memory" counts;
   interpreter and libraries included) and tracemalloc's peak of NumPy allocations.
2. Triangle count at 512^2: the teapot tessellated with nu x nv cells per patch, 4x6
   (1,536), 8x13 (6,656), 12x20 (15,360), 18x40 (46,080), 26x60 (99,840 triangles).
   The BVH render is measured directly. Brute force tests every ray against every
   triangle, so its cost is linear in rays x triangles: rendering 99,840 triangles that way
   would take minutes, so its visibility (camera rays and shadow rays) is timed on every
   k-th ray and scaled to all rays, and the brute-force render time is estimated as
   BVH render - BVH visibility + brute-force visibility (the shading is the same).
   At 1,536 triangles the estimate is checked against the measured brute-force render.

The paper (Intel Xeon E5-1650 v4, 6 cores, Julia): 52.3 ms with BVH vs 85.6 ms without at
512^2, 124.5 vs 207.3 MB; the speedup grows to 58.7% at 10,000 triangles.
"""

from __future__ import annotations

import timing
from bench_visibility import time_brute_visibility, time_bvh_visibility, visibility_workload

from render import render
from render.inverse.plot import line_plot
from render.scene.teapot import paper_scene

PAPER_512 = {"bvh_ms": 52.3, "no_bvh_ms": 85.6, "bvh_mb": 124.5, "no_bvh_mb": 207.3}


def main(argv=None) -> dict:
    return timing.main("fig2_bvh", __doc__, run, argv)


def run(args) -> dict:
    """Both series, the check of the brute-force estimate, the plots and the report."""
    if args.quick:
        sizes, tessellations, size_tri, repeats = [32, 64], [(4, 6), (8, 13)], 64, 2
    else:
        sizes = [64, 128, 256, 512, 1024]
        tessellations = [(4, 6), (8, 13), (12, 20), (18, 40), (26, 60)]
        size_tri, repeats = 512, 7
    resolution = [resolution_point(size, repeats) for size in sizes]
    triangles = [triangle_point(size_tri, nu, nv, repeats) for nu, nv in tessellations]
    # Check of the estimate: brute force measured directly for the first tessellation, right
    # after its estimate (the machine's load changes over minutes, so not from series 1).
    direct = render_point(size_tri, False, 2 if args.quick else 3, *tessellations[0])
    result = {
        "resolution": resolution,
        "triangles": triangles,
        "triangle_series_size": size_tri,
        "estimate_check": {
            "triangles": triangles[0]["triangles"],
            "measured_ms": direct["time"]["median_ms"],
            "estimated_ms": triangles[0]["brute_render_estimate_ms"],
        },
        "paper_512": PAPER_512,
    }
    result["report"] = report(result, plots(result, args.out))
    return result


def resolution_point(size: int, repeats: int) -> dict:
    """Series 1: a render of the 1,536-triangle teapot at ``size``^2, with and without BVH."""
    brute_repeats = repeats if size <= 256 else 3
    point = {
        "size": size,
        "pixels": size * size,
        "bvh": render_point(size, True, repeats),
        "no_bvh": render_point(size, False, brute_repeats),
    }
    print(
        f"{size:5d}^2  BVH {timing.ms(point['bvh']['time'])}  "
        f"no BVH {timing.ms(point['no_bvh']['time'])}",
        flush=True,
    )
    return point


def triangle_point(size: int, nu: int, nv: int, repeats: int) -> dict:
    """Series 2: the BVH render of the teapot tessellated nu x nv, and the brute-force
    render estimated from brute-force visibility timed on a subsample of the rays."""
    w = visibility_workload(size, nu, nv)
    n_tri = len(w["triangles"])
    vis = time_bvh_visibility(w, repeats)
    stride = brute_stride(n_tri, len(w["directions"]))
    brute = time_brute_visibility(w, 3 if stride > 1 else 2, stride=stride, warmup=0)
    bvh_render = render_point(size, True, repeats, nu, nv)
    bvh_vis_ms = vis["closest_hit"]["median_ms"] + vis["occluded"]["median_ms"]
    brute_vis_ms = brute["closest_hit_ms"] + brute["occluded_ms"]
    estimate = bvh_render["time"]["median_ms"] - bvh_vis_ms + brute_vis_ms
    print(
        f"{n_tri:7,d} triangles  BVH render {timing.ms(bvh_render['time'])}  brute force "
        f"(estimated, rays timed 1 in {stride}) {estimate:.0f} ms",
        flush=True,
    )
    return {
        "nu": nu,
        "nv": nv,
        "triangles": n_tri,
        "bvh_render": bvh_render,
        "bvh_visibility_ms": bvh_vis_ms,
        "bvh_build_ms": vis["build"]["median_ms"],
        "brute_visibility": brute,
        "brute_visibility_ms": brute_vis_ms,
        "brute_render_estimate_ms": estimate,
    }


def render_point(size: int, bvh: bool, repeats: int, nu: int = 4, nv: int = 6) -> dict:
    """Median forward render time and peak memory of one render."""
    scene = paper_scene(size, size, nu=nu, nv=nv)

    def fn():
        render(scene, bvh=bvh, reuse_visibility=False)

    # Brute force at large sizes takes seconds per render: its kernels are compiled by the
    # smaller sizes before, so no warm-up render is needed there.
    warmup = 1 if bvh or size <= 256 else 0
    return {"time": timing.measure(fn, repeats, warmup), "memory": timing.measure_memory(fn)}


def memory_text(m: dict) -> str:
    """'268 MB (+12; 18.0)': peak RSS, its growth during the render, NumPy peak."""
    return (
        f"{m['rss_peak_mb']:.0f} MB (+{m['rss_increase_mb']:.0f}; {m['tracemalloc_peak_mb']:.1f})"
    )


def paper_at_512(point: dict, unit: str) -> str:
    """The paper's BVH / no BVH figures in ``unit`` ("ms" or "mb") for a 512^2 point, else
    nothing."""
    if point["size"] != 512:
        return ""
    text = {"ms": "ms", "mb": "MB"}[unit]
    return f"paper {PAPER_512['bvh_' + unit]} / {PAPER_512['no_bvh_' + unit]} {text}"


def brute_stride(n_triangles: int, n_rays: int, budget_tests: float = 4e8) -> int:
    """Every how many rays to time brute force so that about ``budget_tests`` ray-triangle
    tests are made (about a second on this machine)."""
    return max(1, int(n_triangles * n_rays / budget_tests))


def plots(r: dict, out) -> list:
    """Fig. 2a (time) and 2b (memory) against pixels, and time against triangles."""
    resolution, triangles = r["resolution"], r["triangles"]
    memory = {}
    for key, what in (
        ("rss_peak_mb", "process peak RSS"),
        ("tracemalloc_peak_mb", "NumPy peak (tracemalloc)"),
    ):
        for variant, label in (("bvh", "BVH"), ("no_bvh", "no BVH")):
            memory[f"{label}, {what}"] = lambda p, v=variant, k=key: p[v]["memory"][k]
    log = {"logx": True, "logy": True}
    return [
        line_plot(
            timing.series(
                resolution,
                "pixels",
                {
                    "BVH": lambda p: p["bvh"]["time"]["median_ms"],
                    "no BVH": lambda p: p["no_bvh"]["time"]["median_ms"],
                },
            ),
            out / "fig2a_time.png",
            title="Fig. 2a: forward render time, teapot 1,536 triangles (median)",
            xlabel="pixels",
            ylabel="ms",
            **log,
        ),
        line_plot(
            timing.series(resolution, "pixels", memory),
            out / "fig2b_memory.png",
            title="Fig. 2b: peak memory of one forward render",
            xlabel="pixels",
            ylabel="MB",
            **log,
        ),
        line_plot(
            timing.series(
                triangles,
                "triangles",
                {
                    "BVH (measured)": lambda t: t["bvh_render"]["time"]["median_ms"],
                    "no BVH (estimated)": lambda t: t["brute_render_estimate_ms"],
                },
            ),
            out / "fig2c_triangles.png",
            title=f"Forward render time vs triangles at {r['triangle_series_size']}^2",
            xlabel="triangles",
            ylabel="ms",
            **log,
        ),
    ]


def report(r: dict, plots: list) -> dict:
    """Rows: render times and memory per resolution, BVH vs estimated brute force per
    triangle count; notes: how the numbers were taken and the estimate's check."""
    resolution, triangles, check = r["resolution"], r["triangles"], r["estimate_check"]
    size_tri = r["triangle_series_size"]
    rows = []
    for p in resolution:
        b, n = p["bvh"]["time"]["median_ms"], p["no_bvh"]["time"]["median_ms"]
        rows.append(
            timing.row(
                f"{p['size']}^2 render: BVH / no BVH",
                f"{b:.1f} / {n:.1f} ms ({n / b:.1f}x)",
                paper_at_512(p, "ms"),
            )
        )
    for p in resolution:
        rows.append(
            timing.row(
                f"{p['size']}^2 peak RSS (+ growth during the render; NumPy peak): BVH / no BVH",
                f"{memory_text(p['bvh']['memory'])} / {memory_text(p['no_bvh']['memory'])}",
                paper_at_512(p, "mb"),
            )
        )
    for t in triangles:
        ratio = t["brute_render_estimate_ms"] / t["bvh_render"]["time"]["median_ms"]
        rows.append(
            timing.row(
                f"{t['triangles']:,} triangles at {size_tri}^2: BVH / no BVH (est.)",
                f"{t['bvh_render']['time']['median_ms']:.1f} / "
                f"{t['brute_render_estimate_ms']:.0f} ms ({ratio:.0f}x)",
                "paper: BVH saves 58.7% at 10k" if t["triangles"] == 15360 else "",
            )
        )
    first = resolution[0]["bvh"]["memory"]
    baseline = first["rss_peak_mb"] - first["rss_increase_mb"]
    notes = [
        "Times: medians (brute force at >= 512^2: 3 renders). Memory: one more render; RSS is "
        f"the whole process (Python, NumPy, Numba: {baseline:.0f} MB resident before the first "
        "measured render), tracemalloc the NumPy arrays alive at once.",
        "Without BVH, brute force tests every ray against all triangles: the cost is "
        "rays x triangles, so the BVH's advantage grows with both (the paper's 1.6x at 512^2 "
        "means its BVH or its brute force differs a lot from ours).",
        "Triangle series: brute-force visibility timed on 1 ray in k and extrapolated "
        "linearly; brute render = BVH render - BVH visibility + brute visibility.",
        f"Check at {check['triangles']:,} triangles, {size_tri}^2: estimated brute render "
        f"{check['estimated_ms']:.0f} ms vs measured {check['measured_ms']:.0f} ms.",
    ]
    same = next((p for p in resolution if p["size"] == size_tri), None)
    if same is not None and (triangles[0]["nu"], triangles[0]["nv"]) == (4, 6):
        a, b = same["bvh"]["time"]["median_ms"], triangles[0]["bvh_render"]["time"]["median_ms"]
        notes.append(
            f"The same BVH render ({size_tri}^2, 1,536 triangles) measured {a:.1f} ms in series "
            f"1 and {b:.1f} ms in series 2, minutes later: the Numba kernels run on both cores, "
            "so other processes on this shared machine can slow them by up to 2x. Compare "
            "numbers within a series."
        )
    return timing.report_section(
        "Figure 2: BVH vs brute force (fig2_bvh.py)", rows, notes, [p.name for p in plots]
    )


if __name__ == "__main__":
    main()
