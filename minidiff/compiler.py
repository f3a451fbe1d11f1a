"""``minidiff.compile``: a function of minidiff arrays, traced once, run as fused machine code.

    >>> import numpy as np, minidiff as md
    >>> @md.compile(shared=("light",))
    ... def lambert(normals, points, light):
    ...     to_light = md.normalize(light - points)
    ...     return md.maximum(md.dot(normals, to_light), 0.0)

The first call with a new signature (argument shapes and dtypes, and any non-array
arguments, which are passed to the function as they are) *traces* the function
(``trace.py``): it runs once on traced arrays and records each element's arithmetic as a
scalar program (``ir.py``). ``codegen.py`` writes that program as one loop over the batch,
``backend.py`` compiles it. Later calls with the same signature only run machine code.

On the tape the compiled function is **one node** (``record``): its VJP runs the program
backwards (``codegen`` mode "vjp"), its JVP forwards with tangents ("jvp"), both generated
from each primitive's own scalar rules, so it composes with everything else in minidiff,
in reverse and in forward mode. Without the tape (``md.no_grad()``, or nothing requiring
grad) it is just the forward kernel.

The plain function stays what it was: calling ``lambert.function(...)`` runs it on the tape,
primitive by primitive, which is how the course reads it and how the tests check the
compiled one.

Arguments: arrays (Tensors, NumPy arrays, Python floats) are *batched* (their first axis is
the batch, the same length n for all) unless named in ``shared`` (the same for every
element). A tuple or list argument is taken apart: each Tensor or NumPy array in it (at any
depth) is an array argument of its own (batched, or shared if the argument's name is in
``shared``), the rest of it static; so a variable number of arrays (a scene's lights) can
be passed as one argument. Anything else (ints, strings, None, classes...) is a static
argument: part of the signature, passed to the function unchanged. Arrays are float64,
integer (indices) or boolean; float32 is refused (the program is written in double
precision). An empty batch (n = 0) runs the plain function on the tape: there is nothing
to compile for, and it gives the outputs' shapes.
"""

from __future__ import annotations

import contextvars
import ctypes
import dataclasses
import functools
import inspect
import threading
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from minidiff import backend, codegen, ir
from minidiff import buffers as memory
from minidiff.scoped import set_within
from minidiff.tensor import (
    Tensor,
    _accumulate_leaf,
    _anomaly_mode,
    is_grad_enabled,
    no_grad,
    record,
)
from minidiff.threads import thread_count, using_threads  # noqa: F401 (re-exported)
from minidiff.trace import DTYPES, TYPES, CompileError, Slot, Traced, traced

MAX_TRACES = 64  # signatures remembered per compiled function (the oldest is dropped)
# Gathered rows' gradients are added on threads from this many contributions on, and only
# where the threads together would read at most SCATTER_OVERLAP times the blocks of rows
# there are (``_scatter``). Below it, finding the blocks' rows and starting a thread cost
# more than they save (1M contributions, 1 -> 2 threads: ascending rows 1.2 -> 1.15 ms,
# rows in random order 1.8-1.9 -> 2.2-2.3 ms, found to need one thread).
PARALLEL_SCATTER = 1 << 20
SCATTER_OVERLAP = 1.5
# A kernel runs on threads only if its batch times its program's lines (the traced graph's
# nodes) reaches this: handing a job to a pool thread and hearing back costs ~100 us on a
# machine whose idle cores sleep (two wake-ups across cores), and smaller kernels ran
# slower on two threads than on one (docs/compiler.md, "Threads and memory around the
# kernels"; benchmarks/bench_dispatch.py). Only the speed changes: the chunks, and so every
# bit, are the same for any number of jobs.
PARALLEL_WORK = 1 << 21

# Whether compiled functions run their plain function on the tape in this thread (context).
_on_the_tape: contextvars.ContextVar[bool] = contextvars.ContextVar("on_the_tape", default=False)


