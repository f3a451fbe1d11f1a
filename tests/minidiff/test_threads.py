"""``minidiff.threads``: ``borrowing``, Numba functions for a kernel's inner loop compiled
without reference counts: they read and write the arrays they are handed (views included),
give the same values as the same function with counts, and Numba refuses one that would
allocate (an allocation needs the counts to be freed); ``inlined``, such a function
compiled once for every caller, which gives what the same function compiled plainly
gives. ``beside``, a step run on a second thread while the caller goes on: the caller's
threads shared, its context kept, its result or exception handed back, and nothing left
running when the block ends. ``share_tasks``, tasks the work posts for the block's thread to
take once the block has ended: the same results in order, whoever runs them."""

from __future__ import annotations

import threading
import time
from functools import partial

import numba
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from numba.core.compiler import Flags

import minidiff as md
from minidiff.threads import (
    beside,
    borrowing,
    inlined,
    share_tasks,
    thread_count,
    using_threads,
)


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


_inlined_sums = inlined(_row_sums)


@numba.njit(error_model="numpy")  # not cached: compiled here, it asks for the callee's code
def _twice_through_inlined(a, out):
    """Two callers' worth of calls of the inlined function, with different array layouts."""
    return _inlined_sums(a, out) + _inlined_sums(a[::-1], out[::-1])


@given(arrays(np.float64, st.tuples(st.integers(0, 6), st.integers(0, 5))))
def test_an_inlined_function_gives_what_the_plain_function_gives(a):
    """One compile per signature (not a copy per call site), the same values as the
    function compiled with reference counts."""
    got, want = np.full(a.shape[0], -1.0), np.full(a.shape[0], -1.0)
    total = _twice_through_inlined(a, got)
    expected = _counted_sums(a, want) + _counted_sums(a[::-1], want[::-1])
    assert np.array_equal(got, want, equal_nan=True)
    assert np.array_equal(total, expected, equal_nan=True)
    if hasattr(Flags, "forceinline"):  # (else Numba's own inlining: no compile of its own)
        assert 1 <= len(_inlined_sums.signatures) <= 2  # C-ordered and reversed views


def test_a_borrowing_function_that_allocates_is_refused():
    with pytest.raises(numba.core.errors.TypingError, match="zeros"):
        _allocates(3)


