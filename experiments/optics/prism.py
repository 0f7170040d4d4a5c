"""A prism: white light spreads into a spectrum (dispersion).

Notes, "Refraction is wavelength dependent". A collimated beam of white light (a flat
spectrum, i.e. D65 white in `jaxrt.spectral`'s convention) falls on the first face of
a glass prism (apex angle A, in the x–y plane) and leaves through the second. Every ray
is traced per wavelength with the library: `jaxrt.intersect_plane` for the faces, the
glass's Sellmeier index n(λ) (`jaxrt.spectral`), `jaxrt.bsdf.refract` and the exact
`jaxrt.bsdf.fresnel_dielectric` at both faces (a ray that would leave through the base
or is totally reflected at the second face is dropped; the weak beam reflected by the
first face is drawn, the internal reflections are not).

Figures: the deviation δ(λ) of the central ray, traced and from the prism formula
δ = θi + asin(n sin(A − asin(sin θi / n))) − A; the angular dispersion δ_F − δ_C; the
spread of 400–700 nm on the screen. Images: `prism.png`, a top view in which every
ray's path is splatted into a spectral image (one channel per wavelength) and turned
into colour with `jaxrt.spectral.spectral_rgb_matrix` (the incoming beam is white, the
outgoing one a fan of colours), and `prism_screen.png`, the spectrum where the rays
meet a screen `screen_distance` after the prism. Writes `results.json` and the resolved
`config.json` under the output folder (default out/prism/).

    python experiments/optics/prism.py [--config ...] [--out DIR] [--quick]
"""

import argparse
import functools
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
NAME = "prism"


def load_config(path, quick=False):
    """The experiment's TOML config; with `quick`, its [quick] table overrides."""
    cfg = tomllib.loads(Path(path).read_text())
    overrides = cfg.pop("quick", {})
    if quick:
        cfg.update(overrides)
    return cfg


def geometry(cfg, ior):
    """Prism faces (outward unit normals and plane offsets n·p = c), the beam, the screen."""
    a = math.radians(float(cfg["apex_angle"]))
    side = float(cfg["side"])
    h = side * math.cos(a / 2)
    apex = np.array([0.0, h / 2, 0.0])
    left_base = np.array([-side * math.sin(a / 2), -h / 2, 0.0])
    n_left = np.array([-math.cos(a / 2), math.sin(a / 2), 0.0])
    n_right = np.array([math.cos(a / 2), math.sin(a / 2), 0.0])
    n_base = np.array([0.0, -1.0, 0.0])
    n_ref = float(ior(float(cfg["reference_wavelength"])))
    theta_i = math.radians(float(cfg["incidence"])) if float(cfg["incidence"]) > 0 else \
        math.asin(min(1.0, n_ref * math.sin(a / 2)))
    phi = theta_i - a / 2                               # direction of the incoming beam
    d_in = np.array([math.cos(phi), math.sin(phi), 0.0])
    perp = np.array([-math.sin(phi), math.cos(phi), 0.0])
    centre = 0.5 * (apex + left_base)
    source = centre - float(cfg["source_distance"]) * d_in
    g = {
        "n_left": n_left, "c_left": n_left @ apex,
        "n_right": n_right, "c_right": n_right @ apex,
        "n_base": n_base, "c_base": n_base @ left_base,
        "d_in": d_in, "perp": perp, "source": source,
        "theta_i": theta_i, "apex_angle": a,
        "corners": np.stack([apex, left_base, left_base * np.array([-1.0, 1.0, 1.0])]),
    }
    # The screen: perpendicular to the reference wavelength's central ray, after the prism.
    _, p2, _, d2, _, _ = jax.jit(lambda e, g: trace_ray(jnp.zeros_like(e), e, g, screen=False))(
        jnp.asarray(n_ref), {k: jnp.asarray(v) for k, v in g.items() if k != "corners"})
    d2 = np.asarray(d2)
    g["screen_normal"] = -d2
    g["screen_centre"] = np.asarray(p2) + float(cfg["screen_distance"]) * d2
    g["screen_offset"] = g["screen_normal"] @ g["screen_centre"]
    g["screen_tangent"] = np.array([-d2[1], d2[0], 0.0])
    return g


