"""Scaling: render time against pixel count, primitive count and recursion depth;
compile time against primitive count; speed-up from one device to several.

    python experiments/bench/scaling.py [--config configs/experiments/scaling.toml]
                                        [--only pixels,primitives,depth,devices,showcase]

Every time is the median of `repeats` renders after compilation; compile time is
measured apart (trace + lower + XLA compile of `render`). Writes `results.json` and
`scaling.md` under the output folder (default out/scaling) and prints the tables.
"""

import argparse
import json
import os
import time
import tomllib
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", default=str(ROOT / "configs/experiments/scaling.toml"))
    ap.add_argument("--only", default=None)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    cfg = tomllib.loads(Path(args.config).read_text())

    import jax

    gpu = jax.default_backend() == "gpu"
    section = cfg["gpu" if gpu else "cpu"]
    parts = args.only.split(",") if args.only else section["parts"]
    out_dir = Path(args.out or ROOT / "out/scaling")
    out_dir.mkdir(parents=True, exist_ok=True)
    info = dict(device=jax.devices()[0].device_kind, backend=jax.default_backend(),
                devices=len(jax.local_devices()), cpu_cores=os.cpu_count(), jax=jax.__version__)
    print(info, flush=True)
    results = dict(info=info)
    md = [f"# Scaling ({info['device']}, {info['backend']}, {info['devices']} device(s))", ""]
    for part in parts:
        rows = globals()["_" + part](cfg[part], section)
        results[part] = rows
        md += [f"## {part}", "", _table(rows), ""]
        print(f"\n{part}\n{_table(rows)}", flush=True)
        (out_dir / "results.json").write_text(json.dumps(results, indent=1, default=str))
        (out_dir / "scaling.md").write_text("\n".join(md))
    print(f"wrote {out_dir / 'results.json'} and scaling.md")
    return results


def _table(rows):
    keys = list(rows[0])
    lines = ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    for r in rows:
        lines.append("| " + " | ".join(_fmt(r[k]) for k in keys) + " |")
    return "\n".join(lines)


