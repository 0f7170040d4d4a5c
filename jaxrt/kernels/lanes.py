"""Run a one-ray program on a block of rays, one lane per ray ("structure of arrays").

jaxrt's kernels are written for one ray (`trace_radiance(scene, o, d, cone, settings)`)
and `jax.vmap` batches them. vmap keeps the shapes of the one-ray program and adds a
batch axis: a point becomes a [B, 3] array, a dot product a reduction over its last
axis, a sphere-tracing loop a masked loop over the batch. On a CPU this leaves many
small ops with strided access; inside a GPU kernel (Pallas/Triton) shapes like [B, 3]
are not even allowed (block shapes must be powers of two).

`eval_lanes` instead *scalarises* the one-ray program. It traces it once to a jaxpr and
interprets that jaxpr with every value of shape S held as a numpy object array of shape
S whose elements are lanes: a [B] array (one number per ray), a 0-d array (the same
for every ray: scene parameters) or a numpy scalar (a compile-time constant). Every
elementwise primitive is applied lane-wise; structural primitives (slice, reshape,
broadcast, concatenate, transpose, gather/scatter with constant indices, small
reductions and dot products) only rearrange or fold the object arrays, so they cost
nothing at run time. What is left is a flat program of [B] elementwise operations, which
XLA fuses into a few loops on the CPU and Triton compiles into one GPU kernel.

Control flow: a `while` whose condition varies between rays becomes one loop over the
block that runs while any lane is active; inactive lanes keep their state (the
semantics of `vmap` of a while loop: each ray stops where it would alone, and the block
stops when its last ray does). `cond` with a per-ray index evaluates every branch and
selects lane-wise. A `scan` is unrolled, or with `roll_scans` (the "fused"
backend) kept as one loop over lanes (`_scan_rolled`). Dynamic indexing (`x[i]` with a per-ray `i`, as in a material table)
becomes a chain of selects over the possible indices.

The result is the same function as the one-ray program (same primitives, same order of
floating-point operations), so images agree with the vmapped path to rounding. The
forward pass only: differentiate through the reference path (see `fused.py`).
"""

import collections
import functools
import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.extend import core as jcore

__all__ = ["eval_lanes", "lanes_of", "program_size", "stack_lanes", "Uniforms", "Unsupported"]


class Unsupported(NotImplementedError):
    """The one-ray program uses a primitive (or a form of one) that lanes cannot run."""


# --------------------------------------------------------------------------- helpers


def _is_const(x):
    return isinstance(x, np.generic)


def _lane_shape(x):
    return () if _is_const(x) else tuple(jnp.shape(x))


def _obj(shape):
    return np.empty(shape, dtype=object)


def lanes_of(x):
    """A concrete or traced array of shape S as an object array of 0-d lanes.

    Concrete (numpy, or non-traced JAX) arrays become numpy scalars (constants); traced
    arrays are indexed element by element (uniform lanes)."""
    if isinstance(x, (np.ndarray, np.generic, int, float, bool)) or (
        isinstance(x, jax.Array) and not isinstance(x, jax.core.Tracer)
    ):
        a = np.asarray(x)
        if a.size > 65536:
            raise Unsupported(f"a constant of shape {a.shape} (tables are not lane programs)")
        out = _obj(a.shape)
        for idx in np.ndindex(a.shape):
            out[idx] = a[idx]
        return out
    shape = jnp.shape(x)
    out = _obj(shape)
    if shape == ():
        out[()] = x
    else:
        flat = jnp.reshape(x, (-1,))
        for k, idx in enumerate(np.ndindex(shape)):
            out[idx] = flat[k]
    return out


def stack_lanes(obj, block, dtype):
    """An object array of lanes (shape S) as one array [*block, *S]."""
    block = _shape(block)
    shape = obj.shape
    elems = [_broadcast(e, block, dtype) for e in obj.reshape(-1)]
    if not elems:
        return jnp.zeros(block + shape, dtype)
    return jnp.stack(elems, axis=-1).reshape(block + shape)


def _shape(block):
    return (block,) if isinstance(block, int) else tuple(block)


def _broadcast(x, block, dtype, ctx=None):
    """A lane as an array of shape `block` and `dtype`."""
    block = _shape(block)
    if ctx is not None and _is_const(x):
        return _const_lane(x, dtype, ctx)
    x = jnp.asarray(x, dtype)
    return jnp.broadcast_to(x, block) if x.shape != block else x


def _const_lane(c, dtype, ctx):
    """The constant `c` as a full lane, computed from a traced value when there is one:
    a constant array built from constants alone may be evaluated at trace time, and a
    Pallas kernel must not capture arrays. The traced value is ctx.int_anchor (an
    integer scalar, a program id: i·0 folds to 0 at compile time, so the lane is a
    splat of the constant) or else ctx.anchor (a per-ray lane; x·0.0 does not fold)."""
    dtype = np.dtype(dtype)
    source = ctx.anchor if ctx.int_anchor is None else ctx.int_anchor
    if source is None:
        return jnp.broadcast_to(jnp.asarray(c, dtype), ctx.block)
    # Cached per trace scope (ctx.scopes: one dict per loop body being traced): a lane
    # staged inside a loop body must not be reused outside it (a leaked tracer), and
    # within a scope each constant is one lane, not one multiply-add per use.
    key = (dtype.str, np.asarray(c, dtype).tobytes())
    cache = ctx.scopes[-1]
    if key not in cache:
        zero = lax.convert_element_type(source * 0,
                                        np.int32 if dtype == np.dtype(bool) else dtype)
        value = (zero + np.int32(bool(c))) != 0 if dtype == np.dtype(bool) else \
            zero + np.asarray(c, dtype)[()]
        cache[key] = jnp.broadcast_to(value, ctx.block)
    return cache[key]


class _Ctx:
    """Evaluation context: block size, the any-lane reduction and the loop unroll."""

    def __init__(self, block, any_lane, unroll, materialize=False, fast_math=False):
        self.fast_math = fast_math
        self.ptx = None
        self.uniforms = None
        self.bool_carries = False
        self.anchor = None
        self.int_anchor = None
        self.scopes = [{}]
        self.unsupported = frozenset()
        self.block = block
        self.any_lane = any_lane
        self.unroll = unroll
        self.materialize = materialize
        self.loop_depth = 0
        self.roll_scans = False
        self.slice_of = {}  # id of a lane -> (array, i, lane): lane is array[i]
        self.param_pos = {}  # id of a 0-d parameter lane -> (dtype, position in its table)
        self.param_table = {}  # dtype -> [n] array of the program's 0-d parameter lanes


def _any_lane_default(pred):
    return jnp.any(pred)


# -------------------------------------------------------------- elementwise primitives

_ELEMENTWISE = {
    "abs", "acos", "acosh", "add", "add_any", "and", "asin", "asinh", "atan", "atan2",
    "atanh", "cbrt", "ceil", "clamp", "convert_element_type", "copy", "copy_p", "cos",
    "cosh", "div", "eq", "erf", "erf_inv", "erfc", "exp", "exp2", "expm1", "floor", "ge",
    "gt", "integer_pow", "is_finite", "le", "lgamma", "log", "log1p", "logistic", "lt",
    "max", "min", "mul", "ne", "neg", "nextafter", "not", "or", "pow", "reduce_precision",
    "rem", "rsqrt", "select_n", "shift_left", "shift_right_arithmetic",
    "shift_right_logical", "sign", "sin", "sinh", "sqrt", "square", "stop_gradient",
    "sub", "tan", "tanh", "xor", "optimization_barrier_elem",
}
_IDENTITY = {"stop_gradient", "copy", "copy_p"}


