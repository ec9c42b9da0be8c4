"""The drivers against the simulators over a real pseudo terminal and a loopback socket."""

import time

import pytest

from fluxcli.hardware import DeviceError
from fluxcli.hardware.apt_labjack import AptLabJack
from fluxcli.hardware.fw102c import FW102C
from fluxcli.hardware.sim import FW102CSimulator, LabJackSimulator

TS = 0.02  # simulated time x this
CPM = 134737.0


@pytest.fixture(params=["pty", "socket://127.0.0.1:0"])
def url_kind(request):
    return request.param


@pytest.fixture
def wheel_sim(url_kind):
    sim = FW102CSimulator(time_scale=TS)
    sim.start(url_kind)
    yield sim
    sim.stop()


@pytest.fixture
def jack_sim(url_kind):
    sim = LabJackSimulator(time_scale=TS, counts_per_mm=CPM)
    sim.start(url_kind)
    yield sim
    sim.stop()


def test_wheel_moves_with_real_timing(wheel_sim):
    with FW102C(wheel_sim.url, time_scale=TS, filters={"580nm": 3, "650nm": 4}) as wheel:
        assert wheel.identify().startswith("THORLABS FW102C")
        assert wheel.position == 1
        t0 = time.monotonic()
        assert wheel.select("580nm") == 3
        took = time.monotonic() - t0
        # two positions at ~1 s each (fast), x time_scale; the prompt comes only once in position
        assert 2 * 1.0 * TS * 0.9 < took < 2 * 1.0 * TS + 0.5
        assert wheel_sim.position == 3 and wheel.filter == "580nm"
        assert wheel.move_to(6) == 6          # 3 -> 6: three positions
        assert wheel.move_to(1) == 1          # 6 -> 1: one position the short way round
        wheel.set_sensors(False)
        assert wheel_sim.sensors == 0


def test_stage_moves_and_reads_back(jack_sim):
    with AptLabJack(jack_sim.url, counts_per_mm=CPM, time_scale=TS) as jack:
        assert jack_sim.enabled and not jack_sim.homed           # enabled at connect, never homed
        assert jack.info()["model"] == "L490MZ"
        t0 = time.monotonic()
        assert jack.move_to_mm(10.0) == pytest.approx(10.0, abs=1e-5)
        took = time.monotonic() - t0
        # 10 mm at 0.5 mm/s plus the ramps (1 s) = 21 s of device time
        assert 21 * TS * 0.9 < took < 21 * TS + 0.5
        assert jack_sim.position_mm == pytest.approx(10.0, abs=1e-5)
        with pytest.raises(DeviceError, match="outside the travel"):
            jack.move_to_mm(60.0)
        assert jack_sim.position_mm == pytest.approx(10.0, abs=1e-5)
