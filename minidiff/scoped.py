"""A context variable set for the length of a block: minidiff's per-thread switches.

Every mode minidiff keeps (the tape's gradient mode, anomaly checking, running compiled
functions on the tape, the array pool's ``fresh``, the kernels' thread count, the graph a
trace appends to) is a ``contextvars.ContextVar``, never a module-level flag: each thread
(and each asyncio task) sees its own value, so one thread's ``no_grad`` never turns another
thread's tape off. This is the one way they are set: for a ``with`` block, and put back as
they were when it ends, however it ends.
"""

from __future__ import annotations

import contextlib
import contextvars
from collections.abc import Iterator
from typing import TypeVar

T = TypeVar("T")


@contextlib.contextmanager
def set_within(variable: contextvars.ContextVar[T], value: T) -> Iterator[T]:
    """Within the block, ``variable`` holds ``value`` in the current context (thread or
    task) only; the block gets ``value``. Afterwards it holds what it held before."""
    token = variable.set(value)
    try:
        yield value
    finally:
        variable.reset(token)
