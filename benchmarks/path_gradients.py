"""The path integrator's gradients in the Cornell box against central differences, and what
the missing boundary terms cost.

Run:  python benchmarks/path_gradients.py [--out out/path_gradients] [--quick]
(the committed results in docs/path_tracing/ were made with ``--out docs/path_tracing``)

For each parameter (the light's emission, the red wall's albedo with the wall out of view,
the light's position, an interior vertex of the back wall) and each scene (the empty room,
and the room with its two blocks, which cast soft shadows), over independent seeds:

* our gradient of a fixed random linear functional of the image, ``sum(W * image)`` with
  W = 1 + 0.5 N(0, 1) per pixel and channel (mostly the brightness), one render +
  backward per seed;
* central differences of the same functional, same seed on both sides (common random
  numbers), step ``h`` along a fixed direction.

Both are unbiased estimates of the true derivative *if nothing is missing from ours*; the
table gives their means over seeds with standard errors, and the difference in units of the
combined error. Emission and albedo leave every sampling decision unchanged, so the two
agree seed by seed to rounding. The light's position and the wall's vertex move edges: the
shadows' (secondary visibility) in the room with blocks; where the light is in view, its
outline (primary visibility). The camera's position and the sphere's centre move
silhouettes (primary visibility), the sphere its shadow too. Rows with ``antialias`` =
boundary add primary visibility's boundary term (``render.path.boundary.primary``); what no row
includes is secondary visibility's (shadows, indirect occlusion), and the differences
measure it. The camera looks at the lower part of the room unless ``light_in_view``.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import timing

import minidiff as md
import render
from render.inverse.jsonio import write_json
from render.path import render_path
from render.scene.cornell import cornell_box

SIZE = 20
DEPTH = 4
DIRECTIONS = {
    "emission": np.array([1.0, 0.5, 0.2]),
    "bleeding_albedo": np.array([0.2, 1.0, 0.3]),
    "light_position": np.array([0.3, 0.1, 0.2]),
    "interior_vertex": np.array([0.1, 0.2, 0.5]),
    "camera_position": np.array([0.2, 0.3, -0.4]),
    "sphere_centre": np.array([0.3, 0.1, 0.2]),
}


#: The step's multiple for the parameters that move a primary edge.
LONGER_STEP = {"camera_position": 5.0, "sphere_centre": 5.0}


def scene_for(blocks: bool, light_in_view: bool) -> render.Scene:
    """The room (3 x 3 grid walls, so the back wall has interior vertices), seen whole
    (``light_in_view``) or from a camera that sees neither the light nor the red wall."""
    scene = cornell_box(SIZE, SIZE, blocks=blocks, subdivisions=3)
    if not light_in_view:
        scene.camera = render.Camera(
            (0.45, -0.2, 3.9), (0.45, -0.6, 0.0), (0, 1, 0), 28.0, SIZE, SIZE
        )
    return scene


def parameter(scene: render.Scene, name: str) -> md.Tensor:
    """The tensor varied for ``name`` (for the vertex: the whole vertex array)."""
    return {
        "emission": lambda: scene.objects[5].material.emission,
        "bleeding_albedo": lambda: scene.objects[3].material.albedo,
        "light_position": lambda: scene.objects[5].transform.translation,
        "interior_vertex": lambda: scene.objects[2].vertices,
        "camera_position": lambda: scene.camera.position,
        "sphere_centre": lambda: scene.objects[7].center,
    }[name]()


def step(name: str, value: np.ndarray, h: float) -> np.ndarray:
    """``value`` moved by h along the parameter's direction (for the vertex: vertex 5, an
    interior vertex of the back wall's 4 x 4 grid of vertices)."""
    if name == "interior_vertex":
        out = value.copy()
        out[5] += h * DIRECTIONS[name]
        return out
    return value + h * DIRECTIONS[name]


def one_seed(name, blocks, light_in_view, antialias, weights, seed, spp, h):
    """(our directional derivative, the same-seed central difference) for one seed."""

    def functional(delta, grad):
        scene = scene_for(blocks, light_in_view)
        p = parameter(scene, name)
        p.data = step(name, p.data, delta)
        p.requires_grad = grad
        image = render_path(
            scene, spp=spp, max_depth=DEPTH, seed=seed, rr_depth=100, antialias=antialias
        )
        return (image * md.tensor(weights)).sum(), p

    value, p = functional(0.0, True)
    value.backward()
    ours = float(np.sum(step(name, np.zeros_like(p.grad), 1.0) * p.grad))
    with md.no_grad():
        fd = (functional(h, False)[0].item() - functional(-h, False)[0].item()) / (2 * h)
    return ours, fd


