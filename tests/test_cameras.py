"""The Andor (SDK2, SDK3) and PVCAM backends against fakes of pylablib's camera classes,
on their own and driven by ``capture-surface`` end to end; a real camera only when
``FLUXMAP_CAMERA`` names one (``andor_sdk2:0``, ``andor_sdk3:0``, ``pvcam:0``)."""

from __future__ import annotations

import inspect
import os
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

sys.path.insert(0, str(Path(__file__).parent))
import fake_pylablib as F  # noqa: E402

from fluxcli.cli import app  # noqa: E402
from fluxcli.hardware.errors import DeviceError  # noqa: E402
from fluxcli.hardware.pylablib_cameras import AndorSDK2, AndorSDK3, Pvcam  # noqa: E402

BACKENDS = {"andor_sdk2": (AndorSDK2, F.Andor), "andor_sdk3": (AndorSDK3, F.Andor), "pvcam": (Pvcam, F.Photometrics)}
EM = {"andor_sdk2": True, "andor_sdk3": False, "pvcam": True}  # has an EM register


@pytest.fixture
def lab(monkeypatch):
    """The fakes stand in for pylablib's modules (pylablib itself need not be installed)."""
    F.reset()
    F.install(monkeypatch)
    yield F.state
    assert F.state.open == 0, "a camera was left open"


def expected_counts(*, exposure_s, gain=1.0, binning=1, lit=True, s=None):
    """The fakes' sensor in closed form: bias + G (rate b^2 t [lit] + dark t) / e_per_count."""
    s = s or F.state
    return s.bias + gain * ((s.rate_e * binning**2 * exposure_s if lit else 0.0) + s.dark_e * exposure_s) / s.e_per_count


# ------------------------------------------------------------------ the fakes are pylablib's shape
USED = {  # the pylablib calls each backend makes
    ("Andor", "AndorSDK2Camera"): ["__init__", "set_image_indexing", "get_data_dimensions", "set_exposure",
                                   "get_exposure", "set_roi", "get_roi", "snap", "grab", "start_acquisition", "wait_for_frame", "read_oldest_image", "stop_acquisition", "close", "get_device_info",
                                   "get_EMCCD_gain", "set_EMCCD_gain", "set_temperature", "get_temperature",
                                   "get_temperature_setpoint", "get_temperature_status", "is_cooler_on",
                                   "set_cooler", "setup_shutter", "get_shutter"],
    ("Andor", "AndorSDK3Camera"): ["__init__", "set_image_indexing", "get_data_dimensions", "set_exposure",
                                   "get_exposure", "set_roi", "get_roi", "snap", "grab", "start_acquisition", "wait_for_frame", "read_oldest_image", "stop_acquisition", "close", "get_device_info",
                                   "set_temperature", "get_temperature", "get_temperature_setpoint", "is_cooler_on",
                                   "set_cooler", "set_shutter", "get_shutter"],
    ("Photometrics", "PvcamCamera"): ["__init__", "set_image_indexing", "get_data_dimensions", "set_exposure",
                                      "get_exposure", "set_roi", "get_roi", "snap", "grab", "start_acquisition", "wait_for_frame", "read_oldest_image", "stop_acquisition", "close",
                                      "get_device_info", "get_attribute_value", "set_attribute_value",
                                      "set_temperature", "get_temperature", "get_temperature_setpoint"],
}


def _params(fn) -> list[str]:
    return [p for p in inspect.signature(fn).parameters if p != "self"]


@pytest.mark.parametrize("module,cls", list(USED))
def test_fakes_have_pylablibs_names_and_signatures(module, cls):
    """Every call the backend makes exists in the installed pylablib with the same parameters,
    and so in the fake; the device-info tuples have the same fields."""
    real_mod = pytest.importorskip(f"pylablib.devices.{module}", reason="pylablib not installed (pip install "
                                   "'fluxmap[cameras]'): the fakes cannot be compared with it")
    real, fake = getattr(real_mod, cls), getattr(getattr(F, module), cls)
    for name in USED[(module, cls)]:
        assert _params(getattr(fake, name)) == _params(getattr(real, name)), f"{cls}.{name}"
    for fn in ("get_cameras_number_SDK2", "get_cameras_number_SDK3", "get_SDK2_version") if module == "Andor" else (
            "list_cameras",):
        assert callable(getattr(real_mod, fn)) and callable(getattr(getattr(F, module), fn))
    info = {"AndorSDK2Camera": "AndorSDK2", "AndorSDK3Camera": "AndorSDK3", "PvcamCamera": "pvcam"}[cls]
    real_info = getattr(__import__(f"pylablib.devices.{module}.{info}", fromlist=["TDeviceInfo"]), "TDeviceInfo")
    fake_info = {"AndorSDK2Camera": F.SDK2DeviceInfo, "AndorSDK3Camera": F.SDK3DeviceInfo,
                 "PvcamCamera": F.PvcamDeviceInfo}[cls]
    assert real_info._fields == fake_info._fields
    assert issubclass(getattr(real_mod, "PvcamError" if module == "Photometrics" else "AndorError"), RuntimeError)


