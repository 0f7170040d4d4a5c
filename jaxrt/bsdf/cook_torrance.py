"""Cook–Torrance microfacet reflection, optionally over a Lambertian base."""

from typing import Optional

import equinox as eqx
import jax.numpy as jnp

from ..vecmath import dot
from ._util import above, half_vector
from .base import Material, rgb
from .conductors import conductor_preset
from .fresnel import ConductorFresnel, Fresnel, SchlickFresnel
from .geometry import GEOMETRY_TERMS
from .microfacet import GGX, Beckmann, MicrofacetDistribution

_DISTRIBUTIONS = {"ggx": GGX, "beckmann": Beckmann}


def microfacet_specular(distribution, geometry, fresnel, wo, wi):
    """F(wi·wm) D(wm) G(wo, wi, wm) / (4 cos θo cos θi), RGB [3]; 0 below the horizon.

    `geometry` is a name in `GEOMETRY_TERMS`, `fresnel` a `Fresnel` module.
    """
    ok = above(wo, wi)
    wm = half_vector(wo, wi)
    d = distribution.d(wm)
    g = GEOMETRY_TERMS[geometry](distribution, wo, wi, wm)
    f = fresnel(dot(wi, wm))
    co = jnp.where(ok, wo[2], 1.0)
    ci = jnp.where(ok, wi[2], 1.0)
    return jnp.where(ok, f * (d * g / (4.0 * co * ci)), 0.0)


def check_geometry(geometry, owner):
    if geometry not in GEOMETRY_TERMS:
        raise ValueError(
            f"`{owner}(geometry={geometry!r})`: expected one of {sorted(GEOMETRY_TERMS)}"
        )


class CookTorrance(Material):
    """Cook–Torrance microfacet BRDF (Cook & Torrance 1982; Walter et al. 2007):

        f_r = diffuse / π + ks F(wi·wm) D(wm) G(wo, wi, wm) / (4 (n·wi)(n·wo)),
        wm = (wo + wi) / |wo + wi|

    (notes, "Microfacet theory"). Structure (static): the distribution type (`GGX`,
    `Beckmann`, `PhongNDF`), the Fresnel type (`SchlickFresnel(f0)`,
    `DielectricFresnel(eta)`, `ConductorFresnel(eta, k)`), the `geometry` term by name
    ("implicit", "cook_torrance", "smith", "smith_correlated"), and whether there is a
    Lambertian base layer (`diffuse` is None or an RGB albedo).

    Parameters (differentiable): the distribution's roughness, the Fresnel parameters,
    `ks` (RGB specular scale, 1 for a physical surface) and `diffuse`.

    Plausibility: positive and reciprocal. With `ks` ≤ 1, no `diffuse` and a Smith or
    implicit geometry term, the directional albedo is ≤ 1 (single scattering only, so
    rough surfaces lose energy). The diffuse layer is simply added, so `diffuse` + the
    specular albedo can exceed 1; `Plastic` couples the two layers through Fresnel.
    """

    distribution: MicrofacetDistribution
    fresnel: Fresnel
    ks: jnp.ndarray
    diffuse: Optional[jnp.ndarray]
    geometry: str = eqx.field(static=True)

    def __init__(self, distribution=None, fresnel=None, geometry="smith_correlated",
                 diffuse=None, ks=1.0):
        distribution = GGX(0.3) if distribution is None else distribution
        fresnel = SchlickFresnel(0.04) if fresnel is None else fresnel
        if not isinstance(distribution, MicrofacetDistribution):
            raise TypeError("`CookTorrance(distribution=...)` must be GGX, Beckmann or "
                            f"PhongNDF, got {type(distribution).__name__}")
        if not isinstance(fresnel, Fresnel):
            raise TypeError("`CookTorrance(fresnel=...)` must be SchlickFresnel, "
                            f"DielectricFresnel or ConductorFresnel, got {type(fresnel).__name__}")
        check_geometry(geometry, "CookTorrance")
        self.distribution = distribution
        self.fresnel = fresnel
        self.geometry = geometry
        self.ks = rgb(ks, "CookTorrance(ks=...)")
        self.diffuse = None if diffuse is None else rgb(diffuse, "CookTorrance(diffuse=...)")

    @classmethod
    def rough_conductor(cls, name, alpha, distribution="ggx", geometry="smith_correlated"):
        """A rough metal from `conductor_preset(name)` ("gold", "silver", "copper",
        "aluminium") with a `distribution` ("ggx" or "beckmann") of roughness `alpha`."""
        if distribution not in _DISTRIBUTIONS:
            raise ValueError(f"`CookTorrance.rough_conductor(distribution={distribution!r})`:"
                             f" expected one of {sorted(_DISTRIBUTIONS)}")
        eta, k = conductor_preset(name)
        return cls(_DISTRIBUTIONS[distribution](alpha), ConductorFresnel(eta, k), geometry)

    def eval(self, wo, wi):
        spec = self.ks * microfacet_specular(self.distribution, self.geometry,
                                             self.fresnel, wo, wi)
        if self.diffuse is None:
            return spec
        return spec + jnp.where(above(wo, wi), self.diffuse / jnp.pi, 0.0)

    def base_color(self):
        if self.diffuse is not None:
            return self.diffuse
        return self.ks * self.fresnel(jnp.asarray(1.0))
