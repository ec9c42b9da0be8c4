"""Fakes of the pylablib camera classes fluxmap drives: ``Andor`` (``AndorSDK2Camera``,
``AndorSDK3Camera``) and ``Photometrics`` (``PvcamCamera``), as modules.

The vendor libraries behind pylablib (atmcd64d, atcore, PVCAM) come with the cameras'
software, not from a registry, so the backends are tested against these stand-ins.  They
keep pylablib's method names, signatures and return types (``tests/test_cameras.py``
compares the signatures with the installed pylablib), raise the vendor module's error
classes (all deriving from pylablib's ``DeviceError``, a ``RuntimeError``), and synthesise
frames from their own state, so a frame shows the settings the camera actually had:

    counts = bias + G (rate_e * b^2 * exposure * [shutter open] + dark_e * exposure) / e_per_count

with Poisson electrons (``rate_e`` per native pixel per second, ``b`` the binning, ``G``
the EM gain, 1 for sCMOS).  What they *cannot* show: that the real cameras behave so.

Use ``reset(...)`` before each test; ``state.calls`` records every call as
``(class, method, args...)``; ``state.fail[method] = exception`` makes that method raise
once; ``state.stall_frames`` makes every frame time out.
"""

from __future__ import annotations

import collections
import types

import numpy as np


class DeviceError(RuntimeError):
    """pylablib.core.devio.base.DeviceError"""


class AndorError(DeviceError):
    pass


class AndorTimeoutError(AndorError):
    pass


class AndorNotSupportedError(AndorError):
    pass


class PvcamError(DeviceError):
    pass


class PvcamTimeoutError(PvcamError):
    pass


class _State:
    def __init__(self, **kw):
        self.sdk2_serials = ["X-1234"]  # one serial per connected camera
        self.sdk3_serials = ["VSC-0042"]
        self.pvcam_cameras = {"PMUSBCam00": "A19B204001"}  # PVCAM name -> serial
        self.pvcam_em = True  # an EMCCD (Evolve): GAIN_MULT_FACTOR exists
        self.sdk3_shutter = True  # the sCMOS head has a shutter
        self.detector = (128, 96)  # (width, height) native pixels
        self.rate_e = 50.0  # electrons per native pixel per second with the shutter open
        self.dark_e = 0.5
        self.bias = 100.0
        self.e_per_count = 4.0
        self.ambient_c = 20.0
        self.calls: list = []
        self.fail: dict = {}
        self.stall_frames = False
        self.open = 0
        self.seed = 0
        self.__dict__.update(kw)


state = _State()


def reset(**kw) -> _State:
    global state
    state = _State(**kw)
    return state


