"""Render a flat calibration target through a thin-lens camera by ray tracing (sample data, tests).

This is a forward model *independent of the fitting code*: per pixel, ``sub x sub``
sub-pixel points on the front focal plane, and per sub-pixel ``lens_samples`` points on
the lens disk (a randomly rotated golden-angle spiral); every line lens point -> focal
point is followed to the target plane ``z = plane_z_mm`` and the pattern is evaluated
exactly there.  Each ray carries the etendue ``cos^4(theta) dA_lens dA_focal / u^2``
(theta: angle to the optical axis) times the target radiance ``J / pi`` (Lambertian), so
the image is in photons when the exitance is in photons per mm^2.  Defocus blur,
perspective, natural vignetting and pixel integration all come out of the geometry.
Mirror views are rendered by tracing the same rays from the camera reflected in the mirror
(the virtual camera), clipped to the mirror rectangle.
"""

from __future__ import annotations

import numpy as np

from ..optics.camera import PlaneMirror, ThinLensCamera, sunflower_disk


def dot_grid_pattern(x_mm: np.ndarray, y_mm: np.ndarray, *, pitch_mm: float, shape: tuple[int, int],
                     dot_radius_mm: float) -> np.ndarray:
    """1 inside a dot of the grid, 0 elsewhere (the contract's grid: centred on the origin).

    Grid point (i, j) lies at ((i - (nx-1)/2) pitch, (j - (ny-1)/2) pitch).
    """
    nx, ny = shape
    i = np.clip(np.rint(x_mm / pitch_mm + (nx - 1) / 2), 0, nx - 1)
    j = np.clip(np.rint(y_mm / pitch_mm + (ny - 1) / 2), 0, ny - 1)
    dx = x_mm - (i - (nx - 1) / 2) * pitch_mm
    dy = y_mm - (j - (ny - 1) / 2) * pitch_mm
    return (dx * dx + dy * dy <= dot_radius_mm**2).astype(float)


def checker_pattern(x_mm: np.ndarray, y_mm: np.ndarray, *, pitch_mm: float, shape: tuple[int, int]) -> np.ndarray:
    """A checkerboard whose inner corners are the contract's grid points (``shape`` = inner corners).

    The board has (nx+1) x (ny+1) squares; outside it the value is 0.5 (grey surround).
    """
    nx, ny = shape
    u = x_mm / pitch_mm + (nx + 1) / 2
    v = y_mm / pitch_mm + (ny + 1) / 2
    inside = (u >= 0) & (u < nx + 1) & (v >= 0) & (v < ny + 1)
    val = ((np.floor(u) + np.floor(v)) % 2).astype(float)
    return np.where(inside, val, 0.5)


