"""``minidiff.threads.borrowing``: Numba functions for a kernel's inner loop, compiled without
reference counts. They read and write the arrays they are handed (views included), give the
same values as the same function with counts, and Numba refuses one that would allocate
(an allocation needs the counts to be freed)."""

from __future__ import annotations

import numba
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from minidiff.threads import borrowing


def _row_sums(a, out):
    """out[i] = sum of row i of ``a``, through a view of each row."""
    for i in range(a.shape[0]):
        row = a[i]
        total = 0.0
        for j in range(row.shape[0]):
            total += row[j]
        out[i] = total
    return out[0] if out.shape[0] else 0.0


_borrowed_sums = borrowing(_row_sums)
_counted_sums = numba.njit(cache=True, error_model="numpy")(_row_sums)


@borrowing
def _allocates(n):
    return np.zeros(n).sum()


@given(arrays(np.float64, st.tuples(st.integers(0, 6), st.integers(0, 5))))
def test_a_borrowing_function_gives_what_the_counted_one_gives(a):
    got, want = np.full(a.shape[0], -1.0), np.full(a.shape[0], -1.0)
    first = _borrowed_sums(a, got)
    expected = _counted_sums(a, want)
    assert np.array_equal(got, want, equal_nan=True)
    assert np.array_equal(first, expected, equal_nan=True)
    in_order = np.array([sum(row.tolist(), 0.0) for row in a])  # the loop's order
    assert np.array_equal(got, in_order, equal_nan=True)


def test_a_borrowing_function_that_allocates_is_refused():
    with pytest.raises(numba.core.errors.TypingError, match="zeros"):
        _allocates(3)
