"""Benchmark: compile time per scene and backend, for `render` and for `value_and_grad`
of an L2 image loss, and the time of one compiled call.

A scene's structure is static (every change of it compiles), its parameter values are
data. This script measures how compile time grows with the *number* of things of one
kind in a scene: unions of N spheres + a plane (N = 8, 64, 256), 1 vs 16 materials of
one type (Lambert; GGX Cook–Torrance), 1 vs 8 point lights; and with the showcase
(`jaxrt/data/showcase.toml`) and the glass scene (`configs/scenes/glass_spheres.toml`,
max_depth from the config).

    python experiments/bench/compile.py [--config configs/experiments/compile.toml]
        [--scenes showcase,spheres8,...] [--backends jax,fused] [--modes render,grad]
        [--xla default,fast-compile] [--width W --height H] [--repeats N]
        [--glass-depth D] [--cache] [--stacked] [--eqns-only] [--out out/compile]

For each (scene, backend, mode, xla): `lower_s` (trace + lower to StableHLO),
`compile_s` (XLA, with the compiler options of the `KernelOptions.xla` preset `xla`,
`jaxrt.xla`; `compile_cpu_s`: the process's CPU seconds meanwhile, XLA's threads
included, less sensitive than wall seconds to other jobs on a shared machine), the sum
of lowering and compiling `total_s`, `run_ms` (median of `repeats` calls of the compiled
program), `eqns` (equations of the traced program, inner jaxprs included: the program
size that tests/test_union_stack.py counts); against the outputs of the first preset of
the same scene, backend and mode (an image; for "grad" the loss and every gradient
leaf): `max_diff` (the largest absolute difference), `rel_diff` (‖outputs − first‖ /
‖first‖, 2-norms over all of them) and `diff_pixels` (render: pixels whose rgb differs
by more than 1e-3); and `load`, the 1-minute load average when the row was measured.
The presets of one (scene, backend, mode) run back to back. Caches are cleared before every
measurement, and JAX's persistent compilation cache is off unless `--cache` is given
(then `jaxrt.cache` is used where it exists), so compile times are cold ones. On a
shared machine the times are noisy: compare rows of one run. Writes results.json and
compile.md under the output folder and prints the table row by row.
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
    ap.add_argument("--config", default=str(ROOT / "configs/experiments/compile.toml"))
    ap.add_argument("--scenes", help="comma-separated subset of the config's scenes")
    ap.add_argument("--backends", help="comma-separated: jax, fused, pallas, auto")
    ap.add_argument("--modes", help="comma-separated: render, grad")
    ap.add_argument("--xla", help="comma-separated KernelOptions.xla presets: default, fast-compile")
    ap.add_argument("--width", type=int)
    ap.add_argument("--height", type=int)
    ap.add_argument("--repeats", type=int)
    ap.add_argument("--glass-depth", type=int)
    ap.add_argument("--cache", action="store_true", help="use the persistent compilation cache")
    ap.add_argument("--eqns-only", action="store_true",
                    help="trace only: program sizes, no compilation (fast, deterministic)")
    ap.add_argument("--stacked", action="store_true",
                    help="every scene's unions stacked ahead (jaxrt.sdf.stacked), as a fit of many primitives takes them")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    cfg = tomllib.loads(Path(args.config).read_text())
    cfg["stacked"] = args.stacked or cfg.get("stacked", False)
    for key in ("width", "height", "repeats"):
        if getattr(args, key) is not None:
            cfg[key] = getattr(args, key)
    if args.glass_depth is not None:
        cfg["glass"]["max_depth"] = args.glass_depth
    scenes = args.scenes.split(",") if args.scenes else cfg["scenes"]
    unknown = sorted(set(scenes) - set(SCENES))
    if unknown:
        ap.error(f"--scenes {unknown}: expected some of {sorted(SCENES)}")
    backends = args.backends.split(",") if args.backends else cfg["backends"]
    modes = args.modes.split(",") if args.modes else cfg["modes"]
    presets = args.xla.split(",") if args.xla else cfg.get("xla", ["default"])
    from jaxrt.xla import XLA_PRESETS

    unknown = sorted(set(presets) - set(XLA_PRESETS))
    if unknown:
        ap.error(f"--xla {unknown}: expected some of {sorted(XLA_PRESETS)}")

    import jax

    if args.cache:
        try:
            from jaxrt import cache

            cache.enable()
        except (ImportError, AttributeError):
            pass
    else:
        jax.config.update("jax_enable_compilation_cache", False)

    out_dir = Path(args.out or ROOT / "out/compile")
    out_dir.mkdir(parents=True, exist_ok=True)
    info = dict(device=jax.devices()[0].device_kind, platform=jax.default_backend(),
                cpu_cores=os.cpu_count(), jax=jax.__version__, width=cfg["width"],
                height=cfg["height"], glass_depth=cfg["glass"]["max_depth"],
                cache=bool(args.cache), stacked=cfg["stacked"])
    print(info, flush=True)
    rows = []
    for name in scenes:
        for backend in backends:
            for mode in modes:
                first = None
                for preset in presets:
                    row, out = measure(cfg, name, backend, mode, compile_=not args.eqns_only,
                                       xla=preset)
                    first = out if first is None else first
                    row.update(_differences(out, first, mode))
                    rows.append(row)
                    print(_format(row), flush=True)
                    (out_dir / "results.json").write_text(json.dumps(dict(info=info, rows=rows), indent=1))
    md = [f"# Compile time ({info['device']}, {info['platform']}, {info['cpu_cores']} cores, "
          f"jax {info['jax']}, {cfg['width']}×{cfg['height']})", "", _table(rows), ""]
    (out_dir / "compile.md").write_text("\n".join(md))
    print(f"\n{_table(rows)}\nwrote {out_dir / 'results.json'} and compile.md")
    return rows


def _format(row):
    return (f"{row['scene']:>11} {row['backend']:>6} {row['mode']:>6} {row['xla']:>12}"
            f"  lower {row['lower_s']:7.2f} s  compile {row['compile_s']:7.2f} s"
            f" (cpu {row['compile_cpu_s']:7.2f} s)"
            f"  total {row['total_s']:7.2f} s  run {row['run_ms']:9.1f} ms  eqns {row['eqns']}"
            f"  max_diff {row['max_diff']:.3g} (rel {row['rel_diff']:.3g})"
            f"  diff_pixels {row['diff_pixels']}  load {row['load']}")


def _differences(out, first, mode):
    """max |out − first| over every output leaf, `rel_diff` = ‖out − first‖ / ‖first‖
    over all leaves together (2-norms: gradient leaves differ in scale by decades), and
    (render) the pixels whose rgb differs by more than 1e-3; NaN without outputs
    (--eqns-only)."""
    if out is None or first is None:
        return dict(max_diff=float("nan"), rel_diff=float("nan"), diff_pixels=-1)
    import jax

    a = np.concatenate([np.ravel(np.asarray(x, float)) for x in jax.tree_util.tree_leaves(out)])
    b = np.concatenate([np.ravel(np.asarray(x, float)) for x in jax.tree_util.tree_leaves(first)])
    pixels = -1
    if mode == "render":
        pixels = int((np.abs(np.asarray(out) - np.asarray(first)).max(axis=-1) > 1e-3).sum())
    return dict(max_diff=float(np.max(np.abs(a - b), initial=0.0)),
                rel_diff=float(np.linalg.norm(a - b) / max(np.linalg.norm(b), 1e-30)),
                diff_pixels=pixels)


def _table(rows):
    keys = ["scene", "backend", "mode", "xla", "lower_s", "compile_s", "compile_cpu_s", "total_s",
            "run_ms",
            "max_diff", "rel_diff", "diff_pixels", "load", "eqns"]
    lines = ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    for r in rows:
        lines.append("| " + " | ".join(f"{r[k]:.4g}" if isinstance(r[k], float) else str(r[k])
                                       for k in keys) + " |")
    return "\n".join(lines)


def n_equations(jaxpr):
    """Equations of a jaxpr, those of inner jaxprs (loops, calls) included."""
    from jax.extend import core

    count = 0
    for eqn in jaxpr.eqns:
        count += 1
        for v in eqn.params.values():
            for j in v if isinstance(v, (tuple, list)) else (v,):
                if isinstance(j, core.ClosedJaxpr):
                    count += n_equations(j.jaxpr)
                elif isinstance(j, core.Jaxpr):
                    count += n_equations(j)
    return count


def program(scene, camera, settings, mode):
    """(f, dyn): a function of the scene's and camera's float leaves `dyn` that renders
    (mode "render": the rgb image) or returns the value and gradient of the L2 loss
    against a grey image (mode "grad")."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    import jaxrt as jr
    from jaxrt.render import _cast, _dtype

    params = _cast((scene, camera), _dtype(settings))
    dyn, static = eqx.partition(params, eqx.is_inexact_array)

    def image(d):
        s, c = eqx.combine(d, static)
        return jr.render(s, c, settings).rgb

    if mode == "render":
        return image, dyn

    def loss(d):
        return jnp.mean((image(d) - 0.5) ** 2)

    return jax.value_and_grad(loss), dyn


