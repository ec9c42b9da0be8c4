"""Results people open elsewhere: the .vtp files, and the units they carry (radiance)."""

from __future__ import annotations

import copy

import h5py
import numpy as np
import pytest
from conftest import cylinder_sim_config
from typer.testing import CliRunner

from fluxcli.cli import app
from fluxcli.surface.units import element_quantities, lambertian_radiance_per_cm2

runner = CliRunner()


def run(*args):
    r = runner.invoke(app, [str(a) for a in args])
    assert r.exit_code == 0, r.output
    return r


def _read_vtp_with_vtk(path):
    """ParaView's reader: VTK's own XML PolyData reader, not pyvista's wrapper."""
    import vtk
    from vtk.util.numpy_support import vtk_to_numpy

    reader = vtk.vtkXMLPolyDataReader()
    reader.SetFileName(str(path))
    reader.Update()
    poly = reader.GetOutput()
    cd = poly.GetCellData()
    arrays = {cd.GetArrayName(i): vtk_to_numpy(cd.GetArray(i)) for i in range(cd.GetNumberOfArrays())}
    return poly, arrays


@pytest.fixture(scope="module")
def cylinder_run(tmp_path_factory):
    """The shared small cylinder (caps are occluders, not elements), two heights, 2.5 s exposure."""
    import yaml
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    minimal = yaml.safe_load((root / "configs" / "minimal.yaml").read_text())
    minimal["workdir"] = "run"
    cfg = cylinder_sim_config(minimal)
    cfg["simulate"]["noise"]["exposure_s"] = 2.5
    tmp = tmp_path_factory.mktemp("vtp")
    p = tmp / "cfg.yaml"
    p.write_text(yaml.safe_dump(cfg))
    run("simulate", p, "--quiet")
    run("reconstruct", p, "--quiet")
    return tmp / "run"


def test_reconstruction_vtp_holds_the_artefact_per_face(cylinder_run):
    import pyvista as pv

    t = 2.5
    mesh = pv.read(cylinder_run / "reconstruction.vtp")
    with h5py.File(cylinder_run / "reconstruction.h5") as f:
        verts, faces = f["surface/vertices"][()], f["surface/faces"][()]
        eof = f["surface/element_of_face"][()]
        areas = f["surface/areas"][()]
        power, observed, sigma = f["flux/power"][()], f["flux/observed"][()], f["flux/sigma"][()]
        truth = f["truth/power"][()]
        pose_power, pose_obs = f["per_pose/power"][()], f["per_pose/observed"][()]
    assert (eof < 0).any() and observed.any()  # caps: faces that are no element
    np.testing.assert_array_equal(mesh.points, verts)
    np.testing.assert_array_equal(mesh.faces.reshape(-1, 4)[:, 1:], faces)
    cd = mesh.cell_data
    np.testing.assert_array_equal(cd["element_id"], eof)
    # face by face, as a user would map it
    for i, e in enumerate(eof):
        if e < 0:
            assert cd["observed_state"][i] == -1
            assert np.isnan(cd["power_photons"][i]) and np.isnan(cd["truth_power_photons"][i])
            continue
        assert cd["observed_state"][i] == (1 if observed[e] else 0)
        if observed[e]:
            assert cd["power_photons"][i] == power[e]
            assert cd["exitance_photons_per_mm2"][i] == pytest.approx(power[e] / areas[e], rel=1e-12)
            assert cd["flux_photons_per_s"][i] == pytest.approx(power[e] / t, rel=1e-12)
            assert cd["radiance_photons_per_s_per_cm2_per_sr"][i] == pytest.approx(
                power[e] / areas[e] / t * 100 / np.pi, rel=1e-12)
            np.testing.assert_equal(cd["sigma_photons"][i], sigma[e])
        else:
            assert np.isnan(cd["power_photons"][i])  # unobserved: unknown, never zero
        assert cd["truth_power_photons"][i] == truth[e]
        for k in range(len(pose_power)):
            assert cd[f"pose{k + 1}_observed_state"][i] == int(pose_obs[k, e])
    # the total: one value per element, summed over elements (not over faces)
    first = np.unique(eof[eof >= 0], return_index=True)[1]
    assert np.nansum(cd["power_photons"][np.flatnonzero(eof >= 0)[first]]) == pytest.approx(np.nansum(power), rel=1e-12)
    units = "\n".join(mesh.field_data["units"])
    assert "radiance_photons_per_s_per_cm2_per_sr: photons s^-1 cm^-2 sr^-1" in units
    assert float(mesh.field_data["exposure_s"][0]) == t


