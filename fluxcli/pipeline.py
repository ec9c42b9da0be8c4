"""Former home of what several stages share; every name here now lives where it belongs:

- the T cache (plans, keys, builds, cluster blocks, checks): :mod:`fluxcli.transfer_cache`;
- the config-taking calls stages make (T plan, provenance, folders, sensor model):
  :mod:`fluxcli.stages.plans`;
- folder and memory checks: :mod:`fluxcli.resources`;
- the set-up an artefact records: :mod:`fluxcli.artefacts.provenance`;
- the surface artefact: :mod:`fluxcli.artefacts.surface`; the decoding per view:
  :func:`fluxcli.structured.scan.decode_by_view`.

Kept as re-exports while other branches still import them from here; import from the
modules above in new code.
"""

from __future__ import annotations

from .artefacts.provenance import without_emission
from .artefacts.surface import DECODE_UNITS as _DECODE_UNITS
from .artefacts.surface import write_surface_artefact
from .resources import _gb, available_memory_bytes, check_memory, check_writable
from .stages.plans import (cache_dir, check_folders, emccd_model, ensure_pose_T, ensure_T, geometry_of, plan,
                           provenance, transfer_plan)
from .structured.scan import decode_by_view as decode_datasets
from .transfer_cache import (CHECKPOINT_RAYS, EMISSION_NOTICE, SAMPLE_BYTES, SEEN_FRACTION, WEAK_VIEW_FRACTION,
                             PartialFiles, PoseT, TransferPlan, announce, check_collection, check_shared,
                             emission_notice, key_parts, summarise, transfer_bytes)
from .transfer_cache.build import _write_npz
from .transfer_cache.build import build_and_store as _build_and_store
from .transfer_cache.cluster import (CLUSTER_MIN_BLOCK_RAYS, CLUSTER_TASKS_PER_THREAD, WORKER_SCENES_KEPT, _build_block,
                                     _call, _merge, _plan_view, _plans_of, _worker_lock, _worker_scene, _worker_scenes)
from .transfer_cache.cluster import build_on_cluster as _build_on_cluster

__all__ = [
    "CHECKPOINT_RAYS", "CLUSTER_MIN_BLOCK_RAYS", "CLUSTER_TASKS_PER_THREAD", "EMISSION_NOTICE", "SAMPLE_BYTES",
    "SEEN_FRACTION", "WEAK_VIEW_FRACTION", "WORKER_SCENES_KEPT", "PartialFiles", "PoseT", "TransferPlan", "_DECODE_UNITS",
    "_build_and_store", "_build_block", "_build_on_cluster", "_call", "_gb", "_merge", "_plan_view", "_plans_of",
    "_worker_lock", "_worker_scene", "_worker_scenes", "_write_npz", "announce", "available_memory_bytes", "cache_dir",
    "check_collection", "check_folders", "check_memory", "check_shared", "check_writable", "decode_datasets",
    "emccd_model", "emission_notice", "ensure_T", "ensure_pose_T", "geometry_of", "key_parts", "plan", "provenance",
    "summarise", "transfer_bytes", "transfer_plan", "without_emission", "write_surface_artefact",
]
