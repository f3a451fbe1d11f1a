"""Our BVH against Embree 4 (issue 58): closest hits and any-hits on one thread, the build,
one thread against two, and the tree's memory.

Run:  python benchmarks/bench_embree.py [--out out/bench_embree] [--quick] [--repeats 7]
          [--embree-python .venv-mitsuba/bin/python]
(``docs/benchmarks/embree/bench_embree.json`` is this script's output; ``--out
docs/benchmarks/embree`` writes it there)

Embree is not a dependency of this project. Install embreex (Embree 4.4's ray queries) in
a virtualenv of its own, e.g.

    python -m venv .venv-mitsuba
    .venv-mitsuba/bin/pip install embreex==4.4.0.post1 numpy

Its side runs there (``benchmarks/embree_rays.py``: numpy and embreex only); without it
the script measures ours alone and says so.

**The scenes.** A bumpy sphere (``bench_refit.bumpy_sphere``) of 81,920 or 1,310,720
triangles inside a closed room (a cube of side 8, 12 triangles). **The rays**, the same
float64 numbers handed to both (Embree takes them as float32):

* ``camera``: closest hits of 512 x 512 pinhole rays from inside the room at the sphere
  (coherent);
* ``random``: closest hits of 244,000 rays from random points of the room, away from the
  sphere, in random directions (incoherent);
* ``shadow``: any-hits from the camera rays' hit points (0.1 % back along the ray) to a
  point under the ceiling, t in (0, 1);
* ``segments``: any-hits of the random rays over t in (0, 1) (|d| about 1.6: incoherent,
  about half blocked);
* ``shadow_blocked``, ``shadow_open``: the shadow rays that something blocks and those it
  does not (our answers; Embree's are the same), timed apart: where the any-hit's time
  goes. A blocked ray stops at its first hit, often just past its start; an open one must
  visit every box it crosses.

Each side runs in its own fresh process on one thread (ours: ``NUMBA_NUM_THREADS=1``);
the times are medians of ``--repeats``. Ours also on two threads, on the camera and random
rays together (506,144 rays): the scaling target. The answers are compared: the primitive
ids of the closest hits (Embree computes in float32, so a ray that grazes an edge may take
the neighbour) and the occluded flags.
"""

from __future__ import annotations

import json
import os
import subprocess
import tempfile
from pathlib import Path

import numpy as np
import timing
from bench_refit import bumpy_sphere

#: The room around the sphere: a cube of this half side.
ROOM = 4.0
#: (n_theta, n_phi) of the bumpy spheres: 81,920 and 1,310,720 triangles.
SIZES = {"82k": (128, 320), "1.3M": (512, 1280)}
QUICK_SIZES = {"2k": (32, 32)}


def room() -> np.ndarray:
    """(12, 3, 3) triangles of the cube [-ROOM, ROOM]^3."""
    corners = ROOM * np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    tris = [(corners[a], corners[b], corners[c]) for q in quads for a, b, c in
            ((q[0], q[1], q[2]), (q[0], q[2], q[3]))]  # fmt: skip
    return np.array(tris)


def cases(triangles: np.ndarray, side: int, n_random: int) -> dict[str, dict]:
    """The rays of the module docstring: name -> origins, directions (N, 3), far (N,) and
    query ("closest" or "any"). The shadow rays start at our closest hits of the camera
    rays."""
    from render.trace.accel import Accelerator

    rng = np.random.default_rng(0)
    eye = np.array([0.3, 0.4, 3.5])
    x = (np.arange(side) + 0.5) / side * 2 - 1
    sx, sy = np.meshgrid(0.6 * x, -0.6 * x)
    camera_d = np.stack([sx, sy, -np.ones_like(sx)], -1).reshape(-1, 3)
    camera_o = np.broadcast_to(eye, camera_d.shape).copy()
    random_o = rng.uniform(-0.9 * ROOM, 0.9 * ROOM, (n_random, 3))
    near = np.linalg.norm(random_o, axis=1) < 1.3
    random_o[near] *= 1.3 / np.linalg.norm(random_o[near], axis=1, keepdims=True) + 0.5
    random_d = rng.normal(size=(n_random, 3))
    accel = Accelerator(triangles)
    _, t, _, _ = accel.closest_hit(camera_o, camera_d)
    points = camera_o + 0.999 * t[:, None] * camera_d
    light = np.array([0.5, 0.9 * ROOM, 0.5])
    inf = np.full(len(camera_o), np.inf)
    blocked = accel.occluded(points, light - points, np.ones(len(points)), tmin=0.0)
    split = {
        f"shadow_{name}": {"origins": points[rows], "directions": light - points[rows],
                           "far": np.ones(len(rows)), "query": "any", "part_of": "shadow"}
        for name, rows in (("blocked", np.flatnonzero(blocked)), ("open", np.flatnonzero(~blocked)))
    }  # fmt: skip
    return {
        "camera": {"origins": camera_o, "directions": camera_d, "far": inf, "query": "closest"},
        "random": {"origins": random_o, "directions": random_d, "far": np.full(n_random, np.inf),
                   "query": "closest"},
        "shadow": {"origins": points, "directions": light - points, "far": np.ones(len(points)),
                   "query": "any"},
        "segments": {"origins": random_o, "directions": random_d, "far": np.ones(n_random),
                     "query": "any"},
        **split,
    }  # fmt: skip


