"""The report's figures: arrays and numbers in, matplotlib figures out.

Every function takes plain arrays (photons, photons mm^-2, degrees, mm) and returns a
:class:`matplotlib.figure.Figure` built without pyplot (no global state, no display).
3-D views of the flux on the surface are rasterised with pyvista off-screen, or with a
painter's-algorithm projection in matplotlib when no OpenGL context is available; both
colour the faces identically (the colours are computed here, not by the renderer).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib import colormaps
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import Normalize
from matplotlib.cm import ScalarMappable
from matplotlib.figure import Figure
from matplotlib.patches import Patch
from matplotlib.ticker import FixedLocator, FuncFormatter, MultipleLocator, NullFormatter

from ..surface.geometry import rotation_matrix as _rotation

EXITANCE = ("exitance", "photons mm$^{-2}$")
PHOTONS_LABEL = "photons per pixel"
ANGLE_LABEL = "angle about the subject's axis (°, 0 = facing the camera at rest)"
SERIES_NAMES = {"direct_roi": "direct-view ROI sum", "backprojection": "backprojection total (Σ Tᵀa)",
                "reconstruction": "reconstructed total"}
UNOBSERVED_GREY = (0.55, 0.55, 0.55)
NO_ELEMENT_GREY = (0.86, 0.86, 0.86)
VIEW_COLOURS = ["#ffffff", "#00e5ff", "#7CFC00", "#ff66ff", "#ffa500"]
JOINT_COLOUR = "#b2182b"
_POSE_CYCLE = ["C0", "C1", "C2", "C4", "C5", "C6", "C8", "C9", "C7"]  # no red: red is the joint result


def pose_colours(n: int) -> list:
    """Distinct colours for the poses, none of them red or too pale to see on white."""
    if n <= len(_POSE_CYCLE):
        return _POSE_CYCLE[:n]
    return list(colormaps["viridis"](np.linspace(0, 0.85, n)))


class RenderError(RuntimeError):
    """Neither pyvista nor matplotlib could draw the 3-D views."""


def save(fig: Figure, path: Path, dpi: int = 100) -> None:
    from ..artefacts.atomic import atomic_path

    FigureCanvasAgg(fig)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format=Path(path).suffix.lstrip(".") or "png", dpi=dpi, facecolor="white",
                    bbox_inches="tight", pad_inches=0.08)


def scaled(axis, vmax: float, quantity: str, unit: str) -> str:
    """Put a large or small scale into the label, not into an offset text above the axis:
    ticks read 2.5 and the label 'exitance (10⁷ photons mm⁻²)'. Returns the label."""
    e = int(np.floor(np.log10(abs(vmax)))) if vmax and np.isfinite(vmax) else 0
    if -2 <= e <= 4:
        return f"{quantity} ({unit})"
    f = 10.0**e
    axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v / f:g}"))
    return f"{quantity} (×10$^{{{e}}}$, {unit})" if unit == "dimensionless" else f"{quantity} (10$^{{{e}}}$ {unit})"


def _figure(w_in: float, h_in: float) -> Figure:
    fig = Figure(figsize=(w_in, h_in), layout="constrained")
    FigureCanvasAgg(fig)
    return fig


# ------------------------------------------------------------------ labels
def pose_labels(heights_mm, rotations_deg) -> list[str]:
    """Short names of the poses: only what varies between them."""
    h, r = np.asarray(heights_mm, float), np.asarray(rotations_deg, float)
    vary_h, vary_r = np.ptp(h) > 0 if len(h) else False, np.ptp(r) > 0 if len(r) else False
    out = []
    for hk, rk in zip(h, r):
        parts = []
        if vary_h or not vary_r:
            parts.append(f"h = {hk:g} mm")
        if vary_r or (not vary_h and rk != 0):
            parts.append(f"θ = {rk:g}°")
        out.append(", ".join(parts))
    return out


def direction_label(v) -> str:
    """'+x', '−y' for axis directions, else the rounded vector."""
    v = np.asarray(v, float)
    v = v / np.linalg.norm(v)
    k = int(np.argmax(np.abs(v)))
    if abs(abs(v[k]) - 1) < 1e-6:
        return ("+" if v[k] > 0 else "−") + "xyz"[k]
    return "(" + ", ".join(f"{c:.2f}" for c in v) + ")"


def image_axis_labels(look, up) -> tuple[str, str]:
    """Columns grow along look × up, rows along −up (the README's convention)."""
    look, up = np.asarray(look, float), np.asarray(up, float)
    right = np.cross(look, up)
    down = -(up - (up @ look) / (look @ look) * look)
    return f"column (px) → world {direction_label(right)}", f"row (px) → world {direction_label(down)}"


# ------------------------------------------------------------------ 1. images
def fit_figure(measured, fitted, valid, *, footprints=None, view_names=(), title="", chi2=None,
               axis_labels=("column (px)", "row (px)")) -> Figure:
    """Measured | fitted | residual, photons per pixel; curves for a line detector (ny == 1)."""
    measured = np.asarray(measured, float)
    fitted = np.where(valid, np.asarray(fitted, float), np.nan)
    residual = measured - fitted
    if measured.shape[0] == 1:
        return _fit_line(measured[0], fitted[0], residual[0], footprints, view_names, title, chi2, axis_labels[0])
    ok = valid & np.isfinite(measured)
    fit_top = np.nanmax(fitted) if np.any(np.isfinite(fitted)) else 0.0
    # where light falls: the views' footprints, else where the fit is not dark
    lit = np.any(footprints, axis=0) if footprints is not None else np.nan_to_num(fitted) > 1e-3 * max(fit_top, 1e-300)
    # the brightest measured pixel sets the scale (a lone spike far above the rest does not)
    m = measured[ok & lit] if np.any(ok & lit) else measured[ok]
    m_top = 0.0
    if m.size:
        m_top = float(np.nanmax(m))
        if m.size > 50 and m_top > 3 * np.nanpercentile(m, 99.5):
            m_top = float(np.nanpercentile(m, 99.9))
    top = max(m_top, fit_top)
    top = top if top > 0 else 1.0
    bottom = min(0.0, float(np.nanmin(measured[ok]))) if ok.any() else 0.0
    # the residual's scale follows the lit pixels too: dark ones would pull it to ~0
    r = residual[np.isfinite(residual) & lit]
    rmax = float(np.nanpercentile(np.abs(r), 99.5)) if r.size else 1.0
    rmax = rmax if rmax > 0 else 1.0
    ny, nx = measured.shape
    # show the part of the detector the subject can light (the paper crops its Fig. 12 likewise)
    r0, r1, c0, c1 = _crop(lit | (np.nan_to_num(measured) > 0.2 * top), ny, nx)
    ch, cw = r1 - r0, c1 - c0
    fig = _figure(3 * 3.6 * min(1.0, cw / ch) + 2.2, 3.6 * min(1.0, ch / cw) + 1.5)
    axs = fig.subplots(1, 3, sharex=True, sharey=True)
    seq = colormaps["inferno"].with_extremes(bad=UNOBSERVED_GREY)
    div = colormaps["RdBu_r"].with_extremes(bad=UNOBSERVED_GREY)
    norm = Normalize(bottom, top)
    kw = dict(origin="upper", interpolation="nearest", extent=(-0.5, nx - 0.5, ny - 0.5, -0.5))
    im0 = axs[0].imshow(np.where(valid, measured, np.nan), cmap=seq, norm=norm, **kw)
    axs[1].imshow(fitted, cmap=seq, norm=norm, **kw)
    im2 = axs[2].imshow(residual, cmap=div, norm=Normalize(-rmax, rmax), **kw)
    axs[0].set_xlim(c0 - 0.5, c1 - 0.5)
    axs[0].set_ylim(r1 - 0.5, r0 - 0.5)
    axs[0].set_title("measured")
    axs[1].set_title("fitted (T b̃)")
    axs[2].set_title("residual" + (f" (χ²/pixel = {chi2:.3g})" if chi2 is not None else ""))
    if footprints is not None:
        handles = []
        for k, foot in enumerate(footprints):
            if not foot.any():
                continue
            c = VIEW_COLOURS[k % len(VIEW_COLOURS)]
            for ax in axs[:2]:
                ax.contour(np.arange(nx), np.arange(ny), foot.astype(float), levels=[0.5], colors=[c], linewidths=0.8)
            handles.append(Patch(facecolor="none", edgecolor=c if c != "#ffffff" else "0.3",
                                 label=view_names[k] if k < len(view_names) else f"view {k}"))
        if handles:
            fig.legend(handles=handles, loc="outside lower center", ncol=len(handles), fontsize=8, frameon=False,
                       title="outlines: pixels each view reaches", title_fontsize=8)
    for ax in axs:
        ax.set_xlabel(axis_labels[0], fontsize=8)
    axs[0].set_ylabel(axis_labels[1], fontsize=8)
    cb = fig.colorbar(im0, ax=list(axs[:2]), shrink=0.9, extend="min" if bottom < 0 else "neither")
    cb.set_label(scaled(cb.ax.yaxis, top, "signal", PHOTONS_LABEL))
    cb = fig.colorbar(im2, ax=axs[2], shrink=0.9, extend="both")
    cb.set_label(scaled(cb.ax.yaxis, rmax, "residual", PHOTONS_LABEL))
    fig.suptitle(title)
    return fig


def _crop(mask: np.ndarray, ny: int, nx: int) -> tuple[int, int, int, int]:
    """Rows r0:r1 and columns c0:c1 around ``mask`` with a margin (the whole image if it is empty)."""
    if not mask.any():
        return 0, ny, 0, nx
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    pad = max(3, int(0.08 * max(rows[-1] - rows[0], cols[-1] - cols[0])))
    return (max(rows[0] - pad, 0), min(rows[-1] + pad + 1, ny), max(cols[0] - pad, 0), min(cols[-1] + pad + 1, nx))


def _fit_line(m, fi, res, footprints, view_names, title, chi2, xlabel) -> Figure:
    fig = _figure(9.0, 5.0)
    ax, axr = fig.subplots(2, 1, sharex=True, height_ratios=[2, 1])
    x = np.arange(len(m))
    ax.plot(x, m, ".", ms=2.5, color="0.35", label="measured")
    ax.plot(x, fi, "-", lw=1.2, color="C3", label="fitted (T b̃)")
    axr.axhline(0, color="0.5", lw=0.8)
    axr.plot(x, res, ".", ms=2.5, color="C0")
    top = max([np.nanmax(np.abs(v)) for v in (m, fi) if np.any(np.isfinite(v))] or [1.0])
    ax.set_ylabel(scaled(ax.yaxis, top, "signal", PHOTONS_LABEL))
    rtop = np.nanmax(np.abs(res)) if np.any(np.isfinite(res)) else 1.0
    axr.set_ylabel(scaled(axr.yaxis, rtop, "residual", PHOTONS_LABEL).replace(" (", "\n("))
    axr.set_xlabel(xlabel)
    axr.set_title(f"residual (measured − fitted)" + (f", χ²/pixel = {chi2:.3g}" if chi2 is not None else ""), fontsize=9)
    # zoom to where light falls; a line detector is mostly dark
    lit = np.flatnonzero(np.nan_to_num(fi) > 1e-3 * max(np.nanmax(fi), 1e-300)) if np.any(np.isfinite(fi)) else []
    if footprints is not None:
        lit = np.union1d(lit, np.flatnonzero(np.any(footprints[:, 0, :], axis=0)))
    if len(lit):
        pad = max(5, int(0.1 * (lit[-1] - lit[0])))
        ax.set_xlim(max(lit[0] - pad, -0.5), min(lit[-1] + pad, len(m) - 0.5))
    if footprints is not None and footprints.shape[0] > 1:
        for k, foot in enumerate(footprints):
            idx = np.flatnonzero(foot[0])
            if len(idx):
                ax.axvspan(idx[0] - 0.5, idx[-1] + 0.5, color=f"C{k}", alpha=0.08,
                           label=view_names[k] if k < len(view_names) else f"view {k}")
    ax.legend(fontsize=8)
    ax.set_title("measured and fitted")
    fig.suptitle(title)
    return fig


# ------------------------------------------------------------------ 2. flux on the surface
@dataclass
class Panel:
    """One 3-D view: a surface coloured per element, seen along ``look`` with ``up`` up."""

    vertices_mm: np.ndarray  # (V, 3)
    faces: np.ndarray  # (F, 3)
    element_of_face: np.ndarray  # (F,)
    values: np.ndarray  # (n_elements,) photons mm^-2, NaN unobserved
    look: np.ndarray
    up: np.ndarray
    title: str = ""
    row: int = 0
    col: int = 0
    row_label: str = ""
    poorly: np.ndarray | None = None  # (n_elements,) bool: drawn hatched


def exitance_limits(pose_exitance, exitance, truth_exitance=None) -> tuple[float, float, bool]:
    """(vmin, vmax, values above vmax exist): one scale for every 3-D panel, set by the
    truth and the joint result, and by per-pose results except their 0.5 % outliers."""
    tops = [np.nanpercentile(pose_exitance, 99.5) if np.any(np.isfinite(pose_exitance)) else 0.0]
    for v in (exitance, truth_exitance):
        if v is not None and np.any(np.isfinite(v)):
            tops.append(np.nanmax(v))
    vmax = float(max(tops)) if max(tops) > 0 else 1.0
    finite = [np.nanmin(v) for v in (pose_exitance, exitance) if np.any(np.isfinite(v))]
    vmin = float(min(0.0, *finite)) if finite else 0.0
    return vmin, vmax, bool(np.nanmax(pose_exitance) > vmax * 1.0001) if np.any(np.isfinite(pose_exitance)) else False


def surface_panels(study, geometry, truth_exitance, labels) -> tuple[list[Panel], list[Panel]]:
    """Panels seen from the camera (each pose's surface where it was placed) and in a common
    orientation (the rest surface, seen from the camera side and turned 120°, 240° about the axis)."""
    s = study.surface
    look, up = np.asarray(geometry.look, float), np.asarray(geometry.up, float)
    cam = []
    if study.pose_vertices_mm is not None:
        for k in range(study.n_poses):
            cam.append(Panel(study.pose_vertices_mm[k], s.faces, s.element_of_face, study.pose_exitance[k], look, up,
                             f"{k + 1}: {labels[k]}",
                             poorly=None if study.pose_poorly is None else study.pose_poorly[k]))
    pp = study.pose_poorly
    columns = [(f"{k + 1}: {labels[k]}", study.pose_exitance[k], None if pp is None else pp[k])
               for k in range(study.n_poses)]
    if study.joint:
        columns.append(("joint", study.exitance, study.poorly))
    if truth_exitance is not None:
        columns.append(("ground truth", truth_exitance, None))
    rest = []
    for r, turn in enumerate((0.0, 120.0, 240.0)):
        R = _rotation(geometry.axis_direction, turn)
        name = "camera\nside" if turn == 0 else f"turned\n{turn:g}°\nabout\nthe axis"
        for c, (title, values, poorly) in enumerate(columns):
            rest.append(Panel(s.vertices_mm, s.faces, s.element_of_face, values, R @ look, R @ up,
                              title if r == 0 else "", r, c, name, poorly))
    return cam, rest


def _screen(panel: Panel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Screen axes (right, up) and the view direction, orthonormal."""
    d = panel.look / np.linalg.norm(panel.look)
    u = panel.up - (panel.up @ d) * d
    u /= np.linalg.norm(u)
    return np.cross(d, u), u, d


def _face_colours(panel: Panel, norm: Normalize, cmap) -> np.ndarray:
    """(F, 3) RGB in [0, 1]: colour map of the element's value, grey when unobserved, light
    grey for faces that are no element; shaded by the angle to the view (a head light)."""
    e = panel.element_of_face
    vals = np.where(e >= 0, panel.values[np.maximum(e, 0)], np.nan)
    rgb = cmap(norm(np.nan_to_num(vals, nan=0.0)))[:, :3]
    rgb[~np.isfinite(vals)] = UNOBSERVED_GREY
    rgb[e < 0] = NO_ELEMENT_GREY
    if panel.poorly is not None:  # poorly observed: hatched, alternate faces washed out (stripes)
        poor = (e >= 0) & panel.poorly[np.maximum(e, 0)] & np.isfinite(vals)
        stripe = poor & (np.arange(len(e)) % 2 == 0)
        rgb[stripe] = 0.45 * rgb[stripe] + 0.55
    t = panel.vertices_mm[panel.faces]
    n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    _, _, d = _screen(panel)
    return rgb * (0.72 + 0.28 * np.abs(n @ d))[:, None]


def _is_closed(faces: np.ndarray) -> bool:
    e = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    return bool(np.all(counts == 2))


def _render_matplotlib(panel: Panel, colours: np.ndarray, half_w: float, half_h: float, size_px) -> np.ndarray:
    """Painter's algorithm with an orthographic projection; back faces of a closed surface culled."""
    from matplotlib.collections import PolyCollection

    right, upv, d = _screen(panel)
    v = panel.vertices_mm
    c = (v.min(axis=0) + v.max(axis=0)) / 2
    xy = np.stack([(v - c) @ right, (v - c) @ upv], axis=1)
    depth = (v @ d)[panel.faces].mean(axis=1)
    keep = np.ones(len(panel.faces), bool)
    if _is_closed(panel.faces):
        t = v[panel.faces]
        n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
        keep = n @ d < 0
    order = np.flatnonzero(keep)[np.argsort(-depth[keep], kind="stable")]
    w, h = size_px
    fig = Figure(figsize=(w / 100, h / 100), dpi=100)
    canvas = FigureCanvasAgg(fig)
    ax = fig.add_axes((0, 0, 1, 1))
    ax.set_axis_off()
    ax.add_collection(PolyCollection(xy[panel.faces[order]], facecolors=colours[order], edgecolors=colours[order],
                                     linewidths=0.3, antialiaseds=True))
    ax.set_xlim(-half_w, half_w)
    ax.set_ylim(-half_h, half_h)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[:, :, :3].copy()


class _PyvistaRenderer:
    def __init__(self, size_px):
        import pyvista as pv
        import vtk

        # off-screen without an X server VTK logs "bad X server connection" on stderr, then renders fine
        vtk.vtkLogger.SetStderrVerbosity(vtk.vtkLogger.VERBOSITY_OFF)
        pv.OFF_SCREEN = True
        self.pv = pv
        self.plotter = pv.Plotter(off_screen=True, window_size=list(size_px))
        self.plotter.set_background("white")
        self.plotter.enable_parallel_projection()

    def render(self, panel: Panel, colours: np.ndarray, half_h: float) -> np.ndarray:
        pv, pl = self.pv, self.plotter
        pl.clear_actors()
        faces = np.hstack([np.full((len(panel.faces), 1), 3), panel.faces]).ravel()
        mesh = pv.PolyData(panel.vertices_mm, faces)
        mesh.cell_data["rgb"] = np.round(colours * 255).astype(np.uint8)
        pl.add_mesh(mesh, scalars="rgb", rgb=True, lighting=False, show_scalar_bar=False)
        right, upv, d = _screen(panel)
        v = panel.vertices_mm
        c = (v.min(axis=0) + v.max(axis=0)) / 2
        extent = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0))) + 1.0
        pl.camera.focal_point = tuple(c)
        pl.camera.position = tuple(c - d * 10 * extent)
        pl.camera.up = tuple(upv)
        pl.camera.parallel_projection = True
        pl.camera.parallel_scale = half_h
        pl.reset_camera_clipping_range()
        pl.render()  # without it the first screenshot after a camera move can show the previous view
        return np.asarray(pl.screenshot(return_img=True))[:, :, :3].copy()

    def close(self):
        self.plotter.close()


