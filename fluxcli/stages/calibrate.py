"""``fluxmap calibrate CONFIG``: the camera model from grid images (and the sensor from radiometric frames).

Examples
--------
$ fluxmap calibrate configs/calibrate.yaml

Writes ``<workdir>/calibration.h5`` (every fitted parameter with its 1-sigma uncertainty,
per-image detections, residuals and blur, the radiometric maps) and
``<workdir>/camera.yaml``, whose top-level ``camera:`` block is a valid ``system.camera``
(and ``mirrors:`` a valid ``system.mirrors`` when mirrors were refined, ``projectors:`` a
valid ``rig.projectors`` mapping when ``calibrate.projectors`` is given).  Another config
then uses it in one line: ``system: {camera: <workdir>/camera.yaml}`` (``rig: {projectors:
<workdir>/camera.yaml}``).

Projectors (``calibrate.projectors``): frames of a flat board at known heights while each
projector shows column and row codes (files, or made by the simulated rig into
``<workdir>/projector_frames/``), decoded, and fitted against the camera this run
calibrated (Moreno & Taubin's local homographies: :mod:`fluxcli.structured.calibrate`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import yaml

from .. import artefacts as A
from .. import config as C
from ..artefacts import calibration as AC
from ..calibration.fit import BLUR_WARN_PX, CalibrationError, GeometricCalibration, calibrate_geometry
from ..calibration.mirrors import MirrorFit, refine_mirrors
from ..errors import UserError
from ..hardware.projector import projector_model
from ..imaging.imagefiles import read_image
from ..pipeline import provenance
from ..structured import calibrate as SC
from ._radiometric import radiometric_from_capture, run_radiometric, section_files
from .context import RunContext



def run(cfg: C.LoadedConfig, ctx: RunContext) -> Path:
    sec = cfg.model.calibrate
    system = cfg.model.system
    cam = system.camera if system is not None else None
    out = cfg.workdir / "calibration.h5"
    yaml_out = cfg.workdir / "camera.yaml"
    capture_path = cfg.resolve(sec.capture) if sec.capture is not None else None
    if capture_path is not None and not capture_path.is_file():
        raise UserError(f"calibrate.capture: {capture_path} does not exist; take the calibration frames first with "
                        "'fluxmap capture-surface CONFIG' (capture.calibration).")
    image_paths = [cfg.resolve(im.file) for im in sec.images]
    for k, p in enumerate(image_paths):
        if not p.is_file():
            raise UserError(f"calibrate.images[{k}].file: image file {p} does not exist.")
    rad_paths = [cfg.resolve(p) for p in section_files(sec.radiometric)] if sec.radiometric is not None else []
    frame_paths = _projector_frame_paths(cfg, sec)
    prov = provenance(cfg)
    for k, p in enumerate(image_paths):
        prov.add_file(f"calibrate.images[{k}]", p)
    for key, paths in frame_paths.items():
        for k, p in enumerate(paths):
            prov.add_file(f"{key}[{k}]", p)
    for k, p in enumerate(rad_paths):
        if p.is_file():
            prov.add_file(f"calibrate.radiometric[{k}]", p)
    if capture_path is not None:
        prov.add_file("calibrate.capture", capture_path)
    digest = A.inputs_digest(calibrate=sec.model_dump(mode="json"),
                             camera=cam.model_dump(mode="json") if cam is not None else None,
                             mirrors=[m.model_dump(mode="json") for m in system.mirrors] if system is not None else [],
                             files={n: d["sha256"] for n, d in prov.input_files.items()})
    if not ctx.force and A.is_up_to_date(out, "calibration", digest) and yaml_out.is_file():
        ctx.say(f"calibrate: {out} is up to date (use --force to redo)")
        return out

    geo, images = None, []
    mirrors: list[MirrorFit] = []
    shape = (cam.pixels[1], cam.pixels[0]) if cam is not None else None
    src = _from_capture(capture_path, sec, shape) if capture_path is not None else _from_files(cfg, sec, image_paths)
    if src.grid is not None:
        if cam is None:
            raise UserError(f"config {cfg.path}: 'calibrate' with a grid needs 'system.camera' with pixels and "
                            "pixel_pitch_mm (the lens and pose are what it measures).")
        images = src.read_images(cam)
        geo = _geometric(src, cam, images, ctx)
        if system.mirrors and sec.refine_mirrors:
            mirrors = _mirrors(src, system, geo, images, ctx)
    projectors = _projectors(cfg, sec, cam, geo, frame_paths, ctx) if sec.projectors else []
    rad = None
    if sec.radiometric is not None:
        rad = run_radiometric(sec.radiometric, cfg.resolve, ctx, expected_shape=shape)
    elif src.capture is not None and src.capture.bias is not None:
        rad = radiometric_from_capture(src.capture, ctx, bit_depth=cam.sensor.bit_depth if cam is not None else 16)
    truth_errors = None
    if src.capture is not None and src.capture.truth is not None:
        truth_errors = _truth_report(src.capture, geo, rad, ctx)

    text = camera_yaml(cam, geo, rad, mirrors, system, projectors)
    if geo is not None and not (np.isfinite(geo.aperture_diameter_mm) and geo.aperture_diameter_mm > 0) and (
            cam.lens is None):
        ctx.say("calibrate: warning: the aperture was not measured (a checkerboard gives no per-dot blur); "
                "camera.yaml's lens has no aperture: add f_number or aperture_diameter_mm to it before use")
    AC.write(out, AC.Calibration(text, digest, truth_errors,
                                 AC.Geometric(geo, src.grid.model_dump(mode="json"), src.labels, images)
                                 if geo is not None else None, mirrors, rad, projectors),
             config_sha256=cfg.sha256, provenance=prov)
    A.write_text(yaml_out, text)
    ctx.say(f"calibrate: camera written to {yaml_out} (use it as  system: {{camera: {yaml_out}}})")
    return out


def _truth_report(cal, geo: GeometricCalibration | None, rad, ctx: RunContext) -> dict:
    """The simulated rig's true camera against what was measured (said and stored, never used by the fit)."""
    true = C.Camera.model_validate(cal.truth["camera"])
    errors: dict = {}
    if geo is not None and true.lens is not None and true.pose is not None:
        errors["focal_length_relative"] = geo.focal_length_mm / true.lens.focal_length_mm - 1
        errors["lens_center_mm"] = float(np.linalg.norm(geo.camera.center_mm - np.array(true.pose.lens_center_mm)))
        look = np.array(true.pose.look) / np.linalg.norm(true.pose.look)
        errors["look_deg"] = float(np.degrees(np.arccos(np.clip(geo.camera.look @ look, -1, 1))))
        ctx.say(f"calibrate: against the simulated rig's true camera: f {errors['focal_length_relative']:+.3%}, "
                f"lens centre {errors['lens_center_mm']:.3f} mm off, axis {errors['look_deg']:.3f} deg")
    if rad is not None:
        s = true.sensor
        errors["electrons_per_count_relative"] = rad.electrons_per_count / s.electrons_per_count - 1
        msg = f"electrons per count {errors['electrons_per_count_relative']:+.2%}"
        gains = [g for _, _, g in cal.ptc if g > 1.0]
        if rad.em_gain is not None and gains:  # the simulated register multiplies by the gain it was set to
            errors["em_gain_relative"] = rad.em_gain / gains[0] - 1
            msg += f", EM gain {errors['em_gain_relative']:+.2%} (set to {gains[0]:g})"
        ctx.say(f"calibrate: against the simulated rig's true sensor: {msg}")
    return errors


