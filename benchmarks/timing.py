"""The benchmark harness every script in ``benchmarks/`` uses: timing, memory, fresh
processes, the machine description, the command line, JSON and report rows.

Timing:

* ``measure(fn, repeats, warmup)``: ``warmup`` untimed calls first (Numba loads or compiles
  its kernels on the first call, NumPy/glibc warm their caches), then ``repeats`` timed
  calls. Reported: the median and the spread (first and third quartiles, min and max) in
  milliseconds, and the minor page faults per call (``ru_minflt`` of ``getrusage``: each one
  is a fresh 4 KiB page the kernel had to map, i.e. memory the process gave back and took
  again). Medians, because this machine is small (2 cores) and shared: single calls can be
  slowed several-fold by other processes.
* ``measure_interleaved({name: fn}, repeats, warmup, block)``: the same for several
  variants that a script compares, timed in turns (``block`` calls of each per round), so
  that every variant sees the same machine state and their ratios do not drift with the
  machine's load. ``measure`` is this with a single variant.
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

* ``in_fresh_process(fn, env, **kwargs)``: ``fn(**kwargs)`` in a new Python process with
  some environment variables changed, for settings fixed when a process starts (glibc's
  allocator thresholds, the OpenMP wait policy, Numba's threading layer) and so that one
  measurement does not inherit another's allocator state.

Output:

* ``main(name, doc, run, argv, options)``: the common ``main()``: the command line
  (``--out DIR``, ``--quick`` and the script's own options), ``run(args)``, then the result
  written to ``OUT/name.json`` with the machine description (``machine()``: cores, CPU
  model, library versions, thread settings and the load average, since timings from a
  loaded machine are slower) and the report section printed.
* A script's result holds a ``report`` entry (``report_section``): a title, rows of
  (quantity, ours, paper or target, status; ``row`` and ``target_row``) and notes;
  ``run_all.py`` turns those into ``report.md``.
"""

from __future__ import annotations

import argparse
import gc
import importlib
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

from render.inverse.jsonio import write_json as write_strict_json
from render.inverse.plot import line_plot

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
DEFAULT_OUT = ROOT / "out" / "benchmarks"  # out/ is git-ignored

# glibc's "keep freed memory" setting in its environment-variable form: allocations up to
# 32 MiB (glibc's cap on 64-bit) come from the heap instead of mmap, and the heap is not
# given back to the kernel until 1 GiB of it is free. Read once, when the process starts.
KEEP_FREED_MEMORY = {
    "MALLOC_MMAP_THRESHOLD_": str(32 << 20),
    "MALLOC_TRIM_THRESHOLD_": str(1 << 30),
}


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