def render_panels(panels: list[Panel], norm: Normalize, cmap, *, renderer: str = "auto",
                  max_panel_px: int = 320) -> tuple[list[np.ndarray], str]:
    """Rasterise every panel at one scale (mm per pixel); returns the images and the
    renderer used. ``renderer``: auto (pyvista, falling back to matplotlib), pyvista, matplotlib."""
    half_w = half_h = 1e-9
    for p in panels:
        right, upv, _ = _screen(p)
        v = p.vertices_mm - (p.vertices_mm.min(axis=0) + p.vertices_mm.max(axis=0)) / 2
        half_w = max(half_w, np.abs(v @ right).max())
        half_h = max(half_h, np.abs(v @ upv).max())
    half_w, half_h = 1.06 * half_w, 1.06 * half_h
    scale = max_panel_px / (2 * max(half_w, half_h))
    size = (max(16, int(round(2 * half_w * scale))), max(16, int(round(2 * half_h * scale))))
    half_w = half_h * size[0] / size[1]  # the window's aspect decides the width shown
    colours = [_face_colours(p, norm, cmap) for p in panels]
    if renderer in ("auto", "pyvista"):
        try:
            r = _PyvistaRenderer(size)
            try:
                imgs = [r.render(p, c, half_h) for p, c in zip(panels, colours)]
            finally:
                r.close()
            if all(im.shape[:2] == (size[1], size[0]) and im.min() < 250 for im in imgs):
                return imgs, "pyvista"
            if renderer == "pyvista":
                raise RenderError("pyvista produced blank images")
        except RenderError:
            raise
        except Exception as e:  # no OpenGL context, missing VTK module, ...
            if renderer == "pyvista":
                raise RenderError(f"pyvista failed: {e}") from None
    try:
        return [_render_matplotlib(p, c, half_w, half_h, size) for p, c in zip(panels, colours)], "matplotlib"
    except Exception as e:
        raise RenderError(f"matplotlib failed: {e}") from None


