"""What the tape costs: the renderer's shading math with minidiff vs the same math in NumPy.

Run:  python benchmarks/bench_minidiff.py [--out DIR] [--quick] [--repeats 21]

Workload: the paper scene at 512x512 (``docs/paper_scene.md``), ~41,000 pixels that hit the
teapot. Which triangle each pixel sees, and whether the light reaches it, is computed once
with the renderer (``render(..., return_info=True)``), *outside* the timing. Then, per hit:
gather the triangle's three vertices by hit id, recompute the ray-triangle intersection
(Moller-Trumbore), the hit point, the face normal (cross, normalize, flipped towards the
ray), the direction and distance to the point light (dot, normalize, division), Lambert's
cosine max(0, n.l), the radiance, and finally a mean-squared loss against a fixed target.

Two implementations of exactly that math:

* ``numpy_forward``: plain NumPy, no tape: the *floor* that a tape-based forward pass
  cannot beat. It uses the same kernels as minidiff's primitives (``minidiff.kernels``:
  the dot and cross products of (k, 3) rows in one compiled pass, the column-at-a-time
  broadcasting, outputs in reused memory), so the ratio isolates the tape's overhead.
* ``minidiff_forward``: the renderer's own on-tape functions (``render.shade.surface.
  shade_mesh``, which calls ``render.shade.surface`` and ``render.shade.lighting``), with the
  vertices, the camera position, the light position and intensity and the albedo as leaves
  that require gradients, i.e. what ``render.render`` does for a mesh.

Reported, in float64 and float32 (float32 inputs stay float32 on the tape), medians after a
warm-up, the four timed in turns (one call of each per round, so that their ratios see the
same machine state): NumPy forward (floor), minidiff forward without recording
(``no_grad``), minidiff forward (tape recorded), minidiff forward+backward, their ratios
to the floor (targets: forward <= 1.2x, forward+backward <= 2.5x), minor page faults per
pass and the peak of NumPy allocations (tracemalloc).

Each (dtype, allocator) pair runs in a fresh subprocess with OMP_NUM_THREADS =
OPENBLAS_NUM_THREADS = MKL_NUM_THREADS = 1 (single-threaded NumPy: minidiff's gradient
reductions use BLAS), once with the default allocator and once after
``minidiff.memory.keep_freed_memory()`` (glibc keeps freed memory instead of unmapping it),
so neither contaminates the other.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys

import numpy as np
import timing

import minidiff as md
from minidiff.kernels import cross3, dot_last, elementwise  # plain NumPy, as minidiff uses it
from minidiff.memory import keep_freed_memory
from render import render
from render.inverse.plot import line_plot
from render.renderer import shade_mesh
from render.scene.camera import primary_rays
from render.scene.scene import Material, Mesh, PointLight
from render.scene.teapot import paper_scene

THREAD_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


# --------------------------------------------------------------------------------------
# The workload
# --------------------------------------------------------------------------------------


def make_workload(size: int, dtype) -> dict:
    """Plain arrays of the shading problem: the scene's parameters in ``dtype`` and the
    per-hit constants (hit triangle ids, ray directions, light visibility, target)."""
    scene = paper_scene(size, size)
    _, info = render(scene, return_info=True)  # visibility, once, outside the timing
    prim_id = info.prim_id.reshape(-1)
    hit_rays = np.flatnonzero(prim_id >= 0)
    _, directions = primary_rays(scene.camera)
    mesh, light = scene.meshes[0], scene.lights[0]
    w = {
        "faces": mesh.faces,
        "faces_hit": prim_id[hit_rays],
        "directions": directions[hit_rays].astype(dtype),
        "lit": info.lit[0].reshape(-1)[hit_rays].astype(dtype),
        "vertices": mesh.vertices.data.astype(dtype),
        "eye": scene.camera.position.data.astype(dtype),
        "light_position": light.position.data.astype(dtype),
        "intensity": np.asarray(light.intensity.data, dtype=dtype),
        "color": light.color.data.astype(dtype),
        "albedo": mesh.material.albedo.data.astype(dtype),
    }
    w["target"] = (0.8 * numpy_forward(w, return_radiance=True)).astype(dtype)
    return w


def _mul(x, y):
    return elementwise(np.multiply, x, y)


def _normalize(x):
    return _mul(x, (1.0 / np.sqrt(dot_last(x, x)))[:, None])


def numpy_forward(w: dict, return_radiance: bool = False):
    """The floor: the same math as ``render.renderer.shade_mesh`` (flat-shaded mesh, one
    point light, Lambert) and the loss, in plain NumPy with the same fast building blocks
    (np.take gathers and ``minidiff.kernels``: the compiled dot and cross, the
    column-at-a-time broadcasting ``elementwise`` for (k, 3) op (3,) and (k, 1) op (k, 3)),
    no tape."""
    v, d, eye = w["vertices"], w["directions"], w["eye"]
    faces = w["faces"][w["faces_hit"]]
    a, b, c = (np.take(v, faces[:, i], axis=0) for i in range(3))
    # Moller-Trumbore (render.shade.surface.intersect_edges)
    e1, e2 = b - a, c - a
    p = cross3(d, e2)
    inv_det = 1.0 / dot_last(e1, p)
    s = elementwise(np.subtract, eye, a)
    q = cross3(s, e1)
    t = dot_last(e2, q) * inv_det  # no barycentrics: a flat, untextured mesh needs none
    points = elementwise(np.add, eye, _mul(t[:, None], d))
    # Flat normal facing the ray (render.renderer.shade_mesh)
    normals = _normalize(cross3(e1, e2))
    flip = np.where(dot_last(normals, d) > 0, -1.0, 1.0).astype(d.dtype)[:, None]
    normals = _mul(normals, flip)
    # Point light, Lambert (render.shade.lighting.shade / light_incidence)
    offset = elementwise(np.subtract, w["light_position"], points)
    distance_sq = np.maximum(dot_last(offset, offset), 1e-12)
    to_light = _normalize(offset)
    irradiance = w["intensity"] / distance_sq
    cos_theta = np.maximum(dot_last(normals, to_light), 0.0)
    brdf_colour = w["albedo"] * (1.0 / math.pi) * w["color"]
    radiance = _mul((irradiance * cos_theta * w["lit"])[:, None], brdf_colour)
    if return_radiance:
        return radiance
    return np.mean((radiance - w["target"]) ** 2)


def make_leaves(w: dict) -> dict:
    """The differentiable parameters as minidiff leaves, and the renderer's light/material
    objects holding them (float32 stays float32: minidiff keeps the leaves' dtype)."""
    leaves = {
        name: md.tensor(w[name], requires_grad=True)
        for name in ("vertices", "eye", "light_position", "intensity", "albedo")
    }
    leaves["light"] = PointLight(
        leaves["light_position"], leaves["intensity"], color=md.tensor(w["color"])
    )
    leaves["material"] = Material(albedo=leaves["albedo"])
    leaves["mesh"] = Mesh(leaves["vertices"], w["faces"], leaves["material"])
    return leaves


def minidiff_forward(w: dict, leaves: dict) -> md.Tensor:
    """The renderer's own per-hit code on the tape (``render.renderer.shade_mesh``, exactly
    what ``render.render`` runs for a mesh) and the MSE loss (``md.mean_squared_error``, as
    ``render.mse``)."""
    d = md.Tensor(w["directions"])  # constant here (the renderer derives it from the camera)
    radiance, _ = shade_mesh(
        leaves["mesh"], w["faces_hit"], leaves["eye"], d, [leaves["light"]], [w["lit"]]
    )
    return md.mean_squared_error(radiance, w["target"])  # the loss render.mse uses


# --------------------------------------------------------------------------------------
# One worker process: all measurements for one allocator setting
# --------------------------------------------------------------------------------------


def worker(size: int, repeats: int, keep_freed: bool, dtype: str) -> dict:
    """Measure everything for one dtype and one allocator setting, in this process."""
    applied = keep_freed_memory() if keep_freed else False
    w = make_workload(size, np.dtype(dtype).type)
    leaves = make_leaves(w)
    grads = [leaves[k] for k in ("vertices", "eye", "light_position", "intensity", "albedo")]

    def tape_forward():
        minidiff_forward(w, leaves)  # the tape is recorded, then dropped

    def no_grad_forward():
        with md.no_grad():
            minidiff_forward(w, leaves)

    def forward_backward():
        for p in grads:
            p.grad = None
        minidiff_forward(w, leaves).backward()

    floor_loss = float(numpy_forward(w))
    loss = minidiff_forward(w, leaves)
    loss.backward()
    r = {
        "dtype": dtype,
        "keep_freed_memory": keep_freed,
        "keep_freed_applied": applied,
        "hits": int(len(w["faces_hit"])),
        "loss_dtype": str(loss.dtype),
        "grad_dtypes": sorted({str(p.grad.dtype) for p in grads}),
        "loss_relative_difference_to_floor": abs(loss.item() - floor_loss) / floor_loss,
        # In turns, one call of each per round: the ratios below compare like with like.
        **timing.measure_interleaved(
            {
                "numpy_forward": lambda: numpy_forward(w),
                "minidiff_forward_no_grad": no_grad_forward,
                "minidiff_forward": tape_forward,
                "minidiff_forward_backward": forward_backward,
            },
            repeats,
            warmup=2,
        ),
        "memory_numpy_forward": timing.measure_memory(lambda: numpy_forward(w)),
        "memory_minidiff_forward_backward": timing.measure_memory(forward_backward),
        "machine": timing.machine(),
    }
    floor = r["numpy_forward"]["median_ms"]
    r["ratio_forward"] = r["minidiff_forward"]["median_ms"] / floor
    r["ratio_forward_no_grad"] = r["minidiff_forward_no_grad"]["median_ms"] / floor
    r["ratio_forward_backward"] = r["minidiff_forward_backward"]["median_ms"] / floor
    return r


def run_worker(size: int, repeats: int, keep_freed: bool, dtype: str) -> dict:
    """Run ``worker`` in a fresh single-threaded-NumPy subprocess; returns its results."""
    cmd = [
        sys.executable,
        os.path.abspath(__file__),
        "--worker",
        "--size",
        str(size),
        "--repeats",
        str(repeats),
        "--dtype",
        dtype,
    ]
    if keep_freed:
        cmd.append("--keep-freed")
    env = dict(os.environ, **THREAD_ENV)
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"bench_minidiff worker failed:\n{proc.stderr}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


# --------------------------------------------------------------------------------------
# Report
# --------------------------------------------------------------------------------------


def main(argv=None) -> dict:
    parser = timing.make_parser(__doc__)
    parser.add_argument("--repeats", type=int, default=21)
    parser.add_argument("--size", type=int, default=None, help="image side (default 512)")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--keep-freed", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--dtype", default="float64", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    size = args.size or (64 if args.quick else 512)
    repeats = 3 if args.quick else args.repeats
    if args.worker:
        print(json.dumps(worker(size, repeats, args.keep_freed, args.dtype), default=float))
        return {}

    # One fresh process per (allocator setting, dtype): glibc adapts its mmap threshold as
    # a process runs, so a measurement must not inherit another one's allocator state.
    default = {dt: run_worker(size, repeats, False, dt) for dt in ("float64", "float32")}
    tuned = {dt: run_worker(size, repeats, True, dt) for dt in ("float64", "float32")}

    rows, notes = [], []
    for dt in ("float64", "float32"):
        r, k = default[dt], tuned[dt]
        f = r["numpy_forward"]
        rows += [
            timing.row(f"{dt}: NumPy forward (floor)", timing.ms(f)),
            timing.row(
                f"{dt}: minidiff forward, no_grad", timing.ms(r["minidiff_forward_no_grad"])
            ),
            timing.row(f"{dt}: minidiff forward (tape)", timing.ms(r["minidiff_forward"])),
            timing.row(
                f"{dt}: minidiff forward+backward", timing.ms(r["minidiff_forward_backward"])
            ),
            timing.row(
                f"{dt}: forward / floor",
                f"{r['ratio_forward']:.2f}x",
                "<= 1.2x",
                timing.target_status(r["ratio_forward"], 1.2),
            ),
            timing.row(
                f"{dt}: forward+backward / floor",
                f"{r['ratio_forward_backward']:.2f}x",
                "<= 2.5x",
                timing.target_status(r["ratio_forward_backward"], 2.5),
            ),
            timing.row(
                f"{dt}: page faults per pass (floor / fwd / f+b)",
                f"{f['page_faults_per_pass']:.0f} / "
                f"{r['minidiff_forward']['page_faults_per_pass']:.0f} / "
                f"{r['minidiff_forward_backward']['page_faults_per_pass']:.0f}",
            ),
            timing.row(
                f"{dt}: peak NumPy memory (floor / f+b)",
                f"{r['memory_numpy_forward']['tracemalloc_peak_mb']:.1f} / "
                f"{r['memory_minidiff_forward_backward']['tracemalloc_peak_mb']:.1f} MB",
            ),
            timing.row(
                f"{dt} + keep_freed_memory(): forward / floor",
                f"{k['ratio_forward']:.2f}x ({timing.ms(k['minidiff_forward'])})",
                "<= 1.2x",
                timing.target_status(k["ratio_forward"], 1.2),
            ),
            timing.row(
                f"{dt} + keep_freed_memory(): forward+backward / floor",
                f"{k['ratio_forward_backward']:.2f}x ({timing.ms(k['minidiff_forward_backward'])})",
                "<= 2.5x",
                timing.target_status(k["ratio_forward_backward"], 2.5),
            ),
            timing.row(
                f"{dt} + keep_freed_memory(): page faults per pass (floor / fwd / f+b)",
                f"{k['numpy_forward']['page_faults_per_pass']:.0f} / "
                f"{k['minidiff_forward']['page_faults_per_pass']:.0f} / "
                f"{k['minidiff_forward_backward']['page_faults_per_pass']:.0f}",
            ),
        ]
    notes += [
        f"{size}x{size}, {default['float64']['hits']:,} hit pixels; medians of {repeats} runs "
        "[interquartile range] after 2 warm-ups; NumPy single-threaded (OMP/OPENBLAS/MKL_NUM_"
        "THREADS=1); each (dtype, allocator) pair in its own fresh process.",
        "Ratios use the floor measured in the same process (the keep_freed rows divide by the "
        "floor measured with keep_freed_memory() too).",
        "Loss dtypes: float64 -> "
        + default["float64"]["loss_dtype"]
        + ", float32 -> "
        + default["float32"]["loss_dtype"]
        + " (gradients: "
        + ", ".join(default["float32"]["grad_dtypes"])
        + ").",
        f"minidiff loss vs floor loss, relative difference: float64 "
        f"{default['float64']['loss_relative_difference_to_floor']:.1e}, float32 "
        f"{default['float32']['loss_relative_difference_to_floor']:.1e}.",
        "Peak memory is tracemalloc's (NumPy buffers and Python objects alive at once).",
        f"keep_freed_memory() applied: {tuned['float64']['keep_freed_applied']}.",
    ]

    names = ["NumPy fwd", "md fwd no_grad", "md fwd", "md fwd+bwd"]
    keys = [
        "numpy_forward",
        "minidiff_forward_no_grad",
        "minidiff_forward",
        "minidiff_forward_backward",
    ]
    series = {}
    for label, res in (
        ("float64", default),
        ("float32", default),
        ("float64 keep_freed", tuned),
        ("float32 keep_freed", tuned),
    ):
        dt = label.split()[0]
        series[label] = (list(range(1, 5)), [res[dt][k]["median_ms"] for k in keys])
    plot = line_plot(
        series,
        args.out / "bench_minidiff.png",
        title="Shading math on ~41k hits: "
        + " | ".join(f"{i + 1}={n}" for i, n in enumerate(names)),
        xlabel="1 NumPy floor, 2 minidiff no_grad, 3 minidiff forward, 4 forward+backward",
        ylabel="ms",
    )
    section = timing.report_section(
        "Tape cost (bench_minidiff.py): the paper scene's shading math, ~41k hits",
        rows,
        notes,
        [plot.name],
    )
    result = {
        "size": size,
        "repeats": repeats,
        "default": default,
        "keep_freed": tuned,
        "report": section,
    }
    path = timing.write_json(args.out, "bench_minidiff", result)
    timing.print_report(section, default["float64"]["machine"])
    print(f"wrote {path}")
    return result


if __name__ == "__main__":
    main()
