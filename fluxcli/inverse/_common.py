"""Input checks and the linear algebra shared by the reconstruction methods.

Everything here works on the *observed* columns of the transfer matrix only; the public
functions scatter results back to all elements with NaN for the unobserved ones.
"""

from __future__ import annotations

import numbers

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
from ..errors import InputError

DEFAULT_REL_THRESHOLD = 1e-3


def as_transfer(T) -> sp.csr_array:
    """Return ``T`` as a float64 CSR array after checking it is 2-D, finite and ≥ 0."""
    if sp.issparse(T):
        out = sp.csr_array(T, dtype=np.float64)
    else:
        arr = np.asarray(T, dtype=np.float64)
        if arr.ndim != 2:
            raise InputError(
                f"transfer matrix T must be 2-D (n_pixels, n_elements), got shape {arr.shape}."
            )
        out = sp.csr_array(arr)
    if out.ndim != 2 or out.shape[0] == 0 or out.shape[1] == 0:
        raise InputError(f"transfer matrix T must be non-empty and 2-D, got shape {out.shape}.")
    out.sum_duplicates()
    out.eliminate_zeros()
    if out.nnz and (not np.all(np.isfinite(out.data)) or out.data.min() < 0):
        raise InputError("transfer matrix T must be finite and non-negative.")
    return out


def as_pixels(values, n_pixels: int, name: str, *, nonnegative=False, positive=False,
              allow_scalar=False) -> np.ndarray:
    """Check a per-pixel vector (or a scalar, if allowed) and return it as float64 (n_pixels,)."""
    arr = np.asarray(values, dtype=np.float64)
    if arr.ndim == 0 and allow_scalar:
        arr = np.full(n_pixels, float(arr))
    if arr.shape != (n_pixels,):
        raise InputError(
            f"{name} must have shape ({n_pixels},) to match the rows of T, got {arr.shape}."
        )
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{name} must be finite everywhere.")
    if positive and np.any(arr <= 0):
        raise InputError(f"{name} must be strictly positive everywhere.")
    if nonnegative and np.any(arr < 0):
        raise InputError(f"{name} must be non-negative everywhere.")
    return arr


def as_elements(values, n_elements: int, name: str) -> np.ndarray:
    """Check a per-element vector; NaN is allowed (unobserved elements)."""
    arr = np.asarray(values, dtype=np.float64)
    if arr.shape != (n_elements,):
        raise InputError(
            f"{name} must have shape ({n_elements},) to match the columns of T, got {arr.shape}."
        )
    if np.any(np.isinf(arr)):
        raise InputError(f"{name} must not contain infinities.")
    return arr


def check_nonneg_number(value, name: str) -> float:
    """A finite real number ≥ 0 (regularisation weights, tolerances)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise InputError(f"{name} must be a real number, got {type(value).__name__}.")
    value = float(value)
    if not np.isfinite(value) or value < 0:
        raise InputError(f"{name} must be finite and ≥ 0, got {value!r}.")
    return value


def check_positive_int(value, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 1:
        raise InputError(f"{name} must be an integer ≥ 1, got {value!r}.")
    return int(value)


def column_sums(T: sp.csr_array) -> np.ndarray:
    return np.asarray(T.sum(axis=0)).ravel()


def observed(T: sp.csr_array, rel_threshold: float) -> np.ndarray:
    """Boolean (n_elements,): column sum > rel_threshold × the largest column sum."""
    rel_threshold = check_nonneg_number(rel_threshold, "rel_threshold")
    sums = column_sums(T)
    top = sums.max()
    if top <= 0:
        raise InputError("transfer matrix T has no non-zero column: no element is observed.")
    return sums > rel_threshold * top


def scatter(values_observed: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Place observed-element values into a full (n_elements,) vector, NaN elsewhere."""
    out = np.full(mask.shape, np.nan)
    out[mask] = values_observed
    return out


def normal_equations(T_obs: sp.csr_array, a: np.ndarray, weights: np.ndarray | None):
    """Dense ``G = TᵀWT`` (n_obs, n_obs) and ``g = TᵀWa`` (n_obs,); ``W = diag(weights)``."""
    if weights is None:
        TW = T_obs
        g = T_obs.T @ a
    else:
        TW = T_obs.copy()
        TW.data *= np.repeat(weights, np.diff(T_obs.indptr))  # row scaling W T
        g = T_obs.T @ (weights * a)
    G = (T_obs.T @ TW).toarray()
    # Symmetrise: the sparse product is exact in structure but not bitwise symmetric.
    G = 0.5 * (G + G.T)
    return G, np.asarray(g, dtype=np.float64)


def lam_scale(G: np.ndarray) -> float:
    """The paper's normaliser: max diag(TᵀWT), so λ̃ = λ × lam_scale."""
    return float(np.max(np.diag(G)))


def try_cholesky(H: np.ndarray):
    """Upper Cholesky factor of ``H`` as ``cho_factor`` returns it, or None when ``H`` is
    singular to working precision (LAPACK can succeed with a pivot at rounding level,
    which would give garbage)."""
    try:
        cf = sla.cho_factor(H, lower=False, check_finite=False)
    except np.linalg.LinAlgError:
        return None
    pivots = np.diag(cf[0]) ** 2
    if pivots.min() <= np.max(np.diag(H)) * H.shape[0] * 10 * np.finfo(float).eps:
        return None
    return cf


def cholesky(H: np.ndarray, what: str):
    """:func:`try_cholesky` with a ValueError that says how to fix a singular H."""
    cf = try_cholesky(H)
    if cf is None:
        raise InputError(
            f"{what} is singular (not positive definite): increase lam above 0 or raise "
            f"rel_threshold so that poorly observed elements are excluded."
        )
    return cf


def covered_rows(T_obs: sp.csr_array) -> np.ndarray:
    """Boolean (n_pixels,): pixels that see at least one observed element."""
    return np.diff(T_obs.indptr) > 0
