"""Andor (SDK2, SDK3) and Teledyne Photometrics (PVCAM) cameras through pylablib.

pylablib (``pip install 'fluxmap[cameras]'``, pure Python, on PyPI) wraps each vendor's
own library, which comes with the camera's software, not from a registry:

=============  =====================================  ==========================================
backend        pylablib class                         cameras (vendor library)
=============  =====================================  ==========================================
andor_sdk2     ``Andor.AndorSDK2Camera(idx, ...)``    iXon, Newton, iDus EMCCD/CCD (atmcd64d)
andor_sdk3     ``Andor.AndorSDK3Camera(idx)``         Zyla, Neo, Sona, Marana, Balor sCMOS (atcore)
pvcam          ``Photometrics.PvcamCamera(name)``     Evolve, Prime, Kinetix, Retiga (PVCAM)
=============  =====================================  ==========================================

Each backend maps fluxmap's :class:`~fluxcli.hardware.camera.Camera` onto the pylablib
calls (named as pylablib names them, see the tables in each class) and nothing else; every
call the driver refuses becomes a :class:`~fluxcli.hardware.errors.DeviceError` naming the
camera, how it was selected and what the driver said (exit 2).  Frames are read with rows
counted from the top (pylablib's ``"rct"`` indexing) for every vendor, so row 0 is the top
row as the vendor's own viewer shows it.

What is and is not known: the backends are tested against fakes of these three pylablib
classes (``tests/fake_pylablib.py``: same method names and signatures, checked against the
installed pylablib), driven end to end by ``capture-surface`` and ``rig check``.  That a real
camera answers the way pylablib's documentation says is *unverified* until someone runs
``tests/test_cameras.py`` with ``FLUXMAP_CAMERA=andor_sdk2:0`` (or ``andor_sdk3:0``,
``pvcam:0``) on a rig.
"""

from __future__ import annotations

import importlib
import math
from typing import Any, Callable

import numpy as np

from .camera import Camera, DeviceIdentity
from .errors import DeviceError

__all__ = ["PylablibCamera", "AndorSDK2", "AndorSDK3", "Pvcam", "BACKENDS", "INSTALL_HINT"]

INSTALL_HINT = "pip install 'fluxmap[cameras]'"
_MARGIN_S = 5.0  # seconds beyond the exposure to wait for a frame


