"""Reconstruction of the surface flux per element from camera images (DESIGN.md §5).

- :mod:`fluxcli.inverse.methods` — backprojection, the paper's iterative non-negative
  Tikhonov, linear Tikhonov, exact (weighted) NNLS, MLEM, and :func:`reconstruct`.
- :mod:`fluxcli.inverse.regularisation` — automatic λ (GCV, L-curve, discrepancy) and
  per-element uncertainty.
- :mod:`fluxcli.inverse.metrics` — the paper's L1 error (Eq. 15) and total-flux ratio.

Arrays: ``T`` (n_pixels, n_elements) sparse, dimensionless; images (n_pixels,) in
photons; flux (n_elements,) in photons per element, NaN for unobserved elements.
"""

from fluxcli.inverse.methods import (
    METHODS,
    Result,
    backprojection,
    mlem,
    nnls,
    observed_mask,
    paper,
    reconstruct,
    stack_views,
    tikhonov,
    weighted_lsq,
)
from fluxcli.inverse.metrics import error_l1, total_ratio
from fluxcli.inverse.regularisation import (
    LAMBDA_RULES,
    LambdaChoice,
    choose_lambda,
    uncertainty,
)

__all__ = [
    "LAMBDA_RULES",
    "METHODS",
    "LambdaChoice",
    "Result",
    "backprojection",
    "choose_lambda",
    "error_l1",
    "mlem",
    "nnls",
    "observed_mask",
    "paper",
    "reconstruct",
    "stack_views",
    "tikhonov",
    "total_ratio",
    "uncertainty",
    "weighted_lsq",
]
