"""The interpreter: a jaxpr evaluated equation by equation on object arrays of lanes,
each primitive by its rule (`_RULES`; elementwise primitives by `_elementwise`), and
`eval_lanes`, the entry point. Also `program_size`, the lane operations of a program."""

import collections
import functools

import jax.numpy as jnp
import numpy as np

from .control import LOADED_SCAN_MIN, _call, _cond, _scan, _while
from .elementwise import _elementwise, _round
from .gpu import _SUBSTITUTES, _fma, _fma_plan, _substitute, rewrite
from .indexing import _dynamic_slice, _dynamic_update_slice, _gather, _scatter
from .jax_internals import (CALLS, ELEMENTWISE, EMPTY, IDENTITY, ClosedJaxpr, Jaxpr, _scan_counts,
                            has_while, is_dropvar, is_literal, while_parts)
from .structural import (_arg_reduce, _broadcast_in_dim, _concatenate, _dot_general,
                         _empty, _expand_dims, _iota, _optimization_barrier, _pad, _reduce, _reshape,
                         _rev, _slice, _split, _squeeze, _stack, _transpose, _unstack)
from .values import (Row, _Ctx, _any_lane_default, _is_const, _lane_shape, _shape, lanes_of,
                     resolve, row_array, Unsupported)

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
    "optimization_barrier": _optimization_barrier,
    "round": _round,
    **{name: _call for name in CALLS},
    **{name: _empty for name in EMPTY},
}


# Rules that take `Row` lanes as they are: scans (a rolled one scans the rows' array),
# loops and calls (the equations of their bodies resolve what they read, a loop's in the
# body's scope), rules that only move lanes, and identities.
_KEEPS_ROWS = frozenset({"scan", "while", *CALLS, *IDENTITY, "broadcast_in_dim", "reshape", "squeeze",
                         "expand_dims", "transpose", "rev", "slice", "concatenate", "stack",
                         "unstack", "split"})


def _eval_closed(closed, args, ctx, keep_rows=False):
    """The outputs of `closed` on `args`; with `keep_rows` they may hold `Row` lanes
    (a call's results, read in the caller's scope), else they are sliced."""
    consts = [lanes_of(c) for c in closed.consts]
    outs = _eval_jaxpr(closed.jaxpr, consts, args, ctx)
    return outs if keep_rows else [resolve(o, ctx) for o in outs]


def _eval_jaxpr(jaxpr, consts, args, ctx):
    env = {}

    def write(v, x):
        env[v] = x

    def read(v):
        if is_literal(v):
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
    live = {v for v in jaxpr.outvars if not is_literal(v)}
    used_eqns = []
    for eqn in reversed(jaxpr.eqns):
        used = [v in live for v in eqn.outvars]
        if any(used) or eqn.effects:
            live.update(v for v in eqn.invars if not is_literal(v))
        used_eqns.append(used)
    used_eqns.reverse()
    products, fused = _fma_plan(jaxpr) if ctx.ptx and "fma" in ctx.ptx else (set(), {})
    for eqn, used in zip(jaxpr.eqns, used_eqns):
        if not (any(used) or eqn.effects):
            continue
        ctx.used_outputs = used
        ins = [read(v) for v in eqn.invars]
        name = eqn.primitive.name
        if ctx.rows and name in ELEMENTWISE and name not in IDENTITY and len(ins) == 1 \
                and row_array(ins[0]) is not None:
            # a unary operation on all the rows of an array (a record's bool → int32):
            # one operation on the array, whose rows are the result
            out = eqn.primitive.bind(row_array(ins[0]), **eqn.params)
            write(eqn.outvars[0], np.asarray([Row(out, i) for i in range(out.shape[0])],
                                             dtype=object).reshape(ins[0].shape))
            continue
        if ctx.rows and name not in _KEEPS_ROWS:
            ins = [resolve(x, ctx) for x in ins]
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
        elif name in ELEMENTWISE:
            outs = _elementwise(eqn, ins, ctx)
        elif name in _RULES:
            outs = _RULES[name](eqn, ins, ctx)
        else:
            raise Unsupported(
                f"lanes cannot run the primitive `{name}` of the one-ray program; "
                "use RenderSettings(backend=\"jax\")"
            )
        for v, o in zip(eqn.outvars, outs):
            if not is_dropvar(v):
                write(v, o)
    return [read(v) for v in jaxpr.outvars]


