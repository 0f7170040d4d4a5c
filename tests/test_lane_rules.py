"""jaxrt.kernels.lanes, rule by rule: each primitive's rule (elementwise, structural,
indexing), each control-flow rule (while, scan, cond, calls) and the GPU rewrites,
checked against plain JAX (`jax.vmap` of the same one-ray function) on small inputs.
Every case first checks that its jaxpr holds the primitive it is meant to test."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import lax

from jaxrt.kernels.lanes import eval_lanes, lanes_of, stack_lanes
from jaxrt.kernels.lanes import gpu, values
from jaxrt.kernels.lanes.jax_internals import ClosedJaxpr, Jaxpr

N = 7  # rays


def _lane(x):
    out = np.empty((), dtype=object)
    out[()] = x
    return out


def primitives(jaxpr):
    """Names of the primitives of a jaxpr, its inner jaxprs included."""
    names = set()
    for eqn in jaxpr.eqns:
        names.add(eqn.primitive.name)
        for p in eqn.params.values():
            for sub in p if isinstance(p, (list, tuple)) else [p]:
                if isinstance(sub, ClosedJaxpr):
                    names |= primitives(sub.jaxpr)
                elif isinstance(sub, Jaxpr):
                    names |= primitives(sub)
    return names


def inputs(dtype=np.float64):
    rng = np.random.default_rng(3)
    params = rng.normal(size=12).astype(dtype)
    a = np.concatenate([[0.5, -1.5, 2.5], rng.uniform(-2, 2, N - 3)]).astype(dtype)  # halves
    b = rng.uniform(-1, 1, N).astype(dtype)
    return params, a, b


def lanes_and_vmap(fn, params, a, b, **options):
    """(lanes, vmap) outputs of `fn(params, a, b)` on N rays; the parameters are traced
    (shared lanes), as in a render."""
    closed = jax.make_jaxpr(fn)(params, a[0], b[0])

    @jax.jit
    def lanes(params, a, b):
        outs = eval_lanes(closed, [lanes_of(params), _lane(a), _lane(b)], N, **options)
        return [stack_lanes(o, N, v.aval.dtype) for o, v in zip(outs, closed.jaxpr.outvars)]

    want = jax.tree_util.tree_leaves(jax.vmap(fn, in_axes=(None, 0, 0))(jnp.asarray(params), a, b))
    return closed, [np.asarray(x) for x in lanes(params, a, b)], [np.asarray(x) for x in want]


def lane_program(closed, params, a, b, **options):
    """The lane program (a ClosedJaxpr) that `eval_lanes` builds from `closed`."""
    def lanes(p, a, b):
        outs = eval_lanes(closed, [lanes_of(p), _lane(a), _lane(b)], N, **options)
        return [stack_lanes(o, N, v.aval.dtype) for o, v in zip(outs, closed.jaxpr.outvars)]

    return jax.make_jaxpr(lanes)(params, a, b)


def lane_program_primitives(closed, params, a, b, **options):
    """The primitives of the lane program that `eval_lanes` builds from `closed`."""
    return primitives(lane_program(closed, params, a, b, **options).jaxpr)


def test_equations_that_rules_build_print():
    """Rules build equations of `jax.lax` primitives (rounding from floor, products of a
    reduction) with the parameters `jax.lax` gives them on this JAX: printing a jaxpr
    reads `mul`'s `out_dtype` (a KeyError when it was missing, in every Pallas program)."""
    def fn(p, a, b):
        return lax.round(a * p[0], lax.RoundingMethod.TO_NEAREST_EVEN) + jnp.prod(jnp.stack([a, b, p[1]]))

    params, a, b = inputs()
    program = lane_program(jax.make_jaxpr(fn)(params, a[0], b[0]), params, a, b)
    reference = jax.make_jaxpr(lax.mul)(1.0, 1.0).eqns[0].params
    muls = [e for e in program.jaxpr.eqns if e.primitive.name == "mul"]
    assert muls and all(dict(e.params) == dict(reference) for e in muls)
    assert "mul" in str(program)


