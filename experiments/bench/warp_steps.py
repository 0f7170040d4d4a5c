"""Step-count model of the Warp scene: how many march steps a GPU warp pays per ray.

A warp runs until its slowest ray is done, so the work of a tile is the maximum of
its rays' steps (primary march + soft-shadow march). This script counts them on the
CPU for jaxrt's Pallas tiles (4×8 pixels; jaxrt's own march, "fast" dials, and a
shadow march with jaxrt's start and minimum step) and for the hand-written CUDA
kernel's warps (32 consecutive pixels of a row; its own march and shadow loop,
re-implemented here from ../shared/bench/warp_scene_cuda.py), and the share of the
work in each half of the image (what a two-device split into bands sees).

    python experiments/bench/warp_steps.py [--width 1024 --height 512]
"""

import argparse
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxrt as jr

ROOT = Path(__file__).resolve().parents[2]
LIGHT = np.array([0.6, 0.4, 0.5]) / np.linalg.norm([0.6, 0.4, 0.5])


def warp_sdf(p):
    x, y, z = p
    ds = jnp.sqrt(x * x + (y - 0.75) ** 2 + z * z) - 0.75
    ax, ay, az = jnp.abs(x) - 1.0, jnp.abs(y) - 0.5, jnp.abs(z) - 0.5
    db = jnp.sqrt(jnp.maximum(ax, 0) ** 2 + jnp.maximum(ay, 0) ** 2 + jnp.maximum(az, 0) ** 2) \
        + jnp.minimum(jnp.maximum(ax, jnp.maximum(ay, az)), 0.0)
    return jnp.minimum(jnp.maximum(-ds, db), y + 1.0)


def shadow_steps(p, min_step, t0):
    """Steps of the CUDA kernel's soft shadow (early exit when the factor < 1e-3)."""
    def cond(s):
        t, v, i, done = s
        return (i < 64) & ~done

    def body(s):
        t, v, i, _ = s
        d = warp_sdf(p + LIGHT * t)
        t = t + jnp.clip(d, min_step, 2.0)
        h = jnp.clip(4.0 * d / t, 0.0, 1.0)
        v = jnp.minimum(v, h * h * (3.0 - 2.0 * h))
        return t, v, i + 1, (t > 8.0) | (v < 1e-3)

    return jax.lax.while_loop(cond, body, (t0, 1.0, 0, False))[2]


def cuda_steps(width, height):
    """Primary and shadow steps of the CUDA kernel ('early'), [H, W] each."""
    def quat_rpy(roll, pitch, yaw):
        cy, sy = np.cos(yaw / 2), np.sin(yaw / 2)
        cr, sr = np.cos(roll / 2), np.sin(roll / 2)
        cp, sp = np.cos(pitch / 2), np.sin(pitch / 2)
        return (cy * sr * cp - sy * cr * sp, cy * cr * sp + sy * sr * cp,
                sy * cr * cp - cy * sr * sp, cy * cr * cp + sy * sr * sp)

    qx, qy, qz, qw = quat_rpy(-0.5, -0.5, 0.0)
    q, ro = jnp.array([qx, qy, qz]), jnp.array([-1.25, 1.0, 2.0])

    def one(x, y):
        v = jnp.array([(2 * x - width) / height, (2 * y - height) / height, -2.0])
        v = v / jnp.linalg.norm(v)
        rd = v * (2 * qw * qw - 1) + jnp.cross(q, v) * qw * 2 + q * jnp.dot(q, v) * 2

        def cond(s):
            t, d, i = s
            return (i < 128) & ~((d < 1e-3 * t) | (t > 20.0))

        def body(s):
            t, d, i = s
            t = t + d
            return t, warp_sdf(ro + rd * t), i + 1

        t, d, i = jax.lax.while_loop(cond, body, (0.0, warp_sdf(ro), 0))
        s = jnp.where(d < 0.01, shadow_steps(ro + rd * t, 1e-4, 0.0), 0)
        return i, s

    ys, xs = jnp.meshgrid(jnp.arange(height, dtype=jnp.float32),
                          jnp.arange(width, dtype=jnp.float32), indexing="ij")
    i, s = jax.jit(jax.vmap(one))(xs.ravel(), ys.ravel())
    return np.asarray(i).reshape(height, width), np.asarray(s).reshape(height, width)


def jaxrt_steps(width, height):
    """Primary steps of jaxrt's march ("fast" dials) and shadow steps of the same
    soft-shadow loop started as jaxrt starts it (spawn offset, minimum step ε)."""
    scene, camera, base = jr.config.load(ROOT / "configs/scenes/warp_raymarch.toml",
                                         width=width, height=height)
    settings = base.replace(hit_epsilon=1e-5, pixel_epsilon=2.0, newton_steps=1,
                            shadows="none", batch_size=8192)
    img = jr.render(scene, camera, settings)
    ys, xs = jnp.meshgrid(jnp.arange(height) + 0.5, jnp.arange(width) + 0.5, indexing="ij")
    o, d, cone = jax.vmap(camera.generate_ray)(xs.ravel().astype(jnp.float32),
                                               ys.ravel().astype(jnp.float32))
    t = img.depth.reshape(-1)
    p = o + d * t[:, None]
    eps = settings.hit_epsilon + settings.pixel_epsilon * (cone[:, 0] + cone[:, 1] * t)
    p = p + img.normal.reshape(-1, 3) * (settings.ray_offset * eps)[:, None]
    s = jax.jit(jax.vmap(lambda x: shadow_steps(x, settings.hit_epsilon, settings.hit_epsilon)))(p)
    s = np.where(np.asarray(img.coverage).reshape(-1) > 0, np.asarray(s), 0)
    return np.asarray(img.steps), s.reshape(height, width)


def tile_max(a, th, tw):
    h, w = a.shape
    return a.reshape(h // th, th, w // tw, tw).max(axis=(1, 3))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--width", type=int, default=1024)
    ap.add_argument("--height", type=int, default=512)
    args = ap.parse_args(argv)
    for name, (prim, shad), tile in (("jaxrt, 4x8 tiles", jaxrt_steps(args.width, args.height), (4, 8)),
                                     ("CUDA, warps of 32 pixels of a row",
                                      cuda_steps(args.width, args.height), (1, 32))):
        work = tile_max(prim + shad, *tile).astype(float)
        h, w = work.shape
        print(f"{name}: mean steps per ray primary {prim.mean():.1f}, shadow {shad.mean():.1f}; "
              f"per-tile maximum (what a warp pays) {tile_max(prim, *tile).mean():.1f} + "
              f"{tile_max(shad, *tile).mean():.1f} = {work.mean():.1f}; work in the top half "
              f"{work[:h // 2].sum() / work.sum():.1%}, left half {work[:, :w // 2].sum() / work.sum():.1%}")


if __name__ == "__main__":
    main()
