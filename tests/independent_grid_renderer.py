"""Dot-grid calibration images made without fluxcli: a second, independent renderer.

It imports no ``fluxcli`` code (plain numpy), written from DESIGN.md §3 alone, and it
integrates the other way round from ``fluxcli.calibration.synthetic`` (which traces rays
backwards from sub-pixel points on the focal plane through the lens): here light goes
forwards, from the target to the sensor.

- Target: a plane at height ``z`` (normal +z) carrying a grid of Lambertian discs
  (radius ``dot_radius_mm``, exitance ``J``) centred on the contract's grid points
  ``((i - (nx-1)/2) pitch, (j - (ny-1)/2) pitch)``, on a uniform background ``b·J``.
- Camera: an ideal thin lens, centre ``C``, axis ``n`` into the scene, ``right = n × up``,
  ``down = −up``, aperture disc of radius ``R`` perpendicular to ``n``, front focal plane at
  distance ``u`` (``1/f = 1/u + 1/v``), pixels of ``pitch·u/v`` on the focal plane, pixel
  (col, row) = floor of the focal-plane offset along (right, down) over that size, plus
  (nx/2, ny/2).
- Discs: each disc is covered by a jittered square lattice of points (those outside the
  disc dropped, so the kept cells sample the disc's area without bias); each point sends
  rays to a jittered lattice of points on the lens disc. A ray from ``p`` to lens point
  ``l`` carries ``(J/π) cosθ_s cosθ_l dA_l dS / |l − p|²`` and lands where the line p → l
  meets the focal plane, so the defocus blur, perspective and the box integration over
  each pixel come out of the geometry (an in-focus point lands in one pixel).
- Background: a uniform Lambertian plane has the same radiance ``bJ/π`` everywhere, so a
  pixel receives ``(bJ/π) · A_pixel,focal · A_lens · cos⁴θ / u²`` (θ: the pixel centre's
  angle to the axis); this closed form is used instead of tracing it.
"""

from __future__ import annotations

import numpy as np


class Camera:
    """An ideal thin lens looking at the scene (mm; pixels counted from the top left)."""

    def __init__(self, *, lens_center_mm, look, up, focal_length_mm, focus_distance_mm, aperture_diameter_mm,
                 nx, ny, pixel_pitch_mm):
        n = np.asarray(look, float)
        self.axis = n / np.linalg.norm(n)
        up = np.asarray(up, float)
        up = up - (up @ self.axis) * self.axis
        self.up = up / np.linalg.norm(up)
        self.right = np.cross(self.axis, self.up)
        self.down = -self.up
        self.C = np.asarray(lens_center_mm, float)
        self.f, self.u = float(focal_length_mm), float(focus_distance_mm)
        self.v = 1.0 / (1.0 / self.f - 1.0 / self.u)
        self.R = aperture_diameter_mm / 2
        self.nx, self.ny = int(nx), int(ny)
        self.pix_focal_mm = pixel_pitch_mm * self.u / self.v

    @classmethod
    def tilted_down(cls, *, lens_center_mm, tilt_deg, tilt_azimuth_deg, roll_deg, **kw):
        """Axis ``tilt_deg`` away from −z towards azimuth ``tilt_azimuth_deg``; ``up`` starts as
        (−sin roll, cos roll, 0) and is made perpendicular to the axis."""
        t, a, r = np.radians([tilt_deg, tilt_azimuth_deg, roll_deg])
        look = (np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), -np.cos(t))
        return cls(lens_center_mm=lens_center_mm, look=look, up=(-np.sin(r), np.cos(r), 0.0), **kw)

    @property
    def focal_plane_z_mm(self) -> float:
        return float(self.C[2] + self.u * self.axis[2])

    def pixel_of_ray(self, p, lens):
        """Flat pixel index (row·nx + col) of the rays p → lens (arrays (..., 3)), −1 off the sensor."""
        d = lens - p
        s = self.u / (-(d @ self.axis))  # the line lens + s (p − lens) meets the focal plane
        q = lens - s[..., None] * d - (self.C + self.u * self.axis)
        col = np.floor(q @ self.right / self.pix_focal_mm + self.nx / 2).astype(np.int64)
        row = np.floor(q @ self.down / self.pix_focal_mm + self.ny / 2).astype(np.int64)
        ok = (col >= 0) & (col < self.nx) & (row >= 0) & (row < self.ny)
        return np.where(ok, row * self.nx + col, -1)

    def in_focus_pixel_photons_per_exitance(self) -> float:
        """Photons in an on-axis pixel wholly inside a uniform in-focus patch of exitance 1."""
        return self.pix_focal_mm**2 * np.pi * self.R**2 / (np.pi * self.u**2)


