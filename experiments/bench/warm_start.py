"""Where a warm `jaxrt render` spends its time (issue 12's "≤ 5 s with a warm cache").

Run it twice with the same cache folder: the first run fills the cache, the second shows
what a warm start costs. Prints import, scene load, compile (with the part spent reading
XLA's executable back from JAX's persistent cache, timed around JAX's own reader) and
render, in seconds:

    python experiments/bench/warm_start.py [SCENE.toml] [--cache DIR]
"""

import argparse
import time

T0 = time.perf_counter()


def main():
    import jax

    import jaxrt
    from jaxrt import cache, cli, config

    imported = time.perf_counter() - T0
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", nargs="?", default=str(cli.showcase_path()))
    ap.add_argument("--cache", default=None, help="cache folder (default: jaxrt's)")
    args = ap.parse_args()

    read = []
    try:  # JAX-internal: the persistent cache's reader (only timed, behaviour unchanged)
        from jax._src import compilation_cache as jax_cache

        reader = jax_cache.get_executable_and_time

        def timed_reader(*a, **k):
            start = time.perf_counter()
            result = reader(*a, **k)
            read.append((time.perf_counter() - start, result[0] is not None))
            return result

        jax_cache.get_executable_and_time = timed_reader
    except (ImportError, AttributeError):
        pass

    folder = cache.enable_compilation_cache(args.cache)
    start = time.perf_counter()
    scene, camera, settings = config.load(args.scene)
    loaded = time.perf_counter() - start
    start = time.perf_counter()
    run, reused = cache.compile_render_cached(scene, camera, settings, folder)
    compiled = time.perf_counter() - start
    start = time.perf_counter()
    run(scene, camera).rgb.block_until_ready()
    rendered = time.perf_counter() - start
    hits = sum(hit for _, hit in read)
    print(f"jaxrt {jaxrt.__version__}, jax {jax.__version__} ({jax.default_backend()}), "
          f"{args.scene} at {camera.width}×{camera.height}, backend {settings.backend}")
    print(f"import {imported:.2f} s, load {loaded:.2f} s, compile {compiled:.2f} s "
          f"(program reused: {reused}; XLA cache reads {sum(t for t, _ in read):.2f} s, "
          f"{hits} hits of {len(read)}), render {rendered:.2f} s")


if __name__ == "__main__":
    main()
