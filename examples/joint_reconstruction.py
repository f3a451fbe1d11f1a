"""Everything at once: camera pose, light, albedo and shape from views of the paper scene.

Run:  python examples/joint_reconstruction.py [--out out] [--size 128] [--iters 400]
      [--views 1,4] [--antialias boundary] [--quick]

``render.inverse.reconstruction.run_joint`` per number of views: the first camera's
position and look-at point, the point light's position and intensity, the teapot's albedo
and per-vertex offsets (the truth is the teapot bent by a smooth field) optimised together.
Reports each parameter's error and that of albedo x intensity (the teapot is Lambertian:
only their product reaches the image), in ``<out>/joint/joint.json`` and ``joint.md``.

``--quick`` runs one small problem for a few iterations (for tests; not results).
"""

from __future__ import annotations

import numpy as np
from script_support import EDGES, command_line, write_results

from render.inverse.reconstruction import run_joint
from render.scene.image import save_image

EXTRA = {
    "--views": {"default": "1,4", "help": "numbers of views, comma-separated (at most 4)"},
    "--quick": {"action": "store_true", "help": "a tiny run (not results)"},
    **EDGES,
}
COLUMNS = {
    "camera_position_error_percent": "camera position (%)",
    "view_direction_error_degrees": "view direction (degrees)",
    "look_at_error": "look-at point (units; its distance along the view is not observable)",
    "light_position_error_percent": "light position (%)",
    "intensity_error_percent": "intensity (%)",
    "albedo_error_percent": "albedo (%)",
    "albedo_times_intensity_error_percent": "albedo x intensity (%)",
    "shape_chamfer_percent": "shape Chamfer (% of the diagonal)",
}


def main(argv=None) -> dict:
    EXTRA["--antialias"] = {**EXTRA["--antialias"], "default": "boundary"}
    args = command_line(__doc__.splitlines()[0], 400, argv, EXTRA, default_size=128)
    views = [int(v) for v in args.views.split(",")]
    size, iters = (24, 5) if args.quick else (args.size, args.iters)
    if args.quick:
        views = [2]
    runs = [run_joint(n, size, iters, args.seed, args.antialias, quiet=args.quiet,
                      samples=2000 if args.quick else 20_000) for n in views]  # fmt: skip
    lines = [
        f"# Joint reconstruction, {size}x{size}, {iters} iterations, edges: {args.antialias}",
        "",
        "| error of (start -> end) | " + " | ".join(f"{r['views']} view(s)" for r in runs) + " |",
        "|---|" + "---|" * len(runs),
    ]
    for key, label in COLUMNS.items():
        start = "shape_chamfer_at_start_percent" if key.startswith("shape") else f"initial_{key}"
        lines.append(f"| {label} | " + " | ".join(f"{r[start]:.4g} -> {r[key]:.4g}" for r in runs)
                     + " |")  # fmt: skip
    times = " | ".join(f"{r['seconds_per_iteration']:.3f}" for r in runs)
    lines.append(f"| seconds per iteration | {times} |")
    out = args.out / "joint"
    out.mkdir(parents=True, exist_ok=True)
    for r in runs:  # the first view: target | start | result
        save_image(np.concatenate(list(r.pop("images")), axis=1),
                   out / f"joint_{r['views']}views.png")  # fmt: skip
    result = {"size": size, "iters": iters, "runs": runs}
    return write_results(out, "joint", result, "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
