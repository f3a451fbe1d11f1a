"""The primitives: each one's forward computation, its vector-Jacobian product (reverse mode)
and its Jacobian-vector product (forward mode), side by side.

Reading guide. Every primitive follows the same pattern::

    def exp(x):
        x = as_tensor(x)
        y = np.exp(x._data)                                   # forward, plain NumPy
        return record("exp", y, (x,), lambda g: (g * y,),     # VJP: g -> grad for each input
                      saves_output=True,                      # the VJP reads y
                      jvp=lambda t: t * y)                    # JVP: input tangents -> output's

``g`` is the gradient of the final scalar with respect to this primitive's output (same
shape as the output). The VJP returns, for each input, the gradient with respect to that
input. It may return a gradient of the *broadcast* shape; ``backward`` sums it back to the
input's shape. ``None`` means "no gradient flows to this input" (e.g. integer indices).

The JVP goes the other way: it receives one tangent per input (an array of that input's
shape, the direction in which the input moves; ``None`` for an input without one, meaning
zero) and returns the tangent of the output, the directional derivative J t. It may
return an array that still broadcasts to the output's shape (``record`` broadcasts it).
For the same derivative the two are transposes of each other: where the VJP of multiply
gives ``g * b`` to ``a``, the JVP gives ``ta * b`` to the output; where the VJP of a
broadcast sums ``g`` back to the input's shape, the JVP just lets the tangent broadcast.
At kinks (maximum, clip, max, abs) both pick the same subgradient, so that forward and
reverse mode always agree: <u, J t> = <J^T u, t>. The JVP runs during the forward pass
(see ``tensor.py``), so it reads the inputs directly and saves nothing.

``saves`` / ``saves_output`` tell the tape which values the VJP will read at backward
time, so that ``backward`` can refuse to run if they were changed in the meantime (see
``tensor.py``); ``view_of`` names the input whose memory the result shares (a reshape,
a slice). Primitives read ``x._data``, the array itself: the public ``x.data``
additionally watches for in-place edits by the user, which we do not need here.

A few primitives (``dot``, ``cross``, ``norm``, ``normalize``, ``scatter_add``) could be
composed from the others, but are written fused with hand-derived VJPs: renderers call them
on every pixel, and the fused versions allocate fewer temporaries and record fewer nodes.

The mathematics is written as NumPy expressions. Where a function of ``kernels.py`` stands
in for one, it equals that expression bit for bit and its name says which:
``kernels.multiply(g, b)`` is ``g * b``, ``kernels.cross3(a, b)`` is ``np.cross(a, b)``.
It is there because it was measured to be faster on a renderer's arrays (rows of three,
image-sized results); how it is made fast is not this file's business.
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np

from minidiff import ir, kernels, trace
from minidiff.tensor import Tensor, as_tensor, record

# ---------------------------------------------------------------------------------------------
# Traced forms (minidiff.compile)
# ---------------------------------------------------------------------------------------------
# While ``minidiff.compile`` traces a function (``trace.py``), its arrays are ``Traced``: no
# values, only each element's lanes of scalar program values (``ir.py``). Every primitive
# below then runs its *traced form* instead of its array form. For an elementwise primitive
# that is its *scalar form*, written just above it: one element's value from the ``ir``
# operations, and for each input its slope ``d -> d * dy/dx`` -- the same rule as the
# array VJP and JVP beside it, which the code generator applies to gradients (reverse
# mode) and to tangents (forward mode). Vector primitives are traced as the composition of
# elementwise ones they are (dot = sum of products), shape operations as rearrangements of
# lanes. A primitive without a traced form (matmul, linear, ...) refuses a traced argument.


def _traces_as(form):
    """Decorator: when an argument is a traced array, run ``form`` (the traced form)
    instead of the array form below it."""

    def wrap(array_form):
        @functools.wraps(array_form)
        def primitive(*args, **kwargs):
            for a in args:  # the common case first: Tensors only (a Tensor is never traced)
                if type(a) is not Tensor:
                    break
            else:
                if not kwargs:
                    return array_form(*args)
            if trace.is_traced(args) or (kwargs and trace.is_traced(kwargs.values())):
                return form(*args, **kwargs)
            return array_form(*args, **kwargs)

        primitive.traced_form = form
        return primitive

    return wrap


def _elementwise_form(name: str, scalar_form, differentiable=None):
    """The traced form of an elementwise primitive: its scalar form, lane by lane."""
    return lambda *args: trace.elementwise(name, scalar_form, *args, differentiable=differentiable)


def _not_traceable(name: str):
    """The traced form of a primitive a compiled function cannot contain."""

    def refuse(*args, **kwargs):
        raise trace.CompileError(
            f"compile: '{name}' is not supported inside a compiled function (supported: "
            "elementwise arithmetic and functions, where, clip, maximum, minimum, dot, cross, "
            "norm, normalize, sums over an element's axes, shape operations, gathers)"
        )

    return refuse


# ---------------------------------------------------------------------------------------------
# Helpers
# ---------------------------------------------------------------------------------------------


def _scaled(t: np.ndarray | None, factor: Any) -> np.ndarray | None:
    """A tangent times ``factor``, ``t * factor`` (broadcasting); a zero tangent (None)
    stays None."""
    return None if t is None else kernels.multiply(t, factor)


def _plus(*terms: np.ndarray | None) -> np.ndarray | None:
    """The sum of the tangent terms that are not None (broadcasting); None if all are."""
    total = None
    for t in terms:
        if t is not None:
            total = t if total is None else total + t
    return total


def _or_zeros(ts: tuple, tensors: tuple[Tensor, ...]) -> list[np.ndarray]:
    """The tangents ``ts`` of ``tensors`` as arrays: None (zero) becomes zeros of that
    tensor's shape."""
    return [
        np.zeros(x.shape, x.dtype) if t is None else t for t, x in zip(ts, tensors, strict=True)
    ]


def _pair(a: Any, b: Any) -> tuple[Tensor, Tensor]:
    """Both operands as tensors. A Python number takes the dtype of the other operand, so
    that ``x32 * 2`` stays float32 (NumPy would make the 0-d int64 array win)."""
    if type(a) is Tensor and type(b) is Tensor:
        return a, b
    if isinstance(a, (int, float)) and isinstance(b, Tensor):
        a = np.asarray(a, dtype=np.result_type(b.dtype, np.float32))
    elif isinstance(b, (int, float)) and isinstance(a, Tensor):
        b = np.asarray(b, dtype=np.result_type(a.dtype, np.float32))
    return as_tensor(a), as_tensor(b)


