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
from dataclasses import replace
from pathlib import Path

import numpy as np

from .. import artefacts as A
from .. import config as C
from ..errors import UserError
from ..imaging import noise as N
from ..imaging.imagefiles import write_image
from ..optics.transfer import ALGORITHM_VERSION
from ..artefacts.transfer import load_T, load_T_tangent
from ..pipeline import (cache_dir, check_folders, check_memory, emccd_model, ensure_T, geometry_of, plan,
                        provenance, without_emission)
from .context import RunContext
from .outputs import export_3d


from ..truth import forward_transfer, montecarlo_shape, montecarlo_truth, truth_fine, truth_refinement


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
    if isinstance(sim.flux, C.MonteCarloFlux):
        return _run_montecarlo(cfg, ctx)
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
    digest = A.inputs_digest(system=m.system.model_dump(mode="json"), subject=geometry_of(cfg)["subject"],
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
            f"{power.sum():.4g} photons, peak {power.max():.4g} ({truth_seconds:.1f} s)"
            + (f"; the FEM's undershoot clipped: {notes['clipped_photons']:.3g} photons "
               f"({notes['clipped_photons'] / power.sum():.2%})" if notes.get("clipped_photons") else ""))
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
    tangent = None  # the emission's tangential flux (diffuse): the truth's gradient, once
    for k, (scene, pt) in enumerate(todo):
        a1 = load_T(pt.path) @ fine_power  # the truth varies within the elements
        T_tangent = load_T_tangent(pt.path) if truth_refinement(sim) > 0 else None  # one face per column
        if T_tangent is not None:
            from ..optics.emission import tangent_light

            if tangent is None:
                tangent = tangent_light(surface.refined(truth_refinement(sim))[0], fine_power)
            a1 = np.maximum(a1 + T_tangent @ tangent, 0.0)
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