def _bind_lanes(prim, lanes, params, out_dtype, ctx):
    """Apply an elementwise primitive to one lane of each operand."""
    if prim.name in _IDENTITY:
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
    if ctx.fast_math and out_dtype == np.dtype(np.float32):
        fast = _fast_math(prim.name, lanes, ctx, out_dtype)
        if fast is not None:
            return fast
    if prim.name == "neg" and ctx.ptx and out_dtype == np.float32:
        return _neg(lanes[0], ctx)
    ops = []
    for x in lanes:
        if _is_const(x):
            x = _const_lane(x, x.dtype, ctx) if shape == ctx.block else jnp.asarray(x, x.dtype)
        if x.shape != shape:
            x = jnp.broadcast_to(x, shape)
        ops.append(x)
    return prim.bind(*ops, **params)


def _fast_math(name, lanes, ctx, dtype):
    """Cheaper float32 forms for a GPU kernel (within a few ulps of the exact ones).

    With `ctx.ptx` (a Triton kernel: {name: function of [block] lanes}, see
    `fused._ptx_ops`): per-ray sqrt, rsqrt and division as the approximate PTX instructions
    `sqrt.approx.ftz`, `rsqrt.approx.ftz`, `div.approx.ftz` (one special-function
    instruction, or a reciprocal and a multiply, instead of a range-checked sequence),
    exp, log and pow through `ex2.approx`/`lg2.approx` (x^y = 2^(y·log2 x): NaN for
    x < 0), as CUDA's `--use_fast_math` compiles them; x + 0 as x (IEEE keeps the add
    for x = −0). Without it: sqrt(x) as x·rsqrt(x). Both: division of per-ray values by a
    value shared by all rays (a scene parameter, say a Lipschitz factor) as
    multiplication by its reciprocal, computed once."""
    ptx = ctx.ptx
    if name in ("add", "add_any") and ptx is not None:
        a, b = lanes
        for x, y in ((a, b), (b, a)):
            if _is_const(y) and float(y) == 0.0 and not _is_const(x) and x.dtype == dtype:
                return x
        return None
    if name in ("sqrt", "rsqrt", "exp", "log"):
        (x,) = lanes
        if _lane_shape(x) == ():
            return None
        if ptx is not None:
            return ptx[name](x)
        if name != "sqrt":
            return None
        ok = x > 0.0
        return jnp.where(ok, x * lax.rsqrt(jnp.where(ok, x, 1.0)), jnp.zeros_like(x))
    if name == "pow" and ptx is not None and (_lane_shape(lanes[0]) != () or
                                               _lane_shape(lanes[1]) != ()):
        x, y = (_broadcast(v, ctx.block, dtype, ctx) for v in lanes)
        return ptx["pow"](x, y)
    if name == "div":
        x, y = lanes
        if _lane_shape(x) == () and _lane_shape(y) == ():
            return None
        if _lane_shape(y) == ():
            return x * (1.0 / jnp.asarray(y, jnp.float32))
        if ptx is not None:
            if _is_const(x):
                x = _const_lane(x, dtype, ctx)
            return ptx["div"](jnp.broadcast_to(x, y.shape), y)
    return None


def _elementwise(eqn, ins, ctx):
    out_aval = eqn.outvars[0].aval
    arrays = np.broadcast_arrays(*ins) if len(ins) > 1 else ins
    out = _obj(out_aval.shape)
    for idx in np.ndindex(out_aval.shape):
        out[idx] = _bind_lanes(eqn.primitive, [a[idx] for a in arrays], eqn.params,
                               out_aval.dtype, ctx)
    return [out]


def _apply(name, *lanes, dtype, ctx, **params):
    """Elementwise primitive `name` (from jax.lax) on lanes."""
    prim = _PRIMS[name]
    return _bind_lanes(prim, list(lanes), params, dtype, ctx)


_PRIMS = {
    "add": lax.add_p, "mul": lax.mul_p, "max": lax.max_p, "min": lax.min_p,
    "and": lax.and_p, "or": lax.or_p, "select_n": lax.select_n_p, "eq": lax.eq_p,
    "gt": lax.gt_p, "lt": lax.lt_p, "ne": lax.ne_p, "xor": lax.xor_p,
    "convert_element_type": lax.convert_element_type_p, "clamp": lax.clamp_p,
}


def _select(pred, on_false, on_true, dtype, ctx):
    return _apply("select_n", pred, on_false, on_true, dtype=dtype, ctx=ctx)


def _convert(x, dtype, ctx):
    if _is_const(x):
        return np.asarray(x).astype(dtype)[()]
    if x.dtype == dtype:
        return x
    return lax.convert_element_type(x, dtype)


# --------------------------------------------------------------- structural primitives


def _broadcast_in_dim(eqn, ins, ctx):
    (x,) = ins[:1]
    shape, dims = eqn.params["shape"], eqn.params["broadcast_dimensions"]
    new = [1] * len(shape)
    for i, d in enumerate(dims):
        new[d] = x.shape[i]
    return [np.broadcast_to(x.reshape(new), shape)]


def _reshape(eqn, ins, ctx):
    if eqn.params.get("dimensions"):
        raise Unsupported("reshape with `dimensions`")
    return [ins[0].reshape(eqn.params["new_sizes"])]


def _squeeze(eqn, ins, ctx):
    return [np.squeeze(ins[0], axis=tuple(eqn.params["dimensions"]))]


def _expand_dims(eqn, ins, ctx):
    return [np.expand_dims(ins[0], tuple(eqn.params["dimensions"]))]


def _transpose(eqn, ins, ctx):
    return [np.transpose(ins[0], eqn.params["permutation"])]


def _rev(eqn, ins, ctx):
    return [np.flip(ins[0], axis=tuple(eqn.params["dimensions"]))]


def _slice(eqn, ins, ctx):
    p = eqn.params
    strides = p["strides"] or (1,) * len(p["start_indices"])
    idx = tuple(slice(a, b, s) for a, b, s in zip(p["start_indices"], p["limit_indices"], strides))
    return [ins[0][idx]]


def _concatenate(eqn, ins, ctx):
    return [np.concatenate(ins, axis=eqn.params["dimension"])]


def _stack(eqn, ins, ctx):
    return [np.stack(ins, axis=eqn.params["axis"])]


def _unstack(eqn, ins, ctx):
    axis = eqn.params["axis"]
    return [np.take(ins[0], k, axis=axis) for k in range(ins[0].shape[axis])]


def _split(eqn, ins, ctx):
    sizes, axis = eqn.params["sizes"], eqn.params["axis"]
    cuts = np.cumsum(sizes)[:-1]
    return list(np.split(ins[0], cuts, axis=axis))


def _pad(eqn, ins, ctx):
    x, value = ins
    value = value[()]
    cfg = eqn.params["padding_config"]
    out = _obj(eqn.outvars[0].aval.shape)
    out[...] = value
    # positions of the operand's elements in the output
    for idx in np.ndindex(x.shape):
        pos = []
        for i, (lo, _, interior) in zip(idx, cfg):
            pos.append(int(lo) + i * (int(interior) + 1))
        if all(0 <= q < n for q, n in zip(pos, out.shape)):
            out[tuple(pos)] = x[idx]
    return [out]


def _iota(eqn, ins, ctx):
    p = eqn.params
    shape, dim = tuple(p["shape"]), p["dimension"]
    a = np.arange(shape[dim], dtype=p["dtype"]).reshape([-1 if i == dim else 1 for i in range(len(shape))])
    return [lanes_of(np.broadcast_to(a, shape))]


