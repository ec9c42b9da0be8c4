"""One cell of reconstruct's study sweep: every method on every noise repeat of one (level, pose).

Runs in a worker process: T is read by path (no T inside a task graph), the images from
simulation.h5; returns the paper's L1 error (Eq. 15) per method and repeat.
"""

from __future__ import annotations

import numpy as np

from .. import artefacts as A
from ..artefacts.transfer import load_T, load_T_tangent
from ..imaging import noise as N
from .metrics import error_l1
from .solve import run_method
from .unknowns import VertexMap


def sweep_cell(sim_path: str, grids_k: dict, pose: int, level: int, repeats: int,
               methods: list, noise: N.PhotonNoise, sensor: dict | None) -> np.ndarray:
    """Errors (methods x repeats) of one (level, pose) cell; runs in a worker process.
    ``grids_k``: per unknowns (T's cache file, adjacency, parent or VertexMap, n_elements, areas)."""
    Ts, parts = {}, {}
    for u in {m.unknowns for m in methods}:  # T by path: no T inside a task graph
        T, part = load_T(grids_k[u][0]), grids_k[u][2]
        if isinstance(part, VertexMap):  # the fine T: per vertex, and per element for the classes
            T, part = part.unknowns_T(T, load_T_tangent(grids_k[u][0])), part.element_map(T)
        Ts[u], parts[u] = T, part
    out = np.zeros((len(methods), repeats))
    with A.open_artefact(sim_path, "simulation") as f:
        truth = f["truth/power"][()] * f["truth/level_scale"][level]
        imgs = f["images/noisy"][level, :repeats, pose].astype(float)
        counts = f["images/counts"][level, :repeats, pose] if "counts" in f["images"] else None
    model = N.EMCCDModel(**sensor) if (sensor is not None and counts is not None) else None
    for r in range(repeats):
        valid = np.isfinite(imgs[r]) & (~N.saturated(counts[r], model) if model is not None else True)
        for i, m in enumerate(methods):
            _, adjacency, _, n_el, areas = grids_k[m.unknowns]
            res, _ = run_method(Ts[m.unknowns], imgs[r], valid, m, noise, adjacency, parts[m.unknowns], n_el, areas)
            out[i, r] = error_l1(res.power, truth)
    return out
