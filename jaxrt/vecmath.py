"""NaN-safe vector helpers.

Every partial function here is guarded so that neither the value nor the gradient is
NaN or infinite where the function is undefined: the double-`where` pattern (the
argument is replaced by a harmless value *before* the function is applied,
`safe = where(ok, x, 1); y = where(ok, f(safe), fallback)`), or, for square roots, a
custom JVP that puts the guard in the derivative only: the forward program is a bare
`sqrt(max(x, 0))` (a min/max and a square root, no selects: the fused kernels of
`jaxrt.kernels` run forward programs only) and the derivative is the double-`where`
one.

Clamps of computed values on a differentiated path use `maximum`, `minimum` and `clip`
here, whose derivatives follow a comparison: `jnp.maximum`'s derivative tests which
operand *equals* the result, and where XLA computes an operand twice and rounds the
copies apart, neither does and the derivative is 0.
"""

import contextlib
import threading
from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax

#: Squared lengths below this are treated as zero by `normalize` and `safe_norm`.
#: Chosen far below float32's smallest normal number squared would underflow (1e-38),
#: and far above float64's, so it works for both precisions.
TINY = 1e-30


def select(pred, on_true, on_false):
    """`jnp.where(pred, on_true, on_false)` as one `select_n` equation.

    (`jnp.where` is a nested `jit` of its own, with a `convert_element_type` per Python
    scalar, in every SDF evaluation and in every gradient of one.) The operands
    broadcast as in numpy; Python scalars take the dtype of the array operand.
    """
    pred = jnp.asarray(pred)
    dtype = jnp.result_type(on_true, on_false)
    shape = jnp.broadcast_shapes(pred.shape, *(jnp.shape(x) for x in (on_true, on_false)))

    def full(x):
        if isinstance(x, (int, float)):
            return lax.full(shape, x, dtype)
        return _broadcast(lax.convert_element_type(x, dtype), shape)

    return lax.select(_broadcast(pred, shape), full(on_true), full(on_false))


def _broadcast(x, shape):
    """`x` broadcast to `shape` (numpy rules; no equation where it has that shape)."""
    if x.shape == tuple(shape):
        return x
    lead = len(shape) - x.ndim
    keep = tuple(i + lead for i, n in enumerate(x.shape) if n == shape[i + lead])
    if len(keep) != x.ndim:
        x = lax.reshape(x, tuple(n for i, n in enumerate(x.shape) if n == shape[i + lead]))
    return lax.broadcast_in_dim(x, tuple(shape), keep)


def clip(x, lo, hi):
    """min(max(x, lo), hi) as one `clamp` (`jnp.clip` is a nested `jit` whose two
    comparisons each split the derivative at a tie: ½ at x = lo). The derivative is
    that of `lax.clamp`: 1 strictly between the bounds, else 0; the bounds' own
    derivatives are 1 where they are the value (x beyond them), 0 at ties."""
    x = jnp.asarray(x)
    lo, hi = (_broadcast(lax.convert_element_type(jnp.asarray(b), x.dtype), x.shape)
              if jnp.ndim(b) else lax.convert_element_type(b, x.dtype) for b in (lo, hi))
    return lax.clamp(lo, x, hi)


def dot(a, b):
    """Dot product over the last axis."""
    return jnp.sum(a * b, axis=-1)


@partial(jax.custom_jvp, nondiff_argnums=(1,))
def _guarded_sqrt(x, tiny):
    """sqrt(max(x, 0)); its derivative 1/(2 sqrt x) where x > tiny, else 0."""
    return jnp.sqrt(jnp.maximum(x, 0.0))


_STATE = threading.local()


@contextlib.contextmanager
def undifferentiated():
    """Context: the program traced here is never differentiated (the forward lane
    kernels: `kernels.fused.map_samples`), so the rules of `safe_norm` and `safe_sqrt`
    take their square roots unguarded (`_sqrt_where`). The guard made the showcase's
    "fused" render compile 20 % longer (XLA 27.6–29.0 s against 21.6–23.8 s, 32×24,
    session 39)."""
    previous = getattr(_STATE, "undifferentiated", False)
    _STATE.undifferentiated = True
    try:
        yield
    finally:
        _STATE.undifferentiated = previous


def _sqrt_where(x):
    """sqrt(max(x, 0)) in plain operations whose chain rule is finite everywhere (0 where
    x ≤ 0): the double-`where` guard.

    The custom JVPs' rules take their square roots from it: JAX drops a custom JVP rule
    that partial evaluation meets with unknown inputs (`JaxprTrace.process_custom_jvp_call`)
    and differentiates the function's value instead, and a scan's second derivative (the
    gradient of normals through a stacked group) meets there the custom JVPs that its
    first derivative's rules call. A `_guarded_sqrt` in `safe_norm`'s rule gave
    sqrt'(0) = ∞ times a zero tangent, NaN, at a sphere's centre
    (`tests/test_union_stack.py`). Under `undifferentiated`: `_guarded_sqrt`, the same
    values in fewer operations."""
    if getattr(_STATE, "undifferentiated", False):
        return _guarded_sqrt(x, 0.0)
    ok = x > 0.0
    return select(ok, jnp.sqrt(select(ok, x, 1.0)), 0.0)


def _inverse_where(ok, y):
    """1/y where `ok`, else 0, with the double-`where` guard (finite derivatives of every
    order where not `ok`)."""
    return select(ok, 1.0 / select(ok, y, 1.0), 0.0)


