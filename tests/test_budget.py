"""The error budget of every total (issue 26, item 5): photon noise, regularisation, calibration;
and the shift test that warns of a geometry error the data can see."""

from __future__ import annotations

import shutil

import h5py
import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from fluxcli import config as C
from fluxcli.artefacts.reconstruction import read_budget
from fluxcli.cli import app
from fluxcli.errors import UserError
from fluxcli.quantify import budget as Q
from fluxcli.stages import budget as B

from tiny_pipeline import tiny_run  # noqa: F401  (session fixture)


# ------------------------------------------------------------------ the shift test, on images with a known shift
def _blob(shape, cx, cy, width=2.5, peak=4000.0):
    y, x = np.mgrid[:shape[0], :shape[1]]
    return peak * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * width ** 2)) + 5.0


@pytest.mark.parametrize("dx,dy", [(0.3, -0.2), (-0.15, 0.0)])
def test_shift_of_a_moved_image_is_recovered_and_flagged(dx, dy):
    rng = np.random.default_rng(1)
    fitted = _blob((40, 40), 20.0, 19.0)
    measured = rng.poisson(_blob((40, 40), 20.0 + dx, 19.0 + dy)).astype(float)
    s = Q.image_shift(measured, fitted, np.ones_like(fitted, bool), np.maximum(fitted, 0.25))
    # the closed form: the shift that moved the blob, to a few of its standard errors (and 0.05 px)
    assert abs(s.dx_px - dx) < 3 * s.sd_px[0] + 0.05 and abs(s.dy_px - dy) < 3 * s.sd_px[1] + 0.05
    assert s.seen and s.z > Q.SHIFT_Z
    assert Q.shift_warning("p", s, 1.2) is not None


def test_no_shift_in_noise_alone_is_not_flagged():
    fitted = _blob((40, 40), 20.0, 19.0)
    zs = []
    for seed in range(20):
        measured = np.random.default_rng(seed).poisson(fitted).astype(float)
        zs.append(Q.image_shift(measured, fitted, np.ones_like(fitted, bool), fitted).z)
    # z is chi with 2 degrees of freedom under noise alone: mean sqrt(pi/2) = 1.25, never near 5
    assert max(zs) < Q.SHIFT_Z and 0.6 < np.mean(zs) < 2.0


def test_a_residual_that_is_not_a_shift_is_not_read_as_one():
    """A model too dim everywhere (a gain error) leaves a residual shaped like the image, not
    its gradient: no shift, however significant the misfit."""
    fitted = _blob((40, 40), 20.0, 19.0)
    measured = np.random.default_rng(3).poisson(1.3 * fitted).astype(float)
    s = Q.image_shift(measured, fitted, np.ones_like(fitted, bool), fitted)
    assert not s.seen and s.size_px < 0.05


def test_a_misfit_on_one_flank_is_not_read_as_a_shift():
    """The image brighter than the model on one side of its peak (light that varies within an
    element faster than its unknowns, a crease seen edge-on): the residual projects onto the
    gradients, so the whole-image regression is significant, but only the flank that holds the
    misfit sees a shift.  A camera out of place moves both flanks; this is not one."""
    fitted = _blob((40, 40), 20.0, 19.0)
    x = np.mgrid[:40, :40][1]
    measured = np.random.default_rng(0).poisson(fitted * (1 + 0.08 * (x > 21))).astype(float)
    s = Q.image_shift(measured, fitted, np.ones_like(fitted, bool), fitted)
    assert s.z > Q.SHIFT_Z and s.size_px > Q.SHIFT_MIN_PX  # the whole image alone would warn
    assert max(s.flank_z) > Q.SHIFT_Z and min(s.flank_z) < 1.0  # the bright side sees it, the other does not
    assert s.one_flank and not s.seen and Q.shift_warning("p", s, 1.1) is None


