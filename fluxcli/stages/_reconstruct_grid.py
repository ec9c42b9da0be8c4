"""reconstruct's unknowns on this run's T, the dense-solve memory check and the study sweep.

:func:`make_grid` reads T per pose on the chosen unknowns (built or from the cache through
the plan's ``build_T``); :func:`check_solver_size` refuses a solve that cannot fit before it
allocates; :func:`run_sweep` runs every (level, pose) cell of the sweep
(:func:`fluxcli.inverse.sweep.sweep_cell`), in worker processes when asked.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
import scipy.sparse as sp

from .. import artefacts as A
from ..artefacts.reconstruction import SweepRecord
from ..artefacts.transfer import load_T, load_T_curvature, load_T_tangent, load_view
from ..inverse.curvature import curvature_pass
from ..inverse.matfree import DENSE_MAX_UNKNOWNS, stage_bytes as matfree_bytes
from ..inverse.solve import DENSE, describe
from ..inverse.sweep import sweep_cell
from ..inverse.unknowns import Grid, VertexMap, n_vertices, resolve_unknowns
from ..resources import check_memory
from ..transfer_cache import curvature_ratios
from ..workers import pool_for
from ._reconstruct_inputs import photon_noise, simulation_path
from .context import RunContext

def direct_roi(T_path, image: np.ndarray) -> float:
    """The older quantification: photons summed over the region the direct view covers."""
    direct = load_view(T_path, 0)
    rows = np.diff(direct.indptr) > 0
    return float(np.nansum(image.ravel()[rows]))


def _curvature(ctx, todo, views, surface, T_columns, to_unknowns, columns: str):
    """The emission's curvature term's second pass (:mod:`fluxcli.inverse.curvature`), or None."""
    emission = todo[0][0].emission if todo else None
    if emission is None or not emission.has_curvature:
        return None
    T_curv = [load_T_curvature(pt.path, curvature_ratios(scene.surface, views, emission)) for scene, pt in todo]
    cp = curvature_pass(emission, surface, T_columns, T_curv, to_unknowns, columns)
    ctx.say(f"reconstruct: the emission's curvature term: each solve is made again with the profile bent by the "
            f"curvature of its own exitance (fitted over {cp.radius_mm:.3g} mm, |lap_t M / M| <= "
            f"{cp.kappa_max:.3g} /mm^2)")
    return cp


def make_grid(build_T, ctx: RunContext, surface, unknowns: str, system=None, curvature: bool = False) -> Grid:
    """T per pose on ``unknowns`` (``build_T``: the plan's; ``system``: another rig, for the error budget);
    with ``curvature`` also the emission's curvature pass, when its profile has the term (not on
    sub-elements)."""
    if unknowns in ("vertices", "linear_elements"):  # T per face of the once-refined surface, per hat function
        views, _, todo, _ = build_T(ctx, f"building T ({unknowns.replace('_', ' ')})", "refined:1", system)
        vb = surface.vertex_basis()
        _, fine_parent = surface.refined(1)
        fine_to_el = sp.csr_array((np.ones(fine_parent.size), (np.arange(fine_parent.size), fine_parent)),
                                  shape=(fine_parent.size, surface.n_elements))
        stiffness, areas, hats = vb.stiffness, vb.areas_mm2, None
        if unknowns == "linear_elements":  # one unknown per element, still linear within faces
            hats = vb.per_element(fine_to_el)
            stiffness, areas = None, None  # per solve: the unknowns depend on the elements the pixels see
        vmap = VertexMap(vb.to_fine, fine_to_el, vb.to_elements, surface.element_adjacency(), surface.element_areas_mm2,
                         hats)
        Tf = [load_T(pt.path).tocsr() for _, pt in todo]
        Tt = [load_T_tangent(pt.path) for _, pt in todo]
        if any(t is not None for t in Tt):  # the emission's tangential flux: acts through the hats' gradients
            from ..optics.emission import tangent_operator

            vmap = replace(vmap, tangent=tangent_operator(surface, 1))
        cp = None
        if curvature:
            cp = _curvature(ctx, todo, views, surface, Tf, lambda k, T: vmap.unknowns_T(T, Tt[k]), "refined:1")
        return Grid([vmap.unknowns_T(T, t) for T, t in zip(Tf, Tt)], stiffness, None, surface.n_elements, areas, surface,
                    [str(pt.path) for _, pt in todo], vmap, [vmap.element_map(T) for T in Tf], cp)
    label = "building T" if unknowns == "elements" else "building T (sub-elements)"
    views, _, todo, _ = build_T(ctx, label, unknowns, system)
    grid_surface, parent = surface.unknowns() if unknowns == "sub_elements" else (surface, None)
    Ts = [load_T(pt.path) for _, pt in todo]
    cp = None
    if curvature and unknowns == "elements":
        cp = _curvature(ctx, todo, views, surface, Ts, lambda k, T: T, "elements")
    elif curvature and todo and todo[0][0].emission is not None and todo[0][0].emission.has_curvature:
        ctx.say("reconstruct: subject.emission.curvature_term acts on reconstruct.unknowns vertices, linear_elements "
                "and elements; on sub_elements it is not applied")
    return Grid(Ts, grid_surface.element_adjacency(), parent, surface.n_elements,
                grid_surface.element_areas_mm2, surface, [str(pt.path) for _, pt in todo], curvature=cp)


def check_solver_size(settings, sweep, pixels, ctx: RunContext, surface, n_poses: int) -> None:
    """Dense normal matrices are n_unknowns^2: refuse before allocating, naming the keys
    (``settings``: the method; ``sweep``: reconstruct.sweep or None; ``pixels``: (nx, ny))."""
    methods = [resolve_unknowns(x, surface) for x in (settings, *(sweep.methods if sweep else ()))]
    n_sub = {"elements": surface.n_elements}
    if any(s.unknowns == "sub_elements" for s in methods):
        n_sub["sub_elements"] = surface.unknowns()[0].n_elements
    n_sub["vertices"] = n_vertices(surface)
    n_sub["linear_elements"] = surface.n_elements  # and the rim of what each pose sees (a few % more)
    nx, ny = pixels
    need = 8.0 * nx * ny * n_poses * 8  # images, masks, fits and residuals
    for s in methods:
        n = n_sub[s.unknowns]
        if s.method == "smooth" and n > DENSE_MAX_UNKNOWNS:  # the matrix-free path (fluxcli.inverse.matfree)
            need = max(need, matfree_bytes(n, n_poses, nx * ny) * (ctx.jobs if sweep else 1))
        elif s.method in DENSE:
            need = max(need, 8.0 * n ** 2 * 4 * (ctx.jobs if sweep else 1))
    if any(s.method == "smooth" and n_sub[s.unknowns] > DENSE_MAX_UNKNOWNS for s in methods):
        ctx.say(f"reconstruct: more than {DENSE_MAX_UNKNOWNS} unknowns: the matrix-free solve (sparse T'WT and "
                f"Laplacian); about {need / 1e9:.2g} GB of memory at its peak")
    check_memory(need, f"reconstructing {surface.n_elements} elements ({', '.join(sorted({s.method for s in methods}))})",
                 "the elements of subject.surface, use reconstruct.unknowns: elements, or choose "
                 "reconstruct.method: mlem or backprojection (no dense normal matrix)")


def run_sweep(plan, ctx: RunContext, grids: dict, todo) -> SweepRecord:
    """Every (level, pose) cell of ``plan.sweep`` x repeats x methods: the errors, and the table said."""
    sw = plan.sweep
    path = simulation_path(plan.images)
    with A.open_artefact(path, "simulation") as f:
        L, R, P = f["images/noisy"].shape[:3]
        snr = f["images/max_snr"][()]
        levels = f["truth/levels_peak_photons"][()]
        sensor = None
        noise = photon_noise(plan.noise, plan.read_noise_photons, plan.images.sensor,
                             str(f["images"].attrs.get("noise_model", "poisson")).replace("none", "poisson"),
                             float(f["images"].attrs.get("exposure_s", 1.0)))
        if "counts" in f["images"]:
            sensor = plan.images.sensor.model_dump() | {"exposure_s": float(f["images"].attrs["exposure_s"])}
    lv = list(sw.levels) if sw.levels is not None else list(range(L))
    reps = min(sw.repeats or R, R)
    methods = [resolve_unknowns(x, grids["elements"].surface) for x in sw.methods]
    cells = [(li, k) for li in lv for k in range(P)]
    err = np.full((len(methods), L, P, reps), np.nan)
    t0 = time.perf_counter()
    def per_pose(k):  # only what this pose's cell needs crosses to the worker; its T by path
        return {u: (gr.paths[k], gr.adjacency, gr.vmap if gr.vmap is not None else gr.parent, gr.n_elements, gr.areas)
                for u, gr in grids.items()}

    args = [(str(path), per_pose(k), k, li, reps, methods, noise, sensor)
            for li, k in cells]
    with ctx.progress("sweep", total=len(cells)) as advance:
        if ctx.jobs > 1 or ctx.client is not None:  # local processes, or the cells on a Dask cluster
            with pool_for(ctx.client)(ctx.jobs) as ex:
                for (li, k), e in zip(cells, ex.map(sweep_cell, *zip(*args))):
                    err[:, li, k] = e
                    advance()
        else:
            for (li, k), a in zip(cells, args):
                err[:, li, k] = sweep_cell(*a)
                advance()
    names = [describe(m) for m in methods]
    record = SweepRecord(err, snr, levels, names, A.recorded_seconds(time.perf_counter() - t0))
    rows = []
    for k, (_, pt) in enumerate(todo):
        for li in lv:
            rows.append([pt.pose.height_mm, f"{levels[li]:.0e}", f"{snr[li, k]:.1f}",
                         *[f"{100 * np.mean(err[i, li, k]):.2f} ± {100 * np.std(err[i, li, k], ddof=1 if reps > 1 else 0):.2f}"
                           for i in range(len(methods))]])
    ctx.table(["height_mm", "peak", "max SNR", *[f"{n} error %" for n in names]], rows)
    ctx.say(f"sweep: {len(cells)} cells x {reps} repeats x {len(methods)} methods in {time.perf_counter() - t0:.1f} s")
    return record
