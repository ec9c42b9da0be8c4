"""The simulated camera's subject for ``capture-surface`` (``rig.camera.backend: simulated``):
the emission through each filter rendered through the forward model, and the projectors'
patterns on the true surface.  Built from :class:`._capture_plan.SceneParts`, never the config."""

from __future__ import annotations

import numpy as np

from .. import config as C
from ._capture_plan import RENDERER, SceneParts


class SimulatedScene:
    """What the simulated camera sees: ``render(height_mm, filter) -> photons/s per pixel``.

    The truth is ``simulate.flux`` per filter: a filter's ``rig.camera.filters`` entry
    picks the wavelength whose ``simulate.flux.optical`` properties apply (diffusion
    truths) and a transmission; photons per exposure of ``simulate`` become photons/s by
    dividing by ``simulate.noise.exposure_s``.  T is the forward T (``simulate.transfer``,
    finer than reconstruction's) of the subject at the given stage height, from the T cache."""

    def __init__(self, parts: SceneParts):
        self.parts = parts
        self.camera_settings = parts.camera_settings
        self.light = dict(parts.camera_settings.filters)
        self.placer = parts.placer
        self.digest = parts.digest
        self._rates: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        self._images: dict[tuple[float, str], np.ndarray] = {}
        self._pattern_renderers: dict[tuple[float, int, str], tuple] = {}

    RENDERER = RENDERER

    def fine_rate(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """Photons/s leaving each face of the refined surface (``simulate.truth_refinement``;
        subject at rest) as seen through filter ``name``, and the element of each fine face.
        The camera renders this, not a constant per element: a truth constant over the very
        elements that are reconstructed is half an inverse crime, and in focus it images as
        facets no smooth exitance explains (χ²/pixel 2.5 on the demo rig's true mesh)."""
        if name not in self._rates:
            from ..truth import truth_fine

            spec = self.light.get(name)
            truth = self.parts.truth[name if name in self.parts.truth else None]
            fine, parent, _ = truth_fine(truth, self.placer.surface)  # a negligible FEM undershoot is clipped there
            transmission = 1.0 if spec is None else spec.transmission
            self._rates[name] = (fine * transmission / self.parts.simulate.noise.exposure_s, parent)
        return self._rates[name]

    def power_rate(self, name: str) -> np.ndarray:
        """Photons/s leaving each element (subject at rest) as seen through filter ``name``."""
        fine, parent = self.fine_rate(name)
        return np.bincount(parent, weights=fine, minlength=self.placer.surface.n_elements)

    def render(self, height_mm: float, name: str, *, projectors: dict | None = None, binning: int | None = None
               ) -> np.ndarray:
        """Photons/s per pixel: what the projectors shine (when any shows a pattern), else
        the subject's emission through filter ``name`` (at the camera's native binning).  The
        emission is left out of pattern frames (any binning finer than the native one): it is
        orders of magnitude fainter than the projected light."""
        native = self.camera_settings.binning
        binning = native if binning is None else int(binning)
        if projectors:
            return sum(self.pattern_photons_per_s(height_mm, binning, p, img) for p, img in projectors.items())
        if binning != native:  # a pattern frame with every projector black (the emission is left out there too)
            k = native // binning
            nx, ny = self.parts.system.camera.pixels
            return np.zeros((ny * k, nx * k))
        return self.emission(height_mm, name)

    def pattern_renderer(self, height_mm: float, binning: int, projector: str):
        """The traced scene (subject and stage at ``height_mm``, camera at ``binning``) for one
        projector, and the photons/s per pixel per unit of rendered radiance (étendue x intensity)."""
        key = (round(float(height_mm), 4), int(binning), projector)
        if key not in self._pattern_renderers:
            from ..hardware.projector import projector_model
            from ..scene import Pose, plane_mirrors
            from ..structured.render import PatternRenderer, pixel_etendue_mm2_sr

            system = self.parts.system
            camera = camera_at_binning(system.camera, self.camera_settings.binning // int(binning))
            lit = [(self.true_surface_at(key[0]), self.camera_settings.subject_albedo)]
            if system.stage is not None:  # the stage top (the first occluder) is lit too
                lit.append((self.placer.occluders(Pose(key[0], 0.0), system)[0], self.camera_settings.stage_albedo))
            mirrors = [(pm, mm.reflectance) for pm, mm in zip(plane_mirrors(system), system.mirrors)]
            spec = self.parts.projectors[projector]
            renderer = PatternRenderer(camera, mirrors, lit, [], projector_model(spec))
            scale = pixel_etendue_mm2_sr(camera) * spec.intensity_photons_per_s_per_sr
            self._pattern_renderers[key] = (renderer, scale)
        return self._pattern_renderers[key]

    def pattern_photons_per_s(self, height_mm: float, binning: int, projector: str, pattern: np.ndarray) -> np.ndarray:
        renderer, scale = self.pattern_renderer(height_mm, binning, projector)
        return renderer.render(pattern) * scale

    def true_surface_at(self, height_mm: float):
        """The true subject placed with the stage at ``height_mm``."""
        from ..scene import Pose

        return self.placer.place(Pose(float(height_mm), self.parts.rotation_deg))

    def emission(self, height_mm: float, name: str) -> np.ndarray:
        # 0.1 um is far below any depth of field: the stage's microstep rounding (~7 nm)
        # then reuses the T of the planned height instead of building another
        key = (round(float(height_mm), 4), name)
        if key not in self._images:
            from ..scene import Pose
            from ..transfer_cache import pose_T, with_columns
            from ..truth import truth_refinement  # the forward T and truth, as simulate uses

            p = self.parts
            refine = truth_refinement(p.simulate)
            scene = with_columns(self.placer.scene(Pose(key[0], p.rotation_deg), p.system), f"refined:{refine}")
            T, T_tangent = pose_T(scene, p.views, p.forward_transfer, p.cache_dir, p.config_sha256, p.provenance, True)
            nx, ny = p.system.camera.pixels
            rate = self.fine_rate(name)[0]
            image = T @ rate
            if T_tangent is not None and refine > 0:  # the emission's tangential flux, as simulate renders it
                from ..optics.emission import tangent_light

                image = np.maximum(image + T_tangent @ tangent_light(self.placer.surface.refined(refine)[0], rate), 0.0)
            if refine > 0 and scene.emission is not None and scene.emission.has_curvature:  # and its curvature term
                from ..artefacts.transfer import load_T_curvature
                from ..optics.emission import curvature_power
                from ..transfer_cache import curvature_ratios, pose_entry

                Tc = load_T_curvature(pose_entry(scene, p.views, p.forward_transfer, p.cache_dir),
                                      curvature_ratios(scene.surface, p.views, scene.emission))
                image = np.maximum(image + Tc @ curvature_power(self.placer.surface.refined(refine)[0], rate,
                                                                scene.emission), 0.0)
            self._images[key] = image.reshape(ny, nx)
        return self._images[key]


def camera_at_binning(camera: C.Camera, k: int):
    """The thin-lens camera of ``system.camera`` with its pixels split ``k x k`` (a binning k
    times finer than the one system.camera describes)."""
    from ..scene import camera_from_config

    return camera_from_config(camera.model_copy(update={"pixels": (camera.pixels[0] * k, camera.pixels[1] * k),
                                                        "pixel_pitch_mm": camera.pixel_pitch_mm / k}))
