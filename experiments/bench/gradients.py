"""Benchmark: the cost of gradients. Time of `jax.value_and_grad` of an image loss over
the time of `render`, and the memory of the gradient program at max_steps 64 and 1024.

The scene is the showcase (`jaxrt/data/showcase.toml`, every primitive, combination,
placement and deformation family, a row of reflectance models) at the config's size.
The loss is the L2 distance to a target rendered with the lights 10 % brighter; its
gradient is taken with respect to every float of the scene and the camera (shapes,
placements, materials, lights, camera: ~100 leaves). For each variant (silhouette
estimator off/on) and each step budget (max_steps = shadow_steps ∈ budgets):

- render: median seconds of a compiled `render` over `repeats` calls;
- value_and_grad: median seconds of the compiled value and gradient, timed in turns
  with the render (same machine load), and the median of the per-turn ratios;
- memory: XLA's memory analysis of the compiled programs (temporary bytes, what the
  program allocates beyond its inputs and outputs), on a GPU the process's peak
  device memory, and the process's peak resident memory (`ru_maxrss`: on a CPU this is
  the device memory; it includes compilation), each budget measured in a fresh process so
  that peaks do not mix.

The marching loops are not differentiated (implicit gradients at the hit), so the
gradient program's memory must not depend on max_steps: the script prints the ratio of
the 1024-step figure to the 64-step one (expected within 10 %).

    python experiments/bench/gradients.py [--config configs/experiments/bench_gradients.toml]
        [--width W --height H] [--repeats N] [--variants point_samples silhouettes]
        [--out out/bench_gradients]
"""

import argparse
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
    ap.add_argument("--config", default=str(ROOT / "configs/experiments/bench_gradients.toml"))
    ap.add_argument("--width", type=int)
    ap.add_argument("--height", type=int)
    ap.add_argument("--repeats", type=int)
    ap.add_argument("--variants", nargs="+", help="a subset of the config's variants")
    ap.add_argument("--out", default=None)
    ap.add_argument("--one", nargs=2, metavar=("VARIANT", "MAX_STEPS"),
                    help=argparse.SUPPRESS)  # internal: measure one configuration
    args = ap.parse_args(argv)
    cfg = tomllib.loads(Path(args.config).read_text())
    for key in ("width", "height", "repeats"):
        if getattr(args, key) is not None:
            cfg[key] = getattr(args, key)

    if args.variants:
        unknown = sorted(set(args.variants) - set(cfg["variants"]))
        if unknown:
            ap.error(f"--variants {unknown}: expected some of {cfg['variants']}")
        cfg["variants"] = args.variants
    if args.one:
        print(json.dumps(measure(cfg, args.one[0], int(args.one[1]))))
        return

    out = Path(args.out or ROOT / "out" / "bench_gradients")
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for variant in cfg["variants"]:
        for steps in cfg["budgets"]:
            cmd = [sys.executable, __file__, "--config", args.config, "--one", variant, str(steps)]
            for key in ("width", "height", "repeats"):
                cmd += [f"--{key}", str(cfg[key])]
            res = subprocess.run(cmd, capture_output=True, text=True)
            if res.returncode != 0:
                sys.exit(f"{' '.join(cmd)} failed:\n{res.stderr[-4000:]}")
            row = json.loads(res.stdout.strip().splitlines()[-1])
            rows.append(row)
            print(_format(row), flush=True)
    print()
    for variant in cfg["variants"]:
        mine = {r["max_steps"]: r for r in rows if r["variant"] == variant}
        lo, hi = mine[min(mine)], mine[max(mine)]
        for key in ("grad_temp_bytes", "peak_device_bytes", "peak_rss_bytes"):
            if lo.get(key):
                print(f"{variant}: {key} at max_steps {hi['max_steps']} / {lo['max_steps']} = "
                      f"{hi[key] / lo[key]:.3f}")
        print(f"{variant}: value_and_grad / render = {lo['ratio']:.2f} (max_steps "
              f"{lo['max_steps']}), {hi['ratio']:.2f} (max_steps {hi['max_steps']})")
    (out / "results.json").write_text(json.dumps({"config": cfg, "rows": rows}, indent=2))
    (out / "config.toml").write_text(Path(args.config).read_text())
    print(f"wrote {out / 'results.json'}")