def trace_ray(u, eta, g, screen=True):
    """One ray of the beam at offset u (across the beam) for the index eta = n_glass.

    Returns (p1, p2, p3, d_out, s, weight): the hits on the first face, the second face
    and the screen, the outgoing direction, the position s along the screen and the
    transmitted fraction (1 − F1)(1 − F2) (0 for rays lost to the base or to TIR).
    """
    o = g["source"] + u * g["perp"]
    d = g["d_in"]
    t1, _ = jr.intersect_plane(o, d, g["n_left"], g["c_left"])
    p1 = o + t1 * d
    wi = -d
    f1 = jr.bsdf.fresnel_dielectric(dot(wi, g["n_left"]), eta)
    d1, _ = jr.bsdf.refract(wi, g["n_left"], eta)      # eta = n_glass / n_air (normal points out)
    t_right, hit_right = jr.intersect_plane(p1, d1, g["n_right"], g["c_right"])
    t_base, hit_base = jr.intersect_plane(p1, d1, g["n_base"], g["c_base"])
    through = hit_right & ((~hit_base) | (t_right < t_base))
    p2 = p1 + t_right * d1
    wi = -d1
    f2 = jr.bsdf.fresnel_dielectric(dot(wi, g["n_right"]), eta)
    d2, leaves = jr.bsdf.refract(wi, g["n_right"], eta)
    weight = jnp.where(through & leaves, (1.0 - f1) * (1.0 - f2), 0.0)
    if not screen:
        return p1, p2, p2, d2, jnp.zeros(()), weight
    t3, _ = jr.intersect_plane(p2, d2, g["screen_normal"], g["screen_offset"])
    p3 = p2 + t3 * d2
    s = dot(p3 - g["screen_centre"], g["screen_tangent"])
    return p1, p2, p3, d2, s, weight


def prism_deviation(n, theta_i, apex):
    """δ = θi + asin(n sin(A − asin(sin θi / n))) − A (radians; nan beyond TIR)."""
    r1 = math.asin(math.sin(theta_i) / n)
    x = n * math.sin(apex - r1)
    return theta_i + math.asin(x) - apex if abs(x) <= 1.0 else float("nan")


def _jittered(lam, rays):
    """[λ, rays] wavelengths: ray j of stratum i at 380 + (i + u_j) · Δλ, u_j = frac(j φ + ½)
    (golden-ratio jitter), so the beam carries a continuous spectrum; each stratum is
    coloured as its midpoint's channel (stratified sampling)."""
    width = (spectral.LAMBDA_MAX - spectral.LAMBDA_MIN) / lam.shape[0]
    u = jnp.mod(jnp.arange(rays) * 0.6180339887498949 + 0.5, 1.0)
    return (lam - 0.5 * width)[:, None] + u[None, :] * width


