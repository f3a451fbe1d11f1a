"""Recover an area light's position and size from the soft shadows it casts, the light unseen.

Run:  python examples/soft_shadow_light.py [--scene open|cornell] [--out out/soft_shadow]
      [--size 64] [--steps 200] [--spp 8] [--antialias boundary] [--compare none] [--quick]

Two scenes (``SCENES``), every surface diffuse, the light a square (an emitter seen by
no camera ray, nor in any mirror) placed by its ``Transform``: the translation (3,) moves
it, the uniform scale (a scalar, about the light's centre) sizes it.

* ``open`` (the default): a large white floor under the sky (black), a square light 5 above
  it, and two occluders hanging 2 above the floor out of the camera's view (a thin square
  tile and a ball); the camera sees the floor and the occluders' shadows, nothing else.
  The light's power is held fixed: its radiance is ``OPEN_RADIANCE / scale^2`` (set after
  every step; the chain rule through it is added by hand, ``power_chain``), and the light
  is far from the floor (5 vs a visible floor about 3 wide), so the floor's shading alone
  barely tells the light's size or where it is; the shadows do: they move and their
  penumbrae widen with it. This is the scene where the boundary term of secondary
  visibility is needed (see ``docs/path_tracing/soft_shadow_open``).
* ``cornell``: the Cornell box with its blocks (``render.scene.cornell.cornell_box``), seen
  by a camera inside the room that looks down at the floor (neither the ceiling nor the
  light in view), the light's radiance fixed. There the floor's shading (the light is 2
  above it, in a closed room) carries the light's position and size as well as the
  shadows do: the fit converges with and without boundary terms alike
  (``docs/path_tracing/soft_shadow``).

Both start 30 % wrong and are fitted by Adam on the image MSE against a ``--target-spp``
render of the true scene, with the path integrator's replay gradient
(``render.path.replay_gradient``, ``antialias="boundary"``: its boundary terms, new samples
every step, the gradient pass's seed decorrelated). ``--compare none`` fits a second time
without any boundary term (the interior gradient alone), to show what they change.

How wrong: a translation error is measured in the scene's ``unit`` of length (the Cornell
room's half-width, 1; the open scene's light's side, 1): the start moves the light 0.3
units along x and 0.3 along z (0.42 in distance; y starts right and is free). The size
error is |scale - 1| (the true scale is 1): the start is 1.3. The optimiser keeps the
translation in a box where the camera never sees the light (the Cornell light below the
ceiling, it hangs 0.01 under it, and above the camera).

Writes ``result.json`` (the settings; the translation, scale, errors and loss after every
step; the final errors, of the last step and of the mean of the last 10, and the step from
which each error stays below 2 %; the timings; the ``--compare`` run's the same under
``comparison``) and ``soft_shadow.png`` (target, start and result rendered at
``--target-spp``, and the position and size errors against the step, the ``--compare``
run's dashed). ``--quick``: 16x16, 6 steps (a smoke run, not results). The default
``--out`` is scratch (``out/`` is git-ignored); the committed copies are made with
``--scene open --out docs/path_tracing/soft_shadow_open`` and ``--scene cornell --out
docs/path_tracing/soft_shadow``.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from colour_bleeding import display

import minidiff as md
from render.inverse.jsonio import write_json
from render.path import render_path, replay_gradient
from render.scene.camera import Camera
from render.scene.cornell import LIGHT_DROP, WHITE, box_mesh, cornell_box, grid_quad
from render.scene.image import mse
from render.scene.scene import Material, Mesh, Scene, Sphere, Transform

#: The true placement (the light where the scene puts it) and the start, in both scenes.
TRUE_TRANSLATION, TRUE_SCALE = (0.0, 0.0, 0.0), 1.0
START_TRANSLATION, START_SCALE = (0.3, 0.0, 0.3), 1.3
#: Where the optimiser may put the scale.
SMALLEST, LARGEST = 0.2, 2.0
#: The seeds of the target render and of the gradient passes (step + GRAD_SEED).
TARGET_SEED, GRAD_SEED = 10**6, 10**7

#: The open scene: the light's height above the floor, its half side and its radiance at
#: scale 1 (its power is held at this radiance times its area at scale 1).
OPEN_HEIGHT, OPEN_HALF_SIDE, OPEN_RADIANCE = 5.0, 0.5, (50.0, 42.0, 30.0)


@dataclass(frozen=True)
class Setup:
    """One of the example's scenes: ``build(size)`` is the true scene at size x size, its
    object ``light`` the light (with a ``Transform`` pivoting about the light's centre, so
    that the scale sizes it without moving it); the optimiser keeps its translation in the
    box [lowest, highest]; position errors are in units of ``unit`` (``unit_name``);
    ``radiance`` (3,) is the light's radiance at scale 1 where its power is held fixed
    (radiance / scale^2), None where the radiance stays; ``max_depth`` the paths' default
    length."""

    build: Callable[[int], Scene]
    light: int
    lowest: tuple
    highest: tuple
    unit: float
    unit_name: str
    radiance: tuple | None
    max_depth: int


def cornell_scene(size: int) -> Scene:
    """The Cornell box with blocks at ``size`` x ``size``, seen from inside the room looking
    down at the floor (the light out of view), the light's transform pivoting about its
    centre."""
    scene = cornell_box(size, size, blocks=True)
    scene.camera = Camera((0.0, 0.6, 0.95), (0.0, -1.0, -0.35), (0, 1, 0), 75.0, size, size)
    scene.objects[5].transform = Transform(pivot=(0.0, 1.0 - LIGHT_DROP, 0.0))
    return scene


def open_scene(size: int) -> Scene:
    """A white floor (the square |x|, |z| <= 4 at y = 0) under a black sky, the light (a
    square of half side ``OPEN_HALF_SIDE`` facing down, ``OPEN_HEIGHT`` above the floor's
    centre) and two white occluders hanging about 2 above the floor, out of view: a thin
    square tile and a ball. The camera, 1.5 above the floor, looks down at it at about 45
    degrees: it sees the floor and the two soft shadows. Objects: floor, light, tile, ball."""
    x, y, z = np.eye(3)
    centre = (0.0, OPEN_HEIGHT, 0.0)
    side = OPEN_HALF_SIDE
    light = Mesh(*grid_quad(centre, side * x, side * z),  # faces down
                 Material((0.0, 0.0, 0.0), emission=OPEN_RADIANCE),
                 transform=Transform(pivot=centre))  # fmt: skip
    objects = [
        Mesh(*grid_quad((0.0, 0.0, 0.0), 4.0 * x, -4.0 * z), Material(WHITE)),  # faces up
        light,
        box_mesh((-0.45, 2.0, -0.35), (0.3, 0.04, 0.25), Material(WHITE)),
        Sphere((0.45, 2.3, 0.05), 0.3, Material(WHITE)),
    ]
    camera = Camera((0.0, 1.5, 1.5), (0.0, 0.0, 0.1), (0, 1, 0), 60.0, size, size)
    return Scene(objects, [], camera)


SCENES = {
    # The light stays high above the camera (which looks down): never in view.
    "open": Setup(open_scene, 1, (-0.7, -1.0, -0.7), (0.7, 1.0, 0.7), 2.0 * OPEN_HALF_SIDE,
                  "the light's side (1)", OPEN_RADIANCE, 3),
    # The light stays inside the room, below the ceiling (it hangs LIGHT_DROP under it) and
    # above the camera (at y = 0.6, looking down), so that it never comes into view.
    "cornell": Setup(cornell_scene, 5, (-0.7, -0.2, -0.7), (0.7, LIGHT_DROP - 0.001, 0.7), 1.0,
                     "the room's half-width (1)", None, 4),
}  # fmt: skip


def errors(
    setup: Setup, translation: np.ndarray, scale: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Position errors |t - t_true| / ``setup.unit`` and size errors |scale - 1| / 1 of
    placements given as translations (n, 3) and scales (n,)."""
    position = np.linalg.norm(translation - np.array(TRUE_TRANSLATION), axis=-1) / setup.unit
    return position, np.abs(scale - TRUE_SCALE) / TRUE_SCALE


