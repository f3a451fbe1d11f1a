"""The scalar program a compiled function becomes: one element's arithmetic, in SSA form.

``minidiff.compile`` runs a function of minidiff arrays once on *traced* arrays
(``trace.py``): every element of an array there is a ``Value``, one line of a straight-line
program held by a ``Graph``. ``x * y`` on two Values appends the line ``v7 = mul v3 v5`` to
the graph being built and returns ``v7``. The program is the same for every element of the
batch; ``codegen.py`` turns it into a loop over the elements.

Values are plain arithmetic here: they know nothing of derivatives. A primitive's *scalar
form* (in ``primitives.py``, beside its array form) builds its value from these operations
and says, for each input, its *slope*: a function ``d -> d * (dy/dx)`` written with the same
operations (``trace.elementwise`` attaches it to the value). The code generator calls the
slopes with gradients (reverse mode) or tangents (forward mode) to write the derivative
program.

Three scalar types: ``f64`` (double), ``i64`` (integer indices) and ``i1`` (a comparison's
result). Every operation lists the LLVM instruction it becomes in ``INSTRUCTIONS`` below.
"""

from __future__ import annotations

import contextvars
import math
import struct
from collections.abc import Callable
from dataclasses import dataclass, field

from minidiff.scoped import set_within

# The graph that Values are appended to, per thread (a contextvar: two threads can trace
# at once, each into its own graph).
_building: contextvars.ContextVar[Graph | None] = contextvars.ContextVar("building", default=None)


@dataclass(slots=True)
class Node:
    """One line of the program: ``op`` applied to the values ``args`` (ids of earlier
    lines), of scalar ``type``; ``attrs`` hold what the op needs besides values (a
    constant's number; an input's slot and lane). ``parents`` and ``slopes`` are set for
    a differentiable primitive's result: its inputs, and for each the function
    ``d -> d * dy/dx`` (None where the input takes no derivative)."""

    op: str
    args: tuple[int, ...]
    type: str
    attrs: tuple = ()
    parents: tuple[int, ...] = ()
    slopes: tuple[Callable | None, ...] = ()


@dataclass
class Graph:
    """A straight-line scalar program: ``nodes`` in the order they were built (so every
    argument comes before its use)."""

    nodes: list[Node] = field(default_factory=list)
    # Whether the traced function read the batch length n (a batched array's shape, len,
    # size): then its program may depend on n, and is kept per n (compiler.py).
    reads_batch: bool = False

    def add(self, op: str, args: tuple[Value, ...], type_: str, attrs: tuple = ()) -> Value:
        """Append ``op(args)`` and return its Value."""
        self.nodes.append(Node(op, tuple(a.id for a in args), type_, attrs))
        return Value(len(self.nodes) - 1, type_)

    def extended(self) -> Graph:
        """A copy to append derivative lines to; the original stays as traced."""
        return Graph(list(self.nodes), self.reads_batch)

    def building(self):
        """Within the block, operations on Values append to this graph."""
        return set_within(_building, self)


def active() -> Graph:
    """The graph being built in this thread."""
    graph = _building.get()
    if graph is None:
        raise RuntimeError("minidiff.ir: operations on Values need a graph being built")
    return graph


def operators(fn: Callable) -> tuple[Callable, Callable]:
    """The two methods behind a binary operator: ``x op y`` calls ``fn(x, y)``, and the
    reflected one (Python's ``y op x`` when y is not of the class) calls ``fn(y, x)``. For a
    comparison the reflected method is its mirror: ``__lt__, __gt__ = operators(less)``."""
    return (lambda self, other: fn(self, other)), (lambda self, other: fn(other, self))


