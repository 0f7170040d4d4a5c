"""Whitted recursion (jaxrt/integrator.py): against an independent analytic ray tracer,
the static shape of the ray tree in the traced program, radiance conservation in a
white furnace, finiteness at every depth, spectral vs RGB, and height fields in scenes.
"""

import functools

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrt as jr
from jaxrt import integrator, spectral
from jaxrt.camera import pixel_samples
from jaxrt.heightfield import HeightField, PlaneHeight
from jaxrt.render import _cast

ETA = 1.5

# ----------------------------------------------------------- an analytic Whitted tracer


FLOOR = (0.8, 0.7, 0.6)
MIRROR = (0.9, 0.8, 0.5)
SPHERES = [  # centre, radius, material
    (np.array([-0.9, 0.7, 0.0]), 0.7, "mirror"),
    (np.array([0.8, 0.6, 0.3]), 0.6, "glass"),
]
LIGHT = (np.array([2.0, 5.0, -3.0]), np.array([40.0, 40.0, 40.0]))
BACKGROUND = np.array([0.2, 0.3, 0.5])


def whitted_scene():
    spheres = [jr.sdf.Translate(jr.sdf.Sphere(radius=r, material=1 + k), offset=tuple(c))
               for k, (c, r, _) in enumerate(SPHERES)]
    return jr.Scene(
        surface=jr.sdf.Union(jr.sdf.Plane(normal=(0.0, 1.0, 0.0), offset=0.0, material=0), *spheres),
        materials=[jr.bsdf.Lambert(FLOOR), jr.bsdf.Mirror(MIRROR), jr.bsdf.Dielectric(ETA)],
        lights=[jr.PointLight(tuple(LIGHT[0]), tuple(LIGHT[1]))],
        background=tuple(BACKGROUND),
    )


CAMERA = jr.PerspectiveCamera(eye=(0.0, 1.5, -5.0), target=(0.0, 0.6, 0.0), fov=40.0, width=24, height=18)


MAX_DISTANCE = jr.RenderSettings().max_distance  # rays that travel this far miss


def _nearest(o, d):
    """(t, kind, centre/None, radius) of the nearest hit with 1e-9 < t < MAX_DISTANCE."""
    best = (MAX_DISTANCE, None, None, None)
    if d[1] != 0.0:
        t = -o[1] / d[1]
        if 1e-9 < t < best[0]:
            best = (t, "floor", None, None)
    for c, r, kind in SPHERES:
        oc = o - c
        b, cc = oc @ d, oc @ oc - r * r
        disc = b * b - cc
        if disc < 0:
            continue
        for t in (-b - np.sqrt(disc), -b + np.sqrt(disc)):
            if 1e-9 < t < best[0]:
                best = (t, kind, c, r)
                break
    return best


def _fresnel(cos_i, n1, n2):
    sin_t = n1 / n2 * np.sqrt(max(0.0, 1.0 - cos_i**2))
    if sin_t >= 1.0:
        return 1.0, 0.0
    cos_t = np.sqrt(1.0 - sin_t**2)
    rs = (n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t)
    rp = (n2 * cos_i - n1 * cos_t) / (n2 * cos_i + n1 * cos_t)
    return 0.5 * (rs**2 + rp**2), cos_t


def reference_radiance(o, d, depth):
    """The notes' trace(): direct light + c_refl·trace(reflected) + c_trans·trace(refracted)."""
    t, kind, c, r = _nearest(o, d)
    if kind is None:
        return BACKGROUND.copy()
    p = o + t * d
    n_out = np.array([0.0, 1.0, 0.0]) if kind == "floor" else (p - c) / r
    entering = n_out @ d < 0
    n = n_out if entering else -n_out
    if kind == "floor":
        to_light = LIGHT[0] - p
        dist = np.linalg.norm(to_light)
        wi = to_light / dist
        cos = n @ wi
        if cos <= 0 or _nearest(p + 1e-7 * n, wi)[0] < dist:
            return np.zeros(3)
        return np.array(FLOOR) / np.pi * LIGHT[1] / dist**2 * cos
    if depth == 0:
        return np.zeros(3)
    wo = -d
    reflected = 2 * (n @ wo) * n - wo
    if kind == "mirror":
        return np.array(MIRROR) * reference_radiance(p + 1e-7 * n, reflected, depth - 1)
    n1, n2 = (1.0, ETA) if entering else (ETA, 1.0)
    cos_i = n @ wo
    f, cos_t = _fresnel(cos_i, n1, n2)
    out = f * reference_radiance(p + 1e-7 * n, reflected, depth - 1)
    if f < 1.0:
        eta_r = n1 / n2  # the notes' vector form of Snell's law
        refracted = -eta_r * wo + (eta_r * cos_i - cos_t) * n
        out = out + (1.0 - f) / (n2 / n1) ** 2 * reference_radiance(p - 1e-7 * n, refracted, depth - 1)
    return out


