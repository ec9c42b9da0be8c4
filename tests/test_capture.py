"""Acquisition on the simulated rig: crash-safe capture.h5, resume, Ctrl-C, device faults,
and reconstruct from a capture.  The devices are the real drivers talking to the wire-protocol
simulators (pty / loopback socket); only the camera is simulated in-process."""

from __future__ import annotations

import copy
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from conftest import cylinder_sim_config
from fluxcli.cli import app

runner = CliRunner()
FLUXMAP = [sys.executable, "-m", "fluxcli.cli"]


def run(*args):
    return runner.invoke(app, [str(a) for a in args])


def rig_config(minimal: dict, cache: Path, **capture) -> dict:
    """The shared small cylinder, a simulated rig (time x 0.05) and an 18-frame plan."""
    cfg = cylinder_sim_config(minimal)
    cfg["system"]["camera"]["pixels"] = [32, 32]
    cfg["system"]["camera"]["pixel_pitch_mm"] = 0.4
    cfg["transfer"] = {"cache_dir": str(cache)}
    cfg["simulate"]["flux"]["peak_photons"] = 1e7  # photons/s: ~1000 counts above bias at the brightest pixel
    cfg["rig"] = {"time_scale": 0.05,
                  "filter_wheel": {"port": "pty", "positions": 6, "filters": {"open": 1, "580nm": 3}},
                  "stage": {"port": "pty", "counts_per_mm": 134737.0, "travel_mm": [0.0, 50.0]},
                  "camera": {"backend": "simulated", "filters": {"580nm": {"transmission": 0.5}}}}
    cfg["subject"]["poses"] = {"heights_mm": [0, 1]}
    cfg["capture"] = {"heights_mm": [0, 1], "filters": ["open", "580nm"], "exposure_s": 1.0, "em_gain": 100.0,
                      "repeats": 4, "darks": 2, "seed": 11} | capture
    return cfg


def frames(path: Path):
    with h5py.File(path, "r") as f:
        return (f["frames/counts"][()], f["frames/committed"][()].astype(bool),
                {k: f[f"frames/{k}"][()] for k in ("stage_height_mm", "filter_name", "shutter_open", "em_gain")},
                f["plan/height_mm"][()], np.char.decode(f["plan/filter"][()]), f["plan/dark"][()].astype(bool))


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """One uninterrupted capture (and the T cache every test here shares)."""
    root = tmp_path_factory.mktemp("capture_ref")
    minimal = yaml.safe_load((Path(__file__).parents[1] / "configs" / "minimal.yaml").read_text())
    minimal["workdir"] = "run"
    cfg = rig_config(minimal, root / "Tcache")
    path = root / "cfg.yaml"
    path.write_text(yaml.safe_dump(cfg))
    r = run("capture-surface", path)
    assert r.exit_code == 0, r.output
    return cfg, root / "run" / "capture.h5"


def test_capture_holds_every_planned_frame_with_read_back_metadata(reference):
    cfg, path = reference
    counts, committed, meta, ph, pf, dark = frames(path)
    assert committed.all() and len(counts) == 2 + 2 * 2 * 4
    assert dark[:2].all() and not dark[2:].any()
    assert np.array_equal(meta["shutter_open"].astype(bool), ~dark)
    light = ~dark
    # read back from the stage: the planned height to within one microstep
    assert np.allclose(meta["stage_height_mm"][light], ph[light], atol=1 / 134737.0)
    assert list(np.char.decode(meta["filter_name"][light])) == list(pf[light])
    assert np.all(meta["em_gain"] == 100.0)
    # the simulated scene: the 580nm filter passes half the light (signal above the dark level)
    dark_level = counts[dark].mean()
    sig = {f: counts[light & (pf == f)].astype(float).sum(axis=(1, 2)).mean() - dark_level * 32 * 32
           for f in ("open", "580nm")}
    assert sig["580nm"] / sig["open"] == pytest.approx(0.5, rel=0.08)


def _start(path: Path, env: dict) -> subprocess.Popen:
    return subprocess.Popen([*FLUXMAP, "capture-surface", str(path), "--resume"], stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True, env=env, cwd=path.parent)


def _wait_for(p: subprocess.Popen, word: str) -> None:
    for line in p.stdout:
        if word in line:
            return


