"""The Tensor, the tape, the reverse pass, and forward mode.

How it works, in one paragraph: every differentiable operation (a *primitive*, see
``primitives.py``) computes its result with NumPy and, if any input requires a gradient,
appends a ``Node`` to the tape. A node remembers its inputs and a closure, the primitive's
vector-Jacobian product (VJP), which maps the gradient of the output to the gradients of the
inputs. ``backward()`` takes the nodes that lead to the output, walks them in the reverse of
the order in which they were recorded, and hands each node's output gradient to its VJP.
Gradients arriving at the same tensor from several uses are summed.

The tape is kept *implicitly*: each node carries its position ``seq`` on the (global,
ever-growing) recording order, and each tensor points at the node that made it. ``backward``
collects the nodes reachable from the output and sorts them by ``seq``; that sorted list is
exactly the slice of the tape that matters. Storing it this way means that a forward pass
nobody differentiates is freed as soon as its tensors go out of scope, instead of piling up
on a global list.

Versions: a VJP that needs an array from the forward pass (``multiply`` needs the other
operand, ``exp`` its own output) reads it at backward time. If the array was changed in
between, the gradient would silently belong to other values, so, as in PyTorch, every
tensor counts the changes to its data (``version``), each node remembers the versions of
the tensors it saved, and ``backward`` refuses to run a VJP whose saved tensors have
changed, naming the primitive and the tensor. Assigning ``t.data = ...`` (and ``t.data
-= ...``) counts as a change. An in-place write ``t.data[...] = ...`` cannot be seen by
NumPy, so a leaf (parameter or constant) that a node has saved hands out its
array only after keeping a copy, and changes are found by comparing with that copy (see
``Tensor.data`` for what is and is not seen).

Forward mode, in one paragraph: a tensor may also carry a *tangent*, an array of its own
shape: the direction in which its values are imagined to move. Every primitive also has a
Jacobian-vector product (JVP), written next to its VJP in ``primitives.py``, which maps the
tangents of its inputs to the tangent of its output (the directional derivative). When an
input carries a tangent, ``record`` calls the JVP at once, during the forward pass, and
attaches the result to the output: no tape is needed, and the cost is one extra
computation per primitive while the values are at hand. Tangents are given to tensors by
``tangents({tensor: direction})`` (restored afterwards) or by ``functional.jvp``. Both
modes coexist: a tensor may carry a tangent and be on the tape. What reverse mode treats as
a constant, forward mode does too: under ``no_grad()`` and through ``detach()`` no tangent
flows, so that <u, J v> from forward mode equals <J^T u, v> from reverse mode everywhere.
"""

from __future__ import annotations

import contextvars
import itertools
import operator
import threading
from collections.abc import Callable, Sequence
from contextlib import contextmanager
from typing import Any

import numpy as np

from minidiff import kernels
from minidiff.scoped import set_within

# The switches, per context: each thread (and each asyncio task) has its own, like PyTorch's
# grad mode, so that ``no_grad()`` in one thread never turns the tape off in another. A new
# thread starts with gradients on and anomaly detection off. Changed only through the
# context managers below.
_grad_enabled: contextvars.ContextVar[bool] = contextvars.ContextVar("grad", default=True)
_anomaly_mode: contextvars.ContextVar[bool] = contextvars.ContextVar("anomaly", default=False)

# The position of the next node on the tape: one counter for all threads (a node's seq
# orders it among the nodes its backward pass visits), guarded so that no two nodes share
# a position whatever the interpreter does with the GIL.
_SEQUENCE = itertools.count()
_SEQUENCE_LOCK = threading.Lock()


def _next_seq() -> int:
    with _SEQUENCE_LOCK:
        return next(_SEQUENCE)


