"""Blinn–Phong weighted by Schlick's Fresnel, in the classic (non-physical) form.

This is the shading of NVIDIA Warp's ray-marching example, kept so that the shared
benchmark scene (`configs/scenes/warp_raymarch.toml`) is the same picture.
"""

import jax.numpy as jnp

from ..vecmath import clip, normalize, safe_div
from .base import Material, rgb


class FresnelBlinnPhong(Material):
    """f_r · cos θi = scale · color · [(1 − F) cos θi + specular · F · (n·h)^exponent],

    with F = f0 + (1 − f0)(1 − h·wi)⁵ (Schlick) and h the half vector of wo and wi.
    The specular lobe is not multiplied by cos θi, as in the classic Phong of the notes,
    so the model is not energy conserving and not reciprocal: a labelled hack.

    Differentiable: `color`, `specular`, `exponent`, `f0`, `scale`.
    """

    color: jnp.ndarray
    specular: jnp.ndarray
    exponent: jnp.ndarray
    f0: jnp.ndarray
    scale: jnp.ndarray

    def __init__(self, color=(1.0, 1.0, 1.0), specular=10.0, exponent=80.0, f0=0.04, scale=1.0):
        self.color = rgb(color, "FresnelBlinnPhong(color=...)")
        self.specular = jnp.asarray(specular, dtype=float)
        self.exponent = jnp.asarray(exponent, dtype=float)
        self.f0 = jnp.asarray(f0, dtype=float)
        self.scale = jnp.asarray(scale, dtype=float)

    def eval(self, wo, wi):
        cos_i = wi[2]
        above = (wo[2] > 0.0) & (cos_i > 0.0)
        h = normalize(wo + wi)
        fresnel = self.f0 + (1.0 - self.f0) * clip(1.0 - jnp.sum(h * wi), 0.0, 1.0) ** 5
        lobe = clip(h[2], 0.0, 1.0) ** self.exponent
        value = (1.0 - fresnel) + self.specular * fresnel * safe_div(lobe, jnp.where(above, cos_i, 1.0))
        return jnp.where(above, self.scale * self.color * value, 0.0)

    def base_color(self):
        return self.color
