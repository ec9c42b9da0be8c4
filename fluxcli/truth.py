"""The ground truth a simulation (or the simulated rig's camera) images: power per element of
the subject at rest, integrated on a surface finer than the reconstruction's elements, and the
sampling of the forward T that images it (finer than reconstruction's in every key).

Shared by ``fluxmap simulate`` and ``fluxmap capture-surface`` (the simulated camera), so that no
stage imports another.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import artefacts as A
from . import config as C
from .artefacts import tetmesh as AM
from .diffusion.surface_flux import element_power_from_sources
from .errors import InputError, UserError
from .optics.raycast import OcclusionScene
from .resources import check_memory
from .surface.mesh import Surface


@dataclass(frozen=True)
class TruthPlan:
    """What the ground truth is made from: ``simulate.flux``, how often the truth surface is
    refined, where tetrahedral meshes are cached and shipped, and a per-element file's path
    (relative paths resolved; :func:`fluxcli.stages.plans.truth_plan`)."""

    flux: object  # one of the simulate.flux models (fluxcli.config)
    refinement: int  # each triangle split into 4 this often (truth_refinement)
    mesh_cache: Path  # <workdir>/cache/mesh
    mesh_dir: Path | None = None  # simulate.flux.mesh_dir: meshes kept with the config
    flux_file: Path | None = None  # simulate.flux.path (kind file)


def forward_transfer(sim: C.Simulate, transfer: C.Transfer) -> C.Transfer:
    """The forward T's sampling: ``sim.transfer`` as configured, or finer than reconstruction's
    ``transfer`` in every sampling key (and built on the refined surface the truth lives on)."""
    if sim.transfer is not None:
        return sim.transfer
    tr = transfer
    return tr.model_copy(update={
        "lens": tr.lens.model_copy(update={
            "surface_samples_per_pixel": 2 * tr.lens.surface_samples_per_pixel,
            "max_surface_subdivisions": 2 * tr.lens.max_surface_subdivisions,
            "min_surface_subdivisions": 2 * tr.lens.min_surface_subdivisions,
            "lens_samples_min": 4 * tr.lens.lens_samples_min,
            "lens_samples_max": 2 * tr.lens.lens_samples_max,
            "lens_samples_per_blur_pixel": 2 * tr.lens.lens_samples_per_blur_pixel}),
        "pairwise": tr.pairwise.model_copy(update={
            "surface_subdivisions": 2 * tr.pairwise.surface_subdivisions,
            "pixel_subdivisions": 2 * tr.pairwise.pixel_subdivisions}),
    })


# ------------------------------------------------------------------ ground truth
def truth_power(truth: TruthPlan, surface: Surface) -> tuple[np.ndarray, dict]:
    """Power per element (photons per exposure) of the subject at rest, and notes: the
    fine truth (:func:`truth_fine`) summed per element."""
    fine, parent, notes = truth_fine(truth, surface)
    return np.bincount(parent, weights=fine, minlength=surface.n_elements), notes


def truth_refinement(sim: C.Simulate) -> int:
    """How often the truth surface splits each triangle into 4: as configured, else 1 (0 when
    an inverse crime is explicitly allowed: the same T then reproduces the images exactly)."""
    if sim.truth_refinement is not None:
        return sim.truth_refinement
    return 0 if sim.allow_inverse_crime else 1


def truth_fine(truth: TruthPlan, surface: Surface) -> tuple[np.ndarray, np.ndarray, dict]:
    """The truth on a surface finer than the reconstruction's elements (no inverse crime):
    power per face of ``surface.refined(simulate.truth_refinement)``, with the element each
    fine face belongs to. Gaussian, uniform and diffusion truths vary within an element;
    a per-element file can only be spread by area (constant exitance within the element)."""
    levels = truth.refinement
    fine, parent = surface.refined(levels)
    flux = truth.flux
    if isinstance(flux, C.GaussianFlux):
        # exitance J(x) = exp(-|x - c|²/2w²) integrated over the fine faces, scaled so the
        # brightest element emits peak_photons
        cen = surface.element_centroids_mm
        centre = np.asarray(flux.center_mm) if flux.center_mm is not None else cen[np.argmax(cen[:, 2])]
        d2 = ((fine.element_centroids_mm - centre) ** 2).sum(axis=1)
        p = np.exp(-d2 / (2 * flux.width_mm**2)) * fine.element_areas_mm2
        per_element = np.bincount(parent, weights=p, minlength=surface.n_elements)
        if not per_element.max() > 0:  # every face beyond ~38 widths of the centre: exp underflows to 0
            near = float(np.sqrt(d2.min()))
            raise UserError(f"simulate.flux: the gaussian of width_mm {flux.width_mm:g} centred at "
                            f"{np.round(centre, 3).tolist()} mm puts no light on the surface (its nearest face is "
                            f"{near:.3g} mm away, {near / flux.width_mm:.3g} widths); move center_mm onto the "
                            "subject's surface or widen width_mm.")
        return p * flux.peak_photons / per_element.max(), parent, {"center_mm": centre.tolist(),
                                                                   "truth_refinement": levels}
    if isinstance(flux, C.DiffusionFlux):
        p, notes = _diffusion_truth(flux, surface, truth.mesh_cache, fine=fine, shipped=truth.mesh_dir)
        return p, parent, notes | {"truth_refinement": levels}
    per_element, notes = _truth_per_element(flux, surface, truth.flux_file)
    share = fine.element_areas_mm2 / surface.element_areas_mm2[parent]
    return per_element[parent] * share, parent, notes | {"truth_refinement": levels}


def _truth_per_element(flux, surface: Surface, path: Path | None) -> tuple[np.ndarray, dict]:
    areas = surface.element_areas_mm2
    if isinstance(flux, C.UniformFlux):
        return flux.exitance_photons_per_mm2 * areas, {}
    if isinstance(flux, C.FileFlux):
        if not path.is_file():
            raise UserError(f"simulate.flux.path: file {path} does not exist.")
        values = per_element_values(path, "simulate.flux.path")
        if len(values) != surface.n_elements:
            raise UserError(f"simulate.flux.path: {path} holds {len(values)} values; the surface has "
                            f"{surface.n_elements} elements.")
        if np.any(values < 0) or not np.all(np.isfinite(values)):
            raise UserError(f"simulate.flux.path: {path} holds negative or non-finite values.")
        return (values if flux.quantity == "power" else values * areas), {}
    raise AssertionError(f"unhandled flux kind {flux.kind}")


def per_element_values(path: Path, key: str) -> np.ndarray:
    """One number per element from a file: ``.npy`` (any shape, read flat) or text with one value
    per line (a header line, ``#`` comments, blank lines and a spreadsheet's byte-order mark are
    skipped).  A UserError naming ``key`` and the file for anything else."""
    where = f"{key}: {path}"
    if path.suffix.lower() == ".npy":
        try:
            raw = np.load(path, allow_pickle=False)
        except Exception as e:  # numpy raises several kinds for malformed files
            raise UserError(f"{where} is not a readable .npy array ({e}).") from None
        if not (np.issubdtype(raw.dtype, np.number) or raw.dtype == bool):
            raise UserError(f"{where} holds {raw.dtype} values, not numbers.")
        return np.asarray(raw, float).ravel()
    try:
        text = path.read_bytes().decode("utf-8-sig")
    except (OSError, UnicodeDecodeError) as e:
        raise UserError(f"{where} is not a text file of numbers, one per line ({e}).") from None
    lines = [(k, ln.strip()) for k, ln in enumerate(text.splitlines(), start=1)
             if ln.strip() and not ln.lstrip().startswith("#")]
    values = []
    for i, (k, ln) in enumerate(lines):
        cells = [c for c in ln.replace(";", ",").replace("\t", ",").split(",")] if any(
            c in ln for c in ",;\t") else ln.split()
        if len(cells) != 1:
            raise UserError(f"{where}: line {k} holds {len(cells)} values ({ln[:40]!r}); give one value per line, "
                            "in element order.")
        try:
            values.append(float(cells[0]))
        except ValueError:
            if i == 0:  # a header line
                continue
            raise UserError(f"{where}: line {k} holds {cells[0][:40]!r}, which is not a number.") from None
    return np.asarray(values, float)


def source_positions(flux: C.DiffusionFlux, surface: Surface) -> np.ndarray:
    """Sources given by depth sit that far below the surface point hit from the subject's
    centre along ``direction``."""
    scene = OcclusionScene(surface.vertices_mm, surface.faces)
    lo, hi = surface.bounds_mm()
    centre = (lo + hi) / 2
    out = []
    for k, s in enumerate(flux.sources):
        if s.position_mm is not None:
            out.append(np.asarray(s.position_mm, float))
            continue
        d = np.asarray(s.direction, float)
        d /= np.linalg.norm(d)
        t = scene.first_hit_mm(centre[None], d[None])[0]
        back = scene.first_hit_mm(centre[None], -d[None])[0]
        if not (np.isfinite(t) and np.isfinite(back)):
            raise UserError(f"simulate.flux.sources.{k}: no surface along direction {list(s.direction)} "
                            "from the subject's centre.")
        if s.depth_mm >= t + back:
            raise UserError(f"simulate.flux.sources.{k}.depth_mm: {s.depth_mm} mm is deeper than the subject "
                            f"({t + back:.2f} mm through, along that direction).")
        out.append(centre + (t - s.depth_mm) * d)
    return np.array(out)


# A stored mesh must fill the surface it is filed under: fTetWild keeps its boundary within
# 1e-3 of the bounding box's diagonal (its envelope), and the shipped meshes hold 99.9 % of the
# surface's volume with the same bounding box to 1e-16 mm; a mesh of another body, or this one
# scaled or moved, is far outside these bars.
MESH_VOLUME_TOL = 0.03
MESH_BOX_TOL = 0.01  # of the surface's bounding-box diagonal


def _check_tetmesh_fits(mesh: "AM.TetMesh", surface: Surface, path: Path) -> None:
    """A UserError naming ``path`` when ``mesh`` does not fill ``surface`` (volume, bounding box)
    or has tetrahedra of no volume: it was not made for this subject."""
    p = np.asarray(mesh.nodes_mm, float)[np.asarray(mesh.tets, np.int64)]
    vol = np.einsum("ij,ij->i", p[:, 1] - p[:, 0], np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0])) / 6
    t = surface.face_vertices_mm
    body = abs(float(np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() / 6))
    lo, hi = surface.vertices_mm.min(axis=0), surface.vertices_mm.max(axis=0)
    diag = float(np.linalg.norm(hi - lo))
    off = max(float(np.abs(mesh.nodes_mm.min(axis=0) - lo).max()), float(np.abs(mesh.nodes_mm.max(axis=0) - hi).max()))
    if not np.all(vol > 0):
        why = (f"{int(np.sum(vol <= 0))} of its {len(vol)} tetrahedra have no volume or are inverted "
               "(fluxmap's mesher orients every one)")
    elif not abs(vol.sum() / body - 1) <= MESH_VOLUME_TOL:
        why = f"its tetrahedra fill {vol.sum():.6g} mm^3, the subject's surface encloses {body:.6g} mm^3"
    elif not off <= MESH_BOX_TOL * diag:
        why = (f"its nodes span {np.round(mesh.nodes_mm.min(axis=0), 3).tolist()} to "
               f"{np.round(mesh.nodes_mm.max(axis=0), 3).tolist()} mm, the subject's surface "
               f"{np.round(lo, 3).tolist()} to {np.round(hi, 3).tolist()} mm")
    else:
        return
    raise UserError(f"the tetrahedral mesh {path} does not fit the subject it is filed under: {why}")


def tetmesh_key(surface: Surface, mesh_edge_mm: float) -> str:
    """Content address of the tetrahedral mesh of ``surface`` (cache and shipped meshes)."""
    return A.cache_key({"surface": surface.digest(), "edge_length_mm": A.canonical(mesh_edge_mm), "mesher": "ftetwild-1"})


# Judged against a closed form (tests/test_diffusion.py::test_undershoot_rule_against_the_sphere_closed_form:
# eccentric source in a sphere, fTetWild meshes of 1.2-4 mm): faces below zero appeared only at
# mu_eff h >= 1.6, and every such truth put 17-69 % of its light on the wrong faces, so an undershoot
# is never rounding there. Its share below zero was 2.5e-5 - 6e-2, often under UNDERSHOOT_TOTAL; the
# peak bar (those faces reached -1.3 % of the peak or lower) is what refused the small ones. On other
# subjects an unlucky mesh gives lobes of ~1e-8 (the demo rig) to a few 1e-4 (test_simulate's phantom)
# of the light at mu_eff h ~ 0.8, where the sphere's truth never undershot: the share bar is not tightened.
UNDERSHOOT_TOTAL = 1e-3  # negative parts of the FEM truth that are clipped without a word: ≤ this share of the light
UNDERSHOOT_PEAK = 1e-2  # ... and no face below −this × the brightest


def check_undershoot(power: np.ndarray, flux: C.DiffusionFlux) -> tuple[np.ndarray, float]:
    """The diffusion truth with its negligible negative lobes clipped, and how many photons
    were clipped; a :class:`UserError` naming ``simulate.flux.mesh_edge_mm`` when they are not
    negligible.

    Linear finite elements undershoot below zero where the fluence dies faster than the
    mesh can follow (decay length ``1/μ_eff``, ``μ_eff = √(3μa(μa + μs'))``). A lobe of a
    few photons on a peak of 10⁸ is rounding-level and is clipped; more than
    :data:`UNDERSHOOT_TOTAL` of the light, or a face below −:data:`UNDERSHOOT_PEAK` × the
    peak, means the truth itself is wrong (a negative total, images that cannot be
    sampled) and the mesh must be finer.
    """
    power = np.asarray(power, dtype=np.float64)
    neg = float(-power[power < 0].sum())
    pos = float(power[power > 0].sum())
    peak = float(power.max()) if power.size else 0.0
    if neg == 0.0:
        return power, 0.0
    if neg <= UNDERSHOOT_TOTAL * pos and power.min() >= -UNDERSHOOT_PEAK * peak:
        return np.maximum(power, 0.0), neg
    opt = flux.optical[flux.wavelength_nm]
    mu_eff = float(np.sqrt(3 * opt.mua_per_mm * (opt.mua_per_mm + opt.musp_per_mm)))
    decay = f"{1 / mu_eff:.3g} mm" if mu_eff > 0 else "many mm"
    hint = f"; try simulate.flux.mesh_edge_mm: {0.5 / mu_eff:.2g} or finer" if mu_eff > 0 else ""
    raise UserError(
        f"simulate.flux.mesh_edge_mm: the diffusion mesh ({flux.mesh_edge_mm:g} mm) is too coarse for the optical "
        f"properties at {flux.wavelength_nm:g} nm (mua {opt.mua_per_mm:g}/mm, musp {opt.musp_per_mm:g}/mm: the light "
        f"decays over 1/mu_eff = {decay}). The finite-element truth undershoots below zero: {neg:.3g} photons "
        f"negative against {pos:.3g} positive ({neg / max(pos, 1e-300):.2%}), down to {power.min():.3g} on one face "
        f"(peak {peak:.3g}); a truth like that is not light{hint}.")


def _diffusion_truth(flux: C.DiffusionFlux, surface: Surface, mesh_cache: Path, fine: Surface | None = None,
                     shipped: Path | None = None) -> tuple[np.ndarray, dict]:
    """Power per face of ``fine`` (default: per element of ``surface``) from the diffusion
    FEM in the closed ``surface``. The tetrahedral mesh is read from ``shipped`` (a folder
    of meshes kept with the config, what makes a fresh clone byte-reproducible), else
    from the cache, else made and cached."""
    if not surface.is_closed:
        raise UserError(f"simulate.flux: the diffusion model needs a closed subject surface; this one has "
                        f"{surface.boundary_edge_count()} open edge(s) (a ring or patch phantom, or an open mesh).")
    opt = flux.optical[flux.wavelength_nm]
    t = surface.face_vertices_mm
    volume = abs(float(np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() / 6))
    n_tets = 1.5 * volume / (flux.mesh_edge_mm ** 3 / (6 * np.sqrt(2)))  # regular tetrahedra, and some more
    check_memory(1500.0 * n_tets, f"the diffusion model (about {n_tets:.3g} tetrahedra of {flux.mesh_edge_mm:g} mm "
                 f"in {volume:.4g} mm^3)", "the mesh density: raise simulate.flux.mesh_edge_mm")
    pos = source_positions(flux, surface)
    # fTetWild is not deterministic: the tetrahedral mesh is cached by content so that the
    # same config gives the same bytes
    key = tetmesh_key(surface, flux.mesh_edge_mm)
    path = mesh_cache / f"{key}.h5"
    mesh = None
    if shipped is not None and (shipped / f"{key}.h5").is_file():
        # a mesh kept with the config is the user's: a damaged one is named, never replaced
        try:
            stored = AM.read(shipped / f"{key}.h5")
            _check_tetmesh_fits(stored, surface, shipped / f"{key}.h5")
        except UserError as e:
            raise UserError(f"simulate.flux.mesh_dir: {e} (Restore it from where it came from, or delete it: "
                            "fluxmap then makes a new mesh in its cache, and the truth is no longer byte-reproducible.)"
                            ) from None
        mesh = (stored.nodes_mm, stored.tets)
    elif path.is_file():
        try:
            stored = AM.read(path)
            _check_tetmesh_fits(stored, surface, path)
            mesh = (stored.nodes_mm, stored.tets)
        except UserError as e:
            warnings.warn(f"the cached tetrahedral mesh is unusable and is remade: {e}")
            mesh = None
    if mesh is None:
        from .diffusion.mesh import tetrahedralize

        try:
            mesh = tetrahedralize(surface.vertices_mm, surface.faces, edge_length_mm=flux.mesh_edge_mm)
        except ValueError as e:
            raise UserError(f"simulate.flux: {e}") from None
        AM.write(path, AM.TetMesh(mesh[0], mesh[1]))
        made = True
    else:
        made = False
    try:
        power, info = element_power_from_sources(
            fine if fine is not None else surface, mua_per_mm=opt.mua_per_mm, musp_per_mm=opt.musp_per_mm, refractive_index=opt.refractive_index,
            positions_mm=pos, radii_mm=np.array([s.radius_mm for s in flux.sources]),
            powers_photons=np.array([s.power_photons for s in flux.sources]), edge_length_mm=flux.mesh_edge_mm,
            mesh=mesh, solver=flux.solver)
    except InputError as e:
        raise UserError(f"simulate.flux: {e}") from None
    info.pop("nodes_mm"), info.pop("tets")
    power, info["clipped_photons"] = check_undershoot(power, flux)
    info["source_positions_mm"] = pos.tolist()
    info["mesh_cached"] = not made
    info["mesh_key"] = key
    return power, info


# ------------------------------------------------------------------ Monte Carlo truth
SUBJECT_MESH = "the subject's own closed surface"  # montecarlo_shape's answer for any other subject


def montecarlo_shape(surface_cfg) -> "Shape | str":
    """The analytic body of a box or cylinder phantom (its own frame), or :data:`SUBJECT_MESH`
    for any other subject: the photons then travel inside its own triangle mesh (a mesh file,
    a captured surface, a sphere phantom), which :func:`montecarlo_truth` checks is closed."""
    from .montecarlo.transport import Shape

    if isinstance(surface_cfg, C.BoxPhantom):
        return Shape.box(surface_cfg.size_mm)
    if isinstance(surface_cfg, C.CylinderPhantom):
        return Shape.cylinder(surface_cfg.radius_mm, surface_cfg.length_mm)
    return SUBJECT_MESH


def _is_mesh_body(shape) -> bool:
    from .montecarlo.meshbody import MESH

    return shape.kind == MESH


def _surface_key(surface_cfg) -> str:
    return ("subject.surface.mesh" if isinstance(surface_cfg, C.MeshSurface) else "subject.surface.artefact"
            if not hasattr(surface_cfg, "phantom") else f"subject.surface (a {surface_cfg.phantom} phantom)")


def _exits_leave(body, esc, surface_cfg, sample: int = 2000) -> None:
    """A :class:`UserError` when photons that leave a mesh body land inside it: the surface crosses
    itself, or holds overlapping bodies (two spheres merged into one file). A photon that leaves
    a concave but sound body is outside just past its exit; one that leaves through a face lying
    inside the body is not. Checked on the first batch's first ``sample`` photons."""
    k = min(sample, len(esc.weight))
    if k == 0:
        return
    step = 1e-4 * max(float(max(body.half_mm)), 1e-3)
    inside = body.contains(esc.position_mm[:k] + step * esc.direction[:k])
    if inside.mean() > 0.01:
        raise UserError(f"simulate.flux: kind montecarlo: {inside.mean():.0%} of the photons leaving "
                        f"{_surface_key(surface_cfg)} leave into the body again: the surface crosses itself or holds "
                        "overlapping bodies, so inside and outside are not defined. Give one closed surface that "
                        "does not intersect itself (merge overlapping parts into their union).")


def _mesh_body(fine, surface_cfg, src: np.ndarray, radius_mm: float):
    """The body a subject's own (refined, flat-split) surface encloses, checked closed and holding
    the source; a :class:`UserError` naming the key otherwise."""
    from .montecarlo.meshbody import MeshBody

    what = _surface_key(surface_cfg)
    try:
        body = MeshBody.of(fine.vertices_mm, fine.faces, name=what)
    except ValueError as e:
        raise UserError(f"simulate.flux: kind montecarlo: {e}.") from None
    if body.depth_mm(src[None])[0] <= radius_mm:
        lo, hi = fine.bounds_mm()
        raise UserError(f"simulate.flux.position_mm: the source {src.tolist()} mm (radius {radius_mm:g} mm) is not "
                        f"inside {what} (its own coordinates, as the file gives them: it spans "
                        f"{np.round(lo, 3).tolist()} to {np.round(hi, 3).tolist()} mm).")
    return body


@dataclass
class MonteCarloTruth:
    """One photon run serving every pose: the truth per fine face (photons that left through
    it), the photon images per pose and what the photons say about the light."""

    fine_power: np.ndarray  # (n_fine,) photons
    parent: np.ndarray  # (n_fine,) element of each fine face
    images: np.ndarray  # (P, ny, nx) whole photons
    reached_lens: np.ndarray  # (P, V) photons that crossed each view's lens unobstructed
    on_sensor: np.ndarray  # (P, V) ... and landed on a pixel
    angle_histogram: np.ndarray  # photons per exit-angle bin (montecarlo.photons.ANGLE_EDGES_DEG)
    tally: object
    not_on_elements: float  # photons that left through faces of no element (cylinder caps)
    photons: dict | None  # every escaping photon (own frame) when simulate.flux.keep_photons
    seconds: float
    notes: dict


BATCH_S = 30.0  # a batch of photons should take about this long at most: progress moves, and Ctrl-C is heard
SAY_ETA_S = 600.0  # a transport expected to take longer than this is announced with its estimate


def _pace(flux: C.MonteCarloFlux, medium, shape, say) -> int:
    """The photons a batch: ``simulate.flux.batch_photons``, fewer when a batch would take more
    than :data:`BATCH_S` (a numba kernel hears no signal until it returns).  A medium in which a
    photon is expected to make more than a fifth of :data:`MAX_EVENTS` interactions is refused:
    photons would be cut off (lost) and the run would take days (μs 1000 /mm with μa 0 in a
    20-mm box: ~1e8 a photon, 2000 photons kept the CLI busy past its own timeout)."""
    import os

    from .montecarlo import transport as MC

    per = MC.expected_events(medium, shape.half_mm)
    if per > MC.MAX_EVENTS / 5:
        raise UserError(f"simulate.flux: with mu_a {medium.mua_per_mm:g} /mm and mu_s {medium.mus_per_mm:g} /mm (g "
                        f"{medium.g:g}) a photon scatters about {per:.2g} times before it is absorbed or leaves a body "
                        f"{2 * min(shape.half_mm):.3g} mm across, beyond the {MC.MAX_EVENTS:.0e} the transport follows: "
                        "the light would be cut off and the run would take days. Check mus_per_mm and mua_per_mm "
                        "(tissue: mu_s' about 1 /mm, mu_a 0.01-1 /mm).")
    threads = max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1))
    eta = flux.n_photons * per / (MC.EVENTS_PER_S_PER_THREAD * threads)
    if eta > SAY_ETA_S:
        say(f"simulate: about {per:.3g} interactions a photon (mu_a {medium.mua_per_mm:g}, mu_s {medium.mus_per_mm:g} /mm): "
            f"roughly {eta / 3600:.2g} h for {flux.n_photons:.3g} photons on {threads} thread(s)")
    # the batch size fixes which photons a seed draws, so it must not depend on this machine's threads:
    # sized for two (CI's), a batch takes at most BATCH_S there and less on more threads
    return int(min(flux.batch_photons, max(1000, BATCH_S * 2 * MC.EVENTS_PER_S_PER_THREAD / per)))


def montecarlo_truth(flux: C.MonteCarloFlux, shape, refinement: int, ray_offset_mm: float, placer, scenes: list,
                     views: list, say=lambda s: None) -> MonteCarloTruth:
    """Transport ``flux.n_photons`` photons once through the phantom ``shape``
    (:func:`montecarlo_shape`, its own frame) and make, batch by batch, the truth per face of
    its surface refined ``refinement`` times and the image of every pose (``scenes``:
    :class:`fluxcli.scene.PlacedScene` per pose; ``views``: direct first, then mirrors; rays
    leave surfaces ``ray_offset_mm`` off, as T's do)."""
    import time

    from .montecarlo import camera as MC_cam
    from .montecarlo import photons as MC_ph
    from .montecarlo import transport as MC
    from .surface.mesh import merge

    medium = MC.Medium(flux.mua_per_mm, flux.mus_per_mm, flux.g, flux.refractive_index)
    src = np.asarray(flux.position_mm, float)
    levels = refinement
    fine, parent = placer.own_surface.refined(levels)
    if shape is SUBJECT_MESH:  # photons inside the very faces the truth is tallied on: the exit's face is the one met
        shape = _mesh_body(fine, placer.surface_config, src, flux.radius_mm)
    elif shape.depth_mm(src[None])[0] <= flux.radius_mm:
        raise UserError(f"simulate.flux.position_mm: the source {src.tolist()} mm (radius {flux.radius_mm:g} mm) is not "
                        f"inside the phantom (its own frame: centred at the origin, half sizes "
                        f"{list(shape.half_mm)} mm along x, y, z).")
    batch_photons = _pace(flux, medium, shape, say)
    fine_scene = OcclusionScene(fine.vertices_mm, fine.faces)
    cam = views[0].camera
    P, V = len(scenes), len(views)
    check_memory(8.0 * cam.nx * cam.ny * P * 2 + 120.0 * min(batch_photons, flux.n_photons) * (1 + P / 4),
                 f"{P} photon image(s) of {cam.nx} x {cam.ny} pixels and batches of {batch_photons:.3g} photons",
                 "simulate.flux.batch_photons, subject.poses or system.camera.pixels")
    placements = [placer.placement(s.pose) for s in scenes]
    occl = [OcclusionScene(*merge(s.surface, *s.occluders)) for s in scenes]
    offset = ray_offset_mm
    images = np.zeros((P, cam.nx * cam.ny), np.int64)
    reached, on_sensor = np.zeros((P, V), np.int64), np.zeros((P, V), np.int64)
    fine_power = np.zeros(fine.n_elements)
    hist = np.zeros(len(MC_ph.ANGLE_EDGES_DEG) - 1)
    off_elements = 0.0
    kept = {"position_mm": [], "direction": [], "face": []} if flux.keep_photons else None
    tally = MC.Tally()
    t0 = time.perf_counter()
    n_batches = -(-flux.n_photons // batch_photons)
    for b in range(n_batches):
        n = min(batch_photons, flux.n_photons - b * batch_photons)
        esc = MC.transport(medium, shape, src, n, seed=flux.seed, batch=b, source_radius_mm=flux.radius_mm, tally=tally)
        if esc.face is not None:  # a mesh body: the triangle met is the fine face
            if b == 0:
                _exits_leave(shape, esc, placer.surface_config)
            face, normal = esc.face, shape.normals[esc.face]
        else:
            normal = shape.outward_normals(esc.position_mm)
            face = MC_ph.faces_of_exits(shape, fine.vertices_mm, fine.faces, esc.position_mm, scene=fine_scene)
        el = np.where(face >= 0, fine.element_of_face[np.maximum(face, 0)], -1)
        on = el >= 0
        fine_power += np.bincount(el[on], weights=esc.weight[on], minlength=fine.n_elements)
        off_elements += float(esc.weight[~on].sum())
        hist += MC_ph.exit_angle_histogram(normal, esc.direction, esc.weight)
        if kept is not None:
            kept["position_mm"].append(esc.position_mm)
            kept["direction"].append(esc.direction)
            kept["face"].append(face)
        for k, (R, t) in enumerate(placements):
            pos_w = (esc.position_mm + placer.rest_shift_mm) @ R.T + t
            img = MC_cam.image_photons(views, occl[k], pos_w, esc.direction @ R.T, normal @ R.T,
                                       np.random.default_rng([flux.seed, b, k]), ray_offset_mm=offset)
            images[k] += img.counts_per_pixel
            reached[k] += [img.reached_lens[v.name] for v in views]
            on_sensor[k] += [img.on_sensor[v.name] for v in views]
        say(f"simulate: photons {tally.launched:.3g} / {flux.n_photons:.3g} transported "
            f"({tally.launched / max(time.perf_counter() - t0, 1e-9):.3g} photons/s)")
    seconds = time.perf_counter() - t0
    photons = None
    if kept is not None:
        photons = {k: np.concatenate(v) if v else np.zeros((0, 3)) for k, v in kept.items()}
    notes = {"launched": tally.launched, "escaped": tally.escaped, "absorbed": tally.absorbed, "lost": tally.lost,
             "path_mm": tally.path_mm, "photons_per_s": tally.launched / max(seconds, 1e-9),
             "not_on_elements": off_elements, "source_mm": src.tolist(), "truth_refinement": levels,
             "transport": "MCML-style, analogue absorption, probabilistic Fresnel, Henyey-Greenstein",
             "body": (f"the subject's own mesh, {len(shape.faces)} triangles (refined {levels}x)" if _is_mesh_body(shape)
                      else f"analytic {'box' if shape.kind == MC.BOX else 'cylinder'}, half sizes {list(shape.half_mm)} mm"),
             "seconds": seconds}
    return MonteCarloTruth(fine_power, parent, images.reshape(P, cam.ny, cam.nx), reached, on_sensor, hist, tally,
                           off_elements, photons, seconds, notes)


def lost_photons_warning(lost: int, launched: int, flux) -> str | None:
    """Photons the transport cut off (still inside after its cap on interactions): their light
    is in neither the truth nor the images, which the user should hear with the keys to check."""
    from .montecarlo.transport import MAX_EVENTS

    if not lost:
        return None
    return (f"simulate: {lost} of {launched:.4g} photons ({lost / launched:.2%}) were still inside the body after "
            f"{MAX_EVENTS:.0e} interactions each and are left out of the truth and the images; with mu_a "
            f"{flux.mua_per_mm:g} /mm and mu_s {flux.mus_per_mm:g} /mm light stays inside that long (tissue: mu_s' "
            "about 1 /mm, mu_a 0.01-1 /mm).")


FEW_PHOTONS = 1000  # whole photons in an image below which its reconstruction is mostly photon noise


def few_photons_warning(in_image: float, launched: float, where: str) -> list[str]:
    """What to say when a Monte Carlo image holds so few photons that its reconstruction would
    be mostly shot noise (a per-element error of tens of per cent): the photons to launch for
    ~10^5 an image, as this run's own collection implies."""
    if in_image >= FEW_PHOTONS:
        return []
    if in_image <= 0:
        return [f"{where}: no photon reached the image; check that the subject is in view, or launch more "
                f"(simulate.flux.n_photons, {launched:.3g} now)."]
    photons = f"{in_image:.0f} photon{'' if in_image == 1 else 's'}"
    return [f"{where}: only {photons} reached the image, so its reconstruction is mostly photon "
            f"noise; about {launched * 1e5 / in_image:.2g} launched (simulate.flux.n_photons, {launched:.3g} now) "
            f"would give 10^5."]