def run(cfg, out_dir):
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    ior = spectral.ior_preset(cfg["glass"])
    g_np = geometry(cfg, ior)
    g = {k: jnp.asarray(v) for k, v in g_np.items() if k != "corners"}
    lam = spectral.sample_wavelengths(int(cfg["wavelengths"]))
    report = np.asarray(cfg["report_wavelengths"], float)
    rays = int(cfg["rays"])
    width = float(cfg["beam_width"])

    @functools.partial(jax.jit, static_argnums=0)
    def beam(n_rays, lam, g):
        """Every (wavelength, ray) pair of a beam of n_rays, [λ, rays, ...]; one flat vmap
        over the pairs (see rainbow.py on nested vmaps)."""
        u = ((jnp.arange(n_rays) + 0.5) / n_rays - 0.5) * width
        uu = jnp.broadcast_to(u, (lam.shape[0], n_rays))
        eta = ior(_jittered(lam, n_rays))
        out = jax.vmap(lambda ui, e: trace_ray(ui, e, g))(uu.ravel(), eta.ravel())
        return jax.tree_util.tree_map(lambda x: x.reshape(uu.shape + x.shape[1:]), out)

    p1, p2, p3, d_out, s, weight = (np.asarray(x) for x in beam(rays, lam, g))

    # Central rays at the reported wavelengths: traced deviation against the formula.
    central = jax.jit(lambda lam_c, g: jax.vmap(lambda e: (e,) + trace_ray(jnp.zeros_like(e), e, g))(ior(lam_c)))
    eta_report, _, _, p3_c, d_c, s_c, w_c = (
        np.asarray(x) for x in central(jnp.asarray(np.concatenate([report, [400.0, 700.0]])), g))
    d_in = g_np["d_in"]
    traced = np.degrees(np.arccos(np.clip(d_c @ d_in, -1.0, 1.0)))
    formula = [math.degrees(prism_deviation(float(n), g_np["theta_i"], g_np["apex_angle"])) for n in eta_report]
    rows = [{"wavelength_nm": float(w), "ior": float(n), "deviation_deg": float(t), "formula_deg": float(f)}
            for w, n, t, f in zip(report, eta_report, traced, formula)]
    results = {
        "glass": cfg["glass"],
        "apex_angle_deg": float(cfg["apex_angle"]),
        "incidence_deg": math.degrees(g_np["theta_i"]),
        "abbe_number": float(spectral.abbe_number(ior)),
        "deviation": rows,
        "angular_dispersion_F_C_deg": float(traced[0] - traced[2]) if len(report) >= 3 else None,
        "angular_spread_400_700_deg": float(traced[-2] - traced[-1]),
        "screen_spread_400_700": float(abs(s_c[-1] - s_c[-2])),
        "screen_distance": float(cfg["screen_distance"]),
    }

    m = np.asarray(spectral.spectral_rgb_matrix(lam))     # [3, λ]
    top = _top_view(cfg, g_np, p1, p2, p3, weight, m, rays)
    jr.io.write_png(out_dir / "prism.png", top, exposure=float(cfg["exposure"]))
    # The screen from a denser beam (the top view needs few rays, the histogram many).
    screen_rays = int(cfg["screen_rays"])
    out = beam(screen_rays, lam, g)
    s_dense, w_dense = np.asarray(out[4]), np.asarray(out[5])
    strip = _screen(cfg, s_dense, w_dense, m, screen_rays)
    jr.io.write_png(out_dir / "prism_screen.png", strip)
    (out_dir / "results.json").write_text(json.dumps(results, indent=2))
    (out_dir / "config.json").write_text(json.dumps(cfg, indent=2))
    return results