def hold_power(setup: Setup, scene: Scene) -> None:
    """Where ``setup`` holds the light's power fixed, set its radiance to radiance /
    scale^2 for the light's current scale (its area grows as scale^2)."""
    if setup.radiance is not None:
        light = scene.objects[setup.light]
        scale = float(light.transform.scale.data)
        light.material.emission.data = np.array(setup.radiance) / scale**2


def power_chain(setup: Setup, scene: Scene) -> None:
    """Where ``setup`` holds the power fixed, add to the scale's gradient the part that
    reaches it through the radiance: d loss / d radiance . d (radiance0 / s^2) / d s."""
    light = scene.objects[setup.light]
    emission, scale = light.material.emission, light.transform.scale
    if setup.radiance is not None and emission.grad is not None:
        slope = -2.0 * np.array(setup.radiance) / float(scale.data) ** 3
        scale.grad = scale.grad + float(np.sum(emission.grad * slope))
        emission.grad = None


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--out",
        default="out/soft_shadow",
        help="output folder (default out/soft_shadow; the committed copies were made with "
        "--scene open --out docs/path_tracing/soft_shadow_open and --scene cornell --out "
        "docs/path_tracing/soft_shadow)",
    )
    parser.add_argument("--scene", choices=sorted(SCENES), default="open")
    parser.add_argument("--size", type=int, default=64)
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--spp", type=int, default=8, help="samples per pixel per step")
    parser.add_argument("--target-spp", type=int, default=1024)
    parser.add_argument(
        "--max-depth", type=int, help="path length (default: the scene's, open 3, cornell 4)"
    )
    parser.add_argument("--lr", type=float, default=0.02, help="Adam's first step")
    parser.add_argument(
        "--antialias",
        default="boundary",
        help='render_path\'s antialias ("none": no boundary term; default "boundary")',
    )
    parser.add_argument(
        "--compare",
        metavar="ANTIALIAS",
        help="also fit with this antialias (e.g. none), drawn dashed beside the first",
    )
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args(argv)
    if args.quick:
        args.size, args.steps, args.spp, args.target_spp = 16, 6, 2, 16
    if args.max_depth is None:
        args.max_depth = SCENES[args.scene].max_depth
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    begin = time.perf_counter()
    run = recover_light(args, args.antialias)
    run["seconds"]["total"] = time.perf_counter() - begin
    print(summary(run), flush=True)
    if args.compare is not None:
        other = recover_light(args, args.compare)
        print(summary(other), flush=True)
        run["comparison"] = {k: v for k, v in other.items() if k not in ("images", "settings")}
    write_json(out / "result.json", {k: v for k, v in run.items() if k != "images"})
    figure(run, out / "soft_shadow.png")
    return run


