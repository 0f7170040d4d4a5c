"""Ideal specular materials for Whitted recursion: mirror, glass/water, metal, and the
notes' classic material with constant weights.

Notes, "Ray tracing": color = directIllumination + c_refl · trace(reflected ray) +
c_trans · trace(refracted ray). These materials supply the weights. Each has

    specular(cos_o, wavelength=None) -> (c_refl [3], c_trans [3], eta)

where `cos_o = n · wo` is the cosine between the outward surface normal `n` and the
direction towards the viewer `wo` (positive: the ray arrives from outside; negative:
from inside the object), `c_refl`/`c_trans` are the RGB weights of the mirror-reflected
and refracted rays, and `eta = n_inside / n_outside` is the relative index that bends the
refracted ray (`jaxrt.bsdf.refract(wo, n, eta)` handles both sides). The outside medium
is vacuum/air (index 1): nested dielectrics are not modelled.

A smooth specular surface has no BRDF lobe that a point light can hit (a delta), so
`eval` is zero and direct lighting skips these materials, except `Whitted`, which
carries an ordinary BRDF (`base`) for its direct term.

Static flags (what the integrator compiles): Mirror and Conductor reflect; Dielectric
reflects and refracts, and is dispersive when its `eta` is a wavelength model; Whitted
reflects, refracts only when it has a `c_trans`, and is lit directly when it has a
`base`.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._util import scalar
from .base import Material, rgb
from .conductors import conductor_preset
from .scattering import fresnel_conductor, fresnel_dielectric
from ..vecmath import minimum, safe_div

#: Wavelength (nm) at which a dispersive index is evaluated in RGB rendering: the
#: helium d line, where catalogues quote n_d.
REFERENCE_WAVELENGTH_NM = 587.5618


def _check_positive(x, name):
    if not isinstance(x, jax.core.Tracer) and not np.all(np.asarray(x) > 0):
        raise ValueError(f"`{name}` must be > 0, got {np.asarray(x).tolist()}")


def _check_nonnegative(x, name):
    if not isinstance(x, jax.core.Tracer) and not np.all(np.asarray(x) >= 0):
        raise ValueError(f"`{name}` must be ≥ 0, got {np.asarray(x).tolist()}")


class Mirror(Material):
    """Ideal mirror: all light leaves along r = 2 (n·wo) n − wo, scaled by `tint`.

    c_refl = tint, c_trans = 0 (the notes' "perfect mirror"; a constant c_refl).
    Parameters (differentiable): `tint`, linear RGB in [0, 1].
    """

    tint: jnp.ndarray

    has_diffuse = False
    has_reflection = True

    def __init__(self, tint=(1.0, 1.0, 1.0)):
        self.tint = rgb(tint, "Mirror(tint=...)")
        _check_nonnegative(self.tint, "Mirror(tint=...)")

    def eval(self, wo, wi):
        return jnp.zeros_like(self.tint)

    def base_color(self):
        return self.tint

    def ambient(self):
        return jnp.zeros_like(self.tint)

    def specular(self, cos_o, wavelength=None):
        return self.tint, jnp.zeros_like(self.tint), jnp.ones_like(self.tint[0])


class Dielectric(Material):
    """Smooth dielectric interface (glass, water): exact Fresnel split into a reflected
    and a refracted ray, total internal reflection, Beer–Lambert absorption inside.

    c_refl = F(cos θo, η),  c_trans = (1 − F) / η'²,

    F the unpolarised Fresnel reflectance (`fresnel_dielectric`; 1 under total internal
    reflection, so TIR sends everything to the reflected ray), η' = n_t / n_i along the
    camera ray (η entering, 1/η leaving). The 1/η'² is the radiance scaling across an
    interface (radiance transport, pbrt-v4 `DielectricBxDF`, Veach 1997 §5.2); it cancels
    on a path that enters and leaves, and F + (1 − F) = 1 conserves flux.

    Inside, radiance decays as exp(−σ_a · distance) (Beer–Lambert); the integrator applies
    it along every segment that travels inside the object.

    Parameters:
      eta         index of the inside relative to the outside (> 0; 1.5 glass,
                  1.333 water): a number (differentiable), or a wavelength model from
                  `jaxrt.spectral` (Cauchy/Sellmeier, or a preset name such as "bk7",
                  "water", "diamond"), which makes the material dispersive: spectral rendering evaluates it per wavelength sample, RGB
                  rendering at REFERENCE_WAVELENGTH_NM.
      absorption  σ_a, RGB absorption coefficient per unit length, ≥ 0 (differentiable;
                  0: clear).
    """

    eta: object
    absorption: jnp.ndarray

    has_diffuse = False
    has_reflection = True
    has_transmission = True

    def __init__(self, eta=1.5, absorption=0.0):
        if isinstance(eta, str):
            from ..spectral import ior_preset

            eta = ior_preset(eta)
        if isinstance(eta, eqx.Module):
            self.eta = eta
        else:
            self.eta = scalar(eta, "Dielectric(eta=...)")
            _check_positive(self.eta, "Dielectric(eta=...)")
        self.absorption = rgb(absorption, "Dielectric(absorption=...)")
        _check_nonnegative(self.absorption, "Dielectric(absorption=...)")

    @property
    def is_dispersive(self):
        """True when `eta` is a wavelength model that depends on λ (static)."""
        return isinstance(self.eta, eqx.Module) and bool(getattr(self.eta, "is_dispersive", True))

    def ior(self, wavelength=None):
        """η at `wavelength` (nm; None: RGB rendering, REFERENCE_WAVELENGTH_NM)."""
        if not isinstance(self.eta, eqx.Module):
            return self.eta
        lam = REFERENCE_WAVELENGTH_NM if wavelength is None else wavelength
        return jnp.asarray(self.eta(lam), self.absorption.dtype)

    def eval(self, wo, wi):
        return jnp.zeros_like(self.absorption)

    def base_color(self):
        return jnp.ones_like(self.absorption)

    def ambient(self):
        return jnp.zeros_like(self.absorption)

    def specular(self, cos_o, wavelength=None):
        eta = self.ior(wavelength)
        f = fresnel_dielectric(cos_o, eta)
        eta_p = jnp.where(cos_o >= 0.0, eta, safe_div(1.0, eta, 1.0))
        t = safe_div(1.0 - f, eta_p * eta_p)
        one = jnp.ones_like(self.absorption)
        return f * one, t * one, eta


class Conductor(Material):
    """Smooth metal: a mirror whose reflectance is the exact conductor Fresnel term.

    c_refl = F_conductor(cos θo; η + iκ) per RGB channel (`fresnel_conductor`), c_trans = 0
    (light that enters a metal is absorbed within nanometres). Rough metals are the
    microfacet models of `cook_torrance.py`, lit directly.

    Parameters (differentiable): `eta`, `k`, RGB real and imaginary parts of the complex
    index relative to the outside. `Conductor("gold")` takes them from
    `CONDUCTOR_PRESETS` (gold, silver, copper, aluminium).
    """

    eta: jnp.ndarray
    k: jnp.ndarray

    has_diffuse = False
    has_reflection = True

    def __init__(self, eta="silver", k=None):
        if isinstance(eta, str):
            if k is not None:
                raise ValueError(f"`Conductor(eta={eta!r}, k=...)`: give a preset name or (eta, k), not both")
            eta, k = conductor_preset(eta)
        elif k is None:
            raise ValueError("`Conductor(k=...)` is required when `eta` is not a preset name")
        self.eta = rgb(eta, "Conductor(eta=...)")
        self.k = rgb(k, "Conductor(k=...)")
        _check_positive(self.eta, "Conductor(eta=...)")
        _check_nonnegative(self.k, "Conductor(k=...)")

    def eval(self, wo, wi):
        return jnp.zeros_like(self.eta)

    def base_color(self):
        return fresnel_conductor(1.0, self.eta, self.k)

    def ambient(self):
        return jnp.zeros_like(self.eta)

    def specular(self, cos_o, wavelength=None):
        return (fresnel_conductor(cos_o, self.eta, self.k), jnp.zeros_like(self.eta),
                jnp.ones_like(self.eta[0]))


class Whitted(Material):
    """The notes' classic material: a directly lit BRDF plus constant weights,
    color = direct(base) + c_refl · trace(reflected) + c_trans · trace(refracted).

    Constant weights are the hack of Whitted 1980: they do not depend on the angle (no
    Fresnel) and need not conserve energy. Under total internal reflection the
    transmitted weight joins the reflected one (c_refl + c_trans, 0).

    Parameters:
      base     a material lit by direct illumination (e.g. `Phong`, `Lambert`), or
               None for a purely specular surface.
      c_refl   RGB weight of the reflected ray (differentiable).
      c_trans  RGB weight of the refracted ray (differentiable), or None: opaque, and
               the scene compiles no refraction rays for it.
      eta      index of the inside relative to the outside, bends the refracted ray
               (differentiable; only used with `c_trans`).
    """

    base: Material | None
    c_refl: jnp.ndarray
    c_trans: jnp.ndarray | None
    eta: jnp.ndarray

    has_reflection = True

    def __init__(self, base=None, c_refl=0.5, c_trans=None, eta=1.5):
        if base is not None and not isinstance(base, Material):
            raise TypeError(f"`Whitted(base=...)` must be a jaxrt.bsdf material or None, got {type(base).__name__}")
        if base is not None and (base.has_reflection or base.has_transmission):
            raise ValueError("`Whitted(base=...)` must be a directly lit material, not a specular one")
        self.base = base
        self.c_refl = rgb(c_refl, "Whitted(c_refl=...)")
        self.c_trans = None if c_trans is None else rgb(c_trans, "Whitted(c_trans=...)")
        self.eta = scalar(eta, "Whitted(eta=...)")
        _check_positive(self.eta, "Whitted(eta=...)")

    @property
    def has_diffuse(self):
        """Lit directly when it has a `base` with a BRDF (static)."""
        return self.base is not None and self.base.has_diffuse

    @property
    def has_transmission(self):
        """Spawns refracted rays when it has a `c_trans` (static)."""
        return self.c_trans is not None

    def eval(self, wo, wi):
        if self.base is None:
            return jnp.zeros_like(self.c_refl)
        return self.base.eval(wo, wi)

    def base_color(self):
        return self.c_refl if self.base is None else self.base.base_color()

    def ambient(self):
        return jnp.zeros_like(self.c_refl) if self.base is None else self.base.ambient()

    def specular(self, cos_o, wavelength=None):
        if self.c_trans is None:
            return self.c_refl, jnp.zeros_like(self.c_refl), jnp.ones_like(self.eta)
        # Total internal reflection: sin²θt = sin²θo / η'² ≥ 1, η' = η (entering) or 1/η.
        eta_p = jnp.where(cos_o >= 0.0, self.eta, safe_div(1.0, self.eta, 1.0))
        sin2_t = safe_div(1.0 - minimum(cos_o * cos_o, 1.0), eta_p * eta_p, 1.0)
        tir = sin2_t >= 1.0
        return (jnp.where(tir, self.c_refl + self.c_trans, self.c_refl),
                jnp.where(tir, 0.0, self.c_trans), self.eta)
