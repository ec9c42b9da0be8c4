"""What several stages build from a config: the T of each pose (through the T cache),
the sensor model, and the provenance every artefact records.

Stages import this module, never each other.
"""

from __future__ import annotations

import collections
import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import _numba_cache
from . import artefacts as A
from .artefacts import transfer as AT
from .config import LoadedConfig, Sensor, Transfer
from .errors import UserError
from .imaging import noise as N
from .optics.raycast import OcclusionScene
from .optics.transfer import (ALGORITHM_VERSION, Checkpoint, LensSampling, PairwiseSampling, View, build_transfer,
                             cast_lens_block, default_threads, lens_blocks, lens_chunks, lens_plan,
                             surface_sample_count)
from .scene import PlacedScene, Pose, SubjectPlacer, poses_from_config, views_from_config
from .progress import run_tasks
from .surface.mesh import merge
from .workers import pool_for

# build-T refuses a pose whose views collect nothing, and warns when a view collects less than
# WEAK_VIEW_FRACTION of what the best view does, or sees less than SEEN_FRACTION of the subject's area
WEAK_VIEW_FRACTION = 0.02
SEEN_FRACTION = 0.05


@dataclass(frozen=True)
class PoseT:
    pose: Pose
    key: str
    path: Path


# ------------------------------------------------------------------ before any compute
def check_writable(folder: Path, key: str) -> None:
    """Make sure ``folder`` exists (creating it) and a file can be written in it; the
    message names the config key that chose it."""
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise UserError(f"{key}: {folder} is a file, not a folder; choose another path.") from None
    except OSError as e:
        raise UserError(f"{key}: cannot create the folder {folder} ({e.strerror or e}); "
                        "choose a path you can write to.") from None
    if not folder.is_dir():
        raise UserError(f"{key}: {folder} is not a folder; choose another path.")
    probe = folder / f".fluxmap-write-test.{os.getpid()}"
    try:
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise UserError(f"{key}: cannot write in {folder} ({e.strerror or e}); choose a folder you can "
                        "write to, or fix its permissions.") from None


def check_folders(cfg: LoadedConfig, *, cache: bool = True) -> None:
    """The workdir (and the T cache) must be writable before a stage computes anything."""
    check_writable(cfg.workdir, "workdir")
    A.clean_stale_temps(cfg.workdir)
    if cache:
        check_writable(cache_dir(cfg), "transfer.cache_dir" if cfg.model.transfer.cache_dir else "workdir")


