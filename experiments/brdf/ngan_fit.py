"""Fitting analytic BRDFs to a measured one, after Ngan et al. 2005 (notes, "BRDF comparison").

Reads an isotropic BRDF tabulated in MERL's binary format (`--merl PATH` or `merl` in
the config; without one it generates a synthetic "measured" file, a diffuse base plus
two Cook–Torrance lobes with log-normal noise and missing cells, writes it with
`jaxrt.io.write_merl` and reads it back), draws `data.samples` valid cells to fit and
`data.heldout` other cells to test, and fits each model of `[models]` by weighted least
squares on cosine-weighted values (`jaxrt.fit_brdf`: optimistix Levenberg–Marquardt or
BFGS, JAX gradients, positivity through softplus/exp). The error is Ngan et al.'s

    E = sqrt(Σ w (f cos θi − f_model cos θi)² / (3 Σ w))   (1/sr, RGB mean),

on the fitted cells and on the held-out ones; for synthetic data the generating model's
own E (the noise floor) is listed too.

Writes under the output folder (default out/ngan_fit/): `results.md` and
`results.json` (fitted parameters and errors per model), `slices.png` (in-plane
slices of f cos θi, data against fits, at the `plots.theta_i` incident angles, linear
and log), `spheres/<model>.exr|png` (a sphere per model under a point light, rendered
with `jaxrt.render`, and the measured table itself as `reference`, nearest cell, its
missing cells black), `spheres.png` (all
of them side by side with their errors), the synthetic table if one was generated, and
the resolved `config.json`. Prints the table.

    python experiments/brdf/ngan_fit.py [--config configs/experiments/ngan_fit.toml]
        [--merl PATH] [--out DIR] [--quick]
"""

import argparse
import json
import math
import time
import tomllib
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import jaxrt as jr
from jaxrt import fit_brdf as fb
from jaxrt.config import ConfigError
from jaxrt.io import merl_lookup, read_merl, write_merl
from jaxrt.vecmath import luminance

ROOT = Path(__file__).resolve().parents[2]
NAME = "ngan_fit"
DEFAULT_CONFIG = ROOT / "configs" / "experiments" / f"{NAME}.toml"


# --------------------------------------------------------------------------- config


def load_config(path, quick=False):
    """The experiment's TOML config; with `quick`, the tables of its [quick] table
    replace those of the same name."""
    path = Path(path)
    try:
        cfg = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as e:
        raise ConfigError(f"{path}: cannot read the config ({e})") from None
    overrides = cfg.pop("quick", {})
    if quick:
        cfg.update(overrides)
    check_config(cfg, path)
    return cfg


