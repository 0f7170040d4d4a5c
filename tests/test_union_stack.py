"""jaxrt.sdf.stack: a Union of many children of one kind is evaluated stacked (one copy
of the child program per kind). It must be the same function as the loop union (values,
materials, first child on ties, gradients with respect to every child), its traced
program must not grow with the number of children, and it must render the same through
the fused lane backend."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrt as jr
from jaxrt.sdf import stack

S = jr.sdf
LOOP = 10**9  # a threshold no group reaches: the loop union


def mixed_children():
    """Interleaved kinds: 10 spheres (material 0), 9 boxes, 8 twisted boxes (L > 1), 3
    spheres of material 1 (one group with the others), a plane (y = −2, a loop) and a repeated
    box (ties within a group). Exact ties between groups are in `test_ties_...`: here,
    where a child in the loop and one in the scan are at the same distance, the two
    paths may round it differently (by an ulp) and pick different materials."""
    rng = np.random.default_rng(3)
    out = []
    for i in range(10):
        out.append(S.Translate(S.Sphere(radius=0.2 + 0.3 * rng.uniform(), material=0),
                               offset=rng.uniform(-2.0, 2.0, 3)))
        if i < 9:
            out.append(S.Translate(S.Box(half_extents=rng.uniform(0.1, 0.5, 3), material=1),
                                   offset=rng.uniform(-2.0, 2.0, 3)))
        if i < 8:
            out.append(S.Twist(S.Box(half_extents=(0.3, 0.4, 0.3), material=2), rate=0.5 + rng.uniform()))
        if i < 3:
            out.append(S.Translate(S.Sphere(radius=0.3, material=1), offset=rng.uniform(-2.0, 2.0, 3)))
    out.append(S.Plane(normal=(0.0, 1.0, 0.0), offset=-2.0, material=3))
    out.append(out[1])
    return out


def points(n=200, seed=0):
    rng = np.random.default_rng(seed)
    p = rng.uniform(-2.5, 2.5, (n, 3))
    return jnp.asarray(p)


@eqx.filter_jit
def evaluate(union, p, threshold):
    return jax.vmap(lambda q: stack.union_eval(union.children_, q, threshold))(p)


def test_stacking_groups_children():
    groups = stack.group_by_structure(mixed_children())
    sizes = sorted(len(ix) for ix, _ in groups)
    # plane; twisted boxes; boxes (+ repeat); spheres of materials 0 and 1 (materials are
    # data in a group: children that differ only in their material are one kind)
    assert sizes == [1, 8, 10, 13]
    assert sum(len(ix) >= stack.STACK_THRESHOLD for ix, _ in groups) == 3


def test_stacked_union_is_the_loop_union():
    union = S.Union(*mixed_children())
    p = points()
    d, m = evaluate(union, p, None)
    d_loop, m_loop = evaluate(union, p, LOOP)
    np.testing.assert_allclose(d, d_loop, rtol=1e-14, atol=1e-14)
    np.testing.assert_array_equal(m, m_loop)
    # an independent reference: each child alone, the min, the first minimising child
    each = np.stack([jax.vmap(c)(p) for c in union.children_])
    first = np.argmin(each, axis=0)
    mats = np.stack([jax.vmap(c.eval)(p)[1] for c in union.children_])
    np.testing.assert_allclose(d, each.min(axis=0), rtol=1e-14, atol=1e-14)
    np.testing.assert_array_equal(m, mats[first, np.arange(len(p))])
    assert set(np.unique(np.asarray(m)).tolist()) == {0, 1, 2, 3}
    np.testing.assert_allclose(union.lipschitz(), stack.union_lipschitz(union.children_, LOOP),
                               rtol=1e-15)
    assert float(union.lipschitz()) > 1.0  # the twisted boxes


def test_ties_go_to_the_first_child():
    """Exact ties between children of different stacked groups: the material of the
    child that comes first in the list, in either order of the groups."""
    sphere = lambda x, m: S.Translate(S.Sphere(radius=0.4, material=m), offset=(x, 0.0, 0.0))  # noqa: E731
    children = [sphere(5.0, 1)] + [sphere(float(k), 0) for k in range(9)] + [sphere(float(k), 1) for k in range(8)]
    union = S.Union(*children)
    p = jnp.array([[3.0, 0.1, 0.0], [5.0, 0.1, 0.0], [8.0, 0.1, 0.0], [0.0, 0.5, 0.0]])
    each = np.stack([jax.vmap(c)(p) for c in children])
    assert np.all(np.sum(each[:, :2] == each.min(axis=0)[:2], axis=0) >= 2)  # real ties
    d, m = evaluate(union, p, None)
    np.testing.assert_array_equal(m, [0, 1, 0, 0])
    np.testing.assert_array_equal(m, evaluate(union, p, LOOP)[1])
    np.testing.assert_allclose(d, each.min(axis=0), rtol=1e-15)


def test_stacked_union_gradients_reach_every_child():
    """d/dθ of Σ_p f(p) w.r.t. every child's leaves, and ∇_p f (normals): equal to the
    loop's, and nonzero for every child that is nearest to some point."""
    union = S.Union(*mixed_children())
    p = points()

    @eqx.filter_jit
    def loss(u, threshold):
        return jnp.sum(jnp.sin(evaluate(u, p, threshold)[0]))

    g = eqx.filter_grad(loss)(union, None)
    g_loop = eqx.filter_grad(loss)(union, LOOP)
    for a, b in zip(jax.tree_util.tree_leaves(g), jax.tree_util.tree_leaves(g_loop)):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-14)
    nearest = set(np.asarray(jnp.argmin(jnp.stack([jax.vmap(c)(p) for c in union.children_]), axis=0)).tolist())
    assert len(nearest) > 20
    for i in nearest:
        assert any(np.any(np.asarray(x) != 0.0) for x in jax.tree_util.tree_leaves(g.children_[i]))

    @eqx.filter_jit
    def normals(threshold):
        return jax.vmap(jax.grad(lambda q: stack.union_eval(union.children_, q, threshold)[0]))(p)

    np.testing.assert_allclose(normals(None), normals(LOOP), rtol=1e-12, atol=1e-14)
    # finite differences in float64 for one child's radius
    r = lambda u: u.children_[4].child.radius  # noqa: E731
    h = 1e-6
    fd = (loss(eqx.tree_at(r, union, r(union) + h), None) - loss(eqx.tree_at(r, union, r(union) - h), None)) / (2 * h)
    np.testing.assert_allclose(g.children_[4].child.radius, fd, rtol=1e-6)


