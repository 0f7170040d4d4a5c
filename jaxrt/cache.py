"""JAX's persistent compilation cache for jaxrt programs.

A compiled program is stored on disk under a key of its lowered code, the compile
options and the JAX/backend versions, so a scene of an unchanged *structure* (and
unchanged settings) starts without compiling, in a new process too. The `jaxrt` command
turns it on by default; experiments and notebooks call `enable_compilation_cache()`.

Where: `path`, else `$JAXRT_CACHE_DIR`, else `$JAX_COMPILATION_CACHE_DIR` (JAX's own
variable), else `$XDG_CACHE_HOME/jaxrt/jax` (`~/.cache/jaxrt/jax` without XDG_CACHE_HOME).
Off: `JAXRT_NO_CACHE=1` in the environment (or `jaxrt render --no-cache`).
"""

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
