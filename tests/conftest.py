"""Hypothesis profiles shared by every test module.

- ``dev`` (the default): new random examples on every run, which is how property tests find
  bugs. A failure prints the example; add it as an ``@example`` once fixed.
- ``ci`` (``.ci/run`` sets ``HYPOTHESIS_PROFILE=ci``): the same examples on every run
  (``derandomize``), so that CI judges the code, not the luck of the draw.

Both drop Hypothesis' per-example deadline and its "too slow" health check: they are timing
assertions, and timings on a shared 2-core machine are noise (Numba compiles on first call,
too). Modules still choose their own ``max_examples``.
"""

from __future__ import annotations

import gc
import importlib.util
import os
import sys
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import pytest
from hypothesis import HealthCheck, settings

# Keep bytecode. An environment with PYTHONDONTWRITEBYTECODE set (this machine's is) makes
# every Python process the suite starts (the workers, and the scripts, examples and lessons
# tests run as new processes) compile the project's ~90 modules from source again: `import
# render` took 1.5 s instead of 0.9 s here. The suite's processes write __pycache__ as
# Python does by default (ignored by git, where Numba keeps its cache too).
os.environ.pop("PYTHONDONTWRITEBYTECODE", None)
sys.dont_write_bytecode = False

# Under pytest-xdist (``pytest -n 2``, the README's command) each worker process is one of
# the cores: Numba's parallel kernels get one thread each instead of all of them twice over
# (set before anything imports Numba; results do not depend on the thread count).
if os.environ.get("PYTEST_XDIST_WORKER"):
    os.environ.setdefault("NUMBA_NUM_THREADS", "1")

_COMMON = {"deadline": None, "suppress_health_check": [HealthCheck.too_slow]}
settings.register_profile("dev", **_COMMON)
settings.register_profile("ci", derandomize=True, **_COMMON)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "dev"))


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers",
        "new_processes: the test starts new Python processes (scripts, process pools), "
        "which load Numba's compiled kernels from the on-disk cache; such tests run last.",
    )
    if _xdist_controller(config):
        _warm_kernels(config)


def _xdist_controller(config: pytest.Config) -> bool:
    """Whether this process is pytest-xdist's controller, about to start several workers."""
    workers = getattr(config.option, "numprocesses", None)
    return not hasattr(config, "workerinput") and workers not in (None, 0, "0")


def _warm_kernels(config: pytest.Config) -> None:
    """Compile the renderer's kernels into Numba's cache before the workers start, in two
    processes sharing the work (``tests/warm_kernels.py`` says why), one Numba thread each.
    A failure there is only reported: the tests that need those kernels will compile them
    and show any error themselves."""
    import subprocess
    import tempfile
    import time

    start = time.perf_counter()
    env = {**os.environ, "NUMBA_NUM_THREADS": "1"}
    with tempfile.TemporaryDirectory() as claims:
        command = [sys.executable, "-m", "tests.warm_kernels", claims]
        logs = [Path(claims, f"stderr{i}.txt") for i in range(2)]
        with logs[0].open("w") as err0, logs[1].open("w") as err1:
            runs = [subprocess.Popen(command, cwd=ROOT, env=env, stdout=subprocess.DEVNULL,
                                     stderr=err) for err in (err0, err1)]  # fmt: skip
            codes = [run.wait() for run in runs]
        errors = [log.read_text() for code, log in zip(codes, logs, strict=True) if code]
    # pytest_configure runs before the session's clock starts: the time pytest prints at
    # the end leaves this out, so the note says so (the command's wall time is both).
    note = (
        "Numba's kernels compiled or loaded before the workers started: {:.0f} s "
        "(before the session's clock starts: not in the time pytest prints last)"
    )
    _WARM_UP.append(note.format(time.perf_counter() - start))
    _WARM_UP.extend(
        f"the warm-up failed (the tests compile on demand): {e[-2000:]}" for e in errors
    )


#: What ``_warm_kernels`` did, for the summary at the end (output is captured before it).
_WARM_UP: list[str] = []


def pytest_terminal_summary(terminalreporter) -> None:
    for line in _WARM_UP:
        terminalreporter.write_line(line)


def pytest_collection_finish(session: pytest.Session) -> None:
    """Everything alive once the tests are collected (the modules, PyTorch and JAX among
    them: ~600k objects) is moved out of the garbage collector's view (``gc.freeze``).
    Python's full collections walk every tracked object; in a worker holding all that,
    each took ~0.35 s and one worker spent ~40 s of a run in them."""
    gc.freeze()


_RUN = {"tests": 0}


def pytest_runtest_logfinish(nodeid: str, location: tuple) -> None:
    """Every 100 tests (each torn down), a full collection, then what survives it (Numba's
    compiled kernels, Hypothesis' caches: long-lived) is frozen too. Garbage is still
    collected: only objects alive after a collection are frozen."""
    _RUN["tests"] += 1
    if _RUN["tests"] % 100 == 0:
        gc.collect()
        gc.freeze()


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Tests marked ``new_processes`` run after all the others (a stable sort: each group
    keeps its order). On a fresh clone Numba's on-disk cache (``cache=True``) is empty: the
    in-process tests fill it as they go, so scripts started later load the kernels instead of
    each compiling them all again (about 60 s of compiling in all)."""
    items.sort(key=lambda item: item.get_closest_marker("new_processes") is not None)


ROOT = Path(__file__).resolve().parents[1]


def _load_script(relative: str) -> ModuleType:
    """The module of a script in examples/ or benchmarks/ (which import their siblings),
    registered in ``sys.modules`` under its name as an import would (benchmarks/timing.py
    finds a function's script there)."""
    path = ROOT / relative
    sys.path.insert(0, str(path.parent))
    try:
        spec = importlib.util.spec_from_file_location(path.stem, path)
        module = importlib.util.module_from_spec(spec)
        sys.modules[path.stem] = module
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(path.parent))
    return module


@pytest.fixture
def load_script() -> Callable[[str], ModuleType]:
    """``load_script("benchmarks/x.py").main(argv)`` runs a script in this process: it reuses
    the process' compiled kernels instead of starting Python, Numba and the cache again."""
    return _load_script