def index(a, n):
    return jnp.clip(jnp.floor(jnp.abs(a) * n / 2).astype(jnp.int32), 0, n - 1)


# (name, primitive the jaxpr must hold, one-ray function)
RULES = [
    ("select_n", "select_n", lambda p, a, b: jnp.where(a > b, a * p[0] + b, b - a)),
    ("integer_pow", "integer_pow", lambda p, a, b: a ** 3 + b ** 2),
    ("atan2", "atan2", lambda p, a, b: jnp.arctan2(a, b + p[1])),
    ("convert", "convert_element_type", lambda p, a, b: (a * 3).astype(jnp.int32)),
    ("broadcast_reshape", "reshape",
     lambda p, a, b: (jnp.broadcast_to(a, (2, 3)) * p[:6].reshape(2, 3)).reshape(3, 2)),
    ("transpose", "transpose", lambda p, a, b: (p[:6].reshape(2, 3) * b).T),
    ("rev", "rev", lambda p, a, b: jnp.flip(jnp.stack([a, b, p[0]]))),
    ("slice", "slice", lambda p, a, b: jnp.stack([a, b, a * b, p[0]])[1:3]),
    ("concatenate", "concatenate", lambda p, a, b: jnp.concatenate([jnp.stack([a, b]), p[:2]])),
    ("pad", "pad", lambda p, a, b: jnp.pad(jnp.stack([a, b]), (1, 2), constant_values=p[0])),
    # a 1-D operand: each result is a 0-d value (the CSG study's gradient step; jax 0.11
    # also unstacks in `for x in v`), and one of a matrix's rows
    ("unstack_vector", "unstack", lambda p, a, b: [x * a for x in jnp.unstack(jnp.stack([b, p[0]]))]),
    ("unstack_one", "unstack",
     lambda p, a, b: jnp.broadcast_to(jnp.unstack(jnp.stack([a * b]))[0], (2,)) + p[:2]),
    ("unstack_matrix", "unstack",
     lambda p, a, b: jnp.unstack(p[:6].reshape(2, 3) * jnp.stack([a, b, a]), axis=1)),
    ("iota", "iota", lambda p, a, b: jnp.arange(4.0) * a),
    ("reduce_sum", "reduce_sum", lambda p, a, b: jnp.sum(jnp.stack([a, b, p[0]]) ** 2)),
    ("reduce_max", "reduce_max", lambda p, a, b: jnp.max(jnp.stack([a, b, p[0]]))),
    ("reduce_min", "reduce_min", lambda p, a, b: jnp.min(jnp.stack([a, b, p[0]]))),
    ("argmax", "argmax", lambda p, a, b: jnp.argmax(jnp.stack([a, b, p[0], b]))),
    ("argmin", "argmin", lambda p, a, b: jnp.argmin(jnp.stack([a, b, p[0], a]))),
    ("dot_general", "dot_general", lambda p, a, b: p[:9].reshape(3, 3) @ jnp.stack([a, b, a * b])),
    ("round_away", "round", lambda p, a, b: lax.round(a, lax.RoundingMethod.AWAY_FROM_ZERO)),
    ("round_even", "round", lambda p, a, b: lax.round(a, lax.RoundingMethod.TO_NEAREST_EVEN)),
    ("gather_const", "gather", lambda p, a, b: p[jnp.array([3, 1, 1])] * a),
    ("gather_per_ray", "gather", lambda p, a, b: p[:4][jnp.stack([index(a, 4), 1])] + b),
    ("gather_two_per_ray", "gather",
     lambda p, a, b: p[:9].reshape(3, 3)[jnp.stack([index(a, 3), 2]), jnp.stack([1, index(b, 3)])]),
    ("dynamic_slice", "dynamic_slice", lambda p, a, b: lax.dynamic_slice(p[:5] * b, (index(a, 4),), (2,))),
    ("scatter", "scatter", lambda p, a, b: jnp.zeros(4).at[index(a, 4)].set(b)),
    ("scatter_add", "scatter-add", lambda p, a, b: jnp.zeros(4).at[2].add(b).at[index(a, 4)].add(a)),
    ("dynamic_update_slice", "dynamic_update_slice",
     lambda p, a, b: lax.dynamic_update_slice(p[:5], jnp.stack([a, b]), (index(b, 4),))),
]


