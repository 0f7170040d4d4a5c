"""Primitives at the origin: plain distance functions `sd_*` and their scene nodes.

Formulas follow Inigo Quilez, "distance functions" (iquilezles.org), as in the notes
("Common implicit surfaces"). Each docstring says whether the value is the exact
Euclidean signed distance or only a bound (|f| ≤ true distance, same sign).
"""

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from ..vecmath import _guarded_sqrt, clip, dot, minimum, safe_div, safe_norm, select
from .base import Primitive, as_float, check, material_index, non_negative, positive

# The code of these functions is inlined at every march site of a render, once per
# primitive of the scene, so it is written for few equations (under `vmap`, with its
# gradient): whole-vector operations, `p[::2]` (one strided slice) for (x, z), one
# custom JVP where the chain rule would differentiate a max, an abs and a norm apart
# (`_box_like`), and `vecmath.select` in place of `jnp.where` (a nested jit).
# tests/test_sdf.py::test_equation_budget holds each primitive to its size.


# -- plain distance functions (point first, then the shape's parameters) -------------


def _ball(radius, like, weight=None):
    """A `bounding_ball` centred at the origin (in the dtype of the leaf `like`)."""
    dtype = jnp.result_type(like)
    weight = jnp.ones((), dtype) if weight is None else weight
    return jnp.zeros(3, dtype), radius, weight


def sd_sphere(p, radius):
    """Exact: |p| − r."""
    return safe_norm(p) - radius


def sd_plane(p, normal, offset):
    """Exact for unit `normal`: n·p − offset (the plane n·p = offset; notes' sdPlane)."""
    return dot(p, normal) - offset


def _split_last(x):
    """The components of `x` along its last axis, each of shape [..., 1] (one `split`)."""
    return jnp.split(x, x.shape[-1], axis=-1)


def _first_max(q):
    """(max_i q_i, the index's comparison chain): the components of `q` ([..., n]) and
    the conditions c_i = q_i > max(q_0..q_{i−1}), i ≥ 1 (the first maximum wins ties)."""
    comps = _split_last(q)
    best, conds = comps[0], []
    for qi in comps[1:]:
        conds.append(qi > best)
        best = jnp.maximum(best, qi)
    return conds


@jax.custom_jvp
def _box_like(q, band):
    """|max(q, 0)| where max q > band, else max q: the distance of box-like shapes.

    `band` = 64 ulps of the shape's extent (`_box_band`). Within the band outside the
    surface the value is max q (equal to |max(q, 0)| on a face, a bound by less than
    the band at an edge). Newton-polished hits lie within rounding of a face, where the
    plain formula's gradient depends on rounding (the norm below its threshold gives 0,
    ties of max(q, 0) and min(·, 0) at 0 give 2/3 of the normal); the band puts them on
    one side of the switch. (max(max q, 0) > band ⟺ max q > band, as band > 0.)

    Derivative (a custom JVP, so that one evaluation's gradient is a handful of
    equations): d|o| = (o · dq)/|o| with o = max(q, 0) (taken where max q > band, so
    |o| ≥ band > 0; the components with q_i ≤ 0 have o_i = 0, so the derivative of
    max(·, 0) is not needed), and d(max q) = dq_i of the first maximal component, found by the chain of
    comparisons q_i > max(q_0..q_{i−1}) (the gradient of `jnp.max` selects the
    components *equal* to the maximum, and where XLA computes q twice with different
    roundings — it does, in some gradient programs — none is equal and the normal comes
    out as 0; q[argmax q] costs a chain of integer compares in the fused lane kernels).

    The norm's argument is 1 where it is not taken (value and rule), so that its plain
    chain rule is finite too: JAX drops a custom JVP rule that partial evaluation meets
    with unknown inputs (`JaxprTrace.process_custom_jvp_call`, as a scan's second
    derivative does) and differentiates the value instead, where sqrt'(0) times the
    select's zero cotangent gave NaN inside a box (`tests/test_union_stack.py`).
    """
    nearest = jnp.max(q, axis=-1)
    o = jnp.maximum(q, 0.0)
    far = nearest > band  # then |o| > 0: the inner select keeps sqrt's derivative finite
    return select(far, jnp.sqrt(select(far, jnp.sum(o * o, axis=-1), 1.0)), nearest)


