"""The forward model against closed forms it was not built from (DESIGN.md section 3)."""

from __future__ import annotations

import numpy as np
import pytest

from fluxcli.optics.camera import Aperture, PlaneMirror, ThinLensCamera, sunflower_disk
from fluxcli.optics.transfer import LensSampling, PairwiseSampling, build_transfer, views_for
from fluxcli.surface import phantoms
from fluxcli.surface.mesh import Surface, rectangle


def camera(*, d_focus=200.0, R=10.0, n=64, pitch=0.05, f=25.0, apertures=(), up=(0, 1, 0)):
    """A camera at z = 0 looking down -z, focused d_focus in front of it."""
    return ThinLensCamera.from_pose(lens_center_mm=[0, 0, 0], look=[0, 0, -1], up=up, focal_length_mm=f,
                                    aperture_radius_mm=R, focus_distance_mm=d_focus, nx=n, ny=n,
                                    pixel_pitch_mm=pitch, apertures=apertures)


def tiny_patch(center, normal=(0, 0, 1), size=0.02):
    return phantoms.patch(size_mm=(size, size), n=(1, 1), center_mm=center, normal=normal)[0]


def view_factor_offset(H, X, R):
    """Differential element facing a coaxial-parallel disk of radius R at axial distance H,
    offset X sideways (standard radiative-transfer result)."""
    return 0.5 * (1 - (H**2 + X**2 - R**2) / np.sqrt((H**2 + X**2 + R**2) ** 2 - 4 * R**2 * X**2))


def colsum(surface, cam, **kw):
    return np.asarray(build_transfer(surface, views_for(cam, []), **kw).T.sum(axis=0)).ravel()


# ------------------------------------------------------------------ view factors
@pytest.mark.parametrize("d", [20.0, 60.0, 200.0, 500.0])
def test_on_axis_column_sum_is_view_factor_to_lens(d):
    R = 10.0
    cam = camera(d_focus=200.0, R=R, n=256, pitch=0.1)
    got = colsum(tiny_patch([0, 0, -d]), cam)[0]
    want = R**2 / (R**2 + d**2)
    assert got == pytest.approx(want, rel=5e-3)


@pytest.mark.parametrize("H,X", [(100.0, 30.0), (50.0, 25.0), (300.0, 60.0)])
def test_offset_column_sum_is_view_factor_to_lens(H, X):
    R = 8.0
    cam = camera(d_focus=150.0, R=R, n=512, pitch=0.2)
    got = colsum(tiny_patch([X, 0, -H]), cam)[0]
    assert got == pytest.approx(view_factor_offset(H, X, R), rel=5e-3)


def test_pairwise_estimator_also_gives_the_view_factor_out_of_focus():
    R, d = 10.0, 120.0
    cam = camera(d_focus=200.0, R=R, n=128, pitch=0.05)
    got = colsum(tiny_patch([0, 0, -d]), cam, estimator="pairwise",
                 pairwise_sampling=PairwiseSampling(surface_subdivisions=1, pixel_subdivisions=4))[0]
    assert got == pytest.approx(R**2 / (R**2 + d**2), rel=5e-3)


def test_extra_aperture_limits_the_cone_to_its_own_view_factor():
    """An opening of radius rho at distance a in front of the lens, smaller than the cone the
    lens accepts, makes the collected fraction the view factor to the opening itself."""
    R, d, a, rho = 10.0, 200.0, 100.0, 2.0  # the lens cone is 5 mm across at the opening
    cam = camera(R=R, n=256, pitch=0.1, apertures=(Aperture(a, rho),))
    got = colsum(tiny_patch([0, 0, -d]), cam)[0]
    assert got == pytest.approx(rho**2 / (rho**2 + (d - a) ** 2), rel=5e-3)


# ------------------------------------------------------------------ imaging
def test_point_in_focal_plane_lands_in_one_pixel():
    cam = camera(d_focus=200.0, R=10.0, n=64, pitch=0.05)
    p = cam.focal_pixel_mm
    for col, row in [(32, 32), (10, 50), (63, 0)]:
        # the centre of pixel (row, col) in the focal plane; image row grows along -y (down)
        x = (col + 0.5 - 32) * p
        y = -(row + 0.5 - 32) * p
        T = build_transfer(tiny_patch([x, y, -200.0], size=1e-3), views_for(cam, [])).T
        assert T.nnz == 1
        assert T.indices[0] == 0 and np.flatnonzero(np.diff(T.indptr))[0] == row * 64 + col


