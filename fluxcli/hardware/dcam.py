"""The real EMCCD (Hamamatsu ImagEM) through the vendor's DCAM-API: an optional backend.

DCAM-API is a closed vendor library (``dcamapi.dll`` on Windows, ``libdcamapi.so`` on some
Linux installs) with a Python wrapper, ``dcam.py``, in Hamamatsu's DCAM-SDK4 samples.  It
cannot be installed from a package registry, so it **cannot exist on this machine or in
CI**: this backend is tested only against a fake of that wrapper
(``tests/fake_dcam.py``), which follows the wrapper's calls (``Dcamapi.init``,
``Dcam.dev_open``, ``prop_getnextid`` / ``prop_getname`` / ``prop_getvalue`` /
``prop_setgetvalue``, ``buf_alloc``, ``cap_snapshot``, ``wait_capevent_frameready``,
``buf_getlastframedata``, ``lasterr``; failures return ``False``).  Whether it matches a
real camera is *unverified* until someone runs it on one.

Properties are found by their DCAM names (``EXPOSURE TIME``, ``BINNING``, ``SENSITIVITY``,
``DIRECT EM GAIN MODE``, ``SENSOR TEMPERATURE``, ``SENSOR COOLER``, ``CCD MODE``), never by
hard-coded ids.  To use it: put the SDK's ``dcam.py`` (and ``dcamapi4.py``) on the Python
path and set ``rig.camera.backend: dcam``.
"""

from __future__ import annotations

import importlib
from typing import Any

import numpy as np

from .camera import Camera, DeviceIdentity
from .errors import DeviceError

__all__ = ["DcamCamera", "PROPERTY_NAMES"]

# What each setting is called in DCAM (names from the DCAM-API property reference).
PROPERTY_NAMES = {
    "exposure_s": "EXPOSURE TIME",
    "binning": "BINNING",
    "em_gain": "SENSITIVITY",
    "direct_em_gain": "DIRECT EM GAIN MODE",
    "temperature_c": "SENSOR TEMPERATURE",
    "cooler": "SENSOR COOLER",
    "ccd_mode": "CCD MODE",
}
# DCAM property values used here (DCAMPROP_* in dcamapi4.h)
_ON, _OFF = 2, 1  # DIRECT EM GAIN MODE and SENSOR COOLER: 2 = on, 1 = off
_CCD_MODE_EMCCD = 2
_DEFAULT_TIMEOUT_MARGIN_S = 5.0


