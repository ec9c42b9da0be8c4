"""The poses of a build on a Dask cluster: whole poses as tasks, or, with fewer poses than
worker threads, each pose's lens build cut into blocks of whole-element chunks (the blocks of
the within-pose checkpoint), one task each, written as partial files beside the T-cache entry;
this process then merges them into the T file the way an interrupted local build resumes
(same bytes).
"""

from __future__ import annotations

import collections
import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from .. import artefacts as A
from ..config import Transfer
from ..errors import UserError
from ..optics.raycast import OcclusionScene
from ..optics.transfer import LensSampling, View, cast_lens_block, lens_blocks, lens_chunks, lens_plan
from ..progress import run_tasks
from ..surface.mesh import merge
from ..workers import pool_for
from . import build
from .build import PartialFiles, build_and_store

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


def build_on_cluster(client, need: list, views: list[View], tr: Transfer, config_sha: str,
                      prov: A.Provenance, label: str, quiet: bool) -> list[dict]:
    """Build the poses ``need`` [(scene, PoseT)] on the Dask cluster behind ``client``; their
    summaries.  Every task casts on one thread (a worker thread is a core: ``dask worker
    --nthreads``).  A pose goes whole to one task; or, when the poses are fewer than the worker
    threads (lens estimator), the workers plan its views (one task each), this process cuts
    the views into blocks, one task each, and merges their partial files into the T file.
    A split pose's scene reaches the workers as a file beside its blocks, not in the graph."""
    from ..cluster import worker_threads

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
            rays_per_block = min(build.CHECKPOINT_RAYS, max(CLUSTER_MIN_BLOCK_RAYS, -(-rays // per_pose)))
            blocks = [(k, spans) for k, (c, r, _) in enumerate(per_view) for spans in lens_blocks(c, r, rays_per_block)]
        if len(blocks) > 1:
            scene_file = PartialFiles(p.path.parent, p.path.stem).folder / "scene.pickle"
            tasks += [(_build_block, scene_file, views, tr, p.path, k, spans, rays_per_block) for k, spans in blocks]
            cut.append((rays_per_block, blocks))
        else:
            tasks.append((build_and_store, s, views, tr, p.path, config_sha, prov, 1))  # a task: one thread
            cut.append(None)
    # while the cluster casts, this process (idle otherwise) makes the plans the first merge
    # needs (one pose's: memory); the other merges make their own
    merging = [i for i, c in enumerate(cut) if c is not None]
    ahead = ThreadPoolExecutor(1)
    plans = {i: ahead.submit(_plans_of, need[i][0].surface, views, tr, need[i][0].emission) for i in merging[:1]}
    try:
        done = run_tasks(_call, tasks, label=label, quiet=quiet, remote=True, pool=pool)
        whole = iter(r for r, t in zip(done, tasks) if t[0] is build_and_store)
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
    return build_and_store(*head, progress=progress, rays_per_block=rays_per_block, plans=plans)



def check_shared(folder: Path, written: list[Path]) -> None:
    """After a cluster built files: each must be visible here (the workers wrote them under
    the same absolute path, so the folder must be shared by every worker and this machine)."""
    missing = [p for p in written if not Path(p).is_file()]
    if missing:
        raise UserError(f"transfer.cache_dir: the Dask workers wrote {len(missing)} T file(s) such as {missing[0]}, "
                        f"which this machine does not see: with --scheduler the T cache ({folder}) and the workdir "
                        "must be a folder every worker and this machine share under the same path.")

