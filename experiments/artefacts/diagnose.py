"""Quick diagnosis of the showcase without the full integrator (cheap compile):
primary hits (exhausted, holes vs 8x steps), and shadow visibility of both lights at hits.
python experiments/artefacts/diagnose.py W H"""
import sys, time
import numpy as np
import jax, jax.numpy as jnp
import jaxrt as jr
from jaxrt import config, artefacts
from jaxrt.integrator import intersect_scene, spawn_offset, spawn_origin, visibility
from jaxrt.trace import hit_epsilon
from jaxrt.render import _cast

w, h = int(sys.argv[1]), int(sys.argv[2])
path = sys.argv[3] if len(sys.argv) > 3 else "jaxrt/data/showcase.toml"
scene, camera, settings = config.load(path, width=w, height=h, spp=1)
scene = _cast(scene, jnp.dtype("float32"))
px, py = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
px, py = jnp.asarray(px.ravel(), jnp.float32), jnp.asarray(py.ravel(), jnp.float32)

def make(settings):
    def one(px, py):
        o, d, cone = camera.generate_ray(px, py)
        hit = intersect_scene(scene, o, d, settings, cone=cone)
        p = o + hit.t * d
        n = jnp.where(jnp.dot(hit.normal, d) <= 0, hit.normal, -hit.normal)
        off = spawn_offset(p, settings, hit_epsilon(settings, hit.t, cone))
        start = spawn_origin(scene, hit.surface, p, n, off, jnp.where(jnp.dot(hit.normal, d) <= 0, 1.0, -1.0), steps=settings.spawn_steps)
        vis = []
        for light in (scene.lights if settings.shadows != "none" else []):
            wi, dist, _ = light.illuminate(p)
            lit = hit.hit & (jnp.dot(wi, n) > 0)
            v = visibility(scene, start, wi, jnp.where(lit, dist, 0.0), settings)
            vis.append(jnp.where(lit, v, -1.0))
        return hit.t, hit.hit, hit.steps, jnp.stack(vis) if vis else jnp.zeros(1), hit.material
    return jax.jit(jax.vmap(one))

t0 = time.time()
settings = settings.replace(shadows=sys.argv[4]) if len(sys.argv) > 4 else settings
t, hit, steps, vis, mat = map(np.asarray, make(settings)(px, py))
t1 = time.time()
print("compile+run", t1 - t0, flush=True)
hit2 = hit.reshape(h, w)
ref = make(settings.replace(max_steps=settings.max_steps * 8, shadows="none"))(px, py)
rhit = np.asarray(ref[1]).reshape(h, w)
print("ref", time.time() - t1, flush=True)
ex = steps.reshape(h, w) > settings.max_steps
print("exhausted hit", int((ex & hit2).sum()), "exhausted miss", int((ex & ~hit2).sum()))
print("holes", int(artefacts.hole_pixels(hit2, rhit).sum()), "candidates", int(artefacts.outline_candidates(hit2).sum()), "hit!=ref", int((hit2 != rhit).sum()))
print("  holes at", np.argwhere(artefacts.hole_pixels(hit2, rhit))[:40].tolist())
vis = vis.reshape(h, w, -1)
# "speckle" proxy: a lit-facing pixel fully shadowed by a light (v==0) while >=6 of 8 hit neighbours see it (v>0.5)
for k in range(vis.shape[-1]):
    v = vis[..., k]
    nb = artefacts._neighbours(v, artefacts._EIGHT, -1.0)
    lit_nb = (nb > 0.5).sum(0)
    acne = (v == 0.0) & (lit_nb >= 6)
    print("light", k, "isolated shadowed", int(acne.sum()), np.argwhere(acne)[:30].tolist(), "materials", mat.reshape(h, w)[acne].tolist()[:30])
np.savez(f"/tmp/diag_{w}x{h}.npz", t=t, hit=hit, steps=steps, vis=vis, mat=mat, rhit=rhit)
