"""A 1-D test problem shared by the solver tests: a chain of unknowns under blurred pixels."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp


def blur_chain(n: int = 300, m: int = 300, seed: int = 0):
    """n unknowns under m Gaussian-blurred pixels, Poisson counts of a bump on a floor.

    Returns T (sparse, m x n), the counts a, the chain's adjacency, its exitance prior and the truth."""
    from fluxcli.inverse.smooth import exitance_prior

    rng = np.random.default_rng(seed)
    x, px = np.linspace(0, 1, n), np.linspace(0, 1, m)
    T = np.exp(-((px[:, None] - x[None, :]) / 0.01) ** 2)
    T /= T.sum(axis=1, keepdims=True) / 0.5
    truth = 1e3 * np.exp(-((x - 0.4) / 0.1) ** 2) + 10
    a = rng.poisson(T @ truth).astype(float)
    adj = sp.diags_array([np.ones(n - 1), np.ones(n - 1)], offsets=[-1, 1]).tocsr()
    return sp.csr_array(T), a, adj, exitance_prior(adj, np.ones(n, bool)), truth
