"""A simulated FW102C filter wheel on its ASCII wire protocol (hardware.md).

Echoes every command with its ``\\r``, prints reply lines ending in ``\\r`` (error lines end in
``\\n``), then the prompt ``> ``, which after ``pos=n`` comes only once the wheel is in position
(about 1 s per position at fast speed, 2 s at slow, the shorter way round, x ``time_scale``).
Commands that arrive during a move wait, as on the device.  A bare ``\\r`` as the first thing
on a connection gets ``CMD_NOT_DEFINED`` after a stray ``\\x00`` (the connect noise of hardware.md);
a client that starts with a real command sees no noise.
"""

from __future__ import annotations

import threading
import time

from .base import Link, SerialSimulator

IDN = "THORLABS FW102C/FW212C Filter Wheel version 1.04"
S_PER_POSITION = {1: 1.0, 0: 2.0}  # speed mode -> seconds per position
MAX_LINE_BYTES = 4096  # what the simulator keeps of a line not yet ended by CR (the device's own buffer is smaller)


class FW102CSimulator(SerialSimulator):
    """The wheel.

    Parameters
    ----------
    positions : int
        6 or 12 (``pcount``).
    initial_position : int
        Where the wheel starts (1..positions).
    time_scale : float
        Device times x this.
    faults : list of dict or Faults, optional
        Injected faults (see :class:`~fluxcli.hardware.sim.base.Fault`); ``on`` is a command prefix.
    connect_noise : bool
        Answer a bare ``\\r`` first on a connection with a stray ``\\x00`` before the error.
    """

    name = "filter_wheel"

    def __init__(self, *, positions: int = 6, initial_position: int = 1, time_scale: float = 1.0,
                 faults=None, connect_noise: bool = True):
        super().__init__(time_scale=time_scale, faults=faults)
        if positions not in (6, 12):
            raise ValueError("positions must be 6 or 12")
        self.pcount = positions
        self.speed = 1
        self.trig = 0
        self.sensors = 1
        self.baud = 1
        self.saved: dict | None = None
        self.connect_noise = connect_noise
        self.log: list[bytes] = []  # every command received, for tests
        self._lock = threading.Lock()
        self._from = initial_position
        self._to = initial_position
        self._t0 = 0.0
        self._t_per = 1.0
        self._dir = 0
        self._steps = 0

    # ------------------------------------------------------------------ physics
    @property
    def position(self) -> int:
        """The physical position now (1..pcount); changes position by position during a move."""
        with self._lock:
            if self._steps == 0:
                return self._to
            done = int((time.monotonic() - self._t0) / self._t_per)
            if done >= self._steps:
                return self._to
            return (self._from - 1 + self._dir * done) % self.pcount + 1

    @property
    def moving(self) -> bool:
        with self._lock:
            return self._steps > 0 and time.monotonic() < self._t0 + self._steps * self._t_per

    def _start_move(self, target: int) -> float:
        """Start turning to ``target`` the shorter way; return the duration (s)."""
        here = self.position
        fwd = (target - here) % self.pcount
        back = (here - target) % self.pcount
        with self._lock:
            self._from, self._to = here, target
            self._dir, self._steps = (1, fwd) if fwd <= back else (-1, back)
            self._t_per = S_PER_POSITION[self.speed] * self.time_scale
            self._t0 = time.monotonic()
            return self._steps * self._t_per

    def _jam(self, at: int) -> None:
        with self._lock:
            self._from = self._to = at
            self._steps = 0

    # ------------------------------------------------------------------ wire
    def serve(self, link: Link) -> None:
        buf = b""
        while not self.stopping and not link.closed:
            data = link.read(0.02)
            if not data:
                continue
            buf += data
            while b"\r" in buf:
                line, buf = buf.split(b"\r", 1)
                self._handle(link, line)
                if link.closed or self.stopping:
                    return
            if len(buf) > MAX_LINE_BYTES:  # a client that never ends its line: its start is lost, as in a device's buffer
                buf = buf[-MAX_LINE_BYTES:]

    def _handle(self, link: Link, raw: bytes) -> None:
        cmd = raw.replace(b"\n", b"").replace(b"\x00", b"").decode("latin-1").strip()
        self.log.append(raw + b"\r")
        if link.fresh:
            link.fresh = False
            if self.connect_noise and not cmd:
                link.write(b"\x00")
        go_on, fault = self.line_fault(link, (cmd,), ("error_reply",))
        if not go_on:
            return
        if fault is not None and fault.kind == "error_reply":
            link.write(raw + b"\rCommand error CMD_NOT_DEFINED\n> ")
            return
        link.write(raw + b"\r")  # the echo
        reply, error = self._execute(cmd)
        out = b""
        if error:
            out += f"Command error {error}\n".encode()
        elif reply is not None:
            out += reply.encode("latin-1") + b"\r"
        link.write(out + b"> ")

    def _execute(self, cmd: str) -> tuple[str | None, str | None]:
        """(reply line or None, error code or None); blocks during a move."""
        if "=" in cmd:
            key, _, arg = cmd.partition("=")
            if not (arg.isascii() and arg.isdigit()) or len(arg) > 9:  # not '²' (latin-1 digits), nor 10^200000
                return None, "CMD_ARG_INVALID"
            value = int(arg)
            if key == "pos":
                if not 1 <= value <= self.pcount:
                    return None, "CMD_ARG_INVALID"
                fault = self.faults.take(("pos=",), ("stall", "wrong_position"))
                if fault is not None and fault.kind == "stall":
                    here = self.position
                    self._jam(here)
                    # the wheel is stuck: no prompt until the stall ends (0: until the simulator stops)
                    if fault.delay_s > 0:
                        self.sleep(fault.delay_s)
                    else:
                        self._stop.wait()
                    return None, None
                duration = self._start_move(value)
                if not self.sleep(duration):
                    return None, None
                if fault is not None and fault.kind == "wrong_position":
                    self._jam((value - 1 + int(fault.offset)) % self.pcount + 1)
                return None, None
            if key == "pcount" and value in (6, 12):
                self.pcount = value
                if self.position > value:
                    self._jam(1)
                return None, None
            if key in ("speed", "trig", "sensors", "baud") and value in (0, 1):
                setattr(self, key, value)
                return None, None
            if key in ("pcount", "speed", "trig", "sensors", "baud"):
                return None, "CMD_ARG_INVALID"
            return None, "CMD_NOT_DEFINED"
        if cmd == "save":
            self.saved = {"pcount": self.pcount, "speed": self.speed, "trig": self.trig,
                          "sensors": self.sensors, "baud": self.baud}
            return None, None
        if cmd == "*idn?":
            return IDN, None
        if cmd == "pos?":
            return str(self.position), None
        if cmd in ("pcount?", "speed?", "trig?", "sensors?", "baud?"):
            return str(getattr(self, cmd[:-1])), None
        return None, "CMD_NOT_DEFINED"
