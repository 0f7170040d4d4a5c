"""Boolean combinations of shapes, sharp and smooth (notes, "Distance operations").

The smooth versions use the quadratic polynomial smooth minimum of Inigo Quilez
("smooth minimum", iquilezles.org): with h = max(k − |a − b|, 0) / k,

    smin(a, b; k) = min(a, b) − h² k / 4,

which equals min(a, b) where |a − b| ≥ k, blends over a band of width k, and keeps
|∇f| ≤ 1, so the result is still a distance bound. k → 0 gives the sharp operator.
The material of a combination is the material of the operand that is active (the
smaller one for a union, the larger one for an intersection).
"""

import equinox as eqx
import jax
import jax.numpy as jnp

from ..vecmath import maximum as _max, minimum as _min, safe_div, select
from .base import SDF, check_sdf, non_negative
from .stack import STACK_THRESHOLD, enclosing_ball, union_eval, union_lipschitz


def op_union(d1, d2):
    """min(d1, d2): exact outside both shapes, a bound inside."""
    return _min(d1, d2)


def op_subtraction(d1, d2):
    """d1 with d2 removed: max(d1, −d2) (a bound)."""
    return _max(d1, -d2)


def op_intersection(d1, d2):
    """max(d1, d2) (a bound)."""
    return _max(d1, d2)


@jax.custom_jvp
def op_smooth_union(d1, d2, k):
    """Polynomial smooth minimum with blend width `k` (a bound):
    h = max(k − |d1 − d2|, 0) / k (0 where k = 0), smin = min(d1, d2) − h² k / 4.

    Its derivative, a custom JVP (the chain rule through max, abs and the guarded
    division costs some thirty equations per blend and gradient): with s = sign(d1 − d2)
    (+1 at 0, as abs's derivative) and dm the tangent of the smaller operand (the
    first on ties, `vecmath.minimum`),

        d smin = dm − (h/2) (dk − s (dd1 − dd2)) + (h²/4) dk,

    from d(h² k/4) = (h k/2) dh + (h²/4) dk and k dh = du − h dk, du = dk − s d|d1 − d2|
    where the blend is active (h > 0; elsewhere h = 0 and both terms vanish).
    """
    h = safe_div(_max(k - jnp.abs(d1 - d2), 0.0), k)
    return _min(d1, d2) - h * h * k * 0.25


@op_smooth_union.defjvp
def _op_smooth_union_jvp(primals, tangents):
    (d1, d2, k), (t1, t2, tk) = primals, tangents
    d = d1 - d2
    h = safe_div(_max(k - jnp.abs(d), 0.0), k)
    half = 0.5 * h
    dm = select(d2 < d1, t2, t1)
    dd = select(d >= 0.0, t1 - t2, t2 - t1)
    out = _min(d1, d2) - h * h * k * 0.25
    return out, dm + half * dd - (half - 0.5 * half * h) * tk


def op_smooth_subtraction(d1, d2, k):
    """d1 with d2 removed, blended over width `k`: −smin(−d1, d2)."""
    return -op_smooth_union(-d1, d2, k)


def op_smooth_intersection(d1, d2, k):
    """Smooth maximum: −smin(−d1, −d2)."""
    return -op_smooth_union(-d1, -d2, k)



class Union(SDF):
    """Union of any number of shapes: min over children (exact outside).

    The material is that of the nearest child (the first one on ties). Children of one
    structure (same node types and static fields, e.g. many `Translate(Sphere)` with
    one material) are evaluated stacked, one `lax.scan` over their stacked leaves, when
    a group has at least `stack_threshold` members (default `stack.STACK_THRESHOLD`;
    a static field, so part of the scene's structure and of the jit cache key): the
    traced program holds one copy per *kind* of child, so compile time stays flat as
    children are added (`jaxrt.sdf.stack`). `children_` stays the user-facing field:
    `eqx.tree_at(lambda s: s.children_[i].radius, ...)` and gradients reach every child.

    Differentiable: every child's parameters.
    """

    children_: tuple
    stack_threshold: int = eqx.field(static=True)
    balls: tuple | None = None  # the children's bounding balls, set by `stack.prestack`

    def __init__(self, *children, stack_threshold=STACK_THRESHOLD):
        if not children:
            raise ValueError("`Union(...)` needs at least one child")
        if not (isinstance(stack_threshold, int) and not isinstance(stack_threshold, bool)
                and stack_threshold >= 1):
            raise ValueError(f"`Union(stack_threshold={stack_threshold!r})`: expected an integer ≥ 1")
        self.children_ = tuple(check_sdf(c, f"Union(children[{i}])") for i, c in enumerate(children))
        self.stack_threshold = stack_threshold
        self.balls = None

    def children(self):
        return self.children_

    def eval(self, p):
        return union_eval(self.children_, p, self.stack_threshold, self.balls)

    def with_balls(self, balls):
        """A copy holding `balls` (`stack.prestack`; the same function)."""
        copy = object.__new__(type(self))
        copy.__dict__.update(self.__dict__)
        object.__setattr__(copy, "balls", balls)
        return copy

    def bounding_ball(self):
        return enclosing_ball([c.bounding_ball() for c in self.children_])

    def lipschitz(self):
        return union_lipschitz(self.children_, self.stack_threshold)


