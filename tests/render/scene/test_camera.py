"""``camera_directions`` off the tape (its formula compiled by ``minidiff.compile``; NumPy
for float32) gives the bits of its formula written on arrays, x right + y up + forward in
that order (what a compiled function traces and the tape's ``ray_directions`` applies), on
any number of threads."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from minidiff.threads import using_threads
from render.scene.camera import camera_directions


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
