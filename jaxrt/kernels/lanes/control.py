"""Control flow on lanes: calls, `while`, `scan` and `cond`.

A `while` whose condition varies between rays becomes one loop over the block that runs
while any lane is active; inactive lanes keep their state (the semantics of `vmap` of a
while loop). `cond` with a per-ray index evaluates every branch and selects lane-wise
(on XLA, a block in which no ray takes branch 1 of two skips it). A `scan` is
unrolled, or with `roll_scans` (the "fused" backend) kept as one loop over lanes
(`_scan_rolled`), or in a Pallas kernel, when it scans the kernel's parameters, as
one loop that loads them (`_scan_loaded`). Calls are inlined; on XLA their results are
materialised once (`_barrier`). Inner jaxprs are evaluated by `ctx.eval_closed` (the
interpreter)."""

import jax.numpy as jnp
import numpy as np
from jax import lax

from .elementwise import _apply, _fold, _select
from .jax_internals import (ClosedJaxpr, Jaxpr, _closed, _scan_counts, dce_jaxpr, has_while,
                            while_parts)
from .values import (Row, Unsupported, _broadcast, _convert, _is_const, _lane_shape, _obj,
                     resolve, resolve_lane)

def _call(eqn, ins, ctx):
    closed = _closed(eqn)
    if closed is None:
        raise Unsupported(f"{eqn.primitive.name}: no inner jaxpr found")
    # a call runs in its caller's trace scope: its results may stay `Row`s
    outs = ctx.eval_closed(closed, ins, keep_rows=True)
    if ctx.materialize and ctx.loop_depth == 0:
        outs = _barrier([resolve(o, ctx) for o in outs])
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