_ARRAYS = (Tensor, np.ndarray, float, np.floating, np.integer, np.bool_)


def tape_only():
    """Within the block, compiled functions called from this thread (context) run their
    plain function instead, primitive by primitive on the tape: the readable reference the
    compiled kernels are tested against (and the course's path). Other threads keep
    their kernels."""
    return set_within(_on_the_tape, True)


class _Leaf(NamedTuple):
    """An array argument (or an array in a tuple or list argument): its index among the
    call's arrays and its slot. (Named tuples: a signature's key is hashed on every call.)"""

    index: int
    slot: Slot


class _Static(NamedTuple):
    """A static value, passed to the function as it is (part of the signature, with its
    type: 1, 1.0 and True are different signatures)."""

    kind: type
    value: Any
    tag: str = "static"  # (a length of its own: never equal to a _Leaf)


class _Container(NamedTuple):
    """A tuple or list argument taken apart: its type and the trees of its items."""

    kind: type
    parts: tuple
    tag: str = "container"


@dataclass
class _Trace:
    """One signature's program and what it needs at run time."""

    program: codegen.Program
    batch: int
    output_shapes: tuple[tuple[int, ...], ...]  # per output, one element's shape
    single: bool  # the function returned one array (not a tuple)
    kernels: dict
    sizes: np.ndarray  # per slot, a shared array's rows (0 for the others): read by gathers
    lines: str | None = ""  # codegen.program_lines, made on first use ("": not yet)

    def kernel(self, mode: str, wrt: tuple[int, ...]) -> tuple[backend.Kernel, codegen.Layout]:
        """The kernel for ``mode`` and ``wrt``, and its buffers' layout: kept by this trace,
        else from the cache by the program's text (``codegen.program_text``: cheaper than
        writing the kernel), else written and compiled."""
        key = (mode, wrt)
        if key not in self.kernels:
            if self.lines == "":
                self.lines = codegen.program_lines(self.program)  # once for every mode
            program = codegen.program_text(self.program, mode, wrt, self.lines)
            kernel = None if program is None else backend.cached(program)
            if kernel is None:
                name = "kernel" if program is None else backend.kernel_name(program)
                text, layout = codegen.generate(self.program, mode, wrt, name)
                kernel = backend.compile_ir(text, program)
            else:
                layout = codegen.layout(self.program, mode, wrt)
            self.kernels[key] = (kernel, layout)
        return self.kernels[key]


