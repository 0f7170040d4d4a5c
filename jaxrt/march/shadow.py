"""The soft-shadow march (Quilez, "soft shadows in raymarched SDFs") and its options.

Along the shadow ray o + t wi the penumbra estimate is the minimum over the march of

    s(t) = smoothstep(h),  h = clip(k · f(o + t wi) / (L t), 0, 1),

0 once the ray touches a surface (f < ε). The march (no gradient) returns where that
minimum was taken, t* (the sampled minimum, refined by golden section between the
samples around it), whether the ray was blocked and on which side of the surface it
starts; `jaxrt.lights.penumbra`
evaluates s(t*) differentiably. By the envelope theorem the gradient of a minimum over
t is ∂s/∂θ at the minimiser t* held fixed, so the penumbra moves with the occluder.
(The refinement makes s stationary at t*, which the envelope theorem needs: at a
sample alone, finite differences also see t* slide with the samples.)
"""

import dataclasses

import jax
import jax.numpy as jnp

from . import form, tape
from .options import check_options
from .search import _INV_PHI, golden_plain
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
                   penumbra=settings.penumbra, refine_steps=settings.penumbra_refine_steps)


#: The phases of the soft-shadow loop (`march`), one evaluation of f each: the sign at
#: the origin, the march, the end sample of a ray out of budget, the two interior points
#: of the golden section, then its `refine_steps` steps (GOLDEN + j), then done.
SIGN, MARCH, END, FIRST, SECOND, GOLDEN = range(6)


