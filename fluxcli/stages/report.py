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
from ..errors import UserError
from ..pipeline import check_writable, geometry_of
from ..scene import SubjectPlacer
from .context import RunContext


_GEOMETRY = ("system", "system.camera.lens", "system.camera.pose", "subject")


def run(cfg: C.LoadedConfig, ctx: RunContext) -> Path:
    rs = cfg.model.report
    rec = cfg.workdir / "reconstruction.h5"
    cal = cfg.workdir / "calibration.h5"
    if cal.is_file() and not rec.is_file():
        return _calibration_only(cfg, cal, ctx)
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
    settings = rs.model_dump(mode="json") | {"config_sha256": cfg.sha256}
    index = out_dir / "index.html"
    if not ctx.force and index.is_file() and _previous(out_dir).get("provenance") == {"inputs": inputs, "settings": settings}:
        ctx.say(f"report: up to date ({index}); --force redraws it")
        return index

    with A.open_artefact(rec, "reconstruction") as f:  # the result must be the one this config describes
        prov = A.read_provenance(f)
        A.check_geometry(rec, prov, geometry_of(cfg, SubjectPlacer(cfg).surface.digest()),
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
    ctx.say(f"report: {study.n_poses} pose(s), {study.surface.n_elements} elements, method {study.method}")
    index, summary = R.make_report(study, out_dir, title=rs.title or cfg.path.stem, geometry=geometry,
                                   slice_axial_mm=rs.slice_axial_mm, surface_views=rs.surface_views,
                                   extra={"provenance": {"inputs": inputs, "settings": settings}},
                                   sections=[_calibration_section(cal)] if cal.is_file() else None)
    for note in summary["notes"]:
        ctx.say(f"note: {note}")
    sp = summary["spreads"]
    ctx.say("spread over poses: " + ", ".join(f"{k} {v:.1%}" for k, v in sp.items() if v is not None))
    if summary.get("error") is not None:
        ctx.say(f"error {summary['error']:.2%}, total ratio {summary['total_ratio']:.3f}")
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


def _calibration_only(cfg: C.LoadedConfig, cal: Path, ctx: RunContext) -> Path:
    """A calibrate-only workdir: the report is the calibration section alone."""
    from ..report import _write_text, jsonable
    from ..report import figures as F
    from ..report.calibration_figures import add_calibration_section
    from ..report.page import Page

    with A.open_artefact(cal, "calibration"):
        pass
    out_dir = cfg.workdir / "report"
    out_dir.mkdir(parents=True, exist_ok=True)
    figures: list[str] = []

    def save(fig, name):
        F.save(fig, out_dir / name)
        figures.append(name)
        return out_dir / name

    page = Page(cfg.model.report.title or cfg.path.stem)
    summary = {"calibration": add_calibration_section(page, save, cal), "figures": figures,
               "provenance": {"inputs": {"calibration.h5": A.file_sha256(cal)}}}
    _write_text(out_dir / "summary.json", json.dumps(jsonable(summary), indent=1))
    index = out_dir / "index.html"
    _write_text(index, page.html(out_dir))
    ctx.say(f"report: calibration, {len(figures)} figure(s); open {index}")
    return index
