"""Stable at the extremes (design promise 2): epsilons below the float's precision, scenes
modelled in tiny or huge units, dials past their sensible range.

- Every march's threshold is max(ε, rounding floor of f at the sample)
  (`jaxrt.march.sphere.threshold`): a head-on sphere covers its analytic disc for any
  hit_epsilon from 1e-3 down to 1e-10, in float32 and float64, at any scale.
- A scene scaled by s (geometry, distances, ε; point-light intensities by s²) renders the
  same image: no march constant is in world units.
- A ray out of budget is said so (steps = max_steps + 1) and a shadow ray that has not
  reached its light does not light the point.
"""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrt as jr
from jaxrt.render import _cast

N = 48  # rays per side of the head-on grid


@functools.lru_cache(maxsize=None)
def _coverage_fn(hit_epsilon, dtype):
    settings = jr.RenderSettings(hit_epsilon=hit_epsilon, max_distance=1e4, max_steps=128,
                                 newton_steps=0, dtype=dtype)

    def one(scene, o, d):
        return jr.sphere_trace(scene.surface, o, d, settings).hit

    return jax.jit(jax.vmap(one, in_axes=(None, 0, 0)))


def head_on_grid(scale, dtype):
    """Rays parallel to +z from z = −4·scale over [−1.2, 1.2]² · scale, and whether each
    passes inside the unit disc (times scale): the analytic coverage of a sphere."""
    u = (np.arange(N) + 0.5) / N * 2.4 - 1.2
    x, y = np.meshgrid(u, u)
    o = np.stack([x.ravel(), y.ravel(), np.full(N * N, -4.0)], 1) * scale
    d = np.tile([0.0, 0.0, 1.0], (N * N, 1))
    return jnp.asarray(o, dtype), jnp.asarray(d, dtype), (x**2 + y**2 < 1.0).ravel()


def coverage_error(scale, hit_epsilon, dtype):
    """Fraction of the grid's rays whose hit disagrees with the analytic disc."""
    scene = jr.Scene(surface=jr.sdf.Sphere(radius=scale), materials=[jr.bsdf.Lambert()])
    scene = _cast(scene, jnp.dtype(dtype))
    o, d, inside = head_on_grid(scale, dtype)
    hit = np.asarray(_coverage_fn(hit_epsilon * scale, dtype)(scene, o, d))
    return float(np.mean(hit != inside))


@pytest.mark.parametrize("dtype", ["float32", "float64"])
@pytest.mark.parametrize("hit_epsilon", [1e-3, 1e-8, 1e-10])
def test_head_on_sphere_coverage_below_the_floats_precision(hit_epsilon, dtype):
    """hit_epsilon relative to the scale (ε·s): 1e-8 and 1e-10 are below what float32
    resolves at the sphere (an ulp of 1 is 1.2e-7), where the march used to run out."""
    for scale in (1e-3, 1.0, 1e3):
        assert coverage_error(scale, hit_epsilon, dtype) <= 0.005, (scale, hit_epsilon, dtype)


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_absolute_epsilon_in_large_units(dtype):
    """The default ε = 1e-4 absolute on a sphere of radius 1000 seen from 4000 (the issue's
    case: a quarter of the sphere vanished in float32)."""
    scene = _cast(jr.Scene(surface=jr.sdf.Sphere(radius=1000.0), materials=[jr.bsdf.Lambert()]),
                  jnp.dtype(dtype))
    o, d, inside = head_on_grid(1000.0, dtype)
    hit = np.asarray(_coverage_fn(1e-4, dtype)(scene, o, d))
    assert np.mean(hit != inside) <= 0.005


