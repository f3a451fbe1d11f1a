"""The checks of the build-it-yourself exercises (``lessons/exercise_checks.py``) pass the
solutions' code (tests/lessons/test_lessons.py runs those) and reject code that is wrong."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

import minidiff as md
from render.trace.intersect import intersect_triangle, make_ray

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "lessons"))
from exercise_checks import check_any_hit, check_intersection, check_lambert  # noqa: E402


def moller_trumbore(o, d, a, b, c, allow_behind=False):
    e1, e2 = b - a, c - a
    p = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, p)
    safe = np.where(det != 0, det, 1.0)
    s = o - a
    u = np.einsum("ij,ij->i", s, p) / safe
    q = np.cross(s, e1)
    v = np.einsum("ij,ij->i", d, q) / safe
    t = np.einsum("ij,ij->i", e2, q) / safe
    hit = (det != 0) & (u >= 0) & (v >= 0) & (u + v <= 1) & ((t > 0) | allow_behind)
    return np.where(hit, t, np.inf), np.where(hit, u, 0.0), np.where(hit, v, 0.0)


def test_intersection_check_passes_a_right_one_and_rejects_wrong_ones():
    check_intersection(moller_trumbore)
    with pytest.raises(AssertionError, match="the library says a miss"):
        check_intersection(lambda *args: moller_trumbore(*args, allow_behind=True))
    with pytest.raises(AssertionError, match=r"\(t, u, v\)"):  # u and v swapped
        check_intersection(lambda *args: (lambda t, u, v: (t, v, u))(*moller_trumbore(*args)))


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
