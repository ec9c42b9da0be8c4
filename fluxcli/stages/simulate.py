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

import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from .. import artefacts as A
from .. import config as C
from ..artefacts import simulation as AS
from ..artefacts.provenance import without_emission
from ..artefacts.transfer import load_T, load_T_curvature, load_T_tangent
from ..errors import UserError
from ..imaging import noise as N
from ..imaging.imagefiles import write_image
from ..optics.transfer import ALGORITHM_VERSION
from ..resources import check_memory
from ..transfer_cache import TransferPlan, ensure
from ..truth import (TruthPlan, few_photons_warning, forward_transfer, lost_photons_warning, montecarlo_shape,
                     montecarlo_truth, truth_fine)
from .context import RunContext
from .outputs import export_simulation, simulation_exposure_s
from .plans import check_folders, emccd_model, geometry_of, transfer_plan, truth_plan


@dataclass(frozen=True)
class SimulatePlan:
    """What ``simulate`` does, resolved from the config at its top."""

    settings: C.Simulate  # simulate: flux, noise, export
    out: Path  # <workdir>/simulation.h5
    forward: TransferPlan  # the forward T per pose (on the refined truth surface; Monte Carlo: the placed scenes)
    truth: TruthPlan
    sensor: C.Sensor  # system.camera.sensor: the EMCCD chain's noise
    digest: str  # what simulation.h5 depends on (up to date when it records the same)
    ray_offset_mm: float = 0.0  # transfer.ray_offset_mm (Monte Carlo: the photons' rays)


def plan_simulation(cfg: C.LoadedConfig) -> SimulatePlan:
    """The config as :class:`SimulatePlan`; a UserError for an inverse crime not asked for."""
    sim, m = cfg.model.simulate, cfg.model
    out = cfg.workdir / AS.FILE_NAME
    if isinstance(sim.flux, C.MonteCarloFlux):
        tp = transfer_plan(cfg)  # its scenes: no T is built
        digest = A.inputs_digest(system=m.system.model_dump(mode="json"),
                                 subject=m.subject.model_dump(mode="json", exclude={"emission"}),
                                 surface=tp.placer.surface.digest(), simulate=sim.model_dump(mode="json"),
                                 transfer_offset=m.transfer.ray_offset_mm, version=ALGORITHM_VERSION, montecarlo=1)
        return SimulatePlan(sim, out, tp, truth_plan(cfg), m.system.camera.sensor, digest, m.transfer.ray_offset_mm)
    truth = truth_plan(cfg)
    tr_fwd = forward_transfer(sim, m.transfer)
    forward = transfer_plan(cfg, tr_fwd, unknowns=f"refined:{truth.refinement}")
    rec = transfer_plan(cfg)
    what_T_depends_on = {"estimator", "lens", "pairwise", "ray_offset_mm"}  # not where it is cached
    same_sampling = (tr_fwd.model_dump(include=what_T_depends_on)
                     == m.transfer.model_dump(include=what_T_depends_on))
    if not sim.allow_inverse_crime and (same_sampling or [p.key for _, p in forward.poses]
                                        == [p.key for _, p in rec.poses]):
        raise UserError("simulate.transfer: the forward T would be sampled exactly as the T that reconstruct uses "
                        "(an inverse crime, even on the refined truth surface); sample it more finely, or set "
                        "simulate.allow_inverse_crime: true.")
    digest = A.inputs_digest(system=m.system.model_dump(mode="json"), subject=geometry_of(cfg)["subject"],
                             surface=forward.placer.surface.digest(), transfer_fwd=tr_fwd.model_dump(mode="json"),
                             simulate=sim.model_dump(mode="json"), version=ALGORITHM_VERSION)
    return SimulatePlan(sim, out, forward, truth, m.system.camera.sensor, digest)


# ------------------------------------------------------------------ images
def levels(noise: C.Noise, power: np.ndarray) -> np.ndarray:
    """The brightest element's power at each signal level (``noise.peaks_photons``, else the truth's)."""
    return np.array(noise.peaks_photons if noise.peaks_photons is not None else [power.max()], float)


MAX_PIXEL_PHOTONS = 1e30  # no camera collects this in a pixel; float32 holds up to 3.4e38


