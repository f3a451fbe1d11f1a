"""The counter-based random numbers (``render.path.sample.random``): SplitMix64's published
finaliser, folded over (seed, path, dimension), the same bits on any thread count."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from render.path.sample.random import mix, uniform

MASK = 2**64 - 1


def _splitmix(z: int) -> int:
    """SplitMix64's output for state z (Steele, Lea and Flood 2014), in Python integers."""
    z = (z + 0x9E3779B97F4A7C15) & MASK
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & MASK
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & MASK
    return z ^ (z >> 31)


def test_the_hash_is_splitmix64():
    """Its first output from state 0 is SplitMix64's well-known 0xe220a8397b1dcdaf."""
    assert int(mix(np.uint64(0))) == 0xE220A8397B1DCDAF == _splitmix(0)


@settings(max_examples=50, deadline=None)
@given(
    seed=st.integers(0, MASK),
    paths=st.lists(st.integers(0, 2**63 - 1), min_size=1, max_size=40),
    dimension=st.integers(0, 2**62),
)
def test_each_number_is_the_hash_of_seed_path_and_dimension(seed, paths, dimension):
    got = uniform(seed, np.array(paths, np.int64), dimension)
    for value, path in zip(got, paths, strict=True):
        key = _splitmix(_splitmix(_splitmix(seed) ^ path) ^ dimension)
        assert value == (key >> 11) / 2.0**53
        assert 0.0 <= value < 1.0


def test_a_number_does_not_depend_on_the_others_drawn_with_it():
    paths = np.arange(100_000, dtype=np.int64)
    whole = uniform(7, paths, 3)
    some = np.array([0, 5, 99_999, 12_345])
    np.testing.assert_array_equal(uniform(7, paths[some], 3), whole[some])
    assert abs(whole.mean() - 0.5) < 0.01  # 100,000 uniforms: sd of the mean ~0.001
