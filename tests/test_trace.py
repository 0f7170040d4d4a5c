"""Sphere tracing against analytic intersections and brute-force scans of the ray."""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrt as jr
from jaxrt import sdf

from helpers import first_crossing, random_directions, to_dtype, unit

DEFAULT = jr.RenderSettings()
#: float64 reference settings: a tight epsilon and a budget large enough for grazing rays.
TIGHT = jr.RenderSettings(dtype="float64", hit_epsilon=1e-12, max_steps=20000)


@eqx.filter_jit
def trace(node, origins, directions, settings):
    """`sphere_trace` vmapped over rays (settings are static)."""
    return jax.vmap(lambda o, d: jr.sphere_trace(node, o, d, settings))(origins, directions)


def run(node, origins, directions, settings, dtype=jnp.float64):
    node = to_dtype(node, dtype)
    hit = trace(node, jnp.asarray(origins, dtype), jnp.asarray(directions, dtype), settings)
    return jax.tree_util.tree_map(np.asarray, hit)


# -- numpy closed forms --------------------------------------------------------------


def np_sphere_hit(o, d, c, r):
    """Nearest t ≥ 0 of |o + t d − c| = r (unit d), in numpy; (t, hit)."""
    oc = o - c
    b = np.sum(oc * d, axis=1)
    cc = np.sum(oc * oc, axis=1) - r * r
    disc = b * b - cc
    root = np.sqrt(np.maximum(disc, 0.0))
    near, far = -b - root, -b + root
    t = np.where(near >= 0.0, near, far)
    return t, (disc >= 0.0) & (t >= 0.0)


def np_plane_hit(o, d, n, offset):
    t = (offset - o @ n) / (d @ n)
    return t, np.isfinite(t) & (t >= 0.0)


def grazing_rays(origin_distance, impact, radius=1.0):
    """Rays from (0, 0, −D) whose line passes `impact` from the centre of a sphere at
    the origin, in several azimuths: [N, 3] origins and directions."""
    origins, directions = [], []
    for k, b in enumerate(impact):
        phi = 2.0 * np.pi * k / len(impact) * 7.0
        a = np.arcsin(b * radius / origin_distance)
        d = np.array([np.sin(a) * np.cos(phi), np.sin(a) * np.sin(phi), np.cos(a)])
        origins.append([0.0, 0.0, -origin_distance])
        directions.append(d)
    return np.array(origins), np.array(directions)


# -- spheres and planes --------------------------------------------------------------

IMPACT = np.concatenate([np.linspace(0.0, 0.99, 12), [0.995, 0.999, 0.9995, 0.9999]])


def test_sphere_float32_default_settings_including_near_grazing():
    """Depth error ≤ 1e-4 relative in float32 at default settings, down to 0.8° from
    tangent (impact parameter 0.9999 R); beyond the tangent the rays miss."""
    c, r = np.array([0.3, -0.2, 0.5]), 1.0
    o, d = grazing_rays(5.0, IMPACT)
    o = o + c
    h = run(sdf.Translate(sdf.Sphere(r), c), o, d, DEFAULT, jnp.float32)
    t_ref, hit_ref = np_sphere_hit(o, d, c, r)
    assert hit_ref.all() and h.hit.all() and not h.exhausted.any()
    np.testing.assert_array_less(np.abs(h.t - t_ref) / t_ref, 1e-4)
    t_jax, hit_jax = jax.vmap(jr.intersect_sphere, (0, 0, None, None))(
        jnp.asarray(o), jnp.asarray(d), jnp.asarray(c), r)
    np.testing.assert_allclose(np.asarray(t_jax), t_ref, rtol=1e-12)
    # Rays that pass more than ε from the sphere miss; between 0.9999 R and the tangent
    # they either hit accurately, or (at the tangent, where a budget that runs out is
    # finished by the secant of `march.sphere`) hit within the ε band, or run out of
    # budget (and say so).
    o2, d2 = grazing_rays(5.0, [1.0002, 1.001, 1.1, 0.99995, 0.99999, 1.0])
    h2 = run(sdf.Sphere(r), o2, d2, DEFAULT, jnp.float32)
    assert not h2.hit[:3].any()
    t2, _ = np_sphere_hit(o2, d2, np.zeros(3), r)
    in_band = np.abs(np.linalg.norm(o2 + h2.t[:, None] * d2, axis=1) - r) <= 2 * DEFAULT.hit_epsilon
    accurate = np.abs(h2.t - t2) / t2 < 1e-4
    ok = h2.exhausted[3:] | (h2.hit[3:] & (accurate[3:] | (in_band[3:] & (np.arange(3) == 2))))
    assert ok.all()
    assert np.all(np.isfinite(h2.t)) and np.all(h2.t[~h2.hit] == DEFAULT.max_distance)


