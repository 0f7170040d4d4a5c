"""Count NaN, speckle and hole pixels (`jaxrt.artefacts`) in the shipped scenes (issue 14).

Each scene renders with backend "jax" (the cheapest compile) and again with 8× the step
budget, the reference that tells a hole from a real gap:

    python experiments/artefacts/count.py [W H] [SCENE.toml ...]
"""

import sys
import time

import jax
import numpy as np

import jaxrt as jr
from jaxrt import artefacts, config

SCENES = ["jaxrt/data/showcase.toml", "configs/scenes/glass_spheres.toml",
          "configs/scenes/warp_raymarch.toml"]


def main(args):
    sized = len(args) >= 2 and args[0].isdigit()
    w, h = (int(args[0]), int(args[1])) if sized else (96, 54)
    for path in args[2 if sized else 0:] or SCENES:
        scene, camera, settings = config.load(path, width=w, height=h, spp=1)
        settings = settings.replace(backend="jax", aovs=("depth", "steps"))
        start = time.perf_counter()
        img = jr.render(scene, camera, settings)
        ref = jr.render(scene, camera, settings.replace(max_steps=settings.max_steps * 8))
        jax.block_until_ready((img.rgb, ref.rgb))
        seconds = time.perf_counter() - start
        counts = artefacts.counts(img, settings.max_distance, ref)
        hit = artefacts.hit_mask(img.depth, settings.max_distance)
        exhausted = np.asarray(img.steps) > settings.max_steps
        counts["exhausted hits"] = int((exhausted & hit).sum())
        counts["exhausted misses"] = int((exhausted & ~hit).sum())
        print(f"{path} {w}×{h}: {counts} ({seconds:.0f} s)")
        print("  speckles at", np.argwhere(artefacts.speckle_pixels(img.rgb, hit))[:30].tolist())


if __name__ == "__main__":
    main(sys.argv[1:])
