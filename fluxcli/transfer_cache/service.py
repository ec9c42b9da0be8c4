"""The T cache as a service: what a stage asks for (its poses' T, built or read from the
cache), keyed by the content of everything T depends on.

The stage reads what T needs from its config once, into a :class:`TransferSource`
(:func:`fluxcli.stages.plans.source_of`), which makes the :class:`TransferPlan` of its poses;
everything here takes those or their parts, never the config.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property
from pathlib import Path
from typing import Callable

import numpy as np

from .. import _numba_cache
from .. import artefacts as A
from ..artefacts import transfer as AT
from ..artefacts import provenance as AP
from ..config import Subject, System, Transfer
from ..errors import UserError
from ..optics.transfer import ALGORITHM_VERSION, LensSampling, PairwiseSampling, View, default_threads, surface_sample_count
from ..progress import run_tasks
from ..resources import check_memory
from ..optics.emission import Profile
from ..scene import PlacedScene, Pose, SubjectPlacer, poses_from_config, views_from_config
from ..workers import pool_for
from .build import SAMPLE_BYTES, build_and_store, transfer_bytes
from .cluster import build_on_cluster, check_shared

# build-T refuses a pose whose views collect nothing, and warns when a view collects less than
# WEAK_VIEW_FRACTION of what the best view does, or sees less than SEEN_FRACTION of the subject's area
WEAK_VIEW_FRACTION = 0.02
SEEN_FRACTION = 0.05


@dataclass(frozen=True)
class PoseT:
    pose: Pose
    key: str
    path: Path


@dataclass(frozen=True)
class TransferPlan:
    """What a stage asks the T cache for: its views, the subject placer, per pose the placed
    scene and cache entry, the T's sampling, where the cache is, and what the T files record
    (the config's digest and the provenance, with the built surface's digest)."""

    views: list[View]
    placer: SubjectPlacer
    poses: list[tuple[PlacedScene, PoseT]]
    transfer: Transfer
    cache_dir: Path
    config_sha256: str
    provenance: A.Provenance
    emission_assumed: bool = False  # subject.emission absent (Lambertian assumed): a notice once per run


@dataclass(frozen=True)
class TransferSource:
    """What the T cache needs of a config, read once by a stage's plan: the rig, the subject with
    its emission profile, T's sampling, the cache folder and what T files record. A stage hands
    this on instead of the config; :meth:`with_system` is the same subject under another rig
    (the error budget moves the calibrated parameters)."""

    system: System  # system: camera, mirrors, stage
    subject: Subject  # subject: surface, poses, emission
    emission: Profile  # the subject's emission profile (Lambertian when subject.emission is absent)
    resolve: Callable[[Path], Path]  # a path the config gives -> the file it means (beside the config)
    transfer: Transfer  # transfer: T's estimator and sampling
    cache_dir: Path  # the T cache folder
    config_sha256: str  # the config file's sha256 (what T files record)
    config_json: dict  # the resolved config, dumped by alias in JSON mode (what provenance records)
    emission_assumed: bool = False  # subject.emission absent (Lambertian assumed): a notice once per run

    @cached_property
    def placer(self) -> SubjectPlacer:
        """The subject, built once, ready to be placed at any pose on this rig's stage."""
        return SubjectPlacer(self.subject, self.system.stage, self.emission, self.resolve)

    def with_system(self, system: System) -> "TransferSource":
        """The same subject and sampling under another rig (the config as if it stated ``system``)."""
        return replace(self, system=system,
                       config_json={**self.config_json, "system": system.model_dump(mode="json", by_alias=True)})

    def geometry(self, surface_sha256: str | None = None) -> dict:
        """The set-up an artefact of this source is made for (:func:`fluxcli.artefacts.provenance.geometry_of`)."""
        return AP.geometry_of(self.system, self.subject, self.emission.key, surface_sha256)

    def provenance(self, surface_sha256: str | None = None) -> A.Provenance:
        """A fresh provenance record: the resolved config and the geometry (with the built surface's digest)."""
        return AP.provenance_of(self.config_json, self.geometry(surface_sha256))

    def plan(self, transfer: Transfer | None = None, unknowns: str = "elements") -> "TransferPlan":
        """What to ask the T cache for: views, placer, per pose its placed scene and entry.

        ``transfer`` overrides :attr:`transfer` (simulate builds a finer T this way);
        ``unknowns="sub_elements"`` gives T's columns per sub-element (Surface.unknowns),
        ``"refined:n"`` per face of the surface refined n times (Surface.refined)."""
        tr = transfer or self.transfer
        views, placer = views_from_config(self.system), self.placer
        poses = place(placer, self.system, poses_from_config(self.subject), views, tr, self.cache_dir, unknowns)
        return TransferPlan(views, placer, poses, tr, self.cache_dir, self.config_sha256,
                            self.provenance(placer.surface.digest()), emission_assumed=self.emission_assumed)

    def ensure(self, ctx, label: str = "building T", unknowns: str = "elements", transfer: Transfer | None = None):
        """Every pose's T in the cache (:func:`ensure`): views, placer, [(scene, PoseT)], and per
        key a summary dict (cached, seconds, nnz, efficiency per view)."""
        tp = self.plan(transfer, unknowns)
        return tp.views, tp.placer, tp.poses, ensure(tp, ctx, label)