def test_sphere_float64_tight_epsilon():
    """≤ 1e-9 relative in float64 with hit_epsilon = 1e-12, down to 0.26° from tangent."""
    c, r = np.array([-1.0, 2.0, 0.5]), 0.7
    impact = np.concatenate([IMPACT, [0.99999]])
    o, d = grazing_rays(4.0, impact, r)
    o = o + c
    rng = np.random.default_rng(0)
    # And random rays from random places aimed at random points of the sphere.
    o_r = c + random_directions(rng, 200) * rng.uniform(1.5, 20.0, (200, 1))
    d_r = unit(c + rng.uniform(-0.6, 0.6, (200, 3)) - o_r)
    o, d = np.concatenate([o, o_r]), np.concatenate([d, d_r])
    h = run(sdf.Translate(sdf.Sphere(r), c), o, d, TIGHT)
    t_ref, hit_ref = np_sphere_hit(o, d, c, r)
    np.testing.assert_array_equal(h.hit, hit_ref)
    np.testing.assert_allclose(h.t[hit_ref], t_ref[hit_ref], rtol=1e-9)
    assert not h.inside.any()


@pytest.mark.parametrize("precision", ["float32", "float64"])
def test_plane_matches_ray_plane_intersection(precision):
    n, offset = unit([0.2, 1.0, -0.3]), 0.4
    rng = np.random.default_rng(1)
    # Origins above the plane, directions from steep to 6° (float32 default) or 0.1°
    # (float64) above grazing, and some pointing away. In float32 at the default budget
    # of 128 steps, rays between 0.5° and 6° may run out of steps (sphere tracing needs
    # ~ln(h/ε)/sin θ of them): they must say so, or hit accurately (or miss beyond
    # max_distance).
    m = 170
    o = rng.uniform(-3, 3, (m, 3))
    o = o + (offset - o @ n + rng.uniform(0.05, 3.0, m))[:, None] * n
    low = 6.0 if precision == "float32" else 0.1
    elevation = np.radians(np.concatenate([rng.uniform(low, 90.0, m - 40), [low] * 5,
                                           -rng.uniform(1.0, 90.0, 15), rng.uniform(low / 10, low, 20)]))
    tangent = unit(np.cross(n, random_directions(rng, m)))
    d = -np.sin(elevation)[:, None] * n + np.cos(elevation)[:, None] * tangent
    settings = DEFAULT if precision == "float32" else TIGHT
    h = run(sdf.Plane(n, offset), o, d, settings, getattr(jnp, precision))
    t_ref, hit_ref = np_plane_hit(o, d, n, offset)
    hit_ref &= t_ref < settings.max_distance
    tol = 1e-4 if precision == "float32" else 1e-9
    sure = slice(0, m - 20)
    np.testing.assert_array_equal(h.hit[sure], hit_ref[sure])
    np.testing.assert_array_less(np.abs(h.t - t_ref)[sure][hit_ref[sure]] / t_ref[sure][hit_ref[sure]], tol)
    grazing = slice(m - 20, m)
    accurate = h.hit & hit_ref & (np.abs(h.t - t_ref) / t_ref < tol)
    far = ~h.hit & ~hit_ref
    assert np.all((h.exhausted | accurate | far)[grazing])
    if precision == "float32":
        assert accurate[grazing].any()
    t_jax, hit_jax = jax.vmap(jr.intersect_plane, (0, 0, None, None))(
        jnp.asarray(o), jnp.asarray(d), jnp.asarray(n), offset)
    np.testing.assert_array_equal(np.asarray(hit_jax), t_ref >= 0)
    np.testing.assert_allclose(np.asarray(t_jax)[hit_ref], t_ref[hit_ref], rtol=1e-12)


