"""jaxrt.kernels: the lane-wise (fused, Pallas) evaluation computes the same function as
vmap, and the fused render backends give the same images and gradients as "jax"."""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrt as jr
from jaxrt.kernels import Unsupported, eval_lanes, lanes_of, map_samples
from jaxrt.kernels.lanes import stack_lanes
from jaxrt.kernels.fused import resolve_backend

from helpers import warnings_as_errors


def _lane(x):
    out = np.empty((), dtype=object)
    out[()] = x
    return out


def _run_lanes(fn, params, *per_ray, block):
    """fn(params, *per_ray scalars) evaluated lane-wise on [block] inputs."""
    closed = jax.make_jaxpr(fn)(params, *[x[0] for x in per_ray])
    args = [lanes_of(params)] + [_lane(x) for x in per_ray]
    outs = eval_lanes(closed, args, block)
    return [np.asarray(stack_lanes(o, block, v.aval.dtype))
            for o, v in zip(outs, closed.jaxpr.outvars)]


def program(params, a, b):
    """Exercises what lanes must handle: per-ray loops, conds, dynamic indexing, scatters,
    small matrix products, reductions, argmax, round, dynamic_update_slice."""
    table = params[:4]
    m = params[4:13].reshape(3, 3)
    v = jnp.stack([a, b, a * b])
    w = m @ v
    i = jnp.clip(jnp.floor(jnp.abs(a) * 3.0).astype(jnp.int32), 0, 3)
    picked = table[i]  # dynamic index per ray
    branch = jax.lax.switch(i % 3, [lambda x: x + 1.0, lambda x: x * 2.0, jnp.sin], b)

    def cond(s):
        k, t = s
        return (k < 50) & (t < jnp.abs(a) * 5.0 + 0.5)

    def body(s):
        k, t = s
        return k + 1, t + 0.25 + 0.1 * jnp.abs(b)

    k, t = jax.lax.while_loop(cond, body, (0, 0.0))
    s = jnp.zeros(4).at[2].set(b).at[1].add(a).at[i].add(b)  # scatter: constant, per-ray index
    u = jax.lax.dynamic_update_slice(jnp.zeros(5), jnp.stack([a, b]), (jnp.int32(2),))
    return (w.sum() + jnp.max(w) + jnp.argmax(w).astype(jnp.float32), picked, branch,
            k.astype(jnp.float32), t, s, u, jnp.round(a * 7.3), jnp.linalg.norm(v))


def test_lanes_match_vmap():
    rng = np.random.default_rng(0)
    params = jnp.asarray(rng.normal(size=13))
    a = jnp.asarray(rng.uniform(-1.5, 1.5, 64))
    b = jnp.asarray(rng.normal(size=64))
    want = jax.vmap(program, (None, 0, 0))(params, a, b)
    got = _run_lanes(program, params, a, b, block=64)
    for g, w in zip(got, want):
        np.testing.assert_allclose(g, np.asarray(w), rtol=1e-12, atol=1e-12)