def test_vtp_is_vtk_xml_that_paraview_reads(cylinder_run):
    path = cylinder_run / "reconstruction.vtp"
    head = path.read_bytes()[:200]
    assert b"<VTKFile" in head and b'type="PolyData"' in head
    poly, arrays = _read_vtp_with_vtk(path)
    with h5py.File(cylinder_run / "reconstruction.h5") as f:
        n_faces = len(f["surface/faces"])
        eof = f["surface/element_of_face"][()]
    assert poly.GetNumberOfCells() == n_faces
    np.testing.assert_array_equal(arrays["element_id"], eof)
    # the simulated truth too, every element observed by construction
    poly, arrays = _read_vtp_with_vtk(cylinder_run / "simulation_truth.vtp")
    with h5py.File(cylinder_run / "simulation.h5") as f:
        truth = f["truth/power"][()] * f["truth/level_scale"][0]
    m = eof >= 0
    np.testing.assert_allclose(arrays["power_photons"][m], truth[eof[m]], rtol=1e-12)
    assert set(arrays["observed_state"][m]) == {1} and set(arrays["observed_state"][~m]) == {-1}
    assert "level1_power_photons" in arrays


def test_without_an_exposure_only_per_exposure_quantities(tmp_path, write_config, minimal_config):
    q = element_quantities([2.0, np.nan], [4.0, 1.0])
    assert set(q) == {"power_photons", "exitance_photons_per_mm2"}
    assert q["exitance_photons_per_mm2"][0] == 0.5 and np.isnan(q["exitance_photons_per_mm2"][1])
    with pytest.raises(ValueError):
        element_quantities([1.0], [1.0], exposure_s=0.0)


def test_radiance_of_a_steradian_cone():
    # a Lambertian emitter of exitance M sends M/pi per steradian along its normal, per unit area:
    # integrate L cos(theta) over the hemisphere numerically and get M back
    m_per_s_mm2 = 3.0e4
    L_cm2 = lambertian_radiance_per_cm2(m_per_s_mm2)
    th = np.linspace(0, np.pi / 2, 20001)
    hemi = np.trapezoid(np.cos(th) * np.sin(th), th) * 2 * np.pi  # = pi
    assert L_cm2 / 100 * hemi == pytest.approx(m_per_s_mm2, rel=1e-6)


def test_uniform_lambertian_emitter_reports_radiance_M_over_pi(write_config, minimal_config, tmp_path):
    """A flat patch of uniform exitance M in the focal plane, facing the camera: the .vtp's
    radiance is M / (pi t) in photons/s/cm^2/sr, and so is what the noiseless image says
    through the closed form for an on-axis pixel: photons = L t A_pixel pi R^2 / (R^2 + u^2)."""
    M, t = 2.0e5, 4.0  # photons/mm^2 per exposure, s
    f_mm, N, u = 25.0, 4.0, 300.0
    cfg = copy.deepcopy(minimal_config)
    cfg["system"]["camera"] = {"pixels": [32, 32], "pixel_pitch_mm": 0.1,
                               "lens": {"focal_length_mm": f_mm, "f_number": N, "focus_distance_mm": u},
                               "pose": {"lens_center_mm": [0, 0, 320.0]}}
    cfg["subject"]["surface"] = {"phantom": "patch", "size_mm": [12, 12], "n": [3, 3], "center_mm": [0, 0, 20.0]}
    cfg["simulate"] = {"flux": {"kind": "uniform", "exitance_photons_per_mm2": M},
                       "noise": {"model": "none", "exposure_s": t}}
    cfg["reconstruct"] = {"noiseless": True}
    p = write_config(cfg)
    run("simulate", p, "--quiet")
    run("reconstruct", p, "--quiet")
    expected = M / t / np.pi * 100  # photons/s/cm^2/sr

    import pyvista as pv

    mesh = pv.read(tmp_path / "run" / "reconstruction.vtp")
    L = mesh.cell_data["radiance_photons_per_s_per_cm2_per_sr"]
    eid = mesh.cell_data["element_id"]
    centre = L[eid == 4]  # the middle element of 3 x 3
    np.testing.assert_allclose(centre, expected, rtol=0.03)
    assert np.nanmean(L) == pytest.approx(expected, rel=0.05)
    truth = pv.read(tmp_path / "run" / "simulation_truth.vtp").cell_data["radiance_photons_per_s_per_cm2_per_sr"]
    np.testing.assert_allclose(truth, expected, rtol=1e-9)

    # the image itself, through the closed form, with no fluxmap code in between
    with h5py.File(tmp_path / "run" / "simulation.h5") as fh:
        img = fh["images/noiseless"][0, 0]
    v = 1 / (1 / f_mm - 1 / u)
    a_pixel = (0.1 * u / v) ** 2  # mm^2 of the focal plane one pixel sees
    R = f_mm / (2 * N)
    per_pixel = img[15:17, 15:17].mean()  # the four pixels around the axis
    L_image = per_pixel / (t * a_pixel * np.pi * R**2 / (R**2 + u**2)) * 100  # photons/s/cm^2/sr
    assert L_image == pytest.approx(expected, rel=0.01)


