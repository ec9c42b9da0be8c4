"""The transfer artefacts: one T file per pose (a content-addressed cache entry) and the index.

The cache is a folder of ``<key>.h5`` files, ``key`` the sha256 of everything T depends
on (:func:`fluxcli.transfer_cache.key_parts`).  An entry that cannot be read (a killed run, a
corrupt chunk: every chunk carries a Fletcher-32 checksum) is reported by
:func:`check_entry` so that the caller rebuilds it; :func:`load_T` of a corrupt entry
names the file and the remedy.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from ..errors import UserError
from .pieces import read_csr, write_csr, write_surface
from .store import Provenance, open_artefact, portable_path, put, recorded_seconds, write_artefact


INDEX_FILE_NAME = "transfer.h5"  # build-T's index, in the workdir


def entry_path(cache_dir: Path, key: str) -> Path:
    return Path(cache_dir) / f"{key}.h5"


@dataclass
class TSummary:
    """What build-T prints of a cached T: non-zeros, efficiency per view, build time."""

    nnz: int
    efficiency: dict[str, float]
    seconds: float
    seen: dict[str, float] | None = None  # per view: fraction of the subject's area it sees

    def as_dict(self) -> dict:
        return {"nnz": self.nnz, "efficiency": self.efficiency, "seconds": self.seconds, "seen": self.seen or {}}


def seen_fraction(Tv: sp.csr_matrix, areas_mm2: np.ndarray) -> float:
    """Fraction of the subject's area (elements with a non-zero column) that a view sees."""
    col = np.asarray(Tv.sum(axis=0)).ravel()
    return float(areas_mm2[col > 0].sum() / areas_mm2.sum())


def efficiency(Tv: sp.csr_matrix, weight: float, areas_mm2: np.ndarray) -> float:
    """Collection efficiency of one view: the fraction of the power of a uniformly glowing
    surface the view delivers to the sensor (area-weighted mean column sum)."""
    col = np.asarray(Tv.sum(axis=0)).ravel() * weight
    # numpy's own (pairwise) sum, not a BLAS dot: the same bits however many BLAS threads this
    # process has (a Dask worker has one), so a cluster's build-T index matches the local one
    return float(np.sum(col * areas_mm2) / areas_mm2.sum())


def write_T(path: Path, *, T: sp.csr_matrix, T_per_view: list, view_kinds: list[str], weights: list[float],
            stats: list[dict], pixels: tuple[int, int], surface, occluders, height_mm: float, rotation_deg: float,
            estimator: str, seconds: float, config_sha256: str = "", provenance: Provenance | None = None,
            column_error=None, column_error_per_view=None, T_tangent=None) -> None:
    """Write one pose's T file atomically.

    ``column_error`` (n_elements,): the estimated L1 error of each column of T (same unit
    as T); ``column_error_per_view``: the same per view (weight not applied); ``T_tangent``
    (pixels x 2 elements, mm): the tangential-flux term of the emission profile, when it has one
    (:attr:`fluxcli.optics.transfer.TransferResult.T_tangent`)."""
    with write_artefact(path, "transfer", config_sha256=config_sha256, provenance=provenance) as f:
        write_csr(f.create_group("T"), T)
        f["T"].attrs["unit"] = "dimensionless (fraction of element power reaching the pixel)"
        f["T"].attrs["pixel_order"] = "row-major [row, col]; flat index row * nx + col"
        if column_error is not None:
            put(f, "T/column_error", np.asarray(column_error, float))
        if T_tangent is not None:
            write_csr(f.create_group("T_tangent"), T_tangent)
            f["T_tangent"].attrs["unit"] = ("mm (per unit of -grad_t M / M per element power; column 2j + a: along the "
                                            "face's in-plane unit vector a, fluxcli.optics.emission.face_frames)")
        write_surface(f.create_group("surface"), surface)
        occ = f.create_group("occluders")
        for k, o in enumerate(occluders):
            write_surface(occ.create_group(f"{k}"), o)
        vg = f.create_group("views")
        f.attrs["pixels"] = np.array(pixels)
        for k, (kind, w, Tv, st) in enumerate(zip(view_kinds, weights, T_per_view, stats)):
            g = vg.create_group(f"{k}")
            g.attrs["kind"] = kind
            g.attrs["weight"] = w
            write_csr(g, Tv)
            if column_error_per_view is not None:
                put(g, "column_error", np.asarray(column_error_per_view[k], float))
            for name, val in st.items():
                g.attrs[name] = val
        f.attrs["pose_height_mm"] = height_mm
        f.attrs["pose_rotation_deg"] = rotation_deg
        f.attrs["estimator"] = estimator
        f.attrs["build_seconds"] = recorded_seconds(seconds)