def check_config(cfg, path):
    """Raise `ConfigError` naming the file and key of the first bad value."""

    def need(ok, key, expected):
        if not ok:
            value = cfg
            for part in key.split("."):
                value = value.get(part, "<missing>") if isinstance(value, dict) else "<missing>"
            raise ConfigError(f"{path}: {key} = {value!r}, expected {expected}")

    def num(x, lo=-math.inf, hi=math.inf):
        return isinstance(x, (int, float)) and not isinstance(x, bool) and lo <= x <= hi

    def integer(x, lo):
        return isinstance(x, int) and not isinstance(x, bool) and x >= lo

    def nums(x, n=None):
        return isinstance(x, list) and all(num(v) for v in x) and (n is None or len(x) == n)

    for table in ("data", "fit", "models", "plots", "render"):
        need(isinstance(cfg.get(table), dict), table, "a table")
    need(isinstance(cfg.get("merl", ""), str), "merl", "a path (a string; \"\" for synthetic data)")
    need(integer(cfg.get("seed", 0), 0), "seed", "an integer ≥ 0")
    d, f, r = cfg["data"], cfg["fit"], cfg["render"]
    need(integer(d.get("samples"), 1), "data.samples", "an integer ≥ 1")
    need(integer(d.get("heldout"), 1), "data.heldout", "an integer ≥ 1")
    need(num(d.get("max_theta"), 1.0, 90.0), "data.max_theta", "degrees in [1, 90]")
    need(d.get("weighting") in fb.WEIGHTINGS, "data.weighting", f"one of {fb.WEIGHTINGS}")
    need(f.get("compression") in fb.COMPRESSIONS, "fit.compression", f"one of {fb.COMPRESSIONS}")
    need(f.get("solver") in fb.SOLVERS, "fit.solver", f"one of {fb.SOLVERS}")
    need(nums(f.get("alphas")) and len(f["alphas"]) >= 1 and all(0 < a <= 1 for a in f["alphas"]),
         "fit.alphas", "a non-empty list of roughnesses in (0, 1]")
    need(integer(f.get("max_steps"), 1), "fit.max_steps", "an integer ≥ 1")
    need(num(f.get("rtol"), 0.0) and f["rtol"] > 0, "fit.rtol", "a number > 0")
    need(num(f.get("atol"), 0.0) and f["atol"] > 0, "fit.atol", "a number > 0")
    need(len(cfg["models"]) >= 1, "models", "at least one model table")
    for label, options in cfg["models"].items():
        need(isinstance(options, dict), f"models.{label}", "a table")
        options = dict(options)
        name = options.pop("model", label)
        need(name in fb.MODELS, f"models.{label}.model" if "model" in cfg["models"][label]
             else f"models.{label}", f"a model of {sorted(fb.MODELS)}")
        try:
            fb.model_spec(name, **options)
        except (ValueError, KeyError) as e:
            raise ConfigError(f"{path}: models.{label} = {cfg['models'][label]!r}: {e}") from None
    need(nums(cfg["plots"].get("theta_i")) and all(0 <= t < 90 for t in cfg["plots"]["theta_i"]),
         "plots.theta_i", "a list of incident angles in [0, 90) degrees")
    need(integer(r.get("width"), 1), "render.width", "an integer ≥ 1")
    need(integer(r.get("height"), 1), "render.height", "an integer ≥ 1")
    need(nums(r.get("light_position"), 3), "render.light_position", "3 numbers")
    need(nums(r.get("light_intensity"), 3), "render.light_intensity", "3 numbers")
    need(num(r.get("camera_distance"), 1.0) and r["camera_distance"] > 1.0,
         "render.camera_distance", "a number > 1 (the sphere has radius 1)")
    need(num(r.get("fov"), 1.0, 170.0), "render.fov", "degrees in [1, 170]")
    need(nums(r.get("background"), 3), "render.background", "3 numbers")
    need(num(r.get("exposure")), "render.exposure", "a number (stops)")
    if not cfg.get("merl"):
        s = cfg.get("synthetic")
        need(isinstance(s, dict), "synthetic", "a table (no merl file is given)")
        need(nums(s.get("diffuse"), 3), "synthetic.diffuse", "3 numbers")
        need(num(s.get("noise"), 0.0, 1.0), "synthetic.noise", "a number in [0, 1]")
        need(num(s.get("missing"), 0.0, 0.9), "synthetic.missing", "a fraction in [0, 0.9]")
        need(isinstance(s.get("lobes"), list), "synthetic.lobes", "a list of lobe tables")
        for i, lobe in enumerate(s["lobes"]):
            key = f"synthetic.lobes[{i}]"
            need(isinstance(lobe, dict) and lobe.get("distribution") in ("ggx", "beckmann"),
                 key + ".distribution", '"ggx" or "beckmann"')
            need(num(lobe.get("alpha"), 1e-3, 1.0), key + ".alpha", "a number in [0.001, 1]")
            need(num(lobe.get("f0"), 0.0, 1.0), key + ".f0", "a number in [0, 1]")
            need(num(lobe.get("ks"), 0.0) or nums(lobe.get("ks"), 3), key + ".ks",
                 "a number ≥ 0 or 3 numbers")
            need(lobe.get("geometry", "smith_correlated") in jr.bsdf.GEOMETRY_TERMS,
                 key + ".geometry", f"one of {sorted(jr.bsdf.GEOMETRY_TERMS)}")


# --------------------------------------------------------------------------- data


def synthetic_material(s):
    """The generating model of the synthetic data: Lambert + the configured lobes."""
    ndf = {"ggx": jr.bsdf.GGX, "beckmann": jr.bsdf.Beckmann}
    lobes = [jr.bsdf.CookTorrance(ndf[lobe["distribution"]](lobe["alpha"]),
                                  jr.bsdf.SchlickFresnel(lobe["f0"]),
                                  geometry=lobe.get("geometry", "smith_correlated"), ks=lobe["ks"])
             for lobe in s["lobes"]]
    return fb.SumBRDF(jr.bsdf.Lambert(s["diffuse"]), *lobes)


