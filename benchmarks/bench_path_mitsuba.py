"""Our path integrator against Mitsuba 3's ``path`` integrator in the Cornell box: do both
estimate the same image, and how long does a sample take?

Run:  python benchmarks/bench_path_mitsuba.py [--out out/bench_path_mitsuba] [--quick]
          [--skip-timing | --skip-correctness] [--size 32] [--seeds 16] [--spp 256]
          [--depths 1,2,5,8] [--repeats 7] [--baseline DIR]

Needs Mitsuba 3 (not a dependency of this project: the script says so and exits with 1
without it). Install it next to the project, not into the project's environment, e.g.

    python -m venv --system-site-packages .venv-mitsuba
    .venv-mitsuba/bin/pip install mitsuba==3.9.1 drjit==1.5.0
    .venv-mitsuba/bin/python benchmarks/bench_path_mitsuba.py

Its LLVM backend needs a libLLVM (on Debian ``apt-get install libllvm19``); if Dr.Jit finds
none, or an older one that aborts, set ``DRJIT_LIBLLVM_PATH=libLLVM-19.so``.

Writes to ``out/bench_path_mitsuba/`` (git-ignored scratch) unless ``--out`` is given; the
committed results are regenerated with ``--out docs/path_tracing/mitsuba``. ``--quick`` is a
smoke run (seconds), marked so in ``results.md``. With
``--skip-timing`` or ``--skip-correctness`` the other part's results are kept from an
existing ``results.json`` in the output folder (``results.md`` is written from both).

**The same scene in both.** ``cornell_box(size, size, blocks=True)`` placed in world space
(``render.scene.placement``), converted by ``mitsuba_scene``: every mesh handed over as it
is (its vertices and faces, so Mitsuba's face normal is our (b - a) x (c - a)), the sphere
as Mitsuba's analytic ``sphere``, our two-sided Lambert materials as ``twosided(diffuse)``
with the same linear RGB albedo, the emissive square as an ``area`` emitter with the same
radiance per channel (it emits on the side of the face normal, as ours does), the camera as
a ``perspective`` sensor with ``fov_axis="x"`` (our ``Camera.fov`` is the horizontal field
of view: ``render.scene.camera``), a ``box`` reconstruction filter (each pixel the plain
mean of radiance over its area, as our uniformly jittered camera rays give) on an
``hdrfilm`` of linear RGB, and Mitsuba's ``path`` integrator with the same ``max_depth``
(both count segments: 1 shows emitters seen directly, 2 adds direct light, ...) and
``rr_depth`` 5. Its LLVM variant (``llvm_ad_rgb``) on 2 threads.

**Correctness** (``--depths``, default 1, 2, 5 and 8): each renderer renders the image with
``--seeds`` independent seeds of ``--spp`` samples (default 16 x 256 = 4,096 spp at 32x32;
other seeds for every depth, so that the rows are independent tests). Per pixel and
channel, the difference of the two means over seeds divided by its standard error (from the
spread of both renderers' seed means) is a z-score: if both estimate the same expectation,
its mean is ~0, its std ~1 and |z| > 3 rare. Two references for what "~1" and "rare" are
with this many seeds: Student's t with Welch's degrees of freedom (assumes normal seed
means), and the same statistics for Mitsuba against itself with other seeds (no assumption;
free, as Mitsuba is fast). Also the image mean's relative difference with its error bar, and
an orientation check (the root mean square z against Mitsuba's image flipped left-right,
up-down and both: ~1 unflipped, far above flipped; a warning otherwise).

max_depth 1 tests the camera, the film and the light's outline alone; 2 direct light
(emitter sampling, MIS, the emitter's side); 5 three indirect bounces; 8 also Russian
roulette, which neither renderer plays at max_depth <= 5 with rr_depth 5. (Their survival
probabilities differ: ours the product of the mean reflectances of the materials along the
path, clipped to [0.05, 0.95], Mitsuba the largest channel of the path's throughput, at
most 0.95; both are unbiased.) Writes ``results.json``, ``results.md`` and ``images.png``
(one row per depth: ours, Mitsuba, and |z| (largest of the three channels) from black 0 to
white 4, red above 3).

**Speed**: one render of the Cornell box at 128x128, max_depth 4 (and again at 5): ours
``render_path`` without a tape (16 spp), Mitsuba ``mi.render`` with one fixed seed (a new seed would
compile its kernel again) and the image evaluated (256 spp: Mitsuba's time per sample
levels off above ~100 spp); medians of ``--repeats`` calls after a warm-up, in turns
(blocks of ours, blocks of Mitsuba), as microseconds per sample per pixel and their ratio.
``--baseline DIR`` (a checkout of another version of this project, e.g. ``git worktree add
DIR <commit>``) times that version's ``render_path`` in the same turns, in a process of its
own: how far a change moved us.
"""

