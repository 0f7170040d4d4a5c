"""Fitting analytic BRDFs to tabulated (MERL) measurements, after Ngan et al. 2005.

Ngan, Durand & Matusik 2005, "Experimental Analysis of BRDF Models" (EGSR), fit each
model to the isotropic MERL tables (Matusik et al. 2003) by weighted least squares on
*cosine-weighted* values, with directions beyond 80° from the normal left out:

    E(p)² = Σ_s w_s Σ_c [f_c(s) cos θi(s) − f_{p,c}(s) cos θi(s)]² / (3 Σ_s w_s),

s over the sampled (wo, wi) pairs, c over the RGB channels, w_s the solid-angle weight
of a table cell (`merl_cell_weights`): with it, E² estimates the mean over hemisphere
pairs of the squared difference, so densely tabulated regions (MERL's θh axis is
quadratic, dense near the highlight) do not count more than they cover. E is what
`ngan_error` returns and what the notes' "BRDF comparison" slides quote per model.

The objective can compress the cosine-weighted values before differencing
(`compression`): "none" (E itself, dominated by the highlight), "cbrt" (cube root,
Löw et al. 2012 and the perceptual fits that followed Ngan et al.: closer to how a
rendered image differs) or "log" (log(ε + y): relative errors everywhere). The error
table always reports the uncompressed E as well.

Parameterisation: every model parameter is a transform of an unconstrained value, so
that any optimiser step gives a valid model: reflectances ≥ 0 through softplus,
roughness and exponents > 0 through exp, Fresnel reflectances in (0, 1) through the
logistic function (`Parameter.transform`, the transforms of `jaxrt.fit`). Gradients
are JAX's; the driver is `jaxrt.fit` (optimistix's Levenberg–Marquardt or BFGS), run
from several starting roughnesses, keeping the best; the result is a
`jaxrt.fit.FitResult`.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from . import bsdf, fit as _fit
from .bsdf.base import Material
from .io import MERL_SHAPE, half_diff_angles, merl_angles, merl_indices

#: Fresnel f0 and Ashikhmin–Shirley rs start here (a dielectric of index ≈ 1.5).
F0_START = 0.04
#: ε of the "log" compression log(ε + f cos θi): cosine-weighted values (1/sr) below
#: this count as equally dark; about the noise floor of MERL's diffuse measurements.
LOG_EPSILON = 1e-3
#: ε of the "cbrt" compression (ε + y)^(1/3): keeps its slope finite at y = 0.
CBRT_EPSILON = 1e-6
COMPRESSIONS = ("none", "cbrt", "log")
SOLVERS = ("levenberg_marquardt", "bfgs")
WEIGHTINGS = ("solid_angle", "uniform")


# --------------------------------------------------------------------------- data


class BRDFSamples(NamedTuple):
    """Measured BRDF values at direction pairs (local frame, normal +z).

    wo, wi   [N, 3] unit directions, both above the horizon.
    f        [N, 3] measured f_r (linear RGB, 1/sr), ≥ 0.
    weight   [N] weight of each sample in the error (sums to 1).
    """

    wo: jnp.ndarray
    wi: jnp.ndarray
    f: jnp.ndarray
    weight: jnp.ndarray


def merl_directions(theta_h, theta_d, phi_d):
    """(wo, wi), each [..., 3], for Rusinkiewicz angles with φh = 0 (isotropy): the
    inverse of `jaxrt.io.half_diff_angles`.

    wh = (sin θh, 0, cos θh), wd = (sin θd cos φd, sin θd sin φd, cos θd);
    wi = R_y(θh) wd (wd rotated by +θh about y, taking +z to wh), wo = 2 (wi·wh) wh − wi.
    """
    theta_h, theta_d, phi_d = (np.asarray(a, np.float64) for a in (theta_h, theta_d, phi_d))
    st, ct = np.sin(theta_h), np.cos(theta_h)
    wd = np.stack([np.sin(theta_d) * np.cos(phi_d), np.sin(theta_d) * np.sin(phi_d),
                   np.cos(theta_d)], axis=-1)
    wi = np.stack([ct * wd[..., 0] + st * wd[..., 2], wd[..., 1],
                   -st * wd[..., 0] + ct * wd[..., 2]], axis=-1)
    wh = np.stack([st, np.zeros_like(st), ct], axis=-1)
    wo = 2.0 * np.sum(wi * wh, axis=-1, keepdims=True) * wh - wi
    return wo, wi


def merl_cell_weights():
    """Solid-angle measure of every MERL cell, [90, 90, 180] (relative).

    dωi dωo = 4 cos θd dωh dωd = 4 cos θd sin θd sin θh dθh dθd dφh dφd (the half-vector
    Jacobian dωo = 4 (wi·wh) dωh; Rusinkiewicz 1998), with dθh of cell i equal to
    ((i + 1)² − i²) / 90² · π/2 on MERL's quadratic θh axis; dθd and dφd are constant.
    """
    theta_h, theta_d, _ = merl_angles()
    i = np.arange(MERL_SHAPE[0], dtype=np.float64)
    d_theta_h = ((i + 1.0) ** 2 - i**2) / MERL_SHAPE[0] ** 2 * (np.pi / 2)
    return 4.0 * np.cos(theta_d) * np.sin(theta_d) * np.sin(theta_h) * d_theta_h[:, None, None]


def merl_valid_mask(table, max_theta_deg=80.0):
    """[90, 90, 180] True where every channel is finite and ≥ 0 (MERL marks missing
    measurements with negative values) and both directions are within `max_theta_deg`
    of the normal (Ngan et al. 2005 leave out θ > 80°)."""
    table = np.asarray(table)
    if table.shape != (*MERL_SHAPE, 3):
        raise ValueError(f"`table` has shape {table.shape}, expected {(*MERL_SHAPE, 3)}")
    if not 0.0 < max_theta_deg <= 90.0:
        raise ValueError(f"`max_theta_deg` = {max_theta_deg}, expected a number in (0, 90]")
    wo, wi = merl_directions(*merl_angles())
    cos_max = np.cos(np.deg2rad(max_theta_deg))
    inside = (wo[..., 2] > max(cos_max, 0.0)) & (wi[..., 2] > max(cos_max, 0.0))
    measured = np.all(np.isfinite(table) & (table >= 0.0), axis=-1)
    return inside & measured


def sample_merl(table, num_samples, *, max_theta_deg=80.0, weighting="solid_angle", seed=0):
    """A `BRDFSamples` of `num_samples` cells drawn uniformly without replacement from
    the valid cells of a [90, 90, 180, 3] MERL table (`merl_valid_mask`), at their cell
    centres.

    `weighting`: "solid_angle" (each sample weighted by its cell's solid angle,
    `merl_cell_weights`: the weighted mean estimates the mean over hemisphere pairs) or
    "uniform" (every cell alike, which stresses the densely tabulated highlight).
    """
    if weighting not in WEIGHTINGS:
        raise ValueError(f"`weighting` = {weighting!r}, expected one of {WEIGHTINGS}")
    table = np.asarray(table, np.float64)
    valid = np.flatnonzero(merl_valid_mask(table, max_theta_deg))
    if not isinstance(num_samples, (int, np.integer)) or num_samples < 1:
        raise ValueError(f"`num_samples` = {num_samples!r}, expected an integer ≥ 1")
    if valid.size == 0:
        raise ValueError("the MERL table has no valid cells (all negative or beyond max_theta_deg)")
    rng = np.random.default_rng(seed)
    cells = np.sort(rng.choice(valid, size=min(num_samples, valid.size), replace=False))
    idx = np.unravel_index(cells, MERL_SHAPE)
    wo, wi = merl_directions(*(a[idx] for a in merl_angles()))
    w = merl_cell_weights()[idx] if weighting == "solid_angle" else np.ones(cells.size)
    return BRDFSamples(jnp.asarray(wo), jnp.asarray(wi), jnp.asarray(table[idx]),
                       jnp.asarray(w / w.sum()))


def sample_material(material, num_samples, *, max_theta_deg=80.0, seed=0):
    """A `BRDFSamples` of a material itself at `num_samples` direction pairs drawn
    uniformly over the hemisphere pairs within `max_theta_deg` of the normal (equal
    weights): noise-free synthetic data without a table."""
    rng = np.random.default_rng(seed)
    cos_max = np.cos(np.deg2rad(max_theta_deg))

    def draw(n):  # uniform on the spherical cap cos θ ∈ (cos_max, 1]
        z = rng.uniform(cos_max, 1.0, n)
        phi = rng.uniform(0.0, 2.0 * np.pi, n)
        r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
        return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1)

    wo, wi = jnp.asarray(draw(num_samples)), jnp.asarray(draw(num_samples))
    f = jax.vmap(material.eval)(wo, wi)
    return BRDFSamples(wo, wi, f, jnp.full((num_samples,), 1.0 / num_samples))


def tabulate_merl(material, chunk=1 << 16):
    """The [90, 90, 180, 3] MERL table of a material, evaluated at the cell centres;
    cells with a direction at or below the horizon are −1 (MERL's "no data")."""
    wo, wi = (a.reshape(-1, 3) for a in merl_directions(*merl_angles()))
    ev = jax.jit(jax.vmap(material.eval))
    out = np.concatenate([np.asarray(ev(jnp.asarray(wo[s:s + chunk]), jnp.asarray(wi[s:s + chunk])))
                          for s in range(0, wo.shape[0], chunk)])
    below = (wo[:, 2] <= 0.0) | (wi[:, 2] <= 0.0)
    out[below] = -1.0
    return out.reshape(*MERL_SHAPE, 3)


# --------------------------------------------------------------------------- tabulated BRDF


def half_diff(wo, wi):
    """Rusinkiewicz (θh, θd, φd) of direction pairs, in JAX: `jaxrt.io.half_diff_angles`
    with `xp=jax.numpy` (φd in (−π, π])."""
    return half_diff_angles(wo, wi, xp=jnp)


class TabulatedBRDF(Material):
    """A measured isotropic BRDF as a material: nearest-cell lookup in a MERL table.

        f_r(wo, wi) = table[i, j, k],  i = ⌊sqrt(θh / (π/2)) · 90⌋, j = ⌊θd / (π/2) · 90⌋,
        k = ⌊(φd mod π) / π · 180⌋   (MERL's BRDFRead.cpp; `jaxrt.io.merl_indices`),

    0 below the horizon and where the table has no data (negative cells). Not
    differentiable in anything useful (piecewise constant); used to render the
    reference next to the fitted models.

    `table`: [90, 90, 180, 3] linear RGB f_r (1/sr), e.g. from `jaxrt.io.read_merl`.
    """

    table: jnp.ndarray

    def __init__(self, table):
        table = jnp.asarray(table, dtype=float)
        if table.shape != (*MERL_SHAPE, 3):
            raise ValueError(f"`TabulatedBRDF(table=...)` has shape {table.shape}, "
                             f"expected {(*MERL_SHAPE, 3)}")
        self.table = table

    def eval(self, wo, wi):
        i, j, k = merl_indices(wo, wi, xp=jnp)
        f = jnp.maximum(self.table[i, j, k], 0.0)
        return jnp.where((wo[2] > 0.0) & (wi[2] > 0.0), f, 0.0)

    def base_color(self):
        # π f_r at an off-specular cell (θh ≈ 40°, θd ≈ 10°): about the diffuse albedo.
        return jnp.maximum(self.table[60, 10, 90], 0.0) * jnp.pi


class SumBRDF(Material):
    """The sum of several materials' BRDFs, f_r = Σ_j f_j(wo, wi): a multi-lobe
    reference (for example a diffuse base plus a sharp and a hazy specular lobe, as
    many MERL materials look). Plausible when each term is and their albedos sum to
    ≤ 1. Parameters: those of the terms."""

    terms: tuple

    def __init__(self, *terms):
        if not terms or not all(isinstance(t, Material) for t in terms):
            raise TypeError("`SumBRDF(*terms)` needs one or more jaxrt.bsdf materials")
        self.terms = tuple(terms)

    def eval(self, wo, wi):
        return sum(t.eval(wo, wi) for t in self.terms)

    def base_color(self):
        return self.terms[0].base_color()


# --------------------------------------------------------------------------- models


#: The parameter transforms by name (`jaxrt.fit.Transform`).
TRANSFORMS = {"softplus": _fit.POSITIVE, "exp": _fit.LOG, "sigmoid": _fit.UNIT,
              "identity": _fit.IDENTITY}


@dataclasses.dataclass(frozen=True)
class Parameter:
    """A fitted parameter: its `shape` and the `transform` from an unconstrained value,
    "softplus" (≥ 0), "exp" (> 0), "sigmoid" (in (0, 1)) or "identity"."""

    shape: tuple
    transform: str


@dataclasses.dataclass(frozen=True, eq=False)
class ModelSpec:
    """How to fit one model.

    name      the model's name in tables and configs.
    params    name → `Parameter`, in display order.
    build     constrained parameter values (dict) → a `jaxrt.bsdf` material.
    start     (roughness α, diffuse start [3]) → constrained starting values; α is
              turned into the model's own roughness or exponent.
    scale     names of the specular-scale parameters (linear in f), rescaled at each
              start so that the model matches the brightest sample (`starts`).
    """

    name: str
    params: dict
    build: Callable
    start: Callable
    scale: tuple = ()

    @property
    def transforms(self):
        """name → `jaxrt.fit.Transform` of every parameter."""
        return {k: TRANSFORMS[p.transform] for k, p in self.params.items()}

    def to_values(self, raw):
        """Unconstrained → constrained parameter values."""
        return _fit.constrain({k: raw[k] for k in self.params}, self.transforms)

    def to_raw(self, values):
        """Constrained → unconstrained parameter values (clipped into the open range)."""
        values = {k: jnp.broadcast_to(jnp.asarray(values[k], dtype=float), p.shape)
                  for k, p in self.params.items()}
        return _fit.unconstrain(values, self.transforms)


def alpha_to_exponent(alpha):
    """Blinn–Phong exponent of the Beckmann roughness α: 2 α⁻² − 2 (notes)."""
    return 2.0 / (alpha * alpha) - 2.0


_RGB = (3,)


def _lambert():
    return ModelSpec(
        "lambert", {"kd": Parameter(_RGB, "softplus")},
        lambda v: bsdf.Lambert(v["kd"]),
        lambda alpha, kd: {"kd": kd})


def _blinn_phong():
    return ModelSpec(
        "blinn_phong",
        {"kd": Parameter(_RGB, "softplus"), "ks": Parameter(_RGB, "softplus"),
         "q": Parameter((), "exp")},
        lambda v: bsdf.BlinnPhong(v["kd"], v["ks"], v["q"]),
        lambda alpha, kd: {"kd": kd, "ks": 0.5, "q": alpha_to_exponent(alpha)},
        scale=("ks",))


def _ward(normalization):
    return ModelSpec(
        "ward" if normalization == "ward" else "ward_duer",
        {"rho_d": Parameter(_RGB, "softplus"), "rho_s": Parameter(_RGB, "softplus"),
         "alpha": Parameter((), "exp")},
        lambda v: bsdf.Ward(v["rho_d"], v["rho_s"], v["alpha"], normalization=normalization),
        lambda alpha, kd: {"rho_d": kd, "rho_s": 0.1, "alpha": alpha},
        scale=("rho_s",))


def _cook_torrance(distribution, geometry):
    ndf = {"ggx": bsdf.GGX, "beckmann": bsdf.Beckmann}[distribution]
    return ModelSpec(
        f"cook_torrance_{distribution}",
        {"diffuse": Parameter(_RGB, "softplus"), "ks": Parameter(_RGB, "softplus"),
         "alpha": Parameter((), "exp"), "f0": Parameter((), "sigmoid")},
        lambda v: bsdf.CookTorrance(ndf(v["alpha"]), bsdf.SchlickFresnel(v["f0"]),
                                    geometry=geometry, diffuse=v["diffuse"], ks=v["ks"]),
        lambda alpha, kd: {"diffuse": kd, "ks": 1.0, "alpha": alpha, "f0": F0_START},
        scale=("ks",))


def _lafortune(lobes):
    def start(alpha, kd):
        # Lobe j starts 2^j times broader; (wo·r)^n ≈ exp(−n θ²/2) with θ ≈ 2 θh gives
        # n ≈ q / 4 for the half-vector exponent q.
        n = jnp.stack([jnp.maximum(alpha_to_exponent(alpha * 2.0**j) / 4.0, 1.0)
                       for j in range(lobes)])
        return {"kd": kd, "ks": jnp.ones((lobes, 3)), "cxy": -jnp.ones(lobes), "n": n}

    return ModelSpec(
        "lafortune",
        {"kd": Parameter(_RGB, "softplus"), "ks": Parameter((lobes, 3), "softplus"),
         "cxy": Parameter((lobes,), "identity"), "n": Parameter((lobes,), "exp")},
        # cz = 1: the scale of (cxy, cz) is redundant with ks (ks [s b]^n = ks s^n b^n),
        # so it is fixed; cxy is then the lobe's shape (−1: Phong, |cxy| > 1: towards
        # grazing, > 0: retro-reflection).
        lambda v: bsdf.Lafortune(v["kd"], v["ks"], v["cxy"], jnp.ones_like(v["cxy"]), v["n"]),
        start, scale=("ks",))


def _ashikhmin_shirley():
    return ModelSpec(
        "ashikhmin_shirley",
        {"rd": Parameter(_RGB, "softplus"), "rs": Parameter(_RGB, "sigmoid"),
         "n": Parameter((), "exp")},
        lambda v: bsdf.AshikhminShirley(v["rd"], v["rs"], v["n"]),
        lambda alpha, kd: {"rd": kd, "rs": F0_START, "n": alpha_to_exponent(alpha)})


#: Fittable models: name → factory(**options) → ModelSpec. (He et al. 1991 is not in
#: `jaxrt.bsdf`, so it is not here.)
MODELS = {
    "lambert": _lambert,
    "blinn_phong": _blinn_phong,
    "ward": lambda: _ward("ward"),
    "ward_duer": lambda: _ward("duer"),
    "cook_torrance_beckmann": lambda geometry="cook_torrance": _cook_torrance("beckmann", geometry),
    "cook_torrance_ggx": lambda geometry="smith_correlated": _cook_torrance("ggx", geometry),
    "lafortune": lambda lobes=1: _lafortune(int(lobes)),
    "ashikhmin_shirley": _ashikhmin_shirley,
}


@functools.lru_cache(maxsize=None)
def _cached_spec(name, options):
    return MODELS[name](**dict(options))


def model_spec(name, **options):
    """The `ModelSpec` of a model in `MODELS`, with its options (CookTorrance:
    `geometry`; Lafortune: `lobes`). The same name and options give the same object, so
    that its compiled solver (`fit`) is reused."""
    if name not in MODELS:
        raise ValueError(f"unknown BRDF model {name!r}, expected one of {sorted(MODELS)}")
    try:
        return _cached_spec(name, tuple(sorted(options.items())))
    except TypeError:
        raise ValueError(f"model {name!r}: unknown options {sorted(options)}") from None


# --------------------------------------------------------------------------- objective


def compress(y, compression):
    """The value compared by the objective: y ("none"), (ε + y)^(1/3) ("cbrt") or
    log(ε + y) ("log"), y = f cos θi ≥ 0 (ε: `CBRT_EPSILON`, `LOG_EPSILON`)."""
    if compression == "none":
        return y
    if compression == "cbrt":
        return jnp.cbrt(jnp.maximum(y, 0.0) + CBRT_EPSILON)
    if compression == "log":
        return jnp.log(jnp.maximum(y, 0.0) + LOG_EPSILON)
    raise ValueError(f"`compression` = {compression!r}, expected one of {COMPRESSIONS}")


def model_values(material, data):
    """f_model cos θi at the samples, [N, 3]."""
    return jax.vmap(material.eval)(data.wo, data.wi) * data.wi[:, 2:3]


def residuals(material, data, compression="none"):
    """r_s,c = sqrt(w_s / 3) (g(f_model cos θi) − g(f cos θi)), [N, 3]; Σ r² is the
    objective (E² of Ngan et al. for compression "none")."""
    y_model = model_values(material, data)
    y_data = data.f * data.wi[:, 2:3]
    scale = jnp.sqrt(data.weight / 3.0)[:, None]
    return scale * (compress(y_model, compression) - compress(y_data, compression))


def ngan_error(material, data):
    """E = sqrt(Σ_s w_s Σ_c (f_c cos θi − f_model,c cos θi)² / (3 Σ_s w_s)) (Ngan et al.
    2005; cosine-weighted RMS difference, 1/sr)."""
    r = residuals(material, data._replace(weight=data.weight / jnp.sum(data.weight)))
    return jnp.sqrt(jnp.sum(r * r))


def starts(spec, data, alphas):
    """Constrained starting values, one per roughness in `alphas`, stacked along a new
    leading axis. The diffuse start is π × the 10th percentile of the data per channel;
    the specular scale parameters (`spec.scale`, linear in f) are then set to their
    weighted least-squares value for that lobe shape, per channel:
    s = Σ w ℓ (y − y₀) / Σ w ℓ², with y₀ the model without the lobe and ℓ the lobe at
    unit scale (both times cos θi), clipped to [1e-4, 1e4]."""
    f = np.asarray(data.f)
    kd = jnp.asarray(np.clip(np.pi * np.percentile(f, 10.0, axis=0), 1e-3, 0.95))
    y = data.f * data.wi[:, 2:3]
    w = data.weight[:, None]
    out = []
    for alpha in alphas:
        v = {k: jnp.broadcast_to(jnp.asarray(x, float), spec.params[k].shape)
             for k, x in spec.start(float(alpha), kd).items()}
        if spec.scale:
            y0 = model_values(spec.build({**v, **{k: jnp.zeros_like(v[k]) for k in spec.scale}}), data)
            y1 = model_values(spec.build({**v, **{k: jnp.ones_like(v[k]) for k in spec.scale}}), data)
            lobe = y1 - y0
            s = jnp.sum(w * lobe * (y - y0), axis=0) / jnp.maximum(jnp.sum(w * lobe * lobe, axis=0), 1e-30)
            s = jnp.clip(s, 1e-4, 1e4)  # [3]
            v.update({k: jnp.broadcast_to(s, v[k].shape) for k in spec.scale})
        out.append(v)
    return jax.tree_util.tree_map(lambda *x: jnp.stack(x), *out)


def fit(spec, data, *, compression="none", solver="levenberg_marquardt", alphas=(0.05, 0.15, 0.4),
        max_steps=200, rtol=1e-7, atol=1e-10):
    """Fit `spec`'s parameters to `data` by weighted least squares (module docstring),
    from one start per roughness in `alphas`, with `jaxrt.fit`'s drivers and the
    parameters' transforms (`ModelSpec.transforms`); returns the best start's
    `jaxrt.fit.FitResult`:

    params   fitted parameter values (constrained), name → array.
    loss     Σ r² at the fit (in the compressed space).
    steps, result, converged   those of the best start's solver.
    info     "material" (the fitted `jaxrt.bsdf` material), "error" (`ngan_error` on
             the fitting samples) and "objectives" (Σ r² of every start, to judge
             local minima).

    `solver`: "levenberg_marquardt" (`jaxrt.fit.fit_least_squares` with
    `optx.LevenbergMarquardt(rtol, atol)` on the residual vector) or "bfgs"
    (`jaxrt.fit.fit` with `optx.BFGS(rtol, atol)` on Σ r²). Both stop after `max_steps`
    without raising; `converged` says whether they met the tolerance. The compiled
    solve is shared by every start and dataset of one model, options and shapes.
    """
    if compression not in COMPRESSIONS:
        raise ValueError(f"`compression` = {compression!r}, expected one of {COMPRESSIONS}")
    if solver not in SOLVERS:
        raise ValueError(f"`solver` = {solver!r}, expected one of {SOLVERS}")
    x0 = starts(spec, data, alphas)
    results = []
    for i in range(len(alphas)):
        start = {k: x0[k][i] for k in spec.params}
        if solver == "levenberg_marquardt":
            res = _fit.fit_least_squares(_residual_fn(spec, compression), start,
                                         optx.LevenbergMarquardt(rtol=rtol, atol=atol), args=data,
                                         max_steps=max_steps, transforms=spec.transforms)
        else:
            res = _fit.fit(_objective_fn(spec, compression), start, optx.BFGS(rtol=rtol, atol=atol),
                           args=data, max_steps=max_steps, transforms=spec.transforms)
        r = _residual_fn(spec, compression)(res.params, data)
        results.append(res._replace(loss=float(jnp.sum(r * r))))
    losses = np.array([r.loss for r in results])
    best = results[int(np.argmin(np.where(np.isfinite(losses), losses, np.inf)))]
    material = spec.build(best.params)
    return best._replace(info={"material": material, "error": float(ngan_error(material, data)),
                               "objectives": losses})


@functools.lru_cache(maxsize=64)
def _residual_fn(spec, compression):
    """values, data ↦ residuals, one function object per model and compression, so that
    `jaxrt.fit`'s compiled solve is reused across starts and datasets."""
    return lambda values, data: residuals(spec.build(values), data, compression)


@functools.lru_cache(maxsize=64)
def _objective_fn(spec, compression):
    fn = _residual_fn(spec, compression)
    return lambda values, data: jnp.sum(fn(values, data) ** 2)
