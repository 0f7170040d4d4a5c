"""Placement: domain maps that move the point before the child is evaluated.

Notes, "Domain operations": a rigid motion M is applied to a shape by evaluating the
child at M⁻¹ p (opTx); uniform scale evaluates s·f(p / s) (opScale); repetition
evaluates the child at p folded into one period (opRep). Rigid motions and uniform
scales keep exact distances exact.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..vecmath import clip, cross, dot, normalize, safe_div, select
from .base import SDF, as_float, check, check_sdf, non_negative, positive


def rotate_axis_angle(p, axis, angle):
    """Rodrigues' rotation of `p` by `angle` (radians) about unit `axis`."""
    c, s = jnp.cos(angle), jnp.sin(angle)
    return p * c + cross(axis, p) * s + axis * dot(axis, p) * (1.0 - c)


#: ε_ijk, the Levi-Civita symbol: [a]×_ij = −ε_ijk a_k is the cross-product matrix of a.
_LEVI_CIVITA = np.zeros((3, 3, 3))
for _i, _j, _k in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
    _LEVI_CIVITA[_i, _j, _k], _LEVI_CIVITA[_j, _i, _k] = 1.0, -1.0


def axis_angle_matrix(axis, angle):
    """Rodrigues' rotation matrix R = c I + s [a]× + (1 − c) a aᵀ (c = cos θ, s = sin θ)
    of `angle` θ (radians) about unit `axis` a: R p = `rotate_axis_angle(p, a, θ)`.

    Built from the parameters alone (no point), so under `vmap` over points it is
    computed once and each point costs one matrix–vector product.
    """
    c, s = jnp.cos(angle), jnp.sin(angle)
    dtype = jnp.result_type(axis)
    cross_matrix = -jnp.tensordot(jnp.asarray(_LEVI_CIVITA, dtype), axis, axes=1)
    return (c * jnp.eye(3, dtype=dtype) + s * cross_matrix
            + (1.0 - c) * jnp.outer(axis, axis))


def quaternion_to_axis_angle(q):
    """(axis, angle in degrees) of the unit quaternion q = (w, x, y, z) (numpy)."""
    q = np.asarray(q, dtype=float)
    if q.shape != (4,) or not np.all(np.isfinite(q)) or np.linalg.norm(q) == 0.0:
        raise ValueError(f"quaternion must be 4 finite numbers (w, x, y, z), not all 0; got {q}")
    q = q / np.linalg.norm(q)
    if q[0] < 0.0:
        q = -q
    v = q[1:]
    s = np.linalg.norm(v)
    if s == 0.0:
        return np.array([0.0, 1.0, 0.0]), 0.0
    return v / s, float(np.degrees(2.0 * np.arctan2(s, q[0])))


def _moved(ball, move):
    """`ball` with its centre moved by `move` (a rigid motion: radius and weight kept)."""
    return None if ball is None else (move(ball[0]), ball[1], ball[2])


class _Wrap(SDF):
    def children(self):
        return (self.child,)

    def lipschitz(self):
        return self.child.lipschitz()


class Translate(_Wrap):
    """The child moved by `offset`: f(p − offset). Differentiable: `offset`."""

    child: SDF
    offset: jnp.ndarray

    def __init__(self, child, offset=(0.0, 0.0, 0.0)):
        self.child = check_sdf(child, "Translate(child=...)")
        self.offset = as_float(offset, (3,), "Translate(offset=...)")

    def eval(self, p):
        return self.child.eval(p - self.offset)

    def bounding_ball(self):
        return _moved(self.child.bounding_ball(), lambda c: c + self.offset)


class Rotate(_Wrap):
    """The child rotated by `angle` degrees about `axis` (right-handed): f(R⁻¹ p).

    Give either `axis` and `angle`, or a unit `quaternion` (w, x, y, z), which is
    converted to axis–angle. Differentiable: `axis` (normalised on use), `angle`.
    """

    child: SDF
    axis: jnp.ndarray
    angle: jnp.ndarray

    def __init__(self, child, axis=(0.0, 1.0, 0.0), angle=0.0, quaternion=None):
        self.child = check_sdf(child, "Rotate(child=...)")
        if quaternion is not None:
            try:
                axis, angle = quaternion_to_axis_angle(quaternion)
            except ValueError as e:
                raise ValueError(f"`Rotate(quaternion=...)`: {e}") from None
        self.axis = check(as_float(axis, (3,), "Rotate(axis=...)"),
                          lambda a: np.linalg.norm(a) > 0.0, "Rotate(axis=...)", "non-zero")
        self.angle = as_float(angle, (), "Rotate(angle=...)")

    def eval(self, p):
        # f(R(−θ) p) = f(R(θ)ᵀ p): one matrix–vector product per point.
        rotation = axis_angle_matrix(normalize(self.axis), jnp.deg2rad(self.angle))
        return self.child.eval(p @ rotation)

    def bounding_ball(self):
        # q = Mᵀ p: |q − c| = |p − M c|
        rotation = axis_angle_matrix(normalize(self.axis), jnp.deg2rad(self.angle))
        return _moved(self.child.bounding_ball(), lambda c: rotation @ c)


