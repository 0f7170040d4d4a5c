"""Microfacet normal distribution functions (NDFs) with their Smith masking functions.

Notes, "Normal Distribution Function": D(wm) gives the density of microfacet normals
wm, normalised so that ∫ D(wm) cos θm dωm = 1 (the projected microfacet area equals the
macro-surface area). Smith masking G1(w, wm) = χ⁺(w·wm / w·n) / (1 + Λ(w)) belongs to the
distribution through Λ (Heitz 2014, "Understanding the Masking-Shadowing Function in
Microfacet-Based BRDFs", JCGT 3(2)).

All directions are in the local frame (normal +z). Isotropic distributions only.

Numerics: Λ(w) = N(w) / (2 |cos θ|) with a numerator N that is finite at grazing
incidence; `g1` and the Smith geometry terms use N directly, so they are finite (0 at
grazing) where Λ itself is +∞. Roughness is clamped below by `MIN_ALPHA`.
"""

import abc

import equinox as eqx
import jax.numpy as jnp
import jax.scipy.special as jss

from ..vecmath import dot, maximum, safe_div, safe_sqrt

#: Roughness below this is treated as this value: D peaks at 1/(π α²) ≈ 3e7, which keeps
#: D · radiance far from float32 overflow; a smoother surface should be a `Mirror`.
MIN_ALPHA = 1e-4

_SQRT_PI = 1.7724538509055159


def _scalar(x, name):
    a = jnp.asarray(x, dtype=float)
    if a.ndim != 0:
        raise ValueError(f"`{name}` must be a scalar, got shape {a.shape}")
    return a


def _cos_sin2(w):
    c = w[..., 2]
    return c, maximum(0.0, 1.0 - c * c)


class MicrofacetDistribution(eqx.Module):
    """Abstract isotropic microfacet distribution: `d`, `lambda_`, `g1`."""

    @abc.abstractmethod
    def d(self, wm):
        """D(wm) for a unit microfacet normal `wm` [3]; 0 for wm below the horizon."""

    @abc.abstractmethod
    def lambda_numerator(self, w):
        """N(w) = 2 |cos θ| Λ(w) ≥ 0, finite for every direction (0 at normal incidence)."""

    def lambda_(self, w):
        """Smith Λ(w) = N(w) / (2 |cos θ|); +∞ exactly at grazing (cos θ = 0)."""
        c = jnp.abs(w[..., 2])
        return jnp.where(c > 0.0, safe_div(self.lambda_numerator(w), 2.0 * c), jnp.inf)

    def g1(self, w, wm):
        """Smith masking G1(w, wm) = χ⁺(w·wm / w·n) / (1 + Λ(w)) ∈ [0, 1].

        Written as 2|cos θ| / (2|cos θ| + N(w)): 1 at normal incidence, 0 at grazing,
        finite gradients everywhere.
        """
        c = jnp.abs(w[..., 2])
        visible = dot(w, wm) * w[..., 2] > 0.0
        g = safe_div(2.0 * c, 2.0 * c + self.lambda_numerator(w), 0.0)
        return jnp.where(visible, g, 0.0)


def _beckmann_lambda_numerator(w, alpha):
    """2|cos θ| Λ for Beckmann, exact: with a = 1 / (α tan θ),
    Λ(a) = (erf(a) − 1) / 2 + exp(−a²) / (2 a √π) (Walter et al. 2007, eq. 27 exact form;
    no rational approximation), so N = α sin θ exp(−a²) / √π − |cos θ| erfc(a).
    """
    c, sin2 = _cos_sin2(w)
    c = jnp.abs(c)
    s = safe_sqrt(sin2)
    ok = s > 0.0
    a = c / (alpha * jnp.where(ok, s, 1.0))
    n = alpha * s * jnp.exp(-a * a) / _SQRT_PI - c * jss.erfc(a)
    # N > 0 mathematically; rounding in the cancellation at large a can dip below 0.
    return jnp.where(ok, maximum(n, 0.0), 0.0)


def _beckmann_d(wm, alpha):
    c, sin2 = _cos_sin2(wm)
    ok = c > 0.0
    c_safe = jnp.where(ok, c, 1.0)
    # exp(−tan²θ / α²) / (π α² cos⁴θ), the cos⁻⁴ folded into the exponent so that the
    # gradient stays finite (not 0 · ∞) as cos θ → 0.
    expo = -sin2 / (alpha * alpha * c_safe * c_safe) - 4.0 * jnp.log(c_safe)
    return jnp.where(ok, jnp.exp(expo) / (jnp.pi * alpha * alpha), 0.0)


