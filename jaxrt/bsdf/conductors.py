"""Complex indices of refraction of metals at three RGB wavelengths.

Values are linear interpolations (in wavelength) of published tables at
λ = 650 nm (R), 550 nm (G), 450 nm (B):

- gold, silver, copper: P. B. Johnson and R. W. Christy, "Optical constants of the noble
  metals", Phys. Rev. B 6, 4370 (1972), Table I;
- aluminium: H.-J. Hagemann, W. Gudat and C. Kunz, "Optical constants from the far
  infrared to the x-ray region: Mg, Al, Cu, Ag, Au, Bi, C, and Al2O3", DESY SR-74/7 (1974).

Three wavelengths are a coarse sampling of the spectrum; spectral rendering should use
the full tables instead.
"""

import numpy as np

#: Wavelengths (nm) of the R, G, B channels.
RGB_WAVELENGTHS_NM = (650.0, 550.0, 450.0)

# Johnson & Christy 1972, Table I rows from 1.76 to 2.88 eV:
# photon energy (eV), Cu n, Cu k, Ag n, Ag k, Au n, Au k.
_JOHNSON_CHRISTY = np.array([
    [1.76, 0.21, 4.205, 0.04, 4.838, 0.13, 4.103],
    [1.88, 0.22, 3.747, 0.05, 4.483, 0.14, 3.697],
    [2.01, 0.30, 3.205, 0.06, 4.152, 0.21, 3.272],
    [2.13, 0.70, 2.704, 0.05, 3.858, 0.29, 2.863],
    [2.26, 1.02, 2.577, 0.06, 3.586, 0.43, 2.455],
    [2.38, 1.18, 2.608, 0.05, 3.324, 0.62, 2.081],
    [2.50, 1.22, 2.564, 0.05, 3.093, 1.04, 1.833],
    [2.63, 1.25, 2.483, 0.05, 2.869, 1.31, 1.849],
    [2.75, 1.24, 2.397, 0.04, 2.657, 1.38, 1.914],
    [2.88, 1.25, 2.305, 0.04, 2.462, 1.45, 1.948],
])

# Hagemann, Gudat & Kunz 1974, aluminium: wavelength (nm), n, k.
_HAGEMANN_AL = np.array([
    [413.3, 0.548, 5.00],
    [495.9, 0.771, 5.91],
    [619.9, 1.292, 7.28],
    [688.8, 1.731, 7.96],
])

_HC_EV_NM = 1239.84193  # photon energy (eV) × wavelength (nm)


def _at_rgb(wavelength_nm, n, k):
    order = np.argsort(wavelength_nm)
    lam = np.asarray(RGB_WAVELENGTHS_NM)
    w = np.asarray(wavelength_nm)[order]
    return (tuple(float(x) for x in np.interp(lam, w, np.asarray(n)[order])),
            tuple(float(x) for x in np.interp(lam, w, np.asarray(k)[order])))


def _build():
    lam_jc = _HC_EV_NM / _JOHNSON_CHRISTY[:, 0]
    t = _JOHNSON_CHRISTY
    return {
        "copper": _at_rgb(lam_jc, t[:, 1], t[:, 2]),
        "silver": _at_rgb(lam_jc, t[:, 3], t[:, 4]),
        "gold": _at_rgb(lam_jc, t[:, 5], t[:, 6]),
        "aluminium": _at_rgb(_HAGEMANN_AL[:, 0], _HAGEMANN_AL[:, 1], _HAGEMANN_AL[:, 2]),
    }


#: name -> ((eta_R, eta_G, eta_B), (k_R, k_G, k_B)).
CONDUCTOR_PRESETS = _build()
CONDUCTOR_PRESETS["aluminum"] = CONDUCTOR_PRESETS["aluminium"]


def conductor_preset(name):
    """`(eta, k)` RGB tuples for "gold", "silver", "copper" or "aluminium" ("aluminum")."""
    try:
        return CONDUCTOR_PRESETS[name]
    except KeyError:
        raise ValueError(
            f"unknown conductor {name!r}, expected one of {sorted(CONDUCTOR_PRESETS)}"
        ) from None
