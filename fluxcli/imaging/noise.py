"""Noise models that turn expected photons per pixel into simulated measurements.

Three models, from the paper's to the camera's:

- :func:`gaussian_shot` — the paper's model, ``a + N(0, sqrt(a))`` in photons;
- :func:`poisson_shot` — Poisson photon counts;
- :func:`emccd_counts` — the full EMCCD chain of Hirsch et al. (PLoS ONE 2013):
  quantum efficiency, Poisson electrons (photo, dark, clock-induced charge), gamma-
  distributed electron-multiplying gain, read noise, bias, ADC gain, rounding and
  saturation, giving 16-bit counts. :func:`counts_to_photons` inverts its mean.

The EM register's excess noise factor is written once, :func:`excess_noise_factor2`
(``F² = 2 − 1/G``): the simulated chain draws with it, and its closed-form variance
(:func:`expected_variance_counts`) and the reconstruction's noise model
(:class:`PhotonNoise`) evaluate it.

All inputs ``photons_per_pixel`` are noiseless expected photons reaching each pixel
during one exposure (any shape, ≥ 0). Randomness comes only from the
``numpy.random.Generator`` passed in, drawn in a fixed order, so the same seed gives
the same bytes.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, replace

import numpy as np

__all__ = [
    "EMCCDModel",
    "NOISE_KINDS",
    "PhotonNoise",
    "excess_noise_factor2",
    "conventional_counts",
    "counts_to_photons",
    "emccd_counts",
    "expected_counts",
    "expected_variance_counts",
    "gaussian_shot",
    "max_snr",
    "poisson_shot",
    "saturated",
]


def _check_photons(photons_per_pixel) -> np.ndarray:
    photons = np.asarray(photons_per_pixel, dtype=np.float64)
    if not np.all(np.isfinite(photons)) or np.any(photons < 0):
        raise ValueError("photons_per_pixel must be finite and non-negative everywhere.")
    return photons


def _check_rng(rng) -> np.random.Generator:
    if not isinstance(rng, np.random.Generator):
        raise ValueError(
            f"rng must be a numpy.random.Generator (e.g. numpy.random.default_rng(seed)), "
            f"not {type(rng).__name__}."
        )
    return rng


def _check_model(model) -> "EMCCDModel":
    if not isinstance(model, EMCCDModel):
        raise ValueError(f"model must be an EMCCDModel, not {type(model).__name__}.")
    return model


def gaussian_shot(photons_per_pixel, rng: np.random.Generator) -> np.ndarray:
    """Add the paper's Gaussian shot noise: ``a + N(0, sqrt(a))``.

    Parameters
    ----------
    photons_per_pixel : array_like of float, any shape
        Expected photons per pixel ``a`` (photons per exposure), ≥ 0.
    rng : numpy.random.Generator
        Source of randomness.

    Returns
    -------
    numpy.ndarray of float64, same shape
        Noisy photons per pixel. Values may be negative where ``a`` is small, as in
        the paper's simulations; they are not clipped.
    """
    photons = _check_photons(photons_per_pixel)
    _check_rng(rng)
    return photons + np.sqrt(photons) * rng.standard_normal(photons.shape)


def poisson_shot(photons_per_pixel, rng: np.random.Generator) -> np.ndarray:
    """Draw Poisson photon counts with the given means.

    Parameters
    ----------
    photons_per_pixel : array_like of float, any shape
        Expected photons per pixel (photons per exposure), ≥ 0.
    rng : numpy.random.Generator
        Source of randomness.

    Returns
    -------
    numpy.ndarray of float64, same shape
        Integer-valued photon counts per pixel (variance = mean).
    """
    photons = _check_photons(photons_per_pixel)
    _check_rng(rng)
    return rng.poisson(photons).astype(np.float64)


def max_snr(photons_per_pixel) -> float:
    """Peak signal-to-noise ratio of an image under shot noise: ``sqrt(max a)``.

    This is the convention of the paper's Table 1 (SNR of the brightest pixel under
    Gaussian noise of standard deviation ``sqrt(a)``).

    Parameters
    ----------
    photons_per_pixel : array_like of float, any shape, non-empty
        Expected photons per pixel, ≥ 0.

    Returns
    -------
    float
        ``sqrt(max(photons_per_pixel))`` (dimensionless).
    """
    photons = _check_photons(photons_per_pixel)
    if photons.size == 0:
        raise ValueError("photons_per_pixel must hold at least one pixel to compute max_snr.")
    return float(np.sqrt(photons.max()))


@dataclass(frozen=True)
class EMCCDModel:
    """Parameters of an electron-multiplying CCD (one readout mode, one exposure).

    Defaults are typical for the Hamamatsu ImagEM (see reference/hardware.md); they are
    *unverified* and belong in the config for real data.

    Attributes
    ----------
    quantum_efficiency : float
        Fraction of incident photons that become photoelectrons, in (0, 1].
    em_gain : float
        Mean electron-multiplication gain ``G`` of the EM register, ≥ 1.
    read_noise_e : float
        RMS read noise in electrons at the output node, i.e. added *after* the EM
        register (so its effect referred to the input is ``read_noise_e / G``), ≥ 0.
    bias_counts : float
        Offset added by the ADC (counts), ≥ 0.
    electrons_per_count : float
        ADC conversion gain ``g`` at the output node (electrons per count), > 0.
    dark_current_e_per_s : float
        Dark current (electrons per pixel per second, before the EM register), ≥ 0.
    cic_e_per_pixel : float
        Clock-induced charge (electrons per pixel per readout), ≥ 0. Treated like
        photoelectrons (fully multiplied), as in Hirsch et al.; real CIC generated
        inside the EM register sees less gain.
    exposure_s : float
        Exposure time (s), ≥ 0 (0 gives a bias frame plus CIC).
    bit_depth : int
        ADC bit depth, 1 to 16; counts are clipped to ``[0, 2**bit_depth - 1]``.

    Notes
    -----
    The EM register has the excess noise factor ``F² = 2 − 1/G`` of ideal multiplication
    (:func:`excess_noise_factor2`): ``em_gain = 1`` is no multiplication (``F² = 1``).
    """

    quantum_efficiency: float = 0.9
    em_gain: float = 300.0
    read_noise_e: float = 50.0
    bias_counts: float = 500.0
    electrons_per_count: float = 10.0
    dark_current_e_per_s: float = 0.001
    cic_e_per_pixel: float = 0.005
    exposure_s: float = 1.0
    bit_depth: int = 16

    def __post_init__(self) -> None:
        for name in (
            "quantum_efficiency",
            "em_gain",
            "read_noise_e",
            "bias_counts",
            "electrons_per_count",
            "dark_current_e_per_s",
            "cic_e_per_pixel",
            "exposure_s",
        ):
            value = getattr(self, name)
            if (
                isinstance(value, bool)
                or not isinstance(value, numbers.Real)
                or not math.isfinite(value)
            ):
                raise ValueError(f"EMCCDModel.{name} must be a finite number, got {value!r}.")
        if not 0.0 < self.quantum_efficiency <= 1.0:
            raise ValueError(
                f"EMCCDModel.quantum_efficiency must be in (0, 1], got {self.quantum_efficiency!r}."
            )
        if self.em_gain < 1.0:
            raise ValueError(f"EMCCDModel.em_gain must be at least 1, got {self.em_gain!r}.")
        if self.electrons_per_count <= 0.0:
            raise ValueError(
                f"EMCCDModel.electrons_per_count must be positive, got {self.electrons_per_count!r}."
            )
        for name in (
            "read_noise_e",
            "bias_counts",
            "dark_current_e_per_s",
            "cic_e_per_pixel",
            "exposure_s",
        ):
            if getattr(self, name) < 0.0:
                raise ValueError(
                    f"EMCCDModel.{name} must be non-negative, got {getattr(self, name)!r}."
                )
        if (
            isinstance(self.bit_depth, bool)
            or not isinstance(self.bit_depth, numbers.Integral)
            or not 1 <= self.bit_depth <= 16
        ):
            raise ValueError(
                f"EMCCDModel.bit_depth must be an integer from 1 to 16, got {self.bit_depth!r}."
            )

    @property
    def max_count(self) -> int:
        """Largest count the ADC can output, ``2**bit_depth - 1`` (counts)."""
        return (1 << int(self.bit_depth)) - 1

    @property
    def background_e_per_pixel(self) -> float:
        """Mean dark plus clock-induced electrons per pixel per exposure (electrons)."""
        return self.dark_current_e_per_s * self.exposure_s + self.cic_e_per_pixel


def _mean_input_electrons(photons: np.ndarray, model: EMCCDModel) -> np.ndarray:
    """λ = QE·N + dark·t + CIC (electrons entering the EM register, per pixel)."""
    return model.quantum_efficiency * photons + model.background_e_per_pixel


def emccd_counts(photons_per_pixel, model: EMCCDModel, rng: np.random.Generator) -> np.ndarray:
    """Simulate EMCCD counts for one exposure (Hirsch et al. 2013).

    Per pixel, in this order:

    1. electrons ``n ~ Poisson(λ)``, ``λ = QE·N + dark·t + CIC``;
    2. EM register output ``x ~ Gamma(shape=n/(F² − 1), scale=G(F² − 1))`` electrons with
       ``F² = 2 − 1/G`` (:func:`excess_noise_factor2`): mean ``nG`` and variance ``nG²(F² − 1)``
       = ``nG(G − 1)``, the sum of ``n`` outputs of an ideal multiplier (each geometric, mean
       ``G``); ``Gamma(n, G)`` of Hirsch et al. at high gain, and ``x = n`` at ``G = 1``
       (``x = 0`` where ``n = 0``);
    3. read noise: ``x + Normal(0, read_noise_e)`` electrons at the output node;
    4. ADC: ``bias_counts + (x + noise) / electrons_per_count``, rounded to the
       nearest integer and clipped to ``[0, 2**bit_depth - 1]``.

    Parameters
    ----------
    photons_per_pixel : array_like of float, any shape
        Expected photons reaching each pixel during the exposure, ≥ 0.
    model : EMCCDModel
        Camera parameters.
    rng : numpy.random.Generator
        Source of randomness.

    Returns
    -------
    numpy.ndarray of uint16, same shape
        Counts per pixel. Pixels at ``model.max_count`` are saturated (see
        :func:`saturated`).
    """
    photons = _check_photons(photons_per_pixel)
    model = _check_model(model)
    _check_rng(rng)
    electrons_in = rng.poisson(_mean_input_electrons(photons, model))
    excess = excess_noise_factor2(model.em_gain) - 1.0  # per electron: variance G² (F² − 1)
    if excess > 0:
        # Gamma(0, ·) is the point mass at 0; numpy returns 0 there, the where makes it explicit.
        electrons_out = np.where(
            electrons_in > 0, rng.gamma(np.maximum(electrons_in, 1) / excess, model.em_gain * excess), 0.0
        )
    else:  # G = 1: no multiplication
        electrons_out = electrons_in.astype(np.float64)
    electrons_out = electrons_out + model.read_noise_e * rng.standard_normal(photons.shape)
    counts = model.bias_counts + electrons_out / model.electrons_per_count
    return np.clip(np.rint(counts), 0, model.max_count).astype(np.uint16)


def conventional_counts(photons_per_pixel, model: EMCCDModel, rng: np.random.Generator) -> np.ndarray:
    """Simulate counts read out with the EM gain off (no multiplication).

    As :func:`emccd_counts` without step 2: electrons ``n ~ Poisson(λ)`` read out
    directly, ``bias_counts + (n + Normal(0, read_noise_e)) / electrons_per_count``,
    rounded and clipped; ``model.em_gain`` is ignored. Mean ``bias + λ / g`` and variance
    ``λ / g² + (σ_r / g)²`` counts²: the photon-transfer curve of a conventional CCD,
    slope ``1 / g``. This is how a camera's "EM gain off" frames for calibration are made
    (the same as :func:`emccd_counts` at ``em_gain = 1``, which has ``F² = 1``).

    Parameters
    ----------
    photons_per_pixel : array_like of float, any shape
        Expected photons reaching each pixel during the exposure, ≥ 0.
    model : EMCCDModel
        Camera parameters (``em_gain`` unused).
    rng : numpy.random.Generator
        Source of randomness.

    Returns
    -------
    numpy.ndarray of uint16, same shape
        Counts per pixel.
    """
    photons = _check_photons(photons_per_pixel)
    model = _check_model(model)
    _check_rng(rng)
    electrons = rng.poisson(_mean_input_electrons(photons, model)).astype(np.float64)
    electrons = electrons + model.read_noise_e * rng.standard_normal(photons.shape)
    counts = model.bias_counts + electrons / model.electrons_per_count
    return np.clip(np.rint(counts), 0, model.max_count).astype(np.uint16)


def saturated(counts_per_pixel, model: EMCCDModel) -> np.ndarray:
    """Mask of pixels at the ADC's full scale.

    Parameters
    ----------
    counts_per_pixel : array_like, any shape
        Counts, e.g. from :func:`emccd_counts`.
    model : EMCCDModel
        Camera parameters (gives ``bit_depth``).

    Returns
    -------
    numpy.ndarray of bool, same shape
        True where ``counts >= 2**bit_depth - 1``; those pixels carry only a lower
        bound on the signal.
    """
    model = _check_model(model)
    return np.asarray(counts_per_pixel) >= model.max_count


def expected_counts(photons_per_pixel, model: EMCCDModel) -> np.ndarray:
    """Mean counts per pixel of :func:`emccd_counts` (before rounding and clipping).

    With ``λ = QE·N + dark·t + CIC``, ``n ~ Poisson(λ)`` and ``x | n ~ Gamma(n, G)``:
    ``E[x] = E[E[x | n]] = E[n]·G = G·λ``; the read noise has mean zero, so

        E[counts] = bias_counts + G·λ / g,   g = electrons_per_count.

    Rounding to the nearest count changes this by much less than one count once the
    noise spans a few counts; clipping (saturation, or counts below 0) is not modelled.

    Parameters
    ----------
    photons_per_pixel : array_like of float, any shape
        Expected photons per pixel, ≥ 0.
    model : EMCCDModel
        Camera parameters.

    Returns
    -------
    numpy.ndarray of float64, same shape
        Mean counts per pixel.
    """
    photons = _check_photons(photons_per_pixel)
    model = _check_model(model)
    lam = _mean_input_electrons(photons, model)
    return model.bias_counts + model.em_gain * lam / model.electrons_per_count


def expected_variance_counts(photons_per_pixel, model: EMCCDModel) -> np.ndarray:
    """Variance of the counts of :func:`emccd_counts` (before rounding and clipping).

    By the law of total variance, with ``E[x | n] = n·G`` and ``Var[x | n] = n·G²(F² − 1)``
    (the register's gamma distribution) and ``E[n] = Var[n] = λ`` (Poisson):

        Var[x] = E[Var(x | n)] + Var(E[x | n]) = λ·G²(F² − 1) + G²·λ = F²·G²·λ,

    the excess noise factor ``F² = Var[x] / (G·E[x]) = 2 − 1/G``
    (:func:`excess_noise_factor2`). Adding independent read noise ``σ_r`` electrons and
    dividing by ``g`` electrons per count:

        Var[counts] = F²·G²·λ / g² + (σ_r / g)².

    Rounding adds about 1/12 count², which is neglected.

    Parameters
    ----------
    photons_per_pixel : array_like of float, any shape
        Expected photons per pixel, ≥ 0.
    model : EMCCDModel
        Camera parameters.

    Returns
    -------
    numpy.ndarray of float64, same shape
        Variance of the counts per pixel (counts²).
    """
    photons = _check_photons(photons_per_pixel)
    model = _check_model(model)
    lam = _mean_input_electrons(photons, model)
    g = model.electrons_per_count
    return excess_noise_factor2(model.em_gain) * model.em_gain**2 * lam / g**2 + (model.read_noise_e / g) ** 2


def counts_to_photons(counts_per_pixel, model: EMCCDModel) -> np.ndarray:
    """Estimate photons per pixel from EMCCD counts by inverting the mean.

        N̂ = ((counts − bias)·g / G − (dark·t + CIC)) / QE

    Because the mean of the counts is linear in the photons
    (:func:`expected_counts`), ``N̂`` is an unbiased estimator of the expected photons
    ``N``: ``E[N̂] = N`` (up to rounding, negligible once the noise spans a few counts).
    Single pixels are noisy (``Var[N̂] ≈ F²·λ/QE²``, ``F² → 2`` at high gain) and may be negative.
    Saturated or zero-clipped pixels are biased low/high; mask them with
    :func:`saturated`.

    Parameters
    ----------
    counts_per_pixel : array_like, any shape
        Counts (e.g. from :func:`emccd_counts`, or their mean over frames).
    model : EMCCDModel
        Camera parameters the counts were taken with.

    Returns
    -------
    numpy.ndarray of float64, same shape
        Estimated photons per pixel per exposure.
    """
    model = _check_model(model)
    counts = np.asarray(counts_per_pixel, dtype=np.float64)
    if not np.all(np.isfinite(counts)):
        raise ValueError("counts_per_pixel must be finite everywhere.")
    electrons_in = (counts - model.bias_counts) * model.electrons_per_count / model.em_gain
    return (electrons_in - model.background_e_per_pixel) / model.quantum_efficiency


# ------------------------------------------------------------------ the one noise model
NOISE_KINDS = ("gaussian", "poisson", "emccd")


def excess_noise_factor2(em_gain: float) -> float:
    """Excess noise factor ``F²`` of an EM register of mean gain ``G``: ``2 − 1/G``.

    This is the many-stage limit of ``F² = 2(G − 1)G^(−(N+1)/N) + 1/G`` (Robbins & Hadwen
    2003): 1 without multiplication, → 2 at high gain (2 − 1/300 = 1.997 at G = 300).

    Parameters
    ----------
    em_gain : float
        Mean EM gain ``G`` ≥ 1 (dimensionless).

    Returns
    -------
    float
        ``F²`` (dimensionless).
    """
    em_gain = float(em_gain)
    if not math.isfinite(em_gain) or em_gain < 1:
        raise ValueError(f"em_gain must be a finite number ≥ 1, got {em_gain!r}.")
    return 2.0 - 1.0 / em_gain


@dataclass(frozen=True)
class PhotonNoise:
    """How noisy a measured photon image is: the variance of each pixel given its mean.

    The one noise model of fluxmap: every weight, σ, χ² and discrepancy target of the
    reconstruction evaluates :meth:`variance` on a *model* image (``T b̂``), never on
    the measured one (that would bias totals low at low counts).

    Attributes
    ----------
    kind : {"gaussian", "poisson", "emccd"}
        ``gaussian`` (the paper's ``a + N(0, √a)``) and ``poisson`` both have variance
        ``a``; ``emccd`` is the EMCCD chain of :func:`emccd_counts` read back with
        :func:`counts_to_photons`.
    read_noise_photons : float
        Extra additive noise (rms photons) for ``gaussian``/``poisson`` (a conventional
        camera's read noise referred to the input); ignored for ``emccd``, whose read
        noise comes from ``sensor``.
    sensor : EMCCDModel or None
        Required for ``emccd``.
    floor_photons2 : float
        Smallest variance returned (photons²): a pixel whose model is dark must not get
        an infinite weight (default 0.25, a quarter of a photon²).
    frames_averaged : int
        The image is the mean of this many frames (its variance is that much smaller).
    """

    kind: str = "poisson"
    read_noise_photons: float = 0.0
    sensor: EMCCDModel | None = None
    floor_photons2: float = 0.25
    frames_averaged: int = 1

    def __post_init__(self) -> None:
        if isinstance(self.frames_averaged, bool) or not isinstance(self.frames_averaged, numbers.Integral) \
                or self.frames_averaged < 1:
            raise ValueError(f"PhotonNoise.frames_averaged must be an integer ≥ 1, got {self.frames_averaged!r}.")
        if self.kind not in NOISE_KINDS:
            raise ValueError(f"noise kind must be one of {', '.join(NOISE_KINDS)}; got {self.kind!r}.")
        if self.kind == "emccd":
            _check_model(self.sensor)
        for name in ("read_noise_photons", "floor_photons2"):
            v = getattr(self, name)
            if not (isinstance(v, numbers.Real) and math.isfinite(v) and v >= 0):
                raise ValueError(f"PhotonNoise.{name} must be a finite number ≥ 0, got {v!r}.")

    def variance(self, mean_photons) -> np.ndarray:
        """Variance of a measured pixel, in photons², given its mean ``a`` (photons).

        - gaussian, poisson: ``σ² = a + read_noise_photons²``;
        - emccd: ``σ² = [F²(QE·a + d) + (σ_r/G)²] / QE²`` with ``d`` dark + CIC electrons,
          ``σ_r`` the read noise (electrons rms at the output), ``G`` the EM gain and
          ``F² = 2 − 1/G`` (:func:`excess_noise_factor2`) — the variance of
          :func:`counts_to_photons` of :func:`emccd_counts` (ADC rounding neglected).

        Negative means (a model may dip below 0) count as 0; the result is at least
        ``floor_photons2``.

        Parameters
        ----------
        mean_photons : array_like of float, any shape
            Expected photons per pixel.

        Returns
        -------
        numpy.ndarray of float64, same shape
            Variance in photons².
        """
        a = np.maximum(np.asarray(mean_photons, dtype=np.float64), 0.0)
        if self.kind == "emccd":
            s = self.sensor
            qe, gain = s.quantum_efficiency, s.em_gain
            f2 = excess_noise_factor2(gain)
            var = (f2 * (qe * a + s.background_e_per_pixel) + (s.read_noise_e / gain) ** 2) / qe**2
        else:
            var = a + self.read_noise_photons**2
        return np.maximum(var / self.frames_averaged, self.floor_photons2)

    @property
    def variance_per_photon(self) -> float:
        """``dσ²/da`` (photons² per photon): 1 for shot noise, ``F²/QE`` for an EMCCD."""
        if self.kind == "emccd":
            return excess_noise_factor2(self.sensor.em_gain) / self.sensor.quantum_efficiency
        return 1.0


def capture_photons(cap, sensor: EMCCDModel) -> tuple[np.ndarray, np.ndarray]:
    """Photons per pixel per exposure ``(P, ny, nx)`` of a capture's mean light frames, and the
    mask of usable pixels (``cap``: :class:`fluxcli.artefacts.capture.CaptureImages`).

    The mean dark frame (bias + dark current + clock-induced charge, taken at the same
    exposure and gain) is subtracted, then electrons = counts x electrons_per_count /
    EM gain and photons = electrons / QE: ``N = (C - D) g / (G QE)``, unbiased since
    E[C] - E[D] = G QE N / g.  ``sensor`` gives QE, electrons per count and bit depth;
    the gain is the one read back from the camera.  Pixels that saturated in any
    repeat are masked."""
    model = replace(sensor, em_gain=cap.em_gain, exposure_s=cap.exposure_s, bias_counts=cap.dark_mean_counts,
                    dark_current_e_per_s=0.0, cic_e_per_pixel=0.0)
    valid = ~saturated(cap.counts_max, model)
    return counts_to_photons(cap.counts_mean, model), valid


def pattern_photons(pc, sensor: EMCCDModel) -> dict[str, np.ndarray]:
    """Photons per pixel per exposure of every structured-light frame of a capture (``pc``:
    :class:`fluxcli.artefacts.capture.PatternCapture`; the sensor's bias, dark and CIC removed
    at the gain and exposure read back; :func:`counts_to_photons`)."""
    model = replace(sensor, em_gain=pc.em_gain, exposure_s=pc.exposure_s)
    return {p: counts_to_photons(c, model) for p, c in pc.counts.items()}
