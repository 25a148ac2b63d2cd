"""An 8 x float64 SIMD vector as a numba type, `Vec` (an LLVM <8 x double> value), and
lane-generic operations: code written with them and the operators (+, -, *, /, +=, -=, >, >=,
<=; a Vec with a scalar broadcasts the scalar) compiles for a pack of width 1 (one sample, plain
floats) and of width LANES (Vecs, each operation one vector instruction), chosen by a prototype
value `proto` (0.0 or a Vec) the caller passes down: width, fill, load, store (flat entries of
C-contiguous float64 arrays), mask, select, maximum, sqrt, absolute, multiply_add, nan_mask,
lanes_set, lane_value. A lane mask is 1.0 / 0.0 per lane (a float at width 1; `mask` turns a
comparison's bool into one). The solid's element physics (element.py), its solver
(solid/packed.py) and the banded Cholesky (banded.py) are written once this way.

numba does not vectorise such 8-wide lane loops by itself (its SLP vectoriser is off and the
loop vectoriser judges 8 trips not worth it), hence a type of its own.
"""

from __future__ import annotations

import math
import operator

import numba
from llvmlite import ir
from numba.core import cgutils, types
from numba.extending import intrinsic, models, overload, register_model

LANES = 8
_VEC = ir.VectorType(ir.DoubleType(), LANES)
_I32 = ir.IntType(32)


class Vec(types.Type):
    """numba type of an 8 x float64 SIMD value (LLVM <8 x double>)."""

    def __init__(self):
        super().__init__(name="Vec")


vec = Vec()


@register_model(Vec)
class _VecModel(models.PrimitiveModel):
    def __init__(self, dmm, fe_type):
        super().__init__(dmm, fe_type, _VEC)


def _is_f64_array(a) -> bool:
    return isinstance(a, types.Array) and a.dtype == types.float64 and a.layout == "C"


def _element_pointer(context, builder, array_type, array, index_type, index, vector=True):
    """Pointer to flat element `index` of a C-contiguous array, as a <8 x double>* (`vector`)
    or a double*."""
    data = context.make_array(array_type)(context, builder, array).data
    offset = context.cast(builder, index, index_type, types.intp)
    pointer = builder.gep(data, [offset])
    return builder.bitcast(pointer, _VEC.as_pointer()) if vector else pointer


@intrinsic
def splat(typingctx, x):
    """A Vec from a scalar (every lane x) or a Vec (itself)."""
    if isinstance(x, Vec):
        return vec(x), lambda context, builder, sig, args: args[0]
    if isinstance(x, (types.Float, types.Integer, types.Boolean)):
        def codegen(context, builder, sig, args):
            value = context.cast(builder, args[0], sig.args[0], types.float64)
            one = builder.insert_element(ir.Constant(_VEC, ir.Undefined), value, ir.Constant(_I32, 0))
            return builder.shuffle_vector(one, one, ir.Constant(ir.VectorType(_I32, LANES), [0] * LANES))
        return vec(x), codegen
    return None


@intrinsic
def _lane(typingctx, v, k):
    """Lane k of v, a float."""
    if isinstance(v, Vec) and isinstance(k, types.Integer):
        def codegen(context, builder, sig, args):
            return builder.extract_element(args[0], builder.trunc(context.cast(builder, args[1], sig.args[1],
                                                                               types.int64), _I32))
        return types.float64(v, k), codegen
    return None


def _binary(a, b, emit):
    if isinstance(a, Vec) and isinstance(b, Vec):
        return vec(a, b), lambda context, builder, sig, args: emit(builder, *args)
    return None


@intrinsic
def _add(typingctx, a, b):
    return _binary(a, b, lambda builder, x, y: builder.fadd(x, y, flags=("contract",)))


@intrinsic
def _sub(typingctx, a, b):
    return _binary(a, b, lambda builder, x, y: builder.fsub(x, y, flags=("contract",)))


@intrinsic
def _mul(typingctx, a, b):
    return _binary(a, b, lambda builder, x, y: builder.fmul(x, y, flags=("contract",)))