@pytest.mark.parametrize("name,prim,fn", RULES, ids=[r[0] for r in RULES])
def test_rule_matches_jax(name, prim, fn):
    closed, got, want = lanes_and_vmap(fn, *inputs())
    assert prim in primitives(closed.jaxpr), primitives(closed.jaxpr)
    for g, w in zip(got, want, strict=True):
        assert g.dtype == w.dtype, (g.dtype, w.dtype)
        np.testing.assert_allclose(g, w, rtol=1e-13, atol=1e-14)


def _march(p, a, b):
    """A while loop whose trip count varies per ray."""
    def cond(s):
        k, t = s
        return (k < 40) & (t < jnp.abs(a) * 4.0 + p[0] ** 2)

    def body(s):
        k, t = s
        return k + 1, t + 0.25 + 0.1 * jnp.abs(b)

    k, t = lax.while_loop(cond, body, (0, 0.0))
    return k, t


def _batched_while(p, a, b):
    """A while loop vmapped inside the one-ray program (a batch of rays of a ray tree):
    its predicate has a shape; each element stops on its own."""
    return jax.vmap(lambda x: _march(p, x, b))(jnp.stack([a, 2 * a, b]))


def _scan(p, a, b):
    def step(c, x):
        return c * 0.5 + x * a, c + x
    c, ys = lax.scan(step, b, p[:5])
    return c, ys


def _scan_carry_only(p, a, b):
    def step(c, x):
        d, m = c
        take = x[0] * a + x[1] < d
        return (jnp.where(take, x[0] * a + x[1], d), jnp.where(take, x[1], m)), None
    (d, m), _ = lax.scan(step, (jnp.inf + 0 * a, 0.0 * b), p[:8].reshape(4, 2))
    return d, m


def _scan_reverse(p, a, b):
    return lax.scan(lambda c, x: (c * a + x, c), b, p[:4], reverse=True)


def _switch(p, a, b):
    return lax.switch(index(a, 3), [lambda x: x + p[0], lambda x: x * 2.0, jnp.sin], b)


def _cond_shared(p, a, b):
    """A cond whose predicate is shared by all rays (a parameter)."""
    return lax.cond(p[0] > 0, lambda x: x * a, lambda x: x - a, b)


def _cond_per_ray(p, a, b):
    """`tape.cond`'s form: a per-ray predicate, a loop in the taken branch, a cheap other."""
    def live(x):
        return lax.while_loop(lambda c: c[1] < 3.0, lambda c: (c[0] * p[1] + a, c[1] + 1.0), (x, 0.0))[0]

    return lax.cond(a > p[2], live, lambda x: x * 0.0, b)


@jax.custom_jvp
def _softplus(x):
    return jnp.log1p(jnp.exp(x))


_softplus.defjvp(lambda primals, tangents: (_softplus(primals[0]),
                                            jax.nn.sigmoid(primals[0]) * tangents[0]))

def _side(p, a, b):
    """A side decided once (`sdf.primitives.sd_cone`): a barrier on a predicate."""
    return jnp.where(lax.optimization_barrier(a * b + p[0] > 0.0), a, -b)


