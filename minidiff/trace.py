"""Tracing: running a function of minidiff arrays on *traced* arrays, to record its
arithmetic once as a scalar program (``ir.Graph``).

A compiled function works on a batch: every *batched* argument has a first axis of length
n, the same for all of them, and the function treats the n elements alike (a renderer's
hits, a film's pixels). *Shared* arguments are the same for every element: a light's
position, a material's colour, and tables that elements pick rows from by an integer index
(a mesh's vertices, a texture).

A ``Traced`` array stands for one argument, or for a value computed from them. It holds the
*lanes* of one element: an object array of ``ir.Value`` of the shape the array has after
its batch axis. A batched (n, 3) array has three lanes; a shared (3,) colour has three
lanes too, read once for all elements. Everything the function does on traced arrays turns
into operations on lanes:

- elementwise primitives (add, exp, where, maximum...) apply their *scalar form* (see
  ``primitives.py``) lane by lane after NumPy's broadcasting, recording each result's
  slopes (``elementwise``);
- shape operations (reshape, slices, stack, transpose...) only rearrange lanes: they add
  nothing to the program, and derivatives follow the lanes wherever they go;
- a shared table indexed by an integer array (``vertices[faces]``) becomes gathers: one
  lane per column, loaded from the row each element names;
- reductions over an element's own axes (``sum(x, axis=-1)``) add its lanes in order.

What the program cannot express is refused here, naming the operation: a reduction over the
batch axis, Python control flow on a traced value (``if x > 0:``), NumPy functions that would
need the values (``np.sum(x)``), a Tensor that requires grad captured from outside (its
gradient would be lost: pass it as an argument).
"""

from __future__ import annotations

import builtins
from typing import Any, NamedTuple

import numpy as np

from minidiff import ir

# A shared argument is read lane by lane only up to this many elements; larger ones are
# tables, read by gathers (a program with one line per texel would be slow to compile).
MAX_LANES = 1024

TYPES = {"f": "f64", "i": "i64", "u": "i64", "b": "i1"}  # NumPy dtype kind -> scalar type
DTYPES = {"f64": np.float64, "i64": np.int64, "i1": np.bool_}  # scalar type -> NumPy dtype


class CompileError(TypeError):
    """What a function does cannot be compiled (raised at trace time, naming what)."""


class Slot(NamedTuple):
    """One array argument of a compiled function: ``batched`` (its first axis is the
    batch) or shared; ``shape`` of one element (batched) or of the whole array (shared);
    ``type`` the scalar type of its elements."""

    batched: bool
    shape: tuple[int, ...]
    type: str


