"""Mitsuba 3's ``prb_projective`` on path_secondary.py's cases: the same gradient, its spread
and its cost.

Run (Mitsuba is not a dependency of the project: install it as bench_path_mitsuba.py says,
then give its Python path and the project's):

    DRJIT_LIBLLVM_PATH=libLLVM-19.so PYTHONPATH=<mitsuba's site>:. \\
        python benchmarks/path_secondary_mitsuba.py [--out out/path_secondary] [--quick]
        [--seeds N] [--spp N] [--fd-seeds N] [--cases light_position,sphere_centre]
        [--octree-seeds N]

after ``path_secondary.py --out`` the same folder: its ``secondary.json`` holds our side
(without it, Mitsuba's numbers are written alone). Writes ``mitsuba.json`` and
``mitsuba.md`` there.

For each case (``path_secondary.CASES``: the same scene, converted by
``bench_path_mitsuba.mitsuba_scene`` with the same camera conventions, the same max_depth,
no Russian roulette, the same tangent and the same weights W), over seeds:

* Mitsuba's ``prb_projective`` gradient of sum(W * image): a translation t, with
  ``dr.enable_grad``, added to the light's vertex positions (``light_position``) or to the
  sphere's centre in its ``to_world`` (``sphere_centre``); ``mi.render(seed, seed_grad)``,
  ``dr.backward``, then tangent . dL/dt. Its sppc = sppp = sppi = ``--spp``. Guiding
  ``"none"``: the default octree guiding rebuilds its structure on every call, ~50 s per
  gradient at 20x20 here, against ~0.3 s without; ``--octree-seeds`` gradients with it are
  timed and reported beside (their mean too, to see whether guiding changes the spread).
* Mitsuba's own same-seed central differences of the same functional with its ``path``
  integrator and path_secondary's step h: the scene as Mitsuba sees it, to check the
  conversion against our central differences.
* The image mean of Mitsuba's ``path`` against ours (same spp and number of seeds): a
  relative difference above 2 % is flagged.

Compared with ``secondary.json``: z = (Mitsuba - X) / combined standard error against our
central differences and our gradient with antialias="boundary" ("agrees" when |z| < 2), and
the variance per unit time, per-seed variance x median seconds per gradient, of both
(Mitsuba on ``THREADS`` thread(s), ours as run by path_secondary.py).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any

import bench_path_mitsuba as bpm
import numpy as np
import timing
from path_secondary import (
    CASES,
    NO_ROULETTE,
    Case,
    mean_error,
    quick_notice,
    weights,
    write_results,
)

import minidiff as md
from render.path import render_path
from render.scene.placement import placed

#: Mitsuba's threads: one, like path_secondary.py's runs (the machine is shared).
THREADS = 1
#: seed_grad = seed + this: the adjoint's samples independent of the primal's.
GRAD_SEED_OFFSET = 1 << 20
#: Our light and sphere in the Cornell box's objects (path_secondary's cases 1 and 2).
LIGHT, SPHERE = 5, 7


def _opaque(seed: int) -> Any:
    """The seed as an opaque Dr.Jit integer, so that a new seed does not compile Mitsuba's
    kernels again (a literal would)."""
    return bpm.dr.opaque(bpm.mi.UInt32, seed)


class Moved:
    """The Mitsuba scene of a case with its parameter moved by a translation ``t``
    (``mi.Vector3f``): the light's vertex positions or the sphere's centre."""

    def __init__(self, case: Case):
        mi, dr = bpm.mi, bpm.dr
        scene = case.scene()
        self.case, self.world = case, placed(scene)
        self.scene = bpm.mitsuba_scene(scene, case.max_depth, NO_ROULETTE)
        self.params = mi.traverse(self.scene)
        self.tangent = case.tangent(np.asarray(case.parameter(scene).data, np.float64))
        if case.name == "light_position":
            self.key = f"object_{LIGHT}.vertex_positions"
            self.start = dr.unravel(mi.Point3f, self.params[self.key])
        elif case.name == "sphere_centre":
            self.key = f"object_{SPHERE}.to_world"
            sphere = self.world.objects[SPHERE]
            self.start = mi.Point3f(*(float(x) for x in sphere.center.data))
            self.radius = float(sphere.radius.data)
        else:
            raise ValueError(f"path_secondary_mitsuba: no Mitsuba parameter for {case.name}")

    def move(self, t: Any) -> None:
        """Set the parameter to its start plus ``t`` and update the scene."""
        mi, dr = bpm.mi, bpm.dr
        if self.case.name == "light_position":
            self.params[self.key] = dr.ravel(self.start + t)
        else:
            self.params[self.key] = mi.Transform4f().translate(self.start + t).scale(self.radius)
        self.params.update()

    def functional(self, image: Any, w: Any) -> Any:
        """sum(W * image) as a Dr.Jit scalar (``image`` (H, W, 3) row-major, as ours)."""
        return bpm.dr.sum(image.array * w)


def prb_gradients(moved: Moved, w: Any, seeds: range, spp: int, guiding: str) -> dict:
    """Mitsuba's prb_projective directional derivative per seed and the seconds each took
    (render + backward, the gradient read back)."""
    mi, dr = bpm.mi, bpm.dr
    integrator = mi.load_dict(
        {
            "type": "prb_projective",
            "max_depth": moved.case.max_depth,
            "rr_depth": NO_ROULETTE,
            "guiding": guiding,
        }
    )
    values, seconds = [], []
    for seed in seeds:
        start = time.perf_counter()
        t = mi.Vector3f(0.0)
        dr.enable_grad(t)
        moved.move(t)
        image = mi.render(
            moved.scene,
            moved.params,
            integrator=integrator,
            spp=spp,
            seed=_opaque(seed),
            seed_grad=_opaque(seed + GRAD_SEED_OFFSET),
        )
        dr.backward(moved.functional(image, w))
        grad = dr.grad(t)
        values.append(float(np.array([grad.x[0], grad.y[0], grad.z[0]]) @ moved.tangent))
        seconds.append(time.perf_counter() - start)
    moved.move(mi.Vector3f(0.0))  # detached again
    return {"per_seed": np.array(values), "seconds": np.array(seconds)}


def central_differences(moved: Moved, w: Any, seeds: range, spp: int) -> np.ndarray:
    """Mitsuba's same-seed central differences (its ``path`` integrator) per seed."""
    mi = bpm.mi
    h, out = moved.case.h, []
    for seed in seeds:
        sides = []
        for sign in (1.0, -1.0):
            moved.move(mi.Vector3f(*(float(x) for x in sign * h * moved.tangent)))
            image = mi.render(moved.scene, spp=spp, seed=_opaque(seed))
            sides.append(moved.functional(image, w)[0])
        out.append((sides[0] - sides[1]) / (2.0 * h))
    moved.move(mi.Vector3f(0.0))
    return np.array(out)


