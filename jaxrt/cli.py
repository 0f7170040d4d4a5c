"""The `jaxrt` command line (also `python -m jaxrt`).

    jaxrt render [CONFIG] [-o OUT] [--width W] [--height H] [--spp N] [--backend B]
                 [--set KEY=VALUE ...] [--exposure STOPS] [--no-cache]
    jaxrt --version

renders CONFIG (default: the showcase scene shipped inside the package) to OUT.exr
(linear float32 with AOVs) and OUT.png (sRGB preview), default OUT = out/showcase (or
out/<config name>), and prints the resolution, the compile time and the render time;
stderr says when compiling starts and when it ends.

- `--set KEY=VALUE` sets any `RenderSettings` field (repeatable); VALUE is a TOML value
  (`--set max_steps=256 --set shadows=soft --set aovs=[]`; a bare word is a string) and is
  checked as the file's [settings] are. It wins over the file and over --spp.
  `--set kernel.FIELD=VALUE` sets one `KernelOptions` field, keeping the file's others.
- XLA compiles with the library's options (`kernel.xla = "default"`) unless the file's
  [settings.kernel] or `--set kernel.xla=fast-compile` names another preset
  (`jaxrt.xla`). The showcase at 480×270 ("auto", i.e. "fused"), 2 quiet CPU cores,
  `--no-cache`, two runs each: jax 0.10.2 compiles it in 27.6 / 27.1 s and renders it in
  1.73 / 1.82 s with XLA's defaults, against 27.2 / 25.9 s and 3.07 / 2.83 s with
  "fast-compile"; jax 0.11.2 in 23.5 s and 1.34 s against 24.6 s and 1.69 s. So a
  one-shot render costs the same either way, and a program found in the cache renders
  faster (until session 30 the CLI chose "fast-compile", which saved tens of seconds
  when the scene's ray tree was unrolled).
- `--set devices=N` (or the file's `devices`; 0: every core) shards the image over N
  XLA CPU devices, which the command makes before JAX starts (`xla.add_host_devices`):
  XLA:CPU runs one render program on about one core, so on 2 cores the Warp scene
  renders 2.07× faster (docs/performance.md, "Session 24"). Not the default: the
  showcase at 480×270 renders in 1.2 s against 1.7 s on one device, but its sharded
  program compiles for 31–33 s against 25–28 s.
- One device renders with one thread per core instead (`--set threads=N`, default 0:
  one per core; `render.block_rows`): each thread calls the program of a block of rows,
  compiled once, as fast as the whole image's. The showcase at 480×270 on 2 cores,
  cache warm: render 2.4 s against 4.6–4.8 s with `threads=1`, wall 8.2–8.8 s against
  10.4 s (session 41's machine, slower than session 30's above).
- The backend is --backend (or --set backend=...), else the file's `settings.backend`,
  else "auto" (the fused lane kernels: on a 2-core CPU the showcase compiles 2.3× and
  renders 5.9× faster than with "jax"; the same image).
- JAX's persistent compilation cache is on (`jaxrt.cache`: `$XDG_CACHE_HOME/jaxrt/jax`,
  or `$JAXRT_CACHE_DIR`), and the traced render program is kept beside it
  (`cache.compile_render_cached`, `jax.export`): a scene whose structure and settings
  have not changed starts without tracing or compiling. Off: `--no-cache` or
  `JAXRT_NO_CACHE=1`.

Failures are one line on stderr, `jaxrt: error: ...`, and nothing written: a bad config or
setting exits with status 2 before any work; an output that cannot be written exits with
status 1 — the folder is checked before compiling, and the EXR and PNG are renamed into
place only once both are written (`io.write_render`).
"""

import argparse
import dataclasses
import os
import sys
import time
import tomllib
from importlib import resources
from pathlib import Path

#: Exit statuses.
EXIT_USAGE = 2  # a bad config, setting or argument: nothing was done
EXIT_FAILED = 1  # the output could not be written, or the render failed


def showcase_path():
    """Path of the built-in showcase scene."""
    return resources.files("jaxrt") / "data" / "showcase.toml"


def _positive_int(text):
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer ≥ 1, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected an integer ≥ 1, got {value}")
    return value


def _version():
    from . import __version__

    return __version__


