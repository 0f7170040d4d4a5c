"""A gallery of the reflectance models: spheres of each model (rows) at several
roughnesses (columns) under one light, in one image, like the notes' comparisons of
the Phong, Beckmann and GGX distributions ("Normal Distribution Function").

All spheres are in ONE scene, each with its own material (a multi-material scene: the
union of the spheres carries the material index of the nearest one), seen through an
orthographic camera under a directional light, so every sphere is seen and lit alike.

Each column has one Beckmann-equivalent roughness α; each model gets the parameters
that match it (notes: α_p = 2 α⁻² − 2 for lobes about the half vector; a lobe about
the mirror direction, (wo·r)^n, is about as wide when n = α_p / 4, since the angle to
the mirror direction is about twice the half-vector angle). `specular` is the weight of
every specular lobe (see `MODELS`), `diffuse` the albedo of every diffuse base.

Writes `gallery.exr` (linear, with AOVs), `gallery.png` (sRGB preview) and
`gallery_labeled.png` (with model and α labels) and the resolved `config.json` under
the output folder (default out/gallery/), and prints what it rendered.

    python experiments/brdf/gallery.py [--config configs/experiments/gallery.toml]
        [--out DIR] [--quick]
"""

import argparse
import json
import math
import time
import tomllib
from pathlib import Path

import numpy as np

import jaxrt as jr
from jaxrt.bsdf import (AshikhminShirley, Beckmann, BlinnPhong, CookTorrance, GGX, Lafortune,
                        Phong, SchlickFresnel, Ward)
from jaxrt.config import ConfigError

ROOT = Path(__file__).resolve().parents[2]
NAME = "gallery"
DEFAULT_CONFIG = ROOT / "configs" / "experiments" / f"{NAME}.toml"


def half_vector_exponent(alpha):
    """α_p = 2 α⁻² − 2: Blinn–Phong exponent of Beckmann roughness α (notes)."""
    return 2.0 / (alpha * alpha) - 2.0


def mirror_exponent(alpha):
    """Exponent n of a lobe (wo·r)^n about the mirror direction as wide as the
    half-vector lobe of roughness α: n = α_p / 4, at least 1."""
    return max(half_vector_exponent(alpha) / 4.0, 1.0)


#: name → (label, material(α, diffuse, specular)). `specular` is ks (Phong,
#: Blinn–Phong), rho_s (Ward), f0 of Schlick's Fresnel (Cook–Torrance, with ks = 1), rs
#: (Ashikhmin–Shirley) or the albedo of the normalised cosine lobe (Lafortune).
MODELS = {
    "phong": ("Phong (normalised)",
              lambda a, kd, s: Phong(kd, s, mirror_exponent(a), normalized=True)),
    "blinn_phong": ("Blinn-Phong", lambda a, kd, s: BlinnPhong(kd, s, half_vector_exponent(a))),
    "ward": ("Ward", lambda a, kd, s: Ward(kd, s, a)),
    "ward_duer": ("Ward-Duer", lambda a, kd, s: Ward(kd, s, a, normalization="duer")),
    "cook_torrance_beckmann": ("Cook-Torrance Beckmann",
                               lambda a, kd, s: CookTorrance(Beckmann(a), SchlickFresnel(s),
                                                             diffuse=kd)),
    "cook_torrance_ggx": ("Cook-Torrance GGX",
                          lambda a, kd, s: CookTorrance(GGX(a), SchlickFresnel(s), diffuse=kd)),
    "lafortune": ("Lafortune (1 lobe)",
                  lambda a, kd, s: Lafortune(kd, s * (mirror_exponent(a) + 2.0) / (2.0 * math.pi),
                                             -1.0, 1.0, mirror_exponent(a))),
    "ashikhmin_shirley": ("Ashikhmin-Shirley",
                          lambda a, kd, s: AshikhminShirley(kd, s, half_vector_exponent(a))),
}


