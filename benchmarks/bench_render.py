"""The renderer at 512x512 on the paper scene: where the time goes, forward and backward.

Run:  python benchmarks/bench_render.py [--out DIR] [--quick] [--repeats 15] [--size 512]

Measured (medians after a warm-up, see ``timing.py``), on the scene of ``docs/paper_scene.md``:

* the visibility steps on their own (``bench_visibility.py``): BVH build, camera-ray
  generation, closest hit of the 262,144 camera rays (BVH and rasterised), any hit of the
  shadow rays (BVH and in the light's view; the renderer rasterises and uses the light's
  view here, so it builds no BVH);
* shading forward: ``render`` with the visibility cached (the second render of an unchanged
  scene), i.e. the on-tape part only;
* full forward render: ``render(scene, reuse_visibility=False)`` of the plain scene (no
  parameter requires a gradient, so no tape is recorded: what a user's render costs), and
  of the scene whose parameters all require gradients (the tape is recorded);
* forward+backward: the paper's loss (Eq. 1, MSE of the clipped image,
  ``render.inverse.optimize.image_loss``) against a target rendered at the true parameters, from a
  start with the light moved by 0.1, differentiated w.r.t. ALL parameters: light position
  and intensity, albedo, camera position, look_at and fov, and all 1,120 vertices;
* mirror reflection: forward and forward+backward of the teapot on a mirror floor at
  max_bounces = 0, 1, 2 (what each bounce costs);
* the same forward and forward+backward without the BVH (brute force);
* peak memory of one forward and one forward+backward (tracemalloc and process RSS);
* gradient images (``render.gradient_image``, forward mode): one image along one direction
  (light x, camera x, all vertices moved along +x) against a plain forward render, both
  without visibility reuse, with antialias False and True; the target is at most ~3x;
* what visibility reuse buys: one iteration (render + loss + backward) of a material-only
  optimisation, with ``reuse_visibility=True`` (camera, lights and geometry unchanged, so
  the visibility is served from the cache) and ``False``;
* where the time goes: the functions with the largest own time in cProfile of one
  forward+backward (cProfile adds overhead per call; the shares are indicative);
* configurations: forward and forward+backward in fresh processes with different
  Numba/OpenMP settings (the default OpenMP layer whose idle threads spin, OMP_WAIT_POLICY=
  passive, the workqueue layer, one thread) and with glibc told to keep freed memory
  (``MALLOC_MMAP_THRESHOLD_`` and ``MALLOC_TRIM_THRESHOLD_``: ``timing.KEEP_FREED_MEMORY``),
  plus the cost of launching an empty parallel kernel, which the renderer does ~5 times per
  render. (Since the kernels run on ``minidiff.threads``'s pool, not Numba's ``prange``,
  Numba's threading layer and OpenMP's settings no longer reach them: those rows show it.)

Where rows are compared with each other (forward against forward+backward, with and without
antialiasing or visibility reuse, 0, 1 or 2 bounces, gradient images against a render), the
variants are timed in turns (``timing.measure_interleaved``).

Numbers to compare with (from the project brief): targets full forward < 25 ms (stretch
12 ms), primary visibility < 10 ms, forward+backward < 4x forward; Mitsuba 3 on this
machine renders the scene in 3.7 ms and does render+loss+backward in 11-14 ms; Embree casts
the 262,144 camera rays in 10 ms on one thread; the paper reports 52 ms per forward render
on a 6-core Xeon (85 ms without BVH).
"""

from __future__ import annotations

import cProfile
import os
import pstats

import numpy as np
import timing
from bench_visibility import time_brute_visibility, time_bvh_visibility, visibility_workload

import minidiff as md
from render import gradient_image, render
from render.inverse.optimize import image_loss
from render.scene.teapot import paper_scene


def main(argv=None) -> dict:
    return timing.main("bench_render", __doc__, run, argv, repeats=15, size=(512, 64))


