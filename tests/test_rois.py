"""Regions of interest (issue 24): membership, σ of a region's total, geodesic discs, and a
sphere ROI on the analytic Gaussian spot against its closed form."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp
import yaml

from fluxcli import config as C
from fluxcli.artefacts.reconstruction import read_rois
from fluxcli.errors import UserError
from fluxcli.imaging import noise as N
from fluxcli.inverse import reconstruct
from fluxcli.quantify import rois as Q
from fluxcli.surface.mesh import Surface
from fluxcli.surface.phantoms import sphere

from tiny_pipeline import tiny_run  # noqa: F401  (the session fixture)


# ------------------------------------------------------------------ σ of a region's total
def _chain(n=40, m=120, width=0.02):
    """A row of n elements seen by m pixels through a Gaussian blur (an element's light
    spreads over ~7 pixels), collection efficiency 1e-3."""
    x_el, x_px = (np.arange(n) + 0.5) / n, (np.arange(m) + 0.5) / m
    T = np.exp(-(x_px[:, None] - x_el[None, :]) ** 2 / (2 * width**2))
    T *= 1e-3 / T.sum(axis=0)
    return sp.csr_array(np.where(T > 1e-9 * T.max(), T, 0.0)), x_el


@pytest.mark.parametrize("method, kw", [("smooth", {"lam": 1e-2}), ("paper", {"lam": 1e-3}),
                                         ("weighted_lsq", {"lam": 1e-4})])
def test_sigma_of_roi_total_matches_scatter_over_100_noise_draws(method, kw):
    """√(wᵀCw) against the standard deviation of the region's total over 100 Poisson draws
    (ratio 1 ± 0.15); the sum of the per-element σ is far off (the elements of a region
    share pixels and are anti-correlated), so the test also fails on that shortcut."""
    T, x = _chain()
    n = len(x)
    truth = 1e8 * np.exp(-(x - 0.5) ** 2 / (2 * 0.1**2)) + 1e6
    a0 = T @ truth
    w = ((x > 0.35) & (x < 0.6)).astype(float)
    adj = sp.diags_array([np.ones(n - 1), np.ones(n - 1)], offsets=[-1, 1]).tocsr()
    extra = {"adjacency": adj, "areas": np.ones(n)} if method == "smooth" else {}
    rng = np.random.default_rng(7)
    noise = N.PhotonNoise("poisson")
    totals, sigmas, naive = [], [], []
    for _ in range(100):
        res = reconstruct(T, rng.poisson(a0).astype(float), method=method, variance=noise.variance, **kw, **extra)
        totals.append(np.nansum(w * res.power))
        sigmas.append(np.sqrt(res.covariance.variance_of(w)))
        naive.append(np.nansum(w * res.sigma))
    scatter = np.std(totals, ddof=1)
    assert np.mean(sigmas) / scatter == pytest.approx(1.0, abs=0.15)
    assert np.mean(naive) / scatter > 1.5  # why the covariance is needed


# ------------------------------------------------------------------ renumbering
def _renumbered(s: Surface, rng) -> tuple[Surface, np.ndarray]:
    """The same surface with its elements and faces in another order: (surface, old id of each new element)."""
    perm = rng.permutation(s.n_elements)  # new element k is old element perm[k]
    new_of_old = np.argsort(perm)
    order = rng.permutation(len(s.faces))
    eof = s.element_of_face[order]
    eof = np.where(eof >= 0, new_of_old[np.maximum(eof, 0)], -1)
    return Surface(s.vertices_mm, s.faces[order], eof, s.n_elements), perm


def test_rois_unchanged_when_the_elements_are_renumbered():
    s = sphere(radius_mm=10, n_latitude=12, n_longitude=24)[0]
    s2, perm = _renumbered(s, np.random.default_rng(3))
    ex = np.exp(-np.sum((s.element_centroids_mm - [0, 0, 10]) ** 2, axis=1) / 18.0)
    regions = [Q.Region("s", "sphere", center_mm=(0, 0, 10), radius_mm=5.0),
               Q.Region("b", "box", min_mm=(-3, -20, -20), max_mm=(20, 20, 5)),
               Q.Region("d", "disc", center_mm=(0, 0, 11), radius_mm=6.0),
               Q.Region("t", "threshold", fraction=0.3)]
    for r in regions:
        a = Q.members(r, s, exitance=ex)
        b = Q.members(r, s2, exitance=ex[perm])
        assert 0 < a.sum() < s.n_elements
        np.testing.assert_array_equal(b, a[perm])
        p = ex * s.element_areas_mm2
        na = Q.measure(a, p, np.ones(len(p), bool), np.ones(len(p), bool), s.element_areas_mm2, exposure_s=1.0)
        nb = Q.measure(b, p[perm], np.ones(len(p), bool), np.ones(len(p), bool), s2.element_areas_mm2, exposure_s=1.0)
        assert na.total_photons_per_s == pytest.approx(nb.total_photons_per_s, rel=1e-12)
        assert na.area_mm2 == pytest.approx(nb.area_mm2, rel=1e-12)


def test_threshold_roi_is_connected_to_the_peak():
    """Two bright blobs: only the one holding the peak is in the contour."""
    s = sphere(radius_mm=10, n_latitude=12, n_longitude=24)[0]
    c = s.element_centroids_mm
    ex = np.exp(-np.sum((c - [0, 0, 10]) ** 2, axis=1) / 8.0) + 0.9 * np.exp(-np.sum((c - [0, 0, -10]) ** 2, axis=1) / 8.0)
    m = Q.threshold_members(ex, s.element_adjacency(), 0.5)
    assert m.any() and np.all(c[m, 2] > 0)
    assert np.any((ex >= 0.5 * ex.max()) & (c[:, 2] < 0))  # the other blob is above the threshold too


# ------------------------------------------------------------------ geodesic distance
def test_geodesic_distance_on_a_sphere_against_the_great_circle():
    """On a sphere the geodesic from p is R·acos(u·p̂); the mesh is a polyhedron (chords), so
    allow 2 % of R on average and 5 % of the distance at worst beyond 1 mm; plain Dijkstra on
    the edges is also measured and must be worse (the reason for the triangle update)."""
    R = 10.0
    s = sphere(radius_mm=R, n_latitude=16, n_longitude=32)[0]
    fine, _ = s.refined(1)
    src = np.array([R * np.sin(0.3), 0.0, R * np.cos(0.3)])
    d = Q.geodesic_distance_mm(fine.vertices_mm, fine.faces, src)
    u = fine.vertices_mm / np.linalg.norm(fine.vertices_mm, axis=1, keepdims=True)
    exact = R * np.arccos(np.clip(u @ (src / R), -1, 1))
    far = exact > 1.0
    assert np.mean(np.abs(d - exact)) < 0.02 * R
    assert np.max(np.abs(d[far] - exact[far]) / exact[far]) < 0.05
    from scipy.sparse.csgraph import dijkstra

    f = fine.faces
    e = np.sort(f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    L = np.linalg.norm(fine.vertices_mm[e[:, 0]] - fine.vertices_mm[e[:, 1]], axis=1)
    G = sp.csr_matrix((L, (e[:, 0], e[:, 1])), shape=(len(u), len(u)))
    start = int(np.argmin(np.linalg.norm(fine.vertices_mm - src, axis=1)))
    dj = dijkstra(G, directed=False, indices=start) + np.linalg.norm(fine.vertices_mm[start] - src)
    assert np.mean(np.abs(dj - exact)) > 1.5 * np.mean(np.abs(d - exact))


def test_geodesic_disc_on_a_plane_is_the_euclidean_disc():
    n = 30
    g = np.linspace(-15, 15, n + 1)
    X, Y = np.meshgrid(g, g)
    v = np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], axis=1)
    idx = np.arange(X.size).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    s = Surface(v, faces, np.arange(len(faces)), len(faces))
    dist = Q.element_geodesic_mm(s, np.array([0.3, -0.2, 2.0]))
    exact = np.linalg.norm(s.element_centroids_mm[:, :2] - [0.3, -0.2], axis=1)
    assert np.max(np.abs(dist - exact)) < 0.05 * 30 / n + 0.02 * exact.max()


# ------------------------------------------------------------------ the Gaussian spot, closed form
def test_sphere_roi_on_the_gaussian_spot_holds_the_closed_form_fraction(tmp_path):
    """A Gaussian exitance exp(−d²/2w²) centred on the pole of a sphere of radius R, with d the
    chord distance: on a sphere the area at chord distance d is 2πd dd (Archimedes), so the
    part within chord d₀ holds (1 − e^{−d₀²/2w²}) / (1 − e^{−2R²/w²}) of the light.  A sphere
    ROI centred on the pole takes the latitude rows whose centroids it holds: rows down to
    polar angle θ₀, chord d₀ = 2R sin(θ₀/2).  Simulate (truth on a finer surface),
    reconstruct from two poses, and compare ROI total / true total with the closed form, 1 %."""
    from typer.testing import CliRunner

    from fluxcli.cli import app

    R, w, nlat = 10.0, 3.0, 16
    theta0 = 2 * np.pi / nlat * 1  # rows of pi/nlat: two rows around the pole (the first is the cap)
    d0 = 2 * R * np.sin(theta0 / 2)
    closed = (1 - np.exp(-d0**2 / (2 * w**2))) / (1 - np.exp(-2 * R**2 / w**2))
    cfg = {
        "workdir": str(tmp_path / "run"),
        "system": {"camera": {"pixels": [40, 40], "pixel_pitch_mm": 0.06,
                              "lens": {"focal_length_mm": 25.0, "f_number": 4.0, "focus_distance_mm": 300.0},
                              "pose": {"lens_center_mm": [0, 0, 310.0]}}, "mirrors": []},
        "subject": {"surface": {"phantom": "sphere", "radius_mm": R, "n_latitude": nlat, "n_longitude": 2 * nlat},
                    "poses": {"heights_mm": [0], "rotations_deg": [0, 20]}},
        "transfer": {"cache_dir": str(tmp_path / "cache")},
        "simulate": {"flux": {"kind": "gaussian", "center_mm": [0, 0, 2 * R], "width_mm": w, "peak_photons": 1e6},
                     "noise": {"model": "poisson", "peaks_photons": [1e9], "repeats": 1, "seed": 1, "exposure_s": 2.0}},
        # the subject at rest sits on the stage: the pole is at z = 2R; the radius falls between row centroids
        "rois": [{"name": "spot", "kind": "sphere", "center_mm": [0, 0, 2 * R], "radius_mm": float(d0 + 0.3)}],
    }
    p = tmp_path / "cfg.yaml"
    p.write_text(yaml.safe_dump(cfg))
    for stage in ("build-T", "simulate", "reconstruct"):
        r = CliRunner().invoke(app, [stage, str(p), "-q"])
        assert r.exit_code == 0, r.output
    import csv

    import h5py

    with h5py.File(tmp_path / "run" / "simulation.h5") as f:
        truth_total = float(f["truth/power"][()].sum() * f["truth/level_scale"][0])
    rows = list(csv.DictReader((tmp_path / "run" / "rois.csv").open()))
    assert [r_["pose"] for r_ in rows] == ["1", "2", "joint"]
    assert list(rows[0]) == list(Q.CSV_COLUMNS)
    for row in rows:
        frac = float(row["total_photons_per_s"]) * 2.0 / truth_total
        assert frac == pytest.approx(closed, rel=0.01), (row, closed)
        assert float(row["observed_share"]) == 1.0
        sigma = float(row["sigma_photons_per_s"])
        assert 0 < sigma < 0.01 * float(row["total_photons_per_s"])


# ------------------------------------------------------------------ through the stages
def _copy_run(tiny_run, tmp_path, rois):
    import shutil

    src, cfg, _ = tiny_run
    shutil.copytree(src / "run", tmp_path / "run")
    cfg = dict(cfg, workdir=str(tmp_path / "run"), rois=rois)
    p = tmp_path / "cfg.yaml"
    p.write_text(yaml.safe_dump(cfg))
    return p


def test_reconstruct_report_and_vtp_carry_the_rois(tiny_run, tmp_path):
    """reconstruct writes /rois and rois.csv (the contract's columns, a row per ROI per pose
    and 'joint'); report puts them in summary.json and the page; the VTP has a cell array
    per ROI; an unobserved region says so."""
    import csv
    import json

    import h5py
    import pyvista as pv
    from typer.testing import CliRunner

    from fluxcli.cli import app

    p = _copy_run(tiny_run, tmp_path, [
        {"name": "top", "kind": "box", "min_mm": [-20, -20, 12], "max_mm": [20, 20, 40]},
        {"name": "under", "kind": "box", "min_mm": [-20, -20, -5], "max_mm": [20, 20, 3]},
        {"name": "listed", "kind": "elements", "ids": [0, 1]},
        {"name": "tête μ", "kind": "elements", "ids": [2]}])  # the VTP holds ASCII names only (was exit 1)
    for stage in ("reconstruct", "report"):
        r = CliRunner().invoke(app, [stage, str(p)])
        assert r.exit_code == 0, r.output
    run = tmp_path / "run"
    rows = list(csv.DictReader((run / "rois.csv").open()))
    assert list(rows[0]) == list(Q.CSV_COLUMNS)
    assert [(x["roi"], x["pose"]) for x in rows] == [(n, k) for n in ("top", "under", "listed", "tête μ")
                                                      for k in ("1", "2", "joint")]
    with h5py.File(run / "reconstruction.h5") as f:
        got = read_rois(f["rois"])
        power, obs, areas = f["flux/power"][()], f["flux/observed"][()].astype(bool), f["surface/areas"][()]
    top = got["members"][0, -1]
    assert float(rows[2]["total_photons_per_s"]) == pytest.approx(np.nansum(np.where(top & obs, power, 0.0)), rel=1e-6)
    assert float(rows[2]["area_mm2"]) == pytest.approx(areas[top].sum(), rel=1e-6)
    assert 0 < float(rows[2]["sigma_photons_per_s"]) < float(rows[2]["total_photons_per_s"])
    assert got["status"][1, -1].startswith("mostly unobserved")  # the underside faces the stage
    assert "MOSTLY" not in r.output
    s = json.loads((run / "report" / "summary.json").read_text())
    assert s["rois"]["names"] == ["top", "under", "listed", "tête μ"]
    assert "Regions of interest" in (run / "report" / "index.html").read_text()
    m = pv.read(str(run / "reconstruction.vtp"))
    assert {"roi_top", "roi_under", "roi_listed", "roi_tete u03bc"} <= set(m.cell_data.keys())
    assert "roi_tete u03bc: 1 in region of interest 'tete u03bc', 0 outside" in " ".join(m.field_data["units"])


@pytest.mark.parametrize("roi, needle", [
    ({"name": "a", "kind": "sphere", "center_mm": [0, 0, 0]}, "radius_mm"),
    ({"name": "a", "kind": "box", "min_mm": [0, 0, 0], "max_mm": [1, -1, 1]}, "min_mm"),
    ({"name": "a", "kind": "cell_array", "array": "region", "value": 2}, "not a mesh file"),
    ({"name": "joint", "kind": "threshold", "fraction": 0.5}, "joint"),
    # the tiny cylinder's 24 elements are 0..23: 24 is one past the end, as an id counted from 1 is
    ({"name": "a", "kind": "elements", "ids": [3, 24]}, "element id(s) 24 are not on the subject's surface"),
])
def test_bad_rois_exit_2_naming_the_key(tiny_run, tmp_path, roi, needle):
    from typer.testing import CliRunner

    from fluxcli.cli import app

    p = _copy_run(tiny_run, tmp_path, [roi])
    r = CliRunner().invoke(app, ["reconstruct", str(p), "--force"])
    assert r.exit_code == 2, r.output
    text = " ".join(r.output.split())
    assert needle in text and "rois" in text


def test_cell_array_roi_reads_the_mesh_files_integer_array(tmp_path):
    """The cell array of a mesh file per element (elements from the file's 'element' array)."""
    import pyvista as pv

    from fluxcli.config import load_config
    from fluxcli.stages.plans import placer_of
    from fluxcli.stages.rois import cell_array_of_elements

    s = sphere(radius_mm=10, n_latitude=6, n_longitude=8)[0]
    faces = np.hstack([np.full((len(s.faces), 1), 3), s.faces]).ravel()
    mesh = pv.PolyData(s.vertices_mm, faces)
    mesh.cell_data["element"] = s.element_of_face.astype(np.int64)
    region = (s.element_centroids_mm[:, 2] > 5).astype(np.int64)[s.element_of_face]
    mesh.cell_data["region"] = region
    mesh.save(str(tmp_path / "m.vtk"))
    (tmp_path / "c.yaml").write_text(yaml.safe_dump({
        "system": {"camera": {"pixels": [8, 8], "pixel_pitch_mm": 0.1,
                              "lens": {"focal_length_mm": 25.0, "f_number": 4.0, "focus_distance_mm": 300.0},
                              "pose": {"lens_center_mm": [0, 0, 320.0]}}},
        "subject": {"surface": {"mesh": "m.vtk"}}}))
    cfg = load_config(tmp_path / "c.yaml")
    surf = placer_of(cfg).surface
    got = cell_array_of_elements(cfg.resolve(cfg.model.subject.surface.mesh), surf, "region", "rois[0]")
    upper = s.element_centroids_mm[:, 2] > 5  # per element of the file, by its ids
    ids = surf.element_ids if surf.element_ids is not None else np.arange(surf.n_elements)
    np.testing.assert_array_equal(got, upper[ids].astype(np.int64))
    r = Q.Region("upper", "cell_array", array="region", value=1)
    assert np.array_equal(Q.members(r, surf, cell_array=got), got == 1)
    # the same region stored as floating point (as MATLAB writes it) reads the same; a fraction
    # is refused naming the array and the face
    mesh.cell_data["region_f"] = region.astype(np.float64)
    mesh.cell_data["region_x"] = region + 0.5
    mesh.save(str(tmp_path / "m.vtk"))
    path = cfg.resolve(cfg.model.subject.surface.mesh)
    np.testing.assert_array_equal(cell_array_of_elements(path, surf, "region_f", "rois[0]"), got)
    # a value the array does not hold is a mistake, not an empty region
    from fluxcli.stages.rois import RoiMeter

    assert RoiMeter([C.Roi(name="upper", kind="cell_array", array="region", value=1)], path, surf, None).fixed["upper"].any()
    with pytest.raises(UserError, match=r"rois\[0\] \(upper\): no element of the surface has region = 2; the cell "
                                        r"array holds 0, 1\."):
        RoiMeter([C.Roi(name="upper", kind="cell_array", array="region", value=2)], path, surf, None)
    with pytest.raises(UserError, match=r"rois\[0\]: the cell array 'region_x' of .*m.vtk must hold whole-number "
                                        r"region values; face 0 has [01].5 .(80|[0-9]+) face.s. like it.\."):
        cell_array_of_elements(path, surf, "region_x", "rois[0]")


# ------------------------------------------------------------------ fluxmap study
def test_study_table_flags_another_calibration_and_refuses_a_changed_artefact(tiny_run, tmp_path):
    """Two sessions of the tiny run (days 1 and 2) make the table; a third reconstructed with
    another focal length is flagged naming the key; a copy whose numbers were edited is
    refused (exit 2) naming the file; one whose input simulation changed is refused too."""
    import csv
    import shutil

    import h5py
    from typer.testing import CliRunner

    from fluxcli.cli import app

    roi = [{"name": "top", "kind": "box", "min_mm": [-20, -20, 12], "max_mm": [20, 20, 40]}]
    p = _copy_run(tiny_run, tmp_path, roi)
    assert CliRunner().invoke(app, ["reconstruct", str(p), "-q"]).exit_code == 0
    run = tmp_path / "run"
    shutil.copytree(run, tmp_path / "day2")
    cfg = yaml.safe_load(p.read_text())
    cfg["system"]["camera"]["lens"]["focal_length_mm"] = 24.0
    cfg["workdir"] = str(tmp_path / "recal")
    p2 = tmp_path / "recal.yaml"
    p2.write_text(yaml.safe_dump(cfg))
    for stage in ("build-T", "simulate", "reconstruct"):
        r = CliRunner().invoke(app, [stage, str(p2), "-q"])
        assert r.exit_code == 0, r.output
    sessions = [{"artefact": "run/reconstruction.h5", "subject": "a", "day": 1},
                {"artefact": "day2/reconstruction.h5", "subject": "a", "day": 2},
                {"artefact": "recal/reconstruction.h5", "subject": "a", "day": 3}]
    s = tmp_path / "study.yaml"
    s.write_text(yaml.safe_dump({"output": "out", "sessions": sessions}))
    r = CliRunner().invoke(app, ["study", str(s)])
    assert r.exit_code == 0, r.output
    text = " ".join(r.output.split())
    assert "focal_length_mm: 24 in reconstruction.h5, 25 in the first session" in text
    rows = list(csv.DictReader((tmp_path / "out" / "study.csv").open()))
    assert len(rows) == 3 * 1 * 3  # sessions x ROIs x (2 poses + joint)
    assert rows[2]["pose"] == "joint" and rows[0]["setup_flag"] == "" and "focal_length_mm" in rows[-1]["setup_flag"]
    assert float(rows[2]["total_photons_per_s"]) == float(rows[5]["total_photons_per_s"])  # the same artefact twice
    assert "plotly" in (tmp_path / "out" / "index.html").read_text()[:2_000_000]

    with h5py.File(tmp_path / "day2" / "reconstruction.h5", "r+") as f:
        f["flux/power"][0] *= 1.01
    r = CliRunner().invoke(app, ["study", str(s)])
    assert r.exit_code == 2 and "day2/reconstruction.h5 was changed after it was written" in " ".join(r.output.split())

    shutil.rmtree(tmp_path / "day2")
    shutil.copytree(run, tmp_path / "day2")
    with h5py.File(tmp_path / "day2" / "simulation.h5", "r+") as f:
        f.attrs["note"] = "edited"
    r = CliRunner().invoke(app, ["study", str(s)])
    assert r.exit_code == 2 and "day2/simulation.h5 (simulation.h5) changed after" in " ".join(r.output.split())

    # the numbers' attributes are sealed too: the exposure that makes photons/s, a region's names
    # (digest version 2; version 1 hashed the datasets alone and let these through)
    for edit in (lambda f: f["rois"].attrs.__setitem__("exposure_s", 2.0),  # per exposure (NaN) made per 2 s
                 lambda f: f["rois"].attrs.__setitem__("names", '["bottom"]'),
                 lambda f: f.attrs.__setitem__("rate_exposure_s", 2.0)):
        shutil.rmtree(tmp_path / "day2")
        shutil.copytree(run, tmp_path / "day2")
        with h5py.File(tmp_path / "day2" / "reconstruction.h5", "r+") as f:
            edit(f)
        r = CliRunner().invoke(app, ["study", str(s)])
        assert r.exit_code == 2 and "day2/reconstruction.h5 was changed after it was written" in " ".join(r.output.split())

    # a file sealed by version 1 (no version attribute) is still read, by version 1's rule
    from fluxcli.artefacts.digest import results_sha256

    shutil.rmtree(tmp_path / "day2")
    shutil.copytree(run, tmp_path / "day2")
    with h5py.File(tmp_path / "day2" / "reconstruction.h5", "r+") as f:
        assert int(f.attrs["results_sha256_version"]) == 2
        del f.attrs["results_sha256_version"]
        f.attrs["results_sha256"] = results_sha256(f, __import__("json").loads(f.attrs["results_sha256_groups"]), 1)
    assert CliRunner().invoke(app, ["study", str(s), "-q"]).exit_code == 0

    # sealed as it is but missing what reconstruct writes (another tool's file): exit 2, naming it
    with h5py.File(tmp_path / "day2" / "reconstruction.h5", "r+") as f:
        del f["per_pose/direct_roi_photons"]
        f.attrs["results_sha256"] = results_sha256(f, __import__("json").loads(f.attrs["results_sha256_groups"]), 1)
    r = CliRunner().invoke(app, ["study", str(s)])
    text = " ".join(r.output.split())
    assert r.exit_code == 2 and "day2/reconstruction.h5 is incomplete: it has no dataset 'per_pose/direct_roi_photons'" in text


def test_study_file_mistakes_exit_2(tmp_path):
    from typer.testing import CliRunner

    from fluxcli.cli import app

    s = tmp_path / "s.yaml"
    s.write_text(yaml.safe_dump({"sessions": [{"artefact": "nowhere.h5", "subject": "a"}]}))
    r = CliRunner().invoke(app, ["study", str(s)])
    assert r.exit_code == 2 and "day or a date" in " ".join(r.output.split())
    s.write_text(yaml.safe_dump({"sessions": [{"artefact": "nowhere.h5", "subject": "a", "day": 1}]}))
    r = CliRunner().invoke(app, ["study", str(s)])
    assert r.exit_code == 2 and "sessions[0] (a day 1 -): artefact" in " ".join(r.output.split())
    assert "nowhere.h5" in " ".join(r.output.split())
    s.write_text(yaml.safe_dump({"sessions": [{"artefact": "m1\x00.h5", "subject": "a", "day": 1}]}))
    r = CliRunner().invoke(app, ["study", str(s)])  # was exit 1: "embedded null byte" from the OS
    assert r.exit_code == 2 and "'sessions.0.artefact': holds a NUL character" in " ".join(r.output.split()), r.output
    s.write_text(yaml.safe_dump({"output": "", "sessions": [{"artefact": "m1.h5", "subject": "a", "day": 1}]}))
    r = CliRunner().invoke(app, ["study", str(s)])  # was: the table and page written beside the study file
    assert r.exit_code == 2 and "'output': is an empty path" in " ".join(r.output.split()), r.output
    r = CliRunner().invoke(app, ["study", str(tmp_path)])  # was: "study file ... does not exist"
    assert r.exit_code == 2 and "is a folder; give the study's YAML file itself" in " ".join(r.output.split()), r.output


def test_study_dates_are_iso_and_a_subject_keeps_one_time_axis(tmp_path):
    """A date as YAML writes it unquoted (a date, or a date and time for a kinetic series) is
    taken and written as ISO; a date that is not one, or a subject with one session by day
    and another by date (the page's plot once stopped on it, exit 1), exits 2 naming it."""
    from typer.testing import CliRunner

    from fluxcli.cli import app

    s = tmp_path / "s.yaml"

    def study(sessions: str) -> str:
        s.write_text("sessions:\n" + sessions)
        r = CliRunner().invoke(app, ["study", str(s)])
        assert r.exit_code == 2, r.output
        return " ".join(r.output.split())

    # read as dates (it fails later, on the missing artefact, naming the session by its ISO date)
    assert "sessions[0] (a 2026-11-20 -): artefact" in study("- {artefact: x.h5, subject: a, date: 2026-11-20}")
    assert "sessions[0] (a 2026-11-20 10:30:00 -)" in study("- {artefact: x.h5, subject: a, date: 2026-11-20 10:30:00}")
    assert "sessions[0] (a 2026-11-20 10:30:00 -)" in study("- {artefact: x.h5, subject: a, date: '2026-11-20T10:30'}")
    # a date YAML's pattern takes but the calendar does not: a YAML error at its line (was exit 1 in
    # every YAML file fluxmap reads, configs too)
    assert "is not valid YAML: '2026-13-01' is not a date (month must be in 1..12) at line 2" in study(
        "- {artefact: x.h5, subject: a, date: 2026-13-01}")
    for bad in ("tuesday", "'2026-13-01'", "[1]", "5"):
        text = study(f"- {{artefact: x.h5, subject: a, date: {bad}}}")
        assert text.startswith(f"fluxmap: error: study file {s}: 'sessions.0.date': ") and "is not an ISO date" in text
        assert "too short" not in text and "at least 1 item" not in text  # not the tuple's echo of its item
    text = study("- {artefact: x.h5, subject: a, day: 3}\n- {artefact: x.h5, subject: b, date: 2026-11-20}\n"
                 "- {artefact: x.h5, subject: a, date: 2026-11-21}")
    assert ("subject 'a': sessions[0] (a day 3 -) gives a day and sessions[2] (a 2026-11-21 -) only a date" in text)


# ------------------------------------------------------------------ several filters in one reconstruct
def test_filters_reconstructed_one_by_one_in_one_run(tmp_path, monkeypatch):
    """A capture of the simulated rig through 'open' and '580nm' (transmission 0.5): one
    reconstruct with filters [open, 580nm] and the transmission given recovers, per filter,
    the light before the filter (the truth the simulated camera recorded, / transmission);
    one T per pose serves both; rois_spectrum.csv holds each ROI per filter."""
    import csv

    import h5py
    from typer.testing import CliRunner

    from fluxcli.cli import app
    from test_capture import rig_config

    minimal = yaml.safe_load((Path(__file__).parents[1] / "configs" / "minimal.yaml").read_text())
    minimal["workdir"] = "run"
    cfg = rig_config(minimal, tmp_path / "Tcache", repeats=2, exposure_s=[0.5, 1.0])
    cfg["rois"] = [{"name": "all", "kind": "box", "min_mm": [-100, -100, -100], "max_mm": [100, 100, 100]}]
    cfg["subject"]["emission"] = {"model": "diffuse", "refractive_index": 1.4}  # edge-on elements: left out of every filter
    p = tmp_path / "cfg.yaml"
    p.write_text(yaml.safe_dump(cfg))
    r = CliRunner().invoke(app, ["capture-surface", str(p), "-q"])
    assert r.exit_code == 0, r.output
    cfg["reconstruct"] = {"images": {"capture": "capture.h5", "filters": ["open", "580nm"],
                                     "transmissions": {"580nm": 0.5}, "exposure_s": 1.0,
                                     "exposures_s": {"580nm": 0.5}}}  # each filter its own exposure
    p.write_text(yaml.safe_dump(cfg))
    r = CliRunner().invoke(app, ["reconstruct", str(p)])
    assert r.exit_code == 0, r.output
    run = tmp_path / "run"
    with h5py.File(run / "capture.h5") as f:
        truth = {k: f[f"truth/{k}/power"][()] for k in ("open", "580nm")}  # photons/s through each filter
    with h5py.File(run / "reconstruction.h5") as f:
        assert [*__import__("json").loads(f["filters"].attrs["order"])] == ["open", "580nm"]
        obs = f["filters/580nm/flux/observed"][()].astype(bool)
        got = {k: float(np.nansum(f[f"filters/{k}/flux/power"][()])) / t  # photons per exposure -> per s
               for k, t in (("open", 1.0), ("580nm", 0.5))}
        np.testing.assert_array_equal(f["filters/open/flux/power"][()], f["flux/power"][()])
    # per second; the 580nm light before its filter is truth / 0.5
    assert got["open"] == pytest.approx(truth["open"][obs].sum(), rel=0.05)
    assert got["580nm"] == pytest.approx(truth["580nm"][obs].sum() / 0.5, rel=0.05)
    rows = list(csv.DictReader((run / "rois_spectrum.csv").open()))
    assert [(x["filter"], x["pose"]) for x in rows] == [("open", "1"), ("580nm", "1"), ("open", "2"), ("580nm", "2"),
                                                         ("open", "joint"), ("580nm", "joint")]
    assert float(rows[-1]["total_photons_per_s"]) == pytest.approx(got["580nm"], rel=1e-6)
    r = CliRunner().invoke(app, ["summary", str(p)])  # each filter's total, at its own frames' exposure
    text = " ".join(r.output.split())
    assert r.exit_code == 0 and f"filter 580nm: {got['580nm']:.4g} photons/s over observed elements, before the filter " \
        "(transmission 0.5; its frames 0.5 s)" in text and f"filter open: {got['open']:.4g} photons/s" in text, r.output
    r = CliRunner().invoke(app, ["report", str(p)])
    assert r.exit_code == 0, r.output
    s = __import__("json").loads((run / "report" / "summary.json").read_text())
    assert s["rois_spectrum"]["filters"] == ["open", "580nm"] and "rois_spectrum.png" in s["figures"]
    assert [x["name"] for x in s["filters"]] == ["open", "580nm"]  # the report's Filters section
    assert [x["total_photons_per_s"] for x in s["filters"]] == pytest.approx([got["open"], got["580nm"]], rel=1e-9)
    import pyvista as pv

    assert {"filter_open_power_photons", "filter_580nm_power_photons"} <= set(pv.read(str(run / "reconstruction.vtp")).cell_data.keys())
    # a study of it: a row per filter (session x ROI x filter), the filter named by the artefact
    (tmp_path / "study.yaml").write_text(yaml.safe_dump({"output": "out", "sessions": [
        {"artefact": "run/reconstruction.h5", "subject": "a", "day": 1}]}))
    r = CliRunner().invoke(app, ["study", str(tmp_path / "study.yaml"), "-q"])
    assert r.exit_code == 0, r.output
    rows = list(csv.DictReader((tmp_path / "out" / "study.csv").open()))
    joint = {x["filter"]: float(x["total_photons_per_s"]) for x in rows if x["pose"] == "joint"}
    assert joint["580nm"] == pytest.approx(got["580nm"], rel=1e-6) and joint["open"] == pytest.approx(got["open"], rel=1e-6)
    direct = {x["filter"]: float(x["direct_image_photons_per_s"]) for x in rows if x["pose"] == "1"}
    assert direct["580nm"] == pytest.approx(0.5 * direct["open"], rel=0.1)  # the image through a 0.5 filter
    # one artefact in two sessions (a line copied, its day changed and its artefact not): refused, naming both
    (tmp_path / "twice.yaml").write_text(yaml.safe_dump({"output": "out2", "sessions": [
        {"artefact": "run/reconstruction.h5", "subject": "a", "day": d} for d in (1, 5)]}))
    r = CliRunner().invoke(app, ["study", str(tmp_path / "twice.yaml"), "-q"])
    assert r.exit_code == 2 and "sessions[0] (a day 1 -) and sessions[1] (a day 5 -) both read" in " ".join(r.output.split())
    # a session that names one of the artefact's filters takes that one; one it does not hold is refused
    # (its filter was ignored: the rows came out named open and 580nm under a study that said GFP)
    for filt, code in (("580nm", 0), ("GFP", 2)):
        (tmp_path / "one.yaml").write_text(yaml.safe_dump({"output": "out1", "sessions": [
            {"artefact": "run/reconstruction.h5", "subject": "a", "day": 1, "filter": filt}]}))
        r = CliRunner().invoke(app, ["study", str(tmp_path / "one.yaml"), "-q"])
        assert r.exit_code == code, r.output
    assert "filter 'GFP' is not among the filters" in " ".join(r.output.split())
    assert {x["filter"] for x in csv.DictReader((tmp_path / "out1" / "study.csv").open())} == {"580nm"}
    # a filter's numbers edited after the fact are refused like the first filter's (/filters was
    # outside the digest: an edit there went into the study unseen)
    import h5py

    with h5py.File(run / "reconstruction.h5", "r+") as f:
        f["filters/580nm/rois/total_photons_per_s"][-1, -1] *= 1.1
    r = CliRunner().invoke(app, ["study", str(tmp_path / "study.yaml"), "-q"])
    assert r.exit_code == 2 and "was changed after it was written" in " ".join(r.output.split()), r.output

    # The filters the other way round, the first with an exposure of its own: the same two solves
    # (a filter's solve does not depend on the others), /flux now the 580nm one at its 0.5 s. The
    # run used to write the artefact and then stop (exit 2) on "the config states an exposure of
    # 1 s ... reconstructed with 0.5 s", reading exposure_s where the first filter has its own.
    swapped = copy.deepcopy(cfg)
    swapped["reconstruct"]["images"]["filters"] = ["580nm", "open"]
    q = tmp_path / "swapped.yaml"
    q.write_text(yaml.safe_dump(swapped))
    r = CliRunner().invoke(app, ["reconstruct", str(q), "--force"])
    assert r.exit_code == 0, r.output
    with h5py.File(run / "reconstruction.h5") as f:
        assert [*__import__("json").loads(f["filters"].attrs["order"])] == ["580nm", "open"]
        np.testing.assert_array_equal(f["filters/580nm/flux/power"][()], f["flux/power"][()])
        for k, t in (("open", 1.0), ("580nm", 0.5)):
            assert float(np.nansum(f[f"filters/{k}/flux/power"][()])) / t == pytest.approx(got[k], rel=1e-9)
    r = CliRunner().invoke(app, ["report", str(q)])
    assert r.exit_code == 0, r.output

    # A reflection in the 580nm frames only: light where no element of the subject can send any.
    # That filter's solve leaves it out, and it must say so, by filter and pose (the warnings of
    # every filter after the first once stayed inside its solve: exit 0, /warnings silent).
    def warnings_of(path):  # /warnings as written (the seal was broken above on purpose)
        with h5py.File(path) as f:
            return [w.decode() if isinstance(w, bytes) else str(w) for w in f["warnings"][()]]

    def stray(w):
        return "falls on pixels that no element of the subject can reach" in w

    assert not [w for w in warnings_of(run / "reconstruction.h5") if stray(w)]
    with h5py.File(run / "capture.h5", "r+") as f:
        light = ~f["plan/dark"][()].astype(bool) & (np.char.decode(f["plan/filter"][()]) == "580nm")
        for k in np.flatnonzero(light):
            frame = f["frames/counts"][k]
            frame[:2, :2] += (0.5 * (frame.max() - np.median(frame))).astype(frame.dtype)
            f["frames/counts"][k] = frame
    r = CliRunner().invoke(app, ["reconstruct", str(p), "--force"])
    assert r.exit_code == 0, r.output
    moved = warnings_of(run / "reconstruction.h5")
    for label in ("pose h=+0mm", "pose h=+1mm"):
        assert any(w.startswith(f"filter 580nm, {label}") and stray(w) for w in moved), (label, moved)
    assert not [w for w in moved if w.startswith("filter open") and stray(w)], moved
    assert "filter 580nm, pose" in " ".join(r.output.split())  # and on the console
    # Elements seen only beyond the profile's trusted angle leave every filter's observed total,
    # not the first filter's alone (the others' totals held them, so a ratio of two filters'
    # totals mixed two sets of elements). The angle is lowered here so that this small scene,
    # seen from above, has such elements (its rim is seen at up to 80 deg).
    import fluxcli.optics.emission as E

    monkeypatch.setattr(E, "DIFFUSE_TRUSTED_TO_DEG", 60.0)
    r = CliRunner().invoke(app, ["reconstruct", str(p), "--force"])
    assert r.exit_code == 0, r.output
    edge = [w for w in warnings_of(run / "reconstruction.h5") if "seen only beyond 60 deg" in w]
    assert {w.split(",")[0] for w in edge} == {"filter open", "filter 580nm"}, edge
    with h5py.File(run / "reconstruction.h5") as f:
        np.testing.assert_array_equal(f["filters/580nm/flux/observed"][()], f["flux/observed"][()])
        np.testing.assert_array_equal(np.isnan(f["filters/580nm/flux/power"][()]), np.isnan(f["flux/power"][()]))

    # Every 580nm frame at full scale: no pixel that sees the subject is usable. Refused, naming the
    # pose and the filter (it stopped with the solver's "T must be non-empty and 2-D, got shape (0, 112)").
    with h5py.File(run / "capture.h5", "r+") as f:
        for k in np.flatnonzero(light):
            f["frames/counts"][k] = np.full_like(f["frames/counts"][k], np.iinfo(f["frames/counts"].dtype).max)
    r = CliRunner().invoke(app, ["reconstruct", str(p), "--force"])
    text = " ".join(r.output.split())
    assert r.exit_code == 2 and "pose h=+0mm rot=0deg (filter 580nm): none of the" in text, r.output
