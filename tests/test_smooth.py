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


def _chain_problem(n=300, m=300, seed=0):
    """A 1-D chain of n unknowns under m blurred pixels, Poisson counts of a bump on a floor."""
    from chains import blur_chain

    T, a, _, R, truth = blur_chain(n, m, seed)
    return T, a, R, truth


def test_a_provisional_pass_whose_gcv_runs_off_the_grid_falls_back_to_the_noise_model():
    """The first, unweighted pass of a weighted solve picks λ by GCV, which estimates the noise
    from the residual. Here it runs below the grid (λ ~1e-9: a total 239x too large, χ²/pixel
    2e4) and the model weights taken from that would ruin the final solve. The fallback picks
    that pass's λ by UPRE with the noise model's mean variance: the final answer is right."""
    from fluxcli.imaging.noise import PhotonNoise
    from fluxcli.inverse import spectral as S
    from fluxcli.inverse.filtered import filtered_solve

    T, a, R, truth = _chain_problem()
    spec = S.Spectrum(T, a, None, R)
    gcv = S.choose(spec, "gcv", k=10)
    assert gcv.widened and gcv.lam < 1e-6  # the failure the fallback is for
    runaway = S.iterated_clipped(spec, gcv.lam * spec.scale, 10)[0]
    assert runaway.sum() > 10 * truth.sum()
    out = filtered_solve(T, a, prior=R, k=10, variance=PhotonNoise(kind="poisson").variance, free_level=True)
    assert np.abs(out.power - truth).sum() / truth.sum() < 0.05
    assert out.power.sum() / truth.sum() == pytest.approx(1.0, abs=0.02)
    assert 0.5 <= out.chi2_per_pixel <= 2.0


def test_iterated_solve_uses_the_spectrum_when_cholesky_cannot_vouch_for_its_pivots():
    """Columns whose weights span 15 decades make Cholesky's smallest pivot fall under its
    rounding-level test although G + λ̃I is positive definite; the solve then comes from the
    generalised eigenbasis, (G + λ̃R)⁻¹ = V diag(1/(s + λ̃)) Vᵀ, and must equal the closed form
    g_i / (G_ii + λ̃) of this diagonal problem."""
    import scipy.sparse as sp

    from fluxcli.inverse import _common as c
    from fluxcli.inverse import spectral as S

    T = sp.csr_array(np.diag([1.0, np.sqrt(1e-15)]))
    a = np.array([2.0, 3e-8])
    spec = S.Spectrum(T, a)
    lam = 1e-16
    assert c.try_cholesky(spec.G + lam * np.eye(2)) is None
    b, _, _ = S.iterated_clipped(spec, lam, 1)
    np.testing.assert_allclose(b, spec.g / (np.diag(spec.G) + lam), rtol=1e-9)