def test_exhausted_rays_are_marked_and_shadow_rays_out_of_budget_are_not_visible():
    """A ray that runs out of steps reports steps = max_steps + 1; a shadow ray that runs
    out before its light while converging on a surface leaves the point unlit (it was
    lit: 'visible' by default), one that runs out receding from every surface lights it."""
    scene = jr.Scene(surface=jr.sdf.Translate(jr.sdf.Sphere(radius=1.0), offset=(0.0, 0.0, 10.0)),
                     materials=[jr.bsdf.Lambert()])
    settings = jr.RenderSettings(max_steps=2, newton_steps=0)
    o = jnp.zeros(3, jnp.float32)
    d = jnp.array([0.0, 0.3, 1.0], jnp.float32)
    d = d / jnp.linalg.norm(d)  # passes the sphere: sphere tracing slows down beside it
    h = jr.sphere_trace(_cast(scene, jnp.float32).surface, o, d, settings)
    assert bool(h.exhausted) and int(h.steps) == settings.max_steps + 1
    from jaxrt.lights import shadow_ray

    sdf = _cast(scene, jnp.float32).surface
    # Out of budget while still converging on the sphere (one hard step lands beside it,
    # the soft march's steps are capped at 1/16 of the ray): blocked. Out of budget once
    # past the closest approach (two hard steps: the distance grows again): visible.
    for shadows, steps, want in (("hard", 1, 0.0), ("soft", 2, 0.0), ("hard", 2, 1.0)):
        s = jr.RenderSettings(shadows=shadows, shadow_steps=steps)
        v = shadow_ray(sdf, o, d, jnp.float32(50.0), s)
        assert float(v) == want, (shadows, steps)
    for shadows in ("hard", "soft"):
        far = jr.RenderSettings(shadows=shadows, shadow_steps=256)
        assert float(shadow_ray(sdf, o, d, jnp.float32(50.0), far)) > 0.5, shadows  # it clears


def scaled_scene(s):
    """Floor and a row of spheres, one per material kind (Lambert, Cook–Torrance, Phong,
    mirror, absorbing glass), a box, and a point light of intensity ∝ s² (E = I/r² is then
    the same), everything in units of s (the glass's σ in 1/s)."""
    materials = [
        jr.bsdf.Lambert(albedo=(0.6, 0.6, 0.6)),
        jr.bsdf.Lambert(albedo=(0.7, 0.3, 0.2)),
        jr.bsdf.CookTorrance(distribution=jr.bsdf.GGX(0.3)),
        jr.bsdf.Phong(kd=(0.2, 0.5, 0.2), ks=0.3, q=20.0),
        jr.bsdf.Mirror(),
        jr.bsdf.Dielectric(1.5, absorption=(0.3 / s, 0.1 / s, 0.05 / s)),
    ]
    spheres = [jr.sdf.Translate(jr.sdf.Sphere(radius=0.45 * s, material=k + 1),
                                offset=((-2.0 + k) * s, 0.45 * s, 0.0)) for k in range(5)]
    box = jr.sdf.Translate(jr.sdf.Box(half_extents=(0.4 * s, 0.5 * s, 0.4 * s), material=0),
                           offset=(0.5 * s, 0.5 * s, -1.5 * s))
    surface = jr.sdf.Union(jr.sdf.Plane(normal=(0.0, 1.0, 0.0), offset=0.0, material=0), *spheres, box)
    return jr.Scene(surface=surface, materials=materials,
                    lights=[jr.PointLight(position=(2.0 * s, 4.0 * s, 3.0 * s),
                                          intensity=(30.0 * s * s,) * 3)],
                    background=(0.3, 0.35, 0.45))


def render_scaled(s, settings, width=40, height=24):
    camera = jr.PerspectiveCamera(eye=(0.0, 1.6 * s, 4.5 * s), target=(0.0, 0.4 * s, 0.0),
                                  fov=50.0, width=width, height=height)
    return np.asarray(jr.render(scaled_scene(s), camera, settings).rgb)


def scale_free_settings(shadows):
    """Settings with no world unit in them, so one compiled program serves every scale: ε
    below the float's precision at every scale (the rounding floor decides), a max_distance
    past anything the rays meet, only point lights (shadow rays end at the light)."""
    return jr.RenderSettings(hit_epsilon=1e-15, max_distance=1e7, shadows=shadows, max_depth=2,
                             recursion="scan", backend="jax", aovs=(), max_steps=192)


