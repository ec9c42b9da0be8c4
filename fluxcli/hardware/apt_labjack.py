"""Thorlabs L490MZ motorised lab jack on its integrated APT controller: binary driver on pyserial.

At connect: stop update messages, HW_REQ_INFO, enable the channel, read the velocity
parameters and set our own (never trusting the defaults), read the status.  Never homes on
connect (an animal may be on the jack).  A move is complete when the status bits say it is no
longer moving *and* the position read back is the target; every wait is bounded, and
unsolicited messages (move completed/stopped, homed, status updates) are skipped.
"""

from __future__ import annotations

import struct
import time

import serial

from . import apt
from .errors import DeviceError
from .transport import SerialDriver


class _Garbled(Exception):
    """Bytes that do not frame as an APT message: resynchronise and retry."""


class _Silent(Exception):
    """No reply before the deadline."""


class AptLabJack(SerialDriver):
    """The vertical stage.

    Parameters
    ----------
    port : str or serial.Serial
        Port name or pyserial URL, or an open pyserial-like object.
    counts_per_mm : float
        Microsteps per mm of travel (*unverified* for the L490MZ: 134 737 or 2 155 789).
    travel_mm : (float, float)
        Allowed heights (mm); moves outside are refused before anything is sent.
    time_scale : float
        Expected device times x this (simulators run faster); scales move timeouts and polling.
    channel : int
        Motor channel.
    timeout_s : float
        Bound on a reply that is not a move (s).
    velocity_mm_s, acceleration_mm_s2 : float
        Set at connect (default 0.5 mm/s, 0.5 mm/s^2).
    velocity_scale, acceleration_scale : float
        Device velocity units per count/s and acceleration units per count/s^2
        (Trinamic controllers: 53.68 and 1/90.9; *unverified* for the L490MZ).
    retries : int
        Extra attempts after silence, noise or a dropped connection.
    """

    device = "stage (APT lab jack)"

    def __init__(self, port: str | serial.SerialBase, *, counts_per_mm: float,
                 travel_mm: tuple[float, float] = (0.0, 50.0), time_scale: float = 1.0, channel: int = 1,
                 timeout_s: float = 2.0, velocity_mm_s: float = 0.5, acceleration_mm_s2: float = 0.5,
                 velocity_scale: float = 53.68, acceleration_scale: float = 1 / 90.9, retries: int = 1):
        if counts_per_mm <= 0:
            raise ValueError("counts_per_mm must be positive")
        if travel_mm[0] >= travel_mm[1]:
            raise ValueError(f"travel_mm must be [low, high] with low < high, not {list(travel_mm)}")
        self.counts_per_mm = float(counts_per_mm)
        self.travel_mm = (float(travel_mm[0]), float(travel_mm[1]))
        self.time_scale = float(time_scale)
        self.channel = int(channel)
        self.timeout_s = float(timeout_s)
        self.velocity_mm_s = float(velocity_mm_s)
        self.acceleration_mm_s2 = float(acceleration_mm_s2)
        self.velocity_scale = float(velocity_scale)
        self.acceleration_scale = float(acceleration_scale)
        self.retries = int(retries)
        self.tolerance_counts = max(1, round(0.001 * self.counts_per_mm))  # 1 um
        self.default_velparams: tuple[int, int, int] | None = None
        self._info: dict | None = None
        self._buf = b""
        self._open(port, rtscts=True)

    # ------------------------------------------------------------------ public
    def identify(self) -> str:
        """Flash the front panel (MOD_IDENTIFY) and return ``"<model> s/n <serial>, firmware <x.y.z>"``."""
        self._send(apt.short(apt.MOD_IDENTIFY, self.channel))
        i = self.info()
        return f"{i['model']} s/n {i['serial_number']}, firmware {i['firmware']}"

    def info(self) -> dict:
        """HW_GET_INFO as a dict (serial_number, model, hw_type, firmware, notes, hw_version, mod_state, n_channels)."""
        msg = self._query(apt.short(apt.HW_REQ_INFO), apt.HW_GET_INFO, data_size=apt.HW_INFO.size)
        self._info = apt.parse_hw_info(msg.data)
        return dict(self._info)

    def status_bits(self) -> int:
        """The channel's status bits (MOT_REQ_STATUSBITS)."""
        msg = self._query(apt.short(apt.MOT_REQ_STATUSBITS, self.channel), apt.MOT_GET_STATUSBITS,
                          data_size=apt.STATUS_BITS.size)
        return apt.STATUS_BITS.unpack(msg.data[:apt.STATUS_BITS.size])[1]

    def position_counts(self) -> int:
        """The position counter (microsteps)."""
        msg = self._query(apt.short(apt.MOT_REQ_POSCOUNTER, self.channel), apt.MOT_GET_POSCOUNTER,
                          data_size=apt.POSCOUNTER.size)
        return apt.POSCOUNTER.unpack(msg.data[:apt.POSCOUNTER.size])[1]

    def position_mm(self) -> float:
        """The stage height read from the controller (mm)."""
        return self.position_counts() / self.counts_per_mm

    def move_to_mm(self, z_mm: float) -> float:
        """Move to height ``z_mm`` and block until there; return the height read back (mm).

        Refused (DeviceError) outside ``travel_mm``.  Complete when the status bits say
        not moving and the position read back is the target (within 1 um); one retry when
        it stopped elsewhere.  The wait is bounded by the move's duration at the set velocity
        and acceleration x time_scale x 2, plus ``timeout_s``.
        """
        z_mm = float(z_mm)
        lo, hi = self.travel_mm
        if not lo <= z_mm <= hi:
            raise DeviceError(self.device, self.url, f"height {z_mm:g} mm is outside the travel "
                              f"[{lo:g}, {hi:g}] mm (rig.stage.travel_mm); nothing was moved", show_said=False)
        target = round(z_mm * self.counts_per_mm)
        last = None
        for _attempt in range(self.retries + 1):
            start = self.position_counts()
            self._send(apt.with_data(apt.MOT_MOVE_ABSOLUTE, apt.POSCOUNTER.pack(self.channel, target)))
            status, pos = self._wait_still(abs(target - start) / self.counts_per_mm, f"move to {z_mm:g} mm")
            if abs(pos - target) <= self.tolerance_counts:
                return pos / self.counts_per_mm
            last = (status, pos)
        status, pos = last
        raise DeviceError(self.device, self.url,
                          f"move to {z_mm:g} mm ended at {pos / self.counts_per_mm:.4f} mm "
                          f"(status 0x{status:08X}) after {self.retries + 1} attempts", show_said=False)

    def home(self) -> float:
        """Home (towards the lower limit) and wait; return the height read back (mm).  Only when asked."""
        msg = self._query(apt.short(apt.MOT_REQ_HOMEPARAMS, self.channel), apt.MOT_GET_HOMEPARAMS,
                          data_size=apt.HOMEPARAMS.size)
        home_velocity = apt.HOMEPARAMS.unpack(msg.data[:apt.HOMEPARAMS.size])[3]
        home_mm_s = max(home_velocity / (self.counts_per_mm * self.velocity_scale), 0.01)
        self._send(apt.short(apt.MOT_MOVE_HOME, self.channel))
        span = self.travel_mm[1] - self.travel_mm[0]
        # homing runs at the controller's homing velocity (about 0.4 mm/s): bound it by the whole travel
        status, pos = self._wait_still(span, "homing", velocity_mm_s=home_mm_s)
        if not status & apt.ST_HOMED:
            raise DeviceError(self.device, self.url, f"homing ended without the homed bit (status 0x{status:08X})",
                              show_said=False)
        return pos / self.counts_per_mm

    def stop(self, immediate: bool = True) -> None:
        """Stop any motion (immediate or profiled) and wait until the stage is still."""
        self._send(apt.short(apt.MOT_MOVE_STOP, self.channel, 1 if immediate else 2))
        self._wait_still(0.0, "stop")

    # ------------------------------------------------------------------ connect
    def _connect(self) -> None:
        self._port.reset_input_buffer()
        self._send(apt.short(apt.HW_STOP_UPDATEMSGS))  # we poll; a stream of 0x0481 would only be skipped
        try:
            info = self.info()
        except DeviceError as e:
            raise DeviceError(self.device, self.url, e.problem + "; is this the stage's APT controller, "
                              "and is it powered?", e.said) from None
        if info["n_channels"] < self.channel:
            raise DeviceError(self.device, self.url, f"the controller has {info['n_channels']} channel(s), "
                              f"channel {self.channel} was asked for", show_said=False)
        self._send(apt.short(apt.MOD_SET_CHANENABLESTATE, self.channel, 1))
        self.default_velparams = self._velparams()
        want = (0, round(self.acceleration_mm_s2 * self.counts_per_mm * self.acceleration_scale),
                round(self.velocity_mm_s * self.counts_per_mm * self.velocity_scale))
        self._send(apt.with_data(apt.MOT_SET_VELPARAMS, apt.VELPARAMS.pack(self.channel, *want)))
        got = self._velparams()
        if got != want:
            raise DeviceError(self.device, self.url, f"velocity parameters (min, acc, max) read back as {got}, "
                              f"{want} were set", show_said=False)
        status = self.status_bits()
        if status & apt.ST_MOVING_ANY:  # moving at connect (another client?): stop it, do not home
            self.stop(immediate=True)

    def _velparams(self) -> tuple[int, int, int]:
        msg = self._query(apt.short(apt.MOT_REQ_VELPARAMS, self.channel), apt.MOT_GET_VELPARAMS,
                          data_size=apt.VELPARAMS.size)
        return apt.VELPARAMS.unpack(msg.data[:apt.VELPARAMS.size])[1:]

    # ------------------------------------------------------------------ waiting
    def _wait_still(self, distance_mm: float, what: str, velocity_mm_s: float | None = None) -> tuple[int, int]:
        v = velocity_mm_s or self.velocity_mm_s
        expected_s = distance_mm / v + v / self.acceleration_mm_s2
        bound_s = self.timeout_s + 2.0 * expected_s * self.time_scale
        deadline = time.monotonic() + bound_s
        period = min(0.1, max(0.005, 0.1 * self.time_scale))
        while True:
            status = self.status_bits()
            if status & apt.ST_MOTION_ERROR:
                raise DeviceError(self.device, self.url, f"{what}: motion error (status 0x{status:08X})",
                                  show_said=False)
            if not status & apt.ST_MOVING_ANY:
                return status, self.position_counts()
            if time.monotonic() > deadline:
                pos = self.position_counts()
                try:
                    self._send(apt.short(apt.MOT_MOVE_STOP, self.channel, 1))
                finally:
                    raise DeviceError(self.device, self.url,
                                      f"{what} did not complete within {bound_s:.3g} s "
                                      f"(still moving at {pos / self.counts_per_mm:.4f} mm, status "
                                      f"0x{status:08X}); the stage was told to stop", show_said=False)
            time.sleep(period)

    # ------------------------------------------------------------------ wire
    def _send(self, raw: bytes) -> None:
        try:
            self._port.write(raw)
        except (serial.SerialException, OSError):
            self._reopen()
            self._port.write(raw)

    def _read_message(self, deadline: float) -> apt.Message:
        while True:
            msg, used = apt.decode(self._buf)
            if msg is not None:
                self._buf = self._buf[used:]
                return msg
            if len(self._buf) >= 6:
                msgid, dest, src, _, length = apt.parse_header(self._buf[:6])
                if dest != apt.HOST or src != apt.USB_UNIT or (length or 0) > apt.MAX_DATA:
                    raise _Garbled(self._buf)
            if time.monotonic() > deadline:  # checked even while bytes keep coming
                raise _Silent(self._buf[-200:])
            self._buf += self._port.read(max(1, getattr(self._port, "in_waiting", 0) or 0))

    def _drain(self) -> None:
        """Read what is waiting before a request: skip stale and unsolicited messages and noise,
        but raise on an error report (e.g. a refused move), which must not go unnoticed."""
        raw = self._buf
        while getattr(self._port, "in_waiting", 0):
            chunk = self._port.read(self._port.in_waiting)
            if not chunk:
                break
            raw += chunk
        self._buf = b""
        while len(raw) >= 6:
            msg, used = apt.decode(raw)
            if msg is None:
                break
            if msg.dest != apt.HOST or msg.src != apt.USB_UNIT:
                raw = raw[1:]  # noise: slide until something frames
                continue
            raw = raw[used:]
            if msg.msgid in (apt.HW_RESPONSE, apt.HW_RICHRESPONSE):
                raise DeviceError(self.device, self.url, f"the controller reported an error "
                                  f"{_describe_error(msg)}", msg.encode())

    def _exchange(self, request: bytes, reply_id: int, data_size: int) -> apt.Message:
        self._drain()
        self._port.write(request)
        deadline = time.monotonic() + self.timeout_s
        while True:
            msg = self._read_message(deadline)
            if msg.msgid == reply_id:
                if msg.data is None or len(msg.data) < data_size:
                    raise _Garbled(msg.encode())
                return msg
            if msg.msgid in (apt.HW_RESPONSE, apt.HW_RICHRESPONSE):
                raise DeviceError(self.device, self.url, f"the controller reported an error "
                                  f"{_describe_error(msg)}", msg.encode())
            # unsolicited (move completed/stopped, homed, status update) or unknown: skip, within the bound
            if time.monotonic() > deadline:
                raise _Silent(msg.encode())

    def _query(self, request: bytes, reply_id: int, data_size: int) -> apt.Message:
        name = apt.NAMES.get(int.from_bytes(request[:2], "little"), "?")
        last = b""
        for _attempt in range(self.retries + 1):
            try:
                return self._exchange(request, reply_id, data_size)
            except _Garbled as e:
                last, problem = e.args[0], f"garbled reply to {name}"
                time.sleep(0.02)  # let the rest of the noise arrive, then drop it
            except _Silent as e:
                last, problem = e.args[0], f"no reply to {name} within {self.timeout_s:g} s"
            except (serial.SerialException, OSError) as e:
                last, problem = str(e).encode(), f"connection lost during {name}"
                self._reopen()
        raise DeviceError(self.device, self.url, f"{problem} ({self.retries + 1} attempts)", last)

    def _reopen(self) -> None:
        super()._reopen()
        self._buf = b""


def _describe_error(msg: apt.Message) -> str:
    if msg.msgid == apt.HW_RICHRESPONSE and msg.data is not None and len(msg.data) >= 4:
        mid, code = struct.unpack_from("<HH", msg.data)
        notes = msg.data[4:68].split(b"\x00")[0].decode("latin-1").strip()
        return f"(code {code}) about {apt.NAMES.get(mid, f'0x{mid:04X}')}: {notes!r}"
    if msg.data is not None:
        return f"(HW_RESPONSE {msg.data.hex()})"
    return f"(HW_RESPONSE p1={msg.param1} p2={msg.param2})"