def load_config(path, quick=False):
    """The TOML config (its [quick] values replacing the others with `quick`), checked."""
    path = Path(path)
    try:
        cfg = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as e:
        raise ConfigError(f"{path}: cannot read the config ({e})") from None
    overrides = cfg.pop("quick", {})
    if quick:
        cfg.update(overrides)

    def need(ok, key, expected):
        if not ok:
            raise ConfigError(f"{path}: {key} = {cfg.get(key, '<missing>')!r}, expected {expected}")

    def num(x):
        return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)

    def nums(x, n):
        return isinstance(x, list) and len(x) == n and all(num(v) for v in x)

    need(isinstance(cfg.get("models"), list) and cfg["models"]
         and all(m in MODELS for m in cfg["models"]), "models",
         f"a non-empty list of {sorted(MODELS)}")
    need(isinstance(cfg.get("alphas"), list) and cfg["alphas"]
         and all(num(a) and 1e-3 <= a <= 1.0 for a in cfg["alphas"]), "alphas",
         "a non-empty list of roughnesses in [0.001, 1]")
    need(nums(cfg.get("diffuse"), 3) and all(0 <= v <= 1 for v in cfg["diffuse"]), "diffuse",
         "3 numbers in [0, 1]")
    need(num(cfg.get("specular")) and 0 <= cfg["specular"] <= 1, "specular", "a number in [0, 1]")
    need(isinstance(cfg.get("tile"), int) and cfg["tile"] >= 4, "tile", "an integer ≥ 4 (pixels)")
    need(num(cfg.get("spacing")) and cfg["spacing"] > 2.0, "spacing",
         "a number > 2 (the spheres have radius 1)")
    need(nums(cfg.get("light_direction"), 3) and any(cfg["light_direction"]), "light_direction",
         "3 numbers, not all 0")
    need(nums(cfg.get("irradiance"), 3), "irradiance", "3 numbers")
    need(nums(cfg.get("background"), 3), "background", "3 numbers")
    need(num(cfg.get("exposure")), "exposure", "a number (stops)")
    return cfg


def gallery_scene(cfg):
    """The scene (spheres of radius 1 on a grid in the plane z = 0, row 0 at the top)
    and an orthographic camera framing it."""
    models, alphas, spacing = cfg["models"], cfg["alphas"], float(cfg["spacing"])
    rows, cols = len(models), len(alphas)
    materials, spheres = [], []
    for r, name in enumerate(models):
        for c, alpha in enumerate(alphas):
            materials.append(MODELS[name][1](float(alpha), cfg["diffuse"], float(cfg["specular"])))
            # The camera looks along +z with +y up, so +x is on the left of the image.
            centre = (-(c - (cols - 1) / 2) * spacing, -(r - (rows - 1) / 2) * spacing, 0.0)
            spheres.append(jr.sdf.Translate(jr.sdf.Sphere(1.0, material=len(materials) - 1),
                                            offset=centre))
    scene = jr.Scene(surface=jr.sdf.Union(*spheres), materials=materials,
                     lights=[jr.DirectionalLight(cfg["light_direction"], cfg["irradiance"])],
                     background=cfg["background"])
    tile = int(cfg["tile"])
    camera = jr.OrthographicCamera(eye=(0.0, 0.0, -10.0), target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0),
                                   size=rows * spacing / 2.0, width=cols * tile, height=rows * tile)
    return scene, camera


def labeled(path, rgb, cfg):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows, cols, tile = len(cfg["models"]), len(cfg["alphas"]), int(cfg["tile"])
    x = np.clip(np.nan_to_num(rgb * 2.0 ** cfg["exposure"]), 0.0, 1.0)
    scale = max(tile, 48) / 48.0
    fig, ax = plt.subplots(figsize=(1.2 * cols * scale + 2.2, 1.2 * rows * scale + 0.6))
    ax.imshow(jr.io.srgb_encode(x).clip(0, 1), interpolation="nearest")
    ax.set_xticks([(c + 0.5) * tile for c in range(cols)],
                  [f"α = {a:g}" for a in cfg["alphas"]])
    ax.set_yticks([(r + 0.5) * tile for r in range(rows)],
                  [MODELS[m][0] for m in cfg["models"]])
    ax.tick_params(length=0)
    ax.xaxis.tick_top()
    for s in ax.spines.values():
        s.set_visible(False)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def run(cfg, out):
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    scene, camera = gallery_scene(cfg)
    # backend "jax", batch_size=None: one vmap over all rays compiles faster than tiles
    # (or a lane kernel of every BRDF model at once) at these sizes.
    settings = jr.RenderSettings(max_steps=96, shadows="none", batch_size=None, backend="jax")
    t0 = time.perf_counter()
    image = jr.render(scene, camera, settings)
    rgb = np.asarray(image.rgb)
    seconds = time.perf_counter() - t0
    jr.io.write_exr(out / "gallery.exr", image)
    jr.io.write_png(out / "gallery.png", rgb, exposure=cfg["exposure"])
    labeled(out / "gallery_labeled.png", rgb, cfg)
    (out / "config.json").write_text(json.dumps(cfg, indent=2))
    print(f"{len(cfg['models'])} models x {len(cfg['alphas'])} roughnesses "
          f"({len(scene.materials)} materials in one scene), {camera.width}x{camera.height} px, "
          f"rendered (with compilation) in {seconds:.1f} s")
    print(f"wrote {out}/gallery.exr, gallery.png, gallery_labeled.png")
    return rgb


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default=str(DEFAULT_CONFIG))
    parser.add_argument("--out", default=None, help=f"output folder (default out/{NAME})")
    parser.add_argument("--quick", action="store_true", help="the config's [quick] values")
    args = parser.parse_args(argv)
    cfg = load_config(args.config, quick=args.quick)
    return run(cfg, Path(args.out) if args.out else ROOT / "out" / NAME)


if __name__ == "__main__":
    main()
