"""Fitting: image losses, the fitting helpers, and first fits: a sphere's radius and
centre (through the silhouette estimator), a GGX sphere's roughness and f0, a glass
sphere's index of refraction from what it refracts."""

import re
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

import jaxrt as jr
from jaxrt import fit, sdf
from jaxrt.bsdf import GGX, CookTorrance, Dielectric, Lambert, SchlickFresnel

N = 64


# -- losses and helpers -----------------------------------------------------------------


def test_losses_against_their_definitions():
    rng = np.random.default_rng(0)
    a, b = rng.uniform(size=(5, 4, 3)), rng.uniform(size=(5, 4, 3))
    w = rng.uniform(size=(5, 4, 1)) * (rng.uniform(size=(5, 4, 1)) > 0.3)
    wb = np.broadcast_to(w, a.shape)
    assert float(fit.l2_loss(a, b)) == pytest.approx(np.mean((a - b) ** 2), rel=1e-12)
    assert float(fit.l2_loss(a, b, w)) == pytest.approx(np.sum(wb * (a - b) ** 2) / np.sum(wb), rel=1e-12)
    assert float(fit.l1_loss(a, b, w)) == pytest.approx(np.sum(wb * np.abs(a - b)) / np.sum(wb), rel=1e-12)
    # Charbonnier: → |x| − δ far from 0, quadratic x²/2δ near it, finite gradient at 0.
    assert float(fit.l1_loss(a, b, delta=1e-6)) == pytest.approx(np.mean(np.abs(a - b)) - 1e-6, rel=1e-6)
    g = jax.grad(lambda x: fit.l1_loss(x, jnp.zeros(3), delta=1e-3))(jnp.zeros(3))
    assert np.all(np.asarray(g) == 0.0)
    r = fit.image_residuals(lambda p: p * jnp.asarray(a), jnp.asarray(b), w)(2.0)
    assert float(jnp.sum(r * r)) == pytest.approx(np.sum(wb * (2 * a - b) ** 2), rel=1e-12)


def test_free_parameters_rebuild_only_what_they_select():
    scene = jr.Scene(sdf.Translate(sdf.Sphere(1.0), (0.1, 0.2, 0.3)), [Lambert(0.5)])
    params, rebuild = fit.free_parameters(scene, lambda s: (s.surface.child.radius, s.surface.offset))
    new = rebuild((jnp.asarray(2.0), jnp.zeros(3)))
    assert float(new.surface.child.radius) == 2.0 and np.all(np.asarray(new.surface.offset) == 0.0)
    assert np.all(np.asarray(new.materials[0].albedo) == 0.5)
    assert float(params[0]) == 1.0


# -- first fits ---------------------------------------------------------------------------


def _sphere_scene(p):
    return jr.Scene(sdf.Translate(sdf.Sphere(p["radius"]), p["centre"]), [Lambert(0.7)],
                    [jr.PointLight((2.0, 4.0, -4.0), (40.0, 40.0, 40.0))], background=0.1)


@pytest.mark.slow
def test_fit_a_spheres_radius_and_centre_from_one_image():
    """From one 64×64 target, starting 20 % off (radius 1.2 for 1, the centre moved by
    20 % of the radius along every axis and scaled by 1.2), BFGS on the L2 loss with
    the silhouette estimator recovers both to 1e-3 relative (in practice to ~1e-11).
    Slow: the README's example (`test_the_readme_fitting_example_runs_and_recovers_the_sphere`)
    runs the same fit at 32×32 in the quick suite."""
    camera = jr.PerspectiveCamera(eye=(0.0, 0.5, -5.0), target=(0.0, 0.0, 0.0), fov=35.0,
                                  width=N, height=N)
    settings = jr.RenderSettings(dtype="float64", silhouette=True, shadows="none",
                                 hit_epsilon=1e-6)
    truth = {"radius": jnp.asarray(1.0), "centre": jnp.asarray([0.3, -0.2, 0.4])}
    start = {"radius": jnp.asarray(1.2), "centre": truth["centre"] * 1.2 + 0.2}
    target = jr.render(_sphere_scene(truth), camera, settings).rgb

    def loss(p, _):
        return fit.l2_loss(jr.render(_sphere_scene(p), camera, settings).rgb, target)

    assert float(fit.relative_error(start, truth)) >= 0.2
    result = fit.fit(loss, start, optx.BFGS(rtol=1e-10, atol=1e-10), max_steps=100)
    assert float(fit.relative_error(result.params, truth)) < 1e-3
    assert float(result.loss) < 1e-12


def _ggx_scene(p):
    lights = [jr.PointLight((2.0, 3.0, -4.0), (30.0, 30.0, 30.0)),
              jr.PointLight((-3.0, 1.0, -2.0), (10.0, 10.0, 10.0))]
    return jr.Scene(sdf.Sphere(1.0), [CookTorrance(GGX(p["alpha"]), SchlickFresnel(p["f0"]))],
                    lights, background=0.0)


