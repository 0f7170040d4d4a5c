"""The fitting driver (`jaxrt.fit`): transforms, optax loops with per-group learning
rates, the callback's loss history, checkpoints that a killed run resumes from, and
multi-view rendering (`jaxrt.views`)."""

import os
import signal
import subprocess
import sys
import textwrap

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import optimistix as optx
import pytest
from conftest import subprocess_env
from jax.flatten_util import ravel_pytree

import jaxrt as jr
from jaxrt import fit, sdf, views


def test_fit_is_reachable_from_the_package():
    assert jr.fit.fit is fit.fit and jr.render_views is views.render_views
    assert jr.orbit is views.orbit and jr.stack_cameras is views.stack_cameras


# -- transforms -----------------------------------------------------------------------


@pytest.mark.parametrize("t, lo, hi", [(fit.POSITIVE, 0, np.inf), (fit.LOG, 0, np.inf),
                                       (fit.UNIT, 0, 1), (fit.ABOVE_ONE, 1, np.inf),
                                       (fit.between(-2.0, 3.0), -2, 3), (fit.above(0.5), 0.5, np.inf)])
def test_transforms_keep_values_legal_and_invert(t, lo, hi):
    u = jnp.linspace(-30.0, 30.0, 61)
    x = t(u)
    assert np.all(np.asarray(x) >= lo) and np.all(np.asarray(x) <= hi)
    g = jax.vmap(jax.grad(t))(u)
    assert np.all(np.isfinite(np.asarray(g))) and np.all(np.asarray(g) >= 0)
    inside = np.asarray(x)[(np.asarray(x) > lo + 1e-3) & (np.asarray(x) < min(hi, 1e6) - 1e-3)]
    np.testing.assert_allclose(np.asarray(t(t.inverse(inside))), inside, rtol=1e-9)


def test_constrain_applies_a_prefix_tree_of_transforms():
    params = {"r": jnp.asarray([1.0, 2.0]), "m": (jnp.asarray(0.3), jnp.asarray(1.5)), "c": jnp.zeros(3)}
    transforms = {"r": fit.POSITIVE, "m": (fit.UNIT, fit.ABOVE_ONE), "c": None}
    raw = fit.unconstrain(params, transforms)
    assert float(raw["m"][1]) == pytest.approx(np.log(np.expm1(0.5)), rel=1e-12)
    back = fit.constrain(raw, transforms)
    for a, b in zip(jax.tree.leaves(back), jax.tree.leaves(params)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12)
    with pytest.raises(ValueError, match="kind"):
        fit.Transform("tanh")


# -- optax loops ----------------------------------------------------------------------


def _quadratic(p, _):
    return (p["a"] - 3.0) ** 2 + 10.0 * (p["b"] - 0.2) ** 2


START = {"a": jnp.asarray(1.0), "b": jnp.asarray(0.5)}


def test_adam_with_transforms_converges_and_keeps_values_legal():
    seen = []
    result = fit.fit(_quadratic, START, fit.adam(0.1, 400), max_steps=400,
                     transforms={"a": fit.POSITIVE, "b": fit.UNIT},
                     callback=lambda info: seen.append(0.0 < float(info.params["b"]) < 1.0))
    assert all(seen) and result.result == "max_steps" and result.steps == 400
    assert float(result.params["a"]) == pytest.approx(3.0, rel=1e-4)
    assert float(result.params["b"]) == pytest.approx(0.2, rel=1e-4)
    # history: the loss at every iterate, the start's first, the final one last
    assert result.history.shape == (401,)
    assert result.history[0] == pytest.approx(float(_quadratic(START, None)))
    assert result.history[-1] == pytest.approx(float(result.loss))


