"""6-DoF pose estimation: the teapot's rotation and translation from one image.

Run:  python examples/pose_estimation.py [--out out] [--size 128] [--iters 250]
      [--seeds 10] [--seed 42] [--angles 15,30,45,90,180] [--methods alone,starts,search]
      [--search 300] [--antialias boundary] [--quick] [--jobs N]

For each start angle and seed (42, 43, ...): the teapot turned by that angle about a random
axis and shifted by 10 % of its size (``render.inverse.reconstruction.pose_problem``), then
recovered by each method of ``--methods``: ``alone`` (gradients alone), ``starts`` (the
default of ``run_pose``: a multi-start stage, the start and six copies turned 30 degrees,
40 cheap iterations each at 64 px, then the gradients from the lowest loss) and ``search``
(a greedy search stage of ``--search`` renders at half the size and a race, then the
gradients). Writes ``<out>/pose/pose.json`` (every run), ``pose.md`` (success per start
angle: rotation error < 1 degree and translation error < 1 % of the size; median errors;
times, the stages' renders included) and ``basin.png``.

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
    "--methods": {"default": "alone,starts,search", "help": "alone, starts and/or search"},
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
    known = {
        "alone": ("gradients alone", {"starts": 0}),
        "starts": ("multi-start (default)", {}),
        "search": (f"search ({args.search} renders)", {"search": args.search}),
    }
    chosen = [m.strip() for m in args.methods.split(",") if m.strip()]
    if not chosen or any(m not in known for m in chosen):
        raise SystemExit(f"--methods: a list of {', '.join(known)}; got {args.methods!r}")
    methods = [known[m] for m in chosen]
    calls = [partial(run_pose, size, angle, seed, iters, antialias=antialias,
                     quiet=args.quiet or jobs > 1, **options)
             for angle in angles for seed in seeds for _, options in methods]  # fmt: skip
    labels = [label for _ in angles for _ in seeds for label, _ in methods]

    def report(i: int, r: dict) -> None:
        print(f"angle {r['angle']:5.0f} seed {r['seed']} {labels[i]}: "
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
    for r, label in zip(runs, labels, strict=True):
        r["method"] = label
    rows, basin = [], {label: ([], []) for label, _ in methods}
    for angle in angles:
        for label in basin:
            group = [r for r in runs if r["angle"] == angle and r["method"] == label]
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
    result = {"size": size, "iters": iters, "search": args.search, "methods": chosen, "runs": runs}
    return write_results(out, "pose", result, report)


if __name__ == "__main__":
    main()
