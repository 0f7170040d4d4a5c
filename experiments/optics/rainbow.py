"""The rainbow: sunlight through a spherical water droplet, with dispersion.

Notes, "How rainbows work": refraction + internal reflection + refraction, brightest
near 42°. Parallel sunlight (+z) falls on a water droplet of radius 1. Each ray, at
impact parameter b (stratified and uniform over the droplet's cross-section, b = √u),
is traced exactly with the library's `jaxrt.intersect_sphere`, `jaxrt.bsdf.refract`,
`jaxrt.bsdf.reflect` and `jaxrt.bsdf.fresnel_dielectric` (unpolarised):

    enter (refract, weight 1 − F) → k internal reflections (weight F each) → leave
    (refract, weight 1 − F),

with the water's index n(λ) from `jaxrt.spectral.WATER` (Daimon & Masumura 2007) per
wavelength; from inside, the next wall is at the chord t = −2 p·d (|p| = 1). The
outgoing direction's angle from the antisolar point, α = 180° − ∠(d_in, d_out), is
histogrammed with the path weights: the scattered power per degree for k = 1 (primary)
and k = 2 (secondary). Rays pile up at the stationary (minimum-deviation) angle of
Descartes, where the histogram peaks: the bow. Its angle per wavelength is the centre
of the brightest bin (and, as a check, the extreme α over all rays), compared with
Descartes' angle, cos² i = (n² − 1) / ((k + 1)² − 1), D = k·180° + 2i − 2(k + 1)r.

Prints the primary and secondary bow angles per wavelength; writes `rainbow.png` (the
sky around the antisolar point, coloured by `jaxrt.spectral.spectrum_to_rgb` of the
histograms per steradian, blurred by the sun's disk), `rainbow_plot.png` (intensity
against angle; bow angle against wavelength), `results.json`, `config.json` under the
output folder (default out/rainbow/).

    python experiments/optics/rainbow.py [--config ...] [--out DIR] [--quick]
"""

import argparse
import json
import math
import tomllib
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxrt as jr
from jaxrt import spectral
from jaxrt.vecmath import dot

ROOT = Path(__file__).resolve().parents[2]
NAME = "rainbow"


def load_config(path, quick=False):
    """The experiment's TOML config; with `quick`, its [quick] table overrides."""
    cfg = tomllib.loads(Path(path).read_text())
    overrides = cfg.pop("quick", {})
    if quick:
        cfg.update(overrides)
    return cfg


def scatter(b, eta, k):
    """Trace one sun ray at impact parameter b through the unit droplet.

    Returns (α in degrees from the antisolar point, path weight) after k internal
    reflections. `eta` = n_water / n_air (the normal points out, into the air).
    """
    dtype = b.dtype
    d = jnp.array([0.0, 0.0, 1.0], dtype)
    origin = jnp.stack([b, jnp.zeros_like(b), jnp.asarray(-2.0, dtype)])
    t, _ = jr.intersect_sphere(origin, d, jnp.zeros(3, dtype), jnp.asarray(1.0, dtype))
    p = origin + t * d
    wi = -d
    weight = 1.0 - jr.bsdf.fresnel_dielectric(dot(wi, p), eta)
    d, _ = jr.bsdf.refract(wi, p, eta)
    for _ in range(k):
        p = p + (-2.0 * dot(p, d)) * d          # the far wall: chord of the unit sphere
        p = p / jnp.linalg.norm(p)
        wi = -d
        weight = weight * jr.bsdf.fresnel_dielectric(dot(wi, p), eta)
        d = jr.bsdf.reflect(wi, p)
    p = p + (-2.0 * dot(p, d)) * d
    p = p / jnp.linalg.norm(p)
    wi = -d
    weight = weight * (1.0 - jr.bsdf.fresnel_dielectric(dot(wi, p), eta))
    d_out, valid = jr.bsdf.refract(wi, p, eta)
    theta = jnp.degrees(jnp.arccos(jnp.clip(d_out[2], -1.0, 1.0)))
    return 180.0 - theta, jnp.where(valid, weight, 0.0)


def descartes_angle(n, k):
    """Bow angle (degrees from the antisolar point) of Descartes' minimum deviation."""
    cos_i = math.sqrt((n * n - 1.0) / ((k + 1) ** 2 - 1.0))
    i = math.acos(cos_i)
    r = math.asin(math.sin(i) / n)
    deviation = math.degrees(k * math.pi + 2 * i - 2 * (k + 1) * r)
    return abs(180.0 - deviation % 360.0)


