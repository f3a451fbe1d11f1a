"""Code generation: a traced scalar program (``ir.Graph``) becomes an LLVM function that loops
over the elements of a batch, in one of three modes.

- ``forward``: each element's outputs from its inputs.
- ``vjp`` (reverse mode): each element's program, then the same program backwards: every
  differentiable line hands its gradient to its inputs through its slopes (``d -> d *
  dy/dx``, the primitive's own rule), summed in a fixed order. The gradient of a batched
  input is written per element; a shared input's is summed per *chunk* of elements into
  its own row of a buffer (the chunks' rows are added afterwards, always in the same order,
  so the result does not depend on how many threads ran the chunks); a table's, gathered
  at an index, is summed into a copy of the table per group of chunks when the table is
  small (``PARTIAL_LIMIT``), else written per element and added into the table's rows
  afterwards (``compiler.py``), again in a fixed order.
- ``vjp_values``: ``vjp`` that also writes each element's outputs: one pass for a caller
  whose cotangents the program computes itself from its values (an output such as
  ``sum(detach(c) * y)``) and that needs the values as well (the path replay's windows).
- ``jvp`` (forward mode): each element's program with a tangent beside every value, the
  slopes applied to the inputs' tangents.

The function's signature is the same in every mode::

    i64 kernel(ptr buffers, i64 n, i64 first_chunk, i64 end_chunk)

``buffers`` is an array of pointers, laid out by ``Layout``; the function runs the chunks
[first_chunk, end_chunk) of ``CHUNK`` elements each (the last may be short) and returns 0,
or 1 + the first element whose gather index was out of range. Everything is straight-line code
in one loop body; LLVM's optimiser removes what is computed twice and keeps values in
registers. Variables that live across elements (the loop counter, a chunk's sums) are
``alloca`` slots, which LLVM turns into registers.
"""

from __future__ import annotations

from dataclasses import dataclass

from minidiff import ir
from minidiff.trace import Slot

CHUNK = 1024  # elements per chunk: the unit of work of a thread, and of a shared gradient's sums
BLOCK = 64  # elements per block of a chunk, whose frontier gradients are summed after it
# A gathered table of at most this many numbers gets its gradient summed in the element
# kernel, into a *partial* table per group of consecutive chunks (at most PARTIAL_GROUPS
# groups: it stays in the cache, and the groups run in parallel); a larger one has each
# element's contribution written out and added by the scatter kernel (``scatter_add``).
# Measured: the path replay's windows (twelve gathers a path of the Cornell box's 48
# vertices, rows in random order) about 15 % faster summed in the kernel; the compiler
# benchmark's teapot (37k numbers, rows ascending) slower so (1M hits, 1 thread: 133
# against 104 ms), where the contributions' writes vectorise and the scatter reads them in
# order.
PARTIAL_LIMIT = 4096
PARTIAL_GROUPS = 16

_LLVM_TYPES = {"f64": "double", "i64": "i64", "i1": "i1"}
_LOAD_TYPES = {"f64": "double", "i64": "i64", "i1": "i8"}  # booleans are stored as bytes


@dataclass(frozen=True)
class Program:
    """What is compiled: the traced ``graph``, its argument ``slots``, and per output the
    ids of its lanes (row-major, one element's worth)."""

    graph: ir.Graph
    slots: tuple[Slot, ...]
    outputs: tuple[tuple[int, ...], ...]


@dataclass(frozen=True)
class Layout:
    """Where each buffer sits in the kernel's pointer array, for one mode.

    inputs: one per slot, in every mode. Then:

    - forward: one per output, (n, lanes).
    - vjp: the outputs' cotangents (n, lanes); (vjp_values: then one per output, (n,
      lanes), for its values); each differentiated batched slot's gradient
      (n, lanes); the *frontier* sums (chunks, len(frontier)); per gathered index of a
      large table, a contribution buffer (n, columns) and the row each element gathered
      (n,) int64 (``gathers`` lists (slot, index id) in order); per gathered table of at
      most ``PARTIAL_LIMIT`` numbers, its gradient per group of chunks (groups, table
      size) (``partials`` lists the slots), summed over the groups in order afterwards,
      then the chunks a group holds (1,) int64 (a job runs whole groups).
    - vjp_shared: the frontier totals (len(frontier),); each differentiated shared slot's
      gradient (its shape).
    - jvp: each differentiated slot's tangent (its own shape); one per output (n, lanes).

    Last, in every mode, where the program gathers: the slots' row counts (slots,) int64
    (``sizes``), which a kernel reads when it runs, so that one kernel serves a table of
    any length.

    The frontier is the shared values (those computed from shared arguments and constants
    only) that batched values read, or that are outputs: the tape computes them once and
    sums the gradients reaching them over the whole batch *before* going further back, so
    the compiled VJP does too: the element kernel stops there and sums (``vjp``), and a
    one-element kernel takes the totals back to the shared arguments (``vjp_shared``)."""

    mode: str
    wrt: tuple[int, ...]
    gathers: tuple[tuple[int, int], ...]
    frontier: tuple[int, ...]
    partials: tuple[int, ...] = ()
    sizes: bool = False  # whether the last pointer is the tables' row counts (``sizes``)


def shared_values(graph: ir.Graph) -> set[int]:
    """Ids of the lines computed from shared arguments and constants only."""
    shared = set()
    for vid, node in enumerate(graph.nodes):
        if node.op in ("const", "uniform") or (
            node.op not in ("load", "gather", "cot") and all(a in shared for a in node.args)
        ):
            shared.add(vid)
    return shared


