"""Small shared helpers for the BRDF models (private)."""

import jax.numpy as jnp

from ..vecmath import normalize


def above(wo, wi):
    """True where both directions are strictly above the horizon (local frame)."""
    return (wo[..., 2] > 0.0) & (wi[..., 2] > 0.0)


def half_vector(wo, wi):
    """Unit half vector wm = (wo + wi) / |wo + wi| (+z where wo = −wi)."""
    return normalize(wo + wi)


def pow_pos(x, q):
    """max(x, 0)^q as exp(q log x), 0 for x ≤ 0: finite value and gradient (also in q)
    at x = 0 and for q = 0."""
    ok = x > 0.0
    return jnp.where(ok, jnp.exp(q * jnp.log(jnp.where(ok, x, 1.0))), 0.0)


def scalar(x, name):
    """A float scalar array; raises naming `name` if the shape is not ()."""
    a = jnp.asarray(x, dtype=float)
    if a.ndim != 0:
        raise ValueError(f"`{name}` must be a scalar, got shape {a.shape}")
    return a
