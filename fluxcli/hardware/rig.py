"""The rig's devices from the ``rig:`` config section: start simulators, open drivers.

``rig_section`` is the validated :class:`fluxcli.config.Rig` (or anything with the same
attributes).  A port ``"pty"`` or ``"socket://HOST:0"`` means "simulate this device here".
"""

from __future__ import annotations

import re
from urllib.parse import urlparse

from ..errors import UserError
from . import apt
from .apt_labjack import AptLabJack
from .camera import DeviceIdentity
from .errors import DeviceError
from .fw102c import FW102C
from .sim import FW102CSimulator, LabJackSimulator

DEVICES = ("filter_wheel", "stage")


def is_simulator_port(port: str) -> bool:
    """True for ``"pty"`` and ``socket://HOST:0`` (a simulator picks the port)."""
    if port == "pty":
        return True
    if port.startswith("socket://"):
        try:
            return urlparse(port).port == 0
        except ValueError:
            return False
    return False


FW102C_COMMANDS = ("*idn?", "pos", "pcount", "trig", "speed", "sensors", "baud", "save")


def _faults(name: str, section) -> list[dict]:
    """The section's faults as dicts, each ``on`` checked against what the device understands."""
    faults = [f.model_dump() if hasattr(f, "model_dump") else dict(f) for f in (section.faults or ())]
    for i, fault in enumerate(faults):
        on = str(fault.get("on", "*"))
        if on == "*":
            continue
        if name == "stage":
            known = {n.lower() for n in apt.NAMES.values()} | {f"0x{m:04x}" for m in apt.NAMES}
            ok = any(k.startswith(on.lower()) for k in known)
            what = "an APT message name or id (MOT_MOVE_ABSOLUTE, 0x0453)"
        else:
            ok = any(on.startswith(c) or c.startswith(on) for c in FW102C_COMMANDS)
            what = "an FW102C command prefix (pos=, pos?, *idn?)"
        if not ok:
            raise UserError(f"'rig.{name}.faults.{i}.on': {on!r} is not '*' or {what}.")
    return faults


def make_simulator(name: str, rig_section):
    """A simulator (not started) of device ``name`` ("filter_wheel" or "stage") as configured."""
    section = getattr(rig_section, name)
    if name == "filter_wheel":
        return FW102CSimulator(positions=section.positions, time_scale=rig_section.time_scale,
                               faults=_faults(name, section))
    if name == "stage":
        return LabJackSimulator(counts_per_mm=section.counts_per_mm, travel_mm=tuple(section.travel_mm),
                                time_scale=rig_section.time_scale, faults=_faults(name, section),
                                velocity_scale=section.velocity_scale,
                                acceleration_scale=section.acceleration_scale)
    raise ValueError(f"no simulator for device {name!r}")


def start_simulators(rig_section, *, every: bool = False) -> dict:
    """Start a simulator for each device whose port is a simulator port (``every``: for each device,
    serving on its port, e.g. a fixed ``socket://0.0.0.0:5000``); return ``{name: simulator}``,
    each with ``.url`` set to where it serves."""
    sims: dict = {}
    try:
        for name in DEVICES:
            section = getattr(rig_section, name, None)
            if section is None:
                continue
            if not (is_simulator_port(section.port) or (every and section.port.startswith("socket://"))):
                if every:
                    raise DeviceError(f"rig.{name}", section.port, "a simulator serves on 'pty' or "
                                      "'socket://HOST:PORT', not on a device path", show_said=False)
                continue
            sim = make_simulator(name, rig_section)
            try:
                sim.start(section.port)
            except OSError as e:
                raise DeviceError(f"rig.{name} simulator", section.port, f"cannot serve there: {e}",
                                  show_said=False) from None
            sims[name] = sim
    except BaseException:
        for sim in sims.values():
            sim.stop()
        raise
    return sims


