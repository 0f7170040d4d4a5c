"""Benchmark: the cost of gradients. The forward render (fastest backend) against
`jax.value_and_grad` of an L2 image loss with respect to every float of scene and camera.

Scenes (configs/experiments/gradients.toml): the Warp scene, a union of 64 spheres in
two materials on a plane (built here), the showcase and the glass scene at its file's
depth. The loss is the L2 distance to a target rendered with the lights 10 % brighter.
For each scene and each march budget (max_steps = shadow_steps), in a fresh process (so
that peak memory figures do not mix):

- forward: median seconds of a compiled `render` (the config's backend, "auto": Pallas
  on a GPU, fused lanes on a CPU, with their fall-backs) over `repeats` calls;
- value_and_grad: median seconds of the compiled loss and gradient (the fast backends
  record their marches and differentiate a loop-free replay, `jaxrt.render`), timed in
  turns with the forward (same machine load), and the median of the per-turn ratios;
- with --reference, also value_and_grad through backend="jax" (the vmapped program,
  differentiated as it is: how gradients were taken before record/replay);
- compile times; memory: XLA's memory analysis of the compiled programs (temporary
  bytes), on a GPU the peak device memory (`memory_stats()["peak_bytes_in_use"]`), and
  the process's peak resident memory (`ru_maxrss`; on a CPU it includes compilation).

Gradient memory must not grow with max_steps (no march is differentiated): run two
budgets (--max-steps 64 1024) and the script prints the ratios.

    python experiments/bench/gradients.py [--config configs/experiments/gradients.toml]
        [--scenes warp spheres64 showcase glass] [--size warp=2048x1024 ...]
        [--max-steps 64 1024] [--repeats N] [--backend auto] [--silhouette]
        [--reference] [--profile CALLS] [--set KEY=VALUE ...] [--out out/bench_gradients]

Sizes default to the config's `gpu` sizes on a GPU and its `cpu` sizes elsewhere.
"""

import argparse
import dataclasses
import json
import resource
import subprocess
import sys
import time
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", default=str(ROOT / "configs/experiments/gradients.toml"))
    ap.add_argument("--scenes", nargs="+", help="a subset of the config's scenes")
    ap.add_argument("--size", nargs="+", default=[], metavar="SCENE=WxH",
                    help="image sizes, e.g. warp=2048x1024 (default: the config's)")
    ap.add_argument("--max-steps", nargs="+", type=int, help="march budgets")
    ap.add_argument("--repeats", type=int)
    ap.add_argument("--backend", help="forward/gradient backend (default: the config's)")
    ap.add_argument("--silhouette", action="store_true", help="silhouette estimator on")
    ap.add_argument("--reference", action="store_true",
                    help='also time value_and_grad through backend="jax"')
    ap.add_argument("--profile", type=int, default=0, metavar="CALLS",
                    help="also print the device time per kernel of value_and_grad and of the "
                         "forward, over CALLS calls under jax.profiler (gpu_profile.py)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a RenderSettings field for every scene, as `jaxrt render --set` "
                         "(kernel.FIELD for a KernelOptions field); repeatable")
    ap.add_argument("--out", default=None)
    ap.add_argument("--one", nargs=4, metavar=("SCENE", "W", "H", "MAX_STEPS"),
                    help=argparse.SUPPRESS)  # internal: measure one configuration
    args = ap.parse_args(argv)
    cfg = tomllib.loads(Path(args.config).read_text())
    cfg["repeats"] = args.repeats or cfg["repeats"]
    cfg["backend"] = args.backend or cfg["backend"]
    cfg["silhouette"] = args.silhouette
    cfg["reference"] = args.reference
    cfg["profile"] = args.profile
    cfg["set"] = args.set
    own = {"max_steps", "shadow_steps", "backend", "silhouette"}  # the script's own options
    for item in args.set:
        if item.partition("=")[0].strip() in own:
            ap.error(f"--set {item}: use --max-steps, --backend or --silhouette")
    if args.one:
        name, w, h, steps = args.one
        print(json.dumps(measure(cfg, name, int(w), int(h), int(steps))))
        return

    scenes = args.scenes or list(cfg["scenes"])
    unknown = sorted(set(scenes) - set(cfg["scenes"]))
    if unknown:
        ap.error(f"--scenes {unknown}: expected some of {list(cfg['scenes'])}")
    sizes = {}
    for item in args.size:
        try:
            name, wh = item.split("=")
            sizes[name] = tuple(int(v) for v in wh.lower().split("x"))
        except ValueError:
            ap.error(f"--size {item!r}: expected SCENE=WxH, e.g. warp=2048x1024")
    budgets = args.max_steps or cfg["max_steps"]
    gpu = _on_gpu()
    out = Path(args.out or ROOT / "out" / "bench_gradients")
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in scenes:
        w, h = sizes.get(name) or cfg["scenes"][name]["gpu" if gpu else "cpu"]
        for steps in budgets:
            cmd = [sys.executable, __file__, "--config", args.config, "--repeats",
                   str(cfg["repeats"]), "--backend", cfg["backend"], "--one", name, str(w),
                   str(h), str(steps)]
            cmd += ["--silhouette"] * args.silhouette + ["--reference"] * args.reference
            cmd += ["--profile", str(args.profile)] + [f"--set={item}" for item in args.set]
            res = subprocess.run(cmd, capture_output=True, text=True)
            if res.returncode != 0:
                print(f"{' '.join(cmd)} failed:\n{res.stderr[-3000:]}", flush=True)
                continue
            row = json.loads(res.stdout.strip().splitlines()[-1])
            rows.append(row)
            print(_format(row), flush=True)
            if row.get("profile"):
                print(row["profile"], flush=True)
    print()
    for name in scenes:
        mine = {r["max_steps"]: r for r in rows if r["scene"] == name}
        if len(mine) < 2:
            continue
        lo, hi = mine[min(mine)], mine[max(mine)]
        for key in ("grad_temp_bytes", "peak_device_bytes", "peak_rss_bytes"):
            if lo.get(key) and hi.get(key):
                print(f"{name}: {key} at max_steps {hi['max_steps']} / {lo['max_steps']} = "
                      f"{hi[key] / lo[key]:.3f}")
    (out / "results.json").write_text(json.dumps({"config": cfg, "rows": rows}, indent=2))
    (out / "config.toml").write_text(Path(args.config).read_text())
    print(f"wrote {out / 'results.json'}")