def _frontier(program: Program, wrt) -> tuple[int, ...]:
    """The shared values where the element kernel's VJP stops (see ``Layout``)."""
    graph = program.graph
    shared = shared_values(graph)
    leaves = [v for v, node in enumerate(graph.nodes) if _is_leaf_of(node, wrt)]
    active = _depends_on(graph, leaves)
    # the lines a gradient reaches from the outputs (as on the tape: only those)
    reached = {v for lanes in program.outputs for v in lanes if v in active}
    frontier = {v for v in reached if v in shared}
    for vid in range(len(graph.nodes) - 1, -1, -1):
        node = graph.nodes[vid]
        if vid in reached and vid not in shared:
            for p, slope in zip(node.parents, node.slopes, strict=True):
                if slope is not None and p in active:
                    reached.add(p)
                    if p in shared:
                        frontier.add(p)
    return tuple(sorted(frontier))


def _names(mode: str, program: Program, wrt: tuple[int, ...]):
    """Pointer positions: inputs, then mode-specific buffers (see ``Layout``)."""
    position = {("in", s): s for s in range(len(program.slots))}
    k = len(program.slots)

    def add(key):
        nonlocal k
        position[key] = k
        k += 1

    frontier = _frontier(program, wrt) if mode in ("vjp", "vjp_values", "vjp_shared") else ()
    gathers: list[tuple[int, int]] = []
    partials: list[int] = []
    if mode == "forward":
        for o in range(len(program.outputs)):
            add(("out", o))
    elif mode in ("vjp", "vjp_values"):
        for o in range(len(program.outputs)):
            add(("cot", o))
        if mode == "vjp_values":
            for o in range(len(program.outputs)):
                add(("out", o))
        for s in wrt:
            if program.slots[s].batched:
                add(("grad", s))
        add(("frontier",))
        summed = summed_in_kernel(program, wrt)
        for node in program.graph.nodes:
            key = (node.attrs[0], node.args[0]) if node.op == "gather" else None
            if key and key[0] in wrt and key not in gathers and key[0] not in partials:
                if key[0] in summed:
                    partials.append(key[0])
                else:
                    gathers.append(key)
        for g in gathers:
            add(("contrib", g))
            add(("rows", g))
        for slot in partials:
            add(("partial", slot))
        if partials:
            add(("group",))
    elif mode == "vjp_shared":
        add(("frontier",))
        for s in wrt:
            if not program.slots[s].batched:
                add(("grad", s))
    elif mode == "jvp":
        for s in wrt:
            add(("tan", s))
        for o in range(len(program.outputs)):
            add(("out", o))
    else:
        raise ValueError(f"codegen: unknown mode {mode!r}")
    sizes = bool(gathered_slots(program.graph))
    if sizes:
        add(("sizes",))
    return position, Layout(mode, wrt, tuple(gathers), frontier, tuple(partials), sizes)