class Node:
    """One entry on the tape: the record of one primitive application.

    ``vjp(g)`` returns one gradient (or None) per input, each either of the input's shape or
    broadcastable to it (``backward`` sums broadcast axes away, see ``unbroadcast``).
    ``grad`` accumulates the gradient of the node's output during a reverse pass.
    ``saved`` are the tensors whose values the VJP reads, with their ``versions`` at
    recording time; ``output_version`` is the output's version if the VJP reads the output's
    values too (else None).
    """

    __slots__ = ("name", "inputs", "vjp", "seq", "grad", "freed", "saved", "versions")
    __slots__ += ("output_version",)

    def __init__(
        self,
        name: str,
        inputs: tuple[Tensor, ...],
        vjp: Callable,
        saved: tuple[Tensor, ...] = (),
    ):
        self.name = name
        self.inputs = inputs
        self.vjp = vjp
        self.seq = _next_seq()
        self.grad: np.ndarray | None = None
        self.freed = False
        self.saved = saved
        self.versions = tuple([t.version for t in saved]) if saved else ()
        self.output_version: int | None = None  # set by record() if the VJP reads the output

    def free(self) -> None:
        """Drop the closure and the inputs so their arrays can be released."""
        self.inputs = ()
        self.saved = ()
        self.vjp = None
        self.grad = None
        self.freed = True

    def check_versions(self, output: Tensor) -> None:
        """Raise if a tensor the VJP reads (``output`` is this node's result) has changed
        since the forward pass: the VJP would compute the gradient of other values."""
        for t, recorded in zip(self.saved, self.versions, strict=True):
            if t.version != recorded:
                i = next(i for i, x in enumerate(self.inputs) if x is t)
                what = f"input {i} ({_describe(t)})"
                raise RuntimeError(_CHANGED_MESSAGE.format(name=self.name, what=what))
        if self.output_version is not None and output.version != self.output_version:
            what = f"output ({_describe(output)})"
            raise RuntimeError(_CHANGED_MESSAGE.format(name=self.name, what=what))


def _operator(name: str) -> tuple[Callable, Callable]:
    """The two Tensor methods behind a binary operator: ``t op x`` and the reflected
    ``x op t``, both the primitive ``name`` of primitives.py."""

    def method(self, other):
        return getattr(_p, name)(self, other)

    def reflected(self, other):
        return getattr(_p, name)(other, self)

    return method, reflected


def _comparison(compare: Callable) -> Callable:
    """A Tensor comparison method: ``compare(t.data, x)``, a boolean array."""

    def method(self, other):
        return compare(self._data, _values(other))

    return method


