"""3D reconstruction experiments, measured against ground truth: each ``run_*`` function
builds its targets from the true scene, starts from a seeded perturbation, optimises and
returns a dict of metrics (JSON-ready), the way the field reports them.

* ``run_pose``: the teapot's 6-DoF pose (a ``Transform``'s rotation and translation) from
  one view, from a random rotation of a given angle about a random axis plus a translation
  of 10 % of its size. By default a multi-start stage first (``POSE_STARTS`` turned copies
  of the start and the start itself, 40 cheap iterations each at 64 px; the lowest loss
  goes on to the full-size gradients); or gradients alone (``starts=0``), or a greedy
  search stage and a race (``search``; ``render.inverse.basin``). Success: rotation error
  < 1 degree and translation error < 1 % of the teapot's size (its bounding-box diagonal).
* ``run_shape``: a mesh's shape from many views with known cameras and lights, starting
  from an icosphere, with Large Steps, a Laplacian term or neither; Chamfer and Hausdorff
  distances to the true surface and the PSNR of held-out views.
"""

from __future__ import annotations

import time

import numpy as np
from scipy.spatial.transform import Rotation

import minidiff as md
from render.inverse.basin import greedy_search, multi_start
from render.inverse.experiments import relative_error_pct
from render.inverse.optimize import image_loss, optimize
from render.inverse.shape import (
    LargeStepsAdam,
    icosphere,
    laplacian_loss,
    mesh_laplacian,
    surface_distances,
    weld,
)
from render.renderer import render
from render.scene.image import psnr
from render.scene.scene import Camera, DirectionalLight, Material, Mesh, Scene, Transform
from render.scene.teapot import paper_scene

#: pose success thresholds: degrees, and % of the object's size
POSE_ROTATION_OK = 1.0
POSE_TRANSLATION_OK = 1.0
#: the search stage's image width: 64 pixels (half of 128), never fewer (at 32 pixels
#: teapots turned 95-170 degrees matched better than the start turned 15)
SEARCH_SIZE = 64
#: the default multi-start stage (``run_pose``): the start and the start turned by
#: ``POSE_START_TURN`` degrees about each of the six directions +-x, +-y, +-z (world axes),
#: ``POSE_START_ITERS`` iterations each at ``POSE_START_SIZE`` pixels with the cheaper
#: pair-wise edges (``antialias=True``: about 25 ms per iteration at 64 px where the
#: boundary integral costs ~100 ms at any size). Chosen on seeds 100-109 from 30 degrees
#: (docs/reconstruction/pose_seeds.md), where it took the gradients alone from 8 of 10
#: successes to 10 of 10.
POSE_STARTS = 6
POSE_START_TURN = 30.0
POSE_START_ITERS = 40
POSE_START_SIZE = 64


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


def pose_starts(
    rotation: np.ndarray,
    translation: np.ndarray,
    count: int = POSE_STARTS,
    turn: float = POSE_START_TURN,
) -> list[list[np.ndarray]]:
    """The multi-start stage's starts: the given pose, then ``count`` (0-6) copies of it
    turned by ``turn`` degrees about +x, +y, +z, -x, -y, -z (in that order; a turn in world
    space, applied after the rotation), all with the given translation. Rotations are
    rotation vectors in degrees, as ``Transform.rotation`` holds them."""
    if isinstance(count, bool) or not isinstance(count, int) or not 0 <= count <= 6:
        raise ValueError(f"pose_starts: count must be an int in 0..6, got {count!r}")
    start = Rotation.from_rotvec(np.radians(rotation))
    axes = np.vstack([np.eye(3), -np.eye(3)])[:count]
    turned = [Rotation.from_rotvec(np.radians(turn) * axis) * start for axis in axes]
    values = [np.array(rotation, dtype=np.float64)]
    values += [np.degrees(r.as_rotvec()) for r in turned]
    return [[v, np.array(translation, dtype=np.float64)] for v in values]