@pytest.mark.parametrize("shadows", ["soft", pytest.param("hard", marks=pytest.mark.slow)])
def test_scene_scale_does_not_change_the_image(shadows):
    """The same scene at s = 1e-3, 1, 1e3 in float32, every material kind: RMSE ≤ 0.005.
    (Before: soft shadows had a step ceiling of 2 world units, RMSE 0.037 at 10³.)"""
    settings = scale_free_settings(shadows)
    ref = render_scaled(1.0, settings)
    assert np.all(np.isfinite(ref)) and ref.std() > 0.05  # a real image
    for s in (1e-3, 1e3):
        rmse = float(np.sqrt(np.mean((render_scaled(s, settings) - ref) ** 2)))
        assert rmse <= 0.005, (shadows, s, rmse)


def field_scene(s):
    """A Cook–Torrance sphere over a sine height field (amplitude, wavelength and the
    march's min_step in units of s), a point light of intensity ∝ s²."""
    field = jr.HeightField(jr.heightfield.SineHeight(0.15 * s, frequency=(2.0 / s, 1.3 / s),
                                                     phase=(0.3, 0.2), offset=-0.6 * s),
                           material=1, min_step=0.01 * s)
    surface = jr.sdf.Translate(jr.sdf.Sphere(radius=0.7 * s, material=0), offset=(0.2 * s, 0.1 * s, 0.0))
    return jr.Scene(surface=surface,
                    materials=[jr.bsdf.CookTorrance(distribution=jr.bsdf.GGX(0.3)),
                               jr.bsdf.Lambert(albedo=(0.5, 0.6, 0.4))],
                    lights=[jr.PointLight(position=(1.5 * s, 3.0 * s, -2.0 * s),
                                          intensity=(25.0 * s * s,) * 3)],
                    background=(0.2, 0.25, 0.35), heightfields=[field])


def field_camera(s, width=32, height=20):
    return jr.PerspectiveCamera(eye=(0.0, 0.9 * s, -3.2 * s), target=(0.0, -0.1 * s, 0.0),
                                fov=50.0, width=width, height=height)


@pytest.mark.parametrize("shadows", ["soft", pytest.param("hard", marks=pytest.mark.slow)])
def test_height_fields_and_silhouettes_do_not_change_with_scale(shadows):
    """Issue 14: a sphere over a height field, with the silhouette-aware coverage on, at
    s = 1e-3, 1, 1e3 in float32: the same image (RMSE ≤ 0.005, the background seen past
    the sphere's outline and the field's ridges included), and the gradients of the
    image's mean with respect to the sphere's radius and the field's amplitude scale as
    1/s (the silhouette term carries the radius's gradient along the outline): within
    0.2 % in float32 (measured 1e-4)."""
    settings = scale_free_settings(shadows).replace(silhouette=True, max_depth=0)

    def mean_and_grads(s):
        scene, camera = field_scene(s), field_camera(s)

        def mean(sc):
            rgb = jr.render(sc, camera, settings).rgb
            return jnp.mean(rgb), rgb

        (_, image), grads = eqx.filter_value_and_grad(mean, has_aux=True)(scene)
        g = (grads.surface.child.radius, grads.heightfields[0].height.amplitude)
        return np.asarray(image), np.array([float(x) for x in g]) * s

    ref, g_ref = mean_and_grads(1.0)
    assert np.all(np.isfinite(ref)) and ref.std() > 0.05 and np.all(np.abs(g_ref) > 1e-3), g_ref
    for s in (1e-3, 1e3):
        image, g = mean_and_grads(s)
        rmse = float(np.sqrt(np.mean((image - ref) ** 2)))
        assert rmse <= 0.005, (shadows, s, rmse)
        np.testing.assert_allclose(g, g_ref, rtol=2e-3, err_msg=f"{shadows}, s = {s}")