def _param_table(args, param_pos):
    """{dtype: [n] array} of the program's 0-d parameter lanes (the arrays of `Row`
    lanes whole, the other lanes stacked), noting each lane's (dtype, position) in
    `param_pos`."""
    parts = collections.defaultdict(list)  # dtype -> [array or [lanes]]
    sizes = collections.defaultdict(int)
    starts = {}  # id of a Row's array -> its position in the table
    loose = collections.defaultdict(list)
    for a in args:
        for x in a.reshape(-1):
            if id(x) in param_pos:
                continue
            if isinstance(x, Row):
                dt = np.dtype(x.arr.dtype)
                if id(x.arr) not in starts:
                    starts[id(x.arr)] = sizes[dt]
                    parts[dt].append(x.arr)
                    sizes[dt] += x.arr.shape[0]
                param_pos[id(x)] = (dt, starts[id(x.arr)] + x.i)
            elif not _is_const(x) and _lane_shape(x) == ():
                loose[np.dtype(x.dtype)].append(x)
    for dt, xs in loose.items():
        for x in xs:
            param_pos[id(x)] = (dt, sizes[dt])
            sizes[dt] += 1
        parts[dt].append(jnp.stack(xs))
    return {dt: ps[0] if len(ps) == 1 else jnp.concatenate(ps) for dt, ps in parts.items()}


def program_size(jaxpr, per_ray=None, unrolled_scans=False, loaded_scans=False):
    """Lane operations of a one-ray program: its equations (those of loop bodies and
    calls once), an equation that reads a per-ray value counted once per element of its
    result, as `eval_lanes` scalarises them (a batch of 2^k rays in a ray tree: 2^k lanes
    per operation), and one that reads only shared values (the scene's parameters,
    constants) once: lanes compute it once for a whole block, whatever its shape, so a
    stacked group of primitives counts the same for 8 rows as for 72.

    Args:
      jaxpr: the program (a Jaxpr).
      per_ray: one bool per input of `jaxpr`, true for a value that varies from ray to
        ray (default: all of them).
      unrolled_scans: count a scan's body once per iteration, as `eval_lanes` without
        `roll_scans` (Pallas) unrolls it: a stacked union of n children is n copies of
        its child at every site that evaluates the SDF.
      loaded_scans: ... except a scan that Pallas keeps as a loop with `addresses`
        (`control._scan_loaded`): at least `LOADED_SCAN_MIN` iterations over shared
        values, its stacked outputs unused, no `while` in its body.
    """
    per_ray = [True] * len(jaxpr.invars) if per_ray is None else list(per_ray)
    return _size(jaxpr, per_ray, unrolled_scans, loaded_scans)


def _size(jaxpr, per_ray, unrolled_scans=False, loaded_scans=False):
    """Lane operations of `jaxpr` whose inputs are per ray where `per_ray` says
    (`program_size`)."""
    varying = {v: f for v, f in zip(jaxpr.invars, per_ray)}
    read = {v for e in jaxpr.eqns for v in e.invars if not is_literal(v)}
    read.update(v for v in jaxpr.outvars if not is_literal(v))

    def reads(v):
        return not is_literal(v) and varying.get(v, False)

    total = 0
    for eqn in jaxpr.eqns:
        flags = [reads(v) for v in eqn.invars]
        any_ray = any(flags)
        shape = getattr(eqn.outvars[0].aval, "shape", ()) if eqn.outvars else ()
        total += max(1, int(np.prod(shape))) if any_ray else 1
        copies = 1
        if unrolled_scans and eqn.primitive.name == "scan":
            copies = eqn.params["length"]
            consts, nk = _scan_counts(eqn.params)
            if loaded_scans and copies >= LOADED_SCAN_MIN and not any(flags[consts + nk:]) \
                    and not any(v in read for v in eqn.outvars[nk:]) \
                    and not has_while(eqn.params["jaxpr"]):
                copies = 1
        for sub, sub_flags in _bodies(eqn, flags):
            total += copies * _size(sub, sub_flags, unrolled_scans, loaded_scans)
        for v in eqn.outvars:
            varying[v] = any_ray
    return total


