"""reconstruct: from simulated or exported images back to the flux per element."""

from __future__ import annotations

import copy
from pathlib import Path

import h5py
import numpy as np
import pytest
from typer.testing import CliRunner

from fluxcli.artefacts.reconstruction import read_warnings
from fluxcli.cli import app
from fluxcli.imaging.imagefiles import read_image, write_image

ROOT = Path(__file__).resolve().parents[1]
runner = CliRunner()


def run(*args):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture
def patch_config(minimal_config):
    """A flat 6 x 4-element patch facing the camera, a little out of focus: every element
    is seen, and a Gaussian patch of flux lies on it."""
    cfg = copy.deepcopy(minimal_config)
    cfg["system"]["camera"]["pixels"] = [48, 48]
    cfg["system"]["camera"]["pixel_pitch_mm"] = 0.2
    cfg["subject"]["surface"] = {"phantom": "patch", "size_mm": [24, 16], "n": [6, 4], "center_mm": [0, 0, 10]}
    cfg["subject"]["poses"] = {"heights_mm": [0, 8]}
    cfg["simulate"] = {"flux": {"kind": "gaussian", "width_mm": 6.0, "peak_photons": 1e7, "center_mm": [2, 1, 10]},
                       "noise": {"model": "poisson", "peaks_photons": [1e7, 1e5], "repeats": 4, "seed": 2}}
    return cfg


def test_noiseless_data_with_the_same_T_recovers_the_truth(write_config, patch_config, tmp_path):
    cfg = copy.deepcopy(patch_config)
    cfg["simulate"]["transfer"] = {}
    cfg["simulate"]["allow_inverse_crime"] = True
    p = write_config(cfg)
    assert run("simulate", p, "--quiet").exit_code == 0
    for method in ("nnls", "weighted_lsq", "paper"):
        over = ["--set", f"reconstruct.method={method}", "--set", "reconstruct.noiseless=true",
                "--set", "reconstruct.lambda=1e-9"]
        r = run("reconstruct", p, "--quiet", *over)
        assert r.exit_code == 0, r.output
        with h5py.File(tmp_path / "run" / "reconstruction.h5") as f:
            assert f["flux/observed"][()].all()
            truth = f["truth/power"][()]
            got = f["flux/power"][()]
            assert np.abs(got - truth).sum() / truth.sum() < 1e-3, method
            assert f["per_pose/observed"][()].all()


def test_noisy_reconstruction_beats_backprojection_and_sweeps(write_config, patch_config, tmp_path):
    cfg = copy.deepcopy(patch_config)
    # truth constant per element: this test is about the discrepancy principle reaching the
    # noise level, which model error (the honest, finer truth) would rightly prevent at SNR > 30
    cfg["simulate"]["truth_refinement"] = 0
    cfg["reconstruct"] = {"method": "weighted_lsq", "lambda_rule": "discrepancy",
                          "sweep": {"methods": [{"method": "backprojection"},
                                                {"method": "weighted_lsq", "lambda": "auto"}]}}
    p = write_config(cfg)
    assert run("simulate", p, "--quiet").exit_code == 0
    r = run("reconstruct", p, "--jobs", "2")
    assert r.exit_code == 0, r.output
    with h5py.File(tmp_path / "run" / "reconstruction.h5") as f:
        err = f["sweep/error"][()]
        assert err.shape == (2, 2, 2, 4)
        assert np.allclose(f["sweep/mean"][()], err.mean(axis=3))
        assert np.all(err[0] > 0.99)  # backprojection: quantitatively useless (~100 %)
        snr = f["sweep/max_snr"][()]
        assert np.all(snr[0] > 10) and np.all(snr[1] < 3)
        assert np.all(err[1, 0] < 0.10)  # SNR > 10: under 10 % (the paper's own bar)
        assert np.all(err[1, 0].mean(axis=1) < err[1, 1].mean(axis=1))  # error grows as SNR falls
        # the main result is level 0, repeat 0, joint over both poses
        assert f["truth"].attrs["error"] == pytest.approx(
            np.abs(f["flux/power"][()] - f["truth/power"][()]).sum() / f["truth/power"][()].sum())
        assert f["truth"].attrs["error"] < 0.05  # both poses jointly do better than either
        assert abs(f["truth"].attrs["total_ratio"] - 1) < 0.05
        # uncertainty: the 1-sd band covers the truth about as often as it should: 68.3 % of the
        # n elements, within 3 binomial sd (n = 24: 0.40-0.97; the upper bound of 1.0 before could
        # not fail). Measured 0.50 (z mean -0.97, sd 1.26: the discrepancy rule's bias, which a
        # sampling sigma leaves out); with sigma halved 0.29 and x4 1.00 (both fail here), x2
        # 0.83 and x3 0.92 (24 elements cannot tell those apart)
        z = (f["flux/power"][()] - f["truth/power"][()]) / f["flux/sigma"][()]
        p1, n = 0.6827, z.size
        band = 3 * np.sqrt(p1 * (1 - p1) / n)
        assert p1 - band < np.mean(np.abs(z) < 1) < p1 + band, (np.mean(np.abs(z) < 1), n)
        fit = f["fit/fitted"][()]
        meas = f["fit/measured"][()]
        assert np.allclose(f["fit/residual"][()], meas - fit, atol=1e-3)
        # the discrepancy principle: the weighted residual matches the noise it was told of
        seen = fit > 0
        chi2 = ((meas - fit)[seen] ** 2 / np.maximum(meas[seen], 1.0)).sum() / seen.sum()
        assert 0.7 < chi2 < 1.3


