"""The error budget of a total: photon noise, regularisation, calibration; and a shift test.

A reconstructed total ``t = Σ_j b̃_j`` is uncertain for three separate reasons, and a lab
must see each:

- **photon noise**: ``σ_noise = √(wᵀCw)`` with ``C`` the estimate's covariance under the
  images' noise and ``w`` the observed elements (:mod:`fluxcli.inverse.covariance`);
- **regularisation**: how far the total moves when λ is halved or doubled (the prior's
  share of the number; ``σ_reg = max |t(λ/2) − t|, |t(2λ) − t|``);
- **calibration**: the camera (lens centre, optical axis, focal length, focus distance,
  aperture) and mirrors are known to a calibration's 1 σ.  Linearised: T is rebuilt with
  each parameter ``i`` moved by +1 σ, the same images are solved again at the same λ, and
  ``σ_cal² = Σ_i Δ_i² + (t · g)²`` with ``Δ_i`` the total's change and ``g`` the relative
  1 σ of the radiometric gain (photons per count scale every total: analytic).

The three add in quadrature: ``σ² = σ_noise² + σ_reg² + σ_cal²`` (independent causes).

:func:`image_shift` asks whether the residual looks like a shifted image — what a
geometry error leaves that the flux cannot absorb — by regressing it on the fitted
image's gradients; its significance ``z`` is the shift in units of its own standard
error (inflated by χ²/pixel when the fit is worse than the noise).  A camera or mirror out of
place moves the whole image, so each flank of it (the pixels whose brightness rises along the
shift, and those where it falls) must see the shift on its own: a misfit on one flank only
(light that varies within an element faster than its unknowns, a crease seen edge-on) projects
onto the gradients too, but is not a shift.

Arrays and numbers only: the stage that rebuilds T is :mod:`fluxcli.stages.budget`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

SHIFT_Z = 5.0  # |shift| / its standard error above this: a shift the data can see (chance: p < 4e-6)
SHIFT_MIN_PX = 0.05  # and at least this large (pixels): a tiny but formally significant shift is not worth a warning
SHIFT_FLANK_Z = 2.0  # and each flank alone sees it, this many of its standard errors along the shift (chance: p < 0.023)


def total_sigma_noise(res) -> float:
    """1 σ (photons) of the total over ``res``'s observed elements under the images' noise:
    √(wᵀCw) from its covariance (``res.covariance.variance_of``), NaN without one."""
    cov = getattr(res, "covariance", None)
    obs = np.asarray(res.observed, bool)
    if cov is None or not obs.any():
        return float("nan")
    var = float(np.asarray(cov.variance_of(obs.astype(float)), float).reshape(-1)[0])
    return float(np.sqrt(var)) if np.isfinite(var) and var >= 0 else float("nan")


def regularisation_sigma(total: float, total_half: float, total_double: float) -> float:
    """The total's largest move (photons) when λ is halved or doubled."""
    return float(max(abs(total_half - total), abs(total_double - total)))


def calibration_sigma(total: float, deltas, gain_relative: float | None) -> float:
    """√(Σ Δ_i² + (total · gain_relative)²) (photons): ``deltas`` the total's change per
    parameter moved by +1 σ; the gain term is exact (every photon number scales with it)."""
    d = np.asarray([x for x in deltas if np.isfinite(x)], float)
    g = float(total) * float(gain_relative or 0.0)
    return float(np.sqrt(np.sum(d ** 2) + g ** 2))


@dataclass
class TotalBudget:
    """One total (a pose, or all poses jointly) and its σ by cause, in photons."""

    label: str
    total: float
    sigma_noise: float = float("nan")
    sigma_regularisation: float = float("nan")
    sigma_calibration: float = float("nan")
    deltas: dict = field(default_factory=dict)  # parameter -> the total's change at +1 σ (photons)
    sigma_gain: float = float("nan")

    @property
    def sigma(self) -> float:
        """√ of the sum of the known parts (a part not computed is left out, not zero)."""
        parts = np.array([self.sigma_noise, self.sigma_regularisation, self.sigma_calibration], float)
        parts = parts[np.isfinite(parts)]
        return float(np.sqrt(np.sum(parts ** 2))) if parts.size else float("nan")


