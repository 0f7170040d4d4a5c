"""Scene files: every kind of mistake gets a message naming the file, key and expectation."""

import math

import numpy as np
import pytest

import jaxrt as jr
from jaxrt.cli import showcase_path
from jaxrt.config import ConfigError, load, loads

GOOD = """
background = [0.1, 0.2, 0.3]

[camera]
type = "perspective"
eye = [0.0, 2.0, -6.0]
target = [0.0, 1.0, 0.0]
up = [0.0, 1.0, 0.0]
fov = 40.0
width = 8
height = 6

[settings]
max_steps = 32
spp = 2

[materials.red]
type = "lambert"
albedo = [0.8, 0.1, 0.1]

[materials.metal]
type = "cook_torrance"
distribution = { type = "ggx", alpha = 0.2 }

[[lights]]
type = "point"
position = [2.0, 4.0, -3.0]
intensity = [50.0, 50.0, 50.0]

[[lights]]
type = "directional"
direction = [0.0, 1.0, 0.0]
irradiance = 1.0

[surface]
type = "union"
children = [
  { type = "translate", offset = [0.0, 1.0, 0.0], child = { type = "sphere", radius = 1.0, material = "metal" } },
  { type = "plane", normal = [0.0, 1.0, 0.0], offset = 0.0, material = "red" },
]
"""


def test_good_config_builds_the_objects_it_describes():
    scene, camera, settings = loads(GOOD, "good.toml")
    assert settings.max_steps == 32 and settings.spp == 2
    assert isinstance(camera, jr.PerspectiveCamera) and (camera.width, camera.height) == (8, 6)
    assert math.isclose(float(camera.fov), 40.0)
    np.testing.assert_allclose(scene.background, [0.1, 0.2, 0.3])
    sphere, plane = scene.surface.children()
    assert float(sphere.child.radius) == 1.0 and sphere.child.material == 1
    assert plane.material == 0
    assert isinstance(scene.materials[1], jr.bsdf.CookTorrance)
    assert isinstance(scene.lights[1], jr.DirectionalLight)
    np.testing.assert_allclose(scene.lights[1].irradiance, [1.0, 1.0, 1.0])


def test_overrides_from_the_command_line():
    _, camera, settings = loads(GOOD, "good.toml", width=5, height=3, spp=7)
    assert (camera.width, camera.height, settings.spp) == (5, 3, 7)


def test_shipped_scenes_load():
    for path in [showcase_path(), "configs/scenes/warp_raymarch.toml"]:
        scene, camera, settings = load(path)
        assert len(scene.materials) >= 1


def _error(text):
    with pytest.raises(ConfigError) as e:
        loads(text, "bad.toml")
    return str(e.value)


@pytest.mark.parametrize(
    "old, new, expected",
    [
        # malformed TOML
        ("[camera]", "[camera", "bad.toml: malformed TOML"),
        # unknown keys
        ("fov = 40.0", "fov = 40.0\nzoom = 2", "bad.toml: camera.zoom = 2, expected one of the arguments"),
        ("max_steps = 32", "max_step = 32", "bad.toml: settings.max_step = 32, expected a RenderSettings field"),
        ("background =", "backgroud =", "bad.toml: backgroud = [0.1, 0.2, 0.3], expected one of the tables"),
        ("albedo = [0.8, 0.1, 0.1]", "albedo = [0.8, 0.1, 0.1]\ncolour = 1", "bad.toml: materials.red.colour = 1"),
        # wrong types
        ("radius = 1.0", 'radius = "big"', "bad.toml: surface.children[0].child.radius = 'big', expected"),
        ("width = 8", "width = 8.5", "bad.toml: camera.width = 8.5, expected an integer ≥ 1"),
        ("max_steps = 32", "max_steps = 32.0", "bad.toml: settings.max_steps = 32.0, expected an integer ≥ 1"),
        ("spp = 2", 'spp = 2\nshadows = "sharp"', "bad.toml: settings.shadows = 'sharp', expected one of"),
        ("spp = 2", "spp = 2\nsilhouette = 1", "bad.toml: settings.silhouette = 1, expected true or false"),
        # out-of-range values
        ("radius = 1.0", "radius = -1.0", "bad.toml: surface.children[0].child.radius = -1.0, expected a value > 0"),
        ("fov = 40.0", "fov = 180.0", "bad.toml: camera.fov = 180.0, expected a value in (0, 180) degrees"),
        ("spp = 2", "spp = 0", "bad.toml: settings.spp = 0, expected an integer ≥ 1"),
        ("intensity = [50.0, 50.0, 50.0]", "intensity = [50.0, -1.0, 50.0]", "bad.toml: lights[0].intensity = [50.0, -1.0, 50.0], expected a value ≥ 0"),
        ("alpha = 0.2", "alpha = 0.0", "bad.toml: materials.metal.distribution.alpha = 0.0, expected a value > 0"),
        ("offset = 0.0", "offset = nan", "bad.toml: surface.children[1].offset = nan, expected finite numbers"),
        # unknown names
        ('type = "sphere"', 'type = "sphear"', "bad.toml: surface.children[0].child.type = 'sphear', expected a shape type, one of"),
        ('type = "lambert"', 'type = "lamberd"', "bad.toml: materials.red.type = 'lamberd', expected a material type"),
        ('type = "point"', 'type = "spot"', "bad.toml: lights[0].type = 'spot', expected a light type"),
        ('type = "ggx"', 'type = "gxx"', "bad.toml: materials.metal.distribution.type = 'gxx'"),
        # material references
        ('material = "metal"', 'material = "steel"', "bad.toml: surface.children[0].child.material = 'steel', expected the name of a [materials.NAME] table"),
        ('material = "red"', "material = 5", "bad.toml: surface.children[1].material = 5, expected a material index in 0..1"),
        # missing parts
        ("[camera]\ntype", "[cam]\ntype", "bad.toml: cam = "),
    ],
)
def test_bad_configs_name_file_key_and_expectation(old, new, expected):
    assert old in GOOD
    text = GOOD.replace(old, new, 1)
    message = _error(text)
    assert message.startswith(expected), message
    assert "Traceback" not in message and "jax" not in message.lower()