def camera_rays(camera, dtype=jnp.float64):
    """(origins, directions, cones) of the pixel centres, as `render` makes them."""
    samples = pixel_samples(camera, 1, 0).astype(dtype)
    return jax.vmap(_cast(camera, dtype).generate_ray)(samples[:, 0], samples[:, 1])


# A budget that lets sphere tracing converge on the floor up to the horizon (a ray at
# slope s needs ~ln(f0/ε)/s steps), so that the tracer's misses are true misses.
SETTINGS64 = jr.RenderSettings(dtype="float64", max_steps=1024)


@functools.lru_cache(maxsize=None)
def whitted_levels():
    """Per-level radiance of every pixel [H·W, 4, 3] at max_depth 3 (one program, the
    levels unrolled; `test_scan_and_unrolled_recursion_agree` holds the scan to it)."""
    scene = whitted_scene()
    o, d, cone = camera_rays(CAMERA)
    settings = SETTINGS64.replace(max_depth=3, recursion="unrolled")
    levels = jax.jit(jax.vmap(lambda o, d, c: integrator.trace_levels(scene, o, d, c, settings)[0]))
    return np.asarray(levels(o, d, cone)), np.asarray(o), np.asarray(d)


def test_depth_zero_is_direct_lighting_only():
    image = jr.render(whitted_scene(), CAMERA, SETTINGS64.replace(max_depth=0))
    levels, origins, directions = whitted_levels()
    rgb = np.asarray(image.rgb).reshape(-1, 3)
    expected = np.stack([reference_radiance(o, d, 0) for o, d in zip(origins, directions)])
    err = np.abs(rgb - expected).max(axis=1)
    # Mirror and glass pixels are black at depth 0: they have no direct term.
    assert np.mean(err < 1e-4) > 0.98, np.sort(err)[-10:]
    # render(max_depth=0) is the first level of any deeper tree.
    np.testing.assert_allclose(levels[:, 0], rgb, atol=1e-12)


@pytest.mark.parametrize("depth", [1, 2, 3])
def test_recursion_matches_analytic_whitted(depth):
    levels, origins, directions = whitted_levels()
    rgb = levels[:, : depth + 1].sum(axis=1)
    expected = np.stack([reference_radiance(o, d, depth) for o, d in zip(origins, directions)])
    err = np.abs(rgb - expected).max(axis=1)
    specular_pixels = np.abs(levels[:, 1:]).sum(axis=(1, 2)) > 0
    assert specular_pixels.sum() > 40
    # Pixels whose ray tree passes within ε of an outline or a shadow edge may differ.
    assert np.mean(err < 1e-3) > 0.97, np.sort(err)[-10:]
    assert np.median(err[specular_pixels]) < 1e-4


# ----------------------------------------------------------------- the static ray tree


def while_loops(fn, *args):
    """Batch shapes of every `while` in the traced program: one per marched ray batch
    (the leading carry is the ray parameter t, or the march's phase; its shape is the
    batch). The fixed-count loops of `jaxrt.march.search.repeat` (Newton polish, origin
    settling: the cond is `i < n` on the leading carry i, for a literal n) are not
    marches and are skipped."""
    shapes = []

    def is_repeat(eqn):
        cond = eqn.params["cond_jaxpr"].jaxpr
        return (len(cond.eqns) == 1 and cond.eqns[0].primitive.name == "lt"
                and cond.eqns[0].invars[0] is cond.invars[eqn.params["cond_nconsts"]]
                and isinstance(cond.eqns[0].invars[1], jax.extend.core.Literal))

    def visit(jaxpr):
        for eqn in jaxpr.eqns:
            if eqn.primitive.name == "while" and not is_repeat(eqn):
                n_carry = len(eqn.params["body_jaxpr"].jaxpr.outvars)
                shapes.append(tuple(eqn.invars[-n_carry].aval.shape))
            for param in eqn.params.values():
                for sub in param if isinstance(param, (tuple, list)) else (param,):
                    inner = getattr(sub, "jaxpr", sub)
                    if hasattr(inner, "eqns"):
                        visit(inner)

    visit(jax.make_jaxpr(fn)(*args).jaxpr)
    return shapes


