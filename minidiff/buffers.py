"""Output arrays that are used again: how minidiff avoids fresh memory on every pass.

Why: one render and its backward pass allocate hundreds of arrays of a few hundred KB to a
few MB, and free them all when the pass ends.  glibc's allocator gives memory that large
back to the kernel when it is freed (it unmaps the block, or trims the top of the heap), so
the next pass touches brand-new pages: one page fault per 4 KiB, a third of the time of a
forward render measured on the paper scene (``benchmarks/bench_render.py``).

What this does instead: the kernels (``kernels.py``) take their large outputs from here.
``empty(shape, dtype)`` hands out an array of that shape and dtype that was made for an
earlier call and that *nothing refers to any more* -- the pool's own reference is the only
one left, which Python's reference count tells exactly (a view keeps its base alive, so a
result that a user still holds, or a view of it, is never handed out again).  The memory
stays in the process, so the second pass of the same shapes allocates nothing.

Reference counts are how CPython manages memory, not a promise of the language: another
interpreter, a free-threaded build, or a new CPython whose bytecode borrows references
(3.14's ``LOAD_FAST_BORROW``) may count differently, and one count too low would hand an
array someone still holds to the next kernel: a silently wrong image or gradient.  So the
module proves at import, on the running interpreter and through ``empty`` itself, that
held arrays are never handed out (held by a variable, a view, a container, a closure, a
tensor on the tape, another thread) and that an unheld one is; if any of that fails, reuse
is turned off (``REUSE`` says whether it is on and ``REUSE_CHECK`` why).  Only CPython
with its GIL is trusted at all.

This is local to minidiff: no allocator setting of the process is changed, and only the
arrays that come from here are kept.  Arrays in use live on when the pool drops them; they
are just not reused.  The pool drops a shape (with its arrays) when:

* it is old: it has not been asked for in the last ``MAX_AGE`` (256) requests of large
  arrays.  Shapes that come back pass after pass are asked for far more often (a render of
  the paper scene and its backward pass ask for 62 large arrays at 512 x 512, 83 with the
  boundary term), but a shape that a pass made once and that never comes back (a boundary
  term has as many points as its edges cover pixels, a new count in every iteration of an
  optimisation) would otherwise be kept until the cap below; now it is gone after 256
  more requests, so what the pool holds no longer grows with the number of iterations;
* the pool would exceed ``max_bytes`` (default 512 MiB): the shapes used least recently go
  first.

Age is counted in requests, not in time or reference counts: the same calls drop the same
shapes on every run.  ``clear()`` drops everything; ``set_max_bytes(0)`` turns reuse off.

Reuse pays when the same shapes come back pass after pass (the direct renderer: one image,
the same rays). A Monte Carlo pass asks for new shapes every batch (how many paths are
still alive at each depth), which only fills the pool with arrays nobody asks for again;
code like that runs inside ``with fresh():``, which makes ``empty`` plain ``np.empty`` for
the current thread (or asyncio task) only: a context variable, not a process-wide switch.
"""

from __future__ import annotations

import contextlib
import contextvars
import math
import sys
import threading
from collections import OrderedDict

import numpy as np

from minidiff.scoped import set_within

#: Arrays smaller than this come from NumPy directly: glibc keeps small blocks in the
#: process anyway (its mmap threshold starts at 128 KiB), so reusing them would gain nothing.
MIN_BYTES = 128 * 1024

#: A shape not asked for in this many requests of large arrays (outside ``fresh()``) is
#: dropped from the pool (see the module docstring).
MAX_AGE = 256


class _Shape:
    """The pool's arrays of one (shape, dtype), and the request (``_requests``) that last
    asked for that shape."""

    __slots__ = ("arrays", "last")

    def __init__(self, last: int) -> None:
        self.arrays: list[np.ndarray] = []
        self.last = last


_lock = threading.Lock()
# (shape, dtype) -> _Shape, the least recently asked for first (so also the oldest first).
_pool: OrderedDict[tuple, _Shape] = OrderedDict()
_held_bytes = 0
_max_bytes = 512 * 2**20
_requests = 0  # requests of large arrays that the pool has seen: its clock for ages

# sys.getrefcount(array) while the array sits in a pool list and in the loop variable that
# looks at it (plus getrefcount's own argument): nobody else holds it.
_UNUSED = 3

#: True inside ``with fresh():`` (this thread or task only): no reuse.
_fresh: contextvars.ContextVar[bool] = contextvars.ContextVar("minidiff_fresh", default=False)


def fresh() -> contextlib.AbstractContextManager:
    """Within the block, on this thread (or asyncio task) only, ``empty`` neither reuses
    nor keeps arrays: for passes whose shapes will not come back."""
    return set_within(_fresh, True)


