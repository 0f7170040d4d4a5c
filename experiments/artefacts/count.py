"""Count NaN / speckle / hole pixels on the shipped scenes (issue 14).
python experiments/artefacts/count.py [W H] [scene...]"""
import sys, time
import numpy as np
import jax
import jaxrt as jr
from jaxrt import config, artefacts

args = sys.argv[1:]
w, h = (int(args[0]), int(args[1])) if len(args) >= 2 and args[0].isdigit() else (96, 54)
scenes = [a for a in args if not a.isdigit()] or ["jaxrt/data/showcase.toml", "configs/scenes/glass_spheres.toml", "configs/scenes/warp_raymarch.toml"]
for path in scenes:
    scene, camera, settings = config.load(path, width=w, height=h, spp=1)
    settings = settings.replace(backend="jax", aovs=("depth", "steps")) if hasattr(settings, "replace") else settings
    t0 = time.time()
    img = jr.render(scene, camera, settings)
    jax.block_until_ready(img.rgb)
    t1 = time.time()
    import os
    ref_settings = settings.replace(max_steps=settings.max_steps * 8)
    ref = img if os.environ.get("NO_REF") else jr.render(scene, camera, ref_settings)
    jax.block_until_ready(ref.rgb)
    t2 = time.time()
    c = artefacts.counts(img, settings.max_distance, ref)
    steps = np.asarray(img.steps)
    hit = artefacts.hit_mask(img.depth, settings.max_distance)
    c["exhausted_hit"] = int(((steps > settings.max_steps) & hit).sum())
    c["exhausted_miss"] = int(((steps > settings.max_steps) & ~hit).sum())
    c["ref_holes_vs_self"] = artefacts.counts(ref, settings.max_distance, ref)["holes"]
    print(path, w, h, c, f"render {t1-t0:.0f}s ref {t2-t1:.0f}s", flush=True)
    sp = np.argwhere(artefacts.speckle_pixels(img.rgb, hit))
    ho = np.argwhere(artefacts.hole_pixels(hit, artefacts.hit_mask(ref.depth, settings.max_distance)))
    print("  speckles at", sp[:30].tolist()); print("  holes at", ho[:30].tolist(), flush=True)
    np.savez(f"/tmp/art_{path.split('/')[-1]}_{w}x{h}.npz", rgb=np.asarray(img.rgb), depth=np.asarray(img.depth), steps=steps, ref_depth=np.asarray(ref.depth), ref_rgb=np.asarray(ref.rgb))
