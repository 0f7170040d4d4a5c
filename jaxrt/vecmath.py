"""NaN-safe vector helpers.

Every partial function here is guarded so that neither the value nor the gradient is
NaN or infinite where the function is undefined: the double-`where` pattern (the
argument is replaced by a harmless value *before* the function is applied,
`safe = where(ok, x, 1); y = where(ok, f(safe), fallback)`), or, for square roots, a
custom JVP that puts the guard in the derivative only: the forward program is a bare
`sqrt(max(x, 0))` (a min/max and a square root, no selects: the fused kernels of
`jaxrt.kernels` run forward programs only) and the derivative is the double-`where`
one.
"""

from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp

#: Squared lengths below this are treated as zero by `normalize` and `safe_norm`.
#: Chosen far below float32's smallest normal number squared would underflow (1e-38),
#: and far above float64's, so it works for both precisions.
TINY = 1e-30


def dot(a, b):
    """Dot product over the last axis."""
    return jnp.sum(a * b, axis=-1)


@partial(jax.custom_jvp, nondiff_argnums=(1,))
def _guarded_sqrt(x, tiny):
    """sqrt(max(x, 0)); its derivative 1/(2 sqrt x) where x > tiny, else 0."""
    return jnp.sqrt(jnp.maximum(x, 0.0))


@_guarded_sqrt.defjvp
def _guarded_sqrt_jvp(tiny, primals, tangents):
    (x,), (tx,) = primals, tangents
    y = _guarded_sqrt(x, tiny)
    ok = x > tiny
    return y, jnp.where(ok, 0.5 * tx / jnp.where(ok, y, 1.0), 0.0)


def safe_sqrt(x):
    """`sqrt(max(x, 0))` with a finite gradient at and below 0 (the gradient there is 0)."""
    return _guarded_sqrt(x, 0.0)


def safe_norm(x, axis=-1):
    """Euclidean norm with a zero (not NaN) gradient at the zero vector (|x|² ≤ TINY)."""
    return _guarded_sqrt(jnp.sum(x * x, axis=axis), TINY)


def normalize(x, fallback=None):
    """`x / |x|`; the zero vector (|x|² ≤ TINY) maps to `fallback` (default +z) with a
    zero gradient. (1/sqrt(max(|x|², TINY)) is finite everywhere, so one select, for
    the fallback, guards value and gradient.)"""
    sq = jnp.sum(x * x, axis=-1, keepdims=True)
    inv = 1.0 / jnp.sqrt(jnp.maximum(sq, TINY))
    if fallback is None:
        fallback = jnp.zeros_like(x).at[..., 2].set(1.0)
    return jnp.where(sq > TINY, x * inv, fallback)


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
    return minimum(a, b), jnp.where(b < a, tb, ta)


@jax.custom_jvp
def maximum(a, b):
    """max(a, b) whose derivative follows the comparison (see `minimum`)."""
    return jnp.maximum(a, b)


@maximum.defjvp
def _maximum_jvp(primals, tangents):
    (a, b), (ta, tb) = primals, tangents
    return maximum(a, b), jnp.where(b > a, tb, ta)


def safe_div(a, b, fallback=0.0):
    """`a / b` where `b != 0`, else `fallback`; finite gradients everywhere."""
    ok = b != 0.0
    return jnp.where(ok, a / jnp.where(ok, b, 1.0), fallback)


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
