"""The benchmark suite's shared helper: timing, memory, page faults, machine, JSON, plots.

Every script in ``benchmarks/`` measures the same way:

* ``measure(fn, repeats, warmup)``: ``warmup`` untimed calls first (Numba loads or compiles
  its kernels on the first call, NumPy/glibc warm their caches), then ``repeats`` timed
  calls. Reported: the median and the spread (first and third quartiles, min and max) in
  milliseconds, and the minor page faults per call (``ru_minflt`` of ``getrusage``: each one
  is a fresh 4 KiB page the kernel had to map, i.e. memory the process gave back and took
  again). Medians, because this machine is small (2 cores) and shared: single calls can be
  slowed several-fold by other processes.
* ``measure_memory(fn)``: one separate, *untimed* call (tracemalloc slows allocation), with
  two numbers:

  - ``tracemalloc_peak_mb``: the peak of memory allocated through Python's allocators
    during the call and alive at the same moment. NumPy reports its array buffers to
    tracemalloc, so this is the working set of arrays: the tape, the temporaries, the
    images. Memory Numba allocates inside compiled code (e.g. the camera-ray array) is
    *not* seen.
  - ``rss_peak_mb``: the process's peak resident set size during the call (Linux
    ``VmHWM``, reset just before the call through ``/proc/self/clear_refs``): everything
    resident, interpreter, NumPy, Numba, compiled code included, as a system monitor or the
    paper's "resident memory" would count it. ``rss_increase_mb`` is that peak minus the
    resident size just before the call.

* ``machine()``: cores, CPU model, library versions, thread settings and the load average
  (timings from a loaded machine are slower; the load is recorded so readers can tell).
* ``write_json(out, name, payload)``: ``OUT/name.json`` with the machine description added.
* ``make_parser(doc)``: the common command line, ``--out DIR`` and ``--quick``.

Each script also puts a ``report`` entry in its JSON (``report_section``): a title, rows of
(quantity, ours, paper or target, status) and notes; ``run_all.py`` turns those into
``report.md``.
"""

from __future__ import annotations

import argparse
import gc
import math
import os
import platform
import resource
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np

from render.inverse.jsonio import write_json as write_strict_json

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_OUT = ROOT / "out" / "benchmarks"  # out/ is git-ignored


# --------------------------------------------------------------------------------------
# Time and page faults
# --------------------------------------------------------------------------------------


def _minor_faults() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt


def summarize(seconds) -> dict:
    """Median and spread of wall times given in seconds, as milliseconds."""
    ms = np.asarray(seconds, dtype=np.float64) * 1e3
    q1, median, q3 = np.percentile(ms, [25, 50, 75])
    return {
        "median_ms": float(median),
        "q1_ms": float(q1),
        "q3_ms": float(q3),
        "min_ms": float(ms.min()),
        "max_ms": float(ms.max()),
        "repeats": int(ms.size),
    }


def measure(fn, repeats: int = 7, warmup: int = 1) -> dict:
    """Time ``fn()``: ``warmup`` untimed calls, then ``repeats`` timed ones.

    Returns ``summarize`` of the times plus ``page_faults_per_pass`` (median minor page
    faults per call). The garbage collector is left on (it is part of the real cost) but
    run once before the timed calls so earlier garbage is not charged to them.
    """
    for _ in range(warmup):
        fn()
    gc.collect()
    times, faults = [], []
    for _ in range(repeats):
        f0 = _minor_faults()
        t0 = time.perf_counter()
        fn()
        t1 = time.perf_counter()
        faults.append(_minor_faults() - f0)
        times.append(t1 - t0)
    result = summarize(times)
    result["page_faults_per_pass"] = float(np.median(faults))
    return result


def measure_interleaved(fns: dict, repeats: int = 7, warmup: int = 1) -> dict:
    """Time several callables in turns, one call of each per round (``repeats`` rounds),
    so that every one of them sees the same machine state: on a shared machine the speed
    drifts over seconds, and ratios of medians taken one after another drift with it.

    Returns {name: the result ``measure`` would give}.
    """
    for _ in range(warmup):
        for fn in fns.values():
            fn()
    gc.collect()
    times = {name: [] for name in fns}
    faults = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            f0 = _minor_faults()
            t0 = time.perf_counter()
            fn()
            t1 = time.perf_counter()
            faults[name].append(_minor_faults() - f0)
            times[name].append(t1 - t0)
    out = {}
    for name in fns:
        out[name] = summarize(times[name])
        out[name]["page_faults_per_pass"] = float(np.median(faults[name]))
    return out


def time_once(fn) -> float:
    """Wall time of one call of ``fn()`` in seconds."""
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


# --------------------------------------------------------------------------------------
# Memory
# --------------------------------------------------------------------------------------


def _status_kb(field: str) -> float:
    """A ``kB`` field of /proc/self/status (VmRSS, VmHWM), NaN where unavailable."""
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith(field + ":"):
                    return float(line.split()[1])
    except OSError:
        pass
    return float("nan")


def reset_peak_rss() -> bool:
    """Reset the kernel's peak-RSS counter (VmHWM) to the current RSS (Linux >= 4.0)."""
    try:
        with open("/proc/self/clear_refs", "w", encoding="ascii") as f:
            f.write("5")
        return True
    except OSError:
        return False


