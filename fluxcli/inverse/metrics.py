"""Accuracy of a reconstruction against a known ground truth (paper Eq. 15)."""

from __future__ import annotations

import numpy as np
from ..errors import InputError

__all__ = ["error_l1", "total_ratio"]


def _pair(b_hat, b_true, observed_only):
    b_hat = np.asarray(b_hat, dtype=np.float64)
    b_true = np.asarray(b_true, dtype=np.float64)
    if b_hat.ndim != 1 or b_hat.shape != b_true.shape:
        raise InputError(
            f"b_hat and b_true (photons per element) must be 1-D with the same shape, got "
            f"{b_hat.shape} and {b_true.shape}."
        )
    if not np.all(np.isfinite(b_true)):
        raise InputError("b_true (photons per element) must be finite.")
    if np.any(np.isinf(b_hat)):
        raise InputError("b_hat (photons per element) must not contain infinities.")
    seen = np.isfinite(b_hat)
    if observed_only:
        b_hat, b_true = b_hat[seen], b_true[seen]
    else:
        b_hat = np.where(seen, b_hat, 0.0)
    total = b_true.sum()
    if not total > 0:
        raise InputError("b_true (photons per element) must have a positive sum.")
    return b_hat, b_true, total


def error_l1(b_hat, b_true, *, observed_only: bool = False) -> float:
    """Relative L1 error ``Σ|b′ − b| / Σb`` (paper Eq. 15).

    Parameters
    ----------
    b_hat : ndarray, shape (n_elements,)
        Reconstruction in photons per element; NaN marks unobserved elements.
    b_true : ndarray, shape (n_elements,)
        Ground truth in photons per element.
    observed_only : bool, optional
        False (default): sum over all elements, unobserved ones counted as a zero
        estimate, so flux the cameras cannot see counts as error (as in the paper, which
        reports every element). True: sum over observed (finite) elements only.

    Returns
    -------
    float
        Dimensionless; 0 is perfect, 1 is "as wrong as reporting zero everywhere".
    """
    b_hat, b_true, total = _pair(b_hat, b_true, observed_only)
    return float(np.sum(np.abs(b_hat - b_true)) / total)


def total_ratio(b_hat, b_true, *, observed_only: bool = False) -> float:
    """Total-flux ratio ``Σb′ / Σb``; NaN entries of ``b_hat`` are handled as in
    :func:`error_l1`.

    Parameters
    ----------
    b_hat, b_true : ndarray, shape (n_elements,)
        Reconstruction and ground truth in photons per element.
    observed_only : bool, optional
        Restrict both sums to observed (finite) elements of ``b_hat``.

    Returns
    -------
    float
        Dimensionless; 1 is a perfect total.
    """
    b_hat, b_true, total = _pair(b_hat, b_true, observed_only)
    return float(np.sum(b_hat) / total)