def _fold(values, name, dtype, ctx):
    return functools.reduce(lambda a, b: _apply(name, a, b, dtype=dtype, ctx=ctx), values)


def _reduce(name):
    def rule(eqn, ins, ctx):
        (x,) = ins
        axes = tuple(eqn.params["axes"])
        dtype = eqn.outvars[0].aval.dtype
        keep = [a for a in range(x.ndim) if a not in axes]
        moved = np.transpose(x, keep + list(axes))
        out_shape = moved.shape[: len(keep)]
        moved = moved.reshape(out_shape + (-1,))
        out = _obj(out_shape)
        for idx in np.ndindex(out_shape):
            out[idx] = _fold(list(moved[idx]), name, dtype, ctx)
        return [out]

    return rule


def _arg_reduce(better):
    def rule(eqn, ins, ctx):
        (x,) = ins
        axes = tuple(eqn.params["axes"])
        idx_dtype = eqn.params["index_dtype"]
        val_dtype = eqn.invars[0].aval.dtype
        keep = [a for a in range(x.ndim) if a not in axes]
        moved = np.transpose(x, keep + list(axes))
        out_shape = moved.shape[: len(keep)]
        moved = moved.reshape(out_shape + (-1,))
        out = _obj(out_shape)
        for idx in np.ndindex(out_shape):
            vals = list(moved[idx])
            best, arg = vals[0], np.asarray(0, idx_dtype)[()]
            for k, v in enumerate(vals[1:], 1):
                take = _apply(better, v, best, dtype=np.dtype(bool), ctx=ctx)
                best = _select(take, best, v, val_dtype, ctx)
                arg = _select(take, arg, np.asarray(k, idx_dtype)[()], idx_dtype, ctx)
            out[idx] = arg
        return [out]

    return rule


def _dot_general(eqn, ins, ctx):
    lhs, rhs = ins
    (lc, rc), (lb, rb) = eqn.params["dimension_numbers"]
    dtype = eqn.outvars[0].aval.dtype
    lf = [a for a in range(lhs.ndim) if a not in lc and a not in lb]
    rf = [a for a in range(rhs.ndim) if a not in rc and a not in rb]
    L = np.transpose(lhs, list(lb) + lf + list(lc))
    R = np.transpose(rhs, list(rb) + rf + list(rc))
    nb, nlf, nrf = len(lb), len(lf), len(rf)
    bshape = L.shape[:nb]
    lfs, rfs = L.shape[nb:nb + nlf], R.shape[nb:nb + nrf]
    out = _obj(bshape + lfs + rfs)
    for b in np.ndindex(bshape):
        for i in np.ndindex(lfs):
            for j in np.ndindex(rfs):
                a = L[b + i].reshape(-1)
                c = R[b + j].reshape(-1)
                pairs = [(_convert(x, dtype, ctx), _convert(y, dtype, ctx)) for x, y in zip(a, c)]
                if not pairs:
                    out[b + i + j] = np.asarray(0, dtype)[()]
                elif ctx.ptx and "fma" in ctx.ptx and dtype == np.float32:
                    out[b + i + j] = _sum_of_products(pairs, dtype, ctx)
                else:
                    terms = [_apply("mul", x, y, dtype=dtype, ctx=ctx) for x, y in pairs]
                    out[b + i + j] = _fold(terms, "add", dtype, ctx)
    return [out]


# ------------------------------------------------------- indexing (gather, scatter, …)


def _concrete_index_eval(fn, operand_shape, *index_arrays):
    """Run an indexing primitive on element ids (concrete) to see where elements go."""
    ids = np.arange(int(np.prod(operand_shape)), dtype=np.int32).reshape(operand_shape)
    with jax.ensure_compile_time_eval():
        return np.asarray(fn(jnp.asarray(ids), *[jnp.asarray(a) for a in index_arrays]))


def _enumerate_indices(index_objs, ranges):
    """All assignments of the varying lanes among `index_objs` (object arrays).

    Returns (varying, combos): the list of (array k, position) of varying lanes and an
    iterator over tuples of their candidate values; at most 4096 combinations."""
    varying = [(k, idx) for k, a in enumerate(index_objs) for idx in np.ndindex(a.shape)
               if not _is_const(a[idx])]
    sizes = [ranges[k] for k, _ in varying]
    if math.prod(sizes) > 4096:
        raise Unsupported("indexing with too many per-ray indices")
    return varying, itertools.product(*[range(n) for n in sizes])


def _gather_like(eqn, ins, ctx, operand, index_objs, ranges, fn, fill=None):
    """Generic rule: out[e] = operand[f(e)] for concrete indices; selects otherwise."""
    out_aval = eqn.outvars[0].aval
    dtype = out_aval.dtype
    varying, combos = _enumerate_indices(index_objs, ranges)

    def concrete(objs):
        arrays = [np.asarray(a.tolist(), dtype=eqn.invars[1 + k].aval.dtype).reshape(a.shape)
                  for k, a in enumerate(objs)]
        return _concrete_index_eval(fn, operand.shape, *arrays)

    def pick(ids):
        out = _obj(ids.shape)
        flat = operand.reshape(-1)
        for idx in np.ndindex(ids.shape):
            i = int(ids[idx])
            out[idx] = flat[i] if i >= 0 else fill
        return out

    if not varying:
        return [pick(concrete(index_objs))]
    result = None
    for values in combos:
        objs = [a.copy() for a in index_objs]
        for (k, idx), v in zip(varying, values):
            objs[k][idx] = np.asarray(v, eqn.invars[1 + k].aval.dtype)[()]
        candidate = pick(concrete(objs))
        if result is None:
            result = candidate
            continue
        match = None
        for (k, idx), v in zip(varying, values):
            lane = index_objs[k][idx]
            lo, hi = 0, ranges[k] - 1
            clamped = _apply("clamp", np.asarray(lo, lane.dtype)[()], lane,
                             np.asarray(hi, lane.dtype)[()], dtype=lane.dtype, ctx=ctx)
            eq = _apply("eq", clamped, np.asarray(v, lane.dtype)[()], dtype=np.dtype(bool), ctx=ctx)
            match = eq if match is None else _apply("and", match, eq, dtype=np.dtype(bool), ctx=ctx)
        for idx in np.ndindex(result.shape):
            if candidate[idx] is not result[idx]:
                result[idx] = _select(match, result[idx], candidate[idx], dtype, ctx)
    return [result]


def _dynamic_slice(eqn, ins, ctx):
    operand, starts = ins[0], ins[1:]
    sizes = eqn.params["slice_sizes"]
    ranges = [operand.shape[d] - sizes[d] + 1 for d in range(operand.ndim)]

    def fn(ids, *s):
        return lax.dynamic_slice(ids, [x[()] for x in s], sizes)

    return _gather_like(eqn, ins, ctx, operand, list(starts), ranges, fn)


def _gather(eqn, ins, ctx):
    operand, indices = ins
    p = dict(eqn.params)
    dnums = p["dimension_numbers"]
    fill_value = p.get("fill_value")
    dtype = eqn.outvars[0].aval.dtype
    if indices.size and not all(_is_const(x) for x in indices.reshape(-1)):
        # enumerate per-ray index lanes over the axis each indexes
        vdim = indices.ndim - 1
        ranges_flat = {}
        for idx in np.ndindex(indices.shape):
            comp = idx[vdim] if indices.ndim else 0
            ranges_flat[idx] = operand.shape[dnums.start_index_map[comp]]
        varying = [(0, idx) for idx in np.ndindex(indices.shape) if not _is_const(indices[idx])]
        if len(varying) > 2:
            raise Unsupported("gather with more than two per-ray indices")
        rng = [ranges_flat[idx] for _, idx in varying]
        return _gather_varying(eqn, operand, indices, varying, rng, p, dtype, ctx)
    fill = _fill(fill_value, dtype)
    prm = {k: v for k, v in p.items()}
    prm["fill_value"] = -1

    def fn(ids, ix):
        return lax.gather_p.bind(ids, ix, **prm)

    ids = _concrete_index_eval(fn, operand.shape,
                               np.asarray(indices.tolist(), eqn.invars[1].aval.dtype).reshape(indices.shape))
    out = _obj(ids.shape)
    flat = operand.reshape(-1)
    for idx in np.ndindex(ids.shape):
        i = int(ids[idx])
        out[idx] = flat[i] if i >= 0 else fill
    return [out]


