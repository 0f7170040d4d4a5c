"""Spectral rendering: wavelength samples, dispersion models, spectra ──► colour.

Refraction depends on wavelength (notes, "Refraction is wavelength dependent": the prism
and the rainbow). A spectral render traces N wavelengths λᵢ instead of three RGB
channels; every quantity carried along a ray is then a value per λᵢ, and the pixel's
spectrum becomes colour at the end:

    spectrum s(λᵢ) ──(CIE 1931 2° colour matching functions, D65)──► XYZ ──► linear sRGB

Conventions (one ray, one point: every function works on one spectrum; vmap it):

- Wavelengths are in nanometres; `sample_wavelengths(n)` stratifies 380–780 nm.
- Spectra are *relative to D65*, the white point of sRGB: the light that a renderer
  carries is s(λ)·D65(λ), so a spectrum of ones is D65 white, and RGB light colours and
  reflectances turn into spectra by the same linear map (`rgb_to_spectrum`, the
  Mallett–Yuksel 2019 basis, which is built for reflectances under D65). Because D65 is
  a common factor of every path, it is applied once, in `spectrum_to_xyz`.
- `spectrum_to_xyz` is a self-normalised quadrature: each of X, Y, Z is the
  D65·CMF-weighted mean of the samples, scaled to the XYZ of sRGB white,

      X = X_w · Σᵢ s(λᵢ) D65(λᵢ) x̄(λᵢ) / Σᵢ D65(λᵢ) x̄(λᵢ)      (likewise Y, Z),

  so a flat spectrum of ones is exactly the white point for any N and any samples,
  and for many samples it converges to X_w ∫ s D65 x̄ dλ / ∫ D65 x̄ dλ.
- `spectrum_to_rgb` = C · M · XYZ, M the XYZ → linear sRGB matrix (IEC 61966-2-1, from
  colour-science) and C = (M · XYZ(basis))⁻¹ a 3×3 calibration that makes
  rgb → spectrum → rgb the identity for the wavelengths given (C → I as N grows:
  ‖C − I‖ ≈ 2·10⁻² at N = 32, 10⁻³ at N = 64). A flat spectrum of ones gives
  (1, 1, 1) (to ~1e-5, the basis's own sum-to-one error).

Tables (CIE 1931 2° CMFs, D65, the Mallett–Yuksel basis) come from colour-science,
aligned to a 1 nm grid over 360–830 nm on first use, and are interpolated linearly.

Indices of refraction: `Cauchy` and `Sellmeier` Modules (differentiable coefficients),
called on a wavelength in nm, with published presets `BK7`, `FUSED_SILICA`, `WATER`,
`DIAMOND`, `SF11`, `CAUCHY_BK7`; `ConstantIOR` for a non-dispersive index.
"""

import functools
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._colour import colour as _colour
from .vecmath import safe_div, safe_sqrt

#: The visible range that wavelengths are sampled from (nm).
LAMBDA_MIN = 380.0
LAMBDA_MAX = 780.0

#: Fraunhofer lines (nm; Schott data sheets): F (hydrogen, blue), d (helium, yellow),
#: D (sodium doublet centre), C (hydrogen, red).
FRAUNHOFER = {"F": 486.1327, "d": 587.5618, "D": 589.2938, "C": 656.2725}


# ---------------------------------------------------------------------------------------
# wavelength samples


def sample_wavelengths(n, offset=0.5, dtype=None):
    """n stratified wavelengths over 380–780 nm: λᵢ = 380 + (i + uᵢ) · 400 / n.

    Args:
      n: static number of samples (≥ 1).
      offset: uᵢ ∈ [0, 1), a scalar or [n] array: 0.5 (default) gives the stratum
        midpoints; a fixed or per-pixel random jitter gives stratified sampling.
      dtype: float dtype of the result (default: that of `offset`, else the default).

    Returns: [n] wavelengths in nm, increasing.
    """
    if not isinstance(n, (int, np.integer)) or isinstance(n, bool) or n < 1:
        raise ValueError(f"`sample_wavelengths(n=...)` must be an integer ≥ 1, got {n!r}")
    offset = jnp.asarray(offset, dtype=dtype)
    if offset.ndim > 0 and offset.shape != (n,):
        raise ValueError(f"`sample_wavelengths(offset=...)` must be a scalar or shape ({n},), got {offset.shape}")
    if not jnp.issubdtype(offset.dtype, jnp.floating):
        offset = offset.astype(float)
    i = jnp.arange(n, dtype=offset.dtype)
    return LAMBDA_MIN + (i + offset) * ((LAMBDA_MAX - LAMBDA_MIN) / n)


# ---------------------------------------------------------------------------------------
# tables from colour-science (numpy, built on first use)