def measure_interleaved(fns: dict, repeats: int = 7, warmup: int = 1, block: int = 1) -> dict:
    """Time several callables in turns: per round, ``block`` calls of each, until each has
    had at least ``repeats`` timed calls; before that, ``warmup`` untimed calls of each.

    Returns {name: ``summarize`` of its times plus ``page_faults_per_pass``, the median
    minor page faults per call}. The garbage collector is left on (it is part of the real
    cost) but run once before the timed calls so earlier garbage is not charged to them.
    """
    for _ in range(warmup):
        for fn in fns.values():
            fn()
    gc.collect()
    times = {name: [] for name in fns}
    faults = {name: [] for name in fns}
    for _ in range(-(-repeats // block)):
        for name, fn in fns.items():
            for _ in range(block):
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


def measure(fn, repeats: int = 7, warmup: int = 1) -> dict:
    """Time ``fn()``: ``warmup`` untimed calls, then ``repeats`` timed ones (the result of
    ``measure_interleaved`` for this one callable)."""
    return measure_interleaved({"fn": fn}, repeats, warmup)["fn"]


def time_once(fn) -> float:
    """Wall time of one call of ``fn()`` in seconds (for work too long to repeat)."""
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


def allocator_setting() -> dict:
    """Whether this process started with ``KEEP_FREED_MEMORY`` in its environment
    (``keep_freed_memory``) and whether its C library is glibc, which reads those variables
    (``keep_freed_applied``: both)."""
    requested = all(os.environ.get(k) == v for k, v in KEEP_FREED_MEMORY.items())
    glibc = platform.libc_ver()[0] == "glibc"
    return {"keep_freed_memory": requested, "keep_freed_applied": requested and glibc}


# --------------------------------------------------------------------------------------
# Fresh processes
# --------------------------------------------------------------------------------------

# What the child process runs: import the function's module from benchmarks/, call it with
# the keyword arguments and write its (JSON) result to a file (stdout may carry warnings).
_CHILD = "import sys; sys.path.insert(0, sys.argv[1]); import timing; timing._child(*sys.argv[2:])"


def _child(module: str, function: str, kwargs: str, result_path: str) -> None:
    fn = getattr(importlib.import_module(module), function)
    write_strict_json(result_path, fn(**json.loads(kwargs)))


def in_fresh_process(fn, env: dict | None = None, **kwargs) -> dict:
    """``fn(**kwargs)`` run in a new Python process and its result (a JSON-able dict).

    ``fn`` is a module-level function of a script in ``benchmarks/``. ``env`` changes the
    child's environment: name -> value, or name -> None to remove a variable the parent
    has (e.g. one run_all.py sets, which a variant must not inherit).
    """
    child_env = dict(os.environ)
    for name, value in (env or {}).items():
        if value is None:
            child_env.pop(name, None)
        else:
            child_env[name] = value
    # A script run as ``python benchmarks/x.py`` is module __main__: import it by file name.
    module = Path(sys.modules[fn.__module__].__file__).stem
    with tempfile.TemporaryDirectory() as tmp:
        result_path = Path(tmp) / "result.json"
        cmd = [sys.executable, "-c", _CHILD, str(HERE), module, fn.__name__]
        cmd += [json.dumps(kwargs), str(result_path)]
        proc = subprocess.run(cmd, env=child_env, capture_output=True, text=True, check=False)
        if proc.returncode != 0:
            raise RuntimeError(f"{module}.{fn.__name__} failed in its process:\n{proc.stderr}")
        return json.loads(result_path.read_text(encoding="utf-8"))


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
# Command line and output
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


def make_parser(
    doc: str, out: Path = DEFAULT_OUT, quick: str = "tiny sizes and few repeats: a smoke run"
) -> argparse.ArgumentParser:
    """The common command line: ``--out DIR`` (default ``out``) and ``--quick`` (``quick``
    says what it runs); the description is the first line of ``doc``."""
    parser = argparse.ArgumentParser(
        description=doc.strip().splitlines()[0], formatter_class=argparse.RawTextHelpFormatter
    )
    parser.add_argument("--out", type=Path, default=out, help=f"output folder (default {out})")
    parser.add_argument("--quick", action="store_true", help=quick)
    return parser


QUICK_REPEATS = 1  # timed calls per measurement with --quick (a smoke run: each runs)


def path_thread_options(doc: str, out: Path, size: int, repeats: int, argv=None):
    """The command line of the path integrator's thread-scaling scripts: ``make_parser``'s
    with ``--threads``, ``--size``, ``--spp`` and ``--repeats``, read from ``argv``; returns
    (the parsed arguments, the thread counts: ``--threads`` or 1 and all of Numba's)."""
    import numba

    parser = make_parser(doc, out=out, quick="a smoke run")
    parser.add_argument("--threads", default=None, help="e.g. 1,2,4,8,16 (default: 1 and all)")
    parser.add_argument("--size", type=int, default=size)
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--repeats", type=int, default=repeats)
    args = parser.parse_args(argv)
    if args.threads:
        return args, [int(t) for t in args.threads.split(",")]
    return args, sorted({1, numba.get_num_threads()})


def main(
    name: str,
    doc: str,
    run,
    argv=None,
    options: dict | None = None,
    repeats: int | None = None,
    size: tuple[int, int] | None = None,
) -> dict:
    """A script's ``main()``: parse the command line, compute ``result = run(args)`` (a dict
    with its ``report`` section), write it to ``OUT/name.json``, print the report; returns
    the result.

    The command line: ``--out`` and ``--quick``; ``--repeats`` if ``repeats`` is given (its
    default; ``QUICK_REPEATS`` with ``--quick``); ``--size`` if ``size`` = (default, default
    with ``--quick``) is given, the image side; and the script's own ``options``, {flag:
    keyword arguments of ``add_argument``}.
    """
    parser = make_parser(doc)
    if repeats is not None:
        parser.add_argument(
            "--repeats",
            type=int,
            help=f"timed calls per measurement (default {repeats}, {QUICK_REPEATS} with --quick)",
        )
    if size is not None:
        parser.add_argument(
            "--size", type=int, help=f"image side (default {size[0]}, {size[1]} with --quick)"
        )
    for flag, kwargs in (options or {}).items():
        parser.add_argument(flag, **kwargs)
    args = parser.parse_args(argv)
    if repeats is not None:
        args.repeats = args.repeats or (QUICK_REPEATS if args.quick else repeats)
    if size is not None:
        args.size = args.size or (size[1] if args.quick else size[0])
    result = run(args)
    path = write_json(args.out, name, result)
    print_report(result["report"], machine())
    print(f"wrote {path}")
    return result


# --------------------------------------------------------------------------------------
# Report
# --------------------------------------------------------------------------------------


def row(quantity: str, ours: str, reference: str = "", status: str = "") -> dict:
    """One line of a report table: what, our value, the paper's value or the target, and
    for targets whether ours meets it ("met" / "not met")."""
    return {"quantity": quantity, "ours": ours, "reference": reference, "status": status}


def target_status(value: float, limit: float) -> str:
    """'met' if value <= limit (a time or ratio budget), else 'not met'."""
    return "met" if value <= limit else "not met"


def target_row(quantity: str, ours: str, value: float, limit: float, target: str) -> dict:
    """A report line for a quantity with a budget: ``value`` (shown as ``ours``) against
    ``limit`` (described by ``target``)."""
    return row(quantity, ours, target, target_status(value, limit))


def time_rows(results: dict, labels: dict) -> list[dict]:
    """A report line ``label: ms(results[key])`` for every ``key: label`` of ``labels``."""
    return [row(label, ms(results[key])) for key, label in labels.items()]


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


def mb(memory: dict) -> str:
    """'18.0 / 268 MB': tracemalloc peak / process peak RSS of a ``measure_memory`` result."""
    return f"{memory['tracemalloc_peak_mb']:.1f} / {memory['rss_peak_mb']:.0f} MB"


def series(points: list[dict], x: str, ys: dict) -> dict:
    """Plot series over ``points``: {label: (the points' ``x`` values, ``get(point)`` for
    each)} for every ``label: get`` of ``ys``."""
    xs = [p[x] for p in points]
    return {label: (xs, [get(p) for p in points]) for label, get in ys.items()}


def steps_plot(path: Path, title: str, steps: list[str], values: dict, ylabel: str = "ms"):
    """A line plot of ``values`` ({label: one value per step}) against the step numbers
    1, 2, ..., the steps named in the title; returns the PNG's path."""
    x = list(range(1, len(steps) + 1))
    return line_plot(
        {label: (x, v) for label, v in values.items()},
        path,
        title=f"{title}: " + ", ".join(f"{i} {name}" for i, name in enumerate(steps, 1)),
        xlabel="step (see title)",
        ylabel=ylabel,
    )


def fit_power_law(x, y) -> float:
    """Exponent b of y = a x^b by least squares on log-log (NaN with fewer than 2 points)."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    keep = (x > 0) & (y > 0) & np.isfinite(x) & np.isfinite(y)
    if keep.sum() < 2:
        return float("nan")
    slope, _ = np.polyfit(np.log(x[keep]), np.log(y[keep]), 1)
    return float(slope)