def _top_view(cfg, g, p1, p2, p3, weight, m, rays):
    """Splat every ray's path into a spectral image [H, W, λ]; colour it with m."""
    w, h = int(cfg["image_width"]), int(cfg["image_height"])
    n_lam = p1.shape[0]
    source = g["source"][None, None, :] + (np.linspace(-0.5, 0.5, rays)[None, :, None] * float(cfg["beam_width"])
                                           * g["perp"][None, None, :])
    source = np.broadcast_to(source, p1.shape)
    pts = np.concatenate([source.reshape(-1, 3), p3.reshape(-1, 3), g["corners"]])
    lo, hi = pts[:, :2].min(0), pts[:, :2].max(0)
    span = hi - lo
    lo, span = lo - 0.05 * span, 1.1 * span
    scale = min(w / span[0], h / span[1])                # pixels per unit, aspect kept
    offset = 0.5 * (np.array([w, h]) - scale * span)

    def to_px(p):
        xy = (p[..., :2] - lo) * scale + offset
        return xy[..., 0], h - xy[..., 1]

    image = np.zeros((h * w, n_lam))
    lam_index = np.broadcast_to(np.arange(n_lam)[:, None], weight.shape)
    reflected = 2.0 * (-g["d_in"] @ g["n_left"]) * g["n_left"] + g["d_in"]  # mirror of d_in

    def splat(a, b, wgt):
        length = np.linalg.norm(b - a, axis=-1) * scale
        n = int(np.ceil(length.max() * 2)) + 1
        t = np.linspace(0.0, 1.0, n)
        pts = a[..., None, :] + t[:, None] * (b - a)[..., None, :]
        x, y = to_px(pts)
        ok = (x >= 0) & (x < w) & (y >= 0) & (y < h)
        flat = (np.floor(y).astype(int) * w + np.floor(x).astype(int))
        per_point = (wgt * length / n / rays)[..., None] * np.ones(n)
        idx = (flat * n_lam + lam_index[..., None])[ok]
        np.add.at(image.reshape(-1), idx, per_point[ok])

    splat(source, p1, np.ones_like(weight))
    splat(p1, p2, np.where(weight > 0, 1.0, 0.0) * 0.95)
    splat(p2, p3, weight)
    f1 = np.asarray(jax.jit(jax.vmap(lambda e: jr.bsdf.fresnel_dielectric(-g["d_in"] @ g["n_left"], e)))(
        spectral.ior_preset(cfg["glass"])(spectral.sample_wavelengths(n_lam))))
    splat(p1, p1 + 0.6 * reflected, np.broadcast_to(f1[:, None], weight.shape))
    # (the reflected beam uses each stratum's midpoint index: F hardly varies with λ)
    rgb = image @ m.T
    rgb = rgb / max(np.percentile(rgb.max(-1), 99.5), 1e-30)
    # The prism: a faint glass tint inside the triangle (same-sign edge functions).
    yy, xx = np.divmod(np.arange(h * w), w)
    c = np.stack(to_px(g["corners"]), -1)
    edge = np.stack([(c[(i + 1) % 3, 0] - c[i, 0]) * (yy + 0.5 - c[i, 1])
                     - (c[(i + 1) % 3, 1] - c[i, 1]) * (xx + 0.5 - c[i, 0]) for i in range(3)])
    inside = np.all(edge <= 0, axis=0) | np.all(edge >= 0, axis=0)
    rgb = rgb + inside[:, None] * np.array([0.02, 0.03, 0.04])
    return rgb.reshape(h, w, 3)


def _screen(cfg, s, weight, m, rays):
    """The spectrum on the screen: histogram of s per wavelength, coloured."""
    w, h = int(cfg["image_width"]), int(cfg["strip_height"])
    valid = weight > 0
    lo, hi = s[valid].min(), s[valid].max()
    pad = 0.1 * (hi - lo) + 1e-9
    edges = np.linspace(lo - pad, hi + pad, w + 1)
    spectra = np.stack([np.histogram(s[i], bins=edges, weights=weight[i])[0] for i in range(s.shape[0])], -1)
    rgb = spectra @ m.T / rays
    rgb = rgb / max(rgb.max(), 1e-30)
    return np.broadcast_to(rgb[None], (h, w, 3))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", default=str(ROOT / f"configs/experiments/{NAME}.toml"))
    ap.add_argument("--out", default=str(ROOT / f"out/{NAME}"))
    ap.add_argument("--quick", action="store_true", help="small sizes from the config's [quick] table")
    args = ap.parse_args(argv)
    cfg = load_config(args.config, args.quick)
    r = run(cfg, args.out)
    print(f"prism: {r['glass']} (V_d = {r['abbe_number']:.2f}), apex {r['apex_angle_deg']:.1f}°, "
          f"incidence {r['incidence_deg']:.2f}°")
    print("  λ (nm)    n        deviation traced (°)   prism formula (°)")
    for row in r["deviation"]:
        print(f"  {row['wavelength_nm']:7.2f}  {row['ior']:.5f}   {row['deviation_deg']:12.5f}   "
              f"{row['formula_deg']:16.5f}")
    if r["angular_dispersion_F_C_deg"] is not None:
        print(f"angular dispersion δ_F − δ_C = {r['angular_dispersion_F_C_deg']:.3f}°; "
              f"400–700 nm spread {r['angular_spread_400_700_deg']:.3f}°, "
              f"{r['screen_spread_400_700']:.3f} units on a screen {r['screen_distance']} after the prism")
    print(f"wrote {args.out}/prism.png, prism_screen.png, results.json")
    return r


if __name__ == "__main__":
    main()
