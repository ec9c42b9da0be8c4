"""What the simulated camera sees while a projector lights the true surface.

For every camera pixel, ``sub x sub`` points of its focal-plane footprint are joined to
``lens_samples`` points of the lens disk (the thin-lens blur, as in
:mod:`fluxcli.optics.transfer`); each such ray is cast with the project's ray caster
(:class:`fluxcli.optics.raycast.OcclusionScene`) to the first surface it meets, directly
or through a plane mirror (the mirror view is the real camera reflected, as in build-T).
A surface point is lit by the projector when it faces it, projects onto its panel and the
segment to the projector's centre is clear.  Lambertian reflection: the radiance is
``albedo / pi * E`` with irradiance ``E = I(u, v) cos(theta) / d^2`` and the projector's
intensity ``I = radiance(pattern, u, v) * cos^3(off-axis angle)`` (a pinhole panel).

The geometry does not depend on the pattern: :class:`PatternRenderer` traces once and
renders any pattern as a weighted sum over its samples.  Light reaching the subject
through a mirror (projector -> mirror -> subject) and interreflections are not modelled.
"""

from __future__ import annotations

import numpy as np

from ..optics.camera import PlaneMirror, ThinLensCamera, sunflower_disk
from ..optics.raycast import OcclusionScene
from ..surface.mesh import Surface, merge
from .projector import Projector

__all__ = ["PatternRenderer", "view_label", "pixel_etendue_mm2_sr"]

_EPS_MM = 1e-3


def view_label(k: int, mirror_names: list[str]) -> str:
    return "direct" if k == 0 else mirror_names[k - 1]


