"""What the example scripts share: their command line and the files they write.

Not part of the library: ``render.inverse.experiments`` runs the paper's experiments and returns
their numbers and images; this module turns that into a command-line program that prints
JSON and writes PNGs, a loss plot and an animated GIF. Scripts in this folder import it as
``script_support`` (Python puts a script's own folder on the import path).

Importing it is cheap (the standard library and NumPy): the renderer, Pillow and
Matplotlib are imported where they are used, so that a script can parse its command line
and say what it is about to do before the seconds those imports take.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
from hashlib import sha1
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from render.inverse.experiments import ExperimentRun


def command_line(
    description: str,
    default_iters: int | None,
    argv=None,
    extra: dict[str, dict] | None = None,
    default_size: int | None = 512,
    iterative: bool = True,
) -> argparse.Namespace:
    """The shared command line of the example scripts: --size --iters --seed --out --quiet,
    plus ``extra`` options ({"--name": argparse keyword arguments}). A default of None
    means "not given" (the script then picks per experiment). ``iterative=False`` (a plain
    render) leaves out --iters and --seed, which would mean nothing."""
    parser = argparse.ArgumentParser(description=description)
    for name, options in (extra or {}).items():
        parser.add_argument(name, **options)
    parser.add_argument(
        "--size", type=int, default=default_size, help="image width = height (pixels)"
    )
    if iterative:
        parser.add_argument("--iters", type=int, default=default_iters, help="maximum iterations")
        parser.add_argument("--seed", type=int, default=42, help="random seed of the start")
    parser.add_argument("--out", type=Path, default=Path("out"), help="output folder")
    parser.add_argument("--quiet", action="store_true", help="no progress line")
    args = parser.parse_args(argv)
    if args.size is not None and args.size < 8:
        parser.error(f"--size must be at least 8, got {args.size}")
    if getattr(args, "iters", None) is not None and args.iters < 0:
        parser.error(f"--iters must be >= 0, got {args.iters}")
    if args.out.exists() and not args.out.is_dir():
        parser.error(f"--out {args.out} exists and is not a folder")
    return args


def edge_method(text: str) -> bool | str:
    """The --antialias option's value as ``render(antialias=...)`` takes it: "none" (the
    paper's renderer), "pairs" or "boundary"."""
    methods = {"none": False, "pairs": True, "boundary": "boundary"}
    if text not in methods:
        raise argparse.ArgumentTypeError(f"choose one of {', '.join(methods)}, got {text!r}")
    return methods[text]


#: the --antialias option of the experiment scripts
EDGES = {
    "--antialias": {
        "type": edge_method,
        "default": "none",
        "help": "edge gradients: none (the paper's renderer), pairs or boundary",
    }
}


#: the --jobs option of the scripts whose runs are independent (``render.inverse.parallel``)
JOBS = {
    "type": int,
    "default": None,
    "help": "worker processes for the independent runs (default: one per core; 1: serial)",
}


#: Seconds of compiling before the first result on a fresh clone (an empty Numba cache), one
#: process: the renderer's kernels with the pair-sampled edge gradients (tracing, the fused
#: passes, the compiled adjoint's node, edges), and with the boundary integral's kernels too
#: (measured stage by stage with an empty NUMBA_CACHE_DIR on a 2-core AMD EPYC, CPU time:
#: 32 s forward, 23 s the node, 4 s pairs; before issue 45's kernels: 31 s and 61 s). With
#: the boundary term: the paper scene's first boundary gradient at 64x64 took 77.8 s in all
#: (134.9 s before issue 57 deleted three of its kernels' twins, in the same hour).
COMPILE_SECONDS = {"pairs": 60, "boundary": 50}


def numba_cache_folder(source: Path) -> Path:
    """Where Numba caches the kernels of the module file ``source``: under
    ``NUMBA_CACHE_DIR`` if set (a folder named after the source's folder and a hash of its
    path, as ``numba.core.caching`` names it), else the ``__pycache__`` beside it."""
    folder = os.path.dirname(os.path.abspath(source))
    root = os.environ.get("NUMBA_CACHE_DIR", "")
    if root:
        return Path(root) / f"{os.path.basename(folder)}_{sha1(folder.encode()).hexdigest()}"
    return Path(folder) / "__pycache__"


def kernels_cached(modules: dict[str, str]) -> bool:
    """Whether Numba's cache holds a compiled kernel of each module, newer than its source:
    ``modules`` maps a module ("render.trace.intersect") to the name of one of its kernels
    ("closest_hit_bvh"). Found without importing the renderer or Numba (a guess for a
    notice: a kernel whose types changed still compiles)."""
    spec = importlib.util.find_spec("render")
    if spec is None or not spec.submodule_search_locations:
        return False
    root = Path(next(iter(spec.submodule_search_locations))).parent
    for module, kernel in modules.items():
        source = root / (module.replace(".", "/") + ".py")
        name = f"{module.rsplit('.', 1)[-1]}.{kernel}-"
        folder = numba_cache_folder(source)
        try:
            index = [p for p in folder.iterdir() if p.name.startswith(name) and p.suffix == ".nbi"]
            if not index or max(p.stat().st_mtime for p in index) < source.stat().st_mtime:
                return False
        except OSError:
            return False
    return True


