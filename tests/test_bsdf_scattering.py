"""Reflection, refraction and Fresnel (jaxrt/bsdf/scattering.py)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from jax.test_util import check_grads

import jaxrt.bsdf as bsdf
from jaxrt.vecmath import to_world

SETTINGS = settings(max_examples=25, deadline=None)


def _dir(theta, phi):
    return jnp.array([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])


def _unit(v):
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


# ---------------------------------------------------------------- reflect / refract

@SETTINGS
@given(st.floats(0.0, 1.5), st.floats(0.0, 6.28), st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1))
def test_reflect_is_mirror(theta, phi, nx, ny, nz):
    if nx * nx + ny * ny + nz * nz < 1e-2:
        return
    n = jnp.asarray(_unit([nx, ny, nz]))
    wi = _dir(theta, phi)
    r = bsdf.reflect(wi, n)
    assert np.isclose(float(jnp.linalg.norm(r)), 1.0, atol=1e-12)
    assert np.isclose(float(r @ n), float(wi @ n), atol=1e-12)          # same angle
    assert np.allclose(np.asarray(r + wi), 2 * float(wi @ n) * np.asarray(n), atol=1e-12)


@SETTINGS
@given(st.floats(0.0, np.pi / 2), st.floats(0.0, 6.28), st.floats(0.3, 3.0),
       st.booleans())
@example(theta=np.pi / 2, phi=0.28125, eta=0.5, from_inside=False)  # grazing: CI found it
def test_refract_snell_and_unit_length(theta, phi, eta, from_inside):
    n = jnp.asarray(_unit([0.3, -0.2, 1.0]))
    wi_local = _dir(theta, phi)
    wi = to_world(wi_local, n)
    if from_inside:
        wi = -wi
    wt, valid = bsdf.refract(wi, n, eta)
    # eta is n_below / n_above: the incident index is 1 (above) or eta (below). The side
    # is the sign of wi·n, which is from_inside's but at grazing (theta = pi/2), where
    # |wi·n| is rounding and either side is right.
    n_i, n_t = (eta, 1.0) if float(wi @ n) < 0.0 else (1.0, eta)
    cos_i = abs(float(wi @ n))
    sin_i = float(jnp.linalg.norm(jnp.cross(wi, n)))  # well-conditioned near normal
    expected_valid = n_i * sin_i / n_t < 1.0
    assert bool(valid) == expected_valid or abs(n_i * sin_i / n_t - 1) < 1e-9
    assert np.isclose(float(jnp.linalg.norm(wt)), 1.0, atol=1e-9)
    if valid:
        cos_t = float(wt @ n)
        assert np.sign(cos_t) != np.sign(float(wi @ n)) or abs(cos_t) < 1e-9   # other side
        sin_t = float(jnp.linalg.norm(jnp.cross(wt, n)))
        assert abs(n_i * sin_i - n_t * sin_t) < 1e-9
        # wi, n and wt are coplanar
        assert abs(float(jnp.cross(wi, n) @ wt)) < 1e-9
    else:
        assert np.allclose(np.asarray(wt), np.asarray(bsdf.reflect(wi, n)), atol=1e-12)


def test_refract_eta_one_passes_straight_through():
    n = jnp.array([0.0, 0.0, 1.0])
    wi = _dir(0.7, 0.3)
    wt, valid = bsdf.refract(wi, n, 1.0)
    assert bool(valid) and np.allclose(np.asarray(wt), -np.asarray(wi), atol=1e-12)


def test_refract_total_internal_reflection_beyond_critical_angle():
    n = jnp.array([0.0, 0.0, 1.0])
    eta = 1.5
    critical = np.arcsin(1 / eta)
    # From inside the glass (below n): valid below, invalid above the critical angle.
    _, ok = bsdf.refract(-_dir(critical - 1e-3, 0.0), n, eta)
    _, tir = bsdf.refract(-_dir(critical + 1e-3, 0.0), n, eta)
    assert bool(ok) and not bool(tir)


# ---------------------------------------------------------------- Fresnel

def test_fresnel_dielectric_reference_values():
    assert np.isclose(float(bsdf.fresnel_dielectric(1.0, 1.5)), 0.04, atol=1e-12)
    assert np.isclose(float(bsdf.fresnel_dielectric(-1.0, 1.5)), 0.04, atol=1e-12)
    assert np.isclose(float(bsdf.fresnel_dielectric(0.0, 1.5)), 1.0, atol=1e-12)
    assert np.isclose(float(bsdf.fresnel_dielectric(1e-12, 1.5)), 1.0, atol=1e-9)
    assert np.isclose(float(bsdf.f0_from_eta(1.5)), 0.04)
    for c in (-1.0, -0.5, 0.0, 1e-7, 0.3, 1.0):
        assert float(bsdf.fresnel_dielectric(c, 1.0)) == 0.0


def test_fresnel_dielectric_against_polarised_formulas():
    # Independent reference: Fresnel equations with complex numpy (Hecht, Optics §4.6).
    for eta in (1.2, 1.5, 2.4, 1 / 1.5):
        for c in np.linspace(-1, 1, 41):
            n1, n2 = (1.0, eta) if c >= 0 else (eta, 1.0)
            ci = abs(c)
            st2 = (n1 / n2) ** 2 * (1 - ci ** 2)
            ct = np.sqrt(complex(1 - st2))
            rs = (n1 * ci - n2 * ct) / (n1 * ci + n2 * ct)
            rp = (n2 * ci - n1 * ct) / (n2 * ci + n1 * ct)
            ref = 0.5 * (abs(rs) ** 2 + abs(rp) ** 2) if st2 < 1 else 1.0
            assert np.isclose(float(bsdf.fresnel_dielectric(c, eta)), ref, atol=1e-12)


def test_fresnel_dielectric_tir_and_continuity_at_critical_angle():
    eta = 1 / 1.5  # light inside glass (cos > 0 side has the larger index)
    cos_c = np.cos(np.arcsin(eta))
    assert float(bsdf.fresnel_dielectric(cos_c - 1e-3, eta)) == 1.0
    assert float(bsdf.fresnel_dielectric(0.0 + 1e-9, eta)) == 1.0
    # Continuity: F → 1 from the transmitting side (error ~ sqrt(distance)).
    for d in (1e-4, 1e-6, 1e-8):
        assert 1.0 - float(bsdf.fresnel_dielectric(cos_c + d, eta)) < 30 * np.sqrt(d)
    # Same thing seen from the other side: cos < 0 with eta = 1.5.
    assert float(bsdf.fresnel_dielectric(-(cos_c - 1e-3), 1.5)) == 1.0


def test_fresnel_conductor_against_complex_numpy():
    rng = np.random.default_rng(0)
    for _ in range(30):
        eta = rng.uniform(0.05, 3.0, 3)
        k = rng.uniform(0.0, 8.0, 3)
        c = rng.uniform(0.0, 1.0)
        nc = eta + 1j * k
        sin2 = 1 - c * c
        ct = np.sqrt(1 - sin2 / nc ** 2)
        rs = (c - nc * ct) / (c + nc * ct)
        rp = (nc * c - ct) / (nc * c + ct)
        ref = 0.5 * (np.abs(rs) ** 2 + np.abs(rp) ** 2)
        got = np.asarray(bsdf.fresnel_conductor(c, jnp.asarray(eta), jnp.asarray(k)))
        assert got.shape == (3,)
        assert np.allclose(got, ref, atol=1e-10)


def test_fresnel_conductor_limits():
    eta, k = jnp.array([0.2, 0.4, 1.4]), jnp.array([3.6, 2.5, 1.9])
    assert np.allclose(np.asarray(bsdf.fresnel_conductor(0.0, eta, k)), 1.0)
    r0 = ((eta - 1) ** 2 + k ** 2) / ((eta + 1) ** 2 + k ** 2)
    assert np.allclose(np.asarray(bsdf.fresnel_conductor(1.0, eta, k)), np.asarray(r0))
    # k = 0 reduces to the dielectric.
    for c in (0.1, 0.5, 0.9):
        assert np.isclose(float(bsdf.fresnel_conductor(c, 1.5, 0.0)),
                          float(bsdf.fresnel_dielectric(c, 1.5)), atol=1e-12)


def test_schlick_matches_exact_at_endpoints():
    for eta in (1.33, 1.5, 2.0):
        f0 = bsdf.f0_from_eta(eta)
        assert np.isclose(float(bsdf.fresnel_schlick(1.0, f0)),
                          float(bsdf.fresnel_dielectric(1.0, eta)), atol=1e-12)
        assert np.isclose(float(bsdf.fresnel_schlick(0.0, f0)), 1.0)
        assert np.isclose(float(bsdf.fresnel_dielectric(0.0, eta)), 1.0)
        # In between it is an approximation: within 0.06 of the exact curve for glass.
        cs = jnp.linspace(0, 1, 101)
        err = jnp.abs(jax.vmap(lambda c: bsdf.fresnel_schlick(c, f0))(cs)
                      - jax.vmap(lambda c: bsdf.fresnel_dielectric(c, eta))(cs))
        assert float(err.max()) < 0.06


# ---------------------------------------------------------------- gradients

@pytest.mark.parametrize("c, eta", [(0.3, 1.5), (0.8, 1.33), (-0.2, 1.5), (-0.95, 1.5),
                                    (0.7, 0.8)])
def test_fresnel_dielectric_check_grads(c, eta):
    check_grads(bsdf.fresnel_dielectric, (c, eta), order=1, modes=("fwd", "rev"))


@pytest.mark.parametrize("c", [0.2, 0.7, 0.99])
def test_fresnel_conductor_and_schlick_check_grads(c):
    eta, k = jnp.array([0.2, 0.4, 1.4]), jnp.array([3.6, 2.5, 1.9])
    check_grads(bsdf.fresnel_conductor, (c, eta, k), order=1, modes=("fwd", "rev"))
    check_grads(bsdf.fresnel_schlick, (c, jnp.array([0.04, 0.5, 0.9])), order=1,
                modes=("fwd", "rev"))


def test_refract_check_grads():
    n = jnp.asarray(_unit([0.1, 0.2, 1.0]))
    wi = _dir(0.6, 0.4)
    check_grads(lambda w, e: bsdf.refract(w, n, e)[0], (wi, 1.4), order=1,
                modes=("fwd", "rev"))
    check_grads(lambda w, e: bsdf.refract(w, n, e)[0], (-wi, 1.4), order=1,
                modes=("fwd", "rev"))


EXTREME_COS = [0.0, 1e-7, -1e-7, 1.0, -1.0, 0.5]
EXTREME_ETA = [1.0, 1.5, 1 / 1.5, 1.0 + 1e-12]


@pytest.mark.parametrize("c", EXTREME_COS)
@pytest.mark.parametrize("eta", EXTREME_ETA)
def test_fresnel_finite_values_and_gradients_at_extremes(c, eta):
    fns = [lambda c, e: bsdf.fresnel_dielectric(c, e),
           lambda c, e: bsdf.fresnel_conductor(c, e, 0.0),
           lambda c, e: bsdf.fresnel_conductor(c, e, 2.0),
           lambda c, e: bsdf.fresnel_schlick(c, bsdf.f0_from_eta(e))]
    for fn in fns:
        v, g = jax.value_and_grad(fn, argnums=(0, 1))(c, eta)
        assert np.isfinite(float(v)) and 0.0 <= float(v) <= 1.0
        assert all(np.isfinite(float(x)) for x in g)


def test_fresnel_finite_gradient_at_critical_angle():
    eta = 1 / 1.5
    cos_c = float(np.cos(np.arcsin(eta)))
    g = jax.grad(bsdf.fresnel_dielectric, argnums=(0, 1))(cos_c, eta)
    assert all(np.isfinite(float(x)) for x in g)
    n = jnp.array([0.0, 0.0, 1.0])
    wi = jnp.array([np.sqrt(1 - cos_c ** 2), 0.0, cos_c])
    jac = jax.jacobian(lambda w, e: bsdf.refract(w, n, e)[0], argnums=(0, 1))(wi, eta)
    assert all(np.all(np.isfinite(np.asarray(j))) for j in jac)


@pytest.mark.parametrize("wi", [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
@pytest.mark.parametrize("eta", [1.0, 1.5, 0.5])
def test_refract_finite_at_normal_and_grazing(wi, eta):
    n = jnp.array([0.0, 0.0, 1.0])
    wi = jnp.asarray(wi, dtype=float)
    wt, _ = bsdf.refract(wi, n, eta)
    jac = jax.jacobian(lambda w, e: bsdf.refract(w, n, e)[0], argnums=(0, 1))(wi, eta)
    assert np.all(np.isfinite(np.asarray(wt)))
    assert all(np.all(np.isfinite(np.asarray(j))) for j in jac)


def test_jit_and_vmap():
    cs = jnp.linspace(-1, 1, 17)
    f = jax.jit(jax.vmap(bsdf.fresnel_dielectric, in_axes=(0, None)))(cs, 1.5)
    assert f.shape == (17,)
    wis = jnp.stack([_dir(t, 0.0) for t in np.linspace(0, 1.5, 5)])
    wt, ok = jax.jit(jax.vmap(bsdf.refract, in_axes=(0, None, None)))(
        wis, jnp.array([0.0, 0.0, 1.0]), 1.5)
    assert wt.shape == (5, 3) and ok.shape == (5,)