@_guarded_sqrt.defjvp
def _guarded_sqrt_jvp(tiny, primals, tangents):
    # d sqrt(x) = tx / (2 sqrt x); the tangent is one product with a primal-only
    # factor, so its transpose is one product too.
    (x,), (tx,) = primals, tangents
    y = _sqrt_where(x)
    return y, tx * (0.5 * _inverse_where(x > tiny, y))


def safe_sqrt(x):
    """`sqrt(max(x, 0))` with a finite gradient at and below 0 (the gradient there is 0)."""
    return _guarded_sqrt(x, 0.0)


@partial(jax.custom_jvp, nondiff_argnums=(1,))
def safe_norm(x, axis=-1):
    """Euclidean norm with a zero (not NaN) gradient at the zero vector (|x|² ≤ TINY).

    d|x| = (x · dx) / |x| (the gradient x / |x|), written as a custom JVP: the chain
    rule through sqrt(Σ x²) costs a `2x` product, a sum of the two halves of the
    square's tangent and the guard's selects per evaluation; this is one product with
    the primal-only factor 1/|x|. The derivative of that factor uses the guarded square
    root, so second derivatives (gradients of normals) are finite at 0 too.
    """
    return jnp.sqrt(jnp.sum(x * x, axis=axis))


@safe_norm.defjvp
def _safe_norm_jvp(axis, primals, tangents):
    (x,), (tx,) = primals, tangents
    sq = jnp.sum(x * x, axis=axis)
    n = _sqrt_where(sq)
    return n, jnp.sum(x * tx, axis=axis) * _inverse_where(sq > TINY, n)


def normalize(x, fallback=None):
    """`x / |x|`; the zero vector (|x|² ≤ TINY) maps to `fallback` (default +z) with a
    zero gradient. (1/sqrt(max(|x|², TINY)) is finite everywhere, so one select, for
    the fallback, guards value and gradient.)"""
    sq = jnp.sum(x * x, axis=-1, keepdims=True)
    inv = 1.0 / jnp.sqrt(maximum(sq, TINY))
    if fallback is None:
        fallback = jnp.broadcast_to(jnp.array([0.0, 0.0, 1.0], x.dtype), x.shape)
    return select(sq > TINY, x * inv, fallback)


@jax.custom_jvp
def minimum(a, b):
    """min(a, b) whose derivative follows the comparison: the tangent of b where b < a,
    else of a (the first operand on ties). (jnp.minimum's derivative tests
    a == min(a, b); where XLA computes `a` twice with different rounding, e.g. in the
    fused lane programs of jaxrt.kernels, that test fails for both operands and the
    gradient — a normal — is zero.) The value is a plain minimum (one instruction in
    the forward-only fused kernels, where a select needs a compare and a select)."""
    return jnp.minimum(a, b)


@minimum.defjvp
def _minimum_jvp(primals, tangents):
    (a, b), (ta, tb) = primals, tangents
    return minimum(a, b), select(b < a, tb, ta)


@jax.custom_jvp
def maximum(a, b):
    """max(a, b) whose derivative follows the comparison (see `minimum`)."""
    return jnp.maximum(a, b)


@maximum.defjvp
def _maximum_jvp(primals, tangents):
    (a, b), (ta, tb) = primals, tangents
    return maximum(a, b), select(b > a, tb, ta)


def safe_div(a, b, fallback=0.0):
    """`a / b` where `b != 0`, else `fallback`; finite gradients everywhere."""
    ok = b != 0.0
    return select(ok, a / select(ok, b, 1.0), fallback)


def cross(a, b):
    """Cross product of 3-vectors (last axis)."""
    return jnp.cross(a, b)


def coordinate_frame(n):
    """An orthonormal basis `(s, t, n)` around unit `n`, continuous except at n = -z.

    Duff et al. 2017, "Building an Orthonormal Basis, Revisited" (branch-free form).
    """
    sign = jnp.where(n[..., 2] >= 0.0, 1.0, -1.0)
    a = -1.0 / (sign + n[..., 2])
    b = n[..., 0] * n[..., 1] * a
    s = jnp.stack([1.0 + sign * n[..., 0] ** 2 * a, sign * b, -sign * n[..., 0]], axis=-1)
    t = jnp.stack([b, sign + n[..., 1] ** 2 * a, -n[..., 1]], axis=-1)
    return s, t, n


def to_local(v, n):
    """Express world vector `v` in the shading frame whose +z axis is unit `n`."""
    s, t, n = coordinate_frame(n)
    return jnp.stack([dot(v, s), dot(v, t), dot(v, n)], axis=-1)


def to_world(v, n):
    """Inverse of `to_local`."""
    s, t, n = coordinate_frame(n)
    return v[..., 0:1] * s + v[..., 1:2] * t + v[..., 2:3] * n


def luminance(rgb):
    """Relative luminance Y of linear sRGB (ITU-R BT.709 primaries)."""
    return 0.2126 * rgb[..., 0] + 0.7152 * rgb[..., 1] + 0.0722 * rgb[..., 2]


def stop_gradient(tree):
    """`lax.stop_gradient` on the array leaves of a pytree (other leaves pass through)."""
    return jax.tree_util.tree_map(
        lambda x: jax.lax.stop_gradient(x) if eqx.is_array(x) else x, tree
    )