def ours(cases_path: str, repeats: int) -> dict:
    """Our side, in its own process: the build, each case, the answers and the memory."""
    from render.trace.accel import Accelerator

    data = np.load(cases_path)
    triangles = data["triangles"]
    build = timing.measure(lambda: Accelerator(triangles), repeats)
    accel = Accelerator(triangles)
    result = {"build_ms": build["median_ms"], "cases": {}, "bytes_per_triangle": memory(accel)}
    for case in data["cases"]:
        o, d, far = (data[f"{case}_{k}"] for k in ("origins", "directions", "far"))
        if str(data[f"{case}_query"]) == "closest":

            def query(o=o, d=d):
                return accel.closest_hit(o, d)[0]
        else:

            def query(o=o, d=d, far=far):
                return accel.occluded(o, d, far, tmin=0.0)

        result["cases"][str(case)] = {"ms": timing.measure(query, repeats)["median_ms"],
                                      "answers": query().astype(int).tolist()}  # fmt: skip
    both = [np.concatenate([data[f"{c}_{k}"] for c in ("camera", "random")])
            for k in ("origins", "directions")]  # fmt: skip
    result["closest_500k_ms"] = timing.measure(lambda: accel.closest_hit(*both), repeats)[
        "median_ms"
    ]
    result["rays_500k"] = len(both[0])
    return result


def memory(accel) -> dict:
    """Bytes per triangle of the tree's arrays: the binary tree (built, refitted, costed),
    the 4-wide one the rays walk (with the slot map its refit reads)
    and the leaf-ordered primitive table."""
    n = accel.n_triangles
    binary = accel.node_bounds.nbytes + accel.node_first.nbytes + accel.node_count.nbytes
    wide = accel.wide_nodes.nbytes + accel.leaf_start.nbytes
    table = accel.leaf_prim.nbytes + accel.leaf_ids.nbytes
    return {"binary_tree": binary / n, "wide_tree": wide / n,
            "wide_slot_map": accel._slot_node.nbytes / n,
            "primitive_table": table / n}  # fmt: skip


