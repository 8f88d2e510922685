"""Eight float32 lanes as one value in Numba code: `Float32x8`, an LLVM vector that stays in a register.

The rasterizer's kernels walk a strip of eight lanes down every row of a primitive's box, carrying
the strip's values from row to row. Written over arrays, LLVM must keep such state in memory (it
cannot prove that the arrays do not overlap the image being written); as values of this type it
lives in registers, and each operation below is one vector instruction (on AVX2). Arithmetic
carries LLVM's fast-math flags, as the kernels that use it compile with fast-math.

Supported: `load`/`store` of eight consecutive float32 of a 1D array, `splat` (one value in every
lane), `ramp` (start, start + 1, ..., start + 7), `+`, `-` and `*` between vectors, and `where_between`
(a mask on lane positions).
"""

from __future__ import annotations

import operator

from llvmlite import ir
from numba import types
from numba.core.errors import TypingError
from numba.extending import intrinsic, models, overload, register_model

WIDTH = 8
_VECTOR = ir.VectorType(ir.FloatType(), WIDTH)
_INDEX = ir.IntType(32)
_FAST = ("fast",)


class Float32x8(types.Type):
    """Numba type of eight float32 lanes (an LLVM <8 x float>)."""

    def __init__(self):
        super().__init__(name="Float32x8")


float32x8 = Float32x8()


@register_model(Float32x8)
class _Float32x8Model(models.PrimitiveModel):
    def __init__(self, dmm, fe_type):
        super().__init__(dmm, fe_type, _VECTOR)


def _address(context, builder, array_type, array, start):
    """Pointer to array[start] as a pointer to eight float32 lanes."""
    data = context.make_array(array_type)(context, builder, array).data
    return builder.bitcast(builder.gep(data, [start]), _VECTOR.as_pointer())


def _check_float32_array(array) -> None:
    if not (isinstance(array, types.Array) and array.dtype == types.float32 and array.ndim == 1
            and array.layout in "CF"):
        raise TypingError(f"eight-lane loads and stores take a contiguous 1D float32 array, not {array}")


@intrinsic
def load(typingctx, array, start):
    """array[start:start + 8] as one vector (no bounds check)."""
    _check_float32_array(array)

    def codegen(context, builder, signature, args):
        return builder.load(_address(context, builder, signature.args[0], args[0], args[1]), align=4)

    return float32x8(array, types.intp), codegen


@intrinsic
def store(typingctx, array, start, value):
    """array[start:start + 8] = value (no bounds check)."""
    _check_float32_array(array)

    def codegen(context, builder, signature, args):
        builder.store(args[2], _address(context, builder, signature.args[0], args[0], args[1]), align=4)
        return context.get_dummy_value()

    return types.none(array, types.intp, float32x8), codegen


def _broadcast(context, builder, value, value_type):
    scalar = context.cast(builder, value, value_type, types.float32)
    single = builder.insert_element(ir.Constant(_VECTOR, ir.Undefined), scalar, ir.Constant(_INDEX, 0))
    return builder.shuffle_vector(single, single, ir.Constant(ir.VectorType(_INDEX, WIDTH), [0] * WIDTH))


@intrinsic
def splat(typingctx, value):
    """The number `value` (converted to float32) in every lane."""
    if not isinstance(value, (types.Float, types.Integer)):
        raise TypingError(f"splat takes a number, not {value}")

    def codegen(context, builder, signature, args):
        return _broadcast(context, builder, args[0], signature.args[0])

    return float32x8(value), codegen


@intrinsic
def ramp(typingctx, start):
    """(start, start + 1, ..., start + 7) in float32: the lanes' positions."""
    if not isinstance(start, (types.Float, types.Integer)):
        raise TypingError(f"ramp takes a number, not {start}")

    def codegen(context, builder, signature, args):
        first = _broadcast(context, builder, args[0], signature.args[0])
        return builder.fadd(first, ir.Constant(_VECTOR, [float(i) for i in range(WIDTH)]), flags=_FAST)

    return float32x8(start), codegen


@intrinsic
def where_between(typingctx, position, low, high, value):
    """value in the lanes where low ≤ position < high, 0 in the others."""
    def codegen(context, builder, signature, args):
        position, low, high, value = args
        inside = builder.and_(builder.fcmp_ordered(">=", position, low), builder.fcmp_ordered("<", position, high))
        return builder.select(inside, value, ir.Constant(_VECTOR, [0.0] * WIDTH))

    return float32x8(float32x8, float32x8, float32x8, float32x8), codegen


def _lanewise(instruction: str):
    @intrinsic
    def operation(typingctx, left, right):
        def codegen(context, builder, signature, args):
            return getattr(builder, instruction)(args[0], args[1], flags=_FAST)

        return float32x8(float32x8, float32x8), codegen

    def implementation(left, right):
        if left is float32x8 and right is float32x8:
            return lambda left, right: operation(left, right)

    return implementation


overload(operator.add)(_lanewise("fadd"))
overload(operator.sub)(_lanewise("fsub"))
overload(operator.mul)(_lanewise("fmul"))
