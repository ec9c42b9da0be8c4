"""A simulated L490MZ lab jack on its integrated APT controller (binary protocol, hardware.md).

Moves follow a trapezoidal velocity profile with the velocity parameters the client set
(device units converted with ``velocity_scale``/``acceleration_scale``), x ``time_scale``;
status bits and the position counter evolve during a move.  MOVE_COMPLETED, MOVE_STOPPED and
MOVE_HOMED are sent unsolicited, status updates (0x0481) every 100 ms x time_scale after
HW_START_UPDATEMSGS.  Parameter blocks (velocity, homing, jog, limit switches, backlash, power,
relative/absolute move) are stored and given back; jogs and velocity moves take direction 1 as
increasing position (hardware.md: do not trust direction names).  Unknown messages are ignored,
as a controller does.
"""

from __future__ import annotations

import math
import struct
import threading
import time

from .. import apt
from .base import Link, SerialSimulator

MAX_VELOCITY_MM_S = 1.1
HOME_VELOCITY_MM_S = 0.4
BACKLASH_MM = 0.05


class _Motion:
    """A 1-D trapezoidal move from x0 to x1 (counts), starting now."""

    def __init__(self, x0: float, x1: float, v: float, a: float, time_scale: float, kind: str, link: Link | None,
                 stall_fraction: float | None = None, end_error: float = 0.0):
        self.x0, self.x1, self.kind, self.link = x0, x1, kind, link
        self.v, self.a = max(v, 1e-9), max(a, 1e-9)
        self.time_scale = time_scale
        self.t0 = time.monotonic()
        d = abs(x1 - x0)
        if d >= self.v * self.v / self.a:
            self.t_acc = self.v / self.a
            self.duration = d / self.v + self.v / self.a
        else:
            self.t_acc = math.sqrt(d / self.a)
            self.duration = 2 * self.t_acc
        self.v_peak = self.a * self.t_acc
        self.stall_fraction = stall_fraction  # stalls (moving forever) after this fraction of the path
        self.end_error = end_error            # counts added to the final position ("wrong position")
        self.reported = False

    def _travelled(self, tau: float) -> float:
        tau = min(max(tau, 0.0), self.duration)
        ta, T, vp = self.t_acc, self.duration, self.v_peak
        if tau <= ta:
            return 0.5 * self.a * tau * tau
        if tau <= T - ta:
            return 0.5 * vp * ta + vp * (tau - ta)
        rest = T - tau
        return abs(self.x1 - self.x0) - 0.5 * self.a * rest * rest

    def tau(self) -> float:
        return (time.monotonic() - self.t0) / self.time_scale

    def position(self) -> float:
        sign = 1.0 if self.x1 >= self.x0 else -1.0
        d = abs(self.x1 - self.x0)
        s = self._travelled(self.tau())
        if self.stall_fraction is not None:
            s = min(s, self.stall_fraction * d)
        elif self.done():
            return self.x1 + self.end_error
        return self.x0 + sign * s

    def velocity(self) -> float:
        tau = self.tau()
        if self.done() or tau <= 0:
            return 0.0
        ta, T = self.t_acc, self.duration
        return self.a * tau if tau < ta else (self.v_peak if tau < T - ta else self.a * (T - tau))

    def done(self) -> bool:
        return self.stall_fraction is None and self.tau() >= self.duration

    @property
    def direction(self) -> int:
        return 1 if self.x1 >= self.x0 else -1