def synthetic_table(material, noise, missing, seed):
    """MERL table of `material` × exp(σ z − σ²/2) (z standard normal, mean-preserving
    log-normal noise), a fraction `missing` of the cells set to −1."""
    table = fb.tabulate_merl(material)
    rng = np.random.default_rng(seed)
    valid = table >= 0.0
    factor = np.exp(noise * rng.standard_normal(table.shape) - 0.5 * noise * noise)
    table = np.where(valid, table * factor, table)
    drop = rng.random(table.shape[:3]) < missing
    table[drop] = -1.0
    return table


def split_samples(table, n_fit, n_test, d, seed):
    """Disjoint fitting and held-out `BRDFSamples`, each with weights summing to 1
    (with fewer valid cells than asked for, the held-out set gets what is left)."""
    both = fb.sample_merl(table, n_fit + n_test, max_theta_deg=d["max_theta"],
                          weighting=d["weighting"], seed=seed)
    n = both.f.shape[0]
    perm = np.random.default_rng(seed + 1).permutation(n)
    n_fit = min(n_fit, max(n - 1, 1))

    def take(idx):
        part = fb.BRDFSamples(*(a[np.sort(idx)] for a in both))
        return part._replace(weight=part.weight / jnp.sum(part.weight))

    return take(perm[:n_fit]), take(perm[n_fit:]) if n > n_fit else take(perm[:n_fit])


# --------------------------------------------------------------------------- output


def _fmt(x):
    a = np.asarray(x, dtype=float)
    if a.ndim == 0:
        return f"{float(a):.4g}"
    if a.ndim == 1:
        return "(" + ", ".join(f"{v:.3g}" for v in a) + ")"
    return "[" + "; ".join(_fmt(row) for row in a) + "]"


