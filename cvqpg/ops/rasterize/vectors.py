"""Explicit SIMD values in Numba code: `Float32x8` and `Float64x4`, LLVM vectors that stay in a register.

The rasterizer's kernels walk a strip of eight lanes down every row of a primitive's box, carrying
the strip's values from row to row, and walk a primitive's channels along its first row four at a
time. Written over arrays, LLVM must keep such state in memory (it cannot prove that the arrays do
not overlap the image being written); as values of these types it lives in registers, and each
operation below is one vector instruction (on AVX2). Arithmetic carries LLVM's fast-math flags, as
the kernels that use it compile with fast-math.

Supported: `load`/`store` of consecutive values of a contiguous 1D array (eight float32 or four
float64, by the array's type), `load_float64` and `store_float32` (four float32 of an array widened
to a Float64x4, and back, rounded), `splat` and `splat_float64` (one value in every lane), `ramp`
(start, start + 1, ..., start + 7, float32), `+`, `-` and `*` between vectors of one type, and
`where_between` (a mask on float32 lane positions).
"""

from __future__ import annotations

import operator

from llvmlite import ir
from numba import types
from numba.core.errors import TypingError
from numba.extending import intrinsic, models, overload, register_model

WIDTH = 8  # float32 lanes of a Float32x8
WIDTH_FLOAT64 = 4  # float64 lanes of a Float64x4
_INDEX = ir.IntType(32)
_FAST = ("fast",)


class Vector(types.Type):
    """Numba type of `width` lanes of `dtype` (an LLVM vector)."""

    def __init__(self, name: str, dtype: types.Float, width: int, element: ir.Type):
        self.dtype, self.width, self.ir_type = dtype, width, ir.VectorType(element, width)
        super().__init__(name=name)


float32x8 = Vector("Float32x8", types.float32, WIDTH, ir.FloatType())
float64x4 = Vector("Float64x4", types.float64, WIDTH_FLOAT64, ir.DoubleType())
_BY_DTYPE = {types.float32: float32x8, types.float64: float64x4}


@register_model(Vector)
class _VectorModel(models.PrimitiveModel):
    def __init__(self, dmm, fe_type):
        super().__init__(dmm, fe_type, fe_type.ir_type)


_FLOAT32X4 = ir.VectorType(ir.FloatType(), WIDTH_FLOAT64)  # what a Float64x4 is stored as in float32


def _address(context, builder, array_type, array, start, vector_type: ir.VectorType):
    """Pointer to array[start] as a pointer to an LLVM vector."""
    data = context.make_array(array_type)(context, builder, array).data
    return builder.bitcast(builder.gep(data, [start]), vector_type.as_pointer())


def _vector_of(array) -> Vector:
    """The vector type that loads from and stores to `array` (a contiguous 1D float32 or float64 array)."""
    if not (isinstance(array, types.Array) and array.dtype in _BY_DTYPE and array.ndim == 1
            and array.layout in "CF"):
        raise TypingError(f"vector loads and stores take a contiguous 1D float32 or float64 array, not {array}")
    return _BY_DTYPE[array.dtype]


