"""Spectral mode: wavelength samples, colour conversion, dispersion models."""

import colour
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrt import spectral as sp

DENSE = 400  # 1 nm strata over 380–780 nm


# --- wavelengths ----------------------------------------------------------------------


@pytest.mark.parametrize("n", [1, 3, 16])
def test_sample_wavelengths_stratified(n):
    width = 400.0 / n
    jitter = np.linspace(0.0, 0.999, n)
    for offset in (0.5, 0.0, jitter):
        lam = np.asarray(sp.sample_wavelengths(n, offset))
        lo = 380.0 + np.arange(n) * width
        assert lam.shape == (n,)
        assert np.all(lam >= lo - 1e-9) and np.all(lam < lo + width)
    assert np.allclose(np.asarray(sp.sample_wavelengths(n)), 380.0 + (np.arange(n) + 0.5) * width)


def test_sample_wavelengths_errors():
    with pytest.raises(ValueError, match="n="):
        sp.sample_wavelengths(0)
    with pytest.raises(ValueError, match="offset="):
        sp.sample_wavelengths(4, np.zeros(3))


# --- colour ---------------------------------------------------------------------------


def _xy(xyz):
    xyz = np.asarray(xyz)
    return xyz[:2] / xyz.sum()


def test_cmf_flat_spectrum_is_equal_energy_white():
    """∫ x̄, ∫ ȳ, ∫ z̄ of a flat spectrum are equal (CIE's illuminant E): x = y = 1/3."""
    lam = jnp.arange(360.0, 831.0)
    xyz = np.asarray(sp.cmf(lam)).sum(axis=0)
    assert np.allclose(_xy(xyz), [1 / 3, 1 / 3], atol=2e-4)


def test_cmf_d65_integrates_to_the_d65_white_point():
    """∫ D65 · cmf has the tabulated chromaticity of D65 (colour-science)."""
    lam = jnp.arange(360.0, 831.0)
    xyz = np.asarray(sp.illuminant_d65(lam)[:, None] * sp.cmf(lam)).sum(axis=0)
    d65 = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]
    assert np.allclose(_xy(xyz), d65, atol=2e-4)
    assert np.allclose(_xy(sp.white_point_xyz()), d65, atol=2e-4)


@pytest.mark.parametrize("n", [3, 8, 64, DENSE])
def test_flat_spectrum_is_white(n):
    for offset in (0.5, 0.13):
        lam = sp.sample_wavelengths(n, offset)
        xyz = sp.spectrum_to_xyz(jnp.ones(n), lam)
        d65 = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]
        assert np.allclose(_xy(xyz), d65, atol=2e-4)
        assert abs(float(xyz[1]) - 1.0) < 1e-3
        rgb = sp.spectrum_to_rgb(2.5 * jnp.ones(n), lam)
        assert np.allclose(rgb, 2.5, atol=1e-4)


def test_quadrature_converges_to_colour_science():
    """Our XYZ of a smooth spectrum agrees with colour-science's own integration."""
    lam = sp.sample_wavelengths(DENSE)
    shape = colour.SpectralShape(380, 780, 5)
    grid = np.arange(380.0, 781.0, 5.0)
    values = 0.5 + 0.4 * np.sin(grid / 37.0) * np.cos(grid / 91.0)
    sd = colour.SpectralDistribution(dict(zip(grid, values)), name="test").align(shape)
    ref = colour.sd_to_XYZ(sd, illuminant=colour.SDS_ILLUMINANTS["D65"]) / 100.0
    ours = sp.spectrum_to_xyz(jnp.interp(lam, jnp.asarray(grid), jnp.asarray(values)), lam)
    # Both are normalised so that the perfect white has Y = 1.
    assert np.allclose(ours, ref * np.asarray(sp.white_point_xyz())[1], atol=3e-3)


def test_mallett_basis_reproduces_srgb_without_calibration():
    """At 1 nm the basis spectra map to the sRGB primaries by the plain quadrature: the
    calibration of `spectrum_to_rgb` is only a small-N correction."""
    lam = sp.sample_wavelengths(DENSE)
    basis = jax.vmap(lambda c: sp.rgb_to_spectrum(c, lam))(jnp.eye(3))
    rgb = jax.vmap(lambda s: sp.xyz_to_rgb(sp.spectrum_to_xyz(s, lam)))(basis)
    assert np.allclose(rgb, np.eye(3), atol=2e-3)
    assert np.allclose(sp.spectral_rgb_matrix(lam) @ basis.T, np.eye(3), atol=1e-9)


@pytest.mark.parametrize("n", [4, 16, 64])
def test_rgb_spectrum_round_trip(n):
    rng = np.random.default_rng(1)
    colours = rng.uniform(0.0, 1.0, (32, 3))
    lam = sp.sample_wavelengths(n, rng.uniform(0.0, 1.0, n))
    spectra = jax.vmap(lambda c: sp.rgb_to_spectrum(c, lam))(jnp.asarray(colours))
    assert spectra.shape == (32, n)
    # In-gamut reflectances become physically valid reflectance spectra.
    assert np.all(np.asarray(spectra) >= -1e-6) and np.all(np.asarray(spectra) <= 1.0 + 1e-6)
    back = jax.vmap(lambda s: sp.spectrum_to_rgb(s, lam))(spectra)
    assert np.allclose(back, colours, atol=1e-6)


