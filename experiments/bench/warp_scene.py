"""Benchmark: NVIDIA Warp's ray-marching example scene, jaxrt against Warp (CPU) and CUDA.

Renders `configs/scenes/warp_raymarch.toml` with jaxrt in the variants of the config
(`configs/experiments/warp_bench.toml`), and in the same run, where available:

- on a CPU, NVIDIA Warp's example (warp-lang) as shipped (128 fixed march steps) and
  with early termination (timed in the same interleaved rounds as jaxrt) (a ray stops when d < 1e-3·t or t > 20; a shadow ray when its
  factor < 1e-3). Both sample pixel centres (the example samples corners), so that
  the images line up with jaxrt's; nothing else differs from the example.
- on a GPU, the hand-written CUDA kernel `warp_scene_cuda.py` (fixed and early), run
  from `--cuda-reference` (default ../shared/bench/warp_scene_cuda.py); it samples
  pixel corners, so its images are compared with a reference rendered at corners.

Every image is compared with a converged jaxrt reference (float64, hit epsilon 1e-7,
large budgets, two Newton steps) in Warp's display space clamp(x^2.2): RMSE and the
maximum over pixels, and the fraction of pixels off by more than 0.05 (a visible error).
Prints Mrays/s (primary rays = pixels per second) and the ratio of every row to the
fastest Warp/CUDA row with early termination measured in the same run; writes
`out/warp_bench/results.json` (or --out). Times: median of `repeats` renders after
compilation (compiled once with the scene's arrays as arguments, so changing them would
not recompile), compile time reported apart; on a GPU each timing is the mean of
`calls_per_timing` renders launched back to back.

    python experiments/bench/warp_scene.py [--config ...] [--width W --height H]
"""

