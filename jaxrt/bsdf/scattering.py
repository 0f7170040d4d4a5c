"""Scattering at an optically flat interface: reflection, refraction and Fresnel.

Notes, "Physics of shading": Snell–Descartes laws, total internal reflection, Fresnel
reflectance and Schlick's approximation. Directions point away from the surface
(pbrt's convention). Every function works on one direction; `vmap` it for many.

Index convention (pbrt-v4, `scattering.h`): `n` is a unit normal and `eta` is the ratio
n_below / n_above of the indices on the two sides of the interface, where "above" is the
side `n` points to. When `wi` (or `cos_theta_i > 0`) is on the side of `n` this is
exactly eta = n_transmitted / n_incident. Light arriving from below (`dot(wi, n) < 0`,
`cos_theta_i < 0`) is handled internally by flipping `n` and using 1/eta, so the caller
passes the same `eta` for both sides of one surface.
"""

import jax.numpy as jnp

from ..vecmath import clip, dot, maximum, minimum, safe_div, safe_sqrt


def reflect(wi, n):
    """Mirror direction r = 2 (n·wi) n − wi (notes, "Snell Descartes laws"); |r| = |wi|.

    Args:
        wi: [3] direction pointing away from the surface.
        n: [3] unit normal (either side).
    """
    return 2.0 * dot(n, wi)[..., None] * n - wi


def refract(wi, n, eta):
    """Refracted direction by Snell's law, n_i sin θi = n_t sin θt.

    wt = −wi / eta + (cos θi / eta − cos θt) n, with sin²θt = sin²θi / eta²
    (notes, "Snell Descartes laws", with η_r = 1 / eta).

    Args:
        wi: [3] unit direction pointing away from the surface, on either side.
        n: [3] unit normal.
        eta: scalar, n_below / n_above (see the module docstring); = n_t / n_i when
            `wi` is on the side of `n`. Must be > 0.

    Returns:
        `(wt, is_valid)`: `wt` [3] unit transmitted direction on the opposite side from
        `wi`; `is_valid` is False under total internal reflection, where `wt` is the
        mirror direction `reflect(wi, n)` (finite, and what the light actually does).
    """
    cos_i = dot(n, wi)
    inside = cos_i < 0.0
    eta = jnp.where(inside, safe_div(1.0, eta, 1.0), eta)
    n = jnp.where(inside, -n, n)
    cos_i = minimum(jnp.abs(cos_i), 1.0)
    # cos²θt = 1 − sin²θi / eta² = (eta² − 1 + cos²θi) / eta², in the form that is exact
    # for eta = 1 (no cancellation near grazing).
    cos2_t = safe_div(eta * eta - 1.0 + cos_i * cos_i, eta * eta, -1.0)
    is_valid = cos2_t > 0.0
    # safe_sqrt: finite gradient exactly at the critical angle (cos θt = 0).
    cos_t = safe_sqrt(cos2_t)
    inv_eta = safe_div(1.0, eta, 1.0)
    wt = -wi * inv_eta + (cos_i * inv_eta - cos_t) * n
    return jnp.where(is_valid, wt, reflect(wi, n)), is_valid


def fresnel_schlick(cos_theta, f0):
    """Schlick's approximation F = f0 + (1 − f0)(1 − cos θ)^5 (notes, "Fresnel reflectance").

    Args:
        cos_theta: scalar, cosine between the direction and the (micro)normal; clamped to
            [0, 1] (negative values are treated as grazing).
        f0: reflectance at normal incidence, scalar or [3].
    """
    c = clip(cos_theta, 0.0, 1.0)
    return f0 + (1.0 - f0) * (1.0 - c) ** 5


def f0_from_eta(eta):
    """Normal-incidence reflectance of a dielectric, F0 = ((eta − 1) / (eta + 1))²."""
    return ((eta - 1.0) / (eta + 1.0)) ** 2


