"""Fused rendering backends: the one-sample program run lane-wise over tiles of rays.

`map_samples(fn, params, samples, settings, reference)` evaluates
`fn(params, px, py) -> {name: array}` (the whole per-sample pipeline: camera ray, march,
normal, shading, shadow rays) for every sample (px, py), with one of two backends:

- "fused": `lanes.eval_lanes` in plain JAX, one square tile of about
  `settings.batch_size` rays after another (`lax.map`). Each tile is a flat program of
  elementwise operations on [th, tw] lanes whose loops stop when the tile's last ray is
  done. On an idle 2-core CPU 1.7× faster than "jax" on the Warp scene.
- "pallas": the same lane program inside one Pallas (Triton) GPU kernel; each program
  instance traces a tile of rays, the scene's parameters are read from a small vector
  (so changing them never recompiles). Without a GPU it runs in Pallas' interpret mode
  (slow; for tests).

Both compute the forward pass only. Called directly, gradients come from `reference`
(the vmapped `jax` path) through a custom VJP; `jaxrt.render` records the marches in
the kernel instead and differentiates a loop-free replay (`render._recorded`), so this
VJP is not used there.
"""

import contextlib
import functools
import math
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from ..march import form as march_form
from ..march import tape
from ..vecmath import undifferentiated
from .lanes import (Tables, Uniforms, Unsupported, eval_lanes, lanes_of, program_size,
                    stack_lanes)

__all__ = ["map_samples", "resolve_backend", "Unsupported", "pallas_block", "tile_shape"]

# How the kernels are built (unroll, Pallas warps, fast math, FMA, uniforms, "auto"'s
# size limits, the Pallas block) is `settings.kernel` (`jaxrt.settings.KernelOptions`):
# settings are static, so each choice is part of the jit cache key.

#: Elementwise primitives that Pallas' Triton lowering lacks (jax 0.10/0.11). erfc (a
#: Beckmann distribution's Smith term) is computed from a Chebyshev fit instead
#: (`lanes.gpu._erfc`, fractional error < 1.2e-7); a program using the others is Unsupported
#: for "pallas", and "auto" renders it with the "jax" program.
TRITON_UNSUPPORTED = ("erf", "erfc", "lgamma", "digamma", "bessel_i0e", "bessel_i1e")


