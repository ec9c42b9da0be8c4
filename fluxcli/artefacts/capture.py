"""The ``capture`` artefact (``<workdir>/capture.h5``, made by ``fluxmap capture-surface``): the
durable frame-by-frame writer (:class:`CaptureFile`) and the readers (:func:`read_capture`,
:func:`read_patterns`, :func:`read_calibration`) with their containers.  The only code that
touches the file's layout; :mod:`fluxcli.acquisition` sequences the devices and fills it.

Layout (the plan, :class:`Plan` below, lists every frame; emission frame ``k`` of the
plan has slot ``k``, pattern frame ``k`` slot ``k`` of ``/patterns``):

``/frames/counts``           uint16 ``[n_frames, ny, nx]`` ADC counts, row 0 first
``/frames/<metadata>``       per frame, read back from the devices after the exposure:
                             ``time_unix`` (s), ``stage_height_mm``, ``filter_position``,
                             ``filter_name``, ``exposure_s``, ``em_gain``, ``temperature_c``,
                             ``shutter_open``
``/frames/committed``        uint8 ``[n_frames]``: 1 once the frame and its metadata are durable
``/plan/...``                what each slot is meant to hold (dark, height_mm, filter, repeat)
``/truth/<filter>/power``    (simulated camera only) photons per element per second
``/patterns/counts``         uint16 ``[n_pattern_frames, ny', nx']`` (at ``capture.surface.binning``)
``/patterns/<metadata>``     as for ``/frames``, read back per pattern frame, and ``committed``
``/patterns/{projector, pattern_index, label, gray_bit, inverse, phase_step, phase_shift_rad}``
                             what each slot shows: projector name, position in the sequence,
                             ``white``/``black``/``grayB``/``grayB-inverse``/``phaseK``, the
                             Gray-code bit shown (-1: none), 1 for an inverse frame, the phase
                             step (-1: none) and its shift 2 pi K / n_steps (nan: none)
``/calibration/counts``      uint16 ``[n_calibration_frames, ny, nx]`` (``capture.calibration``)
``/calibration/<metadata>``  as for ``/frames``, read back per frame (the grid frames' stage
                             height is the one the grid plane is placed at), and ``committed``
``/calibration/{kind, series, repeat, plan_height_mm, plan_exposure_s, plan_em_gain, filter}``
                             what each slot is: ``grid``/``bias``/``dark``/``flat``/``ptc_off``/
                             ``ptc_on``, its series within the kind (a grid height, a dark or PTC
                             exposure), its frame number in the series (PTC pairs: 0-1, 2-3, ...)
                             and the planned settings; attribute ``grid`` (JSON: kind, pitch_mm,
                             shape, thickness_mm, stage_top_z_mm)

Why it survives a kill at any instant: the skeleton is written in full (every dataset
contiguous and allocated, zero-filled) under a temporary name and renamed into place, so
``capture.h5`` either does not exist or has all of its structure; afterwards a frame only
overwrites bytes inside storage that already exists (no HDF5 metadata changes), is flushed
and fsync'ed, and only then is its ``committed`` flag set (and flushed and fsync'ed
again).  A frame whose flag is not set is discarded on resume and taken again.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import h5py
import numpy as np

from ..errors import UserError
from .store import Provenance, open_artefact, put, write_artefact


FILE_NAME = "capture.h5"  # in the workdir
KIND = "capture"
META = {  # per-frame metadata read back from the devices (units: artefacts.kinds "capture")
    "time_unix": "f8", "stage_height_mm": "f8", "filter_position": "i4", "filter_name": "S32",
    "exposure_s": "f8", "em_gain": "f8", "temperature_c": "f8", "shutter_open": "u1",
}


# ------------------------------------------------------------------ the plan: every frame the file holds
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



# ------------------------------------------------------------------ the file
def _fsync(f: h5py.File) -> None:
    f.flush()
    os.fsync(f.id.get_vfd_handle())


class CaptureFile:
    """``capture.h5`` opened for appending frames (see the module docstring for the layout)."""

    def __init__(self, path: Path, f: h5py.File, plan: Plan):
        self.path = path
        self._f = f
        self.plan = plan
        self.committed = f["frames/committed"][()].astype(bool)
        self.pattern_committed = (f["patterns/committed"][()].astype(bool) if "patterns" in f
                                  else np.zeros(0, bool))
        self.calibration_committed = (f["calibration/committed"][()].astype(bool) if "calibration" in f
                                      else np.zeros(0, bool))

    # ------------------------------------------------------------ create / open
    @classmethod
    def create(cls, path: Path, plan: Plan, *, config_sha256: str = "", provenance: Provenance | None = None,
               truth: dict[str, np.ndarray] | None = None, truth_unit: str = "", pause_s: float = 0.0,
               calibration_truth: dict | None = None) -> "CaptureFile":
        """Write the whole skeleton under a temporary name, then rename it to ``path``
        (the artefacts' atomic writer: fsync, rename, fsync of the folder).

        ``pause_s`` sleeps between the creation steps; the kill test uses it to land
        SIGKILLs inside the creation window (0 otherwise).  ``calibration_truth`` (simulated
        camera) is the camera and sensor that render the calibration frames, stored as JSON
        in ``/calibration`` attribute ``truth`` for calibrate to report its errors against."""
        path = Path(path)
        frames = plan.frames()
        n, (ny, nx) = len(frames), plan.shape
        with write_artefact(path, KIND, config_sha256=config_sha256, provenance=provenance) as f:
            f.attrs["plan"] = json.dumps(plan.as_dict(), sort_keys=True)
            f.attrs["layout"] = "frames/counts[frame, row, col]; frame k is plan slot k; committed[k] = 1 when durable"
            time.sleep(pause_s)
            put(f, "plan/dark", np.array([fr.dark for fr in frames], np.uint8))
            put(f, "plan/height_mm", np.array([fr.height_mm for fr in frames], float))
            put(f, "plan/filter", np.array([fr.filter.encode() for fr in frames], "S32"))
            put(f, "plan/repeat", np.array([fr.repeat for fr in frames], np.int32))
            put(f, "plan/exposure_s", np.array([fr.exposure_s for fr in frames], float))
            # data= writes the zeros: contiguous storage allocated now, so writing a frame
            # later changes no HDF5 metadata
            put(f, "frames/counts", np.zeros((n, ny, nx), np.uint16))
            time.sleep(pause_s)
            for name, dtype in META.items():
                put(f, f"frames/{name}", np.zeros(n, dtype))
            put(f, "frames/committed", np.zeros(n, np.uint8))
            if plan.surface is not None:
                _create_patterns(f, plan.surface)
            if plan.calibration is not None:
                _create_calibration(f, plan.calibration, plan.shape)
                if calibration_truth is not None:
                    f["calibration"].attrs["truth"] = json.dumps(calibration_truth)
            if truth:
                t = f.create_group("truth")
                t.attrs["unit"] = truth_unit
                for name, power in truth.items():
                    t.create_group(name).create_dataset("power", data=np.asarray(power, float))
            time.sleep(pause_s)
        return cls._open(path, plan)

    @classmethod
    def _open(cls, path: Path, plan: Plan) -> "CaptureFile":
        return cls(path, h5py.File(path, "r+"), plan)

    @classmethod
    def resume(cls, path: Path, plan: Plan) -> "CaptureFile":
        """Open an existing capture for the same plan; refuse any other plan."""
        with open_artefact(path, KIND) as f:
            stored = json.loads(f.attrs["plan"])
        diff = plan.differences(stored)
        if diff:
            raise UserError(f"capture-surface --resume: {path} was captured with another plan, so it cannot be "
                            f"continued: {'; '.join(diff)}. Restore the plan, or start over with --force.")
        return cls._open(path, plan)

    # ------------------------------------------------------------ frames
    def write_frame(self, index: int, counts: np.ndarray, meta: dict, *, pattern: bool = False,
                    calibration: bool = False) -> None:
        """Store frame ``index`` (of ``/patterns`` when ``pattern``, of ``/calibration`` when
        ``calibration``) durably, then mark it committed (last)."""
        shape = self.plan.surface.shape if pattern else self.plan.shape
        if counts.shape != tuple(shape):
            raise ValueError(f"frame {index} is {counts.shape}, the plan's frames are {tuple(shape)}")
        g = self._f["patterns" if pattern else "calibration" if calibration else "frames"]
        g["counts"][index] = counts
        for name in META:
            g[name][index] = meta[name]
        _fsync(self._f)
        g["committed"][index] = 1
        _fsync(self._f)
        (self.pattern_committed if pattern else self.calibration_committed if calibration else self.committed)[index] = True

    @property
    def n_committed(self) -> int:
        return int(self.committed.sum() + self.pattern_committed.sum() + self.calibration_committed.sum())

    def close(self) -> None:
        self._f.close()


def _create_patterns(f: h5py.File, sp: SurfacePlan) -> None:
    """The /patterns skeleton: zero-filled, contiguous (a frame later changes no metadata)."""
    frames = sp.frames()
    n, (ny, nx) = len(frames), sp.shape
    g = f.create_group("patterns")
    for key in ("n_gray", "n_steps", "binning", "height_mm", "exposure_s", "em_gain"):
        g.attrs[key] = getattr(sp, key)
    g.attrs["filter"] = sp.filter
    put(g, "projector", np.array([fr.projector.encode() for fr in frames], "S32"))
    put(g, "pattern_index", np.array([fr.pattern for fr in frames], np.int32))
    put(g, "label", np.array([fr.name.encode() for fr in frames], "S32"))
    bit = [sp.n_gray - 1 - int(fr.name[4:].split("-")[0]) if fr.name.startswith("gray") else -1 for fr in frames]
    put(g, "gray_bit", np.array(bit, np.int32))
    put(g, "inverse", np.array([fr.name.endswith("-inverse") for fr in frames], np.uint8))
    step = [int(fr.name[5:]) if fr.name.startswith("phase") else -1 for fr in frames]
    put(g, "phase_step", np.array(step, np.int32))
    put(g, "phase_shift_rad", np.array([2 * np.pi * k / sp.n_steps if k >= 0 else np.nan for k in step]))
    put(g, "counts", np.zeros((n, ny, nx), np.uint16))
    for name, dtype in META.items():
        put(g, name, np.zeros(n, dtype))
    put(g, "committed", np.zeros(n, np.uint8))


def _create_calibration(f: h5py.File, cp: CalibrationPlan, shape: tuple[int, int]) -> None:
    """The /calibration skeleton: zero-filled, contiguous (a frame later changes no metadata)."""
    frames = cp.frames()
    n, (ny, nx) = len(frames), shape
    g = f.create_group("calibration")
    g.attrs["grid"] = json.dumps(dict(cp.grid))
    put(g, "kind", np.array([fr.kind.encode() for fr in frames], "S16"))
    put(g, "series", np.array([fr.series for fr in frames], np.int32))
    put(g, "repeat", np.array([fr.repeat for fr in frames], np.int32))
    put(g, "plan_height_mm", np.array([fr.height_mm for fr in frames], float))
    put(g, "plan_exposure_s", np.array([fr.exposure_s for fr in frames], float))
    put(g, "plan_em_gain", np.array([fr.em_gain for fr in frames], float))
    put(g, "filter", np.array([fr.filter.encode() for fr in frames], "S32"))
    put(g, "counts", np.zeros((n, ny, nx), np.uint16))
    for name, dtype in META.items():
        put(g, name, np.zeros(n, dtype))
    put(g, "committed", np.zeros(n, np.uint8))


# ------------------------------------------------------------------ reading a capture back
@dataclass
class CaptureImages:
    """The light frames of one filter, averaged per stage height, and the dark level."""

    heights_mm: np.ndarray  # (P,) planned heights
    heights_read_mm: np.ndarray  # (P,) mean read-back height of the frames used
    counts_mean: np.ndarray  # (P, ny, nx) mean counts over repeats
    counts_max: np.ndarray  # (P, ny, nx) largest count over repeats (for saturation)
    dark_mean_counts: float  # mean over every dark frame and pixel (bias + dark + CIC, counts)
    n_darks: int
    repeats: int
    exposure_s: float
    em_gain: float
    filter: str
    truth_power: np.ndarray | None  # photons per element per exposure_s, when the camera was simulated
    path: Path | None = None

    def pose_order(self, heights_mm) -> list[int]:
        """Which captured height serves each pose (``heights_mm`` in pose order); UserError
        naming both lists unless they match one to one (to 1 nm)."""
        heights = np.asarray(heights_mm, float)
        order = [int(np.argmin(np.abs(self.heights_mm - h))) for h in heights]
        if len(heights) != len(self.heights_mm) or np.any(np.abs(self.heights_mm[order] - heights) > 1e-6):
            raise UserError(f"reconstruct.images.capture: {self.path} was captured at stage heights "
                            f"{self.heights_mm.tolist()} mm, but subject.poses asks for heights {heights.tolist()} "
                            "mm; they must match one to one (one pose per captured height, no rotations).")
        return order


_READ_BACK = {  # what a frame's read-back value must be, by name: (test, in words)
    "stage_height_mm": (np.isfinite, "a finite height"),
    "height_mm": (np.isfinite, "a finite height"),
    "exposure_s": (lambda x: np.isfinite(x) & (x > 0), "a positive exposure"),
    "em_gain": (lambda x: np.isfinite(x) & (x >= 1), "an EM gain of at least 1"),
}


def _frame_table(f: h5py.File, path: Path, names: list[str]) -> None:
    """The per-frame datasets ``names`` (``frames/counts``, ``plan/height_mm``, ...) hold one
    entry per frame each, and the read-back settings are numbers a camera and a stage can
    give; else UserError naming the dataset (a file damaged, or not written by
    capture-surface: the readers below index one by another)."""
    lengths = {n: f[n].shape[0] if f[n].ndim else 1 for n in names}
    first = names[0]
    for n, k in lengths.items():
        if k != lengths[first]:
            raise UserError(f"capture {path} is damaged: {n} holds {k} frames but {first} {lengths[first]}; each "
                            "per-frame dataset holds one entry per frame. Take the capture again.")
    for n in names:
        test = _READ_BACK.get(n.rsplit("/", 1)[-1])
        if test is not None:
            x = f[n][()].astype(float)
            bad = np.flatnonzero(~test[0](x))
            if bad.size:
                raise UserError(f"capture {path} is damaged: {n}[{bad[0]}] is {x[bad[0]]:g}, not {test[1]}"
                                + (f" ({bad.size} such frames)" if bad.size > 1 else "") + ". Take the capture again.")


def read_capture(path: Path, filter: str | None = None, exposure_s: float | None = None,
                 exposure_key: str = "exposure_s") -> CaptureImages:
    """Read a complete capture: per planned height the mean of its light frames for ``filter``
    at ``exposure_s``, and the mean of the dark frames at that exposure.

    Raises UserError when the capture is incomplete, has no dark frames, or ``filter`` /
    ``exposure_s`` is not one of its own (``None`` is allowed when it has only one), naming the
    config key ``reconstruct.images.<exposure_key>`` the exposure came from."""
    path = Path(path)
    with open_artefact(path, KIND) as f:
        plan = json.loads(f.attrs["plan"])
        _frame_table(f, path, ["frames/committed", "frames/counts", "frames/stage_height_mm", "frames/em_gain",
                               "plan/height_mm", "plan/filter", "plan/exposure_s", "plan/dark"])
        committed = f["frames/committed"][()].astype(bool)
        if not committed.all():
            raise UserError(f"capture {path} is incomplete: {committed.sum()} of {committed.size} frames; finish it "
                            "with 'fluxmap capture-surface CONFIG --resume'.")
        filter = _one_of(path, "filter", filter, list(plan["filters"]))
        exposure_s = float(_one_of(path, exposure_key, exposure_s, [float(e) for e in plan["exposures_s"]]))
        pe = f["plan/exposure_s"][()]
        dark = f["plan/dark"][()].astype(bool)
        if not (dark & (pe == exposure_s)).any():
            raise UserError(f"capture {path} has no dark frames at {exposure_s:g} s (capture.darks: 0), so bias and "
                            "dark signal cannot be subtracted; capture at least one.")
        fr = f["frames"]
        counts = fr["counts"]
        darks = np.flatnonzero(dark & (pe == exposure_s))
        dark_mean = float(np.mean([counts[k].astype(float).mean() for k in darks]))
        pf = np.char.decode(f["plan/filter"][()])
        ph = f["plan/height_mm"][()]
        heights = np.array(plan["heights_mm"], float)
        mean, mx, read, used = [], [], [], []
        for h in heights:
            sel = np.flatnonzero(~dark & (pf == filter) & (ph == h) & (pe == exposure_s))
            if not sel.size:
                raise UserError(f"capture {path} is damaged: its plan names height {h:g} mm, but no light frame of "
                                f"filter {filter!r} at {exposure_s:g} s lies there (plan/height_mm). Take the "
                                "capture again.")
            stack = counts[sel[0]:sel[-1] + 1][sel - sel[0]]
            mean.append(stack.astype(float).mean(axis=0))
            mx.append(stack.max(axis=0))
            read.append(float(fr["stage_height_mm"][sel].mean()))
            used.extend(sel)
        gains = np.unique(np.concatenate([fr["em_gain"][np.array(used)], fr["em_gain"][darks]]))
        if len(gains) != 1:
            raise UserError(f"capture {path}: its frames were read out at EM gains {gains.tolist()}; darks and "
                            "light frames must share one.")
        truth = f[f"truth/{filter}/power"][()] * exposure_s if f"truth/{filter}" in f else None
    return CaptureImages(heights, np.array(read), np.array(mean), np.array(mx), dark_mean, len(darks),
                         int(plan["repeats"]), exposure_s, float(gains[0]), filter, truth, path)


def _one_of(path: Path, key: str, value, choices: list):
    if value is None:
        if len(choices) != 1:
            raise UserError(f"reconstruct.images.{key}: capture {path} holds {key} {choices}; name one.")
        return choices[0]
    if value not in choices:
        raise UserError(f"reconstruct.images.{key}: {value!r} is not in capture {path} (it holds {choices}).")
    return value


# ------------------------------------------------------------------ reading the pattern frames back
@dataclass
class PatternCapture:
    """The structured-light frames of a capture, per projector in sequence order."""

    projectors: list[str]
    counts: dict[str, np.ndarray]  # projector -> uint16 [n_patterns, ny, nx]
    exposure_s: float  # read back
    em_gain: float  # read back
    height_mm: float  # stage height read back (mean over the frames)
    binning: int
    n_gray: int
    n_steps: int
    path: Path | None = None


def _complete_group(f: h5py.File, path: Path, group: str, what: str, missing: str) -> h5py.Group:
    """Group ``group`` of a capture once every frame in it is committed; UserError ``missing``
    when the capture has no such group, or naming the count when frames are missing."""
    if group not in f:
        raise UserError(missing)
    g = f[group]
    committed = g["committed"][()].astype(bool)
    if not committed.all():
        raise UserError(f"capture {path} is incomplete: {committed.sum()} of {committed.size} {what}; "
                        "finish it with 'fluxmap capture-surface CONFIG --resume'.")
    return g


def read_patterns(path: Path) -> PatternCapture:
    """The pattern frames of a capture; UserError when it has none or they are incomplete."""
    path = Path(path)
    with open_artefact(path, KIND) as f:
        g = _complete_group(f, path, "patterns", "pattern frames",
                            f"capture {path} holds no structured-light pattern frames (capture.surface was not set "
                            "when it was taken); capture them with 'fluxmap capture-surface CONFIG --force'.")
        _frame_table(f, path, [f"patterns/{n}" for n in ("committed", "counts", "projector", "pattern_index",
                                                          "em_gain", "exposure_s", "stage_height_mm")])
        proj = np.char.decode(g["projector"][()])
        order = g["pattern_index"][()]
        counts = g["counts"][()]
        names = list(dict.fromkeys(proj.tolist()))
        by = {p: counts[np.flatnonzero(proj == p)[np.argsort(order[proj == p])]] for p in names}
        gains, exps = np.unique(g["em_gain"][()]), np.unique(g["exposure_s"][()])
        if len(gains) != 1 or len(exps) != 1:
            raise UserError(f"capture {path}: its pattern frames were read out at EM gains {gains.tolist()} and "
                            f"exposures {exps.tolist()} s; one of each is expected.")
        return PatternCapture(names, by, float(exps[0]), float(gains[0]), float(g["stage_height_mm"][()].mean()),
                              int(g.attrs["binning"]), int(g.attrs["n_gray"]), int(g.attrs["n_steps"]), path)


# ------------------------------------------------------------------ reading the calibration frames back
@dataclass
class CalibrationCapture:
    """The calibration frames of a capture, as ``calibrate`` uses them (settings as read back).

    ``grid_images`` are the mean of each height's repeats (counts, float), ``grid_stage_mm``
    the stage height read back (mean over the repeats); the grid plane lies at
    ``stage_top_z_mm + grid_stage_mm + thickness_mm`` (:meth:`grid_plane_z_mm`).  Radiometric
    series are count stacks ``[frame, row, col]`` with the exposure (s) and EM gain read back."""

    grid: dict | None  # kind, pitch_mm, shape, thickness_mm, stage_top_z_mm
    grid_images: list[np.ndarray]
    grid_stage_mm: list[float]
    bias: np.ndarray | None
    darks: list[tuple[np.ndarray, float, float]]  # (frames, exposure_s, em_gain)
    flats: np.ndarray | None
    ptc: list[tuple[np.ndarray, float, float]]  # (frames, exposure_s, em_gain), one per exposure and gain
    truth: dict | None = None  # simulated camera: the camera and sensor that made the frames
    path: Path | None = None

    def grid_plane_z_mm(self) -> list[float]:
        g = self.grid or {}
        return [float(g.get("stage_top_z_mm", 0.0)) + h + float(g.get("thickness_mm", 0.0)) for h in self.grid_stage_mm]


def _one_setting(values: np.ndarray, what: str, path: Path, kind: str) -> float:
    u = np.unique(np.round(values, 9))
    if len(u) != 1:
        raise UserError(f"capture {path}: the {kind} frames of one series were read out at {what} {u.tolist()}; "
                        "one value is expected (was the camera changed during the series?).")
    return float(u[0])


def read_calibration(path: Path) -> CalibrationCapture:
    """The calibration frames of a capture; UserError when it has none or they are incomplete."""
    path = Path(path)
    with open_artefact(path, KIND) as f:
        g = _complete_group(f, path, "calibration", "calibration frames",
                            f"capture {path} holds no calibration frames (capture.calibration was not set when it "
                            "was taken); take them with 'fluxmap capture-surface CONFIG' and capture.calibration.")
        _frame_table(f, path, [f"calibration/{n}" for n in ("committed", "counts", "kind", "series", "exposure_s",
                                                             "em_gain", "stage_height_mm")])
        kind = np.char.decode(g["kind"][()])
        series = g["series"][()]
        counts = g["counts"]
        exposure, gain, height = g["exposure_s"][()], g["em_gain"][()], g["stage_height_mm"][()]
        grid = json.loads(g.attrs["grid"]) or None
        truth = json.loads(g.attrs["truth"]) if "truth" in g.attrs else None

        def stacks(k: str) -> list[tuple[np.ndarray, float, float]]:
            out = []
            for s_ in sorted(set(series[kind == k].tolist())):
                sel = np.flatnonzero((kind == k) & (series == s_))
                out.append((counts[sel[0]:sel[-1] + 1][sel - sel[0]].astype(np.float64),
                            _one_setting(exposure[sel], "exposures (s)", path, k),
                            _one_setting(gain[sel], "EM gains", path, k)))
            return out

        grids = stacks("grid")
        grid_stage = []
        for s_ in sorted(set(series[kind == "grid"].tolist())):
            grid_stage.append(float(height[(kind == "grid") & (series == s_)].mean()))
        bias = stacks("bias")
        flats = stacks("flat")
        darks = stacks("dark")
        ptc = stacks("ptc_off") + stacks("ptc_on")
    return CalibrationCapture(grid if grids else None, [s[0].mean(axis=0) for s in grids], grid_stage,
                              bias[0][0] if bias else None, darks, flats[0][0] if flats else None, ptc, truth, path)
