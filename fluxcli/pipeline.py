"""What several stages build from a config: the T of each pose (through the T cache),
the sensor model, and the provenance every artefact records.

Stages import this module, never each other.
"""

from __future__ import annotations

import time
from concurrent.futures import as_completed
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import artefacts as A
from .artefacts import transfer as AT
from .config import LoadedConfig, Sensor, Transfer
from .errors import UserError
from .imaging import noise as N
from .optics.transfer import ALGORITHM_VERSION, LensSampling, PairwiseSampling, View, build_transfer
from .scene import PlacedScene, Pose, SubjectPlacer, poses_from_config, views_from_config
from .workers import worker_pool

# build-T refuses a pose whose views collect nothing, and warns below this fraction of the
# collection efficiency the best pose reaches (a view that barely sees the subject)
WEAK_VIEW_FRACTION = 0.02


@dataclass(frozen=True)
class PoseT:
    pose: Pose
    key: str
    path: Path


# ------------------------------------------------------------------ provenance
def geometry_of(cfg: LoadedConfig, surface_sha256: str | None = None) -> dict:
    """The set-up an artefact is made for: system (camera, lens, sensor, apertures, mirrors,
    stage), subject (surface, poses, rotation axis) and the digest of the built surface."""
    m = cfg.model
    g = {"system": m.system.model_dump(mode="json") if m.system is not None else None,
         "subject": m.subject.model_dump(mode="json") if m.subject is not None else None}
    if surface_sha256 is not None:
        g["surface_sha256"] = surface_sha256
    return g


def provenance(cfg: LoadedConfig, surface_sha256: str | None = None) -> A.Provenance:
    return A.Provenance(config=cfg.model.model_dump(mode="json", by_alias=True),
                        geometry=geometry_of(cfg, surface_sha256))


# ------------------------------------------------------------------ the sensor
def emccd_model(sensor: Sensor, exposure_s: float) -> N.EMCCDModel:
    return N.EMCCDModel(**sensor.model_dump(), exposure_s=exposure_s)


# ------------------------------------------------------------------ T per pose
def cache_dir(cfg: LoadedConfig) -> Path:
    return cfg.resolve(cfg.model.transfer.cache_dir) if cfg.model.transfer.cache_dir else cfg.workdir / "cache" / "T"


def key_parts(scene: PlacedScene, views: list[View], tr: Transfer) -> dict:
    """Everything T depends on, and nothing else (no names, paths or later-stage settings)."""
    cam = views[0].camera
    sampling = tr.lens.model_dump() if tr.estimator == "lens" else tr.pairwise.model_dump()
    return A.canonical({
        "algorithm": ALGORITHM_VERSION,
        "surface": scene.surface.digest(),
        "occluders": [o.digest() for o in scene.occluders],
        "camera": {
            "center_mm": cam.center_mm, "axis": cam.axis, "right": cam.right, "down": cam.down,
            "focal_length_mm": cam.focal_length_mm, "aperture_radius_mm": cam.aperture_radius_mm,
            "focus_distance_mm": cam.focus_distance_mm, "pixels": [cam.nx, cam.ny],
            "pixel_pitch_mm": cam.pixel_pitch_mm,
            "apertures": [[a.distance_mm, a.radius_mm] for a in cam.apertures],
        },
        "mirrors": [{"center_mm": v.mirror.center_mm, "normal": v.mirror.normal, "axis_u": v.mirror.axis_u,
                     "half_size_mm": v.mirror.half_size_mm, "weight": v.weight} for v in views[1:]],
        "estimator": tr.estimator,
        "sampling": sampling,
        "ray_offset_mm": tr.ray_offset_mm,
    })


def plan(cfg: LoadedConfig, transfer: Transfer | None = None, unknowns: str = "elements"
         ) -> tuple[list[View], SubjectPlacer, list[tuple[PlacedScene, PoseT]]]:
    """The views, the subject placer, and per pose its placed scene and cache entry.

    ``transfer`` overrides ``cfg.model.transfer`` (simulate builds a finer T this way);
    ``unknowns="sub_elements"`` gives T's columns per sub-element (Surface.unknowns),
    ``"refined:n"`` per face of the surface refined n times (Surface.refined)."""
    tr = transfer or cfg.model.transfer
    views = views_from_config(cfg.model.system)
    placer = SubjectPlacer(cfg)
    out = []
    cdir = cache_dir(cfg)
    for pose in poses_from_config(cfg.model.subject):
        scene = placer.scene(pose, cfg.model.system)
        if unknowns == "sub_elements":
            scene = PlacedScene(scene.pose, scene.surface.unknowns()[0], scene.occluders)
        elif unknowns.startswith("refined:"):  # simulate: columns per face of the refined surface
            levels = int(unknowns.split(":")[1])
            if levels > 0:
                scene = PlacedScene(scene.pose, scene.surface.refined(levels)[0], scene.occluders)
        key = A.cache_key(key_parts(scene, views, tr))
        out.append((scene, PoseT(pose, key, AT.entry_path(cdir, key))))
    return views, placer, out