def summary(run: dict) -> str:
    """One line: the settings, the errors at the start and the end, the time."""
    final, settings = run["final"], run["settings"]
    return (
        f"{settings['scene']}, antialias {run['antialias']}, {settings['steps']} steps of "
        f"{settings['spp']} spp at {settings['size']}x{settings['size']}: position error "
        f"{run['position_error'][0]:.3f} -> {final['position_error']:.4f} (last 10 averaged: "
        f"{final['settled_position_error']:.4f}), size error {run['size_error'][0]:.3f} -> "
        f"{final['size_error']:.4f} (last 10 averaged: {final['settled_size_error']:.4f}); "
        f"{run['seconds']['steps']:.1f} s of steps"
    )


def recover_light(args: argparse.Namespace, antialias: str) -> dict:
    """Fit the light's translation and scale in ``args.scene`` (see the module docstring)
    with ``antialias`` ("none": False) as ``render_path``'s; returns what ``result.json``
    holds, plus the target, start and result images (H, W, 3)."""
    setup, depth = SCENES[args.scene], args.max_depth
    began = time.perf_counter()
    target = render_path(setup.build(args.size), args.target_spp, depth, TARGET_SEED).data
    target_seconds = time.perf_counter() - began
    scene = setup.build(args.size)
    transform = scene.objects[setup.light].transform
    translation, scale = transform.translation, transform.scale
    translation.data, scale.data = np.array(START_TRANSLATION), np.array(START_SCALE)
    hold_power(setup, scene)
    with md.no_grad():  # the start, rendered as the target is (another seed)
        start = render_path(scene, args.target_spp, depth, TARGET_SEED + 1).data
    translation.requires_grad = scale.requires_grad = True
    # The radiance follows the scale (hold_power): its gradient goes into the scale's.
    scene.objects[setup.light].material.emission.requires_grad = setup.radiance is not None
    box = md.optim.box(np.array(setup.lowest), np.array(setup.highest))
    project = [box, md.optim.box(SMALLEST, LARGEST)]
    optimiser = md.optim.Adam([translation, scale], lr=args.lr, project=project)
    placements, losses, seconds = [(translation.data.copy(), float(scale.data))], [], []
    for step in range(args.steps):
        began = time.perf_counter()
        # The step shrinks tenfold over the run: the last steps average the noise of many
        # gradients instead of following each one.
        optimiser.lr = [args.lr * 0.1 ** (step / args.steps)] * 2
        optimiser.zero_grad()
        value, _ = replay_gradient(
            scene, lambda image: mse(image, target), spp=args.spp, max_depth=depth,
            seed=step, seed_grad=step + GRAD_SEED,
            antialias=False if antialias == "none" else antialias,
        )  # fmt: skip
        power_chain(setup, scene)
        optimiser.step()
        hold_power(setup, scene)
        seconds.append(time.perf_counter() - began)
        placements.append((translation.data.copy(), float(scale.data)))
        losses.append(value)
    with md.no_grad():
        result = render_path(scene, args.target_spp, depth, TARGET_SEED + 2).data
    translations = np.array([t for t, _ in placements])
    scales = np.array([s for _, s in placements])
    position_error, size_error = errors(setup, translations, scales)
    # The mean of the last 10 iterates: what the noisy steps hover around.
    settled = errors(setup, translations[-10:].mean(axis=0), scales[-10:].mean())
    return {
        "settings": {k: v for k, v in vars(args).items() if k not in ("out", "compare")},
        "antialias": antialias,
        "definitions": {
            "position_error": f"|translation - true| in units of {setup.unit_name}",
            "size_error": "|scale - true| / true (true scale 1)",
        },
        "truth": {"translation": TRUE_TRANSLATION, "scale": TRUE_SCALE},
        "start": {"translation": START_TRANSLATION, "scale": START_SCALE},
        "translation": translations,
        "scale": scales,
        "position_error": position_error,
        "size_error": size_error,
        "loss": losses,
        "final": {
            "translation": translations[-1],
            "scale": scales[-1],
            "position_error": position_error[-1],
            "size_error": size_error[-1],
            "settled_translation": translations[-10:].mean(axis=0),
            "settled_scale": scales[-10:].mean(),
            "settled_position_error": settled[0],
            "settled_size_error": settled[1],
            "below_2pct_from_step": {
                "position": settled_below(position_error, 0.02),
                "size": settled_below(size_error, 0.02),
            },
        },
        "seconds": {
            "target_render": target_seconds,
            "steps": sum(seconds),
            "per_step": seconds,
            "mean_per_step": sum(seconds) / max(1, len(seconds)),
        },
        "images": {"target": target, "start": start, "result": result},
    }