@_box_like.defjvp
def _box_like_jvp(primals, tangents):
    (q, band), (tq, _) = primals, tangents
    nearest = jnp.max(q, axis=-1)
    o = jnp.maximum(q, 0.0)
    far = nearest > band  # then |o| ≥ max q > band > 0
    n = jnp.sqrt(select(far, jnp.sum(o * o, axis=-1), 1.0))
    t_far = jnp.sum(o * tq, axis=-1) * (1.0 / n)  # as before the guard: the same roundings
    comps = _split_last(tq)
    t_near = comps[0]
    for c, ti in zip(_first_max(q), comps[1:]):
        t_near = select(c, ti, t_near)
    return select(far, n, nearest), select(far, t_far, t_near[..., 0])


def _box_band(size):
    """64 ulps of a shape of extent `size` (the switch band of `_box_like`)."""
    return 64.0 * jnp.finfo(size.dtype).eps * (1.0 + size)


def sd_box(p, half_extents):
    """Exact: signed distance to an axis-aligned box centred at the origin,
    q = |p| − b, |max(q, 0)| + min(max q, 0) (IQ's sdBox; `_box_like`)."""
    return _box_like(jnp.abs(p) - half_extents, _box_band(jnp.max(jnp.abs(half_extents))))


def sd_round_box(p, half_extents, radius):
    """Exact: a box of `half_extents` whose edges are rounded by `radius`.

    The rounded box is the box shrunk by `radius` then dilated by it, so its outer
    dimensions stay `half_extents` (IQ's sdRoundBox).
    """
    return sd_box(p, half_extents - radius) - radius


def sd_torus(p, major_radius, minor_radius):
    """Exact: torus around the y axis, |(|p_xz| − R, p_y)| − r."""
    q = jnp.stack([safe_norm(p[::2]) - major_radius, p[1]])
    return safe_norm(q) - minor_radius


def sd_cone(p, radius, height):
    """Exact: solid cone, base disc of `radius` in the plane y = 0, apex at y = `height`.

    2-D distance to the profile triangle in the (r, y) half-plane (IQ's capped sdCone):
    with w = (|p_xz|, y − h) and q = (R, −h),

        a = w − q·clip(w·q / q·q, 0, 1),   b = w − q·(clip(w_r / R, 0, 1), 1),
        d = sqrt(min(a·a, b·b)) · sign(max(−(w_r q_y − w_y q_r), −(w_y − q_y))),

    here in scalar components (w_r = r, w_y = y − h; q_y = −h), the same roundings.
    The min's derivative is that of the smaller operand (the first on an exact tie,
    where jnp.minimum gives each ½).

    Where the nearest point lies inside a face (0 < t < 1 on the side, r < R on the
    base) the value is that face's line distance, linear in w and equal to the formula
    above in exact arithmetic: (w_r h + w_y R) / |q| on the side, −(w_y + h) on the
    base. The sqrt's derivative is undefined at d = 0: a hit polished onto the surface
    exactly (f = 0, about one pixel in 200 at XLA:CPU -O0) had a zero gradient, the
    normal's fallback, and a black pixel.
    """
    r = safe_norm(p[::2])
    wy = p[1] - height
    qq = radius * radius + height * height
    t_raw = safe_div(r * radius - wy * height, qq)
    t = clip(t_raw, 0.0, 1.0)
    tb = clip(safe_div(r, radius), 0.0, 1.0)
    ar, ay = r - radius * t, wy + height * t
    br, by = r - radius * tb, wy + height
    aa, bb = ar * ar + ay * ay, br * br + by * by
    # `vecmath.minimum`: its derivative follows the comparison. (jnp.minimum's tests
    # a == min(a, b), and XLA contracts a sum of products into fused multiply–adds in
    # some fusions and not in others: under jit neither operand passed that test.)
    d = _guarded_sqrt(minimum(aa, bb), 0.0)
    # The side, decided once: s cancels to within rounding at the surface, and copies of
    # it that a compiler rounds differently (fused multiply–adds in some fusions) would
    # give a normal's components from opposite sides (a non-unit normal).
    side = r * height + wy * radius
    outside = jax.lax.optimization_barrier(jnp.maximum(side, -by) > 0.0)
    nearer_side = aa <= bb
    inside_face = select(nearer_side, (t_raw > 0.0) & (t_raw < 1.0), tb < 1.0)
    line = select(nearer_side, side * jax.lax.rsqrt(qq), -by)
    return select(inside_face, line, select(outside, d, -d))


