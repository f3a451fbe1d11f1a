"""Checks for the exercises in which you write a piece of the renderer yourself.

Each ``check_*`` function takes *your* function, runs it on many random cases next to the
library's own code, and raises ``AssertionError`` with the first case that differs, or
returns a short report when all agree. From a lesson (``lessons/``) or its solutions:

    from exercise_checks import check_intersection
    print(check_intersection(my_intersect))

(the lessons put their own folder on ``sys.path`` when run as scripts or notebooks).
"""

from __future__ import annotations

import numpy as np

import minidiff as md
import render
from render.scene.camera import primary_rays
from render.scene.teapot import teapot
from render.trace.accel import Accelerator
from render.trace.intersect import intersect_triangle, make_ray, pack_primitives


def check_intersection(intersect, n: int = 2000, seed: int = 0) -> str:
    """Your ray-triangle test against the library's Numba kernel (lesson 4).

    ``intersect(o, d, a, b, c)`` takes k rays (origins o, directions d: (k, 3)) and k
    triangles (corners a, b, c: (k, 3)) and returns (t, u, v), each (k,): the hit at
    ``o + t d = (1 - u - v) a + u b + v c`` with t > 0, or t = inf where the ray misses.
    """
    rng = np.random.default_rng(seed)
    a, b, c = (rng.normal(size=(n, 3)) for _ in range(3))
    o = rng.normal(size=(n, 3)) * 3
    # Aim most rays at a random point near the triangle, so that about half of them hit.
    target = (a + b + c) / 3 + rng.normal(size=(n, 3)) * 0.6
    d = target - o
    t, u, v = (np.asarray(x, float) for x in intersect(o, d, a, b, c))
    if t.shape != (n,) or u.shape != (n,) or v.shape != (n,):
        shapes = (t.shape, u.shape, v.shape)
        raise AssertionError(f"expected three arrays of shape ({n},), got {shapes}")
    table = pack_primitives(np.stack([a, b, c], axis=1), np.zeros((0, 3)), np.zeros(0),
                            np.arange(n))  # fmt: skip
    hits = 0
    for k in range(n):
        t_ref, u_ref, v_ref = intersect_triangle(table, k, make_ray(o[k], d[k], 0.0, np.inf))
        if np.isinf(t_ref) != np.isinf(t[k]):
            theirs = "a miss" if np.isinf(t_ref) else f"t = {t_ref:.6g}"
            ours = "a miss" if np.isinf(t[k]) else f"t = {t[k]:.6g}"
            raise AssertionError(f"ray {k}: the library says {theirs}, yours {ours}")
        if not np.isinf(t_ref):
            hits += 1
            ours = np.array([t[k], u[k], v[k]])
            theirs = np.array([t_ref, u_ref, v_ref])
            if np.abs(ours - theirs).max() > 1e-9 * (1 + np.abs(theirs).max()):
                raise AssertionError(f"ray {k}: (t, u, v) = {ours}, the library's {theirs}")
    return f"{n} rays, {hits} hits: every hit and miss, t, u and v as the library's"


def check_any_hit(occluded, n: int = 400, seed: int = 1) -> str:
    """Your any-hit BVH walk (a shadow ray) against ``Accelerator.occluded`` (lesson 4).

    ``occluded(acc, o, d, t_max)`` takes the library's tree ``acc`` (an ``Accelerator``
    over the teapot) and one ray (o, d: (3,)); it returns True if some triangle is hit at
    0 < t < t_max. The tree's layout is lesson 4's: ``acc.node_bounds`` (nodes, 6) (min
    xyz, max xyz), ``acc.node_first`` and ``acc.node_count`` (a leaf: count > 0 triangles
    from ``node_first`` in ``acc.leaf_prim``; an interior node: count 0, children
    ``node_first`` and ``node_first + 1``), the root is node 0; test a leaf's triangle k
    with ``intersect_triangle(acc.leaf_prim, k, make_ray(o, d, 0.0, t_max))``.
    """
    mesh = teapot()
    triangles = mesh.vertices.data[mesh.faces]
    acc = Accelerator(triangles)
    rng = np.random.default_rng(seed)
    o = rng.normal(size=(n, 3)) * 4
    d = rng.normal(size=(n, 3)) * 0.3 - o / 4  # roughly towards the teapot
    t_max = rng.uniform(0.5, 8.0, size=n)
    expected = acc.occluded(o, d, t_max, tmin=0.0)
    for k in range(n):
        mine = bool(occluded(acc, o[k], d[k], float(t_max[k])))
        if mine != bool(expected[k]):
            raise AssertionError(
                f"ray {k} (o = {o[k]}, d = {d[k]}, t_max = {t_max[k]:.4g}): the library says "
                f"{'blocked' if expected[k] else 'free'}, yours {'blocked' if mine else 'free'}"
            )
    return f"{n} shadow rays, {int(expected.sum())} blocked: every answer as the library's"


