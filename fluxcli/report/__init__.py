"""The report: figures and one self-contained HTML page, from artefacts only.

:func:`load` reads ``reconstruction.h5`` (and, when they exist, the T files it was
solved with and ``simulation.h5``) into a :class:`Study`; :func:`make_report` draws the
figures, writes ``summary.json`` (every number the page shows) and ``index.html`` (PNGs
embedded as data URIs, so the page opens from disk without a server).

Nothing here reads a config or prints: the ``report`` stage passes paths and settings
values, and shows the notes that :func:`make_report` returns.
"""

from __future__ import annotations

import json
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import artefacts as A
from ..surface.mesh import Surface


# ------------------------------------------------------------------ what the artefacts hold
@dataclass
class Sweep:
    """The study sweep of ``reconstruct``: errors (paper Eq. 15) per method, level, pose, repeat."""

    methods: list[str]
    error: np.ndarray  # (M, L, P, R) fraction
    mean: np.ndarray  # (M, L, P)
    sd: np.ndarray  # (M, L, P)
    max_snr: np.ndarray  # (L, P)
    levels_peak_photons: np.ndarray  # (L,)


@dataclass
class PoseTransfer:
    """What the report uses of one pose's T file."""

    sensitivity: np.ndarray  # (n_elements,) column sums of the combined T (dimensionless)
    sensitivity_per_view: np.ndarray  # (n_views, n_elements), each view's weight applied
    footprints: np.ndarray  # (n_views, ny, nx) bool: pixels the view reaches
    row_sums: np.ndarray  # (ny * nx,) row sums of the combined T
    vertices_mm: np.ndarray  # (V, 3) the surface placed at this pose


@dataclass
class Study:
    """Everything the figures need, read from the artefacts of one run."""

    reconstruction_path: Path
    method: str
    settings: dict
    lambda_used: float
    images_source: str
    joint: bool
    surface: Surface  # at rest (height 0, no rotation)
    heights_mm: np.ndarray  # (P,)
    rotations_deg: np.ndarray  # (P,)
    power: np.ndarray  # (n,) photons, NaN unobserved (/flux: joint over poses when there are several)
    observed: np.ndarray  # (n,) bool
    pose_power: np.ndarray  # (P, n) photons, NaN unobserved
    pose_observed: np.ndarray  # (P, n) bool
    pose_total: np.ndarray  # (P,) photons, as stored in /per_pose/total
    pose_lambda: np.ndarray  # (P,)
    measured: np.ndarray  # (P, ny, nx) photons per pixel
    fitted: np.ndarray  # (P, ny, nx) photons per pixel, NaN where not fitted
    valid: np.ndarray  # (P, ny, nx) bool
    pose_vertices_mm: np.ndarray | None = None  # (P, V, 3)
    backprojection_total: np.ndarray | None = None  # (P,)
    direct_roi_photons: np.ndarray | None = None  # (P,)
    truth_power: np.ndarray | None = None  # (n,) photons at the reconstructed level
    error_per_pose: np.ndarray | None = None
    total_ratio_per_pose: np.ndarray | None = None
    error: float | None = None  # over all elements, unobserved ones counted as 0 (the paper's)
    total_ratio: float | None = None
    error_observed: float | None = None  # over the observed elements
    total_ratio_observed: float | None = None
    sweep: Sweep | None = None
    snr: np.ndarray | None = None  # (L, P) max SNR per level and pose
    levels_peak_photons: np.ndarray | None = None  # (L,)
    transfer: list[PoseTransfer] | None = None
    geometry: "Geometry | None" = None  # from /geometry of the reconstruction
    notes: list[str] = field(default_factory=list)
    poorly: np.ndarray | None = None  # (n,) bool: poorly observed (/flux/observation == 1)
    pose_poorly: np.ndarray | None = None  # (P, n)
    warnings: list[str] = field(default_factory=list)  # /warnings of the reconstruction
    total_well_observed: float | None = None
    emission: dict | None = None  # /emission and the grazing shares of the reconstruction (issue 21)
    headline: tuple | None = None  # (photons, over what, why not over all observed elements or "")
    pose_chi2: np.ndarray | None = None  # (P,) χ²/pixel as reconstruct computed and warned on (its noise model)
    budget: dict | None = None  # /budget: each total's σ by cause (fluxcli.artefacts.reconstruction.read_budget)

    @property
    def n_poses(self) -> int:
        return len(self.heights_mm)

    @property
    def areas_mm2(self) -> np.ndarray:
        return self.surface.element_areas_mm2

    @property
    def is_line_detector(self) -> bool:
        return self.measured.shape[1] == 1

    @property
    def exitance(self) -> np.ndarray:
        """(n,) photons mm^-2, NaN unobserved."""
        return np.where(self.observed, self.power, np.nan) / self.areas_mm2

    @property
    def pose_exitance(self) -> np.ndarray:
        """(P, n) photons mm^-2, NaN unobserved."""
        return np.where(self.pose_observed, self.pose_power, np.nan) / self.areas_mm2

    @property
    def truth_exitance(self) -> np.ndarray | None:
        return None if self.truth_power is None else self.truth_power / self.areas_mm2


