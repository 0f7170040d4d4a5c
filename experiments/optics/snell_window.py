"""Snell's window (the optical manhole): the sky seen from under a flat water surface.

Notes, "Physics of shading" (Fig. 3.7): light from the horizon (incidence 90°) is
refracted into the water at the critical angle θc = asin(1 / n), 48.6° for n = 1.333,
so from below the whole sky fills a cone of full angle 2θc = 97.2°; outside it the
surface is a mirror (total internal reflection) showing the dark water.

The eye looks straight up from `depth` below the surface through an equidistant
fisheye (the angle from the zenith is proportional to the distance from the image
centre). Each ray is marched to the surface (`jaxrt.heightfield`, flat or wavy), split
by the exact Fresnel reflectance (`jaxrt.bsdf.fresnel_dielectric`) into a refracted
ray into the sky (`jaxrt.bsdf.refract`; radiance scaled by η² on entering the denser
medium) and a reflected one into the water:

    L = (1 − F) · η² · L_sky(wt) + F · L_water     (wt: the refracted direction).

The full angle of the bright cone is measured from the image: on a one-row strip
through the zenith (the same camera, `profile_width` pixels), the edge on each side is
where the luminance crosses `edge_threshold` of the way from the outside level (the
darkest pixel) to the zenith level, located by linear interpolation between pixels.
(The transmitted brightness falls to zero at θc like sqrt(θc − θ), so a low threshold
locates θc; a half-maximum threshold would read ~0.4° inside it.)

Prints the measured full angle against 2 asin(1/n); writes `snell_window.png` (the
fisheye), `snell_window_waves.png` (through waves, if configured),
`snell_window_profile.png` (the strip's luminance against angle), `results.json` and
the resolved `config.json` under the output folder (default out/snell_window/).

    python experiments/optics/snell_window.py [--config ...] [--out DIR] [--quick]
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
from jaxrt.heightfield import HeightField, SineHeight
from jaxrt.spectral import ior_preset
from jaxrt.vecmath import dot, luminance

ROOT = Path(__file__).resolve().parents[2]
NAME = "snell_window"


def load_config(path, quick=False):
    """The experiment's TOML config; with `quick`, its [quick] table overrides."""
    cfg = tomllib.loads(Path(path).read_text())
    overrides = cfg.pop("quick", {})
    if quick:
        cfg.update(overrides)
    return cfg


def water_index(cfg):
    """n of the water: a preset evaluated at cfg["wavelength"], or a number."""
    ior = cfg["ior"]
    if isinstance(ior, str):
        return float(ior_preset(ior)(cfg["wavelength"]))
    return float(ior)


def fisheye_directions(x, y, fov):
    """Equidistant fisheye looking up +y: image point (x, y) ∈ [−1, 1]² → unit direction.

    θ (from the zenith) = r · fov/2 with r = |(x, y)|, azimuth atan2(y, x). Returns
    (direction [..., 3], r).
    """
    r = jnp.sqrt(x * x + y * y)
    theta = r * jnp.radians(fov) / 2.0
    phi = jnp.arctan2(y, x)
    d = jnp.stack([jnp.sin(theta) * jnp.cos(phi), jnp.cos(theta), jnp.sin(theta) * jnp.sin(phi)], axis=-1)
    return d, r


def radiance(surface, eta, origin, d, sky_zenith, sky_horizon, water, settings):
    """Radiance seen along one ray from below the water surface (module docstring)."""
    hit = surface.intersect(origin, d, settings)
    p = origin + hit.t * d
    n = surface.normal(p)                      # points up, into the air
    wi = -d                                     # towards the eye, below the surface
    f = jr.bsdf.fresnel_dielectric(dot(wi, n), eta)
    wt, valid = jr.bsdf.refract(wi, n, eta)     # eta = n_below / n_above = n_water / n_air
    elevation = jnp.clip(wt[1], 0.0, 1.0)
    sky = sky_horizon + (sky_zenith - sky_horizon) * elevation
    transmitted = jnp.where(valid, (1.0 - f) * eta * eta, 0.0) * sky
    seen = transmitted + jnp.where(valid, f, 1.0) * water
    return jnp.where(hit.hit, seen, water)


