"""The EMCCD camera: one interface, a simulated backend (the default) and a DCAM backend.

:class:`Camera` is what acquisition talks to: exposure, binning, EM gain, sensor
temperature and cooler, a shutter for dark frames, ``snap()`` and ``sequence(n)``, each
frame a ``uint16`` array ``[ny, nx]`` (row 0 first, as the camera reads out).

:class:`SimulatedEmccd` renders what the real camera would see.  It is given a
``render(height_mm, filter_name, projectors=..., binning=...)`` function (expected photons
per pixel per second, from fluxmap's forward model for the emission and the ray-cast
structured-light renderer for what the projectors shine) and read-outs of the rig's
*physical* state (the stage height, the filter in the beam, the pattern each projector
shows), so an image follows where the stage actually is and what is projected, not what
was asked for.  The photons then go through the EMCCD chain of
:mod:`fluxcli.imaging.noise`, seeded by (seed, frame index): the same plan and seed give
the same bytes, frame by frame, however often the run was interrupted and resumed.

Real cameras: the Hamamatsu ImagEM through the vendor's DCAM-API
(:mod:`fluxcli.hardware.dcam`); Andor (SDK2: iXon EMCCDs; SDK3: Zyla, Sona, Marana sCMOS)
and Teledyne Photometrics (PVCAM) through pylablib (:mod:`fluxcli.hardware.pylablib_cameras`).
:func:`fluxcli.hardware.cameras.open_camera` picks one from ``rig.camera.backend``.
"""

from __future__ import annotations

import math
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np

from ..imaging import noise as N
from .errors import DeviceError

__all__ = ["Camera", "DeviceIdentity", "SimulatedEmccd", "dark_current_at"]


@dataclass(frozen=True)
class DeviceIdentity:
    """What a device says it is (``""`` where it does not say)."""

    model: str
    serial: str = ""
    firmware: str = ""


class Camera(ABC):
    """What acquisition needs from an EMCCD camera.

    Settable: ``exposure_s`` (s), ``binning`` (n for n x n), ``em_gain`` (EM register gain,
    dimensionless), ``cooler_on``, ``shutter_open``.  Read-only: ``temperature_c`` (the
    sensor temperature, deg C, read from the camera), ``shape`` ``(ny, nx)`` of a frame.
    Every failure raises :class:`~fluxcli.hardware.errors.DeviceError` naming the camera.
    """

    name = "camera"
    port = "in-process"

    def _error(self, problem: str, said: str | None = None) -> DeviceError:
        return DeviceError(self.name, self.port, problem, said, show_said=said is not None)

    exposure_s: float
    binning: int
    em_gain: float
    cooler_on: bool
    shutter_open: bool

    @property
    @abstractmethod
    def temperature_c(self) -> float:
        """Sensor temperature read from the camera (deg C)."""

    @property
    @abstractmethod
    def shape(self) -> tuple[int, int]:
        """``(ny, nx)`` of a frame at the current binning."""

    @abstractmethod
    def snap(self) -> np.ndarray:
        """Expose once and read out: ``uint16`` counts ``[ny, nx]``."""

    def sequence(self, n: int) -> np.ndarray:
        """``n`` frames in a row: ``uint16`` counts ``[n, ny, nx]``."""
        return np.stack([self.snap() for _ in range(int(n))]) if n > 0 else np.zeros((0, *self.shape), np.uint16)

    def frames(self, n: int):
        """``n`` frames in a row, handed over one at a time as each is read out (``uint16``
        ``[ny, nx]``), so the caller can commit each before the next and stop between any two.
        Closing the generator early ends the sequence.  The default takes them one ``snap`` at a
        time; a camera that streams a sequence in hardware overrides it."""
        for _ in range(int(n)):
            yield self.snap()

    def set_frame_index(self, index: int) -> None:
        """The plan index of the next frame.  Simulated cameras key their noise on it (so a
        resumed run repeats the same frames); real cameras ignore it."""

    def make_safe(self) -> None:
        """Close the shutter (what an interrupted acquisition leaves behind)."""
        self.shutter_open = False

    def identity(self) -> DeviceIdentity:
        """Model, serial number and firmware, as the camera reports them."""
        return DeviceIdentity(self.name)

    @property
    def cooling_status(self) -> str:
        """The cooler in words ("on", "off", or the camera's own word: "stabilized", ...)."""
        return "on" if self.cooler_on else "off"

    def close(self) -> None:
        """Release the camera."""


