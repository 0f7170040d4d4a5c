"""BRDF fitting (`jaxrt.fit_brdf`) and the experiments `experiments/brdf/ngan_fit.py` and
`experiments/brdf/gallery.py`, on small synthetic data."""

import importlib.util
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrt as jr
from jaxrt import fit_brdf as fb
from jaxrt.config import ConfigError
from jaxrt.io import half_diff_angles, merl_angles, merl_lookup, read_exr, write_merl

ROOT = Path(__file__).resolve().parents[1]


def _script(name):
    spec = importlib.util.spec_from_file_location(f"brdf_{name}", ROOT / f"experiments/brdf/{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _random_angles(n, seed):
    rng = np.random.default_rng(seed)
    return (rng.uniform(0.0, np.pi / 2, n), rng.uniform(0.0, np.pi / 2, n),
            rng.uniform(-np.pi, np.pi, n))


# --------------------------------------------------------------------------- coordinates


def test_merl_directions_invert_half_diff_angles():
    angles = _random_angles(2000, 0)
    wo, wi = fb.merl_directions(*angles)
    np.testing.assert_allclose(np.linalg.norm(wo, axis=-1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(wi, axis=-1), 1.0, atol=1e-12)
    back = half_diff_angles(wo, wi)
    for a, b in zip(back, angles):
        np.testing.assert_allclose(a, b, atol=1e-9)
    # and the JAX version used by TabulatedBRDF agrees with the numpy one in jaxrt.io
    jax_back = jax.vmap(fb.half_diff)(jnp.asarray(wo), jnp.asarray(wi))
    for a, b in zip(jax_back, back):
        np.testing.assert_allclose(np.asarray(a), b, atol=1e-9)


def test_tabulated_brdf_matches_merl_lookup():
    """Nearest-cell lookup in JAX against `jaxrt.io.merl_lookup` on random direction
    pairs, upper and lower hemisphere, in a table of distinct values."""
    rng = np.random.default_rng(1)
    table = rng.uniform(0.0, 1.0, (90, 90, 180, 3))
    table[rng.random((90, 90, 180)) < 0.05] = -1.0
    v = rng.normal(size=(2, 3000, 3))
    wo, wi = v / np.linalg.norm(v, axis=-1, keepdims=True)
    wi[:, 2] = np.abs(wi[:, 2])  # most pairs above the horizon, some wo below
    material = fb.TabulatedBRDF(table)
    got = np.asarray(jax.vmap(material.eval)(jnp.asarray(wo), jnp.asarray(wi)))
    want = np.maximum(merl_lookup(table, wo, wi), 0.0)
    # Only pairs that are not within rounding of a cell boundary can be compared.
    assert np.mean(np.all(got == want, axis=-1)) > 0.999


def test_cell_weights_integrate_to_the_measure_of_hemisphere_pairs():
    """Σ over cells with both directions above the horizon of the cell measure, times
    the constant dθd dφd, 2π for φh and 2 for the folded φd, is ∫∫ dωi dωo = (2π)²."""
    wo, wi = fb.merl_directions(*merl_angles())
    above = (wo[..., 2] > 0) & (wi[..., 2] > 0)
    total = np.sum(fb.merl_cell_weights()[above]) * (np.pi / 180) * (np.pi / 180) * 2 * np.pi * 2
    assert total == pytest.approx((2 * np.pi) ** 2, rel=2e-3)


def test_sample_merl_masks_missing_and_grazing_cells():
    table = np.full((90, 90, 180, 3), 0.1)
    table[:, :, :90] = -1.0  # half of φd missing
    data = fb.sample_merl(table, 500, max_theta_deg=60.0, seed=3)
    assert data.f.shape == (500, 3)
    assert np.all(np.asarray(data.f) == 0.1)
    cos60 = np.cos(np.deg2rad(60.0))
    assert np.all(np.asarray(data.wo)[:, 2] > cos60 - 1e-12)
    assert np.all(np.asarray(data.wi)[:, 2] > cos60 - 1e-12)
    assert float(jnp.sum(data.weight)) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="no valid cells"):
        fb.sample_merl(-np.ones((90, 90, 180, 3)), 10)
    with pytest.raises(ValueError, match="weighting"):
        fb.sample_merl(table, 10, weighting="area")


# --------------------------------------------------------------------------- objective


def test_ngan_error_against_numpy():
    material = jr.bsdf.Ward(0.3, 0.1, 0.2)
    data = fb.sample_material(material, 300, seed=2)
    rng = np.random.default_rng(0)
    noisy = data._replace(f=data.f * rng.uniform(0.8, 1.2, (300, 3)),
                          weight=jnp.asarray(rng.uniform(0.5, 1.5, 300)))
    f_model = np.asarray(jax.vmap(material.eval)(noisy.wo, noisy.wi))
    c = np.asarray(noisy.wi)[:, 2:3]
    w = np.asarray(noisy.weight)
    want = np.sqrt(np.sum(w[:, None] * (np.asarray(noisy.f) * c - f_model * c) ** 2) / (3 * w.sum()))
    assert float(fb.ngan_error(material, noisy)) == pytest.approx(want, rel=1e-10)
    assert float(fb.ngan_error(material, data)) == pytest.approx(0.0, abs=1e-14)


@pytest.mark.parametrize("compression", fb.COMPRESSIONS)
def test_residuals_finite_with_zero_values(compression):
    """Black data and a black model (kd = 0 below, lobes vanishing) keep finite
    residuals and gradients under every compression."""
    spec = fb.model_spec("blinn_phong")
    data = fb.sample_material(jr.bsdf.Lambert(0.0), 50, seed=0)
    raw = spec.to_raw({"kd": 1e-6, "ks": 1e-6, "q": 1e4})

    @jax.jit
    def loss(raw):
        return jnp.sum(fb.residuals(spec.build(spec.to_values(raw)), data, compression) ** 2)

    value, g = jax.value_and_grad(loss)(raw)
    assert np.isfinite(float(value))
    assert all(np.all(np.isfinite(np.asarray(v))) for v in g.values())


def test_parameter_transforms_round_trip():
    for name in fb.MODELS:
        spec = fb.model_spec(name)
        values = spec.start(0.2, jnp.array([0.3, 0.2, 0.1]))
        values = {k: jnp.broadcast_to(jnp.asarray(v, float), spec.params[k].shape)
                  for k, v in values.items()}
        back = spec.to_values(spec.to_raw(values))
        for k in values:
            np.testing.assert_allclose(np.asarray(back[k]), np.asarray(values[k]), rtol=1e-9)
    with pytest.raises(ValueError, match="unknown BRDF model"):
        fb.model_spec("he")
    with pytest.raises(ValueError, match="unknown options"):
        fb.model_spec("ward", lobes=2)


# --------------------------------------------------------------------------- fits


def test_fit_recovers_cook_torrance_ggx():
    """Noise-free single-lobe data from a GGX Cook–Torrance with a diffuse base: the
    Levenberg–Marquardt fit of the same model recovers α, f0 and the diffuse albedo."""
    truth = jr.bsdf.CookTorrance(jr.bsdf.GGX(0.18), jr.bsdf.SchlickFresnel(0.06),
                                 geometry="smith_correlated", diffuse=(0.4, 0.2, 0.1))
    data = fb.sample_material(truth, 800, seed=5)
    res = fb.fit(fb.model_spec("cook_torrance_ggx"), data, alphas=(0.05, 0.4), max_steps=100)
    assert res.converged
    assert float(res.params["alpha"]) == pytest.approx(0.18, rel=0.05)
    assert float(res.params["f0"]) == pytest.approx(0.06, rel=0.05)
    np.testing.assert_allclose(np.asarray(res.params["diffuse"]), [0.4, 0.2, 0.1], rtol=0.05)
    assert res.info["error"] < 1e-4


def test_fit_recovers_blinn_phong_with_bfgs():
    truth = jr.bsdf.BlinnPhong(kd=(0.2, 0.3, 0.4), ks=0.3, q=120.0)
    data = fb.sample_material(truth, 600, seed=6)
    res = fb.fit(fb.model_spec("blinn_phong"), data, solver="bfgs", alphas=(0.3,), max_steps=300)
    assert float(res.params["q"]) == pytest.approx(120.0, rel=0.05)
    np.testing.assert_allclose(np.asarray(res.params["ks"]), 0.3, rtol=0.05)


# --------------------------------------------------------------------------- experiments


def test_ngan_fit_end_to_end_on_synthetic_data(tmp_path, capsys):
    ngan = _script("ngan_fit")
    rows = ngan.main(["--quick", "--out", str(tmp_path)])
    for name in ("results.md", "results.json", "config.json", "slices.png", "spheres.png",
                 "synthetic.binary", "spheres/reference.exr", "spheres/lambert.png",
                 "spheres/cook_torrance_ggx.exr"):
        assert (tmp_path / name).is_file(), name
    md = (tmp_path / "results.md").read_text()
    assert "| lambert |" in md and "| cook_torrance_ggx |" in md
    assert md in capsys.readouterr().out  # the table is printed
    result = json.loads((tmp_path / "results.json").read_text())
    errors = {r["label"]: r["error_heldout"] for r in result["rows"]}
    # A specular lobe explains a glossy material better than a constant.
    assert errors["cook_torrance_ggx"] < 0.5 * errors["lambert"]
    assert rows == result["rows"]
    sphere = read_exr(tmp_path / "spheres" / "cook_torrance_ggx.exr")["rgb"]
    assert sphere.shape == (12, 12, 3) and np.all(np.isfinite(sphere)) and sphere.max() > 0


def test_ngan_fit_reads_a_given_merl_file(tmp_path):
    """`--merl PATH`: a noise-free single-lobe table written by the test; the fitted GGX
    roughness is the generating one."""
    truth = jr.bsdf.CookTorrance(jr.bsdf.GGX(0.2), jr.bsdf.SchlickFresnel(0.05),
                                 geometry="smith_correlated", diffuse=(0.25, 0.25, 0.3))
    path = tmp_path / "measured.binary"
    write_merl(path, fb.tabulate_merl(truth))
    ngan = _script("ngan_fit")
    ngan.main(["--quick", "--merl", str(path), "--out", str(tmp_path / "out")])
    result = json.loads((tmp_path / "out" / "results.json").read_text())
    assert result["source"] == str(path)
    ct = next(r for r in result["rows"] if r["label"] == "cook_torrance_ggx")
    assert ct["parameters"]["alpha"] == pytest.approx(0.2, rel=0.05)
    assert not any(r["label"] == "(generating model)" for r in result["rows"])


def test_ngan_fit_config_errors_name_the_key(tmp_path):
    ngan = _script("ngan_fit")
    text = (ROOT / "configs/experiments/ngan_fit.toml").read_text()
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace('compression = "none"      #', 'compression = "sqrt"      #'))
    with pytest.raises(ConfigError, match=r"fit\.compression = 'sqrt'"):
        ngan.load_config(bad)
    bad.write_text(text.replace("[models.ward]\n", "[models.ward]\nlobes = 3\n"))
    with pytest.raises(ConfigError, match=r"models\.ward"):
        ngan.load_config(bad)


