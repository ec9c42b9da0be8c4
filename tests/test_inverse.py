"""Tests of fluxcli.inverse against numbers the package does not produce: the ground
truth of synthetic problems, scipy's dense NNLS, hand-computed values, and empirical
statistics over noise repeats."""

import numpy as np
import pytest
import scipy.optimize as sopt
import scipy.sparse as sp

import fluxcli.inverse as fi


# ------------------------------------------------------------------ test problems


def blocks_problem(n_elements=100, side=45, seed=0):
    """Well-conditioned 2-D problem: each element images to a Gaussian blob on a 7×7
    pixel block (like a blurred element), 2025 pixels, coefficients ~1e-3."""
    rng = np.random.default_rng(seed)
    rows, cols, vals = [], [], []
    for j in range(n_elements):
        cy, cx = rng.uniform(3, side - 3, 2)
        width = rng.uniform(0.8, 1.5)
        ys = np.arange(int(cy) - 3, int(cy) + 4)
        xs = np.arange(int(cx) - 3, int(cx) + 4)
        Y, X = np.meshgrid(ys, xs, indexing="ij")
        rows.append((Y * side + X).ravel())
        cols.append(np.full(Y.size, j))
        vals.append(1e-3 * np.exp(-((Y - cy) ** 2 + (X - cx) ** 2) / (2 * width**2)).ravel())
    T = sp.csr_array(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
        shape=(side * side, n_elements),
    )
    b = rng.uniform(1e5, 1e6, n_elements)
    b[rng.uniform(size=n_elements) < 0.2] = 0.0  # dark elements make constraints active
    return T, b


def blur_problem(n_elements=100, pixels_per_element=4, width_elements=2.5):
    """Ill-posed 1-D problem: Gaussian blur of 2.5 elements, 4 pixels per element, a
    truth of two smooth bumps and a box, scaled to a peak image of 1e4 photons."""
    m = n_elements * pixels_per_element
    x_pix = (np.arange(m) + 0.5) / pixels_per_element
    x_el = np.arange(n_elements) + 0.5
    d = x_pix[:, None] - x_el[None, :]
    K = np.exp(-0.5 * (d / width_elements) ** 2)
    K[np.abs(d) > 4 * width_elements] = 0.0
    T = sp.csr_array(1e-3 * K / pixels_per_element)
    b = (np.exp(-0.5 * ((x_el - 30) / 5) ** 2) + 0.6 * np.exp(-0.5 * ((x_el - 65) / 8) ** 2)
         + 0.3 * ((x_el > 80) & (x_el < 90)))
    return T, b * 1e4 / (T @ b).max()


@pytest.fixture(scope="module")
def blocks():
    return blocks_problem()


@pytest.fixture(scope="module")
def blur():
    return blur_problem()


# ------------------------------------------------------------------ noiseless recovery


@pytest.mark.parametrize(
    "method, kwargs",
    [
        ("nnls", {}),
        ("weighted_lsq", {"sigma2": "model"}),
        ("mlem", {"n_iter": 5000, "rel_tol": 0.0}),
        ("paper", {"lam": 1e-6}),
    ],
)
def test_noiseless_recovery_below_0p1_percent(blocks, method, kwargs):
    T, b = blocks
    a = T @ b
    if kwargs.get("sigma2") == "model":
        kwargs = {"sigma2": a + 1.0}
    result = fi.reconstruct(T, a, method=method, **kwargs)
    assert fi.error_l1(result.power, b) < 1e-3
    assert np.all(result.power >= 0)
    np.testing.assert_allclose(result.fitted + result.residual, a)


def test_paper_first_iteration_is_clipped_tikhonov(blur):
    T, b = blur
    a = T @ b
    G = (T.T @ T).toarray()
    lam_abs = 10.0 * np.max(np.diag(G))
    expected = np.maximum(np.linalg.solve(G + lam_abs * np.eye(G.shape[0]), T.T @ a), 0)
    result = fi.reconstruct(T, a, method="paper", lam=10.0, max_iter=1)
    np.testing.assert_allclose(result.power, expected, rtol=1e-8, atol=1e-8 * expected.max())
    assert result.lam_absolute == pytest.approx(lam_abs)


def test_paper_fit_never_worsens_with_more_iterations(blur):
    T, b = blur
    a = np.random.default_rng(3).poisson(T @ b).astype(float)
    fits = [np.linalg.norm(a - T @ fi.paper(T, a, lam=10.0, max_iter=k, tol=0.0))
            for k in range(1, 8)]
    assert np.all(np.diff(fits) <= 1e-9 * fits[0])
    # The paper's stopping rule: with tol = 1 % it stops before the iteration limit.
    result = fi.reconstruct(T, a, method="paper", lam=10.0, max_iter=50)
    assert result.converged and result.iterations < 50


