"""Edge gradients (``render(..., antialias=True)``) on the paper's camera calibration.

Run:  python examples/edge_gradients.py [--out out] [--size 512] [--iters 500] [--seed 42]
      [--quick]

Four measurements, each written to ``<out>/edge_gradients.json`` and summarised in
``<out>/edge_gradients.md``:

1. calibration: camera calibration from the 10-degree start at --size (512 by default),
   seeds 42..51 (--seed is the first), with antialiasing: the final position error (Eq. 4) per seed;
2. basin: the success rate (final position error < 0.5 %) against the initial view error
   0, 5, ..., 25 degrees, 10 seeds each at 128x128, with and without edge gradients
   (``basin.png``);
3. coverage: at the paper's 30-degree start, the fraction of the target's teapot pixels
   that the initial render shows, per seed: where it is 0 no image loss has a gradient;
4. figure: the teapot's silhouette, zoomed, at pixel centres, antialiased and with 256
   samples per pixel (``silhouette_zoom.png``).

``--quick`` runs a few seeds at small sizes (for tests; its numbers are not results).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from PIL import Image
from script_support import command_line, write_results

import minidiff as md
from render.inverse.experiments import TRUE_CAMERA, camera_calibration_problem
from render.inverse.optimize import optimize
from render.inverse.plot import line_plot
from render.renderer import render
from render.scene.image import linear_to_srgb
from render.scene.teapot import paper_scene

SUCCESS = 0.5  # per cent position error that counts as converged in the basin
QUICK = {"--quick": {"action": "store_true", "help": "a few small runs (not results)"}}


def calibrate(size: int, seed: int, angle: float, antialias: bool, iters: int) -> dict:
    """One camera calibration run: the final position error in per cent (Eq. 4)."""
    scene, params, target = camera_calibration_problem(size, seed, angle)
    start = time.perf_counter()
    _, history = optimize(
        scene, params, target, lr=0.03, max_iters=iters, tol=1e-6, quiet=True,
        render_kwargs={"antialias": antialias},
    )  # fmt: skip
    error = np.linalg.norm(params[0].data - TRUE_CAMERA) / np.linalg.norm(TRUE_CAMERA)
    return {
        "seed": seed,
        "angle": angle,
        "antialias": antialias,
        "error_percent": float(100.0 * error),
        "iterations": history.iterations,
        "seconds": time.perf_counter() - start,
    }


def coverage_at_start(size: int, seed: int, angle: float) -> float:
    """The fraction of the target's teapot pixels that the initial render shows."""
    scene, _, _ = camera_calibration_problem(size, seed, angle)
    with md.no_grad():
        _, initial = render(scene, return_info=True)
        _, target = render(paper_scene(width=size, height=size), return_info=True)
    return float((initial.prim_id >= 0).sum() / max(1, (target.prim_id >= 0).sum()))


def silhouette_figure(path: Path, size: int = 128, crop: tuple[slice, slice] | None = None):
    """Pixel centres | antialiased | 256 spp, of a crop of the teapot's outline."""
    scene = paper_scene(width=size, height=size)
    with md.no_grad():
        images = [
            render(scene).data,
            render(scene, antialias=True).data,
            render(scene, spp=256).data,
        ]
    rows, cols = crop or (slice(size * 5 // 16, size * 9 // 16), slice(size // 2, size * 7 // 8))
    tiles = [linear_to_srgb(np.clip(im[rows, cols], 0, 1)) for im in images]
    gap = np.ones((tiles[0].shape[0], 2, 3))
    strip = np.concatenate([tiles[0], gap, tiles[1], gap, tiles[2]], axis=1)
    picture = Image.fromarray((strip * 255).round().astype(np.uint8))
    scale = max(1, 900 // picture.width)
    picture.resize((picture.width * scale, picture.height * scale), Image.NEAREST).save(path)


def main(argv=None) -> dict:
    args = command_line(
        __doc__.splitlines()[0], default_iters=500, argv=argv, extra=QUICK
    )  # --seed: the first of the ten seeds
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    seeds = [args.seed, args.seed + 1] if args.quick else list(range(args.seed, args.seed + 10))
    size = 48 if args.quick else args.size
    basin_size = 48 if args.quick else 128
    iters = 20 if args.quick else args.iters
    angles = [0.0, 10.0] if args.quick else [0.0, 5.0, 10.0, 15.0, 20.0, 25.0]
    result: dict = {"quick": args.quick, "size": size, "basin_size": basin_size}

    result["calibration"] = [calibrate(size, s, 10.0, True, iters) for s in seeds]
    for run in result["calibration"]:
        if not args.quiet:
            print(f"calibration seed {run['seed']}: {run['error_percent']:.3f} %", flush=True)

    basin = {}
    for antialias in (False, True):
        rates = []
        for angle in angles:
            runs = [calibrate(basin_size, s, angle, antialias, iters) for s in seeds]
            rates.append(float(np.mean([r["error_percent"] < SUCCESS for r in runs])))
            if not args.quiet:
                print(f"basin antialias={antialias} {angle:g} deg: {rates[-1]:.0%}", flush=True)
        basin["edges" if antialias else "pixel centres"] = (angles, rates)
    result["basin"] = {k: {"angles": a, "success_rate": r} for k, (a, r) in basin.items()}
    line_plot(
        basin, out / "basin.png", title=f"Camera calibration at {basin_size}x{basin_size}",
        xlabel="initial view error (degrees)", ylabel=f"runs below {SUCCESS} % error",
    )  # fmt: skip

    result["coverage_30deg"] = [
        {"seed": s, "fraction": coverage_at_start(basin_size, s, 30.0)} for s in seeds
    ]
    silhouette_figure(out / "silhouette_zoom.png")
    return write_results(out, "edge_gradients", result, report(result))


def report(result: dict) -> str:
    """The results as Markdown tables."""
    lines = [f"Camera calibration, 10-degree start, {result['size']}x{result['size']}, "
             "antialias=True:", "", "| seed | final position error | iterations |",
             "|---|---|---|"]  # fmt: skip
    for run in result["calibration"]:
        lines.append(f"| {run['seed']} | {run['error_percent']:.3f} % | {run['iterations']} |")
    below = sum(r["error_percent"] < 0.2 for r in result["calibration"])
    lines += ["", f"{below} of {len(result['calibration'])} runs below 0.20 %.", ""]
    lines += [f"Convergence basin at {result['basin_size']}x{result['basin_size']} "
              f"(share of runs below {SUCCESS} %):", ""]  # fmt: skip
    angles = next(iter(result["basin"].values()))["angles"]
    lines += ["| | " + " | ".join(f"{a:g} deg" for a in angles) + " |",
              "|---" * (len(angles) + 1) + "|"]  # fmt: skip
    for name, b in result["basin"].items():
        lines.append(f"| {name} | " + " | ".join(f"{r:.0%}" for r in b["success_rate"]) + " |")
    lines += ["", "30-degree start: share of the target's teapot pixels in the initial view:", ""]
    lines.append(
        ", ".join(f"seed {c['seed']}: {c['fraction']:.0%}" for c in result["coverage_30deg"])
    )
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
