"""The two loop forms of the marches (`jaxrt.march.form`) compute the same values.

"phases" (one copy of f per march, the default and the "jax" path's) and "plain" (the
start before the loop, the finish after it, short loops unrolled: "auto" on "pallas")
are two programs for one computation: the marches' outputs, a render's image and its
record/replay gradient agree to rounding (float64).
"""

import os
import subprocess
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrt as jr
from jaxrt.march import form, shadow, sphere
from jaxrt.march.search import golden_section


def _surface():
    return jr.sdf.Union(jr.sdf.Sphere(radius=1.0, material=0),
                        jr.sdf.Plane(normal=(0.0, 1.0, 0.0), offset=-1.0, material=1))


def _rays(n=192):
    """Origins around (0, 0.5, −4) (a few inside the sphere) and directions towards it."""
    o = jnp.array([0.0, 0.5, -4.0]) + 0.3 * jax.random.normal(jax.random.PRNGKey(0), (n, 3),
                                                               jnp.float64)
    o = o.at[:8].set(0.3 * jax.random.normal(jax.random.PRNGKey(2), (8, 3), jnp.float64))
    d = 0.3 * jax.random.normal(jax.random.PRNGKey(1), (n, 3), jnp.float64) + jnp.array([0.0, -0.1, 1.0])
    return o, d / jnp.linalg.norm(d, axis=1, keepdims=True)


def _in_both_forms(fn):
    out = {}
    for name in form.FORMS:
        with form.using(name):
            out[name] = jax.tree_util.tree_map(np.asarray, fn())
    return out["phases"], out["plain"]


def _assert_same(a, b, tol=1e-12):
    assert a.keys() == b.keys()
    for k in a:
        assert a[k].dtype == b[k].dtype, k
        if a[k].dtype == bool or np.issubdtype(a[k].dtype, np.integer):
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)
        else:
            np.testing.assert_allclose(a[k], b[k], rtol=tol, atol=tol, err_msg=k)


@pytest.mark.parametrize("relax", [1.0, 1.6])
def test_sphere_march_is_the_same_in_both_forms(relax):
    """Hits, misses, rays that start inside, rays out of budget (some finished by the
    secant, some still converging) and near misses: every `Hit` field agrees."""
    surface, (o, d) = _surface(), _rays()
    options = sphere.SphereTracing(max_steps=10, over_relaxation=relax)
    cone = jnp.array([0.0, 0.002])
    phases, plain = _in_both_forms(lambda: jax.vmap(
        lambda o, d: sphere.march(surface, o, d, options, cone, 20.0))(o, d))
    _assert_same(phases, plain)
    # The bundle exercises every ending of a march.
    for k in ("hit", "inside", "exhausted", "converging"):
        assert phases[k].any(), k
    assert (~phases["hit"] & ~phases["exhausted"]).any()  # misses


@pytest.mark.parametrize("refine", [0, 8])
def test_soft_shadow_march_is_the_same_in_both_forms(refine):
    """Lit, penumbral, blocked and out-of-budget shadow rays, from outside and inside
    the solid: t*, blocked, the sign and f(t*) agree."""
    surface, (o, d) = _surface(), _rays()
    p = o * jnp.array([1.0, 0.0, 1.0]) + jnp.array([0.0, -0.99, 0.0])  # on the floor
    p = p.at[:8].set(o[:8])  # inside the sphere
    wi = d * jnp.array([1.0, -1.0, -1.0])
    options = shadow.SoftShadow(max_steps=12, refine_steps=refine)
    phases, plain = _in_both_forms(lambda: jax.vmap(
        lambda p, w: shadow.march(surface, p, w, jnp.asarray(6.0), options))(p, wi))
    _assert_same(phases, plain)
    assert phases["blocked"].any() and (~phases["blocked"] & (phases["t"] > 0)).any()
    assert (phases["sign"] < 0).any()


def test_golden_section_is_the_same_in_both_forms():
    """With and without h(t0), a few steps (unrolled) and many (a loop)."""

    def h(t):
        return jnp.cos(3.0 * t) + 0.1 * t

    for steps in (3, 10):
        for t0 in (None, jnp.float64(0.2)):
            phases, plain = _in_both_forms(lambda: golden_section(
                h, jnp.float64(0.0), jnp.float64(2.0), steps, t0=t0))
            np.testing.assert_allclose(phases, plain, rtol=0, atol=1e-15)


def test_kernel_option_march_form():
    """`KernelOptions.march_form` is validated; `form.using` takes "phases" or "plain"."""
    assert jr.KernelOptions().march_form == "auto"
    with pytest.raises(ValueError, match="march_form"):
        jr.KernelOptions(march_form="straight")
    assert jr.RenderSettings(kernel={"march_form": "plain"}).kernel.march_form == "plain"
    with pytest.raises(ValueError):
        with form.using("auto"):
            pass
    assert form.current() == "phases"