class GGX(MicrofacetDistribution):
    """Trowbridge–Reitz / GGX: D = α² / (π (cos²θm (α² − 1) + 1)²).

    Walter et al. 2007, "Microfacet Models for Refraction through Rough Surfaces";
    notes, "GGX distribution". Smith Λ in closed form,
    Λ(w) = (−1 + sqrt(1 + α² tan²θ)) / 2.

    Parameters (differentiable): `alpha` > 0, scalar roughness (clamped to `MIN_ALPHA`).
    """

    alpha: jnp.ndarray

    def __init__(self, alpha):
        self.alpha = _scalar(alpha, "GGX(alpha=...)")

    def d(self, wm):
        alpha = jnp.maximum(self.alpha, MIN_ALPHA)
        a2 = alpha * alpha
        c, sin2 = _cos_sin2(wm)
        den = c * c * a2 + sin2  # = cos²θ (α² − 1) + 1, without cancellation
        return jnp.where(c > 0.0, a2 / (jnp.pi * den * den), 0.0)

    def lambda_numerator(self, w):
        # 2|c|Λ = sqrt(c² + α² s²) − |c| = α² s² / (sqrt(c² + α² s²) + |c|).
        alpha = jnp.maximum(self.alpha, MIN_ALPHA)
        c, sin2 = _cos_sin2(w)
        c = jnp.abs(c)
        root = jnp.sqrt(c * c + alpha * alpha * sin2)  # ≥ α min(1, |c|)… > 0
        return alpha * alpha * sin2 / (root + c)


class Beckmann(MicrofacetDistribution):
    """Beckmann: D = exp(−tan²θm / α²) / (π α² cos⁴θm).

    Beckmann & Spizzichino 1963; notes, "Beckmann distribution". Smith Λ is the exact
    erf form (see `_beckmann_lambda_numerator`); no rational approximation is used.

    Parameters (differentiable): `alpha` > 0, RMS slope (clamped to `MIN_ALPHA`).
    """

    alpha: jnp.ndarray

    def __init__(self, alpha):
        self.alpha = _scalar(alpha, "Beckmann(alpha=...)")

    def d(self, wm):
        return _beckmann_d(wm, jnp.maximum(self.alpha, MIN_ALPHA))

    def lambda_numerator(self, w):
        return _beckmann_lambda_numerator(w, jnp.maximum(self.alpha, MIN_ALPHA))


class PhongNDF(MicrofacetDistribution):
    """Phong (Blinn) distribution: D = (α_p + 2) / (2π) cos^α_p θm.

    Notes, "Phong distribution"; Walter et al. 2007, eq. 30. It has no closed-form Smith
    Λ; we use Beckmann's Λ at the corresponding roughness α_b = sqrt(2 / (α_p + 2))
    (notes: α_p = 2 α_b⁻² − 2; Walter et al. 2007 §5.2). This Λ is only approximately
    Smith-consistent with the Phong D: ∫ G1 <wo·wm>⁺ D dωm = cos θo holds to 1.3 % up to
    80° for α_p ≥ 20, but is 17 % off at 80° for α_p = 2 (tests/test_bsdf_microfacet.py).

    Parameters (differentiable): `exponent` α_p ≥ 0 (negative values are clamped to 0).
    """

    exponent: jnp.ndarray

    def __init__(self, exponent):
        self.exponent = _scalar(exponent, "PhongNDF(exponent=...)")

    def d(self, wm):
        p = jnp.maximum(self.exponent, 0.0)
        c = wm[..., 2]
        ok = c > 0.0
        # cos^p as exp(p log cos) with a guarded log: finite gradient in p at cos → 0.
        cp = jnp.exp(p * jnp.log(jnp.where(ok, c, 1.0)))
        return jnp.where(ok, (p + 2.0) / (2.0 * jnp.pi) * cp, 0.0)

    def lambda_numerator(self, w):
        p = jnp.maximum(self.exponent, 0.0)
        return _beckmann_lambda_numerator(w, phong_exponent_to_beckmann_alpha(p))


def phong_exponent_to_beckmann_alpha(exponent):
    """α_b = sqrt(2 / (α_p + 2)), the inverse of α_p = 2 α_b⁻² − 2 (notes; Walter et al.
    2007 eq. 32). Both NDFs then have the same peak D(n) = 1 / (π α_b²)."""
    return jnp.sqrt(2.0 / (jnp.maximum(exponent, 0.0) + 2.0))


def beckmann_alpha_to_phong_exponent(alpha):
    """α_p = 2 α_b⁻² − 2 (notes, "Beckmann distribution")."""
    alpha = jnp.maximum(alpha, MIN_ALPHA)
    return 2.0 / (alpha * alpha) - 2.0


def phong_exponent_to_ggx_alpha(exponent):
    """GGX roughness with the same peak value as Phong: α = sqrt(2 / (α_p + 2)).

    An approximation: GGX has much longer tails than Phong; only the peak height (and so
    the curvature of the highlight at its centre) matches.
    """
    return phong_exponent_to_beckmann_alpha(exponent)


def ggx_alpha_to_phong_exponent(alpha):
    """Inverse of `phong_exponent_to_ggx_alpha`: α_p = 2 α⁻² − 2."""
    return beckmann_alpha_to_phong_exponent(alpha)