class PatternRenderer:
    """Trace the camera's rays once; render any pattern of ``projector`` as the camera sees it.

    Parameters
    ----------
    camera : the real camera.
    mirrors : ``[(PlaneMirror, reflectance)]``; each adds a view (the camera reflected).
    surfaces : ``[(Surface, albedo)]``: the subject and whatever else the projector lights
        (the stage top).  Albedo is the Lambertian reflectance (0..1).
    occluders : surfaces that only block (stage sides, mirror backs); mirrors are added.
    projector : the projector lighting the scene.
    lens_samples, sub : lens points and sub-pixels per side per camera pixel.

    Attributes
    ----------
    view_of_pixel : ``[ny, nx]`` int, the view (0 direct, k for mirror k-1) most samples
        of a pixel came through, -1 where none met a surface.
    """

    def __init__(self, camera: ThinLensCamera, mirrors: list[tuple[PlaneMirror, float]],
                 surfaces: list[tuple[Surface, float]], occluders: list[Surface], projector: Projector, *,
                 lens_samples: int = 4, sub: int = 2):
        from ..surface.mesh import rectangle

        self.camera, self.projector = camera, projector
        mirror_surfs = [rectangle(m.center_mm, m.axis_u, m.axis_v, (2 * m.half_size_mm[0], 2 * m.half_size_mm[1]))
                        for m, _ in mirrors]
        lit = [s for s, _ in surfaces]
        verts, faces = merge(*lit, *occluders, *mirror_surfs)
        n_lit = sum(len(s.faces) for s in lit)
        n_occ = sum(len(s.faces) for s in occluders)
        albedo_face = np.concatenate([np.full(len(s.faces), a, float) for s, a in surfaces]
                                     + [np.zeros(len(faces) - n_lit)])
        mirror_of_face = np.full(len(faces), -1, np.int64)
        mirror_of_face[n_lit + n_occ:] = np.repeat(np.arange(len(mirrors)), 2)
        t = verts[faces]
        normals = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
        normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
        self.scene = OcclusionScene(verts, faces)

        ny, nx = camera.ny, camera.nx
        focal = camera.pixel_centres_focal(sub)  # (ny*sub, nx*sub, 3)
        rr, cc = np.meshgrid(np.arange(ny * sub) // sub, np.arange(nx * sub) // sub, indexing="ij")
        pix = (rr * nx + cc).ravel()
        focal = focal.reshape(-1, 3)
        # lens points in +-pairs: their centroid is the lens centre (a sunflower set of a few points
        # is off-centre by up to 0.16 R, which shifts every defocused image sideways by a z-dependent amount)
        half = sunflower_disk(max((lens_samples + 1) // 2, 1))
        disk = np.concatenate([half, -half]) if lens_samples > 1 else np.zeros((1, 2))
        self.n_samples = sub * sub * len(disk)
        pix_all, u_all, v_all, w_all, view_all = [], [], [], [], []
        for k in range(len(mirrors) + 1):
            cam = camera if k == 0 else camera.mirrored(mirrors[k - 1][0])
            for d in disk:
                L = cam.lens_points(d[None, :])[0]
                dirs = focal_of(cam, camera, focal) - L
                dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
                origins = np.broadcast_to(L, dirs.shape).copy()
                keep = np.ones(len(dirs), bool)
                gain = np.ones(len(dirs))
                if k > 0:
                    mirror, refl = mirrors[k - 1]
                    denom = dirs @ mirror.normal
                    with np.errstate(divide="ignore", invalid="ignore"):
                        tm = ((mirror.center_mm - L) @ mirror.normal) / denom
                    M = L + tm[:, None] * dirs
                    keep = (tm > 0) & mirror.contains(M) & np.isfinite(tm)
                    # the real path: lens -> mirror point, must be clear
                    Lr = camera.lens_points(d[None, :])[0]
                    seg = M - Lr
                    seg_len = np.linalg.norm(seg, axis=1)
                    blocked = self.scene.blocked(np.broadcast_to(Lr, seg.shape), seg / seg_len[:, None],
                                                 seg_len - _EPS_MM)
                    keep &= ~blocked
                    origins = M + _EPS_MM * dirs
                    gain = np.full(len(dirs), float(refl))
                idx = np.flatnonzero(keep)
                tt, face = self.scene.first_hit_face(origins[idx], dirs[idx])
                ok = (face >= 0) & (albedo_face[np.maximum(face, 0)] > 0)
                idx, tt, face = idx[ok], tt[ok], face[ok]
                P = origins[idx] + tt[:, None] * dirs[idx]
                n = normals[face]
                n = np.where(((n * dirs[idx]).sum(1) > 0)[:, None], -n, n)  # the side the camera sees
                u, v, w = self._projector_weights(P, n)
                w *= albedo_face[face] / np.pi * gain[idx]
                pix_all.append(pix[idx]); u_all.append(u); v_all.append(v); w_all.append(w)
                view_all.append(np.full(len(idx), k))
        self._pix = np.concatenate(pix_all)
        self._u, self._v, self._w = np.concatenate(u_all), np.concatenate(v_all), np.concatenate(w_all)
        views = np.concatenate(view_all)
        counts = np.zeros((len(mirrors) + 1, ny * nx))
        np.add.at(counts, (views, self._pix), 1)
        self.view_of_pixel = np.where(counts.max(0) > 0, counts.argmax(0), -1).reshape(ny, nx)

    def _projector_weights(self, P: np.ndarray, n: np.ndarray):
        pr = self.projector
        u, v, z = pr.project(P)
        to_p = pr.center_mm - P
        d = np.linalg.norm(to_p, axis=1)
        to_p /= d[:, None]
        cos_s = (n * to_p).sum(1)
        cos_axis = -(to_p @ pr.axis)
        ok = (cos_s > 0) & (z > 0) & np.isfinite(u) & (u >= 0) & (u < pr.width_px) & (v >= 0) & (v < pr.height_px)
        idx = np.flatnonzero(ok)
        clear = ~self.scene.blocked(P[idx] + _EPS_MM * n[idx], to_p[idx], d[idx] - 2 * _EPS_MM)
        ok[idx[~clear]] = False
        w = np.where(ok, cos_s * np.clip(cos_axis, 0, 1) ** 3 / np.maximum(d, 1e-9) ** 2, 0.0)
        return u, v, w

    def render(self, pattern: np.ndarray) -> np.ndarray:
        """Radiance seen by each camera pixel ``[ny, nx]`` (relative units: projector radiance
        1 at full white times sr/mm^2), averaged over the pixel and the lens."""
        rad = self.projector.radiance(pattern, self._u, self._v) * self._w
        img = np.bincount(self._pix, rad, minlength=self.camera.nx * self.camera.ny) / self.n_samples
        return img.reshape(self.camera.ny, self.camera.nx)


def focal_of(cam: ThinLensCamera, real: ThinLensCamera, focal_real: np.ndarray) -> np.ndarray:
    """The focal-plane points of ``cam`` (a real camera or its mirror copy) matching the real
    camera's ``focal_real``: the same pixel layout, expressed in ``cam``'s frame."""
    rel = focal_real - real.center_mm
    a, r, d = rel @ real.axis, rel @ real.right, rel @ real.down
    return cam.center_mm + a[:, None] * cam.axis + r[:, None] * cam.right + d[:, None] * cam.down


def pixel_etendue_mm2_sr(camera: ThinLensCamera) -> np.ndarray:
    """Etendue of each camera pixel ``[ny, nx]`` (mm^2 sr): its focal-plane footprint times the
    lens's solid angle seen from there, ``G = A_f pi R^2 cos^4(theta) / u^2`` (theta off the
    axis, u the focus distance; small lens).  A Lambertian surface of radiance L (what
    :meth:`PatternRenderer.render` returns, per mm^2 per sr) in focus puts ``L G`` into the
    pixel: the lens form of the forward model (cos theta_s cos theta_l dA_l dS / r^2) for a
    small lens.  Extra apertures (mechanical vignetting) are not counted."""
    rel = camera.pixel_centres_focal(1) - camera.center_mm
    cos = (rel @ camera.axis) / np.linalg.norm(rel, axis=-1)
    return camera.focal_pixel_mm**2 * camera.lens_area_mm2 * cos**4 / camera.focus_distance_mm**2
