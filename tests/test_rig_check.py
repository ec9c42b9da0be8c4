"""``fluxmap rig check`` / ``rig snap``: every device of the shipped simulator config answers,
frames land as TIFF with what the camera reported; a device nobody answers for is named
(exit 2) while the others are still checked; real-camera backends through their fakes."""

from __future__ import annotations

import os
import socket
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

sys.path.insert(0, str(Path(__file__).parent))
import fake_pylablib as F  # noqa: E402

from fluxcli.cli import app  # noqa: E402
from fluxcli.imaging.imagefiles import read_image  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = yaml.safe_load((ROOT / "configs" / "rig-sim.yaml").read_text())


def invoke(*args):
    r = CliRunner().invoke(app, [str(a) for a in args])
    return r.exit_code, " ".join(r.output.split())


def write(tmp_path: Path, cfg: dict) -> Path:
    cfg = dict(cfg, workdir="run")
    path = tmp_path / "cfg.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def test_shipped_simulator_config_serves_every_device_on_a_socket():
    """pylablib's KinesisMotor (the README's example) cannot open a pty (errno 25): every
    device of configs/rig-sim.yaml listens on a loopback socket instead."""
    rig = SHIPPED["rig"]
    assert {k: v["port"] for k, v in rig.items() if isinstance(v, dict) and "port" in v} == {
        "filter_wheel": "socket://127.0.0.1:0", "stage": "socket://127.0.0.1:0"}


def test_rig_check_on_the_simulators_lists_every_device_and_writes_frames(tmp_path):
    code, out = invoke("rig", "check", write(tmp_path, SHIPPED), "--exposure-s", "0.2")
    assert code == 0, out
    assert "rig.filter_wheel: THORLABS FW102C/FW212C" in out and "firmware 1.04" in out
    assert "visited 1 (open), 3 (580nm), 4 (650nm); back at 1" in out
    assert "rig.stage: L490MZ | serial" in out and "moved to 0.5000 mm and back to 0.0000 mm" in out
    assert "rig.camera: simulated EMCCD" in out and "sensor -65 deg C, cooler on" in out
    dark, dmeta = read_image(tmp_path / "run" / "rig-check" / "dark.tif")
    lit, lmeta = read_image(tmp_path / "run" / "rig-check" / "lit.tif")
    assert _stored_as(tmp_path / "run" / "rig-check" / "lit.tif") == "uint16" and dark.shape == lit.shape == (48, 64)
    assert (dmeta["fluxmap:shutter_open"], lmeta["fluxmap:shutter_open"]) == (0, 1)
    assert lmeta["fluxmap:exposure_s"] == 0.2 and lmeta["fluxmap:temperature_c"] == -65.0
    # the test card through the open filter: 2e4 photons/s at the right edge, half at the left;
    # default sensor (QE 0.9, 10 e-/count) at gain 1: lit - dark = 2e4 x ramp x 0.2 s x 0.9 / 10
    ramp = 0.5 + 0.5 * np.arange(64) / 63
    want = 2e4 * ramp * 0.2 * 0.9 / 10
    got = lit.astype(float).mean(axis=0) - dark.astype(float).mean()
    assert np.allclose(got, want, rtol=0.1), (got[[0, -1]], want[[0, -1]])  # ~7 % noise per column (48 px)
    assert abs(got.mean() / want.mean() - 1) < 0.02


def _stored_as(path) -> str:
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    try:
        return str(inp.spec().format)
    finally:
        inp.close()


def _dead_ports(tmp_path):
    """A pseudo terminal nobody answers on, and a loopback port that refuses connections."""
    master, slave = os.openpty()
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    refused = s.getsockname()[1]
    s.close()
    return master, os.ttyname(slave), slave, f"socket://127.0.0.1:{refused}"


def test_rig_check_exits_2_naming_each_device_nobody_answers_for(tmp_path):
    master, pty, slave, refused = _dead_ports(tmp_path)
    try:
        rig = {"time_scale": 0.1,
               "filter_wheel": {"port": refused, "positions": 6, "filters": {"open": 1}},
               "stage": {"port": pty, "counts_per_mm": 134737.0, "timeout_s": 0.3},
               "camera": {"backend": "simulated"}}
        code, out = invoke("rig", "check", write(tmp_path, {"rig": rig}))
    finally:
        os.close(master)
        os.close(slave)
    assert code == 2, out
    assert f"rig.filter_wheel: NO ANSWER on {refused}" in out and f"rig.stage: NO ANSWER on {pty}" in out
    assert "rig check: 2 device(s) did not answer" in out
    assert f"rig.filter_wheel: filter wheel (FW102C) on {refused}: cannot open the port" in out
    assert f"rig.stage: stage (APT lab jack) on {pty}" in out
    assert "rig.camera: simulated EMCCD" in out  # the camera was still checked
    assert (tmp_path / "run" / "rig-check" / "lit.tif").exists()