def _gather_varying(eqn, operand, indices, varying, rng, p, dtype, ctx):
    prm = dict(p)
    prm["fill_value"] = -1
    fill = _fill(p.get("fill_value"), dtype)
    idx_dtype = eqn.invars[1].aval.dtype
    result = None
    flat = operand.reshape(-1)
    for values in itertools.product(*[range(n) for n in rng]):
        ix = indices.copy()
        for (_, pos), v in zip(varying, values):
            ix[pos] = np.asarray(v, idx_dtype)[()]
        arr = np.asarray(ix.tolist(), idx_dtype).reshape(ix.shape)
        ids = _concrete_index_eval(lambda a, b: lax.gather_p.bind(a, b, **prm), operand.shape, arr)
        cand = _obj(ids.shape)
        for idx in np.ndindex(ids.shape):
            i = int(ids[idx])
            cand[idx] = flat[i] if i >= 0 else fill
        if result is None:
            result = cand
            continue
        match = None
        for (_, pos), v, n in zip(varying, values, rng):
            lane = indices[pos]
            clamped = _apply("clamp", np.asarray(0, lane.dtype)[()], lane,
                             np.asarray(n - 1, lane.dtype)[()], dtype=lane.dtype, ctx=ctx)
            eq = _apply("eq", clamped, np.asarray(v, lane.dtype)[()], dtype=np.dtype(bool), ctx=ctx)
            match = eq if match is None else _apply("and", match, eq, dtype=np.dtype(bool), ctx=ctx)
        for idx in np.ndindex(result.shape):
            if cand[idx] is not result[idx]:
                result[idx] = _select(match, result[idx], cand[idx], dtype, ctx)
    return [result]


def _fill(fill_value, dtype):
    if fill_value is not None:
        return np.asarray(fill_value, dtype)[()]
    if np.issubdtype(dtype, np.floating):
        return np.asarray(np.nan, dtype)[()]
    if dtype == np.dtype(bool):
        return np.asarray(True)[()]
    return np.asarray(np.iinfo(dtype).min, dtype)[()]


def _scatter(add):
    def concrete(eqn, operand, ix, updates, ctx):
        p = {k: v for k, v in eqn.params.items() if k not in ("update_jaxpr", "update_consts")}
        dtype = eqn.outvars[0].aval.dtype
        out = operand.copy()
        flat_out = out.reshape(-1)
        flat_upd = updates.reshape(-1)
        # where does each update element land? scatter a one-hot of it (concrete)
        with jax.ensure_compile_time_eval():
            for j in range(updates.size):
                onehot = np.zeros(updates.shape, np.int32)
                onehot.reshape(-1)[j] = 1
                land = np.asarray(lax.scatter_add(
                    jnp.zeros(operand.shape, jnp.int32), jnp.asarray(ix), jnp.asarray(onehot),
                    p["dimension_numbers"], indices_are_sorted=p["indices_are_sorted"],
                    unique_indices=p["unique_indices"], mode=p["mode"])).reshape(-1)
                for i in np.nonzero(land)[0]:
                    for _ in range(int(land[i])):
                        if add:
                            flat_out[i] = _apply("add", flat_out[i], flat_upd[j], dtype=dtype, ctx=ctx)
                        else:
                            flat_out[i] = flat_upd[j]
        return out

    def rule(eqn, ins, ctx):
        operand, indices, updates = ins
        idx_dtype = eqn.invars[1].aval.dtype
        dtype = eqn.outvars[0].aval.dtype
        varying = [pos for pos in np.ndindex(indices.shape) if not _is_const(indices[pos])]
        if not varying:
            ix = np.asarray(indices.tolist(), idx_dtype).reshape(indices.shape)
            return [concrete(eqn, operand, ix, updates, ctx)]
        # per-ray indices (the gradient of x[argmax x], say): every candidate index,
        # then a select per element
        dims = eqn.params["dimension_numbers"].scatter_dims_to_operand_dims
        ranges = [operand.shape[dims[pos[-1] if indices.ndim else 0]] for pos in varying]
        if len(varying) > 2 or math.prod(ranges) > 4096:
            raise Unsupported("scatter with more than two per-ray indices")
        result = None
        for values in itertools.product(*[range(n) for n in ranges]):
            ixo = indices.copy()
            for pos, v in zip(varying, values):
                ixo[pos] = np.asarray(v, idx_dtype)[()]
            ix = np.asarray(ixo.tolist(), idx_dtype).reshape(indices.shape)
            cand = concrete(eqn, operand, ix, updates, ctx)
            if result is None:
                result = cand
                continue
            match = None
            for pos, v in zip(varying, values):
                eq = _apply("eq", indices[pos], np.asarray(v, idx_dtype)[()], dtype=np.dtype(bool), ctx=ctx)
                match = eq if match is None else _apply("and", match, eq, dtype=np.dtype(bool), ctx=ctx)
            for idx in np.ndindex(result.shape):
                if cand[idx] is not result[idx]:
                    result[idx] = _select(match, result[idx], cand[idx], dtype, ctx)
        return [result]

    return rule


def _dynamic_update_slice(eqn, ins, ctx):
    operand, update, starts = ins[0], ins[1], ins[2:]
    dtype = eqn.outvars[0].aval.dtype
    ranges = [operand.shape[d] - update.shape[d] + 1 for d in range(operand.ndim)]
    varying, combos = _enumerate_indices(list(starts), ranges)
    result = operand.copy()

    def place(base, start_vals):
        out = base.copy()
        for idx in np.ndindex(update.shape):
            out[tuple(s + i for s, i in zip(start_vals, idx))] = update[idx]
        return out

    def clamp_start(k, s):
        return min(max(int(s), 0), ranges[k] - 1)

    if not varying:
        return [place(result, [clamp_start(k, s[()]) for k, s in enumerate(starts)])]
    for values in combos:
        vals = [None if not _is_const(s[()]) else clamp_start(k, s[()]) for k, s in enumerate(starts)]
        match = None
        for (k, _), v in zip(varying, values):
            vals[k] = v
            lane = starts[k][()]
            clamped = _apply("clamp", np.asarray(0, lane.dtype)[()], lane,
                             np.asarray(ranges[k] - 1, lane.dtype)[()], dtype=lane.dtype, ctx=ctx)
            eq = _apply("eq", clamped, np.asarray(v, lane.dtype)[()], dtype=np.dtype(bool), ctx=ctx)
            match = eq if match is None else _apply("and", match, eq, dtype=np.dtype(bool), ctx=ctx)
        cand = place(operand, vals)
        for idx in np.ndindex(result.shape):
            if cand[idx] is not operand[idx]:
                result[idx] = _select(match, result[idx], cand[idx], dtype, ctx)
    return [result]


# ------------------------------------------------------------------------ control flow