class Value:
    """A scalar of one element: line ``id`` of the graph being built, of scalar ``type``.
    Arithmetic on Values appends lines (Python numbers become constants). Two Values are
    equal when their ids and types are, as a frozen dataclass's would be; a plain class with
    slots because a trace makes one per line (a frozen dataclass's ``__init__`` costs
    several times as much)."""

    __slots__ = ("id", "type")

    def __init__(self, id: int, type: str):  # noqa: A002 (the fields' names)
        self.id = id
        self.type = type

    def __repr__(self) -> str:
        return f"Value(id={self.id!r}, type={self.type!r})"

    def __eq__(self, other) -> bool:
        if other.__class__ is not Value:
            return NotImplemented
        return self.id == other.id and self.type == other.type

    def __hash__(self) -> int:
        return hash((self.id, self.type))

    __add__, __radd__ = operators(lambda x, y: _binary("add", x, y))
    __sub__, __rsub__ = operators(lambda x, y: _binary("sub", x, y))
    __mul__, __rmul__ = operators(lambda x, y: _binary("mul", x, y))
    __truediv__, __rtruediv__ = operators(lambda x, y: _binary("div", x, y))
    __lt__, __gt__ = operators(lambda x, y: compare("lt", x, y))
    __le__, __ge__ = operators(lambda x, y: compare("le", x, y))

    def __neg__(self):
        return active().add("neg", (self,), "f64")

    def __and__(self, other):
        return active().add("and", (self, other), "i1")

    def __or__(self, other):
        return active().add("or", (self, other), "i1")

    def __invert__(self):
        return active().add("not", (self,), "i1")


def const(x: float | int | bool, type_: str = "f64") -> Value:
    """A constant of ``type_``."""
    value = {"f64": float, "i64": int, "i1": bool}[type_](x)
    return active().add("const", (), type_, (value,))


def _as_value(x, type_: str = "f64") -> Value:
    return x if isinstance(x, Value) else const(x, type_)


def _binary(op: str, a, b) -> Value:
    a, b = _as_value(a), _as_value(b)
    return active().add(op, (a, b), "f64")


def compare(op: str, a, b) -> Value:
    """``a op b`` (op: lt, le, gt, ge, eq, ne) on two f64 or two i64 values: an i1. As in
    NumPy, every comparison with a NaN is false except ``ne``. Values of two types (a float
    against an integer constant: ``z >= 0``) are compared as f64, as NumPy compares them."""
    kinds = {x.type for x in (a, b) if isinstance(x, Value)}
    kind = kinds.pop() if len(kinds) == 1 else "f64"
    return active().add(op, (_of_type(a, kind), _of_type(b, kind)), "i1")


def _of_type(x, kind: str) -> Value:
    """``x`` (a Value or a number) as a Value of type ``kind``; a Value of another type only
    becomes an f64 (``to_float``)."""
    if isinstance(x, Value) and x.type != kind:
        return to_float(x)
    return _as_value(x, kind)


def select(condition: Value, a, b) -> Value:
    """``a`` where ``condition`` (an i1) holds, else ``b``: both are computed, one is
    kept (LLVM's ``select``)."""
    kind = a.type if isinstance(a, Value) else (b.type if isinstance(b, Value) else "f64")
    return active().add("select", (condition, _as_value(a, kind), _as_value(b, kind)), kind)


def call(function: str, *args) -> Value:
    """A math function of f64 values: exp, log, sqrt, sin, cos, tan, tanh, fabs, floor,
    pow (two arguments)."""
    return active().add(function, tuple(_as_value(a) for a in args), "f64")


def constant(x: Value) -> float | int | bool | None:
    """The number of ``x`` if it is a constant line, else None (then its value is known only
    when the kernel runs)."""
    node = active().nodes[x.id]
    return node.attrs[0] if node.op == "const" else None


def integer_power(x: Value, k: int) -> Value:
    """``x ** k`` for an integer ``k >= 0`` as products, by repeated squaring (``x ** 31`` is
    x^16 x^8 x^4 x^2 x: 8 products). Each product rounds, so the result is within about
    ``k`` ulps of a correctly rounded power (NumPy's ``pow``), but it is plain arithmetic,
    which LLVM vectorises, where ``pow`` is a library call per element."""
    result, square = None, x
    while k:
        if k & 1:
            result = square if result is None else result * square
        k >>= 1
        if k:
            square = square * square
    return const(1.0) if result is None else result