class Tensor:
    """A NumPy array that remembers how it was computed.

    Attributes: ``data`` (the ndarray), ``grad`` (ndarray of the same shape, or None; only
    leaves, i.e. tensors created by the user with ``requires_grad=True``, receive it),
    ``requires_grad`` (only floating-point tensors may require grad), ``version`` (how many
    changes to ``data`` minidiff has seen), ``node`` and ``is_leaf``, and ``tangent``
    (forward mode: an ndarray of the same shape, or None for zero).
    """

    __slots__ = ("_data", "_version", "_copy", "_saved", "_base", "_requires_grad", "_node")
    __slots__ += ("grad", "_tangent", "__weakref__")
    # Make NumPy defer to our reflected operators (ndarray + Tensor -> Tensor.__radd__) and
    # refuse ufuncs such as np.exp(tensor), which would silently drop the gradient.
    __array_ufunc__ = None

    def __init__(self, data: Any, requires_grad: bool = False, _node: Node | None = None):
        self._data = data if isinstance(data, np.ndarray) else np.asarray(data)
        self._version = 0
        self._copy: np.ndarray | None = None  # the values handed out by .data, to compare
        self._saved = False  # a node saved this tensor since the last change of data
        self._base: Tensor | None = None  # the tensor whose array ours is a view of
        if requires_grad:  # as the setter does (checks the dtype)
            _check_differentiable_dtype("Tensor", self._data.dtype)
        self._requires_grad = bool(requires_grad)
        self._node = _node
        self.grad: np.ndarray | None = None
        self._tangent: np.ndarray | None = None  # forward mode; None means zero

    # -- the values and their version -----------------------------------------------------
    @property
    def data(self) -> np.ndarray:
        """The values: the ndarray itself, not a copy, so it may be edited in place.

        Edits after ``backward()`` are fine (optimizers make them). Edits between the
        forward pass and ``backward()`` of a tensor that a VJP needs make ``backward``
        raise: assignments ``t.data = ...`` of any tensor a node saved, and in-place writes
        ``t.data[...] = ...`` of a saved *leaf* (a parameter, or a constant such as ``c`` in
        ``x * c``). For in-place writes, the first time a saved leaf hands out its array we
        keep a copy; ``version`` compares the two. A view (``x[1:]``, ``x.reshape``,
        ``x.detach()``) shares memory with its base, so an edit of either counts for both.
        Cost: one copy per saved leaf whose ``.data`` is read before backward (a scene's
        parameters: small).

        Not seen: in-place writes into tensors computed on the tape (a renderer reads the
        ``.data`` of many of its per-hit arrays; copying and comparing each cost ~5 ms of a
        10 ms light-estimation step at 512x512), and writes through an ndarray obtained
        before the forward pass (nothing was handed out after the save, so nothing was
        copied to compare with).
        """
        t = self
        while t is not None:
            if t._saved and t._copy is None and t._node is None:  # a saved leaf
                t._copy = t._data.copy()
            t = t._base
        return self._data

    @data.setter
    def data(self, value: Any) -> None:
        array = value if isinstance(value, np.ndarray) else np.asarray(value)
        if self._requires_grad:
            _check_differentiable_dtype("Tensor.data", array.dtype)
        self._data = array
        self._version += 1
        # The nodes that saved the old values are outdated by the new version; the copy of
        # those values is no longer needed.
        self._copy = None
        self._saved = False

    @property
    def version(self) -> int:
        """How many changes to ``data`` have been seen: assignments to ``.data`` (including
        ``t.data -= ...``) and in-place edits of the array handed out by ``.data``. A view
        counts its base's changes too (they share memory)."""
        if self._copy is not None and not _same_values(self._copy, self._data):
            self._version += 1
            self._copy = self._data.copy()  # the array is still out there: keep watching
        return self._version if self._base is None else self._version + self._base.version

    def mark_saved(self) -> None:
        """Note that a node saved this tensor: from now on its ``.data`` keeps a copy of the
        values it hands out, so that in-place edits can be found. An edit
        of the base of a view changes the view: the base is watched too."""
        t = self
        while t is not None:
            t._saved = True
            t = t._base

    @property
    def requires_grad(self) -> bool:
        """Whether gradients flow to this tensor (floating-point tensors only)."""
        return self._requires_grad

    @requires_grad.setter
    def requires_grad(self, value: bool) -> None:
        if value:
            _check_differentiable_dtype("Tensor", self._data.dtype)
        self._requires_grad = bool(value)

    @property
    def tangent(self) -> np.ndarray | None:
        """Forward mode: the derivative of this tensor's values along the directions given
        to the inputs (``tangents``, ``functional.jvp``), an ndarray of ``shape``; None if
        no input with a tangent reaches this tensor (a zero tangent). Read-only."""
        return self._tangent

    def is_differentiated(self) -> bool:
        """True if derivatives flow through this tensor in either mode: it requires grad
        or carries a tangent. Code that skips work on constants should test this, not
        ``requires_grad`` alone, so that forward mode takes the same path."""
        return self._requires_grad or self._tangent is not None

    @property
    def node(self) -> Node | None:
        """The tape entry of the primitive that computed this tensor; None for a leaf or a
        constant."""
        return self._node

    @property
    def is_leaf(self) -> bool:
        """True if no recorded primitive computed this tensor (a leaf or a constant)."""
        return self._node is None

    # -- array-like properties ------------------------------------------------------------
    @property
    def shape(self) -> tuple[int, ...]:
        return self._data.shape

    @property
    def ndim(self) -> int:
        return self._data.ndim

    @property
    def dtype(self) -> np.dtype:
        return self._data.dtype

    @property
    def size(self) -> int:
        return self._data.size

    def __len__(self) -> int:
        return len(self._data)

    def __repr__(self) -> str:
        flag = ", requires_grad=True" if self.requires_grad else ""
        return f"Tensor({np.array2string(self._data, threshold=20)}{flag})"

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        # np.asarray(tensor) gives the values (for plotting, saving); it is not differentiable.
        return self.data if dtype is None else self._data.astype(dtype)

    __hash__ = object.__hash__  # comparisons return arrays, so keep identity hashing

    def numpy(self) -> np.ndarray:
        """The values as an ndarray (not a copy)."""
        return self.data

    def __bool__(self) -> bool:
        """The truth of a one-element tensor (``if loss < 1`` compares arrays; ``if t`` needs
        one value). As NumPy: several elements are ambiguous, a ValueError; without this,
        every Tensor would be true, whatever its values."""
        if self._data.size != 1:
            raise ValueError(
                f"minidiff: the truth value of a Tensor of shape {self.shape} "
                f"({self._data.size} elements) is ambiguous; use (t.data).any() or .all(), "
                "or t.item() for a one-element tensor"
            )
        return bool(self._data.item())

    def item(self) -> float:
        """The value of a one-element tensor as a Python number."""
        return self._data.item()

    def detach(self) -> Tensor:
        """A tensor sharing these values but cut from the tape (a constant, no tangent)."""
        out = Tensor(self._data)
        out._base = _base_to_link(self)  # the same array: edits through either count for both
        return out

    # -- the reverse pass -----------------------------------------------------------------
    def backward(self, grad: Any = None) -> None:
        """Accumulate d(self)/d(leaf) into ``leaf.grad`` for every leaf that requires grad.

        ``grad`` is the seed, the gradient of some final scalar with respect to ``self``; it
        defaults to 1 for a scalar (one-element) tensor and is required otherwise. Gradients
        add up across calls until they are reset (``optimizer.zero_grad()``). The part of the
        tape used is freed afterwards: a second ``backward`` through it is an error.
        """
        if not self.requires_grad:
            raise ValueError(
                "backward: this tensor does not require grad (no input of the computation "
                "had requires_grad=True, or it was computed under no_grad())"
            )
        if grad is None:
            if self._data.size != 1:
                raise ValueError(
                    f"backward: the output has shape {self.shape}; a seed gradient of that "
                    "shape is needed for a non-scalar output (e.g. t.backward(np.ones(t.shape)))"
                )
            seed = np.ones(self.shape, dtype=self.dtype)
        else:
            seed = np.asarray(_values(grad), dtype=self.dtype)
            if seed.shape != self.shape:
                raise ValueError(
                    f"backward: seed gradient has shape {seed.shape}, output has {self.shape}"
                )
            if not np.isfinite(seed).all():
                raise ValueError("backward: the seed gradient contains NaN or inf")

        if self._node is None:  # a leaf: d(self)/d(self) = 1
            _accumulate_leaf(self, seed)
            return
        if self._node.freed:
            raise RuntimeError(_FREED_MESSAGE.format(name=self._node.name))

        tape = _tape_reaching(self)  # checks versions: raises before any gradient is added
        self._node.grad = seed
        anomaly = _anomaly_mode.get()
        for node in reversed(tape):  # reverse recording order: every user before its inputs
            g = node.grad
            if g is not None:
                input_grads = node.vjp(g)
                for x, gx in zip(node.inputs, input_grads, strict=True):
                    if gx is None or not x._requires_grad:
                        continue
                    # A gradient has its input's dtype: a float32 leaf used with a float64
                    # constant still gets a float32 .grad (also after accumulating).
                    data = x._data
                    if gx.shape != data.shape:
                        gx = unbroadcast(gx, data.shape)
                    if gx.dtype != data.dtype:
                        gx = gx.astype(data.dtype)
                    if anomaly and not np.isfinite(gx).all():
                        raise FloatingPointError(
                            f"anomaly: the VJP of '{node.name}' produced NaN/inf in the "
                            f"gradient of an input of shape {x.shape}"
                        )
                    if x._node is None:
                        _accumulate_leaf(x, gx)
                    elif x._node.grad is None:
                        x._node.grad = gx
                    else:
                        x._node.grad = x._node.grad + gx
            node.free()

    # -- operators (each is a primitive from primitives.py) -------------------------------
    # ``t + x`` calls ``t.__add__(x)``; ``x + t``, when x is a number or an array, calls the
    # reflected ``t.__radd__(x)``, which must keep the order: x - t is subtract(x, t).
    __add__, __radd__ = _operator("add")
    __sub__, __rsub__ = _operator("subtract")
    __mul__, __rmul__ = _operator("multiply")
    __truediv__, __rtruediv__ = _operator("divide")
    __pow__, __rpow__ = _operator("power")
    __matmul__, __rmatmul__ = _operator("matmul")

    def __neg__(self):
        return _p.negative(self)

    def __getitem__(self, index):
        return _p.getitem(self, index)

    # Comparisons are not differentiable: they return plain boolean arrays.
    __lt__ = _comparison(operator.lt)
    __le__ = _comparison(operator.le)
    __gt__ = _comparison(operator.gt)
    __ge__ = _comparison(operator.ge)
    __eq__ = _comparison(operator.eq)
    __ne__ = _comparison(operator.ne)

    # -- methods that forward to primitives -----------------------------------------------
    def sum(self, axis=None, keepdims: bool = False) -> Tensor:
        return _p.sum(self, axis=axis, keepdims=keepdims)

    def mean(self, axis=None, keepdims: bool = False) -> Tensor:
        return _p.mean(self, axis=axis, keepdims=keepdims)

    def max(self, axis=None, keepdims: bool = False) -> Tensor:
        return _p.max(self, axis=axis, keepdims=keepdims)

    def reshape(self, *shape) -> Tensor:
        if len(shape) == 1 and isinstance(shape[0], (tuple, list)):
            shape = tuple(shape[0])
        return _p.reshape(self, shape)

    def transpose(self, *axes) -> Tensor:
        if len(axes) == 1 and isinstance(axes[0], (tuple, list)):
            axes = tuple(axes[0])
        return _p.transpose(self, axes or None)

    @property
    def T(self) -> Tensor:
        return _p.transpose(self, None)