def test_forward_and_reverse_gradients_of_soft_shadows_are_finite_and_agree():
    """A sphere in a point light's soft shadows, float32, jvp and grad of its image with
    respect to the radius: finite at every pixel, and the jvp's mean equals the grad of
    the mean. (Secondary rays start `spawn_offset` off the surface, ∝ max|pᵢ|; the
    derivative of `jnp.max` divides by the count of components equal to the maximum, and
    with p computed twice by XLA that was 0/0 on the shadow terminator: a NaN tangent in
    forward mode, and NaN gradients in reverse mode at XLA:CPU -O0.)"""
    scene = jr.Scene(surface=jr.sdf.Translate(jr.sdf.Sphere(radius=0.7, material=0),
                                              offset=(0.2, 0.1, 0.0)),
                     materials=[jr.bsdf.Lambert(albedo=(0.5, 0.6, 0.4))],
                     lights=[jr.PointLight(position=(1.5, 3.0, -2.0), intensity=(25.0,) * 3)],
                     background=(0.2, 0.25, 0.35))
    camera = field_camera(1.0, width=8, height=6)
    settings = jr.RenderSettings(hit_epsilon=1e-15, max_distance=1e7, shadows="soft",
                                 max_depth=0, backend="jax", aovs=(), max_steps=192)

    def image(radius):
        sc = eqx.tree_at(lambda s: s.surface.child.radius, scene, radius)
        return jr.render(sc, camera, settings).rgb

    def compiled(fn, r, options):
        return jax.jit(fn).lower(r).compile(compiler_options=options)(r)

    radius = scene.surface.child.radius
    for level in (0, 3):  # LLVM -O0 rounds differently; -O3: XLA's default
        options = {"xla_backend_optimization_level": level}
        _, tangent = compiled(lambda r: jax.jvp(image, (r,), (jnp.ones_like(r),)), radius, options)
        grad = compiled(jax.grad(lambda r: jnp.mean(image(r))), radius, options)
        assert np.all(np.isfinite(np.asarray(tangent))) and np.isfinite(float(grad)), level
        assert abs(float(grad)) > 1e-3
        np.testing.assert_allclose(float(jnp.mean(tangent)), float(grad), rtol=1e-4, err_msg=str(level))


# --------------------------------------------------------------------------- dial sweep

#: Values past every dial's sensible range that must be refused at construction.
REFUSED = [
    ("max_steps", 0), ("hit_epsilon", 0.0), ("hit_epsilon", -1e-4), ("hit_epsilon", float("inf")),
    ("hit_epsilon", float("nan")), ("pixel_epsilon", -1.0), ("max_distance", 0.0),
    ("max_distance", float("inf")), ("over_relaxation", 2.0), ("over_relaxation", 0.5),
    ("newton_steps", -1), ("normal_epsilon", 0.0), ("shadow_steps", 0), ("penumbra", 0.0),
    ("penumbra", float("inf")), ("shadow_max_distance", -1.0), ("max_depth", 17),
    ("ray_offset", 1.0), ("ray_offset", 0.5), ("spawn_steps", -1), ("spp", 0), ("seed", 1.5),
    ("wavelengths", -1), ("dtype", "float16"), ("batch_size", 0), ("devices", -1),
    ("silhouette_width", 0.0), ("silhouette_width", 17.0), ("max_steps", 1.5),
    ("penumbra_refine_steps", -1), ("penumbra_refine_steps", 1.5),
]


@pytest.mark.parametrize("field,value", REFUSED)
def test_dials_past_their_range_are_refused_by_name(field, value):
    with pytest.raises(ValueError, match=rf"RenderSettings\.{field} = "):
        jr.RenderSettings(**{field: value})


def _ball_and_floor():
    scene = jr.Scene(
        surface=jr.sdf.Union(jr.sdf.Plane(normal=(0.0, 1.0, 0.0), offset=-1.0, material=0),
                             jr.sdf.Sphere(radius=1.0, material=1)),
        materials=[jr.bsdf.Lambert(), jr.bsdf.CookTorrance(distribution=jr.bsdf.GGX(0.2))],
        lights=[jr.PointLight(position=(2.0, 4.0, -3.0), intensity=(40.0,) * 3)])
    camera = jr.PerspectiveCamera(eye=(0.0, 0.5, -4.0), target=(0.0, 0.0, 0.0), fov=50.0,
                                  width=12, height=8)
    return scene, camera