def one_ray_program(scene, settings):
    o, d, cone = jnp.array([0.0, 1.0, -5.0]), jnp.array([0.0, 0.0, 1.0]), jnp.zeros(2)
    return while_loops(lambda o, d, c: integrator.trace_radiance(scene, o, d, c, settings)["rgb"], o, d, cone)


def scene_with(material, lights=1):
    return jr.Scene(
        surface=jr.sdf.Union(jr.sdf.Sphere(radius=1.0, material=0),
                             jr.sdf.Plane(normal=(0.0, 1.0, 0.0), offset=-1.0, material=1)),
        materials=[material, jr.bsdf.Lambert(0.5)],
        lights=[jr.PointLight((1.0, 4.0, -2.0), (10.0, 10.0, 10.0))] * lights,
    )


def test_diffuse_scene_traces_no_secondary_rays_whatever_max_depth():
    scene = scene_with(jr.bsdf.Lambert(0.8), lights=2)
    for depth in (0, 1, 5):
        # One camera ray and one shadow march for the two point lights (a scan over the
        # lights of one kind, `direct_lighting`): max_depth is ignored.
        assert one_ray_program(scene, jr.RenderSettings(max_depth=depth)) == [(1,)] * 2


def test_mirror_scene_traces_one_ray_per_level():
    scene = scene_with(jr.bsdf.Mirror(), lights=1)
    loops = one_ray_program(scene, jr.RenderSettings(max_depth=3, recursion="unrolled"))
    assert loops == [(1,), (1,)] * 4  # per level: the ray and its shadow ray


def test_glass_scene_traces_both_branches():
    scene = scene_with(jr.bsdf.Dielectric(ETA), lights=1)
    unrolled = jr.RenderSettings(max_depth=3, recursion="unrolled")
    loops = one_ray_program(scene, unrolled)
    assert loops == [(1,), (1,), (2,), (2,), (4,), (4,), (8,), (8,)]
    # Without lights (shadows) only the rays: 1 + 2 + 4 + 8.
    dark = jr.Scene(surface=scene.surface, materials=scene.materials)
    assert one_ray_program(dark, unrolled) == [(1,), (2,), (4,), (8,)]
    # The notes' opaque Whitted material reflects only: no refraction rays.
    opaque = scene_with(jr.bsdf.Whitted(base=jr.bsdf.Lambert(0.5), c_refl=0.5), lights=1)
    assert one_ray_program(opaque, unrolled.replace(max_depth=2)) == [(1,), (1,)] * 3


def test_scan_recursion_compiles_one_shading_step_whatever_the_depth():
    scene = scene_with(jr.bsdf.Dielectric(ETA), lights=1)
    for depth in (1, 3, 8):
        settings = jr.RenderSettings(max_depth=depth, recursion="scan")
        # One ray and one shadow ray, inside one scan over the 2^(depth+1) − 1 slots.
        assert one_ray_program(scene, settings) == [(), ()]
    diffuse = scene_with(jr.bsdf.Lambert(0.8), lights=1)
    assert one_ray_program(diffuse, jr.RenderSettings(max_depth=8, recursion="scan")) == [(1,), (1,)]


def test_auto_recursion_is_the_scan_on_a_cpu_and_unrolled_on_a_gpu():
    scene = scene_with(jr.bsdf.Dielectric(ETA), lights=1)
    settings = jr.RenderSettings(max_depth=3)
    assert settings.recursion == "auto"
    form = "unrolled" if jax.default_backend() == "gpu" else "scan"
    assert settings.ray_tree_form() == form
    same = settings.replace(recursion=form)
    assert one_ray_program(scene, settings) == one_ray_program(scene, same)
    assert jr.RenderSettings(recursion="unrolled").ray_tree_form() == "unrolled"


