"""Projector calibration from a grid at known heights (Moreno & Taubin 2012, local homographies).

The grid (the same one ``calibrate`` fits the camera with) lies flat at several known
heights while the projector shows column and row codes.  Around each grid point seen by
the camera, a homography from camera pixels to decoded projector coordinates ``(u, v)`` is
fitted to the decoded pixels of a small window and applied to the grid point's sub-pixel
image position: the grid point's projector coordinates.  Grid points are known in world
coordinates (the grid's frame, plane heights), so the projector follows by resection: a
direct linear transform, then a least-squares fit of intrinsics, radial distortion and
pose (:func:`calibrate_projector`: points whose residual is far beyond the rest are dropped
and the fit repeated).

The panel's gamma (:func:`gamma_from_phase_frames`): the mean of the N phase-shift frames,
relative to white and black, is ``<cos^(2 gamma)>`` = Gamma(gamma + 1/2) / (sqrt(pi) Gamma(gamma + 1)),
0.5 for a linear panel; camera blur and ambient light leave it unchanged (the mean is a
constant fraction of white at every panel pixel; ambient cancels in the differences).

:func:`simulate_board_frames` is the simulated rig's side (a flat matte board at known
heights rendered by :class:`~.render.PatternRenderer` with EMCCD noise); the fit never
sees the projector it was made with.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from .patterns import PatternSet, column_patterns
from .projector import Projector


class ProjectorFitError(ValueError):
    """The board points' decoded projector coordinates cannot give a projector (too few of them,
    or none that one projector explains): bad input, not a bug."""

__all__ = ["row_patterns", "projector_coordinates_at", "fit_projector", "gamma_from_phase_frames",
           "ProjectorCalibrationResult", "calibrate_projector", "simulate_board_frames"]


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
    if not (np.all(np.isfinite(p0)) and np.all(np.isfinite(resid(p0)))):
        raise ProjectorFitError("no projector explains the decoded coordinates: the first estimate from them puts "
                                "board points behind it or at infinity (frames out of order, or of another board?)")
    fit = least_squares(resid, p0, x_scale="jac", method="lm")
    res = resid(fit.x)
    return make(fit.x), np.c_[res[:len(X)], res[len(X):]]


def _mean_fraction(gamma: float) -> float:
    from scipy.special import gammaln

    return float(np.exp(gammaln(gamma + 0.5) - gammaln(gamma + 1.0)) / np.sqrt(np.pi))


def gamma_from_phase_frames(white: np.ndarray, black: np.ndarray, phase_frames: np.ndarray, mask: np.ndarray) -> float:
    """The panel's gamma from the mean of N phase-shift frames (see the module docstring).

    Parameters
    ----------
    white, black : ``[ny, nx]`` camera frames under the full-white and black patterns.
    phase_frames : ``[N, ny, nx]`` frames under the sinusoids ``0.5 + 0.5 cos(...)`` (not
        pre-compensated).
    mask : ``[ny, nx]`` bool, the pixels to use (lit, decoded).

    Returns the gamma (dimensionless) whose mean fraction matches the median over ``mask``;
    nan when fewer than 100 pixels.
    """
    from scipy.optimize import brentq

    if mask.sum() < 100:
        return float("nan")
    frac = (np.asarray(phase_frames, float).mean(0) - black) / np.maximum(white - black, 1e-12)
    m = float(np.median(frac[mask]))
    if not _mean_fraction(5.0) < m < _mean_fraction(0.2):
        return float("nan")
    return float(brentq(lambda g: _mean_fraction(g) - m, 0.2, 5.0))


@dataclass(frozen=True)
class ProjectorCalibrationResult:
    """A fitted projector and what it rests on.

    ``points_mm (n, 3)`` world points used, ``uv_px (n, 2)`` their measured projector
    coordinates, ``residual_px (n, 2)`` measured - model, ``plane (n,)`` index of the height
    each came from, ``rejected`` how many points were dropped as outliers, ``rms_px``."""

    projector: Projector
    points_mm: np.ndarray
    uv_px: np.ndarray
    residual_px: np.ndarray
    plane: np.ndarray
    rejected: int

    @property
    def rms_px(self) -> float:
        return float(np.sqrt(np.mean(np.sum(self.residual_px**2, axis=1)))) if len(self.residual_px) else float("nan")


def calibrate_projector(planes: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]], *, width_px: int,
                        height_px: int, gamma: float = 1.0, half_window: int = 6,
                        reject_sigma: float = 5.0) -> ProjectorCalibrationResult:
    """Fit a projector from a flat board at several heights.

    Parameters
    ----------
    planes : per height ``(points_mm (n, 3), image_xy (n, 2), column_px [ny, nx], row_px [ny, nx])``:
        world points on the board, where the (calibrated) camera sees them (continuous
        (col, row), pixel (r, c) spanning [c, c+1) x [r, r+1)), and the decoded projector
        column and row per camera pixel (nan where masked).
    width_px, height_px : the panel.
    gamma : stored in the result (measure it with :func:`gamma_from_phase_frames`).
    half_window : local homography window half-size (camera pixels).
    reject_sigma : points whose residual exceeds this many robust sigmas are dropped, once.

    Raises ``ValueError`` when fewer than 12 points on at least two heights are decoded.
    """
    X_all, uv_all, k_all = [], [], []
    for k, (X, xy, col, row) in enumerate(planes):
        uv, ok = projector_coordinates_at(xy, col, row, half_window=half_window)
        X_all.append(np.asarray(X, float)[ok]); uv_all.append(uv[ok]); k_all.append(np.full(int(ok.sum()), k))
    X, uv, plane = np.concatenate(X_all), np.concatenate(uv_all), np.concatenate(k_all)
    if len(X) < 12 or len(np.unique(plane)) < 2:
        raise ProjectorFitError(f"only {len(X)} board point(s) on {len(np.unique(plane))} height(s) have decoded "
                                "projector "
                         "coordinates around them; at least 12 on two heights are needed")
    proj, res = fit_projector(X, uv, width_px=width_px, height_px=height_px, gamma=gamma)
    r = np.hypot(res[:, 0], res[:, 1])
    limit = reject_sigma * 1.4826 * max(np.median(r), 1e-6)
    keep = r <= limit
    rejected = int((~keep).sum())
    if rejected and keep.sum() >= 12:
        X, uv, plane = X[keep], uv[keep], plane[keep]
        proj, res = fit_projector(X, uv, width_px=width_px, height_px=height_px, gamma=gamma)
    return ProjectorCalibrationResult(proj, X, uv, res, plane, rejected)


def simulate_board_frames(camera, projector: Projector, heights_mm, *, board_size_mm=(160.0, 160.0),
                          albedo: float = 0.8, period_px: int = 16, n_steps: int = 8, sensor=None,
                          photons_white: float = 3000.0, ambient_photons: float = 20.0, lens_samples: int = 4,
                          seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    """The simulated rig's camera frames of a flat matte board (top at each height, mm) while
    ``projector`` shows the column code, then the row code.  Returns per height
    ``(column_counts [n, ny, nx], row_counts [m, ny, nx])`` (uint16, through ``sensor``, an
    EMCCD model)."""
    from ..surface.mesh import box
    from .patterns import column_patterns
    from .render import PatternRenderer
    from .scan import simulate_frames

    cols = column_patterns(projector.width_px, projector.height_px, period_px=period_px, n_steps=n_steps)
    rows = row_patterns(projector.width_px, projector.height_px, period_px=period_px, n_steps=n_steps)
    hx, hy = board_size_mm[0] / 2, board_size_mm[1] / 2
    out = []
    for k, z in enumerate(heights_mm):
        board = box([-hx, -hy, z - 3.0], [hx, hy, z])
        r = PatternRenderer(camera, [], [(board, albedo)], [], projector, lens_samples=lens_samples, sub=1)
        pair = []
        for j, pats in enumerate((cols, rows)):
            counts, _ = simulate_frames(r, pats, photons_white=photons_white, ambient_photons=ambient_photons,
                                        sensor=sensor, rng=np.random.default_rng([seed, k, j]))
            pair.append(counts)
        out.append((pair[0], pair[1]))
    return out