def view_directions(width, height, samples, fov, row_only=False):
    """Sample directions of a fisheye view (numpy): [rows, sub_y, width, samples, 3]
    and the image radius r of each, plus the zenith angle (degrees, signed) of each
    column's centre. With `row_only`, one row through the zenith, sub-sampled along it."""
    s = (np.arange(samples) + 0.5) / samples
    x = 2.0 * (np.arange(width)[:, None] + s[None, :]).reshape(-1) / width - 1.0
    if row_only:
        y, rows, sub_y = np.zeros(1), 1, 1
    else:
        y = 1.0 - 2.0 * (np.arange(height)[:, None] + s[None, :]).reshape(-1) / height
        rows, sub_y = height, samples
    xx, yy = np.meshgrid(x, y)
    d, r = (np.asarray(a) for a in fisheye_directions(jnp.asarray(xx), jnp.asarray(yy), fov))
    angle = (2.0 * (np.arange(width) + 0.5) / width - 1.0) * fov / 2.0
    shape = (rows, sub_y, width, samples)
    return d.reshape(shape + (3,)), r.reshape(shape), angle


def render(cfg, views, amplitude=0.0):
    """Render several fisheye views (`view_directions` outputs) in one compiled program;
    returns their box-filtered [rows, width, 3] linear RGB images."""
    eta = water_index(cfg)
    settings = jr.RenderSettings(max_distance=1e3)
    colours = [jnp.asarray(cfg[k], float) for k in ("sky_zenith", "sky_horizon", "water")]
    origin = jnp.array([0.0, -float(cfg["depth"]), 0.0])
    frequency = cfg.get("wave_frequency", (1.0, 0.0))

    @jax.jit
    def shade(d, amplitude):
        surface = HeightField(SineHeight(amplitude, frequency=frequency))
        return jax.vmap(lambda di: radiance(surface, eta, origin, di, *colours, settings))(d)

    flat = np.concatenate([d.reshape(-1, 3) for d, _, _ in views])
    rgb = np.asarray(shade(jnp.asarray(flat), jnp.asarray(amplitude, float)))
    images, start = [], 0
    for d, r, _ in views:
        n = r.size
        part = np.where((r <= 1.0)[..., None], rgb[start:start + n].reshape(d.shape), 0.0)
        images.append(part.mean(axis=(1, 3)))
        start += n
    return images


def measure_window(profile, angle, threshold):
    """Full angle (degrees) of the bright cone of a luminance profile through the zenith.

    level = low + threshold · (high − low), low the darkest pixel, high the zenith
    pixel; on each side the outermost crossing of `level`, interpolated linearly
    between pixel centres. Returns (full_angle, left_edge, right_edge).
    """
    profile = np.asarray(profile, float)
    low, high = profile.min(), profile[np.argmin(np.abs(angle))]
    level = low + threshold * (high - low)
    bright = np.nonzero(profile > level)[0]
    if bright.size == 0:
        raise ValueError("no pixel brighter than the edge level: the window is not in the image")

    def crossing(i_in, i_out):
        a, b = profile[i_in], profile[i_out]
        u = (a - level) / (a - b)
        return angle[i_in] + u * (angle[i_out] - angle[i_in])

    lo, hi = bright[0], bright[-1]
    if lo == 0 or hi == len(profile) - 1:
        raise ValueError("the window reaches the border of the strip: widen field_of_view")
    left, right = crossing(lo, lo - 1), crossing(hi, hi + 1)
    return right - left, left, right