# ------------------------------------------------------------------ geometric
@dataclass
class GridSource:
    """Where the grid frames (and, from a capture, the radiometric frames) come from."""

    grid: C.CalibrationGrid | None
    heights_mm: list[float]  # world z of the grid plane in each image
    labels: list[str]  # per image: the file, or the capture and its stage height
    keys: list[str]  # per image: the config key to name in a message
    files: list[Path] | None = None  # image files (calibrate.images)
    capture: "CalibrationCapture | None" = None  # or the capture's calibration frames

    def read_images(self, cam: C.Camera) -> list[np.ndarray]:
        nx, ny = cam.pixels
        if self.capture is not None:
            imgs = self.capture.grid_images
            if imgs and imgs[0].shape != (ny, nx):
                raise UserError(f"calibrate.capture: the grid frames of {self.capture.path} are {imgs[0].shape[1]} x "
                                f"{imgs[0].shape[0]} pixels but system.camera.pixels is [{nx}, {ny}]; describe the "
                                "camera at the binning the frames were taken at.")
            return [np.asarray(im, float) for im in imgs]
        images = []
        for k, p in enumerate(self.files):
            try:
                img, _ = read_image(p)
            except (ValueError, OSError) as e:
                raise UserError(f"calibrate.images[{k}].file: {e}") from None
            if img.shape != (ny, nx):
                raise UserError(f"calibrate.images[{k}].file: {p} is {img.shape[1]} x {img.shape[0]} pixels but "
                                f"system.camera.pixels is [{nx}, {ny}]; give images of the camera being calibrated "
                                "(same binning) or correct system.camera.pixels.")
            if not np.issubdtype(img.dtype, np.number):
                raise UserError(f"calibrate.images[{k}].file: {p} does not hold numbers.")
            images.append(img.astype(float))
        return images


