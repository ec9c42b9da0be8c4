"""The thin-lens camera from labelled grid points at several known heights, and the lens from blur.

Projection (DESIGN.md section 3): a point P images along its chief ray through the lens
centre C, so with camera axes (right, down, look) as the rows of R and ``x = R (P - C)``,
``col = nx/2 - 1/2 + v x0 / (x2 pitch)`` and ``row = ny/2 - 1/2 + v x1 / (x2 pitch)``
(pixel centres at integers, the sensor centred on the optical axis).  The unknowns are C
(3), the rotation (3: tilt of the axis and in-plane rotation) and the image distance v.
Points at several heights separate v from the height of C.

The lens: a point at axial distance z blurs into a disk of diameter
``D = 2 R v |1/z - 1/u| / pitch`` px (``2R|v' - v|/v'`` on the detector), so the blur
diameters of all dots against their axial distances give the front focal distance u and
the aperture radius R; f = u v / (u + v).  Independently, a focus measure per image (the
normalised gradient energy) against height is fitted by a curve peaked at 1/z = 1/u.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation


def grid_points_mm(ij: np.ndarray, pitch_mm: float, shape: tuple[int, int], plane_z_mm: float) -> np.ndarray:
    """World positions of grid points (i, j): ((i-(nx-1)/2) pitch, (j-(ny-1)/2) pitch, z)."""
    nx, ny = shape
    ij = np.asarray(ij, float)
    return np.column_stack([(ij[:, 0] - (nx - 1) / 2) * pitch_mm, (ij[:, 1] - (ny - 1) / 2) * pitch_mm,
                            np.full(len(ij), float(plane_z_mm))])


@dataclass
class CameraGeometry:
    """Pose and image distance of a thin-lens camera (mm)."""

    center_mm: np.ndarray
    rotation: np.ndarray  # rows: right, down, look (world -> camera)
    image_distance_mm: float
    pixel_pitch_mm: float
    nx: int
    ny: int

    @property
    def look(self) -> np.ndarray:
        return self.rotation[2]

    @property
    def up(self) -> np.ndarray:
        return -self.rotation[1]

    @property
    def right(self) -> np.ndarray:
        return self.rotation[0]

    def camera_coords(self, p_mm: np.ndarray) -> np.ndarray:
        return (np.asarray(p_mm, float) - self.center_mm) @ self.rotation.T

    def axial_mm(self, p_mm: np.ndarray) -> np.ndarray:
        return self.camera_coords(p_mm)[:, 2]

    def project(self, p_mm: np.ndarray) -> np.ndarray:
        """(n, 2) image positions (col, row) of world points, pixel centres at integers."""
        x = self.camera_coords(p_mm)
        k = self.image_distance_mm / self.pixel_pitch_mm
        return np.column_stack([self.nx / 2 - 0.5 + k * x[:, 0] / x[:, 2], self.ny / 2 - 0.5 + k * x[:, 1] / x[:, 2]])

    def mm_per_px(self, p_mm: np.ndarray) -> np.ndarray:
        """Size on a plane perpendicular to the axis through each point of one pixel (mm)."""
        return self.axial_mm(p_mm) * self.pixel_pitch_mm / self.image_distance_mm

    def reflected(self, center_mm: np.ndarray, normal: np.ndarray) -> "CameraGeometry":
        """The virtual camera seen in a plane mirror (point on the plane, unit normal)."""
        n = np.asarray(normal, float) / np.linalg.norm(normal)
        Hm = np.eye(3) - 2 * np.outer(n, n)
        c = self.center_mm - 2 * np.dot(self.center_mm - center_mm, n) * n
        return CameraGeometry(c, self.rotation @ Hm, self.image_distance_mm, self.pixel_pitch_mm, self.nx, self.ny)


def _unpack(x: np.ndarray, pitch: float, nx: int, ny: int) -> CameraGeometry:
    return CameraGeometry(x[0:3].copy(), Rotation.from_rotvec(x[3:6]).as_matrix(), float(x[6]), pitch, nx, ny)


def image_scales(views: list[tuple[np.ndarray, np.ndarray]]):
    """Per view (world (n,3), image (n,2)) of a grid plane: its height z (mm), 1/s with s its
    scale (px per mm, from an affine fit), and the affine part A (2x2) and offset t (px)."""
    inv_s, z, A_list, t_list = [], [], [], []
    for P, q in views:
        M = np.column_stack([P[:, :2], np.ones(len(P))])
        sol, *_ = np.linalg.lstsq(M, q, rcond=None)
        A, t = sol[:2].T, sol[2]
        inv_s.append(1 / np.sqrt(abs(np.linalg.det(A))))
        z.append(P[0, 2])
        A_list.append(A)
        t_list.append(t)
    return np.array(z, float), np.array(inv_s), A_list, t_list


def _scale_line(z: np.ndarray, inv_s: np.ndarray) -> tuple[float, float]:
    """beta and the intercept of 1/s = icpt - beta z (beta > 0 when the image grows as it rises)."""
    if np.ptp(z) > 0:
        slope, icpt = np.polyfit(z, inv_s, 1)
        return float(-slope), float(icpt)
    return float("nan"), float(inv_s[0])


class HeightsDisagree(ValueError):
    """The stated heights of the grid's planes contradict the images: as given, the grid's image
    does not grow as it rises."""

    def __init__(self, z: np.ndarray):
        super().__init__("the grid's image does not grow as it rises over the heights given (plane_z_mm "
                         + ", ".join(f"{v:g}" for v in z) + " mm): a height does not match its image")


def odd_height(z: np.ndarray, inv_s: np.ndarray, tol_mm: float = 2.0, tol_fraction: float = 0.01):
    """The view whose stated height ``z`` the others' scales contradict: of the views without
    which the rest lie on one line 1/s = icpt - beta z (beta > 0) within tolerance, the one that
    leaves them on it most closely, if its own 1/s puts it beyond tolerance from its stated
    height.  Tolerance: max(``tol_mm``, ``tol_fraction`` of the distance from the camera to the
    plane), as the full fit's height check uses.  Returns (index, implied height mm), or None
    when the heights agree or no single view explains the disagreement (the rest must hold three
    distinct heights to vouch for a line)."""
    z, inv_s = np.asarray(z, float), np.asarray(inv_s, float)
    best, closest = None, np.inf
    for k in range(len(z)):
        rest = np.arange(len(z)) != k
        if len(set(z[rest])) < 3:
            continue
        beta, icpt = _scale_line(z[rest], inv_s[rest])
        if not beta > 0:
            continue
        camera_z = icpt / beta

        def off(zz, s):
            return np.abs((icpt - s) / beta - zz) - np.maximum(tol_mm, tol_fraction * np.abs(camera_z - zz))

        spread = float(np.max(np.abs((icpt - inv_s[rest]) / beta - z[rest])))
        if np.any(off(z[rest], inv_s[rest]) > 0) or spread >= closest:
            continue
        closest = spread
        best = (k, float((icpt - inv_s[k]) / beta)) if off(z[k], inv_s[k]) > 0 else None
    return best


def initial_geometry(views: list[tuple[np.ndarray, np.ndarray]], pitch_mm: float, nx: int, ny: int) -> CameraGeometry:
    """A camera looking straight down, from an affine fit per height (views: (world (n,3), image (n,2))).

    The scale s of each height obeys 1/s = pitch (C_z - z)/v: a line in z gives v and C_z.
    """
    z, inv_s, A_list, t_list = image_scales(views)
    beta, icpt = _scale_line(z, inv_s)
    if not (np.isfinite(beta) and beta > 0):
        if np.ptp(z) == 0:
            raise ValueError("the grid's image does not grow as it rises: give images at two or more "
                             "distinct heights (the image distance cannot be separated from the camera height)")
        raise HeightsDisagree(z)
    v = pitch_mm / beta
    cz = icpt / beta
    A = A_list[int(np.argmax(inv_s))] if len(A_list) else A_list[0]
    A = np.mean([a / np.sqrt(abs(np.linalg.det(a))) for a in A_list], axis=0)
    Ai = np.linalg.inv(A)
    right = np.array([*Ai[:, 0], 0.0])
    down = np.array([*Ai[:, 1], 0.0])
    U, _, Vt = np.linalg.svd(np.stack([right, down, np.cross(right, down)]))
    Rm = U @ Vt
    cxy = []
    for (P, q), a, t in zip(views, A_list, t_list):
        cxy.append(np.linalg.solve(a, np.array([nx / 2 - 0.5, ny / 2 - 0.5]) - t))
    c = np.array([*np.mean(cxy, axis=0), cz])
    return CameraGeometry(c, Rm, float(v), pitch_mm, nx, ny)


@dataclass
class GeometryFit:
    camera: CameraGeometry
    sigma: dict[str, float]
    residual_px: np.ndarray  # (n, 2) measured - model
    rms_px: float
    covariance: np.ndarray
    names: tuple[str, ...] = ("cx_mm", "cy_mm", "cz_mm", "rx", "ry", "rz", "v_mm")
    notes: list[str] = field(default_factory=list)


def fit_geometry(world_mm: np.ndarray, image_px: np.ndarray, init: CameraGeometry,
                 *, weights: np.ndarray | None = None) -> GeometryFit:
    """Least squares of the reprojection over all points of all heights.

    Parameters
    ----------
    world_mm : ndarray (n, 3)
    image_px : ndarray (n, 2), (col, row), pixel centres at integers
    init : CameraGeometry
    """
    pitch, nx, ny = init.pixel_pitch_mm, init.nx, init.ny
    x0 = np.concatenate([init.center_mm, Rotation.from_matrix(init.rotation).as_rotvec(), [init.image_distance_mm]])
    w = np.ones(len(world_mm)) if weights is None else weights

    def res(x):
        cam = _unpack(x, pitch, nx, ny)
        return ((cam.project(world_mm) - image_px) * w[:, None]).ravel()

    sol = least_squares(res, x0, loss="soft_l1", f_scale=1.0, x_scale="jac")
    sol = least_squares(res, sol.x, x_scale="jac")
    cam = _unpack(sol.x, pitch, nx, ny)
    r = (image_px - cam.project(world_mm))
    dof = max(r.size - len(x0), 1)
    s2 = float((sol.fun**2).sum() / dof)
    try:
        cov = np.linalg.inv(sol.jac.T @ sol.jac) * s2
    except np.linalg.LinAlgError:
        cov = np.full((7, 7), np.nan)
    sig = np.sqrt(np.clip(np.diag(cov), 0, None))
    names = ("cx_mm", "cy_mm", "cz_mm", "rx", "ry", "rz", "v_mm")
    return GeometryFit(cam, dict(zip(names, sig.tolist())), r, float(np.sqrt((r**2).sum(axis=1).mean())), cov)


def angle_sigmas_deg(fit: GeometryFit) -> tuple[float, float]:
    """1-sigma angular uncertainty of look and of the in-plane rotation (deg), from the rotation vector's covariance."""
    c = fit.covariance[3:6, 3:6]
    if not np.all(np.isfinite(c)):
        return float("nan"), float("nan")
    ev = np.linalg.eigvalsh(c)
    look = fit.camera.look
    # rotation about the look axis = in-plane; perpendicular components tilt the axis
    var_in = float(look @ c @ look)
    var_tilt = float(np.clip(np.trace(c) - var_in, 0, None))
    _ = ev
    return float(np.degrees(np.sqrt(var_tilt))), float(np.degrees(np.sqrt(max(var_in, 0))))


