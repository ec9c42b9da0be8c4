"""One projector's scan end to end: simulated frames, decoding, points per view.

:func:`simulate_frames` is the simulated rig (the renderer, scaled to photons, through
the EMCCD chain); :func:`points_from_frames` is what runs on real frames as well:
decode, triangulate along each pixel's (direct or mirrored) chief ray, and return the
points with the direction they were seen along.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..imaging import noise as N
from ..optics.camera import PlaneMirror, ThinLensCamera
from ..surface.mesh import Surface
from .mesh import closed_surface, estimate_normals, remove_outliers
from .patterns import Decoded, PatternSet, decode
from .projector import Projector
from .render import PatternRenderer
from .triangulate import chief_rays, triangulate_columns

__all__ = ["simulate_frames", "ScanPoints", "points_from_frames", "decode_by_view", "MergedPoints", "merge_points",
           "surface_from_points"]


def simulate_frames(renderer: PatternRenderer, patterns: PatternSet, *, photons_white: float, ambient_photons: float,
                    sensor: N.EMCCDModel, rng: np.random.Generator, scale: float | None = None) -> tuple[np.ndarray, float]:
    """The camera's counts ``[n, ny, nx]`` (uint16) for each pattern, and the scale used.

    ``photons_white``: photons per pixel (per exposure) at the 99th percentile of the
    lit pixels under the full-white pattern (sets ``scale``, photons per unit of
    rendered radiance, unless ``scale`` is given); ``ambient_photons`` per pixel are added
    to every frame (stray light)."""
    images = [renderer.render(p) for p in patterns.frames]
    if scale is None:
        lit = images[0][images[0] > 0]
        scale = photons_white / np.percentile(lit, 99) if len(lit) else 0.0
    counts = np.stack([N.emccd_counts(img * scale + ambient_photons, sensor, rng) for img in images])
    return counts, float(scale)


@dataclass(frozen=True)
class ScanPoints:
    """Triangulated points of one projector's scan.

    ``points_mm`` (n, 3); ``view_dirs`` (n, 3) unit directions they were seen along;
    ``pixel`` (n,) flat camera pixel; ``view`` (n,) 0 direct, j through mirror j-1;
    ``decoded`` the per-pixel decoding."""

    points_mm: np.ndarray
    view_dirs: np.ndarray
    pixel: np.ndarray
    view: np.ndarray
    decoded: Decoded


def points_from_frames(photons: np.ndarray, patterns: PatternSet, camera: ThinLensCamera, mirrors: list[PlaneMirror],
                       projector: Projector, *, min_contrast: float, min_modulation_fraction: float = 0.25) -> ScanPoints:
    """Decode frames (photons, or bias-subtracted counts) and triangulate every valid pixel."""
    dec = decode(photons, patterns, min_contrast=min_contrast, min_modulation_fraction=min_modulation_fraction,
                 width_px=projector.width_px)
    origins, dirs, tmax = chief_rays(camera, mirrors)
    col = dec.column_px.ravel()
    pix = np.flatnonzero(np.isfinite(col))
    P = np.full((len(pix), 3), np.nan)
    V = np.full((len(pix), 3), np.nan)
    view = np.full(len(pix), -1)
    for j in range(len(mirrors) + 1):
        todo = np.flatnonzero(~np.isfinite(P[:, 0]) & np.isfinite(origins[j, pix, 0]))
        if len(todo) == 0:
            continue
        p = pix[todo]
        pts, _ = triangulate_columns(projector, origins[j, p], dirs[j, p], col[p], t_max=tmax[j, p])
        ok = np.isfinite(pts[:, 0])
        P[todo[ok]] = pts[ok]
        V[todo[ok]] = dirs[j, p[ok]]
        view[todo[ok]] = j
    ok = np.isfinite(P[:, 0])
    return ScanPoints(P[ok], V[ok], pix[ok], view[ok], dec)


def decode_by_view(scans: list[ScanPoints], projector_names: list[str], view_names: list[str], camera: ThinLensCamera,
                   mirrors: list[PlaneMirror]) -> dict:
    """``{(view, projector): {"phase", "column_px", "mask"}}`` (the ``surface`` artefact's ``/decode``): each
    projector's decoding (:class:`ScanPoints`) split by the view each camera pixel
    looks through (its chief ray: direct, or reflected in a mirror); mask 1 where a point was triangulated."""
    origins, _, _ = chief_rays(camera, mirrors)
    view_of_pixel = np.zeros(camera.ny * camera.nx, int)
    for j in range(1, len(view_names)):
        view_of_pixel[np.isfinite(origins[j, :, 0])] = j
    out = {}
    for name, scan in zip(projector_names, scans):
        used = np.zeros(view_of_pixel.size, bool)
        used[scan.pixel] = True
        for j, v in enumerate(view_names):
            here = view_of_pixel == j
            out[(v, name)] = {"phase": np.where(here, scan.decoded.wrapped_phase.ravel(), np.nan).reshape(camera.ny, camera.nx),
                              "column_px": np.where(here, scan.decoded.column_px.ravel(), np.nan).reshape(camera.ny, camera.nx),
                              "mask": (here & used).astype(np.uint8).reshape(camera.ny, camera.nx)}
    return out


@dataclass
class MergedPoints:
    points_mm: np.ndarray
    view_dirs: np.ndarray
    view: np.ndarray
    projector: np.ndarray
    n_removed_stage: int
    n_removed_outliers: int
    free_rays: tuple[np.ndarray, np.ndarray] | None = None  # every kept or stage point, and its view direction


def merge_points(scans: list[ScanPoints], *, floor_z_mm: float, stage_margin_mm: float = 1.0) -> MergedPoints:
    """All projectors' points in world coordinates; the stage's points (within
    ``stage_margin_mm`` of its top) and statistical outliers removed."""
    P = np.concatenate([s.points_mm for s in scans])
    V = np.concatenate([s.view_dirs for s in scans])
    view = np.concatenate([s.view for s in scans])
    proj = np.concatenate([np.full(len(s.points_mm), k) for k, s in enumerate(scans)])
    on = P[:, 2] > floor_z_mm + stage_margin_mm
    keep = remove_outliers(P[on], max_plane_distance_mm=0.5)
    idx = np.flatnonzero(on)[keep]
    seen = np.ones(len(P), bool)
    seen[np.flatnonzero(on)[~keep]] = False  # an outlier must not carve
    return MergedPoints(P[idx], V[idx], view[idx], proj[idx], int((~on).sum()), int((~keep).sum()),
                        (P[seen], V[seen]))


def surface_from_points(pts: MergedPoints, *, floor_z_mm: float, element_size_mm: float = 4.0,
                        face_size_mm: float = 1.0, voxel_mm: float = 0.8, centre_spacing_mm: float = 2.5) -> Surface:
    """The closed surface through merged points (normals by local PCA, turned to the viewer;
    :func:`~fluxcli.structured.mesh.closed_surface` with the decoded rays carving free space)."""
    n = estimate_normals(pts.points_mm, pts.view_dirs)
    return closed_surface(pts.points_mm, n, floor_z_mm=floor_z_mm, voxel_mm=voxel_mm,
                          centre_spacing_mm=centre_spacing_mm, face_size_mm=face_size_mm,
                          element_size_mm=element_size_mm, free_rays=pts.free_rays)
