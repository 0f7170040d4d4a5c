"""Microfacet distributions and geometry terms (jaxrt/bsdf/microfacet.py, geometry.py)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from jax.test_util import check_grads

import jaxrt.bsdf as bsdf

SETTINGS = settings(max_examples=25, deadline=None)


def _dir(theta, phi=0.0):
    return jnp.array([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])


def _theta_rule(n=20, panels=40, smallest=1e-5):
    """Composite Gauss–Legendre on [0, π/2] with geometrically shrinking panels near 0,
    so that both very peaked (Phong 2000, α = 0.05) and broad lobes are resolved."""
    br = np.concatenate([[0.0], np.geomspace(smallest, np.pi / 2, panels)])
    x, w = np.polynomial.legendre.leggauss(n)
    th = np.concatenate([0.5 * (b - a) * x + 0.5 * (b + a) for a, b in zip(br[:-1], br[1:])])
    wt = np.concatenate([0.5 * (b - a) * w for a, b in zip(br[:-1], br[1:])])
    return th, wt


def _projected_area(dist):
    """∫ D(wm) cos θm dωm = 2π ∫ D(θ) cos θ sin θ dθ."""
    th, wt = _theta_rule()
    wm = jnp.stack([np.sin(th), np.zeros_like(th), np.cos(th)], axis=-1)
    d = jax.vmap(dist.d)(wm)
    return float(2 * np.pi * jnp.sum(d * np.cos(th) * np.sin(th) * wt))


def _hemisphere_rule(nphi=128):
    th, wt = _theta_rule(n=16, panels=30, smallest=1e-4)
    phi = (np.arange(nphi) + 0.5) * 2 * np.pi / nphi
    T, P = np.meshgrid(th, phi, indexing="ij")
    W = (wt[:, None] * (2 * np.pi / nphi)) * np.sin(T)
    dirs = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], -1)
    return jnp.asarray(dirs.reshape(-1, 3)), jnp.asarray(W.reshape(-1))


ALPHAS = [0.05, 0.1, 0.3, 0.7, 1.0]
EXPONENTS = [0.0, 1.0, 2.0, 10.0, 100.0, 1000.0, 2000.0]


# ---------------------------------------------------------------- normalisation

@pytest.mark.parametrize("alpha", ALPHAS)
@pytest.mark.parametrize("cls", [bsdf.GGX, bsdf.Beckmann])
def test_ndf_normalised(cls, alpha):
    assert abs(_projected_area(cls(alpha)) - 1.0) < 1e-3


@pytest.mark.parametrize("exponent", EXPONENTS)
def test_phong_ndf_normalised(exponent):
    assert abs(_projected_area(bsdf.PhongNDF(exponent)) - 1.0) < 1e-3


def test_ndf_zero_below_horizon():
    for dist in (bsdf.GGX(0.5), bsdf.Beckmann(0.5), bsdf.PhongNDF(10.0)):
        assert float(dist.d(_dir(2.0))) == 0.0
        assert float(dist.d(jnp.array([0.0, 0.0, -1.0]))) == 0.0


# ---------------------------------------------------------------- Smith masking

@pytest.mark.parametrize("dist", [bsdf.GGX(0.1), bsdf.GGX(0.6), bsdf.GGX(1.0),
                                  bsdf.Beckmann(0.1), bsdf.Beckmann(0.6), bsdf.Beckmann(1.0)],
                         ids=lambda d: f"{type(d).__name__}-{float(d.alpha)}")
def test_smith_lambda_is_consistent_with_its_ndf(dist):
    """Heitz 2014 eq. 21 ("weak white furnace"): ∫ G1(wo, wm) <wo·wm>⁺ D(wm) dωm = cos θo.
    Holds exactly only if Λ is the Smith Λ of D: checks the closed form (GGX) and the
    exact erf form (Beckmann) against the NDF itself."""
    wm, w = _hemisphere_rule()
    for theta_o in np.radians([0.0, 30.0, 60.0, 80.0, 88.0]):
        wo = _dir(theta_o, 0.3)
        integrand = jax.vmap(lambda m: dist.g1(wo, m) * jnp.maximum(wo @ m, 0.0) * dist.d(m))(wm)
        assert abs(float(jnp.sum(integrand * w)) - np.cos(theta_o)) < 1e-3 * max(np.cos(theta_o), 0.1)


def test_phong_smith_through_beckmann_correspondence_is_approximate():
    """PhongNDF borrows Beckmann's Λ (α_b = sqrt(2/(α_p + 2))): the projected-area
    identity then holds only approximately. Measured relative error of
    ∫ G1 <wo·wm>⁺ D dωm / cos θo at θo = 45°, 70°, 80°, 88°:
    p = 0: 18 %, 43 %, 57 %, 73 %;  p = 2: 2.6 %, 11 %, 17 %, 23 %;
    p = 20: 0, 0.4 %, 1.3 %, 2.9 %;  p = 200: < 0.2 %;  0 at normal incidence."""
    wm, w = _hemisphere_rule()
    bounds = {2.0: 0.18, 20.0: 0.015, 200.0: 0.002}
    for p, bound in bounds.items():
        dist = bsdf.PhongNDF(p)
        for theta_o in np.radians([0.0, 45.0, 80.0]):
            wo = _dir(theta_o)
            integrand = jax.vmap(lambda m: dist.g1(wo, m) * jnp.maximum(wo @ m, 0.0) * dist.d(m))(wm)
            err = abs(float(jnp.sum(integrand * w)) / np.cos(theta_o) - 1.0)
            assert err < bound, (p, np.degrees(theta_o), err)


@SETTINGS
@given(st.floats(0.0, np.pi / 2), st.floats(0.0, 6.3), st.floats(0.0, np.pi / 2),
       st.floats(0.0, 6.3), st.floats(1e-4, 1.0), st.floats(0.0, 1e4))
def test_g1_in_unit_interval(t, p, tm, pm, alpha, exponent):
    w, wm = _dir(t, p), _dir(tm, pm)
    for dist in (bsdf.GGX(alpha), bsdf.Beckmann(alpha), bsdf.PhongNDF(exponent)):
        g = float(dist.g1(w, wm))
        assert 0.0 <= g <= 1.0
        for name, gfn in bsdf.GEOMETRY_TERMS.items():
            wo, wi = w, _dir(tm, pm + 1.0)
            h = (wo + wi) / jnp.linalg.norm(wo + wi)
            gv = float(gfn(dist, wo, wi, h))
            assert 0.0 <= gv <= 1.0 + 1e-12, name
            assert np.isclose(gv, float(gfn(dist, wi, wo, h)), rtol=1e-12, atol=1e-15), name
        h = (w + _dir(tm, pm)) / jnp.linalg.norm(w + _dir(tm, pm))
        assert (float(bsdf.g_smith_correlated(dist, w, _dir(tm, pm), h))
                >= float(bsdf.g_smith_separable(dist, w, _dir(tm, pm), h)) - 1e-12)


@pytest.mark.parametrize("dist", [bsdf.GGX(1e-4), bsdf.GGX(0.5), bsdf.GGX(1.0),
                                  bsdf.Beckmann(1e-4), bsdf.Beckmann(1.0),
                                  bsdf.PhongNDF(0.0), bsdf.PhongNDF(1e4)])
def test_g1_limits(dist):
    n = jnp.array([0.0, 0.0, 1.0])
    assert float(dist.g1(n, n)) == 1.0
    assert float(dist.lambda_(n)) == 0.0
    assert float(dist.g1(_dir(1e-4), n)) > 1 - 1e-6          # → 1 at normal incidence
    assert float(dist.g1(_dir(np.pi / 2), n)) < 1e-10         # grazing
    assert float(dist.g1(jnp.array([1.0, 0.0, 0.0]), n)) == 0.0
    # back-facing microfacet is masked
    assert float(dist.g1(_dir(1.2, 0.0), _dir(1.2, np.pi) * jnp.array([1, 1, -1]))) == 0.0
    # monotone in θ
    gs = [float(dist.g1(_dir(t), n)) for t in np.linspace(0, np.pi / 2, 20)]
    assert all(a >= b - 1e-12 for a, b in zip(gs, gs[1:]))


def test_ggx_lambda_closed_form():
    for alpha in (0.1, 0.5, 1.0):
        for t in (0.1, 0.7, 1.3, 1.55):
            tan2 = np.tan(t) ** 2
            ref = (-1 + np.sqrt(1 + alpha ** 2 * tan2)) / 2
            assert np.isclose(float(bsdf.GGX(alpha).lambda_(_dir(t))), ref, rtol=1e-10)


def test_beckmann_lambda_against_scipy_free_reference():
    import math
    for alpha in (0.1, 0.5, 1.0):
        for t in (0.1, 0.7, 1.3, 1.55):
            a = 1 / (alpha * math.tan(t))
            ref = (math.erf(a) - 1) / 2 + math.exp(-a * a) / (2 * a * math.sqrt(math.pi))
            got = float(bsdf.Beckmann(alpha).lambda_(_dir(t)))
            assert np.isclose(got, ref, rtol=1e-8, atol=1e-14)


# ---------------------------------------------------------------- Phong ↔ Beckmann

def test_roughness_conversions():
    assert np.isclose(float(bsdf.beckmann_alpha_to_phong_exponent(1.0)), 0.0)
    assert np.isclose(float(bsdf.beckmann_alpha_to_phong_exponent(np.sqrt(2 / 12))), 10.0)
    for p in (0.0, 1.0, 10.0, 1e3, 1e4):
        a = bsdf.phong_exponent_to_beckmann_alpha(p)
        assert np.isclose(float(bsdf.beckmann_alpha_to_phong_exponent(a)), p, rtol=1e-10, atol=1e-9)
        assert np.isclose(float(bsdf.ggx_alpha_to_phong_exponent(bsdf.phong_exponent_to_ggx_alpha(p))),
                          p, rtol=1e-10, atol=1e-9)


def _phong_beckmann_distance(p):
    th, wt = _theta_rule()
    wm = jnp.stack([np.sin(th), np.zeros_like(th), np.cos(th)], axis=-1)
    dp = jax.vmap(bsdf.PhongNDF(p).d)(wm)
    db = jax.vmap(bsdf.Beckmann(bsdf.phong_exponent_to_beckmann_alpha(p)).d)(wm)
    l1 = float(2 * np.pi * jnp.sum(jnp.abs(dp - db) * np.cos(th) * np.sin(th) * wt))
    peak = float(jnp.max(jnp.abs(dp - db)) / db[0])
    return l1, peak


def test_phong_beckmann_correspondence_closeness():
    """α_p = 2 α_b⁻² − 2 makes the two NDFs close, closer for sharper lobes. Measured
    L1 distance of the projected densities ∫|Dp − Db| cos θ dω, and max |Dp − Db| / D(n):
    p = 1: 0.30, 0.39; p = 10: 0.085, 0.043; p = 100: 0.011, 0.0046;
    p = 1000: 0.0011, 4.6e-4; p = 2000: 5.4e-4, 2.3e-4 — about 0.9 / p and 0.46 / p."""
    bounds = {1.0: (0.31, 0.40), 10.0: (0.09, 0.045), 100.0: (0.011, 0.005),
              1000.0: (0.0011, 4.7e-4), 2000.0: (5.5e-4, 2.4e-4)}
    for p, (l1_max, peak_max) in bounds.items():
        l1, peak = _phong_beckmann_distance(p)
        assert l1 < l1_max and peak < peak_max, (p, l1, peak)
        assert l1 * p < 1.1 and peak * p < 0.47


# ---------------------------------------------------------------- gradients

def _dists_of(x):
    return [bsdf.GGX(x), bsdf.Beckmann(x), bsdf.PhongNDF(2.0 / x ** 2 - 2.0)]


@pytest.mark.parametrize("which", [0, 1, 2])
def test_check_grads_ndf_and_masking(which):
    rng = np.random.default_rng(which)
    for _ in range(3):
        alpha = rng.uniform(0.2, 0.9)
        # away from θ = 0, where finite differences would step past |cos θ| = 1
        wm = _dir(rng.uniform(0.1, 1.2), rng.uniform(0, 6))
        w = _dir(rng.uniform(0.1, 1.4), rng.uniform(0, 6))
        if float(w @ wm) <= 0.05:
            continue
        check_grads(lambda a, m: _dists_of(a)[which].d(m), (alpha, wm), order=1,
                    modes=("fwd", "rev"))
        check_grads(lambda a, v: _dists_of(a)[which].g1(v, wm), (alpha, w), order=1,
                    modes=("fwd", "rev"))
        check_grads(lambda a, v: _dists_of(a)[which].lambda_(v), (alpha, w), order=1,
                    modes=("fwd", "rev"))


@pytest.mark.parametrize("name", sorted(bsdf.GEOMETRY_TERMS))
def test_check_grads_geometry_terms(name):
    g = bsdf.GEOMETRY_TERMS[name]
    rng = np.random.default_rng(1)
    for _ in range(3):
        wo = _dir(rng.uniform(0.1, 1.4), rng.uniform(0, 6))
        wi = _dir(rng.uniform(0.1, 1.4), rng.uniform(0, 6))
        h = (wo + wi) / jnp.linalg.norm(wo + wi)
        for dist in _dists_of(rng.uniform(0.2, 0.9)):
            if name == "cook_torrance":  # piecewise (min): check away from the kinks
                vals = [1.0, float(2 * h[2] * wo[2] / (wo @ h)), float(2 * h[2] * wi[2] / (wi @ h))]
                if min(abs(a - b) for a in vals for b in vals if a is not b) < 1e-3:
                    continue
            check_grads(lambda a, b: g(dist, a, b, h), (wo, wi), order=1, modes=("fwd", "rev"))


EXTREME_DIRS = {
    "normal": [0.0, 0.0, 1.0],
    "cos1e-7": [float(np.sqrt(1 - 1e-14)), 0.0, 1e-7],
    "grazing": [1.0, 0.0, 0.0],
    "below": [0.6, 0.0, -0.8],
}


def _all_dists(x):
    return [bsdf.GGX(x["alpha"]), bsdf.Beckmann(x["alpha"]), bsdf.PhongNDF(x["p"])]


def _extreme_terms(params, w_, m_):
    out = []
    wi = jnp.array([-w_[0], -w_[1], w_[2]])
    for dist in _all_dists(params):
        out += [dist.d(m_), dist.g1(w_, m_), dist.lambda_numerator(w_)]
        out += [g(dist, w_, wi, m_) for g in bsdf.GEOMETRY_TERMS.values()]
    return jnp.stack(out)


# Module level, so that they compile once for all parametrisations.
_extreme_vals = jax.jit(jax.vmap(_extreme_terms, in_axes=(None, 0, 0)))
_extreme_rev = jax.jit(jax.vmap(jax.jacrev(_extreme_terms, argnums=(0, 1, 2)),
                                in_axes=(None, 0, 0)))


@pytest.mark.parametrize("alpha, p", [(1e-4, 0.0), (1.0, 1e4), (0.3, 1.0)])
def test_finite_values_and_gradients_at_extremes(alpha, p):
    """α = 1e-4 and 1, Phong exponent 0 and 1e4, at cos θ = 1, 1e-7, 0 and below the
    horizon, for every pair of (w, wm) among those: values and gradients."""
    dirs = jnp.asarray(list(EXTREME_DIRS.values()))
    ws = jnp.repeat(dirs, len(dirs), axis=0)
    ms = jnp.tile(dirs, (len(dirs), 1))
    params = {"alpha": jnp.asarray(alpha), "p": jnp.asarray(p)}
    assert np.all(np.isfinite(np.asarray(_extreme_vals(params, ws, ms))))
    for leaf in jax.tree_util.tree_leaves(_extreme_rev(params, ws, ms)):
        assert np.all(np.isfinite(np.asarray(leaf)))
    # lambda_ is finite except exactly at grazing (where it is +inf by definition)
    for dist in _all_dists({"alpha": alpha, "p": p}):
        assert np.isfinite(float(dist.lambda_(jnp.asarray(EXTREME_DIRS["cos1e-7"]))))


def test_traced_parameters_and_shape_validation():
    @jax.jit
    def f(alpha):
        return bsdf.GGX(alpha).d(jnp.array([0.0, 0.0, 1.0]))

    assert np.isclose(float(f(0.5)), 1 / (np.pi * 0.25))
    assert np.isclose(float(jax.grad(f)(0.5)), -2 / (np.pi * 0.125))
    with pytest.raises(ValueError, match="GGX"):
        bsdf.GGX(jnp.ones(3))