def test_intersect_sphere_from_inside_behind_and_tangent():
    c, r = jnp.array([0.0, 0.0, 0.0]), 1.0
    t, hit = jr.intersect_sphere(jnp.array([0.0, 0.0, 0.5]), jnp.array([0.0, 0.0, 1.0]), c, r)
    assert bool(hit) and float(t) == pytest.approx(0.5)  # exit from inside
    t, hit = jr.intersect_sphere(jnp.array([0.0, 0.0, 3.0]), jnp.array([0.0, 0.0, 1.0]), c, r)
    assert not bool(hit)  # sphere behind the ray
    t, hit = jr.intersect_sphere(jnp.array([1.0, 0.0, -3.0]), jnp.array([0.0, 0.0, 1.0]), c, r)
    assert bool(hit) and float(t) == pytest.approx(3.0)  # tangent
    t, hit = jr.intersect_plane(jnp.zeros(3), jnp.array([1.0, 0.0, 0.0]), jnp.array([0.0, 1.0, 0.0]), 1.0)
    assert not bool(hit) and np.isfinite(float(t))  # parallel


def test_newton_polish_gives_implicit_gradients():
    """dt/dr and dt/do of a sphere hit equal the analytic derivatives (float64)."""
    o0, d = jnp.array([0.2, 0.1, -4.0]), jnp.asarray(unit([0.1, 0.05, 1.0]))

    def t_of(r, o):
        return jr.sphere_trace(sdf.Sphere(r), o, d, jr.RenderSettings(hit_epsilon=1e-6)).t

    def t_ref(r, o):
        b = jnp.dot(o, d)
        return -b - jnp.sqrt(b * b - jnp.dot(o, o) + r * r)

    g, g_ref = jax.grad(t_of, (0, 1))(0.9, o0), jax.grad(t_ref, (0, 1))(0.9, o0)
    np.testing.assert_allclose(float(g[0]), float(g_ref[0]), rtol=1e-9)
    np.testing.assert_allclose(np.asarray(g[1]), np.asarray(g_ref[1]), rtol=1e-9, atol=1e-12)


# -- over-relaxation, inside, exhausted ----------------------------------------------


def thin_plates():
    """Thin plates (half-thickness 0.004) and a thin ring: easy to tunnel through."""
    plates = [sdf.Translate(sdf.Box((1.5, 1.5, 0.004)), (0.0, 0.0, z)) for z in (-0.5, 0.3, 1.0)]
    ring = sdf.Translate(sdf.Torus(0.8, 0.004), (0.0, 0.0, -1.2))
    return sdf.Union(*plates, ring, sdf.Translate(sdf.Sphere(0.3), (0.0, 0.0, 2.0)))


@functools.cache
def thin_plate_rays():
    """Rays at the thin plates, their plain sphere-traced hits and a brute-force scan."""
    node = thin_plates()
    rng = np.random.default_rng(2)
    n = 160
    o = np.tile([0.0, 0.0, -4.0], (n, 1)) + rng.uniform(-2, 2, (n, 3)) * [1, 1, 0]
    d = unit(rng.uniform(-1.8, 1.8, (n, 3)) * [1, 1, 0] + [0, 0, 4.0] - o * [1, 1, 0] * 0.5)
    plain = run(node, o, d, THIN)
    t_ref, step = first_crossing(node, o, d, 8.0, 20001)
    return node, o, d, plain, t_ref, step


THIN = jr.RenderSettings(dtype="float64", hit_epsilon=1e-7, max_steps=1000)


@pytest.mark.parametrize("omega", [1.5, 1.95])
def test_over_relaxation_gives_the_same_hits(omega):
    node, o, d, plain, t_ref, step = thin_plate_rays()
    relaxed = run(node, o, d, THIN.replace(over_relaxation=omega))
    assert 0.3 < plain.hit.mean() < 1.0
    np.testing.assert_array_equal(plain.hit, np.isfinite(t_ref))
    np.testing.assert_array_equal(relaxed.hit, plain.hit)
    np.testing.assert_allclose(relaxed.t[plain.hit], plain.t[plain.hit], atol=1e-6)
    assert np.all(np.abs(plain.t - t_ref)[plain.hit] <= step)
    assert not relaxed.exhausted.any()


