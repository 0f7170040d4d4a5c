"""Whitted shading (notes, "Ray tracing": trace and directIllumination).

`trace_radiance` follows one camera ray: it sphere-traces the scene, shades the hit
with direct illumination from every light (one shadow ray each), and returns the
radiance with the hit's AOVs. Kernels handle one ray; `render` vmaps them.
"""

import jax
import jax.numpy as jnp

from .lights import shadow_ray
from .trace import sphere_trace, surface_normal
from .vecmath import dot, to_local


def select(values, index):
    """values[index] for a static list of equally shaped arrays and a traced index."""
    if len(values) == 1:
        return values[0]
    return jnp.stack(values)[index]


def spawn_offset(p, settings):
    """Distance that a secondary ray starts off the surface at `p`.

    ray_offset · (hit_epsilon + 8 · machine-epsilon · max|pᵢ|): a few hit epsilons, so
    that the new ray does not re-hit the surface it leaves, plus the rounding error of
    the hit point's coordinates, so that it also works far from the origin.
    """
    rounding = 8.0 * jnp.finfo(p.dtype).eps * jnp.max(jnp.abs(p))
    return settings.ray_offset * (settings.hit_epsilon + rounding)


def direct_lighting(scene, p, n, wo, material, settings):
    """Σ_lights f(wo, wi) · E · cos θi · V  +  ambient, at point p with normal n (facing wo).

    f is the material's BRDF in the local frame of n; E the light's irradiance
    (I / r² for point lights); V the shadow-ray visibility.
    """
    wo_local = to_local(wo, n)
    origin = p + spawn_offset(p, settings) * n
    radiance = select([m.ambient() for m in scene.materials], material)
    for light in scene.lights:
        wi, dist, irradiance = light.illuminate(p)
        cos_i = dot(wi, n)
        wi_local = to_local(wi, n)
        f = select([m.eval(wo_local, wi_local) for m in scene.materials if m.has_diffuse]
                   or [jnp.zeros(3, p.dtype)], _diffuse_index(scene, material))
        visible = shadow_ray(scene.surface, origin, wi, dist, settings)
        radiance = radiance + jnp.where(cos_i > 0.0, f * irradiance * cos_i * visible, 0.0)
    return radiance


def _diffuse_index(scene, material):
    """Map a material index to its position among the materials with `has_diffuse`."""
    table = []
    k = 0
    for m in scene.materials:
        table.append(k)
        k += int(m.has_diffuse)
    return jnp.asarray(table, jnp.int32)[material] if len(table) > 1 else 0


def trace_radiance(scene, origin, direction, cone, settings):
    """Radiance and AOVs of one camera ray.

    Returns a dict: rgb [3], depth (hit distance; max_distance on a miss), normal [3]
    (world space, facing the camera; 0 on a miss), albedo [3], steps, coverage (1 on a
    hit, 0 on a miss).
    """
    surface = scene.surface
    hit = sphere_trace(surface, origin, direction, settings, cone=cone)
    p = origin + hit.t * direction
    n = surface_normal(surface, p, settings)
    # Shade with the normal facing the viewer (rays that start inside a surface see
    # its back side).
    n = jnp.where(dot(n, direction) > 0.0, -n, n)
    material = jnp.clip(surface.eval(jax.lax.stop_gradient(p))[1], 0, len(scene.materials) - 1)
    wo = -direction
    color = direct_lighting(scene, p, n, wo, material, settings)
    albedo = select([m.base_color() for m in scene.materials], material)
    zero3 = jnp.zeros(3, p.dtype)
    return {
        "rgb": jnp.where(hit.hit, color, scene.background),
        "depth": hit.t,
        "normal": jnp.where(hit.hit, n, zero3),
        "albedo": jnp.where(hit.hit, albedo, zero3),
        "steps": hit.steps.astype(p.dtype),
        "coverage": hit.hit.astype(p.dtype),
    }