def image_means(moved: Moved, seeds: range, spp: int) -> dict:
    """The image mean per seed, Mitsuba's ``path`` and ours, and their relative difference
    with its standard error."""
    mi = bpm.mi
    theirs = np.array(
        [np.mean(np.array(mi.render(moved.scene, spp=spp, seed=_opaque(s)))) for s in seeds]
    )
    with md.no_grad():
        ours = np.array(
            [
                render_path(
                    moved.case.scene(),
                    spp=spp,
                    max_depth=moved.case.max_depth,
                    seed=s,
                    rr_depth=NO_ROULETTE,
                ).data.mean()
                for s in seeds
            ]
        )
    (m_o, e_o), (m_m, e_m) = mean_error(ours), mean_error(theirs)
    relative, error = m_o / m_m - 1.0, np.hypot(e_o, e_m) / m_m
    return {
        "ours": m_o,
        "ours_error": e_o,
        "mitsuba": m_m,
        "mitsuba_error": e_m,
        "relative": relative,
        "relative_error": error,
        "flag": bool(abs(relative) > 0.02),
    }


def z_score(a: tuple[float, float], b: tuple[float, float]) -> float:
    """(mean_a - mean_b) / combined standard error."""
    return (a[0] - b[0]) / float(np.hypot(a[1], b[1]))