def test_one_view_shifted_alone_is_seen_on_both_its_flanks():
    """A mirror a calibration error away moves its view and not the direct one: both flanks of
    the moved view carry the shift, so the flank test keeps the warning."""
    direct = _blob((40, 60), 15.0, 19.0)
    fitted = direct + _blob((40, 60), 45.0, 20.0, width=3.0, peak=2000.0)
    measured = np.random.default_rng(2).poisson(direct + _blob((40, 60), 45.3, 19.8, width=3.0, peak=2000.0))
    s = Q.image_shift(measured.astype(float), fitted, np.ones_like(fitted, bool), fitted)
    assert min(s.flank_z) > 2 * Q.SHIFT_FLANK_Z and s.seen and s.dx_px > 0 > s.dy_px
    assert "system.mirrors" in Q.shift_warning("p", s, 1.3)


def test_calibration_sigma_adds_in_quadrature_with_the_gain():
    assert Q.calibration_sigma(100.0, [3.0, -4.0], 0.12) == pytest.approx(13.0)
    assert Q.calibration_sigma(100.0, [], None) == 0.0
    tb = Q.TotalBudget("x", 100.0, sigma_noise=3.0, sigma_regularisation=float("nan"), sigma_calibration=4.0)
    assert tb.sigma == pytest.approx(5.0)  # a part not computed is left out, not taken as zero


# ------------------------------------------------------------------ the config
def test_camera_uncertainty_is_read_and_a_negative_sigma_exits_2(write_config, minimal_config):
    cfg = dict(minimal_config)
    cfg["system"] = dict(cfg["system"], camera=dict(cfg["system"]["camera"], uncertainty={
        "lens_center_mm": [0.1, 0.1, 0.3], "look_deg": 0.02, "gain_relative": 0.03}))
    loaded = C.load_config(write_config(cfg))
    u = loaded.model.system.camera.uncertainty
    assert u.lens_center_mm == (0.1, 0.1, 0.3) and u.gain_relative == 0.03 and u.focal_length_mm is None
    names = [n for n, *_ in B.parameters(loaded.model.system)]
    assert names == ["lens_center_mm.x", "lens_center_mm.y", "lens_center_mm.z", "look_deg.pan", "look_deg.tilt"]
    cfg["system"]["camera"]["uncertainty"]["lens_center_mm"] = [0.1, -0.1, 0.3]
    with pytest.raises(UserError, match="lens_center_mm"):
        C.load_config(write_config(cfg, "bad.yaml"))
    cfg["system"]["camera"]["uncertainty"] = {"focal_mm": 0.1}
    with pytest.raises(UserError, match="focal_mm"):
        C.load_config(write_config(cfg, "bad2.yaml"))


def test_an_uncertainty_that_moves_the_camera_past_possible_is_named_before_any_solve(write_config, minimal_config,
                                                                                     tmp_path):
    """A camera.yaml whose focal length's 1 sd reads 1e5 mm (a unit slip) made the error budget
    build a camera with f beyond its focus distance: a ValueError in the optics, exit 1, after the
    whole solve. It is now exit 2 naming the key, from reconstruct's plan."""
    cfg = dict(minimal_config)
    cfg["workdir"] = str(tmp_path / "run")
    cfg["system"] = dict(cfg["system"], camera=dict(cfg["system"]["camera"], uncertainty={"focal_length_mm": 1e5}))
    loaded = C.load_config(write_config(cfg))
    with pytest.raises(UserError, match=r"system\.camera\.uncertainty\.focal_length_mm: .*1 sd of 100000 mm.*impossible"):
        B.parameters(loaded.model.system)
    from fluxcli.stages._reconstruct_plan import plan_of

    with pytest.raises(UserError, match=r"uncertainty\.focal_length_mm"):
        plan_of(loaded)
    cfg["system"]["camera"]["uncertainty"] = {"focal_length_mm": 0.01}  # a measurement's spread: fine
    assert [n for n, *_ in B.parameters(C.load_config(write_config(cfg, "ok.yaml")).model.system)] == ["focal_length_mm"]