def test_scan_and_unrolled_recursion_agree():
    scene = whitted_scene()
    o, d, cone = camera_rays(CAMERA)
    settings = SETTINGS64.replace(max_depth=3, recursion="scan")
    levels = jax.jit(jax.vmap(lambda o, d, c: integrator.trace_levels(scene, o, d, c, settings)))
    scan_levels, scan_aovs = levels(o, d, cone)
    unrolled, _, _ = whitted_levels()
    np.testing.assert_allclose(np.asarray(scan_levels), unrolled, atol=1e-12)
    image = jr.render(scene, CAMERA, SETTINGS64.replace(max_depth=0))
    np.testing.assert_allclose(np.asarray(scan_aovs["depth"]), np.asarray(image.depth).ravel(), atol=1e-12)


def test_slot_writes_have_the_derivatives_of_an_update():
    """`integrator._write_slots` (its tangent an addition, so that the transpose updates
    the cotangent in place) differentiates as `dynamic_update_slice` wherever the slots
    written hold zeros, forwards and backwards; integer buffers take the plain update."""
    rng = np.random.default_rng(0)
    buffer = jnp.zeros((7, 3)).at[:2].set(rng.normal(size=(2, 3)))
    x, d_buffer, d_x = (jnp.asarray(rng.normal(size=s)) for s in [(2, 3), (7, 3), (2, 3)])
    d_buffer = d_buffer.at[3:5].set(0.0)
    plain = functools.partial(jax.lax.dynamic_update_slice_in_dim, axis=0)
    write = functools.partial(integrator._write_slots, axis=0)
    for f in (plain, write):
        out, tangent = jax.jvp(lambda b, v: f(b, v, 3), (buffer, x), (d_buffer, d_x))
        np.testing.assert_array_equal(out, buffer.at[3:5].set(x))
        np.testing.assert_array_equal(tangent, d_buffer.at[3:5].set(d_x))
    cotangent = jnp.asarray(rng.normal(size=(7, 3)))
    for f in (plain, write):
        _, pullback = jax.vjp(lambda v: f(buffer, v, 3), x)
        np.testing.assert_array_equal(pullback(cotangent)[0], cotangent[3:5])
    flags = jnp.zeros(7, bool)
    assert integrator._write_slots(flags, jnp.ones(2, bool), 3, 0).tolist() == [0, 0, 0, 1, 1, 0, 0]


def test_scan_and_unrolled_recursion_have_the_same_gradients():
    """The scan's gradient (its slot buffer written by `_write_slots`) equals that of the
    unrolled levels, through the mirror and the glass ball, for every float of the scene."""
    import equinox as eqx

    o, d, cone = camera_rays(CAMERA)
    params, static = eqx.partition(whitted_scene(), eqx.is_inexact_array)
    weights = jnp.asarray(np.random.default_rng(1).uniform(size=(o.shape[0], 3, 3)))

    def gradient(recursion):
        settings = SETTINGS64.replace(max_depth=2, recursion=recursion, shadows="hard")

        def loss(p):
            scene = eqx.combine(p, static)
            levels = jax.vmap(lambda o, d, c: integrator.trace_levels(scene, o, d, c, settings)[0])
            return jnp.sum(weights * levels(o, d, cone))

        return jax.jit(jax.grad(loss))(params)

    scan, unrolled = gradient("scan"), gradient("unrolled")
    for a, b in zip(jax.tree_util.tree_leaves(scan), jax.tree_util.tree_leaves(unrolled)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-9, atol=1e-12)
    assert max(float(np.max(np.abs(x))) for x in jax.tree_util.tree_leaves(scan)) > 1e-3


def test_only_dispersive_scenes_trace_wavelengths():
    glass = scene_with(jr.bsdf.Dielectric(ETA), lights=0)
    prism = scene_with(jr.bsdf.Dielectric(spectral.BK7), lights=0)
    settings = jr.RenderSettings(max_depth=1, wavelengths=8, recursion="unrolled")
    assert one_ray_program(glass, settings) == [(1,), (2,)]           # RGB, 8 ignored
    # 8 wavelengths from the first bounce on; the camera ray does not depend on the
    # wavelength, so it is traced once.
    assert one_ray_program(prism, settings) == [(1,), (8, 2)]
    assert integrator.ray_tree(prism, settings.replace(wavelengths=0)).wavelengths == 0


