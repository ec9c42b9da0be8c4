"""The rig's devices: serial drivers (FW102C filter wheel, APT lab jack) and their simulators.

Drivers open their ports with :func:`serial.serial_for_url`, so ``/dev/ttyUSB0``, a pseudo
terminal and ``socket://HOST:PORT`` behave the same.  Simulators (:mod:`.sim`) serve the same
wire formats over a pseudo terminal or a loopback socket.  Protocol facts:
``shared/reference/hardware.md``.
"""

from .errors import DeviceError

__all__ = ["DeviceError"]