def measure(cfg, variant, max_steps):
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    import jaxrt as jr
    from jaxrt import fit

    scene, camera, settings = jr.config.load(ROOT / cfg["scene"], width=cfg["width"],
                                             height=cfg["height"])
    settings = settings.replace(max_steps=max_steps, shadow_steps=max_steps,
                                **cfg["settings"], **cfg["variant_settings"].get(variant, {}))
    brighter = eqx.tree_at(lambda s: s.lights, scene,
                           tuple(_brighter(l, 1.1) for l in scene.lights))

    def loss(params):
        sc, cam = params
        return fit.l2_loss(jr.render(sc, cam, settings).rgb, target)

    params = (scene, camera)
    render = eqx.filter_jit(lambda p: jr.render(*p, settings).rgb).lower(params).compile()
    target = render((brighter, camera))  # same structure: no second compile
    t0 = time.perf_counter()
    value_and_grad = eqx.filter_jit(eqx.filter_value_and_grad(loss)).lower(params).compile()
    compile_grad = time.perf_counter() - t0

    # Interleaved (render, value_and_grad) pairs, so that both see the same machine
    # load; medians of each, and the median of the per-pair ratios.
    jax.block_until_ready(render(params))
    jax.block_until_ready(value_and_grad(params))
    times = {"render": [], "grad": []}
    for _ in range(cfg["repeats"]):
        for name, fn in (("render", render), ("grad", value_and_grad)):
            t = time.perf_counter()
            jax.block_until_ready(fn(params))
            times[name].append(time.perf_counter() - t)
    median = lambda xs: sorted(xs)[len(xs) // 2]  # noqa: E731
    t_render, t_grad = median(times["render"]), median(times["grad"])
    ratio = median([g / r for g, r in zip(times["grad"], times["render"])])
    value, grads = value_and_grad(params)
    leaves = [x for x in jax.tree_util.tree_leaves(grads) if eqx.is_array(x)]
    finite = all(bool(jnp.all(jnp.isfinite(x))) for x in leaves)

    def temp(compiled):
        m = getattr(compiled, "compiled", compiled).memory_analysis()  # eqx.Compiled wraps jax's
        return None if m is None else int(m.temp_size_in_bytes)

    device = jax.devices()[0]
    stats = device.memory_stats() if hasattr(device, "memory_stats") else None
    return {
        "variant": variant, "max_steps": max_steps, "device": device.device_kind,
        "width": cfg["width"], "height": cfg["height"],
        "render_s": t_render, "value_and_grad_s": t_grad, "ratio": ratio,
        "compile_grad_s": compile_grad, "render_temp_bytes": temp(render),
        "grad_temp_bytes": temp(value_and_grad),
        "peak_device_bytes": None if not stats else stats.get("peak_bytes_in_use"),
        "peak_rss_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
        "gradient_leaves": int(sum(x.size for x in leaves)), "finite": finite,
        "loss": float(value),
    }


def _brighter(light, factor):
    """`light` with its intensity (point) or irradiance (directional) scaled by `factor`;
    positions and directions unchanged."""
    import equinox as eqx

    field = "intensity" if hasattr(light, "intensity") else "irradiance"
    return eqx.tree_at(lambda l: getattr(l, field), light, factor * getattr(light, field))


def _format(row):
    mb = lambda b: "-" if b is None else f"{b / 2**20:.1f} MiB"  # noqa: E731
    return (f"{row['variant']:>14s} max_steps {row['max_steps']:>5d}: render {row['render_s']*1e3:8.1f} ms"
            f"  value_and_grad {row['value_and_grad_s']*1e3:8.1f} ms  ratio {row['ratio']:5.2f}"
            f"  grad temp {mb(row['grad_temp_bytes'])}  render temp {mb(row['render_temp_bytes'])}"
            f"  peak {mb(row['peak_device_bytes'])}  peak RSS {mb(row['peak_rss_bytes'])}  ({row['gradient_leaves']} gradient floats,"
            f" finite: {row['finite']}, {row['device']})")


if __name__ == "__main__":
    main()
