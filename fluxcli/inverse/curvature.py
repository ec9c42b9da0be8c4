"""The emission's curvature term in reconstruct: a second pass whose profile bends with the exitance.

Where the exitance curves along the surface the light leaves with another angular profile
(:func:`fluxcli.optics.emission.curvature_ratio`): ``L = M p(theta) (1 + r(theta) kappa)`` with
``kappa = lap_t M / M``.  Over a buried source (kappa < 0) more light leaves along the normal and
less at grazing angles than ``p`` says; far from it the reverse.  On issue 21's box (MCX photons)
a profile that ignores it reads the elements over the source 9 % high head-on and 6 % low at 75°.

kappa is a property of the unknown exitance, so it is taken from the data: each solve is made
once with the profile alone, kappa per element is estimated from that solution (the quadratic
fit of :func:`fluxcli.optics.emission.curvature_operator` through the elements within
:data:`RADIUS_ELEMENTS` element widths: a fit over next neighbours alone reads the solution's
element-to-element noise as curvature), its power-weighted mean over each region that faces one
way taken out (a face's light, all positions together, follows the profile), clipped to the
first-order theory's range
(:data:`fluxcli.optics.emission.KAPPA_L2_MAX`), and the solve is made again with each column of
T scaled by ``1 + r(theta_view) kappa`` per view.  The Laplacian is not put into the unknowns' T
itself: tried, the hats' own Laplacians let the inversion fit noise with angle-dependent light
(errors not lower, a residual structured by viewing angle at ±30° with mirrors).
docs/design.md, "The curvature term".
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import scipy.sparse as sp

from ..optics.emission import KAPPA_L2_MAX, curvature_kappa, curvature_operator, curvature_regions

RADIUS_ELEMENTS = 2.0  # kappa fitted over faces within this many element widths (2-mm elements: 4 mm)


@dataclass
class CurvaturePass:
    """What the second pass needs: per pose T on the columns (fine faces or elements) and its
    curvature part ``sum_views w T_view diag(r_view)`` (mm^2), the map from columns to the
    unknowns' T, and how kappa is estimated from a solution's power per element."""

    T_columns: list  # per pose, (n_pixels, n_columns)
    T_curvature: list  # per pose, (n_pixels, n_columns) mm^2 (:func:`fluxcli.artefacts.transfer.load_T_curvature`)
    to_unknowns: Callable  # (pose k, T on the columns) -> T on the unknowns
    K: sp.csr_array  # elements: power -> S_e lap_t M|_e (curvature_operator with the fitting radius)
    element_of_column: np.ndarray | None  # the columns' elements (fine faces: their parents; None: the elements)
    kappa_max: float  # 1/mm^2
    radius_mm: float  # kappa fitted over faces within this distance
    used: dict = field(default_factory=dict)  # pose -> the kappa (per column) its last second pass used
    regions: np.ndarray | None = None  # per element, where kappa's power-weighted mean is 0 (default: K's own)

    def __post_init__(self):
        if self.regions is None:
            self.regions = curvature_regions(self.K)

    def kappa(self, power_per_element: np.ndarray) -> np.ndarray:
        """kappa (1/mm^2) per column from a solution's power per element (unobserved: 0), its
        mean over each region taken out (:func:`fluxcli.optics.emission.curvature_kappa`)."""
        k = curvature_kappa(self.K, power_per_element, self.regions, self.kappa_max)
        return k if self.element_of_column is None else k[self.element_of_column]

    def T(self, k: int, power_per_element: np.ndarray) -> sp.csr_array:
        """Pose k's T on the unknowns with the profile bent by the kappa of ``power_per_element``."""
        kap = self.kappa(power_per_element)
        self.used[k] = kap
        return self.to_unknowns(k, sp.csr_array(self.T_columns[k] + self.T_curvature[k] @ sp.diags_array(kap)))


def curvature_pass(emission, surface, T_columns, T_curvature, to_unknowns, columns: str) -> CurvaturePass | None:
    """The second pass of a run whose emission profile has the curvature term (None: it has not).
    ``T_columns``, ``T_curvature``: per pose T on the columns and its curvature part;
    ``columns``: ``"refined:1"`` (the faces of the surface refined once) or ``"elements"``."""
    if emission is None or not emission.has_curvature or not T_columns:
        return None
    radius = RADIUS_ELEMENTS * float(np.sqrt(np.median(surface.element_areas_mm2)))
    transport = emission.reduced_scattering_per_mm + emission.absorption_per_mm
    return CurvaturePass(list(T_columns), list(T_curvature), to_unknowns, curvature_operator(surface, radius_mm=radius),
                         surface.refined(1)[1] if columns.startswith("refined") else None,
                         KAPPA_L2_MAX * transport**2, radius)