def test_parameters_move_by_one_sigma_and_keep_the_rest():
    cam = C.Camera(pixels=(8, 8), pixel_pitch_mm=0.1,
                   lens=C.Lens(focal_length_mm=25.0, f_number=4.0, focus_distance_mm=300.0),
                   pose=C.CameraPose(lens_center_mm=(0.0, 0.0, 320.0)),
                   uncertainty=C.CameraUncertainty(look_deg=0.5, focal_length_mm=0.2, aperture_diameter_mm=0.1))
    mirror = C.Mirror(center_mm=(0, 30, 10), normal=(0, -1, 1), axis=(1, 0, 0), size_mm=(40, 20),
                      normal_sigma_deg=1.0, offset_sigma_mm=0.5)
    system = C.System(camera=cam, mirrors=(mirror,))
    moved = {n: s for n, _, _, s in B.parameters(system)}
    for key in ("look_deg.pan", "look_deg.tilt"):
        look = np.asarray(moved[key].camera.pose.look)
        assert np.degrees(np.arccos(look @ (0, 0, -1) / np.linalg.norm(look))) == pytest.approx(0.5)
        assert abs(look @ np.asarray(moved[key].camera.pose.up)) < 1e-12  # still a camera frame
    f = moved["focal_length_mm"].camera.lens
    assert f.focal_length_mm == pytest.approx(25.2) and f.aperture_radius_mm == pytest.approx(25.0 / 8)  # aperture kept
    assert moved["aperture_diameter_mm"].camera.lens.aperture_radius_mm == pytest.approx(25.0 / 8 + 0.05)
    m = moved["mirror mirror0 offset_mm"].mirrors[0]
    assert np.dot(np.subtract(m.center_mm, mirror.center_mm), np.asarray(mirror.normal) / np.sqrt(2)) == pytest.approx(0.5)
    for key in ("mirror mirror0 normal_deg about its axis", "mirror mirror0 normal_deg across its axis"):
        m = moved[key].mirrors[0]
        n0 = np.asarray(mirror.normal) / np.sqrt(2)
        assert np.degrees(np.arccos(np.clip(np.asarray(m.normal) @ n0, -1, 1))) == pytest.approx(1.0)
        assert abs(np.asarray(m.normal) @ np.asarray(m.axis)) < 1e-12


# ------------------------------------------------------------------ the budget in a run
def _copied(tiny, d):
    """The tiny run copied into ``d``: (its config dict, pointing at the copy)."""
    src, cfg, _ = tiny
    shutil.copytree(src, d)
    cfg = yaml.safe_load(yaml.safe_dump(cfg))
    cfg["workdir"] = str(d / "run")
    cfg["transfer"]["cache_dir"] = str(d / "cache")
    return cfg


def _budget_run(tiny, tmp_path, uncertainty, rois=None):
    d = tmp_path / "b"
    cfg = _copied(tiny, d)
    if uncertainty is not None:
        cfg["system"]["camera"]["uncertainty"] = uncertainty
    if rois:
        cfg["rois"] = rois
    p = d / "cfg.yaml"
    p.write_text(yaml.safe_dump(cfg))
    r = CliRunner().invoke(app, ["reconstruct", str(p), "--force"])
    assert r.exit_code == 0, r.output
    with h5py.File(d / "run" / "reconstruction.h5") as f:
        return read_budget(f["budget"]), r.output, cfg


