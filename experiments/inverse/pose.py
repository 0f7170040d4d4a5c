"""Study 5, pose: a camera's position and orientation recovered from one image of a
known scene (the CSG shape of study 1 on a floor). Targets: rotation within 0.5°,
position within 1 % of the camera's distance to what it looks at.

The camera is (eye, target) with a fixed up vector and field of view; moving the
target along the line of sight does not change the image, so the orientation is
measured as the angle of the rotation between the fitted and the true camera frames.

    python experiments/inverse/pose.py [--quick] [--size N] [--steps S]
        [--config configs/experiments/inverse_pose.toml] [--out results/inverse/pose]
"""

import sys
from pathlib import Path

import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common  # noqa: E402
import csg  # noqa: E402

import jaxrt as jr  # noqa: E402
from jaxrt import sdf  # noqa: E402

NAME = "pose"


def frame(eye, target, up):
    """[3, 3] rows u (right), v (up), w (forward) of a camera (as `PerspectiveCamera.frame`)."""
    w = np.asarray(target, float) - np.asarray(eye, float)
    w /= np.linalg.norm(w)
    u = np.cross(w, up)
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(u, w), w])


def rotation_deg(a, b):
    """Angle (degrees) of the rotation taking frame `a` to frame `b`."""
    c = (np.trace(a @ b.T) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def make_study(cfg):
    r, c = cfg["run"], cfg["camera"]
    up = np.asarray(c["up"], float)
    truth = {"eye": jnp.asarray(c["eye"], float), "target": jnp.asarray(c["target"], float)}
    lights = [jr.PointLight(l["position"], l["intensity"]) for l in cfg["lights"]]
    p = csg.TRUTH
    materials = [jr.bsdf.Lambert(p["albedo"]),
                 jr.bsdf.CookTorrance(jr.bsdf.GGX(p["alpha"]), jr.bsdf.SchlickFresnel(p["f0"]),
                                      diffuse=p["diffuse"]),
                 jr.bsdf.Lambert(cfg["floor_albedo"])]
    floor = sdf.Displace(sdf.Plane((0.0, 1.0, 0.0), cfg["floor_height"], material=2),
                         sdf.SineDisplacement(cfg["floor_frequency"]), cfg["floor_amplitude"])
    scene = jr.Scene(sdf.Union(csg.shape(p), floor), materials, lights, background=cfg["background"])

    def build(q):
        camera = jr.PerspectiveCamera(q["eye"], q["target"], up, c["fov"], r["size"], r["size"])
        return scene, jr.stack_cameras([camera])

    distance = float(np.linalg.norm(np.asarray(c["eye"]) - np.asarray(c["target"])))

    def metrics(q, t):
        return {"rotation_deg": rotation_deg(frame(q["eye"], q["target"], up), frame(t["eye"], t["target"], up)),
                "position_relative": float(np.linalg.norm(np.asarray(q["eye"]) - np.asarray(t["eye"])) / distance)}

    f = cfg["fit"]
    floors = {"eye": distance, "target": f["target_floor"]}
    rates = {"eye": f["eye_rate"], "target": f["target_rate"]}
    return common.Study(NAME, truth, build, {"eye": None, "target": None}, floors, rates, metrics)


def main(argv=None):
    cfg, out, args = common.parse_args(NAME, argv, __doc__)
    cfg["run"]["views"] = 1
    return common.run(make_study(cfg), cfg, out, fresh=args.fresh)


if __name__ == "__main__":
    main()
