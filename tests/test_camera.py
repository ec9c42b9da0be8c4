"""The EMCCD interface: the simulated camera against closed forms, the DCAM backend
against a fake of the DCAM-API wrapper (the vendor library cannot exist here)."""

import sys
import types
from pathlib import Path

import numpy as np
import pytest

from fluxcli.hardware.camera import DeviceIdentity, SimulatedEmccd, dark_current_at
from fluxcli.hardware.errors import DeviceError
from fluxcli.imaging.noise import EMCCDModel

sys.path.insert(0, str(Path(__file__).parent))
import fake_dcam  # noqa: E402

SENSOR = EMCCDModel(quantum_efficiency=0.8, em_gain=100.0, read_noise_e=40.0, bias_counts=400.0,
                    electrons_per_count=12.0, dark_current_e_per_s=0.5, cic_e_per_pixel=0.02, exposure_s=2.0)


def flat_camera(rate=30.0, shape=(64, 64), seed=3, **kw):
    state = {"h": 0.0, "f": "open"}
    cam = SimulatedEmccd(lambda h, f: np.full(shape, rate * (2.0 if f == "580nm" else 1.0)),
                         stage_height_mm=lambda: state["h"], filter_name=lambda: state["f"], sensor=SENSOR,
                         seed=seed, time_scale=0.0, **kw)
    return cam, state


def test_flat_source_mean_counts_match_qe_gain_and_bias():
    """E[counts] = bias + G (QE N + dark t + CIC) / g for a uniform source of N photons/pixel."""
    cam, _ = flat_camera(rate=30.0)
    cam.shutter_open = True
    frames = cam.sequence(8).astype(float)
    N = 30.0 * 2.0
    expected = 400.0 + 100.0 * (0.8 * N + 0.5 * 2.0 + 0.02) / 12.0  # = 827.5 counts
    var = (2 - 1 / 100.0) * 100.0**2 * (0.8 * N + 1.02) / 12.0**2 + (40 / 12.0) ** 2  # F^2 = 2 - 1/G
    sem = np.sqrt(var / frames.size)
    assert abs(frames.mean() - expected) < 5 * sem
    assert abs(frames.var() / var - 1) < 0.05  # excess noise factor sqrt(2 - 1/G) shows in the spread


def test_dark_frame_mean_is_dark_current_times_exposure_plus_cic():
    cam, _ = flat_camera(rate=1e4)
    cam.shutter_open = False  # no photons at all, however bright the scene
    frames = cam.sequence(20).astype(float)
    expected = 400.0 + 100.0 * (0.5 * 2.0 + 0.02) / 12.0
    var = 2 * 100.0**2 * 1.02 / 144.0 + (40 / 12.0) ** 2
    assert abs(frames.mean() - expected) < 5 * np.sqrt(var / frames.size)


def test_dark_current_doubles_per_doubling_interval_when_the_cooler_is_off():
    assert dark_current_at(-58.7, reference_e_per_s=0.5, reference_c=-65.0, doubling_c=6.3) == pytest.approx(1.0)
    cam, _ = flat_camera(setpoint_c=-65.0, ambient_c=20.0, dark_doubling_c=6.3)
    assert cam.temperature_c == -65.0
    cam.cooler_on = False
    assert cam.temperature_c == 20.0
    assert cam.model().dark_current_e_per_s == pytest.approx(0.5 * 2 ** (85 / 6.3))


def test_image_follows_physical_filter_and_frames_are_keyed_by_plan_index():
    cam, state = flat_camera(rate=30.0)
    cam.shutter_open = True
    cam.set_frame_index(7)
    a = cam.snap()
    state["f"] = "580nm"  # twice the photons
    b = cam.sequence(6).astype(float).mean()
    assert b - 400 > 1.8 * (a.astype(float).mean() - 400)
    state["f"] = "open"
    cam.set_frame_index(7)
    assert np.array_equal(cam.snap(), a)  # same (seed, index), same state: same bytes
    other, _ = flat_camera(rate=30.0, seed=4)
    other.shutter_open = True
    other.set_frame_index(7)
    assert not np.array_equal(other.snap(), a)


