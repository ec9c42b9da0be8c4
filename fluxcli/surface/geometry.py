"""The two formulas of solid geometry every floor uses: a triangle's area and a rotation about
an axis.  Written once here (``surface`` imports nothing of fluxmap, so every package may
import it): the surfaces, the FEM's boundary, the structured-light mesh, the scene's poses, the
report's turned views and the calibration budget's moved camera all call these.
"""

from __future__ import annotations

import numpy as np


def triangle_areas(corners) -> np.ndarray:
    """Areas of triangles, ``½‖(p₁ − p₀) × (p₂ − p₀)‖``.

    Parameters
    ----------
    corners : array_like, shape (n_triangles, 3, 3)
        The three corners of each triangle (any length unit, e.g. mm).

    Returns
    -------
    ndarray, shape (n_triangles,)
        Areas in that unit squared (mm² for corners in mm), ≥ 0.
    """
    t = np.asarray(corners)
    return 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)


def rotation_matrix(axis, angle_deg: float) -> np.ndarray:
    """The rotation by ``angle_deg`` about ``axis`` (right-handed), by Rodrigues' formula
    ``R = I + sin θ K + (1 − cos θ) K²`` with ``K`` the cross-product matrix of the unit axis.

    Parameters
    ----------
    axis : array_like, shape (3,)
        Direction of the axis (any non-zero length; normalised here).
    angle_deg : float
        Angle in degrees; positive turns counter-clockwise seen from the tip of ``axis``.

    Returns
    -------
    ndarray, shape (3, 3)
        Orthonormal, ``det = +1``; apply as ``R @ v`` (or ``points @ R.T``).
    """
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    t = np.deg2rad(angle_deg)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(t) * K + (1 - np.cos(t)) * K @ K