import argparse
import json
import os
import runpy
import sys
import time
import tomllib
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", default=str(ROOT / "configs/experiments/warp_bench.toml"))
    ap.add_argument("--width", type=int)
    ap.add_argument("--height", type=int)
    ap.add_argument("--repeats", type=int)
    ap.add_argument("--variants", help="comma-separated subset of the config's variants")
    ap.add_argument("--cuda-reference", default=str(ROOT.parent / "shared/bench/warp_scene_cuda.py"))
    ap.add_argument("--no-warp", action="store_true", help="skip Warp even if installed")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)

    cfg = tomllib.loads(Path(args.config).read_text())
    cpu_devices = cfg["cpu"].get("devices", 1)
    if cpu_devices > 1 and "jax" not in sys.modules:
        # one XLA CPU device per core, so that RenderSettings(devices=...) can shard the
        # image over the cores (must be set before jax is imported)
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") +
                                   f" --xla_force_host_platform_device_count={cpu_devices}")
    import jax

    jax.config.update("jax_enable_x64", True)  # for the float64 reference only
    import jax.numpy as jnp

    import jaxrt as jr

    gpu = jax.default_backend() == "gpu"
    section = cfg["gpu" if gpu else "cpu"]
    width = args.width or section["width"]
    height = args.height or section["height"]
    repeats = args.repeats or section["repeats"]
    scene, camera, base = jr.config.load(ROOT / cfg["scene"], width=width, height=height)
    npix = width * height
    out_dir = Path(args.out or ROOT / "out/warp_bench")
    out_dir.mkdir(parents=True, exist_ok=True)
    print(f"device: {jax.devices()[0].device_kind} ({jax.default_backend()}), "
          f"{os.cpu_count()} CPU cores, jax {jax.__version__}; {width}x{height}", flush=True)

    # converged references: at pixel centres (jaxrt, Warp CPU) and corners (CUDA)
    ref_settings = base.replace(**cfg["reference"])
    t0 = time.perf_counter()
    ref = {"centre": np.asarray(_render_at(scene, camera, ref_settings, 0.5, 0.5)["rgb"])}
    if gpu:
        ref["corner"] = np.asarray(_render_at(scene, camera, ref_settings, 0.0, 1.0)["rgb"])
    ref_depth = np.asarray(_render_at(scene, camera, ref_settings.replace(shadows="none"), 0.5, 0.5)["depth"])
    print(f"reference: {time.perf_counter() - t0:.1f} s ({ref_settings.dtype})", flush=True)

    jax.config.update("jax_enable_x64", False)  # the timed renders: float32 programs
    import equinox as eqx

    from jaxrt.render import _cast, _render

    # the scene as float32 arrays once, so that a timed call does no casting on the host
    dyn, static = eqx.partition(_cast((scene, camera), jnp.float32), eqx.is_array)
    dyn = jax.device_put(dyn)
    batch = section.get("calls_per_timing", 1)

    names = args.variants.split(",") if args.variants else list(section["variants"])
    compiled = {}
    for name in names:
        overrides = dict(cfg["variants"][name])
        knobs = overrides.pop("kernel", {})
        xla = overrides.pop("xla", None)  # XLA compiler options of this variant
        settings = base.replace(**overrides, kernel=kernel_options(knobs))
        jax.clear_caches()
        t0 = time.perf_counter()
        f = jax.jit(lambda d, settings=settings: _render.__wrapped__(*eqx.combine(d, static), settings))
        f = f.lower(dyn).compile(compiler_options=xla)
        compile_s = time.perf_counter() - t0
        img = f(dyn)
        img.rgb.block_until_ready()
        if xla:
            knobs = dict(knobs, xla=xla)
        compiled[name] = (f, overrides, knobs, compile_s, img)
        print(f"compiled {name} in {compile_s:.1f} s", flush=True)
    # interleaved timing: every variant once per round, so that a machine whose load
    # changes (other jobs) affects all variants alike; the median over rounds. On a GPU a
    # round launches `calls_per_timing` renders back to back and waits for the last
    # (time per render, without the host's dispatch latency of a single call).
    times = {name: [] for name in names}
    warp = None if gpu or args.no_warp else _warp_setup(width, height)
    if warp:  # Warp with early termination is timed in the same rounds
        times["warp-cpu-early"] = []
    for _ in range(repeats):
        for name in names:
            f = compiled[name][0]
            t0 = time.perf_counter()
            for _ in range(batch):
                out = f(dyn)
            out.rgb.block_until_ready()
            times[name].append((time.perf_counter() - t0) / batch)
        if warp:
            t0 = time.perf_counter()
            warp["warp-cpu-early"]()
            times["warp-cpu-early"].append(time.perf_counter() - t0)
    rows = []
    first_image = {}
    for name in names:
        f, overrides, knobs, compile_s, img = compiled[name]
        med = float(np.median(times[name]))
        rgb = np.asarray(img.rgb, np.float64)
        row = dict(name=name, kind="jaxrt", seconds=med, compile_seconds=compile_s,
                   mrays=npix / med / 1e6, settings=overrides, kernel=knobs,
                   **_errors(rgb, ref["centre"]),
                   depth_error=None if img.depth is None or img.coverage is None else
                   _depth_error(np.asarray(img.depth), ref_depth, np.asarray(img.coverage) > 0.5))
        # the same settings through another backend: the same image?
        key = repr(sorted((k, v) for k, v in overrides.items() if k not in ("backend", "batch_size")))
        if key in first_image:
            other, orgb = first_image[key]
            diff = np.abs(rgb - orgb).max(axis=-1)
            row["vs_" + other] = dict(max=float(diff.max()), frac_over_1e_3=float(np.mean(diff > 1e-3)))
        else:
            first_image[key] = (name, rgb)
        rows.append(row)
        _print_row(row)

    if warp:
        rows += _warp_rows(warp, times["warp-cpu-early"], width, height, ref["centre"])
    if gpu and Path(args.cuda_reference).exists():
        rows += _cuda(args.cuda_reference, width, height, ref["corner"])

    early = [r for r in rows if r["kind"] in ("warp", "cuda") and "early" in r["name"]]
    if early:
        best = min(early, key=lambda r: r["seconds"])
        for r in rows:
            r["speed_vs_" + best["name"]] = best["seconds"] / r["seconds"]
        print(f"\nratios against {best['name']} (same run):")
        for r in rows:
            print(f"  {r['name']:<24} {r['speed_vs_' + best['name']]:7.2f}x   "
                  f"rmse {r['rmse']:.4f}  max {r['max']:.3f}  >0.05: {100 * r['bad']:.2f}%")
    result = dict(device=jax.devices()[0].device_kind, backend=jax.default_backend(),
                  cpu_cores=os.cpu_count(), jax=jax.__version__, width=width, height=height,
                  repeats=repeats, reference=cfg["reference"], rows=rows)
    (out_dir / "results.json").write_text(json.dumps(result, indent=1, default=str))
    print(f"wrote {out_dir / 'results.json'}")
    return result


def kernel_options(knobs):
    """A variant's [kernel] table (num_warps, unroll, fast_math, fma, uniforms, march_form) as
    `jaxrt.KernelOptions` (part of RenderSettings, so of the jit cache key); the
    library's choices where the variant says nothing."""
    import jaxrt as jr

    keys = {"num_warps": ["pallas_num_warps"], "unroll": ["unroll", "pallas_unroll"],
            "fast_math": ["pallas_fast_math"], "fma": ["pallas_fma"],
            "uniforms": ["pallas_uniforms"], "march_form": ["march_form"]}
    return jr.KernelOptions(**{key: value for name, value in knobs.items() for key in keys[name]})


