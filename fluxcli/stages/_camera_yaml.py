"""``camera.yaml``: the calibrated camera as a ``system.camera`` block (every value marked measured,
with its 1 sigma, or assumed, with where it comes from), the refined mirrors as ``system.mirrors``,
the projectors as ``rig.projectors``."""

from __future__ import annotations

import numpy as np
import yaml

from .. import config as C
from ..calibration.fit import BLUR_WARN_PX, GeometricCalibration
from ..calibration.mirrors import MirrorFit


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