def run_pose(
    size: int = 128,
    angle: float = 30.0,
    seed: int = 0,
    iters: int = 250,
    search: int = 0,
    antialias: bool | str = "boundary",
    lr: tuple[float, float] = (1.0, 0.02),
    quiet: bool = True,
    race: float = 0.5,
    starts: int | None = None,
) -> dict:
    """One pose run: ``iters`` Adam iterations (learning rates: degrees and scene units per
    step) with the edge method ``antialias``, at full size, after one of two optional
    stages. ``starts`` (default ``POSE_STARTS`` when there is no search, else 0) > 0: first
    ``multi_start`` from ``pose_starts`` (the start and ``starts`` turned copies),
    ``POSE_START_ITERS`` iterations each at ``POSE_START_SIZE`` pixels (or the full size if
    smaller) with ``antialias=True``, and the full-size run goes on from the lowest loss.
    ``search`` > 0: first ``greedy_search`` with that many renders (``SEARCH_SIZE``
    wide), then a race of ``race`` x iters iterations from the start and from the search's
    best each, and the rest from the winner (not with ``starts`` > 0).
    Returns the metrics: the rotation error (degrees), the translation error (% of the
    size), success, the loss, and the time spent (search, race and starts included in
    ``seconds``)."""
    if starts is None:
        starts = 0 if search else POSE_STARTS
    if starts and search:
        raise ValueError("run_pose: starts and search are alternatives; pass one of them")
    scene, params, target, extent = pose_problem(size, angle, seed)
    start = time.perf_counter()
    fit = {"lr": list(lr), "quiet": quiet, "render_kwargs": {"antialias": antialias}}
    searched, raced, started = None, 0, None
    if starts:
        factor = max(f for f in range(1, max(1, size // POSE_START_SIZE) + 1) if size % f == 0)
        started = multi_start(scene, params, target, pose_starts(*(p.data for p in params), starts),
                              iters=POSE_START_ITERS, factor=factor, lr=list(lr), quiet=True,
                              render_kwargs={"antialias": True})  # fmt: skip
    if search:
        begin = [p.data.copy() for p in params]
        factor = max(1, size // SEARCH_SIZE)
        searched = greedy_search(scene, params, target, pose_proposal(extent), renders=search,
                                 factor=factor, seed=seed)  # fmt: skip
        # The search's best has the lowest low-resolution loss it saw, which can be another
        # minimum (a teapot turned 167 degrees matched better than the start turned 15):
        # race the start and the search's best for a fraction ``race`` of the iterations
        # (with a fifth, 4 of 10 runs at 30-45 degrees failed where gradients alone failed
        # once: a start in the right basin had not yet passed a wrong minimum's loss after
        # 40 iterations), go on from the one with the lower loss. Both races count in the
        # time.
        raced = int(iters * race)
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
        "starts": starts,
        "start_renders": 0 if started is None else started.renders,
        "start_seconds": 0.0 if started is None else started.seconds,
        "start_losses": [] if started is None else started.losses,
        "start_kept": None if started is None else started.best,
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


# --------------------------------------------------------------------------------------
# Shape from views
# --------------------------------------------------------------------------------------


#: The unit directions of ``dented_blob``'s three dents, c_k.
DENT_CENTRES = np.array([[1.0, 0.3, 0.2], [-0.5, 0.2, 0.9], [-0.3, -0.6, -0.8]])
DENT_CENTRES /= np.linalg.norm(DENT_CENTRES, axis=1, keepdims=True)


def dented_blob(subdivisions: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """A genus-0 test shape with concavities, generated in code: the unit icosphere with
    each vertex moved along its direction d to radius
    r(d) = 1 + 0.25 d_y^2 - 0.35 sum_k exp(-|d - c_k|^2 / 0.12), three dents (c_k) that
    are concave from outside (a sphere cannot show them in its silhouette from most views;
    shading must)."""
    v, f = icosphere(subdivisions)
    d = v / np.linalg.norm(v, axis=1, keepdims=True)
    dents = sum(np.exp(-np.sum((d - c) ** 2, axis=1) / 0.12) for c in DENT_CENTRES)
    radius = 1.0 + 0.25 * d[:, 1] ** 2 - 0.35 * dents
    return d * radius[:, None], f


def view_cameras(count: int, size: int, distance: float = 4.0, seed: int = 0) -> list[Camera]:
    """``count`` cameras looking at the origin from ``distance``, spread evenly over the
    sphere (a Fibonacci lattice, turned by a seeded random rotation)."""
    k = np.arange(count) + 0.5
    polar, azimuth = np.arccos(1.0 - 2.0 * k / count), np.pi * (1.0 + 5.0**0.5) * k
    points = np.stack([np.sin(polar) * np.cos(azimuth), np.cos(polar),
                       np.sin(polar) * np.sin(azimuth)], axis=1)  # fmt: skip
    points = Rotation.random(random_state=np.random.default_rng(seed)).apply(points)
    cameras = []
    for p in points * distance:
        up = (0.0, 1.0, 0.0) if abs(p[1]) < 0.95 * distance else (1.0, 0.0, 0.0)
        cameras.append(Camera(p, (0.0, 0.0, 0.0), up, fov=40.0, width=size, height=size))
    return cameras


#: The shape experiment's lights: four directional lights from the corners of a
#: tetrahedron (every surface normal faces at least one of them at up to 71 degrees), red,
#: green, blue and a dimmer white, so that a pixel's colour tells the lights apart (as in
#: coloured photometric stereo). With two lights from opposite sides, a dent facing
#: neither was lit by ambient light only and stayed a third unrecovered.
SHAPE_LIGHTS = (
    ((-1.0, -1.0, -1.0), (1.0, 0.25, 0.25), 2.0),
    ((1.0, 1.0, -1.0), (0.25, 1.0, 0.25), 2.0),
    ((1.0, -1.0, 1.0), (0.25, 0.25, 1.0), 2.0),
    ((-1.0, 1.0, 1.0), (1.0, 1.0, 1.0), 1.0),
)


def shape_scene(vertices, faces) -> Scene:
    """The shape experiment's scene: the mesh (grey, smooth shading) lit by
    ``SHAPE_LIGHTS`` and a little ambient light, so that every view shows shading."""
    material = Material((0.7, 0.7, 0.7), ambient=0.05)
    lights = [DirectionalLight(d, e, color=c) for d, c, e in SHAPE_LIGHTS]
    mesh = Mesh(vertices, faces, material, smooth=True)
    return Scene([mesh], lights, view_cameras(1, 8)[0])


def run_shape(
    target_shape: tuple[np.ndarray, np.ndarray],
    views: int = 16,
    size: int = 128,
    iters: int = 300,
    method: str = "large_steps",
    batch: int = 4,
    start_subdivisions: int = 4,
    lr: float = 0.03,
    lam: float = 4.0,
    weight: float = 1e-3,
    antialias: bool | str = "boundary",
    held_out: int = 8,
    seed: int = 0,
    quiet: bool = True,
    samples: int = 20_000,
    region: tuple[np.ndarray, np.ndarray] | None = None,
) -> dict:
    """Shape from ``views`` images of ``target_shape`` (vertices, faces), known cameras
    and lights, starting from an icosphere of radius 1: ``method`` "large_steps"
    (``LargeStepsAdam``, lam), "laplacian" (Adam on the vertices, loss + weight * the
    Laplacian term) or "none" (Adam on the vertices). ``batch`` views per iteration (all
    if fewer). Returns Chamfer and Hausdorff distances (% of the target's bounding-box
    diagonal, from ``samples`` points per surface; with a ``region`` box, its share of the
    Chamfer sum and the Chamfer distance outside it: ``surface_distances``), the PSNR of
    ``held_out`` other views, and the times; and, not JSON, under "mesh" the recovered
    (vertices, faces) and under "held_out_images" (2, H, W, 3) the first held-out view's
    target and render."""
    if method not in ("large_steps", "laplacian", "none"):
        raise ValueError(f'run_shape: method must be "large_steps", "laplacian" or "none", '
                         f"got {method!r}")  # fmt: skip
    truth = shape_scene(*target_shape)
    cameras = view_cameras(views + held_out, size, seed=seed)
    seen, unseen = cameras[:views], cameras[views:]
    with md.no_grad():
        targets = [render(truth.with_camera(c)).data.copy() for c in cameras]
    v0, f0 = icosphere(start_subdivisions)
    vertices = md.tensor(v0, requires_grad=True)
    scene = shape_scene(vertices, f0)
    pairs = [(scene.with_camera(c), t) for c, t in zip(seen, targets, strict=False)]
    loss_fn = image_loss
    if method == "laplacian":
        lap = mesh_laplacian(f0, len(v0))
        loss_fn = lambda image, target: (  # noqa: E731
            image_loss(image, target) + weight * laplacian_loss(lap, vertices)
        )
    optimizer = LargeStepsAdam(vertices, f0, lam=lam, lr=lr) if method == "large_steps" else None
    start = time.perf_counter()
    _, history = optimize(pairs, [vertices], loss_fn=loss_fn, optimizer=optimizer, lr=lr,
                          max_iters=iters, batch=min(batch, views), seed=seed, quiet=quiet,
                          render_kwargs={"antialias": antialias})  # fmt: skip
    seconds = time.perf_counter() - start
    distances = surface_distances(vertices.data, f0, *target_shape, samples=samples,
                                  region=region)  # fmt: skip
    with md.no_grad():
        seen_held = [np.clip(render(scene.with_camera(c)).data, 0, 1) for c in unseen]
    held = [psnr(image, np.clip(t, 0, 1)) for image, t in zip(seen_held, targets[views:],
                                                              strict=True)]  # fmt: skip
    return {
        "views": views,
        "method": method,
        "size": size,
        "chamfer_percent": distances.chamfer,
        "hausdorff_percent": distances.hausdorff,
        "hausdorff_at": distances.worst.tolist(),
        "region_share_percent": distances.region_share,
        "chamfer_outside_region_percent": distances.chamfer_outside,
        "held_out_psnr": float(np.mean(held)),
        **history.summary(seconds),
        "vertices": len(v0),
        "mesh": (vertices.data.copy(), f0),
        "held_out_images": np.stack([np.clip(targets[views], 0, 1), seen_held[0]]),
    }


# --------------------------------------------------------------------------------------
# Everything at once
# --------------------------------------------------------------------------------------

#: The joint experiment's cameras: the paper's, and three more around the teapot.
JOINT_CAMERAS = [(3.0, 2.0, 5.0), (-4.0, 2.5, 3.5), (-3.0, 1.5, -5.0), (5.0, 3.0, -2.0)]


def _bumps(vertices: np.ndarray) -> np.ndarray:
    """The true shape offsets of the joint experiment: a smooth field of up to 0.08 units
    (2 % of the teapot's size), a function of position."""
    x, y, z = vertices.T
    return 0.08 * np.stack([np.sin(2.0 * y) * np.cos(z), 0.5 * np.sin(1.5 * x),
                            np.cos(2.0 * x) * np.sin(y)], axis=1)  # fmt: skip


def run_joint(
    views: int = 4,
    size: int = 128,
    iters: int = 400,
    seed: int = 0,
    antialias: bool | str = "boundary",
    weight: float = 0.1,
    quiet: bool = True,
    samples: int = 20_000,
) -> dict:
    """Camera pose (the first camera's position and look-at point; the others are known
    and fix the frame), the light's position and intensity, the albedo and per-vertex
    shape offsets of the teapot, all at once, from ``views`` images of the paper scene
    (whose teapot is Lambertian: only albedo x intensity reaches the image, so each is
    reported with their product). The truth: the paper scene with the teapot bent by
    ``_bumps``; the start: each parameter perturbed (seeded), the offsets zero. One Adam,
    a learning rate per parameter, the Laplacian of the offsets (``weight``) as the
    regulariser. Returns each parameter's error (the shape's from ``samples`` points per
    surface) and, not JSON, under "images" (3, H, W, 3) the first view's target, start and
    result."""
    rng = np.random.default_rng(seed)
    truth = paper_scene(size, size)
    # The teapot welded (793 positions instead of 1,120; the same triangles): the patches'
    # seam vertices move as one, so the mesh bends but never tears (torn seams would become
    # hundreds of new silhouette edges, all meeting at the poles).
    teapot = truth.objects[0]
    base, faces, _ = weld(teapot.vertices.data, teapot.faces)
    true_vertices = base + _bumps(base)
    truth.objects[0] = teapot = Mesh(true_vertices, faces, teapot.material, smooth=teapot.smooth)
    cameras = [
        Camera.from_focal_length(50.0, 36.0, position=p, look_at=(0.0, 0.0, 0.0), width=size,
                                 height=size)
        for p in JOINT_CAMERAS[:views]
    ]  # fmt: skip
    with md.no_grad():
        targets = [render(truth.with_camera(c)).data.copy() for c in cameras]
    true = {"position": np.array(JOINT_CAMERAS[0]), "look_at": np.zeros(3),
            "light": truth.lights[0].position.data.copy(),
            "intensity": float(truth.lights[0].intensity.data),
            "albedo": teapot.material.albedo.data.copy()}  # fmt: skip
    position = md.tensor(true["position"] + rng.normal(size=3) * 0.3, requires_grad=True)
    look_at = md.tensor(rng.normal(size=3) * 0.2, requires_grad=True)
    light = md.tensor(true["light"] * (1 + 0.2 * rng.normal(size=3)), requires_grad=True)
    intensity = md.tensor(true["intensity"] * rng.uniform(0.6, 1.4), requires_grad=True)
    albedo = md.tensor(rng.uniform(0.2, 0.8, 3), requires_grad=True)
    vertices = md.tensor(base.copy(), requires_grad=True)
    scene = paper_scene(size, size, light_position=light, light_intensity=intensity,
                        albedo=albedo, camera_position=position, look_at=look_at)  # fmt: skip
    scene.objects[0] = Mesh(vertices, faces, scene.objects[0].material, smooth=teapot.smooth)
    others = zip(cameras[1:], targets[1:], strict=True)
    pairs = [(scene, targets[0])] + [(scene.with_camera(c), t) for c, t in others]
    lap = mesh_laplacian(faces, len(base))

    def loss_fn(image, target):
        return image_loss(image, target) + weight * laplacian_loss(lap, vertices - base)

    params = [position, look_at, light, intensity, albedo, vertices]

    def errors(prefix: str) -> dict:
        """Each parameter's error now, the keys prefixed with ``prefix``."""
        product, true_product = albedo.data * intensity.data, true["albedo"] * true["intensity"]
        values = {
            "camera_position_error_percent": relative_error_pct(position.data, true["position"]),
            "look_at_error": float(np.linalg.norm(look_at.data)),
            # Only the direction to the look-at point reaches an image, not its distance.
            "view_direction_error_degrees": _angle_degrees(
                look_at.data - position.data, -true["position"]
            ),  # fmt: skip
            "light_position_error_percent": relative_error_pct(light.data, true["light"]),
            "intensity_error_percent": relative_error_pct(intensity.data, true["intensity"]),
            "albedo_error_percent": relative_error_pct(albedo.data, true["albedo"]),
            "albedo_times_intensity_error_percent": relative_error_pct(product, true_product),
        }
        return {prefix + key: value for key, value in values.items()}

    initial = errors("initial_")
    with md.no_grad():
        before = render(scene).data.copy()
    start = time.perf_counter()
    _, history = optimize(pairs, params, loss_fn=loss_fn, lr=[0.01, 0.01, 0.05, 3.0, 0.01, 0.002],
                          max_iters=iters, quiet=quiet,
                          render_kwargs={"antialias": antialias})  # fmt: skip
    seconds = time.perf_counter() - start
    with md.no_grad():
        after = render(scene).data.copy()
    return {
        "views": views,
        "size": size,
        **errors(""),
        **initial,
        "shape_chamfer_percent": surface_distances(
            vertices.data, faces, true_vertices, faces
        ).chamfer,  # fmt: skip
        "shape_chamfer_at_start_percent": surface_distances(
            base, faces, true_vertices, faces
        ).chamfer,  # fmt: skip
        **history.summary(seconds),
        "images": np.clip(np.stack([targets[0], before, after]), 0.0, 1.0),
    }


def _angle_degrees(a: np.ndarray, b: np.ndarray) -> float:
    cos = np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b))
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