def fresnel_dielectric(cos_theta_i, eta):
    """Exact Fresnel reflectance of a dielectric interface for unpolarised light.

    F = (r_par² + r_perp²) / 2 with
    r_par = (eta cos θi − cos θt) / (eta cos θi + cos θt),
    r_perp = (cos θi − eta cos θt) / (cos θi + eta cos θt),
    sin²θt = sin²θi / eta² (pbrt-v4 `FrDielectric`; Born & Wolf §1.5).

    Args:
        cos_theta_i: scalar in [−1, 1]; negative means the light arrives from the side
            opposite the normal, handled by using 1/eta (see module docstring).
        eta: n_below / n_above (= n_t / n_i for cos_theta_i > 0), > 0.

    Returns:
        F in [0, 1]: 1 under total internal reflection (and continuous at the critical
        angle), 0 when eta = 1, 1 at grazing incidence when eta ≠ 1. Finite values and
        gradients everywhere, including cos θ = 0, 1, eta = 1 and the critical angle.
    """
    inside = cos_theta_i < 0.0
    eta = jnp.where(inside, safe_div(1.0, eta, 1.0), eta)
    cos_i = minimum(jnp.abs(cos_theta_i), 1.0)
    # cos²θt = (eta² − 1 + cos²θi) / eta²: exact for eta = 1.
    cos2_t = safe_div(eta * eta - 1.0 + cos_i * cos_i, eta * eta, -1.0)
    # At cos θt = 0 exactly the formula below gives 1 too, except at grazing with
    # eta = 1, where both denominators vanish: there is no interface and F = 0.
    tir = cos2_t < 0.0
    cos_t = safe_sqrt(cos2_t)
    r_par = safe_div(eta * cos_i - cos_t, eta * cos_i + cos_t, 0.0)
    r_perp = safe_div(cos_i - eta * cos_t, cos_i + eta * cos_t, 0.0)
    f = 0.5 * (r_par * r_par + r_perp * r_perp)
    return jnp.where(tir, 1.0, f)


def fresnel_conductor(cos_theta_i, eta, k):
    """Exact Fresnel reflectance at a conductor with complex index eta + i k (unpolarised).

    Real-arithmetic form of the complex Fresnel equations (pbrt-v3 `FrConductor`,
    after Glassner, "Principles of Digital Image Synthesis", 1995):
    a² + b² = sqrt((eta² − k² − sin²θ)² + 4 eta² k²), a = sqrt((a² + b² + eta² − k² − sin²θ) / 2),
    Rs = (a² + b² + cos²θ − 2a cosθ) / (a² + b² + cos²θ + 2a cosθ),
    Rp = Rs (cos²θ (a² + b²) + sin⁴θ − 2a cosθ sin²θ) / (cos²θ (a² + b²) + sin⁴θ + 2a cosθ sin²θ),
    F = (Rs + Rp) / 2.

    Args:
        cos_theta_i: scalar; its absolute value is used (a conductor is opaque).
        eta, k: real and imaginary parts of the index relative to the outside medium,
            scalars or [3] (RGB); the result broadcasts to their shape.
    """
    cos_i = minimum(jnp.abs(cos_theta_i), 1.0)
    cos2 = cos_i * cos_i
    sin2 = maximum(0.0, 1.0 - cos2)
    eta2 = eta * eta
    k2 = k * k
    t0 = eta2 - k2 - sin2
    a2_plus_b2 = safe_sqrt(t0 * t0 + 4.0 * eta2 * k2)
    a = safe_sqrt(0.5 * (a2_plus_b2 + t0))
    t1 = a2_plus_b2 + cos2
    t2 = 2.0 * cos_i * a
    rs = safe_div(t1 - t2, t1 + t2, 1.0)
    t3 = cos2 * a2_plus_b2 + sin2 * sin2
    t4 = t2 * sin2
    rp = rs * safe_div(t3 - t4, t3 + t4, 1.0)
    return 0.5 * (rp + rs)
