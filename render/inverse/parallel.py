"""Independent runs fanned out over any ``concurrent.futures.Executor``.

The paper reproduction, the pose sweeps and the other experiment series are many runs that
share nothing: each renders its own scene from its own seed. ``run_ordered`` takes them as
zero-argument callables and an executor: ``None`` runs them one after the other in this
process; ``process_pool(jobs)`` spreads them over ``jobs`` processes of this machine; and
because the interface is the standard ``Executor``, a cluster's executor works unchanged,
e.g. Dask's:

    from dask.distributed import Client
    with Client(scheduler_address) as client:
        results = run_ordered(calls, client.get_executor())

Results come back in the order of ``calls``, whatever order the runs finish in, and equal
the serial ones bit for bit (each run is deterministic given its arguments; the thread
count of Numba's kernels does not change their results): only wall times differ. The calls
must be picklable for a process pool or a cluster: ``functools.partial`` of module-level
functions, not lambdas.
"""

from __future__ import annotations

import multiprocessing
import os
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Executor, ProcessPoolExecutor
from typing import TypeVar

import numpy as np

T = TypeVar("T")

__all__ = ["run_ordered", "process_pool", "check_jobs", "warm_cache"]


def run_ordered(
    calls: Sequence[Callable[[], T]],
    executor: Executor | None = None,
    on_result: Callable[[int, T], None] | None = None,
) -> list[T]:
    """``[call() for call in calls]``, the calls run by ``executor`` (None: here, in order).

    on_result(i, result): called in this process for each result in the order of
    ``calls`` (as soon as it and all before it are done), e.g. to print progress.
    An exception raised by a call is raised here, after cancelling the calls not started.
    """
    if executor is None:
        results = []
        for i, call in enumerate(calls):
            results.append(call())
            if on_result is not None:
                on_result(i, results[-1])
        return results
    if not isinstance(executor, Executor):
        raise TypeError(
            "run_ordered: executor must be a concurrent.futures.Executor (or None), got "
            f"{type(executor).__name__}"
        )
    futures = [executor.submit(call) for call in calls]
    results = []
    try:
        for i, future in enumerate(futures):
            results.append(future.result())
            if on_result is not None:
                on_result(i, results[-1])
    except BaseException:
        for future in futures:
            future.cancel()
        raise
    return results


def warm_cache(calls: Sequence[Callable[[], object]]) -> float:
    """Run ``calls`` here, one after the other (small versions of the runs: one iteration
    each), and return the seconds they took. Every Numba kernel they use is then compiled
    once and written to Numba's on-disk cache, which the workers of a process pool load at
    their first call; without it each worker compiles every kernel itself, all at the same
    time (twice the CPU time of one compile on two workers, and no sooner)."""
    start = time.perf_counter()
    for call in calls:
        call()
    return time.perf_counter() - start


def check_jobs(jobs, where: str = "jobs") -> int:
    """``jobs`` as an int >= 1 (None: the number of cores)."""
    if jobs is None:
        return os.cpu_count() or 1
    if isinstance(jobs, bool) or not isinstance(jobs, int | np.integer) or jobs < 1:
        raise ValueError(f"{where} must be an int >= 1, got {jobs!r}")
    return int(jobs)


def process_pool(jobs: int | None = None) -> ProcessPoolExecutor:
    """A pool of ``jobs`` worker processes (None: one per core), started with "spawn" (a
    forked child would inherit the parent's Numba threads in an unknown state), each
    giving its Numba kernels cores // jobs threads so that the workers do not oversubscribe
    the cores. Use it as a context manager."""
    jobs = check_jobs(jobs, "process_pool: jobs")
    threads = max(1, (os.cpu_count() or 1) // jobs)
    return ProcessPoolExecutor(
        max_workers=jobs,
        mp_context=multiprocessing.get_context("spawn"),
        initializer=_worker_threads,
        initargs=(threads,),
    )


def _worker_threads(threads: int) -> None:
    """Worker initializer: Numba's thread count for this process."""
    import numba

    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