def check_lambert(shade) -> str:
    """Your Lambert shader on the tape against the renderer (lesson 5): values and gradients.

    ``shade(points, normals, albedo, light_position, intensity)``: k points and their unit
    normals ((k, 3) minidiff tensors), an albedo (3,), a point light's position (3,) and
    intensity (a scalar tensor); it returns the (k, 3) radiance towards the camera of a
    Lambertian surface lit by that light (no shadows, no ambient), written with minidiff
    operations so that ``backward`` reaches the light and the albedo.
    """
    n_px = 17
    camera = render.Camera(position=(0, 3, 0), look_at=(0, 0, 0), up=(0, 0, -1), fov=60.0,
                           width=n_px, height=n_px)  # fmt: skip
    s = 4.0
    quad = [(-s, 0, s), (s, 0, s), (s, 0, -s), (-s, 0, -s)]
    light_at = md.tensor([0.4, 1.7, -0.3], requires_grad=True)
    albedo = md.tensor([0.6, 0.3, 0.8], requires_grad=True)
    intensity = md.tensor(9.0, requires_grad=True)
    plane = render.Mesh(quad, [[0, 1, 2], [0, 2, 3]], render.Material(albedo))
    scene = render.Scene([plane], [render.PointLight(light_at, intensity)], camera)
    weights = np.random.default_rng(3).random((n_px, n_px, 3))
    image = render.render(scene)
    (image * md.tensor(weights)).sum().backward()
    leaves = (light_at, albedo, intensity)
    reference = [image.data.reshape(-1, 3)] + [p.grad.copy() for p in leaves]
    for p in (light_at, albedo, intensity):
        p.grad = None
    eye, directions = primary_rays(camera)
    points = eye + (-eye[1] / directions[:, 1])[:, None] * directions  # every ray hits y = 0
    normals = np.tile([0.0, 1.0, 0.0], (len(points), 1))
    mine = shade(md.tensor(points), md.tensor(normals), albedo, light_at, intensity)
    if not isinstance(mine, md.Tensor) or mine.shape != (len(points), 3):
        raise AssertionError(f"expected a ({len(points)}, 3) minidiff tensor, got {type(mine)}")
    (mine * md.tensor(weights.reshape(-1, 3))).sum().backward()
    names = ("radiance", "d/d light position", "d/d albedo", "d/d intensity")
    ours = [mine.data] + [
        np.zeros_like(p.data) if p.grad is None else p.grad for p in (light_at, albedo, intensity)
    ]
    for name, x, y in zip(names, ours, reference, strict=True):
        scale = max(float(np.abs(y).max()), 1e-300)
        if np.abs(np.asarray(x) - y).max() > 1e-9 * scale:
            raise AssertionError(f"{name}: yours {np.asarray(x).ravel()[:4]}..., the renderer's "
                                 f"{np.asarray(y).ravel()[:4]}...")  # fmt: skip
    return (f"{n_px * n_px} points: the radiance and its gradients (light position, albedo, "
            "intensity) as the renderer's, to 1e-9 relative")  # fmt: skip
