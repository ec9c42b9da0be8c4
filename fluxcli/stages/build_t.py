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
from ..pipeline import PoseT, check_folders, cache_dir, ensure_T, key_parts, plan, provenance, summarise  # noqa: F401
from .context import RunContext


def run(cfg: LoadedConfig, ctx: RunContext) -> Path:
    check_folders(cfg)
    views, placer, todo = plan(cfg)  # validates the geometry before anything is printed
    ctx.say(f"build-T: {len(todo)} pose(s), {placer.surface.n_elements} elements, views "
            f"{', '.join(v.name for v in views)}, estimator {cfg.model.transfer.estimator}, cache {cache_dir(cfg)}")
    views, placer, todo, results = ensure_T(cfg, ctx)
    names = [v.name for v in views]
    rows = []
    for s, p in todo:
        r = results[p.key]
        rows.append([p.pose.height_mm, p.pose.rotation_deg, "cache hit" if r["cached"] else f"{r['seconds']:.1f} s",
                     r["nnz"], *[r["efficiency"][n] for n in names]])
    ctx.table(["height_mm", "rotation_deg", "build", "nnz", *[f"eff {n}" for n in names]], rows)
    index = cfg.workdir / "transfer.h5"
    prov = provenance(cfg, placer.surface.digest())
    AT.write_index(index, heights_mm=[p.pose.height_mm for _, p in todo],
                   rotations_deg=[p.pose.rotation_deg for _, p in todo], keys=[p.key for _, p in todo],
                   paths=[p.path for _, p in todo],
                   efficiency_pv=[[results[p.key]["efficiency"][n] for n in names] for _, p in todo],
                   view_names=names, estimator=cfg.model.transfer.estimator, config_sha256=cfg.sha256,
                   provenance=prov)
    ctx.say(f"index written to {index}")
    return index
