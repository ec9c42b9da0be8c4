"""Triangulation: each decoded camera pixel's chief ray meets its projector column.

A camera pixel looks along its chief ray (lens centre through the pixel's focal-plane
centre; undeviated by a thin lens).  Where the ray meets a plane mirror it continues
reflected (the mirror view: the real camera reflected, as in build-T).  The point is
where the projector sees the decoded column ``u``: the root of ``u(P(t)) - u`` along the
ray, started from the undistorted column plane and refined by Newton steps through the
projector's distortion.
"""

from __future__ import annotations

import numpy as np

from ..optics.camera import PlaneMirror, ThinLensCamera
from .projector import Projector

__all__ = ["chief_rays", "triangulate_columns"]


def chief_rays(camera: ThinLensCamera, mirrors: list[PlaneMirror]):
    """Per camera pixel (flat index), the ray segments it may look along.

    Returns ``origins (k+1, n, 3), directions (k+1, n, 3), t_max (k+1, n)``: segment 0 is
    the direct ray (nan where the ray meets a mirror); segment j >= 1 the ray reflected in
    mirror j-1 from the mirror point on (nan where the direct ray does not meet that
    mirror).  A pixel whose ray meets a mirror belongs to that mirror's view: a ray meets
    any column plane somewhere, so the direct segment before the mirror cannot be told
    apart by triangulation; in the rig the mirrors stand beside the subject, not behind it."""
    focal = camera.pixel_centres_focal(1).reshape(-1, 3)
    d = focal - camera.center_mm
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    n = len(d)
    origins = np.full((len(mirrors) + 1, n, 3), np.nan)
    dirs = np.full((len(mirrors) + 1, n, 3), np.nan)
    tmax = np.full((len(mirrors) + 1, n), np.inf)
    origins[0], dirs[0] = camera.center_mm, d
    for j, m in enumerate(mirrors, start=1):
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((m.center_mm - camera.center_mm) @ m.normal) / (d @ m.normal)
        M = camera.center_mm + t[:, None] * d
        ok = (t > 0) & np.isfinite(t) & m.contains(M) & ((d @ m.normal) < 0)
        origins[j][ok] = M[ok]
        dirs[j][ok] = m.reflect_directions(d[ok])
        tmax[0] = np.where(ok, np.minimum(tmax[0], t), tmax[0])
    direct_blocked = np.isfinite(tmax[0])
    origins[0][direct_blocked] = np.nan
    dirs[0][direct_blocked] = np.nan
    return origins, dirs, tmax


def _column_at(projector: Projector, O: np.ndarray, D: np.ndarray, t: np.ndarray) -> np.ndarray:
    return projector.project(O + t[:, None] * D)[0]


def triangulate_columns(projector: Projector, origins: np.ndarray, directions: np.ndarray, column_px: np.ndarray,
                        *, t_max: np.ndarray | None = None, iterations: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """Points where rays meet the projector's column ``column_px``.

    Parameters
    ----------
    projector : the projector that coded the columns.
    origins, directions : (n, 3) rays (unit directions), mm.
    column_px : (n,) decoded continuous projector column u.
    t_max : (n,) optional upper bound on the ray parameter (e.g. where the ray meets a mirror).

    Returns
    -------
    points_mm : (n, 3), nan where no valid intersection.
    t_mm : (n,) ray parameter.
    """
    O, D, u = np.asarray(origins, float), np.asarray(directions, float), np.asarray(column_px, float)
    x_t, _ = projector.undistort(u, np.full_like(u, projector.cy_px))
    normal = projector.right[None, :] - x_t[:, None] * projector.axis[None, :]  # the undistorted column plane
    with np.errstate(divide="ignore", invalid="ignore"):
        t = ((projector.center_mm - O) * normal).sum(1) / (D * normal).sum(1)
        for _ in range(iterations):
            h = 1e-3
            f0 = _column_at(projector, O, D, t) - u
            f1 = _column_at(projector, O, D, t + h) - u
            t = t - f0 * h / (f1 - f0)
        ok = np.isfinite(t) & (t > 0) & (np.abs(_column_at(projector, O, D, t) - u) < 1e-3)
    if t_max is not None:
        ok &= t < t_max
    P = O + t[:, None] * D
    P[~ok] = np.nan
    return P, np.where(ok, t, np.nan)
