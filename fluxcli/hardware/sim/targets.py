"""What the simulated rig shows its camera for calibration frames: the grid on the stage, an even light.

The operator of a real rig lays the calibration grid on the stage (and lights it), or puts an
even light in front of the camera (flat and photon-transfer frames), or nothing (the shutter
is closed for bias and dark frames).  :class:`CalibrationTargets` is that set-up for the
simulated camera: :meth:`prepare` sets what is in front of it, :meth:`render` gives the
expected photons per pixel per second at the stage's physical height.

The grid is the calibration module's (the contract's grid: point (i, j) at
((i - (nx-1)/2) pitch, (j - (ny-1)/2) pitch), here on the plane ``z = stage_top_z_mm +
height + thickness_mm``), ray traced through the rig's true thin-lens camera by
:func:`fluxcli.calibration.synthetic.render_plane` (sub-pixels x lens samples: defocus,
perspective and natural vignetting come out of the geometry).  Only the direct view is
rendered (no mirror views of the grid).
"""

from __future__ import annotations

import numpy as np

from ...calibration.synthetic import checker_pattern, dot_grid_pattern, render_plane
from ...optics.camera import ThinLensCamera

__all__ = ["CalibrationTargets", "TARGETS"]

TARGETS = ("closed", "grid", "light")


class CalibrationTargets:
    """The simulated calibration set-up in front of the rig's camera.

    Parameters
    ----------
    camera : ThinLensCamera
        The rig's true camera (at the binning of its frames).
    kind : {"dots", "checkerboard"}
    pitch_mm : float
        Grid point spacing (mm).
    shape : (int, int)
        Grid points [nx, ny] (checkerboard: inner corners).
    plane_offset_mm : float
        z of the grid plane at stage height 0 (mm): the stage top plus the grid's thickness.
    dot_diameter_mm : float
        Printed dot diameter (mm; dots only).
    grid_photons_per_s : float
        Photons per pixel per second inside an in-focus dot on the axis.
    background_fraction : float
        The grid's background relative to a dot (a checkerboard's dark squares).
    light_photons_per_s : float
        Photons per pixel per second of the even light.
    sub, lens_samples : int
        Grid rendering: sub-pixels per pixel side, lens points per sub-pixel.
    """

    def __init__(self, camera: ThinLensCamera, *, kind: str = "dots", pitch_mm: float = 1.0,
                 shape: tuple[int, int] = (2, 2), plane_offset_mm: float = 0.0, dot_diameter_mm: float = 0.5,
                 grid_photons_per_s: float = 1.0, background_fraction: float = 0.05,
                 light_photons_per_s: float = 1.0, sub: int = 2, lens_samples: int = 32):
        self.camera = camera
        self.kind = kind
        self.pitch_mm = float(pitch_mm)
        self.shape = (int(shape[0]), int(shape[1]))
        self.plane_offset_mm = float(plane_offset_mm)
        self.dot_radius_mm = 0.5 * float(dot_diameter_mm)
        self.grid_photons_per_s = float(grid_photons_per_s)
        self.background_fraction = float(background_fraction)
        self.light_photons_per_s = float(light_photons_per_s)
        self.sub = int(sub)
        self.lens_samples = int(lens_samples)
        self.current: str | None = None  # nothing placed: the rig shows its subject
        self._grids: dict[float, np.ndarray] = {}

    def prepare(self, target: str) -> None:
        """Put ``target`` (one of :data:`TARGETS`) in front of the camera; ``"subject"`` takes the
        calibration set-up away (the rig shows its subject again)."""
        if target != "subject" and target not in TARGETS:
            raise ValueError(f"unknown calibration target {target!r} (one of {TARGETS} or 'subject')")
        self.current = None if target == "subject" else target

    def render(self, height_mm: float) -> np.ndarray:
        """Photons per pixel per second ``[ny, nx]`` with the stage at ``height_mm``."""
        cam = self.camera
        if self.current == "light":
            return np.full((cam.ny, cam.nx), self.light_photons_per_s)
        if self.current == "grid":
            return self.grid(height_mm)
        return np.zeros((cam.ny, cam.nx))

    def grid(self, height_mm: float) -> np.ndarray:
        # 0.1 um: far below any depth of field; the stage's microstep rounding reuses the planned height's image
        key = round(float(height_mm), 4)
        if key not in self._grids:
            cam = self.camera
            # the exitance that gives grid_photons_per_s in a pixel inside an in-focus dot on the axis
            per_mm2 = cam.focal_pixel_mm**2 * (np.pi * cam.aperture_radius_mm**2) / (np.pi * cam.focus_distance_mm**2)
            if self.kind == "checkerboard":
                def pattern(x, y):
                    return checker_pattern(x, y, pitch_mm=self.pitch_mm, shape=self.shape)
            else:
                def pattern(x, y):
                    return dot_grid_pattern(x, y, pitch_mm=self.pitch_mm, shape=self.shape,
                                            dot_radius_mm=self.dot_radius_mm)
            rng = np.random.default_rng([7, int(round(abs(key) * 1e4)), int(key < 0)])  # the lens pattern's rotation
            self._grids[key] = render_plane(cam, self.plane_offset_mm + key, pattern,
                                            exitance_photons_per_mm2=self.grid_photons_per_s / per_mm2,
                                            background_fraction=self.background_fraction, sub=self.sub,
                                            lens_samples=self.lens_samples, rng=rng)
        return self._grids[key]