@functools.lru_cache(maxsize=None)
def _tables():
    """1 nm tables over 360–830 nm: wavelengths, CMFs [.,3], D65 [.], basis [.,3], M, X_w."""
    colour = _colour()  # imported here: colour-science is slow to import and needed only here

    shape = colour.SpectralShape(360, 830, 1)
    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"].copy().align(shape)
    d65 = colour.SDS_ILLUMINANTS["D65"].copy().align(shape)
    basis = colour.recovery.MSDS_BASIS_FUNCTIONS_sRGB_MALLETT2019.copy().align(shape)
    m = np.asarray(colour.RGB_COLOURSPACES["sRGB"].matrix_XYZ_to_RGB, dtype=np.float64)
    white = np.linalg.solve(m, np.ones(3))  # XYZ of sRGB (1, 1, 1): D65 with Y ≈ 1
    return {
        "wavelengths": np.asarray(cmfs.wavelengths, np.float64),
        "cmfs": np.asarray(cmfs.values, np.float64),
        "d65": np.asarray(d65.values, np.float64) / 100.0,
        "basis": np.asarray(basis.values, np.float64),
        "xyz_to_rgb": m,
        "xyz_white": white,
    }


def _interp(wavelengths, name):
    """Linear interpolation of a tabulated [K] or [K, C] table at `wavelengths` [N]."""
    t = _tables()
    lam = jnp.asarray(t["wavelengths"], wavelengths.dtype)
    table = jnp.asarray(t[name], wavelengths.dtype)
    if table.ndim == 1:
        return jnp.interp(wavelengths, lam, table)
    return jnp.stack([jnp.interp(wavelengths, lam, table[:, k]) for k in range(table.shape[1])], axis=-1)


def _as_wavelengths(wavelengths, name):
    w = jnp.asarray(wavelengths)
    if not jnp.issubdtype(w.dtype, jnp.floating):
        w = w.astype(float)
    if w.ndim != 1:
        raise ValueError(f"`{name}(wavelengths=...)` must have shape [N], got {w.shape}")
    return w


@jax.jit
def cmf(wavelengths):
    """CIE 1931 2° colour-matching functions x̄, ȳ, z̄ at `wavelengths` [N] (nm): [N, 3]."""
    return _interp(_as_wavelengths(wavelengths, "cmf"), "cmfs")


@jax.jit
def illuminant_d65(wavelengths):
    """Relative spectral power of CIE D65 at `wavelengths` [N] (nm), 1 at 560 nm: [N]."""
    return _interp(_as_wavelengths(wavelengths, "illuminant_d65"), "d65")


def xyz_to_rgb_matrix(dtype=float):
    """The XYZ → linear sRGB matrix (IEC 61966-2-1, D65 white; colour-science), [3, 3]."""
    return jnp.asarray(_tables()["xyz_to_rgb"], dtype)


def white_point_xyz(dtype=float):
    """XYZ of linear sRGB (1, 1, 1): the D65 white point with Y ≈ 1, [3]."""
    return jnp.asarray(_tables()["xyz_white"], dtype)


# ---------------------------------------------------------------------------------------
# spectra ──► colour, and back


def _xyz_weights(wavelengths):
    """[N, 3] quadrature weights wᵢ = X_w D65(λᵢ) cmf(λᵢ) / Σⱼ D65(λⱼ) cmf(λⱼ)."""
    w = illuminant_d65(wavelengths)[:, None] * cmf(wavelengths)
    return white_point_xyz(wavelengths.dtype) * safe_div(w, jnp.sum(w, axis=0))


@jax.jit
def spectrum_to_xyz(values, wavelengths):
    """CIE XYZ of a D65-relative spectrum (module docstring: self-normalised quadrature).

    Args:
      values: [N] spectral values s(λᵢ) (1 everywhere = D65 white).
      wavelengths: [N] their wavelengths in nm.

    Returns: [3] XYZ, with a flat spectrum of ones mapping to `white_point_xyz()`.
    """
    wavelengths = _as_wavelengths(wavelengths, "spectrum_to_xyz")
    values = _check_values(values, wavelengths, "spectrum_to_xyz")
    return values @ _xyz_weights(wavelengths).astype(values.dtype)


@jax.jit
def xyz_to_rgb(xyz):
    """Linear sRGB of CIE XYZ [3] (no clipping: out-of-gamut colours have negatives)."""
    return xyz_to_rgb_matrix(xyz.dtype) @ xyz


