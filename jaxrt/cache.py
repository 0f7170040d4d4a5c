"""JAX's persistent compilation cache for jaxrt programs.

A compiled program is stored on disk under a key of its lowered code, the compile
options and the JAX/backend versions, so a scene of an unchanged *structure* (and
unchanged settings) starts without compiling, in a new process too. The `jaxrt` command
turns it on by default; experiments and notebooks call `enable_compilation_cache()`.

Where: `path`, else `$JAXRT_CACHE_DIR`, else `$JAX_COMPILATION_CACHE_DIR` (JAX's own
variable), else `$XDG_CACHE_HOME/jaxrt/jax` (`~/.cache/jaxrt/jax` without XDG_CACHE_HOME).
Off: `JAXRT_NO_CACHE=1` in the environment (or `jaxrt render --no-cache`).
"""

import functools
import os
from pathlib import Path

#: Environment variables: a non-empty value other than "0" turns the cache off; a path.
NO_CACHE_VAR = "JAXRT_NO_CACHE"
CACHE_DIR_VAR = "JAXRT_CACHE_DIR"

#: Programs that compiled faster than this are not stored (JAX's default is 1 s; jaxrt's
#: small programs still take a few tenths of a second to compile, worth keeping).
MIN_COMPILE_SECONDS = 0.2


def disabled_by_env():
    """True when `$JAXRT_NO_CACHE` asks for no cache (any value but "", "0", "false")."""
    return os.environ.get(NO_CACHE_VAR, "").strip().lower() not in ("", "0", "false", "no")


def default_path():
    """The cache folder used when none is given (see the module docstring)."""
    for var in (CACHE_DIR_VAR, "JAX_COMPILATION_CACHE_DIR"):
        if os.environ.get(var):
            return Path(os.environ[var]).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base).expanduser() / "jaxrt" / "jax"


def enable_compilation_cache(path=None, min_compile_seconds=MIN_COMPILE_SECONDS):
    """Store compiled programs in `path` (default `default_path()`) and reuse them.

    Returns the folder in use, or None when `$JAXRT_NO_CACHE` turns the cache off or the
    folder cannot be created (the cache is an optimisation: rendering goes on without it).
    Call it before the first compile: JAX opens its cache once per process.
    """
    import jax

    if disabled_by_env():
        return None
    path = Path(path).expanduser() if path is not None else default_path()
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_seconds))
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path


# --------------------------------------------------------------------------- traced programs

#: Subfolder of the cache folder that holds serialized render programs (`jax.export`).
PROGRAMS = "programs"


@functools.cache
def source_digest():
    """A hash of jaxrt's own source (every `.py` file of the package, by path and bytes).

    The version number alone would keep serving a program traced by older code to a
    developer who edits jaxrt between two renders (an editable install keeps its version).
    """
    import hashlib

    package = Path(__file__).resolve().parent
    digest = hashlib.sha256()
    for path in sorted(package.rglob("*.py")):
        digest.update(path.relative_to(package).as_posix().encode() + b"\0")
        digest.update(path.read_bytes() + b"\0")
    return digest.hexdigest()


def program_key(scene, camera, settings, rows=None):
    """A key of everything a render program depends on but its float values: the
    structure of scene and camera (their tree, with every static field, and each leaf's
    shape and dtype), the settings, the rows of a block (`render.block_rows`: they
    follow the machine's cores too), jaxrt's version and source (`source_digest`), JAX's
    version and the default backend."""
    import hashlib

    import jax

    from . import __version__

    leaves, treedef = jax.tree_util.tree_flatten((scene, camera))
    shapes = [(getattr(x, "shape", None), str(getattr(x, "dtype", type(x)))) for x in leaves]
    text = repr((str(treedef), shapes, repr(settings), rows, __version__, source_digest(),
                 jax.__version__, jax.default_backend()))
    return hashlib.sha256(text.encode()).hexdigest()[:32]