@pytest.mark.parametrize("method", ["bfgs", "levenberg_marquardt"])
def test_fit_a_ggx_spheres_roughness_and_f0(method):
    """GGX roughness 0.3 and Schlick f0 = (0.9, 0.6, 0.3) from one 64×64 image,
    starting 20 % off (α = 0.36, f0 × 0.8), to 1e-3 relative: BFGS on the L2 loss, or
    Levenberg–Marquardt on the pixel residuals."""
    camera = jr.PerspectiveCamera(eye=(0.0, 0.5, -4.0), target=(0.0, 0.0, 0.0), fov=35.0,
                                  width=N, height=N)
    settings = jr.RenderSettings(dtype="float64", shadows="none")
    truth = {"alpha": jnp.asarray(0.3), "f0": jnp.asarray([0.9, 0.6, 0.3])}
    start = {"alpha": jnp.asarray(0.36), "f0": truth["f0"] * 0.8}
    target = jr.render(_ggx_scene(truth), camera, settings).rgb

    def image(p):
        return jr.render(_ggx_scene(p), camera, settings).rgb

    if method == "bfgs":
        result = fit.fit(lambda p, _: fit.l2_loss(image(p), target), start,
                         optx.BFGS(rtol=1e-10, atol=1e-10), max_steps=100)
    else:
        result = fit.fit_least_squares(fit.image_residuals(image, target), start,
                                       optx.LevenbergMarquardt(rtol=1e-10, atol=1e-10),
                                       max_steps=60)
    assert float(fit.relative_error(result.params, truth)) < 1e-3


def test_least_squares_takes_residuals_of_another_float_type_than_the_parameters():
    """A float32 image's residuals fitted in float64 parameters (a float32 render fitted
    with x64 on): the Jacobian has one float type (the parameters'), and an exponential
    decay's rate and amplitude are recovered to 1e-5."""
    x = jnp.linspace(0.0, 2.0, 50)
    truth = {"rate": jnp.asarray(1.3), "scale": jnp.asarray([2.0, 0.5])}
    data = (truth["scale"][:, None] * jnp.exp(-truth["rate"] * x)).astype(jnp.float32)

    def residuals(p, _):
        return jnp.ravel((p["scale"][:, None] * jnp.exp(-p["rate"] * x)).astype(jnp.float32) - data)

    start = {"rate": jnp.asarray(1.0, jnp.float64), "scale": jnp.asarray([1.5, 0.8], jnp.float64)}
    result = fit.fit_least_squares(residuals, start, max_steps=50, transforms={"rate": fit.LOG})
    assert float(fit.relative_error(result.params, truth)) < 1e-5


@pytest.mark.slow
def test_fit_a_glass_spheres_index_of_refraction_from_what_it_refracts():
    """η = 1.5 of a glass sphere in front of a textured wall (a sine-displaced plane lit
    from the side, so its shading varies smoothly), from η = 1.2, at depth 2."""
    camera = jr.PerspectiveCamera(eye=(0.0, 0.0, -4.0), target=(0.0, 0.0, 0.0), fov=30.0,
                                  width=N, height=N)
    settings = jr.RenderSettings(dtype="float64", shadows="none", max_depth=2)
    wall = sdf.Displace(sdf.Plane((0.0, 0.0, -1.0), -2.0, material=1), sdf.SineDisplacement(3.0),
                        amplitude=0.15)

    def scene(p):
        return jr.Scene(sdf.Union(sdf.Sphere(1.0, material=0), wall),
                        [Dielectric(p["eta"]), Lambert((0.8, 0.7, 0.6))],
                        [jr.PointLight((3.0, 2.0, 0.0), (40.0, 40.0, 40.0))])

    truth, start = {"eta": jnp.asarray(1.5)}, {"eta": jnp.asarray(1.2)}
    target = jr.render(scene(truth), camera, settings).rgb
    result = fit.fit(lambda p, _: fit.l2_loss(jr.render(scene(p), camera, settings).rgb, target),
                     start, optx.BFGS(rtol=1e-10, atol=1e-10), max_steps=100)
    assert float(fit.relative_error(result.params, truth)) < 1e-3


def test_the_readme_fitting_example_runs_and_recovers_the_sphere(capsys):
    """README.md, "Fitting shapes and materials to images": the block runs as written
    (32×32) and recovers the radius and centre to 1e-3 relative."""
    readme = (Path(__file__).parents[1] / "README.md").read_text()
    blocks = [b for b in re.findall(r"```python\n(.*?)```", readme, re.S)
              if "tests/test_fit.py runs this block" in b]
    assert len(blocks) == 1
    namespace = {}
    exec(compile(blocks[0], "README.md", "exec"), namespace)
    assert float(fit.relative_error(namespace["result"].params, namespace["truth"])) < 1e-3
