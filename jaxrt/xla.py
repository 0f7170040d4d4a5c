"""XLA compiler options of jaxrt's programs: the presets of `KernelOptions.xla`.

A preset names a set of XLA `DebugOptions` per platform (`XLA_PRESETS`); `compiler_options`
gives the dict for the current one (`jax.default_backend()`), which every jit that
compiles a render program passes to XLA:

- `render`, `render_views` called outside any trace: a jitted variant of their program
  with `compiler_options` (`jitted`);
- `compile_render` and `cache.compile_render_cached`: `lowered.compile(compiler_options=...)`;
- programs that *contain* renders (the fit step, `experiments/bench/compile.py`): JAX
  accepts `compiler_options` only on a top-level jit, so a render traced inside one notes
  its options (`note`) and the caller that compiles the whole program collects them
  (`compile_collected`).

Options that this XLA does not know (another jax version) are dropped, with one warning
each, after a probe compile of a one-operation program (`usable`): an unknown flag never
fails a render.

One setting cannot travel as a compile option: XLA:CPU's backend options
(`xla_backend_extra_options`, a map that `compiler_options` refuses) are read from
`$XLA_FLAGS` when JAX starts its backend. `add_process_flags`, called when jaxrt is
imported, adds jaxrt's there (`PROCESS_OPTIONS`).
"""

import contextlib
import functools
import os
import threading
import warnings

#: `KernelOptions.xla` presets: {name: {platform: {XLA DebugOptions flag: value}}}.
#:
#:   "default"       XLA's own defaults.
#:   "fast-compile"  on a CPU, `xla_cpu_use_fusion_emitters = False`: XLA:CPU's legacy
#:                   (elemental IR) loop emitter instead of its MLIR fusion emitters,
#:                   and `xla_backend_optimization_level = 1`: LLVM's -O1 pipeline instead
#:                   of -O3 (XLA's default is 3). No flag that changes float semantics
#:                   (no fast math, the same FTZ/denormal mode). Nothing on a GPU.
#:                   jax 0.11's XLA:CPU has no legacy emitter (nor the flag): there
#:                   "fast-compile" is -O1 alone (`usable` drops the flag, warning once).
#: Figures: docs/performance.md ("XLA compiler options").
XLA_PRESETS = {
    "default": {},
    "fast-compile": {
        "cpu": {"xla_backend_optimization_level": 1, "xla_cpu_use_fusion_emitters": False},
    },
}


#: XLA backend options jaxrt adds to `$XLA_FLAGS` on jax >= 0.12 (`add_process_flags`):
#: {key: value}.
#:
#:   xla_cpu_small_while_loop_byte_threshold = 1000000: XLA:CPU compiles a `while` whose
#:   cost analysis reports fewer bytes accessed than this threshold as one LLVM function
#:   instead of a loop of per-fusion kernels ("small while loop hoisting"). With jax
#:   0.12's default threshold every loop we tried was hoisted (states up to 16 MB):
#:   a render program's tile loop became one function of the whole lane program, and
#:   LLVM spent minutes on it, on one thread (the showcase's render program, 96x54,
#:   "auto" -> "fused", jax 0.12.0.1, 2 cores: 103 s; 25 s with this option). 1e6
#:   bytes keeps small loops hoisted (the Warp scene rendered in 13.6 ms with it, 18.0 ms
#:   with no hoisting) and not a program's large ones. jax 0.10 and 0.11 hoist none of
#:   the test's loops with their defaults: jaxrt leaves them be. A GPU ignores the
#:   option. Figures: docs/performance.md ("Session 23").
PROCESS_OPTIONS = {"xla_cpu_small_while_loop_byte_threshold": "1000000"}


