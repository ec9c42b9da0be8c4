"""The default ``smooth`` reconstruction without dense matrices, for meshes beyond the dense limit.

The dense engine (:mod:`.spectral`, :mod:`.filtered`) forms ``G = TᵀWT`` and the exitance prior
``R`` as n × n arrays and eigendecomposes the pair: memory n², time n³, which is why ``auto``
stopped at 6000 unknowns and a 20 000-element mouse never finished (issue 22).  Here the same
estimator is computed from sparse matrices only:

- ``T`` (pixels × unknowns) stays sparse; ``G = TᵀWT`` is formed as a *sparse* product (two
  unknowns couple only where they share a pixel) and ``R = D(L/peak + ridge·I)D`` as the sparse
  graph Laplacian of :func:`fluxcli.inverse.smooth.exitance_prior`, with its square root
  ``R = EᵀE`` (``E``: one row per edge, ``√w (dᵢeᵢ − dⱼeⱼ)``, and ``√ridge·D``) kept for the trace
  estimator;
- every solve with ``H = G + λ̃R`` uses a sparse LU factorisation (SuperLU, fill-reducing
  ordering, no pivoting: ``H`` is symmetric positive definite); nothing n × n is ever dense.

The estimator is the same as the dense ``smooth``: ``k`` iterated solves
``b ← max(b + H⁻¹TᵀW(a − Tb), 0)`` from 0, weights ``1/σ²`` of the noise model on the model
image of an unweighted first pass, the level left to the data, the same warnings.  What the dense
engine reads off the eigenvalues is estimated instead:

- **λ** (UPRE on the weighted pass, GCV on the unweighted first one, the discrepancy principle on
  request): the residual ``‖W^½(a − Tb_λ)‖²`` of the unclipped ``k``-step estimate is computed
  exactly; the degrees of freedom ``tr F_λ``, ``F_λ = I − (λ̃H⁻¹R)^k`` (``Σ f(s)`` of the dense
  engine), by Hutchinson's estimator in the prior's metric, ``E[uᵀRF u]`` with
  ``u = R⁻¹Eᵀξ`` (``Cov u = R⁻¹``; Rademacher ξ): its eigenvalues are the filter factors
  ``f ∈ [0, 1]``, so with ``p`` probes the relative standard error is at most
  ``√(2/(p·tr F))`` (2.5 % at tr F = 200, p = 16).  The same probes are used at every λ, so the
  criterion is a smooth curve: a walk over decades (half decades from the previous pass's λ)
  brackets its minimum, successive parabolas refine it to 0.05 decades (a first pass, which only
  sets the weights: the bracket's parabola).  The final search reads ρ and tr F off Lanczos
  Krylov spaces, one per ~1.5 decades of λ (:class:`_LanczosCurve`: one factorisation and 30
  solves per start vector for every λ the space serves, where the k-step recursion
  (:class:`_Curve`) costs a factorisation and ``k`` solves per start vector at each λ); the
  values agree with the recursion to 1e-8, so the λ chosen is the same;
- **σ** per unknown (and per group): the covariance of the linear estimator under the noise is
  ``M TᵀWΣWT Mᵀ``; its diagonal is estimated from ``N`` exact samples ``M TᵀWΣ^½ξ`` (the same
  ``k``-step recursion), relative standard error of σ ``1/√(2N)`` (6 % at N = 128, the default up
  to the dense limit; 9 % at N = 64 beyond it, where each sample costs ``k`` large solves).

- **the totals' σ** (the stage's error budget, regions of interest): ``wᵀCw`` exactly, by ``k``
  adjoint solves per functional (:class:`MatfreeCovariance`).

Two cores: factorisations and solves run on worker threads (:mod:`fluxcli.inverse._threads`):
two λ of the first pass side by side, the columns of a block split, the chosen λ's solve beside
the λ/2 one and the 2λ one beside σ's samples; the main thread only waits,
so Ctrl-C and SIGTERM are answered at once. The search makes the same decisions as one
evaluation at a time (each value is computed alone), so the numbers do not depend on it.

Where both run (tests/test_matfree.py, ~1000 unknowns) the two paths agree: λ within ×1.5,
totals within 0.3 %, per-element values within 1 % of the peak, σ within 15 %.
"""

from __future__ import annotations


import threading
from collections import OrderedDict

import numpy as np
import scipy.optimize as sopt
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from fluxcli.inverse import _threads as T_
from fluxcli.inverse import spectral as S
from fluxcli.inverse.filtered import Filtered, halved_and_doubled, level_and_fit
from fluxcli.inverse.smooth import graph_laplacian, observed_adjacency
from fluxcli.errors import InputError

DENSE_MAX_UNKNOWNS = 6000  # auto: the dense engine up to here (exact, ~14 s at 5880), this path beyond
TRACE_PROBES = 16
SIGMA_SAMPLES = 128
LU_CACHE = 2  # factorisations kept (the chosen λ's is reused; two more may be in the making)
LU_BUDGET_BYTES = 2.0e9  # factorisations alive at once: one at a time where two would need more (~150 000 unknowns)
SIGMA_TASK = 8  # noise samples per task of the σ estimate
LANCZOS_STEPS = 30  # Lanczos steps per start vector of the final λ search (_LanczosCurve)
LANCZOS_RTOL = 1e-8  # a λ's residual from the Krylov space is used where m and m - 5 steps agree to this
SOLVE_BLOCK = 16  # columns per SuperLU solve call
SEED = 22  # probes and samples are seeded: the same inputs give the same bytes
GRID = (1e-9, 1e3)  # the dense engine's relative λ range ...
WIDE = (1e-15, 1e9)  # ... and how far it widens it


# ------------------------------------------------------------------ the sparse prior