class DcamCamera(Camera):
    """An EMCCD driven through DCAM-API (``dcam`` wrapper module of DCAM-SDK4).

    Parameters
    ----------
    device_index : int
        Which DCAM device (0 = the first camera found).
    api : module, optional
        The ``dcam`` wrapper module; imported by name when not given (tests pass a fake).
    shutter_property : str or None
        Name of a DCAM property that closes a light shutter for dark frames, with
        ``shutter_values = (open, closed)``; *unverified* for the ImagEM, which may have
        none.  Without one, closing the shutter raises a DeviceError (cap the lens and
        take darks by hand, or configure the property).
    readout_timeout_s : float
        Seconds beyond the exposure to wait for a frame before giving up.
    """

    name = "camera (DCAM)"

    def __init__(self, device_index: int = 0, *, api: Any = None, shutter_property: str | None = None,
                 shutter_values: tuple[float, float] = (2, 1), readout_timeout_s: float = _DEFAULT_TIMEOUT_MARGIN_S):
        self.port = f"DCAM device {device_index}"
        if api is None:
            try:
                api = importlib.import_module("dcam")
            except ImportError:
                raise self._error("the DCAM-API Python wrapper 'dcam' (Hamamatsu DCAM-SDK4) is not installed; it "
                                  "comes with the vendor's SDK, not from PyPI. Use rig.camera.backend: simulated "
                                  "without the camera") from None
        self._api = api
        self._shutter_property = shutter_property
        self._shutter_values = shutter_values
        self._timeout_margin_s = float(readout_timeout_s)
        self._buffer_frames = 0
        self._shutter_open = True
        if api.Dcamapi.init() is False:
            raise self._error("DCAM-API failed to initialise", self._lasterr(api.Dcamapi))
        n = api.Dcamapi.get_devicecount()
        if n is False or int(n) <= device_index:
            api.Dcamapi.uninit()
            raise self._error(f"no DCAM device {device_index}: {0 if n is False else int(n)} camera(s) found")
        self._dcam = api.Dcam(device_index)
        if self._dcam.dev_open() is False:
            err = self._lasterr(self._dcam)
            api.Dcamapi.uninit()
            raise self._error("could not open the camera", err)
        self._ids = self._property_ids()
        missing = [n for k, n in PROPERTY_NAMES.items() if n not in self._ids and k != "direct_em_gain"]
        if shutter_property is not None and shutter_property not in self._ids:
            missing.append(shutter_property)
        if missing:
            self.close()
            raise self._error(f"the camera has no propert{'y' if len(missing) == 1 else 'ies'} "
                              f"{', '.join(repr(m) for m in missing)}; is it an EMCCD?")
        self._set("ccd_mode", _CCD_MODE_EMCCD)
        if PROPERTY_NAMES["direct_em_gain"] in self._ids:  # SENSITIVITY is then the gain factor itself
            self._set("direct_em_gain", _ON)

    # ---------------------------------------------------------------- DCAM plumbing
    @staticmethod
    def _lasterr(obj) -> str:
        try:
            err = obj.lasterr()
        except Exception:  # the wrapper's error object is best effort; never mask the real failure
            return "no error code"
        return f"DCAMERR {err!r}"

    def _property_ids(self) -> dict[str, int]:
        ids: dict[str, int] = {}
        idprop = 0
        for _ in range(100_000):  # the property list is finite; never loop forever on a broken wrapper
            idprop = self._dcam.prop_getnextid(idprop)
            if idprop is False or idprop is None:
                break
            name = self._dcam.prop_getname(idprop)
            if name is not False:
                ids[str(name)] = int(idprop)
        return ids

    def _get(self, key: str) -> float:
        name = PROPERTY_NAMES.get(key, key)
        value = self._dcam.prop_getvalue(self._ids[name])
        if value is False:
            raise self._error(f"reading {name!r} failed", self._lasterr(self._dcam))
        return float(value)

    def _set(self, key: str, value: float) -> float:
        """Set and read back (the camera may round to what it supports)."""
        name = PROPERTY_NAMES.get(key, key)
        got = self._dcam.prop_setgetvalue(self._ids[name], float(value))
        if got is False:
            raise self._error(f"setting {name!r} to {value!r} failed", self._lasterr(self._dcam))
        return float(got)

    def identity(self) -> DeviceIdentity:
        """``dev_getstring`` of DCAM_IDSTR MODEL, CAMERAID (``S/N: ...``) and CAMERAVERSION."""
        ids = getattr(self._api, "DCAM_IDSTR", None)
        if ids is None:
            return DeviceIdentity(self.name)

        def text(key: str) -> str:
            got = self._dcam.dev_getstring(getattr(ids, key))
            return "" if got is False else str(got)

        serial = text("CAMERAID")
        return DeviceIdentity(text("MODEL") or self.name, serial.removeprefix("S/N:").strip(), text("CAMERAVERSION"))

    # ---------------------------------------------------------------- settings
    @property
    def exposure_s(self) -> float:
        return self._get("exposure_s")

    @exposure_s.setter
    def exposure_s(self, value: float) -> None:
        self._set("exposure_s", value)

    @property
    def binning(self) -> int:
        return int(self._get("binning"))

    @binning.setter
    def binning(self, value: int) -> None:
        got = int(self._set("binning", int(value)))
        if got != int(value):
            raise self._error(f"binning {value} was not accepted (the camera reports {got})")
        self._release_buffer()  # the frame size changed

    @property
    def em_gain(self) -> float:
        return self._get("em_gain")

    @em_gain.setter
    def em_gain(self, value: float) -> None:
        self._set("em_gain", value)

    @property
    def temperature_c(self) -> float:
        return self._get("temperature_c")

    @property
    def cooler_on(self) -> bool:
        return int(self._get("cooler")) != _OFF

    @cooler_on.setter
    def cooler_on(self, value: bool) -> None:
        self._set("cooler", _ON if value else _OFF)

    @property
    def shutter_open(self) -> bool:
        if self._shutter_property is None:
            return self._shutter_open
        return self._get(self._shutter_property) == self._shutter_values[0]

    @shutter_open.setter
    def shutter_open(self, value: bool) -> None:
        if self._shutter_property is None:
            if not value:
                raise self._error("no shutter property is configured (rig.camera.shutter_property), so dark "
                                  "frames cannot be taken automatically")
            self._shutter_open = True
            return
        self._set(self._shutter_property, self._shutter_values[0 if value else 1])

    def make_safe(self) -> None:
        if self._shutter_property is not None:
            self.shutter_open = False

    @property
    def shape(self) -> tuple[int, int]:
        ny = self._dcam.prop_getvalue(self._ids["IMAGE HEIGHT"]) if "IMAGE HEIGHT" in self._ids else False
        nx = self._dcam.prop_getvalue(self._ids["IMAGE WIDTH"]) if "IMAGE WIDTH" in self._ids else False
        if ny is False or nx is False:
            raise self._error("the camera does not report IMAGE WIDTH / IMAGE HEIGHT", self._lasterr(self._dcam))
        return int(ny), int(nx)

    # ---------------------------------------------------------------- frames
    def _release_buffer(self) -> None:
        if self._buffer_frames:
            self._dcam.buf_release()
            self._buffer_frames = 0

    def _frames(self, n: int) -> np.ndarray:
        if self._buffer_frames != n:
            self._release_buffer()
            if self._dcam.buf_alloc(n) is False:
                raise self._error(f"allocating {n} frame buffer(s) failed", self._lasterr(self._dcam))
            self._buffer_frames = n
        if self._dcam.cap_snapshot() is False:
            raise self._error("starting the capture failed", self._lasterr(self._dcam))
        timeout_ms = int(1000 * (self.exposure_s + self._timeout_margin_s))
        out = []
        try:
            for k in range(n):
                if self._dcam.wait_capevent_frameready(timeout_ms) is False:
                    raise self._error(f"frame {k + 1} of {n} did not arrive within {timeout_ms / 1000:g} s",
                                      self._lasterr(self._dcam))
                data = self._dcam.buf_getframedata(k) if n > 1 else self._dcam.buf_getlastframedata()
                if data is False:
                    raise self._error(f"reading frame {k + 1} of {n} failed", self._lasterr(self._dcam))
                out.append(np.array(data, dtype=np.uint16, copy=True))
        finally:
            self._dcam.cap_stop()
        return np.stack(out)

    def snap(self) -> np.ndarray:
        return self._frames(1)[0]

    def sequence(self, n: int) -> np.ndarray:
        return self._frames(int(n)) if n > 0 else np.zeros((0, *self.shape), np.uint16)

    def close(self) -> None:
        if getattr(self, "_dcam", None) is None:
            return
        try:
            self._release_buffer()
            self._dcam.dev_close()
        finally:
            self._dcam = None
            self._api.Dcamapi.uninit()