class _Emitter:
    """Writes one kernel's LLVM IR text."""

    def __init__(self, program: Program, graph: ir.Graph, position: dict):
        self.program, self.graph, self.position = program, graph, position
        self.entry: list[str] = []  # once per call: buffer pointers, shared loads
        self.body: list[str] = []  # once per element: the values
        self.tail: list[str] = []  # once per element, after the values: the stores
        self.chunk_start: list[str] = []
        self.chunk_end: list[str] = []
        self.sums_allocas: list[str] = []  # a chunk's running sum per frontier value (vjp)
        self.inside: list[str] = []  # per gather, whether its row was in range
        self.reduce: list[str] = []  # per element of a block: add its scratch row (vjp)
        self.frontier_count = 0
        self.grouped = False  # whether the chunk's group of partial tables is computed
        self.sized: set[int] = set()  # the slots whose row count is read (``rows_of``)
        self.temp = 0
        self.emitted: set[int] = set()

    def fresh(self) -> str:
        self.temp += 1
        return f"%t{self.temp}"

    def pointer(self, key) -> str:
        return f"%b{self.position[key]}"

    def name(self, vid: int) -> str:
        node = self.graph.nodes[vid]
        if node.op == "const":
            return ir.llvm_constant(node.attrs[0], node.type)
        return f"%v{vid}"

    def element_address(
        self, lines, base: str, stride: int, offset: int, index: str, type_: str
    ) -> str:
        """The address of ``base[index * stride + offset]`` (a ``type_`` array)."""
        flat = index
        if stride != 1:
            flat = self.fresh()
            lines.append(f"  {flat} = mul i64 {index}, {stride}")
        if offset:
            moved = self.fresh()
            lines.append(f"  {moved} = add i64 {flat}, {offset}")
            flat = moved
        address = self.fresh()
        lines.append(f"  {address} = getelementptr {type_}, ptr {base}, i64 {flat}")
        return address

    def load(self, lines, target: str, address: str, type_: str) -> None:
        if type_ == "i1":
            byte = self.fresh()
            lines.append(f"  {byte} = load i8, ptr {address}")
            lines.append(f"  {target} = icmp ne i8 {byte}, 0")
        else:
            lines.append(f"  {target} = load {_LLVM_TYPES[type_]}, ptr {address}")

    def emit(self, vid: int) -> None:
        """Mark line ``vid`` and the lines it reads as needed; needed lines are written in
        the program's order (``text``), before the stores."""
        stack = [vid]
        while stack:  # iterative: programs can be thousands of lines deep
            top = stack.pop()
            if top not in self.emitted:
                self.emitted.add(top)
                stack.extend(self.graph.nodes[top].args)

    def _emit_one(self, vid: int) -> None:
        node = self.graph.nodes[vid]
        op, target = node.op, f"%v{vid}"
        args = [self.name(a) for a in node.args]
        if op == "const":
            return
        if op in ("load", "tload"):  # lane of a batched slot, or of its tangent
            slot, lane = node.attrs
            lanes = max(1, _size(self.program.slots[slot].shape))
            base = self.pointer(("in", slot) if op == "load" else ("tan", slot))
            address = self.element_address(
                self.body, base, lanes, lane, "%i", _LOAD_TYPES[node.type]
            )
            self.load(self.body, target, address, node.type)
        elif op in ("uniform", "tuniform"):  # element of a shared slot: read once per call
            slot, j = node.attrs
            base = self.pointer(("in", slot) if op == "uniform" else ("tan", slot))
            address = self.fresh()
            self.entry.append(
                f"  {address} = getelementptr {_LOAD_TYPES[node.type]}, ptr {base}, i64 {j}"
            )
            self.load(self.entry, target, address, node.type)
        elif op in ("gather", "tgather"):
            slot, column, columns = node.attrs
            base = self.pointer(("in", slot) if op == "gather" else ("tan", slot))
            row = self.checked_row(args[0], self.rows_of(slot))
            address = self.element_address(
                self.body, base, columns, column, row, _LOAD_TYPES[node.type]
            )
            self.load(self.body, target, address, node.type)
        elif op == "total":  # a frontier value's gradient, summed over the batch (vjp_shared)
            address, base = self.fresh(), self.pointer(("frontier",))
            self.body.append(f"  {address} = getelementptr double, ptr {base}, i64 {node.attrs[0]}")
            self.body.append(f"  {target} = load double, ptr {address}")
        elif op == "cot":  # an output's cotangent (vjp)
            output, lane = node.attrs
            lanes = len(self.program.outputs[output])
            address = self.element_address(
                self.body, self.pointer(("cot", output)), lanes, lane, "%i", "double"
            )
            self.body.append(f"  {target} = load double, ptr {address}")
        elif op in ir.FLOAT_COMPARISONS:
            kind = self.graph.nodes[node.args[0]].type
            if kind == "f64":
                self.body.append(
                    f"  {target} = fcmp {ir.FLOAT_COMPARISONS[op]} double {args[0]}, {args[1]}"
                )
            else:
                compare = ir.INT_COMPARISONS[op]
                self.body.append(f"  {target} = icmp {compare} i64 {args[0]}, {args[1]}")
        elif op == "select":
            t = _LLVM_TYPES[node.type]
            self.body.append(f"  {target} = select i1 {args[0]}, {t} {args[1]}, {t} {args[2]}")
        elif op == "tofloat":
            kind = self.graph.nodes[node.args[0]].type
            cast = "uitofp i1" if kind == "i1" else "sitofp i64"
            self.body.append(f"  {target} = {cast} {args[0]} to double")
        else:
            self.body.append(f"  {target} = " + ir.INSTRUCTIONS[op].format(*args))

    def rows_of(self, slot: int) -> str:
        """The name of table ``slot``'s row count, read once per call from the ``sizes``
        buffer: not a constant of the kernel, which then serves a table of any length."""
        name = f"%rows{slot}"
        if slot not in self.sized:
            self.sized.add(slot)
            address = self.fresh()
            self.entry += [
                f"  {address} = getelementptr i64, ptr {self.pointer(('sizes',))}, i64 {slot}",
                f"  {name} = load i64, ptr {address}",
            ]
        return name

    def checked_row(self, row: str, rows: str) -> str:
        """A gather's row: negative counts from the end. Out of range, row 0 is read instead
        and the element is remembered (the kernel returns the first such one): no branch,
        so that LLVM may vectorise the loop."""
        safe, inside = self.safe_row(self.body, row, rows)
        self.inside.append(inside)
        return safe

    def safe_row(self, lines: list[str], row: str, rows: str) -> tuple[str, str]:
        """Appended to ``lines``: ``row`` of a table of ``rows`` rows counted from the end
        where negative, row 0 where out of range; returns its name and the name of the
        flag saying whether it was in range."""
        negative, shifted, wrapped = self.fresh(), self.fresh(), self.fresh()
        inside, safe = self.fresh(), self.fresh()
        lines += [
            f"  {negative} = icmp slt i64 {row}, 0",
            f"  {shifted} = add i64 {row}, {rows}",
            f"  {wrapped} = select i1 {negative}, i64 {shifted}, i64 {row}",
            f"  {inside} = icmp ult i64 {wrapped}, {rows}",
            f"  {safe} = select i1 {inside}, i64 {wrapped}, i64 0",
        ]
        return safe, inside

    def accumulate(self, f: int, count: int, value: str) -> None:
        """Add ``value`` to this chunk's sum number ``f`` (of ``count``), written to the
        frontier buffer's row for the chunk when the chunk ends.

        The element loop only stores the value in a scratch row (no dependence from one
        element to the next, so LLVM can vectorise it); a second loop after each block of
        ``BLOCK`` elements adds the rows into the sums in element order."""
        total = f"%sum{f}"
        self.sums_allocas.append(f"  {total} = alloca double")
        self.chunk_start.append(f"  store double 0.0, ptr {total}")
        self.frontier_count = count
        address = self.element_address(self.tail, "%scratch", count, f, "%i.block", "double")
        self.tail.append(f"  store double {value}, ptr {address}")
        piece, old, new = self.fresh(), self.fresh(), self.fresh()
        address = self.element_address(self.reduce, "%scratch", count, f, "%j.block", "double")
        self.reduce += [
            f"  {piece} = load double, ptr {address}",
            f"  {old} = load double, ptr {total}",
            f"  {new} = fadd double {old}, {piece}",
            f"  store double {new}, ptr {total}",
        ]
        final = self.fresh()
        self.chunk_end.append(f"  {final} = load double, ptr {total}")
        base = self.pointer(("frontier",))
        address = self.element_address(self.chunk_end, base, count, f, "%c", "double")
        self.chunk_end.append(f"  store double {final}, ptr {address}")

    def add_to_partial(self, slot: int, index: str, columns: int, values) -> None:
        """Add ``values`` (one per column, None: no gradient) to the row ``index`` of this
        chunk's group's partial table of ``slot`` (its rows counted from the end where
        negative, as the gather read it; row 0 where out of range, as the gather read too,
        the kernel then failing)."""
        if not self.grouped:  # the chunk's group, once per chunk
            self.grouped = True
            self.entry.append(f"  %group.size = load i64, ptr {self.pointer(('group',))}")
            self.chunk_start.append("  %group = udiv i64 %c, %group.size")
        rows = self.rows_of(slot)
        lines = self.tail
        safe, _ = self.safe_row(lines, index, rows)  # as the gather read it
        size, base, offset, at = self.fresh(), self.fresh(), self.fresh(), self.fresh()
        lines += [
            f"  {size} = mul i64 {rows}, {columns}",
            f"  {base} = mul i64 %group, {size}",
            f"  {offset} = mul i64 {safe}, {columns}",
            f"  {at} = add i64 {base}, {offset}",
        ]
        for column, value in enumerate(values):
            if value is None:
                continue
            self.emit(value.id)
            address = self.element_address(lines, self.pointer(("partial", slot)), 1, column,
                                           at, "double")  # fmt: skip
            old, new = self.fresh(), self.fresh()
            lines += [
                f"  {old} = load double, ptr {address}",
                f"  {new} = fadd double {old}, {self.name(value.id)}",
                f"  store double {new}, ptr {address}",
            ]

    def value_or_zero(self, d: ir.Value | None) -> str:
        """The name of ``d``, marked as needed; "0.0" for None (no gradient reaches)."""
        if d is None:
            return "0.0"
        self.emit(d.id)
        return self.name(d.id)

    def store(self, key, lanes: int, lane: int, value: str) -> None:
        address = self.element_address(self.tail, self.pointer(key), lanes, lane, "%i", "double")
        self.tail.append(f"  store double {value}, ptr {address}")

    def text(self, n_pointers: int, name: str = "kernel") -> str:
        for vid in sorted(self.emitted):
            self._emit_one(vid)
        checks = []
        if self.inside:  # remember the first element with a row out of range
            all_inside = self.inside[0]
            for flag in self.inside[1:]:
                both = self.fresh()
                checks.append(f"  {both} = and i1 {all_inside}, {flag}")
                all_inside = both
            checks += [  # a min-reduction, which LLVM can vectorise
                f"  %bad.here = select i1 {all_inside}, i64 %n, i64 %i",
                "  %bad.old = load i64, ptr %bad.slot",
                "  %bad.new = call i64 @llvm.smin.i64(i64 %bad.old, i64 %bad.here)",
                "  store i64 %bad.new, ptr %bad.slot",
            ]
        # The work is a function of the buffers as separate ``noalias`` pointers (each
        # buffer is its own array: what the kernel writes, nothing else reads), which lets
        # LLVM keep values in registers across stores; ``kernel`` unpacks the array of
        # pointers and calls it (inlined).
        pointers, arguments = [], []
        for k in range(n_pointers):
            pointers.append(f"  %p{k} = getelementptr ptr, ptr %buffers, i64 {k}")
            pointers.append(f"  %b{k} = load ptr, ptr %p{k}")
            arguments.append(f"ptr noalias %b{k}")
        scalars = ["i64 %n", "i64 %first", "i64 %end"]
        call = ", ".join([f"ptr %b{k}" for k in range(n_pointers)] + scalars)
        return "\n".join(
            [
                f"define i64 @{name}(ptr %buffers, i64 %n, i64 %first, i64 %end) {{",
                "entry:",
                *pointers,
                f"  %result = call i64 @work({call})",
                "  ret i64 %result",
                "}",
                f"define internal i64 @work({', '.join([*arguments, *scalars])}) {{",
                "entry:",
                "  %chunk.slot = alloca i64",
                "  %i.slot = alloca i64",
                "  %bad.slot = alloca i64",
                "  store i64 %n, ptr %bad.slot",
                *self.sums_allocas,
                f"  %scratch = alloca double, i64 {max(1, BLOCK * self.frontier_count)}",
                "  %block.slot = alloca i64",
                "  %j.slot = alloca i64",
                *self.entry,
                "  store i64 %first, ptr %chunk.slot",
                "  br label %chunk.head",
                "chunk.head:",
                "  %c = load i64, ptr %chunk.slot",
                "  %more.chunks = icmp slt i64 %c, %end",
                "  br i1 %more.chunks, label %chunk.body, label %done",
                "chunk.body:",
                f"  %start = mul i64 %c, {CHUNK}",
                f"  %stop.full = add i64 %start, {CHUNK}",
                "  %short = icmp slt i64 %n, %stop.full",
                "  %stop = select i1 %short, i64 %n, i64 %stop.full",
                *self.chunk_start,
                "  store i64 %start, ptr %block.slot",
                "  br label %block.head",
                "block.head:",
                "  %block = load i64, ptr %block.slot",
                "  %more.blocks = icmp slt i64 %block, %stop",
                "  br i1 %more.blocks, label %block.body, label %chunk.tail",
                "block.body:",
                f"  %block.end.full = add i64 %block, {BLOCK}",
                "  %block.short = icmp slt i64 %stop, %block.end.full",
                "  %block.end = select i1 %block.short, i64 %stop, i64 %block.end.full",
                "  store i64 %block, ptr %i.slot",
                "  br label %element.head",
                "element.head:",
                "  %i = load i64, ptr %i.slot",
                "  %more = icmp slt i64 %i, %block.end",
                "  br i1 %more, label %element.body, label %reduce.start",
                "element.body:",
                "  %i.block = sub i64 %i, %block",
                *self.body,
                *self.tail,
                *checks,
                "  %i.next = add i64 %i, 1",
                "  store i64 %i.next, ptr %i.slot",
                "  br label %element.head",
                "reduce.start:",
                "  store i64 %block, ptr %j.slot",
                "  br label %reduce.head",
                "reduce.head:",
                "  %j = load i64, ptr %j.slot",
                "  %more.j = icmp slt i64 %j, %block.end",
                "  br i1 %more.j, label %reduce.body, label %block.next",
                "reduce.body:",
                "  %j.block = sub i64 %j, %block",
                *self.reduce,
                "  %j.next = add i64 %j, 1",
                "  store i64 %j.next, ptr %j.slot",
                "  br label %reduce.head",
                "block.next:",
                "  store i64 %block.end, ptr %block.slot",
                "  br label %block.head",
                "chunk.tail:",
                *self.chunk_end,
                "  %c.next = add i64 %c, 1",
                "  store i64 %c.next, ptr %chunk.slot",
                "  br label %chunk.head",
                "done:",
                "  %bad = load i64, ptr %bad.slot",
                "  %any.bad = icmp slt i64 %bad, %n",
                "  %bad.code = add i64 %bad, 1",
                "  %code = select i1 %any.bad, i64 %bad.code, i64 0",
                "  ret i64 %code",
                "}",
                ir.DECLARATIONS,
            ]
        )