# ------------------------------------------------------------------ each backend on its own
@pytest.mark.parametrize("backend", list(BACKENDS))
def test_settings_are_read_back_and_frames_show_them(lab, backend):
    cls, mod = BACKENDS[backend]
    cam = cls(0, setpoint_c=-60.0)
    try:
        assert cam.identity().serial and cam.identity().model
        assert cam.cooler_on and cam.temperature_c == -60.0
        cam.binning = 2
        cam.exposure_s = 0.5
        gain = 100.0 if EM[backend] else 1.0
        cam.em_gain = gain
        assert (cam.binning, cam.exposure_s, cam.em_gain) == (2, 0.5, gain)
        assert cam.shape == (48, 64)  # (rows, cols) of a 128 x 96 sensor at binning 2
        cam.shutter_open = True
        assert cam.shutter_open
        lit = cam.sequence(4).astype(float)
        assert lit.shape == (4, 48, 64) and cam.snap().dtype == np.uint16
        cam.shutter_open = False
        dark = cam.sequence(4).astype(float)
        for frames, is_lit in ((lit, True), (dark, False)):
            want = expected_counts(exposure_s=0.5, gain=gain, binning=2, lit=is_lit)
            # Poisson electrons: counts vary by gain/e_per_count * sqrt(electrons); rounding adds 1/sqrt(12)
            e = (lab.rate_e * 4 * 0.5 if is_lit else 0.0) + lab.dark_e * 0.5
            sem = np.sqrt((gain / lab.e_per_count) ** 2 * e + 1 / 12) / np.sqrt(frames.size)
            assert abs(frames.mean() - want) < 5 * sem + 0.5, (is_lit, frames.mean(), want)
        assert ("set_image_indexing", "rct") in [c[1:] for c in lab.calls]  # row 0 at the top, every vendor
    finally:
        cam.close()


def test_andor_sdk2_em_gain_above_300_needs_advanced_mode(lab):
    cam = AndorSDK2(0)
    try:
        with pytest.raises(DeviceError, match=r"camera \(Andor SDK2\) on Andor SDK2 camera 0: EM gain 500.*"
                                              r"em_gain_advanced"):
            cam.em_gain = 500
    finally:
        cam.close()
    cam = AndorSDK2(0, em_gain_advanced=True)
    try:
        cam.em_gain = 500
        assert cam.em_gain == 500
        assert ("AndorSDK2Camera", "set_EMCCD_gain", 500, True) in lab.calls
    finally:
        cam.close()


@pytest.mark.parametrize("backend", list(BACKENDS))
def test_errors_name_the_camera_and_what_the_driver_said(lab, backend):
    cls, mod = BACKENDS[backend]
    cam = cls(0)
    try:
        lab.stall_frames = True
        with pytest.raises(DeviceError, match=rf"{cam.name.replace('(', '.').replace(')', '.')}.*taking a frame.*"
                                              r"Timeout"):
            cam.snap()
        lab.stall_frames = False
        if not EM[backend]:
            with pytest.raises(DeviceError, match="no EM register.*capture.em_gain"):
                cam.em_gain = 300
        lab.fail["get_temperature"] = mod.PvcamError("PL_ERR_TIMEOUT") if backend == "pvcam" else \
            mod.AndorError("DRV_ERROR_ACK")
        with pytest.raises(DeviceError, match=r"reading the sensor temperature failed.*(ERR|ACK)"):
            cam.temperature_c
    finally:
        cam.close()


def test_selection_by_index_and_serial_and_missing_cameras(lab, monkeypatch):
    lab.sdk2_serials = ["X-1", "X-2"]
    cam = AndorSDK2(0, serial="X-2")
    try:
        assert cam.identity().serial == "X-2"
    finally:
        cam.close()
    with pytest.raises(DeviceError, match=r"serial X-9\).*no camera with serial X-9.*X-1, X-2"):
        AndorSDK2(0, serial="X-9")
    with pytest.raises(DeviceError, match="there is no camera 5: the Andor SDK2 library lists 2"):
        AndorSDK2(5)
    lab.pvcam_cameras = {}
    with pytest.raises(DeviceError, match=r"camera \(PVCAM\) on PVCAM camera 0: no PVCAM camera found"):
        Pvcam(0)
    monkeypatch.setitem(sys.modules, "pylablib.devices.Andor", None)  # pylablib absent
    with pytest.raises(DeviceError, match=r"needs pylablib: pip install 'fluxmap\[cameras\]'"):
        AndorSDK3(0)