def surface_figure(panels: list[Panel], clim: tuple[float, float, bool], *, renderer: str = "auto",
                   columns: int | None = None, title: str = "") -> tuple[Figure, str]:
    """A grid of 3-D views with one colour bar (photons mm^-2). ``columns`` lays panels out
    in reading order; None uses each panel's row and col."""
    if not panels:
        raise RenderError("no surface to draw")
    vmin, vmax, over = clim
    cmap = colormaps["viridis"].with_extremes(bad=UNOBSERVED_GREY)
    norm = Normalize(vmin, vmax)
    if columns is not None:
        for i, p in enumerate(panels):
            p.row, p.col = divmod(i, columns)
    rows = max(p.row for p in panels) + 1
    cols = max(p.col for p in panels) + 1
    imgs, used = render_panels(panels, norm, cmap, renderer=renderer, max_panel_px=300 if cols <= 4 else 200)
    h, w = imgs[0].shape[:2]
    # laid out by hand, in inches: panels at one image pixel per figure pixel, no gaps to fill
    pw, ph = w / 100, h / 100
    titled = any(p.title and p.row > 0 for p in panels)
    left = 0.75 if any(p.row_label for p in panels) else 0.1
    gap_x, gap_y, top, bottom, bar = 0.08, (0.3 if titled else 0.12), 0.75, 0.4, 1.25
    W = left + cols * pw + (cols - 1) * gap_x + bar
    content = rows * ph + (rows - 1) * gap_y
    bar_h = max(content, 2.6)  # the colour bar's label needs about this much beside a single short row
    pad = (bar_h - content) / 2
    H = top + bar_h + bottom
    fig = Figure(figsize=(W, H))
    FigureCanvasAgg(fig)
    for p, im in zip(panels, imgs):
        x0 = left + p.col * (pw + gap_x)
        y0 = H - top - pad - (p.row + 1) * ph - p.row * gap_y
        ax = fig.add_axes((x0 / W, y0 / H, pw / W, ph / H))
        ax.imshow(im, interpolation="antialiased")
        ax.set_axis_off()
        if p.title:
            ax.set_title(p.title, fontsize=9, pad=3)
        if p.col == 0 and p.row_label:
            ax.text(-0.03, 0.5, p.row_label, transform=ax.transAxes, ha="right", va="center", fontsize=8)
    cax = fig.add_axes(((W - bar + 0.2) / W, bottom / H, 0.16 / W, bar_h / H))
    cb = fig.colorbar(ScalarMappable(norm=norm, cmap=cmap), cax=cax, extend="max" if over else "neither")
    cb.set_label(scaled(cb.ax.yaxis, max(abs(vmin), abs(vmax)), *EXITANCE), fontsize=9)
    handles = [Patch(color=UNOBSERVED_GREY, label="unobserved element"),
               Patch(color=NO_ELEMENT_GREY, label="not an element (occluder only)")]
    if any(p.poorly is not None and p.poorly.any() for p in panels):
        handles.append(Patch(facecolor="white", edgecolor="0.4", hatch="///",
                             label="poorly observed (hatched: pale stripes)"))
    fig.legend(handles=handles, loc="lower center", bbox_to_anchor=(0.5, 0.0), ncol=len(handles), fontsize=8,
               frameon=False)
    fig.suptitle(title)
    return fig, used