_FREED_MESSAGE = (
    "backward: the tape through '{name}' was already used by an earlier backward() and "
    "has been freed; recompute the forward pass before calling backward() again"
)
_CHANGED_MESSAGE = (
    "backward: '{name}' needs the values of its {what} from the forward pass to compute "
    "its gradient, but that tensor's .data was changed after the forward pass; the "
    "gradient would belong to other values. Change .data only after backward() (as the "
    "optimizers do), or recompute the forward pass."
)


def _describe(t: Tensor) -> str:
    """A tensor as an error message names it: shape, dtype and role."""
    role = "a leaf" if t.is_leaf else "computed by '" + t.node.name + "'"
    flag = ", requires_grad=True" if t.requires_grad else ""
    return f"shape {t.shape}, {t.dtype}, {role}{flag}"


# The floating-point dtypes minidiff computes in. float16 is refused, not half-supported:
# its range (max 65504) and 11-bit precision overflow or flush a renderer's sums and
# products, its gradients would round to zero, and NumPy computes it slowly.
SUPPORTED_FLOATS = (np.dtype(np.float32), np.dtype(np.float64))


def _check_supported_float(where: str, dtype: np.dtype) -> None:
    """Refuse floating-point dtypes other than float32 and float64 (float16, longdouble)."""
    if dtype.kind == "f" and dtype not in SUPPORTED_FLOATS:
        raise TypeError(
            f"{where}: dtype {dtype} is not supported; minidiff computes in float32 or "
            "float64 (convert first, e.g. md.tensor(values, dtype=np.float32))"
        )