def _size(shape) -> int:
    total = 1
    for s in shape:
        total *= s
    return total


def _depends_on(graph: ir.Graph, leaves) -> set[int]:
    """Ids of the differentiable lines whose value depends on a line in ``leaves``."""
    active = set(leaves)
    for vid, node in enumerate(graph.nodes):
        if node.parents and any(p in active for p in node.parents):
            active.add(vid)
    return active


def _is_leaf_of(node: ir.Node, wrt) -> bool:
    return node.op in ("load", "uniform", "gather") and node.attrs[0] in wrt and node.type == "f64"


def layout(program: Program, mode: str, wrt: tuple[int, ...] = ()) -> Layout:
    """The buffers' layout of ``program``'s kernel in ``mode``, as ``generate`` gives it
    (without writing the kernel: for a kernel fetched from the cache by ``program_text``)."""
    return _names(mode, program, wrt)[1]


def program_text(program: Program, mode: str, wrt: tuple[int, ...] = (), lines=None) -> str | None:
    """A text that determines the kernel ``generate`` writes for ``program`` in ``mode``
    (with minidiff's own source, which the cache key adds: ``backend._source``): the mode,
    then ``program_lines`` (given as ``lines`` if already made). Cheaper than the kernel's
    text, so that a kernel already on disk is found without writing it. None when a line's
    derivative rule comes from outside minidiff: such a kernel is keyed by its IR text."""
    lines = program_lines(program) if lines is None else lines
    if lines is None:
        return None
    if mode in ("vjp", "vjp_values"):  # which tables' gradients are summed in the kernel
        return f"{mode} {wrt} {sorted(summed_in_kernel(program, wrt))}\n{lines}"
    return f"{mode} {wrt}\n{lines}"