def _broadcast_op(name: str, op, a: Tensor, b: Tensor) -> np.ndarray:
    """``op(a, b)`` on the arrays (a NumPy function, or a kernel equal to one), turning a
    broadcasting failure into a clear message."""
    try:
        return op(a._data, b._data)
    except ValueError:
        raise ValueError(
            f"{name}: cannot broadcast shapes {a.shape} and {b.shape} together"
        ) from None


def _each_reads_the_other(a: Tensor, b: Tensor) -> tuple[Tensor, ...]:
    """What a product-like VJP (multiply, matmul, dot, cross) reads: the gradient of each
    operand is made from the *other* one, so b is needed if a requires grad, and a if b
    does."""
    if a.requires_grad:
        return (b, a) if b.requires_grad else (b,)
    return (a,) if b.requires_grad else ()


def _each_times_the_other(g: np.ndarray, a: Tensor, b: Tensor) -> tuple:
    """The VJP of a * b: ``g * b`` for a and ``g * a`` for b (None for an operand that
    needs no gradient)."""
    return (
        kernels.multiply(g, b._data) if a.requires_grad else None,
        kernels.multiply(g, a._data) if b.requires_grad else None,
    )


def _product_rule(product, a: Tensor, b: Tensor):
    """The JVP of a product that is linear in each operand (multiply, matmul, dot, cross):
    the tangent of ``product(a, b)`` is ``product(ta, b) + product(a, tb)``, a missing
    tangent (None) adding nothing."""

    def jvp(ta, tb):
        return _plus(
            None if ta is None else product(ta, b._data),
            None if tb is None else product(a._data, tb),
        )

    return jvp


def _expand_reduced(g: np.ndarray, shape: tuple[int, ...], axis, keepdims: bool) -> np.ndarray:
    """Give a reduction's output gradient back the reduced axes (as size 1), then broadcast."""
    if axis is not None and not keepdims:
        g = np.expand_dims(g, axis)
    return np.broadcast_to(g, shape)


def _count(shape: tuple[int, ...], axis) -> int:
    """How many elements a reduction over ``axis`` combines."""
    if axis is None:
        return int(np.prod(shape, dtype=np.int64))
    axes = (axis,) if isinstance(axis, int) else axis
    return int(np.prod([shape[a] for a in axes], dtype=np.int64))


def _need_last_axis(name: str, *tensors: Tensor) -> None:
    """Vector primitives work along the last axis: a 0-d tensor has none."""
    if any(t.ndim == 0 for t in tensors):
        shapes = " and ".join(str(t.shape) for t in tensors)
        raise ValueError(f"{name}: needs vectors, shape (..., n), not 0-d; got shape {shapes}")


def _join(name: str, join, tensors, axis: int, mismatch: str) -> tuple[tuple, np.ndarray]:
    """stack's and concatenate's forward: the inputs as tensors, and ``join`` (np.stack or
    np.concatenate) of their arrays along ``axis``. ``mismatch`` says what is wrong if the
    shapes do not fit (formatted with ``shapes``)."""
    tensors = tuple(as_tensor(t) for t in tensors)
    if not tensors:  # nothing has no shape or dtype to give the result
        raise ValueError(f"{name}: needs at least one tensor, got an empty sequence")
    try:
        return tensors, join([t._data for t in tensors], axis=axis)
    except ValueError:
        shapes = [t.shape for t in tensors]
        raise ValueError(f"{name}: " + mismatch.format(shapes=shapes)) from None


# ---------------------------------------------------------------------------------------------
# Arithmetic
# ---------------------------------------------------------------------------------------------


def _add_scalar(a, b):
    return a + b, (lambda d: d, lambda d: d)


@_traces_as(_elementwise_form("add", _add_scalar))
def add(a: Any, b: Any) -> Tensor:
    """a + b with broadcasting.  d/da = 1, d/db = 1."""
    a, b = _pair(a, b)
    out = _broadcast_op("add", kernels.add, a, b)  # a + b
    return record("add", out, (a, b), lambda g: (g, g), jvp=_plus)


def _subtract_scalar(a, b):
    return a - b, (lambda d: d, lambda d: -d)


@_traces_as(_elementwise_form("subtract", _subtract_scalar))
def subtract(a: Any, b: Any) -> Tensor:
    """a - b with broadcasting.  d/da = 1, d/db = -1."""
    a, b = _pair(a, b)
    out = _broadcast_op("subtract", kernels.subtract, a, b)  # a - b
    return record(
        "subtract",
        out,
        (a, b),
        lambda g: (g, -g if b.requires_grad else None),
        jvp=lambda ta, tb: _plus(ta, None if tb is None else -tb),
    )


def _multiply_scalar(a, b):
    return a * b, (lambda d: d * b, lambda d: d * a)


@_traces_as(_elementwise_form("multiply", _multiply_scalar))
def multiply(a: Any, b: Any) -> Tensor:
    """a * b with broadcasting.  d/da = b, d/db = a."""
    a, b = _pair(a, b)
    out = _broadcast_op("multiply", kernels.multiply, a, b)  # a * b
    return record(
        "multiply",
        out,
        (a, b),
        lambda g: _each_times_the_other(g, a, b),
        saves=_each_reads_the_other(a, b),
        jvp=_product_rule(kernels.multiply, a, b),  # ta * b + a * tb
    )


def _divide_scalar(a, b):
    y = a / b
    return y, (lambda d: d / b, lambda d: -(d / b) * y)


@_traces_as(_elementwise_form("divide", _divide_scalar))
def divide(a: Any, b: Any) -> Tensor:
    """a / b with broadcasting.  d/da = 1/b, d/db = -a/b^2 = -out/b."""
    a, b = _pair(a, b)
    out = _broadcast_op("divide", np.divide, a, b)

    def vjp(g):
        ga = g / b._data
        return (ga if a.requires_grad else None, -ga * out if b.requires_grad else None)

    def jvp(ta, tb):  # ta / b - (tb / b) out: the VJP's (and the scalar form's) products
        return _plus(
            None if ta is None else ta / b._data, None if tb is None else -(tb / b._data) * out
        )

    return record("divide", out, (a, b), vjp, saves=(b,), saves_output=b.requires_grad, jvp=jvp)


def _negative_scalar(x):
    return -x, (lambda d: -d,)


@_traces_as(_elementwise_form("negative", _negative_scalar))
def negative(x: Any) -> Tensor:
    """-x."""
    x = as_tensor(x)
    return record("negative", -x._data, (x,), lambda g: (-g,), jvp=lambda t: -t)


# Exponents written as integer constants up to this are products, not pow (``_power_scalar``).
PRODUCT_POWERS = 64


