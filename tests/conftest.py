"""Test configuration: float64 on (references and finite differences need it), XLA:CPU's
fast-compile flags.

jaxrt's own cache (the CLI's traced programs and its folder) stays off in tests
(`JAXRT_NO_CACHE=1`, unless the environment sets it): the tests that check it turn it
on themselves, in a folder of their own. JAX's persistent compilation cache serves the
suite's programs instead (not a slow run's), in a folder of the suite's (`suite_cache_folder`): the first
run of a checkout writes every program there, and a later run reads back those whose
code did not change. On 2 cores (jax 0.10.2, session 34) the README's `pytest` took
370 s without it, 410 s writing it and 273 s reading it back.

The suite is mostly compiles (about half of its time goes to XLA, a third to tracing and
lowering), so every program compiles with the flags that this XLA knows of
`TEST_XLA_FLAGS` (added to `$XLA_FLAGS`; `JAXRT_TEST_XLA=default` leaves XLA's
defaults): those of `jaxrt.xla`'s "fast-compile" preset, but LLVM's -O0 (-O1 for a run
of the slow tests, `SLOW_TESTS_LEVEL`). On 2 quiet cores (jax 0.10.2) the README's
`pytest` took 739 s with XLA's defaults and 484 s with "fast-compile"; 502 s with
"fast-compile" and 356 s with -O0 (session 31). The flags change no float semantics;
the last bits of a result may differ from XLA's defaults, as they may between any two
programs (tests compare to rounding), and -O0 rounds differently from -O1 in more
places, which found two NaN gradients and a black pixel (`integrator.spawn_offset`,
`sdf.sd_cone`). `tests/test_xla_options.py` still compiles XLA's defaults where it
compares the presets: options given to a compile override these.
"""

import os
import subprocess
import sys

os.environ.setdefault("JAXRT_NO_CACHE", "1")

#: `jaxrt.xla.XLA_PRESETS["fast-compile"]["cpu"]` with LLVM -O0, as XLA_FLAGS (read when
#: XLA starts, so set before the first computation; flags already in `$XLA_FLAGS` are
#: kept).
TEST_XLA_FLAGS = {"xla_cpu_use_fusion_emitters": "false", "xla_backend_optimization_level": "0"}


def _accepted(flags):
    """Whether this XLA accepts `flags` in $XLA_FLAGS: it aborts the process on a flag it
    does not know (jax 0.11's has no `xla_cpu_use_fusion_emitters`), so a subprocess
    tries them. Once per test session: xdist's workers inherit the flags found."""
    env = {**os.environ, "XLA_FLAGS": " ".join(flags), "JAX_PLATFORMS": "cpu"}
    probe = [sys.executable, "-c", "import jax.numpy as jnp; jnp.ones(1).block_until_ready()"]
    try:
        return subprocess.run(probe, env=env, capture_output=True, timeout=300).returncode == 0
    except (OSError, subprocess.SubprocessError):
        return False


#: The LLVM level of a run that selects the slow tests (`pytest -m slow`): they run their
#: programs for longer (fits, large renders), and at -O0 one of them (the free-form fit's
#: `render_views`) grew past 16 GB and five failed (session 31). Session 32 fixed two
#: causes; the pose and materials quick studies and the scan tree's replay still fail at
#: -O0. Session 33 found them configuration-dependent: each passes at -O1; the pose
#: study's NaN VJP is finite compiled alone at -O0; the materials study fails at -O0 with
#: the legacy emitter only, and the replay test fails a different variant with each
#: emitter (docs/performance.md, "Session 33").
SLOW_TESTS_LEVEL = "1"


def pytest_configure(config):
    """`TEST_XLA_FLAGS` into $XLA_FLAGS, before XLA starts (it reads them when its first
    backend is made, not at `import jax`); xdist's workers inherit them. And the suite's
    compilation cache (`_use_suite_cache`)."""
    _use_suite_cache(config)
    if os.environ.get("JAXRT_TEST_XLA", "fast-compile") == "default":
        return
    wanted = dict(TEST_XLA_FLAGS)
    if config.getoption("markexpr") != "not slow":
        wanted["xla_backend_optimization_level"] = SLOW_TESTS_LEVEL
    flags = os.environ.get("XLA_FLAGS", "")
    new = [f"--{k}={v}" for k, v in wanted.items() if f"--{k}=" not in flags]
    if new and not _accepted(new):
        new = [f for f in new if _accepted([f])]
    os.environ["XLA_FLAGS"] = " ".join([flags, *new]).strip()


import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)


def suite_cache_folder():
    """The folder of the suite's compilation cache: `$JAXRT_TEST_CACHE`, else `tests`
    beside the CLI's cache folder (`jaxrt.cache.default_path()`: `~/.cache/jaxrt/tests`);
    None, the cache off, when `$JAXRT_TEST_CACHE` is 0, off, false or no. Its files are
    keyed by program, flags and versions (JAX's cache keys): the folder can be deleted
    at any time."""
    from pathlib import Path

    from jaxrt.cache import default_path

    value = os.environ.get("JAXRT_TEST_CACHE", "").strip()
    if value.lower() in ("0", "off", "false", "no"):
        return None
    return Path(value).expanduser() if value else default_path().parent / "tests"


def _use_suite_cache(config):
    """The suite's compilation cache on (`suite_cache_folder`), for every program: the
    suite's are small and many. Not for a run that selects the slow tests: there, with
    the cache filled, a worker grew to 18.9 GB and was killed for memory (2 cores,
    24 GB, session 34), where the same run with the cache empty passed."""
    folder = suite_cache_folder()
    if folder is None or config.getoption("markexpr") != "not slow":
        return
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)


def subprocess_env(**changes):
    """The environment of a test's subprocess (a fresh JAX, for virtual XLA devices):
    this one's, with the suite's compilation cache on there too when it is on here (JAX
    reads its options from `JAX_*` variables at import), and `changes` on top. With it
    warm, `test_sharding.py` took 16.9 s against 26.5 s (2 cores, jax 0.10.2)."""
    env = dict(os.environ)
    folder = jax.config.jax_compilation_cache_dir
    if folder:
        env.update(JAX_COMPILATION_CACHE_DIR=str(folder),
                   JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
                   JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES="0")
    env.update(changes)
    return env


#: The test files that take longest (seconds of one worker, 2 quiet cores, session 30),
#: collected first: xdist's `--dist loadfile` hands files to its workers in collection
#: order, and a long file dealt last leaves the other worker idle at the end (the
#: README's `pytest` took 482 s, with the two workers 35 s apart).
LONGEST_FIRST = ("test_gradients.py", "test_kernels.py", "test_integrator.py", "test_fit_driver.py",
                 "test_silhouette.py", "test_extremes.py", "test_fit.py", "test_ngan_fit.py",
                 "test_march_forms.py", "test_grid.py", "test_union_stack.py", "test_render.py",
                 "test_sharding.py")


def pytest_collection_modifyitems(items):
    rank = {name: k for k, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))
