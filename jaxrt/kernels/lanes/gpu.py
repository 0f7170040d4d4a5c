"""Rewrites for GPU (Triton) kernels only: approximate float32 forms (`_fast_math`, PTX
fast math), fused multiply-adds (`_fma_plan`, `_fma`), primitives Triton lacks as lane
programs of ones it has (`_SUBSTITUTES`: erfc), and values shared by all rays computed
once outside the kernel (`Uniforms`). `rewrite` is the hook `_bind_lanes` calls
(`ctx.rewrite`) for every elementwise operation."""

import collections

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from .elementwise import _apply
from .jax_internals import is_literal
from .values import _broadcast, _const_lane, _is_const, _lane_shape, _obj


def rewrite(name, lanes, dtype, ctx):
    """A GPU kernel's form of the elementwise primitive `name` on `lanes`, or None (the
    plain form): fast math (with ctx.fast_math, float32) and PTX negation."""
    if ctx.fast_math and dtype == np.dtype(np.float32):
        fast = _fast_math(name, lanes, ctx, dtype)
        if fast is not None:
            return fast
    if name == "neg" and ctx.ptx and dtype == np.float32:
        return _neg(lanes[0], ctx)
    return None


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
    return ctx.eval_closed(closed, ins)


def _fma_plan(jaxpr):
    """Products to fuse into fused multiply-adds: float32 `mul`s whose only use is an
    `add`/`sub` of the same shape or a `reduce_sum` in the same jaxpr. Returns (the
    products' variables, {id of the consumer equation: index of the product among its
    operands})."""
    uses = collections.Counter(v for e in jaxpr.eqns for v in e.invars
                               if not is_literal(v))
    uses.update(v for v in jaxpr.outvars if not is_literal(v))
    muls = {e.outvars[0] for e in jaxpr.eqns
            if e.primitive.name == "mul" and e.outvars[0].aval.dtype == np.float32}
    products, fused = set(), {}
    for e in jaxpr.eqns:
        if e.primitive.name not in ("add", "add_any", "sub", "reduce_sum"):
            continue
        for k, v in enumerate(e.invars):
            if (not is_literal(v) and v in muls and uses[v] == 1
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
        self.addresses = None  # `eval_lanes(addresses=...)`: each value's ("u", order) noted

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
        if self.addresses is not None:
            self.addresses[id(out)] = (out, ("u", len(self.ops) - 1))
        return out

    def check(self, recorded):
        if self.ops != recorded.ops:
            raise RuntimeError("lanes.Uniforms: the kernel's shared values do not match the "
                               "recorded ones (the two evaluations diverged)")
