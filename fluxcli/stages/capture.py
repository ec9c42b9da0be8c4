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
import signal
import threading
from pathlib import Path

from .. import artefacts as A
from .. import config as C
from ..acquisition import CaptureFile, Interrupted, Plan, RigDevices, acquire
from ..errors import UserError
from . import _capture_scene as _scene
from ._capture_plan import (CREATE_PAUSE_ENV, CapturePlan, calibration_plan, calibration_targets,  # noqa: F401
                            calibration_truth, patterns, plan_of, scene_parts, surface_plan, truth_config)
from ._capture_scene import camera_at_binning  # noqa: F401  (re-exported)
from ._capture_surface import make_surface
from .context import RunContext


def SimulatedScene(cfg: C.LoadedConfig) -> _scene.SimulatedScene:  # noqa: N802  (the name tests and notebooks use)
    """The simulated camera's subject of a config (the stage itself builds it from its plan)."""
    return _scene.SimulatedScene(scene_parts(cfg))


# ------------------------------------------------------------------ devices
def _camera(plan: CapturePlan, sims: dict, wheel, stage, scene, displays: dict | None = None, targets=None):
    """The camera of ``rig.camera``: a real one, or the simulated EMCCD rendering ``scene`` (and ``targets``)."""
    from .plans import emccd_model

    cap, rig, cc, camera = plan.capture, plan.rig, plan.camera_settings, plan.system.camera if plan.system else None
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
                          sensor=emccd_model(camera.sensor, cap.exposures_s[0]), seed=cap.seed,
                          native_binning=cc.binning, setpoint_c=cc.setpoint_c, ambient_c=cc.ambient_c,
                          dark_doubling_c=cc.dark_doubling_c, em_gain_range=tuple(cc.em_gain_range),
                          time_scale=rig.time_scale, shape=tuple(reversed(camera.pixels)))


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
    plan = plan_of(cfg)  # config checked before any file is touched
    scene = _scene.SimulatedScene(plan.scene) if plan.scene is not None else None
    out = _acquire_plan(plan, ctx, scene, resume)
    if plan.capture.surface is not None:
        make_surface(plan, ctx, scene, out)
    return out


def _acquire_plan(plan_: CapturePlan, ctx: RunContext, scene, resume: bool) -> Path:
    from ..hardware.projector import open_display
    from ..hardware.rig import open_devices, start_simulators

    cap, rig, cc, names = plan_.capture, plan_.rig, plan_.camera_settings, plan_.projectors
    out = plan_.output
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
        displays = {}
        for name in names:
            displays[name] = open_display(name, rig.projectors[name])
            stack.callback(displays[name].close)
        cal = cap.calibration
        targets = calibration_targets(plan_.system, cal) if cal is not None and cc.backend == "simulated" else None
        camera = _camera(plan_, sims, wheel, stage, scene, displays, targets)
        stack.callback(camera.close)
        plan = Plan(heights_mm=tuple(cap.heights_mm), filters=tuple(cap.filters), exposures_s=cap.exposures_s,
                    em_gain=cap.em_gain, repeats=cap.repeats, darks=cap.darks, seed=cap.seed,
                    shape=tuple(camera.shape), camera=cc.backend, scene=scene.digest if scene else "",
                    filter_positions=tuple((f, rig.filter_wheel.filters[f]) for f in dict.fromkeys(
                        cap.filters + ((sf.filter,) if sf else ()))),
                    surface=surface_plan(sf, rig, camera) if sf else None,
                    calibration=calibration_plan(cal, plan_.system, cc.backend) if cal else None)
        if out.exists():
            capfile = CaptureFile.resume(out, plan)
        else:
            truth = ({f: scene.power_rate(f) for f in cap.filters} if scene is not None else None)
            ctx.say(f"capture-surface: creating {out}")
            capfile = CaptureFile.create(out, plan, config_sha256=plan_.config_sha256, provenance=plan_.provenance,
                                         truth=truth,
                                         truth_unit="photons per element per second (subject at rest)",
                                         pause_s=plan_.create_pause_s,
                                         calibration_truth=(calibration_truth(plan_.system.camera)
                                                            if targets is not None else None))
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
        pattern_sets = {p: patterns(sf, rig.projectors[p]) for p in names}
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


