"""render(): the one place that maps the per-ray kernels over the pixels of an image."""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import sharding, silhouette, xla
from .camera import pixel_samples
from .integrator import ray_tree, trace_radiance
from .kernels.fused import resolve_backend
from .march import tape
from .sdf.stack import prestack
from .settings import RenderSettings


class Image(eqx.Module):
    """A rendered image: linear HDR `rgb` [H, W, 3] and AOVs.

    depth     [H, W] distance along the ray to the first hit (max_distance on a miss).
    normal    [H, W, 3] world-space unit normal facing the camera (0 on a miss).
    albedo    [H, W, 3] base colour of the material hit (0 on a miss).
    steps     [H, W] sphere-tracing steps of the primary ray; a ray that ran out of its
              budget counts max_steps + 1 (steps > max_steps marks it).
    coverage  [H, W] fraction of the pixel's samples that hit a surface.
    Values are averaged over the pixel's samples (box filter). AOVs left out of
    `RenderSettings.aovs` are None.
    """

    rgb: jnp.ndarray
    depth: jnp.ndarray | None = None
    normal: jnp.ndarray | None = None
    albedo: jnp.ndarray | None = None
    steps: jnp.ndarray | None = None
    coverage: jnp.ndarray | None = None


def render(scene, camera, settings=None):
    """Render `scene` through `camera`; returns an `Image`.

    Compiled once per scene *structure* and settings: changing parameter values (any
    float in the scene or camera) reuses the compiled program. The program is compiled
    with the XLA options of `settings.kernel.xla` (`jaxrt.xla`); inside a larger traced
    program (a jitted loss, a fit step) those are the outer program's to pass.
    """
    settings = RenderSettings() if settings is None else settings
    dtype = _dtype(settings)
    scene, camera = _cast((scene, camera), dtype)
    if xla.tracing() and derivative_by_replay(settings, (scene, camera)):
        return differentiable(_render, (scene, camera), settings)
    fn = xla.jitted(_render, settings)
    rows = camera.height if xla.tracing() else block_rows(camera, settings)
    if rows == camera.height:
        return fn(scene, camera, settings)
    return in_blocks(lambda row0: fn(scene, camera, settings, rows, row0), camera.height, rows,
                     threads(settings))


def threads(settings):
    """CPU threads of a render called outside a trace: `settings.threads`, 0 for one per
    core that this process may run on."""
    return settings.threads or xla.cores()


