"""The searches of the silhouette estimator (`jaxrt.silhouette`), no gradient: the
golden-section refinement of a ray's near miss, the projection of a point onto the
surface, and the regula falsi that finds where the inner ray enters the surface.
"""

import jax
import jax.numpy as jnp

from ..trace import sphere_trace
from ..vecmath import dot, normalize, safe_div, stop_gradient
from .search import golden_section, repeat as _repeat
from .sphere import SphereTracing, rounding_floor

#: Golden-section evaluations that refine the marched near miss: the bracket shrinks
#: to 0.618¹⁰ ≈ 0.8 % of its width, so t* lies within ~0.4 % of a step of the minimum
#: and the distance d* (quadratic there) is exact to ~1e-5 of a step.
GOLDEN_STEPS = 10

#: The inner ray aims this many pixels inside the outline. The colour it sees should
#: be the limit at the outline: on a smooth surface the normal there turns towards the
#: viewer as sqrt(2 · INSIDE_AIM / ρ) (ρ the outline's curvature radius in pixels),
#: 0.06 at ρ = 6 px; smaller values need more precision than float32 has for the
#: entry point at typical scene scales.
INSIDE_AIM = 0.01

#: The shape derivative of the outline is taken this fraction of (d* + one pixel)
#: outside the surface point nearest the near miss.
EDGE_OFFSET = 0.05

#: Sphere-tracing steps from the near miss to the surface along its normal.
PROJECT_STEPS = 8

#: Regula falsi (Illinois) steps that find the inner ray's entry point.
ILLINOIS_STEPS = 24

def refine_closest(sdf, origin, direction, cone, hit):
    """t* minimising f(o + t d) / r(t) in `hit.closest_bracket` (golden section; no gradient).

    Returns the better of the refined t and the marched `hit.closest_t`.
    """
    sdf, o, d, cone = stop_gradient((sdf, origin, direction, cone))
    dtype = o.dtype
    big = jnp.asarray(jnp.finfo(dtype).max, dtype)

    def h(t):
        return safe_div(jnp.abs(sdf(o + t * d)), cone[0] + cone[1] * t, big)

    t_c = jax.lax.stop_gradient(hit.closest_t)
    if hit.closest_bracket is None:
        return t_c
    a, b = jax.lax.stop_gradient(hit.closest_bracket)
    a, b = jnp.minimum(a, t_c), jnp.maximum(b, t_c)
    # One loop evaluates h(t_c) and the golden section's points (one copy of f).
    t_g, h_g, h_c = golden_section(h, a, b, GOLDEN_STEPS, t0=t_c)
    return jnp.where(h_g < h_c, t_g, t_c)


def project_to_surface(sdf, p, n):
    """The surface point on the line p − s n, s ≥ 0, from p outside (no gradient):
    `PROJECT_STEPS` sphere-tracing steps s ← s + f(p − s n) / L along −n (they never
    pass the surface; head-on, each step removes at least 1 − |∇f|/L of the gap).
    """
    sdf, p, n = stop_gradient((sdf, p, n))
    lipschitz = sdf.lipschitz().astype(p.dtype)

    def body(_, s):
        return s + jnp.maximum(sdf(p - s * n), 0.0) / lipschitz

    return p - _repeat(PROJECT_STEPS, body, jnp.zeros((), p.dtype)) * n


def inner_hit(sdf, origin, p_s, n_s, radius, settings):
    """Where a ray from `origin` aimed INSIDE_AIM pixel inside the outline enters the
    surface: (entry point, unit direction, found), no gradient.

    The aim point q = p_s − κ n_s, κ = max(INSIDE_AIM · 2r*, 4 rounding floors), lies inside the surface
    (f(q) ≈ −κ). A coarse march (hit threshold a quarter of a pixel) brings the ray
    near the surface without passing it, and `ILLINOIS_STEPS` steps of regula falsi
    (Illinois) on [t_march, |q − o|], where f changes sign, find the entry: grazing
    entries, which sphere tracing approaches only geometrically, cost no more.
    """
    sdf, o, p_s, n_s, radius = stop_gradient((sdf, origin, p_s, n_s, radius))
    dtype = o.dtype
    # The aim's depth κ never below a few rounding floors of f at p_s: closer, f(q)
    # could round to ≥ 0 (scenes in large units, a far outline) and the entry is lost.
    kappa = jnp.maximum(INSIDE_AIM * 2.0 * radius, 4.0 * rounding_floor(p_s))
    q = p_s - kappa * n_s
    v = q - o
    t_q = jnp.sqrt(dot(v, v))
    aim = normalize(v)
    spread = safe_div(radius, t_q)  # a cone of a quarter pixel for the coarse march
    coarse = SphereTracing.of(settings, newton_steps=0, pixel_epsilon=0.5)
    march = sphere_trace(sdf, o, aim, coarse, cone=jnp.stack([jnp.zeros_like(spread), spread]),
                         t_max=t_q)
    a = jnp.minimum(march.t, t_q)

    def g(t):
        return sdf(o + t * aim)

    def body(i, s):
        a, ga, b, gb, side, found = s
        # Regula falsi with the Illinois modification (halve the weight of an end
        # point that is kept twice), which converges superlinearly.
        c = a + safe_div(ga * (b - a), ga - gb, 0.5 * (b - a))
        c = jnp.clip(c, jnp.minimum(a, b), jnp.maximum(a, b))
        # One evaluation per iteration: the ends of the bracket g(a), g(t_q) first.
        gc = g(jnp.where(i == 0, a, jnp.where(i == 1, b, c)))
        outside = gc >= 0.0
        a_new, ga_new = jnp.where(outside, c, a), jnp.where(outside, gc, ga)
        b_new, gb_new = jnp.where(outside, b, c), jnp.where(outside, gb, gc)
        gb_new = jnp.where(outside & (side > 0), 0.5 * gb_new, gb_new)
        ga_new = jnp.where((~outside) & (side < 0), 0.5 * ga_new, ga_new)
        side_new = jnp.where(outside, 1, -1).astype(jnp.int32)
        stepping = i >= 2
        ga = jnp.where(i == 0, gc, ga)
        gb = jnp.where(i == 1, gc, gb)
        found = jnp.where(i == 1, found & (ga >= 0.0) & (gc < 0.0), found)
        return (jnp.where(stepping, a_new, a), jnp.where(stepping, ga_new, ga),
                jnp.where(stepping, b_new, b), jnp.where(stepping, gb_new, gb),
                jnp.where(stepping, side_new, side), found)

    zero = jnp.zeros((), dtype)
    init = (a, zero, t_q, zero, jnp.zeros((), jnp.int32), ~march.inside)
    a, _, _, _, _, found = _repeat(ILLINOIS_STEPS + 2, body, init)
    # The outside end of the bracket: f ≥ 0 there, within rounding of the root.
    return o + a * aim, aim, found & jnp.isfinite(a)