from __future__ import annotations

import os
import subprocess

# Numba's OpenMP threads sleep when idle instead of spinning (as run_all.py sets): spinning
# threads would slow Mitsuba's calls that follow ours.
os.environ.setdefault("OMP_WAIT_POLICY", "passive")

import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import timing
from bench_mitsuba import mitsuba_sensor
from scipy import stats

import minidiff as md
from render.path import render_path
from render.path.integrator import RR_DEPTH
from render.scene.cornell import cornell_box
from render.scene.image import save_image
from render.scene.placement import placed
from render.scene.scene import Material, Mesh, Scene, Sphere

#: Scratch output (git-ignored); the committed results: --out docs/path_tracing/mitsuba.
DEFAULT_OUT = Path("out/bench_path_mitsuba")
VARIANT = "llvm_ad_rgb"
THREADS = 2
#: The speed workload: image side, max_depth, our spp and Mitsuba's per call; it is timed
#: at max_depth 4 (``speed`` in results.json) and again at max_depth 5 (``speed_depth_5``).
SPEED = {"size": 128, "max_depth": 4, "our_spp": 16, "mitsuba_spp": 256}
QUICK_SPEED = {"size": 32, "max_depth": 4, "our_spp": 4, "mitsuba_spp": 64}
SPEED_DEPTHS = {"speed": 4, "speed_depth_5": 5}
#: |z| shown white in images.png (and red above this).
Z_WHITE, Z_RED = 4.0, 3.0
#: Pixels per image pixel in images.png (nearest neighbour), so that 32x32 can be seen.
ZOOM = 8
#: Seeds of max_depth d start at SEED_STRIDE * d (both renderers; disjoint per depth).
SEED_STRIDE = 10_000

# Mitsuba and Dr.Jit, imported by ``load_mitsuba`` (not dependencies of the project).
mi: Any = None
dr: Any = None


def load_mitsuba() -> str:
    """Import Mitsuba 3 and Dr.Jit, set the variant and the thread count; their version. No
    Mitsuba: a clear message and exit status 1."""
    global mi, dr
    try:
        import drjit
        import mitsuba
    except ImportError as error:
        sys.exit(
            f"bench_path_mitsuba: Mitsuba 3 is not installed ({error}). It is the second "
            "renderer this benchmark compares against, not a dependency of the project: "
            "install it in a separate virtualenv (see this script's docstring) and run the "
            "script with that Python."
        )
    mi, dr = mitsuba, drjit
    try:
        mi.set_variant(VARIANT)
    except Exception as error:  # e.g. no libLLVM for the LLVM backend
        sys.exit(
            f"bench_path_mitsuba: Mitsuba's {VARIANT} variant does not start ({error}). Its "
            "LLVM backend needs a libLLVM: point DRJIT_LIBLLVM_PATH at one (see the docstring)."
        )
    dr.set_thread_count(THREADS)
    mi.set_log_level(mi.LogLevel.Warn)
    return mi.__version__


# --- the scene in Mitsuba ------------------------------------------------------------------


def _rgb(value: md.Tensor) -> list[float]:
    """A scalar or (3,) material field as three floats."""
    return [float(x) for x in np.broadcast_to(np.asarray(value.data, np.float64), (3,))]


def _bsdf(material: Material) -> Any:
    """Our material as a Mitsuba BSDF: Lambert, two-sided. Anything else is refused (this
    conversion is for the scenes compared here, not a general exporter)."""
    unsupported = {
        "specular": np.any(material.specular.data),
        "reflectance": np.any(material.reflectance.data),
        "texture": material.texture is not None,
        "ambient": np.any(material.ambient.data),
    }
    used = [name for name, present in unsupported.items() if present]
    if used:
        raise ValueError(f"mitsuba_scene: materials with {', '.join(used)} are not converted")
    diffuse = {"type": "diffuse", "reflectance": {"type": "rgb", "value": _rgb(material.albedo)}}
    return mi.load_dict({"type": "twosided", "bsdf": diffuse})


