"""What the tape costs: the renderer's shading math with minidiff vs the same math in NumPy.

Run:  python benchmarks/bench_minidiff.py [--out DIR] [--quick] [--repeats 21] [--size 512]

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
reductions use BLAS), once with glibc's default allocator settings and once with glibc told
to keep freed memory instead of unmapping it (``MALLOC_MMAP_THRESHOLD_`` and
``MALLOC_TRIM_THRESHOLD_`` in the environment, ``timing.KEEP_FREED_MEMORY``: what page
faults per pass remain for the allocator to save), so neither contaminates the other.
"""

from __future__ import annotations

import math

import numpy as np
import timing

import minidiff as md
from minidiff.kernels import add, cross3, dot_last, multiply, subtract  # as minidiff uses them
from render import render
from render.renderer import shade_mesh
from render.scene.camera import primary_rays
from render.scene.scene import Material, Mesh, PointLight
from render.scene.teapot import paper_scene

# Single-threaded NumPy in the workers: the floor is single-threaded NumPy code, and
# minidiff's gradient reductions use BLAS, which would otherwise take both cores.
THREAD_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
DTYPES = ("float64", "float32")


def main(argv=None) -> dict:
    return timing.main("bench_minidiff", __doc__, run, argv, repeats=21, size=(512, 64))


def run(args) -> dict:
    """Every (allocator setting, dtype) pair measured in its own process, and the report."""
    size, repeats = args.size, args.repeats
    # One fresh process per pair: glibc adapts its mmap threshold as a process runs, so a
    # measurement must not inherit another one's allocator state. (--quick, a smoke run
    # whose times are not results, measures both dtypes in one process per setting.)
    result = {"size": size, "repeats": repeats}
    groups = [DTYPES] if args.quick else [(dt,) for dt in DTYPES]
    for variant, keep_freed in (("default", False), ("keep_freed", True)):
        result[variant] = {}
        for dtypes in groups:
            result[variant] |= run_worker(size, repeats, keep_freed, dtypes)
    result["report"] = report(result, args.out)
    return result


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
    return multiply(x, y)


def _normalize(x):
    return _mul(x, (1.0 / np.sqrt(dot_last(x, x)))[:, None])


def numpy_forward(w: dict, return_radiance: bool = False):
    """The floor: the same math as ``render.renderer.shade_mesh`` (flat-shaded mesh, one
    point light, Lambert) and the loss, in plain NumPy with the same fast building blocks
    (np.take gathers and ``minidiff.kernels``: the compiled dot and cross, the
    broadcasting ``kernels.add``, ``subtract`` and ``multiply`` for (k, 3) op (3,) and
    (k, 1) op (k, 3)),
    no tape."""
    v, d, eye = w["vertices"], w["directions"], w["eye"]
    faces = w["faces"][w["faces_hit"]]
    a, b, c = (np.take(v, faces[:, i], axis=0) for i in range(3))
    # Moller-Trumbore (render.shade.surface.intersect_edges)
    e1, e2 = b - a, c - a
    p = cross3(d, e2)
    inv_det = 1.0 / dot_last(e1, p)
    s = subtract(eye, a)
    q = cross3(s, e1)
    t = dot_last(e2, q) * inv_det  # no barycentrics: a flat, untextured mesh needs none
    points = add(eye, _mul(t[:, None], d))
    # Flat normal facing the ray (render.renderer.shade_mesh)
    normals = _normalize(cross3(e1, e2))
    flip = np.where(dot_last(normals, d) > 0, -1.0, 1.0).astype(d.dtype)[:, None]
    normals = _mul(normals, flip)
    # Point light, Lambert (render.shade.lighting.shade / PointLight.incidence)
    offset = subtract(w["light_position"], points)
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


def worker(size: int, repeats: int, dtype: str) -> dict:
    """Measure everything for one dtype with this process's allocator setting."""
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
        **timing.allocator_setting(),
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


def workers(size: int, repeats: int, dtypes: list[str]) -> dict:
    """``worker`` for each of ``dtypes`` in this process: {dtype: its measurements}."""
    return {dt: worker(size, repeats, dt) for dt in dtypes}