def test_reconstruct_from_exported_count_images(write_config, patch_config, tmp_path):
    cfg = copy.deepcopy(patch_config)
    cfg["simulate"]["noise"] = {"model": "emccd", "peaks_photons": [1e7], "repeats": 1, "seed": 4}
    cfg["simulate"]["export"] = {"format": "tiff"}
    cfg["system"]["camera"]["sensor"] = {"em_gain": 20}
    p = write_config(cfg)
    assert run("simulate", p, "--quiet").exit_code == 0
    assert run("reconstruct", p, "--quiet").exit_code == 0
    with h5py.File(tmp_path / "run" / "reconstruction.h5") as f:
        from_sim = f["flux/power"][()]
    files = [f"run/images/level0/h{h:+g}_rot0_rep0.tif" for h in (0, 8)]
    cfg["reconstruct"] = {"images": {"files": files, "units": "counts"}}
    p = write_config(cfg)
    r = run("reconstruct", p, "--quiet")
    assert r.exit_code == 0, r.output
    with h5py.File(tmp_path / "run" / "reconstruction.h5") as f:
        assert "truth" not in f
        assert np.allclose(f["flux/power"][()], from_sim, rtol=1e-6)


def test_bad_reconstruction_input(write_config, patch_config):
    p = write_config(patch_config)
    r = run("reconstruct", p)
    assert r.exit_code == 2 and "simulate" in " ".join(r.output.split())
    cfg = copy.deepcopy(patch_config)
    cfg["reconstruct"] = {"images": {"files": ["one.tif"]}}
    r = run("reconstruct", write_config(cfg))
    assert r.exit_code == 2 and "2 pose(s)" in " ".join(r.output.split())
    r = run("reconstruct", p, "--set", "reconstruct.method=magic")
    assert r.exit_code == 2 and "reconstruct.method" in r.output


def test_solving_on_sub_elements_and_summing_back(write_config, minimal_config, tmp_path):
    """unknowns: sub_elements (the paper solved on its 9x-subdivided surface): the ring's strips
    are the unknowns, summed back per element.  A wrong strip-to-element map would give errors
    of tens of percent; the split between neighbouring strips is poorly determined, their sums
    per element well."""
    from fluxcli.surface import phantoms

    ring = phantoms.ring(radius_mm=10, thickness_mm=1, n_elements=40, strips_per_element=5)[0]
    sub, parent = ring.unknowns()
    assert sub.n_elements == 200 and np.all(np.bincount(parent) == 5)
    assert np.allclose(np.bincount(parent, weights=sub.element_areas_mm2), ring.element_areas_mm2)
    cfg = copy.deepcopy(minimal_config)
    cfg["system"]["camera"]["pixels"] = [256, 1]
    cfg["system"]["camera"]["pixel_pitch_mm"] = 0.02
    cfg["subject"]["surface"] = {"phantom": "ring", "radius_mm": 10, "n_elements": 40, "strips_per_element": 5}
    cfg["subject"]["poses"] = {"heights_mm": [-2.0]}  # the ring's top 2 mm below the focal plane (z = 20)
    cfg["simulate"] = {"flux": {"kind": "gaussian", "width_mm": 3.0, "peak_photons": 1e9},
                       "noise": {"model": "none"}, "transfer": {}, "allow_inverse_crime": True}
    cfg["reconstruct"] = {"method": "paper", "lambda": 0.1, "unknowns": "sub_elements", "noiseless": True}
    p = write_config(cfg)
    assert run("simulate", p, "--quiet").exit_code == 0
    r = run("reconstruct", p)
    assert r.exit_code == 0, r.output
    assert "on sub-elements" in r.output
    with h5py.File(tmp_path / "run" / "reconstruction.h5") as f:
        truth, got, obs = f["truth/power"][()], f["flux/power"][()], f["flux/observed"][()]
        assert got.shape == (40,) and 0 < obs.sum() < 40
        assert np.nansum(np.abs(got - truth)[obs]) / truth[obs].sum() < 0.05


