"""The silhouette estimator: outline gradients against the exact derivative of a disc's
area and against finite differences of heavily supersampled renders; the near misses
the tracer records; the documented dilation; zero outline gradients without it."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrt as jr
from jaxrt import sdf
from jaxrt.bsdf import Lambert, Phong

BASE = jr.RenderSettings(dtype="float64", hit_epsilon=1e-6, shadows="none", batch_size=None)


# -- a disc of constant colour: exact references ---------------------------------------

D, N, FOV = 5.0, 16, 30.0


def _flat_sphere(radius):
    """A sphere of constant radiance 1 (Phong's ambient term only) on black."""
    return jr.Scene(sdf.Sphere(radius), [Phong(kd=0.0, ks=0.0, ka=1.0)], [], background=0.0)


def _disc_radius_px(radius):
    """Screen radius (pixels) of a sphere at distance D: tan(asin(R/D)) / tan(fov/2)."""
    return np.tan(np.arcsin(radius / D)) / np.tan(np.radians(FOV / 2)) * N / 2


@pytest.fixture(scope="module")
def flat_disc():
    camera = jr.PerspectiveCamera(eye=(0.0, 0.0, -D), target=(0.03, 0.01, 0.0), fov=FOV,
                                  width=N, height=N)

    @eqx.filter_jit
    def run(radius, settings):
        def mean(r):
            image = jr.render(_flat_sphere(r), camera, settings)
            return jnp.mean(image.rgb[..., 0]), image
        (value, image), grad = jax.value_and_grad(mean, has_aux=True)(radius)
        return value, image, grad

    return run


def test_outline_gradient_is_the_derivative_of_the_disc_area(flat_disc):
    """d(mean)/dR of a uniformly bright disc is d(area)/dR / N² (in pixels)."""
    _, _, grad = flat_disc(jnp.asarray(1.0), BASE.replace(silhouette=True))
    exact = 2 * np.pi * _disc_radius_px(1.0) * (
        (_disc_radius_px(1.0 + 1e-6) - _disc_radius_px(1.0 - 1e-6)) / 2e-6) / N**2
    assert float(grad) == pytest.approx(exact, rel=0.02)


def test_without_the_estimator_outlines_have_no_gradient(flat_disc):
    """The documented behaviour of silhouette=False: a change of the disc's size only
    moves its outline, and point samples see no gradient of it."""
    _, _, grad = flat_disc(jnp.asarray(1.0), BASE)
    assert float(grad) == 0.0


def test_coverage_is_the_disc_dilated_by_the_ramp(flat_disc):
    """The coverage AOV sums to the disc's area plus the ramp outside it,
    Σ α = π r² + 2π r W + 2π W² · 7/12 (W = silhouette_width pixels; ∫ u ramp(u) du = 7/12),
    within the error of sampling an outline at pixel centres."""
    value, image, _ = flat_disc(jnp.asarray(1.0), BASE.replace(silhouette=True))
    r, w = _disc_radius_px(1.0), 1.0
    expected = np.pi * r * r + 2 * np.pi * r * w + 2 * np.pi * w * w * 7 / 12
    assert float(jnp.sum(image.coverage)) == pytest.approx(expected, rel=0.02)
    assert float(value) == pytest.approx(float(jnp.mean(image.coverage)), rel=1e-12)
    assert float(jnp.min(image.coverage)) >= 0.0 and float(jnp.max(image.coverage)) <= 1.0


# -- the tracer's near misses -----------------------------------------------------------


def test_near_miss_is_recorded_in_front_of_a_hit_and_on_a_miss():
    """A ray passing b from a sphere's centre at distance D records its closest approach
    b − R at t = sqrt(D² − b²) whether it then hits a wall behind or nothing."""
    radius, b = 1.0, 1.05
    wall = sdf.Plane((0.0, 0.0, -1.0), -3.0)
    sphere = sdf.Sphere(radius)
    o = jnp.array([0.0, b, -D])
    d = jnp.array([0.0, 0.0, 1.0])
    cone = jnp.array([0.0, np.tan(np.radians(FOV / 2)) / N])
    settings = BASE.replace(hit_epsilon=1e-9, max_steps=1000)

    @jax.jit
    def trace(o):
        return (jr.sphere_trace(sphere, o, d, settings, cone=cone),
                jr.sphere_trace(sdf.Union(sphere, wall), o, d, settings, cone=cone))

    miss, behind = trace(o)
    assert not bool(miss.hit) and bool(behind.hit)
    for hit in (miss, behind):
        # The ratio f / r(t) is minimal a little after the foot of the perpendicular.
        assert float(hit.closest_d) == pytest.approx(b - radius, rel=0.05)
        assert float(hit.closest_bracket[0]) <= float(hit.closest_t) <= float(hit.closest_bracket[1])
        assert abs(float(hit.closest_t) - D) < 0.5
    # A ray that hits the sphere head-on has no near miss before it.
    head_on = trace(jnp.array([0.0, 0.0, -D]))[0]
    assert bool(head_on.hit) and float(head_on.closest_t) == 0.0


# -- against finite differences of supersampled renders --------------------------------


LIGHT = [jr.DirectionalLight((0.4, 0.6, -1.0), (2.0, 2.0, 2.0))]


def _sphere(p):
    return jr.Scene(sdf.Sphere(p), [Lambert(0.7)], LIGHT, background=0.1)


def _box(p):
    return jr.Scene(sdf.Translate(sdf.Box((0.5, 0.4, 0.4)), (p, 0.05, 0.0)), [Lambert(0.7)],
                    LIGHT, background=0.1)


def _blend(p):
    a = sdf.Translate(sdf.Sphere(0.6), (-0.55, 0.0, 0.0))
    b = sdf.Translate(sdf.Sphere(0.5), (0.5, 0.0, 0.0))
    return jr.Scene(sdf.SmoothUnion(a, b, p), [Lambert(0.3)], LIGHT, background=0.6)


#: name: (scene builder, θ₀, finite-difference step, camera, image region)
CASES = {
    "sphere_radius": (_sphere, 1.0, 0.02, dict(eye=(0.0, 0.0, -5.0), target=(0.05, 0.02, 0.0),
                                               fov=28.0), np.s_[:, :]),
    # The box's front face only: its right outline (and no crease) in the region.
    "box_position": (_box, 0.03, 0.02, dict(eye=(0.0, 0.0, -5.0), target=(0.0, 0.0, 0.0),
                                            fov=20.0), np.s_[:, 8:]),
    # Darker than the background, so both necks' outlines pull the same way.
    "blend_width": (_blend, 0.5, 0.05, dict(eye=(0.0, 0.0, -5.0), target=(0.0, 0.0, 0.0),
                                            fov=30.0), np.s_[:, :]),
}


def _compare(case, size, reference_spp, estimator_spp=4):
    build, theta, h, view, region = CASES[case]
    camera = jr.PerspectiveCamera(width=size, height=size, **view)

    @eqx.filter_jit
    def mean(p, settings):
        return jnp.mean(jr.render(build(p), camera, settings).rgb[region])

    estimate = float(jax.grad(mean)(theta, BASE.replace(silhouette=True, spp=estimator_spp)))
    ref = BASE.replace(spp=reference_spp)
    reference = (float(mean(theta + h, ref)) - float(mean(theta - h, ref))) / (2 * h)
    return estimate, reference


def test_outline_gradients_in_forward_and_reverse_mode_are_finite_and_agree():
    """The box's outline, 4 jittered samples per pixel, compiled at XLA:CPU -O0: the
    gradient of the region's mean equals its jvp. (The outline's shape term, f(p_s) with
    the shape's derivative, came from `value_and_gradient`, whose reverse pass was then
    differentiated too: at -O0 its gradient was NaN, the jvp finite.)"""
    build, theta, _, view, region = CASES["box_position"]
    camera = jr.PerspectiveCamera(width=16, height=16, **view)
    settings = BASE.replace(silhouette=True, spp=4,  # forward mode too, also on a GPU
                            kernel=BASE.kernel.replace(replay_kernel=False))

    def mean(p):
        return jnp.mean(jr.render(build(p), camera, settings).rgb[region])

    def both(p):
        return jax.grad(mean)(p), jax.jvp(mean, (p,), (jnp.ones_like(p),))[1]

    p = jnp.asarray(theta)
    options = {"xla_backend_optimization_level": 0}
    grad, tangent = jax.jit(both).lower(p).compile(compiler_options=options)(p)
    assert np.isfinite(float(grad)) and abs(float(grad)) > 1e-2
    assert float(grad) == pytest.approx(float(tangent), rel=1e-9)


@pytest.mark.slow
@pytest.mark.parametrize("case", sorted(CASES))
def test_outline_gradients_match_finite_differences_of_32x32_supersampled_renders(case):
    """The gradient of a region's mean (shading and outlines) with the estimator on (16
    jittered samples per pixel) is within 5 % of central differences of renders with
    32 × 32 samples per pixel and no estimator."""
    estimate, reference = _compare(case, 16, 1024, estimator_spp=16)
    assert estimate == pytest.approx(reference, rel=0.05)


def test_outline_gradient_matches_finite_differences_of_a_supersampled_render_fast():
    """The sphere's radius on a 12 × 12 image (4 samples per pixel) against 16 × 16
    samples per pixel."""
    estimate, reference = _compare("sphere_radius", 12, 256)
    assert estimate == pytest.approx(reference, rel=0.05)


# -- silhouette_gradient = "outline": the derivative on the outline's own pixels -------


@pytest.fixture(scope="module")
def disc_tangents():
    """{mode: (image, ∂image/∂R)} of the flat disc at R = 1 (one compile per mode)."""
    camera = jr.PerspectiveCamera(eye=(0.0, 0.0, -D), target=(0.03, 0.01, 0.0), fov=FOV,
                                  width=N, height=N)

    @eqx.filter_jit
    def run(settings):
        render = lambda r: jr.render(_flat_sphere(r), camera, settings)  # noqa: E731
        image, tangent = jax.jvp(render, (jnp.asarray(1.0),), (jnp.asarray(1.0),))
        return image, tangent.rgb[..., 0]

    forward = BASE.kernel.replace(replay_kernel=False)  # forward mode, also on a GPU
    return {mode: run(BASE.replace(silhouette=True, silhouette_gradient=mode, kernel=forward))
            for mode in ("ramp", "outline")}


def test_outline_mode_moves_the_derivative_onto_the_outline(disc_tangents):
    """Both modes render the same image (to rounding: two programs, fused differently)
    and the same total derivative (that of the disc's area). The derivative's mean
    distance from the disc's centre is the outline's radius with "outline" (within
    0.1 px; the box-filtered image's derivative lies on the pixels the outline crosses)
    and about W = 1 px more with "ramp" (the tent's mean)."""
    (ramp_image, ramp), (image, outline) = disc_tangents["ramp"], disc_tangents["outline"]
    np.testing.assert_allclose(np.asarray(image.rgb), np.asarray(ramp_image.rgb), rtol=0, atol=1e-14)
    assert float(jnp.sum(outline)) == pytest.approx(float(jnp.sum(ramp)), rel=1e-12)
    coverage = np.asarray(image.coverage)
    y, x = np.mgrid[0:N, 0:N] + 0.5  # the coverage's centroid: the disc's centre
    centre = ((coverage * x).sum() / coverage.sum(), (coverage * y).sum() / coverage.sum())
    rho = np.hypot(x - centre[0], y - centre[1])
    moment = lambda t: float((np.asarray(t) * rho).sum() / np.asarray(t).sum())  # noqa: E731
    assert moment(outline) == pytest.approx(_disc_radius_px(1.0), abs=0.1)
    assert moment(ramp) == pytest.approx(_disc_radius_px(1.0) + 1.0, abs=0.15)


@pytest.mark.slow
@pytest.mark.parametrize("radius", [1.04, 0.96])
def test_debiased_loss_gradient_of_a_wrong_disc_matches_finite_differences(radius):
    """A straight-through loss (values of box-filtered renders, gradient of the estimator)
    of a disc 4 % too large or too small against the box-filtered truth: with "outline"
    its gradient is within 3 % of central differences of the box-filtered loss (32 × 32
    image, 16 × 16 samples per pixel). With "ramp" the pull that would shrink a disc that
    is too large is several times too weak: the residual lies inside the outline, the
    ramp's samples outside it (docs/inverse.md)."""
    size = 32
    camera = jr.PerspectiveCamera(eye=(0.0, 0.0, -D), target=(0.03, 0.01, 0.0), fov=FOV,
                                  width=size, height=size)

    @eqx.filter_jit
    def box(r, spp):
        return jr.render(_flat_sphere(r), camera, BASE.replace(spp=spp)).rgb

    target, r = box(jnp.asarray(1.0), 64), jnp.asarray(radius)
    values = box(r, 64)
    h = 0.01
    reference = float(jnp.mean((box(r + h, 256) - target) ** 2)
                      - jnp.mean((box(r - h, 256) - target) ** 2)) / (2 * h)

    @eqx.filter_jit
    def debiased(r, settings):
        image = jr.render(_flat_sphere(r), camera, settings).rgb
        return jnp.mean((image + jax.lax.stop_gradient(values - image) - target) ** 2)

    grads = {mode: float(jax.grad(debiased)(r, BASE.replace(silhouette=True,
                                                             silhouette_gradient=mode)))
             for mode in ("ramp", "outline")}
    assert grads["outline"] == pytest.approx(reference, rel=0.03)
    if radius > 1.0:
        assert 0.0 < grads["ramp"] < 0.5 * reference


def test_outline_mode_gradient_is_the_same_on_the_fused_backend():
    """The outline term travels as two more per-sample outputs of the kernel: the fused
    backend's recorded replay gives the "jax" path's gradient (float32, 2 spp)."""
    camera = jr.PerspectiveCamera(eye=(0.0, 0.0, -5.0), target=(0.03, 0.01, 0.0), fov=30.0,
                                  width=12, height=12)
    weights = jax.random.uniform(jax.random.PRNGKey(0), (12, 12, 3))
    grads = []
    for backend in ("jax", "fused"):
        settings = jr.RenderSettings(silhouette=True, silhouette_gradient="outline", shadows="none",
                                     backend=backend, spp=2)
        loss = lambda r: jnp.sum(weights * jr.render(_sphere(r), camera, settings).rgb)  # noqa: E731
        grads.append(float(jax.grad(loss)(jnp.asarray(1.0))))
    assert grads[1] == pytest.approx(grads[0], rel=1e-3)