# ------------------------------------------------------------------ 3. slice
def _wrap(a):
    return (np.asarray(a, float) + 180.0) % 360.0 - 180.0


def _angle_axis(ax):
    ax.set_xlim(-180, 180)
    ax.xaxis.set_major_locator(MultipleLocator(90))
    ax.xaxis.set_minor_locator(MultipleLocator(30))
    ax.grid(True, lw=0.4, alpha=0.5)


def slice_figure(angles_deg, per_pose, joint, truth, labels, *, rotations_deg, title="") -> Figure:
    """Exitance against angle: one panel per pose (with the truth) and one with all overlaid."""
    P = len(per_pose)
    n = P + 1
    cols = min(4, n)
    rows = -(-n // cols)
    fig = _figure(3.4 * cols + 0.4, 2.7 * rows + 0.6)
    axs = np.atleast_2d(fig.subplots(rows, cols, sharex=True, sharey=True, squeeze=False)).ravel()
    mk = "o" if len(angles_deg) <= 80 else None
    colours = pose_colours(P)
    for k in range(P):
        ax = axs[k]
        if truth is not None:
            ax.plot(angles_deg, truth, "--", color="k", lw=1.1, label="ground truth")
        ax.plot(angles_deg, per_pose[k], "-", marker=mk, ms=2.5, color=colours[k], lw=1.3, label="reconstruction")
        ax.axvline(_wrap(-rotations_deg[k]), color="0.4", ls=":", lw=0.9)
        ax.set_title(f"pose {k + 1}: {labels[k]}", fontsize=9)
    ax = axs[P]
    for k in range(P):
        ax.plot(angles_deg, per_pose[k], "-", color=colours[k], lw=0.9, label=f"{k + 1}")
    if joint is not None:
        ax.plot(angles_deg, joint, "-", color=JOINT_COLOUR, lw=2.2, label="joint")
    if truth is not None:
        ax.plot(angles_deg, truth, "--", color="k", lw=1.2, label="truth")
    ax.set_title("all poses overlaid", fontsize=9)
    ax.legend(fontsize=7, ncol=2 if P > 4 else 1, loc="upper right", title="pose", title_fontsize=7)
    axs[0].legend(fontsize=7, loc="upper right")
    for ax in axs[n:]:
        ax.set_axis_off()
    for ax in axs[:n]:
        _angle_axis(ax)
        ax.set_ylim(bottom=min(0.0, ax.get_ylim()[0]))
    fig.supxlabel(ANGLE_LABEL, fontsize=9)
    vmax = max([np.nanmax(np.abs(v)) for v in (per_pose, joint, truth) if v is not None and np.any(np.isfinite(v))] or [1.0])
    fig.supylabel(scaled(axs[0].yaxis, vmax, *EXITANCE), fontsize=9)
    fig.suptitle(title)
    return fig


# ------------------------------------------------------------------ 4. totals
def pose_axis(heights_mm, rotations_deg):
    """x values, label and tick labels for per-pose plots: the one thing that varies, or the pose number."""
    h, r = np.asarray(heights_mm, float), np.asarray(rotations_deg, float)
    if np.ptp(h) == 0 and np.ptp(r) > 0 and len(np.unique(r)) == len(r):
        return r, "rotation (°)", None
    if np.ptp(r) == 0 and len(np.unique(h)) == len(h):
        return h, "stage height (mm)", None
    return np.arange(1, len(h) + 1), "pose", pose_labels(h, r)


def totals_figure(heights_mm, rotations_deg, totals: dict[str, np.ndarray], *, truth_total=None, joint_total=None,
                  spreads: dict | None = None, truth_observed=None) -> Figure:
    """Left: every total divided by its own mean over poses; right: reconstructed totals in photons."""
    x, xlabel, ticks = pose_axis(heights_mm, rotations_deg)
    fig = _figure(11.0, 4.3)
    ax, ax2 = fig.subplots(1, 2)
    styles = {"direct_roi": ("s", "C0"), "backprojection": ("^", "C2"), "reconstruction": ("o", JOINT_COLOUR)}
    for name, v in totals.items():
        mean = np.nanmean(v)
        if not np.isfinite(mean) or mean == 0:
            continue
        sp = (spreads or {}).get(name)
        m, c = styles.get(name, ("o", None))
        ax.plot(x, v / mean, "-", marker=m, color=c,
                label=SERIES_NAMES.get(name, name) + (f" (spread {sp:.1%})" if sp is not None else ""))
    ax.axhline(1.0, color="0.6", lw=0.8)
    ax.set_ylabel("total / its mean over poses (dimensionless)")
    ax.set_title("spread of each estimate over poses")
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=8)
    else:  # every total is 0: nothing to spread
        ax.text(0.5, 0.5, "no light in any pose:\nno spread to show", ha="center", va="center", transform=ax.transAxes)
    ax2.plot(x, totals["reconstruction"], "o-", color=JOINT_COLOUR, label="reconstruction, per pose")
    if joint_total is not None:
        ax2.axhline(joint_total, color="C1", ls="-.", label=f"joint over poses: {joint_total:.4g}")
    if truth_total is not None:
        ax2.axhline(truth_total, color="k", ls="--", label=f"ground truth, all elements: {truth_total:.4g}")
    if truth_observed is not None:
        # what a reconstruction can recover: light leaving elements that the pose's views see
        ax2.plot(x, truth_observed, "x:", color="k", label="ground truth on the elements each pose observes")
    tops = [np.nanmax(totals["reconstruction"]), truth_total or 0.0, joint_total or 0.0]
    ax2.set_ylim(0, 1.12 * max(tops) if max(tops) > 0 else 1.0)
    ax2.set_ylabel(scaled(ax2.yaxis, max(np.nanmax(totals["reconstruction"]), truth_total or 0, joint_total or 0),
                          "total flux", "photons"))
    ax2.set_title("reconstructed total flux")
    ax2.legend(fontsize=8, loc="center right")
    for a in (ax, ax2):
        a.set_xlabel(xlabel)
        a.grid(True, lw=0.4, alpha=0.5)
        if ticks is not None:
            a.set_xticks(x, ticks, rotation=30 if len(x) > 3 else 0, ha="right" if len(x) > 3 else "center", fontsize=8)
        elif len(x) <= 12:
            a.set_xticks(x)
    return fig


