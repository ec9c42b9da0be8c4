"""``fluxmap simulate CONFIG``: ground-truth surface flux and realistic camera images.

Examples
--------
$ fluxmap simulate configs/paper-2d.yaml
$ fluxmap simulate configs/paper-3d.yaml --set simulate.noise.repeats=3

The truth is a power per surface element (photons per exposure); images are
``a = T_fwd b`` per pose, with ``T_fwd`` sampled more finely than the T that
reconstruction uses (no inverse crime unless ``simulate.allow_inverse_crime``), then noise.
"""

from __future__ import annotations

import json
import time
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np

from .. import artefacts as A
from .. import config as C
from ..diffusion.surface_flux import element_power_from_sources
from ..errors import UserError
from ..imaging import noise as N
from ..imaging.imagefiles import write_image
from ..optics.raycast import OcclusionScene
from ..scene import SubjectPlacer
from ..surface.mesh import Surface
from ..optics.transfer import ALGORITHM_VERSION
from ..artefacts.transfer import load_T
from ..pipeline import cache_dir, check_folders, check_memory, emccd_model, ensure_T, plan, provenance
from .context import RunContext
from .outputs import export_3d


def forward_transfer(cfg: C.LoadedConfig) -> C.Transfer:
    """The forward T's sampling: as configured, or finer than reconstruction's in every
    sampling key (and built on the refined surface the truth lives on)."""
    sim = cfg.model.simulate
    if sim.transfer is not None:
        return sim.transfer
    tr = cfg.model.transfer
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
def truth_power(cfg: C.LoadedConfig, surface: Surface) -> tuple[np.ndarray, dict]:
    """Power per element (photons per exposure) of the subject at rest, and notes: the
    fine truth (:func:`truth_fine`) summed per element."""
    fine, parent, notes = truth_fine(cfg, surface)
    return np.bincount(parent, weights=fine, minlength=surface.n_elements), notes


def truth_refinement(sim: C.Simulate) -> int:
    """How often the truth surface splits each triangle into 4: as configured, else 1 (0 when
    an inverse crime is explicitly allowed: the same T then reproduces the images exactly)."""
    if sim.truth_refinement is not None:
        return sim.truth_refinement
    return 0 if sim.allow_inverse_crime else 1


def truth_fine(cfg: C.LoadedConfig, surface: Surface) -> tuple[np.ndarray, np.ndarray, dict]:
    """The truth on a surface finer than the reconstruction's elements (no inverse crime):
    power per face of ``surface.refined(simulate.truth_refinement)``, with the element each
    fine face belongs to. Gaussian, uniform and diffusion truths vary within an element;
    a per-element file can only be spread by area (constant exitance within the element)."""
    levels = truth_refinement(cfg.model.simulate)
    fine, parent = surface.refined(levels)
    flux = cfg.model.simulate.flux
    if isinstance(flux, C.GaussianFlux):
        # exitance J(x) = exp(-|x - c|²/2w²) integrated over the fine faces, scaled so the
        # brightest element emits peak_photons
        cen = surface.element_centroids_mm
        centre = np.asarray(flux.center_mm) if flux.center_mm is not None else cen[np.argmax(cen[:, 2])]
        d2 = ((fine.element_centroids_mm - centre) ** 2).sum(axis=1)
        p = np.exp(-d2 / (2 * flux.width_mm**2)) * fine.element_areas_mm2
        per_element = np.bincount(parent, weights=p, minlength=surface.n_elements)
        return p * flux.peak_photons / per_element.max(), parent, {"center_mm": centre.tolist(),
                                                                   "truth_refinement": levels}
    if isinstance(flux, C.DiffusionFlux):
        p, notes = _diffusion_truth(flux, surface, cfg.workdir / "cache" / "mesh", fine=fine,
                                    shipped=cfg.resolve(flux.mesh_dir) if flux.mesh_dir is not None else None)
        return p, parent, notes | {"truth_refinement": levels}
    per_element, notes = _truth_per_element(cfg, surface)
    share = fine.element_areas_mm2 / surface.element_areas_mm2[parent]
    return per_element[parent] * share, parent, notes | {"truth_refinement": levels}


