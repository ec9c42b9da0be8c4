"""Crash-safe acquisition: the plan and the frame loop that fills ``capture.h5``.

The plan (:class:`Plan`, kept with the layout in :mod:`fluxcli.artefacts.capture`) lists every frame: first, with ``capture.calibration``, the
calibration frames (:class:`CalibrationPlan`: bias and dark frames with the shutter closed,
the grid at each stage height, the flat and photon-transfer frames of an even light), then,
with ``capture.surface``, the structured-light pattern frames (:class:`SurfacePlan`: for each projector each pattern of
the Gray-code + phase-shift sequence, the other projectors black), then the dark frames
(shutter closed) of each exposure time, then for each stage height, each filter, each
exposure, ``repeats`` emission frames.  Emission frame ``k`` of the plan has slot ``k`` in
``capture.h5``, pattern frame ``k`` slot ``k`` of ``/patterns``;

the layout, and why the file survives a kill at any instant (skeleton first, then each
frame fsync'ed before its ``committed`` flag), are :mod:`fluxcli.artefacts.capture`'s, the
only code that opens the file.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from .artefacts.capture import (CalibrationCapture, CalibrationFrame, CalibrationPlan, CaptureFile,  # noqa: F401
                                CaptureImages, Frame, PatternCapture, PatternFrame, Plan, SurfacePlan,
                                read_calibration, read_capture, read_patterns)
from .errors import UserError

__all__ = ["Frame", "PatternFrame", "SurfacePlan", "CalibrationFrame", "CalibrationPlan", "CalibrationCapture",
           "read_calibration", "Plan", "CaptureFile", "RigDevices", "acquire", "read_capture",
           "CaptureImages", "Interrupted", "PatternCapture", "read_patterns"]  # the file's names: re-exported


class Interrupted(Exception):
    """The acquisition stopped at a frame boundary because it was asked to (Ctrl-C)."""


@dataclass
class RigDevices:
    """The devices acquisition drives, and how filter names map to wheel positions."""

    stage: object  # .move_to_mm(z) -> float, .position_mm() -> float, .stop()
    wheel: object  # .move_to(pos) -> int, .position -> int
    camera: object  # fluxcli.hardware.camera.Camera
    filter_positions: dict[str, int] = field(default_factory=dict)
    displays: dict = field(default_factory=dict)  # projector name -> PatternDisplay (.show(image))
    pattern_image: Callable[[str, int], np.ndarray] | None = None  # (projector, pattern index) -> image
    panels: dict = field(default_factory=dict)  # projector name -> (height_px, width_px)
    prepare: Callable[[str], None] | None = None  # calibration: set up "closed" / "grid" / "light" in front of the camera

    def filter_name(self, position: int) -> str:
        for name, p in self.filter_positions.items():
            if p == position:
                return name
        return f"position {position}"


# ------------------------------------------------------------------ the frame loop
def _settle(rig: "RigDevices", cam, *, filter: str, height_mm: float, on_step, tolerance_mm: float) -> None:
    pos = rig.filter_positions[filter]
    if rig.wheel.position != pos:
        on_step(f"filter -> {filter}")
        rig.wheel.move_to(pos)
    if abs(rig.stage.position_mm() - height_mm) > tolerance_mm:
        on_step(f"stage -> {height_mm:g} mm")
        rig.stage.move_to_mm(height_mm)


def _meta(rig: "RigDevices", cam) -> dict:
    position = int(rig.wheel.position)
    return {"time_unix": time.time(), "stage_height_mm": float(rig.stage.position_mm()), "filter_position": position,
            "filter_name": rig.filter_name(position).encode()[:32], "exposure_s": float(cam.exposure_s),
            "em_gain": float(cam.em_gain), "temperature_c": float(cam.temperature_c),
            "shutter_open": int(bool(cam.shutter_open))}


def _show(rig: "RigDevices", shown: dict, projector: str | None, pattern: int | None) -> None:
    """Projector ``projector`` shows pattern ``pattern``, every other one black (``shown``
    remembers what each shows, so a display is only redrawn when its image changes)."""
    for name, display in rig.displays.items():
        want = pattern if name == projector else None
        if name not in shown or shown[name] != want:
            display.show(np.zeros(rig.panels[name]) if want is None else rig.pattern_image(name, want))
            shown[name] = want


def _acquire_patterns(plan: Plan, out: "CaptureFile", rig: "RigDevices", cam, *, stop_requested, on_step, on_frame,
                      tolerance_mm: float) -> int:
    sp = plan.surface
    todo = [fr for fr in sp.frames() if not out.pattern_committed[fr.index]]
    if not todo:
        return 0
    emission_binning = cam.binning
    n_emission = len(plan.frames())
    shown: dict = {}
    for fr in todo:
        if stop_requested():
            raise Interrupted(fr.label)
        _settle(rig, cam, filter=sp.filter, height_mm=sp.height_mm, on_step=on_step, tolerance_mm=tolerance_mm)
        if cam.binning != sp.binning:
            cam.binning = sp.binning
        if cam.em_gain != sp.em_gain:
            cam.em_gain = sp.em_gain
        if cam.exposure_s != sp.exposure_s:
            cam.exposure_s = sp.exposure_s
        _show(rig, shown, fr.projector, fr.pattern)
        cam.shutter_open = True
        on_step(fr.label)
        cam.set_frame_index(n_emission + fr.index)  # the noise of pattern frame k: slot n_emission + k
        counts = cam.snap()
        out.write_frame(fr.index, np.asarray(counts), _meta(rig, cam), pattern=True)
        on_frame(fr)
    _show(rig, shown, None, None)
    cam.binning = emission_binning
    return len(todo)


def _acquire_calibration(plan: Plan, out: "CaptureFile", rig: "RigDevices", cam, *, stop_requested, on_step,
                         on_frame, tolerance_mm: float) -> int:
    """The calibration frames not yet in ``out``: ``rig.prepare(target)`` whenever what must be
    in front of the camera changes (also before the first frame taken in this run)."""
    todo = [fr for fr in plan.calibration.frames() if not out.calibration_committed[fr.index]]
    first_slot = len(plan.frames()) + (len(plan.surface.frames()) if plan.surface is not None else 0)
    current = None
    for fr in todo:
        if stop_requested():
            raise Interrupted(fr.label)
        if fr.target != current:
            cam.shutter_open = False
            if rig.prepare is not None:
                on_step(f"set up: {fr.target}")
                rig.prepare(fr.target)
            current = fr.target
        if fr.kind == "grid":
            _settle(rig, cam, filter=fr.filter, height_mm=fr.height_mm, on_step=on_step, tolerance_mm=tolerance_mm)
        elif fr.filter and rig.wheel.position != rig.filter_positions[fr.filter]:
            on_step(f"filter -> {fr.filter}")
            rig.wheel.move_to(rig.filter_positions[fr.filter])
        if cam.em_gain != fr.em_gain:
            cam.em_gain = fr.em_gain
        if cam.exposure_s != fr.exposure_s:
            cam.exposure_s = fr.exposure_s
        cam.shutter_open = fr.target != "closed"
        on_step(fr.label)
        cam.set_frame_index(first_slot + fr.index)  # the noise of calibration frame k: after every other slot
        counts = cam.snap()
        out.write_frame(fr.index, np.asarray(counts), _meta(rig, cam), calibration=True)
        on_frame(fr)
    if todo and rig.prepare is not None and (plan.frames() or plan.surface is not None):
        cam.shutter_open = False
        on_step("set up: subject")
        rig.prepare("subject")
    return len(todo)


def acquire(plan: Plan, out: CaptureFile, rig: RigDevices, *, stop_requested: Callable[[], bool] = lambda: False,
            on_step: Callable[[str], None] = lambda s: None, on_frame: Callable[[Frame], None] = lambda fr: None,
            height_tolerance_mm: float = 1e-3) -> int:
    """Take every frame of ``plan`` that ``out`` does not hold yet; returns how many were taken.

    Between frames ``stop_requested()`` is checked; when true the loop raises
    :class:`Interrupted`.  Whatever happens, the camera's shutter is closed and the stage
    is told to stop before returning (devices left safe)."""
    cam = rig.camera
    taken = 0
    todo = [fr for fr in plan.frames() if not out.committed[fr.index]]
    if not todo and (plan.surface is None or out.pattern_committed.all()) and (
            plan.calibration is None or out.calibration_committed.all()):
        return 0
    try:
        on_step("camera settings")
        cam.cooler_on = True
        if plan.calibration is not None:
            taken += _acquire_calibration(plan, out, rig, cam, stop_requested=stop_requested, on_step=on_step,
                                          on_frame=on_frame, tolerance_mm=height_tolerance_mm)
        if plan.surface is not None:
            taken += _acquire_patterns(plan, out, rig, cam, stop_requested=stop_requested, on_step=on_step,
                                       on_frame=on_frame, tolerance_mm=height_tolerance_mm)
        cam.em_gain = plan.em_gain
        for run in _runs(todo):  # the repeats of one setting: one camera sequence
            fr = run[0]
            if stop_requested():
                raise Interrupted(fr.label)
            if fr.dark:
                cam.shutter_open = False
            else:
                _settle(rig, cam, filter=fr.filter, height_mm=fr.height_mm, on_step=on_step,
                        tolerance_mm=height_tolerance_mm)
                cam.shutter_open = True
            if cam.exposure_s != fr.exposure_s:
                cam.exposure_s = fr.exposure_s
            cam.set_frame_index(fr.index)
            stream = cam.frames(len(run))
            try:
                for one in run:  # each frame committed as it is read out; a stop between any two
                    if one is not fr and stop_requested():
                        raise Interrupted(one.label)
                    on_step(one.label)
                    counts = next(stream, None)
                    if counts is None:
                        raise UserError(f"camera ({plan.camera} backend): a sequence of {len(run)} frames ended "
                                        f"before {one.label}; the frames before it are kept, run again with --resume.")
                    out.write_frame(one.index, np.asarray(counts), _meta(rig, cam))
                    taken += 1
                    on_frame(one)
            finally:
                stream.close()
    except BaseException:
        _make_safe(rig, report=False)  # what went wrong first is what the user must read
        raise
    _make_safe(rig)
    return taken


def _runs(frames: list[Frame]) -> list[list[Frame]]:
    """Consecutive frames of one setting (dark or lit, height, filter, exposure) with consecutive
    plan indices: the repeats a camera takes as one sequence (``Camera.frames``)."""
    runs: list[list[Frame]] = []
    for fr in frames:
        last = runs[-1][-1] if runs else None
        if (last is not None and fr.index == last.index + 1 and fr.dark == last.dark and fr.height_mm == last.height_mm
                and fr.filter == last.filter and fr.exposure_s == last.exposure_s):
            runs[-1].append(fr)
        else:
            runs.append([fr])
    return runs


def _make_safe(rig: RigDevices, report: bool = True) -> None:
    """Shutter closed and stage stopped, each tried even when the other fails."""
    errors = []
    blank = [lambda d=d, n=n: d.show(np.zeros(rig.panels[n])) for n, d in rig.displays.items()]
    for action in (rig.camera.make_safe, rig.stage.stop, *blank):
        try:
            action()
        except Exception as e:  # keep going: the other device must still be made safe
            errors.append(e)
    if errors and report:
        raise errors[0]
