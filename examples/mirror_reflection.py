"""Mirror reflection: the teapot on a mirror floor, and a light recovered through a mirror.

Run:  python examples/mirror_reflection.py [--out out] [--size 256] [--iters 500]
      [--seed 42] [--quick]

1. figure: the paper's teapot standing on a mirror floor (reflectance 0.8 over a dark grey
   albedo), with reflections (``max_bounces=2``) and without (``max_bounces=0``), side by
   side -> ``<out>/mirror_reflection/teapot_mirror_floor.png``;
2. inverse problem: the teapot stands *behind* the camera, which looks at a vertical mirror:
   every camera ray that reaches the teapot does so by way of the mirror (checked from
   ``RenderInfo``: no camera ray hits the teapot directly). The paper's light-estimation
   problem (light at (1, 4, 2), I = 150, the paper's seeded starts) is solved from that
   image alone, five seeds from ``--seed``. Reported: the position and intensity
   errors (the paper's Eqs. 5 and 6) and the iterations until the loss fell below 1e-9.
Results: ``<out>/mirror_reflection/mirror_reflection.json`` and ``.md``.

``--quick`` runs one seed at 48x48 for 20 iterations (for tests; not results).
"""

from __future__ import annotations

import time

import numpy as np
from script_support import command_line, write_results

import minidiff as md
from render.inverse.experiments import (
    TRUE_INTENSITY,
    TRUE_LIGHT,
    light_errors_pct,
    light_estimation_problem,
)
from render.inverse.optimize import optimize
from render.renderer import render
from render.scene.image import save_image
from render.scene.scene import Camera, Material, Mesh, PointLight, Scene
from render.scene.teapot import paper_scene, teapot

INITIAL_ERRORS = ("initial_position_error_pct", "initial_intensity_error_pct")
ERRORS = ("position_error_pct", "intensity_error_pct")
QUICK = {"--quick": {"action": "store_true", "help": "one small run (not results)"}}
MIRROR_FLOOR = Material((0.05, 0.05, 0.05), reflectance=0.8)


def mirror_floor_figure(size: int) -> np.ndarray:
    """(size, 2 size, 3): the teapot on a mirror floor with and without reflections."""
    scene = paper_scene(size, size, ground=True, ground_material=MIRROR_FLOOR)
    with_mirror = render(scene).data
    without = render(scene, max_bounces=0).data
    return np.concatenate([with_mirror, without], axis=1)


def teapot_behind_the_camera(size: int, light, intensity) -> Scene:
    """The teapot at the origin, a 10 x 5 vertical mirror at z = 4.5 facing it (the side
    the light is on), and the camera between them at z = 1.8 (past the teapot's extent,
    z <= 1) looking at the mirror: the teapot is seen only reflected."""
    x, y0, y1, z = 5.0, -1.0, 4.0, 4.5
    mirror = Mesh(
        [(-x, y0, z), (x, y0, z), (x, y1, z), (-x, y1, z)],
        [[0, 1, 2], [0, 2, 3]],
        Material((0.0, 0.0, 0.0), reflectance=0.9),
    )
    camera = Camera.from_focal_length(
        50.0, 36.0, position=(0.3, 1.0, 1.8), look_at=(0.1, 0.7, 4.5), width=size, height=size
    )
    return Scene([teapot(), mirror], [PointLight(light, intensity)], camera, background=(0, 0, 0))


def seen_only_in_the_mirror(scene: Scene) -> dict:
    """How many camera rays hit the teapot directly, and how many by way of the mirror."""
    with md.no_grad():
        _, info = render(scene, return_info=True)
    n_teapot = scene.meshes[0].num_faces  # the teapot's triangles come first
    direct = int(((info.prim_id >= 0) & (info.prim_id < n_teapot)).sum())
    reflected = int(((info.bounces[0] >= 0) & (info.bounces[0] < n_teapot)).sum())
    return {"direct_teapot_rays": direct, "teapot_rays_via_mirror": reflected}


def estimate_light(size: int, seed: int, iters: int, tol: float) -> dict:
    """The paper's light estimation, from the image of the teapot in the mirror."""
    scene, (position, strength), target = light_estimation_problem(
        size, seed, lambda light_position, light_intensity: teapot_behind_the_camera(
            size, light_position, light_intensity
        ),
    )  # fmt: skip
    target = np.clip(target, 0.0, 1.0)
    initial = light_errors_pct(position.data.copy(), strength.item())
    start = time.perf_counter()
    _, history = optimize(
        scene, [position, strength], target, lr=[0.3, 20.0], max_iters=iters, tol=tol,
        quiet=True,
    )  # fmt: skip
    seconds = time.perf_counter() - start
    below = [i for i, loss in enumerate(history.loss) if loss < tol]
    return {
        "seed": seed,
        **seen_only_in_the_mirror(scene),
        **dict(zip(INITIAL_ERRORS, initial, strict=True)),
        **dict(zip(ERRORS, light_errors_pct(position, strength), strict=True)),
        "iterations": len(history.loss),
        "iterations_to_tol": below[0] if below else None,
        "seconds": seconds,
    }


def report(result: dict) -> str:
    size, runs = result["size"], result["runs"]
    lines = [
        f"Light estimation through a mirror, {size}x{size}, at most {result['iters']} "
        "iterations (the teapot is behind the camera):",
        "",
        "| seed | teapot rays: direct / via mirror | position error: start -> end | "
        "intensity error: start -> end | iterations to loss < 1e-9 | seconds |",
        "|---|---|---|---|---|---|",
    ]
    for r in runs:
        lines.append(
            f"| {r['seed']} | {r['direct_teapot_rays']} / {r['teapot_rays_via_mirror']} | "
            f"{r['initial_position_error_pct']:.3g} % -> {r['position_error_pct']:.3g} % | "
            f"{r['initial_intensity_error_pct']:.3g} % -> {r['intensity_error_pct']:.3g} % | "
            f"{r['iterations_to_tol']} | {r['seconds']:.1f} |"
        )
    return "\n".join(lines) + "\n"


def main(argv=None) -> dict:
    args = command_line(
        __doc__.splitlines()[0], default_iters=500, argv=argv, extra=QUICK, default_size=256
    )
    out = args.out / "mirror_reflection"
    out.mkdir(parents=True, exist_ok=True)
    size, iters = (48, 20) if args.quick else (args.size, args.iters)
    seeds = [args.seed] if args.quick else list(range(args.seed, args.seed + 5))
    save_image(mirror_floor_figure(size), out / "teapot_mirror_floor.png", srgb=True)
    target_view = teapot_behind_the_camera(size, TRUE_LIGHT, TRUE_INTENSITY)
    save_image(render(target_view), out / "teapot_in_the_mirror.png", srgb=True)
    result = {"quick": args.quick, "size": size, "iters": iters, "runs": []}
    for seed in seeds:
        result["runs"].append(estimate_light(size, seed, iters, 1e-9))
        if not args.quiet:
            print(result["runs"][-1], flush=True)
    return write_results(out, "mirror_reflection", result, report(result))


if __name__ == "__main__":
    main()