def sparse_exitance_prior(adjacency, mask: np.ndarray, areas=None, ridge: float = 1e-3):
    """``R`` of :func:`fluxcli.inverse.smooth.exitance_prior` as a sparse matrix, and ``E`` with
    ``EᵀE = R`` (for sampling ``u ~ N(0, R⁻¹)``).

    Returns
    -------
    R : sparse csc (n_obs, n_obs), symmetric positive definite.
    E : sparse csr (n_edges + n_obs, n_obs).
    """
    A = observed_adjacency(adjacency, mask)
    if A.nnz and abs(A - A.T).max() > 1e-12 * abs(A).max():
        raise InputError("adjacency must be symmetric.")
    n_obs = A.shape[0]
    deg = np.asarray(A.sum(axis=1)).ravel()
    peak = deg.max() if n_obs else 0.0
    unit = 1.0 / peak if peak > 0 else 1.0
    d = np.ones(n_obs)
    if areas is not None:
        S_ = np.asarray(areas, dtype=np.float64)
        if S_.shape != mask.shape or not np.all(S_[mask] > 0):
            raise InputError(f"areas must be ({mask.size},) and > 0 on observed elements.")
        d = S_[mask].mean() / S_[mask]
    L = graph_laplacian(A, np.ones(n_obs, bool)) * unit + ridge * sp.eye_array(n_obs)
    Dg = sp.diags_array(d)
    R = sp.csc_array(Dg @ L @ Dg)
    up = sp.triu(sp.coo_array(A), k=1)
    i, j, w = up.row, up.col, np.sqrt(up.data * unit)
    e = np.arange(i.size)
    edges = sp.csr_array((np.concatenate([w * d[i], -w * d[j]]), (np.concatenate([e, e]), np.concatenate([i, j]))),
                         shape=(i.size, n_obs))
    E = sp.csr_array(sp.vstack([edges, sp.diags_array(np.sqrt(ridge) * d)]))
    return R, E


# ------------------------------------------------------------------ the normal operator


def _factor(H):
    """SuperLU of the SPD ``H`` (fill-reducing symmetric ordering, no pivoting).

    Called on a worker thread (:mod:`fluxcli.inverse._threads`; SuperLU releases the GIL): the
    main thread stays free to run the Ctrl-C / SIGTERM handlers (~3 s of CPU at 50 000
    elements, more beyond), and two factorisations of the λ search run on the two cores."""
    return spla.splu(H, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})


def g_per_unknown(n_unknowns: int, n_poses: int = 1, n_pixels: int = 0) -> float:
    """Nonzeros of ``G = TᵀWT`` per unknown and pose, from how many unknowns share a pixel: issue
    22's scene (1024², three views) measured 42 / 82 / 258 at 18 200 / 45 568 / 181 713 unknowns
    (unknowns per sensor pixel 0.017 / 0.043 / 0.17); ``85·(density / 0.043)^0.8`` (n_pixels 0:
    that scene's density at 50 000 elements)."""
    if n_pixels <= 0:
        return G_PER_UNKNOWN
    dens = float(max(n_unknowns, 1)) / (float(n_pixels) / max(n_poses, 1)) / REF_DENSITY
    # held at the densest measured (4x): how far G fills beyond depends on the optics' blur in
    # pixels, which is not known here (a 48 x 48 sensor under 62 500 elements: 27 per pixel)
    return G_PER_UNKNOWN * min(dens, 4.0) ** 0.8


def lu_bytes(n_unknowns: int, n_poses: int = 1, g_per: float | None = None) -> float:
    """Estimated bytes of one SuperLU factorisation of ``H`` (see :func:`memory_estimate_bytes`):
    ~12 bytes per nonzero of the factors, ``LU_PER_UNKNOWN·g/82`` nonzeros per unknown
    (``g``: :func:`g_per_unknown`, or the measured one; measured 302 / 753 / ~2 200 at
    g = 42 / 82 / 258, the last from the peak of the factorisation, 4.7 GB: the fill follows
    G's density, not n)."""
    g = G_PER_UNKNOWN if g_per is None else float(g_per)
    return 12.0 * float(max(n_unknowns, 1)) * LU_PER_UNKNOWN * (g / 82.0) * np.sqrt(n_poses)


def lu_cache(n_unknowns: int, n_poses: int = 1, g_per: float | None = None) -> int:
    """Factorisations kept: :data:`LU_CACHE`, or 1 where ``LU_CACHE + 2`` (two in the making
    while the λ search evaluates two values at once) would pass :data:`LU_BUDGET_BYTES`."""
    return LU_CACHE if (LU_CACHE + 2) * lu_bytes(n_unknowns, n_poses, g_per) <= LU_BUDGET_BYTES else 1


