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
    jack_sim.enabled = False  # as if disabled earlier: the driver enables the channel at connect
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


def test_wheel_turns_position_by_position_and_the_short_way():
    sim = FW102CSimulator(time_scale=TS)
    sim.start("pty")
    try:
        with FW102C(sim.url, time_scale=TS) as wheel:
            seen = []
            import threading

            t = threading.Thread(target=wheel.move_to, args=(4,))
            t.start()
            while t.is_alive():
                if not seen or seen[-1] != sim.position:
                    seen.append(sim.position)
                time.sleep(TS / 10)
            t.join()
            seen.append(sim.position)
            assert [p for i, p in enumerate(seen) if i == 0 or p != seen[i - 1]] == [1, 2, 3, 4]
            seen.clear()
            t = threading.Thread(target=wheel.move_to, args=(6,))   # 4 -> 6 forward, then 6 -> 1 is one step
            t.start()
            t.join()
            t0 = time.monotonic()
            wheel.move_to(1)
            assert time.monotonic() - t0 < 2 * TS + 0.3
    finally:
        sim.stop()


def test_stage_follows_the_trapezoidal_profile_and_its_status_bits():
    """0 -> 10 mm at 0.5 mm/s with 0.5 mm/s^2: 1 s ramps, 21 s in all (device time)."""
    import threading

    from fluxcli.hardware import apt

    sim = LabJackSimulator(time_scale=TS, counts_per_mm=CPM)
    sim.start("pty")
    try:
        with AptLabJack(sim.url, counts_per_mm=CPM, time_scale=TS) as jack:
            samples = []
            t = threading.Thread(target=jack.move_to_mm, args=(10.0,))
            t0 = time.monotonic()
            t.start()
            while t.is_alive():
                samples.append(((time.monotonic() - t0) / TS, sim.position_mm, sim.status_bits()))
                time.sleep(TS / 5)
            t.join()

            def closed_form(tau):
                if tau < 1:
                    return 0.25 * tau * tau
                if tau < 20:
                    return 0.25 + 0.5 * (tau - 1)
                return 10 - 0.25 * max(0.0, 21 - tau) ** 2

            # the move starts when the controller gets it, a little after t0: fit that shift (device s)
            def errors(shift):
                return sorted(abs(z - closed_form(tau - shift)) for tau, z, _ in samples if 0.5 < tau - shift < 20.5)

            shift = min((k * 0.05 for k in range(0, 41)), key=lambda d: errors(d)[len(errors(d)) * 9 // 10])
            err = errors(shift)
            assert len(err) > 20
            assert err[len(err) * 9 // 10] < 0.05 and err[-1] < 0.5   # mm; a preempted sample may lag
            assert all(b & apt.ST_MOVING_ANY for tau, _, b in samples if 0.5 + shift < tau < 20.5 + shift)
            assert samples[-1][1] <= 10.0 and not sim.status_bits() & apt.ST_MOVING_ANY
            assert sim.status_bits() & apt.ST_SETTLED and sim.position_mm == pytest.approx(10.0, abs=1 / CPM)
    finally:
        sim.stop()


def test_simulator_speaks_apt_as_the_independent_decoder_reads_it():
    """Requests built by thorlabs-apt-protocol, replies decoded by it: headers, swaps, payloads."""
    import socket

    import thorlabs_apt_protocol as tap

    sim = LabJackSimulator(time_scale=TS, counts_per_mm=CPM)
    url = sim.start("socket://127.0.0.1:0")
    host, port = url.removeprefix("socket://").split(":")
    try:
        with socket.create_connection((host, int(port)), timeout=5) as s:
            f = s.makefile("rb")
            msgs = tap.Unpacker(f, on_error="raise")

            def ask(raw):
                s.sendall(raw)
                return next(msgs)

            info = ask(tap.hw_req_info(0x50, 0x01))
            assert (info.msg, info.source, info.dest, info.nchs) == ("hw_get_info", 0x50, 0x01, 1)
            v = ask(tap.mot_req_velparams(0x50, 0x01, 1))
            assert v.msg == "mot_get_velparams" and v.max_velocity == round(1.0 * CPM * 53.68)
            s.sendall(tap.mot_set_velparams(0x50, 0x01, 1, 0, round(2 * CPM / 90.9), round(1.0 * CPM * 53.68)))
            s.sendall(tap.hw_start_updatemsgs(0x50, 0x01))
            s.sendall(tap.mot_move_absolute(0x50, 0x01, 1, round(0.5 * CPM)))
            kinds = []
            while True:
                m = next(msgs)
                kinds.append(m.msg)
                if m.msg == "mot_get_statusupdate" and len(kinds) == 1:
                    assert m.moving_forward or m.moving_reverse
                if m.msg == "mot_move_completed":
                    break
            assert kinds.count("mot_get_statusupdate") >= 2          # updates stream during the move
            s.sendall(tap.hw_stop_updatemsgs(0x50, 0x01))
            s.sendall(tap.mot_move_home(0x50, 0x01, 1))
            while (m := next(msgs)).msg != "mot_move_homed":
                pass
            assert m.chan_ident == 1 and sim.homed
            p = ask(tap.mot_req_poscounter(0x50, 0x01, 1))
            assert p.msg == "mot_get_poscounter" and p.position == 0
            st = ask(tap.mot_req_statusupdate(0x50, 0x01, 1))
            assert st.homed and st.settled and st.motor_connected and not (st.moving_forward or st.moving_reverse)
    finally:
        sim.stop()


def test_a_hostile_client_gets_the_wheels_error_and_the_wheel_keeps_answering():
    """Over a loopback socket, as a third-party client would: an argument of 200 000 digits, a
    latin-1 digit ('²' is a digit to str.isdigit, not to int) and a line that never ends once
    stopped the simulator's thread with a ValueError (a traceback, the link dead); each now gets
    the FW102C's command error, or nothing, and the next command its answer."""
    import re
    import socket

    sim = FW102CSimulator(time_scale=TS)
    sim.start("socket://127.0.0.1:0")
    try:
        host, port = sim.url.removeprefix("socket://").split(":")
        with socket.create_connection((host, int(port)), timeout=5) as s:
            def ask(raw: bytes, until: bytes = b"> ") -> bytes:
                s.sendall(raw)
                got = b""
                while not got.endswith(until):
                    chunk = s.recv(65536)
                    assert chunk, f"the wheel closed the link after {got[-80:]!r}"
                    got += chunk
                return got

            # (its start may be lost past the simulator's line buffer: then the command is not defined)
            assert re.search(rb"\rCommand error CMD_(ARG_INVALID|NOT_DEFINED)\n> $", ask(b"pos=" + b"9" * 200_000 + b"\r"))
            assert ask("pos=\u00b2\r".encode("latin-1")).endswith(b"Command error CMD_ARG_INVALID\n> ")
            s.sendall(b"x" * 1_000_000)  # no CR: the simulator keeps only the end of it
            assert ask(b"\rpos?\r", until=b"1\r> ").endswith(b"pos?\r1\r> ")
            assert ask(b"pos=2\r") == b"pos=2\r> " and sim.position == 2
    finally:
        sim.stop()
