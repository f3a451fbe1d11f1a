"""What handing work to a second thread costs on this machine, and what that means for the
compiled kernels (``minidiff.compiler.PARALLEL_WORK``, and their outputs from
``minidiff.buffers``): docs/compiler.md, "Threads and memory around the kernels".

Run:  python benchmarks/bench_dispatch.py [--out DIR] [--quick] [--repeats 300]
(``out/benchmarks/bench_dispatch`` by default; ``--out docs/benchmarks/dispatch`` writes
the committed one)

Medians of ``--repeats`` calls each:

* ``run_jobs``: an empty job kernel (``minidiff.threads.kernel``) run as one job and as two
  (``minidiff.threads.run_jobs``: the second on the pool's thread);
* ``round_trip``: a Python function handed to a thread of a pool and waited for, with that
  thread pinned to the caller's core, then to another (Linux, two cores or more);
* ``level_set``: the secondary term's level set of silhouette edges
  (``render.path.boundary.silhouettes._level_set_of``, compiled, its program's lines
  counted), forward and forward+VJP, over batches of 1k to 256k points against 200 random
  edges, on one thread and on two (``PARALLEL_WORK`` set to 0, so that every batch is split),
  with the job count the rule picks;
* ``fresh_memory``: the 363k candidate samples' directions in the 512x512 boundary term
  (``render.edges.interior``, 64x64 with ``--quick``): each job's time in the call, with
  the compiled outputs from minidiff's pool (as the renderer runs) and from fresh memory
  (``buffers.fresh()`` around the call);
* ``leaf_gradient``: the backward of ``(r * w).sum()`` over a leaf ``r`` of 1M rows of three,
  on one thread and on two, its first ``.grad`` copied by ``kernels.copy`` (on the threads,
  into reused memory: as minidiff runs) and by ``np.array`` (one thread, fresh memory: as it
  did before), in turns.
"""

from __future__ import annotations

import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import bench_render
import numpy as np
import timing

BATCHES = (1024, 4096, 16384, 65536, 262144)


def median_us(fn, repeats: int) -> float:
    """The median time of ``repeats`` calls of ``fn``, in microseconds, after a warm-up."""
    return 1e3 * timing.measure(fn, repeats, warmup=min(repeats, 20))["median_ms"]


def run_jobs_cost(repeats: int) -> dict:
    """An empty job kernel as one job and as two."""
    from minidiff.threads import kernel, run_jobs

    @kernel
    def nothing(job, n_jobs, x):
        x[job] += 1.0

    x = np.zeros(2)
    return {f"{n}_jobs_us": median_us(lambda n=n: run_jobs(nothing, n, x), repeats) for n in (1, 2)}


def round_trip_cost(repeats: int) -> dict | None:
    """A Python function handed to a pool thread and waited for, the thread on the caller's
    core and on another; None where threads cannot be pinned."""
    if not hasattr(os, "sched_setaffinity") or len(os.sched_getaffinity(0)) < 2:
        return None
    mine = os.sched_getaffinity(0)
    first, other = sorted(mine)[:2]
    out = {}
    with ThreadPoolExecutor(1) as pool:
        try:
            os.sched_setaffinity(threading.get_native_id(), {first})
            for name, cpu in (("same_core_us", first), ("other_core_us", other)):
                pool.submit(os.sched_setaffinity, 0, {cpu}).result()
                out[name] = median_us(lambda: pool.submit(int).result(), repeats)
        finally:
            os.sched_setaffinity(threading.get_native_id(), mine)
    return out


def level_set_costs(repeats: int, batches) -> list[dict]:
    """``_level_set_of`` over each batch: forward, and forward+VJP, on one thread and on
    two, and the job count ``PARALLEL_WORK`` picks."""
    rng = np.random.default_rng(0)
    edges = rng.normal(size=(200, 3)), rng.normal(size=(200, 3))
    return [_level_set_row(n, rng, edges, repeats) for n in batches]


