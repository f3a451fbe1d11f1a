"""``camera_directions`` off the tape (its formula compiled by ``minidiff.compile``; NumPy
for float32) gives the bits of its formula written on arrays, x right + y up + forward in
that order (what a compiled function traces and the tape's ``ray_directions`` applies), on
any number of threads; so do the parallel passes ``sample_coords`` (the image-plane points
of some pixels' samples) and ``ray_ends`` (where rays end), against their NumPy forms."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from minidiff import compiler
from minidiff.threads import using_threads
from render.scene.camera import (
    camera_directions,
    ray_ends,
    sample_coords,
    subpixel_offsets,
    to_image_plane,
)


@pytest.fixture(autouse=True)
def every_kernel_on_the_threads(monkeypatch):
    """Compiled kernels on the threads however small their batch (the test is of the
    two-thread path too)."""
    monkeypatch.setattr(compiler, "PARALLEL_WORK", 0)


@settings(max_examples=20, deadline=None)
@given(
    n=st.integers(0, 3) | st.integers(65_536, 140_000),  # one job, and two on two threads
    seed=st.integers(0, 2**32 - 1),
    scale=st.sampled_from([1e-3, 1.0, 1e3]),
    dtype=st.sampled_from([np.float64, np.float32]),
)
def test_camera_directions_are_the_formulas_bits(n, seed, scale, dtype):
    rng = np.random.default_rng(seed)
    coords = rng.uniform(-scale, scale, (n, 2)).astype(dtype)
    right, up, forward = (rng.normal(size=(3, 3)) * scale).astype(dtype)
    want = coords[:, :1] * right + coords[:, 1:] * up + forward
    for threads in (1, 2):
        with using_threads(threads):
            got = camera_directions(coords, right, up, forward)
        assert got.shape == (n, 3) and got.dtype == dtype
        np.testing.assert_array_equal(got, want)


@settings(max_examples=20, deadline=None)
@given(
    m=st.integers(0, 3) | st.integers(16_384, 40_000),  # one job, and two on two threads
    spp=st.sampled_from([1, 4, 16]),
    width=st.integers(1, 700),
    height=st.integers(1, 700),
    seed=st.integers(0, 2**32 - 1),
)
def test_sample_coords_are_to_image_planes_bits(m, spp, width, height, seed):
    pixels = np.random.default_rng(seed).integers(0, width * height, m)
    corner = np.stack([pixels % width, pixels // width], axis=1).astype(np.float64)
    offsets = subpixel_offsets(spp)
    want = to_image_plane((corner[:, None] + offsets).reshape(-1, 2), width, height)
    for threads in (1, 2):
        with using_threads(threads):
            got = sample_coords(pixels, spp, width, height)
        assert got.shape == (m * spp, 2)
        np.testing.assert_array_equal(got, want)


@settings(max_examples=20, deadline=None)
@given(
    n=st.integers(0, 3) | st.integers(16_384, 40_000),
    seed=st.integers(0, 2**32 - 1),
    scale=st.sampled_from([1e-3, 1.0, 1e3]),
)
def test_ray_ends_are_eye_plus_depth_times_direction(n, seed, scale):
    rng = np.random.default_rng(seed)
    eye = rng.normal(size=3) * scale
    directions = rng.normal(size=(n, 3))
    depth = np.where(rng.random(n) < 0.2, np.inf, rng.uniform(0, 10 * scale, n))
    rays = np.flatnonzero(np.isfinite(depth))
    want = np.take(depth, rays)[:, None] * np.take(directions, rays, axis=0) + eye
    for threads in (1, 2):
        with using_threads(threads):
            got = ray_ends(eye, directions, depth, rays)
        assert got.shape == (len(rays), 3)
        np.testing.assert_array_equal(got, want)