def _closed(eqn):
    for key in ("jaxpr", "call_jaxpr", "fun_jaxpr"):
        j = eqn.params.get(key)
        if isinstance(j, jcore.ClosedJaxpr):
            return j
        if isinstance(j, jcore.Jaxpr):
            return jcore.ClosedJaxpr(j, ())
    raise Unsupported(f"{eqn.primitive.name}: no inner jaxpr found")


def _call(eqn, ins, ctx):
    outs = _eval_closed(_closed(eqn), ins, ctx)
    if ctx.materialize and ctx.loop_depth == 0:
        outs = _barrier(outs)
    return outs


def _materialise(x):
    """`x`, computed once into memory: a fusion boundary for XLA on CPUs.

    XLA:CPU removes `optimization_barrier`s before fusion (the `cse_barrier_expander`
    pass of jax 0.10), so a barrier does not stop a producer from being fused, and so
    recomputed, into each of its consumers. A reduction is never fused into its
    consumers: x = max(x, identity) over a stacked axis of two stores x, exactly."""
    dt = np.dtype(x.dtype)
    if dt == np.dtype(bool):
        return lax.reduce_or(jnp.stack([x, jnp.zeros_like(x)]), (0,))
    low = -np.inf if np.issubdtype(dt, np.floating) else np.iinfo(dt).min
    return lax.reduce_max(jnp.stack([x, jnp.full_like(x, low)]), (0,))


def _barrier(objs):
    """`_materialise` on the traced lanes of `objs`: XLA then computes them once,
    instead of fusing (and so duplicating) their whole expression into every
    consumer: a program scalarised into lanes has many consumers per value (each
    component of each output), and XLA's CPU fusion would recompute shared work."""
    flat, where = [], []
    for k, o in enumerate(objs):
        for idx in np.ndindex(o.shape):
            x = o[idx]
            if not _is_const(x):
                flat.append(x)
                where.append((k, idx))
    if not flat:
        return objs
    flat = [_materialise(x) for x in flat]
    objs = [o.copy() for o in objs]
    for (k, idx), x in zip(where, flat):
        objs[k][idx] = x
    return objs


def _while(eqn, ins, ctx):
    p = eqn.params
    cn, bn = p["cond_nconsts"], p["body_nconsts"]
    cond_j, body_j = p["cond_jaxpr"], p["body_jaxpr"]
    cconsts, bconsts, init = ins[:cn], ins[cn:cn + bn], ins[cn + bn:]
    used = getattr(ctx, "used_outputs", None) or [True] * len(init)
    cond_j, body_j, cconsts, bconsts, keep = _prune_loop(cond_j, body_j, cconsts, bconsts, used)
    full_init = init
    init = [x for x, k in zip(init, keep) if k]
    avals = [v.aval for v, k in zip(eqn.outvars, keep) if k]
    block = ctx.block
    # loop state: every lane of every carried value as a [block] array (bools as int32
    # unless ctx.bool_carries: a Triton kernel carries predicates, which saves a
    # conversion each way per step)
    shapes = [a.shape for a in avals]
    dtypes = [a.dtype for a in avals]
    sizes = [int(np.prod(s)) for s in shapes]

    def store_dtype(dt):
        return np.dtype(np.int32) if dt == np.dtype(bool) and not ctx.bool_carries else dt

    def pack(objs):
        flat = []
        for obj, dt in zip(objs, dtypes):
            for x in obj.reshape(-1):
                flat.append(_broadcast(_convert(x, store_dtype(dt), ctx), block, store_dtype(dt), ctx))
        return flat

    def unpack(flat):
        objs, k = [], 0
        for shape, dt, n in zip(shapes, dtypes, sizes):
            obj = _obj(shape)
            ravel = obj.reshape(-1)
            for i in range(n):
                x = flat[k + i]
                ravel[i] = (x != 0) if dt == np.dtype(bool) and x.dtype != np.dtype(bool) else x
            objs.append(obj)
            k += n
        return objs

    def cond_lanes(objs):
        # a batched while (vmap inside the one-ray program) has a predicate of shape S
        # (the leading axes of every carry): it runs while any element is true
        (c,) = _eval_closed(cond_j, list(cconsts) + objs, ctx)
        return _fold(list(c.reshape(-1)), "or", np.dtype(bool), ctx)

    def step(state):
        flat, active = state
        objs = unpack(flat)
        new = _eval_closed(body_j, list(bconsts) + objs, ctx)
        (c,) = _eval_closed(cond_j, list(cconsts) + objs, ctx)
        if c.shape != ():
            # ... and only its elements whose predicate holds take a step (the body does
            # not mask itself: XLA's lowering of a batched while selects per element)
            new = [_select_elements(c, n, o) for n, o in zip(new, objs)]
        new_flat = pack(new)
        flat = [jnp.where(active, n, o) for n, o in zip(new_flat, flat)]
        still = cond_lanes(unpack(flat))
        active = active & _broadcast(still, block, bool, ctx)
        return flat, active

    def body_fn(state):
        ctx.scopes.append({})
        try:
            for _ in range(ctx.unroll):
                state = step(state)
        finally:
            ctx.scopes.pop()
        return state

    def cond_fn(state):
        return ctx.any_lane(state[1])

    flat0 = pack(init)
    active0 = _broadcast(cond_lanes(unpack(flat0)), block, bool, ctx)
    ctx.loop_depth += 1
    try:
        flat, _ = lax.while_loop(cond_fn, body_fn, (flat0, active0))
    finally:
        ctx.loop_depth -= 1
    results = iter(unpack(flat))
    # carries that nothing reads keep their initial value (placeholders)
    return [next(results) if k else x for x, k in zip(full_init, keep)]


def _select_elements(pred, new, old):
    """new where pred else old, elementwise over pred's shape S, the leading axes of the
    object arrays new and old (shape S + rest)."""
    out = _obj(new.shape)
    for i in np.ndindex(*new.shape):
        out[i] = jnp.where(pred[i[:pred.ndim]], new[i], old[i])
    return out


def _scan(eqn, ins, ctx):
    """`lax.scan`, unrolled: the body once per iteration on that iteration's slices of
    the scanned inputs (static slices of object arrays: free). A lane program is
    scalarised anyway, so a scan of length n is n copies of its body (as a Python loop
    would be). With ctx.roll_scans (the "fused" XLA backend) a scan without stacked
    outputs stays a loop (`_scan_rolled`): one copy of its body, whatever n (`Union`'s
    stacked children, a material taken by index, the lights of one kind)."""
    p = eqn.params
    nc, nk = _scan_counts(p)
    length = p["length"]
    closed = p["jaxpr"]
    if isinstance(closed, jcore.Jaxpr):
        closed = jcore.ClosedJaxpr(closed, ())
    consts, carry, xs = ins[:nc], list(ins[nc:nc + nk]), ins[nc + nk:]
    if ctx.roll_scans and length > 1:
        return _scan_rolled(eqn, closed, consts, carry, xs, length, p["reverse"], ctx)
    order = range(length - 1, -1, -1) if p["reverse"] else range(length)
    ys = [None] * length
    for i in order:
        outs = _eval_closed(closed, [*consts, *carry, *[x[i, ...] for x in xs]], ctx)
        carry, ys[i] = list(outs[:nk]), outs[nk:]
    stacked = []
    for k, v in enumerate(eqn.outvars[nk:]):
        out = _obj(v.aval.shape)
        for i in range(length):
            out[i, ...] = ys[i][k]
        stacked.append(out)
    return carry + stacked