def test_prestacked_union_is_the_union():
    """`stack.prestack` (what `render` does at the top of its program): the same values,
    materials, Lipschitz bound and gradients (to every child's own leaves, through the
    stack) as the union, also for a union nested in a transform; one leaf per leaf of a
    group's structure instead of one per child; the plane stays a child of its own
    (`integrator.analytic_planes` still meets it)."""
    union = S.Union(*mixed_children())
    scene = S.Translate(S.Union(union, S.Sphere(radius=0.1, material=0)), offset=(0.1, 0.0, 0.0))
    p = points()

    @eqx.filter_jit
    def loss(s):
        d, m = jax.vmap(stack.prestack(s).eval)(p)
        return jnp.sum(jnp.sin(d)), m

    (value, m), g = eqx.filter_value_and_grad(loss, has_aux=True)(scene)
    (value_ref, m_ref), g_ref = eqx.filter_value_and_grad(
        lambda s: (lambda d, m: (jnp.sum(jnp.sin(d)), m))(*jax.vmap(s.eval)(p)), has_aux=True)(scene)
    np.testing.assert_allclose(value, value_ref, rtol=1e-15)
    np.testing.assert_array_equal(m, m_ref)
    for a, b in zip(jax.tree_util.tree_leaves(g), jax.tree_util.tree_leaves(g_ref)):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-14)
    pre = stack.prestack(union)
    assert isinstance(pre, stack.StackedUnion)
    np.testing.assert_allclose(pre.lipschitz(), union.lipschitz(), rtol=1e-15)
    assert pre.material_ids() == union.material_ids() == {0, 1, 2, 3}
    (plane,) = jr.integrator.analytic_planes(pre)
    assert eqx.tree_equal(plane, union.children_[-2])
    # leaves per kind, not per child: twice the children of each group, the same leaves
    kids = mixed_children()
    double = S.Union(*(kids[:-2] * 2 + kids[-2:]))
    assert len(jax.tree_util.tree_leaves(double)) > 2 * len(jax.tree_util.tree_leaves(union)) - 5
    assert len(jax.tree_util.tree_leaves(stack.prestack(double))) == \
        len(jax.tree_util.tree_leaves(pre)) == 12
    nested = stack.prestack(scene)
    assert isinstance(nested.child.children_[0], stack.StackedUnion)
    # a union of stacked unions that is stacked in turn: 8 grids of 8 spheres
    grid = lambda k: S.Translate(S.Union(*[S.Translate(S.Sphere(radius=0.2, material=j % 2), offset=(0.5 * j, 0.0, 0.0))  # noqa: E731
                                           for j in range(8)]), offset=(0.0, 0.0, 0.6 * k - 2.0))
    grids = S.Union(*[grid(k) for k in range(8)])
    pre = stack.prestack(grids)
    assert pre.stacked == (True,)
    d, m = jax.vmap(pre.eval)(p)
    d_ref, m_ref = jax.vmap(grids.eval)(p)
    np.testing.assert_allclose(d, d_ref, rtol=1e-15)
    np.testing.assert_array_equal(m, m_ref)


