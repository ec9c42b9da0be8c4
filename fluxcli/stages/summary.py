"""``fluxmap summary CONFIG``: the run in a few console lines, from its artefacts.

Examples
--------
$ fluxmap summary configs/demo.yaml

Per pose: the photons summed over the direct view's region of the image (the usual ROI
number), fluxmap's reconstructed total, and the share of the light that pose observes
(the joint reconstruction's power on the elements the pose sees); then the joint total,
the spread of each number over the poses, the truth when the images were simulated, and
where the report and the 3-D files are.  Rates (photons/s) when the exposure is known.
"""

from __future__ import annotations

import numpy as np

from ..artefacts import reconstruction as RA
from .. import config as C
from ..errors import UserError
from .context import RunContext
from ..report import spread
from ..report.notebook import observed_share
from .outputs import reconstruction_exposure_s, recorded_rate_exposure_s


def run(cfg: C.LoadedConfig, ctx: RunContext) -> None:
    rec = cfg.workdir / RA.FILENAME
    if not rec.is_file():
        raise UserError(f"summary: {rec} does not exist; run 'fluxmap reconstruct {cfg.path}' first.")
    r = RA.read_summary(rec)
    heights, rots, roi, totals = r.heights_mm, r.rotations_deg, r.direct_roi_photons, r.totals
    heads, why, pose_obs, power, joint = r.headline_total, r.headline_reason, r.pose_observed, r.power, r.joint_over_poses
    truth, error, budget, rois = r.truth, r.error, r.budget, r.rois
    t = recorded_rate_exposure_s(reconstruction_exposure_s(cfg.model.reconstruct.images, cfg.model.simulate), rec,
                                 cfg.path)  # as reconstruct recorded it
    rate, unit = (1.0 / t, "photons/s") if t is not None else (1.0, "photons per exposure")
    share = observed_share(pose_obs, truth if truth is not None else power)
    share_name = ("share observed (of the true light)" if truth is not None
                  else "share observed (of the light the joint reconstruction finds)")
    sd = budget["sigma"] if budget is not None else None
    # against the truth on the elements each total is over: what stays 1 as the subject turns
    on = [r.pose_well_observed[k] if why[k] else pose_obs[k] for k in range(len(heights))]
    vs_truth = (np.array([heads[k] / truth[on[k]].sum() if truth[on[k]].sum() > 0 else np.nan
                          for k in range(len(heights))]) if truth is not None else None)

    def pm(i):  # ' ± σ' of total i (poses, then joint); none where the total is over well-observed elements
        return f" ± {sd[i] * rate:.2g}" if sd is not None and i < len(sd) and np.isfinite(sd[i]) else ""
    rows = []
    for k in range(len(heights)):
        rows.append([k + 1, f"{heights[k]:g}", f"{rots[k]:g}", f"{roi[k] * rate:.4g}" if roi is not None else "-",
                     (f"{heads[k] * rate:.4g} (well-observed elements: " + why[k] + ")") if why[k]
                     else f"{heads[k] * rate:.4g}{pm(k)}", f"{share[k]:.0%}"])
    joint_total = float(np.nansum(power))
    if joint and len(heights) > 1:
        rows.append(["joint", "", "", "", f"{joint_total * rate:.4g}{pm(len(heights))}",
                     f"{np.isfinite(power).mean():.0%} of the elements"])
    when = f", exposure {t:g} s" if t is not None else " (no exposure time given: totals per exposure)"
    ctx.say(f"summary of {rec}{when}")
    ctx.table(["pose", "height_mm", "rotation_deg", f"direct ROI sum ({unit})",
               f"fluxmap total ({unit}" + (", ± 1 sd" if sd is not None else "") + ")", share_name], rows)
    if budget is not None:
        cal = "calibration included" if budget["parameters"] else \
            "photon noise and no calibration error (system.camera.uncertainty not given)"
        ctx.say(f"± 1 sd of each total: {cal}; the error budget by cause is in the report and /budget")
    if len(heights) > 1:
        parts = [f"fluxmap total {spread(totals):.1%}"]
        if roi is not None:
            parts.insert(0, f"direct ROI sum {spread(roi):.0%} (from {roi.min() * rate:.3g} to {roi.max() * rate:.3g} {unit})")
        ctx.say("spread over the poses, (max - min) / mean: " + "; ".join(parts))
        if roi is not None:
            ctx.say(f"turning and raising the subject changed the direct ROI sum {roi.max() / roi.min():.1f}-fold; "
                    f"fluxmap's total moved {spread(totals):.1%}.")
    if vs_truth is not None:
        seen = np.isfinite(power)
        ctx.say("fluxmap total over the truth on the elements it is over, per pose: "
                + " ".join(f"{x:.3f}" for x in vs_truth)
                + (f" (spread {spread(vs_truth):.1%})" if len(heights) > 1 and np.isfinite(vs_truth).all() else "")
                + (f"; jointly {joint_total / truth[seen].sum():.3f}" if joint and len(heights) > 1 and seen.any() else ""))
    if truth is not None:
        ctx.say(f"ground truth {truth.sum() * rate:.4g} {unit}: the joint reconstruction finds "
                f"{joint_total / truth.sum():.3f} of it" + (f", error sum|b' - b| / sum b = {error:.1%}" if error is not None else ""))
    for x in RA.read_filters(rec):  # several filters in one run: each one's total, before the filter
        f_rate, f_unit = (1.0 / x["exposure_s"], "photons/s") if x["exposure_s"] else (1.0, "photons per exposure")
        ctx.say(f"filter {x['name']}: {x['total'] * f_rate:.4g} {f_unit} over {x['over']}, before the filter "
                f"(transmission {x['transmission']:g}" + (f"; its frames {x['exposure_s']:g} s" if x["exposure_s"] else "")
                + ")")
    if rois is not None:  # regions of interest: the last map (joint, or the only pose)
        r_unit = "photons/s" if rois["exposure_s"] is not None else "photons per exposure"
        for i, name in enumerate(rois["names"]):
            n = rois["numbers"]
            st = rois["status"][i, -1]
            extra = ""
            if budget is not None and "rois" in budget and name in budget["rois"]["names"]:
                j = budget["rois"]["names"].index(name)
                r_rate = 1.0 / rois["exposure_s"] if rois["exposure_s"] is not None else 1.0
                cal = budget["rois"]["sigma_calibration"][j][-1] * r_rate
                reg = budget["rois"]["sigma_regularisation"][j][-1] * r_rate
                extra = f" (photon noise) ± {cal:.2g} (calibration) ± {reg:.2g} (regularisation)"
            ctx.say(f"ROI {name} ({rois['maps'][-1]}): " + (
                f"{n['total_photons_per_s'][i, -1]:.4g} ± {n['sigma_photons_per_s'][i, -1]:.2g}{extra} {r_unit}, "
                f"{n['area_mm2'][i, -1]:.3g} mm², {n['observed_share'][i, -1]:.0%} observed")
                + (f" — {st}" if st else ""))
        ctx.say(f"ROI numbers per pose: {cfg.workdir / 'rois.csv'}")
    report = cfg.workdir / "report" / "index.html"
    vtp = cfg.workdir / "reconstruction.vtp"
    if vtp.is_file():
        ctx.say(f"3-D flux map for ParaView or pyvista: {vtp}")
    ctx.say(f"report: {report}" if report.is_file() else f"report: run 'fluxmap report {cfg.path}'")
    return None  # the lines above end with where to look
