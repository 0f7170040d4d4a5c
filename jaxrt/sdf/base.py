"""The node interface of the shape language."""

import abc

import equinox as eqx
import jax.numpy as jnp


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
    """A float array of the given shape (broadcasting a scalar), with a clear error."""
    a = jnp.asarray(x, dtype=float)
    if shape is not None:
        if a.ndim == 0 and shape != ():
            a = jnp.broadcast_to(a, shape)
        if a.shape != shape:
            raise ValueError(f"`{name}` must have shape {shape}, got {a.shape}")
    return a