def test_defocused_point_spreads_over_the_thin_lens_blur_disk_conserving_power():
    f, R, u = 25.0, 6.0, 200.0
    cam = camera(f=f, R=R, d_focus=u, n=160, pitch=0.01)
    z = 150.0  # the point is nearer than the focal plane
    v = f * u / (u - f)
    v_p = f * z / (z - f)
    D_detector = 2 * R * abs(v_p - v) / v_p  # closed-form blur diameter on the detector
    res = build_transfer(tiny_patch([0, 0, -z], size=1e-3), views_for(cam, []),
                         lens_sampling=LensSampling(lens_samples_min=4096, lens_samples_max=8192))
    a = res.T.toarray()[:, 0].reshape(160, 160)
    rows, cols = np.indices(a.shape)
    # second moment of a uniform disk of radius rho is rho^2 / 2 (per axis rho^2 / 4)
    w = a / a.sum()
    rc, cc = (w * rows).sum(), (w * cols).sum()
    m2 = (w * ((rows - rc) ** 2 + (cols - cc) ** 2)).sum() - 2 / 12  # remove pixel-box variance
    rho_px = np.sqrt(2 * m2)
    assert 2 * rho_px * cam.pixel_pitch_mm == pytest.approx(D_detector, rel=0.02)
    assert np.count_nonzero(a) == pytest.approx(np.pi / 4 * (D_detector / 0.01) ** 2, rel=0.1)
    assert a.sum() == pytest.approx(R**2 / (R**2 + z**2), rel=5e-3)


def test_lens_samples_are_equal_area_on_the_unit_disk():
    pts = sunflower_disk(4000)
    r2 = (pts**2).sum(axis=1)
    assert r2.max() <= 1
    assert r2.mean() == pytest.approx(0.5, rel=1e-3)  # E[r^2] of the uniform disk


# ------------------------------------------------------------------ occlusion
def test_far_side_of_a_sphere_gets_exactly_zero_and_the_near_side_is_unoccluded():
    """Focal plane through the sphere's centre: testing visibility towards r_vd (inside the
    sphere) instead of the lens point would wrongly hide the near side (the paper's fix)."""
    R = 5.0
    cam = camera(d_focus=100.0, R=R, n=48, pitch=0.2)
    sph, _, _ = phantoms.sphere(radius_mm=10.0, n_latitude=12, n_longitude=24)
    sph = sph.transformed(np.eye(3), np.array([0, 0, -100.0]))
    T = build_transfer(sph, views_for(cam, [])).T
    col = np.asarray(T.sum(axis=0)).ravel()
    # lens points on the rim; an element faces away when every corner sees every rim point from behind
    rim = cam.lens_points(np.stack([np.cos(np.linspace(0, 2 * np.pi, 64)), np.sin(np.linspace(0, 2 * np.pi, 64))], 1))
    tri = sph.face_vertices_mm
    nrm = sph.face_normals
    facing = np.einsum("fk,fcrk->fcr", nrm, rim[None, None] - tri[:, :, None])
    away = np.zeros(sph.n_elements, bool)
    toward = np.zeros(sph.n_elements, bool)
    for e in range(sph.n_elements):
        fe = facing[sph.element_of_face == e]
        away[e] = np.all(fe < 0)
        toward[e] = np.all(fe > 0)
    assert away.sum() > 50 and toward.sum() > 20
    assert np.all(col[away] == 0.0)
    # convex: elements facing every lens point cannot be hidden; same T as with nothing to block
    parts = []  # each such element alone: nothing else to block it
    for e in np.flatnonzero(toward):
        faces = sph.faces[sph.element_of_face == e]
        single = Surface(sph.vertices_mm, faces, np.zeros(len(faces), np.int64), 1)
        parts.append(colsum(single, cam)[0])
    assert np.allclose(col[toward], parts, rtol=1e-9, atol=0)


def test_an_occluder_between_patch_and_lens_blocks_exactly_its_shadow():
    """An opaque half-plane just in front of the lens, covering x < 0, hides the half of the
    lens disk behind it: the patch on axis then collects half the view factor."""
    R, d = 10.0, 300.0
    cam = camera(d_focus=200.0, R=R, n=256, pitch=0.1)
    blocker = rectangle([-50.0, 0, -1.0], [1, 0, 0], [0, 1, 0], (100.0, 100.0))
    res = build_transfer(tiny_patch([0, 0, -d]), views_for(cam, []), [blocker],
                         lens_sampling=LensSampling(lens_samples_min=2048))
    got = res.T.sum()
    assert got == pytest.approx(0.5 * R**2 / (R**2 + d**2), rel=1e-2)