@jax.jit
def rgb_to_spectrum(rgb, wavelengths):
    """Spectrum [N] of a linear sRGB colour [3] (reflectance or light colour).

    s(λ) = r·B_r(λ) + g·B_g(λ) + b·B_b(λ) with the spectral primaries B of Mallett &
    Yuksel 2019, "Spectral Primary Decomposition for Rendering with sRGB Reflectance"
    (colour-science `MSDS_BASIS_FUNCTIONS_sRGB_MALLETT2019`): linear, so it applies to
    light colours of any magnitude; B_r + B_g + B_b = 1, so white (1, 1, 1) is the flat
    spectrum; an in-gamut reflectance in [0, 1]³ gives a spectrum in [0, 1].
    """
    wavelengths = _as_wavelengths(wavelengths, "rgb_to_spectrum")
    rgb = jnp.asarray(rgb)
    if rgb.shape != (3,):
        raise ValueError(f"`rgb_to_spectrum(rgb=...)` must have shape (3,), got {rgb.shape}")
    return _interp(wavelengths, "basis").astype(jnp.result_type(rgb, wavelengths)) @ rgb


@jax.jit
def spectrum_to_rgb(values, wavelengths):
    """Linear sRGB [3] of a D65-relative spectrum [N] (module docstring).

    rgb = C · M · XYZ(s), with the calibration C = (M · XYZ(B))⁻¹ that makes
    `spectrum_to_rgb(rgb_to_spectrum(c, λ), λ) == c` for every colour c. A flat
    spectrum of ones gives (1, 1, 1) within ~1e-5. Needs N ≥ 3 samples (C must be
    invertible); the result is not clipped.
    """
    wavelengths = _as_wavelengths(wavelengths, "spectrum_to_rgb")
    values = _check_values(values, wavelengths, "spectrum_to_rgb")
    if wavelengths.shape[0] < 3:
        raise ValueError(
            "`spectrum_to_rgb(wavelengths=...)` needs at least 3 samples to calibrate "
            f"colour, got {wavelengths.shape[0]}"
        )
    return spectral_rgb_matrix(wavelengths).astype(values.dtype) @ values


@jax.jit
def spectral_rgb_matrix(wavelengths):
    """The [3, N] linear map of `spectrum_to_rgb` for these wavelengths (C · M · Wᵀ).

    Handy to convert many spectra at once: `rgb = spectra @ spectral_rgb_matrix(λ).T`.
    """
    wavelengths = _as_wavelengths(wavelengths, "spectral_rgb_matrix")
    w = _xyz_weights(wavelengths)                            # [N, 3]
    m = xyz_to_rgb_matrix(wavelengths.dtype) @ w.T            # [3, N]: uncalibrated
    basis = _interp(wavelengths, "basis")                     # [N, 3]
    return jnp.linalg.solve(m @ basis, m)


def _check_values(values, wavelengths, name):
    values = jnp.asarray(values)
    if values.shape != wavelengths.shape:
        raise ValueError(
            f"`{name}(values=...)` must have the shape of `wavelengths` {wavelengths.shape}, "
            f"got {values.shape}"
        )
    if not jnp.issubdtype(values.dtype, jnp.floating):
        values = values.astype(wavelengths.dtype)
    return values


# ---------------------------------------------------------------------------------------
# index of refraction models


class IOR(eqx.Module):
    """Abstract index of refraction n(λ), callable on a wavelength in nm (scalar or array).

    `is_dispersive` (static) tells the renderer whether the index depends on λ, so that
    a scene without dispersion traces one wavelength band.
    """

    is_dispersive: ClassVar[bool] = True

    def __call__(self, wavelength):
        raise NotImplementedError

    def at_d_line(self):
        """n_d at the helium d line, 587.5618 nm (the usual catalogue index)."""
        return self(FRAUNHOFER["d"])


class ConstantIOR(IOR):
    """A wavelength-independent index n (differentiable)."""

    is_dispersive: ClassVar[bool] = False
    n: jnp.ndarray

    def __init__(self, n):
        self.n = _leaf(n)

    def __call__(self, wavelength):
        return jnp.broadcast_to(self.n, jnp.shape(wavelength)).astype(jnp.result_type(self.n, wavelength))


class Cauchy(IOR):
    """Cauchy's dispersion formula n(λ) = a + b / λ² + c / λ⁴, λ in micrometres.

    Cauchy 1836; a good fit over the visible for weakly dispersive glasses.
    Coefficients a (1), b (µm²), c (µm⁴) are differentiable leaves.
    """

    a: jnp.ndarray
    b: jnp.ndarray
    c: jnp.ndarray

    def __init__(self, a, b, c=0.0):
        self.a, self.b, self.c = (_leaf(x) for x in (a, b, c))

    @eqx.filter_jit
    def __call__(self, wavelength):
        lam2 = (jnp.asarray(wavelength) * 1e-3) ** 2
        inv = safe_div(1.0, lam2)
        return self.a + self.b * inv + self.c * inv * inv