def _from_files(cfg, sec: C.Calibrate, paths: list[Path]) -> GridSource:
    return GridSource(sec.grid, [im.plane_z_mm for im in sec.images], [str(p) for p in paths],
                      [f"calibrate.images[{k}]" for k in range(len(paths))], files=paths)


def _from_capture(path: Path, sec: C.Calibrate, shape) -> GridSource:
    """The calibration frames of ``path``: the grid (its description from the capture unless
    calibrate.grid is given) at the plane heights the read-back stage heights give."""
    from ..acquisition import read_calibration

    cal = read_calibration(path)
    if cal.grid is None and cal.bias is None:
        raise UserError(f"calibrate.capture: {path} holds neither grid frames nor bias and photon-transfer frames: "
                        "nothing to calibrate (capture.calibration.grid, or .bias and .ptc).")
    if cal.grid is None and sec.grid is not None:
        raise UserError(f"calibrate.grid: the capture {path} holds no grid frames (capture.calibration.grid was not "
                        "set); leave calibrate.grid out for a radiometric calibration from it.")
    grid = sec.grid
    if grid is None and cal.grid is not None:
        grid = C.CalibrationGrid(kind=cal.grid["kind"], pitch_mm=cal.grid["pitch_mm"], shape=tuple(cal.grid["shape"]))
    heights = cal.grid_plane_z_mm() if grid is not None else []
    labels = [f"{path} (stage at {h:.4g} mm)" for h in cal.grid_stage_mm]
    keys = [f"calibrate.capture, grid frames at stage height {h:.4g} mm" for h in cal.grid_stage_mm]
    return GridSource(grid, heights, labels, keys, capture=cal)


def _geometric(src: GridSource, cam: C.Camera, images: list[np.ndarray], ctx: RunContext) -> GeometricCalibration:
    g = src.grid
    try:
        geo = calibrate_geometry(images, src.heights_mm, kind=g.kind, pitch_mm=g.pitch_mm, shape=tuple(g.shape),
                                 pixel_pitch_mm=cam.pixel_pitch_mm)
    except CalibrationError as e:
        where = f"{src.keys[e.image]} ({src.labels[e.image]}): " if e.image is not None else "calibrate: "
        raise UserError(where + str(e) + _hint(e)) from None
    _summary(geo, ctx)
    return geo


def _hint(e: CalibrationError) -> str:
    msg = str(e)
    if "does not match shape" in msg:
        return " Check calibrate.grid.shape (points along x, then along y)."
    if "no " in msg and "grid" in msg:
        return " Check calibrate.grid.kind and that the grid is in the image, lit and not saturated."
    if "plane_z_mm" in msg:
        return " Check calibrate.images[].plane_z_mm against the files."
    return ""


def _summary(geo: GeometricCalibration, ctx: RunContext) -> None:
    c = geo.camera
    s = geo.sigma
    rows = [
        ["focal_length_mm", geo.focal_length_mm, s["focal_length_mm"]],
        ["focus_distance_mm (u)", geo.focus_distance_mm, s["focus_distance_mm"]],
        ["focal plane z (mm)", geo.focal_plane_z_mm, s["focus_distance_mm"]],
        ["aperture_diameter_mm", geo.aperture_diameter_mm, s["aperture_diameter_mm"]],
        ["image distance v (mm)", c.image_distance_mm, s["image_distance_mm"]],
        ["lens centre x (mm)", float(c.center_mm[0]), s["lens_center_x_mm"]],
        ["lens centre y (mm)", float(c.center_mm[1]), s["lens_center_y_mm"]],
        ["lens centre z (mm)", float(c.center_mm[2]), s["lens_center_z_mm"]],
        ["axis tilt from -z (deg)", float(np.degrees(np.arccos(np.clip(-c.look[2], -1, 1)))), s["look_deg"]],
        ["RMS reprojection (px)", geo.rms_px, None],
        ["RMS reprojection (mm)", geo.rms_mm, None],
    ]
    ctx.table(["quantity", "value", "1 sigma"], [[a, float(b), "-" if e is None else float(e)] for a, b, e in rows])
    for im in geo.images:
        for n in im.notes:
            ctx.say(f"calibrate: z={im.plane_z_mm:g} mm: {n}")
    for w in geo.warnings:
        ctx.say(f"calibrate: warning: {w}")


