"""reconstruction.h5 (kind ``reconstruction``): the container ``fluxmap reconstruct`` fills, its writer and reader.

:class:`Reconstruction` holds every group of the file as typed records whose fields say
their unit and meaning; :func:`write` lays them out in one fixed order (the same bytes for
the same run), :func:`read` gives back what the summary, report and outputs read.  The
schema that ``open_artefact`` checks is :mod:`fluxcli.artefacts.kinds` (``reconstruction``).
Parts with writers of their own (the error budget, regions of interest) come as callables
that write their group.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import h5py
import numpy as np

from ..errors import UserError
from .digest import seal
from .pieces import write_surface
from .store import Provenance, open_artefact, write_artefact

KIND = "reconstruction"
FILENAME = "reconstruction.h5"
# every group and dataset reconstruct writes: every reader refuses a file changed after writing
SEALED = ("flux", "per_pose", "rois", "surface", "truth", "filters", "fit", "budget", "emission", "geometry", "sweep",
          "warnings")


@dataclass
class Headline:
    """The total to read first (fluxcli.inverse.methods.headline_total)."""

    photons: float  # photons over ``over``
    over: str  # "observed elements" or "well-observed elements"
    reason: str | None  # why it is over well-observed elements (None: it is not)


@dataclass
class Flux:
    """/flux: one solve on the elements (the joint one, else the first pose's)."""

    result: object  # inverse.Result: power (photons per element, NaN unobserved), observed, sigma (photons, 1 sd), ...
    headline: Headline  # /flux/headline_total
    areas_mm2: np.ndarray  # (n_elements,) mm²: exitance = power / area


@dataclass
class Geometry:
    """/geometry: what the report draws besides the flux, so that it reads artefacts only."""

    axis_point_mm: np.ndarray  # (3,) mm: a point of the subject's rotation axis
    axis_direction: np.ndarray  # (3,) unit: the rotation axis
    camera_look: np.ndarray  # (3,) unit: where the camera looks
    camera_up: np.ndarray  # (3,) unit: the camera's up
    view_names: list  # the camera views (direct, mirrors)
    T_files: list  # per pose, T's cache file relative to the artefact's folder
    image_files: list  # image files relative to the artefact's folder (empty: not image files)


@dataclass
class PerPose:
    """/per_pose: each pose solved on its own [pose, ...]."""

    power: np.ndarray  # [pose, element] photons
    sigma: np.ndarray  # [pose, element] photons (1 sd)
    observed: np.ndarray  # [pose, element] bool
    total: list  # [pose] photons over observed elements
    lam: list  # [pose] regularisation used (None: none)
    vertices_mm: np.ndarray  # [pose, vertex, 3] mm: the surface placed at each pose
    backprojection_total: list  # [pose] a.u.: sum of T'a (not a flux)
    direct_roi_photons: list  # [pose] photons summed over the pixels the direct view reaches
    heights_mm: list  # [pose] mm stage height
    rotations_deg: list  # [pose] deg rotation
    chi2_per_pixel: list = field(default_factory=list)  # [pose] χ² per pixel under the noise model
    headline: list = field(default_factory=list)  # [pose] Headline
    observation: np.ndarray | None = None  # [pose, element] 0 unobserved, 1 poorly, 2 well observed


@dataclass
class Fit:
    """/fit: the images and the model's, [pose, row, col] photons."""

    measured: np.ndarray  # photons
    fitted: np.ndarray  # photons, T b (NaN where not fitted)
    valid: np.ndarray  # bool: pixels used (finite, not saturated, no isolated spike)


@dataclass
class Truth:
    """/truth: the simulated truth at the reconstructed level and the errors against it."""

    power: np.ndarray  # (n_elements,) photons
    error_per_pose: list  # [pose] L1 error (paper Eq. 15), dimensionless
    total_ratio_per_pose: list  # [pose] reconstructed / true total
    attrs: dict  # error, total_ratio and their observed / well-observed variants, in write order


@dataclass
class Emission:
    """/emission and the grazing-angle checks in /per_pose (issue 21)."""

    model: str  # subject.emission's model
    description: str  # what it means, in words
    refractive_index: float  # NaN: not a diffuse model
    table_file: str  # a tabulated profile's file ('' none)
    angle_deg: np.ndarray  # deg from the normal
    relative_radiance: np.ndarray  # L(theta) / L(0)
    bands_deg: np.ndarray  # deg: the grazing bands
    light_beyond_deg: np.ndarray  # [pose, band] share of the model image's light from beyond each angle
    total_beyond_deg: np.ndarray  # [pose, band] share of the total resting on views beyond each angle
    residual_vs_angle: np.ndarray  # [pose, 2] relative residual change per 10 deg and its t (NaN: not testable)
    joint_light_beyond_deg: np.ndarray | None = None  # [band] all poses jointly
    joint_total_beyond_deg: np.ndarray | None = None  # [band] all poses jointly


@dataclass
class SweepRecord:
    """/sweep: the study's errors error[method, level, pose, repeat] (paper Eq. 15)."""

    error: np.ndarray  # dimensionless, NaN where not run
    max_snr: np.ndarray  # [level, pose] the simulation's peak SNR
    levels_peak_photons: np.ndarray  # [level] photons at the brightest pixel
    methods: list  # each method described
    seconds: float  # run time (NaN under SOURCE_DATE_EPOCH)


@dataclass
class FilterRecord:
    """/filters/<name>: one filter's reconstruction, before the filter (divided by its transmission)."""

    name: str
    transmission: float  # dimensionless
    source: str  # where its images came from
    flux: Flux  # the joint solve, else the first pose's
    per_pose_power: np.ndarray  # [pose, element] photons
    per_pose_total: list  # [pose] photons
    direct_roi_photons: list  # [pose] measured photons (through the filter) over the direct view's pixels
    truth_power: np.ndarray | None  # photons before the filter (None: no truth)
    write_rois: Callable | None  # writes its /rois group (None: no regions)
    rate_exposure_s: float | None = None  # s: what makes this filter's rates (its own frames'); None: per exposure


@dataclass
class Reconstruction:
    """Everything reconstruction.h5 holds, in the order it is written."""

    config_sha256: str  # the config's sha256
    T_keys: list  # per pose, T's cache key
    images_source: str  # where the images came from, in words
    provenance: Provenance  # the config and geometry, with the input files
    inputs_digest: str  # the artefact is up to date when a run would compute this digest
    surface: object  # the elements' surface (fluxcli.surface.Surface)
    geometry: Geometry
    flux: Flux
    joint_over_poses: bool  # /flux is the joint solve over the poses
    per_pose: PerPose
    fit: Fit
    method: str  # reconstruct.method
    rate_exposure_s: float | None  # s: what makes rates (None: per exposure)
    rate_exposure_source: str  # "capture.h5 frames", "config" or "none"
    settings: dict  # the method settings as used (unknowns resolved)
    lambda_used: float | None  # λ of /flux
    seconds: float  # s of solving (NaN under SOURCE_DATE_EPOCH)
    truth: Truth | None
    emission: Emission
    warnings: list  # every solve's warnings, labelled
    write_budget: Callable  # writes /budget (fluxcli.stages.budget.write)
    totals_summary: list  # the console's total lines (an up-to-date rerun says them again)
    sweep: SweepRecord | None = None
    write_rois: Callable | None = None  # writes /rois (None: no regions)
    filters: list | None = None  # [FilterRecord], the first the one of /flux (None: one filter)


def _write_flux(g: h5py.Group, x: Flux) -> None:
    res = x.result
    g.create_dataset("power", data=res.power).attrs["unit"] = "photons per element (NaN: unobserved)"
    g.create_dataset("exitance", data=res.power / x.areas_mm2).attrs["unit"] = "photons mm^-2"
    g.create_dataset("observed", data=res.observed)
    g.create_dataset("sigma", data=res.sigma).attrs["unit"] = "photons (1 sd)"
    g.create_dataset("total", data=np.nansum(res.power)).attrs["unit"] = "photons over observed elements"
    # issue 8: what the data pin down, what they barely see, and what went wrong — in the artefact
    well = res.well_observed
    g.create_dataset("observation", data=res.observation).attrs["meaning"] = \
        "0 unobserved, 1 poorly observed (tiny sensitivity next to its neighbours, or sigma >= value), 2 well observed"
    g.create_dataset("well_observed", data=well)
    g.create_dataset("total_well_observed", data=np.nansum(np.where(well, res.power, 0.0))).attrs["unit"] = \
        "photons over well-observed elements"
    g.create_dataset("total_poorly_observed", data=np.nansum(np.where(res.observed & ~well, res.power, 0.0))
                     ).attrs["unit"] = "photons over poorly observed elements"
    # issue 25: the number to read first; the total over observed elements when it is pinned down
    h = x.headline
    d = g.create_dataset("headline_total", data=h.photons)
    d.attrs["unit"] = f"photons over {h.over}"
    d.attrs["over"] = h.over
    d.attrs["reason"] = h.reason or ""
    g.attrs["chi2_per_pixel"] = res.chi2_per_pixel
    g.attrs["converged"] = res.converged
    g.attrs["iterations"] = res.iterations
    g.attrs["lambda"] = res.lam
    g.attrs["warnings"] = json.dumps(list(res.warnings))


def _write_geometry(g: h5py.Group, x: Geometry) -> None:
    g.attrs["axis_point_mm"] = np.asarray(x.axis_point_mm, float)
    g.attrs["axis_direction"] = np.asarray(x.axis_direction, float)
    g.attrs["camera_look"] = np.asarray(x.camera_look, float)
    g.attrs["camera_up"] = np.asarray(x.camera_up, float)
    g.attrs["view_names"] = json.dumps(list(x.view_names))
    g.attrs["T_files"] = json.dumps(list(x.T_files))
    g.attrs["image_files"] = json.dumps(list(x.image_files))


def _write_per_pose(pp: h5py.Group, x: PerPose) -> None:
    pp.create_dataset("power", data=x.power).attrs["unit"] = "photons"
    pp.create_dataset("sigma", data=x.sigma).attrs["unit"] = "photons"
    pp.create_dataset("observed", data=x.observed)
    pp.create_dataset("total", data=x.total).attrs["unit"] = "photons"
    pp.create_dataset("lambda", data=x.lam)
    pp.create_dataset("vertices_mm", data=x.vertices_mm,
                      compression="gzip").attrs["meaning"] = "the surface placed at each pose (faces as /surface/faces)"
    pp.create_dataset("backprojection_total", data=x.backprojection_total).attrs["unit"] = \
        "a.u.: sum of T'a (photons weighted by the dimensionless T; not a flux)"
    pp.create_dataset("direct_roi_photons", data=x.direct_roi_photons
                      ).attrs["meaning"] = "measured photons summed over the pixels the direct view reaches"
    pp.create_dataset("heights_mm", data=x.heights_mm)
    pp.create_dataset("rotations_deg", data=x.rotations_deg)


def _write_fit(fit: h5py.Group, x: Fit) -> None:
    fit.create_dataset("measured", data=x.measured.astype(np.float32), compression="gzip").attrs["unit"] = "photons"
    fit.create_dataset("fitted", data=x.fitted.astype(np.float32), compression="gzip").attrs["unit"] = "photons"
    fit.create_dataset("residual", data=(x.measured - x.fitted).astype(np.float32), compression="gzip")
    fit.create_dataset("valid", data=x.valid, compression="gzip")


def _write_emission(f: h5py.File, x: Emission) -> None:
    g = f.create_group("emission")
    g.attrs["model"] = x.model
    g.attrs["description"] = x.description
    g.attrs["refractive_index"] = x.refractive_index
    g.attrs["table_file"] = x.table_file
    g.create_dataset("angle_deg", data=x.angle_deg)
    g.create_dataset("relative_radiance", data=x.relative_radiance).attrs["meaning"] = "L(theta) / L(0)"
    pp = f["per_pose"]
    pp.create_dataset("light_beyond_deg", data=x.light_beyond_deg).attrs["bands_deg"] = x.bands_deg
    pp["light_beyond_deg"].attrs["meaning"] = "share of the model image's light that left the surface beyond each angle"
    pp.create_dataset("total_beyond_deg", data=x.total_beyond_deg).attrs["bands_deg"] = x.bands_deg
    pp["total_beyond_deg"].attrs["meaning"] = ("share of the reconstructed total resting on views beyond each angle "
                                               "(each element weighted by the share of its collected light from there)")
    pp.create_dataset("residual_vs_angle", data=x.residual_vs_angle).attrs["meaning"] = \
        "relative residual change per 10 deg of emission angle, and its t value (NaN: not testable)"
    if x.joint_light_beyond_deg is not None:
        g.create_dataset("joint_light_beyond_deg", data=x.joint_light_beyond_deg)
        g.create_dataset("joint_total_beyond_deg", data=x.joint_total_beyond_deg)


def _write_sweep(g: h5py.Group, x: SweepRecord) -> None:
    err = x.error
    reps = err.shape[3]
    g.create_dataset("error", data=err).attrs["layout"] = "error[method, level, pose, repeat] (paper Eq. 15)"
    g.create_dataset("mean", data=np.nanmean(err, axis=3))
    g.create_dataset("sd", data=np.nanstd(err, axis=3, ddof=1) if reps > 1 else np.zeros(err.shape[:3]))
    g.create_dataset("max_snr", data=x.max_snr)
    g.create_dataset("levels_peak_photons", data=x.levels_peak_photons)
    g.attrs["methods"] = json.dumps(list(x.methods))
    g.attrs["seconds"] = x.seconds


def _write_filters(g: h5py.Group, filters: list) -> None:
    g.attrs["order"] = json.dumps([x.name for x in filters])
    g.attrs["meaning"] = "the light leaving the surface within each filter's band, before the filter (divided by its transmission)"
    for x in filters:
        h = g.create_group(x.name)
        h.attrs["transmission"] = x.transmission
        h.attrs["source"] = x.source
        if x.rate_exposure_s is not None:
            h.attrs["rate_exposure_s"] = float(x.rate_exposure_s)
        _write_flux(h.create_group("flux"), x.flux)
        h.create_dataset("per_pose_power", data=x.per_pose_power).attrs["unit"] = "photons"
        h.create_dataset("per_pose_total", data=x.per_pose_total).attrs["unit"] = "photons"
        h.create_dataset("direct_roi_photons", data=x.direct_roi_photons
                         ).attrs["meaning"] = "measured photons (through the filter) summed over the pixels the direct view reaches"
        if x.truth_power is not None:
            h.create_dataset("truth_power", data=x.truth_power).attrs["unit"] = "photons (before the filter)"
        if x.write_rois is not None:
            x.write_rois(h.create_group("rois"))


def write(path: Path, r: Reconstruction) -> Path:
    """Write ``r`` to ``path`` atomically (it appears only when complete), sealed."""
    with write_artefact(path, KIND, config_sha256=r.config_sha256,
                        inputs={"T": json.dumps(list(r.T_keys)), "images": r.images_source},
                        provenance=r.provenance) as f:
        f.attrs["inputs_digest"] = r.inputs_digest
        write_surface(f.create_group("surface"), r.surface)
        _write_geometry(f.create_group("geometry"), r.geometry)
        g = f.create_group("flux")
        _write_flux(g, r.flux)
        g.attrs["joint_over_poses"] = r.joint_over_poses
        _write_per_pose(f.create_group("per_pose"), r.per_pose)
        _write_fit(f.create_group("fit"), r.fit)
        f.attrs["method"] = r.method
        # the exposure that makes rates (photons/s), fixed here: summary, report and the VTP read it
        # from this file, and refuse a config that later states another (a published rate must not move)
        f.attrs["rate_exposure_s"] = float(r.rate_exposure_s) if r.rate_exposure_s is not None else np.nan
        f.attrs["rate_exposure_source"] = r.rate_exposure_source
        f.attrs["settings"] = json.dumps(r.settings)
        f.attrs["lambda_used"] = float(r.lambda_used) if r.lambda_used is not None else np.nan
        f.attrs["seconds"] = r.seconds
        if r.truth is not None:
            t = f.create_group("truth")
            t.create_dataset("power", data=r.truth.power)
            t.create_dataset("error_per_pose", data=r.truth.error_per_pose)
            t.create_dataset("total_ratio_per_pose", data=r.truth.total_ratio_per_pose)
            for k, v in r.truth.attrs.items():
                t.attrs[k] = v
        _write_emission(f, r.emission)
        f.create_dataset("warnings", data=np.array(r.warnings, dtype=object), dtype=h5py.string_dtype())
        r.write_budget(f.create_group("budget"))
        f.attrs["totals_summary"] = json.dumps(r.totals_summary)
        pp = f["per_pose"]
        pp.create_dataset("chi2_per_pixel", data=r.per_pose.chi2_per_pixel)
        heads = r.per_pose.headline
        pp.create_dataset("headline_total", data=[h.photons for h in heads]).attrs["unit"] = \
            "photons: the total over observed elements, or over well-observed ones where headline_reason says why"
        pp.create_dataset("headline_reason", data=np.array([h.reason or "" for h in heads], dtype=object),
                          dtype=h5py.string_dtype())
        pp.create_dataset("observation", data=r.per_pose.observation)
        if r.sweep is not None:
            _write_sweep(f.create_group("sweep"), r.sweep)
        if r.write_rois is not None:
            r.write_rois(f.create_group("rois"))
        if r.filters:
            _write_filters(f.create_group("filters"), r.filters)
        seal(f, SEALED)
    return path


# the numbers /rois holds per region and map, one dataset each [roi, map]
ROI_NUMBER_KEYS = ("total_photons_per_s", "sigma_photons_per_s", "mean_radiance", "peak_radiance", "area_mm2",
                   "observed_share", "well_observed_share")


def write_rois(g: h5py.Group, regions, labels: list[str], exposure_s: float | None, numbers, members) -> None:
    """``/rois`` of reconstruction.h5: one column per number, [roi, map] (``regions``: the ROIs in order;
    ``labels``: the maps measured; ``numbers[map][roi]``: what was measured; ``members[map]``: [roi, element])."""
    g.attrs["names"] = json.dumps([r.name for r in regions])
    g.attrs["definitions"] = json.dumps([{k: v for k, v in r.__dict__.items() if v is not None} for r in regions])
    g.attrs["maps"] = json.dumps(labels)
    g.attrs["exposure_s"] = exposure_s if exposure_s is not None else np.nan
    g.attrs["frame"] = "the subject at rest (before any pose): element centroids, area-weighted"
    g.attrs["radiance"] = "Lambertian radiance L = M / pi of the exitance M, photons s^-1 cm^-2 sr^-1"
    g.attrs["sigma"] = "sqrt(w' C w) from the reconstruction's covariance (linear approximation), not a sum of per-element sigma"
    units = {"total_photons_per_s": "photons/s" if exposure_s is not None else "photons per exposure",
             "sigma_photons_per_s": "photons/s (1 sd)" if exposure_s is not None else "photons per exposure (1 sd)",
             "mean_radiance": "photons s^-1 cm^-2 sr^-1", "peak_radiance": "photons s^-1 cm^-2 sr^-1",
             "area_mm2": "mm^2", "observed_share": "of the area", "well_observed_share": "of the area"}
    assert tuple(units) == ROI_NUMBER_KEYS
    for key, unit in units.items():
        d = g.create_dataset(key, data=np.array([[getattr(numbers[m][i], key) for m in range(len(labels))]
                                                 for i in range(len(regions))], float).reshape(len(regions), -1))
        d.attrs["unit"] = unit
    g.create_dataset("status", data=np.array([[numbers[m][i].status for m in range(len(labels))]
                                             for i in range(len(regions))], dtype=object),
                     dtype=h5py.string_dtype())
    g.create_dataset("members", data=np.array(members, bool).transpose(1, 0, 2), compression="gzip"
                     ).attrs["layout"] = "members[roi, map, element]"



def write_budget(g: h5py.Group, b) -> None:
    """``/budget``: per total (poses, then joint) its σ by cause (``b``: fluxcli.stages.budget.Budget)."""
    g.attrs["meaning"] = ("1 sd of each total (photons per exposure) by cause: photon noise sqrt(w'Cw); "
                          "regularisation max |t(lambda/2) - t|, |t(2 lambda) - t|; calibration sqrt(sum_i delta_i^2 "
                          "+ (t gain_relative)^2) with delta_i the total's change when T is rebuilt with parameter i "
                          "moved by +1 sd (same lambda); sigma = the three in quadrature (NaN: not computed)")
    g.attrs["labels"] = json.dumps([t.label for t in b.totals])
    g.attrs["t_builds"] = b.t_builds
    g.attrs["gain_relative"] = b.gain_relative if b.gain_relative is not None else np.nan
    g.attrs["parameters"] = json.dumps([{"name": n, "sigma": s, "unit": u} for n, s, u in b.parameters])
    for key in ("total", "sigma_noise", "sigma_regularisation", "sigma_calibration", "sigma"):
        g.create_dataset(key, data=np.array([getattr(t, key) for t in b.totals], float)).attrs["unit"] = "photons"
    if b.parameters:
        g.create_dataset("deltas", data=np.array([[t.deltas.get(n, np.nan) for n, _, _ in b.parameters]
                                                  for t in b.totals], float)).attrs["layout"] = "deltas[total, parameter] photons"
    if b.roi_names:
        r = g.create_group("rois")
        r.attrs["names"] = json.dumps(b.roi_names)
        r.attrs["layout"] = "[roi, total] in the order of /budget/labels (poses, then joint); photons per exposure"
        r.create_dataset("sigma_regularisation", data=b.roi_sigma_regularisation).attrs["unit"] = "photons"
        r.create_dataset("sigma_calibration", data=b.roi_sigma_calibration).attrs["unit"] = "photons"
    if b.shifts:
        g.create_dataset("shift_px", data=np.array([[s.dx_px, s.dy_px] for s in b.shifts], float)).attrs["meaning"] = \
            "per pose: the shift (x, y pixels) of the fitted image that best explains the residual"
        g.create_dataset("shift_z", data=np.array([s.z for s in b.shifts], float)).attrs["meaning"] = \
            f"per pose: |shift| in units of its standard error; {b.shifts[0].RULE}"
        g.create_dataset("shift_flank_z", data=np.array([s.flank_z or (np.nan, np.nan) for s in b.shifts], float)
                         ).attrs["meaning"] = ("per pose: the shift along its direction as each flank of the image "
                                               "alone sees it (where the image brightens along it, then where it "
                                               "darkens), in that flank's standard error; NaN: not asked")


# ------------------------------------------------------------------ reading
def read_rois(g: h5py.Group) -> dict:
    """``/rois`` (as :func:`write_rois` wrote it) as plain data: names, definitions, maps (pose
    numbers and 'joint'), exposure_s (None: per exposure), numbers[key] (n_roi, n_maps) for each
    of :data:`ROI_NUMBER_KEYS`, status (n_roi, n_maps) and members (n_roi, n_maps, n_elements) bool."""
    t = float(g.attrs.get("exposure_s", np.nan))
    return {"names": json.loads(g.attrs["names"]), "maps": json.loads(g.attrs["maps"]),
            "definitions": json.loads(g.attrs.get("definitions", "[]")),
            "exposure_s": t if np.isfinite(t) else None,
            "numbers": {k: g[k][()] for k in ROI_NUMBER_KEYS},
            "status": np.array([[x.decode() if isinstance(x, bytes) else str(x) for x in row] for row in g["status"][()]]),
            "members": g["members"][()].astype(bool)}


def read_budget(g: h5py.Group) -> dict:
    """``/budget`` (as :func:`write_budget` wrote it) as plain lists (photons per exposure; NaN:
    not computed)."""
    out = {"labels": json.loads(g.attrs["labels"]), "t_builds": int(g.attrs.get("t_builds", 0)),
           "parameters": json.loads(g.attrs.get("parameters", "[]")),
           "gain_relative": float(g.attrs.get("gain_relative", np.nan))}
    for key in ("total", "sigma_noise", "sigma_regularisation", "sigma_calibration", "sigma"):
        out[key] = np.asarray(g[key][()], float).tolist()
    if "rois" in g:
        out["rois"] = {"names": json.loads(g["rois"].attrs["names"]),
                       "sigma_regularisation": g["rois/sigma_regularisation"][()].tolist(),
                       "sigma_calibration": g["rois/sigma_calibration"][()].tolist()}
    if "shift_z" in g:
        out["shift_z"] = g["shift_z"][()].tolist()
        out["shift_px"] = g["shift_px"][()].tolist()
        if "shift_flank_z" in g:  # written since the flank test (older files: absent)
            out["shift_flank_z"] = g["shift_flank_z"][()].tolist()
    return out


def up_to_date_summary(path: Path) -> list[str]:
    """The total lines an up-to-date reconstruction said when it was made."""
    with open_artefact(path, KIND) as f:
        return json.loads(f.attrs.get("totals_summary", "[]"))


@dataclass
class Summary:
    """What ``fluxmap summary`` reads of a reconstruction."""

    heights_mm: np.ndarray  # [pose] mm
    rotations_deg: np.ndarray  # [pose] deg
    direct_roi_photons: np.ndarray | None  # [pose] photons (None: not recorded)
    totals: np.ndarray  # [pose] photons over observed elements
    headline_total: np.ndarray  # [pose] photons: the total to read first
    headline_reason: list  # [pose] why it is over well-observed elements ('' not)
    pose_observed: np.ndarray  # [pose, element] bool
    pose_well_observed: np.ndarray  # [pose, element] bool: the elements of a headline over well-observed ones
    power: np.ndarray  # [element] photons of /flux, NaN unobserved
    joint_over_poses: bool  # /flux is the joint solve
    truth: np.ndarray | None  # [element] photons (None: no truth)
    error: float | None  # L1 error of /flux against the truth
    budget: dict | None  # /budget (read_budget)
    rois: dict | None  # /rois (read_rois)


def read_summary(path: Path) -> Summary:
    """The summary's view of reconstruction.h5."""
    with open_artefact(path, KIND) as f:
        pp = f["per_pose"]
        totals = pp["total"][()]
        truth = f["truth/power"][()] if "truth" in f else None
        return Summary(
            heights_mm=pp["heights_mm"][()], rotations_deg=pp["rotations_deg"][()],
            direct_roi_photons=pp["direct_roi_photons"][()] if "direct_roi_photons" in pp else None,
            totals=totals,
            # issue 25: where the observed total is not pinned down, the headline is over well-observed elements
            headline_total=pp["headline_total"][()] if "headline_total" in pp else totals,
            headline_reason=[w.decode() if isinstance(w, bytes) else str(w) for w in pp["headline_reason"][()]]
            if "headline_reason" in pp else [""] * len(totals),
            pose_observed=pp["observed"][()].astype(bool),
            pose_well_observed=pp["observation"][()] == 2 if "observation" in pp else pp["observed"][()].astype(bool),
            power=np.where(f["flux/observed"][()].astype(bool), f["flux/power"][()], np.nan),
            joint_over_poses=bool(f["flux"].attrs.get("joint_over_poses", False)),
            truth=truth,
            error=float(f["truth"].attrs["error"]) if truth is not None and "error" in f["truth"].attrs else None,
            budget=read_budget(f["budget"]) if "budget" in f else None,
            rois=read_rois(f["rois"]) if "rois" in f else None)


def recorded_exposure(path: Path) -> tuple[float, str] | None:
    """(rate_exposure_s, its source) as reconstruct recorded them (NaN s: none); None before they were recorded."""
    with open_artefact(path, KIND) as f:
        if "rate_exposure_s" not in f.attrs:
            return None
        return float(f.attrs["rate_exposure_s"]), str(f.attrs.get("rate_exposure_source", "reconstruct"))


@dataclass
class Maps:
    """What the 3-D export (``reconstruction.vtp``) reads: the maps on the surface."""

    surface: object  # the elements' surface
    power: np.ndarray  # [element] photons of /flux, NaN unobserved
    observed: np.ndarray  # [element] bool: seen by some camera view
    sigma: np.ndarray | None  # [element] photons (1 sd), NaN unobserved
    truth: np.ndarray | None  # [element] photons
    pose_power: np.ndarray | None  # [pose, element] photons
    pose_observed: np.ndarray | None  # [pose, element] bool
    method: str  # reconstruct.method
    joint_over_poses: bool  # /flux is the joint solve
    rois: dict | None  # /rois (read_rois)
    per_filter: dict  # filter -> [element] photons before the filter, NaN unobserved
    headline: tuple | None  # (photons, over, reason) of /flux/headline_total


def read_maps(path: Path) -> Maps:
    """The maps of reconstruction.h5 for the 3-D export."""
    from .pieces import read_surface

    with open_artefact(path, KIND) as f:
        fl = f["flux"]
        observed = fl["observed"][()].astype(bool)
        pp = f["per_pose"] if "per_pose" in f else None
        rois = None
        if "rois" in f:  # one cell array per region of interest (the last map's: joint, or the only pose)
            rois = read_rois(f["rois"])
        per_filter = {}
        if "filters" in f:  # several filters in one reconstruct: each filter's map
            for name in json.loads(f["filters"].attrs["order"]):
                fo = f[f"filters/{name}/flux"]
                per_filter[name] = np.where(fo["observed"][()].astype(bool), fo["power"][()], np.nan)
        head = fl["headline_total"] if "headline_total" in fl else None
        return Maps(
            surface=read_surface(f["surface"]), power=np.where(observed, fl["power"][()], np.nan), observed=observed,
            sigma=np.where(observed, fl["sigma"][()], np.nan) if "sigma" in fl else None,
            truth=f["truth/power"][()] if "truth" in f and "power" in f["truth"] else None,
            pose_power=pp["power"][()] if pp is not None and "power" in pp else None,
            pose_observed=pp["observed"][()].astype(bool) if pp is not None and "observed" in pp else None,
            method=str(f.attrs.get("method", "")), joint_over_poses=bool(fl.attrs.get("joint_over_poses", False)),
            rois=rois, per_filter=per_filter,
            headline=(float(head[()]), str(head.attrs.get("over", "")), str(head.attrs.get("reason", "")))
            if head is not None else None)


def read_filters(path: Path) -> list[dict]:
    """Each filter of a run that reconstructed several (none: []), in order: name, transmission,
    headline total (photons per exposure, before the filter), what it is over, and the exposure
    that makes its rates (s; None: not recorded)."""
    with open_artefact(path, KIND) as f:
        if "filters" not in f:
            return []
        out = []
        for name in json.loads(f["filters"].attrs["order"]):
            h = f[f"filters/{name}"]
            head = h["flux/headline_total"]
            t = h.attrs.get("rate_exposure_s")
            out.append({"name": name, "transmission": float(h.attrs["transmission"]), "total": float(head[()]),
                        "over": str(head.attrs.get("over", "")), "exposure_s": float(t) if t is not None else None})
        return out


def read_roi_spectrum(path: Path) -> tuple[dict | None, dict]:
    """/rois (None: no regions) and, when several filters were reconstructed, filter ->
    (transmission, that filter's /rois)."""
    with open_artefact(path, KIND) as f:
        if "rois" not in f:
            return None, {}
        spectrum = {}
        if "filters" in f:
            for name in json.loads(f["filters"].attrs["order"]):
                if "rois" in f[f"filters/{name}"]:
                    spectrum[name] = (float(f[f"filters/{name}"].attrs["transmission"]),
                                      read_rois(f[f"filters/{name}/rois"]))
        return read_rois(f["rois"]), spectrum


def read_provenance(path: Path) -> Provenance:
    """The config, geometry and input files reconstruction.h5 was made from."""
    from .store import read_provenance as _read

    with open_artefact(path, KIND) as f:
        return _read(f)


@dataclass
class StudyView:
    """What ``fluxmap study`` reads of one session's reconstruction.h5."""

    unchanged: bool | None  # results still match their recorded digest (None: none recorded)
    provenance: Provenance  # config, geometry and input files (with their sha256)
    has_rois: bool  # the file holds regions of interest
    heights_mm: np.ndarray  # [pose] mm
    rotations_deg: np.ndarray  # [pose] deg
    parts: list  # per filter: (filter, /rois as read_rois gives it, truth power [element] photons or None,
    #             direct_roi_photons [pose] photons); ``filter_name`` for a file of one filter


def read_for_study(path: Path, filter_name: str) -> StudyView:
    """The session's numbers, one part per filter of the artefact (``filter_name``: the study
    file's filter, for a file of one filter)."""
    from .digest import unchanged
    from .store import read_provenance as _read

    with open_artefact(path, KIND) as f:
        same, prov, has_rois = unchanged(f), _read(f), "rois" in f
        if not same or not has_rois:  # the caller refuses it, saying why: read nothing more
            return StudyView(same, prov, has_rois, np.zeros(0), np.zeros(0), [])
        try:
            pp = f["per_pose"]
            parts = [(filter_name, read_rois(f["rois"]),
                      f["truth/power"][()] if "truth" in f and "power" in f["truth"] else None,
                      pp["direct_roi_photons"][()])]
            if "filters" in f:  # one reconstruct of several filters: a part per filter
                parts = [(name, read_rois(h["rois"]), h["truth_power"][()] if "truth_power" in h else None,
                          h["direct_roi_photons"][()])
                         for name in json.loads(f["filters"].attrs["order"])
                         for h in [f[f"filters/{name}"]] if "rois" in h]
            heights, rotations = pp["heights_mm"][()], pp["rotations_deg"][()]
        except (KeyError, json.JSONDecodeError) as e:  # sealed as it is, yet not what reconstruct writes
            raise UserError(f"artefact {path} lacks what a study reads ({e}); it was not written by this fluxmap's "
                            "reconstruct. Reconstruct it again.") from None
        return StudyView(same, prov, has_rois, heights, rotations, parts)


def read_warnings(path: Path) -> tuple[list[str], int | None]:
    """The warnings reconstruct stored (/warnings) and the number of poorly observed elements
    (/flux/observation == 1; None where the file does not hold them)."""
    out, poor = [], None
    with open_artefact(path, KIND) as f:
        if "warnings" in f:
            out = [w.decode() if isinstance(w, bytes) else str(w) for w in np.atleast_1d(f["warnings"][()])]
        if "flux" in f and "observation" in f["flux"]:
            poor = int(np.sum(f["flux/observation"][()] == 1))
    return out, poor
