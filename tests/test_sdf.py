"""The shape language: primitives against independent closed forms, bounds against exact
distances, and combinations, placements and deformations against their definitions."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrt import sdf

from helpers import (
    batch,
    grad_norms,
    materials_of,
    quaternion_matrix,
    ref_box,
    ref_capsule,
    ref_cone,
    ref_cylinder,
    ref_ellipsoid,
    ref_plane,
    ref_round_box,
    ref_sphere,
    ref_torus,
    rotation_matrix,
    two_sphere_boolean,
    unit,
)

N = 1500


def points(seed, n=N, lo=-2.0, hi=2.0):
    return np.random.default_rng(seed).uniform(lo, hi, (n, 3))


# (node, plain distance function applied to a point, numpy reference)
EXACT = {
    "sphere": (sdf.Sphere(0.8), lambda p: sdf.sd_sphere(p, 0.8), lambda p: ref_sphere(p, 0.8)),
    "plane": (sdf.Plane((1.0, 2.0, -0.5), 0.3),
              lambda p: sdf.sd_plane(p, jnp.asarray(unit((1.0, 2.0, -0.5))), 0.3),
              lambda p: ref_plane(p, (1.0, 2.0, -0.5), 0.3)),
    "box": (sdf.Box((1.0, 0.5, 0.25)), lambda p: sdf.sd_box(p, jnp.array([1.0, 0.5, 0.25])),
            lambda p: ref_box(p, (1.0, 0.5, 0.25))),
    "round_box": (sdf.RoundBox((1.0, 0.6, 0.4), 0.15),
                  lambda p: sdf.sd_round_box(p, jnp.array([1.0, 0.6, 0.4]), 0.15),
                  lambda p: ref_round_box(p, (1.0, 0.6, 0.4), 0.15)),
    "torus": (sdf.Torus(1.0, 0.3), lambda p: sdf.sd_torus(p, 1.0, 0.3),
              lambda p: ref_torus(p, 1.0, 0.3)),
    "cone": (sdf.Cone(0.7, 1.3), lambda p: sdf.sd_cone(p, 0.7, 1.3),
             lambda p: ref_cone(p, 0.7, 1.3)),
    "flat_cone": (sdf.Cone(1.5, 0.4), lambda p: sdf.sd_cone(p, 1.5, 0.4),
                  lambda p: ref_cone(p, 1.5, 0.4)),
    "capsule": (sdf.Capsule(0.6, 0.3), lambda p: sdf.sd_capsule(p, 0.6, 0.3),
                lambda p: ref_capsule(p, 0.6, 0.3)),
    "cylinder": (sdf.Cylinder(0.5, 0.8), lambda p: sdf.sd_cylinder(p, 0.5, 0.8),
                 lambda p: ref_cylinder(p, 0.5, 0.8)),
}


@pytest.mark.parametrize("name", EXACT)
def test_exact_primitive_matches_closed_form(name):
    node, plain, ref = EXACT[name]
    p = points(1)
    # More points near and inside the shape, where sign and small distances matter most.
    p = np.concatenate([p, points(2, lo=-1.2, hi=1.2), points(3, lo=-0.6, hi=0.6)])
    expected = ref(p)
    np.testing.assert_allclose(batch(node)(p), expected, rtol=0, atol=1e-9)
    np.testing.assert_allclose(batch(plain)(p), expected, rtol=0, atol=1e-9)
    assert (expected < 0).mean() > 0.05 and (expected > 0).mean() > 0.3  # both sides sampled


@pytest.mark.parametrize("name", EXACT)
def test_exact_primitive_has_unit_gradient(name):
    """|∇f| = 1 almost everywhere (random points miss the medial axis and the centre)."""
    node = EXACT[name][0]
    p = points(3, n=500, lo=-1.5, hi=1.5)
    np.testing.assert_allclose(grad_norms(node, p), 1.0, atol=1e-9)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_the_cone_has_its_faces_normals_on_its_surface(dtype):
    """Points exactly on the cone (f = 0 in floating point: on the base, and on the side
    where r·h + (y − h)·R cancels exactly), as a hit that Newton polished onto the
    surface: ∇f is the face's outward unit normal, (0, −1, 0) on the base and
    (h x/r, R, h z/r)/√(R² + h²) on the side. (The sqrt of the squared distance has no
    derivative at 0: the gradient was zero there, and the pixel black.)"""
    radius, height = 0.5, 1.0
    node = sdf.Cone(radius, height)
    theta = np.linspace(0.0, 2.0 * np.pi, 7, endpoint=False)
    ring = np.stack([np.cos(theta), np.zeros_like(theta), np.sin(theta)], axis=-1)
    base = np.concatenate([[[0.0, 0.0, 0.0]], 0.25 * ring]).astype(dtype)
    base_normals = np.tile([0.0, -1.0, 0.0], (len(base), 1))
    axes = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    side = (0.25 * axes + [0.0, 0.5, 0.0]).astype(dtype)  # r = 0.25, y = 0.5
    side_normals = (height * axes + [0.0, radius, 0.0]) / np.hypot(radius, height)
    for p, normals in ((base, base_normals), (side, side_normals)):
        p = jnp.asarray(p, dtype)
        assert np.all(np.asarray(jax.vmap(node)(p)) == 0.0)
        grads = np.asarray(jax.vmap(jax.grad(node))(p))
        np.testing.assert_allclose(grads, normals, atol=1e-6 if dtype == jnp.float32 else 1e-12)


@pytest.mark.parametrize("radii", [(1.0, 0.5, 0.25), (0.3, 2.0, 0.8), (1.0, 1.0, 1.0)])
def test_ellipsoid_is_a_bound_and_exact_on_the_surface(radii):
    node = sdf.Ellipsoid(radii)
    r = np.asarray(radii)
    p = np.concatenate([points(4, n=1000, lo=-2.5, hi=2.5), points(5, n=1000, lo=-1.0, hi=1.0) * r])
    f, exact = batch(node)(p), ref_ellipsoid(p, radii)
    assert np.all(np.abs(f) <= np.abs(exact) + 1e-12)
    assert np.all(np.sign(f) == np.sign(exact))
    # Zero on the surface, and exact at the centre and on the longest semi-axis.
    s = unit(np.random.default_rng(6).normal(size=(200, 3))) * r
    np.testing.assert_allclose(batch(node)(s), 0.0, atol=1e-12)
    assert float(node(jnp.zeros(3))) == pytest.approx(-r.min(), abs=1e-12)
    i = int(np.argmax(r))
    far = np.zeros((1, 3))
    far[0, i] = 2.0 * r[i]
    np.testing.assert_allclose(batch(node)(far), [r[i]], atol=1e-12)
    if len(set(radii)) == 1:  # a sphere: exact everywhere
        np.testing.assert_allclose(f, ref_sphere(p, radii[0]), atol=1e-9)


# -- combinations ------------------------------------------------------------------

C1, R1 = np.array([0.0, 0.0, 0.0]), 1.0
C2, R2 = np.array([0.9, 0.4, -0.2]), 0.7


def two_balls():
    return (sdf.Translate(sdf.Sphere(R1, material=1), C1),
            sdf.Translate(sdf.Sphere(R2, material=2), C2))


@pytest.mark.parametrize("op", ["union", "intersection", "subtraction"])
def test_sharp_combinations_are_bounds_of_the_exact_distance(op):
    a, b = two_balls()
    node = {"union": sdf.Union(a, b), "intersection": sdf.Intersection(a, b),
            "subtraction": sdf.Subtraction(a, b)}[op]
    p = points(7, n=3000, lo=-2.0, hi=2.0)
    f, exact = batch(node)(p), two_sphere_boolean(p, C1, R1, C2, R2, op)
    assert np.all(np.abs(f) <= np.abs(exact) + 1e-12)
    away = np.abs(exact) > 1e-9
    assert np.all(np.sign(f[away]) == np.sign(exact[away]))
    if op == "union":  # min of exact distances is exact outside
        out = exact > 0
        np.testing.assert_allclose(f[out], exact[out], atol=1e-12)


def test_sharp_combinations_follow_their_definitions():
    a, b = two_balls()
    c = sdf.Box((0.5, 0.5, 0.5), material=3)
    p = points(8)
    fa, fb, fc = batch(a)(p), batch(b)(p), batch(c)(p)
    np.testing.assert_array_equal(batch(sdf.Union(a, b, c))(p), np.minimum(np.minimum(fa, fb), fc))
    np.testing.assert_array_equal(batch(sdf.Intersection(a, b, c))(p), np.maximum(np.maximum(fa, fb), fc))
    np.testing.assert_array_equal(batch(sdf.Subtraction(a, b))(p), np.maximum(fa, -fb))
    np.testing.assert_array_equal(batch(sdf.Union(a))(p), fa)
    for fn, expected in ((sdf.op_union, np.minimum(fa, fb)), (sdf.op_intersection, np.maximum(fa, fb)),
                         (sdf.op_subtraction, np.maximum(fa, -fb))):
        np.testing.assert_array_equal(np.asarray(fn(jnp.asarray(fa), jnp.asarray(fb))), expected)


@pytest.mark.parametrize("k", [0.05, 0.3, 1.0])
def test_smooth_combinations(k):
    a, b = two_balls()
    p = points(9, n=3000)
    fa, fb = batch(a)(p), batch(b)(p)
    cases = [
        # node, sharp value, |argument gap|, sign: +1 if the blend lies below the sharp value
        (sdf.SmoothUnion(a, b, k), np.minimum(fa, fb), np.abs(fa - fb), +1),
        (sdf.SmoothIntersection(a, b, k), np.maximum(fa, fb), np.abs(fa - fb), -1),
        (sdf.SmoothSubtraction(a, b, k), np.maximum(fa, -fb), np.abs(fa + fb), -1),
    ]
    for node, sharp, gap, below in cases:
        f = batch(node)(p)
        far = gap >= k
        assert far.any() and (~far).any()
        np.testing.assert_allclose(f[far], sharp[far], atol=1e-12)
        # Within the band: on the blended side of the sharp value, by at most k/4.
        blend = below * (sharp - f)
        assert np.all(blend >= -1e-12) and np.all(blend <= k / 4 + 1e-12)
        assert np.max(blend) > 0.0
        # |∇f| ≤ 1: the blend is still a distance bound.
        assert np.max(grad_norms(node, p)) <= 1.0 + 1e-9
    plain = (sdf.op_smooth_union, sdf.op_smooth_intersection, sdf.op_smooth_subtraction)
    for fn, (node, _, _, _) in zip(plain, cases):
        np.testing.assert_allclose(np.asarray(fn(jnp.asarray(fa), jnp.asarray(fb), k)),
                                   batch(node)(p), atol=1e-12)


def test_smooth_combinations_with_k_zero_are_sharp():
    """k = 0 gives the sharp min/max of the children, to the rounding of the children's
    distances: those are computed in another program than fa, fb, and XLA may round the
    two programs differently in the last bits (it does with `xla_backend_optimization_level=1`)."""
    a, b = two_balls()
    p = points(10, n=500)
    fa, fb = batch(a)(p), batch(b)(p)
    np.testing.assert_allclose(batch(sdf.SmoothUnion(a, b, 0.0))(p), np.minimum(fa, fb),
                               rtol=0, atol=1e-14)
    np.testing.assert_allclose(batch(sdf.SmoothSubtraction(a, b, 0.0))(p), np.maximum(fa, -fb),
                               rtol=0, atol=1e-14)


# -- placement ---------------------------------------------------------------------

BOX_H = (0.9, 0.4, 0.2)  # an asymmetric box: any wrong rotation shows


def test_translate():
    node = sdf.Translate(sdf.Box(BOX_H), (0.3, -1.0, 2.0))
    p = points(11)
    np.testing.assert_allclose(batch(node)(p), ref_box(p - [0.3, -1.0, 2.0], BOX_H), atol=1e-12)


@pytest.mark.parametrize("axis,angle", [((0, 0, 1), 90.0), ((1, 2, 3), 37.0), ((0, 1, 0), -120.0)])
def test_rotate_axis_angle_is_right_handed_and_preserves_distance(axis, angle):
    node = sdf.Rotate(sdf.Box(BOX_H), axis=axis, angle=angle)
    r = rotation_matrix(axis, angle)
    p = points(12)
    # The shape moves by R: its distance at p is the box's at Rᵀ p (row vectors: p R).
    np.testing.assert_allclose(batch(node)(p), ref_box(p @ r, BOX_H), atol=1e-12)
    np.testing.assert_allclose(grad_norms(node, p[:300]), 1.0, atol=1e-9)
    # Right-handed: a quarter turn about z takes +x to +y.
    quarter = sdf.Rotate(sdf.Translate(sdf.Sphere(0.1), (1.0, 0.0, 0.0)), axis=(0, 0, 1), angle=90.0)
    assert float(quarter(jnp.array([0.0, 1.0, 0.0]))) == pytest.approx(-0.1, abs=1e-12)


@pytest.mark.parametrize("q", [(0.9, 0.1, -0.3, 0.2), (-0.5, 0.5, 0.5, -0.5), (1.0, 0.0, 0.0, 0.0),
                               (0.0, 0.0, 1.0, 0.0)])
def test_rotate_quaternion_agrees_with_matrix_and_axis_angle(q):
    node = sdf.Rotate(sdf.Box(BOX_H), quaternion=q)
    p = points(13, n=500)
    np.testing.assert_allclose(batch(node)(p), ref_box(p @ quaternion_matrix(q), BOX_H), atol=1e-12)
    # The same rotation as axis–angle: q = (cos θ/2, sin θ/2 · axis).
    q = np.asarray(q) / np.linalg.norm(q)
    angle = 2.0 * np.degrees(np.arctan2(np.linalg.norm(q[1:]), q[0]))
    axis = q[1:] if np.linalg.norm(q[1:]) > 0 else (0.0, 1.0, 0.0)
    np.testing.assert_allclose(batch(sdf.Rotate(sdf.Box(BOX_H), axis=axis, angle=angle))(p),
                               batch(node)(p), atol=1e-12)


def test_rotations_with_their_matrices_computed_ahead_are_the_same_function():
    """`domain.with_matrices` (what a render does at the top of its program): nested
    rotations, one inside a union, keep their values, materials, bounding balls and
    gradients with respect to axis and angle (float64)."""
    from jaxrt.sdf.domain import with_matrices

    inner = sdf.Rotate(sdf.Box(BOX_H, material=1), (1.0, 2.0, 3.0), 37.0)
    surface = sdf.Union(sdf.Rotate(sdf.Translate(inner, (0.5, 0.0, 0.2)), (0.0, 1.0, 0.0), -70.0),
                        sdf.Sphere(0.3))
    ahead = with_matrices(surface)

    def kinds(node):
        return [type(node).__name__] + [k for c in node.children() for k in kinds(c)]
    assert kinds(ahead) == ["Union", "Rotated", "Translate", "Rotated", "Box", "Sphere"]
    p = jnp.asarray(points(15, n=400))
    (d0, m0), (d1, m1) = jax.vmap(surface.eval)(p), jax.vmap(ahead.eval)(p)
    np.testing.assert_allclose(d1, d0, rtol=1e-14, atol=1e-14)
    np.testing.assert_array_equal(m1, m0)
    for b0, b1 in zip(surface.children_[0].bounding_ball(), ahead.children_[0].bounding_ball()):
        np.testing.assert_allclose(b1, b0, rtol=1e-14, atol=1e-14)

    def loss(node, prepare):
        node = with_matrices(node) if prepare else node
        return jnp.sum(jnp.sin(jax.vmap(node.eval)(p)[0]))
    g0, g1 = jax.grad(loss)(surface, False), jax.grad(loss)(surface, True)
    for a, b in zip(jax.tree_util.tree_leaves(g0), jax.tree_util.tree_leaves(g1)):
        np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-14)
    assert np.abs(g0.children_[0].angle) > 1e-3 and np.abs(g0.children_[0].child.child.axis).max() > 1e-3


def test_transform_agrees_with_rotate_then_translate():
    axis, angle, t = (0.3, -1.0, 0.5), 64.0, (0.5, 0.2, -0.7)
    child = sdf.Box(BOX_H)
    node = sdf.Transform(child, rotation=rotation_matrix(axis, angle), translation=t)
    p = points(14)
    np.testing.assert_allclose(batch(node)(p),
                               batch(sdf.Translate(sdf.Rotate(child, axis, angle), t))(p), atol=1e-12)
    np.testing.assert_allclose(batch(node)(p), ref_box((p - t) @ rotation_matrix(axis, angle), BOX_H),
                               atol=1e-12)


@pytest.mark.parametrize("rotation", [np.diag([1.0, 1.0, -1.0]), 2.0 * np.eye(3),
                                      np.array([[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])])
def test_transform_rejects_matrices_that_are_not_rotations(rotation):
    with pytest.raises(ValueError, match="Transform\\(rotation"):
        sdf.Transform(sdf.Sphere(), rotation=rotation)


@pytest.mark.parametrize("s", [0.25, 1.0, 3.5])
def test_scale_keeps_exact_distances_exact(s):
    p = points(15, lo=-3, hi=3)
    np.testing.assert_allclose(batch(sdf.Scale(sdf.Box(BOX_H), s))(p), ref_box(p, np.multiply(BOX_H, s)),
                               atol=1e-12)
    np.testing.assert_allclose(batch(sdf.Scale(sdf.Torus(1.0, 0.3), s))(p), ref_torus(p, s, 0.3 * s),
                               atol=1e-12)
    np.testing.assert_allclose(grad_norms(sdf.Scale(sdf.Torus(1.0, 0.3), s), p[:300]), 1.0, atol=1e-9)


def test_infinite_repetition_is_periodic_and_exact_for_a_small_child():
    period = np.array([1.0, 0.0, 1.5])  # no repetition along y
    node = sdf.Repeat(sdf.Sphere(0.3), period=period)
    p = points(16, lo=-5, hi=5)
    f = batch(node)(p)
    for shift in ([1.0, 0.0, 0.0], [0.0, 0.0, 1.5], [-3.0, 0.0, 4.5]):
        np.testing.assert_allclose(batch(node)(p + shift), f, atol=1e-12)
    # Distance to the nearest of all copies (brute force over a window of copies).
    ks = np.arange(-8, 9)
    centres = np.array([[i, 0.0, k] for i in ks for k in ks]) * period
    brute = np.min(np.linalg.norm(p[:, None, :] - centres[None], axis=2), axis=1) - 0.3
    np.testing.assert_allclose(f, brute, atol=1e-12)


def test_finite_repetition_stops_after_count_copies():
    period, count = np.array([1.0, 0.0, 2.0]), (2, 0, 1)
    node = sdf.Repeat(sdf.Sphere(0.3), period=period, count=count)
    copies = np.array([[i, 0.0, k] for i in range(-2, 3) for k in range(-1, 2)]) * period
    p = points(17, lo=-6, hi=6)
    brute = np.min(np.linalg.norm(p[:, None, :] - copies[None], axis=2), axis=1) - 0.3
    np.testing.assert_allclose(batch(node)(p), brute, atol=1e-12)
    # Copies at ±2 periods along x and ±1 along z; none beyond.
    at = lambda x, z: float(node(jnp.array([x, 0.0, z])))  # noqa: E731
    assert at(2.0, 0.0) == pytest.approx(-0.3) and at(-2.0, 2.0) == pytest.approx(-0.3)
    assert at(3.0, 0.0) == pytest.approx(0.7) and at(0.0, 4.0) == pytest.approx(1.7)


# -- deformations ------------------------------------------------------------------


def test_displace_is_child_plus_amplitude_times_function():
    g = sdf.SineDisplacement(4.0)
    node = sdf.Displace(sdf.Sphere(1.0), g, amplitude=0.3)
    p = points(18)
    expected = ref_sphere(p, 1.0) + 0.3 * np.prod(np.sin(4.0 * p), axis=1)
    np.testing.assert_allclose(batch(node)(p), expected, atol=1e-12)
    custom = sdf.Displace(sdf.Sphere(1.0), lambda q: jnp.sin(q[0]), amplitude=-0.5, lipschitz=1.0)
    np.testing.assert_allclose(batch(custom)(p), ref_sphere(p, 1.0) - 0.5 * np.sin(p[:, 0]), atol=1e-12)
    assert float(custom.lipschitz()) == pytest.approx(1.5)


def test_sine_displacement_lipschitz_bound_is_tight():
    w = 3.0
    g = sdf.SineDisplacement(w)
    p = points(19, n=4000, lo=-3, hi=3)
    assert np.max(grad_norms(g, p)) <= float(g.lipschitz()) + 1e-12
    peak = jnp.array([0.0, np.pi / (2 * w), np.pi / (2 * w)])
    assert float(jnp.linalg.norm(jax.grad(g)(peak))) == pytest.approx(float(g.lipschitz()), rel=1e-12)


def test_twist_and_bend_follow_their_definitions():
    k = 1.3
    p = points(20)
    twist = sdf.Twist(sdf.Box(BOX_H), rate=k)
    # The box turned about +y by k·y (right-handed): the child sees Rᵀ p.
    expected = [ref_box((rotation_matrix((0, 1, 0), np.degrees(k * y)).T @ q)[None], BOX_H)[0]
                for q, y in zip(p, p[:, 1])]
    np.testing.assert_allclose(batch(twist)(p), expected, atol=1e-12)
    bend = sdf.Bend(sdf.Box(BOX_H), rate=k)
    # The child is evaluated at p turned about +z by k·x.
    expected = [ref_box((rotation_matrix((0, 0, 1), np.degrees(k * x)) @ q)[None], BOX_H)[0]
                for q, x in zip(p, p[:, 0])]
    np.testing.assert_allclose(batch(bend)(p), expected, atol=1e-12)


def _max_gradient_over_planes(make, p, seed):
    """max |∇f| of make(Plane(n)) over points p and random plane normals n: planes have
    |∇child| = 1 in every direction, so this probes the Jacobian's spectral norm."""
    normals = unit(np.random.default_rng(seed).normal(size=p.shape))

    @jax.jit
    def worst(p, normals):
        def norm(q, n):
            return jnp.linalg.norm(jax.grad(lambda x: make(sdf.Plane(n, 0.1))(x))(q))

        return jnp.max(jax.vmap(norm)(p, normals))

    return float(worst(jnp.asarray(p), jnp.asarray(normals)))