def dark_current_at(temperature_c: float, *, reference_e_per_s: float, reference_c: float,
                    doubling_c: float) -> float:
    """Dark current (electrons/s per pixel) at a sensor temperature.

    Silicon dark current roughly doubles every ``doubling_c`` degrees (about 6-7 deg C for
    CCDs near room temperature and below); ``reference_e_per_s`` holds at ``reference_c``.
    """
    return reference_e_per_s * 2.0 ** ((temperature_c - reference_c) / doubling_c)


class SimulatedEmccd(Camera):
    name = "camera (simulated EMCCD)"

    """An EMCCD that renders the rig's scene through the forward model, with EMCCD noise.

    Parameters
    ----------
    render : callable ``(height_mm, filter_name) -> ndarray [ny, nx]``, and with
        ``projectors`` (or a binning finer than the native one) ``(height_mm, filter_name, *,
        projectors, binning)``
        Expected photons per pixel per second reaching the sensor with the stage at
        ``height_mm`` (mm), filter ``filter_name`` in the beam, ``projectors`` (a dict
        projector name -> the pattern ``[height_px, width_px]`` it shows; only projectors
        showing something other than black) and the camera at ``binning``.
    stage_height_mm : callable ``() -> float``
        The stage's physical height (mm) right now (the simulator's state, or a read-back).
    filter_name : callable ``() -> str``
        The filter physically in the beam right now.
    projectors : callable ``() -> dict``, optional
        What the projectors show right now (name -> pattern; black ones left out).
    sensor : fluxcli.imaging.noise.EMCCDModel
        The detector: QE, read noise, bias, electrons per count, CIC, bit depth, and the
        dark current ``dark_current_e_per_s`` that holds at ``setpoint_c``.
        Its ``em_gain`` and ``exposure_s`` are only the initial settings.
    seed : int
        Frame ``k`` draws its noise from ``numpy.random.default_rng([seed, k])``.
    native_binning : int
        The binning of ``shape`` (system.camera's pixel grid).  Finer binnings that divide
        it are accepted (``render`` is asked for that binning: structured light at full
        resolution); coarser ones are refused (not needed).
    setpoint_c, ambient_c : float
        Sensor temperature with the cooler on / off (deg C).  The cool-down is not
        modelled: the simulated sensor is at its set point as soon as the cooler is on.
    dark_doubling_c : float
        Dark current doubles per this many deg C (see :func:`dark_current_at`).
    em_gain_range : (float, float)
        Accepted EM gains.
    time_scale : float
        The exposure takes ``exposure_s * time_scale`` seconds of wall time.
    shape : (int, int), optional
        ``(ny, nx)`` of ``render``'s images, when known without rendering one.
    """

    def __init__(self, render: Callable[[float, str], np.ndarray], *, stage_height_mm: Callable[[], float],
                 filter_name: Callable[[], str], sensor: N.EMCCDModel, seed: int = 0, native_binning: int = 1,
                 projectors: Callable[[], dict] | None = None,
                 setpoint_c: float = -65.0, ambient_c: float = 20.0, dark_doubling_c: float = 6.3,
                 em_gain_range: tuple[float, float] = (1.0, 1200.0), time_scale: float = 1.0,
                 shape: tuple[int, int] | None = None):
        self._render = render
        self._height = stage_height_mm
        self._filter = filter_name
        self._projectors = projectors
        self._sensor = sensor
        self._seed = int(seed)
        self._native_binning = int(native_binning)
        self._setpoint_c = float(setpoint_c)
        self._ambient_c = float(ambient_c)
        self._doubling_c = float(dark_doubling_c)
        self._gain_range = (float(em_gain_range[0]), float(em_gain_range[1]))
        self._time_scale = float(time_scale)
        self._exposure_s = float(sensor.exposure_s)
        self._em_gain = float(sensor.em_gain)
        self._binning = self._native_binning
        self.cooler_on = True
        self.shutter_open = False
        self._next_frame = 0
        self._shape = None if shape is None else (int(shape[0]), int(shape[1]))

    # ---------------------------------------------------------------- settings
    @property
    def exposure_s(self) -> float:
        return self._exposure_s

    @exposure_s.setter
    def exposure_s(self, value: float) -> None:
        value = float(value)
        if not (math.isfinite(value) and value > 0):
            raise self._error(f"exposure {value!r} s is not a positive number of seconds")
        self._exposure_s = value

    @property
    def em_gain(self) -> float:
        return self._em_gain

    @em_gain.setter
    def em_gain(self, value: float) -> None:
        value = float(value)
        lo, hi = self._gain_range
        if not lo <= value <= hi:
            raise self._error(f"EM gain {value:g} is outside the camera's range {lo:g}..{hi:g}")
        self._em_gain = value

    @property
    def binning(self) -> int:
        return self._binning

    @binning.setter
    def binning(self, value: int) -> None:
        if int(value) < 1 or self._native_binning % int(value):
            raise self._error(f"the simulated camera renders system.camera's pixel grid (binning "
                              f"{self._native_binning}) or finer grids dividing it; binning {value} was asked for")
        self._binning = int(value)

    @property
    def temperature_c(self) -> float:
        return self._setpoint_c if self.cooler_on else self._ambient_c

    @property
    def shape(self) -> tuple[int, int]:
        if self._shape is None:
            b, self._binning = self._binning, self._native_binning
            try:
                self._shape = tuple(np.shape(self._expected_photons(open_shutter=False)))  # type: ignore[assignment]
            finally:
                self._binning = b
        k = self._native_binning // self._binning
        return (self._shape[0] * k, self._shape[1] * k)  # type: ignore[index]

    def set_frame_index(self, index: int) -> None:
        self._next_frame = int(index)

    def identity(self) -> DeviceIdentity:
        return DeviceIdentity("simulated EMCCD (fluxcli.hardware.camera.SimulatedEmccd)", "none", "fluxmap")

    # ---------------------------------------------------------------- frames
    def model(self) -> N.EMCCDModel:
        """The EMCCD chain at the current settings and sensor temperature."""
        dark = dark_current_at(self.temperature_c, reference_e_per_s=self._sensor.dark_current_e_per_s,
                               reference_c=self._setpoint_c, doubling_c=self._doubling_c)
        return replace(self._sensor, em_gain=self._em_gain, exposure_s=self._exposure_s, dark_current_e_per_s=dark)

    def _expected_photons(self, *, open_shutter: bool) -> np.ndarray:
        if not open_shutter and self._shape is not None:
            return np.zeros(self.shape)  # a dark frame: nothing to render
        h, f = float(self._height()), str(self._filter())
        if self._projectors is None and self._binning == self._native_binning:  # emission only
            rate = np.asarray(self._render(h, f), dtype=np.float64)
        else:
            rate = np.asarray(self._render(h, f, projectors=self._projectors() if self._projectors else {},
                                           binning=self._binning), dtype=np.float64)
        want = self.shape if self._shape is not None else None
        if rate.ndim != 2 or (want is not None and rate.shape != want):
            raise ValueError(f"render must return a 2-D image {want or '[ny, nx]'}, got shape {rate.shape}")
        return rate * self._exposure_s if open_shutter else np.zeros_like(rate)

    def snap(self) -> np.ndarray:
        photons = self._expected_photons(open_shutter=self.shutter_open)
        rng = np.random.default_rng([self._seed, self._next_frame])
        self._next_frame += 1
        if self._time_scale > 0:
            time.sleep(self._exposure_s * self._time_scale)
        # EM gain 1 is the gain off (calibration's bias, flat and gain-off PTC frames): no multiplication,
        # F^2 = 1, read as a conventional CCD
        read = N.conventional_counts if self._em_gain <= 1.0 else N.emccd_counts
        return read(photons, self.model(), rng)
