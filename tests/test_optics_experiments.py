"""The optics experiments of the notes from their fast [quick] configurations: Snell's
window, the rainbow and the prism, each against theory computed here independently."""

import importlib.util
import math
import tomllib
from pathlib import Path

import numpy as np
import pytest

from jaxrt import spectral

ROOT = Path(__file__).resolve().parents[1]


def _load(name):
    spec = importlib.util.spec_from_file_location(f"optics_{name}", ROOT / f"experiments/optics/{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _config(name):
    return tomllib.loads((ROOT / f"configs/experiments/{name}.toml").read_text())


@pytest.fixture(scope="module")
def snell(tmp_path_factory):
    out = tmp_path_factory.mktemp("snell_window")
    return _load("snell_window").main(["--quick", "--out", str(out)]), out


@pytest.fixture(scope="module")
def rainbow(tmp_path_factory):
    out = tmp_path_factory.mktemp("rainbow")
    return _load("rainbow").main(["--quick", "--out", str(out)]), out


@pytest.fixture(scope="module")
def prism(tmp_path_factory):
    out = tmp_path_factory.mktemp("prism")
    return _load("prism").main(["--quick", "--out", str(out)]), out


# --- Snell's window ----------------------------------------------------------------------


def test_snell_window_matches_the_critical_angle(snell):
    results, out = snell
    cfg = _config("snell_window")
    n = float(spectral.ior_preset(cfg["ior"])(cfg["wavelength"]))
    theory = 2.0 * math.degrees(math.asin(1.0 / n))
    assert abs(results["measured_full_angle_deg"] - theory) < 0.5
    assert abs(results["measured_full_angle_deg"] - 97.2) < 0.5   # the notes' figure
    left, right = results["edges_deg"]
    assert abs(left + right) < 0.05                                # symmetric about the zenith
    for f in ("snell_window.png", "snell_window_profile.png", "results.json", "config.json"):
        assert (out / f).stat().st_size > 0


def test_window_edge_measurement_on_a_synthetic_profile():
    """A profile that is bright (and shaded) inside ±40° and uniformly dark outside, as
    under total internal reflection, measures 80° to a pixel (0.5°)."""
    measure = _load("snell_window").measure_window
    angle = np.linspace(-89.75, 89.75, 360)
    profile = np.where(np.abs(angle) < 40.0, 1.0 + 0.3 * np.cos(np.radians(angle)), 0.02)
    full, left, right = measure(profile, angle, 0.05)
    assert abs(full - 80.0) < 0.5 and abs(left + 40.0) < 0.5
    with pytest.raises(ValueError, match="border"):
        measure(np.where(np.arange(angle.size) == 100, 0.0, 1.0), angle, 0.05)  # no dark rim


# --- rainbow ---------------------------------------------------------------------------


def _bow_by_minimum_deviation(n, k):
    """α = 180° − D for the primary (k = 1), D − 180° for the secondary (k = 2), with D
    the minimum over incidence i of the deviation k·180° + 2i − 2(k + 1) asin(sin i / n),
    found on a fine grid of i (no closed form)."""
    i = np.linspace(0.0, np.pi / 2, 2_000_001)
    d = np.degrees(k * np.pi + 2 * i - 2 * (k + 1) * np.arcsin(np.sin(i) / n))
    d_min = d.min()
    return 180.0 - d_min if k == 1 else d_min - 180.0


@pytest.mark.parametrize("k", [1, 2])
def test_bow_angles_match_minimum_deviation(rainbow, k):
    results, _ = rainbow
    cfg = _config("rainbow")
    rows = results["bows"][str(k)]
    assert rows, "the quick config reports at least one wavelength"
    for row in rows:
        n = float(spectral.ior_preset(cfg["ior"])(row["wavelength_nm"]))
        expected = _bow_by_minimum_deviation(n, k)
        assert abs(row["peak_deg"] - expected) < 0.5
        assert abs(row["extreme_deg"] - expected) < 0.05
    if k == 1:
        assert abs(rows[0]["peak_deg"] - 42.0) < 0.5   # the notes: "max for angle around 42 deg"


def test_bows_are_dispersed_in_opposite_orders(rainbow):
    """Red is outside in the primary bow, inside in the secondary (reversed colours)."""
    results, out = rainbow
    primary = sorted(results["bows_spectral_samples"]["1"], key=lambda r: r["wavelength_nm"])
    secondary = sorted(results["bows_spectral_samples"]["2"], key=lambda r: r["wavelength_nm"])
    assert np.all(np.diff([r["extreme_deg"] for r in primary]) > 0)
    assert np.all(np.diff([r["extreme_deg"] for r in secondary]) < 0)
    assert (out / "rainbow.png").stat().st_size > 0 and (out / "rainbow_plot.png").stat().st_size > 0


# --- prism -----------------------------------------------------------------------------


def test_prism_deviation_matches_the_prism_formula(prism):
    results, out = prism
    cfg = _config("prism")
    ior = spectral.ior_preset(cfg["glass"])
    a = math.radians(cfg["apex_angle"])
    theta_i = math.radians(results["incidence_deg"])
    if cfg["incidence"] == 0.0:  # minimum deviation at the reference wavelength
        assert abs(theta_i - math.asin(float(ior(cfg["reference_wavelength"])) * math.sin(a / 2))) < 1e-9
    for row in results["deviation"]:
        n = float(ior(row["wavelength_nm"]))
        # Snell at both faces, by hand: r1 = asin(sin θi / n), r2 = A − r1, θe = asin(n sin r2).
        r1 = math.asin(math.sin(theta_i) / n)
        expected = math.degrees(theta_i + math.asin(n * math.sin(a - r1)) - a)
        assert abs(row["deviation_deg"] - expected) < 1e-6
    dev = [r["deviation_deg"] for r in sorted(results["deviation"], key=lambda r: r["wavelength_nm"])]
    assert np.all(np.diff(dev) < 0)                     # blue is bent more than red
    assert results["angular_spread_400_700_deg"] > 0.0
    for f in ("prism.png", "prism_screen.png", "results.json"):
        assert (out / f).stat().st_size > 0
