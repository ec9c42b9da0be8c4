"""Refine a plane mirror from the grid seen in its view (virtual camera = real camera reflected).

Starting from the approximate plane, the grid points are predicted through the virtual
camera (only those whose line of sight crosses the mirror rectangle), matched to the dots
found in the image, and the plane (normal: 2 angles, offset along it: 1) is fitted by least
squares of the reprojection over all images; match and fit alternate with a shrinking
match radius.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial import cKDTree

from .geometry import CameraGeometry, grid_points_mm
from .grid import blob_points, to_unit


class MirrorFitError(ValueError):
    """The grid cannot be used in a mirror's view (too few points matched): bad input, not a bug."""


@dataclass
class MirrorFit:
    center_mm: np.ndarray
    normal: np.ndarray
    axis: np.ndarray
    rms_px: float
    n_points: int
    normal_sigma_deg: float
    offset_sigma_mm: float
    normal_change_deg: float
    offset_change_mm: float
    warnings: list[str] = field(default_factory=list)


def _tangent_basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.array([1.0, 0, 0]) if abs(n[0]) < 0.9 else np.array([0, 1.0, 0])
    t1 = np.cross(n, a)
    t1 /= np.linalg.norm(t1)
    return t1, np.cross(n, t1)


def _visible(cam_v: CameraGeometry, P: np.ndarray, center, normal, axis_u, axis_v, half) -> np.ndarray:
    """Grid points whose virtual line of sight crosses the mirror rectangle, in front of the camera, in the image."""
    c = cam_v.center_mm
    d = P - c
    dn = d @ normal
    with np.errstate(divide="ignore", invalid="ignore"):
        t = ((center - c) @ normal) / dn
    M = c + t[:, None] * d
    r = M - center
    inside = (np.abs(r @ axis_u) <= half[0]) & (np.abs(r @ axis_v) <= half[1]) & (t > 0) & (t < 1)
    x = cam_v.camera_coords(P)
    q = cam_v.project(P)
    inimg = (x[:, 2] > 0) & (q[:, 0] > 1) & (q[:, 0] < cam_v.nx - 2) & (q[:, 1] > 1) & (q[:, 1] < cam_v.ny - 2)
    front = ((P - center) @ normal) > 0
    return inside & inimg & front


