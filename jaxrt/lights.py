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

from .march import tape
from .march.shadow import SoftShadow, march as soft_shadow_march
from .march.sphere import SphereTracing
from .sdf.base import as_float, check, non_negative
from .vecmath import clip, dot, normalize, safe_div, safe_norm, stop_gradient


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

    "hard": 0 if a sphere-traced ray hits anything before the light, or runs out of
    steps before reaching it while still converging on a surface (its distance falling:
    it passes close by an occluder), else 1 (no gradient: a step). A ray that runs out
    while receding (leaving the surface it started on at a grazing angle, say) is
    visible: nothing was in its way.
    "soft": Quilez's penumbra estimate min over the march of smoothstep(k · f(t) / t),
    with k = settings.penumbra (0 once the ray touches a surface), evaluated at the
    march's minimiser (`penumbra`): differentiable in the occluder, the shaded point
    and the light direction (envelope theorem, `jaxrt.march.shadow`). A shadow ray that
    starts inside a solid (the shaded point is seen from inside it) marches on |f|, as
    `sphere_trace` does: it is blocked where it leaves the solid.
    "none": 1. The loops are bounded by `settings.shadow_steps` and not differentiated.
    """
    from .trace import sphere_trace

    if settings.shadows == "none":
        return jnp.ones((), origin.dtype)
    t_max = settings.shadow_max_distance or settings.max_distance
    t_max = jnp.minimum(distance, t_max)
    if settings.shadows == "hard":
        options = SphereTracing(max_steps=settings.shadow_steps, hit_epsilon=settings.hit_epsilon,
                                max_distance=settings.max_distance, newton_steps=0)
        # A shadow ray that ran out of steps still converging on a surface is blocked.
        found = sphere_trace(sdf, origin, wi, options, t_max=t_max, fields=("converging",))
        return jnp.where(found.hit | found.converging, 0.0, 1.0).astype(origin.dtype)
    options = SoftShadow.of(settings)
    found = tape.march(lambda *a: soft_shadow_march(*a, options), stop_gradient(sdf),
                       stop_gradient(origin), stop_gradient(wi), stop_gradient(t_max))
    return penumbra(sdf, origin, wi, found, options)


def penumbra(sdf, origin, wi, found, options):
    """Soft-shadow visibility at the march's minimiser t* = found["t"]:

        V = 0 if blocked, 1 if no sample lowered it (t* = 0), else smoothstep(h),
        h = clip(k · sign · f(o + t* wi) / (L t*), 0, 1),

    with t* held fixed (no gradient) and everything else differentiable (f's value is
    the march's, found["f"]: `trace.evaluated`); the sign
    (inside a solid: found["sign"], which the march measured) and the Lipschitz factor
    L carry no gradient.
    """
    from .trace import evaluated

    dtype = origin.dtype
    sign = jax.lax.stop_gradient(found["sign"]).astype(dtype)  # the march's f(o) < 0
    inv_lipschitz = 1.0 / stop_gradient(sdf).lipschitz().astype(dtype)
    t = found["t"]
    lowered = t > 0.0
    safe_t = jnp.where(lowered, t, 1.0)
    # f at the minimiser is in the record: evaluated only where differentiated.
    d = sign * evaluated(sdf, origin + safe_t * wi, found["f"]) * inv_lipschitz
    h = clip(jnp.asarray(options.penumbra, dtype) * d / safe_t, 0.0, 1.0)
    value = h * h * (3.0 - 2.0 * h)
    return jnp.where(found["blocked"], 0.0, jnp.where(lowered, value, 1.0)).astype(dtype)
