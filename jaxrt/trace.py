"""Ray queries: sphere tracing, differentiable hit points, analytic intersections, normals.

Sphere tracing (notes, "Ray marching implicit surfaces"; Hart 1996): march
t ← t + f(o + t d) / L from t = 0 until f < ε (hit), t > max_distance (miss) or the step
budget runs out (exhausted). L is the scene's Lipschitz factor (1 for distance bounds).
A ray that starts inside a surface (f(o) < 0) marches on |f| and finds where it leaves.

The loop (`jaxrt.march.sphere`, called through the tape of `jaxrt.march.tape`, so that a
render can record it in a fast kernel and replay it) is a bounded `lax.while_loop`
(vmapped it runs until every ray of the batch is done) and is not differentiated. The hit distance gets its gradient from the implicit
function theorem at the root of g(t; θ) = f(o + t d; θ): one Newton step from the
marched t̂ (held constant),

    t* = t̂ − f(o + t̂ d; θ) / (∇f · d),

has the value of a polished root and, because t̂ and ∇f·d carry no gradient, exactly the
derivative dt*/dθ = −(∂f/∂θ + ∇f · ∂(o + t d)/∂θ) / (∇f · d) of the design notes.
`settings.newton_steps` such steps are taken; the gradient is that of the last one, so
it is evaluated at the second-to-last iterate. The steps before it run in one bounded
loop with no gradient (`newton_march`: the program holds one copy of f and ∇f whatever
the number of steps), and only the last is taken differentiably (`newton_at`: one
evaluation of f, the slope recorded by the loop).

`settings.root_solver = "optimistix"` polishes instead with `optimistix.root_find`
(Newton from t̂, `ImplicitAdjoint`, `max_steps = newton_steps`, `throw=False`), whose
gradient is the implicit-function derivative at the final iterate. The two agree to
O(|t_k − t_{k−1}|) (the last Newton correction): to ~1e-12 in float64 at
newton_steps ≥ 2, to ~hit_epsilon·curvature at newton_steps = 1 (tests/test_gradients).
The hand-written rule is the default: it needs one SDF gradient per step and compiles
to a few lines.

Grazing hits (|∇f·d| ≤ GRAZING_COSINE·|∇f|) are not polished: t keeps the marched value
with a zero gradient, instead of dividing by ~0.

Closest approach (for silhouettes, `jaxrt.silhouette`): the tracer records the near
misses of the ray, the samples after which the cone-relative distance f/r(t) starts to
grow again (local minima along the march; r(t) = cone[0] + cone[1]·t, the pixel-cone
radius), and keeps the smallest, with its bracket (the samples before and after it). The
final approach to a hit is not a near miss (the ratio falls to ~0 there), so a ray that
hits the floor just behind a sphere still reports its near miss of the sphere.
"""

import equinox as eqx
import jax
import jax.numpy as jnp

