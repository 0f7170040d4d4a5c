"""Ray queries: sphere tracing, differentiable hit points, analytic intersections, normals.

Sphere tracing (notes, "Ray marching implicit surfaces"; Hart 1996): march
t ← t + f(o + t d) / L from t = 0 until f < ε (hit), t > max_distance (miss) or the step
budget runs out (exhausted). L is the scene's Lipschitz factor (1 for distance bounds).
A ray that starts inside a surface (f(o) < 0) marches on |f| and finds where it leaves.

The loop is a bounded `lax.while_loop` (vmapped it runs until every ray of the batch is
done) and is not differentiated. The hit distance gets its gradient from the implicit
function theorem at the root of g(t; θ) = f(o + t d; θ): one Newton step from the
marched t̂ (held constant),

    t* = t̂ − f(o + t̂ d; θ) / (∇f · d),

has the value of a polished root and, because t̂ and ∇f·d carry no gradient, exactly the
derivative dt*/dθ = −(∂f/∂θ + ∇f · ∂(o + t d)/∂θ) / (∇f · d) of the design notes.
"""

import equinox as eqx
import jax
import jax.numpy as jnp

from .vecmath import dot, normalize, safe_div, safe_sqrt

#: |∇f · d| below this is a grazing hit: the Newton correction (and its gradient) is
#: dropped there instead of dividing by ~0. A cosine of 1e-6 is ~0.00006° from tangent.
GRAZING_COSINE = 1e-6


class Hit(eqx.Module):
    """Result of tracing one ray.

    t          distance along the unit direction to the hit (max_distance on a miss).
    hit        True where the ray reached the surface (|f| < ε).
    steps      march steps used.
    inside     the ray started inside a surface (f(origin) < 0).
    exhausted  the budget ran out before the ray hit or left the scene.
    closest_t, closest_d
               the point of closest approach relative to the pixel cone: the marched
               sample that minimised f / r(t) (r(t) the cone radius), and f there.
    """

    t: jnp.ndarray
    hit: jnp.ndarray
    steps: jnp.ndarray
    inside: jnp.ndarray
    exhausted: jnp.ndarray
    closest_t: jnp.ndarray
    closest_d: jnp.ndarray


def hit_epsilon(settings, t, cone):
    """ε(t) = hit_epsilon + pixel_epsilon · r(t), with r(t) = cone[0] + cone[1] · t."""
    return settings.hit_epsilon + settings.pixel_epsilon * (cone[0] + cone[1] * t)


def sphere_trace(sdf, origin, direction, settings, cone=None, t_max=None):
    """Sphere-trace one ray against `sdf`; see the module docstring.

    Args:
      sdf: a `jaxrt.sdf` node (or any object with `eval(p) -> (d, material)` and
        `lipschitz()`).
      origin, direction: [3] arrays; `direction` must be unit length.
      settings: `RenderSettings` (max_steps, hit_epsilon, pixel_epsilon, max_distance,
        over_relaxation, newton_steps).
      cone: (r0, spread) of the pixel cone, r(t) = r0 + spread · t (default: a cone of
        zero width, so the pixel epsilon is inactive).
      t_max: stop at this distance instead of settings.max_distance (shadow rays).

    Returns: `Hit`; `t` is differentiable with respect to the scene, origin and
    direction through the implicit function theorem when the ray hits.
    """
    if cone is None:
        cone = jnp.zeros(2, origin.dtype)
    t_max = settings.max_distance if t_max is None else t_max
    t, hit, steps, inside, exhausted, ct, cd = _march(
        stop_gradient(sdf), stop_gradient(origin), stop_gradient(direction), settings,
        stop_gradient(cone), stop_gradient(t_max),
    )
    for _ in range(settings.newton_steps):
        t = jnp.where(hit, newton_step(sdf, origin, direction, t), t)
    return Hit(t=t, hit=hit, steps=steps, inside=inside, exhausted=exhausted,
               closest_t=ct, closest_d=cd)


def newton_step(sdf, origin, direction, t):
    """One Newton step on g(t) = f(o + t d) from constant t̂, with implicit gradients.

    t̂ − f(o + t̂ d) / (∇f · d); the slope ∇f·d carries no gradient (module docstring).
    Grazing hits (|∇f·d| ≤ GRAZING_COSINE·|∇f|) keep t̂, with a zero gradient.
    """
    t0 = jax.lax.stop_gradient(t)
    f, grad = jax.value_and_grad(lambda q: sdf(q))(origin + t0 * direction)
    grad = jax.lax.stop_gradient(grad)
    slope = dot(grad, jax.lax.stop_gradient(direction))
    ok = jnp.abs(slope) > GRAZING_COSINE * jnp.sqrt(dot(grad, grad))
    return jnp.where(ok, t0 - safe_div(f, jnp.where(ok, slope, 1.0)), t0)


def stop_gradient(tree):
    """`lax.stop_gradient` on the array leaves of a pytree (other leaves pass through)."""
    return jax.tree_util.tree_map(
        lambda x: jax.lax.stop_gradient(x) if eqx.is_array(x) else x, tree
    )


