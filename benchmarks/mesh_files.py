"""The boundary term's gradients on mesh files as another program wrote them (RayTracer.jl's
OBJ files in tests/data/raytracerjl): against finite differences of supersampled renders.

Run:  python benchmarks/mesh_files.py [--out out/mesh_files] [--quick]
(the committed results in docs/edges/ were made with ``--out docs/edges``)

Each file's meshes (``render.load_mesh``: one mesh per material, flat-shaded, every face
with its own vertices where Blender wrote them so) are scaled together to a unit box,
lifted by 0.5 over a grey floor, lit by a point light from above and seen at 48x48 with
shadows, flat-shaded and (the tree and the teapot) smooth-shaded with the file's vertex
normals; the sign also with 16 samples per pixel, and with its textures replaced by their
materials' plain albedo. For a translation of all the file's meshes along x, y and z: the
derivative of a fixed random weighting of the image with ``antialias="boundary"`` (the
mean of 64 gradients over the window s in [-h, h], h = 0.02, whose integral is L(h) -
L(-h)), against that window's
central difference of 1,024-spp jittered renders (``render.inverse.reference``), 4 seeds:
their mean and its standard error. ``z``: the difference over that standard error.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import timing

import minidiff as md
import render
from render.inverse.reference import window_difference, window_mean_gradient
from render.scene.cornell import grid_quad

MESHES = Path(__file__).resolve().parents[1] / "tests" / "data" / "raytracerjl" / "meshes"
#: (name, file, textures kept, our samples per pixel, smooth: shaded with the file's normals)
CASES = (
    ("tree", "tree.obj", True, 1, False),
    ("tree_smooth", "tree.obj", True, 1, True),
    ("teapot", "teapot_rtjl.obj", True, 1, False),
    ("teapot_smooth", "teapot_rtjl.obj", True, 1, True),
    ("sign", "sign_yield.obj", True, 1, False),
    ("sign_16_spp", "sign_yield.obj", True, 16, False),
    ("sign_untextured", "sign_yield.obj", False, 1, False),
)


def scene_maker(file: str, textured: bool, axis: int, size: int, smooth: bool = False):
    """``window_difference``'s scene maker: the file's meshes (module docstring) moved by s
    along ``axis``, smooth-shaded with the file's vertex normals if ``smooth``; returns
    (scene, the translation, its direction)."""
    meshes = render.load_mesh(MESHES / file)
    everything = np.concatenate([np.asarray(m.vertices.data) for m in meshes])
    lo, hi = everything.min(axis=0), everything.max(axis=0)
    direction = np.eye(3)[axis]

    def make(s: float):
        translation = md.tensor(direction * s)
        objects = [render.Mesh(*grid_quad((0, -0.55, 0), (2, 0, 0), (0, 0, -2)),
                               render.Material((0.6, 0.6, 0.6)))]  # fmt: skip
        for mesh in meshes:
            vertices = (np.asarray(mesh.vertices.data) - (lo + hi) / 2) / np.max(hi - lo)
            material = mesh.material if textured else render.Material(mesh.material.albedo.data)
            moved = render.Mesh(vertices + [0.0, 0.5, 0.0], np.asarray(mesh.faces), material,
                                uvs=mesh.uvs if textured else None, normals=mesh.normals,
                                smooth=smooth and mesh.normals is not None)  # fmt: skip
            moved.transform = render.Transform(translation=translation)
            objects.append(moved)
        camera = render.Camera((0.9, 0.8, 1.6), (0, 0, 0), (0, 1, 0), 40.0, size, size)
        light = render.PointLight((0.8, 2.0, 1.0), 6.0)
        return render.Scene(objects, [light], camera), translation, direction

    return make


def case(
    file: str, textured: bool, ours_spp: int, smooth: bool, size: int, spp: int, seeds: int,
    points: int,
) -> list[dict]:  # fmt: skip
    """Per axis: the supersampled difference (mean, standard error) and ours (``ours_spp``
    samples per pixel)."""
    weights = np.random.default_rng(1).uniform(0.0, 1.0, (size, size, 3))
    rows = []
    for axis in range(3):
        make = scene_maker(file, textured, axis, size, smooth)
        truth = [window_difference(make, weights, 0.02, spp, seed) for seed in range(seeds)]
        ours = window_mean_gradient(make, weights, 0.02, "boundary", points, ours_spp)
        mean, error = float(np.mean(truth)), float(np.std(truth, ddof=1) / np.sqrt(seeds))
        off = ours - mean
        rows.append({"axis": "xyz"[axis], "truth": mean, "truth_error": error, "ours": ours,
                     "relative": off / abs(mean), "z": off / error})  # fmt: skip
    return rows


def main(argv=None) -> None:
    parser = timing.make_parser(__doc__, Path("out/mesh_files"), quick="24x24, 2 seeds of 64")
    args = parser.parse_args(argv)
    size, spp, seeds, points = (24, 64, 2, 8) if args.quick else (48, 1024, 4, 64)
    results = {name: case(file, textured, ours_spp, smooth, size, spp, seeds, points)
               for name, file, textured, ours_spp, smooth in CASES}  # fmt: skip
    rows = [timing.row(f"{name}, {r['axis']}: ours / supersampled - 1",
                       f"{100 * r['relative']:+.1f} % (z {r['z']:+.1f})")
            for name, found in results.items() for r in found]  # fmt: skip
    report = timing.report_section(f"Mesh files, {size}x{size}", rows, [], [])
    timing.print_report(report, timing.machine())
    timing.write_json(args.out, "mesh_files", {"size": size, "spp": spp, "seeds": seeds,
                                               "points": points, "cases": results,
                                               "report": report})  # fmt: skip


if __name__ == "__main__":
    main()