@pytest.mark.parametrize("rate", [0.5, 2.0, -4.0])
def test_deformation_lipschitz_factor_bounds_the_gradient(rate):
    radius = 0.8
    rng = np.random.default_rng(21)
    p = rng.uniform(-1, 1, (6000, 3)) * [radius, 2.0, radius]
    p_twist = p[np.hypot(p[:, 0], p[:, 2]) <= radius]
    q = rng.uniform(-1, 1, (6000, 3)) * [radius, radius, 2.0]
    p_bend = q[np.hypot(q[:, 0], q[:, 1]) <= radius]
    for make, pts in ((lambda c: sdf.Twist(c, rate, radius), p_twist),
                      (lambda c: sdf.Bend(c, rate, radius), p_bend)):
        lipschitz = float(make(sdf.Sphere()).lipschitz())
        worst = _max_gradient_over_planes(make, pts, 22)
        assert worst <= lipschitz * (1 + 1e-9)
        assert worst >= 0.9 * lipschitz  # and the factor is not needlessly loose
        # Box children, and the factor composes with the child's.
        box = make(sdf.Box(BOX_H))
        assert np.max(grad_norms(box, pts)) <= lipschitz * (1 + 1e-9)
    displaced = sdf.Displace(sdf.Twist(sdf.Box(BOX_H), rate, radius), sdf.SineDisplacement(5.0), 0.2)
    expected = float(sdf.Twist(sdf.Box(BOX_H), rate, radius).lipschitz()) + 0.2 * 5.0
    assert float(displaced.lipschitz()) == pytest.approx(expected)
    assert np.max(grad_norms(displaced, p_twist)) <= expected * (1 + 1e-9)