def _level_set_row(n: int, rng, edges, repeats: int) -> dict:
    """``level_set_costs`` for a batch of ``n`` points."""
    import minidiff as md
    from minidiff import compiler
    from render.path.boundary.silhouettes import _level_set_of

    apex, far = rng.normal(size=(n, 3)) * 4.0, rng.normal(size=(n, 3))
    # (rows of the edges' table, of a one-row table of spheres, every row an edge)
    args = (rng.integers(0, 200, n), np.zeros(n, np.int64), np.ones(n, bool), *edges,
            np.zeros((1, 3)), np.ones(1))  # fmt: skip

    def forward():
        with md.no_grad():
            _level_set_of(apex, far, *args)

    def forward_backward():
        x = md.tensor(far, requires_grad=True)
        _level_set_of(apex, x, *args).backward(np.ones(n))

    lines = len(_level_set_of.trace(apex, far, *args).graph.nodes)
    row = {"n": n, "lines": lines, "rule_jobs": 1 if n * lines < compiler.PARALLEL_WORK else 2}
    saved = compiler.PARALLEL_WORK
    try:
        compiler.PARALLEL_WORK = 0  # every batch split: the two-thread times
        for threads in (1, 2):
            with compiler.using_threads(threads):
                row[f"forward_{threads}_us"] = median_us(forward, repeats)
                row[f"forward_backward_{threads}_us"] = median_us(forward_backward, repeats)
    finally:
        compiler.PARALLEL_WORK = saved
    # what a line costs an element, on one thread
    row["forward_ns_per_element_line"] = 1e3 * row["forward_1_us"] / (n * lines)
    return row


def fresh_memory_jobs(size: int, calls: int) -> dict:
    """Each job's time (ms) in the boundary term's compiled sample directions, outputs from
    the pool and from fresh memory: medians over ``calls`` forward+backward passes."""
    from minidiff import backend, buffers
    from render.edges import interior

    problem = bench_render.loss_problem(size, ground=False)
    record: list[tuple[int, float]] | None = None
    run = backend.Kernel.run

    def timed_run(self, pointers, n, chunks, n_threads, unit=1):
        """``Kernel.run``, each job's call of the machine code timed while ``record`` is a
        list: (the first chunk it runs, seconds)."""
        function = self._function
        if record is None:
            return run(self, pointers, n, chunks, n_threads, unit)

        def timed(*call):  # (pointers, n, first chunk, end chunk)
            start = time.perf_counter()
            status = function(*call)
            record.append((call[2], time.perf_counter() - start))
            return status

        self._function = timed
        try:
            return run(self, pointers, n, chunks, n_threads, unit)
        finally:
            self._function = function

    directions = interior.camera_directions
    out = {"rays": 0}
    calls_jobs: dict[str, list] = {"pool": [], "fresh": []}
    for source, jobs in calls_jobs.items():

        def watched(coords, *frame, source=source, jobs=jobs):
            nonlocal record
            record = []
            try:
                if source == "fresh":
                    with buffers.fresh():
                        return directions(coords, *frame)
                return directions(coords, *frame)
            finally:  # job j: the j-th first chunk
                jobs.append([(j, t) for j, (_, t) in enumerate(sorted(record))])
                out["rays"] = len(coords)
                record = None

        backend.Kernel.run, interior.camera_directions = timed_run, watched
        try:
            for _ in range(calls + 2):
                bench_render.forward_backward(*problem, antialias="boundary")
        finally:
            backend.Kernel.run, interior.camera_directions = run, directions
        measured = jobs[2:]  # after a warm-up
        for j in range(max(len(r) for r in measured)):
            times = [t for r in measured for k, t in r if k == j]
            out[f"{source}_job_{j}_ms"] = 1e3 * float(np.median(times))
    return out