# ------------------------------------------------------------------ mirrors
def _mirrors(src: GridSource, system: C.System, geo: GeometricCalibration, images, ctx) -> list[MirrorFit]:
    g = src.grid
    heights = src.heights_mm
    fits = []
    for k, m in enumerate(system.mirrors):
        try:
            fit = refine_mirrors(images, heights, geo.camera, center_mm=np.array(m.center_mm), normal=np.array(m.normal),
                                 axis=np.array(m.axis), size_mm=tuple(m.size_mm), pitch_mm=g.pitch_mm,
                                 shape=tuple(g.shape))
        except ValueError as e:
            raise UserError(f"system.mirrors[{k}]: the grid could not be used in this mirror's view: {e}") from None
        fits.append(fit)
        ctx.say(f"calibrate: mirror {m.name or f'mirror{k}'}: {fit.n_points} points, RMS {fit.rms_px:.3f} px; "
                f"normal moved {fit.normal_change_deg:.2f} deg, plane moved {fit.offset_change_mm:.2f} mm")
        for w in fit.warnings:
            ctx.say(f"calibrate: warning: mirror {k}: {w}")
    return fits


# ------------------------------------------------------------------ camera.yaml
def _r(x, nd=6):
    return [round(float(v), nd) for v in x] if np.ndim(x) else round(float(x), nd)


SENSOR_MEASURED = ("electrons_per_count", "read_noise_e", "bias_counts", "em_gain", "dark_current_e_per_s",
                   "cic_e_per_pixel")  # what a radiometric calibration can measure (RadiometricResult names)


def _given(cam: C.Camera, key: str, where: str) -> str:
    """Where a value that was not measured comes from: the config, or fluxmap's default."""
    if key in cam.assumed:  # a camera.yaml of an earlier calibration said so
        return cam.assumed[key]
    sensor = key in C.Sensor.model_fields
    if sensor and key not in cam.sensor.model_fields_set:
        value = getattr(C.Sensor(), key)
        hint = " set from the camera's datasheet" if key in ("quantum_efficiency", "bit_depth") else \
            " measure it (calibrate with bias, dark and photon-transfer frames) or set it from the datasheet"
        return f"fluxmap default {value:g}, not measured —{hint}"
    path = f"system.camera.{'sensor.' if sensor else ''}{key}"
    return f"given in the config ({path}{where}), not measured"


