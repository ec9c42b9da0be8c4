"""What one ``fluxmap reconstruct`` run does, resolved once from the config.

:func:`plan_of` is the only function below the command that reads the loaded config; every
helper of the stage (inputs, grids, solves, error budget, regions of interest, outputs, the
artefact) takes parts of the :class:`ReconstructPlan` it returns.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, replace
from pathlib import Path

from .. import artefacts as A
from .. import config as C
from ..artefacts.reconstruction import FILENAME as RECONSTRUCTION_FILE
from ..transfer_cache import TransferSource
from .plans import check_folders, source_of
from ._radiometric import assumed_qe_warning, counts_in
from .outputs import reconstruction_exposure_s, simulation_exposure_s

# what `unknowns: auto` and the solvers do; a reconstruction made by an older version is redone
SOLVER_VERSION = ("2026-11 vertex basis, cotangent prior, provisional UPRE, isolated spikes left out, exact non-negative "
                  "steps, linear_elements beyond 2500 vertices, discrepancy where UPRE interpolates, no element unknown where "
                  "only the element's edges are seen")


@dataclass(frozen=True)
class ImagesPlan:
    """Where the images come from and how to read them."""

    source: object  # reconstruct.images: C.ImageFiles, C.CaptureSource, or None (simulation.h5)
    simulation: Path  # <workdir>/simulation.h5: the images when reconstruct.images is not given
    files: tuple[Path, ...]  # image files, one per pose, resolved (empty: not image files)
    calibration: Path | None  # radiometric calibration of the image files (bias, dark, flat), resolved
    capture: Path | None  # capture.h5, resolved (None: not a capture)
    level: int  # simulation: which signal level
    repeat: int  # simulation: which noise repeat
    noiseless: bool  # simulation: the noiseless images instead of a repeat
    pixels: tuple[int, int]  # camera pixels (nx, ny), binned
    sensor: C.Sensor  # the camera's sensor model (counts -> photons)
    sensor_given: bool  # whether the config states system.camera.sensor
    heights_mm: tuple[float, ...]  # stage height of each pose, subject.poses order (a capture's order)

    @property
    def is_capture(self) -> bool:
        return isinstance(self.source, C.CaptureSource)


@dataclass(frozen=True)
class ReconstructPlan:
    """One reconstruct run: paths, placed poses with their T keys, noise model, method, filters, ROIs, sweep."""

    config_path: Path  # the config file (named in remedies)
    config_sha256: str  # its sha256 (recorded in the artefact)
    workdir: Path  # where the artefacts are read and written
    output: Path  # <workdir>/reconstruction.h5
    images: ImagesPlan  # the images and how to read them
    settings: C.MethodSettings  # reconstruct's method (unknowns may still be auto)
    noise: str  # reconstruct.noise: auto | gaussian | poisson | emccd
    read_noise_photons: float  # added to the shot-noise variance (photons rms)
    joint: bool  # also solve all poses jointly
    sweep: C.Sweep | None  # the study sweep (levels x repeats x poses x methods), or None
    filters: tuple[str, ...]  # a capture's filters in order (empty: one filter or not a capture)
    main_filter: str | None  # the filter of /flux (None: none named)
    transmissions: dict  # filter -> transmission (dimensionless); 1 for a filter not listed
    rois: tuple  # the config's regions of interest (C.Roi), in order
    roi_mesh: Path | None  # the mesh file cell_array ROIs read (None: subject.surface is not a mesh file)
    config_exposure_s: float | None  # the exposure the config states for the images (s), None: not stated
    simulation_exposure_s: float | None  # the simulated exposure the config states (s), None: not stated
    camera: C.Camera  # system.camera (pose for the report's drawing, sensor)
    system: C.System  # the rig (the error budget moves its calibrated parameters)
    calibration_budget: bool  # reconstruct.calibration_budget
    digest: str  # inputs digest: the artefact is up to date when it holds this
    geometry: dict  # the geometry the images must have been made with (surface digest included)
    subject_emission: object  # subject.emission as the geometry records it (None: Lambertian)
    qe_warning: str | None  # the warning when the quantum efficiency is assumed
    views: list  # the camera views (direct, mirrors)
    placer: object  # the subject placed at each pose (surface, axis, emission)
    todo: list  # per pose (placed scene, T plan with its key and cache path)
    transfer: TransferSource  # what the T cache needs (rig, subject, sampling, cache folder), read once from the config
    surface_sha256: str  # the built surface's digest (what the artefact's geometry records)

    def transmission(self, name: str | None) -> float:
        """The filter's transmission (1 without a capture's filter)."""
        if name is None or not self.images.is_capture:
            return 1.0
        return float(self.transmissions.get(name, 1.0))

    def build_T(self, ctx, label: str, unknowns: str, system: C.System | None = None):
        """Every pose's T on ``unknowns``, built or from the cache (never forced: ``--force`` redoes
        the reconstruction, not T): views, placer, [(scene, PoseT)], summaries. ``system``: another
        rig (the error budget's moved parameters)."""
        source = self.transfer if system is None else self.transfer.with_system(system)
        return source.ensure(replace(ctx, force=False), label, unknowns)

    def new_provenance(self) -> A.Provenance:
        """A fresh provenance record of this run (the files read are added to it)."""
        return self.transfer.provenance(self.surface_sha256)

    def rate_exposure_s(self, inp_exposure_s: float, recorded: bool = False) -> float | None:
        """The exposure that makes rates: a capture knows its frames', image files that record
        theirs (``recorded``) theirs, else as the config states it."""
        return inp_exposure_s if self.images.is_capture or recorded else self.config_exposure_s


def _image_sources(cfg: C.LoadedConfig, capture: Path | None) -> list[str]:
    """sha256 of the image files reconstruct reads (what makes its output stale)."""
    rc = cfg.model.reconstruct
    if isinstance(rc.images, C.CaptureSource):
        return [A.file_sha256(capture)] if capture.is_file() else []
    if rc.images is not None:
        out = [A.file_sha256(cfg.resolve(p)) for p in rc.images.files if cfg.resolve(p).is_file()]
        if rc.images.calibration is not None and cfg.resolve(rc.images.calibration).is_file():
            out.append(A.file_sha256(cfg.resolve(rc.images.calibration)))
        return out
    sim = cfg.workdir / "simulation.h5"
    return [A.file_sha256(sim)] if sim.is_file() else []


def plan_of(cfg: C.LoadedConfig) -> ReconstructPlan:
    """The run plan of ``fluxmap reconstruct`` (checks the folders, places the poses)."""
    m_ = cfg.model
    rc = m_.reconstruct
    check_folders(cfg)
    src = rc.images
    capture = cfg.images_capture_path() if isinstance(src, C.CaptureSource) else None
    source = source_of(cfg)
    geometry = source.geometry()
    digest = A.inputs_digest(system=m_.system.model_dump(mode="json"), subject=geometry["subject"],
                             transfer=m_.transfer.model_dump(mode="json"),
                             reconstruct=rc.model_dump(mode="json", by_alias=True), images=_image_sources(cfg, capture),
                             solver=SOLVER_VERSION,
                             **({"rois": [r.model_dump(mode="json") for r in m_.rois]} if m_.rois else {}))
    tp = source.plan()
    views, placer, todo = tp.views, tp.placer, tp.poses
    surface_sha = placer.surface.digest()
    files = tuple(cfg.resolve(p) for p in getattr(src, "files", None) or ())
    calibration = getattr(src, "calibration", None) if isinstance(src, C.ImageFiles) else None
    filters = tuple(src.filters) if isinstance(src, C.CaptureSource) and src.filters else ()
    from ..scene import poses_from_config

    images = ImagesPlan(
        source=src, simulation=cfg.workdir / "simulation.h5", files=files,
        calibration=cfg.resolve(calibration) if calibration is not None else None, capture=capture,
        level=rc.level, repeat=rc.repeat, noiseless=rc.noiseless, pixels=tuple(m_.system.camera.pixels),
        sensor=m_.system.camera.sensor, sensor_given="sensor" in m_.system.camera.model_fields_set,
        heights_mm=tuple(p.height_mm for p in poses_from_config(m_.subject)) if capture is not None else ())
    surface = m_.subject.surface if m_.subject is not None else None
    from . import budget

    if budget.wanted(m_.system, rc.calibration_budget):
        budget.parameters(m_.system)  # an uncertainty that moves the camera past possible is named before any solve
    return ReconstructPlan(
        config_path=cfg.path, config_sha256=cfg.sha256, workdir=cfg.workdir, output=cfg.workdir / RECONSTRUCTION_FILE,
        images=images, settings=rc.settings(), noise=rc.noise, read_noise_photons=rc.read_noise_photons,
        joint=rc.joint, sweep=rc.sweep, filters=filters,
        main_filter=filters[0] if filters else getattr(src, "filter", None),
        transmissions=dict(src.transmissions) if isinstance(src, C.CaptureSource) else {},
        rois=tuple(m_.rois or ()), roi_mesh=cfg.resolve(surface.mesh) if isinstance(surface, C.MeshSurface) else None,
        config_exposure_s=reconstruction_exposure_s(src, m_.simulate), simulation_exposure_s=simulation_exposure_s(m_.simulate),
        camera=m_.system.camera, system=m_.system, calibration_budget=rc.calibration_budget, digest=digest,
        geometry=source.geometry(surface_sha), subject_emission=copy.deepcopy((geometry.get("subject") or {}).get("emission")),
        qe_warning=assumed_qe_warning(m_.system, "reconstruct", real_counts=counts_in(src, m_.rig)),
        views=views, placer=placer, todo=todo, transfer=source, surface_sha256=surface_sha)