def test_aperture_sigma_moves_the_total_as_the_collected_light(tiny_run, tmp_path):
    """The light a thin lens collects from a distant point grows as its aperture's area: with the
    diameter 1 sd larger, the same images need a total smaller by D²/(D+δ)² (a closed form, not
    the code's)."""
    b, out, cfg = _budget_run(tiny_run, tmp_path, {"aperture_diameter_mm": 0.1, "gain_relative": 0.02},
                              rois=[{"name": "top", "kind": "elements", "ids": list(range(12))}])
    lens = cfg["system"]["camera"]["lens"]
    D = lens["focal_length_mm"] / lens["f_number"]
    expected = D ** 2 / (D + 0.1) ** 2 - 1.0  # -3.1 %
    assert [p["name"] for p in b["parameters"]] == ["aperture_diameter_mm"] and b["t_builds"] == 2
    for k, t in enumerate(b["total"]):
        with h5py.File(tmp_path / "b" / "run" / "reconstruction.h5") as f:
            delta = f["budget/deltas"][k, 0]
        assert delta / t == pytest.approx(expected, rel=0.15)
        # the calibration sigma holds the aperture's change and the gain's 2 % of the total
        assert b["sigma_calibration"][k] == pytest.approx(np.hypot(delta, 0.02 * t), rel=1e-6)
        assert b["sigma"][k] >= max(b["sigma_noise"][k], b["sigma_calibration"][k])
    assert "error budget, all poses jointly" in out and "calibration" in out and "2 T builds" in out
    # a region's total is scaled by the aperture as every element is: its calibration sigma by the same closed form
    with h5py.File(tmp_path / "b" / "run" / "reconstruction.h5") as f:
        roi_total = f["rois/total_photons_per_s"][0] * f["rois"].attrs["exposure_s"] if np.isfinite(
            f["rois"].attrs["exposure_s"]) else f["rois/total_photons_per_s"][0]
    assert b["rois"]["names"] == ["top"]
    for k, t in enumerate(roi_total):
        assert 0 < t < b["total"][k]  # a part of the subject
        assert b["rois"]["sigma_calibration"][0][k] == pytest.approx(np.hypot(expected * t, 0.02 * t), rel=0.15)


def test_without_uncertainty_only_photon_noise_and_no_t_builds(tiny_run, tmp_path):
    b, out, _ = _budget_run(tiny_run, tmp_path, None)
    assert b["t_builds"] == 0 and b["parameters"] == []
    assert all(np.isnan(b["sigma_calibration"])) and all(np.isnan(b["sigma_regularisation"]))
    assert all(s > 0 for s in b["sigma_noise"])  # every total carries its photon-noise sigma
    assert "system.camera.uncertainty not given" in out and "photon noise only" in out


# ------------------------------------------------------------------ one number per pose, each warning once
def test_report_shows_reconstructs_chi2_and_each_warning_once(tiny_run, tmp_path):
    import json

    d = tmp_path / "r"
    cfg = _copied(tiny_run, d)
    p = d / "cfg.yaml"
    p.write_text(yaml.safe_dump(cfg))
    r = CliRunner().invoke(app, ["report", str(p), "--set", "report.surface_views=false"])
    assert r.exit_code == 0, r.output
    summary = json.loads((d / "run" / "report" / "summary.json").read_text())
    with h5py.File(d / "run" / "reconstruction.h5") as f:
        stored = f["per_pose/chi2_per_pixel"][()]
        n_sigma = len(f["budget/sigma"][()])
    assert [p_["chi2_per_pixel"] for p_ in summary["poses"]] == pytest.approx(stored.tolist())
    page = (d / "run" / "report" / "index.html").read_text()
    for w in summary["warnings"]:  # the page lists each warning once
        assert page.count(_html(w)) == 1, w
    assert len(summary["warnings"]) == len(set(summary["warnings"]))
    assert "Error budget of each total" in page and len(summary["budget"]["sigma"]) == n_sigma


def _html(text: str) -> str:
    import html

    return html.escape(text)


def test_the_shift_warning_blames_the_geometry_unless_the_residual_is_also_structured_by_angle():
    s = Q.Shift(0.02, 0.6, (0.01, 0.01), 55.0, 900)
    geometry = Q.shift_warning("p", s, 1.7)
    emission = Q.shift_warning("p", s, 1.7, angle_structured=True)
    assert "system.camera.pose" in geometry and "subject.emission" not in geometry
    assert "subject.emission" in emission
    assert emission.index("subject.emission") < emission.index("system.camera.pose")
    assert Q.shift_warning("p", Q.Shift(0.01, 0.0, (0.01, 0.01), 1.0, 900), 1.0, True) is None  # not seen: none