@pytest.mark.parametrize("backend", ["fused", pytest.param("jax", marks=pytest.mark.slow)])
def test_a_surface_stacked_ahead_renders_and_differentiates_as_its_unions(backend):
    """`sdf.stacked` (what a fit of many primitives differentiates): its render and the
    gradient of a loss of it are the union's, each stacked leaf's gradient the stack of
    the children's (rotated capsules in one group: their rotations under `vmap` in
    `with_matrices`); its leaves do not grow with the children; `unstacked` gives the
    union back, static materials and threshold included."""
    kids = [S.Translate(S.Rotate(S.Capsule(0.15 + 0.01 * i, 0.12, material=i % 2),
                                 axis=(0.2 * i, 1.0, 0.3), angle=12.0 * i + 20.0),
                        offset=(0.45 * i - 1.8, 0.25, 0.1 * i)) for i in range(9)]
    kids += [S.Translate(S.Sphere(0.2 + 0.02 * i, material=2), offset=(0.5 * i - 1.8, 0.8, 0.3))
             for i in range(8)]
    union = S.Union(*kids, S.Plane(normal=(0.0, 1.0, 0.0), offset=-0.1, material=1), stack_threshold=7)
    ahead = S.stacked(union)
    assert isinstance(ahead, stack.StackedUnion) and ahead.stacked.count(True) == 2
    twice = S.stacked(S.Union(*(kids * 2), union.children_[-1], stack_threshold=7))
    assert len(jax.tree_util.tree_leaves(twice)) == len(jax.tree_util.tree_leaves(ahead))
    back = S.unstacked(ahead)
    assert eqx.tree_equal(back, union)
    materials = [jr.bsdf.Lambert((0.7, 0.4, 0.3)), jr.bsdf.Lambert((0.5, 0.6, 0.7)),
                 jr.bsdf.Lambert((0.3, 0.7, 0.4))]
    light = [jr.PointLight((1.0, 4.0, 3.0), (30.0, 30.0, 30.0))]
    camera = jr.PerspectiveCamera(eye=(0.0, 1.5, 4.0), target=(0.0, 0.3, 0.0), fov=50.0, width=8, height=6)
    settings = jr.RenderSettings(dtype="float64", backend=backend, batch_size=16, shadows="hard")

    def loss(surface):
        image = jr.render(jr.Scene(surface, materials, light, background=0.1), camera, settings)
        return jnp.sum(image.rgb * jnp.linspace(0.5, 1.5, 3))

    value, grad = eqx.filter_value_and_grad(loss)(union)
    value_ahead, grad_ahead = eqx.filter_value_and_grad(loss)(ahead)
    np.testing.assert_allclose(value_ahead, value, rtol=1e-12)
    want = eqx.filter(S.stacked(grad), eqx.is_inexact_array)
    got = eqx.filter(grad_ahead, eqx.is_inexact_array)
    leaves = jax.tree_util.tree_leaves(want)
    assert max(np.abs(x).max() for x in leaves) > 0
    for a, b in zip(jax.tree_util.tree_leaves(got), leaves, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12)