def test_lipschitz_of_combinations_and_placements_is_that_of_the_worst_child():
    twist = sdf.Twist(sdf.Sphere(), 3.0, 1.0)
    lt = float(twist.lipschitz())
    assert lt > 1.0
    for node in (sdf.Union(sdf.Sphere(), twist), sdf.Intersection(twist, sdf.Box()),
                 sdf.Subtraction(sdf.Sphere(), twist), sdf.SmoothUnion(twist, sdf.Sphere(), 0.2),
                 sdf.Translate(twist, (1.0, 0.0, 0.0)), sdf.Rotate(twist, (1, 0, 0), 30.0),
                 sdf.Scale(twist, 2.0), sdf.Repeat(twist, (4.0, 4.0, 4.0))):
        assert float(node.lipschitz()) == pytest.approx(lt)
    assert float(sdf.Union(sdf.Sphere(), sdf.Box()).lipschitz()) == 1.0


# -- materials ---------------------------------------------------------------------


def test_materials_propagate_through_every_node():
    wrap = [
        lambda c: sdf.Translate(c, (0.1, 0.0, 0.0)),
        lambda c: sdf.Rotate(c, (0, 1, 0), 30.0),
        lambda c: sdf.Rotate(c, quaternion=(0.9, 0.1, 0.2, 0.3)),
        lambda c: sdf.Transform(c, rotation_matrix((1, 0, 0), 20.0), (0.0, 0.1, 0.0)),
        lambda c: sdf.Scale(c, 1.5),
        lambda c: sdf.Repeat(c, (3.0, 0.0, 3.0)),
        lambda c: sdf.Repeat(c, (3.0, 0.0, 3.0), count=1),
        lambda c: sdf.Displace(c, amplitude=0.05),
        lambda c: sdf.Twist(c, 0.5),
        lambda c: sdf.Bend(c, 0.5),
    ]
    p = points(23, n=200)
    for w in wrap:
        node = w(sdf.Sphere(0.5, material=4))
        assert node.material_ids() == {4}
        assert np.all(materials_of(node, p) == 4)
    # Combinations: the active operand's material, also below wrappers.
    a, b = two_balls()  # materials 1 and 2
    p = points(24, n=2000)
    fa, fb = batch(a)(p), batch(b)(p)
    combos = [
        (sdf.Union(a, b), np.where(fb < fa, 2, 1)),
        (sdf.Intersection(a, b), np.where(fb > fa, 2, 1)),
        (sdf.Subtraction(a, b), np.where(-fb > fa, 2, 1)),
        (sdf.SmoothUnion(a, b, 0.3), np.where(fb < fa, 2, 1)),
        (sdf.SmoothIntersection(a, b, 0.3), np.where(fb > fa, 2, 1)),
        (sdf.SmoothSubtraction(a, b, 0.3), np.where(-fb > fa, 2, 1)),
    ]
    for node, expected in combos:
        assert node.material_ids() == {1, 2}
        np.testing.assert_array_equal(materials_of(node, p), expected)
        for w in wrap[:1] + wrap[4:5]:
            assert w(node).material_ids() == {1, 2}
    nested = sdf.Union(sdf.Twist(sdf.Union(a, sdf.Box(material=7)), 0.1), sdf.Scale(b, 1.0))
    assert nested.material_ids() == {1, 2, 7}
    # On the surface carved out by b, a subtraction shows b's material.
    cut = C2 - R2 * unit(C2 - C1)  # the point of sphere 2 deepest inside ball 1
    assert int(sdf.Subtraction(a, b).eval(jnp.asarray(cut))[1]) == 2