class PylablibCamera(Camera):
    """What the three pylablib backends share: selection, exposure, binning, frames, errors.

    Parameters
    ----------
    index : int
        Which camera of this vendor (0 = the first the vendor library lists).
    serial : str or None
        The serial number the camera must report.  With several cameras, the one with this
        serial is chosen (each is opened in turn); none matching is an error naming what
        was found.
    setpoint_c : float
        Sensor temperature set point (deg C); the cooler is switched on at connect.
    driver : module, optional
        The pylablib device module (``pylablib.devices.Andor`` or
        ``pylablib.devices.Photometrics``); imported when not given (tests pass a fake).
    readout_timeout_s : float
        Seconds beyond the exposure to wait for a frame before giving up.
    linux_sdk : bool
        Let pylablib load the vendor's Linux library (pylablib refuses non-Windows vendor
        libraries unless told, calling them untested).
    """

    name = "camera"
    module = ""  # pylablib.devices.<module>
    vendor = ""  # for messages
    error_class = ""  # the module's base error class (every driver error derives from it)

    def __init__(self, index: int = 0, *, serial: str | None = None, setpoint_c: float = -65.0,
                 driver: Any = None, readout_timeout_s: float = _MARGIN_S, linux_sdk: bool = False):
        self.port = f"{self.vendor} camera {index}" + (f" (serial {serial})" if serial else "")
        self._margin_s = float(readout_timeout_s)
        self._cam = None
        if driver is None:
            try:
                driver = importlib.import_module(f"pylablib.devices.{self.module}")
            except ImportError:
                raise self._error(f"the {self.vendor} backend needs pylablib: {INSTALL_HINT} (and the vendor's "
                                  "own library, which comes with the camera's software)") from None
            if linux_sdk:
                import pylablib

                pylablib.par["devices/only_windows_dlls"] = False
        self._driver = driver
        self._cam = self._select(int(index), serial)
        try:
            self._cam.set_image_indexing("rct")
            self._setup(setpoint_c)
        except BaseException:
            self.close()
            raise

    # ---------------------------------------------------------------- plumbing
    def _errors(self) -> tuple[type, ...]:
        """What the driver raises for a device problem: the vendor module's error class (its
        timeouts and "not supported" derive from it) and OSError (the vendor library is
        missing).  Anything else is a bug and is not dressed up as a device error."""
        err = getattr(getattr(self, "_driver", None), self.error_class, None)
        return (err, OSError) if isinstance(err, type) else (OSError,)

    def _call(self, what: str, fn: Callable, *args, **kwargs):
        """``fn(*args, **kwargs)``; a driver error becomes a DeviceError saying ``what`` failed."""
        try:
            return fn(*args, **kwargs)
        except self._errors() as e:
            raise self._error(f"{what} failed", f"{type(e).__name__}: {e}") from None

    def _candidates(self) -> list:
        """Selectors of the cameras this vendor library lists, in its order."""
        raise NotImplementedError

    def _open(self, selector):
        raise NotImplementedError

    def _select(self, index: int, serial: str | None):
        found = self._call("listing the cameras", self._candidates)
        if not found:
            raise self._error(f"no {self.vendor} camera found (is it on, connected, and not open in another program?)")
        if serial is None:
            if index >= len(found):
                raise self._error(f"there is no camera {index}: the {self.vendor} library lists {len(found)}")
            return self._call("connecting", self._open, found[index])
        seen = []
        for sel in found:
            cam = self._call("connecting", self._open, sel)
            self._cam = cam
            got = self.identity().serial
            if got == str(serial):
                return cam
            seen.append(got)
            self._call("closing", cam.close)
            self._cam = None
        raise self._error(f"no camera with serial {serial}; the {self.vendor} library lists serial(s) "
                          f"{', '.join(seen) or 'none'}")

    def _setup(self, setpoint_c: float) -> None:
        """At connect: the sensor set point (and the cooler on), read back."""
        self._call(f"setting the sensor set point to {setpoint_c:g} deg C", self._set_setpoint, float(setpoint_c))
        got = self.setpoint_c
        if got is not None and abs(got - setpoint_c) > 0.5:
            raise self._error(f"set point {setpoint_c:g} deg C was asked for (rig.camera.setpoint_c), the camera "
                              f"set {got:g} deg C (outside its range?)")

    def _set_setpoint(self, t: float) -> None:
        self._cam.set_temperature(t, enable_cooler=True)

    @property
    def setpoint_c(self) -> float | None:
        """The sensor temperature set point the camera reports (deg C), None if it reports none."""
        t = self._call("reading the set point", self._cam.get_temperature_setpoint)
        return None if t is None else float(t)

    # ---------------------------------------------------------------- settings
    @property
    def exposure_s(self) -> float:
        return float(self._call("reading the exposure", self._cam.get_exposure))

    @exposure_s.setter
    def exposure_s(self, value: float) -> None:
        value = float(value)
        if not (math.isfinite(value) and value > 0):
            raise self._error(f"exposure {value!r} s is not a positive number of seconds")
        self._call(f"setting the exposure to {value:g} s", self._cam.set_exposure, value)
        got = self.exposure_s  # cameras round to their clock; capture.h5 records what they set
        if not math.isclose(got, value, rel_tol=1e-2, abs_tol=1e-5):
            raise self._error(f"exposure {value:g} s was asked for, the camera set {got:g} s (outside its range?)")

    @property
    def binning(self) -> int:
        roi = self._call("reading the binning", self._cam.get_roi)
        return int(roi[4])

    @binning.setter
    def binning(self, value: int) -> None:
        b = int(value)
        if b < 1:
            raise self._error(f"binning {value} is not a positive integer")
        roi = self._call(f"setting binning {b}", self._cam.set_roi, hbin=b, vbin=b)
        if roi is None or (int(roi[4]), int(roi[5])) != (b, b):
            got = self._call("reading the binning", self._cam.get_roi)
            raise self._error(f"binning {b} x {b} was not accepted (the camera reports {got[4]} x {got[5]})")

    @property
    def shape(self) -> tuple[int, int]:
        rows, cols = self._call("reading the frame size", self._cam.get_data_dimensions)
        return int(rows), int(cols)

    @property
    def em_gain(self) -> float:
        return 1.0

    @em_gain.setter
    def em_gain(self, value: float) -> None:
        if float(value) != 1.0:
            raise self._error(f"EM gain {float(value):g} was asked for, but this camera has no EM register; set "
                              "capture.em_gain (and capture.surface.em_gain) to 1")

    def _check_gain(self, g: float) -> None:
        lo, hi = self._range
        if not lo <= g <= hi:
            raise self._error(f"EM gain {g:g} is outside rig.camera.em_gain_range {lo:g}..{hi:g}")

    # ---------------------------------------------------------------- frames
    def _frame(self, data) -> np.ndarray:
        a = np.asarray(data)
        if a.size and (a.min() < 0 or a.max() > np.iinfo(np.uint16).max):
            raise self._error(f"a frame holds counts {a.min()}..{a.max()}, outside 16 bits; choose a 16-bit "
                              "readout mode")
        return a.astype(np.uint16, copy=True)

    def _timeout_s(self) -> float:
        return self.exposure_s + self._margin_s

    def snap(self) -> np.ndarray:
        t = self._timeout_s()
        return self._frame(self._call(f"taking a frame (waited up to {t:g} s)", self._cam.snap, timeout=t))

    def sequence(self, n: int) -> np.ndarray:
        n = int(n)
        if n <= 0:
            return np.zeros((0, *self.shape), np.uint16)
        t = self._timeout_s()
        frames = self._call(f"taking a sequence of {n} frames (up to {t:g} s each)", self._cam.grab, n,
                            frame_timeout=t)
        frames = [self._frame(f) for f in frames]
        if len(frames) != n:
            raise self._error(f"a sequence of {n} frames returned {len(frames)}")
        return np.stack(frames)

    def frames(self, n: int):
        """A hardware sequence of ``n`` frames (pylablib's ``sequence`` acquisition, a ring buffer of
        ``n``), each handed over as it is read out; closing early stops the acquisition."""
        n = int(n)
        if n <= 0:
            return
        t = self._timeout_s()
        self._call(f"starting a sequence of {n} frames", self._cam.start_acquisition, mode="sequence", nframes=n)
        try:
            for i in range(n):
                self._call(f"waiting for frame {i + 1} of a sequence of {n} (up to {t:g} s)",
                           self._cam.wait_for_frame, since="lastread", nframes=1, timeout=t)
                yield self._frame(self._call(f"reading frame {i + 1} of a sequence of {n}",
                                             self._cam.read_oldest_image))
        finally:
            try:
                self._cam.stop_acquisition()
            except self._errors():  # stopping must not mask the error that led here
                pass

    def close(self) -> None:
        cam, self._cam = self._cam, None
        if cam is not None:
            try:
                cam.close()
            except self._errors():  # closing must not mask the error that led here
                pass