def test_per_group_learning_rates():
    """Adam's first step moves every leaf by about its learning rate: with per-leaf
    scales (1, 0.25) the two leaves move in that ratio; a scale of 0 freezes a leaf; and
    optax.multi_transform (labels per leaf) works through the same driver."""
    one = fit.fit(_quadratic, START, fit.adam(0.01, scales={"a": 1.0, "b": 0.25}), max_steps=1,
                  progress=False)
    da, db = abs(float(one.params["a"]) - 1.0), abs(float(one.params["b"]) - 0.5)
    assert da == pytest.approx(0.01, rel=1e-3) and db == pytest.approx(0.0025, rel=1e-3)
    frozen = fit.fit(_quadratic, START, fit.adam(0.1, scales={"a": 1.0, "b": 0.0}), max_steps=20)
    assert float(frozen.params["b"]) == 0.5 and float(frozen.params["a"]) > 1.5
    multi = optax.multi_transform({"fast": optax.adam(0.1), "slow": optax.sgd(0.0)},
                                  {"a": "fast", "b": "slow"})
    res = fit.fit(_quadratic, START, multi, max_steps=20)
    assert float(res.params["b"]) == 0.5 and float(res.params["a"]) > 1.5


def test_a_warm_up_longer_than_the_run_is_cut_to_half_of_it():
    """schedule(steps=5, warmup=10): the rate rises over the first 2 steps to its peak,
    then decays to end_factor × peak at step 5 (optax alone refuses this schedule)."""
    rates = np.array([float(fit.schedule(0.1, 5, warmup=10, end_factor=0.01)(i)) for i in range(6)])
    assert rates[0] == 0.0 and rates[2] == pytest.approx(0.1)
    assert rates[5] == pytest.approx(0.001) and np.all(np.diff(rates[2:]) < 0)


def test_reset_moments_restarts_adam_but_not_its_schedule():
    """After k steps and `reset_moments`, Adam's next step is a first step again (every
    leaf moves by its rate, m̂/√v̂ = ±1 whatever the gradients so far), at the rate the
    schedule has reached after k steps, not its initial one; per-leaf scales stay."""
    steps, k = 10, 6
    rate = fit.schedule(0.1, steps, kind="cosine")
    opt = fit.adam(0.1, steps, kind="cosine", scales={"a": 1.0, "b": 0.25})
    params = {"a": jnp.asarray(1.0), "b": jnp.asarray(0.5)}
    state = opt.init(params)
    for i in range(k):  # gradients of changing sizes and signs fill the moments
        g = {"a": jnp.asarray((-2.0) ** i), "b": jnp.asarray(3.0 + i)}
        updates, state = opt.update(g, state, params)
        params = optax.apply_updates(params, updates)
    g = {"a": jnp.asarray(0.5), "b": jnp.asarray(-7.0)}
    kept, _ = opt.update(g, state, params)
    fresh, _ = opt.update(g, fit.reset_moments(state), params)
    want = {"a": -float(rate(k)), "b": 0.25 * float(rate(k))}
    for name in ("a", "b"):
        assert float(fresh[name]) == pytest.approx(want[name], rel=1e-4), name
        assert float(kept[name]) != pytest.approx(want[name], rel=1e-2), name  # the moments mattered
    assert float(rate(k)) < 0.09  # the schedule had moved on


def test_callback_sees_the_loss_history_and_can_stop_the_fit():
    calls = []

    def callback(info):
        calls.append((info.step, info.history.copy(), info.loss))
        return info.step == 7

    result = fit.fit(_quadratic, START, fit.adam(0.05), max_steps=50, callback=callback)
    assert result.result == "callback" and result.steps == 7 and result.converged
    assert [c[0] for c in calls] == list(range(1, 8))
    for step, history, loss in calls:
        assert history.shape == (step,) and history[-1] == loss
    np.testing.assert_array_equal(result.history[:7], calls[-1][1])
    assert np.all(np.diff(result.history) < 0)  # Adam descends on this quadratic


