"""The ``surface`` artefact (``surface.h5``, made by ``fluxmap capture-surface``'s structured
light): the subject's closed surface in world coordinates, what ``subject.surface: {artefact:
PATH}`` reads, with the points it was built from, the decoding per camera view and projector,
and (simulated rig) the truth it is measured against.

:class:`CapturedSurface` is the container; :func:`write` and :func:`read` the only code that
knows the layout.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..surface.mesh import Surface
from .kinds import SURFACE_DATASETS, Kind, attribute, datasets_of, quantity, register
from .pieces import read_surface, write_surface
from .store import Provenance, open_artefact, put, write_artefact

FILE_NAME = "surface.h5"  # in the workdir (capture-surface)
DECODE_UNITS = {"phase": "rad", "column_px": "projector px"}


@dataclass
class CapturedSurface:
    """A surface measured by structured light, and what it was measured from."""

    surface: Surface = quantity("surface", "mm", "the closed surface, at rest (stage at height 0)")
    points_mm: np.ndarray | None = quantity("points/positions_mm", "mm",
                                            "triangulated points the surface was built from (n, 3)", required=False,
                                            default=None)
    point_view: np.ndarray | None = quantity(
        "points/view", "", "view each point was seen in: 0 direct, j through mirror j-1 (attribute view_names: their "
        "names)", required=False, default=None)
    point_projector: np.ndarray | None = quantity("points/projector", "", "index of the projector that coded each point",
                                                  required=False, default=None)
    distance_to_truth_mm: np.ndarray | None = quantity(
        "points/distance_to_truth_mm", "mm", "simulated rig: each point's distance to the true surface", required=False,
        default=None)
    truth: Surface | None = quantity("truth/vertices", "mm",
                                     "simulated rig: the true surface the capture is measured against", required=False,
                                     default=None)
    metrics: dict = quantity(
        "metrics", "", "simulated rig: attributes points, within_0.1mm/0.2mm/0.4mm, median_distance_mm, "
        "covered_fraction_1mm, volume/area (mm^3, mm^2) and their errors against the truth", required=False,
        default_factory=dict)
    decode: dict = quantity(
        "decode", "", "decode/<view>/<projector>/{phase (wrapped, rad), column_px (decoded projector column, px), "
        "mask (1: decoded and triangulated)} per camera pixel [row, col] of the pattern frames", required=False,
        default_factory=dict)  # {(view, projector): {"phase", "column_px", "mask"}}
    view_names: list = attribute("points@view_names", "", "the name of each value of points/view, in order",
                                 default_factory=list)
    attrs: dict = field(default_factory=dict)  # root attributes (inputs_digest, capture_height_mm)


KIND = register(Kind("surface", 1, "fluxmap capture-surface (structured light)",
                     "the subject's closed surface measured by structured light, in world coordinates",
                     (*SURFACE_DATASETS, *(d for d in datasets_of(CapturedSurface) if d.name != "surface"))))


def write(path: Path, cs: CapturedSurface, *, config_sha256: str = "", inputs: dict[str, str] | None = None,
          provenance: Provenance | None = None) -> Path:
    """Write ``cs`` atomically as ``path``; points are written when ``cs.points_mm`` is set."""
    with write_artefact(Path(path), "surface", config_sha256=config_sha256, inputs=inputs,
                        provenance=provenance) as f:
        for key, value in cs.attrs.items():
            f.attrs[key] = value
        write_surface(f.create_group("surface"), cs.surface)
        if cs.points_mm is not None:
            g = f.create_group("points")
            put(g, "positions_mm", cs.points_mm)
            put(g, "view", np.asarray(cs.point_view).astype(np.int16))
            put(g, "projector", np.asarray(cs.point_projector).astype(np.int16))
            if cs.distance_to_truth_mm is not None:
                put(g, "distance_to_truth_mm", np.asarray(cs.distance_to_truth_mm, float))
            names = cs.view_names or list(dict.fromkeys(view for view, _ in cs.decode))
            if names:
                g.attrs["view_names"] = names
        if cs.truth is not None:
            write_surface(f.create_group("truth"), cs.truth)
        if cs.metrics:
            g = f.create_group("metrics")
            for key, value in cs.metrics.items():
                g.attrs[key] = value
        for (view, proj), arrays in cs.decode.items():
            g = f.require_group(f"decode/{view}/{proj}")
            for name, data in arrays.items():
                put(g, name, np.asarray(data), compression="gzip").attrs["unit"] = DECODE_UNITS.get(name, "")
    return Path(path)


def read(path: Path, *, decode: bool = True) -> CapturedSurface:
    """The captured surface in ``path`` (a UserError naming the file when it is not one); with
    ``decode=False`` the per-pixel decoding is left out (what ``subject.surface`` needs)."""
    with open_artefact(path, "surface") as f:
        cs = CapturedSurface(read_surface(f["surface"]), attrs=dict(f.attrs))
        if "points" in f:
            g = f["points"]
            cs.points_mm = g["positions_mm"][()]
            cs.point_view = g["view"][()] if "view" in g else None
            cs.point_projector = g["projector"][()] if "projector" in g else None
            cs.distance_to_truth_mm = g["distance_to_truth_mm"][()] if "distance_to_truth_mm" in g else None
            cs.view_names = [str(v) for v in g.attrs.get("view_names", [])]
        cs.truth = read_surface(f["truth"]) if "truth" in f else None
        if "metrics" in f:
            cs.metrics = {k: (v.item() if hasattr(v, "item") else v) for k, v in f["metrics"].attrs.items()}
        if decode and "decode" in f:
            for v in f["decode"]:
                for p in f["decode"][v]:
                    g = f["decode"][v][p]
                    cs.decode[(v, p)] = {name: g[name][()] for name in g}
    return cs


def write_surface_artefact(path: Path, surface: Surface, *, points=None, decode: dict | None = None,
                           distance_to_truth_mm: np.ndarray | None = None, config_sha256: str = "",
                           inputs: dict[str, str] | None = None, provenance: Provenance | None = None,
                           attrs: dict | None = None, truth: Surface | None = None,
                           metrics: dict | None = None) -> Path:
    """:func:`write` of a :class:`CapturedSurface` made from its parts: ``points`` the merged points
    (:class:`fluxcli.structured.scan.MergedPoints`), ``decode`` :func:`fluxcli.structured.scan.decode_by_view`,
    ``metrics`` :func:`fluxcli.structured.mesh.capture_metrics`, ``attrs`` root attributes."""
    cs = CapturedSurface(surface, truth=truth, metrics=dict(metrics or {}), decode=dict(decode or {}),
                         attrs=dict(attrs or {}))
    if points is not None:
        cs.points_mm, cs.point_view, cs.point_projector = points.points_mm, points.view, points.projector
        cs.distance_to_truth_mm = distance_to_truth_mm
    return write(path, cs, config_sha256=config_sha256, inputs=inputs, provenance=provenance)
