"""The Embree side of ``bench_embree.py``, run by that script in Embree's own environment
(numpy and embreex only: nothing of this project is imported, nor needed there).

``bench_embree.py`` runs ``main(CASES.npz, RESULT.json, REPEATS, CORES)`` in Embree's Python:
CORES "one", the process pinned to one core before Embree starts (its build then runs on
one thread; its queries are one thread's loop either way), or "all", the build alone on
every core the process may use (Embree's default: as many threads as cores).

``CASES.npz`` holds ``triangles`` (T, 3, 3) and, per case name ``c`` in ``cases``, its
rays ``c_origins``, ``c_directions`` (N, 3), ``c_far`` (N,) and its query ``c_query``:
"closest" (``rtcIntersect1`` per ray, in a loop on one thread; tfar = inf) or "any"
(``rtcOccluded1``, tfar = ``c_far``); tnear is 0 for both. Embree 4 (embreex 4.4) builds
its scene ``REPEATS`` times (timed: the scene, the mesh and the commit, which the first
query makes), then each case is timed ``REPEATS`` times. Written: the medians in
milliseconds, and each case's answers (primitive ids, or occluded flags) for
``bench_embree.py``'s agreement check.
"""

from __future__ import annotations

import json
import os
import time

import numpy as np


def median_ms(fn, repeats: int) -> float:
    fn()  # untimed: first touches of the arrays
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e3)


def main(cases_path: str, result_path: str, repeats: int, cores: str = "one") -> None:
    if cores == "one":  # before Embree's thread pool exists: it takes this mask's size
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh

    repeats = int(repeats)
    data = np.load(cases_path)
    triangles = data["triangles"].astype(np.float32)
    one = np.zeros((1, 3), np.float32)

    def build():
        scene = rtcore_scene.EmbreeScene()
        TriangleMesh(scene, triangles)
        scene.run(one, one + 1, query="INTERSECT")  # commits the scene
        return scene

    builds = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        scene = build()
        builds.append(time.perf_counter() - t0)
    result = {"build_ms": float(np.median(builds) * 1e3), "cases": {}}
    for case in data["cases"] if cores == "one" else ():
        o = data[f"{case}_origins"].astype(np.float32)
        d = data[f"{case}_directions"].astype(np.float32)
        far = data[f"{case}_far"].astype(np.float32)
        if str(data[f"{case}_query"]) == "closest":

            def query(o=o, d=d):
                return scene.run(o, d, query="INTERSECT")
        else:

            def query(o=o, d=d, far=far):
                # embreex answers an occluded ray with its geometry's id (0), else -1.
                return scene.run(o, d, dists=far.copy(), query="OCCLUDED") != -1

        result["cases"][str(case)] = {
            "ms": median_ms(query, repeats),
            "answers": np.asarray(query()).astype(int).tolist(),
        }
    with open(result_path, "w", encoding="utf-8") as f:
        json.dump(result, f)
