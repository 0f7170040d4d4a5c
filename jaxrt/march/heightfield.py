"""The height-field march (notes, "Ray marching height-fields"; `jaxrt.heightfield`):
growing steps dt = max(min_step, rel_step · t) through the slab of the height's bounds
until g(t) = P(t).y − h(P(t).x, P(t).z) changes sign, then linear interpolation and
safeguarded Newton steps inside the bracket. No gradient: `HeightField.intersect`
polishes the root with implicit gradients.
"""

import jax
import jax.numpy as jnp

from ..vecmath import safe_div
from .search import repeat
from .sphere import rounding_floor


def march(field, origin, direction, cone, t_max):
    """The bounded march of one ray against a `jaxrt.HeightField` (no gradient; its
    fields max_steps, min_step, rel_step, interpolate, refine_steps are the options).
    Returns (t, hit, steps, inside, exhausted, t_lo, t_hi, closest_t, closest_d): the
    hit (t_max on a miss) and the bracket [t_lo, t_hi] of its sign change."""
    dtype = origin.dtype
    lo, hi = (jnp.asarray(b, dtype) for b in field.height.bounds())
    scale = 1.0 / jnp.sqrt(1.0 + jnp.asarray(field.height.slope_bound(), dtype) ** 2)
    big = jnp.asarray(jnp.finfo(dtype).max, dtype)
    min_step, rel_step = (jnp.asarray(x, dtype) for x in (field.min_step, field.rel_step))

    def g_at(t):
        return field.gap(origin + t * direction)

    g_origin = g_at(jnp.zeros((), dtype))
    inside = g_origin < 0.0
    sign = jnp.where(inside, -1.0, 1.0).astype(dtype)
    oy, dy = origin[1], direction[1]
    # Slab lo ≤ y ≤ hi: start where the ray enters it, miss if it never does.
    above, below = oy > hi, oy < lo
    t_enter = jnp.where(above & (dy < 0.0), safe_div(hi - oy, jnp.where(above, dy, -1.0)),
                        jnp.where(below & (dy > 0.0), safe_div(lo - oy, jnp.where(below, dy, 1.0)), 0.0))
    never = (above & (dy >= 0.0)) | (below & (dy <= 0.0))
    t0 = jnp.where(never, t_max, jnp.minimum(t_enter, t_max)).astype(dtype)
    g0 = g_at(t0)

    def ratio(t, g):
        return safe_div(sign * g * scale, cone[0] + cone[1] * t, big)

    # state: t, g, t_prev, g_prev, steps, done, hit, best_ratio, best_t, best_g
    init = (t0, g0, t0, g0, jnp.zeros((), jnp.int32), never, jnp.zeros((), bool),
            ratio(t0, g0), t0, g0)

    def cond(s):
        return (~s[5]) & (s[4] < field.max_steps)

    def body(s):
        t, g, _, _, steps, _, _, best, best_t, best_g = s
        # Never below the rounding floor at the sample: a step smaller than a few ulps
        # of max|p| would not move the sample (min_step = 1e-6 at scale 10³ in float32).
        dt = jnp.maximum(jnp.maximum(min_step, rel_step * t),
                         rounding_floor(origin + t * direction))
        t_next = jnp.minimum(t + dt, t_max)
        p = origin + t_next * direction
        g_next = field.gap(p)
        crossed = sign * g_next <= 0.0
        # Leaving the slab on the side the ray started on, or running out of range.
        left = jnp.where(inside, (p[1] < lo) & (dy <= 0.0), (p[1] > hi) & (dy >= 0.0))
        escaped = (~crossed) & ((t_next >= t_max) | left)
        r = ratio(t_next, g_next)
        better = (~crossed) & (r < best)
        return (t_next, g_next, t, g, steps + 1, crossed | escaped, crossed,
                jnp.where(better, r, best), jnp.where(better, t_next, best_t),
                jnp.where(better, g_next, best_g))

    t1, g1, t_prev, g_prev, steps, _, hit, _, best_t, best_g = jax.lax.while_loop(cond, body, init)
    ran_out = (steps >= field.max_steps) & ~hit & (t1 < t_max) & ~never
    # A ray that ran out of budget within the rounding floor of the surface (its gap
    # there is below what the float resolves at the sample) is a hit at its last sample.
    p1 = origin + t1 * direction
    within = ran_out & (sign * g1 * scale < rounding_floor(p1))
    hit = hit | within
    exhausted = ran_out & ~within
    g_prev = jnp.where(within, g1, g_prev)
    t_prev = jnp.where(within, t1, t_prev)
    t_lo, t_hi = t_prev, t1
    if field.interpolate:
        # Linear interpolation between the last two samples (notes, optimisation 1).
        t_hit = t_prev + (t1 - t_prev) * jnp.clip(safe_div(g_prev, g_prev - g1, 1.0), 0.0, 1.0)
        # `refine_steps` safeguarded Newton steps inside the bracket [t_lo, t_hi]
        # ("rtsafe", Numerical Recipes §9.4): a Newton step that leaves the bracket
        # is replaced by bisection; the bracket shrinks to the sign change.
        # One loop: the program holds one copy of g and g' whatever refine_steps.
        slope_of = jax.value_and_grad(g_at)

        def refine(_, s):
            t_hit, t_lo, t_hi = s
            g_hit, slope = slope_of(t_hit)
            past = sign * g_hit <= 0.0
            t_lo, t_hi = jnp.where(past, t_lo, t_hit), jnp.where(past, t_hit, t_hi)
            t_newton = t_hit - safe_div(g_hit, slope, jnp.inf)
            ok = (t_newton >= t_lo) & (t_newton <= t_hi)
            return jnp.where(ok, t_newton, 0.5 * (t_lo + t_hi)), t_lo, t_hi

        if field.refine_steps:
            t_hit, t_lo, t_hi = repeat(field.refine_steps, refine, (t_hit, t_lo, t_hi))
    else:
        t_hit = t1
    t = jnp.where(hit, t_hit, t_max)
    t_lo = jnp.where(hit, t_lo, t_max)
    t_hi = jnp.where(hit, t_hi, t_max)
    return t, hit, steps, inside, exhausted, t_lo, t_hi, best_t, sign * best_g * scale
