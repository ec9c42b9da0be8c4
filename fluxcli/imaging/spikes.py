"""Isolated spikes: pixels far above a model that none of their neighbours follows.

Cosmic rays, hot pixels, a stray reflection off a screw head: light no smooth surface behind
a lens with a point spread of a pixel or more can send to one pixel alone.  ``reconstruct``
leaves them out after a first solve (:func:`reject_spikes`) and does not count them as stray
light (:mod:`fluxcli.imaging.stray`).  Images are photons, [ny, nx].
"""

from __future__ import annotations

import numpy as np

from . import noise as N

SPIKE_SIGMA = 20.0  # a pixel this many sigma of the noise model above the model ...
SPIKE_SPREAD = 5.0  # ... and this many times the residuals' own spread (where the fit is off by more than noise) ...
SPIKE_ISOLATION = 8.0  # ... and this many times further above it than any of its 8 neighbours
MAX_SPIKE_SHARE = 0.005  # at most this share of the valid pixels is left out as spikes


def isolated_spikes(image: np.ndarray, model: np.ndarray, valid: np.ndarray, noise: N.PhotonNoise) -> np.ndarray:
    """Pixels far above the model that none of their neighbours follows: cosmic rays, hot
    pixels, a stray reflection off a screw head — light no smooth surface behind a lens
    with a point spread of a pixel or more can send to one pixel alone.

    ``z = (a - model) / sqrt(var(max(a, model)))`` (the variance at the larger of the two,
    so a spike cannot shrink its own sigma). Noise alone gives a Gaussian z, whose largest
    value on 10⁷ pixels is about 5.3: SPIKE_SIGMA = 20 is no false alarm on noise. Where the
    model is off by more than noise (a camera a calibration error away, a surface finer than
    the elements: |z| of 25 and more along edges at high signal, as the accuracy battery met,
    or up to 67 on test_plausible_but_wrong's images at 2e4 photons a pixel) the residuals'
    own spread ``s`` (1.4826 x the median |z| where the model has light: a Gaussian's sigma,
    robust to the spikes themselves; 1.6 on issue 25's scene at a 2e4 peak, 3.7 at 2e5, 36-39
    there) sets the bar too: a spike is a 5-sigma outlier of that spread (SPIKE_SPREAD). So a spike has
    ``z > max(SPIKE_SIGMA, SPIKE_SPREAD s)`` and ``z > SPIKE_ISOLATION x`` the largest ``z`` of
    its valid neighbours (at least 1). Images are [ny, nx] (a 1-D array is one row).
    Returns a mask of the image's shape."""
    from scipy.ndimage import maximum_filter

    a = np.asarray(image, dtype=np.float64)
    shape = a.shape
    a2 = a.reshape(1, -1) if a.ndim == 1 else a
    m2 = np.broadcast_to(np.asarray(model, dtype=np.float64).reshape(a2.shape) if np.ndim(model) else model, a2.shape)
    ok = np.asarray(valid, bool).reshape(a2.shape) & np.isfinite(a2) & np.isfinite(m2)
    with np.errstate(invalid="ignore"):
        z = np.where(ok, (a2 - m2) / np.sqrt(noise.variance(np.where(ok, np.maximum(a2, m2), 0.0))), 0.0)
    scale = residual_spread(z, ok & (m2 > 0))
    ring = np.ones((3, 3), bool)
    ring[1, 1] = False
    neighbours = maximum_filter(z, footprint=ring, mode="constant", cval=0.0)
    return ((z > max(SPIKE_SIGMA, SPIKE_SPREAD * scale))
            & (z > SPIKE_ISOLATION * np.maximum(neighbours, 1.0))).reshape(shape)


def residual_spread(z: np.ndarray, where: np.ndarray) -> float:
    """The spread of the residuals ``z`` (in noise sigma) over ``where``, robust to the spikes
    among them: 1.4826 x the median |z| (a Gaussian's sigma), at least 1 (the noise model's)."""
    return max(1.0, 1.4826 * float(np.median(np.abs(z[where])))) if np.any(where) else 1.0


def describe_pixels(mask: np.ndarray, excess: np.ndarray, limit: int = 3) -> str:
    """'(row r, column c) +X photons' for the brightest few pixels of ``mask``."""
    m2 = mask.reshape(1, -1) if mask.ndim == 1 else mask
    e2 = excess.reshape(m2.shape)
    rows, cols = np.nonzero(m2)
    order = np.argsort(-e2[rows, cols])[:limit]
    text = ", ".join(f"(row {rows[i]}, column {cols[i]}) +{e2[rows[i], cols[i]]:.3g}" for i in order)
    return text + (f" and {rows.size - limit} more" if rows.size > limit else "") + " photons"



def reject_spikes(image: np.ndarray, fitted: np.ndarray, valid: np.ndarray,
                  noise: N.PhotonNoise) -> tuple[np.ndarray, str | None]:
    """After a solve: the valid mask without the isolated spikes above the fit, and the
    warning that names them.  More than :data:`MAX_SPIKE_SHARE` of the pixels is not a few
    cosmic rays: nothing is left out, and the warning says so."""
    spikes = isolated_spikes(image, fitted, valid, noise)
    n = int(spikes.sum())
    if n == 0:
        return valid, None
    excess = np.where(spikes, np.asarray(image, float) - np.nan_to_num(fitted), 0.0)
    where = describe_pixels(spikes, excess)
    if n > MAX_SPIKE_SHARE * np.count_nonzero(valid):
        return valid, (f"{n} pixels stand alone more than {SPIKE_SIGMA:g} sigma above the fit "
                       f"({where}); too many to be cosmic rays or hot pixels, so all were kept: check the images")
    return valid & ~spikes, (f"left out {n} isolated pixel(s) more than {SPIKE_SIGMA:g} sigma above "
                             f"the fit that no neighbour follows ({where}): cosmic rays or hot pixels? They "
                             "held light no surface behind the lens can send to one pixel; set them to NaN to "
                             "silence this")
