"""Counts to photons with per-pixel sensor maps (bias, dark current, flat field).

The per-pixel form of :func:`fluxcli.imaging.noise.counts_to_photons`: a pixel with bias
``B`` (counts), dark current ``D`` (electrons/s) and relative response ``F`` (mean 1 over
the sensor) has mean counts

    E[counts] = B + G · (QE · F · N + D · t + CIC) / K,

so ``N̂ = ((counts − B) · K / G − D · t − CIC) / (QE · F)`` is unbiased, ``E[N̂] = N``.
Maps come from a radiometric calibration (``fluxmap calibrate``); a map not given falls
back to the scalar in the model (flat: 1).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .noise import EMCCDModel, counts_to_photons

__all__ = ["counts_to_photons_with_maps"]


def counts_to_photons_with_maps(counts_per_pixel, model: EMCCDModel, *, bias_counts_map=None,
                                dark_e_per_s_map=None, flat_map=None, min_flat: float = 0.05) -> np.ndarray:
    """Estimate photons per pixel from counts, pixel by pixel.

    Parameters
    ----------
    counts_per_pixel : array_like, shape (ny, nx)
        Counts of one exposure (or their mean over frames).
    model : EMCCDModel
        Camera parameters (``electrons_per_count``, ``em_gain``, ``quantum_efficiency``,
        ``cic_e_per_pixel``, ``exposure_s``; ``bias_counts`` and
        ``dark_current_e_per_s`` where no map replaces them).
    bias_counts_map : array_like, shape (ny, nx), optional
        Bias per pixel (counts), replacing ``model.bias_counts``.
    dark_e_per_s_map : array_like, shape (ny, nx), optional
        Dark current per pixel (electrons/s), replacing ``model.dark_current_e_per_s``.
    flat_map : array_like, shape (ny, nx), optional
        Relative response per pixel (dimensionless, mean 1 over the sensor).
    min_flat : float, optional
        Pixels whose flat value is below this are dead: NaN is returned there.

    Returns
    -------
    numpy.ndarray of float64, shape (ny, nx)
        Estimated photons per pixel per exposure (NaN at dead pixels).

    Raises
    ------
    ValueError
        A map whose shape differs from the counts', or with non-finite values.
    """
    counts = np.asarray(counts_per_pixel, dtype=np.float64)
    maps = {"bias_counts_map": bias_counts_map, "dark_e_per_s_map": dark_e_per_s_map, "flat_map": flat_map}
    for name, m in maps.items():
        if m is not None:
            m = np.asarray(m, dtype=np.float64)
            if m.shape != counts.shape:
                raise ValueError(f"{name} has shape {m.shape}; the counts have {counts.shape}.")
            if not np.all(np.isfinite(m)):
                raise ValueError(f"{name} holds non-finite values.")
            maps[name] = m
    if maps["bias_counts_map"] is not None:  # shift so that the model's scalar bias removes the map
        counts = counts - maps["bias_counts_map"] + model.bias_counts
    dark_photons = 0.0
    if maps["dark_e_per_s_map"] is not None:
        model = replace(model, dark_current_e_per_s=0.0)
        dark_photons = maps["dark_e_per_s_map"] * model.exposure_s / model.quantum_efficiency
    photons = counts_to_photons(counts, model) - dark_photons
    if maps["flat_map"] is not None:
        flat = maps["flat_map"]
        photons = np.where(flat >= min_flat, photons / np.where(flat >= min_flat, flat, 1.0), np.nan)
    return photons


BELOW_BIAS_SIGMAS, BELOW_BIAS_COUNTS, BELOW_BIAS_SHARE = 5.0, 2.0, 0.25
"""Raw counts fall below the bias only by the read noise: a quarter of the pixels lower than the
bias by 5 read-noise sigmas + 2 counts is an image bias-subtracted (or scaled) already, or a bias
that is not this camera's (its whole background lies below). A bias that varies over the sensor by
more than the margin puts a few pixels there too (5 % for ±30 counts about a scalar bias with 5
counts of read noise); those are left to the calibration's bias map."""


def below_bias(counts, model: EMCCDModel, valid, bias_counts_map=None) -> tuple[float, float, float] | None:
    """``(share of valid pixels below the bias by more than the margin, the margin (counts), the
    image's median (counts))`` when that share exceeds :data:`BELOW_BIAS_SHARE`; None otherwise.
    Without it a bias-subtracted image given as counts had the bias taken off twice: most pixels
    500 counts below zero, and a total 0.79x the truth under a chi² warning."""
    counts = np.asarray(counts, dtype=np.float64)
    valid = np.asarray(valid, bool) & np.isfinite(counts)
    if not valid.any():
        return None
    bias = model.bias_counts if bias_counts_map is None else np.asarray(bias_counts_map, dtype=np.float64)
    margin = BELOW_BIAS_SIGMAS * model.read_noise_e / model.electrons_per_count + BELOW_BIAS_COUNTS
    low = (counts < bias - margin) & valid
    share = float(low.sum() / valid.sum())
    return (share, margin, float(np.median(counts[valid]))) if share > BELOW_BIAS_SHARE else None
