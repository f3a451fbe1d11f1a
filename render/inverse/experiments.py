"""The paper's three inverse-rendering experiments (sections 5.6-5.8) on the reference scene.

Each ``run_*`` function builds the target from the true parameters, starts from a seeded
perturbation, runs ``optimize`` and returns an ``ExperimentRun``: the paper's metrics (a
dict, JSON-ready), the loss history and the target, initial and final renders. A
``callback`` sees every iteration (e.g. to keep frames for an animation).

The example scripts in ``examples/`` are the command line around these; writing images,
plots and animations is theirs (``examples/script_support.py``).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

import minidiff as md
from render.inverse.basin import greedy_search
from render.inverse.optimize import History, optimize
from render.renderer import render
from render.scene.image import psnr
from render.scene.teapot import paper_scene

# The true parameters of the reference scene (docs/paper_scene.md).
TRUE_CAMERA = np.array([3.0, 2.0, 5.0])
TRUE_LOOK_AT = np.array([0.0, 0.0, 0.0])
TRUE_LIGHT = np.array([1.0, 4.0, 2.0])  # the light-estimation variant
TRUE_INTENSITY = 150.0


def rotate(vector: np.ndarray, axis: np.ndarray, degrees: float) -> np.ndarray:
    """Rodrigues' rotation of ``vector`` about the unit ``axis``."""
    a = math.radians(degrees)
    k = axis / np.linalg.norm(axis)
    return (
        vector * math.cos(a)
        + np.cross(k, vector) * math.sin(a)
        + k * np.dot(k, vector) * (1 - math.cos(a))
    )


def relative_error_pct(estimate: np.ndarray, truth: np.ndarray) -> float:
    """The paper's Eqs. 4-6: ||estimate - truth|| / ||truth||, in percent."""
    return float(100.0 * np.linalg.norm(estimate - truth) / np.linalg.norm(truth))


def _first_below(values, threshold: float) -> float:
    """The first iteration whose value is below ``threshold`` (NaN if never)."""
    below = np.flatnonzero(np.asarray(values) < threshold)
    return float(below[0]) if len(below) else float("nan")


@dataclass
class ExperimentRun:
    """One run of an experiment: ``metrics`` (the paper's numbers and ours, JSON-ready),
    the optimisation's ``history``, and the (H, W, 3) ``target``, ``initial`` and ``final``
    renders; ``name`` says which experiment, start and seed."""

    name: str
    metrics: dict
    history: History
    target: np.ndarray
    initial: np.ndarray
    final: np.ndarray


def _run(scene, params, target, *, lr, iters, tol, name, antialias=False, **options):
    """Shared driver: initial render, optimisation (``options`` go to ``optimize``: e.g.
    ``callback``, ``quiet``, ``project``; ``antialias`` is the edge method of the renders
    optimised, False the paper's renderer), final render, timings."""
    options.setdefault("quiet", True)
    options["render_kwargs"] = {**options.get("render_kwargs", {}), "antialias": antialias}
    target = np.clip(target, 0.0, 1.0)  # what the paper's Eq. 1 compares against
    initial = render(scene).data.copy()
    start = time.perf_counter()
    _, history = optimize(
        scene,
        params,
        target,
        lr=lr,
        max_iters=iters,
        tol=tol,
        **options,
    )
    total = time.perf_counter() - start
    final = render(scene).data.copy()
    result = {
        "iterations": history.iterations,
        "converged": history.converged,
        "stalled": history.stalled,
        "initial_loss": history.loss[0],
        "final_loss": history.loss[-1],
        "initial_psnr": psnr(np.clip(initial, 0, 1), target),  # a camera's clipped view
        "final_psnr": psnr(np.clip(final, 0, 1), target),
        "seconds_total": total,
        "seconds_per_iteration": total / max(1, len(history.loss)),
    }
    return ExperimentRun(name, result, history, target, initial, final)


def camera_calibration_problem(size: int, seed: int = 42, angle: float = 10.0):
    """The camera-calibration problem: (scene, [position, look_at], target).

    The target is the reference scene's render. The scene starts with the camera displaced
    by 0.5 along x and y and its viewing direction rotated by ``angle`` degrees about a
    random axis (seeded) perpendicular to it; position and look_at require grad.
    """
    rng = np.random.default_rng(seed)
    target = render(paper_scene(width=size, height=size)).data.copy()
    start_position = TRUE_CAMERA + np.array([0.5, 0.5, 0.0])
    view = TRUE_LOOK_AT - start_position
    axis = np.cross(view, rng.normal(size=3))
    start_look_at = start_position + rotate(view, axis, angle)
    position = md.tensor(start_position, requires_grad=True)
    look_at = md.tensor(start_look_at, requires_grad=True)
    scene = paper_scene(width=size, height=size, camera_position=position, look_at=look_at)
    return scene, [position, look_at], target


