"""render(): a closed-form image, finiteness at the extremes, compilation caching, and
validation of settings and scenes."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrt as jr
from jaxrt import sdf
from jaxrt.render import block_rows, block_starts, compile_render

from helpers import cluttered_scene, inside_sphere_scene

RHO = (0.2, 0.5, 0.8)
AOVS = ("rgb", "depth", "normal", "albedo", "steps", "coverage")


def _camera(kind, eye, target, size):
    if kind == "perspective":
        return jr.PerspectiveCamera(eye, target, (0.0, 1.0, 0.0), fov=120.0, width=9, height=7)
    return jr.OrthographicCamera(eye, target, (0.0, 1.0, 0.0), size=size, width=9, height=7)


@pytest.mark.parametrize("kind,shadows,spp,dtype", [
    ("perspective", "hard", 1, "float32"),
    ("perspective", "soft", 4, "float32"),
    ("orthographic", "hard", 1, "float64"),
])
def test_lambert_sphere_seen_from_inside_has_radiance_albedo(kind, shadows, spp, dtype):
    """Radiance at a point p of the sphere: ρ/π · (π / |p − c|²) · cos 0 = ρ / r²
    wherever the camera is inside, with direct lighting and shadow rays from inside."""
    settings = jr.RenderSettings(shadows=shadows, spp=spp, dtype=dtype)
    tol = 1e-3 if dtype == "float32" else 1e-9
    cases = [  # radius, centre, eye offset from the centre
        (1.0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)),
        (1.0, (0.0, 0.0, 0.0), (0.3, -0.4, 0.2)),
        (2.0, (1.0, -2.0, 3.0), (-0.5, 0.8, 0.6)),
    ]
    for radius, centre, offset in cases:
        eye = np.add(centre, offset)
        target = eye + [0.2, 0.1, 1.0]
        image = jr.render(inside_sphere_scene(RHO, radius, centre), _camera(kind, eye, target, 0.3),
                          settings)
        for name in AOVS:
            assert getattr(image, name).dtype == jnp.dtype(dtype), name
        expected = np.broadcast_to(np.divide(RHO, radius**2), image.rgb.shape)
        np.testing.assert_allclose(np.asarray(image.rgb), expected, atol=tol, rtol=0)
        np.testing.assert_array_equal(np.asarray(image.coverage), 1.0)
        np.testing.assert_allclose(np.asarray(image.albedo), np.broadcast_to(RHO, image.rgb.shape),
                                   rtol=1e-6)
        # The normal AOV faces the camera: inwards, towards the centre.
        if offset == (0.0, 0.0, 0.0) and kind == "perspective" and spp == 1:
            np.testing.assert_allclose(np.asarray(image.depth), radius, rtol=10 * tol)
            n = np.asarray(image.normal)
            np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-5)


def _finite(image):
    for name in AOVS:
        value = np.asarray(getattr(image, name))
        assert np.all(np.isfinite(value)), name
    return image


def test_extreme_rays_give_finite_images_and_aovs_with_nan_checks_on():
    """Cameras inside objects, and just above a plane looking along it (near-tangent
    rays, some of which exhaust the step budget); NaN checking on (jax_debug_nans)."""
    scene = cluttered_scene()
    settings = jr.RenderSettings(shadows="soft", over_relaxation=1.6, max_steps=48)
    cameras = {
        "outside": jr.PerspectiveCamera((0.0, 2.0, -6.0), (0.0, 1.0, 0.0), fov=50.0, width=8, height=6),
        "in_sphere": jr.PerspectiveCamera((0.0, 1.0, 0.0), (0.3, 1.2, 1.0), fov=90.0, width=8, height=6),
        "in_box": jr.PerspectiveCamera((1.8, 0.8, 0.0), (1.8, 0.8, 1.0), fov=90.0, width=8, height=6),
        "grazing": jr.PerspectiveCamera((0.0, 1e-3, -6.0), (-3.0, 1e-3, 0.0), fov=10.0, width=8, height=6),
    }
    with jax.debug_nans(True):
        images = {name: _finite(jr.render(scene, camera, settings)) for name, camera in cameras.items()}
    assert np.asarray(images["outside"].coverage).mean() > 0.3
    for name in ("in_sphere", "in_box"):  # walls all around
        np.testing.assert_array_equal(np.asarray(images[name].coverage), 1.0)
    grazing = images["grazing"]
    exhausted = np.asarray(grazing.steps) == settings.max_steps
    covered = np.asarray(grazing.coverage) == 1.0
    assert exhausted.any() and covered.any()
    # Rays that ran out of budget are misses with finite AOVs.
    np.testing.assert_array_equal(np.asarray(grazing.depth)[exhausted & ~covered], settings.max_distance)
    np.testing.assert_array_equal(np.asarray(grazing.normal)[exhausted & ~covered], 0.0)


def test_gradients_of_a_small_render_are_finite_with_nan_checks_on():
    """From inside a sphere (shadow rays from inside), with a plane seen edge-on."""
    scene = jr.Scene(
        sdf.Union(sdf.Translate(sdf.Sphere(1.0), (0.0, 1.0, 0.0)), sdf.Plane((0.0, 1.0, 0.0), 0.0)),
        [jr.bsdf.Lambert(0.6)], [jr.PointLight((0.2, 1.3, 0.1), (5.0, 5.0, 5.0))], 0.1)
    camera = jr.PerspectiveCamera((0.0, 1.0, 0.0), (0.0, 0.0, 1.0), fov=120.0, width=3, height=2)
    params, static = eqx.partition((scene, camera), eqx.is_inexact_array)

    def loss(params):
        scene, camera = eqx.combine(params, static)
        image = jr.render(scene, camera, jr.RenderSettings(shadows="soft"))
        return jnp.sum(image.rgb) + jnp.sum(image.depth)

    with jax.debug_nans(True):
        grads = jax.grad(loss)(params)
    leaves = jax.tree_util.tree_leaves(grads)
    assert all(np.all(np.isfinite(np.asarray(g))) for g in leaves)
    assert any(np.any(np.asarray(g) != 0.0) for g in leaves)


# -- compilation ---------------------------------------------------------------------

TRACES = [0]


class Counted(sdf.SDF):
    """A pass-through node that counts how often the render program is traced: its
    Python `eval` only runs while JAX traces (never when a compiled program runs)."""

    child: sdf.SDF

    def eval(self, p):
        TRACES[0] += 1
        return self.child.eval(p)

    def lipschitz(self):
        return self.child.lipschitz()

    def children(self):
        return (self.child,)


def _counted_scene(radius=1.0, albedo=0.5, light=(2.0, 3.0, -4.0), intensity=20.0,
                   background=0.1, lights=1):
    surface = sdf.Union(Counted(sdf.Sphere(radius)), sdf.Plane((0.0, 1.0, 0.0), -1.0, material=1))
    return jr.Scene(surface, [jr.bsdf.Lambert(albedo), jr.bsdf.Lambert(0.3)],
                    [jr.PointLight(light, (intensity,) * 3)] * lights, background)


def test_changing_parameter_values_never_recompiles():
    # A resolution no other test uses, so that the first render has to compile.
    camera = jr.PerspectiveCamera((0.0, 0.5, -5.0), (0.0, 0.0, 0.0), fov=40.0, width=11, height=5)
    first = jr.render(_counted_scene(), camera)
    compiled = TRACES[0]
    assert compiled > 0
    changed = [
        (_counted_scene(radius=0.7), camera),
        (_counted_scene(albedo=(0.9, 0.1, 0.4)), camera),
        (_counted_scene(light=(-1.0, 5.0, 0.0), intensity=3.0, background=0.5), camera),
        (_counted_scene(), jr.PerspectiveCamera((1.0, 1.5, -4.0), (0.0, 0.2, 0.0), fov=25.0,
                                                width=11, height=5)),
    ]
    images = [jr.render(scene, cam) for scene, cam in changed]
    assert TRACES[0] == compiled, "a change of parameter values retraced the render"
    # The new values were used.
    for image in images:
        assert not np.allclose(np.asarray(image.rgb), np.asarray(first.rgb))
    # A change of structure compiles (here: another light).
    jr.render(_counted_scene(lights=2), camera)
    assert TRACES[0] > compiled



@pytest.mark.parametrize("backend,spp", [("jax", 1), ("fused", 2)])
def test_blocks_of_rows_in_threads_are_the_one_call_image_and_compile_once(backend, spp):
    """A render outside a trace on a CPU runs blocks of rows in threads (`block_rows`):
    the same pixels as one call (each ray's program is the same), the last block
    overlapping the one before (13 rows in blocks of 5: starts 0, 5, 8), one program for
    every block and every parameter value."""
    camera = jr.PerspectiveCamera((0.0, 0.5, -5.0), (0.0, 0.0, 0.0), fov=40.0, width=9, height=13)
    settings = jr.RenderSettings(backend=backend, batch_size=16 * spp, spp=spp, shadows="soft",
                                 threads=3)
    assert block_rows(camera, settings) == 5
    assert block_starts(13, 5) == [0, 5, 8]
    one = jr.render(_counted_scene(), camera, settings.replace(threads=1))
    before = TRACES[0]
    blocks = jr.render(_counted_scene(), camera, settings)
    traced = TRACES[0]
    assert traced > before  # the block program is a program of its own
    for name in jr.Image.__dataclass_fields__:  # two programs: equal to float32 rounding
        np.testing.assert_allclose(np.asarray(getattr(blocks, name)), np.asarray(getattr(one, name)),
                                   rtol=1e-5, atol=1e-6, err_msg=name)
    moved = jr.render(_counted_scene(radius=0.8), camera, settings)
    assert TRACES[0] == traced, "a block of other rows or other values retraced the render"
    np.testing.assert_allclose(np.asarray(moved.rgb),
                               np.asarray(jr.render(_counted_scene(radius=0.8), camera,
                                                    settings.replace(threads=1)).rgb),
                               rtol=1e-5, atol=1e-6)
    # compiled ahead of time (`compile_render`, the CLI's path without its cache): the same
    compiled = compile_render(_counted_scene(), camera, settings)
    np.testing.assert_array_equal(np.asarray(compiled(_counted_scene(), camera).rgb),
                                  np.asarray(blocks.rgb))


def test_one_call_where_blocks_do_not_apply(monkeypatch):
    camera = jr.PerspectiveCamera((0.0, 0.5, -5.0), (0.0, 0.0, 0.0), fov=40.0, width=64, height=64)
    settings = jr.RenderSettings(batch_size=1024, threads=4)
    assert block_rows(camera, settings) == 16
    assert block_rows(camera, settings.replace(batch_size=2048)) == 32  # 2 tiles
    for other in ({"threads": 1}, {"devices": 2}, {"batch_size": None},
                  {"silhouette": True, "silhouette_gradient": "outline"}):
        assert block_rows(camera, settings.replace(**other)) == 64, other
    with jax.debug_nans(True):  # a context of this thread's, which threads would not see
        assert block_rows(camera, settings) == 64
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    assert block_rows(camera, settings) == 64

# -- validation ----------------------------------------------------------------------

BAD_SETTINGS = [
    ("max_steps", 0), ("max_steps", 10.0), ("max_steps", True), ("hit_epsilon", 0.0),
    ("hit_epsilon", float("nan")), ("pixel_epsilon", -1.0), ("max_distance", 0.0),
    ("over_relaxation", 2.0), ("over_relaxation", 0.9), ("newton_steps", -1),
    ("normal_mode", "sobel"), ("normal_epsilon", 0.0), ("shadows", "fuzzy"), ("shadow_steps", 0),
    ("penumbra", -8.0), ("shadow_max_distance", 0.0), ("max_depth", -1), ("max_depth", 17),
    ("ray_offset", 0.0), ("spawn_steps", -1), ("spawn_steps", 1.5), ("spp", 0), ("seed", 0.5), ("wavelengths", -1), ("dtype", "float16"),
    ("batch_size", 0), ("batch_size", "whole"), ("silhouette", 1), ("aovs", ("rgb",)), ("aovs", ("depth", "depth")),
    ("aovs", "depth"), ("threads", -1), ("threads", 2.0),
]


@pytest.mark.parametrize("field,value", BAD_SETTINGS)
def test_settings_reject_bad_values_naming_the_field(field, value):
    with pytest.raises(ValueError, match=f"RenderSettings.{field}"):
        jr.RenderSettings(**{field: value})
    with pytest.raises(ValueError, match=f"RenderSettings.{field}"):
        jr.RenderSettings().replace(**{field: value})


@pytest.mark.parametrize("backend", ["jax", "fused"])
def test_aovs_left_out_are_none_and_leave_rgb_unchanged(backend):
    scene, camera = _counted_scene(), _camera("perspective", (0.0, 0.5, -4.0), (0.0, 0.0, 0.0), 8)
    settings = jr.RenderSettings(shadows="soft", backend=backend)
    full = jr.render(scene, camera, settings)
    some = jr.render(scene, camera, settings.replace(aovs=["depth"]))  # a TOML list
    assert some.normal is None and some.albedo is None and some.steps is None
    assert some.coverage is None
    # two programs: equal to rounding (a few ulps where XLA fuses them differently; the
    # Newton polish of a ray grazing the floor 27 units away converges to within the
    # rounding of f there, which at the tests' -O0 moved its float32 t by 10 ulps)
    np.testing.assert_allclose(np.asarray(some.rgb), np.asarray(full.rgb), rtol=2e-6, atol=1e-7)
    np.testing.assert_allclose(np.asarray(some.depth), np.asarray(full.depth), rtol=2e-6)


@pytest.mark.parametrize("platform,auto", [("cpu", 4096), ("gpu", 1 << 18)])
def test_rays_per_tile_caps_batch_size_at_the_image(monkeypatch, platform, auto):
    monkeypatch.setattr(jax, "default_backend", lambda: platform)
    tile = jr.RenderSettings().rays_per_tile  # batch_size "auto", the default
    assert (tile(10**7), tile(100)) == (auto, 100)
    assert jr.RenderSettings(batch_size=None).rays_per_tile(10**7) == 10**7
    assert jr.RenderSettings(batch_size=64).rays_per_tile(10**7) == 64
    assert jr.RenderSettings(batch_size=64).rays_per_tile(10) == 10


def test_every_setting_has_a_documented_default():
    doc = jr.RenderSettings.__doc__
    for field in dataclasses.fields(jr.RenderSettings):
        assert field.name in doc, field.name
    jr.RenderSettings()  # the defaults are valid


def test_scene_rejects_bad_values_naming_the_argument():
    lambert = jr.bsdf.Lambert(0.5)
    with pytest.raises(ValueError, match="material indices \\[2\\]"):
        jr.Scene(sdf.Union(sdf.Sphere(material=0), sdf.Box(material=2)), [lambert, lambert])
    with pytest.raises(TypeError, match="Scene\\(surface"):
        jr.Scene("sphere", [lambert])
    with pytest.raises(ValueError, match="Scene\\(materials"):
        jr.Scene(sdf.Sphere(), [])
    with pytest.raises(TypeError, match="Scene\\(lights\\[0\\]"):
        jr.Scene(sdf.Sphere(), [lambert], lights=[(0.0, 1.0, 0.0)])