@pytest.mark.parametrize("lam0, channel", [(450.0, 2), (535.0, 1), (620.0, 0)])
def test_monochromatic_light_has_its_hue(lam0, channel):
    lam = sp.sample_wavelengths(80)
    values = jnp.exp(-0.5 * ((lam - lam0) / 8.0) ** 2)
    rgb = np.asarray(sp.spectrum_to_rgb(values, lam))
    assert np.argmax(rgb) == channel


def test_spectrum_to_rgb_errors():
    lam = sp.sample_wavelengths(8)
    with pytest.raises(ValueError, match="values="):
        sp.spectrum_to_rgb(jnp.ones(7), lam)
    with pytest.raises(ValueError, match="at least 3"):
        sp.spectrum_to_rgb(jnp.ones(2), sp.sample_wavelengths(2))
    with pytest.raises(ValueError, match="rgb="):
        sp.rgb_to_spectrum(jnp.ones(4), lam)


def test_float32_conversion_stays_float32():
    lam = sp.sample_wavelengths(8, dtype=jnp.float32)
    rgb = sp.spectrum_to_rgb(jnp.ones(8, jnp.float32), lam)
    assert rgb.dtype == jnp.float32 and np.allclose(rgb, 1.0, atol=1e-4)


# --- indices of refraction --------------------------------------------------------------

# Catalogue values (Schott data sheets; Malitson 1965; Daimon & Masumura 2007 at 20 °C;
# Peter 1923 / gemmological n_D of diamond).
PUBLISHED = [
    (sp.BK7, "d", 1.5168),
    (sp.CAUCHY_BK7, "d", 1.5168),
    (sp.FUSED_SILICA, "d", 1.4585),
    (sp.WATER, "D", 1.333),
    (sp.DIAMOND, "D", 2.417),
    (sp.SF11, "d", 1.78472),
]


@pytest.mark.parametrize("ior, line, n", PUBLISHED)
def test_presets_match_published_index(ior, line, n):
    assert abs(float(ior(sp.FRAUNHOFER[line])) - n) < 1e-3


@pytest.mark.parametrize("ior, v_d", [(sp.BK7, 64.17), (sp.FUSED_SILICA, 67.82), (sp.SF11, 25.68)])
def test_presets_match_published_abbe_number(ior, v_d):
    assert abs(float(sp.abbe_number(ior)) - v_d) < 0.1


@pytest.mark.parametrize("name", sorted(sp.IOR_PRESETS))
def test_normal_dispersion_over_the_visible(name):
    """n decreases with λ over 380–780 nm (normal dispersion), dn/dλ < 0."""
    ior = sp.ior_preset(name)
    lam = jnp.linspace(380.0, 780.0, 81)
    n = ior(lam)
    dn = jax.vmap(jax.grad(lambda w: ior(w)))(lam)
    assert np.all(np.diff(np.asarray(n)) < 0.0)
    assert np.all(np.asarray(dn) < 0.0)
    assert np.all(np.asarray(n) > 1.0)


def test_cauchy_and_sellmeier_bk7_agree():
    lam = jnp.linspace(400.0, 750.0, 36)
    assert np.max(np.abs(np.asarray(sp.CAUCHY_BK7(lam) - sp.BK7(lam)))) < 1.5e-3


def test_constant_ior_is_not_dispersive():
    ior = sp.ConstantIOR(1.5)
    assert not ior.is_dispersive and sp.BK7.is_dispersive
    assert np.allclose(ior(jnp.linspace(400.0, 700.0, 4)), 1.5)


@pytest.mark.parametrize("ior", [sp.BK7, sp.CAUCHY_BK7], ids=["sellmeier", "cauchy"])
def test_ior_gradient_matches_finite_differences(ior):
    lam = 512.0
    grads = jax.grad(lambda m: m(lam))(ior)
    leaves, treedef = jax.tree_util.tree_flatten(ior)
    g_leaves = jax.tree_util.tree_leaves(grads)
    for k, (leaf, g) in enumerate(zip(leaves, g_leaves)):
        leaf = np.asarray(leaf, dtype=np.float64)
        for idx in np.ndindex(leaf.shape):
            h = 1e-6 * max(1.0, abs(leaf[idx]))
            up, down = leaf.copy(), leaf.copy()
            up[idx] += h
            down[idx] -= h

            def at(v):
                new = list(leaves)
                new[k] = jnp.asarray(v)
                return float(jax.tree_util.tree_unflatten(treedef, new)(lam))

            fd = (at(up) - at(down)) / (2 * h)
            assert np.isclose(float(np.asarray(g)[idx]), fd, rtol=1e-6, atol=1e-9)


def test_sellmeier_finite_at_a_resonance():
    ior = sp.Sellmeier(b=(1.0,), c=(0.5**2,))  # resonance at 500 nm
    n, dn = jax.value_and_grad(lambda w: ior(w))(500.0)
    assert np.isfinite(n) and np.isfinite(dn)


def test_ior_errors():
    with pytest.raises(ValueError, match="Sellmeier"):
        sp.Sellmeier(b=(1.0, 2.0), c=(1.0,))
    with pytest.raises(ValueError, match="unknown IOR preset"):
        sp.ior_preset("unobtainium")
