"""What ``minidiff.compile`` buys: the renderer's per-hit shading traced into one kernel,
against the same formulas on the NumPy tape.

Run:  python benchmarks/bench_compiler.py [--out DIR] [--quick] [--repeats 7] [--hits 1000000]
(--quick: 100,000 hits, 3 repeats, one latency sample)

Workload (``hit_radiance`` below): for each of ``--hits`` rays that hit the paper's teapot
(finely tessellated: 24,576 triangles; rays in triangle order, as an image's are), gather
the triangle's corners by the hit's primitive id (a shared table), recompute the hit
(``render.shade.surface.intersect_edges``: Moller-Trumbore), the face normal turned
towards the ray, the direction and irradiance of two point lights
(``render.scene.lights.PointLight.incidence``) and the Lambert + Blinn-Phong BRDF
(``render.shade.lighting.brdf``): the library's own formulas, called on traced arrays. The
loss is the sum of the radiance times a fixed weight image; gradients go to the vertices,
both lights' positions and intensities, the albedo and the specular colour.

Reported (medians, the two routes timed in turns in one process; this machine's cores):
- forward+VJP on the tape (``fn.function``) and compiled, on 1 and 2 threads, their ratio
  (target: compiled >= 5x faster on 1 thread) and the compiled route's 1 -> 2 thread gain
  (target >= 1.8x); the compiled forward alone (no tape) on 1 and 2 threads; and the gain
  of a second thread on work that shares nothing (``two_thread_ceiling``), the most this
  machine gives;
- the peak of NumPy's allocations during a forward+backward (tracemalloc), both routes;
- compile latency: a new kernel of the random 200-primitive program (``random_program``)
  traced, generated and compiled (forward and VJP), with an empty disk cache (target <=
  0.5 s per kernel), and fetched again from the disk cache by a fresh function (<= 10 ms);
- the number of primitives in the shading graph (tape nodes of one forward);
- where a compiled forward+backward goes on 1 and 2 threads: each kernel, the scatter-add
  of gathered rows' gradients, and the rest (``kernel_split``).
"""

from __future__ import annotations

import copy
import math
import os
import random
import statistics
import tempfile
import threading
import time
import tracemalloc

import numpy as np
import timing

import minidiff as md
from minidiff import backend, codegen, compiler
from render.scene.lights import PointLight
from render.scene.teapot import teapot_geometry
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
    """The paper's teapot (``teapot_geometry(16, 24)``: 24,576 triangles) and ``hits`` rays
    from the eye to random points on it, in triangle order (in an image, neighbouring
    pixels hit neighbouring triangles)."""
    rng = np.random.default_rng(seed)
    vertices, faces = teapot_geometry(16, 24)
    a, b, c = np.moveaxis(vertices[faces], 1, 0)
    proper = np.flatnonzero(np.linalg.norm(np.cross(b - a, c - a), axis=1) > 0)  # no poles
    prim = np.sort(rng.choice(proper, size=hits))
    eye = np.array([0.0, 1.0, 8.0])
    weights = rng.dirichlet(np.ones(3), size=hits)  # barycentric points on the triangles
    targets = np.einsum("kj,kjc->kc", weights, vertices[faces[prim]])
    directions = targets - eye
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    parameters = dict(
        vertices=vertices, positions=np.array([l.position.data for l in LIGHTS]),
        intensities=np.array([float(l.intensity.data) for l in LIGHTS]),
        albedo=np.array([0.7, 0.5, 0.3]), specular=np.array([0.2, 0.2, 0.2]),
    )  # fmt: skip
    image_weights = rng.random((hits, 3))
    return parameters, dict(faces=faces, prim=prim, eye=eye, directions=directions), image_weights


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
    before = os.environ.get("MINIDIFF_CACHE_DIR")
    with tempfile.TemporaryDirectory() as cache:
        os.environ["MINIDIFF_CACHE_DIR"] = cache
        try:
            _as_new_process()
            start = time.perf_counter()
            random_program(seed)(*leaves).sum().backward()
            fresh = time.perf_counter() - start
            _as_new_process()  # only the disk cache is left
            leaves = [md.tensor(v, requires_grad=True) for v in x]
            start = time.perf_counter()
            random_program(seed)(*leaves).sum().backward()
            cached = time.perf_counter() - start
            split = _fetch_split(seed, leaves)
        finally:
            if before is None:
                del os.environ["MINIDIFF_CACHE_DIR"]
            else:
                os.environ["MINIDIFF_CACHE_DIR"] = before
    return fresh, cached, split


