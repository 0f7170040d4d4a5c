"""Deformations (notes, "Distance deformations"): displacement, twist, cheap bend.

They do not preserve distances. Each node reports a Lipschitz factor L ≥ |∇f| and the
sphere tracer divides its steps by the scene's L, so that no ray tunnels through the
deformed surface.
"""

import equinox as eqx
import jax.numpy as jnp

from ..vecmath import safe_sqrt
from .base import SDF, as_float


def _warp_lipschitz(rate, radius):
    """Largest singular value of [[1, k r], [0, 1]]: the Jacobian bound of a twist/bend.

    A rotation by angle k·y of the (x, z) plane has Jacobian R + u e_yᵀ with |u| = k r
    (r the distance from the axis), whose spectral norm is (kr + sqrt(k²r² + 4)) / 2.
    """
    kr = jnp.abs(rate) * radius
    return 0.5 * (kr + safe_sqrt(kr * kr + 4.0))


class SineDisplacement(eqx.Module):
    """sin(ω x) sin(ω y) sin(ω z): the notes' example displacement; Lipschitz ω√3."""

    frequency: jnp.ndarray

    def __init__(self, frequency=5.0):
        self.frequency = as_float(frequency, (), "SineDisplacement(frequency=...)")

    def __call__(self, p):
        return jnp.prod(jnp.sin(self.frequency * p))

    def lipschitz(self):
        return jnp.abs(self.frequency) * jnp.sqrt(3.0)


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
        self.child = child
        self.displacement = SineDisplacement() if displacement is None else displacement
        self.amplitude = as_float(amplitude, (), "Displace(amplitude=...)")
        if lipschitz is None and not hasattr(self.displacement, "lipschitz"):
            raise ValueError(
                "`Displace(lipschitz=...)` is required when the displacement function "
                "has no `lipschitz()` method: give a bound on |∇g|"
            )
        self.displacement_lipschitz = None if lipschitz is None else float(lipschitz)

    def children(self):
        return (self.child,)

    def eval(self, p):
        d, m = self.child.eval(p)
        return d + self.amplitude * self.displacement(p), m

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
        self.child = child
        self.rate = as_float(rate, (), "Twist(rate=...)")
        self.radius = as_float(radius, (), "Twist(radius=...)")

    def children(self):
        return (self.child,)

    def eval(self, p):
        a = self.rate * p[1]
        c, s = jnp.cos(a), jnp.sin(a)
        q = jnp.stack([c * p[0] - s * p[2], p[1], s * p[0] + c * p[2]])
        return self.child.eval(q)

    def lipschitz(self):
        return self.child.lipschitz() * _warp_lipschitz(self.rate, self.radius)


class Bend(SDF):
    """Cheap bend (opCheapBend): the xy plane rotated by `rate`·x radians.

    `radius` bounds |p.xy| over the region that matters; Lipschitz factor as `Twist`.
    Differentiable: `rate`.
    """

    child: SDF
    rate: jnp.ndarray
    radius: jnp.ndarray

    def __init__(self, child, rate=0.5, radius=1.0):
        self.child = child
        self.rate = as_float(rate, (), "Bend(rate=...)")
        self.radius = as_float(radius, (), "Bend(radius=...)")

    def children(self):
        return (self.child,)

    def eval(self, p):
        a = self.rate * p[0]
        c, s = jnp.cos(a), jnp.sin(a)
        q = jnp.stack([c * p[0] - s * p[1], s * p[0] + c * p[1], p[2]])
        return self.child.eval(q)

    def lipschitz(self):
        return self.child.lipschitz() * _warp_lipschitz(self.rate, self.radius)