class LabJackSimulator(SerialSimulator):
    """The stage.

    Parameters
    ----------
    counts_per_mm : float
        Microsteps per mm (the same number the driver is given).
    travel_mm : (float, float)
        Hardware limits (mm): a move beyond stops there with the limit bit set.
    initial_mm : float
        Height at power-up; the position counter starts at the matching count, not homed.
    time_scale : float
        Device times x this.
    faults : list of dict or Faults, optional
        ``on`` is a message name or id (``"MOT_MOVE_ABSOLUTE"``, ``"0x0453"``).
    velocity_scale, acceleration_scale : float
        Device velocity units per count/s, acceleration units per count/s^2.
    serial_number, model, firmware : identity in HW_GET_INFO.
    updates : bool
        Send status updates without being asked (as after HW_START_UPDATEMSGS).
    """

    name = "stage"

    def __init__(self, *, counts_per_mm: float = 134737.0, travel_mm=(0.0, 50.0), initial_mm: float = 0.0,
                 time_scale: float = 1.0, faults=None, velocity_scale: float = 53.68,
                 acceleration_scale: float = 1 / 90.9, serial_number: int = 49000123, model: str = "L490MZ",
                 firmware=(1, 0, 3), updates: bool = False):
        super().__init__(time_scale=time_scale, faults=faults)
        self.counts_per_mm = float(counts_per_mm)
        self.travel_mm = (float(travel_mm[0]), float(travel_mm[1]))
        self.velocity_scale = float(velocity_scale)
        self.acceleration_scale = float(acceleration_scale)
        self.serial_number, self.model, self.firmware = serial_number, model, tuple(firmware)
        self.updates_default = updates
        self.enabled = True  # channels come up enabled; MOD_SET_CHANENABLESTATE can disable them
        self.homed = False
        self.identify_count = 0
        self.log: list[apt.Message] = []  # every message received, for tests
        self._lock = threading.RLock()
        self._x = initial_mm * self.counts_per_mm  # physical position (counts from the lower limit)
        self._offset = 0.0                          # position counter - physical counts
        self._motion: _Motion | None = None
        # defaults a driver must not trust: 1 mm/s, 1 mm/s^2
        self.velparams = (0, self._acc_units(1.0), self._vel_units(1.0))
        self.homeparams = (1, 2, 1, self._vel_units(HOME_VELOCITY_MM_S), 0)
        # other parameter blocks, stored as sent and given back on request (payload after the channel)
        self.params: dict[int, bytes] = {
            apt.MOT_SET_JOGPARAMS: struct.pack("<HiiiiH", 2, round(0.1 * self.counts_per_mm), 0,
                                               self._acc_units(1.0), self._vel_units(0.5), 2),
            apt.MOT_SET_LIMSWITCHPARAMS: struct.pack("<HHiiH", 2, 2, round(self.travel_mm[1] * self.counts_per_mm),
                                                     round(self.travel_mm[0] * self.counts_per_mm), 1),
            apt.MOT_SET_GENMOVEPARAMS: struct.pack("<i", round(BACKLASH_MM * self.counts_per_mm)),
            apt.MOT_SET_POWERPARAMS: struct.pack("<HH", 10, 30),
            apt.MOT_SET_MOVERELPARAMS: struct.pack("<i", 0),
            apt.MOT_SET_MOVEABSPARAMS: struct.pack("<i", 0),
        }

    # ------------------------------------------------------------------ units
    def _vel_units(self, mm_s: float) -> int:
        return round(mm_s * self.counts_per_mm * self.velocity_scale)

    def _acc_units(self, mm_s2: float) -> int:
        return round(mm_s2 * self.counts_per_mm * self.acceleration_scale)

    # ------------------------------------------------------------------ physics
    def _physical(self) -> float:
        with self._lock:
            if self._motion is not None:
                self._x = self._motion.position()
                if self._motion.done() and self._motion.kind == "home":
                    self._x = self.travel_mm[0] * self.counts_per_mm
            return self._x

    @property
    def position_mm(self) -> float:
        """Physical height now (mm), evolving during a move."""
        return self._physical() / self.counts_per_mm

    @property
    def position_counter(self) -> int:
        """What the controller reports as the position (counts)."""
        return round(self._physical() + self._offset)

    def status_bits(self) -> int:
        with self._lock:
            x = self._physical()
            bits = apt.ST_CONNECTED
            if self.enabled:
                bits |= apt.ST_ENABLED
            if self.homed:
                bits |= apt.ST_HOMED
            m = self._motion
            moving = m is not None and not m.done()
            if moving:
                bits |= apt.ST_MOVING_FWD if m.direction > 0 else apt.ST_MOVING_REV
                if m.kind == "home":
                    bits |= apt.ST_HOMING
            else:
                bits |= apt.ST_SETTLED
            lo, hi = (t * self.counts_per_mm for t in self.travel_mm)
            if x <= lo + 0.5:
                bits |= apt.ST_HW_LIMIT_REV
            if x >= hi - 0.5:
                bits |= apt.ST_HW_LIMIT_FWD
            return bits

    def _status_block(self) -> bytes:
        pos = self.position_counter
        return apt.STATUS_BLOCK.pack(1, pos, pos, self.status_bits())  # no encoder: it mirrors the counter

    @property
    def moving(self) -> bool:
        with self._lock:
            return self._motion is not None and not self._motion.done()

    def _start(self, x1_counter: float, link: Link, kind: str = "move", fault=None) -> None:
        with self._lock:
            x0 = self._physical()
            lo, hi = (t * self.counts_per_mm for t in self.travel_mm)
            x1 = min(max(x1_counter - self._offset, lo), hi)
            _, acc, vmax = self.velparams
            v = min(vmax / self.velocity_scale, MAX_VELOCITY_MM_S * self.counts_per_mm)
            if kind == "home":
                v = self.homeparams[3] / self.velocity_scale
            a = max(acc / self.acceleration_scale, 1e-3 * self.counts_per_mm)
            stall = end_error = None
            if fault is not None and fault.kind == "stall":
                stall = 0.5
            if fault is not None and fault.kind == "wrong_position":
                end_error = fault.offset * self.counts_per_mm
                if not lo <= x1 + end_error <= hi:
                    end_error = -end_error
            self._motion = _Motion(x0, x1, v, a, self.time_scale, kind, link, stall, end_error or 0.0)

    def _stop_motion(self, immediate: bool) -> None:
        with self._lock:
            m = self._motion
            if m is None or m.done() and m.stall_fraction is None:
                return
            x = m.position()
            if not immediate and m.stall_fraction is None:
                v = m.velocity()
                x_end = x + m.direction * v * v / (2 * m.a)
                self._motion = _Motion(x, x_end, max(v, 1e-9), m.a, self.time_scale, "stop", m.link)
            else:
                self._x = x
                self._motion = _Motion(x, x, 1.0, 1.0, self.time_scale, "stop", m.link)

    # ------------------------------------------------------------------ wire
    def serve(self, link: Link) -> None:
        buf = b""
        updates = self.updates_default
        next_update = time.monotonic()
        while not self.stopping and not link.closed:
            data = link.read(0.005)
            buf += data
            while True:
                if len(buf) >= 6:
                    _, dest, _, _, length = apt.parse_header(buf[:6])
                    if (length or 0) > apt.MAX_DATA:
                        buf = b""  # noise: drop it
                        break
                msg, used = apt.decode(buf)
                if msg is None:
                    break
                buf = buf[used:]
                if msg.msgid == apt.HW_START_UPDATEMSGS:
                    updates = True
                elif msg.msgid == apt.HW_STOP_UPDATEMSGS:
                    updates = False
                self._handle(link, msg)
                if link.closed:
                    return
            self._report_events()
            if updates and time.monotonic() >= next_update:
                link.write(apt.with_data(apt.MOT_GET_STATUSUPDATE, self._status_block(), dest=apt.HOST, src=apt.USB_UNIT))
                next_update = time.monotonic() + max(0.01, 0.1 * self.time_scale)

    def _report_events(self) -> None:
        with self._lock:
            m = self._motion
            if m is None or m.reported or not m.done():
                return
            m.reported = True
            if m.kind == "home":
                self._x = self.travel_mm[0] * self.counts_per_mm
                self._offset = -self._x
                self.homed = True
            else:
                self._x = m.position()
            link = m.link
            if m.kind == "home":
                out = apt.short(apt.MOT_MOVE_HOMED, 1, dest=apt.HOST, src=apt.USB_UNIT)
            elif m.kind == "stop":
                out = apt.with_data(apt.MOT_MOVE_STOPPED, self._status_block(), dest=apt.HOST, src=apt.USB_UNIT)
            else:
                out = apt.with_data(apt.MOT_MOVE_COMPLETED, self._status_block(), dest=apt.HOST, src=apt.USB_UNIT)
        if link is not None:
            link.write(out)

    def _reply(self, link: Link, msgid: int, data: bytes | None = None, p1: int = 0, p2: int = 0,
               to: int = apt.HOST) -> None:
        if data is None:
            link.write(apt.short(msgid, p1, p2, dest=to, src=apt.USB_UNIT))
        else:
            link.write(apt.with_data(msgid, data, dest=to, src=apt.USB_UNIT))

    def _handle(self, link: Link, msg: apt.Message) -> None:
        self.log.append(msg)
        if msg.dest not in (apt.USB_UNIT, 0x11, 0x21):
            return  # not for us
        to = msg.src
        names = (msg.name, f"0x{msg.msgid:04X}")
        is_move = msg.msgid in (apt.MOT_MOVE_ABSOLUTE, apt.MOT_MOVE_RELATIVE, apt.MOT_MOVE_HOME, apt.MOT_MOVE_JOG,
                                apt.MOT_MOVE_VELOCITY)
        go_on, fault = self.line_fault(link, names, ("error_reply",) + (("stall", "wrong_position") if is_move else ()))
        if not go_on:
            return
        if fault is not None and fault.kind == "error_reply":
            notes = b"simulated fault: command refused"
            self._reply(link, apt.HW_RICHRESPONSE, apt.RICHRESPONSE.pack(msg.msgid, 0x0B, notes), to=to)
            return
        move_fault = fault if fault is not None and fault.kind in ("stall", "wrong_position") else None
        d = msg.data or b""
        mid = msg.msgid
        if mid == apt.HW_REQ_INFO:
            self._reply(link, apt.HW_GET_INFO, apt.hw_info(self.serial_number, self.model, 16, self.firmware,
                                                           "L490MZ lab jack (fluxmap simulator)", 1, 0, 1), to=to)
        elif mid == apt.MOD_IDENTIFY:
            self.identify_count += 1
        elif mid == apt.MOD_SET_CHANENABLESTATE:
            self.enabled = msg.param2 == 1
        elif mid == apt.MOD_REQ_CHANENABLESTATE:
            self._reply(link, apt.MOD_GET_CHANENABLESTATE, p1=msg.param1, p2=1 if self.enabled else 2, to=to)
        elif mid == apt.MOT_SET_POSCOUNTER and len(d) >= 6:
            _, pos = apt.POSCOUNTER.unpack_from(d)
            with self._lock:
                self._offset = pos - self._physical()
        elif mid == apt.MOT_REQ_POSCOUNTER:
            self._reply(link, apt.MOT_GET_POSCOUNTER, apt.POSCOUNTER.pack(msg.param1 or 1, self.position_counter), to=to)
        elif mid == apt.MOT_SET_VELPARAMS and len(d) >= apt.VELPARAMS.size:
            self.velparams = apt.VELPARAMS.unpack_from(d)[1:]
        elif mid == apt.MOT_REQ_VELPARAMS:
            self._reply(link, apt.MOT_GET_VELPARAMS, apt.VELPARAMS.pack(msg.param1 or 1, *self.velparams), to=to)
        elif mid == apt.MOT_SET_HOMEPARAMS and len(d) >= apt.HOMEPARAMS.size:
            self.homeparams = apt.HOMEPARAMS.unpack_from(d)
        elif mid == apt.MOT_REQ_HOMEPARAMS:
            self._reply(link, apt.MOT_GET_HOMEPARAMS, apt.HOMEPARAMS.pack(msg.param1 or 1, *self.homeparams[1:]), to=to)
        elif mid == apt.MOT_MOVE_HOME:
            if self.enabled:
                self.homed = False
                self._start(self.travel_mm[0] * self.counts_per_mm + self._offset, link, "home", move_fault)
        elif mid == apt.MOT_MOVE_ABSOLUTE:  # with a position, or header only: the stored MOVEABSPARAMS
            if self.enabled:
                pos = struct.unpack_from("<i", d, 2)[0] if len(d) >= 6 else \
                    struct.unpack("<i", self.params[apt.MOT_SET_MOVEABSPARAMS])[0]
                self._start(pos, link, "move", move_fault)
        elif mid == apt.MOT_MOVE_RELATIVE:
            if self.enabled:
                dist = struct.unpack_from("<i", d, 2)[0] if len(d) >= 6 else \
                    struct.unpack("<i", self.params[apt.MOT_SET_MOVERELPARAMS])[0]
                self._start(self.position_counter + dist, link, "move", move_fault)
        elif mid == apt.MOT_MOVE_JOG:  # p2: 1 forward, 2 reverse; a step of the jog step size
            if self.enabled:
                step = struct.unpack_from("<i", self.params[apt.MOT_SET_JOGPARAMS], 2)[0]
                self._start(self.position_counter + (step if msg.param2 == 1 else -step), link, "move", move_fault)
        elif mid == apt.MOT_MOVE_VELOCITY:  # p2: 1 forward, 2 reverse; runs until stopped or at a limit
            if self.enabled:
                end = self.travel_mm[1] if msg.param2 == 1 else self.travel_mm[0]
                self._start(end * self.counts_per_mm + self._offset, link, "move", move_fault)
        elif mid in self.params and len(d) >= 2 + len(self.params[mid]):
            self.params[mid] = d[2:2 + len(self.params[mid])]
        elif mid - 1 in self.params:  # a REQ: answer with the GET (REQ + 1)
            self._reply(link, mid + 1, struct.pack("<H", msg.param1 or 1) + self.params[mid - 1], to=to)
        elif mid == apt.MOT_MOVE_STOP:
            self._stop_motion(immediate=msg.param2 != 2)
        elif mid == apt.MOT_REQ_STATUSUPDATE:
            self._reply(link, apt.MOT_GET_STATUSUPDATE, self._status_block(), to=to)
        elif mid == apt.MOT_REQ_STATUSBITS:
            self._reply(link, apt.MOT_GET_STATUSBITS, apt.STATUS_BITS.pack(msg.param1 or 1, self.status_bits()), to=to)
        # anything else (MOT_ACK_STATUSUPDATE keep-alives, unknown ids) is ignored

