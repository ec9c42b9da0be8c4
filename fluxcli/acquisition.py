"""Crash-safe acquisition: the plan and the frame loop that fills ``capture.h5``.

The plan (:class:`Plan`) lists every frame: first, with ``capture.calibration``, the
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

import json
import time
from dataclasses import asdict, dataclass, field
from typing import Callable

import numpy as np

from .artefacts.capture import (CalibrationCapture, CaptureFile, CaptureImages, PatternCapture,  # noqa: F401
                                read_calibration, read_capture, read_patterns)
from .errors import UserError

__all__ = ["Frame", "PatternFrame", "SurfacePlan", "CalibrationFrame", "CalibrationPlan", "CalibrationCapture",
           "read_calibration", "Plan", "CaptureFile", "RigDevices", "acquire", "read_capture",
           "CaptureImages", "Interrupted", "PatternCapture", "read_patterns"]  # the file's names: re-exported


class Interrupted(Exception):
    """The acquisition stopped at a frame boundary because it was asked to (Ctrl-C)."""


@dataclass(frozen=True)
class Frame:
    index: int
    dark: bool
    height_mm: float
    filter: str
    repeat: int
    exposure_s: float

    @property
    def label(self) -> str:
        if self.dark:
            return f"dark {self.repeat + 1} ({self.exposure_s:g} s)"
        return f"h={self.height_mm:g} mm, {self.filter}, {self.exposure_s:g} s, repeat {self.repeat + 1}"


@dataclass(frozen=True)
class PatternFrame:
    index: int  # slot in /patterns
    projector: str
    pattern: int  # position in the pattern sequence
    name: str  # white, black, grayB, grayB-inverse, phaseK

    @property
    def label(self) -> str:
        return f"projector {self.projector}, pattern {self.pattern + 1} ({self.name})"


@dataclass(frozen=True)
class SurfacePlan:
    """The structured-light part of a plan: every projector shows every pattern, one frame each."""

    projectors: tuple[str, ...]
    patterns: tuple[str, ...]  # names of the sequence, in order (the same for every projector)
    height_mm: float
    filter: str
    exposure_s: float
    em_gain: float
    binning: int
    shape: tuple[int, int]  # (ny, nx) of a pattern frame
    n_gray: int
    n_steps: int
    content: str  # digest of the pattern images and the projectors' models

    def frames(self) -> list[PatternFrame]:
        return [PatternFrame(k * len(self.patterns) + i, p, i, name)
                for k, p in enumerate(self.projectors) for i, name in enumerate(self.patterns)]


CALIBRATION_KINDS = ("bias", "dark", "grid", "flat", "ptc_off", "ptc_on")  # the order they are taken in
_SHUTTER_CLOSED = ("bias", "dark")


@dataclass(frozen=True)
class CalibrationFrame:
    index: int  # slot in /calibration
    kind: str  # one of CALIBRATION_KINDS
    series: int  # which series of its kind (grid: the height; dark, PTC: the exposure)
    repeat: int  # frame number in its series (PTC and bias pairs: 0-1, 2-3, ...)
    exposure_s: float
    em_gain: float
    height_mm: float  # planned stage height (nan: the stage stays where it is)
    filter: str  # filter in the beam ("": shutter closed, any filter)

    @property
    def target(self) -> str:
        """What must be in front of the camera: ``closed`` (shutter), ``grid`` (on the stage, lit), ``light``."""
        return "closed" if self.kind in _SHUTTER_CLOSED else "grid" if self.kind == "grid" else "light"

    @property
    def label(self) -> str:
        where = f"h={self.height_mm:g} mm, " if self.kind == "grid" else ""
        return (f"calibration {self.kind} {where}{self.exposure_s:g} s, gain {self.em_gain:g}, "
                f"frame {self.repeat + 1}")


@dataclass(frozen=True)
class CalibrationPlan:
    """The calibration part of a plan: series of (kind, height, exposure, gain, filter, frames)."""

    series: tuple[tuple[str, int, float, float, float | None, str, int], ...]  # kind, series, exposure, gain, height (None: not moved), filter, n
    grid: tuple[tuple[str, object], ...] = ()  # (key, value) of the grid's description (JSON in the file)
    content: str = ""  # digest of what a simulated camera shows (grid brightness, light) ("" for a real camera)

    def frames(self) -> list[CalibrationFrame]:
        out: list[CalibrationFrame] = []
        for kind, series, exposure_s, gain, height, filter, n in self.series:
            for r in range(n):
                out.append(CalibrationFrame(len(out), kind, series, r, exposure_s, gain,
                                            float("nan") if height is None else height, filter))
        return out


@dataclass(frozen=True)
class Plan:
    """What to acquire.  Two runs may share a file only when their plans are equal."""

    heights_mm: tuple[float, ...]
    filters: tuple[str, ...]
    exposures_s: tuple[float, ...]
    em_gain: float
    repeats: int
    darks: int
    seed: int
    shape: tuple[int, int]  # (ny, nx) of a frame
    filter_positions: tuple[tuple[str, int], ...] = ()  # (name, wheel position) of each planned filter
    camera: str = "simulated"  # backend
    scene: str = ""  # digest of what a simulated camera renders ("" for a real camera)
    surface: SurfacePlan | None = None  # structured-light pattern frames, taken first
    calibration: CalibrationPlan | None = None  # calibration frames, taken before everything else

    def frames(self) -> list[Frame]:
        out: list[Frame] = []
        for e in self.exposures_s:
            for r in range(self.darks if self.heights_mm else 0):  # no subject frames: nothing to subtract darks from
                out.append(Frame(len(out), True, self.heights_mm[0], self.filters[0], r, e))
        for h in self.heights_mm:
            for name in self.filters:
                for e in self.exposures_s:
                    for r in range(self.repeats):
                        out.append(Frame(len(out), False, h, name, r, e))
        return out

    def as_dict(self) -> dict:
        return json.loads(json.dumps(asdict(self)))

    def differences(self, other: dict) -> list[str]:
        """What differs between this plan and ``other`` (a stored plan), in words."""
        mine = self.as_dict()
        names = {"scene": "the simulated scene (system, subject, simulate, rig.camera)", "shape": "frame shape",
                 "exposures_s": "capture.exposure_s", "filter_positions": "rig.filter_wheel.filters",
                 "camera": "rig.camera.backend"}
        out = []
        for k in mine:
            theirs = other.get(k)
            if theirs == mine[k]:
                continue
            if k in ("surface", "calibration") and isinstance(theirs, dict) and isinstance(mine[k], dict):
                sub = {"content": "the patterns or rig.projectors", "shape": "pattern frame shape",
                       "patterns": "the pattern sequence"} if k == "surface" else {
                       "content": "capture.calibration.simulated", "series": "the calibration series",
                       "grid": "capture.calibration.grid or system.stage.top_z_mm"}
                out += [f"{sub.get(j, f'capture.{k}.' + j)}: file has {theirs.get(j)!r}, config has {v!r}"
                        for j, v in mine[k].items() if theirs.get(j) != v]
            elif k in ("surface", "calibration"):
                what = "structured-light" if k == "surface" else "calibration"
                out.append(f"capture.{k}: the file was captured {'without' if theirs is None else 'with'} "
                           f"{what} frames, the config asks {'without' if mine[k] is None else 'with'} them")
            else:
                out.append(f"{names.get(k, 'capture.' + k)}: file has {theirs!r}, config has {mine[k]!r}")
        return out


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