def _scan_rolled(eqn, closed, consts, carry, xs, length, reverse, ctx):
    """A scan without stacked outputs as one `lax.scan` over lanes: each carried
    element a [block] array (bools as int32 unless ctx.bool_carries), each scanned
    element its `length` lanes stacked ([length] when they are shared by all rays,
    else [length, *block]); the body is interpreted once."""
    block = ctx.block
    nk = len(carry)
    avals = [v.aval for v in eqn.outvars[:nk]]
    shapes = [a.shape for a in avals]
    dtypes = [np.dtype(a.dtype) for a in avals]
    y_avals = [v.aval for v in eqn.outvars[nk:]]
    y_dtypes = [np.dtype(a.dtype) for a in y_avals]

    def store_dtype(dt):
        return np.dtype(np.int32) if dt == np.dtype(bool) and not ctx.bool_carries else dt

    def pack(objs):
        return [_broadcast(_convert(x, store_dtype(dt), ctx), block, store_dtype(dt), ctx)
                for obj, dt in zip(objs, dtypes) for x in obj.reshape(-1)]

    def unpack(flat):
        objs, k = [], 0
        for shape, dt in zip(shapes, dtypes):
            obj = _obj(shape)
            ravel = obj.reshape(-1)
            for i in range(ravel.size):
                x = flat[k + i]
                ravel[i] = (x != 0) if dt == np.dtype(bool) and x.dtype != np.dtype(bool) else x
            objs.append(obj)
            k += ravel.size
        return objs

    # scanned inputs: element idx of x over the iterations, as one array
    xs_flat, xs_meta = [], []
    for x, var in zip(xs, eqn.invars[len(eqn.invars) - len(xs):]):
        dt = np.dtype(var.aval.dtype)
        elem_shape = x.shape[1:]
        for idx in np.ndindex(elem_shape):
            lanes = [x[(i,) + idx] for i in range(length)]
            source = [ctx.slice_of.get(id(v)) for v in lanes]
            if all(_is_const(v) for v in lanes):
                xs_flat.append(np.asarray([np.asarray(v, dt) for v in lanes], dt))
            elif all(src is not None and src[0] is source[0][0] and src[1] == i
                     for i, src in enumerate(source)) and source[0][0].dtype == dt:
                # the stacked outputs of another rolled scan (a gradient's residuals)
                xs_flat.append(source[0][0])
            elif all(id(v) in ctx.param_pos for v in lanes) and \
                    len({ctx.param_pos[id(v)][0] for v in lanes}) == 1:
                # parameters of the program: one gather from their table (built once,
                # outside every loop), not a stack of n lanes at every site
                table = ctx.param_table[ctx.param_pos[id(lanes[0])][0]]
                xs_flat.append(table[np.asarray([ctx.param_pos[id(v)][1] for v in lanes])].astype(dt))
            elif all(_lane_shape(v) == () for v in lanes):
                xs_flat.append(jnp.stack([jnp.asarray(v, dt) for v in lanes]))
            else:
                xs_flat.append(jnp.stack([_broadcast(v, block, dt, ctx) for v in lanes]))
        xs_meta.append((elem_shape, dt))

    def unpack_xs(flat):
        objs, k = [], 0
        for shape, _ in xs_meta:
            obj = _obj(shape)
            for idx in np.ndindex(shape):
                obj[idx] = flat[k]
                k += 1
            objs.append(obj)
        return objs

    def body(flat, x_flat):
        ctx.scopes.append({})
        try:
            outs = _eval_closed(closed, [*consts, *unpack(flat), *unpack_xs(x_flat)], ctx)
        finally:
            ctx.scopes.pop()
        ys = [_broadcast(_convert(x, dt, ctx), block, dt, ctx)
              for obj, dt in zip(outs[nk:], y_dtypes) for x in obj.reshape(-1)]
        return pack(outs[:nk]), ys

    ctx.loop_depth += 1
    try:
        flat, ys_flat = lax.scan(body, pack(carry), xs_flat, length=length, reverse=reverse)
    finally:
        ctx.loop_depth -= 1
    # stacked outputs: lane i of an element is ys[i] (remembered, so that a rolled scan
    # that scans over them takes the array itself)
    stacked, k = [], 0
    for aval in y_avals:
        obj = _obj(aval.shape)
        for idx in np.ndindex(aval.shape[1:]):
            arr = ys_flat[k]
            k += 1
            for i in range(length):
                lane = arr[i]
                ctx.slice_of[id(lane)] = (arr, i, lane)
                obj[(i,) + idx] = lane
        stacked.append(obj)
    return unpack(flat) + stacked


def _scan_counts(params):
    """(consts, carries) of a scan equation: jax ≤ 0.10 has num_consts/num_carry, jax
    0.11 the flat trees ft_in = (consts, carries, xs)."""
    if "num_consts" in params:
        return params["num_consts"], params["num_carry"]
    consts, carry, _ = (len(list(t.vals)) for t in params["ft_in"].unpack())
    return consts, carry


def _prune_loop(cond_j, body_j, cconsts, bconsts, used):
    """Drop the carries of a while loop that neither its used results nor its condition
    need (a march that also tracks a closest approach nobody reads, say). Returns the
    pruned (cond, body, cond consts, body consts) and the mask of kept carries."""
    from jax._src.interpreters import partial_eval as pe

    n = len(used)
    nc, nb = len(cconsts), len(bconsts)
    if cond_j.consts or body_j.consts:
        return cond_j, body_j, cconsts, bconsts, [True] * n
    _, cond_in = pe.dce_jaxpr(cond_j.jaxpr, [True])
    keep = [bool(u) or bool(c) for u, c in zip(used, cond_in[nc:])]
    while True:
        _, body_in = pe.dce_jaxpr(body_j.jaxpr, keep)
        new = [k or bool(b) for k, b in zip(keep, body_in[nb:])]
        if new == keep:
            break
        keep = new
    if all(keep):
        return cond_j, body_j, cconsts, bconsts, keep
    cond_new, cond_used = pe.dce_jaxpr(cond_j.jaxpr, [True], instantiate=[True] * nc + keep)
    body_new, body_used = pe.dce_jaxpr(body_j.jaxpr, keep, instantiate=[True] * nb + keep)
    cond_new = jcore.ClosedJaxpr(cond_new, ())
    body_new = jcore.ClosedJaxpr(body_new, ())
    return cond_new, body_new, cconsts, bconsts, keep


def _cond(eqn, ins, ctx):
    index, ops = ins[0][()], ins[1:]
    branches = eqn.params["branches"]
    if _is_const(index):
        return _eval_closed(branches[int(index)], ops, ctx)
    outs = [_eval_closed(b, ops, ctx) for b in branches]
    result = [o.copy() for o in outs[0]]
    n = len(branches)
    clamped = _apply("clamp", np.asarray(0, index.dtype)[()], index,
                     np.asarray(n - 1, index.dtype)[()], dtype=index.dtype, ctx=ctx)
    for k in range(1, n):
        match = _apply("eq", clamped, np.asarray(k, index.dtype)[()], dtype=np.dtype(bool), ctx=ctx)
        for r, o, var in zip(result, outs[k], eqn.outvars):
            for idx in np.ndindex(r.shape):
                if o[idx] is not r[idx]:
                    r[idx] = _select(match, r[idx], o[idx], var.aval.dtype, ctx)
    return result


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


def _optimization_barrier(eqn, ins, ctx):
    return list(ins)