@pytest.mark.parametrize("count", [2, 3, 4, 7])
def test_beside_runs_the_work_on_another_thread_with_the_callers_threads_shared(count):
    """While both run, the work's kernels get half the threads and the block's the rest;
    once the block has ended, the work's get them all, and the other way round."""
    seen, recorded = {}, threading.Event()

    def work():
        seen["thread"] = threading.get_ident()
        seen["during"] = thread_count()
        recorded.set()
        deadline = time.monotonic() + 10.0
        while thread_count() != count and time.monotonic() < deadline:
            time.sleep(0.001)  # the block's end hands its threads over
        seen["after"] = thread_count()
        return "done"

    with using_threads(count):
        with beside(work) as result:
            inside = thread_count()
            assert recorded.wait(10.0)
        assert thread_count() == count  # restored after the block
    assert result() == "done"
    assert seen["thread"] != threading.get_ident()
    assert (seen["during"], inside) == (count // 2, count - count // 2)
    assert seen["after"] == count
    read = threading.Event()

    def second():
        during = thread_count()
        assert read.wait(10.0)  # the block has read its count while this work ran
        return during

    with using_threads(count):
        with beside(second) as result:
            first = thread_count()
            read.set()
            deadline = time.monotonic() + 10.0
            while thread_count() != count and time.monotonic() < deadline:
                time.sleep(0.001)  # the work's end hands its threads over
            last = thread_count()
    assert (result(), first, last) == (count // 2, count - count // 2, count)


def test_beside_on_one_thread_runs_the_work_here_before_the_block():
    order = []
    with using_threads(1):
        with beside(lambda: order.append(("work", threading.get_ident())) or 5) as result:
            order.append(("block", threading.get_ident()))
            inside = thread_count()
    assert result() == 5 and inside == 1
    assert order == [("work", threading.get_ident()), ("block", threading.get_ident())]


def test_beside_without_work_keeps_every_thread_for_the_block():
    with using_threads(4):
        with beside(None) as result:
            inside = thread_count()
    assert result() is None and inside == 4


@pytest.mark.parametrize("count", [1, 2])
def test_beside_hands_the_works_exception_to_result(count):
    def work():
        raise KeyError("from the work")

    ran = []
    with using_threads(count):
        with beside(work) as result:
            ran.append(True)  # the block runs all the same
        with pytest.raises(KeyError, match="from the work"):
            result()
    assert ran == [True]


def test_beside_waits_for_the_work_when_the_block_raises():
    finished = []

    def work():
        time.sleep(0.05)
        finished.append(True)

    with using_threads(2), pytest.raises(ValueError, match="block"):
        with beside(work):
            raise ValueError("block")
    assert finished == [True]  # not left running


def test_beside_runs_the_work_in_the_callers_context():
    with using_threads(2), md.no_grad():
        with beside(md.is_grad_enabled) as result:
            assert not md.is_grad_enabled()
    assert result() is False
    assert md.is_grad_enabled()


def test_share_tasks_elsewhere_runs_the_tasks_here_in_order():
    order = []
    tasks = [lambda k=k: order.append((k, threading.get_ident())) or k * k for k in range(4)]
    for count in (1, 2):
        order.clear()
        with using_threads(count):
            assert share_tasks(tasks) == [0, 1, 4, 9]
        assert order == [(k, threading.get_ident()) for k in range(4)]
    assert share_tasks([]) == []


@pytest.mark.parametrize("count", [2, 3])
def test_the_block_takes_the_tasks_the_work_has_not_begun(count):
    """The work's first task waits until another has run: only the block's thread, once its
    block has ended, can run that one. The last posted is taken first; each runs in the
    work's context (``no_grad``) on the block's share of the threads; the results come back
    in the tasks' order."""
    ran, other_ran = {}, threading.Event()

    def first():
        ran[0] = threading.get_ident()
        assert other_ran.wait(10.0)
        return "first"

    def later(k):
        ran[k] = (threading.get_ident(), md.is_grad_enabled(), thread_count())
        other_ran.set()
        return k

    def work():
        with md.no_grad():
            return threading.get_ident(), share_tasks([first, partial(later, 1),
                                                       partial(later, 2)])  # fmt: skip

    with using_threads(count):
        with beside(work) as result:
            pass
    worker, values = result()
    assert values == ["first", 1, 2]
    assert ran[0] == worker != threading.get_ident()
    assert ran[2] == (threading.get_ident(), False, count - count // 2)
    here, there = (threading.get_ident(), False, count - count // 2), (worker, False, count // 2)
    assert ran[1] in {here, there}


def test_nested_shared_tasks_are_taken_too():
    """Tasks posted by a task, on either thread, are run once each, results in order."""
    calls = []

    def leaf(k):
        calls.append(k)
        time.sleep(0.001)
        return k

    def branch(k):
        return share_tasks([partial(leaf, 10 * k + j) for j in range(5)])

    with using_threads(2):
        with beside(lambda: share_tasks([partial(branch, k) for k in range(6)])) as result:
            pass
    assert result() == [[10 * k + j for j in range(5)] for k in range(6)]
    assert sorted(calls) == sorted(10 * k + j for k in range(6) for j in range(5))


@pytest.mark.parametrize("count", [1, 2])
def test_share_tasks_raises_the_first_failure_in_order_once_the_begun_have_ended(count):
    ended, began = [], threading.Event()

    def slow_then_fail():
        began.set()
        time.sleep(0.05)
        ended.append("slow")
        raise KeyError("second")

    def fail_first():
        assert began.wait(10.0) or count == 1
        raise ValueError("first")

    tasks = [fail_first, lambda: ended.append("never") or 3, slow_then_fail]
    if count == 1:
        tasks = tasks[:2]
    with using_threads(count):
        with beside(lambda: share_tasks(tasks)) as result:
            pass
        with pytest.raises(ValueError, match="first"):
            result()
    assert "never" not in ended
    assert ended == (["slow"] if count == 2 else [])
