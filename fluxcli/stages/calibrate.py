"""``fluxmap calibrate CONFIG``: the camera model from grid images (and the sensor from radiometric frames).

Examples
--------
$ fluxmap calibrate configs/calibrate.yaml

Writes ``<workdir>/calibration.h5`` (every fitted parameter with its 1-sigma uncertainty,
per-image detections, residuals and blur, the radiometric maps) and
``<workdir>/camera.yaml``, whose top-level ``camera:`` block is a valid ``system.camera``
(and ``mirrors:`` a valid ``system.mirrors`` when mirrors were refined).  Another config
then uses it in one line: ``system: {camera: <workdir>/camera.yaml}``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import yaml

from .. import artefacts as A
from .. import config as C
from ..calibration.fit import CalibrationError, GeometricCalibration, calibrate_geometry
from ..calibration.mirrors import MirrorFit, refine_mirrors
from ..errors import UserError
from ..imaging.imagefiles import read_image
from ..pipeline import provenance
from ._radiometric import run_radiometric, section_files, write_radiometric
from .context import RunContext



def run(cfg: C.LoadedConfig, ctx: RunContext) -> Path:
    sec = cfg.model.calibrate
    system = cfg.model.system
    cam = system.camera if system is not None else None
    out = cfg.workdir / "calibration.h5"
    yaml_out = cfg.workdir / "camera.yaml"
    image_paths = [cfg.resolve(im.file) for im in sec.images]
    for k, p in enumerate(image_paths):
        if not p.is_file():
            raise UserError(f"calibrate.images[{k}].file: image file {p} does not exist.")
    rad_paths = [cfg.resolve(p) for p in section_files(sec.radiometric)] if sec.radiometric is not None else []
    prov = provenance(cfg)
    for k, p in enumerate(image_paths):
        prov.add_file(f"calibrate.images[{k}]", p)
    for k, p in enumerate(rad_paths):
        if p.is_file():
            prov.add_file(f"calibrate.radiometric[{k}]", p)
    digest = A.inputs_digest(calibrate=sec.model_dump(mode="json"),
                             camera=cam.model_dump(mode="json") if cam is not None else None,
                             mirrors=[m.model_dump(mode="json") for m in system.mirrors] if system is not None else [],
                             files={n: d["sha256"] for n, d in prov.input_files.items()})
    if not ctx.force and A.is_up_to_date(out, "calibration", digest) and yaml_out.is_file():
        ctx.say(f"calibrate: {out} is up to date (use --force to redo)")
        return out

    geo, images = None, []
    mirrors: list[MirrorFit] = []
    if sec.grid is not None:
        if cam is None:
            raise UserError(f"config {cfg.path}: 'calibrate' with a grid needs 'system.camera' with pixels and "
                            "pixel_pitch_mm (the lens and pose are what it measures).")
        geo, images = _geometric(cfg, sec, cam, image_paths, ctx)
        if system.mirrors and sec.refine_mirrors:
            mirrors = _mirrors(cfg, sec, system, geo, images, ctx)
    rad = None
    if sec.radiometric is not None:
        shape = (cam.pixels[1], cam.pixels[0]) if cam is not None else None
        rad = run_radiometric(sec.radiometric, cfg.resolve, ctx, expected_shape=shape)

    text = camera_yaml(cam, geo, rad.sensor_block() if rad is not None else None, mirrors, system)
    if geo is not None and not (np.isfinite(geo.aperture_diameter_mm) and geo.aperture_diameter_mm > 0) and (
            cam.lens is None):
        ctx.say("calibrate: warning: the aperture was not measured (a checkerboard gives no per-dot blur); "
                "camera.yaml's lens has no aperture: add f_number or aperture_diameter_mm to it before use")
    with A.write_artefact(out, "calibration", config_sha256=cfg.sha256, provenance=prov) as f:
        f.attrs["inputs_digest"] = digest
        f.create_dataset("camera_yaml", data=text)
        if geo is not None:
            _write_geometric(f.create_group("geometric"), geo, sec, image_paths, cfg, images)
        if mirrors:
            _write_mirrors(f.create_group("mirrors"), mirrors)
        if rad is not None:
            write_radiometric(f.create_group("radiometric"), rad)
    A.write_text(yaml_out, text)
    ctx.say(f"calibrate: camera written to {yaml_out} (use it as  system: {{camera: {yaml_out}}})")
    return out


# ------------------------------------------------------------------ geometric
def _geometric(cfg, sec: C.Calibrate, cam: C.Camera, paths: list[Path], ctx: RunContext):
    nx, ny = cam.pixels
    images = []
    for k, p in enumerate(paths):
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
    heights = [im.plane_z_mm for im in sec.images]
    g = sec.grid
    try:
        geo = calibrate_geometry(images, heights, kind=g.kind, pitch_mm=g.pitch_mm, shape=tuple(g.shape),
                                 pixel_pitch_mm=cam.pixel_pitch_mm)
    except CalibrationError as e:
        where = f"calibrate.images[{e.image}] ({paths[e.image]}): " if e.image is not None else "calibrate: "
        raise UserError(where + str(e) + _hint(e)) from None
    _summary(geo, ctx)
    return geo, images


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


def _write_geometric(g, geo: GeometricCalibration, sec: C.Calibrate, paths, cfg, images) -> None:
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
    g.attrs["grid"] = json.dumps(sec.grid.model_dump(mode="json"))
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
        h.attrs["file"] = str(paths[k])
        h.attrs["focus_measure"] = im.focus_measure
        h.attrs["notes"] = json.dumps(im.notes)
        h.create_dataset("image", data=np.asarray(images[k], np.float32), compression="gzip", shuffle=True)
        for name, arr, unit in (("ij", im.ij, ""), ("xy_px", im.xy_px, "px (col, row), pixel centres at integers"),
                                ("residual_px", im.residual_px, "px, measured - model"),
                                ("residual_mm", im.residual_mm, "mm on the grid plane"),
                                ("blur_diameter_px", im.blur_diameter_px, "px"), ("axial_mm", im.axial_mm, "mm")):
            h.create_dataset(name, data=arr).attrs["unit"] = unit


# ------------------------------------------------------------------ mirrors
def _mirrors(cfg, sec, system: C.System, geo: GeometricCalibration, images, ctx) -> list[MirrorFit]:
    g = sec.grid
    heights = [im.plane_z_mm for im in sec.images]
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


def _write_mirrors(g, mirrors: list[MirrorFit]) -> None:
    for k, m in enumerate(mirrors):
        h = g.create_group(str(k))
        h.create_dataset("center_mm", data=m.center_mm).attrs["unit"] = "mm"
        h.create_dataset("normal", data=m.normal)
        h.attrs["rms_px"] = m.rms_px
        h.attrs["n_points"] = m.n_points
        h.attrs["normal_sigma_deg"] = m.normal_sigma_deg
        h.attrs["offset_sigma_mm"] = m.offset_sigma_mm


# ------------------------------------------------------------------ camera.yaml
def _r(x, nd=6):
    return [round(float(v), nd) for v in x] if np.ndim(x) else round(float(x), nd)


def camera_yaml(cam: C.Camera | None, geo: GeometricCalibration | None, sensor: dict | None,
                mirrors: list[MirrorFit], system: C.System | None) -> str:
    """The YAML text: ``camera:`` valid as ``system.camera``, ``mirrors:`` valid as ``system.mirrors``."""
    doc: dict = {}
    block: dict = {}
    if cam is not None:
        block = {"pixels": [int(cam.pixels[0]), int(cam.pixels[1])], "pixel_pitch_mm": float(cam.pixel_pitch_mm)}
        if geo is not None:
            c = geo.camera
            lens = {"focal_length_mm": _r(geo.focal_length_mm), "focus_distance_mm": _r(geo.focus_distance_mm)}
            if np.isfinite(geo.aperture_diameter_mm) and geo.aperture_diameter_mm > 0:
                lens["aperture_diameter_mm"] = _r(geo.aperture_diameter_mm)
            elif cam.lens is not None:  # not measured: keep what the config says
                lens.update({k: v for k, v in cam.lens.model_dump().items()
                             if k in ("f_number", "aperture_diameter_mm") and v is not None})
            block["lens"] = lens
            block["pose"] = {"lens_center_mm": _r(c.center_mm), "look": _r(c.look, 9), "up": _r(c.up, 9)}
        else:
            if cam.lens is not None:
                block["lens"] = cam.lens.model_dump(exclude_none=True)
            if cam.pose is not None:
                block["pose"] = cam.pose.model_dump(mode="json")
        if cam.apertures:
            block["apertures"] = [a.model_dump() for a in cam.apertures]
        sens = cam.sensor.model_dump()
        if sensor is not None:
            sens.update(sensor)
            block["sensor"] = sens
        doc["camera"] = block
    elif sensor is not None:
        doc["sensor"] = sensor
    if mirrors and system is not None:
        out = []
        for m, fit in zip(system.mirrors, mirrors):
            d = m.model_dump(mode="json", exclude_none=True)
            d["center_mm"] = _r(fit.center_mm)
            d["normal"] = _r(fit.normal, 9)
            d["axis"] = _r(fit.axis, 9)
            out.append(d)
        doc["mirrors"] = out
    head = ("# Written by `fluxmap calibrate`. Use it in any config in one line:\n"
            "#   system: {camera: path/to/camera.yaml}" + ("   (and  mirrors: path/to/camera.yaml)" if mirrors else "")
            + "\n")
    if geo is not None:
        s = geo.sigma
        head += (f"# 1-sigma: f {s['focal_length_mm']:.3g} mm, u {s['focus_distance_mm']:.3g} mm, aperture "
                 f"{s['aperture_diameter_mm']:.3g} mm, lens centre ({s['lens_center_x_mm']:.3g}, "
                 f"{s['lens_center_y_mm']:.3g}, {s['lens_center_z_mm']:.3g}) mm, look {s['look_deg']:.3g} deg; "
                 f"RMS reprojection {geo.rms_px:.3f} px\n")
    return head + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None)