@intrinsic
def _div(typingctx, a, b):
    return _binary(a, b, lambda builder, x, y: builder.fdiv(x, y))


def _llvm_call(builder, name, *args):
    """Call the LLVM intrinsic `name` (e.g. llvm.sqrt) on <8 x double> arguments."""
    function = cgutils.get_or_insert_function(builder.module, ir.FunctionType(_VEC, [_VEC] * len(args)),
                                              f"{name}.v{LANES}f64")
    return builder.call(function, args)


@intrinsic
def _max(typingctx, a, b):
    return _binary(a, b, lambda builder, x, y: _llvm_call(builder, "llvm.maxnum", x, y))


@intrinsic
def _greater(typingctx, a, b):
    return _binary(a, b, lambda builder, x, y: builder.uitofp(builder.fcmp_ordered(">", x, y), _VEC))


@intrinsic
def _greater_equal(typingctx, a, b):
    return _binary(a, b, lambda builder, x, y: builder.uitofp(builder.fcmp_ordered(">=", x, y), _VEC))


@intrinsic
def _vsqrt(typingctx, a):
    """sqrt per lane."""
    if isinstance(a, Vec):
        return vec(a), lambda context, builder, sig, args: _llvm_call(builder, "llvm.sqrt", args[0])
    return None


@intrinsic
def _isnan(typingctx, a):
    """Mask: 1.0 where the lane is NaN, else 0.0."""
    if isinstance(a, Vec):
        def codegen(context, builder, sig, args):
            return builder.uitofp(builder.fcmp_unordered("uno", args[0], args[0]), _VEC)
        return vec(a), codegen
    return None


@intrinsic
def _fma(typingctx, a, b, c):
    if isinstance(a, Vec) and isinstance(b, Vec) and isinstance(c, Vec):
        return vec(a, b, c), lambda context, builder, sig, args: _llvm_call(builder, "llvm.fma", *args)
    return None


@intrinsic
def _where(typingctx, m, a, b):
    if isinstance(m, Vec) and isinstance(a, Vec) and isinstance(b, Vec):
        def codegen(context, builder, sig, args):
            chosen = builder.fcmp_ordered("!=", args[0], ir.Constant(_VEC, [0.0] * LANES))
            return builder.select(chosen, args[1], args[2])
        return vec(m, a, b), codegen
    return None


def _involves_vec(*args) -> bool:
    return any(isinstance(a, Vec) for a in args)


def _overload_binary(op, implementation):
    @overload(op)
    def _impl(a, b):
        if _involves_vec(a, b):
            return lambda a, b: implementation(splat(a), splat(b))
        return None


for _op, _implementation in ((operator.add, _add), (operator.sub, _sub), (operator.mul, _mul),
                             (operator.truediv, _div), (operator.iadd, _add), (operator.isub, _sub),
                             (operator.gt, _greater), (operator.ge, _greater_equal)):
    _overload_binary(_op, _implementation)


@overload(operator.neg)
def _neg(a):
    if isinstance(a, Vec):
        return lambda a: _sub(splat(0.0), a)
    return None


@overload(operator.le)
def _less_equal(a, b):
    if _involves_vec(a, b):
        return lambda a, b: _greater_equal(splat(b), splat(a))
    return None


@numba.njit(inline="always")
def _count(m) -> float:
    """Number of lanes set in a Vec mask (sum of its lanes)."""
    total = 0.0
    for k in range(LANES):
        total += _lane(m, k)
    return total


def sqrt(x):
    """sqrt of a float, or per lane of a Vec (compiled code only)."""
    return math.sqrt(x)


def maximum(a, b):
    """max of two floats, or per lane where either is a Vec (compiled code only)."""
    return max(a, b)


def select(mask, a, b):
    """a if mask else b: a bool mask on floats, a lane mask on Vecs (compiled code only)."""
    return a if mask else b


@overload(sqrt)
def _sqrt(x):
    if isinstance(x, Vec):
        return lambda x: _vsqrt(x)
    return lambda x: math.sqrt(x)


