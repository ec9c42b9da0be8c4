"""``fluxmap build-T CONFIG``: one transfer matrix per pose, cached by content.

Examples
--------
$ fluxmap build-T configs/demo.yaml
$ fluxmap build-T configs/paper-3d.yaml --jobs 2
$ fluxmap build-T configs/paper-2d.yaml --set transfer.estimator=pairwise
"""

from __future__ import annotations

import json
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from .. import artefacts as A
from ..config import LoadedConfig, Transfer
from ..optics.transfer import ALGORITHM_VERSION, LensSampling, PairwiseSampling, TransferResult, View, build_transfer
from ..scene import PlacedScene, Pose, SubjectPlacer, poses_from_config, views_from_config
from .context import RunContext


@dataclass(frozen=True)
class PoseT:
    pose: Pose
    key: str
    path: Path


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
    ``unknowns="sub_elements"`` gives T's columns per sub-element (Surface.unknowns)."""
    tr = transfer or cfg.model.transfer
    views = views_from_config(cfg.model.system)
    placer = SubjectPlacer(cfg)
    out = []
    cdir = cache_dir(cfg)
    for pose in poses_from_config(cfg.model.subject):
        scene = placer.scene(pose, cfg.model.system)
        if unknowns == "sub_elements":
            scene = PlacedScene(scene.pose, scene.surface.unknowns()[0], scene.occluders)
        key = A.cache_key(key_parts(scene, views, tr))
        out.append((scene, PoseT(pose, key, cdir / f"{key}.h5")))
    return views, placer, out


def _build_and_store(scene: PlacedScene, views: list[View], tr: Transfer, target: Path, config_sha: str) -> dict:
    """Worker: compute T for one pose and write it atomically; returns a summary."""
    t0 = time.perf_counter()
    res = build_transfer(
        scene.surface, views, scene.occluders, estimator=tr.estimator,
        lens_sampling=LensSampling(**tr.lens.model_dump()),
        pairwise_sampling=PairwiseSampling(**tr.pairwise.model_dump()),
        ray_offset_mm=tr.ray_offset_mm, rays_per_batch=tr.rays_per_batch,
    )
    seconds = time.perf_counter() - t0
    write_T(target, res, scene, tr.estimator, seconds, config_sha)
    return summarise(res, scene) | {"seconds": seconds}


def write_T(path: Path, res: TransferResult, scene: PlacedScene, estimator: str, seconds: float, config_sha: str) -> None:
    with A.write_artefact(path, "transfer", config_sha256=config_sha) as f:
        A.write_csr(f.create_group("T"), res.T)
        f["T"].attrs["unit"] = "dimensionless (fraction of element power reaching the pixel)"
        f["T"].attrs["pixel_order"] = "row-major [row, col]; flat index row * nx + col"
        A.write_surface(f.create_group("surface"), scene.surface)
        occ = f.create_group("occluders")
        for k, o in enumerate(scene.occluders):
            A.write_surface(occ.create_group(f"{k}"), o)
        vg = f.create_group("views")
        cam = res.views[0].camera
        f.attrs["pixels"] = np.array([cam.nx, cam.ny])
        for k, (view, Tv) in enumerate(zip(res.views, res.T_per_view)):
            g = vg.create_group(f"{k}")
            g.attrs["kind"] = "direct" if view.mirror is None else "mirror"
            g.attrs["weight"] = view.weight
            A.write_csr(g, Tv)
            for name, val in res.stats[view.name].items():
                g.attrs[name] = val
        f.attrs["pose_height_mm"] = scene.pose.height_mm
        f.attrs["pose_rotation_deg"] = scene.pose.rotation_deg
        f.attrs["estimator"] = estimator
        f.attrs["build_seconds"] = seconds


def summarise(res: TransferResult, scene: PlacedScene) -> dict:
    """Collection efficiency per view: the fraction of the power of a uniformly glowing
    surface that the view delivers to the sensor (area-weighted mean column sum)."""
    areas = scene.surface.element_areas_mm2
    eff = {}
    for view, Tv in zip(res.views, res.T_per_view):
        col = np.asarray(Tv.sum(axis=0)).ravel() * view.weight
        eff[view.name] = float(col @ areas / areas.sum())
    return {"nnz": int(res.T.nnz), "efficiency": eff}