class Rotated(_Wrap):
    """A `Rotate` with its matrix computed ahead: f(p R), R = `axis_angle_matrix`.

    `with_matrices` builds it once at the top of a render program (`stack.prestack`),
    so that every site that evaluates the SDF (march, Newton steps, normals, shadow
    rays) costs one matrix–vector product per point, not the matrix (normalize, cos,
    sin, 18 products) again: the showcase's "fused" render program 20 404 → 17 264
    equations. The same function as the `Rotate`; gradients reach its axis and angle
    through `rotation`.
    """

    child: SDF
    rotation: jnp.ndarray

    def eval(self, p):
        return self.child.eval(p @ self.rotation)

    def bounding_ball(self):
        return _moved(self.child.bounding_ball(), lambda c: self.rotation @ c)


def with_matrices(surface):
    """`surface` with every `Rotate` replaced by its `Rotated` (the same function); in a
    union stacked ahead (`stack.stacked`), each group's rotations under `vmap`."""
    from .stack import StackedUnion

    def convert(node):
        if type(node) is StackedUnion:
            parts = tuple(jax.vmap(with_matrices)(p) if st else with_matrices(p)
                          for p, st in zip(node.parts, node.stacked))
            return eqx.tree_at(lambda u: u.parts, node, parts)
        if type(node) is not Rotate:
            return node
        rotation = axis_angle_matrix(normalize(node.axis), jnp.deg2rad(node.angle))
        return Rotated(with_matrices(node.child), rotation)

    return jax.tree_util.tree_map(convert, surface,
                                  is_leaf=lambda x: type(x) in (Rotate, StackedUnion))


class Transform(_Wrap):
    """The child moved by a rigid transform p ↦ R p + t: f(Rᵀ (p − t)).

    `rotation` must be a 3×3 rotation matrix (checked when given as concrete numbers).
    Differentiable: `rotation`, `translation`.
    """

    child: SDF
    rotation: jnp.ndarray
    translation: jnp.ndarray

    def __init__(self, child, rotation=np.eye(3), translation=(0.0, 0.0, 0.0)):
        self.child = check_sdf(child, "Transform(child=...)")
        self.rotation = as_float(rotation, (3, 3), "Transform(rotation=...)")
        self.translation = as_float(translation, (3,), "Transform(translation=...)")
        if not isinstance(self.rotation, jax.core.Tracer):
            r = np.asarray(self.rotation)
            if not np.allclose(r @ r.T, np.eye(3), atol=1e-5) or np.linalg.det(r) < 0:
                raise ValueError("`Transform(rotation=...)` must be a rotation matrix")

    def eval(self, p):
        return self.child.eval(self.rotation.T @ (p - self.translation))

    def bounding_ball(self):
        return _moved(self.child.bounding_ball(), lambda c: self.rotation @ c + self.translation)


class Scale(_Wrap):
    """The child scaled uniformly by `factor` > 0: s·f(p / s) (exact stays exact)."""

    child: SDF
    factor: jnp.ndarray

    def __init__(self, child, factor=1.0):
        self.child = check_sdf(child, "Scale(child=...)")
        self.factor = positive(factor, (), "Scale(factor=...)")

    def eval(self, p):
        d, m = self.child.eval(safe_div(p, self.factor))
        return d * self.factor, m

    def bounding_ball(self):
        # s f(p/s) ≥ s w (|p/s − c| − r) = w (|p − s c| − s r)
        ball = self.child.bounding_ball()
        return None if ball is None else (ball[0] * self.factor, ball[1] * self.factor, ball[2])


class Repeat(_Wrap):
    """The child repeated with `period` per axis (0 on an axis: no repetition there).

    Infinite repetition folds p into the cell around the origin (opRep); with `count`
    (static, per axis) only copies −count … +count exist (IQ's limited repetition).
    A bound only if the child fits inside one cell (its distance then never looks past
    the neighbouring copy). Differentiable: `period`.
    """

    child: SDF
    period: jnp.ndarray
    count: tuple | None = eqx.field(static=True)

    def __init__(self, child, period=(1.0, 1.0, 1.0), count=None):
        self.child = check_sdf(child, "Repeat(child=...)")
        self.period = non_negative(period, (3,), "Repeat(period=...)")
        if count is not None:
            count = tuple(int(c) for c in np.broadcast_to(np.asarray(count), (3,)))
            if min(count) < 0:
                raise ValueError(f"`Repeat(count=...)` must be ≥ 0 per axis, got {count}")
        self.count = count

    def eval(self, p):
        active = self.period != 0.0
        cell = jnp.round(safe_div(p, self.period))
        if self.count is not None:
            c = jnp.asarray(self.count, dtype=p.dtype)
            cell = clip(cell, -c, c)
        q = select(active, p - self.period * cell, p)
        return self.child.eval(q)

    def bounding_ball(self):
        # f(p) = f_child(p − period·k) for one copy k ∈ [−count, count]: every copy's
        # ball lies within |period · count| of the child's
        ball = self.child.bounding_ball()
        if ball is None or self.count is None:
            return None
        reach = jnp.sqrt(jnp.sum((self.period * jnp.asarray(self.count, self.period.dtype)) ** 2))
        return ball[0], ball[1] + reach, ball[2]