def sd_capsule(p, half_height, radius):
    """Exact: points within `radius` of the segment from y = −h to y = +h:
    |p − clip(p, (0, −h, 0), (0, h, 0))| − r."""
    h = jnp.stack([0.0, half_height, 0.0])
    return safe_norm(p - clip(p, -h, h)) - radius


def sd_cylinder(p, radius, half_height):
    """Exact: capped cylinder around the y axis, |y| ≤ half_height: the 2-D box distance
    of d = |(|p_xz|, p_y)| − (R, h) (IQ's sdCappedCylinder; `_box_like`)."""
    d = jnp.abs(jnp.stack([safe_norm(p[::2]), p[1]])) - jnp.stack([radius, half_height])
    return _box_like(d, _box_band(jnp.maximum(jnp.abs(radius), jnp.abs(half_height))))


def sd_ellipsoid(p, radii):
    """Bound (not exact), with k0 = |p/r| and k1 = |p/r²|:

    - outside (k0 > 1): IQ's ellipsoid bound k0·(k0 − 1)/k1, exact on the surface,
      with a unit gradient there;
    - inside: (k0 − 1)·min(r). IQ's formula overestimates the depth there (by up to
      max(r)/min(r): near the centre on the longest axis it gives −max(r), while the
      surface is min(r) away). k0 has Lipschitz constant 1/min(r) and vanishes on the
      surface, so (k0 − 1)·min(r) is a bound; it is exact at the centre.

    |f| never exceeds the true distance, and the sign is exact.
    """
    k0 = safe_norm(p / radii)
    k1 = safe_norm(p / (radii * radii))
    outside = safe_div(k0 * (k0 - 1.0), k1)
    inside = (k0 - 1.0) * jnp.min(radii)
    return select(k0 > 1.0, outside, inside)


# -- scene nodes ---------------------------------------------------------------------


class Sphere(Primitive):
    """Sphere of `radius` centred at the origin (exact). Differentiable: `radius`."""

    radius: jnp.ndarray

    def __init__(self, radius=1.0, material=0):
        self.radius = positive(radius, (), "Sphere(radius=...)")
        self.material = material_index(material, f"{type(self).__name__}(material=...)")

    def distance(self, p):
        return sd_sphere(p, self.radius)

    def bounding_ball(self):
        return _ball(self.radius, self.radius)


class Plane(Primitive):
    """The plane n·p = offset, solid on the side opposite to `normal` (exact).

    `normal` is normalised on use. Differentiable: `normal`, `offset`.
    """

    normal: jnp.ndarray
    offset: jnp.ndarray

    def __init__(self, normal=(0.0, 1.0, 0.0), offset=0.0, material=0):
        self.normal = check(as_float(normal, (3,), "Plane(normal=...)"),
                            lambda n: np.linalg.norm(n) > 0.0, "Plane(normal=...)", "non-zero")
        self.offset = as_float(offset, (), "Plane(offset=...)")
        self.material = material_index(material, f"{type(self).__name__}(material=...)")

    def distance(self, p):
        n = self.normal / safe_norm(self.normal)
        return sd_plane(p, n, self.offset)


class Box(Primitive):
    """Axis-aligned box with `half_extents` (exact). Differentiable: `half_extents`."""

    half_extents: jnp.ndarray

    def __init__(self, half_extents=(1.0, 1.0, 1.0), material=0):
        self.half_extents = positive(half_extents, (3,), "Box(half_extents=...)")
        self.material = material_index(material, f"{type(self).__name__}(material=...)")

    def distance(self, p):
        return sd_box(p, self.half_extents)

    def bounding_ball(self):
        return _ball(safe_norm(self.half_extents), self.half_extents)


