"""A/B: a gradient's replay with stacked unions as scans or evaluated wide.

`KernelOptions.replay_wide_unions`: the replay of a fast backend's gradient evaluates a
stacked union's children in a scan (False) or all at once, `vmap` + argmin (True; the
default on a GPU). This times `jax.value_and_grad` of an L2 image loss on the union of
64 spheres of experiments/bench/gradients.py, both ways in one process (median of
`repeats` calls after the compile), and prints the largest relative difference of the
two gradients.

    python experiments/bench/replay_unions.py [--size 512] [--repeats 9]
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", type=int, default=512, help="image width and height")
    ap.add_argument("--repeats", type=int, default=9)
    args = ap.parse_args(argv)

    import jax
    import jax.numpy as jnp

    import jaxrt as jr
    from gradients import spheres64

    scene, camera, settings = spheres64()
    camera = camera.with_resolution(args.size, args.size)
    settings = settings.replace(max_steps=64, shadow_steps=64)
    target = jr.render(scene, camera, settings).rgb * 1.1
    grads = {}
    for wide in (False, True):
        s = settings.replace(kernel=settings.kernel.replace(replay_wide_unions=wide))

        @jax.jit
        def value_and_grad(sc, s=s):
            return jax.value_and_grad(
                lambda q: jnp.mean((jr.render(q, camera, s).rgb - target) ** 2))(sc)

        start = time.perf_counter()
        grads[wide] = jax.block_until_ready(value_and_grad(scene))
        compile_s = time.perf_counter() - start
        times = []
        for _ in range(args.repeats):
            start = time.perf_counter()
            jax.block_until_ready(value_and_grad(scene))
            times.append(time.perf_counter() - start)
        print(f"replay_wide_unions={wide}: value_and_grad {1e3 * np.median(times):.2f} ms, "
              f"compile {compile_s:.1f} s ({jax.devices()[0].device_kind}, jax {jax.__version__}, "
              f"{args.size}x{args.size})", flush=True)
    diffs = [float(jnp.max(jnp.abs(a - b)) / (jnp.max(jnp.abs(a)) + 1e-30))
             for a, b in zip(jax.tree_util.tree_leaves(grads[False]),
                             jax.tree_util.tree_leaves(grads[True]))]
    print(f"largest relative difference of the gradients: {max(diffs):.2e}")


if __name__ == "__main__":
    main()
