"""Glass, water, mirror and metal over a height-field terrain, at Whitted depths 1–8.

Notes, "Ray tracing" (trace = direct illumination + c_refl · trace(reflected) +
c_trans · trace(refracted)) and "Ray marching height-fields". The scene: a terrain
y = h(x, z) (a `GridHeight` of summed random sine waves, marched by
`jaxrt.heightfield`), and on it a glass sphere (`Dielectric`, a number or a dispersive
preset such as "bk7"), a block of water (`Dielectric(1.333)` with Beer–Lambert
absorption), a mirror sphere (`Mirror`), a gold sphere and a copper torus
(`Conductor`, complex-index Fresnel), lit by the sun (hard shadows; glass and water
cast opaque shadows, as in Whitted 1980) under a sky.

For each way of compiling the ray tree in `recursions` (`RenderSettings.recursion`:
"unrolled" levels, or one "scan" over the tree's slots) and each of its depths, the
scene is compiled (`jaxrt.render.compile_render`) and rendered; the
script prints the compile time, the render time, the ray slots per camera ray
(1 + 2 + … + 2^depth: the glass and water split every ray into a reflected and a
refracted one), and how far the image still is from the deepest one (mean and max |Δ|
of linear RGB), so that the price of each level can be read against what it adds; the
recursions must give the same images. Writes `glass_scene_d{depth}.png` (sRGB previews), `glass_scene.exr` (the deepest,
linear, with AOVs), `glass_scene_depths.png` (all depths side by side), `results.json`
and the resolved `config.json` under the output folder (default out/glass_scene/).

    python experiments/optics/glass_scene.py [--config ...] [--out DIR] [--quick]
"""

import argparse
import json
import time
import tomllib
from pathlib import Path

import jax
import numpy as np

import jaxrt as jr
from jaxrt import integrator, spectral
from jaxrt.heightfield import GridHeight, HeightField
from jaxrt.render import compile_render

ROOT = Path(__file__).resolve().parents[2]
NAME = "glass_scene"


def load_config(path, quick=False):
    """The experiment's TOML config; with `quick`, its [quick] table overrides."""
    cfg = tomllib.loads(Path(path).read_text())
    overrides = cfg.pop("quick", {})
    if quick:
        cfg.update(overrides)
    return cfg


def terrain_heights(cfg):
    """[nz, nx] heights of the terrain: `terrain_waves` sine waves of random direction
    and phase, wavelengths from `terrain_wavelengths`, amplitude ∝ wavelength (a 1/f
    spectrum), scaled to `terrain_amplitude`, rising into hills behind the objects
    (`terrain_rise`); deterministic from `seed`."""
    rng = np.random.default_rng(int(cfg["seed"]))
    x0, x1, z0, z1 = cfg["terrain_extent"]
    nx, nz = cfg["terrain_samples"]
    x, z = np.meshgrid(np.linspace(x0, x1, nx), np.linspace(z0, z1, nz))
    lo, hi = cfg["terrain_wavelengths"]
    h = np.zeros_like(x)
    for _ in range(int(cfg["terrain_waves"])):
        wavelength = np.exp(rng.uniform(np.log(lo), np.log(hi)))
        angle, phase = rng.uniform(0, 2 * np.pi, 2)
        k = 2 * np.pi / wavelength
        h += wavelength * np.sin(k * (np.cos(angle) * x + np.sin(angle) * z) + phase)
    h = h / np.abs(h).max() * float(cfg["terrain_amplitude"])
    # Hills behind the objects: a smooth rise from z = rise[0] to z = rise[1].
    z_lo, z_hi, height = cfg["terrain_rise"]
    s = np.clip((z - z_lo) / (z_hi - z_lo), 0.0, 1.0)
    ridge = 1.0 + 0.6 * np.sin(0.45 * x + 1.0) * np.cos(0.3 * x)  # uneven hill tops
    return h * (1.0 + 3.0 * s) + height * ridge * s * s * (3.0 - 2.0 * s)


def ior(value):
    """A Dielectric's `eta` from the config: a number, or an IOR preset name."""
    return spectral.ior_preset(value) if isinstance(value, str) else float(value)