def map_samples(fn, params, samples, settings, reference, grid=None, centres=None,
                inputs=None, summed=False, max_lane_ops=None, info=None):
    """Evaluate `fn(params, px, py)` for every row of `samples` [N, 2].

    Args:
      fn: the one-sample program; returns a dict of arrays.
      params: a pytree (scene, camera); its arrays are the program's parameters.
      samples: [N, 2] pixel positions.
      settings: `RenderSettings` (backend, batch_size).
      reference: `reference(params, samples) -> dict of [N, ...]`, the vmapped path,
        used for gradients.
      grid: (rows, columns) with rows · columns = N when the samples form a row-major
        grid (an image: rows = height, columns = width · spp); tiles are then squares
        of the grid, whose rays are coherent (they stop after similar numbers of
        steps), rather than runs of a row.
      centres: (row, column) offset of the grid in an image (integers, may be traced)
        when the samples are the centres of the image's cells (column + ½, row + ½)
        over the grid; the Pallas kernel then computes them instead of reading them.
      inputs: a pytree of [N, ...] arrays, the samples' own values (a render's records
        and the cotangents of its image): then `fn(params, px, py, inputs_of_a_sample)`
        and `reference(params, samples, inputs)`.
      summed: the outputs summed over the samples (a sample's cotangents of the
        parameters, summed into the gradient), as `reference` returns them; no
        gradient of this.
      max_lane_ops: a one-sample program of more lane operations (`_lane_ops`) runs
        `reference` instead, with no warning (a choice of the caller's, not a failure).
      info: a dict in which `info["lanes"]` tells whether the lane kernel ran (False
        where `reference` did).

    Returns: a dict of [N, ...] arrays (with `summed`, of the outputs' own shapes), the
    same as `reference` gives.
    """
    dyn, static = eqx.partition(params, eqx.is_array)
    backend = resolve_backend(settings.backend)
    grid = (1, samples.shape[0]) if grid is None else tuple(grid)
    extra = () if inputs is None else (inputs,)

    def one(dyn_, px, py, *extra_):
        return fn(eqx.combine(dyn_, static), px, py, *extra_)

    program = []

    def traced():
        # the one-sample program, traced once: "auto" reads its size, then builds the
        # kernel twice (abstractly, then in the caller's trace); the showcase's program
        # takes seconds to trace
        if not program:
            # a kernel under `custom_vjp` is never differentiated; a gradient's own is
            with contextlib.nullcontext() if summed else undifferentiated():
                program.append(_trace_one(one, dyn, samples.dtype, settings, backend, extra))
        return program[0]

    def lanes(dyn_, samples_, *extra_):
        if backend == "pallas":
            return _pallas(traced(), dyn_, samples_, settings, grid, centres, extra_, summed)
        return _tiles(traced(), dyn_, samples_, settings, grid, extra_, summed)

    if summed:  # a gradient's kernel: not differentiated
        run = lanes
    else:
        run = jax.custom_vjp(lanes)

        def run_fwd(dyn_, samples_, *extra_):
            return run(dyn_, samples_, *extra_), (dyn_, samples_, extra_)

        def run_bwd(res, g):
            dyn_, samples_, extra_ = res
            _, vjp = jax.vjp(lambda d, s, *e: reference(eqx.combine(d, static), s, *e),
                             dyn_, samples_, *extra_)
            return vjp(g)

        run.defvjp(run_fwd, run_bwd)

    def lane_ops():
        return _lane_ops(traced()[0], backend, _loaded_scans(backend, settings),
                         len(jax.tree_util.tree_leaves(dyn)))

    too_large = False  # `reference` runs (over the caller's `max_lane_ops`: quietly)
    if settings.backend == "auto":
        # "auto" falls back to the vmapped program for what lanes cannot run, or would
        # take long to compile. The test traces the lane program abstractly, apart from
        # the caller's trace (an exception in the middle of that trace would leave
        # constants behind in it).
        def abstract(x):
            return jax.ShapeDtypeStruct(jnp.shape(x), jnp.result_type(x))

        try:
            size = lane_ops()
            too_large = max_lane_ops is not None and size > max_lane_ops
            limit = settings.kernel.auto_max_lane_ops(backend)
            if size > limit and not too_large:
                raise Unsupported(
                    f"the one-ray program has {size} lane operations (more than "
                    f"RenderSettings.kernel.auto_max_lane_ops_{backend} = {limit}: a large "
                    f"scene or a deep ray tree), whose {backend} kernel would compile for "
                    "minutes")
            if not too_large:
                jax.eval_shape(lambda d, s, *e: run(d, s, *e), jax.tree_util.tree_map(abstract, dyn),
                               abstract(samples), *jax.tree_util.tree_map(abstract, extra))
        except Exception as e:  # noqa: BLE001  any lane failure (also a JAX version's
            # primitive parameters that lanes do not know) falls back, with one line
            reason = (str(e).strip().splitlines() or [""])[0]
            if not isinstance(e, Unsupported):
                reason = f"{type(e).__name__} {reason}".strip()
            warnings.warn(f"RenderSettings(backend='auto'): {reason}; rendering with backend='jax'",
                          stacklevel=3)
            too_large = True
    elif max_lane_ops is not None:
        too_large = lane_ops() > max_lane_ops
    if info is not None:
        info["lanes"] = not too_large
    if too_large:
        return reference(params, samples, *extra)
    return run(dyn, samples, *extra)