def add_process_flags(environ=None):
    """On jax >= 0.12, add `PROCESS_OPTIONS` to `$XLA_FLAGS` (as
    `--xla_backend_extra_options=k=v`, which XLA merges with any other such flag), for
    the backend that JAX has yet to start.

    A key that `$XLA_FLAGS` already names is left as it is (set it there for another
    threshold). If JAX started its backend before jaxrt was imported, `$XLA_FLAGS` has
    been read: nothing is added, and a warning says so. Returns the keys added."""
    import jax

    environ = os.environ if environ is None else environ
    flags = environ.get("XLA_FLAGS", "")
    missing = {k: v for k, v in PROCESS_OPTIONS.items() if k not in flags}
    if not missing or jax.__version_info__ < (0, 12):
        return []
    added = ",".join(f"{k}={v}" for k, v in missing.items())
    if _backend_started():
        warnings.warn(f"jaxrt: JAX started before jaxrt was imported, so XLA_FLAGS cannot get "
                      f"--xla_backend_extra_options={added} (large render programs compile "
                      f"several times slower on a CPU without it): import jaxrt before the first "
                      f"JAX computation, or set it in XLA_FLAGS", stacklevel=3)
        return []
    environ["XLA_FLAGS"] = f"{flags} --xla_backend_extra_options={added}".strip()
    return list(missing)