def build_scene(cfg):
    """(scene, camera) of the showcase."""
    heights = terrain_heights(cfg)
    height = GridHeight(heights, tuple(cfg["terrain_extent"]))
    terrain = HeightField(height, material=0, max_steps=int(cfg["terrain_steps"]),
                          min_step=float(cfg["terrain_min_step"]), rel_step=float(cfg["terrain_rel_step"]))

    def ground(x, z, r):
        """Highest terrain point under a footprint of radius r around (x, z)."""
        ring = [(x + dx, z + dz) for dx in (-r, 0.0, r) for dz in (-r, 0.0, r)]
        return max(float(height(jax.numpy.asarray(a), jax.numpy.asarray(b))) for a, b in ring)

    sdf = jr.sdf
    objects = []
    gx, gz, r = cfg["glass_sphere"]
    objects.append(sdf.Translate(sdf.Sphere(radius=r, material=1), offset=(gx, ground(gx, gz, r / 2) + r, gz)))
    wx, wz, half = cfg["water_block"]
    objects.append(sdf.Translate(sdf.RoundBox(half_extents=(half, half, half), radius=0.1 * half, material=2),
                                 offset=(wx, ground(wx, wz, half) + half * 0.9, wz)))
    mx, mz, r = cfg["mirror_sphere"]
    objects.append(sdf.Translate(sdf.Sphere(radius=r, material=3), offset=(mx, ground(mx, mz, r / 2) + r, mz)))
    ax, az, r = cfg["gold_sphere"]
    objects.append(sdf.Translate(sdf.Sphere(radius=r, material=4), offset=(ax, ground(ax, az, r / 2) + r, az)))
    tx, tz, big, small = cfg["copper_torus"]
    objects.append(sdf.Translate(sdf.Torus(major_radius=big, minor_radius=small, material=5),
                                 offset=(tx, ground(tx, tz, big) + small, tz)))
    materials = [
        jr.bsdf.Lambert(cfg["terrain_albedo"]),
        jr.bsdf.Dielectric(ior(cfg["glass_ior"])),
        jr.bsdf.Dielectric(ior(cfg["water_ior"]), absorption=cfg["water_absorption"]),
        jr.bsdf.Mirror(cfg["mirror_tint"]),
        jr.bsdf.Conductor("gold"),
        jr.bsdf.Conductor("copper"),
    ]
    scene = jr.Scene(
        surface=sdf.Union(*objects),
        materials=materials,
        lights=[jr.DirectionalLight(direction=tuple(cfg["sun_direction"]), irradiance=tuple(cfg["sun_irradiance"]))],
        background=tuple(cfg["sky"]),
        heightfields=[terrain],
    )
    camera = jr.PerspectiveCamera(eye=tuple(cfg["eye"]), target=tuple(cfg["target"]), up=(0.0, 1.0, 0.0),
                                  fov=float(cfg["fov"]), width=int(cfg["width"]), height=int(cfg["height"]))
    return scene, camera


def settings_for(cfg, depth, recursion="unrolled"):
    return jr.RenderSettings(max_depth=int(depth), max_steps=int(cfg["max_steps"]),
                             max_distance=float(cfg["max_distance"]), spp=int(cfg["spp"]),
                             wavelengths=int(cfg["wavelengths"]), batch_size=int(cfg["batch_size"]),
                             recursion=recursion)


