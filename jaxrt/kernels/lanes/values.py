"""How the lane interpreter holds values: every value of shape S of the one-ray program
is a numpy object array of shape S whose elements are lanes, each

- a [block] array: one number per ray (a tile of rays: `block` may be (rows, columns));
- a 0-d array: the same for every ray (a scene parameter, or a value computed from them);
- a numpy scalar: a compile-time constant (`_is_const`).

A lane may also be a `Row`: row i of an array (the stacked outputs of a rolled scan, or
a leaf of the scene), not yet sliced out; `resolve` slices it where a rule reads it.

`lanes_of` and `stack_lanes` convert between arrays and object arrays of lanes;
`_broadcast` and `_const_lane` make full lanes; `_Ctx` is the evaluation context that
the rules of the other modules receive."""

import jax.numpy as jnp
import numpy as np
from jax import lax

from .jax_internals import Tracer, jax_array

class Unsupported(NotImplementedError):
    """The one-ray program uses a primitive (or a form of one) that lanes cannot run."""


class Row:
    """Lane `arr[i]`, sliced only where a rule reads it (`resolve`): an element of the
    stacked outputs of a rolled scan (`control._scan_rolled`, arr [n, *block]) or of a
    leaf of the scene (`lanes_of(lazy=True)`, arr the flattened leaf). A rolled scan
    over rows of one array takes the array (a gradient's residuals, stacked by one scan
    and read by its transpose; a union's stacked children), so neither costs a slice
    per element at every site."""

    __slots__ = ("arr", "i")

    def __init__(self, arr, i):
        self.arr, self.i = arr, i


def resolve_lane(x, ctx):
    """`x`, or the lane `x.arr[x.i]` if `x` is a `Row`: sliced once per trace scope (a
    lane sliced inside a loop body must not be reused outside it)."""
    if not isinstance(x, Row):
        return x
    cache = ctx.scopes[-1]
    key = ("row", id(x))
    if key not in cache or cache[key][0] is not x:  # (the id of a freed row may recur)
        cache[key] = (x, x.arr[x.i])
    return cache[key][1]


def row_array(obj):
    """The [n, ...] array whose rows, in order, are the elements of the object array
    `obj` (of n elements), or None."""
    flat = obj.reshape(-1)
    first = flat[0] if flat.size else None
    if not isinstance(first, Row) or first.arr.shape[0] != flat.size:
        return None
    if all(isinstance(e, Row) and e.arr is first.arr and e.i == i for i, e in enumerate(flat)):
        return first.arr
    return None


def resolve(obj, ctx):
    """The object array `obj` with its `Row`s sliced (`resolve_lane`); `obj` itself if
    it holds none (or if no rolled scan made any)."""
    if not ctx.rows or obj.dtype != object or not any(isinstance(x, Row) for x in obj.flat):
        return obj
    out = _obj(obj.shape)
    for idx in np.ndindex(obj.shape):
        out[idx] = resolve_lane(obj[idx], ctx)
    return out


def _is_const(x):
    return isinstance(x, np.generic)


def _lane_shape(x):
    return () if _is_const(x) else tuple(jnp.shape(x))


def _obj(shape):
    return np.empty(shape, dtype=object)


def lanes_of(x, lazy=False):
    """A concrete or traced array of shape S as an object array of 0-d lanes.

    Concrete (numpy, or non-traced JAX) arrays become numpy scalars (constants); traced
    arrays are indexed element by element (uniform lanes), or with `lazy` held as `Row`s
    of the flattened array, sliced only where read (a scene's stacked children are
    then gathered from the parameter table by rolled scans, never sliced one by one)."""
    if isinstance(x, (np.ndarray, np.generic, int, float, bool)) or (
        isinstance(x, jax_array) and not isinstance(x, Tracer)
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
            out[idx] = Row(flat, k) if lazy else flat[k]
    return out


def stack_lanes(obj, block, dtype):
    """An object array of lanes (shape S) as one array [*block, *S]. Its lanes may be
    `Row`s (`eval_lanes(keep_rows=True)`): all the rows of one [n, *block] array, in
    order, are that array, moved; other rows are sliced."""
    block = _shape(block)
    shape = obj.shape
    arr = row_array(obj)
    if arr is not None and arr.shape[1:] == block:
        return jnp.moveaxis(arr.astype(dtype), 0, -1).reshape(block + shape)
    elems = [_broadcast(e.arr[e.i] if isinstance(e, Row) else e, block, dtype)
             for e in obj.reshape(-1)]
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


def _convert(x, dtype, ctx):
    if _is_const(x):
        return np.asarray(x).astype(dtype)[()]
    if x.dtype == dtype:
        return x
    return lax.convert_element_type(x, dtype)


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
        self.compact = 1  # a loop narrows to 1/compact of its block (`control._compacted`)
        self.compact_min = 32  # ... if that is at least this many lanes
        self.compacting = False  # inside a narrowed loop (no nested narrowing)
        self.roll_scans = False
        self.rows = False  # whether a rolled scan has made `Row` lanes
        self.param_pos = {}  # id of a 0-d parameter lane -> (dtype, position in its table)
        self.param_table = {}  # dtype -> [n] array of the program's 0-d parameter lanes
        # Pallas: id of a shared lane -> (the lane, (space, position)) where the kernel
        # can load it, and the load, (space, position, dtype, scope) -> lane (`control._scan_loaded`)
        self.addresses = None
        self.load = None
        self.tables = None  # Pallas: constant tables that loops index (`control.Tables`)
        self.rewrite = None  # (name, lanes, dtype, ctx) -> lane or None: GPU forms (`gpu.rewrite`)
        self.eval_closed = None  # (closed jaxpr, args) -> outputs: the interpreter, for rules
        self.used_outputs = None  # which results of the equation being evaluated are used


def _any_lane_default(pred):
    return jnp.any(pred)