def _emitter(material: Material) -> Any | None:
    """An ``area`` emitter with the material's radiance, or None if it does not emit."""
    radiance = _rgb(material.emission)
    if not any(radiance):
        return None
    return mi.load_dict({"type": "area", "radiance": {"type": "rgb", "value": radiance}})


def _mesh(name: str, mesh: Mesh) -> Any:
    """Our (world-space) mesh as a Mitsuba mesh: the same vertices and faces (so the same
    winding: Mitsuba's face normal is (b - a) x (c - a), the side an area emitter emits
    to), flat-shaded like ours (no vertex normals), its BSDF and emitter."""
    if mesh.smooth:
        raise ValueError("mitsuba_scene: smooth meshes are not converted")
    props = mi.Properties()
    props["bsdf"] = _bsdf(mesh.material)
    emitter = _emitter(mesh.material)
    if emitter is not None:
        props["emitter"] = emitter
    out = mi.Mesh(name, mesh.num_vertices, mesh.num_faces, props)
    params = mi.traverse(out)
    params["vertex_positions"] = mi.Float(mesh.vertices.data.astype(np.float32).ravel())
    params["faces"] = mi.UInt32(mesh.faces.astype(np.uint32).ravel())
    params.update()
    return out


def mitsuba_scene(scene: Scene, max_depth: int, rr_depth: int = RR_DEPTH) -> Any:
    """``scene`` as a Mitsuba scene with the ``path`` integrator (see the module docstring
    for each convention). Refuses what it does not convert (point and directional lights,
    glossy, mirror and textured materials)."""
    if scene.lights:
        raise ValueError("mitsuba_scene: point and directional lights are not converted")
    world = placed(scene)  # transforms applied: world-space vertices, centres and radii
    camera = world.camera
    description: dict[str, Any] = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": max_depth, "rr_depth": rr_depth},
        "sensor": mitsuba_sensor(mi, camera),
    }
    if np.any(world.background.data):
        description["environment"] = {
            "type": "constant",
            "radiance": {"type": "rgb", "value": _rgb(world.background)},
        }
    for i, obj in enumerate(world.objects):
        name = f"object_{i}"
        if isinstance(obj, Mesh):
            description[name] = _mesh(name, obj)
        elif isinstance(obj, Sphere):
            sphere = {
                "type": "sphere",
                "center": obj.center.data.tolist(),
                "radius": float(obj.radius.data),
                "bsdf": _bsdf(obj.material),
            }
            emitter = _emitter(obj.material)
            if emitter is not None:
                sphere["emitter"] = emitter
            description[name] = sphere
        else:
            raise TypeError(f"mitsuba_scene: cannot convert {type(obj).__name__}")
    return mi.load_dict(description)


# --- renders over seeds --------------------------------------------------------------------


def our_images(scene: Scene, max_depth: int, seeds: range, spp: int) -> np.ndarray:
    """(K, H, W, 3) our images, one per seed, each of ``spp`` samples per pixel."""
    with md.no_grad():
        return np.stack(
            [render_path(scene, spp=spp, max_depth=max_depth, seed=s).data for s in seeds]
        )


def mitsuba_images(scene: Any, seeds: range, spp: int) -> np.ndarray:
    """(K, H, W, 3) Mitsuba's images, one per seed (``mi.render(seed=k)``)."""
    return np.stack([np.array(mi.render(scene, spp=spp, seed=s), dtype=np.float64) for s in seeds])


