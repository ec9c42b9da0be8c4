"""report: the page, summary.json, the figures, the 3-D fallback, and a science regression check.

A tiny pipeline (cylinder phantom of 16 x 6 elements, 40 x 40 px camera, two stage
heights, Gaussian flux, seeded Poisson noise, a two-method sweep) runs once per module;
its reconstruction is judged against the simulation's truth with fixed bars, on the
elements whose column sum is at least 5 % of the largest (a set fixed by T, not by the
reconstruction).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml
from conftest import cylinder_sim_config

from fluxcli import report as R
from fluxcli.config import load_config
from fluxcli.errors import UserError
from fluxcli.report import figures as F
from fluxcli.stages import reconstruct, report, simulate
from fluxcli.stages.build_t import cache_dir
from fluxcli.stages.context import RunContext

ROOT = Path(__file__).resolve().parents[1]
QUIET = RunContext(quiet=True)


def small_config(minimal: dict) -> dict:
    """test_simulate's cylinder, reconstructed by the default method (judged against the
    truth below), with a two-method sweep."""
    cfg = cylinder_sim_config(minimal, peaks_photons=(1e7, 1e5))
    wlsq = {"method": "weighted_lsq", "lambda": "auto", "lambda_rule": "discrepancy"}
    cfg["reconstruct"] = {"sweep": {"methods": [{"method": "backprojection"}, wlsq]}}  # the default method
    return cfg


def _minimal() -> dict:
    # as conftest's minimal_config, which is function-scoped; the pipeline here runs once per module
    cfg = yaml.safe_load((ROOT / "configs" / "minimal.yaml").read_text())
    cfg["workdir"] = "run"
    return cfg


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    """The pipeline up to the report; returns (config, index.html)."""
    tmp = tmp_path_factory.mktemp("report")
    path = tmp / "cfg.yaml"
    path.write_text(yaml.safe_dump(small_config(_minimal())))
    cfg = load_config(path)
    simulate.run(cfg, QUIET)
    reconstruct.run(cfg, QUIET)
    index = report.run(cfg, QUIET)
    return cfg, index


def _summary(index: Path) -> dict:
    return json.loads((index.parent / "summary.json").read_text())


# ------------------------------------------------------------------ the page and the numbers
def test_page_is_self_contained_and_shows_every_figure(small_run):
    cfg, index = small_run
    assert index == cfg.workdir / "report" / "index.html" and index.is_file()
    text = index.read_text()
    s = _summary(index)
    figures = s["figures"]
    for name in ("fit_pose1.png", "fit_pose2.png", "surface_camera.png", "surface_common.png", "slice.png",
                 "totals.png", "sweep_error.png", "sensitivity.png"):
        assert name in figures
    for name in figures:
        png = index.parent / name
        assert png.is_file() and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # nothing is fetched from anywhere: the only scripts are inline (plotly.js and the 3-D view's data),
    # every src outside them is a data URI, every link an anchor on the page
    assert re.findall(r"<script[^>]*>", text) and all(" src=" not in t for t in re.findall(r"<script[^>]*>", text))
    page = re.sub(r"<script[^>]*>.*?</script>", "", text, flags=re.S)
    assert page.count('src="data:image/png;base64,') == len(figures)
    assert all(v.startswith("data:image/png;base64,") for v in re.findall(r'src="([^"]*)"', page))
    assert all(v.startswith("#") for v in re.findall(r'href="([^"]*)"', page))
    assert "<script" not in page and "url(" not in page
    assert s["renderer"] in ("pyvista", "matplotlib")
    # the tables say what the paper's Table 1 and Fig. 18 say
    assert "Maximum SNR" in text and "spread" in text


def test_summary_numbers_are_the_artefacts_numbers(small_run):
    cfg, index = small_run
    s = _summary(index)
    with h5py.File(cfg.workdir / "reconstruction.h5") as f:
        totals = f["per_pose/total"][()]
        roi = f["per_pose/direct_roi_photons"][()]
        bp = f["per_pose/backprojection_total"][()]
        err = f["truth/error_per_pose"][()]
        ratio = f["truth/total_ratio_per_pose"][()]
        joint_error = f["truth"].attrs["error"]
        truth_total = f["truth/power"][()].sum()
        sweep_mean = f["sweep/mean"][()]
        power = f["flux/power"][()]
        observed = f["flux/observed"][()]
    with h5py.File(cfg.workdir / "simulation.h5") as f:
        snr = f["images/max_snr"][()]
    assert [p["total_photons"] for p in s["poses"]] == pytest.approx(totals, rel=1e-12)
    assert [p["direct_roi_photons"] for p in s["poses"]] == pytest.approx(roi, rel=1e-12)
    assert [p["error"] for p in s["poses"]] == pytest.approx(err, rel=1e-12)
    assert [p["total_ratio"] for p in s["poses"]] == pytest.approx(ratio, rel=1e-12)
    assert s["error"] == pytest.approx(joint_error, rel=1e-12)
    assert s["truth_total_photons"] == pytest.approx(truth_total, rel=1e-12)
    for name, v in (("reconstruction", totals), ("direct_roi", roi), ("backprojection", bp)):
        assert s["spreads"][name] == pytest.approx((v.max() - v.min()) / v.mean(), rel=1e-9)
        assert s["totals_normalised_by_mean"][name] == pytest.approx(v / v.mean(), rel=1e-9)
    assert np.array(s["snr_table"]["max_snr"]) == pytest.approx(snr, rel=1e-6)
    assert np.array(s["sweep"]["mean_error"], float) == pytest.approx(sweep_mean, rel=1e-12, nan_ok=True)
    assert s["flux_total_photons"] == pytest.approx(np.nansum(power), rel=1e-12)
    # the slice: unobserved elements are null (drawn as gaps), never zero
    sl = s["slice"]
    assert len(sl["angle_deg"]) == len(sl["exitance_joint"]) and sl["angle_deg"] == sorted(sl["angle_deg"])
    assert not observed.all()
    hidden = [i for i, e in enumerate(sl["elements"]) if not observed[e]]
    assert hidden, "the slice should cross the unobserved underside"
    assert None in sl["exitance_joint"]
    assert all(v is None or v >= 0 for v in sl["exitance_joint"])


def test_report_is_kept_when_up_to_date_and_redrawn_with_force(small_run):
    cfg, index = small_run
    before = index.stat().st_mtime_ns
    assert report.run(cfg, QUIET) == index
    assert index.stat().st_mtime_ns == before
    assert report.run(cfg, RunContext(quiet=True, force=True)) == index
    assert index.stat().st_mtime_ns != before


def test_missing_reconstruction_names_the_command(write_config, minimal_config):
    cfg = load_config(write_config(minimal_config))
    with pytest.raises(UserError, match="fluxmap reconstruct"):
        report.run(cfg, QUIET)


# ------------------------------------------------------------------ 3-D views: pyvista and its fallback
def _study(cfg):
    return R.load(cfg.workdir / "reconstruction.h5", t_cache_dir=cache_dir(cfg))


def _geometry(cfg):
    from fluxcli.stages.plans import placer_of

    placer = placer_of(cfg)
    return R.Geometry(tuple(placer.axis_point), tuple(placer.axis))


def test_matplotlib_fallback_draws_the_surface_when_pyvista_fails(small_run, tmp_path, monkeypatch):
    cfg, _ = small_run

    class NoOpenGL:
        def __init__(self, *a, **k):
            raise RuntimeError("no OpenGL context")

    monkeypatch.setattr(F, "_PyvistaRenderer", NoOpenGL)
    index, s = R.make_report(_study(cfg), tmp_path / "fallback", title="t", geometry=_geometry(cfg))
    assert s["renderer"] == "matplotlib"
    assert any("matplotlib" in n for n in s["notes"])
    assert "surface_common.png" in s["figures"] and (tmp_path / "fallback" / "surface_common.png").is_file()
    with pytest.raises(F.RenderError):
        F.render_panels(F.surface_panels(_study(cfg), _geometry(cfg), None, ["a", "b"])[0],
                        F.Normalize(0, 1), F.colormaps["viridis"], renderer="pyvista")


def test_both_renderers_put_the_surface_in_the_same_place(small_run):
    """Top view of the subject at rest: pyvista and the matplotlib fallback agree on its
    outline (same projection, scale and orientation) and on its colours."""
    cfg, _ = small_run
    st = _study(cfg)
    cam, _ = F.surface_panels(st, _geometry(cfg), st.truth_exitance, ["1", "2"])
    norm = F.Normalize(0, np.nanmax(st.pose_exitance))
    cmap = F.colormaps["viridis"]
    mpl, used = F.render_panels(cam[:1], norm, cmap, renderer="matplotlib")
    assert used == "matplotlib"
    try:
        pv, used = F.render_panels(cam[:1], norm, cmap, renderer="pyvista")
    except F.RenderError as e:
        pytest.skip(f"no off-screen OpenGL here: {e}")
    a, b = mpl[0].astype(float), pv[0].astype(float)
    assert a.shape == b.shape
    fa, fb = a.min(axis=2) < 240, b.min(axis=2) < 240  # not background
    assert (fa & fb).sum() / (fa | fb).sum() > 0.9
    both = fa & fb
    assert np.median(np.abs(a[both] - b[both])) < 12  # colours agree (edges aside)


# ------------------------------------------------------------------ a line detector (the 2-D study)
def test_line_detector_plots_curves_and_flux_around_the_ring(write_config, tmp_path):
    cfg = {"workdir": "run",
           "system": {"camera": {"pixels": [128, 1], "pixel_pitch_mm": 0.104,
                                 "lens": {"focal_length_mm": 23.9, "f_number": 1.4, "focus_distance_mm": 317.0},
                                 "pose": {"lens_center_mm": [0, 0, 338.0]}}, "mirrors": []},
           "subject": {"surface": {"phantom": "ring", "radius_mm": 25, "thickness_mm": 1, "n_elements": 48},
                       "poses": {"heights_mm": [-40, 0]}},
           "simulate": {"flux": {"kind": "gaussian", "width_mm": 8.0, "peak_photons": 1e7},
                        "noise": {"model": "gaussian", "repeats": 1, "seed": 1}},
           "reconstruct": {"method": "paper", "lambda": 10}}
    c = load_config(write_config(cfg))
    simulate.run(c, QUIET)
    reconstruct.run(c, QUIET)
    index = report.run(c, QUIET)
    s = _summary(index)
    assert "flux_ring.png" in s["figures"] and "fit_pose2.png" in s["figures"]
    assert not any(n.startswith("surface_") for n in s["figures"])
    assert len(s["slice"]["elements"]) == 48  # the whole ring
    assert "snr_table" in s and "sweep" not in s


# ------------------------------------------------------------------ science against the truth
def _judged_set(index: Path):
    """Per pose: (power, truth, set) with the set fixed by the truth's T alone: elements whose
    column sum is at least 5 % of the largest (not the reconstruction's own σ or classes)."""
    from fluxcli.artefacts.transfer import load_T

    rec = index.parent.parent / "reconstruction.h5"
    with h5py.File(rec) as f:
        truth = f["truth/power"][()]
        power = f["per_pose/power"][()]
        T_files = json.loads(f["geometry"].attrs["T_files"])
    out = []
    for k, name in enumerate(T_files):
        sums = np.asarray(load_T(rec.parent / name).sum(axis=0)).ravel()
        out.append((power[k], truth, sums >= 0.05 * sums.max()))
    return out


def test_science_against_the_simulated_truth(small_run):
    """Fixed bars against the simulation's truth (issue 25: this test used to compare the
    summary with a file it could rewrite itself, with bars of stored value x 1.2 + slack).

    Per pose, over the elements whose column sum is >= 5 % of the largest (a set fixed by T):
    the share of the true light outside that set is bounded, and the L1 error, the total ratio
    and the agreement of the two poses meet fixed bars (peak 1e7 photons: the noise alone is
    far below them; what is left is the model error of a 40 x 40 camera on 96 elements). The figures the old file pinned as "expected" (11 % error, total 0.91)
    are over all elements, unobserved ones counted as zero."""
    _, index = small_run
    figures = []
    for power, truth, judged in _judged_set(index):
        assert np.all(np.isfinite(power[judged]))
        left_out = truth[~judged].sum() / truth.sum()
        err = np.abs(power[judged] - truth[judged]).sum() / truth[judged].sum()
        ratio = power[judged].sum() / truth[judged].sum()
        figures.append((left_out, err, ratio))
    for left_out, err, ratio in figures:
        assert left_out < BAR_LEFT_OUT, figures
        assert err < BAR_ERROR, figures
        assert abs(ratio - 1) < BAR_TOTAL, figures
    totals = [r for _, _, r in figures]
    assert max(totals) - min(totals) < BAR_SPREAD, figures
    s = _summary(index)
    sw = s["sweep"]  # backprojection is wrong in scale by orders of magnitude: its error is ~1
    assert all(e > 0.99 for e in np.ravel(sw["mean_error"][0])), sw["mean_error"][0]


# Measured (default smooth on vertices): light left out 1.1 %, errors 12.8 % / 5.4 %, totals 1.017 / 0.979.
# The clipped iterated solve this replaced gave 81 % and a total of 1.355 on the first pose.
BAR_LEFT_OUT, BAR_ERROR, BAR_TOTAL, BAR_SPREAD = 0.02, 0.15, 0.03, 0.05