def _opt(g, name):
    return g[name][()] if name in g else None


def load(reconstruction: Path, *, t_cache_dir: Path | None = None, simulation: Path | None = None) -> Study:
    """Read a reconstruction artefact and, where present, its T files and the simulation.

    ``t_cache_dir`` is where the T files named in the reconstruction's inputs live;
    ``simulation`` supplies the SNR table when the reconstruction came from it."""
    with A.open_artefact(reconstruction, "reconstruction") as f:
        pp, fit, flux = f["per_pose"], f["fit"], f["flux"]
        st = Study(
            reconstruction_path=Path(reconstruction),
            method=str(f.attrs.get("method", "")),
            settings=json.loads(f.attrs.get("settings", "{}")),
            lambda_used=float(f.attrs.get("lambda_used", np.nan)),
            images_source=str(json.loads(f.attrs.get("inputs", "{}")).get("images", "")),
            joint=bool(flux.attrs.get("joint_over_poses", False)),
            surface=A.read_surface(f["surface"]),
            heights_mm=pp["heights_mm"][()].astype(float),
            rotations_deg=pp["rotations_deg"][()].astype(float),
            power=flux["power"][()],
            observed=flux["observed"][()].astype(bool),
            pose_power=pp["power"][()],
            pose_observed=pp["observed"][()].astype(bool),
            pose_total=pp["total"][()].astype(float),
            pose_lambda=np.asarray(pp["lambda"][()], float),
            measured=fit["measured"][()].astype(float),
            fitted=fit["fitted"][()].astype(float),
            valid=fit["valid"][()].astype(bool),
            pose_vertices_mm=_opt(pp, "vertices_mm"),
            backprojection_total=_opt(pp, "backprojection_total"),
            direct_roi_photons=_opt(pp, "direct_roi_photons"),
        )
        if "observation" in flux:  # issue 8: poorly observed elements are shown hatched, summed apart
            st.poorly = flux["observation"][()] == 1
            st.total_well_observed = float(flux["total_well_observed"][()])
        if "headline_total" in flux:
            st.headline = (float(flux["headline_total"][()]), str(flux["headline_total"].attrs.get("over", "")),
                           str(flux["headline_total"].attrs.get("reason", "")))
        if "observation" in pp:
            st.pose_poorly = pp["observation"][()] == 1
        if "warnings" in f:
            st.warnings = [w.decode() if isinstance(w, bytes) else str(w) for w in f["warnings"][()]]
        st.pose_chi2 = _opt(pp, "chi2_per_pixel")
        if "budget" in f:
            from ..artefacts.reconstruction import read_budget

            st.budget = read_budget(f["budget"])
        if "emission" in f:
            st.emission = _load_emission(f)
        if "truth" in f:
            t = f["truth"]
            st.truth_power = t["power"][()]
            st.error_per_pose = _opt(t, "error_per_pose")
            st.total_ratio_per_pose = _opt(t, "total_ratio_per_pose")
            st.error = float(t.attrs["error"]) if "error" in t.attrs else None
            st.total_ratio = float(t.attrs["total_ratio"]) if "total_ratio" in t.attrs else None
            st.error_observed = float(t.attrs["error_observed"]) if "error_observed" in t.attrs else None
            st.total_ratio_observed = float(t.attrs["total_ratio_observed"]) if "total_ratio_observed" in t.attrs else None
        if "sweep" in f:
            s = f["sweep"]
            st.sweep = Sweep(json.loads(s.attrs["methods"]), s["error"][()], s["mean"][()], s["sd"][()],
                             s["max_snr"][()], s["levels_peak_photons"][()])
            st.snr, st.levels_peak_photons = st.sweep.max_snr, st.sweep.levels_peak_photons
        keys = json.loads(json.loads(f.attrs.get("inputs", "{}")).get("T", "[]"))
        t_files = []
        if "geometry" in f:
            g = f["geometry"].attrs
            st.geometry = Geometry(axis_point_mm=tuple(float(x) for x in g["axis_point_mm"]),
                                   axis_direction=tuple(float(x) for x in g["axis_direction"]),
                                   look=tuple(float(x) for x in g["camera_look"]),
                                   up=tuple(float(x) for x in g["camera_up"]),
                                   view_names=tuple(json.loads(g["view_names"])))
            # relative paths are relative to the reconstruction's folder (portable artefacts)
            t_files = [Path(reconstruction).parent / p for p in json.loads(g.get("T_files", "[]"))]
    if st.snr is None and st.truth_power is not None and simulation is not None and Path(simulation).is_file():
        with A.open_artefact(simulation, "simulation") as f:
            snr = f["images/max_snr"][()]
            if snr.shape[1] == st.n_poses:
                st.snr, st.levels_peak_photons = snr, f["truth/levels_peak_photons"][()]
    if t_cache_dir is not None:
        st.transfer = _load_transfer(st, [Path(t_cache_dir) / f"{k}.h5" for k in keys])
    elif t_files:
        st.transfer = _load_transfer(st, t_files)
    _fill_gaps(st)
    return st


