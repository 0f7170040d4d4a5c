"""Primitives at the origin: plain distance functions `sd_*` and their scene nodes.

Formulas follow Inigo Quilez, "distance functions" (iquilezles.org), as in the notes
("Common implicit surfaces"). Each docstring says whether the value is the exact
Euclidean signed distance or only a bound (|f| ≤ true distance, same sign).
"""

import jax
import jax.numpy as jnp
import numpy as np

from ..vecmath import dot, maximum, safe_div, safe_norm, safe_sqrt
from .base import Primitive, as_float, check, material_index, non_negative, positive


# -- plain distance functions (point first, then the shape's parameters) -------------


def sd_sphere(p, radius):
    """Exact: |p| − r."""
    return safe_norm(p) - radius


def sd_plane(p, normal, offset):
    """Exact for unit `normal`: n·p − offset (the plane n·p = offset; notes' sdPlane)."""
    return dot(p, normal) - offset


def _box_like(q, size):
    """|max(q, 0)| + min(max q, 0), the distance of box-like shapes of extent `size`.

    Within a band of 64 ulps of `size` outside the surface the value is max q (equal
    to |max(q, 0)| on a face, a bound by less than the band at an edge). Newton-polished
    hits lie within rounding of a face, where the plain formula's gradient depends on
    rounding (`safe_norm` below its threshold gives 0, ties of max(q, 0) and min(·, 0)
    at 0 give 2/3 of the normal); the band puts them on one side of the switch.

    max q is taken by `vecmath.maximum`, whose gradient follows the comparison (the
    first of equal components, as argmax): the nearest face's normal. (The gradient of
    `jnp.max` selects the components equal to the maximum, and where XLA computes q
    twice with different roundings — it does, in some gradient programs — none is
    equal and the normal comes out as 0; q[argmax q] costs a chain of integer
    compares in the fused lane kernels.)
    """
    band = 64.0 * jnp.finfo(q.dtype).eps * (1.0 + size)
    outside = jnp.maximum(q, 0.0)
    far = jnp.max(outside) > band
    nearest = q[0]
    for i in range(1, q.shape[0]):
        nearest = maximum(nearest, q[i])
    return jnp.where(far, safe_norm(outside), nearest)


def sd_box(p, half_extents):
    """Exact: signed distance to an axis-aligned box centred at the origin."""
    return _box_like(jnp.abs(p) - half_extents, jnp.max(jnp.abs(half_extents)))


def sd_round_box(p, half_extents, radius):
    """Exact: a box of `half_extents` whose edges are rounded by `radius`.

    The rounded box is the box shrunk by `radius` then dilated by it, so its outer
    dimensions stay `half_extents` (IQ's sdRoundBox).
    """
    return sd_box(p, half_extents - radius) - radius


def sd_torus(p, major_radius, minor_radius):
    """Exact: torus around the y axis."""
    q = jnp.stack([safe_norm(p[jnp.array([0, 2])]) - major_radius, p[1]])
    return safe_norm(q) - minor_radius


def sd_cone(p, radius, height):
    """Exact: solid cone, base disc of `radius` in the plane y = 0, apex at y = `height`.

    2-D distance to the profile triangle in the (r, y) half-plane (IQ's capped sdCone).
    """
    w = jnp.stack([safe_norm(p[jnp.array([0, 2])]), p[1] - height])
    q = jnp.stack([radius, -height])
    a = w - q * jnp.clip(safe_div(dot(w, q), dot(q, q)), 0.0, 1.0)
    b = w - q * jnp.stack([jnp.clip(safe_div(w[0], q[0]), 0.0, 1.0), 1.0])
    d2 = jnp.minimum(dot(a, a), dot(b, b))
    s = jnp.maximum(-(w[0] * q[1] - w[1] * q[0]), -(w[1] - q[1]))
    return safe_sqrt(d2) * jnp.where(s > 0.0, 1.0, -1.0)


def sd_capsule(p, half_height, radius):
    """Exact: points within `radius` of the segment from y = −h to y = +h."""
    q = p.at[1].set(p[1] - jnp.clip(p[1], -half_height, half_height))
    return safe_norm(q) - radius


def sd_cylinder(p, radius, half_height):
    """Exact: capped cylinder around the y axis, |y| ≤ half_height."""
    d = jnp.abs(jnp.stack([safe_norm(p[jnp.array([0, 2])]), p[1]])) - jnp.stack(
        [radius, half_height]
    )
    return _box_like(d, jnp.maximum(jnp.abs(radius), jnp.abs(half_height)))


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
    return jnp.where(k0 > 1.0, outside, inside)


# -- scene nodes ---------------------------------------------------------------------


class Sphere(Primitive):
    """Sphere of `radius` centred at the origin (exact). Differentiable: `radius`."""

    radius: jnp.ndarray

    def __init__(self, radius=1.0, material=0):
        self.radius = positive(radius, (), "Sphere(radius=...)")
        self.material = material_index(material, f"{type(self).__name__}(material=...)")

    def distance(self, p):
        return sd_sphere(p, self.radius)


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


class Ellipsoid(Primitive):
    """Axis-aligned ellipsoid with semi-axes `radii` (a bound, exact on the surface)."""

    radii: jnp.ndarray

    def __init__(self, radii=(1.0, 0.5, 0.5), material=0):
        self.radii = positive(radii, (3,), "Ellipsoid(radii=...)")
        self.material = material_index(material, f"{type(self).__name__}(material=...)")

    def distance(self, p):
        return sd_ellipsoid(p, self.radii)
