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
  λ-selection cheap: with weights 1/σ² of the noise model the noise level is known and λ
  minimises the unbiased predictive risk ‖W^½r_λ‖² + 2Σf − m (UPRE, GCV's known-variance
  form; GCV proper, m‖r_λ‖² / (m − Σ f)², would take model error for noise and over-smooth);
- the same k clipped solves as the paper then give the non-negative estimate.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from . import _common as c
from fluxcli.errors import InputError


def observed_adjacency(adjacency, mask: np.ndarray) -> sp.csr_array:
    """The edge weights among the observed elements (``mask``), checked: square, finite,
    non-negative; the diagonal dropped."""
    A = sp.csr_array(adjacency, dtype=np.float64)
    n = mask.size
    if A.shape != (n, n):
        raise InputError(f"adjacency must have shape ({n}, {n}), got {A.shape}.")
    if A.nnz and not (np.all(np.isfinite(A.data)) and A.data.min() >= 0):
        raise InputError("adjacency weights must be finite and non-negative.")
    A = sp.csr_array(A[mask][:, mask])
    A.setdiag(0.0)
    A.eliminate_zeros()
    return A


def graph_laplacian(adjacency, mask: np.ndarray, *, dense: bool = False):
    """The weighted graph Laplacian ``L = diag(A1) − A`` of the observed elements: the one
    Laplacian of fluxmap: the smoothness prior of ``smooth`` (dense, :func:`exitance_prior`, and
    matrix-free, :func:`fluxcli.inverse.matfree.sparse_exitance_prior`) and MLEM's one-step-late
    penalty are built on it.

    ``bᵀLb = Σ_edges A_ij (b_i − b_j)²`` (each edge once), so ``L`` has zero row sums and is
    positive semi-definite.

    Parameters
    ----------
    adjacency : (n_elements, n_elements) sparse or dense, symmetric edge weights ≥ 0: 1 where
        two elements touch (``Surface.element_adjacency``), or the cotangent weights of a vertex
        basis (``Surface.vertex_basis().stiffness``), for which ``bᵀLb`` is the exact
        ``∫|∇J|² dS`` of a field linear within faces.  Edges to unobserved elements and the
        diagonal are dropped.
    mask : (n_elements,) bool, the observed elements.
    dense : return an ndarray (the degrees then summed as numpy sums a dense row, so the
        dense prior keeps its bits) instead of a sparse matrix.

    Returns
    -------
    sparse csr or ndarray (n_obs, n_obs), the unit of the weights.
    """
    A = sp.csr_array(adjacency, dtype=np.float64)
    if A.shape == (mask.size, mask.size) and abs(A - A.T).sum() > 1e-12 * max(abs(A).sum(), 1.0):
        raise InputError("adjacency must be symmetric.")
    A = observed_adjacency(A, mask)
    if dense:
        A = A.toarray()
        return np.diag(A.sum(axis=1)) - A
    degree = np.asarray(A.sum(axis=1)).ravel()
    return sp.csr_array(sp.diags_array(degree) - A)


def exitance_scaling(areas, mask: np.ndarray) -> np.ndarray | None:
    """``d_j = S̄/S_j`` over the observed elements (``S̄`` their mean area): a prior ``JᵀLJ`` on
    exitance ``J = b/S`` is ``bᵀ D L D b`` on power, ``D = diag(d)``.  None for ``areas`` None
    (equal areas, ``D = I``).

    Parameters
    ----------
    areas : (n_elements,) mm², > 0 on observed elements, or None.
    mask : (n_elements,) bool, the observed elements.
    """
    if areas is None:
        return None
    S = np.asarray(areas, dtype=np.float64)
    if S.shape != mask.shape or not np.all(S[mask] > 0):
        raise InputError(f"areas must be ({mask.size},) and > 0 on observed elements.")
    return S[mask].mean() / S[mask]


def on_exitance(L, d):
    """``D L D`` with ``D = diag(d)`` (:func:`exitance_scaling`), for a dense or sparse ``L``;
    ``L`` itself when ``d`` is None."""
    if d is None:
        return L
    if sp.issparse(L):
        D = sp.diags_array(d)
        return sp.csr_array(D @ L @ D)
    return d[:, None] * L * d[None, :]


def element_laplacian(adjacency, mask: np.ndarray, ridge: float = 1e-3) -> np.ndarray:
    """:func:`graph_laplacian` as a dense matrix scaled to unit max diagonal, plus ``ridge``
    times the identity (so it is positive definite)."""
    L = graph_laplacian(adjacency, mask, dense=True)
    peak = L.diagonal().max() if len(L) else 0.0
    return (L / peak if peak > 0 else L) + ridge * np.eye(len(L))


