"""`fluxmap rig serve` as a subprocess, driven by third-party clients exactly as the hardware.

pylablib's ``Thorlabs.FW`` and ``Thorlabs.KinesisMotor`` over ``socket://`` (pylablib opens ports
with ``serial.serial_for_url``; KinesisMotor needs ``("serial", url)`` to pick the pyserial
backend instead of its FTDI one), and plain pyserial with the ``thorlabs-apt-protocol``
encoder/decoder over a pseudo terminal.  (KinesisMotor cannot run on a Linux pty: it toggles
RTS, which a pty refuses with ENOTTY.)
"""

import queue
import signal
import subprocess
import sys
import threading
import time
import warnings

import pytest
import serial
import thorlabs_apt_protocol as tap
import yaml

TS = 0.02
CPM = 134737.0


def _serve(tmp_path, rig, name="rig.yaml"):
    cfg = tmp_path / name
    cfg.write_text(yaml.safe_dump({"rig": rig}))
    proc = subprocess.Popen([sys.executable, "-m", "fluxcli.cli", "rig", "serve", str(cfg)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines: queue.Queue = queue.Queue()
    threading.Thread(target=lambda: [lines.put(ln) for ln in proc.stdout], daemon=True).start()
    urls = {}
    while True:
        try:
            line = lines.get(timeout=30)
        except queue.Empty:
            proc.kill()
            raise AssertionError(f"rig serve printed no 'ready' within 30 s: {urls}") from None
        if line.strip() == "ready":
            return proc, urls
        device, url = line.split()
        urls[device] = url


def _end(proc, sig):
    proc.send_signal(sig)
    assert proc.wait(timeout=10) == 0


@pytest.fixture(scope="module")
def served_socket(tmp_path_factory):
    proc, urls = _serve(tmp_path_factory.mktemp("serve"), {
        "time_scale": TS,
        "filter_wheel": {"port": "socket://127.0.0.1:0", "positions": 6, "filters": {"open": 1, "580nm": 3}},
        "stage": {"port": "socket://127.0.0.1:0", "counts_per_mm": CPM, "travel_mm": [0.0, 50.0]},
        "camera": {"backend": "simulated"}})
    yield urls
    _end(proc, signal.SIGTERM)


@pytest.fixture(scope="module")
def served_pty(tmp_path_factory):
    proc, urls = _serve(tmp_path_factory.mktemp("serve"), {
        "time_scale": TS,
        "filter_wheel": {"port": "pty"},
        "stage": {"port": "pty", "counts_per_mm": CPM}})
    yield urls
    _end(proc, signal.SIGINT)


def test_serve_prints_one_line_per_device(served_socket, served_pty):
    assert set(served_socket) == {"filter_wheel", "stage"}
    assert all(u.startswith("socket://127.0.0.1:") and not u.endswith(":0") for u in served_socket.values())
    assert all(u.startswith("/dev/pts/") for u in served_pty.values())


def test_pylablib_filter_wheel_over_socket(served_socket):
    from pylablib.devices import Thorlabs

    fw = Thorlabs.FW(served_socket["filter_wheel"])
    try:
        assert fw.get_pcount() == 6
        assert "FW102C" in fw.ask("*idn?")
        fw.set_position(5)                      # pylablib goes round through intermediate positions
        assert fw.get_position() == 5
        fw.set_position(2)
        assert fw.get_position() == 2
        assert fw.set_speed_mode("low") == "low"
        fw.set_position(3)
        assert fw.get_position() == 3
        assert fw.set_sensor_mode("off") == "off"
    finally:
        fw.close()


def test_pylablib_kinesis_motor_over_socket(served_socket):
    from pylablib.devices import Thorlabs

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "can't recognize motor model L490MZ": steps are our units
        motor = Thorlabs.KinesisMotor(("serial", served_socket["stage"]), scale="step")
    try:
        assert motor.get_device_info().model_no == "L490MZ"
        target = round(4.0 * CPM)
        motor.move_to(target)
        assert motor.is_moving()
        motor.wait_move(timeout=10)
        assert motor.get_position() == target
        motor.move_by(-round(1.0 * CPM))
        motor.wait_move(timeout=10)
        assert motor.get_position() == target - round(1.0 * CPM)
        motor.setup_velocity(max_velocity=round(0.8 * CPM * 53.68))
        assert motor.get_velocity_parameters().max_velocity == round(0.8 * CPM * 53.68)
        motor.home(force=True, sync=True, timeout=20)
        assert motor.get_position() == 0 and "homed" in motor.get_status()
        info = motor.get_full_info()   # every parameter block it knows is answered
        assert info["gen_move_parameters"].backlash_distance == round(0.05 * CPM)
        # pylablib's "-" is APT direction 1 (forward, up) for KinesisMotor: drivers disagree on the names
        motor.jog("-", kind="builtin")
        motor.wait_move(timeout=10)
        assert motor.get_position() == motor.get_jog_parameters().step_size
        motor.jog("-", kind="continuous")
        time.sleep(0.05)
        assert motor.is_moving()
        motor.stop(immediate=False, sync=True, timeout=10)
        stopped = motor.get_position()
        time.sleep(0.05)
        assert not motor.is_moving() and motor.get_position() == stopped > 0
    finally:
        motor.close()


def _read_until(port, end: bytes, timeout_s=5.0) -> bytes:
    buf, deadline = b"", time.monotonic() + timeout_s
    while not buf.endswith(end):
        assert time.monotonic() < deadline, f"no {end!r} within {timeout_s} s: {buf!r}"
        buf += port.read(1)
    return buf


def test_plain_pyserial_drives_the_wheel_on_a_pty(served_pty):
    with serial.Serial(served_pty["filter_wheel"], 115200, timeout=0.1) as port:
        port.write(b"\r")     # the usual greeting: a bare CR, answered with noise and an error
        assert _read_until(port, b"> ") == b"\x00\rCommand error CMD_NOT_DEFINED\n> "
        port.write(b"pos=4\r")
        assert _read_until(port, b"> ") == b"pos=4\r> "
        port.write(b"pos?\r")
        assert _read_until(port, b"> ") == b"pos?\r4\r> "
        port.write(b"pos=9\r")
        assert _read_until(port, b"> ") == b"pos=9\rCommand error CMD_ARG_INVALID\n> "


def test_plain_pyserial_drives_the_stage_on_a_pty(served_pty):
    with serial.Serial(served_pty["stage"], 115200, rtscts=True, timeout=0.05) as port:
        port.write(tap.hw_req_info(0x50, 0x01))
        msgs = tap.Unpacker(port)
        info = next(msgs)
        assert info.msg == "hw_get_info" and info.model_number.rstrip(b"\0") == b"L490MZ"
        assert (info.source, info.dest) == (0x50, 0x01)
        target = round(2.5 * CPM)
        port.write(tap.mot_move_absolute(0x50, 0x01, 1, target))
        deadline = time.monotonic() + 5
        while True:   # MOVE_COMPLETED arrives on its own when the move ends
            assert time.monotonic() < deadline
            try:
                m = next(msgs)
            except StopIteration:
                continue
            if m.msg == "mot_move_completed":
                assert m.position == target
                break
        port.write(tap.mot_req_poscounter(0x50, 0x01, 1))
        m = next(msgs)
        assert m.msg == "mot_get_poscounter" and m.position == target


def test_serve_refuses_a_device_path_and_a_config_without_rig(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump({"rig": {"stage": {"port": "/dev/ttyUSB0", "counts_per_mm": CPM}}}))
    r = subprocess.run([sys.executable, "-m", "fluxcli.cli", "rig", "serve", str(bad)],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "rig.stage" in r.stderr and "Traceback" not in r.stderr
    empty = tmp_path / "norig.yaml"
    empty.write_text("workdir: out\n")
    r = subprocess.run([sys.executable, "-m", "fluxcli.cli", "rig", "serve", str(empty)],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "'rig'" in r.stderr


def test_serve_on_a_busy_port_exits_2_naming_the_device(tmp_path):
    import socket

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen(1)
        port = busy.getsockname()[1]
        cfg = tmp_path / "busy.yaml"
        cfg.write_text(yaml.safe_dump({"rig": {"filter_wheel": {"port": f"socket://127.0.0.1:{port}"}}}))
        r = subprocess.run([sys.executable, "-m", "fluxcli.cli", "rig", "serve", str(cfg)],
                           capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert "rig.filter_wheel simulator on socket://127.0.0.1:" in r.stderr and "cannot serve there" in r.stderr


@pytest.mark.parametrize("stage, rig, words", [
    # 100 m of travel at the L490MZ's 134737 counts/mm is 1.3e10 counts: the simulator's APT
    # reply failed to pack (struct.error, exit 1) before this was checked
    ({"travel_mm": [0.0, 100000.0]}, {}, "travel_mm's far end is 1.347e+10 device units"),
    ({"velocity_scale": 1e6}, {}, "velocity_mm_s is 6.737e+10 device units"),
    ({}, {"time_scale": 1e5}, "time_scale"),  # a move of seconds would last days, and the check with it
])
def test_a_rig_the_wire_cannot_carry_exits_2_before_a_device_starts(tmp_path, stage, rig, words):
    cfg = tmp_path / "rig.yaml"
    cfg.write_text(yaml.safe_dump({"rig": {**rig, "stage": {"port": "socket://127.0.0.1:0", "counts_per_mm": CPM,
                                                             **stage}}}))
    r = subprocess.run([sys.executable, "-m", "fluxcli.cli", "rig", "check", str(cfg)],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert words in " ".join(r.stderr.split())


def test_the_l490mz_s_finer_count_fits_the_wire():
    """2155789 counts/mm (the other figure given for the L490MZ) over its 50 mm at its top speed."""
    from fluxcli.config import RigStage

    RigStage(port="pty", counts_per_mm=2155789.0, travel_mm=(0.0, 50.0), velocity_mm_s=1.1)


def test_a_duration_beyond_a_day_is_refused_naming_the_key(tmp_path):
    """capture.exposure_s 1e300 reached time.sleep in the simulated camera (OverflowError, exit 1)."""
    from pydantic import ValidationError

    from fluxcli.config import Capture, RigStage

    with pytest.raises(ValidationError, match="durations are in seconds here and at most 86400 s"):
        Capture.model_validate({"heights_mm": [0], "exposure_s": 1e300})
    with pytest.raises(ValidationError, match="exposure_s"):
        Capture.model_validate({"heights_mm": [0], "exposure_s": [1.0, 1e5]})
    Capture.model_validate({"heights_mm": [0], "exposure_s": 600.0})  # a long bioluminescence exposure
    RigStage(port="pty", counts_per_mm=CPM, velocity_mm_s=1.1)  # mm/s is a rate, not a duration