def _as_new_process() -> None:
    """Forget this process's compiled kernels (and the engine holding them): as a new
    process starts, with only the disk cache."""
    backend._compiled.clear()
    backend._shared = None


def _fetch_split(seed: int, leaves) -> dict:
    """Where a fetch from the disk cache goes, its steps timed apart (ms): tracing the
    function again, the traced program's text (the key, both kernels), loading both kernels'
    object code."""
    _as_new_process()
    start = time.perf_counter()
    program = random_program(seed).trace(*leaves)
    traced = time.perf_counter()
    keys = [codegen.program_text(program, mode, wrt) for mode, wrt in (("forward", ()),
            ("vjp", tuple(range(len(leaves)))))]  # fmt: skip
    keyed = time.perf_counter()
    for key in keys:
        backend.cached(key)
    loaded = time.perf_counter()
    return {"trace_ms": 1e3 * (traced - start), "key_ms": 1e3 * (keyed - traced),
            "load_ms": 1e3 * (loaded - keyed)}  # fmt: skip


def peak_bytes(function, *args) -> int:
    tracemalloc.start()
    function(*args)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return peak


def two_thread_ceiling(repeats: int) -> float:
    """What a second thread buys on this machine for work that shares nothing: NumPy's sin
    over cache-sized arrays (it releases the GIL), 512 calls on one thread against 256 on each
    of two, in turns. A virtual machine's two cores may be two threads of one physical core,
    or share it with neighbours: this is the gain no program can beat here."""
    x = [np.linspace(0.0, 1.0, 1 << 14) + k for k in range(2)]
    out = [np.empty_like(v) for v in x]

    def work(k: int, calls: int) -> None:
        for _ in range(calls):
            np.sin(x[k], out=out[k])

    def two() -> None:
        threads = [threading.Thread(target=work, args=(k, 256)) for k in range(2)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()

    times = timing.measure_interleaved({"one": lambda: work(0, 512), "two": two}, repeats=repeats)
    return times["one"]["median_ms"] / times["two"]["median_ms"]


def kernel_split(parameters, constants, weights, repeats: int) -> dict:
    """Where one compiled forward+backward goes, per thread count (1, 2): the median time
    (ms) of the whole call and of each compiled kernel it runs, by mode ("forward", "vjp",
    "vjp_shared"), and of the kernels that add gathered rows' gradients ("scatter": the
    blocks' rows found, then the scatter-add); "rest" is the call less these (the tape's
    loss and its backward, NumPy around the kernels). Found by wrapping
    ``backend.Kernel.run``, one call in turns per thread count."""
    scatter_keys = {compiler._scatter_kernel(c).key for c in range(1, 5)}
    scatter_keys.add(compiler._row_bounds().key)
    times: dict[int, dict[str, list[float]]] = {1: {}, 2: {}}
    current = {"mode": ""}
    run, run_kernel = compiler.CompiledFunction._run, backend.Kernel.run

    def timed_run(self, trace, mode, *args, **kwargs):
        current["mode"] = mode
        return run(self, trace, mode, *args, **kwargs)

    def timed_kernel(kernel, *args, **kwargs):
        start = time.perf_counter()
        status = run_kernel(kernel, *args, **kwargs)
        name = "scatter" if kernel.key in scatter_keys else current["mode"]
        calls[name] = calls.get(name, 0.0) + time.perf_counter() - start
        return status

    compiler.CompiledFunction._run, backend.Kernel.run = timed_run, timed_kernel
    try:
        for _ in range(repeats):
            for threads in (1, 2):
                calls: dict[str, float] = {}
                with compiler.using_threads(threads):
                    start = time.perf_counter()
                    forward_backward(hit_radiance, parameters, constants, weights)
                    calls["call"] = time.perf_counter() - start
                calls["rest"] = 2 * calls["call"] - sum(calls.values())
                for name, seconds in calls.items():
                    times[threads].setdefault(name, []).append(seconds)
    finally:
        compiler.CompiledFunction._run, backend.Kernel.run = run, run_kernel
    return {
        f"threads_{t}": {name: 1e3 * statistics.median(v) for name, v in by.items()}
        for t, by in times.items()
    }


def run(args) -> dict:
    hits = 100_000 if args.quick else args.hits
    parameters, constants, weights = scene(hits)
    tape = hit_radiance.function
    with md.no_grad():
        lines = len(hit_radiance.trace(**parameters, **constants).graph.nodes)
    forward_backward(hit_radiance, parameters, constants, weights)  # compile, outside timing

    def route(function, threads):
        def call():
            with compiler.using_threads(threads):
                forward_backward(function, parameters, constants, weights)

        return call

    def forward_only(threads):  # the compiled forward alone, no tape: the kernel and NumPy
        def call():
            with compiler.using_threads(threads), md.no_grad():
                hit_radiance(**parameters, **constants)

        return call

    results = timing.measure_interleaved(
        {"tape": route(tape, 1), "compiled_1": route(hit_radiance, 1),
         "compiled_2": route(hit_radiance, 2), "forward_1": forward_only(1),
         "forward_2": forward_only(2)},
        repeats=args.repeats,
    )  # fmt: skip
    latency = [compile_latency(seed) for seed in range(1 if args.quick else 3)]
    r = {
        "hits": hits,
        "tape_primitives_per_forward": _count_tape_nodes(tape, parameters, constants),
        "scalar_program_lines": lines,
        "results": results,
        "speedup_1_thread": results["tape"]["median_ms"] / results["compiled_1"]["median_ms"],
        "threads_gain": results["compiled_1"]["median_ms"] / results["compiled_2"]["median_ms"],
        "forward_threads_gain": results["forward_1"]["median_ms"]
        / results["forward_2"]["median_ms"],
        "machine_threads_gain": two_thread_ceiling(args.repeats),
        "peak_mb_tape": peak_bytes(forward_backward, tape, parameters, constants, weights) / 2**20,
        "peak_mb_compiled": peak_bytes(
            forward_backward, hit_radiance, parameters, constants, weights
        )
        / 2**20,
        "compile_s": statistics.median(f for f, _, _ in latency),
        "fetch_s": statistics.median(c for _, c, _ in latency),
        "fetch_split_ms": {
            k: statistics.median(s[k] for _, _, s in latency) for k in latency[0][2]
        },
        "repeats": args.repeats,
        "kernel_split_ms": kernel_split(parameters, constants, weights, args.repeats),
    }
    r["report"] = make_report(r)
    return r


def make_report(r: dict) -> dict:
    res = r["results"]
    rows = [
        timing.row("forward+VJP on the tape, 1 thread", timing.ms(res["tape"])),
        timing.row("forward+VJP compiled, 1 thread", timing.ms(res["compiled_1"])),
        timing.row("forward+VJP compiled, 2 threads", timing.ms(res["compiled_2"])),
        timing.row("tape / compiled, 1 thread", f"{r['speedup_1_thread']:.2f}x", "target >= 5x",
                   "met" if r["speedup_1_thread"] >= 5 else "not met"),
        timing.row("compiled, 1 -> 2 threads", f"{r['threads_gain']:.2f}x", "target >= 1.8x",
                   "met" if r["threads_gain"] >= 1.8 else "not met"),
        timing.row("compiled forward alone (no tape), 1 -> 2 threads",
                   f"{r['forward_threads_gain']:.2f}x"),
        timing.row("this machine's ceiling: independent NumPy work, 1 -> 2 threads",
                   f"{r['machine_threads_gain']:.2f}x"),
        timing.row("peak NumPy memory of a f+b, tape / compiled",
                   f"{r['peak_mb_tape']:.1f} / {r['peak_mb_compiled']:.1f} MB"),
        timing.target_row("new 200-primitive kernel (forward + VJP), s", f"{r['compile_s']:.3f}",
                          r["compile_s"], 0.5, "target <= 0.5 s"),
        timing.target_row("the same from the disk cache, s", f"{r['fetch_s']:.4f}",
                          r["fetch_s"], 0.010, "target <= 0.01 s"),
        timing.row("shading graph: tape primitives / scalar program lines",
                   f"{r['tape_primitives_per_forward']} / {r['scalar_program_lines']}"),
    ]  # fmt: skip
    one, two = r["kernel_split_ms"]["threads_1"], r["kernel_split_ms"]["threads_2"]
    for name in one:
        label = f"of a compiled f+b, 1 / 2 threads: {name}"
        rows.append(timing.row(label, f"{one[name]:.1f} / {two[name]:.1f} ms"))
    notes = [f"{r['hits']:,} hits on the teapot, medians of {r['repeats']} calls, in turns."]
    return timing.report_section("minidiff.compile (bench_compiler.py)", rows, notes, [])


def main(argv=None) -> dict:
    return timing.main(
        "bench_compiler", __doc__, run, argv, repeats=7,
        options={"--hits": dict(type=int, default=1_000_000, help="rays (default 10^6)")},
    )  # fmt: skip


def _count_tape_nodes(function, parameters, constants) -> int:
    leaves = {k: md.tensor(v, requires_grad=True) for k, v in parameters.items()}
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