def run_worker(size: int, repeats: int, keep_freed: bool, dtypes) -> dict:
    """``workers`` in a fresh single-threaded-NumPy process, with glibc keeping freed
    memory or at its defaults (the variables removed, should the parent have them)."""
    allocator = timing.KEEP_FREED_MEMORY if keep_freed else dict.fromkeys(timing.KEEP_FREED_MEMORY)
    env = THREAD_ENV | allocator
    return timing.in_fresh_process(workers, env, size=size, repeats=repeats, dtypes=list(dtypes))


# --------------------------------------------------------------------------------------
# Report
# --------------------------------------------------------------------------------------


def report(r: dict, out) -> dict:
    """Rows per dtype: the four times, the ratios to the floor against their targets, page
    faults and peak memory; then the ratios and page faults with glibc keeping freed memory."""
    default, tuned = r["default"], r["keep_freed"]
    rows = []
    for dt in DTYPES:
        d = default[dt]
        rows += [
            timing.row(f"{dt}: NumPy forward (floor)", timing.ms(d["numpy_forward"])),
            timing.row(
                f"{dt}: minidiff forward, no_grad", timing.ms(d["minidiff_forward_no_grad"])
            ),
            timing.row(f"{dt}: minidiff forward (tape)", timing.ms(d["minidiff_forward"])),
            timing.row(
                f"{dt}: minidiff forward+backward", timing.ms(d["minidiff_forward_backward"])
            ),
            *ratio_rows(dt, d),
            timing.row(
                f"{dt}: peak NumPy memory (floor / f+b)",
                f"{d['memory_numpy_forward']['tracemalloc_peak_mb']:.1f} / "
                f"{d['memory_minidiff_forward_backward']['tracemalloc_peak_mb']:.1f} MB",
            ),
            *ratio_rows(f"{dt}, keep freed memory", tuned[dt]),
        ]
    keep = " ".join(f"{k}={v}" for k, v in timing.KEEP_FREED_MEMORY.items())
    notes = [
        f"{r['size']}x{r['size']}, {default['float64']['hits']:,} hit pixels; medians of "
        f"{r['repeats']} runs [interquartile range] after 2 warm-ups, the four timed in turns; "
        "NumPy single-threaded (OMP/OPENBLAS/MKL_NUM_THREADS=1); each (dtype, allocator) pair "
        "in its own fresh process.",
        f"'keep freed memory': the process started with {keep} (glibc then serves allocations "
        "up to 32 MiB from its heap and keeps freed memory instead of unmapping it; applied: "
        f"{tuned['float64']['keep_freed_applied']}). Its ratios divide by the floor measured "
        "in the same process.",
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
    ]
    keys = [
        "numpy_forward",
        "minidiff_forward_no_grad",
        "minidiff_forward",
        "minidiff_forward_backward",
    ]
    plot = timing.steps_plot(
        out / "bench_minidiff.png",
        "Shading math on ~41k hits",
        ["NumPy floor", "minidiff no_grad", "minidiff forward", "forward+backward"],
        {
            f"{dt}{label}": [res[dt][k]["median_ms"] for k in keys]
            for label, res in (("", default), (" keep_freed", tuned))
            for dt in DTYPES
        },
    )
    return timing.report_section(
        "Tape cost (bench_minidiff.py): the paper scene's shading math, ~41k hits",
        rows,
        notes,
        [plot.name],
    )


def ratio_rows(label: str, r: dict) -> list:
    """The tape's cost against the floor measured in the same process (forward <= 1.2x,
    forward+backward <= 2.5x) and the page faults per pass."""
    faults = " / ".join(
        f"{r[k]['page_faults_per_pass']:.0f}"
        for k in ("numpy_forward", "minidiff_forward", "minidiff_forward_backward")
    )
    return [
        timing.target_row(
            f"{label}: forward / floor",
            f"{r['ratio_forward']:.2f}x ({timing.ms(r['minidiff_forward'])})",
            r["ratio_forward"],
            1.2,
            "<= 1.2x",
        ),
        timing.target_row(
            f"{label}: forward+backward / floor",
            f"{r['ratio_forward_backward']:.2f}x ({timing.ms(r['minidiff_forward_backward'])})",
            r["ratio_forward_backward"],
            2.5,
            "<= 2.5x",
        ),
        timing.row(f"{label}: page faults per pass (floor / fwd / f+b)", faults),
    ]


if __name__ == "__main__":
    main()