class Traced:
    """An array inside a function being compiled: the lanes (object array of ``ir.Value``)
    of one element, ``batch`` the batch length n (None for a shared array), ``dtype``.

    A shared argument's lanes are made on first use (``slot`` says which argument), so
    that a large table costs nothing until it is gathered from."""

    __array_ufunc__ = None  # NumPy operators defer to ours: np_array * traced -> __rmul__

    def __init__(self, lanes, batch: int | None, dtype, slot: int | None = None, shape=None):
        if lanes is not None and not isinstance(lanes, np.ndarray):  # one Value: 0-d lanes
            single = np.empty((), dtype=object)
            single[()] = lanes
            lanes = single
        self._lanes = lanes
        self.batch = batch
        self.dtype = np.dtype(dtype)
        self.slot = slot
        self._shape = tuple(lanes.shape) if lanes is not None else tuple(shape)

    @property
    def lanes(self) -> np.ndarray:
        """The lanes, made from the argument on first use for a shared one."""
        if self._lanes is None:
            if int(np.prod(self._shape)) > MAX_LANES:
                raise CompileError(
                    f"compile: a shared argument of shape {self._shape} is used elementwise; "
                    f"only arrays of up to {MAX_LANES} elements can be (index a table with an "
                    "integer array instead, or pass it as a batched argument)"
                )
            type_ = TYPES[self.dtype.kind]
            flat = [
                ir.active().add("uniform", (), type_, (self.slot, j))
                for j in range(int(np.prod(self._shape)))
            ]
            self._lanes = _object_array(flat, self._shape)
        return self._lanes

    @property
    def lane_shape(self) -> tuple[int, ...]:
        return self._shape

    @property
    def shape(self) -> tuple[int, ...]:
        """The array's shape, batch axis first. Reading a batched array's shape tells the
        compiler that the program may depend on n (``ir.Graph.reads_batch``)."""
        if self.batch is not None:
            graph = ir._building.get()
            if graph is not None:
                graph.reads_batch = True
        return self.full_shape

    @property
    def full_shape(self) -> tuple[int, ...]:
        """``shape``, without telling the compiler (for minidiff's own checks)."""
        return self._shape if self.batch is None else (self.batch, *self._shape)

    @property
    def ndim(self) -> int:
        return len(self._shape) + (self.batch is not None)

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))

    def __len__(self) -> int:
        return self.shape[0]

    def __repr__(self) -> str:
        kind = "shared" if self.batch is None else "batched"
        return f"Traced({kind}, shape={self.full_shape}, dtype={self.dtype})"

    def is_differentiated(self) -> bool:
        """True: the program is written once for every call, with or without derivatives,
        so code that drops a term on constants (``Tensor.is_differentiated``) keeps it."""
        return True

    # Values do not exist at trace time: refuse what would need them, saying what to do.
    def _no_values(self, what: str):
        raise CompileError(
            f"compile: {what} needs the values of a traced array, which a compiled "
            "function does not have while it is traced; write the choice with md.where "
            "and the arithmetic with minidiff functions"
        )

    def __bool__(self):
        self._no_values("Python control flow on a traced array (if, and, or, while)")

    def __float__(self):
        self._no_values("float()")

    def __array__(self, dtype=None, copy=None):
        self._no_values("a NumPy function (np.asarray, np.sum, ...)")

    @property
    def data(self):
        self._no_values(".data")

    def item(self):
        self._no_values(".item()")

    # Arithmetic goes through minidiff's primitives, which trace it (primitives.py).
    __add__, __radd__ = ir.operators(lambda x, y: _md().add(x, y))
    __sub__, __rsub__ = ir.operators(lambda x, y: _md().subtract(x, y))
    __mul__, __rmul__ = ir.operators(lambda x, y: _md().multiply(x, y))
    __truediv__, __rtruediv__ = ir.operators(lambda x, y: _md().divide(x, y))
    __pow__, __rpow__ = ir.operators(lambda x, y: _md().power(x, y))
    __matmul__, __rmatmul__ = ir.operators(lambda x, y: _md().matmul(x, y))
    __lt__, __gt__ = ir.operators(lambda x, y: compare("lt", x, y))
    __le__, __ge__ = ir.operators(lambda x, y: compare("le", x, y))
    __eq__ = ir.operators(lambda x, y: compare("eq", x, y))[0]  # type: ignore[assignment]
    __ne__ = ir.operators(lambda x, y: compare("ne", x, y))[0]  # type: ignore[assignment]

    def __neg__(self):
        return _md().negative(self)

    def __getitem__(self, index):
        return _md().getitem(self, index)

    def __and__(self, other):
        return logical("and", self, other)

    def __or__(self, other):
        return logical("or", self, other)

    def __invert__(self):
        return _map(lambda v: ~v, self)

    __hash__ = None  # type: ignore[assignment]

    def sum(self, axis=None, keepdims: bool = False):
        return _md().sum(self, axis=axis, keepdims=keepdims)

    def mean(self, axis=None, keepdims: bool = False):
        return _md().mean(self, axis=axis, keepdims=keepdims)

    def max(self, axis=None, keepdims: bool = False):
        return _md().max(self, axis=axis, keepdims=keepdims)

    def reshape(self, *shape):
        return _md().reshape(self, shape[0] if len(shape) == 1 else shape)

    def transpose(self, *axes):
        return _md().transpose(self, axes if axes else None)

    @property
    def T(self):
        return _md().transpose(self)


def _md():
    import minidiff

    return minidiff


def _object_array(values: list, shape: tuple[int, ...]) -> np.ndarray:
    out = np.empty(len(values), dtype=object)
    out[:] = values
    return out.reshape(shape)


def is_traced(args) -> bool:
    """Whether any argument (or any item of a list/tuple argument) is traced."""
    for a in args:
        if isinstance(a, Traced):
            return True
        if isinstance(a, (list, tuple)) and any(isinstance(b, Traced) for b in a):
            return True
    return False