# ----------------------------------------------------------------------------- lens
@dataclass
class BlurFit:
    """D = sqrt((K |1/z - 1/u|)^2 + D0^2) px, K = 2 R v / pitch."""

    focus_distance_mm: float
    focus_distance_sigma_mm: float
    k_px_mm: float
    k_sigma: float
    floor_px: float
    rms_px: float

    def diameter_px(self, axial_mm: np.ndarray) -> np.ndarray:
        z = np.asarray(axial_mm, float)
        return np.hypot(self.k_px_mm * (1 / z - 1 / self.focus_distance_mm), self.floor_px)


def fit_blur(axial_mm: np.ndarray, diameter_px: np.ndarray, u0_mm: float) -> BlurFit:
    """Fit the blur-diameter V against axial distance (per dot), robust to outliers."""
    z = np.asarray(axial_mm, float)
    d = np.asarray(diameter_px, float)
    iz = 1 / z

    def res(x):
        k, w, d0 = x
        return np.hypot(k * (iz - w), d0) - d

    # initial slope from the far branch
    k0 = np.median(d / np.maximum(np.abs(iz - 1 / u0_mm), 1e-9))
    best = None
    for w0 in (1 / u0_mm, iz.min(), iz.max(), np.median(iz)):
        sol = least_squares(res, [k0, w0, 0.3], loss="soft_l1", f_scale=0.3,
                            bounds=([0, iz.min() * 0.5, 0], [np.inf, iz.max() * 2, np.inf]), x_scale="jac")
        if best is None or sol.cost < best.cost:
            best = sol
    k, w, d0 = best.x
    r = best.fun
    dof = max(len(d) - 3, 1)
    try:
        cov = np.linalg.inv(best.jac.T @ best.jac) * float((r**2).sum() / dof)
        sk, sw = np.sqrt(max(cov[0, 0], 0)), np.sqrt(max(cov[1, 1], 0))
    except np.linalg.LinAlgError:
        sk = sw = float("nan")
    return BlurFit(float(1 / w), float(sw / w**2), float(k), float(sk), float(d0), float(np.sqrt(np.mean(r**2))))