def _program_sizes(monkeypatch, settings, limit):
    """Lane-operation counts of the one-ray programs `fused._trace_one` gives for
    `settings.backend` (in a render under `jax.eval_shape`, which traces but does not
    lower the kernel; "auto" as on a GPU, i.e. "pallas"), with
    `kernel.plain_max_lane_ops = limit`; the last is the kernel's."""
    from jaxrt.kernels import fused

    sizes = []
    trace = fused._trace_one

    def traced(*args):
        closed, out_shapes = trace(*args)
        settings_, backend = args[3:5]
        sizes.append(fused._lane_ops(closed, backend, settings_.kernel.pallas_scan_loops))
        return closed, out_shapes

    monkeypatch.setattr(fused, "_trace_one", traced)
    jax.clear_caches()  # trace again, also settings that an earlier test rendered
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")  # "auto" → "pallas"
    scene, camera, _ = _scene()
    settings = settings.replace(kernel=settings.kernel.replace(plain_max_lane_ops=limit))
    jax.eval_shape(lambda p: jr.render(*p, settings).rgb, (scene, camera))
    return sizes


@pytest.mark.parametrize("backend,option", [("auto", "auto"), ("auto", "plain"), ("fused", "auto")])
def test_auto_takes_phases_for_plain_programs_over_the_limit(monkeypatch, backend, option):
    """"auto" runs the plain form up to `plain_max_lane_ops` lane operations and the
    phases beyond (a large plain program compiles for long: minutes in Triton), on
    "pallas" and on "fused"; an explicit "plain" is kept at any size."""
    base = jr.RenderSettings(shadows="soft", backend=backend, max_depth=0)
    kernel = lambda name: base.replace(kernel=base.kernel.replace(march_form=name))  # noqa: E731
    plain = _program_sizes(monkeypatch, kernel("plain"), 10**9)[-1]
    phases = _program_sizes(monkeypatch, kernel("phases"), 10**9)[-1]
    assert plain > phases
    assert _program_sizes(monkeypatch, kernel(option), plain)[-1] == plain
    expected = phases if option == "auto" else plain
    assert _program_sizes(monkeypatch, kernel(option), plain - 1)[-1] == expected


def _scene():
    """A sphere over a floor under a point light: soft shadows (refined), silhouettes."""
    surface = jr.sdf.Union(jr.sdf.Translate(jr.sdf.Sphere(0.8, material=0), offset=(0.0, -0.1, 0.0)),
                           jr.sdf.Plane(normal=(0.0, 1.0, 0.0), offset=-1.0, material=1))
    scene = jr.Scene(surface, [jr.bsdf.Lambert((0.7, 0.5, 0.4)), jr.bsdf.Lambert((0.5, 0.6, 0.7))],
                     [jr.PointLight((1.5, 3.0, -1.5), (20.0, 20.0, 20.0))],
                     background=(0.1, 0.2, 0.3))
    camera = jr.PerspectiveCamera(eye=(0.0, 0.6, -3.5), target=(0.0, -0.2, 0.0), fov=45.0,
                                  width=8, height=6)
    settings = jr.RenderSettings(dtype="float64", max_depth=0, shadows="soft", silhouette=True,
                                 shadow_steps=24, batch_size=64, backend="fused")
    return scene, camera, settings


@pytest.mark.slow
def test_both_forms_render_the_same_image_and_gradient():
    """The fused backend's kernel in either form (`KernelOptions.march_form`): the same
    image and AOVs, and the same record/replay gradient of every scene and camera float
    (float64; soft shadows refined by golden section, silhouettes).

    Under xdist it runs in a fresh process: in the full slow suite its gradient's XLA:CPU
    compile segfaulted the worker that had compiled the tests before it (session 16,
    twice, jax 0.10.2), where alone it passes."""
    if os.environ.get("PYTEST_XDIST_WORKER") is not None:
        env = {k: v for k, v in os.environ.items() if k != "PYTEST_XDIST_WORKER"}
        node = f"{__file__}::test_both_forms_render_the_same_image_and_gradient"
        run = subprocess.run([sys.executable, "-m", "pytest", "-q", "-n0", "-m", "slow", "-p", "no:cacheprovider", node],
                             env=env, capture_output=True, text=True)
        assert run.returncode == 0 and " passed" in run.stdout, run.stdout[-3000:] + run.stderr[-3000:]
        return
    scene, camera, settings = _scene()
    weights = jax.random.uniform(jax.random.PRNGKey(3), (6, 8, 3), jnp.float64)
    images, grads = {}, {}
    for name in form.FORMS:
        s = settings.replace(kernel=settings.kernel.replace(march_form=name))
        images[name] = jr.render(scene, camera, s)
        loss = lambda p, s=s: jnp.sum(weights * jr.render(*p, s).rgb)  # noqa: E731
        grads[name] = eqx.filter_grad(loss)((scene, camera))
    a, b = images["phases"], images["plain"]
    assert float(np.ptp(np.asarray(a.rgb))) > 0.1
    for k in ("rgb",) + tuple(settings.aovs):
        x, y = np.asarray(getattr(a, k)), np.asarray(getattr(b, k))
        np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-12, err_msg=k)
    ga, gb = (jax.tree_util.tree_leaves(g) for g in (grads["phases"], grads["plain"]))
    assert len(ga) == len(gb) and max(float(np.max(np.abs(x))) for x in ga) > 0.0
    for x, y in zip(ga, gb):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-10, atol=1e-12)
