"""The emission model's domain in reconstruct (issue 21): elements whose light every view
collects only beyond the angle up to which the profile is known
(:attr:`fluxcli.optics.emission.Profile.trusted_to_deg`) are solved for but left out of the
observed total, per pose and jointly (:func:`fluxcli.inverse.diagnostics.leave_out_edge_on`); one call in reconstruct."""

from __future__ import annotations

import numpy as np

from ..artefacts.transfer import load_view
from . import diagnostics as D


def leave_out_edge_on(profile, views, todo, per_pose, joint):
    """``per_pose`` [(Result, fitted)] and ``joint`` (Result or None) with the edge-on
    elements unobserved; unchanged for a profile known to 90 deg (Lambertian, table)."""
    limit = profile.trusted_to_deg
    if limit >= 90.0:
        return per_pose, joint
    cameras = [v.camera for v in views]
    best_all = None
    out = []
    for (res, fitted), (scene, pt) in zip(per_pose, todo):
        best = D.best_view_deg(scene.surface, cameras, [load_view(pt.path, v) for v in range(len(views))])
        best_all = best if best_all is None else np.minimum(best_all, best)
        out.append((D.leave_out_edge_on(res, best, limit, profile.describe()), fitted))
    if joint is not None and best_all is not None:
        joint = D.leave_out_edge_on(joint, best_all, limit, profile.describe())
    return out, joint
