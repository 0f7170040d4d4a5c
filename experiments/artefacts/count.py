"""Count NaN, speckle and hole pixels (`jaxrt.artefacts`) in the shipped scenes (issue 14).

Each scene renders with the scene file's own settings and backend (its "auto" is the
fused lanes on a CPU; a render that fell back to "jax" says so), then twice more: with
8× the step budget (the reference that tells a hole from a real gap) and with
shadows="none" (the reference that tells a speckle, darkened by its shadow rays, from
a pixel dark by its shading):

    python experiments/artefacts/count.py [W H] [SCENE.toml ...]

Every see-through pixel (out of budget, deeper than the 8×-steps reference) and every
dark outlier is listed as (row, column) with its luminance, its luminance
without shadows and the verdict (speckle or shading); trace one with
experiments/artefacts/trace_pixel.py SCENE W H COLUMN ROW.
"""

import sys
import time
import warnings

import jax
import numpy as np

import jaxrt as jr
from jaxrt import artefacts, config
from jaxrt.kernels.fused import resolve_backend

SCENES = ["jaxrt/data/showcase.toml", "configs/scenes/glass_spheres.toml",
          "configs/scenes/warp_raymarch.toml"]


def render(scene, camera, settings):
    """(Image, seconds, the backend's fall-back warning or None)."""
    start = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        image = jr.render(scene, camera, settings)
        jax.block_until_ready(image.rgb)
    fallback = [str(w.message) for w in caught if "backend=" in str(w.message)]
    return image, time.perf_counter() - start, (fallback or [None])[0]


def main(args):
    sized = len(args) >= 2 and args[0].isdigit()
    w, h = (int(args[0]), int(args[1])) if sized else (96, 54)
    for path in args[2 if sized else 0:] or SCENES:
        scene, camera, settings = config.load(path, width=w, height=h, spp=1)
        settings = settings.replace(aovs=("depth", "steps"))
        img, seconds, fallback = render(scene, camera, settings)
        ref, _, _ = render(scene, camera, settings.replace(max_steps=settings.max_steps * 8))
        flat, _, _ = render(scene, camera, settings.replace(shadows="none"))
        counts = artefacts.counts(img, settings.max_distance, ref, flat, settings.max_steps)
        hit = artefacts.hit_mask(img.depth, settings.max_distance)
        exhausted = np.asarray(img.steps) > settings.max_steps
        counts["exhausted hits"] = int((exhausted & hit).sum())
        counts["exhausted misses"] = int((exhausted & ~hit).sum())
        backend = (f"{settings.backend} fell back to jax ({fallback})" if fallback
                   else f"{settings.backend} ({resolve_backend(settings.backend)})")
        print(f"{path} {w}×{h}, backend {backend}: {counts} ({seconds:.0f} s)")
        lum, lum0 = artefacts.luminance(img.rgb), artefacts.luminance(flat.rgb)
        speckle = artefacts.speckle_pixels(img.rgb, hit, flat.rgb)
        seen = artefacts.see_through_pixels(img.depth, ref.depth, exhausted)
        for y, x in np.argwhere(seen).tolist():
            print(f"  see-through ({y}, {x}): depth {float(img.depth[y, x]):.4f}, "
                  f"{float(ref.depth[y, x]):.4f} with 8× the steps")
        for y, x in np.argwhere(artefacts.dark_outliers(img.rgb, hit)).tolist():
            verdict = "speckle" if speckle[y, x] else "shading"
            print(f"  dark outlier ({y}, {x}): Y = {lum[y, x]:.4f}, without shadows "
                  f"{lum0[y, x]:.4f}: {verdict}")


if __name__ == "__main__":
    main(sys.argv[1:])