def camera_block(cam: C.Camera, geo: GeometricCalibration | None, rad) -> dict:
    """The ``camera:`` block: valid as ``system.camera``, every value marked measured or assumed.

    ``measured`` maps each measured value (``lens.focal_length_mm``, ``sensor.em_gain``, ...) to
    its 1 sigma (same unit); ``assumed`` maps each other value to where it comes from;
    ``uncertainty`` is the 1-sigma block the reconstruction propagates (``system.camera.uncertainty``:
    focal_length_mm, focus_distance_mm, aperture_diameter_mm, lens_center_mm [x, y, z],
    look_deg, gain_relative: the relative 1 sigma of photons per count, K / (G QE), without QE's)."""
    block: dict = {"pixels": [int(cam.pixels[0]), int(cam.pixels[1])], "pixel_pitch_mm": float(cam.pixel_pitch_mm)}
    measured: dict = {}
    assumed: dict = {"pixels": _given(cam, "pixels", ": the frames' size agrees"),
                     "pixel_pitch_mm": _given(cam, "pixel_pitch_mm", ": the sensor's pixel pitch x binning")}
    unc: dict = {}
    if geo is not None:
        c, sg = geo.camera, geo.sigma
        lens = {"focal_length_mm": _r(geo.focal_length_mm), "focus_distance_mm": _r(geo.focus_distance_mm)}
        measured["lens.focal_length_mm"] = _r(sg["focal_length_mm"], 9)
        measured["lens.focus_distance_mm"] = _r(sg["focus_distance_mm"], 9)
        unc["focal_length_mm"] = measured["lens.focal_length_mm"]
        unc["focus_distance_mm"] = measured["lens.focus_distance_mm"]
        fitted = np.isfinite(geo.aperture_diameter_mm) and geo.aperture_diameter_mm > 0
        given = {k: v for k, v in (cam.lens.model_dump().items() if cam.lens is not None else ())
                 if k in ("f_number", "aperture_diameter_mm") and v is not None}
        if fitted and (geo.aperture_resolved or not given):
            lens["aperture_diameter_mm"] = _r(geo.aperture_diameter_mm)
            measured["lens.aperture_diameter_mm"] = unc["aperture_diameter_mm"] = _r(sg["aperture_diameter_mm"], 9)
        else:  # not measured, or the dots blur too little to trust it (it comes out low): keep the config's
            why = (f": the dots blur < {BLUR_WARN_PX:g} px, so the fitted {geo.aperture_diameter_mm:.3g} mm is not "
                   "trusted" if fitted else ": a checkerboard gives no per-dot blur")
            for k, v in given.items():
                lens[k] = v
                assumed[f"lens.{k}"] = _given(cam, f"lens.{k}", why)
        block["lens"] = lens
        block["pose"] = {"lens_center_mm": _r(c.center_mm), "look": _r(c.look, 9), "up": _r(c.up, 9)}
        centre = _r([sg["lens_center_x_mm"], sg["lens_center_y_mm"], sg["lens_center_z_mm"]], 9)
        measured["pose.lens_center_mm"] = unc["lens_center_mm"] = centre
        measured["pose.look_deg"] = unc["look_deg"] = _r(sg["look_deg"], 9)
        measured["pose.up_deg"] = _r(sg["roll_deg"], 9)  # the in-plane rotation about the axis
    else:
        if cam.lens is not None:
            block["lens"] = cam.lens.model_dump(exclude_none=True)
            assumed["lens"] = _given(cam, "lens", "")
        if cam.pose is not None:
            block["pose"] = cam.pose.model_dump(mode="json")
            assumed["pose"] = _given(cam, "pose", "")
    if cam.apertures:
        block["apertures"] = [a.model_dump() for a in cam.apertures]
        assumed["apertures"] = _given(cam, "apertures", ": measured by hand")
    if rad is not None:
        sens = cam.sensor.model_dump()
        got = rad.sensor_block()
        sens.update(got)
        block["sensor"] = sens
        for k in sens:
            if k in got:
                sigma = getattr(rad, f"{k}_sigma", None)
                measured[f"sensor.{k}"] = _r(sigma, 9) if sigma is not None and np.isfinite(sigma) else None
            else:
                assumed[k] = _given(cam, k, "")
        rel = [rad.electrons_per_count_sigma / rad.electrons_per_count]
        if rad.em_gain is not None and rad.em_gain_sigma is not None:
            rel.append(rad.em_gain_sigma / rad.em_gain)
        unc["gain_relative"] = _r(float(np.hypot.reduce(rel)), 9)
    if unc:
        block["uncertainty"] = unc
    block["measured"] = {k: v for k, v in measured.items() if v is not None}
    block["assumed"] = assumed
    return block