def test_refresh_feeds_the_step_values_computed_outside_it():
    """`refresh(params)` runs before every step on the legal values and the loss sees
    its result as `args`: a straight-through loss whose forward values come from
    refresh takes the same iterates as the one computing them inline."""
    biased = lambda p: p["a"] * 1.1 + 0.0 * p["b"]  # noqa: E731  (the estimator)
    exact = lambda p: p["a"]  # noqa: E731  (the values the loss should see)

    def inline(p, _):
        v = biased(p) + jax.lax.stop_gradient(exact(p) - biased(p))
        return (v - 3.0) ** 2 + 10.0 * (p["b"] - 0.2) ** 2

    def outside(p, values):
        v = biased(p) + jax.lax.stop_gradient(values - biased(p))
        return (v - 3.0) ** 2 + 10.0 * (p["b"] - 0.2) ** 2

    seen = []

    def refresh(p):
        seen.append(float(p["a"]))
        return exact(p)

    t = {"a": fit.POSITIVE}
    a = fit.fit(inline, START, fit.adam(0.1, 300), max_steps=300, transforms=t)
    b = fit.fit(outside, START, fit.adam(0.1, 300), max_steps=300, transforms=t, refresh=refresh)
    np.testing.assert_allclose(b.history, a.history, rtol=1e-6)
    assert float(b.params["a"]) == pytest.approx(float(a.params["a"]), rel=1e-6)
    assert float(b.params["a"]) == pytest.approx(3.0, rel=1e-3)  # the exact values' minimum
    assert len(seen) == 301 and seen[0] == pytest.approx(1.0)  # every step and the final loss
    with pytest.raises(ValueError, match="refresh"):
        fit.fit(outside, START, optx.BFGS(rtol=1e-6, atol=1e-6), refresh=refresh)


def test_the_step_compiles_once_when_its_outputs_are_sharded(caplog):
    """A loss through `shard_map` (as `render_views(devices=...)`) makes the step's
    outputs NamedSharding arrays; fed back as they are, the second step would compile
    again. The driver calls the executable compiled on the first step (`fit._Step`),
    which takes equivalent shardings: one compile."""
    from jax.sharding import Mesh, PartitionSpec as P

    mesh = Mesh(np.asarray(jax.local_devices()[:1]), ("views",))

    def loss(p, _):
        per_view = jax.shard_map(lambda a, b: jnp.stack([(a - 3.0) ** 2 + 10.0 * (b - 0.2) ** 2]),
                                 mesh=mesh, in_specs=(P(), P()), out_specs=P("views"))
        return jnp.sum(per_view(p["a"], p["b"]))

    with jax.log_compiles(True), caplog.at_level("WARNING"):
        fit.fit(loss, START, fit.adam(0.05), max_steps=5, transforms={"a": fit.POSITIVE})
    compiles = [r for r in caplog.records if "Compiling jit(_optax_step)" in r.getMessage()]
    assert len(compiles) == 1, [r.getMessage()[:200] for r in compiles]


def test_a_sharded_step_feeds_the_next_on_the_device():
    """Step k's outputs (NamedShardings of the loss's mesh) are step k+1's inputs as they
    are: steps 2..5 run with every transfer disallowed (no copy through the host, no
    reshard), and take the iterates of `fit.fit`."""
    from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

    mesh = Mesh(np.asarray(jax.local_devices()[:1]), ("views",))

    def loss(p, _):
        per_view = jax.shard_map(lambda a, b: jnp.stack([(a - 3.0) ** 2 + 10.0 * (b - 0.2) ** 2]),
                                 mesh=mesh, in_specs=(P(), P()), out_specs=P("views"))
        return jnp.sum(per_view(p["a"], p["b"]))

    transforms, opt = {"a": fit.POSITIVE}, fit.adam(0.05)
    raw = fit._strong(fit.unconstrain(START, transforms))
    state = fit._strong(opt.init(raw))
    step = fit._Step(loss, transforms, opt)
    losses = []
    value, raw, state = step(raw, state, None)
    losses.append(value)
    assert isinstance(raw["a"].sharding, NamedSharding)  # the mesh's, not the inputs'
    with jax.transfer_guard("disallow"):
        for _ in range(4):
            value, raw, state = step(raw, state, None)
            losses.append(value)
    want = fit.fit(loss, START, opt, max_steps=5, transforms=transforms)
    np.testing.assert_allclose([float(v) for v in losses], want.history[:5], rtol=1e-12)
    for a, b in zip(jax.tree.leaves(fit.constrain(raw, transforms)), jax.tree.leaves(want.params)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12)


