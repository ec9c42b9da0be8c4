"""``fluxmap capture-surface CONFIG [--resume]``: acquire the emission images of ``capture:``.

Examples
--------
$ fluxmap capture-surface configs/demo-rig.yaml            # simulated rig, in-process
$ fluxmap capture-surface configs/demo-rig.yaml --resume   # continue after a crash or Ctrl-C
$ fluxmap capture-surface lab.yaml --force                 # start the capture over

Devices come from ``rig:``: a port ``pty`` or ``socket://127.0.0.1:0`` starts that device's
simulator in this process, any other port is opened as the real device (or a ``fluxmap
rig serve`` elsewhere).  ``rig.camera.backend: simulated`` renders the subject's emission
through the forward model (``simulate.flux``, T at the stage's physical height, the filter
in the beam) with EMCCD noise; ``dcam`` drives the real camera.  Frames go to
``<workdir>/capture.h5`` as they arrive (see :mod:`fluxcli.acquisition`).  Ctrl-C stops at
a frame boundary with the shutter closed and the stage stopped (exit 130); a device fault
exits 2 naming the device.  (Structured-light surface capture is a later issue.)
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
from .context import RunContext

# Test hook: sleep this long between the steps of creating capture.h5, so that the kill
# test can land SIGKILLs inside the creation window.  0 (unset) in normal use.
CREATE_PAUSE_ENV = "FLUXMAP_CAPTURE_CREATE_PAUSE_S"


# ------------------------------------------------------------------ the simulated scene
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
        self.cfg = cfg
        self.light = dict((cfg.model.rig.camera or C.RigCamera()).filters)
        self._placer = None
        self._rates: dict[str, np.ndarray] = {}
        self._images: dict[tuple[float, str], np.ndarray] = {}
        for name, spec in self.light.items():
            self._flux_for(name, spec)  # refuse bad wavelengths before any device moves

    @property
    def digest(self) -> str:
        m = self.cfg.model
        return A.inputs_digest(system=m.system.model_dump(mode="json"), subject=m.subject.model_dump(mode="json"),
                               simulate=m.simulate.model_dump(mode="json"),
                               camera=(m.rig.camera or C.RigCamera()).model_dump(mode="json"))

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

    def power_rate(self, name: str) -> np.ndarray:
        """Photons/s leaving each element (subject at rest) as seen through filter ``name``."""
        if name not in self._rates:
            from ..truth import truth_power

            spec = self.light.get(name)
            m = self.cfg.model
            sim = m.simulate.model_copy(update={"flux": self._flux_for(name, spec)})
            cfg = C.LoadedConfig(m.model_copy(update={"simulate": sim}), self.cfg.path, self.cfg.raw)
            power, _ = truth_power(cfg, self.placer.surface)
            if power.min() < -1e-9 * power.max():  # a coarse FEM mesh undershoots where light dies fast
                raise UserError(f"simulate.flux seen through filter {name!r}: the truth dips to {power.min():.3g} "
                                f"photons on some element (peak {power.max():.3g}); the diffusion mesh "
                                "(simulate.flux.mesh_edge_mm) is too coarse for these optical properties.")
            power = np.maximum(power, 0.0)
            transmission = 1.0 if spec is None else spec.transmission
            self._rates[name] = power * transmission / m.simulate.noise.exposure_s
        return self._rates[name]

    def render(self, height_mm: float, name: str) -> np.ndarray:
        # 0.1 um is far below any depth of field: the stage's microstep rounding (~7 nm)
        # then reuses the T of the planned height instead of building another
        key = (round(float(height_mm), 4), name)
        if key not in self._images:
            from ..pipeline import ensure_pose_T
            from ..scene import Pose
            from ..truth import forward_transfer  # the forward T's sampling, as simulate uses

            rot = (self.cfg.model.subject.poses or C.Poses()).rotations_deg[0]
            T = ensure_pose_T(self.cfg, Pose(key[0], float(rot)), forward_transfer(self.cfg), self.placer)
            nx, ny = self.cfg.model.system.camera.pixels
            self._images[key] = (T @ self.power_rate(name)).reshape(ny, nx)
        return self._images[key]


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
    unknown = [f for f in cap.filters if f not in rig.filter_wheel.filters]
    if unknown:
        raise UserError(f"capture.filters: {unknown} not in rig.filter_wheel.filters "
                        f"({sorted(rig.filter_wheel.filters)}).")
    lo, hi = rig.stage.travel_mm
    out = [h for h in cap.heights_mm if not lo <= h <= hi]
    if out:
        raise UserError(f"capture.heights_mm: {out} mm outside the stage's travel rig.stage.travel_mm [{lo}, {hi}].")
    return cap, rig


def _camera(cfg: C.LoadedConfig, cap: C.Capture, rig: C.Rig, sims: dict, wheel, stage, scene):
    from ..pipeline import emccd_model

    cc = rig.camera or C.RigCamera()
    if cc.backend == "dcam":
        from ..hardware.dcam import DcamCamera

        cam = DcamCamera(cc.device_index, shutter_property=cc.shutter_property)
        cam.binning = cc.binning
        return cam
    from ..hardware.camera import SimulatedEmccd

    positions = {p: n for n, p in rig.filter_wheel.filters.items()}
    # the physical state: the simulator's when it runs here, else the driver's read-back
    height = (lambda: sims["stage"].position_mm) if "stage" in sims else stage.position_mm
    pos = (lambda: sims["filter_wheel"].position) if "filter_wheel" in sims else (lambda: wheel.position)
    return SimulatedEmccd(scene.render, stage_height_mm=height, filter_name=lambda: positions.get(pos(), f"position {pos()}"),
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
    from ..hardware.rig import open_devices, start_simulators
    from ..pipeline import provenance

    cap, rig = _check(cfg)
    cc = rig.camera or C.RigCamera()
    scene = SimulatedScene(cfg) if cc.backend == "simulated" else None  # config checked before any file is touched
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
        camera = _camera(cfg, cap, rig, sims, wheel, stage, scene)
        stack.callback(camera.close)
        plan = Plan(heights_mm=tuple(cap.heights_mm), filters=tuple(cap.filters), exposures_s=cap.exposures_s,
                    em_gain=cap.em_gain, repeats=cap.repeats, darks=cap.darks, seed=cap.seed,
                    shape=tuple(camera.shape), camera=cc.backend, scene=scene.digest if scene else "",
                    filter_positions=tuple((f, rig.filter_wheel.filters[f]) for f in cap.filters))
        if out.exists():
            capfile = CaptureFile.resume(out, plan)
        else:
            truth = ({f: scene.power_rate(f) for f in cap.filters} if scene is not None else None)
            ctx.say(f"capture-surface: creating {out}")
            prov = (provenance(cfg) if scene is not None  # the geometry the simulated camera rendered
                    else A.Provenance(config=cfg.model.model_dump(mode="json", by_alias=True)))
            capfile = CaptureFile.create(out, plan, config_sha256=cfg.sha256, provenance=prov, truth=truth,
                                         truth_unit="photons per element per second (subject at rest)",
                                         pause_s=float(os.environ.get(CREATE_PAUSE_ENV, "0") or 0))
        stack.callback(capfile.close)
        total, done = len(plan.frames()), int(capfile.committed.sum())
        if done == total:
            ctx.say(f"capture-surface: {out} already holds all {total} frames")
            return out
        if scene is not None:  # T and truth ready before the devices move (the frames then flow)
            for h, name in dict.fromkeys((fr.height_mm, fr.filter) for fr in plan.frames()
                                         if not fr.dark and not capfile.committed[fr.index]):
                scene.render(h, name)
        try:  # from here Ctrl-C waits for the frame under way (before, it stops at once)
            with _stop_on_signals(ctx) as stop_requested:
                ctx.say(f"capture-surface: {total - done} of {total} frames to take"
                        + (f" ({done} already in {out.name})" if done else ""))
                with ctx.progress_steps("capture", total, done) as update:
                    acquire(plan, capfile, RigDevices(stage, wheel, camera, dict(rig.filter_wheel.filters)),
                            stop_requested=stop_requested, on_step=update,
                            on_frame=lambda fr: update(fr.label, advance=True))
        except Interrupted as e:
            ctx.say(f"capture-surface: stopped before frame '{e}'; shutter closed, stage stopped; "
                    f"{int(capfile.committed.sum())} of {total} frames are in {out} (--resume continues).")
            raise KeyboardInterrupt from None
    return out