def camera_yaml(cam: C.Camera | None, geo: GeometricCalibration | None, rad,
                mirrors: list[MirrorFit], system: C.System | None, projectors: list | None = None) -> str:
    """The YAML text: ``camera:`` valid as ``system.camera`` (geometric and radiometric results in
    one block, see :func:`camera_block`), ``mirrors:`` valid as ``system.mirrors``,
    ``projectors:`` valid as ``rig.projectors`` (name -> optics and pose)."""
    doc: dict = {}
    if cam is not None:
        doc["camera"] = camera_block(cam, geo, rad)
    elif rad is not None:
        doc["sensor"] = rad.sensor_block()
    if mirrors and system is not None:
        out = []
        for m, fit in zip(system.mirrors, mirrors):
            d = m.model_dump(mode="json", exclude_none=True)
            d["center_mm"] = _r(fit.center_mm)
            d["normal"] = _r(fit.normal, 9)
            d["axis"] = _r(fit.axis, 9)
            for key in ("normal_sigma_deg", "offset_sigma_mm"):  # measured: 1 sigma of the refined plane
                if np.isfinite(getattr(fit, key)):
                    d[key] = _r(getattr(fit, key), 9)
            out.append(d)
        doc["mirrors"] = out
    if projectors:
        doc["projectors"] = {pf.name: pf.block for pf in projectors}
    head = ("# Written by `fluxmap calibrate`. Use it in any config in one line:\n"
            "#   system: {camera: path/to/camera.yaml}" + ("   (and  mirrors: path/to/camera.yaml)" if mirrors else "")
            + ("\n#   rig: {projectors: path/to/camera.yaml}   (the projectors; display keys beside file: {file: ..., NAME: {display: window}})" if projectors else "") + "\n")
    if cam is not None:
        head += ("# camera.measured: the 1 sigma of each measured value; camera.assumed: where each other value comes\n"
                 "# from; camera.uncertainty: the 1 sigma the reconstruction propagates into its totals (gain_relative:\n"
                 "# photons per count from electrons per count and EM gain; an assumed QE adds an error not in it).\n")
    if geo is not None:
        s = geo.sigma
        head += (f"# 1-sigma: f {s['focal_length_mm']:.3g} mm, u {s['focus_distance_mm']:.3g} mm, aperture "
                 f"{s['aperture_diameter_mm']:.3g} mm, lens centre ({s['lens_center_x_mm']:.3g}, "
                 f"{s['lens_center_y_mm']:.3g}, {s['lens_center_z_mm']:.3g}) mm, look {s['look_deg']:.3g} deg; "
                 f"RMS reprojection {geo.rms_px:.3f} px\n")
    if mirrors:
        head += ("# mirrors: their planes are measured (normal_sigma_deg, offset_sigma_mm: 1 sigma); size, axis "
                 "direction and reflectance are given in the config\n")
    for pf in projectors or []:
        head += (f"# projector {pf.name}: {len(pf.result.points_mm)} board points, RMS reprojection "
                 f"{pf.result.rms_px:.3f} projector px; gamma {'measured' if pf.gamma_measured else 'given'}\n")
    return head + yaml.dump(doc, Dumper=_NoAliases, sort_keys=False, default_flow_style=None, allow_unicode=True)


class _NoAliases(yaml.SafeDumper):
    """Writes a list used twice (uncertainty and measured) twice, not as an anchor and alias."""

    def ignore_aliases(self, data):
        return True


# ------------------------------------------------------------------ projectors
@dataclass
class ProjectorFit:
    """One projector's calibration: the fit, its ``rig.projectors`` block, and (simulated) the truth."""

    name: str
    result: "SC.ProjectorCalibrationResult"
    block: dict
    gamma_measured: bool
    heights_mm: list[float]
    valid_fraction: list[float]
    truth: dict | None = None  # simulated: the true projector's block and the fit's errors


def _projector_name(pc: C.ProjectorCalibration, k: int) -> str:
    return pc.name or f"projector{k}"


def _expand(cfg, spec, key: str) -> list[Path]:
    if isinstance(spec, str):
        import glob

        pattern = cfg.resolve(Path(spec))
        files = sorted(Path(f) for f in glob.glob(str(pattern)))
        if not files:
            raise UserError(f"{key}: the pattern {pattern} matches no file.")
        return files
    return [cfg.resolve(p) for p in spec]


def _projector_frame_paths(cfg, sec: C.Calibrate) -> dict[str, list[Path]]:
    """Every projector frame file the config names (simulated frames are made later), by config key."""
    from ..structured.patterns import column_patterns

    out = {}
    for k, pc in enumerate(sec.projectors):
        for i, im in enumerate(pc.images):
            for which, cells in (("columns", pc.pixels[0]), ("rows", pc.pixels[1])):
                key = f"calibrate.projectors[{k}].images[{i}].{which}"
                paths = _expand(cfg, getattr(im, which), key)
                for p in paths:
                    if not p.is_file():
                        raise UserError(f"{key}: frame file {p} does not exist.")
                n = len(column_patterns(cells, 1, period_px=pc.patterns.period_px, n_steps=pc.patterns.n_steps).frames)
                _check_count(paths, key, n)
                out[key] = paths
    return out


def _check_count(paths: list[Path], key: str, n_expected: int) -> None:
    if len(paths) != n_expected:
        raise UserError(f"{key}: {len(paths)} frame file(s) given, the pattern sequence has {n_expected} "
                        "(white, black, each Gray bit and its inverse, the phase steps; check "
                        "calibrate.projectors[].pixels and .patterns).")