def test_sigkill_at_random_instants_then_resume_is_bit_identical(reference, tmp_path):
    """>= 20 SIGKILLs at random instants (3 inside the creation of capture.h5, the others
    anywhere from start-up to the last frame), each followed by --resume: the final file
    holds every frame exactly once, bit-identical to the uninterrupted run."""
    cfg, ref_path = reference
    ref_counts, *_ = frames(ref_path)
    path = tmp_path / "cfg.yaml"
    path.write_text(yaml.safe_dump(cfg))
    out = tmp_path / "run" / "capture.h5"
    env = os.environ | {"FLUXMAP_CAPTURE_CREATE_PAUSE_S": "0.05"}  # widens the creation window to ~0.15 s
    rng = np.random.default_rng(2026)
    kills, in_creation, progress = 0, 0, []
    for i in range(40):
        if kills >= 20:
            break
        p = _start(path, env)
        if i < 3:  # inside the creation: after "creating", before its three pauses are over
            _wait_for(p, "creating")
            time.sleep(rng.uniform(0.0, 0.1))
        elif i % 2:  # during acquisition
            _wait_for(p, "frames to take")
            time.sleep(rng.uniform(0.0, 0.5))
        else:  # anywhere from start-up on
            time.sleep(rng.uniform(0.0, 1.0))
        if p.poll() is None:
            os.kill(p.pid, signal.SIGKILL)
            kills += 1
        p.wait()
        p.stdout.close()
        if not out.exists() and list(out.parent.glob(".capture.h5.*.tmp*")):
            in_creation += 1
        if out.exists():  # whatever the instant, the file opens and its committed frames are right
            counts, committed, *_ = frames(out)
            assert np.array_equal(counts[committed], ref_counts[committed])
            progress.append(int(committed.sum()))
    r = subprocess.run([*FLUXMAP, "capture-surface", str(path), "--resume"], capture_output=True, text=True,
                       cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    counts, committed, *_ = frames(out)
    assert kills >= 20 and in_creation >= 2, (kills, in_creation, progress)
    assert committed.all() and len(counts) == len(ref_counts)
    assert np.array_equal(counts, ref_counts)  # every frame exactly once, the same bytes
    assert not list(out.parent.glob(".capture.h5.*.tmp*"))  # killed creations were cleaned up
    print(f"{kills} kills ({in_creation} during creation); committed frames after each: {progress}")


def test_resume_refuses_another_plan_and_an_existing_capture_needs_a_flag(reference, tmp_path):
    cfg, ref_path = reference
    other = copy.deepcopy(cfg)
    other["capture"]["em_gain"] = 200.0
    other["workdir"] = str(ref_path.parent)
    p = tmp_path / "other.yaml"
    p.write_text(yaml.safe_dump(other))
    r = run("capture-surface", p, "--resume")
    assert r.exit_code == 2 and "capture.em_gain: file has 100.0, config has 200.0" in " ".join(r.output.split())
    r = run("capture-surface", p)
    assert r.exit_code == 2 and "--resume" in r.output and "--force" in r.output
    r = run("capture-surface", p.parent / "nonexistent.yaml")
    assert r.exit_code == 2


def test_ctrl_c_stops_at_a_frame_boundary_and_leaves_the_devices_safe(reference, tmp_path):
    """In-process: the real drivers on the simulators; 'Ctrl-C' after the third frame."""
    from fluxcli.acquisition import CaptureFile, Interrupted, Plan, RigDevices, acquire
    from fluxcli.config import load_config
    from fluxcli.hardware.rig import open_devices, start_simulators
    from fluxcli.stages.capture import SimulatedScene, _camera, plan_of

    cfg_dict, ref_path = reference
    cfg_dict = copy.deepcopy(cfg_dict)
    p = tmp_path / "cfg.yaml"
    p.write_text(yaml.safe_dump(cfg_dict))
    cfg = load_config(p)
    rig, cap = cfg.model.rig, cfg.model.capture
    sims = start_simulators(rig)
    wheel, stage = open_devices(rig, {n: s.url for n, s in sims.items()})
    try:
        cam = _camera(plan_of(cfg), sims, wheel, stage, SimulatedScene(cfg))
        plan = Plan(tuple(cap.heights_mm), tuple(cap.filters), cap.exposures_s, cap.em_gain, cap.repeats, cap.darks,
                    cap.seed, cam.shape)
        out = CaptureFile.create(tmp_path / "capture.h5", plan)
        taken = []
        with pytest.raises(Interrupted):
            acquire(plan, out, RigDevices(stage, wheel, cam, dict(rig.filter_wheel.filters)),
                    stop_requested=lambda: len(taken) >= 3, on_frame=taken.append)
        out.close()
        assert cam.shutter_open is False
        assert not sims["stage"].moving and not sims["filter_wheel"].moving
        counts, committed, *_ = frames(tmp_path / "capture.h5")
        assert committed.sum() == 3 and committed[:3].all()
        ref_counts, *_ = frames(ref_path)
        assert np.array_equal(counts[:3], ref_counts[:3])
    finally:
        wheel.close()
        stage.close()
        for s in sims.values():
            s.stop()


@pytest.mark.parametrize("device, command, named, kept", [
    # the darks and the frames at 0 mm (no move needed) are kept; nothing at 1 mm
    ("stage", "MOT_MOVE_ABSOLUTE", "stage", 10),
    # the darks and 'open' (already in the beam) at 0 mm are kept
    ("filter_wheel", "pos=", "filter wheel", 6),
])
def test_a_device_that_never_answers_exits_2_naming_it_and_keeps_the_file(reference, tmp_path, device, command,
                                                                          named, kept):
    cfg, _ = reference
    cfg = copy.deepcopy(cfg)
    cfg["rig"][device]["timeout_s"] = 0.3
    cfg["rig"][device]["faults"] = [{"kind": "no_reply", "on": command, "count": 0}]
    p = tmp_path / "cfg.yaml"
    p.write_text(yaml.safe_dump(cfg))
    t0 = time.perf_counter()
    r = run("capture-surface", p)
    assert r.exit_code == 2, r.output
    assert named in r.output.lower() and "Traceback" not in r.output
    assert time.perf_counter() - t0 < 30  # bounded, never a hang
    counts, committed, *_ = frames(tmp_path / "run" / "capture.h5")
    assert committed[:kept].all() and not committed[kept:].any()


def _reconstruct_from_capture(reference, tmp_path):
    """The reference capture's config, reconstructing from its capture.h5 (open filter): (ref_path, cfg path)."""
    cfg, ref_path = reference
    cfg = copy.deepcopy(cfg)
    cfg["workdir"] = str(ref_path.parent)
    cfg["reconstruct"] = {"images": {"capture": "capture.h5", "filter": "open"}}
    p = tmp_path / "cfg.yaml"
    p.write_text(yaml.safe_dump(cfg))
    return ref_path, p, cfg


def test_reconstruct_from_the_capture_recovers_the_total(reference, tmp_path):
    ref_path, p, cfg = _reconstruct_from_capture(reference, tmp_path)
    r = run("reconstruct", p)
    assert r.exit_code == 0, r.output
    with h5py.File(ref_path.parent / "reconstruction.h5", "r") as f:
        total, truth = float(f["flux/total"][()]), f["truth/power"][()]
        observed = f["flux/observed"][()]
    # the truth that the capture recorded for 'open', on the elements the camera sees
    assert total == pytest.approx(truth[observed].sum(), rel=0.05)
    cfg["reconstruct"]["images"]["filter"] = "650nm"
    p.write_text(yaml.safe_dump(cfg))
    r = run("reconstruct", p, "--force")
    assert r.exit_code == 2 and "'650nm' is not in capture" in " ".join(r.output.split())
    cfg["reconstruct"]["images"]["filter"] = "open"
    cfg["subject"]["poses"] = {"heights_mm": [0, 10]}
    p.write_text(yaml.safe_dump(cfg))
    r = run("reconstruct", p, "--force")
    text = " ".join(r.output.split())
    assert r.exit_code == 2 and "[0.0, 1.0]" in text and "[0.0, 10.0]" in text


@pytest.mark.parametrize("damage, words", [
    ("d = f['plan/height_mm'][()]; del f['plan/height_mm']; f['plan/height_mm'] = d[:-1]",
     "plan/height_mm holds 17 frames but frames/committed 18"),
    ("f['frames/em_gain'][3] = float('nan')", "frames/em_gain[3] is nan, not an EM gain of at least 1"),
    ("f['frames/stage_height_mm'][5] = float('inf')", "frames/stage_height_mm[5] is inf, not a finite height"),
    ("f['plan/height_mm'][:] = 7.0", "its plan names height 0 mm, but no light frame"),
])
def test_a_damaged_capture_exits_2_naming_what_is_wrong(reference, tmp_path, damage, words):
    """A capture whose per-frame datasets disagree in length, or whose read-back settings no
    camera gives (NaN gain), stopped inside the reader with an index or broadcast error, or
    in the EMCCD model (exit 1; found by fuzzing capture.h5)."""
    cfg, ref_path = reference
    shutil.copytree(ref_path.parent, tmp_path / "run", ignore=shutil.ignore_patterns("reconstruction*", "report"))
    cfg = copy.deepcopy(cfg)
    cfg["workdir"] = str(tmp_path / "run")
    cfg["reconstruct"] = {"images": {"capture": "capture.h5", "filter": "open"}}
    p = tmp_path / "cfg.yaml"
    p.write_text(yaml.safe_dump(cfg))
    with h5py.File(tmp_path / "run" / "capture.h5", "r+") as f:
        exec(damage, {"f": f})
    r = run("reconstruct", p)
    text = " ".join(r.output.split())
    assert r.exit_code == 2 and "is damaged" in text and words in text, r.output


def test_counts_to_photons_subtracts_the_dark_level_without_bias():
    """N = (C - D) g / (G QE): the mean over many pixels recovers the photons per pixel,
    whatever the bias, dark current and CIC (they are in the dark frames too)."""
    from fluxcli.acquisition import CaptureImages
    from fluxcli.hardware.camera import SimulatedEmccd
    from fluxcli.imaging.noise import EMCCDModel, capture_photons

    sensor = EMCCDModel(quantum_efficiency=0.7, em_gain=50.0, read_noise_e=30.0, bias_counts=321.0,
                        electrons_per_count=8.0, dark_current_e_per_s=2.0, cic_e_per_pixel=0.1, exposure_s=0.5)
    N = np.linspace(5.0, 40.0, 64 * 64).reshape(64, 64)  # photons per exposure
    cam = SimulatedEmccd(lambda h, f: N / 0.5, stage_height_mm=lambda: 0.0, filter_name=lambda: "open",
                         sensor=sensor, seed=1, time_scale=0.0)
    darks = cam.sequence(6)
    cam.shutter_open = True
    light = cam.sequence(4)
    images = CaptureImages(np.array([0.0]), np.array([0.0]), light.astype(float).mean(axis=0)[None],
                           light.max(axis=0)[None], float(darks.astype(float).mean()), 6, 4, 0.5, 50.0, "open", None)
    # the sensor's bias/dark/CIC are deliberately wrong here: the dark frames must carry them
    wrong = EMCCDModel(quantum_efficiency=0.7, electrons_per_count=8.0, bias_counts=0.0, dark_current_e_per_s=99.0)
    photons, valid = capture_photons(images, wrong)
    assert valid.all()
    var_one = (2 - 1 / 50) * (0.7 * N + 1.1) / 0.7**2 / 4  # F^2 = 2 - 1/G, averaged over 4 repeats (read noise negligible at G=50)
    assert abs(photons.mean() - N.mean()) < 5 * np.sqrt(var_one.sum()) / N.size + 0.05
    # unbiased per level: compare the lower and upper halves of the ramp
    assert photons[0, :32].mean() == pytest.approx(N[:32].mean(), rel=0.03)
    assert photons[0, 32:].mean() == pytest.approx(N[32:].mean(), rel=0.03)


def test_ctrl_c_end_to_end_exits_130_with_a_consistent_file(reference, tmp_path):
    cfg, ref_path = reference
    ref_counts, *_ = frames(ref_path)
    path = tmp_path / "cfg.yaml"
    path.write_text(yaml.safe_dump(cfg))
    p = _start(path, dict(os.environ))
    _wait_for(p, "frames to take")
    time.sleep(0.3)
    p.send_signal(signal.SIGINT)
    rest = p.communicate(timeout=30)[0]
    assert p.returncode == 130, rest
    assert "shutter closed, stage stopped" in " ".join(rest.split())
    counts, committed, *_ = frames(tmp_path / "run" / "capture.h5")
    n = int(committed.sum())
    assert 0 < n < len(committed) and committed[:n].all()  # stopped between frames, in plan order
    assert np.array_equal(counts[:n], ref_counts[:n])


def test_a_wavelength_needs_a_diffusion_truth(reference, tmp_path):
    cfg, _ = reference
    cfg = copy.deepcopy(cfg)
    cfg["rig"]["camera"]["filters"]["580nm"] = {"wavelength_nm": 580}
    p = tmp_path / "cfg.yaml"
    p.write_text(yaml.safe_dump(cfg))
    r = run("capture-surface", p)
    assert r.exit_code == 2 and "rig.camera.filters.580nm.wavelength_nm" in r.output
    assert not (tmp_path / "run" / "capture.h5").exists()


def test_several_exposures_each_with_its_own_darks(reference, tmp_path):
    cfg, _ = reference
    cfg = copy.deepcopy(cfg)
    cfg["capture"] |= {"exposure_s": [0.5, 2.0], "filters": ["open"], "repeats": 2, "darks": 2}
    cfg["reconstruct"] = {"images": {"capture": "capture.h5"}}
    # totals are compared with the truth, so the camera must resolve the subject: the shared
    # 32 x 32 camera at 0.4 mm images the 96-element cylinder onto ~17 pixels (χ²/pixel 0.03,
    # "the fit follows the noise"), where a total within 5 % was luck of the per-element
    # rendering; at 0.05 mm it covers ~1000 pixels
    cfg["system"]["camera"] |= {"pixels": [64, 64], "pixel_pitch_mm": 0.05}
    p = tmp_path / "cfg.yaml"
    p.write_text(yaml.safe_dump(cfg))
    assert run("capture-surface", p).exit_code == 0
    with h5py.File(tmp_path / "run" / "capture.h5", "r") as f:
        pe, dark = f["plan/exposure_s"][()], f["plan/dark"][()].astype(bool)
        assert np.array_equal(f["frames/exposure_s"][()], pe)  # read back from the camera
        assert sorted(pe[dark]) == [0.5, 0.5, 2.0, 2.0]
    r = run("reconstruct", p)
    assert r.exit_code == 2 and "reconstruct.images.exposure_s" in r.output
    totals = {}
    for e in (0.5, 2.0):
        assert run("reconstruct", p, "--force", "--set", f"reconstruct.images.exposure_s={e}").exit_code == 0
        with h5py.File(tmp_path / "run" / "reconstruction.h5", "r") as f:
            totals[e] = float(f["flux/total"][()])
            truth = f["truth/power"][()]
        assert totals[e] == pytest.approx(truth.sum(), rel=0.05)
    assert totals[2.0] / totals[0.5] == pytest.approx(4.0, rel=0.1)  # photons per exposure scale with it


def test_devices_served_elsewhere_are_driven_through_their_ports(reference, tmp_path):
    """Ports that are not simulator ports are opened as devices (here simulators started
    outside the command, as 'fluxmap rig serve' would); the simulated camera then follows
    the drivers' read-back."""
    from fluxcli.config import load_config
    from fluxcli.hardware.rig import start_simulators

    cfg, ref_path = reference
    sims = start_simulators(load_config(ref_path.parent.parent / "cfg.yaml").model.rig)
    try:
        cfg = copy.deepcopy(cfg)
        cfg["rig"]["filter_wheel"]["port"] = sims["filter_wheel"].url
        cfg["rig"]["stage"]["port"] = sims["stage"].url
        p = tmp_path / "cfg.yaml"
        p.write_text(yaml.safe_dump(cfg))
        r = run("capture-surface", p)
        assert r.exit_code == 0, r.output
        assert sims["stage"].position_mm == pytest.approx(1.0)  # the served stage moved
    finally:
        for s in sims.values():
            s.stop()
    counts, committed, *_ = frames(tmp_path / "run" / "capture.h5")
    # the same frames as with in-process simulators: the scene depends on physical state only
    assert committed.all() and np.array_equal(counts, frames(ref_path)[0])


def test_the_simulated_camera_renders_a_truth_finer_than_the_elements(reference, tmp_path):
    """The rig simulator's emission is T_fwd per face of the refined surface times the truth
    per face (simulate.truth_refinement), not a constant per element: summed per element it
    is /truth/<filter>/power, the light on the sensor is the same to the forward T's sampling,
    and the variation within elements shows in the image (a constant per element would be
    half an inverse crime for a reconstruction on those elements)."""
    from fluxcli.config import load_config
    from fluxcli.stages.plans import ensure_pose_T
    from fluxcli.scene import Pose
    from fluxcli.stages.capture import SimulatedScene
    from fluxcli.truth import forward_transfer

    cfg_dict, _ = reference
    cfg_dict = copy.deepcopy(cfg_dict)
    cfg_dict["system"]["camera"] |= {"pixels": [64, 64], "pixel_pitch_mm": 0.05}  # resolves the elements
    p = tmp_path / "cfg.yaml"
    p.write_text(yaml.safe_dump(cfg_dict))
    cfg = load_config(p)  # no rig.camera.true_surface: the scene renders this config's subject
    scene = SimulatedScene(cfg)
    fine, parent = scene.fine_rate("open")
    surface = scene.placer.surface
    n = surface.n_elements
    assert len(fine) == 4 * np.count_nonzero(surface.element_of_face >= 0)  # truth_refinement 1: faces split in 4
    per_element = scene.power_rate("open")
    assert np.allclose(np.bincount(parent, weights=fine, minlength=n), per_element, rtol=1e-12)
    image = scene.emission(0.0, "open")
    T_el = ensure_pose_T(cfg, Pose(0.0, 0.0), forward_transfer(cfg.model.simulate, cfg.model.transfer),
                         scene.placer)
    constant = (T_el @ per_element).reshape(image.shape)
    assert image.sum() == pytest.approx(constant.sum(), rel=0.01)
    assert np.abs(image - constant).max() > 0.05 * image.max()


def test_calibration_frames_first_leave_the_subject_frames_unchanged(reference, tmp_path):
    """capture.calibration (issue 26) is taken before the subject: with it in the plan the
    subject's frames are byte-identical to a capture without it (the set-up is taken away again,
    and each frame's noise is keyed by its own plan slot), and the calibration frames see the
    even light and the closed shutter."""
    cfg, ref_path = reference
    ref_counts, *_ = frames(ref_path)
    cfg = copy.deepcopy(cfg)
    cfg["workdir"] = str(tmp_path / "run")
    cfg["capture"]["calibration"] = {"bias": {"frames": 2, "exposure_s": 0.001},
                                     "ptc": {"exposures_off_s": [0.01, 0.02]},
                                     "simulated": {"light_photons_per_s": 1.0e5}}
    path = tmp_path / "cfg.yaml"
    path.write_text(yaml.safe_dump(cfg))
    r = run("capture-surface", path)
    assert r.exit_code == 0, r.output
    counts, committed, *_ = frames(tmp_path / "run" / "capture.h5")
    assert committed.all() and np.array_equal(counts, ref_counts)
    with h5py.File(tmp_path / "run" / "capture.h5", "r") as f:
        kind = np.char.decode(f["calibration/kind"][()])
        cal = f["calibration/counts"][()].astype(float)
        exposure = f["calibration/exposure_s"][()]
    sensor = cfg["system"]["camera"].get("sensor", {})
    bias = sensor.get("bias_counts", 500.0)
    assert abs(cal[kind == "bias"].mean() - bias) < 2  # shutter closed: the bias (dark and CIC negligible)
    ptc = kind == "ptc_off"
    expected = 0.9 * 1.0e5 * exposure[ptc] / sensor.get("electrons_per_count", 10.0)  # QE 0.9, gain off
    assert np.allclose(cal[ptc].mean(axis=(1, 2)) - bias, expected, rtol=0.02)


def test_a_real_rig_is_told_what_to_set_up_and_waits(monkeypatch):
    from fluxcli.stages import capture as S

    said, asked = [], []
    ctx = type("Ctx", (), {"say": lambda self, m: said.append(m)})()
    monkeypatch.setattr("builtins.input", lambda prompt="": asked.append(prompt) or "")
    prepare = S._operator_prepare(ctx, confirm=True)
    prepare("grid")
    prepare("closed")  # the shutter does it: nothing to wait for
    assert "grid flat on the stage" in said[0] and len(asked) == 1
    S._operator_prepare(ctx, confirm=False)("light")
    assert "even light" in said[-1] and len(asked) == 1


def test_the_record_shows_the_sensor_as_the_frames_were_taken(reference, tmp_path):
    """issue 26: the report's sensor row showed the config's em_gain (300, the schema default)
    for frames read out at 100; it reads the gain the camera reported per frame."""
    from fluxcli import config as C
    from fluxcli.stages.outputs import sensor_row

    ref_path, p, cfg = _reconstruct_from_capture(reference, tmp_path)
    loaded = C.load_config(p)
    assert loaded.model.system.camera.sensor.em_gain == 300.0  # what the config says

    label, text = sensor_row(loaded.model.system.camera.sensor, loaded.model.reconstruct.images, loaded.images_capture_path())
    assert label == "sensor" and "as the frames were taken" in text and "em_gain 100;" in text
    assert "em_gain 300" not in text
