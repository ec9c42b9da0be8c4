"""Detector-side imaging: noise models for simulated images and image files.

- :mod:`fluxcli.imaging.noise` — Gaussian (the paper's), Poisson and EMCCD noise,
  turning expected photons per pixel into simulated measurements and counts back into
  photons.
- :mod:`fluxcli.imaging.imagefiles` — single-channel TIFF / FITS / EXR files through
  OpenImageIO, ``[row, col]`` = ``[ny, nx]``, row 0 first, with metadata.
"""

from fluxcli.imaging.imagefiles import read_image, write_image
from fluxcli.imaging.noise import (
    EMCCDModel,
    PhotonNoise,
    counts_to_photons,
    emccd_counts,
    excess_noise_factor2,
    expected_counts,
    expected_variance_counts,
    gaussian_shot,
    max_snr,
    poisson_shot,
    saturated,
)

__all__ = [
    "EMCCDModel",
    "PhotonNoise",
    "counts_to_photons",
    "emccd_counts",
    "excess_noise_factor2",
    "expected_counts",
    "expected_variance_counts",
    "gaussian_shot",
    "max_snr",
    "poisson_shot",
    "read_image",
    "saturated",
    "write_image",
]