def compile_render_cached(scene, camera, settings, folder=None):
    """`render.compile_render`, with the traced program kept too: the first call exports
    the render program (`jax.export`, after tracing and lowering it) to
    `folder/programs/<program_key>.bin`; a later call for a scene of the same structure
    reads it back and skips tracing, and with the compilation cache on, XLA's compile
    too. XLA compiles it with the options of `settings.kernel.xla` (`jaxrt.xla`; the
    settings are part of the key, the options part of XLA's cache key). On a CPU the
    program is that of a block of rows, called by several threads (`render.in_blocks`).
    Returns `(f(scene, camera) -> Image, reused)`.

    Anything the export cannot hold (a Pallas kernel on some backends, a pytree it cannot
    flatten) falls back to `render.compile_render` (reused False), so this is never worse
    than compiling.
    """
    import importlib

    import jax

    from . import xla

    render_module = importlib.import_module("jaxrt.render")  # the module, not jaxrt.render()
    folder = Path(folder) if folder is not None else default_path()
    rows = render_module.block_rows(camera, settings)
    blocks = rows != camera.height
    path = folder / PROGRAMS / f"{program_key(scene, camera, settings, rows)}.bin"
    dtype = render_module._dtype(settings)
    args = render_module._cast((scene, camera), dtype)
    leaves, treedef = jax.tree_util.tree_flatten(args)
    arrays = [i for i, x in enumerate(leaves) if hasattr(x, "shape")]
    names = ("rgb",) + tuple(settings.aovs)

    def rebuild(outputs):
        return render_module.Image(**dict(zip(names, outputs)))

    specs = [jax.ShapeDtypeStruct(leaves[i].shape, leaves[i].dtype) for i in arrays]
    if blocks:  # the block's first row, last
        specs.append(jax.ShapeDtypeStruct((), jax.numpy.int32))
    mesh, replicated = None, {}  # a program sharded over `settings.devices` names its mesh
    if settings.devices != 1:
        from .sharding import local_devices, pixel_mesh

        mesh = pixel_mesh(local_devices(settings.devices))
        replicated = dict(in_shardings=jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec()))

    def call_with(exported):
        """The exported program compiled (from XLA's cache when it is on), not run."""
        options = xla.compiler_options(settings)
        shardings = {}
        if mesh is not None:
            shardings = dict(in_shardings=exported.in_shardings_jax(mesh),
                             out_shardings=exported.out_shardings_jax(mesh))
        call = jax.jit(exported.call, **shardings).lower(*specs).compile(
            compiler_options=options or None)

        def run(scene, camera):
            flat = jax.tree_util.tree_leaves(render_module._cast((scene, camera), dtype))
            flat = [jax.numpy.asarray(flat[i], leaves[i].dtype) for i in arrays]
            if not blocks:
                return rebuild(call(*flat))
            return render_module.in_blocks(lambda row0: rebuild(call(*flat, row0)), camera.height,
                                           rows, render_module.threads(settings))

        return run

    try:
        if path.is_file():
            exported = jax.export.deserialize(bytearray(path.read_bytes()))
            return call_with(exported), True
    except Exception:  # a stale or foreign file: export anew
        pass
    try:
        def flat_render(*array_leaves):
            full = list(leaves)
            for i, x in zip(arrays, array_leaves):
                full[i] = x
            scene_, camera_ = jax.tree_util.tree_unflatten(treedef, full)
            block = (rows, array_leaves[-1]) if blocks else ()
            image = render_module._render(scene_, camera_, settings, *block)
            return tuple(getattr(image, k) for k in names)

        exported = jax.export.export(jax.jit(flat_render, **replicated))(*specs)
        run = call_with(exported)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(".tmp")
            tmp.write_bytes(exported.serialize())
            tmp.replace(path)
        except OSError:
            pass
        return run, False
    except Exception as e:  # noqa: BLE001 (any failure: compile as usual)
        if os.environ.get("JAXRT_DEBUG"):
            raise
        del e
        return render_module.compile_render(scene, camera, settings), False
