"""The interface every material implements.

A material is an equinox Module whose floats are differentiable leaves. Directions are
in the local shading frame (normal along +z) and point away from the surface (pbrt's
convention): `wo` towards the viewer, `wi` towards the light.
"""

import abc
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp


class Material(eqx.Module):
    """Abstract base of all materials.

    Static class flags tell the integrator which branches of the ray tree a material
    needs, so that a scene compiles only what it uses:

    - `has_diffuse`: `eval` is not identically zero (direct lighting is computed).
    - `has_reflection`: it spawns an ideal-specular reflected ray (Whitted recursion).
    - `has_transmission`: it spawns a refracted ray.
    - `is_dispersive`: its index of refraction depends on wavelength.
    """

    has_diffuse: ClassVar[bool] = True
    has_reflection: ClassVar[bool] = False
    has_transmission: ClassVar[bool] = False
    is_dispersive: ClassVar[bool] = False

    @abc.abstractmethod
    def eval(self, wo, wi):
        """BRDF value f_r(wo, wi) as linear RGB, shape [3], without the cosine factor."""

    @abc.abstractmethod
    def base_color(self):
        """A representative base colour (linear RGB, [3]) for the `albedo` AOV."""

    def ambient(self):
        """Radiance added once per hit regardless of lights (Phong's ambient term).

        Zero for every physically based model.
        """
        return jnp.zeros(3)


def rgb(x, name):
    """Broadcast a scalar or 3-sequence to a float RGB array of shape [3]."""
    a = jnp.asarray(x, dtype=float)
    if a.ndim == 0:
        a = jnp.full((3,), a)
    if a.shape != (3,):
        raise ValueError(f"`{name}` must be a number or 3 numbers (RGB), got shape {a.shape}")
    return a