def test_backprojection_is_off_in_scale(blocks):
    T, b = blocks
    ratio = fi.total_ratio(fi.backprojection(T, T @ b), b)
    assert not 0.5 < ratio < 1.5
    assert ratio < 1e-3  # T (~1e-3) applied twice


# ------------------------------------------------------------------ NNLS


@pytest.mark.parametrize("lam", [0.0, 1e-3])
def test_nnls_kkt_and_agreement_with_dense_scipy(blocks, lam):
    T, b = blocks
    rng = np.random.default_rng(7)
    a = T @ b + rng.normal(0, 30.0, T.shape[0])  # noise pushes dark elements negative
    weights = 1.0 / (np.abs(T @ b) + 30.0**2)
    b_hat = fi.nnls(T, a, weights=weights, lam=lam)

    Td = T.toarray()
    G = Td.T @ (weights[:, None] * Td)
    lam_abs = lam * np.max(np.diag(G))
    grad = G @ b_hat - Td.T @ (weights * a) + lam_abs * b_hat
    scale = np.max(np.abs(Td.T @ (weights * a)))
    free = b_hat > 0
    assert np.sum(~free) > 5  # the constraint is active somewhere
    assert np.all(b_hat >= 0)
    assert np.max(np.abs(grad[free])) < 1e-8 * scale
    assert np.min(grad[~free]) > -1e-8 * scale

    # Independent route: scipy's Lawson-Hanson on the stacked dense system.
    sw = np.sqrt(weights)
    A = np.vstack([sw[:, None] * Td, np.sqrt(lam_abs) * np.eye(Td.shape[1])])
    y = np.concatenate([sw * a, np.zeros(Td.shape[1])])
    reference, _ = sopt.nnls(A, y)
    np.testing.assert_allclose(b_hat, reference, rtol=0, atol=1e-6 * reference.max())


# ------------------------------------------------------------------ automatic λ


def test_lambda_curves_match_direct_tikhonov(blur):
    T, b = blur
    a = np.random.default_rng(1).poisson(T @ b).astype(float)
    sigma2 = np.maximum(a, 1.0)
    for weighted in (False, True):
        choice = fi.choose_lambda(T, a, method="gcv", sigma2=sigma2, weighted=weighted)
        w = 1.0 / sigma2 if weighted else np.ones_like(a)
        for k in (10, 60, 110):
            b_lam = fi.tikhonov(T, a, lam=choice.lambdas[k],
                                sigma2=sigma2 if weighted else None)
            assert choice.residual_norm2[k] == pytest.approx(np.sum(w * (a - T @ b_lam) ** 2),
                                                             rel=1e-6)
            assert choice.solution_norm2[k] == pytest.approx(np.sum(b_lam**2), rel=1e-6)
        assert np.all(np.diff(choice.residual_norm2) >= -1e-9 * choice.residual_norm2[-1])
        assert np.all(np.diff(choice.solution_norm2) <= 0)


def _oracle_ratios(T, b, rule, method, seeds, **rule_opts):
    grid = np.logspace(-7, 0, 36)
    ratios = []
    for seed in seeds:
        a = np.random.default_rng(seed).poisson(T @ b).astype(float)
        sigma2 = np.maximum(a, 1.0)
        if method == "weighted_lsq":
            best = min(fi.error_l1(fi.weighted_lsq(T, a, sigma2=sigma2, lam=lam), b)
                       for lam in grid)
        else:
            best = min(fi.error_l1(fi.nnls(T, a, lam=lam), b) for lam in grid)
        auto = fi.reconstruct(T, a, method=method, lam_rule=rule, sigma2=sigma2, **rule_opts)
        ratios.append(fi.error_l1(auto.power, b) / best)
    return np.array(ratios)


def test_discrepancy_lambda_near_oracle(blur):
    T, b = blur
    ratios = _oracle_ratios(T, b, "discrepancy", "weighted_lsq", range(10))
    assert np.median(ratios) < 1.2
    assert np.mean(ratios <= 1.5) >= 0.8