def program_lines(program: Program) -> str | None:
    """``program`` as text: the slots, the outputs, and every line (op, arguments, type,
    attributes, its parents and the scalar form each one's derivative rule comes from);
    None when a rule comes from outside minidiff (a scalar form written elsewhere, whose
    edits minidiff's source would not show)."""
    lines = [f"{_slots_text(program)} {program.outputs}"]
    for node in program.graph.nodes:
        rules = []  # which scalar form's rule each parent takes
        for slope in node.slopes:
            if slope is not None and not slope.__module__.startswith("minidiff."):
                return None
            rules.append("-" if slope is None else slope.__qualname__)
        lines.append(f"{node.op} {node.args} {node.type} {node.attrs!r} {node.parents} {rules}")
    return "\n".join(lines)


def gathered_slots(graph: ir.Graph) -> set[int]:
    """The slots that ``graph`` gathers rows of."""
    return {node.attrs[0] for node in graph.nodes if node.op == "gather"}


def summed_in_kernel(program: Program, wrt: tuple[int, ...]) -> set[int]:
    """The gathered tables among the slots ``wrt`` whose gradient the VJP's element kernel
    sums into partial tables: those of at most ``PARTIAL_LIMIT`` numbers (``Layout``)."""
    gathered = gathered_slots(program.graph) & set(wrt)
    return {s for s in gathered if _size(program.slots[s].shape) <= PARTIAL_LIMIT}


def _slots_text(program: Program) -> str:
    """The slots as the kernels see them: a table read only by gathers has its row count
    read when the kernel runs (``_Emitter.rows_of``), so its length is left out: one kernel
    for every length (``program_text`` adds what else the length decides: which tables'
    gradients are summed in the VJP's kernel, ``PARTIAL_LIMIT``)."""
    graph = program.graph
    free = gathered_slots(graph) - {n.attrs[0] for n in graph.nodes if n.op == "uniform"}
    return repr(tuple(
        (s.batched, ("rows", *s.shape[1:]), s.type) if k in free else s
        for k, s in enumerate(program.slots)
    ))  # fmt: skip