# ------------------------------------------------------------------ sizes, before allocating
def available_memory_bytes() -> int:
    """Memory the OS says can be allocated now (MemAvailable), else the physical memory."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return 1 << 62


def _gb(n: float) -> str:
    return f"{n / 1e9:.3g} GB" if n >= 1e8 else f"{n / 1e6:.3g} MB"


def check_memory(need_bytes: float, what: str, keys: str) -> None:
    """Refuse work whose estimated memory exceeds what is available, naming the keys to change."""
    avail = available_memory_bytes()
    if need_bytes > 0.8 * avail:
        raise UserError(f"{what} would need about {_gb(need_bytes)} of memory; {_gb(avail)} is available. "
                        f"Reduce {keys}.")


SAMPLE_BYTES = 600.0  # per surface sample point: position, normal, weights, edges, lens disk, masks and copies


def transfer_bytes(n_pixels: int, n_views: int, n_elements: int) -> float:
    """Rough peak memory of building one pose's T: CSR row pointers per view and combined,
    the pending COO pieces, and per-element sampling arrays."""
    return 8.0 * n_pixels * (2 * n_views + 4) + 2000.0 * n_elements


# ------------------------------------------------------------------ provenance
def geometry_of(cfg: LoadedConfig, surface_sha256: str | None = None) -> dict:
    """The set-up an artefact is made for: system (camera, lens, sensor, apertures, mirrors,
    stage), subject (surface, poses, rotation axis) and the digest of the built surface."""
    m = cfg.model
    g = {"system": m.system.model_dump(mode="json") if m.system is not None else None,
         "subject": m.subject.model_dump(mode="json") if m.subject is not None else None}
    if g["system"] is not None:  # a calibration's 1 sd is not the set-up (reconstruct's error budget reads it)
        g["system"]["camera"].pop("uncertainty", None)
        for mirror in g["system"].get("mirrors") or ():
            mirror.pop("normal_sigma_deg", None)
            mirror.pop("offset_sigma_mm", None)
    if g["subject"] is not None:  # Lambertian (absent or explicit): the digest of before emission profiles
        em = g["subject"].pop("emission", None)
        if em is not None and em.get("model") != "lambertian":
            from .config import emission_profile

            g["subject"]["emission"] = emission_profile(cfg).key()  # a table by its numbers, not its path
    if surface_sha256 is not None:
        g["surface_sha256"] = surface_sha256
    return g


def without_emission(geometry: dict) -> dict:
    """The geometry with no emission model: what a Monte Carlo simulation is made for (its photons
    assume none, so its images serve a reconstruction under any ``subject.emission``)."""
    g = dict(geometry)
    if g.get("subject") is not None:
        g["subject"] = {k: v for k, v in g["subject"].items() if k != "emission"}
    return g


def provenance(cfg: LoadedConfig, surface_sha256: str | None = None) -> A.Provenance:
    return A.Provenance(config=cfg.model.model_dump(mode="json", by_alias=True),
                        geometry=geometry_of(cfg, surface_sha256))


EMISSION_NOTICE = ("subject.emission is not set: the surface is taken as Lambertian. Light leaving tissue or a turbid "
                   "phantom is better described by subject.emission: {model: diffuse, refractive_index: 1.40} (read as "
                   "Lambertian it is ~11 % too bright head-on and ~37 % too dim at 80 deg from the normal; "
                   "docs/design.md, Emission).")


def emission_notice(cfg: LoadedConfig, ctx) -> None:
    """One short notice per run when ``subject.emission`` is absent (Lambertian is assumed)."""
    if cfg.model.subject is None or cfg.model.subject.emission is not None or EMISSION_NOTICE in ctx.warned:
        return
    ctx.warned.add(EMISSION_NOTICE)
    ctx.say(EMISSION_NOTICE)


def announce(ctx, placer: SubjectPlacer) -> None:
    """Say what a mesh file yielded, and warn about what was repaired in it (once per run)."""
    for k, note in enumerate(placer.notes):
        if k == 0:
            if note not in ctx.warned:
                ctx.warned.add(note)
                ctx.say(note)
        else:
            ctx.warn(note)


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
    } | ({"emission": scene.emission.key()} if scene.emission is not None and not scene.emission.is_lambertian
         else {}))  # Lambertian: no entry, so that its keys are those made before emission profiles


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
            scene = PlacedScene(scene.pose, scene.surface.unknowns()[0], scene.occluders, scene.emission)
        elif unknowns.startswith("refined:"):  # simulate: columns per face of the refined surface
            levels = int(unknowns.split(":")[1])
            if levels > 0:
                scene = PlacedScene(scene.pose, scene.surface.refined(levels)[0], scene.occluders, scene.emission)
        key = A.cache_key(key_parts(scene, views, tr))
        out.append((scene, PoseT(pose, key, AT.entry_path(cdir, key))))
    return views, placer, out


# a view of a pose with more rays than this keeps its finished blocks of this many rays as
# partial files beside the T cache entry, so that an interrupted build resumes within the pose
CHECKPOINT_RAYS = 20_000_000


class PartialFiles(Checkpoint):
    """Finished blocks of one pose's build as atomic ``.npz`` files in ``<cache>/<key>.part/``;
    read back by the next run of the same pose (same key: same inputs, same blocks) and
    removed when the pose's T file is written."""

    def __init__(self, cache: Path, key: str, rays_per_block: int | None = None, plans: dict | None = None):
        self.folder = Path(cache) / f"{key}.part"
        self.rays_per_block = CHECKPOINT_RAYS if rays_per_block is None else rays_per_block
        self.plans = plans or {}  # view -> its lens plan, when made beforehand (a cluster's merge)

    def plan(self, view: int):
        return self.plans.get(view)

    def _path(self, view: int, spans: list[tuple[int, int]]) -> Path:
        return self.folder / f"view{view}-samples{spans[0][0]}-{spans[-1][1]}-chunks{len(spans)}.npz"

    def load(self, view: int, spans: list[tuple[int, int]]):
        path = self._path(view, spans)
        if not path.is_file():
            return None
        try:
            with np.load(path) as z:
                if not np.array_equal(z["spans"], np.asarray(spans, np.int64).reshape(-1, 2)):
                    return None  # made with another chunking (transfer.rays_per_batch): cast again
                n = len(spans)
                el_off, nz_off = z["el_off"], z["nz_off"]
                tval = z["tval"] if "tval" in z.files else np.zeros((0, 2))
                return [(z["elements"][el_off[i]:el_off[i + 1]], z["starts"][el_off[i] + i:el_off[i + 1] + i + 1],
                         z["pix"][nz_off[i]:nz_off[i + 1]], z["val"][nz_off[i]:nz_off[i + 1]],
                         z["err"][el_off[i]:el_off[i + 1]], int(z["cast"][i]), int(z["rays"][i]), 0,
                         tval[nz_off[i]:nz_off[i + 1]] if len(tval) else tval) for i in range(n)]
        except (OSError, ValueError, KeyError):
            return None  # a damaged partial file is recomputed

    def save(self, view: int, spans: list[tuple[int, int]], results: list) -> None:
        from .artefacts.atomic import atomic_path

        self.folder.mkdir(parents=True, exist_ok=True)
        el_off = np.concatenate([[0], np.cumsum([len(r[0]) for r in results])])
        nz_off = np.concatenate([[0], np.cumsum([len(r[2]) for r in results])])
        with atomic_path(self._path(view, spans)) as tmp:
            with open(tmp, "wb") as fh:
                _write_npz(fh, elements=np.concatenate([r[0] for r in results]),
                           starts=np.concatenate([r[1] for r in results]), pix=np.concatenate([r[2] for r in results]),
                           val=np.concatenate([r[3] for r in results]), err=np.concatenate([r[4] for r in results]),
                           cast=np.array([r[5] for r in results]), rays=np.array([r[6] for r in results]),
                           tval=np.concatenate([r[8] for r in results]),
                           el_off=el_off, nz_off=nz_off, spans=np.asarray(spans, np.int64).reshape(-1, 2))

    def save_scene(self, scene: PlacedScene) -> Path:
        """The pose's scene, pickled beside its blocks (atomic): what a cluster's block tasks
        read it from (a path in their graph, not the arrays); removed with the blocks."""
        import pickle

        from .artefacts.atomic import atomic_path

        self.folder.mkdir(parents=True, exist_ok=True)
        path = self.folder / "scene.pickle"
        with atomic_path(path) as tmp:
            Path(tmp).write_bytes(pickle.dumps(scene, protocol=pickle.HIGHEST_PROTOCOL))
        return path

    def remove(self) -> None:
        import shutil

        shutil.rmtree(self.folder, ignore_errors=True)