def trace(etas, rays, orders):
    """α and weights [len(orders), len(etas), rays] for stratified impact parameters.

    One flat vmap over (wavelength, ray) pairs: a nested vmap (outer over the index,
    inner over the rays) is miscompiled by XLA:CPU in jax 0.10.2 for large batches
    (every row but the first uses the first row's index; see the report of issue 4).
    """
    u = (jnp.arange(rays) + 0.5) / rays
    b, eta = jnp.meshgrid(jnp.sqrt(u), jnp.asarray(etas))      # [λ, rays]
    out_alpha, out_weight = [], []
    for k in orders:
        f = jax.jit(jax.vmap(lambda bi, e, k=k: scatter(bi, e, k)))
        a, w = f(b.ravel(), eta.ravel())
        out_alpha.append(np.asarray(a).reshape(b.shape))
        out_weight.append(np.asarray(w).reshape(b.shape))
    return np.stack(out_alpha), np.stack(out_weight)


def histograms(alpha, weight, edges, rays):
    """Scattered power per degree (fraction of the power hitting the droplet) per bin."""
    width = np.diff(edges)
    h = np.stack([np.histogram(a, bins=edges, weights=w)[0] for a, w in zip(alpha, weight)])
    return h / rays / width


def run(cfg, out_dir):
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    ior = spectral.ior_preset(cfg["ior"])
    orders = [int(k) for k in cfg["orders"]]
    if 1 not in orders:
        raise ValueError(f"configs/experiments/{NAME}.toml: orders = {orders}, expected a list containing 1")
    lam = np.asarray(spectral.sample_wavelengths(int(cfg["wavelengths"])))
    report = np.asarray(cfg["report_wavelengths"], float)
    all_lam = np.concatenate([lam, report])
    etas = np.asarray(ior(jnp.asarray(all_lam)))
    rays = int(cfg["rays"])
    alpha, weight = trace(jnp.asarray(etas), rays, orders)

    lo, hi = cfg["angle_range"]
    edges = np.arange(lo, hi + 1e-9, float(cfg["bin_width"]))
    centres = 0.5 * (edges[1:] + edges[:-1])
    table = {}
    per_degree = []
    for j, k in enumerate(orders):
        h = np.stack([histograms(alpha[j, i][None], weight[j, i][None], edges, rays)[0]
                      for i in range(len(all_lam))])           # [λ, bins]
        per_degree.append(h)
        rows = []
        for i, (wl, n) in enumerate(zip(all_lam, etas)):
            peak = float(centres[np.argmax(h[i])])
            # the stationary angle: the largest α of the primary, the smallest of the secondary
            a = alpha[j, i][weight[j, i] > 0]
            extreme = float(a.max() if k % 2 == 1 else a.min())
            rows.append({"wavelength_nm": float(wl), "ior": float(n), "peak_deg": peak,
                         "extreme_deg": extreme, "descartes_deg": descartes_angle(float(n), k)})
        table[k] = rows
    per_degree = np.stack(per_degree)                           # [orders, λ, bins]

    results = {
        "ior": cfg["ior"],
        "bin_width_deg": float(cfg["bin_width"]),
        "rays_per_wavelength": rays,
        "bows": {str(k): [r for r in table[k] if r["wavelength_nm"] in set(report.tolist())] for k in orders},
        "bows_spectral_samples": {str(k): table[k][: len(lam)] for k in orders},
    }
    image, strip = _render(cfg, per_degree[:, : len(lam)], lam, centres)
    jr.io.write_png(out_dir / "rainbow.png", image, exposure=float(cfg["exposure"]))
    _plot(out_dir / "rainbow_plot.png", centres, per_degree, all_lam, report, table, orders, strip)
    (out_dir / "results.json").write_text(json.dumps(results, indent=2))
    (out_dir / "config.json").write_text(json.dumps(cfg, indent=2))
    return results


def _render(cfg, per_degree, lam, centres):
    """The sky around the antisolar point: bow colours from the spectral histograms."""
    # Per steradian (dP/dΩ = dP/dα / (2π sin α)), summed over the orders, blurred by the
    # sun's disk (a half-disk kernel sqrt(1 − x²) across the bin axis).
    spectra = per_degree.sum(axis=0) / np.sin(np.radians(centres))[None, :]   # [λ, bins]
    step = centres[1] - centres[0]
    half = max(1, int(round(0.5 * float(cfg["sun_diameter"]) / step)))
    x = np.arange(-half, half + 1) / (half + 0.5)
    kernel = np.sqrt(1.0 - x * x)
    kernel /= kernel.sum()
    spectra = np.stack([np.convolve(s, kernel, mode="same") for s in spectra])
    m = np.asarray(spectral.spectral_rgb_matrix(jnp.asarray(lam)))            # [3, λ]
    strip = spectra.T @ m.T                                                   # [bins, 3]
    strip = strip / max(spectral_max_luminance(strip), 1e-30)
    # The view: azimuth and elevation grid (equirectangular), the sun behind the eye at
    # `sun_elevation`, so the antisolar point is that far below the horizon.
    w, h = int(cfg["image_width"]), int(cfg["image_height"])
    deg_per_px = float(cfg["image_fov"]) / w
    az = np.radians((np.arange(w) + 0.5 - w / 2) * deg_per_px)
    el = np.radians(float(cfg["view_elevation"]) - (np.arange(h) + 0.5 - h / 2) * deg_per_px)
    az, el = np.meshgrid(az, el)
    view = np.stack([np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)], -1)
    sun = np.radians(float(cfg["sun_elevation"]))
    antisolar = np.array([0.0, -np.sin(sun), np.cos(sun)])
    alpha = np.degrees(np.arccos(np.clip(view @ antisolar, -1.0, 1.0)))
    idx = np.clip(np.searchsorted(centres, alpha) - 1, 0, len(centres) - 1)
    inside = (alpha >= centres[0]) & (alpha <= centres[-1])
    bow = np.where(inside[..., None], np.clip(strip[idx], 0.0, None), 0.0)
    sky = np.asarray(cfg["sky"], float)
    ground = np.asarray(cfg["ground"], float)
    image = np.where((el < 0.0)[..., None], ground, sky + float(cfg["bow_brightness"]) * bow)
    return image, strip


