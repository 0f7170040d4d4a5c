"""Phong's reflection model, as in the notes and energy-normalised."""

import equinox as eqx
import jax.numpy as jnp

from ._util import above, pow_pos, scalar
from .base import Material, rgb


class Phong(Material):
    """Phong 1975, in the notes' form: L_o = [ka + kd (n·l) + ks (v·r)^q] L_i,
    r = 2 (n·l) n − l the mirror direction of the light.

    Classic (`normalized=False`, the default): as a BRDF (L_o = f_r L_i cos θi + ambient)
        f_r = kd + ks (wo·r)^q / cos θi,   ambient() = ka.
    Exactly the notes' shading; and, as the notes say, it is a hack: it does NOT conserve
    energy (kd is not divided by π, so kd = 1 reflects π times what it receives, and the
    specular term lacks the cosine: its albedo grows without bound at grazing light), it
    is not reciprocal (the 1/cos θi), and the ambient term is not physical.

    Normalised (`normalized=True`; Lewis 1994, Lafortune & Willems 1994):
        f_r = kd / π + ks (q + 2) / (2π) (wo·r)^q,
    reciprocal and energy-conserving when kd + ks ≤ 1. The ambient term is still
    returned by `ambient()` (default ka = 0).

    Parameters (differentiable): `kd`, `ks`, `ka` (RGB), exponent `q` ≥ 0 (scalar).
    Static: `normalized`. Zero below the horizon.
    """

    kd: jnp.ndarray
    ks: jnp.ndarray
    q: jnp.ndarray
    ka: jnp.ndarray
    normalized: bool = eqx.field(static=True)

    def __init__(self, kd=0.5, ks=0.5, q=20.0, ka=0.0, normalized=False):
        self.kd = rgb(kd, "Phong(kd=...)")
        self.ks = rgb(ks, "Phong(ks=...)")
        self.q = scalar(q, "Phong(q=...)")
        self.ka = rgb(ka, "Phong(ka=...)")
        self.normalized = bool(normalized)

    def eval(self, wo, wi):
        ok = above(wo, wi)
        r = jnp.stack([-wi[0], -wi[1], wi[2]])  # reflect(wi, +z)
        q = jnp.maximum(self.q, 0.0)
        lobe = pow_pos(jnp.dot(wo, r), q)
        if self.normalized:
            f = self.kd / jnp.pi + self.ks * (q + 2.0) / (2.0 * jnp.pi) * lobe
        else:
            ci = jnp.where(ok, wi[2], 1.0)
            f = self.kd + self.ks * (lobe / ci)
        return jnp.where(ok, f, 0.0)

    def base_color(self):
        return self.kd

    def ambient(self):
        return self.ka