def measure_memory(fn) -> dict:
    """Peak memory of one call of ``fn()`` (see the module docstring for the two numbers)."""
    gc.collect()
    rss_before = _status_kb("VmRSS") / 1024
    reset_ok = reset_peak_rss()
    tracemalloc.start()
    fn()
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    rss_peak = _status_kb("VmHWM") / 1024
    if not reset_ok:  # fall back to the lifetime maximum
        rss_peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return {
        "tracemalloc_peak_mb": peak / 2**20,
        "rss_peak_mb": rss_peak,
        "rss_increase_mb": rss_peak - rss_before,
        "rss_peak_reset": reset_ok,
    }


# --------------------------------------------------------------------------------------
# Machine description
# --------------------------------------------------------------------------------------


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def machine() -> dict:
    """What the numbers were measured on (and how loaded the machine was)."""
    import numba

    try:
        layer = numba.threading_layer()
    except ValueError:  # no parallel kernel has run yet in this process
        layer = "not initialised"
    try:
        usable = len(os.sched_getaffinity(0))
    except AttributeError:
        usable = os.cpu_count()
    return {
        "cpu_model": _cpu_model(),
        "logical_cores": os.cpu_count(),
        "usable_cores": usable,
        "load_average_1_5_15min": [round(x, 2) for x in os.getloadavg()],
        "python": platform.python_version(),
        "platform": platform.platform(),
        "numpy": np.__version__,
        "numba": numba.__version__,
        "numba_threads": numba.get_num_threads(),
        "numba_threading_layer": layer,
        "thread_env": {
            k: os.environ.get(k)
            for k in (
                "OMP_NUM_THREADS",
                "OPENBLAS_NUM_THREADS",
                "MKL_NUM_THREADS",
                "NUMBA_NUM_THREADS",
                "OMP_WAIT_POLICY",
                "NUMBA_THREADING_LAYER",
            )
        },
    }


def machine_line(m: dict) -> str:
    """One printable line describing the machine."""
    return (
        f"{m['cpu_model']}, {m['usable_cores']} cores, load {m['load_average_1_5_15min'][0]}, "
        f"numpy {m['numpy']}, numba {m['numba']} ({m['numba_threads']} threads, "
        f"{m['numba_threading_layer']})"
    )


# --------------------------------------------------------------------------------------
# Output
# --------------------------------------------------------------------------------------


def write_json(out: Path, name: str, payload: dict) -> Path:
    """Write ``payload`` (plus the machine description and the command line) to
    ``out/name.json``; returns the path."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    payload = dict(payload)
    payload["machine"] = machine()
    payload["argv"] = sys.argv
    # Strict JSON (NaN and infinities become null), which every parser reads: see
    # render.inverse.jsonio.
    return write_strict_json(out / f"{name}.json", payload, indent=2)


def make_parser(doc: str) -> argparse.ArgumentParser:
    """The common command line: ``--out DIR`` and ``--quick``."""
    parser = argparse.ArgumentParser(
        description=doc.strip().splitlines()[0], formatter_class=argparse.RawTextHelpFormatter
    )
    parser.add_argument(
        "--out", type=Path, default=DEFAULT_OUT, help=f"output folder (default {DEFAULT_OUT})"
    )
    parser.add_argument(
        "--quick", action="store_true", help="tiny sizes and few repeats: a smoke run"
    )
    return parser


def row(quantity: str, ours: str, reference: str = "", status: str = "") -> dict:
    """One line of a report table: what, our value, the paper's value or the target, and
    for targets whether ours meets it ("met" / "not met")."""
    return {"quantity": quantity, "ours": ours, "reference": reference, "status": status}


def target_status(value: float, limit: float) -> str:
    """'met' if value <= limit (a time or ratio budget), else 'not met'."""
    return "met" if value <= limit else "not met"


def report_section(title: str, rows: list[dict], notes: list[str], plots: list) -> dict:
    """The part of a script's JSON that run_all.py turns into a report.md section."""
    return {"title": title, "rows": rows, "notes": notes, "plots": [str(p) for p in plots]}


def print_report(section: dict, m: dict | None = None) -> None:
    """Print a report section as an aligned text table."""
    print(f"\n== {section['title']} ==")
    if m is not None:
        print(f"machine: {machine_line(m)}")
    rows = section["rows"]
    if rows:
        w0 = max(len(r["quantity"]) for r in rows)
        w1 = max(len(r["ours"]) for r in rows)
        w2 = max(len(r["reference"]) for r in rows)
        print(f"{'quantity':<{w0}}  {'ours':>{w1}}  {'paper / target':<{w2}}  status")
        for r in rows:
            print(
                f"{r['quantity']:<{w0}}  {r['ours']:>{w1}}  {r['reference']:<{w2}}  {r['status']}"
            )
    for note in section["notes"]:
        print(f"- {note}")
    for plot in section["plots"]:
        print(f"plot: {plot}")


def ms(stats: dict) -> str:
    """'12.3 ms [11.9-13.0]': median and interquartile range of a ``measure`` result."""
    return f"{stats['median_ms']:.1f} ms [{stats['q1_ms']:.1f}-{stats['q3_ms']:.1f}]"


def fit_power_law(x, y) -> float:
    """Exponent b of y = a x^b by least squares on log-log (NaN with fewer than 2 points)."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    keep = (x > 0) & (y > 0) & np.isfinite(x) & np.isfinite(y)
    if keep.sum() < 2:
        return float("nan")
    slope, _ = np.polyfit(np.log(x[keep]), np.log(y[keep]), 1)
    return float(slope)


def finite_positive(x) -> bool:
    """True for a finite number > 0 (used by the smoke test's checks too)."""
    return isinstance(x, int | float) and math.isfinite(x) and x > 0
