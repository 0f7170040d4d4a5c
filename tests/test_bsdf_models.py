"""BRDF models and materials (jaxrt/bsdf/*.py): plausibility, references, gradients."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from jax.test_util import check_grads

import jaxrt.bsdf as bsdf

SETTINGS = settings(max_examples=20, deadline=None)
TWO_PI = 2 * np.pi


def _dir(theta, phi=0.0):
    return jnp.array([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])


# name -> (material, reciprocal, plausible up to 80° incidence)
MODELS = {
    "lambert": (bsdf.Lambert(1.0), True, True),
    "ct_ggx_correlated": (bsdf.CookTorrance(bsdf.GGX(0.3), bsdf.SchlickFresnel(1.0)), True, True),
    "ct_ggx_separable": (bsdf.CookTorrance(bsdf.GGX(0.1), bsdf.SchlickFresnel(1.0), "smith"), True, True),
    "ct_beckmann_correlated": (bsdf.CookTorrance(bsdf.Beckmann(0.5), bsdf.SchlickFresnel(1.0)), True, True),
    "ct_beckmann_vgroove": (bsdf.CookTorrance(bsdf.Beckmann(0.3), bsdf.SchlickFresnel(1.0), "cook_torrance"), True, True),
    "ct_ggx_implicit": (bsdf.CookTorrance(bsdf.GGX(0.7), bsdf.SchlickFresnel(1.0), "implicit"), True, True),
    "ct_phong_correlated": (bsdf.CookTorrance(bsdf.PhongNDF(50.0), bsdf.SchlickFresnel(1.0)), True, True),
    "ct_dielectric_diffuse": (bsdf.CookTorrance(bsdf.GGX(0.2), bsdf.DielectricFresnel(1.5), diffuse=0.5), True, True),
    "gold": (bsdf.CookTorrance.rough_conductor("gold", 0.2), True, True),
    "plastic": (bsdf.Plastic(1.0, 1.5, bsdf.GGX(0.2)), True, True),
    "phong_normalized": (bsdf.Phong(0.5, 0.5, 30.0, normalized=True), True, True),
    "phong_classic": (bsdf.Phong(0.2, 0.5, 10.0, ka=0.1), False, False),
    "blinn_phong": (bsdf.BlinnPhong(0.5, 0.5, 40.0), True, True),
    "ward": (bsdf.Ward(0.5, 0.5, 0.2), True, True),
    "ward_duer": (bsdf.Ward(0.5, 0.5, 0.2, "duer"), True, True),
    "lafortune": (bsdf.Lafortune(0.5, [[0.3 * 22 / TWO_PI] * 3, [0.2 * 7 / TWO_PI] * 3],
                                 [-1.0, -1.0], [1.0, 1.0], [20.0, 5.0]), True, True),
    "ashikhmin_shirley": (bsdf.AshikhminShirley(0.5, 0.5, 100.0), True, True),
    "ashikhmin_shirley_diffuse": (bsdf.AshikhminShirley(1.0, 0.0, 10.0), True, True),
}
NAMES = sorted(MODELS)
NON_RECIPROCAL = sorted(n for n in NAMES if not MODELS[n][1])


@eqx.filter_jit
def _eval_pairs(material, wo, wi):
    # Module level and taking the material as an argument: compiles once per model
    # structure and input shape, not once per call.
    return jax.vmap(material.eval)(wo, wi)


# ---------------------------------------------------------------- plausibility

@SETTINGS
@given(st.lists(st.floats(0.0, np.pi), min_size=4, max_size=4),
       st.lists(st.floats(0.0, 6.3), min_size=4, max_size=4))
def test_positive_finite_and_zero_below_horizon(thetas, phis):
    wo = jnp.stack([_dir(t, p) for t, p in zip(thetas[:2], phis[:2])] * 2)
    wi = jnp.stack([_dir(t, p) for t, p in zip(thetas[2:], phis[2:])] * 2)
    for name in NAMES:
        f = np.asarray(_eval_pairs(MODELS[name][0], wo, wi))
        assert f.shape == (4, 3) and np.all(np.isfinite(f)) and np.all(f >= 0), name
        below = (np.asarray(wo[:, 2]) <= 0) | (np.asarray(wi[:, 2]) <= 0)
        assert np.all(f[below] == 0), name


@SETTINGS
@given(st.lists(st.floats(0.0, 1.5), min_size=2, max_size=2),
       st.lists(st.floats(0.0, 6.3), min_size=2, max_size=2))
def test_reciprocity(thetas, phis):
    wo, wi = _dir(thetas[0], phis[0])[None], _dir(thetas[1], phis[1])[None]
    for name in NAMES:
        material, reciprocal, _ = MODELS[name]
        if not reciprocal:
            continue
        a = np.asarray(_eval_pairs(material, wo, wi))
        b = np.asarray(_eval_pairs(material, wi, wo))
        assert np.allclose(a, b, rtol=1e-6, atol=1e-300), name


def test_which_models_are_not_reciprocal():
    """Only the notes' classic Phong breaks reciprocity (its specular term is divided
    by cos θi, the cosine the notes say it lacks)."""
    assert NON_RECIPROCAL == ["phong_classic"]
    m = MODELS["phong_classic"][0]
    wo, wi = _dir(0.3, 0.0)[None], _dir(1.0, np.pi)[None]
    a, b = np.asarray(_eval_pairs(m, wo, wi)), np.asarray(_eval_pairs(m, wi, wo))
    assert not np.allclose(a, b, rtol=1e-3)


def _theta_rule(center, n=16):
    # A fixed number of panels (clipped, possibly empty ones) keeps shapes constant.
    br = list(np.linspace(0, np.pi / 2, 9))
    for d in (0.0, 0.01, 0.03, 0.08, 0.2):
        br += [float(np.clip(t, 0.0, np.pi / 2)) for t in (center - d, center + d)]
    br = np.sort(br)
    x, w = np.polynomial.legendre.leggauss(n)
    th = np.concatenate([0.5 * (b - a) * x + 0.5 * (b + a) for a, b in zip(br[:-1], br[1:])])
    wt = np.concatenate([0.5 * (b - a) * w for a, b in zip(br[:-1], br[1:])])
    return th, wt


def directional_albedo(material, theta_i, n=16, nphi=256):
    """ρ(wi) = ∫ f(wo, wi) cos θo dωo (the light's energy that leaves, notes "Energy
    conservation"): Gauss–Legendre panels in θo refined around the mirror direction,
    periodic trapezoid in φo."""
    th, wth = _theta_rule(theta_i, n)
    phi = (np.arange(nphi) + 0.5) * TWO_PI / nphi
    T, P = np.meshgrid(th, phi, indexing="ij")
    W = (wth[:, None] * (TWO_PI / nphi)) * np.sin(T) * np.cos(T)
    wo = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], -1).reshape(-1, 3)
    wi = jnp.broadcast_to(_dir(theta_i), wo.shape)
    f = _eval_pairs(material, jnp.asarray(wo), wi)
    return np.asarray(jnp.sum(f * W.reshape(-1, 1), axis=0))


INCIDENT = np.radians([0.0, 30.0, 60.0, 80.0])


def test_furnace_quadrature_is_exact_for_lambert():
    for t in INCIDENT:
        assert np.allclose(directional_albedo(bsdf.Lambert(0.7), t), 0.7, atol=1e-6)


@pytest.mark.parametrize("name", [n for n in NAMES if MODELS[n][2]])
def test_white_furnace_plausible_models(name):
    """Directional albedo ≤ 1 + 1e-2 at θi = 0°, 30°, 60°, 80°."""
    albedo = np.array([directional_albedo(MODELS[name][0], t) for t in INCIDENT])
    assert albedo.max() <= 1.0 + 1e-2, (name, albedo.max(axis=1))


def test_white_furnace_near_grazing():
    """At θi = 89° (finer grid): microfacet models with a Smith term stay ≤ 1; Ward's
    models do not. Measured (ρs = 1, ρd = 0, α = 0.3): Ward 0.36 at 89° but 1.04 at
    89.9°; Ward–Dür 4.3 at 89°."""
    t = np.radians(89.0)
    for material in (bsdf.CookTorrance(bsdf.GGX(0.5), bsdf.SchlickFresnel(1.0)),
                     bsdf.CookTorrance(bsdf.Beckmann(0.5), bsdf.SchlickFresnel(1.0)),
                     bsdf.Plastic(1.0, 1.5, bsdf.GGX(0.3)), bsdf.Lambert(1.0)):
        assert directional_albedo(material, t, n=24, nphi=512).max() <= 1.0 + 1e-2
    duer = directional_albedo(bsdf.Ward(0.0, 1.0, 0.3, "duer"), t, n=24, nphi=512).max()
    assert duer > 2.0


def test_classic_phong_exceeds_one():
    """The notes' Phong does not conserve energy: kd is not divided by π, and the
    specular lobe lacks the cosine (albedo 2π/3 ≈ 2.09 at normal incidence for ks = 1,
    q = 1, and growing without bound towards grazing)."""
    spec = bsdf.Phong(0.0, 1.0, 1.0)
    a0 = directional_albedo(spec, 0.0)
    assert np.allclose(a0, TWO_PI / 3, rtol=1e-4)
    assert directional_albedo(spec, np.radians(80.0)).max() > 4.0
    assert np.allclose(directional_albedo(bsdf.Phong(0.5, 0.0, 1.0), 0.3), 0.5 * np.pi, rtol=1e-6)
    # while the normalised variant with the same parameters conserves energy
    assert directional_albedo(bsdf.Phong(0.0, 1.0, 1.0, normalized=True), 0.0).max() <= 1 + 1e-6


# ---------------------------------------------------------------- references

def test_models_against_their_formulas():
    wo, wi = _dir(0.4, 0.2), _dir(0.9, 2.8)
    h = (wo + wi) / jnp.linalg.norm(wo + wi)
    r = jnp.array([-wi[0], -wi[1], wi[2]])
    q = 10.0
    lobe = max(float(wo @ r), 0.0) ** q
    # Phong, classic: f cos θi = kd cos θi + ks (v·r)^q, exactly the notes' shading.
    p = bsdf.Phong(0.2, 0.5, q, ka=0.1)
    assert np.allclose(np.asarray(p.eval(wo, wi)) * float(wi[2]), 0.2 * float(wi[2]) + 0.5 * lobe)
    assert np.allclose(np.asarray(p.ambient()), 0.1)
    # normalised Phong
    pn = bsdf.Phong(0.2, 0.5, q, normalized=True)
    assert np.allclose(np.asarray(pn.eval(wo, wi)), 0.2 / np.pi + 0.5 * (q + 2) / TWO_PI * lobe)
    # Lafortune with cxy = −1, cz = 1 is the Phong lobe
    la = bsdf.Lafortune(0.2, 0.5 * (q + 2) / TWO_PI, -1.0, 1.0, q)
    assert np.allclose(np.asarray(la.eval(wo, wi)), np.asarray(pn.eval(wo, wi)))
    # Cook–Torrance with the implicit G is F D / 4
    dist = bsdf.Beckmann(0.4)
    ct = bsdf.CookTorrance(dist, bsdf.DielectricFresnel(1.5), "implicit")
    ref = bsdf.fresnel_dielectric(wi @ h, 1.5) * dist.d(h) / 4
    assert np.allclose(np.asarray(ct.eval(wo, wi)), float(ref))
    # Blinn–Phong = ks D_phong(h) / 4 + kd / π
    bp = bsdf.BlinnPhong(0.1, 0.6, q)
    assert np.allclose(np.asarray(bp.eval(wo, wi)), 0.1 / np.pi + 0.6 * float(bsdf.PhongNDF(q).d(h)) / 4)
    # Ward, by hand
    a = 0.3
    tan2 = (1 - float(h[2]) ** 2) / float(h[2]) ** 2
    spec = np.exp(-tan2 / a ** 2) / (4 * np.pi * a ** 2)
    w = bsdf.Ward(0.1, 0.4, a)
    assert np.allclose(np.asarray(w.eval(wo, wi)), 0.1 / np.pi + 0.4 * spec / np.sqrt(float(wo[2] * wi[2])))
    wd = bsdf.Ward(0.1, 0.4, a, "duer")
    assert np.allclose(np.asarray(wd.eval(wo, wi)), 0.1 / np.pi + 0.4 * spec / float(wo[2] * wi[2]))
    # Ashikhmin–Shirley at wi = wo = n: diffuse 28 rd/(23π)(1 − rs)(1 − 2⁻⁵)² plus
    # specular (n + 1)/(8π) · rs
    n = jnp.array([0.0, 0.0, 1.0])
    rd, rs, e = 0.5, 0.2, 10.0
    ref = 28 * rd / (23 * np.pi) * (1 - rs) * (1 - 0.5 ** 5) ** 2 + (e + 1) / (8 * np.pi) * rs
    assert np.allclose(np.asarray(bsdf.AshikhminShirley(rd, rs, e).eval(n, n)), ref)


def test_conductor_presets():
    for name in ("gold", "silver", "copper", "aluminium", "aluminum"):
        eta, k = bsdf.conductor_preset(name)
        assert len(eta) == len(k) == 3 and min(eta) > 0 and min(k) > 1
    r0 = {name: np.asarray(bsdf.CookTorrance.rough_conductor(name, 0.3).base_color())
          for name in ("gold", "silver", "copper", "aluminium")}
    assert r0["gold"][0] > r0["gold"][1] > r0["gold"][2]          # yellow
    assert r0["copper"][0] > r0["copper"][1] > r0["copper"][2]    # reddish
    assert r0["silver"].min() > 0.9 and r0["aluminium"].min() > 0.85
    assert np.all(r0["gold"] < 1)
    with pytest.raises(ValueError, match="unknown conductor"):
        bsdf.conductor_preset("unobtainium")


def test_base_color_and_ambient():
    for name in NAMES:
        m = MODELS[name][0]
        assert m.base_color().shape == (3,) and m.ambient().shape == (3,)
        if name != "phong_classic":
            assert np.all(np.asarray(m.ambient()) == 0)
    assert np.allclose(np.asarray(bsdf.Plastic((0.1, 0.2, 0.3)).base_color()), [0.1, 0.2, 0.3])


def test_construction_errors_name_the_argument():
    with pytest.raises(ValueError, match="geometry"):
        bsdf.CookTorrance(geometry="smit")
    with pytest.raises(TypeError, match="distribution"):
        bsdf.CookTorrance(distribution=bsdf.Lambert())
    with pytest.raises(ValueError, match="Ward"):
        bsdf.Ward(normalization="dur")
    with pytest.raises(ValueError, match="Lafortune"):
        bsdf.Lafortune(cxy=[-1.0, -1.0], cz=[1.0], n=[2.0, 3.0])
    with pytest.raises(ValueError, match="ks"):
        bsdf.Lafortune(ks=jnp.ones((3, 3)), cxy=[-1.0, -1.0], cz=[1.0, 1.0], n=[2.0, 3.0])
    with pytest.raises(ValueError, match="kd"):
        bsdf.Phong(kd=(1.0, 2.0))


# ---------------------------------------------------------------- differentiability

def test_traced_parameters_jit_vmap_and_no_recompile():
    wo, wi = _dir(0.3), _dir(0.5, 3.0)
    compiles = []

    @eqx.filter_jit
    def shade(material):
        compiles.append(1)
        return material.eval(wo, wi)

    a = shade(bsdf.CookTorrance(bsdf.GGX(0.3), bsdf.ConductorFresnel((0.2, 0.4, 1.4), 3.0)))
    b = shade(bsdf.CookTorrance(bsdf.GGX(0.5), bsdf.ConductorFresnel((0.3, 0.4, 1.4), 2.0)))
    assert len(compiles) == 1 and not np.allclose(np.asarray(a), np.asarray(b))
    # parameters can be tracers: built inside jit / vmap / grad
    alphas = jnp.linspace(0.1, 0.9, 5)
    f = jax.vmap(lambda al: bsdf.CookTorrance.rough_conductor("gold", al).eval(wo, wi))(alphas)
    assert f.shape == (5, 3)
    g = jax.grad(lambda q: bsdf.Phong(0.1, 0.5, q, normalized=True).eval(wo, wi).sum())(20.0)
    assert np.isfinite(float(g))


def _param_grads(material, wo, wi):
    return eqx.filter_grad(lambda m, a, b: jnp.sum(m.eval(a, b)))(material, wo, wi)


@pytest.mark.parametrize("name", NAMES)
def test_float32_materials_evaluate_in_float32_with_x64_on(name):
    """A material whose parameters are float32 (as `render` casts them for a float32
    render) returns float32 values of float32 directions, also with jax_enable_x64 on
    (conftest): nothing in `eval` makes a float64 array. Plastic built a
    `DielectricFresnel(eta)` in every evaluation, whose constructor made its eta a
    float64 array: the float32 showcase (a plastic cylinder) failed to render with x64
    on (its lights' `lax.scan` carried float32 radiance and returned float64)."""
    from jaxrt.render import _cast

    material = _cast(MODELS[name][0], jnp.dtype(jnp.float32))
    wo = _dir(0.4, 0.3).astype(jnp.float32)
    wi = _dir(0.9, 2.0).astype(jnp.float32)
    out = jax.eval_shape(material.eval, wo, wi)
    assert out.dtype == jnp.float32, (name, out.dtype)


@pytest.mark.parametrize("name", NAMES)
def test_check_grads_eval(name):
    material = MODELS[name][0]
    params, static = eqx.partition(material, eqx.is_inexact_array)
    rng = np.random.default_rng(3)
    for _ in range(2):
        wo = _dir(rng.uniform(0.2, 1.3), rng.uniform(0, 6.3))
        wi = _dir(rng.uniform(0.2, 1.3), rng.uniform(0, 6.3))

        def f(p, a, b):
            return eqx.combine(p, static).eval(a, b)

        check_grads(f, (params, wo, wi), order=1, modes=("fwd", "rev"), rtol=2e-4, atol=1e-6)


EXTREMES = {
    "normal": [0.0, 0.0, 1.0],
    "cos1e-7": [float(np.sqrt(1 - 1e-14)), 0.0, 1e-7],
    "grazing": [0.0, 1.0, 0.0],
    "below": [0.6, 0.0, -0.8],
}

EXTREME_MATERIALS = {
    "ggx_1e-4": bsdf.CookTorrance(bsdf.GGX(1e-4), bsdf.DielectricFresnel(1.0), diffuse=0.2),
    "ggx_1": bsdf.CookTorrance(bsdf.GGX(1.0), bsdf.ConductorFresnel(0.2, 3.0)),
    "beckmann_1e-4": bsdf.CookTorrance(bsdf.Beckmann(1e-4), bsdf.SchlickFresnel(0.04), "smith"),
    "beckmann_1": bsdf.CookTorrance(bsdf.Beckmann(1.0), bsdf.SchlickFresnel(0.04), "cook_torrance"),
    "phongndf_0": bsdf.CookTorrance(bsdf.PhongNDF(0.0), bsdf.SchlickFresnel(0.04), "implicit"),
    "phongndf_1e4": bsdf.CookTorrance(bsdf.PhongNDF(1e4), bsdf.SchlickFresnel(0.04)),
    "plastic_eta1": bsdf.Plastic(0.5, 1.0, bsdf.GGX(1e-4)),
    "phong_0": bsdf.Phong(0.5, 0.5, 0.0),
    "phong_1e4": bsdf.Phong(0.5, 0.5, 1e4, normalized=True),
    "blinn_0": bsdf.BlinnPhong(0.5, 0.5, 0.0),
    "blinn_1e4": bsdf.BlinnPhong(0.5, 0.5, 1e4),
    "ward_1e-4": bsdf.Ward(0.5, 0.5, 1e-4, "duer"),
    "ward_1": bsdf.Ward(0.5, 0.5, 1.0),
    "lafortune_0_1e4": bsdf.Lafortune(0.5, 1.0, [-1.0, -1.0], [1.0, 1.0], [0.0, 1e4]),
    "as_0": bsdf.AshikhminShirley(0.5, 0.5, 0.0),
    "as_1e4": bsdf.AshikhminShirley(0.5, 0.5, 1e4),
}


@eqx.filter_jit
def _batched_param_grads(material, wo, wi):
    return jax.vmap(_param_grads, in_axes=(None, 0, 0))(material, wo, wi)


@pytest.mark.parametrize("name", sorted(EXTREME_MATERIALS))
def test_finite_values_and_gradients_at_extremes(name):
    """α = 1e-4 and 1, exponents 0 and 1e4, eta = 1, for (wo, wi) among cos θ = 1
    (wi = wo = n), 1e-7, 0 and below the horizon."""
    material = EXTREME_MATERIALS[name]
    dirs = jnp.asarray(list(EXTREMES.values()))
    wo = jnp.repeat(dirs, len(dirs), axis=0)
    wi = jnp.tile(dirs, (len(dirs), 1))
    vals = _eval_pairs(material, wo, wi)
    assert np.all(np.isfinite(np.asarray(vals))) and np.all(np.asarray(vals) >= 0)
    grads = _batched_param_grads(material, wo, wi)
    for leaf in jax.tree_util.tree_leaves(eqx.filter(grads, eqx.is_inexact_array)):
        assert np.all(np.isfinite(np.asarray(leaf))), name