CONTROL = [
    ("while", "while", _march, {}),
    ("while_unroll_3", "while", _march, dict(unroll=3)),
    ("while_batched", "while", _batched_while, {}),
    ("scan_unrolled", "scan", _scan, {}),
    ("scan_rolled", "scan", _scan, dict(roll_scans=True)),
    ("scan_carry_only_rolled", "scan", _scan_carry_only, dict(roll_scans=True)),
    ("scan_reverse", "scan", _scan_reverse, dict(roll_scans=True)),
    ("switch_per_ray", "cond", _switch, {}),
    ("cond_shared", "cond", _cond_shared, {}),
    ("cond_per_ray", "cond", _cond_per_ray, {}),
    ("cond_per_ray_skipping", "cond", _cond_per_ray, dict(roll_scans=True)),
    ("jit_call", "jit", lambda p, a, b: jax.jit(lambda x, y: x * y + p[0])(a, b), {}),
    ("jit_call_materialized", "jit", lambda p, a, b: jax.jit(lambda x: x * p[1])(a) + b,
     dict(materialize=True)),
    ("custom_jvp", "custom_jvp_call", lambda p, a, b: _softplus(a * b), {}),
    ("barrier", "optimization_barrier", lambda p, a, b: _side(p, a, b), {}),
    ("barrier_materialized", "optimization_barrier", lambda p, a, b: _side(p, a, b),
     dict(materialize=True)),
]


@pytest.mark.parametrize("name,prim,fn,options", CONTROL, ids=[c[0] for c in CONTROL])
def test_control_flow_rule_matches_jax(name, prim, fn, options):
    params, a, b = inputs()
    for p0 in (1.0, -1.0):  # both branches of a shared predicate
        params = params.copy()
        params[0] = p0 * abs(params[0])
        closed, got, want = lanes_and_vmap(fn, params, a, b, **options)
        names = primitives(closed.jaxpr)
        assert prim in names or (prim == "jit" and "pjit" in names), names
        for g, w in zip(got, want, strict=True):
            np.testing.assert_allclose(g, w, rtol=1e-13, atol=1e-14)


def _slot_buffer(p, a, b):
    """The ray tree of `recursion = "scan"` in small: a scan over 12 slots reads slot i
    of a buffer and writes two children at 2i + 1 (indices shared by all rays: the
    scan's counter), the leaves into scratch slots at the end."""
    slots = 12
    buf = jnp.zeros((slots + 2, 2), a.dtype).at[0].set(jnp.stack([a, b]))

    def step(buf, i):
        x = buf[i]
        kids = jnp.stack([x * p[0] + a, x[::-1] - b * p[1]])
        start = jnp.where(i < 5, 2 * i + 1, slots)
        return lax.dynamic_update_slice_in_dim(buf, kids, start, 0), x[0] * x[1]

    return lax.scan(step, buf, jnp.arange(slots))


@pytest.mark.parametrize("roll_scans", [False, True])
def test_shared_index_into_a_slot_buffer(roll_scans):
    """A dynamic slice and update at an index shared by all rays: enumerated as selects
    (unrolled scans), or on "fused" (rolled scans, more than `ENUMERATE_SHARED`
    candidates) one `dynamic_update_slice` of the stacked lanes in the lane program."""
    from jaxrt.kernels.lanes import indexing

    assert 14 - 2 + 1 > indexing.ENUMERATE_SHARED  # the candidates of a 2-row write
    params, a, b = inputs()
    closed, got, want = lanes_and_vmap(_slot_buffer, params, a, b, roll_scans=roll_scans)
    assert {"dynamic_slice", "dynamic_update_slice"} <= primitives(closed.jaxpr)
    for g, w in zip(got, want, strict=True):
        np.testing.assert_allclose(g, w, rtol=1e-13, atol=1e-14)

    names = lane_program_primitives(closed, params, a, b, roll_scans=roll_scans)
    assert ("dynamic_update_slice" in names) == roll_scans, names