def run(seeds: int, spp: int, h: float) -> list[dict]:
    weights = 1.0 + 0.5 * np.random.default_rng(5).standard_normal((SIZE, SIZE, 3))
    rows = []
    plain = ("emission", "bleeding_albedo", "light_position", "interior_vertex")
    cases = [(n, b, False, False) for n in plain for b in (False, True)]
    cases += [("light_position", b, True, a) for a in (False, "boundary") for b in (False, True)]
    cases += [("camera_position", True, True, a) for a in (False, "boundary")]
    cases += [("sphere_centre", True, False, a) for a in (False, "boundary")]
    for name, blocks, in_view, antialias in cases:
        start = time.perf_counter()
        # Where an outline moves across the pixels' samples (the light in view, the camera,
        # the sphere), a same-seed difference is a count of flipped samples: its noise falls
        # as 1/sqrt(h), so those rows take a longer step (the light's 2.5x: at 5x it would
        # reach the ceiling, 0.01 above it).
        h_case = h * LONGER_STEP.get(name, 2.5 if in_view else 1.0)
        pairs = np.array(
            [
                one_seed(name, blocks, in_view, antialias, weights, s, spp, h_case)
                for s in range(seeds)
            ]
        )
        ours, fd = pairs[:, 0], pairs[:, 1]
        err_ours, err_fd = ours.std(ddof=1) / np.sqrt(seeds), fd.std(ddof=1) / np.sqrt(seeds)
        row = {
            "parameter": name, "blocks": blocks, "light_in_view": in_view,
            "antialias": antialias or "none", "h": h_case,
            "ours": ours.mean(), "ours_error": err_ours, "fd": fd.mean(), "fd_error": err_fd,
            "difference_in_errors": (ours.mean() - fd.mean()) / np.hypot(err_ours, err_fd),
            "missing_fraction": 1.0 - ours.mean() / fd.mean(),
            "max_seed_relative_difference": float(np.max(np.abs(ours - fd)) / np.mean(np.abs(fd))),
            "seconds": time.perf_counter() - start,
        }  # fmt: skip
        rows.append(row)
        print(
            f"{name:16s} blocks={blocks!s:5s} in_view={in_view!s:5s} "
            f"edges={row['antialias']:8s} ours {row['ours']:+.4f} "
            f"± {err_ours:.4f}  FD {row['fd']:+.4f} ± {err_fd:.4f}  "
            f"({row['difference_in_errors']:+.1f} errors, {row['seconds']:.0f} s)",
            flush=True,
        )
    return rows


def markdown(rows: list[dict], seeds: int, spp: int, h: float) -> str:
    lines = [
        f"Cornell box {SIZE}x{SIZE}, max_depth {DEPTH}, {spp} spp per seed, {seeds} seeds, "
        f"central differences with step {h} (where a primary edge moves, longer: 2.5x for "
        "the light in view, 5x for the camera and the sphere), the same seed on both sides.",
        "",
        "| parameter | blocks | light in view | edge term | ours | central differences | "
        "difference (errors) | missing fraction |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['parameter']} | {r['blocks']} | {r['light_in_view']} | {r['antialias']} | "
            f"{r['ours']:+.4f} ± {r['ours_error']:.4f} | {r['fd']:+.4f} ± {r['fd_error']:.4f} | "
            f"{r['difference_in_errors']:+.1f} | {r['missing_fraction']:+.1%} |"
        )
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    parser = timing.make_parser(__doc__, out=Path("out/path_gradients"), quick="2 seeds at 2 spp")
    parser.add_argument("--seeds", type=int, default=48)
    parser.add_argument("--spp", type=int, default=32)
    parser.add_argument("--h", type=float, default=0.02)
    args = parser.parse_args(argv)
    seeds, spp = (2, 2) if args.quick else (args.seeds, args.spp)
    rows = run(seeds, spp, args.h)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "gradients.json", {"seeds": seeds, "spp": spp, "h": args.h, "rows": rows})
    (out / "gradients.md").write_text(markdown(rows, seeds, spp, args.h))
    print(markdown(rows, seeds, spp, args.h))


if __name__ == "__main__":
    main()
