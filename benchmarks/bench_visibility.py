"""Visibility benchmark: BVH vs brute force on the paper's teapot scene (no shading, no tape).

Run:  python benchmarks/bench_visibility.py [--out DIR] [--quick] [--repeats 15] [--size 512]
      [--no-brute]

Workload (``docs/paper_scene.md``): the Newell teapot tessellated into 1,536 triangles
(``render.teapot``), the 512x512 pinhole camera at (3, 2, 5) looking at the origin, one ray
per pixel centre (``render.scene.camera.primary_rays``), and shadow rays from the camera hits to
the point light at (2, 5, 3), built exactly as the renderer builds them
(``render.trace.visibility.shadow_rays``: started off the surface by the scale-relative
``SHADOW_EPSILON`` offset, tmin = 0, the start triangle ignored).
A finer tessellation (26 x 60 cells per patch: 99,840 triangles) measures build time and
ray casting on a bigger mesh.

Measured (medians after a warm-up call, see ``timing.py``): BVH build, camera-ray
generation, closest-hit for all camera rays (also with Numba limited to one thread), any-hit
for the shadow rays; brute force for
the same rays (identical answers are checked). The thread count is Numba's default (set
NUMBA_NUM_THREADS to change it).

The functions ``visibility_workload``, ``time_bvh_visibility`` and ``time_brute_visibility``
are used by ``bench_render.py`` and ``fig2_bvh.py`` too.
"""

from __future__ import annotations

import numba
import numpy as np
import timing

from render.scene.camera import primary_rays
from render.scene.teapot import paper_scene
from render.trace.accel import Accelerator
from render.trace.light_view import occluded_towards_light
from render.trace.primitives import scene_primitives
from render.trace.raster import raster_closest_hit
from render.trace.visibility import scene_size, shadow_rays


def main(argv=None) -> dict:
    options = {"--no-brute": {"action": "store_true", "help": "skip the brute-force runs"}}
    return timing.main("bench_visibility", __doc__, run, argv, options, repeats=15, size=(512, 64))


