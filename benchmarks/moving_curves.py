"""What the default boundary term costs for one parameter's gradient when only some of its
curves move with that parameter (``render.edges.boundary.curves``: ``CurveKind.moves``).

Run:  python benchmarks/moving_curves.py [--out out/moving_curves] [--quick] [--repeats 15]
(the committed results in docs/edges/ were made with ``--out docs/edges``)

The paper scene at 512x512 (64x64 with ``--quick``), one forward+backward of a weighted
sum of the image (``reuse_visibility=False``) into each of: the light's position (its
shadow borders move; the mesh edges do not), the teapot's albedo (no curve moves), the
teapot's vertices and every parameter (every curve moves). For each, in turns (medians):
``plain`` (no edge terms), ``boundary`` (the default boundary term, 16 interior samples
per mixed pixel) and ``every_kind`` (the same, every curve kind taken to move, as before
``moves``: the points' factors of every kind computed, and the curves looked for whatever
is differentiated). The gradients of ``boundary`` and ``every_kind`` are compared too
(``gradient_difference``: the largest difference over the largest value).

``fits``: the same ``plain`` and ``boundary`` as steps of a fit, with the render cache
(``reuse_visibility=True``, the default): the albedo's (nothing the cache keys on moves:
the visibility and the mixed pixels are found once) and the light position's (the light
set before every call to one of two places 1e-3 apart, each variant's own: its shadows
are traced again at every call); for the light, also ``boundary_hits_not_kept``: the
mixed pixels' candidates' first hits traced anew at every step, as before they were kept.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from pathlib import Path

import numpy as np
import timing

import minidiff as md
import render
import render.renderer
from render.edges import interior, terms
from render.edges.boundary.crossing import SurfaceCrossing
from render.edges.boundary.mesh_edge import MeshEdge
from render.edges.boundary.shadow_border import ShadowBorder
from render.edges.boundary.sphere import SphereCut, SphereOutline

KINDS = (MeshEdge, SurfaceCrossing, SphereOutline, SphereCut, ShadowBorder)
#: Which tensors each workload differentiates.
CHOICES: dict[str, Callable[[render.Scene], list[md.Tensor]]] = {
    "light_position": lambda s: [s.lights[0].position],
    "albedo": lambda s: [s.objects[0].material.albedo],
    "vertices": lambda s: [s.objects[0].vertices],
    "every_parameter": lambda s: s.parameters(),
}


def every_kind_moves(fn: Callable[[], list[np.ndarray]]) -> Callable[[], list[np.ndarray]]:
    """``fn`` run with every curve kind taken to move (each kind's ``moves`` answering True,
    the renderer looking for curves whenever something is differentiated)."""

    def run() -> list[np.ndarray]:
        own = {kind: kind.moves for kind in KINDS}
        own_gate = render.renderer.curves_move
        try:
            for kind in KINDS:
                kind.moves = lambda self, scene: True
            render.renderer.curves_move = lambda scene, world: terms.differentiated(scene)
            return fn()
        finally:
            for kind, moves in own.items():
                kind.moves = moves
            render.renderer.curves_move = own_gate

    return run


def workloads(size: int, choice: str) -> dict[str, Callable[[], list[np.ndarray]]]:
    """The three variants (module docstring) of one parameter choice, each returning the
    gradients."""
    scene = render.paper_scene(size, size)
    for tensor in scene.parameters():
        tensor.requires_grad = False
    chosen = CHOICES[choice](scene)
    for tensor in chosen:
        tensor.requires_grad = True
    weights = np.random.default_rng(3).uniform(0.0, 1.0, (size, size, 3))

    def gradient(antialias) -> Callable[[], list[np.ndarray]]:
        def run() -> list[np.ndarray]:
            for tensor in chosen:
                tensor.grad = None
            image = render.render(scene, antialias=antialias, reuse_visibility=False)
            md.sum(image * weights).backward()
            return [np.array(tensor.grad) for tensor in chosen]

        return run

    boundary = gradient("boundary")
    return {"plain": gradient(False), "boundary": boundary,
            "every_kind": every_kind_moves(boundary)}  # fmt: skip


def measure(size: int, repeats: int) -> dict:
    """Per parameter choice: each variant's median (ms), the ratios to ``plain`` and the
    gradients' difference."""
    out = {}
    for choice in CHOICES:
        fns = workloads(size, choice)
        now, before = fns["boundary"](), fns["every_kind"]()
        scale = max(max(np.abs(g).max() for g in before), 1e-300)
        difference = max(np.abs(a - b).max() for a, b in zip(now, before, strict=True)) / scale
        stats = timing.measure_interleaved(fns, repeats=repeats, warmup=2)
        ms = {name: stats[name]["median_ms"] for name in fns}
        out[choice] = {
            **ms,
            "boundary_over_plain": ms["boundary"] / ms["plain"],
            "every_kind_over_plain": ms["every_kind"] / ms["plain"],
            "gradient_difference": float(difference),
        }
    return out