def ours_from(folder: Path) -> dict:
    """path_secondary.py's rows by case name, each with the run's spp, from
    ``secondary.json`` (empty if absent)."""
    path = folder / "secondary.json"
    if not path.exists():
        return {}
    result = json.loads(path.read_text())
    return {row["case"]: row | {"spp": result["spp"]} for row in result["rows"]}


def run_case(case: Case, args, ours: dict) -> dict:
    """Mitsuba's numbers for one case, and their comparison with ours where we have them."""
    w = bpm.mi.Float(weights().astype(np.float32).ravel())
    moved = Moved(case)
    prb = prb_gradients(moved, w, range(args.seeds), args.spp, "none")
    grad = mean_error(prb["per_seed"])
    row: dict[str, Any] = {
        "case": case.name,
        "h": case.h,
        "tangent": moved.tangent,
        "spp": args.spp,
        "seeds": args.seeds,
        "guiding": "none",
        "prb_projective": grad[0],
        "prb_projective_error": grad[1],
        "per_seed": prb["per_seed"],
        "seconds_per_gradient": float(np.median(prb["seconds"])),
        "first_call_seconds": float(prb["seconds"][0]),
        "variance_times_seconds": float(prb["per_seed"].var(ddof=1) * np.median(prb["seconds"])),
    }
    if args.octree_seeds:
        octree = prb_gradients(moved, w, range(args.octree_seeds), args.spp, "octree")
        row["octree"] = dict(zip(("mean", "error"), mean_error(octree["per_seed"]), strict=True))
        row["octree"] |= {
            "seeds": args.octree_seeds,
            "per_seed": octree["per_seed"],
            "seconds_per_gradient": float(np.median(octree["seconds"])),
        }
    fd = central_differences(moved, w, range(args.fd_seeds), args.spp)
    row["mitsuba_fd"], row["mitsuba_fd_error"] = mean_error(fd)
    row["mitsuba_fd_seeds"] = args.fd_seeds
    row["image_mean"] = image_means(moved, range(args.fd_seeds), args.spp)
    mine = ours.get(case.name)
    if mine is not None and mine["h"] == case.h:
        boundary = mine["modes"].get("boundary")
        row["ours_fd"], row["ours_fd_error"] = mine["fd"], mine["fd_error"]
        row["z_vs_ours_fd"] = z_score(grad, (mine["fd"], mine["fd_error"]))
        row["z_mitsuba_fd_vs_ours_fd"] = z_score(
            (row["mitsuba_fd"], row["mitsuba_fd_error"]), (mine["fd"], mine["fd_error"])
        )
        if boundary is not None:
            row["ours_boundary"], row["ours_boundary_error"] = (
                boundary["ours"],
                boundary["ours_error"],
            )
            row["z_vs_ours_boundary"] = z_score(grad, (boundary["ours"], boundary["ours_error"]))
            if "cost" in mine and mine["spp"] == args.spp:
                per_seed = np.asarray(boundary["per_seed"])
                row["ours_variance_times_seconds"] = float(
                    per_seed.var(ddof=1) * mine["cost"]["boundary"]
                )
    print(
        f"{case.name}: prb_projective {grad[0]:+.4f} ± {grad[1]:.4f} "
        f"({row['seconds_per_gradient']:.2f} s per gradient), Mitsuba FD "
        f"{row['mitsuba_fd']:+.4f} ± {row['mitsuba_fd_error']:.4f}, image mean ours / Mitsuba "
        f"- 1 = {row['image_mean']['relative']:+.2%} ± {row['image_mean']['relative_error']:.2%}",
        flush=True,
    )
    return row


def _agrees(z: float | None) -> str:
    return "" if z is None else f"{z:+.1f} ({'agrees' if abs(z) < 2 else 'differs'})"


