"""Every injected fault ends in a retry that succeeds or a DeviceError naming the device and what
it said -- never a hang: each case runs under a watchdog."""

import threading
import time

import pytest

from fluxcli.hardware import DeviceError
from fluxcli.hardware.apt_labjack import AptLabJack
from fluxcli.hardware.fw102c import FW102C
from fluxcli.hardware.sim import FW102CSimulator, LabJackSimulator

TS = 0.01
CPM = 134737.0
WATCHDOG_S = 10.0


def bounded(fn, seconds=WATCHDOG_S):
    """Run ``fn`` in a thread; fail the test if it has not returned (or raised) within ``seconds``."""
    out: dict = {}

    def target():
        try:
            out["value"] = fn()
        except BaseException as e:  # noqa: BLE001 - handed back to the test
            out["error"] = e

    t = threading.Thread(target=target, daemon=True)
    t0 = time.monotonic()
    t.start()
    t.join(seconds)
    assert not t.is_alive(), f"hung for more than {seconds} s"
    out["elapsed"] = time.monotonic() - t0
    if "error" in out:
        raise out["error"]
    return out["value"]


@pytest.fixture
def where():
    """The fault matrix runs over a pty (pyserial's socket close sleeps 0.3 s); socket-specific
    cases (a dropped connection is a closed socket there) are below each matrix."""
    return "pty"


SOCKET = "socket://127.0.0.1:0"


def _fails_naming_the_device(run, device: str, said: str) -> None:
    """``run()`` raises a DeviceError whose message starts by naming the device and says ``said``."""
    with pytest.raises(DeviceError) as err:
        run()
    msg = str(err.value)
    assert msg.startswith(device) and said in msg, msg


def wheel_case(where, fault, action):
    sim = FW102CSimulator(time_scale=TS)
    sim.start(where)
    try:
        def run():
            with FW102C(sim.url, time_scale=TS, timeout_s=0.3) as wheel:
                sim.faults.add(**fault)
                return action(wheel, sim)
        return bounded(run)
    finally:
        sim.stop()


def jack_case(where, fault, action, at_connect=False):
    sim = LabJackSimulator(time_scale=TS, counts_per_mm=CPM, updates=True)
    sim.start(where)
    try:
        if at_connect:
            sim.faults.add(**fault)

        def run():
            with AptLabJack(sim.url, counts_per_mm=CPM, time_scale=TS, timeout_s=0.3) as jack:
                if not at_connect:
                    sim.faults.add(**fault)
                return action(jack, sim)
        return bounded(run)
    finally:
        sim.stop()


def wheel_move(wheel, sim):
    assert wheel.move_to(4) == 4
    return sim.position


def jack_move(jack, sim):
    z = jack.move_to_mm(3.0)
    return z, sim.position_mm


# ----------------------------------------------------------------------------- filter wheel
@pytest.mark.parametrize("fault", [
    {"kind": "no_reply", "on": "pos?"},
    {"kind": "late_reply", "on": "pos?", "delay_s": 0.5},       # later than the 0.3 s bound: retried
    {"kind": "late_reply", "on": "pos=", "delay_s": 0.1},       # late but within the bound
    {"kind": "garbage", "on": "pos?"},
    {"kind": "garbage", "on": "pos="},
    {"kind": "drop", "on": "pos?"},
    {"kind": "wrong_position", "on": "pos=", "offset": 1},
], ids=lambda f: f"{f['kind']}-{f['on']}")
def test_wheel_recovers(where, fault):
    assert wheel_case(where, fault, wheel_move) == 4


@pytest.mark.parametrize("fault, said", [
    ({"kind": "error_reply", "on": "pos="}, "CMD_NOT_DEFINED"),
    ({"kind": "stall", "on": "pos="}, "no prompt within"),
    ({"kind": "wrong_position", "on": "pos=", "count": 0}, "the wheel reports 5"),
    ({"kind": "no_reply", "on": "pos?", "count": 0}, "no prompt within 0.3 s after 'pos?' (2 attempts)"),
], ids=lambda v: v["kind"] if isinstance(v, dict) else "")
def test_wheel_fails_clearly(where, fault, said):
    _fails_naming_the_device(lambda: wheel_case(where, fault, wheel_move), "filter wheel (FW102C) on ", said)


@pytest.mark.parametrize("fault", [{"kind": "drop", "on": "pos?"}, {"kind": "drop", "on": "pos="},
                                   {"kind": "no_reply", "on": "pos="}, {"kind": "garbage", "on": "pos?"}],
                         ids=lambda f: f"{f['kind']}-{f['on']}")
def test_wheel_recovers_over_socket(fault):
    assert wheel_case(SOCKET, fault, wheel_move) == 4


def test_wheel_error_reply_names_what_it_said():
    with pytest.raises(DeviceError, match=r"'pos=4' was refused: Command error CMD_NOT_DEFINED.*it said: 'pos=4\\\\r"):
        wheel_case("socket://127.0.0.1:0", {"kind": "error_reply", "on": "pos="}, wheel_move)


# ----------------------------------------------------------------------------- stage
@pytest.mark.parametrize("fault", [
    {"kind": "no_reply", "on": "MOT_REQ_POSCOUNTER"},
    {"kind": "no_reply", "on": "MOT_MOVE_ABSOLUTE"},           # the move is lost: it never started; re-sent
    {"kind": "late_reply", "on": "MOT_REQ_STATUSBITS", "delay_s": 0.5},
    {"kind": "garbage", "on": "MOT_REQ_STATUSBITS"},
    {"kind": "garbage", "on": "0x0411"},
    {"kind": "drop", "on": "MOT_REQ_STATUSBITS"},
    {"kind": "wrong_position", "on": "MOT_MOVE_ABSOLUTE", "offset": 0.2},
], ids=lambda f: f"{f['kind']}-{f['on']}")
def test_stage_recovers(where, fault):
    z, physical = jack_case(where, fault, jack_move)
    assert z == pytest.approx(3.0, abs=1 / CPM) and physical == pytest.approx(3.0, abs=1 / CPM)