def _power_scalar(a, b):
    n = ir.constant(b)
    if n is not None and float(n).is_integer() and 1 <= n <= PRODUCT_POWERS:
        # A constant integer exponent (a Blinn-Phong lobe's a ** 32): a^(n-1) by repeated
        # squaring, then one more product. LLVM vectorises products but calls pow once per
        # element (in the benchmark's shading, six calls a hit were about a third of the
        # compiled time); the products are within n ulps of pow, with the same inf, NaN
        # and signed zeros. The slope
        # reads a^(n-1) from the same chain; b, a constant, takes no derivative.
        below = ir.integer_power(a, int(n) - 1)
        return below * a, (lambda d: d * b * below, None)
    y = ir.call("pow", a, b)
    b_is_0 = ir.compare("eq", b, 0.0)  # a^0 = 1 is constant (see the array form's docstring)
    a_is_0 = ir.compare("eq", a, 0.0) & (b >= 0.0)  # weight 0 on log(0) = -inf
    return y, (
        lambda d: ir.select(b_is_0, 0.0, d * b * ir.call("pow", a, b - 1.0)),
        lambda d: ir.select(a_is_0, 0.0, d * y * ir.call("log", a)),
    )


@_traces_as(_elementwise_form("power", _power_scalar))
def power(a: Any, b: Any) -> Tensor:
    """a ** b.  d/da = b a^(b-1);  d/db = a^b log(a).

    Values are NumPy's: a negative base gives a real number for an integer-valued b and
    NaN otherwise (with NumPy's "invalid value" warning); 0 ** b is 0 for b > 0, 1 for
    b = 0 and inf for b < 0.

    d/da is b a^(b-1), finite wherever the value has a finite slope: at a = 0 it is 1 for
    b = 1 and 0 for b > 1; for b = 0 it is 0 everywhere (a^0 = 1 is constant; the formula
    would give 0 * 0^-1 = NaN at a = 0); for a < 0 it is real for integer-valued b, NaN
    otherwise (like the value). At a = 0 with 0 < b < 1 it is inf, as in the mathematics.

    d/db is a^b log(a). Where a = 0 and b >= 0 it is defined as 0, as PyTorch does: there
    the weight a^b of log(a) = -inf is 0 (or, for b = 0, the one-sided limit is taken as
    0), and the product would be NaN. For a < 0 it is NaN: log(a) is not real (a^b of a
    negative base is not differentiable in b).
    """
    a, b = _pair(a, b)
    out = _broadcast_op("power", np.power, a, b)

    def zero_where_b_is_0(d):  # a^0 = 1 is constant: 0, where b a^(b-1) may be 0 * inf
        zero_b = b._data == 0
        return np.where(zero_b, 0.0, d) if zero_b.any() else d

    def zero_where_a_is_0(d):  # 0 where a = 0 and b >= 0, where a^b log(a) may be 0 * -inf
        zero_a = (a._data == 0) & (b._data >= 0)
        return np.where(zero_a, 0.0, d) if zero_a.any() else d

    def vjp(g):
        ga = gb = None
        with np.errstate(divide="ignore", invalid="ignore"):  # 0 * inf there: replaced by 0
            if a.requires_grad:
                ga = zero_where_b_is_0(g * b._data * np.power(a._data, b._data - 1))
            if b.requires_grad:
                gb = zero_where_a_is_0(g * out * np.log(a._data))
        return ga, gb

    def jvp(ta, tb):
        with np.errstate(divide="ignore", invalid="ignore"):  # as in the VJP
            slope_a = None if ta is None else ta * b._data * np.power(a._data, b._data - 1)
            slope_b = None if tb is None else tb * out * np.log(a._data)
            return _plus(
                None if ta is None else zero_where_b_is_0(slope_a),
                None if tb is None else zero_where_a_is_0(slope_b),
            )

    saves = (a, b) if a.requires_grad else (a,)
    return record("power", out, (a, b), vjp, saves=saves, saves_output=b.requires_grad, jvp=jvp)


@_traces_as(_not_traceable("matmul"))
def matmul(a: Any, b: Any) -> Tensor:
    """Matrix product a @ b (NumPy semantics, including 1-D vectors and batches).

    For 2-D operands: d/da = g @ b^T, d/db = a^T @ g. Vectors are treated as a row (left)
    or a column (right) and the added axis is removed again from their gradients.
    """
    a, b = _pair(a, b)
    try:
        out = a._data @ b._data
    except ValueError:
        raise ValueError(f"matmul: shapes {a.shape} and {b.shape} are not aligned") from None

    def vjp(g):
        a2 = a._data[None, :] if a.ndim == 1 else a._data
        b2 = b._data[:, None] if b.ndim == 1 else b._data
        # Put the removed vector axes back into g: b's (last) first, then a's, so that a
        # 1-D @ 1-D product (g of shape ()) becomes (1, 1) rather than failing.
        g2 = g
        if b.ndim == 1:
            g2 = np.expand_dims(g2, -1)
        if a.ndim == 1:
            g2 = np.expand_dims(g2, -2)
        ga = gb = None
        if a.requires_grad:
            ga = g2 @ np.swapaxes(b2, -1, -2)
            ga = ga[..., 0, :] if a.ndim == 1 else ga
        if b.requires_grad:
            gb = np.swapaxes(a2, -1, -2) @ g2
            gb = gb[..., 0] if b.ndim == 1 else gb
        return ga, gb

    # JVP: ta @ b + a @ tb, (a + ta) @ (b + tb) to first order; vectors need no special case.
    jvp = _product_rule(np.matmul, a, b)
    return record("matmul", out, (a, b), vjp, saves=_each_reads_the_other(a, b), jvp=jvp)


@_traces_as(_not_traceable("linear"))
def linear(apply, adjoint, x: Any) -> Tensor:
    """y = A x for a constant linear map A given as two functions of arrays: ``apply``
    (x -> A x) and ``adjoint`` (g -> A^T g). A may be anything a function can apply: a
    sparse matrix (``lambda x: L @ x``, ``lambda g: L.T @ g``), or the inverse of a
    prefactored one (``lu.solve`` and ``lambda g: lu.solve(g, trans="T")``), which is how
    a mesh's Large Steps parameterisation solves for its vertices.

    VJP: d/dx = A^T g. JVP: A t (the map is its own derivative).
    """
    x = as_tensor(x)
    y = np.asarray(apply(x._data))
    return record("linear", y, (x,), lambda g: (np.asarray(adjoint(g)),),
                  jvp=lambda t: np.asarray(apply(t)))  # fmt: skip


# ---------------------------------------------------------------------------------------------
# Elementwise functions
# ---------------------------------------------------------------------------------------------


def _exp_scalar(x):
    y = ir.call("exp", x)
    return y, (lambda d: d * y,)


@_traces_as(_elementwise_form("exp", _exp_scalar))
def exp(x: Any) -> Tensor:
    """e^x.  d/dx = e^x (the output itself)."""
    x = as_tensor(x)
    y = np.exp(x._data)
    return record("exp", y, (x,), lambda g: (g * y,), saves_output=True, jvp=lambda t: t * y)