def tile_shape(block, grid, pow2=False):
    """(th, tw): a tile of about `block` samples, as square as the grid allows."""
    rows, cols = grid
    if pow2:
        block = 1 << (max(1, int(block)).bit_length() - 1)
        th = 1 << ((block.bit_length() - 1) // 2)
        while th > 1 and th > rows:
            th //= 2
        return th, block // th
    th = max(1, min(rows, int(math.isqrt(max(1, int(block))))))
    return th, max(1, int(block) // th)


def _to_tiles(x, grid, tile):
    """[rows·cols, ...] → padded [ty, tx, th, tw, ...] (edge padding)."""
    (rows, cols), (th, tw) = grid, tile
    ty, tx = -(-rows // th), -(-cols // tw)
    x = x.reshape((rows, cols) + x.shape[1:])
    pad = [(0, ty * th - rows), (0, tx * tw - cols)] + [(0, 0)] * (x.ndim - 2)
    x = jnp.pad(x, pad, mode="edge")
    x = x.reshape((ty, th, tx, tw) + x.shape[2:])
    return jnp.moveaxis(x, 2, 1)


def _from_tiles(x, grid):
    """Inverse of `_to_tiles`: [ty, tx, th, tw, ...] → [rows·cols, ...]."""
    rows, cols = grid
    ty, tx, th, tw = x.shape[:4]
    x = jnp.moveaxis(x, 1, 2).reshape((ty * th, tx * tw) + x.shape[4:])
    return x[:rows, :cols].reshape((rows * cols,) + x.shape[2:])


def resolve_backend(backend):
    """"auto" → "pallas" on a GPU, "fused" elsewhere; others unchanged. (On 2 CPU
    cores the fused lanes rendered the Warp scene 1.4–2× faster than vmap; they were
    slower while XLA:CPU recomputed shared lanes, see `lanes.control._materialise`.)"""
    if backend == "auto":
        return "pallas" if jax.default_backend() == "gpu" else "fused"
    return backend


def _trace_one(one, dyn, dtype, settings, backend, extra=()):
    """The jaxpr of the one-sample program (inputs: the leaves of `dyn`, the sample's
    two coordinates, then one sample's slice of `extra`, the samples' own inputs) and
    the pytree of its outputs, its marches
    in the loop form of `settings.kernel.march_form` (`jaxrt.march.form`). "auto" traces
    the phases and, for a program of at most `kernel.plain_max_lane_ops` lane operations,
    the plain form, which it takes if that is within the limit too: the plain form renders
    faster (Warp scene on 2 CPU cores, "fused", 1024×512: 0.60 s against 2.47 s; twice as
    fast on an H200, Pallas), but larger programs compile for much longer in it (the
    showcase on "fused": 70 s against 35 s) and Triton's compile time grows faster still."""
    px = jax.ShapeDtypeStruct((), dtype)
    shapes = jax.tree_util.tree_map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), dyn)
    ones = jax.tree_util.tree_map(lambda x: jax.ShapeDtypeStruct(x.shape[1:], x.dtype), extra)
    nparams = len(jax.tree_util.tree_leaves(dyn))

    loops = _loaded_scans(backend, settings)

    def trace(form):  # a new function each time: make_jaxpr caches traces by function
        with march_form.using(form), tape.lanes(backend), tape.forward_gradients(loops):
            return jax.make_jaxpr(lambda *a: one(*a), return_shape=True)(shapes, px, px, *ones)

    option, limit = settings.kernel.march_form, settings.kernel.plain_max_lane_ops
    closed, out_shapes = trace("phases" if option == "auto" else option)
    if option == "auto" and _lane_ops(closed, backend, loops, nparams) <= limit:
        plain = trace("plain")
        if _lane_ops(plain[0], backend, loops, nparams) <= limit:
            closed, out_shapes = plain
    return closed, out_shapes


def _loaded_scans(backend, settings):
    """Whether the kernel keeps scans over its parameters as loops that load their rows
    (Pallas with `KernelOptions.pallas_scan_loops`: `lanes.control._scan_loaded`)."""
    return backend == "pallas" and settings.kernel.pallas_scan_loops


def _lane_ops(closed, backend, loops=False, nparams=None):
    """`program_size` of a one-sample program of `_trace_one` (its inputs: the scene's
    `nparams` values, then the sample's two coordinates and its own inputs; default:
    the coordinates alone). On "fused" an operation on the scene's
    values alone counts once (lanes compute it once per tile, and scans stay loops), so a
    stacked group's rows do not count. Pallas with `loops` (`pallas_scan_loops`) counts
    the same way, but a scan that it cannot keep as a loop (`lanes.control._loads`: the
    slots of a ray tree) once per iteration; without, every scan is unrolled and every
    input counts per element: 64 stacked spheres on a plane are 14.7k lane operations
    (Pallas compiled them in 66–85 s on an H100), 256 spheres 52k, against 2.5k for
    both with loops."""
    n = len(closed.jaxpr.invars)
    nparams = n - 2 if nparams is None else nparams
    unrolled = backend != "fused"
    per_ray = [unrolled and not loops] * nparams + [True] * (n - nparams)
    return program_size(closed.jaxpr, per_ray, unrolled_scans=unrolled, loaded_scans=loops)


# ----------------------------------------------------------------- "fused": XLA tiles


def _tiles(traced, dyn, samples, settings, grid, extra=(), summed=False):
    """The one-sample program `traced` (`_trace_one`: jaxpr, output shapes) evaluated by
    `eval_lanes` in `lax.map` over square tiles of `grid`; `extra`, `summed`: the
    samples' own inputs and summed outputs of `map_samples`."""
    closed, out_shapes = traced
    leaves = jax.tree_util.tree_leaves(dyn)
    out_leaves, out_tree = jax.tree_util.tree_flatten(out_shapes)
    n = samples.shape[0]
    tile = tile_shape(settings.rays_per_tile(n, lanes=True), grid)

    def tiled(x):  # [N, ...] → [tiles, th, tw, ...]
        x = _to_tiles(x, grid, tile)
        return x.reshape((-1,) + x.shape[2:])

    s = tiled(samples)
    per = [tiled(x) for x in jax.tree_util.tree_leaves(extra)]
    # the padding's samples (copies of the edge's) count for nothing in a sum
    real = _to_tiles_real(grid, tile) if summed else None

    def run_tile(block):
        sb, pb, rb = block
        args = [lanes_of(leaf, lazy=True) for leaf in leaves]
        args += [_lane(sb[..., 0]), _lane(sb[..., 1])] + [_lanes_per_ray(x) for x in pb]
        outs = eval_lanes(closed, args, tile, unroll=settings.kernel.unroll,
                          materialize=settings.kernel.materialize, roll_scans=True, keep_rows=True,
                          compact=settings.kernel.compaction)
        outs = [stack_lanes(o, tile, sh.dtype) for o, sh in zip(outs, out_leaves)]
        if summed:
            outs = [jnp.where(rb.reshape(rb.shape + (1,) * (o.ndim - 2)), o, 0).sum((0, 1))
                    for o in outs]
        return outs

    if s.shape[0] == 1:
        res = [r[None] for r in run_tile((s[0], [x[0] for x in per],
                                          None if real is None else real[0]))]
    else:
        res = lax.map(run_tile, (s, per, real))
    if summed:
        res = [r.sum(0) for r in res]
    else:
        ty, tx = -(-grid[0] // tile[0]), -(-grid[1] // tile[1])
        res = [_from_tiles(r.reshape((ty, tx) + r.shape[1:]), grid) for r in res]
    return jax.tree_util.tree_unflatten(out_tree, res)


def _to_tiles_real(grid, tile):
    """[tiles, th, tw]: whether a tile's sample is one of the grid's (not padding)."""
    (rows, cols), (th, tw) = grid, tile
    ty, tx = -(-rows // th), -(-cols // tw)
    real = (np.arange(ty * th)[:, None] < rows) & (np.arange(tx * tw)[None, :] < cols)
    return real.reshape(ty, th, tx, tw).swapaxes(1, 2).reshape(ty * tx, th, tw)


def _lanes_per_ray(x):
    """A tile of one per-sample input [th, tw, *S] as an object array of [th, tw] lanes."""
    out = np.empty(x.shape[2:], dtype=object)
    for idx in np.ndindex(x.shape[2:]):
        out[idx] = x[(slice(None), slice(None)) + idx]
    return out


def _lane(x):
    out = np.empty((), dtype=object)
    out[()] = x
    return out


# --------------------------------------------------------------- "pallas": one kernel


def pallas_block(settings):
    """Rays per program instance: batch_size (a power of two, 16–256) when it is at most
    256, else (None, "auto", or a CPU-sized tile such as 4096)
    settings.kernel.pallas_block."""
    b = settings.batch_size
    b = settings.kernel.pallas_block if b in (None, "auto") or b > 256 else b
    return max(16, 1 << (int(b).bit_length() - 1))


def _ptx_ops(interpret):
    """`lanes.eval_lanes`'s `ptx` operations: inline PTX in a Triton kernel; their plain
    JAX forms in interpret mode (so that tests run the same lane program on a CPU)."""
    if interpret:
        return {"fma": lambda x, y, z: x * y + z, "sqrt": jnp.sqrt, "rsqrt": lax.rsqrt,
                "div": jnp.divide, "neg": jnp.negative, "exp": jnp.exp, "log": jnp.log,
                "pow": lambda x, y: jnp.where(y == 0, 1.0, jnp.exp2(y * jnp.log2(x)))}
    from jax.experimental.pallas import triton as pltriton

    def asm(code, arity):
        def f(*xs):
            [r] = pltriton.elementwise_inline_asm(
                code, args=list(xs), constraints=",".join(["=f"] + ["f"] * arity), pack=1,
                result_shape_dtypes=[jax.ShapeDtypeStruct(xs[0].shape, xs[0].dtype)])
            return r
        return f

    def op(instruction, arity):
        return asm(f"{instruction} " + ", ".join(f"${k}" for k in range(arity + 1)) + ";", arity)

    return {"fma": op("fma.rn.f32", 3), "sqrt": op("sqrt.approx.ftz.f32", 1),
            "rsqrt": op("rsqrt.approx.ftz.f32", 1), "div": op("div.approx.ftz.f32", 2),
            "neg": op("neg.f32", 1),
            # e^x = 2^(x·log2 e), ln x = log2 x · ln 2, x^y = 2^(y·log2 x) (1 where y = 0;
            # NaN for x < 0, as CUDA's __powf)
            "exp": asm("{ .reg .f32 t; mul.ftz.f32 t, $1, 0f3FB8AA3B; "
                       "ex2.approx.ftz.f32 $0, t; }", 1),
            "log": asm("{ .reg .f32 t; lg2.approx.ftz.f32 t, $1; "
                       "mul.ftz.f32 $0, t, 0f3F317218; }", 1),
            "pow": asm("{ .reg .f32 t; .reg .pred z; lg2.approx.ftz.f32 t, $1; "
                       "mul.ftz.f32 t, t, $2; ex2.approx.ftz.f32 t, t; "
                       "setp.eq.f32 z, $2, 0f00000000; selp.f32 $0, 0f3F800000, t, z; }", 2)}


def _as_float32_word(x):
    """A float32, int32 or bool scalar as the float32 with the same 32 bits."""
    x = jnp.asarray(x)
    if x.dtype == jnp.float32:
        return x.reshape(1)
    return lax.bitcast_convert_type(x.astype(jnp.int32), jnp.float32).reshape(1)


def _from_float32_word(w, dtype):
    """Inverse of `_as_float32_word`."""
    if np.dtype(dtype) == np.float32:
        return w
    i = lax.bitcast_convert_type(w, jnp.int32)
    return i != 0 if np.dtype(dtype) == np.dtype(bool) else i


def _read(p_ref, position, dtype):
    """Element `position` of a Pallas kernel's parameter vector as `dtype` (ints and
    bools are stored there exactly as floats)."""
    v = p_ref[position]
    return v if v.dtype == dtype else v.astype(dtype)


def _recording_load(leaves, dtype, recorded, tables):
    """`eval_lanes`'s `load` for the `Uniforms`' recording run, outside the kernel: the
    kernel's `load` (in `_pallas`) on the parts of its parameter vector known so far
    (the parameters, the values recorded, the tables collected). A loop's iteration i
    reads its row as one element of a vector, where stacking the row's lanes took
    O(n) operations per loaded value: 256 spheres' render traced in 2.9 s against 1.5 s
    for 8 (CPU, Pallas lowered for CUDA), most of it `jnp.stack` of 256 scalars. The
    recorded values' vector is built once per loop body (`scope`: a vector staged in
    one body must not be read in another) and count (no value is recorded inside a
    loop: the list is complete when a loop reads it)."""
    flat = jnp.concatenate([jnp.ravel(x).astype(dtype) for x in leaves] or [jnp.zeros(1, dtype)])

    def load(space, position, dt, scope):
        if space == "p":
            return _read(flat, position, dt)
        if space == "u":
            key = ("recorded", len(recorded.values))
            if key not in scope:
                scope[key] = jnp.concatenate([_as_float32_word(v) for v in recorded.values])
            return _from_float32_word(scope[key][position], dt)
        return _read(jnp.asarray(np.concatenate(tables.arrays), dtype), position, dt)

    return load


def _pow2(n, at_least=1):
    return max(at_least, 1 << max(0, math.ceil(math.log2(max(n, 1)))))


def _pallas(traced, dyn, samples, settings, grid, centres=None, extra=(), summed=False):
    """The one-sample program `traced` as one Pallas kernel over tiles of `grid`;
    `extra`, `summed`: the samples' own inputs and summed outputs of `map_samples`
    (each tile writes its sums, which XLA adds up)."""
    from jax.experimental import pallas as pl

    dtype = samples.dtype
    closed, out_shapes = traced
    leaves, _ = jax.tree_util.tree_flatten(dyn)
    out_leaves, out_tree = jax.tree_util.tree_flatten(out_shapes)

    rows, cols = grid
    th, tw = tile_shape(pallas_block(settings), grid, pow2=True)
    ty, tx = -(-rows // th), -(-cols // tw)
    opts = settings.kernel
    interpret = (jax.default_backend() != "gpu") if opts.interpret is None else opts.interpret
    ptx = None
    if dtype == jnp.float32 and (opts.pallas_fma or opts.pallas_fast_math):
        ptx = {k: f for k, f in _ptx_ops(interpret).items() if opts.pallas_fma or k != "fma"}
    per = jax.tree_util.tree_leaves(extra)
    lane_options = dict(unroll=opts.pallas_unroll, fast_math=opts.pallas_fast_math,
                        unsupported=TRITON_UNSUPPORTED, bool_carries=True)
    # parameters: one vector of the float dtype (ints and bools stored exactly as floats),
    # then the shared values as 32-bit words
    offsets, k = [], 0
    for leaf in leaves:
        offsets.append(k)
        k += int(np.prod(leaf.shape))

    def addressed(args):
        """{id: (lane, ("p", position))} of the parameters' lanes (`eval_lanes`'s
        `addresses`: scans over them stay loops), or None (scans unrolled)."""
        if not opts.pallas_scan_loops:
            return None
        return {id(x): (x, ("p", off + j)) for a, off in zip(args, offsets)
                for j, x in enumerate(a.reshape(-1)) if not isinstance(x, np.generic)}

    # the values shared by all rays, computed here (the lane program evaluated once on
    # placeholder rays, whose work XLA then drops) and read by the kernel; the same run
    # collects the constant tables that the kernel's loops index
    recorded = Uniforms() if opts.pallas_uniforms and dtype == jnp.float32 else None
    tables = Tables(dtype) if opts.pallas_scan_loops else None
    if recorded is not None or tables is not None:
        placeholder = _lane(jnp.zeros((th, tw), dtype))
        args = [lanes_of(x) for x in leaves]
        ones = [_lanes_per_ray(jnp.zeros((th, tw) + x.shape[1:], x.dtype)) for x in per]
        eval_lanes(closed, args + [placeholder, placeholder] + ones,
                   (th, tw), uniforms=recorded, addresses=addressed(args), tables=tables,
                   load=_recording_load(leaves, dtype, recorded, tables),
                   ptx=None if ptx is None else {k: f for k, f in _ptx_ops(True).items() if k in ptx},
                   **lane_options)
        if tables is not None:
            tables.frozen = True
    parts = [jnp.ravel(x).astype(dtype) for x in leaves]
    if centres is not None:  # the grid's offset in the image (exact as floats < 2^24)
        parts.append(jnp.stack([jnp.asarray(c).astype(dtype) for c in centres]))
        k += 2
    ubase = k
    if recorded is not None and recorded.values:
        parts += [_as_float32_word(v) for v in recorded.values]
        k += len(recorded.values)
    cbase = k
    if tables is not None and tables.arrays:
        parts += [jnp.asarray(np.concatenate(tables.arrays))]
        k += tables.size
    nparams = _pow2(k, 16)
    pvec = jnp.zeros((nparams,), dtype)
    if parts:
        pvec = pvec.at[:k].set(jnp.concatenate(parts))

    def any_lane(pred):
        v = jnp.where(pred, 1.0, 0.0)
        while v.ndim:
            v = jnp.max(v, axis=-1)
        return v > 0.5

    def kernel(p_ref, *refs):
        if centres is not None:  # pixel centres, computed here: no sample array to read
            i, j = pl.program_id(0), pl.program_id(1)
            row0, col0 = p_ref[ubase - 2], p_ref[ubase - 1]
            py = (i * th + lax.broadcasted_iota(jnp.int32, (th, tw), 0)).astype(dtype) + (row0 + 0.5)
            px = (j * tw + lax.broadcasted_iota(jnp.int32, (th, tw), 1)).astype(dtype) + (col0 + 0.5)
        else:
            s_ref, *refs = refs
            px, py = s_ref[0], s_ref[1]
        x_refs, o_refs = refs[:len(per)], refs[len(per):]
        args = []
        for leaf, off in zip(leaves, offsets):
            obj = np.empty(leaf.shape, dtype=object)
            for j_, idx in enumerate(np.ndindex(leaf.shape)):
                obj[idx] = _read(p_ref, off + j_, leaf.dtype)
            args.append(obj)
        addresses = addressed(args)
        args += [_lane(px), _lane(py)]
        for x, x_ref in zip(per, x_refs):  # a sample's own inputs, component by component
            obj = np.empty(x.shape[1:], dtype=object)
            for c, idx in enumerate(np.ndindex(obj.shape)):
                obj[idx] = x_ref[c]
            args.append(obj)
        uniforms = None
        if recorded is not None:
            uniforms = Uniforms(read=lambda k_, dt: _from_float32_word(p_ref[ubase + k_], dt))

        def load(space, position, dt, scope):  # a loop's load of an address (`addressed`)
            if space == "u":
                return _from_float32_word(p_ref[ubase + position], dt)
            return _read(p_ref, position + (cbase if space == "c" else 0), dt)

        outs = eval_lanes(closed, args, (th, tw), any_lane=any_lane,
                          int_anchor=pl.program_id(0), ptx=ptx, uniforms=uniforms,
                          addresses=addresses, load=load, tables=tables, **lane_options)
        if recorded is not None:
            uniforms.check(recorded)
        zero = px * 0  # outputs that are constants: lanes computed from a traced zero
        if summed:  # the tile's sum of each element, over the grid's samples only
            i, j = pl.program_id(0), pl.program_id(1)
            real = ((i * th + lax.broadcasted_iota(jnp.int32, (th, tw), 0) < rows)
                    & (j * tw + lax.broadcasted_iota(jnp.int32, (th, tw), 1) < cols))
        for o, o_ref in zip(outs, o_refs):
            for c, x in enumerate(o.reshape(-1)):
                dt = o_ref.dtype
                if isinstance(x, np.generic):
                    x = (zero + np.float32(x)).astype(dt)
                x = jnp.broadcast_to(jnp.asarray(x).astype(dt), (th, tw))
                if summed:
                    o_ref[0, 0, c] = jnp.sum(jnp.sum(jnp.where(real, x, 0), axis=-1), axis=-1)
                elif o.shape == ():
                    o_ref[...] = x
                else:
                    o_ref[:, :, c] = x

    kwargs = {}
    if not interpret:
        from jax.experimental.pallas import triton as pltriton

        warps = opts.pallas_num_warps or max(1, min(4, (th * tw) // 64))
        kwargs["compiler_params"] = pltriton.CompilerParams(num_warps=warps, num_stages=1)
    # one output array per output of the program, in image layout ([rows, columns] and
    # its components last, as the caller wants them): written once, no padding rows
    out_shape, out_specs = [], []
    for o in out_leaves:
        size = int(np.prod(o.shape))
        if summed:  # a row of sums per tile
            out_shape.append(jax.ShapeDtypeStruct((ty, tx, size), o.dtype))
            out_specs.append(pl.BlockSpec((1, 1, size), lambda i, j: (i, j, 0)))
        elif o.shape == ():
            out_shape.append(jax.ShapeDtypeStruct((ty * th, tx * tw), o.dtype))
            out_specs.append(pl.BlockSpec((th, tw), lambda i, j: (i, j)))
        else:
            out_shape.append(jax.ShapeDtypeStruct((ty * th, tx * tw, size), o.dtype))
            out_specs.append(pl.BlockSpec((th, tw, size), lambda i, j: (i, j, 0)))
    in_specs = [pl.BlockSpec((nparams,), lambda i, j: (0,))]
    args = [pvec]

    def planes(x):  # [N, ...] → [components, ty·th, tx·tw] (edge padding), and its block
        x = _to_tiles(x.reshape(x.shape[:1] + (-1,)), grid, (th, tw))  # [ty, tx, th, tw, m]
        m = x.shape[-1]
        args.append(jnp.moveaxis(jnp.moveaxis(x, -1, 0), 2, 3).reshape(m, ty * th, tx * tw))
        in_specs.append(pl.BlockSpec((m, th, tw), lambda i, j: (0, i, j)))

    if centres is None:
        planes(samples)
    for x in per:
        planes(x)
    call = pl.pallas_call(
        kernel,
        out_shape=out_shape,
        grid=(ty, tx),
        in_specs=in_specs,
        out_specs=out_specs,
        interpret=interpret,
        name="jaxrt_render",
        **kwargs,
    )
    if summed:
        res = [x.sum((0, 1)).reshape(sh.shape) for x, sh in zip(call(*args), out_leaves)]
    else:
        res = [x[:rows, :cols].reshape((rows * cols,) + sh.shape)
               for x, sh in zip(call(*args), out_leaves)]
    return jax.tree_util.tree_unflatten(out_tree, res)