def generate(
    program: Program, mode: str, wrt: tuple[int, ...] = (), name: str = "kernel"
) -> tuple[str, Layout]:
    """The LLVM IR text of ``program``'s kernel in ``mode`` ("forward", "vjp",
    "vjp_values", "vjp_shared", "jvp") with derivatives for the slots ``wrt``, and its
    buffers' layout. ``name``: the kernel function's (``backend.kernel_name``)."""
    position, layout = _names(mode, program, wrt)
    graph = program.graph.extended()
    emitter = _Emitter(program, graph, position)
    with graph.building():
        if mode in ("forward", "vjp_values"):
            for o, lanes in enumerate(program.outputs):
                for lane, vid in enumerate(lanes):
                    emitter.emit(vid)
                    emitter.store(("out", o), len(lanes), lane, emitter.name(vid))
        if mode in ("vjp", "vjp_values"):
            _reverse_elements(program, graph, emitter, wrt, layout)
        elif mode == "vjp_shared":
            _reverse_shared(program, graph, emitter, wrt, layout)
        elif mode == "jvp":
            _tangents(program, graph, emitter, wrt)
    return emitter.text(len(position), name), layout


def _sweep(graph: ir.Graph, adjoint: dict, lines, active: set[int]) -> None:
    """Reverse sweep over ``lines`` (descending): each line with a gradient gives its
    parents ``slope(gradient)``, added in this fixed order."""
    for vid in lines:
        node = graph.nodes[vid]
        if vid not in adjoint or not node.parents:
            continue
        d = adjoint[vid]
        for parent, slope in zip(node.parents, node.slopes, strict=True):
            if slope is not None and parent in active:
                _give(adjoint, parent, slope(d))


def _give(adjoint: dict, vid: int, d: ir.Value) -> None:
    adjoint[vid] = d if vid not in adjoint else adjoint[vid] + d


def _reverse_elements(program: Program, graph: ir.Graph, emitter: _Emitter, wrt, layout) -> None:
    """The element kernel of the VJP: the outputs' cotangents pushed back line by line
    through the slopes, down to the batched arguments, the gathers, and the frontier."""
    traced = len(program.graph.nodes)
    shared = shared_values(program.graph)
    leaves = [v for v in range(traced) if _is_leaf_of(graph.nodes[v], wrt)]
    active = _depends_on(graph, leaves)
    adjoint: dict[int, ir.Value] = {}
    for o, lanes in enumerate(program.outputs):
        for lane, vid in enumerate(lanes):
            if vid in active:
                _give(adjoint, vid, graph.add("cot", (), "f64", (o, lane)))
    batched_lines = [v for v in range(traced - 1, -1, -1) if v not in shared]
    _sweep(graph, adjoint, batched_lines, active)
    # Every element writes every lane of its gradient buffers (0.0 where no gradient
    # reaches), so that they need not be zeroed first. A table row gathered twice at the
    # same index by one element gets both gradients.
    gathered: dict[tuple, ir.Value] = {}
    columns_of: dict[tuple, int] = {}
    for vid in leaves:
        node = graph.nodes[vid]
        if node.op == "gather":
            slot, column, columns = node.attrs
            columns_of[slot, node.args[0]] = columns
            if vid in adjoint:
                _give(gathered, (slot, node.args[0], column), adjoint[vid])
    for (slot, index), columns in columns_of.items():
        if slot in layout.partials:
            emitter.emit(index)
            sums = [gathered.get((slot, index, column)) for column in range(columns)]
            emitter.add_to_partial(slot, emitter.name(index), columns, sums)
            continue
        for column in range(columns):
            value = emitter.value_or_zero(gathered.get((slot, index, column)))
            emitter.store(("contrib", (slot, index)), columns, column, value)
        emitter.emit(index)  # the row it was gathered from, as given
        address = emitter.element_address(
            emitter.tail, emitter.pointer(("rows", (slot, index))), 1, 0, "%i", "i64"
        )
        emitter.tail.append(f"  store i64 {emitter.name(index)}, ptr {address}")
    loaded = {  # (slot, lane) of a batched argument: its gradient
        graph.nodes[v].attrs: adjoint[v]
        for v in leaves
        if graph.nodes[v].op == "load" and v in adjoint
    }
    for slot in wrt:
        if program.slots[slot].batched:
            lanes = max(1, _size(program.slots[slot].shape))
            for lane in range(lanes):
                value = emitter.value_or_zero(loaded.get((slot, lane)))
                emitter.store(("grad", slot), lanes, lane, value)
    for f, vid in enumerate(layout.frontier):  # this chunk's sum of each frontier gradient
        if vid in adjoint:
            emitter.emit(adjoint[vid].id)
            emitter.accumulate(f, len(layout.frontier), emitter.name(adjoint[vid].id))


def _reverse_shared(program: Program, graph: ir.Graph, emitter: _Emitter, wrt, layout) -> None:
    """The one-element kernel of the VJP: the frontier's totals pushed back through the
    shared lines to the shared arguments."""
    shared = shared_values(program.graph)
    leaves = [v for v in sorted(shared) if _is_leaf_of(graph.nodes[v], wrt)]
    active = _depends_on(graph, leaves)
    adjoint: dict[int, ir.Value] = {}
    for f, vid in enumerate(layout.frontier):
        _give(adjoint, vid, graph.add("total", (), "f64", (f,)))
    _sweep(graph, adjoint, sorted(shared, reverse=True), active)
    for vid in leaves:
        if vid in adjoint:
            slot, j = graph.nodes[vid].attrs
            emitter.emit(adjoint[vid].id)
            size = _size(program.slots[slot].shape)
            emitter.store(("grad", slot), size, j, emitter.name(adjoint[vid].id))


