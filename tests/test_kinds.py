"""Scene size is data (jaxrt.kinds, jaxrt.bsdf.dispatch, lights scanned by kind): a
material taken from a stack is the material itself, dispatch by kind gives what each
material gives alone, and scenes that differ only in how many primitives, materials or
lights of one kind they hold trace programs of the same size (render and value_and_grad,
"jax" and "fused"), apart from a few data-movement equations per scene leaf."""

import collections

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrt as jr
from jaxrt import kinds
from jaxrt.bsdf.dispatch import dispatch
from jaxrt.kernels import lanes

S = jr.sdf


def test_take_is_indexing_and_its_gradient_reaches_the_member():
    rng = np.random.default_rng(0)
    members = [{"a": jnp.asarray(rng.normal(size=3)), "b": jnp.asarray(rng.normal())} for _ in range(5)]
    stacked = kinds.stack(members)
    for i in range(5):
        got = kinds.take(stacked, jnp.int32(i))
        np.testing.assert_array_equal(got["a"], members[i]["a"])
        np.testing.assert_array_equal(got["b"], members[i]["b"])
    g = jax.grad(lambda s: jnp.sum(kinds.take(s, jnp.int32(3))["a"] * 2.0))(stacked)
    want = np.zeros((5, 3))
    want[3] = 2.0
    np.testing.assert_array_equal(g["a"], want)
    np.testing.assert_array_equal(kinds.lookup([4, 4, 4], jnp.int32(1)), 4)
    np.testing.assert_array_equal(jax.vmap(lambda i: kinds.lookup([True, False, True], i))(jnp.arange(3)),
                                  [True, False, True])


def mixed_materials():
    ggx = lambda a, f0, c: jr.bsdf.CookTorrance(jr.bsdf.GGX(a), jr.bsdf.SchlickFresnel(f0), diffuse=c)  # noqa: E731
    return [jr.bsdf.Lambert(albedo=(0.8, 0.2, 0.1)), ggx(0.2, 0.04, (0.1, 0.5, 0.2)),
            jr.bsdf.Mirror(tint=(0.9, 0.8, 0.7)), jr.bsdf.Lambert(albedo=(0.1, 0.3, 0.9)),
            ggx(0.4, 0.08, (0.6, 0.6, 0.1)), jr.bsdf.Phong(kd=0.3, ks=0.4, q=12.0, ka=0.05),
            jr.bsdf.CookTorrance(jr.bsdf.Beckmann(0.3), jr.bsdf.SchlickFresnel(0.05)),
            jr.bsdf.Lambert(albedo=(0.5, 0.5, 0.5))]


def test_dispatch_is_each_material_alone():
    """Values (eval, ambient, base_color, the lit predicate's default) and gradients of
    dispatch by kind equal those of the material at the index, evaluated alone."""
    materials = mixed_materials()
    assert len(kinds.group_by_kind(materials)) == 5  # Lambert ×3, GGX ×2, Mirror, Phong, Beckmann
    wo = jnp.asarray([0.3, -0.2, 0.93])
    wo = wo / jnp.linalg.norm(wo)
    wi = jnp.asarray([-0.4, 0.1, 0.91])
    wi = wi / jnp.linalg.norm(wi)
    lit = lambda m: m.has_diffuse  # noqa: E731

    def f(ms, i):
        return (dispatch(ms, i, lambda m: m.eval(wo, wi), jnp.zeros(3), lit),
                dispatch(ms, i, lambda m: m.ambient()), dispatch(ms, i, lambda m: m.base_color()))

    got = jax.jit(jax.vmap(lambda i: f(materials, i)))(jnp.arange(len(materials)))
    for i, m in enumerate(materials):
        want = (m.eval(wo, wi) if m.has_diffuse else jnp.zeros(3), m.ambient(), m.base_color())
        for a, b in zip(got, want):
            np.testing.assert_allclose(a[i], b, rtol=1e-14, atol=1e-15)
    loss = lambda ms, i: jnp.sum(f(ms, i)[0])  # noqa: E731
    for i in (1, 4):
        g = jax.grad(loss)(materials, jnp.int32(i))
        g_alone = jax.grad(lambda m: jnp.sum(m.eval(wo, wi)))(materials[i])
        for a, b in zip(jax.tree_util.tree_leaves(g[i]), jax.tree_util.tree_leaves(g_alone)):
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-15)
        other = 4 if i == 1 else 1
        assert all(np.all(np.asarray(x) == 0) for x in jax.tree_util.tree_leaves(g[other]))


def test_lanes_scan_rule_rolled_and_unrolled():
    """lanes' scan rule (either jax's scan params) unrolled and, for the fused backend,
    as one loop (`roll_scans`), against vmap: carries of floats and bools, a per-ray
    and a uniform operand, a scanned input."""
    ys = jnp.arange(4.0)

    def f(x):
        (c, b), _ = jax.lax.scan(lambda c, y: ((c[0] * 0.5 + y * x, c[1] | (y > x)), None), (x, x > 2.0), ys)
        return c + b

    closed = jax.make_jaxpr(f)(1.0)
    x = jnp.linspace(0.0, 3.0, 8)
    arg = np.empty((), object)
    arg[()] = x
    for roll in (False, True):
        (out,) = lanes.eval_lanes(closed, [arg], 8, roll_scans=roll)
        np.testing.assert_allclose(lanes.stack_lanes(out, 8, x.dtype), jax.vmap(f)(x), rtol=1e-14)


