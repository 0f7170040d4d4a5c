"""The showcase trimmed to its floor and orange cone: speckles and their diagnosis."""
import re, sys, time
import numpy as np
import jax, jax.numpy as jnp
import jaxrt as jr
from jaxrt import config, artefacts

text = open("jaxrt/data/showcase.toml").read()
head, rest = text.split("[surface]", 1)
children = rest.split("[[surface.children]]")
keep = [c for c in children[1:] if 'type = "plane"' in c or 'type = "cone"' in c]
text = head + "[surface]" + children[0] + "".join("[[surface.children]]" + c for c in keep)
w, h = int(sys.argv[1]), int(sys.argv[2])
scene, camera, settings = config.loads(text, width=w, height=h, spp=1)
settings = settings.replace(backend="jax", aovs=("depth", "steps", "normal"))
t0 = time.time()
img = jr.render(scene, camera, settings)
hit = artefacts.hit_mask(img.depth, settings.max_distance)
sp = artefacts.speckle_pixels(img.rgb, hit)
print("render", time.time() - t0, "nan", int(artefacts.nan_pixels(img.rgb).sum()), "speckles", int(sp.sum()), np.argwhere(sp).tolist()[:20], flush=True)
o, d = [], []
for y, x in np.argwhere(sp):
    o_, d_, _ = camera.generate_ray(jnp.float32(x + 0.5), jnp.float32(y + 0.5))
    print(" px", y, x, "steps", float(img.steps[y, x]), "depth", float(img.depth[y, x]), "normal", np.asarray(img.normal[y, x]).round(3), "n.d", float(jnp.dot(img.normal[y, x], d_)), "rgb", np.asarray(img.rgb[y, x]).round(3))
np.savez(f"/tmp/cone_{w}x{h}.npz", rgb=np.asarray(img.rgb), depth=np.asarray(img.depth), steps=np.asarray(img.steps), normal=np.asarray(img.normal))
