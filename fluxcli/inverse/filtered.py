"""The regularised, non-negative, iteratively reweighted solve shared by ``smooth`` and
``paper`` (and any method whose linear part is a filter of :mod:`.spectral`).

One call does, on the observed columns and the pixels that see them:

1. weights: none for an unweighted method; otherwise ``W = 1/σ²(T b̂)`` from the noise
   model evaluated on the *model* image of the previous pass (the first pass is
   unweighted), ``passes`` times — weights from the noisy data would bias totals low;
2. λ: given, or chosen by a rule on the filter factors of the very scheme that runs
   (``k`` iterated solves; if the paper's tolerance stops it after fewer, λ is chosen
   again for that many);
3. the iterated clipped solve;
4. checks that are reported, never silent: the pick at the edge of the λ range (the range
   is widened first), a χ²/pixel far from 1, and a total that moves by more than 5 %
   when λ is halved or doubled.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fluxcli.inverse import spectral as S

CHI2_RANGE = (0.5, 2.0)
CHI2_FAR = 25.0
FAR_OFF = ("far beyond what model error in the light or the noise model gives: the images and the set-up "
           "disagree in kind. Check system.camera against the images (pixel_pitch_mm: on-chip binning multiplies "
           "it; pixels; pose; lens), reconstruct.images.units, and that the images are this set-up's")
"""Above this χ² per pixel, with more than 10 % of the images' light unexplained (:func:`_unexplained`),
the misfit is geometric or one of units: images binned 2 × 2 by the camera with pixel_pitch_mm left
as it was fitted at χ² 42-736 (the total 1.14× the truth). A wrong emission model (issue 21's
Lambertian on Monte Carlo photons, χ² 2.3), images out of pose order (5-14) or upside down (5) stay
below it; a small model error at very many photons a pixel passes χ² but not the share."""
NNLS_LAMBDA = 1e-12  # relative: "no prior" for guard_lambda's reference fit, yet a non-singular system
TOTAL_JUMP = 0.05


FAR_UNEXPLAINED = 0.10


def _unexplained(a, fitted) -> float:
    """The share of the images' light the fit leaves unexplained, ‖a − T b̂‖ / ‖a‖: scale-free where
    χ² grows with the photons (1 % of model error is χ² ≈ 1000 at 10⁷ photons a pixel)."""
    a, fitted = np.asarray(a, float), np.asarray(fitted, float)
    norm = float(np.sqrt(np.sum(a * a)))
    return float(np.sqrt(np.sum((a - fitted) ** 2)) / norm) if norm > 0 else 0.0


def poses_disagree(per_pose_chi2, joint_chi2: float, totals, labels=None) -> str | None:
    """A warning when each pose alone fits its images to the noise but the poses together do not
    (joint χ² above the range and above twice every pose's): the images disagree about the light.
    Files out of ``subject.poses`` order, one image given for two poses, a dark or bias frame given
    for a pose (it fits alone: no light, nothing to misfit), or a light that changed between poses
    do this; each pose alone then finds *a* surface that explains its image, and the joint total
    (1.83× the truth, two files swapped; 0.47× with a bias frame for one pose; without another word
    before) is not one to trust. None: nothing to say."""
    chi = np.asarray(per_pose_chi2, dtype=float)
    t = np.asarray(totals, dtype=float)
    labels = list(labels) if labels is not None else [str(k) for k in range(len(chi))]
    hi = CHI2_RANGE[1]
    lit = np.isfinite(chi)
    dark = ~lit & (np.abs(t) <= 0.01 * np.nanmax(np.abs(t), initial=0.0))  # no light to fit: fits alone trivially
    if (len(chi) < 2 or not lit.any() or not np.isfinite(joint_chi2) or not np.all(lit | dark)
            or chi[lit].max() > hi or joint_chi2 <= max(hi, 2.0 * chi[lit].max())):
        return None
    unlit = "" if not dark.any() else (f" Pose(s) {', '.join(l for l, d in zip(labels, dark) if d)} read no light "
                                       "while the others do: a dark or bias frame given for a pose?")
    return (f"each pose alone fits its image to the noise (chi^2 per pixel {chi[lit].min():.2g}-{chi[lit].max():.2g}) "
            f"but the poses together do not ({joint_chi2:.3g}): their images disagree about the light.{unlit} Are "
            "reconstruct.images.files in subject.poses order, one image per pose and none given twice? Did the "
            "light change between poses (a decaying or moving source), or does the model (emission, geometry) "
            f"hold for some poses only? The per-pose totals ({np.nanmin(t):.4g}-{np.nanmax(t):.4g} photons) are "
            "each a pose's own reading; the joint total rests on images that do not agree.")


def chi2_per_pixel(a, fitted, var) -> float:
    """``Σ (a − T b̂)² / σ²(T b̂)`` per pixel, over pixels whose model holds ≥ 1 photon
    (below that the noise is far from Gaussian and a variance floor makes χ² meaningless);
    NaN when there are none."""
    use = fitted >= 1.0
    if not use.any():
        return float("nan")
    return float(np.mean((a[use] - fitted[use]) ** 2 / var[use]))


@dataclass
class Filtered:
    """Outcome of :func:`filtered_solve` on the observed elements (all arrays (n_obs,))."""

    power: np.ndarray
    sigma: np.ndarray
    lam: float
    lam_absolute: float
    iterations: int
    converged: bool
    choice: S.Choice | None
    chi2_per_pixel: float
    total_at_half_and_double_lambda: tuple = (np.nan, np.nan)
    weighted: bool = False
    warnings: list = field(default_factory=list)
    sigma_sums: np.ndarray | None = None
    covariance: S.FilterCovariance | None = None  # variance_of(weights over the observed unknowns)


def _provisional_upre(T_obs, a, prior, variance, k, lambdas, gamma, tau) -> S.Choice:
    """λ for the first, unweighted pass of a weighted solve when GCV ran off its grid.

    GCV estimates the noise from the residual, and where the data cannot pin every unknown
    down (more vertices than pixels that see them) it can drive λ towards an interpolant of
    the noise: on a 5880-vertex cylinder it went below the grid (6.8e-11), the provisional
    total came out 270x too large, and the model weights taken from it left the final solve
    at χ²/pixel 7 and 16 % error. The noise model is known, so this pass uses it as a single
    level instead: UPRE with every pixel's variance set to the mean variance of the image
    (a scalar of all pixels together, not a per-pixel weight from noisy data, and
    the same relative λ as the unweighted solve since the weights are uniform)."""
    mean_var = float(np.mean(variance(np.maximum(a, 0.0))))
    spec = S.Spectrum(T_obs, a, np.full(len(a), 1.0 / max(mean_var, 1e-300)), prior, noise_weighted=True)
    return S.choose(spec, "gcv", k=k, lambdas=lambdas, gamma=gamma, tau=tau)


DOF_SHARE_MAX = 0.5  # UPRE's pick may spend at most this share of the pixels on degrees of freedom ...
# ... unless its minimum lies this many times its own noise, √(2m), below its value at the grid's
# smallest λ (the interpolating end): then the curve is not flat and its pick stands
UPRE_CLEAR_MIN = 1.0


def _unless_interpolating(spec: S.Spectrum, choice: S.Choice, k, lambdas, gamma, tau):
    """UPRE's pick, or the discrepancy principle's where UPRE cannot choose.

    UPRE estimates the predictive risk ``‖W^½r‖² + 2Σf − m``; where the filter can nearly
    interpolate the pixels (more unknowns than pixels that see them: issue 25's scene at 0.5
    pixels per element, 420 pixels for 670 unknowns) the estimate is flat from λ → 0 up to
    the useful range (399 at 1e-9, 437 at 1e-4, against its own noise of √(2m) = 29), and its
    minimum lands on an interpolant of the noise and of the model error (19.8 % error, 2.9 %
    at λ = 1e-4). When the pick's degrees of freedom exceed :data:`DOF_SHARE_MAX` of the
    pixels and the curve is that flat — its minimum not :data:`UPRE_CLEAR_MIN` × √(2m) below
    its value at the grid's smallest λ — the known noise level decides instead: ``‖W^½r‖² = τm``
    (Morozov's discrepancy principle, which cannot fit below the noise; there 2.6 %). Where
    the minimum is clear, UPRE's pick stands however many degrees of freedom it spends: the
    demo's cylinder on faces split once (850 vertex unknowns on 962 pixels) has its minimum
    300 below the λ → 0 end (√(2m) = 44) at 560 degrees of freedom, 5 % error; the discrepancy
    principle, which over-smooths wherever the model can fit below the noise, gave 20 %.
    Returns the choice and a note (None when UPRE's pick stands)."""
    m = spec.m
    df = float(spec.curves([choice.lam * spec.scale], k)[2][0])
    if df <= DOF_SHARE_MAX * m:
        return choice, None
    crit = np.asarray(choice.criterion, float)
    if len(crit) and np.isfinite(crit[0]) and crit[0] - np.nanmin(crit) > UPRE_CLEAR_MIN * np.sqrt(2.0 * m):
        return choice, None  # a minimum well above the interpolating end (λ → 0): UPRE can choose here
    disc = S.choose(spec, "discrepancy", k=k, lambdas=lambdas, gamma=gamma, tau=tau, noise_total=float(m))
    if disc.at_edge:
        return choice, None
    return disc, (f"lambda (UPRE) at {choice.lam:.3g} spent {df:.0f} degrees of freedom on {m} pixels (it can "
                  f"interpolate the noise there); chose lambda {disc.lam:.3g} by the discrepancy principle "
                  "(chi^2/pixel 1 under the noise model)")


def guard_lambda(spec: S.Spectrum, choice: S.Choice, b, it: int, conv: bool, k: int, *, tol=None):
    """Check a λ picked on the linear filter against the non-negative estimator that runs,
    and pick again by that estimator's fit when the check fails.

    UPRE takes the noise model's variance as the whole misfit. When the images hold more
    than noise (a finer true surface, a camera a calibration error away: χ²/pixel ≫ 1 even
    for the best non-negative fit), fitting that model error lowers ‖W^½r‖² faster than 2Σf
    grows and the pick runs towards λ → 0 (issue 25: to the edge of a widened range, 2.4e-10).
    The check: the pick is trusted when it is inside the range and the estimator's own
    χ²/pixel is within :data:`CHI2_RANGE`. Otherwise the variance is scaled by ``φ``, what the
    plain non-negative least-squares fit (no prior) leaves per degree of freedom,
    ``φ = max(1, ‖W^½r₀‖² / (m − n_free))`` (the divergence of NNLS is its number of free
    unknowns), and the candidates — the first pick, UPRE with variance ``φσ²``, the L-curve's
    corner, and NNLS itself — are scored on the estimator that actually runs:
    ``‖W^½r(b_λ)‖²/φ + 2 df − m``, df = Σf of the filter at λ (NNLS: n_free). The lowest wins.

    Returns b, λ (relative), iterations, converged, and a warning (None when the first pick
    stands).
    """
    m = spec.m
    w = spec.weights

    def rho(x):
        r = spec.a - spec.T @ x
        return float(np.sum(w * r * r))

    lam0 = choice.lam
    if not choice.at_edge and rho(b) / m <= CHI2_RANGE[1]:
        return b, lam0, it, conv, None
    b_nn = S.iterated_exact(spec, NNLS_LAMBDA * spec.scale, 1, start=b)[0]  # NNLS; λ below any pick
    rho_nn, free_nn = rho(b_nn), int(np.count_nonzero(b_nn > 0))
    phi = max(1.0, rho_nn / max(m - free_nn, 1))
    grid = choice.lambdas
    r_lin, _, dof = spec.curves(grid * spec.scale, k)
    cands = {lam0: None}
    cands[float(grid[int(np.argmin(r_lin / phi + 2 * dof - m))])] = None
    lc = S._pick(spec, "lcurve", k, grid, 1.0, 1.0, None)
    if not lc.at_edge:
        cands[lc.lam] = None
    scores = {}
    for lam_c in cands:  # the first pick's estimate is b: not solved again
        x, it_x, conv_x = (b, it, conv) if lam_c == lam0 else S.iterated_exact(spec, lam_c * spec.scale, k, tol=tol)
        df = float(spec.curves([lam_c * spec.scale], k)[2][0])
        scores[lam_c] = (rho(x) / phi + 2 * df - m, x, it_x, conv_x)
    scores[NNLS_LAMBDA] = (rho_nn / phi + 2 * free_nn - m, b_nn, 1, True)
    best = min(scores, key=lambda x: scores[x][0])
    _, x, it_c, conv_c = scores[best]
    why = (f"at the edge of its range ({lam0:.3g})" if choice.at_edge else
           f"at {lam0:.3g} with chi^2/pixel {rho(b) / m:.3g}")
    if best == lam0:
        return b, lam0, it, conv, None
    what = "the plain non-negative fit (no prior)" if best == NNLS_LAMBDA else f"lambda {best:.3g}"
    return x, best, it_c, conv_c, (
        f"lambda ({choice.rule}) sat {why}; chose {what} by the fit of the non-negative estimator itself "
        f"(UPRE with the noise variance x{phi:.3g}, the misfit the best non-negative fit leaves per degree of "
        f"freedom: the images hold more than the noise model's noise)")


def filtered_solve(T_obs, a, *, prior=None, k: int = 10, tol: float | None = None, lam: float | None = None,
                   rule: str = "gcv", gamma: float = 1.0, tau: float = 1.0, lambdas=None, variance=None,
                   sigma2=None, weighted: bool = True, passes: int = 2, free_level: bool = False, sums=None,
                   exact: bool = False) -> Filtered:
    """Solve ``min ‖W^½(a − Tb)‖² + λ̃ bᵀRb, b ≥ 0`` by ``k`` iterated clipped solves.

    Parameters
    ----------
    T_obs : sparse (m, n_obs)
        Observed columns, only rows (pixels) that see one of them; dimensionless.
    a : (m,) photons.
    prior : (n_obs, n_obs) SPD matrix ``R`` or None (identity).
    k : int, solves of the iterated scheme.
    tol : float or None, the paper's stopping rule (relative fit improvement).
    lam : relative λ (``λ̃ = lam × max diag TᵀWT``), or None to choose it with ``rule``.
    rule, gamma, tau, lambdas : see :func:`fluxcli.inverse.spectral.choose`.
    variance : callable (m,) photons → (m,) photons², the noise model, or None.
    sigma2 : (m,) photons², a fixed noise variance (when there is no ``variance``).
    weighted : bool, weight the fit by ``1/σ²`` (needs ``variance`` or ``sigma2``).
    passes : int, reweighting passes when ``variance`` is given (the first is unweighted).
    sums : sparse (n_groups, n_obs), optional: also the σ of these sums of the estimate.
    free_level : bool, leave the overall level to the data (one unpenalised scale factor
        fitted last), so the prior cannot shrink the total.
    exact : bool, solve every step of the iterated scheme exactly under ``b ≥ 0``
        (:func:`~fluxcli.inverse.spectral.iterated_exact`; ``smooth``) instead of clipping
        the unconstrained step (:func:`~fluxcli.inverse.spectral.iterated_clipped`, the
        paper's); an automatic λ is then also checked on the estimator that runs
        (:func:`guard_lambda`).

    Returns
    -------
    Filtered
    """
    m = T_obs.shape[0]
    if weighted and variance is None and sigma2 is None:
        weighted = False
    weights = 1.0 / sigma2 if (weighted and variance is None) else None
    n_pass = max(int(passes), 1) if (weighted and variance is not None) else 1
    if rule == "discrepancy" and variance is not None and n_pass == 1:
        n_pass = 2  # the unweighted discrepancy target needs σ² of a model image first
    var_model = sigma2
    run = S.iterated_exact if exact else S.iterated_clipped
    choice = None
    warn: list[str] = []
    for p in range(n_pass):
        spec = S.Spectrum(T_obs, a, weights, prior, noise_weighted=weights is not None)
        lam_p = lam
        if lam is None:
            eff_rule = rule
            if rule == "discrepancy":
                if weights is not None:
                    noise_total = float(m)
                elif var_model is not None:
                    noise_total = float(np.sum(var_model))
                else:
                    eff_rule, noise_total = "gcv", None
            else:
                noise_total = None
            choice = S.choose(spec, eff_rule, k=k, lambdas=lambdas, gamma=gamma, tau=tau, noise_total=noise_total)
            if (weights is None and variance is not None and weighted and eff_rule == "gcv"
                    and (choice.widened or choice.at_edge)):
                choice = _provisional_upre(T_obs, a, prior, variance, k, lambdas, gamma, tau)
            if spec.noise_weighted and eff_rule == "gcv":
                choice, note = _unless_interpolating(spec, choice, k, lambdas, gamma, tau)
                if note and p == n_pass - 1:
                    warn.append(note)
            lam_p = choice.lam
        b, it, conv = run(spec, lam_p * spec.scale, k, tol=tol)
        if lam is None and tol is not None and it < k:
            choice = S.choose(spec, choice.rule, k=it, lambdas=lambdas, gamma=gamma, tau=tau,
                              noise_total=noise_total)
            lam_p = choice.lam
            b, it, conv = run(spec, lam_p * spec.scale, k, tol=tol)
        if lam is None and exact and spec.noise_weighted and p == n_pass - 1:
            b, lam_p, it, conv, note = guard_lambda(spec, choice, b, it, conv, k, tol=tol)
            if note:
                warn.append(note)
        if variance is not None:
            var_model = variance(T_obs @ b)
            if p < n_pass - 1 and weighted:
                weights = 1.0 / var_model
    if choice is not None:
        warn += choice.warnings
    lam_abs = lam_p * spec.scale
    b, fitted, var_model, level, chi2 = level_and_fit(a, b, T_obs @ b, weights=weights, var_model=var_model,
                                                      variance=variance, free_level=free_level, warnings=warn)
    sigma = np.full(len(b), np.nan)
    sigma_sums = None if sums is None else np.full(sums.shape[0], np.nan)
    if weights is not None or var_model is not None:
        s2 = None if weights is not None else var_model
        sigma = spec.sigma(lam_abs, it, sigma2=s2) * level
        if sums is not None:
            sigma_sums = spec.sigma(lam_abs, it, sigma2=s2, sums=sums) * level
        covariance = S.FilterCovariance(spec, lam_abs, it, s2, level)
    else:
        covariance = None
    totals = (np.nan, np.nan)
    if lam is None and b.sum() > 0:
        totals = halved_and_doubled(lambda lam_x: run(spec, lam_x, k, tol=tol)[0], T_obs, a, b, lam_abs,
                                    var_model=var_model, free_level=free_level, warnings=warn)
    return Filtered(power=b, sigma=sigma, lam=float(lam_p), lam_absolute=float(lam_abs), iterations=int(it),
                    converged=bool(conv), choice=choice, chi2_per_pixel=chi2,
                    total_at_half_and_double_lambda=totals, weighted=weights is not None, warnings=warn,
                    sigma_sums=sigma_sums, covariance=covariance)


def level_and_fit(a, b, fitted, *, weights, var_model, variance, free_level: bool, warnings: list):
    """The overall level left to the data, then χ² per pixel (a warning appended when out of range).

    Any quadratic penalty shrinks the overall level (b → cb lowers bᵀRb by c²), so the level is
    left to the data: the c minimising ‖W^½(a − c T b)‖² (with Poisson model weights, Σa / ΣTb:
    MLEM's count conservation). The prior shapes; the data set the total.

    Returns (b, fitted, var_model, level, chi2_per_pixel) with b and fitted scaled by the level.
    """
    level = 1.0
    if free_level and fitted.any():
        w = np.ones(len(a)) if (weights is None and var_model is None) else (
            1.0 / var_model if var_model is not None else weights)
        level = float((fitted * w) @ a / ((fitted * w) @ fitted))
        if level > 0:
            b, fitted = b * level, fitted * level
            if var_model is not None and variance is not None:
                var_model = variance(fitted)
    chi2 = np.nan
    if var_model is not None:
        chi2 = chi2_per_pixel(a, fitted, var_model)
        lo, hi = CHI2_RANGE
        if np.isfinite(chi2) and not lo <= chi2 <= hi:
            warnings.append(f"chi^2 per pixel is {chi2:.3g} (expected about 1 under the noise model): "
                            + ("the model does not explain the data to the noise (model error, a wrong noise model, "
                               "or too much regularisation)" if hi < chi2 <= CHI2_FAR else
                               FAR_OFF if chi2 > CHI2_FAR and _unexplained(a, fitted) > FAR_UNEXPLAINED else
                               "the model does not explain the data to the noise (model error, a wrong noise model, "
                               "or too much regularisation)" if chi2 > CHI2_FAR else
                               "the fit follows the noise (too little regularisation, or the noise model overstates it)"))
    return b, fitted, var_model, level, chi2


def halved_and_doubled(solve, T_obs, a, b, lam_abs: float, *, var_model, free_level: bool, warnings: list) -> tuple:
    """The totals at λ/2 and 2λ relative to ``b``'s (``solve(lam_abs) -> b``), with the level left
    to the data as in the solve; a warning appended when either moves by more than TOTAL_JUMP."""

    def total_at(lam_x):
        bx = solve(lam_x)
        if not free_level:
            return float(bx.sum())
        fx = T_obs @ bx
        w = 1.0 / var_model if var_model is not None else np.ones(len(a))
        return float(bx.sum() * ((fx * w) @ a) / max((fx * w) @ fx, 1e-300))

    totals = tuple(total_at(f * lam_abs) for f in (0.5, 2.0))
    jump = max(abs(t / b.sum() - 1) for t in totals)
    if jump > TOTAL_JUMP:
        warnings.append(f"the total changes by {jump:.0%} when lambda is halved or doubled "
                        f"({totals[0] / b.sum():.3f}x, {totals[1] / b.sum():.3f}x): it is not determined by the data "
                        "alone; treat it with care")
    return totals
