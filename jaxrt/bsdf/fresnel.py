"""Fresnel terms as small modules, so that a material's Fresnel choice is part of its
structure and its parameters are differentiable leaves.

Each is callable on cos θ (between the light direction and the microfacet normal) and
returns an RGB reflectance [3]. Formulas: `scattering.py`.
"""

import abc

import equinox as eqx
import jax.numpy as jnp

from ._util import scalar
from .base import rgb
from .scattering import fresnel_conductor, fresnel_dielectric, fresnel_schlick


class Fresnel(eqx.Module):
    """Abstract Fresnel term: `fresnel(cos_theta) -> [3]`."""

    @abc.abstractmethod
    def __call__(self, cos_theta):
        """Reflectance for unpolarised light, RGB [3]."""


class SchlickFresnel(Fresnel):
    """Schlick 1994: F = f0 + (1 − f0)(1 − cos θ)^5. Parameter `f0` (RGB, differentiable)."""

    f0: jnp.ndarray

    def __init__(self, f0=0.04):
        self.f0 = rgb(f0, "SchlickFresnel(f0=...)")

    def __call__(self, cos_theta):
        return fresnel_schlick(cos_theta, self.f0)


class DielectricFresnel(Fresnel):
    """Exact dielectric Fresnel with relative index `eta` (scalar, differentiable)."""

    eta: jnp.ndarray

    def __init__(self, eta=1.5):
        self.eta = scalar(eta, "DielectricFresnel(eta=...)")

    def __call__(self, cos_theta):
        return jnp.broadcast_to(fresnel_dielectric(cos_theta, self.eta), (3,))


class ConductorFresnel(Fresnel):
    """Exact conductor Fresnel with complex index `eta` + i `k` (RGB, differentiable)."""

    eta: jnp.ndarray
    k: jnp.ndarray

    def __init__(self, eta, k):
        self.eta = rgb(eta, "ConductorFresnel(eta=...)")
        self.k = rgb(k, "ConductorFresnel(k=...)")

    def __call__(self, cos_theta):
        return fresnel_conductor(cos_theta, self.eta, self.k)