def add_noise(a: np.ndarray, noise: C.Noise, sensor: C.Sensor, rng: np.random.Generator):
    """Noisy photons (and counts for the EMCCD chain, else None). Images are stored as float32
    (max 3.4e38): a pixel past MAX_PIXEL_PHOTONS is a ValueError, not an inf written."""
    if not (np.all(np.isfinite(a)) and np.max(a, initial=0.0) <= MAX_PIXEL_PHOTONS):
        raise ValueError(f"its brightest pixel would hold {np.max(a):.3g} photons, beyond the {MAX_PIXEL_PHOTONS:g} "
                         "the images (float32) store faithfully")
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
    shape = None
    if isinstance(sim.flux, C.MonteCarloFlux):
        shape = montecarlo_shape(cfg.model.subject.surface)  # refuse what it cannot model before anything else
        _refuse_montecarlo_noise(sim)
    sp = plan_simulation(cfg)
    if not ctx.force and A.is_up_to_date(sp.out, "simulation", sp.digest):
        ctx.say(f"simulate: {sp.out} is up to date (--force to redo)")
        return sp.out
    out = _simulate(sp, ctx) if shape is None else _simulate_montecarlo(sp, shape, ctx)
    export_simulation(ctx, out, simulation_exposure_s(cfg.model.simulate))  # <workdir>/*.vtp for ParaView/pyvista
    return out


def _refuse_montecarlo_noise(sim: C.Simulate) -> None:
    if sim.noise.model not in ("none", "poisson"):
        raise UserError(f"simulate.noise.model: {sim.noise.model!r} with simulate.flux.kind montecarlo; the photons are "
                        "whole photons and their count is the shot noise: use poisson (or none, the same here).")
    if sim.noise.peaks_photons is not None or sim.noise.repeats != 1:
        raise UserError("simulate.noise.peaks_photons / repeats: a Monte Carlo run has one level (simulate.flux.n_photons "
                        "sets it) and one draw (another simulate.flux.seed is another draw); remove them.")