class _Camera:
    """What pylablib's ICamera / IBinROICamera / IExposureCamera give every camera."""

    Error = DeviceError
    TimeoutError = DeviceError
    _maxbin = 8

    def __init__(self):
        self._indexing = "rct"
        self._exposure = 0.0
        self._roi = (0, state.detector[0], 0, state.detector[1], 1, 1)
        self._shutter = "closed"
        self._cooler = False
        self._setpoint = 0.0
        self._gain = 1
        self._opened = True
        self._frames = 0
        state.open += 1

    def _call(self, method, *args):
        state.calls.append((type(self).__name__, method, *args))
        err = state.fail.pop(method, None)
        if err is not None:
            raise err
        if not self._opened:
            raise self.Error("camera is not opened")

    # ICamera
    def set_image_indexing(self, indexing):
        self._call("set_image_indexing", indexing)
        self._indexing = indexing
        return indexing

    def get_image_indexing(self):
        return self._indexing

    def get_data_dimensions(self):
        self._call("get_data_dimensions")
        h0, h1, v0, v1, hb, vb = self._roi
        rows, cols = (v1 - v0) // vb, (h1 - h0) // hb
        return (rows, cols) if self._indexing.startswith("rc") else (cols, rows)

    def get_detector_size(self):
        return state.detector

    def close(self):
        state.calls.append((type(self).__name__, "close"))
        if self._opened:
            self._opened = False
            state.open -= 1

    def is_opened(self):
        return self._opened

    # IExposureCamera
    def set_exposure(self, exposure):
        self._call("set_exposure", exposure)
        self._exposure = float(exposure)
        return self.get_exposure()

    def get_exposure(self):
        return self._exposure

    # IBinROICamera
    def get_roi(self):
        return self._roi

    def set_roi(self, hstart=0, hend=None, vstart=0, vend=None, hbin=1, vbin=1):
        self._call("set_roi", hstart, hend, vstart, vend, hbin, vbin)
        w, h = state.detector
        hbin, vbin = max(1, min(hbin, self._maxbin)), max(1, min(vbin, self._maxbin))  # truncated, like the real ones
        hend = w if hend is None else hend
        vend = h if vend is None else vend
        self._roi = (hstart, hstart + (hend - hstart) // hbin * hbin, vstart, vstart + (vend - vstart) // vbin * vbin,
                     hbin, vbin)
        return self._roi

    # frames
    def _gain_factor(self) -> float:
        return 1.0

    def _temperature(self) -> float:
        return self._setpoint if self._cooler else state.ambient_c

    def _one_frame(self) -> np.ndarray:
        rows, cols = self.get_data_dimensions()
        b = self._roi[4] * self._roi[5]
        lit = state.rate_e * b * self._exposure if self._shutter == "open" else 0.0
        rng = np.random.default_rng([state.seed, self._frames])
        self._frames += 1
        electrons = rng.poisson(lit + state.dark_e * self._exposure, size=(rows, cols))
        counts = state.bias + self._gain_factor() * electrons / state.e_per_count
        return np.clip(np.round(counts), 0, 65535).astype(np.uint16)

    def grab(self, nframes=1, frame_timeout=5., missing_frame="skip", return_info=False, buff_size=None):
        self._call("grab", nframes, frame_timeout)
        if state.stall_frames:
            raise self.TimeoutError(f"timeout while waiting for a frame ({frame_timeout} s)")
        return [self._one_frame() for _ in range(nframes)]

    # a streamed acquisition (pylablib's IAcqCamera): what Camera.frames drives
    def start_acquisition(self, *args, **kwargs):
        self._call("start_acquisition", kwargs.get("mode"), kwargs.get("nframes"))
        self._acq = {"left": int(kwargs.get("nframes") or 1), "ready": 0}

    def wait_for_frame(self, since="lastread", nframes=1, timeout=20., error_on_stopped=False):
        self._call("wait_for_frame", since, nframes, timeout)
        acq = getattr(self, "_acq", None)
        if acq is None or state.stall_frames or acq["left"] <= 0:
            raise self.TimeoutError(f"timeout while waiting for a frame ({timeout} s)")
        acq["left"] -= 1
        acq["ready"] += 1

    def read_oldest_image(self, peek=False, return_info=False):
        self._call("read_oldest_image")
        acq = getattr(self, "_acq", None)
        if acq is None or acq["ready"] <= 0:
            return None
        acq["ready"] -= 1
        return self._one_frame()

    def stop_acquisition(self):
        self._call("stop_acquisition")
        self._acq = None

    def snap(self, timeout=5., return_info=False):
        self._call("snap", timeout)
        if state.stall_frames:
            raise self.TimeoutError(f"timeout while waiting for a frame ({timeout} s)")
        return self._one_frame()


# ------------------------------------------------------------------ Andor
SDK2DeviceInfo = collections.namedtuple("TDeviceInfo", ["controller_model", "head_model", "serial_number"])
SDK3DeviceInfo = collections.namedtuple("TDeviceInfo", ["camera_name", "camera_model", "serial_number",
                                                        "firmware_version", "software_version"])


class _AndorCamera(_Camera):
    """What AndorSDK2Camera and AndorSDK3Camera share."""

    Error = AndorError
    TimeoutError = AndorTimeoutError

    def get_temperature_setpoint(self):
        return self._setpoint

    def get_temperature(self):
        self._call("get_temperature")
        return float(self._temperature())

    def is_cooler_on(self):
        self._call("is_cooler_on")
        return self._cooler

    def set_cooler(self, on=True):
        self._call("set_cooler", on)
        self._cooler = bool(on)
        return self._cooler