def _truth_per_element(cfg: C.LoadedConfig, surface: Surface) -> tuple[np.ndarray, dict]:
    flux = cfg.model.simulate.flux
    areas = surface.element_areas_mm2
    if isinstance(flux, C.UniformFlux):
        return flux.exitance_photons_per_mm2 * areas, {}
    if isinstance(flux, C.FileFlux):
        path = cfg.resolve(flux.path)
        if not path.is_file():
            raise UserError(f"simulate.flux.path: file {path} does not exist.")
        try:
            values = np.load(path) if path.suffix == ".npy" else np.loadtxt(path)
        except Exception as e:  # numpy raises several kinds for malformed files
            raise UserError(f"simulate.flux.path: {path} is not a readable list of numbers ({e}).") from None
        values = np.asarray(values, float).ravel()
        if len(values) != surface.n_elements:
            raise UserError(f"simulate.flux.path: {path} holds {len(values)} values; the surface has "
                            f"{surface.n_elements} elements.")
        if np.any(values < 0) or not np.all(np.isfinite(values)):
            raise UserError(f"simulate.flux.path: {path} holds negative or non-finite values.")
        return (values if flux.quantity == "power" else values * areas), {}
    raise AssertionError(f"unhandled flux kind {flux.kind}")


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


def tetmesh_key(surface: Surface, mesh_edge_mm: float) -> str:
    """Content address of the tetrahedral mesh of ``surface`` (cache and shipped meshes)."""
    return A.cache_key({"surface": surface.digest(), "edge_length_mm": A.canonical(mesh_edge_mm), "mesher": "ftetwild-1"})


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
    if shipped is not None and (shipped / f"{key}.h5").is_file():
        path = shipped / f"{key}.h5"
    mesh = None
    if path.is_file():
        try:
            with A.open_artefact(path, "tetmesh") as f:
                mesh = (f["nodes"][()], f["tets"][()])
        except UserError as e:
            warnings.warn(f"the cached tetrahedral mesh is unreadable and is remade: {e}")
            mesh = None
    if mesh is None:
        from ..diffusion.mesh import tetrahedralize

        try:
            mesh = tetrahedralize(surface.vertices_mm, surface.faces, edge_length_mm=flux.mesh_edge_mm)
        except ValueError as e:
            raise UserError(f"simulate.flux: {e}") from None
        with A.write_artefact(path, "tetmesh") as f:
            A.put(f, "nodes", mesh[0])
            A.put(f, "tets", mesh[1])
        made = True
    else:
        made = False
    try:
        power, info = element_power_from_sources(
            fine if fine is not None else surface, mua_per_mm=opt.mua_per_mm, musp_per_mm=opt.musp_per_mm, refractive_index=opt.refractive_index,
            positions_mm=pos, radii_mm=np.array([s.radius_mm for s in flux.sources]),
            powers_photons=np.array([s.power_photons for s in flux.sources]), edge_length_mm=flux.mesh_edge_mm,
            mesh=mesh)
    except ValueError as e:
        raise UserError(f"simulate.flux: {e}") from None
    info.pop("nodes_mm"), info.pop("tets")
    info["source_positions_mm"] = pos.tolist()
    info["mesh_cached"] = not made
    info["mesh_key"] = key
    return power, info


# ------------------------------------------------------------------ images
def levels(cfg: C.LoadedConfig, power: np.ndarray) -> np.ndarray:
    peaks = cfg.model.simulate.noise.peaks_photons
    return np.array(peaks if peaks is not None else [power.max()], float)


def add_noise(a: np.ndarray, noise: C.Noise, sensor: C.Sensor, rng: np.random.Generator):
    """Noisy photons (and counts for the EMCCD chain, else None)."""
    if noise.model == "none":
        return a.copy(), None
    if noise.model == "gaussian":
        return N.gaussian_shot(a, rng), None
    if noise.model == "poisson":
        return N.poisson_shot(a, rng), None
    model = emccd_model(sensor, noise.exposure_s)
    counts = N.emccd_counts(a, model, rng)
    return N.counts_to_photons(counts, model), counts