def test_vertex_basis_integrates_a_linear_exitance_exactly():
    """unknowns: vertices: exitance linear within each face. For J(x) = 1 + x·g (linear on
    every flat face) the element powers from the vertex values must equal the closed form
    Σ_faces S_f J(centroid_f) (a linear function's integral over a triangle), every vertex's
    lumped power must be shared out completely (columns sum to 1), and the lumped areas must
    add up to the surface."""
    from fluxcli.surface import phantoms

    surf = phantoms.cylinder(radius_mm=12.5, length_mm=50, n_angular=24, n_axial=12)[0]
    for levels in (1, 2):
        vb = surf.vertex_basis(levels)
        V = surf.vertices_mm[vb.vertex_index]
        g = np.array([0.013, -0.02, 0.031])
        u = (1.0 + V @ g) * vb.areas_mm2  # lumped power of each vertex, photons
        ok = surf.element_of_face >= 0
        c = surf.face_vertices_mm[ok].mean(axis=1)
        exact = np.bincount(surf.element_of_face[ok], weights=surf.face_areas_mm2[ok] * (1.0 + c @ g),
                            minlength=surf.n_elements)
        assert np.allclose(vb.to_elements @ u, exact, rtol=1e-12)
        assert np.allclose(np.asarray(vb.to_elements.sum(axis=0)).ravel(), 1.0)
        assert vb.areas_mm2.sum() == pytest.approx(surf.element_areas_mm2.sum(), rel=1e-12)
        # the fine faces' powers are the same integrals on the refined surface
        fine, parent = surf.refined(levels)
        cf = fine.face_vertices_mm[fine.element_of_face >= 0].mean(axis=1)
        assert np.allclose(vb.to_fine @ u, fine.face_areas_mm2[fine.element_of_face >= 0] * (1.0 + cf @ g))


def test_vertex_prior_is_the_exact_gradient_energy_of_a_linear_exitance():
    """The prior of a solve on vertices: Jᵀ(diag(W1) − W)J with W = vertex_basis().stiffness
    must equal ∫|∇J|² dS of J linear on each face, computed face by face from each face's
    own gradient (the triangle's edge vectors, not the cotangent formula), for any vertex
    values; on the cylinder (right triangles) no weight is clipped. A linear J along the
    axis has energy |g|² × the side area; a constant has none."""
    from fluxcli.surface import phantoms

    surf = phantoms.cylinder(radius_mm=12.5, length_mm=50, n_angular=24, n_axial=12)[0]
    vb = surf.vertex_basis()
    W = vb.stiffness
    K = np.diag(np.asarray(W.sum(axis=1)).ravel()) - W.toarray()
    ok = surf.element_of_face >= 0
    local = np.searchsorted(vb.vertex_index, surf.faces[ok])
    P = surf.vertices_mm[surf.faces[ok]]

    def energy(J):  # Σ_f S_f |∇J_f|²: the gradient solves ∇J·e1 = J1 − J0, ∇J·e2 = J2 − J0 in the face's plane
        e1, e2 = P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]
        G = np.stack([np.einsum("ij,ij->i", e1, e1), np.einsum("ij,ij->i", e1, e2),
                      np.einsum("ij,ij->i", e2, e2)], axis=1)
        dJ = J[local[:, 1:]] - J[local[:, :1]]
        det = G[:, 0] * G[:, 2] - G[:, 1] ** 2
        a = (G[:, 2] * dJ[:, 0] - G[:, 1] * dJ[:, 1]) / det  # ∇J = a e1 + b e2
        b = (G[:, 0] * dJ[:, 1] - G[:, 1] * dJ[:, 0]) / det
        grad = a[:, None] * e1 + b[:, None] * e2
        return float(np.sum(0.5 * np.linalg.norm(np.cross(e1, e2), axis=1) * np.sum(grad * grad, axis=1)))

    rng = np.random.default_rng(2)
    for _ in range(3):
        J = rng.normal(size=vb.n_vertices)
        assert J @ K @ J == pytest.approx(energy(J), rel=1e-10)
    J = 0.7 * surf.vertices_mm[vb.vertex_index, 0]  # along the axis: |∇J| = 0.7 on the side, 0 on the caps
    side = 2 * np.pi * 12.5 * 50 * (np.sin(np.pi / 24) / (np.pi / 24))  # the 24-gon's side area
    assert J @ K @ J == pytest.approx(0.49 * side, rel=1e-10)
    assert np.allclose(K @ np.ones(vb.n_vertices), 0.0, atol=1e-12)


def test_light_outside_the_model_is_warned_or_refused_never_ignored():
    """The solve uses only the pixels T reaches; light elsewhere is counted against the
    image's total: a warning above 5 %, exit 2 above 50 %, nothing for noise alone."""
    import scipy.sparse as sp

    from fluxcli.errors import UserError
    from fluxcli.imaging.noise import PhotonNoise
    from fluxcli.stages.reconstruct import light_outside
    from fluxcli.surface.phantoms import cylinder

    surface = cylinder(radius_mm=8, length_mm=24, n_angular=8, n_axial=3)[0]
    n = 400
    T = sp.csr_array((np.ones(100), (np.arange(100), np.zeros(100, int))), shape=(n, 1))  # pixels 0-99 seen
    noise = PhotonNoise(kind="poisson")
    valid = np.ones(n, bool)
    rng = np.random.default_rng(0)
    a = np.zeros(n)
    a[:100] = 900.0
    a[100:] = 10.0  # 300 pixels x 10 = 3000 of 93 000 photons outside: 3 %, well above the noise
    assert light_outside(T, a, valid, noise, "p", surface) is None
    a[100:] = 40.0  # 12 000 of 102 000: 12 %
    w = light_outside(T, a, valid, noise, "p", surface)
    assert w is not None and w.startswith("12% of the image's light")
    a[100:] = 400.0  # 120 000 of 210 000: refused
    with pytest.raises(UserError, match="no element of the subject can reach"):
        light_outside(T, a, valid, noise, "p", surface)
    a[100:] = rng.normal(0.0, 30.0, 300)  # bias-subtracted read noise only: sums to about 0
    assert light_outside(T, a, valid, PhotonNoise(kind="gaussian", read_noise_photons=30.0), "p", surface) is None
    a[100:] = 400.0
    valid[100:] = False  # NaN-masked by the user: left out
    assert light_outside(T, a, valid, noise, "p", surface) is None


