"""Photometric quantities people compare: rates per second and surface radiance.

fluxmap's native quantity is the power per element in photons per exposure (b = T⁻¹ a).
Laboratories compare rates and radiance (what Living Image reports), so with a known
exposure time t:

* flux            Φ = b / t                  photons s⁻¹
* exitance        M = b / (S t)              photons s⁻¹ mm⁻²
* radiance        L = M / π                  photons s⁻¹ mm⁻² sr⁻¹  (a Lambertian emitter)
                    = 100 M / π              photons s⁻¹ cm⁻² sr⁻¹

For a Lambertian surface the radiance is the same in every direction and M = ∫ L cosθ dΩ
over the hemisphere = π L, hence L = M / π.
"""

from __future__ import annotations

import numpy as np

MM2_PER_CM2 = 100.0

# The units every exported array carries (names carry them too).
UNITS = {
    "power_photons": "photons per exposure, per element",
    "exitance_photons_per_mm2": "photons mm^-2 per exposure",
    "sigma_photons": "photons per exposure (1 sd), per element",
    "flux_photons_per_s": "photons s^-1, per element",
    "exitance_photons_per_s_per_mm2": "photons s^-1 mm^-2",
    "radiance_photons_per_s_per_cm2_per_sr": "photons s^-1 cm^-2 sr^-1 (Lambertian: L = M / pi)",
    "sigma_photons_per_s": "photons s^-1 (1 sd), per element",
}


def lambertian_radiance_per_cm2(exitance_photons_per_s_per_mm2):
    """Radiance of a Lambertian emitter from its exitance.

    Parameters
    ----------
    exitance_photons_per_s_per_mm2 : array_like
        Exitance M (photons s⁻¹ mm⁻²).

    Returns
    -------
    ndarray
        Radiance L = M / π converted to photons s⁻¹ cm⁻² sr⁻¹ (NaN stays NaN).
    """
    return np.asarray(exitance_photons_per_s_per_mm2, float) * MM2_PER_CM2 / np.pi


def element_quantities(power_photons, areas_mm2, *, exposure_s: float | None = None,
                       sigma_photons=None) -> dict[str, np.ndarray]:
    """Every per-element quantity fluxmap exports, from the power per element.

    Parameters
    ----------
    power_photons : (n,) array
        Power b per element (photons per exposure); NaN where unobserved.
    areas_mm2 : (n,) array
        Element areas S (mm²).
    exposure_s : float, optional
        Exposure time t (s). Without it only per-exposure quantities are returned.
    sigma_photons : (n,) array, optional
        Standard deviation of b (photons per exposure).

    Returns
    -------
    dict
        Keys of :data:`UNITS` (names carry the units); values (n,) float arrays.
    """
    b = np.asarray(power_photons, float)
    s = np.asarray(areas_mm2, float)
    with np.errstate(divide="ignore", invalid="ignore"):
        m = np.where(s > 0, b / np.where(s > 0, s, 1.0), np.nan)
    out = {"power_photons": b, "exitance_photons_per_mm2": m}
    if sigma_photons is not None:
        out["sigma_photons"] = np.asarray(sigma_photons, float)
    if exposure_s is not None:
        if not exposure_s > 0:
            raise ValueError(f"exposure_s must be positive, got {exposure_s}")
        out["flux_photons_per_s"] = b / exposure_s
        out["exitance_photons_per_s_per_mm2"] = m / exposure_s
        out["radiance_photons_per_s_per_cm2_per_sr"] = lambertian_radiance_per_cm2(m / exposure_s)
        if sigma_photons is not None:
            out["sigma_photons_per_s"] = out["sigma_photons"] / exposure_s
    return out