def test_normals_of_a_stacked_group_of_boxes_have_finite_gradients():
    """The gradient of a loss of the normals (a second derivative: what a shaded
    render's gradient holds) through a stacked group of boxes is the loop union's, and
    finite at points inside one box: the scan's second derivative differentiates the
    value of `_box_like` and of its rule (JAX drops a custom JVP rule there), whose
    sqrt at 0 gave ∞ · 0 = NaN before their norms' arguments were guarded."""
    kids = [S.Translate(S.Box((0.25, 0.15, 0.2)), offset=(0.5 * i - 1.0, 0.2, 0.1)) for i in range(2)]
    p = jnp.asarray(np.random.default_rng(0).uniform((-1.35, 0.0, -0.15), (-0.15, 0.4, 0.35), (400, 3)))
    inside = jax.vmap(lambda q: S.Union(*kids).eval(q)[0])(p) < 0
    assert 20 < int(inside.sum()) < 380
    _assert_normal_loss_gradients_finite_and_equal(kids, p)


def _assert_normal_loss_gradients_finite_and_equal(kids, p):
    """The gradient, with respect to the children, of a loss of the normals ∇f at
    points `p` (a second derivative) through the union of `kids` stacked (groups of 2
    and more) is finite, not all zero, and the loop union's to 1e-12."""
    def gradient(threshold):
        def loss(union):
            surface = stack.prestack(union)
            normals = jax.vmap(jax.grad(lambda q: surface.eval(q)[0]))(p)
            return jnp.sum(normals * jnp.array([0.3, 0.5, 0.7]))

        return eqx.filter_jit(eqx.filter_grad(loss))(S.Union(*kids, stack_threshold=threshold))

    stacked, loop = (jax.tree_util.tree_leaves(gradient(t)) for t in (2, LOOP))
    assert all(np.all(np.isfinite(x)) for x in stacked)
    assert max(np.abs(x).max() for x in stacked) > 0
    for a, b in zip(stacked, loop, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12)


def test_normals_through_stacked_groups_have_finite_gradients_at_centres_and_axes():
    """A loss of normals through stacked groups of the round primitives, at the
    points where their norms vanish (centres, points on their axes, a torus's core
    circle) and around them: finite, and the loop union's gradient. `safe_norm`'s rule
    took |x| from `_guarded_sqrt`, a custom JVP whose rule the scan's second derivative
    drops: the chain rule of its value, sqrt'(0) = ∞ times a zero tangent, was NaN
    (`vecmath._sqrt_where`)."""
    kinds = {  # a shape, and points in its frame where a norm vanishes
        "sphere": (S.Sphere(0.3), [(0.0, 0.0, 0.0)]),
        "torus": (S.Torus(0.3, 0.1), [(0.0, 0.0, 0.0), (0.3, 0.0, 0.0), (0.0, 0.05, 0.0)]),
        "cone": (S.Cone(0.3, 0.4), [(0.0, 0.0, 0.0), (0.0, 0.2, 0.0), (0.0, -0.1, 0.0)]),
        "capsule": (S.Capsule(0.2, 0.1), [(0.0, 0.0, 0.0), (0.0, -0.3, 0.0)]),
        "cylinder": (S.Cylinder(0.2, 0.3), [(0.0, 0.0, 0.0), (0.0, 0.1, 0.0)]),
        "ellipsoid": (S.Ellipsoid((0.3, 0.2, 0.25)), [(0.0, 0.0, 0.0)]),
    }
    kids, points = [], []
    for k, (shape, special) in enumerate(kinds.values()):
        for offset in ((2.0 * k, 0.0, 0.0), (2.0 * k, 0.0, 1.5)):
            kids.append(S.Translate(shape, offset=offset))
            points += [np.add(offset, q) for q in special]
    points += list(np.random.default_rng(1).uniform((-0.5, -0.5, -0.5), (10.5, 0.5, 2.0), (40, 3)))
    _assert_normal_loss_gradients_finite_and_equal(kids, jnp.asarray(np.array(points)))