def test_cotangent_weights_clip_negative_and_never_leave_a_vertex_untied():
    """Obtuse angles on both sides of an edge give it a negative weight: clipped to 0 so the
    prior stays positive semi-definite. A vertex left with no weight at all (here only in a
    degenerate, zero-area face) keeps its edges at the median weight, so the prior still ties
    it to its neighbours."""
    from fluxcli.surface.mesh import cotangent_weights

    # edge 0-1 between two flat triangles whose apexes (2, 3) are at 157°: cot sum < 0
    V = np.array([[0, 0, 0], [10, 0, 0], [5, 1, 0], [5, -1, 0], [20, 0, 0], [30, 0, 0], [40, 0, 0]], float)
    F = np.array([[0, 1, 2], [1, 0, 3], [4, 5, 6]])  # the last face is degenerate (collinear)
    W = cotangent_weights(V, F).toarray()
    assert W[0, 1] == 0.0 and np.all(W >= 0) and np.allclose(W, W.T)
    a = np.arctan2(1, 5)  # the angle at 0 (and at 1) of the flat triangles
    assert W[0, 2] == pytest.approx(0.5 / np.tan(a)) and W[1, 3] == pytest.approx(0.5 / np.tan(a))
    median = np.median(W[W > 0])
    assert W[4, 5] == W[5, 6] == W[4, 6] == median
    K = np.diag(W.sum(axis=1)) - W
    assert np.linalg.eigvalsh(K).min() > -1e-12


def test_rates_are_fixed_at_reconstruct_time(write_config, patch_config, tmp_path):
    """A rate (photons/s) uses the exposure reconstruct recorded: a config edited afterwards to
    state another exposure is refused by summary and report, naming both values (issue 26: a
    summary printed 7.669e+07 photons/s for a reconstruction that gives 1.278e+07 at 30 s)."""
    cfg = copy.deepcopy(patch_config)
    cfg["simulate"]["noise"] = {"model": "poisson", "peaks_photons": [1e5], "repeats": 1, "seed": 4}
    cfg["simulate"]["export"] = {"format": "tiff"}
    p = write_config(cfg)
    assert run("simulate", p, "--quiet").exit_code == 0
    cfg["reconstruct"] = {"images": {"files": [f"run/images/level0/h{h:+g}_rot0_rep0.tif" for h in (0, 8)],
                                     "exposure_s": 30.0}}
    p = write_config(cfg)
    r = run("reconstruct", p, "--quiet")
    assert r.exit_code == 0, r.output
    with h5py.File(tmp_path / "run" / "reconstruction.h5") as f:
        assert f.attrs["rate_exposure_s"] == 30.0
        total = float(np.nansum(f["per_pose/total"][()][0]))
    r = run("summary", p)
    assert r.exit_code == 0, r.output
    assert "exposure 30 s" in r.output and f"{total / 30.0:.4g}" in r.output
    for stage in ("summary", "report"):
        r = run(stage, p, "--set", "reconstruct.images.exposure_s=5")
        text = " ".join(r.output.split())
        assert r.exit_code == 2, r.output
        assert "5 s" in text and "30 s" in text and "reconstruction.h5" in text
    # no exposure at reconstruct time, one stated later: refused too (per exposure is not per second)
    del cfg["reconstruct"]["images"]["exposure_s"]
    p = write_config(cfg)
    assert run("reconstruct", p, "--quiet").exit_code == 0
    r = run("summary", p, "--set", "reconstruct.images.exposure_s=5")
    assert r.exit_code == 2 and "no exposure time" in " ".join(r.output.split())


