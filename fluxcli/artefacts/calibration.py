"""The ``calibration`` artefact (``<workdir>/calibration.h5``, made by ``fluxmap calibrate``): the
fitted camera (every parameter with its 1 sigma), per-image detections, residuals and blur,
the refined mirrors, the radiometric maps and photon-transfer series, the projectors.

:class:`Calibration` is what the stage fills and :func:`write` stores; :func:`read` gives the
report a :class:`CalibrationRecord` back.  The only code that touches the file's layout (the
``/radiometric`` maps that reconstruct reads are :mod:`fluxcli.artefacts.radiometric`'s).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from .digest import seal
from .store import Provenance, open_artefact, write_artefact

KIND = "calibration"
FILE_NAME = "calibration.h5"  # in the workdir
YAML_NAME = "camera.yaml"  # beside it: the camera block another config takes in one line
RADIOMETRIC_GROUP = "radiometric"
MAPS = {  # dataset name in /radiometric -> unit
    "bias_counts_map": "counts",
    "dark_e_per_s_map": "electrons/s per pixel",
    "flat_map": "relative response, mean 1",
}
SCALARS = {  # attribute of /radiometric -> unit
    "electrons_per_count": "electrons/count",
    "em_gain": "1",
    "em_gain_from_ratio": "1",
    "em_gain_from_ptc": "1",
    "read_noise_counts": "counts rms",
    "read_noise_e": "electrons rms",
    "bias_counts": "counts",
    "dark_current_e_per_s": "electrons/s per pixel",
    "cic_e_per_pixel": "electrons per pixel per frame",
}


@dataclass
class Geometric:
    """The geometric fit and the images it came from."""

    fit: object  # fluxcli.calibration.fit.GeometricCalibration: camera, f, u, aperture, sigma, per-image detections
    grid: dict  # calibrate.grid as JSON: kind, pitch_mm, shape, ...
    labels: list[str]  # per image: the file, or the capture and its stage height
    images: list[np.ndarray]  # per image: counts [row, col] (stored as float32, gzip)


@dataclass
class Calibration:
    """What one ``fluxmap calibrate`` run stores (units in each part's own fields)."""

    camera_yaml: str  # the camera.yaml text written beside the artefact
    inputs_digest: str  # of calibrate, the camera, the mirrors and every input file: up to date when equal
    truth_errors: dict | None = None  # simulated rig: the fit's errors against the true camera (never used by it)
    geometric: Geometric | None = None
    mirrors: list = field(default_factory=list)  # fluxcli.calibration.mirrors.MirrorFit, one per system.mirrors
    radiometric: object | None = None  # fluxcli.calibration.radiometry.RadiometricResult
    projectors: list = field(default_factory=list)  # fluxcli.calibration.projectors.ProjectorFit


# what calibrate writes: the report, reconstruct's maps and the camera it describes rest on it, so
# a reader refuses it once edited (a file of other tools with only /radiometric has no seal)
SEALED = ("camera_yaml", "geometric", "mirrors", "radiometric", "projectors")


def write(path: Path, cal: Calibration, *, config_sha256: str, provenance: Provenance) -> Path:
    """Write ``cal`` to ``path`` atomically (the layout the readers and kinds.py expect)."""
    with write_artefact(path, KIND, config_sha256=config_sha256, provenance=provenance) as f:
        f.attrs["inputs_digest"] = cal.inputs_digest
        if cal.truth_errors is not None:  # simulated rig: how far the calibration is from the camera that made the frames
            f.attrs["truth_errors"] = json.dumps(cal.truth_errors)
        f.create_dataset("camera_yaml", data=cal.camera_yaml)
        if cal.geometric is not None:
            g = cal.geometric
            _write_geometric(f.create_group("geometric"), g.fit, g.grid, g.labels, g.images)
        if cal.mirrors:
            _write_mirrors(f.create_group("mirrors"), cal.mirrors)
        if cal.radiometric is not None:
            write_radiometric(f.create_group(RADIOMETRIC_GROUP), cal.radiometric)
        if cal.projectors:
            _write_projectors(f.create_group("projectors"), cal.projectors)
        seal(f, SEALED)
    return path


def _write_geometric(g, geo, grid: dict, labels: list[str], images) -> None:
    c = geo.camera
    g.create_dataset("lens_center_mm", data=c.center_mm).attrs["unit"] = "mm"
    g.create_dataset("rotation", data=c.rotation)
    for name, value, unit in (("image_distance_mm", c.image_distance_mm, "mm"),
                              ("focal_length_mm", geo.focal_length_mm, "mm"),
                              ("focus_distance_mm", geo.focus_distance_mm, "mm"),
                              ("focus_distance_from_measure_mm", geo.focus_distance_from_measure_mm, "mm"),
                              ("focal_plane_z_mm", geo.focal_plane_z_mm, "mm"),
                              ("aperture_diameter_mm", geo.aperture_diameter_mm, "mm"),
                              ("dot_diameter_mm", geo.dot_diameter_mm, "mm"),
                              ("rms_px", geo.rms_px, "px"), ("rms_mm", geo.rms_mm, "mm"),
                              ("pixel_pitch_mm", c.pixel_pitch_mm, "mm")):
        g.attrs[name] = float(value)
        g.attrs[f"{name}_unit"] = unit
    g.attrs["pixels"] = np.array([c.nx, c.ny])
    g.attrs["grid"] = json.dumps(grid)
    g.attrs["warnings"] = json.dumps(geo.warnings)
    sg = g.create_group("sigma")
    for k, v in geo.sigma.items():
        sg.attrs[k] = float(v)
    if geo.blur is not None:
        b = g.create_group("blur_fit")
        for k in ("focus_distance_mm", "focus_distance_sigma_mm", "k_px_mm", "k_sigma", "floor_px", "rms_px"):
            b.attrs[k] = float(getattr(geo.blur, k))
        b.attrs["model"] = "D_px = hypot(k_px_mm * (1/z - 1/u), floor_px), z axial distance (mm)"
    if geo.focus is not None:
        fc = g.create_group("focus_fit")
        fc.attrs["params"] = geo.focus.params
        fc.attrs["model"] = "F = p0 + p1 / (1 + ((1/z - p2) / p3)^2), z mean axial distance (mm)"
        fc.attrs["focus_distance_mm"] = geo.focus.focus_distance_mm
    ims = g.create_group("images")
    for k, im in enumerate(geo.images):
        h = ims.create_group(str(k))
        h.attrs["plane_z_mm"] = im.plane_z_mm
        h.attrs["file"] = labels[k]
        h.attrs["focus_measure"] = im.focus_measure
        h.attrs["notes"] = json.dumps(im.notes)
        h.create_dataset("image", data=np.asarray(images[k], np.float32), compression="gzip", shuffle=True)
        for name, arr, unit in (("ij", im.ij, ""), ("xy_px", im.xy_px, "px (col, row), pixel centres at integers"),
                                ("residual_px", im.residual_px, "px, measured - model"),
                                ("residual_mm", im.residual_mm, "mm on the grid plane"),
                                ("blur_diameter_px", im.blur_diameter_px, "px"), ("axial_mm", im.axial_mm, "mm")):
            h.create_dataset(name, data=arr).attrs["unit"] = unit


def _write_mirrors(g, mirrors: list) -> None:
    for k, m in enumerate(mirrors):
        h = g.create_group(str(k))
        h.create_dataset("center_mm", data=m.center_mm).attrs["unit"] = "mm"
        h.create_dataset("normal", data=m.normal)
        h.attrs["rms_px"] = m.rms_px
        h.attrs["n_points"] = m.n_points
        h.attrs["normal_sigma_deg"] = m.normal_sigma_deg
        h.attrs["offset_sigma_mm"] = m.offset_sigma_mm


def _write_projectors(g, fits: list) -> None:
    for k, fit in enumerate(fits):
        h = g.create_group(str(k))
        r = fit.result
        h.attrs["name"] = fit.name
        h.attrs["block"] = json.dumps(fit.block)
        h.attrs["rms_px"] = r.rms_px
        h.attrs["rejected"] = r.rejected
        h.attrs["gamma_measured"] = fit.gamma_measured
        h.attrs["heights_mm"] = np.asarray(fit.heights_mm, float)
        h.attrs["valid_fraction"] = np.asarray(fit.valid_fraction, float)
        for name, arr, unit in (("points_mm", r.points_mm, "mm, world"), ("uv_px", r.uv_px, "projector px, measured"),
                                ("residual_px", r.residual_px, "projector px, measured - model"),
                                ("plane", r.plane, "index into heights_mm")):
            h.create_dataset(name, data=arr).attrs["unit"] = unit
        if fit.truth is not None:
            h.attrs["truth"] = json.dumps(fit.truth)


def write_radiometric(group: h5py.Group, result) -> None:
    """Store ``result`` in ``group`` (normally ``/radiometric`` of calibration.h5).

    Layout: attributes ``<name>`` and ``<name>_sigma`` for each scalar (``SCALARS``, NaN
    when not measured) with ``<name>_unit``; datasets ``bias_counts_map``,
    ``dark_e_per_s_map``, ``flat_map`` when measured (attribute ``unit``); one subgroup
    per PTC series in ``ptc/`` with datasets ``exposure_s``, ``mean_counts``,
    ``variance_counts2``, ``variance_sigma_counts2``, ``n_pixels`` and scalar datasets
    ``slope_counts``, ``intercept_counts2`` (and their ``*_sigma*``), ``em_gain_on``;
    attribute ``warnings`` (JSON list) and ``sensor_block`` (JSON).
    """
    for name, unit in SCALARS.items():
        value, sigma = getattr(result, name), getattr(result, f"{name}_sigma")
        group.attrs[name] = np.nan if value is None else float(value)
        group.attrs[f"{name}_sigma"] = np.nan if sigma is None else float(sigma)
        group.attrs[f"{name}_unit"] = unit
    group.attrs["excess_noise_factor_squared"] = float(result.excess_noise_factor_squared)
    group.attrs["warnings"] = json.dumps(result.warnings)
    group.attrs["sensor_block"] = json.dumps(result.sensor_block())
    for name, unit in MAPS.items():
        arr = getattr(result, name)
        if arr is not None:
            group.create_dataset(name, data=np.asarray(arr, dtype=np.float64), compression="gzip").attrs["unit"] = unit
    ptc = group.create_group("ptc")
    for name, s in result.ptc.items():
        g = ptc.create_group(name)
        for key, unit in (("exposure_s", "s"), ("mean_counts", "counts above bias"),
                          ("variance_counts2", "counts^2"), ("variance_sigma_counts2", "counts^2 (1 sigma)"),
                          ("n_pixels", "pixels")):
            g.create_dataset(key, data=getattr(s, key)).attrs["unit"] = unit
        g.create_dataset("illumination", data=np.array(s.illumination, dtype=h5py.string_dtype()))
        for key in ("slope_counts", "slope_sigma_counts", "intercept_counts2", "intercept_sigma_counts2",
                    "reduced_chi2"):
            g.create_dataset(key, data=float(getattr(s, key)))
        g.create_dataset("em_gain_on", data=bool(s.em_gain_on))


# ------------------------------------------------------------------ reading it back (the report)
@dataclass
class ImageRecord:
    """One grid image's detections as stored."""

    plane_z_mm: float  # world z of the grid plane
    xy_px: np.ndarray  # (n, 2) detected points, px (col, row), pixel centres at integers
    residual_px: np.ndarray  # (n, 2) measured - model, px
    axial_mm: np.ndarray  # (n,) axial distance of each point from the lens, mm
    blur_diameter_px: np.ndarray  # (n,) fitted blur diameter, px
    focus_measure: float  # the image's sharpness measure
    image: np.ndarray | None  # counts [row, col], when stored


@dataclass
class GeometricRecord:
    """``/geometric``: the fitted camera as stored."""

    values: dict[str, float]  # focal_length_mm, focus_distance_mm, aperture_diameter_mm, image_distance_mm, rms_px,
    #                           rms_mm, focal_plane_z_mm, ... (mm or px, as named)
    lens_center_mm: list[float]
    sigma: dict[str, float]  # 1 sigma of each fitted parameter (unit as named)
    warnings: list[str]
    pixels: tuple[int, int]  # (nx, ny)
    images: list[ImageRecord]
    blur_fit: dict | None  # D_px = hypot(k_px_mm * (1/z - 1/u), floor_px)
    focus_params: np.ndarray | None  # F = p0 + p1 / (1 + ((1/z - p2) / p3)^2)


@dataclass
class RadiometricRecord:
    """``/radiometric``: the scalars (NaN: not measured), the maps and the photon-transfer series."""

    scalars: dict[str, float]  # SCALARS' names (units there) -> value
    maps: dict[str, np.ndarray]  # MAPS' names (units there) that were measured
    ptc: dict[str, dict[str, np.ndarray]]  # series name -> exposure_s, mean_counts, variance_counts2, ...


@dataclass
class ProjectorRecord:
    """``/projectors/<k>``: one projector's fit."""

    name: str
    block: dict  # its rig.projectors block (pixels, focal_px, principal_px, distortion, gamma, pose)
    heights_mm: list[float]  # board heights
    valid_fraction: list[float]  # per height: fraction of camera pixels decoded in both directions
    rms_px: float  # reprojection RMS, projector px
    rejected: int  # board points left out of the fit
    gamma_measured: bool
    uv_px: np.ndarray  # (n, 2) measured projector coordinates, px
    residual_px: np.ndarray  # (n, 2) measured - model, projector px
    plane: np.ndarray  # (n,) index into heights_mm
    truth: dict | None  # simulated: the true block and the fit's errors


@dataclass
class CalibrationRecord:
    camera_yaml: str
    geometric: GeometricRecord | None
    radiometric: RadiometricRecord | None
    projectors: list[ProjectorRecord]


_GEOMETRIC_VALUES = ("focal_length_mm", "focus_distance_mm", "aperture_diameter_mm", "image_distance_mm", "rms_px",
                     "rms_mm", "focal_plane_z_mm")


def read(path: Path) -> CalibrationRecord:
    """The calibration artefact at ``path`` as the report shows it (a file with only some groups is fine)."""
    with open_artefact(path, KIND) as f:
        text = f["camera_yaml"][()]
        text = text.decode() if isinstance(text, bytes) else str(text)
        geo = rad = None
        if "geometric" in f:
            g = f["geometric"]
            ims = [g["images"][k] for k in sorted(g["images"], key=int)]
            geo = GeometricRecord(
                {k: float(g.attrs[k]) for k in _GEOMETRIC_VALUES}, g["lens_center_mm"][()].tolist(),
                {k: float(v) for k, v in g["sigma"].attrs.items()}, json.loads(g.attrs["warnings"]),
                tuple(int(x) for x in g.attrs["pixels"]),
                [ImageRecord(float(h.attrs["plane_z_mm"]), h["xy_px"][()], h["residual_px"][()], h["axial_mm"][()],
                             h["blur_diameter_px"][()], float(h.attrs["focus_measure"]),
                             h["image"][()] if "image" in h else None) for h in ims],
                dict(g["blur_fit"].attrs) if "blur_fit" in g else None,
                g["focus_fit"].attrs["params"] if "focus_fit" in g else None)
        if RADIOMETRIC_GROUP in f:
            r = f[RADIOMETRIC_GROUP]
            rad = RadiometricRecord({k: r.attrs[k] for k in SCALARS if k in r.attrs},
                                    {k: r[k][()] for k in MAPS if k in r},
                                    {name: {k: r["ptc"][name][k][()] for k in r["ptc"][name]} for name in r["ptc"]})
        projectors = []
        if "projectors" in f:
            for k in sorted(f["projectors"], key=int):
                h = f["projectors"][k]
                projectors.append(ProjectorRecord(
                    str(h.attrs["name"]), json.loads(h.attrs["block"]), [float(x) for x in h.attrs["heights_mm"]],
                    [float(x) for x in h.attrs["valid_fraction"]], float(h.attrs["rms_px"]), int(h.attrs["rejected"]),
                    bool(h.attrs["gamma_measured"]), h["uv_px"][()], h["residual_px"][()], h["plane"][()],
                    json.loads(h.attrs["truth"]) if "truth" in h.attrs else None))
    return CalibrationRecord(text, geo, rad, projectors)