def render_plane(camera: ThinLensCamera, plane_z_mm: float, pattern, *, exitance_photons_per_mm2: float = 1.0,
                 background_fraction: float = 0.0, sub: int = 3, lens_samples: int = 64,
                 mirror: PlaneMirror | None = None, occluders: tuple[PlaneMirror, ...] = (),
                 rng: np.random.Generator | None = None) -> np.ndarray:
    """Photons per pixel of a flat Lambertian target at ``z = plane_z_mm`` (image [ny, nx]).

    Parameters
    ----------
    camera : ThinLensCamera
        The real camera.
    plane_z_mm : float
        Height of the target plane (mm, world z).
    pattern : callable (x_mm, y_mm) -> array in [0, 1]
        Relative exitance on the plane; the exitance is
        ``exitance_photons_per_mm2 * (background_fraction + (1 - background_fraction) * pattern)``.
    sub : int
        Sub-pixels per pixel side.
    lens_samples : int
        Lens points per sub-pixel.
    mirror : PlaneMirror, optional
        Render the view in this mirror instead of the direct view (only rays crossing
        the mirror plane inside its rectangle, between the plane and the lens, count).
    occluders : tuple of PlaneMirror
        Rectangles that block the direct view (the mirrors' backs and fronts).
    rng : numpy.random.Generator, optional
        Rotates the lens pattern per sub-pixel (default seed 0).
    """
    rng = np.random.default_rng(0) if rng is None else rng
    cam = camera if mirror is None else camera.mirrored(mirror)
    focal = cam.pixel_centres_focal(sub)  # (ny*sub, nx*sub, 3)
    disk = sunflower_disk(lens_samples)
    u = cam.focus_distance_mm
    R = cam.aperture_radius_mm
    weight0 = (np.pi * R**2 / lens_samples) * (cam.focal_pixel_mm / sub) ** 2 / u**2 / np.pi
    ny, nx = cam.ny, cam.nx
    out = np.zeros((ny * sub, nx * sub))
    rows_per_chunk = max(1, 400_000 // (nx * sub * lens_samples))
    for r0 in range(0, ny * sub, rows_per_chunk):
        F = focal[r0:r0 + rows_per_chunk].reshape(-1, 3)
        ang = rng.uniform(0, 2 * np.pi, len(F))
        c, s = np.cos(ang)[:, None], np.sin(ang)[:, None]
        dx = c * disk[None, :, 0] - s * disk[None, :, 1]
        dy = s * disk[None, :, 0] + c * disk[None, :, 1]
        L = cam.center_mm + R * (dx[..., None] * cam.right + dy[..., None] * cam.down)  # (n, k, 3)
        d = F[:, None, :] - L
        dn = np.linalg.norm(d, axis=-1)
        cos_t = (d @ cam.axis) / dn
        w = cos_t**4
        if mirror is not None:
            # The virtual ray L -> F: its part in front of the mirror plane is real after reflection.
            # Reflect it back to the real world: start at the real lens, reach the mirror, then the plane.
            Lr = mirror.reflect_points(L)
            dr = mirror.reflect_directions(d)
            t_m = ((mirror.center_mm - Lr) @ mirror.normal) / (dr @ mirror.normal)
            hit_m = Lr + t_m[..., None] * dr
            ok = (t_m > 0) & mirror.contains(hit_m)
            # After reflection the ray continues along the virtual direction from the mirror point.
            t_p = (plane_z_mm - hit_m[..., 2]) / d[..., 2]
            P = hit_m + t_p[..., None] * d
            ok &= t_p > 0
        else:
            t_p = (plane_z_mm - L[..., 2]) / d[..., 2]
            P = L + t_p[..., None] * d
            ok = t_p > 0
            for m in occluders:
                with np.errstate(divide="ignore", invalid="ignore"):
                    t_o = ((m.center_mm - L) @ m.normal) / (d @ m.normal)
                hit = L + t_o[..., None] * d
                ok &= ~((t_o > 0) & (t_o < t_p) & m.contains(hit))
        val = background_fraction + (1 - background_fraction) * pattern(P[..., 0], P[..., 1])
        out[r0:r0 + rows_per_chunk] = (np.where(ok, val, 0) * w).sum(axis=1).reshape(-1, nx * sub)
    img = out.reshape(ny, sub, nx, sub).sum(axis=(1, 3))
    return img * weight0 * exitance_photons_per_mm2


def camera_looking_down(*, lens_center_mm, tilt_deg: float, tilt_azimuth_deg: float, roll_deg: float,
                        focal_length_mm: float, focus_distance_mm: float, aperture_diameter_mm: float,
                        nx: int, ny: int, pixel_pitch_mm: float) -> ThinLensCamera:
    """A camera above the grid: optical axis tilted ``tilt_deg`` from -z (towards azimuth), rolled by ``roll_deg``."""
    t, a, r = np.radians([tilt_deg, tilt_azimuth_deg, roll_deg])
    look = np.array([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), -np.cos(t)])
    up0 = np.array([-np.sin(r), np.cos(r), 0.0])
    return ThinLensCamera.from_pose(lens_center_mm=lens_center_mm, look=look, up=up0, focal_length_mm=focal_length_mm,
                                    aperture_radius_mm=aperture_diameter_mm / 2, focus_distance_mm=focus_distance_mm,
                                    nx=nx, ny=ny, pixel_pitch_mm=pixel_pitch_mm)


def render_grid_set(camera: ThinLensCamera, heights_mm, *, pitch_mm: float, shape: tuple[int, int],
                    dot_radius_mm: float, peak_photons: float, background_fraction: float = 0.05,
                    sub: int = 3, lens_samples: int = 64, seed: int = 0, noise_model=None) -> list[np.ndarray]:
    """Dot-grid images at several heights: photons (float) or, with an EMCCD ``noise_model``, uint16 counts.

    ``peak_photons`` is the photons a pixel fully inside an in-focus dot receives on axis.
    """
    from ..imaging.noise import emccd_counts

    rng = np.random.default_rng(seed)
    # exitance giving peak_photons per pixel on axis in focus: pixel footprint^2 * etendue per mm^2
    u = camera.focus_distance_mm
    R = camera.aperture_radius_mm
    per_mm2 = camera.focal_pixel_mm**2 * (np.pi * R**2) / (np.pi * u**2)
    exitance = peak_photons / per_mm2

    def pattern(x, y):
        return dot_grid_pattern(x, y, pitch_mm=pitch_mm, shape=shape, dot_radius_mm=dot_radius_mm)

    out = []
    for z in heights_mm:
        img = render_plane(camera, float(z), pattern, exitance_photons_per_mm2=exitance,
                           background_fraction=background_fraction, sub=sub, lens_samples=lens_samples, rng=rng)
        if noise_model is not None:
            img = emccd_counts(img, noise_model, rng).astype(np.uint16)
        else:
            img = img.astype(np.float32)
        out.append(img)
    return out