class _Andor(PylablibCamera):
    """What both Andor SDKs name alike in pylablib: temperature, cooler, shutter read-back."""

    module = "Andor"
    error_class = "AndorError"

    @property
    def temperature_c(self) -> float:
        return float(self._call("reading the sensor temperature", self._cam.get_temperature))

    @property
    def cooler_on(self) -> bool:
        return bool(self._call("reading the cooler", self._cam.is_cooler_on))

    @cooler_on.setter
    def cooler_on(self, value: bool) -> None:
        self._call("switching the cooler " + ("on" if value else "off"), self._cam.set_cooler, bool(value))

    @property
    def shutter_open(self) -> bool:
        return self._call("reading the shutter", self._cam.get_shutter) == "open"

    @shutter_open.setter
    def shutter_open(self, value: bool) -> None:
        self._call(("opening" if value else "closing") + " the shutter (a camera without one: cap the lens for "
                   "darks)", self._set_shutter, "open" if value else "closed")

    def _set_shutter(self, mode: str) -> None:
        raise NotImplementedError


class AndorSDK2(_Andor):
    """An Andor SDK2 camera (iXon EMCCDs) through ``pylablib.devices.Andor.AndorSDK2Camera``.

    ==================  ============================================================
    fluxmap             pylablib (AndorSDK2Camera)
    ==================  ============================================================
    connect             ``AndorSDK2Camera(idx, temperature=setpoint_c, fan_mode=fan)``;
                        ``set_temperature(setpoint_c, enable_cooler=True)``
    exposure_s          ``set_exposure`` / ``get_exposure``
    binning             ``set_roi(hbin=b, vbin=b)`` / ``get_roi()[4:6]``
    em_gain             ``set_EMCCD_gain(gain, advanced)`` / ``get_EMCCD_gain()[0]``
    temperature_c       ``get_temperature()``; ``get_temperature_status()`` in words
    cooler_on           ``set_cooler`` / ``is_cooler_on``
    shutter_open        ``setup_shutter("open" | "closed")`` / ``get_shutter()``
    snap / sequence     ``snap(timeout)`` / ``grab(n, frame_timeout)``
    identity            ``get_device_info()`` (head model, serial); the SDK version
    ==================  ============================================================

    EM gains above 300 need ``em_gain_advanced`` (Andor: strong light can then damage the
    sensor).  The number set is the SDK's EM gain value; that it is the real multiplication
    factor depends on the camera's EM gain mode (*unverified*: calibrate the gain
    radiometrically).
    """

    name = "camera (Andor SDK2)"
    vendor = "Andor SDK2"

    def __init__(self, index: int = 0, *, em_gain_advanced: bool = False, fan: str = "full",
                 em_gain_range: tuple[float, float] = (1.0, 1000.0), **kw):
        self._advanced = bool(em_gain_advanced)
        self._fan = fan
        self._range = (float(em_gain_range[0]), float(em_gain_range[1]))
        self._setpoint = float(kw.get("setpoint_c", -65.0))
        super().__init__(index, **kw)

    def _candidates(self) -> list:
        return list(range(int(self._driver.get_cameras_number_SDK2())))

    def _open(self, idx):
        return self._driver.AndorSDK2Camera(idx, temperature=self._setpoint, fan_mode=self._fan)

    def identity(self) -> DeviceIdentity:
        info = self._call("reading the device info", self._cam.get_device_info)
        sdk = self._call("reading the SDK version", self._driver.get_SDK2_version)
        return DeviceIdentity(str(info.head_model), str(info.serial_number), f"SDK {sdk} (firmware not reported)")

    @property
    def em_gain(self) -> float:
        got = self._call("reading the EM gain", self._cam.get_EMCCD_gain)
        return 1.0 if got is None else float(got[0])  # None: a CCD without an EM register

    @em_gain.setter
    def em_gain(self, value: float) -> None:
        g = float(value)
        self._check_gain(g)
        if g > 300 and not self._advanced:
            raise self._error(f"EM gain {g:g} is above 300, which Andor allows only in advanced mode (strong light "
                              "can then damage the sensor); set rig.camera.em_gain_advanced: true to allow it")
        self._call(f"setting the EM gain to {g:g}", self._cam.set_EMCCD_gain, int(round(g)),
                   advanced=(g > 300) if self._advanced else None)
        got = self.em_gain
        if got != int(round(g)):
            raise self._error(f"EM gain {g:g} was asked for, the camera reports {got:g}")

    @property
    def cooling_status(self) -> str:
        return str(self._call("reading the temperature status", self._cam.get_temperature_status))

    def _set_shutter(self, mode: str) -> None:
        self._cam.setup_shutter(mode)


