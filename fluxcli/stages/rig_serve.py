"""``fluxmap rig serve CONFIG``: simulators of the configured devices, served until a signal.

Prints ``<device> <url-or-pty-path>`` per device, then ``ready`` (flushed), and serves until
SIGINT or SIGTERM (exit 0).
"""

from __future__ import annotations

import signal
import sys
import threading

from ..errors import UserError
from ..hardware.rig import start_simulators


def run(cfg, ctx) -> None:
    rig = cfg.model.rig
    if rig.filter_wheel is None and rig.stage is None:
        raise UserError(f"config {cfg.path}: 'rig' has neither 'filter_wheel' nor 'stage': nothing to serve.")
    done = threading.Event()
    previous = {s: signal.signal(s, lambda *_: done.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        sims = start_simulators(rig, every=True)
        try:
            for name, sim in sims.items():
                sys.stdout.write(f"{name} {sim.url}\n")
            sys.stdout.write("ready\n")
            sys.stdout.flush()
            while not done.wait(0.2):
                pass
        finally:
            for sim in sims.values():
                sim.stop()
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
    return None
