"""Geometric calibration from grid images at known heights: detection, camera, focus, aperture.

:func:`calibrate_geometry` takes image arrays and numbers (no config, no paths) and returns a
:class:`GeometricCalibration` with every fitted parameter, its 1-sigma uncertainty, the
per-image detections, residuals and blur, and warnings.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field

import numpy as np

from . import dots as D
from . import grid as G
from .geometry import (BlurFit, CameraGeometry, FocusCurve, GeometryFit, angle_sigmas_deg, fit_blur,
                       HeightsDisagree, fit_focus_curve, fit_geometry, focus_measure, grid_points_mm,
                       image_scales, initial_geometry, odd_height)

REPROJECTION_WARN_PX = 0.5
BLUR_WARN_PX = 2.0  # defocus blur (px) the farthest heights should reach for the aperture to be measured


class CalibrationError(ValueError):
    """The images cannot give a calibration; ``image`` is the index of the offending image (or None)."""

    def __init__(self, message: str, image: int | None = None):
        super().__init__(message)
        self.image = image


@dataclass
class ImageResult:
    plane_z_mm: float
    ij: np.ndarray            # (n, 2) labels
    xy_px: np.ndarray         # (n, 2) measured (col, row), pixel centres at integers
    residual_px: np.ndarray   # (n, 2) measured - model
    residual_mm: np.ndarray   # (n, 2) on the grid plane
    blur_diameter_px: np.ndarray  # (n,) nan where not fitted
    axial_mm: np.ndarray      # (n,)
    focus_measure: float
    notes: list[str] = field(default_factory=list)


@dataclass
class GeometricCalibration:
    camera: CameraGeometry
    focal_length_mm: float
    focus_distance_mm: float
    aperture_diameter_mm: float
    sigma: dict[str, float]
    images: list[ImageResult]
    rms_px: float
    rms_mm: float
    blur: BlurFit | None
    focus: FocusCurve | None
    focus_distance_from_measure_mm: float
    dot_diameter_mm: float
    warnings: list[str]
    aperture_resolved: bool = True  # False: the dots blur too little (< BLUR_WARN_PX) for the aperture to be trusted

    @property
    def focal_plane_z_mm(self) -> float:
        return float(self.camera.center_mm[2] + self.focus_distance_mm * self.camera.look[2])


def _detect(image: np.ndarray, kind: str, shape) -> G.Detection:
    if kind == "checkerboard":
        return G.detect_checkerboard(image, shape)
    return G.detect_dots(image, shape)


def calibrate_geometry(images: list[np.ndarray], heights_mm: list[float], *, kind: str, pitch_mm: float,
                       shape: tuple[int, int], pixel_pitch_mm: float, refine: bool = True) -> GeometricCalibration:
    """Fit the thin-lens camera to grid images taken at known plane heights.

    Parameters
    ----------
    images : list of ndarray (ny, nx)
        Counts or photons (any real dtype), one per height.
    heights_mm : list of float
        World z of the grid plane in each image (mm).
    kind : {"dots", "checkerboard"}
    pitch_mm : float
        Grid point spacing (mm).
    shape : (nx, ny)
        Grid points along x and y (checkerboard: inner corners).
    pixel_pitch_mm : float
        Detector pixel pitch (mm): converts the fitted scale into the image distance v.

    Raises
    ------
    CalibrationError
        With ``image`` set when one image is the problem.
    """
    if len(images) != len(heights_mm):
        raise CalibrationError(f"{len(images)} images but {len(heights_mm)} heights")
    ny, nx = images[0].shape
    for k, im in enumerate(images):
        if im.shape != (ny, nx):
            raise CalibrationError(f"image {k} is {im.shape[1]} x {im.shape[0]} px, the first is {nx} x {ny}", k)
    warnings: list[str] = []
    if len(set(heights_mm)) < 3:
        warnings.append(f"only {len(set(heights_mm))} distinct heights: the image distance, focal plane and "
                        "aperture are poorly constrained (give five or more through and around focus)")
    dets = []
    for k, im in enumerate(images):
        try:
            dets.append(_detect(im, kind, shape))
        except G.GridShapeMismatch as e:
            raise CalibrationError(f"the grid seen does not match shape {list(shape)}: {e}", k) from None
        except G.GridNotFound as e:
            raise CalibrationError(f"no {kind} grid of shape {list(shape)} found: {e}", k) from None
        except ValueError as e:
            raise CalibrationError(f"the image cannot be used: {e}", k) from None
    units = [G.to_unit(im) for im in images]
    as_detected = copy.deepcopy(dets)  # (the fit labels the ambiguous ones in place)
    try:
        geo = _consistent_geometry(dets, heights_mm, pitch_mm, shape, pixel_pitch_mm, nx, ny)
    except CalibrationError as e:
        odd = _odd_one_out(as_detected, heights_mm, pitch_mm, shape, pixel_pitch_mm, nx, ny)
        if odd is None or odd[0] == e.image:
            raise
        k, rms = odd
        raise CalibrationError(f"this image disagrees with the others: without it the rest calibrate ({rms:.2f} px "
                               f"RMS), with it they do not ({e}). Is it of this grid at plane_z_mm {heights_mm[k]:g}, "
                               "in the camera's own orientation (not transposed, flipped or turned by the camera "
                               "software) and of this camera?", k) from None
    used = list(range(len(dets)))
    n_found = [len(d.ij) for d in dets]  # before the per-dot fit drops any
    # per-dot model: sub-pixel centres and blur
    blur_px = [np.full(len(d.ij), np.nan) for d in dets]
    dot_diam = float("nan")
    if kind == "dots" and refine:
        first = [D.fit_dots(units[k], dets[k].xy_px, dets[k].spacing_px) for k in used]
        new_xy = []
        for k, fits in zip(used, first):
            xy = np.where(fits.ok[:, None], fits.xy_px, dets[k].xy_px)
            new_xy.append(xy)
        trial = [G.Detection(d.ij, xy, False, d.spacing_px) for d, xy in zip(dets, new_xy)]
        geo2 = _fit(trial, used, heights_mm, pitch_mm, shape, geo.camera)
        keep = [fits.ok for fits in first]
        if geo2.rms_px < geo.rms_px:
            # keep only model-refined points (blob centres are less accurate than these)
            for k, fits in zip(used, first):
                dets[k] = G.Detection(dets[k].ij[fits.ok], fits.xy_px[fits.ok], False, dets[k].spacing_px, dets[k].notes)
            keep = [np.ones(len(dets[k].ij), bool) for k in used]
            first = [_subset(f, f.ok) for f in first]
            geo = _fit(dets, used, heights_mm, pitch_mm, shape, geo2.camera)
        # dot radius in mm: the fitted radius that is the same at every height
        lo, hi = [], []
        for k, fits in zip(used, first):
            m = 1 / geo.camera.mm_per_px(grid_points_mm(dets[k].ij, pitch_mm, shape, heights_mm[k]))
            lo.append(np.minimum(fits.radius_a_px, fits.radius_b_px) / m)
            hi.append(np.maximum(fits.radius_a_px, fits.radius_b_px) / m)
        rho = D.resolve_dot_radius(lo, hi)
        dot_diam = 2 * rho
        for k in used:
            P = grid_points_mm(dets[k].ij, pitch_mm, shape, heights_mm[k])
            a = rho / geo.camera.mm_per_px(P)
            prev = first[used.index(k)]
            nb = prev if len(prev.xy_px) == len(dets[k].xy_px) else None
            for _ in range(2):  # neighbours drawn from the latest fit
                second = D.fit_dots(units[k], dets[k].xy_px, dets[k].spacing_px, radius_a_px=a, neighbours=nb)
                nb = second
            blur_px[k] = np.where(second.ok, 2 * second.radius_b_px, np.nan)
        _ = keep
    # focus measure per image, over the grid's bounding region
    fm = []
    for k in used:
        xy = dets[k].xy_px
        mask = np.zeros((ny, nx), bool)
        r0, r1 = int(max(xy[:, 1].min(), 0)), int(min(xy[:, 1].max() + 1, ny))
        c0, c1 = int(max(xy[:, 0].min(), 0)), int(min(xy[:, 0].max() + 1, nx))
        mask[r0:r1, c0:c1] = True
        # x magnification (px/mm): the gradient energy per signal falls as 1/(dot size x edge width)
        m = 1 / np.mean(geo.camera.mm_per_px(grid_points_mm(dets[k].ij, pitch_mm, shape, heights_mm[k])))
        fm.append(focus_measure(units[k], mask) * m)
    axial_mean = np.array([np.mean(geo.camera.axial_mm(grid_points_mm(dets[k].ij, pitch_mm, shape, heights_mm[k])))
                           for k in used])
    focus = None
    u_measure = float("nan")
    if len(used) >= 4:
        focus = fit_focus_curve(axial_mean, np.array(fm))
        u_measure = focus.focus_distance_mm
    # lens from blur growth
    cam = geo.camera
    v = cam.image_distance_mm
    blur = None
    aperture_resolved = True
    z_all = np.concatenate([cam.axial_mm(grid_points_mm(dets[k].ij, pitch_mm, shape, heights_mm[k])) for k in used])
    d_all = np.concatenate([blur_px[k] for k in used])
    ok = np.isfinite(d_all)
    if ok.sum() >= 10 and len(set(heights_mm)) >= 3:
        u0 = u_measure if np.isfinite(u_measure) else float(np.median(z_all))
        blur = fit_blur(z_all[ok], d_all[ok], u0)
        u, su = blur.focus_distance_mm, blur.focus_distance_sigma_mm
        R = blur.k_px_mm * pixel_pitch_mm / (2 * v)
        sR = blur.k_sigma * pixel_pitch_mm / (2 * v)
    elif np.isfinite(u_measure):
        u, su, R, sR = u_measure, float("nan"), float("nan"), float("nan")
        warnings.append("the aperture could not be measured (no per-dot blur): aperture_diameter_mm is missing")
    else:
        raise CalibrationError("too few heights to find the focal plane (four or more are needed)")
    sv = geo.sigma["v_mm"]
    f = u * v / (u + v)
    sf = float(np.hypot(v**2 / (u + v) ** 2 * su, u**2 / (u + v) ** 2 * sv))
    # warnings
    if geo.rms_px > REPROJECTION_WARN_PX:
        warnings.append(f"RMS reprojection error {geo.rms_px:.2f} px exceeds {REPROJECTION_WARN_PX} px: "
                        "the grid detection or the camera model does not fit these images")
    if blur is not None:
        # the blur the lens adds at the farthest heights: when it stays near a pixel it hides in the
        # floor (pixel, dot edge) and the aperture comes out low (-17 % at ~1 px on the simulated rig)
        defocus_px = float(blur.k_px_mm * np.max(np.abs(1 / z_all - 1 / blur.focus_distance_mm)))
        aperture_resolved = defocus_px >= BLUR_WARN_PX
        if not aperture_resolved:
            warnings.append(f"the dots blur by at most {defocus_px:.1f} px over these heights: the aperture "
                            f"({2 * R:.3g} mm) is poorly measured and likely low, beyond its 1 sigma; spread the "
                            "heights further from the focal plane, or give the lens' f_number")
    zmin, zmax = axial_mean.min(), axial_mean.max()
    if not (zmin < u < zmax):
        warnings.append(f"the heights do not span the focal plane (focus at axial {u:.1f} mm, images at "
                        f"{zmin:.1f}-{zmax:.1f} mm): focus and aperture are extrapolated")
    if np.isfinite(u_measure) and blur is not None and abs(u_measure - u) > max(3 * su, 2.0):
        warnings.append(f"the focus measure peaks at {u_measure:.1f} mm, the blur fit at {u:.1f} mm "
                        "(they should agree): check the heights")
    n_all = shape[0] * shape[1]
    partial = []
    for k in used:
        if len(dets[k].ij) < n_all:
            partial.append(f"z={heights_mm[k]:g} mm: {len(dets[k].ij)} of {n_all}")
        # one count per image: the points used (the detection's count, less any the per-dot fit dropped)
        notes = [n for n in dets[k].notes if not n.endswith(" points found")]
        if len(dets[k].ij) < n_all:
            dropped = n_found[k] - len(dets[k].ij)
            notes.append(f"{len(dets[k].ij)} of {n_all} points used"
                         + (f" ({n_found[k]} found, {dropped} dropped by the per-dot fit)" if dropped > 0 else ""))
        dets[k].notes = notes
    if partial:
        warnings.append("the grid leaves the field (or some points were not found, or not fitted) in some images; "
                        "points used: " + ", ".join(partial))
    images_out = []
    for k in used:
        P = grid_points_mm(dets[k].ij, pitch_mm, shape, heights_mm[k])
        r = dets[k].xy_px - cam.project(P)
        images_out.append(ImageResult(float(heights_mm[k]), dets[k].ij, dets[k].xy_px, r,
                                      r * cam.mm_per_px(P)[:, None], blur_px[k], cam.axial_mm(P), fm[used.index(k)],
                                      list(dets[k].notes)))
    rms_mm = float(np.sqrt(np.mean(np.concatenate([(im.residual_mm**2).sum(axis=1) for im in images_out]))))
    s_tilt, s_roll = angle_sigmas_deg(geo)
    sigma = {"lens_center_x_mm": geo.sigma["cx_mm"], "lens_center_y_mm": geo.sigma["cy_mm"],
             "lens_center_z_mm": geo.sigma["cz_mm"], "image_distance_mm": sv, "look_deg": s_tilt,
             "roll_deg": s_roll, "focus_distance_mm": su, "focal_length_mm": sf,
             "aperture_diameter_mm": 2 * sR}
    return GeometricCalibration(cam, float(f), float(u), float(2 * R), sigma, images_out, geo.rms_px, rms_mm, blur,
                                focus, u_measure, dot_diam, warnings, aperture_resolved)


def _consistent_geometry(dets, heights_mm, pitch_mm, shape, pixel_pitch_mm, nx, ny) -> GeometryFit:
    """The camera's geometry fitted to every image's grid points, after the checks that name one
    image: a height its scale contradicts, a partly seen grid that cannot be labelled from the
    camera fitted on the others.  Labels the ambiguous detections in ``dets`` (in place)."""
    known = [k for k, d in enumerate(dets) if not d.ambiguous]
    if len({heights_mm[k] for k in known}) < 2:
        raise CalibrationError("fewer than two heights show the grid with a known offset (cut on one side at most, "
                               "or whole): the camera cannot be started; check calibrate.grid.shape against the images")

    def views(idx):
        return [(grid_points_mm(dets[k].ij, pitch_mm, shape, heights_mm[k]), dets[k].xy_px) for k in idx]

    odd = odd_height(*image_scales(views(known))[:2])  # a wrong plane_z_mm, named before it skews the fit
    if odd is not None:
        k = known[odd[0]]
        raise CalibrationError(f"the grid in this image lies at z = {odd[1]:.1f} mm by its scale against the other "
                               f"images, but its plane_z_mm is {heights_mm[k]:g} mm (the heights do not match the "
                               "images)", k)
    try:
        init = initial_geometry(views(known), pixel_pitch_mm, nx, ny)
    except HeightsDisagree as e:
        raise CalibrationError(str(e)) from None
    geo = _fit(dets, known, heights_mm, pitch_mm, shape, init)
    # ambiguous images: label from the camera fitted so far
    allij = np.stack(np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij"), -1).reshape(-1, 2)
    for k, d in enumerate(dets):
        if d.ambiguous:
            pred = geo.camera.project(grid_points_mm(allij, pitch_mm, shape, heights_mm[k]))
            try:
                G.relabel_from_prediction(d, pred, allij)
            except G.GridNotFound as e:
                raise CalibrationError(f"{e}; check that its plane_z_mm ({heights_mm[k]:g}) matches the image "
                                       "(the heights may not match the images)", k) from None
    geo = _fit(dets, list(range(len(dets))), heights_mm, pitch_mm, shape, geo.camera)
    _check_heights(dets, heights_mm, pitch_mm, shape, geo.camera)
    return geo


def _odd_one_out(dets, heights_mm, pitch_mm, shape, pixel_pitch_mm, nx, ny) -> tuple[int, float] | None:
    """(k, RMS px) when the images calibrate without image k alone and fit well there (four images
    or more, the rest at three heights or more): a transposed, flipped, shifted or foreign frame,
    named instead of the frame its presence made fail.  None when no single image explains it."""
    if len(dets) < 4:
        return None
    ok = []
    for k in range(len(dets)):
        rest = [j for j in range(len(dets)) if j != k]
        if len({heights_mm[j] for j in rest}) < 3:
            continue
        try:
            geo = _consistent_geometry([copy.deepcopy(dets[j]) for j in rest], [heights_mm[j] for j in rest],
                                       pitch_mm, shape, pixel_pitch_mm, nx, ny)
        except (CalibrationError, ValueError, np.linalg.LinAlgError):
            continue
        if geo.rms_px <= REPROJECTION_WARN_PX:
            ok.append((k, float(geo.rms_px)))
    return ok[0] if len(ok) == 1 else None


def _subset(f: D.DotFits, m: np.ndarray) -> D.DotFits:
    return D.DotFits(f.xy_px[m], f.amplitude[m], f.background[m], f.radius_a_px[m], f.radius_b_px[m], f.rms[m], f.ok[m])


def _fit(dets, idx, heights_mm, pitch_mm, shape, init: CameraGeometry) -> GeometryFit:
    P = np.concatenate([grid_points_mm(dets[k].ij, pitch_mm, shape, heights_mm[k]) for k in idx])
    q = np.concatenate([dets[k].xy_px for k in idx])
    return fit_geometry(P, q, init)


def _check_heights(dets, heights_mm, pitch_mm, shape, cam: CameraGeometry) -> None:
    """Refuse a stated height the image contradicts: the grid's scale there implies another plane.

    With the camera fitted to all images, each image's plane height is re-fitted alone; a
    difference above max(2 mm, 1 % of the distance) is a wrong ``plane_z_mm`` (or the
    wrong file), not noise.
    """
    from scipy.optimize import minimize_scalar

    for k, d in enumerate(dets):
        z0 = float(heights_mm[k])

        def cost(z):
            P = grid_points_mm(d.ij, pitch_mm, shape, z)
            return float(((cam.project(P) - d.xy_px) ** 2).sum())

        dist = float(np.mean(cam.axial_mm(grid_points_mm(d.ij, pitch_mm, shape, z0))))
        tol = max(2.0, 0.01 * dist)
        sol = minimize_scalar(cost, bounds=(z0 - 0.5 * dist, z0 + 0.5 * dist), method="bounded")
        if abs(sol.x - z0) > tol:
            raise CalibrationError(f"the grid in this image lies at z = {sol.x:.1f} mm by its scale, but its "
                                   f"plane_z_mm is {z0:g} mm (the heights do not match the images)", k)