class AndorSDK2Camera(_AndorCamera):
    """pylablib.devices.Andor.AndorSDK2Camera (an iXon Ultra 888)."""

    Error = AndorError
    TimeoutError = AndorTimeoutError
    _range = (-100, 20)

    def __init__(self, idx=0, ini_path="", temperature=None, fan_mode="off", amp_mode=None):
        if idx >= len(state.sdk2_serials):
            raise AndorError(f"camera index {idx} is not available ({len(state.sdk2_serials)} cameras exist)")
        super().__init__()
        self.idx = idx
        self._fan = fan_mode
        self._advanced = False
        state.calls.append(("AndorSDK2Camera", "__init__", idx, temperature, fan_mode))
        if temperature is None:  # what pylablib does at connect: 20 % up the range, cooler on
            self.set_temperature(self._range[0] + int((self._range[1] - self._range[0]) * 0.2))
        self.setup_shutter("closed")

    def get_device_info(self):
        self._call("get_device_info")
        return SDK2DeviceInfo("USB", "DU888_BV", state.sdk2_serials[self.idx])

    def _gain_factor(self):
        return float(self._gain)

    def get_EMCCD_gain(self):
        self._call("get_EMCCD_gain")
        return self._gain, self._advanced

    def set_EMCCD_gain(self, gain, advanced=None):
        self._call("set_EMCCD_gain", gain, advanced)
        if advanced is not None:
            self._advanced = bool(advanced)
        if gain > (1000 if self._advanced else 300):
            raise AndorError(f"function 'SetEMCCDGain' raised error 20066(DRV_P1INVALID): gain {gain}")
        self._gain = int(gain)

    def set_temperature(self, temperature, enable_cooler=True):
        self._call("set_temperature", temperature, enable_cooler)
        self._setpoint = int(min(max(temperature, self._range[0]), self._range[1]))
        if enable_cooler:
            self.set_cooler(True)
        return self._setpoint

    def get_temperature_status(self):
        self._call("get_temperature_status")
        return "stabilized" if self._cooler else "off"

    def get_temperature_range(self):
        return self._range

    def setup_shutter(self, mode, ttl_mode=0, open_time=None, close_time=None):
        self._call("setup_shutter", mode)
        if mode not in ("open", "closed", "auto"):
            raise AndorError(f"unknown shutter mode {mode!r}")
        self._shutter = mode
        return (mode, ttl_mode, open_time or 0, close_time or 0)

    def get_shutter(self):
        return self._shutter


class AndorSDK3Camera(_AndorCamera):
    """pylablib.devices.Andor.AndorSDK3Camera (a Zyla 4.2: sCMOS, no EM register)."""

    Error = AndorError
    TimeoutError = AndorTimeoutError

    def __init__(self, idx=0):
        if idx >= len(state.sdk3_serials):
            raise AndorError(f"function 'AT_Open' raised error 2(AT_ERR_NOTINITIALISED): camera {idx}")
        super().__init__()
        self.idx = idx
        state.calls.append(("AndorSDK3Camera", "__init__", idx))

    def get_device_info(self):
        self._call("get_device_info")
        return SDK3DeviceInfo("Zyla", "ZYLA-4.2P-USB3", state.sdk3_serials[self.idx], "15.3.13.0", "3.15.30092.0")

    def set_temperature(self, temperature, enable_cooler=True):
        self._call("set_temperature", temperature, enable_cooler)
        self._setpoint = float(temperature)
        if enable_cooler:
            self.set_cooler(True)
        return self._setpoint

    def get_shutter(self):
        self._call("get_shutter")
        if not state.sdk3_shutter:
            raise AndorNotSupportedError("feature ShutterMode is not supported by ZYLA-4.2P-USB3")
        return self._shutter

    def set_shutter(self, mode):
        self._call("set_shutter", mode)
        if not state.sdk3_shutter:
            raise AndorNotSupportedError("feature ShutterMode is not supported by ZYLA-4.2P-USB3")
        self._shutter = mode
        return self._shutter


def get_cameras_number_SDK2():
    return len(state.sdk2_serials)


def get_cameras_number_SDK3():
    return len(state.sdk3_serials)


def get_SDK2_version():
    return "2.104.30084.0"


Andor = types.ModuleType("pylablib.devices.Andor", "Fake of pylablib.devices.Andor")
for _n in ("AndorSDK2Camera", "AndorSDK3Camera", "get_cameras_number_SDK2", "get_cameras_number_SDK3",
           "get_SDK2_version", "AndorError", "AndorTimeoutError", "AndorNotSupportedError"):
    setattr(Andor, _n, globals()[_n])


