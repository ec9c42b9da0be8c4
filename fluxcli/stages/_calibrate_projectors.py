"""calibrate's projectors (``calibrate.projectors``): frames of a flat board at known heights
while each projector shows column and row codes (files, or rendered by the simulated rig),
decoded, and fitted against the camera this run calibrated (Moreno & Taubin's local
homographies: :mod:`fluxcli.structured.calibrate` does the maths)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from .. import config as C
from ..calibration.fit import GeometricCalibration
from ..errors import UserError
from ..hardware.projector import projector_model
from ..imaging.imagefiles import read_image
from ..structured import calibrate as SC
from ._calibrate_plan import check_count
from ._camera_yaml import _r


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


def _projector_block(p) -> dict:
    return {"pixels": [int(p.width_px), int(p.height_px)], "focal_px": _r([p.fx_px, p.fy_px]),
            "principal_px": _r([p.cx_px, p.cy_px]), "distortion": _r([p.k1, p.k2], 8), "gamma": _r(p.gamma, 4),
            "pose": {"center_mm": _r(p.center_mm), "look": _r(p.axis, 9), "up": _r(-p.down, 9)}}


def _read_frames(paths: list[Path], key: str, n_expected: int, shape) -> np.ndarray:
    check_count(paths, key, n_expected)
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


def _simulated_frames(frames_dir: Path, k: int, pc: C.ProjectorCalibration, ctx) -> list[tuple[float, list[Path], list[Path]]]:
    """Render the board at each height with the simulated rig; write the frames as 16-bit TIFF files."""
    from ..imaging.imagefiles import write_image
    from .plans import emccd_model
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
    folder = frames_dir / name
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


def fit_projectors(sec: C.Calibrate, cam: C.Camera, geo: GeometricCalibration, frame_paths: dict, frames_dir: Path,
                   ctx) -> list[ProjectorFit]:
    """Decode each projector's frames of the board at each height and fit it against the calibrated camera."""
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
            sets = _simulated_frames(frames_dir, k, pc, ctx)
        else:
            sets = [(im.plane_z_mm, frame_paths[f"calibrate.projectors[{k}].images[{i}].columns"],
                     frame_paths[f"calibrate.projectors[{k}].images[{i}].rows"]) for i, im in enumerate(pc.images)]
        planes, gammas, valid_frac, heights, seen = [], [], [], [], {}
        for i, (z, cpaths, rpaths) in enumerate(sets):
            key = f"calibrate.projectors[{k}].images[{i}]" if pc.simulated is None else \
                f"calibrate.projectors[{k}].simulated (z={z:g} mm)"
            decoded = []
            for which, pats, paths in (("columns", cols, cpaths), ("rows", rows, rpaths)):
                f = _read_frames(paths, f"{key}.{which}", len(pats.frames), (ny, nx))
                _no_frame_twice(f, paths, seen, f"calibrate.projectors[{k}] ({name})")
                contrast = f[0] - f[1]
                lit = contrast[contrast > 0]
                level = pc.min_contrast_fraction * (np.percentile(lit, 99) if len(lit) else 0.0)
                dec = decode(f, pats, min_contrast=level, width_px=w if which == "columns" else h)
                if dec.disagreement > GRAY_PHASE_REFUSE:
                    raise UserError(f"{key}.{which}: the Gray code and the phase steps disagree by more than a quarter "
                                    f"period at {dec.disagreement:.0%} of the lit pixels (frames in order: under 1 %): "
                                    "the frames are out of order (each Gray bit then its inverse, the phase steps in "
                                    "the order shown) or one of them is not of this code.")
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
        except SC.ProjectorFitError as e:  # only the fit's own refusal is bad input; any other error is a bug
            raise UserError(f"calibrate.projectors[{k}] ({name}): {e}; check that the board is lit by the projector "
                            "in the frames and that min_contrast_fraction is not too high.") from None
        fit = ProjectorFit(name, res, _projector_block(res.projector), bool(pc.gamma is None and gamma_meas),
                           heights, valid_frac)
        if pc.simulated is not None:
            fit.truth = _truth_errors(pc.simulated.projector, res.projector)
        fits.append(fit)
        _projector_summary(fit, ctx)
        if res.rms_px > RMS_REFUSE_PX:
            raise UserError(f"calibrate.projectors[{k}] ({name}): the best projector leaves an RMS reprojection of "
                            f"{res.rms_px:.3g} projector px (a good fit: under 0.5): these frames do not show one "
                            "board under this projector's codes. Check each height's frame order (white, black, "
                            "each Gray bit then its inverse, the phase steps), that columns and rows are not "
                            "swapped, and each images[].plane_z_mm.")
    return fits


GRAY_PHASE_REFUSE = 0.1  # a frame swapped or reversed: 23-50 %; in order: 0 %
RMS_REFUSE_PX = 2.0  # a fit this poor moves a structured-light surface by millimetres (a frame swapped: 2-130 px)


def _no_frame_twice(frames: np.ndarray, paths, seen: dict, where: str) -> None:
    """A UserError when two frames of a projector's set hold the same pixels: every pattern
    frame differs from every other, and so does each height's view of the board."""
    import hashlib

    for f, p in zip(frames, paths):
        h = hashlib.sha256(np.ascontiguousarray(f).tobytes()).hexdigest()
        if h in seen:
            raise UserError(f"{where}: {p} and {seen[h]} hold the same pixels (the same frame listed twice, or one "
                            "height's frames given for another); each pattern at each height is its own frame.")
        seen[h] = p


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