def test_gcv_lambda_near_oracle(blur):
    T, b = blur
    seeds = range(10)
    # GCV estimates the image prediction risk ‖T(b_λ − b)‖² and gets it right ...
    grid = np.logspace(-7, 0, 36)
    for seed in seeds:
        a = np.random.default_rng(seed).poisson(T @ b).astype(float)
        risk = [np.sum((T @ (fi.tikhonov(T, a, lam=lam) - b)) ** 2) for lam in grid]
        chosen = fi.choose_lambda(T, a, method="gcv")
        assert np.sum((T @ (fi.tikhonov(T, a, lam=chosen.lam) - b)) ** 2) < 1.5 * min(risk)
    # ... but the flux error wants more damping: standard GCV is within 1.5× of the
    # oracle only about half the time here, modified GCV (gamma = 1.4) mostly.
    plain = _oracle_ratios(T, b, "gcv", "nnls", seeds)
    modified = _oracle_ratios(T, b, "gcv", "nnls", seeds, gamma=1.4)
    assert np.median(plain) < 2.0
    assert np.median(modified) < 1.5
    assert np.max(modified) < 2.5


def test_lcurve_picks_interior_lambda(blur):
    T, b = blur
    a = np.random.default_rng(2).poisson(T @ b).astype(float)
    choice = fi.choose_lambda(T, a, method="lcurve")
    assert not choice.at_edge
    assert choice.lambdas[0] < choice.lam < choice.lambdas[-1]


# ------------------------------------------------------------------ uncertainty


def test_sampling_uncertainty_matches_empirical_scatter(blur):
    T, b = blur
    sigma2 = T @ b + 1.0
    lam = 1e-4
    rng = np.random.default_rng(5)
    estimates = np.array([fi.tikhonov(T, T @ b + rng.normal(0, np.sqrt(sigma2)), lam=lam,
                                      sigma2=sigma2) for _ in range(400)])
    empirical = estimates.std(axis=0, ddof=1)
    predicted = fi.uncertainty(T, T @ b, b, sigma2=sigma2, lam=lam, kind="sampling")
    deviation = np.abs(predicted / empirical - 1)
    assert np.median(deviation) < 0.05
    assert np.max(deviation) < 0.15
    # The posterior adds the prior's variance along poorly measured directions.
    posterior = fi.uncertainty(T, T @ b, b, sigma2=sigma2, lam=lam, kind="posterior")
    assert np.all(posterior >= predicted * (1 - 1e-9))


def test_posterior_uncertainty_matches_empirical_when_data_dominate(blocks):
    T, b = blocks
    sigma2 = T @ b + 25.0
    rng = np.random.default_rng(6)
    estimates = np.array([fi.tikhonov(T, T @ b + rng.normal(0, np.sqrt(sigma2)), lam=1e-6,
                                      sigma2=sigma2) for _ in range(400)])
    empirical = estimates.std(axis=0, ddof=1)
    posterior = fi.uncertainty(T, T @ b, b, sigma2=sigma2, lam=1e-6)
    assert np.max(np.abs(posterior / empirical - 1)) < 0.15


# ------------------------------------------------------------------ MLEM


def test_mlem_preserves_counts_and_stays_nonnegative(blur):
    T, b = blur
    a = np.random.default_rng(4).poisson(T @ b).astype(float)
    for n_iter in (1, 7, 300):
        b_hat = fi.mlem(T, a, n_iter=n_iter)
        assert np.all(b_hat >= 0)
        assert np.sum(T @ b_hat) == pytest.approx(np.sum(a), rel=1e-10)

    # Plain MLEM amplifies noise as iterations go on; one-step-late smoothing with a
    # chain adjacency holds the error down.
    n = T.shape[1]
    chain = sp.diags_array([np.ones(n - 1), np.ones(n - 1)], offsets=[-1, 1])
    plain = fi.mlem(T, a, n_iter=2000, rel_tol=0.0)
    smooth = fi.mlem(T, a, n_iter=2000, rel_tol=0.0, smooth=0.01, adjacency=chain)
    assert np.all(smooth >= 0)
    assert fi.error_l1(smooth, b) < 0.6 * fi.error_l1(plain, b)


# ------------------------------------------------------------------ observability, views


