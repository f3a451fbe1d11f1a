"""A network that reads the light's position off an image, trained through the renderer.

Run:  python examples/light_network.py [--out out] [--size 32] [--iters 1500] [--lr 0.003]
      [--quick]

A PyTorch MLP maps an image of the paper scene to the position of its light. It never
sees a position label: each step draws 8 random light positions, renders them (the
targets), predicts a position from each target, renders the predictions through
``render.torch`` and minimises the image difference (``torch_networks.py``). Reported
on 50 held-out targets: the distance from the predicted to the true position, and after 30
Adam steps of inverse rendering started from the prediction, or from the centre of the
light's box instead. Writes ``<out>/light_network/``: ``light_network.json`` and ``.md``,
``loss.png`` and ``light_network.png`` (rows: held-out targets; the renders with the light
at the box centre, and 4 |render - target|; at the network's prediction, and 4 |render -
target|).

``--quick`` trains for 10 steps at 16x16 and tests on 6 targets (for tests; its numbers
are not results).
"""

from __future__ import annotations

import numpy as np
from script_support import command_line, write_results
from torch_networks import LIGHT_BOX, train_light_network

import minidiff as md
from render.inverse.plot import line_plot
from render.renderer import render
from render.scene.image import save_image
from render.scene.teapot import paper_scene

EXTRA = {
    "--lr": {"type": float, "default": 3e-3, "help": "Adam's step size for the network"},
    "--quick": {"action": "store_true", "help": "a short small run (not results)"},
}


def _stats(errors: np.ndarray) -> dict:
    return {"median": float(np.median(errors)), "mean": float(np.mean(errors)),
            "max": float(np.max(errors))}  # fmt: skip


def main(argv=None) -> dict:
    args = command_line(__doc__.splitlines()[0], 1500, argv, EXTRA, default_size=32)
    size, iters = (16, 10) if args.quick else (args.size, args.iters)
    small = {"held_out": 6, "refine": 3} if args.quick else {}
    run = train_light_network(size=size, iters=iters, lr=args.lr, seed=args.seed, **small)
    centre = (LIGHT_BOX[0] + LIGHT_BOX[1]) / 2
    result = {
        "size": size, "iterations": iters, "lr": args.lr, "parameters": run["parameters"],
        "training_renders": run["renders"], "training_seconds": run["seconds"],
        "held_out": len(run["true"]),
        "error_predicting_the_box_centre": _stats(run["centre_error"]),
        "error_network": _stats(run["held_out_error"]),
        "error_refined_from_network": _stats(run["refined_error"]),
        "error_refined_from_centre": _stats(run["refined_from_centre_error"]),
        "refine_renders": run["refine_renders"], "refine_seconds": run["refine_seconds"],
        "light_distance_from_teapot_median": float(np.median(np.linalg.norm(run["true"], axis=1))),
        "loss": run["loss"],
    }  # fmt: skip
    out = args.out / "light_network"
    out.mkdir(parents=True, exist_ok=True)
    shown = range(min(4, len(run["true"])))

    def images(positions) -> np.ndarray:  # the teapot's rows of a 128x128 render
        with md.no_grad():
            row = [render(paper_scene(128, 128, light_position=p)).data[32:96] for p in positions]
        return np.concatenate(row, axis=1)

    target = images([run["true"][k] for k in shown])
    at_centre = images([centre for _ in shown])
    predicted = images([run["predicted"][k] for k in shown])
    grid = np.concatenate([target, at_centre, 4.0 * np.abs(at_centre - target), predicted,
                           4.0 * np.abs(predicted - target)], axis=0)  # fmt: skip
    save_image(np.clip(grid, 0.0, 1.0), out / "light_network.png")
    line_plot({"image MSE": (np.arange(len(run["loss"])), run["loss"])}, out / "loss.png",
              title="light network: training loss (batch of 8)", xlabel="step",
              ylabel="MSE", logy=True)  # fmt: skip
    rows = [
        ("the box centre (no network)", "error_predicting_the_box_centre"),
        ("the network's prediction", "error_network"),
        (f"{run['refine_steps']} Adam steps from the centre", "error_refined_from_centre"),
        (f"{run['refine_steps']} Adam steps from the prediction", "error_refined_from_network"),
    ]
    table = "\n".join(
        f"| {label} | {result[key]['median']:.3f} | {result[key]['mean']:.3f} | "
        f"{result[key]['max']:.3f} |"
        for label, key in rows
    )
    report = (
        f"# A network that predicts the light, trained through the renderer\n\n"
        f"{size}x{size} images of the paper scene, light uniform in the box "
        f"{LIGHT_BOX[0].tolist()}..{LIGHT_BOX[1].tolist()}; MLP with {run['parameters']} "
        f"parameters; {iters} steps of 8 (image loss only, no position labels): "
        f"{run['renders']} renders, {run['seconds']:.0f} s.\n\n"
        f"Distance to the true light position on {len(run['true'])} held-out targets "
        f"(scene units; the light is ~{result['light_distance_from_teapot_median']:.1f} "
        f"from the teapot):\n\n| estimate | median | mean | max |\n|---|---|---|---|\n"
        f"{table}\n"
    )
    return write_results(out, "light_network", result, report)


if __name__ == "__main__":
    main()