def test_image_files_that_record_their_exposure_give_the_rate(write_config, patch_config, tmp_path):
    """Frames that record their exposure (fluxmap's own: rig snap, simulate's export; FITS
    EXPTIME of camera software) make the rate when the config states none, and a stated
    exposure they contradict, or poses at different exposures, exit 2 naming the file.  The
    frames' exposure was ignored: a rig snap frame of 0.5 s was turned into photons/s at the
    schema's 1 s, silently half the rate."""
    from astropy.io import fits

    from fluxcli.imaging.imagefiles import read_image

    cfg = copy.deepcopy(patch_config)
    cfg["simulate"]["noise"] = {"model": "poisson", "peaks_photons": [1e5], "repeats": 1, "seed": 4, "exposure_s": 0.5}
    cfg["simulate"]["export"] = {"format": "tiff"}
    p = write_config(cfg)
    assert run("simulate", p, "--quiet").exit_code == 0
    tifs = [f"run/images/level0/h{h:+g}_rot0_rep0.tif" for h in (0, 8)]
    cfg["reconstruct"] = {"images": {"files": tifs}}
    p = write_config(cfg)
    r = run("reconstruct", p, "--quiet")
    assert r.exit_code == 0, r.output
    with h5py.File(tmp_path / "run" / "reconstruction.h5") as f:
        assert f.attrs["rate_exposure_s"] == 0.5 and f.attrs["rate_exposure_source"] == "image files' metadata"
        total = float(np.nansum(f["per_pose/total"][()][0]))
    r = run("summary", p)
    assert r.exit_code == 0 and "exposure 0.5 s" in r.output and f"{total / 0.5:.4g}" in r.output, r.output

    cfg["reconstruct"]["images"]["exposure_s"] = 30.0
    r = run("reconstruct", write_config(cfg), "--quiet", "--force")
    text = " ".join(r.output.split())
    assert r.exit_code == 2 and "files[0]" in text and "h+0_rot0_rep0.tif) was exposed for 0.5 s (fluxmap:exposure_s" in text
    assert "reconstruct.images.exposure_s is 30 s" in text and "off by 60x" in text

    # camera software's FITS (EXPTIME, written by astropy here): its exposure, and one per scene
    for k, (tif, t) in enumerate(zip(tifs, (2.0, 2.0))):
        img, _ = read_image(tmp_path / tif)
        fits.PrimaryHDU(img.astype(np.float32), header=fits.Header({"EXPTIME": t})).writeto(tmp_path / f"p{k}.fits")
    cfg["reconstruct"]["images"] = {"files": ["p0.fits", "p1.fits"]}
    assert run("reconstruct", write_config(cfg), "--quiet", "--force").exit_code == 0
    with h5py.File(tmp_path / "run" / "reconstruction.h5") as f:
        assert f.attrs["rate_exposure_s"] == 2.0
    cfg["reconstruct"]["images"] = {"files": ["p0.fits", tifs[1]]}
    r = run("reconstruct", write_config(cfg), "--quiet", "--force")
    text = " ".join(r.output.split())
    assert r.exit_code == 2 and "was exposed for 0.5 s (fluxmap:exposure_s) but reconstruct.images.files[0] for 2 s" in text
    fits.PrimaryHDU(img.astype(np.float32), header=fits.Header({"EXPTIME": -1.0})).writeto(tmp_path / "bad.fits")
    cfg["reconstruct"]["images"] = {"files": ["p0.fits", "bad.fits"]}
    assert run("reconstruct", write_config(cfg), "--quiet", "--force").exit_code == 0  # EXPTIME -1 is no measurement
    with h5py.File(tmp_path / "run" / "reconstruction.h5") as f:
        assert f.attrs["rate_exposure_s"] == 2.0  # p0's


def test_faces_split_finer_keep_the_elements_and_their_geometry():
    """subject.refine_faces splits every face into four at its edge midpoints; the elements (what is
    reported) keep their areas, centroids and normals, written out here for the box's flat faces:
    an element of side a x b has area a b; the surface stays closed; each level gives 4x the faces
    and, on a closed triangulated surface, V' = V + E new vertices (E = 3F/2)."""
    from fluxcli.surface import phantoms

    surf = phantoms.box(size_mm=(12.0, 16.0, 8.0), element_mm=4.0)[0]
    assert np.allclose(surf.element_areas_mm2, 16.0)
    for levels in (1, 2):
        fine = surf.subdivided(levels)
        assert fine.n_elements == surf.n_elements and len(fine.faces) == len(surf.faces) * 4 ** levels
        assert np.allclose(fine.element_areas_mm2, 16.0, rtol=1e-12)
        assert np.allclose(fine.element_centroids_mm, surf.element_centroids_mm, atol=1e-12)
        assert np.allclose(fine.element_normals, surf.element_normals, atol=1e-12)
        assert fine.is_closed
        v, f = len(surf.vertices_mm), len(surf.faces)
        for _ in range(levels):
            v, f = v + 3 * f // 2, 4 * f
        assert len(fine.vertices_mm) == v
        # each fine face lies inside its element's coarse face: its centroid is within the element's square
        c = fine.face_vertices_mm.mean(axis=1)
        half = np.abs(c - surf.element_centroids_mm[fine.element_of_face])
        assert (np.sort(half, axis=1)[:, 1:] <= 2.0 + 1e-9).all() and (np.sort(half, axis=1)[:, 0] < 1e-9).all()
    assert surf.subdivided(0) is surf