def _parser():
    parser = argparse.ArgumentParser(prog="jaxrt", description="jaxrt: a differentiable ray marcher")
    parser.add_argument("--version", action="version", version=f"jaxrt {_version()}")
    sub = parser.add_subparsers(dest="command", required=True)
    render = sub.add_parser("render", help="render a scene file to EXR and PNG")
    render.add_argument("config", nargs="?", help="scene TOML file (default: the built-in showcase)")
    render.add_argument("-o", "--out", help="output path without extension (default: out/<scene name>)")
    render.add_argument("--width", type=_positive_int, help="image width in pixels")
    render.add_argument("--height", type=_positive_int, help="image height in pixels")
    render.add_argument("--spp", type=_positive_int, help="samples per pixel")
    render.add_argument("--exposure", type=float, default=0.0, help="PNG exposure in stops")
    render.add_argument("--backend", choices=["jax", "fused", "pallas", "auto"],
                        help="how rays are batched (default: the file's settings.backend, else auto)")
    render.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="set a RenderSettings field; VALUE is a TOML value (repeatable)")
    render.add_argument("--no-cache", action="store_true",
                        help="do not use the persistent compilation cache (also: JAXRT_NO_CACHE=1)")
    return parser


def main(argv=None, keep=None):
    """The `jaxrt` command line; returns the exit status. `keep`, a list, receives the
    compiled render program, left to the caller to free (see `run`)."""
    args = _parser().parse_args(argv)
    if args.command == "render":
        try:
            return _render(args, [] if keep is None else keep)
        except _Failure as e:
            print(f"jaxrt: error: {e}", file=sys.stderr)
            return e.status
        except KeyboardInterrupt:
            print("jaxrt: interrupted; nothing written", file=sys.stderr)
            return 130
    return EXIT_USAGE


def run():
    """The `jaxrt` console script and `python -m jaxrt`: `main()`, then the process ends
    without freeing the compiled program or tearing down JAX (the outputs are written
    and closed by then). Freeing the showcase's CPU program took 0.35 s of a warm
    `jaxrt render`, and the interpreter's teardown as much again. Errors and `--help`
    leave as usual, through `SystemExit`."""
    held = []
    status = main(keep=held)
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(status)


class _Failure(Exception):
    """A failure reported as one line (its message) and exit status `status`."""

    def __init__(self, message, status):
        super().__init__(message)
        self.status = status


def parse_overrides(items):
    """`--set KEY=VALUE` items -> {KEY: value}, VALUE read as a TOML value (a bare word
    that is not TOML is a string). KEY is a `RenderSettings` field, or `kernel.FIELD` for
    one field of `KernelOptions` (gathered into {"kernel": {FIELD: value}}). Raises
    `_Failure` for a malformed item or an unknown KEY."""
    from .settings import KernelOptions, RenderSettings

    fields = [f.name for f in dataclasses.fields(RenderSettings)]
    kernel_fields = [f.name for f in dataclasses.fields(KernelOptions)]
    out = {}
    for item in items:
        key, eq, text = item.partition("=")
        key = key.strip()
        if not eq or not key:
            raise _Failure(f"--set {item}: expected KEY=VALUE, KEY a RenderSettings field", EXIT_USAGE)
        head, dot, sub = key.partition(".")
        if dot and head == "kernel" and sub not in kernel_fields:
            raise _Failure(f"--set {item}: unknown kernel option `{sub}`, expected one of "
                           f"{', '.join(kernel_fields)}", EXIT_USAGE)
        if (dot and head != "kernel") or (not dot and key not in fields):
            raise _Failure(f"--set {item}: unknown setting `{key}`, expected one of {', '.join(fields)} "
                           "(or kernel.FIELD)", EXIT_USAGE)
        try:
            value = tomllib.loads(f"value = {text.strip()}")["value"]
        except tomllib.TOMLDecodeError:
            value = text.strip()
        if dot:
            kernel = out.setdefault("kernel", {})
            if not isinstance(kernel, dict):
                raise _Failure(f"--set {item}: `kernel` was set to {kernel!r} already", EXIT_USAGE)
            kernel[sub] = value
        else:
            out[key] = value
    return out


