"""From light sources inside a closed subject to power leaving each surface element."""

from __future__ import annotations

import time

import numpy as np

from ..surface.mesh import Surface
from .fem import DiffusionModel
from .mesh import check_closed, tetrahedralize
from .transfer_to_surface import exitance_to_elements


def element_power_from_sources(
    surface: Surface,
    *,
    mua_per_mm: float,
    musp_per_mm: float,
    refractive_index: float,
    positions_mm: np.ndarray,
    radii_mm: np.ndarray,
    powers_photons: np.ndarray,
    edge_length_mm: float,
    mesh: tuple[np.ndarray, np.ndarray] | None = None,
    solver: str = "auto",
) -> tuple[np.ndarray, dict]:
    """Solve the diffusion FEM in the closed ``surface`` and integrate the exitance over
    its elements.

    Parameters
    ----------
    surface : closed Surface (faces with element -1, such as unmeshed caps, still bound
        the volume; the light leaving through them is reported in ``info`` but belongs to
        no element).
    positions_mm, radii_mm, powers_photons : (n_sources, 3), (n_sources,), (n_sources,)
        Sources; radius 0 means a point source.
    edge_length_mm : target tetrahedron edge.
    mesh : (nodes_mm, tets) to reuse instead of meshing again (fTetWild is not
        deterministic, so a cached mesh is what makes a simulation reproducible).
    solver : "auto", "direct" or "amg" (:class:`fluxcli.diffusion.fem.DiffusionModel`).

    Returns
    -------
    power_per_element : (n_elements,) photons (per exposure, like the sources).
    info : dict with mesh size, timings, source power, total exitance, absorbed power.
    """
    check_closed(surface.vertices_mm, surface.faces)
    t0 = time.perf_counter()
    if mesh is None:
        mesh = tetrahedralize(surface.vertices_mm, surface.faces, edge_length_mm=edge_length_mm)
    nodes, tets = mesh
    t1 = time.perf_counter()
    model = DiffusionModel(nodes, tets, mua_per_mm=mua_per_mm, musp_per_mm=musp_per_mm,
                           refractive_index=refractive_index, solver=solver)
    positions_mm = np.atleast_2d(np.asarray(positions_mm, float))
    radii_mm = np.asarray(radii_mm, float)
    powers = np.asarray(powers_photons, float)
    rhs = np.zeros(len(nodes))
    point = radii_mm <= 0
    if point.any():
        rhs += model.point_source_rhs(positions_mm[point], powers[point]).sum(axis=1)
    if (~point).any():
        rhs += model.sphere_source_rhs(positions_mm[~point], radii_mm[~point], powers[~point]).sum(axis=1)
    phi = model.solve(rhs)
    t2 = time.perf_counter()
    J = model.exitance_at_boundary_nodes(phi)
    bv, bf = model.boundary_surface()
    # faces that belong to no element get one pseudo-element, so that rescaling to the
    # total exitance does not pour their light onto real elements
    eof = surface.element_of_face.copy()
    n_el = surface.n_elements
    extra = eof < 0
    if extra.any():
        eof[extra] = n_el
    power, _ = exitance_to_elements(bv, bf, J, surface.vertices_mm, surface.faces, eof, n_el + int(extra.any()))
    info = {
        "n_nodes": len(nodes), "n_tets": len(tets), "nodes_mm": nodes, "tets": tets,
        "mesh_seconds": t1 - t0, "solve_seconds": t2 - t1,
        "source_photons": float(powers.sum()),
        "total_exitance_photons": float(model.total_exitance_photons_s(phi)),
        "absorbed_photons": float(model.absorbed_power_photons_s(phi)),
        "exitance_outside_elements_photons": float(power[n_el:].sum()),
        "boundary_A": float(model.A),
        "solver": model.solver,
    }
    return np.asarray(power[:n_el], float), info