@dataclass
class Shift:
    """The shift (pixels, +x = +column, +y = +row) of the fitted image that best explains
    the residual, its standard errors, and its significance ``z``."""

    dx_px: float
    dy_px: float
    sd_px: tuple[float, float]
    z: float
    pixels: int
    flank_z: tuple[float, float] | None = None  # the shift along its direction as each flank alone sees it, in its sd
    RULE: ClassVar[str] = (f"warned above {SHIFT_Z:g} (and {SHIFT_MIN_PX:g} px, and {SHIFT_FLANK_Z:g} on each flank "
                           "of the image alone)")  # when :attr:`seen`, in words

    @property
    def size_px(self) -> float:
        return float(np.hypot(self.dx_px, self.dy_px))

    @property
    def one_flank(self) -> bool:
        """Significant as a whole but not seen by each flank alone: a local misfit, not a shift."""
        return self.flank_z is not None and not min(self.flank_z) > SHIFT_FLANK_Z

    @property
    def seen(self) -> bool:
        """A shift the data can see: significant, not negligible, and on both flanks of the image
        (where :attr:`flank_z` was measured)."""
        return bool(np.isfinite(self.z) and self.z > SHIFT_Z and self.size_px > SHIFT_MIN_PX and not self.one_flank)


def image_shift(measured: np.ndarray, fitted: np.ndarray, valid: np.ndarray, variance: np.ndarray) -> Shift:
    """Regress the residual ``measured − fitted`` on the fitted image's gradients.

    A model image moved by (dx, dy) pixels is ``f(x − dx, y − dy) ≈ f − dx ∂f/∂x − dy ∂f/∂y``,
    so a residual ``r ≈ −dx ∂f/∂x − dy ∂f/∂y`` says the data sit (dx, dy) from where the model
    puts them: what a camera or mirror a calibration error away leaves after the flux has
    absorbed what it can.  Weighted least squares with weights 1/``variance`` (photons², the
    noise model evaluated on ``fitted``) over the valid pixels whose 4 neighbours are valid
    and whose model holds ≥ 1 photon.  The standard errors are inflated by √(χ²/pixel of the
    regression) when above 1, so that model error other than a shift does not read as one.

    Then each flank alone (:func:`_flank_z`): a shift (dx, dy) moves the edges where the image
    brightens along it and those where it darkens alike, while a misfit on one side of a spot or
    along one crease projects onto the gradients as well.  On the Monte Carlo battery's exact
    cameras the whole-image test read 0.08-0.09 px (5-7 sd) on a round body's spot and 0.33 px
    (7 sd) on a box's edge-on face; one flank saw 0.03 ± 0.02 and 0.14 ± 0.09 px of it.

    Parameters
    ----------
    measured, fitted, variance : (ny, nx) photons, photons, photons².
    valid : (ny, nx) bool.
    """
    m = np.asarray(measured, float)
    f = np.asarray(fitted, float)
    if min(f.shape) < 3:  # a line detector: no image to shift across its rows (not tested)
        return Shift(np.nan, np.nan, (np.nan, np.nan), np.nan, 0)
    ok = np.asarray(valid, bool) & np.isfinite(m) & np.isfinite(f) & (f >= 1.0) & (np.asarray(variance) > 0)
    f0 = np.where(np.isfinite(f), f, 0.0)
    gy, gx = np.gradient(f0)
    inner = ok.copy()  # central differences need both neighbours in the fit
    inner[1:-1, :] &= ok[:-2, :] & ok[2:, :]
    inner[:, 1:-1] &= ok[:, :-2] & ok[:, 2:]
    inner[[0, -1], :] = False
    inner[:, [0, -1]] = False
    n = int(inner.sum())
    if n < 10:
        return Shift(np.nan, np.nan, (np.nan, np.nan), np.nan, n)
    w = 1.0 / np.asarray(variance, float)[inner]
    J = -np.stack([gx[inner], gy[inner]], axis=1)
    r = (m - f)[inner]
    G = (J * w[:, None]).T @ J
    try:
        cov = np.linalg.inv(G)
    except np.linalg.LinAlgError:
        return Shift(np.nan, np.nan, (np.nan, np.nan), np.nan, n)
    s = cov @ ((J * w[:, None]).T @ r)
    chi2 = float(np.sum(w * (r - J @ s) ** 2) / max(n - 2, 1))
    cov = cov * max(chi2, 1.0)
    z = float(np.sqrt(max(s @ np.linalg.solve(cov, s), 0.0)))
    flanks = _flank_z(J, r, w, s)
    return Shift(float(s[0]), float(s[1]), (float(np.sqrt(cov[0, 0])), float(np.sqrt(cov[1, 1]))), z, n, flanks)


