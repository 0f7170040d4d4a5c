"""The README's examples run as written (at a smaller image size)."""

import re
from pathlib import Path

import numpy as np

import jaxrt as jr

README = (Path(__file__).parents[1] / "README.md").read_text()


def test_python_example_runs(tmp_path, monkeypatch):
    code = re.findall(r"```python\n(.*?)```", README, re.S)[0]
    code = code.replace("width=320, height=240", "width=16, height=12")
    monkeypatch.chdir(tmp_path)
    namespace = {}
    exec(compile(code, "README.md", "exec"), namespace)
    assert namespace["image"].rgb.shape == (12, 16, 3)
    assert (tmp_path / "sphere.exr").exists() and (tmp_path / "sphere.png").exists()


def test_config_example_loads(tmp_path):
    toml = re.findall(r"```toml\n(.*?)```", README, re.S)[0]
    path = tmp_path / "scene.toml"
    path.write_text(toml)
    scene, camera, settings = jr.config.load(path, width=8, height=6)
    image = jr.render(scene, camera, settings)
    assert np.all(np.isfinite(image.rgb))