def _march(sdf, origin, direction, settings, cone, t_max):
    dtype = origin.dtype
    lipschitz = sdf.lipschitz().astype(dtype)
    omega0 = jnp.asarray(settings.over_relaxation, dtype)
    start = sdf(origin)
    sign = jnp.where(start < 0.0, -1.0, 1.0).astype(dtype)
    big = jnp.asarray(jnp.finfo(dtype).max, dtype)

    def radius_at(t):
        return sign * sdf(origin + t * direction) / lipschitz

    # state: t, r(t), t_prev, r_prev, omega, steps, done, hit, best_ratio, best_t, best_d
    r0 = sign * start / lipschitz
    init = (jnp.zeros((), dtype), r0, jnp.zeros((), dtype), r0, omega0,
            jnp.zeros((), jnp.int32), jnp.zeros((), bool), jnp.zeros((), bool),
            big, jnp.zeros((), dtype), r0)

    def cond(s):
        return (~s[6]) & (s[5] < settings.max_steps)

    def body(s):
        t, r, t_prev, r_prev, omega, steps, done, hit, best, best_t, best_d = s
        eps = hit_epsilon(settings, t, cone)
        # Over-relaxation fall-back (Keinert et al. 2014): if the unbounding spheres of
        # the previous and current samples do not overlap, the long step may have
        # skipped a surface: return to the safe step from the previous sample.
        fail = (omega > 1.0) & (r + r_prev < t - t_prev) & (steps > 0)
        is_hit = (~fail) & (r < eps)
        ratio = safe_div(r, cone[0] + cone[1] * t, big)
        better = (~fail) & (ratio < best)
        best, best_t, best_d = (jnp.where(better, ratio, best), jnp.where(better, t, best_t),
                                jnp.where(better, r, best_d))
        t_next = jnp.where(fail, t_prev + r_prev, t + omega * r)
        r_next_prev = jnp.where(fail, r_prev, r)
        t_next_prev = jnp.where(fail, t_prev, t)
        omega = jnp.where(fail, 1.0, omega).astype(dtype)
        escaped = (~is_hit) & (t_next > t_max)
        done = is_hit | escaped
        t_new = jnp.where(done, t, t_next)
        r_new = jnp.where(done, r, radius_at(jnp.minimum(t_new, t_max)))
        return (t_new, r_new, jnp.where(done, t_prev, t_next_prev),
                jnp.where(done, r_prev, r_next_prev), omega, steps + 1, done, is_hit,
                best, best_t, best_d)

    s = jax.lax.while_loop(cond, body, init)
    t, r, _, _, _, steps, done, hit, _, best_t, best_d = s
    # A ray whose budget ran out while already within epsilon still counts as a hit.
    hit = hit | ((~done) & (r < hit_epsilon(settings, t, cone)))
    exhausted = (~done) & (~hit)
    t = jnp.where(hit, t, jnp.asarray(t_max, dtype))
    return t, hit, steps, start < 0.0, exhausted, best_t, best_d * lipschitz * sign


def surface_normal(sdf, p, settings):
    """Unit outward normal ∇f/|∇f| at `p` by the estimator `settings.normal_mode`.

    "autodiff": exact gradient of the SDF; "central": central differences
    (f(p + h eᵢ) − f(p − h eᵢ)) / 2h; "tetrahedron": Σₖ kᵢ f(p + h kᵢ) over the four
    vertices kᵢ of a tetrahedron (Quilez, "normals for an SDF").
    """
    h = settings.normal_epsilon
    if settings.normal_mode == "autodiff":
        g = jax.grad(lambda q: sdf(q))(p)
    elif settings.normal_mode == "central":
        e = jnp.eye(3, dtype=p.dtype) * h
        g = jax.vmap(lambda ei: sdf(p + ei) - sdf(p - ei))(e)
    else:
        k = jnp.array([[1, -1, -1], [-1, -1, 1], [-1, 1, -1], [1, 1, 1]], dtype=p.dtype)
        g = jnp.sum(k * jax.vmap(lambda ki: sdf(p + h * ki))(k)[:, None], axis=0)
    return normalize(g)


def intersect_plane(origin, direction, normal, offset):
    """Ray–plane intersection (notes): t = (offset − n·o) / (n·d) for the plane n·p = offset.

    Returns (t, hit): hit is False for rays parallel to the plane or with t < 0.
    """
    denom = dot(normal, direction)
    ok = jnp.abs(denom) > 0.0
    t = safe_div(offset - dot(normal, origin), denom)
    return t, ok & (t >= 0.0)


def intersect_sphere(origin, direction, center, radius):
    """Ray–sphere intersection for a unit direction: nearest t ≥ 0 of |o + t d − c| = r.

    With oc = o − c, b = oc·d, c' = |oc|² − r²: t = −b ∓ sqrt(b² − c'). A ray from
    inside returns the exit point. Returns (t, hit).
    """
    oc = origin - center
    b = dot(oc, direction)
    c = dot(oc, oc) - radius * radius
    disc = b * b - c
    ok = disc >= 0.0
    root = safe_sqrt(disc)
    # Numerically stable pair of roots (avoid cancellation in −b + root).
    q = -b - jnp.where(b >= 0.0, root, -root)
    t1 = q
    t2 = safe_div(c, q)
    near, far = jnp.minimum(t1, t2), jnp.maximum(t1, t2)
    t = jnp.where(near >= 0.0, near, far)
    return t, ok & (t >= 0.0)
