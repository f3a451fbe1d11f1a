"""A neural field for the teapot's albedo, trained through the renderer, in minidiff and in
PyTorch.

Run:  python examples/neural_field.py [--out out] [--size 64] [--iters 500] [--lr 0.005]
      [--quick]

An MLP on Fourier features of 3-D position (``render.inverse.networks``) gives the albedo at
every texel centre of the teapot's atlas; 8 views rendered with that texture are compared
with targets painted by a 3-D pattern. The same training runs twice from the same initial
weights: in minidiff (network, renderer and Adam on one tape) and in PyTorch (network and
Adam in PyTorch, the renderer through ``render.torch``). Writes ``<out>/neural_field/``:
``neural_field.json`` and ``.md`` (both loss curves and their largest relative
difference, held-out-view PSNR, parameter count, time per iteration), ``neural_field.png``
(held-out views: target, start, minidiff's result, PyTorch's result), ``loss.png`` and
``training.gif`` (a held-out view during training, beside its target).

``--quick`` trains for 5 iterations at 16x16 (for tests; its numbers are not results).
"""

from __future__ import annotations

import numpy as np
from PIL import Image
from script_support import command_line, write_results
from torch_networks import train_field_torch

from render.inverse.networks import (
    field_setup,
    field_texture,
    held_out_renders,
    init_mlp,
    train_field_minidiff,
)
from render.inverse.plot import line_plot
from render.scene.image import save_image

EXTRA = {
    "--lr": {"type": float, "default": 0.005, "help": "Adam's step size"},
    "--views": {"type": int, "default": 8, "help": "training views"},
    "--quick": {"action": "store_true", "help": "a short small run (not results)"},
}


def report(r: dict) -> str:
    """neural_field.md from the result ``r``: the setup, and minidiff against PyTorch (final
    loss, held-out PSNR, time per iteration)."""
    size = r["size"]
    return (
        f"# Neural field trained through the renderer\n\n"
        f"{r['views']} views at {size}x{size}, {r['iterations']} Adam iterations "
        f"(lr {r['lr']}); MLP {r['layers']} on Fourier features: {r['parameters']} parameters, "
        f"evaluated at {r['texels']} texel centres.\n\n"
        f"| | minidiff | PyTorch (render.torch) |\n|---|---|---|\n"
        f"| final loss | {r['loss_minidiff'][-1]:.4e} | {r['loss_torch'][-1]:.4e} |\n"
        f"| held-out PSNR ({r['held_out_views']} views; start "
        f"{r['held_out_psnr_start']:.1f} dB) | {r['held_out_psnr_minidiff']:.2f} dB | "
        f"{r['held_out_psnr_torch']:.2f} dB |\n"
        f"| time per iteration (median) | {1e3 * r['seconds_per_iteration_minidiff']:.0f}"
        f" ms | {1e3 * r['seconds_per_iteration_torch']:.0f} ms |\n\n"
        f"Largest relative difference between the two loss curves: "
        f"{r['loss_max_relative_difference']:.1e}.\n"
    )


def main(argv=None) -> dict:
    args = command_line(__doc__.splitlines()[0], 500, argv, EXTRA, default_size=64)
    size, iters = (16, 5) if args.quick else (args.size, args.iters)
    setup = field_setup(views=args.views, size=size)
    weights = init_mlp(setup.sizes, seed=args.seed)
    count = sum(w.size for w in weights)
    mine = train_field_minidiff(setup, weights, iters, args.lr, frames=40)
    theirs = train_field_torch(setup, weights, iters, args.lr)
    a, b = np.array(mine["loss"]), np.array(theirs["loss"])
    result = {
        "views": args.views, "size": size, "iterations": iters, "lr": args.lr,
        "parameters": count, "layers": setup.sizes, "texels": int(setup.features.shape[0]),
        "loss_minidiff": mine["loss"], "loss_torch": theirs["loss"],
        "loss_max_relative_difference": float(np.max(np.abs(a - b) / np.abs(a))),
        "held_out_views": len(setup.held_out),
        "held_out_psnr_start": mine["held_out_psnr_start"],
        "held_out_psnr_minidiff": mine["held_out_psnr"],
        "held_out_psnr_torch": theirs["held_out_psnr"],
        "seconds_per_iteration_minidiff": float(np.median(mine["seconds"])),
        "seconds_per_iteration_torch": float(np.median(theirs["seconds"])),
    }  # fmt: skip
    out = args.out / "neural_field"
    out.mkdir(parents=True, exist_ok=True)
    start = held_out_renders(setup, field_texture(setup, weights))
    rows = [setup.held_out_targets, start, held_out_renders(setup, mine["texture"])]
    rows.append(held_out_renders(setup, field_texture(setup, theirs["weights"])))
    grid = np.concatenate([np.concatenate(list(r), axis=1) for r in rows], axis=0)
    save_image(np.clip(grid, 0.0, 1.0), out / "neural_field.png")
    steps = np.arange(len(a))
    line_plot({"minidiff": (steps, a), "PyTorch": (steps, b)}, out / "loss.png",
              title="neural field: loss per iteration", xlabel="iteration", ylabel="MSE",
              logy=True)  # fmt: skip
    frames = [
        Image.fromarray((np.clip(np.concatenate([f, setup.held_out_targets[0]], 1), 0, 1)
                         * 255 + 0.5).astype(np.uint8))
        for f in mine["frames"]
    ]  # fmt: skip
    if frames:
        frames[0].save(out / "training.gif", save_all=True, append_images=frames[1:],
                       duration=100, loop=0)  # fmt: skip
    return write_results(out, "neural_field", result, report(result))


if __name__ == "__main__":
    main()