def test_missing_tables_and_empty_unions():
    assert _error(GOOD.replace("[surface]\ntype = \"union\"", "[nothing]")).startswith("bad.toml: nothing =")
    no_surface = GOOD[: GOOD.index("[surface]")]
    assert "surface is missing" in _error(no_surface)
    empty = GOOD[: GOOD.index("children = [")] + "children = []\n"
    assert "surface.children = [], expected a non-empty array" in _error(empty)


def test_unreadable_file(tmp_path):
    with pytest.raises(ConfigError, match="cannot read the file"):
        load(tmp_path / "missing.toml")


HEIGHTFIELDS = """
[[heightfields]]
material = "red"
max_steps = 256
height = { type = "sine", amplitude = 0.2, frequency = [1.0, 0.5] }

[[heightfields]]
height = { type = "grid", heights = "terrain.npy", extent = [-2.0, 2.0, -1.0, 1.0] }
"""


def test_heightfields_build_the_surfaces_they_describe(tmp_path):
    heights = np.array([[0.0, 0.1, 0.2], [0.3, 0.4, 0.5]])
    np.save(tmp_path / "terrain.npy", heights)
    path = tmp_path / "scene.toml"
    path.write_text(GOOD + HEIGHTFIELDS)
    scene, camera, settings = load(path)
    sine, grid = scene.heightfields
    assert isinstance(sine.height, jr.heightfield.SineHeight) and sine.material == 0
    assert sine.max_steps == 256 and float(sine.height.amplitude) == pytest.approx(0.2)
    np.testing.assert_allclose(sine.height.frequency, [1.0, 0.5])
    np.testing.assert_allclose(grid.height.heights, heights)  # relative to the scene file
    np.testing.assert_allclose(grid.height.extent, [-2.0, 2.0, -1.0, 1.0])
    assert grid.material == 0 and grid.max_steps == 512  # HeightField's defaults


@pytest.mark.parametrize("old, new, expected", [
    ('type = "sine", amplitude = 0.2,', 'type = "sine",', "bad.toml: heightfields[0].height.amplitude is missing"),
    ('type = "sine"', 'type = "cubic"', "bad.toml: heightfields[0].height.type = 'cubic', expected a height type"),
    ('heights = "terrain.npy"', 'heights = "terrain.txt"', "bad.toml: heightfields[1].height.heights = 'terrain.txt', expected"),
    ('heights = "terrain.npy"', 'heights = "absent.npy"', "bad.toml: heightfields[1].height.heights = 'absent.npy', expected a readable .npy file"),
    ('heights = "terrain.npy"', "heights = [[1.0, 2.0]]", "bad.toml: heightfields[1].height: `GridHeight(heights=...)` must have shape"),
    ('material = "red"', 'material = "clay"', "bad.toml: heightfields[0].material = 'clay', expected the name of a [materials.NAME] table"),
    ("max_steps = 256", "max_steps = 0", "bad.toml: heightfields[0]: `HeightField(max_steps=0)`: expected an integer ≥ 1"),
    ("max_steps = 256", "steps = 256", "bad.toml: heightfields[0].steps = 256, expected one of the arguments"),
    ("max_steps = 256\nheight =", "max_steps = 256\nheigth =", "bad.toml: heightfields[0].height is missing"),
])
def test_bad_heightfields_name_file_key_and_expectation(old, new, expected):
    assert old in HEIGHTFIELDS
    message = _error(GOOD + HEIGHTFIELDS.replace(old, new, 1))
    assert message.startswith(expected), message
