"""The ``tetmesh`` artefact: the tetrahedral mesh of a closed subject surface that the diffusion
truth is solved on, kept by content (:func:`fluxcli.truth.tetmesh_key`) because the mesher is
not deterministic.  :class:`TetMesh` is the container; :func:`write` and :func:`read` the layout.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import UserError
from .kinds import Kind, datasets_of, quantity, register
from .store import open_artefact, put, write_artefact


@dataclass
class TetMesh:
    """Nodes and tetrahedra of a closed surface's interior."""

    nodes_mm: np.ndarray = quantity("nodes", "mm", "node positions (N, 3)")
    tets: np.ndarray = quantity("tets", "", "tetrahedra (M, 4)")


KIND = register(Kind("tetmesh", 1, "fluxmap simulate", "tetrahedral mesh of the subject (cached by content)",
                     datasets_of(TetMesh)))


def write(path: Path, mesh: TetMesh) -> Path:
    """Write ``mesh`` atomically as ``path``."""
    with write_artefact(path, "tetmesh") as f:
        put(f, "nodes", mesh.nodes_mm)
        put(f, "tets", mesh.tets)
    return Path(path)


def read(path: Path) -> TetMesh:
    """The mesh in ``path``; a UserError naming the file when it is not a readable one, or when
    its arrays cannot be a mesh (:func:`damage`)."""
    with open_artefact(path, "tetmesh") as f:
        mesh = TetMesh(f["nodes"][()], f["tets"][()])
    what = damage(mesh.nodes_mm, mesh.tets)
    if what:
        raise UserError(f"artefact {path} is damaged: {what}. It is a tetrahedral mesh made by 'fluxmap "
                        "simulate' (simulate.flux.kind: diffusion); delete it to have it made again.")
    return mesh


def damage(nodes_mm: np.ndarray, tets: np.ndarray) -> str | None:
    """What makes ``nodes_mm``/``tets`` no tetrahedral mesh a FEM can solve on, or None: shapes,
    types, finite coordinates, node numbers in range, every node in a tetrahedron (an unused
    node leaves the stiffness matrix singular), no tetrahedron twice."""
    from ..config import MAX_LENGTH_MM

    nodes_mm, tets = np.asarray(nodes_mm), np.asarray(tets)
    if nodes_mm.dtype.kind not in "fiu" or nodes_mm.ndim != 2 or nodes_mm.shape[1] != 3 or len(nodes_mm) < 4:
        return f"its nodes are {nodes_mm.shape} of {nodes_mm.dtype}, not (n >= 4, 3) coordinates in mm"
    if tets.dtype.kind not in "iu" or tets.ndim != 2 or tets.shape[1] != 4 or len(tets) == 0:
        return f"its tets are {tets.shape} of {tets.dtype}, not (m > 0, 4) node numbers"
    if not np.all(np.isfinite(nodes_mm)) or np.abs(nodes_mm).max() > MAX_LENGTH_MM:
        return f"a node is not finite or lies beyond {MAX_LENGTH_MM:g} mm"
    if tets.min() < 0 or tets.max() >= len(nodes_mm):
        return f"a tetrahedron names node {int(tets.min() if tets.min() < 0 else tets.max())} of {len(nodes_mm)}"
    used = np.bincount(tets.ravel().astype(np.int64), minlength=len(nodes_mm)) > 0
    if not used.all():
        return f"{int((~used).sum())} of its {len(nodes_mm)} nodes are in no tetrahedron"
    key = np.sort(tets.astype(np.int64), axis=1)
    if len(np.unique(key, axis=0)) < len(tets):
        return "a tetrahedron appears more than once"
    return None