def exitance_prior(adjacency, mask: np.ndarray, areas=None, ridge: float = 1e-3) -> np.ndarray:
    """The smoothness prior on exitance ``J = b/S`` as a matrix on power ``b``.

    ``Jᵀ(L + ridge·I)J = bᵀ D(L + ridge·I)D b`` with ``D = diag(S̄/S_j)`` (``S̄`` the mean
    observed area, so equal areas give back :func:`element_laplacian`): light leaving a
    diffusing body is smooth *per unit area*; a prior on power per element would pull
    small elements up and large ones down.

    Parameters
    ----------
    adjacency : (n_elements, n_elements), nonzero where two elements touch.
    mask : (n_elements,) bool, the observed elements.
    areas : (n_elements,) mm², or None for equal areas.
    ridge : weight of the identity (penalises a constant exitance a little).

    Returns
    -------
    (n_obs, n_obs) symmetric positive definite matrix.
    """
    return on_exitance(element_laplacian(adjacency, mask, ridge), exitance_scaling(areas, mask))


def smooth_iterated(T, a, *, adjacency, lam: float | None = None, n_iter: int = 10, gamma: float = 1.0,
                    lambdas=None, sigma2=None, rel_threshold: float = c.DEFAULT_REL_THRESHOLD,
                    areas=None, variance=None, rule: str = "gcv") -> dict:
    """Non-negative iterated Tikhonov with a smoothness prior on exitance; λ by GCV (UPRE once weighted)
    (on the filter factors of the ``n_iter`` solves) if not given.

    Parameters
    ----------
    T : sparse (n_pixels, n_elements), dimensionless.
    a : (n_pixels,) photons.
    adjacency : (n_elements, n_elements) sparse or dense; nonzero where two elements touch.
    lam : relative λ (λ̃ = lam · max diag(TᵀWT)); None chooses it.
    n_iter : k, the number of clipped solves (the paper used 5–10).
    gamma : the weight of the degrees of freedom in GCV / UPRE (1: the unbiased rule).
    lambdas : the relative grid searched (default 10^-9 … 10^3, widened at an edge pick).
    sigma2 : (n_pixels,) fixed noise variance in photons², used for ``sigma`` only (the
        fit stays unweighted).
    areas : (n_elements,) element areas in mm² (the prior acts on exitance); None: equal.
    variance : callable, photons → photons², the noise model; when given the fit is
        weighted by ``1/σ²`` of the model image, iteratively reweighted, and σ and χ²
        follow from it.
    rule : "gcv" | "lcurve" | "discrepancy".

    Returns
    -------
    dict with power (n_elements, NaN where unobserved), observed, sigma, lam, lam_absolute,
    iterations, converged, chi2_per_pixel, warnings, gcv (the curve: lambdas, criterion).
    """
    from fluxcli.inverse.filtered import filtered_solve

    T = c.as_transfer(T)
    a = c.as_pixels(a, T.shape[0], "image a (photons)")
    n_iter = c.check_positive_int(n_iter, "n_iter")
    if lam is not None:
        lam = c.check_nonneg_number(lam, "lam")
    mask = c.observed(T, rel_threshold)
    To = sp.csr_array(T[:, mask])
    rows = c.covered_rows(To)
    Tc, ac = sp.csr_array(To[rows]), a[rows]
    s2 = None
    if sigma2 is not None:
        s2 = c.as_pixels(sigma2, T.shape[0], "sigma2", positive=True, allow_scalar=True)[rows]
    R = exitance_prior(adjacency, mask, areas)
    out = filtered_solve(Tc, ac, prior=R, k=n_iter, lam=lam, rule=rule, gamma=gamma, lambdas=lambdas,
                         variance=variance, sigma2=s2, weighted=variance is not None, free_level=True, exact=True)
    sigma = np.full(mask.size, np.nan)
    sigma[mask] = out.sigma
    ch = out.choice
    return {"power": c.scatter(out.power, mask), "observed": mask, "sigma": sigma, "lam": out.lam,
            "lam_absolute": out.lam_absolute, "iterations": out.iterations, "converged": out.converged,
            "chi2_per_pixel": out.chi2_per_pixel, "warnings": out.warnings, "filtered": out,
            "gcv": {"lambdas": ch.lambdas if ch else np.array([out.lam]),
                    "criterion": ch.criterion if ch else np.array([np.nan])}}
