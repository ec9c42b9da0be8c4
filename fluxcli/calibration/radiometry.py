"""Radiometric calibration of an EMCCD: bias, read noise, dark current, flat field, photon
transfer (electrons per count) and EM gain, from stacks of frames in counts.

Arrays in, numbers out: every function takes frames as arrays ``[frame, row, col]`` of
counts (ADC units) and returns numbers with their units in their names. Nothing here
reads files, knows the config or prints; :func:`calibrate_radiometric` runs the whole
chain and returns a :class:`RadiometricResult`.

The camera model is the one of :mod:`fluxcli.imaging.noise` (Hirsch et al. 2013):
``counts = bias + x / K`` with ``x`` the electrons at the output node, ``K`` electrons
per count, ``x = Σ`` over ``n ~ Poisson(λ)`` input electrons multiplied by the EM
register (mean gain ``G``, excess noise factor ``F² = 2 − 1/G`` of ideal multiplication,
:func:`fluxcli.imaging.noise.excess_noise_factor2`, unless the config states another) or not multiplied
(EM gain off: ``x = n``; the gain set to 1 in EM mode, read through the same amplifier,
so ``K`` is the same in both), plus Gaussian read noise ``σ_r`` electrons. So for a pixel with mean signal ``S = E[counts] − bias`` (counts):

- EM gain off: ``Var = S / K + (σ_r / K)²`` — the photon-transfer curve (Janesick,
  *Photon Transfer*, SPIE 2007): its slope is ``1 / K``;
- EM gain on: ``Var = F² G S / K + (σ_r / K)²`` — slope ``F² G / K``;
- at the same illumination, ``S_on / S_off = G``.

Temporal variances are taken from the difference of two frames of a pair,
``Var = var(a − b) / 2``, which cancels every fixed pattern (bias structure, flat-field
non-uniformity, uneven illumination) without a model of it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import brentq

from ..errors import InputError
from ..imaging.noise import excess_noise_factor2

__all__ = [
    "PTCLevel",
    "PTCSeries",
    "RadiometricResult",
    "bias_frames",
    "calibrate_radiometric",
    "dark_current",
    "em_gain_from_ptc",
    "em_gain_from_ratio",
    "fit_ptc",
    "flat_field",
    "pair_statistics",
    "read_noise_counts",
]

# ------------------------------------------------------------------ input checks
def _stack(frames, what: str, *, min_frames: int = 1) -> np.ndarray:
    """Frames as float64 ``[frame, row, col]``; one 2-D frame becomes a stack of one."""
    stack = np.asarray(frames, dtype=np.float64)
    if stack.ndim == 2:
        stack = stack[np.newaxis]
    if stack.ndim != 3 or stack.shape[1] == 0 or stack.shape[2] == 0:
        raise InputError(f"{what}: expected frames [frame, row, col], got an array of shape {stack.shape}.")
    if stack.shape[0] < min_frames:
        raise InputError(f"{what}: need at least {min_frames} frame(s), got {stack.shape[0]}.")
    if not np.all(np.isfinite(stack)):
        raise InputError(f"{what}: frames hold non-finite values.")
    return stack


def _bias_for(bias_counts, shape: tuple[int, int], what: str) -> np.ndarray | float:
    bias = np.asarray(bias_counts, dtype=np.float64)
    if bias.ndim == 0:
        return float(bias)
    if bias.shape != shape:
        raise InputError(f"{what}: the bias map is {bias.shape}, the frames are {shape}.")
    return bias


def _pairs(stack: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Disjoint consecutive pairs (0, 1), (2, 3), ...; an odd last frame is left out."""
    return [(stack[i], stack[i + 1]) for i in range(0, stack.shape[0] - 1, 2)]


# ------------------------------------------------------------------ bias and read noise
def bias_frames(frames) -> tuple[float, float, np.ndarray]:
    """Bias level and bias map from frames taken with no light and the shortest exposure.

    Parameters
    ----------
    frames : array_like, shape (n_frames, ny, nx) or (ny, nx)
        Bias frames (counts), EM gain off (with the gain on, clock-induced charge is
        multiplied and shows up as bright single pixels).

    Returns
    -------
    bias_counts : float
        Mean bias over the sensor (counts).
    bias_counts_sigma : float
        Its 1-sigma uncertainty (counts): the scatter of the per-frame means over
        ``sqrt(n_frames)`` (frame-to-frame offset drift included), or the per-pixel
        scatter over ``sqrt(n_pixels)`` for a single frame.
    bias_counts_map : numpy.ndarray of float64, shape (ny, nx)
        Mean over frames per pixel (counts); its noise is ``σ_r / (K sqrt(n_frames))``.
    """
    stack = _stack(frames, "bias frames")
    bias_map = stack.mean(axis=0)
    level = float(bias_map.mean())
    if stack.shape[0] > 1:
        sigma = float(stack.mean(axis=(1, 2)).std(ddof=1) / math.sqrt(stack.shape[0]))
    else:
        sigma = float(stack[0].std(ddof=1) / math.sqrt(stack[0].size))
    return level, sigma, bias_map