# --------------------------------------------------- furnace and finiteness at all depths


def furnace(eta=ETA, radius=1.0):
    """A clear glass sphere under a uniform white sky: radiance is conserved, so every
    camera ray sees 1 in the limit of infinite depth."""
    return jr.Scene(surface=jr.sdf.Sphere(radius=radius, material=0),
                    materials=[jr.bsdf.Dielectric(eta)], background=(1.0, 1.0, 1.0))


def special_rays():
    """Rays from outside (grid, tangent), from inside the glass, and at the critical angle."""
    critical = np.arcsin(1.0 / ETA)
    origins, directions = [], []
    for x in np.linspace(-1.1, 1.1, 23):
        origins.append([x, 0.3, -3.0])
        directions.append([0.0, 0.0, 1.0])
    for x in (1.0, 1.0 - 1e-9, 1.0 - 1e-6, 1.0 - 1e-4):   # tangent, and grazing
        origins.append([x, 0.0, -3.0])
        directions.append([0.0, 0.0, 1.0])
    rng = np.random.default_rng(3)
    for _ in range(12):                        # inside the glass, random directions
        origins.append(rng.uniform(-0.5, 0.5, 3))
        directions.append(rng.normal(size=3))
    for angle in critical + np.array([-1e-7, 0.0, 1e-7]):
        # From inside, hitting (0, 0, 1) at incidence `angle`: start at the chord's middle.
        direction = np.array([np.sin(angle), 0.0, np.cos(angle)])
        origins.append(np.array([0.0, 0.0, 1.0]) - np.cos(angle) * direction)
        directions.append(direction)
    d = np.asarray(directions, float)
    return jnp.asarray(origins, float), jnp.asarray(d / np.linalg.norm(d, axis=1, keepdims=True))


def test_every_depth_is_finite_and_conserves_radiance():
    origins, directions = special_rays()
    # (The scan recursion: the same tree as the unrolled levels, compiled once.)
    settings = jr.RenderSettings(dtype="float64", shadows="none", max_depth=8, recursion="scan")
    scene = furnace()
    levels = jax.jit(jax.vmap(lambda o, d: integrator.trace_levels(scene, o, d, jnp.zeros(2), settings)[0]))
    lv = np.asarray(levels(origins, directions))  # [rays, 9, 3]: depth d = sum of levels 0..d
    assert np.all(np.isfinite(lv)) and np.all(lv >= 0.0)
    partial = np.cumsum(lv, axis=1)
    outside = np.arange(len(lv)) < 27
    assert np.all(partial[outside] <= 1.0 + 1e-9)           # never more than the furnace
    # Inside the glass the sky's radiance is η² larger (radiance scales with n²);
    # rays beyond the critical angle stay trapped in the sphere and see nothing.
    assert np.all(partial[~outside] <= ETA**2 + 1e-9)
    # Outside rays through the middle of the sphere (F small): the missing energy after
    # depth 8 is (1 − F)·F⁷ < 1e-9.
    middle = np.abs(np.asarray(origins)[:23, 0]) < 0.7
    np.testing.assert_allclose(partial[:23][middle, -1], 1.0, atol=1e-6)
    # And rays that miss see the sky at every depth.
    missing = np.abs(np.asarray(origins)[:23, 0]) > 1.0
    np.testing.assert_allclose(partial[:23][missing], 1.0, atol=1e-12)


def test_gradients_are_finite_grazing_inside_and_at_the_critical_angle():
    origins, directions = special_rays()
    settings = jr.RenderSettings(dtype="float64", shadows="none", max_depth=2)

    def rgb(params, o, d):
        scene = jr.Scene(surface=jr.sdf.Sphere(radius=params[0], material=0),
                         materials=[jr.bsdf.Dielectric(params[1], absorption=params[2])],
                         background=(1.0, 0.8, 0.6))
        return integrator.trace_radiance(scene, o, d, jnp.zeros(2), settings)["rgb"]

    grad = jax.jit(jax.vmap(jax.jacfwd(rgb), in_axes=(None, 0, 0)))
    g = np.asarray(grad(jnp.array([1.0, ETA, 0.3]), origins, directions))
    assert np.all(np.isfinite(g))


# --------------------------------------------------------------------- spectral vs RGB


