"""Sub-pixel centre and defocus blur of each dot: a rendered defocused-disk model fitted per dot.

The image of a flat disk (radius ``a`` px) through a thin lens out of focus is the disk
convolved with the uniform circle of confusion (radius ``b`` px), integrated over the
pixel.  The convolution of two uniform disks is their overlap area, in closed form, so
the model of one dot is ``bg + A * overlap(a, b, |x - x0|) / (pi min(a, b)^2)`` averaged
over ``sub x sub`` points of each pixel.  All dots of an image are fitted at once by a
batched Levenberg-Marquardt (one small normal-equation solve per dot per iteration).

Because the shape is symmetric in ``a`` and ``b``, one dot alone cannot tell the dot's
size from the blur; :func:`resolve_dot_radius` takes the value that is the same (in mm on
the grid) at every height, and the second pass fits ``b`` with ``a`` fixed to it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def disk_overlap(a: np.ndarray, b: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Area common to two disks of radii ``a``, ``b`` whose centres are ``d`` apart (same units squared)."""
    a, b, d = np.broadcast_arrays(np.asarray(a, float), np.asarray(b, float), np.asarray(d, float))
    out = np.zeros(d.shape)
    small = np.minimum(a, b)
    inside = d <= np.abs(a - b)
    out[inside] = np.pi * small[inside] ** 2
    part = (~inside) & (d < a + b)
    aa, bb, dd = a[part], b[part], np.maximum(d[part], 1e-12)
    c1 = np.clip((dd**2 + aa**2 - bb**2) / (2 * dd * aa), -1, 1)
    c2 = np.clip((dd**2 + bb**2 - aa**2) / (2 * dd * bb), -1, 1)
    k = np.clip((-dd + aa + bb) * (dd + aa - bb) * (dd - aa + bb) * (dd + aa + bb), 0, None)
    out[part] = aa**2 * np.arccos(c1) + bb**2 * np.arccos(c2) - 0.5 * np.sqrt(k)
    return out


@dataclass
class DotFits:
    """Per-dot fitted parameters (px; pixel centres at integers).

    ``ok`` is False where the window left the image or the fit failed.
    """

    xy_px: np.ndarray
    amplitude: np.ndarray
    background: np.ndarray
    radius_a_px: np.ndarray
    radius_b_px: np.ndarray
    rms: np.ndarray
    ok: np.ndarray


_MIN_R = 0.15  # px: keeps the model smooth in its parameters near focus


def _shape(a, b, d):
    a = np.maximum(np.abs(a), _MIN_R)
    b = np.maximum(np.abs(b), _MIN_R)
    return disk_overlap(a, b, d) / (np.pi * np.minimum(a, b) ** 2)


def _model(p: np.ndarray, X: np.ndarray, Y: np.ndarray, sub: int, fixed: np.ndarray | None = None) -> np.ndarray:
    """p (n, 6): x0, y0, A, bg, a, b.  X, Y (m*sub*sub,) sub-sample offsets.  Returns (n, m).

    ``fixed`` (n, m*sub*sub): light of the neighbouring dots inside each window (kept fixed).
    """
    d = np.hypot(X[None, :] - p[:, 0:1], Y[None, :] - p[:, 1:2])
    k = p[:, 2:3] * _shape(p[:, 4:5], p[:, 5:6], d)
    if fixed is not None:
        k = k + fixed
    k = k.reshape(len(p), -1, sub * sub).mean(axis=2)
    return p[:, 3:4] + k