@pytest.mark.parametrize("threshold", [-10.0, 0.0, 10.0], ids=["all", "some", "none"])
def test_per_ray_cond_skips_a_branch_no_ray_takes(threshold):
    """On "fused" (XLA) a two-branch cond with a per-ray predicate is a `cond` of the lane
    program on "some ray of the block takes branch 1": the same values when all, some
    or none of the rays take it (elsewhere every branch runs and lanes select)."""
    params, a, b = inputs()
    params[2] = threshold
    closed, got, want = lanes_and_vmap(_cond_per_ray, params, a, b, roll_scans=True)
    for g, w in zip(got, want, strict=True):
        np.testing.assert_allclose(g, w, rtol=1e-13, atol=1e-14)
    for roll_scans in (False, True):
        names = lane_program_primitives(closed, params, a, b, roll_scans=roll_scans)
        assert ("cond" in names) == roll_scans, names


def test_while_rule_steps_each_ray_as_often_as_alone():
    """The loop over the block runs until its last ray stops; every ray's trip count is
    the one it has alone (inactive lanes keep their state)."""
    params, a, b = inputs()
    _, (k, _), _ = lanes_and_vmap(_march, params, a, b)
    alone = [int(_march(params, a[i], b[i])[0]) for i in range(N)]
    assert k.tolist() == alone and len(set(alone)) > 1, (k, alone)


def test_values_constants_fold_at_trace_time():
    """A program of constants alone evaluates to constants (numpy scalars, no lanes);
    lanes_of/stack_lanes are inverse for per-ray lanes."""
    closed = jax.make_jaxpr(lambda x: jnp.sin(x) * 2.0 + jnp.arange(3.0))(np.float64(0.3))
    (out,) = eval_lanes(closed, [lanes_of(np.float64(0.3))], N)
    assert all(values._is_const(x) for x in out.reshape(-1))
    np.testing.assert_allclose(out.astype(float), np.sin(0.3) * 2 + np.arange(3.0), rtol=1e-15)
    x = jnp.arange(2 * 3 * N, dtype=jnp.float32).reshape(2, 3, N)
    obj = values._obj((2, 3))
    for idx in np.ndindex(2, 3):
        obj[idx] = x[idx]
    np.testing.assert_array_equal(np.asarray(stack_lanes(obj, N, jnp.float32)),
                                  np.moveaxis(np.asarray(x), -1, 0))


def test_arrays_of_constants_fold_in_one_call_as_element_by_element(monkeypatch):
    """Elementwise operations and reductions on arrays of constants fold at trace time
    at once (`elementwise._folded`, `_fold`: a stacked union's per-child constants),
    to the values of the same float32 operations element by element and in order."""
    import functools

    from jaxrt.kernels.lanes import elementwise

    folded, at_once = [], elementwise._folded
    monkeypatch.setattr(elementwise, "_folded", lambda *a: folded.append(a) or at_once(*a))
    c = np.linspace(-2.0, 3.0, elementwise.FOLD_AT_ONCE + 4).astype(np.float32)
    k = np.arange(c.size, dtype=np.int32) % 3

    def fn(x):
        y = c * k.astype(np.float32) + x
        return y, jnp.sum(y), jnp.max(y.at[4].set(np.nan)), jnp.any(k == 2), jnp.prod(y[1:4])

    closed = jax.make_jaxpr(fn)(np.float32(0.1))
    outs = eval_lanes(closed, [lanes_of(np.float32(0.1))], N)
    assert all(values._is_const(x) for o in outs for x in o.reshape(-1)) and folded
    y = [np.float32(ci * np.float32(ki) + np.float32(0.1)) for ci, ki in zip(c, k)]
    want = [np.asarray(y), functools.reduce(np.add, y), np.float32(np.nan), True,
            functools.reduce(np.multiply, y[1:4])]
    for o, w in zip(outs, want, strict=True):
        np.testing.assert_array_equal(o.astype(np.asarray(w).dtype), w)