def cores():
    """The CPU cores this process may run on (its affinity, else the machine's)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def add_host_devices(count, environ=None):
    """Ask XLA for `count` CPU devices (`--xla_force_host_platform_device_count`), so that
    `RenderSettings(devices=count)` can shard a render over as many CPU cores
    (`jaxrt.sharding`; XLA:CPU runs one render program on about one core). Only before
    JAX starts its backend, and only if `$XLA_FLAGS` does not name a count already;
    returns whether the flag was added. `jaxrt render` calls it for its own process; in
    a program of your own, set the flag before the first JAX computation."""
    environ = os.environ if environ is None else environ
    flags = environ.get("XLA_FLAGS", "")
    if count <= 1 or "xla_force_host_platform_device_count" in flags or _backend_started():
        return False
    environ["XLA_FLAGS"] = f"{flags} --xla_force_host_platform_device_count={count}".strip()
    return True


def _backend_started():
    """Whether JAX has started a backend (and so read `$XLA_FLAGS`). `xla_bridge` is
    internal: without it, assume it has (nothing is changed then)."""
    try:
        from jax._src import xla_bridge
    except ImportError:
        return True
    started = getattr(xla_bridge, "backends_are_initialized", None)
    return True if started is None else bool(started())


def compiler_options(settings, platform=None):
    """The XLA options of `settings` (`RenderSettings`, `KernelOptions` or a preset name)
    on `platform` (default: JAX's default backend), as a dict for `compiler_options=`;
    empty for "default", on a platform the preset does not name, and for flags this XLA
    does not know (`usable`)."""
    import jax

    preset = getattr(getattr(settings, "kernel", settings), "xla", settings)
    if preset not in XLA_PRESETS:
        raise ValueError(f"RenderSettings.kernel.xla = {preset!r}, expected one of {sorted(XLA_PRESETS)}")
    platform = jax.default_backend() if platform is None else platform
    return usable(XLA_PRESETS[preset].get(platform, {}))


def usable(options):
    """`options` without the flags that this XLA rejects (each reported once)."""
    return {k: v for k, v in options.items() if _accepted(k, v)}


@functools.cache
def _accepted(flag, value):
    """Whether XLA accepts `flag = value` (a probe compile of x + 1, once per process)."""
    import jax
    import jax.numpy as jnp

    try:
        jax.jit(lambda x: x + 1).lower(jnp.float32(0)).compile(compiler_options={flag: value})
        return True
    except Exception as e:  # noqa: BLE001  (XlaRuntimeError: "No such compile option", ...)
        reason = (str(e).strip().splitlines() or [type(e).__name__])[0]
        warnings.warn(f"jaxrt.xla: XLA option {flag}={value!r} left out ({reason})", stacklevel=2)
        return False


# --------------------------------------------------------------------------- top level


def tracing():
    """True while JAX traces (jit, grad, vmap): `compiler_options` are then refused on an
    inner jit. `jax._src.core.trace_state_clean` is internal: without it, True (the
    options are then collected from the program that contains the render, never lost
    to an error)."""
    try:
        from jax._src.core import trace_state_clean
    except ImportError:
        return True
    return not trace_state_clean()


def jitted(jit_fn, settings):
    """`jit_fn` (an `eqx.filter_jit` function of a render program) as it should be called
    with `settings`: outside a trace, a variant jitted with the settings' XLA options
    (the same function when they are empty); inside one, `jit_fn` itself, the options
    noted for the top-level program (`note`)."""
    options = compiler_options(settings)
    if tracing():
        note(options)
        return jit_fn
    if not options:
        return jit_fn
    return _variant(jit_fn, tuple(sorted(options.items())))


_VARIANTS = {}


def _variant(jit_fn, items):
    import equinox as eqx

    key = (id(jit_fn), items)
    if key not in _VARIANTS:  # jit_fn kept in the value: its id stays its own
        _VARIANTS[key] = (jit_fn, eqx.filter_jit(jit_fn.__wrapped__, compiler_options=dict(items)))
    return _VARIANTS[key][1]


# --------------------------------------------------------------------------- collected


_local = threading.local()


def note(options):
    """Record the XLA options of a render traced inside a larger program, for the
    `collecting` block (if any) that compiles it."""
    stack = getattr(_local, "stack", None)
    if stack:
        stack[-1].append(tuple(sorted(options.items())))


@contextlib.contextmanager
def collecting():
    """`with collecting() as seen:` the options `note`d while tracing in the block
    (a list of sorted item tuples, one per render traced)."""
    stack = _local.__dict__.setdefault("stack", [])
    seen = []
    stack.append(seen)
    try:
        yield seen
    finally:
        stack.pop()


def merged(seen):
    """One options dict for a program whose renders noted `seen`: theirs when they agree,
    {} (XLA's defaults, with a warning) when renders of one program ask for different
    presets."""
    distinct = set(seen)
    if len(distinct) > 1:
        warnings.warn("jaxrt.xla: renders of one program ask for different KernelOptions.xla "
                      f"options ({sorted(distinct)}); compiling with XLA's defaults", stacklevel=3)
        return {}
    return dict(next(iter(distinct))) if distinct else {}


#: Options collected per traced program (`lower_collected`): JAX caches traces, and a
#: cached trace runs no render, so notes nothing.
_COLLECTED = {}
_COLLECTED_MAX = 256


def lower_collected(jit_fn, *args):
    """(`jit_fn.lower(*args)`, the XLA options of the renders traced in it).

    When JAX reuses a cached trace (no render runs, nothing is noted), the options
    collected when that program was traced (`jit_fn` and the `signature` of `args`) are
    used again, so every compile of one program gets the same options."""
    with collecting() as seen:
        lowered = jit_fn.lower(*args)
    key = signature((jit_fn,) + args)
    if seen:
        options = merged(seen)
        if key is not None:
            if len(_COLLECTED) >= _COLLECTED_MAX:
                _COLLECTED.pop(next(iter(_COLLECTED)))
            _COLLECTED[key] = options
    else:
        options = _COLLECTED.get(key, {}) if key is not None else {}
    return lowered, options


def compile_collected(jit_fn, *args):
    """`jit_fn.lower(*args)` compiled with the XLA options of the renders traced in it
    (`lower_collected`)."""
    lowered, options = lower_collected(jit_fn, *args)
    return lowered.compile(compiler_options=options or None)


def call_collected(jit_fn, *args):
    """`jit_fn(*args)`, compiled with the XLA options of the renders traced in it: the
    plain call (JAX's dispatch, equinox's error messages) when they are XLA's defaults,
    else the program compiled with them (`compile_collected`; cached by JAX)."""
    lowered, options = lower_collected(jit_fn, *args)
    if not options:
        return jit_fn(*args)
    return lowered.compile(compiler_options=options)(*args)


def signature(args):
    """A hashable key of `args` as a jit cache sees them (the non-array leaves and the
    arrays' shapes and dtypes), or None where a leaf is not hashable."""
    import equinox as eqx
    import jax

    dyn, static = eqx.partition(args, eqx.is_array)
    leaves, treedef = jax.tree_util.tree_flatten(dyn)
    key = (static, treedef, tuple((x.shape, str(x.dtype)) for x in leaves))
    try:
        hash(key)
    except TypeError:
        return None
    return key