def spheres(n):
    k = int(np.ceil(np.sqrt(n)))
    return S.Union(*[S.Translate(S.Sphere(radius=0.5, material=0), offset=((i % k) * 1.2, 0.5, (i // k) * 1.2))
                     for i in range(n)], S.Plane(normal=(0.0, 1.0, 0.0), offset=0.0, material=1))


def n_equations(jaxpr, skip=()):
    """Equations of a jaxpr, counting those of inner jaxprs (loops, calls) too, except
    those of the primitives named in `skip`."""
    count = 0
    for eqn in jaxpr.eqns:
        count += eqn.primitive.name not in skip
        for v in eqn.params.values():
            for j in v if isinstance(v, (tuple, list)) else (v,):
                if isinstance(j, jax.extend.core.ClosedJaxpr):
                    count += n_equations(j.jaxpr, skip)
                elif isinstance(j, jax.extend.core.Jaxpr):
                    count += n_equations(j, skip)
    return count


def test_program_size_does_not_grow_with_children():
    """The traced program (its number of equations) of a union of 8 or 256 spheres is
    the same size; the loop union's grows with every child."""
    p = jnp.array([0.1, 0.2, 0.3])

    def size(union, threshold):
        f = lambda u, q: stack.union_eval(u.children_, q, threshold)  # noqa: E731
        return n_equations(jax.make_jaxpr(f)(union, p).jaxpr)

    stacked = [size(spheres(n), None) for n in (8, 64, 256)]
    assert stacked[0] == stacked[1] == stacked[2]
    loop = [size(spheres(n), LOOP) for n in (8, 64)]
    assert loop[1] - loop[0] >= 56 * 5
    # the render program too (trace only: no compilation), apart from what `render` does
    # to every leaf of the scene (a cast to the render dtype, `stop_gradient` for the
    # marching loop): per leaf, not per copy of a child program
    camera = jr.PerspectiveCamera(eye=(0.0, 4.0, 8.0), target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0),
                                  fov=45.0, width=4, height=4)

    def render_size(n):
        scene = jr.Scene(surface=spheres(n), materials=[jr.bsdf.Lambert(albedo=(0.8, 0.3, 0.2))] * 2,
                         lights=[jr.PointLight(position=(3.0, 6.0, 4.0), intensity=(60.0, 60.0, 60.0))])
        # backend "jax": the lane backends' programs still grow with the children
        # (per-lane slicing of the stacked parameters; tests/test_kinds.py, issue 12)
        settings = jr.RenderSettings(backend="jax")
        jaxpr = jax.make_jaxpr(lambda s: jr.render(s, camera, settings).rgb)(scene).jaxpr
        return n_equations(jaxpr, skip=("convert_element_type", "stop_gradient"))

    assert render_size(16) == render_size(128)


def test_parameter_change_does_not_retrace():
    traces = []

    @jax.jit
    def f(union, p):
        traces.append(1)
        return union.eval(p)

    union = spheres(16)
    p = jnp.array([0.0, 0.5, 0.0])
    d0, _ = f(union, p)
    radius = union.children_[0].child.radius
    moved = eqx.tree_at(lambda u: u.children_[0].child.radius, union, jnp.asarray(0.25, radius.dtype))
    d1, _ = f(moved, p)
    assert len(traces) == 1
    np.testing.assert_allclose([d0, d1], [-0.5, -0.25], rtol=1e-14)


def test_a_wide_union_is_the_scan():
    """`tape.wide_unions` (a GPU's replay): every stacked child evaluated at once and the
    first nearest taken, no scan left. The scan's distances, materials, gradients with
    respect to every child's leaves, and normals."""
    from jaxrt.march import tape

    union = S.Union(*mixed_children())
    p = points()

    def run(wide):
        def loss(u):
            return jnp.sum(jnp.sin(jax.vmap(lambda q: stack.union_eval(u.children_, q)[0])(p)))

        with tape.wide_unions(wide):  # new functions: traced in the context
            program = str(jax.make_jaxpr(lambda u: evaluate.__wrapped__(u, p, None))(union))
            d, m = jax.jit(lambda u: evaluate.__wrapped__(u, p, None))(union)
            g = jax.jit(jax.grad(loss))(union)
            n = jax.jit(lambda u: jax.vmap(jax.grad(lambda q: u.eval(q)[0]))(p))(union)
        return program, (d, m, g, n)

    (scan, want), (wide, got) = run(False), run(True)
    assert "scan" in scan and "scan" not in wide and "argmin" in wide
    for a, b in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-15)


def many_spheres_scene(stack_threshold=stack.STACK_THRESHOLD):
    rng = np.random.default_rng(5)
    children = [S.Translate(S.Sphere(radius=0.2 + 0.15 * rng.uniform(), material=0),
                            offset=(rng.uniform(-1.2, 1.2), 0.4, rng.uniform(-1.0, 0.2)))
                for i in range(8)]
    children += [S.Translate(S.Sphere(radius=0.25, material=1), offset=(x, 0.3, 0.6)) for x in (-0.6, 0.6)]
    surface = S.Union(*children, S.Plane(normal=(0.0, 1.0, 0.0), offset=0.0, material=2),
                      stack_threshold=stack_threshold)
    scene = jr.Scene(surface=surface,
                     materials=[jr.bsdf.Lambert(albedo=(0.8, 0.3, 0.2)),
                                jr.bsdf.Lambert(albedo=(0.2, 0.5, 0.8)),
                                jr.bsdf.Lambert(albedo=(0.6, 0.6, 0.6))],
                     lights=[jr.PointLight(position=(2.0, 4.0, 3.0), intensity=(30.0, 30.0, 30.0))],
                     background=(0.1, 0.1, 0.15))
    camera = jr.PerspectiveCamera(eye=(0.0, 1.8, 3.0), target=(0.0, 0.3, 0.0), up=(0.0, 1.0, 0.0),
                                  fov=50.0, width=10, height=6)
    return scene, camera


@pytest.mark.parametrize("backend", ["fused", "pallas"])
def test_stacked_union_renders_the_same_through_lanes(backend, monkeypatch):
    """8 spheres (stacked, scanned) + 2 spheres and a plane (a loop): the lane backends
    give the image of the loop union. Both keep the scan as a loop: "fused" over its
    lanes, Pallas (interpret mode on CPUs) loading each child's parameters
    (`lanes.control._scan_loaded`)."""
    from jaxrt.kernels.lanes import control

    loaded = []
    scan_loaded = control._scan_loaded
    monkeypatch.setattr(control, "_scan_loaded", lambda *a: loaded.append(1) or scan_loaded(*a))
    scene, camera = many_spheres_scene()
    settings = jr.RenderSettings(batch_size=16)
    got = jr.render(scene, camera, settings.replace(backend=backend))
    assert bool(loaded) == (backend == "pallas")
    loop_scene, _ = many_spheres_scene(stack_threshold=LOOP)
    want = jr.render(loop_scene, camera, settings)
    np.testing.assert_array_equal(np.asarray(got.coverage), np.asarray(want.coverage))
    np.testing.assert_allclose(np.asarray(got.rgb), np.asarray(want.rgb), atol=1e-4)
    np.testing.assert_allclose(np.asarray(got.depth), np.asarray(want.depth), rtol=1e-5, atol=1e-5)
    assert len(np.unique(np.asarray(want.albedo).reshape(-1, 3), axis=0)) >= 3  # all materials seen


def test_stack_threshold_is_a_static_field_of_the_union():
    """`Union(stack_threshold=...)` is part of the scene's structure (so of the jit cache
    key): the same children looped or stacked are different programs, with the same
    distances; it is validated and read from TOML."""
    children = [S.Translate(S.Sphere(radius=0.3, material=0), offset=(1.0 * i, 0.0, 0.0))
                for i in range(8)]
    stacked, looped = S.Union(*children), S.Union(*children, stack_threshold=LOOP)
    assert jax.tree_util.tree_structure(stacked) != jax.tree_util.tree_structure(looped)
    p = jnp.array([0.2, 0.1, -0.4])
    size = [len(jax.make_jaxpr(u.eval)(p).jaxpr.eqns) for u in (stacked, looped)]
    assert size[0] < size[1], size
    np.testing.assert_allclose(stacked.eval(p)[0], looped.eval(p)[0], rtol=1e-15)
    with pytest.raises(ValueError, match="stack_threshold"):
        S.Union(*children, stack_threshold=0)
    scene, _, _ = jr.config.loads("""
[camera]
eye = [0.0, 0.0, 3.0]
target = [0.0, 0.0, 0.0]
[materials.m]
type = "lambert"
albedo = [0.5, 0.5, 0.5]
[surface]
type = "union"
stack_threshold = 2
children = [{type = "sphere", material = "m"}, {type = "sphere", material = "m", radius = 0.5}]
""")
    assert scene.surface.stack_threshold == 2