def block_rows(camera, settings):
    """Rows of the image per call of a render called outside a trace on a CPU.

    XLA:CPU runs a render program on about one core, so `threads(settings)` threads
    call the program of a block of rows at once (`in_blocks`), one block each, no block
    smaller than a tile of the kernel (`RenderSettings.rays_per_tile`). One block per
    thread: the ray tree's slots gather their live rays per call, so smaller blocks
    cost more in all (the showcase at 480×270 on "fused", 2 cores: one call 3.8 s, two
    blocks one after the other 5.2 s, eight 7.6 s; two blocks in two threads 2.0–2.4 s
    against 4.2–4.3 s for one call). The image's height (one call) on a GPU, with
    `devices` other than 1 (the image is sharded over devices instead), with the
    outline term of silhouettes (it splats onto neighbouring pixels), inside one of
    JAX's configuration contexts (`_jax_contexts`), and with `threads = 1`."""
    h, w, spp = camera.height, camera.width, settings.spp
    n = threads(settings)
    if (n == 1 or settings.devices != 1 or _outline_keys(settings)
            or jax.default_backend() != "cpu" or _jax_contexts()):
        return h
    rays = h * w * spp
    tiles = -(-rays // settings.rays_per_tile(rays, lanes=resolve_backend(settings.backend) != "jax"))
    blocks = min(n, tiles, h)
    return -(-h // blocks)


def _jax_contexts():
    """Whether this thread is inside one of JAX's configuration contexts (`with
    jax.debug_nans(True):`, `jax.default_matmul_precision(...)`, ...). They hold in the
    thread that entered them only, so a render there is one call, in this thread."""
    try:
        from jax._src import config

        unset = config.config_ext.unset
        return any(state.get_local() is not unset for state in config.config_states.values())
    except (ImportError, AttributeError):  # another JAX: contexts cannot be told apart
        return False


def block_starts(height, rows):
    """The first row of each block of `rows` rows: the last block ends at the image's
    last row (it overlaps the one before when `rows` does not divide `height`)."""
    return [min(start, height - rows) for start in range(0, height, rows)]


_POOL = {}


def in_blocks(call, height, rows, workers):
    """The Image of `call(row0)` (an Image of the `rows` rows from `row0`) over every
    block (`block_starts`), called by `workers` threads at once, its rows put together."""
    import concurrent.futures

    if workers not in _POOL:
        _POOL[workers] = concurrent.futures.ThreadPoolExecutor(workers, "jaxrt-render")
    starts = block_starts(height, rows)
    images = list(_POOL[workers].map(lambda r: call(np.int32(r)), starts))
    fields = {}
    for name in Image.__dataclass_fields__:
        parts = [getattr(image, name) for image in images]
        if parts[0] is not None:  # the overlap of the last block is the block before's
            parts = [x[i * rows - start:] for i, (x, start) in enumerate(zip(parts, starts))]
            fields[name] = jnp.concatenate(parts, axis=0)
    return Image(**fields)


def derivative_by_replay(settings, params):
    """Whether a derivative of the render is the record and replay of `_recorded` (a lane
    backend whose replay XLA differentiates), not the "jax" program's own derivative."""
    return resolve_backend(settings.backend) != "jax" and not _replays_in_kernel(settings, params)


def differentiable(jit_fn, params, settings, *args):
    """`jit_fn(*params, settings, *args)` (a jitted render program: `_render`,
    `views._render_views`) inside a trace, as a custom JVP: its primal is `jit_fn`, its
    rule a jitted JVP of the function `jit_fn` wraps (`_jvp`), traced without the jit.

    Called as it is, a derivative of `jit_fn` traced the plain lane kernel first (JAX
    traces a jitted function before it differentiates it, and a custom JVP's primal
    with it: `_recorded`'s), then the recording kernel and the replay that the
    derivative is made of: the plain kernel was traced for nothing. Here a derivative
    never meets the primal (showcase, "fused", value_and_grad at 32×24, 2 cores:
    lowering 16.7–18.1 s → 14.0–14.8 s; the same values, gradients and JVPs, bit for
    bit). Both functions are jitted, so a loss that renders one structure several
    times traces each once."""
    dyn, static = eqx.partition(params, eqx.is_array)
    jit_fn = xla.jitted(jit_fn, settings)

    @jax.custom_jvp
    def image(dyn_):
        return jit_fn(*eqx.combine(dyn_, static), settings, *args)

    @image.defjvp
    def image_jvp(primals, tangents):
        return _jvp(jit_fn.__wrapped__, primals[0], tangents[0], static, (settings, *args))

    return image(dyn)


@eqx.filter_jit
def _jvp(fn, dyn, tangents, static, args):
    return jax.jvp(lambda d: fn(*eqx.combine(d, static), *args), (dyn,), (tangents,))


@eqx.filter_jit
def _render(scene, camera, settings, rows=None, row0=0):
    """The Image of `scene` through `camera`; with `rows`, of the block of `rows` rows
    from `row0` (an int32 scalar, dynamic) alone (`in_blocks`)."""
    scene = _prestacked(scene, settings)
    samples = pixel_samples(camera, settings.spp, settings.seed).astype(camera.eye.dtype)
    h, w, spp = camera.height, camera.width, settings.spp
    if rows is not None:
        samples = jax.lax.dynamic_slice_in_dim(samples, row0 * w * spp, rows * w * spp)
        h = rows

    kernel = _sample_kernel(settings)

    def trace_block(params, samples, grid, offset):
        """Every sample of a block of the image (all of it, or one device's block):
        `grid` (rows, columns of samples), `offset` its first (row, column)."""
        if resolve_backend(settings.backend) != "jax":
            return _recorded(kernel, params, samples, settings, grid, offset)
        return _vmapped(kernel, params, samples, settings)

    if settings.devices == 1:
        out = trace_block((scene, camera), samples, (h, w * spp), (row0, 0))
        out = {k: v.reshape((h, w * spp) + v.shape[1:]) for k, v in out.items()}
    else:  # a block of the image on each device, and the image kept in blocks on them
        devices = sharding.local_devices(settings.devices)
        out = sharding.shard_image(trace_block, (scene, camera), samples, (h, w * spp), devices,
                                   split=settings.split)
    outline = [out.pop(k).reshape(h * w * spp, -1) for k in _outline_keys(settings)]
    out = {k: v.reshape((h, w, spp) + v.shape[2:]).mean(axis=2) for k, v in out.items()}
    if outline:  # the outline terms onto the outlines' pixels
        out["rgb"] = out["rgb"] + silhouette.splat_outline(*outline, h, w, spp)
    if settings.devices != 1:
        out = sharding.image_sharded(out, devices, split=settings.split)
    return Image(**out)


def _outline_keys(settings):
    """The per-sample outputs of the outline term (`silhouette_gradient = "outline"`)."""
    if settings.silhouette and settings.silhouette_gradient == "outline":
        return (silhouette.OUTLINE_RGB, silhouette.OUTLINE_XY)
    return ()


def _vmapped(kernel, params, samples, settings):
    """The "jax" backend: the per-sample program vmapped over rays (in `lax.map` tiles
    of `settings.rays_per_tile`), differentiated as it is (the reference)."""
    scene, camera = params
    origins, directions, cones = jax.vmap(camera.generate_ray)(samples[:, 0], samples[:, 1])
    rays = (origins, directions, cones, samples)
    n, tile = samples.shape[0], settings.rays_per_tile(samples.shape[0])
    if tile >= n:
        return jax.vmap(lambda r: kernel(r, scene, camera))(rays)
    return jax.lax.map(lambda r: kernel(r, scene, camera), rays, batch_size=tile)


def _recorded(kernel, params, samples, settings, grid, offset):
    """The fast backends ("fused", "pallas", "auto"), differentiable by record and replay.

    A plain render runs the per-sample program lane-wise (`_fused`) and writes no tape.
    Its derivative (a custom JVP, so forward and reverse mode both work) runs the same
    kernel with its marches recorded (`jaxrt.march.tape`: hit t and flags, penumbra
    minima, near misses, as extra per-sample outputs; its image is the primal output)
    and differentiates the *replay*: the same program vmapped over every sample
    of the block at once, each march replaced by its record, so no loop is left; the
    Newton steps at the recorded roots give the hit points their implicit gradients,
    the penumbrae and coverage are evaluated at their recorded minima. The replay
    computes the kernel's image (to rounding: tests/test_gradients.py), and gradients
    equal those of the "jax" path wherever the records do not change under an
    infinitesimal change of the parameters (a march's hit flag, step count, or the
    sample at which a penumbra or a near miss took its minimum); where they would, the
    gradient is that of the replay with the records held fixed (one-sided, as for the
    "jax" path, whose loops are not differentiated either).
    """
    dyn, static = eqx.partition(params, eqx.is_array)
    gather = _replay_gathers(settings, params[0])
    wide = settings.kernel.replay_wide_unions
    wide = jax.default_backend() == "gpu" if wide is None else wide
    if _replays_in_kernel(settings, params):
        return _recorded_vjp(kernel, dyn, static, samples, settings, grid, offset, gather, wide)

    @jax.custom_jvp
    def image(dyn_, s):  # a plain render: the kernel alone, no tape written
        return _fused(*eqx.combine(dyn_, static), s, settings, kernel, grid, offset)

    @image.defjvp
    def image_jvp(primals, tangents):  # a derivative: the recording kernel, then the replay
        out, kinds = _record(kernel, eqx.combine(primals[0], static), primals[1], settings,
                             grid, offset)
        entries = jax.lax.stop_gradient(out["tape"])
        replay = lambda d, s: _replay(kernel, eqx.combine(d, static), s, entries, kinds, gather,  # noqa: E731
                                      wide)
        _, tangent = jax.jvp(replay, primals, tangents)
        return out["image"], tangent

    return image(dyn, samples)


def _replays_in_kernel(settings, params):
    """Whether a derivative of the render differentiates its replay in a lane kernel
    (`_recorded_vjp`): `KernelOptions.replay_kernel`, for scenes whose floats are all
    small (a per-sample cotangent of a voxel grid would be a lane per voxel)."""
    option = settings.kernel.replay_kernel
    option = resolve_backend(settings.backend) == "pallas" if option is None else option
    leaves = jax.tree_util.tree_leaves(eqx.filter(params, eqx.is_inexact_array))
    return option and all(x.size <= PER_SAMPLE_MAX for x in leaves)


def _recorded_vjp(kernel, dyn, static, samples, settings, grid, offset, gather, wide):
    """`_recorded` in reverse mode only, with the replay's derivative in the lane kernel.

    The forward pass runs the recording kernel (`_record`); the backward pass runs a
    second lane kernel whose one-sample program is the VJP of one sample's replay (the
    cotangent of that sample's outputs in, its cotangents of the scene's and camera's
    floats out), summed over the samples in the kernel's tiles (`map_samples` with
    `summed`). The replay's intermediates never leave the kernel: no per-sample array
    but the records and the image's cotangent is read or written, where the vmapped
    replay's reverse pass reads what its forward stored (on a GPU, 99 kernels
    re-reading 10–20 per-sample arrays each: docs/performance.md, "Session 34").
    The gradient is the vmapped replay's (`_replay`) to rounding; it is that
    program's "auto" fall-back. No forward mode (a `custom_vjp`)."""
    kinds, record = [], {}

    @jax.custom_vjp
    def image(dyn_, s):
        return _fused(*eqx.combine(dyn_, static), s, settings, kernel, grid, offset)

    def image_fwd(dyn_, s):
        out, kinds_ = _record(kernel, eqx.combine(dyn_, static), s, settings, grid, offset,
                              info=record)
        kinds[:] = [kinds_]
        return out["image"], (dyn_, s, out["tape"])

    def image_bwd(res, cotangent):
        dyn_, s, entries = res
        ints = eqx.filter(dyn_, eqx.is_inexact_array, inverse=True)
        # a record that "auto" took from the vmapped program: its replay's VJP is too
        # large for a kernel as well (the showcase traced for Pallas: 6.6 s saved)
        grads = _replay_vjp(kernel, eqx.combine(dyn_, static), s, entries, kinds[0], cotangent,
                            settings, grid, offset, gather, wide, lanes=record.get("lanes", True))
        zeros = jax.tree_util.tree_map(lambda x: np.zeros(x.shape, jax.dtypes.float0), ints)
        return eqx.combine(grads, zeros), jnp.zeros_like(s)

    image.defvjp(image_fwd, image_bwd)
    return image(dyn, samples)


def _replay_vjp(kernel, params, samples, entries, kinds, cotangent, settings, grid, offset,
                gather, wide, lanes=True):
    """Σ_samples (∂ replay(sample) / ∂ floats)ᵀ · cotangent(sample): the gradient of the
    render's floats (a pytree of `params` with None at the rest), each sample's
    VJP of its replay in one lane kernel (`map_samples`, `summed`). Its "auto"
    fall-back is the VJP of the vmapped replay (`_replay`), which also serves a VJP
    program of more than `KernelOptions.replay_kernel_max_lane_ops` when
    `replay_kernel` is None, and one whose record's program was not a kernel
    (`lanes` false)."""
    from .kernels.fused import map_samples

    float_out = {k: v.dtype != jax.dtypes.float0 for k, v in cotangent.items()}
    cotangent = {k: v for k, v in cotangent.items() if float_out[k]}

    def vjp_one(params_, px, py, inputs):
        entry, ct = inputs
        entry = jax.tree_util.tree_map(lambda x, b: x != 0 if b else x, entry, kinds)
        floats, rest = eqx.partition(params_, eqx.is_inexact_array)

        def one(d):
            scene, camera = eqx.combine(d, rest)
            with tape.replaying(entry):
                out = kernel((*camera.generate_ray(px, py), jnp.stack([px, py])), scene, camera)
            return {k: v for k, v in out.items() if float_out[k]}

        return jax.vjp(one, floats)[1](ct)[0]

    def reference(params_, s, inputs):
        entries_, ct = inputs
        floats, rest = eqx.partition(params_, eqx.is_inexact_array)

        def replayed(d):
            out = _replay(kernel, eqx.combine(d, rest), s, entries_, kinds, gather, wide)
            return {k: v for k, v in out.items() if float_out[k]}

        return jax.vjp(replayed, floats)[1](ct)[0]

    if not lanes:
        return reference(params, samples, (entries, cotangent))
    limit = settings.kernel.replay_kernel_max_lane_ops if settings.kernel.replay_kernel is None else None
    return map_samples(vjp_one, params, samples, settings, reference, grid=grid,
                       centres=offset if settings.spp == 1 else None,
                       inputs=(entries, cotangent), summed=True, max_lane_ops=limit)


def _sample_kernel(settings):
    """The per-sample program: `kernel((o, d, cone, xy), scene, camera) -> {name: value}`."""

    def kernel(ray, scene, camera):
        o, d, cone, xy = ray
        out = trace_radiance(scene, o, d, cone, settings)
        if settings.silhouette:
            out = silhouette.blend(scene, camera, xy, out, settings)
        return {k: out[k] for k in ("rgb",) + settings.aovs + _outline_keys(settings)}

    return kernel


def _record(kernel, params, samples, settings, grid, offset, info=None):
    """({"image": per-sample outputs, "tape": per-sample records of every march}, kinds):
    the kernel run lane-wise (`_fused`) with its marches recorded (no gradient).
    Boolean records travel as int32 (kernels store words, not predicates); `kinds`
    (static: the tape's structure with True at its boolean records) lets `_replay` read
    them back."""
    kinds = []

    def record_kernel(ray, scene, camera):
        with tape.recording() as t:
            out = kernel(ray, scene, camera)
        kinds[:] = [jax.tree_util.tree_map(lambda x: x.dtype == jnp.bool_, t.entries)]
        words = jax.tree_util.tree_map(
            lambda x: x.astype(jnp.int32) if x.dtype == jnp.bool_ else x, t.entries)
        return {"image": out, "tape": words}

    out = _fused(*params, samples, settings, record_kernel, grid, offset, info)
    return out, kinds[0]


def _replay(kernel, params, samples, entries, kinds, gather=0, wide=False):
    """The kernel vmapped over all `samples` at once with every march read from `entries`
    (the records of `_record`, `kinds` its boolean ones): loop-free and differentiable.

    The floats of scene and camera enter the vmap as per-sample copies (`_per_sample`),
    so the transpose of that broadcast — the sum of every sample's cotangent — is one
    plain reduction of a materialised [samples, ...] array instead of XLA fusing the
    whole backward pass into narrow column reductions (on an H200, Warp scene
    2048×1024, jax 0.11.2: value_and_grad 8.8 → 3.3 ms).

    The floats of large arrays (voxel grids, height maps, textures: over
    `PER_SAMPLE_MAX` values) stay shared: each sample reads a few of them, so their
    cotangent is a scatter-add into one array, where per-sample copies would take
    samples × size (a 129³ grid at 128×128: 131 GiB).

    With `gather` rays (`_replay_gathers`), the vmap is over a named axis and the
    secondary rays of the ray tree (a level, or a slot of the scan tree) are shaded
    only where alive, in batches of `gather` (`tape.gathering`); the scene then enters
    unbatched, since the batches close over it.

    With `wide`, stacked unions evaluate their children at once (`tape.wide_unions`)."""
    dyn, static = eqx.partition(params, eqx.is_inexact_array)
    small, large = eqx.partition(dyn, lambda x: x.size <= PER_SAMPLE_MAX)
    entries = jax.tree_util.tree_map(lambda x, b: x != 0 if b else x, entries, kinds)
    n = samples.shape[0]

    def one(d, s, entry):
        scene, camera = eqx.combine(d, large, static)
        with tape.replaying(entry), tape.wide_unions(wide):
            return kernel((*camera.generate_ray(s[0], s[1]), s), scene, camera)

    if not gather:
        per_sample = jax.tree_util.tree_map(lambda x: _per_sample(x, n), small)
        return jax.vmap(one)(per_sample, samples, entries)
    with tape.gathering(_RAYS_AXIS, gather):
        return jax.vmap(one, in_axes=(None, 0, 0), axis_name=_RAYS_AXIS)(small, samples, entries)


_RAYS_AXIS = "jaxrt_replay_rays"


def _replay_gathers(settings, scene):
    """The batch of rays in which `_replay` shades the secondary rays of the ray tree,
    only those alive (`KernelOptions.replay_gather`), or 0: on "fused", for an RGB ray
    tree (most of its rays are dead for most pixels). Not on a GPU, where the replay is
    one wide program and each batch would be kernels of their own."""
    tree = ray_tree(scene, settings)
    gathers = resolve_backend(settings.backend) == "fused" and tree.depth > 0
    return settings.kernel.replay_gather if gathers and not tree.wavelengths else 0


PER_SAMPLE_MAX = 4096
"""The largest float leaf `_replay` copies per sample (64 stacked spheres: 192 centre coordinates)."""


@functools.partial(jax.custom_jvp, nondiff_argnums=(1,))
def _per_sample(x, n):
    """x broadcast to [n, *x.shape]. Its tangent passes an `optimization_barrier`, whose
    transpose materialises the per-sample cotangent before the sum over samples."""
    return jnp.broadcast_to(x, (n,) + x.shape)


@_per_sample.defjvp
def _per_sample_jvp(n, primals, tangents):
    (x,), (t,) = primals, tangents
    return _per_sample(x, n), jax.lax.optimization_barrier(jnp.broadcast_to(t, (n,) + t.shape))


def replay_image(scene, camera, settings=None):
    """(record, replay): the per-sample outputs [H·W·spp, ...] of one recorded render
    (the fast backend's values) and of its replay (plain vmapped JAX); for tests."""
    settings = RenderSettings() if settings is None else settings
    scene, camera = _cast((scene, camera), _dtype(settings))
    return _replay_image(scene, camera, settings)


@eqx.filter_jit
def _replay_image(scene, camera, settings):
    scene = _prestacked(scene, settings)
    samples = pixel_samples(camera, settings.spp, settings.seed).astype(camera.eye.dtype)
    kernel = _sample_kernel(settings)
    grid = (camera.height, camera.width * settings.spp)
    out, kinds = _record(kernel, (scene, camera), samples, settings, grid, (0, 0))
    gather = _replay_gathers(settings, scene)
    return out["image"], _replay(kernel, (scene, camera), samples, out["tape"], kinds, gather)


def _fused(scene, camera, samples, settings, kernel, grid, offset, info=None):
    """The per-sample kernel run lane-wise by `jaxrt.kernels` (backend "fused"/"pallas"/
    "auto") on a block `grid` of samples at `offset` in the image (no gradient: see
    `_recorded`); `info`: `map_samples`'s."""
    from .kernels.fused import map_samples

    def one(params, px, py):
        return kernel((*params[1].generate_ray(px, py), jnp.stack([px, py])), *params)

    def reference(params, s):
        rays = (*jax.vmap(params[1].generate_ray)(s[:, 0], s[:, 1]), s)
        return jax.lax.map(lambda r: kernel(r, *params), rays,
                           batch_size=settings.rays_per_tile(s.shape[0]))

    # pixel_samples gives pixel centres at spp 1: the Pallas kernel then computes them
    return map_samples(one, (scene, camera), samples, settings, reference, grid=grid,
                       centres=offset if settings.spp == 1 else None, info=info)


def _prestacked(scene, settings):
    """The scene with the stacked groups of its unions stacked once, here, at the top of
    the program (`sdf.stack.prestack`): the rest of the program sees one leaf per leaf
    of a group's structure, not one per child. For the "fused" lanes, whose unions skip
    far children, the children's bounding balls are computed here too (once, not at
    every site that evaluates the SDF)."""
    balls = resolve_backend(settings.backend) == "fused"
    return eqx.tree_at(lambda s: s.surface, scene, prestack(scene.surface, balls=balls))


def _dtype(settings):
    if settings.dtype == "float64":
        if not jax.config.jax_enable_x64:
            raise ValueError(
                'RenderSettings.dtype = "float64" needs 64-bit JAX: call '
                'jax.config.update("jax_enable_x64", True) before creating the scene'
            )
        return jnp.float64
    return jnp.float32


def _cast(tree, dtype):
    def cast(x):
        if eqx.is_array(x) and jnp.issubdtype(x.dtype, jnp.floating) and x.dtype != dtype:
            return x.astype(dtype)
        return x

    return jax.tree_util.tree_map(cast, tree)


def compile_render(scene, camera, settings=None):
    """Compile ahead of time (with the XLA options of `settings.kernel.xla`); returns
    `f(scene, camera) -> Image` for scenes of this structure (used to report compile and
    render time apart)."""
    settings = RenderSettings() if settings is None else settings
    dtype = _dtype(settings)
    options = xla.compiler_options(settings)
    rows = block_rows(camera, settings)
    blocks = () if rows == camera.height else (rows, np.int32(0))
    compiled = _render.lower(*_cast((scene, camera), dtype), settings, *blocks).compile(
        compiler_options=options or None)
    if not blocks:
        return lambda scene, camera: compiled(*_cast((scene, camera), dtype), settings)

    def run(scene, camera):
        scene, camera = _cast((scene, camera), dtype)
        return in_blocks(lambda row0: compiled(scene, camera, settings, rows, row0),
                         camera.height, rows, threads(settings))

    return run
