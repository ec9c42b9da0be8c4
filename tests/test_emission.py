"""The emission profile (issue 21): against numbers fluxmap did not produce, and in T.

Reference numbers: issue 21 / DESIGN.md section 3 (diffusion theory with a Fresnel
partial-current boundary, n 1.37-1.40; 2e9 MCX photons leaving a box of n 1.40), Haskell et
al. 1994 (JOSA A 11:2727) for the effective reflection coefficient.  Closed forms and scipy
quadratures are computed here, independently of fluxcli.optics.emission.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest
import yaml
from scipy import integrate

from fluxcli.optics import emission as E
from fluxcli.optics.camera import PlaneMirror, ThinLensCamera
from fluxcli.optics.transfer import LensSampling, PairwiseSampling, build_transfer, views_for
from fluxcli.surface import phantoms

ANGLES = (30.0, 45.0, 60.0, 70.0, 80.0)
DIFFUSION_THEORY = (0.975, 0.94, 0.88, 0.79, 0.59)  # issue 21, n 1.37-1.40
MCX_N140 = (0.972, 0.936, 0.873, 0.781, 0.563)  # issue 21, 2e9 photons, n 1.40


# ------------------------------------------------------------------ the diffuse profile
@pytest.mark.parametrize("n", [1.37, 1.40])
def test_diffuse_profile_matches_diffusion_theory_values_within_2_percent(n):
    got = E.diffuse(n).radiance(np.radians(ANGLES))
    assert np.abs(got - DIFFUSION_THEORY).max() < 0.02, got


def test_diffuse_profile_matches_monte_carlo_exit_photons_within_2_percent_up_to_75_degrees():
    got = E.diffuse(1.40).radiance(np.radians(ANGLES))
    up_to_75 = np.array(ANGLES) <= 75
    assert np.abs(got - MCX_N140)[up_to_75].max() < 0.02, got
    # beyond 75 deg (not required): diffusion theory is known to overestimate grazing exits a little
    assert abs(got[-1] - MCX_N140[-1]) < 0.03
    # what the issue reads off the same photons: Lambertian is ~11 % too bright head-on
    assert 1.08 < E.diffuse(1.40).weight(1.0) < 1.13


def test_the_default_profile_with_its_depth_term_also_matches_the_issue_s_numbers():
    """What {model: diffuse, refractive_index: 1.40} gives (with the depth term of the default
    medium, mu_a 0.01 and mu_s' 1 /mm, the issue's phantom): within 2 % of L(0) of both the
    diffusion-theory values and the MCX photons up to 75 deg, and closer to the photons at 80."""
    prof = E.profile({"model": "diffuse", "refractive_index": 1.40})
    assert prof.depth_term == pytest.approx(3 * 0.01 / 1.01)
    got = prof.radiance(np.radians(ANGLES))
    up_to_75 = np.array(ANGLES) <= 75
    assert np.abs(got - DIFFUSION_THEORY)[up_to_75].max() < 0.02, got
    assert np.abs(got - MCX_N140)[up_to_75].max() < 0.02, got
    assert abs(got[-1] - MCX_N140[-1]) < abs(E.diffuse(1.40).radiance(np.radians(80.0)) - MCX_N140[-1])


def _exit_bands(mua: float, n: float, n_photons: int, edges):
    """Our photon Monte Carlo: an isotropic source 4 mm under the top of a wide box (mu_s 1 /mm,
    g 0); the top face's photons per band of exit angle, as shares."""
    from fluxcli.montecarlo.transport import Medium, Shape, transport

    counts = np.zeros(len(edges) - 1)
    for b in range(-(-n_photons // 1_000_000)):
        e = transport(Medium(mua, 1.0, 0.0, n), Shape.box((80, 80, 40)), (0, 0, 16), 1_000_000, seed=5, batch=b)
        top = e.position_mm[:, 2] > 20 - 1e-6
        d = e.direction[top]
        cos_t = np.clip(d[:, 2] / np.linalg.norm(d, axis=1), -1, 1)
        counts += np.histogram(np.degrees(np.arccos(cos_t)), bins=edges)[0]
    return counts / counts.sum(), np.sqrt(counts) / counts.sum()


def _band_shares(prof, edges):
    """2 int pi p mu dmu over each band, by scipy (independent of the table's own quadrature)."""
    return np.array([2 * integrate.quad(lambda m: float(prof.weight(m)) * m, np.cos(np.radians(hi)),
                                        np.cos(np.radians(lo)), limit=200)[0] for lo, hi in zip(edges[:-1], edges[1:])])


def test_depth_term_matches_monte_carlo_exit_photons_in_an_absorbing_medium():
    """mu_a 0.1 /mm (tissue in the red): the photons leave much more along the normal than P1's
    profile (+4 % at 0-20 deg, -6 % at 70-80 deg); the depth term 1 + c mu'^2,
    c = 3 mu_a / mu_t' = 0.27 (emission.depth_term), puts them back within 1.5 % in every band
    to 80 deg (asserted: 2.5 %).  P1 alone misses by 6 %."""
    edges = np.array([0, 20, 40, 60, 70, 80, 90.0])
    shares, sigma = _exit_bands(0.1, 1.40, 3_000_000, edges)
    shares, sigma = shares[:-1], sigma[:-1]  # to 80 deg, as shares of every photon leaving the top
    with_term = E.diffuse(1.40, depth=True, reduced_scattering_per_mm=1.0, absorption_per_mm=0.1)
    ratio = shares / _band_shares(with_term, edges)[:-1]
    assert np.all(sigma / shares < 0.01)  # the photons resolve what is claimed
    assert np.abs(ratio - 1).max() < 0.025, ratio
    p1 = shares / _band_shares(E.diffuse(1.40), edges)[:-1]
    assert np.abs(p1 - 1).max() > 0.04, p1
    assert p1[0] > 1.03 and p1[-1] < 0.97  # the photons are steeper than P1, in the term's sense


def test_depth_term_is_in_the_key_and_off_gives_p1_alone():
    on = E.profile({"model": "diffuse", "refractive_index": 1.40, "tangential_flux": False})
    off = E.profile({"model": "diffuse", "refractive_index": 1.40, "tangential_flux": False, "depth_term": False,
                     "body_curvature": False})
    assert np.array_equal(off.table, E.diffuse(1.40).table) and off.key() == E.diffuse(1.40).key()
    assert on.key() != off.key() and "depth_term" in on.key()
    more = E.profile({"model": "diffuse", "refractive_index": 1.40, "tangential_flux": False, "absorption_per_mm": 0.1})
    assert more.key() != on.key()
    # steeper with absorption: head-on weight up, grazing down
    assert more.weight(1.0) > on.weight(1.0) > off.weight(1.0)
    assert more.weight(0.2) < on.weight(0.2) < off.weight(0.2)
    # a clear medium (mu_a 0) has no depth term
    clear = E.diffuse(1.40, depth=True, absorption_per_mm=0.0)
    assert np.array_equal(clear.table, off.table)
    with pytest.raises(ValueError, match="absorption_per_mm"):
        E.diffuse(1.40, depth=True, absorption_per_mm=-1.0)


def test_the_medium_s_g_is_in_the_key_only_where_a_term_uses_it(write_config, minimal_config):
    """scattering_anisotropy 0 (the default) keeps every diffuse key and table byte for byte, so
    the isotropic cases' T caches stand; g 0.9 changes the depth and tangential tables and the key;
    P1 alone (no term that uses the medium) does not depend on it; the config reads it and refuses
    g outside [0, 1) naming the key."""
    from fluxcli import config as C
    from fluxcli.errors import UserError

    base = {"model": "diffuse", "refractive_index": 1.40}
    iso, told = E.profile(base), E.profile(dict(base, scattering_anisotropy=0.9))
    assert E.profile(dict(base, scattering_anisotropy=0.0)).key() == iso.key() and "scattering_anisotropy" not in iso.key()
    assert told.key() != iso.key() and told.key()["scattering_anisotropy"] == 0.9 and "g 0.9" in told.describe()
    assert not np.array_equal(told.tangent, iso.tangent) and not np.array_equal(told.table, iso.table)
    assert told.tangent_weight(0.6) / told.weight(0.6) < 0.8 * iso.tangent_weight(0.6) / iso.weight(0.6)
    p1 = dict(base, depth_term=False, tangential_flux=False, body_curvature=False)
    assert E.profile(dict(p1, scattering_anisotropy=0.9)).key() == E.profile(p1).key()
    cfg = dict(minimal_config)
    cfg["subject"] = dict(cfg["subject"], emission=dict(base, scattering_anisotropy=0.9))
    assert C.load_config(write_config(cfg)).model.subject.emission.scattering_anisotropy == 0.9
    cfg["subject"]["emission"]["scattering_anisotropy"] = 1.0
    with pytest.raises(UserError, match="scattering_anisotropy"):
        C.load_config(write_config(cfg, "bad.yaml"))


@pytest.mark.parametrize("n,r_eff", [(1.33, 0.431), (1.40, 0.493)])
def test_boundary_coefficient_gives_haskell_1994_effective_reflection(n, r_eff):
    A = E.boundary_A(n)
    assert (A - 1) / (A + 1) == pytest.approx(r_eff, abs=1.5e-3)


def test_index_matched_limit_is_the_closed_form_diffusion_profile():
    """n = 1: no Fresnel, A = 1, L ~ 1 + 3/2 cos(theta); normalised, pi p = (1 + 1.5 mu) / 2."""
    mu = np.linspace(0.01, 1, 57)
    assert E.diffuse(1.0).weight(mu) == pytest.approx((1 + 1.5 * mu) / 2, rel=1e-9)
    # and it is approached from above (away from grazing, where Fresnel transmission still falls to 0)
    away = mu >= 0.1
    near = E.diffuse(1.0001).weight(mu)
    assert np.abs(near - (1 + 1.5 * mu) / 2)[away].max() < 2e-3


@pytest.mark.filterwarnings("ignore::scipy.integrate.IntegrationWarning")  # kinks of the table: roundoff only
@pytest.mark.parametrize("prof", [E.diffuse(1.40), E.diffuse(1.56), E.diffuse(1.0),
                                  E.diffuse(1.40, depth=True, absorption_per_mm=0.3),
                                  E.table([0, 40, 85], [1.0, 0.5, 0.1])],
                         ids=["n1.40", "n1.56", "n1", "n1.40-depth", "table"])
def test_profile_conserves_power_by_independent_quadrature(prof):
    """integral over the hemisphere of p(theta) cos(theta) dOmega = 1 (scipy, adaptive, in theta)."""
    total, _ = integrate.quad(lambda t: float(prof.p(np.cos(t))) * np.cos(t) * np.sin(t) * 2 * np.pi, 0, np.pi / 2,
                              limit=400, points=[np.radians(40), np.radians(85)])
    assert total == pytest.approx(1.0, rel=1e-6)


def test_lambertian_weight_is_exactly_one_in_front_and_zero_behind():
    lam = E.lambertian()
    assert lam.is_lambertian and lam.key() is None
    assert np.array_equal(lam.weight(np.array([1.0, 0.3, 1e-9, 0.0, -0.5])), [1, 1, 1, 0, 0])
    assert lam.radiance(np.radians(80)) == 1.0


# ------------------------------------------------------------------ tables
def test_table_of_the_diffuse_curve_reproduces_it(tmp_path):
    deg = np.arange(0, 91, 1.0)
    diff = E.diffuse(1.40)
    f = tmp_path / "profile.csv"
    f.write_text("angle_deg,radiance\n" + "".join(f"{a:g},{3.7 * r:.9f}\n" for a, r in zip(deg, diff.radiance(np.radians(deg)))))
    tab = E.table_from_csv(f.read_text())
    mu = np.cos(np.radians(np.arange(0, 85, 0.5)))
    assert tab.weight(mu) == pytest.approx(diff.weight(mu), rel=2e-3)
    for scale in (1e-320, 1e308):  # any scale
        assert E.table_from_csv(f"angle_deg,radiance\n0,{scale}\n90,{scale}\n").weight(mu) == pytest.approx(1.0)
    c = tmp_path / "cos.csv"
    c.write_text("cos_theta,radiance\n1,2\n0,2\n")
    assert E.table_from_csv(c.read_text()).weight(mu) == pytest.approx(1.0, rel=1e-12)
    # as a spreadsheet saves "CSV UTF-8": a byte-order mark first, CRLF line ends
    excel = tmp_path / "excel.csv"
    excel.write_bytes(f.read_text().replace("\n", "\r\n").encode("utf-8-sig"))
    assert np.array_equal(E.table_from_csv(excel.read_text(encoding="utf-8")).table, tab.table)


@pytest.mark.parametrize("text", [
    "angle_deg,radiance\n0,1\n45,0.9\n75,0.6\n90,0.2\n",  # as the docs write it
    "0,1\n45,0.9\n75,0.6\n90,0.2\n",  # no header: values beyond 1, so degrees
    "theta_deg,L\n90,0.2\n75,0.6\n45,0.9\n0,1\n",  # another tool's header, rows from 90 down
    "Theta (rad),relative radiance\n0,1\n0.785398163397,0.9\n1.308996938996,0.6\n1.570796326795,0.2\n",
    "angle_deg;radiance\n0;1\n45;0,9\n75;0,6\n90;0,2\n",  # a decimal-comma spreadsheet
    "angle_deg\tradiance\n0\t1\n45\t0.9\n75\t0.6\n90\t0.2\n",
    "# measured 2026\n0 1\n45 0.9\n75 0.6\n90 0.2\n",  # whitespace, a comment
])
def test_a_table_reads_the_same_however_a_lab_writes_it(text):
    ref = E.table([0, 45, 75, 90], [1, 0.9, 0.6, 0.2])
    assert np.allclose(E.table_from_csv(text).table, ref.table, rtol=1e-10, atol=0)


@pytest.mark.parametrize("name,text,encoding", [
    # a spreadsheet on Windows saves "angle (°)" in Windows-1252, which is not UTF-8
    ("p.csv", "angle (°);radiance\n0;1\n45;0,9\n75;0,6\n90;0,2\n", "cp1252"),
    # its "Unicode Text" export: UTF-16 behind a byte-order mark, tab-separated; read as UTF-8 or
    # Latin-1 its header is 'ÿþa\x00n\x00...' and names no angle
    ("p.txt", "angle (°)\tradiance\r\n0\t1\r\n45\t0.9\r\n75\t0.6\r\n90\t0.2\r\n", "utf-16"),
    ("p.txt", "\ufeffangle (°)\tradiance\r\n0\t1\r\n45\t0.9\r\n75\t0.6\r\n90\t0.2\r\n", "utf-16-be"),
])
def test_a_table_saved_by_a_spreadsheet_reads_through_the_config(tmp_path, minimal_config, name, text, encoding):
    from fluxcli.config import emission_profile, load_config

    (tmp_path / name).write_bytes(text.encode(encoding))
    cfg = copy.deepcopy(minimal_config)
    cfg["subject"]["emission"] = {"model": "table", "file": name}
    cfg["subject"]["surface"] = {"phantom": "sphere", "radius_mm": 5, "n_latitude": 4, "n_longitude": 6}
    (tmp_path / "c.yaml").write_text(yaml.safe_dump(cfg))
    got = emission_profile(load_config(tmp_path / "c.yaml"))
    assert np.allclose(got.table, E.table([0, 45, 75, 90], [1, 0.9, 0.6, 0.2]).table, rtol=1e-10, atol=0)


def test_a_table_file_that_is_not_a_regular_file_is_named_as_such(tmp_path, minimal_config):
    from fluxcli.config import emission_profile, load_config
    from fluxcli.errors import UserError

    cfg = copy.deepcopy(minimal_config)
    cfg["subject"]["surface"] = {"phantom": "sphere", "radius_mm": 5, "n_latitude": 4, "n_longitude": 6}
    for name, words in (("/dev/null", "not a regular file"), ("nothere.csv", "does not exist"), (".", "folder")):
        cfg["subject"]["emission"] = {"model": "table", "file": name}
        (tmp_path / "c.yaml").write_text(yaml.safe_dump(cfg))
        with pytest.raises(UserError, match=words):
            emission_profile(load_config(tmp_path / "c.yaml"))


def test_a_table_without_a_header_in_0_to_1_is_cos_theta():
    a = E.table_from_csv("1,1\n0.5,0.8\n0,0.1\n", source="p.csv")
    assert np.array_equal(a.table, E.table([1, 0.5, 0], [1, 0.8, 0.1], unit="cos").table)
    assert a.source == "p.csv (no header: the first column read as cos theta)"


@pytest.mark.parametrize("rows,words", [
    ("angle_deg,radiance\n0,1\n95,1\n", "0..90"),
    ("angle_deg,radiance\n0,1\n40,1\n30,1\n", "increase"),
    ("angle_deg,radiance\n0,1\n40,-1\n", "negative"),
    ("angle_deg,radiance\n0,1\n40,nan\n", "finite"),
    ("angle_deg,radiance\n0,1\n40,x\n", "numbers"),
    ("intensity,value\n0,1\n40,1\n", "names neither an angle"),
    ("angle_deg,radiance\n0,0\n40,1\n", "normal"),
    ("angle_deg,radiance\n0,0\n40,0\n", "nothing"),
    ("angle_deg\n0\n", "header"),
])
def test_bad_table_files_say_what_is_wrong(tmp_path, rows, words):
    f = tmp_path / "p.csv"
    f.write_text(rows)
    with pytest.raises(ValueError, match=words):
        E.table_from_csv(f.read_text())


# ------------------------------------------------------------------ in T: closed forms and quadratures
def camera(*, d_focus=200.0, R=10.0, n=64, pitch=0.05, f=25.0):
    return ThinLensCamera.from_pose(lens_center_mm=[0, 0, 0], look=[0, 0, -1], up=(0, 1, 0), focal_length_mm=f,
                                    aperture_radius_mm=R, focus_distance_mm=d_focus, nx=n, ny=n, pixel_pitch_mm=pitch)


def tiny_patch(center, normal=(0, 0, 1), size=0.02):
    return phantoms.patch(size_mm=(size, size), n=(1, 1), center_mm=center, normal=normal)[0]


def collected_by_lens(prof, q, normal, R):
    """Fraction of a small element's power entering a lens disk (radius R, in the plane z = 0,
    axis -z) from point q with the given normal: the integral over the disk of
    p(theta_s) cos(theta_s) cos(theta_l) / r^2 dA (scipy dblquad in polar coordinates)."""
    nrm = np.asarray(normal, float) / np.linalg.norm(normal)

    def f(rho, phi):
        v = np.array([rho * np.cos(phi), rho * np.sin(phi), 0.0]) - q
        r = np.linalg.norm(v)
        cs = float(nrm @ v) / r
        if cs <= 0:
            return 0.0
        cl = -q[2] / r
        return float(prof.p(cs)) * cs * cl / r**2 * rho

    return integrate.dblquad(f, 0, 2 * np.pi, 0, R, epsabs=1e-13, epsrel=1e-9)[0]


def test_on_axis_column_sum_is_the_one_dimensional_integral_of_the_profile():
    """On axis at distance d: 2 int_{mu_min}^1 pi p(mu) mu dmu, mu_min = d / sqrt(R^2 + d^2)
    (Lambertian: R^2 / (R^2 + d^2)); here integrated from the closed-form diffuse radiance."""
    R, d, n = 10.0, 25.0, 1.40  # a wide cone: 22 deg
    prof = E.diffuse(n)
    shape = lambda mu: E.diffuse_radiance(mu, n)  # noqa: E731 - unnormalised closed form
    norm = 2 * integrate.quad(lambda m: shape(m) * m, 0, 1, limit=200)[0]
    mu_min = d / np.hypot(R, d)
    want = 2 * integrate.quad(lambda m: shape(m) * m, mu_min, 1)[0] / norm
    cam = camera(d_focus=200.0, R=R, n=256, pitch=0.1)
    got = build_transfer(tiny_patch([0, 0, -d]), views_for(cam, []), emission=prof).T.sum()
    assert got == pytest.approx(want, rel=5e-3)
    assert want / (R**2 / (R**2 + d**2)) > 1.05  # and it differs from Lambertian by more than the tolerance


@pytest.mark.filterwarnings("ignore::scipy.integrate.IntegrationWarning")  # 1e-9 asked: roundoff only
@pytest.mark.parametrize("estimator", ["lens", "pairwise"])
@pytest.mark.parametrize("q,normal", [((30.0, 0.0, -60.0), (0, 0, 1)),  # off axis, facing the lens plane
                                      ((10.0, 5.0, -40.0), (0.0, 0.94, 0.34))])  # tilted: seen at ~75 deg
def test_column_sum_off_axis_and_tilted_matches_quadrature_with_both_estimators(estimator, q, normal):
    R = 8.0
    prof = E.diffuse(1.40)
    want = collected_by_lens(prof, np.array(q), normal, R)
    lam = collected_by_lens(E.lambertian(), np.array(q), normal, R)
    cam = camera(d_focus=150.0, R=R, n=384, pitch=0.2)
    kw = ({"pairwise_sampling": PairwiseSampling(surface_subdivisions=1, pixel_subdivisions=6)}
          if estimator == "pairwise" else {})
    got = build_transfer(tiny_patch(q, normal), views_for(cam, []), estimator=estimator, emission=prof, **kw).T.sum()
    assert got == pytest.approx(want, rel=5e-3)
    assert abs(want / lam - 1) > 0.02  # the profile matters here


def test_a_flat_table_gives_the_lambertian_T():
    cam = camera(d_focus=120.0, R=6.0, n=48, pitch=0.1)
    subject = phantoms.patch(size_mm=(4, 4), n=(2, 2), center_mm=[0.5, 0.2, -110.0], normal=[0.4, 0, 1])[0]
    lam = build_transfer(subject, views_for(cam, [])).T.toarray()
    flat = build_transfer(subject, views_for(cam, []), emission=E.table([0, 90], [5, 5])).T.toarray()
    assert flat == pytest.approx(lam, rel=1e-12, abs=1e-18)
    explicit = build_transfer(subject, views_for(cam, []), emission=E.lambertian()).T.toarray()
    assert np.array_equal(explicit, lam)


def test_mirror_view_weighs_rays_by_the_angle_at_the_real_surface():
    """A mirror view of a tilted patch with the diffuse profile equals the direct view of the
    reflected patch (emission angles are preserved by the reflection), and both differ from
    Lambertian by the profile's weight at that angle."""
    cam = camera(d_focus=180.0, R=6.0, n=96, pitch=0.08)
    mirror = PlaneMirror.from_axis([0, 20.0, -135.0], [0, -1, 1], [1, 0, 0], (200.0, 200.0))
    subject = phantoms.patch(size_mm=(3, 2), n=(1, 1), center_mm=[2.0, -10.0, -150.0], normal=[0, 1, 0.3])[0]
    Rm = np.eye(3) - 2 * np.outer(mirror.normal, mirror.normal)
    reflected = subject.transformed(Rm, 2 * np.dot(mirror.center_mm, mirror.normal) * mirror.normal)
    prof = E.diffuse(1.40)
    via_mirror = build_transfer(subject, views_for(cam, [("m", mirror, 1.0)])[1:], emission=prof).T.sum()
    direct = build_transfer(reflected, views_for(cam, []), emission=prof).T.sum()
    lam = build_transfer(subject, views_for(cam, [("m", mirror, 1.0)])[1:]).T.sum()
    assert via_mirror == pytest.approx(direct, rel=1e-4)
    # the ray leaves the real patch at theta_s: the ratio to Lambertian is the profile's weight there
    c = subject.element_centroids_mm[0]
    to_lens = mirror.reflect_points(np.zeros((1, 3)))[0] - c
    cos_s = subject.face_normals[0] @ to_lens / np.linalg.norm(to_lens)
    assert via_mirror / lam == pytest.approx(float(prof.weight(cos_s)), rel=5e-3)


def test_pairwise_and_lens_converge_with_a_non_lambertian_profile():
    cam = camera(d_focus=100.0, R=5.0, n=48, pitch=0.05, f=25.0)
    subject = phantoms.patch(size_mm=(1.5, 1.5), n=(2, 2), center_mm=[0.3, 0.1, -110.0], normal=[1.5, 0, 1])[0]
    prof = E.diffuse(1.40)
    lens = build_transfer(subject, views_for(cam, []), emission=prof,
                          lens_sampling=LensSampling(surface_samples_per_pixel=6, lens_samples_min=512,
                                                     lens_samples_max=4096)).T.toarray()
    errs = []
    for ns, npx in ((4, 2), (14, 7)):
        pw = build_transfer(subject, views_for(cam, []), estimator="pairwise", emission=prof,
                            pairwise_sampling=PairwiseSampling(surface_subdivisions=ns, pixel_subdivisions=npx)).T.toarray()
        errs.append(np.abs(pw - lens).sum() / lens.sum())
    assert errs[1] < 0.01 and errs[1] < errs[0]


# ------------------------------------------------------------------ the config key, the cache key, bad input
def _keys(write_config, cfg, name):
    from fluxcli import artefacts as A
    from fluxcli.config import load_config
    from fluxcli.stages.plans import geometry_of, plan

    c = load_config(write_config(cfg, name=name))
    return [pt.key for _, pt in plan(c)[2]], A.cache_key(geometry_of(c))


def test_explicit_lambertian_keeps_the_keys_and_other_models_change_them(write_config, minimal_config, tmp_path):
    cfg = copy.deepcopy(minimal_config)
    absent = _keys(write_config, cfg, "a.yaml")
    seen = {}
    (tmp_path / "flat.csv").write_text("angle_deg,radiance\n0,1\n90,1\n")
    (tmp_path / "diffuse140.csv").write_text("angle_deg,radiance\n" + "".join(
        f"{a},{r}\n" for a, r in zip(range(91), E.diffuse(1.40).radiance(np.radians(np.arange(91))))))
    for name, em in [("lam", {"model": "lambertian"}), ("d140", {"model": "diffuse"}),
                     ("d140b", {"model": "diffuse", "refractive_index": 1.40}),
                     ("d137", {"model": "diffuse", "refractive_index": 1.37}),
                     ("flat", {"model": "table", "file": "flat.csv"}),
                     ("tab", {"model": "table", "file": "diffuse140.csv"})]:
        cfg["subject"]["emission"] = em
        seen[name] = _keys(write_config, cfg, f"{name}.yaml")
    assert seen["lam"] == absent  # T cache key and geometry digest as before emission profiles
    assert seen["d140"] == seen["d140b"]  # 1.40 is the default index
    others = [seen[k] for k in ("d140", "d137", "flat", "tab")]
    for a in range(len(others)):
        assert others[a][0] != absent[0] and others[a][1] != absent[1]
        for b in range(a):
            assert others[a][0] != others[b][0] and others[a][1] != others[b][1]


def _cli(*args):
    from typer.testing import CliRunner

    from fluxcli.cli import app

    return CliRunner().invoke(app, [str(a) for a in args])


@pytest.mark.parametrize("em,words", [
    ({"model": "table", "file": "missing.csv"}, ["subject.emission.file", "missing.csv", "does not exist"]),
    ({"model": "table", "file": "bad.csv"}, ["subject.emission.file", "bad.csv", "negative"]),
    ({"model": "diffuse", "refractive_index": 0.5}, ["subject.emission", "refractive_index"]),
    ({"model": "phong"}, ["subject.emission"]),
])
def test_bad_emission_settings_exit_2_naming_the_key_or_file(write_config, minimal_config, tmp_path, em, words):
    (tmp_path / "bad.csv").write_text("angle_deg,radiance\n0,1\n45,-0.2\n")
    cfg = copy.deepcopy(minimal_config)
    cfg["subject"]["emission"] = em
    r = _cli("build-T", write_config(cfg))
    assert r.exit_code == 2, r.output
    assert "Traceback" not in r.output
    text = " ".join(r.output.split())
    for w in words:
        assert w in text, (w, r.output)


# ------------------------------------------------------------------ through the stages
@pytest.fixture
def patch_config(minimal_config):
    """A flat 6 x 4-element patch tilted 50 deg from the camera, two poses (as test_reconstruct)."""
    cfg = copy.deepcopy(minimal_config)
    cfg["system"]["camera"]["pixels"] = [40, 40]
    cfg["system"]["camera"]["pixel_pitch_mm"] = 0.25
    cfg["subject"]["surface"] = {"phantom": "patch", "size_mm": [24, 16], "n": [6, 4], "center_mm": [0, 0, 10],
                                 "normal": [0, 0.77, 0.64]}
    cfg["subject"]["poses"] = {"heights_mm": [0, 8]}
    cfg["simulate"] = {"flux": {"kind": "gaussian", "width_mm": 6.0, "peak_photons": 1e7, "center_mm": [2, 1, 10]},
                       "noise": {"model": "poisson", "peaks_photons": [1e7], "repeats": 1, "seed": 2}}
    cfg["reconstruct"] = {"method": "nnls"}
    return cfg


def test_stages_use_the_model_store_it_and_report_grazing_shares(write_config, patch_config, tmp_path):
    import h5py

    cfg = copy.deepcopy(patch_config)
    p = write_config(cfg, name="absent.yaml")
    r = _cli("simulate", p)
    assert r.exit_code == 0, r.output
    assert "subject.emission is not set" in " ".join(r.output.split())  # the notice, once
    assert " ".join(r.output.split()).count("subject.emission is not set") == 1
    absent = p
    cfg["subject"]["emission"] = {"model": "diffuse", "refractive_index": 1.40}
    p = write_config(cfg, name="diffuse.yaml")
    # images simulated with another emission model: reconstructed (a model-mismatch experiment), saying so
    r = _cli("reconstruct", p)
    assert r.exit_code == 0, r.output
    text = " ".join(r.output.split())
    assert "simulated with the emission model lambertian and are reconstructed with diffuse" in text, r.output
    # a reconstruction (its T) made with another emission model than the config's is refused, naming both
    r = _cli("report", absent)
    assert r.exit_code == 2, r.output
    text = " ".join(r.output.split())
    assert "subject.emission.model: diffuse in reconstruction.h5, not set now" in text, r.output
    assert _cli("simulate", p, "--quiet").exit_code == 0
    r = _cli("reconstruct", p)
    assert r.exit_code == 0, r.output
    text = " ".join(r.output.split())
    assert "subject.emission is not set" not in text and "model-mismatch" not in text
    assert "emission model: diffuse (refractive index 1.4)" in text
    assert "beyond 60 deg" in text and "beyond 75 deg" in text
    with h5py.File(tmp_path / "run" / "reconstruction.h5") as f:
        assert f["emission"].attrs["model"] == "diffuse"
        assert f["emission"].attrs["refractive_index"] == 1.40
        curve = f["emission/relative_radiance"][()]
        assert curve[0] == 1.0 and curve[np.searchsorted(f["emission/angle_deg"][()], 80.0)] == pytest.approx(0.587, abs=0.01)
        shares = f["per_pose/light_beyond_deg"][()]
        assert shares.shape == (2, 2)
        # the patch is seen ~50 deg from its normal: none of its light beyond 60 deg
        assert np.all(shares < 0.05)
        assert np.all(f["per_pose/total_beyond_deg"][()] < 0.05)
        # the model matches the images: no grazing or structure warning
        assert not any("viewing angle" in w.decode() if isinstance(w, bytes) else "viewing angle" in w
                       for w in f["warnings"][()])
    # the report states the model and draws its curve, from the artefact
    import json

    r = _cli("report", p, "--quiet", "--set", "report.surface_views=false")
    assert r.exit_code == 0, r.output
    summary = json.loads((tmp_path / "run" / "report" / "summary.json").read_text())
    assert summary["emission"]["model"] == "diffuse" and summary["emission"]["refractive_index"] == 1.40
    assert "emission.png" in summary["figures"]
    assert len(summary["emission"]["light_beyond_per_pose"]) == 2
    assert "diffuse (refractive index 1.4)" in (tmp_path / "run" / "report" / "index.html").read_text()


def test_the_report_figure_keeps_its_axes_for_the_longest_model_description(tmp_path):
    """diffuse with every term describes itself in ~160 characters; as the legend label it took
    the axes' width, matplotlib's layout gave up (a UserWarning on the console) and both panels
    were squashed to slivers. The description is now a wrapped title and the legend the model's
    short name: each panel keeps over a third of the figure's width, and no warning is raised."""
    import warnings

    from fluxcli.report import figures as F

    a = np.linspace(0.0, 90.0, 91)
    # the default's terms (squashed without a warning before) and every term (the warning)
    for prof in (E.diffuse(1.40, tangential=True, depth=True, body=True),
                 E.diffuse(1.40, tangential=True, depth=True, curvature=True, body=True)):
        assert len(prof.describe()) > 130
        fig = F.emission_figure(a, prof.radiance(np.radians(a)), prof.describe())
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            F.save(fig, tmp_path / "emission.png")
        assert (tmp_path / "emission.png").stat().st_size > 0
        for ax in fig.axes:
            assert ax.get_position().width > 0.33, (prof.describe(), ax.get_position())
        assert prof.describe().split(" with ")[0] in [t.get_text() for t in fig.axes[0].get_legend().get_texts()]


def test_the_rig_simulated_camera_renders_with_the_emission_model(minimal_config, tmp_path):
    """The simulated camera renders the subject's emission through the forward T: with the
    diffuse profile its image of a cylinder is brighter where the surface faces the camera and
    dimmer at its limbs, by the profile's weights, than the Lambertian one (same total power)."""
    from conftest import cylinder_sim_config

    from fluxcli.config import load_config
    from fluxcli.stages.capture import SimulatedScene

    cfg = cylinder_sim_config(minimal_config)
    cfg["system"]["camera"] |= {"pixels": [32, 32], "pixel_pitch_mm": 0.4}
    cfg["transfer"] = {"cache_dir": str(tmp_path / "Tcache")}
    cfg["rig"] = {"camera": {"backend": "simulated"}}
    cfg["simulate"]["flux"] = {"kind": "uniform", "exitance_photons_per_mm2": 1e4}
    images = {}
    for name in ("lambertian", "diffuse"):
        cfg["subject"]["emission"] = {"model": name}
        p = tmp_path / f"{name}.yaml"
        p.write_text(yaml.safe_dump(cfg))
        images[name] = SimulatedScene(load_config(p)).emission(0.0, "open")
    lam, dif = images["lambertian"], images["diffuse"]
    lit = lam > 0.05 * lam.max()
    ratio = dif[lit] / lam[lit]
    w = E.diffuse(1.40)
    # head-on pixels gain close to pi p(0) = 1.10; pixels holding the limbs (70-90 deg: weights
    # 0.9-0, mixed with nearer faces in these 4.8 mm pixels) gain much less or lose
    assert ratio.max() == pytest.approx(float(w.weight(1.0)), abs=0.02)
    assert ratio.min() < ratio.max() - 0.1


# ------------------------------------------------------------------ the tangential flux
def _g_from_photons(n: float, n_photons: int, seed: int = 5, g_hg: float = 0.0, rho_mm=(3.0, 12.0)):
    """Photons of fluxcli.montecarlo leaving the top of a wide slab (mu_a 0.01, mu_s' 1 /mm:
    isotropic scattering, or Henyey-Greenstein ``g_hg`` at mu_s = 1 / (1 - g_hg) /mm; index n)
    from an isotropic point 6 mm deep: per band of exit angle, the length g the
    photons' own drift implies.  Within 3-12 mm of the source's foot the exitance falls as
    M(rho) (slope -k = d ln M / d rho, fitted to the photons' own exit density); a radiance
    ``M p (1 + g k sin(theta) cos(phi))`` gives a mean radial component of the exit directions
    ``<sin theta cos phi> = g k sin^2(theta) / 2`` per band, so ``g = 2 sum d_r / sum k sin^2``."""
    from fluxcli.montecarlo.transport import Medium, Shape, transport

    top_z = 15.0
    e = transport(Medium(0.01, 1.0 / (1.0 - g_hg), g_hg, n), Shape.box((80, 80, 30)), (0, 0, top_z - 6.0), n_photons,
                  seed=seed)
    p, d = e.position_mm, e.direction
    top = p[:, 2] > top_z - 1e-6
    p, d = p[top], d[top]
    rho = np.hypot(p[:, 0], p[:, 1])
    d_r = np.einsum("ij,ij->i", d[:, :2], p[:, :2] / np.maximum(rho, 1e-12)[:, None])
    edges = np.arange(1.0, 16.01, 0.5)
    count, _ = np.histogram(rho, edges)
    mid, ring = 0.5 * (edges[1:] + edges[:-1]), np.pi * (edges[1:] ** 2 - edges[:-1] ** 2)
    fit = np.polyfit(mid, np.log(count / ring), 3, w=np.sqrt(count))
    k = -np.polyval(np.polyder(fit), rho)
    near = (rho > rho_mm[0]) & (rho < rho_mm[1])
    out = []
    for lo, hi in ((20, 65), (20, 40), (40, 65)):
        b = near & (d[:, 2] <= np.cos(np.radians(lo))) & (d[:, 2] > np.cos(np.radians(hi)))
        s2 = 1 - d[b, 2] ** 2
        g = 2 * d_r[b].sum() / (k[b] * s2).sum()
        sigma = 2 * d_r[b].std() * np.sqrt(b.sum()) / (k[b] * s2).sum()
        out.append((lo, hi, g, sigma, float(np.cos(np.radians((lo + hi) / 2)))))
    return out


@pytest.mark.parametrize("n,n_photons", [(1.40, 500_000), (1.00, 350_000)])
def test_tangential_flux_matches_the_drift_of_monte_carlo_exit_photons(n, n_photons):
    """The light leaving a turbid medium drifts away from where the exitance is higher; the
    model's length g(theta) (emission.tangent_length, through the profile's tables) against
    the drift of the photons of our Monte Carlo.  Without the term g = 0; P1's J_t = -D grad phi
    at the surface gives g short by the factor 1 + 3 mu'/A (~2 at n 1.40, ~3.5 at n 1): both fail."""
    prof = E.diffuse(n, tangential=True, reduced_scattering_per_mm=1.0, absorption_per_mm=0.01)
    for lo, hi, g_mc, sigma, mu in _g_from_photons(n, n_photons):
        g_model = float(prof.tangent_weight(mu) / prof.weight(mu))
        tol = 0.10 if hi - lo > 30 else 0.2  # the photons sit ~7 % above the model at n 1.40, ~2 % at n 1
        assert g_mc == pytest.approx(g_model, rel=tol), (n, lo, hi, g_mc, sigma, g_model)
        assert sigma < tol * g_mc / 2.5  # the photons resolve the agreement the test claims
        mu_in = np.sqrt(1 - (1 - mu * mu) / n**2)
        p1 = 1 / (n * 1.01 * (1 + 3 * mu_in / (2 * E.boundary_A(n))))  # J_t = -D grad phi at the surface
        assert abs(g_mc / p1 - 1) > 3 * tol


def test_forward_scattering_drifts_as_the_delta_eddington_term_says():
    """Henyey-Greenstein g 0.5 at the same mu_s' (1 /mm): the photons' drift against the term told
    the medium's g (scattering_anisotropy: the δ-Eddington ray integral) and against the term
    built for isotropic scattering, which overstates it by a sixth (docs/design.md: beyond 5 mm
    the drift falls from ~0.91 mm at g 0 to ~0.78 at g 0.5 and ~0.72 at g 0.9), 5-12 mm from the
    source's foot (nearer, the light drifts further whatever g: the third-order term of
    docs/design.md, not modelled). 2 × 10⁶ photons (~25 s)."""
    told = E.diffuse(1.40, tangential=True, reduced_scattering_per_mm=1.0, absorption_per_mm=0.01,
                     scattering_anisotropy=0.5)
    isotropic = E.diffuse(1.40, tangential=True, reduced_scattering_per_mm=1.0, absorption_per_mm=0.01)
    lo, hi, g_mc, sigma, mu = _g_from_photons(1.40, 2_000_000, g_hg=0.5, rho_mm=(5.0, 12.0))[0]  # 20-65 deg
    g_told = float(told.tangent_weight(mu) / told.weight(mu))
    g_iso = float(isotropic.tangent_weight(mu) / isotropic.weight(mu))
    assert g_mc == pytest.approx(g_told, rel=0.06), (g_mc, sigma, g_told)
    assert g_iso > 1.1 * g_mc and sigma < 0.025 * g_mc, (g_mc, sigma, g_iso)


def _ray_integral(mu_in: float, g_star: float, zb: float, c: float = 0.0, grad: float = 0.0) -> float:
    """The radiance reaching the surface from inside along a ray at cosine ``mu_in`` to the
    normal, by quadrature (lengths in l = 1 / mu_s'; mu_a neglected beside mu_s'): the δ-Eddington
    source ``mu_s* (phi + 3 g* J . s) / 4pi`` (dropping the 4pi) integrated back along the ray with
    ``e^{-mu_s* t}``, mu_s* = 1 / (1 - g*), in the field ``phi = (z + z_b)(1 + grad x) + c z_b (z^2/2 +
    z^3 / 6 z_b)`` (z depth, x along the ray's tangential direction; phi(0) = z_b) and J = -grad(phi) / 3."""
    mus = 1.0 / (1.0 - g_star)
    st = np.sqrt(1.0 - mu_in**2)

    def source(t):
        z, x = t * mu_in, -t * st  # back along the ray: deeper, and behind it sideways
        phi = (z + zb) * (1.0 + grad * x) + c * (zb * z * z / 2 + z**3 / 6)
        dphi_dz = (1.0 + grad * x) + c * (zb * z + z * z / 2)
        dphi_dx = (z + zb) * grad
        j_dot_s = (dphi_dz * mu_in - dphi_dx * st) / 3.0  # J = -grad phi / 3; s = (x: +st, depth: -mu_in)
        return mus * (phi + 3 * g_star * j_dot_s) * np.exp(-mus * t)

    return integrate.quad(source, 0.0, np.inf, epsabs=0, epsrel=1e-11, limit=400)[0]


@pytest.mark.parametrize("g", [0.0, 0.5, 0.9])
@pytest.mark.parametrize("n", [1.0, 1.40])
def test_the_anisotropic_terms_are_the_delta_eddington_ray_integral(g, n):
    """tangent_length and the depth term with scattering_anisotropy g against the ray integral
    done by quadrature with the δ-Eddington source (g* = g / (1 + g), Joseph et al. 1976): the
    tangential part over the normal part is the drift length, the normal part with the fluence's
    curvature the depth term.  g 0 is the isotropic derivation the photons checked; for g > 0 the
    normal profile without the depth term stays P1's (similarity)."""
    A = E.boundary_A(n)
    zb, gs, c = 2 * A / 3, g / (1 + g), 0.06
    assert E.delta_eddington_g(g) == pytest.approx(gs)
    for theta in (0.0, 30.0, 60.0, 80.0):
        mu_out = np.cos(np.radians(theta))
        mu_in = np.sqrt(1 - (1 - mu_out**2) / n**2)
        base = _ray_integral(mu_in, gs, zb)
        assert base == pytest.approx(zb + mu_in, rel=1e-9)  # P1's normal part, whatever g
        if theta > 0:  # head-on the ray has no tangential part to drift along
            # the tangential part per unit of s_in,t . grad m (|s_in,t| = sin theta'); through the
            # surface s_in,t = s_out,t / n, so the length outside is (tilt / base) l / n
            tilt = (base - _ray_integral(mu_in, gs, zb, grad=1e-3)) / 1e-3 / np.sqrt(1 - mu_in**2)
            model = float(E.tangent_length(mu_out, n, 1.0, g))
            assert model == pytest.approx(tilt / base / n, rel=1e-6), (g, n, theta)
        deep = _ray_integral(mu_in, gs, zb, c=c)
        ratio = E.diffuse_radiance(mu_out, n, c, g) / E.diffuse_radiance(mu_out, n, 0.0)
        assert float(ratio) == pytest.approx(deep / base, rel=1e-9), (g, n, theta)
    with pytest.raises(ValueError, match="scattering_anisotropy"):
        E.delta_eddington_g(1.0)


def tiny_triangle(center, normal, size=0.02):
    """One triangle (one element, one face frame) centred at ``center`` facing ``normal``."""
    from fluxcli.surface.mesh import Surface

    nrm = np.asarray(normal, float) / np.linalg.norm(normal)
    u = np.cross(nrm, [1.0, 0, 0] if abs(nrm[0]) < 0.9 else [0, 1.0, 0])
    u /= np.linalg.norm(u)
    v = np.cross(nrm, u)
    pts = np.asarray(center, float) + size * np.array([u, -0.5 * u + 0.87 * v, -0.5 * u - 0.87 * v])
    return Surface(pts, np.array([[0, 1, 2]]), np.array([0]), 1)


@pytest.mark.parametrize("estimator", ["lens", "pairwise"])
def test_tangential_columns_are_g_times_the_direction_leaving_the_surface(estimator):
    """A small tilted triangle: the tangential matrix summed over pixels over T's column sum is
    g(theta_s) times the in-plane components of the unit vector from it to the lens (a closed
    form); the scalar T is the same to the bit with and without the term; Lambertian and table
    profiles have none."""
    q, nrm = np.array([30.0, 10.0, -60.0]), np.array([0.0, 0.3, 1.0]) / np.hypot(0.3, 1.0)
    cam = camera(d_focus=150.0, R=2.0, n=384, pitch=0.2)
    kw = ({"pairwise_sampling": PairwiseSampling(surface_subdivisions=1, pixel_subdivisions=4)}
          if estimator == "pairwise" else {})
    subject = tiny_triangle(q, nrm)
    assert np.allclose(subject.face_normals[0], nrm)
    on = E.diffuse(1.40, tangential=True, reduced_scattering_per_mm=0.8, absorption_per_mm=0.05)
    r = build_transfer(subject, views_for(cam, []), estimator=estimator, emission=on, **kw)
    s = -q / np.linalg.norm(q)
    mu_in = np.sqrt(1 - (1 - (nrm @ s) ** 2) / 1.40**2)
    A = E.boundary_A(1.40)
    g = (1 + 3 * mu_in / A) / (1.40 * 0.85 * (1 + 3 * mu_in / (2 * A)))
    e = E.face_frames(subject.face_vertices_mm)[0]
    assert np.allclose(e @ e.T, np.eye(2)) and np.allclose(e @ nrm, 0)
    got = np.asarray(r.T_tangent.sum(axis=0)).ravel() / r.T.sum()
    assert got == pytest.approx(g * (e @ s), abs=3e-3 * g)
    off = build_transfer(subject, views_for(cam, []), estimator=estimator, emission=E.diffuse(1.40), **kw)
    assert off.T_tangent is None and np.array_equal(off.T.toarray(), r.T.toarray())
    for prof in (E.lambertian(), E.table([0, 90], [1, 0.5])):
        assert build_transfer(subject, views_for(cam, []), estimator=estimator, emission=prof,
                              **kw).T_tangent is None


def test_tangential_columns_of_a_mirror_view_follow_the_ray_leaving_the_real_surface():
    cam = camera(d_focus=180.0, R=4.0, n=96, pitch=0.08)
    mirror = PlaneMirror.from_axis([0, 20.0, -135.0], [0, -1, 1], [1, 0, 0], (200.0, 200.0))
    subject = tiny_triangle([2.0, -10.0, -150.0], (0, 1, 0.3), size=0.05)
    prof = E.diffuse(1.40, tangential=True)
    r = build_transfer(subject, views_for(cam, [("m", mirror, 0.9)])[1:], emission=prof)
    c = subject.element_centroids_mm[0]
    s = mirror.reflect_points(np.zeros((1, 3)))[0] - c  # towards the mirror image of the lens
    s /= np.linalg.norm(s)
    g = float(prof.tangent_weight(subject.face_normals[0] @ s) / prof.weight(subject.face_normals[0] @ s))
    e = E.face_frames(subject.face_vertices_mm)[0]
    got = np.asarray(r.T_tangent.sum(axis=0)).ravel() / r.T.sum()
    assert got == pytest.approx(g * (e @ s), abs=3e-3 * g)


def test_tangential_values_do_not_depend_on_the_pose():
    """T_tangent is held in each face's own frame: the subject and the lens turned together
    give the same numbers (what lets one tangent operator of the subject's surface serve every pose)."""
    from scipy.spatial.transform import Rotation

    prof = E.diffuse(1.40, tangential=True)
    subject = tiny_triangle([0.0, 0.0, -80.0], (0.2, 0.4, 1.0), size=0.5)
    a = build_transfer(subject, views_for(camera(d_focus=80.0, R=3.0, n=64, pitch=0.1), []), emission=prof)
    R = Rotation.from_rotvec([0.3, -0.5, 0.2]).as_matrix()
    turned = subject.transformed(R, np.zeros(3))
    cam = ThinLensCamera.from_pose(lens_center_mm=[0, 0, 0], look=R @ [0, 0, -1], up=R @ [0, 1, 0], focal_length_mm=25.0,
                                   aperture_radius_mm=3.0, focus_distance_mm=80.0, nx=64, ny=64, pixel_pitch_mm=0.1)
    b = build_transfer(turned, views_for(cam, []), emission=prof)
    assert a.T_tangent.sum() != 0
    assert np.abs((a.T_tangent - b.T_tangent).toarray()).max() < 1e-6 * np.abs(a.T_tangent.toarray()).max()


def test_tangent_operator_gives_the_surface_gradient_of_a_linear_exitance():
    """Vertex unknowns of an exitance linear in space (u_v = M(r_v) A_v): the operator gives
    -S_f grad_t M on every fine face (the in-plane part of the gradient, per face of a box)."""
    surf = phantoms.box(size_mm=(6, 8, 4), element_mm=2.0)[0]
    vb = surf.vertex_basis(1)
    G = E.tangent_operator(surf, 1)
    a = np.array([0.3, -0.2, 0.5])
    u = (surf.vertices_mm[vb.vertex_index] @ a + 2.0) * vb.areas_mm2
    fine = vb.fine
    ok = fine.element_of_face >= 0
    nrm, S = fine.face_normals[ok], fine.face_areas_mm2[ok]
    frames = E.face_frames(fine.face_vertices_mm[ok])
    want = -S[:, None] * np.einsum("j,iaj->ia", a, frames)  # the in-plane components of grad M
    assert np.allclose(np.einsum("iaj,ij->ia", frames, nrm), 0)
    assert G.shape == (2 * ok.sum(), vb.n_vertices)
    assert np.abs((G @ u).reshape(-1, 2) - want).max() < 1e-12
    assert np.abs(G @ vb.areas_mm2).max() < 1e-12  # a uniform exitance: no gradient, no term


def test_the_tangential_term_is_in_the_key_only_when_on():
    on, off = E.diffuse(1.40, tangential=True), E.diffuse(1.40)
    assert "tangent_sha256" in on.key() and "tangent_sha256" not in off.key()
    assert {k: v for k, v in on.key().items() if not k.startswith("tangent")} == off.key()
    assert E.diffuse(1.40, tangential=True, reduced_scattering_per_mm=2.0).key() != on.key()
    assert E.profile({"model": "diffuse", "refractive_index": 1.4}).has_tangent  # the config's default
    assert not E.profile({"model": "diffuse", "tangential_flux": False}).has_tangent


def test_vertex_unknowns_take_the_tangential_term_from_the_cached_T(write_config, patch_config, tmp_path):
    """build-T keeps T_tangent beside T (diffuse, term on: the config's default) and it is a
    correction of T per vertex, T_tangent @ G (off: no T_tangent, tested on T itself above)."""
    import glob

    import h5py

    from fluxcli.artefacts.transfer import load_T, load_T_tangent
    from fluxcli.config import load_config
    from fluxcli.stages.plans import placer_of

    cfg = copy.deepcopy(patch_config)
    cfg["subject"]["emission"] = {"model": "diffuse", "refractive_index": 1.40}
    cfg["reconstruct"] = {"method": "smooth", "unknowns": "vertices", "joint": False}
    p = write_config(cfg, name="on.yaml")
    assert _cli("simulate", p, "--quiet").exit_code == 0
    r = _cli("reconstruct", p)
    assert r.exit_code == 0, r.output
    files = glob.glob(str(tmp_path / "run" / "cache" / "T" / "*.h5"))
    fine = [f for f in files if h5py.File(f, "r")["surface/faces"].shape[0] == 4 * 48]  # refined once: 4 x 48 faces
    assert fine and all(load_T_tangent(f) is not None for f in fine)
    surf = placer_of(load_config(p)).surface
    vb = surf.vertex_basis(1)
    G = E.tangent_operator(surf, 1)
    T, Tt = load_T(fine[0]), load_T_tangent(fine[0])
    assert Tt.shape == (T.shape[0], 2 * T.shape[1]) and G.shape == (Tt.shape[1], vb.n_vertices)
    extra = Tt @ G
    assert 0.01 < np.abs(extra).sum() / (T @ vb.to_fine).sum() < 0.5  # the term acts, as a correction


def test_the_tangential_term_tilts_a_hat_s_light_but_never_adds_to_it():
    """A hat's column of T per vertex (scalar + tangential) can go negative at its rim; the
    solvers need T >= 0, and the column must still send the camera the light the signed model
    says: clipping alone added 2.4-3.1 % of T's mass at 45-60 deg on issue 21's box and read
    every oblique total that much low."""
    import scipy.sparse as sp

    from fluxcli.inverse.unknowns import VertexMap

    rng = np.random.default_rng(3)
    n_pix, n_fine, n_v = 400, 60, 20
    T_fine = sp.random_array((n_pix, n_fine), density=0.2, rng=rng, format="csr")
    to_fine = sp.random_array((n_fine, n_v), density=0.3, rng=rng, format="csr")
    T_tan = sp.random_array((n_pix, 2 * n_fine), density=0.2, rng=rng, format="csr")
    T_tan.data -= 0.5  # the term takes light from some pixels and gives it to others
    G = sp.random_array((2 * n_fine, n_v), density=0.3, rng=rng, format="csr")
    G.data -= 0.5
    vm = VertexMap(to_fine, None, None, None, None, tangent=sp.csr_array(G))
    signed = (T_fine @ to_fine + T_tan @ G).toarray()
    assert (signed < 0).sum() > 50  # the case that matters: many negative entries
    T = vm.unknowns_T(T_fine, T_tan).toarray()
    assert T.min() >= 0.0
    np.testing.assert_allclose(T.sum(axis=0), np.maximum(signed.sum(axis=0), 0.0), rtol=1e-12)
    # where the signed entry was positive, T keeps its shape (one scale per column)
    ratio = np.where(signed > 0, T / np.where(signed > 0, signed, 1.0), np.nan)
    np.testing.assert_allclose(np.nanmax(ratio, axis=0), np.nanmin(ratio, axis=0), rtol=1e-12)
    assert np.nanmax(ratio) < 1.0  # clipping alone would have kept them at 1 and added light


def test_a_resumed_build_gives_the_same_tangential_values(tmp_path, monkeypatch):
    """The partial files of a long build keep the tangential values too: a build that reads
    its blocks back makes the same T_tangent as the one that cast them."""
    from fluxcli.transfer_cache import PartialFiles

    cam = camera(d_focus=120.0, R=6.0, n=48, pitch=0.1)
    subject = phantoms.patch(size_mm=(4, 4), n=(2, 2), center_mm=[0.5, 0.2, -110.0], normal=[0.4, 0, 1])[0]
    prof = E.diffuse(1.40, tangential=True)
    kw = dict(emission=prof, rays_per_batch=2000, threads=1)
    a = build_transfer(subject, views_for(cam, []), checkpoint=PartialFiles(tmp_path, "k", rays_per_block=4000), **kw)
    saved = list((tmp_path / "k.part").glob("*.npz"))
    assert len(saved) > 1
    from fluxcli.optics import transfer_kernel

    def no_cast(*args):
        raise AssertionError("cast again: the partial files were not read")

    monkeypatch.setattr(transfer_kernel, "lens_columns", no_cast)
    b = build_transfer(subject, views_for(cam, []), checkpoint=PartialFiles(tmp_path, "k", rays_per_block=4000), **kw)
    assert a.T_tangent.nnz > 0 and np.array_equal(a.T_tangent.toarray(), b.T_tangent.toarray())
    assert np.array_equal(a.T.toarray(), b.T.toarray())


def test_simulate_s_tangential_light_is_the_gradient_of_a_linear_truth():
    """simulate adds T_tangent @ tangent_light(fine truth): for an exitance linear in space, on
    every fine face of a box (edges and corners included), -S_f times its in-plane gradient."""
    surf = phantoms.box(size_mm=(12, 16, 8), element_mm=2.0)[0]
    fine = surf.refined(1)[0]
    a = np.array([0.3, -0.2, 0.5])
    power = (fine.face_vertices_mm.mean(axis=1) @ a + 5.0) * fine.face_areas_mm2
    got = E.tangent_light(fine, power).reshape(-1, 2)
    want = -fine.face_areas_mm2[:, None] * np.einsum("j,iaj->ia", a, E.face_frames(fine.face_vertices_mm))
    assert np.abs(got - want).max() < 1e-12 * np.abs(want).max() + 1e-14
    assert np.abs(E.tangent_light(fine, 3.0 * fine.face_areas_mm2)).max() < 1e-12  # uniform: none


# ------------------------------------------------------------------ the curvature term
@pytest.mark.parametrize("unknowns,gain", [("vertices", 0.95), ("elements", 1.0)])
def test_simulate_and_reconstruct_carry_the_curvature_term(write_config, patch_config, tmp_path, unknowns, gain):
    """subject.emission.curvature_term: simulate bends each element's profile by its truth's
    lap M / M (the Gaussian spot: over its centre more light along the normal, where the patch
    is seen from, 15 deg off it); reconstruct solves once with the profile, then again with it
    bent by its own solution's curvature, and on those images reads closer to the truth than
    without the term."""
    import h5py

    cfg = copy.deepcopy(patch_config)
    cfg["subject"]["surface"]["normal"] = [0, 0.26, 0.97]  # seen ~15 deg from its normal
    # 2-mm elements: the term moves light within the spot only (kappa has no mean over the patch), so
    # the spot must span a few elements for the second pass to see its curvature
    cfg["subject"]["surface"]["n"] = [12, 8]
    cfg["subject"]["emission"] = {"model": "diffuse", "refractive_index": 1.40}
    cfg["reconstruct"] = {"method": "smooth", "unknowns": unknowns}
    cfg["workdir"] = "plain"
    plain = write_config(cfg, name="plain.yaml")
    cfg["subject"]["emission"]["curvature_term"] = True
    cfg["workdir"] = "run"
    curv = write_config(cfg, name="curv.yaml")
    for p in (plain, curv):
        r = _cli("simulate", p, "--quiet")
        assert r.exit_code == 0, r.output
    with h5py.File(tmp_path / "plain" / "simulation.h5") as f:
        a0 = f["images/noiseless"][0]
    with h5py.File(tmp_path / "run" / "simulation.h5") as f:
        a1 = f["images/noiseless"][0]
        truth = f["truth/power"][()]
    change = np.abs(a1 - a0).sum() / a0.sum()
    assert 0.005 < change < 0.05, change  # 1 % of the light moved
    # the rig's simulated camera renders the same light (its own units: a constant factor)
    from fluxcli.config import load_config
    from fluxcli.stages.capture import SimulatedScene

    rig = copy.deepcopy(cfg) | {"rig": {"camera": {"backend": "simulated"}}}
    frame = SimulatedScene(load_config(write_config(rig, name="rig.yaml"))).emission(0.0, "open")
    lit = a1[0] > 1e-3 * a1[0].max()
    scale = frame[lit] / a1[0][lit]
    np.testing.assert_allclose(scale, np.median(scale), rtol=1e-5)
    r = _cli("reconstruct", curv)
    assert r.exit_code == 0, r.output
    assert "curvature term: each solve is made again" in " ".join(r.output.split())
    with h5py.File(tmp_path / "run" / "reconstruction.h5") as f:
        err_on = np.abs(f["flux/power"][()] - truth).sum() / truth.sum()
    cfg["subject"]["emission"]["curvature_term"] = False  # the same images, read without the term
    import shutil

    shutil.copytree(tmp_path / "run", tmp_path / "off", ignore=shutil.ignore_patterns("reconstruction*"))
    cfg["workdir"] = "off"
    r = _cli("reconstruct", write_config(cfg, name="off.yaml"), "--force")
    assert r.exit_code == 0, r.output
    with h5py.File(tmp_path / "off" / "reconstruction.h5") as f:
        err_off = np.abs(f["flux/power"][()] - truth).sum() / truth.sum()
    # vertices: 2.14 % against 2.32 % (2-mm elements, 6-mm spot); elements: 3.89 % against 4.16 % (their steps)
    assert err_on < gain * err_off, (err_on, err_off)