def traced(x: Any, batch: int | None = None) -> Traced:
    """``x`` as a traced array: a Traced as it is; a constant (a number, a small NumPy array,
    a Tensor that does not require grad) as constant lanes."""
    if isinstance(x, Traced):
        return x
    from minidiff.tensor import Tensor

    if isinstance(x, Tensor):
        if x.requires_grad or x.tangent is not None:
            raise CompileError(
                f"compile: a Tensor of shape {x.shape} that requires grad is used inside the "
                "compiled function without being one of its arguments; its gradient would be "
                "lost: pass it as an argument"
            )
        x = x._data
    array = np.asarray(x)
    if array.dtype.kind not in TYPES:
        raise CompileError(f"compile: a constant of dtype {array.dtype} cannot be compiled")
    if array.size > MAX_LANES:
        raise CompileError(
            f"compile: a constant array of shape {array.shape} is captured by the compiled "
            "function; pass it as an argument instead"
        )
    type_ = TYPES[array.dtype.kind]
    flat = [ir.const(v, type_) for v in array.ravel().tolist()]
    return Traced(_object_array(flat, array.shape), None, DTYPES[type_])


def _batch_of(arrays: list[Traced]) -> int | None:
    batches = {a.batch for a in arrays if a.batch is not None}
    if len(batches) > 1:
        raise CompileError(f"compile: batched arrays of different lengths {sorted(batches)}")
    return batches.pop() if batches else None


def _element_lanes(a: Traced, batch: int | None, rank: int) -> np.ndarray:
    """``a``'s lanes, ready to broadcast against other elements' lanes of ``rank`` axes
    (NumPy's rule, with the batch axis set aside): a shared array that has an axis where the
    batch is must have length 1 there."""
    lanes = a.lanes
    if a.batch is None and batch is not None and lanes.ndim > rank:
        if lanes.ndim > rank + 1 or lanes.shape[0] != 1:
            raise CompileError(
                f"compile: a shared array of shape {a.full_shape} spans the batch axis of a "
                f"batched one (n = {batch}); pass it as a batched argument"
            )
        lanes = lanes[0]
    return lanes


def broadcast(arrays: list[Traced], name: str) -> tuple[list[np.ndarray], int | None]:
    """The arrays' lanes broadcast together (NumPy's rules on the shapes after the batch
    axis), and the batch length of the result (None if all are shared)."""
    batch = _batch_of(arrays)
    rank = builtins.max(len(a.lane_shape) for a in arrays if a.batch is not None) if batch else 0
    lanes = [_element_lanes(a, batch, rank) for a in arrays]
    if all(lane.shape == lanes[0].shape for lane in lanes):
        return lanes, batch  # nothing to broadcast
    try:
        return list(np.broadcast_arrays(*lanes)), batch
    except ValueError:
        shapes = " and ".join(str(a.full_shape) for a in arrays)
        raise CompileError(f"{name}: cannot broadcast shapes {shapes} together") from None


def elementwise(name: str, form, *args, differentiable=None) -> Traced:
    """Apply a primitive's scalar ``form`` lane by lane to broadcast arguments.

    ``form(*values) -> (y, slopes)``: the element's value and, per argument, its slope
    ``d -> d * dy/dx`` (None: no derivative). ``differentiable`` says which arguments take
    derivatives (default: all float ones). A Python int among the arguments is a float
    constant, as NumPy's promotion makes it beside a float array (``sum`` starts from 0).
    """
    arrays = [a if type(a) is Traced else traced(float(a) if type(a) is int else a) for a in args]
    for a, wanted in zip(arrays, differentiable or [True] * len(arrays), strict=True):
        if wanted and a.dtype.kind != "f":
            raise CompileError(
                f"{name}: needs float arrays inside a compiled function, got {a.dtype}"
            )
    lanes, batch = broadcast(arrays, name)
    nodes = ir.active().nodes
    shape = lanes[0].shape if lanes else ()
    columns = [lane.ravel().tolist() for lane in lanes]  # each lane's Values, row-major
    out = []
    for values in zip(*columns, strict=True) if columns else [()]:
        y, slopes = form(*values)
        node = nodes[y.id]
        if node.parents:  # a form must make a new value (not hand back an argument)
            raise AssertionError(f"{name}: the scalar form returned a value it did not make")
        node.parents = tuple(v.id for v in values)
        node.slopes = tuple(slopes)
        out.append(y)
    return Traced(_object_array(out, shape), batch, np.float64)