def _tangents(program: Program, graph: ir.Graph, emitter: _Emitter, wrt) -> None:
    """The JVP: a tangent beside each value, from the inputs' tangents through the slopes."""
    traced = len(program.graph.nodes)
    tangent: dict[int, ir.Value] = {}
    for vid in range(traced):
        node = graph.nodes[vid]
        if _is_leaf_of(node, wrt):
            op = "t" + node.op
            args = tuple(ir.Value(a, graph.nodes[a].type) for a in node.args)
            tangent[vid] = graph.add(op, args, "f64", node.attrs)
        elif node.parents:
            terms = [
                slope(tangent[p])
                for p, slope in zip(node.parents, node.slopes, strict=True)
                if slope is not None and p in tangent
            ]
            if terms:
                total = terms[0]
                for t in terms[1:]:
                    total = total + t
                tangent[vid] = total
    for o, lanes in enumerate(program.outputs):
        for lane, vid in enumerate(lanes):
            if vid in tangent:
                emitter.emit(tangent[vid].id)
                value = emitter.name(tangent[vid].id)
            else:
                value = "0.0"
            emitter.store(("out", o), len(lanes), lane, value)


#: Elements per block of a scatter-add's rows: the unit whose lowest and highest row
#: (``row_bounds``) let a thread skip the blocks that hold none of its rows.
SCATTER_BLOCK = 4096


def _row_of(name: str, index: str) -> list[str]:
    """IR: ``%name``, the row of element ``index`` of ``%rows``, a negative one counted from
    the end (``%count`` rows)."""
    return [
        f"  %{name}.ptr = getelementptr i64, ptr %rows, i64 {index}",
        f"  %{name}.given = load i64, ptr %{name}.ptr",
        f"  %{name}.negative = icmp slt i64 %{name}.given, 0",
        f"  %{name}.shifted = add i64 %{name}.given, %count",
        f"  %{name} = select i1 %{name}.negative, i64 %{name}.shifted, i64 %{name}.given",
    ]


def _buffer(k: int, name: str, kind: str = "ptr") -> list[str]:
    """IR: ``%name``, entry ``k`` of the pointer array ``%buffers`` (loaded as ``kind``)."""
    return [
        f"  %{name}.at = getelementptr ptr, ptr %buffers, i64 {k}",
        f"  %{name} = load {kind}, ptr %{name}.at",
    ]


def row_bounds(block: int = SCATTER_BLOCK) -> str:
    """The kernel that finds each block's lowest and highest row for ``scatter_add``:
    buffers (rows (n,) int64, bounds (blocks, 2) int64 written, sizes (2,) int64 whose first
    entry is the table's row count); its "chunks" are the blocks of ``block`` elements."""
    return "\n".join(
        [
            "define i64 @kernel(ptr %buffers, i64 %n, i64 %first, i64 %end) {",
            "entry:",
            *_buffer(0, "rows"),
            *_buffer(1, "bounds"),
            *_buffer(2, "sizes"),
            "  %count = load i64, ptr %sizes",
            "  %b.slot = alloca i64",
            "  %i.slot = alloca i64",
            "  %lo.slot = alloca i64",
            "  %hi.slot = alloca i64",
            "  store i64 %first, ptr %b.slot",
            "  br label %block",
            "block:",
            "  %b = load i64, ptr %b.slot",
            "  %more = icmp slt i64 %b, %end",
            "  br i1 %more, label %start, label %done",
            "start:",
            f"  %i.first = mul i64 %b, {block}",
            f"  %i.past = add i64 %i.first, {block}",
            "  %short = icmp slt i64 %n, %i.past",
            "  %stop = select i1 %short, i64 %n, i64 %i.past",
            "  store i64 %i.first, ptr %i.slot",
            "  store i64 9223372036854775807, ptr %lo.slot",
            "  store i64 -9223372036854775808, ptr %hi.slot",
            "  br label %head",
            "head:",
            "  %i = load i64, ptr %i.slot",
            "  %inside = icmp slt i64 %i, %stop",
            "  br i1 %inside, label %body, label %store",
            "body:",
            *_row_of("r", "%i"),
            "  %lo = load i64, ptr %lo.slot",
            "  %hi = load i64, ptr %hi.slot",
            "  %lower = icmp slt i64 %r, %lo",
            "  %higher = icmp sgt i64 %r, %hi",
            "  %lo.new = select i1 %lower, i64 %r, i64 %lo",
            "  %hi.new = select i1 %higher, i64 %r, i64 %hi",
            "  store i64 %lo.new, ptr %lo.slot",
            "  store i64 %hi.new, ptr %hi.slot",
            "  %i.next = add i64 %i, 1",
            "  store i64 %i.next, ptr %i.slot",
            "  br label %head",
            "store:",
            "  %lo.end = load i64, ptr %lo.slot",
            "  %hi.end = load i64, ptr %hi.slot",
            "  %at = mul i64 %b, 2",
            "  %lo.ptr = getelementptr i64, ptr %bounds, i64 %at",
            "  %hi.ptr = getelementptr i64, ptr %lo.ptr, i64 1",
            "  store i64 %lo.end, ptr %lo.ptr",
            "  store i64 %hi.end, ptr %hi.ptr",
            "  %b.next = add i64 %b, 1",
            "  store i64 %b.next, ptr %b.slot",
            "  br label %block",
            "done:",
            "  ret i64 0",
            "}",
        ]
    )


