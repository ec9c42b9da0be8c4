"""One pose's T built and written as a T-cache entry, and the partial files that let an
interrupted build resume within the pose (and a cluster's blocks merge into the same bytes).
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from .. import artefacts as A
from ..artefacts import transfer as AT
from ..config import Transfer
from ..optics.transfer import Checkpoint, LensSampling, PairwiseSampling, View, build_transfer
from ..scene import PlacedScene

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
        from ..artefacts.atomic import atomic_path

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

        from ..artefacts.atomic import atomic_path

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


def build_and_store(scene: PlacedScene, views: list[View], tr: Transfer, target: Path, config_sha: str,
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



def summarise(res, scene: PlacedScene) -> dict:
    """Collection efficiency per view: the fraction of the power of a uniformly glowing
    surface that the view delivers to the sensor (area-weighted mean column sum)."""
    areas = scene.surface.element_areas_mm2
    eff = {view.name: AT.efficiency(Tv, view.weight, areas) for view, Tv in zip(res.views, res.T_per_view)}
    seen = {view.name: AT.seen_fraction(Tv, areas) for view, Tv in zip(res.views, res.T_per_view)}
    return {"nnz": int(res.T.nnz), "efficiency": eff, "seen": seen}



SAMPLE_BYTES = 600.0  # per surface sample point: position, normal, weights, edges, lens disk, masks and copies


def transfer_bytes(n_pixels: int, n_views: int, n_elements: int) -> float:
    """Rough peak memory of building one pose's T: CSR row pointers per view and combined,
    the pending COO pieces, and per-element sampling arrays."""
    return 8.0 * n_pixels * (2 * n_views + 4) + 2000.0 * n_elements