def march(sdf, origin, wi, t_max, options):
    """The bounded penumbra march of one shadow ray (no gradient).

    Returns {"t": t* (the sample where s took its minimum; 0 if no sample lowered it
    below 1), "blocked": the ray touched a surface (visibility 0), "sign": −1 if the
    ray starts inside a solid (f(o) < 0), else 1, "f": f(o + t* wi), 0 where t* = 0}.

    One loop whose every iteration evaluates f once, at a point its phase chooses
    (`SIGN` … `GOLDEN`): the sign at the origin, the march itself, the sample after the
    last one of a ray that ran out of budget, and the golden-section refinement of the
    minimum (`search.golden_section`'s steps). The values that the tests after the
    loop need (f at the last sample, at the minimum) are carried in its state, so the
    program holds one copy of f whatever max_steps and refine_steps. That is the
    "phases" form (`jaxrt.march.form`); the "plain" form is `_plain`.
    """
    if form.current() == "plain":
        return _plain(sdf, origin, wi, t_max, options)
    dtype = origin.dtype
    k = jnp.asarray(options.penumbra, dtype)
    eps = options.hit_epsilon
    inv_lipschitz = 1.0 / sdf.lipschitz().astype(dtype)  # a product per step
    refine = options.refine_steps
    done_phase = GOLDEN + refine if refine else END + 1
    # Steps are clamped to [eps, max_step]: a floor so that grazing rays progress and a
    # ceiling so that thin occluders are sampled (both as in Quilez's soft shadows), the
    # floor never below the rounding floor of f, the ceiling relative to the ray's length.
    max_step = jnp.asarray(MAX_STEP_FRACTION, dtype) * t_max

    def ratio(t, f, sign):  # k · f / (L t), the argument of the penumbra's smoothstep
        return k * sign * f * inv_lipschitz / jnp.maximum(t, eps)

    def marching(s):
        return (s["i"] < options.max_steps) & (s["t"] < t_max) & (s["vis"] > MIN_VISIBILITY)

    def golden_point(s):
        # The golden-section step (`search.golden_section`): the next point to evaluate.
        left = s["g1"] < s["g2"]  # the minimum lies in [a, x2]
        a = jnp.where(left, s["a"], s["x1"])
        b = jnp.where(left, s["x2"], s["b"])
        x = jnp.where(left, b - _INV_PHI * (b - a), a + _INV_PHI * (b - a))
        return left, a, b, x

    def body(s):
        phase = s["phase"]
        new = dict(s)
        # The bracket of the golden section, fixed once the march is over.
        tau = s["t"]
        if refine:
            a0, b0 = s["lo"], jnp.minimum(s["hi"], t_max)
            x1, x2 = b0 - _INV_PHI * (b0 - a0), a0 + _INV_PHI * (b0 - a0)
            left, a, b, x = golden_point(s)
            tau = jnp.where(phase == FIRST, x1, jnp.where(phase == SECOND, s["x2"],
                                                          jnp.where(phase >= GOLDEN, x, tau)))
        f = sdf(jnp.where(phase == SIGN, origin, origin + tau * wi))

        # SIGN: inside a solid the distance to its surface is −f.
        sign = jnp.where(phase == SIGN, jnp.where(f < 0.0, -1.0, 1.0).astype(dtype), s["sign"])
        new["sign"] = sign

        # MARCH: one step of the march.
        t, vis = s["t"], s["vis"]
        x_t = origin + t * wi
        floor = jnp.maximum(eps, rounding_floor(x_t))
        d = sign * f * inv_lipschitz
        h = jnp.clip(k * d / t, 0.0, 1.0)  # t ≥ eps > 0: starts at eps, steps ≥ eps
        value = h * h * (3.0 - 2.0 * h)
        t_next = t + jnp.clip(d, floor, jnp.maximum(max_step, floor))
        lower = value < vis  # the minimum so far, bracketed by the samples around it
        vis_next = jnp.where(d < floor, 0.0, jnp.minimum(vis, value))
        step = phase == MARCH
        new["t"] = jnp.where(step, t_next, t)
        new["vis"] = jnp.where(step, vis_next, vis)
        new["i"] = jnp.where(step, s["i"] + 1, s["i"])
        new["t_prev"] = jnp.where(step, t, s["t_prev"])
        new["f_prev"] = jnp.where(step, f, s["f_prev"])
        lower = step & lower
        new["t_best"] = jnp.where(lower, t, s["t_best"])
        new["lo"] = jnp.where(lower, s["t_prev"], s["lo"])
        new["hi"] = jnp.where(lower, t_next, s["hi"])
        new["f_best"] = jnp.where(lower, f, s["f_best"])

        # END: f at the sample after the last (a ray out of budget).
        new["f_end"] = jnp.where(phase == END, f, s["f_end"])

        if refine:
            g = ratio(tau, f, sign)
            first, second, golden = phase == FIRST, phase == SECOND, phase >= GOLDEN
            new["a"] = jnp.where(first, a0, jnp.where(golden, a, s["a"]))
            new["b"] = jnp.where(first, b0, jnp.where(golden, b, s["b"]))
            new["x1"] = jnp.where(first, x1, jnp.where(golden, jnp.where(left, x, s["x2"]), s["x1"]))
            new["g1"] = jnp.where(first, g, jnp.where(golden, jnp.where(left, g, s["g2"]), s["g1"]))
            new["x2"] = jnp.where(first, x2, jnp.where(golden, jnp.where(left, s["x1"], x), s["x2"]))
            new["g2"] = jnp.where(second, g, jnp.where(golden, jnp.where(left, s["g1"], g), s["g2"]))
            # f itself at x1, x2 (the penumbra's value at the refined minimum).
            new["f1"] = jnp.where(first, f, jnp.where(golden, jnp.where(left, f, s["f2"]), s["f1"]))
            new["f2"] = jnp.where(second, f, jnp.where(golden, jnp.where(left, s["f1"], f), s["f2"]))

        # The next phase: the march while it lasts, then END for a ray out of budget
        # (the march stopped before the light, not yet dark), then the refinement of a
        # minimum that it can change: none where no sample lowered the penumbra below 1
        # (t_best = 0) or the ray was blocked (visibility 0), which after the loop keep
        # their sample alone (the "plain" form refines them and discards the result).
        after_march = dict(new)
        out_of_budget = (after_march["t"] < t_max) & (after_march["vis"] > MIN_VISIBILITY)
        finished = done_phase
        if refine:
            finished = jnp.where((new["t_best"] > 0.0) & (new["vis"] > 0.0), FIRST, done_phase)
        from_march = jnp.where(marching(after_march), MARCH, jnp.where(out_of_budget, END, finished))
        new["phase"] = jnp.where((phase == SIGN) | (phase == MARCH), from_march,
                                 jnp.where(phase == END, finished, phase + 1)).astype(jnp.int32)
        return new

    zero = jnp.zeros((), dtype)
    t0 = jnp.maximum(jnp.asarray(eps, dtype), rounding_floor(origin))
    init = dict(phase=jnp.asarray(SIGN, jnp.int32), t=t0, vis=jnp.ones((), dtype),
                i=jnp.zeros((), jnp.int32), t_prev=t0, f_prev=zero, t_best=zero, lo=t0, hi=t0,
                sign=jnp.ones((), dtype), f_end=zero, f_best=zero)
    if refine:
        init.update(a=zero, b=zero, x1=zero, g1=zero, x2=zero, g2=zero, f1=zero, f2=zero)
    with tape.stepping():
        s = jax.lax.while_loop(lambda s: s["phase"] < done_phase, body, init)
    sign, t_best = s["sign"], s["t_best"]
    f_best = s["f_best"]
    # Out of budget before the light (and not already dark) while still converging on a
    # surface (the distance falling over the last step: it passes close by an
    # occluder): blocked. One that was receding keeps the minimum it found.
    ran_out = (s["t"] < t_max) & (s["vis"] > MIN_VISIBILITY)
    falling = s["f_end"] * sign < s["f_prev"] * sign
    blocked = (s["vis"] <= 0.0) | (ran_out & falling)
    if refine:
        # The sampled minimum refined by golden section on k·f/t in [lo, hi] (the samples
        # around it): the gradient (`jaxrt.lights.penumbra`) is then that of the minimum
        # over t, where the penumbra is stationary.
        t_g = jnp.where(s["g1"] < s["g2"], s["x1"], s["x2"])
        r_g = jnp.minimum(s["g1"], s["g2"])
        better = (t_best > 0.0) & (~blocked) & (r_g < ratio(t_best, s["f_best"], sign))
        t_best = jnp.where(better, t_g, t_best)
        f_best = jnp.where(better, jnp.where(s["g1"] < s["g2"], s["f1"], s["f2"]), f_best)
    return {"t": t_best, "blocked": blocked, "sign": sign, "f": f_best}