def _check_differentiable_dtype(where: str, dtype: np.dtype) -> None:
    """Gradients are real numbers: an integer or boolean tensor would truncate them to 0,
    a complex one has no gradient in minidiff's (real) sense."""
    if dtype in SUPPORTED_FLOATS:  # the common case, checked first: every primitive's output
        return
    if dtype.kind == "c":
        raise TypeError(
            f"{where}: only floating-point tensors can require grad; a complex tensor "
            f"(dtype {dtype}) cannot: minidiff's gradients are real (use float32 or float64)"
        )
    if not np.issubdtype(dtype, np.floating):
        raise TypeError(
            f"{where}: only floating-point tensors can require grad, got dtype {dtype} "
            "(convert first, e.g. md.tensor(values, dtype=np.float64))"
        )
    _check_supported_float(where, dtype)


def _base_to_link(base: Tensor) -> Tensor | None:
    """The base a constant view may point to: a leaf or constant only. Pointing at a tensor
    computed on the tape would keep that tape (and its arrays) alive as long as the view,
    so edits through views of *computed* tensors made under no_grad() or by detach() are
    not linked (a known gap)."""
    return base if base._node is None else None


def _same_values(a: np.ndarray, b: np.ndarray) -> bool:
    """True if a and b hold the same values (NaN equals NaN: a NaN is not an edit)."""
    return np.array_equal(a, b, equal_nan=a.dtype.kind in "fc")