def _on_gpu():
    code = "import jax; print(jax.default_backend())"
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    return res.stdout.strip() == "gpu"


def spheres64():
    """64 spheres (radius 0.3, an 8×8 grid, two Lambert materials in a checkerboard) on a
    plane of a third, under one point light: stacked unions of one kind."""
    import jaxrt as jr
    from jaxrt import sdf
    from jaxrt.bsdf import Lambert

    spheres = [sdf.Translate(sdf.Sphere(0.3, material=(i + j) % 2),
                             offset=(0.8 * (i - 3.5), 0.3, 0.8 * (j - 3.5)))
               for i in range(8) for j in range(8)]
    surface = sdf.Union(*spheres, sdf.Plane((0.0, 1.0, 0.0), 0.0, material=2))
    materials = [Lambert((0.7, 0.3, 0.2)), Lambert((0.2, 0.4, 0.7)), Lambert((0.6, 0.6, 0.6))]
    scene = jr.Scene(surface, materials, [jr.PointLight((2.0, 6.0, -3.0), (60.0, 60.0, 60.0))],
                     background=(0.1, 0.1, 0.15))
    camera = jr.PerspectiveCamera(eye=(0.0, 5.0, -7.0), target=(0.0, 0.0, 0.0), fov=45.0,
                                  width=512, height=512)
    return scene, camera, jr.RenderSettings(shadows="hard", max_depth=0)