class CompiledFunction:
    """A function of minidiff arrays, compiled per signature (see the module docstring)."""

    def __init__(self, function: Callable, shared=()):
        self.function = function
        self.signature = inspect.signature(function)
        unknown = set(shared) - set(self.signature.parameters)
        if unknown:
            raise ValueError(
                f"compile: shared names {sorted(unknown)} are not parameters of "
                f"{function.__name__}{self.signature}"
            )
        self.shared = frozenset(shared)
        # The parameters' names, when each can be given by position (no *args, **kwargs).
        kinds = {p.kind for p in self.signature.parameters.values()}
        plain = kinds <= {
            inspect.Parameter.POSITIONAL_ONLY,
            inspect.Parameter.POSITIONAL_OR_KEYWORD,
        }
        self._names = list(self.signature.parameters) if plain else None
        self._traces: OrderedDict = OrderedDict()
        self._lock = threading.Lock()
        functools.update_wrapper(self, function)

    # ----------------------------------------------------------------------------------------
    def __call__(self, *args, **kwargs):
        if _on_the_tape.get():
            return self.function(*args, **kwargs)
        names, values = self._bind(args, kwargs)
        arrays, trees, key = self._classify(names, values)
        if key[1] == 0:  # an empty batch: nothing to compile for; the tape gives its shapes
            return self.function(*args, **kwargs)
        trace = self._trace_for(key, arrays, trees)
        given = [value for value, _ in arrays]  # Tensors, or the NumPy arrays passed
        data = [_contiguous(v) for v in given]
        outputs = self._forward(trace, data)
        needs_tape = is_grad_enabled() and any(
            isinstance(v, Tensor) and (v.requires_grad or v.tangent is not None) for v in given
        )
        if not needs_tape:
            results = [Tensor(o) for o in outputs]
        else:
            tensors = [v if isinstance(v, Tensor) else Tensor(v) for v in given]
            results = self._on_tape(trace, tensors, data, outputs)
        return results[0] if trace.single else tuple(results)

    def add_vjp(self, cotangents, *args, **kwargs) -> None:
        """``backward`` of ``sum_j sum(cotangents[j] * output_j)`` through this function at
        these arguments, without recording the call: its gradient is added to ``.grad`` of
        every Tensor argument that requires grad, as ``backward`` would add it (in argument
        order; each must be a leaf). For a caller that already holds the outputs' values
        (from a call without the tape) and computes their cotangents from them: the path
        replay's windows. ``cotangents``: one array per output, of its shape (a single
        array for a function of one output)."""
        self._add_vjp(cotangents, args, kwargs, values=False)

    def value_and_add_vjp(self, cotangents, *args, **kwargs) -> np.ndarray | tuple:
        """``add_vjp``, and the outputs' values (NumPy arrays; one for a function of one
        output) from the same pass over the elements: the VJP computes them anyway. For a
        function that computes its own objective from its values (an output such as
        ``sum(detach(c) * y)``, whose cotangent is 1): the values for the caller's
        bookkeeping and the gradient in one call."""
        return self._add_vjp(cotangents, args, kwargs, values=True)

    def _add_vjp(self, cotangents, args, kwargs, values: bool) -> np.ndarray | tuple | None:
        """``add_vjp``; and with ``values``, the outputs' values returned."""
        names, bound = self._bind(args, kwargs)
        arrays, trees, key = self._classify(names, bound)
        given = [value for value, _ in arrays]
        floats = _floats([slot for _, slot in arrays])
        wrt = tuple(s for s in floats if isinstance(given[s], Tensor) and given[s].requires_grad)
        name = self.function.__name__ + (".value_and_add_vjp" if values else ".add_vjp")
        for s in wrt:
            if not given[s].is_leaf:
                raise ValueError(
                    f"{name}: argument {s} requires grad and is computed on the tape; "
                    "add_vjp adds to leaves only (call the function on the tape and use "
                    "backward)"
                )
        if key[1] == 0:  # an empty batch: zero gradients, as backward on the tape gives
            for s in wrt:
                _accumulate_leaf(given[s], np.zeros(given[s].shape, given[s].dtype))
            if values:  # the tape gives the shapes
                with no_grad():
                    results = self.function(*args, **kwargs)
                single = not isinstance(results, (tuple, list))
                results = [results] if single else results
                outputs = [np.asarray(r.data if isinstance(r, Tensor) else r) for r in results]
                return outputs[0] if single else tuple(outputs)
            return None
        trace = self._trace_for(key, arrays, trees)
        cotangents = [cotangents] if trace.single else list(cotangents)
        shapes = [(trace.batch, *shape) for shape in trace.output_shapes]
        if [np.shape(c) for c in cotangents] != shapes:
            raise ValueError(
                f"{name}: cotangents of shapes {[np.shape(c) for c in cotangents]}, the "
                f"outputs have {shapes}"
            )
        data = [_contiguous(v) for v in given]
        if not wrt:
            outputs = self._forward(trace, data) if values else None
        else:
            outputs = [] if values else None
            grads = self._vjp(trace, data, wrt, cotangents, outputs)
            anomaly = _anomaly_mode.get()
            for s in wrt:
                if anomaly and not np.isfinite(grads[s]).all():  # as backward checks then
                    raise FloatingPointError(
                        f"anomaly: the VJP of 'compiled {self.function.__name__}' produced "
                        f"NaN/inf in the gradient of an input of shape {given[s].shape}"
                    )
                _accumulate_leaf(given[s], grads[s].astype(given[s].dtype, copy=False))
        if outputs is None:
            return None
        return outputs[0] if trace.single else tuple(outputs)

    def trace(self, *args, **kwargs) -> codegen.Program:
        """The scalar program this function becomes for these arguments (for reading)."""
        names, values = self._bind(args, kwargs)
        arrays, trees, key = self._classify(names, values)
        return self._trace_for(key, arrays, trees).program

    def source(self, *args, mode: str = "forward", **kwargs) -> str:
        """The LLVM IR of the kernel for these arguments in ``mode`` ("forward", "vjp" with
        respect to every float argument, "jvp" likewise)."""
        names, values = self._bind(args, kwargs)
        arrays, trees, key = self._classify(names, values)
        trace = self._trace_for(key, arrays, trees)
        wrt = () if mode == "forward" else _floats(trace.program.slots)
        return codegen.generate(trace.program, mode, wrt)[0]

    # ----------------------------------------------------------------------------------------
    def _bind(self, args, kwargs):
        if not kwargs and self._names is not None and len(args) == len(self._names):
            return self._names, list(args)
        try:
            bound = self.signature.bind(*args, **kwargs)
        except TypeError as error:
            raise TypeError(f"{self.function.__name__}: {error}") from None
        bound.apply_defaults()
        return list(bound.arguments), list(bound.arguments.values())

    def _classify(self, names, values):
        """Array arguments as (Tensor, Slot), each argument's *tree* (``_Leaf``s of array
        arguments in tuples and lists, static values elsewhere), and the key of this
        call's signature."""
        arrays, batch = [], [None]
        trees = [
            self._tree(name, value, False, arrays, batch)
            for name, value in zip(names, values, strict=True)
        ]
        if batch[0] is None:
            raise ValueError(f"{self.function.__name__}: needs at least one batched array argument")
        key = tuple(zip(names, trees, strict=True))
        return arrays, trees, (key, batch[0])

    def _tree(self, name: str, value, inside: bool, arrays: list, batch: list) -> Any:
        """The tree of argument ``name``'s ``value`` (``inside`` a tuple or list), its
        arrays appended to ``arrays``. (A method, not a recursive closure: a closure that
        calls itself is a reference cycle, which would keep every call's arrays alive
        until the cyclic garbage collector runs.)"""
        if isinstance(value, (tuple, list)):  # arrays in containers: each its own slot
            parts = tuple([self._tree(name, v, True, arrays, batch) for v in value])
            return _Container(type(value), parts)
        if not isinstance(value, (Tensor, np.ndarray) if inside else _ARRAYS):
            try:
                hash(value)
            except TypeError:
                raise TypeError(
                    f"{self.function.__name__}: argument '{name}' holds a "
                    f"{type(value).__name__}, neither an array nor hashable; a static "
                    "argument must be hashable"
                ) from None
            return _Static(type(value), value)
        slot, t = self._slot(name, value, batch)
        arrays.append((t, slot))
        return _Leaf(len(arrays) - 1, slot)

    def _slot(self, name: str, value, batch: list) -> tuple[Slot, Tensor | np.ndarray]:
        """The slot of array argument ``name`` (in ``shared``, or batched: then its first
        axis must have the length ``batch[0]`` of the others, which it sets if unset), and
        the argument as a Tensor or NumPy array (a Tensor is made only for the tape)."""
        if isinstance(value, Tensor):
            array = value._data
        else:
            value = array = value if isinstance(value, np.ndarray) else np.asarray(value)
        dtype = array.dtype
        if dtype.kind == "f" and dtype != np.float64:
            raise TypeError(
                f"{self.function.__name__}: argument '{name}' is {dtype}; a compiled "
                "function takes float64 arrays (convert with .astype(np.float64))"
            )
        if dtype.kind not in "fiub":
            raise TypeError(f"{self.function.__name__}: argument '{name}' has dtype {dtype}")
        shape = array.shape
        batched = name not in self.shared
        if batched:
            if not shape:
                raise ValueError(
                    f"{self.function.__name__}: batched argument '{name}' is a 0-d "
                    "array; it needs a first (batch) axis, or name it in shared="
                )
            if batch[0] is not None and shape[0] != batch[0]:
                raise ValueError(
                    f"{self.function.__name__}: batched argument '{name}' has "
                    f"{shape[0]} elements, others {batch[0]}"
                )
            batch[0] = shape[0]
        return Slot(batched, shape[1:] if batched else shape, TYPES[dtype.kind]), value

    def _trace_for(self, key, arrays, trees) -> _Trace:
        """The trace for this signature: one for every batch length n, unless the function
        read n while traced (``ir.Graph.reads_batch``), then one per n."""
        signature, n = key
        with self._lock:
            trace = self._traces.get(signature) or self._traces.get(key)
            if trace is not None:
                self._traces.move_to_end(signature if signature in self._traces else key)
        if trace is None:
            trace = self._trace(arrays, trees)
            with self._lock:
                self._traces[key if trace.program.graph.reads_batch else signature] = trace
                while len(self._traces) > MAX_TRACES:
                    self._traces.popitem(last=False)
        return trace if trace.batch == n else dataclasses.replace(trace, batch=n)

    def _trace(self, arrays, trees) -> _Trace:
        graph = ir.Graph()
        slots = tuple(slot for _, slot in arrays)
        batch = next(t.shape[0] for t, slot in arrays if slot.batched)
        with graph.building():

            def rebuild(tree):
                if isinstance(tree, _Static):
                    return tree.value
                if isinstance(tree, _Leaf):
                    t, slot = arrays[tree.index]
                    return _argument(graph, tree.index, slot, t, batch)
                parts = [rebuild(part) for part in tree.parts]
                return tree.kind(*parts) if hasattr(tree.kind, "_fields") else tree.kind(parts)

            call_args = [rebuild(tree) for tree in trees]
            result = self.function(*call_args)
            single = not isinstance(result, (tuple, list))
            results = [result] if single else list(result)
            outputs, shapes = [], []
            for j, r in enumerate(results):
                r = traced(r)
                if r.dtype.kind != "f":
                    raise CompileError(
                        f"compile: output {j} of {self.function.__name__} is {r.dtype}; outputs "
                        "must be float (use md.where(condition, 1.0, 0.0) for a mask)"
                    )
                if r.batch is not None and r.batch != batch:
                    raise CompileError(f"compile: output {j} has batch {r.batch}, inputs {batch}")
                lanes = r.lanes
                outputs.append(tuple(v.id for v in lanes.ravel().tolist()))
                shapes.append(tuple(lanes.shape))
        program = codegen.Program(graph, slots, tuple(outputs))
        sizes = np.array([0 if s.batched or not s.shape else s.shape[0] for s in slots], np.int64)
        return _Trace(program, batch, tuple(shapes), single, {}, sizes)

    # ----------------------------------------------------------------------------------------
    def _run(self, trace: _Trace, mode: str, wrt, buffers: list[np.ndarray], batch=None,
             unit: int = 1) -> None:  # fmt: skip
        kernel, layout = trace.kernel(mode, wrt)
        if layout.sizes:  # the tables' lengths, which the kernel reads as it runs
            buffers = [*buffers, trace.sizes]
        pointers = _addresses(buffers)
        n = trace.batch if batch is None else batch
        chunks = -(-n // codegen.CHUNK)
        small = n * len(trace.program.graph.nodes) < PARALLEL_WORK
        threads = 1 if small else thread_count()
        status = kernel.run(pointers, n, chunks, threads, unit)
        if status:
            raise IndexError(
                f"{self.function.__name__}: element {status - 1} gathers a row out of range "
                "of a table argument"
            )

    def _forward(self, trace: _Trace, data) -> list[np.ndarray]:
        # Batch-sized outputs (here and in the VJP and JVP) come from minidiff's pool of
        # reused arrays (``minidiff.buffers``), as the tape's kernels' do: fresh memory is
        # faulted in by whichever thread writes it first, and NumPy asks the kernel for huge
        # pages for large arrays, whose faults can stall one thread for milliseconds while
        # the other waits (docs/compiler.md, "Threads and memory around the kernels").
        outputs = [memory.empty((trace.batch, *shape), np.float64) for shape in trace.output_shapes]
        self._run(trace, "forward", (), [*data, *outputs])
        return outputs

    def _vjp(self, trace: _Trace, data, wrt, cotangents, outputs=None) -> list[np.ndarray | None]:
        """Gradients of sum(cotangent * output) for the slots ``wrt``: one array per slot,
        None for the others. The element kernel, then the shared kernel on the batch's
        totals at the frontier (``codegen.Layout``), then the small tables' partial
        sums added group after group, and the large tables' scatter-adds.
        ``outputs``: a list to which the element kernel's values of the outputs are
        appended (its ``vjp_values`` form), or None."""
        mode = "vjp" if outputs is None else "vjp_values"
        _, layout = trace.kernel(mode, wrt)
        slots = trace.program.slots
        n, chunks = trace.batch, -(-trace.batch // codegen.CHUNK)
        # the kernel writes every element of these (codegen._reverse_elements): not zeroed
        grads = {s: memory.empty((n, *slots[s].shape), np.float64) for s in wrt if slots[s].batched}
        sums = np.zeros((chunks, max(1, len(layout.frontier))))
        blocks, contributions, rows = _gather_blocks(layout.gathers, slots, n)
        cotangents = [np.ascontiguousarray(g, dtype=np.float64) for g in cotangents]
        per_gather = [b for pair in zip(contributions, rows, strict=True) for b in pair]
        if outputs is not None:
            outputs += [memory.empty((n, *shape), np.float64) for shape in trace.output_shapes]
        # The partial tables' groups: at most PARTIAL_GROUPS, of ``unit`` chunks each (fixed
        # by n alone, so that each group's sums are the same whatever runs them).
        unit = -(-chunks // codegen.PARTIAL_GROUPS)
        groups = -(-chunks // unit)
        partials = [
            np.zeros((groups, slots[s].shape[0], _columns(slots[s]))) for s in layout.partials
        ]
        group = [np.array([unit], np.int64)] if partials else []
        buffers = [*data, *cotangents, *(outputs or ()), *grads.values(), sums, *per_gather,
                   *partials, *group]  # fmt: skip
        self._run(trace, mode, wrt, buffers, unit=unit)
        shared = {s: np.zeros(slots[s].shape) for s in wrt if not slots[s].batched}
        if shared and layout.frontier:
            totals = np.ascontiguousarray(sums.sum(axis=0))  # chunk by chunk, in order
            self._run(trace, "vjp_shared", wrt, [*data, totals, *shared.values()], batch=1)
        grads.update(shared)
        for slot, partial in zip(layout.partials, partials, strict=True):
            # Each table entry's groups added in group order (a sum along the first axis is
            # one row after the other, whatever the machine).
            grads[slot] += np.add.reduce(partial, axis=0).reshape(slots[slot].shape)
        for slot, (share, where) in blocks.items():
            table = grads[slot].reshape(slots[slot].shape[0], -1)  # a fresh array: ours
            _scatter(where, share, table)
        return [grads.get(s) for s in range(len(slots))]

    def _jvp(self, trace: _Trace, data, tangents) -> list[np.ndarray]:
        wrt = tuple(s for s, t in enumerate(tangents) if t is not None)
        outputs = [memory.empty((trace.batch, *shape), np.float64) for shape in trace.output_shapes]
        ts = [
            np.ascontiguousarray(np.broadcast_to(tangents[s], data[s].shape), dtype=np.float64)
            for s in wrt
        ]
        self._run(trace, "jvp", wrt, [*data, *ts, *outputs])
        return outputs

    def _on_tape(self, trace: _Trace, tensors, data, outputs) -> list[Tensor]:
        """The forward result as one tape node (outputs packed side by side, then split
        by views), with the compiled VJP and JVP."""
        n = trace.batch
        sizes = [int(np.prod(s)) for s in trace.output_shapes]
        packed = _side_by_side(outputs, n)
        floats = _floats(trace.program.slots)

        def vjp(g):
            cuts = np.cumsum(sizes)[:-1]
            cotangents = [
                c.reshape(n, *shape)
                for c, shape in zip(np.split(g, cuts, axis=1), trace.output_shapes, strict=True)
            ]
            wrt = tuple(s for s in floats if tensors[s].requires_grad)
            return tuple(self._vjp(trace, data, wrt, cotangents))

        def jvp(*tangents):
            ts = [t if s in floats else None for s, t in enumerate(tangents)]
            if all(t is None for t in ts):
                return None
            return _side_by_side(self._jvp(trace, data, ts), n)

        node = record(
            f"compiled {self.function.__name__}",
            packed,
            tuple(tensors),
            vjp,
            saves=tuple(tensors),
            jvp=jvp,
        )
        results, start = [], 0
        for size, shape in zip(sizes, trace.output_shapes, strict=True):
            piece = node[:, start : start + size] if len(sizes) > 1 else node
            results.append(piece.reshape((n, *shape)))
            start += size
        return results


def _gather_blocks(gathers, slots, n: int):
    """The VJP's buffers for its gathers' contributions: per table slot gathered, one block
    (contributions (g n, columns), rows (g n,)) for its g gathers, in their order, and each
    gather's (n, columns) and (n,) part of it. The table's gradient is then one scatter-add
    over the block, which adds gather after gather, each in element order: the order the
    gathers' own scatter-adds took one after the other, in one call instead of g."""
    count: dict[int, int] = {}
    for slot, _ in gathers:
        count[slot] = count.get(slot, 0) + 1
    # From the pool, as the outputs (``_forward``): the element kernel writes every row.
    blocks = {
        slot: (
            memory.empty((g * n, _columns(slots[slot])), np.float64),
            memory.empty((g * n,), np.int64),
        )
        for slot, g in count.items()
    }
    contributions, rows, used = [], [], dict.fromkeys(count, 0)
    for slot, _ in gathers:
        share, where = blocks[slot]
        k = used[slot]
        used[slot] += 1
        contributions.append(share[k * n : (k + 1) * n])
        rows.append(where[k * n : (k + 1) * n])
    return blocks, contributions, rows


def _addresses(buffers: list[np.ndarray]) -> ctypes.Array:
    """The arrays' data addresses, as the kernel's pointer argument. The caller keeps
    ``buffers`` alive for the call."""
    return (ctypes.c_void_p * len(buffers))(*(_address(b) for b in buffers))


def _address(array: np.ndarray) -> int:
    """The address of ``array``'s data: through a ctypes view of its buffer, or, where
    ctypes cannot view it (read-only, or empty), from ``__array_interface__``, whose
    dictionary takes four times as long to build (10 of a small call's 45 us: one per
    array). Not NumPy's ``.ctypes``: it makes objects in a reference cycle that hold the
    array, which then stays alive until the cyclic garbage collector runs."""
    try:
        return ctypes.addressof(ctypes.c_char.from_buffer(array))
    except (TypeError, ValueError):
        return array.__array_interface__["data"][0]


def _columns(slot: Slot) -> int:
    """The numbers in one row of a table slot."""
    return int(np.prod(slot.shape[1:], dtype=np.int64))


def _scatter(where: np.ndarray, share: np.ndarray, table: np.ndarray) -> None:
    """table (rows, columns) += the contributions ``share`` (k, columns) at rows ``where``
    (k,) int64, each row's in element order (``codegen.scatter_add``): on threads, each a
    range of the table's rows, where the rows come in blocks that mostly belong to one
    range (a gather by the hits' triangles of rays in triangle order: each thread then
    reads about its share of the contributions, and skips the other blocks); else on one
    thread (a thread must read every element's row of the blocks it cannot skip, and
    rows in random order mispredict its branch half the time). The same bits either way."""
    rows = len(table)
    blocks = -(-len(where) // codegen.SCATTER_BLOCK)
    n_jobs = min(thread_count(), rows) if len(where) >= PARALLEL_SCATTER else 1
    bounds = np.empty((blocks, 2), np.int64)
    sizes = np.array([rows, 0], np.int64)
    if n_jobs > 1:
        _row_bounds().run(_addresses([where, bounds, sizes]), len(where), blocks, n_jobs)
        # the blocks each job would read, with the rows split as ``Kernel.run`` splits them
        cuts = backend.job_bounds(rows, n_jobs)
        read = sum(
            np.count_nonzero((bounds[:, 1] >= low) & (bounds[:, 0] < high))
            for low, high in zip(cuts[:-1], cuts[1:], strict=True)
        )
        if read <= SCATTER_OVERLAP * blocks:
            sizes[1] = 1
        else:
            n_jobs = 1
    pointers = _addresses([where, share, table, sizes, bounds])
    _scatter_kernel(share.shape[1]).run(pointers, len(where), rows, n_jobs)


@functools.cache
def _row_bounds() -> backend.Kernel:
    """The kernel that finds each block's lowest and highest row (``codegen.row_bounds``)."""
    return backend.compile_ir(codegen.row_bounds())


@functools.cache
def _scatter_kernel(columns: int) -> backend.Kernel:
    """The serial kernel that adds gathered rows' gradients into their table, in element
    order (``codegen.scatter_add``), for tables of ``columns`` columns."""
    return backend.compile_ir(codegen.scatter_add(columns))


def _side_by_side(outputs: list[np.ndarray], n: int) -> np.ndarray:
    """The outputs (n, ...) each, as the columns of one (n, m) array (one output: itself,
    not copied)."""
    columns = [o.reshape(n, int(np.prod(o.shape[1:]))) for o in outputs]  # n may be 0
    return columns[0] if len(columns) == 1 else np.concatenate(columns, axis=1)


def _floats(slots) -> tuple[int, ...]:
    return tuple(s for s, slot in enumerate(slots) if slot.type == "f64")


def _contiguous(t: Tensor | np.ndarray) -> np.ndarray:
    data = t._data if isinstance(t, Tensor) else t
    if data.dtype.kind in "iu":
        return np.ascontiguousarray(data, dtype=np.int64)
    if data.dtype.kind == "b":
        return np.ascontiguousarray(data, dtype=np.uint8)
    return np.ascontiguousarray(data, dtype=np.float64)


def _argument(graph: ir.Graph, k: int, slot: Slot, t: Tensor, batch: int) -> Traced:
    """The traced array standing for argument ``k``."""
    dtype = DTYPES[slot.type]
    if not slot.batched:
        return Traced(None, None, dtype, slot=k, shape=slot.shape)
    size = int(np.prod(slot.shape))
    lanes = np.empty(size, dtype=object)
    lanes[:] = [graph.add("load", (), slot.type, (k, j)) for j in range(size)]
    return Traced(lanes.reshape(slot.shape), batch, dtype)


def compile(function: Callable | None = None, *, shared=()) -> Any:
    """Compile ``function`` (or, without it, a decorator that does): see the module
    docstring. ``shared`` names the arguments that are the same for every element."""
    if function is None:
        return lambda f: CompiledFunction(f, shared)
    return CompiledFunction(function, shared)
