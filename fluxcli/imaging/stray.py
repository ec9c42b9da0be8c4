"""Light on pixels that no element of the subject can reach (stray light, a wrong geometry)."""

from __future__ import annotations

import numpy as np

from ..errors import UserError
from . import noise as N
from .spikes import MAX_SPIKE_SHARE, isolated_spikes

STRAY_WARN = 0.05  # share of the image's light on pixels no element reaches: warned above this
STRAY_REFUSE = 0.5  # ... and refused above this: the images do not show this geometry


def light_outside(T, image: np.ndarray, valid: np.ndarray, noise: N.PhotonNoise, label: str, surface) -> str | None:
    """The image's light that no element of the subject can have sent: on pixels where every
    column of T (all views) is zero.  The solve only looks at the pixels T reaches, so light
    elsewhere would otherwise be ignored without a word — a mesh in metres instead of mm, a
    pose or a camera that does not match the images would give a plausible total.

    Counted when it stands out of the noise (more than 5 σ of the noise model summed over
    those pixels); a warning above :data:`STRAY_WARN` of the light, a :class:`UserError`
    above :data:`STRAY_REFUSE`.  Isolated spikes there (:func:`isolated_spikes` against a
    model of 0: cosmic rays, hot pixels) say nothing of the geometry and are not counted
    (:func:`reject_spikes` names them after the solve).  Returns the warning or None."""
    reach = np.asarray(abs(T).sum(axis=1)).ravel() > 0
    a = np.asarray(image, dtype=np.float64).ravel()
    ok = np.asarray(valid).ravel() & np.isfinite(a)
    out_px = ok & ~reach
    spikes = isolated_spikes(np.asarray(image), 0.0, np.asarray(valid).reshape(np.shape(image)), noise).ravel() & out_px
    if spikes.sum() <= MAX_SPIKE_SHARE * ok.sum():
        out_px &= ~spikes
        ok &= ~spikes
    outside = float(a[out_px].sum())
    total = float(a[ok].sum())
    if total <= 0 or outside <= 0:
        return None
    noise_sd = float(np.sqrt(noise.variance(a[out_px]).sum()))
    share = outside / total
    if outside <= 5 * noise_sd or share <= STRAY_WARN:
        return None
    lo, hi = surface.bounds_mm()
    what = (f"{share:.0%} of the image's light ({outside:.3g} of {total:.3g} photons, {noise_sd:.2g} of it noise) "
            f"falls on pixels that no element of the subject can reach")
    if share > STRAY_REFUSE:
        raise UserError(
            f"reconstruct, pose {label}: {what}: the images do not show this geometry. Check the mesh's units "
            f"(fluxmap reads millimetres; subject.surface spans {np.ptp(np.stack([lo, hi]), axis=0).round(3).tolist()} mm; "
            "a mesh in metres needs subject.surface.scale_to_mm: 1000), "
            "subject.poses (their order is the images' order), system.camera (pose, pixels, binning) and whether "
            "the images still hold a bias or background; set pixels that show something else to NaN to leave "
            "them out.")
    return (f"{what}: it is left out of the fit (light from outside the subject's mesh, a misplaced pose or "
            "camera, an unsubtracted bias or background, or stray light); set such pixels to NaN to silence this")