def test_fused_multiply_adds_and_shared_values_keep_the_function():
    """The Pallas kernel's lane forms: products used once by an add, sub or sum become
    fused multiply-adds (here counted, in their plain form), and scalar chains of the
    parameters alone are recorded once outside the kernel and replayed as reads, an
    operation met twice on the same operands read once (lanes.Uniforms)."""
    from jaxrt.kernels.lanes import Uniforms

    rng = np.random.default_rng(2)
    params = jnp.asarray(rng.normal(size=13), jnp.float32)
    a = jnp.asarray(rng.uniform(-1.5, 1.5, 64), jnp.float32)
    b = jnp.asarray(rng.normal(size=64), jnp.float32)

    def shared_twice(p, a, b):  # the same normalisation of parameters, twice
        n1 = p[:3] / jnp.linalg.norm(p[:3])
        n2 = p[:3] / jnp.linalg.norm(p[:3])
        v = jnp.stack([a, b, a * b])
        w = p[4:13].reshape(3, 3) @ v  # sums of products (dot_general)

        def body(s):
            k, x = s
            return k + 1, x * 0.9 - 0.05 * a  # x·0.9 − 0.05·a: fused, in a loop
        _, x = jax.lax.while_loop(lambda s: (s[0] < 5) & (s[1] > -1.0), body, (0, b))
        return (jnp.sum(w * v) + jnp.dot(n1, jnp.stack([a, b, a - b])) - n2[0] * b
                + p[3] - a * x)

    with jax.default_matmul_precision("highest"):  # a GPU's XLA: TF32 dots otherwise
        want = jax.vmap(shared_twice, (None, 0, 0))(params, a, b)
    closed = jax.make_jaxpr(shared_twice)(params, a[0], b[0])
    calls = []
    ptx = {"fma": lambda x, y, z: calls.append(1) or x * y + z, "neg": jnp.negative}
    seen = {}

    def record_and_replay(p):  # the parameters traced, as in a kernel
        lanes = [lanes_of(p), _lane(a), _lane(b)]
        recorded = Uniforms()
        eval_lanes(closed, lanes, 64, ptx=ptx, uniforms=recorded)
        replay = Uniforms(read=lambda k, dtype: recorded.values[k])
        (out,) = eval_lanes(closed, lanes, 64, ptx=ptx, uniforms=replay)
        replay.check(recorded)
        seen["ops"] = recorded.ops
        return stack_lanes(out, 64, jnp.float32)

    got = jax.jit(record_and_replay)(params)
    ops = [name for name, _ in seen["ops"]]
    assert ops.count("sqrt") == 1 and ops.count("div") == 3, ops  # one norm, not two
    assert calls, "no product was fused"
    np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=2e-5, atol=2e-5)


def test_erfc_for_targets_without_it_is_within_its_fit_error():
    """A target without erfc (Triton) gets lanes' Chebyshev fit: fractional error below
    1.2e-7 (Numerical Recipes' bound) over the range a Beckmann Smith term uses."""
    import jax.scipy.special as jss

    x = jnp.linspace(-5.0, 10.0, 3001)
    closed = jax.make_jaxpr(jss.erfc)(x[0])
    (got,) = eval_lanes(closed, [_lane(x)], x.shape[0], unsupported=("erfc",))
    want = np.asarray(jss.erfc(x))
    rel = np.abs(np.asarray(got[()]) - want) / want
    assert rel.max() < 1.2e-7, rel.max()


def test_pallas_kernel_lowers_for_cuda_with_ptx_forms(small_scene):
    """Without a GPU, the Triton lowering of a render (not its compilation) still runs:
    the kernel with fused multiply-adds and PTX fast math lowers for CUDA."""
    import equinox as eqx
    from jaxrt.render import _cast, _render

    scene, camera, _ = small_scene
    settings = jr.RenderSettings(backend="pallas", shadows="soft", batch_size=32, aovs=(),
                                 kernel=jr.KernelOptions(interpret=False))
    dyn, static = eqx.partition(_cast((scene, camera), jnp.float32), eqx.is_array)
    f = jax.jit(lambda d: _render.__wrapped__(*eqx.combine(d, static), settings))
    try:
        text = f.trace(dyn).lower(lowering_platforms=("cuda",)).as_text()
    except Exception as e:  # jax 0.11's Triton lowering asks the GPU for its compute capability
        if "No supported GPU devices" not in str(e):
            raise
        pytest.skip(f"this JAX cannot lower Pallas for CUDA without a GPU ({jax.__version__})")
    assert "jaxrt_render" in text
    for instruction in ("fma.rn.f32", "sqrt.approx.ftz.f32", "neg.f32"):
        assert instruction in text, instruction


