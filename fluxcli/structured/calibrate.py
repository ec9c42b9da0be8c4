"""Projector calibration from a grid at known heights (Moreno & Taubin 2012, local homographies).

The grid (the same one ``calibrate`` fits the camera with) lies flat at several known
heights while the projector shows column and row codes.  Around each grid point seen by
the camera, a homography from camera pixels to decoded projector coordinates ``(u, v)`` is
fitted to the decoded pixels of a small window and applied to the grid point's sub-pixel
image position: the grid point's projector coordinates.  Grid points are known in world
coordinates (the grid's frame, plane heights), so the projector follows by resection: a
direct linear transform, then a least-squares fit of intrinsics, radial distortion and
pose.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from .patterns import PatternSet, column_patterns
from .projector import Projector

__all__ = ["row_patterns", "projector_coordinates_at", "fit_projector"]


def row_patterns(width_px: int, height_px: int, **kw) -> PatternSet:
    """The column code of :func:`column_patterns` turned to code the panel's rows."""
    p = column_patterns(height_px, width_px, **kw)
    return PatternSet(np.ascontiguousarray(p.frames.transpose(0, 2, 1)), p.period_px, p.n_steps, p.n_gray)


def _homography(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """3x3 H with dst ~ H src (normalised DLT), src/dst (n, 2), n >= 4."""
    def norm(p):
        c = p.mean(0)
        s = np.sqrt(2) / max(np.mean(np.linalg.norm(p - c, axis=1)), 1e-12)
        return np.array([[s, 0, -s * c[0]], [0, s, -s * c[1]], [0, 0, 1]])
    Ts, Td = norm(src), norm(dst)
    a = (Ts @ np.c_[src, np.ones(len(src))].T).T
    b = (Td @ np.c_[dst, np.ones(len(dst))].T).T
    rows = []
    for (x, y, _), (u, v, _) in zip(a, b):
        rows.append([-x, -y, -1, 0, 0, 0, u * x, u * y, u])
        rows.append([0, 0, 0, -x, -y, -1, v * x, v * y, v])
    H = np.linalg.svd(np.asarray(rows), full_matrices=False)[2][-1].reshape(3, 3)
    return np.linalg.inv(Td) @ H @ Ts


def projector_coordinates_at(image_xy: np.ndarray, u_px: np.ndarray, v_px: np.ndarray, *,
                             half_window: int = 6, min_pixels: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """Projector ``(u, v)`` at sub-pixel camera positions by local homographies.

    Parameters
    ----------
    image_xy : (n, 2) continuous camera (col, row) of grid points (pixel (r, c) spans [c, c+1) x [r, r+1)).
    u_px, v_px : ``[ny, nx]`` decoded projector column and row per camera pixel (nan where masked).
    half_window : the window is (2 half_window + 1)^2 camera pixels.
    min_pixels : fewer decoded pixels in the window: no result.

    Returns ``uv (n, 2)`` (nan where none) and ``ok (n,)``.
    """
    ny, nx = u_px.shape
    out = np.full((len(image_xy), 2), np.nan)
    for k, (x, y) in enumerate(np.asarray(image_xy, float)):
        c0, r0 = int(np.floor(x)), int(np.floor(y))
        rs = slice(max(r0 - half_window, 0), min(r0 + half_window + 1, ny))
        cs = slice(max(c0 - half_window, 0), min(c0 + half_window + 1, nx))
        uu, vv = u_px[rs, cs], v_px[rs, cs]
        rr, cc = np.mgrid[rs, cs]
        ok = np.isfinite(uu) & np.isfinite(vv)
        if ok.sum() < min_pixels:
            continue
        H = _homography(np.c_[cc[ok] + 0.5, rr[ok] + 0.5], np.c_[uu[ok], vv[ok]])
        p = H @ np.array([x, y, 1.0])
        out[k] = p[:2] / p[2]
    return out, np.isfinite(out[:, 0])


def _dlt(X: np.ndarray, uv: np.ndarray) -> np.ndarray:
    rows = []
    for (x, y, z), (u, v) in zip(X, uv):
        rows.append([x, y, z, 1, 0, 0, 0, 0, -u * x, -u * y, -u * z, -u])
        rows.append([0, 0, 0, 0, x, y, z, 1, -v * x, -v * y, -v * z, -v])
    return np.linalg.svd(np.asarray(rows), full_matrices=False)[2][-1].reshape(3, 4)


def fit_projector(points_mm: np.ndarray, uv_px: np.ndarray, *, width_px: int, height_px: int,
                  gamma: float = 1.0) -> tuple[Projector, np.ndarray]:
    """Projector intrinsics, radial distortion (k1, k2) and pose from world points and their
    projector coordinates (points on two or more planes).  Returns the projector and the
    residuals (n, 2) in projector pixels."""
    X, uv = np.asarray(points_mm, float), np.asarray(uv_px, float)
    P = _dlt(X, uv)
    M = P[:, :3]
    if np.linalg.det(M) < 0:
        P, M = -P, -M
    center = -np.linalg.solve(M, P[:, 3])
    # RQ decomposition of M = K R
    q, r = np.linalg.qr(np.flipud(M).T)
    R = np.flipud(q.T)
    K = np.flipud(np.fliplr(r.T))
    D = np.diag(np.sign(np.diag(K)))
    K, R = K @ D, D @ R
    K = K / K[2, 2]
    if np.linalg.det(R) < 0:
        R = -R

    def make(p):
        fx, fy, cx, cy, k1, k2 = p[:6]
        Rm = Rotation.from_rotvec(p[6:9]).as_matrix()
        return Projector(p[9:12].copy(), Rm[2], Rm[0], Rm[1], width_px, height_px, fx, fy, cx, cy, k1, k2, gamma)

    def resid(p):
        u, v, _ = make(p).project(X)
        return np.r_[u - uv[:, 0], v - uv[:, 1]]

    p0 = np.r_[K[0, 0], K[1, 1], K[0, 2], K[1, 2], 0.0, 0.0, Rotation.from_matrix(R).as_rotvec(), center]
    fit = least_squares(resid, p0, x_scale="jac", method="lm")
    res = resid(fit.x)
    return make(fit.x), np.c_[res[:len(X)], res[len(X):]]
