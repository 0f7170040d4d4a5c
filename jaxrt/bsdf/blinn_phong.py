"""Blinn–Phong: the Phong lobe around the half vector."""

import jax.numpy as jnp

from ._util import above, half_vector, pow_pos, scalar
from .base import Material, rgb


class BlinnPhong(Material):
    """Blinn 1977 lobe, normalised as a microfacet BRDF:

        f_r = kd / π + ks (q + 2) / (8π) (n·wm)^q,   wm = (wo + wi) / |wo + wi|,

    i.e. ks D_Phong(wm) / 4: the Phong NDF with the implicit geometry term and no
    Fresnel (notes, "Phong distribution" and "No visibility"; the form fitted by
    Ngan et al. 2005). Positive, reciprocal, directional albedo ≤ kd + ks.

    Parameters (differentiable): `kd`, `ks` (RGB), exponent `q` ≥ 0 (scalar).
    """

    kd: jnp.ndarray
    ks: jnp.ndarray
    q: jnp.ndarray

    def __init__(self, kd=0.5, ks=0.5, q=50.0):
        self.kd = rgb(kd, "BlinnPhong(kd=...)")
        self.ks = rgb(ks, "BlinnPhong(ks=...)")
        self.q = scalar(q, "BlinnPhong(q=...)")

    def eval(self, wo, wi):
        q = jnp.maximum(self.q, 0.0)
        wm = half_vector(wo, wi)
        lobe = (q + 2.0) / (8.0 * jnp.pi) * pow_pos(wm[2], q)
        return jnp.where(above(wo, wi), self.kd / jnp.pi + self.ks * lobe, 0.0)

    def base_color(self):
        return self.kd