def test_faces_split_on_a_round_phantom_follow_its_round_body():
    """A cylinder phantom's 20 facets are chords of the round body a Monte Carlo truth leaves (the
    side is 0.41 % smaller than 2 pi r L); split with its RoundBody, the new vertices of edges on the
    body lie on it, so each level halves the facets' angle and the side's area converges to the
    closed form with the chord's error falling 4x a level (sin(x)/x), the caps staying flat and the
    surface closed. The sphere's area converges to 4 pi r^2 the same way. Split without the body (a
    mesh file: nothing known beyond its faces) the area does not move."""
    from fluxcli.surface import phantoms

    r, length, n = 12.5, 50.0, 20
    surf = phantoms.cylinder(radius_mm=r, length_mm=length, n_angular=n, n_axial=12)[0]
    body = phantoms.RoundBody(r, axis=0)
    exact = 2 * np.pi * r * length
    errors = []
    for levels in (0, 1, 2):
        fine = surf.subdivided(levels, body)
        side = fine.element_of_face >= 0
        area = fine.face_areas_mm2[side].sum()
        chord = n * 2 ** levels * 2 * r * np.sin(np.pi / (n * 2 ** levels)) * length  # a prism of n 2^levels facets
        assert area == pytest.approx(chord, rel=1e-12)
        errors.append(1 - area / exact)
        assert fine.is_closed and fine.n_elements == surf.n_elements
        rho = np.hypot(*fine.vertices_mm[:, 1:].T)
        on_caps = np.isclose(np.abs(fine.vertices_mm[:, 0]), length / 2)
        assert np.allclose(rho[~on_caps], r)  # every side vertex on the body
    assert errors[0] == pytest.approx(0.0041, abs=2e-4) and errors[1] / errors[2] == pytest.approx(4, rel=0.01)
    assert surf.subdivided(1).face_areas_mm2[surf.subdivided(1).element_of_face >= 0].sum() == pytest.approx(exact * (1 - errors[0]))
    sphere = phantoms.sphere(radius_mm=5.0, n_latitude=8, n_longitude=12)[0]
    s_err = [1 - sphere.subdivided(k, phantoms.RoundBody(5.0)).face_areas_mm2.sum() / (4 * np.pi * 25) for k in (0, 1, 2, 3)]
    assert s_err[0] > s_err[1] > s_err[2] > s_err[3] > 0 and s_err[2] / s_err[3] == pytest.approx(4, rel=0.05), s_err


def _turned_demo_cylinder(write_config, tmp_path, noise: str):
    """The demo's cylinder turned 0 and -90 degrees, simulated, and its images saved again as
    another program would (the pixels without fluxmap's pose metadata): config and file names."""
    import yaml

    cfg = yaml.safe_load((ROOT / "configs" / "demo.yaml").read_text())
    cfg["workdir"] = "run"
    cfg.pop("report", None)
    cfg["subject"]["poses"] = {"heights_mm": [0], "rotations_deg": [0, -90]}
    cfg["subject"]["surface"].update({"n_angular": 16, "n_axial": 8})
    cfg["simulate"]["noise"] = {"model": noise, "repeats": 1, "seed": 7, "exposure_s": 10.0}
    if noise == "emccd":
        cfg["system"]["camera"]["sensor"] = {}
    assert run("simulate", write_config(cfg), "--quiet").exit_code == 0
    tifs = []
    for rot in (0, -90):
        image, _ = read_image(tmp_path / f"run/images/level0/h+0_rot{rot}_rep0.tif")
        write_image(tmp_path / f"plain{rot}.tif", image.astype(np.float32))
        tifs.append(f"plain{rot}.tif")
    return cfg, tifs


def _reconstruct_files(write_config, tmp_path, cfg, files, **images) -> tuple[list[str], float]:
    """reconstruct from ``files``: the warnings that say the poses disagree, and the total."""
    cfg["reconstruct"] = {"images": {"files": files, **images}}
    r = run("reconstruct", write_config(cfg), "--quiet", "--force")
    assert r.exit_code == 0, r.output
    with h5py.File(tmp_path / "run" / "reconstruction.h5") as f:
        total = float(f["flux/total"][()])
    return [w for w in read_warnings(tmp_path / "run" / "reconstruction.h5")[0] if "disagree about the light" in w], total


def test_images_given_in_another_order_than_the_poses_are_said_to_disagree(write_config, tmp_path):
    """Two image files swapped, or one given for both poses, saved by another program (no pose
    metadata to check). Each pose alone fits its image to the noise, and only the joint fit cannot:
    the joint total read 1.83x the truth (1.43x with one image twice) under a chi^2 warning that
    blamed the model or the noise model. The warning now says that the poses disagree and asks for
    the files' order; in order it is silent."""
    cfg, tifs = _turned_demo_cylinder(write_config, tmp_path, "poisson")
    said, total = {}, {}
    for name, files in (("in order", tifs), ("swapped", tifs[::-1]), ("one twice", [tifs[0], tifs[0]])):
        said[name], total[name] = _reconstruct_files(write_config, tmp_path, cfg, files)
    assert not said["in order"]
    for name in ("swapped", "one twice"):
        assert total[name] > 1.2 * total["in order"], (name, total)  # what the warning is about
        assert said[name] and "subject.poses order" in said[name][0], name


