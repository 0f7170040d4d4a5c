"""Specular materials in the renderer path (jaxrt/bsdf/specular.py through
`integrator.shade_ray`): Snell's law, total internal reflection, Fresnel weights, a glass
slab, Beer–Lambert absorption, conductors and the notes' constant weights.

Every check runs the ray through the integrator (trace, normal, material, weights,
spawned children), in float64, and compares with closed forms written here.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrt as jr
from jaxrt import integrator
from jaxrt.bsdf import Conductor, Dielectric, Lambert, Mirror, Whitted

ETA = 1.5
# Sphere tracing towards a plane at slope s converges like (1 − s)^k: a budget that
# reaches the plane at 89° incidence.
SETTINGS = jr.RenderSettings(dtype="float64", shadows="none", max_steps=2048)
UP = (0.0, 1.0, 0.0)


def half_space(material):
    """y < 0 filled with `material` (the plane y = 0, normal +y)."""
    return jr.Scene(surface=jr.sdf.Plane(normal=UP, offset=0.0, material=0),
                    materials=[material], background=(1.0, 1.0, 1.0))


def slab(material, thickness=1.0):
    """−thickness < y < 0 filled with `material`."""
    surface = jr.sdf.Intersection(jr.sdf.Plane(normal=UP, offset=0.0, material=0),
                                  jr.sdf.Plane(normal=(0.0, -1.0, 0.0), offset=thickness, material=0))
    return jr.Scene(surface=surface, materials=[material], background=(0.25, 0.5, 1.0))


@functools.lru_cache(maxsize=None)
def _shader(scene_key):
    scene = _SCENES[scene_key]

    @jax.jit
    def shade(origins, directions):
        return jax.vmap(lambda o, d: integrator.shade_ray(
            scene, integrator.camera_ray(o, d), SETTINGS))(origins, directions)

    return shade


_SCENES = {
    "glass": half_space(Dielectric(ETA)),
    "slab": slab(Dielectric(ETA)),
}


@jax.jit
def shade_one(scene, o, d):
    return integrator.shade_ray(scene, integrator.camera_ray(o, d), SETTINGS)


def shade(key, origins, directions):
    return _shader(key)(jnp.asarray(origins, float), jnp.asarray(directions, float))


def rays_to_plane(theta, from_below=False):
    """Rays in the xy plane that hit y = 0 at x = 0 with incidence angle theta."""
    theta = np.asarray(theta, float)
    s, c = np.sin(theta), np.cos(theta)
    sign = -1.0 if from_below else 1.0
    d = np.stack([s, -sign * c, 0 * s], -1)
    o = -d * (0.7 / np.maximum(c, 0.05))[:, None]
    return o, d


def sin_to_normal(w):
    """sin of the angle between w and the y axis."""
    w = np.asarray(w)
    return np.hypot(w[:, 0], w[:, 2]) / np.linalg.norm(w, axis=1)


THETAS = np.radians(np.linspace(0.0, 85.0, 35))


def test_snell_law_and_unit_length_entering():
    o, d = rays_to_plane(THETAS)
    out = shade("glass", o, d)
    wt = np.asarray(out.children["transmit"].direction)
    assert np.all(np.asarray(out.children["transmit"].alive))
    np.testing.assert_allclose(np.linalg.norm(wt, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.sin(THETAS) - ETA * sin_to_normal(wt), 0.0, atol=1e-9)
    assert np.all(wt[:, 1] < 0.0)                       # goes into the glass
    assert np.all(np.sign(wt[:, 0]) >= 0.0) and np.allclose(wt[:, 2], 0.0, atol=1e-15)  # plane of incidence
    wr = np.asarray(out.children["reflect"].direction)
    np.testing.assert_allclose(wr, d * np.array([1.0, -1.0, 1.0]), atol=1e-12)  # mirror
    # Each child starts off the surface on the side it leaves, by spawn_offset.
    offset = float(integrator.spawn_offset(jnp.zeros(3), SETTINGS))
    np.testing.assert_allclose(np.asarray(out.children["reflect"].origin)[:, 1], offset, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(out.children["transmit"].origin)[:, 1], -offset, rtol=1e-6)


def test_snell_law_leaving_and_total_internal_reflection():
    critical = np.arcsin(1.0 / ETA)
    below = THETAS[THETAS < critical - 1e-3]
    o, d = rays_to_plane(below, from_below=True)
    out = shade("glass", o, d)                             # rays start inside the glass
    wt = np.asarray(out.children["transmit"].direction)
    assert np.all(np.asarray(out.children["transmit"].alive))
    np.testing.assert_allclose(ETA * np.sin(below) - sin_to_normal(wt), 0.0, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(wt, axis=1), 1.0, atol=1e-12)
    assert np.all(wt[:, 1] > 0.0)

    # TIR exactly beyond the critical angle, and not before it.
    thetas = critical * np.array([1 - 1e-6, 1 - 1e-9, 1 + 1e-9, 1 + 1e-6, 1.2, 1.5])
    o, d = rays_to_plane(thetas, from_below=True)
    out = shade("glass", o, d)
    alive = np.asarray(out.children["transmit"].alive)
    np.testing.assert_array_equal(alive, thetas < critical)
    reflected = np.asarray(out.children["reflect"].weight)
    np.testing.assert_allclose(reflected[~alive], 1.0, atol=0)           # all to reflection
    assert np.all(np.asarray(out.children["transmit"].weight)[~alive] == 0.0)
    assert np.all(np.isfinite(np.asarray(out.children["transmit"].direction)))


def fresnel_reference(cos_i, n1, n2):
    """Unpolarised Fresnel reflectance from the s and p amplitudes (Born & Wolf)."""
    sin_t = n1 / n2 * np.sqrt(1.0 - cos_i**2)
    tir = sin_t >= 1.0
    cos_t = np.sqrt(np.maximum(0.0, 1.0 - sin_t**2))
    rs = (n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t)
    rp = (n2 * cos_i - n1 * cos_t) / (n2 * cos_i + n1 * cos_t)
    return np.where(tir, 1.0, 0.5 * (rs**2 + rp**2))


@pytest.mark.parametrize("from_below", [False, True])
def test_fresnel_weights_split_flux(from_below):
    thetas = np.radians(np.linspace(0.0, 89.0, 40))
    o, d = rays_to_plane(thetas, from_below)
    out = shade("glass", o, d)
    r = np.asarray(out.children["reflect"].weight)[:, 0]
    t = np.asarray(out.children["transmit"].weight)[:, 0]
    n1, n2 = (ETA, 1.0) if from_below else (1.0, ETA)
    np.testing.assert_allclose(r, fresnel_reference(np.cos(thetas), n1, n2), atol=1e-12)
    # The transmitted weight carries the radiance factor 1/η'², η' = n2/n1; in flux,
    # reflected + transmitted = 1 for a non-absorbing dielectric.
    np.testing.assert_allclose(r + t * (n2 / n1) ** 2, 1.0, atol=1e-12)
    assert np.all((r >= 0) & (r <= 1) & (t >= 0))


def test_glass_slab_path_leaves_parallel_and_shifted():
    thetas = np.radians([0.0, 10.0, 35.0, 60.0, 80.0])
    o, d = rays_to_plane(thetas)
    first = shade("slab", o, d).children["transmit"]
    second = shade("slab", first.origin, first.direction)   # starts inside the glass
    exit_ray = second.children["transmit"]
    assert np.all(np.asarray(exit_ray.alive))
    np.testing.assert_allclose(np.asarray(exit_ray.direction), d, atol=1e-9)
    # Lateral shift of the exit point: x = thickness · tan θt (closed form), where the
    # ray inside starts `offset` below the top face.
    theta_t = np.arcsin(np.sin(thetas) / ETA)
    exit_point = np.asarray(exit_ray.origin)
    offset = float(integrator.spawn_offset(jnp.zeros(3), SETTINGS))
    np.testing.assert_allclose(exit_point[:, 1], -1.0 - offset, atol=1e-9)
    np.testing.assert_allclose(exit_point[:, 0], (1.0 - offset) * np.tan(theta_t), atol=1e-9)
    # Radiance weights (1 − F)/η² in, (1 − F')·η² out (`second` restarts at weight 1);
    # F' = F (the angle inside is θt on both faces): the path carries (1 − F)².
    f = fresnel_reference(np.cos(thetas), 1.0, ETA)
    w_in, w_out = np.asarray(first.weight)[:, 0], np.asarray(exit_ray.weight)[:, 0]
    np.testing.assert_allclose(w_in, (1 - f) / ETA**2, atol=1e-12)
    np.testing.assert_allclose(w_in * w_out, (1 - f) ** 2, atol=1e-12)


@functools.partial(jax.jit, static_argnums=3)
def _render_ray(scene, o, d, depth):
    settings = SETTINGS.replace(max_depth=depth)
    return integrator.trace_radiance(scene, o, d, jnp.zeros(2), settings)["rgb"]


def test_beer_lambert_through_index_matched_slab():
    # η = 1: no refraction and no reflection, only absorption, exp(−σ L) with L = 1/cos θ.
    sigma = jnp.array([0.2, 0.7, 1.5])
    theta = np.radians(30.0)
    d = np.array([np.sin(theta), -np.cos(theta), 0.0])
    o = -2.0 * d

    def rgb(sigma):
        return _render_ray(slab(Dielectric(1.0, absorption=sigma)), o, d, depth=2)

    # The whole path through the slab: the ray inside starts `offset` below the top face
    # (spawn_offset), and the part it skips, offset / cos θ, is absorbed at the spawn.
    length = 1.0 / np.cos(theta)
    background = np.array([0.25, 0.5, 1.0])
    expected = background * np.exp(-np.asarray(sigma) * length)
    # Channel i depends on σ_i only, so one JVP along (1, 1, 1) gives the diagonal of
    # the Jacobian: the gradient flows through the tree, d/dσ = −L · expected.
    value, diagonal = jax.jvp(rgb, (sigma,), (jnp.ones(3),))
    np.testing.assert_allclose(np.asarray(value), expected, rtol=1e-9)
    np.testing.assert_allclose(np.asarray(diagonal), -length * expected, rtol=1e-7)


def test_conductor_weight_is_complex_fresnel():
    eta, k = np.array([0.2, 0.9, 1.4]), np.array([3.9, 2.4, 1.9])
    scene = half_space(Conductor(eta, k))
    o, d = rays_to_plane(np.radians([0.0]))
    out = shade_one(scene, jnp.asarray(o[0]), jnp.asarray(d[0]))
    normal_incidence = ((eta - 1) ** 2 + k**2) / ((eta + 1) ** 2 + k**2)
    np.testing.assert_allclose(np.asarray(out.children["reflect"].weight), normal_incidence, rtol=1e-12)
    assert "transmit" not in out.children                  # metals spawn no refraction
    gold = Conductor("gold")
    assert np.all(np.asarray(gold.base_color()) > 0) and gold.base_color()[0] > gold.base_color()[2]


def test_mirror_and_whitted_constant_weights():
    # A tinted mirror over the white sky: rgb = tint (one bounce, no lights).
    o, d = np.array([0.0, 1.0, -1.0]), np.array([0.0, -1.0, 1.0]) / np.sqrt(2)
    tint = np.array([0.9, 0.5, 0.2])
    np.testing.assert_allclose(np.asarray(_render_ray(half_space(Mirror(tint)), o, d, 1)), tint, rtol=1e-12)
    # depth 0: the mirror has no direct term.
    np.testing.assert_allclose(np.asarray(_render_ray(half_space(Mirror(tint)), o, d, 0)), 0.0, atol=0)
    # Whitted's constant c_refl, independent of the angle, plus its base's direct term (no lights: 0).
    w = Whitted(base=Lambert(0.5), c_refl=0.3)
    for dd in (d, np.array([0.0, -0.1, 1.0]) / np.sqrt(1.01)):
        np.testing.assert_allclose(np.asarray(_render_ray(half_space(w), -dd, dd, 1)), 0.3, rtol=1e-12)


def test_whitted_transmission_and_tir():
    w = Whitted(c_refl=0.2, c_trans=0.7, eta=ETA)
    scene = half_space(w)
    critical = np.arcsin(1.0 / ETA)
    o, d = rays_to_plane(np.array([0.3, 1.2]) * critical, from_below=True)
    rays = [shade_one(scene, jnp.asarray(a), jnp.asarray(b)) for a, b in zip(o, d)]
    np.testing.assert_allclose(rays[0].children["reflect"].weight, 0.2, rtol=1e-12)
    np.testing.assert_allclose(rays[0].children["transmit"].weight, 0.7, rtol=1e-12)
    np.testing.assert_allclose(rays[1].children["reflect"].weight, 0.9, rtol=1e-12)  # TIR: c_refl + c_trans
    assert not bool(rays[1].children["transmit"].alive)


def test_flags_decide_the_branches():
    assert (Mirror().has_reflection, Mirror().has_transmission, Mirror().has_diffuse) == (True, False, False)
    assert (Dielectric().has_reflection, Dielectric().has_transmission) == (True, True)
    assert not Dielectric(1.5).is_dispersive
    assert Dielectric("bk7").is_dispersive and abs(float(Dielectric("bk7").ior()) - 1.5168) < 1e-4  # n_d
    assert not Whitted(c_refl=0.5).has_transmission and Whitted(c_refl=0.5, c_trans=0.5).has_transmission
    assert Whitted(base=Lambert()).has_diffuse and not Whitted().has_diffuse
    assert not Conductor("silver").has_transmission


@pytest.mark.parametrize("make, message", [
    (lambda: Dielectric(eta=-1.0), "Dielectric(eta=...)"),
    (lambda: Dielectric(absorption=(0.1, -0.2, 0.0)), "Dielectric(absorption=...)"),
    (lambda: Mirror(tint=(1.0, 1.0)), "Mirror(tint=...)"),
    (lambda: Conductor(eta=(1.0, 1.0, 1.0)), "Conductor(k=...)"),
    (lambda: Conductor("unobtainium"), "unobtainium"),
    (lambda: Dielectric("glassy"), "glassy"),
    (lambda: Whitted(base=Mirror()), "Whitted(base=...)"),
    (lambda: Whitted(eta=0.0, c_trans=0.5), "Whitted(eta=...)"),
])
def test_bad_parameters_name_the_argument(make, message):
    with pytest.raises((ValueError, TypeError), match=message.replace("(", r"\(").replace(")", r"\)").replace(".", r"\.")):
        make()


def test_grazing_and_normal_incidence_stay_finite_with_gradients():
    # cos θ → 0 and = 1, entering and leaving, including at the critical angle.
    critical = np.arcsin(1.0 / ETA)
    cases = [(np.pi / 2 - 1e-12, False), (np.pi / 2 - 1e-7, False), (0.0, False), (0.0, True),
             (critical, True), (np.pi / 2 - 1e-9, True)]

    @jax.jit
    def weights(eta, o, d):
        out = integrator.shade_ray(half_space(Dielectric(eta)), integrator.camera_ray(o, d), SETTINGS)
        return jnp.concatenate([out.children["reflect"].weight, out.children["transmit"].weight,
                                out.children["transmit"].direction])

    jacobian = jax.jit(jax.jacfwd(weights))
    for theta, below in cases:
        o, d = (jnp.asarray(x[0]) for x in rays_to_plane(np.array([theta]), below))
        value, grad = weights(jnp.asarray(ETA), o, d), jacobian(jnp.asarray(ETA), o, d)
        assert np.all(np.isfinite(np.asarray(value))) and np.all(np.isfinite(np.asarray(grad))), (theta, below)