def _flank_z(J: np.ndarray, r: np.ndarray, w: np.ndarray, s: np.ndarray) -> tuple[float, float] | None:
    """The shift along the direction of ``s`` as each flank alone sees it, in its standard error
    (inflated by that flank's χ²/pixel when above 1): the pixels where the template ``J û`` is
    positive, then negative.  The gradients of a compact image sum to zero along any direction,
    so both flanks are there wherever the image has an edge.  None for a zero shift, or where a
    flank holds fewer than 3 pixels (then the whole-image test stands alone)."""
    size = float(np.hypot(*s))
    if not size > 0:
        return None
    t = J @ (s / size)
    out = []
    for part in (t > 0, t < 0):
        a = float(np.sum(w[part] * t[part] ** 2))
        if part.sum() < 3 or not a > 0:
            return None  # one flank only (the image cut by its valid pixels): the test cannot be asked
        est = float(np.sum(w[part] * t[part] * r[part])) / a
        chi2 = float(np.sum(w[part] * (r[part] - est * t[part]) ** 2)) / max(int(part.sum()) - 1, 1)
        out.append(est / np.sqrt(max(chi2, 1.0) / a))
    return (float(out[0]), float(out[1]))


def shift_warning(label: str, shift: Shift, chi2_per_pixel: float, angle_structured: bool = False) -> str | None:
    """The warning for a pose whose residual is structured like a shift (None when not).

    ``angle_structured``: the same pose's residual is also structured by viewing angle
    (:func:`fluxcli.inverse.diagnostics.angle_structure`).  A wrong emission profile misjudges
    the light of every element seen obliquely, most at the silhouette's edges, and that misfit
    lies along the image's gradients too: on the same Monte Carlo photons through two mirrors a
    Lambertian model reads a 0.63-pixel shift (55 standard errors) and ``diffuse`` none
    (docs/accuracy.md).  The warning then points at the emission model before the geometry."""
    if not shift.seen:
        return None
    head = (f"the residual looks like the image shifted by ({shift.dx_px:+.2f}, {shift.dy_px:+.2f}) pixels "
            f"(x, y; {shift.z:.0f} times its standard error) although chi^2/pixel is {chi2_per_pixel:.3g}")
    if angle_structured:
        return (head + ", and it is also structured by viewing angle: an emission model that does not fit the "
                "surface (subject.emission) misjudges the light of elements seen obliquely, most at the edges of "
                "the subject's image, and reads as a shift; check subject.emission first, then system.camera.pose "
                "and system.mirrors; the total may be off by more than its sigma")
    return (head + ": the camera or a mirror is likely a calibration error away from where the config puts it "
            "(check system.camera.pose, system.mirrors, or calibrate again); the total may be off by more than "
            "its sigma")
