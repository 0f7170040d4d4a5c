"""The inverse-rendering studies (experiments/inverse/): each one's --quick version
runs end to end, writes its outputs and meets its quick targets (the config's
[quick.targets]). Slow: each takes minutes on 2 CPU cores."""

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

from jaxrt.config import load as load_scene

ROOT = Path(__file__).resolve().parents[1]
OUTPUTS = ("results.json", "results.md", "curves.png", "grid.png", "fitted.toml", "fitted.exr",
           "config.json")


def _script(name):
    path = ROOT / "experiments" / "inverse" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(f"inverse_{name}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
@pytest.mark.parametrize("name", ["materials", "optics", "pose", "csg"])
def test_quick_study_meets_its_quick_targets(name, tmp_path):
    results = _script(name).main(["--quick", "--fresh", "--out", str(tmp_path)])
    for f in OUTPUTS:
        assert (tmp_path / f).is_file(), f
    assert json.loads((tmp_path / "results.json").read_text())["metrics"] == results["metrics"]
    assert results["met"] and all(results["met"].values()), (results["metrics"], results["targets"])
    scene, camera, settings = load_scene(tmp_path / "fitted.toml")  # the fitted scene reads back
    assert camera.width == results["size"]


@pytest.mark.parametrize("method", ["bfgs", "levenberg-marquardt"])
def test_refine_reaches_the_truth_of_a_smooth_loss_and_holds_the_rest(method):
    """The studies' [refine] phase (BFGS on the loss, or Levenberg–Marquardt on the
    residuals, of the targets' own estimator): from 10 % and
    40 % off, a Lambert albedo and the background are recovered to 1e-4 (the loss is
    smooth in both: geometry is known), the light's intensity, left out of `free`,
    keeps its value (with it free, albedo × intensity alone would be observable), and
    the loss at the truth is 0."""
    common = _script("common")
    import jax.numpy as jnp
    import jaxrt as jr

    camera = jr.PerspectiveCamera(eye=(0.0, 0.3, -3.0), target=(0.0, 0.0, 0.0), fov=40.0,
                                  width=10, height=10)
    cameras = jr.stack_cameras([camera])
    truth = {"albedo": jnp.asarray([0.6, 0.4, 0.2]), "background": jnp.asarray(0.5),
             "power": jnp.asarray(30.0)}

    def build(p):
        scene = jr.Scene(jr.sdf.Sphere(1.0), [jr.bsdf.Lambert(p["albedo"])],
                         [jr.PointLight((2.0, 3.0, -3.0), (p["power"],) * 3)],
                         background=p["background"])
        return scene, cameras

    study = common.Study("tiny", truth, build, {"albedo": jr.fit.UNIT, "background": jr.fit.UNIT})
    cfg = {"target_settings": {"shadows": "none", "aovs": []}, "run": {"devices": 1},
           "refine": {"steps": 60, "free": ["albedo", "background"], "method": method}}
    targets = jr.render_views(*build(truth), common.settings(cfg, "target_settings"), devices=1).rgb
    start = {"albedo": truth["albedo"] * 1.1, "background": jnp.asarray(0.3), "power": truth["power"]}
    fitted, info = common.refine(study, cfg, start, targets)
    assert info["loss_end"] < 1e-6 * info["loss_start"] and info["loss_truth"] == 0.0
    assert info["method"] == method
    for k in ("albedo", "background"):
        err = np.max(np.abs(np.asarray(fitted[k]) - np.asarray(truth[k])) / np.asarray(truth[k]))
        assert err < 1e-4, (k, err)
    assert fitted["power"] is start["power"]