def markdown(result: dict) -> str:
    """The comparison table and the cost table."""
    lines = quick_notice(result) + [
        f"Mitsuba {result['mitsuba_version']} `prb_projective` ({result['variant']}, "
        f"{THREADS} thread, guiding none), {result['spp']} spp (sppc = sppp = sppi), "
        f"{result['seeds']} seeds; Mitsuba's own same-seed central differences (`path`, "
        f"{result['fd_seeds']} seeds, path_secondary's h). Ours: path_secondary.py's "
        "secondary.json (antialias boundary). z: the difference in combined standard "
        f"errors. Commit {result['commit']}, {result['seconds']:.0f} s.",
        "",
        "| case | prb_projective | Mitsuba FD | our FD | ours (boundary) | "
        "z prb vs our FD | z prb vs ours | z Mitsuba FD vs our FD | image mean, ours / "
        "Mitsuba - 1 |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in result["rows"]:
        im = r["image_mean"]
        ours_fd = f"{r['ours_fd']:+.4f} ± {r['ours_fd_error']:.4f}" if "ours_fd" in r else ""
        ours = (
            f"{r['ours_boundary']:+.4f} ± {r['ours_boundary_error']:.4f}"
            if "ours_boundary" in r
            else ""
        )
        lines.append(
            f"| {r['case']} | {r['prb_projective']:+.4f} ± {r['prb_projective_error']:.4f} | "
            f"{r['mitsuba_fd']:+.4f} ± {r['mitsuba_fd_error']:.4f} | {ours_fd} | {ours} | "
            f"{_agrees(r.get('z_vs_ours_fd'))} | {_agrees(r.get('z_vs_ours_boundary'))} | "
            f"{_agrees(r.get('z_mitsuba_fd_vs_ours_fd'))} | "
            f"{im['relative']:+.2%} ± {im['relative_error']:.2%}"
            f"{' (over 2 %)' if im['flag'] else ''} |"
        )
    lines += [
        "",
        "Cost (medians; shared machine, indicative): seconds per gradient, and the per-seed "
        "variance times those seconds (lower: less noise for the same time).",
        "",
        "| case | prb_projective s | its variance x s | ours (boundary) variance x s | "
        "octree guiding: s per gradient, gradient |",
        "|---|---|---|---|---|",
    ]
    for r in result["rows"]:
        ours = r.get("ours_variance_times_seconds")
        octree = r.get("octree")
        lines.append(
            f"| {r['case']} | {r['seconds_per_gradient']:.2f} | "
            f"{r['variance_times_seconds']:.3g} | {'' if ours is None else f'{ours:.3g}'} | "
            + (
                ""
                if octree is None
                else f"{octree['seconds_per_gradient']:.1f}, "
                f"{octree['mean']:+.3f} ± {octree['error']:.3f} ({octree['seeds']} seeds)"
            )
            + " |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> dict:
    parser = timing.make_parser(
        __doc__, out=Path("out/path_secondary"), quick="4 seeds at 8 spp, no octree"
    )
    parser.add_argument("--seeds", type=int, default=256, help="prb_projective gradients")
    parser.add_argument("--spp", type=int, default=32, help="path_secondary.py's spp")
    parser.add_argument("--fd-seeds", type=int, default=256, help="Mitsuba's FD, image means")
    parser.add_argument("--octree-seeds", type=int, default=2, help="gradients with octree")
    parser.add_argument("--cases", default="light_position,sphere_centre")
    args = parser.parse_args(argv)
    if args.quick:
        args.seeds, args.spp, args.fd_seeds, args.octree_seeds = 4, 8, 4, 0
    version = bpm.load_mitsuba()
    bpm.dr.set_thread_count(THREADS)
    bpm.mi.set_log_level(bpm.mi.LogLevel.Error)  # its sample_border advice: no shape leaves
    out = Path(args.out)
    ours = ours_from(out)
    if not ours:
        print(f"no {out / 'secondary.json'}: Mitsuba's numbers alone", file=sys.stderr)
    start = time.perf_counter()
    rows = [run_case(CASES[name], args, ours) for name in args.cases.split(",")]
    result = {
        "quick": args.quick,
        "mitsuba_version": version,
        "variant": bpm.VARIANT,
        "threads": THREADS,
        "spp": args.spp,
        "seeds": args.seeds,
        "fd_seeds": args.fd_seeds,
        "rows": rows,
    }
    result["commit"] = bpm._commit(str(timing.ROOT))
    result["seconds"] = time.perf_counter() - start
    write_results(out, "mitsuba", result, markdown(result))
    return result


if __name__ == "__main__":
    main()
