"""How far the boundary term's and the pixel pairs' gradients move when one surface is
written as several meshes whose seams are not exact (``render.scene.surgery``).

Run:  python benchmarks/seams.py [--out out/seams] [--quick] [--boxes 24]
(the committed results in docs/edges/ were made with ``--out docs/edges``)

Each case is a box (0.3 x 0.2 x 0.24) with 0-4 of its faces split at T-junctions, its
faces dealt at random to two or three meshes, over a floor (3 x 3) under a point light,
seen at 32 x 32 with shadows; the last mesh is then rounded to float32 (``float32``) or
has its positions moved by up to ``distance`` in random directions (``moved``: 4e-6 and
1e-4, inside the welding of seams, ``render.trace.topology.seam_reach``: 4e-6 of the
meshes' size, 1.7e-5 here, or 1e-3 of the open edges at a vertex, 5e-5 to 3e-4 here;
1e-3, outside it: a crack a hundredth of a pixel wide). The error
of a case is the largest difference between its gradients (the light's position and the
meshes' translation, of a fixed random weighting of the image) and those of the box as
one mesh, over the largest of the latter.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import timing

import render
from render.scene.cornell import box_mesh
from render.scene.surgery import (
    in_meshes,
    light_and_translation,
    moved_apart,
    through_float32,
    with_t_junctions,
)

SIZE = 32
GREY = render.Material((0.6, 0.6, 0.6))

#: How far ``moved_apart`` moves the positions: inside and outside the welding of seams.
DISTANCES = (4e-6, 1e-4, 1e-3)
#: The perturbations of the last mesh: name -> (mesh, rng) -> mesh.
CASES = {
    "float32": lambda mesh, rng: through_float32(mesh),
    **{f"moved_{d:.0e}": lambda mesh, rng, d=d: moved_apart(mesh, d, rng) for d in DISTANCES},
}


def gradients(meshes: list[render.Mesh], antialias) -> np.ndarray:
    """The light's position gradient and the meshes' translation gradient of a fixed
    random weighting of the image (SIZE x SIZE, shadows): ``surgery.light_and_translation``."""
    return light_and_translation(
        meshes, lambda scene: render.render(scene, antialias=antialias, interior_samples=1), SIZE
    )


def case_errors(boxes: int) -> dict:
    """Per perturbation and per way of antialiasing, the errors of ``boxes`` cases."""
    out = {name: {"boundary": [], "pairs": []} for name in CASES}
    for seed in range(boxes):
        rng = np.random.default_rng(seed)
        picks = [(int(rng.integers(0, 12)), float(rng.uniform(0.2, 0.8)))
                 for _ in range(rng.integers(0, 5))]  # fmt: skip
        box = with_t_junctions(box_mesh((0.1, 0.6, 0.0), (0.15, 0.1, 0.12), GREY), picks)
        owner = rng.integers(0, 3, len(box.faces))
        owner[:2] = [0, 1]  # two meshes at least
        meshes = in_meshes(box, owner.tolist(), bool(rng.integers(0, 2)))
        for antialias, key in (("boundary", "boundary"), (True, "pairs")):
            one = gradients([box], antialias)
            for name, perturb in CASES.items():
                apart = [*meshes[:-1], perturb(meshes[-1], np.random.default_rng(seed))]
                many = gradients(apart, antialias)
                out[name][key].append(float(np.abs(many - one).max() / np.abs(one).max()))
        print(seed, {n: {k: f"{v[-1]:.1e}" for k, v in e.items()} for n, e in out.items()},
              flush=True)  # fmt: skip
    return out


def summary(errors: dict) -> dict:
    """Per perturbation and antialiasing: the largest error, the median, and how many
    cases are off by more than 1e-3 and by more than 1e-2."""
    return {
        name: {
            key: {
                "max": max(v),
                "median": float(np.median(v)),
                "above_1e-3": sum(x > 1e-3 for x in v),
                "above_1e-2": sum(x > 1e-2 for x in v),
                "cases": len(v),
            }
            for key, v in per.items()
        }
        for name, per in errors.items()
    }


def main(argv=None) -> None:
    parser = timing.make_parser(__doc__, Path("out/seams"), quick="two boxes")
    parser.add_argument("--boxes", type=int, default=24, help="boxes (default 24)")
    args = parser.parse_args(argv)
    errors = case_errors(2 if args.quick else args.boxes)
    boxes = len(errors["float32"]["boundary"])
    result = {"size": SIZE, "boxes": boxes, "distances": list(DISTANCES)}
    result.update(errors=errors, summary=summary(errors))
    print(result["summary"])
    timing.write_json(args.out, "seams", result)


if __name__ == "__main__":
    main()
