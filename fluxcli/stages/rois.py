"""The ``rois:`` of a config measured on the reconstructions of one ``reconstruct`` run.

reconstruct calls :meth:`RoiMeter.measure` right after each solve (each pose, then the
joint solve), while the solve's covariance is alive, then drops the covariance; at the end
:meth:`RoiMeter.write` puts the numbers into ``/rois`` of reconstruction.h5 and
:meth:`RoiMeter.write_csv` writes ``<workdir>/rois.csv`` (the contract other tools read).
The science is in :mod:`fluxcli.quantify.rois`.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .. import artefacts as A
from ..artefacts import reconstruction as RA
from ..errors import UserError
from ..quantify import rois as Q
from ..surface.mesh import element_ids_of


def regions(rois) -> list[Q.Region]:
    """The config's ``rois:`` (C.Roi, in order) as the science's regions."""
    return [Q.Region(name=r.name, kind=r.kind, center_mm=r.center_mm, radius_mm=r.radius_mm, min_mm=r.min_mm,
                     max_mm=r.max_mm, fraction=r.fraction, array=r.array, value=r.value, ids=r.ids)
            for r in rois]


def cell_array_of_elements(mesh: Path | None, surface, name: str, where: str) -> np.ndarray:
    """(n_elements,) int: the mesh file's integer cell array ``name`` per element (the value
    of most of its area where its triangles disagree); ``mesh``: subject.surface.mesh resolved
    (None: the surface is not a mesh file)."""
    if mesh is None:
        raise UserError(f"{where}: a cell_array ROI reads an integer cell array of the mesh file; subject.surface "
                        "is not a mesh file (give subject.surface.mesh, or use a sphere, box, disc or elements ROI).")
    import pyvista as pv

    path = Path(mesh)
    mesh = pv.read(str(path))
    if isinstance(mesh, pv.MultiBlock):
        mesh = mesh.combine()
    if not isinstance(mesh, pv.PolyData):
        mesh = mesh.extract_surface(algorithm=None)
    if name not in mesh.cell_data:
        have = ", ".join(sorted(mesh.cell_data.keys())) or "none"
        raise UserError(f"{where}: {path} has no cell array '{name}' (its cell arrays: {have}).")
    try:  # whole numbers, integer or floating point (as MATLAB and many writers store them)
        mesh.cell_data["_roi"] = element_ids_of(np.asarray(mesh.cell_data[name]), f"the cell array '{name}' of {path}")
    except ValueError as e:
        raise UserError(f"{where}: {str(e).replace('element ids', 'region values')}.") from None
    values = np.asarray(mesh.triangulate().cell_data["_roi"]).ravel()
    if len(values) != len(surface.faces):
        raise UserError(f"{where}: {path} has {len(values)} triangles but the subject's surface {len(surface.faces)} "
                        "(it was repaired on reading); the cell array cannot be matched to the elements.")
    ok = surface.element_of_face >= 0
    el, val, area = surface.element_of_face[ok], values[ok], surface.face_areas_mm2[ok]
    pairs, inv = np.unique(np.stack([el, val], axis=1), axis=0, return_inverse=True)
    weight = np.bincount(inv.ravel(), weights=area)
    order = np.lexsort((-weight, pairs[:, 0]))  # per element, the value with most area first
    first = np.unique(pairs[order, 0], return_index=True)[1]
    out = np.full(surface.n_elements, np.iinfo(np.int64).min, np.int64)
    out[pairs[order[first], 0]] = pairs[order[first], 1]
    return out


def check_ids(ids, surface, where: str) -> None:
    """An ``elements`` region's ids must all be elements of ``surface``: an id that is not (an
    off-by-one, ids from another mesh) would leave the region smaller than asked, silently."""
    known = np.asarray(surface.element_ids) if surface.element_ids is not None else np.arange(surface.n_elements)
    missing = sorted(set(int(i) for i in ids) - set(known.tolist()))
    if not missing:
        return
    lo, hi = int(known.min()), int(known.max())
    kind = ("the mesh file's element ids" if surface.element_ids is not None
            else f"indices from 0 (the surface has no element ids of its own, so {surface.n_elements} elements: 0..{hi})")
    shown = ", ".join(map(str, missing[:8])) + (f" and {len(missing) - 8} more" if len(missing) > 8 else "")
    raise UserError(f"{where}: element id(s) {shown} are not on the subject's surface, whose ids are {kind}"
                    + (f", from {lo} to {hi}" if surface.element_ids is not None else "")
                    + "; give ids the surface has.")


class RoiMeter:
    """Measures the config's regions on each reconstruction of a run."""

    def __init__(self, rois, mesh: Path | None, surface, exposure_s: float | None):
        """``rois``: the config's regions (C.Roi); ``mesh``: the mesh file cell_array regions read."""
        self.regions = regions(rois)
        self.surface = surface
        self.areas = surface.element_areas_mm2
        self.exposure_s = exposure_s
        self.fixed = {}
        for k, r in enumerate(self.regions):
            where = f"rois[{k}] ({r.name})"
            if r.needs_map:
                continue
            if r.kind == "elements":
                check_ids(r.ids, surface, where)
            cells = cell_array_of_elements(mesh, surface, r.array, where) if r.kind == "cell_array" else None
            if cells is not None and not np.any(cells == int(r.value)):
                have = np.unique(cells[cells != np.iinfo(np.int64).min])
                shown = ", ".join(map(str, have[:12])) + (f" and {len(have) - 12} more" if len(have) > 12 else "")
                raise UserError(f"{where}: no element of the surface has {r.array} = {r.value}; the cell array "
                                f"holds {shown or 'no value'}.")
            self.fixed[r.name] = Q.members(r, surface, cell_array=cells)
        self.labels: list[str] = []
        self.poses: list[tuple] = []
        self.numbers: list[list[Q.RoiNumbers]] = []  # [map][roi]
        self.members: list[np.ndarray] = []  # [map] (n_roi, n_elements)

    def __bool__(self) -> bool:
        return bool(self.regions)

    def measure(self, label: str, height_mm, rotation_deg, res) -> None:
        """Measure every region on one reconstruction (``res``: power, observed, well_observed,
        covariance in element space or None)."""
        power = np.asarray(res.power, float)
        observed = np.asarray(res.observed, bool)
        with np.errstate(invalid="ignore", divide="ignore"):
            exitance = np.where(observed, power / self.areas, np.nan)
        M = np.array([self.fixed[r.name] if not r.needs_map else Q.members(r, self.surface, exitance=exitance)
                      for r in self.regions], bool).reshape(len(self.regions), -1)
        W = (M & observed).astype(float)
        var = np.full(len(self.regions), np.nan)
        cov = getattr(res, "covariance", None)
        if cov is not None and W.any():
            var = np.asarray(cov.variance_of(W), float).reshape(-1)
        t = self.exposure_s if self.exposure_s is not None else 1.0
        self.labels.append(label)
        self.poses.append((height_mm, rotation_deg))
        self.members.append(M)
        self.numbers.append([Q.measure(M[i], power, observed, res.well_observed, self.areas, exposure_s=t,
                                       variance=var[i]) for i in range(len(self.regions))])

    # ---------------------------------------------------------------- outputs
    def rows(self):
        return [(r.name, label, h, rot, self.numbers[m][i])
                for i, r in enumerate(self.regions) for m, (label, (h, rot)) in enumerate(zip(self.labels, self.poses))]

    def write(self, g) -> None:
        """``/rois`` of reconstruction.h5 (:func:`fluxcli.artefacts.reconstruction.write_rois`)."""
        RA.write_rois(g, self.regions, self.labels, self.exposure_s, self.numbers, self.members)

    def write_csv(self, path: Path) -> Path:
        A.write_text(path, Q.csv_text([(n, lab, h, r, x) for n, lab, h, r, x in self.rows()]))
        return path

    def table(self) -> tuple[list[str], list[list]]:
        unit = "photons/s" if self.exposure_s is not None else "photons/exposure"
        rows = []
        for name, label, _, _, x in self.rows():
            rows.append([name, label, f"{x.total_photons_per_s:.4g} ± {x.sigma_photons_per_s:.2g}"
                         + (f" [{x.status.split(':')[0].upper()}]" if x.status else ""),
                         f"{x.mean_radiance:.3g}", f"{x.area_mm2:.3g}", f"{x.observed_share:.0%}",
                         f"{x.well_observed_share:.0%}"])
        return ["roi", "pose", f"total ({unit}) ± 1 sd", "mean radiance (ph/s/cm²/sr)", "area mm²", "observed",
                "well observed"], rows
