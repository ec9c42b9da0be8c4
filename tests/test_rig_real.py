"""Opt-in tests on the real devices: ``pytest tests/test_rig_real.py --fw102c /dev/ttyUSB0
--labjack /dev/ttyUSB1 [--labjack-counts-per-mm N] [--labjack-home]``.  Skipped by default.

They move only a little: the wheel visits every position and returns; the jack goes up
0.5 mm and back (never homes unless --labjack-home is given: an animal may be on it).
"""

import time

import pytest

from fluxcli.hardware.apt_labjack import AptLabJack
from fluxcli.hardware.fw102c import FW102C


def test_real_fw102c(fw102c_port):
    with FW102C(fw102c_port, timeout_s=3.0) as wheel:
        assert "FW102C" in wheel.identify() or "FW212C" in wheel.identify()
        start = wheel.position
        for pos in list(range(1, wheel.positions + 1)) + [start]:
            t0 = time.monotonic()
            assert wheel.move_to(pos) == pos
            print(f"pos={pos}: {time.monotonic() - t0:.2f} s")
        wheel.set_sensors(True)


def test_real_labjack(labjack_port, request):
    cpm = request.config.getoption("--labjack-counts-per-mm")
    with AptLabJack(labjack_port, counts_per_mm=cpm) as jack:
        print(jack.identify(), jack.info(), "default velocity params:", jack.default_velparams)
        if request.config.getoption("--labjack-home"):
            assert jack.home() == pytest.approx(0.0, abs=1e-3)
        z0 = jack.position_mm()
        up = min(z0 + 0.5, jack.travel_mm[1])
        assert jack.move_to_mm(up) == pytest.approx(up, abs=1e-3)
        assert jack.move_to_mm(z0) == pytest.approx(z0, abs=1e-3)
