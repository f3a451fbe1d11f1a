"""Independent runs over any Executor (``render.inverse.parallel``): the same results, bit
for bit and in the same order, serially, in threads, in processes and on a Dask cluster."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from functools import partial

import numpy as np
import pytest

from render.inverse.experiments import run_camera_calibration, run_light_estimation
from render.inverse.parallel import check_jobs, process_pool, run_ordered

# Starts new Python processes: runs after the in-process tests (tests/conftest.py).
pytestmark = pytest.mark.new_processes


def _metrics(run) -> dict:
    """A run's numbers without its wall times (the only thing allowed to differ)."""
    return {k: v for k, v in run.metrics.items() if "second" not in k}


def _calls() -> list:
    # Different sizes and budgets: the runs finish out of order in a pool.
    return [
        partial(run_camera_calibration, size=32, iters=12, seed=42, antialias="boundary"),
        partial(run_light_estimation, size=16, iters=3, seed=43),
        partial(run_camera_calibration, size=24, iters=4, seed=44),
    ]


@pytest.fixture(scope="module")
def serial() -> list[dict]:
    return [_metrics(r) for r in run_ordered(_calls())]


def _same(results, serial) -> None:
    np.testing.assert_equal([_metrics(r) for r in results], serial)  # NaN equals NaN here


def test_threads_and_processes_give_the_serial_results_in_order(serial):
    seen = []
    with ThreadPoolExecutor(2) as pool:
        _same(run_ordered(_calls(), pool, on_result=lambda i, r: seen.append(i)), serial)
    assert seen == [0, 1, 2]
    with process_pool(2) as pool:
        _same(run_ordered(_calls(), pool), serial)


def test_a_dask_cluster_gives_the_serial_results(serial):
    distributed = pytest.importorskip("dask.distributed")
    with (
        distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                 dashboard_address=None) as cluster,
        distributed.Client(cluster) as client,
    ):  # fmt: skip
        _same(run_ordered(_calls(), client.get_executor()), serial)


def _fails():
    raise FloatingPointError("run 1 failed")


def test_errors():
    with ThreadPoolExecutor(2) as pool, pytest.raises(FloatingPointError, match="run 1 failed"):
        run_ordered([partial(np.zeros, 3), _fails], pool)
    with pytest.raises(TypeError, match="must be a concurrent.futures.Executor"):
        run_ordered([_fails], executor="processes")
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match="jobs must be an int >= 1"):
            check_jobs(bad)
    assert check_jobs(None) >= 1 and check_jobs(3) == 3