def run(args) -> dict:
    """Every measurement of the module docstring, in its order, and the report."""
    size, repeats = args.size, args.repeats
    brute_repeats = 1 if args.quick else 3
    r = {"size": size, "repeats": repeats}
    w = visibility_workload(size)
    r["visibility"] = time_bvh_visibility(w, repeats)
    r |= time_forward(size, repeats)
    # Edge antialiasing (silhouettes, creases and, on the teapot and its ground, shadows)
    r["antialias"] = time_antialias(size, repeats)
    r["iterations"] = time_iterations(size, max(16, size // 4), repeats)
    r["reflection"] = time_reflection(size, repeats)
    r["gradient_image"] = time_gradient_image(size, repeats)
    r |= time_without_bvh(size, brute_repeats)
    r["brute_visibility"] = time_brute_visibility(w, brute_repeats, warmup=0)
    r |= time_material_iteration(size, repeats)
    variants = list(THREADING_VARIANTS)[:1] if args.quick else list(THREADING_VARIANTS)
    r["threading"] = {
        label: timing.in_fresh_process(
            threading_worker, THREADING_VARIANTS[label], size=size, repeats=repeats
        )
        for label in variants
    }
    r["report"] = make_report(r, args.out)
    return r


def time_forward(size: int, repeats: int) -> dict:
    """Forward renders of the plain scene and of the scene on the tape, each with and
    without the visibility cache, and forward+backward, in turns; their ratios, the peak
    memory of a forward and a forward+backward, and a profile of the latter."""
    plain = paper_scene(size, size)
    scene, params, target = loss_problem(size)
    r = timing.measure_interleaved(
        {
            "forward": lambda: render(plain, reuse_visibility=False),
            # The warm-up call fills the scene's visibility cache for the timed ones.
            "shading_forward_cached_visibility": lambda: render(plain),
            "forward_tape": lambda: render(scene, reuse_visibility=False),
            "forward_tape_cached_visibility": lambda: render(scene),
            "forward_backward": lambda: forward_backward(scene, params, target),
        },
        repeats,
    )
    fb = r["forward_backward"]["median_ms"]
    r["ratio_forward_backward_to_forward"] = fb / r["forward"]["median_ms"]
    r["ratio_forward_backward_to_forward_tape"] = fb / r["forward_tape"]["median_ms"]
    r["memory_forward"] = timing.measure_memory(lambda: render(plain, reuse_visibility=False))
    r["memory_forward_backward"] = timing.measure_memory(
        lambda: forward_backward(scene, params, target)
    )
    r["profile_forward_backward"] = profile_top(lambda: forward_backward(scene, params, target))
    return r


#: The edge methods timed against no edges: pixel pairs (``antialias=True``) and the
#: boundary integral.
#: name -> (antialias, render's interior_samples); "boundary_centres": the boundary integral
#: with the interior term of the pixels' own samples (as before the mixed pixels' 4x4).
EDGE_METHODS = {
    "antialias": (True, 16),
    "boundary": ("boundary", 16),
    "boundary_centres": ("boundary", 1),
}


def time_antialias(size: int, repeats: int) -> dict:
    """Forward render and forward+backward (all parameters) without edges, with pixel
    pairs (``antialias=True``) and with the boundary integral, in turns, on the paper
    scene and on the teapot standing on a ground plane (where shadow edges appear), and
    the ratios to no edges (``ratio_{kind}`` for pairs, ``ratio_{kind}_boundary``)."""
    out = {}
    for name, ground in (("paper", False), ("ground", True)):
        plain = paper_scene(size, size, ground=ground)
        problem = loss_problem(size, ground=ground)
        fns = {}
        for key, (antialias, interior) in {"plain": (False, 16), **EDGE_METHODS}.items():
            fns[f"forward_{key}"] = lambda a=antialias, i=interior, sc=plain: render(
                sc, reuse_visibility=False, antialias=a, interior_samples=i
            )
            fns[f"forward_backward_{key}"] = lambda a=antialias, i=interior, pr=problem: (
                forward_backward(*pr, antialias=a, interior_samples=i)
            )
        row = timing.measure_interleaved(fns, repeats)
        for kind in ("forward", "forward_backward"):
            for key in EDGE_METHODS:
                suffix = "" if key == "antialias" else f"_{key}"
                row[f"ratio_{kind}{suffix}"] = (
                    row[f"{kind}_{key}"]["median_ms"] / row[f"{kind}_plain"]["median_ms"]
                )
        out[name] = row
    return out


def time_iterations(size: int, shape_size: int, repeats: int) -> dict:
    """One optimisation iteration of each reconstruction kind, with the boundary integral
    and without edges, in turns: ``camera`` — camera calibration (section 5.6, the 10
    degree start of seed 42) at ``size``, render + loss + backward into position and
    look-at, the camera moved a little before every call (as an optimiser step moves it,
    so no visibility is reused); ``shape`` — the shape experiment's Large Steps step at
    ``shape_size`` (one view of the dented blob, the 2,562-vertex icosphere, four
    directional lights): render + loss + backward + ``LargeStepsAdam.step``."""
    from render.inverse.experiments import camera_calibration_problem
    from render.inverse.reconstruction import dented_blob, shape_scene, view_cameras
    from render.inverse.shape import LargeStepsAdam, icosphere

    scene, (position, look_at), target = camera_calibration_problem(size, 42, 10.0)
    moves = [0]

    def camera_step(antialias, interior) -> None:
        moves[0] += 1
        position.data[0] += 1e-4 * (-1) ** moves[0]
        position.grad = look_at.grad = None
        image = render(scene, antialias=antialias, interior_samples=interior)
        image_loss(image, target).backward()

    camera = view_cameras(1, shape_size)[0]
    with md.no_grad():
        shape_target = render(shape_scene(*dented_blob()).with_camera(camera)).data.copy()
    v0, f0 = icosphere(4)
    vertices = md.tensor(v0, requires_grad=True)
    blob = shape_scene(vertices, f0).with_camera(camera)
    optimizer = LargeStepsAdam(vertices, f0, lam=4.0, lr=0.03)

    def shape_step(antialias, interior) -> None:
        vertices.grad = None
        image = render(blob, antialias=antialias, interior_samples=interior)
        image_loss(image, shape_target).backward()
        optimizer.step()

    fns = {}
    methods = {"plain": (False, 16), "boundary": ("boundary", 16),
               "boundary_centres": ("boundary", 1)}  # fmt: skip
    for key, (antialias, interior) in methods.items():
        fns[f"camera_{key}"] = lambda a=antialias, i=interior: camera_step(a, i)
        fns[f"shape_{key}"] = lambda a=antialias, i=interior: shape_step(a, i)
    row = timing.measure_interleaved(fns, repeats)
    for kind in ("camera", "shape"):
        for key in ("boundary", "boundary_centres"):
            suffix = "" if key == "boundary" else "_centres"
            row[f"ratio_{kind}{suffix}"] = (
                row[f"{kind}_{key}"]["median_ms"] / row[f"{kind}_plain"]["median_ms"]
            )
    row["size"], row["shape_size"], row["shape_vertices"] = size, shape_size, len(v0)
    return row


def time_reflection(size: int, repeats: int) -> dict:
    """The teapot on a mirror floor (``paper_scene(ground=True)`` with reflectance 0.8):
    forward render and forward+backward (all parameters, reflectance included) at
    max_bounces = 0, 1, 2, in turns."""
    from render.scene.scene import Material

    def floor():
        return Material((0.05, 0.05, 0.05), reflectance=0.8)

    plain = paper_scene(size, size, ground=True, ground_material=floor())
    target = render(plain).data.copy()
    scene, params = differentiable_scene(size, names=None, ground=True)
    scene.objects[1].material = floor()
    reflectance = scene.objects[1].material.reflectance
    reflectance.requires_grad = True
    params = {**params, "reflectance": reflectance}
    scene.lights[0].position.data[0] += 0.1

    def step(b):
        for p in params.values():
            p.grad = None
        image_loss(render(scene, reuse_visibility=False, max_bounces=b), target).backward()

    fns = {}
    for bounces in (0, 1, 2):
        fns[f"forward_{bounces}"] = lambda b=bounces: render(
            plain, reuse_visibility=False, max_bounces=b
        )
        fns[f"forward_backward_{bounces}"] = lambda b=bounces: step(b)
    return timing.measure_interleaved(fns, repeats)


def time_gradient_image(size: int, repeats: int) -> dict:
    """One forward-mode pass (a gradient image along one direction) against a plain forward
    render of the paper scene, in turns, both with ``reuse_visibility=False`` (each pass
    traces its own rays), with and without antialiasing, and the ratios (the target: at
    most ~3)."""
    scene = paper_scene(size, size)
    along_x = np.zeros(scene.meshes[0].vertices.shape)
    along_x[:, 0] = 1.0
    directions = {
        "light_x": ("lights[0].position", np.array([1.0, 0.0, 0.0])),
        "camera_x": ("camera.position", np.array([1.0, 0.0, 0.0])),
        "vertices_x": ("objects[0].vertices", along_x),
    }
    out = {}
    for antialias in (False, True):
        fns = {"forward": lambda a=antialias: render(scene, reuse_visibility=False, antialias=a)}
        for key, (name, d) in directions.items():
            fns[key] = lambda a=antialias, n=name, d=d: gradient_image(
                scene, n, d, reuse_visibility=False, antialias=a
            )
        row = timing.measure_interleaved(fns, repeats)
        for key in directions:
            row[f"ratio_{key}"] = row[key]["median_ms"] / row["forward"]["median_ms"]
        out["antialias" if antialias else "plain"] = row
    return out


def time_without_bvh(size: int, repeats: int) -> dict:
    """Forward render and forward+backward with brute-force visibility, in turns, and the
    peak memory of a forward render."""
    plain = paper_scene(size, size)
    problem = loss_problem(size)
    r = timing.measure_interleaved(
        {
            "forward_no_bvh": lambda: render(plain, bvh=False, reuse_visibility=False),
            "forward_backward_no_bvh": lambda: forward_backward(*problem, bvh=False),
        },
        repeats,
    )
    r["memory_forward_no_bvh"] = timing.measure_memory(
        lambda: render(plain, bvh=False, reuse_visibility=False)
    )
    return r


def time_material_iteration(size: int, repeats: int) -> dict:
    """One iteration of a material-only optimisation (the albedo changes, then render, loss
    and backward) with and without visibility reuse, in turns."""
    scene, params, target = loss_problem(size, names=("albedo",))
    albedo = params["albedo"]

    def material_iteration(reuse: bool):
        albedo.data *= 0.999  # what an optimiser step does: only the material changes
        forward_backward(scene, params, target, reuse=reuse)

    return timing.measure_interleaved(
        {
            "material_iteration_reuse": lambda: material_iteration(True),
            "material_iteration_no_reuse": lambda: material_iteration(False),
        },
        repeats,
    )


# --------------------------------------------------------------------------------------
# The problems
# --------------------------------------------------------------------------------------

PARAMETERS = (
    # (name, object path, attribute): every continuous parameter of the paper scene
    ("light_position", "light", "position"),
    ("light_intensity", "light", "intensity"),
    ("albedo", "material", "albedo"),
    ("camera_position", "camera", "position"),
    ("look_at", "camera", "look_at"),
    ("fov", "camera", "fov"),
    ("vertices", "mesh", "vertices"),
)


def differentiable_scene(size: int, nu: int = 4, nv: int = 6, names=None, ground=False):
    """The paper scene with the named parameters (default: all of ``PARAMETERS``) replaced
    by leaves that require gradients. Returns (scene, {name: leaf})."""
    scene = paper_scene(size, size, nu=nu, nv=nv, ground=ground)
    owners = {
        "light": scene.lights[0],
        "material": scene.meshes[0].material,
        "camera": scene.camera,
        "mesh": scene.meshes[0],
    }
    params = {}
    for name, owner, attr in PARAMETERS:
        if names is None or name in names:
            leaf = md.tensor(getattr(owners[owner], attr).data, requires_grad=True)
            setattr(owners[owner], attr, leaf)
            params[name] = leaf
    return scene, params


def loss_problem(size: int, nu: int = 4, nv: int = 6, names=None, ground=False):
    """(scene, params, target): the target is rendered at the true parameters, the scene
    starts with the light moved by 0.1 along x, so the loss and its gradient are not zero.
    ``ground``: the teapot stands on a ground plane (``paper_scene(ground=True)``)."""
    target = render(paper_scene(size, size, nu=nu, nv=nv, ground=ground)).data.copy()
    scene, params = differentiable_scene(size, nu, nv, names, ground)
    scene.lights[0].position.data[0] += 0.1
    return scene, params, target


def forward_backward(
    scene, params, target, bvh: bool = True, reuse: bool = False, antialias: bool = False,
    interior_samples: int = 16,
) -> float:  # fmt: skip
    """One gradient evaluation: render, Eq. 1 loss, backward into every parameter."""
    for p in params.values():
        p.grad = None
    image = render(scene, bvh=bvh, reuse_visibility=reuse, antialias=antialias,
                   interior_samples=interior_samples)  # fmt: skip
    loss = image_loss(image, target)
    loss.backward()
    return loss.item()


def profile_top(fn, n: int = 10) -> list[dict]:
    """The ``n`` functions with the largest own time in a cProfile of one ``fn()``."""
    prof = cProfile.Profile()
    prof.enable()
    fn()
    prof.disable()
    stats = pstats.Stats(prof).stats
    total = sum(v[2] for v in stats.values())
    top = sorted(stats.items(), key=lambda kv: kv[1][2], reverse=True)[:n]
    rows = []
    for (filename, line, func), (_, calls, tottime, _, _) in top:
        where = f"{os.path.basename(filename)}:{line}" if line else filename
        rows.append(
            {
                "function": f"{func} ({where})",
                "calls": calls,
                "own_ms": tottime * 1e3,
                "share": tottime / total,
            }
        )
    return rows


# --------------------------------------------------------------------------------------
# Threading configurations (each in a fresh process: the threading layer is fixed at the
# first parallel kernel launch, and OMP_WAIT_POLICY at libgomp's load)
# --------------------------------------------------------------------------------------

# Every variable a variant may set; a variant removes the others (run_all.py sets
# OMP_WAIT_POLICY=passive for the suite; the "default" variant must not inherit it).
THREADING_SETTINGS = (
    "OMP_WAIT_POLICY",
    "NUMBA_THREADING_LAYER",
    "NUMBA_NUM_THREADS",
    "GOMP_SPINCOUNT",
    *timing.KEEP_FREED_MEMORY,
)
THREADING_VARIANTS = {
    label: dict.fromkeys(THREADING_SETTINGS) | settings
    for label, settings in {
        "default (OpenMP layer, spin-waiting)": {},
        "OMP_WAIT_POLICY=passive": {"OMP_WAIT_POLICY": "passive"},
        "NUMBA_THREADING_LAYER=workqueue": {"NUMBA_THREADING_LAYER": "workqueue"},
        "NUMBA_NUM_THREADS=1": {"NUMBA_NUM_THREADS": "1"},
        "OMP_WAIT_POLICY=passive + keep freed memory": {
            "OMP_WAIT_POLICY": "passive",
            **timing.KEEP_FREED_MEMORY,
        },
    }.items()
}


def threading_worker(size: int, repeats: int) -> dict:
    """Forward render time and the launch cost of an empty parallel kernel (a ``nogil``
    Numba function run as one job per thread by ``minidiff.threads``, as the renderer's
    kernels are), this process."""
    from numba import njit

    from minidiff.threads import run_jobs, thread_count

    @njit(nogil=True)
    def empty_job(job, n_jobs, a):
        s = 0.0
        for i in range(job, a.shape[0], n_jobs):
            s += a[i]
        return s

    def empty_kernel(a):
        return run_jobs(empty_job, thread_count(), a)

    scene = paper_scene(size, size)
    small = paper_scene(64, 64)
    grad_scene, params, target = loss_problem(size)
    a = np.ones(16)
    return {
        "parallel_launch": timing.measure(lambda: empty_kernel(a), 100, warmup=3),
        "forward": timing.measure(lambda: render(scene, reuse_visibility=False), repeats, 2),
        "forward_64": timing.measure(lambda: render(small, reuse_visibility=False), repeats, 2),
        "forward_backward": timing.measure(
            lambda: forward_backward(grad_scene, params, target), repeats, 2
        ),
        "machine": timing.machine(),
        **timing.allocator_setting(),
    }


# --------------------------------------------------------------------------------------
# Report
# --------------------------------------------------------------------------------------


def ratio_row(quantity: str, num: dict, den: dict, ratio: float, limit: float, target: str):
    """A report row for a ratio of two timings, checked against ``limit``."""
    ours = f"{timing.ms(num)} / {timing.ms(den)} = {ratio:.2f}x"
    return timing.target_row(quantity, ours, ratio, limit, target)


def antialias_rows(aa: dict) -> list:
    """Each edge method / no edges, forward and forward+backward, on both scenes."""
    rows = []
    methods = (
        ("antialias", "", "antialias=True (pixel pairs)", 1.25, "target <= 1.25x"),
        ("boundary", "_boundary", 'antialias="boundary"', 1.5, "target <= 1.5x"),
    )
    for name, label in (("paper", "paper scene"), ("ground", "teapot on a ground plane")):
        a = aa[name]
        for key, suffix, method, limit, target in methods:
            for kind, text in (("forward", "forward"), ("forward_backward", "forward+backward")):
                rows.append(
                    ratio_row(
                        f"{text} with {method} / without, {label}",
                        a[f"{kind}_{key}"],
                        a[f"{kind}_plain"],
                        a[f"ratio_{kind}{suffix}"],
                        limit,
                        target,
                    )  # fmt: skip
                )
    return rows


def iteration_rows(it: dict) -> list:
    """One reconstruction iteration with the boundary integral against one without edges."""
    rows = []
    for kind, text in (
        ("camera", f"camera-calibration iteration, {it['size']}x{it['size']}"),
        ("shape", f"shape iteration (Large Steps, {it['shape_vertices']:,} vertices, one "
                  f"{it['shape_size']}x{it['shape_size']} view)"),
    ):  # fmt: skip
        rows.append(
            ratio_row(
                f'{text}, antialias="boundary" / without edges',
                it[f"{kind}_boundary"],
                it[f"{kind}_plain"],
                it[f"ratio_{kind}"],
                1.5,
                "target <= 1.5x",
            )  # fmt: skip
        )
    return rows


def reflection_rows(refl: dict) -> list:
    """Forward and forward+backward at 0, 1, 2 bounces, and what each bounce adds."""
    rows = []
    for kind, text in (("forward", "forward"), ("forward_backward", "forward+backward")):
        times = [refl[f"{kind}_{b}"]["median_ms"] for b in (0, 1, 2)]
        each = " / ".join(timing.ms(refl[f"{kind}_{b}"]) for b in (0, 1, 2))
        added = f"first bounce +{times[1] - times[0]:.1f} ms, second +{times[2] - times[1]:.1f} ms"
        rows.append(
            timing.row(f"{text}, teapot on a mirror floor, max_bounces 0 / 1 / 2", each, added)
        )
    return rows


def gradient_image_rows(g: dict) -> list:
    """Each gradient image against the forward render, without and with antialiasing."""
    rows = []
    for mode, label in (("plain", ""), ("antialias", ", antialias=True")):
        row = g[mode]
        for key, text in (
            ("light_x", "light x"),
            ("camera_x", "camera x"),
            ("vertices_x", "all vertices along x"),
        ):
            rows.append(
                ratio_row(
                    f"gradient image ({text}) / forward render{label}",
                    row[key],
                    row["forward"],
                    row[f"ratio_{key}"],
                    3.0,
                    "target <= ~3x",
                )  # fmt: skip
            )
    return rows


def make_report(r: dict, out) -> dict:
    """Rows in the order of the module docstring; notes: the forward's breakdown, the
    profile, how memory and configurations were measured; a plot of the breakdown."""
    v = r["visibility"]
    fwd = r["forward"]["median_ms"]
    # The renderer rasterises this scene's camera rays (render(primary="auto")) and answers
    # its shadow rays in the light's view, so it builds no BVH.
    primary = v["closest_hit_raster"]["median_ms"]
    parts = {
        "camera-ray hits (raster)": primary,
        "shadow rays (light's view)": v["occluded_light_view"]["median_ms"],
        "shading (cached visibility)": r["shading_forward_cached_visibility"]["median_ms"],
    }
    rest = fwd - sum(parts.values())
    size = r["size"]
    rows = [
        *timing.time_rows(
            v,
            {
                "build": "BVH build (1,536 triangles)",
                "ray_generation": f"camera-ray generation ({v['camera_rays']:,} rays)",
                "closest_hit": "closest hit, BVH",
            },
        ),
        timing.row(
            "closest hit, BVH, 1 thread",
            timing.ms(v["closest_hit_1_thread"]),
            "Embree 1 thread: 10 ms",
        ),
        timing.row("closest hit by rasterisation, camera rays included", f"{primary:.1f} ms"),
        timing.target_row(
            "primary visibility (the renderer's choice here: rasterisation)",
            f"{primary:.1f} ms",
            primary,
            10.0,
            "target < 10 ms",
        ),
        *timing.time_rows(
            v,
            {
                "occluded": f"shadow rays ({v['shadow_rays']:,}), BVH",
                "occluded_light_view": "shadow rays in the light's view (the renderer's choice "
                "here), binning included",
            },
        ),
        *timing.time_rows(
            r,
            {
                "shading_forward_cached_visibility": "shading forward (visibility cached, no tape)",
                "forward_tape_cached_visibility": "shading forward (visibility cached, tape)",
            },
        ),
        timing.row("full forward - sum of the parts above (timed separately)", f"{rest:.1f} ms"),
        timing.row(
            "full forward render (no tape)",
            timing.ms(r["forward"]),
            "target < 25 ms (stretch 12); paper 52.3; Mitsuba 3.7",
            timing.target_status(fwd, 25.0) + (" (stretch met)" if fwd <= 12 else ""),
        ),
        timing.row(
            "full forward render (all parameters require grad)", timing.ms(r["forward_tape"])
        ),
        timing.row(
            "forward+backward, all parameters",
            timing.ms(r["forward_backward"]),
            "Mitsuba render+loss+backward 11-14 ms",
        ),
        timing.target_row(
            "forward+backward / forward",
            f"{r['ratio_forward_backward_to_forward']:.2f}x",
            r["ratio_forward_backward_to_forward"],
            4.0,
            "target < 4x",
        ),
        timing.row(
            "forward+backward / forward with tape",
            f"{r['ratio_forward_backward_to_forward_tape']:.2f}x",
        ),
        timing.row("full forward render, no BVH", timing.ms(r["forward_no_bvh"]), "paper 85.6 ms"),
        *antialias_rows(r["antialias"]),
        *iteration_rows(r["iterations"]),
        *reflection_rows(r["reflection"]),
        *gradient_image_rows(r["gradient_image"]),
        timing.row("forward+backward, no BVH", timing.ms(r["forward_backward_no_bvh"])),
        timing.row(
            "minor page faults per pass: forward / forward+backward",
            f"{r['forward']['page_faults_per_pass']:.0f} / "
            f"{r['forward_backward']['page_faults_per_pass']:.0f}",
        ),
    ]
    for key, label, paper in (
        ("memory_forward", "forward: tracemalloc / process RSS", "paper 124.5 MB (resident)"),
        (
            "memory_forward_no_bvh",
            "forward, no BVH: tracemalloc / RSS",
            "paper 207.3 MB (resident)",
        ),
        ("memory_forward_backward", "forward+backward: tracemalloc / RSS", ""),
    ):
        rows.append(timing.row(f"peak memory {label}", timing.mb(r[key]), paper))
    rows += timing.time_rows(
        r,
        {
            "material_iteration_reuse": "material-only iteration, reuse_visibility=True",
            "material_iteration_no_reuse": "material-only iteration, reuse_visibility=False",
        },
    )
    saved = (
        r["material_iteration_no_reuse"]["median_ms"] - r["material_iteration_reuse"]["median_ms"]
    )
    rows.append(timing.row("visibility reuse saves per iteration", f"{saved:.1f} ms"))
    for label, t in r["threading"].items():
        rows.append(
            timing.row(
                f"config {label}: forward {size}^2 / f+b {size}^2 / forward 64^2 / "
                "empty parallel kernel",
                f"{t['forward']['median_ms']:.1f} / {t['forward_backward']['median_ms']:.1f} / "
                f"{t['forward_64']['median_ms']:.1f} ms / "
                f"{t['parallel_launch']['median_ms'] * 1e3:.0f} us",
            )
        )
    top = r["profile_forward_backward"][:6]
    notes = [
        f"{size}x{size}; medians of {r['repeats']} runs [interquartile range] after a warm-up "
        "(no-BVH rows: fewer runs); NumPy and Numba use their default threads (2 cores). "
        "Rows compared with each other (the forward renders and forward+backward; antialias "
        "on and off; 0, 1, 2 bounces; gradient images and their forward render; reuse on and "
        "off; with and without BVH) were timed in turns, one call of each per round.",
        "Breakdown of a full forward (no BVH is built: the camera rays are rasterised, the "
        "shadow rays answered in the light's view): "
        + ", ".join(f"{k} {val:.1f} ms" for k, val in parts.items())
        + f"; full forward - their sum = {rest:.1f} ms: what the parts leave out, chiefly "
        "the hits' surfaces recomputed on the tape (the cached-visibility row reuses them), "
        "the set-up of the shadow rays and the hits' image coordinates, and composing the "
        "image.",
        "Largest own times in cProfile of one forward+backward: "
        + "; ".join(f"{p['function']} {p['own_ms']:.1f} ms ({100 * p['share']:.0f}%)" for p in top),
        "Memory: tracemalloc = NumPy/Python allocations alive at the peak of the call; RSS = "
        "the whole process's peak resident memory (interpreter, libraries and Numba included).",
        "Config rows: each configuration in a fresh process (the rows above run in this "
        "process, with the environment run_all.py sets); 'empty parallel kernel' is the "
        "median time of launching a Numba prange loop over 16 elements; 'keep freed memory' "
        "= MALLOC_MMAP_THRESHOLD_=32 MiB, MALLOC_TRIM_THRESHOLD_=1 GiB.",
    ]
    plot = timing.steps_plot(
        out / "bench_render_breakdown.png",
        "Forward render breakdown",
        [*parts, "full - sum"],
        {"forward breakdown (ms)": [*parts.values(), rest]},
    )
    return timing.report_section(
        f"Renderer at {size}x{size} (bench_render.py)", rows, notes, [plot.name]
    )


if __name__ == "__main__":
    main()