def _render(args, keep):
    from . import config, io

    path = Path(args.config) if args.config else showcase_path()
    overrides = parse_overrides(args.overrides)
    if args.backend:
        overrides.setdefault("backend", args.backend)
    try:
        file_settings = _file_settings(path)
        if "backend" not in overrides and "backend" not in file_settings:
            overrides["backend"] = "auto"
        if args.spp is not None:
            overrides.setdefault("spp", args.spp)
        config.check_settings(overrides, "--set")
        _host_devices({**file_settings, **overrides}.get("devices", 1))
        if {**file_settings, **overrides}.get("dtype") == "float64":
            import jax

            jax.config.update("jax_enable_x64", True)
        scene, camera, settings = config.load(path, width=args.width, height=args.height,
                                              settings=overrides)
    except config.ConfigError as e:
        raise _Failure(str(e), EXIT_USAGE) from None
    out = Path(args.out) if args.out else Path("out") / Path(str(path)).stem
    exr, png = out.with_suffix(".exr"), out.with_suffix(".png")
    try:  # before compiling: a render that cannot be saved is not started
        io.check_writable(exr)
        io.check_writable(png)
    except io.JaxrtIOError as e:
        raise _Failure(str(e), EXIT_FAILED) from None
    cache_folder = None
    if not args.no_cache:
        from .cache import enable_compilation_cache

        cache_folder = enable_compilation_cache()
    from .render import compile_render

    print(f"jaxrt: rendering {path} at {camera.width}×{camera.height}, {settings.spp} spp, "
          f"backend {settings.backend}, xla {settings.kernel.xla}, "
          f"{ {0: 'every device', 1: '1 device'}.get(settings.devices, f'{settings.devices} devices')}")
    sys.stdout.flush()
    print("jaxrt: compiling…", file=sys.stderr, flush=True)
    start = time.perf_counter()
    try:
        reused = False
        if cache_folder is None:
            render = compile_render(scene, camera, settings)
        else:
            from .cache import compile_render_cached

            render, reused = compile_render_cached(scene, camera, settings, cache_folder)
        keep.append(render)
        compile_seconds = time.perf_counter() - start
        how = " (the cached program)" if reused else ""
        print(f"jaxrt: compiled in {compile_seconds:.2f} s{how}", file=sys.stderr, flush=True)
        start = time.perf_counter()
        image = render(scene, camera)
        image.rgb.block_until_ready()
    except (ValueError, TypeError) as e:  # e.g. a backend this machine cannot run
        raise _Failure(f"{path}: cannot render: {e}".splitlines()[0], EXIT_FAILED) from None
    seconds = time.perf_counter() - start
    rays = camera.width * camera.height * settings.spp
    print(f"jaxrt: compile {compile_seconds:.2f} s, render {seconds:.3f} s "
          f"({format_rate(rays / max(seconds, 1e-9) / 1e6)} Mrays/s)")
    try:
        io.write_render(exr, png, image, exposure=args.exposure)
    except io.JaxrtIOError as e:
        raise _Failure(str(e), EXIT_FAILED) from None
    print(f"jaxrt: wrote {exr} and {png}")
    return 0


def _host_devices(devices):
    """Before JAX starts: `devices` (the file's or --set's) other than 1 gets as many
    XLA CPU devices (0: one per core this process may run on), so that a render on a CPU
    can be sharded over its cores (`xla.add_host_devices`). A GPU's devices are its own;
    a bad value is left for `config.load` to report."""
    from . import xla

    wanted = isinstance(devices, int) and not isinstance(devices, bool)
    if wanted and (devices == 0 or devices > 1):
        xla.add_host_devices(devices if devices > 1 else xla.cores())


def format_rate(x):
    """x with three significant digits, never in exponent form: 0.00123, 4.56, 789, 12345."""
    if not x > 0:
        return "0"
    import math

    decimals = max(0, 2 - math.floor(math.log10(x)))
    return f"{x:.{decimals}f}"


def _file_settings(path):
    """The [settings] table of a scene file, {} if it cannot be read (`config.load`
    reports that)."""
    try:
        table = tomllib.loads(Path(str(path)).read_text(encoding="utf-8")).get("settings", {})
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        return {}
    return table if isinstance(table, dict) else {}


if __name__ == "__main__":
    sys.exit(main())
