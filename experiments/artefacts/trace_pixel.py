"""Print the Whitted ray tree of one pixel of a scene file (issue 14's artefact hunt):

    python experiments/artefacts/trace_pixel.py SCENE.toml W H X Y [key=value ...]

For pixel (column X, row Y) of the scene rendered at W×H (1 spp, pixel centre), every
node of the tree is printed with its hit t, hit flag, steps used, surface and material,
normal, `inside` flag and weight; for every hit, each light's cos θi, BRDF value f,
shadow-ray visibility V and how the shadow march ended (hard: its hit t, steps and
`converging` flag; soft: t*, blocked, sign). The node's radiance is given with the
scene's shadows and with shadows = "none" (what the pixel would be without occlusion).
`key=value` override `RenderSettings` fields (e.g. max_steps=1280, max_depth=12);
`quiet=1` prints only the pixel's radiance, `min_weight=W` skips rays of smaller weight. The same functions
as the renderer (`integrator.shade_ray`, `lights.shadow_ray`) in float32 by default,
one ray at a time (backend "jax").
"""

import sys

import jax
import jax.numpy as jnp
import numpy as np

from jaxrt import config
from jaxrt.integrator import camera_ray, intersect_scene, ray_tree, shade_ray, spawn_offset, spawn_origin
from jaxrt.lights import shadow_ray
from jaxrt.march.shadow import SoftShadow, march as soft_march
from jaxrt.march.sphere import SphereTracing
from jaxrt.render import _cast, _dtype
from jaxrt.trace import hit_epsilon, sphere_trace
from jaxrt.vecmath import dot, to_local
from jaxrt.bsdf.dispatch import dispatch


def _fmt(x):
    x = np.asarray(x)
    if x.ndim == 0:
        return f"{x.item():.6g}" if x.dtype.kind == "f" else str(x.item())
    return "(" + ", ".join(f"{v:.5g}" for v in x.ravel()) + ")"


def trace(path, width, height, x, y, overrides=None, quiet=False, min_weight=0.0):
    scene, camera, settings = config.load(path, width=width, height=height, spp=1,
                                          settings=overrides or None)
    settings = settings.replace(backend="jax")
    say = (lambda *a: None) if quiet else print
    dtype = _dtype(settings)
    scene, camera = _cast((scene, camera), dtype)
    flat = settings.replace(shadows="none")
    tree = ray_tree(scene, settings)
    o, d, cone = camera.generate_ray(jnp.asarray(x + 0.5, dtype), jnp.asarray(y + 0.5, dtype))
    say(f"{path} {width}×{height} pixel ({x}, {y}); shadows={settings.shadows}, "
        f"max_steps={settings.max_steps}, shadow_steps={settings.shadow_steps}, "
        f"depth={tree.depth}, branches={tree.branches}")
    shade = jax.jit(lambda r, s: shade_ray(scene, r, s, tree, spawn=True), static_argnums=1)
    hit_of = jax.jit(lambda o, d, cone: intersect_scene(scene, o, d, settings, cone=cone))
    total, total_flat = np.zeros(3), np.zeros(3)

    def node(ray, label, level):
        nonlocal total, total_flat
        if not bool(ray.alive) or float(jnp.max(ray.weight)) < min_weight:
            return
        pad = "  " * level
        h = hit_of(ray.origin, ray.direction, ray.cone)
        out, out_flat = shade(ray, settings), shade(ray, flat)
        total += np.asarray(out.radiance)
        total_flat += np.asarray(out_flat.radiance)
        say(f"{pad}{label}: o={_fmt(ray.origin)} d={_fmt(ray.direction)} weight={_fmt(ray.weight)}")
        say(f"{pad}  hit={bool(h.hit)} t={_fmt(h.t)} steps={_fmt(h.steps)} surface={_fmt(h.surface)} "
            f"material={_fmt(h.material)} inside={bool(h.inside)} normal={_fmt(h.normal)}")
        say(f"{pad}  radiance={_fmt(out.radiance)}  (shadows=none: {_fmt(out_flat.radiance)})")
        if bool(h.hit) and tree.direct:
            lights(ray, h, pad)
        if level < tree.depth:
            for name in tree.branches:
                node(jax.tree_util.tree_map(lambda a: a, out.children[name]), name, level + 1)

    def lights(ray, h, pad):
        p = ray.origin + h.t * ray.direction
        n = jnp.where(dot(h.normal, ray.direction) <= 0.0, h.normal, -h.normal)
        entering = ~h.inside
        offset = spawn_offset(p, settings, hit_epsilon(settings, h.t, ray.cone))
        above = spawn_origin(scene, h.surface, p, n, offset, jnp.where(entering, 1.0, -1.0),
                             steps=settings.spawn_steps)
        f_above = scene.surface(above) / scene.surface.lipschitz()
        say(f"{pad}  p={_fmt(p)} f(p)={_fmt(scene.surface(p))} offset={_fmt(offset)} "
            f"shadow origin={_fmt(above)} f/L there={_fmt(f_above)}")
        wo_local = to_local(-ray.direction, n)
        for k, light in enumerate(scene.lights):
            wi, dist, irr = light.illuminate(p)
            cos_i = dot(wi, n)
            f = dispatch(scene.materials, h.material, lambda m: m.eval(wo_local, to_local(wi, n)),
                         jnp.zeros(3, dtype), lambda m: m.has_diffuse)
            v = shadow_ray(scene.surface, above, wi, dist, settings)
            t_max = jnp.minimum(dist, settings.shadow_max_distance or settings.max_distance)
            line = f"{pad}  light {k}: wi={_fmt(wi)} cos={_fmt(cos_i)} f={_fmt(f)} V={_fmt(v)}"
            if settings.shadows == "hard":
                opts = SphereTracing(max_steps=settings.shadow_steps, hit_epsilon=settings.hit_epsilon,
                                     max_distance=settings.max_distance, newton_steps=0)
                s = sphere_trace(scene.surface, above, wi, opts, t_max=t_max)
                line += (f" | hard: hit={bool(s.hit)} t={_fmt(s.t)} steps={_fmt(s.steps)} "
                         f"converging={bool(s.converging)} exhausted={bool(s.exhausted)}")
                if bool(s.hit):
                    q = above + s.t * wi
                    _, mat = scene.surface.eval(q)
                    line += f" at {_fmt(q)} (material {_fmt(mat)})"
            elif settings.shadows == "soft":
                m = soft_march(scene.surface, above, wi, t_max, SoftShadow.of(settings))
                line += f" | soft: t*={_fmt(m['t'])} blocked={bool(m['blocked'])} sign={_fmt(m['sign'])}"
            say(line)

    node(camera_ray(o, d, cone), "camera", 0)
    print(f"pixel radiance {_fmt(total)}  (shadows=none: {_fmt(total_flat)})")
    return total, total_flat


def main(args):
    path, w, h, x, y = args[0], *map(int, args[1:5])
    overrides, options = {}, {}
    for kv in args[5:]:
        key, value = kv.split("=", 1)
        try:
            value = int(value)
        except ValueError:
            try:
                value = float(value)
            except ValueError:
                pass
        (options if key in ("quiet", "min_weight") else overrides)[key] = value
    trace(path, w, h, x, y, overrides, **options)


if __name__ == "__main__":
    main(sys.argv[1:])
