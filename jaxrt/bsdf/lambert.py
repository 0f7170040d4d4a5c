"""Ideal diffuse reflection."""

import jax.numpy as jnp

from .base import Material, rgb


class Lambert(Material):
    """Lambertian (ideal diffuse) reflection: f_r = albedo / π (notes, "Ideal diffuse").

    Physically plausible: positive, reciprocal, and its directional albedo equals
    `albedo` ≤ 1 at every incident angle. Zero below the horizon (wo.z ≤ 0 or wi.z ≤ 0).

    Parameters (differentiable): `albedo`, linear RGB reflectance in [0, 1].
    """

    albedo: jnp.ndarray

    def __init__(self, albedo=(0.8, 0.8, 0.8)):
        self.albedo = rgb(albedo, "Lambert(albedo=...)")

    def eval(self, wo, wi):
        above = (wo[2] > 0.0) & (wi[2] > 0.0)
        return jnp.where(above, self.albedo / jnp.pi, 0.0)

    def base_color(self):
        return self.albedo