def along_last_axis(name: str, form, x) -> Traced:
    """Apply a vector primitive's scalar ``form`` to each element's last axis.

    ``form(xs) -> (ys, slopes)``: the m lanes of one vector in, k lanes out (k = m, or 1 for
    a length), and ``slopes[i][j]`` the slope ``d -> d * dy_i/dx_j`` (None: zero). Used
    where the tape's rule has special cases the composition would not reproduce (a zero
    vector, a NaN)."""
    x = traced(x)
    if x.dtype.kind != "f" or not x.lane_shape:
        raise CompileError(f"{name}: needs float vectors (..., m) inside a compiled function")
    graph = ir.active()
    lanes = x.lanes
    out = None
    for position in np.ndindex(lanes.shape[:-1]):
        xs = list(lanes[position])
        ys, slopes = form(xs)
        for y, row in zip(ys, slopes, strict=True):
            node = graph.nodes[y.id]
            node.parents = tuple(v.id for v in xs)
            node.slopes = tuple(row)
        if out is None:
            out = np.empty(lanes.shape[:-1] + (len(ys),), dtype=object)
        out[position] = ys
    return Traced(out, x.batch, np.float64)


def _map(function, *args, dtype=np.bool_) -> Traced:
    """A non-differentiable elementwise operation (comparisons, logic) lane by lane."""
    arrays = [traced(a) for a in args]
    lanes, batch = broadcast(arrays, "compare")
    out = np.empty(lanes[0].shape, dtype=object)
    for position in np.ndindex(out.shape):
        out[position] = function(*(lane[position] for lane in lanes))
    return Traced(out, batch, dtype)


def compare(op: str, a, b) -> Traced:
    """``a op b`` elementwise: a boolean traced array (a condition for ``md.where``)."""
    return _map(lambda x, y: ir.compare(op, x, y), a, b)


def to_index(x) -> Traced:
    """Floats that hold integers as int64 indices, elementwise (``ir.to_index``)."""
    return _map(ir.to_index, x, dtype=np.int64)


def select_integers(condition, a, b) -> Traced:
    """``where`` on integer arrays (indices, which take no derivative): ``a`` where the
    boolean ``condition`` holds, else ``b``, elementwise."""
    return _map(ir.select, condition, a, b, dtype=np.int64)


def logical(op: str, a, b) -> Traced:
    """``a & b`` or ``a | b`` of boolean traced arrays."""
    for x in (a, b):
        if not (isinstance(x, Traced) and x.dtype == np.bool_):
            raise CompileError(f"compile: '{op}' needs two boolean traced arrays")
    return _map(lambda x, y: ir.active().add(op, (x, y), "i1"), a, b)


# ---------------------------------------------------------------------------------------------
# Shape operations: rearranging lanes (nothing is added to the program)
# ---------------------------------------------------------------------------------------------


def _lane_axis(x: Traced, axis: int, name: str) -> int:
    """``axis`` of ``x`` (negative counts from the end) as an axis of its lanes; the batch
    axis has none."""
    axis = axis % x.ndim if x.ndim else axis
    if x.batch is not None:
        if axis == 0:
            raise CompileError(
                f"compile: {name} along the batch axis (axis 0) mixes elements; a compiled "
                "function treats each element alone: reduce its output instead"
            )
        axis -= 1
    return axis


def with_lanes(x: Traced, lanes: np.ndarray) -> Traced:
    return Traced(lanes, x.batch, x.dtype)


def reshape(x: Traced, shape) -> Traced:
    """Reshape; a batched array keeps its batch axis first (length n, or -1)."""
    shape = (shape,) if isinstance(shape, int) else tuple(shape)
    if x.batch is None:
        return with_lanes(x, x.lanes.reshape(shape))
    if not shape or shape[0] not in (x.batch, -1):
        raise CompileError(
            f"reshape: a batched array of shape {x.full_shape} must keep its batch axis first, "
            f"got {shape}"
        )
    if shape[0] == -1 and -1 in shape[1:]:
        raise CompileError(f"reshape: the batch axis and another are both -1 in {shape}")
    return with_lanes(x, x.lanes.reshape(shape[1:]))


def transpose(x: Traced, axes=None) -> Traced:
    if x.batch is None:
        return with_lanes(x, np.transpose(x.lanes, axes))
    axes = tuple(reversed(range(x.ndim))) if axes is None else tuple(a % x.ndim for a in axes)
    if axes[0] != 0:
        raise CompileError(f"transpose: a batched array must keep its batch axis first, got {axes}")
    return with_lanes(x, np.transpose(x.lanes, [a - 1 for a in axes[1:]]))


def broadcast_to(x: Traced, shape) -> Traced:
    shape = (shape,) if isinstance(shape, int) else tuple(shape)
    batch = x.batch
    if batch is None and len(shape) > x.ndim and len(shape) >= 1:
        # a shared array broadcast over a batch: the result's first axis is the batch
        # when the caller asks for one as long as the batch (that is how renderers use it)
        return Traced(np.broadcast_to(x.lanes, shape[1:]), shape[0], x.dtype)
    if batch is not None:
        if shape[0] != batch:
            raise CompileError(f"broadcast_to: cannot broadcast {x.full_shape} to {shape}")
        shape = shape[1:]
    return with_lanes(x, np.broadcast_to(x.lanes, shape))


