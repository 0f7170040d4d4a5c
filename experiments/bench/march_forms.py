"""Benchmark: the Warp scene's forward render with the marches in each loop form.

`jaxrt.march.form`: "plain" (what backend "pallas" takes under march_form = "auto")
against "phases". The scene file's settings and AOVs, max_steps = shadow_steps = 64,
backend "auto" (→ "pallas" on a GPU, "fused" elsewhere); the time of a render is the
median of 7 timings, each the mean of 10 calls launched back to back (after
compilation, which is reported apart). Also prints the largest difference between the
two forms' images.

    python experiments/bench/march_forms.py [--width 2048 --height 1024]
"""

import argparse
import time

import numpy as np


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--width", type=int, default=2048)
    ap.add_argument("--height", type=int, default=1024)
    ap.add_argument("--scene", default="configs/scenes/warp_raymarch.toml")
    args = ap.parse_args(argv)

    import equinox as eqx
    import jax

    import jaxrt as jr

    print(jr.__file__, jax.__version__, jax.devices()[0].device_kind, flush=True)
    scene, camera, settings = jr.config.load(args.scene, width=args.width, height=args.height)
    images = {}
    for march_form in ("auto", "phases", "plain"):
        s = settings.replace(max_steps=64, shadow_steps=64, backend="auto",
                             kernel=settings.kernel.replace(march_form=march_form))
        dyn, static = eqx.partition((scene, camera), eqx.is_array)
        f = jax.jit(lambda d, s=s: jr.render(*eqx.combine(d, static), s).rgb)
        t0 = time.perf_counter()
        images[march_form] = np.asarray(f(dyn).block_until_ready())
        compile_s = time.perf_counter() - t0
        times = []
        for _ in range(7):
            t0 = time.perf_counter()
            for _ in range(10):
                out = f(dyn)
            out.block_until_ready()
            times.append((time.perf_counter() - t0) / 10)
        print(f"march_form={march_form:7s} forward {1e3 * np.median(times):.3f} ms "
              f"(min {1e3 * min(times):.3f}) compile {compile_s:.1f} s", flush=True)
    diff = np.abs(images["plain"] - images["phases"])
    print(f"|plain − phases|: max {diff.max():.3g}, pixels > 1e-3: {(diff.max(-1) > 1e-3).mean():.2%}")


if __name__ == "__main__":
    main()