def _write_npz(fh, **arrays: np.ndarray) -> None:
    """``np.savez`` with fixed member times: the same arrays make the same bytes (a retried or
    duplicated cluster task rewrites its partial file identically)."""
    import zipfile

    with zipfile.ZipFile(fh, "w", zipfile.ZIP_STORED, allowZip64=True) as z:
        for name, a in arrays.items():
            with z.open(zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0)), "w", force_zip64=True) as f:
                np.lib.format.write_array(f, np.asanyarray(a), allow_pickle=False)


def _build_and_store(scene: PlacedScene, views: list[View], tr: Transfer, target: Path, config_sha: str,
                     prov: A.Provenance | None = None, threads: int | None = None, progress=None,
                     rays_per_block: int | None = None, plans: dict | None = None) -> dict:
    """Worker: compute T for one pose and write it atomically; returns a summary.
    ``progress`` gets the fraction done after every chunk of rays; ``threads`` cast rays
    within the pose (the bytes do not depend on it); ``rays_per_block``: the size of the
    partial files' blocks (default :data:`CHECKPOINT_RAYS`; the bytes do not depend on it);
    ``plans``: view -> lens plan already made for these inputs (not made again)."""
    t0, c0 = time.perf_counter(), time.process_time()
    partial = PartialFiles(Path(target).parent, Path(target).stem, rays_per_block, plans)
    res = build_transfer(
        scene.surface, views, scene.occluders, estimator=tr.estimator,
        lens_sampling=LensSampling(**tr.lens.model_dump()),
        pairwise_sampling=PairwiseSampling(**tr.pairwise.model_dump()),
        ray_offset_mm=tr.ray_offset_mm, rays_per_batch=tr.rays_per_batch, progress=progress,
        threads=threads, checkpoint=partial, emission=scene.emission,
    )
    seconds = time.perf_counter() - t0
    cam = res.views[0].camera
    AT.write_T(target, T=res.T, T_per_view=res.T_per_view,
               view_kinds=["direct" if v.mirror is None else "mirror" for v in res.views],
               weights=[v.weight for v in res.views], stats=[res.stats[v.name] for v in res.views],
               pixels=(cam.nx, cam.ny), surface=scene.surface, occluders=scene.occluders,
               height_mm=scene.pose.height_mm, rotation_deg=scene.pose.rotation_deg, estimator=tr.estimator,
               seconds=seconds, config_sha256=config_sha, provenance=prov, column_error=res.column_error,
               column_error_per_view=res.column_error_per_view, T_tangent=res.T_tangent)
    partial.remove()
    return summarise(res, scene) | {"seconds": seconds, "cpu_seconds": time.process_time() - c0, "pid": os.getpid()}