def time_depths(cfg, scene, camera, recursion, depths, out_dir=None):
    """Compile and render at every depth of `depths`; rows of figures and images."""
    rows, images = [], []
    for depth in depths:
        settings = settings_for(cfg, depth, recursion)
        tree = integrator.ray_tree(scene, settings)
        t0, c0 = time.perf_counter(), time.process_time()
        render = compile_render(scene, camera, settings)
        compile_s, compile_cpu = time.perf_counter() - t0, time.process_time() - c0
        times, cpu = [], []
        for _ in range(int(cfg["repeats"])):
            t0, c0 = time.perf_counter(), time.process_time()
            image = jax.block_until_ready(render(scene, camera))
            times.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
        rgb = np.asarray(image.rgb)
        if not np.all(np.isfinite(rgb)):
            raise FloatingPointError(f"glass_scene: non-finite pixels at max_depth={depth} ({recursion})")
        if out_dir is not None:
            jr.io.write_png(out_dir / f"glass_scene_d{depth}.png", rgb, exposure=float(cfg["exposure"]))
        images.append(rgb)
        rows.append({
            "recursion": recursion,
            "max_depth": int(depth),
            "compile_s": compile_s,
            "render_s": min(times),
            "compile_cpu_s": compile_cpu,   # CPU seconds of this process (all threads):
            "render_cpu_s": min(cpu),       # unlike wall time, not inflated by other load
            "rays_per_level": tree.rays_per_level(),
            "ray_slots": sum(tree.rays_per_level()),
            "wavelengths": tree.wavelengths,
            "mean_rgb": float(rgb.mean()),
        })
        print(f"  {recursion} depth {depth}: compile {compile_s:.1f} s ({compile_cpu:.1f} CPU s), "
              f"render {min(times):.2f} s ({min(cpu):.2f} CPU s)", flush=True)
    deepest = images[-1]
    for row, rgb in zip(rows, images):
        diff = np.abs(rgb - deepest)
        row["mean_abs_diff_to_deepest"] = float(diff.mean())
        row["max_abs_diff_to_deepest"] = float(diff.max())
    return rows, images, image


def run(cfg, out_dir):
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    scene, camera = build_scene(cfg)
    rows, first = [], None
    for k, (recursion, depths) in enumerate(cfg["recursions"].items()):
        mode_rows, images, image = time_depths(cfg, scene, camera, recursion, depths,
                                               out_dir if k == 0 else None)
        if first is None:
            first = dict(zip(depths, images))
            jr.io.write_exr(out_dir / "glass_scene.exr", image)
            jr.io.write_png(out_dir / "glass_scene_depths.png", np.concatenate(images, axis=1),
                            exposure=float(cfg["exposure"]))
        else:  # the recursions build the same tree: the images must agree
            name = next(iter(cfg["recursions"]))
            for row, depth, b in zip(mode_rows, depths, images):
                if depth in first:
                    row["max_abs_diff_to_recursion_" + name] = float(np.abs(first[depth] - b).max())
        rows += mode_rows
    results = {
        "resolution": [camera.width, camera.height],
        "spp": int(cfg["spp"]),
        "device": jax.devices()[0].device_kind,
        "cpu_count": __import__("os").cpu_count(),
        "depths": rows,
    }
    (out_dir / "results.json").write_text(json.dumps(results, indent=2))
    (out_dir / "config.json").write_text(json.dumps(cfg, indent=2))
    return results


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", default=str(ROOT / f"configs/experiments/{NAME}.toml"))
    ap.add_argument("--out", default=str(ROOT / f"out/{NAME}"))
    ap.add_argument("--quick", action="store_true", help="small sizes from the config's [quick] table")
    args = ap.parse_args(argv)
    cfg = load_config(args.config, args.quick)
    r = run(cfg, args.out)
    w, h = r["resolution"]
    print(f"glass_scene: {w}×{h}, {r['spp']} spp, on {r['device']} ({r['cpu_count']} cores)")
    print("  (wall seconds, and CPU seconds of this process in brackets; |Δ| to the deepest")
    print("   depth of the same recursion)")
    print("  recursion  depth  ray slots  compile (s)        render (s)        mean |Δ| to deepest  max |Δ|")
    for row in r["depths"]:
        print(f"  {row['recursion']:9s}  {row['max_depth']:5d}  {row['ray_slots']:9d}  "
              f"{row['compile_s']:7.1f} ({row['compile_cpu_s']:6.1f})  {row['render_s']:7.2f} ({row['render_cpu_s']:6.2f})"
              f"  {row['mean_abs_diff_to_deepest']:19.5f}  {row['max_abs_diff_to_deepest']:.4f}")
    others = [row for row in r["depths"] if row["recursion"] != r["depths"][0]["recursion"]]
    if others:
        diffs = [row[k] for row in others for k in row if k.startswith("max_abs_diff_to_recursion_")]
        if diffs:
            print(f"  the recursions agree: max |Δ| between their images {max(diffs):.2e}")
    print(f"wrote {args.out}/glass_scene_d*.png, glass_scene_depths.png, glass_scene.exr, results.json")
    return r


if __name__ == "__main__":
    main()