def _load_emission(f) -> dict:
    """The emission model a reconstruction used, its curve and the grazing shares (issue 21)."""
    g, pp = f["emission"], f["per_pose"]
    ri = float(g.attrs.get("refractive_index", np.nan))
    return {"model": str(g.attrs.get("model", "")), "description": str(g.attrs.get("description", "")),
            "refractive_index": ri if np.isfinite(ri) else None,
            "table_file": str(g.attrs.get("table_file", "")) or None,
            "angle_deg": g["angle_deg"][()], "relative_radiance": g["relative_radiance"][()],
            "bands_deg": pp["light_beyond_deg"].attrs["bands_deg"] if "light_beyond_deg" in pp else None,
            "light_beyond_per_pose": _opt(pp, "light_beyond_deg"),
            "light_beyond_joint": _opt(g, "joint_light_beyond_deg"),
            "total_beyond_per_pose": _opt(pp, "total_beyond_deg"),
            "total_beyond_joint": _opt(g, "joint_total_beyond_deg"),
            "residual_vs_angle_per_pose": _opt(pp, "residual_vs_angle")}


def _load_transfer(st: Study, paths: list[Path]) -> list[PoseTransfer] | None:
    if len(paths) != st.n_poses:
        st.notes.append("the reconstruction does not name one T file per pose; sensitivity and view outlines are left out.")
        return None
    missing = [p for p in paths if not p.is_file()]
    if missing:
        st.notes.append(f"{len(missing)} T file(s) the reconstruction used are no longer in the cache "
                        f"({missing[0].parent}); run 'fluxmap build-T' to see sensitivity and view outlines.")
        return None
    ny, nx = st.measured.shape[1:]
    out = []
    for p in paths:
        with A.open_artefact(p, "transfer") as f:
            T = A.read_csr(f["T"])
            if T.shape != (nx * ny, st.surface.n_elements):
                st.notes.append(f"T file {p.name} is {T.shape[0]} pixels x {T.shape[1]} elements; the reconstruction has "
                                f"{nx * ny} x {st.surface.n_elements}: sensitivity and view outlines are left out.")
                return None
            per_view, feet = [], []
            for k in sorted(f["views"], key=int):
                g = f["views"][k]
                Tv = A.read_csr(g)
                per_view.append(np.asarray(Tv.sum(axis=0)).ravel() * float(g.attrs.get("weight", 1.0)))
                feet.append((np.diff(Tv.indptr) > 0).reshape(ny, nx))
            out.append(PoseTransfer(np.asarray(T.sum(axis=0)).ravel(), np.array(per_view), np.array(feet),
                                    np.asarray(T.sum(axis=1)).ravel(), f["surface/vertices"][()]))
    return out


def _fill_gaps(st: Study) -> None:
    """Older reconstruction artefacts lack some per-pose numbers: take them from the T files."""
    tr = st.transfer
    if st.pose_vertices_mm is None and tr is not None and all(t.vertices_mm.shape == st.surface.vertices_mm.shape for t in tr):
        st.pose_vertices_mm = np.array([t.vertices_mm for t in tr])
    if tr is not None:
        a = st.measured.reshape(st.n_poses, -1)
        if st.backprojection_total is None:  # sum_j (T'a)_j = sum_i a_i (row sum of T)_i
            st.backprojection_total = np.array([np.nansum(t.row_sums * ak) for t, ak in zip(tr, a)])
        if st.direct_roi_photons is None:
            st.direct_roi_photons = np.array([np.nansum(ak[t.footprints[0].ravel()]) for t, ak in zip(tr, a)])


# ------------------------------------------------------------------ geometry of the subject
def element_angles_deg(centroids_mm: np.ndarray, axis_point_mm, axis_direction, reference) -> np.ndarray:
    """Angle of each element about the subject's axis, in [-180, 180) degrees.

    0 is the side facing ``reference`` (a direction, e.g. towards the camera); angles are
    right-handed about ``axis_direction``, the sense in which a pose's rotation turns the
    subject, so the element facing the reference at rotation θ lies at −θ at rest."""
    a = np.asarray(axis_direction, float)
    a = a / np.linalg.norm(a)
    r = np.asarray(reference, float)
    e1 = r - (r @ a) * a
    if np.linalg.norm(e1) < 1e-9:  # looking along the axis: any perpendicular will do
        e1 = np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 1.0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(a, e1)
    d = np.asarray(centroids_mm, float) - np.asarray(axis_point_mm, float)
    ang = np.degrees(np.arctan2(d @ e2, d @ e1))
    return (ang + 180.0) % 360.0 - 180.0