_RULES = {
    "broadcast_in_dim": _broadcast_in_dim,
    "reshape": _reshape,
    "squeeze": _squeeze,
    "expand_dims": _expand_dims,
    "transpose": _transpose,
    "rev": _rev,
    "slice": _slice,
    "concatenate": _concatenate,
    "stack": _stack,
    "unstack": _unstack,
    "split": _split,
    "pad": _pad,
    "iota": _iota,
    "reduce_sum": _reduce("add"),
    "reduce_max": _reduce("max"),
    "reduce_min": _reduce("min"),
    "reduce_prod": _reduce("mul"),
    "reduce_and": _reduce("and"),
    "reduce_or": _reduce("or"),
    "reduce_xor": _reduce("xor"),
    "argmax": _arg_reduce("gt"),
    "argmin": _arg_reduce("lt"),
    "dot_general": _dot_general,
    "dynamic_slice": _dynamic_slice,
    "dynamic_update_slice": _dynamic_update_slice,
    "gather": _gather,
    "scatter": _scatter(False),
    "scatter-add": _scatter(True),
    "scatter_add": _scatter(True),
    "while": _while,
    "scan": _scan,
    "cond": _cond,
    "pjit": _call,
    "jit": _call,
    "closed_call": _call,
    "core_call": _call,
    "remat": _call,
    "checkpoint": _call,
    "custom_jvp_call": _call,
    "custom_vjp_call": _call,
    "custom_vjp_call_jaxpr": _call,
    "optimization_barrier": _optimization_barrier,
    "round": _round,
}
_PRIMS.update({"sub": lax.sub_p, "div": lax.div_p, "not": lax.not_p, "abs": lax.abs_p,
               "floor": lax.floor_p, "sign": lax.sign_p, "ge": lax.ge_p})


# ---------------------------------------------------------------------- the interpreter


def _eval_closed(closed, args, ctx):
    consts = [lanes_of(c) for c in closed.consts]
    return _eval_jaxpr(closed.jaxpr, consts, args, ctx)


def _eval_jaxpr(jaxpr, consts, args, ctx):
    env = {}

    def write(v, x):
        env[v] = x

    def read(v):
        if isinstance(v, jcore.Literal):
            return lanes_of(np.asarray(v.val, dtype=v.aval.dtype))
        return env[v]

    for v, x in zip(jaxpr.constvars, consts):
        write(v, x)
    if len(args) != len(jaxpr.invars):
        raise Unsupported(f"arity mismatch: {len(args)} arguments for {len(jaxpr.invars)} inputs")
    for v, x in zip(jaxpr.invars, args):
        write(v, x)
    # liveness: skip equations whose results are unused, and tell `while` which of its
    # results are used (it then carries only what they and its condition need)
    live = {v for v in jaxpr.outvars if not isinstance(v, jcore.Literal)}
    used_eqns = []
    for eqn in reversed(jaxpr.eqns):
        used = [v in live for v in eqn.outvars]
        if any(used) or eqn.effects:
            live.update(v for v in eqn.invars if not isinstance(v, jcore.Literal))
        used_eqns.append(used)
    used_eqns.reverse()
    products, fused = _fma_plan(jaxpr) if ctx.ptx and "fma" in ctx.ptx else (set(), {})
    for eqn, used in zip(jaxpr.eqns, used_eqns):
        if not (any(used) or eqn.effects):
            continue
        ctx.used_outputs = used
        ins = [read(v) for v in eqn.invars]
        name = eqn.primitive.name
        if eqn.outvars[0] in products:  # a product that its one consumer fuses
            write(eqn.outvars[0], ins)
            continue
        if id(eqn) in fused:
            write(eqn.outvars[0], _fma(eqn, ins, fused[id(eqn)], ctx))
            continue
        if name in ctx.unsupported and name in _SUBSTITUTES:
            outs = _substitute(eqn, ins, ctx)
        elif name in ctx.unsupported:
            raise Unsupported(f"this backend cannot run the primitive `{name}` of the one-ray "
                              "program; use RenderSettings(backend=\"jax\")")
        elif name in _ELEMENTWISE:
            outs = _elementwise(eqn, ins, ctx)
        elif name in _RULES:
            outs = _RULES[name](eqn, ins, ctx)
        else:
            raise Unsupported(
                f"lanes cannot run the primitive `{name}` of the one-ray program; "
                "use RenderSettings(backend=\"jax\")"
            )
        for v, o in zip(eqn.outvars, outs):
            if not isinstance(v, jcore.DropVar):
                write(v, o)
    return [read(v) for v in jaxpr.outvars]


def _erfc(x):
    """erfc(x) = t·exp(−x² − 1.26551223 + t·P(t)), t = 1/(1 + |x|/2), for x ≥ 0 and
    2 − erfc(−x) below: the Chebyshev fit of Numerical Recipes (2nd ed., §6.2, `erfcc`),
    fractional error < 1.2e-7 everywhere; for targets without erfc (Triton)."""
    z = jnp.abs(x)
    t = 1.0 / (1.0 + 0.5 * z)
    p = 0.17087277
    for c in (-0.82215223, 1.48851587, -1.13520398, 0.27886807, -0.18628806, 0.09678418,
              0.37409196, 1.00002368, -1.26551223):
        p = c + t * p
    r = t * jnp.exp(p - z * z)
    return jnp.where(x >= 0.0, r, 2.0 - r)


#: Primitives a target may lack (`eval_lanes(unsupported=...)`), as lane programs of
#: primitives it has.
_SUBSTITUTES = {"erfc": _erfc}


def _substitute(eqn, ins, ctx):
    (x,) = eqn.invars
    closed = jax.make_jaxpr(_SUBSTITUTES[eqn.primitive.name])(
        jax.ShapeDtypeStruct(x.aval.shape, x.aval.dtype))
    return _eval_closed(closed, ins, ctx)


def _fma_plan(jaxpr):
    """Products to fuse into fused multiply-adds: float32 `mul`s whose only use is an
    `add`/`sub` of the same shape or a `reduce_sum` in the same jaxpr. Returns (the
    products' variables, {id of the consumer equation: index of the product among its
    operands})."""
    uses = collections.Counter(v for e in jaxpr.eqns for v in e.invars
                               if not isinstance(v, jcore.Literal))
    uses.update(v for v in jaxpr.outvars if not isinstance(v, jcore.Literal))
    muls = {e.outvars[0] for e in jaxpr.eqns
            if e.primitive.name == "mul" and e.outvars[0].aval.dtype == np.float32}
    products, fused = set(), {}
    for e in jaxpr.eqns:
        if e.primitive.name not in ("add", "add_any", "sub", "reduce_sum"):
            continue
        for k, v in enumerate(e.invars):
            if (not isinstance(v, jcore.Literal) and v in muls and uses[v] == 1
                    and v not in products and (e.primitive.name == "reduce_sum"
                                               or v.aval.shape == e.outvars[0].aval.shape)):
                products.add(v)
                fused[id(e)] = k
                break
    return products, fused


def _neg(x, ctx):
    if _is_const(x) or _lane_shape(x) == () or "neg" not in ctx.ptx:
        return -x if _is_const(x) else lax.neg(x)
    return ctx.ptx["neg"](x)


def _fma_lane(a, b, c, dtype, ctx):
    """a·b + c, one lane each: one fused multiply-add (one rounding) where the product
    varies per ray, the plain multiply and add where it is shared by all rays."""
    if _lane_shape(a) == () and _lane_shape(b) == ():
        return _apply("add", _apply("mul", a, b, dtype=dtype, ctx=ctx), c, dtype=dtype, ctx=ctx)
    a, b, c = (_broadcast(v, ctx.block, dtype, ctx) for v in (a, b, c))
    return ctx.ptx["fma"](a, b, c)


def _sum_of_products(pairs, dtype, ctx):
    """Σ x·y over lane pairs as a chain of fused multiply-adds."""
    (x, y), rest = pairs[0], pairs[1:]
    acc = _apply("mul", x, y, dtype=dtype, ctx=ctx)
    for x, y in rest:
        acc = _fma_lane(x, y, acc, dtype, ctx)
    return acc