def _carries(avals, ctx):
    """(pack, unpack) of a loop's state: `pack` holds every element of the carried
    values (of `avals`) as a full lane of the block, bools as int32 unless
    ctx.bool_carries (a Triton kernel carries predicates, which saves a conversion
    each way per step); `unpack` gives the object arrays back."""
    shapes = [a.shape for a in avals]
    dtypes = [np.dtype(a.dtype) for a in avals]

    def store_dtype(dt):
        return np.dtype(np.int32) if dt == np.dtype(bool) and not ctx.bool_carries else dt

    def pack(objs):
        return [_broadcast(_convert(x, store_dtype(dt), ctx), ctx.block, store_dtype(dt), ctx)
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

    return pack, unpack


def _while(eqn, ins, ctx):
    cn, bn, cond_j, body_j = while_parts(eqn.params)
    cconsts, bconsts = ins[:cn], ins[cn:cn + bn]
    init = [resolve(x, ctx) for x in ins[cn + bn:]]
    used = ctx.used_outputs or [True] * len(init)
    cond_j, body_j, cconsts, bconsts, keep = _prune_loop(cond_j, body_j, cconsts, bconsts, used)
    full_init = init
    init = [x for x, k in zip(init, keep) if k]
    avals = [v.aval for v, k in zip(eqn.outvars, keep) if k]
    block = ctx.block
    # the loop state (`_carries`); in a compacted loop (`_compacted`) the block is the
    # narrow one while its second body is traced
    pack, unpack = _carries(avals, ctx)

    def cond_lanes(objs, consts=cconsts):
        # a batched while (vmap inside the one-ray program) has a predicate of shape S
        # (the leading axes of every carry): it runs while any element is true
        (c,) = ctx.eval_closed(cond_j, list(consts) + objs)
        return _fold(list(c.reshape(-1)), "or", np.dtype(bool), ctx)

    def step(state, consts=(cconsts, bconsts)):
        flat, active = state
        objs = unpack(flat)
        new = ctx.eval_closed(body_j, list(consts[1]) + objs)
        (c,) = ctx.eval_closed(cond_j, list(consts[0]) + objs)
        if c.shape != ():
            # ... and only its elements whose predicate holds take a step (the body does
            # not mask itself: XLA's lowering of a batched while selects per element)
            new = [_select_elements(c, n, o) for n, o in zip(new, objs)]
        new_flat = pack(new)
        flat = [jnp.where(active, n, o) for n, o in zip(new_flat, flat)]
        still = cond_lanes(unpack(flat), consts[0])
        active = active & _broadcast(still, ctx.block, bool, ctx)
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
        if _compacts(ctx) and not _uniform_condition(cond_j, body_j, cconsts, bconsts, init):
            flat = _compacted(flat0, active0, (cconsts, bconsts), step, ctx)
        else:
            flat, _ = lax.while_loop(cond_fn, body_fn, (flat0, active0))
    finally:
        ctx.loop_depth -= 1
    results = iter(unpack(flat))
    # carries that nothing reads keep their initial value (placeholders)
    return [next(results) if k else x for x, k in zip(full_init, keep)]


def _compacts(ctx):
    """Whether a `while` on this block may narrow to its active rays (`_compacted`): on
    XLA with `ctx.compact` > 1, outside another narrowed loop, to at least
    `ctx.compact_min` lanes."""
    n = int(np.prod(ctx.block))
    return ctx.compact > 1 and not ctx.compacting and n // ctx.compact >= ctx.compact_min


def _uniform_condition(cond_j, body_j, cconsts, bconsts, init):
    """Whether a loop's condition is the same for every ray: it reads (through the
    body's updates, to a fixed point) only carries that start equal for all rays and
    constants shared by all rays. A loop of a static count (`march.search.repeat`)
    has such a condition: all rays stop together, and narrowing would gain nothing."""
    def shared(obj):
        return all(_is_const(x) or (isinstance(x, Row) and x.arr.ndim == 1)
                   or (not isinstance(x, Row) and jnp.shape(x) == ()) for x in obj.reshape(-1))

    nc, nb, n = len(cconsts), len(bconsts), len(init)
    _, reads = dce_jaxpr(cond_j.jaxpr, [True])
    if not all(shared(c) for c, r in zip(cconsts, reads[:nc]) if r):
        return False
    need = {k for k, r in enumerate(reads[nc:]) if r}
    while True:
        _, reads = dce_jaxpr(body_j.jaxpr, [k in need for k in range(n)])
        if not all(shared(c) for c, r in zip(bconsts, reads[:nb]) if r):
            return False
        more = {k for k, r in enumerate(reads[nb:]) if r} - need
        if not more:
            break
        need |= more
    return all(shared(init[k]) for k in need)


def _compacted(flat0, active0, consts, step, ctx):
    """A `while` over a block of N rays that narrows to its last W = N / ctx.compact
    active rays: the loop runs on the whole block while more than W rays are active,
    then on those W rays alone, gathered into a narrow block, and writes them back.

    Sphere tracing is divergent: on the showcase (480×270, 32×32 tiles) the slowest
    camera ray of a tile takes 2.8× the tile's mean number of steps (grazing rays near
    silhouettes up to 400), and a block loop runs until its slowest ray is done, every
    step on all N lanes. The narrow loop's steps cost W lanes each. Each ray takes
    exactly the steps it would take in the block loop, so the results are the same,
    lane for lane. The loop body is traced twice (once per width). The narrow loop
    reads the per-ray constants of the body (its [block] lanes and the [n, *block]
    arrays of `Row`s) gathered like the state. On XLA only (a Triton kernel has no
    gather across its lanes); `KernelOptions.compaction`.

    Args: flat0, active0: the packed initial state ([block] arrays) and which rays
    enter the loop; consts: (cond consts, body consts) as lists of object arrays;
    step: `step(state, consts)` of `_while` at the current `ctx.block`. Returns the
    final packed state ([block] arrays).
    """
    block = ctx.block
    n = int(np.prod(block))
    width = n // ctx.compact

    def body(state, local=consts):
        ctx.scopes.append({})
        try:
            for _ in range(ctx.unroll):
                state = step(state, local)
        finally:
            ctx.scopes.pop()
        return state

    flat, active = lax.while_loop(lambda s: jnp.sum(s[1], dtype=jnp.int32) > width, body,
                                  (flat0, active0))
    # the per-ray arrays the body reads (its [block] constants, the anchor of constant
    # lanes and the [n, *block] arrays behind Rows), gathered like the state
    per_ray = {}
    anchor = _obj(())
    anchor[()] = ctx.anchor
    for obj in (*consts[0], *consts[1], anchor):
        for x in obj.reshape(-1):
            a = x.arr if isinstance(x, Row) else x
            if a is None or _is_const(a):
                continue
            shape = tuple(jnp.shape(a))
            if (shape[1:] if isinstance(x, Row) else shape) == block:
                per_ray[id(a)] = a
    rows = jnp.nonzero(active.reshape(n), size=width, fill_value=n)[0]
    take = jnp.minimum(rows, n - 1)
    narrow = {key: a.reshape(a.shape[:a.ndim - len(block)] + (n,))[..., take]
              for key, a in per_ray.items()}

    def substitute(obj):
        out = _obj(obj.shape)
        for idx in np.ndindex(obj.shape):
            x = obj[idx]
            if isinstance(x, Row):
                out[idx] = Row(narrow[id(x.arr)], x.i) if id(x.arr) in narrow else x
            else:
                out[idx] = narrow.get(id(x), x) if not _is_const(x) else x
        return out

    local = tuple([substitute(obj) for obj in c] for c in consts)
    state = ([f.reshape(n)[take] for f in flat], active.reshape(n)[take] & (rows < n))
    saved = ctx.block, ctx.anchor
    ctx.block, ctx.compacting = (width,), True
    ctx.anchor = narrow.get(id(ctx.anchor), ctx.anchor)
    try:
        work, _ = lax.while_loop(lambda s: ctx.any_lane(s[1]),
                                 lambda s: body(s, local), state)
    finally:
        (ctx.block, ctx.anchor), ctx.compacting = saved, False
    return [f.reshape(n).at[rows].set(w, mode="drop").reshape(block)
            for f, w in zip(flat, work)]


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
    would be). With ctx.roll_scans (the "fused" XLA backend) a scan stays a loop
    (`_scan_rolled`): one copy of its body, whatever n (`Union`'s stacked children, a
    material taken by index, the lights), also for n = 1, so that the program of a
    scene does not change with how many things of a kind it has. In a Pallas kernel
    (ctx.addresses) a scan of at least `LOADED_SCAN_MIN` iterations over values it can
    load, with no loop in its body and no stacked output read, is one loop too
    (`_scan_loaded`)."""
    p = eqn.params
    nc, nk = _scan_counts(p)
    length = p["length"]
    closed = p["jaxpr"]
    if isinstance(closed, Jaxpr):
        closed = ClosedJaxpr(closed, ())
    consts, carry, xs = ins[:nc], [resolve(c, ctx) for c in ins[nc:nc + nk]], ins[nc + nk:]
    if ctx.roll_scans and length > 0:
        return _scan_rolled(eqn, closed, consts, carry, xs, length, p["reverse"], ctx)
    used = ctx.used_outputs or [True] * len(eqn.outvars)
    if ctx.addresses is not None and length >= LOADED_SCAN_MIN and not any(used[nk:]) \
            and not has_while(closed):
        loads = _loads(xs, eqn.invars[len(eqn.invars) - len(xs):], length, ctx)
        if loads is not None:
            return _scan_loaded(eqn, closed, consts, carry, loads, length, p["reverse"], ctx)
    xs = [resolve(x, ctx) for x in xs]
    order = range(length - 1, -1, -1) if p["reverse"] else range(length)
    ys = [None] * length
    for i in order:
        outs = ctx.eval_closed(closed, [*consts, *carry, *[x[i, ...] for x in xs]])
        carry, ys[i] = list(outs[:nk]), outs[nk:]
    stacked = []
    for k, v in enumerate(eqn.outvars[nk:]):
        out = _obj(v.aval.shape)
        for i in range(length):
            out[i, ...] = ys[i][k]
        stacked.append(out)
    return carry + stacked


def _scan_rolled(eqn, closed, consts, carry, xs, length, reverse, ctx):
    """A scan as one `lax.scan` over lanes: each carried element a [block] array (bools
    as int32 unless ctx.bool_carries), each scanned element its `length` lanes stacked
    ([length] when they are shared by all rays, else [length, *block]), each element of
    a stacked output a [length, *block] array whose rows are `Row` lanes; the body is
    interpreted once."""
    block = ctx.block
    nk = len(carry)
    pack, unpack = _carries([v.aval for v in eqn.outvars[:nk]], ctx)
    y_avals = [v.aval for v in eqn.outvars[nk:]]
    y_dtypes = [np.dtype(a.dtype) for a in y_avals]

    # scanned inputs: element idx of x over the iterations, as one array
    xs_flat, xs_meta = [], []
    for x, var in zip(xs, eqn.invars[len(eqn.invars) - len(xs):]):
        dt = np.dtype(var.aval.dtype)
        elem_shape = x.shape[1:]
        for idx in np.ndindex(elem_shape):
            lanes = [x[(i,) + idx] for i in range(length)]
            arr = lanes[0].arr if isinstance(lanes[0], Row) else None
            if arr is not None and all(isinstance(v, Row) and v.arr is arr for v in lanes):
                # rows of one array: the stacked outputs of another rolled scan (a
                # gradient's residuals), or a stacked leaf of the scene
                rows = [v.i for v in lanes]
                whole = rows == list(range(arr.shape[0]))
                xs_flat.append((arr if whole else arr[np.asarray(rows)]).astype(dt))
            elif all(id(v) in ctx.param_pos for v in lanes) and \
                    len({ctx.param_pos[id(v)][0] for v in lanes}) == 1:
                # parameters of the program: one gather from their table (built once,
                # outside every loop), not a stack of n lanes at every site
                table = ctx.param_table[ctx.param_pos[id(lanes[0])][0]]
                xs_flat.append(table[np.asarray([ctx.param_pos[id(v)][1] for v in lanes])].astype(dt))
            elif all(_is_const(v) for v in lanes):
                xs_flat.append(np.asarray([np.asarray(v, dt) for v in lanes], dt))
            else:
                lanes = [resolve_lane(v, ctx) for v in lanes]
                if all(_lane_shape(v) == () for v in lanes):
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
            outs = ctx.eval_closed(closed, [*consts, *unpack(flat), *unpack_xs(x_flat)])
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
    # stacked outputs: lane i of an element is row i of its array, sliced where read (a
    # rolled scan that scans over them takes the array itself)
    stacked, k = [], 0
    for aval in y_avals:
        obj = _obj(aval.shape)
        for idx in np.ndindex(aval.shape[1:]):
            arr = ys_flat[k]
            k += 1
            for i in range(length):
                obj[(i,) + idx] = Row(arr, i)
        stacked.append(obj)
        ctx.rows = True
    return unpack(flat) + stacked


#: The shortest scan that `_scan_loaded` keeps as a loop (shorter ones are unrolled: a
#: light or two, a material of one kind). A scan whose body holds a `while` (the slots of
#: a ray tree, each with its marches) is unrolled too: Triton compiled the glass scene's
#: tree as such a loop for 148 s on an H100 (its union's children are loops either way).
LOADED_SCAN_MIN = 4


class Tables:
    """The constant tables that loaded scans index (`_loads`: the constant material
    indices of a union's children, say), each at its position in one vector of
    `dtype`: collected by the run of the program outside the kernel, stored by the
    kernel after its parameters (space "c"), and found again by the kernel's run."""

    def __init__(self, dtype):
        self.dtype = np.dtype(dtype)
        self.positions = {}
        self.arrays = []
        self.size = 0
        self.frozen = False  # the kernel's run: no table is added any more

    def position(self, values, dtype):
        """The position of the table of `values` (numpy scalars of `dtype`), added if
        new (unless `frozen`); None when `self.dtype` cannot hold them exactly, or
        when it is new to a frozen collection (the loop is then unrolled)."""
        a = np.asarray(values, dtype)
        with np.errstate(all="ignore"):
            if not np.array_equal(a.astype(self.dtype).astype(dtype), a):
                return None
        key = (a.dtype.str, a.tobytes())
        if key not in self.positions:
            if self.frozen:
                return None
            self.positions[key] = self.size
            self.arrays.append(a.astype(self.dtype))
            self.size += a.size
        return self.positions[key]


def _loads(xs, invars, length, ctx):
    """How a loaded scan (`_scan_loaded`) takes iteration i of each scanned input: per
    element of an input, `("const", c)` when every iteration's lane is the constant c,
    or `("load", lanes, space, base, stride)` when each lane i is a value that the
    kernel can load at position base + i·stride of `space` (`ctx.addresses`: a
    parameter of the program, or a shared value the `Uniforms` computed outside the
    kernel; constants that differ between iterations: a table of `ctx.tables`). None
    when some element is none of these (the scan is then unrolled)."""
    plan = []
    for x, var in zip(xs, invars):
        dt = np.dtype(var.aval.dtype)
        elems = _obj(x.shape[1:])
        for idx in np.ndindex(elems.shape):
            lanes = [x[(i,) + idx] for i in range(length)]
            if all(_is_const(v) for v in lanes):
                if len({np.asarray(v).tobytes() for v in lanes}) == 1:
                    elems[idx] = ("const", lanes[0])
                    continue
                base = None if ctx.tables is None else ctx.tables.position(lanes, dt)
                if base is None:
                    return None
                elems[idx] = ("load", lanes, "c", base, 1)
                continue
            where = [ctx.addresses.get(id(v)) for v in lanes]
            if any(w is None or w[0] is not v for w, v in zip(where, lanes)):
                return None
            spaces = {w[1][0] for w in where}
            base = where[0][1][1]
            stride = where[1][1][1] - base
            if len(spaces) != 1 or any(w[1][1] != base + i * stride for i, w in enumerate(where)):
                return None
            elems[idx] = ("load", lanes, spaces.pop(), base, stride)
        plan.append((elems, dt))
    return plan


def _scan_loaded(eqn, closed, consts, carry, loads, length, reverse, ctx):
    """A scan as one `lax.fori_loop` in a GPU kernel (Pallas, `ctx.addresses`), one copy
    of its body, whatever n: a stacked union of n primitives at every site that
    evaluates the SDF. Triton holds no array it could index by the loop's counter, so
    iteration i loads its scanned values from the kernel's parameters (`_loads`:
    `ctx.load(space, position, dtype, scope)`, scope: the body's cache; the `Uniforms`'
    recording run outside the kernel reads the same values from XLA arrays,
    `fused._recording_load`); without `ctx.load` it indexes their lanes stacked.
    Carries are full lanes (`_carries`); the scan's stacked outputs are unused (`_scan`
    checks)."""
    nk = len(carry)
    pack, unpack = _carries([v.aval for v in eqn.outvars[:nk]], ctx)
    stacked = {}
    if ctx.load is None:
        for elems, dt in loads:
            for spec in elems.flat:
                if spec[0] == "load":
                    stacked[id(spec[1])] = jnp.stack([jnp.asarray(v, dt) for v in spec[1]])

    def take(spec, dt, i):
        if spec[0] == "const":
            return spec[1]
        _, lanes, space, base, stride = spec
        if ctx.load is None:
            return stacked[id(lanes)][i]
        return ctx.load(space, base + i * stride, dt, ctx.scopes[-1])

    def body(k, flat):
        i = length - 1 - k if reverse else k
        ctx.scopes.append({})
        try:
            xs = []
            for elems, dt in loads:
                obj = _obj(elems.shape)
                for idx in np.ndindex(elems.shape):
                    obj[idx] = take(elems[idx], dt, i)
                xs.append(obj)
            outs = ctx.eval_closed(closed, [*consts, *unpack(flat), *xs])
        finally:
            ctx.scopes.pop()
        return pack(outs[:nk])

    ctx.loop_depth += 1
    try:
        flat = lax.fori_loop(0, length, body, pack(carry))
    finally:
        ctx.loop_depth -= 1
    # the stacked outputs, which nothing reads
    unused = [np.full(v.aval.shape, np.zeros((), v.aval.dtype)[()], dtype=object)
              for v in eqn.outvars[nk:]]
    return unpack(flat) + unused


def _prune_loop(cond_j, body_j, cconsts, bconsts, used):
    """Drop the carries of a while loop that neither its used results nor its condition
    need (a march that also tracks a closest approach nobody reads, say). Returns the
    pruned (cond, body, cond consts, body consts) and the mask of kept carries."""
    n = len(used)
    nc, nb = len(cconsts), len(bconsts)
    if cond_j.consts or body_j.consts:
        return cond_j, body_j, cconsts, bconsts, [True] * n
    _, cond_in = dce_jaxpr(cond_j.jaxpr, [True])
    keep = [bool(u) or bool(c) for u, c in zip(used, cond_in[nc:])]
    while True:
        _, body_in = dce_jaxpr(body_j.jaxpr, keep)
        new = [k or bool(b) for k, b in zip(keep, body_in[nb:])]
        if new == keep:
            break
        keep = new
    if all(keep):
        return cond_j, body_j, cconsts, bconsts, keep
    cond_new, cond_used = dce_jaxpr(cond_j.jaxpr, [True], instantiate=[True] * nc + keep)
    body_new, body_used = dce_jaxpr(body_j.jaxpr, keep, instantiate=[True] * nb + keep)
    cond_new = ClosedJaxpr(cond_new, ())
    body_new = ClosedJaxpr(body_new, ())
    return cond_new, body_new, cconsts, bconsts, keep


def _cond(eqn, ins, ctx):
    index, ops = ins[0][()], ins[1:]
    branches = eqn.params["branches"]
    if _is_const(index):
        return ctx.eval_closed(branches[int(index)], ops)
    if ctx.roll_scans and len(branches) == 2:
        return _cond_skipping(eqn, index, ops, ctx)
    outs = [ctx.eval_closed(b, ops) for b in branches]
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


def _cond_skipping(eqn, index, ops, ctx):
    """A two-branch `cond` with a per-ray index, on XLA: branch 1 runs only in blocks
    where some ray takes it, lax.cond(any lane, select(index, branch 1, branch 0),
    branch 0). Branch 0 runs for every block (`tape.cond`'s: the cheap one, such as a
    dead ray of the tree), so a block of rays that all skip pays for branch 0 alone."""
    branches = eqn.params["branches"]
    block = ctx.block
    take = _apply("ne", index, np.asarray(0, index.dtype)[()], dtype=np.dtype(bool), ctx=ctx)
    base = [resolve(o, ctx) for o in ctx.eval_closed(branches[0], ops)]
    where = [(k, idx, var.aval.dtype) for k, (o, var) in enumerate(zip(base, eqn.outvars))
             for idx in np.ndindex(o.shape)]
    base_flat = [_broadcast(base[k][idx], block, dt, ctx) for k, idx, dt in where]

    def run():
        ctx.scopes.append({})
        ctx.loop_depth += 1
        try:
            outs = [resolve(o, ctx) for o in ctx.eval_closed(branches[1], ops)]
            return [_broadcast(_select(take, x, outs[k][idx], dt, ctx), block, dt, ctx)
                    for (k, idx, dt), x in zip(where, base_flat)]
        finally:
            ctx.loop_depth -= 1
            ctx.scopes.pop()

    flat = lax.cond(ctx.any_lane(_broadcast(take, block, bool, ctx)), run, lambda: base_flat)
    result = [_obj(o.shape) for o in base]
    for (k, idx, _), x in zip(where, flat):
        result[k][idx] = x
    return result
