"""The CSG study's boundary-gradient check (docs/inverse.md, "why it does not converge"):
at the escaped point of the full run (arm half-height 0.52, centre 0.47 high), the
debiased loss's gradient against central differences (h = 0.01) of the box-filtered
loss: with `silhouette_gradient = "ramp"` (plain, and with the residual blurred by a
5-tap tent before it weights the gradient) and with "outline" (the study's setting).
Quick settings, 12 views.

    python experiments/inverse/boundary_gradient.py [--size 40] [--capsule]
"""

import argparse
import sys
from pathlib import Path

import jax
import jax.numpy as jnp

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common  # noqa: E402
import csg  # noqa: E402

import jaxrt as jr  # noqa: E402

KEYS = [("arm_half_height", ()), ("arm_offset", 1), ("arm_offset", 0), ("arm_radius", ())]


def blur(r, taps):
    """r [V, H, W, 3] convolved along H and W with the normalised `taps`."""
    k = jnp.asarray(taps, r.dtype) / sum(taps)
    for axis in (1, 2):
        r = jnp.apply_along_axis(lambda v: jnp.convolve(v, k, mode="same"), axis, r)
    return r


def main(argv=None):
    a = argparse.ArgumentParser(description=__doc__)
    a.add_argument("--size", type=int, default=40)
    a.add_argument("--capsule", action="store_true", help="the arm capsule alone")
    args = a.parse_args(argv)
    cfg = common.load_config(common.ROOT / "configs" / "experiments" / "inverse_csg.toml", quick=True)
    cfg["run"].update(size=args.size, views=12)
    study = csg.make_study(cfg)
    if args.capsule:
        full = study.build

        def build(p):
            scene, cameras = full(p)
            arm = csg.sdf.Translate(csg.sdf.Capsule(p["arm_half_height"], p["arm_radius"], material=1), p["arm_offset"])
            return jr.Scene(arm, scene.materials, scene.lights, background=cfg["background"]), cameras
        study = study._replace(build=build)
    ts = common.settings(cfg, "target_settings").replace(spp=16)
    fs = common.settings(cfg, "fit_settings")
    targets = jr.render_views(*study.build(study.truth), ts).rgb
    p0 = dict(study.truth)
    p0["arm_half_height"] = jnp.asarray(0.52)
    p0["arm_offset"] = p0["arm_offset"].at[1].set(0.47)

    def debiased(taps, mode):
        def loss(p):
            scene, cameras = study.build(p)
            image = jr.render_views(scene, cameras, fs.replace(silhouette_gradient=mode)).rgb
            r = jax.lax.stop_gradient(jr.render_views(scene, cameras, ts).rgb) - targets
            weight = jax.lax.stop_gradient(2.0 * (blur(r, taps) if taps else r))
            return jnp.mean(r * r) + jnp.mean(weight * (image - jax.lax.stop_gradient(image)))
        return loss

    def pick(g, k, i):
        return float(g[k][i]) if g[k].ndim else float(g[k])

    print("                " + " ".join((k if i == () else f"{k}[{i}]").rjust(18) for k, i in KEYS))
    for name, taps, mode in (("ramp", None, "ramp"), ("ramp, tent 5", (1, 2, 3, 2, 1), "ramp"),
                             ("outline", None, "outline")):
        g = jax.grad(debiased(taps, mode))(p0)
        print(f"{name:16s}" + " ".join(f"{pick(g, k, i):+18.3e}" for k, i in KEYS), flush=True)
    box = jax.jit(lambda p: jr.fit.l2_loss(jr.render_views(*study.build(p), ts).rgb, targets))
    h, fd = 0.01, []
    for k, i in KEYS:
        def at(s):
            p = dict(p0)
            p[k] = p[k].at[i].add(s * h) if p[k].ndim else p[k] + s * h
            return float(box(p))
        fd.append((at(1) - at(-1)) / (2 * h))
    print(f"{'FD, box filter':16s}" + " ".join(f"{v:+18.3e}" for v in fd))


if __name__ == "__main__":
    main()
