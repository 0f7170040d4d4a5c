"""The node interface of the shape language."""

import abc

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


class SDF(eqx.Module):
    """Abstract node of a signed-distance scene.

    A node is callable on one point `p` ([3]) and returns its signed distance (negative
    inside). `eval(p)` also returns the material index of the surface nearest to `p`, and
    `lipschitz()` a bound L on |∇f| that the sphere tracer divides its steps by: exact
    distances and bounds have L = 1; deformations report L > 1 so that no ray tunnels.
    Every float is a differentiable leaf; structure (node types, material indices,
    counts) is static.
    """

    @abc.abstractmethod
    def eval(self, p):
        """`(distance, material)`: signed distance (scalar) and material index (int32)."""

    def __call__(self, p):
        return self.eval(p)[0]

    def lipschitz(self):
        """Upper bound on |∇f| over space (1 for exact distances and bounds)."""
        return jnp.asarray(1.0)

    def material_ids(self):
        """The set of material indices this subtree can return (static)."""
        ids = set()
        for child in self.children():
            ids |= child.material_ids()
        return ids

    def children(self):
        """Direct child nodes (static structure)."""
        return ()

    def bounding_ball(self):
        """(centre [3], radius, weight) with f(p) ≥ weight · (|p − centre| − radius)
        wherever |p − centre| ≥ radius (0 < weight ≤ 1), or None (unknown, or
        unbounded). For an exact distance (and any bound that is exact outside) it is a
        ball that holds the shape, weight 1. A union skips a child whose ball shows it
        cannot be the nearest (`jaxrt.sdf.stack.culled_eval`)."""
        return None


class Primitive(SDF):
    """A shape at the origin carrying a (static) material index."""

    material: int = eqx.field(static=True)

    @abc.abstractmethod
    def distance(self, p):
        """Signed distance at `p`."""

    def eval(self, p):
        return self.distance(p), jnp.asarray(self.material, jnp.int32)

    def material_ids(self):
        return {self.material}


def as_float(x, shape=None, name="value"):
    """A float array of the given shape (broadcasting a scalar), with a clear error.

    Concrete values must be finite; traced ones (inside jit, grad, vmap) pass unchecked.
    """
    try:
        a = jnp.asarray(x, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"`{name}` must be a number or an array of numbers, got {x!r}") from None
    if shape is not None:
        if a.ndim == 0 and shape != ():
            a = jnp.broadcast_to(a, shape)
        if a.shape != shape:
            raise ValueError(f"`{name}` must have shape {shape}, got {a.shape}")
    return check(a, np.isfinite, name, "finite")


def check(a, ok, name, expected):
    """`a`, after checking that `ok(a)` holds elementwise; else a `ValueError` that names
    the argument: "`Sphere(radius=...)` must be > 0, got -1.0". Traced values pass."""
    if isinstance(a, jax.core.Tracer):
        return a
    v = np.asarray(a)
    if not np.all(ok(v)):
        raise ValueError(f"`{name}` must be {expected}, got {v.tolist()}")
    return a


def positive(x, shape, name):
    """`as_float` of a value that must be > 0."""
    return check(as_float(x, shape, name), lambda v: v > 0.0, name, "> 0")


def non_negative(x, shape, name):
    """`as_float` of a value that must be ≥ 0."""
    return check(as_float(x, shape, name), lambda v: v >= 0.0, name, "≥ 0")


def material_index(material, name):
    """A material index: an integer ≥ 0."""
    if isinstance(material, bool) or not isinstance(material, (int, np.integer)) or material < 0:
        raise ValueError(f"`{name}` must be an integer ≥ 0 (an index into Scene.materials), got {material!r}")
    return int(material)


def check_sdf(child, name):
    """`child`, after checking that it is a shape node."""
    if not isinstance(child, SDF):
        raise TypeError(f"`{name}` must be a jaxrt.sdf node, got {type(child).__name__}")
    return child
