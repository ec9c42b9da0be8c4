"""From a loaded config to the typed parts the floors below take: the T cache's plan, the
provenance an artefact records, the folders to check, the sensor model.

Only stage commands call these (they hold the config); everything below them takes what
these return, never the config.
"""

from __future__ import annotations

from pathlib import Path

from .. import artefacts as A
from ..artefacts import provenance as AP
from ..config import FileFlux, LoadedConfig, Sensor, Transfer, emission_profile
from ..imaging import noise as N
from ..resources import check_folders as _check_folders
from ..scene import Pose, SubjectPlacer, poses_from_config, views_from_config
from ..transfer_cache import TransferPlan, TransferSource, pose_T, with_columns
from ..truth import TruthPlan, truth_refinement


def source_of(cfg: LoadedConfig) -> TransferSource:
    """What the T cache needs of this config (:class:`~fluxcli.transfer_cache.TransferSource`), read once."""
    m = cfg.model
    return TransferSource(m.system, m.subject, emission_profile(cfg), cfg.resolver, m.transfer, cache_dir(cfg),
                          cfg.sha256, m.model_dump(mode="json", by_alias=True),
                          emission_assumed=m.subject is not None and m.subject.emission is None)


def placer_of(cfg: LoadedConfig) -> SubjectPlacer:
    """The subject as the config describes it, ready to be placed at any pose."""
    return SubjectPlacer(cfg.model.subject, cfg.model.system.stage, emission_profile(cfg), cfg.resolver)


def cache_dir(cfg: LoadedConfig) -> Path:
    """The T cache: ``transfer.cache_dir``, else ``<workdir>/cache/T``."""
    return cfg.resolve(cfg.model.transfer.cache_dir) if cfg.model.transfer.cache_dir else cfg.workdir / "cache" / "T"


def check_folders(cfg: LoadedConfig, *, cache: bool = True) -> None:
    """The workdir (and the T cache) must be writable before a stage computes anything."""
    _check_folders(cfg.workdir, cache_dir(cfg) if cache else None,
                   "transfer.cache_dir" if cfg.model.transfer.cache_dir else "workdir")


def geometry_of(cfg: LoadedConfig, surface_sha256: str | None = None) -> dict:
    """The set-up an artefact of this config is made for (:func:`fluxcli.artefacts.provenance.geometry_of`)."""
    return AP.geometry_of(cfg.model.system, cfg.model.subject, lambda: emission_profile(cfg).key(), surface_sha256)


def provenance(cfg: LoadedConfig, surface_sha256: str | None = None) -> A.Provenance:
    """The provenance an artefact of this config records: the resolved config and its geometry."""
    return AP.provenance_of(cfg.model.model_dump(mode="json", by_alias=True), geometry_of(cfg, surface_sha256))


def emccd_model(sensor: Sensor, exposure_s: float) -> N.EMCCDModel:
    """The EMCCD noise model of ``system.camera.sensor`` at an exposure."""
    return N.EMCCDModel(**sensor.model_dump(), exposure_s=exposure_s)


def transfer_plan(cfg: LoadedConfig, transfer: Transfer | None = None, unknowns: str = "elements") -> TransferPlan:
    """What this config asks of the T cache (:meth:`TransferSource.plan`): views, placer, per pose
    its placed scene and entry."""
    return source_of(cfg).plan(transfer, unknowns)


# ------------------------------------------------------------------ the former pipeline's cfg-taking calls
def plan(cfg: LoadedConfig, transfer: Transfer | None = None, unknowns: str = "elements"):
    """``(views, placer, [(scene, PoseT)])`` of :func:`transfer_plan`."""
    tp = transfer_plan(cfg, transfer, unknowns)
    return tp.views, tp.placer, tp.poses


def ensure_pose_T(cfg: LoadedConfig, pose: Pose, transfer: Transfer | None = None,
                  placer: SubjectPlacer | None = None, refine: int = 0, tangent: bool = False):
    """T (CSR) of one pose that need not be in ``subject.poses`` (:func:`fluxcli.transfer_cache.pose_T`);
    with ``refine`` its columns are the faces of the surface refined that often; with ``tangent``
    also its tangential-flux matrix: (T, T_tangent)."""
    views = views_from_config(cfg.model.system)
    scene = with_columns((placer or placer_of(cfg)).scene(pose, cfg.model.system), f"refined:{refine}")
    return pose_T(scene, views, transfer or cfg.model.transfer, cache_dir(cfg), cfg.sha256, provenance(cfg), tangent)


def truth_plan(cfg: LoadedConfig, flux=None) -> TruthPlan:
    """What ``simulate.flux`` (or ``flux`` in its place: the simulated rig's per-filter truth)
    makes the ground truth from, its paths resolved."""
    sim = cfg.model.simulate
    flux = flux if flux is not None else sim.flux
    mesh_dir = getattr(flux, "mesh_dir", None)
    return TruthPlan(flux, truth_refinement(sim), cfg.workdir / "cache" / "mesh",
                     cfg.resolve(mesh_dir) if mesh_dir is not None else None,
                     cfg.resolve(flux.path) if isinstance(flux, FileFlux) else None)
