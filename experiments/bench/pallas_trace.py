"""Benchmark: how long JAX takes to trace and lower a Pallas render for a GPU, on any
machine (no GPU needed): the part of a Pallas compile that is Python, which grows with
a scene's counts where Triton's kernel does not.

For each scene of `compile.py` (config `configs/experiments/compile.toml`) and mode
(render, or value_and_grad of an L2 loss), the program of `compile.program` with
`backend = "pallas"` is traced and lowered for CUDA
(`jax.jit(f).trace(dyn).lower(lowering_platforms=("cuda",))`). Prints seconds of each
and the size of the lowered text:

    python experiments/bench/pallas_trace.py [--scenes spheres8,spheres256]
        [--modes render,grad] [--size 64]
"""

import argparse
import time
import tomllib
from pathlib import Path

import compile as bench

ROOT = Path(__file__).resolve().parents[2]


def main():
    import jax

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", default="spheres8,spheres256")
    ap.add_argument("--modes", default="render,grad")
    ap.add_argument("--size", type=int, default=64, help="image width and height")
    args = ap.parse_args()
    cfg = tomllib.loads((ROOT / "configs/experiments/compile.toml").read_text())
    cfg.update(width=args.size, height=args.size)
    print(f"jax {jax.__version__} on {jax.default_backend()}, lowered for cuda, {args.size}²")
    for name in args.scenes.split(","):
        for mode in args.modes.split(","):
            scene, camera, settings = bench.SCENES[name](cfg)
            settings = settings.replace(**{**cfg.get("settings", {}), "backend": "pallas"})
            # the GPU's program: Triton, not the interpreter; the replay's unions wide
            settings = settings.replace(kernel=settings.kernel.replace(
                interpret=False, replay_wide_unions=True))
            f, dyn = bench.program(scene, camera, settings, mode)
            jax.clear_caches()
            start = time.perf_counter()
            traced = jax.jit(f).trace(dyn)
            traced_s = time.perf_counter() - start
            text = traced.lower(lowering_platforms=("cuda",)).as_text()
            lowered_s = time.perf_counter() - start - traced_s
            print(f"{name:>12} {mode:>6}  trace {traced_s:6.2f} s  lower {lowered_s:5.2f} s  "
                  f"{len(text) / 1e3:7.0f} kB", flush=True)


if __name__ == "__main__":
    main()
