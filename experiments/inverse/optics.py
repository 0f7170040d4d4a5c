"""Study 4, optics: the index of refraction of a glass sphere — a constant η, or the
Cauchy coefficients n(λ) = a + b/λ² with spectral rendering — from images of a textured
background seen through it (a sine-displaced wall lit from the side, whose shading
varies smoothly, so the refracted image moves smoothly with η). Target: η at the
d line within 1e-3.

    python experiments/inverse/optics.py [--quick] [--size N] [--views V] [--steps S]
        [--config configs/experiments/inverse_optics.toml] [--out results/inverse/optics]
"""

import sys
from pathlib import Path

import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common  # noqa: E402

import jaxrt as jr  # noqa: E402
from jaxrt import sdf  # noqa: E402
from jaxrt.fit import ABOVE_ONE, LOG  # noqa: E402
from jaxrt.spectral import FRAUNHOFER, Cauchy  # noqa: E402

NAME = "optics"


def make_study(cfg):
    r, c, o = cfg["run"], cfg["camera"], cfg["optics"]
    cameras = jr.orbit(r["views"], target=c["target"], distance=c["distance"], elevation=c["elevation"],
                       azimuth=c.get("azimuth", 0.0), fov=c["fov"], width=r["size"], height=r["size"],
                       turns=c["spread"] / 360.0)
    wall = sdf.Displace(sdf.Plane((0.0, 0.0, -1.0), o["wall_distance"], material=1),
                        sdf.SineDisplacement(o["wall_frequency"]), o["wall_amplitude"])
    lights = [jr.PointLight(l["position"], l["intensity"]) for l in cfg["lights"]]
    dispersive = o["model"] == "cauchy"
    truth = {"a": jnp.asarray(o["a"]), "b": jnp.asarray(o["b"])} if dispersive else \
        {"eta": jnp.asarray(o["eta"])}

    def build(p):
        eta = Cauchy(p["a"], p["b"]) if dispersive else p["eta"]
        scene = jr.Scene(sdf.Union(sdf.Sphere(o["radius"], material=0), wall),
                         [jr.bsdf.Dielectric(eta), jr.bsdf.Lambert(o["wall_albedo"])], lights,
                         background=cfg["background"])
        return scene, cameras

    lam = FRAUNHOFER["d"]

    def n_d(p):
        return float(Cauchy(p["a"], p["b"])(lam)) if dispersive else float(p["eta"])

    def metrics(p, t):
        out = {"eta_d_error": abs(n_d(p) - n_d(t))}
        if dispersive:
            out["b_relative_error"] = abs(float(p["b"]) - float(t["b"])) / float(t["b"])
        return out

    transforms = {"a": ABOVE_ONE, "b": LOG} if dispersive else {"eta": ABOVE_ONE}
    return common.Study(NAME, truth, build, transforms, {}, {"b": cfg["fit"].get("b_rate", 1.0)}
                        if dispersive else {}, metrics)


def main(argv=None):
    cfg, out, args = common.parse_args(NAME, argv, __doc__)
    return common.run(make_study(cfg), cfg, out, fresh=args.fresh)


if __name__ == "__main__":
    main()