def fit_dots(unit: np.ndarray, xy_px: np.ndarray, spacing_px: float, *, radius_a_px: np.ndarray | None = None,
             neighbours: "DotFits | None" = None, sub: int = 3, iterations: int = 30) -> DotFits:
    """Fit the defocused-disk model to every dot.

    Parameters
    ----------
    unit : ndarray (ny, nx)
        Image, background ~0 and dots bright (:func:`fluxcli.calibration.grid.to_unit`).
    xy_px : ndarray (n, 2)
        Starting centres (col, row).
    spacing_px : float
        Distance between neighbouring dots (px): the fit window is a disk of half of it.
    radius_a_px : ndarray (n,), optional
        Fix the dot radius (px) and fit only the blur radius.
    neighbours : DotFits, optional
        A previous fit of the same dots: each dot's neighbours (within 1.6 spacings) are
        drawn from it into the window, which then grows to 0.75 spacing (their blurred
        edges are modelled instead of biasing this dot's blur).
    """
    ny, nx = unit.shape
    n = len(xy_px)
    win = 0.75 if neighbours is not None else 0.5
    w = int(np.clip(np.ceil(win * spacing_px), 2, 40))
    off = np.arange(-w, w + 1)
    oy, ox = np.meshgrid(off, off, indexing="ij")
    inside = (ox**2 + oy**2) <= (win * spacing_px + 0.5) ** 2
    ox, oy = ox[inside], oy[inside]
    s = (np.arange(sub) + 0.5) / sub - 0.5
    sy, sx = np.meshgrid(s, s, indexing="ij")
    c = np.rint(xy_px).astype(int)
    ok = (c[:, 0] - w >= 0) & (c[:, 0] + w < nx) & (c[:, 1] - w >= 0) & (c[:, 1] + w < ny)
    cc = np.where(ok[:, None], c, 0)
    data = unit[cc[:, 1:2] + oy[None], cc[:, 0:1] + ox[None]]  # (n, m)
    # sub-sample coordinates relative to each dot's integer centre (same for all dots)
    X = (ox[:, None] + sx.ravel()[None]).ravel()
    Y = (oy[:, None] + sy.ravel()[None]).ravel()
    p = np.zeros((n, 6))
    p[:, 0:2] = xy_px - cc
    edge = np.abs(ox) + np.abs(oy) >= w
    p[:, 3] = np.median(data[:, edge], axis=1) if edge.any() else 0.0
    p[:, 2] = np.maximum(data.max(axis=1) - p[:, 3], 1e-3)
    mass = np.clip(data - p[:, 3:4], 0, None).sum(axis=1) / p[:, 2]
    r0 = np.sqrt(np.maximum(mass, 1.0) / np.pi)
    if radius_a_px is None:
        p[:, 4], p[:, 5] = r0, 0.5 * r0
        free = np.arange(6)
    else:
        p[:, 4] = radius_a_px
        p[:, 5] = np.maximum(np.sqrt(np.maximum(r0**2 - radius_a_px**2, 0)) * 1.5, 0.4)
        free = np.array([0, 1, 2, 3, 5])
    lam = np.full(n, 1e-2)

    fixed = None
    if neighbours is not None:
        from scipy.spatial import cKDTree

        nbx = neighbours.xy_px
        dd, ii = cKDTree(nbx).query(xy_px, k=min(9, len(nbx)), distance_upper_bound=1.6 * spacing_px)
        fixed = np.zeros((n, X.size))
        for j in range(dd.shape[1]):
            have = np.isfinite(dd[:, j]) & (dd[:, j] > 0.3 * spacing_px)
            if not have.any():
                continue
            m = ii[have, j]
            rel = nbx[m] - cc[have]
            d = np.hypot(X[None, :] - rel[:, 0:1], Y[None, :] - rel[:, 1:2])
            fixed[have] += neighbours.amplitude[m, None] * _shape(neighbours.radius_a_px[m, None],
                                                                   neighbours.radius_b_px[m, None], d)

    def residual(q):
        return _model(q, X, Y, sub, fixed) - data

    def residual_of(q, rows):
        return _model(q, X, Y, sub, None if fixed is None else fixed[rows]) - data[rows]

    r = residual(p)
    cost = (r**2).sum(axis=1)
    eps = np.array([1e-3, 1e-3, 1e-4, 1e-4, 1e-3, 1e-3])
    active = np.ones(n, bool)
    for _ in range(iterations):
        act = np.flatnonzero(active)
        if len(act) == 0:
            break
        pa, ra = p[act], r[act]
        J = np.empty((len(act), r.shape[1], len(free)))
        for k, f in enumerate(free):
            q = pa.copy()
            step = eps[f] * np.maximum(1.0, np.abs(pa[:, f])) if f in (2, 3) else np.full(len(act), eps[f])
            q[:, f] += step
            J[:, :, k] = (residual_of(q, act) - ra) / step[:, None]
        JtJ = np.einsum("nmi,nmj->nij", J, J)
        g = np.einsum("nmi,nm->ni", J, ra)
        Dg = np.einsum("nii->ni", JtJ)
        A = JtJ + lam[act, None, None] * np.einsum("ni,ij->nij", Dg + 1e-12, np.eye(len(free)))
        try:
            delta = -np.linalg.solve(A, g[..., None])[..., 0]
        except np.linalg.LinAlgError:
            delta = -g / (np.einsum("nii->ni", A) + 1e-12)
        q = pa.copy()
        q[:, free] += delta
        q[:, 4:6] = np.abs(q[:, 4:6])
        rq = residual_of(q, act)
        cq = (rq**2).sum(axis=1)
        better = cq < cost[act]
        upd = act[better]
        p[upd], r[upd], cost[upd] = q[better], rq[better], cq[better]
        lam[act] = np.clip(np.where(better, lam[act] * 0.3, lam[act] * 10), 1e-7, 1e7)
        small = np.abs(delta[:, :2]).max(axis=1) < 2e-4
        active[act[(better & small) | (lam[act] >= 1e7)]] = False
    a = np.maximum(np.abs(p[:, 4]), _MIN_R)
    b = np.maximum(np.abs(p[:, 5]), _MIN_R)
    moved = np.hypot(*(p[:, 0:2] + cc - xy_px).T)
    good = ok & (p[:, 2] > 0) & (moved < 0.5 * spacing_px) & np.isfinite(p).all(axis=1)
    rms = np.sqrt(cost / r.shape[1])
    return DotFits(p[:, 0:2] + cc, p[:, 2], p[:, 3], a, b, rms, good)


def resolve_dot_radius(lo_mm_per_image: list[np.ndarray], hi_mm_per_image: list[np.ndarray]) -> float:
    """The dot radius (mm on the grid): the one of each dot's two fitted radii that agrees across heights.

    For every image the dot radius is either the smaller or the larger of the two fitted
    radii (the other being the blur); the candidate that is nearest to one of the two in
    every image wins.
    """
    lo = np.array([np.median(x) for x in lo_mm_per_image if len(x)])
    hi = np.array([np.median(x) for x in hi_mm_per_image if len(x)])
    cands = np.concatenate([lo, hi])
    cost = [np.sum(np.minimum(np.abs(lo - c), np.abs(hi - c)) / c) for c in cands]
    return float(cands[int(np.argmin(cost))])