def _simulate(sp: SimulatePlan, ctx: RunContext) -> Path:
    """Truth, forward T per pose, images at every level and repeat; ``simulation.h5``."""
    sim, fwd = sp.settings, sp.forward
    surface = fwd.placer.surface
    t0 = time.perf_counter()
    fine_power, parent, notes = truth_fine(sp.truth, surface)
    power = np.bincount(parent, weights=fine_power, minlength=surface.n_elements)
    if power.max() <= 0:
        raise UserError("simulate.flux: the ground truth is zero everywhere.")
    truth_seconds = time.perf_counter() - t0
    ctx.say(f"simulate: truth '{sim.flux.kind}' on {surface.n_elements} elements, total "
            f"{power.sum():.4g} photons, peak {power.max():.4g} ({truth_seconds:.1f} s)"
            + (f"; the FEM's undershoot clipped: {notes['clipped_photons']:.3g} photons "
               f"({notes['clipped_photons'] / power.sum():.2%})" if notes.get("clipped_photons") else ""))
    ensure(fwd, replace(ctx, force=False), label="building forward T")
    todo = fwd.poses
    lv = levels(sim.noise, power)
    scale = lv / power.max()
    nx, ny = fwd.views[0].camera.nx, fwd.views[0].camera.ny
    P, L, R = len(todo), len(lv), sim.noise.repeats
    check_memory(4.0 * nx * ny * P * L * (1 + R * (1.5 if sim.noise.model == "emccd" else 1)) * 2,
                 f"simulating {L} level(s) x {R} repeat(s) x {P} pose(s) of {nx} x {ny} pixels",
                 "simulate.noise.peaks_photons, simulate.noise.repeats, subject.poses or system.camera.pixels")
    clean = np.zeros((L, P, ny, nx), np.float32)
    noisy = np.zeros((L, R, P, ny, nx), np.float32)
    counts = np.zeros((L, R, P, ny, nx), np.uint16) if sim.noise.model == "emccd" else None
    tangent = None  # the emission's tangential flux (diffuse): the truth's gradient, once
    curvature = None  # the emission's curvature term: the truth's Laplacian, once
    for k, (scene, pt) in enumerate(todo):
        a1 = load_T(pt.path) @ fine_power  # the truth varies within the elements
        T_tangent = load_T_tangent(pt.path) if sp.truth.refinement > 0 else None  # one face per column
        if T_tangent is not None:
            from ..optics.emission import tangent_light

            if tangent is None:
                tangent = tangent_light(surface.refined(sp.truth.refinement)[0], fine_power)
            a1 = np.maximum(a1 + T_tangent @ tangent, 0.0)
        if sp.truth.refinement > 0 and scene.emission is not None and scene.emission.has_curvature:
            from ..optics.emission import curvature_power
            from ..transfer_cache import curvature_ratios

            if curvature is None:
                curvature = curvature_power(surface.refined(sp.truth.refinement)[0], fine_power, scene.emission)
            a1 = np.maximum(a1 + load_T_curvature(pt.path, curvature_ratios(scene.surface, fwd.views, scene.emission))
                            @ curvature, 0.0)
        level_key = ("simulate.noise.peaks_photons" if sim.noise.peaks_photons is not None
                     else "simulate.flux (its own level; simulate.noise.peaks_photons sets another)")
        for li in range(L):
            a = a1 * scale[li]
            for r in range(R):
                rng = np.random.default_rng([sim.noise.seed, li, r, k])
                try:
                    ph, c = add_noise(a, sim.noise, sp.sensor, rng)
                except ValueError as e:  # e.g. numpy's Poisson sampler above ~1e19 photons
                    raise UserError(f"{level_key}: level {lv[li]:.3g} photons, pose {k}, cannot be sampled "
                                    f"with the {sim.noise.model} noise model ({e}); use a lower level.") from None
                clean[li, k], noisy[li, r, k] = a.reshape(ny, nx), ph.reshape(ny, nx)
                if counts is not None:
                    counts[li, r, k] = c.reshape(ny, nx)
    snr = np.sqrt(clean.reshape(L, P, -1).max(axis=2))
    AS.write(sp.out, AS.Simulation(
        surface=surface, power=power, exitance=power / surface.element_areas_mm2, levels_peak_photons=lv,
        level_scale=scale, power_fine=fine_power, fine_parent=parent,
        heights_mm=[pt.pose.height_mm for _, pt in todo], rotations_deg=[pt.pose.rotation_deg for _, pt in todo],
        T_fwd_keys=[pt.key for _, pt in todo], noiseless=clean, noisy=noisy, counts=counts, max_snr=snr,
        truth_kind=sim.flux.kind, truth_notes=_recorded(notes, "_seconds"), noise_model=sim.noise.model,
        seed=sim.noise.seed, exposure_s=sim.noise.exposure_s, inputs_digest=sp.digest,
        truth_seconds=A.recorded_seconds(truth_seconds), transfer_fwd=fwd.transfer.model_dump(mode="json"),
        transfer_fwd_cache=A.portable_path(fwd.cache_dir, sp.out.parent)),
        config_sha256=fwd.config_sha256, inputs={f"T_fwd_{k}": pt.key for k, (_, pt) in enumerate(todo)},
        provenance=fwd.provenance)
    if sim.export.format != "none":
        from .outputs import simulation_exposure_s

        export_images(sim.export, sp.out.parent / "images", noisy, counts, todo, lv, simulation_exposure_s(sim))
    rows = [[pt.pose.height_mm, pt.pose.rotation_deg, *[f"{snr[li, k]:.1f}" for li in range(L)]]
            for k, (_, pt) in enumerate(todo)]
    ctx.table(["height_mm", "rotation_deg", *[f"SNR @ peak {x:.0e}" for x in lv]], rows)
    return sp.out


def _recorded(notes: dict, ending: str) -> dict:
    """Notes as an artefact records them: durations NaN in a reproducible run."""
    return {k: (A.recorded_seconds(v) if k.endswith(ending) else v) for k, v in notes.items()}


def export_images(export: C.Export, folder: Path, noisy, counts, todo, lv, exposure_s: float | None = None) -> None:
    """One file per level, repeat and pose: counts as 16-bit TIFF (EMCCD) or photons as float,
    with the exposure the config states (``fluxmap:exposure_s``; reconstruct takes rates from it)."""
    suffix = ".tif" if export.format == "tiff" else ".fits"
    for li in range(noisy.shape[0]):
        for r in range(min(export.repeats, noisy.shape[1])):
            for k, (_, pt) in enumerate(todo):
                name = folder / f"level{li}" / f"h{pt.pose.height_mm:+g}_rot{pt.pose.rotation_deg:g}_rep{r}{suffix}"
                name.parent.mkdir(parents=True, exist_ok=True)
                meta = {"fluxmap:height_mm": pt.pose.height_mm, "fluxmap:rotation_deg": pt.pose.rotation_deg,
                        "fluxmap:level_peak_photons": float(lv[li]), "fluxmap:repeat": r}
                if exposure_s is not None:
                    meta["fluxmap:exposure_s"] = float(exposure_s)
                if counts is not None:
                    write_image(name, counts[li, r, k], metadata=meta | {"fluxmap:units": "counts"})
                else:
                    write_image(name, noisy[li, r, k].astype(np.float32), metadata=meta | {"fluxmap:units": "photons"})