def open_devices(rig_section, urls: dict | None = None) -> tuple[FW102C | None, AptLabJack | None]:
    """Open the drivers of the configured devices; ``urls[name]`` (e.g. a simulator's URL)
    overrides the configured port."""
    urls = dict(urls or {})
    for name, value in list(urls.items()):
        if hasattr(value, "url"):
            urls[name] = value.url
    for name in DEVICES:
        section = getattr(rig_section, name, None)
        if section is not None and name not in urls and is_simulator_port(section.port):
            raise DeviceError(f"rig.{name}", section.port, "this port means 'simulate the device here': "
                              "start it with start_simulators() (or `fluxmap rig serve`) and pass its URL",
                              show_said=False)
    wheel = stage = None
    try:
        if rig_section.filter_wheel is not None:
            wheel = open_filter_wheel(rig_section, urls.get("filter_wheel"))
        if rig_section.stage is not None:
            stage = open_stage(rig_section, urls.get("stage"))
    except BaseException:
        if wheel is not None:
            wheel.close()
        raise
    return wheel, stage


def open_filter_wheel(rig_section, url: str | None = None) -> FW102C:
    """The FW102C driver on ``url`` (default: the configured port)."""
    fw = rig_section.filter_wheel
    return FW102C(url or fw.port, positions=fw.positions, time_scale=rig_section.time_scale, timeout_s=fw.timeout_s,
                  filters=dict(fw.filters))


def open_stage(rig_section, url: str | None = None) -> AptLabJack:
    """The lab-jack driver on ``url`` (default: the configured port)."""
    st = rig_section.stage
    return AptLabJack(url or st.port, counts_per_mm=st.counts_per_mm, travel_mm=tuple(st.travel_mm),
                      time_scale=rig_section.time_scale, channel=st.channel, timeout_s=st.timeout_s,
                      velocity_mm_s=st.velocity_mm_s, acceleration_mm_s2=st.acceleration_mm_s2,
                      velocity_scale=st.velocity_scale, acceleration_scale=st.acceleration_scale)


# --------------------------------------------------------------------------- device checks (fluxmap rig check)
def wheel_identity(wheel: FW102C) -> DeviceIdentity:
    """Model and firmware from the wheel's ``*idn?`` line (the FW102C reports no serial number)."""
    line = wheel.identify().strip()
    version = re.search(r"version\s+(\S+)", line, flags=re.I)
    return DeviceIdentity(line, "", version.group(1) if version else "")


def stage_identity(stage: AptLabJack) -> DeviceIdentity:
    """Model, serial number and firmware from the controller's HW_GET_INFO."""
    info = stage.info()
    return DeviceIdentity(str(info["model"]), str(info["serial_number"]), str(info["firmware"]))


def exercise_wheel(wheel: FW102C) -> list[str]:
    """Visit every named filter's position (in position order) and return to the start;
    each position is read back by the driver.  Returns what happened, in words."""
    start = wheel.position
    names = {p: n for n, p in wheel.filters.items()}
    visited = [f"{p} ({names[p]})" for p in sorted(names) if wheel.move_to(p) == p]
    wheel.move_to(start)
    return [f"at position {start}; visited {', '.join(visited) or 'no named filter'}; back at {wheel.position}"]


def exercise_stage(stage: AptLabJack, *, step_mm: float = 0.5) -> list[str]:
    """Move ``step_mm`` up (down when that leaves the travel) and back, never homing (an
    animal may be on the jack).  Returns what happened, in words."""
    start = stage.position_mm()
    lo, hi = stage.travel_mm
    target = start + step_mm if start + step_mm <= hi else start - step_mm
    if not lo <= target <= hi:
        return [f"at {start:.4f} mm; no move (the travel {lo:g}..{hi:g} mm is narrower than {step_mm:g} mm)"]
    there = stage.move_to_mm(target)
    back = stage.move_to_mm(start)
    return [f"at {start:.4f} mm; moved to {there:.4f} mm and back to {back:.4f} mm (read back)"]
