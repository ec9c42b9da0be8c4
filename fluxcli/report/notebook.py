"""The report as a lab-notebook page: what was measured with what, what to distrust, and
the flux map in 3-D.

Blocks added to :class:`fluxcli.report.page.Page` by :func:`add_top` (right after the
header: warnings, then the measurement record, then the per-pose share of the light) and
:func:`add_3d_view` (the rotatable flux map). Everything is read from the artefacts or
handed in as plain values by the report stage; nothing here reads a config or prints.
"""

from __future__ import annotations

import html
from pathlib import Path

import numpy as np

from ..surface.units import element_quantities

CHI2_FAR = (0.5, 2.0)  # chi^2/pixel outside this band: the noise model or the fit is off
SHARE_LOW = 0.9  # a pose that observes less than this share of the light says so


def observed_share(pose_observed, power) -> np.ndarray:
    """(P,) fraction of the total ``power`` on the elements each pose observes.

    Parameters
    ----------
    pose_observed : (P, n) bool
    power : (n,) float, photons; NaN (unobserved) counts as nothing.
    """
    b = np.where(np.isfinite(power), power, 0.0)
    total = b.sum()
    return np.array([b[o].sum() / total if total > 0 else np.nan for o in np.asarray(pose_observed, bool)])


def artefact_warnings(reconstruction: Path) -> tuple[list[str], int | None]:
    """The warnings ``reconstruct`` stored (``/warnings``) and the number of poorly observed
    elements (``/flux/observation`` == 1), where the artefact holds them."""
    from ..artefacts.reconstruction import read_warnings

    return read_warnings(reconstruction)


def warnings_for(study, summary: dict) -> list[str]:
    """Everything a reader should know before trusting the numbers, most important first."""
    stored, poor = artefact_warnings(study.reconstruction_path)
    out = list(stored)
    if poor:
        out.append(f"{poor} element(s) are poorly observed (tiny sensitivity or σ ≥ value): their flux is "
                   "mostly the prior's, not the data's.")
    share = summary.get("observed_share")
    if share:
        for k, s in enumerate(share["per_pose"]):
            if s is not None and s < SHARE_LOW:
                out.append(f"pose {k + 1} observes only {s:.0%} of the light ({share['basis']}): its own total "
                           "misses the rest; compare poses through the joint reconstruction.")
    for k, p in enumerate(summary.get("poses", [])):
        c = p.get("chi2_per_pixel")
        if getattr(study, "pose_chi2", None) is not None:
            break  # reconstruct warned on this very χ² (its warnings are above): once, not twice
        if c is not None and not CHI2_FAR[0] <= c <= CHI2_FAR[1]:
            out.append(f"pose {k + 1}: χ²/pixel = {c:.3g}, far from 1: the fit is "
                       + ("worse than the noise allows (model error, or the noise model underestimates the noise)."
                          if c > 1 else "better than the noise allows (the noise model overestimates the noise)."))
    return list(dict.fromkeys(out))  # each warning once


def share_summary(study) -> dict:
    """Per-pose observed share of the light, on the truth when known, else on the joint reconstruction."""
    if study.truth_power is not None:
        basis, power = "of the true light", study.truth_power
    else:
        basis, power = "of the light the joint reconstruction finds", np.where(study.observed, study.power, np.nan)
    return {"per_pose": observed_share(study.pose_observed, power).tolist(), "basis": basis}


def _table(rows) -> str:
    return ('<table class="meta">' + "".join(
        f'<tr><th class="l">{html.escape(str(k))}</th><td class="l">{html.escape(str(v))}</td></tr>' for k, v in rows)
        + "</table>")


def add_top(page, study, summary: dict, record: list[tuple[str, str]] | None = None, *,
            exposure_s: float | None = None) -> None:
    """Warnings (first), the measurement record, and the per-pose share of the light; with
    the exposure, the totals as rates (photons/s)."""
    summary["observed_share"] = share_summary(study)
    warns = warnings_for(study, summary)
    summary["warnings"] = warns
    if warns:
        page.parts.append('<div class="warnings"><h2 id="warnings">Warnings</h2>'
                          + "".join(f'<p class="warn">{html.escape(w)}</p>' for w in warns) + "</div>")
    else:
        page.parts.append('<p class="ok">No warnings: every pose fits its images to within the noise '
                          "(χ²/pixel near 1) and observes most of the light.</p>")
    b = getattr(study, "budget", None)
    sd = b["sigma"] if b and len(b.get("sigma", [])) >= study.n_poses else None

    def pm(i):  # ' ± σ' of total i (poses, then joint) in photons/s
        return f" ± {sd[i] / exposure_s:.2g}" if sd is not None and i < len(sd) and _finite(sd[i]) else ""
    if exposure_s is not None:
        rates = [("exposure", f"{exposure_s:g} s")]
        rates += [(f"total flux, pose {k + 1} alone (photons/s, ± 1 sd)", f"{t / exposure_s:.4g}{pm(k)}")
                  for k, t in enumerate(study.pose_total)]
        rates.append(("total flux, " + ("joint over poses" if study.joint else "first pose") + " (photons/s, ± 1 sd)",
                      f"{np.nansum(study.power) / exposure_s:.4g}" + pm(study.n_poses if study.joint else 0)))
        if study.truth_power is not None:
            rates.append(("ground-truth total (photons/s)", f"{study.truth_power.sum() / exposure_s:.4g}"))
        page.parts.append('<h2 id="rates">Flux as a rate</h2>' + _table(rates))
        summary["rates_photons_per_s"] = {"exposure_s": exposure_s,
                                          "pose_total": (study.pose_total / exposure_s).tolist(),
                                          "total": float(np.nansum(study.power) / exposure_s)}
    if b:
        _budget_table(page, b, exposure_s)
    if record:
        page.parts.append('<h2 id="record">What was measured, with what</h2>' + _table(record))
        summary["record"] = [list(r) for r in record]
    sh = summary["observed_share"]
    rows = [[str(k + 1), f"{study.heights_mm[k]:g}", f"{study.rotations_deg[k]:g}",
             "–" if s is None else f"{s:.1%}", f"{study.pose_observed[k].mean():.0%}"]
            for k, s in enumerate(sh["per_pose"])]
    page.parts.append(f"<p>Share of the light each pose observes ({html.escape(sh['basis'])}): a pose that sees only "
                      "part of the subject reconstructs only that part, so its own total is smaller by this share.</p>")
    page.table(["pose", "height (mm)", "rotation (°)", f"share of the light observed ({sh['basis']})",
                "elements observed (of all elements)"], rows)