def join(join_lanes, tensors, axis: int, name: str) -> Traced:
    """stack or concatenate (``join_lanes``: np.stack / np.concatenate) along ``axis``."""
    arrays = [traced(t) for t in tensors]
    batch = _batch_of(arrays)
    if batch is None:
        return Traced(join_lanes([a.lanes for a in arrays], axis=axis), None, arrays[0].dtype)
    if builtins.any(a.batch is None for a in arrays):
        raise CompileError(f"{name}: cannot join shared and batched arrays; broadcast first")
    rank = arrays[0].ndim + (1 if join_lanes is np.stack else 0)
    axis = axis % rank
    if axis == 0:
        raise CompileError(f"{name}: along the batch axis mixes elements of a compiled function")
    lanes = join_lanes([a.lanes for a in arrays], axis=axis - 1)
    return Traced(lanes, batch, arrays[0].dtype)


def getitem(x: Traced, index) -> Traced:
    """``x[index]``: a gather when ``index`` is a traced integer array and ``x`` a shared
    table; otherwise basic indexing of an element's lanes (slices, integers, None,
    Ellipsis, constant integer arrays)."""
    if isinstance(index, Traced):
        return gather(x, index)
    index = index if isinstance(index, tuple) else (index,)
    if builtins.any(isinstance(i, Traced) for i in index):
        raise CompileError("getitem: a traced index must be the whole index (table[rows])")
    if x.batch is None:
        return with_lanes(x, x.lanes[index])
    first, rest = _split_batch_index(index, x.ndim)
    if first != slice(None):
        raise CompileError(
            f"getitem: a batched array's batch axis must be kept whole (x[:, ...]), got "
            f"{first!r}; choose elements before calling the compiled function"
        )
    return with_lanes(x, x.lanes[rest])


def _split_batch_index(index: tuple, ndim: int):
    """The part of a NumPy index that applies to the batch axis, and the rest."""
    if not index:
        return slice(None), ()
    if index[0] is Ellipsis:
        explicit = builtins.sum(1 for i in index[1:] if i is not None)
        if explicit < ndim:
            return slice(None), index
        index = index[1:]
    return index[0], index[1:]


def gather(table: Traced, rows: Traced) -> Traced:
    """``table[rows]``: for every element, the table's row(s) at its integer index(es).
    ``table`` must be a shared argument; a negative index counts from the end, an index out
    of range is an IndexError when the function runs."""
    if rows.dtype.kind not in "iu":
        raise CompileError(f"getitem: a traced index must be an integer array, got {rows.dtype}")
    if table.slot is None or table.batch is not None:
        raise CompileError(
            "getitem: only a shared argument of the compiled function can be indexed by a "
            "traced integer array (a table such as a mesh's vertices)"
        )
    shape = table.lane_shape
    columns = int(np.prod(shape[1:]))
    type_ = TYPES[table.dtype.kind]
    graph = ir.active()
    out = np.empty(rows.lane_shape + (columns,), dtype=object)
    for position in np.ndindex(rows.lane_shape):
        row = rows.lanes[position]
        for c in range(columns):
            out[position + (c,)] = graph.add("gather", (row,), type_, (table.slot, c, columns))
    return Traced(out.reshape(rows.lane_shape + shape[1:]), rows.batch, table.dtype)


def reduce_lanes(x: Traced, axis, keepdims: bool, combine, name: str) -> Traced:
    """Reduce over axes of an element (never the batch axis), combining lanes in order
    with ``combine(a, b)`` (a traced binary primitive)."""
    x = traced(x)
    axes = range(x.ndim) if axis is None else ((axis,) if isinstance(axis, int) else axis)
    lane_axes = sorted({_lane_axis(x, a, name) for a in axes}, reverse=True)
    lanes = x.lanes
    for a in lane_axes:
        parts = [Traced(np.take(lanes, j, axis=a), x.batch, x.dtype) for j in range(lanes.shape[a])]
        if not parts:
            raise CompileError(f"{name}: over an empty axis")
        total = parts[0]
        for p in parts[1:]:
            total = combine(total, p)
        lanes = np.expand_dims(total.lanes, a) if keepdims else total.lanes
    return Traced(lanes, x.batch, x.dtype)
