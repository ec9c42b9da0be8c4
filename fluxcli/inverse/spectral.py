"""One spectral-filter engine for the Tikhonov family: λ choice, residuals and uncertainty.

Every regularised linear estimator fluxmap runs is, before clipping, a *filter* in the
generalised eigenbasis of the pair ``(G, R)``, ``G = TᵀWT`` (n_obs, n_obs), ``R`` the
prior's matrix (identity for the paper's ``‖b‖²``, an exitance Laplacian for ``smooth``):

    G V = R V diag(s),   Vᵀ R V = I,   c = Vᵀ TᵀW a,
    b_λ = V diag(f(s)/s) c,

with filter factors ``f = 1 − (λ̃/(s + λ̃))^k`` for ``k`` solves of the iterated scheme
``b ← b + (G + λ̃R)⁻¹TᵀW(a − Tb)`` started from 0 (``k = 1`` is Tikhonov).  From one
eigendecomposition every λ then costs O(n_obs):

- the weighted residual ``‖W^½(a − T b_λ)‖² = ‖r_LS‖² + Σ (1 − f)² c²/s``, with the
  least-squares residual computed explicitly (never ``aᵀWa − …``, which cancels
  catastrophically when the fit is good and then had to be clamped at zero);
- the degrees of freedom ``Σ f`` (GCV), the solution norm (L-curve);
- the covariance of the estimator under noise ``Σ``: ``M TᵀWΣWT Mᵀ`` with
  ``M = V diag(f/s) Vᵀ``; when ``W = Σ⁻¹`` this is ``V diag(f²/s) Vᵀ``.

The rules (:func:`choose`) widen the grid when the pick lands on its edge and say so.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as sla
import scipy.optimize as sopt
import scipy.sparse as sp

from fluxcli.inverse import _common as c
from fluxcli.errors import InputError

RULES = ("gcv", "lcurve", "discrepancy")


class Spectrum:
    """The generalised eigendecomposition of ``(TᵀWT, R)`` and the filter algebra on it.

    Parameters
    ----------
    T_obs : sparse (m, n_obs)
        Observed columns of T restricted to the rows (pixels) used, dimensionless.
    a : (m,) photons.
    weights : (m,) 1/photons², or None for ``W = I``.
    prior : (n_obs, n_obs) symmetric positive definite, or None for the identity.
    noise_weighted : bool
        The weights are ``1/σ²`` of a known noise model (each weighted residual has unit
        variance): GCV then uses the known variance instead of estimating it (UPRE).
    """

    def __init__(self, T_obs, a, weights=None, prior=None, noise_weighted=False):
        self.T = T_obs
        self.a = a
        self.weights = weights
        self.noise_weighted = bool(noise_weighted and weights is not None)
        G, g = c.normal_equations(T_obs, a, weights)
        self.G, self.g = G, g
        self.scale = c.lam_scale(G)
        self.prior = prior
        if prior is None:
            s, V = sla.eigh(G, check_finite=False)
        else:
            s, V = sla.eigh(G, prior, check_finite=False)
        self.s = np.clip(s, 0.0, None)
        self.V = V
        self.coef = V.T @ g
        n = len(self.s)
        self.pos = self.s > max(self.s.max(), 0.0) * n * 10 * np.finfo(float).eps
        b_ls = V[:, self.pos] @ (self.coef[self.pos] / self.s[self.pos])
        r = a - T_obs @ b_ls
        self.rho_ls = float(np.sum(r * r if weights is None else weights * r * r))
        self.m = len(a)

    # ------------------------------------------------------------------ filter algebra
    def factors(self, lam_abs: float, k: int):
        """Filter factors ``f`` and ``f/s`` (finite where ``s → 0``: ``k/λ̃``)."""
        lam_abs = max(float(lam_abs), 1e-300)
        q = lam_abs / (self.s + lam_abs)
        f = -np.expm1(k * np.log(q))  # 1 − q^k without cancellation for q → 1
        with np.errstate(divide="ignore", invalid="ignore"):
            fos = np.where(self.pos, f / np.where(self.pos, self.s, 1.0), k / lam_abs)
        return f, fos

    def curves(self, lam_abs, k: int = 1):
        """Residual ‖W^½r‖², solution norm ‖b‖² and Σf for each λ̃ in ``lam_abs``."""
        lam = np.maximum(np.atleast_1d(np.asarray(lam_abs, dtype=np.float64)), 1e-300)[:, None]
        s, p, c2 = self.s[None, :], self.pos[None, :], self.coef[None, :] ** 2
        f = -np.expm1(k * np.log(lam / (s + lam)))
        with np.errstate(divide="ignore", invalid="ignore"):
            fos = np.where(p, f / np.where(p, s, 1.0), k / lam)
            # filtered-out part of the LS fit comes back as residual; modes the LS
            # solution dropped (s ≈ 0) can only lower it, by the tiny (2 − f) f c²/s
            back = np.where(p, (1 - f) ** 2 * c2 / np.where(p, s, 1.0), -(2 - f) * fos * c2)
        rho = self.rho_ls + back.sum(axis=1)
        B = self.V @ (fos * self.coef[None, :]).T  # (n_obs, n_lambdas)
        eta = np.sum(B * B, axis=0)
        return np.maximum(rho, 0.0), eta, f.sum(axis=1)

    def solution(self, lam_abs: float, k: int = 1) -> np.ndarray:
        """The unclipped filtered estimate b_λ (n_obs,) in photons."""
        _, fos = self.factors(lam_abs, k)
        return self.V @ (fos * self.coef)

    def sigma(self, lam_abs: float, k: int = 1, sigma2=None, sums=None, kind: str = "sampling") -> np.ndarray:
        """Standard deviation (n_obs,) of the filtered estimator under noise, photons.

        ``sigma2`` (m,) is the per-pixel noise variance in photons²; None means the
        weights already are ``1/σ²`` (then the covariance is ``V diag(f²/s) Vᵀ``).
        ``sums`` (n_groups, n_obs), optional: the standard deviation of these sums of
        the estimate instead (sub-elements summed per element, covariances included).
        ``kind``: see :meth:`variance_of`."""
        return np.sqrt(np.maximum(self.variance_of(
            sp.identity(len(self.s), format="csr") if sums is None else sums, lam_abs, k, sigma2, kind), 0.0))

    def variance_of(self, weights, lam_abs: float, k: int = 1, sigma2=None, kind: str = "sampling") -> np.ndarray:
        """Variance ``wᵀ C w`` of linear functionals ``w·b_λ`` of the filtered estimator,
        photons² (the covariances between unknowns included: a region's total is not the
        sum of its per-element σ).  The one uncertainty engine of fluxmap
        (:func:`fluxcli.inverse.regularisation.uncertainty` is its Tikhonov case).

        ``weights`` (n_obs,) or (n_functionals, n_obs), dense or sparse; ``sigma2`` as in
        :meth:`sigma`.  ``kind``:

        - ``"sampling"``: ``C`` is the covariance of the estimator under the noise,
          ``M TᵀWΣWT Mᵀ`` with ``M = V diag(f/s) Vᵀ`` (``V diag(f²/s) Vᵀ`` when ``W = Σ⁻¹``);
        - ``"posterior"`` (``k = 1``, weights ``1/σ²``): ``C = (G + λ̃R)⁻¹ = V diag(1/(s + λ̃)) Vᵀ``,
          the posterior covariance of the Gaussian model with prior ``b ~ N(0, (λ̃R)⁻¹)``.

        With ``lam_abs = 0`` the modes the data do not determine (``s ≈ 0``) are left out
        (the pseudo-inverse) and a functional that has weight on them gets an infinite
        variance.  Returns (n_functionals,) (a scalar's shape for one functional)."""
        if kind not in ("sampling", "posterior"):
            raise InputError(f"kind must be 'sampling' or 'posterior', got {kind!r}.")
        one = not sp.issparse(weights) and np.ndim(weights) == 1
        W = sp.csr_array(weights) if sp.issparse(weights) else np.atleast_2d(np.asarray(weights, float))
        AV = np.asarray(W @ self.V)
        singular = lam_abs <= 0 and not self.pos.all()
        if kind == "posterior":
            if lam_abs > 0:
                inv = 1.0 / (self.s + float(lam_abs))
            else:
                inv = np.where(self.pos, 1.0 / np.where(self.pos, self.s, 1.0), 0.0)
            var = (AV**2) @ inv
        else:
            f, fos = self.factors(lam_abs, k)
            if singular:  # the pseudo-inverse: undetermined modes are not estimated (their variance: below)
                f, fos = np.where(self.pos, f, 0.0), np.where(self.pos, fos, 0.0)
            if sigma2 is None:
                var = (AV**2) @ (f * fos)
            else:
                M = (AV * fos) @ self.V.T
                TW = self.T if self.weights is None else sp.csr_array(sp.diags_array(self.weights) @ self.T)
                C = TW.T @ sp.csr_array(sp.diags_array(sigma2) @ TW)  # sparse (elements that share pixels), symmetric
                var = np.einsum("ij,ji->i", M, C @ M.T)  # diag(M C Mᵀ): sparse x dense, not a 3-operand O(n³) einsum
        if singular:
            var = np.where(np.sum(AV[:, ~self.pos] ** 2, axis=1) > 1e-12, np.inf, var)
        return var[0] if one else var


class FilterCovariance:
    """The covariance of a filtered estimate as an operator: ``variance_of(weights)``.

    Built by :func:`fluxcli.inverse.filtered.filtered_solve` for the spectrum it solved on;
    ``weights`` run over the observed unknowns (n_obs,) or (n_functionals, n_obs).  The
    estimate was multiplied by ``level`` (a free overall level), so its variance is by
    ``level²``.  The linear approximation: the clipping at zero is ignored (see
    :meth:`Spectrum.sigma`)."""

    def __init__(self, spec: Spectrum, lam_abs: float, k: int, sigma2=None, level: float = 1.0,
                 kind: str = "sampling"):
        self.spec, self.lam_abs, self.k, self.sigma2, self.level = spec, float(lam_abs), int(k), sigma2, float(level)
        self.kind = kind

    def variance_of(self, weights) -> np.ndarray:
        return self.spec.variance_of(weights, self.lam_abs, self.k, self.sigma2, self.kind) * self.level**2


@dataclass
class Choice:
    """A λ picked on a spectrum, with its curve and what went wrong picking it."""

    lam: float  # relative (λ̃ / max diag TᵀWT)
    lam_absolute: float
    rule: str
    lambdas: np.ndarray
    criterion: np.ndarray
    residual_norm2: np.ndarray
    solution_norm2: np.ndarray
    target: float
    at_edge: bool
    widened: int = 0
    warnings: list = field(default_factory=list)


def default_grid() -> np.ndarray:
    return np.logspace(-9, 3, 73)


def choose(spec: Spectrum, rule: str = "gcv", *, k: int = 1, lambdas=None, gamma: float = 1.0,
           tau: float = 1.0, noise_total=None, widen: int = 2) -> Choice:
    """Pick the relative λ for the estimator with ``k`` iterated solves on ``spec``.

    Parameters
    ----------
    spec : Spectrum
    rule : {"gcv", "lcurve", "discrepancy"}
        GCV: minimise ``m‖W^½r‖² / (m − γΣf)²``, which estimates the noise level from the
        residual itself; on a spectrum weighted by a *known* noise model
        (``spec.noise_weighted``: unit variance per weighted pixel) its known-variance form,
        the unbiased predictive risk (UPRE, Mallows' C_p) ``‖W^½r‖² + 2γΣf − m``, is used:
        GCV's estimate ``‖W^½r‖²/m`` also counts model error (a surface finer than the
        elements, real optics) as noise and then over-smooths in proportion to χ²/pixel
        (an independent renderer's images: λ ~10x too large). L-curve: maximise the curvature of
        ``(log‖W^½r‖, log‖b‖)`` along ``log λ``; discrepancy: ``‖W^½r‖² = τ × E‖W^½ε‖²``.
    k : int
        Solves of the iterated scheme (its filter factors are used).
    lambdas : relative grid (> 0); default ``logspace(-9, 3, 73)``.
    gamma : modified-GCV weight (1: plain GCV).
    tau : discrepancy safety factor.
    noise_total : float
        ``E‖W^½ε‖²``: ``m`` when ``W = 1/σ²``, ``Σσ²`` when ``W = I``; required for
        the discrepancy rule.
    widen : int
        How many times a pick on the edge of the grid widens it by 3 decades on each side.

    Returns
    -------
    Choice
    """
    if rule not in RULES:
        raise InputError(f"lambda rule must be one of {', '.join(RULES)}; got {rule!r}.")
    grid = default_grid() if lambdas is None else np.sort(np.asarray(lambdas, dtype=np.float64).ravel())
    if grid.size < 3 or not np.all(np.isfinite(grid)) or grid[0] <= 0:
        raise InputError("lambdas must hold at least 3 finite values > 0.")
    if rule == "discrepancy" and noise_total is None:
        raise InputError("the discrepancy principle needs the expected noise (noise_total).")
    step = np.median(np.diff(np.log10(grid)))
    widened = 0
    while True:
        out = _pick(spec, rule, k, grid, gamma, tau, noise_total)
        if not out.at_edge or widened >= widen:
            break
        lo, hi = np.log10(grid[0]), np.log10(grid[-1])
        n_extra = max(int(round(3 / step)), 3)
        # both sides: a criterion that is flat over a range far from the optimum picks
        # an arbitrary end
        grid = np.concatenate([np.logspace(lo - 3, lo, n_extra + 1)[:-1], grid,
                               np.logspace(hi, hi + 3, n_extra + 1)[1:]])
        widened += 1
    out.widened = widened
    if out.at_edge and rule == "gcv":
        # a safer rule: GCV has no minimum inside a wide range (typically under model error);
        # the L-curve's corner does not need the residual to reach the noise level
        alt = _pick(spec, "lcurve", k, grid, gamma, tau, noise_total)
        if not alt.at_edge:
            alt.widened = widened
            alt.warnings.append(
                f"lambda (gcv) sat at the edge of the search range ({out.lam:.3g}, range {grid[0]:.3g}..{grid[-1]:.3g}) "
                f"after widening it {widened}x; fell back to the L-curve's corner ({alt.lam:.3g}).")
            return alt
    if out.at_edge:
        out.warnings.append(
            f"lambda ({rule}) sits at the edge of the search range ({out.lam:.3g}, range "
            f"{grid[0]:.3g}..{grid[-1]:.3g}, widened {widened}x): the rule found no optimum; "
            "the result may be over- or under-regularised.")
    elif widened:
        out.warnings.append(f"lambda ({rule}) was at the edge of the search range; the range was widened "
                            f"{widened}x (3 decades each) to {grid[0]:.3g}..{grid[-1]:.3g}.")
    return out


def _pick(spec, rule, k, grid, gamma, tau, noise_total) -> Choice:  # also regularisation.choose_lambda
    rho, eta, dof = spec.curves(grid * spec.scale, k)
    n = grid.size
    m = spec.m
    target = np.nan
    if rule == "gcv":
        def gcv(log_lam):
            r, _, tr = spec.curves(np.exp(log_lam) * spec.scale, k)
            if spec.noise_weighted:  # UPRE: the noise variance is known (1 per weighted pixel)
                return r + 2 * gamma * tr - m
            d = m - gamma * tr
            return np.where(d > 0, m * r / np.where(d > 0, d, 1.0) ** 2, np.inf)

        if spec.noise_weighted:
            crit = rho + 2 * gamma * dof - m
        else:
            d = m - gamma * dof
            crit = np.full(grid.size, np.inf)
            crit[d > 0] = m * rho[d > 0] / d[d > 0] ** 2  # no degrees of freedom left: not a candidate
        i = int(np.argmin(crit))
        lam, at_edge = grid[i], i in (0, n - 1)
        if not at_edge:
            # GCV is +inf where no degrees of freedom are left; Brent's parabola would make inf - inf
            # of it (nan and a RuntimeWarning), so the search sees a finite value above the curve there
            fin = crit[np.isfinite(crit)]
            cap = float(fin.max() + (fin.max() - fin.min()) + 1.0)
            res = sopt.minimize_scalar(lambda x: min(float(gcv(x)[0]), cap), method="bounded",
                                       bounds=(np.log(grid[i - 1]), np.log(grid[i + 1])))
            if res.success and float(gcv(res.x)[0]) <= crit[i]:
                lam = float(np.exp(res.x))
    elif rule == "lcurve":
        x, y, t = np.log(np.maximum(rho, 1e-300)), np.log(np.maximum(eta, 1e-300)), np.log(grid)
        dx, dy = np.gradient(x, t), np.gradient(y, t)
        ddx, ddy = np.gradient(dx, t), np.gradient(dy, t)
        crit = (dx * ddy - dy * ddx) / np.maximum((dx**2 + dy**2) ** 1.5, 1e-300)
        crit[[0, -1]] = -np.inf  # one-sided derivatives at the ends
        i = int(np.argmax(crit))
        lam, at_edge = grid[i], i in (1, n - 2)
    else:
        target = tau * float(noise_total)
        crit = rho - target
        if crit[-1] < 0:
            lam, at_edge = grid[-1], True
        elif crit[0] >= 0:
            lam, at_edge = grid[0], True
        else:
            i = int(np.nonzero(crit >= 0)[0][0])

            def excess(log_lam):
                return float(spec.curves(np.exp(log_lam) * spec.scale, k)[0][0] - target)

            lam = float(np.exp(sopt.brentq(excess, np.log(grid[i - 1]), np.log(grid[i]), xtol=1e-8)))
            at_edge = False
    return Choice(lam=float(lam), lam_absolute=float(lam * spec.scale), rule=rule, lambdas=grid,
                  criterion=crit, residual_norm2=rho, solution_norm2=eta, target=float(target),
                  at_edge=bool(at_edge))


def nonneg_quadratic(H: np.ndarray, rhs: np.ndarray, *, passive=None, max_iter: int | None = None,
                     inverse=None) -> np.ndarray:
    """``argmin_{x ≥ 0} ½xᵀHx − rhsᵀx`` for a symmetric positive (semi-)definite ``H`` (n, n).

    Block principal pivoting (Júdice & Pires 1994; Kim & Park 2011): guess the set of
    positive unknowns, solve the equations on it, swap every unknown that breaks the KKT
    conditions (a negative value, or a zero whose gradient asks to grow), and fall back to
    swapping one at a time when the count of violations stops falling (which makes it
    finite). ``passive`` (n,) bool is the first guess (e.g. the previous solution's
    support), so a sequence of nearby problems costs about one solve each. The KKT tests
    are relative to the rounding level of ``H x`` and ``rhs``.

    ``inverse``, optional: ``(H⁻¹ rhs, cols)`` with ``cols(idx)`` the columns ``H⁻¹[:, idx]``
    (e.g. from an eigendecomposition). With few unknowns at zero (set A) the solution with
    ``x_A = 0`` is then ``H⁻¹rhs − H⁻¹[:, A] (H⁻¹[A, A])⁻¹ (H⁻¹rhs)_A``: O(n²|A|) instead of a
    Cholesky of the free block, O((n − |A|)³/3); used while |A| ≤ n/8.
    """
    n = len(rhs)
    F = np.zeros(n, bool) if passive is None else np.asarray(passive, bool).copy()
    max_iter = max_iter or 50
    scale_h = float(np.abs(np.diag(H)).max()) if n else 0.0
    best, alpha = n + 1, 3
    x = np.zeros(n)
    best_x = x
    for _ in range(max_iter):
        x = np.zeros(n)
        A = np.flatnonzero(~F)
        # Schur on the zero set costs n²|A|, a Cholesky of the free block (n − |A|)³/3: the
        # former wins below |A| ≈ n/6
        if inverse is not None and 8 * A.size <= n:
            full, cols = inverse
            if A.size:
                C = cols(A)  # (n, |A|)
                x = full - C @ np.linalg.solve(C[A], full[A])
                x[A] = 0.0
            else:
                x = full.copy()
        elif F.any():
            x[F] = _spd_solve(H[np.ix_(F, F)], rhs[F])
        y = H @ x - rhs
        y[F] = 0.0
        # rounding level of the gradient: |H||x| + |c| times a few ulps per term
        tol = 1e3 * np.finfo(float).eps * (scale_h * np.abs(x).max(initial=0.0) + np.abs(rhs).max(initial=0.0))
        bad = (F & (x < 0)) | (~F & (y < -tol))
        nb = int(bad.sum())
        if nb == 0:
            return np.maximum(x, 0.0)
        if nb < best:
            best, alpha, best_x = nb, 3, x
            F ^= bad
        elif alpha > 0:
            alpha -= 1
            F ^= bad
        else:  # Murty's rule: the last violating index alone (finite termination)
            j = int(np.flatnonzero(bad)[-1])
            F[j] = not F[j]
    if n <= MAX_LAWSON_HANSON:
        return _nonneg_quadratic_lawson_hanson(H, rhs)
    # Lawson-Hanson on thousands of unknowns takes hours (issue 25's direct scene, 5666 vertices:
    # the pivoting did not settle in 50 rounds in the λ/2, 2λ check and scipy's NNLS ran on):
    # the pivoting's best iterate (fewest KKT violations), clipped, is what is left
    return np.maximum(best_x, 0.0)


MAX_LAWSON_HANSON = 2000  # unknowns; beyond, nonneg_quadratic keeps its best pivoting iterate


def _nonneg_quadratic_lawson_hanson(H, rhs):
    """The same problem by Lawson–Hanson (scipy's NNLS, finite and exact) on the square root
    ``UᵀU = H``, ``Uᵀd = c``: for pivoting that cycles on a matrix singular to working
    precision."""
    cf = c.try_cholesky(H)
    if cf is not None:
        U = np.triu(cf[0])
        d = sla.solve_triangular(U, rhs, trans="T", check_finite=False)
    else:
        w, V = sla.eigh(H, check_finite=False)
        keep = w > max(w.max(), 0.0) * len(w) * 10 * np.finfo(float).eps
        sw = np.sqrt(w[keep])
        U = sw[:, None] * V[:, keep].T
        d = (V[:, keep].T @ rhs) / sw
    x, _ = sopt.nnls(U, d, maxiter=50 * len(rhs))
    return x


def _spd_solve(H: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """``H⁻¹ rhs`` by Cholesky; when Cholesky cannot vouch for its pivots (singular to working
    precision) with a ridge at the rounding level of ``H`` (what lies below it is not
    determined by the arithmetic: an O(n³) Cholesky instead of an eigendecomposition ~10x
    dearer on a 5666-unknown problem), and on the range of ``H`` (eigh) as the last resort."""
    cf = c.try_cholesky(H)
    if cf is None:
        ridge = 1e3 * len(H) * np.finfo(float).eps * float(np.abs(np.diag(H)).max(initial=0.0))
        cf = c.try_cholesky(H + ridge * np.eye(len(H))) if ridge > 0 else None
    if cf is not None:
        return sla.cho_solve(cf, rhs, check_finite=False)
    w, V = sla.eigh(H, check_finite=False)
    keep = w > max(w.max(), 0.0) * len(w) * 10 * np.finfo(float).eps
    return V[:, keep] @ ((V[:, keep].T @ rhs) / w[keep])


def iterated_exact(spec: Spectrum, lam_abs: float, k: int, *, tol: float | None = None, start=None):
    """The iterated non-negative Tikhonov scheme with each step solved exactly:
    ``b ← argmin_{b ≥ 0} ‖W^½(a − Tb)‖² + λ̃ (b − b_prev)ᵀR(b − b_prev)``, ``k`` steps from 0
    (the proximal-point method).

    Without the constraint every step is the paper's update ``b + (G + λ̃R)⁻¹TᵀW(a − Tb)``, so
    the linear filter ``1 − (λ̃/(s + λ̃))^k`` that the λ rules evaluate is the same. With it,
    :func:`iterated_clipped` sets the negatives of that full step to zero, a projection in
    the wrong metric: when λ̃ is small the step is the (oscillating) least-squares solution,
    clipping it leaves an image far from the data, and repeating does not recover (a 1-D
    chain at λ = 1e-9: total 260x, χ²/pixel 2e4, where NNLS fits at 0.6). Solved exactly,
    each step decreases the penalised fit, and as λ̃ → 0 one step *is* non-negative least
    squares: the scheme cannot do worse than NNLS on the same data.

    Returns b (n_obs,) ≥ 0, iterations, converged (as :func:`iterated_clipped`).
    """
    R = np.eye(len(spec.s)) if spec.prior is None else spec.prior
    if lam_abs <= 0 and c.try_cholesky(spec.G) is None:
        c.cholesky(spec.G, "TᵀWT")  # raises: singular without regularisation, saying what to change
    H = spec.G + lam_abs * R
    T, a, w = spec.T, spec.a, spec.weights

    def fit(b):
        r = a - T @ b
        return float(np.sqrt(np.sum(r * r if w is None else w * r * r)))

    inverse = None
    if lam_abs > 0:  # H⁻¹ = V diag(1/(s + λ̃)) Vᵀ from the spectrum (VᵀGV = diag(s), VᵀRV = I)
        d = 1.0 / (spec.s + lam_abs)

        def inverse(x):
            return spec.V @ (d * (spec.V.T @ x)), lambda idx: spec.V @ (d[:, None] * spec.V[idx].T)

    guess = spec.solution(lam_abs, 1) > 0 if start is None else np.asarray(start) > 0
    b = nonneg_quadratic(H, spec.g, passive=guess, inverse=inverse and inverse(spec.g))
    norm = fit(b)
    it, converged, gain = 1, False, np.inf
    while it < k and norm > 0:
        rhs = spec.g + lam_abs * (R @ b)
        b_new = nonneg_quadratic(H, rhs, passive=b > 0, inverse=inverse and inverse(rhs))
        norm_new = fit(b_new)
        it += 1
        gain = (norm - norm_new) / norm
        b, norm = b_new, norm_new  # each exact step lowers the penalised objective: keep it
        if tol is not None and gain < tol:
            converged = True
            break
    return b, it, _settled(converged, tol=tol, gain=gain, k=k, norm=norm)


def _settled(converged: bool, *, tol, gain: float, k: int, norm: float) -> bool:
    """Whether an iterated scheme converged.  With a fixed number of solves (``tol`` None),
    "converged" means the last one no longer moved the fit by more than 1 % (the iterates have
    settled), not merely that k solves ran; a perfect fit (norm 0) has converged."""
    if tol is None:
        converged = bool(abs(gain) < 0.01) if k > 1 else True
    return True if norm == 0 else converged


def iterated_clipped(spec: Spectrum, lam_abs: float, k: int, *, tol: float | None = None):
    """The paper's scheme on ``spec``: ``b ← max(b + (G + λ̃R)⁻¹TᵀW(a − Tb), 0)``, ``k``
    solves from 0 (the first one is clipped Tikhonov).

    With ``tol`` the loop stops when the weighted fit ``‖W^½r‖`` improves by less than
    that fraction (and keeps the better iterate), as the paper does.

    Returns
    -------
    b : (n_obs,) photons, ≥ 0.
    iterations : int, solves made.
    converged : bool, the tolerance was met; without ``tol``, the last solve changed the fit
        by less than 1 %.
    """
    R = np.eye(len(spec.s)) if spec.prior is None else spec.prior
    cf = c.try_cholesky(spec.G + lam_abs * R)
    if cf is not None:
        def solve(x):
            return sla.cho_solve(cf, x, check_finite=False)
    elif lam_abs > 0:
        # Cholesky cannot vouch for its pivots (a wide range of column weights: bright and
        # dark pixels), but the spectrum already holds the inverse exactly: VᵀGV = diag(s),
        # VᵀRV = I, so (G + λ̃R)⁻¹ = V diag(1/(s + λ̃)) Vᵀ, finite for any λ̃ > 0
        d = 1.0 / (spec.s + lam_abs)

        def solve(x):
            return spec.V @ (d * (spec.V.T @ x))
    else:
        c.cholesky(spec.G, "TᵀWT")  # raises: singular without regularisation, saying what to change
    T, a, w = spec.T, spec.a, spec.weights

    def fit(b):
        r = a - T @ b
        return r, float(np.sqrt(np.sum(r * r if w is None else w * r * r)))

    b = np.maximum(solve(spec.g), 0.0)
    r, norm = fit(b)
    it, converged, gain = 1, False, np.inf
    while it < k and norm > 0:
        step = solve(T.T @ (r if w is None else w * r))
        b_new = np.maximum(b + step, 0.0)
        r_new, norm_new = fit(b_new)
        it += 1
        gain = (norm - norm_new) / norm
        if tol is None:
            b, r, norm = b_new, r_new, norm_new
            continue
        if gain >= 0:
            b, r, norm = b_new, r_new, norm_new
        if gain < tol:
            converged = True
            break
    return b, it, _settled(converged, tol=tol, gain=gain, k=k, norm=norm)
