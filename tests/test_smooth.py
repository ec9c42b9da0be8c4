"""fluxmap's default inversion (`smooth`) against numbers it did not produce: the truth of
synthetic problems, an oracle search over λ, and the empirical scatter over noise draws."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from fluxcli.inverse import error_l1, reconstruct
from fluxcli.inverse.smooth import smooth_iterated


def ring_problem(n=60, px_per_element=6, blur_px=9.0):
    """A ring of n elements imaged onto a line: each element paints a Gaussian-blurred box
    of pixels (like the 2-D study out of focus); adjacency = ring neighbours."""
    n_px = n * px_per_element
    x = np.arange(n_px) + 0.5
    cols = []
    for j in range(n):
        lo, hi = j * px_per_element, (j + 1) * px_per_element
        box = ((x >= lo) & (x < hi)).astype(float)
        kernel = np.exp(-0.5 * (np.arange(-30, 31) / (blur_px / 2.355)) ** 2)
        col = np.convolve(box, kernel / kernel.sum(), mode="same")
        cols.append(col * 1e-4 / col.sum())  # collection efficiency 1e-4
    T = sp.csr_array(np.array(cols).T)
    adj = sp.lil_array((n, n))
    for j in range(n):
        adj[j, (j + 1) % n] = adj[(j + 1) % n, j] = 1
    truth = 5e8 * np.exp(-0.5 * ((np.arange(n) - 22.3) / 4.0) ** 2)
    return T, adj.tocsr(), truth


def test_noiseless_data_converge_to_the_truth():
    T, adj, truth = ring_problem(blur_px=4.0)
    out = smooth_iterated(T, T @ truth, adjacency=adj, lam=1e-9, n_iter=10)
    assert error_l1(out["power"], truth) < 1e-3


def test_gcv_lambda_is_close_to_the_oracle():
    """Over noise draws, the error at the λ modified GCV picks is within 1.5x of the best
    error any λ of the grid achieves (an oracle that knows the truth), in the median."""
    T, adj, truth = ring_problem()
    a0 = T @ truth
    grid = np.logspace(-8, 2, 31)
    ratios = []
    for seed in range(8):
        a = np.random.default_rng(seed).poisson(a0).astype(float)
        chosen = error_l1(smooth_iterated(T, a, adjacency=adj, lambdas=grid)["power"], truth)
        oracle = min(error_l1(smooth_iterated(T, a, adjacency=adj, lam=lam)["power"], truth) for lam in grid)
        ratios.append(chosen / oracle)
    assert np.median(ratios) < 1.5
    assert max(ratios) < 3.0


def test_smooth_beats_the_papers_fixed_lambda_in_and_out_of_focus():
    for blur in (2.0, 12.0):
        T, adj, truth = ring_problem(blur_px=blur)
        a0 = T @ truth
        e_smooth, e_paper = [], []
        for seed in range(5):
            a = np.random.default_rng(100 + seed).poisson(a0).astype(float)
            e_smooth.append(error_l1(reconstruct(T, a, method="smooth", adjacency=adj).power, truth))
            e_paper.append(error_l1(reconstruct(T, a, method="paper", lam=10.0, max_iter=10).power, truth))
        assert np.mean(e_smooth) < np.mean(e_paper), blur


def test_sigma_matches_the_scatter_over_noise_draws():
    """At a fixed λ and high signal (so clipping never bites) the estimator is linear and its
    standard deviation is sqrt(diag(M T' S T M')); compare with 300 Poisson draws."""
    T, adj, truth = ring_problem()
    truth = truth + 2e8  # bright everywhere: no element near zero
    a0 = T @ truth
    rng = np.random.default_rng(7)
    draws = np.array([smooth_iterated(T, rng.poisson(a0).astype(float), adjacency=adj, lam=1e-3)["power"]
                      for _ in range(300)])
    predicted = smooth_iterated(T, a0, adjacency=adj, lam=1e-3, sigma2=a0)["sigma"]
    ratio = draws.std(axis=0, ddof=1) / predicted
    assert np.median(ratio) == pytest.approx(1.0, abs=0.1)
    assert np.all(np.abs(ratio - 1) < 0.3)


def test_smooth_needs_an_adjacency():
    T, adj, truth = ring_problem()
    with pytest.raises(ValueError, match="adjacency"):
        reconstruct(T, T @ truth, method="smooth")