def test_atol_stops_and_non_finite_losses_keep_the_last_finite_iterate():
    res = fit.fit(_quadratic, START, fit.adam(0.1), max_steps=500, atol=1e-2)
    assert res.result == "atol" and res.converged and float(res.loss) <= 1e-2 and res.steps < 500
    # log(a − 0.5) becomes NaN once a step takes a below 0.5 (lr 1 from a = 1).
    res = fit.fit(lambda p, _: jnp.log(p["a"] - 0.5) + 0.0 * p["b"], START, optax.sgd(1.0),
                  max_steps=10)
    assert res.result == "non-finite loss" and np.isfinite(float(res.loss))
    assert np.all(np.isfinite(res.history))


def test_optimistix_solvers_take_transforms_too():
    result = fit.fit(_quadratic, START, optx.BFGS(rtol=1e-10, atol=1e-10),
                     transforms={"a": fit.POSITIVE, "b": fit.UNIT})
    assert result.converged and float(fit.relative_error(result.params, {"a": 3.0, "b": 0.2})) < 1e-6
    assert result.history.shape == (2,)
    with pytest.raises(ValueError, match="optax"):
        fit.fit(_quadratic, START, checkpoint="x.npz")


# -- checkpoints ----------------------------------------------------------------------

KILLED = textwrap.dedent(
    """
    import os, signal, sys
    import jax
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    sys.path.insert(0, {tests!r})
    from test_fit_driver import run_checkpointed
    def die(info):
        if info.step == 13:
            os.kill(os.getpid(), signal.SIGKILL)  # killed mid-fit, between checkpoints
    run_checkpointed({path!r}, die)
    """)


def run_checkpointed(path, callback=None):
    """The fit of the checkpoint test: a small rendered problem would do as well; the
    driver's state (params, Adam moments, schedule count, history) is what matters."""
    def loss(p, _):
        return jnp.sum((p["x"] - jnp.arange(4.0)) ** 2 * (1.0 + jnp.sin(p["x"]) ** 2)) + p["s"] ** 2

    start = {"x": jnp.full(4, 2.0), "s": jnp.asarray(1.5)}
    return fit.fit(loss, start, fit.adam(0.05, 40, warmup=5), max_steps=40,
                   transforms={"x": None, "s": fit.POSITIVE}, callback=callback,
                   checkpoint=path, checkpoint_every=5, progress=False)


def test_a_killed_fit_resumes_from_its_checkpoint_to_the_same_result(tmp_path):
    path = str(tmp_path / "fit.npz")
    script = KILLED.format(tests=os.path.dirname(__file__), path=path)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          env={**os.environ, "JAX_PLATFORMS": "cpu"}, timeout=300)
    assert proc.returncode == -signal.SIGKILL, proc.stderr[-2000:]
    with np.load(path) as z:
        assert int(z["step"]) == 10 and z["history"].shape == (10,)
    resumed = run_checkpointed(path)
    fresh = run_checkpointed(str(tmp_path / "fresh.npz"))
    assert resumed.steps == fresh.steps == 40
    for a, b in zip(jax.tree.leaves(resumed.params), jax.tree.leaves(fresh.params)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12, atol=0)
    np.testing.assert_allclose(resumed.history, fresh.history, rtol=1e-12)
    # a finished checkpoint resumes to the same result without stepping
    again = run_checkpointed(path)
    np.testing.assert_array_equal(np.asarray(again.params["x"]), np.asarray(resumed.params["x"]))
    # a checkpoint of another fit is refused with the file's name
    with pytest.raises(ValueError, match="fit.npz: checkpoint of another fit"):
        fit.fit(_quadratic, START, fit.adam(0.1), max_steps=3, checkpoint=path)