def empty(shape: tuple[int, ...], dtype: np.dtype | type) -> np.ndarray:
    """Equals ``np.empty(shape, dtype)``: an array of that shape and dtype, contents arbitrary.

    Large arrays are reused from earlier calls once nothing else refers to them.
    """
    dtype = np.dtype(dtype)
    shape = tuple(int(n) for n in shape)
    nbytes = dtype.itemsize * math.prod(shape)
    if nbytes < MIN_BYTES or nbytes > _max_bytes or _fresh.get():
        return np.empty(shape, dtype)
    key = (shape, dtype)
    global _held_bytes, _requests
    with _lock:
        _requests += 1
        _drop_old(_requests - MAX_AGE)
        entry = _pool.get(key)
        if entry is None:
            entry = _pool[key] = _Shape(_requests)
        else:
            _pool.move_to_end(key)  # most recently used last
            entry.last = _requests
            arrays = entry.arrays
            for a in arrays:
                if sys.getrefcount(a) == _UNUSED:
                    return a
        while _held_bytes + nbytes > _max_bytes and len(_pool) > 1:
            old_key = next(iter(_pool))
            if old_key == key:
                break
            _drop(old_key)
        a = np.empty(shape, dtype)
        if _held_bytes + nbytes <= _max_bytes:
            entry.arrays.append(a)
            _held_bytes += nbytes
        return a


def _drop_old(oldest: int) -> None:
    """Drop the shapes last asked for before request ``oldest`` (holding ``_lock``). The
    pool is in the order of last requests, so they are at its front."""
    while _pool:
        key, entry = next(iter(_pool.items()))
        if entry.last >= oldest:
            return
        _drop(key)


def _drop(key: tuple) -> None:
    """Forget the pool's arrays of ``key`` (holding ``_lock``)."""
    global _held_bytes
    _held_bytes -= sum(a.nbytes for a in _pool.pop(key).arrays)


def _proof() -> str | None:
    """None if ``empty`` provably reuses exactly the arrays nobody holds on this
    interpreter; else what went wrong. Runs ``empty`` on a shape of its own and drops it."""
    if sys.implementation.name != "cpython":
        return f"not CPython ({sys.implementation.name}): reference counts are not exact"
    if not getattr(sys, "_is_gil_enabled", lambda: True)():
        return "free-threaded CPython: another thread's references are counted lazily"
    shape, dtype = (MIN_BYTES // 8 + 1,), np.dtype(np.float64)
    key = (shape, dtype)
    try:

        class Owner:  # e.g. a Tensor holding its data, or a cache entry
            def __init__(self, array):
                self.array = array

        def in_thread(array):
            """A thread that holds ``array`` (in its frame) until released: (thread, event)."""
            held, release = threading.Event(), threading.Event()

            def hold(a=array):
                held.set()
                release.wait()

            worker = threading.Thread(target=hold, daemon=True)
            worker.start()
            held.wait()
            return worker, release, array

        # How a user, the tape or a cache may hold an array: (holder of a, a from holder).
        ways = {
            "a variable": (lambda a: a, lambda h: h),
            "a view": (lambda a: a[1:], lambda h: h),
            "a list": (lambda a: [a], lambda h: h[0]),
            "a closure": (lambda a: lambda: a, lambda h: h()),
            "an object": (Owner, lambda h: h.array),
            "another thread": (in_thread, lambda h: h[2]),
        }
        for how, (hold, get) in ways.items():
            holder = hold(empty(shape, dtype))
            if how == "another thread":  # only the thread holds it while we ask
                worker, release, array = holder
                address, holder = array.ctypes.data, None
                del array
                fresh = empty(shape, dtype)
                reused = fresh.ctypes.data == address
                release.set()
                worker.join()
            else:
                fresh = empty(shape, dtype)
                reused = np.shares_memory(fresh, get(holder))
            if reused:
                return f"an array held by {how} was handed out again"
            del holder, fresh
        first = empty(shape, dtype)
        address = first.ctypes.data
        del first
        again = empty(shape, dtype)
        if again.ctypes.data != address:
            return "an array nobody held was not reused"
        del again
        return None
    finally:
        with _lock:
            if key in _pool:
                _drop(key)


def zeros(shape: tuple[int, ...], dtype: np.dtype | type) -> np.ndarray:
    """Equals ``np.zeros(shape, dtype)``, reusing memory as :func:`empty` does."""
    out = empty(shape, dtype)
    out.fill(0)
    return out


def held_bytes() -> int:
    """Bytes of the arrays the pool keeps (in use or free)."""
    return _held_bytes


def max_bytes() -> int:
    """The most bytes of arrays the pool keeps for reuse (``set_max_bytes``)."""
    return _max_bytes


def set_max_bytes(n: int) -> None:
    """Keep at most ``n`` bytes of arrays for reuse (0 turns reuse off); drops the pool."""
    global _max_bytes
    if isinstance(n, bool) or not isinstance(n, int) or n < 0:
        raise ValueError(f"n must be an integer >= 0 (bytes), got {n!r}")
    clear()
    _max_bytes = n


def clear() -> None:
    """Forget every array kept for reuse (their memory is freed once nothing uses them)."""
    global _held_bytes
    with _lock:
        _pool.clear()
        _held_bytes = 0


#: Why reuse is on or off on this interpreter (see the module docstring): None if proven.
REUSE_CHECK = _proof()
#: Whether ``empty`` reuses arrays at all.
REUSE = REUSE_CHECK is None
if not REUSE:
    _max_bytes = 0