from .march import tape
from .march.search import repeat
from .march.sphere import SphereTracing, hit_epsilon as hit_epsilon, march as march_sphere
from .vecmath import dot, normalize, safe_div, safe_sqrt, stop_gradient as stop_gradient

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
               the nearest near miss relative to the pixel cone: the marched sample
               with the smallest f / r(t) among those after which f / r grows again
               (and the last sample of a ray that did not hit), and f there; r(t) the
               cone radius. closest_t = 0 where there was none (or with a zero cone).
    closest_bracket
               [2] the marched samples before and after closest_t: the minimum of
               f / r along the ray near the near miss lies between them.
    converging an exhausted ray whose distance was still falling when the budget ran out
               (and whose secant finish found no surface): it may be about to hit
               something, where an exhausted ray that was receding is not.
    last_t, last_d
               the last sample that the march accepted and f there: where a ray out of
               budget stopped (an over-relaxed candidate that the next step would have
               rejected is not accepted; the safe sample before it is), the sample from
               which a ray that escaped stepped beyond t_max, or a hit's marched sample
               (before the secant finish and the polish). No gradient.
    normal, material
               with `sphere_trace(..., normal=True)`, the unit outward normal ∇f/|∇f|
               (differentiable) and the material index at o + t d, which the Newton
               loop evaluates in one more iteration (`newton_march`); None where that
               loop does not run (newton_steps = 0, root_solver "optimistix") or is
               replayed (the tape holds its t, not its normal).
    """

    t: jnp.ndarray
    hit: jnp.ndarray
    steps: jnp.ndarray | None
    inside: jnp.ndarray | None
    exhausted: jnp.ndarray | None
    closest_t: jnp.ndarray | None
    closest_d: jnp.ndarray | None
    closest_bracket: jnp.ndarray | None = None
    converging: jnp.ndarray | None = None
    last_t: jnp.ndarray | None = None
    last_d: jnp.ndarray | None = None
    normal: jnp.ndarray | None = None
    material: jnp.ndarray | None = None


HIT_FIELDS = ("t", "hit", "steps", "inside", "exhausted", "closest_t", "closest_d",
              "closest_bracket", "converging", "last_t", "last_d")


def sphere_trace(sdf, origin, direction, settings, cone=None, t_max=None, fields=None,
                 normal=False):
    """Sphere-trace one ray against `sdf`; see the module docstring.

    Args:
      sdf: a `jaxrt.sdf` node (or any object with `eval(p) -> (d, material)` and
        `lipschitz()`).
      origin, direction: [3] arrays; `direction` must be unit length.
      settings: `RenderSettings` or `jaxrt.march.SphereTracing` (max_steps, hit_epsilon,
        pixel_epsilon, max_distance, over_relaxation, newton_steps, root_solver).
      cone: (r0, spread) of the pixel cone, r(t) = r0 + spread · t (default: a cone of
        zero width, so the pixel epsilon is inactive).
      t_max: stop at this distance instead of settings.max_distance (shadow rays).
      fields: the `Hit` fields wanted (default all; the others are None): the march
        records only these when a render records its marches (`jaxrt.march.tape`).
      normal: also the normal and material at the hit (`Hit.normal`), from the Newton
        loop (one copy of f and ∇f in the program for the polish and the normal).

    Returns: `Hit`; `t` is differentiable with respect to the scene, origin and
    direction through the implicit function theorem when the ray hits.
    """
    options = SphereTracing.of(settings)
    if cone is None:
        cone = jnp.zeros(2, origin.dtype)
    t_max = options.max_distance if t_max is None else t_max
    wanted = HIT_FIELDS if fields is None else ("t", "hit") + tuple(fields)

    def run(sdf, origin, direction, cone, t_max):
        m = march_sphere(sdf, origin, direction, options, cone, t_max)
        return {k: m[k] for k in HIT_FIELDS if k in wanted}

    m = tape.march(run, stop_gradient(sdf), stop_gradient(origin), stop_gradient(direction),
                   stop_gradient(cone), stop_gradient(t_max))
    t, record = _polish(sdf, origin, direction, m["t"], m["hit"], options, normal)
    surface = {}
    if record is not None and "normal" in record:
        p = origin + t * direction
        surface = {"normal": evaluated(jax.tree_util.Partial(unit_gradient, sdf), p,
                                       record["normal"]),
                   "material": record["material"]}
    return Hit(**{**dict.fromkeys(HIT_FIELDS), **m, "t": t, **surface})


def polish_root(sdf, origin, direction, t, hit, settings):
    """Polish the marched root t̂ of g(t) = f(o + t d) where `hit`, with implicit gradients.

    `settings.newton_steps` Newton steps by the rule of `settings.root_solver`:
    "newton" (the default) or "optimistix" (`optimistix.root_find`).
    Where not `hit`, and at grazing hits, t̂ is returned with a zero gradient.

    Newton steps after the first are kept only while they contract,
    |Δt_k| ≤ |Δt_{k−1}| / 2 (quadratic convergence has set in): a ray that passes
    within ε of a surface without crossing it has a slope ≈ 0 at its closest approach,
    where an unguarded second step would jump arbitrarily far along the ray.

    "newton": the steps run in one bounded loop with no gradient (`newton_march`,
    through the tape: one copy of f and ∇f whatever newton_steps), which returns the
    iterate t_j from which the last kept step was taken and the slope ∇f·d there;
    that step is then taken once more, differentiably (`newton_at`): its value is the
    loop's last iterate and its gradient the implicit-function derivative of the
    module docstring, evaluated at t_j.
    """
    return _polish(sdf, origin, direction, t, hit, settings)[0]


def _polish(sdf, origin, direction, t, hit, settings, normal=False):
    """(`polish_root`'s t, the record of its Newton loop or None where none ran); with
    `normal`, the record also holds the unit normal and material at the polished root
    (`newton_march`), except on a replay (the tape keeps only what `newton_at` reads)."""
    if settings.newton_steps == 0:
        return t, None
    if settings.root_solver == "optimistix":
        return _polish_optimistix(sdf, origin, direction, t, hit, settings.newton_steps), None
    steps = settings.newton_steps
    record = tape.march(lambda *a: newton_march(*a, steps, normal=normal), stop_gradient(sdf),
                        stop_gradient(origin), stop_gradient(direction),
                        jax.lax.stop_gradient(t), hit, keep=("t", "slope", "f"))
    return newton_at(sdf, origin, direction, record["t"], record["slope"], record["f"]), record


def value_and_gradient(f, p, has_aux=False):
    """(f(p), ∇f(p)) of a scalar function of a point, as `jax.value_and_grad(f,
    has_aux=has_aux)(p)` gives them (with `has_aux`, f returns (value, aux), and the
    result is ((value, aux), ∇f)).

    Reverse mode, except in a program traced for a Pallas kernel that keeps scans as
    loops (`tape.forward_gradient()`): there forward mode, one JVP along each axis eₖ
    (∂f/∂xₖ = ∇f·eₖ) under `vmap`. A reverse pass through a stacked union's scan
    stacks one residual per child and reads them back in a second scan, which a Triton
    kernel cannot hold as a loop; the JVPs carry their tangents through the one scan.
    """
    if not tape.forward_gradient():
        return jax.value_and_grad(f, has_aux=has_aux)(p)
    g = f if has_aux else (lambda q: (f(q), ()))

    def along(e):
        value_aux, (slope, _) = jax.jvp(g, (p,), (e,))
        return value_aux, slope

    basis = jnp.eye(p.shape[-1], dtype=p.dtype)
    value_aux, grad = jax.vmap(along, out_axes=(None, 0))(basis)
    return (value_aux if has_aux else value_aux[0]), grad


def newton_march(sdf, origin, direction, t, hit, steps, normal=False):
    """`steps` guarded Newton steps t ← t − f(o + t d) / (∇f · d) from t̂ (no gradient;
    the rule of `polish_root`). Returns {"t": the iterate from which the last kept step
    was taken (t̂ if none was), "slope": ∇f·d there (0 if none was kept, or the hit
    grazes there), "f": f there (0 if none was kept)}: `newton_at` of the three is the
    polished root.

    With `normal`, the loop runs once more, at the polished root, and also returns the
    unit normal ∇f/|∇f| and the material index there ("normal", "material"): what
    `normal_and_material` would compute at the hit, from the loop's one copy of f and
    ∇f instead of a copy of its own (the showcase's "fused" render at 32×24 on 2 CPU
    cores, jax 0.10.2: XLA compile 21.3 → 19.4 s, one run each)."""
    def f_and_grad(q):
        return value_and_gradient(lambda x: sdf.eval(x) if normal else (sdf(x), ()), q,
                                  has_aux=True)

    inf = jnp.asarray(jnp.inf, t.dtype)
    zero = jnp.zeros((), t.dtype)
    material = jnp.zeros((), jnp.int32) if normal else ()

    def body(i, s):
        (t, ok, last, base, base_slope, base_f), _ = s
        (f, aux), grad = f_and_grad(origin + t * direction)
        slope, steep = _slope(grad, direction)
        t_new = jnp.where(steep, t - safe_div(f, jnp.where(steep, slope, 1.0)), t)
        delta = jnp.abs(t_new - t)
        ok = ok & ((i == 0) | (delta <= 0.5 * last))
        base = jnp.where(ok, t, base)
        base_slope = jnp.where(ok, jnp.where(steep, slope, zero), base_slope)
        base_f = jnp.where(ok, f, base_f)
        newton = (jnp.where(ok, t_new, t), ok, delta, base, base_slope, base_f)
        if normal:  # the last iteration only evaluates, at the polished root
            newton = jax.tree_util.tree_map(lambda a, b: jnp.where(i < steps, a, b), newton,
                                            s[0])
            return newton, (grad, aux)
        return newton, ()

    surface = (jnp.zeros_like(origin), material) if normal else ()
    (_, _, _, base, slope, f), surface = repeat(
        steps + normal, body, ((t, hit, inf, t, zero, zero), surface))
    out = {"t": base, "slope": slope, "f": f}
    if normal:
        out.update(normal=normalize(surface[0]), material=surface[1])
    return out


def newton_at(sdf, origin, direction, t, slope, f=None):
    """One Newton step on g(t) = f(o + t d) from constant t̂ with a given slope s = ∇f·d
    at t̂ (no gradient): t̂ − f(o + t̂ d) / s, with implicit gradients (module docstring).
    s = 0 (a grazing hit, or nothing to polish) keeps t̂, with a zero gradient. `f`: the
    value f(o + t̂ d) where a march has it (`evaluated`: f is then only evaluated where
    the step is differentiated)."""
    t0 = jax.lax.stop_gradient(t)
    slope = jax.lax.stop_gradient(slope)
    ok = slope != 0.0
    x = origin + t0 * direction
    f = sdf(x) if f is None else evaluated(sdf, x, f)
    return jnp.where(ok, t0 - safe_div(f, jnp.where(ok, slope, 1.0)), t0)


def evaluated(fn, x, value):
    """fn(x) whose value is known (`value`, from a march's record, no gradient): returns
    `value`, with the derivative of fn at x (its JVP in fn's float leaves and in x).

    A custom JVP: the primal program does not evaluate fn at all (a render without
    derivatives holds no copy of it); only a derivative traces fn's JVP at x."""
    dyn, static = eqx.partition((fn, x), eqx.is_inexact_array)

    @jax.custom_jvp
    def known(dyn, value):
        return value

    @known.defjvp
    def known_jvp(primals, tangents):
        dyn, value = primals
        d_dyn, _ = tangents

        def apply(dyn):
            fn, x = eqx.combine(dyn, static)
            return fn(x)

        _, d_value = jax.jvp(apply, (dyn,), (d_dyn,))
        return value, d_value.astype(value.dtype)

    return known(dyn, jax.lax.stop_gradient(value))


def newton_step(sdf, origin, direction, t):
    """One Newton step on g(t) = f(o + t d) from constant t̂, with implicit gradients.

    t̂ − f(o + t̂ d) / (∇f · d); the slope ∇f·d carries no gradient (module docstring).
    Grazing hits (|∇f·d| ≤ GRAZING_COSINE·|∇f|) keep t̂, with a zero gradient.
    """
    t0 = jax.lax.stop_gradient(t)
    f, grad = value_and_gradient(lambda q: sdf(q), origin + t0 * direction)
    slope, ok = _slope(grad, direction)
    return jnp.where(ok, t0 - safe_div(f, jnp.where(ok, slope, 1.0)), t0)


def _slope(grad, direction):
    """(∇f·d, not grazing), both without gradient."""
    grad = jax.lax.stop_gradient(grad)
    slope = dot(grad, jax.lax.stop_gradient(direction))
    return slope, jnp.abs(slope) > GRAZING_COSINE * jnp.sqrt(dot(grad, grad))


def _polish_optimistix(sdf, origin, direction, t, hit, steps):
    """`optimistix.root_find` (Newton, ImplicitAdjoint, `steps` steps, throw=False) from t̂.

    Rays that missed or graze are given the root problem y − t̂ = 0 instead (slope 1,
    no dependence on the scene), the double-`where` guard: their t keeps t̂ with a zero
    gradient, and the implicit adjoint never divides by a slope near 0.
    """
    t0 = jax.lax.stop_gradient(t)
    _, grad = value_and_gradient(lambda q: sdf(q),
                                 stop_gradient(origin) + t0 * stop_gradient(direction))
    _, ok = _slope(grad, direction)
    ok = ok & hit

    def g(y, args):
        sdf_, o, d = args
        return jnp.where(ok, sdf_(o + y * d), y - t0)

    import optimistix as optx  # here: importing it costs `jaxrt render` 0.12 s

    # Tolerances at rounding level: the step budget, not convergence, ends the polish.
    tol = 4.0 * float(jnp.finfo(t0.dtype).eps)
    solution = optx.root_find(g, optx.Newton(rtol=tol, atol=tol), t0,
                              args=(sdf, origin, direction), max_steps=steps,
                              adjoint=optx.ImplicitAdjoint(), throw=False)
    return jnp.where(ok, solution.value, t0)


def surface_normal(sdf, p, settings):
    """Unit outward normal ∇f/|∇f| at `p` by the estimator `settings.normal_mode`.

    "autodiff": exact gradient of the SDF; "central": central differences
    (f(p + h eᵢ) − f(p − h eᵢ)) / 2h; "tetrahedron": Σₖ kᵢ f(p + h kᵢ) over the four
    vertices kᵢ of a tetrahedron (Quilez, "normals for an SDF").
    """
    h = settings.normal_epsilon
    if settings.normal_mode == "autodiff":
        _, g = value_and_gradient(lambda q: sdf(q), p)
    elif settings.normal_mode == "central":
        e = jnp.eye(3, dtype=p.dtype) * h
        g = jax.vmap(lambda ei: sdf(p + ei) - sdf(p - ei))(e)
    else:
        k = jnp.array([[1, -1, -1], [-1, -1, 1], [-1, 1, -1], [1, 1, 1]], dtype=p.dtype)
        g = jnp.sum(k * jax.vmap(lambda ki: sdf(p + h * ki))(k)[:, None], axis=0)
    return normalize(g)


def unit_gradient(sdf, p):
    """∇f/|∇f| at p (the "autodiff" normal)."""
    return normalize(value_and_gradient(lambda q: sdf(q), p)[1])


def normal_and_material(sdf, p, settings):
    """(`surface_normal(sdf, p, settings)`, the material index at p): with the
    "autodiff" estimator both come from one evaluation of f (its gradient, and its
    material as an auxiliary output), so the program holds one copy of f for them."""
    if settings.normal_mode == "autodiff":
        (_, material), g = value_and_gradient(lambda q: sdf.eval(q), p, has_aux=True)
        return normalize(g), material
    return surface_normal(sdf, p, settings), sdf.eval(jax.lax.stop_gradient(p))[1]


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