def _projector_block(p) -> dict:
    return {"pixels": [int(p.width_px), int(p.height_px)], "focal_px": _r([p.fx_px, p.fy_px]),
            "principal_px": _r([p.cx_px, p.cy_px]), "distortion": _r([p.k1, p.k2], 8), "gamma": _r(p.gamma, 4),
            "pose": {"center_mm": _r(p.center_mm), "look": _r(p.axis, 9), "up": _r(-p.down, 9)}}


def _read_frames(paths: list[Path], key: str, n_expected: int, shape) -> np.ndarray:
    _check_count(paths, key, n_expected)
    out = []
    for p in paths:
        try:
            img, _ = read_image(p)
        except (ValueError, OSError) as e:
            raise UserError(f"{key}: {e}") from None
        if img.shape != shape:
            raise UserError(f"{key}: {p} is {img.shape[1]} x {img.shape[0]} pixels but system.camera.pixels is "
                            f"[{shape[1]}, {shape[0]}].")
        out.append(np.asarray(img, float))
    return np.stack(out)


def _simulated_frames(cfg, k: int, pc: C.ProjectorCalibration, ctx) -> list[tuple[float, list[Path], list[Path]]]:
    """Render the board at each height with the simulated rig; write the frames as 16-bit TIFF files."""
    from ..imaging.imagefiles import write_image
    from ..pipeline import emccd_model
    from ..scene import camera_from_config

    sim = pc.simulated
    if sim.camera.lens is None or sim.camera.pose is None:
        raise UserError(f"calibrate.projectors[{k}].simulated.camera: the true camera needs lens and pose.")
    name = _projector_name(pc, k)
    ctx.say(f"calibrate: projector {name}: rendering the board at {len(sim.heights_mm)} height(s) (simulated rig)")
    sensor = replace(emccd_model(sim.camera.sensor, sim.exposure_s), em_gain=sim.em_gain)
    frames = SC.simulate_board_frames(camera_from_config(sim.camera), projector_model(sim.projector),
                                      sim.heights_mm, board_size_mm=sim.board_size_mm, albedo=sim.albedo,
                                      period_px=pc.patterns.period_px, n_steps=pc.patterns.n_steps, sensor=sensor,
                                      photons_white=sim.photons_white, ambient_photons=sim.ambient_photons,
                                      lens_samples=sim.lens_samples, seed=sim.seed)
    folder = cfg.workdir / "projector_frames" / name
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for z, (cols, rows) in zip(sim.heights_mm, frames):
        paths = []
        for which, stack in (("columns", cols), ("rows", rows)):
            ps = [folder / f"z{z:+07.2f}_{which}_{i:03d}.tif" for i in range(len(stack))]
            for pth, im in zip(ps, stack):
                write_image(pth, im)
            paths.append(ps)
        out.append((float(z), paths[0], paths[1]))
    return out


