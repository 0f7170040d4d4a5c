"""Point and directional lights, and shadow rays (notes, "directIllumination").

A light answers `illuminate(p) -> (wi, distance, radiance)`: the unit direction from
the shaded point towards the light, the distance to it (inf for directional lights),
and the incident radiance scale (irradiance on a surface facing the light):

- PointLight: E = I / r² (inverse-square fall-off), I the radiant intensity [W/sr].
- DirectionalLight: E constant; `direction` points from the scene towards the light.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .sdf.base import as_float, check, non_negative
from .vecmath import dot, normalize, safe_div, safe_norm


class PointLight(eqx.Module):
    """Isotropic point light at `position` with RGB `intensity` (W/sr).

    Differentiable: `position`, `intensity`.
    """

    position: jnp.ndarray
    intensity: jnp.ndarray

    def __init__(self, position=(0.0, 5.0, 0.0), intensity=(10.0, 10.0, 10.0)):
        self.position = as_float(position, (3,), "PointLight(position=...)")
        self.intensity = non_negative(intensity, (3,), "PointLight(intensity=...)")

    def illuminate(self, p):
        v = self.position - p
        dist = safe_norm(v)
        return normalize(v), dist, safe_div(self.intensity, dist * dist)


class DirectionalLight(eqx.Module):
    """Light from infinitely far in `direction` (towards the light) with RGB `irradiance`
    (W/m² on a surface facing it). Differentiable: `direction`, `irradiance`.
    """

    direction: jnp.ndarray
    irradiance: jnp.ndarray

    def __init__(self, direction=(0.0, 1.0, 0.0), irradiance=(1.0, 1.0, 1.0)):
        self.direction = check(as_float(direction, (3,), "DirectionalLight(direction=...)"),
                               lambda d: np.linalg.norm(d) > 0.0,
                               "DirectionalLight(direction=...)", "non-zero")
        self.irradiance = non_negative(irradiance, (3,), "DirectionalLight(irradiance=...)")

    def illuminate(self, p):
        return normalize(self.direction), jnp.asarray(jnp.inf, p.dtype), self.irradiance


def shadow_ray(sdf, origin, wi, distance, settings):
    """Visibility in [0, 1] of a light at `distance` along `wi` from `origin`.

    "hard": 0 if a sphere-traced ray hits anything before the light, else 1.
    "soft": Quilez's penumbra estimate min over the march of smoothstep(k · f(t) / t),
    with k = settings.penumbra (0 once the ray touches a surface). A shadow ray that
    starts inside a solid (the shaded point is seen from inside it) marches on |f|,
    as `sphere_trace` does: it is blocked where it leaves the solid.
    "none": 1. The loop is bounded by `settings.shadow_steps` and not differentiated.
    """
    from .trace import sphere_trace, stop_gradient

    if settings.shadows == "none":
        return jnp.ones((), origin.dtype)
    t_max = settings.shadow_max_distance or settings.max_distance
    t_max = jnp.minimum(distance, t_max)
    if settings.shadows == "hard":
        steps = settings.replace(max_steps=settings.shadow_steps, over_relaxation=1.0,
                                 newton_steps=0, pixel_epsilon=0.0)
        hit = sphere_trace(sdf, origin, wi, steps, t_max=t_max).hit
        return jnp.where(hit, 0.0, 1.0).astype(origin.dtype)
    return _soft_shadow(stop_gradient(sdf), jax.lax.stop_gradient(origin),
                        jax.lax.stop_gradient(wi), jax.lax.stop_gradient(t_max), settings)


def _soft_shadow(sdf, origin, wi, t_max, settings):
    dtype = origin.dtype
    k = jnp.asarray(settings.penumbra, dtype)
    eps = settings.hit_epsilon
    inv_lipschitz = 1.0 / sdf.lipschitz().astype(dtype)  # a product per step
    # Inside a solid the distance to its surface is −f.
    sign = jnp.where(sdf(origin) < 0.0, -1.0, 1.0).astype(dtype)
    # Steps are clamped to [eps, max_step]: a floor so that grazing rays progress and a
    # ceiling so that thin occluders are sampled (both as in Quilez's soft shadows).
    max_step = jnp.asarray(2.0, dtype)

    def cond(s):
        t, vis, i = s
        return (i < settings.shadow_steps) & (t < t_max) & (vis > 1e-3)

    def body(s):
        t, vis, i = s
        d = sign * sdf(origin + t * wi) * inv_lipschitz
        h = jnp.clip(k * d / t, 0.0, 1.0)  # t ≥ eps > 0: starts at eps, steps ≥ eps
        vis = jnp.minimum(vis, h * h * (3.0 - 2.0 * h))
        vis = jnp.where(d < eps, 0.0, vis)
        return t + jnp.clip(d, eps, max_step), vis, i + 1

    init = (jnp.asarray(eps, dtype), jnp.ones((), dtype), jnp.zeros((), jnp.int32))
    return jax.lax.while_loop(cond, body, init)[1]