def test_sdk3_without_a_shutter_and_pvcam_sCMOS_without_em_register(lab):
    lab.sdk3_shutter = False
    lab.pvcam_em = False
    cam = AndorSDK3(0)
    try:
        with pytest.raises(DeviceError, match="closing the shutter.*cap the lens.*not supported"):
            cam.shutter_open = False
    finally:
        cam.close()
    cam = Pvcam(0)
    try:
        assert cam.em_gain == 1.0
        with pytest.raises(DeviceError, match="no EM register"):
            cam.em_gain = 10
        with pytest.raises(DeviceError, match="cannot switch the cooler off"):
            cam.cooler_on = False
    finally:
        cam.close()


# ------------------------------------------------------------------ capture-surface through each fake
def _rig_config(backend: str) -> dict:
    gain = 100.0 if EM[backend] else 1.0
    return {"workdir": "run",
            "rig": {"time_scale": 0.02,
                    "filter_wheel": {"port": "pty", "positions": 6, "filters": {"open": 1, "580nm": 3}},
                    "stage": {"port": "pty", "counts_per_mm": 134737.0, "travel_mm": [0.0, 50.0]},
                    "camera": {"backend": backend, "binning": 2, "setpoint_c": -70.0}},
            "capture": {"heights_mm": [0, 1], "filters": ["open", "580nm"], "exposure_s": [0.02, 0.05],
                        "em_gain": gain, "repeats": 2, "darks": 2}}


@pytest.mark.parametrize("backend", list(BACKENDS))
def test_capture_surface_drives_each_backend_through_its_fake(lab, tmp_path, backend):
    """Exposure (two of them), gain, binning, set point and cooler, shutter (darks) reach the
    camera, are read back into capture.h5, and the frames show them (the fake's sensor)."""
    cfg = _rig_config(backend)
    path = tmp_path / "cfg.yaml"
    path.write_text(yaml.safe_dump(cfg))
    r = CliRunner().invoke(app, ["capture-surface", str(path), "--quiet"])
    assert r.exit_code == 0, r.output
    with h5py.File(tmp_path / "run" / "capture.h5", "r") as f:
        counts = f["frames/counts"][()].astype(float)
        meta = {k: f[f"frames/{k}"][()] for k in ("exposure_s", "em_gain", "temperature_c", "shutter_open")}
        dark = f["plan/dark"][()].astype(bool)
        planned_t = f["plan/exposure_s"][()]
        assert f["frames/committed"][()].all()
    gain = cfg["capture"]["em_gain"]
    assert counts.shape == (2 * 2 + 2 * 2 * 2 * 2, 48, 64)  # binning 2 of 128 x 96
    assert np.array_equal(meta["exposure_s"], planned_t) and set(planned_t) == {0.02, 0.05}
    assert np.all(meta["em_gain"] == gain) and np.all(meta["temperature_c"] == -70.0)
    assert np.array_equal(meta["shutter_open"].astype(bool), ~dark)
    for k in range(len(counts)):
        want = expected_counts(exposure_s=planned_t[k], gain=gain, binning=2, lit=not dark[k])
        e = (0 if dark[k] else lab.rate_e * 4 * planned_t[k]) + lab.dark_e * planned_t[k]
        sem = np.sqrt((gain / lab.e_per_count) ** 2 * e + 1 / 12) / np.sqrt(counts[k].size)
        assert abs(counts[k].mean() - want) < 6 * sem + 0.5, (k, counts[k].mean(), want)
    calls = [c[1:] for c in lab.calls]
    assert ("set_roi", 0, None, 0, None, 2, 2) in calls
    assert any(c[0] == "set_temperature" and c[1] == -70.0 for c in calls)
    closes = [i for i, c in enumerate(calls) if c in (("setup_shutter", "closed"), ("set_shutter", "closed"),
                                                      ("set_attribute_value", "SHTR_OPEN_MODE", 0))]
    assert closes, "the shutter was never closed for the darks"
    # the repeats of each setting are one hardware sequence (2 darks per exposure, 2 repeats per
    # height/filter/exposure): 2 + 8 sequences of 2 frames, each started, read frame by frame, stopped
    starts = [c for c in calls if c[0] == "start_acquisition"]
    assert starts == [("start_acquisition", "sequence", 2)] * (2 + 2 * 2 * 2), starts
    assert sum(c[0] == "read_oldest_image" for c in calls) == len(counts)
    assert sum(c[0] == "stop_acquisition" for c in calls) == len(starts)
    assert not any(c[0] == "snap" for c in calls)