def test_lanes_reject_unsupported_primitives():
    def fn(params, a):
        return jnp.sort(jnp.stack([a, params, -a]))

    with pytest.raises(Unsupported, match="sort"):
        _run_lanes(fn, jnp.float64(1.0), jnp.ones(4), block=4)


# ------------------------------------------------------------------ render backends


@pytest.fixture(scope="module")
def small_scene():
    S = jr.sdf
    surface = S.Union(
        S.Translate(S.Sphere(radius=0.6, material=0), offset=(0.0, 0.6, 0.0)),
        S.Subtraction(S.Translate(S.Box(half_extents=(0.4, 0.4, 0.4), material=1), offset=(1.1, 0.4, 0.0)),
                      S.Translate(S.Sphere(radius=0.45, material=1), offset=(1.1, 0.8, 0.0))),
        S.Plane(normal=(0.0, 1.0, 0.0), offset=0.0, material=2))
    scene = jr.Scene(surface=surface,
                     materials=[jr.bsdf.Lambert(albedo=(0.8, 0.3, 0.2)),
                                jr.bsdf.BlinnPhong(kd=0.5, ks=0.3, q=30.0),
                                jr.bsdf.Lambert(albedo=(0.6, 0.6, 0.6))],
                     lights=[jr.PointLight(position=(2.0, 4.0, 3.0), intensity=(30.0, 30.0, 30.0)),
                             jr.DirectionalLight(direction=(-0.3, 1.0, 0.2), irradiance=(0.5, 0.5, 0.5))],
                     background=(0.1, 0.1, 0.15))
    camera = jr.PerspectiveCamera(eye=(0.5, 1.6, 3.5), target=(0.4, 0.4, 0.0), up=(0.0, 1.0, 0.0),
                                  fov=45.0, width=20, height=12)
    settings = jr.RenderSettings(shadows="soft", batch_size=16)
    return scene, camera, settings


