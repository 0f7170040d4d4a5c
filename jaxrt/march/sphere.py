"""The sphere-tracing loop and its options (Hart 1996; the notes, "Ray marching implicit
surfaces"). `jaxrt.trace.sphere_trace` calls it through the tape and polishes its root.

    t ← t + f(o + t d) / L  from t = 0, until f < ε(t) (hit), t > t_max (miss) or the
    budget runs out (exhausted),

with over-relaxation (Keinert et al. 2014) and the near-miss search of
`jaxrt.silhouette` folded in. A ray that starts inside a surface marches on |f|.
"""

import dataclasses

import jax
import jax.numpy as jnp

from ..vecmath import safe_div
from . import form, tape
from .options import check_options


@dataclasses.dataclass(frozen=True)
class SphereTracing:
    """Options of a sphere-traced ray (the fields of `RenderSettings` that it reads).

    max_steps        step budget.
    hit_epsilon      absolute hit threshold ε (world units).
    pixel_epsilon    hit threshold relative to the pixel cone: ε(t) = hit_epsilon +
                     pixel_epsilon · r(t).
    max_distance     the ray misses beyond it (unless the call gives `t_max`).
    over_relaxation  ω of enhanced sphere tracing (1 = plain).
    newton_steps     Newton steps that polish a hit (and carry its implicit gradient).
    root_solver      "newton" or "optimistix" (`jaxrt.trace.polish_root`).
    """

    max_steps: int = 128
    hit_epsilon: float = 1e-4
    pixel_epsilon: float = 0.0
    max_distance: float = 100.0
    over_relaxation: float = 1.0
    newton_steps: int = 2
    root_solver: str = "newton"

    def __post_init__(self):
        check_options(self, max_steps=("int", 1), hit_epsilon=("num>", 0),
                      pixel_epsilon=("num", 0), max_distance=("num>", 0),
                      newton_steps=("int", 0))

    @classmethod
    def of(cls, settings, **changes):
        """The options of `settings` (a `RenderSettings` or a `SphereTracing`), changed."""
        values = {f.name: getattr(settings, f.name) for f in dataclasses.fields(cls)}
        return cls(**{**values, **changes})

    def replace(self, **changes):
        return dataclasses.replace(self, **changes)


#: The rounding floor of a distance evaluated at p, in ulps of max|pᵢ|: the coordinates
#: of p = o + t d are rounded to an ulp of max|pᵢ| and every primitive then subtracts
#: numbers of that size, so f(p) is uncertain by a few such ulps (the distance bound f/L
#: of a deformed shape by as many: its coordinates are stretched by at most L). A march
#: that asks for |f|/L below this cannot get there; it would only run out of budget.
#: 8 ulps: the same margin as the rounding term of `integrator.spawn_offset`, which
#: therefore always starts secondary rays outside the band.
ROUNDING_ULPS = 8.0


def rounding_floor(p):
    """ROUNDING_ULPS · machine epsilon · max|pᵢ|: what a distance at p cannot resolve.

    A tolerance, with no gradient. (The derivative of `jnp.max` divides by the number of
    components equal to the maximum; where XLA computes p twice with different roundings
    none is, and it was 0/0: NaN gradients of every shading point that spawns a ray.)"""
    return ROUNDING_ULPS * jnp.finfo(p.dtype).eps * jax.lax.stop_gradient(jnp.max(jnp.abs(p)))


def hit_epsilon(settings, t, cone):
    """ε(t) = hit_epsilon + pixel_epsilon · r(t), with r(t) = cone[0] + cone[1] · t.

    The threshold a march uses at p is `max(ε(t), rounding_floor(p))` (`threshold`)."""
    return settings.hit_epsilon + settings.pixel_epsilon * (cone[0] + cone[1] * t)


def threshold(settings, t, cone, p):
    """The hit threshold at the sample p = o + t d: ε(t), but never below the rounding
    floor of f at p, so that an epsilon below the float's precision (hit_epsilon = 1e-8
    in float32) or a scene modelled in large units (a sphere of radius 1000 seen from
    4000) still converges instead of running out of steps."""
    return jnp.maximum(hit_epsilon(settings, t, cone), rounding_floor(p))


#: The phases of the sphere-tracing loop (`march`), one evaluation of f each: the sign
#: at the origin, the march, the secant finish of a ray out of budget, then done.
START, MARCH, FINISH, DONE = range(4)


