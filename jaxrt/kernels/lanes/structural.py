"""Structural primitives: they only rearrange or fold the object arrays of lanes
(broadcast, reshape, slice, concatenate, transpose, pad, iota: no work at run time), or
fold a few lanes into one (reductions, argmax, small dot products: a chain of
elementwise operations, fused multiply-adds in GPU kernels)."""

import numpy as np

from .elementwise import _apply, _fold, _select
from .gpu import _sum_of_products
from .values import Unsupported, _convert, _obj, lanes_of

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
    """x[..., k, ...] along `axis` for every k, each an object array: `[k, ...]` keeps a
    0-d array where np.take would return the element itself (a bare lane) for a 1-D x."""
    x = np.moveaxis(ins[0], eqn.params["axis"], 0)
    return [x[k, ...] for k in range(x.shape[0])]


def _split(eqn, ins, ctx):
    sizes, axis = eqn.params["sizes"], eqn.params["axis"]
    cuts = np.cumsum(sizes)[:-1]
    return list(np.split(ins[0], cuts, axis=axis))


def _pad(eqn, ins, ctx):
    x, value = ins
    value = value[()]
    cfg = eqn.params["padding_config"]
    out = _obj(eqn.outvars[0].aval.shape)
    for idx in np.ndindex(out.shape):  # one by one: numpy would convert a traced value
        out[idx] = value
    # positions of the operand's elements in the output
    for idx in np.ndindex(x.shape):
        pos = []
        for i, (lo, _, interior) in zip(idx, cfg):
            pos.append(int(lo) + i * (int(interior) + 1))
        if all(0 <= q < n for q, n in zip(pos, out.shape)):
            out[tuple(pos)] = x[idx]
    return [out]


def _empty(eqn, ins, ctx):
    """An uninitialised value (`jax_internals.EMPTY`): zeros, constants."""
    aval = eqn.outvars[0].aval
    return [lanes_of(np.zeros(aval.shape, aval.dtype))]


def _iota(eqn, ins, ctx):
    p = eqn.params
    shape, dim = tuple(p["shape"]), p["dimension"]
    a = np.arange(shape[dim], dtype=p["dtype"]).reshape([-1 if i == dim else 1 for i in range(len(shape))])
    return [lanes_of(np.broadcast_to(a, shape))]


def _reduced_last(x, axes):
    """x with the reduced `axes` moved last and flattened into one: shape kept + (n,)."""
    keep = [a for a in range(x.ndim) if a not in axes]
    moved = np.transpose(x, keep + list(axes))
    return moved.reshape(moved.shape[: len(keep)] + (-1,))


def _reduce(name):
    def rule(eqn, ins, ctx):
        (x,) = ins
        dtype = eqn.outvars[0].aval.dtype
        moved = _reduced_last(x, tuple(eqn.params["axes"]))
        out_shape = moved.shape[:-1]
        out = _obj(out_shape)
        for idx in np.ndindex(out_shape):
            out[idx] = _fold(list(moved[idx]), name, dtype, ctx)
        return [out]

    return rule


def _arg_reduce(better):
    def rule(eqn, ins, ctx):
        (x,) = ins
        idx_dtype = eqn.params["index_dtype"]
        val_dtype = eqn.invars[0].aval.dtype
        moved = _reduced_last(x, tuple(eqn.params["axes"]))
        out_shape = moved.shape[:-1]
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


def _optimization_barrier(eqn, ins, ctx):
    """The values, computed once (`control._barrier`) where the program materialises
    (`materialize`, outside loops): every consumer then reads the same rounding, which
    is what a barrier in a jaxrt formula asks for (`sdf.primitives.sd_cone`'s side)."""
    if ctx.materialize and ctx.loop_depth == 0:
        from .control import _barrier

        return _barrier(list(ins))
    return list(ins)
