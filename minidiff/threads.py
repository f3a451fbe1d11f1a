"""Threads: one pool runs every parallel kernel, minidiff's compiled ones and the renderer's
hand-written Numba ones alike.

A kernel releases the GIL while it runs (a ctypes call into minidiff's machine code; a
Numba function compiled with ``nogil=True``), so Python threads run its jobs side by side.
A kernel of ``n_jobs`` jobs is called once per job as ``kernel(job, n_jobs, *args)``, and
each job does a fixed share of the work that depends only on ``job`` and ``n_jobs``: no
result depends on which thread ran a job or when.

Why not Numba's ``prange``: its parallel-loop pass roughly doubles the time Numba takes to
compile a kernel (the closest-hit traversal: about 4 s against 2 s here, cold; everything
the renderer compiles on a fresh clone is paid by the first render), and its default
threading layer on a machine without OpenMP or TBB (``workqueue``) aborts the process when
two Python threads launch parallel kernels at once. A thread pool has neither problem.

How many threads: ``thread_count()``, which is ``using_threads``'s count within its block
in this thread, else Numba's ``numba.get_num_threads()`` (itself per thread; set with
``numba.set_num_threads`` or ``NUMBA_NUM_THREADS``).
"""

from __future__ import annotations

import contextlib
import contextvars
import os
import threading
from collections import deque
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor, wait

import numba
from numba.core.compiler import CompilerBase, DefaultPassBuilder, Flags
from numba.core.compiler_machinery import FunctionPass, register_pass
from numba.core.ir_utils import simplify
from numba.core.typed_passes import NopythonRewrites

from minidiff.scoped import set_within

__all__ = [
    "using_threads",
    "thread_count",
    "run_jobs",
    "beside",
    "share_tasks",
    "job_count",
    "share",
    "jit",
    "kernel",
    "borrowing",
]


class _Budget:
    """How many threads kernels launched under a ``using_threads`` block may use. Under
    ``beside``, the work's and the block's budgets grow when the other one ends (``count``
    is read at each launch; the count changes only the speed, never a result)."""

    def __init__(self, count: int) -> None:
        self.count = count


# Threads a kernel may use in this thread (context); None: Numba's setting.
_threads: contextvars.ContextVar[_Budget | None] = contextvars.ContextVar("threads", default=None)

_lock = threading.Lock()
_pool: ThreadPoolExecutor | None = None


@contextlib.contextmanager
def using_threads(count: int):
    """Within the block, kernels launched from this thread run on ``count`` threads
    (results are the same for any count; this only changes the speed)."""
    if isinstance(count, bool) or not isinstance(count, int) or count < 1:
        raise ValueError(f"using_threads: count must be a positive int, got {count!r}")
    with _budget(_Budget(count)):
        yield


def _budget(budget: _Budget):
    """``using_threads`` with a budget the caller may change while the block runs."""
    return set_within(_threads, budget)


def thread_count() -> int:
    """How many threads a kernel launched now from this thread may use."""
    budget = _threads.get()
    return budget.count if budget is not None else numba.get_num_threads()


def job_count(n_items: int, per_job: int = 1) -> int:
    """Jobs for ``n_items`` items dealt in blocks of ``per_job``: one per thread, fewer if
    there are fewer blocks, at least one."""
    blocks = -(-n_items // per_job)
    return max(1, min(blocks, thread_count()))


def executor() -> ThreadPoolExecutor:
    """The shared thread pool (made on first use)."""
    global _pool
    with _lock:
        if _pool is None:
            workers = os.cpu_count() or 1
            _pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="minidiff")
        return _pool


def run_jobs(kernel: Callable, n_jobs: int, *args) -> list:
    """``[kernel(job, n_jobs, *args) for job in range(n_jobs)]``: job 0 in the calling
    thread (which would otherwise only wait), the others on the pool's threads."""
    if n_jobs <= 1:
        return [kernel(0, 1, *args)]
    others = [executor().submit(kernel, job, n_jobs, *args) for job in range(1, n_jobs)]
    try:
        first = kernel(0, n_jobs, *args)
    finally:
        wait(others)  # even if job 0 failed: the others still write into the arrays
    return [first, *(future.result() for future in others)]


