"""A fake of Hamamatsu's DCAM-API Python wrapper (``dcam.py`` of DCAM-SDK4).

The vendor library cannot exist on this machine or in CI (a closed binary, not on any
package registry), so the DCAM backend is tested against this stand-in.  It follows the
wrapper's conventions: ``Dcamapi.init()`` / ``uninit()`` / ``get_devicecount()``
classmethods; ``Dcam(index)`` with ``dev_open``, ``prop_getnextid`` (walks the property
ids, ``False`` at the end), ``prop_getname``, ``prop_getvalue``, ``prop_setgetvalue``
(clamps to the property's range like the camera does), ``buf_alloc``, ``cap_snapshot``,
``wait_capevent_frameready(timeout_ms)``, ``buf_getlastframedata``, ``buf_getframedata``,
``cap_stop``, ``buf_release``, ``dev_getstring(DCAM_IDSTR.*)``, ``dev_close``; every call returns ``False`` on failure and
``lasterr()`` then says why.  Property ids here are made up: the backend must find
properties by name.  What it *cannot* show: that the real SDK behaves like this.
"""

from __future__ import annotations

import numpy as np

ERR_TIMEOUT = "DCAMERR.TIMEOUT"
ERR_INVALIDVALUE = "DCAMERR.INVALIDVALUE"
ERR_NOCAMERA = "DCAMERR.NOCAMERA"
ERR_NOTREADY = "DCAMERR.NOTREADY"

# name: (made-up id, initial value, min, max)
PROPERTIES = {
    "EXPOSURE TIME": (0x1F0110, 0.1, 1e-4, 3600.0),
    "BINNING": (0x401110, 1, 1, 4),
    "SENSITIVITY": (0x400220, 1, 1, 1200),
    "DIRECT EM GAIN MODE": (0x401F10, 1, 1, 2),
    "SENSOR TEMPERATURE": (0x200310, 20.0, -100.0, 50.0),
    "SENSOR COOLER": (0x200320, 1, 1, 4),
    "CCD MODE": (0x400210, 1, 1, 2),
    "READOUT SPEED": (0x400110, 1, 1, 3),
    "IMAGE WIDTH": (0x420210, 1024, 1, 1024),
    "IMAGE HEIGHT": (0x420220, 1024, 1, 1024),
}


class DCAM_IDSTR:  # dcamapi4's string ids, re-exported by dcam.py (``from dcamapi4 import *``)
    BUS = 0x04000101
    CAMERAID = 0x04000102
    VENDOR = 0x04000103
    MODEL = 0x04000104
    CAMERAVERSION = 0x04000105


_STRINGS = {DCAM_IDSTR.BUS: "USB2.0", DCAM_IDSTR.CAMERAID: "S/N: 100123", DCAM_IDSTR.VENDOR: "Hamamatsu",
            DCAM_IDSTR.MODEL: "C9100-13", DCAM_IDSTR.CAMERAVERSION: "3.10.B"}


class _State:
    initialised = 0
    devices = 1
    calls: list = []
    fail_next: dict = {}  # method name -> error to report once
    stall_frames = False  # frames never arrive (wait_capevent_frameready times out)


class Dcamapi:
    _err = None

    @classmethod
    def init(cls, *args):
        _State.initialised += 1
        _State.calls.append(("init",))
        return True

    @classmethod
    def uninit(cls):
        _State.initialised -= 1
        _State.calls.append(("uninit",))
        return True

    @classmethod
    def get_devicecount(cls):
        return _State.devices

    @classmethod
    def lasterr(cls):
        return cls._err