# -- several views --------------------------------------------------------------------


def _scene(radius=0.6):
    return jr.Scene(sdf.Union(sdf.Translate(sdf.Sphere(radius, material=0), (0.0, 0.6, 0.0)),
                              sdf.Plane(material=1)),
                    [jr.bsdf.Lambert((0.8, 0.3, 0.2)), jr.bsdf.Lambert(0.5)],
                    [jr.PointLight((2.0, 4.0, -3.0), (30.0, 30.0, 30.0))], background=0.1)


def test_render_views_is_the_per_camera_render_and_differentiable():
    settings = jr.RenderSettings(dtype="float64", silhouette=True, shadows="none")
    cameras = views.orbit(3, target=(0.0, 0.5, 0.0), distance=4.0, elevation=[20.0, 35.0, 10.0],
                          width=8, height=6)
    assert views.num_views(cameras) == 3 and cameras.eye.shape == (3, 3) and cameras.width == 8
    images = views.render_views(_scene(), cameras, settings)
    assert images.rgb.shape == (3, 6, 8, 3) and images.depth.shape == (3, 6, 8)
    for i in range(3):
        one = jr.render(_scene(), views.view(cameras, i), settings)
        np.testing.assert_allclose(np.asarray(images.rgb[i]), np.asarray(one.rgb), atol=1e-12)
    # eye k at distance 4 from the target, azimuth 120° apart
    np.testing.assert_allclose(np.linalg.norm(np.asarray(cameras.eye - cameras.target), axis=-1), 4.0)

    def loss_all(r):
        return jnp.sum(views.render_views(_scene(r), cameras, settings).rgb)

    # one view's gradient, compiled once for every camera (the cameras share a structure)
    grad_one = jax.jit(jax.grad(lambda r, camera: jnp.sum(jr.render(_scene(r), camera, settings).rgb)))
    g_all = jax.grad(loss_all)(0.6)
    g_each = sum(grad_one(0.6, views.view(cameras, i)) for i in range(3))
    assert float(g_all) != 0.0 and float(g_all) == pytest.approx(float(g_each), rel=1e-9)