# ------------------------------------------------------------------ mirrors
def test_mirror_view_equals_the_direct_view_of_the_reflected_scene():
    """Reciprocity: the virtual camera must see exactly what the real camera sees of the
    scene reflected in the mirror plane.  The two builds sample the (reflected) faces with
    differently ordered corners, so they agree to quadrature accuracy, per element and per
    pixel, and the pixel-level difference shrinks under refinement."""
    cam = camera(d_focus=180.0, R=6.0, n=96, pitch=0.08)
    mirror = PlaneMirror.from_axis([0, 20.0, -135.0], [0, -1, 1], [1, 0, 0], (200.0, 200.0))
    subject = phantoms.patch(size_mm=(6, 4), n=(3, 2), center_mm=[2.0, -10.0, -150.0], normal=[0, 1, 0.3])[0]
    R = np.eye(3) - 2 * np.outer(mirror.normal, mirror.normal)
    t = 2 * np.dot(mirror.center_mm, mirror.normal) * mirror.normal
    reflected = subject.transformed(R, t)
    mirror_only = views_for(cam, [("m", mirror, 1.0)])[1:]
    diffs = []
    for ls in (LensSampling(), LensSampling(surface_samples_per_pixel=4, lens_samples_min=128)):
        T_mirror = build_transfer(subject, mirror_only, lens_sampling=ls).T.toarray()
        T_direct = build_transfer(reflected, views_for(cam, []), lens_sampling=ls).T.toarray()
        assert T_mirror.sum() > 1e-3
        assert T_mirror.sum(axis=0) == pytest.approx(T_direct.sum(axis=0), rel=2e-5)
        diffs.append(np.abs(T_mirror - T_direct).sum() / T_direct.sum())
    assert diffs[1] < 0.01 and diffs[1] < diffs[0] < 0.03


def test_a_small_mirror_only_passes_rays_that_hit_it():
    cam = camera(d_focus=180.0, R=6.0, n=96, pitch=0.08)
    big = PlaneMirror.from_axis([0, 20.0, -135.0], [0, -1, 1], [1, 0, 0], (200.0, 200.0))
    # a 0.5 mm strip of the same plane, across the beam where it crosses (y = 4.56, z = -150.44)
    small = PlaneMirror.from_axis([0, 4.56, -150.44], [0, -1, 1], [1, 0, 0], (200.0, 0.5))
    subject = phantoms.patch(size_mm=(6, 4), n=(1, 1), center_mm=[2.0, -10.0, -150.0], normal=[0, 1, 0.3])[0]
    big_T = build_transfer(subject, views_for(cam, [("m", big, 1.0)])[1:]).T.sum()
    small_T = build_transfer(subject, views_for(cam, [("m", small, 1.0)])[1:]).T.sum()
    assert 0 < small_T < 0.3 * big_T


# ------------------------------------------------------------------ estimators agree
def test_pairwise_and_lens_agree_within_one_percent_once_refined():
    cam = camera(d_focus=100.0, R=5.0, n=48, pitch=0.05, f=25.0)
    subject = phantoms.patch(size_mm=(1.5, 1.5), n=(2, 2), center_mm=[0.3, 0.1, -110.0], normal=[0.2, 0, 1])[0]
    lens = build_transfer(subject, views_for(cam, []),
                          lens_sampling=LensSampling(surface_samples_per_pixel=6, lens_samples_min=512,
                                                     lens_samples_max=4096)).T.toarray()
    coarse = build_transfer(subject, views_for(cam, []), estimator="pairwise",
                            pairwise_sampling=PairwiseSampling(surface_subdivisions=4, pixel_subdivisions=2)).T.toarray()
    fine = build_transfer(subject, views_for(cam, []), estimator="pairwise",
                          pairwise_sampling=PairwiseSampling(surface_subdivisions=14, pixel_subdivisions=7)).T.toarray()
    err_coarse = np.abs(coarse - lens).sum() / lens.sum()
    err_fine = np.abs(fine - lens).sum() / lens.sum()
    assert err_fine < 0.01
    assert err_fine < err_coarse  # convergence under refinement
    assert fine.sum(axis=0) == pytest.approx(lens.sum(axis=0), rel=5e-3)


def test_a_line_sensor_sees_exactly_the_middle_row_of_a_full_sensor():
    """Lens sampling is clipped to the part of the lens whose rays reach the sensor; the
    clipping must not bias what a one-row sensor records."""
    # three elements side by side along x, the row direction
    subject = phantoms.patch(size_mm=(1, 3), n=(1, 3), center_mm=[0.2, 0.1, -112.0], normal=[0.1, 0, 1])[0]
    full_cam = ThinLensCamera.from_pose(lens_center_mm=[0, 0, 0], look=[0, 0, -1], up=[0, 1, 0], focal_length_mm=25,
                                        aperture_radius_mm=5, focus_distance_mm=100, nx=64, ny=15, pixel_pitch_mm=0.05)
    line_cam = ThinLensCamera.from_pose(lens_center_mm=[0, 0, 0], look=[0, 0, -1], up=[0, 1, 0], focal_length_mm=25,
                                        aperture_radius_mm=5, focus_distance_mm=100, nx=64, ny=1, pixel_pitch_mm=0.05)
    fine = LensSampling(lens_samples_min=2048)
    full = build_transfer(subject, views_for(full_cam, []), lens_sampling=fine).T.toarray().reshape(15, 64, 3)
    line = build_transfer(subject, views_for(line_cam, []), lens_sampling=fine).T.toarray().reshape(1, 64, 3)
    assert full.sum() > 5 * full[7].sum() > 0  # the blur spreads over many rows
    assert line.sum(axis=(0, 1)) == pytest.approx(full[7].sum(axis=0), rel=0.01)
    assert np.abs(line[0] - full[7]).sum() / full[7].sum() < 0.03
