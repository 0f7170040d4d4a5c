"""The soft-shadow march (Quilez, "soft shadows in raymarched SDFs") and its options.

Along the shadow ray o + t wi the penumbra estimate is the minimum over the march of

    s(t) = smoothstep(h),  h = clip(k · f(o + t wi) / (L t), 0, 1),

0 once the ray touches a surface (f < ε). The march (no gradient) returns where that
minimum was taken, t* (the sampled minimum, refined by golden section between the
samples around it), and whether the ray was blocked; `jaxrt.lights.penumbra`
evaluates s(t*) differentiably. By the envelope theorem the gradient of a minimum over
t is ∂s/∂θ at the minimiser t* held fixed, so the penumbra moves with the occluder.
(The refinement makes s stationary at t*, which the envelope theorem needs: at a
sample alone, finite differences also see t* slide with the samples.)
"""

import dataclasses

import jax
import jax.numpy as jnp

from .options import check_options
from .search import golden_section
from .sphere import rounding_floor

#: Largest step of a soft-shadow march, as a fraction of the ray's length (to its light,
#: or to the shadow distance): the penumbra is sampled at least every 1/16 of the way,
#: whatever the scene's units (it was 2 world units, so a scene scaled by 10³ had other
#: soft shadows). A ray in open space reaches its light in 16 such steps.
MAX_STEP_FRACTION = 1.0 / 16.0

#: Golden-section evaluations that refine the sampled penumbra minimum between the
#: samples around it: the bracket shrinks to 0.618⁸ ≈ 2 % of its width. Without them
#: the gradient (the envelope gradient at a sample) was 2–5 % off finite differences
#: on a sphere's penumbra on a floor at 64 shadow steps; the image darkens slightly
#: where the true minimum lies between samples.
REFINE_STEPS = 8

#: The march stops once the visibility falls below this (the rest of the ray cannot
#: make it visibly darker).
MIN_VISIBILITY = 1e-3


@dataclasses.dataclass(frozen=True)
class SoftShadow:
    """Options of a soft-shadow march.

    max_steps    step budget (`RenderSettings.shadow_steps`). A ray that spends it before
                 reaching its light is blocked: it has not shown the light visible.
    hit_epsilon  the ray is blocked where f < max(hit_epsilon, the rounding floor of f
                 at the sample, `jaxrt.march.sphere.rounding_floor`); that threshold is
                 also the smallest step.
    penumbra     k: larger is sharper.
    refine_steps golden-section evaluations that refine the sampled minimum (0: Quilez's
                 sampled minimum as it is).
    """

    max_steps: int = 64
    hit_epsilon: float = 1e-4
    penumbra: float = 8.0
    refine_steps: int = REFINE_STEPS

    def __post_init__(self):
        check_options(self, max_steps=("int", 1), hit_epsilon=("num>", 0), penumbra=("num>", 0),
                      refine_steps=("int", 0))

    @classmethod
    def of(cls, settings):
        """The soft-shadow options of a `RenderSettings`."""
        return cls(max_steps=settings.shadow_steps, hit_epsilon=settings.hit_epsilon,
                   penumbra=settings.penumbra)


def march(sdf, origin, wi, t_max, options):
    """The bounded penumbra march of one shadow ray (no gradient).

    Returns {"t": t* (the sample where s took its minimum; 0 if no sample lowered it
    below 1), "blocked": the ray touched a surface (visibility 0)}.
    """
    dtype = origin.dtype
    k = jnp.asarray(options.penumbra, dtype)
    eps = options.hit_epsilon
    inv_lipschitz = 1.0 / sdf.lipschitz().astype(dtype)  # a product per step
    # Inside a solid the distance to its surface is −f.
    sign = jnp.where(sdf(origin) < 0.0, -1.0, 1.0).astype(dtype)
    # Steps are clamped to [eps, max_step]: a floor so that grazing rays progress and a
    # ceiling so that thin occluders are sampled (both as in Quilez's soft shadows), the
    # floor never below the rounding floor of f, the ceiling relative to the ray's length.
    max_step = jnp.asarray(MAX_STEP_FRACTION, dtype) * t_max

    def cond(s):
        t, vis, i = s[:3]
        return (i < options.max_steps) & (t < t_max) & (vis > MIN_VISIBILITY)

    def body(s):
        t, vis, i, t_prev, t_best, lo, hi = s
        x = origin + t * wi
        floor = jnp.maximum(eps, rounding_floor(x))
        d = sign * sdf(x) * inv_lipschitz
        h = jnp.clip(k * d / t, 0.0, 1.0)  # t ≥ eps > 0: starts at eps, steps ≥ eps
        value = h * h * (3.0 - 2.0 * h)
        t_next = t + jnp.clip(d, floor, jnp.maximum(max_step, floor))
        lower = value < vis  # the minimum so far, bracketed by the samples around it
        t_best, lo, hi = (jnp.where(lower, t, t_best), jnp.where(lower, t_prev, lo),
                          jnp.where(lower, t_next, hi))
        vis = jnp.minimum(vis, value)
        vis = jnp.where(d < floor, 0.0, vis)
        return t_next, vis, i + 1, t, t_best, lo, hi

    zero = jnp.zeros((), dtype)
    t0 = jnp.maximum(jnp.asarray(eps, dtype), rounding_floor(origin))
    init = (t0, jnp.ones((), dtype), jnp.zeros((), jnp.int32), t0, zero, t0, t0)
    t_end, vis, _, t_last, t_best, lo, hi = jax.lax.while_loop(cond, body, init)
    # Out of budget before the light (and not already dark) while still converging on a
    # surface (the distance falling over the last step: it passes close by an
    # occluder): blocked. One that was receding keeps the minimum it found.
    ran_out = (t_end < t_max) & (vis > MIN_VISIBILITY)
    falling = sdf(origin + t_end * wi) * sign < sdf(origin + t_last * wi) * sign
    blocked = (vis <= 0.0) | (ran_out & falling)
    if options.refine_steps:
        # The sampled minimum refined by golden section on k·f/t in [lo, hi] (the samples
        # around it): the gradient (`jaxrt.lights.penumbra`) is then that of the minimum
        # over t, where the penumbra is stationary.
        def ratio(t):
            return k * sign * sdf(origin + t * wi) * inv_lipschitz / jnp.maximum(t, eps)

        t_g, r_g = golden_section(ratio, lo, jnp.minimum(hi, t_max), options.refine_steps)
        better = (t_best > 0.0) & (~blocked) & (r_g < ratio(t_best))
        t_best = jnp.where(better, t_g, t_best)
    return {"t": t_best, "blocked": blocked}