@overload(maximum)
def _maximum(a, b):
    if _involves_vec(a, b):
        return lambda a, b: _max(splat(a), splat(b))
    return lambda a, b: max(a, b)


@overload(select)
def _select(mask, a, b):
    if isinstance(mask, Vec):
        return lambda mask, a, b: _where(mask, splat(a), splat(b))
    return lambda mask, a, b: a if mask else b


# Lane-generic operations (module docstring).


def width(proto) -> int:
    """Lanes of a pack whose values are like proto: 1 (a float) or LANES (a Vec)."""
    return 1


@overload(width)
def _width(proto):
    if isinstance(proto, Vec):
        return lambda proto: LANES
    return lambda proto: 1


def fill(proto, x):
    """x in every lane, as proto's type (float(x) or splat(x))."""
    return float(x)


@overload(fill)
def _fill(proto, x):
    if isinstance(proto, Vec):
        return lambda proto, x: splat(x)
    return lambda proto, x: float(x)


@intrinsic
def load(typingctx, a, i, proto):
    """a.flat[i:i + width(proto)] of a C-contiguous float64 array as proto's type (no bounds
    check)."""
    if not (_is_f64_array(a) and isinstance(i, types.Integer)):
        return None
    wide = isinstance(proto, Vec)

    def codegen(context, builder, sig, args):
        pointer = _element_pointer(context, builder, sig.args[0], args[0], sig.args[1], args[1], wide)
        return builder.load(pointer, align=8)
    return (vec if wide else types.float64)(a, i, proto), codegen


@intrinsic
def store(typingctx, a, i, v):
    """a.flat[i:i + width] = v, a Vec or a float (no bounds check)."""
    if not (_is_f64_array(a) and isinstance(i, types.Integer) and isinstance(v, (Vec, types.Float))):
        return None
    wide = isinstance(v, Vec)

    def codegen(context, builder, sig, args):
        value = args[2] if wide else context.cast(builder, args[2], sig.args[2], types.float64)
        builder.store(value, _element_pointer(context, builder, sig.args[0], args[0], sig.args[1], args[1], wide),
                      align=8)
        return context.get_dummy_value()
    return types.none(a, i, v), codegen


def mask(condition):
    """A lane mask from a comparison: a bool -> 1.0 / 0.0; a Vec mask stays as it is."""
    return 1.0 if condition else 0.0


@overload(mask)
def _mask(condition):
    if isinstance(condition, Vec):
        return lambda condition: condition
    return lambda condition: 1.0 if condition else 0.0


def lanes_set(m) -> float:
    """Number of lanes set in a lane mask."""
    return m


@overload(lanes_set)
def _lanes_set(m):
    if isinstance(m, Vec):
        return lambda m: _count(m)
    return lambda m: m


def lane_value(v, k: int) -> float:
    """Lane k of v (a float is its own lane 0)."""
    return v


@overload(lane_value)
def _lane_value(v, k):
    if isinstance(v, Vec):
        return lambda v, k: _lane(v, k)
    return lambda v, k: v


def multiply_add(a, b, c):
    """a b + c per lane."""
    return a * b + c


@overload(multiply_add)
def _multiply_add(a, b, c):
    if _involves_vec(a, b, c):
        return lambda a, b, c: _fma(splat(a), splat(b), splat(c))
    return lambda a, b, c: a * b + c


def nan_mask(x):
    """Lane mask: 1.0 where x is NaN."""
    return 1.0 if math.isnan(x) else 0.0


@overload(nan_mask)
def _nan_mask(x):
    if isinstance(x, Vec):
        return lambda x: _isnan(x)
    return lambda x: 1.0 if math.isnan(x) else 0.0


def absolute(x):
    """|x| per lane."""
    return abs(x)


@overload(absolute)
def _absolute(x):
    if isinstance(x, Vec):
        return lambda x: _max(x, _sub(splat(0.0), x))
    return lambda x: abs(x)