# ------------------------------------------------------------------ Photometrics (PVCAM)
PvcamDeviceInfo = collections.namedtuple("TDeviceInfo", ["vendor", "product", "chip", "system", "part", "serial"])


class PvcamCamera(_Camera):
    """pylablib.devices.Photometrics.PvcamCamera (an Evolve 512 EMCCD, or a Prime sCMOS
    without GAIN_MULT_FACTOR when ``state.pvcam_em`` is False)."""

    Error = PvcamError
    TimeoutError = PvcamTimeoutError

    def __init__(self, name=None):
        cams = list_cameras()
        if not cams:
            raise PvcamError("no cameras are avaliable")
        if name is None:
            name = cams[0]
        elif name not in cams:
            raise PvcamError(f"camera with name {name} isn't present among available cameras: {cams}")
        super().__init__()
        self.name = name
        self._params = {"TEMP": 2000, "TEMP_SETPOINT": -8000, "SHTR_OPEN_MODE": 1, "CAM_FW_VERSION": 0x0A04}
        if state.pvcam_em:
            self._params["GAIN_MULT_FACTOR"] = 1
        self._cooler = True  # PVCAM cameras cool whenever powered
        self._setpoint = -80.0
        state.calls.append(("PvcamCamera", "__init__", name))

    def get_device_info(self):
        self._call("get_device_info")
        return PvcamDeviceInfo("Photometrics", "Evolve 512" if state.pvcam_em else "Prime 95B", "EMCCD",
                               "", "", state.pvcam_cameras[self.name])

    def _gain_factor(self):
        return float(self._params.get("GAIN_MULT_FACTOR", 1))

    def get_attribute_value(self, name, error_on_missing=True, error_on_noacq=False, default=None, enum_as_str=True):
        self._call("get_attribute_value", name)
        if name == "TEMP":
            return int(round(self._temperature() * 100))
        if name == "SHTR_OPEN_MODE":
            v = 1 if self._shutter == "open" else 0
            return ("Open Pre-Exposure" if v else "Open Never") if enum_as_str else v
        if name not in self._params:
            if error_on_missing and default is None:
                raise PvcamError(f"attribute {name} is missing")
            return default
        return self._params[name]

    def set_attribute_value(self, name, value, truncate=True, error_on_missing=True):
        self._call("set_attribute_value", name, value)
        if name == "SHTR_OPEN_MODE":
            if value not in (0, 1, 2, 3, 4):
                raise PvcamError(f"value {value} is not in allowed values [0, 1, 2, 3, 4] for attribute {name}")
            self._shutter = "open" if value else "closed"
            return
        if name not in self._params:
            if error_on_missing:
                raise PvcamError(f"attribute {name} is missing")
            return
        if name == "GAIN_MULT_FACTOR" and not 1 <= value <= 1000:
            if not truncate:
                raise PvcamError(f"function 'pl_set_param' raised error 37: GAIN_MULT_FACTOR {value} out of range")
            value = min(max(value, 1), 1000)
        self._params[name] = value

    def get_temperature(self):
        self._call("get_temperature")
        return self._temperature()

    def get_temperature_setpoint(self):
        return self._setpoint

    def set_temperature(self, temp):
        self._call("set_temperature", temp)
        self._setpoint = float(temp)
        self._params["TEMP_SETPOINT"] = int(temp * 100)
        return self._setpoint


def list_cameras():
    return list(state.pvcam_cameras)


def get_cameras_number():
    return len(state.pvcam_cameras)


Photometrics = types.ModuleType("pylablib.devices.Photometrics", "Fake of pylablib.devices.Photometrics")
for _n in ("PvcamCamera", "list_cameras", "get_cameras_number", "PvcamError", "PvcamTimeoutError"):
    setattr(Photometrics, _n, globals()[_n])


def install(monkeypatch) -> None:
    """Make ``import pylablib.devices.Andor`` / ``.Photometrics`` give these fakes (pylablib
    itself need not be installed)."""
    import sys

    monkeypatch.setitem(sys.modules, "pylablib.devices.Andor", Andor)
    monkeypatch.setitem(sys.modules, "pylablib.devices.Photometrics", Photometrics)
