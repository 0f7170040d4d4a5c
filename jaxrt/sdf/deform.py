"""Deformations (notes, "Distance deformations"): displacement, twist, cheap bend.

They do not preserve distances. Each node reports a Lipschitz factor L ≥ |∇f| and the
sphere tracer divides its steps by the scene's L, so that no ray tunnels through the
deformed surface.
"""

import equinox as eqx
import jax.numpy as jnp

from ..vecmath import safe_sqrt
from .base import SDF, as_float, check_sdf, non_negative, positive


def _twist_lipschitz(rate, radius):
    """Largest singular value of [[1, k r], [0, 1]]: the Jacobian bound of a twist.

    A rotation by angle k·y of the (x, z) plane has Jacobian R·(I + u e_yᵀ) with
    |u| = k r (r the distance from the y axis) and u ⊥ e_y, whose spectral norm is
    (kr + sqrt(k²r² + 4)) / 2.
    """
    kr = jnp.abs(rate) * radius
    return 0.5 * (kr + safe_sqrt(kr * kr + 4.0))


def _bend_lipschitz(rate, radius):
    """1 + k r: the Jacobian bound of a cheap bend.

    A rotation by angle k·x of the (x, y) plane has Jacobian R·(I + u e_xᵀ) with
    u = k·(−y, x), |u| = k r. Unlike the twist's, u can be parallel to e_x (at x = 0,
    y = −r), where the spectral norm reaches |I + u e_xᵀ| = 1 + kr; the triangle
    inequality makes it the maximum.
    """
    return 1.0 + jnp.abs(rate) * radius


def _about_origin(ball):
    """The ball of a child evaluated at a rotation q of p (|q| = |p|; twist, bend):
    |q − c| ≥ |p| − |c|, so a ball about the origin of radius |c| + r."""
    if ball is None:
        return None
    c, r, w = ball
    return jnp.zeros_like(c), jnp.sqrt(jnp.sum(c * c)) + r, w


class SineDisplacement(eqx.Module):
    """sin(ω x) sin(ω y) sin(ω z): the notes' example displacement; Lipschitz |ω|.

    |∇g|² = ω² (ab + bc + ca − 3abc) with a, b, c the squared sines, which is affine in
    each of a, b, c ∈ [0, 1], so its maximum is at a corner: 1 (e.g. at x = 0,
    y = z = π/2ω). The bound is attained.
    """

    frequency: jnp.ndarray

    def __init__(self, frequency=5.0):
        self.frequency = as_float(frequency, (), "SineDisplacement(frequency=...)")

    def __call__(self, p):
        a, b, c = jnp.split(jnp.sin(self.frequency * p), 3, axis=-1)
        return jnp.squeeze(a * b * c, -1)

    def lipschitz(self):
        return jnp.abs(self.frequency)


class Displace(SDF):
    """f(p) + amplitude · g(p) for a displacement function g (notes' opDisplace).

    `displacement` is any callable on a point; if it has a `lipschitz()` method (as
    `SineDisplacement` has) it is used, otherwise give `lipschitz` (a bound on |∇g|).
    Lipschitz factor of the result: L_f + |amplitude| · L_g. Differentiable:
    `amplitude` and the displacement's own leaves.
    """

    child: SDF
    displacement: object
    amplitude: jnp.ndarray
    displacement_lipschitz: float | None = eqx.field(static=True)

    def __init__(self, child, displacement=None, amplitude=0.1, lipschitz=None):
        self.child = check_sdf(child, "Displace(child=...)")
        self.displacement = SineDisplacement() if displacement is None else displacement
        if not callable(self.displacement):
            raise TypeError("`Displace(displacement=...)` must be callable on a point, got "
                            f"{type(self.displacement).__name__}")
        self.amplitude = as_float(amplitude, (), "Displace(amplitude=...)")
        if lipschitz is None and not hasattr(self.displacement, "lipschitz"):
            raise ValueError(
                "`Displace(lipschitz=...)` is required when the displacement function "
                "has no `lipschitz()` method: give a bound on |∇g|"
            )
        self.displacement_lipschitz = (
            None if lipschitz is None
            else float(non_negative(lipschitz, (), "Displace(lipschitz=...)")))

    def children(self):
        return (self.child,)

    def eval(self, p):
        d, m = self.child.eval(p)
        return d + self.amplitude * self.displacement(p), m

    def bounding_ball(self):
        # |g| ≤ 1 for the sine displacement: f ≥ w (|p − c| − r) − |a|
        ball = self.child.bounding_ball()
        if ball is None or not isinstance(self.displacement, SineDisplacement):
            return None
        c, r, w = ball
        return c, r + jnp.abs(self.amplitude) / w, w

    def lipschitz(self):
        if self.displacement_lipschitz is None:
            lg = self.displacement.lipschitz()
        else:
            lg = self.displacement_lipschitz
        return self.child.lipschitz() + jnp.abs(self.amplitude) * lg


class Twist(SDF):
    """The child twisted about the y axis by `rate` radians per unit of y (opTwist).

    The point is rotated in the xz plane by −rate·y before the child is evaluated.
    `radius` bounds the distance from the y axis of the region that matters (the
    twisted child's extent); the Lipschitz factor is (kr + sqrt(k²r² + 4)) / 2.
    Differentiable: `rate`.
    """

    child: SDF
    rate: jnp.ndarray
    radius: jnp.ndarray

    def __init__(self, child, rate=1.0, radius=1.0):
        self.child = check_sdf(child, "Twist(child=...)")
        self.rate = as_float(rate, (), "Twist(rate=...)")
        self.radius = positive(radius, (), "Twist(radius=...)")

    def children(self):
        return (self.child,)

    def eval(self, p):
        x, y, z = jnp.split(p, 3, axis=-1)
        a = self.rate * y
        c, s = jnp.cos(a), jnp.sin(a)
        return self.child.eval(jnp.concatenate([c * x - s * z, y, s * x + c * z], axis=-1))

    def bounding_ball(self):
        return _about_origin(self.child.bounding_ball())

    def lipschitz(self):
        return self.child.lipschitz() * _twist_lipschitz(self.rate, self.radius)


class Bend(SDF):
    """Cheap bend (opCheapBend): the xy plane rotated by `rate`·x radians.

    `radius` bounds |p.xy| over the region that matters; the Lipschitz factor is
    1 + |rate|·radius.
    Differentiable: `rate`.
    """

    child: SDF
    rate: jnp.ndarray
    radius: jnp.ndarray

    def __init__(self, child, rate=0.5, radius=1.0):
        self.child = check_sdf(child, "Bend(child=...)")
        self.rate = as_float(rate, (), "Bend(rate=...)")
        self.radius = positive(radius, (), "Bend(radius=...)")

    def children(self):
        return (self.child,)

    def eval(self, p):
        x, y, z = jnp.split(p, 3, axis=-1)
        a = self.rate * x
        c, s = jnp.cos(a), jnp.sin(a)
        return self.child.eval(jnp.concatenate([c * x - s * y, s * x + c * y, z], axis=-1))

    def bounding_ball(self):
        return _about_origin(self.child.bounding_ball())

    def lipschitz(self):
        return self.child.lipschitz() * _bend_lipschitz(self.rate, self.radius)
