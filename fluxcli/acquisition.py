"""Crash-safe acquisition of emission images: the plan, ``capture.h5``, the frame loop, the reader.

The plan (:class:`Plan`) lists every frame: first the dark frames (shutter closed) of each
exposure time, then for each stage height, each filter, each exposure, ``repeats`` frames.  Frame ``k`` of the plan has slot
``k`` in ``capture.h5``:

``/frames/counts``           uint16 ``[n_frames, ny, nx]`` ADC counts, row 0 first
``/frames/<metadata>``       per frame, read back from the devices after the exposure:
                             ``time_unix`` (s), ``stage_height_mm``, ``filter_position``,
                             ``filter_name``, ``exposure_s``, ``em_gain``, ``temperature_c``,
                             ``shutter_open``
``/frames/committed``        uint8 ``[n_frames]``: 1 once the frame and its metadata are durable
``/plan/...``                what each slot is meant to hold (dark, height_mm, filter, repeat)
``/truth/<filter>/power``    (simulated camera only) photons per element per second

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
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable

import h5py
import numpy as np

from . import artefacts as A
from .errors import UserError
from .imaging import noise as N

__all__ = ["Frame", "Plan", "CaptureFile", "RigDevices", "acquire", "read_capture", "CaptureImages", "Interrupted"]

KIND = "capture"
_META = {  # per-frame metadata read back from the devices (units: artefacts.kinds "capture")
    "time_unix": "f8", "stage_height_mm": "f8", "filter_position": "i4", "filter_name": "S32",
    "exposure_s": "f8", "em_gain": "f8", "temperature_c": "f8", "shutter_open": "u1",
}


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

    def frames(self) -> list[Frame]:
        out: list[Frame] = []
        for e in self.exposures_s:
            for r in range(self.darks):
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
        return [f"{names.get(k, 'capture.' + k)}: file has {other.get(k)!r}, config has {mine[k]!r}"
                for k in mine if other.get(k) != mine[k]]


@dataclass
class RigDevices:
    """The devices acquisition drives, and how filter names map to wheel positions."""

    stage: object  # .move_to_mm(z) -> float, .position_mm() -> float, .stop()
    wheel: object  # .move_to(pos) -> int, .position -> int
    camera: object  # fluxcli.hardware.camera.Camera
    filter_positions: dict[str, int] = field(default_factory=dict)

    def filter_name(self, position: int) -> str:
        for name, p in self.filter_positions.items():
            if p == position:
                return name
        return f"position {position}"


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

    # ------------------------------------------------------------ create / open
    @classmethod
    def create(cls, path: Path, plan: Plan, *, config_sha256: str = "", provenance: A.Provenance | None = None,
               truth: dict[str, np.ndarray] | None = None, truth_unit: str = "", pause_s: float = 0.0) -> "CaptureFile":
        """Write the whole skeleton under a temporary name, then rename it to ``path``
        (the artefacts' atomic writer: fsync, rename, fsync of the folder).

        ``pause_s`` sleeps between the creation steps; the kill test uses it to land
        SIGKILLs inside the creation window (0 otherwise)."""
        path = Path(path)
        frames = plan.frames()
        n, (ny, nx) = len(frames), plan.shape
        with A.write_artefact(path, KIND, config_sha256=config_sha256, provenance=provenance) as f:
            f.attrs["plan"] = json.dumps(plan.as_dict(), sort_keys=True)
            f.attrs["layout"] = "frames/counts[frame, row, col]; frame k is plan slot k; committed[k] = 1 when durable"
            time.sleep(pause_s)
            A.put(f, "plan/dark", np.array([fr.dark for fr in frames], np.uint8))
            A.put(f, "plan/height_mm", np.array([fr.height_mm for fr in frames], float))
            A.put(f, "plan/filter", np.array([fr.filter.encode() for fr in frames], "S32"))
            A.put(f, "plan/repeat", np.array([fr.repeat for fr in frames], np.int32))
            A.put(f, "plan/exposure_s", np.array([fr.exposure_s for fr in frames], float))
            # data= writes the zeros: contiguous storage allocated now, so writing a frame
            # later changes no HDF5 metadata
            A.put(f, "frames/counts", np.zeros((n, ny, nx), np.uint16))
            time.sleep(pause_s)
            for name, dtype in _META.items():
                A.put(f, f"frames/{name}", np.zeros(n, dtype))
            A.put(f, "frames/committed", np.zeros(n, np.uint8))
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
        with A.open_artefact(path, KIND) as f:
            stored = json.loads(f.attrs["plan"])
        diff = plan.differences(stored)
        if diff:
            raise UserError(f"capture-surface --resume: {path} was captured with another plan, so it cannot be "
                            f"continued: {'; '.join(diff)}. Restore the plan, or start over with --force.")
        return cls._open(path, plan)

    # ------------------------------------------------------------ frames
    def write_frame(self, index: int, counts: np.ndarray, meta: dict) -> None:
        """Store frame ``index`` durably, then mark it committed (last)."""
        if counts.shape != self.plan.shape:
            raise ValueError(f"frame {index} is {counts.shape}, the plan's frames are {self.plan.shape}")
        g = self._f["frames"]
        g["counts"][index] = counts
        for name in _META:
            g[name][index] = meta[name]
        _fsync(self._f)
        g["committed"][index] = 1
        _fsync(self._f)
        self.committed[index] = True

    def close(self) -> None:
        self._f.close()


# ------------------------------------------------------------------ the frame loop
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
    if not todo:
        return 0
    try:
        on_step("camera settings")
        cam.cooler_on = True
        cam.em_gain = plan.em_gain
        for fr in todo:
            if stop_requested():
                raise Interrupted(fr.label)
            if fr.dark:
                cam.shutter_open = False
            else:
                pos = rig.filter_positions[fr.filter]
                if rig.wheel.position != pos:
                    on_step(f"filter -> {fr.filter}")
                    rig.wheel.move_to(pos)
                if abs(rig.stage.position_mm() - fr.height_mm) > height_tolerance_mm:
                    on_step(f"stage -> {fr.height_mm:g} mm")
                    rig.stage.move_to_mm(fr.height_mm)
                cam.shutter_open = True
            if cam.exposure_s != fr.exposure_s:
                cam.exposure_s = fr.exposure_s
            on_step(fr.label)
            cam.set_frame_index(fr.index)
            counts = cam.snap()
            t = time.time()
            position = int(rig.wheel.position)
            meta = {"time_unix": t, "stage_height_mm": float(rig.stage.position_mm()), "filter_position": position,
                    "filter_name": rig.filter_name(position).encode()[:32], "exposure_s": float(cam.exposure_s),
                    "em_gain": float(cam.em_gain), "temperature_c": float(cam.temperature_c),
                    "shutter_open": int(bool(cam.shutter_open))}
            out.write_frame(fr.index, np.asarray(counts), meta)
            taken += 1
            on_frame(fr)
    except BaseException:
        _make_safe(rig, report=False)  # what went wrong first is what the user must read
        raise
    _make_safe(rig)
    return taken


def _make_safe(rig: RigDevices, report: bool = True) -> None:
    """Shutter closed and stage stopped, each tried even when the other fails."""
    errors = []
    for action in (rig.camera.make_safe, rig.stage.stop):
        try:
            action()
        except Exception as e:  # keep going: the other device must still be made safe
            errors.append(e)
    if errors and report:
        raise errors[0]


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

    def photons(self, sensor: "N.EMCCDModel") -> tuple[np.ndarray, np.ndarray]:
        """Photons per pixel per exposure ``(P, ny, nx)`` and the mask of usable pixels.

        The mean dark frame (bias + dark current + clock-induced charge, taken at the same
        exposure and gain) is subtracted, then electrons = counts x electrons_per_count /
        EM gain and photons = electrons / QE: ``N = (C - D) g / (G QE)``, unbiased since
        E[C] - E[D] = G QE N / g.  ``sensor`` gives QE, electrons per count and bit depth;
        the gain is the one read back from the camera.  Pixels that saturated in any
        repeat are masked."""
        model = replace(sensor, em_gain=self.em_gain, exposure_s=self.exposure_s, bias_counts=self.dark_mean_counts,
                        dark_current_e_per_s=0.0, cic_e_per_pixel=0.0)
        valid = ~N.saturated(self.counts_max, model)
        return N.counts_to_photons(self.counts_mean, model), valid


def read_capture(path: Path, filter: str | None = None, exposure_s: float | None = None) -> CaptureImages:
    """Read a complete capture: per planned height the mean of its light frames for ``filter``
    at ``exposure_s``, and the mean of the dark frames at that exposure.

    Raises UserError when the capture is incomplete, has no dark frames, or ``filter`` /
    ``exposure_s`` is not one of its own (``None`` is allowed when it has only one)."""
    path = Path(path)
    with A.open_artefact(path, KIND) as f:
        plan = json.loads(f.attrs["plan"])
        committed = f["frames/committed"][()].astype(bool)
        if not committed.all():
            raise UserError(f"capture {path} is incomplete: {committed.sum()} of {committed.size} frames; finish it "
                            "with 'fluxmap capture-surface CONFIG --resume'.")
        filter = _one_of(path, "filter", filter, list(plan["filters"]))
        exposure_s = float(_one_of(path, "exposure_s", exposure_s, [float(e) for e in plan["exposures_s"]]))
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