def embree(embree_python: str, cases_path: str, repeats: int, cores: str) -> dict | None:
    """Embree's side (``embree_rays.py`` in its own environment), or None without it:
    ``cores`` "one", pinned to one core (the build and the queries); "all", the build alone
    on every core (Embree's default)."""
    if not Path(embree_python).exists():
        return None
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "embree.json"
        run = (
            "import sys; sys.path.insert(0, sys.argv[1]); import embree_rays; "
            "embree_rays.main(*sys.argv[2:])"
        )
        command = [embree_python, "-c", run, str(Path(__file__).parent), cases_path, str(out),
                   str(repeats), cores]  # fmt: skip
        subprocess.run(command, check=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
        return json.loads(out.read_text(encoding="utf-8"))


def one_size(name: str, shape: tuple[int, int], args) -> dict:
    triangles = np.concatenate([bumpy_sphere(*shape), room()])
    side, n_random = (64, 4000) if args.quick else (512, 244_000)
    rays = cases(triangles, side, n_random)
    with tempfile.TemporaryDirectory() as tmp:
        path = str(Path(tmp) / "cases.npz")
        arrays = {f"{c}_{k}": v for c, case in rays.items() for k, v in case.items()}
        np.savez(path, triangles=triangles, cases=np.array(list(rays)), **arrays)
        one = timing.in_fresh_process(ours, {"NUMBA_NUM_THREADS": "1"}, cases_path=path,
                                      repeats=args.repeats)  # fmt: skip
        two = timing.in_fresh_process(ours, {"NUMBA_NUM_THREADS": "2"}, cases_path=path,
                                      repeats=args.repeats)  # fmt: skip
        theirs = embree(args.embree_python, path, args.repeats, "one")
        theirs_all = embree(args.embree_python, path, args.repeats, "all")
    row = {"mesh": name, "triangles": len(triangles), "build_ms": one["build_ms"],
           "build_ms_2_threads": two["build_ms"], "bytes_per_triangle": one["bytes_per_triangle"],
           "rays_500k": one["rays_500k"], "closest_500k_ms_1_thread": one["closest_500k_ms"],
           "closest_500k_ms_2_threads": two["closest_500k_ms"],
           "speedup_2_threads": one["closest_500k_ms"] / two["closest_500k_ms"],
           "cases": {}}  # fmt: skip
    for case, mine in one["cases"].items():
        entry = {"query": rays[case]["query"], "rays": len(rays[case]["origins"]),
                 "ours_ms": mine["ms"]}  # fmt: skip
        if "part_of" in rays[case]:
            entry["part_of"] = rays[case]["part_of"]
        if theirs is not None:
            other = theirs["cases"][case]
            entry["embree_ms"] = other["ms"]
            entry["throughput_vs_embree"] = other["ms"] / mine["ms"]
            entry["same_answers"] = float(np.mean(np.array(mine["answers"]) ==
                                                  np.array(other["answers"])))  # fmt: skip
        row["cases"][case] = entry
    if theirs is not None:
        row["embree_build_ms"] = theirs["build_ms"]  # one core
        row["embree_build_ms_all_cores"] = theirs_all["build_ms"]
    return row


def run(args) -> dict:
    rows = [one_size(name, shape, args)
            for name, shape in (QUICK_SIZES if args.quick else SIZES).items()]  # fmt: skip
    report = []
    for r in rows:
        for case, c in r["cases"].items():
            text = f"{c['ours_ms']:.1f} ms"
            if "part_of" in c:  # a part of a case, timed apart: no target of its own
                per_ray = f"{1e6 * c['ours_ms'] / c['rays']:.0f} ns a ray"
                if "embree_ms" in c:
                    per_ray += (
                        f", Embree {1e6 * c['embree_ms'] / c['rays']:.0f} ns: "
                        f"{c['throughput_vs_embree']:.2f}x"
                    )
                report.append(timing.row(f"{r['mesh']} {case} ({c['rays']:,} rays), 1 thread",
                                         f"{text} ({per_ray})"))  # fmt: skip
                continue
            if "embree_ms" in c:
                text += f" (Embree {c['embree_ms']:.1f} ms; {c['same_answers']:.4%} same answers)"
                report.append(timing.target_row(
                    f"{r['mesh']} {case} ({c['query']} hit, {c['rays']:,} rays), throughput / "
                    "Embree's, 1 thread", f"{c['throughput_vs_embree']:.2f}x: {text}",
                    -c["throughput_vs_embree"], -0.7, ">= 0.7x"))  # fmt: skip
            else:
                report.append(timing.row(f"{r['mesh']} {case}", text, "Embree not installed"))
        report.append(
            timing.target_row(
                f"{r['mesh']} closest hit, {r['rays_500k']:,} rays, 1 -> 2 threads",
                f"{r['speedup_2_threads']:.2f}x ({r['closest_500k_ms_1_thread']:.1f} -> "
                f"{r['closest_500k_ms_2_threads']:.1f} ms)",
                -r["speedup_2_threads"],
                -1.9,
                ">= 1.9x",
            )
        )
        if "embree_build_ms" in r:
            for label, ours, theirs in (
                ("1 thread / Embree's on one core", r["build_ms"], r["embree_build_ms"]),
                (f"2 threads / Embree's on every core ({timing.machine()['usable_cores']})",
                 r["build_ms_2_threads"],
                 r["embree_build_ms_all_cores"]),
            ):  # fmt: skip
                report.append(timing.target_row(
                    f"{r['mesh']} build, {label}",
                    f"{ours / theirs:.2f}x ({ours:.1f} against {theirs:.1f} ms)",
                    ours / theirs, 1.0, "<= 1.0x"))  # fmt: skip
        else:
            build = f"{r['build_ms']:.1f} ms (2 threads {r['build_ms_2_threads']:.1f} ms)"
            report.append(timing.row(f"{r['mesh']} build, 1 thread", build))
        b = r["bytes_per_triangle"]
        report.append(timing.row(f"{r['mesh']} bytes per triangle",
                                 ", ".join(f"{k} {v:.1f}" for k, v in b.items())))  # fmt: skip
    notes = ["Each side in its own process; ours on one Numba thread unless stated, Embree's "
             "rtcIntersect1/rtcOccluded1 loop (embreex) on one thread, its process pinned to "
             "one core; Embree's build on one core, and again on every core (its "
             "default)."]  # fmt: skip
    return {
        "meshes": rows,
        "report": timing.report_section("BVH against Embree", report, notes, []),
    }


def main(argv=None) -> dict:
    parser = timing.make_parser(__doc__, out=Path("out/bench_embree"))
    parser.add_argument("--repeats", type=int, default=7, help="timed calls per measurement")
    parser.add_argument("--embree-python", default=".venv-mitsuba/bin/python",
                        help="the Python of Embree's environment (embreex)")  # fmt: skip
    args = parser.parse_args(argv)
    if args.quick:
        args.repeats = timing.QUICK_REPEATS
    result = run(args)
    print(f"wrote {timing.write_json(args.out, 'bench_embree', result)}")
    timing.print_report(result["report"], timing.machine())
    return result


if __name__ == "__main__":
    main()