def test_rig_snap_takes_a_sequence_and_dark_frames(tmp_path):
    cfg = write(tmp_path, SHIPPED)
    code, out = invoke("rig", "snap", cfg, "--frames", "3", "--exposure-s", "0.5", "--out", tmp_path / "f.tif")
    assert code == 0, out
    frames = [read_image(tmp_path / f"f-{k}.tif") for k in (1, 2, 3)]
    assert [m["fluxmap:frame"] for _, m in frames] == [1, 2, 3]
    assert not np.array_equal(frames[0][0], frames[1][0])  # three exposures, not one copied
    code, out = invoke("rig", "snap", cfg, "--dark", "--exposure-s", "0.5")
    assert code == 0, out
    dark, meta = read_image(tmp_path / "run" / "snap.tif")
    assert meta["fluxmap:shutter_open"] == 0
    lit_minus_dark = frames[0][0].astype(float).mean() - dark.astype(float).mean()
    assert abs(lit_minus_dark / (2e4 * 0.75 * 0.5 * 0.9 / 10) - 1) < 0.02


# ------------------------------------------------------------------ real-camera backends (fakes)
@pytest.fixture
def lab(monkeypatch):
    F.reset()
    F.install(monkeypatch)
    yield F.state
    assert F.state.open == 0


def test_rig_check_reports_an_andor_camera_through_its_fake(lab, tmp_path):
    rig = dict(SHIPPED["rig"], camera={"backend": "andor_sdk2", "setpoint_c": -80.0})
    code, out = invoke("rig", "check", write(tmp_path, {"rig": rig}), "--no-move", "--em-gain", "10")
    assert code == 0, out
    assert ("rig.camera: DU888_BV | serial X-1234 | firmware SDK 2.104.30084.0 (firmware not reported) | "
            "on backend andor_sdk2") in out
    assert "sensor -80 deg C, cooler stabilized; frames 128 x 96 px at binning 1" in out
    lit, meta = read_image(tmp_path / "run" / "rig-check" / "lit.tif")
    assert meta["fluxmap:camera_serial"] == "X-1234" and meta["fluxmap:em_gain"] == 10.0
    assert ("AndorSDK2Camera", "setup_shutter", "closed") in lab.calls[-6:]  # left with the shutter closed


def test_rig_check_names_a_missing_camera_and_still_checks_the_rest(lab, tmp_path):
    lab.pvcam_cameras = {}
    rig = dict(SHIPPED["rig"], camera={"backend": "pvcam"})
    code, out = invoke("rig", "check", write(tmp_path, {"rig": rig}), "--no-move")
    assert code == 2, out
    assert "rig.filter_wheel: THORLABS" in out and "rig.stage: L490MZ" in out
    assert "rig check: 1 device(s) did not answer: rig.camera: camera (PVCAM) on PVCAM camera 0: no PVCAM camera" in out


def test_a_window_projector_without_pyglet_names_the_key_and_the_extra(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "pyglet", None)
    rig = dict(SHIPPED["rig"], projectors={"left": {
        "pixels": [1024, 768], "focal_px": [3000, 3000], "display": "window",
        "pose": {"center_mm": [0, -200, 150], "look": [0, 200, -140], "up": [-1, 0, 0]}}})
    code, out = invoke("rig", "check", write(tmp_path, {"rig": rig}), "--no-move")
    assert code == 2, out
    assert "rig.projectors.left: rig.projectors.left.display on screen 1: 'window' needs pyglet" in out
    assert "pip install 'fluxmap[projector]'" in out


def test_rig_check_on_a_dcam_camera_without_a_shutter_takes_the_lit_frame_only(tmp_path, monkeypatch):
    import fake_dcam

    fake_dcam.reset()
    monkeypatch.setitem(sys.modules, "dcam", fake_dcam)  # the vendor's wrapper module, faked
    rig = dict(SHIPPED["rig"], camera={"backend": "dcam", "binning": 4})
    code, out = invoke("rig", "check", write(tmp_path, {"rig": rig}), "--no-move")
    assert code == 0, out
    assert "rig.camera: C9100-13 | serial 100123 | firmware 3.10.B | on backend dcam" in out
    assert "frames 256 x 256 px at binning 4" in out
    assert "dark: not taken (no shutter property is configured" in out
    assert not (tmp_path / "run" / "rig-check" / "dark.tif").exists()
    assert (tmp_path / "run" / "rig-check" / "lit.tif").exists()
    assert fake_dcam.state.initialised == 0  # the camera was released