EMISSION_NOTICE = ("subject.emission is not set: the surface is taken as Lambertian. Light leaving tissue or a turbid "
                   "phantom is better described by subject.emission: {model: diffuse, refractive_index: 1.40} (read as "
                   "Lambertian it is ~11 % too bright head-on and ~37 % too dim at 80 deg from the normal; "
                   "docs/design.md, Emission).")


def emission_notice(ctx) -> None:
    """One short notice per run that ``subject.emission`` is absent (Lambertian is assumed)."""
    if EMISSION_NOTICE in ctx.warned:
        return
    ctx.warned.add(EMISSION_NOTICE)
    ctx.say(EMISSION_NOTICE)


def announce(ctx, placer: SubjectPlacer) -> None:
    """Say what a mesh file yielded, and warn about what was repaired in it and what placing it
    found (once per run)."""
    for k, note in enumerate(placer.notes):
        if k == 0:
            if note not in ctx.warned:
                ctx.warned.add(note)
                ctx.say(note)
        else:
            ctx.warn(note)
    for w in placer.warnings:
        ctx.warn(w)


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
    } | ({"emission": scene.emission.key()} if scene.emission is not None and not scene.emission.is_lambertian
         else {}))  # Lambertian: no entry, so that its keys are those made before emission profiles


def with_columns(scene: PlacedScene, unknowns: str = "elements") -> PlacedScene:
    """The scene whose surface gives T's columns: per element (``"elements"``), per sub-element
    (``"sub_elements"``, Surface.unknowns) or per face of the surface refined n times
    (``"refined:n"``, Surface.refined; what simulate images the truth with)."""
    if unknowns == "sub_elements":
        return PlacedScene(scene.pose, scene.surface.unknowns()[0], scene.occluders, scene.emission)
    if unknowns.startswith("refined:"):
        levels = int(unknowns.split(":")[1])
        if levels > 0:
            return PlacedScene(scene.pose, scene.surface.refined(levels)[0], scene.occluders, scene.emission)
    return scene


def place(placer: SubjectPlacer, system: System, poses: list[Pose], views: list[View], transfer: Transfer,
          cache_dir: Path, unknowns: str = "elements") -> list[tuple[PlacedScene, PoseT]]:
    """Per pose its placed scene (columns as ``unknowns`` says, :func:`with_columns`) and its
    cache entry in ``cache_dir``."""
    out = []
    for pose in poses:
        scene = with_columns(placer.scene(pose, system), unknowns)
        key = A.cache_key(key_parts(scene, views, transfer))
        out.append((scene, PoseT(pose, key, AT.entry_path(cache_dir, key))))
    return out


