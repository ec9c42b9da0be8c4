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
