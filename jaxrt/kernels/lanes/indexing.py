"""Indexing primitives (gather, scatter, dynamic_slice, dynamic_update_slice) on object
arrays of lanes. With constant indices, where each element goes is found by running the
primitive on element ids at trace time (a free rearrangement). A per-ray index (`x[i]`,
as in a material table) is enumerated: every candidate value gives one rearrangement,
and the result is a chain of selects on `clamp(i) == candidate` (at most 4096
combinations, two varying indices). On "fused" (XLA, `ctx.roll_scans`), a dynamic slice
or update whose starts are shared by all rays (a rolled scan's counter, as the slot of
the ray tree that `recursion = "scan"` shades) is one `lax.dynamic_slice` /
`dynamic_update_slice` of the operand's lanes stacked into an array (`_uniform_slice`):
enumerating the 129 slots of a depth-6 tree as selects made a program that XLA:CPU
compiled for over 5 minutes."""

import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from .elementwise import _apply, _select
from .values import Unsupported, _broadcast, _is_const, _lane_shape, _obj

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


#: Enumerate a dynamic slice's shared starts as selects up to this many candidates; over
#: it, slice an array of the stacked lanes (`_uniform_slice`).
ENUMERATE_SHARED = 8


def _shared_starts(starts, ranges, ctx):
    """Whether `starts` (0-d object arrays) vary only in lanes shared by all rays (0-d),
    over more than `ENUMERATE_SHARED` candidates, on a target that slices arrays."""
    varying = [k for k, s in enumerate(starts) if not _is_const(s[()])]
    return (ctx.roll_scans and varying and all(_lane_shape(starts[k][()]) == () for k in varying)
            and math.prod(ranges[k] for k in varying) > ENUMERATE_SHARED)


def _stacked(obj, shape, dtype):
    """The object array of lanes `obj` as one array [*obj.shape, *shape]."""
    lanes = [_broadcast(x, shape, dtype) for x in obj.reshape(-1)]
    return jnp.stack(lanes).reshape(obj.shape + tuple(shape))


def _unstacked(arr, shape):
    """The leading `shape` axes of `arr` as an object array of lanes."""
    out = _obj(shape)
    for idx in np.ndindex(shape):
        out[idx] = arr[idx]
    return out


def _uniform_slice(operand, update, starts, sizes, dtype):
    """`dynamic_slice` (update None) or `dynamic_update_slice` of the object array
    `operand` at shared `starts`: on the stacked lanes, clamped as the primitive clamps."""
    lane_shapes = {_lane_shape(x) for x in operand.reshape(-1)}
    if update is not None:
        lane_shapes |= {_lane_shape(x) for x in update.reshape(-1)}
    shape = max(lane_shapes, key=len)
    index = [jnp.asarray(s[()], jnp.int32) for s in starts] + [jnp.int32(0)] * len(shape)
    arr = _stacked(operand, shape, dtype)
    if update is None:
        return _unstacked(lax.dynamic_slice(arr, index, tuple(sizes) + shape), tuple(sizes))
    res = lax.dynamic_update_slice(arr, _stacked(update, shape, dtype), index)
    return _unstacked(res, operand.shape)


def _dynamic_slice(eqn, ins, ctx):
    operand, starts = ins[0], ins[1:]
    sizes = eqn.params["slice_sizes"]
    ranges = [operand.shape[d] - sizes[d] + 1 for d in range(operand.ndim)]
    if _shared_starts(starts, ranges, ctx):
        return [_uniform_slice(operand, None, starts, sizes, eqn.outvars[0].aval.dtype)]

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
    if _shared_starts(starts, ranges, ctx):
        return [_uniform_slice(operand, update, starts, update.shape, dtype)]
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