def scatter_add(columns: int, block: int = SCATTER_BLOCK) -> str:
    """The kernel that adds a gather's contributions into its table's gradient: buffers
    (rows (n,) int64, contributions (n, columns), gradient (table rows, columns), sizes (2,)
    int64: the table's row count and whether ``bounds`` is filled, bounds (blocks, 2) int64:
    each block's lowest and highest row, ``row_bounds``); a negative row counts from the
    end, as the gather read it.

    A call adds the contributions to the table rows [first, end) (its "chunks" are the
    table's rows): each call reads the elements' rows in element order and takes its own,
    skipping (where ``bounds`` is filled) the blocks of ``block`` elements (a power of two)
    whose rows all lie elsewhere. So threads given different row ranges never write the
    same row, and each row's sum is made in element order whatever the split: the same
    bits on any thread count.

    A run of consecutive elements on one row (the hits on one triangle gather its corners
    one after the other) is summed in registers, starting from the row's value, and stored
    once at its end: the same additions in the same order as a load, add and store per
    element, without each addition waiting for the store before it (1M hits of the
    compiler benchmark's teapot, three corners each, the kernel alone on one thread: 11.8
    ms before, 6.4-6.9 ms so)."""
    run_start, run_step, flush = [], [], []
    for c in range(columns):
        run_start += [
            f"  %at{c} = add i64 %from, {c}",
            f"  %to{c} = add i64 %base, {c}",
            f"  %src{c} = getelementptr double, ptr %contrib, i64 %at{c}",
            f"  %dst{c} = getelementptr double, ptr %grad, i64 %to{c}",
            f"  %x{c} = load double, ptr %src{c}",
            f"  %old{c} = load double, ptr %dst{c}",
            f"  %first{c} = fadd double %old{c}, %x{c}",
            f"  store double %first{c}, ptr %acc{c}",
        ]
        run_step += [
            f"  %jat{c} = add i64 %jfrom, {c}",
            f"  %jsrc{c} = getelementptr double, ptr %contrib, i64 %jat{c}",
            f"  %jx{c} = load double, ptr %jsrc{c}",
            f"  %sum{c} = load double, ptr %acc{c}",
            f"  %next{c} = fadd double %sum{c}, %jx{c}",
            f"  store double %next{c}, ptr %acc{c}",
        ]
        flush += [
            f"  %total{c} = load double, ptr %acc{c}",
            f"  store double %total{c}, ptr %dst{c}",
        ]
    accumulators = [f"  %acc{c} = alloca double" for c in range(columns)]
    return "\n".join(
        [
            "define i64 @kernel(ptr %buffers, i64 %n, i64 %first, i64 %end) {",
            "entry:",
            *_buffer(0, "rows"),
            *_buffer(1, "contrib"),
            *_buffer(2, "grad"),
            *_buffer(3, "sizes"),
            *_buffer(4, "bounds"),
            "  %count = load i64, ptr %sizes",
            "  %bounded.ptr = getelementptr i64, ptr %sizes, i64 1",
            "  %bounded = load i64, ptr %bounded.ptr",
            "  %skips = icmp ne i64 %bounded, 0",
            "  %i.slot = alloca i64",
            "  %j.slot = alloca i64",
            *accumulators,
            "  store i64 0, ptr %i.slot",
            "  br label %head",
            "head:",  # element i: the next one not yet added
            "  %i = load i64, ptr %i.slot",
            "  %more = icmp slt i64 %i, %n",
            "  br i1 %more, label %check, label %done",
            "check:",  # at a block's first element: skip the block if none of its rows is ours
            f"  %offset = and i64 %i, {block - 1}",
            "  %starts = icmp eq i64 %offset, 0",
            "  %look = and i1 %starts, %skips",
            "  br i1 %look, label %block, label %body",
            "block:",
            f"  %b = sdiv i64 %i, {block}",
            "  %b2 = mul i64 %b, 2",
            "  %lo.ptr = getelementptr i64, ptr %bounds, i64 %b2",
            "  %hi.ptr = getelementptr i64, ptr %lo.ptr, i64 1",
            "  %lo = load i64, ptr %lo.ptr",
            "  %hi = load i64, ptr %hi.ptr",
            "  %before = icmp slt i64 %hi, %first",
            "  %after = icmp sge i64 %lo, %end",
            "  %none = or i1 %before, %after",
            "  br i1 %none, label %jump, label %body",
            "jump:",
            f"  %i.jump = add i64 %i, {block}",
            "  store i64 %i.jump, ptr %i.slot",
            "  br label %head",
            "body:",
            *_row_of("r", "%i"),
            "  %below = icmp slt i64 %r, %first",
            "  %above = icmp sge i64 %r, %end",
            "  %elsewhere = or i1 %below, %above",
            "  br i1 %elsewhere, label %skip, label %add",
            "skip:",
            "  %i.skip = add i64 %i, 1",
            "  store i64 %i.skip, ptr %i.slot",
            "  br label %head",
            "add:",  # a run of elements on row r starts at i
            f"  %from = mul i64 %i, {columns}",
            f"  %base = mul i64 %r, {columns}",
            *run_start,
            "  %j.first = add i64 %i, 1",
            "  store i64 %j.first, ptr %j.slot",
            "  br label %run",
            "run:",
            "  %j = load i64, ptr %j.slot",
            "  %j.more = icmp slt i64 %j, %n",
            "  br i1 %j.more, label %run.row, label %flush",
            "run.row:",
            *_row_of("rj", "%j"),
            "  %same = icmp eq i64 %rj, %r",
            "  br i1 %same, label %run.add, label %flush",
            "run.add:",
            f"  %jfrom = mul i64 %j, {columns}",
            *run_step,
            "  %j.next = add i64 %j, 1",
            "  store i64 %j.next, ptr %j.slot",
            "  br label %run",
            "flush:",
            *flush,
            "  %i.next = load i64, ptr %j.slot",
            "  store i64 %i.next, ptr %i.slot",
            "  br label %head",
            "done:",
            "  ret i64 0",
            "}",
        ]
    )