class AndorSDK3(_Andor):
    """An Andor SDK3 camera (sCMOS: Zyla, Sona, Marana, ...) through
    ``pylablib.devices.Andor.AndorSDK3Camera``.

    ==================  ============================================================
    fluxmap             pylablib (AndorSDK3Camera)
    ==================  ============================================================
    connect             ``AndorSDK3Camera(idx)``; ``set_temperature(setpoint_c)``
    exposure_s          ``set_exposure`` / ``get_exposure``
    binning             ``set_roi(hbin=b, vbin=b)`` / ``get_roi()[4:6]``
    em_gain             none: an sCMOS has no EM register (1 only)
    temperature_c       ``get_temperature()``
    cooler_on           ``set_cooler`` / ``is_cooler_on``
    shutter_open        ``set_shutter("open" | "closed")`` / ``get_shutter()``
    snap / sequence     ``snap(timeout)`` / ``grab(n, frame_timeout)``
    identity            ``get_device_info()``: model, serial, firmware
    ==================  ============================================================

    Many sCMOS heads have no mechanical shutter: then closing it fails naming the camera
    (take darks with the lens capped).  SDK3 set points are fixed lists on some models
    (``TemperatureControl``); the one set is read back and reported.
    """

    name = "camera (Andor SDK3)"
    vendor = "Andor SDK3"

    def _candidates(self) -> list:
        return list(range(int(self._driver.get_cameras_number_SDK3())))

    def _open(self, idx):
        return self._driver.AndorSDK3Camera(idx)

    def identity(self) -> DeviceIdentity:
        info = self._call("reading the device info", self._cam.get_device_info)
        return DeviceIdentity(f"{info.camera_model} ({info.camera_name})", str(info.serial_number),
                              str(info.firmware_version))

    def _set_shutter(self, mode: str) -> None:
        self._cam.set_shutter(mode)


# PVCAM's PARAM_SHTR_OPEN_MODE values (pvcam_defs.PL_SHTR_OPEN_MODES)
_OPEN_NEVER, _OPEN_PRE_EXPOSURE = 0, 1


