"""Where the time of a GPU render goes: device time per kernel, from JAX's profiler.

    python experiments/bench/gpu_profile.py [--variant pallas-fast] [--calls 20]

Renders the Warp benchmark scene with one variant of `configs/experiments/warp_bench.toml`
under `jax.profiler.trace`, then reads the trace back (`jax.profiler.ProfileData`) and
prints the device time of every kernel, summed over the calls and divided by their
number, largest first: the fused render kernel and the XLA kernels around it.
"""

import argparse
import glob
import os
import sys
import tempfile
import tomllib
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(Path(__file__).parent))
from warp_scene import kernel_options  # noqa: E402  (the variants' Pallas knobs)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", default=str(ROOT / "configs/experiments/warp_bench.toml"))
    ap.add_argument("--variant", action="append")
    ap.add_argument("--calls", type=int, default=20)
    ap.add_argument("--width", type=int)
    ap.add_argument("--height", type=int)
    ap.add_argument("--devices", type=int, action="append", help="RenderSettings.devices values")
    ap.add_argument("--split", action="append", choices=["columns", "rows"],
                    help="RenderSettings.split values (the image axis cut over the devices)")
    ap.add_argument("--no-trace", action="store_true", help="time only, no profile")
    args = ap.parse_args(argv)
    cfg = tomllib.loads(Path(args.config).read_text())

    import equinox as eqx
    import jax
    import jax.numpy as jnp

    import jaxrt as jr
    from jaxrt.render import _cast, _render

    section = cfg["gpu" if jax.default_backend() == "gpu" else "cpu"]
    scene, camera, base = jr.config.load(ROOT / cfg["scene"], width=args.width or section["width"],
                                         height=args.height or section["height"])
    dyn, static = eqx.partition(_cast((scene, camera), jnp.float32), eqx.is_array)
    from jaxrt import sharding

    runs = [(name, d, s) for name in (args.variant or ["pallas-fast"]) for d in (args.devices or [1])
            for s in ((args.split or [base.split]) if d != 1 else [base.split])]
    for name, devices, split in runs:
        overrides = dict(cfg["variants"][name])
        kernel = kernel_options(overrides.pop("kernel", {}))
        settings = base.replace(**overrides, devices=devices, split=split, kernel=kernel)
        name = f"{name} devices={devices}" + (f" split={split}" if devices != 1 else "")
        f = jax.jit(lambda d, settings=settings: _render.__wrapped__(*eqx.combine(d, static), settings))
        dyn_ = dyn
        if devices != 1:  # the scene's arrays on every device, as a fitting loop keeps them
            mesh = sharding.pixel_mesh(sharding.local_devices(devices))
            dyn_ = jax.device_put(dyn, jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec()))
        f = f.lower(dyn_).compile()
        f(dyn_).rgb.block_until_ready()
        import time

        t0 = time.perf_counter()
        for _ in range(args.calls):
            out = f(dyn_)
        out.rgb.block_until_ready()
        print(f"{name}: {1e3 * (time.perf_counter() - t0) / args.calls:.3f} ms per render "
              f"({args.calls} back to back)", flush=True)
        if args.no_trace:
            continue
        print_kernel_times(lambda: f(dyn_).rgb, args.calls, name)


def print_kernel_times(call, calls, name, top=12):
    """Run `call()` `calls` times under `jax.profiler.trace` and print the device time of
    each kernel per call (summed over the calls, divided by their number), largest first."""
    import jax

    tmp = tempfile.mkdtemp()
    with jax.profiler.trace(tmp):
        for _ in range(calls):
            out = call()
        jax.block_until_ready(out)
    path = glob.glob(os.path.join(tmp, "**", "*.xplane.pb"), recursive=True)[0]
    pd = jax.profiler.ProfileData.from_file(path)
    for plane in pd.planes:
        if not (plane.name.startswith("/device:GPU") or (
                jax.default_backend() == "cpu" and plane.name.startswith("/host:CPU"))):
            continue
        for line in plane.lines:
            totals, counts = defaultdict(float), defaultdict(int)
            for ev in line.events:
                totals[ev.name] += ev.duration_ns
                counts[ev.name] += 1
            if not totals:
                continue
            total = sum(totals.values()) / calls / 1e3
            print(f"\n{name} | {plane.name} | {line.name}: {total:.1f} us per call, "
                  f"{sum(counts.values()) / calls:.0f} kernels")
            for k, v in sorted(totals.items(), key=lambda kv: -kv[1])[:top]:
                print(f"  {v / calls / 1e3:9.1f} us  x{counts[k] / calls:<5.1f} {k[:90]}")


if __name__ == "__main__":
    main()
