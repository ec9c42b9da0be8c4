"""The variance of linear functionals of a reconstruction: ``variance_of(weights)``.

A region's total ``Σ_j w_j b̃_j`` has the variance ``wᵀ C w`` with ``C`` the covariance of
the estimate under the images' noise; the per-element σ alone cannot give it (neighbouring
elements share pixels and are anti-correlated, so summing σ, or σ², is wrong either way).
Every covariance here is an operator with one method, ``variance_of(weights)``: weights
(n,) or (n_functionals, n), dense or sparse, over the unknowns the object names, returning
photons² (n_functionals,).  A matrix-free estimator (probing, Lanczos) for large problems
can stand in anywhere with the same method.

- :class:`fluxcli.inverse.spectral.FilterCovariance`: the one engine, exact for the linear filter
  (paper, smooth: from the eigendecomposition they solved on);
- the other Tikhonov-family estimators (tikhonov, nnls, weighted_lsq; MLEM as the weighted
  λ = 0 estimator) use the same engine with ``k = 1`` and ``R = I``
  (:func:`fluxcli.inverse.regularisation.linear_covariance`, made on first use by :class:`Deferred`);
- :class:`OnObserved` and :class:`Mapped` change the unknowns the weights run over.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp


def _rows(weights):
    one = not sp.issparse(weights) and np.ndim(weights) == 1
    W = sp.csr_array(weights) if sp.issparse(weights) else np.atleast_2d(np.asarray(weights, float))
    return W, one


class Deferred:
    """A covariance made on first use by ``make()`` (most reconstructions never ask for one)."""

    def __init__(self, make):
        self._make, self._inner = make, None

    def variance_of(self, weights) -> np.ndarray:
        if self._inner is None:
            self._inner = self._make()
        return self._inner.variance_of(weights)


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