class Sellmeier(IOR):
    """Sellmeier's formula n²(λ) = 1 + Σₖ Bₖ λ² / (λ² − Cₖ), λ in micrometres.

    Sellmeier 1872; the form of the Schott catalogue. `b` ([K]) are dimensionless,
    `c` ([K]) in µm² (resonance wavelengths squared); both differentiable. Terms are
    guarded at a resonance (λ² = Cₖ, far outside the visible for real materials) and n
    at n² ≤ 0.
    """

    b: jnp.ndarray
    c: jnp.ndarray

    def __init__(self, b, c):
        b, c = _leaf(b, ndmin=1), _leaf(c, ndmin=1)
        if b.ndim != 1 or b.shape != c.shape:
            raise ValueError(f"`Sellmeier(b=..., c=...)` must be two sequences of equal length, got shapes {b.shape} and {c.shape}")
        self.b, self.c = b, c

    @eqx.filter_jit
    def __call__(self, wavelength):
        lam2 = (jnp.asarray(wavelength) * 1e-3) ** 2
        lam2 = lam2[..., None]
        n2 = 1.0 + jnp.sum(safe_div(self.b * lam2, lam2 - self.c), axis=-1)
        return safe_sqrt(n2)


def _leaf(x, ndmin=0):
    """A float leaf: JAX arrays (and tracers) stay JAX arrays; Python numbers and
    sequences become float64 numpy arrays, so that presets built at import keep full
    precision whether or not 64-bit JAX is switched on later."""
    if isinstance(x, jax.Array):
        x = x if jnp.issubdtype(x.dtype, jnp.floating) else x.astype(float)
        return jnp.atleast_1d(x) if ndmin else x
    return np.array(x, dtype=np.float64, ndmin=ndmin)


# Published coefficients (each comment gives the source and its catalogue n_d / V_d).

#: Schott N-BK7 (Schott optical glass data sheet): n_d = 1.5168, V_d = 64.17.
BK7 = Sellmeier(b=(1.03961212, 0.231792344, 1.01046945),
                c=(0.00600069867, 0.0200179144, 103.560653))

#: Fused silica, Malitson 1965, "Interspecimen comparison of the refractive index of
#: fused silica", JOSA 55, 1205 (Cₖ = λₖ² of 0.0684043, 0.1162414, 9.896161 µm):
#: n_d = 1.4585, V_d = 67.8.
FUSED_SILICA = Sellmeier(b=(0.6961663, 0.4079426, 0.8974794),
                         c=(0.0684043**2, 0.1162414**2, 9.896161**2))

#: Distilled water at 20 °C, Daimon & Masumura 2007, "Measurement of the refractive
#: index of distilled water from the near-infrared region to the ultraviolet region",
#: Appl. Opt. 46, 3811 (4-term Sellmeier, absolute index): n_D = 1.3334 (relative to
#: air, ÷ 1.00027: 1.3330).
WATER = Sellmeier(b=(5.684027565e-1, 1.726177391e-1, 2.086189578e-2, 1.130748688e-1),
                  c=(5.101829712e-3, 1.821153936e-2, 2.620722293e-2, 1.069792721e1))

#: Diamond, Peter 1923, "Temperaturabhängigkeit der Brechung des Diamanten",
#: Z. Phys. 15, 358 (Cₖ = λₖ² of 0.175, 0.106 µm): n_D = 2.417.
DIAMOND = Sellmeier(b=(0.3306, 4.3356), c=(0.1750**2, 0.1060**2))

#: Schott N-SF11 dense flint (Schott data sheet), a strongly dispersive glass for
#: prisms: n_d = 1.7847, V_d = 25.68.
SF11 = Sellmeier(b=(1.73759695, 0.313747346, 1.89878101),
                 c=(0.013188707, 0.0623068142, 155.23629))

#: Cauchy fit of BK7 (a = 1.5046, b = 0.00420 µm²; e.g. Hecht, "Optics"): n_d = 1.5168.
CAUCHY_BK7 = Cauchy(a=1.5046, b=0.00420)

#: The presets by name (configs refer to them by these keys).
IOR_PRESETS = {
    "bk7": BK7,
    "fused_silica": FUSED_SILICA,
    "water": WATER,
    "diamond": DIAMOND,
    "sf11": SF11,
    "cauchy_bk7": CAUCHY_BK7,
}


def ior_preset(name):
    """An IOR preset by name (case-insensitive); see `IOR_PRESETS`."""
    key = str(name).lower()
    if key not in IOR_PRESETS:
        raise ValueError(f"unknown IOR preset {name!r}, expected one of {sorted(IOR_PRESETS)}")
    return IOR_PRESETS[key]


def abbe_number(ior):
    """Abbe number V_d = (n_d − 1) / (n_F − n_C): small means strongly dispersive."""
    n_d, n_f, n_c = (ior(FRAUNHOFER[k]) for k in ("d", "F", "C"))
    return (n_d - 1.0) / (n_f - n_c)