def settled_below(error: np.ndarray, level: float) -> int | None:
    """The first step from which ``error`` (steps + 1,) stays below ``level`` to the end;
    None if its last value is not below."""
    above = np.flatnonzero(error >= level)
    if len(above) == 0:
        return 0
    return None if above[-1] == len(error) - 1 else int(above[-1] + 1)


def figure(run: dict, path: Path) -> None:
    """``soft_shadow.png``: the target, start and result images (2x exposure, gamma 1/2.2)
    and the position and size errors against the step (log scale; the ``--compare`` run's
    dashed)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(13.0, 3.4), dpi=100, layout="constrained")
    FigureCanvasAgg(fig)  # renders to PNG without pyplot
    axes = fig.subplots(1, 4, width_ratios=[1, 1, 1, 1.6])
    for ax, name in zip(axes, ("target", "start", "result"), strict=False):
        ax.imshow(display(run["images"][name]), interpolation="nearest")
        ax.set_title(name, fontsize=10)
        ax.set_axis_off()
    ax = axes[3]
    for other, style in ((run, "-"), (run.get("comparison"), "--")):
        if other is None:
            continue
        steps, aa = np.arange(len(other["position_error"])), other["antialias"]
        ax.semilogy(steps, other["position_error"], style, color="C0",
                    label=f"position |t - t*| / unit, {aa}")  # fmt: skip
        ax.semilogy(
            steps, other["size_error"], style, color="C1", label=f"size |s - s*| / s*, {aa}"
        )
    ax.axhline(0.02, color="0.5", linestyle=":", linewidth=1, label="2 %")
    ax.set_xlabel("step")
    ax.set_ylabel("error")
    ax.grid(True, which="major", color="0.9")
    ax.legend(fontsize=8, frameon=False)
    fig.savefig(path)


if __name__ == "__main__":
    main()