def _fma(eqn, ins, k, ctx):
    """The consumer `eqn` (add, sub or reduce_sum) of the deferred product ins[k] =
    [x, y] (object arrays): x·y + z, x·y − z = fma(x, y, −z), z − x·y = fma(−x, y, z),
    or a sum of products."""
    x, y = ins[k]
    dtype = eqn.outvars[0].aval.dtype
    if eqn.primitive.name == "reduce_sum":
        x, y = np.broadcast_arrays(x, y)
        axes = tuple(eqn.params["axes"])
        keep = [a for a in range(x.ndim) if a not in axes]
        x, y = (np.transpose(v, keep + list(axes)) for v in (x, y))
        out_shape = x.shape[: len(keep)]
        x, y = (v.reshape(out_shape + (-1,)) for v in (x, y))
        out = _obj(out_shape)
        for idx in np.ndindex(out_shape):
            out[idx] = _sum_of_products(list(zip(x[idx], y[idx])), dtype, ctx)
        return out
    shape = eqn.outvars[0].aval.shape
    sub = eqn.primitive.name == "sub"
    x, y, z = np.broadcast_arrays(x, y, ins[1 - k])
    out = _obj(shape)
    for idx in np.ndindex(shape):
        a, b, c = x[idx], y[idx], z[idx]
        if sub and k == 0:
            c = _neg(c, ctx)
        elif sub:
            a = _neg(a, ctx)
        out[idx] = _fma_lane(a, b, c, dtype, ctx)
    return out


def program_size(jaxpr):
    """Lane operations of a one-ray program: its equations (those of loop bodies and
    calls once), each counted once per element of its result, as `eval_lanes`
    scalarises them (a batch of 2^k rays in a ray tree: 2^k lanes per operation)."""
    total = 0
    for eqn in jaxpr.eqns:
        shape = getattr(eqn.outvars[0].aval, "shape", ()) if eqn.outvars else ()
        total += max(1, int(np.prod(shape)))
        for p in eqn.params.values():
            for sub in p if isinstance(p, (list, tuple)) else [p]:
                if isinstance(sub, jcore.ClosedJaxpr):
                    total += program_size(sub.jaxpr)
                elif isinstance(sub, jcore.Jaxpr):
                    total += program_size(sub)
    return total


class Uniforms:
    """Values shared by all rays (functions of the scene's parameters alone: a camera's
    basis, a normalised light direction, tan(fov/2)), computed once outside a GPU kernel
    instead of by every thread.

    `eval_lanes` runs twice with the same program and block: first outside the kernel
    with `Uniforms()` (recording: every elementwise operation on shared scalars outside
    loops is computed and kept in `values`), then inside it with
    `Uniforms(read=k ↦ value)` (replaying: the k-th such operation reads the k-th value
    instead; loads that nothing uses are removed by the compiler, and with them the
    work). An operation met again on the same operands (the same scalar chain in
    several evaluations of an SDF) gives the value already made. `check` confirms that
    both runs met the same operations in the same order."""

    def __init__(self, read=None):
        self.read = read
        self.values = []
        self.ops = []
        self._labels = {}  # id of an operand -> the order in which it was first seen
        self._alive = []  # ... kept alive, so that ids are not reused
        self._made = {}

    #: the dtypes kept (as 32-bit words); operations on others run where they are
    DTYPES = (np.dtype(np.float32), np.dtype(np.int32), np.dtype(bool))

    def _label(self, x):
        if _is_const(x):
            return ("const", x.dtype.str, x.tobytes())
        if id(x) not in self._labels:
            self._labels[id(x)] = len(self._labels)
            self._alive.append(x)
        return self._labels[id(x)]

    def __call__(self, prim, lanes, params, dtype):
        if np.dtype(dtype) not in self.DTYPES:
            return None
        key = (prim.name, str(sorted(params.items())), tuple(self._label(x) for x in lanes))
        if key in self._made:
            return self._made[key]
        self.ops.append((prim.name, np.dtype(dtype).str))
        if self.read is not None:
            out = self.read(len(self.ops) - 1, dtype)
        else:
            out = prim.bind(*[jnp.asarray(x) for x in lanes], **params)
            self.values.append(out)
        self._made[key] = out
        return out

    def check(self, recorded):
        if self.ops != recorded.ops:
            raise RuntimeError("lanes.Uniforms: the kernel's shared values do not match the "
                               "recorded ones (the two evaluations diverged)")


def eval_lanes(closed, args, block, any_lane=None, unroll=1, materialize=False,
               fast_math=False, unsupported=(), int_anchor=None, ptx=None, uniforms=None,
               bool_carries=False, roll_scans=False):
    """Evaluate the one-ray program `closed` (a ClosedJaxpr) on a block of rays.

    Args:
      closed: the jaxpr of the one-ray function (`jax.make_jaxpr`).
      args: one object array per input (see `lanes_of`): elements are [block] arrays
        (per ray), 0-d arrays (shared by all rays) or numpy scalars (constants).
      block: the shape of a lane: the number of rays, or a tile shape (rows, columns).
      any_lane: `pred[block] -> bool scalar`, the loop condition of a block (default
        `jnp.any`; Triton kernels need a max of 0/1 floats).
      unroll: march steps per test of the block's loop condition.
      materialize: compute the results of the program's function calls (outside
        loops) once, behind an optimization barrier (see `_barrier`; for XLA on CPUs).
      fast_math: float32 sqrt and division by shared values in cheaper forms, within a
        few ulps (`_fast_math`; for GPU kernels).
      unsupported: primitive names the target cannot compile (raise `Unsupported`).
      int_anchor: a traced integer scalar (a Pallas program id) from which constant
        lanes are built (`_const_lane`), so that they fold to splats.
      ptx: {name: function of [block] lanes} for "fma", "neg" and, with fast_math,
        "sqrt", "rsqrt", "div", "exp", "log", "pow": the target's fused multiply-add (a
        product used once by an add, a sub or a sum is fused into it), negation and
        approximate functions (`_fast_math`).
      uniforms: a `Uniforms`, recording or replaying the values shared by all rays.
      bool_carries: loops carry boolean lanes as booleans (else as int32).
      roll_scans: scans without stacked outputs stay loops (`_scan_rolled`: one copy
        of the body), else they are unrolled.

    Returns: one object array of lanes per output of the program.
    """
    ctx = _Ctx(_shape(block), any_lane or _any_lane_default, unroll, materialize, fast_math)
    ctx.unsupported = frozenset(unsupported)
    ctx.int_anchor = int_anchor
    ctx.ptx = ptx
    ctx.uniforms = uniforms
    ctx.bool_carries = bool_carries
    ctx.roll_scans = roll_scans
    if roll_scans:  # a table of the 0-d parameter lanes, for rolled scans to gather from
        by_dtype = collections.defaultdict(list)
        for a in args:
            for x in a.reshape(-1):
                if not _is_const(x) and _lane_shape(x) == () and id(x) not in ctx.param_pos:
                    dt = np.dtype(x.dtype)
                    ctx.param_pos[id(x)] = (dt, len(by_dtype[dt]))
                    by_dtype[dt].append(x)
        ctx.param_table = {dt: jnp.stack(xs) for dt, xs in by_dtype.items()}
    for a in args:  # a traced per-ray input: constants become lanes through it
        for x in a.reshape(-1):
            if ctx.anchor is None and not _is_const(x) and tuple(jnp.shape(x)) == ctx.block \
                    and jnp.issubdtype(x.dtype, jnp.floating):
                ctx.anchor = x
    return _eval_closed(closed, list(args), ctx)