def load_T(path: Path) -> sp.csr_matrix:
    """The combined T (CSR, pixels x elements) of one cached pose."""
    with open_artefact(path, "transfer") as f:
        return read_csr(f["T"])


def load_T_tangent(path: Path) -> sp.csr_matrix | None:
    """The tangential-flux matrix (pixels x 2 elements, column 2j + a) of one cached pose, or
    None when its emission profile has no tangential term."""
    with open_artefact(path, "transfer") as f:
        return read_csr(f["T_tangent"]) if "T_tangent" in f else None


def load_column_error(path: Path) -> np.ndarray | None:
    """The estimated L1 error of each column of T (same unit as T), or None for a file
    written before the estimate existed (or by an estimator without one: all NaN)."""
    with open_artefact(path, "transfer") as f:
        return f["T/column_error"][()] if "T/column_error" in f else None


def load_view(path: Path, k: int) -> sp.csr_matrix:
    """View ``k``'s T (0: direct) of one cached pose, its weight not applied."""
    with open_artefact(path, "transfer") as f:
        return read_csr(f[f"views/{k}"])


def load_T_curvature(path: Path, ratios: list) -> sp.csr_matrix:
    """The emission's curvature term for one cached pose (pixels x columns, mm^2): the sum over
    its views of weight x view T x diag(ratio), ``ratios`` per view per column
    (:func:`fluxcli.transfer_cache.curvature_ratios`), so that ``this @ (S_f lap_t M|_f)`` is
    the light the term sends to each pixel (:func:`fluxcli.optics.emission.curvature_operator`)."""
    out = None
    with open_artefact(path, "transfer") as f:
        if len(ratios) != len(f["views"]):
            raise ValueError(f"{path} holds {len(f['views'])} view(s), {len(ratios)} given")
        for k, r in enumerate(ratios):
            w = float(f[f"views/{k}"].attrs["weight"])
            part = read_csr(f[f"views/{k}"]) @ sp.diags_array(w * np.asarray(r, float))
            out = part if out is None else out + part
    return sp.csr_matrix(out)


def read_summary(path: Path, view_names: list[str], areas: np.ndarray) -> dict:
    """Summary of a T file; reads every chunk, so a corrupt file raises UserError."""
    with open_artefact(path, "transfer") as f:
        eff, seen = {}, {}
        for k, name in enumerate(view_names):
            g = f[f"views/{k}"]
            Tv = read_csr(g)
            eff[name] = efficiency(Tv, float(g.attrs["weight"]), areas)
            seen[name] = seen_fraction(Tv, areas)
        T = read_csr(f["T"])
        return TSummary(int(T.nnz), eff, float(f.attrs["build_seconds"]), seen).as_dict()


_CHECKED: dict[tuple, dict] = {}  # (path, size, mtime) -> summary, so one run reads an entry once


def check_entry(path: Path, view_names: list[str], areas: np.ndarray) -> tuple[dict | None, str]:
    """``(summary, "")`` for a good cache entry, ``(None, why)`` for a missing or bad one."""
    try:
        st = Path(path).stat()
    except OSError:
        return None, "missing"
    memo = (str(path), st.st_size, st.st_mtime_ns, tuple(view_names))
    if memo in _CHECKED:
        return _CHECKED[memo], ""
    try:
        summary = read_summary(path, view_names, areas)
    except UserError as e:
        return None, str(e)
    except (OSError, KeyError, ValueError) as e:
        return None, f"{path} cannot be read ({e})"
    _CHECKED[memo] = summary
    return summary, ""


def write_index(path: Path, *, heights_mm, rotations_deg, keys: list[str], paths: list[Path], efficiency_pv,
                view_names: list[str], estimator: str, config_sha256: str = "",
                provenance: Provenance | None = None) -> None:
    import h5py
    import json

    with write_artefact(path, "transfer-index", config_sha256=config_sha256, inputs={k: k for k in keys},
                        provenance=provenance) as f:
        put(f, "heights_mm", np.asarray(heights_mm, float))
        put(f, "rotations_deg", np.asarray(rotations_deg, float))
        put(f, "keys", np.array(keys, dtype="S64"))
        # relative to the index's folder: the same bytes wherever the project lives
        put(f, "paths", np.array([portable_path(p, Path(path).parent) for p in paths], dtype=object),
            dtype=h5py.string_dtype())
        put(f, "efficiency", np.asarray(efficiency_pv, float))
        f.attrs["view_names"] = json.dumps(view_names)
        f.attrs["estimator"] = estimator