class Pvcam(PylablibCamera):
    """A Teledyne Photometrics camera through ``pylablib.devices.Photometrics.PvcamCamera``.

    ==================  ============================================================
    fluxmap             pylablib (PvcamCamera) and PVCAM parameters
    ==================  ============================================================
    connect             ``PvcamCamera(name)`` (name from ``list_cameras()``);
                        ``set_temperature(setpoint_c)``
    exposure_s          ``set_exposure`` / ``get_exposure``
    binning             ``set_roi(hbin=b, vbin=b)`` / ``get_roi()[4:6]``
    em_gain             ``GAIN_MULT_FACTOR`` (EMCCDs: Evolve); none: 1 only
    temperature_c       ``get_temperature()``
    cooler_on           always on (PVCAM has no cooler switch); asking off fails
    shutter_open        ``SHTR_OPEN_MODE``: pre-exposure (open) / never (closed)
    snap / sequence     ``snap(timeout)`` / ``grab(n, frame_timeout)``
    identity            ``get_device_info()`` (product, serial), ``CAM_FW_VERSION``
    ==================  ============================================================
    """

    name = "camera (PVCAM)"
    module = "Photometrics"
    vendor = "PVCAM"
    error_class = "PvcamError"

    def __init__(self, index: int = 0, *, em_gain_range: tuple[float, float] = (1.0, 1000.0), **kw):
        self._range = (float(em_gain_range[0]), float(em_gain_range[1]))
        super().__init__(index, **kw)

    def _candidates(self) -> list:
        return list(self._driver.list_cameras())

    def _open(self, name):
        return self._driver.PvcamCamera(name)

    def _set_setpoint(self, t: float) -> None:
        self._cam.set_temperature(t)

    def _param(self, name: str, default=None):
        return self._call(f"reading {name}", self._cam.get_attribute_value, name, error_on_missing=False,
                          default=default, enum_as_str=False)

    def identity(self) -> DeviceIdentity:
        info = self._call("reading the device info", self._cam.get_device_info)
        fw = self._param("CAM_FW_VERSION")
        return DeviceIdentity(f"{info.vendor} {info.product}".strip(), str(info.serial or ""),
                              "" if fw is None else str(fw))

    @property
    def em_gain(self) -> float:
        g = self._param("GAIN_MULT_FACTOR")
        return 1.0 if g is None else float(g)

    @em_gain.setter
    def em_gain(self, value: float) -> None:
        g = float(value)
        if self._param("GAIN_MULT_FACTOR") is None:
            PylablibCamera.em_gain.fset(self, g)  # no EM register: 1 only
            return
        self._check_gain(g)
        self._call(f"setting GAIN_MULT_FACTOR to {g:g}", self._cam.set_attribute_value, "GAIN_MULT_FACTOR",
                   int(round(g)), truncate=False)
        got = self.em_gain
        if got != int(round(g)):
            raise self._error(f"EM gain {g:g} was asked for, the camera reports {got:g}")

    @property
    def temperature_c(self) -> float:
        t = self._call("reading the sensor temperature", self._cam.get_temperature)
        if t is None:
            raise self._error("the camera does not report its sensor temperature (PVCAM parameter TEMP)")
        return float(t)

    @property
    def cooler_on(self) -> bool:
        return True

    @cooler_on.setter
    def cooler_on(self, value: bool) -> None:
        if not value:
            raise self._error("PVCAM cannot switch the cooler off from software (only the set point)")

    @property
    def cooling_status(self) -> str:
        sp = self._call("reading the set point", self._cam.get_temperature_setpoint)
        return "on (always)" + ("" if sp is None else f", set point {float(sp):g} deg C")

    @property
    def shutter_open(self) -> bool:
        mode = self._param("SHTR_OPEN_MODE")
        return mode is not None and int(mode) != _OPEN_NEVER

    @shutter_open.setter
    def shutter_open(self, value: bool) -> None:
        if self._param("SHTR_OPEN_MODE") is None:
            if value:
                return  # no shutter: always open
            raise self._error("the camera has no shutter (PVCAM parameter SHTR_OPEN_MODE): cap the lens for darks")
        self._call(("opening" if value else "closing") + " the shutter", self._cam.set_attribute_value,
                   "SHTR_OPEN_MODE", _OPEN_PRE_EXPOSURE if value else _OPEN_NEVER, truncate=False)


# rig.camera.backend -> class
BACKENDS: dict[str, type[PylablibCamera]] = {"andor_sdk2": AndorSDK2, "andor_sdk3": AndorSDK3, "pvcam": Pvcam}
