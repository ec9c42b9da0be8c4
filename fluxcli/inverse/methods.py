"""Reconstruction of the surface flux per element from camera images.

The forward model is ``a = T b + noise``: ``T`` (n_pixels, n_elements) is the
dimensionless, non-negative transfer matrix, ``a`` (n_pixels,) the image in photons and
``b`` (n_elements,) the flux per surface element in photons, ``b ≥ 0``. Several poses or
views are reconstructed jointly by stacking their rows (:func:`stack_views`).

Only *observed* elements are solved for (:func:`observed_mask`); every method returns
NaN, not zero, for the others, because "the cameras cannot see it" is not "it is dark".

Methods
-------
- :func:`backprojection` — ``Tᵀa``, the older method; wrong in scale by orders of
  magnitude (``T`` is applied twice), kept for comparison.
- :func:`paper` — the paper's iterative non-negative Tikhonov scheme.
- :func:`tikhonov` — the linear (unconstrained) Tikhonov estimator.
- :func:`nnls` — exact non-negative (optionally weighted, regularised) least squares.
- :func:`weighted_lsq` — :func:`nnls` with weights ``1/σ²`` per pixel.
- :func:`mlem` — Poisson maximum likelihood by EM, optional one-step-late smoothing.
- :func:`reconstruct` — one entry point returning a :class:`Result`.

Regularisation ``lam`` is always given in the paper's relative units:
``λ̃ = lam × max diag(TᵀWT)`` (``W = I`` unless the method is weighted), so the same
``lam`` means the same relative damping whatever the scale of ``T``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as sla
import scipy.optimize as sopt
import scipy.sparse as sp

from fluxcli.inverse import _common as c
from fluxcli.inverse.smooth import exitance_scaling, graph_laplacian, on_exitance
from fluxcli.errors import InputError

__all__ = [
    "METHODS",
    "REGISTRY",
    "observation_classes",
    "headline_total",
    "Headline",
    "register",
    "Result",
    "backprojection",
    "mlem",
    "nnls",
    "observed_mask",
    "paper",
    "reconstruct",
    "stack_views",
    "tikhonov",
    "weighted_lsq",
]



# --------------------------------------------------------------------------- helpers


def observed_mask(T, *, rel_threshold: float = c.DEFAULT_REL_THRESHOLD) -> np.ndarray:
    """Elements that the cameras see well enough to reconstruct.

    Parameters
    ----------
    T : scipy.sparse array or ndarray, shape (n_pixels, n_elements)
        Transfer matrix, dimensionless, ≥ 0.
    rel_threshold : float, optional
        An element is observed when its column sum (total sensitivity) exceeds
        ``rel_threshold`` × the largest column sum.

    Returns
    -------
    ndarray of bool, shape (n_elements,)
    """
    return c.observed(c.as_transfer(T), rel_threshold)


def stack_views(transfers, images_photons):
    """Stack several poses / views into one joint problem.

    Parameters
    ----------
    transfers : sequence of sparse arrays, each shape (n_pixels_k, n_elements)
        One transfer matrix per view, all over the same surface elements.
    images_photons : sequence of ndarray, each shape (n_pixels_k,)
        The matching images in photons.

    Returns
    -------
    T : scipy.sparse.csr_array, shape (Σ n_pixels_k, n_elements)
    a : ndarray, shape (Σ n_pixels_k,)
    """
    transfers = [c.as_transfer(t) for t in transfers]
    images = list(images_photons)
    if not transfers or len(transfers) != len(images):
        raise InputError(
            f"stack_views needs one image per transfer matrix, got {len(transfers)} "
            f"transfer matrices and {len(images)} images."
        )
    n_elements = transfers[0].shape[1]
    for k, t in enumerate(transfers):
        if t.shape[1] != n_elements:
            raise InputError(
                f"transfer matrix {k} has {t.shape[1]} elements (columns), view 0 has "
                f"{n_elements}: all views must share the surface elements."
            )
    a = np.concatenate(
        [c.as_pixels(img, t.shape[0], f"image {k}") for k, (t, img) in enumerate(zip(transfers, images))]
    )
    return sp.csr_array(sp.vstack(transfers, format="csr")), a


def _prepare(T, a, rel_threshold):
    T = c.as_transfer(T)
    a = c.as_pixels(a, T.shape[0], "image a (photons)")
    mask = c.observed(T, rel_threshold)
    return T, a, mask, sp.csr_array(T[:, mask])


def _weights_from_sigma2(sigma2, n_pixels):
    sigma2 = c.as_pixels(sigma2, n_pixels, "noise variance sigma2 (photons²)", positive=True,
                         allow_scalar=True)
    return 1.0 / sigma2


# ----------------------------------------------------------------- private solvers
# Each takes the observed columns only and returns (b_observed, iterations, converged,
# lam_absolute).


def _backprojection(T_obs, a):
    return np.asarray(T_obs.T @ a, dtype=np.float64), 1, True, 0.0


def _tikhonov(T_obs, a, lam, weights):
    G, g = c.normal_equations(T_obs, a, weights)
    lam_abs = lam * c.lam_scale(G)
    cf = c.cholesky(G + lam_abs * np.eye(G.shape[0]), "TᵀWT + λ̃I")
    return sla.cho_solve(cf, g, check_finite=False), 1, True, lam_abs


def _paper(T_obs, a, lam, max_iter, tol):
    G, g = c.normal_equations(T_obs, a, None)
    lam_abs = lam * c.lam_scale(G)
    cf = c.cholesky(G + lam_abs * np.eye(G.shape[0]), "TᵀT + λ̃I")

    b = np.maximum(sla.cho_solve(cf, g, check_finite=False), 0.0)
    r = a - T_obs @ b
    fit = np.linalg.norm(r)
    iterations, converged = 1, False
    while iterations < max_iter and fit > 0:
        delta = sla.cho_solve(cf, T_obs.T @ r, check_finite=False)
        b_new = np.maximum(b + delta, 0.0)
        r_new = a - T_obs @ b_new
        fit_new = np.linalg.norm(r_new)
        iterations += 1
        improvement = (fit - fit_new) / fit
        if improvement >= 0:
            b, r, fit = b_new, r_new, fit_new
        # A worse fit (possible once clipping bites) ends the loop at the better iterate.
        if improvement < tol:
            converged = True
            break
    if fit == 0:
        converged = True
    return b, iterations, converged, lam_abs


def _nnls(T_obs, a, weights, lam):
    G, g = c.normal_equations(T_obs, a, weights)
    lam_abs = lam * c.lam_scale(G)
    H = G + lam_abs * np.eye(G.shape[0])
    # ½‖W^½(Tb − a)‖² + ½λ̃‖b‖² = ½‖Rb − d‖² + const with RᵀR = H, Rᵀd = g: the same
    # minimiser over b ≥ 0, but an n_obs × n_obs problem instead of n_pixels × n_obs.
    cf = c.try_cholesky(H)
    if cf is not None:
        R = np.triu(cf[0])
        d = sla.solve_triangular(R, g, trans="T", check_finite=False)
    else:
        # Singular H (lam = 0, rank-deficient T): use the square root from eigh and
        # drop the null space, where g has no component anyway (g ∈ range(Tᵀ)).
        w, V = np.linalg.eigh(H)
        keep = w > w.max() * H.shape[0] * np.finfo(float).eps
        sw = np.sqrt(w[keep])
        R = sw[:, None] * V[:, keep].T
        d = (V[:, keep].T @ g) / sw
    try:
        b, _ = sopt.nnls(R, d, maxiter=50 * H.shape[0])
    except RuntimeError as exc:  # pragma: no cover - Lawson-Hanson essentially always ends
        raise InputError(
            "non-negative least squares did not converge: the problem is too badly "
            "conditioned; use lam > 0."
        ) from exc
    return b, 1, True, lam_abs


def _mlem(T_obs, a, n_iter, background, smooth, laplacian, rel_tol):
    sens = c.column_sums(T_obs)
    flat = max(np.sum(a - background), 0.0) / np.sum(sens)
    b = np.full(T_obs.shape[1], flat if flat > 0 else np.finfo(float).tiny)
    # Relative smoothing: smooth = 1 lets a neighbour difference of the flat flux level
    # change the denominator by the largest sensitivity.
    beta = smooth * sens.max() / flat if flat > 0 else 0.0
    converged = False
    iterations = 0
    for iterations in range(1, n_iter + 1):
        model = T_obs @ b + background
        ratio = np.divide(a, model, out=np.zeros_like(a), where=model > 0)
        denom = sens
        if smooth > 0:
            # One-step-late (Green 1990): the prior gradient at the current estimate joins
            # the sensitivity. Floored at half the sensitivity so that a steep gradient
            # can neither flip the sign nor blow an element up in one step.
            denom = np.maximum(sens + beta * (laplacian @ b), 0.5 * sens)
        b_new = b * (T_obs.T @ ratio) / denom
        norm = np.linalg.norm(b)
        change = np.linalg.norm(b_new - b) / norm if norm > 0 else 0.0
        b = b_new
        if change < rel_tol:
            converged = True
            break
    return b, iterations, converged, 0.0


# ------------------------------------------------------------------ public methods


def backprojection(T, a, *, rel_threshold: float = c.DEFAULT_REL_THRESHOLD) -> np.ndarray:
    """Backprojection ``b̃ = Tᵀa`` (the older, unnormalised method).

    Parameters
    ----------
    T : scipy.sparse array or ndarray, shape (n_pixels, n_elements)
        Transfer matrix, dimensionless, ≥ 0.
    a : ndarray, shape (n_pixels,)
        Image in photons.
    rel_threshold : float, optional
        See :func:`observed_mask`.

    Returns
    -------
    ndarray, shape (n_elements,)
        ``Tᵀa``; NaN for unobserved elements. Its scale is wrong by roughly the square of
        the typical transfer coefficient (orders of magnitude): only its shape means
        anything.
    """
    _, a, mask, T_obs = _prepare(T, a, rel_threshold)
    return c.scatter(_backprojection(T_obs, a)[0], mask)


def tikhonov(T, a, *, lam: float, sigma2=None,
             rel_threshold: float = c.DEFAULT_REL_THRESHOLD) -> np.ndarray:
    """Linear Tikhonov estimator ``b̃ = (TᵀWT + λ̃I)⁻¹ TᵀWa`` (may be negative).

    Parameters
    ----------
    T : scipy.sparse array or ndarray, shape (n_pixels, n_elements)
        Transfer matrix, dimensionless, ≥ 0.
    a : ndarray, shape (n_pixels,)
        Image in photons.
    lam : float
        Relative regularisation, ``λ̃ = lam × max diag(TᵀWT)``.
    sigma2 : float or ndarray, shape (n_pixels,), optional
        Noise variance per pixel in photons²; if given, ``W = diag(1/sigma2)``,
        otherwise ``W = I``.
    rel_threshold : float, optional
        See :func:`observed_mask`.

    Returns
    -------
    ndarray, shape (n_elements,)
        Photons per element; NaN for unobserved elements.
    """
    lam = c.check_nonneg_number(lam, "lam")
    _, a, mask, T_obs = _prepare(T, a, rel_threshold)
    w = None if sigma2 is None else _weights_from_sigma2(sigma2, a.size)
    return c.scatter(_tikhonov(T_obs, a, lam, w)[0], mask)


def paper(T, a, *, lam: float = 10.0, max_iter: int = 10, tol: float = 0.01,
          rel_threshold: float = c.DEFAULT_REL_THRESHOLD) -> np.ndarray:
    """The paper's iterative, regularised, non-negative least squares.

    Solve ``b̃ = (TᵀT + λ̃I)⁻¹ Tᵀa`` with ``λ̃ = lam × max diag(TᵀT)`` and set negative
    entries to zero; then repeat with the residual ``r = a − T b̃``:
    ``b̃ ← max(b̃ + (TᵀT + λ̃I)⁻¹ Tᵀr, 0)``, until the fit ``‖a − T b̃‖₂`` improves by
    less than ``tol`` (relative) between iterations, or ``max_iter`` solves were made.

    Parameters
    ----------
    T : scipy.sparse array or ndarray, shape (n_pixels, n_elements)
        Transfer matrix, dimensionless, ≥ 0.
    a : ndarray, shape (n_pixels,)
        Image in photons.
    lam : float, optional
        Relative regularisation (paper: 10 in 2-D, 0.1 for noiseless 3-D, 1 for real
        data).
    max_iter : int, optional
        Maximum number of solves, the first one included (paper: 5 or 10).
    tol : float, optional
        Relative improvement of the fit below which iteration stops (paper: 1 %).
    rel_threshold : float, optional
        See :func:`observed_mask`.

    Returns
    -------
    ndarray, shape (n_elements,)
        Photons per element, ≥ 0; NaN for unobserved elements.

    Notes
    -----
    Interpretation of the paper's text: "the fit" is the Euclidean norm of the image
    residual; an iteration counts one solve, so ``max_iter=1`` is clipped Tikhonov;
    ``TᵀT + λ̃I`` is factorised once (Cholesky) and reused. Without clipping this is
    iterated Tikhonov, which tends to the unregularised least-squares solution as the
    iterations go on, so ``max_iter`` and ``tol`` regularise as much as ``lam`` does. If
    an update makes the fit worse (possible after clipping) the previous iterate is kept
    and iteration stops.
    """
    b, *_ = _paper_info(T, a, lam=lam, max_iter=max_iter, tol=tol,
                        rel_threshold=rel_threshold)
    return b


def _paper_info(T, a, *, lam, max_iter, tol, rel_threshold):
    lam = c.check_nonneg_number(lam, "lam")
    max_iter = c.check_positive_int(max_iter, "max_iter")
    tol = c.check_nonneg_number(tol, "tol")
    _, a, mask, T_obs = _prepare(T, a, rel_threshold)
    b, it, conv, lam_abs = _paper(T_obs, a, lam, max_iter, tol)
    return c.scatter(b, mask), it, conv, lam_abs


def nnls(T, a, *, weights=None, lam: float = 0.0,
         rel_threshold: float = c.DEFAULT_REL_THRESHOLD) -> np.ndarray:
    """Non-negative least squares, optionally weighted and Tikhonov-regularised.

    Minimises ``‖W^½(T b − a)‖² + λ̃‖b‖²`` over ``b ≥ 0`` exactly (Lawson–Hanson active
    set, :func:`scipy.optimize.nnls`, on the equivalent n_obs × n_obs problem built from
    the Cholesky factor of ``TᵀWT + λ̃I``).

    Parameters
    ----------
    T : scipy.sparse array or ndarray, shape (n_pixels, n_elements)
        Transfer matrix, dimensionless, ≥ 0.
    a : ndarray, shape (n_pixels,)
        Image in photons.
    weights : ndarray, shape (n_pixels,), optional
        ``W = diag(weights)``, ≥ 0 (1/photons²); default all ones.
    lam : float, optional
        Relative regularisation, ``λ̃ = lam × max diag(TᵀWT)``.
    rel_threshold : float, optional
        See :func:`observed_mask`.

    Returns
    -------
    ndarray, shape (n_elements,)
        Photons per element, ≥ 0; NaN for unobserved elements.

    Notes
    -----
    Working with the normal matrix squares the condition number of ``W^½T``; with
    ``lam = 0`` on a badly conditioned ``T`` the solution is accurate only to about
    ``cond(T)² × 1e-16`` relative.
    """
    b, *_ = _nnls_info(T, a, weights=weights, lam=lam, rel_threshold=rel_threshold)
    return b


def _nnls_info(T, a, *, weights, lam, rel_threshold):
    lam = c.check_nonneg_number(lam, "lam")
    _, a, mask, T_obs = _prepare(T, a, rel_threshold)
    if weights is not None:
        weights = c.as_pixels(weights, a.size, "weights", nonnegative=True,
                              allow_scalar=True)
    b, it, conv, lam_abs = _nnls(T_obs, a, weights, lam)
    return c.scatter(b, mask), it, conv, lam_abs


def weighted_lsq(T, a, *, sigma2, lam: float = 0.0,
                 rel_threshold: float = c.DEFAULT_REL_THRESHOLD) -> np.ndarray:
    """Noise-weighted non-negative least squares: :func:`nnls` with ``W = 1/σ²``.

    Parameters
    ----------
    T : scipy.sparse array or ndarray, shape (n_pixels, n_elements)
        Transfer matrix, dimensionless, ≥ 0.
    a : ndarray, shape (n_pixels,)
        Image in photons.
    sigma2 : float or ndarray, shape (n_pixels,)
        Noise variance per pixel in photons², > 0; e.g. ``max(a, 0) + read_noise²``.
    lam : float, optional
        Relative regularisation, ``λ̃ = lam × max diag(TᵀWT)``.
    rel_threshold : float, optional
        See :func:`observed_mask`.

    Returns
    -------
    ndarray, shape (n_elements,)
        Photons per element, ≥ 0; NaN for unobserved elements.
    """
    T_ = c.as_transfer(T)
    w = _weights_from_sigma2(sigma2, T_.shape[0])
    return nnls(T_, a, weights=w, lam=lam, rel_threshold=rel_threshold)


def mlem(T, a, *, n_iter: int = 200, background=0.0, smooth: float = 0.0,
         adjacency=None, rel_tol: float = 1e-6,
         rel_threshold: float = c.DEFAULT_REL_THRESHOLD) -> np.ndarray:
    """Poisson maximum likelihood by expectation maximisation (MLEM).

    ``b ← b · Tᵀ(a / (T b + background)) / (Tᵀ1 + β L b)``, started from the flat
    estimate ``b̄ = Σ(a − background) / ΣTᵀ1``, where ``L`` is the graph Laplacian of
    ``adjacency`` and ``β = smooth × max(Tᵀ1) / b̄`` (one-step-late smoothing, Green
    1990; ``smooth = 0`` is plain MLEM).

    Parameters
    ----------
    T : scipy.sparse array or ndarray, shape (n_pixels, n_elements)
        Transfer matrix, dimensionless, ≥ 0.
    a : ndarray, shape (n_pixels,)
        Image in photons, ≥ 0 (counts).
    n_iter : int, optional
        Maximum number of EM iterations.
    background : float or ndarray, shape (n_pixels,), optional
        Known additive background in photons per pixel, ≥ 0.
    smooth : float, optional
        Relative, dimensionless weight of the quadratic smoothness penalty ``½ β bᵀLb``
        added to the negative log-likelihood (``β`` above, in 1/photons); 0 disables
        smoothing. One-step-late is stable only for small values (≲ 0.1).
    adjacency : scipy.sparse array, shape (n_elements, n_elements), optional
        Symmetric, non-negative element adjacency weights; required when ``smooth > 0``.
        Edges to unobserved elements are dropped.
    rel_tol : float, optional
        Stop when ``‖b_new − b‖ / ‖b‖`` falls below this.
    rel_threshold : float, optional
        See :func:`observed_mask`.

    Returns
    -------
    ndarray, shape (n_elements,)
        Photons per element, ≥ 0; NaN for unobserved elements.

    Notes
    -----
    Without background and smoothing every iteration preserves the counts seen by the
    observed elements, ``Σ T b = Σ a`` over pixels that see some observed element.
    """
    b, *_ = _mlem_info(T, a, n_iter=n_iter, background=background, smooth=smooth,
                       adjacency=adjacency, rel_tol=rel_tol, rel_threshold=rel_threshold)
    return b


def _mlem_info(T, a, *, n_iter, background, smooth, adjacency, rel_tol, rel_threshold):
    n_iter = c.check_positive_int(n_iter, "n_iter")
    smooth = c.check_nonneg_number(smooth, "smooth")
    rel_tol = c.check_nonneg_number(rel_tol, "rel_tol")
    _, a, mask, T_obs = _prepare(T, a, rel_threshold)
    if np.any(a < 0):
        raise InputError("image a (photons) must be non-negative for MLEM (Poisson counts).")
    background = c.as_pixels(background, a.size, "background (photons)", nonnegative=True,
                             allow_scalar=True)
    laplacian = None
    if smooth > 0:
        if adjacency is None:
            raise InputError("smooth > 0 needs an element adjacency matrix (adjacency=...).")
        laplacian = graph_laplacian(adjacency, mask)
    b, it, conv, lam_abs = _mlem(T_obs, a, n_iter, background, smooth, laplacian, rel_tol)
    return c.scatter(b, mask), it, conv, lam_abs


# ------------------------------------------------------------------- entry point


@dataclass(frozen=True)
class Result:
    """A reconstruction and what is needed to judge it.

    Attributes
    ----------
    power : ndarray, shape (n_elements,)
        Reconstructed flux in photons per element; NaN for unobserved elements.
    observed : ndarray of bool, shape (n_elements,)
        Elements that were solved for (see :func:`observed_mask`).
    sigma : ndarray, shape (n_elements,)
        Standard deviation of ``power`` under noise, in photons per element: the
        ``kind="sampling"`` linear approximation of :func:`fluxcli.inverse.uncertainty`
        (it excludes the regularisation bias). NaN where unobserved, or everywhere when
        ``sigma2`` was not given or the method is backprojection.
    fitted : ndarray, shape (n_pixels,)
        Model image ``T b̃`` in photons (unobserved elements contribute nothing).
    residual : ndarray, shape (n_pixels,)
        ``a − T b̃`` in photons.
    method : str
        One of :data:`METHODS`.
    lam : float
        Relative regularisation used (0 for methods without one).
    lam_absolute : float
        ``λ̃ = lam × max diag(TᵀWT)``.
    iterations : int
        Solves or EM iterations made (1 for direct solvers).
    converged : bool
        Whether the method's stopping criterion was met before its iteration limit.
    lam_choice : LambdaChoice, spectral.Choice or None
        The λ-selection curve when λ was chosen automatically.
    chi2_per_pixel : float
        ``Σ (a − T b̃)²/σ²(T b̃) / m`` under the noise model (NaN without one).
    warnings : tuple of str
        What the solve detected and the user must know (λ at the edge of its range,
        χ²/pixel far from 1, a total that depends on λ, …). Never silent.
    observation : ndarray of int8, shape (n_elements,)
        :data:`UNOBSERVED` (0), :data:`POORLY_OBSERVED` (1) or :data:`WELL_OBSERVED` (2),
        see :func:`observation_classes`.
    """

    power: np.ndarray
    observed: np.ndarray
    sigma: np.ndarray
    fitted: np.ndarray
    residual: np.ndarray
    method: str
    lam: float
    lam_absolute: float
    iterations: int
    converged: bool
    lam_choice: object = None
    chi2_per_pixel: float = float("nan")
    warnings: tuple = ()
    observation: np.ndarray | None = None
    sigma_groups: np.ndarray | None = None
    # variance_of(weights over the unknowns): wᵀCw of a linear functional (fluxcli.inverse.covariance)
    covariance: object = field(default=None, compare=False, repr=False)

    @property
    def well_observed(self) -> np.ndarray:
        """Observed elements the data pin down (not :data:`POORLY_OBSERVED`)."""
        return self.observed if self.observation is None else self.observation == WELL_OBSERVED


UNOBSERVED, POORLY_OBSERVED, WELL_OBSERVED = 0, 1, 2
POOR_SHARE_WARNING = 0.10  # warn when poorly observed elements hold more of the total than this


def observation_classes(T, power, sigma, *, adjacency=None, areas=None, rel_threshold: float = c.DEFAULT_REL_THRESHOLD,
                        neighbour_fraction: float = 0.1, per_area_fraction: float = 0.25,
                        sigma_floor_fraction: float = 0.01) -> np.ndarray:
    """Unobserved / poorly observed / well observed, per element.

    - unobserved (0): column sum ≤ ``rel_threshold`` × the largest (not solved for, NaN);
    - poorly observed (1): solved for, but the data cannot tell it from its neighbours:
      its column sum is below ``neighbour_fraction`` × the largest column sum among the
      elements it touches, or (with ``areas``) its sensitivity per unit area is below
      ``per_area_fraction`` × the median over observed elements (the silhouette band, seen
      edge-on and imaged onto a sliver of a pixel: cos θ ≲ 0.25), or its σ is at least its
      value while also above ``sigma_floor_fraction`` of the largest value (a dark element
      known to be dark is well observed);
    - well observed (2): the rest.

    Parameters
    ----------
    T : sparse (n_pixels, n_elements), dimensionless.
    power, sigma : (n_elements,) photons (NaN where unobserved / unknown).
    adjacency : (n_elements, n_elements) sparse, nonzero where elements touch; without it
        only the σ test applies.

    Returns
    -------
    ndarray of int8, shape (n_elements,)
    """
    T = c.as_transfer(T)
    sums = c.column_sums(T)
    seen = sums > rel_threshold * sums.max()
    poor = np.zeros(seen.size, bool)
    if adjacency is not None:
        A = sp.csr_array(adjacency, dtype=np.float64)
        A = sp.csr_array(A + sp.eye_array(A.shape[0], format="csr"))
        # largest column sum in each element's closed neighbourhood
        best = np.array([sums[A.indices[A.indptr[j]:A.indptr[j + 1]]].max() for j in range(A.shape[0])])
        poor |= sums < neighbour_fraction * best
    if areas is not None and seen.any():
        per_area = sums / np.maximum(np.asarray(areas, float), 1e-300)
        poor |= per_area < per_area_fraction * np.median(per_area[seen])
    p = np.asarray(power, float)
    sg = np.asarray(sigma, float)
    top = np.nanmax(np.where(seen, p, np.nan)) if np.any(seen & np.isfinite(p)) else 0.0
    with np.errstate(invalid="ignore"):
        poor |= np.isfinite(sg) & (sg >= np.abs(p)) & (sg > sigma_floor_fraction * top)
        poor |= np.isinf(sg)
    out = np.where(seen, np.where(poor, POORLY_OBSERVED, WELL_OBSERVED), UNOBSERVED)
    return out.astype(np.int8)


POOR_SHARE_TEXT = "of the total over observed elements lies in poorly observed elements"


def poor_share_warning(power, observed, observation) -> str | None:
    """The warning when poorly observed elements hold more than :data:`POOR_SHARE_WARNING`
    of the total over observed ones (None otherwise)."""
    total = np.nansum(np.where(observed, power, 0.0))
    share = np.nansum(np.where(observation == POORLY_OBSERVED, power, 0.0)) / total if total > 0 else 0.0
    if share <= POOR_SHARE_WARNING:
        return None
    return (f"{share:.0%} {POOR_SHARE_TEXT} (seen edge-on, or uncertain beyond their value): that total is not "
            "pinned down by the data; the total over well-observed elements is the one to trust.")


# ------------------------------------------------------------------ the method registry


@dataclass
class Problem:
    """What every method receives: the observed columns, the pixels that see them, and the
    noise model."""

    T: sp.csr_array  # (n_pixels, n_elements)
    a: np.ndarray  # (n_pixels,) photons
    mask: np.ndarray  # (n_elements,) observed
    T_obs: sp.csr_array  # (n_pixels, n_obs)
    rows: np.ndarray  # (n_pixels,) pixels that see an observed element
    variance: object  # callable photons -> photons², or None
    sigma2: np.ndarray | None  # fixed variance (n_pixels,) photons², or None
    adjacency: object
    areas: np.ndarray | None
    rel_threshold: float
    groups: object = None  # (parent (n_elements,), n_groups) or sparse (n_groups, n_unknowns): also σ per group

    def sums(self):
        """Sparse (n_groups, n_obs) summing observed unknowns into their groups, or None."""
        if self.groups is None:
            return None
        if sp.issparse(self.groups):  # a weighted map, e.g. vertex unknowns -> elements
            return sp.csr_array(sp.csc_array(self.groups)[:, self.mask])
        parent, n_groups = self.groups
        idx = np.flatnonzero(self.mask)
        return sp.csr_array((np.ones(idx.size), (np.asarray(parent)[idx], np.arange(idx.size))),
                            shape=(n_groups, idx.size))

    @property
    def T_cov(self):
        return sp.csr_array(self.T_obs[self.rows])


@dataclass(frozen=True)
class MethodSpec:
    """A reconstruction method: how to run it and what it accepts."""

    name: str
    solve: object  # (Problem, lam, lam_rule, opts) -> dict
    options: frozenset
    default_lam: float | None  # None: the method takes no λ
    lam_rules: tuple  # the automatic λ rules it takes (empty: no λ from reconstruct.lambda / lambda_rule)
    from_settings: tuple = ()  # (solver option, reconstruct setting) pairs the stage passes on
    dense: bool = False  # forms T'WT (n x n) densely: reconstruct checks the memory before it solves
    nonnegative_data: bool = False  # a Poisson likelihood: bias-subtracted counts below zero are clipped to 0


REGISTRY: dict[str, MethodSpec] = {}


def register(name: str, *, options=(), default_lam=None, lam_rules=(), from_settings=(), dense=False,
             nonnegative_data=False):
    """Add a method to :data:`REGISTRY` (decorator)."""
    def deco(fn):
        REGISTRY[name] = MethodSpec(name, fn, frozenset(options), default_lam, tuple(lam_rules), tuple(from_settings),
                                    dense, nonnegative_data)
        return fn
    return deco


def solver_options(method: str, settings) -> dict:
    """The keyword arguments :func:`reconstruct` takes for ``method`` from reconstruct's settings
    (``settings``: lam — a number or "auto" —, lambda_rule and the spec's ``from_settings``)."""
    spec = REGISTRY[method]
    kw: dict = {}
    if spec.lam_rules:
        if settings.lam == "auto":
            kw["lam_rule"] = settings.lambda_rule
        else:
            kw["lam"] = float(settings.lam)
    for option, key in spec.from_settings:
        kw[option] = getattr(settings, key)
    return kw


_RULE_OPTS = ("lambdas", "tau", "gamma")


@register("backprojection")
def _run_backprojection(P, lam, rule, opts):
    return {"power": _backprojection(P.T_obs, P.a)[0], "no_sigma": True}


def _filtered(P, *, prior, k, tol, lam, rule, opts, weighted, free_level=False, exact=False):
    from fluxcli.inverse.filtered import filtered_solve

    s2 = None if P.sigma2 is None else P.sigma2[P.rows]
    out = filtered_solve(P.T_cov, P.a[P.rows], prior=prior, k=k, tol=tol, lam=lam, rule=rule or "gcv",
                         gamma=opts.get("gamma", 1.0), tau=opts.get("tau", 1.0), lambdas=opts.get("lambdas"),
                         variance=P.variance, sigma2=s2, weighted=weighted, free_level=free_level, sums=P.sums(),
                         exact=exact)
    return {"sigma_groups": out.sigma_sums, "power": out.power, "sigma": out.sigma, "lam": out.lam, "lam_absolute": out.lam_absolute,
            "iterations": out.iterations, "converged": out.converged, "choice": out.choice,
            "chi2": out.chi2_per_pixel, "warnings": out.warnings,
            "covariance": out.covariance}


@register("paper", options=("max_iter", "tol", *_RULE_OPTS), default_lam=10.0, lam_rules=("gcv", "lcurve", "discrepancy"),
          from_settings=(("max_iter", "max_iter"), ("tol", "tol")), dense=True)
def _run_paper(P, lam, rule, opts):
    # the paper's unweighted scheme; an automatic λ is chosen on its own filter factors
    return _filtered(P, prior=None, k=c.check_positive_int(opts.get("max_iter", 10), "max_iter"),
                     tol=c.check_nonneg_number(opts.get("tol", 0.01), "tol"), lam=lam, rule=rule, opts=opts,
                     weighted=False)


SMOOTH_SOLVERS = ("auto", "dense", "matfree")


@register("smooth", options=("adjacency", "n_iter", "solver", *_RULE_OPTS), default_lam=None,
          lam_rules=("gcv", "lcurve", "discrepancy"), from_settings=(("n_iter", "max_iter"),), dense=True)
def _run_smooth(P, lam, rule, opts):
    from fluxcli.inverse.matfree import DENSE_MAX_UNKNOWNS
    from fluxcli.inverse.smooth import exitance_prior

    if P.adjacency is None:
        raise InputError("method 'smooth' needs the element adjacency (adjacency=...).")
    # gamma 1: with weights 1/σ² of the noise model the rule is UPRE, unbiased as it stands
    opts = {"gamma": 1.0} | opts
    solver = opts.get("solver", "auto")
    if solver not in SMOOTH_SOLVERS:
        raise InputError(f"solver must be one of {', '.join(SMOOTH_SOLVERS)}; got {solver!r}.")
    if solver == "matfree" or (solver == "auto" and int(P.mask.sum()) > DENSE_MAX_UNKNOWNS):
        return _run_smooth_matfree(P, lam, rule, opts)
    R = exitance_prior(P.adjacency, P.mask, P.areas)
    exact = int(P.mask.sum()) <= EXACT_MAX_UNKNOWNS
    return _filtered(P, prior=R, k=c.check_positive_int(opts.get("n_iter", 10), "n_iter"), tol=None, lam=lam,
                     rule=rule, opts=opts, weighted=True, free_level=True, exact=exact)


# Exact non-negative steps (and the λ guard that re-scores picks on them) up to this many unknowns;
# beyond, the clipped steps as before issue 25's fix.  The exact steps cost ~n³ per active-set
# change: on 5 666 vertices (issue 25's mesh) one solve took 7.5 min of CPU against ~100 s clipped,
# and the simulated rig's captured surface (5 576 vertices for 302 elements) went from about a
# minute to many.  Below the cap (every battery case, ≤ ~1 700 vertices) the exact steps cost
# seconds.  Beyond, `unknowns: auto` solves on a basis sized by the elements (`linear_elements`,
# inverse.unknowns.resolve_unknowns), so the default's unknowns stay under this cap up to 2 500
# elements (issue 25's scene: 1 168 elements plus the rim, ~3 s of CPU direct, ~6 s with mirrors).
EXACT_MAX_UNKNOWNS = 2500


def _run_smooth_matfree(P, lam, rule, opts):
    """``smooth`` on sparse matrices only (:mod:`fluxcli.inverse.matfree`): beyond the dense limit."""
    from fluxcli.inverse.matfree import matfree_solve, sparse_exitance_prior

    s2 = None if P.sigma2 is None else P.sigma2[P.rows]
    out = matfree_solve(P.T_cov, P.a[P.rows], prior=sparse_exitance_prior(P.adjacency, P.mask, P.areas),
                        k=c.check_positive_int(opts.get("n_iter", 10), "n_iter"), lam=lam, rule=rule or "gcv",
                        gamma=opts.get("gamma", 1.0), tau=opts.get("tau", 1.0), lambdas=opts.get("lambdas"),
                        variance=P.variance, sigma2=s2, weighted=True, free_level=True, sums=P.sums())
    return {"sigma_groups": out.sigma_sums, "power": out.power, "sigma": out.sigma, "lam": out.lam,
            "lam_absolute": out.lam_absolute, "iterations": out.iterations, "converged": out.converged,
            "choice": out.choice, "chi2": out.chi2_per_pixel, "warnings": out.warnings, "covariance": out.covariance}


def _lam_from_rule(P, lam, rule, opts, weighted):
    if rule is None:
        return lam, None
    from fluxcli.inverse.regularisation import choose_lambda

    s2 = P.sigma2
    if s2 is None and P.variance is not None:  # σ² of a model image: a first unregularised-ish fit
        b0, *_ = _nnls(P.T_obs, P.a, None, 1e-6)
        s2 = P.variance(P.T_obs @ b0)
    choice = choose_lambda(P.T_obs, P.a, method=rule, sigma2=s2, weighted=weighted, rel_threshold=0.0,
                           **{k: v for k, v in opts.items() if k in _RULE_OPTS})
    return choice.lam, choice


@register("tikhonov", options=_RULE_OPTS, default_lam=0.0, lam_rules=("gcv", "lcurve", "discrepancy"), dense=True)
def _run_tikhonov(P, lam, rule, opts):
    lam, choice = _lam_from_rule(P, lam, rule, opts, False)
    b, it, conv, lam_abs = _tikhonov(P.T_obs, P.a, lam, None)
    return {"power": b, "lam": lam, "lam_absolute": lam_abs, "iterations": it, "converged": conv, "choice": choice}


@register("nnls", options=("weights", *_RULE_OPTS), default_lam=0.0, lam_rules=("gcv", "lcurve", "discrepancy"), dense=True)
def _run_nnls(P, lam, rule, opts):
    lam, choice = _lam_from_rule(P, lam, rule, opts, False)
    w = opts.get("weights")
    if w is not None:
        w = c.as_pixels(w, P.a.size, "weights", nonnegative=True, allow_scalar=True)
    b, it, conv, lam_abs = _nnls(P.T_obs, P.a, w, lam)
    return {"power": b, "lam": lam, "lam_absolute": lam_abs, "iterations": it, "converged": conv, "choice": choice}


@register("weighted_lsq", options=_RULE_OPTS, default_lam=0.0, lam_rules=("gcv", "lcurve", "discrepancy"), dense=True)
def _run_weighted_lsq(P, lam, rule, opts):
    if P.sigma2 is None and P.variance is None:
        raise InputError("method 'weighted_lsq' needs the noise variance sigma2 (photons²) or a noise model.")
    if P.sigma2 is not None:
        w = 1.0 / P.sigma2
    else:  # weights from the model image of an unweighted fit, reweighted once
        b0, *_ = _nnls(P.T_obs, P.a, None, 1e-6)
        w = 1.0 / P.variance(P.T_obs @ b0)
    lam, choice = _lam_from_rule(P, lam, rule, opts, True) if P.sigma2 is not None else (
        _lam_from_rule(Problem(**{**P.__dict__, "sigma2": 1.0 / w}), lam, rule, opts, True))
    b, it, conv, lam_abs = _nnls(P.T_obs, P.a, w, lam)
    if P.sigma2 is None:
        b, it, conv, lam_abs = _nnls(P.T_obs, P.a, 1.0 / P.variance(P.T_obs @ b), lam)
    return {"power": b, "lam": lam, "lam_absolute": lam_abs, "iterations": it, "converged": conv, "choice": choice,
            "weighted": True}


@register("mlem", options=("n_iter", "background", "smooth", "adjacency", "rel_tol"), from_settings=(("n_iter", "n_iter"),),
          nonnegative_data=True)
def _run_mlem(P, lam, rule, opts):
    if np.any(P.a < 0):
        raise InputError("image a (photons) must be non-negative for MLEM (Poisson counts).")
    n_iter = c.check_positive_int(opts.get("n_iter", 200), "n_iter")
    smooth = c.check_nonneg_number(opts.get("smooth", 0.0), "smooth")
    rel_tol = c.check_nonneg_number(opts.get("rel_tol", 1e-6), "rel_tol")
    background = c.as_pixels(opts.get("background", 0.0), P.a.size, "background (photons)", nonnegative=True,
                              allow_scalar=True)
    lap = None
    if smooth > 0:
        adjacency = opts.get("adjacency", P.adjacency)
        if adjacency is None:
            raise InputError("smooth > 0 needs an element adjacency matrix (adjacency=...).")
        lap = on_exitance(graph_laplacian(adjacency, P.mask), exitance_scaling(P.areas, P.mask))
    b, it, conv, lam_abs = _mlem(P.T_obs, P.a, n_iter, background, smooth, lap, rel_tol)
    return {"power": b, "iterations": it, "converged": conv, "weighted": True, "lam": 0.0}


METHODS = tuple(REGISTRY)


from fluxcli.inverse._threads import off_main_thread as _off_main_thread  # noqa: E402 (issue 22)

ISOLATE_MIN_UNKNOWNS = 800  # dense solves above this run in a child process (fluxcli.inverse._threads.in_child)
_DENSE_METHODS = ("paper", "tikhonov", "nnls", "weighted_lsq", "smooth")


def _solve_method(spec, P, lam, lam_rule, opts):
    """``spec.solve`` — in a child process for a dense solve of more than ISOLATE_MIN_UNKNOWNS
    unknowns: scipy's LAPACK calls hold the GIL (a generalised ``eigh`` at 6 000 unknowns: a
    minute), and only another process leaves this one free to stop at Ctrl-C or SIGTERM."""
    from fluxcli.inverse import _threads
    from fluxcli.inverse.matfree import DENSE_MAX_UNKNOWNS

    n = int(P.mask.sum())
    matfree = spec.name == "smooth" and (opts.get("solver") == "matfree" or (
        opts.get("solver", "auto") == "auto" and n > DENSE_MAX_UNKNOWNS))
    if spec.name in _DENSE_METHODS and not matfree and n > ISOLATE_MIN_UNKNOWNS:
        return _threads.in_child(spec.solve, P, lam, lam_rule, opts)
    return spec.solve(P, lam, lam_rule, opts)


@_off_main_thread  # Ctrl-C / SIGTERM stop it at once (issue 22)
def reconstruct(T, a, *, method: str, lam: float | None = None, lam_rule: str | None = None,
                sigma2=None, variance=None, adjacency=None, areas=None, groups=None,
                rel_threshold: float = c.DEFAULT_REL_THRESHOLD, **opts) -> Result:
    """Reconstruct the flux per element with one of :data:`METHODS` (:data:`REGISTRY`).

    Parameters
    ----------
    T : scipy.sparse array or ndarray, shape (n_pixels, n_elements)
        Transfer matrix, dimensionless, ≥ 0 (stack views with :func:`stack_views`).
    a : ndarray, shape (n_pixels,)
        Image in photons.
    method : str
        A key of :data:`REGISTRY`: backprojection, paper, smooth, tikhonov, nnls,
        weighted_lsq, mlem.
    lam : float, optional
        Relative regularisation (``λ̃ = lam × max diag TᵀWT``); default 10 for ``paper``,
        0 for the other Tikhonov-family methods, chosen automatically for ``smooth``.
    lam_rule : {"gcv", "lcurve", "discrepancy"}, optional
        Choose ``lam`` automatically (``paper`` and ``smooth`` on the filter factors of
        their own iterated scheme). Not allowed together with ``lam``.
    sigma2 : float or ndarray, shape (n_pixels,), optional
        A fixed noise variance per pixel in photons² (weights, σ, χ²).
    variance : callable, optional
        The noise model (e.g. :meth:`fluxcli.imaging.PhotonNoise.variance`): photons →
        photons², evaluated on model images (iteratively reweighted). Preferred over
        ``sigma2``.
    adjacency : sparse (n_elements, n_elements), optional
        Elements touching: the ``smooth`` prior, MLEM smoothing, and the
        poorly-observed test.
    areas : ndarray, shape (n_elements,), optional
        Element areas in mm²; priors act on exitance ``b/S``.
    groups : (parent, n_groups) or sparse (n_groups, n_elements), optional
        ``parent`` (n_elements,) int: when the unknowns are sub-elements, the element
        each belongs to; or a matrix of weights (e.g. vertex unknowns shared by
        elements); ``Result.sigma_groups`` is then the σ of these sums, with the
        covariances between parts (methods on the spectral engine; else None).
    rel_threshold : float, optional
        See :func:`observed_mask`.
    **opts
        Method options: ``max_iter``, ``tol`` (paper); ``n_iter`` (smooth, mlem);
        ``background``, ``smooth``, ``rel_tol`` (mlem); ``weights`` (nnls); ``lambdas``,
        ``tau``, ``gamma`` (automatic λ).

    Returns
    -------
    Result
    """
    if method not in REGISTRY:
        raise InputError(f"method must be one of {', '.join(REGISTRY)}; got {method!r}.")
    spec = REGISTRY[method]
    T = c.as_transfer(T)
    a = c.as_pixels(a, T.shape[0], "image a (photons)")
    if "adjacency" in opts and adjacency is None:
        adjacency = opts.pop("adjacency")
    unknown = set(opts) - spec.options
    if unknown:
        raise InputError(f"unknown options for method {method!r}: {sorted(unknown)} "
                         f"(it takes {', '.join(sorted(spec.options)) or 'none'}).")
    if lam_rule is not None:
        if lam_rule not in spec.lam_rules:
            raise InputError(f"lam_rule applies to the Tikhonov family, not to method {method!r}.")
        if lam is not None:
            raise InputError("give either lam or lam_rule, not both.")
    elif any(k in opts for k in _RULE_OPTS) and spec.default_lam is not None and method != "smooth":
        raise InputError(f"options {sorted(k for k in opts if k in _RULE_OPTS)} only apply with lam_rule.")
    if lam is not None:
        if spec.default_lam is None and method != "smooth":
            raise InputError(f"method {method!r} takes no lam.")
        lam = c.check_nonneg_number(lam, "lam")
    elif lam_rule is None:
        if method == "smooth":
            lam_rule = "gcv"
        elif spec.default_lam is not None:
            lam = spec.default_lam
    if sigma2 is not None:
        sigma2 = c.as_pixels(sigma2, T.shape[0], "noise variance sigma2 (photons²)", positive=True,
                             allow_scalar=True)
    if areas is not None:
        areas = c.as_elements(areas, T.shape[1], "areas (mm²)")
    mask = c.observed(T, rel_threshold)
    T_obs = sp.csr_array(T[:, mask])
    P = Problem(T, a, mask, T_obs, c.covered_rows(T_obs), variance, sigma2, adjacency, areas, rel_threshold, groups)
    out = _solve_method(spec, P, lam, lam_rule, dict(opts))

    power = c.scatter(out["power"], mask)
    fitted = T @ np.where(mask, power, 0.0)
    var = sigma2 if sigma2 is not None else (variance(fitted) if variance is not None else None)
    chi2 = out.get("chi2", np.nan)
    warnings = list(out.get("warnings", []))
    rows = P.rows
    if var is not None and not np.isfinite(chi2):
        from fluxcli.inverse.filtered import chi2_per_pixel

        chi2 = chi2_per_pixel(a[rows], fitted[rows], var[rows])
    lam_used = out.get("lam", 0.0)
    covariance = out.get("covariance")
    if "sigma" in out:
        sigma = c.scatter(out["sigma"], mask)
    elif var is not None and not out.get("no_sigma"):
        # the scatter of the linear estimator at the method's λ (uncertainty, kind="sampling");
        # MLEM as the weighted λ = 0 estimator (inverse Fisher information at the model image)
        from fluxcli.inverse.regularisation import linear_covariance

        covariance = linear_covariance(T_obs, var, lam_used if method != "mlem" else 0.0, bool(out.get("weighted")))
        sigma = c.scatter(np.sqrt(np.maximum(covariance.variance_of(sp.identity(T_obs.shape[1], format="csr")), 0.0)),
                          mask)
    else:
        sigma = np.full(power.shape, np.nan)
    if covariance is None and var is not None and not out.get("no_sigma"):
        from fluxcli.inverse.covariance import Deferred
        from fluxcli.inverse.regularisation import linear_covariance

        lam_lin, weighted = (lam_used if method != "mlem" else 0.0), bool(out.get("weighted"))
        covariance = Deferred(lambda: linear_covariance(T_obs, var, lam_lin, weighted))  # most runs never ask
    if covariance is not None:
        from fluxcli.inverse.covariance import OnObserved

        covariance = OnObserved(covariance, mask)
    if method != "backprojection":
        observation = observation_classes(T, power, sigma, adjacency=adjacency, areas=areas,
                                          rel_threshold=rel_threshold)
    else:
        observation = np.where(mask, WELL_OBSERVED, UNOBSERVED).astype(np.int8)
    poor = poor_share_warning(power, mask, observation)
    if poor:
        warnings.append(poor)
    return Result(power=power, observed=mask, sigma=sigma, fitted=fitted, residual=a - fitted, method=method,
                  lam=float(lam_used), lam_absolute=float(out.get("lam_absolute", 0.0)),
                  iterations=int(out.get("iterations", 1)), converged=bool(out.get("converged", True)),
                  lam_choice=out.get("choice"), chi2_per_pixel=float(chi2), warnings=tuple(warnings),
                  observation=observation, sigma_groups=out.get("sigma_groups"), covariance=covariance)


# Warnings that say the total over observed elements is not pinned down by the data (their texts
# are written in poor_share_warning, filtered.filtered_solve and spectral.choose).
# ("sits at the edge" is a final pick on the edge; "was at the edge ... widened" and "sat at the edge ... fell back" /
# "sat ...; chose" are picks that were replaced and say so)
UNTRUSTED_TOTAL_MARKERS = (POOR_SHARE_TEXT, "when lambda is halved or doubled", "sits at the edge of the search range")


@dataclass(frozen=True)
class Headline:
    """The one total to print first: over the observed elements, or, when a warning says that
    total is not pinned down, over the well-observed ones, with the reason."""

    photons: float
    over: str  # "observed elements" | "well-observed elements"
    reason: str | None  # why the total over observed elements is not the headline (None: it is)
    total_observed_photons: float

    def line(self, what: str = "total flux") -> str:
        """One console line: the number, what it sums, and (when not the observed total) why."""
        head = f"{what}: {self.photons:.4g} photons over {self.over}"
        if self.reason is None:
            return head
        return (f"{head} (the total over all observed elements, {self.total_observed_photons:.4g}, "
                f"is not pinned down by the data: {self.reason})")


def headline_total(power, observed, well_observed, warnings) -> Headline:
    """The trustworthy total of a reconstruction (issue 25: a plausible wrong total was printed
    first while the warnings below it said it was not determined).

    Parameters
    ----------
    power : (n_elements,) photons, NaN where unobserved.
    observed, well_observed : (n_elements,) bool.
    warnings : the reconstruction's warnings (strings).
    """
    p = np.asarray(power, float)
    total = float(np.nansum(np.where(observed, p, 0.0)))
    well = float(np.nansum(np.where(well_observed, p, 0.0)))
    hits = [w for w in warnings if any(m in w for m in UNTRUSTED_TOTAL_MARKERS)]
    if not hits or not np.any(well_observed):
        return Headline(total, "observed elements", None, total)
    reasons = []
    for w in hits:
        if POOR_SHARE_TEXT in w:
            reasons.append(w.split(" (")[0])  # "26% of the total over observed elements lies in poorly ..."
        elif "halved or doubled" in w:
            reasons.append(w.split(" (")[0].replace("the total changes", "it changes"))
        else:
            reasons.append("lambda sat at the edge of its search range")
    return Headline(well, "well-observed elements", "; ".join(dict.fromkeys(reasons)), total)
