"""Four slab tests at once: the wide BVH's box test as LLVM vector instructions (Numba
``@intrinsic``).

A node of the 4-wide tree (``render.trace.wide``) keeps each coordinate of its four children's
boxes side by side, so one load gives the four children's low x, the next their low y, and
so on. :func:`enter4` loads those six rows of four float32, widens them to float64 and runs
the slab test of one ray on all four boxes with vector instructions (on AVX, one instruction
a step for all four): the same arithmetic as the scalar ``intersect.enter_slot``, to which
``tests/render/trace/test_wide.py`` ties it, bit for bit.

Why by hand: Numba turns off LLVM's SLP vectoriser, the pass that would find these four
independent computations and pack them (``NUMBA_SLP_VECTORIZE`` is a process-wide setting,
and turning it on would recompile every kernel of every library in the process); its loop
vectoriser skips a loop of four. The box test decides only which leaves a ray opens, never
a hit's value: this is discrete work, not mathematics that gradients flow through.
"""

from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.core.errors import TypingError
from numba.extending import intrinsic

from render.trace.wide import WIDTH

_F64x4 = ir.VectorType(ir.DoubleType(), WIDTH)
_F32x4 = ir.VectorType(ir.FloatType(), WIDTH)
_I32 = ir.IntType(32)


def _splat(builder: ir.IRBuilder, x: ir.Value) -> ir.Value:
    """The scalar double ``x`` in all four lanes."""
    v = builder.insert_element(ir.Constant(_F64x4, ir.Undefined), x, ir.Constant(_I32, 0))
    return builder.shuffle_vector(v, v, ir.Constant(ir.VectorType(_I32, WIDTH), [0] * WIDTH))


def _min(builder: ir.IRBuilder, a: ir.Value, b: ir.Value) -> ir.Value:
    """Lane by lane the smaller of ``a`` and ``b`` (either where they are equal; no slab
    distance is NaN: ``intersect.safe_inverse``)."""
    return builder.select(builder.fcmp_ordered("<", b, a), b, a)


def _max(builder: ir.IRBuilder, a: ir.Value, b: ir.Value) -> ir.Value:
    """Lane by lane the larger of ``a`` and ``b``."""
    return builder.select(builder.fcmp_ordered(">", b, a), b, a)


@intrinsic
def enter4(typingctx, boxes, w, origin, inverse, t_min, t_far):
    """Entry distances of one ray into the four boxes of wide node ``w`` of ``boxes`` (W,
    32) float32, C-contiguous (its columns 0 to 23, ``render.trace.wide``): a tuple of
    four float64, each ``max(t_min, t_enter)`` where the ray overlaps that box within
    ``[t_min, t_far]`` and ``inf`` where it does not (an empty slot: always). ``origin``
    and ``inverse`` are the ray's (x, y, z) origin and inverse direction, float64."""
    if not (
        isinstance(boxes, types.Array)
        and boxes.dtype == types.float32
        and boxes.ndim == 2
        and boxes.layout == "C"
    ):
        raise TypingError(f"enter4: boxes must be a C-contiguous 2-d float32 array, got {boxes}")
    f64 = types.float64
    triple = types.UniTuple(f64, 3)
    signature = types.UniTuple(f64, WIDTH)(boxes, types.intp, triple, triple, f64, f64)

    def codegen(context, builder, sig, args):
        boxes_v, w_v, origin_v, inverse_v, t_min_v, t_far_v = args
        array = context.make_array(sig.args[0])(context, builder, boxes_v)
        # Row w starts w * (the row stride, in bytes) past the data pointer.
        offset = builder.mul(w_v, builder.extract_value(array.strides, 0))
        start = builder.gep(builder.bitcast(array.data, ir.IntType(8).as_pointer()), [offset])
        row = builder.bitcast(start, ir.FloatType().as_pointer())

        def column(c: int) -> ir.Value:
            """The four float32 at column ``c`` of the row, widened to float64."""
            at = builder.gep(row, [ir.Constant(ir.IntType(64), c)])
            return builder.fpext(builder.load(builder.bitcast(at, _F32x4.as_pointer()), align=4),
                                 _F64x4)  # fmt: skip

        t_enter = _splat(builder, t_min_v)
        t_leave = _splat(builder, t_far_v)
        for axis in range(3):
            o = _splat(builder, builder.extract_value(origin_v, axis))
            inv = _splat(builder, builder.extract_value(inverse_v, axis))
            t0 = builder.fmul(builder.fsub(column(axis * WIDTH), o), inv)
            t1 = builder.fmul(builder.fsub(column((3 + axis) * WIDTH), o), inv)
            t_enter = _max(builder, t_enter, _min(builder, t0, t1))
            t_leave = _min(builder, t_leave, _max(builder, t0, t1))
        missed = _splat(builder, ir.Constant(ir.DoubleType(), float("inf")))
        entry = builder.select(builder.fcmp_ordered("<=", t_enter, t_leave), t_enter, missed)
        lanes = [builder.extract_element(entry, ir.Constant(_I32, k)) for k in range(WIDTH)]
        return context.make_tuple(builder, sig.return_type, lanes)

    return signature, codegen