def _fmt(v):
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def measure(scene, camera, settings, repeats):
    """(compile seconds, median render seconds, image) for one configuration."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    from jaxrt.render import _cast, _dtype, _render

    dyn, static = eqx.partition(_cast((scene, camera), _dtype(settings)), eqx.is_array)
    jax.clear_caches()
    t0 = time.perf_counter()
    f = jax.jit(lambda d: _render.__wrapped__(*eqx.combine(d, static), settings))
    lowered = f.lower(dyn)
    t1 = time.perf_counter()
    f = lowered.compile()
    t2 = time.perf_counter()
    img = f(dyn)
    img.rgb.block_until_ready()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        f(dyn).rgb.block_until_ready()
        times.append(time.perf_counter() - t)
    return t1 - t0, t2 - t1, float(np.median(times)), img


def _settings(section, **extra):
    import jaxrt as jr

    return jr.RenderSettings(**{**section.get("settings", {}), **extra})


# ------------------------------------------------------------------------------- parts


def _pixels(cfg, section):
    import jaxrt as jr

    rows = []
    for w, h in section["pixel_sizes"]:
        scene, camera, base = jr.config.load(ROOT / cfg["scene"], width=w, height=h)
        st = base.replace(**section.get("settings", {}))
        tl, tc, t, _ = measure(scene, camera, st, section["repeats"])
        rows.append(dict(width=w, height=h, pixels=w * h, compile_s=tl + tc, render_ms=1e3 * t,
                         mrays_per_s=w * h / t / 1e6))
    return rows


def primitive_scene(n, width, height, stack_threshold=None):
    """n spheres on a grid over a plane, in one Union (n + 1 children): two kinds of
    sphere (materials 0 and 1, n/2 each) and the plane."""
    import jaxrt as jr

    S = jr.sdf
    k = int(np.ceil(np.sqrt(n)))
    spheres = []
    for i in range(n):
        x, z = (i % k - (k - 1) / 2) * 1.2, (i // k - (k - 1) / 2) * 1.2
        spheres.append(S.Translate(S.Sphere(radius=0.5, material=i % 2), offset=(x, 0.5, z)))
    children = [*spheres, S.Plane(normal=(0.0, 1.0, 0.0), offset=0.0, material=2)]
    surface = S.Union(*children) if stack_threshold is None else \
        S.Union(*children, stack_threshold=stack_threshold)
    scene = jr.Scene(surface=surface,
                     materials=[jr.bsdf.Lambert(albedo=(0.8, 0.3, 0.2)),
                                jr.bsdf.Lambert(albedo=(0.2, 0.5, 0.8)),
                                jr.bsdf.Lambert(albedo=(0.7, 0.7, 0.7))],
                     lights=[jr.PointLight(position=(3.0, 6.0, 4.0), intensity=(60.0, 60.0, 60.0))],
                     background=(0.05, 0.05, 0.08))
    r = 1.2 * k
    camera = jr.PerspectiveCamera(eye=(0.0, 0.8 * r + 2.0, 1.4 * r + 3.0), target=(0.0, 0.0, 0.0),
                                  up=(0.0, 1.0, 0.0), fov=45.0, width=width, height=height)
    return scene, camera


# Union variants: the threshold of `jaxrt.sdf.stack` (groups of at least this many
# children of one structure are stacked) that each measures.
UNIONS = {"library": None, "loop": 10**9, "stacked": 2}


def _primitives(cfg, section):
    """Compile and render time against the number of spheres in one `sdf.Union`:
    "library" (the Union as shipped: groups of ≥ STACK_THRESHOLD children of one kind
    stacked), "loop" (every child a copy in the program, as before stacking) and
    "stacked" (every group of ≥ 2 stacked), each up to cfg["max_count"][variant]
    (`Union(stack_threshold=...)`)."""
    rows = []
    st = _settings(section)
    for union in cfg.get("unions", list(UNIONS)):
        for n in cfg["counts"]:
            if n > cfg.get("max_count", {}).get(union, n):
                continue
            scene, camera = primitive_scene(n, *cfg["size"], stack_threshold=UNIONS[union])
            tl, tc, t, img = measure(scene, camera, st, section["repeats"])
            rows.append(dict(union=union, primitives=n, trace_lower_s=tl, xla_compile_s=tc,
                             compile_s=tl + tc, compile_per_primitive_ms=1e3 * (tl + tc) / n,
                             render_ms=1e3 * t, mean_rgb=float(np.asarray(img.rgb).mean())))
            print(rows[-1], flush=True)
    return rows


def depth_scene(width, height):
    """Two facing mirrors with a sphere between them: one reflected ray per level."""
    import jaxrt as jr

    S = jr.sdf
    surface = S.Union(
        S.Translate(S.Sphere(radius=0.6, material=0), offset=(0.0, 0.6, 0.0)),
        S.Plane(normal=(0.0, 1.0, 0.0), offset=0.0, material=1),
        S.Plane(normal=(0.0, 0.0, 1.0), offset=-2.0, material=2),
        S.Plane(normal=(0.0, 0.0, -1.0), offset=-2.0, material=2))
    scene = jr.Scene(surface=surface,
                     materials=[jr.bsdf.Lambert(albedo=(0.8, 0.3, 0.2)),
                                jr.bsdf.Lambert(albedo=(0.6, 0.6, 0.6)),
                                jr.bsdf.Mirror()],
                     lights=[jr.PointLight(position=(1.0, 3.0, 0.5), intensity=(20.0, 20.0, 20.0))],
                     background=(0.1, 0.1, 0.12))
    camera = jr.PerspectiveCamera(eye=(0.3, 1.5, 1.8), target=(0.0, 0.5, -1.0), up=(0.0, 1.0, 0.0),
                                  fov=60.0, width=width, height=height)
    return scene, camera


def _depth(cfg, section):
    rows = []
    scene, camera = depth_scene(*cfg["size"])
    for d in cfg["max_depth"]:
        tl, tc, t, _ = measure(scene, camera, _settings(section, max_depth=d), section["repeats"])
        rows.append(dict(max_depth=d, compile_s=tl + tc, render_ms=1e3 * t))
    return rows


def _showcase(cfg, section):
    import jax

    import jaxrt as jr

    path = ROOT / "jaxrt/data/showcase.toml"
    scene, camera, base = jr.config.load(path, width=cfg["size"][0], height=cfg["size"][1])
    rows = []
    from jaxrt.kernels import resolve_backend

    backends = [b for b in cfg["backends"] if b != "pallas" or jax.default_backend() == "gpu"]
    for backend in backends:
        tl, tc, t, _ = measure(scene, camera, base.replace(backend=backend), section["repeats"])
        rows.append(dict(scene="showcase", backend=f"{backend} ({resolve_backend(backend)})", width=cfg["size"][0],
                         height=cfg["size"][1], trace_lower_s=tl, xla_compile_s=tc, render_ms=1e3 * t))
    return rows


def _devices(cfg, section):
    import jax

    import jaxrt as jr

    rows = []
    n = len(jax.local_devices())
    counts = [c for c in cfg["counts"] if c <= n]
    for w, h in cfg["sizes"]:
        scene, camera, base = jr.config.load(ROOT / cfg["scene"], width=w, height=h)
        st = base.replace(**cfg.get("settings", {}))
        one = None
        for c in counts:
            _, _, t, img = measure(scene, camera, st.replace(devices=c), section["repeats"])
            rgb = np.asarray(img.rgb)
            if one is None:
                one, rgb1 = t, rgb
            rows.append(dict(width=w, height=h, devices=c, render_ms=1e3 * t, speedup=one / t,
                             max_diff_vs_1=float(np.abs(rgb - rgb1).max())))
            print(rows[-1], flush=True)
    return rows


if __name__ == "__main__":
    main()
