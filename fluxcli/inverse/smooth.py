"""fluxmap's default inversion: the paper's iterated, non-negative Tikhonov scheme, with a
surface-smoothness prior and λ chosen by (modified) generalised cross-validation.

The paper solves (TᵀT + λ̃I) δ = Tᵀr repeatedly, clipping negatives, with λ fixed by
hand.  Its fixed λ̃ = λ·max diag(TᵀT) regularises an in-focus, nearly diagonal TᵀT far
more than a blurred one, so its error depends on focus.  Here:

- the penalty is λ̃ bᵀLb with L the graph Laplacian of the elements (plus a small
  multiple of I so constants are penalised a little too): light leaving a diffusing
  body varies smoothly from element to element;
- k solves of (TᵀT + λ̃L) δ = Tᵀr act, before clipping, as the spectral filter
  f(s) = 1 − (λ̃/(s + λ̃))^k in the generalised eigenbasis of (TᵀT, L), which makes
  GCV cheap: GCV(λ) = m‖r_λ‖² / (m − γ Σ f)², with γ = 1.4 (modified GCV, which avoids
  GCV's occasional under-smoothing);
- the same k clipped solves as the paper then give the non-negative estimate.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from . import _common as c


def element_laplacian(adjacency, mask: np.ndarray, ridge: float = 1e-3) -> np.ndarray:
    """Dense graph Laplacian of the observed elements, scaled to unit max diagonal, plus
    ``ridge`` times the identity (so it is positive definite)."""
    A = sp.csr_array(adjacency, dtype=np.float64)
    n = mask.size
    if A.shape != (n, n):
        raise ValueError(f"adjacency must have shape ({n}, {n}), got {A.shape}.")
    A = A[mask][:, mask].toarray()
    np.fill_diagonal(A, 0.0)
    A = (A > 0).astype(float)
    L = np.diag(A.sum(axis=1)) - A
    peak = L.diagonal().max()
    return (L / peak if peak > 0 else L) + ridge * np.eye(len(L))


def smooth_iterated(T, a, *, adjacency, lam: float | None = None, n_iter: int = 10, gamma: float = 1.4,
                    lambdas=None, sigma2=None, rel_threshold: float = c.DEFAULT_REL_THRESHOLD) -> dict:
    """Non-negative iterated Tikhonov with a smoothness prior; λ by modified GCV if not given.

    Parameters
    ----------
    T : sparse (n_pixels, n_elements), dimensionless.
    a : (n_pixels,) photons.
    adjacency : (n_elements, n_elements) sparse or dense; nonzero where two elements touch.
    lam : relative λ (λ̃ = lam · max diag(TᵀT)); None chooses it.
    n_iter : k, the number of clipped solves (the paper used 5–10).
    gamma : the modified-GCV factor (1 is plain GCV).
    lambdas : the relative grid searched (default 10^-8 … 10^4, 73 values).
    sigma2 : (n_pixels,) noise variance in photons²; when given, the per-element standard
        deviation of the linear (unclipped) estimator is returned.

    Returns
    -------
    dict with power (n_elements, NaN where unobserved), observed, sigma, lam, lam_absolute,
    iterations, gcv (the curve: lambdas, criterion).
    """
    T = c.as_transfer(T)
    a = c.as_pixels(a, T.shape[0], "image a (photons)")
    n_iter = c.check_positive_int(n_iter, "n_iter")
    mask = c.observed(T, rel_threshold)
    idx = np.flatnonzero(mask)
    To = sp.csr_array(T[:, idx])
    G, g = c.normal_equations(To, a, None)
    L = element_laplacian(adjacency, mask)
    scale = c.lam_scale(G)
    s, V = sla.eigh(G, L)  # G V = L V diag(s), Vᵀ L V = I
    s = np.maximum(s, 0.0)
    coef = V.T @ g
    seen = np.asarray(To.sum(axis=1)).ravel() > 0
    m = int(seen.sum())
    a2 = float(a[seen] @ a[seen])

    def filt(lam_abs):
        f = 1.0 - (lam_abs / (s + lam_abs)) ** n_iter
        with np.errstate(divide="ignore", invalid="ignore"):
            f_over_s = np.where(s > 1e-14 * scale, f / s, n_iter / lam_abs)
        return f, f_over_s

    grid = np.logspace(-8, 4, 73) if lambdas is None else np.asarray(lambdas, float)
    crit = np.full(len(grid), np.inf)
    if lam is None:
        for i, lr in enumerate(grid):
            f, fos = filt(lr * scale)
            # ‖a − T b_λ‖² = ‖a‖² − Σ (2 − f) f c²/s  for b_λ = V diag(f/s) Vᵀ Tᵀa
            r2 = a2 - float(((2 - f) * coef * coef * fos).sum())
            dof = m - gamma * f.sum()
            if dof > 0:
                crit[i] = m * max(r2, 0.0) / dof**2
        lam = float(grid[int(np.argmin(crit))])
    lam = c.check_nonneg_number(lam, "lam")
    lam_abs = lam * scale
    H = G + lam_abs * L
    cf = c.cholesky(H, "TᵀT + λ̃L")
    b = np.maximum(sla.cho_solve(cf, g, check_finite=False), 0.0)
    for _ in range(n_iter - 1):
        r = a - To @ b
        b = np.maximum(b + sla.cho_solve(cf, To.T @ r, check_finite=False), 0.0)
    sigma = np.full(mask.size, np.nan)
    if sigma2 is not None:
        s2 = c.as_pixels(sigma2, T.shape[0], "sigma2", positive=True)
        _, fos = filt(lam_abs)
        M = (V * fos) @ V.T  # the linear estimator is M Tᵀ a
        TS = To.T.multiply(s2[None, :]) if hasattr(To.T, "multiply") else To.T @ sp.diags(s2)
        C = (sp.csr_array(TS) @ To).toarray()
        sigma[idx] = np.sqrt(np.maximum(np.einsum("ij,jk,ik->i", M, C, M), 0.0))
    return {"power": c.scatter(b, mask), "observed": mask, "sigma": sigma, "lam": lam, "lam_absolute": lam_abs,
            "iterations": n_iter, "gcv": {"lambdas": grid, "criterion": crit}}
