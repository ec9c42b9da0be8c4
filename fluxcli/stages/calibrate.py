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

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydantic import ValidationError

from .. import artefacts as A
from .. import config as C
from ..artefacts import calibration as AC
from ..calibration.fit import CalibrationError, GeometricCalibration, calibrate_geometry
from ..calibration.mirrors import MirrorFit, MirrorFitError, refine_mirrors
from ..errors import UserError
from ..imaging.imagefiles import read_image
from ._calibrate_plan import CalibratePlan, plan_of  # noqa: F401
from ._calibrate_projectors import ProjectorFit, fit_projectors  # noqa: F401  (re-exported)
from ._camera_yaml import SENSOR_MEASURED, camera_block, camera_yaml  # noqa: F401  (re-exported)
from ._radiometric import radiometric_from_capture, run_radiometric
from .context import RunContext


def run(cfg: C.LoadedConfig, ctx: RunContext) -> Path:
    plan = plan_of(cfg)  # every input resolved and checked before anything is computed
    sec, system, cam = plan.section, plan.system, plan.camera
    out, yaml_out, capture_path, digest = plan.output, plan.yaml_output, plan.capture, plan.inputs_digest
    if not ctx.force and A.is_up_to_date(out, "calibration", digest) and yaml_out.is_file():
        ctx.say(f"calibrate: {out} is up to date (use --force to redo)")
        return out

    geo, images = None, []
    mirrors: list[MirrorFit] = []
    shape = (cam.pixels[1], cam.pixels[0]) if cam is not None else None
    src = _from_capture(capture_path, sec, shape) if capture_path is not None else _from_files(sec, list(plan.image_files))
    if src.grid is not None:
        if cam is None:
            raise UserError(f"config {plan.config_path}: 'calibrate' with a grid needs 'system.camera' with pixels and "
                            "pixel_pitch_mm (the lens and pose are what it measures).")
        images = src.read_images(cam)
        geo = _geometric(src, cam, images, ctx)
        if system.mirrors and sec.refine_mirrors:
            mirrors = _mirrors(src, system, geo, images, ctx)
    projectors = (fit_projectors(sec, cam, geo, plan.projector_frames, plan.projector_frames_dir, ctx)
                  if sec.projectors else [])
    rad = None
    if sec.radiometric is not None:
        rad = run_radiometric(sec.radiometric, plan.resolve, ctx, expected_shape=shape,
                              bit_depth=cam.sensor.bit_depth if cam is not None else 16)
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
             config_sha256=plan.config_sha256, provenance=plan.provenance)
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


def _from_files(sec: C.Calibrate, paths: list[Path]) -> GridSource:
    return GridSource(sec.grid, [im.plane_z_mm for im in sec.images], [str(p) for p in paths],
                      [f"calibrate.images[{k}]" for k in range(len(paths))], files=paths)


def _from_capture(path: Path, sec: C.Calibrate, shape) -> GridSource:
    """The calibration frames of ``path``: the grid (its description from the capture unless
    calibrate.grid is given) at the plane heights the read-back stage heights give."""
    from ..artefacts.capture import read_calibration

    cal = read_calibration(path)
    if cal.grid is None and cal.bias is None:
        raise UserError(f"calibrate.capture: {path} holds neither grid frames nor bias and photon-transfer frames: "
                        "nothing to calibrate (capture.calibration.grid, or .bias and .ptc).")
    if cal.grid is None and sec.grid is not None:
        raise UserError(f"calibrate.grid: the capture {path} holds no grid frames (capture.calibration.grid was not "
                        "set); leave calibrate.grid out for a radiometric calibration from it.")
    grid = sec.grid
    if grid is None and cal.grid is not None:
        try:
            grid = C.CalibrationGrid(kind=cal.grid.get("kind"), pitch_mm=cal.grid.get("pitch_mm"),
                                     shape=tuple(cal.grid.get("shape") or ()))
        except ValidationError as e:  # a capture from before its grid was checked, or edited since
            why = "; ".join(f"{'.'.join(map(str, x['loc']))}: {x['msg'].removeprefix('Value error, ')}" for x in e.errors())
            raise UserError(f"calibrate.capture: {path} records a grid that cannot be detected ({why}); give the "
                            "printed grid as calibrate.grid, or take the calibration frames again.") from None
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
        except MirrorFitError as e:  # only the fit's own refusal is bad input; any other error is a bug
            raise UserError(f"system.mirrors[{k}]: the grid could not be used in this mirror's view: {e}") from None
        fits.append(fit)
        ctx.say(f"calibrate: mirror {m.name or f'mirror{k}'}: {fit.n_points} points, RMS {fit.rms_px:.3f} px; "
                f"normal moved {fit.normal_change_deg:.2f} deg, plane moved {fit.offset_change_mm:.2f} mm")
        for w in fit.warnings:
            ctx.say(f"calibrate: warning: mirror {k}: {w}")
    return fits