def grey_scene(glass):
    return jr.Scene(
        surface=jr.sdf.Union(jr.sdf.Translate(jr.sdf.Sphere(radius=0.8, material=0), offset=(0.0, 0.8, 0.0)),
                             jr.sdf.Plane(normal=(0.0, 1.0, 0.0), offset=0.0, material=1),
                             jr.sdf.Translate(jr.sdf.Sphere(radius=0.5, material=2), offset=(1.3, 0.5, 0.6))),
        materials=[jr.bsdf.Dielectric(glass), jr.bsdf.Lambert(0.6), jr.bsdf.Mirror(0.9)],
        lights=[jr.PointLight((2.0, 4.0, -3.0), (30.0, 30.0, 30.0))],
        background=(0.5, 0.5, 0.5),
    )


def test_white_scene_renders_the_same_in_spectral_and_rgb():
    camera = jr.PerspectiveCamera(eye=(0.0, 1.5, -4.5), target=(0.3, 0.6, 0.0), fov=40.0, width=12, height=9)
    settings = jr.RenderSettings(max_depth=1, wavelengths=8, shadows="none")
    rgb = jr.render(grey_scene(1.5), camera, settings).rgb
    # A "dispersive" index with zero dispersion takes the spectral path of render().
    flat = jr.render(grey_scene(spectral.Cauchy(1.5, 0.0)), camera, settings).rgb
    assert integrator.ray_tree(grey_scene(spectral.Cauchy(1.5, 0.0)), settings).wavelengths == 8
    assert float(jnp.max(rgb)) > 0.1
    np.testing.assert_allclose(np.asarray(flat), np.asarray(rgb), atol=1e-2)


# ---------------------------------------------------------------------- height fields


def test_heightfield_in_a_scene_matches_the_sdf_plane():
    sphere = jr.sdf.Translate(jr.sdf.Sphere(radius=0.7, material=0), offset=(0.0, 0.5, 0.0))
    materials = [jr.bsdf.Mirror(0.9), jr.bsdf.Lambert((0.6, 0.5, 0.4))]
    lights = [jr.PointLight((1.0, 4.0, -2.0), (20.0, 20.0, 20.0))]
    camera = jr.PerspectiveCamera(eye=(0.0, 1.5, -4.0), target=(0.0, 0.3, 0.0), fov=45.0, width=16, height=12)
    settings = SETTINGS64.replace(max_depth=1)
    plane = jr.Scene(surface=jr.sdf.Union(sphere, jr.sdf.Plane(normal=(0.0, 1.0, 0.0), offset=0.0, material=1)),
                     materials=materials, lights=lights, background=(0.3, 0.4, 0.5))
    field = jr.Scene(surface=sphere, materials=materials, lights=lights, background=(0.3, 0.4, 0.5),
                     heightfields=[HeightField(PlaneHeight(offset=0.0), material=1)])
    a, b = jr.render(plane, camera, settings), jr.render(field, camera, settings)
    # The sphere dips below the height field (nearest hit wins), reflects it, and
    # shadows it.
    hit = np.asarray(a.coverage) > 0
    np.testing.assert_allclose(np.asarray(b.coverage), np.asarray(a.coverage))
    np.testing.assert_allclose(np.asarray(b.depth)[hit], np.asarray(a.depth)[hit], atol=1e-6)
    err = np.abs(np.asarray(b.rgb) - np.asarray(a.rgb)).max(axis=-1)
    assert np.mean(err < 1e-4) > 0.97, np.sort(err.ravel())[-5:]


@pytest.mark.slow
def test_glass_scene_experiment_quick(tmp_path):
    """experiments/optics/glass_scene.py --quick: finite images, a ray tree that doubles
    per level, and an image that moves towards the deepest one as depth grows."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "experiments/optics/glass_scene.py"
    spec = importlib.util.spec_from_file_location("glass_scene", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    results = module.main(["--quick", "--out", str(tmp_path)])
    rows = results["depths"]
    assert [r["ray_slots"] for r in rows] == [2 ** (r["max_depth"] + 1) - 1 for r in rows]
    assert rows[-1]["mean_abs_diff_to_deepest"] == 0.0 and rows[0]["mean_abs_diff_to_deepest"] > 0.0
    for name in ("glass_scene_depths.png", "glass_scene.exr", "results.json", "config.json"):
        assert (tmp_path / name).exists()