def test_rays_that_start_inside_find_the_exit():
    rng = np.random.default_rng(3)
    c, r = np.array([0.5, 0.0, -0.2]), 1.2
    o = c + random_directions(rng, 200) * rng.uniform(0.0, 0.95 * r, (200, 1))
    d = random_directions(rng, 200)
    h = run(sdf.Translate(sdf.Sphere(r), c), o, d, TIGHT)
    t_ref, _ = np_sphere_hit(o, d, c, r)
    assert h.inside.all() and h.hit.all()
    np.testing.assert_allclose(h.t, t_ref, rtol=1e-9)
    # Inside a union of a box and a sphere (a bound inside): the exit is the first
    # crossing of the surface from inside.
    node = sdf.Union(sdf.Box((1.0, 0.4, 0.4)), sdf.Translate(sdf.Sphere(0.6), (1.0, 0.0, 0.0)))
    o = rng.uniform(-0.3, 0.3, (100, 3)) * [3, 1, 1]
    d = random_directions(rng, 100)
    h = run(node, o, d, TIGHT)
    t_ref, step = first_crossing(node, o, d, 3.0, 15001, inside=True)
    assert h.inside.all() and h.hit.all()
    assert np.all(np.abs(h.t - t_ref) <= step)


def test_rays_that_exhaust_their_budget_say_so_with_finite_output():
    # Rays that pass close to a sphere (or graze it) need many steps.
    o, d = grazing_rays(10.0, [0.9, 0.99, 1.01, 1.001])
    settings = jr.RenderSettings(max_steps=4)
    h = run(sdf.Sphere(1.0), o, d, settings, jnp.float32)
    assert h.exhausted.all() and not h.hit.any()
    assert np.all(h.steps == 4 + 1)  # max_steps + 1 marks a ray that ran out
    assert np.all(h.t == settings.max_distance)
    for leaf in jax.tree_util.tree_leaves(h):
        assert np.all(np.isfinite(np.asarray(leaf, float)))
    # A ray parallel to a plane, just above it, never reaches it nor leaves.
    h = run(sdf.Plane((0.0, 1.0, 0.0), 0.0), [[0.0, 1e-3, 0.0]], [[1.0, 0.0, 0.0]], DEFAULT, jnp.float32)
    assert h.exhausted.all() and np.all(np.isfinite(h.t))


def test_rays_on_the_surface_and_tangent_rays_are_finite():
    node = sdf.Sphere(1.0)
    o = np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, -3.0], [0.0, 0.0, 0.0]])
    d = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    h = run(node, o, d, DEFAULT, jnp.float32)
    for leaf in jax.tree_util.tree_leaves(h):
        assert np.all(np.isfinite(np.asarray(leaf, float)))
    assert h.hit[:2].all()  # starting on the surface is a hit at t ≈ 0
    assert np.all(np.abs(h.t[:2]) < 1e-3)
    assert h.hit[3] and h.t[3] == pytest.approx(1.0, abs=1e-5)


# -- deformations are never tunnelled through ----------------------------------------

DEFORMED = {  # shape, over-relaxation
    "twist": (sdf.Twist(sdf.Box((0.6, 1.0, 0.08)), rate=3.0, radius=float(np.hypot(0.6, 0.08))), 1.0),
    "bend": (sdf.Bend(sdf.Box((1.0, 0.08, 0.4)), rate=1.5, radius=float(np.hypot(1.0, 0.08))), 1.0),
    "displace": (sdf.Displace(sdf.Sphere(1.0), sdf.SineDisplacement(6.0), amplitude=0.35), 1.6),
    "displaced_twist": (sdf.Displace(sdf.Twist(sdf.Box((0.5, 0.8, 0.5)), rate=2.0, radius=0.71),
                                     sdf.SineDisplacement(8.0), amplitude=0.1), 1.6),
}


