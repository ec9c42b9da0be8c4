"""Elements seen only edge-on leave the observed total under ``diffuse`` emission (issue 21):
the best view angle over a lens aperture against its closed form, and the reclassification
(solved for, left out of the total, the poorly-observed share recomputed)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import scipy.sparse as sp

from fluxcli.inverse import diagnostics as D
from fluxcli.inverse.methods import POOR_SHARE_TEXT, Result, poor_share_warning
from fluxcli.optics import emission as E
from fluxcli.surface.mesh import Surface


def _square(normal_axis: int, side_mm: float = 0.2):
    """Two triangles of a small square at the origin, normal +z (2) or +y (1)."""
    h = side_mm / 2
    if normal_axis == 2:
        v = np.array([[-h, -h, 0], [h, -h, 0], [h, h, 0], [-h, h, 0]])
    else:  # in the x-z plane, counter-clockwise seen from +y
        v = np.array([[-h, 0, -h], [-h, 0, h], [h, 0, h], [h, 0, -h]])
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def test_best_view_angle_over_the_aperture_matches_its_closed_form():
    va, fa = _square(2)
    vb, fb = _square(1)
    surf = Surface(np.vstack([va, vb]), np.vstack([fa, fb + 4]), np.array([0, 0, 1, 1]), 2)
    D_mm, R_mm = 100.0, 10.0
    cam = SimpleNamespace(center_mm=np.array([0.0, 0.0, D_mm]), axis=np.array([0.0, 0.0, -1.0]), aperture_radius_mm=R_mm)
    both = sp.csr_array(np.ones((3, 2)))
    best = D.best_view_deg(surf, [cam], [both])
    assert best[0] < 0.1  # facing the lens
    # turned edge-on to the lens centre (90 deg there); the rim of the disk sees it at 90 - atan(R/D)
    assert best[1] == pytest.approx(90.0 - np.degrees(np.arctan(R_mm / D_mm)), abs=0.1)
    # a view that collects none of an element's light says nothing about it
    only_a = sp.csr_array(np.array([[1.0, 0.0]]))
    best = D.best_view_deg(surf, [cam], [only_a])
    assert best[0] < 0.1 and np.isinf(best[1])


def _result(power, observed, observation, warnings=()):
    p = np.asarray(power, float)
    return Result(power=p, observed=np.asarray(observed, bool), sigma=0.1 * p, fitted=np.zeros(3), residual=np.zeros(3),
                  method="smooth", lam=1.0, lam_absolute=1.0, iterations=1, converged=True,
                  observation=np.asarray(observation, np.int8), warnings=tuple(warnings))


def test_edge_on_elements_leave_the_observed_total_and_nothing_else_changes():
    power, observed, observation = [1.0, 2.0, 3.0, 4.0], [True, True, True, False], [2, 1, 2, 0]
    poor = poor_share_warning(np.array(power), np.array(observed), np.array(observation))
    assert poor is not None  # element 1 (poorly observed) holds 2/6 of the observed total
    res = _result(power, observed, observation, warnings=("another warning", poor))
    best = np.array([10.0, 85.0, 79.9, 89.0])
    out = D.leave_out_edge_on(res, best, 80.0, "diffuse (refractive index 1.4)")
    assert out.observed.tolist() == [True, False, True, False]
    assert np.isnan(out.power[1]) and np.isnan(out.sigma[1]) and out.observation[1] == 0
    np.testing.assert_array_equal(out.power[[0, 2]], [1.0, 3.0])  # the rest untouched
    assert out.observation[[0, 2]].tolist() == [2, 2]
    assert "another warning" in out.warnings
    assert not any(POOR_SHARE_TEXT in w for w in out.warnings)  # no poorly observed element is left
    (edge,) = [w for w in out.warnings if D.EDGE_ON_TEXT in w]
    assert "1 element(s) seen only beyond 80 deg" in edge and "33%" in edge
    # a profile known to 90 deg, or nothing beyond the limit: the very same result
    assert D.leave_out_edge_on(res, best, 90.0, "lambertian") is res
    assert D.leave_out_edge_on(res, np.full(4, 30.0), 80.0, "diffuse") is res


def test_only_diffuse_has_a_limit():
    assert E.diffuse(1.40).trusted_to_deg == E.DIFFUSE_TRUSTED_TO_DEG < 90.0
    assert E.lambertian().trusted_to_deg == 90.0
    assert E.table([0, 45, 90], [1.0, 0.8, 0.2]).trusted_to_deg == 90.0