def run(cfg: C.LoadedConfig, ctx: RunContext) -> Path:
    sim = cfg.model.simulate
    if sim is None:
        raise UserError(f"config {cfg.path}: 'simulate': section is missing (flux, noise, ...); see the README.")
    check_folders(cfg)
    tr_fwd = forward_transfer(cfg)
    views, placer, todo = plan(cfg, tr_fwd, unknowns=f"refined:{truth_refinement(sim)}")
    _, _, todo_rec = plan(cfg)
    what_T_depends_on = {"estimator", "lens", "pairwise", "ray_offset_mm"}  # not where it is cached
    same_sampling = (tr_fwd.model_dump(include=what_T_depends_on)
                     == cfg.model.transfer.model_dump(include=what_T_depends_on))
    if not sim.allow_inverse_crime and (same_sampling or [p.key for _, p in todo] == [p.key for _, p in todo_rec]):
        raise UserError("simulate.transfer: the forward T would be sampled exactly as the T that reconstruct uses "
                        "(an inverse crime, even on the refined truth surface); sample it more finely, or set "
                        "simulate.allow_inverse_crime: true.")
    surface = placer.surface
    out = cfg.workdir / "simulation.h5"
    m = cfg.model
    digest = A.inputs_digest(system=m.system.model_dump(mode="json"), subject=m.subject.model_dump(mode="json"),
                             surface=surface.digest(), transfer_fwd=tr_fwd.model_dump(mode="json"),
                             simulate=sim.model_dump(mode="json"), version=ALGORITHM_VERSION)
    if not ctx.force and A.is_up_to_date(out, "simulation", digest):
        ctx.say(f"simulate: {out} is up to date (--force to redo)")
        return out
    t0 = time.perf_counter()
    fine_power, parent, notes = truth_fine(cfg, surface)
    power = np.bincount(parent, weights=fine_power, minlength=surface.n_elements)
    if power.max() <= 0:
        raise UserError("simulate.flux: the ground truth is zero everywhere.")
    truth_seconds = time.perf_counter() - t0
    ctx.say(f"simulate: truth '{sim.flux.kind}' on {surface.n_elements} elements, total "
            f"{power.sum():.4g} photons, peak {power.max():.4g} ({truth_seconds:.1f} s)")
    views, placer, todo, built = ensure_T(cfg, replace(ctx, force=False), tr_fwd, label="building forward T",
                                          unknowns=f"refined:{truth_refinement(sim)}")
    lv = levels(cfg, power)
    scale = lv / power.max()
    nx, ny = cfg.model.system.camera.pixels
    P, L, R = len(todo), len(lv), sim.noise.repeats
    check_memory(4.0 * nx * ny * P * L * (1 + R * (1.5 if sim.noise.model == "emccd" else 1)) * 2,
                 f"simulating {L} level(s) x {R} repeat(s) x {P} pose(s) of {nx} x {ny} pixels",
                 "simulate.noise.peaks_photons, simulate.noise.repeats, subject.poses or system.camera.pixels")
    clean = np.zeros((L, P, ny, nx), np.float32)
    noisy = np.zeros((L, R, P, ny, nx), np.float32)
    counts = np.zeros((L, R, P, ny, nx), np.uint16) if sim.noise.model == "emccd" else None
    for k, (scene, pt) in enumerate(todo):
        a1 = load_T(pt.path) @ fine_power  # the truth varies within the elements
        for li in range(L):
            a = a1 * scale[li]
            clean[li, k] = a.reshape(ny, nx)
            for r in range(R):
                rng = np.random.default_rng([sim.noise.seed, li, r, k])
                try:
                    ph, c = add_noise(a, sim.noise, cfg.model.system.camera.sensor, rng)
                except ValueError as e:  # e.g. numpy's Poisson sampler above ~1e19 photons
                    raise UserError(f"simulate.noise.peaks_photons: level {lv[li]:.3g} photons cannot be sampled "
                                    f"with the {sim.noise.model} noise model ({e}); use a lower level.") from None
                noisy[li, r, k] = ph.reshape(ny, nx)
                if counts is not None:
                    counts[li, r, k] = c.reshape(ny, nx)
    snr = np.sqrt(clean.reshape(L, P, -1).max(axis=2))
    prov = provenance(cfg, surface.digest())
    with A.write_artefact(out, "simulation", config_sha256=cfg.sha256,
                          inputs={f"T_fwd_{k}": pt.key for k, (_, pt) in enumerate(todo)}, provenance=prov) as f:
        f.attrs["inputs_digest"] = digest
        A.write_surface(f.create_group("surface"), surface)
        A.put(f, "truth/power", power)
        A.put(f, "truth/exitance", power / surface.element_areas_mm2)
        A.put(f, "truth/power_fine", fine_power)
        A.put(f, "truth/fine_parent", parent)
        g = f["truth"]
        g.attrs["kind"] = sim.flux.kind
        g.attrs["notes"] = json.dumps({k: (A.recorded_seconds(v) if k.endswith("_seconds") else v)
                                       for k, v in notes.items()})
        A.put(f, "truth/levels_peak_photons", lv)
        A.put(f, "truth/level_scale", scale)
        A.put(f, "poses/heights_mm", [pt.pose.height_mm for _, pt in todo])
        A.put(f, "poses/rotations_deg", [pt.pose.rotation_deg for _, pt in todo])
        A.put(f, "poses/T_fwd_keys", np.array([pt.key for _, pt in todo], dtype="S64"))
        chunk = (1, 1, 1, ny, nx)
        packed = dict(compression="gzip", fletcher32=True)
        A.put(f, "images/noiseless", clean, chunks=(1, 1, ny, nx), **packed)
        A.put(f, "images/noisy", noisy, chunks=chunk, **packed)
        if counts is not None:
            A.put(f, "images/counts", counts, chunks=chunk, **packed)
        A.put(f, "images/max_snr", snr)
        ig = f["images"]
        ig.attrs["layout"] = "noisy[level, repeat, pose, row, col]; noiseless[level, pose, row, col]"
        ig.attrs["noise_model"] = sim.noise.model
        ig.attrs["seed"] = sim.noise.seed
        ig.attrs["exposure_s"] = sim.noise.exposure_s
        f.attrs["transfer_fwd"] = json.dumps(tr_fwd.model_dump(mode="json"))
        f.attrs["transfer_fwd_cache"] = A.portable_path(cache_dir(cfg), out.parent)
        f.attrs["truth_seconds"] = A.recorded_seconds(truth_seconds)
    if sim.export.format != "none":
        export_images(cfg, out.parent / "images", noisy, counts, todo, lv)
    rows = [[pt.pose.height_mm, pt.pose.rotation_deg, *[f"{snr[li, k]:.1f}" for li in range(L)]]
            for k, (_, pt) in enumerate(todo)]
    ctx.table(["height_mm", "rotation_deg", *[f"SNR @ peak {x:.0e}" for x in lv]], rows)
    export_3d(cfg, ctx, out)  # <workdir>/*.vtp for ParaView/pyvista, from the artefact
    return out


def export_images(cfg: C.LoadedConfig, folder: Path, noisy, counts, todo, lv) -> None:
    """One file per level, repeat and pose: counts as 16-bit TIFF (EMCCD) or photons as float."""
    fmt = cfg.model.simulate.export
    suffix = ".tif" if fmt.format == "tiff" else ".fits"
    for li in range(noisy.shape[0]):
        for r in range(min(fmt.repeats, noisy.shape[1])):
            for k, (_, pt) in enumerate(todo):
                name = folder / f"level{li}" / f"h{pt.pose.height_mm:+g}_rot{pt.pose.rotation_deg:g}_rep{r}{suffix}"
                name.parent.mkdir(parents=True, exist_ok=True)
                meta = {"fluxmap:height_mm": pt.pose.height_mm, "fluxmap:rotation_deg": pt.pose.rotation_deg,
                        "fluxmap:level_peak_photons": float(lv[li]), "fluxmap:repeat": r}
                if counts is not None:
                    write_image(name, counts[li, r, k], metadata=meta | {"fluxmap:units": "counts"})
                else:
                    write_image(name, noisy[li, r, k].astype(np.float32), metadata=meta | {"fluxmap:units": "photons"})