def test_a_stop_inside_a_camera_sequence_keeps_the_frames_read_and_ends_the_sequence(lab, tmp_path, monkeypatch):
    """A sequence interrupted after its first frame: that frame is committed, the camera's
    acquisition is stopped, and --resume takes the rest."""
    import fluxcli.stages.capture as stage

    cfg = _rig_config("andor_sdk3")
    path = tmp_path / "cfg.yaml"
    path.write_text(yaml.safe_dump(cfg))
    taken = []
    real = stage.acquire

    def stop_after_three(*a, **kw):
        on_frame = kw.get("on_frame", lambda fr: None)
        kw.update(stop_requested=lambda: len(taken) >= 3, on_frame=lambda fr: (taken.append(fr), on_frame(fr)))
        return real(*a, **kw)

    monkeypatch.setattr(stage, "acquire", stop_after_three)
    r = CliRunner().invoke(app, ["capture-surface", str(path), "--quiet"])
    monkeypatch.setattr(stage, "acquire", real)
    assert r.exit_code == 130, r.output
    with h5py.File(tmp_path / "run" / "capture.h5", "r") as f:
        committed = f["frames/committed"][()]
    assert committed.sum() == 3 and committed[:3].all()  # the 2nd sequence stopped after its 1st frame
    calls = [c[1:] for c in lab.calls]
    assert sum(c[0] == "start_acquisition" for c in calls) == sum(c[0] == "stop_acquisition" for c in calls) == 2
    r = CliRunner().invoke(app, ["capture-surface", str(path), "--quiet", "--resume"])
    assert r.exit_code == 0, r.output
    with h5py.File(tmp_path / "run" / "capture.h5", "r") as f:
        assert f["frames/committed"][()].all()


def test_capture_surface_exits_2_naming_the_camera(lab, tmp_path):
    cfg = _rig_config("andor_sdk2")
    cfg["capture"]["em_gain"] = 600.0
    path = tmp_path / "cfg.yaml"
    path.write_text(yaml.safe_dump(cfg))
    r = CliRunner().invoke(app, ["capture-surface", str(path), "--quiet"])
    assert r.exit_code == 2, r.output
    assert "camera (Andor SDK2) on Andor SDK2 camera 0: EM gain 600" in " ".join(r.output.split())


# ------------------------------------------------------------------ a real camera (opt-in)
REAL = os.environ.get("FLUXMAP_CAMERA", "")


@pytest.mark.skipif(not REAL, reason="no real camera named: FLUXMAP_CAMERA=andor_sdk2:0 (or andor_sdk3:0, pvcam:0) "
                                     "runs this on the rig")
def test_a_real_camera_answers_and_takes_dark_and_lit_frames():
    """Cap the lens or close the box: dark frames at two exposures, then a sequence."""
    backend, _, index = REAL.partition(":")
    cls = {"andor_sdk2": AndorSDK2, "andor_sdk3": AndorSDK3, "pvcam": Pvcam}[backend]
    cam = cls(int(index or 0), serial=os.environ.get("FLUXMAP_CAMERA_SERIAL") or None,
              setpoint_c=float(os.environ.get("FLUXMAP_CAMERA_SETPOINT_C", "-20")),
              linux_sdk=sys.platform.startswith("linux"))
    try:
        ident = cam.identity()
        print(f"{ident.model} serial {ident.serial} firmware {ident.firmware}; {cam.temperature_c:g} deg C, "
              f"cooler {cam.cooling_status}")
        assert ident.model and ident.serial
        cam.binning = 1
        cam.em_gain = 1
        means = []
        for t in (0.01, 0.1):
            cam.exposure_s = t
            assert cam.exposure_s == pytest.approx(t, rel=1e-3)
            try:
                cam.shutter_open = False
            except DeviceError:
                pass  # no shutter: the lens is capped
            means.append(cam.snap().astype(float).mean())
        assert means[1] >= means[0] - 5  # dark current only adds
        seq = cam.sequence(3)
        assert seq.shape == (3, *cam.shape) and seq.dtype == np.uint16
    finally:
        cam.close()