def measure(cfg, name, backend, mode, compile_=True, xla="default"):
    """(row, outputs of the compiled program) for one scene, backend, mode and
    `KernelOptions.xla` preset; outputs None with `compile_=False`."""
    import jax

    from jaxrt import xla as jaxrt_xla

    scene, camera, settings = SCENES[name](cfg)
    if cfg.get("stacked"):
        import equinox as eqx

        from jaxrt.sdf import stacked

        scene = eqx.tree_at(lambda s: s.surface, scene, stacked(scene.surface))
    settings = settings.replace(**{**cfg.get("settings", {}), "backend": backend})
    settings = settings.replace(kernel=settings.kernel.replace(xla=xla))
    f, dyn = program(scene, camera, settings, mode)
    jax.clear_caches()
    eqns = n_equations(jax.make_jaxpr(f)(dyn).jaxpr)
    jax.clear_caches()
    if not compile_:
        nan = float("nan")
        return dict(scene=name, backend=backend, mode=mode, xla=xla, lower_s=nan, compile_s=nan,
                    compile_cpu_s=nan, total_s=nan, run_ms=nan, eqns=eqns, load=_load()), None
    t0 = time.perf_counter()
    # the options of the renders traced in f (their settings.kernel.xla), as a fit step gets them
    lowered, options = jaxrt_xla.lower_collected(jax.jit(f), dyn)
    t1, c1 = time.perf_counter(), time.process_time()
    compiled = lowered.compile(compiler_options=options or None)
    t2, c2 = time.perf_counter(), time.process_time()
    out = jax.block_until_ready(compiled(dyn))
    times = []
    for _ in range(cfg["repeats"]):
        t = time.perf_counter()
        jax.block_until_ready(compiled(dyn))
        times.append(time.perf_counter() - t)
    return dict(scene=name, backend=backend, mode=mode, xla=xla, lower_s=t1 - t0,
                compile_s=t2 - t1, compile_cpu_s=c2 - c1, total_s=t2 - t0, run_ms=1e3 * float(np.median(times)),
                eqns=eqns, load=_load()), out