def _accumulate_leaf(x: Tensor, g: np.ndarray) -> None:
    """Add g into a leaf's .grad (copying the first time, so .grad never aliases; large
    ones on the threads, ``kernels.copy`` and ``kernels.add``: NumPy's bits)."""
    if x.grad is None:
        x.grad = kernels.copy(g, x.dtype)
    elif isinstance(x.grad, np.ndarray) and isinstance(g, np.ndarray):
        x.grad = kernels.add(x.grad, g)
    else:
        x.grad = x.grad + g


def _tape_reaching(output: Tensor) -> list[Node]:
    """The nodes that the output depends on, in recording order (the relevant tape slice).

    Each node's saved tensors are checked on the way (``Node.check_versions``), so that a
    changed tensor stops ``backward`` before any gradient has been added anywhere."""
    output._node.check_versions(output)
    seen = {output._node}  # nodes hash by identity
    stack = [output._node]
    nodes = []
    while stack:
        node = stack.pop()
        nodes.append(node)
        for x in node.inputs:
            parent = x._node
            if parent is not None and parent not in seen:
                if parent.freed:
                    raise RuntimeError(_FREED_MESSAGE.format(name=parent.name))
                parent.check_versions(x)
                seen.add(parent)
                stack.append(parent)
    nodes.sort(key=_SEQ)
    return nodes


_SEQ = operator.attrgetter("seq")


