"""A float32 exp(x) and 2^x for x <= 0 that LLVM can vectorise inside numba loops.

numba lowers ``math.exp`` to a libm call, which keeps a loop scalar (no SVML here), and its
float<->int conversions go through int64, which AVX2 cannot do lane-wise. This version uses
Cody-Waite range reduction, a degree-6 Taylor polynomial on |r| <= ln(2)/2 and builds 2^n from
exponent bits, all in float32/int32 lanes. Max relative error ~3e-7 (a few ulp) on [-87, 0];
the argument is clamped to [-87, 0] (so rounding noise above 0 gives 1, and the far tail
exp(-87) ~ 1.6e-38 instead of a subnormal).

``exp2_nonpositive`` is the cheaper base-2 form the inference rasterizer uses (its conics come scaled
by log2(e), so no range reduction by ln 2 is needed): n = x rounded by adding and subtracting 1.5 * 2^23,
2^n read off that sum's bits, 2^(x - n) by a degree-5 polynomial fitted for relative error on
[-1/2, 1/2] with its constant 1, so that 2^0 is exactly 1 (max 2.0e-7 in float32).
"""

import numba
import numpy as np
from llvmlite import ir
from numba.core import types
from numba.extending import intrinsic


@intrinsic
def _trunc(typingctx, x):
    """float32 rounded toward zero through an int32 (|x| < 2^31)."""
    if x != types.float32:
        return None

    def codegen(context, builder, sig, args):
        return builder.sitofp(builder.fptosi(args[0], ir.IntType(32)), ir.FloatType())
    return types.float32(types.float32), codegen


@intrinsic
def _pow2(typingctx, n):
    """2^n for an integral float32 n in [-126, 127], assembled from its exponent bits."""
    if n != types.float32:
        return None

    def codegen(context, builder, sig, args):
        i32 = ir.IntType(32)
        biased = builder.add(builder.fptosi(args[0], i32), ir.Constant(i32, 127))
        return builder.bitcast(builder.shl(biased, ir.Constant(i32, 23)), ir.FloatType())
    return types.float32(types.float32), codegen


@intrinsic
def _pow2_rounded(typingctx, shifted):
    """2^n for ``shifted`` = n + _ROUND (float32, n an integer in [-126, 127]): its bits are those of
    _ROUND plus n, whose low 9 bits are 0, so shifting them up by 23 leaves n << 23."""
    if shifted != types.float32:
        return None

    def codegen(context, builder, sig, args):
        i32 = ir.IntType(32)
        bits = builder.shl(builder.bitcast(args[0], i32), ir.Constant(i32, 23))
        return builder.bitcast(builder.add(bits, ir.Constant(i32, 127 << 23)), ir.FloatType())
    return types.float32(types.float32), codegen


_ROUND = np.float32(1.5 * 2**23)  # x + _ROUND - _ROUND rounds x to an integer (|x| < 2^22)
_EXP2 = tuple(np.float32(c) for c in (1.0, 0.693146977598858, 0.24022242085173176, 0.055507337436910255,
                                       0.00967151264891175, 0.001326472706531119))
LOG2E = 1.4426950408889634
"""log2(e), float64 (the inference rasterizer scales its conics by it)."""
_LOG2E = np.float32(LOG2E)
_LN2_HI = np.float32(0.693359375)       # ln 2 split so that n * _LN2_HI is exact for |n| < 2^8
_LN2_LO = np.float32(-2.12194440e-4)


@numba.njit(inline="always")
def exp_nonpositive(x):
    """exp(min(x, 0)) for float32 x."""
    x = min(max(x, np.float32(-87.0)), np.float32(0.0))
    n = _trunc(x * _LOG2E - np.float32(0.5))  # the integer nearest to x log2(e), as x <= 0
    r = x - n * _LN2_HI - n * _LN2_LO
    p = np.float32(1.0 / 720.0)
    p = p * r + np.float32(1.0 / 120.0)
    p = p * r + np.float32(1.0 / 24.0)
    p = p * r + np.float32(1.0 / 6.0)
    p = p * r + np.float32(0.5)
    p = p * r + np.float32(1.0)
    p = p * r + np.float32(1.0)
    return p * _pow2(n)


@numba.njit(inline="always")
def exp2_nonpositive(x):
    """2^x for float32 x <= 0 (rounding noise above 0 gives about 1 + x ln 2); clamped below at -125, so
    that no result is subnormal (a subnormal costs the CPU a microcode assist)."""
    x = max(x, np.float32(-125.0))
    shifted = x + _ROUND
    r = x - (shifted - _ROUND)
    p = _EXP2[5]
    p = p * r + _EXP2[4]
    p = p * r + _EXP2[3]
    p = p * r + _EXP2[2]
    p = p * r + _EXP2[1]
    p = p * r + _EXP2[0]
    return p * _pow2_rounded(shifted)