def _fit_step(scene, tensor, weights, places, antialias) -> None:
    """One forward+backward into ``tensor``, first set to the next of ``places`` (None:
    not moved)."""
    tensor.grad = None
    if places is not None:
        with md.no_grad():
            tensor.data[...] = next(places)
    md.sum(render.render(scene, antialias=antialias) * weights).backward()


def fits(size: int, repeats: int) -> dict:
    """``fits`` of the module docstring: per choice, each variant's median (ms) and the
    ratio."""
    out = {}
    for choice in ("albedo", "light_position"):
        scene = render.paper_scene(size, size)
        (tensor,) = CHOICES[choice](scene)
        tensor.requires_grad = True
        weights = np.random.default_rng(3).uniform(0.0, 1.0, (size, size, 3))
        base = np.array(tensor.data)
        fns = {}
        for k, (name, antialias) in enumerate((("plain", False), ("boundary", "boundary"))):
            # Each variant's calls alternate between two places of the light of its own,
            # so that no call finds the light where the call before it (of either variant)
            # left it: the render cache serves nothing that a fit's step would recompute.
            # (With one sequence of steps taken in turns, every boundary call met the light
            # where the boundary call before had: its mixed pixels were served, 5.03x.)
            places = None
            if choice == "light_position":
                offsets = np.tile([1e-3 * (2 * k + 1), 1e-3 * (2 * k + 2)], 10_000)
                places = (base + offset for offset in offsets)
            fns[name] = partial(_fit_step, scene, tensor, weights, places, antialias)
        if choice == "light_position":  # the candidates' first hits traced at every step
            offsets = np.tile([5e-3, 6e-3], 10_000)
            step = partial(_fit_step, scene, tensor, weights, (base + o for o in offsets))
            fns["boundary_hits_not_kept"] = partial(hits_not_kept, partial(step, "boundary"))
        stats = timing.measure_interleaved(fns, repeats=repeats, warmup=2)
        ms = {name: stats[name]["median_ms"] for name in fns}
        out[choice] = {**ms, "boundary_over_plain": ms["boundary"] / ms["plain"]}
        if "boundary_hits_not_kept" in ms:
            out[choice]["hits_not_kept_over_plain"] = ms["boundary_hits_not_kept"] / ms["plain"]
    return out


def hits_not_kept(fn: Callable[[], None]) -> None:
    """``fn()`` with the mixed pixels' candidates' first hits traced anew at every render
    (``interior._kept_first_hits`` without its cache: as before it kept them)."""
    kept = interior._kept_first_hits
    try:
        interior._kept_first_hits = lambda scene, vis, cache, *rest: kept(scene, vis, None, *rest)
        fn()
    finally:
        interior._kept_first_hits = kept


def report(result: dict) -> dict:
    """The report section (``timing.report_section``) of ``main``'s result."""
    rows = []
    for choice, r in result["choices"].items():
        rows.append(timing.target_row(
            f"{choice}: boundary f+b / plain f+b (every kind moving: "
            f"{r['every_kind_over_plain']:.2f}x; gradients apart by "
            f"{r['gradient_difference']:.1e})",
            f"{r['boundary_over_plain']:.2f}x", r["boundary_over_plain"], 3.0, "at most 3x",
        ))  # fmt: skip
    for choice, r in result["fits"].items():
        before = r.get("hits_not_kept_over_plain")
        note = "" if before is None else f" (first hits not kept: {before:.2f}x)"
        rows.append(timing.target_row(
            f"{choice}, a fit's step (the render cache): boundary f+b / plain f+b{note}",
            f"{r['boundary_over_plain']:.2f}x", r["boundary_over_plain"], 3.0, "at most 3x",
        ))  # fmt: skip
    title = f"The boundary term when only some curves move, {result['size']}x{result['size']}"
    return timing.report_section(title, rows, [], [])


def main(argv=None) -> None:
    parser = timing.make_parser(__doc__, Path("out/moving_curves"), quick="64x64, 1 repeat")
    parser.add_argument("--repeats", type=int, default=15, help="timed calls (default 15)")
    args = parser.parse_args(argv)
    size = 64 if args.quick else 512
    repeats = timing.QUICK_REPEATS if args.quick else args.repeats
    result = {"size": size, "choices": measure(size, repeats), "fits": fits(size, repeats)}
    result["report"] = report(result)
    timing.print_report(result["report"], timing.machine())
    timing.write_json(args.out, "moving_curves", result)


if __name__ == "__main__":
    main()
