"""Thin-lens camera, its virtual copies in plane mirrors, and the pixel grid.

Conventions (DESIGN.md section 3): the optical axis ``axis`` points from the lens into
the scene; the front focal plane lies at ``focus_distance_mm`` (u) along it and the
detector at v behind the lens, 1/f = 1/u + 1/v.  Images are indexed ``[row, col]``;
column index grows along ``right`` and row index along ``down`` *as seen in the focal
plane*, so an image shows the scene upright (the world ``up`` of the config at row 0)
exactly as the camera's read-out presents it.  Pixel ``(row, col)`` has flat index
``row * nx + col``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np


@dataclass(frozen=True)
class Aperture:
    """A circular opening centred on the optical axis, ``distance_mm`` in front of the lens."""

    distance_mm: float
    radius_mm: float


@dataclass(frozen=True)
class PlaneMirror:
    """A finite rectangular plane mirror; reflects on the side ``normal`` points to."""

    center_mm: np.ndarray
    normal: np.ndarray
    axis_u: np.ndarray
    axis_v: np.ndarray
    half_size_mm: tuple[float, float]

    @classmethod
    def from_axis(cls, center_mm, normal, axis, size_mm) -> "PlaneMirror":
        n = np.asarray(normal, float)
        n = n / np.linalg.norm(n)
        a = np.asarray(axis, float)
        a = a - np.dot(a, n) * n
        a = a / np.linalg.norm(a)
        return cls(np.asarray(center_mm, float), n, a, np.cross(n, a), (size_mm[0] / 2, size_mm[1] / 2))

    def reflect_points(self, p: np.ndarray) -> np.ndarray:
        d = (p - self.center_mm) @ self.normal
        return p - 2 * d[..., None] * self.normal

    def reflect_directions(self, d: np.ndarray) -> np.ndarray:
        return d - 2 * (d @ self.normal)[..., None] * self.normal

    def contains(self, p_on_plane: np.ndarray) -> np.ndarray:
        r = p_on_plane - self.center_mm
        return (np.abs(r @ self.axis_u) <= self.half_size_mm[0]) & (np.abs(r @ self.axis_v) <= self.half_size_mm[1])


@dataclass(frozen=True)
class ThinLensCamera:
    """A thin-lens camera with a rectangular pixel grid (possibly a mirror's virtual copy)."""

    center_mm: np.ndarray
    axis: np.ndarray
    right: np.ndarray
    down: np.ndarray
    focal_length_mm: float
    aperture_radius_mm: float
    focus_distance_mm: float
    nx: int
    ny: int
    pixel_pitch_mm: float
    apertures: tuple[Aperture, ...] = ()

    @classmethod
    def from_pose(cls, *, lens_center_mm, look, up, focal_length_mm: float, aperture_radius_mm: float,
                  focus_distance_mm: float, nx: int, ny: int, pixel_pitch_mm: float,
                  apertures: tuple[Aperture, ...] = ()) -> "ThinLensCamera":
        n = np.asarray(look, float)
        n = n / np.linalg.norm(n)
        up = np.asarray(up, float)
        up = up - np.dot(up, n) * n
        up = up / np.linalg.norm(up)
        right = np.cross(n, up)
        if focus_distance_mm <= focal_length_mm:
            raise ValueError("focus distance must exceed the focal length")
        return cls(np.asarray(lens_center_mm, float), n, right, -up, float(focal_length_mm),
                   float(aperture_radius_mm), float(focus_distance_mm), int(nx), int(ny),
                   float(pixel_pitch_mm), tuple(apertures))

    # ------------------------------------------------------------------ optics
    @property
    def image_distance_mm(self) -> float:
        """v, the lens-to-detector distance: 1/f = 1/u + 1/v."""
        f, u = self.focal_length_mm, self.focus_distance_mm
        return f * u / (u - f)

    @property
    def magnification(self) -> float:
        """t = v/u (detector size / focal-plane size)."""
        return self.image_distance_mm / self.focus_distance_mm

    @property
    def focal_pixel_mm(self) -> float:
        """Pixel pitch projected onto the focal plane (mm)."""
        return self.pixel_pitch_mm / self.magnification

    @property
    def lens_area_mm2(self) -> float:
        return np.pi * self.aperture_radius_mm**2

    def blur_diameter_px(self, axial_mm: np.ndarray) -> np.ndarray:
        """Diameter of the circle of confusion, in pixels, of points at axial distance z.

        On the focal plane the cone of lines from the point through the lens disk has
        diameter 2R|u - z|/z; the same in focal-plane pixels.  (On the detector this is
        the thin-lens blur 2R|v' - v|/v'.)
        """
        z = np.asarray(axial_mm, float)
        return 2 * self.aperture_radius_mm * np.abs(self.focus_distance_mm - z) / (z * self.focal_pixel_mm)

    # ------------------------------------------------------------------ mapping
    def axial(self, p_mm: np.ndarray) -> np.ndarray:
        return (p_mm - self.center_mm) @ self.axis

    def lens_points(self, unit_disk_xy: np.ndarray) -> np.ndarray:
        """Map points of the unit disk (n, 2) onto the lens aperture (n, 3)."""
        r = self.aperture_radius_mm
        return self.center_mm + r * (unit_disk_xy[:, :1] * self.right + unit_disk_xy[:, 1:] * self.down)

    def focal_plane_hit(self, p_mm: np.ndarray, lens_mm: np.ndarray, axial_p_mm: np.ndarray | None = None) -> np.ndarray:
        """Where the line through ``p`` and the lens point crosses the front focal plane."""
        z = self.axial(p_mm) if axial_p_mm is None else axial_p_mm
        return lens_mm + (self.focus_distance_mm / z)[..., None] * (p_mm - lens_mm)

    def pixel_coords(self, focal_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Continuous (col, row) of focal-plane points; pixel (r, c) spans [c, c+1) x [r, r+1)."""
        rel = focal_mm - (self.center_mm + self.focus_distance_mm * self.axis)
        col = rel @ self.right / self.focal_pixel_mm + self.nx / 2
        row = rel @ self.down / self.focal_pixel_mm + self.ny / 2
        return col, row

    def pixel_index(self, focal_mm: np.ndarray) -> np.ndarray:
        """Flat pixel index (row * nx + col) of focal-plane points, -1 off the sensor."""
        col, row = self.pixel_coords(focal_mm)
        c, r = np.floor(col).astype(np.int64), np.floor(row).astype(np.int64)
        ok = (c >= 0) & (c < self.nx) & (r >= 0) & (r < self.ny)
        return np.where(ok, r * self.nx + c, -1)

    def pixel_centres_focal(self, sub: int = 1) -> np.ndarray:
        """Focal-plane centres of (sub x sub) sub-pixels, shape (ny*sub, nx*sub, 3)."""
        cc = (np.arange(self.nx * sub) + 0.5) / sub - self.nx / 2
        rr = (np.arange(self.ny * sub) + 0.5) / sub - self.ny / 2
        o = self.center_mm + self.focus_distance_mm * self.axis
        p = self.focal_pixel_mm
        return o + p * (cc[None, :, None] * self.right + rr[:, None, None] * self.down)

    def passes_apertures(self, p_mm: np.ndarray, lens_mm: np.ndarray, axial_p_mm: np.ndarray) -> np.ndarray:
        """beta: the segment from ``p`` to the lens passes inside every extra aperture.

        An aperture farther from the lens than the point itself does not constrain it.
        """
        ok = np.ones(len(p_mm), bool)
        for ap in self.apertures:
            s = ap.distance_mm / axial_p_mm
            x = lens_mm + s[:, None] * (p_mm - lens_mm) - self.center_mm
            radial = x - (x @ self.axis)[:, None] * self.axis
            inside = np.einsum("ij,ij->i", radial, radial) <= ap.radius_mm**2
            ok &= inside | (s >= 1)
        return ok

    def mirrored(self, mirror: PlaneMirror) -> "ThinLensCamera":
        """The virtual camera seen in ``mirror``: lens, axes and apertures reflected."""
        return replace(
            self,
            center_mm=mirror.reflect_points(self.center_mm),
            axis=mirror.reflect_directions(self.axis),
            right=mirror.reflect_directions(self.right),
            down=mirror.reflect_directions(self.down),
        )


def sunflower_disk(n: int) -> np.ndarray:
    """``n`` equal-area points on the unit disk (Vogel's golden-angle spiral), shape (n, 2).

    Each point stands for area pi/n; the pattern is deterministic and nearly uniform for
    any n, which makes it a good quadrature for smooth integrands over the lens and an
    even painter of blur disks.
    """
    k = np.arange(n) + 0.5
    r = np.sqrt(k / n)
    a = k * np.pi * (3 - np.sqrt(5))
    return np.stack([r * np.cos(a), r * np.sin(a)], axis=1)