def march(sdf, origin, direction, settings, cone, t_max):
    """The bounded sphere-tracing loop of one ray (no gradient); `settings` a `SphereTracing`
    (or anything with its fields). Returns a dict of `jaxrt.Hit` fields.

    In the "phases" form (`jaxrt.march.form`), one loop whose every iteration evaluates
    f once, at the point its phase chooses (`START`, `MARCH`, `FINISH`): f(o) (which
    side the ray starts on), the march, and the secant finish of a ray whose budget ran
    out while approaching a surface. The program holds one copy of f. In the "plain"
    form f(o) comes before the loop, the loop only marches, and the secant finish comes
    after it: three copies of f, no phase logic in the loop.
    """
    dtype = origin.dtype
    lipschitz = sdf.lipschitz().astype(dtype)
    inv_lipschitz = 1.0 / lipschitz  # once per ray: a product per step, not a division
    relax = settings.over_relaxation != 1.0  # static: plain sphere tracing needs no fall-back
    omega0 = jnp.asarray(settings.over_relaxation, dtype)
    big = jnp.asarray(jnp.finfo(dtype).max, dtype)
    zero = jnp.zeros((), dtype)

    def ratio_at(t, r):
        # f / r(t): distance in pixel-cone radii (big where the cone has no width).
        return safe_div(r, cone[0] + cone[1] * t, big)

    def secant(s):
        # A ray whose budget ran out while already within the threshold still counts as a
        # hit. One still approaching a surface is finished: while sphere tracing converges
        # on a surface its distances fall geometrically, r_{k+1} = q r_k, and the secant
        # through the last two samples lands where the rest of the series would,
        # t + r / (1 − q) (grazing rays, with q → 1, are the ones that run out). It is a
        # hit if the distance there is within the threshold (or below the surface: the
        # ray crossed it; the Newton polish of `trace.polish_root` then settles it).
        t, r, done = s["t"], s["r"], s["done"]
        hit = s["hit"] | ((~done) & (r < threshold(settings, t, cone, origin + t * direction)))
        t_prev, r_prev = s["last_t"], s["last_r"]
        approaching = (~done) & (~hit) & (r < r_prev) & (t > t_prev)
        t_star = t + safe_div(r * (t - t_prev), jnp.where(approaching, r_prev - r, 1.0))
        t_star = jnp.where(approaching, jnp.minimum(t_star, t_max), t)
        return hit, approaching, t_star, origin + t_star * direction

    # t, r: the current sample (r = |f|/L there); t_prev, r_prev: the previous accepted
    # sample (over-relaxation); last_*: the previous accepted sample for the near-miss
    # search, last_lo the sample before it; best_*: the nearest near miss so far; start:
    # f(o), sign: −1 if the ray starts inside (it marches on |f|), f_star: f at the
    # secant finish. START sets the r's.
    init = dict(phase=jnp.asarray(START, jnp.int32), start=zero, sign=jnp.ones((), dtype),
                f_star=zero, t=zero, r=zero, steps=jnp.zeros((), jnp.int32),
                done=jnp.zeros((), bool), hit=jnp.zeros((), bool), last=big, last_t=zero,
                last_r=zero, last_lo=zero, best=big, best_t=zero, best_r=zero, best_lo=zero,
                best_hi=zero)
    if relax:
        init.update(t_prev=zero, r_prev=zero, omega=omega0)

    def step(s):
        """The march's step from the sample (t, r): the next state but for its r."""
        t, r = s["t"], s["r"]
        eps = threshold(settings, t, cone, origin + t * direction)
        new = dict(s)
        fail = None  # ω = 1: no step can fail, and the selects below vanish at trace time
        if relax:
            # Over-relaxation fall-back (Keinert et al. 2014): if the unbounding spheres
            # of the previous and current samples do not overlap, the long step may have
            # skipped a surface: return to the safe step from the previous sample.
            t_prev, r_prev, omega = s["t_prev"], s["r_prev"], s["omega"]
            fail = (omega > 1.0) & (r + r_prev < t - t_prev) & (s["steps"] > 0)

        def unless_fail(a, b):
            return b if fail is None else jnp.where(fail, a, b)

        def accepted(x):
            return x if fail is None else (~fail) & x

        is_hit = accepted(r < eps)
        # Near misses: when f/r grows again, the previous sample was a local minimum.
        ratio = ratio_at(t, r)
        rising = accepted(ratio > s["last"])
        better = rising & (s["last"] < s["best"])
        new["best"] = jnp.where(better, s["last"], s["best"])
        new["best_t"] = jnp.where(better, s["last_t"], s["best_t"])
        new["best_r"] = jnp.where(better, s["last_r"], s["best_r"])
        new["best_lo"] = jnp.where(better, s["last_lo"], s["best_lo"])
        new["best_hi"] = jnp.where(better, t, s["best_hi"])
        new["last"] = unless_fail(s["last"], ratio)
        new["last_t"] = unless_fail(s["last_t"], t)
        new["last_r"] = unless_fail(s["last_r"], r)
        new["last_lo"] = unless_fail(s["last_lo"], s["last_t"])
        t_next = unless_fail(t_prev + r_prev, t + omega * r) if relax else t + r
        escaped = (~is_hit) & (t_next > t_max)
        done = is_hit | escaped
        new["t"] = jnp.where(done, t, t_next)
        if relax:
            new["omega"] = unless_fail(1.0, omega).astype(dtype)
            new["t_prev"] = jnp.where(done, t_prev, unless_fail(t_prev, t))
            new["r_prev"] = jnp.where(done, r_prev, unless_fail(r_prev, r))
        new["steps"] = s["steps"] + 1
        new["done"] = done
        new["hit"] = is_hit
        return new

    def body(s):
        phase = s["phase"]
        marched = step(s)
        # The one evaluation: f(o), f at the next sample, or f at the secant finish.
        _, _, _, x_star = secant(s)
        x = jnp.where(phase == START, origin, jnp.where(
            phase == FINISH, x_star, origin + jnp.minimum(marched["t"], t_max) * direction))
        f = sdf(x)
        sign = jnp.where(phase == START, jnp.where(f < 0.0, -1.0, 1.0).astype(dtype), s["sign"])
        r = sign * f * inv_lipschitz
        marched["r"] = jnp.where(marched["done"], s["r"], r)
        is_march = phase == MARCH
        new = {k: jnp.where(is_march, marched[k], v) for k, v in s.items()}
        first = phase == START
        new["start"] = jnp.where(first, f, s["start"])
        new["sign"] = sign
        for k in ("r", "last_r", "best_r") + (("r_prev",) if relax else ()):
            new[k] = jnp.where(first, r, new[k])
        new["f_star"] = jnp.where(phase == FINISH, f, s["f_star"])
        # Next: the march while it lasts; the finish for a ray out of budget approaching
        # a surface; then done.
        going = (~new["done"]) & (new["steps"] < settings.max_steps)
        approaching = secant(new)[1]
        after = jnp.where(going, MARCH, jnp.where(approaching, FINISH, DONE))
        new["phase"] = jnp.where(first | is_march, after, DONE).astype(jnp.int32)
        return new

    if form.current() == "plain":
        s, start, f_star = _plain(sdf, origin, direction, settings, init, step, secant,
                                  inv_lipschitz, t_max)
    else:
        with tape.stepping():
            s = jax.lax.while_loop(lambda s: s["phase"] < DONE, body, init)
        start, f_star = s["start"], s["f_star"]
    t, r, done, sign = s["t"], s["r"], s["done"], s["sign"]
    hit, approaching, t_star, x_star = secant(s)
    finished = approaching & (t_star < t_max) & (
        sign * f_star * inv_lipschitz < threshold(settings, t_star, cone, x_star))
    hit = hit | finished
    t = jnp.where(finished, t_star, t)
    exhausted = (~done) & (~hit)
    # The last sample that the march accepted, and f there: where a ray out of budget
    # stopped (the candidate of an over-relaxed step that the next step would have
    # rejected is not accepted: the last safe sample before it is), where a ray that
    # escaped stepped beyond t_max from, or the hit's sample.
    last_t, last_r = s["t"], r
    if relax:
        rejected = exhausted & (s["omega"] > 1.0) & (r + s["r_prev"] < last_t - s["t_prev"]) & (
            s["steps"] > 0)
        last_t = jnp.where(rejected, s["t_prev"], last_t)
        last_r = jnp.where(rejected, s["r_prev"], last_r)
    # A ray that did not hit ends with a near miss: the smaller of its last two samples
    # (a budget that ran out leaves one sample that the loop did not examine).
    final = ratio_at(t, r)
    use_final = (~hit) & (~done) & (final < s["last"]) & (final < s["best"])
    use_last = (~hit) & (~use_final) & (s["last"] < s["best"])
    best_t = jnp.where(use_final, t, jnp.where(use_last, s["last_t"], s["best_t"]))
    best_r = jnp.where(use_final, r, jnp.where(use_last, s["last_r"], s["best_r"]))
    lo = jnp.where(use_final, s["last_t"], jnp.where(use_last, s["last_lo"], s["best_lo"]))
    hi = jnp.where(use_final, t, jnp.where(use_last, t, s["best_hi"]))
    return dict(
        # steps = max_steps + 1 marks a ray that ran out of budget (the `steps` AOV).
        t=jnp.where(hit, t, jnp.asarray(t_max, dtype)), hit=hit,
        steps=s["steps"] + exhausted.astype(jnp.int32),
        inside=start < 0.0, exhausted=exhausted, closest_t=best_t,
        closest_d=best_r * lipschitz * sign, closest_bracket=jnp.stack([lo, hi]),
        converging=exhausted & approaching, last_t=last_t, last_d=last_r * lipschitz * sign,
    )


def _plain(sdf, origin, direction, settings, init, step, secant, inv_lipschitz, t_max):
    """The "plain" form of `march`'s loop: f(o) before it, the march's steps alone in
    it (`step`, then f at the new sample), f at the secant finish after it. Returns
    (the final state, f(o), f at the secant finish)."""
    dtype = origin.dtype
    start = sdf(origin)
    sign = jnp.where(start < 0.0, -1.0, 1.0).astype(dtype)
    r0 = sign * start * inv_lipschitz
    init = {k: v for k, v in init.items() if k not in ("phase", "start", "f_star")}
    init.update(sign=sign, r=r0, last_r=r0, best_r=r0)
    if "r_prev" in init:
        init["r_prev"] = r0

    def body(s):
        new = step(s)
        x = origin + jnp.minimum(new["t"], t_max) * direction
        new["r"] = jnp.where(new["done"], s["r"], sign * sdf(x) * inv_lipschitz)
        return new

    with tape.stepping():
        s = jax.lax.while_loop(lambda s: (~s["done"]) & (s["steps"] < settings.max_steps),
                               body, init)
    x_star = secant(s)[3]
    return s, start, sdf(x_star)