def _plain(sdf, origin, wi, t_max, options):
    """`march` in the "plain" form: the sign f(o) before the loop, the march's steps
    alone in it (f at the last sample and at the minimum carried in its state), the
    sample after the last and the golden section (`search.golden_plain`) after it.
    The same values as the phases to rounding; five copies of f with refine_steps
    (the golden section's three), three without."""
    dtype = origin.dtype
    k = jnp.asarray(options.penumbra, dtype)
    eps = options.hit_epsilon
    inv_lipschitz = 1.0 / sdf.lipschitz().astype(dtype)
    sign = jnp.where(sdf(origin) < 0.0, -1.0, 1.0).astype(dtype)
    max_step = jnp.asarray(MAX_STEP_FRACTION, dtype) * t_max

    def cond(s):
        t, vis, i = s[:3]
        return (i < options.max_steps) & (t < t_max) & (vis > MIN_VISIBILITY)

    def body(s):
        t, vis, i, t_prev, f_prev, t_best, lo, hi, f_best = s
        x = origin + t * wi
        floor = jnp.maximum(eps, rounding_floor(x))
        f = sdf(x)
        d = sign * f * inv_lipschitz
        h = jnp.clip(k * d / t, 0.0, 1.0)  # t ≥ eps > 0: starts at eps, steps ≥ eps
        value = h * h * (3.0 - 2.0 * h)
        t_next = t + jnp.clip(d, floor, jnp.maximum(max_step, floor))
        lower = value < vis  # the minimum so far, bracketed by the samples around it
        t_best, lo, hi, f_best = (jnp.where(lower, t, t_best), jnp.where(lower, t_prev, lo),
                                  jnp.where(lower, t_next, hi), jnp.where(lower, f, f_best))
        vis = jnp.where(d < floor, 0.0, jnp.minimum(vis, value))
        return t_next, vis, i + 1, t, f, t_best, lo, hi, f_best

    zero = jnp.zeros((), dtype)
    t0 = jnp.maximum(jnp.asarray(eps, dtype), rounding_floor(origin))
    init = (t0, jnp.ones((), dtype), jnp.zeros((), jnp.int32), t0, zero, zero, t0, t0, zero)
    with tape.stepping():
        t_end, vis, _, _, f_last, t_best, lo, hi, f_best = jax.lax.while_loop(cond, body, init)
    # As in `march`: a ray out of budget while its distance still falls is blocked.
    ran_out = (t_end < t_max) & (vis > MIN_VISIBILITY)
    falling = sdf(origin + t_end * wi) * sign < f_last * sign
    blocked = (vis <= 0.0) | (ran_out & falling)
    if options.refine_steps:
        def ratio(t, f):
            return k * sign * f * inv_lipschitz / jnp.maximum(t, eps)

        def golden(t):
            f = sdf(origin + t * wi)
            return ratio(t, f), f

        t_g, r_g, f_g = golden_plain(golden, lo, jnp.minimum(hi, t_max), options.refine_steps,
                                     aux=True)
        better = (t_best > 0.0) & (~blocked) & (r_g < ratio(t_best, f_best))
        t_best = jnp.where(better, t_g, t_best)
        f_best = jnp.where(better, f_g, f_best)
    return {"t": t_best, "blocked": blocked, "sign": sign, "f": f_best}
