"""The back end: LLVM IR text (from ``codegen.py``) to machine code, cached, run on threads.

Why LLVM IR through llvmlite rather than Numba source: measured on the 2-core development
machine (``docs/compiler.md``), Numba spends most of a compile in its own type inference
and parallel-loop pass (0.36 s serial, 1.17 s parallel for a 200-operation loop), where
llvmlite (which Numba itself uses, so nothing new is installed) parses, optimises and emits
the same loop in tens of milliseconds. Threads come from Python instead of Numba's
``prange``: a ctypes call releases the GIL, so the thread pool of ``minidiff.threads``
runs a kernel's chunks side by side.

Compiled kernels are kept twice: in memory for this process, and as object code on disk
(``MINIDIFF_CACHE_DIR``, default ``~/.cache/minidiff``) for the next one, keyed by a hash
of the IR text, the generator's version and the CPU (object code for one CPU may use
instructions another lacks); or, for a compiled function's kernels, of the traced program
(``codegen.program_text``) and minidiff's own source, so that a kernel on disk is found
without writing or parsing its IR (``cached``). A file is written under a temporary name
then renamed, and carries a checksum of its contents, so concurrent processes and
interrupted writes never load a partial file.
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import os
import tempfile
import threading
from pathlib import Path

import llvmlite.binding as llvm

from minidiff import threads

# Part of every cache key: bump it whenever codegen.py or ir.py changes what they emit for
# the same program in a way the IR text would not show (the text itself is hashed).
GENERATOR_VERSION = "1"

_lock = threading.Lock()  # LLVM's global state is not thread-safe: one compile at a time
_compiled: dict[str, Kernel] = {}
_machine: tuple[str, str] | None = None  # (cpu name, features), read once

KERNEL_TYPE = ctypes.CFUNCTYPE(
    ctypes.c_int64, ctypes.c_void_p, ctypes.c_int64, ctypes.c_int64, ctypes.c_int64
)


class Kernel:
    """A compiled kernel: ``run(pointers, n, chunks, n_threads)`` calls it over chunks
    [0, chunks) of ``n`` elements, split into contiguous ranges, one per thread
    (``minidiff.threads``)."""

    def __init__(self, engine, key: str, name: str = "kernel"):
        self._engine = engine  # keeps the machine code alive
        self.key = key
        self._function = KERNEL_TYPE(engine.get_function_address(name))

    def run(self, pointers: ctypes.Array, n: int, chunks: int, n_threads: int,
            unit: int = 1) -> int:  # fmt: skip
        """0, or 1 + the first element (of the first failing range) whose gather index was out
        of range. Every chunk is computed the same whatever ``n_threads`` is. A job runs
        whole units of ``unit`` chunks (the groups of a VJP's partial tables)."""
        if n == 0:
            return 0
        bounds = job_bounds(chunks, n_threads, unit)
        n_jobs = len(bounds) - 1

        def job(j: int, _: int) -> int:
            return self._function(pointers, n, bounds[j], bounds[j + 1])

        failed = [r for r in threads.run_jobs(job, n_jobs) if r]
        return min(failed) if failed else 0


def job_bounds(chunks: int, n_threads: int, unit: int = 1) -> list[int]:
    """How ``Kernel.run`` splits chunks [0, chunks) among at most ``n_threads`` jobs of whole
    units of ``unit`` chunks: job j runs chunks [bounds[j], bounds[j + 1])."""
    units = -(-chunks // unit)
    n_jobs = max(1, min(n_threads, units))
    return [min(chunks, j * units // n_jobs * unit) for j in range(n_jobs + 1)]


def _after_fork_in_child() -> None:
    """A forked child's copy of the lock may be held by a thread that no longer exists."""
    global _lock
    _lock = threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_after_fork_in_child)


def _target_machine():
    """A new target machine for this CPU. One per engine: an execution engine owns its
    target machine and frees it with itself, so sharing one would leave the others with a
    dangling one."""
    global _machine
    if _machine is None:
        llvm.initialize_native_target()
        llvm.initialize_native_asmprinter()
        _machine = (llvm.get_host_cpu_name(), llvm.get_host_cpu_features().flatten())
    cpu, features = _machine
    target = llvm.Target.from_default_triple()
    return target.create_target_machine(cpu=cpu, features=features, opt=3)


def cache_dir() -> Path:
    """Where object code is kept between processes."""
    root = os.environ.get("MINIDIFF_CACHE_DIR") or os.path.join(Path.home(), ".cache", "minidiff")
    return Path(root) / "kernels"


@functools.cache
def _this_cpu() -> tuple[str, ...]:
    """The process's triple, CPU name and features and LLVM's version (asked of LLVM once)."""
    _target_machine()  # initialises LLVM's view of this CPU
    return (
        llvm.get_process_triple(),
        llvm.get_host_cpu_name(),
        llvm.get_host_cpu_features().flatten(),
        str(llvm.llvm_version_info),
    )


def _key(text: str, program: str | None = None) -> str:
    """The cache key of a kernel: its IR ``text``'s, or, given the ``program`` text that
    determines it (``codegen.program_text``), that one's with minidiff's source."""
    parts = [text] if program is None else ["program", _source(), program]
    stamp = "\n".join([GENERATOR_VERSION, *_this_cpu(), *parts])
    return hashlib.sha256(stamp.encode()).hexdigest()


#: The modules that turn a traced program into IR: the primitives' scalar forms and
#: derivative rules, the tracer that applies them, the scalar operations, the generator.
SOURCE_FILES = ("primitives.py", "trace.py", "ir.py", "codegen.py")


@functools.cache
def _source() -> str:
    """A hash of ``SOURCE_FILES``, whose edits a program's text does not show."""
    digest = hashlib.sha256()
    for name in SOURCE_FILES:
        digest.update(name.encode() + b"\0" + (Path(__file__).parent / name).read_bytes())
    return digest.hexdigest()


def _read_object(path: Path) -> bytes | None:
    """The object code stored at ``path``, or None if absent or damaged."""
    try:
        stored = path.read_bytes()
    except OSError:
        return None
    checksum, payload = stored[:32], stored[32:]
    return payload if hashlib.sha256(payload).digest() == checksum else None


def _write_object(path: Path, payload: bytes) -> None:
    """Store object code atomically (another process sees the whole file or none)."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        handle, temporary = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
        with os.fdopen(handle, "wb") as f:
            f.write(hashlib.sha256(payload).digest() + payload)
        os.replace(temporary, path)
    except OSError:  # a read-only home: the kernel still works, just is not kept
        pass


def kernel_name(program: str) -> str:
    """The function name of the kernel of the ``program`` text: its key's, unique among the
    kernels that share one execution engine (``_add_shared``)."""
    return "k" + _key("", program)


def cached(program: str) -> Kernel | None:
    """The kernel of the ``program`` text (``codegen.program_text``) if this process or
    the disk cache has it, else None: loaded from its object code into the shared engine,
    its IR neither written nor parsed."""
    key = _key("", program)
    kernel = _compiled.get(key)
    if kernel is not None:
        return kernel
    stored = _read_object(cache_dir() / f"{key}.o")
    if stored is None:
        return None
    with _lock:
        kernel = _compiled.get(key)
        if kernel is None:
            kernel = _compiled[key] = _add_shared(stored, key)
    return kernel


#: The execution engine that holds every kernel keyed by its program (``_add_shared``):
#: creating an engine costs about as much as loading a kernel's object code (~0.3 ms) and
#: finalising a new engine's first object more (~0.6 ms), adding to one ~0.05 ms.
_shared: object | None = None


def _add_shared(payload: bytes, key: str) -> Kernel:
    """The kernel of object code ``payload`` (function ``"k" + key``), added to the shared
    engine (made on first use). Call with ``_lock`` held."""
    global _shared
    if _shared is None:
        _shared = llvm.create_mcjit_compiler(llvm.parse_assembly(""), _target_machine())
    name = "k" + key
    if not _shared.get_function_address(name):  # else already there (the same key: the same code)
        _shared.add_object_file(llvm.ObjectFileRef.from_data(payload))
        _shared.finalize_object()
    return Kernel(_shared, key, name)


def compile_ir(text: str, program: str | None = None) -> Kernel:
    """The kernel for IR ``text``: from memory, from disk, or compiled now (optimised at
    LLVM's -O3 pipeline, for this CPU). ``program``: the program text that determines
    ``text`` (``codegen.program_text``), under whose key the kernel is then kept (and
    found again by ``cached``); None: keyed by ``text``."""
    key = _key(text, program)
    kernel = _compiled.get(key)
    if kernel is not None:
        return kernel
    with _lock:
        kernel = _compiled.get(key)
        if kernel is None:
            kernel = _build(text, key, shared=program is not None)
            _compiled[key] = kernel
    return kernel


def _build(text: str, key: str, shared: bool = False) -> Kernel:
    """The kernel of IR ``text``: its object code from disk, or compiled (and stored). In
    the ``shared`` engine (``text`` names its function ``"k" + key``), else in an engine of
    its own (function ``kernel``)."""
    machine = _target_machine()
    path = cache_dir() / f"{key}.o"
    stored = _read_object(path)
    if shared:
        if stored is None:
            stored = machine.emit_object(_optimised(text, key, machine))
            _write_object(path, stored)
        return _add_shared(stored, key)
    if stored is None:
        module = _optimised(text, key, machine)
    else:  # the engine wants a module; the object cache below gives its code
        module = llvm.parse_assembly(text)
        module.name = key
    engine = llvm.create_mcjit_compiler(module, machine)
    engine.set_object_cache(
        lambda _module, payload: _write_object(path, payload),
        lambda _module: stored,
    )
    engine.finalize_object()
    return Kernel(engine, key)


def _optimised(text: str, key: str, machine):
    """IR ``text`` parsed, checked and optimised by LLVM's -O3 pipeline for ``machine``."""
    module = llvm.parse_assembly(text)
    module.name = key
    module.verify()
    tuning = llvm.create_pipeline_tuning_options(speed_level=3)
    builder = llvm.create_pass_builder(machine, tuning)
    builder.getModulePassManager().run(module, builder)
    return module
