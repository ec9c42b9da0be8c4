"""Choosing the Tikhonov regularisation and the uncertainty of a reconstruction.

Both exploit that the number of elements is small (≲ a few thousand): the normal matrix
``G = TᵀWT`` (n_obs, n_obs) is formed densely and eigendecomposed or factorised once,
after which every λ costs O(n_obs).

``lam`` is in the paper's relative units throughout: ``λ̃ = lam × max diag(TᵀWT)``, with
``W = diag(1/σ²)`` for weighted problems and ``W = I`` otherwise (so a weighted ``lam`` is
relative to the weighted normal matrix).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from fluxcli.inverse import _common as c
from fluxcli.inverse.spectral import FilterCovariance, Spectrum, _pick
from fluxcli.errors import InputError

__all__ = ["LAMBDA_RULES", "LambdaChoice", "choose_lambda", "linear_covariance", "uncertainty"]

LAMBDA_RULES = ("gcv", "lcurve", "discrepancy")


@dataclass(frozen=True)
class LambdaChoice:
    """The chosen λ and the curve it was chosen from (for plotting).

    Attributes
    ----------
    lam : float
        Chosen relative regularisation.
    lam_absolute : float
        ``λ̃ = lam × max diag(TᵀWT)``.
    method : str
        ``"gcv"``, ``"lcurve"`` or ``"discrepancy"``.
    lambdas : ndarray, shape (n_lambdas,)
        Relative λ grid scanned.
    criterion : ndarray, shape (n_lambdas,)
        GCV function (minimised), L-curve curvature (maximised) or residual minus target
        (zero crossing), on ``lambdas``.
    residual_norm2 : ndarray, shape (n_lambdas,)
        ``‖W^½(a − T b_λ)‖²`` of the linear Tikhonov solution (photons² if unweighted,
        dimensionless if weighted).
    solution_norm2 : ndarray, shape (n_lambdas,)
        ``‖b_λ‖²`` in photons².
    target : float
        Discrepancy target for the residual (NaN for the other rules).
    n_data : int
        Pixels that see at least one observed element (the data count used).
    weighted : bool
        Whether ``W = diag(1/σ²)``.
    at_edge : bool
        True when the choice sits at an end of the grid: widen ``lambdas``.
    """

    lam: float
    lam_absolute: float
    method: str
    lambdas: np.ndarray
    criterion: np.ndarray
    residual_norm2: np.ndarray
    solution_norm2: np.ndarray
    target: float
    n_data: int
    weighted: bool
    at_edge: bool


def choose_lambda(T, a, *, method: str = "gcv", sigma2=None, lambdas=None,
                  weighted: bool | None = None, tau: float = 1.0, gamma: float = 1.0,
                  rel_threshold: float = c.DEFAULT_REL_THRESHOLD) -> LambdaChoice:
    """Choose the Tikhonov λ automatically (the paper tunes it by hand).

    All three rules use the linear Tikhonov solution
    ``b_λ = (TᵀWT + λ̃I)⁻¹TᵀWa`` on the observed elements and the pixels that see them.

    - ``"gcv"``: minimise ``‖W^½ r_λ‖² / (m − gamma · tr H_λ)²`` (generalised
      cross-validation, ``H_λ`` the influence matrix, ``m`` the number of pixels used).
      GCV estimates the *image* prediction error; the flux error is minimised by a
      somewhat larger λ, and GCV occasionally picks a spurious tiny λ. ``gamma > 1``
      (modified GCV, e.g. 1.4, Cummins et al. 2001) makes it more robust.
    - ``"lcurve"``: maximise the curvature of ``(log ‖W^½ r_λ‖, log ‖b_λ‖)`` along
      ``log λ`` (numerical derivatives on the grid).
    - ``"discrepancy"``: the λ at which ``‖W^½ r_λ‖² = tau × E‖W^½ noise‖²``, i.e.
      ``tau × m`` when weighted and ``tau × Σσ²`` when not (Morozov).

    Parameters
    ----------
    T : scipy.sparse array or ndarray, shape (n_pixels, n_elements)
        Transfer matrix, dimensionless, ≥ 0.
    a : ndarray, shape (n_pixels,)
        Image in photons.
    method : {"gcv", "lcurve", "discrepancy"}, optional
    sigma2 : float or ndarray, shape (n_pixels,), optional
        Noise variance per pixel in photons² (> 0). Required for ``"discrepancy"`` and
        for weighted problems.
    lambdas : ndarray, shape (n_lambdas,), optional
        Relative λ values to scan (> 0); default ``logspace(-9, 3, 121)``.
    weighted : bool, optional
        Use ``W = 1/sigma2``; default: weighted if ``sigma2`` is given. Choose the
        weighting of the reconstruction the λ is meant for (``paper``/``nnls``
        unweighted, ``weighted_lsq`` weighted).
    tau : float, optional
        Safety factor of the discrepancy principle (≥ 1 is conservative).
    gamma : float, optional
        Trace weight of modified GCV; 1 is standard GCV.
    rel_threshold : float, optional
        See :func:`fluxcli.inverse.observed_mask`.

    Returns
    -------
    LambdaChoice
    """
    if method not in LAMBDA_RULES:
        raise InputError(f"lam_rule/method must be one of {', '.join(LAMBDA_RULES)}; got {method!r}.")
    tau = c.check_nonneg_number(tau, "tau")
    gamma = c.check_nonneg_number(gamma, "gamma")
    T = c.as_transfer(T)
    a = c.as_pixels(a, T.shape[0], "image a (photons)")
    if weighted is None:
        weighted = sigma2 is not None
    if sigma2 is not None:
        sigma2 = c.as_pixels(sigma2, T.shape[0], "noise variance sigma2 (photons²)",
                             positive=True, allow_scalar=True)
    elif weighted or method == "discrepancy":
        raise InputError(
            "the noise variance sigma2 (photons²) is required for weighted problems and "
            "for the discrepancy principle."
        )
    if lambdas is None:
        lambdas = np.logspace(-9, 3, 121)
    lambdas = np.sort(np.asarray(lambdas, dtype=np.float64).ravel())
    if lambdas.size < 3 or not np.all(np.isfinite(lambdas)) or lambdas[0] <= 0:
        raise InputError("lambdas must hold at least 3 finite values > 0.")

    mask = c.observed(T, rel_threshold)
    T_obs = sp.csr_array(T[:, mask])
    cov = c.covered_rows(T_obs)
    T_cov, a_cov = sp.csr_array(T_obs[cov]), a[cov]
    weights = 1.0 / sigma2[cov] if weighted else None
    m = int(cov.sum())
    spec = Spectrum(T_cov, a_cov, weights)  # the one spectral-filter engine (k = 1: Tikhonov)
    noise_total = None
    if method == "discrepancy":
        noise_total = m if weighted else float(np.sum(sigma2[cov]))
    # the rules of the engine, on this grid as given (no widening: at_edge tells the caller)
    pick = _pick(spec, method, 1, lambdas, gamma, tau, noise_total)
    lam, at_edge, criterion, target = pick.lam, pick.at_edge, pick.criterion, pick.target
    rho, eta = pick.residual_norm2, pick.solution_norm2

    return LambdaChoice(
        lam=float(lam), lam_absolute=float(lam * spec.scale), method=method,
        lambdas=lambdas, criterion=criterion, residual_norm2=rho, solution_norm2=eta,
        target=float(target), n_data=m, weighted=bool(weighted),
        at_edge=bool(at_edge),
    )


def uncertainty(T, a, b_hat, *, sigma2, lam: float, weighted: bool = True,
                kind: str | None = None,
                rel_threshold: float = c.DEFAULT_REL_THRESHOLD) -> np.ndarray:
    """Per-element standard deviation of a Tikhonov-family reconstruction.

    With ``H = TᵀWT + λ̃I`` (``λ̃ = lam × max diag(TᵀWT)``):

    - ``kind="posterior"`` (default when weighted): ``diag(H⁻¹)``, the posterior
      covariance of the Gaussian model with noise ``N(0, σ²)`` and prior
      ``b ~ N(0, I/λ̃)``. It includes the prior variance, so it exceeds the scatter of the
      estimate under noise when λ̃ is not small compared with the signal eigenvalues.
    - ``kind="sampling"`` (default when unweighted): the covariance of the linear
      estimator ``b_λ = H⁻¹TᵀWa`` under noise ``diag(σ²)``,
      ``diag(H⁻¹ TᵀWΣWT H⁻¹)``; for ``lam = 0`` and weighted both kinds agree.

    Parameters
    ----------
    T : scipy.sparse array or ndarray, shape (n_pixels, n_elements)
        Transfer matrix, dimensionless, ≥ 0.
    a : ndarray, shape (n_pixels,)
        Image in photons (shape check only).
    b_hat : ndarray, shape (n_elements,)
        The reconstruction in photons per element (NaN where unobserved); used for the
        model variance when ``sigma2`` is None.
    sigma2 : float or ndarray, shape (n_pixels,), or None
        Noise variance per pixel in photons². None means Poisson noise of the model
        image, ``max(T b̂, 1)`` (a one-photon floor keeps dark pixels finite).
    lam : float
        Relative regularisation of the reconstruction.
    weighted : bool, optional
        Whether the reconstruction was weighted with ``W = 1/σ²`` (``weighted_lsq``);
        False for ``paper``/``nnls``/``tikhonov`` (``W = I``).
    kind : {"posterior", "sampling"}, optional
    rel_threshold : float, optional
        See :func:`fluxcli.inverse.observed_mask`.

    Returns
    -------
    ndarray, shape (n_elements,)
        Standard deviation in photons per element; NaN for unobserved elements, inf for
        elements the data cannot determine (singular ``H`` with ``lam = 0``).

    Notes
    -----
    For the non-negative methods this is the linear approximation: it ignores the
    constraint, so it is accurate for elements well above zero and conservative for
    elements at or near zero (the clipped estimator scatters less). MLEM at convergence is
    approximated by the weighted ``lam = 0`` form (inverse Fisher information when
    ``σ²`` is the model image).
    """
    lam = c.check_nonneg_number(lam, "lam")
    if kind is None:
        kind = "posterior" if weighted else "sampling"
    if kind not in ("posterior", "sampling"):
        raise InputError(f"kind must be 'posterior' or 'sampling', got {kind!r}.")
    if kind == "posterior" and not weighted:
        raise InputError(
            "kind='posterior' needs a weighted problem (weighted=True): an unweighted fit "
            "has no posterior for per-pixel σ²; use kind='sampling'."
        )
    T = c.as_transfer(T)
    a = c.as_pixels(a, T.shape[0], "image a (photons)")
    b_hat = c.as_elements(b_hat, T.shape[1], "b_hat (photons per element)")
    mask = c.observed(T, rel_threshold)
    T_obs = sp.csr_array(T[:, mask])
    if sigma2 is None:
        if np.any(np.isnan(b_hat[mask])):
            raise InputError("b_hat (photons per element) is NaN for an observed element.")
        sigma2 = np.maximum(T_obs @ b_hat[mask], 1.0)
    sigma2 = c.as_pixels(sigma2, T.shape[0], "noise variance sigma2 (photons²)",
                         positive=True, allow_scalar=True)
    cov = linear_covariance(T_obs, sigma2, lam, weighted, kind=kind)
    return c.scatter(np.sqrt(np.maximum(cov.variance_of(sp.identity(T_obs.shape[1], format="csr")), 0.0)), mask)


def linear_covariance(T_obs, sigma2, lam: float, weighted: bool, *, kind: str = "sampling") -> FilterCovariance:
    """The covariance of the Tikhonov estimator ``b = H⁻¹TᵀWa``, ``H = TᵀWT + λ̃I``
    (``λ̃ = lam × max diag TᵀWT``), as an operator (``variance_of(weights)``), from the one
    spectral engine (:class:`fluxcli.inverse.spectral.Spectrum` with ``k = 1`` and ``R = I``).

    Parameters
    ----------
    T_obs : sparse (n_pixels, n_obs), the observed columns, dimensionless.
    sigma2 : (n_pixels,) photons², the noise variance of the pixels.
    lam : relative λ (0 for MLEM, taken as the weighted λ = 0 estimator).
    weighted : the estimator weights the fit by ``W = 1/sigma2`` (else ``W = I``).
    kind : "sampling" (the scatter under the noise) or "posterior" (``H⁻¹``, weighted only).
    """
    T_obs = sp.csr_array(T_obs)
    rows = c.covered_rows(T_obs)
    T_cov, s2 = sp.csr_array(T_obs[rows]), np.asarray(sigma2, float)[rows]
    spec = Spectrum(T_cov, np.zeros(T_cov.shape[0]), 1.0 / s2 if weighted else None)
    return FilterCovariance(spec, lam * spec.scale, 1, None if weighted else s2, kind=kind)