def ensure(plan: TransferPlan, ctx, label: str = "building T") -> dict[str, dict]:
    """Build every pose's T of ``plan`` that the cache lacks (all with ``ctx.force``); a cache
    entry that cannot be read is rebuilt with a warning.

    Returns per key a summary dict (cached, seconds, nnz, efficiency per view)."""
    views, placer, todo, tr, cache = plan.views, plan.placer, plan.poses, plan.transfer, plan.cache_dir
    announce(ctx, placer)
    if plan.emission_assumed:
        emission_notice(ctx)
    A.clean_stale_temps(cache)  # what killed runs left, even when nothing is rebuilt
    nx, ny = views[0].camera.nx, views[0].camera.ny
    n_el = todo[0][0].surface.n_elements if todo else 0
    jobs = max(1, min(ctx.jobs, len(todo)))
    check_memory(transfer_bytes(nx * ny, len(views), n_el) * jobs,
                 f"building T ({nx} x {ny} pixels, {len(views)} view(s), {n_el} elements"
                 + (f", {ctx.jobs} jobs)" if ctx.jobs > 1 else ")"),
                 "system.camera.pixels (bin the sensor), the elements of subject.surface, or --jobs")
    if todo:
        n = max(surface_sample_count(s.surface, views, tr.estimator, LensSampling(**tr.lens.model_dump()),
                                     PairwiseSampling(**tr.pairwise.model_dump())) for s, _ in todo[:1] + todo[-1:])
        check_memory(SAMPLE_BYTES * n * jobs, f"building T ({n:.3g} surface sample points per view"
                     + (f", {ctx.jobs} jobs)" if ctx.jobs > 1 else ")"),
                     "transfer.lens.surface_samples_per_pixel or transfer.lens.max_surface_subdivisions "
                     "(or transfer.pairwise.surface_subdivisions), the faces of subject.surface, or --jobs")
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
    prov = plan.provenance
    compiling = bool(need) and not _numba_cache.kernels_compiled()
    if compiling:  # the first build after an install: say why it waits
        ctx.say(_numba_cache.COMPILING)
    cluster = getattr(ctx, "client", None)  # --scheduler: a Dask cluster builds the poses
    # one bar over the poses, advanced after every batch of rays in every worker (with an ETA)
    # processes x threads <= cores locally; on a cluster one thread per task (a worker thread is a core)
    if cluster is not None:
        built = build_on_cluster(cluster, need, views, tr, plan.config_sha256, prov, label, ctx.quiet)
        check_shared(cache, [p.path for _, p in need])
    else:
        threads = max(1, default_threads() // max(1, min(ctx.jobs, len(need))))
        tasks = [(s, views, tr, p.path, plan.config_sha256, prov, threads) for s, p in need]
        built = []
        if compiling and ctx.jobs > 1 and len(tasks) > 1:  # compile once, here; the workers then load the cache
            built = run_tasks(build_and_store, tasks[:1], label=f"{label} (compiling)", jobs=1, quiet=ctx.quiet)
        built += run_tasks(build_and_store, tasks[len(built):], label=label, jobs=ctx.jobs, quiet=ctx.quiet,
                           pool=pool_for(None, temp_dirs=(cache,)))
    results |= {p.key: r | {"cached": False} for (_, p), r in zip(need, built)}
    check_collection(todo, results, names, ctx)
    return results



def pose_entry(scene: PlacedScene, views: list[View], transfer: Transfer, cache_dir: Path) -> Path:
    """Where the T cache keeps (or will keep) the T of one placed scene."""
    return AT.entry_path(cache_dir, A.cache_key(key_parts(scene, views, transfer)))


def pose_T(scene: PlacedScene, views: list[View], transfer: Transfer, cache_dir: Path, config_sha256: str,
           provenance: A.Provenance, tangent: bool = False):
    """T (CSR) of one placed scene (a pose that need not be in ``subject.poses``: the simulated
    rig renders at the stage's physical height), from the T cache or built and cached; with
    ``tangent`` also its tangential-flux matrix (None without one): (T, T_tangent)."""
    path = pose_entry(scene, views, transfer, cache_dir)
    if not path.is_file():
        build_and_store(scene, views, transfer, path, config_sha256, provenance)
    if tangent:
        return AT.load_T(path), AT.load_T_tangent(path)
    return AT.load_T(path)


def curvature_ratios(surface, views: list[View], emission: Profile) -> list[np.ndarray]:
    """Per view, per column of ``surface`` (one face per element, placed) the emission profile's
    curvature ratio (:meth:`Profile.curvature_ratio`, mm^2) at the face's emission angle towards
    the view's lens centre (a mirror view's virtual one: the ray leaving the real surface runs
    towards it).  Across the aperture the angle moves by its half-width seen from the subject
    (1.5 deg at 317 mm for a 17-mm aperture); the chief ray stands for it."""
    ok = surface.element_of_face >= 0
    cen = surface.vertices_mm[surface.faces[ok]].mean(axis=1)
    nrm = surface.face_normals[ok]
    out = []
    for v in views:
        d = np.asarray(v.camera.center_mm, float) - cen
        cos = np.einsum("ij,ij->i", nrm, d) / np.linalg.norm(d, axis=1)
        r = np.zeros(surface.n_elements)
        r[surface.element_of_face[ok]] = emission.curvature_ratio(cos)
        out.append(r)
    return out


def check_collection(todo, results: dict, view_names: list[str], ctx) -> None:
    """Refuse a pose no view collects light from; warn about views that barely see the subject."""
    def finite(x):
        return x if np.isfinite(x) else 0.0

    best = max((max(finite(v) for v in results[p.key]["efficiency"].values()) for _, p in todo), default=0.0)
    for _, p in todo:
        eff = {k: finite(v) for k, v in results[p.key]["efficiency"].items()}
        if not sum(eff.values()) > 0:
            raise UserError(
                f"at pose {p.pose.label} no camera view collects any light from the subject (T is all zero): "
                "check system.camera.pose.lens_center_mm and system.camera.pose.look (does the camera look at "
                "the subject?), system.camera.lens.focus_distance_mm, system.mirrors, and subject.poses.heights_mm "
                "(is the subject between the stage and the lens?).")
        for name in view_names:
            seen = results[p.key].get("seen", {}).get(name)
            if best > 0 and eff[name] < WEAK_VIEW_FRACTION * best:
                ctx.warn(f"view {name} at pose {p.pose.label} collects {eff[name] / best:.1%} of the light the best "
                         f"view collects (below {WEAK_VIEW_FRACTION:.0%}): it barely sees the subject.")
            elif seen is not None and seen < SEEN_FRACTION:
                ctx.warn(f"view {name} at pose {p.pose.label} sees {seen:.1%} of the subject's area (below "
                         f"{SEEN_FRACTION:.0%}): check its placement (system.camera.pose, system.mirrors).")

