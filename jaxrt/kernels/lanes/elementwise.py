"""Elementwise primitives on lanes: one primitive applied to one lane of each operand
(`_bind_lanes`; constants are folded at trace time, shared values computed once when a
`Uniforms` records them, GPU forms substituted by `ctx.rewrite`), the rule for every
elementwise equation (`_elementwise`: once per element of its result), the helpers that
other rules build from (`_apply`, `_select`, `_fold`), and `round` from `floor`."""

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from .jax_internals import IDENTITY, PRIMS, default_params
from .values import _const_lane, _is_const, _lane_shape, _obj

def _bind_lanes(prim, lanes, params, out_dtype, ctx):
    """Apply an elementwise primitive to one lane of each operand."""
    if prim.name in IDENTITY:
        return lanes[0]
    if all(_is_const(x) for x in lanes):
        with jax.ensure_compile_time_eval():
            out = prim.bind(*[jnp.asarray(x) for x in lanes], **params)
        return np.asarray(out).astype(out_dtype)[()]
    shapes = {_lane_shape(x) for x in lanes}
    shape = max(shapes, key=len)
    if shape == () and ctx.uniforms is not None and ctx.loop_depth == 0:
        out = ctx.uniforms(prim, lanes, params, out_dtype)
        if out is not None:
            return out
    if ctx.rewrite is not None:  # a GPU kernel's forms (`gpu.rewrite`)
        out = ctx.rewrite(prim.name, lanes, out_dtype, ctx)
        if out is not None:
            return out
    ops = []
    for x in lanes:
        if _is_const(x):
            x = _const_lane(x, x.dtype, ctx) if shape == ctx.block else jnp.asarray(x, x.dtype)
        if x.shape != shape:
            x = jnp.broadcast_to(x, shape)
        ops.append(x)
    return prim.bind(*ops, **params)


def _elementwise(eqn, ins, ctx):
    out_aval = eqn.outvars[0].aval
    if eqn.primitive.name in IDENTITY:
        return [ins[0].copy()]
    arrays = np.broadcast_arrays(*ins) if len(ins) > 1 else ins
    if math.prod(out_aval.shape) >= FOLD_AT_ONCE and all(_is_const(x) for a in arrays for x in a.flat):
        return [_folded(eqn.primitive, arrays, eqn.params, out_aval.dtype)]
    out = _obj(out_aval.shape)
    for idx in np.ndindex(out_aval.shape):
        out[idx] = _bind_lanes(eqn.primitive, [a[idx] for a in arrays], eqn.params,
                               out_aval.dtype, ctx)
    return [out]


#: Arrays of constants of at least this many elements fold in one call (`_folded`): each
#: new shape compiles a small XLA program once (about 10 ms), where the scalar programs
#: of `_bind_lanes` are compiled once per primitive and dtype.
FOLD_AT_ONCE = 16


def _folded(prim, arrays, params, out_dtype):
    """An elementwise primitive on arrays of constants, evaluated at trace time in one
    call, not once per element (`_bind_lanes`): a stacked union's 256 per-child
    constants at each of eight sites were 2 048 evaluations."""
    typed = [np.asarray(a.tolist(), dtype=a.flat[0].dtype) for a in arrays]
    with jax.ensure_compile_time_eval():
        value = np.asarray(prim.bind(*[jnp.asarray(t) for t in typed], **params)).astype(out_dtype)
    out = _obj(value.shape)
    for idx in np.ndindex(value.shape):
        out[idx] = value[idx]
    return out


def _apply(name, *lanes, dtype, ctx, **params):
    """Elementwise primitive `name` (from jax.lax) on lanes."""
    prim = PRIMS[name]
    return _bind_lanes(prim, list(lanes), {**default_params(name), **params}, dtype, ctx)


def _select(pred, on_false, on_true, dtype, ctx):
    return _apply("select_n", pred, on_false, on_true, dtype=dtype, ctx=ctx)


#: numpy's scalar forms of the primitives that `_fold` reduces with (IEEE operations on
#: scalars of one dtype, as XLA's).
_NUMPY_FOLDS = {"add": np.add, "mul": np.multiply, "max": np.maximum, "min": np.minimum,
                "and": np.bitwise_and, "or": np.bitwise_or, "xor": np.bitwise_xor}


def _fold(values, name, dtype, ctx):
    """values[0] ∘ values[1] ∘ … in that order; constants alone in numpy, at once."""
    if len(values) > 2 and name in _NUMPY_FOLDS and all(_is_const(v) for v in values):
        with np.errstate(all="ignore"):
            out = functools.reduce(_NUMPY_FOLDS[name], [v.astype(dtype) for v in values])
        return np.asarray(out, dtype)[()]
    return functools.reduce(lambda a, b: _apply(name, a, b, dtype=dtype, ctx=ctx), values)


def _round(eqn, ins, ctx):
    """lax.round from floor, which every backend has (Triton has no round):
    half away from zero: sign(x)·floor(|x| + ½); half to even: floor(x + ½), minus 1
    where x + ½ was an odd integer. |x| ≥ 2^(mantissa bits) is already an integer."""
    (x,) = ins
    dtype = eqn.outvars[0].aval.dtype
    method = int(eqn.params["rounding_method"])
    big = np.asarray(2.0 ** np.finfo(dtype).nmant, dtype)[()]
    half, one, two = (np.asarray(v, dtype)[()] for v in (0.5, 1.0, 2.0))
    out = _obj(x.shape)
    for idx in np.ndindex(x.shape):
        v = x[idx]
        a = _apply("abs", v, dtype=dtype, ctx=ctx)
        if method == 0:
            r = _apply("floor", _apply("add", a, half, dtype=dtype, ctx=ctx), dtype=dtype, ctx=ctx)
            r = _apply("mul", _apply("sign", v, dtype=dtype, ctx=ctx), r, dtype=dtype, ctx=ctx)
        else:
            s = _apply("add", v, half, dtype=dtype, ctx=ctx)
            r = _apply("floor", s, dtype=dtype, ctx=ctx)
            tie = _apply("eq", r, s, dtype=np.dtype(bool), ctx=ctx)
            odd = _apply("ne", _apply("sub", r, _apply("mul", two, _apply(
                "floor", _apply("mul", r, half, dtype=dtype, ctx=ctx), dtype=dtype, ctx=ctx),
                dtype=dtype, ctx=ctx), dtype=dtype, ctx=ctx), np.asarray(0.0, dtype)[()],
                dtype=np.dtype(bool), ctx=ctx)
            fix = _apply("and", tie, odd, dtype=np.dtype(bool), ctx=ctx)
            r = _select(fix, r, _apply("sub", r, one, dtype=dtype, ctx=ctx), dtype, ctx)
        large = _apply("ge", a, big, dtype=np.dtype(bool), ctx=ctx)
        out[idx] = _select(large, r, v, dtype, ctx)
    return [out]
