"""A stand-alone simulated structured-light rig (the paper's): render, decode, triangulate.

What ``pipelines/structured_light.py`` (``make structured-light``) measures the capture's
accuracy with, against a known true surface.  ``fluxmap capture-surface`` is what makes a
``surface.h5`` from a config's rig (simulated or real); both write it through
:func:`fluxcli.artefacts.surface.write`.

The rig of :func:`paper_like_rig`: the camera of ``configs/demo-rig.yaml`` unbinned
(384 x 384), two 45-degree mirrors beside the stage (the paper's rig), two projectors
(1024 x 768, gamma 2.2, radial distortion) at 37 degrees elevation from -y and +y, so
that each lights one flank down to about 50 degrees below a lying cylinder's equator,
which the mirror on that side sees.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..imaging import noise as N
from ..optics.camera import PlaneMirror, ThinLensCamera
from ..surface.mesh import Surface, box
from .patterns import PatternSet, column_patterns
from .projector import Projector
from .render import PatternRenderer
from .scan import ScanPoints, points_from_frames, simulate_frames


@dataclass
class ScanRig:
    """A camera, its mirrors (with reflectance), the projectors, and the stage (a box)."""

    camera: ThinLensCamera
    mirrors: list[tuple[PlaneMirror, float]]
    projectors: list[Projector]
    stage_lo_mm: np.ndarray
    stage_hi_mm: np.ndarray
    patterns: PatternSet
    sensor: N.EMCCDModel = field(default_factory=lambda: N.EMCCDModel(em_gain=10, exposure_s=0.1))
    photons_white: float = 3000.0
    ambient_photons: float = 20.0
    min_contrast: float = 200.0

    @property
    def floor_z_mm(self) -> float:
        return float(self.stage_hi_mm[2])

    def describe(self) -> dict:
        """The rig as plain numbers (an artefact's provenance geometry)."""
        c = self.camera
        return {
            "camera": {"center_mm": c.center_mm.tolist(), "axis": c.axis.tolist(), "down": c.down.tolist(),
                       "focal_length_mm": c.focal_length_mm, "focus_distance_mm": c.focus_distance_mm,
                       "aperture_radius_mm": c.aperture_radius_mm, "pixels": [c.nx, c.ny],
                       "pixel_pitch_mm": c.pixel_pitch_mm},
            "mirrors": [{"center_mm": m.center_mm.tolist(), "normal": m.normal.tolist(),
                         "half_size_mm": list(m.half_size_mm), "reflectance": r} for m, r in self.mirrors],
            "projectors": [{"center_mm": p.center_mm.tolist(), "axis": p.axis.tolist(), "right": p.right.tolist(),
                            "pixels": [p.width_px, p.height_px], "f_px": [p.fx_px, p.fy_px],
                            "c_px": [p.cx_px, p.cy_px], "k": [p.k1, p.k2], "gamma": p.gamma}
                           for p in self.projectors],
            "patterns": {"period_px": self.patterns.period_px, "n_steps": self.patterns.n_steps,
                         "n_gray": self.patterns.n_gray},
            "stage_top_z_mm": self.floor_z_mm,
        }


def paper_like_rig(nx: int = 384) -> ScanRig:
    cam = ThinLensCamera.from_pose(lens_center_mm=[0, 0, 338], look=[0, 0, -1], up=[0, 1, 0], focal_length_mm=23.9,
                                   aperture_radius_mm=23.9 / 2.8 / 2, focus_distance_mm=317, nx=nx, ny=nx,
                                   pixel_pitch_mm=0.13 * 96 / nx)
    mirrors = [(PlaneMirror.from_axis([0, s * 31.14, 14.14], [0, -s, 1], [1, 0, 0], [70, 40]), 0.9) for s in (1, -1)]
    projs = [Projector.from_pose(center_mm=[0, s * 200, 150], look=[0, -s * 200, -140], up=[s, 0, 0], width_px=1024,
                                 height_px=768, fx_px=3000, k1=0.05, gamma=2.2) for s in (-1, 1)]
    return ScanRig(cam, mirrors, projs, np.array([-50.0, -17, -5]), np.array([50.0, 17, 0]),
                   column_patterns(1024, 768, period_px=16, n_steps=8))


@dataclass
class SimulatedScan:
    frames: list[np.ndarray]  # per projector: counts [n_patterns, ny, nx]
    scans: list[ScanPoints]   # per projector


def simulate_scan(rig: ScanRig, true_surface: Surface, *, albedo: float = 0.8, stage_albedo: float = 0.5,
                  seed: int = 0, lens_samples: int = 4, sub: int = 2) -> SimulatedScan:
    """Render every projector's pattern sequence on the true surface, add EMCCD noise, decode, triangulate."""
    stage = box(rig.stage_lo_mm, rig.stage_hi_mm)
    frames, scans = [], []
    plain_mirrors = [m for m, _ in rig.mirrors]
    for k, proj in enumerate(rig.projectors):
        r = PatternRenderer(rig.camera, rig.mirrors, [(true_surface, albedo), (stage, stage_albedo)], [], proj,
                            lens_samples=lens_samples, sub=sub)
        counts, _ = simulate_frames(r, rig.patterns, photons_white=rig.photons_white,
                                    ambient_photons=rig.ambient_photons, sensor=rig.sensor,
                                    rng=np.random.default_rng([seed, k]))
        frames.append(counts)
        scans.append(points_from_frames(N.counts_to_photons(counts, rig.sensor), rig.patterns, rig.camera,
                                        plain_mirrors, proj, min_contrast=rig.min_contrast))
    return SimulatedScan(frames, scans)