def add_3d_view(page, study, *, rig=None, exposure_s: float | None = None) -> None:
    """The rotatable flux map (plotly, offline), with uncertainty layers in its menu."""
    from . import view3d

    page.section("flux3d-section", "The flux map in 3-D")
    areas = study.areas_mm2
    power = np.where(study.observed, study.power, np.nan)
    q = element_quantities(power, areas, exposure_s=exposure_s)
    layers = {}
    if exposure_s is not None:
        layers["radiance (photons/s/cm²/sr)"] = q["radiance_photons_per_s_per_cm2_per_sr"]
        layers["exitance (photons/s/mm²)"] = q["exitance_photons_per_s_per_mm2"]
    else:
        layers["exitance (photons/mm² per exposure)"] = q["exitance_photons_per_mm2"]
    from ..artefacts.reconstruction import read_maps

    maps = read_maps(study.reconstruction_path)
    sigma = np.where(study.observed, maps.sigma, np.nan) if maps.sigma is not None else None
    if sigma is not None and np.isfinite(sigma).any():
        per = (1.0 / exposure_s, "photons/s") if exposure_s is not None else (1.0, "photons per exposure")
        layers[f"uncertainty σ of the power ({per[1]}, 1 sd)"] = sigma * per[0]
        with np.errstate(divide="ignore", invalid="ignore"):
            layers["relative uncertainty σ / power"] = np.where(power > 0, sigma / power, np.nan)
    if study.truth_power is not None:
        qt = element_quantities(study.truth_power, areas, exposure_s=exposure_s)
        key = "exitance_photons_per_s_per_mm2" if exposure_s is not None else "exitance_photons_per_mm2"
        layers["ground truth " + ("exitance (photons/s/mm²)" if exposure_s is not None
                                  else "exitance (photons/mm² per exposure)")] = qt[key]
    s = study.surface
    outlines = None
    if maps.rois is not None:  # regions of interest on the map shown (the last map: joint, or the only pose)
        r = maps.rois
        outlines = {n: r["members"][i, -1] for i, n in enumerate(r["names"])}
    fig = view3d.flux_figure(s.vertices_mm, s.faces, s.element_of_face, study.observed, layers, rig=rig,
                             title="joint reconstruction, subject at rest" if study.joint else "reconstruction",
                             outlines=outlines)
    page.parts.append(
        "<p>Drag to turn, scroll to zoom, hover for each element's numbers; the menu at the top left switches "
        "between the quantities" + (", the uncertainty maps" if len(layers) > 2 else "") + " and the truth. Axes in "
        "millimetres, world frame (z up); the camera's lens, its optical axis to the focal plane and its field, and the "
        "mirrors are drawn where they are. Mid grey: elements no view observes (unknown, not zero); light grey: faces "
        "that are no element.</p>")
    page.parts.append('<div class="plot3d">' + view3d.to_html(fig) + "</div>")


def _budget_table(page, b: dict, exposure_s: float | None) -> None:
    """Each total with its σ by cause: photon noise, regularisation, calibration (reconstruct's /budget)."""
    t = exposure_s or 1.0
    unit = "photons/s" if exposure_s else "photons per exposure"

    def cell(x):
        return f"{x / t:.2g}" if _finite(x) else "not computed"
    rows = [[lab, f"{b['total'][i] / t:.4g}", cell(b["sigma_noise"][i]), cell(b["sigma_regularisation"][i]),
             cell(b["sigma_calibration"][i]), cell(b["sigma"][i])] for i, lab in enumerate(b["labels"])]
    how = (f"T rebuilt with each of {len(b['parameters'])} calibrated parameter(s) moved by +1 sd "
           f"({', '.join(p['name'] for p in b['parameters'])}; {b['t_builds']} T builds), solved again at the same λ"
           + (f", and the radiometric gain's {b['gain_relative']:.1%}" if _finite(b.get("gain_relative")) and b["gain_relative"] else "")
           if b["parameters"] else "not computed: the config gives no system.camera.uncertainty (calibrate writes it)")
    page.parts.append('<h2 id="budget">Error budget of each total</h2><p>' + html.escape(
        f"1 sd of each total over its observed elements ({unit}), by cause. Photon noise: from the reconstruction's "
        "covariance. Regularisation: the total's largest move when λ is halved or doubled. Calibration: " + how
        + ". σ: the three in quadrature.") + "</p>")
    page.table(["total", f"value ({unit})", "photon noise", "regularisation", "calibration", "σ"], rows)


def _finite(x) -> bool:
    return x is not None and bool(np.isfinite(x))