# -- gradients with respect to parameters stay finite at degenerate points -----------


@pytest.mark.parametrize("name", list(EXACT) + ["ellipsoid"])
def test_values_and_gradients_are_finite_at_degenerate_points(name):
    node = EXACT[name][0] if name in EXACT else sdf.Ellipsoid((1.0, 0.5, 0.3))
    special = jnp.array([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0],
                         [0.0, 1.3, 0.0], [0.0, 0.8, 0.0], [1.0, 0.5, 0.25], [0.0, 0.4, 0.0]])

    def f(node, q):
        return node(q)

    @eqx.filter_jit
    def evaluate(node):
        values = jax.vmap(lambda q: f(node, q))(special)
        dp = jax.vmap(jax.grad(lambda q: f(node, q)))(special)
        dnode = jax.vmap(lambda q: jax.grad(f)(node, q))(special)
        return values, dp, dnode

    values, dp, dnode = evaluate(node)
    for leaf in [values, dp] + jax.tree_util.tree_leaves(dnode):
        assert np.all(np.isfinite(np.asarray(leaf)))


# -- constructors ------------------------------------------------------------------

BAD = [
    (lambda: sdf.Sphere(-1.0), "Sphere(radius"),
    (lambda: sdf.Sphere(float("nan")), "Sphere(radius"),
    (lambda: sdf.Sphere(1.0, material=-1), "Sphere(material"),
    (lambda: sdf.Sphere(1.0, material=1.5), "Sphere(material"),
    (lambda: sdf.Box((1.0, 0.0, 1.0)), "Box(half_extents"),
    (lambda: sdf.Box((1.0, 1.0)), "Box(half_extents"),
    (lambda: sdf.RoundBox((1.0, 1.0, 0.1), 0.2), "RoundBox(radius"),
    (lambda: sdf.Torus(1.0, -0.1), "Torus(minor_radius"),
    (lambda: sdf.Cone(0.0, 1.0), "Cone(radius"),
    (lambda: sdf.Cone(1.0, -1.0), "Cone(height"),
    (lambda: sdf.Capsule(-0.5, 0.2), "Capsule(half_height"),
    (lambda: sdf.Cylinder(0.5, 0.0), "Cylinder(half_height"),
    (lambda: sdf.Ellipsoid((1.0, -1.0, 1.0)), "Ellipsoid(radii"),
    (lambda: sdf.Plane((0.0, 0.0, 0.0)), "Plane(normal"),
    (lambda: sdf.Plane((0.0, 1.0, 0.0), float("inf")), "Plane(offset"),
    (lambda: sdf.Union(), "Union"),
    (lambda: sdf.Union(sdf.Sphere(), 1.0), "Union(children[1]"),
    (lambda: sdf.Subtraction(sdf.Sphere(), "b"), "Subtraction(b"),
    (lambda: sdf.SmoothUnion(sdf.Sphere(), sdf.Box(), k=-0.1), "SmoothUnion(k"),
    (lambda: sdf.Translate(sdf.Sphere(), (1.0, 2.0)), "Translate(offset"),
    (lambda: sdf.Rotate(sdf.Sphere(), axis=(0.0, 0.0, 0.0), angle=10.0), "Rotate(axis"),
    (lambda: sdf.Rotate(sdf.Sphere(), quaternion=(0.0, 0.0, 0.0, 0.0)), "Rotate(quaternion"),
    (lambda: sdf.Scale(sdf.Sphere(), 0.0), "Scale(factor"),
    (lambda: sdf.Repeat(sdf.Sphere(), (1.0, -1.0, 1.0)), "Repeat(period"),
    (lambda: sdf.Repeat(sdf.Sphere(), (1.0, 1.0, 1.0), count=-1), "Repeat(count"),
    (lambda: sdf.Twist(sdf.Sphere(), 1.0, radius=0.0), "Twist(radius"),
    (lambda: sdf.Bend(sdf.Sphere(), 1.0, radius=-1.0), "Bend(radius"),
    (lambda: sdf.Displace(sdf.Sphere(), lambda p: p[0]), "Displace(lipschitz"),
    (lambda: sdf.Displace(sdf.Sphere(), 3.0, lipschitz=1.0), "Displace(displacement"),
    (lambda: sdf.Displace(sdf.Sphere(), amplitude=float("nan")), "Displace(amplitude"),
]


@pytest.mark.parametrize("make,name", BAD, ids=[b[1] for b in BAD])
def test_constructors_reject_bad_values_naming_the_argument(make, name):
    with pytest.raises((ValueError, TypeError)) as info:
        make()
    assert name in str(info.value)


def test_constructors_accept_traced_values():
    """Scenes built inside jit/grad (e.g. from optimised parameters) are not checked."""

    def f(r):
        return sdf.Scale(sdf.RoundBox((1.0, 1.0, 1.0), r), r)(jnp.array([3.0, 0.0, 0.0]))

    assert np.isfinite(float(jax.jit(jax.grad(f))(0.2)))