def jittered_disc(radius_mm: float, n_side: int, rng) -> tuple[np.ndarray, float]:
    """Points (k, 2) of a jittered n_side × n_side lattice over the disc's bounding square,
    those inside the disc; each stands for the cell area (returned)."""
    cell = 2 * radius_mm / n_side
    g = (np.arange(n_side) + 0.0) * cell - radius_mm
    x, y = np.meshgrid(g, g)
    x = x.ravel() + rng.uniform(0, cell, x.size)
    y = y.ravel() + rng.uniform(0, cell, y.size)
    keep = x * x + y * y <= radius_mm**2
    return np.column_stack([x[keep], y[keep]]), cell * cell


def render_dot_grid(cam: Camera, plane_z_mm: float, *, pitch_mm: float, shape: tuple[int, int],
                    dot_radius_mm: float, exitance_photons_per_mm2: float, background_fraction: float,
                    rng, dot_side: int = 14, lens_side: int = 9) -> np.ndarray:
    """Mean photons per pixel (ny, nx) of the dot grid at ``plane_z_mm``."""
    J = exitance_photons_per_mm2
    img = np.zeros(cam.ny * cam.nx)
    gx, gy = shape
    centres = [((i - (gx - 1) / 2) * pitch_mm, (j - (gy - 1) / 2) * pitch_mm) for i in range(gx) for j in range(gy)]
    for cx, cy in centres:
        pts, dS = jittered_disc(dot_radius_mm, dot_side, rng)
        p = np.column_stack([pts[:, 0] + cx, pts[:, 1] + cy, np.full(len(pts), plane_z_mm)])
        # each surface point gets its own jittered lattice on the lens (cells outside the disc dropped)
        cell = 2 * cam.R / lens_side
        g = np.arange(lens_side) * cell - cam.R
        gx0, gy0 = (a.ravel() for a in np.meshgrid(g, g))
        lx = gx0[None, :] + rng.uniform(0, cell, (len(p), gx0.size))
        ly = gy0[None, :] + rng.uniform(0, cell, (len(p), gx0.size))
        used = lx * lx + ly * ly <= cam.R**2
        dA = cell * cell
        lens = cam.C + lx[..., None] * cam.right + ly[..., None] * cam.down  # (k, m, 3)
        d = lens - p[:, None, :]
        dist = np.linalg.norm(d, axis=-1)
        cos_s = d[..., 2] / dist  # target normal +z
        cos_l = -(d @ cam.axis) / dist
        w = J / np.pi * cos_s * cos_l * dA * dS / dist**2
        w = np.where(used & (cos_s > 0), w, 0.0)
        pix = cam.pixel_of_ray(p[:, None, :], lens)
        on = pix >= 0
        img += np.bincount(pix[on], weights=w[on], minlength=img.size)
    img = img.reshape(cam.ny, cam.nx)
    # the background: uniform radiance, closed form per pixel (the discs replace it where they lie,
    # so the discs above carry (1 − b) J on top of it)
    cc = (np.arange(cam.nx) + 0.5 - cam.nx / 2) * cam.pix_focal_mm
    rr = (np.arange(cam.ny) + 0.5 - cam.ny / 2) * cam.pix_focal_mm
    r2 = cc[None, :] ** 2 + rr[:, None] ** 2
    cos4 = (cam.u**2 / (cam.u**2 + r2)) ** 2
    bg = background_fraction * J * cam.in_focus_pixel_photons_per_exitance() * cos4
    return (1 - background_fraction) * img + bg