def refine_mirrors(images: list[np.ndarray], heights_mm: list[float], camera: CameraGeometry, *, center_mm: np.ndarray,
                   normal: np.ndarray, axis: np.ndarray, size_mm: tuple[float, float], pitch_mm: float,
                   shape: tuple[int, int], min_points: int = 8) -> MirrorFit:
    """Fit one mirror plane to the grid dots seen in its view.

    Parameters
    ----------
    images : list of (ny, nx) arrays, heights_mm : list of float
        The calibration images and their grid heights.
    camera : CameraGeometry
        The real camera, already calibrated from the direct view.
    center_mm, normal, axis, size_mm
        The mirror as configured (approximate): rectangle centre, reflecting-side normal,
        first side direction, side lengths.
    """
    n0 = np.asarray(normal, float) / np.linalg.norm(normal)
    c0 = np.asarray(center_mm, float)
    d0 = float(c0 @ n0)
    t1, t2 = _tangent_basis(n0)
    half = (size_mm[0] / 2, size_mm[1] / 2)
    nx, ny = shape
    allij = np.stack(np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij"), -1).reshape(-1, 2)
    blobs = [blob_points(to_unit(im))[0] for im in images]
    trees = [cKDTree(b) if len(b) else None for b in blobs]

    def plane(x):
        n = n0 + x[0] * t1 + x[1] * t2
        n /= np.linalg.norm(n)
        d = d0 + x[2]
        return n, d

    def frame(x):
        n, d = plane(x)
        c = c0 + (d - c0 @ n) * n
        au = np.asarray(axis, float) - (np.asarray(axis, float) @ n) * n
        au /= np.linalg.norm(au)
        return n, c, au, np.cross(n, au)

    def match(x, frac):
        """Grid points (world) paired with dots (image) within ``frac`` of the predicted spacing, and the
        distances in spacings, for the plane x (one dot per point)."""
        n, c, au, av = frame(x)
        cam_v = camera.reflected(c, n)
        W, Q, dists = [], [], []
        for k, z in enumerate(heights_mm):
            if trees[k] is None:
                continue
            P = grid_points_mm(allij, pitch_mm, shape, z)
            vis = _visible(cam_v, P, c, n, au, av, half)
            if vis.sum() < 2:
                continue
            q = cam_v.project(P[vis])
            sp = float(np.median(cKDTree(q).query(q, k=2)[0][:, 1]))  # the predicted local spacing
            dist, idx = trees[k].query(q)
            ok = dist < frac * sp
            _, first = np.unique(idx[ok], return_index=True)
            sel = np.flatnonzero(ok)[first]
            W.append(P[vis][sel])
            Q.append(blobs[k][idx[sel]])
            dists.extend((dist[sel] / sp).tolist())
        return W, Q, dists

    def score(x, frac):
        """(matched points, median distance) of the plane x: a coarse search needs no derivatives."""
        _, _, dists = match(x, frac)
        return len(dists), (np.median(dists) if dists else 1.0)

    # coarse search around the configured plane (+-3 deg, +-2 mm): the start must match the right dots
    best_x, best = np.zeros(3), score(np.zeros(3), 0.3)
    for a1 in np.radians(np.arange(-3, 3.01, 0.75)):
        for a2 in np.radians(np.arange(-3, 3.01, 0.75)):
            for dz in np.arange(-2, 2.01, 0.5):
                xx = np.array([a1, a2, dz])
                sc = score(xx, 0.3)
                if sc[0] > best[0] or (sc[0] == best[0] and sc[1] < best[1]):
                    best_x, best = xx, sc
    x = best_x
    matches = None
    for radius_frac in (0.45, 0.3, 0.2, 0.2):
        W, Q, _ = match(x, radius_frac)
        if not W or sum(len(w) for w in W) < min_points:
            raise MirrorFitError(f"only {sum(len(w) for w in W) if W else 0} grid points were matched in the "
                                 "mirror's "
                             "view (the approximate mirror in system.mirrors may be too far off, or the grid is not "
                             "seen in it)")
        Wm, Qm = np.concatenate(W), np.concatenate(Q)
        matches = (Wm, Qm)

        def res(xx):
            nn, cc, _, _ = frame(xx)
            return (camera.reflected(cc, nn).project(Wm) - Qm).ravel()

        sol = least_squares(res, x, loss="soft_l1", f_scale=0.5, x_scale="jac")
        x = sol.x
    Wm, Qm = matches
    sol = least_squares(lambda xx: (camera.reflected(frame(xx)[1], frame(xx)[0]).project(Wm) - Qm).ravel(), x)
    x = sol.x
    r = sol.fun.reshape(-1, 2)
    rms = float(np.sqrt((r**2).sum(axis=1).mean()))
    dof = max(r.size - 3, 1)
    try:
        cov = np.linalg.inv(sol.jac.T @ sol.jac) * float((sol.fun**2).sum() / dof)
        sn = float(np.degrees(np.sqrt(max(cov[0, 0] + cov[1, 1], 0))))
        so = float(np.sqrt(max(cov[2, 2], 0)))
    except np.linalg.LinAlgError:
        sn = so = float("nan")
    n, c, au, _ = frame(x)
    warnings = []
    if rms > 0.5:
        warnings.append(f"RMS reprojection in the mirror view is {rms:.2f} px (above 0.5 px)")
    return MirrorFit(c, n, au, rms, len(Wm), sn, so, float(np.degrees(np.arccos(np.clip(n @ n0, -1, 1)))),
                     float(abs(x[2])), warnings)
