"""What ``minidiff.compile`` buys: the renderer's per-hit shading traced into one kernel,
against the same formulas on the NumPy tape.

Run:  python benchmarks/bench_compiler.py [--out DIR] [--quick] [--repeats 7] [--hits 1000000]

Workload (``hit_radiance`` below): for each of ``--hits`` camera rays that hit a triangle
mesh, gather the triangle's corners by the hit's primitive id (a shared table), recompute
the hit (``render.shade.surface.intersect_edges``: Moller-Trumbore), the face normal
turned towards the ray, the direction and irradiance of two point lights
(``render.scene.lights.PointLight.incidence``) and the Lambert + Blinn-Phong BRDF
(``render.shade.lighting.brdf``): the library's own formulas, called on traced arrays. The
loss is the sum of the radiance times a fixed weight image; gradients go to the vertices,
both lights' positions and intensities, the albedo and the specular colour.

Reported (medians, the two routes timed in turns in one process; this machine's cores):
- forward+VJP on the tape (``fn.function``) and compiled, on 1 and 2 threads, their ratio
  (target: compiled >= 5x faster on 1 thread) and the compiled route's 1 -> 2 thread gain
  (target >= 1.8x);
- the peak of NumPy's allocations during a forward+backward (tracemalloc), both routes;
- compile latency: a new kernel of the random 200-primitive program (``random_program``)
  traced, generated and compiled (forward and VJP), with an empty disk cache (target <=
  0.5 s per kernel), and fetched again from the disk cache by a fresh function (<= 10 ms);
- the number of primitives in the shading graph (tape nodes of one forward).
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import os
import random
import statistics
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

import minidiff as md
from minidiff import backend, compiler
from render.scene.lights import PointLight
from render.shade.lighting import Appearance, brdf
from render.shade.surface import face_normals, intersect_edges


def _with_fields(light: PointLight, **values) -> PointLight:
    """A copy of ``light`` whose parameters are the given (traced) arrays."""
    twin = copy.copy(light)
    for name, value in values.items():
        object.__setattr__(twin, name, value)
    return twin


LIGHTS = (PointLight([2.0, 3.0, 4.0], 40.0), PointLight([-3.0, 2.0, 1.0], 25.0, [1.0, 0.8, 0.6]))


@md.compile(shared=("vertices", "faces", "eye", "positions", "intensities", "albedo", "specular"))
def hit_radiance(vertices, faces, prim, eye, directions, positions, intensities, albedo, specular):
    """Radiance (k, 3) of k hits: the mesh's vertices (V, 3) and faces (F, 3), the hit
    primitive per ray (k,), the eye (3,) and ray directions (k, 3); two point lights'
    positions (2, 3) and intensities (2,); the albedo and specular colours (3,)."""
    corners = faces[prim]  # (k, 3) vertex ids
    a, b, c = vertices[corners[:, 0]], vertices[corners[:, 1]], vertices[corners[:, 2]]
    e1, e2 = b - a, c - a
    t, _, _ = intersect_edges(eye, directions, a, e1, e2, barycentrics=False)
    points = eye + t[:, None] * directions
    normals = md.normalize(face_normals(a, b, c))
    normals = normals * md.where(md.dot(normals, directions) > 0.0, -1.0, 1.0)[:, None]
    view = -md.normalize(directions)
    look = Appearance(albedo, specular, None, 32.0, None)
    radiance = 0.0
    for j, light in enumerate(LIGHTS):
        light = _with_fields(light, position=positions[j], intensity=intensities[j])
        to_light, irradiance = light.incidence(points)
        cosine = md.maximum(md.dot(normals, to_light), 0.0)
        f = brdf(normals, view, to_light, albedo * (1.0 / math.pi), look)
        radiance = radiance + (irradiance * cosine)[:, None] * (f * light.color)
    return radiance


def scene(hits: int, seed: int = 0):
    """A random mesh and ``hits`` rays from the eye into it (hit ids drawn uniformly)."""
    rng = np.random.default_rng(seed)
    vertices = rng.normal(size=(20_000, 3))
    faces = rng.integers(0, len(vertices), size=(40_000, 3))
    prim = rng.integers(0, len(faces), size=hits)
    eye = np.array([0.0, 0.0, 8.0])
    centres = vertices[faces[prim]].mean(axis=1)
    directions = centres - eye
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    parameters = dict(
        vertices=vertices, positions=np.array([l.position.data for l in LIGHTS]),
        intensities=np.array([float(l.intensity.data) for l in LIGHTS]),
        albedo=np.array([0.7, 0.5, 0.3]), specular=np.array([0.2, 0.2, 0.2]),
    )  # fmt: skip
    weights = rng.random((hits, 3))
    return parameters, dict(faces=faces, prim=prim, eye=eye, directions=directions), weights


def forward_backward(function, parameters, constants, weights) -> None:
    leaves = {k: md.tensor(v, requires_grad=True) for k, v in parameters.items()}
    radiance = function(**leaves, **constants)
    (radiance * weights).sum().backward()


def random_program(seed: int, size: int = 200):
    """A compiled function of 200 random elementwise primitives over four inputs."""
    rng = random.Random(seed)
    ops = [md.add, md.subtract, md.multiply, md.maximum, md.minimum]
    unary = [md.sin, md.cos, md.tanh, md.exp, lambda x: md.sqrt(md.abs(x) + 1.0)]

    def program(x, y, z, w):
        pool = [x, y, z, w]
        for _ in range(size):
            if rng.random() < 0.3:
                pool.append(rng.choice(unary)(rng.choice(pool[-8:]) * 0.5))
            else:
                pool.append(rng.choice(ops)(rng.choice(pool[-8:]), rng.choice(pool[-8:])))
        return pool[-1]

    return md.compile(program)


def compile_latency(seed: int) -> tuple[float, float]:
    """Seconds to trace, generate and compile the forward and VJP kernels of a new random
    program with an empty disk cache, then to get them again in a fresh function from disk."""
    x = [np.linspace(0.1, 1, 64)[:, None] * (k + 1) for k in range(4)]
    leaves = [md.tensor(v, requires_grad=True) for v in x]
    with tempfile.TemporaryDirectory() as cache:
        os.environ["MINIDIFF_CACHE_DIR"] = cache
        backend._compiled.clear()
        start = time.perf_counter()
        random_program(seed)(*leaves).sum().backward()
        fresh = time.perf_counter() - start
        backend._compiled.clear()  # as a new process: only the disk cache is left
        leaves = [md.tensor(v, requires_grad=True) for v in x]
        start = time.perf_counter()
        random_program(seed)(*leaves).sum().backward()
        cached = time.perf_counter() - start
        del os.environ["MINIDIFF_CACHE_DIR"]
    return fresh, cached


def peak_bytes(function, *args) -> int:
    tracemalloc.start()
    function(*args)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return peak


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", default="out/bench_compiler")
    parser.add_argument("--hits", type=int, default=1_000_000)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--quick", action="store_true", help="100,000 hits, 3 repeats")
    args = parser.parse_args()
    hits, repeats = (100_000, 3) if args.quick else (args.hits, args.repeats)
    parameters, constants, weights = scene(hits)
    tape = hit_radiance.function
    with md.no_grad():
        graph = hit_radiance.trace(**parameters, **constants)
    nodes = _count_tape_nodes(tape, parameters, constants)
    times = {"tape": [], "compiled, 1 thread": [], "compiled, 2 threads": []}
    forward_backward(hit_radiance, parameters, constants, weights)  # compile, outside timing
    for _ in range(repeats):
        for name in times:
            threads = 2 if "2 threads" in name else 1
            function = tape if name == "tape" else hit_radiance
            with compiler.using_threads(threads):
                start = time.perf_counter()
                forward_backward(function, parameters, constants, weights)
                times[name].append(time.perf_counter() - start)
    medians = {k: statistics.median(v) for k, v in times.items()}
    latency = [compile_latency(seed) for seed in range(3)]
    result = {
        "hits": hits,
        "tape_primitives_per_forward": nodes,
        "scalar_program_lines": len(graph.graph.nodes),
        "median_seconds": medians,
        "compiled_speedup_1_thread": medians["tape"] / medians["compiled, 1 thread"],
        "compiled_threads_gain": medians["compiled, 1 thread"] / medians["compiled, 2 threads"],
        "peak_bytes_tape": peak_bytes(forward_backward, tape, parameters, constants, weights),
        "peak_bytes_compiled": peak_bytes(forward_backward, hit_radiance, parameters, constants, weights),
        "compile_seconds_new_200_primitive_program": statistics.median(f for f, _ in latency),
        "fetch_seconds_from_disk": statistics.median(c for _, c in latency),
        "cpu_count": os.cpu_count(),
    }
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench_compiler.json").write_text(json.dumps(result, indent=2))
    print(json.dumps(result, indent=2))


def _count_tape_nodes(function, parameters, constants) -> int:
    leaves = {k: md.tensor(v[:1] if k == "prim" else v, requires_grad=True) for k, v in parameters.items()}
    small = {k: (v[:8] if k in ("prim", "directions") else v) for k, v in constants.items()}
    out = function(**leaves, **small)
    seen, stack = set(), [out.node]
    while stack:
        node = stack.pop()
        if node is None or id(node) in seen:
            continue
        seen.add(id(node))
        stack.extend(t.node for t in node.inputs)
    return len(seen)


if __name__ == "__main__":
    main()
