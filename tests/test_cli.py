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


# --------------------------------------------------------------------------- conventions


def test_python_m_jaxrt_and_version():
    import subprocess
    import sys

    import jaxrt

    out = subprocess.run([sys.executable, "-m", "jaxrt", "--version"], capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == f"jaxrt {jaxrt.__version__}"


def test_devices_on_a_cpu_get_as_many_xla_devices(tmp_path):
    """`--set devices=2` makes two XLA CPU devices before JAX starts (a fresh process:
    this one's backend has started) and shards the image over them: the same image as
    on one device. A second run reads the sharded program back from the cache."""
    import os
    import subprocess
    import sys

    config = tmp_path / "ball.toml"
    config.write_text(SCENE)
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    env.update(JAX_PLATFORMS="cpu", JAXRT_NO_CACHE="", JAXRT_CACHE_DIR=str(tmp_path / "cache"))
    runs = {"one": ["devices=1"], "two": ["devices=2"], "cached": ["devices=2"]}
    for name, settings in runs.items():
        out = subprocess.run([sys.executable, "-m", "jaxrt", "render", str(config), "-o",
                              str(tmp_path / name), "--width", "16", "--height", "8",
                              *[a for s in settings for a in ("--set", s)]],
                             capture_output=True, text=True, timeout=600, env=env)
        assert out.returncode == 0, out.stderr[-2000:]
        assert (", 1 device\n" if name == "one" else ", 2 devices\n") in out.stdout
        assert ("(the cached program)" in out.stderr) == (name == "cached")
    one, *others = (io.read_exr(tmp_path / f"{name}.exr")["rgb"] for name in runs)
    for image in others:
        np.testing.assert_allclose(image, one, atol=1e-6)


def test_add_host_devices_only_before_jax_starts_and_keeps_a_users_count(monkeypatch):
    from jaxrt import xla

    monkeypatch.setattr(xla, "_backend_started", lambda: False)
    env = {"XLA_FLAGS": "--xla_cpu_use_fusion_emitters=false"}
    assert xla.add_host_devices(3, env)
    assert env["XLA_FLAGS"] == ("--xla_cpu_use_fusion_emitters=false "
                                "--xla_force_host_platform_device_count=3")
    assert not xla.add_host_devices(2, env) and env["XLA_FLAGS"].endswith("count=3")
    assert not xla.add_host_devices(1, {})
    monkeypatch.setattr(xla, "_backend_started", lambda: True)
    env = {}
    assert not xla.add_host_devices(2, env) and env == {}


def test_set_overrides_any_setting_and_compile_lines(tmp_path, capsys):
    config = tmp_path / "ball.toml"
    config.write_text(SCENE)
    out = tmp_path / "ball"
    argv = ["render", str(config), "-o", str(out), "--set", "max_steps=64", "--set", "shadows=none",
            "--set", 'aovs=["depth"]', "--set", "backend=jax", "--no-cache"]
    assert main(argv) == 0
    captured = capsys.readouterr()
    assert "backend jax" in captured.out and "Mrays/s" in captured.out
    assert "0.000 Mrays/s" not in captured.out
    lines = captured.err.strip().splitlines()
    assert lines[0] == "jaxrt: compiling…" and lines[1].startswith("jaxrt: compiled in ")
    image = io.read_exr(out.with_suffix(".exr"))
    assert "depth" in image and "normal" not in image  # aovs = ["depth"]


def test_set_unknown_or_invalid_is_one_line(tmp_path, capsys):
    config = tmp_path / "ball.toml"
    config.write_text(SCENE)
    out = tmp_path / "renders" / "ball"
    for item, expected in [
        ("max_stepz=3", "--set max_stepz=3: unknown setting `max_stepz`, expected one of max_steps, "),
        ("max_steps=0", "--set: settings.max_steps = 0, expected an integer ≥ 1"),
        ("shadows=sharp", "--set: settings.shadows = 'sharp', expected one of ('none', 'hard', 'soft')"),
        ("max_steps", "--set max_steps: expected KEY=VALUE"),
    ]:
        assert main(["render", str(config), "-o", str(out), "--set", item]) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and err.startswith(f"jaxrt: error: {expected}"), err
    assert not (tmp_path / "renders").exists()


def test_format_rate_has_three_significant_digits():
    from jaxrt.cli import format_rate

    assert [format_rate(x) for x in (0.000123456, 0.0456, 4.567, 78.9, 789.4, 12345.6, 0.0)] == \
        ["0.000123", "0.0456", "4.57", "78.9", "789", "12346", "0"]


# --------------------------------------------------------------------------- all or nothing


def _fake_compile(monkeypatch, calls=None):
    """`compile_render` replaced by one that returns a 6×10 image at once (the output
    tests are about files, not rendering)."""
    import importlib

    import jax.numpy as jnp

    render_module = importlib.import_module("jaxrt.render")  # the module, not jaxrt.render()

    def fake(scene, camera, settings):
        if calls is not None:
            calls.append(1)
        h, w = camera.height, camera.width
        return lambda scene, camera: render_module.Image(
            rgb=jnp.full((h, w, 3), 0.5), depth=jnp.ones((h, w)))

    monkeypatch.setattr(render_module, "compile_render", fake)
    monkeypatch.setenv("JAXRT_NO_CACHE", "1")  # the CLI then calls compile_render itself


def _ball(tmp_path):
    config = tmp_path / "ball.toml"
    config.write_text(SCENE)
    return config


def _one_error_line(capsys, *fragments):
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert lines[-1].startswith("jaxrt: error: ") and "Traceback" not in captured.err, captured.err
    assert all(f in lines[-1] for f in fragments), lines[-1]
    errors = [line for line in lines if line.startswith("jaxrt: error")]
    assert len(errors) == 1
    return lines[-1]


def _unwritable_folder(tmp_path):
    """A folder in which no file can be created, for root too where possible."""
    import os

    import pytest

    folder = tmp_path / "locked"
    folder.mkdir()
    folder.chmod(0o555)
    try:
        io.check_writable(folder / "x.exr")
    except io.JaxrtIOError:
        return folder
    if os.path.isdir("/sys"):  # root ignores modes; sysfs is read-only
        try:
            io.check_writable("/sys/jaxrt-test.exr")
        except io.JaxrtIOError:
            return Path("/sys")
    pytest.skip("no unwritable folder on this machine")


from pathlib import Path  # noqa: E402


def test_unwritable_folder_fails_before_compiling(tmp_path, capsys, monkeypatch):
    calls = []
    _fake_compile(monkeypatch, calls)
    folder = _unwritable_folder(tmp_path)
    assert main(["render", str(_ball(tmp_path)), "-o", str(folder / "sub" / "ball")]) == 1
    _one_error_line(capsys, "cannot write in", str(folder))
    assert calls == [] and not (folder / "sub").exists()


def test_parent_is_a_file_or_target_is_a_folder(tmp_path, capsys, monkeypatch):
    calls = []
    _fake_compile(monkeypatch, calls)
    config = _ball(tmp_path)
    (tmp_path / "afile").write_text("x")
    assert main(["render", str(config), "-o", str(tmp_path / "afile" / "ball")]) == 1
    _one_error_line(capsys, "is a file, not a folder")
    (tmp_path / "ball.png").mkdir()
    assert main(["render", str(config), "-o", str(tmp_path / "ball")]) == 1
    _one_error_line(capsys, f"{tmp_path / 'ball.png'}: is a folder")
    assert calls == [] and not (tmp_path / "ball.exr").exists()


def _no_outputs(folder):
    return sorted(p.name for p in folder.rglob("*") if p.name not in ("ball.toml", "afile"))


def test_png_failing_after_the_exr_leaves_neither(tmp_path, capsys, monkeypatch):
    import errno

    _fake_compile(monkeypatch)

    def broken_png(path, rgb, exposure=0.0):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(io, "write_png", broken_png)
    out = tmp_path / "renders" / "ball"
    assert main(["render", str(_ball(tmp_path)), "-o", str(out)]) == 1
    _one_error_line(capsys, f"{out.with_suffix('.png')}: cannot write (No space left on device)")
    assert _no_outputs(tmp_path) == []  # no EXR, no temporary file, no folder


def test_exr_failing_leaves_neither(tmp_path, capsys, monkeypatch):
    _fake_compile(monkeypatch)

    def broken_exr(path, image, channels=None):
        raise io.JaxrtIOError(f"{path}: AOV `depth` has shape (1,), expected [6, 10]")

    monkeypatch.setattr(io, "write_exr", broken_exr)
    out = tmp_path / "ball"
    assert main(["render", str(_ball(tmp_path)), "-o", str(out)]) == 1
    _one_error_line(capsys, f"{out.with_suffix('.exr')}: AOV `depth`")  # named as the target
    assert _no_outputs(tmp_path) == []


def test_rename_failing_after_the_exr_is_in_place_removes_it(tmp_path, capsys, monkeypatch):
    """The PNG's target becomes a folder while rendering: its rename fails after the
    EXR's succeeded, and the EXR is taken back."""
    _fake_compile(monkeypatch)
    out = tmp_path / "ball"
    real_png = io.write_png

    def racing_png(path, rgb, exposure=0.0):
        real_png(path, rgb, exposure)
        (tmp_path / "ball.png").mkdir()
        (tmp_path / "ball.png" / "keep").write_text("x")

    monkeypatch.setattr(io, "write_png", racing_png)
    assert main(["render", str(_ball(tmp_path)), "-o", str(out)]) == 1
    _one_error_line(capsys, f"{out.with_suffix('.png')}: cannot write")
    assert _no_outputs(tmp_path) == ["ball.png", "keep"]  # only the folder that was in the way


def test_success_replaces_old_outputs_and_leaves_no_temporaries(tmp_path, capsys, monkeypatch):
    _fake_compile(monkeypatch)
    out = tmp_path / "ball"
    out.with_suffix(".exr").write_text("old")
    assert main(["render", str(_ball(tmp_path)), "-o", str(out)]) == 0
    assert _no_outputs(tmp_path) == ["ball.exr", "ball.png"]
    assert io.read_exr(out.with_suffix(".exr"))["rgb"].shape == (8, 12, 3)


def test_second_render_reuses_the_cached_program(tmp_path, capsys, monkeypatch):
    """With the cache on, the second render of an unchanged structure reads the exported
    program back (no tracing) and gives the same image; other values, same structure."""
    import jax

    import jaxrt.cache as cache

    monkeypatch.delenv("JAXRT_NO_CACHE", raising=False)
    folder = tmp_path / "cache"
    config = _ball(tmp_path)
    scene, camera, settings = __import__("jaxrt").config.load(config)
    settings = settings.replace(backend="jax")
    first, reused = cache.compile_render_cached(scene, camera, settings, folder)
    assert not reused and len(list((folder / cache.PROGRAMS).iterdir())) == 1
    second, reused = cache.compile_render_cached(scene, camera, settings, folder)
    assert reused
    np.testing.assert_array_equal(np.asarray(first(scene, camera).rgb), np.asarray(second(scene, camera).rgb))
    import equinox as eqx

    bigger = eqx.tree_at(lambda s: s.surface.radius, scene, scene.surface.radius * 1.2)
    reference = __import__("jaxrt").render(bigger, camera, settings)
    np.testing.assert_allclose(np.asarray(second(bigger, camera).rgb), np.asarray(reference.rgb), atol=1e-6)



def test_the_program_key_follows_jaxrts_source(tmp_path, monkeypatch):
    """A program traced by other jaxrt code is not served again: the key holds a hash of
    the package's source, which an edit changes (the version number need not)."""
    import jaxrt.cache as cache

    scene, camera, settings = __import__("jaxrt").config.load(_ball(tmp_path))
    key = cache.program_key(scene, camera, settings)
    assert cache.program_key(scene, camera, settings) == key
    digest = cache.source_digest()
    assert len(digest) == 64 and digest == cache.source_digest()
    monkeypatch.setattr(cache, "source_digest", lambda: "edited")
    assert cache.program_key(scene, camera, settings) != key