def test_simulated_camera_refuses_impossible_settings():
    cam, _ = flat_camera()
    with pytest.raises(DeviceError, match="EM gain 5000"):
        cam.em_gain = 5000
    with pytest.raises(DeviceError, match="binning 4"):
        cam.binning = 4
    with pytest.raises(DeviceError, match="exposure"):
        cam.exposure_s = -1


# ------------------------------------------------------------------ DCAM backend (fake API)
@pytest.fixture
def dcam():
    fake_dcam.reset()
    from fluxcli.hardware.dcam import DcamCamera

    cams = []

    def make(**kw):
        cam = DcamCamera(0, api=fake_dcam, **kw)
        cams.append(cam)
        return cam

    yield make
    for c in cams:
        c.close()


def test_dcam_sets_emccd_mode_and_finds_properties_by_name(dcam):
    cam = dcam()
    sets = [c[1:] for c in fake_dcam.state.calls if c[0] == "set"]
    assert ("CCD MODE", 2.0) in sets and ("DIRECT EM GAIN MODE", 2.0) in sets
    cam.exposure_s = 0.5
    cam.em_gain = 300
    cam.binning = 4
    cam.cooler_on = True
    assert (cam.exposure_s, cam.em_gain, cam.binning, cam.cooler_on) == (0.5, 300, 4, True)
    assert cam.temperature_c == -65.0
    assert cam.shape == (256, 256)
    assert cam.identity() == DeviceIdentity("C9100-13", "100123", "3.10.B")  # for `fluxmap rig check`
    frame = cam.snap()
    assert frame.shape == (256, 256) and frame.dtype == np.uint16
    seq = cam.sequence(3)
    assert seq.shape == (3, 256, 256) and seq[2].min() >= 102  # the three frames of one sequence, in order
    waits = [c[1] for c in fake_dcam.state.calls if c[0] == "wait"]
    assert all(w == int(1000 * (0.5 + 5.0)) for w in waits)  # the wait is bounded by exposure + margin


def test_dcam_errors_name_the_camera_and_the_dcam_error(dcam):
    cam = dcam()
    with pytest.raises(DeviceError, match=r"camera \(DCAM\).*SENSITIVITY.*INVALIDVALUE"):
        cam.em_gain = 5000
    fake_dcam.state.stall_frames = True
    with pytest.raises(DeviceError, match="did not arrive within.*TIMEOUT"):
        cam.snap()
    assert fake_dcam.state.calls[-1] == ("cap_stop",)  # the capture is stopped after a timeout
    with pytest.raises(DeviceError, match="no shutter property"):
        cam.shutter_open = False


def test_dcam_without_a_camera_or_library_says_so():
    fake_dcam.reset(devices=0)
    from fluxcli.hardware.dcam import DcamCamera

    with pytest.raises(DeviceError, match="no DCAM device 0"):
        DcamCamera(0, api=fake_dcam)
    assert fake_dcam.state.initialised == 0  # the API was released again
    with pytest.raises(DeviceError, match="not installed"):
        DcamCamera(0)  # the real wrapper module 'dcam' does not exist here


def test_dcam_refuses_a_camera_without_em_properties(dcam):
    fake_dcam.reset()
    api = types.SimpleNamespace(Dcamapi=fake_dcam.Dcamapi, Dcam=_without("SENSITIVITY"))
    from fluxcli.hardware.dcam import DcamCamera

    with pytest.raises(DeviceError, match="'SENSITIVITY'"):
        DcamCamera(0, api=api)


def _without(name):
    class Limited(fake_dcam.Dcam):
        def __init__(self, i=0):
            super().__init__(i)
            self._by_id = {k: v for k, v in self._by_id.items() if v != name}

    return Limited
