"""Shape from views: a mesh recovered from images with known cameras and lights.

Run:  python examples/shape_from_views.py [--out out] [--size 128] [--iters 300]
      [--views 1,4,16,32] [--methods large_steps,laplacian,none] [--shape blob|teapot]
      [--batch 4] [--lr 0.03] [--lam 4] [--antialias boundary|pairs] [--quick]

Starts from an icosphere (2,562 vertices) and fits it to ``--shape``: "blob", a genus-0
shape with three dents generated in code (``render.inverse.reconstruction.dented_blob``),
or "teapot" (whose handle's hole a sphere cannot grow). Per number of views and method
(Large Steps, a Laplacian term, no regulariser; the same budget each): symmetric Chamfer
and Hausdorff distances to the true surface (% of its bounding-box diagonal), the PSNR of
8 held-out views, and the times. Writes ``<out>/shape/<shape>.json`` and ``.md``, and per
run the recovered mesh (``.npz``) and a held-out view beside its target (``.png``).

The regularisers are compared with ``--antialias pairs``: a crumpling mesh (no
regulariser) turns thousands of its edges into silhouettes, and the boundary integral's
cost grows with the square of the edges crossing a pixel (15 s per iteration after six
iterations, measured), while the pixel pairs' cost is bounded by the pixels.

``--quick`` runs two views at 32x32 for a few iterations (for tests; not results).
"""

from __future__ import annotations

import numpy as np
from script_support import EDGES, command_line, write_results

from render.inverse.reconstruction import dented_blob, run_shape
from render.scene.image import save_image
from render.scene.teapot import teapot_geometry

EXTRA = {
    "--views": {"default": "1,4,16,32", "help": "numbers of views, comma-separated"},
    "--methods": {"default": "large_steps,laplacian,none", "help": "regularisers compared"},
    "--shape": {"default": "blob", "choices": ["blob", "teapot"], "help": "the true shape"},
    "--batch": {"type": int, "default": 4, "help": "views rendered per iteration"},
    "--lr": {"type": float, "default": 0.03, "help": "Adam's learning rate"},
    "--lam": {"type": float, "default": 4.0, "help": "Large Steps' lambda"},
    "--quick": {"action": "store_true", "help": "a tiny run (not results)"},
    **EDGES,
}


def true_shape(name: str):
    """(vertices, faces) of the shape to recover, about the size of the unit sphere, and a
    box (lo, hi) whose share of the error is reported: the teapot's handle (the bounding
    box of its four patches, grown by 2 % of the diagonal), None for the blob."""
    if name == "blob":
        return dented_blob(5), None
    vertices, faces = teapot_geometry()[:2]
    vertices, faces = np.asarray(vertices, dtype=np.float64), np.asarray(faces)
    centre = 0.5 * (vertices.min(axis=0) + vertices.max(axis=0))
    radius = np.linalg.norm(vertices - centre, axis=1).max()
    vertices = (vertices - centre) / radius * 1.2
    handle = vertices[faces[HANDLE_PATCHES[0] * 48 : HANDLE_PATCHES[1] * 48]].reshape(-1, 3)
    grow = 0.02 * np.linalg.norm(np.ptp(vertices, axis=0))
    return (vertices, faces), (handle.min(axis=0) - grow, handle.max(axis=0) + grow)


#: The teapot's handle: patches 12..15 of Newell's 32 (48 triangles each at the default
#: tessellation), whose hole a sphere cannot grow.
HANDLE_PATCHES = (12, 16)


def save_comparison(run: dict, path) -> None:
    """The first held-out view: the target beside the recovered shape's render (PNG)."""
    target, fitted = run.pop("held_out_images")
    save_image(np.concatenate([target, fitted], axis=1), path)


def main(argv=None) -> dict:
    EXTRA["--antialias"] = {**EXTRA["--antialias"], "default": "boundary"}
    args = command_line(__doc__.splitlines()[0], 300, argv, EXTRA, default_size=128)
    views = [int(v) for v in args.views.split(",")]
    methods = args.methods.split(",")
    size, iters, start = args.size, args.iters, 4
    if args.quick:
        views, methods, size, iters, start = [2], methods[:1], 32, 5, 2
    shape, region = true_shape(args.shape)
    out = args.out / "shape"
    out.mkdir(parents=True, exist_ok=True)
    runs = []
    for n in views:
        for method in methods:
            options = {"antialias": args.antialias, "seed": args.seed, "quiet": args.quiet,
                       "lam": args.lam}  # fmt: skip
            r = run_shape(shape, n, size, iters, method, args.batch, start, args.lr,
                          region=region, **options)  # fmt: skip
            save_comparison(r, out / f"{args.shape}_{n}views_{method}.png")
            vertices, faces = r.pop("mesh")
            np.savez_compressed(out / f"{args.shape}_{n}views_{method}.npz", vertices=vertices,
                                faces=faces)  # fmt: skip
            runs.append(r)
            share = f"handle's share {r['region_share_percent']:.1f} %, " if region else ""
            print(f"{n:3d} views, {method:12s}: Chamfer {r['chamfer_percent']:.3f} %, {share}"
                  f"Hausdorff {r['hausdorff_percent']:.3f} % at {np.round(r['hausdorff_at'], 2)}, "
                  "held-out PSNR "
                  f"{r['held_out_psnr']:.2f} dB, {r['seconds']:.0f} s", flush=True)  # fmt: skip
    handle = region is not None
    rows = [
        f"| {r['views']} | {r['method']} | {r['chamfer_percent']:.3f} "
        + (f"| {r['region_share_percent']:.0f} | {r['chamfer_outside_region_percent']:.3f} "
           if handle else "")
        + f"| {r['hausdorff_percent']:.3f} | {r['held_out_psnr']:.2f} "
        f"| {r['seconds_per_iteration'] * 1e3:.0f} | {r['seconds']:.0f} |"
        for r in runs
    ]  # fmt: skip
    extra_head = "| handle's share of it (%) | Chamfer outside the handle (%) " if handle else ""
    report = "\n".join([
        f"# Shape from views: {args.shape}, {size}x{size}, {iters} iterations, batch "
        f"{args.batch}, edges: {args.antialias}, start: icosphere ({runs[0]['vertices']} "
        f"vertices), Adam lr {args.lr}, Large Steps lambda {args.lam}",
        "",
        f"| views | method | Chamfer (% of diagonal) {extra_head}| Hausdorff (%) "
        "| held-out PSNR (dB) | ms per iteration | seconds |",
        "|---|---|---|" + ("---|---|" if handle else "") + "---|---|---|---|",
        *rows,
        "",
    ])  # fmt: skip
    return write_results(out, args.shape, {"size": size, "iters": iters, "runs": runs}, report)


if __name__ == "__main__":
    main()
