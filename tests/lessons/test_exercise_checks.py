"""The checks of the build-it-yourself exercises (``lessons/exercise_checks.py``) pass the
solutions' code (tests/lessons/test_lessons.py runs those) and reject code that is wrong."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

import minidiff as md
from render.trace.intersect import intersect_triangle, make_ray, pack_primitives

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "lessons"))
from exercise_checks import check_any_hit, check_intersection, check_lambert  # noqa: E402


def library_intersect(o, d, a, b, c, tmin=0.0):
    """The library's ray-triangle kernel in the exercise's form: (t, u, v) for k rays and k
    triangles; hits at t > tmin (tmin = -inf also takes those behind the ray's origin)."""
    table = pack_primitives(np.stack([a, b, c], axis=1), np.zeros((0, 3)), np.zeros(0))
    hits = [intersect_triangle(table, k, make_ray(o[k], d[k], tmin, np.inf)) for k in range(len(o))]
    return tuple(np.array(column) for column in zip(*hits, strict=True))


def test_intersection_check_passes_a_right_one_and_rejects_wrong_ones():
    check_intersection(library_intersect)
    with pytest.raises(AssertionError, match="the library says a miss"):  # hits behind the eye
        check_intersection(lambda *args: library_intersect(*args, tmin=-np.inf))
    with pytest.raises(AssertionError, match=r"\(t, u, v\)"):  # u and v swapped
        check_intersection(lambda *args: (lambda t, u, v: (t, v, u))(*library_intersect(*args)))


def test_any_hit_check_rejects_a_walk_that_ignores_t_max():
    def leaves_only(acc, o, d, t_max, respect_t_max=True):
        ray = make_ray(o, d, 0.0, t_max if respect_t_max else np.inf)
        limit = t_max if respect_t_max else np.inf
        return any(intersect_triangle(acc.leaf_prim, k, ray)[0] < limit
                   for k in range(len(acc.leaf_ids)))  # fmt: skip

    check_any_hit(leaves_only, n=60)  # brute force over every triangle is right
    with pytest.raises(AssertionError, match="the library says free"):
        check_any_hit(lambda *args: leaves_only(*args, respect_t_max=False), n=60)


def test_lambert_check_rejects_a_missing_pi_and_a_detached_light():
    def lambert(points, normals, albedo, light_position, intensity, pi=math.pi, detach=False):
        light = md.tensor(light_position.data) if detach else light_position
        to_light = light - points
        r2 = md.sum(to_light * to_light, axis=1, keepdims=True)
        cos = md.maximum(md.sum(normals * to_light, axis=1, keepdims=True) / md.sqrt(r2), 0.0)
        return albedo * (1 / pi) * intensity * cos / r2

    check_lambert(lambert)
    with pytest.raises(AssertionError, match="radiance"):
        check_lambert(lambda *args: lambert(*args, pi=3.0))
    with pytest.raises(AssertionError, match="d/d light position"):
        check_lambert(lambda *args: lambert(*args, detach=True))
