"""The compiled ray set-up (camera coordinates, shadow rays) against plain NumPy formulas,
bit for bit."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

import render
from render.scene.camera import image_plane_coords, subpixel_offsets
from render.trace.visibility import shadow_offset, shadow_rays


def plain_image_plane_coords(camera: render.Camera, ray_ids: np.ndarray, spp: int):
    """The formula of ``image_plane_coords`` in NumPy (ray r: pixel r // spp, row-major from
    the top, sample r % spp)."""
    offsets = subpixel_offsets(spp)
    pixel, sample = np.divmod(ray_ids, spp)
    py, px = np.divmod(pixel, camera.width)
    x = 2.0 * (px + offsets[sample, 0]) / camera.width - 1.0
    y = 1.0 - 2.0 * (py + offsets[sample, 1]) / camera.height
    return np.stack([x, y], axis=1).reshape(len(ray_ids), 2)


@settings(max_examples=40, deadline=None)
@given(
    width=st.integers(1, 700),
    height=st.integers(1, 700),
    spp=st.sampled_from([1, 4, 9, 16]),
    n=st.integers(0, 3000),
    seed=st.integers(0, 2**16),
)
def test_image_plane_coords_equal_the_plain_formula(width, height, spp, n, seed):
    camera = render.Camera((0.0, 0.0, 5.0), (0.0, 0.0, 0.0), width=width, height=height)
    ids = np.random.default_rng(seed).integers(0, width * height * spp, size=n)
    got = image_plane_coords(camera, ids, spp)
    np.testing.assert_array_equal(got, plain_image_plane_coords(camera, ids, spp))
    assert got.shape == (n, 2) and got.dtype == np.float64


def plain_point_light_rays(position, points, offset):
    """``shadow_rays`` for a point light in NumPy: origins moved ``offset`` towards the light
    (lit, with tmax = 0 and an arbitrary direction, when the light is that close), the
    unnormalised direction to the light, tmax just short of it."""
    to_light = position - points
    distance = np.sqrt((to_light[:, 0] * to_light[:, 0] + to_light[:, 1] * to_light[:, 1])
                       + to_light[:, 2] * to_light[:, 2])  # fmt: skip
    near = distance <= 2.0 * offset
    fraction = offset / np.where(near, 1.0, distance)
    origins = points + fraction[:, None] * to_light
    directions = position - origins
    directions[near] = (0.0, 1.0, 0.0)
    tmax = np.where(near, 0.0, 1.0 - fraction / (1.0 - fraction))
    return origins, directions, tmax


@settings(max_examples=40, deadline=None)
@given(
    n=st.integers(0, 2000),
    scale=st.sampled_from([1e-3, 1.0, 1e4]),
    near_light=st.booleans(),
    seed=st.integers(0, 2**16),
)
def test_point_light_shadow_rays_equal_the_plain_formula(n, scale, near_light, seed):
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(n, 3)) * scale
    position = rng.normal(size=3) * scale
    if near_light and n:
        points[: n // 2] = position + 1e-12 * scale  # within the offset of the light
    light = render.PointLight(position, 10.0)
    start = rng.integers(0, 50, size=n)
    rays = shadow_rays(light, points, start, 40, 2.0 * scale)
    offset = shadow_offset(points, 2.0 * scale, position)
    for got, expected in zip(
        (rays.origins, rays.directions, rays.tmax),
        plain_point_light_rays(position, points, offset),
        strict=True,
    ):
        np.testing.assert_array_equal(got, expected)
    np.testing.assert_array_equal(rays.ignore_prim, np.where(start < 40, start, -1))