def to_float(x: Value) -> Value:
    """An i1 (0 or 1) or an i64 as an f64."""
    return active().add("tofloat", (x,), "f64")


def to_index(x: Value) -> Value:
    """An f64 that holds an integer as an i64 (an index for a gather): saturating at
    int64's range, NaN as 0 (LLVM's ``fptosi.sat``: defined for every input)."""
    return active().add("toint", (x,), "i64")


def is_nan(x: Value) -> Value:
    """True where x is NaN (the only value unequal to itself)."""
    return compare("ne", x, x)


def sign(x: Value) -> Value:
    """NumPy's sign: -1, 0 or 1, and NaN for NaN."""
    return select(x > 0.0, 1.0, select(x < 0.0, -1.0, select(is_nan(x), x, 0.0)))


# The LLVM instruction of each operation: a format string over the arguments' names
# (``{0}``, ``{1}``, ...) giving the right-hand side of ``%vN = ...``. Math functions are
# LLVM intrinsics (or the C library's tan and tanh), which compute what NumPy's do to
# within an ulp. No fast-math flags: NaN and inf propagate, and nothing is reordered, so
# the program's rounding is the program's.
INSTRUCTIONS = {
    "add": "fadd double {0}, {1}",
    "sub": "fsub double {0}, {1}",
    "mul": "fmul double {0}, {1}",
    "div": "fdiv double {0}, {1}",
    "neg": "fneg double {0}",
    "exp": "call double @llvm.exp.f64(double {0})",
    "log": "call double @llvm.log.f64(double {0})",
    "sqrt": "call double @llvm.sqrt.f64(double {0})",
    "sin": "call double @llvm.sin.f64(double {0})",
    "cos": "call double @llvm.cos.f64(double {0})",
    "tan": "call double @tan(double {0})",
    "tanh": "call double @tanh(double {0})",
    "fabs": "call double @llvm.fabs.f64(double {0})",
    "floor": "call double @llvm.floor.f64(double {0})",
    "toint": "call i64 @llvm.fptosi.sat.i64.f64(double {0})",
    "pow": "call double @llvm.pow.f64(double {0}, double {1})",
    "and": "and i1 {0}, {1}",
    "or": "or i1 {0}, {1}",
    "not": "xor i1 {0}, true",
}

# Comparisons: ordered (false with a NaN) except "ne", as NumPy's operators.
FLOAT_COMPARISONS = {"lt": "olt", "le": "ole", "gt": "ogt", "ge": "oge", "eq": "oeq", "ne": "une"}
INT_COMPARISONS = {"lt": "slt", "le": "sle", "gt": "sgt", "ge": "sge", "eq": "eq", "ne": "ne"}

DECLARATIONS = """declare double @llvm.exp.f64(double)
declare double @llvm.log.f64(double)
declare double @llvm.sqrt.f64(double)
declare double @llvm.sin.f64(double)
declare double @llvm.cos.f64(double)
declare double @llvm.fabs.f64(double)
declare double @llvm.floor.f64(double)
declare double @llvm.pow.f64(double, double)
declare double @tan(double)
declare double @tanh(double)
declare i64 @llvm.smin.i64(i64, i64)
declare i64 @llvm.fptosi.sat.i64.f64(double)
"""


def llvm_constant(value, type_: str) -> str:
    """A constant as LLVM IR writes it: doubles in hexadecimal, exactly (inf and NaN
    included)."""
    if type_ == "f64":
        if math.isnan(value):
            return "0x7FF8000000000000"
        bits = struct.unpack("<Q", struct.pack("<d", value))[0]
        return f"0x{bits:016X}"
    if type_ == "i1":
        return "true" if value else "false"
    return str(int(value))
