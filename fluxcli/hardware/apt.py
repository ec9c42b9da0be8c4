"""Thorlabs APT binary protocol: message ids, header framing, payload layouts.

A 6-byte little-endian header: without data ``<H id><B p1><B p2><B dest><B src>``; with data
``<H id><H len><B dest|0x80><B src>`` followed by ``len`` bytes.  The host is 0x01, a USB
controller 0x50; replies swap destination and source.  Shared by the driver and the simulator
(the tests check these bytes against the independent ``thorlabs-apt-protocol`` package).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

HOST = 0x01
USB_UNIT = 0x50

MOD_IDENTIFY = 0x0223
MOD_SET_CHANENABLESTATE = 0x0210
MOD_REQ_CHANENABLESTATE = 0x0211
MOD_GET_CHANENABLESTATE = 0x0212
HW_REQ_INFO = 0x0005
HW_GET_INFO = 0x0006
HW_START_UPDATEMSGS = 0x0011
HW_STOP_UPDATEMSGS = 0x0012
HW_RESPONSE = 0x0080
HW_RICHRESPONSE = 0x0081
MOT_SET_POSCOUNTER = 0x0410
MOT_REQ_POSCOUNTER = 0x0411
MOT_GET_POSCOUNTER = 0x0412
MOT_SET_VELPARAMS = 0x0413
MOT_REQ_VELPARAMS = 0x0414
MOT_GET_VELPARAMS = 0x0415
MOT_SET_HOMEPARAMS = 0x0440
MOT_REQ_HOMEPARAMS = 0x0441
MOT_GET_HOMEPARAMS = 0x0442
MOT_MOVE_HOME = 0x0443
MOT_MOVE_HOMED = 0x0444
MOT_MOVE_RELATIVE = 0x0448
MOT_MOVE_ABSOLUTE = 0x0453
MOT_MOVE_VELOCITY = 0x0457
MOT_MOVE_JOG = 0x046A
MOT_MOVE_COMPLETED = 0x0464
MOT_MOVE_STOP = 0x0465
MOT_MOVE_STOPPED = 0x0466
MOT_REQ_STATUSUPDATE = 0x0480
MOT_GET_STATUSUPDATE = 0x0481
MOT_ACK_STATUSUPDATE = 0x0492
MOT_REQ_DCSTATUSUPDATE = 0x0490
MOT_GET_DCSTATUSUPDATE = 0x0491
MOT_SET_JOGPARAMS = 0x0416
MOT_REQ_JOGPARAMS = 0x0417
MOT_GET_JOGPARAMS = 0x0418
MOT_SET_LIMSWITCHPARAMS = 0x0423
MOT_REQ_LIMSWITCHPARAMS = 0x0424
MOT_GET_LIMSWITCHPARAMS = 0x0425
MOT_SET_POWERPARAMS = 0x0426
MOT_REQ_POWERPARAMS = 0x0427
MOT_GET_POWERPARAMS = 0x0428
MOT_SET_GENMOVEPARAMS = 0x043A
MOT_REQ_GENMOVEPARAMS = 0x043B
MOT_GET_GENMOVEPARAMS = 0x043C
MOT_SET_MOVERELPARAMS = 0x0445
MOT_REQ_MOVERELPARAMS = 0x0446
MOT_GET_MOVERELPARAMS = 0x0447
MOT_SET_MOVEABSPARAMS = 0x0450
MOT_REQ_MOVEABSPARAMS = 0x0451
MOT_GET_MOVEABSPARAMS = 0x0452
MOT_REQ_STATUSBITS = 0x0429
MOT_GET_STATUSBITS = 0x042A

NAMES = {v: k for k, v in dict(globals()).items() if k.isupper() and isinstance(v, int) and k not in ("HOST", "USB_UNIT")}

#: Messages a controller may send on its own; skipped while waiting for a reply.
UNSOLICITED = frozenset({MOT_MOVE_COMPLETED, MOT_MOVE_STOPPED, MOT_MOVE_HOMED, MOT_GET_STATUSUPDATE,
                         MOT_GET_DCSTATUSUPDATE})

# Status bits (hardware.md)
ST_HW_LIMIT_REV = 0x1
ST_HW_LIMIT_FWD = 0x2
ST_MOVING_REV = 0x10
ST_MOVING_FWD = 0x20
ST_JOG_REV = 0x40
ST_JOG_FWD = 0x80
ST_CONNECTED = 0x100
ST_HOMING = 0x200
ST_HOMED = 0x400
ST_SETTLED = 0x2000
ST_MOTION_ERROR = 0x4000
ST_ENABLED = 0x80000000
#: "Moving" is any of these (the direction names differ between drivers: not trusted).
ST_MOVING_ANY = ST_MOVING_REV | ST_MOVING_FWD | ST_JOG_REV | ST_JOG_FWD | ST_HOMING

HW_INFO = struct.Struct("<l8sH4B60sHHH")  # 84 bytes
STATUS_BLOCK = struct.Struct("<HiiI")      # chan, position, encoder, status bits (14 bytes)
STATUS_BITS = struct.Struct("<HI")
POSCOUNTER = struct.Struct("<Hi")
VELPARAMS = struct.Struct("<Hiii")          # chan, min velocity, acceleration, max velocity
HOMEPARAMS = struct.Struct("<HHHii")        # chan, direction, limit switch, velocity, offset
RICHRESPONSE = struct.Struct("<HH64s")      # message id, code, notes
MAX_DATA = 255  # longest payload accepted before calling a header noise


@dataclass(frozen=True)
class Message:
    """One APT message.  ``data`` is None for a header-only message (then p1, p2 hold its parameters)."""

    msgid: int
    dest: int
    src: int
    param1: int = 0
    param2: int = 0
    data: bytes | None = None

    @property
    def name(self) -> str:
        return NAMES.get(self.msgid, f"0x{self.msgid:04X}")

    def encode(self) -> bytes:
        if self.data is None:
            return struct.pack("<HBBBB", self.msgid, self.param1, self.param2, self.dest, self.src)
        return struct.pack("<HHBB", self.msgid, len(self.data), self.dest | 0x80, self.src) + self.data


def short(msgid: int, p1: int = 0, p2: int = 0, *, dest: int = USB_UNIT, src: int = HOST) -> bytes:
    """A header-only message."""
    return Message(msgid, dest, src, p1, p2).encode()


def with_data(msgid: int, data: bytes, *, dest: int = USB_UNIT, src: int = HOST) -> bytes:
    """A message with a data packet (``dest | 0x80`` in the header)."""
    return Message(msgid, dest, src, data=data).encode()


def parse_header(header: bytes) -> tuple[int, int, int, int, int | None]:
    """``(msgid, dest, src, p1p2_or_len, data_len)`` from 6 header bytes; data_len None for short messages."""
    msgid, p1, p2, dest, src = struct.unpack("<HBBBB", header)
    if dest & 0x80:
        (length,) = struct.unpack_from("<H", header, 2)
        return msgid, dest & 0x7F, src, length, length
    return msgid, dest, src, p1 | (p2 << 8), None


def decode(buf: bytes) -> tuple[Message | None, int]:
    """Decode the first message of ``buf``: ``(message, bytes used)``, or ``(None, 0)`` when incomplete."""
    if len(buf) < 6:
        return None, 0
    msgid, p1, p2, dest, src = struct.unpack_from("<HBBBB", buf)
    if dest & 0x80:
        (length,) = struct.unpack_from("<H", buf, 2)
        if len(buf) < 6 + length:
            return None, 0
        return Message(msgid, dest & 0x7F, src, data=bytes(buf[6:6 + length])), 6 + length
    return Message(msgid, dest, src, p1, p2), 6


def hw_info(serial_number: int, model: str, hw_type: int, firmware: tuple[int, int, int], notes: str,
            hw_version: int, mod_state: int, n_channels: int) -> bytes:
    """The 84-byte HW_GET_INFO payload; firmware (major, minor, patch) is stored minor-most first."""
    major, minor, patch = firmware
    return HW_INFO.pack(serial_number, model.encode("ascii")[:8], hw_type, patch, minor, major, 0,
                        notes.encode("ascii")[:60], hw_version, mod_state, n_channels)


def parse_hw_info(data: bytes) -> dict:
    """HW_GET_INFO payload -> dict (serial_number, model, hw_type, firmware, notes, hw_version, mod_state, n_channels)."""
    sn, model, hw_type, b0, b1, b2, _b3, notes, hw_version, mod_state, n_channels = HW_INFO.unpack(data[:HW_INFO.size])
    return {"serial_number": sn, "model": model.rstrip(b"\x00").decode("latin-1").strip(), "hw_type": hw_type,
            "firmware": f"{b2}.{b1}.{b0}", "notes": notes.split(b"\x00")[0].decode("latin-1").strip(),
            "hw_version": hw_version, "mod_state": mod_state, "n_channels": n_channels}