def unbroadcast(g: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """Sum a gradient of a broadcast result back to the input's ``shape``.

    If x of shape (3,) was broadcast against (k, 3), its gradient is the (k, 3) gradient
    summed over the k rows: first the leading axes that broadcasting added, then the axes
    where ``shape`` has size 1 (kept, as size 1). The sums are NumPy kernels that are fast
    on tall, thin arrays (``minidiff.kernels``).
    """
    if g.shape == shape:
        return g
    lead = g.ndim - len(shape)
    if lead > 0:
        g = kernels.sum_leading_axes(g, lead)
    axes = tuple(i for i, n in enumerate(shape) if n == 1 and g.shape[i] != 1)
    if axes:
        g = kernels.sum_keepdims(g, axes)
    return g


def _values(x: Any) -> Any:
    """The raw values of a Tensor, or x itself."""
    return x._data if isinstance(x, Tensor) else x


def tensor(data: Any, requires_grad: bool = False, dtype: Any = None) -> Tensor:
    """Make a leaf tensor from array-like data.

    Floating-point data keeps its dtype (float32 stays float32); integer and boolean data
    (lists of Python numbers, integer arrays) becomes float64 unless ``dtype`` says
    otherwise. Complex data stays complex (a constant: it cannot require grad). Anything
    else (strings, None, objects) is a TypeError, and so are float16 and longdouble (see
    ``SUPPORTED_FLOATS``). The data is copied, so later changes to ``data`` do not affect
    the tensor.
    """
    data = _values(data)
    try:
        arr = np.array(data) if dtype is None else np.array(data, dtype=dtype)
    except (TypeError, ValueError) as error:
        raise TypeError(
            f"tensor: cannot make a tensor of {type(data).__name__} {data!r:.60} ({error}); "
            "expected numbers, nested lists of numbers, or a NumPy array of them"
        ) from None
    if arr.dtype.kind not in "biufc":
        raise TypeError(
            f"tensor: cannot make a tensor of {type(data).__name__} {data!r:.60} (NumPy "
            f"dtype {arr.dtype}); expected numbers, nested lists of numbers, or a NumPy "
            "array of them"
        )
    if dtype is None and arr.dtype.kind in "biu":
        arr = arr.astype(np.float64)
    _check_supported_float("tensor", arr.dtype)
    if requires_grad:
        _check_differentiable_dtype("tensor", arr.dtype)
    return Tensor(arr, requires_grad=requires_grad)


def as_tensor(x: Any) -> Tensor:
    """x itself if it is a Tensor, else a constant (non-differentiable) tensor of its values
    (float16 refused, as by ``tensor``)."""
    if isinstance(x, Tensor):
        return x
    x = x if isinstance(x, np.ndarray) else np.asarray(x)
    if x.dtype.kind == "f" and x.dtype not in SUPPORTED_FLOATS:  # float16: see tensor()
        _check_supported_float("as_tensor", x.dtype)
    return Tensor(x)


def record(
    name: str,
    out: np.ndarray,
    inputs: Sequence[Tensor],
    vjp: Callable,
    saves: Sequence[Tensor] = (),
    saves_output: bool = False,
    view_of: Tensor | None = None,
    jvp: Callable | None = None,
) -> Tensor:
    """Wrap a primitive's forward result and, if needed, put its node on the tape and give
    it a tangent.

    A node is recorded only if gradients are enabled and some input requires grad; otherwise
    the result is a constant and nothing is remembered. ``saves`` are the inputs whose
    values the VJP reads, and ``saves_output`` says whether it reads ``out``: their versions
    are remembered, and ``backward`` raises if they have changed by then. ``view_of`` is the
    input whose memory ``out`` may share (reshape, slices): edits of one change the other,
    so their versions are linked.

    Forward mode: if gradients are enabled and some input carries a tangent, ``jvp`` is
    called now with one tangent per input (None for an input without one, meaning zero)
    and returns the output's tangent, of ``out``'s shape or broadcastable to it (or None
    for zero). A primitive without a JVP refuses inputs with tangents.
    """
    if _anomaly_mode.get() and np.issubdtype(out.dtype, np.inexact) and not np.isfinite(out).all():
        raise FloatingPointError(f"anomaly: forward of '{name}' produced NaN/inf")
    grad_enabled = _grad_enabled.get()
    differentiated = tangents = False
    if grad_enabled:  # one pass over the inputs: does one require grad, carry a tangent?
        for x in inputs:
            differentiated = differentiated or x._requires_grad
            tangents = tangents or x._tangent is not None
    if differentiated:
        for t in saves:
            t.mark_saved()
        node = Node(name, tuple(inputs), vjp, tuple(saves))
        result = Tensor(out, requires_grad=True, _node=node)
    else:
        node, result = None, Tensor(out)
    if view_of is not None and np.may_share_memory(out, view_of._data):
        # An on-tape result holds view_of anyway (its node's input); a constant must not
        # keep view_of's part of the tape alive (see _base_to_link).
        result._base = view_of if node is not None else _base_to_link(view_of)
    if node is not None and saves_output:
        result.mark_saved()
        node.output_version = result.version
    if tangents:
        result._tangent = _output_tangent(name, out, inputs, jvp)
    return result


def _output_tangent(name: str, out: np.ndarray, inputs: Sequence[Tensor], jvp) -> np.ndarray | None:
    """The JVP's result for ``out``, broadcast to its shape and cast to its dtype."""
    if jvp is None:
        raise NotImplementedError(
            f"forward mode: the primitive '{name}' has no JVP, but an input carries a tangent"
        )
    t = jvp(*(x._tangent for x in inputs))
    if t is None:
        return None
    t = np.asarray(t)
    if t.shape != out.shape:  # e.g. a + b where only the smaller operand has a tangent
        t = np.broadcast_to(t, out.shape)
    if t.dtype != out.dtype:
        t = t.astype(out.dtype)
    if _anomaly_mode.get() and not np.isfinite(t).all():
        raise FloatingPointError(f"anomaly: the JVP of '{name}' produced NaN/inf")
    return t


def _grad_mode(enabled: bool):
    """Gradients enabled or not in the current thread (context) within the block."""
    return set_within(_grad_enabled, enabled)


def no_grad():
    """Within this block nothing is differentiated: results are constants, with no node on
    the tape and no tangent (faster, no memory). It applies to the current thread (context)
    only: other threads keep recording."""
    return _grad_mode(False)


def enable_grad():
    """Within this block operations are recorded again, even inside ``no_grad()`` (as
    PyTorch's ``enable_grad``): for code that must build a tape of its own, such as a VJP
    that differentiates a replayed computation while the caller's ``backward`` runs under
    ``no_grad()``. Current thread (context) only."""
    return _grad_mode(True)


def detect_anomaly():
    """Opt-in checking: raise at the first primitive whose forward value or backward
    gradient contains NaN or inf, naming it. Costs one ``isfinite`` scan per array."""
    return set_within(_anomaly_mode, True)


def as_tangent(where: str, what: str, primal: Tensor, direction: Any) -> np.ndarray:
    """``direction`` as a tangent for ``primal``: an array of the primal's shape and dtype.

    Integer and floating-point directions are accepted (``[1, 0, 0]``) and converted;
    anything else, a wrong shape, or a primal that is not floating-point is a ValueError
    naming ``what`` (e.g. "tangent 0") and the expected shape."""
    if not np.issubdtype(primal.dtype, np.floating):
        raise ValueError(
            f"{where}: {what} belongs to a {primal.dtype} tensor; only floating-point "
            "tensors can have tangents"
        )
    array = np.asarray(_values(direction))
    if array.dtype.kind not in "iuf":
        raise ValueError(
            f"{where}: {what} must be a real number array of shape {primal.shape} "
            f"(floating-point or integer), got dtype {array.dtype}"
        )
    if array.shape != primal.shape:
        raise ValueError(
            f"{where}: {what} has shape {array.shape}, expected {primal.shape} (the shape "
            "of the tensor it moves)"
        )
    return np.array(array, dtype=primal.dtype)  # a copy: later edits of direction do not leak


@contextmanager
def tangents(directions: dict[Tensor, Any]):
    """Forward mode on existing tensors: within this block each tensor in ``directions``
    carries its direction (an array of the tensor's shape) as its tangent, so every result
    computed from it carries its derivative along that direction (``Tensor.tangent``).
    The previous tangents (usually None) are restored afterwards.

        >>> with md.tangents({light_position: np.array([1.0, 0.0, 0.0])}):
        ...     image = render(scene)
        >>> image.tangent          # d image / d (light x), shape (H, W, 3)
    """
    # Lists of pairs, not dicts: a Tensor's == compares values, so it makes a poor dict key.
    checked = []
    for t, d in directions.items():
        if not isinstance(t, Tensor):
            raise TypeError(f"tangents: keys must be minidiff Tensors, got {type(t).__name__}")
        what = f"the direction of a tensor of shape {t.shape}"
        checked.append((t, as_tangent("tangents", what, t, d)))
    previous = [(t, t._tangent) for t, _ in checked]
    try:
        for t, d in checked:
            t._tangent = d
        yield
    finally:
        for t, d in reversed(previous):
            t._tangent = d


def is_grad_enabled() -> bool:
    """True unless inside ``no_grad()`` (in this thread or context)."""
    return _grad_enabled.get()


from minidiff import primitives as _p  # noqa: E402  (primitives import Tensor from here)