def _render_at(scene, camera, settings, dx, dy):
    """The per-ray program at pixel positions (col + dx, row + dy), through the
    reference (vmap) path; for the references at centres and at Warp's corners."""
    import jax
    import jax.numpy as jnp

    from jaxrt.integrator import trace_radiance
    from jaxrt.render import _cast, _dtype

    dtype = _dtype(settings)
    scene, camera = _cast((scene, camera), dtype)
    h, w = camera.height, camera.width

    @jax.jit
    def run(scene, camera):
        rows, cols = jnp.meshgrid(jnp.arange(h), jnp.arange(w), indexing="ij")
        px = cols.ravel().astype(dtype) + dx
        py = rows.ravel().astype(dtype) + dy

        def one(s):
            o, d, cone = camera.generate_ray(s[0], s[1])
            return trace_radiance(scene, o, d, cone, settings)

        s = jnp.stack([px, py], -1)
        if jax.default_backend() == "gpu":  # one loop over the image: GPU loops cost per iteration
            out = jax.vmap(one)(s)
        else:
            out = jax.lax.map(one, s, batch_size=settings.rays_per_tile(h * w))
        return {k: v.reshape((h, w) + v.shape[1:]) for k, v in out.items()}

    return run(scene, camera)


def display(rgb):
    """Warp's display transform clamp(x^2.2, 0, 1) (see the scene file)."""
    return np.clip(np.maximum(rgb, 0.0) ** 2.2, 0.0, 1.0)


def _errors(rgb, ref):
    a, b = display(rgb), display(ref)
    e = np.abs(a - b).max(axis=-1)
    return dict(rmse=float(np.sqrt(np.mean((a - b) ** 2))), max=float(e.max()),
                bad=float(np.mean(e > 0.05)))


def _depth_error(depth, ref_depth, hit):
    if not hit.any():
        return None
    rel = np.abs(depth - ref_depth)[hit] / np.maximum(ref_depth[hit], 1e-9)
    return dict(median_rel=float(np.median(rel)), p99_rel=float(np.percentile(rel, 99)))


def _print_row(r):
    extra = "  ".join(f"{k}: max {v['max']:.1e}, {100 * v['frac_over_1e_3']:.3f}% > 1e-3"
                      for k, v in r.items() if k.startswith("vs_"))
    comp = f"compile {r['compile_seconds']:.1f} s  " if r.get("compile_seconds") else ""
    print(f"{r['name']:<24} {1e3 * r['seconds']:9.3f} ms  {r['mrays']:9.2f} Mrays/s  {comp}"
          f"rmse {r['rmse']:.4f}  max {r['max']:.3f}  >0.05: {100 * r['bad']:.2f}%  {extra}",
          flush=True)


# ------------------------------------------------------------------------- Warp (CPU)


def _warp_setup(width, height):
    """Warp's kernel compiled for the CPU; returns {name: launch-and-wait} (or None)."""
    try:
        import warp as wp
    except ImportError:
        print("warp-lang is not installed: no Warp rows (pip install warp-lang)")
        return None
    wp.config.quiet = True
    wp.init()
    kernel = _warp_kernel(wp)
    pixels = wp.zeros(width * height, dtype=wp.vec3, device="cpu")
    runs = {}
    for name, early in (("warp-cpu-shipped", 0), ("warp-cpu-early", 1)):
        inputs = [wp.vec3(-1.25, 1.0, 2.0), wp.quat_rpy(-0.5, -0.5, 0.0), width, height, early, pixels]

        def run(inputs=inputs):
            wp.launch(kernel, dim=width * height, inputs=inputs, device="cpu")
            wp.synchronize()
            return pixels.numpy().reshape(height, width, 3)[::-1].astype(np.float64)  # row 0 top

        run()  # compile
        runs[name] = run
    return runs


def _warp_rows(warp, early_times, width, height, ref):
    rows = []
    for name, run in warp.items():
        if name == "warp-cpu-early":
            times = early_times
        else:  # as shipped: slow, timed apart (3 launches)
            times = []
            for _ in range(3):
                t0 = time.perf_counter()
                run()
                times.append(time.perf_counter() - t0)
        img = run()
        med = float(np.median(times))
        # Warp's pixels are display values already: compare them with the reference's
        e = np.abs(img - display(ref)).max(axis=-1)
        row = dict(name=name, kind="warp", seconds=med, mrays=width * height / med / 1e6,
                   rmse=float(np.sqrt(np.mean((img - display(ref)) ** 2))), max=float(e.max()),
                   bad=float(np.mean(e > 0.05)))
        rows.append(row)
        _print_row(row)
    return rows