def kernel_notice(edges) -> str:
    """One line on the compiling to come: which kernels, about how long on a fresh clone,
    or that they are in Numba's cache. ``edges``: the camera rows' ``antialias``."""
    boundary = edges == "boundary"
    modules = {
        "render.trace.intersect": "closest_hit_bvh",
        "render.shade.compiled": "_shade_kernel",
    }
    if boundary:
        modules["render.edges.boundary.pixels"] = "_split_all"
    what = "ray tracing, shading" + (", boundary-integral edges" if boundary else ", edges")
    if kernels_cached(modules):
        return f"The renderer's Numba kernels ({what}) are in Numba's cache: no compiling."
    seconds = COMPILE_SECONDS["boundary" if boundary else "pairs"]
    return (f"Compiling the renderer's Numba kernels ({what}) first: about {seconds} s on a "
            "fresh clone (2 cores), once; cached for later runs.")  # fmt: skip


class FrameRecorder:
    """An ``optimize`` callback that keeps a downsampled frame every ``every`` iterations,
    for the animation."""

    def __init__(self, every: int, max_side: int = 192):
        self.every, self.max_side, self.frames = max(1, every), max_side, []

    def __call__(self, it, loss, image, history):
        if it % self.every == 0:
            from PIL import Image

            frame = Image.fromarray((np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8))
            if max(frame.size) > self.max_side:
                frame.thumbnail((self.max_side, self.max_side))
            self.frames.append(frame)


def write_outputs(run: ExperimentRun, out: Path, frames: list | None = None) -> Path:
    """Write ``out/<run.name>/``: target, initial and final PNGs, the |final - target|
    difference (scaled to its maximum), the loss curve and, given ``frames``, the GIF."""
    from render.inverse.plot import line_plot
    from render.scene.image import save_image

    folder = Path(out) / run.name
    save_image(run.target, folder / "target.png")
    save_image(run.initial, folder / "initial.png")
    save_image(run.final, folder / "final.png")
    difference = np.abs(run.final - run.target)
    scale = max(float(difference.max()), 1e-12)
    save_image(difference / scale, folder / "difference.png")
    loss = run.history.loss
    line_plot(
        {"loss (MSE)": (np.arange(len(loss)), loss)},
        folder / "loss.png",
        title=f"{run.name}: loss per iteration (difference image scaled by 1/{scale:.3g})",
        xlabel="iteration",
        ylabel="MSE",
        logy=True,
    )
    if frames:
        frames[0].save(
            folder / "optimisation.gif",
            save_all=True,
            append_images=frames[1:],
            duration=80,
            loop=0,
        )
    return folder


def run_with_outputs(experiment, out: Path | None, iters: int | None = None, **options) -> dict:
    """Run ``experiment`` (a ``render.inverse.experiments.run_*``) and, if ``out`` is given, write
    its images with frames for the GIF (about 40 of them); the metrics are returned, with
    the output folder under "outputs"."""
    budget = {} if iters is None else {"iters": iters}
    recorder = FrameRecorder(every=max(1, (iters or 500) // 40)) if out else None
    run = experiment(callback=recorder, **budget, **options)
    if out:
        run.metrics["outputs"] = str(write_outputs(run, out, recorder.frames))
    return run.metrics


def run_example(run, description: str, default_iters: int, argv=None, extra=None) -> dict:
    """What each paper-experiment script does: read the shared command line (plus ``extra``
    options, passed on to ``run`` by name), run, write the images, print the metrics as
    JSON."""
    args = command_line(description, default_iters=default_iters, argv=argv, extra=extra)
    options = {name.lstrip("-").replace("-", "_"): None for name in (extra or {})}
    options = {name: getattr(args, name) for name in options}
    metrics = run_with_outputs(
        run, args.out, iters=args.iters, size=args.size, seed=args.seed, quiet=args.quiet,
        **options,
    )  # fmt: skip
    print(json.dumps(metrics, indent=2))
    return metrics


def write_results(out: Path, name: str, result: dict, report: str) -> dict:
    """Write ``out/name.json`` (the result, strict JSON) and ``out/name.md`` (the report),
    print the report, and return the result."""
    from render.inverse.jsonio import write_json

    write_json(out / f"{name}.json", result)
    (out / f"{name}.md").write_text(report)
    print(report)
    return result
