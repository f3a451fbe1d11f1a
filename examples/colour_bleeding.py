"""Recover the albedo of a wall the camera does not see, from the light it bleeds.

Run:  python examples/colour_bleeding.py [--out out/colour_bleeding] [--size 128]
      [--iters 150] [--spp 1 4 16 64] [--quick]

The Cornell box seen without its red wall (``render.inverse.bleeding``): the wall's albedo
starts grey (0.4, 0.4, 0.4) and is fitted, by Adam on the image MSE against a 1,024-spp
render of the true room, with the path integrator's replay gradient (max_depth 4, new
samples every iteration, decorrelated gradient seeds), once per spp in ``--spp``. Writes
``results.json`` and ``results.md`` (the albedo error per spp after every 10 iterations),
``error.png`` (error against iterations, one line per spp) and ``images.png`` (target,
start, final, each rendered at 1,024 spp, the final one the highest-spp run's, and 10x
|target - start|; shown with 2x exposure and gamma 1/2.2, enlarged to at least 128 pixels).
``--quick``: 16x16, 20 iterations, spp 1 and 4 (a smoke run, not results). The default
``--out`` is scratch (``out/`` is git-ignored); the README's figures are regenerated with
``--out docs/path_tracing/bleeding``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from render.inverse.bleeding import recover_hidden_albedo
from render.inverse.jsonio import write_json
from render.inverse.plot import line_plot
from render.scene.cornell import RED
from render.scene.image import save_image


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--out",
        default="out/colour_bleeding",
        help="output folder (default out/colour_bleeding; the README's figures were made "
        "with --out docs/path_tracing/bleeding)",
    )
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--iters", type=int, default=150)
    parser.add_argument("--spp", type=int, nargs="+", default=[1, 4, 16, 64])
    parser.add_argument("--target-spp", type=int, default=1024)
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args(argv)
    if args.quick:
        args.size, args.iters, args.spp, args.target_spp = 16, 20, [1, 4], 64
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    result = {"size": args.size, "iterations": args.iters, "target_spp": args.target_spp,
              "truth": list(RED), "runs": {}}  # fmt: skip
    curves, last = {}, None
    for spp in args.spp:
        start = time.perf_counter()
        run = recover_hidden_albedo(args.size, spp, args.iters, target_spp=args.target_spp)
        # The mean of the last 10 iterates: what the noisy steps hover around.
        settled = run.albedo[-10:].mean(axis=0)
        result["runs"][str(spp)] = {
            "final_albedo": run.albedo[-1].tolist(),
            "settled_albedo": settled.tolist(),
            "settled_error": float(np.linalg.norm(settled - RED) / np.linalg.norm(RED)),
            "error_every_10": run.error[::10].tolist(),
            "final_error": float(run.error[-1]),
            "seconds": run.seconds,
            "seconds_per_iteration": run.seconds / args.iters,
            "total_seconds": time.perf_counter() - start,
        }
        curves[f"{spp} spp"] = (np.arange(len(run.error)), run.error)
        last = run
        print(f"{spp:4d} spp: error {run.error[0]:.3f} -> {run.error[-1]:.4f} "
              f"(last 10 averaged: {result['runs'][str(spp)]['settled_error']:.4f}), "
              f"{run.seconds / args.iters:.2f} s/iteration", flush=True)  # fmt: skip
    line_plot(curves, out / "error.png", "Hidden wall's albedo: relative error",
              "iteration", "|albedo - true| / |true|", logy=True)  # fmt: skip
    images = [last.images[k] for k in ("target", "start", "final")]
    # What the wall's colour changes: 10x the difference the start's grey wall makes.
    images.append(10.0 * np.abs(last.images["target"] - last.images["start"]))
    strip = np.concatenate([display(im) for im in images], axis=1)
    zoom = max(1, -(-128 // args.size))  # small images enlarged to be seen
    save_image(np.repeat(np.repeat(strip, zoom, axis=0), zoom, axis=1), out / "images.png")
    write_json(out / "results.json", result)
    (out / "results.md").write_text(report(result))
    print(report(result))
    return result


def display(image: np.ndarray) -> np.ndarray:
    """Linear radiance made viewable: 2x exposure, clipped, gamma 1/2.2 (the saved PNG
    stores values as they are)."""
    return np.clip(2.0 * image, 0.0, 1.0) ** (1.0 / 2.2)


def report(result: dict) -> str:
    lines = [
        f"Cornell box {result['size']}x{result['size']}, red wall out of view, "
        f"{result['iterations']} iterations, target {result['target_spp']} spp; albedo error "
        "|albedo - true| / |true| (start 0.844):",
        "",
        "| spp per iteration | final | mean of the last 10 | albedo (last 10) | s/iteration |",
        "|---|---|---|---|---|",
    ]
    for spp, r in result["runs"].items():
        albedo = ", ".join(f"{a:.3f}" for a in r["settled_albedo"])
        lines.append(
            f"| {spp} | {r['final_error']:.4f} | {r['settled_error']:.4f} | ({albedo}) | "
            f"{r['seconds_per_iteration']:.2f} |"
        )
    lines.append(f"\nTrue albedo: ({', '.join(f'{a:.3f}' for a in result['truth'])}).")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