def _trim() -> None:
    """Hand freed factor memory back to the system (glibc); nothing elsewhere."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


class Pencil:
    """``G = TᵀWT`` (sparse), ``g = TᵀWa``, the prior ``R`` and factorisations of ``G + λ̃R``.

    Parameters
    ----------
    T : sparse (m, n_obs), the observed columns on the pixels that see them.
    a : (m,) photons.
    weights : (m,) 1/photons², or None for ``W = I``.
    R : sparse (n_obs, n_obs), the prior.
    """

    def __init__(self, T, a, weights, R, check=None):
        self.T = sp.csr_array(T)
        self.a = a
        self.w = weights
        TW = self.T.copy()
        if weights is not None:
            TW.data *= np.repeat(weights, np.diff(self.T.indptr))
        G = sp.csc_array(self.T.T @ TW)
        self.G = sp.csc_array(0.5 * (G + G.T))
        self.g = np.asarray(self.T.T @ (a if weights is None else weights * a), dtype=np.float64)
        self.R = sp.csc_array(R)
        self.scale = float(self.G.diagonal().max())
        self.check = check or (lambda: None)
        self._lu: OrderedDict = OrderedDict()  # λ̃ -> SuperLU, least recently used first
        self._lock = threading.Lock()
        self.pinned = None  # the chosen λ̃: its factorisation outlives the λ/2, 2λ solves (σ, covariance)
        n = self.G.shape[0]
        self.keep = lu_cache(n, 1, self.G.nnz / max(n, 1))  # from G's measured density

    def lu(self, lam_abs: float):
        """SuperLU of ``G + λ̃R``, on a worker thread; the ``keep`` most recently used are kept (two
        λ of the search are factorised at once, and the chosen one is reused)."""
        key = float(lam_abs)
        with self._lock:
            if key in self._lu:
                self._lu.move_to_end(key)
                return self._lu[key]
        self.check()
        if self.keep < LU_CACHE:  # memory-bound: the old factorisation goes before the new one is built
            with self._lock:
                for x in [x for x in self._lu if x != self.pinned]:
                    del self._lu[x]
            _trim()
        lu = T_.owned(lambda: _factor(sp.csc_array(self.G + key * self.R)))
        with self._lock:
            self._lu[key] = lu
            dropped = False
            while len(self._lu) > self.keep:
                old = next((x for x in self._lu if x != self.pinned and x != key), None)
                if old is None:
                    break
                del self._lu[old]
                dropped = True
        if dropped:
            _trim()
        return lu

    def release(self) -> None:
        """Drop every factorisation (the pinned one too) and hand the memory back."""
        with self._lock:
            self._lu.clear()
        self.pinned = None
        _trim()

    def solve(self, lam_abs: float, X, lu=None):
        """``H⁻¹X``, the columns shared out to the worker threads, each thread's in blocks of
        :data:`SOLVE_BLOCK` (SuperLU's multi-column solve: 26 ms a column against 36 ms one at a
        time at 50 000 elements, one thread); ``lu``: the factorisation at ``lam_abs`` if the
        caller holds it."""
        lu = self.lu(lam_abs) if lu is None else lu
        X = np.asarray(X, dtype=np.float64)
        if X.ndim == 1:
            return lu.solve(X)
        out = np.empty_like(X)

        def cols(js):
            def run():
                for lo in range(0, len(js), SOLVE_BLOCK):
                    sel = js[lo:lo + SOLVE_BLOCK]
                    out[:, sel] = lu.solve(np.asfortranarray(X[:, sel]))
            return run

        T_.run_all([cols(js) for js in np.array_split(np.arange(X.shape[1]), min(T_.WORKERS, X.shape[1]))])
        return out

    def iterate(self, lam_abs: float, C, k: int, X0=None, lu=None):
        """``X ← λ̃H⁻¹RX + C`` ``k`` times (from ``X0``, default 0): the ``k``-step filter."""
        X = np.zeros_like(C) if X0 is None else X0
        lu = self.lu(lam_abs) if (lu is None and k > 0) else lu
        for _ in range(k):
            self.check()
            X = lam_abs * self.solve(lam_abs, self.R @ X, lu) + C
        return X

    def wnorm2(self, r) -> float:
        return float(np.sum(r * r) if self.w is None else np.sum(self.w * r * r))


# ------------------------------------------------------------------ λ


class _Curve:
    """Residual, solution norm and degrees of freedom of the unclipped k-step estimate, per λ."""

    def __init__(self, P: Pencil, k: int, probes: int, rng):
        self.P, self.k = P, k
        n = P.G.shape[0]
        self.E = None
        self.cache: dict = {}
        self.probes = probes
        self._rng = rng
        self._U = self._EtXi = None
        self.n = n

    def _probes(self, E):
        if self._U is None:
            xi = self._rng.choice([-1.0, 1.0], size=(E.shape[0], self.probes))
            self._EtXi = np.asarray(E.T @ xi)
            lu = T_.owned(_factor, sp.csc_array(self.P.R))
            self._U = np.column_stack([lu.solve(np.ascontiguousarray(c)) for c in self._EtXi.T])
        return self._U, self._EtXi

    def prefetch(self, lams, E) -> None:
        """Evaluate the λ values not yet known two at a time, one per core (each value is the
        same as evaluated alone: the search's decisions do not change). Only where two more
        factorisations fit (:func:`lu_cache`); otherwise :meth:`at` evaluates them when asked."""
        todo = [x for x in dict.fromkeys(float(v) for v in lams) if x not in self.cache]
        if len(todo) < 2 or T_.WORKERS < 2 or self.P.keep < LU_CACHE or T_.in_worker():
            return
        self._probes(E)
        T_.run_all([lambda x=x: self.at(x, E) for x in todo])

    def at(self, lam_rel: float, E):
        key = float(lam_rel)
        if key not in self.cache:
            P = self.P
            lam_abs = key * P.scale
            U, EtXi = self._probes(E)
            lu = P.lu(lam_abs)  # held here: another evaluation running beside this one may drop it from the cache
            C = np.zeros((self.n, 1 + U.shape[1]))
            C[:, 0] = P.solve(lam_abs, P.g, lu)
            X0 = np.zeros_like(C)
            X0[:, 1:] = U
            # b_{j+1} = S b_j + H⁻¹g (b_0 = 0) and y_{j+1} = S y_j (y_0 = u), S = λ̃H⁻¹R, in one block;
            # the first step of b is C itself, so k steps of the block give b_k and S^k u
            X = P.iterate(lam_abs, C, self.k, X0, lu)
            b = X[:, 0]
            tr = float(np.mean(np.sum(EtXi * (U - X[:, 1:]), axis=0)))
            rho = P.wnorm2(P.a - P.T @ b)
            self.cache[key] = (rho, float(b @ b), min(max(tr, 0.0), float(self.n)))
        return self.cache[key]


def _psi(s, lam_abs: float, k: int):
    """``ψ(s) = (1 − (λ̃/(s+λ̃))^k)/s`` (→ ``k/λ̃`` at s = 0) and ``f(s) = 1 − (λ̃/(s+λ̃))^k``: the
    k-step estimate is ``b = ψ(R⁻¹G)R⁻¹g``, its filter ``F = f(R⁻¹G)``."""
    x = np.maximum(s, 0.0) / lam_abs
    f = -np.expm1(-k * np.log1p(x))
    small = x < 1e-8
    psi = np.where(small, k * (1.0 - 0.5 * (k + 1) * x) / lam_abs, f / np.where(small, 1.0, np.maximum(s, 1e-300)))
    return f, psi


class _LanczosCurve(_Curve):
    """:class:`_Curve`'s values (the residual, ``‖b‖²`` and the Hutchinson ``tr F`` of the unclipped
    ``k``-step estimate, with the same probes) for every λ near a shift μ from ONE Krylov space per
    start vector, instead of a factorisation and ``k`` solves per probe at each λ.

    In the prior's metric ``B = (G + μ̃R)⁻¹R`` is self-adjoint, with eigenvalues ``t = 1/(s + μ̃)``
    (``s`` those of the pencil ``(G, R)``).  ``F_λ = f(s)`` and ``b_λ = ψ(s)R⁻¹g`` (:func:`_psi`) are
    functions of ``B``: Lanczos in the R-inner product on ``B`` (full reorthogonalisation), started
    at each probe ``u`` and at ``R⁻¹g``, gives ``uᵀR f(B) u ≈ ‖u‖²_R e₁ᵀf(T_m)e₁`` (Gauss quadrature)
    and ``b_λ ≈ ‖R⁻¹g‖_R V_m ψ(T_m) e₁``.  ``f`` and ``ψ`` are rational in ``t`` with one pole, at
    ``t = 1/(μ̃ − λ̃)``: at λ = μ they are polynomials of degree ``k`` (exact after ``k/2`` steps), and
    the error falls geometrically with the pole's distance from the spectrum in ``[0, 1/μ̃]``
    (measured on issue 22's 50 000 elements, m = 30 steps: ρ to 1e-13 from μ/3 to 10μ, 1e-4 at
    μ/10).  Each value is accepted only where the quadrature with ``m − 5`` steps agrees (ρ to
    :data:`LANCZOS_RTOL` relative, tr F to 1e-6·n); elsewhere a new space is made at
    ``λ·10^-½`` (the criterion's λ walk then stays within one or two spaces).  One space costs a
    factorisation and ``m`` solves per start vector (``m = 30``), about three λ of the exact
    recursion; the λ search asks for six to ten."""

    def __init__(self, P: Pencil, k: int, probes: int, rng, steps: int = 0):
        super().__init__(P, k, probes, rng)
        self.steps = int(steps or LANCZOS_STEPS)
        self.spaces: list = []  # (μ̃, ‖s₀‖_R, alpha (m, c), beta (m, c), V₀ (m, n))

    def prefetch(self, lams, E) -> None:  # a value costs a few small eigendecompositions once a space exists
        return

    def _space(self, mu_abs: float, E):
        """The Krylov space at ``mu_abs``: Lanczos in the R-inner product from ``R⁻¹g`` (its
        basis kept: ``b_λ`` is built from it; fully reorthogonalised, twice) and from each probe
        (the tridiagonal matrix only: the three-term recurrence with the last two vectors
        re-orthogonalised against, as Gauss quadrature tolerates the rest (its own error is checked
        by :meth:`_value`); memory ``m·n`` for the first, ``3n`` per probe)."""
        P, m = self.P, self.steps
        U, _ = self._probes(E)
        S0 = np.column_stack([self._luR.solve(np.ascontiguousarray(P.g)), U])
        RS = P.R @ S0
        nrm = np.sqrt(np.maximum(np.sum(S0 * RS, axis=0), 1e-300))
        nc = S0.shape[1]
        V0 = np.empty((m + 1, self.n))  # the basis of the first chain
        Q = S0 / nrm
        Qp = np.zeros_like(Q)
        RQ = RS / nrm
        V0[0] = Q[:, 0]
        alpha, beta = np.zeros((m, nc)), np.zeros((m, nc))
        lu = P.lu(mu_abs)
        for j in range(m):
            P.check()
            W = P.solve(mu_abs, RQ, lu)
            for rep in range(2):  # against the last two vectors (all, for the first chain), twice
                RW = P.R @ W
                a_ = np.sum(Q * RW, axis=0)
                b_ = np.sum(Qp * RW, axis=0)
                if rep == 0:
                    alpha[j] = a_
                W -= Q * a_ + Qp * b_
                c0 = V0[:j + 1] @ (P.R @ W[:, 0])
                W[:, 0] -= V0[:j + 1].T @ c0
            RW = P.R @ W
            beta[j] = np.sqrt(np.maximum(np.sum(W * RW, axis=0), 1e-300))
            Qp, Q = Q, W / beta[j]
            RQ = RW / beta[j]
            V0[j + 1] = Q[:, 0]
        return float(mu_abs), nrm, alpha, beta, np.ascontiguousarray(V0[:m])

    def _quad(self, space, lam_abs: float, steps: int):
        mu, nrm, alpha, beta, V0 = space
        b, tr = None, []
        for c in range(alpha.shape[1]):
            Tm = np.diag(alpha[:steps, c]) + np.diag(beta[: steps - 1, c], 1) + np.diag(beta[: steps - 1, c], -1)
            th, Y = np.linalg.eigh(Tm)
            s = 1.0 / np.maximum(th, 1e-300) - mu
            f, psi = _psi(s, lam_abs, self.k)
            if c == 0:
                b = V0[:steps].T @ (Y @ (psi * Y[0])) * nrm[0]
            else:
                tr.append(nrm[c] ** 2 * float(np.sum(Y[0] ** 2 * f)))
        return b, float(np.mean(tr))

    def _value(self, space, lam_abs: float):
        P = self.P
        out = []
        for steps in (self.steps, self.steps - 5):
            b, tr = self._quad(space, lam_abs, steps)
            out.append((P.wnorm2(P.a - P.T @ b), float(b @ b), tr))
        (rho, bb, tr), (rho5, _, tr5) = out
        ok = abs(rho - rho5) <= LANCZOS_RTOL * rho and abs(tr - tr5) <= 1e-6 * self.n
        return (rho, bb, min(max(tr, 0.0), float(self.n))), ok

    def at(self, lam_rel: float, E):
        key = float(lam_rel)
        if key not in self.cache:
            lam_abs = key * self.P.scale
            val = None
            for space in sorted(self.spaces, key=lambda sp_: abs(np.log(sp_[0] / lam_abs))):
                v, ok = self._value(space, lam_abs)
                if ok:
                    val = v
                    break
            if val is None:
                self.spaces.append(self._space(lam_abs / np.sqrt(10.0), E))
                val, _ = self._value(self.spaces[-1], lam_abs)
            self.cache[key] = val
        return self.cache[key]

    def _probes(self, E):
        if self._U is None:
            xi = self._rng.choice([-1.0, 1.0], size=(E.shape[0], self.probes))
            self._EtXi = np.asarray(E.T @ xi)
            self._luR = T_.owned(_factor, sp.csc_array(self.P.R))
            self._U = np.column_stack([self._luR.solve(np.ascontiguousarray(c)) for c in self._EtXi.T])
        return self._U, self._EtXi


def _criterion(rule, rho, tr, m, gamma, mean_var=None, target=None):
    if rule == "upre":
        return rho + 2 * gamma * tr - m
    if rule == "upre_uniform":  # the provisional UPRE: one noise level for every pixel
        return rho / mean_var + 2 * gamma * tr - m
    if rule == "gcv":
        d = m - gamma * tr
        return m * rho / d**2 if d > 0 else np.inf
    return rho - target  # discrepancy


def _refine(crit, ahead, x: float, f: float, h: float, tol: float, lo: float, hi: float) -> float:
    """The minimum of ``crit`` (over log λ) bracketed by ``x - h, x, x + h`` (``x`` the lowest of
    the three, all evaluated), by successive parabolas with a golden-section safeguard, to
    ``tol`` decades.  The criterion is a smooth curve (the probes are fixed), so the vertex of
    the parabola through the best point and its neighbours converges in two or three
    evaluations (the halving walk it replaces took six to eight); each round also evaluates the
    point ``tol`` beyond the vertex, side by side (one per core), which closes the bracket."""
    pts = {x - h: crit(x - h), x: f, x + h: crit(x + h)}
    for _ in range(12):
        b = min(pts, key=pts.get)
        left = max((t for t in pts if t < b), default=None)
        right = min((t for t in pts if t > b), default=None)
        if left is None or right is None or right - left <= 2 * tol:
            break
        fa, fb, fc = pts[left], pts[b], pts[right]
        p, q = (b - left) * (fb - fc), (b - right) * (fb - fa)
        v = b - 0.5 * ((b - left) * p - (b - right) * q) / (p - q) if p != q else np.nan
        if not (np.isfinite(v) and left < v < right):
            v = b + 0.382 * ((right - b) if right - b > b - left else (left - b))
        if abs(v - b) < tol:  # the parabola puts the minimum within tol of b: look once beside it
            v = b + (tol if v >= b else -tol)
            if not left < v < right:
                break
        if min(abs(v - t) for t in pts) < tol / 2:  # nothing new to learn there
            break
        d = np.sign(v - b)
        w = v + d * tol  # beside the vertex, away from b: with v, brackets a minimum that sits at v
        w = w if (left < w < right and abs(w - v) > 1e-9) else None
        ahead(*(t for t in (v, w) if t is not None and lo <= t <= hi))
        pts[v] = crit(v)
        if w is not None and pts[v] < fb:
            pts[w] = crit(w)
    return float(min(pts, key=pts.get))


def _choose(curve: _Curve, E, rule: str, *, m: int, gamma: float, mean_var=None, target=None,
            start: float = 1e-4, bounds=None, finest: float = 0.125, first_step: float = 1.0) -> S.Choice:
    """Minimise the criterion over log λ: steps of ``first_step`` decades downhill from ``start``,
    then successive parabolas in the bracket down to ``finest`` decades (:func:`_refine`)
    (discrepancy: the zero crossing, by Brent's root finder). The dense engine's range and its
    widening (3 decades each side, twice) bound the walk."""
    def crit(lam):
        rho, _, tr = curve.at(lam, E)
        return _criterion(rule, rho, tr, m, gamma, mean_var, target)

    grid, wide = (GRID, WIDE) if bounds is None else (bounds, bounds)
    lo, hi = np.log10(wide[0]), np.log10(wide[1])
    # a first search starts on a whole decade; one that follows a previous pass's λ starts there,
    # in half decades (the weights move λ, not by decades)
    x0 = float(np.clip(np.round(np.log10(start)) if first_step >= 1 else np.log10(start), lo, hi))
    at_edge = False
    def ahead(*ts):  # the values the next steps ask for, evaluated side by side
        curve.prefetch([10**t for t in ts if lo <= t <= hi], E)

    if rule == "discrepancy":
        x = x0
        f = crit(10**x)
        step = 1.0 if f < 0 else -1.0
        while True:
            xn = x + step
            if xn < lo or xn > hi:
                at_edge = True
                lam = 10**x
                break
            ahead(xn, xn + step)
            fn = crit(10**xn)
            if (fn >= 0) != (f >= 0):
                a_, b_ = sorted((x, xn))
                lam = 10 ** sopt.brentq(lambda t: crit(10**t), a_, b_, xtol=0.01)
                break
            x, f = xn, fn
    else:
        ahead(x0, min(x0 + first_step, hi))
        x, f = x0, crit(10**x0)
        fu = crit(10 ** min(x + first_step, hi))
        step = first_step if fu < f else -first_step
        while True:
            xn = x + step
            if xn < lo or xn > hi:
                at_edge = True
                break
            ahead(xn, xn + step)
            fn = crit(10**xn)
            if not fn < f:
                break
            x, f = xn, fn
        lam = 10**x
        if not at_edge and finest >= abs(step):
            # a coarse λ (a first pass, which only sets the weights): the vertex of the parabola
            # through the bracket, within half a step of its best point, not evaluated
            fa, fc = crit(10 ** (x - step)), crit(10 ** (x + step))
            den = fa - 2 * f + fc
            off = 0.5 * step * (fa - fc) / den if (den > 0 and np.isfinite(den)) else 0.0
            lam = float(10 ** (x + float(np.clip(off, -abs(step) / 2, abs(step) / 2))))
        elif not at_edge:
            lam = float(10 ** _refine(lambda t: crit(10**t), ahead, x, f, abs(step), finest, lo, hi))
    lams = np.array(sorted(curve.cache))
    vals = np.array([curve.cache[v] for v in lams])
    critv = np.array([_criterion(rule, r, t, m, gamma, mean_var, target) for r, _, t in vals])
    out = S.Choice(lam=float(lam), lam_absolute=float(lam * curve.P.scale), rule="gcv" if rule != "discrepancy"
                   else "discrepancy", lambdas=lams, criterion=critv, residual_norm2=vals[:, 0],
                   solution_norm2=vals[:, 1], target=float(target) if target is not None else np.nan,
                   at_edge=bool(at_edge))
    out.widened = int(not (grid[0] <= lam <= grid[1]))
    if at_edge:
        out.warnings.append(f"lambda ({out.rule}) sits at the edge of the search range ({lam:.3g}, range "
                            f"{wide[0]:.3g}..{wide[1]:.3g}): the rule found no optimum; the result may be over- or "
                            "under-regularised.")
    elif out.widened:
        out.warnings.append(f"lambda ({out.rule}) lies outside {grid[0]:.3g}..{grid[1]:.3g}: the search went "
                            f"beyond the usual range to {lam:.3g}.")
    return out


# ------------------------------------------------------------------ the clipped solve and σ


def _clipped(P: Pencil, lam_abs: float, k: int):
    """:func:`fluxcli.inverse.spectral.iterated_clipped` with ``tol=None`` on the sparse pencil."""
    def fit(b):
        r = P.a - P.T @ b
        return r, float(np.sqrt(P.wnorm2(r)))

    lu = P.lu(lam_abs)  # held: a solve beside this one may drop it from the cache
    b = np.maximum(P.solve(lam_abs, P.g, lu), 0.0)
    r, norm = fit(b)
    it, gain = 1, np.inf
    while it < k and norm > 0:
        P.check()
        step = P.solve(lam_abs, P.T.T @ (r if P.w is None else P.w * r), lu)
        b = np.maximum(b + step, 0.0)
        r_new, norm_new = fit(b)
        it += 1
        gain = (norm - norm_new) / norm
        r, norm = r_new, norm_new
    converged = bool(abs(gain) < 0.01) if k > 1 else True
    return b, it, converged or norm == 0


def _sigma_tasks(P: Pencil, lam_abs: float, k: int, sigma2, n_samples: int, rng, sums=None, lu=None):
    """The work of :func:`_sigma` as independent tasks (a few samples each, for
    :func:`fluxcli.inverse._threads.run_all` beside other work) and the function that sums their
    results into (σ, σ of ``sums @ b``).  The samples are drawn here, in order (the same for any
    number of threads)."""
    m = P.T.shape[0]
    if sigma2 is None:
        amp = np.sqrt(P.w)
    else:
        amp = np.sqrt(sigma2) * (1.0 if P.w is None else P.w)
    lu = P.lu(lam_abs) if lu is None else lu

    def task(xi):
        def run():
            Z = np.asarray(P.T.T @ (amp[:, None] * xi))
            C = P.solve(lam_abs, Z, lu)
            X = P.iterate(lam_abs, C, k - 1, C, lu) if k > 1 else C
            return np.sum(X * X, axis=1), (None if sums is None else np.sum(np.asarray(sums @ X) ** 2, axis=1))
        return run

    tasks, done = [], 0
    while done < n_samples:
        nb = min(32, n_samples - done)
        xi = rng.standard_normal((m, nb))
        tasks += [task(xi[:, lo:lo + SIGMA_TASK]) for lo in range(0, nb, SIGMA_TASK)]
        done += nb

    def total(results):
        acc = np.sum([r[0] for r in results], axis=0)
        acc_s = None if sums is None else np.sum([r[1] for r in results], axis=0)
        return np.sqrt(acc / n_samples), (None if sums is None else np.sqrt(acc_s / n_samples))

    return tasks, total


def _sigma(P: Pencil, lam_abs: float, k: int, sigma2, n_samples: int, rng, sums=None):
    """σ of the linear k-step estimator under noise ``Σ`` (``sigma2``; None: ``Σ = W⁻¹``) from
    ``n_samples`` exact samples ``M TᵀWΣ^½ξ``; also σ of ``sums @ b`` when given."""
    tasks, total = _sigma_tasks(P, lam_abs, k, sigma2, n_samples, rng, sums)
    return total(T_.run_all(tasks))


class MatfreeCovariance:
    """``wᵀCw`` of the linear ``k``-step estimator (:func:`_sigma`'s covariance
    ``M TᵀWΣWT Mᵀ``) for a few functionals ``w`` (a region's or the pose's total), *exactly*, by
    the adjoint: ``Mᵀw = WT H⁻¹ Σ_{j<k} (λ̃RH⁻¹)^j w``, ``k`` solves per functional; nothing n × n.
    The dense engine's :class:`~fluxcli.inverse.spectral.FilterCovariance` does the same from its
    eigenvectors (the reconstruct stage's error budget asks every solve for its total's σ: the
    generic dense covariance it fell back to needed 16 GB at 45 000 unknowns).  Keeps the pencil
    (and its factorisation) alive while it is: the stage measures, then drops it."""

    def __init__(self, P: Pencil, lam_abs: float, k: int, sigma2=None, level: float = 1.0):
        self.P, self.lam_abs, self.k, self.sigma2, self.level = P, float(lam_abs), max(int(k), 1), sigma2, float(level)

    def variance_of(self, weights) -> np.ndarray:
        from fluxcli.inverse.covariance import _rows

        W, one = _rows(weights)
        P, lam = self.P, self.lam_abs
        Y = np.asarray(W.T.toarray() if sp.issparse(W) else W.T, dtype=np.float64)  # (n_obs, g)
        acc = Y.copy()
        for _ in range(self.k - 1):
            Y = lam * (P.R @ P.solve(lam, Y))
            acc += Y
        U = np.asarray(P.T @ P.solve(lam, acc))
        if P.w is not None:
            U = P.w[:, None] * U
        s2 = (1.0 / P.w) if self.sigma2 is None else np.asarray(self.sigma2, dtype=np.float64)
        var = (s2 @ (U * U)) * self.level**2
        return var[0] if one else var


# ------------------------------------------------------------------ the solve


def matfree_solve(T_obs, a, *, prior, k: int = 10, lam: float | None = None, rule: str = "gcv",
                  gamma: float = 1.0, tau: float = 1.0, lambdas=None, variance=None, sigma2=None, weighted: bool = True,
                  passes: int = 2, free_level: bool = True, sums=None, check=None,
                  probes: int = TRACE_PROBES, samples: int | None = None) -> Filtered:
    """:func:`fluxcli.inverse.filtered.filtered_solve` (``tol=None``) on sparse matrices.

    Parameters
    ----------
    T_obs : sparse (m, n_obs), observed columns on the pixels that see them; dimensionless.
    a : (m,) photons.
    prior : (R, E) from :func:`sparse_exitance_prior`.
    k, lam, rule, gamma, tau, variance, sigma2, weighted, passes, free_level, sums :
        as :func:`~fluxcli.inverse.filtered.filtered_solve`; ``rule`` is "gcv" (UPRE once
        weighted) or "discrepancy".
    lambdas : relative λ values whose range bounds the search (not widened); default the dense
        engine's 1e-9..1e3, widened to 1e-15..1e9 when the criterion runs off it.
    check : callable or None, called between factorisations and solves (raise there to stop).
    probes, samples : Hutchinson probes for tr F (a first, unweighted pass uses a quarter), and
        noise samples for σ (default :data:`SIGMA_SAMPLES`, half that beyond :data:`DENSE_MAX_UNKNOWNS`:
        σ to 1/√(2N), 6 % then 9 %).

    Returns
    -------
    Filtered
    """
    if rule not in ("gcv", "discrepancy"):
        raise InputError(f"lam_rule {rule!r} is not available on the matrix-free path (more than "
                         f"{DENSE_MAX_UNKNOWNS} unknowns); use gcv or discrepancy, or give lam.")
    R, E = prior
    m = T_obs.shape[0]
    bounds = None
    if lambdas is not None:
        grid = np.asarray(lambdas, dtype=np.float64).ravel()
        if grid.size < 3 or not np.all(np.isfinite(grid)) or grid.min() <= 0:
            raise InputError("lambdas must hold at least 3 finite values > 0.")
        bounds = (float(grid.min()), float(grid.max()))
    rng = np.random.default_rng(SEED)
    if weighted and variance is None and sigma2 is None:
        weighted = False
    weights = 1.0 / sigma2 if (weighted and variance is None) else None
    n_pass = max(int(passes), 1) if (weighted and variance is not None) else 1
    if rule == "discrepancy" and variance is not None and n_pass == 1:
        n_pass = 2
    var_model = sigma2
    choice = None
    start = 1e-4
    P = None
    for p in range(n_pass):
        if P is not None:  # the previous pass's factorisations go before this pass's G is made
            P.release()
        P = Pencil(T_obs, a, weights, R, check)
        # one factorisation alive at a time (lu_cache): each counts (minutes beyond ~150 000 unknowns)
        big = P.keep < LU_CACHE
        lam_p = lam
        if lam is None:
            last = p == n_pass - 1
            # a first pass only sets the weights: fewer probes, a coarser λ
            # the final, fine search from Krylov spaces (a handful of solves per probe for every λ);
            # a first pass, a coarse walk with a quarter of the probes, by the k-step recursion (a
            # factorisation per λ; two at once on the two cores), or from Krylov spaces where
            # factorisations are one at a time (one space spans ~2 of its whole-decade steps)
            curve = (_LanczosCurve if (last or big) else _Curve)(P, k, probes if last else max(probes // 4, 2),
                                                                np.random.default_rng(SEED + p))
            fine = 0.05 if last else 1.0  # a first pass: the bracket's parabola, to about a third of a decade
            step0 = 1.0 if p == 0 else 0.5  # a later pass starts at the previous pass's λ
            noise_weighted = weights is not None
            if rule == "discrepancy":
                if weights is not None:
                    choice = _choose(curve, E, "discrepancy", m=m, gamma=gamma, target=tau * m, start=start, bounds=bounds, finest=fine, first_step=step0)
                elif var_model is not None:
                    choice = _choose(curve, E, "discrepancy", m=m, gamma=gamma, target=tau * float(np.sum(var_model)),
                                     start=start, bounds=bounds, finest=fine, first_step=step0)
                else:
                    choice = _choose(curve, E, "gcv", m=m, gamma=gamma, start=start, bounds=bounds, finest=fine, first_step=step0)
            else:
                choice = _choose(curve, E, "upre" if noise_weighted else "gcv", m=m, gamma=gamma, start=start, bounds=bounds, finest=fine, first_step=step0)
                if (not noise_weighted and variance is not None and weighted
                        and (choice.widened or choice.at_edge)):
                    mean_var = float(np.mean(variance(np.maximum(a, 0.0))))
                    choice = _choose(curve, E, "upre_uniform", m=m, gamma=gamma, mean_var=max(mean_var, 1e-300),
                                     start=start, bounds=bounds, finest=fine, first_step=step0)
            lam_p = choice.lam
            start = lam_p
            del curve  # its Krylov spaces
        side: dict = {}
        if p == n_pass - 1 and lam is None and big:
            # the totals' bracket first, one factorisation at a time: the chosen λ's is then kept
            # (σ, the stage's covariance) and never beside another
            for x in (0.5 * lam_p * P.scale, 2.0 * lam_p * P.scale):
                side[x] = _clipped(P, x, k)[0]
            P.release()
        if p == n_pass - 1 and lam is None and not big and T_.WORKERS > 1:
            # the chosen λ's solve and the λ/2 one (the totals' bracket, below) side by side, one per core
            lam_at = lam_p * P.scale
            P.pinned = float(lam_at)
            (b, it, conv), side[0.5 * lam_at] = T_.run_all([lambda: _clipped(P, lam_at, k),
                                                            lambda: _clipped(P, 0.5 * lam_at, k)[0]])
        else:
            b, it, conv = _clipped(P, lam_p * P.scale, k)
        if variance is not None:
            var_model = variance(P.T @ b)
            if p < n_pass - 1 and weighted:
                weights = 1.0 / var_model
    warn: list[str] = list(choice.warnings) if choice is not None else []
    lam_abs = lam_p * P.scale
    b, fitted, var_model, level, chi2 = level_and_fit(a, b, P.T @ b, weights=weights, var_model=var_model,
                                                      variance=variance, free_level=free_level, warnings=warn)
    sigma = np.full(len(b), np.nan)
    sigma_sums = None if sums is None else np.full(sums.shape[0], np.nan)
    covariance = None
    P.pinned = float(lam_abs)
    sides = lam is None and b.sum() > 0
    tasks = []  # the λ/2, 2λ solves not yet made, then σ's samples: one pool for the two cores
    if sides:
        tasks += [lambda x=x: (x, _clipped(P, x, k)[0]) for x in (0.5 * lam_abs, 2.0 * lam_abs) if x not in side]
    n_side = len(tasks)
    total_sigma = None
    if weights is not None or var_model is not None:
        s2 = None if weights is not None else var_model
        covariance = MatfreeCovariance(P, lam_abs, it, s2, level)
        n_s = samples if samples is not None else (SIGMA_SAMPLES if len(b) <= DENSE_MAX_UNKNOWNS
                                                   else SIGMA_SAMPLES // 2 if not P.keep < LU_CACHE else SIGMA_SAMPLES // 4)
        more, total_sigma = _sigma_tasks(P, lam_abs, it, s2, n_s, np.random.default_rng(SEED + 100), sums)
        tasks += more
    # two factorisations alive beside the chosen λ's only where they fit (lu_cache)
    results = T_.run_all(tasks, workers=None if P.keep >= LU_CACHE else 1)
    side.update(dict(results[:n_side]))
    if total_sigma is not None:
        sg, sgs = total_sigma(results[n_side:])
        sigma = sg * level
        if sums is not None:
            sigma_sums = sgs * level
    totals = (np.nan, np.nan)
    if sides:
        totals = halved_and_doubled(lambda lam_x: side[lam_x] if lam_x in side else _clipped(P, lam_x, k)[0],
                                    P.T, a, b, lam_abs,
                                    var_model=var_model, free_level=free_level, warnings=warn)
    return Filtered(power=b, sigma=sigma, lam=float(lam_p), lam_absolute=float(lam_abs), iterations=int(it),
                    converged=bool(conv), choice=choice, chi2_per_pixel=chi2,
                    total_at_half_and_double_lambda=totals, weighted=weights is not None, warnings=warn,
                    sigma_sums=sigma_sums, covariance=covariance)


def memory_estimate_bytes(n_unknowns: int, n_poses: int = 1, n_pixels: int = 0, g_per: float | None = None) -> float:
    """What :func:`matfree_solve` holds at its peak, in bytes, before anything is allocated.

    Per unknown and pose ~40 nonzeros of T (three copies: T, its observed part, the weighted
    copy) and :func:`g_per_unknown` of ``G`` (three: ``G``, the sum that symmetrises it, ``H``),
    the factorisations of ``H`` (:func:`lu_bytes`, from G's density: the fill grows with how many
    unknowns share a pixel, ~2 200 nonzeros per unknown at 200 000 elements on 1024² pixels,
    four times 50 000's): up to four alive where they fit in :data:`LU_BUDGET_BYTES` (two kept,
    two in the making), else one (:func:`lu_cache`); the λ search's Krylov basis
    (``LANCZOS_STEPS + 1`` vectors) and its probes' recurrences, the probe and sample
    blocks, ~12 copies of the pixel vectors, and :data:`BASE_BYTES` (the interpreter, its libraries
    and the stage's own arrays: the whole process's peak is what is compared).  ``g_per``: G's
    nonzeros per unknown where known (else :func:`g_per_unknown`).  Measured against issue 22's
    scene by benchmarks/bench_scale.py at 2 000 - 200 000 elements (said and measured side by
    side) and in tests/test_matfree.py (slow) at 20 000 unknowns."""
    n = float(max(n_unknowns, 1))
    g = g_per_unknown(int(n), n_poses, n_pixels) if g_per is None else float(g_per)
    keep = lu_cache(int(n), n_poses, g)
    alive = keep + 2 if keep >= LU_CACHE else 1
    return (12.0 * n * n_poses * (3 * T_PER_UNKNOWN + 3 * g) + lu_bytes(int(n), n_poses, g) * alive
            + 8.0 * n * (LANCZOS_STEPS + 1) + 8.0 * n * (TRACE_PROBES + 1) * 8 + 8.0 * n * 32 * 3
            + 12 * 8.0 * n_pixels + BASE_BYTES)


def stage_bytes(n_unknowns: int, n_poses: int, n_pixels_per_pose: int) -> float:
    """The whole reconstruct's peak on this path, in bytes, before anything is allocated: the
    larger of one pose's solve and the joint one (:func:`memory_estimate_bytes`), plus what the
    other poses hold meanwhile (their T per fine face, per unknown and per element, and their
    images: :data:`POSE_HELD_BYTES_PER_UNKNOWN`)."""
    P = max(int(n_poses), 1)
    solves = [_up_to(n_unknowns, 1, n_pixels_per_pose)]
    if P > 1:
        solves.append(_up_to(n_unknowns, P, n_pixels_per_pose * P))
    return max(solves) + (P - 1) * POSE_HELD_BYTES_PER_UNKNOWN * float(max(n_unknowns, 1))


def _up_to(n_unknowns: int, n_poses: int, n_pixels: int) -> float:
    """:func:`memory_estimate_bytes` for any count up to ``n_unknowns``: a solve has only the
    unknowns its pixels see, and the estimate drops where that many stop fitting
    :data:`LU_CACHE` factorisations (one is kept instead), so it is also taken at the largest count
    where they still fit.  (At 50 000 elements the stage counted 50 299 vertices, which said 1.3 GB;
    the solve had 45 568 observed unknowns, kept two factorisations and took 2.0 GB.)"""
    n = int(max(n_unknowns, 1))
    best = memory_estimate_bytes(n, n_poses, n_pixels)

    def several(m: int) -> bool:
        return lu_cache(m, n_poses, g_per_unknown(m, n_poses, n_pixels)) == LU_CACHE

    if several(n) or not several(1):
        return best
    lo, hi = 1, n  # several(lo), not several(hi): the fill grows with the count, so one change between
    while hi - lo > 1:
        mid = (lo + hi) // 2
        lo, hi = (mid, hi) if several(mid) else (lo, mid)
    return max(best, memory_estimate_bytes(lo, n_poses, n_pixels))


# What each further pose holds while another is solved, per unknown: issue 22's 50 000-element scene
# (45 568 unknowns, 1024², three views) peaked at 2.02 GB with one pose and 2.75 GB with two (rotations
# 0 and 120 deg, each alone and jointly; 26 Nov 2026), where one solve's estimate alone said 2.47 GB.
POSE_HELD_BYTES_PER_UNKNOWN = 16e3


T_PER_UNKNOWN = 40.0
G_PER_UNKNOWN = 85.0
LU_PER_UNKNOWN = 760.0
BASE_BYTES = 0.35e9  # the process before the solve: Python, numpy/scipy/numba, the stage's arrays (~0.25-0.3 GB measured)
REF_DENSITY = 45568 / 1024**2  # unknowns per sensor pixel where G_PER_UNKNOWN was measured