def test_counts_bias_subtracted_already_or_a_bias_frame_for_a_pose(write_config, tmp_path):
    """EMCCD counts. An image bias-subtracted by another program and given as counts had the bias
    taken off again (median 0, most pixels 500 counts below it) and read a total 0.79x the truth
    under a chi^2 warning: now exit 2 naming the file and system.camera.sensor.bias_counts. A bias
    frame given for one pose fits alone (no light) and pulled the joint total to 0.47x: the warning
    now names that pose as reading no light while the others do."""
    cfg, tifs = _turned_demo_cylinder(write_config, tmp_path, "emccd")
    said, good = _reconstruct_files(write_config, tmp_path, cfg, tifs, units="counts")
    assert not said
    image, _ = read_image(tmp_path / tifs[0])
    write_image(tmp_path / "subtracted.tif", (image - 500.0).astype(np.float32))
    cfg["reconstruct"] = {"images": {"files": ["subtracted.tif", tifs[1]], "units": "counts"}}
    r = run("reconstruct", write_config(cfg), "--quiet", "--force")
    text = " ".join(r.output.split())
    assert r.exit_code == 2 and "files[0]" in text and "below the bias" in text and "bias_counts 500" in text, text
    rng = np.random.default_rng(1)
    write_image(tmp_path / "bias.tif", (500.0 + 5.0 * rng.standard_normal(image.shape)).round().astype(np.float32))
    said, total = _reconstruct_files(write_config, tmp_path, cfg, ["bias.tif", tifs[1]], units="counts")
    assert total < 0.8 * good
    assert said and "h=+0mm rot=0deg read no light" in said[0], said


def test_an_image_upside_down_is_said_to_fit_better_turned(write_config, tmp_path):
    """One pose's image saved upside down (another program's row order: FITS stores rows
    bottom-up). It misfit (chi^2 per pixel 5.0) and read the total 0.946x with a warning that blamed
    the model or the noise model. The pose's warning now says it fits 4x better upside down; the
    images as taken say nothing of the kind."""
    cfg, tifs = _turned_demo_cylinder(write_config, tmp_path, "poisson")

    def turned_warnings(files):
        cfg["reconstruct"] = {"images": {"files": files}}
        r = run("reconstruct", write_config(cfg), "--quiet", "--force")
        assert r.exit_code == 0, r.output
        return [w for w in read_warnings(tmp_path / "run" / "reconstruction.h5")[0] if "better" in w]

    assert not turned_warnings(tifs)
    image, _ = read_image(tmp_path / tifs[0])
    write_image(tmp_path / "flipped.tif", image[::-1].astype(np.float32))
    said = turned_warnings(["flipped.tif", tifs[1]])
    assert len(said) == 1 and said[0].startswith("pose h=+0mm rot=0deg") and "better upside down" in said[0], said



def test_a_camera_a_calibration_error_away_is_said_to_shift_the_image(write_config, tmp_path):
    """The demo's cylinder imaged with the camera where the config says, then reconstructed with
    the lens centre 1 mm across the cylinder (~0.23 pixel on the sensor): a real calibration
    error, which moves both flanks of each image. Both poses are warned that the image looks
    shifted (the flank test keeps a true shift), and neither is offered a turned image (whose
    light would fall outside the subject's reach). With the config's own camera nothing is said."""
    cfg, tifs = _turned_demo_cylinder(write_config, tmp_path, "poisson")
    said = {}
    for dy in (0.0, 1.0):
        cfg["system"]["camera"]["pose"]["lens_center_mm"] = [0.0, dy, 338.0]
        cfg["reconstruct"] = {"images": {"files": tifs}}
        path = write_config(cfg)
        assert run("build-T", path, "--quiet").exit_code == 0
        r = run("reconstruct", path, "--quiet", "--force")
        assert r.exit_code == 0, r.output
        warnings = read_warnings(tmp_path / "run" / "reconstruction.h5")[0]
        with h5py.File(tmp_path / "run" / "reconstruction.h5") as f:
            flanks = f["budget/shift_flank_z"][()]
        said[dy] = ([w for w in warnings if "looks like the image shifted" in w], [w for w in warnings if "better" in w],
                    flanks)
    assert not said[0.0][0] and not said[0.0][1]
    shifted, turned, flanks = said[1.0]
    assert len(shifted) == 2 and all("calibration error" in w or "system.camera.pose" in w for w in shifted), shifted
    assert not turned, turned
    assert np.all(flanks > 2.5), flanks  # each flank of each image sees the move on its own


def test_images_binned_on_the_chip_with_the_pitch_left_are_said_to_disagree_in_kind(write_config, tmp_path):
    """The demo's images binned 2 x 2 by the camera; the config's pixels halved to match, but
    pixel_pitch_mm left as it was. The fit misfit at chi^2 42-736 and read the total 1.14x the
    truth, with a warning that offered model error, the noise model or regularisation. Beyond
    chi^2 25 it now says the images and the set-up disagree in kind and names the pitch and
    binning; with the pitch doubled as it should be, nothing of the kind is said."""
    cfg, tifs = _turned_demo_cylinder(write_config, tmp_path, "poisson")
    binned = []
    for k, name in enumerate(tifs):
        image, _ = read_image(tmp_path / name)
        write_image(tmp_path / f"binned{k}.tif", image.reshape(48, 2, 48, 2).sum(axis=(1, 3)).astype(np.float32))
        binned.append(f"binned{k}.tif")
    cfg["system"]["camera"]["pixels"] = [48, 48]
    said = {}
    for pitch in (0.13, 0.26):
        cfg["system"]["camera"]["pixel_pitch_mm"] = pitch
        cfg["reconstruct"] = {"images": {"files": binned}}
        r = run("reconstruct", write_config(cfg), "--quiet", "--force")
        assert r.exit_code == 0, r.output
        said[pitch] = [w for w in read_warnings(tmp_path / "run" / "reconstruction.h5")[0] if "disagree in kind" in w]
    assert said[0.13] and "binning multiplies" in said[0.13][0]
    assert not said[0.26]


