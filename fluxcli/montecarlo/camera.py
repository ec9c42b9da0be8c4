"""Images made from the photons themselves: each escaping photon is a ray (exit point,
direction in air) traced through the ideal thin lens of :mod:`fluxcli.optics.camera`,
directly or via one plane mirror, in whole photons.

A photon counts in a view when its ray crosses the lens plane inside the aperture (for a
mirror: the plane of the mirror's virtual lens, after crossing the mirror rectangle from
its reflecting side), passes every extra aperture, and every real segment it travels
(exit point → lens; or exit point → mirror, mirror → lens) is clear of the subject and the
occluders. Its pixel is where the line meets the front focal plane (the thin-lens map).
A mirror returns a photon with probability ρ·s (its reflectance times its per-view scale),
so the images stay whole photons. No emission model is assumed anywhere: the photons'
own directions decide.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..optics.camera import ThinLensCamera
from ..optics.raycast import OcclusionScene


@dataclass
class PhotonImage:
    """Counts per pixel (flat, row-major) and, per view, how many photons crossed the lens
    aperture unobstructed (``reached_lens``) and how many of those landed on the sensor."""

    counts_per_pixel: np.ndarray
    reached_lens: dict[str, int] = field(default_factory=dict)
    on_sensor: dict[str, int] = field(default_factory=dict)
    pixel_of_photon: dict[str, np.ndarray] = field(default_factory=dict)  # -1: not imaged in that view


def _lens_crossing(cam: ThinLensCamera, p: np.ndarray, d: np.ndarray):
    """Rays that cross the (possibly virtual) lens disk travelling towards it and pass the
    extra apertures: mask, distance to the lens plane, lens point, pixel index."""
    z = cam.axial(p)
    dz = d @ cam.axis
    ok = (z > 0) & (dz < 0)
    t = np.where(ok, -z / np.where(dz < 0, dz, -1.0), 0.0)
    lens = p + t[:, None] * d
    rel = lens - cam.center_mm
    ok &= np.einsum("ij,ij->i", rel, rel) <= cam.aperture_radius_mm ** 2
    if cam.apertures and ok.any():
        ok[ok] = cam.passes_apertures(p[ok], lens[ok], z[ok])
    pix = np.full(len(p), -1, np.int64)
    if ok.any():
        pix[ok] = cam.pixel_index(cam.focal_plane_hit(p[ok], lens[ok], z[ok]))
    return ok, t, lens, pix


def image_photons(views, scene: OcclusionScene, position_mm: np.ndarray, direction: np.ndarray,
                  normal: np.ndarray, rng: np.random.Generator, *, ray_offset_mm: float = 1e-3,
                  keep_pixels: bool = False) -> PhotonImage:
    """Add the photons (placed in the world: exit points (n, 3) mm, unit directions in air
    (n, 3), outward surface normals at the exit points (n, 3)) to the image of every view.

    ``views``: the :class:`fluxcli.optics.transfer.View` list (direct first; a mirror view
    holds the virtual camera, the mirror and its weight ρ·s); ``scene``: the subject and
    every occluder (mirrors included), as the T estimators see them.
    """
    cam0 = views[0].camera
    counts = np.zeros(cam0.nx * cam0.ny, np.int64)
    out = PhotonImage(counts)
    start = position_mm + ray_offset_mm * normal  # off the surface: no self-hit at the exit point
    for v in views:
        ok, t, lens, pix = _lens_crossing(v.camera, start, direction)
        if v.mirror is None:
            idx = np.flatnonzero(ok)
            if idx.size:
                blocked = scene.blocked(start[idx], direction[idx], t[idx])
                idx = idx[~blocked]
        else:
            m = v.mirror
            side = (start - m.center_mm) @ m.normal
            dn = direction @ m.normal
            ok &= (side > 0) & (dn < 0)
            tm = np.where(ok, -side / np.where(dn < 0, dn, -1.0), 0.0)
            ok &= tm < t  # the mirror comes before the virtual lens
            hit = start + tm[:, None] * direction
            ok &= m.contains(hit)
            idx = np.flatnonzero(ok)
            if idx.size:
                keep = rng.random(idx.size) < v.weight  # reflectance x scale, in whole photons
                idx = idx[keep]
            if idx.size:
                eps = 1e-6 * (1 + tm[idx])
                blocked = scene.blocked(start[idx], direction[idx], tm[idx] - eps)  # up to the mirror
                d2 = m.reflect_directions(direction[idx])
                real_lens = m.reflect_points(lens[idx])
                seg = np.linalg.norm(real_lens - hit[idx], axis=1)
                blocked |= scene.blocked(hit[idx] + eps[:, None] * d2, d2, seg - eps)  # mirror to lens
                idx = idx[~blocked]
        out.reached_lens[v.name] = int(idx.size)
        on = pix[idx] >= 0
        out.on_sensor[v.name] = int(on.sum())
        np.add.at(counts, pix[idx][on], 1)
        if keep_pixels:
            p = np.full(len(start), -1, np.int64)
            p[idx] = pix[idx]
            out.pixel_of_photon[v.name] = p
    return out
