"""Study 1, CSG recovery: a shape of 8 primitives (smooth blends, placements, two
materials) recovered from ≥ 8 views, every shape and material parameter free, started
with each perturbed by up to 10 % (fixed seed). Target: every parameter within 1 %.

    python experiments/inverse/csg.py [--quick] [--size N] [--views V] [--steps S]
        [--config configs/experiments/inverse_csg.toml] [--out results/inverse/csg]

Writes under the output folder what `experiments/inverse/common.py` lists.
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

NAME = "csg"

#: The true shape: name → value. Sizes and blend widths are positive (exp transform),
#: offsets free, reflectances in (0, 1) (logistic).
TRUTH = {
    "body_half_extents": [0.55, 0.22, 0.38], "body_radius": 0.08, "body_offset": [0.0, -0.1, 0.0],
    "dome_radius": 0.34, "dome_offset": [0.08, 0.18, 0.02],
    "arm_half_height": 0.3, "arm_radius": 0.11, "arm_offset": [-0.5, 0.25, 0.08],
    "post_radius": 0.13, "post_half_height": 0.3, "post_offset": [0.48, 0.1, 0.12],
    "ring_major_radius": 0.3, "ring_minor_radius": 0.09, "ring_angle": 70.0,
    "ring_offset": [0.0, 0.05, -0.45],
    "egg_radii": [0.22, 0.14, 0.17], "egg_offset": [-0.42, -0.3, -0.25],
    "cube_half_extents": [0.13, 0.13, 0.13], "cube_offset": [0.45, -0.25, -0.28],
    "ball_radius": 0.16, "ball_offset": [-0.12, 0.05, 0.46],
    "blend_body": 0.12, "blend_arms": 0.1, "blend_all": 0.08,
    "albedo": [0.75, 0.45, 0.25],
    "alpha": 0.3, "f0": 0.08, "diffuse": [0.2, 0.35, 0.6],
}
TRUTH = {k: jnp.asarray(v) for k, v in TRUTH.items()}
POSITIVE_KEYS = [k for k in TRUTH if k.endswith(("half_extents", "radius", "radii", "half_height"))
                 or k.startswith("blend")]
UNIT_KEYS = ["albedo", "alpha", "f0", "diffuse"]
OFFSET_KEYS = [k for k in TRUTH if k.endswith("offset")]


def shape(p):
    """The shape tree of parameters `p`: (body ∪ₖ dome) ∪ₖ (arm ∪ₖ post), ∪ ring, egg,
    cube, ball. Material 0 (Lambert) or 1 (GGX Cook–Torrance over a diffuse base)."""
    t = sdf.Translate
    body = sdf.SmoothUnion(t(sdf.RoundBox(p["body_half_extents"], p["body_radius"], material=0), p["body_offset"]),
                           t(sdf.Sphere(p["dome_radius"], material=1), p["dome_offset"]), p["blend_body"])
    # the arm and the post each stand on the body, so both blends shape a junction
    body = sdf.SmoothUnion(body, t(sdf.Capsule(p["arm_half_height"], p["arm_radius"], material=1),
                                   p["arm_offset"]), p["blend_arms"])
    post = t(sdf.Cylinder(p["post_radius"], p["post_half_height"], material=0), p["post_offset"])
    ring = t(sdf.Rotate(sdf.Torus(p["ring_major_radius"], p["ring_minor_radius"], material=1),
                        (1.0, 0.0, 0.0), p["ring_angle"]), p["ring_offset"])
    return sdf.Union(sdf.SmoothUnion(body, post, p["blend_all"]), ring,
                     t(sdf.Ellipsoid(p["egg_radii"], material=0), p["egg_offset"]),
                     t(sdf.Box(p["cube_half_extents"], material=1), p["cube_offset"]),
                     t(sdf.Sphere(p["ball_radius"], material=0), p["ball_offset"]))


def make_study(cfg):
    r, c = cfg["run"], cfg["camera"]
    cameras = jr.orbit(r["views"], target=c["target"], distance=c["distance"], elevation=np.resize(c["elevations"], r["views"]),
                       azimuth=c.get("azimuth", 0.0), fov=c["fov"], width=r["size"], height=r["size"])
    lights = [jr.PointLight(l["position"], l["intensity"]) for l in cfg["lights"]]

    def build(p):
        materials = [jr.bsdf.Lambert(p["albedo"]),
                     jr.bsdf.CookTorrance(jr.bsdf.GGX(p["alpha"]), jr.bsdf.SchlickFresnel(p["f0"]),
                                          diffuse=p["diffuse"])]
        return jr.Scene(shape(p), materials, lights, background=cfg["background"]), cameras

    transforms = {k: LOG if k in POSITIVE_KEYS else UNIT if k in UNIT_KEYS else None for k in TRUTH}
    f = cfg["fit"]
    floors = {k: f["offset_floor"] for k in OFFSET_KEYS}
    rates = {k: f["offset_rate"] for k in OFFSET_KEYS} | {k: f["unit_rate"] for k in UNIT_KEYS}
    rates["ring_angle"] = f["angle_rate"]
    return common.Study(NAME, TRUTH, build, transforms, floors, rates)


def main(argv=None):
    cfg, out, args = common.parse_args(NAME, argv, __doc__)
    return common.run(make_study(cfg), cfg, out, fresh=args.fresh)


if __name__ == "__main__":
    main()
