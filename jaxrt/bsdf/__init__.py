"""Scattering: reflect/refract, Fresnel, microfacet distributions and BRDF models."""

from .base import Material as Material
from .lambert import Lambert as Lambert