class RoundBox(Primitive):
    """Box with edges rounded by `radius`, outer size `half_extents` (exact)."""

    half_extents: jnp.ndarray
    radius: jnp.ndarray

    def __init__(self, half_extents=(1.0, 1.0, 1.0), radius=0.1, material=0):
        self.half_extents = positive(half_extents, (3,), "RoundBox(half_extents=...)")
        self.radius = non_negative(radius, (), "RoundBox(radius=...)")
        # The box is shrunk by `radius` before it is rounded: radius ≤ every half extent.
        if not isinstance(self.half_extents, jax.core.Tracer):
            check(self.radius, lambda r: r <= np.min(np.asarray(self.half_extents)),
                  "RoundBox(radius=...)", "≤ every half extent (the box is shrunk by it)")
        self.material = material_index(material, f"{type(self).__name__}(material=...)")

    def distance(self, p):
        return sd_round_box(p, self.half_extents, self.radius)

    def bounding_ball(self):
        return _ball(safe_norm(self.half_extents), self.half_extents)


class Torus(Primitive):
    """Torus in the xz plane around the y axis (exact)."""

    major_radius: jnp.ndarray
    minor_radius: jnp.ndarray

    def __init__(self, major_radius=1.0, minor_radius=0.25, material=0):
        self.major_radius = positive(major_radius, (), "Torus(major_radius=...)")
        self.minor_radius = positive(minor_radius, (), "Torus(minor_radius=...)")
        self.material = material_index(material, f"{type(self).__name__}(material=...)")

    def distance(self, p):
        return sd_torus(p, self.major_radius, self.minor_radius)

    def bounding_ball(self):
        return _ball(self.major_radius + self.minor_radius, self.major_radius)


class Cone(Primitive):
    """Solid cone: base disc of `radius` at y = 0, apex at y = `height` (exact)."""

    radius: jnp.ndarray
    height: jnp.ndarray

    def __init__(self, radius=1.0, height=1.0, material=0):
        self.radius = positive(radius, (), "Cone(radius=...)")
        self.height = positive(height, (), "Cone(height=...)")
        self.material = material_index(material, f"{type(self).__name__}(material=...)")

    def distance(self, p):
        return sd_cone(p, self.radius, self.height)

    def bounding_ball(self):
        # base rim at distance R from the origin, apex at distance h
        return _ball(jnp.maximum(self.radius, self.height), self.radius)


class Capsule(Primitive):
    """Capsule: segment y ∈ [−half_height, half_height] dilated by `radius` (exact)."""

    half_height: jnp.ndarray
    radius: jnp.ndarray

    def __init__(self, half_height=0.5, radius=0.25, material=0):
        self.half_height = non_negative(half_height, (), "Capsule(half_height=...)")
        self.radius = positive(radius, (), "Capsule(radius=...)")
        self.material = material_index(material, f"{type(self).__name__}(material=...)")

    def distance(self, p):
        return sd_capsule(p, self.half_height, self.radius)

    def bounding_ball(self):
        return _ball(self.half_height + self.radius, self.radius)


class Cylinder(Primitive):
    """Capped cylinder around the y axis (exact)."""

    radius: jnp.ndarray
    half_height: jnp.ndarray

    def __init__(self, radius=0.5, half_height=0.5, material=0):
        self.radius = positive(radius, (), "Cylinder(radius=...)")
        self.half_height = positive(half_height, (), "Cylinder(half_height=...)")
        self.material = material_index(material, f"{type(self).__name__}(material=...)")

    def distance(self, p):
        return sd_cylinder(p, self.radius, self.half_height)

    def bounding_ball(self):
        return _ball(jnp.sqrt(self.radius ** 2 + self.half_height ** 2), self.radius)


class Ellipsoid(Primitive):
    """Axis-aligned ellipsoid with semi-axes `radii` (a bound, exact on the surface)."""

    radii: jnp.ndarray

    def __init__(self, radii=(1.0, 0.5, 0.5), material=0):
        self.radii = positive(radii, (3,), "Ellipsoid(radii=...)")
        self.material = material_index(material, f"{type(self).__name__}(material=...)")

    def distance(self, p):
        return sd_ellipsoid(p, self.radii)

    def bounding_ball(self):
        # Outside the ball of radius r_max (where k0 ≥ 1), with k0 ≥ |p|/r_max and
        # k1 ≤ |p|/r_min²: f = k0 (k0 − 1)/k1 ≥ (r_min/r_max)² (|p| − r_max).
        r_max, r_min = jnp.max(self.radii), jnp.min(self.radii)
        return _ball(r_max, self.radii, (r_min / r_max) ** 2)
