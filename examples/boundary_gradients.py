"""Edge gradients of the paper teapot against the truth: pixel pairs vs the boundary integral.

Run:  python examples/boundary_gradients.py [--out out] [--quick]

The teapot is moved rigidly; the loss is L = sum(W * image), W a fixed random weight image.
The truth is the central difference of L between renders with 1,024 samples per pixel
(box-filtered pixels); each method's gradient is one reverse pass at one sample per pixel:
``antialias=False`` (pixel centres), ``True`` (pixel pairs), ``"boundary"`` (the boundary
integral). Writes ``boundary.md`` (relative l2 errors, with and without shadows) and
``boundary_gradient_images.png`` (d image / d y for each method next to the truth).
``--quick`` runs one small size (for tests; its numbers are not results).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from script_support import command_line, write_results

import minidiff as md
from render.inverse.gradient_image import gradient_image
from render.renderer import render
from render.scene.teapot import paper_scene

METHODS = {"pixel centres": False, "pixel pairs": True, "boundary integral": "boundary"}
H = 0.01  # world units: about a tenth of a pixel at 128x128
QUICK = {"--quick": {"action": "store_true", "help": "one small size (not results)"}}


def _loss(size: int, offset, weights, spp: int, shadows: bool) -> float:
    scene = paper_scene(width=size, height=size)
    with md.no_grad():
        scene.meshes[0].vertices.data[...] += offset
        image = render(scene, spp=spp, shadows=shadows, reuse_visibility=False)
    return float(np.sum(weights * image.data))


def errors(size: int, shadows: bool, spp: int = 1024) -> dict:
    """Relative l2 error of d L / d translation for each method, and the truth."""
    weights = np.random.default_rng(0).uniform(0.0, 1.0, (size, size, 3))
    truth = np.array([
        (_loss(size, H * e, weights, spp, shadows) - _loss(size, -H * e, weights, spp, shadows))
        / (2 * H)
        for e in np.eye(3)
    ])  # fmt: skip
    row = {"size": size, "shadows": shadows, "truth": truth.tolist()}
    for name, antialias in METHODS.items():
        scene = paper_scene(width=size, height=size)
        vertices = scene.meshes[0].vertices
        vertices.requires_grad = True
        image = render(scene, antialias=antialias, shadows=shadows, reuse_visibility=False)
        (image * weights).sum().backward()
        ours = vertices.grad.sum(axis=0)
        row[name] = float(np.linalg.norm(ours - truth) / np.linalg.norm(truth))
    return row


def figure(path: Path, size: int) -> None:
    """d image / d y (red channel) of each method next to the supersampled truth."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def image(offset):
        scene = paper_scene(width=size, height=size)
        with md.no_grad():
            scene.meshes[0].vertices.data[...] += offset
            return render(scene, spp=1024, reuse_visibility=False).data[..., 0]

    step = np.array([0.0, H / 2, 0.0])
    panels = {"truth (1,024 spp, central difference)": (image(step) - image(-step)) / H}
    for name, antialias in METHODS.items():
        scene = paper_scene(width=size, height=size)
        direction = np.zeros(scene.meshes[0].vertices.shape)
        direction[:, 1] = 1.0
        grad = gradient_image(scene, scene.meshes[0].vertices, direction, antialias=antialias)
        panels[name] = grad[..., 0]
    crop = (slice(size // 8, size * 7 // 8), slice(size // 8, size * 15 // 16))
    scale = np.abs(panels["truth (1,024 spp, central difference)"][crop]).max()
    fig, axes = plt.subplots(1, len(panels), figsize=(4 * len(panels), 3.6))
    for ax, (name, values) in zip(axes, panels.items(), strict=True):
        ax.imshow(values[crop], cmap="RdBu", vmin=-scale, vmax=scale)
        ax.set_title(name, fontsize=9)
        ax.set_axis_off()
    fig.suptitle(f"paper teapot moved up: d red / d y, {size}x{size}")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main() -> None:
    args = command_line(__doc__, None, extra=QUICK, default_size=None, iterative=False)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    sizes = [32] if args.quick else [64, 128]
    spp = 64 if args.quick else 1024
    rows = [errors(size, shadows, spp) for size in sizes for shadows in (True, False)]
    lines = [
        "Rigid translation of the paper teapot, L = sum(W * image): relative l2 error of "
        "d L / d translation against central differences of 1,024-sample renders "
        "(`examples/boundary_gradients.py`).",
        "",
        "| size | shadows | " + " | ".join(METHODS) + " |",
        "|---|---|" + "---|" * len(METHODS),
    ]
    for row in rows:
        cells = " | ".join(f"{row[name]:.3f}" for name in METHODS)
        lines.append(f"| {row['size']} | {'yes' if row['shadows'] else 'no'} | {cells} |")
    lines += [
        "",
        "For context, Mitsuba 3.9 `direct_projective` on the same kind of check at 128x128: "
        "1.6 (issue 23).",
        "",
        "![gradient images](boundary_gradient_images.png)",
    ]
    if not args.quick:
        figure(out / "boundary_gradient_images.png", 128)
    write_results(out, "boundary", {"rows": rows}, "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