def markdown_table(rows, source, settings=""):
    lines = [f"Fits to {source} (E: Ngan et al. 2005 cosine-weighted RMS error, 1/sr).",
             *([settings] if settings else []), "",
             "| model | parameters | E (fit) | E (held out) | objective | steps | converged | time (s) |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        params = " ".join(f"{k}={_fmt(v)}" for k, v in r["parameters"].items())
        obj = "" if r["objective"] is None else f"{r['objective']:.3g}"
        conv = "" if r["converged"] is None else ("yes" if r["converged"] else "no")
        lines.append(f"| {r['label']} | {params} | {r['error_fit']:.5f} | {r['error_heldout']:.5f} "
                     f"| {obj} | {r['steps'] if r['steps'] is not None else ''} | {conv} "
                     f"| {r['seconds'] if r['seconds'] is not None else ''} |")
    return "\n".join(lines) + "\n"


def in_plane(theta_i_deg, theta_o_deg):
    """Directions of the incidence plane: wi at θi on the −x side, wo at signed θo
    (positive: the mirror side, so the specular peak is at θo = θi)."""
    ti, to = np.deg2rad(theta_i_deg), np.deg2rad(np.asarray(theta_o_deg, float))
    wi = np.broadcast_to([-np.sin(ti), 0.0, np.cos(ti)], to.shape + (3,))
    wo = np.stack([np.sin(to), np.zeros_like(to), np.cos(to)], axis=-1)
    return wo, np.array(wi)


def plot_slices(path, table, fits, theta_is, max_theta):
    """In-plane slices of luminance(f cos θi): the table's cells (dots, nearest cell)
    against each model (lines), one column per θi, linear (top) and log (bottom)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    theta_o = np.linspace(-89.0, 89.0, 357)
    fig, axes = plt.subplots(2, len(theta_is), figsize=(4.2 * len(theta_is), 7.0), squeeze=False)
    colours = plt.get_cmap("tab10")
    for col, ti in enumerate(theta_is):
        wo, wi = in_plane(ti, theta_o)
        data = merl_lookup(table, wo, wi)
        ok = np.all(data >= 0.0, axis=-1)
        y_data = np.asarray(luminance(np.maximum(data, 0.0))) * np.cos(np.deg2rad(ti))
        for row, log in enumerate((False, True)):
            ax = axes[row, col]
            ax.plot(theta_o[ok], y_data[ok], "k.", ms=3, label="measured")
            for m, (label, material) in enumerate(fits):
                f = np.asarray(jax.vmap(material.eval)(jnp.asarray(wo), jnp.asarray(wi)))
                ax.plot(theta_o, np.asarray(luminance(f)) * np.cos(np.deg2rad(ti)),
                        color=colours(m % 10), lw=1.2, label=label)
            ax.axvspan(max_theta, 90, color="0.9")
            ax.axvspan(-90, -max_theta, color="0.9")
            ax.set_xlim(-90, 90)
            top = y_data[ok].max() if ok.any() else 1.0
            if not log:  # a fit that is far off must not squash the data
                ax.set_ylim(0.0, 1.3 * top)
            if log:
                ax.set_yscale("log")
                positive = y_data[ok & (y_data > 0)]
                if positive.size:
                    ax.set_ylim(max(positive.min() * 0.5, 1e-4), top * 3.0)
            ax.set_xlabel("θo (degrees; > 0 on the mirror side)")
            if col == 0:
                ax.set_ylabel(("log " if log else "") + "luminance of f cos θi (1/sr)")
            if row == 0:
                ax.set_title(f"θi = {ti:g}°, in plane")
    axes[0, -1].legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def render_spheres(materials, r):
    """One unit sphere per material, each under the same point light (`render.light_*`,
    placed relative to the sphere) and seen from the same relative viewpoint. Returns a
    list of [H, W, 3] linear RGB (float32, no shadows: a sphere cannot shadow itself
    where it is lit).

    All spheres are in one multi-material scene, far enough apart that each camera
    sees only its own sphere (rays stop at 2 × the camera distance); the light and the
    camera are moved from sphere to sphere. Moving them changes values, not structure,
    so the scene is compiled once for all the models.
    """
    d = float(r["camera_distance"])
    # A ray stops within 2d, so at most 2d·tan(half-diagonal angle) off axis; the next
    # sphere (radius 1) starts farther than that.
    aspect = r["width"] / r["height"]
    spread = math.tan(math.radians(r["fov"]) / 2.0) * math.hypot(1.0, aspect)
    spacing = 2.0 * d * spread + 3.0
    centres = [np.array([(k - (len(materials) - 1) / 2) * spacing, 0.0, 0.0])
               for k in range(len(materials))]
    surface = jr.sdf.Union(*(jr.sdf.Translate(jr.sdf.Sphere(1.0, material=k), offset=c)
                             for k, c in enumerate(centres)))
    light = np.asarray(r["light_position"], float)
    scene = jr.Scene(surface, materials, lights=[jr.PointLight(light, r["light_intensity"])],
                     background=r["background"])
    # backend "jax", batch_size=None: one vmap over the (few) rays compiles ~3x faster
    # than tiles, and far faster than a lane kernel of every BRDF model at once.
    settings = jr.RenderSettings(max_steps=64, shadows="none", batch_size=None,
                                 max_distance=2.0 * d, backend="jax")
    images = []
    for c in centres:
        lit = eqx.tree_at(lambda s: s.lights[0].position, scene, jnp.asarray(c + light))
        camera = jr.PerspectiveCamera(eye=tuple(c + [0.0, 0.0, -d]), target=tuple(c),
                                      up=(0.0, 1.0, 0.0), fov=r["fov"], width=r["width"],
                                      height=r["height"])
        images.append(np.asarray(jr.render(lit, camera, settings).rgb))
    return images


def sphere_sheet(path, images, exposure):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(images)
    cols = min(n, 5)
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(2.2 * cols, 2.7 * rows), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, (title, rgb) in zip(axes.ravel(), images):
        x = np.clip(np.nan_to_num(rgb * 2.0**exposure), 0.0, 1.0)
        ax.imshow(jr.io.srgb_encode(x).clip(0, 1), interpolation="nearest")
        ax.set_title(title, fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# --------------------------------------------------------------------------- main


def run(cfg, out):
    """Run the study with a checked config; write everything under `out`; return the
    rows of the table."""
    jax.config.update("jax_enable_x64", True)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    seed = int(cfg.get("seed", 0))
    truth = None
    if cfg.get("merl"):
        merl_path = Path(cfg["merl"])
        source = str(merl_path)
    else:
        truth = synthetic_material(cfg["synthetic"])
        s = cfg["synthetic"]
        merl_path = out / "synthetic.binary"
        write_merl(merl_path, synthetic_table(truth, s["noise"], s["missing"], seed))
        source = f"a synthetic MERL file ({merl_path.name}: Lambert + {len(s['lobes'])} lobes, noise {s['noise']})"
    table = read_merl(merl_path)
    d = cfg["data"]
    fit_data, test_data = split_samples(table, d["samples"], d["heldout"], d, seed)
    f = cfg["fit"]

    rows, fits = [], []
    if truth is not None:
        rows.append({"label": "(generating model)", "model": "synthetic", "parameters": {},
                     "error_fit": float(fb.ngan_error(truth, fit_data)),
                     "error_heldout": float(fb.ngan_error(truth, test_data)),
                     "objective": None, "steps": None, "converged": None, "seconds": None})
    for label, options in cfg["models"].items():
        options = dict(options)
        name = options.pop("model", label)
        spec = fb.model_spec(name, **options)
        t0 = time.perf_counter()
        res = fb.fit(spec, fit_data, compression=f["compression"], solver=f["solver"],
                     alphas=tuple(f["alphas"]), max_steps=f["max_steps"], rtol=f["rtol"], atol=f["atol"])
        seconds = round(time.perf_counter() - t0, 2)
        rows.append({"label": label, "model": name, "options": options,
                     "parameters": {k: np.asarray(v).tolist() for k, v in res.params.items()},
                     "error_fit": res.info["error"],
                     "error_heldout": float(fb.ngan_error(res.info["material"], test_data)),
                     "objective": res.loss, "objectives_per_start": res.info["objectives"].tolist(),
                     "steps": res.steps, "converged": res.converged, "seconds": seconds})
        fits.append((label, res.info["material"]))
        print(f"  {label}: E = {res.info['error']:.5f} ({res.steps} steps, {seconds} s)", flush=True)

    settings = (f"{int(fit_data.f.shape[0])} cells fitted, {int(test_data.f.shape[0])} held out; "
                f"θi, θo ≤ {d['max_theta']}°; weighting {d['weighting']}; compression "
                f"{f['compression']}; solver {f['solver']}; starts α = {f['alphas']}.")
    md = markdown_table(rows, source, settings)
    (out / "results.md").write_text(md)
    (out / "results.json").write_text(json.dumps(
        {"source": source, "samples_fit": int(fit_data.f.shape[0]),
         "samples_heldout": int(test_data.f.shape[0]), "rows": rows}, indent=2))
    (out / "config.json").write_text(json.dumps(cfg, indent=2))

    plot_slices(out / "slices.png", table, fits, cfg["plots"]["theta_i"], d["max_theta"])

    r = cfg["render"]
    images = []
    named = [("reference", fb.TabulatedBRDF(table))] + fits
    for (label, _), rgb in zip(named, render_spheres([m for _, m in named], r)):
        jr.io.write_exr(out / "spheres" / f"{label}.exr", rgb)
        jr.io.write_png(out / "spheres" / f"{label}.png", rgb, exposure=r["exposure"])
        err = next((row["error_heldout"] for row in rows if row["label"] == label), None)
        images.append((label if err is None else f"{label}\nE = {err:.4f}", rgb))
    sphere_sheet(out / "spheres.png", images, r["exposure"])

    print(md)
    print(f"wrote {out}/results.md, results.json, slices.png, spheres.png, spheres/*.exr|png")
    return rows


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default=str(DEFAULT_CONFIG))
    parser.add_argument("--merl", default=None, help="a MERL .binary file (overrides the config)")
    parser.add_argument("--out", default=None, help=f"output folder (default out/{NAME})")
    parser.add_argument("--quick", action="store_true", help="the config's [quick] values")
    args = parser.parse_args(argv)
    cfg = load_config(args.config, quick=args.quick)
    if args.merl is not None:
        cfg["merl"] = args.merl
    out = Path(args.out) if args.out else ROOT / "out" / NAME
    return run(cfg, out)


if __name__ == "__main__":
    main()
