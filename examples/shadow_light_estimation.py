"""Light estimation where the shadow is the main cue, with and without shadow-edge gradients.

Run:  python examples/shadow_light_estimation.py [--out out] [--size 256] [--iters 500]
      [--seed 42] [--quick]

1. "teapot on a ground plane": the paper's teapot standing on a grey ground, lit by the
   paper's light-estimation truth (light at (1, 4, 2), I = 150), recovered from one image
   from the paper's seeded random starts, seeds 42..51, with ``antialias=True`` (silhouette
   and shadow-edge gradients) and ``False`` (pixel centres: the shadow is a constant);
2. the paper's own light-estimation experiment (no ground), rerun with ``antialias=True``.
Reported per run: the final light position error (Eq. 5), the intensity error (Eq. 6) and
the iterations until the loss fell below the tolerance (None: never). Results go to
``<out>/shadow_light_estimation.json`` and ``.md``.

``--quick`` runs two seeds at 48x48 for 20 iterations (for tests; not results).
"""

from __future__ import annotations

import numpy as np
from script_support import command_line, write_results

from render.inverse.experiments import light_errors_pct, light_estimation_problem
from render.inverse.optimize import optimize
from render.scene.teapot import paper_scene

ERRORS = ("position_error_pct", "intensity_error_pct")
QUICK = {"--quick": {"action": "store_true", "help": "a few small runs (not results)"}}


def estimate(size, seed, ground: bool, antialias: bool, iters: int, tol: float) -> dict:
    """One light estimation run."""
    scene, (position, strength), target = light_estimation_problem(
        size, seed, lambda **light: paper_scene(size, size, ground=ground, **light),
        antialias=antialias,
    )  # fmt: skip
    _, history = optimize(
        scene, [position, strength], np.clip(target, 0, 1), lr=[0.3, 20.0], max_iters=iters,
        tol=tol, quiet=True, render_kwargs={"antialias": antialias},
    )  # fmt: skip
    below = [i for i, loss in enumerate(history.loss) if loss < tol]
    return {
        "seed": seed,
        "ground": ground,
        "antialias": antialias,
        **dict(zip(ERRORS, light_errors_pct(position, strength), strict=True)),
        "iterations_to_tol": below[0] if below else None,
        "final_loss": history.loss[-1],
    }


def report(result: dict) -> str:
    lines = []
    for title, key in (
        ("Teapot on a ground plane", "ground"),
        ("The paper's light estimation (no ground)", "paper"),
    ):
        runs = result[key]
        lines += [f"{title}, {result['size']}x{result['size']}, {result['iters']} iterations:",
                  "", "| antialias | seed | position error | intensity error | iterations to tol |",
                  "|---|---|---|---|---|"]  # fmt: skip
        for r in runs:
            lines.append(
                f"| {r['antialias']} | {r['seed']} | {r['position_error_pct']:.3g} % | "
                f"{r['intensity_error_pct']:.3g} % | {r['iterations_to_tol']} |"
            )
        for antialias in sorted({r["antialias"] for r in runs}):
            errors = [r["position_error_pct"] for r in runs if r["antialias"] == antialias]
            lines.append(
                f"\nantialias={antialias}: median position error {np.median(errors):.3g} %, "
                f"max {np.max(errors):.3g} %"
            )
        lines.append("")
    return "\n".join(lines) + "\n"


def main(argv=None) -> dict:
    args = command_line(
        __doc__.splitlines()[0], default_iters=500, argv=argv, extra=QUICK, default_size=256
    )  # --seed: the first of the ten seeds
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    seeds = [args.seed, args.seed + 1] if args.quick else list(range(args.seed, args.seed + 10))
    size, iters, tol = (48, 20, 1e-9) if args.quick else (args.size, args.iters, 1e-9)
    result = {"quick": args.quick, "size": size, "iters": iters, "ground": [], "paper": []}
    for antialias in (False, True):
        for seed in seeds:
            result["ground"].append(estimate(size, seed, True, antialias, iters, tol))
            if not args.quiet:
                print(result["ground"][-1], flush=True)
    for seed in seeds:
        result["paper"].append(estimate(size, seed, False, True, iters, tol))
        if not args.quiet:
            print(result["paper"][-1], flush=True)
    return write_results(out, "shadow_light_estimation", result, report(result))


if __name__ == "__main__":
    main()