def _simulate_montecarlo(sp: SimulatePlan, shape, ctx: RunContext) -> Path:
    """``simulate.flux.kind: montecarlo``: one photon run through the phantom ``shape``; the truth
    is the photons that left through each element, the images those photons through lens and
    mirrors (no forward T, no emission model)."""
    from ..montecarlo.photons import ANGLE_EDGES_DEG

    sim, fwd = sp.settings, sp.forward
    placer, views, scenes = fwd.placer, fwd.views, [s for s, _ in fwd.poses]
    poses = [s.pose for s in scenes]
    surface = placer.surface
    mc = montecarlo_truth(sim.flux, shape, sp.truth.refinement, sp.ray_offset_mm, placer, scenes, views, say=ctx.say)
    power = np.bincount(mc.parent, weights=mc.fine_power, minlength=surface.n_elements)
    if power.max() <= 0:
        raise UserError("simulate.flux: no photon left through an element (too few photons or too much absorption).")
    t = mc.tally
    ctx.say(f"simulate: {t.launched:.4g} photons launched, {t.escaped:.4g} escaped ({t.escaped / t.launched:.1%}), "
            f"{t.absorbed:.4g} absorbed, {t.lost} lost; {power.sum():.4g} through the {surface.n_elements} elements "
            f"({mc.seconds:.1f} s, {mc.notes['photons_per_s']:.3g} photons/s)")
    if (lost := lost_photons_warning(t.lost, t.launched, sim.flux)) is not None:
        ctx.warn(lost)
    P = mc.images.shape[0]
    clean = mc.images.astype(np.float32)[None]
    prov = replace(fwd.provenance, geometry=without_emission(fwd.provenance.geometry))  # the photons assume none
    record = AS.MonteCarloRecord(
        power, mc.angle_histogram, ANGLE_EDGES_DEG, mc.reached_lens, mc.on_sensor, [v.name for v in views],
        int(t.launched), int(t.escaped), int(t.absorbed), int(t.lost), mc.not_on_elements, placer.rest_shift_mm,
        mc.photons)
    AS.write(sp.out, AS.Simulation(
        surface=surface, power=power, exitance=power / surface.element_areas_mm2,
        levels_peak_photons=[power.max()], level_scale=[1.0], power_fine=mc.fine_power, fine_parent=mc.parent,
        heights_mm=[p.height_mm for p in poses], rotations_deg=[p.rotation_deg for p in poses],
        T_fwd_keys=["montecarlo"] * P, noiseless=clean, noisy=clean[:, None], counts=None,
        max_snr=np.sqrt(clean.reshape(1, P, -1).max(axis=2)), truth_kind=sim.flux.kind,
        truth_notes=_recorded(mc.notes, "seconds"),
        noise_model="photons (Monte Carlo: whole photons; noisy and noiseless hold the same image)",
        seed=sim.flux.seed, exposure_s=sim.noise.exposure_s, inputs_digest=sp.digest,
        truth_seconds=A.recorded_seconds(mc.seconds), montecarlo=record),
        config_sha256=fwd.config_sha256, inputs={}, provenance=prov)
    rows = [[p.height_mm, p.rotation_deg, int(mc.images[k].sum()), *[int(x) for x in mc.reached_lens[k]]]
            for k, p in enumerate(poses)]
    ctx.table(["height_mm", "rotation_deg", "photons in image", *[f"reached lens: {v.name}" for v in views]], rows)
    for k, p in enumerate(poses):
        for w in few_photons_warning(float(mc.images[k].sum()), t.launched, f"pose h={p.height_mm:+g}mm "
                                                                             f"rot={p.rotation_deg:g}deg"):
            ctx.warn(w)
    return sp.out
