"""Benchmark: how stable the showcase's pixels are under each set of XLA compiler options.

    python experiments/bench/xla_consistency.py [--backends fused,jax]
        [--variants default,fast-compile,...] [--width 96 --height 54] [--moves 8]
        [--out out/xla_consistency]

For each backend and variant (a `KernelOptions.xla` preset, or one of the single flags
in `VARIANTS`), the showcase is compiled once and rendered at its camera and at `moves`
eye positions moved by at most 1e-5 (uniform per axis, fixed seed). Per variant:
`compile_s`; `nonunit_normals`, the hit pixels whose normal AOV is not of unit length
(|‖n‖ − 1| > 1e-3: a normal assembled from copies of the SDF gradient that disagree),
per render; `flips`, the pixels whose rgb moved by more than 0.1 against the unmoved
render, per moved render (a 1e-5 move is 1e-4 of a pixel here: almost no pixel should
cross an edge); and `vs_first`: the largest rgb difference, and the pixels above 1e-3,
against the unmoved render of the first variant of the first backend (the reference).
Writes results.json, and the unmoved images as <backend>_<variant>.npy.
"""

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]

#: Variants beyond the presets of `jaxrt.xla.XLA_PRESETS`: one XLA flag each.
VARIANTS = {
    "emitters-off": {"xla_cpu_use_fusion_emitters": False},
    "O1": {"xla_backend_optimization_level": 1},
    "xla-fast-compile-preset": {"xla_cpu_opt_preset": "CPU_OPT_PRESET_FAST_COMPILE"},
}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--backends", default="fused,jax")
    ap.add_argument("--variants", default="default,fast-compile,emitters-off,O1,xla-fast-compile-preset")
    ap.add_argument("--width", type=int, default=96)
    ap.add_argument("--height", type=int, default=54)
    ap.add_argument("--moves", type=int, default=8)
    ap.add_argument("--out", default=str(ROOT / "out/xla_consistency"))
    args = ap.parse_args(argv)

    import equinox as eqx
    import jax
    import jax.numpy as jnp

    import jaxrt as jr
    from jaxrt.render import _cast

    jax.config.update("jax_enable_compilation_cache", False)
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    variants = args.variants.split(",")
    for v in variants:
        if v not in jr.xla.XLA_PRESETS and v not in VARIANTS:
            ap.error(f"--variants {v}: expected one of {sorted(jr.xla.XLA_PRESETS) + sorted(VARIANTS)}")
    rng = np.random.default_rng(0)
    moves = [rng.uniform(-1e-5, 1e-5, 3) for _ in range(args.moves)]
    info = dict(jax=jax.__version__, platform=jax.default_backend(), cpu_cores=os.cpu_count(),
                width=args.width, height=args.height, moves=args.moves)
    print(info, flush=True)
    rows, reference = [], None
    for backend in args.backends.split(","):
        scene, camera, settings = jr.config.load(ROOT / "jaxrt/data/showcase.toml", width=args.width,
                                                 height=args.height)
        settings = settings.replace(batch_size=4096, backend=backend)
        dyn, static = eqx.partition(_cast((scene, camera), jnp.float32), eqx.is_inexact_array)

        def image(d):
            s, c = eqx.combine(d, static)
            im = jr.render(s, c, settings)
            return {"rgb": im.rgb, "normal": im.normal, "coverage": im.coverage}

        lowered = jax.jit(image).lower(dyn)
        for variant in variants:
            options = (jr.xla.compiler_options(variant) if variant in jr.xla.XLA_PRESETS
                       else jr.xla.usable(VARIANTS[variant]))
            t = time.perf_counter()
            compiled = lowered.compile(compiler_options=options or None)
            compile_s = time.perf_counter() - t
            renders = [jax.tree.map(np.asarray, compiled(dyn))]
            for m in moves:
                moved = eqx.tree_at(lambda d: d[1].eye, dyn, dyn[1].eye + jnp.asarray(m, jnp.float32))
                renders.append(jax.tree.map(np.asarray, compiled(moved)))
            base = renders[0]["rgb"]
            np.save(out_dir / f"{backend}_{variant}.npy", base)
            reference = base if reference is None else reference
            diff = np.abs(base - reference).max(axis=-1)
            row = dict(backend=backend, variant=variant, options=options, compile_s=round(compile_s, 2),
                       nonunit_normals=[_nonunit(r) for r in renders],
                       flips=[int((np.abs(r["rgb"] - base).max(axis=-1) > 0.1).sum()) for r in renders[1:]],
                       vs_first=dict(max=float(diff.max()), pixels=int((diff > 1e-3).sum())),
                       load=os.getloadavg()[0])
            rows.append(row)
            print(json.dumps(row), flush=True)
            (out_dir / "results.json").write_text(json.dumps(dict(info=info, rows=rows), indent=1))
    return rows


def _nonunit(render):
    n = np.linalg.norm(render["normal"], axis=-1)
    return int(((render["coverage"] > 0) & (np.abs(n - 1.0) > 1e-3)).sum())


if __name__ == "__main__":
    main()
