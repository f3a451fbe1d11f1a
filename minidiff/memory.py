"""Opt-in allocator tuning for repeated large passes (never applied on import).

Why: a forward+backward pass allocates hundreds of arrays of a few hundred KB each. glibc
serves those with mmap and returns them to the kernel when freed; the next pass then pays a
page fault for every 4 KiB page it touches again. Measured on the paper scene, that can be a
large share of the wall time (see benchmarks/bench_minidiff.py, which reports page faults per
pass). Raising the mmap and trim thresholds keeps freed memory in the process for reuse.

minidiff's kernels avoid most of this on their own (``minidiff.buffers`` reuses their
outputs); this switch remains for other code.

The same effect without code: start Python with e.g.
``MALLOC_MMAP_THRESHOLD_=1073741824 MALLOC_TRIM_THRESHOLD_=1073741824``.
"""

from __future__ import annotations

import ctypes
import ctypes.util

# glibc's mallopt parameter numbers (malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3


def keep_freed_memory(threshold_bytes: int = 1 << 30) -> bool:
    """Ask glibc to serve allocations below ``threshold_bytes`` from the heap and not to give
    freed memory back to the kernel until that much is free. Returns True on success, False
    where it does not apply (not glibc). Affects the whole process; call it once, early."""
    name = ctypes.util.find_library("c")
    if name is None:
        return False
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    # The mmap threshold is capped by glibc (32 MiB on 64-bit); ask for at most that.
    mmap_ok = mallopt(_M_MMAP_THRESHOLD, min(threshold_bytes, 32 << 20)) == 1
    trim_ok = mallopt(_M_TRIM_THRESHOLD, threshold_bytes) == 1
    return mmap_ok and trim_ok
