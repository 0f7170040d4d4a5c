"""Geometry (shadowing–masking) terms G(wo, wi, wm) of microfacet BRDFs.

Notes, "Geometry function"; Heitz 2014, "Understanding the Masking-Shadowing Function in
Microfacet-Based BRDFs" (JCGT 3(2)). Every term has the signature
`g(distribution, wo, wi, wm)` so that `CookTorrance` can pick one by name; the implicit
and V-groove terms ignore the distribution. Values are in [0, 1], finite, with finite
gradients, and 0 when either direction is below the horizon or sees the back of wm.
"""

import jax.numpy as jnp

from ..vecmath import dot, minimum, safe_div


def _visible(wo, wi, wm):
    return (dot(wo, wm) * wo[..., 2] > 0.0) & (dot(wi, wm) * wi[..., 2] > 0.0)


def g_implicit(distribution, wo, wi, wm):
    """Implicit G = (n·wi)(n·wo): cancels the 1/(4 (n·wi)(n·wo)) of Cook–Torrance."""
    del distribution
    ok = (wo[..., 2] > 0.0) & (wi[..., 2] > 0.0)
    return jnp.where(ok, wo[..., 2] * wi[..., 2], 0.0)


def g_cook_torrance(distribution, wo, wi, wm):
    """V-groove G = min(1, 2 (n·wm)(n·wo) / (wo·wm), 2 (n·wm)(n·wi) / (wi·wm)).

    Cook & Torrance 1982 (after Torrance & Sparrow 1967); notes, "Cook-Terrance".
    """
    del distribution
    ok = _visible(wo, wi, wm) & (wm[..., 2] > 0.0)
    nh = wm[..., 2]
    g_o = safe_div(2.0 * nh * wo[..., 2], dot(wo, wm), 1.0)
    g_i = safe_div(2.0 * nh * wi[..., 2], dot(wi, wm), 1.0)
    return jnp.where(ok, minimum(1.0, minimum(g_o, g_i)), 0.0)


def g_smith_separable(distribution, wo, wi, wm):
    """Separable Smith G = G1(wo, wm) G1(wi, wm) (notes, "Smith"; Heitz 2014 eq. 98)."""
    return distribution.g1(wo, wm) * distribution.g1(wi, wm)


def g_smith_correlated(distribution, wo, wi, wm):
    """Height-correlated Smith G = χ⁺ / (1 + Λ(wo) + Λ(wi)) (Heitz 2014 eq. 99).

    Written as 2 co ci / (2 co ci + N(wo) ci + N(wi) co) with N = 2 |cos| Λ, finite at
    grazing angles. Always ≥ the separable form.
    """
    co = jnp.abs(wo[..., 2])
    ci = jnp.abs(wi[..., 2])
    num = 2.0 * co * ci
    den = num + distribution.lambda_numerator(wo) * ci + distribution.lambda_numerator(wi) * co
    return jnp.where(_visible(wo, wi, wm), safe_div(num, den, 0.0), 0.0)


#: Geometry terms by the name `CookTorrance(geometry=...)` accepts.
GEOMETRY_TERMS = {
    "implicit": g_implicit,
    "cook_torrance": g_cook_torrance,
    "smith": g_smith_separable,
    "smith_correlated": g_smith_correlated,
}