def _warp_kernel(wp):
    """Warp's example_raymarch.py `draw`, with pixel centres and an `early` switch."""

    @wp.func
    def sdf(p: wp.vec3):
        ds = wp.length(p - wp.vec3(0.0, 0.75, 0.0)) - 0.75
        qx = wp.abs(p[0]) - 1.0
        qy = wp.abs(p[1]) - 0.5
        qz = wp.abs(p[2]) - 0.5
        e = wp.vec3(wp.max(qx, 0.0), wp.max(qy, 0.0), wp.max(qz, 0.0))
        db = wp.length(e) + wp.min(wp.max(qx, wp.max(qy, qz)), 0.0)
        d = wp.max(-ds, db)
        return wp.min(d, p[1] + 1.0)

    @wp.func
    def normal(p: wp.vec3):
        eps = 1.0e-5
        dx = sdf(p + wp.vec3(eps, 0.0, 0.0)) - sdf(p - wp.vec3(eps, 0.0, 0.0))
        dy = sdf(p + wp.vec3(0.0, eps, 0.0)) - sdf(p - wp.vec3(0.0, eps, 0.0))
        dz = sdf(p + wp.vec3(0.0, 0.0, eps)) - sdf(p - wp.vec3(0.0, 0.0, eps))
        return wp.normalize(wp.vec3(dx, dy, dz))

    @wp.func
    def shadow(ro: wp.vec3, rd: wp.vec3, early: int):
        t = float(0.0)
        s = float(1.0)
        for _ in range(64):
            d = sdf(ro + t * rd)
            t = t + wp.clamp(d, 0.0001, 2.0)
            h = wp.clamp(4.0 * d / t, 0.0, 1.0)
            s = wp.min(s, h * h * (3.0 - 2.0 * h))
            if t > 8.0:
                return 1.0
            if early != 0 and s < 1.0e-3:
                return s
        return s

    @wp.kernel
    def draw(cam_pos: wp.vec3, cam_rot: wp.quat, width: int, height: int, early: int,
             pixels: wp.array(dtype=wp.vec3)):
        tid = wp.tid()
        x = tid % width
        y = tid // width
        sx = (2.0 * (float(x) + 0.5) - float(width)) / float(height)
        sy = (2.0 * (float(y) + 0.5) - float(height)) / float(height)
        ro = cam_pos
        rd = wp.quat_rotate(cam_rot, wp.normalize(wp.vec3(sx, sy, -2.0)))
        t = float(0.0)
        d = sdf(ro)
        for _ in range(128):
            if early != 0:
                if d < 1.0e-3 * t or t > 20.0:
                    break
                t = t + d
                d = sdf(ro + rd * t)
            else:
                d = sdf(ro + rd * t)
                t = t + d
        if d < 0.01:
            p = ro + rd * t
            n = normal(p)
            l = wp.normalize(wp.vec3(0.6, 0.4, 0.5))
            h = wp.normalize(l - rd)
            diffuse = wp.dot(n, l)
            specular = wp.clamp(wp.dot(n, h), 0.0, 1.0) ** 80.0
            fresnel = 0.04 + 0.96 * wp.clamp(1.0 - wp.dot(h, l), 0.0, 1.0) ** 5.0
            result = (wp.vec3(0.85, 0.9, 0.95) * (diffuse * (1.0 - fresnel) + specular * fresnel * 10.0)
                      * shadow(p, l, early) * 2.0)
            pixels[tid] = wp.vec3(wp.clamp(result[0] ** 2.2, 0.0, 1.0),
                                  wp.clamp(result[1] ** 2.2, 0.0, 1.0),
                                  wp.clamp(result[2] ** 2.2, 0.0, 1.0))
        else:
            pixels[tid] = wp.vec3(0.4, 0.45, 0.5) * 1.5

    return draw


# ------------------------------------------------------------------------- CUDA (GPU)


def _cuda(path, width, height, ref_corner):
    rows = []
    for mode in ("fixed", "early"):
        argv = sys.argv
        sys.argv = [path, str(width), str(height)] + (["early"] if mode == "early" else [])
        try:
            g = runpy.run_path(path, run_name="__main__")
        finally:
            sys.argv = argv
        ms = float(g["ms"])
        img = g["out"].get().reshape(height, width, 3)[::-1].astype(np.float64)
        e = np.abs(img - display(ref_corner)).max(axis=-1)
        row = dict(name=f"cuda-{mode}", kind="cuda", seconds=ms / 1e3, mrays=width * height / ms / 1e3,
                   rmse=float(np.sqrt(np.mean((img - display(ref_corner)) ** 2))),
                   max=float(e.max()), bad=float(np.mean(e > 0.05)))
        rows.append(row)
        _print_row(row)
    return rows


if __name__ == "__main__":
    main()