@intrinsic
def load(typingctx, array, start):
    """array[start:start + 8] (float32) or array[start:start + 4] (float64) as one vector (no bounds check)."""
    vector = _vector_of(array)

    def codegen(context, builder, signature, args):
        return builder.load(_address(context, builder, signature.args[0], args[0], args[1], vector.ir_type),
                            align=vector.dtype.bitwidth // 8)

    return vector(array, types.intp), codegen


@intrinsic
def store(typingctx, array, start, value):
    """array[start:start + width] = value (no bounds check), `value` of the array's vector type."""
    vector = _vector_of(array)
    if value is not vector:
        raise TypingError(f"a {vector} stores into {array}, not a {value}")

    def codegen(context, builder, signature, args):
        builder.store(args[2], _address(context, builder, signature.args[0], args[0], args[1], vector.ir_type),
                      align=vector.dtype.bitwidth // 8)
        return context.get_dummy_value()

    return types.none(array, types.intp, value), codegen


@intrinsic
def store_float32(typingctx, array, start, value):
    """array[start:start + 4] = value rounded to float32 (no bounds check), for a Float64x4 `value` and
    a float32 `array`."""
    if _vector_of(array) is not float32x8 or value is not float64x4:
        raise TypingError(f"store_float32 rounds a Float64x4 into a float32 array, not a {value} into {array}")

    def codegen(context, builder, signature, args):
        pointer = _address(context, builder, signature.args[0], args[0], args[1], _FLOAT32X4)
        builder.store(builder.fptrunc(args[2], _FLOAT32X4), pointer, align=4)
        return context.get_dummy_value()

    return types.none(array, types.intp, float64x4), codegen


@intrinsic
def load_float64(typingctx, array, start):
    """array[start:start + 4] of a float32 `array`, widened to a Float64x4 (no bounds check)."""
    if _vector_of(array) is not float32x8:
        raise TypingError(f"load_float64 widens four values of a float32 array, not of {array}")

    def codegen(context, builder, signature, args):
        pointer = _address(context, builder, signature.args[0], args[0], args[1], _FLOAT32X4)
        return builder.fpext(builder.load(pointer, align=4), float64x4.ir_type)

    return float64x4(array, types.intp), codegen


def _broadcast(context, builder, value, value_type, vector: Vector = float32x8):
    scalar = context.cast(builder, value, value_type, vector.dtype)
    single = builder.insert_element(ir.Constant(vector.ir_type, ir.Undefined), scalar, ir.Constant(_INDEX, 0))
    every = ir.Constant(ir.VectorType(_INDEX, vector.width), [0] * vector.width)
    return builder.shuffle_vector(single, single, every)


def _check_number(name: str, value) -> None:
    if not isinstance(value, (types.Float, types.Integer)):
        raise TypingError(f"{name} takes a number, not {value}")


def _splat_codegen(vector: Vector):
    def codegen(context, builder, signature, args):
        return _broadcast(context, builder, args[0], signature.args[0], vector)

    return codegen


@intrinsic
def splat(typingctx, value):
    """The number `value` (converted to float32) in all eight lanes."""
    _check_number("splat", value)
    return float32x8(value), _splat_codegen(float32x8)


@intrinsic
def splat_float64(typingctx, value):
    """The number `value` (as float64) in all four lanes of a Float64x4."""
    _check_number("splat_float64", value)
    return float64x4(value), _splat_codegen(float64x4)


@intrinsic
def ramp(typingctx, start):
    """(start, start + 1, ..., start + 7) in float32: the lanes' positions."""
    _check_number("ramp", start)

    def codegen(context, builder, signature, args):
        first = _broadcast(context, builder, args[0], signature.args[0])
        return builder.fadd(first, ir.Constant(float32x8.ir_type, [float(i) for i in range(WIDTH)]), flags=_FAST)

    return float32x8(start), codegen


@intrinsic
def where_between(typingctx, position, low, high, value):
    """value in the lanes where low ≤ position < high, 0 in the others (Float32x8)."""
    def codegen(context, builder, signature, args):
        position, low, high, value = args
        inside = builder.and_(builder.fcmp_ordered(">=", position, low), builder.fcmp_ordered("<", position, high))
        return builder.select(inside, value, ir.Constant(float32x8.ir_type, [0.0] * WIDTH))

    return float32x8(float32x8, float32x8, float32x8, float32x8), codegen


def _lanewise(instruction: str):
    @intrinsic
    def operation(typingctx, left, right):
        def codegen(context, builder, signature, args):
            return getattr(builder, instruction)(args[0], args[1], flags=_FAST)

        return left(left, right), codegen

    def implementation(left, right):
        if isinstance(left, Vector) and left is right:
            return lambda left, right: operation(left, right)

    return implementation


overload(operator.add)(_lanewise("fadd"))
overload(operator.sub)(_lanewise("fsub"))
overload(operator.mul)(_lanewise("fmul"))
