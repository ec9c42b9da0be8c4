"""Simulated devices serving the real wire protocols over a pseudo terminal or a loopback socket."""

from .base import FAULT_KINDS, Fault, Faults, SerialSimulator
from .fw102c import FW102CSimulator
from .labjack import LabJackSimulator

__all__ = ["FAULT_KINDS", "Fault", "Faults", "SerialSimulator", "FW102CSimulator", "LabJackSimulator"]
