"""The calibration section of the report, from ``calibration.h5`` only.

Figures: the detected points over each image with their residual vectors (magnified), all
residual vectors in the image plane, and sharpness and blur against height with the fits;
the photon-transfer curve and sensor maps when radiometric results are present; per
projector, its reprojection residuals over the panel and per height.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np
from matplotlib.figure import Figure


def detections_figure(images: list[np.ndarray], xy_px: list[np.ndarray], residual_px: list[np.ndarray],
                      heights_mm: list[float], *, magnify: float = 50.0) -> Figure:
    """Each image with its detected grid points (dots) and residual vectors x ``magnify`` (lines)."""
    n = len(images)
    cols = min(n, 4)
    rows = int(np.ceil(n / cols))
    fig = Figure(figsize=(3.2 * cols, 3.3 * rows), layout="constrained")
    for k in range(n):
        ax = fig.add_subplot(rows, cols, k + 1)
        im = images[k]
        lo, hi = np.percentile(im, [1, 99.5])
        ax.imshow(im, cmap="gray", vmin=lo, vmax=hi, interpolation="nearest")
        q, r = xy_px[k], residual_px[k]
        ax.plot(q[:, 0], q[:, 1], ".", ms=2, color="tab:orange")
        seg = np.stack([q, q + magnify * r], axis=1)
        for s in seg:
            ax.plot(s[:, 0], s[:, 1], "-", lw=0.6, color="tab:red")
        rms = float(np.sqrt((r**2).sum(axis=1).mean())) if len(r) else float("nan")
        ax.set_title(f"z = {heights_mm[k]:g} mm: {len(q)} points, RMS {rms:.3f} px", fontsize=8)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.suptitle(f"Detected grid points (orange) and residuals x{magnify:g} (red)", fontsize=9)
    return fig


def _residual_panels(points_px: list[np.ndarray], residual_px: list[np.ndarray], labels: list[str],
                     extent_px: tuple[int, int], arrow_px: float, names: tuple[str, str, str]) -> Figure:
    """Residual vectors (measured - model) over an image of ``extent_px`` (columns, rows) and
    their scatter, one colour per group (board height).  ``names``: the column and row axis
    names and the unit of the residuals."""
    fig = Figure(figsize=(9, 4), layout="constrained")
    ax, ax2 = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
    cmap = __import__("matplotlib").colormaps["viridis"]
    all_r = np.concatenate(residual_px) if residual_px else np.zeros((0, 2))
    scale = max(float(np.percentile(np.linalg.norm(all_r, axis=1), 95)), 1e-4) if len(all_r) else 1.0
    col, row, unit = names
    for k, (q, r, label) in enumerate(zip(points_px, residual_px, labels)):
        c = cmap(k / max(len(points_px) - 1, 1))
        ax.quiver(q[:, 0], q[:, 1], r[:, 0], -r[:, 1], color=c, angles="xy", scale_units="xy",
                  scale=scale / arrow_px, width=0.003)
        ax2.plot(r[:, 0], r[:, 1], ".", ms=2, color=c, label=label)
    ax.set_xlim(0, extent_px[0])
    ax.set_ylim(extent_px[1], 0)
    ax.set_aspect("equal")
    ax.set_xlabel(f"{col} ({unit})")
    ax.set_ylabel(f"{row} ({unit})")
    ax.set_title(f"residual vectors (arrow of {arrow_px:.0f} {unit} = {scale:.3f} {unit})", fontsize=9)
    ax2.set_aspect("equal")
    ax2.axhline(0, color="0.7", lw=0.5)
    ax2.axvline(0, color="0.7", lw=0.5)
    ax2.set_xlabel(f"{col} residual ({unit})")
    ax2.set_ylabel(f"{row} residual ({unit})")
    ax2.legend(fontsize=7, markerscale=3)
    return fig


def residuals_figure(xy_px: list[np.ndarray], residual_px: list[np.ndarray], heights_mm: list[float],
                     shape_px: tuple[int, int]) -> Figure:
    """Residual vectors (measured - model) over the sensor, and their scatter, per height."""
    return _residual_panels(xy_px, residual_px, [f"z={h:g} mm" for h in heights_mm], (shape_px[1], shape_px[0]),
                            12.0, ("column", "row", "px"))


def focus_figure(axial_mm: list[np.ndarray], blur_px: list[np.ndarray], heights_mm: list[float], *,
                 blur_fit: dict | None, focus_axial_mm: np.ndarray, focus_measure: np.ndarray,
                 focus_params: np.ndarray | None, focus_distance_mm: float) -> Figure:
    """Blur diameter per dot against axial distance with the thin-lens V fit; focus measure per image with its curve."""
    fig = Figure(figsize=(9, 3.8), layout="constrained")
    ax = fig.add_subplot(1, 2, 1)
    for z, d, h in zip(axial_mm, blur_px, heights_mm):
        ok = np.isfinite(d)
        ax.plot(z[ok], d[ok], ".", ms=2, alpha=0.5, label=f"z={h:g} mm")
    allz = np.concatenate(axial_mm) if axial_mm else np.array([1.0])
    if blur_fit is not None:
        zz = np.linspace(allz.min() * 0.98, allz.max() * 1.02, 300)
        dd = np.hypot(blur_fit["k_px_mm"] * (1 / zz - 1 / blur_fit["focus_distance_mm"]), blur_fit["floor_px"])
        ax.plot(zz, dd, "k-", lw=1, label="fit 2Rv|1/z-1/u|/pitch")
        ax.axvline(blur_fit["focus_distance_mm"], color="k", ls=":", lw=0.8)
    ax.set_xlabel("axial distance of the dot from the lens (mm)")
    ax.set_ylabel("blur diameter (px)")
    ax.legend(fontsize=6, markerscale=3)
    ax.set_title(f"blur vs defocus; focus at u = {focus_distance_mm:.2f} mm", fontsize=9)
    ax2 = fig.add_subplot(1, 2, 2)
    ax2.plot(focus_axial_mm, focus_measure, "o", color="tab:blue", label="focus measure per image")
    if focus_params is not None:
        zz = np.linspace(focus_axial_mm.min() * 0.98, focus_axial_mm.max() * 1.02, 300)
        f0, a, w, s = focus_params
        ax2.plot(zz, f0 + a / (1 + ((1 / zz - w) / s) ** 2), "k-", lw=1, label=f"fit: peak at {1 / w:.2f} mm")
        ax2.axvline(1 / w, color="k", ls=":", lw=0.8)
    ax2.set_xlabel("mean axial distance of the grid (mm)")
    ax2.set_ylabel("normalised gradient energy x magnification")
    ax2.legend(fontsize=7)
    ax2.set_title("sharpness vs height", fontsize=9)
    return fig


def projector_residuals_figure(name: str, uv_px: np.ndarray, residual_px: np.ndarray, plane: np.ndarray,
                               heights_mm: list[float], panel_px: tuple[int, int]) -> Figure:
    """A projector's reprojection residuals (measured - model, projector pixels): vectors over the
    panel and their scatter, coloured by board height."""
    groups = [plane == k for k in range(len(heights_mm))]
    labels = [f"z={h:g} mm: {int(m.sum())} points, RMS "
              f"{float(np.sqrt(np.mean(np.sum(residual_px[m] ** 2, axis=1)))) if m.any() else float('nan'):.3f} px"
              for h, m in zip(heights_mm, groups)]
    fig = _residual_panels([uv_px[m] for m in groups], [residual_px[m] for m in groups], labels, tuple(panel_px),
                           0.04 * max(panel_px), ("panel column u", "panel row v", "px"))
    fig.suptitle(f"projector {name}: reprojection residuals (projector pixels)", fontsize=9)
    return fig


def _projector_section(page, save: Callable, projectors: list) -> dict:
    out = {}
    rows = []
    for h in projectors:
        name, block, heights, truth = h.name, h.block, h.heights_mm, h.truth
        out[name] = {"rms_px": h.rms_px, "points": int(len(h.uv_px)), "rejected": h.rejected,
                     "gamma": block["gamma"], "gamma_measured": h.gamma_measured,
                     "center_mm": block["pose"]["center_mm"], "focal_px": block["focal_px"],
                     "valid_fraction": h.valid_fraction}
        if truth is not None:
            out[name]["against_truth"] = {k2: v for k2, v in truth.items() if k2 != "block"}
        err = (f"{truth['center_error_mm']:.3f} mm / {truth['rotation_error_deg']:.3f} deg" if truth is not None else "-")
        rows.append([name, f"{len(h.uv_px)} ({h.rejected} rejected)", f"{h.rms_px:.3f}",
                     f"{block['focal_px'][0]:.1f}, {block['focal_px'][1]:.1f}", f"{block['distortion'][0]:.4f}, {block['distortion'][1]:.4f}",
                     f"{block['gamma']:.3f}" + (" (measured)" if h.gamma_measured else ""), err])
        fig = projector_residuals_figure(name, h.uv_px, h.residual_px, h.plane, heights, tuple(block["pixels"]))
        page.figure(save(fig, f"calibration_projector_{name}.png"),
                    f"Projector {name}: reprojection residuals of the board points (measured by local homographies "
                    "around each grid point - fitted model), per height.")
    page.table(["projector", "board points", "RMS (px)", "f (px)", "k1, k2", "gamma", "pose error vs simulated truth"],
               rows, caption="Projectors fitted against the calibrated camera (camera.yaml's projectors list).")
    return out


def add_calibration_section(page, save: Callable, calibration_h5: Path) -> dict:
    """Append the calibration section to a report page; returns the numbers it shows (for summary.json)."""
    from ..artefacts import calibration as AC

    summary: dict = {}
    cal = AC.read(calibration_h5)
    page.section("calibration", "Calibration")
    page.text("The camera model fitted by `fluxmap calibrate`; the camera.yaml it wrote:")
    page.parts.append("<pre>" + __import__("html").escape(cal.camera_yaml) + "</pre>")
    g = cal.geometric
    if g is not None:
        ims = g.images
        heights = [h.plane_z_mm for h in ims]
        xy = [h.xy_px for h in ims]
        res = [h.residual_px for h in ims]
        summary = dict(g.values)
        summary["lens_center_mm"] = g.lens_center_mm
        summary["sigma"] = dict(g.sigma)
        summary["warnings"] = list(g.warnings)
        page.table(["quantity", "value", "1 sigma"], [
            ["focal length f (mm)", f"{summary['focal_length_mm']:.4f}", f"{summary['sigma'].get('focal_length_mm', np.nan):.2g}"],
            ["focus distance u (mm)", f"{summary['focus_distance_mm']:.3f}", f"{summary['sigma'].get('focus_distance_mm', np.nan):.2g}"],
            ["aperture diameter (mm)", f"{summary['aperture_diameter_mm']:.3f}", f"{summary['sigma'].get('aperture_diameter_mm', np.nan):.2g}"],
            ["image distance v (mm)", f"{summary['image_distance_mm']:.4f}", f"{summary['sigma'].get('image_distance_mm', np.nan):.2g}"],
            ["RMS reprojection (px / mm)", f"{summary['rms_px']:.3f} / {summary['rms_mm']:.4f}", ""],
        ])
        if all(h.image is not None for h in ims):
            fig = detections_figure([h.image for h in ims], xy, res, heights)
            page.figure(save(fig, "calibration_detections.png"), "Detected grid points and residuals per image.")
        shape = tuple(reversed(g.pixels))
        page.figure(save(residuals_figure(xy, res, heights, shape), "calibration_residuals.png"),
                    "Reprojection residuals (measured - model).")
        fa = np.array([float(np.mean(h.axial_mm)) for h in ims])
        fm = np.array([h.focus_measure for h in ims])
        fig = focus_figure([h.axial_mm for h in ims], [h.blur_diameter_px for h in ims], heights,
                           blur_fit=g.blur_fit, focus_axial_mm=fa, focus_measure=fm, focus_params=g.focus_params,
                           focus_distance_mm=summary["focus_distance_mm"])
        page.figure(save(fig, "calibration_focus.png"), "Blur and sharpness against height, with the fits.")
        for w in summary["warnings"]:
            page.parts.append(f'<p class="note">{__import__("html").escape(w)}</p>')
    r = cal.radiometric
    if r is not None:
        from .radiometry_figures import ptc_figure, sensor_maps_figure

        def val(name):
            v = r.scalars.get(name)
            return None if v is None or not np.isfinite(v) else float(v)

        fig = ptc_figure(r.ptc, electrons_per_count=val("electrons_per_count"), em_gain=val("em_gain"),
                         read_noise_counts=val("read_noise_counts"))
        page.figure(save(fig, "calibration_ptc.png"), "Photon-transfer curve.")
        maps = {k: r.maps[k] for k in ("bias_counts_map", "dark_e_per_s_map", "flat_map") if k in r.maps}
        if maps:
            page.figure(save(sensor_maps_figure(maps), "calibration_sensor_maps.png"), "Sensor maps.")
        summary["radiometric"] = {k: val(k) for k in ("electrons_per_count", "em_gain", "read_noise_e", "bias_counts")}
    if cal.projectors:
        summary["projectors"] = _projector_section(page, save, cal.projectors)
    return summary