def _bodies(eqn, flags):
    """(jaxpr, per-ray flags of its inputs) for each body of a loop, branch or call. A
    loop's carries count as per ray when any operand is (a carry may become per ray in
    the body)."""
    p, any_ray = eqn.params, any(flags)
    if eqn.primitive.name == "while":
        nc, nb, cond, body = while_parts(p)
        carry = [any_ray] * (len(flags) - nc - nb)
        return [(cond.jaxpr, flags[:nc] + carry), (body.jaxpr, flags[nc:nc + nb] + carry)]
    if eqn.primitive.name == "scan":
        consts, carries = _scan_counts(p)
        return [(p["jaxpr"].jaxpr, flags[:consts] + [any_ray] * carries + flags[consts + carries:])]
    if eqn.primitive.name == "cond":
        return [(b.jaxpr, flags[1:]) for b in p["branches"]]
    out = []
    for value in p.values():
        for sub in value if isinstance(value, (list, tuple)) else [value]:
            sub = sub.jaxpr if isinstance(sub, ClosedJaxpr) else sub
            if isinstance(sub, Jaxpr):
                same = len(sub.invars) == len(flags)
                out.append((sub, flags if same else [any_ray] * len(sub.invars)))
    return out


def eval_lanes(closed, args, block, any_lane=None, unroll=1, materialize=False,
               fast_math=False, unsupported=(), int_anchor=None, ptx=None, uniforms=None,
               bool_carries=False, roll_scans=False, keep_rows=False, compact=1,
               addresses=None, load=None, tables=None):
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
      roll_scans: scans stay loops (`_scan_rolled`: one copy of the body), else they
        are unrolled.
      keep_rows: the outputs may hold `Row` lanes (for `stack_lanes`).
      compact: a loop whose condition varies between rays narrows to its active rays
        once at most 1/compact of the block is active (`control._compacted`; XLA only);
        1: it runs on the whole block to the end.
      addresses: {id of a shared lane: (the lane, (space, position))}, the values a
        GPU kernel can load by position (its parameters; the `Uniforms` add theirs, in
        space "u", by their order): a scan over such values stays a loop
        (`control._scan_loaded`), else scans are unrolled.
      load: `(space, position, dtype, scope) -> lane`, the kernel's load of an address
        (None: outside a kernel, the lanes themselves); scope: a dict, one per loop body
        traced, where the load may keep what it builds for the body's later loads.
      tables: a `control.Tables` of the constant tables such loops index (space "c").

    Returns: one object array of lanes per output of the program.
    """
    ctx = _Ctx(_shape(block), any_lane or _any_lane_default, unroll, materialize, fast_math)
    ctx.unsupported = frozenset(unsupported)
    ctx.int_anchor = int_anchor
    ctx.ptx = ptx
    ctx.uniforms = uniforms
    ctx.bool_carries = bool_carries
    ctx.roll_scans = roll_scans
    ctx.addresses, ctx.load, ctx.tables = addresses, load, tables
    if uniforms is not None:
        uniforms.addresses = addresses
    ctx.compact = int(compact)
    ctx.rewrite = rewrite if (fast_math or ptx) else None
    ctx.eval_closed = functools.partial(_eval_closed, ctx=ctx)
    ctx.rows = any(isinstance(x, Row) for a in args for x in a.reshape(-1))
    if roll_scans:  # a table of the 0-d parameter lanes, for rolled scans to gather from
        ctx.param_table = _param_table(args, ctx.param_pos)
    for a in args:  # a traced per-ray input: constants become lanes through it
        for x in a.reshape(-1):
            if isinstance(x, Row):
                continue
            if ctx.anchor is None and not _is_const(x) and tuple(jnp.shape(x)) == ctx.block \
                    and jnp.issubdtype(x.dtype, jnp.floating):
                ctx.anchor = x
    return _eval_closed(closed, list(args), ctx, keep_rows=keep_rows)
