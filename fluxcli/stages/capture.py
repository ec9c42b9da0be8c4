"""``fluxmap capture-surface CONFIG [--resume]``: acquire ``capture:``: the subject's surface
by structured light (``capture.surface``) and its emission images.

Examples
--------
$ fluxmap capture-surface configs/demo-rig.yaml            # simulated rig, in-process
$ fluxmap capture-surface configs/demo-rig.yaml --resume   # continue after a crash or Ctrl-C
$ fluxmap capture-surface lab.yaml --force                 # start the capture over

Devices come from ``rig:``: a port ``pty`` or ``socket://127.0.0.1:0`` starts that device's
simulator in this process, any other port is opened as the real device (or a ``fluxmap
rig serve`` elsewhere).  ``rig.camera.backend: simulated`` renders the subject's emission
through the forward model (``simulate.flux``, T at the stage's physical height, the filter
in the beam) with EMCCD noise; ``dcam``, ``andor_sdk2``, ``andor_sdk3`` and ``pvcam`` drive a
real camera (:mod:`fluxcli.hardware.cameras`).  Frames go to
``<workdir>/capture.h5`` as they arrive (see :mod:`fluxcli.acquisition`).  Ctrl-C stops at
a frame boundary with the shutter closed and the stage stopped (exit 130); a device fault
exits 2 naming the device.

Structured light (``capture.surface``): first, each projector of ``rig.projectors`` shows
the Gray-code + phase-shift sequence (the others black) while the camera takes one frame
per pattern into ``capture.h5`` (``/patterns``, same crash safety and ``--resume``).  The
simulated camera renders the shown pattern on the true surface
(:class:`fluxcli.structured.render.PatternRenderer`: camera blur, mirror views, shadows)
with EMCCD noise; a ``window`` display shows it full screen on the projector in the lab.
Once every frame is in, the frames are decoded, triangulated (all views and projectors),
meshed and written to ``<workdir>/surface.h5`` (at rest: as at stage height 0), which
``subject.surface: {artefact: ...}`` reads.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
from pathlib import Path

import numpy as np

from .. import artefacts as A
from .. import config as C
from ..acquisition import CaptureFile, Interrupted, Plan, RigDevices, acquire
from ..errors import UserError
from ._radiometric import assumed_qe_warning
from .context import RunContext

# Test hook: sleep this long between the steps of creating capture.h5, so that the kill
# test can land SIGKILLs inside the creation window.  0 (unset) in normal use.
CREATE_PAUSE_ENV = "FLUXMAP_CAPTURE_CREATE_PAUSE_S"


# ------------------------------------------------------------------ the simulated scene

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

class SimulatedScene:
    """What the simulated camera sees: ``render(height_mm, filter) -> photons/s per pixel``.

    The truth is ``simulate.flux`` per filter: a filter's ``rig.camera.filters`` entry
    picks the wavelength whose ``simulate.flux.optical`` properties apply (diffusion
    truths) and a transmission; photons per exposure of ``simulate`` become photons/s by
    dividing by ``simulate.noise.exposure_s``.  T is the forward T (``simulate.transfer``,
    finer than reconstruction's) of the subject at the given stage height, from the T cache."""

    def __init__(self, cfg: C.LoadedConfig):
        # what the simulated camera looks at: the geometry, and what the subject emits
        C.require(cfg, "capture-surface with rig.camera.backend: simulated",
                  ("system", "system.camera.lens", "system.camera.pose", "subject", "simulate"))
        cc = cfg.model.rig.camera or C.RigCamera()
        cfg = truth_config(cfg)
        if isinstance(cfg.model.subject.surface, C.ArtefactSurface):
            raise UserError("rig.camera.true_surface: subject.surface is a captured surface artefact; the simulated "
                            "camera needs the true surface to render (a phantom or a mesh file).")
        self.cfg = cfg
        self.camera_settings = cc
        self.light = dict(cc.filters)
        self._placer = None
        self._rates: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        self._images: dict[tuple[float, str], np.ndarray] = {}
        self._pattern_renderers: dict[tuple[float, int, str], tuple] = {}
        for name, spec in self.light.items():
            self._flux_for(name, spec)  # refuse bad wavelengths before any device moves

    RENDERER = "truth per face of the refined surface"  # in the digest: frames rendered otherwise do not resume

    @property
    def digest(self) -> str:
        from ..pipeline import geometry_of

        m = self.cfg.model
        return A.inputs_digest(system=m.system.model_dump(mode="json"), subject=geometry_of(self.cfg)["subject"],
                               simulate=m.simulate.model_dump(mode="json"), renderer=self.RENDERER,
                               camera=self.camera_settings.model_dump(mode="json"),
                               projectors={k: v.model_dump(mode="json") for k, v in m.rig.projectors.items()})

    def _flux_for(self, name: str, spec):
        flux = self.cfg.model.simulate.flux
        if spec is None or spec.wavelength_nm is None:
            return flux
        if not isinstance(flux, C.DiffusionFlux):
            raise UserError(f"rig.camera.filters.{name}.wavelength_nm: only a diffusion truth (simulate.flux.kind: "
                            f"diffusion) depends on the wavelength; this one is {flux.kind!r} (use transmission).")
        if spec.wavelength_nm not in flux.optical:
            raise UserError(f"rig.camera.filters.{name}.wavelength_nm: {spec.wavelength_nm} nm has no entry in "
                            f"simulate.flux.optical ({sorted(flux.optical)}).")
        return flux.model_copy(update={"wavelength_nm": spec.wavelength_nm})

    @property
    def placer(self):
        if self._placer is None:
            from ..scene import SubjectPlacer

            self._placer = SubjectPlacer(self.cfg)
        return self._placer

    def fine_rate(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """Photons/s leaving each face of the refined surface (``simulate.truth_refinement``;
        subject at rest) as seen through filter ``name``, and the element of each fine face.
        The camera renders this, not a constant per element: a truth constant over the very
        elements that are reconstructed is half an inverse crime, and in focus it images as
        facets no smooth exitance explains (χ²/pixel 2.5 on the demo rig's true mesh)."""
        if name not in self._rates:
            from ..truth import truth_fine
            from .plans import truth_plan

            spec = self.light.get(name)
            m = self.cfg.model
            truth = truth_plan(self.cfg, self._flux_for(name, spec))
            fine, parent, _ = truth_fine(truth, self.placer.surface)  # a negligible FEM undershoot is clipped there
            transmission = 1.0 if spec is None else spec.transmission
            self._rates[name] = (fine * transmission / m.simulate.noise.exposure_s, parent)
        return self._rates[name]

    def power_rate(self, name: str) -> np.ndarray:
        """Photons/s leaving each element (subject at rest) as seen through filter ``name``."""
        fine, parent = self.fine_rate(name)
        return np.bincount(parent, weights=fine, minlength=self.placer.surface.n_elements)

    def render(self, height_mm: float, name: str, *, projectors: dict | None = None, binning: int | None = None
               ) -> np.ndarray:
        """Photons/s per pixel: what the projectors shine (when any shows a pattern), else
        the subject's emission through filter ``name`` (at the camera's native binning).  The
        emission is left out of pattern frames (any binning finer than the native one): it is
        orders of magnitude fainter than the projected light."""
        native = self.camera_settings.binning
        binning = native if binning is None else int(binning)
        if projectors:
            return sum(self.pattern_photons_per_s(height_mm, binning, p, img) for p, img in projectors.items())
        if binning != native:  # a pattern frame with every projector black (the emission is left out there too)
            k = native // binning
            nx, ny = self.cfg.model.system.camera.pixels
            return np.zeros((ny * k, nx * k))
        return self.emission(height_mm, name)

    def pattern_renderer(self, height_mm: float, binning: int, projector: str):
        """The traced scene (subject and stage at ``height_mm``, camera at ``binning``) for one
        projector, and the photons/s per pixel per unit of rendered radiance (étendue x intensity)."""
        key = (round(float(height_mm), 4), int(binning), projector)
        if key not in self._pattern_renderers:
            from ..hardware.projector import projector_model
            from ..scene import Pose, plane_mirrors
            from ..structured.render import PatternRenderer, pixel_etendue_mm2_sr

            m = self.cfg.model
            camera = camera_at_binning(m.system.camera, self.camera_settings.binning // int(binning))
            lit = [(self.true_surface_at(key[0]), self.camera_settings.subject_albedo)]
            if m.system.stage is not None:  # the stage top (the first occluder) is lit too
                lit.append((self.placer.occluders(Pose(key[0], 0.0), m.system)[0], self.camera_settings.stage_albedo))
            mirrors = [(pm, mm.reflectance) for pm, mm in zip(plane_mirrors(m.system), m.system.mirrors)]
            spec = m.rig.projectors[projector]
            renderer = PatternRenderer(camera, mirrors, lit, [], projector_model(spec))
            scale = pixel_etendue_mm2_sr(camera) * spec.intensity_photons_per_s_per_sr
            self._pattern_renderers[key] = (renderer, scale)
        return self._pattern_renderers[key]

    def pattern_photons_per_s(self, height_mm: float, binning: int, projector: str, pattern: np.ndarray) -> np.ndarray:
        renderer, scale = self.pattern_renderer(height_mm, binning, projector)
        return renderer.render(pattern) * scale

    def true_surface_at(self, height_mm: float):
        """The true subject placed with the stage at ``height_mm``."""
        from ..scene import Pose

        rot = (self.cfg.model.subject.poses or C.Poses()).rotations_deg[0]
        return self.placer.place(Pose(float(height_mm), float(rot)))

    def emission(self, height_mm: float, name: str) -> np.ndarray:
        # 0.1 um is far below any depth of field: the stage's microstep rounding (~7 nm)
        # then reuses the T of the planned height instead of building another
        key = (round(float(height_mm), 4), name)
        if key not in self._images:
            from ..pipeline import ensure_pose_T
            from ..scene import Pose
            from ..truth import forward_transfer, truth_refinement  # the forward T and truth, as simulate uses

            rot = (self.cfg.model.subject.poses or C.Poses()).rotations_deg[0]
            refine = truth_refinement(self.cfg.model.simulate)
            T, T_tangent = ensure_pose_T(self.cfg, Pose(key[0], float(rot)),
                                         forward_transfer(self.cfg.model.simulate, self.cfg.model.transfer), self.placer,
                                         refine=refine, tangent=True)
            nx, ny = self.cfg.model.system.camera.pixels
            rate = self.fine_rate(name)[0]
            image = T @ rate
            if T_tangent is not None and refine > 0:  # the emission's tangential flux, as simulate renders it
                from ..optics.emission import tangent_light

                image = np.maximum(image + T_tangent @ tangent_light(self.placer.surface.refined(refine)[0], rate), 0.0)
            self._images[key] = image.reshape(ny, nx)
        return self._images[key]


def camera_at_binning(camera: C.Camera, k: int):
    """The thin-lens camera of ``system.camera`` with its pixels split ``k x k`` (a binning k
    times finer than the one system.camera describes)."""
    from ..scene import camera_from_config

    return camera_from_config(camera.model_copy(update={"pixels": (camera.pixels[0] * k, camera.pixels[1] * k),
                                                        "pixel_pitch_mm": camera.pixel_pitch_mm / k}))


# ------------------------------------------------------------------ devices
def _check(cfg: C.LoadedConfig) -> tuple[C.Capture, C.Rig]:
    cap, rig = cfg.model.capture, cfg.model.rig
    if cap is None:
        raise UserError(f"config {cfg.path}: 'capture' is missing: the plan (heights_mm, filters, exposure_s, "
                        "em_gain, repeats, darks).")
    if rig is None or rig.stage is None or rig.filter_wheel is None:
        missing = "rig" if rig is None else "rig.stage" if rig.stage is None else "rig.filter_wheel"
        raise UserError(f"config {cfg.path}: '{missing}' is missing; capture-surface drives the stage, the filter "
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
        _check_calibration(cfg, cap.calibration, rig)
    return cap, rig


def _check_calibration(cfg: C.LoadedConfig, cal: C.CaptureCalibration, rig: C.Rig) -> None:
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
    if cc.backend == "simulated":
        C.require(cfg, "capture.calibration with the simulated camera (it renders with the true camera)",
                  ("system", "system.camera.lens", "system.camera.pose"))


def _calibration_plan(cfg: C.LoadedConfig, cal: C.CaptureCalibration, backend: str):
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
        stage = cfg.model.system.stage if cfg.model.system is not None else None
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
        m = cfg.model
        content = A.inputs_digest(simulated=cal.simulated.model_dump(mode="json"),
                                  camera=m.system.camera.model_dump(mode="json"),
                                  dot_diameter_mm=cal.grid.dot_diameter_mm if cal.grid else None,
                                  renderer="calibration.synthetic.render_plane, direct view")
    return CalibrationPlan(series=tuple(series), grid=grid, content=content)


def _calibration_targets(cfg: C.LoadedConfig, cal: C.CaptureCalibration):
    """The simulated calibration set-up (grid on the stage, even light) for the rig's true camera."""
    from ..hardware.sim.targets import CalibrationTargets
    from ..scene import camera_from_config

    m = cfg.model
    g = cal.grid
    top = m.system.stage.top_z_mm if m.system.stage is not None else 0.0
    sim = cal.simulated
    return CalibrationTargets(camera_from_config(m.system.camera), kind=g.kind if g else "dots",
                              pitch_mm=g.pitch_mm if g else 1.0, shape=tuple(g.shape) if g else (2, 2),
                              plane_offset_mm=top + (g.thickness_mm if g else 0.0),
                              dot_diameter_mm=(g.dot_diameter_mm or g.pitch_mm / 2) if g else 0.5,
                              grid_photons_per_s=sim.grid_photons_per_s, background_fraction=sim.background_fraction,
                              light_photons_per_s=sim.light_photons_per_s, sub=sim.sub, lens_samples=sim.lens_samples)


_SET_UP = {"grid": "lay the calibration grid flat on the stage, centred under the camera, and light it evenly",
           "light": "put the even light in front of the camera (flat field and photon transfer); nothing on the stage",
           "closed": "the shutter closes for bias and dark frames",
           "subject": "calibration frames done: remove the calibration set-up and place the subject"}


def _operator_prepare(ctx: RunContext, confirm: bool):
    """A real rig: tell the operator what to set up (and wait for Enter when ``confirm``)."""
    def prepare(target: str) -> None:
        ctx.say(f"capture-surface: calibration: {_SET_UP[target]}")
        if confirm and target != "closed":
            input("  press Enter when ready ... ")
    return prepare


def _calibration_truth(cfg: C.LoadedConfig) -> dict:
    cam = cfg.model.system.camera
    return {"about": "the simulated rig's true camera (system.camera of the capture's config)",
            "camera": cam.model_dump(mode="json")}


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
    gray = {p: _patterns(sf, rig.projectors[p]).n_gray for p in names}
    if len(set(gray.values())) > 1:
        raise UserError(f"rig.projectors: the panels' widths give Gray codes of different lengths {gray}; "
                        "capture.surface needs projectors of the same width.")


def _patterns(sf: C.CaptureSurface, spec: C.RigProjector):
    from ..structured.patterns import column_patterns

    return column_patterns(spec.pixels[0], spec.pixels[1], period_px=sf.patterns.period_px,
                           n_steps=sf.patterns.n_steps)


def _surface_plan(cfg: C.LoadedConfig, sf: C.CaptureSurface, rig: C.Rig, camera) -> "SurfacePlan":
    from ..acquisition import SurfacePlan

    names = tuple(sf.projectors) if sf.projectors is not None else tuple(rig.projectors)
    cc = rig.camera or C.RigCamera()
    binning = sf.binning or cc.binning
    native = camera.binning
    camera.binning = binning  # the camera says the frame shape at that binning
    shape = tuple(camera.shape)
    camera.binning = native
    ps = _patterns(sf, rig.projectors[names[0]])
    content = A.inputs_digest(patterns=sf.patterns.model_dump(mode="json"),
                              projectors={p: rig.projectors[p].model_dump(mode="json") for p in names})
    return SurfacePlan(projectors=names, patterns=tuple(ps.labels), height_mm=float(sf.height_mm), filter=sf.filter,
                       exposure_s=float(sf.exposure_s), em_gain=float(sf.em_gain), binning=int(binning),
                       shape=(int(shape[0]), int(shape[1])), n_gray=ps.n_gray, n_steps=ps.n_steps, content=content)


def _camera(cfg: C.LoadedConfig, cap: C.Capture, rig: C.Rig, sims: dict, wheel, stage, scene,
            displays: dict | None = None, targets=None):
    from ..pipeline import emccd_model

    cc = rig.camera or C.RigCamera()
    if cc.backend != "simulated":
        from ..hardware.cameras import open_real_camera

        return open_real_camera(cc)
    from ..hardware.camera import SimulatedEmccd

    positions = {p: n for n, p in rig.filter_wheel.filters.items()}
    # the physical state: the simulator's when it runs here, else the driver's read-back
    height = (lambda: sims["stage"].position_mm) if "stage" in sims else stage.position_mm
    pos = (lambda: sims["filter_wheel"].position) if "filter_wheel" in sims else (lambda: wheel.position)
    def shown():  # what the simulated projectors show right now (black ones left out)
        return {n: d.current for n, d in (displays or {}).items() if d.current.any()}

    def render(height_mm, filter_name, **kw):  # a calibration set-up in front of the camera, else the subject
        if targets is not None and (targets.current is not None or scene is None):
            return targets.render(height_mm)
        return scene.render(height_mm, filter_name, **kw)

    return SimulatedEmccd(render, stage_height_mm=height, filter_name=lambda: positions.get(pos(), f"position {pos()}"),
                          projectors=shown,
                          sensor=emccd_model(cfg.model.system.camera.sensor, cap.exposures_s[0]), seed=cap.seed,
                          native_binning=cc.binning, setpoint_c=cc.setpoint_c, ambient_c=cc.ambient_c,
                          dark_doubling_c=cc.dark_doubling_c, em_gain_range=tuple(cc.em_gain_range),
                          time_scale=rig.time_scale, shape=tuple(reversed(cfg.model.system.camera.pixels)))


@contextlib.contextmanager
def _stop_on_signals(ctx: RunContext):
    """Ctrl-C (SIGINT) sets a flag that the frame loop checks between frames.  (SIGTERM
    keeps the CLI's handling: it unwinds at once, through the same clean-up.)"""
    stop = threading.Event()

    def handler(signum, frame):
        if not stop.is_set():
            ctx.say("capture-surface: stopping after this frame ...")
        stop.set()

    old = {s: signal.signal(s, handler) for s in (signal.SIGINT,)}
    try:
        yield stop.is_set
    finally:
        for s, h in old.items():
            signal.signal(s, h)


# ------------------------------------------------------------------ the stage
def run(cfg: C.LoadedConfig, ctx: RunContext, resume: bool = False) -> Path:
    cap, rig = _check(cfg)
    cc = rig.camera or C.RigCamera()
    # config checked before any file is touched (a calibration-only capture has no subject to render)
    scene = SimulatedScene(cfg) if cc.backend == "simulated" and cap.heights_mm else None
    out = _acquire_plan(cfg, ctx, cap, rig, scene, resume)
    if cap.surface is not None:
        _make_surface(cfg, ctx, cap.surface, scene, out)
    return out


def _acquire_plan(cfg: C.LoadedConfig, ctx: RunContext, cap: C.Capture, rig: C.Rig, scene, resume: bool) -> Path:
    from ..hardware.projector import open_display
    from ..hardware.rig import open_devices, start_simulators
    from ..pipeline import provenance

    cc = rig.camera or C.RigCamera()
    out = cfg.workdir / "capture.h5"
    A.clean_stale_temps(out.parent)  # e.g. a capture.h5 whose creation was killed
    if out.exists() and not resume:
        if not ctx.force:
            raise UserError(f"capture-surface: {out} exists; continue it with --resume, or start over with --force.")
        out.unlink()
    with contextlib.ExitStack() as stack:
        sims = start_simulators(rig)
        stack.callback(lambda: [s.stop() for s in sims.values()])
        wheel, stage = open_devices(rig, {n: s.url for n, s in sims.items()})
        stack.callback(wheel.close)
        stack.callback(stage.close)
        sf = cap.surface
        names = (tuple(sf.projectors) if sf.projectors is not None else tuple(rig.projectors)) if sf else ()
        displays = {}
        for name in names:
            displays[name] = open_display(name, rig.projectors[name])
            stack.callback(displays[name].close)
        cal = cap.calibration
        targets = _calibration_targets(cfg, cal) if cal is not None and cc.backend == "simulated" else None
        camera = _camera(cfg, cap, rig, sims, wheel, stage, scene, displays, targets)
        stack.callback(camera.close)
        plan = Plan(heights_mm=tuple(cap.heights_mm), filters=tuple(cap.filters), exposures_s=cap.exposures_s,
                    em_gain=cap.em_gain, repeats=cap.repeats, darks=cap.darks, seed=cap.seed,
                    shape=tuple(camera.shape), camera=cc.backend, scene=scene.digest if scene else "",
                    filter_positions=tuple((f, rig.filter_wheel.filters[f]) for f in dict.fromkeys(
                        cap.filters + ((sf.filter,) if sf else ()))),
                    surface=_surface_plan(cfg, sf, rig, camera) if sf else None,
                    calibration=_calibration_plan(cfg, cal, cc.backend) if cal else None)
        if out.exists():
            capfile = CaptureFile.resume(out, plan)
        else:
            truth = ({f: scene.power_rate(f) for f in cap.filters} if scene is not None else None)
            ctx.say(f"capture-surface: creating {out}")
            prov = (provenance(cfg) if scene is not None  # the geometry the simulated camera rendered
                    else A.Provenance(config=cfg.model.model_dump(mode="json", by_alias=True)))
            capfile = CaptureFile.create(out, plan, config_sha256=cfg.sha256, provenance=prov, truth=truth,
                                         truth_unit="photons per element per second (subject at rest)",
                                         pause_s=float(os.environ.get(CREATE_PAUSE_ENV, "0") or 0),
                                         calibration_truth=_calibration_truth(cfg) if targets is not None else None)
        stack.callback(capfile.close)
        total = len(plan.frames()) + len(capfile.pattern_committed) + len(capfile.calibration_committed)
        done = capfile.n_committed
        if done == total:
            ctx.say(f"capture-surface: {out} already holds all {total} frames")
            return out
        if scene is not None:  # T, truth and traced scenes ready before the devices move (the frames then flow)
            if sf is not None and not capfile.pattern_committed.all():
                for name in names:
                    scene.pattern_renderer(plan.surface.height_mm, plan.surface.binning, name)
            for h, name in dict.fromkeys((fr.height_mm, fr.filter) for fr in plan.frames()
                                         if not fr.dark and not capfile.committed[fr.index]):
                scene.render(h, name)
        if targets is not None and cal.grid is not None and not capfile.calibration_committed.all():
            heights = list(cal.grid.heights_mm)
            with ctx.progress("render grid", len(heights)) as tick:  # the simulated grid images, before any move
                for h in heights:
                    targets.grid(h)
                    tick()
        pattern_sets = {p: _patterns(sf, rig.projectors[p]) for p in names}
        prepare = None
        if cal is not None:
            prepare = targets.prepare if targets is not None else _operator_prepare(ctx, cal.confirm)
        devices = RigDevices(stage, wheel, camera, dict(rig.filter_wheel.filters), displays=displays,
                             pattern_image=lambda p, k: pattern_sets[p].frames[k],
                             panels={p: tuple(reversed(rig.projectors[p].pixels)) for p in names}, prepare=prepare)
        try:  # from here Ctrl-C waits for the frame under way (before, it stops at once)
            with _stop_on_signals(ctx) as stop_requested:
                ctx.say(f"capture-surface: {total - done} of {total} frames to take"
                        + (f" ({done} already in {out.name})" if done else ""))
                with ctx.progress_steps("capture", total, done) as update:
                    acquire(plan, capfile, devices, stop_requested=stop_requested, on_step=update,
                            on_frame=lambda fr: update(fr.label, advance=True))
        except Interrupted as e:
            ctx.say(f"capture-surface: stopped before frame '{e}'; shutter closed, stage stopped; "
                    f"{capfile.n_committed} of {total} frames are in {out} (--resume continues).")
            raise KeyboardInterrupt from None
    return out


# ------------------------------------------------------------------ from pattern frames to surface.h5
def _make_surface(cfg: C.LoadedConfig, ctx: RunContext, sf: C.CaptureSurface, scene, capture_path: Path) -> Path:
    """Decode the pattern frames of ``capture_path``, triangulate, mesh, write ``surface.h5``."""
    from ..acquisition import read_patterns
    from ..hardware.projector import projector_model
    from ..artefacts.surface import write_surface_artefact
    from ..structured.scan import decode_by_view
    from .plans import emccd_model, provenance
    from ..scene import mirror_names, plane_mirrors
    from ..structured.mesh import capture_metrics, distances_to_surface
    from ..structured.scan import merge_points, points_from_frames, surface_from_points

    m = cfg.model
    out = cfg.workdir / "surface.h5"
    digest = A.inputs_digest(capture=A.file_sha256(capture_path), surface=sf.model_dump(mode="json"),
                             system=m.system.model_dump(mode="json"),
                             projectors={k: v.model_dump(mode="json") for k, v in m.rig.projectors.items()})
    if not ctx.force and A.is_up_to_date(out, "surface", digest):
        ctx.say(f"capture-surface: {out} is up to date")
        return out
    pc = read_patterns(capture_path)
    camera = camera_at_binning(m.system.camera, (m.rig.camera or C.RigCamera()).binning // pc.binning)
    mirrors = plane_mirrors(m.system)
    views = ["direct"] + mirror_names(m.system)
    photons = pc.photons(emccd_model(m.system.camera.sensor, pc.exposure_s))
    warning = assumed_qe_warning(cfg.model.system, "capture-surface", real_counts=scene is None)
    if warning:
        ctx.say(warning)
    scans = []
    with ctx.progress("decode", len(pc.projectors)) as tick:
        for name in pc.projectors:
            ps = _patterns(sf, m.rig.projectors[name])
            scan = points_from_frames(photons[name], ps, camera, mirrors, projector_model(m.rig.projectors[name]),
                                      min_contrast=sf.min_contrast_photons,
                                      min_modulation_fraction=sf.min_modulation_fraction)
            scans.append(scan)
            tick()
    decode = decode_by_view(scans, list(pc.projectors), views, camera, mirrors)
    h = pc.height_mm
    floor = (m.system.stage.top_z_mm + h) if m.system.stage is not None else None
    merged = merge_points(scans, floor_z_mm=-np.inf if floor is None else floor)
    if len(merged.points_mm) < 50:
        raise UserError(f"capture-surface: only {len(merged.points_mm)} points were decoded from the pattern frames "
                        f"of {capture_path}; is the subject lit (rig.projectors) and the shadow mask "
                        f"(capture.surface.min_contrast_photons = {sf.min_contrast_photons:g}) right?")
    ctx.say(f"capture-surface: {len(merged.points_mm)} points "
            f"({', '.join(f'{v} {int((merged.view == j).sum())}' for j, v in enumerate(views))}); meshing ...")
    mesh = surface_from_points(merged, floor_z_mm=floor, element_size_mm=sf.mesh.element_size_mm,
                               face_size_mm=sf.mesh.face_size_mm, voxel_mm=sf.mesh.voxel_mm,
                               centre_spacing_mm=sf.mesh.centre_spacing_mm)
    distance = truth = metrics = None
    if scene is not None:  # the simulated rig knows the truth
        truth = scene.true_surface_at(h)
        distance = distances_to_surface(merged.points_mm, truth)
        metrics = capture_metrics(merged.points_mm, distance, mesh, truth)
        truth = truth.transformed(np.eye(3), np.array([0.0, 0.0, -h]))
        ctx.say("capture-surface: points within 0.1 / 0.2 / 0.4 mm of the true surface: "
                + " / ".join(f"{np.mean(distance < t):.1%}" for t in (0.1, 0.2, 0.4)))
    # at rest: as with the stage at height 0 (poses raise it by their height)
    shift = np.array([0.0, 0.0, -h])
    mesh = mesh.transformed(np.eye(3), shift)
    merged.points_mm = merged.points_mm + shift
    write_surface_artefact(out, mesh, points=merged, decode=decode, distance_to_truth_mm=distance, truth=truth, metrics=metrics,
                           config_sha256=cfg.sha256, inputs={"capture": A.file_sha256(capture_path)},
                           provenance=provenance(cfg), attrs={"inputs_digest": digest, "capture_height_mm": h})
    ctx.say(f"capture-surface: {out}: {len(mesh.faces)} faces, {mesh.n_elements} elements, "
            f"area {mesh.face_areas_mm2.sum():.0f} mm^2")
    return out