def leaf_gradient(repeats: int, rows: int = 1_000_000) -> dict:
    """The backward of ``(r * w).sum()`` over a (rows, 3) leaf, in ms (medians), on 1 and 2
    threads, its ``.grad`` copied by ``kernels.copy`` and by ``np.array``."""
    import minidiff as md
    from minidiff import kernels
    from minidiff.threads import using_threads

    rng = np.random.default_rng(0)
    r0, w = rng.random((rows, 3)), rng.random((rows, 3))
    copy = kernels.copy
    plain = {"kernels_copy": copy, "np_array": lambda g, dtype: np.array(g, dtype=dtype)}
    times: dict[str, list[float]] = {}
    for _ in range(repeats):
        for name, function in plain.items():
            for threads in (1, 2):
                kernels.copy = function
                try:
                    with using_threads(threads):
                        r = md.tensor(r0, requires_grad=True)
                        total = (r * w).sum()
                        start = time.perf_counter()
                        total.backward()
                        seconds = time.perf_counter() - start
                finally:
                    kernels.copy = copy
                times.setdefault(f"{name}_{threads}_ms", []).append(1e3 * seconds)
    return {key: float(np.median(v[2:])) for key, v in times.items()} | {"rows": rows}


def main(argv=None) -> dict:
    parser = timing.make_parser(__doc__, out=timing.DEFAULT_OUT / "bench_dispatch")
    parser.add_argument("--repeats", type=int, default=300)
    args = parser.parse_args(argv)
    repeats = 5 if args.quick else args.repeats
    from minidiff import compiler
    from minidiff.threads import using_threads

    with using_threads(2):
        result = {
            "run_jobs": run_jobs_cost(repeats),
            "round_trip": round_trip_cost(repeats),
            "parallel_work": compiler.PARALLEL_WORK,
            "level_set": level_set_costs(
                max(3, repeats // 10), BATCHES[:2] if args.quick else BATCHES
            ),
            "fresh_memory": fresh_memory_jobs(64 if args.quick else 512, 2 if args.quick else 9),
            "leaf_gradient": leaf_gradient(5 if args.quick else 21),
        }
    jobs = result["run_jobs"]
    rows = [
        timing.row(
            "an empty kernel, 1 / 2 jobs", f"{jobs['1_jobs_us']:.1f} / {jobs['2_jobs_us']:.1f} us"
        ),
    ]
    if result["round_trip"]:
        trip = result["round_trip"]
        times = f"{trip['same_core_us']:.1f} / {trip['other_core_us']:.1f} us"
        rows.append(timing.row("a pool thread's round trip, same / other core", times))
    for r in result["level_set"]:
        rows.append(timing.row(
            f"level set, {r['n']} points x {r['lines']} lines, f+b on 1 / 2 threads",
            f"{r['forward_backward_1_us']:.0f} / {r['forward_backward_2_us']:.0f} us "
            f"(rule: {r['rule_jobs']} job{'s' if r['rule_jobs'] > 1 else ''})",
        ))  # fmt: skip
    fresh = result["fresh_memory"]
    rows.append(timing.row(
        f"{fresh['rays']} sample directions, jobs from the pool / fresh memory",
        " / ".join(
            ", ".join(f"{fresh[k]:.2f}" for k in sorted(fresh) if k.startswith(f"{s}_job"))
            for s in ("pool", "fresh")
        ) + " ms",
    ))  # fmt: skip
    leaf = result["leaf_gradient"]
    rows.append(timing.row(
        f"backward of (r * w).sum(), r {leaf['rows']} x 3, 1 / 2 threads: kernels.copy; np.array",
        f"{leaf['kernels_copy_1_ms']:.1f} / {leaf['kernels_copy_2_ms']:.1f}; "
        f"{leaf['np_array_1_ms']:.1f} / {leaf['np_array_2_ms']:.1f} ms",
    ))  # fmt: skip
    result["report"] = timing.report_section("Handing work to a thread (bench_dispatch.py)",
                                             rows, [], [])  # fmt: skip
    timing.write_json(args.out, "bench_dispatch", result)
    timing.print_report(result["report"], timing.machine())
    return result


if __name__ == "__main__":
    main()