def run_camera_calibration(
    size: int = 512,
    iters: int = 500,
    seed: int = 42,
    angle: float = 10.0,
    lr: float = 0.03,
    tol: float = 1e-6,
    antialias: bool | str = False,
    search: int = 0,
    **options,
) -> ExperimentRun:
    """Section 5.6: recover the camera position and look-at point from a target render.

    Start: position displaced by 0.5 along x and y; the viewing direction rotated by
    ``angle`` degrees about a random axis (seeded) perpendicular to it. Reported: Eq. 4
    position error before and after, the loss, PSNR, iterations until the loss is < tol.
    ``antialias``: the edge method of the renders optimised (False: the paper's renderer).
    ``search`` > 0: first a greedy search of that many renders at ``SEARCH_SIZE`` pixels
    (``camera_proposal``), its renders and time counted in the metrics and the total time.
    """
    scene, (position, look_at), target = camera_calibration_problem(size, seed, angle)
    start_position = position.data.copy()
    with md.no_grad():
        _, truth = render(paper_scene(width=size, height=size), return_info=True)
    initial_view = object_in_view_pct(scene, truth)
    searched, before = None, None
    if search:
        with md.no_grad():
            before = render(scene).data.copy()
        searched = greedy_search(scene, [position, look_at], np.clip(target, 0.0, 1.0),
                                 camera_proposal([start_position, look_at.data]),
                                 renders=search, pool=SEARCH_POOL,
                                 factor=max(1, size // SEARCH_SIZE), seed=seed)  # fmt: skip
    run = _run(
        scene, [position, look_at], target, lr=lr, iters=iters, tol=tol, antialias=antialias,
        name=f"camera_calibration_{angle:g}deg{_edges_suffix(antialias)}_seed{seed}", **options,
    )  # fmt: skip
    if searched is not None:  # the run starts where the search started, and pays for it
        run.initial = before
        run.metrics["seconds_total"] += searched.seconds
        run.metrics.update(search_renders=searched.renders, search_seconds=searched.seconds)
    run.metrics.update(
        experiment="camera_calibration",
        seed=seed,
        angle_degrees=angle,
        antialias=antialias,
        initial_position_error_pct=relative_error_pct(start_position, TRUE_CAMERA),
        final_position_error_pct=relative_error_pct(position.data, TRUE_CAMERA),
        final_position=position.data.tolist(),
        iterations_to_tol=_first_below(run.history.loss, tol),
        iterations_to_half_percent=_first_below(
            [relative_error_pct(p[0], TRUE_CAMERA) for p in run.history.params], 0.5
        ),
        initial_object_in_view_pct=initial_view,
        final_object_in_view_pct=object_in_view_pct(scene, truth),
    )
    return run


def _edges_suffix(antialias: bool | str) -> str:
    """The output folder's mark of the edge method: none for the paper's renderer, so that
    a reproduction's edge and plain runs of one seed do not write over each other."""
    return {False: "", True: "_pairs"}.get(antialias, f"_{antialias}")


#: the search stage's image width for camera calibration (64: an eighth of 512), and the
#: blocks it compares (4 x 4 pixels: a 16 x 16 blurred image; with a sharp loss, nothing
#: in view scored better than a teapot in the wrong place, and the search kept nothing)
SEARCH_SIZE = 64
SEARCH_POOL = 4


def camera_proposal(start: list[np.ndarray], cone: float = 45.0, local: float = 5.0):
    """The search stage's proposals for a look-at camera starting at ``start`` (position,
    look-at point). First half of the budget: the viewing direction drawn uniformly from
    the cone of half-angle ``cone`` degrees around the *start's* (wide jumps: the loss has
    a barrier between a view showing nothing and the true one, so only a proposal that
    lands past it is accepted; centred on the start, not on the best so far, because the
    best may be a view showing nothing that points further away); second half: the best
    direction turned by a normally distributed angle of scale ``local`` degrees. The
    position moves by 0.1 units (normal, per axis) throughout."""
    start = [np.array(v, dtype=np.float64) for v in start]

    def propose(rng, best, progress):
        position, look_at = start if progress < 0.5 else best
        view = look_at - position
        axis = np.cross(view, rng.normal(size=3))  # a random axis perpendicular to the view
        if progress < 0.5:  # uniform on the cap: cos(angle) uniform in [cos(cone), 1]
            angle = math.degrees(math.acos(rng.uniform(math.cos(math.radians(cone)), 1.0)))
        else:
            angle = local * rng.normal()
        moved = position + rng.normal(size=3) * 0.1
        return [moved, moved + rotate(view, axis, angle)]

    return propose


def object_in_view_pct(scene, target_info) -> float:
    """How many pixels show the object, as a percentage of those of the target render
    (``target_info``: its ``RenderInfo``): 0 means nothing in view (no image loss has a
    gradient), 100 as many as in the target."""
    with md.no_grad():
        _, info = render(scene, return_info=True)
    shown = (info.prim_id >= 0).sum()
    return float(100.0 * shown / max(1, (target_info.prim_id >= 0).sum()))


def light_estimation_start(seed: int) -> tuple[np.ndarray, float]:
    """The light-estimation experiment's seeded start: (position (3,), intensity). The true
    position moved by a random direction times a distance drawn from [0.5, 1.0] x |truth|
    (kept above y = 1, so the light stays over the teapot), the intensity scaled by a
    factor from [0.3, 1.7]."""
    rng = np.random.default_rng(seed)
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    distance = rng.uniform(0.5, 1.0) * np.linalg.norm(TRUE_LIGHT)
    position = TRUE_LIGHT + distance * direction
    position[1] = max(position[1], 1.0)
    return position, TRUE_INTENSITY * rng.uniform(0.3, 1.7)


def light_estimation_problem(size: int, seed: int = 42, scene_of=None, **render_kwargs):
    """The light-estimation problem: (scene, [position, intensity], target).

    ``scene_of(light_position=..., light_intensity=...)`` builds the scene around a point
    light (default: the reference scene, ``size`` x ``size``). The target is its render
    (with ``render_kwargs``) with the light at ``TRUE_LIGHT`` and intensity
    ``TRUE_INTENSITY``; the scene returned starts from ``light_estimation_start(seed)``,
    its light's position and intensity require grad.
    """
    if scene_of is None:
        scene_of = lambda **light: paper_scene(width=size, height=size, **light)  # noqa: E731
    with md.no_grad():
        truth = scene_of(light_position=TRUE_LIGHT, light_intensity=TRUE_INTENSITY)
        target = render(truth, **render_kwargs).data.copy()
    start_light, start_intensity = light_estimation_start(seed)
    position = md.tensor(start_light, requires_grad=True)
    intensity = md.tensor(start_intensity, requires_grad=True)
    scene = scene_of(light_position=position, light_intensity=intensity)
    return scene, [position, intensity], target


def light_errors_pct(position, intensity) -> tuple[float, float]:
    """The paper's Eq. 5 and Eq. 6: the light's position and intensity errors, in percent
    (position (3,), intensity a scalar: arrays, tensors or numbers)."""
    position = np.asarray(getattr(position, "data", position), dtype=np.float64)
    intensity = float(np.asarray(getattr(intensity, "data", intensity)))
    return (
        relative_error_pct(position, TRUE_LIGHT),
        100 * abs(intensity - TRUE_INTENSITY) / TRUE_INTENSITY,
    )


def run_light_estimation(
    size: int = 512,
    iters: int = 500,
    seed: int = 42,
    lr: tuple[float, float] = (0.3, 20.0),
    tol: float = 1e-9,
    **options,
) -> ExperimentRun:
    """Section 5.7: recover a point light's position and intensity from a random start.

    Truth: light at (1, 4, 2) with I = 150. Start: ``light_estimation_start(seed)``.
    Reported: Eq. 5 (position) and Eq. 6 (intensity) errors.
    """
    scene, (position, intensity), target = light_estimation_problem(size, seed)
    start_light, start_intensity = position.data.copy(), intensity.item()

    run = _run(
        scene, [position, intensity], target, lr=list(lr), iters=iters, tol=tol,
        name=f"light_estimation_seed{seed}", **options,
    )  # fmt: skip
    initial_errors, final_errors = (
        light_errors_pct(start_light, start_intensity),
        light_errors_pct(position, intensity),
    )
    run.metrics.update(
        experiment="light_estimation",
        seed=seed,
        initial_position_error_pct=initial_errors[0],
        final_position_error_pct=final_errors[0],
        initial_intensity_error_pct=initial_errors[1],
        final_intensity_error_pct=final_errors[1],
        final_light=position.data.tolist(),
        final_intensity=intensity.item(),
        iterations_to_tol=_first_below(run.history.loss, tol),
    )
    return run


def run_material_recovery(
    size: int = 512,
    iters: int = 100,
    seed: int = 42,
    lr: float = 0.05,
    tol: float = 1e-10,
    **options,
) -> ExperimentRun:
    """Section 5.8: recover the teapot's albedo, projected onto [0, 1]^3 after every step.

    Truth: albedo drawn from [0.1, 0.9]^3; start: drawn from [0, 1]^3 (both seeded).
    Reported: the Euclidean RGB error at the start, after one iteration and at the end.
    """
    rng = np.random.default_rng(seed)
    true_albedo = rng.uniform(0.1, 0.9, size=3)
    start_albedo = rng.uniform(0.0, 1.0, size=3)
    target = render(paper_scene(width=size, height=size, albedo=true_albedo)).data.copy()
    albedo = md.tensor(start_albedo, requires_grad=True)
    scene = paper_scene(width=size, height=size, albedo=albedo)

    run = _run(
        scene, [albedo], target, lr=lr, iters=iters, tol=tol, project=md.optim.box(0.0, 1.0),
        name=f"material_recovery_seed{seed}", **options,
    )  # fmt: skip
    errors = [float(np.linalg.norm(p[0] - true_albedo)) for p in run.history.params]
    errors.append(float(np.linalg.norm(albedo.data - true_albedo)))
    run.metrics.update(
        experiment="material_recovery",
        seed=seed,
        true_albedo=true_albedo.tolist(),
        final_albedo=albedo.data.tolist(),
        initial_rgb_error=errors[0],
        rgb_error_after_1=errors[min(1, len(errors) - 1)],
        rgb_error_after_50=errors[min(50, len(errors) - 1)],
        final_rgb_error=errors[-1],
        iterations_to_tol=_first_below(run.history.loss, tol),
    )
    return run