def focus_measure(unit: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Normalised gradient energy: sum |grad I|^2 / sum I^2 over the grid's region (1/px^2).

    Independent of the brightness; grows as the dots sharpen.
    """
    gy, gx = np.gradient(unit)
    g2 = gx**2 + gy**2
    m = np.ones(unit.shape, bool) if mask is None else mask
    return float(g2[m].sum() / max((unit[m] ** 2).sum(), 1e-30))


@dataclass
class FocusCurve:
    """F = F0 + A / (1 + ((1/z - 1/u) / s)^2) against mean axial distance z."""

    focus_distance_mm: float
    params: np.ndarray

    def value(self, axial_mm: np.ndarray) -> np.ndarray:
        f0, a, w, s = self.params
        return f0 + a / (1 + ((1 / np.asarray(axial_mm, float) - w) / s) ** 2)


def fit_focus_curve(axial_mm: np.ndarray, measure: np.ndarray) -> FocusCurve:
    """Fit a peaked curve in 1/z to the focus measure; its peak is the focal plane (not the best sample)."""
    z = np.asarray(axial_mm, float)
    m = np.asarray(measure, float)
    iz = 1 / z
    k = int(np.argmax(m))
    span = max(np.ptp(iz), 1e-9)

    def res(x):
        f0, a, w, s = x
        return (f0 + a / (1 + ((iz - w) / s) ** 2) - m) / m.max()

    x0 = [m.min() * 0.5, m.max() - m.min() * 0.5, iz[k], span / 4]
    sol = least_squares(res, x0, bounds=([0, 0, iz.min() - span, span / 1000], [np.inf, np.inf, iz.max() + span, 10 * span]))
    return FocusCurve(float(1 / sol.x[2]), sol.x)
