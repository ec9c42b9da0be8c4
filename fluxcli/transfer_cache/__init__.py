"""The T cache: one transfer matrix per placed pose, built once and kept under the content
address of everything it depends on.

- :mod:`.service`: what a stage asks for (:class:`TransferPlan`, :func:`ensure`, :func:`pose_T`),
  the cache keys and the checks of what was built;
- :mod:`.build`: one pose's T built and written, and the partial files a build resumes from;
- :mod:`.cluster`: the poses (or blocks of one pose) built on a Dask cluster.

The files themselves (T entries, the index) are :mod:`fluxcli.artefacts.transfer`.
"""

from .build import CHECKPOINT_RAYS, SAMPLE_BYTES, PartialFiles, build_and_store, summarise, transfer_bytes
from .cluster import build_on_cluster, check_shared
from .service import (EMISSION_NOTICE, SEEN_FRACTION, WEAK_VIEW_FRACTION, PoseT, TransferPlan, TransferSource, announce,
                      check_collection, curvature_ratios, emission_notice, ensure, key_parts, place,
                      pose_entry, pose_T, with_columns)

__all__ = [
    "CHECKPOINT_RAYS", "EMISSION_NOTICE", "SAMPLE_BYTES", "SEEN_FRACTION", "WEAK_VIEW_FRACTION", "PartialFiles",
    "PoseT", "TransferPlan", "TransferSource", "announce", "build_and_store", "build_on_cluster", "check_collection",
    "check_shared", "curvature_ratios", "emission_notice", "ensure", "key_parts", "place", "pose_entry", "pose_T",
    "summarise", "transfer_bytes", "with_columns",
]