#: Accepted extremes: each renders finite values and (but for budgets) the same hits as the
#: defaults. The first few run by default, the rest are slow.
ACCEPTED = [
    dict(hit_epsilon=1e-30), dict(max_distance=1e30), dict(normal_mode="central", normal_epsilon=1e-12),
    dict(hit_epsilon=1e-30, dtype="float64"),
    dict(max_steps=1), dict(newton_steps=0), dict(newton_steps=8), dict(over_relaxation=1.99),
    dict(penumbra=1e6, shadows="soft"), dict(penumbra=1e-6, shadows="soft"), dict(ray_offset=1.0001),
    dict(spawn_steps=8), dict(shadow_steps=1), dict(max_depth=0), dict(pixel_epsilon=1e3),
    dict(silhouette=True, silhouette_width=16.0), dict(shadow_max_distance=1e-6),
]


@pytest.mark.parametrize("dials", [d if i < 3 else pytest.param(d, marks=pytest.mark.slow)
                                   for i, d in enumerate(ACCEPTED)], ids=str)
def test_accepted_extremes_render_finite_images_without_dropped_hits(dials):
    scene, camera = _ball_and_floor()
    base = jr.RenderSettings(backend="jax", aovs=("coverage",))
    image = jr.render(scene, camera, base.replace(**dials))
    assert np.all(np.isfinite(np.asarray(image.rgb)))
    budget = {"max_steps", "pixel_epsilon", "shadow_max_distance"} & set(dials)
    if not budget:  # an accuracy dial may not lose a hit that the defaults find
        ref = jr.render(scene, camera, base)
        got, want = np.asarray(image.coverage) > 0, np.asarray(ref.coverage) > 0
        if dials.get("silhouette"):  # the outline band adds partial coverage beside outlines
            assert np.all(got[want]), dials
        else:
            assert np.array_equal(got, want), dials


# --------------------------------------------------------------------------- analytic planes


@pytest.mark.parametrize("analytic", [True, False])
def test_a_floor_reaches_the_horizon(analytic):
    """Every camera ray that points below the horizon meets the floor y = 0 at the
    analytic t = −o_y / d_y when planes are intersected analytically (the default), even
    far past max_distance; sphere-traced only, the floor ends at max_distance."""
    scene = jr.Scene(surface=jr.sdf.Union(jr.sdf.Plane(normal=(0.0, 1.0, 0.0), offset=0.0),
                                          jr.sdf.Translate(jr.sdf.Sphere(radius=0.5), offset=(0.0, 0.5, 0.0))),
                     materials=[jr.bsdf.Lambert()], lights=[jr.DirectionalLight()])
    camera = jr.PerspectiveCamera(eye=(0.0, 1.0, -4.0), target=(0.0, 1.0, 0.0), fov=40.0,
                                  width=16, height=12)
    settings = jr.RenderSettings(max_distance=10.0, analytic_planes=analytic, backend="jax",
                                 aovs=("depth", "coverage"))
    image = jr.render(scene, camera, settings)
    o, d, _ = jax.vmap(jax.vmap(camera.generate_ray))(*jnp.meshgrid(jnp.arange(16) + 0.5,
                                                                       jnp.arange(12) + 0.5))
    below = np.asarray(d[..., 1]) < 0
    covered = np.asarray(image.coverage) > 0
    assert np.all(np.isfinite(np.asarray(image.rgb)))
    if analytic:
        assert np.array_equal(covered, below)
        t_floor = -np.asarray(o[..., 1]) / np.asarray(d[..., 1])
        far = below & (t_floor > 10.0) & (np.asarray(image.depth) > 5.0)  # not the sphere
        assert far.sum() >= 8  # the test sees the floor beyond max_distance
        np.testing.assert_allclose(np.asarray(image.depth)[far], t_floor[far], rtol=1e-4)
    else:
        assert covered.sum() < below.sum()