# ------------------------------------------------------------------ T chunks on a Dask cluster
# With fewer poses to build than worker threads, each pose's lens build is split into blocks
# of whole-element chunks (the blocks of the within-pose checkpoint), one task each, written as
# partial files beside the T cache entry; this process then merges them into the T file the
# way an interrupted local build resumes (same bytes).
CLUSTER_TASKS_PER_THREAD = 4  # blocks per worker thread: uneven blocks and workers still balance (0: never split)
CLUSTER_MIN_BLOCK_RAYS = 2_000_000  # below this a block costs more to schedule than to cast
WORKER_SCENES_KEPT = 2  # poses whose Embree scene and lens plans a worker process keeps

_worker_scenes: collections.OrderedDict = collections.OrderedDict()  # in a worker: file -> (scene, Embree, plans)
_worker_lock = threading.Lock()


def _worker_scene(scene_file: Path, views: list[View], tr: Transfer, view: int):
    """This process's Embree scene of a pose and the lens plan of one of its views, made once
    per process from the pose's pickled scene (its other blocks on this worker reuse them)."""
    import pickle

    key = str(scene_file)
    with _worker_lock:
        entry = _worker_scenes.get(key)
        if entry is None:
            try:
                scene = pickle.loads(Path(scene_file).read_bytes())
            except FileNotFoundError:
                raise UserError(f"transfer.cache_dir: a Dask worker does not see {scene_file}, which this machine "
                                "wrote: with --scheduler the T cache and the workdir must be a folder every worker "
                                "and this machine share under the same path.") from None
            occ = OcclusionScene(*merge(scene.surface, *scene.occluders))
            occ.native  # noqa: B018 - the Embree scene, built once here and not by two threads
            entry = _worker_scenes[key] = (scene, occ, {})
            while len(_worker_scenes) > WORKER_SCENES_KEPT:
                _worker_scenes.popitem(last=False)
        _worker_scenes.move_to_end(key)
        scene, occ, plans = entry
        if (view, tr.rays_per_batch) not in plans:
            plans[view, tr.rays_per_batch] = lens_plan(scene.surface, views[view], LensSampling(**tr.lens.model_dump()),
                                                       tr.rays_per_batch, scene.occluders, tr.ray_offset_mm,
                                                       emission=scene.emission)
        return occ, plans[view, tr.rays_per_batch]


def _build_block(scene_file: Path, views: list[View], tr: Transfer, target: Path, view: int,
                 spans: list[tuple[int, int]], rays_per_block: int, progress=None) -> dict:
    """Worker: one block of one view of a pose's lens T, written atomically as its partial file
    beside the T cache entry ``target``; the pose's scene is read from ``scene_file``
    (:meth:`PartialFiles.save_scene`).  A block whose file is already there is not cast again,
    and a block cast twice makes the same bytes: a retried task is harmless."""
    c0 = time.process_time()
    partial = PartialFiles(Path(target).parent, Path(target).stem, rays_per_block)
    if partial.load(view, spans) is None:
        occ, plan = _worker_scene(scene_file, views, tr, view)
        partial.save(view, spans, cast_lens_block(views[view], occ, plan, tr.ray_offset_mm, spans, progress))
    return {"view": view, "cpu_seconds": time.process_time() - c0, "pid": os.getpid()}


