"""Is the fitted image shifted against the measured one?  The shift test of each pose's fit
(:func:`fluxcli.quantify.budget.image_shift`): a camera pose a calibration error away shows
as a residual that a sub-pixel shift of the model explains."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..quantify import budget as Q


def shifts(per_pose, images, valid, noise) -> list:
    """The shift test on each pose's fit (``per_pose``: [(Result, fitted image)]; ``images``,
    ``valid``: [pose, ny, nx] measured photons and the pixels used; the noise model's variance)."""
    out = []
    for k, (r, fitted) in enumerate(per_pose):
        var = noise.variance(np.where(np.isfinite(fitted), np.maximum(fitted, 0.0), 0.0))
        out.append(Q.image_shift(images[k], fitted, valid[k], var))
    return out


def with_shift_warnings(per_pose, shifts_: list, labels: list[str], angle_structured=None, explained=None):
    """Each pose's result with the shift warning added to its warnings (where the test fires);
    ``angle_structured``: per pose, whether its residual is also structured by viewing angle
    (the warning then points at the emission model first); ``explained``: per pose, whether its
    misfit is already explained (a peak sharper than the unknowns: :mod:`fluxcli.inverse.sharp_peak`),
    when no shift warning is added."""
    flags = list(angle_structured) if angle_structured is not None else [False] * len(per_pose)
    done = list(explained) if explained is not None else [False] * len(per_pose)
    out = []
    for (r, fitted), s, lab, by_angle, known in zip(per_pose, shifts_, labels, flags, done):
        w = None if known else Q.shift_warning(lab, s, r.chi2_per_pixel, bool(by_angle))
        out.append((replace(r, warnings=tuple(r.warnings) + (w,)) if w else r, fitted))
    return out
