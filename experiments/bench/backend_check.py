"""One scene file rendered with a fused backend and with "jax": compile and render times,
non-finite values and the difference between the images.

    python experiments/bench/backend_check.py jaxrt/data/showcase.toml --backend pallas \
        --width 160 --height 90 [--save ref.npy | --reference ref.npy]

`--save` writes the "jax" image (to compare on another machine later, say a CPU
reference for a GPU run); `--reference` compares with such a file instead of rendering
"jax" here. Render times: mean of `--repeats` renders after compilation.
"""

import argparse
import time

import numpy as np

import jaxrt as jr
from jaxrt.render import compile_render


def render(scene, camera, settings, repeats):
    t0 = time.perf_counter()
    f = compile_render(scene, camera, settings)
    t1 = time.perf_counter()
    f(scene, camera).rgb.block_until_ready()
    t2 = time.perf_counter()
    for _ in range(repeats):
        img = f(scene, camera)
    rgb = np.asarray(img.rgb)
    t3 = time.perf_counter()
    print(f"{settings.backend:7s} compile {t1 - t0:6.1f} s  render {(t3 - t2) / repeats * 1e3:9.2f} ms  "
          f"non-finite values {int((~np.isfinite(rgb)).sum())}", flush=True)
    return rgb


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scene")
    ap.add_argument("--backend", default="pallas", choices=["fused", "pallas", "auto"])
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--height", type=int, default=90)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--save", help="write the 'jax' image here (.npy) and stop")
    ap.add_argument("--reference", help="compare with this .npy image instead of 'jax'")
    args = ap.parse_args(argv)

    scene, camera, base = jr.config.load(args.scene, width=args.width, height=args.height)
    if args.reference:
        want = np.load(args.reference)
    else:
        want = render(scene, camera, base.replace(backend="jax"), args.repeats)
        if args.save:
            np.save(args.save, want)
            return
    got = render(scene, camera, base.replace(backend=args.backend), args.repeats)
    d = np.abs(got - want).max(axis=-1)
    print(f"difference: max {d.max():.3g}, RMSE {np.sqrt(np.mean((got - want) ** 2)):.3g}, "
          f"pixels off by > 0.01: {(d > 0.01).mean():.3%}, by > 0.1: {(d > 0.1).mean():.3%}")


if __name__ == "__main__":
    main()
