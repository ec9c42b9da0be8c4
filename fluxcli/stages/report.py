"""``fluxmap report CONFIG``: figures and one HTML page from the run's artefacts.

Examples
--------
$ fluxmap report configs/paper-3d.yaml
$ fluxmap report configs/paper-3d.yaml --set report.slice_axial_mm=10
$ fluxmap report configs/paper-2d.yaml --set report.surface_views=false

Writes ``<workdir>/report/index.html`` (self-contained: opens from disk), the figures as
PNG files beside it, and ``summary.json`` with every number the page shows.  Reads
``reconstruction.h5``, the T files it was solved with, and ``simulation.h5`` when the
images came from a simulation.  A report already made from the same artefacts and
settings is kept unless ``--force``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .. import artefacts as A
from .. import config as C
from .. import report as R
from ..artefacts import reconstruction as RA
from ..errors import UserError
from ..resources import check_writable
from .plans import geometry_of, placer_of
from .context import RunContext
from .outputs import reconstruction_exposure_s, recorded_rate_exposure_s, record_of, rig_of


_GEOMETRY = ("system", "system.camera.lens", "system.camera.pose", "subject")


def run(cfg: C.LoadedConfig, ctx: RunContext) -> Path:
    rs = cfg.model.report
    rec = cfg.workdir / RA.FILENAME
    cal = cfg.workdir / "calibration.h5"
    subject_surface = cfg.model.subject.surface if cfg.model.subject is not None else None
    surf = _surface_artefact([cfg.captured_surface_path, cfg.workdir / "surface.h5"]
                             + ([cfg.resolve(subject_surface.artefact)]
                                if getattr(subject_surface, "artefact", None) is not None else []))
    if not rec.is_file() and (cal.is_file() or surf is not None):
        return _sections_only(cfg.workdir / "report", rs.title or cfg.path.stem, cal if cal.is_file() else None, surf,
                              ctx)
    C.require(cfg, "report", _GEOMETRY)
    if not rec.is_file():
        raise UserError(f"report: {rec} does not exist; run 'fluxmap reconstruct {cfg.path}' first "
                        f"(after 'fluxmap simulate' or with reconstruct.images naming image files).")
    out_dir = cfg.workdir / "report"
    check_writable(out_dir, "workdir")
    sim = cfg.workdir / "simulation.h5"
    inputs = {"reconstruction.h5": A.file_sha256(rec)}
    if cal.is_file():
        inputs["calibration.h5"] = A.file_sha256(cal)
    if sim.is_file():
        inputs["simulation.h5"] = A.file_sha256(sim)
    if surf is not None:
        inputs["surface.h5"] = A.file_sha256(surf)
    settings = rs.model_dump(mode="json") | {"config_sha256": cfg.sha256}
    index = out_dir / "index.html"
    if not ctx.force and index.is_file() and _previous(out_dir).get("provenance") == {"inputs": inputs, "settings": settings}:
        ctx.say(f"report: up to date ({index}); --force redraws it")
        return index

    prov = RA.read_provenance(rec)  # the result must be the one this config describes
    A.check_geometry(rec, prov, geometry_of(cfg, placer_of(cfg).surface.digest()),
                     remedy=f"Run 'fluxmap reconstruct {cfg.path}' again")
    used = prov.input_files.get("simulation.h5", {}).get("sha256")
    same_sim = sim.is_file() and used is not None and used == inputs.get("simulation.h5")
    if sim.is_file() and used is not None and not same_sim:
        ctx.warn(f"{sim} changed since {rec.name} was made from it; its SNR table is left out "
                 f"(run 'fluxmap reconstruct {cfg.path}' again to use it).")
    study = R.load(rec, simulation=sim if same_sim else None)
    geometry = study.geometry
    if geometry is None:
        raise UserError(f"report: {rec} records no geometry (made by an older fluxmap); run "
                        f"'fluxmap reconstruct {cfg.path} --force'.")
    _check_slice(study, geometry, rs.slice_axial_mm)
    _remove_old_figures(out_dir)
    exposure_s = recorded_rate_exposure_s(reconstruction_exposure_s(cfg.model.reconstruct.images, cfg.model.simulate),
                                          rec, cfg.path)  # as reconstruct recorded it
    ctx.say(f"report: {study.n_poses} pose(s), {study.surface.n_elements} elements, method {study.method}")
    index, summary = R.make_report(study, out_dir, title=rs.title or cfg.path.stem, geometry=geometry,
                                   slice_axial_mm=rs.slice_axial_mm, surface_views=rs.surface_views,
                                   extra={"provenance": {"inputs": inputs, "settings": settings}},
                                   sections=_filters_section(rec) + _rois_section(rec)
                                   + ([_calibration_section(cal)] if cal.is_file() else [])
                                   + ([_surface_section(surf, plotly_loaded=True)] if surf is not None else []),
                                   record=record_of(cfg, inputs, exposure_s), rig=rig_of(cfg.model.system),
                                   exposure_s=exposure_s)
    for note in summary["notes"]:
        ctx.say(f"note: {note}")
    sp = summary["spreads"]
    ctx.say("spread over poses: " + (", ".join(f"{k} {v:.1%}" for k, v in sp.items() if v is not None)
                                     or "none (no pose found light)"))
    if summary.get("error") is not None:
        obs = (f"; over observed elements {summary['error_observed']:.2%}, {summary['total_ratio_observed']:.3f}"
               if summary.get("error_observed") is not None else "")
        ctx.say(f"error {summary['error']:.2%}, total ratio {summary['total_ratio']:.3f} over all elements "
                f"(unobserved ones count as 0){obs}")
    ctx.say(f"{len(summary['figures'])} figure(s); open {index}")
    return index


def _check_slice(study, geometry, at_mm: float) -> None:
    """The slice must cut the subject: a plane beyond its ends would silently show the end ring."""
    if study.is_line_detector:
        return
    surf = study.surface
    axial = R.axial_positions_mm(surf.element_centroids_mm, surf.vertices_mm, np.asarray(geometry.axis_point_mm),
                                 geometry.axis_direction)
    lo, hi = float(axial.min()), float(axial.max())
    size = float(np.sqrt(np.median(study.areas_mm2))) if len(study.areas_mm2) else 0.0
    if not (lo - size <= at_mm <= hi + size):
        raise UserError(f"report.slice_axial_mm: {at_mm:g} mm is outside the subject, whose elements lie between "
                        f"{lo:.3g} and {hi:.3g} mm along its axis (from its centre).")


def _previous(out_dir: Path) -> dict:
    try:
        return json.loads((out_dir / "summary.json").read_text())
    except (OSError, ValueError):
        return {}


def _remove_old_figures(out_dir: Path) -> None:
    """Figures of a previous report that this one might not redraw (e.g. fewer poses)."""
    for name in _previous(out_dir).get("figures", []):
        p = out_dir / Path(name).name
        if p.suffix == ".png" and p.is_file():
            p.unlink()


def _calibration_section(cal: Path):
    from ..report.calibration_figures import add_calibration_section

    def add(page, save):
        return {"calibration": add_calibration_section(page, save, cal)}
    return add


def _surface_artefact(candidates: list) -> Path | None:
    """The first of ``candidates`` that exists: the structured-light surface this run measured
    (capture-surface's ``surface.h5``), or the one ``subject.surface.artefact`` names; None when
    there is none."""
    return next((p for p in candidates if p is not None and p.is_file()), None)


def _surface_section(surf: Path, *, plotly_loaded: bool):
    from ..report.surface_figures import add_surface_section

    def add(page, save):
        return {"surface": add_surface_section(page, save, surf, plotly_loaded=plotly_loaded)}
    return add


def _sections_only(out_dir: Path, title: str, cal: Path | None, surf: Path | None, ctx: RunContext) -> Path:
    """No reconstruction yet (a calibrate-only or capture-surface-only workdir): the calibration
    and surface sections alone, into ``out_dir`` under ``title``."""
    inputs = {}
    if cal is not None:
        with A.open_artefact(cal, "calibration"):
            pass
        inputs["calibration.h5"] = A.file_sha256(cal)
    if surf is not None:
        with A.open_artefact(surf, "surface"):
            pass
        inputs["surface.h5"] = A.file_sha256(surf)
    check_writable(out_dir, "workdir")
    sections = ([_calibration_section(cal)] if cal is not None else []) + (
        [_surface_section(surf, plotly_loaded=False)] if surf is not None else [])
    index, summary = R.sections_report(out_dir, title, sections,
                                       extra={"provenance": {"inputs": inputs}})
    ctx.say(f"report: {' and '.join(k.split('.')[0] for k in inputs)}, {len(summary['figures'])} figure(s); open {index}")
    return index


def _filters_section(rec: Path) -> list:
    """Several filters in one run: each filter's total before the filter, at its frames' exposure."""
    filters = RA.read_filters(rec)
    if not filters:
        return []

    def add(page, save):
        page.section("filters", "Filters")
        page.text("Each filter's images were reconstructed with the same T and divided by the filter's transmission: "
                  "the light leaving the surface within its band, before the filter. The first filter's is the map "
                  "shown above; each one's map is in /filters/<name> and in the VTP.")
        rows = []
        for x in filters:
            rate, unit = (1.0 / x["exposure_s"], "photons/s") if x["exposure_s"] else (1.0, "photons per exposure")
            rows.append([x["name"], f"{x['transmission']:g}", f"{x['exposure_s']:g}" if x["exposure_s"] else "-",
                         f"{x['total'] * rate:.4g} {unit}", x["over"]])
        page.table(["filter", "transmission", "frames (s)", "total before the filter", "over"], rows, left_columns=1)
        return {"filters": [x | {"total_photons_per_s": x["total"] / x["exposure_s"] if x["exposure_s"] else None}
                            for x in filters]}
    return [add]


def _rois_section(rec: Path) -> list:
    """The regions of interest (issue 24): a table per region and map, numbers into summary.json."""
    from ..artefacts.reconstruction import ROI_NUMBER_KEYS as NUMBER_KEYS, read_roi_spectrum

    # spectrum: filter -> (transmission, ROI numbers) when several filters were reconstructed
    r, spectrum = read_roi_spectrum(rec)
    if r is None:
        return []

    def add(page, save):
        unit = "photons/s" if r["exposure_s"] is not None else "photons per exposure"
        page.section("rois", "Regions of interest")
        page.text(f"Per region and pose (and all poses jointly): the total light leaving the region's observed elements "
                  f"({unit}) ± 1 sd from the reconstruction's covariance (the elements' covariances included, not a sum "
                  "of their σ), the mean and peak Lambertian radiance L = M/π (photons s⁻¹ cm⁻² sr⁻¹), the area and the "
                  "shares of it that are observed and well observed. A region mostly unobserved or poorly observed shows "
                  "why instead of a number. The regions are outlined in the 3-D view. Every number is in rois.csv.")
        rows = []
        for i, name in enumerate(r["names"]):
            for m, label in enumerate(r["maps"]):
                x = {k: r["numbers"][k][i, m] for k in NUMBER_KEYS}
                st = r["status"][i, m]
                total = f"{x['total_photons_per_s']:.4g} ± {x['sigma_photons_per_s']:.2g}" + (f" — {st}" if st else "")
                rows.append([name, label, total, f"{x['mean_radiance']:.3g}", f"{x['peak_radiance']:.3g}",
                             f"{x['area_mm2']:.3g}", f"{x['observed_share']:.0%}", f"{x['well_observed_share']:.0%}"])
        page.table(["region", "pose", f"total ({unit})", "mean radiance", "peak radiance", "area (mm²)", "observed",
                    "well observed"], rows, left_columns=2)
        out_spec = {}
        if spectrum:
            out_spec = _spectrum_part(page, save, r, spectrum, unit)
        return {"rois_spectrum": out_spec, "rois": {"names": r["names"], "maps": r["maps"], "unit_total": unit, "exposure_s": r["exposure_s"],
                         "definitions": r["definitions"], "status": r["status"].tolist(),
                         **{k: r["numbers"][k].tolist() for k in NUMBER_KEYS}}}
    return [add]


def _spectrum_part(page, save, r, spectrum: dict, unit: str) -> dict:
    """Per region, the joint total per filter (± 1 sd): a table and a bar plot."""
    from matplotlib.figure import Figure

    names = list(spectrum)
    tot = np.array([[spectrum[n][1]["numbers"]["total_photons_per_s"][i, -1] for n in names] for i in range(len(r["names"]))])
    sd = np.array([[spectrum[n][1]["numbers"]["sigma_photons_per_s"][i, -1] for n in names] for i in range(len(r["names"]))])
    page.text(f"Per region, the light leaving it within each filter's band ({unit}, the last map: joint, or the only "
              "pose), each filter's images divided by its transmission (the light before the filter). Every number is "
              "in rois_spectrum.csv.")
    page.table(["region", *[f"{n} (T {spectrum[n][0]:g})" for n in names]],
               [[name, *[f"{tot[i, j]:.4g} ± {sd[i, j]:.2g}" for j in range(len(names))]] for i, name in enumerate(r["names"])])
    fig = Figure(figsize=(7, 3.6))
    ax = fig.add_subplot()
    w = 0.8 / max(len(names), 1)
    x = np.arange(len(r["names"]))
    for j, n in enumerate(names):
        ax.bar(x + (j - (len(names) - 1) / 2) * w, tot[:, j], w, yerr=sd[:, j], capsize=3, label=n)
    ax.set_xticks(x, r["names"])
    ax.set_ylabel(unit)
    ax.set_title("per-region spectrum (joint reconstruction)")
    ax.legend(title="filter")
    fig.tight_layout()
    page.figure(save(fig, "rois_spectrum.png"), "Each region's total per filter, ± 1 sd.")
    return {"filters": names, "transmissions": [spectrum[n][0] for n in names], "total": tot.tolist(), "sigma": sd.tolist()}