@pytest.mark.parametrize("fault", [{"kind": "drop", "on": "MOT_REQ_STATUSBITS"}, {"kind": "drop", "on": "MOT_MOVE_ABSOLUTE"},
                                   {"kind": "garbage", "on": "MOT_REQ_POSCOUNTER"}],
                         ids=lambda f: f"{f['kind']}-{f['on']}")
def test_stage_recovers_over_socket(fault):
    z, physical = jack_case(SOCKET, fault, jack_move)
    assert z == pytest.approx(3.0, abs=1 / CPM) and physical == pytest.approx(3.0, abs=1 / CPM)


@pytest.mark.parametrize("fault", [
    {"kind": "garbage", "on": "HW_REQ_INFO"},
    {"kind": "no_reply", "on": "MOT_REQ_VELPARAMS"},
], ids=lambda f: f"{f['kind']}-{f['on']}")
def test_stage_recovers_at_connect(where, fault):
    z, _ = jack_case(where, fault, jack_move, at_connect=True)
    assert z == pytest.approx(3.0, abs=1 / CPM)


def test_stage_recovers_from_a_drop_at_connect():
    z, _ = jack_case(SOCKET, {"kind": "drop", "on": "MOT_REQ_VELPARAMS"}, jack_move, at_connect=True)
    assert z == pytest.approx(3.0, abs=1 / CPM)


@pytest.mark.parametrize("fault, said", [
    ({"kind": "error_reply", "on": "MOT_MOVE_ABSOLUTE"}, "about MOT_MOVE_ABSOLUTE: 'simulated fault: command refused'"),
    ({"kind": "stall", "on": "MOT_MOVE_ABSOLUTE"}, "did not complete within"),
    ({"kind": "wrong_position", "on": "MOT_MOVE_ABSOLUTE", "count": 0, "offset": 0.2}, "ended at 3.2000 mm"),
    ({"kind": "no_reply", "on": "MOT_REQ_STATUSBITS", "count": 0}, "no reply to MOT_REQ_STATUSBITS within 0.3 s"),
], ids=lambda v: v["kind"] if isinstance(v, dict) else "")
def test_stage_fails_clearly(where, fault, said):
    _fails_naming_the_device(lambda: jack_case(where, fault, jack_move), "stage (APT lab jack) on ", said)


def test_stalled_stage_is_stopped():
    sim = LabJackSimulator(time_scale=TS, counts_per_mm=CPM, faults=[{"kind": "stall", "on": "MOT_MOVE_ABSOLUTE"}])
    sim.start("socket://127.0.0.1:0")
    try:
        with AptLabJack(sim.url, counts_per_mm=CPM, time_scale=TS, timeout_s=0.3) as jack:
            with pytest.raises(DeviceError, match="the stage was told to stop"):
                bounded(lambda: jack.move_to_mm(10.0))
            time.sleep(0.05)
            assert not sim.moving and 0 < sim.position_mm < 10.0   # stopped halfway, not still "moving"
    finally:
        sim.stop()


def test_faults_from_the_rig_config():
    from fluxcli.config import Rig
    from fluxcli.hardware.rig import open_devices, start_simulators

    rig = Rig.model_validate({"time_scale": TS,
                              "filter_wheel": {"port": "pty", "faults": [{"kind": "garbage", "on": "pos?", "count": 0}]},
                              "stage": {"port": "socket://127.0.0.1:0", "counts_per_mm": CPM, "timeout_s": 0.3,
                                        "faults": [{"kind": "stall", "on": "MOT_MOVE_ABSOLUTE"}]}})
    sims = start_simulators(rig)
    try:
        wheel, jack = open_devices(rig, sims)
        with wheel, jack:
            assert bounded(lambda: wheel.move_to(2)) == 2          # noise before every reply: read through
            with pytest.raises(DeviceError, match="did not complete"):
                bounded(lambda: jack.move_to_mm(1.0))
    finally:
        for s in sims.values():
            s.stop()


def test_a_fault_on_an_unknown_command_is_a_config_error():
    from fluxcli.config import Rig
    from fluxcli.errors import UserError
    from fluxcli.hardware.rig import start_simulators

    rig = Rig.model_validate({"stage": {"port": "pty", "counts_per_mm": CPM,
                                        "faults": [{"kind": "stall", "on": "MOT_MOVE_ABSOLUT"}, {"kind": "stall", "on": "MOVE"}]}})
    with pytest.raises(UserError, match=r"'rig.stage.faults.1.on': 'MOVE' is not"):
        start_simulators(rig)


def test_swapped_ports_name_the_device_expected_there():
    wheel_sim, jack_sim = FW102CSimulator(time_scale=TS), LabJackSimulator(time_scale=TS)
    wheel_sim.start("pty")
    jack_sim.start("pty")
    try:
        with pytest.raises(DeviceError, match=r"filter wheel \(FW102C\) on /dev/pts/\d+: no prompt .* is this the filter wheel"):
            bounded(lambda: FW102C(jack_sim.url, timeout_s=0.2))
        with pytest.raises(DeviceError, match=r"stage \(APT lab jack\) on /dev/pts/\d+: no reply to HW_REQ_INFO .* APT controller"):
            bounded(lambda: AptLabJack(wheel_sim.url, counts_per_mm=CPM, timeout_s=0.2))
    finally:
        wheel_sim.stop()
        jack_sim.stop()
