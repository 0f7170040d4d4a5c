"""RenderSettings.preset: the presets keep the error they claim (PRESET_CLAIMS), and
sit in order (balanced is more accurate than fast)."""

import numpy as np
import pytest

import jaxrt as jr
from jaxrt.settings import PRESET_CLAIMS, PRESETS


@pytest.fixture(scope="module")
def scene_camera():
    S = jr.sdf
    scene = jr.Scene(
        surface=S.Union(S.Translate(S.Sphere(radius=0.6, material=0), offset=(0.0, 0.6, 0.0)),
                        S.Translate(S.Box(half_extents=(0.35, 0.35, 0.35), material=1),
                                    offset=(1.0, 0.35, -0.3)),
                        S.Plane(normal=(0.0, 1.0, 0.0), offset=0.0, material=1)),
        materials=[jr.bsdf.Lambert(albedo=(0.8, 0.3, 0.2)), jr.bsdf.Lambert(albedo=(0.6, 0.6, 0.6))],
        lights=[jr.PointLight(position=(2.0, 4.0, 3.0), intensity=(30.0, 30.0, 30.0))],
        background=(0.1, 0.1, 0.15))
    camera = jr.PerspectiveCamera(eye=(0.0, 1.5, 3.5), target=(0.3, 0.4, 0.0), up=(0.0, 1.0, 0.0),
                                  fov=45.0, width=24, height=16)
    return scene, camera


@pytest.fixture(scope="module")
def reference(scene_camera):
    scene, camera = scene_camera
    base = jr.RenderSettings(shadows="soft")
    return np.asarray(jr.render(scene, camera, jr.RenderSettings.preset("reference", base=base)).rgb)


@pytest.fixture(scope="module")
def preset_rmse(scene_camera, reference):
    """RMSE of linear RGB against the reference, per claimed preset (at 16 spp)."""
    scene, camera = scene_camera
    out = {}
    for name in PRESET_CLAIMS:
        settings = jr.RenderSettings.preset(name, base=jr.RenderSettings(shadows="soft"), spp=16)
        rgb = np.asarray(jr.render(scene, camera, settings).rgb)
        assert np.isfinite(rgb).all()
        out[name] = float(np.sqrt(np.mean((rgb - reference) ** 2)))
    return out


@pytest.mark.parametrize("name", sorted(PRESET_CLAIMS))
def test_preset_error_within_claim(preset_rmse, name):
    assert preset_rmse[name] <= PRESET_CLAIMS[name], (name, preset_rmse[name])


def test_balanced_is_more_accurate_than_fast(preset_rmse):
    # measured, not only claimed: the presets sit in order on the front
    assert PRESET_CLAIMS["balanced"] < PRESET_CLAIMS["fast"]
    assert preset_rmse["balanced"] < preset_rmse["fast"], preset_rmse


def test_preset_keeps_the_scene_dials_and_applies_changes():
    base = jr.RenderSettings(shadows="soft", penumbra=3.0, max_depth=5, max_distance=7.0)
    s = jr.RenderSettings.preset("fast", base=base, spp=2)
    assert (s.shadows, s.penumbra, s.max_depth, s.max_distance) == ("soft", 3.0, 5, 7.0)
    assert s.spp == 2 and s.pixel_epsilon == PRESETS["fast"]["pixel_epsilon"]
    with pytest.raises(ValueError, match="preset"):
        jr.RenderSettings.preset("fastest")
