"""``fluxmap rig check CONFIG``: does every device of ``rig:`` answer?

Examples
--------
$ fluxmap rig check configs/rig-sim.yaml            # the simulators
$ fluxmap rig check lab.yaml --no-move              # identify and snap only, nothing moves

For each configured device, in turn: connect and report model, serial number and
firmware; move the filter wheel through its named positions and back, and the stage
0.5 mm and back (never homing); read the camera's sensor temperature and cooler state and
snap one dark frame (shutter closed) and one lit frame (shutter open) into
``<workdir>/rig-check/{dark,lit}.tif``; show black on each projector.  A device that does
not answer is reported and the others are still checked; then the command exits 2
naming every device that did not answer.
"""

from __future__ import annotations

from pathlib import Path

from .. import config as C
from ..errors import UserError
from ..hardware.errors import DeviceError
from . import _rig
from .context import RunContext


def run(cfg: C.LoadedConfig, ctx: RunContext, *, move: bool = True, exposure_s: float = 0.1,
        em_gain: float | None = None) -> Path:
    from ..hardware.rig import exercise_stage, exercise_wheel, stage_identity, wheel_identity

    rig = _rig.rig_of(cfg)
    out_dir = cfg.workdir / "rig-check"
    with _rig.open_rig(rig, cfg.model.system, keep_going=True) as devices:
        def check(key: str, port: str, device, identify, exercise) -> None:
            if device is None:
                ctx.say(f"{key}: NO ANSWER on {devices.where(key, port)}")
                return
            try:
                ident = identify(device)
                ctx.say(f"{key}: {ident.model} | serial {ident.serial or 'not reported'} | firmware "
                        f"{ident.firmware or 'not reported'} | on {devices.where(key, port)}")
                for line in exercise(device):
                    ctx.say(f"  {line}")
            except UserError as e:
                devices.failed[key] = str(e)
                ctx.say(f"{key}: FAILED: {e}")

        if rig.filter_wheel is not None:
            check("rig.filter_wheel", rig.filter_wheel.port, devices.wheel, wheel_identity,
                  exercise_wheel if move else lambda w: [f"at position {w.position} (not moved: --no-move)"])
        if rig.stage is not None:
            check("rig.stage", rig.stage.port, devices.stage, stage_identity,
                  exercise_stage if move else lambda s: [f"at {s.position_mm():.4f} mm (not moved: --no-move)"])
        cc = rig.camera or C.RigCamera()
        gain = _rig.lowest_gain(rig) if em_gain is None else float(em_gain)
        check("rig.camera", f"backend {cc.backend}", devices.camera, lambda c: c.identity(),
              lambda c: _exercise_camera(c, out_dir, exposure_s, gain))
        for name, spec in rig.projectors.items():
            check(f"rig.projectors.{name}", spec.display, spec, _projector_identity, lambda s, n=name: _show_black(n, s))
    if devices.failed:
        raise UserError(f"rig check: {len(devices.failed)} device(s) did not answer: "
                        + "; ".join(f"{k}: {v}" for k, v in devices.failed.items()))
    ctx.say(f"rig check: every configured device answered; frames in {out_dir}")
    return out_dir


def _exercise_camera(camera, out_dir: Path, exposure_s: float, em_gain: float) -> list[str]:
    lines = [f"sensor {camera.temperature_c:g} deg C, cooler {camera.cooling_status}; frames "
             f"{camera.shape[1]} x {camera.shape[0]} px at binning {camera.binning}"]
    camera.exposure_s = exposure_s
    camera.em_gain = em_gain
    try:
        camera.shutter_open = False
    except DeviceError as e:  # the camera answers; it has no shutter to close
        lines.append(f"dark: not taken ({e.problem})")
    else:
        dark = camera.snap()
        path = _rig.write_frame(out_dir / "dark.tif", dark, camera, shutter_open=0)
        lines.append(f"dark: {_rig.describe(dark)} at {exposure_s:g} s, gain {em_gain:g} -> {path}")
    camera.shutter_open = True
    lit = camera.snap()
    path = _rig.write_frame(out_dir / "lit.tif", lit, camera, shutter_open=1)
    lines.append(f"lit: {_rig.describe(lit)} at {exposure_s:g} s, gain {em_gain:g} -> {path}")
    camera.make_safe()
    return lines


def _projector_identity(spec):
    from ..hardware.camera import DeviceIdentity

    w, h = spec.pixels
    return DeviceIdentity(f"projector {w} x {h} px, display {spec.display}"
                          + (f" on screen {spec.screen}" if spec.display == "window" else ""))


def _show_black(name: str, spec) -> list[str]:
    from ..hardware.projector import open_display

    display = open_display(name, spec)  # shows black
    display.close()
    return ["showed black"]