def _elementwise(name: str, x: Tensor, y: np.ndarray, times_slope, reads: str) -> Tensor:
    """Record y = f(x) for an elementwise f, as ``exp`` above does written out.

    The Jacobian of an elementwise function is diagonal, f'(x), so the VJP and the JVP are
    the same map: ``times_slope(d)`` multiplies by f'(x) (d is the gradient g, or the
    tangent t). ``reads`` says what it reads at backward time: "x" or "y" (the output)."""
    return record(
        name, y, (x,), lambda g: (times_slope(g),), saves=(x,) if reads == "x" else (),
        saves_output=reads == "y", jvp=times_slope,
    )  # fmt: skip


def _detach_scalar(x):
    # A new value equal to x (a form must make one), with no slope: LLVM folds the select.
    return ir.select(ir.const(True, "i1"), x, x), (None,)


@_traces_as(lambda x: trace.elementwise("detach", _detach_scalar, x, differentiable=(False,)))
def detach(x: Any) -> Tensor:
    """x's value as a constant: d/dx = 0 (PyTorch's ``detach``, JAX's ``stop_gradient``).

    ``x / detach(x)`` is 1 with the derivative dx / x: how an estimator keeps a factor's
    derivative without its value (a change of measure, ``render.path.gradient.transport``). Inside
    a compiled function it is the same value with no slope."""
    return Tensor(as_tensor(x)._data)


def _floor_scalar(x):
    return ir.call("floor", x), (None,)


@_traces_as(lambda x: trace.elementwise("floor", _floor_scalar, x, differentiable=(False,)))
def floor(x: Any) -> Tensor:
    """The largest integer <= x, elementwise, as floats. A step function: its derivative
    is 0 wherever it exists and is taken as 0 at the steps too, so the result is a
    constant (which cell of a texture a point falls in is a discrete choice of the
    renderer, as visibility is)."""
    return Tensor(np.floor(as_tensor(x)._data))


@_traces_as(trace.to_index)
def to_index(x: Any) -> np.ndarray:
    """Floats that hold integers (a texel's row, say) as an int64 NumPy array of indices
    for a gather; a traced one inside a compiled function. Not differentiable: an index
    is a discrete choice. Outside int64's range the value saturates, and NaN gives 0, as
    the compiled form's LLVM ``fptosi.sat`` does (NumPy's cast would be undefined
    there)."""
    data = as_tensor(x)._data
    safe = np.clip(np.where(np.isnan(data), 0.0, data), -(2.0**63), 2.0**63 - 1024.0)
    return safe.astype(np.int64)


def _log_scalar(x):
    return ir.call("log", x), (lambda d: d / x,)


@_traces_as(_elementwise_form("log", _log_scalar))
def log(x: Any) -> Tensor:
    """Natural log (x > 0).  d/dx = 1/x."""
    x = as_tensor(x)
    return _elementwise("log", x, np.log(x._data), lambda d: d / x._data, reads="x")


def _sqrt_scalar(x):
    y = ir.call("sqrt", x)
    return y, (lambda d: d * 0.5 / y,)


@_traces_as(_elementwise_form("sqrt", _sqrt_scalar))
def sqrt(x: Any) -> Tensor:
    """Square root (x >= 0).  d/dx = 1 / (2 sqrt(x)).

    At x = 0 the derivative is inf, kept as in PyTorch (no clamping: a clamp would hide a
    real singularity). So a gradient g != 0 arriving at sqrt(0) gives x the gradient
    +-inf, and g = 0 gives 0 * inf = NaN (PyTorch: the same). For x < 0 the value is NaN
    (NumPy's warning) and so is the gradient. To take the root of something that may be 0,
    use ``norm`` (subgradient 0 at 0) or the "double where" of ``where``."""
    x = as_tensor(x)
    y = np.sqrt(x._data)
    return _elementwise("sqrt", x, y, lambda d: d * 0.5 / y, reads="y")


def _sin_scalar(x):
    return ir.call("sin", x), (lambda d: d * ir.call("cos", x),)


@_traces_as(_elementwise_form("sin", _sin_scalar))
def sin(x: Any) -> Tensor:
    """sin x.  d/dx = cos x."""
    x = as_tensor(x)
    return _elementwise("sin", x, np.sin(x._data), lambda d: d * np.cos(x._data), reads="x")


def _cos_scalar(x):
    return ir.call("cos", x), (lambda d: -d * ir.call("sin", x),)


@_traces_as(_elementwise_form("cos", _cos_scalar))
def cos(x: Any) -> Tensor:
    """cos x.  d/dx = -sin x."""
    x = as_tensor(x)
    return _elementwise("cos", x, np.cos(x._data), lambda d: -d * np.sin(x._data), reads="x")


def _tan_scalar(x):
    y = ir.call("tan", x)
    return y, (lambda d: d * (1.0 + y * y),)


@_traces_as(_elementwise_form("tan", _tan_scalar))
def tan(x: Any) -> Tensor:
    """tan x.  d/dx = 1 + tan^2 x."""
    x = as_tensor(x)
    y = np.tan(x._data)
    return _elementwise("tan", x, y, lambda d: d * (1.0 + y * y), reads="y")


def _tanh_scalar(x):
    y = ir.call("tanh", x)
    return y, (lambda d: d * (1.0 - y * y),)


@_traces_as(_elementwise_form("tanh", _tanh_scalar))
def tanh(x: Any) -> Tensor:
    """tanh x.  d/dx = 1 - tanh^2 x."""
    x = as_tensor(x)
    y = np.tanh(x._data)
    return _elementwise("tanh", x, y, lambda d: d * (1.0 - y * y), reads="y")


def _abs_scalar(x):
    return ir.call("fabs", x), (lambda d: d * ir.sign(x),)


@_traces_as(_elementwise_form("abs", _abs_scalar))
def abs(x: Any) -> Tensor:
    """|x|.  d/dx = sign(x); at x = 0 we use the subgradient 0."""
    x = as_tensor(x)
    return _elementwise("abs", x, np.abs(x._data), lambda d: d * np.sign(x._data), reads="x")


def _pick_scalar(a_wins, a, b):
    """maximum's and minimum's scalar form: a where ``a_wins``, else b; the derivative
    goes to the input picked (as the array forms' np.where)."""
    return ir.select(a_wins, a, b), (
        lambda d: ir.select(a_wins, d, 0.0),
        lambda d: ir.select(a_wins, 0.0, d),
    )


def _maximum_scalar(a, b):
    return _pick_scalar((a >= b) | ir.is_nan(a), a, b)  # a tie, or a is NaN