def pair_statistics(frame_a, frame_b, bias_counts=0.0, *, max_counts: float | None = None,
                    outlier_sigma: float | None = 8.0) -> tuple[float, float, float, int]:
    """Mean signal and temporal variance of one pair of frames at the same exposure.

    ``mean = mean((a + b) / 2 − bias)`` and ``variance = var(a − b) / 2``; the
    difference cancels fixed patterns. The uncertainty of the variance is estimated
    from the data (the scatter of the squared differences), so it holds for the
    heavy-tailed EM-gain distribution as well as for Gaussian noise.

    Parameters
    ----------
    frame_a, frame_b : array_like, shape (ny, nx)
        Two frames (counts) taken at the same illumination and exposure.
    bias_counts : float or array_like of shape (ny, nx), optional
        Bias level or bias map to subtract (counts).
    max_counts : float, optional
        Pixels at or above this in either frame (saturated), or at or below 0
        (clipped), are left out.
    outlier_sigma : float or None, optional
        Pixels whose difference lies further than this many standard deviations from
        the mean difference (cosmic-ray hits, flickering pixels) are left out, once.
        At 8 sigma this removes no Gaussian pixel and a fraction ~1e-5 of the
        exponential-tailed EM-gain differences (a ~0.1 % bias on their variance).

    Returns
    -------
    mean_counts : float
        Mean signal above bias (counts).
    variance_counts2 : float
        Temporal variance per pixel (counts²).
    variance_sigma_counts2 : float
        1-sigma uncertainty of ``variance_counts2`` (counts²).
    n_pixels : int
        Pixels used.
    """
    a = np.asarray(frame_a, dtype=np.float64)
    b = np.asarray(frame_b, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 2:
        raise InputError(f"a frame pair must be two 2-D frames of one shape, got {a.shape} and {b.shape}.")
    bias = _bias_for(bias_counts, a.shape, "pair_statistics")
    ok = np.isfinite(a) & np.isfinite(b) & (a > 0) & (b > 0)
    if max_counts is not None:
        ok &= (a < max_counts) & (b < max_counts)
    if outlier_sigma is not None and ok.sum() > 1:
        d = (a - b)[ok]
        ok[ok] = np.abs(d - d.mean()) <= outlier_sigma * d.std()
    n = int(ok.sum())
    if n < 16:
        raise InputError(f"a frame pair has only {n} usable pixels (the rest saturated or clipped at 0).")
    signal = (0.5 * (a + b) - bias)[ok]
    diff = (a - b)[ok]
    if not np.any(diff):
        raise InputError("the two frames of a pair are identical (the same file twice?): a pair must be two "
                         "exposures.")
    centred = diff - diff.mean()
    half_sq = 0.5 * centred**2
    variance = float(half_sq.sum() / (n - 1))
    variance_sigma = float(half_sq.std(ddof=1) / math.sqrt(n))
    return float(signal.mean()), variance, variance_sigma, n


def read_noise_counts(frames, *, quantization_counts: float = 1.0) -> tuple[float, float]:
    """Read noise from pairs of bias frames: ``σ² = var(a − b) / 2``, pooled over pairs.

    Parameters
    ----------
    frames : array_like, shape (n_frames, ny, nx), n_frames ≥ 2
        Bias frames (counts), EM gain off; consecutive frames (0, 1), (2, 3), ... are
        paired.
    quantization_counts : float, optional
        ADC step (counts, 1 for integer frames; 0 for frames that are not quantised).

    Returns
    -------
    read_noise_counts : float
        RMS read noise at the output node expressed in counts (multiply by electrons
        per count for electrons).
    read_noise_counts_sigma : float
        Its 1-sigma uncertainty (counts).

    Notes
    -----
    Rounding to whole counts adds ``q²/12`` to the variance of every frame; it is taken
    off (Sheppard's correction) so that the result is the Gaussian read noise of the
    camera model, which fluxmap's noise model adds before the ADC. The correction holds
    once the noise spans a count or more; below ``q/2`` rms nothing is taken off.
    """
    stack = _stack(frames, "bias frames for the read noise", min_frames=2)
    stats = [pair_statistics(a, b) for a, b in _pairs(stack)]
    n = np.array([s[3] for s in stats], dtype=np.float64)
    variance = float((n * np.array([s[1] for s in stats])).sum() / n.sum())
    variance_sigma = float(np.sqrt((n**2 * np.array([s[2] for s in stats]) ** 2).sum()) / n.sum())
    step2 = quantization_counts**2 / 12.0
    if variance > 3.0 * step2:  # noise of half a step rms or more
        variance -= step2
    sigma = math.sqrt(max(variance, 0.0))
    return sigma, (variance_sigma / (2.0 * sigma) if sigma > 0 else math.inf)


# ------------------------------------------------------------------ photon transfer
@dataclass(frozen=True)
class PTCSeries:
    """One photon-transfer curve (variance against mean) and its straight-line fit.

    Attributes
    ----------
    em_gain_on : bool
        Whether the EM register was on for these frames.
    exposure_s : numpy.ndarray, shape (n_levels,)
        Exposure of each level (s).
    mean_counts : numpy.ndarray, shape (n_levels,)
        Mean signal above bias per level (counts).
    variance_counts2 : numpy.ndarray, shape (n_levels,)
        Temporal variance per level (counts²).
    variance_sigma_counts2 : numpy.ndarray, shape (n_levels,)
        1-sigma uncertainty of each variance (counts²).
    n_pixels : numpy.ndarray of int, shape (n_levels,)
        Pixels used per level (saturated ones left out).
    illumination : tuple of str, length n_levels
        Light-source label of each level.
    slope_counts, slope_sigma_counts : float
        Fitted ``d Var / d mean`` (counts per count of signal, i.e. counts) and its
        1-sigma uncertainty: ``1 / K`` with the gain off, ``F² G / K`` with it on.
    intercept_counts2, intercept_sigma_counts2 : float
        Fitted variance at zero signal (counts²): the read noise squared.
    reduced_chi2 : float
        Goodness of the straight line (≈ 1 when the variances scatter as estimated).
    """

    em_gain_on: bool
    exposure_s: np.ndarray
    mean_counts: np.ndarray
    variance_counts2: np.ndarray
    variance_sigma_counts2: np.ndarray
    n_pixels: np.ndarray
    illumination: tuple[str, ...]
    slope_counts: float
    slope_sigma_counts: float
    intercept_counts2: float
    intercept_sigma_counts2: float
    reduced_chi2: float


def fit_ptc(mean_counts, variance_counts2, variance_sigma_counts2
            ) -> tuple[float, float, float, float, float]:
    """Weighted straight-line fit ``Var = intercept + slope · mean`` of a PTC.

    Parameters
    ----------
    mean_counts, variance_counts2, variance_sigma_counts2 : array_like, shape (n,), n ≥ 2
        Mean signal (counts), variance (counts²) and its 1-sigma uncertainty (counts²)
        per illumination level; at least two distinct means.

    Returns
    -------
    slope_counts, slope_sigma_counts, intercept_counts2, intercept_sigma_counts2, reduced_chi2 : float
        Fitted slope (counts) and intercept (counts²) with 1-sigma uncertainties; the
        uncertainties are scaled up by ``sqrt(reduced_chi2)`` when the points scatter
        more than their error bars say (never scaled down).
    """
    x = np.asarray(mean_counts, dtype=np.float64)
    y = np.asarray(variance_counts2, dtype=np.float64)
    s = np.asarray(variance_sigma_counts2, dtype=np.float64)
    if not (x.shape == y.shape == s.shape) or x.ndim != 1:
        raise InputError("fit_ptc: mean, variance and sigma must be 1-D arrays of one length.")
    if len(np.unique(x)) < 2:
        raise InputError("a photon-transfer curve needs at least two different illumination levels.")
    if np.any(~np.isfinite(s)) or np.any(s <= 0):
        raise InputError("fit_ptc: the variance uncertainties must be positive.")
    w = 1.0 / s**2
    A = np.stack([np.ones_like(x), x], axis=1)
    cov = np.linalg.inv(A.T @ (w[:, None] * A))
    intercept, slope = cov @ (A.T @ (w * y))
    dof = len(x) - 2
    chi2 = float((w * (y - intercept - slope * x) ** 2).sum() / dof) if dof > 0 else 1.0
    scale = math.sqrt(max(chi2, 1.0))
    return (float(slope), float(math.sqrt(cov[1, 1]) * scale), float(intercept),
            float(math.sqrt(cov[0, 0]) * scale), chi2)


MAX_SATURATED_FRACTION = 0.01
"""A PTC pair with more of its pixels saturated (or clipped at 0) is left out of the fit:
dropping only the saturated pixels would keep their neighbours in value that noise
happened to push down, and bias the variance low."""


REGISTRATION_RATIO = 0.5
REGISTRATION_SIGMAS = 8.0
"""A PTC frame whose fixed pattern agrees with the other pairs' less than half as well as its
partner's, by more than 8 standard errors of the agreement, is not registered with its partner."""


def _fine_pattern(signal: np.ndarray) -> np.ndarray:
    """The pixel-scale part of a frame's signal: the frame less its 3 × 3 running mean, so that
    the smooth light falls out and the pixel response (the part a misregistered pair difference
    keeps) stays."""
    from scipy.ndimage import uniform_filter

    return signal - uniform_filter(signal, 3, mode="nearest")


def _robust_corr(x: np.ndarray, y: np.ndarray) -> float:
    """Pearson correlation of ``x`` and ``y`` after each is clipped at 5 robust standard deviations
    (a cosmic ray or a hot pixel moves it little)."""
    def z(v):
        v = v - np.median(v)
        s = 1.4826 * np.median(np.abs(v))
        return np.clip(v / s, -5, 5) if s > 0 else np.zeros_like(v)
    zx, zy = z(x), z(y)
    zx -= zx.mean()
    zy -= zy.mean()
    den = math.sqrt(float((zx * zx).sum() * (zy * zy).sum()))
    return float((zx * zy).sum() / den) if den > 0 else 0.0


def _usable(a: np.ndarray, b: np.ndarray, max_counts: float | None) -> np.ndarray:
    """Pixels of a pair neither saturated, clipped at 0 nor hit by a cosmic ray (a difference
    beyond 6 robust standard deviations)."""
    ok = np.isfinite(a) & np.isfinite(b) & (a > 0) & (b > 0)
    if max_counts is not None:
        ok &= (a < max_counts) & (b < max_counts)
    if not ok.any():
        return ok
    d = np.where(ok, a - b, 0.0)
    dev = np.abs(d - np.median(d[ok]))
    return ok & (dev <= 6.0 * 1.4826 * max(float(np.median(dev[ok])), 1e-12))


def _filled(values: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """``values`` with each pixel left out replaced by its 3 × 3 neighbours' median, so that a
    running mean or a block mean does not spread it."""
    from scipy.ndimage import median_filter

    if ok.all():
        return values
    base = np.where(ok, values, np.median(values[ok]) if ok.any() else 0.0)
    return np.where(ok, values, median_filter(base, 3))


STRUCTURE_BLOCK_PX = 8
STRUCTURE_SHARE = 0.05
"""A pair whose difference holds structure larger than a pixel (over 8 × 8 blocks) worth more
than 5 % of its variance, beyond what the bias pairs' difference holds and by more than 6
standard errors, is refused: its variance would be that much too high."""


def _block_structure(d: np.ndarray, block: int) -> tuple[float, float, float]:
    """(variance of the difference's structure larger than a pixel, its standard error if the
    difference were white, the difference's pixel variance), in counts². White noise of pixel
    variance σ² gives block means of variance σ²/B²; the excess over that is structure."""
    ny, nx = (d.shape[0] // block) * block, (d.shape[1] // block) * block
    d = d[:ny, :nx] - d[:ny, :nx].mean()
    means = d.reshape(ny // block, block, nx // block, block).mean(axis=(1, 3)).ravel()
    b2, m = block * block, means.size
    var_d, var_m = float(d.var()), float(means.var(ddof=1))
    return (b2 * var_m - var_d) / (b2 - 1), var_d * math.sqrt(2.0 / (m - 1)) / (b2 - 1), var_d


def check_pairs(levels: list[tuple[int, np.ndarray]], bias_stack: np.ndarray, bias_counts,
                max_counts: float | None) -> None:
    """Refuse a photon-transfer pair whose difference keeps what it should cancel.

    ``var(a − b) / 2`` cancels the fixed pattern (pixel response × light) only pixel for pixel,
    and only if the light stayed put. Two checks, each on what the other cannot see:

    - *Pixel pattern.* Each frame's pixel-scale pattern (less its 3 × 3 running mean) is
      correlated with the pattern a frame of its signal should hold: the bias map's, plus its
      signal times the pixel response seen by every other pair of the series (the pair itself left
      out: a frame agrees with itself). Both frames of a pair see the same light, so they agree
      alike. Where the pattern stands 8 standard errors above the noise, a frame that agrees less
      than half as well as its partner is named: transposed, flipped or shifted (one frame of the
      sample set transposed read electrons per count 8.21 for 8.55, without a sign).
    - *Structure larger than a pixel.* The difference of a good pair is white: its 8 × 8 block
      means vary as its pixels over 64. The excess (a smooth light moved with the frame, or a
      light whose shape changed between the two exposures) beyond the bias pairs' own (row noise
      of the readout) is refused above 5 % of the pair's variance. The second frame is scaled to
      the first's mean signal first: a lamp a few per cent brighter for one frame is left alone.

    ``levels``: (index in the PTC list, frames [n, ny, nx]) of one EM-gain setting."""
    bias_stack = np.asarray(bias_stack, dtype=np.float64)
    pairs = [(j, k, a, b) for j, frames in levels
             for k, (a, b) in zip(range(0, len(frames) - 1, 2), _pairs(np.asarray(frames, dtype=np.float64)))]
    block = STRUCTURE_BLOCK_PX if min(bias_stack.shape[1:]) >= 4 * STRUCTURE_BLOCK_PX else 4
    bias_structure = [_block_structure(_filled(a - b, ok), block)[0] for a, b in _pairs(bias_stack)
                      for ok in [_usable(a, b, max_counts)]] if min(bias_stack.shape[1:]) >= 4 * block else []
    floor = max(float(np.median(bias_structure)), 0.0) if bias_structure else 0.0
    fine, weight = [], []
    for j, k, a, b in pairs:
        ok = _usable(a, b, max_counts)
        if bias_structure and ok.mean() > 0.5:
            # b scaled to a's mean signal: a lamp a little brighter for one frame (the light's shape
            # unchanged) is not what this check is about; a frame moved, or light that changed shape, is
            sa, sb = float(np.mean((a - bias_counts)[ok])), float(np.mean((b - bias_counts)[ok]))
            k_ab = sa / sb if sa > 0 and sb > 0 else 1.0
            v_s, v_se, var_d = _block_structure(_filled((a - bias_counts) - k_ab * (b - bias_counts), ok), block)
            excess = v_s - floor
            if excess > STRUCTURE_SHARE * var_d and excess > 6.0 * v_se:
                raise InputError(f"ptc[{j}].files[{k}] and [{k + 1}]: their difference holds structure larger than a pixel, "
                                 f"{excess / var_d:.0%} of its variance (the bias pairs' difference: "
                                 f"{floor / max(var_d, 1e-300):.1%}). A frame moved, flipped or transposed, or the "
                                 "light changed between the two exposures? The pair's variance would read electrons "
                                 "per count low.")
        both = [(np.where(ok, _fine_pattern(_filled(f, ok)), 0.0)) for f in (a, b)]
        fine.append((both, ok))
        weight.append(max(float(np.median(0.5 * (a + b) - bias_counts)), 0.0))
    if len(pairs) < 2:
        return
    # what a frame of signal S should hold at the pixel scale: the bias map's pattern plus S times the
    # pixel response (the other pairs' pattern above bias over their signal)
    bias_fine = _fine_pattern(np.broadcast_to(np.asarray(bias_counts, dtype=np.float64), bias_stack.shape[1:]))
    total = sum(g - np.where(ok, bias_fine, 0.0) for both, ok in fine for g in both)
    total_level = 2.0 * sum(weight)
    for (j, k, _, _), (both, ok), w in zip(pairs, fine, weight):
        rest_level = total_level - 2.0 * w
        n = int(ok.sum())
        if rest_level <= 0 or n < 64:
            continue
        reference = bias_fine + w * (total - both[0] - both[1] + 2.0 * np.where(ok, bias_fine, 0.0)) / rest_level
        c = [_robust_corr(g[ok], reference[ok]) for g in both]
        hi, lo, se = max(c), min(c), 1.0 / math.sqrt(n)
        if hi > REGISTRATION_SIGMAS * se and hi - lo > REGISTRATION_SIGMAS * se and lo < REGISTRATION_RATIO * hi:
            bad = k + int(c[1] < c[0])
            raise InputError(f"ptc[{j}].files[{bad}] is not registered with files[{k + (bad == k)}], its pair: its "
                             f"pixel pattern agrees with the other PTC frames' at {lo:.3f}, its partner's at {hi:.3f}. "
                             "Transposed, flipped, shifted or from another camera? A pair's difference cancels the "
                             "fixed pattern only pixel for pixel; a misregistered frame keeps it and reads electrons "
                             "per count low.")


def _ptc_series(pairs: list, exposures_s: list[float], labels: list[str], bias_counts, em_gain_on: bool,
                max_counts: float | None, warnings: list[str]) -> PTCSeries:
    name = "gain-on" if em_gain_on else "gain-off"
    stats, keep = [], []
    for k, (a, b) in enumerate(pairs):
        bad = (a <= 0) | (b <= 0)
        if max_counts is not None:
            bad |= (a >= max_counts) | (b >= max_counts)
        lost = float(bad.mean())
        st = pair_statistics(a, b, bias_counts, max_counts=max_counts) if lost <= MAX_SATURATED_FRACTION else None
        if lost > MAX_SATURATED_FRACTION:
            warnings.append(f"the {name} PTC level at {exposures_s[k]:g} s has {lost:.0%} of its pixels saturated "
                            "or clipped at 0: it is left out of the fit.")
            continue
        if lost > 0:
            warnings.append(f"the {name} PTC level at {exposures_s[k]:g} s: {lost:.2%} of its pixels saturated or "
                            "clipped at 0 were left out.")
        stats.append(st)
        keep.append(k)
    settings = {(exposures_s[k], labels[k]) for k in keep}  # distinct illumination x exposure
    if len(settings) < (1 if em_gain_on else 2):
        raise InputError(f"too few {name} photon-transfer levels: the gain-off curve needs two different exposures "
                         "or illuminations free of saturation, the gain-on one at least one.")
    mean = np.array([st[0] for st in stats])
    var = np.array([st[1] for st in stats])
    var_sigma = np.array([st[2] for st in stats])
    n_pixels = np.array([st[3] for st in stats])
    if len(settings) >= 2:
        slope, slope_sigma, icpt, icpt_sigma, chi2 = fit_ptc(mean, var, var_sigma)
    else:  # one gain-on level: its signal still gives the gain ratio, but no slope
        slope = slope_sigma = icpt = icpt_sigma = chi2 = math.nan
    return PTCSeries(em_gain_on, np.asarray(exposures_s, dtype=np.float64)[keep], mean, var, var_sigma, n_pixels,
                     tuple(labels[k] for k in keep), slope, slope_sigma, icpt, icpt_sigma, chi2)


def em_gain_from_ptc(slope_on_counts: float, slope_on_sigma_counts: float, electrons_per_count: float,
                     electrons_per_count_sigma: float, *,
                     excess_noise_factor_squared: float | None = None) -> tuple[float, float]:
    """EM gain from the slope of the gain-on PTC: ``G · F² = slope · K``.

    Parameters
    ----------
    slope_on_counts, slope_on_sigma_counts : float
        Slope of variance against mean with the EM gain on (counts) and its 1-sigma.
    electrons_per_count, electrons_per_count_sigma : float
        ``K`` (electrons per count) and its 1-sigma, from the gain-off PTC.
    excess_noise_factor_squared : float or None, optional
        ``F²`` of the register; ``None`` (the default): the ideal register's ``2 − 1/G``
        (:func:`fluxcli.imaging.noise.excess_noise_factor2`), solved together with ``G``.

    Returns
    -------
    em_gain, em_gain_sigma : float
        ``G`` (dimensionless) and its 1-sigma uncertainty.
    """
    def f2(gain: float) -> float:
        return excess_noise_factor2(gain) if excess_noise_factor_squared is None else float(excess_noise_factor_squared)

    s = slope_on_counts * electrons_per_count  # = G · F²(G), which grows with G from 1 · F²(1)
    rel = math.hypot(slope_on_sigma_counts / slope_on_counts, electrons_per_count_sigma / electrons_per_count)
    if excess_noise_factor_squared is not None or not s > f2(1.0):  # a stated F², or no multiplication seen
        g = s / f2(1.0)
        return float(g), float(abs(g) * rel)
    g = brentq(lambda gain: gain * f2(gain) - s, 1.0, max(s, 1.0), xtol=1e-12 * s)
    h = 1e-6 * g
    slope_of_s = ((g + h) * f2(g + h) - (g - h) * f2(g - h)) / (2 * h)  # d(G F²)/dG
    return float(g), float(abs(s) * rel / slope_of_s)


def em_gain_from_ratio(rate_on_counts_per_s, rate_on_sigma, rate_off_counts_per_s, rate_off_sigma
                       ) -> tuple[float, float]:
    """EM gain from signals at the same illumination: ``G = S_on / S_off``.

    Signals are compared per second of exposure, so gain-on frames may (and usually
    must) be exposed for less time than gain-off frames of the same source.

    Parameters
    ----------
    rate_on_counts_per_s, rate_on_sigma : float
        Mean signal above bias per second with the EM gain on (counts/s) and its 1-sigma.
    rate_off_counts_per_s, rate_off_sigma : float
        The same with the EM gain off (counts/s).

    Returns
    -------
    em_gain, em_gain_sigma : float
        ``G`` (dimensionless) and its 1-sigma uncertainty.
    """
    if rate_off_counts_per_s <= 0 or rate_on_counts_per_s <= 0:
        raise InputError("the EM gain ratio needs a positive signal above bias with the gain on and off.")
    g = rate_on_counts_per_s / rate_off_counts_per_s
    rel = math.hypot(rate_on_sigma / rate_on_counts_per_s, rate_off_sigma / rate_off_counts_per_s)
    return float(g), float(g * rel)


def _rate(series: PTCSeries, pick: np.ndarray) -> tuple[float, float]:
    """Mean signal per second of exposure over the chosen levels (counts/s) and its 1-sigma.

    Each level's mean has the temporal noise ``sqrt(Var / (2 n_pixels))``; the levels are
    combined by weighted least squares through the origin and the uncertainty is scaled
    up by ``sqrt(reduced chi²)`` when they scatter more (unstable light, non-linearity)."""
    t = series.exposure_s[pick]
    rates = series.mean_counts[pick] / t
    sigma = np.sqrt(np.maximum(series.variance_counts2[pick], 1e-12) / (2.0 * series.n_pixels[pick])) / t
    w = 1.0 / sigma**2
    rate = float((w * rates).sum() / w.sum())
    chi2 = float((w * (rates - rate) ** 2).sum() / (len(t) - 1)) if len(t) > 1 else 1.0
    return rate, float(math.sqrt(max(chi2, 1.0) / w.sum()))


# ------------------------------------------------------------------ dark current, flat
def dark_current(frame_sets, exposures_s, bias_counts, electrons_per_count: float, em_gains
                 ) -> tuple[float, float, float | None, float | None, np.ndarray]:
    """Dark current (and clock-induced charge) from dark frames at known exposures.

    Per exposure the mean dark signal in electrons per pixel is
    ``e = (counts − bias) · K / G``. With two or more different exposures a straight
    line ``e = dark · t + cic`` is fitted (per pixel for the map, and to the means);
    with one exposure ``dark = e / t`` and the clock-induced charge is counted as dark.

    Parameters
    ----------
    frame_sets : sequence of array_like, each (n_frames, ny, nx)
        Dark frames (counts), one stack per exposure.
    exposures_s : sequence of float
        Exposure of each stack (s), > 0.
    bias_counts : float or array_like (ny, nx)
        Bias level or map (counts).
    electrons_per_count : float
        ``K`` (electrons per count).
    em_gains : sequence of float
        EM gain each stack was taken with (1 for gain off).

    Returns
    -------
    dark_current_e_per_s, dark_current_sigma_e_per_s : float
        Mean dark current per pixel (electrons/s) and its 1-sigma.
    cic_e_per_pixel, cic_sigma_e_per_pixel : float or None
        Charge per pixel per frame at zero exposure (electrons), when two or more
        exposures were given.
    dark_e_per_s_map : numpy.ndarray, shape (ny, nx)
        Dark current per pixel (electrons/s).
    """
    if len(frame_sets) == 0 or not (len(frame_sets) == len(exposures_s) == len(em_gains)):
        raise InputError("dark_current: give one exposure and one EM gain per stack of dark frames.")
    stacks = [_stack(f, "dark frames") for f in frame_sets]
    shape = stacks[0].shape[1:]
    if any(s.shape[1:] != shape for s in stacks):
        raise InputError("dark_current: all dark frames must have one shape.")
    bias = _bias_for(bias_counts, shape, "dark_current")
    t = np.asarray(exposures_s, dtype=np.float64)
    if np.any(t <= 0):
        raise InputError("dark_current: exposures must be positive.")
    e_maps = np.array([(s.mean(axis=0) - bias) * electrons_per_count / g for s, g in zip(stacks, em_gains)])
    e_means = e_maps.mean(axis=(1, 2))
    # sigma of each mean: the temporal noise per pixel over all pixels and frames (with one
    # frame, the pixel-to-pixel scatter, which also holds the fixed pattern: conservative)
    e_sig = np.array([
        (math.sqrt(s.var(axis=0, ddof=1).mean() / s.size) if len(s) > 1 else s[0].std(ddof=1) / math.sqrt(s[0].size))
        * electrons_per_count / g for s, g in zip(stacks, em_gains)])
    if not np.all(np.isfinite(e_sig) & (e_sig > 0)):
        raise InputError("dark_current: a stack of dark frames shows no temporal noise (identical frames?) or "
                         "values beyond any camera's counts; each stack must be separate raw exposures.")
    if len(np.unique(t)) >= 2:
        w = 1.0 / e_sig**2
        A = np.stack([t, np.ones_like(t)], axis=1)
        try:
            cov = np.linalg.inv(A.T @ (w[:, None] * A))
        except np.linalg.LinAlgError:
            cov = np.full((2, 2), np.nan)
        if not (np.all(np.isfinite(cov)) and cov[0, 0] > 0 and cov[1, 1] > 0):
            raise InputError("dark_current: the dark frames' means cannot be fitted against their exposures (their "
                             "noise estimates span too many orders of magnitude); check the dark frames.")
        dark, cic = cov @ (A.T @ (w * e_means))
        dof = len(t) - 2
        chi2 = float((w * (e_means - dark * t - cic) ** 2).sum() / dof) if dof > 0 else 1.0
        scale = math.sqrt(max(chi2, 1.0))
        tc = t - t.mean()
        dark_map = np.tensordot(tc, e_maps - e_maps.mean(axis=0), axes=1) / (tc**2).sum()
        return (float(dark), float(math.sqrt(cov[0, 0]) * scale), float(cic), float(math.sqrt(cov[1, 1]) * scale),
                dark_map)
    rate = e_means / t
    rate_sig = e_sig / t
    w = 1.0 / rate_sig**2
    dark_map = (e_maps / t[:, None, None]).mean(axis=0)
    return float((w * rate).sum() / w.sum()), float(1.0 / math.sqrt(w.sum())), None, None, dark_map


def flat_field(frames, bias_counts) -> tuple[np.ndarray, float]:
    """Flat-field map (mean 1) from frames of a uniformly lit sensor.

    Parameters
    ----------
    frames : array_like, shape (n_frames, ny, nx)
        Flat frames (counts), EM gain off, well above the read noise and below saturation.
    bias_counts : float or array_like (ny, nx)
        Bias level or map (counts).

    Returns
    -------
    flat_map : numpy.ndarray of float64, shape (ny, nx)
        Relative response per pixel, mean 1 (dimensionless).
    mean_signal_counts : float
        Mean signal above bias of the flat frames (counts).

    Notes
    -----
    The flat describes the *sensor* (pixel response non-uniformity): take it with the
    sensor evenly lit (an integrating sphere, or a diffuser without the lens).
    Vignetting of the lens and apertures is already in fluxmap's transfer matrix; a flat
    taken through the lens would count it twice.
    """
    stack = _stack(frames, "flat frames")
    bias = _bias_for(bias_counts, stack.shape[1:], "flat_field")
    signal = stack.mean(axis=0) - bias
    level = float(signal.mean())
    if level <= 0:
        raise InputError("flat frames: the mean signal is not above the bias; were they lit?")
    return signal / level, level


# ------------------------------------------------------------------ the whole chain
@dataclass
class RadiometricResult:
    """What a radiometric calibration measured (``None``: not measured).

    Attributes
    ----------
    electrons_per_count, electrons_per_count_sigma : float
        ADC conversion gain ``K`` (electrons per count), from the gain-off PTC.
    em_gain, em_gain_sigma : float or None
        EM gain ``G``: from the gain-on/gain-off signal ratio when both were taken at one
        illumination, else from the gain-on PTC slope.
    em_gain_from_ratio, em_gain_from_ratio_sigma : float or None
        ``G = S_on / S_off`` per second of exposure.
    em_gain_from_ptc, em_gain_from_ptc_sigma : float or None
        ``G`` from ``G · F² = slope_on · K`` (:func:`em_gain_from_ptc`).
    read_noise_counts, read_noise_counts_sigma : float
        RMS read noise from bias pairs (counts).
    read_noise_e, read_noise_e_sigma : float
        The same in electrons at the output node (``· K``).
    bias_counts, bias_counts_sigma : float
        Mean bias level (counts).
    dark_current_e_per_s, dark_current_e_per_s_sigma : float or None
        Mean dark current per pixel (electrons/s).
    cic_e_per_pixel, cic_e_per_pixel_sigma : float or None
        Clock-induced charge per pixel per frame (electrons), from darks at two or more
        exposures.
    bias_counts_map : numpy.ndarray (ny, nx)
        Bias per pixel (counts).
    dark_e_per_s_map, flat_map : numpy.ndarray (ny, nx) or None
        Dark current per pixel (electrons/s); relative response per pixel (mean 1).
    ptc : dict of str to PTCSeries
        ``"em_gain_off"`` and, when measured, ``"em_gain_on"``.
    excess_noise_factor_squared : float
        ``F²`` of the register for the gain-on PTC: the one the config states, else the
        ideal register's ``2 − 1/G`` at the measured gain (NaN when no gain was measured).
    warnings : list of str
        Things the user should look at (poor fits, disagreeing gains, saturation).
    """

    electrons_per_count: float
    electrons_per_count_sigma: float
    read_noise_counts: float
    read_noise_counts_sigma: float
    read_noise_e: float
    read_noise_e_sigma: float
    bias_counts: float
    bias_counts_sigma: float
    bias_counts_map: np.ndarray
    ptc: dict[str, PTCSeries]
    em_gain: float | None = None
    em_gain_sigma: float | None = None
    em_gain_from_ratio: float | None = None
    em_gain_from_ratio_sigma: float | None = None
    em_gain_from_ptc: float | None = None
    em_gain_from_ptc_sigma: float | None = None
    dark_current_e_per_s: float | None = None
    dark_current_e_per_s_sigma: float | None = None
    cic_e_per_pixel: float | None = None
    cic_e_per_pixel_sigma: float | None = None
    dark_e_per_s_map: np.ndarray | None = None
    flat_map: np.ndarray | None = None
    excess_noise_factor_squared: float = math.nan
    warnings: list[str] = field(default_factory=list)

    def sensor_block(self) -> dict:
        """The measured values as a ``system.camera.sensor`` block (keys of ``Sensor``).

        Only measured quantities appear; ``quantum_efficiency`` and ``bit_depth`` are not
        measured here and keep whatever the config says.
        """
        block: dict = {
            "electrons_per_count": float(self.electrons_per_count),
            "read_noise_e": float(max(self.read_noise_e, 0.0)),
            "bias_counts": float(max(self.bias_counts, 0.0)),
        }
        if self.em_gain is not None:
            block["em_gain"] = float(max(self.em_gain, 1.0))
        if self.dark_current_e_per_s is not None:
            block["dark_current_e_per_s"] = float(max(self.dark_current_e_per_s, 0.0))
        if self.cic_e_per_pixel is not None:
            block["cic_e_per_pixel"] = float(max(self.cic_e_per_pixel, 0.0))
        return block


@dataclass(frozen=True)
class PTCLevel:
    """Frames of one photon-transfer level (see :func:`calibrate_radiometric`).

    Attributes
    ----------
    frames : numpy.ndarray, shape (n_frames ≥ 2, ny, nx)
        Frames (counts) at one illumination and exposure; consecutive frames are paired.
    exposure_s : float
        Exposure (s), > 0.
    em_gain_on : bool
        Whether the EM register was on.
    illumination : str
        Label of the light-source setting; signal ratios are only formed between levels
        with the same label (the signal then scales with exposure).
    """

    frames: np.ndarray
    exposure_s: float
    em_gain_on: bool
    illumination: str = ""


def calibrate_radiometric(
    *,
    bias,
    ptc: list[PTCLevel],
    darks: list[tuple[np.ndarray, float, bool]] | None = None,
    flats=None,
    max_counts: float | None = 65535.0,
    excess_noise_factor_squared: float | None = None,
    gain_tolerance: float = 0.1,
) -> RadiometricResult:
    """Run the radiometric calibration on frames.

    Parameters
    ----------
    bias : array_like, shape (n_frames ≥ 2, ny, nx)
        Bias frames (counts), EM gain off, no light, shortest exposure.
    ptc : list of PTCLevel
        Photon-transfer levels: at least two different signals with the EM gain off
        (for ``K``); levels with the gain on give ``G``.
    darks : list of (frames, exposure_s, em_gain_on), optional
        Dark frames (counts, ``[n_frames, ny, nx]``) at each exposure (s); with the gain
        on they are converted with the measured ``G``.
    flats : array_like, shape (n_frames, ny, nx), optional
        Flat frames (counts), EM gain off.
    max_counts : float or None, optional
        Saturation level (counts): such pixels are left out of the PTC.
    excess_noise_factor_squared : float or None, optional
        ``F²`` for the gain-on PTC; ``None``: the ideal register's ``2 − 1/G``.
    gain_tolerance : float, optional
        Relative difference between the ratio and PTC EM gains above which a warning is
        given.

    Returns
    -------
    RadiometricResult
    """
    warnings: list[str] = []
    bias_stack = _stack(bias, "bias frames", min_frames=2)
    shape = bias_stack.shape[1:]
    bias_level, bias_sigma, bias_map = bias_frames(bias_stack)
    rn_counts, rn_counts_sigma = read_noise_counts(bias_stack)

    series: dict[str, PTCSeries] = {}
    groups: dict[bool, list[PTCLevel]] = {False: [], True: []}
    for level in ptc:
        frames = _stack(level.frames, "PTC frames", min_frames=2)
        if frames.shape[1:] != shape:
            raise InputError(f"PTC frames are {frames.shape[1:]}, the bias frames {shape}.")
        if level.exposure_s <= 0:
            raise InputError("PTC levels need a positive exposure_s.")
        groups[bool(level.em_gain_on)].append(level)
    if not groups[False]:
        raise InputError("the photon-transfer series has no level with the EM gain off; electrons per count "
                         "come from the gain-off curve.")
    for on, levels in groups.items():
        if not levels:
            continue
        check_pairs([(j, lv.frames) for j, lv in enumerate(ptc) if bool(lv.em_gain_on) == on], bias_stack,
                    bias_map, max_counts)
        pairs, exposures, labels = [], [], []
        for level in levels:
            for a, b in _pairs(np.asarray(level.frames, dtype=np.float64)):
                pairs.append((a, b))
                exposures.append(level.exposure_s)
                labels.append(level.illumination)
        name = "em_gain_on" if on else "em_gain_off"
        s = _ptc_series(pairs, exposures, labels, bias_map, on, max_counts, warnings)
        series[name] = s
        if s.reduced_chi2 > 4.0:
            warnings.append(f"the {name.replace('_', ' ')} photon-transfer curve is not a straight line "
                            f"(reduced chi² {s.reduced_chi2:.1f}): saturation, non-linearity or unstable light?")
        if np.any(s.mean_counts <= 0):
            warnings.append(f"a {name.replace('_', ' ')} PTC level has no signal above bias.")

    off = series["em_gain_off"]
    if off.slope_counts <= 0:
        raise InputError("the gain-off photon-transfer curve does not rise with signal; cannot measure "
                         "electrons per count.")
    K = 1.0 / off.slope_counts
    K_sigma = off.slope_sigma_counts / off.slope_counts**2
    if off.intercept_counts2 > 0:
        rn_ptc = math.sqrt(off.intercept_counts2)
        if abs(rn_ptc - rn_counts) > max(0.2 * rn_counts, 3 * off.intercept_sigma_counts2 / (2 * rn_ptc)):
            warnings.append(f"the read noise from the PTC intercept ({rn_ptc:.3g} counts) differs from the one "
                            f"from bias pairs ({rn_counts:.3g} counts).")
    result = RadiometricResult(
        electrons_per_count=K, electrons_per_count_sigma=K_sigma,
        read_noise_counts=rn_counts, read_noise_counts_sigma=rn_counts_sigma,
        read_noise_e=rn_counts * K, read_noise_e_sigma=rn_counts * K * math.hypot(rn_counts_sigma / rn_counts, K_sigma / K),
        bias_counts=bias_level, bias_counts_sigma=bias_sigma, bias_counts_map=bias_map, ptc=series,
        warnings=warnings)

    on = series.get("em_gain_on")
    if on is not None:
        if math.isfinite(on.slope_counts):
            result.em_gain_from_ptc, result.em_gain_from_ptc_sigma = em_gain_from_ptc(
                on.slope_counts, on.slope_sigma_counts, K, K_sigma,
                excess_noise_factor_squared=excess_noise_factor_squared)
            result.excess_noise_factor_squared = (excess_noise_factor2(result.em_gain_from_ptc)
                                                  if excess_noise_factor_squared is None
                                                  else float(excess_noise_factor_squared))
        else:
            warnings.append("one gain-on PTC level: the EM gain has no PTC-slope cross-check (take two or more).")
        ratios = []
        labels_off = np.array(off.illumination)
        labels_on = np.array(on.illumination)
        for label in sorted(set(labels_on) & set(labels_off)):
            ratios.append(em_gain_from_ratio(*_rate(on, labels_on == label), *_rate(off, labels_off == label)))
        if ratios:
            g = np.array([r[0] for r in ratios])
            gs = np.array([r[1] for r in ratios])
            w = 1.0 / gs**2
            result.em_gain_from_ratio = float((w * g).sum() / w.sum())
            result.em_gain_from_ratio_sigma = float(1.0 / math.sqrt(w.sum()))
            result.em_gain, result.em_gain_sigma = result.em_gain_from_ratio, result.em_gain_from_ratio_sigma
            diff = (abs(result.em_gain_from_ptc - result.em_gain_from_ratio) / result.em_gain_from_ratio
                    if result.em_gain_from_ptc is not None else 0.0)
            if diff > gain_tolerance:
                warnings.append(
                    f"EM gain from the signal ratio ({result.em_gain_from_ratio:.4g}) and from the gain-on PTC slope "
                    f"with F² = {result.excess_noise_factor_squared:.4g} ({result.em_gain_from_ptc:.4g}) differ by {diff:.0%}: "
                    "check the illumination was the same, saturation, and F².")
        elif result.em_gain_from_ptc is None:
            raise InputError("the EM gain cannot be measured: the gain-on levels share no illumination label with "
                             "gain-off levels (for the signal ratio) and are too few for a PTC slope.")
        else:
            result.em_gain, result.em_gain_sigma = result.em_gain_from_ptc, result.em_gain_from_ptc_sigma
            warnings.append("no gain-on and gain-off PTC levels share an illumination: the EM gain comes from the "
                            f"gain-on PTC slope alone (assuming F² = {result.excess_noise_factor_squared:.4g}).")

    if darks:
        gains = []
        for _, _, gain_on in darks:
            if gain_on and result.em_gain is None:
                raise InputError("dark frames taken with the EM gain on need gain-on PTC levels to measure the gain.")
            gains.append(result.em_gain if gain_on else 1.0)
        (result.dark_current_e_per_s, result.dark_current_e_per_s_sigma, result.cic_e_per_pixel,
         result.cic_e_per_pixel_sigma, result.dark_e_per_s_map) = dark_current(
            [d[0] for d in darks], [d[1] for d in darks], bias_map, K, gains)
        # the conversion to electrons scales with K / G: their uncertainties carry over
        rel = math.hypot(K_sigma / K, (result.em_gain_sigma / result.em_gain)
                         if any(d[2] for d in darks) and result.em_gain_sigma is not None else 0.0)
        result.dark_current_e_per_s_sigma = math.hypot(result.dark_current_e_per_s_sigma,
                                                       rel * abs(result.dark_current_e_per_s))
        if result.cic_e_per_pixel is not None:
            result.cic_e_per_pixel_sigma = math.hypot(result.cic_e_per_pixel_sigma, rel * abs(result.cic_e_per_pixel))
        if result.cic_e_per_pixel is None:
            warnings.append("dark frames at a single exposure: clock-induced charge is counted as dark current.")
    if flats is not None:
        result.flat_map, level = flat_field(flats, bias_map)
        if level < 100 * rn_counts:
            warnings.append(f"the flat frames have only {level:.3g} counts of signal: the flat map is noisy.")
    return result
