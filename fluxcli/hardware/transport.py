"""Opening a port: anything :func:`serial.serial_for_url` opens, tolerant of pseudo terminals."""

from __future__ import annotations

import errno

import serial

from .errors import DeviceError


def open_port(url: str, *, baudrate: int = 115200, timeout_s: float = 0.05, rtscts: bool = False,
              device: str = "device") -> serial.SerialBase:
    """Open ``url`` (``/dev/ttyUSB0``, a pty path, ``socket://HOST:PORT``, ``loop://``) at 8N1.

    Parameters
    ----------
    url : str
        Port name or pyserial URL.
    baudrate : int
        Line rate (bits/s); ignored by ``socket://``.
    timeout_s : float
        Read timeout of a single ``read`` call (s); drivers loop on their own deadlines.
    rtscts : bool
        Hardware flow control.  A pseudo terminal refuses the RTS ioctl: then the port is
        reopened without flow control rather than failing.
    device : str
        Device name used in the error message.

    Raises
    ------
    DeviceError
        When the port cannot be opened (missing, permission denied, refused).
    """
    def _open(flow: bool) -> serial.SerialBase:
        port = serial.serial_for_url(url, do_not_open=True, baudrate=baudrate, bytesize=8, parity="N",
                                     stopbits=1, timeout=timeout_s, write_timeout=max(1.0, timeout_s),
                                     rtscts=flow)
        port.open()
        return port

    try:
        try:
            return _open(rtscts)
        except (serial.SerialException, OSError) as e:
            if not rtscts or getattr(e, "errno", None) not in (errno.EINVAL, errno.ENOTTY, None):
                raise
            # A pseudo terminal (simulators, socat) has no modem lines: run without flow control.
            return _open(False)
    except (serial.SerialException, OSError, ValueError) as e:
        hint = ""
        if isinstance(e, PermissionError) or "Permission denied" in str(e):
            hint = " Add yourself to the 'dialout' group or install a udev rule (see the README's Hardware section)."
        raise DeviceError(device, url, f"cannot open the port: {e}.{hint}", show_said=False) from None


class SerialDriver:
    """What the drivers share: the port (opened here from a URL, or given), closing, reopening.

    Subclasses set ``device`` (a name for messages), implement ``_connect`` (the greeting) and
    call :meth:`_open` at the end of ``__init__``.
    """

    device = "device"

    def _open(self, port: "str | serial.SerialBase", *, rtscts: bool = False) -> None:
        if isinstance(port, str):
            self.url = port
            self._port = open_port(port, timeout_s=0.02, rtscts=rtscts, device=self.device)
        else:
            self.url = getattr(port, "port", None) or getattr(port, "name", None) or repr(port)
            self._port = port
        try:
            self._connect()
        except BaseException:
            self.close()
            raise

    def _connect(self) -> None:  # pragma: no cover - each driver greets its device
        raise NotImplementedError

    def _reopen(self) -> None:
        """After a dropped connection: close and open again (a socket reconnects)."""
        try:
            self._port.close()
            self._port.open()
        except (serial.SerialException, OSError, AttributeError):
            pass

    def close(self) -> None:
        """Close the port."""
        port, self._port = getattr(self, "_port", None), None
        if port is not None:
            try:
                port.close()
            except Exception:  # noqa: BLE001 - closing must not mask the real error
                pass

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()
