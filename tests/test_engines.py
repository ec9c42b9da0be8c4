"""The formulas written once (issue 23, "one engine per idea") against closed forms written out
here: a triangle's area, a rotation about an axis, the graph Laplacian of the smoothness prior
and MLEM's penalty, and the uncertainty of the Tikhonov family."""

import numpy as np
import pytest
import scipy.sparse as sp

from fluxcli.inverse import regularisation as reg
from fluxcli.inverse.smooth import element_laplacian, exitance_prior, graph_laplacian
from fluxcli.surface.geometry import rotation_matrix, triangle_areas


def test_triangle_areas_closed_forms():
    # a 3-4-5 right triangle (area 6) in the xy plane, the same turned into 3-D, and a sliver
    tri = np.array([[[0, 0, 0], [3, 0, 0], [0, 4, 0]],
                    [[1, 1, 1], [1, 4, 1], [1, 1, 5]],
                    [[0, 0, 0], [1, 0, 0], [2, 0, 0]]], float)
    np.testing.assert_allclose(triangle_areas(tri), [6.0, 6.0, 0.0], atol=1e-15)
    # an equilateral triangle of side 2: sqrt(3)
    eq = np.array([[[0, 0, 0], [2, 0, 0], [1, np.sqrt(3), 0]]])
    assert triangle_areas(eq)[0] == pytest.approx(np.sqrt(3), rel=1e-15)


def test_rotation_matrix_closed_forms():
    R = rotation_matrix([0, 0, 2.0], 90.0)  # any length of axis
    np.testing.assert_allclose(R @ [1.0, 0, 0], [0, 1.0, 0], atol=1e-15)  # counter-clockwise seen from +z
    axis = np.array([1.0, 2.0, -0.5])
    R = rotation_matrix(axis, 37.0)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-15)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-14)
    np.testing.assert_allclose(R @ axis, axis, atol=1e-14)  # the axis stays put
    np.testing.assert_allclose(rotation_matrix(axis, 20.0) @ rotation_matrix(axis, 17.0), R, atol=1e-14)
    # the angle between a vector normal to the axis and its image is the angle turned
    n = np.cross(axis, [0, 0, 1.0])
    assert np.degrees(np.arccos(n @ R @ n / (n @ n))) == pytest.approx(37.0, abs=1e-9)


def _chain(n, rng):
    """A ring of n elements with random symmetric edge weights, as a dense matrix."""
    A = np.zeros((n, n))
    for i in range(n):
        j = (i + 1) % n
        A[i, j] = A[j, i] = rng.uniform(0.5, 2.0)
    return A


def test_graph_laplacian_is_the_edge_penalty():
    rng = np.random.default_rng(1)
    A = _chain(9, rng)
    mask = np.ones(9, bool)
    mask[4] = False  # an unobserved element: its two edges are dropped
    b = rng.normal(size=9)
    want = sum(A[i, j] * (b[i] - b[j]) ** 2 for i in range(9) for j in range(i + 1, 9) if mask[i] and mask[j])
    for L in (graph_laplacian(sp.csr_array(A), mask), graph_laplacian(A, mask, dense=True)):
        L = L.toarray() if sp.issparse(L) else L
        assert L.shape == (8, 8)
        np.testing.assert_allclose(L.sum(axis=1), 0.0, atol=1e-14)
        assert b[mask] @ L @ b[mask] == pytest.approx(want, rel=1e-13)
    # the prior: unit max diagonal plus the ridge, and on exitance J = b/S for unequal areas
    S = rng.uniform(1.0, 3.0, size=9)
    Lp = element_laplacian(A, mask, ridge=0.0)
    assert Lp.diagonal().max() == pytest.approx(1.0)
    J = b[mask] / S[mask]
    R = exitance_prior(A, mask, S, ridge=0.0)
    bs = b[mask]
    assert bs @ R @ bs == pytest.approx(S[mask].mean() ** 2 * (J @ Lp @ J), rel=1e-12)


def test_graph_laplacian_refuses_an_asymmetric_adjacency():
    A = np.zeros((3, 3))
    A[0, 1] = 1.0
    with pytest.raises(ValueError, match="symmetric"):
        graph_laplacian(A, np.ones(3, bool))


@pytest.fixture
def problem():
    rng = np.random.default_rng(3)
    T = sp.random(60, 12, density=0.4, random_state=4, data_rvs=lambda k: rng.uniform(0.1, 1.0, k)).tocsr()
    T = sp.csr_array(T + sp.eye(60, 12) * 0.5)  # every element seen
    sigma2 = rng.uniform(0.5, 3.0, size=60)
    return T, sigma2


@pytest.mark.parametrize("weighted", [True, False])
def test_uncertainty_is_the_tikhonov_covariance_written_out(problem, weighted):
    """The engine's sigma against H⁻¹ K H⁻¹ (sampling) and H⁻¹ (posterior), with numpy's inverse."""
    T, sigma2 = problem
    Td = T.toarray()
    W = np.diag(1 / sigma2) if weighted else np.eye(len(sigma2))
    G = Td.T @ W @ Td
    lam = 0.03
    H = G + lam * np.diag(G).max() * np.eye(12)
    Hi = np.linalg.inv(H)
    K = Td.T @ W @ np.diag(sigma2) @ W @ Td
    a = np.zeros(60)
    b = np.ones(12)
    got = reg.uncertainty(T, a, b, sigma2=sigma2, lam=lam, weighted=weighted, kind="sampling")
    np.testing.assert_allclose(got, np.sqrt(np.diag(Hi @ K @ Hi)), rtol=1e-9)
    if weighted:
        got = reg.uncertainty(T, a, b, sigma2=sigma2, lam=lam, weighted=True, kind="posterior")
        np.testing.assert_allclose(got, np.sqrt(np.diag(Hi)), rtol=1e-9)
    # a region's total: wᵀ C w with the covariances, not the sum of the per-element variances
    w = np.zeros(12)
    w[[2, 3, 7]] = 1.0
    cov = reg.linear_covariance(T, sigma2, lam, weighted)
    assert cov.variance_of(w) == pytest.approx(w @ Hi @ K @ Hi @ w, rel=1e-9)