def compare(ours: np.ndarray, theirs: np.ndarray) -> dict:
    """z-scores per pixel and channel, and the image mean's relative difference, from two
    stacks of independent per-seed images (K, H, W, 3). Pixel-channels where both are
    exactly constant over seeds (zero standard error, e.g. inside the light at max_depth 1)
    have no z-score: counted, and whether the two agree there exactly to float32."""
    k_o, k_m = len(ours), len(theirs)
    mean_o, mean_m = ours.mean(axis=0), theirs.mean(axis=0)
    var_o = ours.var(axis=0, ddof=1) / k_o  # squared standard errors of the means
    var_m = theirs.var(axis=0, ddof=1) / k_m
    se = np.sqrt(var_o + var_m)
    has_error = se > 0
    z_map = np.zeros_like(se)
    z_map[has_error] = (mean_o - mean_m)[has_error] / se[has_error]
    z = z_map[has_error]
    # Welch-Satterthwaite degrees of freedom: the reference distribution of each z.
    dof = (var_o + var_m)[has_error] ** 2 / (
        var_o[has_error] ** 2 / (k_o - 1) + var_m[has_error] ** 2 / (k_m - 1)
    )
    dof = np.maximum(dof, 2.5)  # t has a std for dof > 2 (Welch: dof >= min(K) - 1 anyway)
    constant = ~has_error
    gap = np.abs(mean_o - mean_m)[constant]
    scale = np.maximum(np.abs(mean_m[constant]), 1e-30)

    def image_mean(stack: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per channel and overall (4,): the mean over seeds and its standard error."""
        per_seed = np.concatenate(
            [stack.mean(axis=(1, 2)), stack.mean(axis=(1, 2, 3))[:, None]], axis=1
        )
        return per_seed.mean(axis=0), per_seed.std(axis=0, ddof=1) / np.sqrt(len(stack))

    (m_o, e_o), (m_m, e_m) = image_mean(ours), image_mean(theirs)
    relative = (m_o - m_m) / m_m
    relative_error = np.hypot(e_o, e_m) / m_m
    return {
        "compared": int(z.size),
        "z_mean": float(z.mean()),
        "z_std": float(z.std()),
        "z_std_expected": float(np.sqrt(np.mean(dof / (dof - 2.0)))),
        "frac_abs_z_above_3": float(np.mean(np.abs(z) > 3.0)),
        "frac_abs_z_above_3_expected": float(np.mean(2.0 * stats.t.sf(3.0, dof))),
        "max_abs_z": float(np.abs(z).max()),
        "z_mean_per_channel": [float(z_map[..., c][has_error[..., c]].mean()) for c in range(3)],
        "constant_pixel_channels": int(constant.sum()),
        "constant_max_relative_gap": float((gap / scale).max()) if gap.size else 0.0,
        "image_mean_ours": m_o.tolist(),
        "image_mean_ours_error": e_o.tolist(),
        "image_mean_mitsuba": m_m.tolist(),
        "image_mean_mitsuba_error": e_m.tolist(),
        "image_mean_relative_difference": relative.tolist(),
        "image_mean_relative_difference_error": relative_error.tolist(),
        "_maps": {"ours": mean_o, "mitsuba": mean_m, "z": z_map},
    }


def orientation(ours: np.ndarray, theirs: np.ndarray) -> dict:
    """Whether the images are the same way round: the root mean square z-score (over the
    pixel-channels with a spread) of our seed images (K, H, W, 3) against Mitsuba's as they
    are and flipped. "none" must be ~1 and the flips far above (the red wall is on the
    left, the light at the top)."""
    flips = {"none": theirs, "left-right": theirs[:, :, ::-1], "up-down": theirs[:, ::-1],
             "both": theirs[:, ::-1, ::-1]}  # fmt: skip
    out = {}
    for name, flipped in flips.items():
        se = np.sqrt(
            ours.var(axis=0, ddof=1) / len(ours) + flipped.var(axis=0, ddof=1) / len(flipped)
        )
        diff = ours.mean(axis=0) - flipped.mean(axis=0)
        out[name] = float(np.sqrt(np.mean((diff[se > 0] / se[se > 0]) ** 2)))
    return out


def correctness(size: int, depths: list[int], seeds: int, spp: int) -> tuple[dict, list]:
    """Both renderers at every max_depth: ``compare``'s numbers per depth (ours against
    Mitsuba, and Mitsuba against itself with other seeds: the null distribution of the same
    statistics, free of any assumption on the noise), the orientation check, the seconds
    each took, and the (ours, Mitsuba, z) maps for images.png. Every depth has its own
    seeds, so that the rows are independent tests."""
    scene = cornell_box(size, size, blocks=True)
    # Numba compiles or loads its kernels on the first render: not part of the time.
    with md.no_grad():
        render_path(scene, spp=1, max_depth=max(depths), seed=0)
    rows, maps = [], []
    for depth in depths:
        first = SEED_STRIDE * depth
        start = time.perf_counter()
        ours = our_images(scene, depth, range(first, first + seeds), spp)
        ours_seconds = time.perf_counter() - start
        start = time.perf_counter()
        theirs = mitsuba_images(mitsuba_scene(scene, depth), range(first, first + 2 * seeds), spp)
        mitsuba_seconds = time.perf_counter() - start
        row = compare(ours, theirs[:seeds])
        row["orientation"] = orientation(ours, theirs[:seeds])
        null = compare(theirs[seeds:], theirs[:seeds])
        null.pop("_maps")
        maps.append(row.pop("_maps"))
        row |= {
            "max_depth": depth,
            "seeds": [first, first + seeds],
            "mitsuba_vs_mitsuba": null,
            "ours_seconds": ours_seconds,
            "mitsuba_seconds": mitsuba_seconds,
        }
        rows.append(row)
        best = min(row["orientation"], key=row["orientation"].get)
        if best != "none":
            print(f"WARNING: at max_depth {depth} the images match best flipped {best}")
        rel = row["image_mean_relative_difference"][3]
        err = row["image_mean_relative_difference_error"][3]
        print(
            f"max_depth {depth}: z mean {row['z_mean']:+.3f} std {row['z_std']:.3f} "
            f"(t: {row['z_std_expected']:.3f}, Mitsuba vs itself: {null['z_std']:.3f}), "
            f"|z|>3 {row['frac_abs_z_above_3']:.2%} (t: {row['frac_abs_z_above_3_expected']:.2%}"
            f", Mitsuba vs itself: {null['frac_abs_z_above_3']:.2%}) of {row['compared']}; "
            f"image mean {rel:+.3%} ± {err:.3%}; ours {ours_seconds:.0f} s, Mitsuba "
            f"{mitsuba_seconds:.0f} s",
            flush=True,
        )
    return {"size": size, "seeds": seeds, "spp_per_seed": spp, "rows": rows}, maps


def write_images(maps: list[dict], path: Path) -> None:
    """images.png: per depth a row of ours | Mitsuba | |z| map (see the module docstring)."""

    def show(image: np.ndarray) -> np.ndarray:  # 2x exposure, gamma 1/2.2, as the examples
        return np.clip(2.0 * image, 0.0, 1.0) ** (1.0 / 2.2)

    def z_colours(z: np.ndarray) -> np.ndarray:
        worst = np.abs(z).max(axis=2)
        out = np.repeat(np.clip(worst / Z_WHITE, 0.0, 1.0)[..., None], 3, axis=2)
        out[worst > Z_RED] = (1.0, 0.0, 0.0)
        return out

    rows = []
    for m in maps:
        tiles = [show(m["ours"]), show(m["mitsuba"]), z_colours(m["z"])]
        tiles = [np.repeat(np.repeat(t, ZOOM, axis=0), ZOOM, axis=1) for t in tiles]
        gap = np.ones((tiles[0].shape[0], 4, 3))
        rows.append(np.concatenate([tiles[0], gap, tiles[1], gap, tiles[2]], axis=1))
        rows.append(np.ones((4, rows[-1].shape[1], 3)))
    save_image(np.concatenate(rows[:-1], axis=0), path)


# --- speed ---------------------------------------------------------------------------------


#: The baseline's render, in a process of its own (``--baseline``): it renders the speed
#: workload once per line it reads, and answers each with a line.
_BASELINE_SERVER = """
import sys
import minidiff as md
from render.path import render_path
from render.scene.cornell import cornell_box
size, spp, depth = (int(x) for x in sys.argv[1:4])
scene = cornell_box(size, size, blocks=True)
for _ in sys.stdin:
    with md.no_grad():
        render_path(scene, spp=spp, max_depth=depth, seed=0)
    print("done", flush=True)
