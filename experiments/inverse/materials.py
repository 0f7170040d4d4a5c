"""Study 3, materials under known geometry: per-object reflectance (a Lambert albedo,
GGX roughness with Schlick f0 over a diffuse base, a rough conductor's η and κ), a
spatially varying albedo (per-primitive floor tiles), and the lights' intensities, from
≥ 4 views. Target: every parameter within 2 %.

One floor tile is a grey card of known albedo: without it image = intensity ×
reflectance leaves their common scale unobservable.

    python experiments/inverse/materials.py [--quick] [--size N] [--views V] [--steps S]
        [--config configs/experiments/inverse_materials.toml] [--out results/inverse/materials]
"""

import sys
from pathlib import Path

import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common  # noqa: E402

import jaxrt as jr  # noqa: E402
from jaxrt import sdf  # noqa: E402
from jaxrt.fit import LOG, UNIT  # noqa: E402

NAME = "materials"


def make_study(cfg):
    r, c, g = cfg["run"], cfg["camera"], cfg["geometry"]
    cameras = jr.orbit(r["views"], target=c["target"], distance=c["distance"],
                       elevation=np.resize(c["elevations"], r["views"]), azimuth=c.get("azimuth", 0.0),
                       fov=c["fov"], width=r["size"], height=r["size"], turns=c.get("spread", 360.0) / 360.0)
    m = cfg["truth"]
    truth = {k: jnp.asarray(v, float) for k, v in m.items()}
    tiles = np.asarray(g["tile_centres"], float)
    spheres = np.asarray(g["sphere_centres"], float)
    h = g["tile_half_extents"]

    # materials: 0 Lambert sphere, 1 GGX plastic-like, 2 rough conductor, 3 grey card,
    # 4.. free tiles
    shapes = [sdf.Translate(sdf.Sphere(g["sphere_radius"], material=i), spheres[i]) for i in range(3)]
    shapes += [sdf.Translate(sdf.Box(h, material=3 + i), tiles[i]) for i in range(len(tiles))]
    surface = sdf.Union(*shapes)

    def build(p):
        materials = [
            jr.bsdf.Lambert(p["lambert_albedo"]),
            jr.bsdf.CookTorrance(jr.bsdf.GGX(p["ggx_alpha"]), jr.bsdf.SchlickFresnel(p["ggx_f0"]),
                                 diffuse=p["ggx_diffuse"]),
            jr.bsdf.CookTorrance(jr.bsdf.GGX(p["metal_alpha"]),
                                 jr.bsdf.ConductorFresnel(p["metal_eta"], p["metal_k"])),
            jr.bsdf.Lambert(g["grey_card"]),
        ] + [jr.bsdf.Lambert(p["tile_albedo"][i]) for i in range(p["tile_albedo"].shape[0])]
        lights = [jr.PointLight(pos, p["light_intensity"][i]) for i, pos in enumerate(g["light_positions"])]
        return jr.Scene(surface, materials, lights, background=cfg["background"]), cameras

    transforms = {k: LOG if k in ("metal_eta", "metal_k", "light_intensity") else UNIT for k in truth}
    rates = cfg["fit"].get("rates", {})
    return common.Study(NAME, truth, build, transforms, {}, rates)


def main(argv=None):
    cfg, out, args = common.parse_args(NAME, argv, __doc__)
    return common.run(make_study(cfg), cfg, out, fresh=args.fresh)


if __name__ == "__main__":
    main()