def run(cfg, out_dir):
    """Render, measure, plot; returns the figures as a dict."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    eta = water_index(cfg)
    theory = 2.0 * math.degrees(math.asin(1.0 / eta))

    fov = float(cfg["field_of_view"])
    strip_view = view_directions(int(cfg["profile_width"]), 1, int(cfg["profile_samples"]), fov, row_only=True)
    image_view = view_directions(int(cfg["width"]), int(cfg["height"]), int(cfg["samples"]), fov)
    strip, image = render(cfg, [strip_view, image_view])
    angle, image_angle = strip_view[2], image_view[2]
    profile = np.asarray(luminance(strip[0]))
    full, left, right = measure_window(profile, angle, float(cfg["edge_threshold"]))

    row = np.asarray(luminance(image[image.shape[0] // 2]))
    # The centre row of an even-sized image sits half a pixel below the zenith.
    full_image, _, _ = measure_window(row, image_angle, float(cfg["edge_threshold"]))
    jr.io.write_png(out_dir / "snell_window.png", image, exposure=float(cfg["exposure"]))
    if float(cfg.get("wave_amplitude", 0.0)) > 0.0:
        waves, = render(cfg, [image_view], amplitude=float(cfg["wave_amplitude"]))
        jr.io.write_png(out_dir / "snell_window_waves.png", waves, exposure=float(cfg["exposure"]))

    results = {
        "ior": eta,
        "critical_angle_deg": math.degrees(math.asin(1.0 / eta)),
        "theory_full_angle_deg": theory,
        "measured_full_angle_deg": float(full),
        "error_deg": float(full - theory),
        "edges_deg": [float(left), float(right)],
        "measured_full_angle_image_deg": float(full_image),
        "strip_pixel_deg": float(cfg["field_of_view"]) / int(cfg["profile_width"]),
        "image_pixel_deg": float(cfg["field_of_view"]) / int(cfg["width"]),
    }
    _plot(out_dir / "snell_window_profile.png", angle, profile, results)
    (out_dir / "results.json").write_text(json.dumps(results, indent=2))
    (out_dir / "config.json").write_text(json.dumps(cfg, indent=2))
    return results


def _plot(path, angle, profile, results):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.5))
    ax.plot(angle, profile, lw=1.2, label="luminance of the strip through the zenith")
    for e in results["edges_deg"]:
        ax.axvline(e, color="C1", lw=0.8)
    c = results["critical_angle_deg"]
    for e in (-c, c):
        ax.axvline(e, color="k", ls=":", lw=0.8)
    ax.set_xlabel("angle from the zenith (degrees)")
    ax.set_ylabel("luminance")
    ax.set_title(f"Snell's window: measured {results['measured_full_angle_deg']:.2f}°, "
                 f"theory 2·asin(1/n) = {results['theory_full_angle_deg']:.2f}° (n = {results['ior']:.4f})")
    ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", default=str(ROOT / f"configs/experiments/{NAME}.toml"))
    ap.add_argument("--out", default=str(ROOT / f"out/{NAME}"))
    ap.add_argument("--quick", action="store_true", help="small sizes from the config's [quick] table")
    args = ap.parse_args(argv)
    cfg = load_config(args.config, args.quick)
    r = run(cfg, args.out)
    print(f"Snell's window (n = {r['ior']:.4f}, critical angle {r['critical_angle_deg']:.2f}°): "
          f"full angle measured {r['measured_full_angle_deg']:.2f}° "
          f"(strip, {r['strip_pixel_deg']:.3f}°/pixel; edges {r['edges_deg'][0]:.2f}°, {r['edges_deg'][1]:.2f}°), "
          f"theory {r['theory_full_angle_deg']:.2f}°, error {r['error_deg']:+.3f}°; "
          f"from the {cfg['width']}-pixel image row: {r['measured_full_angle_image_deg']:.2f}° "
          f"({r['image_pixel_deg']:.2f}°/pixel)")
    print(f"wrote {args.out}/snell_window.png, snell_window_profile.png, results.json")
    return r


if __name__ == "__main__":
    main()
