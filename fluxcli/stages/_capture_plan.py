"""What one ``fluxmap capture-surface`` run does, resolved once from the config.

:func:`plan_of` is the only function below the command that reads the loaded config (it checks
``capture:`` and ``rig:`` before any file is touched); the stage's helpers, the simulated scene
(:mod:`._capture_scene`) and the surface step (:mod:`._capture_surface`) take parts of the
:class:`CapturePlan` it returns.  The acquisition's own plan (:class:`fluxcli.acquisition.Plan`,
stored in capture.h5 and compared on ``--resume``) is made from it once the camera is open.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from .. import artefacts as A
from .. import config as C
from ..artefacts.capture import FILE_NAME as CAPTURE_FILE
from ..errors import UserError

if TYPE_CHECKING:
    from ..acquisition import SurfacePlan

# Test hook: sleep this long between the steps of creating capture.h5, so that the kill
# test can land SIGKILLs inside the creation window.  0 (unset) in normal use.
CREATE_PAUSE_ENV = "FLUXMAP_CAPTURE_CREATE_PAUSE_S"
RENDERER = "truth per face of the refined surface"  # in the scene's digest: frames rendered otherwise do not resume
SURFACE_FILE = "surface.h5"  # in the workdir: what capture.surface makes


@dataclass(frozen=True)
class SceneParts:
    """What the simulated camera looks at (the truth's config: ``rig.camera.true_surface`` when given)."""

    system: C.System  # cameras, mirrors, stage of the rig
    simulate: C.Simulate  # the truth (simulate.flux) and its exposure (simulate.noise.exposure_s)
    forward_transfer: C.Transfer  # the forward T's sampling (finer than reconstruction's)
    camera_settings: C.RigCamera  # rig.camera: filters, albedos, binning
    projectors: dict  # rig.projectors: name -> C.RigProjector
    rotation_deg: float  # the subject's rotation (subject.poses' first), deg
    placer: object  # fluxcli.scene.SubjectPlacer of the true surface
    truth: dict  # filter name (None: no rig.camera.filters entry) -> fluxcli.truth.TruthPlan of what it passes
    views: list  # fluxcli.scene views of the system (direct and mirrors)
    cache_dir: Path  # the T cache
    config_sha256: str  # recorded in the T files
    provenance: A.Provenance  # the T files' provenance (the truth's geometry)
    digest: str  # of everything the frames depend on: frames rendered otherwise do not resume


@dataclass(frozen=True)
class CapturePlan:
    """One capture-surface run: paths, the checked capture and rig sections, the simulated scene."""

    config_path: Path  # the config file (named in messages)
    config_sha256: str  # its sha256 (recorded in the artefacts)
    output: Path  # <workdir>/capture.h5
    surface_output: Path  # <workdir>/surface.h5 (capture.surface)
    capture: C.Capture  # heights_mm, filters, exposures, em_gain, repeats, darks; .surface, .calibration
    rig: C.Rig  # the devices: stage, filter wheel, camera, projectors
    camera_settings: C.RigCamera  # rig.camera (backend, binning, filters, ...)
    system: C.System | None  # system.camera (pixels, sensor: counts -> photons), mirrors, stage
    projectors: tuple  # names of the projectors capture.surface uses (empty: no surface)
    scene: SceneParts | None  # the simulated camera's subject (None: real camera, or no subject frames)
    provenance: A.Provenance  # what capture.h5 records (the rendered geometry when simulated)
    surface_provenance: A.Provenance | None  # what surface.h5 records (capture.surface)
    create_pause_s: float  # test hook: sleep between the steps of creating capture.h5 (0: none), s


def plan_of(cfg: C.LoadedConfig) -> CapturePlan:
    """Check ``capture:`` and ``rig:`` (UserError naming the key) and resolve the run."""
    from .plans import provenance

    cap, rig = _check(cfg.model.capture, cfg.model.rig, cfg.path)
    cc = rig.camera or C.RigCamera()
    if cap.calibration is not None and cc.backend == "simulated":
        C.require(cfg, "capture.calibration with the simulated camera (it renders with the true camera)",
                  ("system", "system.camera.lens", "system.camera.pose"))
    # a calibration-only capture has no subject to render
    scene = scene_parts(cfg) if cc.backend == "simulated" and cap.heights_mm else None
    sf = cap.surface
    names = (tuple(sf.projectors) if sf.projectors is not None else tuple(rig.projectors)) if sf else ()
    prov = (provenance(cfg) if scene is not None  # the geometry the simulated camera rendered
            else A.Provenance(config=cfg.model.model_dump(mode="json", by_alias=True)))
    return CapturePlan(cfg.path, cfg.sha256, cfg.workdir / CAPTURE_FILE, cfg.workdir / SURFACE_FILE, cap, rig, cc,
                       cfg.model.system, names, scene, prov, provenance(cfg) if sf is not None else None,
                       float(os.environ.get(CREATE_PAUSE_ENV, "0") or 0))


def scene_parts(cfg: C.LoadedConfig) -> SceneParts:
    """What the simulated camera renders: the true subject, its truth per filter, the forward T."""
    from ..scene import views_from_config
    from ..truth import forward_transfer
    from .plans import cache_dir, geometry_of, placer_of, provenance, truth_plan

    C.require(cfg, "capture-surface with rig.camera.backend: simulated",
              ("system", "system.camera.lens", "system.camera.pose", "subject", "simulate"))
    cc = cfg.model.rig.camera or C.RigCamera()
    cfg = truth_config(cfg)
    if isinstance(cfg.model.subject.surface, C.ArtefactSurface):
        raise UserError("rig.camera.true_surface: subject.surface is a captured surface artefact; the simulated "
                        "camera needs the true surface to render (a phantom or a mesh file).")
    m = cfg.model
    truth = {name: truth_plan(cfg, _flux_for(m.simulate.flux, name, spec))  # bad wavelengths refused here
             for name, spec in cc.filters.items()}
    truth[None] = truth_plan(cfg, m.simulate.flux)
    digest = A.inputs_digest(system=m.system.model_dump(mode="json"), subject=geometry_of(cfg)["subject"],
                             simulate=m.simulate.model_dump(mode="json"), renderer=RENDERER,
                             camera=cc.model_dump(mode="json"),
                             projectors={k: v.model_dump(mode="json") for k, v in m.rig.projectors.items()})
    return SceneParts(m.system, m.simulate, forward_transfer(m.simulate, m.transfer), cc, dict(m.rig.projectors),
                      float((m.subject.poses or C.Poses()).rotations_deg[0]), placer_of(cfg), truth,
                      views_from_config(m.system), cache_dir(cfg), cfg.sha256, provenance(cfg), digest)


def _flux_for(flux, name: str, spec):
    """``simulate.flux`` as filter ``name`` sees it (its wavelength's optical properties)."""
    if spec is None or spec.wavelength_nm is None:
        return flux
    if not isinstance(flux, C.DiffusionFlux):
        raise UserError(f"rig.camera.filters.{name}.wavelength_nm: only a diffusion truth (simulate.flux.kind: "
                        f"diffusion) depends on the wavelength; this one is {flux.kind!r} (use transmission).")
    if spec.wavelength_nm not in flux.optical:
        raise UserError(f"rig.camera.filters.{name}.wavelength_nm: {spec.wavelength_nm} nm has no entry in "
                        f"simulate.flux.optical ({sorted(flux.optical)}).")
    return flux.model_copy(update={"wavelength_nm": spec.wavelength_nm})


def truth_config(cfg: C.LoadedConfig) -> C.LoadedConfig:
    """The config whose ``subject.surface`` is what the simulated camera looks at:
    ``rig.camera.true_surface`` when given (the truth differs from ``subject.surface``, e.g.
    a captured one), else ``cfg`` itself. data-samples/make_tetmeshes.py meshes that surface."""
    rig = cfg.model.rig
    cc = (rig.camera if rig is not None else None) or C.RigCamera()
    if cc.true_surface is None:
        return cfg
    m = cfg.model
    return C.LoadedConfig(m.model_copy(update={"subject": m.subject.model_copy(update={"surface": cc.true_surface})}),
                          cfg.path, cfg.raw)


def _check(cap: C.Capture | None, rig: C.Rig | None, config_path: Path) -> tuple[C.Capture, C.Rig]:
    """``capture:`` against ``rig:`` (the devices it drives, their ranges), UserError naming the key."""
    if cap is None:
        raise UserError(f"config {config_path}: 'capture' is missing: the plan (heights_mm, filters, exposure_s, "
                        "em_gain, repeats, darks).")
    if rig is None or rig.stage is None or rig.filter_wheel is None:
        missing = "rig" if rig is None else "rig.stage" if rig.stage is None else "rig.filter_wheel"
        raise UserError(f"config {config_path}: '{missing}' is missing; capture-surface drives the stage, the filter "
                        "wheel and the camera.")
    unknown = [f for f in cap.filters if f not in rig.filter_wheel.filters] if cap.heights_mm else []
    if unknown:
        raise UserError(f"capture.filters: {unknown} not in rig.filter_wheel.filters "
                        f"({sorted(rig.filter_wheel.filters)}).")
    lo, hi = rig.stage.travel_mm
    out = [h for h in cap.heights_mm if not lo <= h <= hi]
    if out:
        raise UserError(f"capture.heights_mm: {out} mm outside the stage's travel rig.stage.travel_mm [{lo}, {hi}].")
    if cap.surface is not None:
        _check_surface(cap.surface, rig)
    if cap.calibration is not None:
        _check_calibration(cap.calibration, rig)
    return cap, rig


def _check_calibration(cal: C.CaptureCalibration, rig: C.Rig) -> None:
    wheel = rig.filter_wheel.filters
    for key, name in (("filter", cal.filter if (cal.flats or cal.ptc) else None),
                      ("grid.filter", cal.grid.filter if cal.grid else None)):
        if name is not None and name not in wheel:
            raise UserError(f"capture.calibration.{key}: {name!r} not in rig.filter_wheel.filters ({sorted(wheel)}).")
    lo, hi = rig.stage.travel_mm
    out = [h for h in cal.grid.heights_mm if not lo <= h <= hi] if cal.grid else []
    if out:
        raise UserError(f"capture.calibration.grid.heights_mm: {out} mm outside the stage's travel "
                        f"rig.stage.travel_mm [{lo}, {hi}].")
    cc = rig.camera or C.RigCamera()
    gains = [("grid.em_gain", cal.grid.em_gain if cal.grid else None),
             ("darks.em_gain", cal.darks.em_gain if cal.darks else None),
             ("ptc.em_gain", cal.ptc.em_gain if cal.ptc and cal.ptc.exposures_on_s else None)]
    g_lo, g_hi = cc.em_gain_range
    for key, g in gains:
        if g is not None and not g_lo <= g <= g_hi:
            raise UserError(f"capture.calibration.{key}: EM gain {g:g} is outside rig.camera.em_gain_range "
                            f"[{g_lo:g}, {g_hi:g}].")
    if (cal.bias or cal.flats or cal.ptc) and g_lo > 1:
        raise UserError(f"capture.calibration: bias, flat and gain-off PTC frames are taken at EM gain 1, below "
                        f"rig.camera.em_gain_range [{g_lo:g}, {g_hi:g}]; set the range's low end to 1 if the camera "
                        "allows it.")


def _check_surface(sf: C.CaptureSurface, rig: C.Rig) -> None:
    names = list(sf.projectors) if sf.projectors is not None else list(rig.projectors)
    if not names:
        raise UserError("capture.surface: no projector; list them in rig.projectors (and optionally "
                        "capture.surface.projectors).")
    unknown = [p for p in names if p not in rig.projectors]
    if unknown:
        raise UserError(f"capture.surface.projectors: {unknown} not in rig.projectors ({sorted(rig.projectors)}).")
    if sf.filter not in rig.filter_wheel.filters:
        raise UserError(f"capture.surface.filter: {sf.filter!r} not in rig.filter_wheel.filters "
                        f"({sorted(rig.filter_wheel.filters)}).")
    lo, hi = rig.stage.travel_mm
    if not lo <= sf.height_mm <= hi:
        raise UserError(f"capture.surface.height_mm: {sf.height_mm} mm outside rig.stage.travel_mm [{lo}, {hi}].")
    cc = rig.camera or C.RigCamera()
    if sf.binning is not None and cc.binning % sf.binning:
        raise UserError(f"capture.surface.binning: {sf.binning} must divide rig.camera.binning ({cc.binning}): "
                        "system.camera describes the frames at rig.camera.binning, pattern frames are as fine or finer.")
    want = "simulated" if cc.backend == "simulated" else "window"
    wrong = [p for p in names if rig.projectors[p].display != want]
    if wrong:
        raise UserError(f"rig.projectors.{wrong[0]}.display: the {cc.backend} camera needs '{want}' displays "
                        "(the simulated camera sees only simulated projectors; a real camera sees a real one).")
    gray = {p: patterns(sf, rig.projectors[p]).n_gray for p in names}
    if len(set(gray.values())) > 1:
        raise UserError(f"rig.projectors: the panels' widths give Gray codes of different lengths {gray}; "
                        "capture.surface needs projectors of the same width.")


def patterns(sf: C.CaptureSurface, spec: C.RigProjector):
    from ..structured.patterns import column_patterns

    return column_patterns(spec.pixels[0], spec.pixels[1], period_px=sf.patterns.period_px,
                           n_steps=sf.patterns.n_steps)


def surface_plan(sf: C.CaptureSurface, rig: C.Rig, camera) -> "SurfacePlan":
    from ..acquisition import SurfacePlan

    names = tuple(sf.projectors) if sf.projectors is not None else tuple(rig.projectors)
    cc = rig.camera or C.RigCamera()
    binning = sf.binning or cc.binning
    native = camera.binning
    camera.binning = binning  # the camera says the frame shape at that binning
    shape = tuple(camera.shape)
    camera.binning = native
    ps = patterns(sf, rig.projectors[names[0]])
    content = A.inputs_digest(patterns=sf.patterns.model_dump(mode="json"),
                              projectors={p: rig.projectors[p].model_dump(mode="json") for p in names})
    return SurfacePlan(projectors=names, patterns=tuple(ps.labels), height_mm=float(sf.height_mm), filter=sf.filter,
                       exposure_s=float(sf.exposure_s), em_gain=float(sf.em_gain), binning=int(binning),
                       shape=(int(shape[0]), int(shape[1])), n_gray=ps.n_gray, n_steps=ps.n_steps, content=content)


def calibration_plan(cal: C.CaptureCalibration, system: C.System | None, backend: str):
    """The calibration series in the order they are taken: shutter closed (bias, darks), the
    grid at each height, then the even light (flats, gain-off and gain-on PTC pairs)."""
    from ..acquisition import CalibrationPlan

    nan = None  # the stage stays where it is (None, not NaN: the plan is compared as JSON on --resume)
    series = []
    if cal.bias:
        series.append(("bias", 0, cal.bias.exposure_s, 1.0, nan, "", cal.bias.frames))
    if cal.darks:
        series += [("dark", k, float(e), cal.darks.em_gain, nan, "", cal.darks.frames)
                   for k, e in enumerate(cal.darks.exposures_s)]
    grid = ()
    if cal.grid:
        g = cal.grid
        series += [("grid", k, g.exposure_s, g.em_gain, float(h), g.filter, g.repeats) for k, h in enumerate(g.heights_mm)]
        stage = system.stage if system is not None else None
        grid = (("kind", g.kind), ("pitch_mm", g.pitch_mm), ("shape", list(g.shape)), ("thickness_mm", g.thickness_mm),
                ("stage_top_z_mm", stage.top_z_mm if stage is not None else 0.0))
    if cal.flats:
        series.append(("flat", 0, cal.flats.exposure_s, 1.0, nan, cal.filter, cal.flats.frames))
    if cal.ptc:
        p = cal.ptc
        series += [("ptc_off", k, float(e), 1.0, nan, cal.filter, 2 * p.pairs) for k, e in enumerate(p.exposures_off_s)]
        series += [("ptc_on", k, float(e), p.em_gain, nan, cal.filter, 2 * p.pairs)
                   for k, e in enumerate(p.exposures_on_s)]
    content = ""
    if backend == "simulated":
        content = A.inputs_digest(simulated=cal.simulated.model_dump(mode="json"),
                                  camera=system.camera.model_dump(mode="json"),
                                  dot_diameter_mm=cal.grid.dot_diameter_mm if cal.grid else None,
                                  renderer="calibration.synthetic.render_plane, direct view")
    return CalibrationPlan(series=tuple(series), grid=grid, content=content)


def calibration_targets(system: C.System, cal: C.CaptureCalibration):
    """The simulated calibration set-up (grid on the stage, even light) for the rig's true camera."""
    from ..hardware.sim.targets import CalibrationTargets
    from ..scene import camera_from_config

    g = cal.grid
    top = system.stage.top_z_mm if system.stage is not None else 0.0
    sim = cal.simulated
    return CalibrationTargets(camera_from_config(system.camera), kind=g.kind if g else "dots",
                              pitch_mm=g.pitch_mm if g else 1.0, shape=tuple(g.shape) if g else (2, 2),
                              plane_offset_mm=top + (g.thickness_mm if g else 0.0),
                              dot_diameter_mm=(g.dot_diameter_mm or g.pitch_mm / 2) if g else 0.5,
                              grid_photons_per_s=sim.grid_photons_per_s, background_fraction=sim.background_fraction,
                              light_photons_per_s=sim.light_photons_per_s, sub=sim.sub, lens_samples=sim.lens_samples)


def calibration_truth(camera: C.Camera) -> dict:
    cam = camera
    return {"about": "the simulated rig's true camera (system.camera of the capture's config)",
            "camera": cam.model_dump(mode="json")}