def _projectors(cfg, sec: C.Calibrate, cam: C.Camera, geo: GeometricCalibration, frame_paths, ctx) -> list[ProjectorFit]:
    from ..calibration.geometry import grid_points_mm
    from ..structured.patterns import column_patterns, decode

    ny, nx = cam.pixels[1], cam.pixels[0]
    g = sec.grid
    ii, jj = np.meshgrid(np.arange(g.shape[0]), np.arange(g.shape[1]), indexing="ij")
    ij = np.c_[ii.ravel(), jj.ravel()]
    fits = []
    for k, pc in enumerate(sec.projectors):
        name = _projector_name(pc, k)
        w, h = pc.pixels
        cols = column_patterns(w, h, period_px=pc.patterns.period_px, n_steps=pc.patterns.n_steps)
        rows = SC.row_patterns(w, h, period_px=pc.patterns.period_px, n_steps=pc.patterns.n_steps)
        if pc.simulated is not None:
            sets = _simulated_frames(cfg, k, pc, ctx)
        else:
            sets = [(im.plane_z_mm, frame_paths[f"calibrate.projectors[{k}].images[{i}].columns"],
                     frame_paths[f"calibrate.projectors[{k}].images[{i}].rows"]) for i, im in enumerate(pc.images)]
        planes, gammas, valid_frac, heights = [], [], [], []
        for i, (z, cpaths, rpaths) in enumerate(sets):
            key = f"calibrate.projectors[{k}].images[{i}]" if pc.simulated is None else \
                f"calibrate.projectors[{k}].simulated (z={z:g} mm)"
            decoded = []
            for which, pats, paths in (("columns", cols, cpaths), ("rows", rows, rpaths)):
                f = _read_frames(paths, f"{key}.{which}", len(pats.frames), (ny, nx))
                contrast = f[0] - f[1]
                lit = contrast[contrast > 0]
                level = pc.min_contrast_fraction * (np.percentile(lit, 99) if len(lit) else 0.0)
                dec = decode(f, pats, min_contrast=level, width_px=w if which == "columns" else h)
                decoded.append(dec)
                if which == "columns" and pc.gamma is None:
                    ph = f[2 + 2 * pats.n_gray:]
                    gammas.append(SC.gamma_from_phase_frames(f[0], f[1], ph, dec.valid))
            X = grid_points_mm(ij, g.pitch_mm, tuple(g.shape), z)
            xy = geo.camera.project(X) + 0.5  # pixel centres at integers -> pixel (r, c) spans [c, c+1)
            inside = (xy[:, 0] >= 0) & (xy[:, 0] < nx) & (xy[:, 1] >= 0) & (xy[:, 1] < ny)
            planes.append((X[inside], xy[inside], decoded[0].column_px, decoded[1].column_px))
            valid_frac.append(float(np.mean(decoded[0].valid & decoded[1].valid)))
            heights.append(float(z))
        gamma_meas = [x for x in gammas if np.isfinite(x)]
        gamma = float(pc.gamma) if pc.gamma is not None else (float(np.median(gamma_meas)) if gamma_meas else 1.0)
        if pc.gamma is None and not gamma_meas:
            ctx.say(f"calibrate: warning: projector {name}: gamma could not be measured (too few decoded pixels); 1 assumed")
        try:
            res = SC.calibrate_projector(planes, width_px=w, height_px=h, gamma=gamma, half_window=pc.half_window_px)
        except ValueError as e:
            raise UserError(f"calibrate.projectors[{k}] ({name}): {e}; check that the board is lit by the projector "
                            "in the frames and that min_contrast_fraction is not too high.") from None
        fit = ProjectorFit(name, res, _projector_block(res.projector), bool(pc.gamma is None and gamma_meas),
                           heights, valid_frac)
        if pc.simulated is not None:
            fit.truth = _truth_errors(pc.simulated.projector, res.projector)
        fits.append(fit)
        _projector_summary(fit, ctx)
    return fits


def _truth_errors(true_cfg: C.ProjectorModel, fitted) -> dict:
    """The simulated projector's block and how far the fit is from it (reported, never used by the fit)."""
    from scipy.spatial.transform import Rotation

    t = projector_model(true_cfg)
    return {"block": _projector_block(t),
            "center_error_mm": float(np.linalg.norm(fitted.center_mm - t.center_mm)),
            "rotation_error_deg": float(np.degrees(Rotation.from_matrix(fitted.rotation @ t.rotation.T).magnitude())),
            "focal_error": float(fitted.fx_px / t.fx_px - 1), "gamma_error": float(fitted.gamma - t.gamma)}


def _projector_summary(fit: ProjectorFit, ctx) -> None:
    p, r = fit.result.projector, fit.result
    ctx.say(f"calibrate: projector {fit.name}: {len(r.points_mm)} board points on {len(fit.heights_mm)} heights "
            f"({r.rejected} rejected), RMS {r.rms_px:.3f} px; f ({p.fx_px:.1f}, {p.fy_px:.1f}) px, c ({p.cx_px:.1f}, "
            f"{p.cy_px:.1f}) px, k ({p.k1:.4f}, {p.k2:.4f}), gamma {p.gamma:.3f}"
            f"{' (measured)' if fit.gamma_measured else ''}, centre {np.round(p.center_mm, 2).tolist()} mm")
    if fit.truth is not None:
        t = fit.truth
        ctx.say(f"calibrate: projector {fit.name} against the simulated truth: centre {t['center_error_mm']:.3f} mm, "
                f"rotation {t['rotation_error_deg']:.3f} deg, fx {t['focal_error']:+.2%}, gamma {t['gamma_error']:+.3f}")
    if r.rms_px > 0.5:
        ctx.say(f"calibrate: warning: projector {fit.name}: RMS reprojection {r.rms_px:.2f} projector px > 0.5")