@_traces_as(_elementwise_form("maximum", _maximum_scalar))
def maximum(a: Any, b: Any) -> Tensor:
    """Elementwise max(a, b). Subgradient at a tie (a == b): all of it goes to ``a`` (one
    side, not split: PyTorch splits, JAX too; one side keeps the renderer's clamps
    ``maximum(x, 0)`` passing the whole gradient at x = 0).

    NaN propagates as in NumPy (``np.maximum``: the NaN is the result) and the gradient
    goes to the NaN input (to ``a`` if both are NaN), the input the result came from."""
    a, b = _pair(a, b)
    out = _broadcast_op("maximum", np.maximum, a, b)

    def vjp(g):
        a_wins = (a._data >= b._data) | (a._data != a._data)  # a tie, or a is NaN
        return (
            np.where(a_wins, g, 0.0) if a.requires_grad else None,
            np.where(a_wins, 0.0, g) if b.requires_grad else None,
        )

    def jvp(ta, tb):  # the same choice as the VJP: a tie takes a's tangent
        a_wins = (a._data >= b._data) | (a._data != a._data)  # a tie, or a is NaN
        return np.where(a_wins, 0.0 if ta is None else ta, 0.0 if tb is None else tb)

    return record("maximum", out, (a, b), vjp, saves=(a, b), jvp=jvp)


def _minimum_scalar(a, b):
    return _pick_scalar((a <= b) | ir.is_nan(a), a, b)  # a tie, or a is NaN


@_traces_as(_elementwise_form("minimum", _minimum_scalar))
def minimum(a: Any, b: Any) -> Tensor:
    """Elementwise min(a, b). Subgradient at a tie (a == b): all of it goes to ``a``. NaN
    propagates, and its gradient goes to the NaN input, as for ``maximum``."""
    a, b = _pair(a, b)
    out = _broadcast_op("minimum", np.minimum, a, b)

    def vjp(g):
        a_wins = (a._data <= b._data) | (a._data != a._data)  # a tie, or a is NaN
        return (
            np.where(a_wins, g, 0.0) if a.requires_grad else None,
            np.where(a_wins, 0.0, g) if b.requires_grad else None,
        )

    def jvp(ta, tb):  # the same choice as the VJP: a tie takes a's tangent
        a_wins = (a._data <= b._data) | (a._data != a._data)  # a tie, or a is NaN
        return np.where(a_wins, 0.0 if ta is None else ta, 0.0 if tb is None else tb)

    return record("minimum", out, (a, b), vjp, saves=(a, b), jvp=jvp)


def _clip_scalar(x, lo, hi):
    # np.clip(x, lo, hi): min(max(x, lo), hi), NaN propagating; slope 1 where the value
    # is x itself (bounds included), as the array form's VJP
    above = ir.select((x >= lo) | ir.is_nan(x), x, lo)
    y = ir.select((above <= hi) | ir.is_nan(above), above, hi)
    inside = ir.compare("eq", y, x)
    return y, (lambda d: ir.select(inside, d, 0.0), None, None)


@_traces_as(_elementwise_form("clip", _clip_scalar, differentiable=(True, False, False)))
def clip(x: Any, lo: Any, hi: Any) -> Tensor:
    """x limited to [lo, hi] (lo, hi constants). d/dx = 1 inside [lo, hi] (bounds included),
    0 outside."""
    x = as_tensor(x)
    # Python numbers are passed on as they are (not via np.asarray, which would make them
    # int64/float64 arrays) so that NumPy treats them as weak and float32 stays float32.
    lo_v, hi_v = (v._data if isinstance(v, Tensor) else v for v in (lo, hi))
    try:
        out = kernels.clip(x._data, lo_v, hi_v)  # np.clip(x, lo, hi)
    except ValueError:
        raise ValueError(
            f"clip: cannot broadcast x {x.shape}, lo {np.shape(lo_v)} and hi {np.shape(hi_v)}"
        ) from None

    def vjp(g):
        return (kernels.pass_where_equal(g, out, x._data),)  # np.where(out == x, g, 0.0)

    def jvp(t):  # slope 1 wherever the VJP passes the gradient (bounds included)
        return np.where(out == x._data, t, 0.0)

    return record("clip", out, (x,), vjp, saves=(x,), saves_output=True, jvp=jvp)


def _where_scalar(condition, a, b):
    return ir.select(condition, a, b), (
        None,
        lambda d: ir.select(condition, d, 0.0),
        lambda d: ir.select(condition, 0.0, d),
    )


def _where_traced(condition, a, b):
    condition = trace.traced(condition)
    if condition.dtype != np.bool_:
        raise trace.CompileError(f"where: the condition must be boolean, got {condition.dtype}")
    if all(trace.traced(x).dtype.kind == "i" for x in (a, b)):  # indices: no derivative
        return trace.select_integers(condition, a, b)
    return trace.elementwise(
        "where", _where_scalar, condition, a, b, differentiable=(False, True, True)
    )


@_traces_as(_where_traced)
def where(condition: Any, a: Any, b: Any) -> Tensor:
    """Pick a where ``condition`` (a boolean array, not differentiable) is true, else b.

    d/da = g where the condition holds, exactly 0 elsewhere; d/db the other way round. The
    gradient is *selected* with ``np.where``, not multiplied by a 0/1 mask, so a NaN or
    inf in the unselected branch (or in g there) never leaks: 0 * inf would be NaN.

    The trap that remains (as in JAX and PyTorch): ``where(x > 0, sqrt(x), 0.0)`` at
    x < 0 still gives x a NaN gradient. where's VJP hands sqrt a 0, but sqrt's own VJP
    computes 0 * 0.5 / sqrt(x) = 0 * NaN = NaN: the unselected computation was done, and
    its derivative is NaN. The cure is the "double where": make the unselected branch
    compute on a safe value, so that its derivative is finite, then select::

        safe = md.where(x > 0, x, 1.0)              # any value where sqrt is smooth
        y = md.where(x > 0, md.sqrt(safe), 0.0)     # gradient: 0.5/sqrt(x) or exactly 0
    """
    cond = np.asarray(getattr(condition, "data", condition), dtype=bool)
    a, b = _pair(a, b)
    try:
        out = np.where(cond, a._data, b._data)
    except ValueError:
        raise ValueError(
            f"where: cannot broadcast condition {cond.shape}, a {a.shape} and b {b.shape}"
        ) from None

    def vjp(g):
        return (
            np.where(cond, g, 0.0) if a.requires_grad else None,
            np.where(cond, 0.0, g) if b.requires_grad else None,
        )

    def jvp(ta, tb):
        return np.where(cond, 0.0 if ta is None else ta, 0.0 if tb is None else tb)

    return record("where", out, (a, b), vjp, jvp=jvp)


# ---------------------------------------------------------------------------------------------
# Reductions
# ---------------------------------------------------------------------------------------------