def test_gallery_end_to_end(tmp_path):
    """2 models x 2 roughnesses in one scene: a sphere in every tile, and the rougher
    sphere of each model has the dimmer highlight."""
    gallery = _script("gallery")
    cfg = gallery.load_config(gallery.DEFAULT_CONFIG, quick=True)
    cfg["tile"] = 16
    rgb = gallery.run(cfg, tmp_path)
    for name in ("gallery.exr", "gallery.png", "gallery_labeled.png"):
        assert (tmp_path / name).is_file()
    tile = cfg["tile"]
    rows, cols = len(cfg["models"]), len(cfg["alphas"])
    assert rgb.shape == (rows * tile, cols * tile, 3) and np.all(np.isfinite(rgb))
    depth = read_exr(tmp_path / "gallery.exr")["depth"]
    peak = np.zeros((rows, cols))
    for r in range(rows):
        for c in range(cols):
            block = (slice(r * tile, (r + 1) * tile), slice(c * tile, (c + 1) * tile))
            assert depth[block][tile // 2, tile // 2] < 20.0  # the sphere is there
            assert depth[block][0, 0] > 20.0                   # the corners miss
            peak[r, c] = rgb[block].sum(-1).max()
    assert np.all(peak[:, 0] > peak[:, 1])
    bad = tmp_path / "bad.toml"
    bad.write_text((ROOT / "configs/experiments/gallery.toml").read_text()
                   .replace("alphas = [0.05,", "alphas = [-0.05,"))
    with pytest.raises(ConfigError, match="alphas"):
        gallery.load_config(bad)