def measure(cfg, name, width, height, max_steps):
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    import jaxrt as jr
    from jaxrt import fit
    from jaxrt.cli import parse_overrides

    spec = cfg["scenes"][name]
    if spec["file"] == "spheres64":
        scene, camera, settings = spheres64()
        camera = camera.with_resolution(width, height)
    else:
        scene, camera, settings = jr.config.load(ROOT / spec["file"], width=width, height=height)
    overrides = {k: v for k, v in cfg.get("settings", {}).items() if not isinstance(v, dict)}
    overrides.update(cfg.get("settings", {}).get(name, {}))
    overrides.update(parse_overrides(cfg["set"]))
    if isinstance(overrides.get("kernel"), dict):  # merged into the scene's own options
        overrides["kernel"] = dataclasses.replace(settings.kernel, **overrides["kernel"])
    settings = settings.replace(max_steps=max_steps, shadow_steps=max_steps,
                                backend=cfg["backend"], silhouette=cfg["silhouette"], **overrides)
    brighter = eqx.tree_at(lambda s: s.lights, scene,
                           tuple(_brighter(light, 1.1) for light in scene.lights))
    params = (scene, camera)

    def compiled(fn):
        t0 = time.perf_counter()
        c = eqx.filter_jit(fn).lower(params).compile()
        return c, time.perf_counter() - t0

    render, compile_render = compiled(lambda p: jr.render(*p, settings).rgb)
    target = jax.block_until_ready(render((brighter, camera)))  # same structure: no recompile

    def loss_with(s):
        return lambda p: fit.l2_loss(jr.render(*p, s).rgb, target)

    grad, compile_grad = compiled(eqx.filter_value_and_grad(loss_with(settings)))
    fns = {"render": render, "grad": grad}
    compile_ref = None
    if cfg["reference"]:
        fns["reference"], compile_ref = compiled(
            eqx.filter_value_and_grad(loss_with(settings.replace(backend="jax"))))

    # Interleaved turns, so that every function sees the same machine load; medians of
    # each, and the median of the per-turn ratios to the forward render.
    for fn in fns.values():
        jax.block_until_ready(fn(params))
    times = {k: [] for k in fns}
    for _ in range(cfg["repeats"]):
        for k, fn in fns.items():
            t = time.perf_counter()
            jax.block_until_ready(fn(params))
            times[k].append(time.perf_counter() - t)
    median = lambda xs: sorted(xs)[len(xs) // 2]  # noqa: E731
    ratio = lambda k: median([g / r for g, r in zip(times[k], times["render"])])  # noqa: E731
    value, grads = grad(params)
    leaves = [x for x in jax.tree_util.tree_leaves(grads) if eqx.is_array(x)]
    finite = all(bool(jnp.all(jnp.isfinite(x))) for x in leaves)

    def temp(c):
        m = getattr(c, "compiled", c).memory_analysis()  # eqx.Compiled wraps jax's
        return None if m is None else int(m.temp_size_in_bytes)

    device = jax.local_devices()[0]
    stats = device.memory_stats() if hasattr(device, "memory_stats") else None
    row = {
        "scene": name, "width": width, "height": height, "max_steps": max_steps,
        "backend": settings.backend, "silhouette": settings.silhouette, "set": cfg["set"],
        "device": device.device_kind, "jax": jax.__version__,
        "render_s": median(times["render"]), "value_and_grad_s": median(times["grad"]),
        "ratio": ratio("grad"), "compile_render_s": compile_render,
        "compile_grad_s": compile_grad, "render_temp_bytes": temp(render),
        "grad_temp_bytes": temp(grad),
        "peak_device_bytes": None if not stats else stats.get("peak_bytes_in_use"),
        "peak_rss_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
        "gradient_floats": int(sum(x.size for x in leaves)), "finite": finite,
        "loss": float(value),
    }
    if cfg["profile"]:
        row["profile"] = _profile(fns, params, cfg["profile"])
    if cfg["reference"]:
        row.update(reference_s=median(times["reference"]), reference_ratio=ratio("reference"),
                   compile_reference_s=compile_ref)
    return row


def _profile(fns, params, calls):
    """The device time per kernel of the forward and of value_and_grad, as text."""
    import contextlib
    import io

    sys.path.insert(0, str(Path(__file__).parent))
    from gpu_profile import print_kernel_times

    text = io.StringIO()
    with contextlib.redirect_stdout(text):
        for k in ("render", "grad"):
            print_kernel_times(lambda k=k: fns[k](params), calls, k)
    return text.getvalue()


def _brighter(light, factor):
    """`light` with its intensity (point) or irradiance (directional) scaled by `factor`."""
    import equinox as eqx

    field = "intensity" if hasattr(light, "intensity") else "irradiance"
    return eqx.tree_at(lambda l: getattr(l, field), light, factor * getattr(light, field))


def _format(row):
    mb = lambda b: "-" if b is None else f"{b / 2**20:.1f} MiB"  # noqa: E731
    ref = ""
    if "reference_s" in row:
        ref = (f"  jax-path grad {row['reference_s']*1e3:9.1f} ms ({row['reference_ratio']:.1f}x,"
               f" compile {row['compile_reference_s']:.0f} s)")
    return (f"{row['scene']:>10s} {row['width']}x{row['height']} max_steps {row['max_steps']:>5d}:"
            f" forward {row['render_s']*1e3:9.2f} ms  value_and_grad {row['value_and_grad_s']*1e3:9.2f} ms"
            f"  ratio {row['ratio']:5.2f}{ref}  compile {row['compile_render_s']:.0f} s / "
            f"{row['compile_grad_s']:.0f} s  grad temp {mb(row['grad_temp_bytes'])}"
            f"  peak {mb(row['peak_device_bytes'])}  peak RSS {mb(row['peak_rss_bytes'])}"
            f"  ({row['gradient_floats']} floats, finite: {row['finite']}, {row['device']},"
            f" jax {row['jax']})" + (f"  --set {' '.join(row['set'])}" if row["set"] else ""))


if __name__ == "__main__":
    main()