def spectral_max_luminance(rgb):
    return float(np.max(0.2126 * rgb[:, 0] + 0.7152 * rgb[:, 1] + 0.0722 * rgb[:, 2]))


def _plot(path, centres, per_degree, all_lam, report, table, orders, strip):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lam_set = list(all_lam)
    fig = plt.figure(figsize=(12, 4.6))
    grid = fig.add_gridspec(2, 2, height_ratios=(8, 1), hspace=0.05)
    ax = fig.add_subplot(grid[0, 0])
    for wl in report:
        i = lam_set.index(wl)
        colour = _wavelength_colour(wl)
        for j, k in enumerate(orders):
            ax.semilogy(centres, np.maximum(per_degree[j, i], 1e-7), color=colour, lw=1.0,
                        ls="-" if k == 1 else "--", label=f"{wl:.0f} nm" if j == 0 else None)
    ax.set_ylabel("scattered power per degree")
    ax.set_title("k = 1 (solid, primary) and k = 2 (dashed, secondary)")
    ax.legend(fontsize=7, ncol=2)
    ax.set_xlim(centres[0], centres[-1])
    ax.tick_params(labelbottom=False)
    strip_ax = fig.add_subplot(grid[1, 0], sharex=ax)
    shown = np.clip(strip / max(np.percentile(strip, 99.5), 1e-30), 0.0, 1.0) ** (1 / 2.2)
    strip_ax.imshow(shown[None], extent=(centres[0], centres[-1], 0, 1), aspect="auto")
    strip_ax.set_yticks([])
    strip_ax.set_xlabel("angle from the antisolar point α (degrees); the bow's colour per steradian")
    axes = [ax, fig.add_subplot(grid[:, 1])]
    ax = axes[1]
    for j, k in enumerate(orders):
        rows = sorted(table[k], key=lambda r: r["wavelength_nm"])
        wl = [r["wavelength_nm"] for r in rows]
        ax.plot(wl, [r["descartes_deg"] for r in rows], "k-", lw=0.8,
                label="Descartes (minimum deviation)" if j == 0 else None)
        ax.plot(wl, [r["peak_deg"] for r in rows], "o", ms=3, label=f"traced peak, k = {k}")
    ax.set_xlabel("wavelength (nm)")
    ax.set_ylabel("bow angle α (degrees)")
    ax.legend(fontsize=8)
    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)


def _wavelength_colour(wl):
    lam = spectral.sample_wavelengths(80)
    s = jnp.exp(-0.5 * ((lam - wl) / 6.0) ** 2)
    rgb = np.clip(np.asarray(spectral.spectrum_to_rgb(s, lam)), 0.0, None)
    return tuple(rgb / max(rgb.max(), 1e-12))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", default=str(ROOT / f"configs/experiments/{NAME}.toml"))
    ap.add_argument("--out", default=str(ROOT / f"out/{NAME}"))
    ap.add_argument("--quick", action="store_true", help="small sizes from the config's [quick] table")
    args = ap.parse_args(argv)
    cfg = load_config(args.config, args.quick)
    r = run(cfg, args.out)
    print(f"rainbow in a {cfg['ior']} droplet ({r['rays_per_wavelength']} rays per wavelength, "
          f"{r['bin_width_deg']}° bins): bow angle from the antisolar point")
    print("  λ (nm)    n       k   peak (°)  extreme (°)  Descartes (°)")
    for k, rows in r["bows"].items():
        for row in rows:
            print(f"  {row['wavelength_nm']:6.1f}  {row['ior']:.5f}  {k}   {row['peak_deg']:7.2f}   "
                  f"{row['extreme_deg']:9.3f}    {row['descartes_deg']:9.3f}")
    print(f"wrote {args.out}/rainbow.png, rainbow_plot.png, results.json")
    return r


if __name__ == "__main__":
    main()