class Dcam:
    def __init__(self, iDevice=0):
        self.index = iDevice
        self._err = None
        self._open = False
        self._values = {name: v for name, (_, v, _, _) in PROPERTIES.items()}
        self._by_id = {pid: name for name, (pid, _, _, _) in PROPERTIES.items()}
        self._frames: list[np.ndarray] = []
        self._nbuf = 0
        self._armed = 0
        self._rng = np.random.default_rng(0)

    def _fail(self, err):
        self._err = err
        return False

    def _check(self, method):
        _State.calls.append((method,))
        if method in _State.fail_next:
            return self._fail(_State.fail_next.pop(method))
        if not self._open and method != "dev_open":
            return self._fail(ERR_NOTREADY)
        return True

    def lasterr(self):
        return self._err

    def dev_open(self, index=-1):
        if not self._check("dev_open"):
            return False
        if self.index >= _State.devices:
            return self._fail(ERR_NOCAMERA)
        self._open = True
        return True

    def dev_getstring(self, idstr):
        if not self._check("dev_getstring"):
            return False
        return _STRINGS.get(idstr, False) or self._fail("DCAMERR.INVALIDPARAM")

    def dev_close(self):
        self._check("dev_close")
        self._open = False
        return True

    # ---------------------------------------------------------------- properties
    def prop_getnextid(self, idprop):
        ids = sorted(self._by_id)
        later = [i for i in ids if i > idprop]
        return later[0] if later else self._fail("DCAMERR.NOPROPERTY")

    def prop_getname(self, idprop):
        return self._by_id.get(idprop, False)

    def prop_getvalue(self, idprop):
        if not self._check("prop_getvalue"):
            return False
        name = self._by_id[idprop]
        if name == "SENSOR TEMPERATURE":  # follows the cooler (no cool-down in the fake)
            return -65.0 if self._values["SENSOR COOLER"] != 1 else 20.0
        return self._values[name]

    def prop_setgetvalue(self, idprop, fValue, option=0):
        if not self._check("prop_setgetvalue"):
            return False
        name = self._by_id[idprop]
        _, _, lo, hi = PROPERTIES[name]
        if name in ("SENSOR TEMPERATURE", "IMAGE WIDTH", "IMAGE HEIGHT"):
            return self._fail("DCAMERR.ACCESSDENY")  # read-only
        if not lo <= fValue <= hi:
            return self._fail(ERR_INVALIDVALUE)
        if name == "BINNING":
            if int(fValue) not in (1, 2, 4):
                return self._fail(ERR_INVALIDVALUE)
            self._values["IMAGE WIDTH"] = self._values["IMAGE HEIGHT"] = 1024 // int(fValue)
        _State.calls.append(("set", name, fValue))
        self._values[name] = fValue
        return fValue

    # ---------------------------------------------------------------- capture
    def buf_alloc(self, nFrame):
        if not self._check("buf_alloc"):
            return False
        self._nbuf = nFrame
        return True

    def buf_release(self):
        self._check("buf_release")
        self._nbuf = 0
        return True

    def cap_snapshot(self):
        if not self._check("cap_snapshot"):
            return False
        if self._nbuf == 0:
            return self._fail(ERR_NOTREADY)
        ny, nx = int(self._values["IMAGE HEIGHT"]), int(self._values["IMAGE WIDTH"])
        self._frames = [(100 + k + self._rng.integers(0, 3, (ny, nx))).astype(np.uint16) for k in range(self._nbuf)]
        self._armed = 0
        return True

    def wait_capevent_frameready(self, timeout_millisec):
        if not self._check("wait_capevent_frameready"):
            return False
        _State.calls.append(("wait", timeout_millisec))
        if _State.stall_frames or self._armed >= len(self._frames):
            return self._fail(ERR_TIMEOUT)
        self._armed += 1
        return True

    def buf_getlastframedata(self):
        if not self._check("buf_getlastframedata"):
            return False
        return self._frames[self._armed - 1] if self._armed else self._fail(ERR_NOTREADY)

    def buf_getframedata(self, iFrame):
        if not self._check("buf_getframedata"):
            return False
        return self._frames[iFrame] if iFrame < self._armed else self._fail(ERR_NOTREADY)

    def cap_stop(self):
        self._check("cap_stop")
        return True


def reset(devices: int = 1) -> None:
    _State.initialised = 0
    _State.devices = devices
    _State.calls = []
    _State.fail_next = {}
    _State.stall_frames = False


state = _State