def _assert_same(a, b, rgb_tol):
    np.testing.assert_array_equal(np.asarray(a.coverage), np.asarray(b.coverage))
    # step counts: equal but where a march's last test is within rounding of its
    # threshold (one pixel of 240 at XLA:CPU -O0)
    steps_a, steps_b = np.asarray(a.steps), np.asarray(b.steps)
    assert np.max(np.abs(steps_a - steps_b)) <= 1 and np.mean(steps_a != steps_b) <= 0.01
    np.testing.assert_allclose(np.asarray(a.rgb), np.asarray(b.rgb), atol=rgb_tol)
    np.testing.assert_allclose(np.asarray(a.depth), np.asarray(b.depth), rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(np.asarray(a.normal), np.asarray(b.normal), atol=1e-4)


@pytest.mark.parametrize("backend", ["fused", "pallas"])
def test_fused_backends_match_jax(small_scene, backend):
    """Same image as the vmapped program (float32; Pallas in interpret mode on CPUs).
    Tiles of 4×4 rays; the image (20×12) is not a multiple of them."""
    scene, camera, settings = small_scene
    want = jr.render(scene, camera, settings)
    got = jr.render(scene, camera, settings.replace(backend=backend))
    _assert_same(got, want, rgb_tol=1e-4)


def test_auto_traces_the_one_sample_program_once_per_kernel(small_scene, monkeypatch):
    """"auto" checks the lane program's size and builds its kernel abstractly before the
    real one: the one-sample program (seconds to trace for a large scene) is traced once
    for all three. A gradient traces one kernel, the record: `render.differentiable`
    keeps the plain render (the primal of `render._recorded`'s custom JVP) out of a
    derivative's trace. On Pallas (a GPU), where the replay's VJP is a kernel too
    (`KernelOptions.replay_kernel`, a custom VJP), three: that one, the record and the
    plain render, which the jit of `render` traces first."""
    import jaxrt.kernels.fused as fused

    scene, camera, settings = small_scene
    calls = []
    trace_one = fused._trace_one
    monkeypatch.setattr(fused, "_trace_one", lambda *a: calls.append(a[4]) or trace_one(*a))

    def loss(scene, steps):  # settings of their own: no trace cached by another test
        settings_ = settings.replace(backend="auto", max_steps=steps)
        return jnp.mean(jr.render(scene, camera, settings_).rgb)

    jax.jit(loss, static_argnums=1).lower(scene, 37)
    assert calls == [resolve_backend("auto")]
    calls.clear()
    jax.jit(jax.grad(loss), static_argnums=1).lower(scene, 38)
    backend = resolve_backend("auto")
    assert calls == [backend] * (3 if backend == "pallas" else 1)


def test_fused_ray_tree_scan_skips_dead_slots_per_tile(small_scene):
    """The sphere as a mirror, the ray tree as a scan over its 7 slots (depth 2): tiles of
    4×4 rays that see no mirror skip every slot past the camera ray's, the others shade
    them; the same image as the vmapped program, which shades every slot of every ray."""
    scene, camera, settings = small_scene
    scene = jr.Scene(scene.surface, [jr.bsdf.Mirror((0.9, 0.8, 0.7))] + list(scene.materials[1:]),
                     scene.lights, background=scene.background)
    settings = settings.replace(recursion="scan", max_depth=2)
    want = jr.render(scene, camera, settings)
    assert float(np.max(np.asarray(want.rgb))) > 0.0
    _assert_same(jr.render(scene, camera, settings.replace(backend="fused")), want, rgb_tol=1e-4)


@pytest.mark.slow
def test_fused_backend_spp_and_float64(small_scene):
    scene, camera, settings = small_scene
    s = settings.replace(spp=2, dtype="float64", batch_size=32)
    want = jr.render(scene, camera, s)
    got = jr.render(scene, camera, s.replace(backend="fused"))
    _assert_same(got, want, rgb_tol=1e-9)


@pytest.mark.slow
def test_fused_backend_gradients_are_the_reference_gradients(small_scene):
    """Forward lane-wise, backward through the vmapped program (custom VJP)."""
    scene, camera, settings = small_scene
    camera = camera.with_resolution(8, 6)
    s = settings.replace(dtype="float64", batch_size=16)

    def loss(radius, backend):
        sc = jax.tree_util.tree_map(lambda x: x, scene)
        sc = eqx_set_radius(sc, radius)
        return jnp.mean(jr.render(sc, camera, s.replace(backend=backend)).rgb)

    g_jax = jax.grad(loss)(0.6, "jax")
    g_fused = jax.grad(loss)(0.6, "fused")
    assert np.isfinite(g_jax) and g_jax != 0.0
    np.testing.assert_allclose(g_fused, g_jax, rtol=1e-10)


@pytest.mark.slow
def test_multi_view_gradient_step_runs_the_lanes_and_matches_jax():
    """value_and_grad of a multi-view image loss (`render_views`: vmapped over the
    cameras) with backend "auto" runs the lane kernels (no fallback warning: warnings are
    errors) and equals backend "jax" (float64). A torus and a cylinder: their distances
    stack 2-vectors, so the normals' and the silhouette's derivatives unstack them (the
    inverse studies' gradient step failed there; tests/test_lane_rules.py `unstack_*`)."""
    assert resolve_backend("auto") in ("fused", "pallas")
    cameras = jr.orbit(2, target=(0.0, 0.3, 0.0), distance=3.0, elevation=[25.0, -10.0],
                       width=6, height=5)
    settings = jr.RenderSettings(dtype="float64", silhouette=True, shadows="none", max_steps=48,
                                 aovs=())

    def loss(p, backend):
        S = jr.sdf
        shape = S.Union(S.Translate(S.Torus(p[0], p[1], material=0), (0.0, 0.3, 0.0)),
                        S.Translate(S.Cylinder(p[2], 0.3, material=0), (0.5, 0.0, 0.2)))
        scene = jr.Scene(shape, [jr.bsdf.Lambert((0.8, 0.4, 0.2))],
                         [jr.PointLight((2.0, 4.0, -3.0), (30.0, 30.0, 30.0))], background=0.1)
        rgb = jr.render_views(scene, cameras, settings.replace(backend=backend)).rgb
        return jnp.mean((rgb - 0.3) ** 2)

    p = jnp.asarray([0.45, 0.12, 0.15])
    want_value, want_grad = jax.value_and_grad(loss)(p, "jax")
    with warnings_as_errors():
        value, grad = jax.value_and_grad(loss)(p, "auto")
    assert np.all(np.asarray(want_grad) != 0.0)
    np.testing.assert_allclose(float(value), float(want_value), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(grad), np.asarray(want_grad), rtol=1e-6)


def eqx_set_radius(scene, radius):
    import equinox as eqx

    return eqx.tree_at(lambda s: s.surface.children_[0].child.radius, scene, jnp.asarray(radius))


def test_auto_backend_falls_back_where_lanes_cannot_run():
    """backend="auto" renders programs that lanes cannot run through the vmapped path."""

    def fn(params, px, py):
        return {"v": jnp.sort(jnp.stack([px, py, params]))}

    samples = jnp.asarray(np.random.default_rng(1).uniform(0, 4, (8, 2)))

    def reference(params, s):
        return jax.vmap(lambda q: fn(params, q[0], q[1]))(s)

    with pytest.warns(UserWarning, match="backend='jax'"):
        out = map_samples(fn, jnp.float64(2.0), samples, jr.RenderSettings(backend="auto"), reference)
    np.testing.assert_allclose(out["v"], reference(jnp.float64(2.0), samples)["v"])
    with pytest.raises(Unsupported):
        map_samples(fn, jnp.float64(2.0), samples, jr.RenderSettings(backend="fused"), reference)
    assert resolve_backend("auto") == ("pallas" if jax.default_backend() == "gpu" else "fused")


def test_program_size_counts_shared_values_once_and_per_ray_values_per_element():
    """`lanes.program_size`: an equation that reads a per-ray value costs one lane
    operation per element of its result; one that reads only shared values (a stacked
    group's rows of parameters) costs one, whatever the number of rows; loop bodies
    count once, and a carry that meets a per-ray value is per ray."""
    from jaxrt.kernels.lanes import program_size

    def fn(rows, px):
        shared = jnp.sin(rows) * 2.0  # 2 equations on shared rows
        per_ray = jnp.cos(shared * px)  # 2 equations of len(rows) lanes

        def body(carry, row):
            return carry + row * px, None  # 2 equations, per ray through the carry

        total, _ = jax.lax.scan(body, jnp.zeros((), rows.dtype), rows)
        return jnp.sum(per_ray) + total  # the scan, a reduction and an add: 1 lane each

    for n in (4, 64):
        closed = jax.make_jaxpr(fn)(jnp.zeros(n), jnp.zeros(()))  # no weak types: no casts
        assert program_size(closed.jaxpr, [False, True]) == 2 + 2 * n + 2 + 3, n
        assert program_size(closed.jaxpr) == 4 * n + 2 + 3, n  # all inputs per ray
        # Unrolled (Pallas), the scan's body counts once per row ...
        assert program_size(closed.jaxpr, unrolled_scans=True) == 4 * n + 2 * n + 3, n
        # ... unless Pallas keeps it as a loop that loads its shared rows: once.
        loaded = program_size(closed.jaxpr, [False, True], unrolled_scans=True, loaded_scans=True)
        assert loaded == 2 + 2 * n + 2 + 3, n
        assert program_size(closed.jaxpr, unrolled_scans=True, loaded_scans=True) == \
            4 * n + 2 * n + 3, n  # rows that vary per ray cannot be loaded


def test_auto_counts_a_stacked_union_once_unless_pallas_unrolls_it(monkeypatch):
    """A stacked union is one scan: the "fused" count does not grow with its children,
    nor does the Pallas count while the kernel keeps the scan as a loop
    (`pallas_scan_loops`, default). Unrolled, the Pallas count grows with every child,
    and 128 spheres exceed "auto"'s Pallas limit (64 compiled in about a minute on an
    H100)."""
    from jaxrt.kernels import fused

    sizes = {}

    def spy(closed, backend, loops=False, nparams=None):
        sizes[backend, loops] = size = lane_ops(closed, backend, loops, nparams)
        return size

    lane_ops = fused._lane_ops
    monkeypatch.setattr(fused, "_lane_ops", spy)
    camera = jr.PerspectiveCamera(eye=(0.0, 3.0, -6.0), target=(0.0, 0.0, 0.0), width=4, height=4)
    counts = {}
    for n in (8, 128):
        spheres = [jr.sdf.Translate(jr.sdf.Sphere(0.3, material=0), offset=(0.7 * i, 0.3, 0.0))
                   for i in range(n)]
        scene = jr.Scene(jr.sdf.Union(*spheres, jr.sdf.Plane((0.0, 1.0, 0.0), 0.0, material=0)),
                         [jr.bsdf.Lambert(0.5)], [jr.PointLight((2.0, 6.0, -3.0), (9.0,) * 3)])
        for seed, (backend, loops) in enumerate((("fused", True), ("pallas", True),
                                                 ("pallas", False))):
            monkeypatch.setattr(fused, "resolve_backend", lambda b, to=backend: to)
            # a seed per variant: settings of their own, so the render is traced anew
            settings = jr.RenderSettings(backend="auto", max_depth=0, aovs=(), seed=seed,
                                         kernel=jr.KernelOptions(pallas_scan_loops=loops))
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # Pallas on a CPU falls back
                jax.eval_shape(lambda s, c: jr.render(s, c, settings).rgb, scene, camera)
            counts[n, backend, loops] = sizes[backend, loops and backend == "pallas"]
    limit = jr.RenderSettings().kernel.auto_max_lane_ops_pallas
    for variant in (("fused", True), ("pallas", True)):
        assert counts[(8, *variant)] == counts[(128, *variant)] < limit, counts
    per_child = (counts[128, "pallas", False] - counts[8, "pallas", False]) / 120
    assert per_child > 50, counts
    assert counts[8, "pallas", False] < limit < counts[128, "pallas", False], counts


def test_auto_backend_falls_back_for_programs_too_large_to_compile_quickly():
    """backend="auto" renders a program of more lane operations than
    settings.kernel.auto_max_lane_ops_<backend>
    (a batch of rays counts once per ray, as lanes unroll it) with the vmapped path."""
    from jaxrt.kernels.lanes import program_size

    def fn(params, px, py):
        v = jnp.stack([px, py, params]) * jnp.ones((4, 3))  # 12 lanes per operation
        return {"v": jnp.sum(jnp.sin(v) * v, axis=0)}

    closed = jax.make_jaxpr(fn)(jnp.float64(2.0), 0.0, 0.0)
    size = program_size(closed.jaxpr)
    assert size > 3 * 12, size
    samples = jnp.asarray(np.random.default_rng(1).uniform(0, 4, (8, 2)))

    def reference(params, s):
        return jax.vmap(lambda q: fn(params, q[0], q[1]))(s)

    backend = resolve_backend("auto")

    def settings_with_limit(limit):
        return jr.RenderSettings(backend="auto", kernel=jr.KernelOptions(
            **{f"auto_max_lane_ops_{backend}": limit}))

    settings = settings_with_limit(3 * 12)
    with pytest.warns(UserWarning, match="lane operations"):
        out = map_samples(fn, jnp.float64(2.0), samples, settings, reference)
    np.testing.assert_allclose(out["v"], reference(jnp.float64(2.0), samples)["v"])
    settings = settings_with_limit(10 * size)
    with warnings_as_errors():  # under the limit: the fused path, no warning
        out = map_samples(fn, jnp.float64(2.0), samples, settings, reference)
    np.testing.assert_allclose(out["v"], reference(jnp.float64(2.0), samples)["v"])


def test_store_is_exact_and_a_fusion_boundary_on_cpu():
    """lanes.control._materialise (how "fused" materialises shared lanes on XLA:CPU) returns its input
    bit for bit, and XLA computes a stored expression once: without the store, the
    shared chain is fused into (so recomputed in) each of 8 consumer outputs."""
    from jaxrt.kernels.lanes.control import _materialise as _store

    x = np.array([0.0, -0.0, 1.5, -np.inf, np.inf, np.nan, 1e-45, -3e38], np.float32)
    # as the library compiles (XLA's -O3; at -O0 the denormal is flushed to 0, as by any
    # arithmetic of XLA:CPU, which runs with denormals off)
    got = np.asarray(jax.jit(_store).lower(x).compile(
        compiler_options={"xla_backend_optimization_level": 3})(x))
    assert got.tobytes() == x.tobytes()
    i = np.array([np.iinfo(np.int32).min, -1, 0, 7], np.int32)
    assert np.array_equal(np.asarray(jax.jit(_store)(i)), i)
    b = np.array([True, False, True])
    assert np.array_equal(np.asarray(jax.jit(_store)(b)), b)

    def program(store):
        def f(v):
            for k in range(20):  # a chain of cheap ops (XLA duplicates these freely)
                v = jnp.maximum(v * 1.1 - 0.2, v * 0.7) + 0.01 * k
            v = store(v)
            return [v * k + jnp.abs(v - k) for k in range(8)]  # 8 separate outputs
        return f

    cpu = jax.devices("cpu")[0]
    v = jax.device_put(jnp.ones((64, 64), jnp.float32), cpu)
    counts = {}
    for name, store in (("none", lambda v: v), ("store", _store)):
        hlo = jax.jit(program(store)).lower(v).compile().as_text()
        counts[name] = hlo.count(" multiply(")
    assert counts["store"] <= 40 + 8 + 8, counts  # the chain once (2 per step), 8 outputs
    assert counts["none"] >= 4 * counts["store"], counts  # what the store prevents


def test_batched_while_steps_only_its_active_elements():
    """A while loop inside a vmap of the one-ray program (ray-tree levels, wavelengths)
    steps each element only while its own predicate holds, as vmap does: lanes used to
    step every element while any was active (a height field hit behind a glass sphere
    marched on past its crossing)."""

    def fn(params, px, py):
        def count(x):
            return jax.lax.while_loop(lambda s: s[0] < x, lambda s: (s[0] + 1.0, s[1] + 1), (0.0, 0))

        t, n = jax.vmap(count)(jnp.stack([px, py]) * params)
        return {"t": t, "n": n}

    samples = jnp.asarray(np.random.default_rng(1).uniform(0, 6, (8, 2)))

    def reference(params, s):
        return jax.vmap(lambda q: fn(params, q[0], q[1]))(s)

    out = map_samples(fn, jnp.float64(1.0), samples, jr.RenderSettings(backend="fused"), reference)
    want = reference(jnp.float64(1.0), samples)
    np.testing.assert_array_equal(out["n"], want["n"])
    np.testing.assert_array_equal(out["t"], want["t"])


def test_kernel_options_are_part_of_the_cache_key():
    """`RenderSettings.kernel` is static: after a render, changing an option changes the
    compiled program (no cache clearing). "auto" with a lane-operation limit of 1 falls
    back to "jax" (a warning) although the same scene was just rendered fused; and the
    fused program with unroll=2 lowers to other code than with unroll=1."""
    import equinox as eqx
    from jaxrt.render import _cast, _render

    scene = jr.Scene(surface=jr.sdf.Sphere(radius=1.0, material=0),
                     materials=[jr.bsdf.Lambert(albedo=(0.8, 0.3, 0.2))],
                     lights=[jr.DirectionalLight(direction=(0.3, 1.0, 0.5), irradiance=(1.0, 1.0, 1.0))])
    camera = jr.PerspectiveCamera(eye=(0.0, 0.0, 3.0), target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0),
                                  fov=45.0, width=6, height=4)
    base = jr.RenderSettings(backend="auto", batch_size=64, aovs=(), shadows="none", max_depth=0)
    with warnings_as_errors():
        first = jr.render(scene, camera, base)
    backend = resolve_backend("auto")
    tiny = base.replace(kernel=base.kernel.replace(**{f"auto_max_lane_ops_{backend}": 1}))
    with pytest.warns(UserWarning, match="auto_max_lane_ops"):
        again = jr.render(scene, camera, tiny)
    np.testing.assert_allclose(np.asarray(again.rgb), np.asarray(first.rgb), atol=1e-4)

    dyn, static = eqx.partition(_cast((scene, camera), jnp.float32), eqx.is_array)

    def lowered(settings):
        f = jax.jit(lambda d: _render.__wrapped__(*eqx.combine(d, static), settings))
        return f.trace(dyn).lower().as_text()

    fused = base.replace(backend="fused")
    assert lowered(fused) != lowered(fused.replace(kernel=jr.KernelOptions(unroll=2)))
    assert hash(fused) != hash(fused.replace(kernel=jr.KernelOptions(unroll=2)))