class Intersection(SDF):
    """Intersection of any number of shapes: max over children (a bound)."""

    children_: tuple

    def __init__(self, *children):
        if not children:
            raise ValueError("`Intersection(...)` needs at least one child")
        self.children_ = tuple(check_sdf(c, f"Intersection(children[{i}])") for i, c in enumerate(children))

    def children(self):
        return self.children_

    def eval(self, p):
        d, m = self.children_[0].eval(p)
        for child in self.children_[1:]:
            dc, mc = child.eval(p)
            m = select(dc > d, mc, m)
            d = _max(d, dc)
        return d, m

    def lipschitz(self):
        return jnp.max(jnp.stack([c.lipschitz() for c in self.children_]))

    def bounding_ball(self):
        # max_i f_i ≥ f_j: any child's ball
        return next((b for b in (c.bounding_ball() for c in self.children_) if b is not None), None)


class Subtraction(SDF):
    """`a` with `b` removed: max(a, −b) (a bound). The cut takes `b`'s material."""

    a: SDF
    b: SDF

    def __init__(self, a, b):
        self.a = check_sdf(a, "Subtraction(a=...)")
        self.b = check_sdf(b, "Subtraction(b=...)")

    def children(self):
        return (self.a, self.b)

    def eval(self, p):
        da, ma = self.a.eval(p)
        db, mb = self.b.eval(p)
        return op_subtraction(da, db), select(-db > da, mb, ma)

    def lipschitz(self):
        return jnp.maximum(self.a.lipschitz(), self.b.lipschitz())

    def bounding_ball(self):
        return self.a.bounding_ball()  # max(a, −b) ≥ a


class _Smooth(SDF):
    a: SDF
    b: SDF
    k: jnp.ndarray

    def __init__(self, a, b, k=0.25):
        name = type(self).__name__
        self.a, self.b = check_sdf(a, f"{name}(a=...)"), check_sdf(b, f"{name}(b=...)")
        self.k = non_negative(k, (), f"{name}(k=...)")

    def children(self):
        return (self.a, self.b)

    def lipschitz(self):
        return jnp.maximum(self.a.lipschitz(), self.b.lipschitz())

    def bounding_ball(self):
        # smooth subtraction and intersection: max(a, ·) + h²k/4 ≥ a
        return self.a.bounding_ball()


class SmoothUnion(_Smooth):
    """Union blended over width `k` (polynomial smooth minimum; a bound).

    Differentiable: `k` (and both children).
    """

    def eval(self, p):
        da, ma = self.a.eval(p)
        db, mb = self.b.eval(p)
        return op_smooth_union(da, db, self.k), select(db < da, mb, ma)

    def bounding_ball(self):
        # smin(a, b) ≥ min(a, b) − k/4
        ball = enclosing_ball([self.a.bounding_ball(), self.b.bounding_ball()])
        return None if ball is None else (ball[0], ball[1] + 0.25 * self.k / ball[2], ball[2])


class SmoothSubtraction(_Smooth):
    """`a` with `b` removed, blended over width `k` (a bound)."""

    def eval(self, p):
        da, ma = self.a.eval(p)
        db, mb = self.b.eval(p)
        return op_smooth_subtraction(da, db, self.k), select(-db > da, mb, ma)


class SmoothIntersection(_Smooth):
    """Intersection blended over width `k` (a bound)."""

    def eval(self, p):
        da, ma = self.a.eval(p)
        db, mb = self.b.eval(p)
        return op_smooth_intersection(da, db, self.k), select(db > da, mb, ma)