# ------------------------------------------------------------------ 5. the study
def sweep_figure(methods: list[str], mean, sd, max_snr, labels) -> Figure:
    """Error (paper Eq. 15) against maximum SNR, mean ± sd over repeats, per method; one panel per pose."""
    M, L, P = mean.shape
    cols = min(P, 3)
    rows = -(-P // cols)
    fig = _figure(2.9 * cols + 3.6, 2.9 * rows + 1.0)
    axs = np.atleast_2d(fig.subplots(rows, cols, sharex=True, sharey=True, squeeze=False)).ravel()
    for k in range(P):
        ax = axs[k]
        for i in range(M):
            ok = np.isfinite(mean[i, :, k]) & np.isfinite(max_snr[:, k])
            if not ok.any():
                continue
            o = np.flatnonzero(ok)[np.argsort(max_snr[ok, k])]
            ax.errorbar(max_snr[o, k], 100 * mean[i, o, k], yerr=100 * np.nan_to_num(sd[i, o, k]), marker="o", ms=3.5,
                        capsize=2.5, lw=1.1, color=f"C{i}", label=methods[i])
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_title(labels[k], fontsize=9)
        ax.grid(True, which="major", lw=0.4, alpha=0.6)
    for ax in axs[P:]:
        ax.set_axis_off()
    _log_ticks(axs[0].xaxis, axs[0].get_xlim(), "{:g}")
    _log_ticks(axs[0].yaxis, axs[0].get_ylim(), "{:g}%")
    handles, names = axs[0].get_legend_handles_labels()
    fig.legend(handles, names, loc="outside right upper", fontsize=8, frameon=False, title="method", title_fontsize=8)
    fig.supxlabel("maximum SNR of the image, √(largest pixel in photons) (dimensionless)", fontsize=9)
    fig.supylabel("error Σ|b̃ − b| / Σb (%)", fontsize=9)
    fig.suptitle("reconstruction error against SNR (mean ± sd over noise repeats)", x=0.02, ha="left")
    return fig


def _log_ticks(axis, lim, fmt: str) -> None:
    """Ticks at 1-2-5 × 10^k on a log axis, labelled plainly (no 2×10⁰ clutter)."""
    lo, hi = sorted(lim)
    lo = max(lo, 1e-12)
    decades = range(int(np.floor(np.log10(lo))) - 1, int(np.ceil(np.log10(hi))) + 1)
    for mantissas in ((1, 2, 5), (1, 2, 3, 5, 7), (1, 1.5, 2, 3, 4, 5, 6, 7, 8, 9)):
        ticks = [t for t in (m * 10.0**e for e in decades for m in mantissas) if lo <= t <= hi]
        if len(ticks) >= 3:
            break
    if len(ticks) > 6:
        ticks = [t for t in ticks if round(t / 10.0 ** np.floor(np.log10(t))) in (1, 5)]
        if len(ticks) > 6:
            ticks = [t for t in ticks if round(t / 10.0 ** np.floor(np.log10(t))) == 1]
    axis.set_major_locator(FixedLocator(ticks))
    axis.set_major_formatter(FuncFormatter(lambda v, _: fmt.format(float(f"{v:.3g}"))))
    axis.set_minor_formatter(NullFormatter())


def sensitivity_figure(angles_deg, per_pose, per_view, view_names, labels) -> Figure:
    """Column sums of T against element angle: per pose, and (with mirrors) per view at pose 1."""
    two = per_view is not None
    fig = _figure(11.0 if two else 6.5, 4.2)
    axs = fig.subplots(1, 2 if two else 1, sharey=True, squeeze=False).ravel()
    colours = pose_colours(len(per_pose))
    for k, s in enumerate(per_pose):
        axs[0].plot(angles_deg, s, "-", color=colours[k], lw=1.2, label=labels[k])
    axs[0].set_title("combined T, per pose")
    axs[0].legend(fontsize=7, ncol=2 if len(per_pose) > 5 else 1)
    if two:
        for v in range(per_view.shape[1]):
            axs[1].plot(angles_deg, per_view[0, v], "-", color=f"C{v}", lw=1.2,
                        label=view_names[v] if v < len(view_names) else f"view {v}")
        axs[1].set_title(f"each view, pose 1 ({labels[0]})")
        axs[1].legend(fontsize=8)
    axs[0].set_ylabel(scaled(axs[0].yaxis, np.nanmax(per_pose), "sensitivity: column sum of T", "dimensionless"))
    for ax in axs:
        _angle_axis(ax)
        ax.set_xlabel(ANGLE_LABEL, fontsize=8)
        ax.set_ylim(bottom=0)
    return fig


def emission_figure(angle_deg, relative_radiance, label: str) -> Figure:
    """The emission profile used, L(theta)/L(0), beside Lambertian (1 everywhere), and the ray
    weight pi p(theta) of both (what each estimator multiplies a ray by, power kept per element)."""
    import textwrap

    # the model's full description (its terms and medium, 140-170 characters for diffuse) as a
    # wrapped title: in the legend it took the axes' width and the layout collapsed them
    short, _, terms = str(label).partition(" with ")
    fig = _figure(9.0, 3.6 if not terms else 4.2)
    if terms:
        fig.suptitle(textwrap.fill(str(label), 110), fontsize=8)
    ax, ax2 = fig.subplots(1, 2)
    a = np.asarray(angle_deg, float)
    r = np.asarray(relative_radiance, float)
    ax.plot(a, np.ones_like(a), "--", color="0.4", label="lambertian")
    ax.plot(a, r, "-", color=JOINT_COLOUR, label=textwrap.shorten(short, 60, placeholder=" …"))
    ax.set_xlabel("emission angle from the surface normal (°)")
    ax.set_ylabel("L(θ) / L(0)")
    ax.set_xlim(0, 90)
    ax.set_ylim(0, 1.1)
    ax.xaxis.set_major_locator(MultipleLocator(15))
    ax.set_title("radiance relative to the normal")
    ax.legend(fontsize=8)
    # pi p = r / (2 int r mu dmu): normalised so each element emits the same power
    mu = np.cos(np.radians(a))
    order = np.argsort(mu)
    norm = 2 * np.trapezoid(r[order] * mu[order], mu[order])
    ax2.plot(a, np.ones_like(a), "--", color="0.4", label="lambertian")
    ax2.plot(a, r / norm if norm > 0 else r, "-", color=JOINT_COLOUR, label=short)
    ax2.set_xlabel("emission angle from the surface normal (°)")
    ax2.set_ylabel("π p(θ): radiance per unit exitance, × π")
    ax2.set_xlim(0, 90)
    ax2.set_ylim(0, None)
    ax2.xaxis.set_major_locator(MultipleLocator(15))
    ax2.set_title("the same power per element")
    return fig