# ------------------------------------------------------------------ the report in a real browser
def _chromium_or_skip():
    from fluxcli.report import browser_check as B

    if B.find_chromium() is None:
        pytest.skip("no Chromium installed (Debian: apt-get install chromium); `make check-report` needs it too")
    return B


@pytest.mark.slow  # a browser run: `make bench` and `make check-report`, not `make test`
def test_report_renders_its_3d_view_in_headless_chromium(cylinder_run, tmp_path):
    B = _chromium_or_skip()
    cfg = cylinder_run.parent / "cfg.yaml"
    run("report", cfg, "--quiet")
    index = cylinder_run / "report" / "index.html"
    png = tmp_path / "report.png"
    assert B.check(index, png) == []
    from matplotlib.image import imread

    rgb = (imread(png)[:, :, :3] * 255).astype(np.uint8)
    t, b, l, r = B.scene_box(rgb)
    assert (b - t) > 200 and (r - l) > 300


@pytest.mark.slow
def test_browser_check_catches_a_blank_view_and_console_errors(tmp_path):
    B = _chromium_or_skip()
    page = tmp_path / "bad.html"
    page.write_text("<!DOCTYPE html><html><body><h1>no 3-D here</h1>"
                    "<script>console.error('broken');</script></body></html>")
    problems = B.check(page, tmp_path / "bad.png", height=600)
    assert any("broken" in p for p in problems)
    assert any("no 3-D scene" in p for p in problems)


def test_report_warnings_name_a_pose_that_sees_half_the_light_and_a_bad_fit(cylinder_run):
    from types import SimpleNamespace

    from fluxcli.report.notebook import observed_share, warnings_for

    # half the power on elements the first pose sees, all of it for the second; NaN counts as nothing
    power = np.array([1.0, 1.0, 2.0, np.nan])
    obs = np.array([[True, True, False, False], [True, True, True, True]])
    np.testing.assert_allclose(observed_share(obs, power), [0.5, 1.0])
    study = SimpleNamespace(reconstruction_path=cylinder_run / "reconstruction.h5")
    summary = {"observed_share": {"per_pose": [0.5, 1.0], "basis": "of the true light"},
               "poses": [{"chi2_per_pixel": 1.1}, {"chi2_per_pixel": 7.0}]}
    w = warnings_for(study, summary)
    assert any(s.startswith("pose 1 observes only 50%") for s in w)
    assert any(s.startswith("pose 2: χ²/pixel = 7") for s in w)
    assert not any(s.startswith("pose 2 observes") or s.startswith("pose 1: χ²") for s in w)


def test_summary_prints_per_pose_totals_spreads_and_rates(cylinder_run):
    out = run("summary", cylinder_run.parent / "cfg.yaml").output
    with h5py.File(cylinder_run / "reconstruction.h5") as f:
        totals = f["per_pose/total"][()]
        roi = f["per_pose/direct_roi_photons"][()]
    # issue 26: the ROI sum beside the total in the same unit (photons/s), every total with its sigma
    assert "exposure 2.5 s" in out and "fluxmap total (photons/s, ± 1 sd)" in out and "direct ROI sum (photons/s)" in out
    assert f"{totals[0] / 2.5:.4g} ± " in out and f"{roi[0] / 2.5:.4g}" in out
    assert f"fluxmap total {(totals.max() - totals.min()) / totals.mean():.1%}" in out
    assert out.rstrip().splitlines()[-1].startswith("report:")


def test_summary_sets_each_pose_s_total_against_the_truth_on_the_elements_it_observes(cylinder_run):
    """A simulated run: each pose's total over the truth summed on the elements that pose observes
    (what stays 1 as the subject turns, issue 21's measure), and its spread over the poses."""
    out = run("summary", cylinder_run.parent / "cfg.yaml").output
    with h5py.File(cylinder_run / "reconstruction.h5") as f:
        truth = f["truth/power"][()]
        obs = f["per_pose/observed"][()].astype(bool)
        pp = f["per_pose/power"][()]
        reason = f["per_pose/headline_reason"][()]
    assert not any(reason), "this run's headline totals are over observed elements"
    ratio = np.array([np.nansum(pp[k][obs[k]]) / truth[obs[k]].sum() for k in range(len(obs))])
    spread = (ratio.max() - ratio.min()) / ratio.mean()
    assert ("fluxmap total over the truth on the elements it is over, per pose: "
            + " ".join(f"{r:.3f}" for r in ratio) + f" (spread {spread:.1%})") in out
