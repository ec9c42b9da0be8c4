"""The ``tetmesh`` artefact: the tetrahedral mesh of a closed subject surface that the diffusion
truth is solved on, kept by content (:func:`fluxcli.truth.tetmesh_key`) because the mesher is
not deterministic.  :class:`TetMesh` is the container; :func:`write` and :func:`read` the layout.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

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
    """The mesh in ``path``; a UserError naming the file when it is not a readable one."""
    with open_artefact(path, "tetmesh") as f:
        return TetMesh(f["nodes"][()], f["tets"][()])