def axial_positions_mm(centroids_mm: np.ndarray, vertices_mm: np.ndarray, axis_point_mm, axis_direction) -> np.ndarray:
    """Position of each element along the axis, from the middle of the subject's extent."""
    a = np.asarray(axis_direction, float) / np.linalg.norm(axis_direction)
    sv = (np.asarray(vertices_mm) - axis_point_mm) @ a
    return (np.asarray(centroids_mm) - axis_point_mm) @ a - (sv.min() + sv.max()) / 2


def slice_elements(axial_mm: np.ndarray, areas_mm2: np.ndarray, at_mm: float) -> np.ndarray:
    """Indices of the elements whose centroids lie closest to the plane ``axial = at_mm``.

    On a regular mesh that is the ring of elements nearest the plane (both rings when the
    plane falls exactly between two); on an irregular mesh, every element within half an
    element's size of the plane (or the nearest ones, if none is that close)."""
    d = np.abs(axial_mm - at_mm)
    size = float(np.sqrt(np.median(areas_mm2[areas_mm2 > 0]))) if np.any(areas_mm2 > 0) else 1.0
    return np.flatnonzero(d <= max(d.min() + 0.05 * size, 0.5 * size))


def merge_equal_angles(angles_deg: np.ndarray, values: np.ndarray, tol_deg: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """Sort by angle and average values whose angles agree within ``tol_deg`` (two rings
    equally near the plane give one curve, the mean of the two, not a zig-zag).
    ``values`` is (..., n); NaN (unobserved) only where every merged value is NaN."""
    order = np.argsort(angles_deg, kind="stable")
    ang = angles_deg[order]
    vals = np.asarray(values)[..., order]
    group = np.concatenate([[0], np.cumsum(np.diff(ang) > tol_deg)])
    n = group[-1] + 1 if len(group) else 0
    out_ang = np.array([ang[group == g].mean() for g in range(n)])
    with warnings.catch_warnings():  # an all-NaN group is meant: it stays NaN (unobserved)
        warnings.simplefilter("ignore", RuntimeWarning)
        out = np.stack([np.nanmean(vals[..., group == g], axis=-1) for g in range(n)], axis=-1) if n else vals
    return out_ang, out


def spread(values) -> float | None:
    """(max − min) / mean over poses, or None when undefined."""
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    if len(v) == 0 or v.mean() == 0:
        return None
    return float((v.max() - v.min()) / v.mean())


# ------------------------------------------------------------------ the numbers
def summarise(st: Study, *, title: str, slice_axial_mm: float, view_names: list[str]) -> dict:
    """Every number the page shows, as plain JSON types (NaN as null)."""
    P = st.n_poses
    poses = []
    chi2 = chi2_per_pixel(st)
    for k in range(P):
        row = {"height_mm": st.heights_mm[k], "rotation_deg": st.rotations_deg[k],
               "total_photons": st.pose_total[k],
               "observed_fraction": float(st.pose_observed[k].mean()),
               "lambda": st.pose_lambda[k], "chi2_per_pixel": chi2[k],
               "max_measured_photons_per_pixel": float(np.nanmax(st.measured[k])) if np.any(np.isfinite(st.measured[k])) else None}
        if st.direct_roi_photons is not None:
            row["direct_roi_photons"] = st.direct_roi_photons[k]
        if st.backprojection_total is not None:
            row["backprojection_total"] = st.backprojection_total[k]
        if st.error_per_pose is not None:
            row["error"] = st.error_per_pose[k]
        if st.total_ratio_per_pose is not None:
            row["total_ratio"] = st.total_ratio_per_pose[k]
        if st.transfer is not None:
            areas = st.areas_mm2
            row["collection_efficiency"] = {n: float(s @ areas / areas.sum())
                                            for n, s in zip(view_names, st.transfer[k].sensitivity_per_view)}
        poses.append(row)
    totals = _totals(st)
    normalised = {k: (np.asarray(v, float) / np.nanmean(v)).tolist() if np.nanmean(v) != 0 else None
                  for k, v in totals.items()}
    out = {
        "title": title,
        "reconstruction": st.reconstruction_path.name,  # beside the report's folder: portable
        "images": st.images_source,
        "method": st.method,
        "settings": st.settings,
        "lambda_used": st.lambda_used,
        "joint_over_poses": st.joint,
        "n_elements": st.surface.n_elements,
        "pixels": [st.measured.shape[2], st.measured.shape[1]],
        "views": view_names,
        "poses": poses,
        "flux_total_photons": float(np.nansum(st.power)),
        "flux_observed_fraction": float(st.observed.mean()),
        "flux_total_well_observed_photons": st.total_well_observed,
        "flux_headline_total_photons": st.headline[0] if st.headline else float(np.nansum(st.power)),
        "flux_headline_over": st.headline[1] if st.headline else "observed elements",
        "flux_headline_reason": (st.headline[2] or None) if st.headline else None,
        "flux_poorly_observed_fraction": float(st.poorly.mean()) if st.poorly is not None else None,
        "warnings": st.warnings,
        "budget": st.budget,  # each total's σ by cause (photons per exposure), poses then joint
        "totals_normalised_by_mean": normalised,
        "spreads": {k: spread(v) for k, v in totals.items()},
        "slice_axial_mm": slice_axial_mm,
    }
    if st.truth_power is not None:
        out["truth_total_photons"] = float(st.truth_power.sum())
        out["truth_observed_total_photons_per_pose"] = [float(st.truth_power[o].sum()) for o in st.pose_observed]
        out["error"] = st.error
        out["total_ratio"] = st.total_ratio
        out["error_observed"] = st.error_observed
        out["total_ratio_observed"] = st.total_ratio_observed
    if st.snr is not None:
        out["snr_table"] = {"levels_peak_photons": st.levels_peak_photons, "heights_mm": st.heights_mm,
                            "rotations_deg": st.rotations_deg, "max_snr": st.snr,
                            "layout": "max_snr[level][pose]"}
    if st.sweep is not None:
        sw = st.sweep
        out["sweep"] = {"methods": sw.methods, "levels_peak_photons": sw.levels_peak_photons,
                        "max_snr": sw.max_snr, "mean_error": sw.mean, "sd_error": sw.sd,
                        "repeats": int(sw.error.shape[3]), "layout": "[method][level][pose]; errors as fractions"}
    return jsonable(out)


def chi2_per_pixel(st: Study) -> list[float | None]:
    """χ²/pixel per pose: the one reconstruct computed under its noise model and warned on
    (one number per pose, everywhere); for an artefact without it, the mean of
    residual² / max(measured, 1) over the fitted pixels that some view reaches."""
    if st.pose_chi2 is not None and len(st.pose_chi2) == st.n_poses:
        return [float(c) if np.isfinite(c) else None for c in np.asarray(st.pose_chi2, float)]
    out = []
    for k, (m, fi, v) in enumerate(zip(st.measured, st.fitted, st.valid)):
        ok = v & np.isfinite(fi) & np.isfinite(m)
        if st.transfer is not None:
            ok &= np.any(st.transfer[k].footprints, axis=0)
        out.append(float(np.mean((m[ok] - fi[ok]) ** 2 / np.maximum(m[ok], 1.0))) if ok.any() else None)
    return out


def jsonable(x):
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return jsonable(x.tolist())
    if isinstance(x, (np.bool_, bool)):
        return bool(x)
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        return float(x) if np.isfinite(x) else None
    if isinstance(x, Path):
        return str(x)
    return x


# ------------------------------------------------------------------ the whole report
@dataclass
class Geometry:
    """Where the subject's axis is and which way the camera looks (world frame, mm)."""

    axis_point_mm: tuple[float, float, float]
    axis_direction: tuple[float, float, float]
    look: tuple[float, float, float] = (0.0, 0.0, -1.0)
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    view_names: tuple[str, ...] = ("direct",)


def make_report(study: Study, out_dir: Path, *, title: str, geometry: Geometry, slice_axial_mm: float = 0.0,
                surface_views: bool = True, renderer: str = "auto", extra: dict | None = None,
                sections: list | None = None, record: list | None = None, rig=None,
                exposure_s: float | None = None) -> tuple[Path, dict]:
    """Draw every figure into ``out_dir``, write summary.json and index.html.

    ``renderer`` is ``auto`` (pyvista, else matplotlib), ``pyvista`` or ``matplotlib``
    for the 3-D views. ``extra`` is merged into summary.json (e.g. provenance).
    ``record`` ((label, value) rows: camera, lens, files and digests), ``rig`` (a
    :class:`fluxcli.report.view3d.Rig`) and ``exposure_s`` (rates and radiance when known)
    feed the lab-notebook blocks of :mod:`fluxcli.report.notebook`.
    Returns the index.html path and the summary."""
    from . import figures as F
    from .page import Page

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    names = list(geometry.view_names)
    if study.transfer is not None and len(names) != study.transfer[0].footprints.shape[0]:
        names = ["direct"] + [f"mirror {k}" for k in range(1, study.transfer[0].footprints.shape[0])]
    summary = summarise(study, title=title, slice_axial_mm=slice_axial_mm, view_names=names)
    figures: list[str] = []

    def save(fig, name: str) -> Path:
        path = out_dir / name
        F.save(fig, path)
        figures.append(name)
        return path

    page = Page(title)
    page.header(summary)
    from . import notebook  # warnings, what was measured with what, the share of light, the 3-D map
    notebook.add_top(page, study, summary, record, exposure_s=exposure_s)
    notebook.add_3d_view(page, study, rig=rig, exposure_s=exposure_s)

    # ---------------------------------------------------------------- angles and the slice
    surf = study.surface
    cen = surf.element_centroids_mm
    toward_camera = -np.asarray(geometry.look, float)
    angles = element_angles_deg(cen, geometry.axis_point_mm, geometry.axis_direction, toward_camera)
    axial = axial_positions_mm(cen, surf.vertices_mm, np.asarray(geometry.axis_point_mm), geometry.axis_direction)
    sel = np.arange(surf.n_elements) if study.is_line_detector else slice_elements(axial, study.areas_mm2, slice_axial_mm)
    sl_ang, sl_vals = merge_equal_angles(angles[sel], np.vstack([study.pose_exitance[:, sel], study.exitance[sel][None]]))
    sl_truth = merge_equal_angles(angles[sel], study.truth_exitance[sel])[1] if study.truth_power is not None else None
    summary["slice"] = jsonable({
        "axial_mm": slice_axial_mm, "elements": sel, "element_axial_mm": axial[sel],
        "angle_deg": sl_ang, "exitance_per_pose": sl_vals[:-1], "exitance_joint": sl_vals[-1],
        "exitance_truth": sl_truth, "unit": "photons mm^-2"})

    # ---------------------------------------------------------------- 1. images
    page.section("images", "Measured and fitted images")
    page.text(
        "Per pose: the measured image, the image the reconstruction predicts (a = T b̃), both on one colour "
        "scale, and their difference on a symmetric diverging scale (white = 0), in photons per pixel. "
        "Direct and mirror views share one frame, as on the detector; outlines mark the pixels each view "
        "can reach. Grey: pixels left out of the fit (saturated or not finite). "
        "χ²/pixel is reconstruct's: the mean of residual² / σ² of the noise model (evaluated on the fitted "
        "image) over the pixels whose model holds at least one photon — the number it prints and warns on; about "
        "1 when the fit is as good as the noise allows.")
    labels = F.pose_labels(study.heights_mm, study.rotations_deg)
    axis_labels = F.image_axis_labels(geometry.look, geometry.up)
    for k in range(study.n_poses):
        feet = study.transfer[k].footprints if study.transfer is not None else None
        fig = F.fit_figure(study.measured[k], study.fitted[k], study.valid[k], footprints=feet, view_names=names,
                           title=f"pose {k + 1}: {labels[k]}", chi2=summary["poses"][k]["chi2_per_pixel"],
                           axis_labels=axis_labels)
        page.figure(save(fig, f"fit_pose{k + 1}.png"), f"Pose {k + 1} ({labels[k]}).")

    # ---------------------------------------------------------------- 2. flux on the surface
    truth_ex = study.truth_exitance
    if study.is_line_detector:
        page.section("surface", "Flux around the ring")
        page.text(
            "Exitance (photons mm⁻²) of every element against its angle about the ring's axis (0° faces the camera; "
            "the sense in which the poses turn the subject). One panel per pose and the joint reconstruction, "
            "with the ground truth where it is known. Gaps: elements no view observes (never drawn as zero).")
        fig = F.slice_figure(sl_ang, sl_vals[:-1], sl_vals[-1] if study.joint else None, sl_truth, labels,
                             rotations_deg=study.rotations_deg, title="exitance around the ring")
        page.figure(save(fig, "flux_ring.png"), "Flux around the ring, per pose and joint.")
    elif surface_views:
        page.section("surface", "Flux on the surface")
        clim = F.exitance_limits(study.pose_exitance, study.exitance, truth_ex)
        panels_cam, panels_rest = F.surface_panels(study, geometry, truth_ex, labels)
        try:
            fig_rest, used = F.surface_figure(panels_rest, clim, renderer=renderer, columns=None,
                                              title="in a common orientation: the subject at rest")
            fig_cam = None
            if panels_cam:
                fig_cam, _ = F.surface_figure(panels_cam, clim, renderer=used, columns=min(4, len(panels_cam)),
                                              title="reconstructed exitance, each pose seen from the camera")
            else:
                study.notes.append("where each pose placed the surface is unknown (no /per_pose/vertices_mm and no "
                                   "T files): the views from the camera are left out.")
            summary["renderer"] = used
            if used != "pyvista" and renderer == "auto":
                study.notes.append("pyvista could not render off-screen here; the 3-D views were drawn with matplotlib.")
            page.text(
                "Reconstructed exitance (photons mm⁻²) on the subject's surface, one colour scale for every panel. "
                "Mid grey: elements no view observes (unknown, not zero); light grey: faces that are not elements "
                "(e.g. cylinder caps). "
                + ("First, each pose's own reconstruction on the surface where that pose placed it, seen from the "
                   "camera (looking along the optical axis, the image's up at the top: the orientation of the direct "
                   "view in the images above). Then e" if fig_cam is not None else "E")
                + "very reconstruction on the subject at rest, seen from the camera side and turned 120° and 240° "
                "about its axis, so that the poses can be compared element by element"
                + (", next to the joint reconstruction and the ground truth." if truth_ex is not None else "."))
            if fig_cam is not None:
                page.figure(save(fig_cam, "surface_camera.png"), "Each pose from the camera.")
            page.figure(save(fig_rest, "surface_common.png"), "All poses in the rest orientation.")
        except F.RenderError as e:
            study.notes.append(f"the 3-D views could not be drawn ({e}).")
    # ---------------------------------------------------------------- 3. slice
    if not study.is_line_detector:
        page.section("slice", f"Slice around the circumference at {slice_axial_mm:g} mm")
        page.text(
            f"Exitance (photons mm⁻²) of the elements whose centroids lie closest to the plane {slice_axial_mm:g} mm "
            f"along the subject's axis from its middle ({len(sel)} elements; where two rings are equally close their "
            "mean is shown), against the angle about the axis: 0° faces the camera at rest, angles run in the sense "
            "the poses turn the subject, and the dotted line marks the element facing the camera at that pose. "
            "Gaps: unobserved elements.")
        fig = F.slice_figure(sl_ang, sl_vals[:-1], sl_vals[-1] if study.joint else None, sl_truth, labels,
                             rotations_deg=study.rotations_deg, title=f"slice at {slice_axial_mm:g} mm along the axis")
        page.figure(save(fig, "slice.png"), "Slice through the reconstructions (and the truth).")

    # ---------------------------------------------------------------- 4. totals
    page.section("totals", "Total flux per pose")
    sp = summary["spreads"]
    spread_txt = ", ".join(f"{F.SERIES_NAMES[k]} {v:.1%}" for k, v in sp.items() if v is not None)
    page.text(
        "Left: each estimate of the total divided by its own mean over the poses, so their spreads compare: the "
        "photons summed over the direct view's region of the image (the usual ROI number), the backprojection "
        "total (Σ Tᵀa) and the reconstructed total. Right: the reconstructed totals in photons"
        + (" against the ground truth." if study.truth_power is not None else ".")
        + f" Spread, (max − min) / mean over poses: {spread_txt}.")
    fig = F.totals_figure(study.heights_mm, study.rotations_deg, {k: np.asarray(v, float) for k, v in _totals(study).items()},
                          truth_total=float(study.truth_power.sum()) if study.truth_power is not None else None,
                          joint_total=float(np.nansum(study.power)) if study.joint else None, spreads=sp,
                          truth_observed=([float(study.truth_power[o].sum()) for o in study.pose_observed]
                                          if study.truth_power is not None else None))
    page.figure(save(fig, "totals.png"), "Total flux per pose.")
    page.pose_table(summary)
    if study.emission is not None:
        _emission_section(page, save, study, summary, labels)

    # ---------------------------------------------------------------- 5. the study
    if study.snr is not None or study.sweep is not None or study.transfer is not None:
        page.section("study", "Signal, noise and sensitivity")
    if study.snr is not None:
        page.text("Maximum SNR in the simulated images, √(largest noiseless pixel value), per signal level (the "
                  "truth scaled so its brightest element emits that many photons) and pose (the paper's Table 1).")
        page.snr_table(summary["snr_table"])
    if study.sweep is not None:
        sw = study.sweep
        page.text(f"Error Σ|b̃ − b| / Σb (paper Eq. 15) against the maximum SNR of the image, mean ± sd over "
                  f"{sw.error.shape[3]} noise repeats, per method and pose (the paper's Fig. 10).")
        fig = F.sweep_figure(sw.methods, sw.mean, sw.sd, sw.max_snr, labels)
        page.figure(save(fig, "sweep_error.png"), "Error against SNR.")
        page.sweep_table(summary["sweep"], labels)
    if study.transfer is not None:
        sens = np.array([t.sensitivity for t in study.transfer])
        views = np.array([t.sensitivity_per_view for t in study.transfer])
        where = "every element of the ring" if study.is_line_detector else f"the elements of the slice at {slice_axial_mm:g} mm"
        page.text(f"System sensitivity: the column sums of T, the fraction of each element's power that reaches the "
                  f"detector (dimensionless), for {where}, against the angle at rest, per pose (the paper's Fig. 7)"
                  + ("; right: each view's share at every pose." if views.shape[1] > 1 else "."))
        s_ang, s_vals = merge_equal_angles(angles[sel], sens[:, sel])
        v_vals = merge_equal_angles(angles[sel], views[:, :, sel])[1] if views.shape[1] > 1 else None
        fig = F.sensitivity_figure(s_ang, s_vals, v_vals, names, labels)
        page.figure(save(fig, "sensitivity.png"), "System sensitivity per element.")
        summary["sensitivity"] = jsonable({"angle_deg": s_ang, "per_pose": s_vals, "unit": "dimensionless"})

    for add in sections or ():  # more sections (e.g. the calibration): add(page, save) -> numbers for summary.json
        summary.update(jsonable(add(page, save)))
    page.notes(study.notes)
    summary["notes"] = list(study.notes)
    return _finish(out_dir, page, summary, figures, extra)


def _emission_section(page, save, study: Study, summary: dict, labels: list[str]) -> None:
    """Which emission model T was built with, its curve beside Lambertian, and how much of the
    observed light was seen at grazing angles (where the model matters most)."""
    from . import figures as F

    em = study.emission
    page.section("emission", "Emission model")
    ang, rad = np.asarray(em["angle_deg"], float), np.asarray(em["relative_radiance"], float)
    at = [30.0, 60.0, 75.0, 80.0]
    vals = np.interp(at, ang, rad)
    page.text(
        f"T was built with the emission model '{em['description']}': radiance leaving the surface is its exitance "
        "times p(θ), p normalised so that an element's power is the same whatever the model "
        "(docs/design.md, Emission). Relative to the normal it is "
        + ", ".join(f"{v:.2f} at {a:g}°" for a, v in zip(at, vals))
        + (" (Lambertian: 1 everywhere)." if em["model"] != "lambertian" else ".")
        + (" Light leaving tissue or a turbid phantom is better described by {model: diffuse, refractive_index: "
           "1.40}: read as Lambertian it is ~11 % too bright head-on and ~37 % too dim at 80° (Monte Carlo photons, n 1.40)."
           if em["model"] == "lambertian" else ""))
    fig = F.emission_figure(ang, rad, em["description"])
    page.figure(save(fig, "emission.png"), "The emission profile used, beside Lambertian.")
    out = {k: em[k] for k in ("model", "description", "refractive_index", "table_file")}
    out["relative_radiance"] = {"angle_deg": ang[::10], "value": rad[::10]}
    if em["light_beyond_per_pose"] is not None:
        bands = [float(b) for b in em["bands_deg"]]
        light = np.asarray(em["light_beyond_per_pose"], float)
        total = (np.asarray(em["total_beyond_per_pose"], float) if em["total_beyond_per_pose"] is not None
                 else np.full_like(light, np.nan))
        rows = [[labels[k]] + [f"{s:.1%}" for s in (*light[k], *total[k])] for k in range(len(light))]
        if em["light_beyond_joint"] is not None:
            jt = em["total_beyond_joint"] if em["total_beyond_joint"] is not None else [np.nan] * len(bands)
            rows.append(["joint"] + [f"{s:.1%}" for s in (*em["light_beyond_joint"], *jt)])
        page.text("Where the emission model matters: per pose, the share of the light in the model image (T b̃) that "
                  "left the surface beyond these angles from its normal, and the share of the reconstructed total "
                  "resting on such views (each element weighted by the share of its collected light seen from "
                  "there; an element seen only at grazing angles counts whole). Reconstruct warns when more than "
                  "25 % of a total rests beyond 75°.")
        page.table(["pose"] + [f"light beyond {b:g}°" for b in bands] + [f"total beyond {b:g}°" for b in bands], rows)
        out["bands_deg"] = bands
        out["light_beyond_per_pose"] = light
        out["light_beyond_joint"] = em["light_beyond_joint"]
        out["total_beyond_per_pose"] = total
        out["total_beyond_joint"] = em["total_beyond_joint"]
        out["residual_vs_angle_per_pose"] = em["residual_vs_angle_per_pose"]
    summary["emission"] = jsonable(out)


def _finish(out_dir: Path, page, summary: dict, figures: list[str], extra: dict | None) -> tuple[Path, dict]:
    """Write ``summary.json`` (with the figures' names and ``extra``) and ``index.html``."""
    summary["figures"] = figures
    if extra:
        summary.update(jsonable(extra))
    _write_text(out_dir / "summary.json", json.dumps(summary, indent=1))
    index = out_dir / "index.html"
    _write_text(index, page.html(out_dir))
    return index, summary


def _totals(st: Study) -> dict[str, np.ndarray]:
    out = {}
    if st.direct_roi_photons is not None:
        out["direct_roi"] = st.direct_roi_photons
    if st.backprojection_total is not None:
        out["backprojection"] = st.backprojection_total
    out["reconstruction"] = st.pose_total
    return out


def _write_text(path: Path, text: str) -> None:
    """Atomic: the file appears complete or not at all (the one atomic writer)."""
    A.write_text(path, text)


def sections_report(out_dir: Path, title: str, sections: list, *, extra: dict | None = None) -> tuple[Path, dict]:
    """A page of sections alone (no reconstruction yet: a calibrate-only or capture-only workdir,
    or ``make structured-light``'s surfaces).  Each section is ``add(page, save) -> numbers``;
    writes ``index.html``, the figures and ``summary.json`` into ``out_dir``."""
    from . import figures as F
    from .page import Page

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    figures: list[str] = []

    def save(fig, name: str) -> Path:
        F.save(fig, out_dir / name)
        figures.append(name)
        return out_dir / name

    page = Page(title)
    summary: dict = {}
    for add in sections:
        summary.update(jsonable(add(page, save)))
    return _finish(out_dir, page, summary, figures, extra)