def test_gpu_rewrites_keep_the_function():
    """The GPU rewrites in their interpret-mode forms (`fused._ptx_ops(True)`): fast math
    (sqrt, rsqrt, division, exp, log, pow) and fused multiply-adds give the plain
    program's float32 values within a few ulps; `gpu.rewrite` leaves shared (0-d)
    lanes alone."""
    from jaxrt.kernels.fused import _ptx_ops

    def fn(p, a, b):
        x = jnp.abs(a) + 0.5
        return (jnp.sqrt(x) * b + lax.rsqrt(x), a / (b + 2.0), b / p[0], jnp.exp(b) - jnp.log(x),
                x ** (b + 1.5), p[:3] @ jnp.stack([a, b, x]))

    params, a, b = (v.astype(np.float32) for v in inputs())
    params[0] = 1.7
    for options in (dict(fast_math=True), dict(fast_math=True, ptx=_ptx_ops(True)),
                    dict(ptx={"fma": _ptx_ops(True)["fma"]})):
        _, got, want = lanes_and_vmap(fn, params, a, b, **options)
        for g, w in zip(got, want, strict=True):
            np.testing.assert_allclose(g, w, rtol=4e-6, atol=1e-6)

    class Ctx:
        fast_math, ptx = True, None

    shared = jnp.float32(2.0)
    assert gpu.rewrite("sqrt", [shared], np.dtype(np.float32), Ctx()) is None
    lane = jnp.full((N,), 2.0, jnp.float32)
    np.testing.assert_allclose(gpu.rewrite("sqrt", [lane], np.dtype(np.float32), Ctx()),
                               np.sqrt(2.0), rtol=2e-7)
    assert gpu.rewrite("add", [lane, lane], np.dtype(np.float32), Ctx()) is None


def test_erfc_substitute_matches_jax():
    """Targets without erfc (Triton) run its Chebyshev fit (`gpu._erfc`) instead."""
    import jax.scipy.special as jss

    x = jnp.linspace(-4.0, 6.0, 101)
    closed = jax.make_jaxpr(jss.erfc)(x[0])
    assert "erfc" in primitives(closed.jaxpr)
    (got,) = eval_lanes(closed, [_lane(x)], x.shape[0], unsupported=("erfc",))
    np.testing.assert_allclose(np.asarray(got[()]), np.asarray(jss.erfc(x)), rtol=1.2e-7)


def test_a_barrier_materialises_its_values_once():
    """With `materialize`, the lanes of an `optimization_barrier` are computed once (a
    reduction XLA does not fuse into its consumers, `control._materialise`), so every
    consumer reads one rounding; without it they pass through."""
    params, a, b = inputs()
    closed = jax.make_jaxpr(_side)(params, a[0], b[0])

    def lowered(materialize):
        def lanes(params, a, b):
            outs = eval_lanes(closed, [lanes_of(params), _lane(a), _lane(b)], N,
                              materialize=materialize)
            return [stack_lanes(o, N, v.aval.dtype) for o, v in zip(outs, closed.jaxpr.outvars)]

        return primitives(jax.make_jaxpr(lanes)(params, a, b).jaxpr)

    assert "reduce_or" in lowered(True) and "reduce_or" not in lowered(False)


def _divergent(p, a, b):
    """A march whose trip count varies between rays from 0 to 100 (ceil(50 |a|)); its
    body reads a per-ray value (b), shared ones (p), and the stacked output of a scan
    before the loop (ys: on "fused" the rows of one [3, *block] array)."""
    _, ys = lax.scan(lambda c, r: (c, r * a + b), 0.0, p[:3])

    def body(s):
        k, x = s
        y = lax.scan(lambda c, r: (c * p[1] + r, None), x, ys)[0]
        return k + 1.0, jnp.sin(y) + b

    return lax.while_loop(lambda s: s[0] < jnp.abs(a) * 50.0, body, (jnp.zeros_like(a), a))


def _counted(p, a, b):
    """A loop of a static count (`march.search.repeat`): the same trip count for all rays."""
    return lax.while_loop(lambda s: s[0] < 5, lambda s: (s[0] + 1, s[1] * p[1] + b),
                          (0, a))[1]


