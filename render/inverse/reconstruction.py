"""3D reconstruction experiments, measured against ground truth: each ``run_*`` function
builds its targets from the true scene, starts from a seeded perturbation, optimises and
returns a dict of metrics (JSON-ready), the way the field reports them.

* ``run_pose``: the teapot's 6-DoF pose (a ``Transform``'s rotation and translation) from
  one view, from a random rotation of a given angle about a random axis plus a translation
  of 10 % of its size; gradients alone, or after a greedy search stage
  (``render.inverse.basin``). Success: rotation error < 1 degree and translation error
  < 1 % of the teapot's size (its bounding-box diagonal).
"""

from __future__ import annotations

import time

import numpy as np
from scipy.spatial.transform import Rotation

import minidiff as md
from render.inverse.basin import greedy_search
from render.inverse.optimize import optimize
from render.renderer import render
from render.scene.scene import Transform
from render.scene.teapot import paper_scene

#: pose success thresholds: degrees, and % of the object's size
POSE_ROTATION_OK = 1.0
POSE_TRANSLATION_OK = 1.0
#: the search stage's image width: 64 pixels (half of 128), never fewer (at 32 pixels
#: teapots turned 95-170 degrees matched better than the start turned 15)
SEARCH_SIZE = 64


def rotation_error_degrees(rotation: np.ndarray, truth: np.ndarray | None = None) -> float:
    """The angle of the rotation taking ``truth`` to ``rotation`` (rotation vectors in
    degrees; truth: the identity), in degrees, in [0, 180]."""
    r = Rotation.from_rotvec(np.radians(rotation))
    if truth is not None:
        r = r * Rotation.from_rotvec(np.radians(truth)).inv()
    return float(np.degrees(r.magnitude()))


def pose_problem(size: int, angle: float, seed: int):
    """(scene, [rotation, translation], target, object size): the paper scene's teapot
    placed by a Transform about its centre; the target is rendered at the identity pose;
    the start is a rotation of ``angle`` degrees about a random axis and a translation of
    10 % of the teapot's size in a random direction (both seeded)."""
    scene = paper_scene(size, size)
    teapot = scene.objects[0]
    vertices = teapot.vertices.data
    extent = float(np.linalg.norm(np.ptp(vertices, axis=0)))
    teapot.transform = Transform(pivot=vertices.mean(axis=0))
    target = render(scene).data.copy()
    rng = np.random.default_rng(seed)
    axis, direction = (v / np.linalg.norm(v) for v in rng.normal(size=(2, 3)))
    rotation = md.tensor(axis * angle, requires_grad=True)
    translation = md.tensor(direction * 0.1 * extent, requires_grad=True)
    teapot.transform.rotation, teapot.transform.translation = rotation, translation
    return scene, [rotation, translation], target, extent


def pose_proposal(extent: float):
    """The search stage's proposals for a pose: early on often a uniformly random rotation
    (a global jump: what finds a start that is upside down; with probability
    0.5 (1 - progress)), otherwise the best rotation turned by a random angle whose scale
    shrinks from 60 to 5 degrees; the translation moved by up to 5 % of the object's size,
    shrinking too."""

    def propose(rng, best, progress):
        rotation, translation = best
        if rng.random() < 0.5 * (1.0 - progress):
            turned = Rotation.random(random_state=rng)
        else:
            axis = rng.normal(size=3)
            step = np.radians(60.0 + (5.0 - 60.0) * progress) * abs(rng.normal())
            turned = Rotation.from_rotvec(axis / np.linalg.norm(axis) * step)
            turned = turned * Rotation.from_rotvec(np.radians(rotation))
        shift = rng.normal(size=3) * 0.05 * extent * (1.0 - progress)
        return [np.degrees(turned.as_rotvec()), translation + shift]

    return propose


def run_pose(
    size: int = 128,
    angle: float = 30.0,
    seed: int = 0,
    iters: int = 250,
    search: int = 0,
    antialias: bool | str = "boundary",
    lr: tuple[float, float] = (1.0, 0.02),
    quiet: bool = True,
) -> dict:
    """One pose run: ``iters`` Adam iterations (learning rates: degrees and scene units per
    step) with the edge method ``antialias``. ``search`` > 0: first ``greedy_search`` with
    that many renders (``SEARCH_SIZE`` wide), then a race of iters / 5 iterations from the
    start and from the search's best each, and the rest of the iterations from the winner.
    Returns the metrics: the rotation error (degrees), the translation error (% of the
    size), success, the loss, and the time spent (search and race included in
    ``seconds``)."""
    scene, params, target, extent = pose_problem(size, angle, seed)
    start = time.perf_counter()
    fit = {"lr": list(lr), "quiet": quiet, "render_kwargs": {"antialias": antialias}}
    searched, raced = None, 0
    if search:
        begin = [p.data.copy() for p in params]
        factor = max(1, size // SEARCH_SIZE)
        searched = greedy_search(scene, params, target, pose_proposal(extent), renders=search,
                                 factor=factor, seed=seed)  # fmt: skip
        # The search's best has the lowest low-resolution loss it saw, which can be another
        # minimum (a teapot turned 167 degrees matched better than the start turned 15):
        # race the start and the search's best for a fifth of the iterations, go on from
        # the one with the lower loss. Both races count in the time.
        raced = iters // 5
        finishes = []
        for values in (begin, [p.data.copy() for p in params]):
            for p, v in zip(params, values, strict=True):
                p.data[...] = v
            _, race = optimize(scene, params, target, max_iters=raced, **fit)
            finishes.append((race.loss[-1], [p.data.copy() for p in params]))
        for p, v in zip(params, min(finishes, key=lambda f: f[0])[1], strict=True):
            p.data[...] = v
    after_search = rotation_error_degrees(params[0].data)
    _, history = optimize(scene, params, target, max_iters=iters - raced, **fit)
    rotation = rotation_error_degrees(params[0].data)
    translation = float(100.0 * np.linalg.norm(params[1].data) / extent)
    return {
        "angle": angle,
        "seed": seed,
        "size": size,
        "search_renders": 0 if searched is None else searched.renders,
        "search_seconds": 0.0 if searched is None else searched.seconds,
        "rotation_error_after_search": after_search,
        "rotation_error_degrees": rotation,
        "translation_error_percent": translation,
        "success": rotation < POSE_ROTATION_OK and translation < POSE_TRANSLATION_OK,
        "rotation": params[0].data.tolist(),
        "translation": params[1].data.tolist(),
        "extent": extent,
        "initial_loss": history.loss[0],
        "final_loss": history.loss[-1],
        "iterations": history.iterations,
        "stalled": history.stalled,
        "seconds": time.perf_counter() - start,
        "seconds_per_iteration": sum(history.seconds) / max(1, len(history.seconds)),
        "antialias": antialias,
    }