def _load():
    """The 1-minute load average (the machine may be shared), or NaN."""
    try:
        return float(os.getloadavg()[0])
    except OSError:
        return float("nan")


# --------------------------------------------------------------------------- scenes


def _camera(r, width, height):
    import jaxrt as jr

    return jr.PerspectiveCamera(eye=(0.0, 0.8 * r + 2.0, 1.4 * r + 3.0), target=(0.0, 0.0, 0.0),
                                up=(0.0, 1.0, 0.0), fov=45.0, width=width, height=height)


def _grid(n, material):
    """n unit-diameter spheres on a square grid over the plane y = 0; sphere i has
    material material(i)."""
    import jaxrt as jr

    S = jr.sdf
    k = int(np.ceil(np.sqrt(n)))
    out = []
    for i in range(n):
        x, z = (i % k - (k - 1) / 2) * 1.2, (i // k - (k - 1) / 2) * 1.2
        out.append(S.Translate(S.Sphere(radius=0.5, material=material(i)), offset=(x, 0.5, z)))
    return out, 1.2 * k


def spheres_scene(n, width, height):
    """A union of n spheres (one material) and a plane (another), one point light."""
    import jaxrt as jr

    S = jr.sdf
    spheres, r = _grid(n, lambda i: 0)
    scene = jr.Scene(surface=S.Union(*spheres, S.Plane(normal=(0.0, 1.0, 0.0), offset=0.0, material=1)),
                     materials=[jr.bsdf.Lambert(albedo=(0.8, 0.3, 0.2)),
                                jr.bsdf.Lambert(albedo=(0.7, 0.7, 0.7))],
                     lights=[jr.PointLight(position=(3.0, 6.0, 4.0), intensity=(60.0, 60.0, 60.0))],
                     background=(0.05, 0.05, 0.08))
    return scene, _camera(r, width, height), jr.RenderSettings()


def materials_scene(kind, k, width, height):
    """16 spheres + a plane and k + 1 materials of one type (`kind`: "lambert" or "ggx",
    a GGX Cook–Torrance with a Lambertian base): sphere i has material i mod k, the
    plane material k."""
    import jaxrt as jr

    S = jr.sdf
    rng = np.random.default_rng(1)

    def material(j):
        c = tuple(float(x) for x in rng.uniform(0.1, 0.9, 3))
        if kind == "lambert":
            return jr.bsdf.Lambert(albedo=c)
        return jr.bsdf.CookTorrance(jr.bsdf.GGX(float(rng.uniform(0.1, 0.5))),
                                    jr.bsdf.SchlickFresnel(float(rng.uniform(0.02, 0.1))),
                                    diffuse=c)

    spheres, r = _grid(16, lambda i: i % k)
    scene = jr.Scene(surface=S.Union(*spheres, S.Plane(normal=(0.0, 1.0, 0.0), offset=0.0, material=k)),
                     materials=[material(j) for j in range(k + 1)],
                     lights=[jr.PointLight(position=(3.0, 6.0, 4.0), intensity=(60.0, 60.0, 60.0))],
                     background=(0.05, 0.05, 0.08))
    return scene, _camera(r, width, height), jr.RenderSettings()


def lights_scene(n_lights, width, height):
    """8 spheres + a plane lit by n_lights point lights on a circle."""
    import jaxrt as jr

    S = jr.sdf
    spheres, r = _grid(8, lambda i: 0)
    lights = []
    for j in range(n_lights):
        a = 2 * np.pi * j / n_lights
        lights.append(jr.PointLight(position=(4.0 * np.cos(a), 6.0, 4.0 * np.sin(a)),
                                    intensity=(60.0 / n_lights,) * 3))
    scene = jr.Scene(surface=S.Union(*spheres, S.Plane(normal=(0.0, 1.0, 0.0), offset=0.0, material=1)),
                     materials=[jr.bsdf.Lambert(albedo=(0.8, 0.3, 0.2)),
                                jr.bsdf.Lambert(albedo=(0.7, 0.7, 0.7))],
                     lights=lights, background=(0.05, 0.05, 0.08))
    return scene, _camera(r, width, height), jr.RenderSettings()


def _file(cfg, key, **changes):
    import jaxrt as jr

    scene, camera, settings = jr.config.load(ROOT / cfg[key]["file"], width=cfg["width"],
                                             height=cfg["height"])
    return scene, camera, settings.replace(**changes)


SCENES = {
    "showcase": lambda cfg: _file(cfg, "showcase"),
    "glass": lambda cfg: _file(cfg, "glass", max_depth=cfg["glass"]["max_depth"]),
    **{f"spheres{n}": (lambda cfg, n=n: spheres_scene(n, cfg["width"], cfg["height"]))
       for n in (8, 64, 256)},
    **{f"{kind}{k}": (lambda cfg, kind=kind, k=k: materials_scene(kind, k, cfg["width"], cfg["height"]))
       for kind in ("lambert", "ggx") for k in (1, 16)},
    **{f"lights{n}": (lambda cfg, n=n: lights_scene(n, cfg["width"], cfg["height"])) for n in (1, 8)},
}


if __name__ == "__main__":
    main()