def read_summary(path: Path, view_names: list[str], areas: np.ndarray) -> dict:
    with A.open_artefact(path, "transfer") as f:
        eff = {}
        for k, name in enumerate(view_names):
            g = f["views"][str(k)]
            col = np.asarray(A.read_csr(g).sum(axis=0)).ravel() * float(g.attrs["weight"])
            eff[name] = float(col @ areas / areas.sum())
        return {"nnz": int(f["T"]["data"].shape[0]), "efficiency": eff, "seconds": float(f.attrs["build_seconds"])}


def ensure_T(cfg: LoadedConfig, ctx: RunContext, transfer: Transfer | None = None, label: str = "building T",
             unknowns: str = "elements"):
    """Build every pose's T that the cache lacks (all with ``ctx.force``).

    Returns views, placer, [(scene, PoseT)], and per key a summary dict (cached, seconds,
    nnz, efficiency per view)."""
    tr = transfer or cfg.model.transfer
    views, placer, todo = plan(cfg, tr, unknowns)
    names = [v.name for v in views]
    results: dict[str, dict] = {}
    need, seen = [], set()
    for s, p in todo:
        if (ctx.force or not p.path.is_file()) and p.key not in seen:
            need.append((s, p))
            seen.add(p.key)
    for s, p in todo:
        if p.key not in seen:
            results[p.key] = read_summary(p.path, names, s.surface.element_areas_mm2) | {"cached": True}
    with ctx.progress(label, total=len(need)) as advance:
        if ctx.jobs > 1 and len(need) > 1:
            with ProcessPoolExecutor(max_workers=ctx.jobs) as ex:
                futs = {ex.submit(_build_and_store, s, views, tr, p.path, cfg.sha256): p for s, p in need}
                for fut in futs:
                    results[futs[fut].key] = fut.result() | {"cached": False}
                    advance()
        else:
            for s, p in need:
                results[p.key] = _build_and_store(s, views, tr, p.path, cfg.sha256) | {"cached": False}
                advance()
    return views, placer, todo, results


def load_T(path: Path):
    """The combined T (CSR, pixels x elements) of one cached pose."""
    with A.open_artefact(path, "transfer") as f:
        return A.read_csr(f["T"])


def run(cfg: LoadedConfig, ctx: RunContext) -> Path:
    views, _, todo = plan(cfg)  # validates the geometry before anything is printed
    ctx.say(f"build-T: {len(todo)} pose(s), views {', '.join(v.name for v in views)}, "
            f"estimator {cfg.model.transfer.estimator}, cache {cache_dir(cfg)}")
    views, placer, todo, results = ensure_T(cfg, ctx)
    names = [v.name for v in views]
    rows = []
    for s, p in todo:
        r = results[p.key]
        rows.append([p.pose.height_mm, p.pose.rotation_deg, "cache hit" if r["cached"] else f"{r['seconds']:.1f} s",
                     r["nnz"], *[r["efficiency"][n] for n in names]])
    ctx.table(["height_mm", "rotation_deg", "build", "nnz", *[f"eff {n}" for n in names]], rows)
    index = cfg.workdir / "transfer.h5"
    with A.write_artefact(index, "transfer-index", config_sha256=cfg.sha256,
                          inputs={p.key: p.key for _, p in todo}) as f:
        f.create_dataset("heights_mm", data=[p.pose.height_mm for _, p in todo])
        f.create_dataset("rotations_deg", data=[p.pose.rotation_deg for _, p in todo])
        f.create_dataset("keys", data=np.array([p.key for _, p in todo], dtype="S64"))
        f.create_dataset("paths", data=np.array([str(p.path) for _, p in todo], dtype=object),
                         dtype=__import__("h5py").string_dtype())
        f.create_dataset("efficiency", data=np.array([[results[p.key]["efficiency"][n] for n in names] for _, p in todo]))
        f.attrs["view_names"] = json.dumps(names)
        f.attrs["estimator"] = cfg.model.transfer.estimator
    ctx.say(f"index written to {index}")
    return index


def ensure_pose_T(cfg: LoadedConfig, pose: Pose, transfer: Transfer | None = None,
                  placer: SubjectPlacer | None = None):
    """T (CSR) of one pose that need not be in ``subject.poses`` (the simulated rig renders
    at the stage's physical height), from the cache or built and cached."""
    tr = transfer or cfg.model.transfer
    views = views_from_config(cfg.model.system)
    scene = (placer or SubjectPlacer(cfg)).scene(pose, cfg.model.system)
    path = cache_dir(cfg) / f"{A.cache_key(key_parts(scene, views, tr))}.h5"
    if not path.is_file():
        _build_and_store(scene, views, tr, path, cfg.sha256)
    return load_T(path)