def _build_and_store(scene: PlacedScene, views: list[View], tr: Transfer, target: Path, config_sha: str,
                     prov: A.Provenance | None = None) -> dict:
    """Worker: compute T for one pose and write it atomically; returns a summary."""
    t0 = time.perf_counter()
    res = build_transfer(
        scene.surface, views, scene.occluders, estimator=tr.estimator,
        lens_sampling=LensSampling(**tr.lens.model_dump()),
        pairwise_sampling=PairwiseSampling(**tr.pairwise.model_dump()),
        ray_offset_mm=tr.ray_offset_mm, rays_per_batch=tr.rays_per_batch,
    )
    seconds = time.perf_counter() - t0
    cam = res.views[0].camera
    AT.write_T(target, T=res.T, T_per_view=res.T_per_view,
               view_kinds=["direct" if v.mirror is None else "mirror" for v in res.views],
               weights=[v.weight for v in res.views], stats=[res.stats[v.name] for v in res.views],
               pixels=(cam.nx, cam.ny), surface=scene.surface, occluders=scene.occluders,
               height_mm=scene.pose.height_mm, rotation_deg=scene.pose.rotation_deg, estimator=tr.estimator,
               seconds=seconds, config_sha256=config_sha, provenance=prov)
    return summarise(res, scene) | {"seconds": seconds}


def summarise(res, scene: PlacedScene) -> dict:
    """Collection efficiency per view: the fraction of the power of a uniformly glowing
    surface that the view delivers to the sensor (area-weighted mean column sum)."""
    areas = scene.surface.element_areas_mm2
    eff = {view.name: AT.efficiency(Tv, view.weight, areas) for view, Tv in zip(res.views, res.T_per_view)}
    return {"nnz": int(res.T.nnz), "efficiency": eff}


def ensure_T(cfg: LoadedConfig, ctx, transfer: Transfer | None = None, label: str = "building T",
             unknowns: str = "elements"):
    """Build every pose's T that the cache lacks (all with ``ctx.force``); a cache entry
    that cannot be read is rebuilt with a warning.

    Returns views, placer, [(scene, PoseT)], and per key a summary dict (cached, seconds,
    nnz, efficiency per view)."""
    tr = transfer or cfg.model.transfer
    views, placer, todo = plan(cfg, tr, unknowns)
    names = [v.name for v in views]
    results: dict[str, dict] = {}
    need, seen = [], set()
    for s, p in todo:
        if p.key in seen:
            continue
        seen.add(p.key)
        if not ctx.force:
            summary, why = AT.check_entry(p.path, names, s.surface.element_areas_mm2)
            if summary is not None:
                results[p.key] = summary | {"cached": True}
                continue
            if why != "missing":
                ctx.warn(f"the cached T of pose {p.pose.label} is unreadable and is rebuilt: {why}")
        need.append((s, p))
    prov = provenance(cfg, placer.surface.digest())
    with ctx.progress(label, total=len(need)) as advance:
        if ctx.jobs > 1 and len(need) > 1:
            with worker_pool(min(ctx.jobs, len(need)), temp_dirs=(cache_dir(cfg),)) as ex:
                futs = {ex.submit(_build_and_store, s, views, tr, p.path, cfg.sha256, prov): p for s, p in need}
                for fut in as_completed(futs):
                    results[futs[fut].key] = fut.result() | {"cached": False}
                    advance()
        else:
            for s, p in need:
                results[p.key] = _build_and_store(s, views, tr, p.path, cfg.sha256, prov) | {"cached": False}
                advance()
    check_collection(todo, results, names, ctx)
    return views, placer, todo, results


def check_collection(todo, results: dict, view_names: list[str], ctx) -> None:
    """Refuse a pose no view collects light from; warn about views that barely see the subject."""
    best = max((max(results[p.key]["efficiency"].values()) for _, p in todo), default=0.0)
    for _, p in todo:
        eff = results[p.key]["efficiency"]
        if sum(eff.values()) <= 0:
            raise UserError(
                f"at pose {p.pose.label} no camera view collects any light from the subject (T is all zero): "
                "check system.camera.pose.lens_center_mm and system.camera.pose.look (does the camera look at "
                "the subject?), system.camera.lens.focus_distance_mm, system.mirrors, and subject.poses.heights_mm "
                "(is the subject between the stage and the lens?).")
        for name in view_names:
            if best > 0 and eff[name] < WEAK_VIEW_FRACTION * best:
                ctx.warn(f"view {name} at pose {p.pose.label} collects {eff[name] / best:.1%} of the light the best "
                         f"view collects (below {WEAK_VIEW_FRACTION:.0%}): it barely sees the subject.")
