"""The variance of linear functionals of a reconstruction: ``variance_of(weights)``.

A region's total ``Σ_j w_j b̃_j`` has the variance ``wᵀ C w`` with ``C`` the covariance of
the estimate under the images' noise; the per-element σ alone cannot give it (neighbouring
elements share pixels and are anti-correlated, so summing σ, or σ², is wrong either way).
Every covariance here is an operator with one method, ``variance_of(weights)``: weights
(n,) or (n_functionals, n), dense or sparse, over the unknowns the object names, returning
photons² (n_functionals,).  A matrix-free estimator (probing, Lanczos) for large problems
can stand in anywhere with the same method.

- :class:`fluxcli.inverse.spectral.FilterCovariance`: the spectral filter methods (paper,
  smooth), exact for the linear filter, from the eigendecomposition they solved on;
- :class:`DenseCovariance`: the other Tikhonov-family estimators (tikhonov, nnls,
  weighted_lsq; MLEM as the weighted λ = 0 estimator), ``H⁻¹ K H⁻¹`` as in
  :func:`fluxcli.inverse.regularisation.uncertainty` (``kind="sampling"``);
- :class:`OnObserved` and :class:`Mapped` change the unknowns the weights run over.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from fluxcli.inverse import _common as c


def _rows(weights):
    one = not sp.issparse(weights) and np.ndim(weights) == 1
    W = sp.csr_array(weights) if sp.issparse(weights) else np.atleast_2d(np.asarray(weights, float))
    return W, one


class DenseCovariance:
    """``C = H⁻¹ K H⁻¹`` of the linear estimator ``b = H⁻¹TᵀWa``, ``H = TᵀWT + λ̃I``,
    ``K = TᵀWΣWT`` (= ``TᵀWT`` when ``W = Σ⁻¹``), on the observed unknowns.

    Parameters
    ----------
    T_obs : sparse (m, n_obs), dimensionless.
    sigma2 : (m,) photons², the noise variance of the pixels.
    lam : relative λ (``λ̃ = lam × max diag TᵀWT``).
    weighted : the estimator weights the fit by ``W = 1/sigma2`` (else ``W = I``)."""

    def __init__(self, T_obs, sigma2, lam: float, weighted: bool):
        self._args = (sp.csr_array(T_obs), np.asarray(sigma2, float), float(lam), bool(weighted))
        self._cf = self._pinv = self._K = None

    def _factor(self):  # on first use: most reconstructions never ask
        T_obs, sigma2, lam, weighted = self._args
        G, _ = c.normal_equations(T_obs, np.zeros(T_obs.shape[0]), 1.0 / sigma2 if weighted else None)
        H = G + lam * c.lam_scale(G) * np.eye(G.shape[0])
        self._K = G if weighted else c.normal_equations(T_obs, np.zeros(T_obs.shape[0]), sigma2)[0]
        self._cf = c.try_cholesky(H)
        if self._cf is None:  # singular (λ = 0 and unknowns the data cannot tell apart): pseudo-inverse
            w, V = np.linalg.eigh(H)
            keep = w > max(w.max(), 0.0) * len(w) * np.finfo(float).eps
            self._pinv = (V[:, keep] / w[keep]) @ V[:, keep].T

    def _solve(self, X):
        if self._K is None:
            self._factor()
        return sla.cho_solve(self._cf, X, check_finite=False) if self._cf is not None else self._pinv @ X

    def variance_of(self, weights) -> np.ndarray:
        W, one = _rows(weights)
        Z = self._solve(np.asarray(W.T.toarray() if sp.issparse(W) else W.T))  # H⁻¹ wᵀ, (n_obs, g)
        var = np.einsum("ig,ig->g", Z, self._K @ Z)
        return var[0] if one else var


class OnObserved:
    """A covariance over the observed unknowns, taking weights over all of them (the
    unobserved ones are not estimated and carry no variance)."""

    def __init__(self, inner, observed: np.ndarray):
        self.inner, self.observed = inner, np.asarray(observed, bool)

    def variance_of(self, weights) -> np.ndarray:
        W, one = _rows(weights)
        W = sp.csr_array(W)[:, np.flatnonzero(self.observed)] if sp.issparse(W) else W[:, self.observed]
        var = self.inner.variance_of(W)
        return var[0] if one else var


class Mapped:
    """Weights over groups (elements) whose values are ``M @ x`` of the unknowns ``x``
    (sub-elements summed, vertices shared out): ``w·(M x) = (w M)·x``."""

    def __init__(self, inner, to_groups):
        self.inner, self.M = inner, sp.csr_array(to_groups)

    def variance_of(self, weights) -> np.ndarray:
        W, one = _rows(weights)
        WM = sp.csr_array(W) @ self.M
        var = self.inner.variance_of(WM)
        return var[0] if one else var


def parent_map(parent: np.ndarray, n_groups: int) -> sp.csr_array:
    """(n_groups, n_unknowns) 0/1: unknown i belongs to group ``parent[i]``."""
    parent = np.asarray(parent)
    return sp.csr_array((np.ones(parent.size), (parent, np.arange(parent.size))), shape=(n_groups, parent.size))


class Scaled:
    """The covariance of ``c · x``: variances times c² (e.g. a filter's transmission undone)."""

    def __init__(self, inner, factor: float):
        self.inner, self.factor = inner, float(factor)

    def variance_of(self, weights) -> np.ndarray:
        return self.inner.variance_of(weights) * self.factor**2