@_traces_as(lambda x, axis=None, keepdims=False: trace.reduce_lanes(x, axis, keepdims, add, "sum"))
def sum(x: Any, axis=None, keepdims: bool = False) -> Tensor:
    """Sum over ``axis`` (all axes if None). Every summed element gets the output's gradient."""
    x = as_tensor(x)
    out = np.sum(x._data, axis=axis, keepdims=keepdims)
    return record(
        "sum",
        np.asarray(out),
        (x,),
        lambda g: (_expand_reduced(g, x.shape, axis, keepdims),),
        jvp=lambda t: np.sum(t, axis=axis, keepdims=keepdims),
    )


def _mean_traced(x, axis=None, keepdims=False):
    x = trace.traced(x)
    total = trace.reduce_lanes(x, axis, keepdims, add, "mean")
    count = int(np.prod(x.lane_shape)) // int(np.prod(total.lane_shape))
    return divide(total, float(count))  # np.mean: the sum, then one division


@_traces_as(_mean_traced)
def mean(x: Any, axis=None, keepdims: bool = False) -> Tensor:
    """Mean over ``axis``. Like sum, with the gradient divided by the element count."""
    x = as_tensor(x)
    n = _count(x.shape, axis)
    if n == 0:  # NumPy would warn and return NaN
        raise ValueError(
            f"mean: no elements to average (shape {x.shape}, axis={axis}); "
            "the mean of an empty array is undefined"
        )
    out = np.mean(x._data, axis=axis, keepdims=keepdims)
    return record(
        "mean",
        np.asarray(out),
        (x,),
        lambda g: (_expand_reduced(g / n, x.shape, axis, keepdims),),
        jvp=lambda t: np.mean(t, axis=axis, keepdims=keepdims),
    )


@_traces_as(_not_traceable("mean_squared_error"))
def mean_squared_error(a: Any, b: Any) -> Tensor:
    """mean((a - b)^2) over all elements, a and b of one shape (an image loss: no
    broadcasting).  d/da = 2 (a - b) / n = -d/db.

    The same numbers, bit for bit, as ``mean((a - b) * (a - b))`` built from subtract,
    multiply and mean, fused: on a 512x512 image those allocate five image-sized arrays
    per forward+backward pass, this two (the difference, kept, and the gradient). They
    come from ``kernels`` in reused memory: fresh, image-sized arrays would be page-faulted
    in again on every pass (measured: ~1,800 faults per light-estimation iteration)."""
    a, b = _pair(a, b)
    if a.shape != b.shape:
        raise ValueError(f"mean_squared_error: shapes differ, {a.shape} and {b.shape}")
    if a.size == 0:
        raise ValueError("mean_squared_error: no elements to average (empty arrays)")
    diff = kernels.subtract(a._data, b._data)  # a - b
    n = diff.size
    out = np.asarray(np.mean(kernels.multiply(diff, diff)))  # mean(diff * diff)

    def vjp(g):
        # multiply's VJP for d * d gives (g/n) d + (g/n) d: formed the same way, so that
        # the bits agree. (d (2 g/n) is the same number except where (g/n) d is subnormal:
        # rounding it first, then doubling, differs there.)
        grad = kernels.multiply(diff, g / n)
        kernels.double_in_place(grad)  # grad + grad
        return grad, (-grad if b.requires_grad else None)

    def jvp(ta, tb):
        dt = _plus(ta, None if tb is None else -tb)
        return np.asarray(2.0 * np.sum(diff * dt) / n, dtype=out.dtype)

    return record("mean_squared_error", out, (a, b), vjp, jvp=jvp)


def _max_scalar(*xs):
    """max's scalar form over one element's lanes: the largest (NaN if any is NaN); the
    derivative split equally among the lanes that tie for it (or are NaN), as the array
    form's."""
    y = xs[0]
    for x in xs[1:]:
        y = ir.select((y >= x) | ir.is_nan(y), y, x)
    winners = [ir.compare("eq", x, y) | ir.is_nan(x) for x in xs]
    ties = ir.to_float(winners[0])
    for w in winners[1:]:
        ties = ties + ir.to_float(w)
    # the gradient selected for the winners, as the array form's (a NaN elsewhere stays there)
    return y, tuple((lambda d, w=w: ir.select(w, d / ties, 0.0)) for w in winners)


def _max_traced(x, axis=None, keepdims=False):
    x = trace.traced(x)
    axes = range(x.ndim) if axis is None else ((axis,) if isinstance(axis, int) else axis)
    moved = x
    for a in sorted((a % x.ndim for a in axes), reverse=True):  # reduce one axis at a time
        lane_axis = trace._lane_axis(moved, a, "max")
        parts = [
            trace.with_lanes(moved, np.take(moved.lanes, j, axis=lane_axis))
            for j in range(moved.lanes.shape[lane_axis])
        ]
        moved = trace.elementwise("max", _max_scalar, *parts)
        if keepdims:
            moved = trace.with_lanes(moved, np.expand_dims(moved.lanes, lane_axis))
    return moved


@_traces_as(_max_traced)
def max(x: Any, axis=None, keepdims: bool = False) -> Tensor:
    """Maximum over ``axis``. Subgradient: when several elements tie for the maximum, the
    gradient is split equally among them (so the total is preserved; PyTorch's ``amax``
    and JAX do the same). A NaN in a slice makes its maximum NaN (as ``np.max``), and that
    slice's gradient goes to its NaN elements (split among them if several)."""
    x = as_tensor(x)
    out = np.max(x._data, axis=axis, keepdims=keepdims)

    def vjp(g):
        peak = _expand_reduced(out, x.shape, axis, keepdims)
        winners = (x._data == peak) | (x._data != x._data)  # NaN wins
        ties = np.sum(winners, axis=axis, keepdims=True, dtype=x.dtype)
        share = _expand_reduced(g, x.shape, axis, keepdims) / ties
        return (np.where(winners, share, 0.0),)  # selected: a NaN g reaches the winners only

    def jvp(t):  # the mean of the tied maxima's tangents: the transpose of the equal split
        winners = (x._data == _expand_reduced(out, x.shape, axis, keepdims)) | (x._data != x._data)
        ties = np.sum(winners, axis=axis, keepdims=keepdims)
        return np.sum(np.where(winners, t, 0.0), axis=axis, keepdims=keepdims) / ties

    return record("max", np.asarray(out), (x,), vjp, saves=(x,), saves_output=True, jvp=jvp)


# ---------------------------------------------------------------------------------------------
# Vector algebra along the last axis (fused, hand-written VJPs)
# ---------------------------------------------------------------------------------------------


