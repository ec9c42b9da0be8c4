"""``fluxmap build-T CONFIG``: one transfer matrix per pose, cached by content.

Examples
--------
$ fluxmap build-T configs/demo.yaml
$ fluxmap build-T configs/paper-3d.yaml --jobs 2
$ fluxmap build-T configs/paper-2d.yaml --set transfer.estimator=pairwise
"""

from __future__ import annotations

from pathlib import Path

from ..artefacts import transfer as AT
from ..artefacts.transfer import load_T, read_summary  # noqa: F401  (public names of this stage's output)
from ..config import LoadedConfig
from ..transfer_cache import PoseT, TransferPlan, ensure, key_parts, summarise  # noqa: F401
from .context import RunContext
from .plans import cache_dir, check_folders, plan, provenance  # noqa: F401  (as before: importable from here)
from .plans import transfer_plan


def run(cfg: LoadedConfig, ctx: RunContext) -> Path:
    check_folders(cfg)
    tp = transfer_plan(cfg)  # validates the geometry before anything is printed
    index = cfg.workdir / AT.INDEX_FILE_NAME
    surf = tp.placer.surface
    faces = (f" on {len(surf.faces)} faces (subject.refine_faces: {cfg.model.subject.refine_faces})"
             if cfg.model.subject.refine_faces else "")
    ctx.say(f"build-T: {len(tp.poses)} pose(s), {surf.n_elements} elements{faces}, views "
            f"{', '.join(v.name for v in tp.views)}, estimator {tp.transfer.estimator}, cache {tp.cache_dir}")
    results = ensure(tp, ctx)
    write_index(index, tp, results, ctx)
    return index


def write_index(index: Path, tp: TransferPlan, results: dict[str, dict], ctx: RunContext) -> None:
    """Print each pose's build and efficiency per view, and write the transfer index."""
    names = [v.name for v in tp.views]
    rows = []
    for s, p in tp.poses:
        r = results[p.key]
        rows.append([p.pose.height_mm, p.pose.rotation_deg, "cache hit" if r["cached"] else f"{r['seconds']:.1f} s",
                     r["nnz"], *[r["efficiency"][n] for n in names]])
    ctx.table(["height_mm", "rotation_deg", "build", "nnz", *[f"eff {n}" for n in names]], rows)
    AT.write_index(index, heights_mm=[p.pose.height_mm for _, p in tp.poses],
                   rotations_deg=[p.pose.rotation_deg for _, p in tp.poses], keys=[p.key for _, p in tp.poses],
                   paths=[p.path for _, p in tp.poses],
                   efficiency_pv=[[results[p.key]["efficiency"][n] for n in names] for _, p in tp.poses],
                   view_names=names, estimator=tp.transfer.estimator, config_sha256=tp.config_sha256,
                   provenance=tp.provenance)
    ctx.say(f"index written to {index}")