@contextlib.contextmanager
def beside(work: Callable[[], object] | None):
    """Run ``work()`` on a thread of its own while the ``with`` block runs in this one;
    yields ``result()``, which waits for ``work`` and returns what it returned (or raises
    what it raised). The block and ``work`` share this thread's kernel threads
    (``thread_count``): ``work``'s kernels get half of them, the block's the rest, so that
    the two together use as many as the caller asked for; whichever ends first hands its
    threads to the other (kernels launched after that get them all). With one thread there
    is nothing to share: ``work`` runs here, before the block (what it raises is raised by
    ``result()`` all the same). ``work`` None: nothing runs beside the block, which keeps
    every thread (``result()`` is None).

    For two independent steps of which neither needs the other's results, each running
    parts that hold the GIL (NumPy's loops that are not threaded, Python): one step's such
    parts run while the other's do. ``work`` runs in a copy of the caller's context
    (``contextvars``: the tape's gradient mode, ``using_threads``); results do not depend
    on the split. Leaving the block, by its end or an exception, waits for ``work``, and
    meanwhile this thread runs the tasks ``work`` shares out (``share_tasks``) that it has
    not begun."""
    count = thread_count()
    outcome: dict[str, object] = {"value": None}

    def run() -> None:
        try:
            outcome["value"] = work()
        except BaseException as error:  # handed to result(), raised in the caller
            outcome["error"] = error

    def result():
        if thread is not None:
            thread.join()
        if "error" in outcome:
            raise outcome["error"]
        return outcome["value"]

    thread = None
    if work is None or count < 2:
        if work is not None:
            run()
        yield result
        return
    mine, theirs = _Budget(count // 2), _Budget(count - count // 2)
    board = _Board()

    def run_beside() -> None:
        with _budget(mine), set_within(_board, board):
            try:
                run()
            finally:
                theirs.count = count  # the work is done: its threads are free for the block
                board.close()

    thread = threading.Thread(target=contextvars.copy_context().run, args=(run_beside,))
    thread.start()
    try:
        with _budget(theirs):
            yield result
    finally:
        board.help(mine, theirs, count)  # the block is done: its thread and threads help
        thread.join()


class _Task:
    """One of ``share_tasks``'s callables, run once by whichever thread claims it first
    (``claimed``, set under the board's lock); ``done`` is set when it has run."""

    def __init__(self, call: Callable[[], object]) -> None:
        self.call, self.context = call, contextvars.copy_context()  # the poster's context
        self.claimed, self.done = False, threading.Event()
        self.value: object = None
        self.error: BaseException | None = None

    def run(self) -> None:
        """Call it here, keeping what it returns or raises."""
        try:
            self.value = self.call()
        except BaseException as error:  # raised by share_tasks, in the task's order
            self.error = error
        finally:
            self.done.set()


class _Board:
    """The tasks ``beside``'s work has posted (``share_tasks``) and not yet begun, for the
    block's thread to take once its block has ended, until the work ends (``close``)."""

    def __init__(self) -> None:
        self.lock = threading.Condition()
        self.posted: deque[_Task] = deque()
        self.closed = False

    def post(self, tasks: Sequence[_Task]) -> None:
        with self.lock:
            self.posted.extend(tasks)
            self.lock.notify_all()

    def claim(self, task: _Task) -> bool:
        """True if ``task`` was not begun: it is now the caller's to run."""
        with self.lock:
            mine, task.claimed = not task.claimed, True
            return mine

    def close(self) -> None:
        with self.lock:
            self.closed = True
            self.lock.notify_all()

    def help(self, work: _Budget, block: _Budget, count: int) -> None:
        """Run the posted tasks no one has begun, the last posted first (the poster takes its
        own in order: the two meet in the middle), each in its poster's context on the
        block's share of the threads (``block``), until the work ends. While there is none
        to run, the work's kernels may use every thread (``work``, of ``count``)."""
        while True:
            with self.lock:
                task = self._take()
                while task is None and not self.closed:
                    work.count = count
                    self.lock.wait()
                    task = self._take()
                if task is None:
                    return
                work.count = count // 2
            task.context.run(_run_with, block, task)

    def _take(self) -> _Task | None:
        while self.posted:
            task = self.posted.pop()
            if not task.claimed:
                task.claimed = True
                return task
        return None


def _run_with(budget: _Budget, task: _Task) -> None:
    with _budget(budget):
        task.run()


# The board of the ``beside`` work this thread runs (context); None: not under ``beside``.
_board: contextvars.ContextVar[_Board | None] = contextvars.ContextVar("board", default=None)


def share_tasks(tasks: Sequence[Callable[[], object]]) -> list:
    """``[task() for task in tasks]`` for independent ``tasks`` (none needs another's
    result, none writes what another reads). Run by ``beside``'s work, the tasks are posted
    for the block's thread, which, once its block has ended, takes those the work has not
    begun yet: the two threads end together rather than one waiting for the other's last
    steps. Who runs a task changes only when, never what it returns; a task must not record
    on the tape (under ``no_grad``, as ``beside``'s work should be), whose order would then
    depend on who ran what. Elsewhere the tasks run here, in order. If tasks raise, what
    the first of them (in order) raised is raised, once every task begun has ended (none
    is begun after one has failed)."""
    board = _board.get()
    if board is None or len(tasks) < 2:
        return [task() for task in tasks]
    posted = [_Task(task) for task in tasks]
    board.post(posted)
    for task in posted:
        if board.claim(task):
            task.run()
            if task.error is not None:
                break
    for task in posted:
        if board.claim(task):  # left unbegun after a failure: never to run
            task.done.set()
        task.done.wait()
    for task in posted:
        if task.error is not None:
            raise task.error
    return [task.value for task in posted]


@register_pass(mutates_CFG=True, analysis_only=False)
class _Simplify(FunctionPass):
    """Numba's own clean-up of its typed IR (copy propagation, dead code, the control-flow
    graph simplified), which its ``parallel=True`` pipeline runs and its plain one does
    not."""

    _name = "minidiff_kernel_simplify"

    def __init__(self) -> None:
        FunctionPass.__init__(self)

    def run_pass(self, state) -> bool:
        simplify(state.func_ir, state.typemap, state.calltypes, {})
        return True


class _KernelPipeline(CompilerBase):
    """Numba's nopython pipeline with ``_Simplify`` after its rewrites: the IR a kernel
    compiled with ``parallel=True`` had. Without it the light's-view shadow test, lowered
    from the same source, ran 2.2x slower (5.4 against 2.4 ms, one thread, the paper scene
    at 512x512), the IR's extra copies and blocks left to LLVM."""

    def define_pipelines(self):
        pipeline = DefaultPassBuilder.define_nopython_pipeline(self.state)
        pipeline.add_pass_after(_Simplify, NopythonRewrites)
        pipeline.finalize()
        return [pipeline]


#: Options every Numba function of the project is compiled with: no C-callable wrapper,
#: which Numba makes for each function so that it can be passed around as a first-class
#: function object (none of ours is), at about 20 ms of compiling each: a second of a cold
#: start's first boundary-term gradient. (An option of Numba's compiler flags without a
#: public description: asked for only where this Numba has it.)
_OPTIONS = {"no_cfunc_wrapper": True} if hasattr(Flags, "no_cfunc_wrapper") else {}


def jit(function: Callable | None = None, **options) -> Callable:
    """``numba.njit(function, **options)`` with the project's own options (``_OPTIONS``):
    how every hand-written Numba function in ``minidiff`` and ``render`` is compiled, used
    as ``@jit(cache=True, ...)``. Unless ``options`` say otherwise, NumPy's error model
    (x / 0 is inf or NaN, as in the kernels) and the GIL released: every function compiled
    with the same flags, so that the NumPy functions they use (``np.empty``, ``max``, ...),
    which Numba compiles once per caller's flags, are compiled once (119 -> 100 functions
    compiled for a cold first boundary-term gradient)."""
    options = {"error_model": "numpy", "nogil": True, **options}
    if function is None:
        return lambda f: numba.njit(**_OPTIONS, **options)(f)
    return numba.njit(**_OPTIONS, **options)(function)


def kernel(function: Callable) -> Callable:
    """A job kernel (``kernel(job, n_jobs, ...)``, run by ``run_jobs``): ``function``
    compiled by Numba with the GIL released, cached on disk, NumPy's error model (x / 0 is
    inf or NaN, not an exception), through ``_KernelPipeline``."""
    return jit(function, cache=True, pipeline_class=_KernelPipeline)


def borrowing(function: Callable) -> Callable:
    """A Numba function for a kernel's inner loop that allocates nothing: compiled without
    Numba's reference counting (``_nrt=False``), so the arrays it is handed stay borrowed
    from its caller, which keeps them alive.

    Why: Numba counts the references to every array a function receives or passes on, with
    an atomic add and subtract on the array's shared count; where it cannot pair them up
    (across loops and calls) they stay, at each call, each inlined assignment, each path.
    The path kernel spent 65 % of its time (one thread, the Cornell box) on them, and
    threads that share a scene's arrays contend for their counts. Numba refuses to compile
    a function with this flag that would allocate (``np.empty``, a new array): such work
    stays in the kernel that calls it (``kernel``, counted as usual)."""
    return jit(function, cache=True, _nrt=False)


def inlined(function: Callable) -> Callable:
    """A ``borrowing`` function that LLVM inlines into every caller (Numba's
    ``forceinline``: LLVM's ``alwaysinline``), for the per-ray and per-primitive work of
    the kernels' inner loops (a traversal, a ray-primitive test).

    Why not Numba's own ``inline="always"``: that copies the function's IR into each
    caller, where it is typed and lowered again, which is most of a cold compile (a
    traversal copied into four kernels cost 1.8-2.4 s of compiling each). This one is typed,
    lowered and optimised once, then linked into each caller and inlined there by LLVM, so
    the callers run the same inlined code (the BVH's closest and any hits of 1.3M
    triangles within noise of Numba's inlining: 61 against 61 ms, 41 against 41 ms)."""
    if not hasattr(Flags, "forceinline"):  # a Numba without it: its own inlining, same code
        return jit(function, cache=True, inline="always")
    return jit(function, cache=True, _nrt=False, forceinline=True)


@jit(cache=True, inline="always")
def share(job, n_jobs, n):
    """(start, stop): job ``job``'s contiguous share of ``n`` independent items split among
    ``n_jobs`` jobs (for a kernel, inside its ``nogil`` Numba code)."""
    return job * n // n_jobs, (job + 1) * n // n_jobs


def _after_fork_in_child() -> None:
    """A forked child's copy of the pool has no threads left, and its copy of the lock may
    be held by a thread that no longer exists: start both afresh."""
    global _pool, _lock
    _pool, _lock = None, threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_after_fork_in_child)