@_traces_as(lambda a, b: sum(multiply(a, b), axis=-1))  # a0 b0 + a1 b1 + ..., in order
def dot(a: Any, b: Any) -> Tensor:
    """Dot product along the last axis, broadcasting the others: (..., n) . (..., n) -> (...).

    d/da = g[..., None] * b,  d/db = g[..., None] * a.
    """
    a, b = _pair(a, b)
    _need_last_axis("dot", a, b)
    if a.shape[-1:] != b.shape[-1:]:
        raise ValueError(f"dot: last axes differ: {a.shape} and {b.shape}")
    out = _broadcast_op("dot", kernels.dot_last, a, b)  # np.sum(a * b, axis=-1)
    return record(
        "dot",
        out,
        (a, b),
        lambda g: _each_times_the_other(g[..., None], a, b),  # multiply's, g along the last axis
        saves=_each_reads_the_other(a, b),
        jvp=_product_rule(kernels.dot_last, a, b),
    )


def _cross_traced(a, b):
    a, b = trace.traced(a), trace.traced(b)
    if a.full_shape[-1:] != (3,) or b.full_shape[-1:] != (3,):
        shapes = f"{a.full_shape}, {b.full_shape}"
        raise trace.CompileError(f"cross: both inputs need a last axis of size 3, got {shapes}")
    a0, a1, a2 = (a[..., j] for j in range(3))
    b0, b1, b2 = (b[..., j] for j in range(3))
    return stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


@_traces_as(_cross_traced)
def cross(a: Any, b: Any) -> Tensor:
    """Cross product of 3-vectors along the last axis, broadcasting the others.

    For c = a x b and upstream g:  d/da = b x g,  d/db = g x a  (from g.(a x b) = a.(b x g)).
    """
    a, b = _pair(a, b)
    if a.shape[-1:] != (3,) or b.shape[-1:] != (3,):
        raise ValueError(f"cross: both inputs need a last axis of size 3, got {a.shape}, {b.shape}")
    out = _broadcast_op("cross", kernels.cross3, a, b)  # np.cross(a, b)

    def vjp(g):  # b x g and g x a
        return (
            kernels.cross3(b._data, g) if a.requires_grad else None,
            kernels.cross3(g, a._data) if b.requires_grad else None,
        )

    jvp = _product_rule(kernels.cross3, a, b)
    return record("cross", out, (a, b), vjp, saves=_each_reads_the_other(a, b), jvp=jvp)


def _length_scalar(xs):
    """One vector's length, and where it is positive the safe divisor (as in the array
    forms of norm and normalize)."""
    squared = xs[0] * xs[0]
    for x in xs[1:]:
        squared = squared + x * x
    length = ir.call("sqrt", squared)
    positive = length > 0.0
    return length, positive, ir.select(positive, length, 1.0)


def _norm_scalar(xs):
    """norm's scalar form: |x|, with slopes d x_j / |x| (0 at |x| = 0)."""
    length, positive, safe = _length_scalar(xs)
    return [length], [[(lambda d, x=x: ir.select(positive, d / safe, 0.0) * x) for x in xs]]


def _norm_traced(x, axis=-1, keepdims=False):
    x = trace.traced(x)
    if axis not in (-1, x.ndim - 1):
        raise trace.CompileError("norm: inside a compiled function only along the last axis")
    length = trace.along_last_axis("norm", _norm_scalar, x)
    return length if keepdims else trace.with_lanes(length, length.lanes[..., 0])


@_traces_as(_norm_traced)
def norm(x: Any, axis: int = -1, keepdims: bool = False) -> Tensor:
    """Euclidean length along ``axis`` (default last). d/dx = g x / |x|; at |x| = 0 we use
    the subgradient 0 (never NaN)."""
    x = as_tensor(x)
    _need_last_axis("norm", x)
    length = np.sqrt(np.sum(x._data * x._data, axis=axis, keepdims=True))
    out = length if keepdims else np.squeeze(length, axis=axis)

    def vjp(g):
        if not keepdims:
            g = np.expand_dims(g, axis)
        safe = np.where(length > 0, length, 1.0)
        return (np.where(length > 0, g / safe, 0.0) * x._data,)

    def jvp(t):  # (x . t) / |x|, and 0 at |x| = 0 as in the VJP (NaN for a NaN x, too)
        safe = np.where(length > 0, length, 1.0)
        along = np.sum(x._data * t, axis=axis, keepdims=True)
        d = np.where(length > 0, along / safe, along * 0.0)
        return d if keepdims else np.squeeze(d, axis=axis)

    # ``out`` is ``length`` or a view of it: the VJP reads the output.
    return record("norm", out, (x,), vjp, saves=(x,), saves_output=True, jvp=jvp)


def _normalize_scalar(xs):
    """normalize's scalar form: y = x / |x| (0 at 0), and the tape's slope
    d -> d (I - y y^T) / |x| as a matrix of lanes."""
    _, positive, safe = _length_scalar(xs)
    inv = ir.select(positive, 1.0 / safe, 0.0)
    ys = [x * inv for x in xs]

    def slope(i, j):
        if i == j:
            return lambda d: (d - d * ys[i] * ys[j]) * inv
        return lambda d: (-(d * ys[i] * ys[j])) * inv

    return ys, [[slope(i, j) for j in range(len(xs))] for i in range(len(xs))]


@_traces_as(lambda x: trace.along_last_axis("normalize", _normalize_scalar, x))
def normalize(x: Any) -> Tensor:
    """x / |x| along the last axis. The zero vector maps to the zero vector, with zero
    gradient (and zero tangent): never NaN. (x / |x| is undefined at 0; PyTorch's
    ``F.normalize`` makes the same choice by dividing by max(|x|, eps).)

    With y = x/|x|:  d/dx = (g - y (y . g)) / |x|  (the part of g orthogonal to y, scaled).
    """
    x = as_tensor(x)
    _need_last_axis("normalize", x)
    # x . x, np.sum(x * x, axis=-1): a fresh array, so its root can go in place
    squared = kernels.dot_last(x._data, x._data)
    length = np.sqrt(squared, out=squared if isinstance(squared, np.ndarray) else None)[..., None]
    inv = np.divide(1.0, length, out=np.zeros_like(length), where=length > 0)
    y = kernels.multiply(x._data, inv)  # x * inv

    def project(g):  # the Jacobian (I - y y^T) / |x| is symmetric: the VJP's g and the JVP's t
        return kernels.project_out(y, g, inv)  # (g - y * (y . g)) * inv

    return record("normalize", y, (x,), lambda g: (project(g),), saves_output=True, jvp=project)


# ---------------------------------------------------------------------------------------------
# Shape manipulation
# ---------------------------------------------------------------------------------------------


