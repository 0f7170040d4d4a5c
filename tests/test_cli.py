"""The `jaxrt render` command: outputs on success, a clear message and no files on error."""

import numpy as np

from jaxrt import io
from jaxrt.cli import main

SCENE = """
[camera]
eye = [0.0, 0.0, -4.0]
target = [0.0, 0.0, 0.0]
width = 12
height = 8

[materials.white]
type = "lambert"

[[lights]]
type = "directional"
direction = [0.0, 0.0, -1.0]
irradiance = 3.0

[surface]
type = "sphere"
radius = 1.0
"""


def test_render_writes_exr_and_png(tmp_path, capsys):
    config = tmp_path / "ball.toml"
    config.write_text(SCENE)
    out = tmp_path / "renders" / "ball"
    assert main(["render", str(config), "-o", str(out), "--width", "10", "--height", "6", "--spp", "2"]) == 0
    printed = capsys.readouterr().out
    assert "10×6" in printed and "compile" in printed and "render" in printed
    assert "backend auto" in printed  # the file names none
    image = io.read_exr(out.with_suffix(".exr"))
    assert image["rgb"].shape == (6, 10, 3) and image["depth"].shape == (6, 10)
    assert np.all(np.isfinite(image["rgb"]))
    # The centre of the ball faces the light: lit; the corners see the black background.
    assert image["rgb"][3, 5, 0] > 0.5 and image["rgb"][0, 0, 0] == 0.0
    assert out.with_suffix(".png").read_bytes().startswith(b"\x89PNG")


def test_bad_config_exits_nonzero_and_writes_nothing(tmp_path, capsys):
    config = tmp_path / "bad.toml"
    config.write_text(SCENE.replace("radius = 1.0", "radius = -2.0"))
    out = tmp_path / "renders" / "bad"
    assert main(["render", str(config), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"{config}: surface.radius = -2.0, expected a value > 0" in err
    assert not (tmp_path / "renders").exists()


def test_missing_config_exits_nonzero(tmp_path, capsys):
    assert main(["render", str(tmp_path / "nope.toml"), "-o", str(tmp_path / "x")]) == 2
    assert "cannot read the file" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_backend_from_the_flag_else_the_file(tmp_path, capsys):
    """--backend wins; else the file's settings.backend; the images agree."""
    config = tmp_path / "ball.toml"
    config.write_text(SCENE.replace("[materials.white]", '[settings]\nbackend = "jax"\n\n[materials.white]'))
    assert main(["render", str(config), "-o", str(tmp_path / "a")]) == 0
    assert "backend jax" in capsys.readouterr().out
    assert main(["render", str(config), "-o", str(tmp_path / "b"), "--backend", "fused"]) == 0
    assert "backend fused" in capsys.readouterr().out
    a, b = io.read_exr(tmp_path / "a.exr")["rgb"], io.read_exr(tmp_path / "b.exr")["rgb"]
    np.testing.assert_allclose(a, b, atol=1e-5)