def _run_montecarlo(cfg: C.LoadedConfig, ctx: RunContext) -> Path:
    """``simulate.flux.kind: montecarlo``: one photon run through the phantom; the truth is the
    photons that left through each element, the images those photons through lens and mirrors
    (no forward T, no emission model)."""
    from ..scene import SubjectPlacer, poses_from_config, views_from_config
    from ..montecarlo.photons import ANGLE_EDGES_DEG

    sim, m = cfg.model.simulate, cfg.model
    montecarlo_shape(m.subject.surface)  # refuse what it cannot model before anything else
    if sim.noise.model not in ("none", "poisson"):
        raise UserError(f"simulate.noise.model: {sim.noise.model!r} with simulate.flux.kind montecarlo; the photons are "
                        "whole photons and their count is the shot noise: use poisson (or none, the same here).")
    if sim.noise.peaks_photons is not None or sim.noise.repeats != 1:
        raise UserError("simulate.noise.peaks_photons / repeats: a Monte Carlo run has one level (simulate.flux.n_photons "
                        "sets it) and one draw (another simulate.flux.seed is another draw); remove them.")
    placer = SubjectPlacer(cfg)
    views = views_from_config(m.system)
    poses = poses_from_config(m.subject)
    scenes = [placer.scene(p, m.system) for p in poses]
    surface = placer.surface
    out = cfg.workdir / "simulation.h5"
    digest = A.inputs_digest(system=m.system.model_dump(mode="json"),
                             subject=m.subject.model_dump(mode="json", exclude={"emission"}),
                             surface=surface.digest(), simulate=sim.model_dump(mode="json"),
                             transfer_offset=m.transfer.ray_offset_mm, version=ALGORITHM_VERSION, montecarlo=1)
    if not ctx.force and A.is_up_to_date(out, "simulation", digest):
        ctx.say(f"simulate: {out} is up to date (--force to redo)")
        return out
    mc = montecarlo_truth(cfg, placer, scenes, views, say=ctx.say)
    power = np.bincount(mc.parent, weights=mc.fine_power, minlength=surface.n_elements)
    if power.max() <= 0:
        raise UserError("simulate.flux: no photon left through an element (too few photons or too much absorption).")
    t = mc.tally
    ctx.say(f"simulate: {t.launched:.4g} photons launched, {t.escaped:.4g} escaped ({t.escaped / t.launched:.1%}), "
            f"{t.absorbed:.4g} absorbed, {t.lost} lost; {power.sum():.4g} through the {surface.n_elements} elements "
            f"({mc.seconds:.1f} s, {mc.notes['photons_per_s']:.3g} photons/s)")
    P, ny, nx = mc.images.shape
    clean = mc.images.astype(np.float32)[None]
    prov = provenance(cfg, surface.digest())
    prov.geometry = without_emission(prov.geometry)  # the photons assume no emission model
    with A.write_artefact(out, "simulation", config_sha256=cfg.sha256, inputs={}, provenance=prov) as f:
        f.attrs["inputs_digest"] = digest
        A.write_surface(f.create_group("surface"), surface)
        A.put(f, "truth/power", power)
        A.put(f, "truth/exitance", power / surface.element_areas_mm2)
        A.put(f, "truth/power_fine", mc.fine_power)
        A.put(f, "truth/fine_parent", mc.parent)
        g = f["truth"]
        g.attrs["kind"] = sim.flux.kind
        g.attrs["notes"] = json.dumps({k: (A.recorded_seconds(v) if k.endswith("seconds") else v)
                                       for k, v in mc.notes.items()})
        A.put(f, "truth/levels_peak_photons", [power.max()])
        A.put(f, "truth/level_scale", [1.0])
        A.put(f, "poses/heights_mm", [p.height_mm for p in poses])
        A.put(f, "poses/rotations_deg", [p.rotation_deg for p in poses])
        A.put(f, "poses/T_fwd_keys", np.array([b"montecarlo"] * P, dtype="S64"))
        packed = dict(compression="gzip", fletcher32=True)
        A.put(f, "images/noiseless", clean, chunks=(1, 1, ny, nx), **packed)
        A.put(f, "images/noisy", clean[:, None], chunks=(1, 1, 1, ny, nx), **packed)
        A.put(f, "images/max_snr", np.sqrt(clean.reshape(1, P, -1).max(axis=2)))
        ig = f["images"]
        ig.attrs["layout"] = "noisy[level, repeat, pose, row, col]; noiseless[level, pose, row, col]"
        ig.attrs["noise_model"] = "photons (Monte Carlo: whole photons; noisy and noiseless hold the same image)"
        ig.attrs["seed"] = sim.flux.seed
        ig.attrs["exposure_s"] = sim.noise.exposure_s
        mg = f.create_group("montecarlo")
        A.put(f, "montecarlo/photons_per_element", power)
        A.put(f, "montecarlo/exit_angle_histogram", mc.angle_histogram)
        A.put(f, "montecarlo/exit_angle_edges_deg", ANGLE_EDGES_DEG)
        A.put(f, "montecarlo/reached_lens", mc.reached_lens)
        A.put(f, "montecarlo/on_sensor", mc.on_sensor)
        mg.attrs["views"] = json.dumps([v.name for v in views])
        for k in ("launched", "escaped", "absorbed", "lost"):
            mg.attrs[k] = int(getattr(t, k))
        mg.attrs["not_on_elements"] = mc.not_on_elements
        mg.attrs["rest_shift_mm"] = placer.rest_shift_mm
        if mc.photons is not None:
            for k, v in mc.photons.items():
                A.put(f, f"montecarlo/photons/{k}", v, **packed)
        f.attrs["truth_seconds"] = A.recorded_seconds(mc.seconds)
    rows = [[p.height_mm, p.rotation_deg, int(mc.images[k].sum()), *[int(x) for x in mc.reached_lens[k]]]
            for k, p in enumerate(poses)]
    ctx.table(["height_mm", "rotation_deg", "photons in image", *[f"reached lens: {v.name}" for v in views]], rows)
    export_3d(cfg, ctx, out)
    return out