# ------------------------------------------------------------------- program size


def _grid(n, material):
    k = int(np.ceil(np.sqrt(n)))
    return [S.Translate(S.Sphere(radius=0.5, material=material(i)), offset=((i % k) * 1.2, 0.5, (i // k) * 1.2))
            for i in range(n)]


def scene_with(primitives=8, materials=2, lights=1, kind="lambert"):
    """`primitives` spheres and a plane; `materials` materials of one kind (sphere i has
    material i mod (materials − 1), the plane the last); `lights` point lights."""
    rng = np.random.default_rng(2)

    def material():
        c = tuple(float(v) for v in rng.uniform(0.1, 0.9, 3))
        if kind == "lambert":
            return jr.bsdf.Lambert(albedo=c)
        return jr.bsdf.CookTorrance(jr.bsdf.GGX(float(rng.uniform(0.1, 0.5))), jr.bsdf.SchlickFresnel(0.04),
                                    diffuse=c)

    k = materials - 1
    surface = S.Union(*_grid(primitives, lambda i: i % k), S.Plane(normal=(0.0, 1.0, 0.0), offset=0.0, material=k))
    return jr.Scene(surface=surface, materials=[material() for _ in range(materials)],
                    lights=[jr.PointLight(position=(3.0 + j, 6.0, 4.0 - j), intensity=(30.0, 30.0, 30.0))
                            for j in range(lights)])


CAMERA = jr.PerspectiveCamera(eye=(0.0, 4.0, 8.0), target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0),
                              fov=45.0, width=4, height=3)
#: What `render` and its gradient do per leaf of the scene (a cast to the render dtype,
#: `stop_gradient` for the marching loops, the sum of a leaf's cotangents over the
#: sites that read it, zero cotangents; on the lane backends the replay's per-sample
#: copy of the leaf and the sum of its cotangent over the samples, `render._per_sample`;
#: a `stop_gradient` of the derivative's own custom JVP, `render.differentiable`): data
#: movement, not a copy of a program. At most `PER_LEAF_MAX` of them per leaf.
PER_LEAF = ("convert_element_type", "stop_gradient", "add_any", "broadcast_in_dim",
            "custom_jvp_call", "optimization_barrier", "reduce_sum")
PER_LEAF_MAX = 9


def histogram(jaxpr, counts=None):
    counts = collections.Counter() if counts is None else counts
    for eqn in jaxpr.eqns:
        counts[eqn.primitive.name] += 1
        for v in eqn.params.values():
            for j in v if isinstance(v, (tuple, list)) else (v,):
                if isinstance(j, jax.extend.core.ClosedJaxpr):
                    histogram(j.jaxpr, counts)
                elif isinstance(j, jax.extend.core.Jaxpr):
                    histogram(j, counts)
    return counts


def program_size(scene, backend, mode):
    """(equations apart from PER_LEAF ones, PER_LEAF equations, scene leaves). "auto"'s
    choice of march form (`plain_max_lane_ops`) follows a lane-operation count in which
    a stacked group's shared rows count once, so it is the same for 8 spheres and 72."""
    settings = jr.RenderSettings(backend=backend, batch_size=None)

    def image(s):
        return jr.render(s, CAMERA, settings).rgb

    f = image if mode == "render" else jax.grad(lambda s: jnp.mean(image(s) ** 2))
    counts = histogram(jax.make_jaxpr(f)(scene).jaxpr)
    per_leaf = sum(counts[k] for k in PER_LEAF)
    return sum(counts.values()) - per_leaf, per_leaf, len(jax.tree_util.tree_leaves(scene))


CASES = {
    "primitives": (dict(primitives=8), dict(primitives=72)),
    "lambert materials": (dict(materials=2), dict(materials=17)),
    "ggx materials": (dict(materials=2, kind="ggx"), dict(materials=17, kind="ggx")),
    "lights": (dict(lights=1), dict(lights=8)),
}


@pytest.mark.parametrize("mode", ["render", "grad"])
@pytest.mark.parametrize("backend", ["jax", pytest.param("fused", marks=pytest.mark.slow)])
@pytest.mark.parametrize("case", list(CASES))
def test_program_size_follows_kinds_not_counts(case, backend, mode):
    small, large = (scene_with(**kw) for kw in CASES[case])
    a, a_leaf, a_n = program_size(small, backend, mode)
    b, b_leaf, b_n = program_size(large, backend, mode)
    # The lane program of a gradient may differ by a fixed equation or two (how many
    # 0-d parameters lanes stack into their table), never by one per thing.
    assert abs(a - b) <= (0 if backend == "jax" else 2), (case, a, b)
    assert b_leaf - a_leaf <= PER_LEAF_MAX * (b_n - a_n), (case, a_leaf, b_leaf, a_n, b_n)