def test_render_views_differentiates_a_mirror_as_the_sum_of_its_views():
    """A mirror: the replay shades the reflected rays in gathered batches behind a
    `lax.cond` whose predicate the vmap over views batches, and JAX's batching rule then
    puts `stop_gradient` (no transpose of its own) on the cond's tangents (JAX issues
    #22011, #39219). The reverse pass runs, and its gradient is the sum of each view's
    (float64, "fused"). jaxrt gives `stop_gradient` its transpose itself: in a process
    that has not imported lineax (which registers one too, and this file imports it)."""
    scene = _scene()
    scene = jr.Scene(scene.surface, [jr.bsdf.Mirror((0.9, 0.8, 0.7)), scene.materials[1]],
                     scene.lights, background=scene.background)
    settings = jr.RenderSettings(dtype="float64", backend="fused", shadows="none", max_depth=1)
    cameras = views.orbit(2, target=(0.0, 0.5, 0.0), distance=4.0, width=8, height=6)
    dyn, static = eqx.partition(scene, eqx.is_inexact_array)

    def loss_all(d):
        return jnp.sum(views.render_views(eqx.combine(d, static), cameras, settings).rgb)

    grad_one = jax.jit(jax.grad(lambda d, camera: jnp.sum(
        jr.render(eqx.combine(d, static), camera, settings).rgb)))
    g_all = ravel_pytree(jax.grad(loss_all)(dyn))[0]
    g_each = sum(ravel_pytree(grad_one(dyn, views.view(cameras, i)))[0] for i in range(2))
    assert float(jnp.max(jnp.abs(g_each))) > 0
    np.testing.assert_allclose(np.asarray(g_all), np.asarray(g_each), rtol=1e-9, atol=1e-12)

    check = ("import sys, jaxrt\n"
             "from jax._src.ad_util import stop_gradient_p\n"
             "from jax._src.interpreters import ad\n"
             "assert 'lineax' not in sys.modules\n"
             "assert stop_gradient_p in ad.primitive_transposes\n")
    run = subprocess.run([sys.executable, "-c", check], env=subprocess_env(JAX_PLATFORMS="cpu"),
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr


def test_stack_cameras_needs_one_type_and_resolution():
    a = jr.PerspectiveCamera(width=8, height=8)
    with pytest.raises(ValueError, match="one resolution"):
        views.stack_cameras([a, jr.PerspectiveCamera(width=8, height=6)])
    with pytest.raises(ValueError, match="one camera type"):
        views.stack_cameras([a, jr.OrthographicCamera(width=8, height=8)])
    with pytest.raises(ValueError, match="stacked"):
        views.render_views(_scene(), a)
    with pytest.raises(ValueError, match="split evenly"):
        views.render_views(_scene(), views.stack_cameras([a, a, a]), devices=[jax.devices()[0]] * 2)


def test_the_readme_multi_view_example_runs(tmp_path, monkeypatch):
    """README.md's multi-view optax example, at 12×12 and 60 steps: it runs, writes its
    checkpoint, lowers the loss fivefold and keeps the values legal."""
    import re
    from pathlib import Path

    readme = (Path(__file__).parents[1] / "README.md").read_text()
    blocks = [b for b in re.findall(r"```python\n(.*?)```", readme, re.S)
              if "tests/test_fit_driver.py runs this block" in b]
    assert len(blocks) == 1
    code = blocks[0].replace("width=48, height=48", "width=12, height=12").replace("200", "60")
    monkeypatch.chdir(tmp_path)
    namespace = {}
    exec(compile(code, "README.md", "exec"), namespace)
    assert (tmp_path / "sphere_fit.npz").is_file()
    result = namespace["result"]
    # (at 12×12 pixels the parameters are not all identifiable: only the loss is checked)
    assert result.history.shape == (61,) and result.history[-1] < 0.2 * result.history[0]
    assert 0.0 < float(result.params["radius"]) and np.all(np.asarray(result.params["albedo"]) < 1.0)


SHARDED = textwrap.dedent(
    """
    import jax
    jax.config.update("jax_enable_x64", True)
    import numpy as np
    import jaxrt as jr
    assert len(jax.devices()) == 2, jax.devices()
    S = jr.sdf
    scene = jr.Scene(S.Translate(S.Sphere(0.6), (0.0, 0.2, 0.0)), [jr.bsdf.Lambert(0.7)],
                     [jr.PointLight((2.0, 4.0, -3.0), (30.0, 30.0, 30.0))], background=0.1)
    cameras = jr.orbit(4, distance=3.0, width=6, height=4)
    settings = jr.RenderSettings(dtype="float64", shadows="none")
    one = jr.render_views(scene, cameras, settings)
    two = jr.render_views(scene, cameras, settings, devices=2)
    assert len(two.rgb.sharding.device_set) == 2, two.rgb.sharding
    np.testing.assert_allclose(np.asarray(two.rgb), np.asarray(one.rgb), atol=1e-12)
    print("ok")
    """)


def test_render_views_shards_the_views_over_devices():
    """Two virtual CPU devices (set before jax starts, so in a subprocess): the views
    are split between them and the images are those of one device."""
    env = subprocess_env(XLA_FLAGS="--xla_force_host_platform_device_count=2", JAX_PLATFORMS="cpu")
    proc = subprocess.run([sys.executable, "-c", SHARDED], capture_output=True, text=True, env=env,
                          timeout=300)
    assert proc.returncode == 0 and "ok" in proc.stdout, proc.stderr[-3000:]