def run(args) -> dict:
    """Visibility timed on the 1,536-triangle teapot (with brute force, unless
    ``--no-brute``) and on a finer tessellation; the results and their report."""
    size, repeats = args.size, args.repeats
    fine = (8, 13) if args.quick else (26, 60)

    w = visibility_workload(size)
    coarse = time_bvh_visibility(w, repeats)
    if not args.no_brute:
        coarse["brute"] = time_brute_visibility(w, max(1, repeats // 5))
    wf = visibility_workload(size, *fine)
    finer = time_bvh_visibility(wf, max(3, repeats // 3))
    result = {"size": size, "repeats": repeats, "teapot_1536": coarse, "teapot_fine": finer}
    result["report"] = report(result)
    return result


def visibility_workload(size: int = 512, nu: int = 4, nv: int = 6) -> dict:
    """The plain arrays of the paper scene's visibility queries at ``size`` x ``size`` with
    the teapot tessellated into nu x nv cells per patch: triangles, camera rays, and the
    shadow rays of the camera hits (computed here once with the BVH)."""
    scene = paper_scene(size, size, nu=nu, nv=nv)
    triangles = scene.meshes[0].triangles()
    eye, directions = primary_rays(scene.camera)
    origins = np.broadcast_to(eye, directions.shape)  # as the renderer passes them
    accel = Accelerator(triangles)
    prim_id, t, _, _ = accel.closest_hit(origins, directions)
    hit = np.flatnonzero(prim_id >= 0)
    points = eye + t[hit, None] * directions[hit]
    size = scene_size(scene_primitives(scene))
    shadows = shadow_rays(scene.lights[0], points, prim_id[hit], accel.n_triangles, size)
    return {
        "scene": scene,
        "triangles": triangles,
        "accel": accel,
        "origins": origins,
        "directions": directions,
        "prim_id": prim_id,
        "shadow_origins": shadows.origins,
        "shadow_directions": shadows.directions,  # unnormalised: the light is at t = 1
        "shadow_tmin": 0.0,  # the rays start off the surface (render.trace.visibility)
        "shadow_tmax": shadows.tmax,
        "shadow_ignore": shadows.ignore_prim,
    }


def _occluded(accel: Accelerator, w: dict, rays=slice(None)) -> np.ndarray:
    # tmax is one value per ray (point light: the distance to it), so it is sliced too.
    tmax = w["shadow_tmax"]
    return accel.occluded(
        w["shadow_origins"][rays],
        w["shadow_directions"][rays],
        tmax[rays] if np.ndim(tmax) else tmax,
        tmin=w["shadow_tmin"],
        ignore_prim=w["shadow_ignore"][rays],
    )


def closest_hit_one_thread(w: dict, repeats: int) -> dict:
    """The camera rays' closest hits with Numba limited to one thread (for comparison with
    single-threaded ray casters such as Embree's 10 ms)."""
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        return timing.measure(
            lambda: w["accel"].closest_hit(w["origins"], w["directions"]), repeats
        )
    finally:
        numba.set_num_threads(threads)


def time_bvh_visibility(w: dict, repeats: int) -> dict:
    """Medians (ms) of the BVH build, camera-ray generation, closest hit of all camera rays
    and any-hit of all shadow rays, plus counts and the tree's statistics."""
    accel = w["accel"]
    camera = w["scene"].camera
    n_shadow = len(w["shadow_origins"])
    occluded = _occluded(accel, w)
    return {
        "triangles": int(len(w["triangles"])),
        "camera_rays": int(len(w["directions"])),
        "hits": int((w["prim_id"] >= 0).sum()),
        "shadow_rays": int(n_shadow),
        "in_shadow": int(occluded.sum()),
        "bvh_nodes": accel.n_nodes,
        "bvh_depth": accel.depth,
        "build": timing.measure(lambda: Accelerator(w["triangles"]), repeats),
        "ray_generation": timing.measure(lambda: primary_rays(camera), repeats),
        "closest_hit": timing.measure(
            lambda: accel.closest_hit(w["origins"], w["directions"]), repeats
        ),
        "closest_hit_1_thread": closest_hit_one_thread(w, repeats),
        # The same hits by rasterisation (render.trace.raster; the renderer's choice while there
        # are >= 16 camera rays per primitive), camera rays made inside.
        "closest_hit_raster": timing.measure(
            lambda: raster_closest_hit(*scene_primitives(w["scene"]), camera, with_uv=False),
            repeats,
        ),
        "occluded": timing.measure(lambda: _occluded(accel, w), repeats),
        # The same answers in the light's view (render.trace.raster; the renderer's choice from 4
        # shadow rays per primitive on), primitives binned inside.
        "occluded_light_view": timing.measure(lambda: _occluded_in_light_view(w), repeats),
        "light_view_identical": bool(np.array_equal(_occluded_in_light_view(w), occluded)),
    }


def _occluded_in_light_view(w: dict) -> np.ndarray:
    light = np.asarray(w["scene"].lights[0].position.data, np.float64)
    return occluded_towards_light(
        scene_primitives(w["scene"]), light, w["shadow_origins"], w["shadow_directions"],
        w["shadow_tmax"], w["shadow_ignore"],
    )  # fmt: skip


def time_brute_visibility(w: dict, repeats: int, stride: int = 1, warmup: int = 1) -> dict:
    """Brute force (every ray against every triangle) on every ``stride``-th camera and
    shadow ray; the times are scaled by (all rays / rays timed) to the full ray count.
    Brute force costs the same for every ray (it tests all triangles), so the linear
    extrapolation is sound; ``stride = 1`` times all rays. Also checks that the answers are
    identical to the BVH's on the rays timed."""
    brute = Accelerator(w["triangles"], use_bvh=False)
    rays = slice(None, None, stride)
    origins = np.ascontiguousarray(w["origins"][rays])
    directions = np.ascontiguousarray(w["directions"][rays])
    n_cam, n_cam_timed = len(w["directions"]), len(directions)
    n_sh = len(w["shadow_origins"])
    n_sh_timed = len(range(n_sh)[rays])

    prim_id, _, _, _ = brute.closest_hit(origins, directions)
    same_hits = bool(np.array_equal(prim_id, w["prim_id"][rays]))
    same_shadows = bool(np.array_equal(_occluded(brute, w, rays), _occluded(w["accel"], w, rays)))
    closest = timing.measure(lambda: brute.closest_hit(origins, directions), repeats, warmup)
    occluded = timing.measure(lambda: _occluded(brute, w, rays), repeats, warmup)
    scale_cam, scale_sh = n_cam / n_cam_timed, n_sh / max(1, n_sh_timed)
    return {
        "stride": stride,
        "camera_rays_timed": n_cam_timed,
        "shadow_rays_timed": n_sh_timed,
        "closest_hit_timed": closest,
        "occluded_timed": occluded,
        "closest_hit_ms": closest["median_ms"] * scale_cam,
        "occluded_ms": occluded["median_ms"] * scale_sh,
        "extrapolated": stride > 1,
        "identical_to_bvh": same_hits and same_shadows,
    }


def report(r: dict) -> dict:
    """The report section: one block of rows per mesh, brute force last."""
    coarse, finer, size = r["teapot_1536"], r["teapot_fine"], r["size"]
    rows = []
    for m in (coarse, finer):
        label = f"{m['triangles']:,} tri"
        rows += [
            timing.row(f"{label}: BVH build", timing.ms(m["build"])),
            timing.row(f"{label}: camera rays generation", timing.ms(m["ray_generation"])),
            timing.row(
                f"{label}: closest hit, {m['camera_rays']:,} camera rays",
                timing.ms(m["closest_hit"]),
            ),
            timing.row(
                f"{label}: closest hit, 1 thread",
                timing.ms(m["closest_hit_1_thread"]),
                "Embree 1 thread: 10 ms" if m is coarse else "",
            ),
            timing.row(
                f"{label}: closest hit by rasterisation (camera rays included)",
                timing.ms(m["closest_hit_raster"]),
            ),
            timing.row(
                f"{label}: any hit, {m['shadow_rays']:,} shadow rays", timing.ms(m["occluded"])
            ),
            timing.row(
                f"{label}: any hit in the light's view (binning included)",
                timing.ms(m["occluded_light_view"]),
            ),
        ]
    if "brute" in coarse:
        b = coarse["brute"]
        rows += [
            timing.row("1,536 tri: closest hit, brute force", f"{b['closest_hit_ms']:.1f} ms"),
            timing.row("1,536 tri: any hit, brute force", f"{b['occluded_ms']:.1f} ms"),
        ]
    notes = [
        f"{size}x{size} image; medians of {r['repeats']} runs [interquartile range] after a "
        "warm-up.",
        f"BVH: {coarse['bvh_nodes']} nodes, depth {coarse['bvh_depth']} (1,536 triangles); "
        f"{finer['bvh_nodes']} nodes, depth {finer['bvh_depth']} ({finer['triangles']:,}).",
    ]
    if "brute" in coarse:
        notes.append(
            "Brute force gives identical answers: " + str(coarse["brute"]["identical_to_bvh"])
        )
    notes.append(
        "The light's view gives the BVH's shadow answers: "
        + str(coarse["light_view_identical"] and finer["light_view_identical"])
    )
    return timing.report_section("Visibility only (bench_visibility.py)", rows, notes, [])


if __name__ == "__main__":
    main()