@_traces_as(trace.reshape)
def reshape(x: Any, shape) -> Tensor:
    """Same values, new shape. The gradient is reshaped back."""
    x = as_tensor(x)
    try:
        out = x._data.reshape(shape)
    except ValueError:
        raise ValueError(f"reshape: cannot reshape {x.shape} into {shape}") from None
    return record(
        "reshape", out, (x,), lambda g: (g.reshape(x.shape),), view_of=x,
        jvp=lambda t: t.reshape(out.shape),
    )  # fmt: skip


@_traces_as(trace.transpose)
def transpose(x: Any, axes=None) -> Tensor:
    """Permute axes (reverse them if ``axes`` is None). The gradient is permuted back."""
    x = as_tensor(x)
    out = np.transpose(x._data, axes)
    # The inverse permutation; negative axes are made positive first (argsort of (-1, 0, 1)
    # would otherwise give the identity).
    inverse = None if axes is None else np.argsort([a % x.ndim for a in axes])
    return record(
        "transpose", out, (x,), lambda g: (np.transpose(g, inverse),), view_of=x,
        jvp=lambda t: np.transpose(t, axes),
    )  # fmt: skip


@_traces_as(trace.broadcast_to)
def broadcast_to(x: Any, shape) -> Tensor:
    """Broadcast to ``shape``; backward sums the repeated axes away."""
    x = as_tensor(x)
    shape = (shape,) if isinstance(shape, int) else tuple(shape)
    try:
        out = np.broadcast_to(x._data, shape)
    except ValueError:
        raise ValueError(f"broadcast_to: cannot broadcast {x.shape} to {shape}") from None
    return record(
        "broadcast_to", out, (x,), lambda g: (g,), view_of=x,
        jvp=lambda t: np.broadcast_to(t, shape),
    )  # fmt: skip


@_traces_as(lambda tensors, axis=0: trace.join(np.stack, tensors, axis, "stack"))
def stack(tensors, axis: int = 0) -> Tensor:
    """Stack equal-shaped tensors along a new axis; the gradient is split back into slices."""
    mismatch = "all inputs need the same shape, got {shapes}"
    tensors, out = _join("stack", np.stack, tensors, axis, mismatch)

    def vjp(g):
        return tuple(np.moveaxis(g, axis, 0))

    def jvp(*ts):  # the tangents stacked as the values were
        return np.stack(_or_zeros(ts, tensors), axis=axis)

    return record("stack", out, tensors, vjp, jvp=jvp)


@_traces_as(lambda tensors, axis=0: trace.join(np.concatenate, tensors, axis, "concatenate"))
def concatenate(tensors, axis: int = 0) -> Tensor:
    """Join tensors along an existing axis; the gradient is cut back into the pieces."""
    mismatch = "shapes {shapes} do not match off axis " + str(axis)
    tensors, out = _join("concatenate", np.concatenate, tensors, axis, mismatch)
    cuts = np.cumsum([t.shape[axis] for t in tensors])[:-1]

    def vjp(g):
        return tuple(np.split(g, cuts, axis=axis))

    def jvp(*ts):  # the tangents joined as the values were
        return np.concatenate(_or_zeros(ts, tensors), axis=axis)

    return record("concatenate", out, tensors, vjp, jvp=jvp)


# ---------------------------------------------------------------------------------------------
# Indexing: gather and scatter
# ---------------------------------------------------------------------------------------------


def _is_row_gather(index: Any) -> bool:
    """True for x[int_array] with a 1-D integer array: the renderer's hot path."""
    return isinstance(index, np.ndarray) and index.ndim == 1 and index.dtype.kind in "iu"


def _has_integer_array(index: Any) -> bool:
    """True if the index contains an integer array or list (repeats possible)."""
    parts = index if isinstance(index, tuple) else (index,)
    for p in parts:
        if isinstance(p, list):
            p = np.asarray(p)
        if isinstance(p, np.ndarray) and p.dtype.kind in "iu":
            return True
    return False


@_traces_as(lambda x, index: trace.getitem(trace.traced(x), index))
def getitem(x: Any, index: Any) -> Tensor:
    """x[index] for basic slices, integer-array gathers and boolean masks.

    VJP: scatter the gradient back to where the values came from, *adding* where an index
    repeats (x[[0, 0]] uses x[0] twice, so it gets both gradients).
    """
    x = as_tensor(x)
    if isinstance(index, Tensor):
        index = index._data
    if isinstance(index, tuple):
        index = tuple(i._data if isinstance(i, Tensor) else i for i in index)
    row_gather = _is_row_gather(index)
    try:
        out = kernels.gather_rows(x._data, index) if row_gather and x.ndim else x._data[index]
    except IndexError as error:  # out of range, or a float index: name the operation
        raise IndexError(f"getitem: {error} (indexing a tensor of shape {x.shape})") from None

    if row_gather:

        def vjp(g):
            negative = index.size and index.min() < 0  # one pass; mapping them takes three
            rows = np.where(index < 0, index + x.shape[0], index) if negative else index
            return (kernels.scatter_add_rows(rows, g, x.shape[0]),)  # np.add.at into zeros

    elif _has_integer_array(index):

        def vjp(g):
            gx = np.zeros(x.shape, dtype=g.dtype)
            np.add.at(gx, index, g)
            return (gx,)

    else:  # slices and masks never select an element twice: plain assignment is enough

        def vjp(g):
            gx = np.zeros(x.shape, dtype=g.dtype)
            gx[index] = g
            return (gx,)

    def jvp(t):  # the tangent is gathered like the values
        return kernels.gather_rows(t, index) if row_gather else t[index]

    # Basic slices give a view of x; gathers and masks give a copy (record tells them apart).
    return record("getitem", np.asarray(out), (x,), vjp, view_of=x, jvp=jvp)


@_traces_as(_not_traceable("scatter_add"))
def scatter_add(values: Any, index: Any, size: int) -> Tensor:
    """out = zeros((size, ...)); out[index[i]] += values[i]  (rows; repeats accumulate).

    The inverse of a row gather: a renderer uses it to put per-hit colours into the image.
    VJP: each value receives the gradient of the row it was added to, d/dvalues = g[index].
    """
    values = as_tensor(values)
    index = np.asarray(getattr(index, "data", index))
    if index.ndim != 1 or index.dtype.kind not in "iu" or len(index) != len(values):
        raise ValueError(
            f"scatter_add: index must be a 1-D integer array of length {len(values)}, "
            f"got shape {index.shape} dtype {index.dtype}"
        )
    if index.size and (index.min() < 0 or index.max() >= size):
        raise ValueError(f"scatter_add: indices must lie in [0, {size}), got {index.min()}..")
    out = kernels.scatter_add_rows(index, values._data, size)
    return record(
        "scatter_add", out, (values,), lambda g: (kernels.gather_rows(g, index),),
        jvp=lambda t: kernels.scatter_add_rows(index, t, size),
    )  # fmt: skip
