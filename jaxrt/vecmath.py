"""NaN-safe vector helpers.

Every partial function here uses the double-`where` pattern: the argument is replaced
by a harmless value where the function is undefined *before* the function is applied,
so that neither the value nor the gradient is NaN or infinite there
(`safe = where(ok, x, 1); y = where(ok, f(safe), fallback)`).
"""

import jax.numpy as jnp

#: Squared lengths below this are treated as zero by `normalize` and `safe_norm`.
#: Chosen far below float32's smallest normal number squared would underflow (1e-38),
#: and far above float64's, so it works for both precisions.
TINY = 1e-30


def dot(a, b):
    """Dot product over the last axis."""
    return jnp.sum(a * b, axis=-1)


def safe_sqrt(x):
    """`sqrt(max(x, 0))` with a finite gradient at and below 0 (the gradient there is 0)."""
    ok = x > 0.0
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, x, 1.0)), 0.0)


def safe_norm(x, axis=-1):
    """Euclidean norm with a zero (not NaN) gradient at the zero vector."""
    sq = jnp.sum(x * x, axis=axis)
    ok = sq > TINY
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, sq, 1.0)), 0.0)


def normalize(x, fallback=None):
    """`x / |x|`; the zero vector maps to `fallback` (default +z) with a zero gradient."""
    sq = jnp.sum(x * x, axis=-1, keepdims=True)
    ok = sq > TINY
    inv = jnp.where(ok, 1.0 / jnp.sqrt(jnp.where(ok, sq, 1.0)), 0.0)
    if fallback is None:
        fallback = jnp.zeros_like(x).at[..., 2].set(1.0)
    return jnp.where(ok, x * inv, fallback)


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