"""


def _baseline_renderer(folder: str, size: int, spp: int, depth: int):
    """A callable that renders the workload once with the code checked out in ``folder``
    (another version of this project), in a process of its own, and its process."""
    env = dict(os.environ, PYTHONPATH=str(Path(folder).resolve()))
    process = subprocess.Popen(
        [sys.executable, "-c", _BASELINE_SERVER, str(size), str(spp), str(depth)],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env, cwd=folder,
    )  # fmt: skip

    def once() -> None:
        process.stdin.write("go\n")
        process.stdin.flush()
        if process.stdout.readline().strip() != "done":
            raise RuntimeError(f"bench_path_mitsuba: the baseline in {folder} failed")

    return once, process


def speed(workload: dict, repeats: int, baseline: str | None = None) -> dict:
    """Time per sample per pixel of one render, ours and Mitsuba's (and the ``baseline``
    checkout's, if given), timed in turns."""
    size, depth = workload["size"], workload["max_depth"]
    our_spp, their_spp = workload["our_spp"], workload["mitsuba_spp"]
    scene = cornell_box(size, size, blocks=True)
    theirs = mitsuba_scene(scene, depth)

    def ours_once() -> None:
        with md.no_grad():
            render_path(scene, spp=our_spp, max_depth=depth, seed=0)

    def mitsuba_once() -> None:
        np.array(mi.render(theirs, spp=their_spp, seed=0))  # evaluated: the kernel has run

    block = max(1, repeats // 3)
    fns, spps = {"ours": ours_once, "mitsuba": mitsuba_once}, {"ours": our_spp,
                                                                "mitsuba": their_spp}  # fmt: skip
    process = None
    if baseline:
        fns["baseline"], process = _baseline_renderer(baseline, size, our_spp, depth)
        spps["baseline"] = our_spp
    try:
        times = timing.measure_interleaved(fns, repeats, warmup=1, block=block)
    finally:
        if process is not None:
            process.stdin.close()
            process.wait()
    out = dict(workload) | {"repeats": repeats, "threads": THREADS}
    for name, spp in spps.items():
        out[name] = times[name] | {
            "us_per_sample_per_pixel": times[name]["median_ms"] * 1e3 / (size * size * spp)
        }
    out["ratio"] = out["ours"]["us_per_sample_per_pixel"] / out["mitsuba"][
        "us_per_sample_per_pixel"]  # fmt: skip
    if baseline:
        out["baseline_commit"] = _commit(baseline)
        out["baseline_over_ours"] = out["baseline"]["median_ms"] / out["ours"]["median_ms"]
        out["baseline_over_mitsuba"] = out["baseline"]["us_per_sample_per_pixel"] / out[
            "mitsuba"]["us_per_sample_per_pixel"]  # fmt: skip
    print(
        f"speed {size}x{size}, max_depth {depth}: ours "
        f"{out['ours']['us_per_sample_per_pixel']:.3f} us/sample/pixel ({our_spp} spp), "
        f"Mitsuba {out['mitsuba']['us_per_sample_per_pixel']:.4f} ({their_spp} spp): "
        f"{out['ratio']:.0f}x",
        flush=True,
    )
    return out


# --- report --------------------------------------------------------------------------------


def report(result: dict) -> dict:
    """The rows run_all.py-style reports read (``timing.report_section``): per max_depth the
    z-scores' std and the image mean's difference, and the speed ratio."""
    rows = []
    for r in (result.get("correctness") or {}).get("rows", []):
        null = r["mitsuba_vs_mitsuba"]
        rel = r["image_mean_relative_difference"][3]
        err = r["image_mean_relative_difference_error"][3]
        rows.append(
            timing.row(
                f"Cornell box, max_depth {r['max_depth']}: z std; image mean, ours vs Mitsuba",
                f"{r['z_std']:.3f}; {rel:+.2%} ± {err:.2%}",
                f"z std {null['z_std']:.3f} Mitsuba vs Mitsuba",
            )
        )
    for s in (result.get(key) for key in SPEED_DEPTHS):
        if not s:
            continue
        rows.append(
            timing.row(
                f"path tracing {s['size']}x{s['size']}, max_depth {s['max_depth']}, us per "
                "sample per pixel",
                f"{s['ours']['us_per_sample_per_pixel']:.3f} vs "
                f"{s['mitsuba']['us_per_sample_per_pixel']:.4f}: {s['ratio']:.0f}x",
                "Mitsuba 3 path, llvm_ad_rgb, 2 threads",
            )
        )
    notes = ["Details, references and images: docs/path_tracing/mitsuba/results.md."]
    return timing.report_section("Path integrator vs Mitsuba 3 (bench_path_mitsuba.py)", rows,
                                 notes, [])  # fmt: skip


def _quick_notice(part: dict, why: str) -> list[str]:
    """The warning that opens a part of results.md measured with --quick, or nothing."""
    return [f"**A --quick smoke run: {why}.**", ""] if part.get("quick") else []


def _correctness_markdown(c: dict, version: str) -> list[str]:
    """results.md's correctness part: the z table per max_depth, what it compares, and the
    images."""
    lines = [
        f"Cornell box {c['size']}x{c['size']} with its blocks, {c['seeds']} seeds x "
        f"{c['spp_per_seed']} spp = {c['seeds'] * c['spp_per_seed']:,} spp per pixel in "
        f"each renderer (ours; Mitsuba {version} `path`, {VARIANT}), "
        "rr_depth 5, other seeds for every max_depth. z = (ours - Mitsuba) / combined "
        "standard error, per pixel and channel (standard errors from the spread of the "
        "seed means). In brackets, what z would be if both estimated the same image: "
        "Student's t with Welch's degrees of freedom; Mitsuba against itself with "
        "other seeds.",
        "",
        "| max_depth | pixel-channels | mean z | std z (t; Mitsuba vs Mitsuba) | "
        "\\|z\\| > 3 (t; Mitsuba vs Mitsuba) | image mean, ours | Mitsuba | "
        "relative difference |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in c["rows"]:
        null = r["mitsuba_vs_mitsuba"]
        rel = r["image_mean_relative_difference"][3]
        err = r["image_mean_relative_difference_error"][3]
        compared = f"{r['compared']:,}"
        if r["constant_pixel_channels"]:
            compared += f" (+{r['constant_pixel_channels']:,} constant)"
        lines.append(
            f"| {r['max_depth']} | {compared} | {r['z_mean']:+.3f} | {r['z_std']:.3f} "
            f"({r['z_std_expected']:.3f}; {null['z_std']:.3f}) | "
            f"{r['frac_abs_z_above_3']:.2%} ({r['frac_abs_z_above_3_expected']:.2%}; "
            f"{null['frac_abs_z_above_3']:.2%}) | "
            f"{r['image_mean_ours'][3]:.5f} ± {r['image_mean_ours_error'][3]:.5f} | "
            f"{r['image_mean_mitsuba'][3]:.5f} ± {r['image_mean_mitsuba_error'][3]:.5f} | "
            f"{rel:+.2%} ± {err:.2%} |"
        )
    flips = ", ".join(
        f"max_depth {r['max_depth']}: "
        + ", ".join(f"{k} {v:.2g}" for k, v in r["orientation"].items())
        for r in c["rows"]
    )
    lines += [
        "",
        "Image means over all three channels. Constant pixel-channels: zero spread in "
        "both renderers (black, or inside the light at max_depth 1), where the two are "
        "equal to a relative "
        + ", ".join(f"{r['constant_max_relative_gap']:.1g}" for r in c["rows"])
        + " (by max_depth). Orientation: the root mean square z of our image against "
        f"Mitsuba's as it is and flipped ({flips}).",
        "",
        "![ours, Mitsuba, |z| (largest of the three channels; black 0, white 4, red above "
        "3); one row per max_depth in the table's order](images.png)",
        "",
    ]
    return lines


def _commit(folder: str) -> str:
    """The git commit checked out in ``folder`` (or "unknown")."""
    try:
        command = ["git", "-C", folder, "rev-parse", "--short", "HEAD"]
        return subprocess.run(command, capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def _speed_markdown(s: dict) -> list[str]:
    """results.md's speed part: how the times were taken, and the table."""
    rows = []
    if "baseline" in s:
        rows = [
            f"| the same, baseline (commit {s['baseline_commit']}, run beside them) | "
            f"{s['baseline']['us_per_sample_per_pixel']:.3f} ({s['our_spp']} spp, "
            f"{timing.ms(s['baseline'])}) | | {s['baseline_over_mitsuba']:.0f}x "
            f"(ours is {s['baseline_over_ours']:.1f}x faster) |"
        ]
    return [
        f"Speed: one render, {s['size']}x{s['size']}, max_depth {s['max_depth']}, "
        f"medians of {s['repeats']} after a warm-up, timed in turns, {s['threads']} "
        "threads each (ours: no tape; Mitsuba: one fixed seed, image evaluated). "
        "Provisional unless measured on a quiet machine (1-minute load average "
        f"{s.get('load_average', 'not recorded')} when the script started).",
        "",
        "| workload | ours | Mitsuba 3 | ours / Mitsuba |",
        "|---|---|---|---|",
        f"| path tracing, us per sample per pixel | "
        f"{s['ours']['us_per_sample_per_pixel']:.3f} ({s['our_spp']} spp, "
        f"{timing.ms(s['ours'])}) | {s['mitsuba']['us_per_sample_per_pixel']:.4f} "
        f"({s['mitsuba_spp']} spp, {timing.ms(s['mitsuba'])}) | {s['ratio']:.1f}x |",
        *rows,
        "",
    ]


def markdown(result: dict) -> str:
    """results.md: the correctness table, the speed row, and how they were measured."""
    c = result.get("correctness")
    lines = []
    if c:
        lines += _quick_notice(c, "too few samples to judge anything by")
        lines += _correctness_markdown(c, result["mitsuba_version"])
    for s in (result.get(key) for key in SPEED_DEPTHS):
        if s:
            lines += _quick_notice(s, "not the benchmark's workload")
            lines += _speed_markdown(s)
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict:
    parser = timing.make_parser(__doc__, out=DEFAULT_OUT, quick="a smoke run (under a minute)")
    parser.add_argument("--skip-timing", action="store_true", help="correctness only")
    parser.add_argument("--skip-correctness", action="store_true", help="speed only")
    parser.add_argument("--size", type=int, help="correctness image side (default 32)")
    parser.add_argument("--seeds", type=int, help="independent seeds per renderer (16)")
    parser.add_argument("--spp", type=int, help="samples per pixel per seed (256)")
    parser.add_argument("--depths", help="max_depths compared, comma-separated (1,2,5,8)")
    parser.add_argument("--repeats", type=int, help="timed calls per renderer (7)")
    parser.add_argument(
        "--baseline",
        help="a checkout of another version of this project (e.g. a git worktree) whose "
        "path integrator is timed beside ours, in a process of its own",
    )
    args = parser.parse_args(argv)
    quick = args.quick
    out = args.out
    size = args.size or (16 if quick else 32)
    seeds = args.seeds or (4 if quick else 16)
    spp = args.spp or (64 if quick else 256)
    depths = [int(d) for d in (args.depths or ("2,5,8" if quick else "1,2,5,8")).split(",")]
    repeats = args.repeats or (3 if quick else 7)
    if args.skip_timing and args.skip_correctness:
        parser.error("--skip-timing and --skip-correctness leave nothing to do")
    if not 2 <= seeds <= SEED_STRIDE // 2:
        parser.error(
            f"--seeds must be in [2, {SEED_STRIDE // 2}] (the standard error is their spread)"
        )

    load = round(os.getloadavg()[0], 2)  # others' load (ours raises it from here on)
    version = load_mitsuba()
    start = time.perf_counter()
    previous = out / "results.json"
    result = json.loads(previous.read_text()) if previous.exists() else {}
    result |= {"mitsuba_version": version, "variant": VARIANT}
    result.pop("quick", None)  # written per part
    if not args.skip_correctness:
        part = time.perf_counter()
        result["correctness"], maps = correctness(size, depths, seeds, spp)
        result["correctness"] |= {"quick": quick, "seconds": time.perf_counter() - part}
        out.mkdir(parents=True, exist_ok=True)
        write_images(maps, out / "images.png")
    if not args.skip_timing:
        for key, depth in SPEED_DEPTHS.items():
            part = time.perf_counter()
            workload = (QUICK_SPEED if quick else SPEED) | {"max_depth": depth}
            result[key] = speed(workload, repeats, args.baseline)
            result[key] |= {"quick": quick, "seconds": time.perf_counter() - part,
                            "load_average": load}  # fmt: skip
    result["seconds"] = time.perf_counter() - start  # this run's
    result["report"] = report(result)
    path = timing.write_json(out, "results", result)
    (out / "results.md").write_text(markdown(result), encoding="utf-8")
    print(markdown(result))
    print(f"wrote {path}, {out / 'results.md'}" + ("" if args.skip_correctness else
          f", {out / 'images.png'}") + f" in {result['seconds']:.0f} s")  # fmt: skip
    return result


if __name__ == "__main__":
    main()