def test_kernel_options_are_validated_like_other_settings():
    """KernelOptions reject bad values with the field's name; a TOML table (a [settings]
    sub-table or `--set kernel={...}`) is read as KernelOptions and checked as such."""
    with pytest.raises(ValueError, match=r"RenderSettings.kernel.unroll = 0, expected"):
        jr.KernelOptions(unroll=0)
    with pytest.raises(ValueError, match=r"RenderSettings.kernel.pallas_block"):
        jr.RenderSettings(kernel={"pallas_block": 4})
    with pytest.raises(ValueError, match=r"RenderSettings.kernel.replay_gather = -1, expected"):
        jr.RenderSettings(kernel={"replay_gather": -1})
    with pytest.raises(ValueError, match=r"RenderSettings.kernel.speed"):
        jr.RenderSettings(kernel={"speed": 11})
    with pytest.raises(ValueError, match=r"RenderSettings.split"):
        jr.RenderSettings(split="diagonal")
    s = jr.RenderSettings(kernel={"unroll": 3, "pallas_fma": False})
    assert s.kernel == jr.KernelOptions(unroll=3, pallas_fma=False)
    assert jr.config.check_settings({"kernel": {"unroll": 2}}).kernel.unroll == 2
    from jaxrt.cli import parse_overrides

    over = parse_overrides(["kernel={unroll=2, pallas_fma=false}", "split=rows"])
    got = jr.config.check_settings(over, "--set")
    assert got.kernel == jr.KernelOptions(unroll=2, pallas_fma=False) and got.split == "rows"
    with pytest.raises(jr.config.ConfigError, match=r"settings.kernel.unroll = 0, expected"):
        jr.config.check_settings({"kernel": {"unroll": 0}}, "--set")
    text = jr.config_writer.dumps(jr.Scene(surface=jr.sdf.Sphere(radius=1.0, material=0),
                                           materials=[jr.bsdf.Lambert(albedo=(0.5, 0.5, 0.5))],
                                           lights=[]),
                                  jr.PerspectiveCamera(eye=(0.0, 0.0, 3.0), target=(0.0, 0.0, 0.0),
                                                       up=(0.0, 1.0, 0.0), fov=45.0, width=4,
                                                       height=4), settings=s)
    assert jr.config.loads(text)[2].kernel == s.kernel, text