def _plan_view(scene_file: Path, views: list[View], tr: Transfer, view: int, progress=None):
    """Worker: one view's lens plan, kept for the blocks this worker will cast; its chunks and
    their rays (:func:`fluxcli.optics.transfer.lens_chunks`), for this process to cut blocks,
    and the CPU seconds it took."""
    c0 = time.process_time()
    chunks, rays = lens_chunks(_worker_scene(scene_file, views, tr, view)[1])
    return chunks, rays, {"cpu_seconds": time.process_time() - c0, "pid": os.getpid()}


def _call(fn, *args, progress=None):
    return fn(*args, progress=progress)


def _build_on_cluster(client, need: list, views: list[View], tr: Transfer, config_sha: str,
                      prov: A.Provenance, label: str, quiet: bool) -> list[dict]:
    """Build the poses ``need`` [(scene, PoseT)] on the Dask cluster behind ``client``; their
    summaries.  Every task casts on one thread (a worker thread is a core: ``dask worker
    --nthreads``).  A pose goes whole to one task; or, when the poses are fewer than the worker
    threads (lens estimator), the workers plan its views (one task each), this process cuts
    the views into blocks, one task each, and merges their partial files into the T file.
    A split pose's scene reaches the workers as a file beside its blocks, not in the graph."""
    from .cluster import worker_threads

    threads = worker_threads(client)
    split = tr.estimator == "lens" and len(need) < threads and CLUSTER_TASKS_PER_THREAD > 0
    per_pose = -(-CLUSTER_TASKS_PER_THREAD * threads // max(len(need), 1))
    pool = pool_for(client)
    planned: list = []
    if split:
        files = [PartialFiles(p.path.parent, p.path.stem).save_scene(s) for s, p in need]
        planned = run_tasks(_call, [(_plan_view, f, views, tr, k) for f in files for k in range(len(views))],
                            label=f"{label} (planning blocks)", quiet=quiet, remote=True, pool=pool)
    tasks, cut = [], []
    for i, (s, p) in enumerate(need):
        blocks, rays_per_block = [], None
        if split:
            per_view = planned[i * len(views):(i + 1) * len(views)]
            rays = sum(sum(r) for _, r, _ in per_view)
            rays_per_block = min(CHECKPOINT_RAYS, max(CLUSTER_MIN_BLOCK_RAYS, -(-rays // per_pose)))
            blocks = [(k, spans) for k, (c, r, _) in enumerate(per_view) for spans in lens_blocks(c, r, rays_per_block)]
        if len(blocks) > 1:
            scene_file = PartialFiles(p.path.parent, p.path.stem).folder / "scene.pickle"
            tasks += [(_build_block, scene_file, views, tr, p.path, k, spans, rays_per_block) for k, spans in blocks]
            cut.append((rays_per_block, blocks))
        else:
            tasks.append((_build_and_store, s, views, tr, p.path, config_sha, prov, 1))  # a task: one thread
            cut.append(None)
    # while the cluster casts, this process (idle otherwise) makes the plans the first merge
    # needs (one pose's: memory); the other merges make their own
    merging = [i for i, c in enumerate(cut) if c is not None]
    ahead = ThreadPoolExecutor(1)
    plans = {i: ahead.submit(_plans_of, need[i][0].surface, views, tr, need[i][0].emission) for i in merging[:1]}
    try:
        done = run_tasks(_call, tasks, label=label, quiet=quiet, remote=True, pool=pool)
        whole = iter(r for r, t in zip(done, tasks) if t[0] is _build_and_store)
        merges = []
        for i in merging:
            (s, p), (rays_per_block, blocks) = need[i], cut[i]
            partial = PartialFiles(p.path.parent, p.path.stem, rays_per_block)
            missing = [partial._path(k, spans) for k, spans in blocks if not partial._path(k, spans).is_file()]
            if missing:
                check_shared(p.path.parent, missing)
            merges.append((s, views, tr, p.path, config_sha, prov, None, rays_per_block,
                           plans[i].result() if i in plans else None))
    finally:  # on Ctrl-C the plans not begun are dropped (one being made ends in a second or so)
        ahead.shutdown(wait=False, cancel_futures=True)
    merged = iter(run_tasks(_merge, merges, label="merging T blocks", quiet=quiet))
    return [next(whole) if c is None else next(merged) for c in cut]


def _plans_of(surface, views: list[View], tr: Transfer, emission=None) -> dict:
    sampling = LensSampling(**tr.lens.model_dump())
    return {k: lens_plan(surface, v, sampling, tr.rays_per_batch, emission=emission) for k, v in enumerate(views)}


def _merge(*args, progress=None) -> dict:
    """This process: a pose's T from the partial files its blocks left (as a resumed build)."""
    *head, rays_per_block, plans = args
    return _build_and_store(*head, progress=progress, rays_per_block=rays_per_block, plans=plans)


def summarise(res, scene: PlacedScene) -> dict:
    """Collection efficiency per view: the fraction of the power of a uniformly glowing
    surface that the view delivers to the sensor (area-weighted mean column sum)."""
    areas = scene.surface.element_areas_mm2
    eff = {view.name: AT.efficiency(Tv, view.weight, areas) for view, Tv in zip(res.views, res.T_per_view)}
    seen = {view.name: AT.seen_fraction(Tv, areas) for view, Tv in zip(res.views, res.T_per_view)}
    return {"nnz": int(res.T.nnz), "efficiency": eff, "seen": seen}


def ensure_T(cfg: LoadedConfig, ctx, transfer: Transfer | None = None, label: str = "building T",
             unknowns: str = "elements"):
    """Build every pose's T that the cache lacks (all with ``ctx.force``); a cache entry
    that cannot be read is rebuilt with a warning.

    Returns views, placer, [(scene, PoseT)], and per key a summary dict (cached, seconds,
    nnz, efficiency per view)."""
    tr = transfer or cfg.model.transfer
    views, placer, todo = plan(cfg, tr, unknowns)
    announce(ctx, placer)
    emission_notice(cfg, ctx)
    A.clean_stale_temps(cache_dir(cfg))  # what killed runs left, even when nothing is rebuilt
    nx, ny = cfg.model.system.camera.pixels
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
    prov = provenance(cfg, placer.surface.digest())
    compiling = bool(need) and not _numba_cache.kernels_compiled()
    if compiling:  # the first build after an install: say why it waits
        ctx.say(_numba_cache.COMPILING)
    cluster = getattr(ctx, "client", None)  # --scheduler: a Dask cluster builds the poses
    # one bar over the poses, advanced after every batch of rays in every worker (with an ETA)
    # processes x threads <= cores locally; on a cluster one thread per task (a worker thread is a core)
    if cluster is not None:
        built = _build_on_cluster(cluster, need, views, tr, cfg.sha256, prov, label, ctx.quiet)
        check_shared(cache_dir(cfg), [p.path for _, p in need])
    else:
        threads = max(1, default_threads() // max(1, min(ctx.jobs, len(need))))
        tasks = [(s, views, tr, p.path, cfg.sha256, prov, threads) for s, p in need]
        built = []
        if compiling and ctx.jobs > 1 and len(tasks) > 1:  # compile once, here; the workers then load the cache
            built = run_tasks(_build_and_store, tasks[:1], label=f"{label} (compiling)", jobs=1, quiet=ctx.quiet)
        built += run_tasks(_build_and_store, tasks[len(built):], label=label, jobs=ctx.jobs, quiet=ctx.quiet,
                           pool=pool_for(None, temp_dirs=(cache_dir(cfg),)))
    results |= {p.key: r | {"cached": False} for (_, p), r in zip(need, built)}
    check_collection(todo, results, names, ctx)
    return views, placer, todo, results


def check_shared(folder: Path, written: list[Path]) -> None:
    """After a cluster built files: each must be visible here (the workers wrote them under
    the same absolute path, so the folder must be shared by every worker and this machine)."""
    missing = [p for p in written if not Path(p).is_file()]
    if missing:
        raise UserError(f"transfer.cache_dir: the Dask workers wrote {len(missing)} T file(s) such as {missing[0]}, "
                        f"which this machine does not see: with --scheduler the T cache ({folder}) and the workdir "
                        "must be a folder every worker and this machine share under the same path.")


def ensure_pose_T(cfg: LoadedConfig, pose: Pose, transfer: Transfer | None = None,
                  placer: SubjectPlacer | None = None, refine: int = 0, tangent: bool = False):
    """T (CSR) of one pose that need not be in ``subject.poses`` (the simulated rig renders
    at the stage's physical height), from the T cache or built and cached; with ``refine``
    its columns are the faces of the surface refined that often (Surface.refined); with
    ``tangent`` also its tangential-flux matrix (None without one): (T, T_tangent)."""
    tr = transfer or cfg.model.transfer
    views = views_from_config(cfg.model.system)
    scene = (placer or SubjectPlacer(cfg)).scene(pose, cfg.model.system)
    if refine > 0:
        scene = PlacedScene(scene.pose, scene.surface.refined(refine)[0], scene.occluders, scene.emission)
    path = AT.entry_path(cache_dir(cfg), A.cache_key(key_parts(scene, views, tr)))
    if not path.is_file():
        _build_and_store(scene, views, tr, path, cfg.sha256, provenance(cfg))
    if tangent:
        return AT.load_T(path), AT.load_T_tangent(path)
    return AT.load_T(path)


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


# ------------------------------------------------------------------ the surface artefact
_DECODE_UNITS = {"phase": "rad", "column_px": "projector px"}

def decode_datasets(scans, projector_names: list[str], view_names: list[str], camera, mirrors) -> dict:
    """``{(view, projector): {"phase", "column_px", "mask"}}`` for :func:`write_surface_artefact`: each
    projector's decoding (:class:`fluxcli.structured.scan.ScanPoints`) split by the view each camera pixel
    looks through (its chief ray: direct, or reflected in a mirror); mask 1 where a point was triangulated."""
    from .structured.triangulate import chief_rays

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


def write_surface_artefact(path: Path, surface, *, points=None, decode: dict | None = None,
                           distance_to_truth_mm: np.ndarray | None = None, config_sha256: str = "",
                           inputs: dict[str, str] | None = None, provenance: "A.Provenance | None" = None,
                           attrs: dict | None = None, truth=None, metrics: dict | None = None) -> Path:
    """Write ``surface`` (a :class:`~fluxcli.surface.mesh.Surface`) atomically as a ``surface``
    artefact, which ``subject.surface: {artefact: PATH}`` reads.

    ``points``: the merged points it was built from (:class:`fluxcli.structured.scan.MergedPoints`);
    ``decode``: ``{(view, projector): {"phase": rad [ny, nx], "column_px": [ny, nx], "mask": bool
    [ny, nx]}}`` written under ``/decode/<view>/<projector>/``; ``distance_to_truth_mm``: each
    point's distance to the true surface (simulated rig only); ``attrs``: root attributes; ``truth``:
    the true surface (simulated rig; ``/truth``, what the report draws the capture over); ``metrics``:
    :func:`fluxcli.structured.mesh.capture_metrics` (``/metrics`` attributes)."""
    with A.write_artefact(Path(path), "surface", config_sha256=config_sha256, inputs=inputs,
                          provenance=provenance) as f:
        for key, value in (attrs or {}).items():
            f.attrs[key] = value
        A.write_surface(f.create_group("surface"), surface)
        if points is not None:
            g = f.create_group("points")
            A.put(g, "positions_mm", points.points_mm)
            A.put(g, "view", points.view.astype(np.int16))
            A.put(g, "projector", points.projector.astype(np.int16))
            if distance_to_truth_mm is not None:
                A.put(g, "distance_to_truth_mm", np.asarray(distance_to_truth_mm, float))
            if decode:  # the name of each value of points/view, in order
                g.attrs["view_names"] = list(dict.fromkeys(view for view, _ in decode))
        if truth is not None:
            A.write_surface(f.create_group("truth"), truth)
        if metrics:
            g = f.create_group("metrics")
            for key, value in metrics.items():
                g.attrs[key] = value
        for (view, proj), arrays in (decode or {}).items():
            g = f.require_group(f"decode/{view}/{proj}")
            for name, data in arrays.items():
                A.put(g, name, np.asarray(data), compression="gzip").attrs["unit"] = _DECODE_UNITS.get(name, "")
    return Path(path)
