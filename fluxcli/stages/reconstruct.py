"""``fluxmap reconstruct CONFIG``: from images to the flux leaving each surface element.

Examples
--------
$ fluxmap reconstruct configs/paper-3d.yaml
$ fluxmap reconstruct configs/paper-2d.yaml --jobs 2        # runs the configured sweep too
$ fluxmap reconstruct configs/demo.yaml --set reconstruct.method=paper --set reconstruct.lambda=1

Images come from ``<workdir>/simulation.h5`` (a chosen level and repeat) or from image
files named per pose (``reconstruct.images``).  Each pose is reconstructed on its own and,
with several poses, all of them jointly (their T and images stacked).  Saturated pixels
are masked.  Elements no camera sees are reported as unobserved (NaN), never as zero.

The config is read once, into a :class:`~._reconstruct_plan.ReconstructPlan`; the images
are :mod:`._reconstruct_inputs`, the unknowns and the sweep :mod:`._reconstruct_grid`, the
science :mod:`fluxcli.inverse.solve` (and :mod:`fluxcli.imaging.spikes`,
:mod:`fluxcli.imaging.stray`, :mod:`fluxcli.inverse.unknowns`), the file
:mod:`fluxcli.artefacts.reconstruction`.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from .. import artefacts as A
from .. import config as C
from ..artefacts import reconstruction as RA
from ..imaging.spikes import (MAX_SPIKE_SHARE, SPIKE_ISOLATION, SPIKE_SIGMA, SPIKE_SPREAD,  # noqa: F401 (importers)
                              describe_pixels, isolated_spikes, reject_spikes, residual_spread)
from ..imaging.stray import STRAY_REFUSE, STRAY_WARN, light_outside  # noqa: F401
from ..inverse import backprojection, error_l1, total_ratio
from ..inverse.emission_checks import emission_checks
from ..inverse.emission_domain import leave_out_edge_on
from ..inverse.solve import DENSE, REGULARISED, describe, run_method, scaled, solve_poses  # noqa: F401
from ..inverse.unknowns import (MAX_AUTO_SUB_ELEMENTS, ElementMap, Grid, VertexMap,  # noqa: F401
                                element_unknowns, n_vertices, resolve_unknowns)
from . import budget as B
from ._reconstruct_grid import check_solver_size, direct_roi, make_grid, run_sweep  # noqa: F401
from ._reconstruct_filters import checked_solves, dark_poses, named, noise_of, other_filters, solve_warnings  # noqa: F401
from ._reconstruct_inputs import Inputs, check_sweep, from_capture, load_inputs, photon_noise, simulated_emission  # noqa: F401
from ._reconstruct_plan import SOLVER_VERSION, ReconstructPlan, plan_of  # noqa: F401
from .context import RunContext
from .outputs import export_reconstruction
from .rois import RoiMeter


def run(cfg: C.LoadedConfig, ctx: RunContext) -> Path:
    """The command: the run plan once, then :func:`reconstruct` unless the artefact is up to date."""
    plan = plan_of(cfg)
    if not ctx.force and A.is_up_to_date(plan.output, "reconstruction", plan.digest):
        ctx.say(f"reconstruct: {plan.output} is up to date (--force to redo)")
        for line in RA.up_to_date_summary(plan.output):
            ctx.say(line)
        return plan.output
    return reconstruct(plan, ctx)


def reconstruct(plan: ReconstructPlan, ctx: RunContext) -> Path:
    """Solve every pose (and jointly), check, budget and write reconstruction.h5 (and the ROI files, the VTP)."""
    out, surface = plan.output, plan.placer.surface
    check_solver_size(plan.settings, plan.sweep, plan.images.pixels, ctx, surface, len(plan.todo))
    inp = load_inputs(plan.images, len(plan.todo), surface.n_elements, plan.geometry,  # checked before any T is built
                      plan.config_path, [pt.pose for _, pt in plan.todo])
    if plan.sweep is not None:
        check_sweep(plan.sweep, plan.images, inp)
    t_rate = plan.rate_exposure_s(inp.exposure_s, inp.exposure_recorded)
    rois = RoiMeter(plan.rois, plan.roi_mesh, surface, t_rate)  # regions of interest (issue 24): checked before T
    views, placer, todo, _ = plan.build_T(ctx, "building T", "elements")
    P = len(todo)
    nx, ny = plan.images.pixels
    m = resolve_unknowns(plan.settings, surface)
    grids = {u: make_grid(plan.build_T, ctx, surface, u, curvature=u == m.unknowns)
             for u in {"elements", m.unknowns,
                       *[resolve_unknowns(s, surface).unknowns for s in (plan.sweep.methods if plan.sweep else ())]}}
    Ts = grids["elements"].Ts
    gm = grids[m.unknowns]
    noise = noise_of(plan, inp)
    tag = f" (filter {plan.main_filter})" if len(plan.filters or ()) > 1 else ""  # in a pose's errors
    stray = [light_outside(Ts[k], inp.images[k], inp.valid[k], noise, pt.pose.label + tag, surface)
             for k, (_, pt) in enumerate(todo)]
    ctx.say(f"reconstruct: {inp.source}; {describe(m)}, {P} pose(s); {noise.kind} noise model")
    if plan.qe_warning:  # QE scales every photon
        ctx.say(plan.qe_warning)
    t0 = time.perf_counter()
    scale = plan.transmission(plan.main_filter)
    if inp.truth is not None and scale != 1.0:
        inp.truth = inp.truth / scale  # the truth through the filter, as the results: before it
    totals = B.TotalMeter(ctx, P + int(plan.joint and P > 1))  # each total's photon-noise sigma; progress
    per_pose, joint = solve_poses(gm, inp, m, noise, stray, todo, (ny, nx), plan.joint, B.Both(rois, totals), scale, tag)
    per_pose, joint = leave_out_edge_on(placer.emission, views, todo, per_pose, joint)  # issue 21: the model's domain
    others, filter_warnings = other_filters(plan, surface, gm, m, Ts, todo, views, placer.emission, (ny, nx),
                                            gm.Ts[0].shape[1] / surface.n_elements)  # {filter: ...}, each checked
    seconds = time.perf_counter() - t0
    budget = B.error_budget(plan.system, plan.calibration_budget, plan.build_T, ctx, surface, m, gm, inp, noise,
                            per_pose, joint, todo, scale, totals, t_rate, rois)
    main = joint if joint is not None else per_pose[0][0]
    areas = surface.element_areas_mm2
    rows = _rows(per_pose, joint, todo, inp.truth)
    checked, joint_checked, emission_lines, emission, by_angle = emission_checks(
        placer.emission, views, todo, per_pose, joint, inp.images, inp.valid, noise,
        simulated_emission(plan.images, plan.subject_emission))
    checked, joint_checked, peaked = checked_solves(checked, joint_checked, inp, noise, Ts, gm.Ts[0].shape[1] /
                                                    surface.n_elements, plan.transfer.subject.refine_faces, todo)
    checked = B.with_shift_warnings(checked, budget.shifts, [pt.pose.label for _, pt in todo], by_angle, peaked)
    warnings = named(plan.filters, plan.main_filter,
                     dark_poses(inp, todo, noise, Ts) + solve_warnings(checked, joint_checked, todo))
    warnings += filter_warnings
    summary = _total_summary(checked, joint_checked, todo, {b.label: b.sigma for b in budget.totals}) + budget.lines()
    sweep = run_sweep(plan, ctx, grids, todo) if plan.sweep is not None else None
    prov = plan.new_provenance()
    for name, path in (inp.files or {}).items():
        prov.add_file(name, path, base=out.parent)
    truth = None
    if inp.truth is not None:
        attrs = {"error": error_l1(main.power, inp.truth), "total_ratio": total_ratio(main.power, inp.truth)}
        for name, sel in (("observed", main.observed), ("well_observed", main.well_observed)):
            if sel.any() and inp.truth[sel].sum() > 0:  # (a truth lit only where no view looks: nothing to compare)
                only = np.where(sel, main.power, np.nan)
                attrs[f"error_{name}"] = error_l1(only, inp.truth, observed_only=True)
                attrs[f"total_ratio_{name}"] = total_ratio(only, inp.truth, observed_only=True)
        truth = RA.Truth(inp.truth, [error_l1(r.power, inp.truth) for r, _ in per_pose],
                         [total_ratio(r.power, inp.truth) for r, _ in per_pose], attrs)
    filters = None
    if plan.filters:
        filters = [_filter_record(plan, name, *x, areas, [pt.path for _, pt in todo]) for name, x in
                   {plan.filters[0]: (inp, checked, joint_checked, rois), **others}.items()]
    cam, base = plan.camera, plan.workdir  # paths relative to the artefact's folder: the same bytes in any clone
    RA.write(out, RA.Reconstruction(
        config_sha256=plan.config_sha256, T_keys=[pt.key for _, pt in todo], images_source=inp.source, provenance=prov,
        inputs_digest=plan.digest, surface=surface,
        geometry=RA.Geometry(placer.axis_point, placer.axis, cam.pose.look, cam.pose.up, [v.name for v in views],
                             [A.portable_path(pt.path, base) for _, pt in todo],
                             [A.portable_path(p, base) for p in plan.images.files]),
        flux=_flux(main, areas), joint_over_poses=joint is not None,
        per_pose=RA.PerPose(
            power=np.array([r.power for r, _ in per_pose]), sigma=np.array([r.sigma for r, _ in per_pose]),
            observed=np.array([r.observed for r, _ in per_pose]), total=[np.nansum(r.power) for r, _ in per_pose],
            lam=[r.lam for r, _ in per_pose], vertices_mm=np.array([sc.surface.vertices_mm for sc, _ in todo]),
            backprojection_total=[np.nansum(backprojection(Ts[k], np.where(inp.valid[k], inp.images[k], 0.0).ravel()))
                                  for k in range(P)],
            direct_roi_photons=[direct_roi(todo[k][1].path, inp.images[k]) for k in range(P)],
            heights_mm=[pt.pose.height_mm for _, pt in todo], rotations_deg=[pt.pose.rotation_deg for _, pt in todo],
            chi2_per_pixel=[r.chi2_per_pixel for r, _ in checked], headline=[headline_of(r) for r, _ in checked],
            observation=np.array([r.observation for r, _ in checked])),
        fit=RA.Fit(inp.images, np.array([fi for _, fi in per_pose]), inp.valid),
        method=m.method, rate_exposure_s=t_rate,
        rate_exposure_source=("capture.h5 frames" if plan.images.is_capture else "image files' metadata"
                              if inp.exposure_recorded else "config" if t_rate is not None else "none"),
        settings=m.model_dump(mode="json", by_alias=True), lambda_used=main.lam,
        seconds=A.recorded_seconds(seconds), truth=truth, emission=emission, warnings=warnings,
        write_budget=lambda g: RA.write_budget(g, budget), totals_summary=summary, sweep=sweep,
        write_rois=rois.write if rois else None, filters=filters))
    for w in warnings:
        ctx.warn(w)
    header = ["height_mm", "rotation_deg", "total photons", "observed", "lambda"]
    if inp.truth is not None:  # the paper's convention (unobserved elements count as 0) beside the observed ones
        header += ["error all / observed", "total ratio all / observed"]
    ctx.table(header, rows)
    ctx.say(f"{seconds:.2f} s of solving")
    _roi_outputs(plan, ctx, rois, others)
    export_reconstruction(ctx, out, plan.config_exposure_s, plan.config_path)  # <workdir>/*.vtp, from the artefact
    for line in summary + emission_lines:
        ctx.say(line)
    return out


def _roi_outputs(plan: ReconstructPlan, ctx: RunContext, rois, others: dict) -> None:
    """rois_spectrum.csv (several filters), rois.csv and the ROI table."""
    if plan.filters and rois:
        from ..quantify.rois import spectrum_csv_text

        A.write_text(plan.workdir / "rois_spectrum.csv", spectrum_csv_text(
            [(nm, plan.transmission(nm), mt)
             for nm, mt in [(plan.filters[0], rois)] + [(k, v[3]) for k, v in others.items()]]))
        ctx.say(f"ROI spectrum over {len(plan.filters)} filters: {plan.workdir / 'rois_spectrum.csv'}")
    if rois:
        ctx.table(*rois.table())
        for name, label, _, _, x in rois.rows():
            if x.status:
                ctx.warn(f"ROI {name}, {label}: {x.status}")
        ctx.say(f"ROI numbers for other tools: {rois.write_csv(plan.workdir / 'rois.csv')}"
                + ("" if rois.exposure_s is not None else " (no exposure time given: per exposure, not per second)"))


def _filter_record(plan: ReconstructPlan, name, inp_f, pp, joint, meter, areas, T_paths) -> RA.FilterRecord:
    """/filters/<name>: its reconstruction (joint, else the first pose), per-pose powers, ROI numbers."""
    main = joint if joint is not None else pp[0][0]
    return RA.FilterRecord(
        name, plan.transmission(name), inp_f.source, _flux(main, areas), np.array([r.power for r, _ in pp]),
        [np.nansum(r.power) for r, _ in pp], [direct_roi(T_paths[k], inp_f.images[k]) for k in range(len(pp))],
        inp_f.truth, meter.write if meter else None, plan.rate_exposure_s(inp_f.exposure_s, inp_f.exposure_recorded))


def _flux(res, areas) -> RA.Flux:
    return RA.Flux(res, headline_of(res), areas)


def headline_of(res):
    """The trustworthy total of one solve (:func:`fluxcli.inverse.methods.headline_total`)."""
    from ..inverse.methods import headline_total

    return headline_total(res.power, res.observed, res.well_observed, res.warnings)


def _rows(per_pose, joint, todo, truth) -> list[list]:
    """The console table: per pose (and jointly) the headline total, share observed, λ, the errors."""
    def row(first, second, r):
        out = [first, second, _headline_cell(r), f"{r.observed.mean():.0%}", f"{r.lam:.3g}" if r.lam is not None else "-"]
        return out + (_vs_truth(r.power, r.observed, truth) if truth is not None else [])

    rows = [row(pt.pose.height_mm, pt.pose.rotation_deg, r) for (r, _), (_, pt) in zip(per_pose, todo)]
    return rows + ([row("joint", "", joint)] if joint is not None else [])


def _vs_truth(power, observed, truth) -> list[str]:
    """Error and total ratio against the simulated truth over all elements (unobserved ones
    count as 0, the paper's convention) and over the observed ones."""
    only = np.where(observed, power, np.nan)
    if not observed.any() or not truth[observed].sum() > 0:
        return [f"{error_l1(power, truth):.2%} / -", f"{total_ratio(power, truth):.3f} / -"]
    return [f"{error_l1(power, truth):.2%} / {error_l1(only, truth, observed_only=True):.2%}",
            f"{total_ratio(power, truth):.3f} / {total_ratio(only, truth, observed_only=True):.3f}"]


def _headline_cell(res) -> str:
    h = headline_of(res)
    return f"{h.photons:.4g}" if h.reason is None else f"{h.photons:.4g} over well-observed (see below)"


def _total_summary(per_pose, joint, todo, sigmas: dict | None = None) -> list[str]:
    """The number the mission is about: the total per pose and jointly, with its spread and,
    from the error budget (``sigmas``: its label -> 1 sd in photons), its σ."""
    sigmas = sigmas or {}
    tot = np.array([np.nansum(r.power) for r, _ in per_pose])
    well = np.array([np.nansum(np.where(r.well_observed, r.power, 0.0)) for r, _ in per_pose])

    def pm(label: str) -> str:
        s = sigmas.get(label, np.nan)
        return f" ± {s:.2g}" if np.isfinite(s) else ""

    lines = []
    for (r, _), (_, pt), t, w in zip(per_pose, todo, tot, well):
        h, what = headline_of(r), f"pose {pt.pose.label}"
        lines.append(h.line(f"total flux, {what}") + (f"; observed total {t:.4g}{pm(what)} photons" if pm(what) else "")
                     if h.reason else
                     f"total flux, {what}: {t:.4g}{pm(what)} photons over observed elements ({w:.4g} over well-observed)")
    if len(tot) > 1:
        if tot.mean() > 0:
            lines.append(f"total flux over {len(tot)} poses: mean {tot.mean():.4g} photons, spread (max-min)/mean "
                         f"{(tot.max() - tot.min()) / tot.mean():.1%}, sd/mean {tot.std(ddof=1) / tot.mean():.1%}")
        else:  # no light anywhere: a spread relative to nothing means nothing
            lines.append(f"total flux over {len(tot)} poses: mean {tot.mean():.4g} photons "
                         "(no spread: no pose found light)")
    if joint is not None:
        h, what, t = headline_of(joint), "all poses jointly", np.nansum(joint.power)
        lines.append(h.line(f"total flux, {what}") + (f"; observed total {t:.4g}{pm(what)} photons" if pm(what) else "")
                     if h.reason else
                     f"total flux, {what}: {t:.4g}{pm(what)} photons over observed elements "
                     f"({np.nansum(np.where(joint.well_observed, joint.power, 0.0)):.4g} over well-observed)")
    return lines