def test_orientation_hint_is_a_diagnostic_that_never_stops_a_reconstruction():
    """The turned images are solved only to say something: a solve that fails on one of them is
    passed over (it used to be able to end the reconstruction with the solver's error), and
    nothing is said unless one fits 2x better and within the chi^2 range."""
    from fluxcli.errors import UserError
    from fluxcli.inverse.solve import orientation_hint

    image, valid = np.arange(12.0).reshape(3, 4), np.ones((3, 4), bool)

    def chi2_of(a, v):
        if np.array_equal(a, image[::-1]):
            raise UserError("reconstruct.method smooth: the solver failed")
        return 1.1 if np.array_equal(a, image[:, ::-1]) else 6.0

    hint = orientation_hint(chi2_of, image, valid, 5.0, 100)
    assert hint is not None and "better mirrored left to right" in hint and "1.1" in hint
    assert orientation_hint(lambda a, v: 3.0, image, valid, 5.0, 100) is None  # not within the range
    assert orientation_hint(chi2_of, image, valid, 1.5, 100) is None  # the pose fits: nothing tried
    assert orientation_hint(chi2_of, image, valid, 5.0, 10**6) is None  # too big to try


def test_a_turned_image_whose_light_falls_where_nothing_is_seen_is_not_offered():
    """χ² counts the pixels the fit lights, so a turned image whose light lands where the subject
    cannot be seen "fits" by leaving it out: the demo with its lens 0.6 mm off the config's read
    "3.85x better turned half a turn" (44 % of the turned light out of reach, 2.3 % as given). A
    turning may put at most 2 % more of the light out of reach; one that keeps it in reach is
    still offered."""
    from fluxcli.inverse.solve import orientation_hint

    image = np.zeros((4, 6))
    image[:, :2] = 100.0  # the light on the left, where the subject is seen
    valid = np.ones_like(image, bool)
    reach = np.zeros_like(valid)
    reach[:, :3] = True
    chi2_of = lambda a, v: 1.1 if a[:, -1].sum() > 0 else 6.0  # noqa: E731  (light on the right "fits")
    assert orientation_hint(chi2_of, image, valid, 5.0, 100) is not None  # without reach: the trap
    assert orientation_hint(chi2_of, image, valid, 5.0, 100, reach) is None
    up = lambda a, v: 1.1 if np.array_equal(a, image[::-1]) else 6.0  # noqa: E731  (stays in reach)
    assert "better upside down" in orientation_hint(up, image, valid, 5.0, 100, reach)
    image[0, 4] = 50.0  # 6 % of the light out of reach as given: upside down it stays so, and is offered
    assert "better upside down" in orientation_hint(up, image, valid, 5.0, 100, reach)


def test_a_pose_with_no_light_beyond_the_noise_is_said_to_be_dark():
    """A bias-level frame after dark subtraction holds small values of both signs: some pixels
    are above 0, so "no valid pixel above 0" missed it (a second filter set to a bias-level frame
    reconstructed with warnings about lambda and poorly observed elements only). Light over the
    subject's pixels within 5 noise sigmas of nothing is now dark; 200 photons of a faint spot
    over Poisson noise of 14 are not."""
    from types import SimpleNamespace

    import scipy.sparse as sp

    from fluxcli.imaging.noise import PhotonNoise
    from fluxcli.stages._reconstruct_filters import dark_poses
    from fluxcli.stages._reconstruct_inputs import Inputs

    rng = np.random.default_rng(3)
    ny = nx = 16
    T = sp.csr_array(np.vstack([np.ones((64, 1)), np.zeros((ny * nx - 64, 1))]))  # the subject: the first 64 pixels
    bias = rng.normal(0.0, 1.0, (ny, nx))  # dark-subtracted bias: read noise of 1 photon, no light
    faint = bias.copy()
    faint.ravel()[:64] += 200.0 / 64
    todo = [(None, SimpleNamespace(pose=SimpleNamespace(label=lab))) for lab in ("a", "b")]
    inp = Inputs(np.stack([bias, faint]), np.ones((2, ny, nx), bool), None, "test")
    noise = PhotonNoise("poisson", read_noise_photons=1.0)
    said = dark_poses(inp, todo, noise, [T, T])
    assert len(said) == 1 and said[0].startswith("pose a: its images hold no light (") and "against" in said[0], said
    assert np.any(bias.ravel()[:64] > 0)  # the old test (a pixel above 0) passed it
    assert dark_poses(inp, todo) == []  # without the noise model: the old test only
