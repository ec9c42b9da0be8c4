"""A projector: a pinhole with radial distortion, a pose, a resolution and a gamma.

Conventions: projector pixel ``(row, col)`` spans ``[col, col+1) x [row, row+1)`` in
continuous coordinates ``(u, v)`` (u along columns); the projector looks along ``axis``,
``right`` is the direction of growing u and ``down`` of growing v, as for the camera
(:mod:`fluxcli.optics.camera`).  Normalised coordinates ``x = X_right / X_axis``, ``y =
X_down / X_axis`` are distorted by ``(1 + k1 r^2 + k2 r^4)`` and mapped to pixels by the
intrinsics ``u = fx x_d + cx``, ``v = fy y_d + cy`` (Brown's radial model, as OpenCV).

Showing a pattern: :class:`PatternDisplay` is the interface; :class:`ImageSink` (the
simulator) keeps the image it was shown.  In a lab the same interface is a full-screen,
borderless window on the projector's display (vsync on, the image drawn 1:1 without
scaling, then a wait of a few frames before the camera exposes):
:class:`fluxcli.hardware.projector.WindowDisplay`.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

__all__ = ["Projector", "PatternDisplay", "ImageSink"]


@dataclass(frozen=True)
class Projector:
    """A pinhole projector with radial distortion.

    Attributes
    ----------
    center_mm : (3,) the centre of projection (mm, world).
    axis, right, down : (3,) orthonormal world directions (axis into the scene).
    width_px, height_px : the panel's resolution (pixels).
    fx_px, fy_px, cx_px, cy_px : intrinsics (pixels).
    k1, k2 : radial distortion coefficients (dimensionless).
    gamma : the panel's response: emitted radiance = (pattern value) ** gamma for values in [0, 1].
    """

    center_mm: np.ndarray
    axis: np.ndarray
    right: np.ndarray
    down: np.ndarray
    width_px: int
    height_px: int
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    k1: float = 0.0
    k2: float = 0.0
    gamma: float = 1.0

    @classmethod
    def from_pose(cls, *, center_mm, look, up, width_px: int, height_px: int, fx_px: float, fy_px: float | None = None,
                  cx_px: float | None = None, cy_px: float | None = None, k1: float = 0.0, k2: float = 0.0,
                  gamma: float = 1.0) -> "Projector":
        """A projector at ``center_mm`` looking along ``look``; ``up`` is the world direction of row 0."""
        n = np.asarray(look, float)
        n = n / np.linalg.norm(n)
        u = np.asarray(up, float)
        u = u - np.dot(u, n) * n
        u = u / np.linalg.norm(u)
        return cls(np.asarray(center_mm, float), n, np.cross(n, u), -u, int(width_px), int(height_px),
                   float(fx_px), float(fx_px if fy_px is None else fy_px),
                   float(width_px / 2 if cx_px is None else cx_px), float(height_px / 2 if cy_px is None else cy_px),
                   float(k1), float(k2), float(gamma))

    @property
    def rotation(self) -> np.ndarray:
        """World -> projector rotation: rows ``right, down, axis``."""
        return np.stack([self.right, self.down, self.axis])

    def _distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r2 = x * x + y * y
        s = 1 + self.k1 * r2 + self.k2 * r2 * r2
        return x * s, y * s

    def project(self, points_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Continuous pixel coordinates ``(u, v)`` and depth along the axis (mm) of points (n, 3).

        Points behind the projector get ``nan`` coordinates."""
        rel = np.asarray(points_mm, float) - self.center_mm
        with np.errstate(invalid="ignore"):
            X = rel @ self.rotation.T
        z = X[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            x, y = X[:, 0] / z, X[:, 1] / z
        xd, yd = self._distort(x, y)
        bad = ~(z > 0)
        u = np.where(bad, np.nan, self.fx_px * xd + self.cx_px)
        v = np.where(bad, np.nan, self.fy_px * yd + self.cy_px)
        return u, v, z

    def undistort(self, u: np.ndarray, v: np.ndarray, iterations: int = 20) -> tuple[np.ndarray, np.ndarray]:
        """Normalised undistorted ``(x, y)`` of pixel coordinates (fixed-point inversion)."""
        xd = (np.asarray(u, float) - self.cx_px) / self.fx_px
        yd = (np.asarray(v, float) - self.cy_px) / self.fy_px
        x, y = xd.copy(), yd.copy()
        for _ in range(iterations):
            r2 = x * x + y * y
            s = 1 + self.k1 * r2 + self.k2 * r2 * r2
            x, y = xd / s, yd / s
        return x, y

    def rays(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Unit world directions (n, 3) of the rays leaving the projector through pixel coordinates."""
        x, y = self.undistort(u, v)
        d = x[:, None] * self.right + y[:, None] * self.down + self.axis
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def radiance(self, pattern: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Relative radiance sent towards pixel coordinates ``(u, v)`` while ``pattern`` is shown.

        ``pattern`` is ``[height_px, width_px]`` with values in [0, 1]; the panel's response
        is ``value ** gamma``; its image is interpolated linearly between pixel centres
        (a projector focused to about one pixel); 0 outside the panel."""
        img = np.clip(np.asarray(pattern, float), 0, 1) ** self.gamma
        u = np.nan_to_num(np.asarray(u, float), nan=-10.0)
        v = np.nan_to_num(np.asarray(v, float), nan=-10.0)
        inside = (u >= 0) & (u < self.width_px) & (v >= 0) & (v < self.height_px)
        x = np.clip(u - 0.5, 0, self.width_px - 1)
        y = np.clip(v - 0.5, 0, self.height_px - 1)
        c0 = np.minimum(np.floor(x).astype(np.int64), self.width_px - 2) if self.width_px > 1 else np.zeros(len(x), np.int64)
        r0 = np.minimum(np.floor(y).astype(np.int64), self.height_px - 2) if self.height_px > 1 else np.zeros(len(y), np.int64)
        c1 = np.minimum(c0 + 1, self.width_px - 1)
        r1 = np.minimum(r0 + 1, self.height_px - 1)
        a, b = x - c0, y - r0
        out = ((1 - a) * (1 - b) * img[r0, c0] + a * (1 - b) * img[r0, c1]
               + (1 - a) * b * img[r1, c0] + a * b * img[r1, c1])
        return np.where(inside, out, 0.0)


class PatternDisplay(ABC):
    """Something that shows an image on a projector's panel."""

    @abstractmethod
    def show(self, pattern: np.ndarray) -> None:
        """Show ``pattern`` (``[height_px, width_px]`` floats in [0, 1]) until the next call."""

    def close(self) -> None:
        """Release the display."""


class ImageSink(PatternDisplay):
    """The simulator's projector display: it keeps what it was shown (``current``)."""

    def __init__(self, projector: Projector):
        self.projector = projector
        self.current = np.zeros((projector.height_px, projector.width_px))

    def show(self, pattern: np.ndarray) -> None:
        pattern = np.asarray(pattern, float)
        if pattern.shape != self.current.shape:
            raise ValueError(f"pattern shape {pattern.shape} is not the panel's {self.current.shape}")
        self.current = pattern