def _whiles(jaxpr):
    return sum(e.primitive.name == "while" for e in jaxpr.eqns) + sum(
        _whiles(sub.jaxpr if isinstance(sub, ClosedJaxpr) else sub)
        for e in jaxpr.eqns for p in e.params.values()
        for sub in (p if isinstance(p, (list, tuple)) else [p])
        if isinstance(sub, (ClosedJaxpr, Jaxpr)))


@pytest.mark.parametrize("compact", [1, 4, 8])
def test_a_narrowed_loop_gives_every_ray_its_own_result(compact):
    """`KernelOptions.compaction`: a loop over a 16×16 block whose rays stop after 0 to
    100 steps runs on the whole block until at most 1/compact of its rays are active,
    then on those alone (`control._compacted`). Every ray ends where it ends alone (vmap),
    to the bit, rays that never enter the loop included; a loop of a static count
    never narrows."""
    block = (16, 16)
    rng = np.random.default_rng(5)
    params = rng.normal(size=12)
    a = rng.uniform(-2, 2, block)
    a[0, :5] = 0.0  # rays that never enter the loop
    b = rng.uniform(-1, 1, block)
    for fn, narrows in ((_divergent, compact > 1), (_counted, False)):
        closed = jax.make_jaxpr(fn)(params, a[0, 0], b[0, 0])

        def lanes(params, a, b):
            outs = eval_lanes(closed, [lanes_of(params, lazy=True), _lane(a), _lane(b)], block,
                              roll_scans=True, compact=compact)
            return [stack_lanes(o, block, v.aval.dtype) for o, v in zip(outs, closed.jaxpr.outvars)]

        got = jax.jit(lanes)(params, a, b)
        want = jax.vmap(jax.vmap(fn, in_axes=(None, 0, 0)), in_axes=(None, 0, 0))(
            jnp.asarray(params), a, b)
        for g, w in zip(got, jax.tree_util.tree_leaves(want), strict=True):
            np.testing.assert_array_equal(np.asarray(g), np.asarray(w))
        program = jax.make_jaxpr(lanes)(params, a, b).jaxpr
        assert _whiles(program) == _whiles(closed.jaxpr) + narrows
    trips = np.ceil(np.abs(a) * 50)
    assert trips.min() == 0 and trips.max() > 90 and (trips > 50).mean() < 0.5


def _nearest_child(p, a, b):
    """A stacked union in small: a scan over 6 children, each a centre (a row of the
    parameters, at stride 2), a radius and a kind (constants that differ from child to
    child: tables); it carries the nearest distance and its kind, and stacks nothing."""
    radii = jnp.asarray(np.linspace(0.1, 0.6, 6), a.dtype)
    kinds = jnp.asarray(np.arange(6) % 2, jnp.int32)

    def step(carry, x):
        d, k = carry
        c, r, kind = x
        dist = jnp.abs(a - c) - r + b * kind
        return (jnp.minimum(d, dist), jnp.where(dist < d, kind, k)), None

    init = (jnp.asarray(jnp.inf, a.dtype), jnp.int32(-1))
    return lax.scan(step, init, (p[1:13:2], radii, kinds))[0]


def _count(jaxpr, name):
    """Equations of primitive `name` in a jaxpr, its inner jaxprs included."""
    n = 0
    for eqn in jaxpr.eqns:
        n += eqn.primitive.name == name
        for p in eqn.params.values():
            for sub in p if isinstance(p, (list, tuple)) else [p]:
                if isinstance(sub, (ClosedJaxpr, Jaxpr)):
                    n += _count(getattr(sub, "jaxpr", sub), name)
    return n