def test_unobserved_elements_are_nan(blocks):
    T, b = blocks
    scale = np.ones(T.shape[1])
    scale[3] = 0.0  # invisible element
    scale[8] = 1e-6  # tiny column: below rel_threshold
    T = sp.csr_array(T @ sp.diags_array(scale))
    a = T @ b
    mask = fi.observed_mask(T)
    assert not mask[3] and not mask[8] and mask.sum() == T.shape[1] - 2
    sigma2 = a + 1.0
    for method, kw in [("backprojection", {}), ("paper", {"lam": 1e-6}), ("tikhonov", {}),
                       ("nnls", {}), ("weighted_lsq", {"sigma2": sigma2}),
                       ("mlem", {"n_iter": 5})]:
        result = fi.reconstruct(T, a, method=method, **kw)
        assert np.isnan(result.power[[3, 8]]).all(), method
        assert np.isfinite(result.power[mask]).all(), method
        assert not result.observed[3] and not result.observed[8]
    result = fi.reconstruct(T, a, method="nnls", sigma2=sigma2)
    assert np.isnan(result.sigma[[3, 8]]).all() and np.isfinite(result.sigma[mask]).all()
    # Counted as a zero estimate over all elements, skipped over observed ones.
    missed = (b[3] + b[8]) / b.sum()
    assert fi.error_l1(result.power, b) == pytest.approx(missed, abs=1e-9)
    assert fi.error_l1(result.power, b, observed_only=True) == pytest.approx(0, abs=1e-9)


def test_stacked_views_see_what_each_view_misses(blocks):
    T, b = blocks
    half = T.shape[1] // 2
    left = sp.csr_array(T.multiply(np.r_[np.ones(half), np.zeros(T.shape[1] - half)]))
    right = sp.csr_array(T.multiply(np.r_[np.zeros(half), np.ones(T.shape[1] - half)]))
    assert not fi.observed_mask(left)[half:].any()
    T_joint, a_joint = fi.stack_views([left, right], [left @ b, right @ b])
    assert T_joint.shape == (2 * T.shape[0], T.shape[1])
    assert fi.error_l1(fi.nnls(T_joint, a_joint), b) < 1e-9


# ------------------------------------------------------------------ metrics and input


def test_metrics_by_hand():
    b_true = np.array([1.0, 2.0, 3.0, 4.0])
    b_hat = np.array([1.0, 2.5, np.nan, 4.0])
    assert fi.error_l1(b_hat, b_true) == pytest.approx(3.5 / 10)
    assert fi.error_l1(b_hat, b_true, observed_only=True) == pytest.approx(0.5 / 7)
    assert fi.total_ratio(b_hat, b_true) == pytest.approx(7.5 / 10)
    assert fi.total_ratio(b_hat, b_true, observed_only=True) == pytest.approx(7.5 / 7)


def test_bad_input_raises_value_error_naming_the_quantity(blocks):
    T, b = blocks
    a = T @ b
    with pytest.raises(ValueError, match="image a"):
        fi.nnls(T, a[:-1])
    with pytest.raises(ValueError, match="lam"):
        fi.paper(T, a, lam=-1.0)
    with pytest.raises(ValueError, match="lam"):
        fi.reconstruct(T, a, method="nnls", lam=-0.1)
    with pytest.raises(ValueError, match="transfer matrix T"):
        fi.nnls(-T, a)
    with pytest.raises(ValueError, match="sigma2"):
        fi.weighted_lsq(T, a, sigma2=np.zeros_like(a))
    with pytest.raises(ValueError, match="sigma2"):
        fi.reconstruct(T, a, method="weighted_lsq")
    with pytest.raises(ValueError, match="method"):
        fi.reconstruct(T, a, method="art")
    with pytest.raises(ValueError, match="lam_rule"):
        fi.reconstruct(T, a, method="nnls", lam=1.0, lam_rule="gcv")
    with pytest.raises(ValueError, match="sigma2"):
        fi.choose_lambda(T, a, method="discrepancy")
    with pytest.raises(ValueError, match="non-negative"):
        fi.mlem(T, a - 1e9)
    with pytest.raises(ValueError, match="adjacency"):
        fi.mlem(T, a, smooth=1.0)
    with pytest.raises(ValueError, match="b_hat and b_true"):
        fi.error_l1(b[:-1], b)


def test_duplicate_columns_are_reported_undetermined(blocks):
    T, b = blocks
    dense = T.toarray()
    dense[:, 5] = dense[:, 4]  # two elements the cameras cannot tell apart
    T2 = sp.csr_array(dense)
    a = T2 @ b
    with pytest.raises(ValueError, match="singular"):
        fi.tikhonov(T2, a, lam=0.0)
    sigma = fi.uncertainty(T2, a, b, sigma2=a + 1.0, lam=0.0)
    assert np.isinf(sigma[[4, 5]]).all() and np.isfinite(np.delete(sigma, [4, 5])).all()
    b_hat = fi.nnls(T2, a)  # still solvable: only the sum of the pair is determined
    assert b_hat[4] + b_hat[5] == pytest.approx(b[4] + b[5], rel=1e-6)
    assert fi.error_l1(np.delete(b_hat, [4, 5]), np.delete(b, [4, 5])) < 1e-6
