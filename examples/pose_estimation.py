"""6-DoF pose estimation: the teapot's rotation and translation from one image.

Run:  python examples/pose_estimation.py [--out out] [--size 128] [--iters 250]
      [--seeds 10] [--angles 15,30,45,90,180] [--search 300] [--antialias boundary]
      [--quick] [--jobs N]

For each start angle and seed (42, 43, ...): the teapot turned by that angle about a random
axis and shifted by 10 % of its size (``render.inverse.reconstruction.pose_problem``), then
recovered by gradients alone, and by a greedy search stage (``--search`` renders at a
quarter of the size) followed by the same gradients. Writes ``<out>/pose/pose.json`` (every
run), ``pose.md`` (success per start angle: rotation error < 1 degree and translation error
< 1 % of the size; median errors; times, the search's renders included) and ``basin.png``.

``--quick`` runs two angles and two seeds at 48x48 (for tests; its numbers are not results).
``--jobs N`` runs the runs in N processes (default: one per core), with the same results.
"""

from __future__ import annotations

from functools import partial

import numpy as np
from script_support import JOBS, command_line, write_results

from render.inverse.parallel import check_jobs, process_pool, run_ordered
from render.inverse.plot import line_plot
from render.inverse.reconstruction import run_pose

EXTRA = {
    "--seeds": {"type": int, "default": 10, "help": "seeds per start angle"},
    "--angles": {"default": "15,30,45,90,180", "help": "start rotation angles (degrees)"},
    "--search": {"type": int, "default": 300, "help": "renders of the search stage"},
    "--antialias": {"default": "boundary", "help": "edge method: boundary, pairs or none"},
    "--quick": {"action": "store_true", "help": "a few small runs (not results)"},
    "--jobs": JOBS,
}


def main(argv=None) -> dict:
    args = command_line(__doc__.splitlines()[0], 250, argv, EXTRA, default_size=128)
    angles = [float(a) for a in args.angles.split(",")]
    seeds = list(range(args.seed, args.seed + args.seeds))
    size, iters = args.size, args.iters
    if args.quick:
        angles, seeds, size, iters = [15.0, 90.0], seeds[:2], 48, 30
    antialias = {"none": False, "pairs": True}.get(args.antialias, args.antialias)
    jobs = check_jobs(args.jobs, "--jobs")
    calls = [partial(run_pose, size, angle, seed, iters, search, antialias,
                     quiet=args.quiet or jobs > 1)
             for angle in angles for seed in seeds for search in (0, args.search)]  # fmt: skip

    def report(i: int, r: dict) -> None:
        print(f"angle {r['angle']:5.0f} seed {r['seed']} search {r['search_renders']:4d}: "
              f"rotation {r['rotation_error_degrees']:8.3f} deg, translation "
              f"{r['translation_error_percent']:7.3f} %, {r['seconds']:.1f} s")  # fmt: skip

    pool = process_pool(jobs) if jobs > 1 else None
    try:
        runs = run_ordered(calls, pool, on_result=report)
    finally:
        if pool is not None:
            pool.shutdown()
    out = args.out / "pose"
    out.mkdir(parents=True, exist_ok=True)
    rows, basin = [], {"gradients alone": ([], []), f"search ({args.search} renders)": ([], [])}
    for angle in angles:
        for label, search in zip(basin, (0, args.search), strict=True):
            group = [r for r in runs if r["angle"] == angle and r["search_renders"] == (
                0 if search == 0 else search + 1)]  # fmt: skip
            share = 100.0 * np.mean([r["success"] for r in group])
            basin[label][0].append(angle)
            basin[label][1].append(share)
            rows.append(
                f"| {angle:.0f} | {label} | {sum(r['success'] for r in group)} of {len(group)} "
                f"| {np.median([r['rotation_error_degrees'] for r in group]):.3f} "
                f"| {np.median([r['translation_error_percent'] for r in group]):.3f} "
                f"| {np.median([r['seconds'] for r in group]):.1f} "
                f"| {np.median([r['seconds_per_iteration'] for r in group]) * 1e3:.1f} |"
            )
    line_plot(basin, out / "basin.png", title=f"Teapot pose at {size}x{size}",
              xlabel="start rotation (degrees)", ylabel="runs succeeding (%)")  # fmt: skip
    report = "\n".join([
        f"# Pose estimation, {size}x{size}, {len(seeds)} seeds per angle, {iters} iterations, "
        f"edges: {args.antialias}",
        "",
        "Success: rotation error < 1 degree and translation error < 1 % of the teapot's size.",
        "",
        "| start angle | method | success | median rotation error (deg) "
        "| median translation error (%) | median seconds per run | ms per iteration |",
        "|---|---|---|---|---|---|---|",
        *rows,
        "",
    ])  # fmt: skip
    result = {"size": size, "iters": iters, "search": args.search, "runs": runs}
    return write_results(out, "pose", result, report)


if __name__ == "__main__":
    main()
