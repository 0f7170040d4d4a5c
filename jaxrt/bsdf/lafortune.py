"""Lafortune's generalised cosine lobes."""

import jax.numpy as jnp

from ._util import above, pow_pos
from .base import Material, rgb


class Lafortune(Material):
    """Lafortune et al. 1997, "Non-linear approximation of reflectance functions"
    (isotropic, C_x = C_y):

        f_r = kd / π + Σ_j ks_j [cxy_j (wo_x wi_x + wo_y wi_y) + cz_j wo_z wi_z]^n_j,

    a lobe being 0 where its bracket is ≤ 0. cxy = −1, cz = 1 gives the Phong lobe
    (wo·r)^n; |cxy| > cz moves the lobe towards grazing (off-specular); cxy > 0 gives
    retro-reflection. Positive and reciprocal; its energy depends on the parameters
    (a lobe with cxy = −1, cz = 1 conserves energy when ks ≤ (n + 2) / (2π)).

    Parameters (differentiable): `kd` (RGB), per lobe `cxy`, `cz`, `n` (shape [L]) and
    `ks` (shape [L, 3]; a scalar or an RGB triple is shared by all lobes). The number of
    lobes L comes from the shapes (static).
    """

    kd: jnp.ndarray
    ks: jnp.ndarray
    cxy: jnp.ndarray
    cz: jnp.ndarray
    n: jnp.ndarray

    def __init__(self, kd=0.5, ks=1.0, cxy=-1.0, cz=1.0, n=20.0):
        self.kd = rgb(kd, "Lafortune(kd=...)")
        cxy, cz, n = (jnp.atleast_1d(jnp.asarray(x, dtype=float)) for x in (cxy, cz, n))
        if not (cxy.ndim == cz.ndim == n.ndim == 1 and cxy.shape == cz.shape == n.shape):
            raise ValueError("`Lafortune(cxy=..., cz=..., n=...)` must be scalars or 1-D "
                             f"arrays of one length, got shapes {cxy.shape}, {cz.shape}, "
                             f"{n.shape}")
        num_lobes = n.shape[0]
        ks = jnp.asarray(ks, dtype=float)
        if ks.ndim == 0 or ks.shape == (3,):
            ks = jnp.broadcast_to(ks, (num_lobes, 3))
        if ks.shape != (num_lobes, 3):
            raise ValueError(f"`Lafortune(ks=...)` must be a scalar, RGB or shape "
                             f"({num_lobes}, 3), got {ks.shape}")
        self.ks, self.cxy, self.cz, self.n = ks, cxy, cz, n

    def eval(self, wo, wi):
        base = self.cxy * (wo[0] * wi[0] + wo[1] * wi[1]) + self.cz * wo[2] * wi[2]
        lobes = pow_pos(base, jnp.maximum(self.n, 0.0))  # [L]
        f = self.kd / jnp.pi + jnp.sum(self.ks * lobes[:, None], axis=0)
        return jnp.where(above(wo, wi), f, 0.0)

    def base_color(self):
        return self.kd
