"""Thorlabs FW102C / FW212C filter wheel: ASCII driver on pyserial.

The wire (hardware.md): commands end in ``\\r``; the wheel echoes the whole command, prints its
reply lines (``\\r``, error lines possibly ``\\n``) and then the prompt ``> ``; after ``pos=n`` the
prompt comes only once the wheel is in position.  A bare ``\\r`` gives ``CMD_NOT_DEFINED``,
sometimes after a stray ``\\x00``: the driver sends one at connect to get in step.
"""

from __future__ import annotations

import time

import serial

from .errors import DeviceError
from .transport import SerialDriver

PROMPT = b"> "
#: Seconds per position at slow speed (fast is about 1 s); bounds the wait for a move.
SLOW_S_PER_POSITION = 2.0


class _Garbled(Exception):
    """A reply that does not parse (noise on the line): retried."""


class _Silent(Exception):
    """No prompt before the deadline."""


class FW102C(SerialDriver):
    """The filter wheel.

    Parameters
    ----------
    port : str or serial.Serial
        Port name or pyserial URL (opened with :func:`serial.serial_for_url`), or an open
        pyserial-like object (tests pass a scripted transport).
    positions : int
        6 or 12; checked against the wheel's ``pcount?``.
    time_scale : float
        Expected device times x this (simulators run faster); scales move timeouts.
    timeout_s : float
        Bound on any reply that is not a move (s).
    filters : dict of str to int, optional
        Filter names and their positions, for :meth:`select`.
    retries : int
        Extra attempts after a garbled reply, silence or a dropped connection.

    Examples
    --------
    >>> with FW102C("socket://127.0.0.1:40123", filters={"580nm": 3}) as wheel:  # doctest: +SKIP
    ...     wheel.select("580nm")
    """

    device = "filter wheel (FW102C)"

    def __init__(self, port: str | serial.SerialBase, *, positions: int = 6, time_scale: float = 1.0,
                 timeout_s: float = 2.0, filters: dict[str, int] | None = None, retries: int = 1):
        if positions not in (6, 12):
            raise ValueError(f"positions must be 6 or 12, not {positions}")
        self.positions = positions
        self.time_scale = float(time_scale)
        self.timeout_s = float(timeout_s)
        self.retries = int(retries)
        self.filters = dict(filters or {})
        for name, pos in self.filters.items():
            if not 1 <= pos <= positions:
                raise ValueError(f"filter {name!r} is at position {pos}, outside 1..{positions}")
        self._open(port)

    # ------------------------------------------------------------------ public
    def identify(self) -> str:
        """The wheel's identity line (``*idn?``), e.g. ``THORLABS FW102C/FW212C ... version 1.04``."""
        return self._query("*idn?")

    @property
    def position(self) -> int:
        """The position the wheel reports (``pos?``), 1..positions."""
        return self._query_int("pos?")

    @property
    def filter(self) -> str | None:
        """Name of the filter in the beam (None when the position has no name)."""
        pos = self.position
        return next((n for n, p in self.filters.items() if p == pos), None)

    def select(self, name: str) -> int:
        """Move the filter called ``name`` into the beam; return the position read back."""
        if name not in self.filters:
            raise DeviceError(self.device, self.url,
                              f"no filter called {name!r}; known: {sorted(self.filters)}", show_said=False)
        return self.move_to(self.filters[name])

    def move_to(self, pos: int) -> int:
        """Turn to position ``pos`` and block until the wheel is there; return the position read back.

        The wait is bounded by the distance moved (the shorter way round) at slow speed,
        x time_scale, plus ``timeout_s``.  A read-back that differs is retried once.
        """
        pos = int(pos)
        if not 1 <= pos <= self.positions:
            raise DeviceError(self.device, self.url, f"position {pos} is outside 1..{self.positions}",
                              show_said=False)
        got = None
        for _attempt in range(self.retries + 1):
            start = self.position
            steps = abs(pos - start)
            steps = min(steps, self.positions - steps)
            bound = self.timeout_s + 1.5 * SLOW_S_PER_POSITION * steps * self.time_scale
            self._command(f"pos={pos}", bound, retry=False)
            got = self.position
            if got == pos:
                return got
        raise DeviceError(self.device, self.url,
                          f"asked for position {pos}, the wheel reports {got} after {self.retries + 1} attempts",
                          str(got))

    def set_sensors(self, on: bool) -> None:
        """Position sensors on (1) or off when idle (0: less stray light in a dark box)."""
        self._command(f"sensors={1 if on else 0}", self.timeout_s)
        if self._query_int("sensors?") != (1 if on else 0):
            raise DeviceError(self.device, self.url, "sensors did not change", show_said=False)

    def set_speed(self, fast: bool) -> None:
        """Fast (1) or slow (0) moves."""
        self._command(f"speed={1 if fast else 0}", self.timeout_s)

    # ------------------------------------------------------------------ wire
    def _connect(self) -> None:
        """A bare \\r gets the wheel's parser in step (it answers CMD_NOT_DEFINED); then check pcount."""
        self._port.reset_input_buffer()
        self._port.write(b"\r")
        try:
            self._read_to_prompt(time.monotonic() + self.timeout_s)
        except _Silent as e:
            raise DeviceError(self.device, self.url, f"no prompt within {self.timeout_s:g} s at connect; "
                              "is this the filter wheel, and is it powered?", e.args[0]) from None
        pcount = self._query_int("pcount?")
        if pcount != self.positions:
            raise DeviceError(self.device, self.url,
                              f"the wheel has {pcount} positions (pcount?), the config says {self.positions}",
                              str(pcount))

    def _read_to_prompt(self, deadline: float) -> bytes:
        buf = b""
        while True:
            chunk = self._port.read(max(1, getattr(self._port, "in_waiting", 0) or 0))
            buf += chunk
            if chunk and buf.endswith(PROMPT):
                return buf
            if time.monotonic() > deadline:  # checked even while bytes keep coming (a noisy line)
                raise _Silent(buf[-200:])

    def _exchange(self, cmd: str, bound_s: float) -> list[str]:
        """Send ``cmd``; return the reply lines after the echo.  Raises _Garbled/_Silent/DeviceError."""
        self._port.reset_input_buffer()
        self._port.write(cmd.encode("ascii") + b"\r")
        deadline = time.monotonic() + bound_s
        while True:
            raw = self._read_to_prompt(deadline)
            text = raw[: -len(PROMPT)].decode("latin-1").replace("\x00", "")
            lines = [ln.strip() for ln in text.replace("\n", "\r").split("\r")]
            lines = [ln for ln in lines if ln]
            if not lines:
                continue  # a stray prompt (an earlier reply's tail): keep reading
            if not lines[0].endswith(cmd):
                if any(ln.endswith(cmd) for ln in lines[1:]):
                    # a stale reply precedes ours in the same chunk
                    lines = lines[next(i for i, ln in enumerate(lines) if ln.endswith(cmd)):]
                elif lines[0].startswith("Command error"):
                    raise DeviceError(self.device, self.url, f"'{cmd}' was refused: {lines[0]}", raw)
                elif all(_looks_like_echo(ln) for ln in lines[:1]):
                    continue  # a stale reply to another command: wait for ours
                else:
                    raise _Garbled(raw)
            for ln in lines[1:]:
                if "Command error" in ln or "CMD_" in ln:
                    raise DeviceError(self.device, self.url, f"'{cmd}' was refused: {ln}", raw)
            return lines[1:]

    def _command(self, cmd: str, bound_s: float, retry: bool = True) -> list[str]:
        last: bytes | None = None
        attempts = self.retries + 1
        for attempt in range(attempts):
            try:
                return self._exchange(cmd, bound_s)
            except _Garbled as e:
                last = e.args[0]
                problem = f"garbled reply to '{cmd}'"
            except _Silent as e:
                last = e.args[0]
                problem = f"no prompt within {bound_s:.3g} s after '{cmd}'"
                if not retry and cmd.encode() in last:
                    # echoed but no prompt: the wheel took the move and did not finish it; resending would not help
                    raise DeviceError(self.device, self.url, problem + " (a stalled or blocked wheel?)",
                                      last) from None
            except (serial.SerialException, OSError) as e:
                last = str(e).encode()
                problem = f"connection lost during '{cmd}'"
                self._reopen()
        raise DeviceError(self.device, self.url, f"{problem} ({attempts} attempts)", last)

    def _query(self, cmd: str) -> str:
        for _ in range(self.retries + 1):
            lines = self._command(cmd, self.timeout_s)
            if lines:
                return lines[0]
        raise DeviceError(self.device, self.url, f"'{cmd}' gave no value", "")

    def _query_int(self, cmd: str) -> int:
        said = ""
        for _ in range(self.retries + 1):
            said = self._query(cmd)
            try:
                return int(said)
            except ValueError:
                continue  # noise in the value line: ask again
        raise DeviceError(self.device, self.url, f"'{cmd}' did not give a number", said)


def _looks_like_echo(line: str) -> bool:
    return line.startswith(("pos", "pcount", "*idn", "trig", "speed", "sensors", "baud", "save"))