def test_a_scan_over_parameters_stays_a_loop_that_loads_its_rows():
    """Pallas's loaded scan (`control._scan_loaded`): a scan over rows of the program's
    parameters (`addresses`: positions 1 + 2i) and over constant tables (`Tables`) is
    one loop whose iteration i loads its row: outside a kernel from the lanes stacked
    (the `Uniforms`' recording run, which collects the tables), in a kernel from one
    vector of the parameters and the tables (`load`). The values of `vmap`, with one
    copy of the body where unrolling makes six."""
    from jaxrt.kernels.lanes import Tables

    params, a, b = inputs()
    closed = jax.make_jaxpr(_nearest_child)(params, a[0], b[0])
    tables = Tables(np.float64)

    def run(p, a, b, in_kernel, loops=True):
        args = lanes_of(p)
        addresses = {id(x): (x, ("p", j)) for j, x in enumerate(args.reshape(-1))}

        def load(space, position, dtype, scope):  # the kernel's vector: parameters, then tables
            vector = jnp.concatenate([p, jnp.asarray(np.concatenate(tables.arrays))])
            return vector[position + (p.shape[0] if space == "c" else 0)].astype(dtype)

        outs = eval_lanes(closed, [args, _lane(a), _lane(b)], N, tables=tables,
                          addresses=addresses if loops else None,
                          load=load if in_kernel else None)
        return [stack_lanes(o, N, v.aval.dtype) for o, v in zip(outs, closed.jaxpr.outvars)]

    want = jax.vmap(_nearest_child, in_axes=(None, 0, 0))(jnp.asarray(params), a, b)
    recording = jax.make_jaxpr(lambda *x: run(*x, in_kernel=False))(params, a, b)
    assert [len(t) for t in tables.arrays] == [6, 6] and tables.size == 12
    tables.frozen = True
    kernel = jax.make_jaxpr(lambda *x: run(*x, in_kernel=True))(params, a, b)
    unrolled = jax.make_jaxpr(lambda *x: run(*x, in_kernel=False, loops=False))(params, a, b)
    assert _count(recording.jaxpr, "abs") == _count(kernel.jaxpr, "abs") == 1
    assert _count(unrolled.jaxpr, "abs") == 6
    for program in (recording, kernel, unrolled):
        got = jax.core.eval_jaxpr(program.jaxpr, program.consts, params, a, b)
        for g, w in zip(got, want, strict=True):
            np.testing.assert_array_equal(np.asarray(g), np.asarray(w))
    assert set(np.asarray(want[1])) == {0, 1}  # both kinds are nearest somewhere


def test_two_loops_read_the_recorded_values_each_in_its_own_body():
    """The `Uniforms`' recording run (`fused._recording_load`): two loaded scans over
    the same shared values (no value recorded between them) each read them from a
    vector built in their own body; a vector built in the first body and read in the
    second was a leaked tracer."""
    from jaxrt.kernels import fused
    from jaxrt.kernels.lanes import Uniforms

    def two_scans(p, x):
        q = p * 2.0  # shared values, recorded
        c, _ = lax.scan(lambda c, qi: (c + qi * x, None), x, q)
        c, _ = lax.scan(lambda c, qi: (c * 0.5 + qi, None), c, q)
        return c

    p = np.arange(1.0, 5.0, dtype=np.float32)
    x = np.linspace(0.0, 1.0, N, dtype=np.float32)
    closed = jax.make_jaxpr(two_scans)(p, x[0])
    recorded = Uniforms()

    @jax.jit
    def run(p, x):
        args = lanes_of(p)
        addresses = {id(v): (v, ("p", j)) for j, v in enumerate(args.reshape(-1))}
        out, = eval_lanes(closed, [args, _lane(x)], N, uniforms=recorded, addresses=addresses,
                          load=fused._recording_load([p], jnp.float32, recorded, None))
        return stack_lanes(out, N, np.float32)

    got = run(p, x)
    assert len(recorded.values) == 4
    np.testing.assert_array_equal(np.asarray(got),
                                  np.asarray(jax.vmap(two_scans, in_axes=(None, 0))(p, x)))
