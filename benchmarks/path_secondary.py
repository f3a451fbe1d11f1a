"""Secondary visibility's gradients (issue 44's targets): the path integrator's derivatives
of shadows and indirect occlusion against central differences, and what the boundary terms
cost.

Run:  python benchmarks/path_secondary.py [--out out/path_secondary] [--quick]
          [--seeds N] [--spp N] [--cases light_position,...] [--antialias primary,boundary]
          [--repeats N]
(the committed results in docs/path_tracing/secondary/ are made with
``--out docs/path_tracing/secondary``)

The Cornell box with its blocks (``render.scene.cornell``: 0 floor, 1 ceiling, 2 back wall,
3 left, 4 right, 5 the area light, 6 the tall box, 7 the sphere), ``SIZE`` x ``SIZE``
pixels, no Russian roulette. The cases, each a parameter moved along a fixed direction:

1. ``light_position``: the area light's translation, the camera of
   ``path_gradients.scene_for(light_in_view=False)`` (it sees the floor, the blocks and
   their soft shadows, not the light);
2. ``sphere_centre``: the sphere's centre, moved sideways (it touches the floor: moving it
   down would push it through), the same camera (its silhouette and its shadow move);
3. ``box_corner``: a top corner of the tall box (the box's sides are separate quads, so the
   corner is three vertices at one place, moved together; a bottom corner would leave the
   floor, a contact no boundary term handles), the same camera;
4. ``light_scale``: the area light's size (its ``Transform.scale``, about the light's
   centre so that it stays under the ceiling), the same camera;
5. ``point_light_bounce``: the room without its area light, lit by a point light under a
   plate that keeps its light off the whole ceiling, seen by a camera that looks straight up
   and sees the ceiling only: the shadows' borders (the plate's on the walls, the blocks' on
   the floor) reach the image only after one diffuse bounce; max_depth 3 (camera, ceiling,
   the bounce, the light).

For each case, over independent seeds: our directional derivative of the fixed random linear
functional ``sum(W * image)`` (W = 1 + 0.5 N(0, 1) per pixel and channel, as in
``path_gradients.py``), one render + backward per seed and per ``antialias`` mode
("primary": the camera's silhouettes only; "boundary": primary and secondary visibility's
boundary terms), against the central difference of the same functional with the same seed on
both sides (common random numbers; one per seed, shared by the modes). Where a shadow's
border crosses the samples, a same-seed difference counts flipped samples: its noise falls
as 1 / sqrt(h), so each case has its own step ``h``, long enough for the difference not to be
dominated by that noise and short enough for its O(h^2) bias to be small (the point light's,
0.2 under the plate, is the most curved: its difference is -106.9 +- 0.9 at h = 0.02, -103.8 at
0.05 and -98.8 at 0.1, 128 seeds each; it takes 0.02). The table gives the
means over seeds with standard errors and ``ours / FD - 1`` with its standard error (from the
per-seed spread of ``ours - r FD``, r the ratio of the means: the seeds pair the two).
Target (issue 44): within 5 %; "met" when the 95 % interval (2 standard errors) lies inside
+-5 %, "missed" when it lies outside, "open" otherwise.

Cost: per case, the seconds of one render + backward with ``antialias`` False, "primary"
and "boundary" at the same spp, timed in turns (medians; the machine is shared, so these are
indicative).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numba
import numpy as np
import timing
from bench_path_mitsuba import _commit
from path_gradients import scene_for

import minidiff as md
import render
from render.inverse.jsonio import write_json
from render.path import render_path
from render.scene.cornell import LIGHT_DROP, WHITE, cornell_box, grid_quad
from render.scene.scene import Material, Mesh

#: Image side: path_gradients.scene_for's (its camera is the one cases 1 to 4 use).
SIZE = 20
#: Seed of the functional's weights (path_gradients.py's).
WEIGHT_SEED = 5
#: No Russian roulette: every path runs to max_depth.
NO_ROULETTE = 100
#: Index of the area light and of the tall box in the Cornell box's objects.
LIGHT, BOX = 5, 6
#: Case 5's point light, and the plate 0.2 above it that keeps its light off the ceiling
#: (its shadow's border is at y ~ 0.27 on the side walls, ~ 0.67 on the back wall).
POINT_LIGHT = (0.0, -0.4, 0.6)
POINT_INTENSITY = 3.0
PLATE_CENTRE, PLATE_HALF_SIDE = (0.0, -0.2, 0.6), 0.3


@dataclass(frozen=True)
class Case:
    """One gradient compared: a scene (a fresh one per call), the parameter tensor in it,
    the tangent it moves along (the parameter's shape) and the central differences' step."""

    name: str
    scene: Callable[[], render.Scene]
    parameter: Callable[[render.Scene], md.Tensor]
    tangent: Callable[[np.ndarray], np.ndarray]
    h: float
    max_depth: int
    description: str
    #: Seeds as a multiple of the run's ``--seeds`` (for a case whose gradient is noisier).
    seed_multiple: int = 1


def room() -> render.Scene:
    """The Cornell box with its blocks, seen from a camera that sees the floor, the blocks
    and their shadows but not the light (``path_gradients.scene_for``); the light scales
    about its own centre."""
    scene = scene_for(blocks=True, light_in_view=False)
    scene.objects[LIGHT].transform.pivot.data = np.array([0.0, 1.0 - LIGHT_DROP, 0.0])
    return scene


def point_lit_room() -> render.Scene:
    """The Cornell box with its blocks and without its area light, lit by a point light
    under a white square plate that shades the whole ceiling: the ceiling is lit only by
    what the floor, the blocks and the walls below the plate's shadow reflect. A camera
    above the blocks looks straight up and sees the ceiling only, so the shadows' borders
    (the plate's on the walls, the blocks' on the floor) reach the image only after one
    diffuse bounce."""
    box = cornell_box(SIZE, SIZE, blocks=True, subdivisions=1)
    objects = [o for i, o in enumerate(box.objects) if i != LIGHT]
    x, z = np.eye(3)[0], np.eye(3)[2]
    vertices, faces = grid_quad(PLATE_CENTRE, PLATE_HALF_SIDE * x, PLATE_HALF_SIDE * z)
    objects.append(Mesh(vertices, faces, Material(WHITE)))
    light = render.PointLight(POINT_LIGHT, POINT_INTENSITY)
    camera = render.Camera((0.0, 0.3, 0.2), (0.0, 1.0, 0.2), (0.0, 0.0, -1.0), 90.0, SIZE, SIZE)
    return render.Scene(objects, [light], camera)


def along(direction) -> Callable[[np.ndarray], np.ndarray]:
    """The tangent ``direction`` (the same for every value)."""
    return lambda value: np.broadcast_to(np.asarray(direction, float), np.shape(value)).copy()


def top_corner(vertices: np.ndarray) -> np.ndarray:
    """The tangent moving every copy of the tall box's top corner nearest the camera's
    side (largest y, then largest x + z) along (0.2, 0.3, 0.1), the rest fixed:
    (V, 3)."""
    top = vertices[:, 1] == vertices[:, 1].max()
    key = np.where(top, vertices[:, 0] + vertices[:, 2], -np.inf)
    corner = vertices[np.argmax(key)]
    tangent = np.zeros_like(vertices)
    tangent[np.all(vertices == corner, axis=1)] = (0.2, 0.3, 0.1)
    return tangent


def _translation(scene: render.Scene) -> md.Tensor:
    return scene.objects[LIGHT].transform.translation


CASES = {
    case.name: case
    for case in (
        Case("light_position", room, _translation, along((0.3, 0.0, 0.2)), 0.05, 4,
             "area light's position, light out of view"),
        Case("sphere_centre", room, lambda s: s.objects[7].center, along((0.3, 0.0, 1.0)),
             0.05, 4, "sphere's centre (silhouette and shadow)", seed_multiple=3),
        Case("box_corner", room, lambda s: s.objects[BOX].vertices, top_corner, 0.1, 4,
             "tall box's top corner (silhouette and shadow)"),
        Case("light_scale", room, lambda s: s.objects[LIGHT].transform.scale, along(1.0),
             0.05, 4, "area light's size (scale), light out of view"),
        Case("point_light_bounce", point_lit_room, lambda s: s.lights[0].position,
             along((0.2, 1.0, 0.3)), 0.02, 3,
             "point light's position, its shadows seen after one bounce", seed_multiple=2),
    )
}  # fmt: skip


def weights() -> np.ndarray:
    """The functional's fixed weights W (SIZE, SIZE, 3)."""
    return 1.0 + 0.5 * np.random.default_rng(WEIGHT_SEED).standard_normal((SIZE, SIZE, 3))


def functional(
    case: Case,
    w: np.ndarray,
    seed: int,
    spp: int,
    delta: float = 0.0,
    antialias: bool | str = False,
) -> tuple[md.Tensor, md.Tensor, np.ndarray]:
    """sum(W * image) of the case's scene with its parameter moved by ``delta`` along the
    tangent, the parameter tensor and the tangent. Differentiable in the parameter when
    called outside ``md.no_grad``."""  # fmt: skip
    scene = case.scene()
    p = case.parameter(scene)
    tangent = case.tangent(np.asarray(p.data))
    p.data = p.data + delta * tangent
    p.requires_grad = md.is_grad_enabled()
    image = render_path(scene, spp=spp, max_depth=case.max_depth, seed=seed,
                        rr_depth=NO_ROULETTE, antialias=antialias)  # fmt: skip
    return (image * md.tensor(w)).sum(), p, tangent


def derivative(case: Case, w: np.ndarray, seed: int, spp: int, antialias: bool | str) -> float:
    """Our directional derivative of the functional: one render + backward."""
    value, p, tangent = functional(case, w, seed, spp, antialias=antialias)
    value.backward()
    return float(np.sum(tangent * p.grad))


def central_difference(case: Case, w: np.ndarray, seed: int, spp: int) -> float:
    """The same-seed central difference of the functional with the case's step."""
    with md.no_grad():
        plus = functional(case, w, seed, spp, case.h)[0].item()
        minus = functional(case, w, seed, spp, -case.h)[0].item()
    return (plus - minus) / (2.0 * case.h)


def ratio(ours: np.ndarray, fd: np.ndarray) -> tuple[float, float]:
    """ours / FD - 1 of the means over seeds and its standard error, from the per-seed
    spread of ours - r FD (r the ratio of the means; the same seeds pair the two)."""
    r = ours.mean() / fd.mean()
    return r - 1.0, float((ours - r * fd).std(ddof=1) / np.sqrt(len(ours)) / abs(fd.mean()))


def status(relative: float, error: float, target: float = 0.05) -> str:
    """ "met" (the 95 % interval inside +-target), "missed" (outside) or "open"."""
    if abs(relative) + 2 * error <= target:
        return "met"
    return "missed" if abs(relative) - 2 * error > target else "open"


def mean_error(x: np.ndarray) -> tuple[float, float]:
    """The mean of per-seed values and its standard error."""
    return float(x.mean()), float(x.std(ddof=1) / np.sqrt(len(x)))


def compare(case: Case, seeds: int, spp: int, modes: list) -> dict:
    """Per seed the central difference and our derivative in every mode; their summary."""
    w = weights()
    seeds *= case.seed_multiple
    start = time.perf_counter()
    fd = np.array([central_difference(case, w, s, spp) for s in range(seeds)])
    ours = {m: np.array([derivative(case, w, s, spp, m) for s in range(seeds)]) for m in modes}
    fd_mean, fd_error = mean_error(fd)
    row = {"case": case.name, "description": case.description, "h": case.h,
           "tangent": case.tangent(np.asarray(case.parameter(case.scene()).data)),
           "seeds": seeds, "max_depth": case.max_depth, "fd": fd_mean, "fd_error": fd_error,
           "fd_per_seed": fd, "modes": {}}  # fmt: skip
    for mode, values in ours.items():
        rel, rel_error = ratio(values, fd)
        mean, error = mean_error(values)
        row["modes"][mode] = {"ours": mean, "ours_error": error, "relative": rel,
                              "relative_error": rel_error, "status": status(rel, rel_error),
                              "per_seed": values}  # fmt: skip
        print(
            f"{case.name:18s} {mode!s:9s} ours {mean:+.4f} ± {error:.4f}  FD {fd_mean:+.4f} "
            f"± {fd_error:.4f}  ours/FD - 1 = {rel:+.1%} ± {rel_error:.1%}",
            flush=True,
        )
    row["seconds"] = time.perf_counter() - start
    return row


def cost(case: Case, spp: int, modes: list, repeats: int) -> dict:
    """Median seconds of one render + backward per mode (False and ``modes``), in turns."""
    w = weights()
    fns = {str(m): (lambda m=m: derivative(case, w, 0, spp, m)) for m in [False, *modes]}
    times = timing.measure_interleaved(fns, repeats, warmup=1)
    return {mode: t["median_ms"] / 1e3 for mode, t in times.items()}


def markdown(result: dict) -> str:
    """The tables: gradients against central differences, and the cost."""
    modes = result["modes"]
    lines = quick_notice(result) + [
        f"Cornell box with its blocks, {SIZE}x{SIZE}, {result['spp']} spp per seed, "
        f"{result['seeds']} seeds (a multiple for a noisier case), no Russian roulette; "
        "central differences (FD) with the same seed on both sides, step h per case. "
        "ours / FD - 1 with its standard error; target within 5 % (met: the 95 % interval "
        f"inside +-5 %). Commit {result['commit']}, {result['numba_threads']} Numba "
        f"thread(s), {result['seconds']:.0f} s in all.",
        "",
        "| case | seeds | max_depth | h | FD | antialias | ours | ours / FD - 1 | target |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in result["rows"]:
        for mode in modes:
            m = r["modes"][mode]
            lines.append(
                f"| {r['case']}: {r['description']} | {r['seeds']} | {r['max_depth']} | {r['h']} | "
                f"{r['fd']:+.4f} ± {r['fd_error']:.4f} | {mode} | "
                f"{m['ours']:+.4f} ± {m['ours_error']:.4f} | "
                f"{m['relative']:+.1%} ± {m['relative_error']:.1%} | {m['status']} |"
            )
    names = ["False", *modes]
    lines += [
        "",
        f"Cost: seconds of one render + backward at {result['spp']} spp (medians of "
        f"{result['repeats']} in turns, shared machine: indicative).",
        "",
        "| case | " + " | ".join(f"antialias={n}" for n in names) + " | "
        + " | ".join(f"{n} / False" for n in modes) + " |",
        "|---|" + "---|" * (2 * len(names) - 1),
    ]  # fmt: skip
    for r in result["rows"]:
        c = r["cost"]
        lines.append(
            f"| {r['case']} | " + " | ".join(f"{c[n]:.3f}" for n in names) + " | "
            + " | ".join(f"{c[n] / c['False']:.2f}" for n in modes) + " |"
        )  # fmt: skip
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> dict:
    parser = timing.make_parser(
        __doc__, out=Path("out/path_secondary"), quick="2 seeds at 1 spp, 1 timed call"
    )
    parser.add_argument("--seeds", type=int, default=64)
    parser.add_argument("--spp", type=int, default=32)
    parser.add_argument("--repeats", type=int, default=5, help="timed calls per mode")
    parser.add_argument("--cases", default=",".join(CASES), help="comma-separated")
    parser.add_argument("--antialias", default="primary,boundary",
                        help="the modes compared, comma-separated")  # fmt: skip
    args = parser.parse_args(argv)
    seeds, spp, repeats = (2, 1, 1) if args.quick else (args.seeds, args.spp, args.repeats)
    modes = args.antialias.split(",")
    start = time.perf_counter()
    rows = []
    for name in args.cases.split(","):
        row = compare(CASES[name], seeds, spp, modes)
        row["cost"] = cost(CASES[name], spp, modes, repeats)
        rows.append(row)
    result = {"quick": args.quick, "size": SIZE, "seeds": seeds, "spp": spp,
              "repeats": repeats, "modes": modes, "rows": rows}  # fmt: skip
    result["numba_threads"] = numba.get_num_threads()
    result["commit"] = _commit(str(timing.ROOT))  # the code measured
    result["seconds"] = time.perf_counter() - start
    write_results(Path(args.out), "secondary", result, markdown(result))
    return result


def write_results(out: Path, stem: str, result: dict, text: str) -> None:
    """``result`` to OUT/stem.json and the tables ``text`` to OUT/stem.md; print them."""
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / f"{stem}.json", result)
    (out / f"{stem}.md").write_text(text)
    print(text)
    print(f"wrote {out / stem}.json and .md: {result['seconds']:.0f} s")


def quick_notice(result: dict) -> list[str]:
    """The warning that opens a --quick run's tables, or nothing."""
    return ["**A --quick smoke run: too few samples to judge anything by.**", ""] * result["quick"]


if __name__ == "__main__":
    main()
