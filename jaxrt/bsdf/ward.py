"""Ward's isotropic Gaussian BRDF, with Dür's normalisation as an option."""

import equinox as eqx
import jax.numpy as jnp

from ._util import above, half_vector, scalar
from .base import Material, rgb
from .microfacet import MIN_ALPHA
from ..vecmath import maximum

_NORMALIZATIONS = ("ward", "duer")


class Ward(Material):
    """Ward 1992, "Measuring and modeling anisotropic reflection" (isotropic form):

        f_r = rho_d / π + rho_s exp(−tan²θm / α²) / (4π α² N(wo, wi)),

    with wm the half vector and N = sqrt(cos θi cos θo) (`normalization="ward"`) or
    N = cos θi cos θo (`normalization="duer"`: Dür 2006, "An improved normalization for
    the Ward reflectance model", JGT 11(1); the "Ward-Duer" model of Ngan et al. 2005).

    Positive and reciprocal. Not strictly energy-conserving near grazing incidence:
    measured directional albedo with rho_s = 1, rho_d = 0, α = 0.3 is ≤ 0.8 up to 80°
    for both forms, but at 89° / 89.9° it is 0.36 / 1.04 (Ward) and 4.3 / 39 (Dür).

    Parameters (differentiable): `rho_d`, `rho_s` (RGB), `alpha` > 0 (scalar, clamped to
    `MIN_ALPHA`). Static: `normalization`.
    """

    rho_d: jnp.ndarray
    rho_s: jnp.ndarray
    alpha: jnp.ndarray
    normalization: str = eqx.field(static=True)

    def __init__(self, rho_d=0.5, rho_s=0.1, alpha=0.2, normalization="ward"):
        if normalization not in _NORMALIZATIONS:
            raise ValueError(f"`Ward(normalization={normalization!r})`: expected one of "
                             f"{_NORMALIZATIONS}")
        self.rho_d = rgb(rho_d, "Ward(rho_d=...)")
        self.rho_s = rgb(rho_s, "Ward(rho_s=...)")
        self.alpha = scalar(alpha, "Ward(alpha=...)")
        self.normalization = normalization

    def eval(self, wo, wi):
        ok = above(wo, wi)
        alpha = jnp.maximum(self.alpha, MIN_ALPHA)
        co = jnp.where(ok, wo[2], 1.0)
        ci = jnp.where(ok, wi[2], 1.0)
        hz = jnp.where(ok, half_vector(wo, wi)[2], 1.0)
        tan2 = maximum(0.0, 1.0 - hz * hz) / (hz * hz)
        norm = jnp.sqrt(co * ci) if self.normalization == "ward" else co * ci
        spec = jnp.exp(-tan2 / (alpha * alpha)) / (4.0 * jnp.pi * alpha * alpha * norm)
        return jnp.where(ok, self.rho_d / jnp.pi + self.rho_s * spec, 0.0)

    def base_color(self):
        return self.rho_d