@pytest.mark.parametrize("name", DEFORMED)
def test_deformed_shapes_are_never_tunnelled_through(name):
    node, omega = DEFORMED[name]
    rng = np.random.default_rng(4)
    n = 120
    o = random_directions(rng, n) * 3.0
    d = unit(rng.uniform(-0.9, 0.9, (n, 3)) - o)
    t_ref, step = first_crossing(node, o, d, 6.0, 20001)
    settings = jr.RenderSettings(dtype="float64", hit_epsilon=1e-6, max_steps=3000,
                                 over_relaxation=omega)
    marched = run(node, o, d, settings.replace(newton_steps=0))
    np.testing.assert_array_equal(marched.hit, np.isfinite(t_ref))
    assert not marched.exhausted.any()
    # The march stops before the first crossing, never beyond it.
    h = marched.hit
    assert np.all(marched.t[h] <= t_ref[h] + 1e-9)
    polished = run(node, o, d, settings)
    assert np.all(np.abs(polished.t - t_ref)[h] <= step)


# -- normals -------------------------------------------------------------------------


@pytest.mark.parametrize("mode", ["autodiff", "central", "tetrahedron"])
def test_normal_estimators_converge_to_the_sphere_normal(mode):
    """autodiff is exact; central differences are O(h²); the tetrahedron technique is
    O(h·curvature) (its vertices' third moment does not vanish)."""
    rng = np.random.default_rng(5)
    c, r = np.array([0.2, -0.4, 1.0]), 0.8
    n_true = random_directions(rng, 50)
    p = c + r * n_true
    node = sdf.Translate(sdf.Sphere(r), c)

    def error(h):
        settings = jr.RenderSettings(normal_mode=mode, normal_epsilon=h)
        n = jax.vmap(lambda q: jr.surface_normal(node, q, settings))(jnp.asarray(p))
        return np.max(np.linalg.norm(np.asarray(n) - n_true, axis=1))

    e1, e2 = error(1e-3), error(2.5e-4)
    if mode == "autodiff":
        assert e1 < 1e-14 and e2 < 1e-14
    elif mode == "central":
        assert e1 < 1e-6 and e1 / e2 > 10.0  # 16 for second order
    else:
        assert e1 < 1e-3 / r and e1 / e2 > 3.0  # 4 for first order
    # Finite at the centre, where the gradient of the sphere vanishes.
    settings = jr.RenderSettings(normal_mode=mode)
    assert np.all(np.isfinite(np.asarray(jr.surface_normal(node, jnp.asarray(c), settings))))


def test_value_and_gradient_in_forward_mode_is_reverse_modes():
    """`trace.value_and_gradient`: in a program traced for Pallas's loops
    (`tape.forward_gradients`) the gradient is three JVPs, elsewhere one reverse pass;
    both are the gradient of a stacked union (a scan) and carry its material along."""
    from jaxrt.march import tape
    from jaxrt.trace import value_and_gradient

    union = sdf.Union(*[sdf.Translate(sdf.Sphere(0.3 + 0.1 * i, material=i % 2),
                                      offset=(0.7 * i, 0.2 * i, -0.1 * i)) for i in range(8)])
    union = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float64)
                                   if eqx.is_inexact_array(x) else x, union)
    p = jnp.array([1.3, 0.4, -0.2])
    assert "scan" in str(jax.make_jaxpr(union.eval)(p))  # the children stacked
    results = []
    for forward in (False, True):
        with tape.forward_gradients(forward):
            f, g = jax.jit(lambda q: value_and_gradient(lambda x: union.eval(x)[0], q))(p)
            (f_aux, material), g_aux = jax.jit(
                lambda q: value_and_gradient(union.eval, q, has_aux=True))(p)
        results.append((f, g, f_aux, material, g_aux))
    (f0, g0, fa0, m0, ga0), (f1, g1, fa1, m1, ga1) = results
    np.testing.assert_allclose([f1, fa1, fa0], f0, rtol=1e-15)
    np.testing.assert_allclose(g1, g0, rtol=1e-14, atol=1e-15)
    np.testing.assert_allclose(ga1, g0, rtol=1e-14, atol=1e-15)
    np.testing.assert_allclose(ga0, g0, rtol=1e-15)
    assert int(m0) == int(m1) == 0 and abs(float(jnp.linalg.norm(g0)) - 1.0) < 1e-12
