"""Plastic: a Lambertian base under a rough dielectric coat."""

import equinox as eqx
import jax.numpy as jnp

from ._util import above, scalar
from .base import Material, rgb
from .cook_torrance import check_geometry, microfacet_specular
from .microfacet import GGX, MicrofacetDistribution
from .scattering import fresnel_dielectric


class Plastic(Material):
    """Diffuse base + dielectric specular coat:

        f_r = (1 − F(cos θo)) (1 − F(cos θi)) albedo / π
              + F(wi·wm) D(wm) G(wo, wi, wm) / (4 cos θo cos θi),

    F the exact dielectric Fresnel of index `eta`. The diffuse part is the light that
    enters the coat, scatters in the base and leaves again, each crossing weighted by the
    smooth-interface transmittance 1 − F (after Shirley et al. 1997, "Reflection models
    for computer graphics"; multiple bounces under the coat are ignored, so it is
    slightly darker than a full layered model).

    Parameters (differentiable): `albedo` (RGB), `eta` (scalar, ≈ 1.5 for plastics), the
    distribution's roughness. Static: distribution type, `geometry`.
    Physically plausible: positive, reciprocal, directional albedo ≤ 1 for albedo ≤ 1.
    """

    albedo: jnp.ndarray
    eta: jnp.ndarray
    distribution: MicrofacetDistribution
    geometry: str = eqx.field(static=True)

    def __init__(self, albedo=(0.5, 0.1, 0.1), eta=1.5, distribution=None,
                 geometry="smith_correlated"):
        self.albedo = rgb(albedo, "Plastic(albedo=...)")
        self.eta = scalar(eta, "Plastic(eta=...)")
        self.distribution = GGX(0.1) if distribution is None else distribution
        if not isinstance(self.distribution, MicrofacetDistribution):
            raise TypeError("`Plastic(distribution=...)` must be GGX, Beckmann or PhongNDF")
        check_geometry(geometry, "Plastic")
        self.geometry = geometry

    def eval(self, wo, wi):
        # The coat's F is `DielectricFresnel`'s, on self.eta as it is: a DielectricFresnel
        # built here would convert eta to the default float (float64 with x64 on) and
        # turn a float32 render's radiance into float64.
        def coat(cos_theta):
            return jnp.broadcast_to(fresnel_dielectric(cos_theta, self.eta), (3,))

        spec = microfacet_specular(self.distribution, self.geometry, coat, wo, wi)
        t_o = 1.0 - fresnel_dielectric(wo[2], self.eta)
        t_i = 1.0 - fresnel_dielectric(wi[2], self.eta)
        diff = jnp.where(above(wo, wi), t_o * t_i * self.albedo / jnp.pi, 0.0)
        return spec + diff

    def base_color(self):
        return self.albedo
