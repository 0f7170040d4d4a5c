"""Ashikhmin–Shirley anisotropic Phong model, isotropic case."""

import jax.numpy as jnp

from ..vecmath import dot, maximum
from ._util import above, half_vector, pow_pos, scalar
from .base import Material, rgb
from .scattering import fresnel_schlick


class AshikhminShirley(Material):
    """Ashikhmin & Shirley 2000, "An anisotropic Phong BRDF model" (JGT 5(2)), with
    n_u = n_v = n:

        f_spec = (n + 1) / (8π) (n·wm)^n / ((wi·wm) max(cos θi, cos θo)) F(wi·wm),
        F = rs + (1 − rs)(1 − wi·wm)^5  (Schlick),
        f_diff = 28 rd / (23π) (1 − rs) (1 − (1 − cos θi / 2)^5) (1 − (1 − cos θo / 2)^5).

    Positive, reciprocal, and designed to conserve energy when rd, rs ≤ 1 (the diffuse
    term is the energy left by the specular coat; the coupling is approximate).

    Parameters (differentiable): `rd`, `rs` (RGB), exponent `n` ≥ 0 (scalar).
    """

    rd: jnp.ndarray
    rs: jnp.ndarray
    n: jnp.ndarray

    def __init__(self, rd=0.5, rs=0.05, n=100.0):
        self.rd = rgb(rd, "AshikhminShirley(rd=...)")
        self.rs = rgb(rs, "AshikhminShirley(rs=...)")
        self.n = scalar(n, "AshikhminShirley(n=...)")

    def eval(self, wo, wi):
        ok = above(wo, wi)
        n = jnp.maximum(self.n, 0.0)
        co = jnp.where(ok, wo[2], 1.0)
        ci = jnp.where(ok, wi[2], 1.0)
        wm = half_vector(wo, wi)
        hk = jnp.where(ok, dot(wi, wm), 1.0)
        spec = ((n + 1.0) / (8.0 * jnp.pi) * pow_pos(wm[2], n)
                / (hk * maximum(ci, co)) * fresnel_schlick(hk, self.rs))
        diff = (28.0 / (23.0 * jnp.pi) * self.rd * (1.0 - self.rs)
                * (1.0 - (1.0 - 0.5 * ci) ** 5) * (1.0 - (1.0 - 0.5 * co) ** 5))
        return jnp.where(ok, spec + diff, 0.0)

    def base_color(self):
        return self.rd
