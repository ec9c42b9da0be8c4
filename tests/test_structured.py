"""Structured light (issue 12): projector model, patterns and decoding, rendering,
triangulation and meshing, each against numbers the code did not produce (closed forms,
the known geometry of a plane or sphere, the column a point truly projects to)."""

import numpy as np
import pytest

from fluxcli.imaging import noise as N
from fluxcli.optics.camera import PlaneMirror, ThinLensCamera
from fluxcli.structured.mesh import closed_surface, coverage, distances_to_surface, estimate_normals, remove_outliers
from fluxcli.structured.patterns import column_patterns, decode
from fluxcli.structured.projector import ImageSink, Projector
from fluxcli.structured.render import PatternRenderer
from fluxcli.structured.scan import points_from_frames, simulate_frames
from fluxcli.structured.triangulate import chief_rays, triangulate_columns
from fluxcli.surface import phantoms
from fluxcli.surface.mesh import box


def _projector(**kw):
    args = dict(center_mm=[0, -120, 160], look=[0, 120, -150], up=[-1, 0, 0], width_px=320, height_px=240,
                fx_px=900.0, k1=0.08, k2=-0.01, gamma=1.0)
    args.update(kw)
    return Projector.from_pose(**args)


# ---------------------------------------------------------------- projector
def test_pinhole_projection_closed_form():
    p = Projector.from_pose(center_mm=[1, 2, 100], look=[0, 0, -1], up=[0, 1, 0], width_px=640, height_px=480,
                            fx_px=1000, fy_px=1010, cx_px=300, cy_px=250)
    # right = look x up = (0,0,-1) x (0,1,0) = (1,0,0); down = -y; depth along -z
    u, v, z = p.project(np.array([[11.0, -3.0, 50.0]]))
    assert z[0] == pytest.approx(50.0)
    assert u[0] == pytest.approx(1000 * 10 / 50 + 300)
    assert v[0] == pytest.approx(1010 * 5 / 50 + 250)


def test_distortion_round_trip_and_radial_law():
    p = _projector()
    rng = np.random.default_rng(1)
    u, v = rng.uniform(0, 320, 500), rng.uniform(0, 240, 500)
    d = p.rays(u, v)
    pts = p.center_mm + d * rng.uniform(50, 300, (500, 1))
    u2, v2, _ = p.project(pts)
    assert np.max(np.abs(u2 - u)) < 1e-6 and np.max(np.abs(v2 - v)) < 1e-6
    # Brown's law: a point at normalised radius r lands at r (1 + k1 r^2 + k2 r^4) * f from the centre
    r = 0.15
    q = p.center_mm + 100 * (p.axis + r * p.right)
    uq, vq, _ = p.project(q[None])
    assert uq[0] - p.cx_px == pytest.approx(900 * r * (1 + 0.08 * r**2 - 0.01 * r**4), rel=1e-12)
    assert vq[0] == pytest.approx(p.cy_px)


def test_image_sink_keeps_the_pattern_and_refuses_wrong_shapes():
    p = _projector()
    sink = ImageSink(p)
    img = np.random.default_rng(0).random((240, 320))
    sink.show(img)
    assert sink.current is img or np.array_equal(sink.current, img)
    with pytest.raises(ValueError):
        sink.show(np.zeros((10, 10)))


# ---------------------------------------------------------------- patterns and decoding
def _frames_at_columns(p: Projector, pats, u, v):
    return np.stack([p.radiance(f, u, v) for f in pats.frames])[:, None, :]


@pytest.mark.parametrize("period", [8, 16, 32])
def test_decoding_recovers_every_column_including_period_edges(period):
    p = _projector(k1=0.0, k2=0.0)
    pats = column_patterns(320, 240, period_px=period, n_steps=4)
    # columns at and next to every Gray cell boundary, inside the panel's interpolation range
    edges = np.arange(0, 320, period / 4)
    u = np.clip(np.concatenate([edges - 0.02, edges + 0.02, edges + period / 8]), 0.6, 319.4)
    frames = _frames_at_columns(p, pats, u, np.full_like(u, 120.5))
    dec = decode(frames, pats, min_contrast=0.1, width_px=320, max_column_jump_px=np.inf)
    err = dec.column_px[0] - u
    # a sinusoid sampled at pixel centres and interpolated linearly is not a sinusoid:
    # its phase is exact at centres and midpoints and off by < 0.05 px between
    assert np.all(np.isfinite(err)) and np.max(np.abs(err)) < 0.05 * period / 8


def test_gamma_phase_error_is_the_aliased_harmonics_and_eight_steps_remove_it():
    """Projector gamma 2.2 adds fringe harmonics a_m.  An N-step phase shift sees
    S ~ a1 sin t - a_{N-1} sin((N-1) t) + a_{N+1} sin((N+1) t) ..., C ~ a1 cos t + a_{N-1} cos((N-1) t) + ...
    (harmonics m = +-1 mod N alias onto the fundamental).  The harmonics come from an FFT
    of the gamma curve, not from the decoder.  Columns at pixel centres: no interpolation."""
    gamma, P = 2.2, 32
    u = np.arange(40, 72) + 0.5
    v = np.full_like(u, 100.5)
    t = np.linspace(0, 2 * np.pi, 4096, endpoint=False)
    a = 2 * np.fft.rfft((0.5 + 0.5 * np.cos(t)) ** gamma).real / len(t)
    theta = 2 * np.pi * u / P
    errs = {}
    for steps, comp in [(4, 1.0), (8, 1.0), (4, gamma)]:
        p = _projector(k1=0.0, k2=0.0, gamma=gamma)
        pats = column_patterns(320, 240, period_px=P, n_steps=steps, gamma=comp)
        dec = decode(_frames_at_columns(p, pats, u, v), pats, min_contrast=0.05, max_column_jump_px=np.inf)
        errs[(steps, comp)] = dec.column_px[0] - u
    S = a[1] * np.sin(theta) - a[3] * np.sin(3 * theta) + a[5] * np.sin(5 * theta) - a[7] * np.sin(7 * theta)
    C = a[1] * np.cos(theta) + a[3] * np.cos(3 * theta) + a[5] * np.cos(5 * theta) + a[7] * np.cos(7 * theta)
    predicted = (np.angle(np.exp(1j * (np.arctan2(S, C) - theta)))) * P / (2 * np.pi)
    assert np.max(np.abs(predicted)) > 0.02  # px: the 4-step error is real
    assert np.allclose(errs[(4, 1.0)], predicted, atol=2e-3 * np.max(np.abs(predicted)) + 1e-9)
    assert np.max(np.abs(errs[(8, 1.0)])) < 0.05 * np.max(np.abs(predicted))
    assert np.max(np.abs(errs[(4, gamma)])) < 1e-9


def test_masks_shadow_and_low_modulation():
    p = _projector(k1=0.0, k2=0.0)
    pats = column_patterns(320, 240, period_px=16, n_steps=4)
    u = np.array([100.2, 150.7, 200.1])
    fr = _frames_at_columns(p, pats, u, np.full(3, 50.5)) * 100.0 + 5.0
    fr[:, 0, 1] = 5.0  # a shadow: nothing but ambient light
    fr[2:, 0, 2] = fr[2:, 0, 2].mean()  # no fringe (blurred across periods), lit
    fr[0, 0, 2], fr[1, 0, 2] = 105.0, 5.0
    dec = decode(fr, pats, min_contrast=20.0, max_column_jump_px=np.inf)
    assert dec.valid[0].tolist() == [True, False, False]
    assert dec.lit[0].tolist() == [True, False, True]
    assert dec.modulated[0, 2] == False  # noqa: E712
    assert abs(dec.column_px[0, 0] - 100.2) < 0.01


# ---------------------------------------------------------------- triangulation
def test_triangulation_recovers_points_on_a_plane_through_distortion():
    p = _projector()
    cam = ThinLensCamera.from_pose(lens_center_mm=[0, 0, 200], look=[0, 0, -1], up=[0, 1, 0], focal_length_mm=25,
                                   aperture_radius_mm=2, focus_distance_mm=200, nx=40, ny=30, pixel_pitch_mm=0.2)
    o, d, tmax = chief_rays(cam, [])
    # the truth: where each chief ray meets the plane z = 5 (closed form), and its projector column
    t_true = (5.0 - o[0, :, 2]) / d[0, :, 2]
    X = o[0] + t_true[:, None] * d[0]
    u, _, _ = p.project(X)
    P, t = triangulate_columns(p, o[0], d[0], u)
    assert np.nanmax(np.abs(P - X)) < 1e-6


def test_mirror_pixels_take_the_reflected_ray():
    cam = ThinLensCamera.from_pose(lens_center_mm=[0, 0, 300], look=[0, 0, -1], up=[0, 1, 0], focal_length_mm=25,
                                   aperture_radius_mm=2, focus_distance_mm=290, nx=64, ny=64, pixel_pitch_mm=0.2)
    m = PlaneMirror.from_axis([0, 30, 15], [0, -1, 1], [1, 0, 0], [60, 40])
    o, d, _ = chief_rays(cam, [m])
    in_mirror = np.isfinite(o[1, :, 0])
    assert in_mirror.any() and not np.isfinite(o[0, in_mirror, 0]).any()
    # a vertical ray reflected by a 45-degree mirror facing -y travels along -y
    k = np.flatnonzero(in_mirror)[len(np.flatnonzero(in_mirror)) // 2]
    assert d[1, k, 1] < -0.95


# ---------------------------------------------------------------- rendering
def test_white_on_a_plane_is_lambertian_irradiance():
    """A plane z = 0 facing a projector straight above at height H: the radiance the camera
    sees at the projector's axis is albedo / pi * 1 / H^2 (closed form)."""
    H, albedo = 150.0, 0.6
    p = Projector.from_pose(center_mm=[0, 0, H], look=[0, 0, -1], up=[0, 1, 0], width_px=64, height_px=64, fx_px=200)
    cam = ThinLensCamera.from_pose(lens_center_mm=[0, 0, 200], look=[0, 0, -1], up=[0, 1, 0], focal_length_mm=25,
                                   aperture_radius_mm=1, focus_distance_mm=200, nx=16, ny=16, pixel_pitch_mm=0.1)
    plane = box([-100, -100, -5], [100, 100, 0])
    r = PatternRenderer(cam, [], [(plane, albedo)], [], p, lens_samples=4, sub=2)
    img = r.render(np.ones((64, 64)))
    # centre pixels (off-axis angle ~ 0.01 rad: cos^4 effects < 1e-3)
    assert img[7:9, 7:9].mean() == pytest.approx(albedo / np.pi / H**2, rel=2e-3)
    # a shadow: a small block at z = 100 centred at x = 1.5 casts its shadow (seen from the
    # projector at H) around x = 1.5 H / (H - 100) = 4.5 mm, pixel column 14 (0.7 mm per
    # pixel on the plane); the camera, from 200, sees the block itself around x = 3 mm
    block = box([1.25, -0.25, 100], [1.75, 0.25, 100.5])
    r2 = PatternRenderer(cam, [], [(plane, albedo)], [block], p, lens_samples=4, sub=2)
    img2 = r2.render(np.ones((64, 64)))
    assert img2[7:9, 14].max() == 0.0
    assert np.allclose(img2[:, :10], img[:, :10]) and np.allclose(img2[:5], img[:5])


@pytest.fixture(scope="module")
def sphere_scan():
    """A small rig: camera above, one 45-degree mirror, two projectors; a sphere on a stage."""
    R, centre = 8.0, np.array([0.0, 0.0, 8.0])
    surf, _, _ = phantoms.sphere(radius_mm=R, n_latitude=64, n_longitude=128)
    surf = surf.transformed(np.eye(3), centre)
    stage = box([-40, -14, -5], [40, 14, 0])
    cam = ThinLensCamera.from_pose(lens_center_mm=[0, 0, 300], look=[0, 0, -1], up=[0, 1, 0], focal_length_mm=25,
                                   aperture_radius_mm=2.5, focus_distance_mm=292, nx=128, ny=128, pixel_pitch_mm=0.04)
    mirror = PlaneMirror.from_axis([0, 22, 10], [0, -1, 1], [1, 0, 0], [40, 28])
    projs = [Projector.from_pose(center_mm=[0, s * 160, 130], look=[0, -s * 160, -125], up=[s, 0, 0], width_px=384,
                                 height_px=256, fx_px=1100, k1=0.05, gamma=2.2) for s in (-1, 1)]
    pats = column_patterns(384, 256, period_px=16, n_steps=8)
    sensor = N.EMCCDModel(em_gain=10, exposure_s=0.1)
    out = []
    for k, p in enumerate(projs):
        r = PatternRenderer(cam, [(mirror, 0.9)], [(surf, 0.8), (stage, 0.5)], [], p, lens_samples=3, sub=2)
        counts, _ = simulate_frames(r, pats, photons_white=3000, ambient_photons=20, sensor=sensor,
                                    rng=np.random.default_rng(k))
        out.append(points_from_frames(N.counts_to_photons(counts, sensor), pats, cam, [mirror], p, min_contrast=300))
    return R, centre, surf, out, cam, mirror


def test_captured_sphere_points_lie_on_the_true_sphere(sphere_scan):
    R, centre, surf, scans, *_ = sphere_scan
    P = np.concatenate([s.points_mm for s in scans])
    view = np.concatenate([s.view for s in scans])
    on = P[:, 2] > 1.0  # the stage top is known: its points are not the subject's
    P, view = P[on], view[on]
    d = np.abs(np.linalg.norm(P - centre, axis=1) - R)  # analytic sphere, not the mesh
    assert len(P) > 1500 and (view == 1).sum() > 100  # the mirror view contributes
    assert np.mean(d < 0.1) > 0.8 and np.mean(d < 0.4) > 0.95
    assert np.mean(d[view == 1] < 0.2) > 0.8
    # coverage measured on the faceted truth agrees with the points being on it: at most what the
    # rig can see and light (a closed-form geometry of the sphere, below: 0.69 within 1 mm), and
    # not much less (measured 0.536: the decoding loses grazing views; the direct view alone
    # 0.374). The bound 0.4-1.0 before could not fail from above; a copy measuring within 4 mm
    # instead of 1 (0.743) fails this one
    ideal = _seen_and_lit_share(R, centre, radius_mm=1.0)
    assert 0.7 * ideal < coverage(P, surf, radius_mm=1.0) < ideal + 0.02, ideal


def _seen_and_lit_share(R, centre, *, radius_mm: float, n: int = 50_000) -> float:
    """The share of the sphere's area within ``radius_mm`` of a point that sphere_scan's rig can
    both see (camera directly or through the mirror, inside the sensor) and light (either
    projector, the mirror's back blocking): numpy geometry of the analytic sphere, no fluxcli."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(0)
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1)[:, None]
    q = centre + R * nrm
    C = np.array([0.0, 0.0, 300.0])
    mc, mn = np.array([0.0, 22.0, 10.0]), np.array([0.0, -1.0, 1.0]) / np.sqrt(2)
    ax = np.array([1.0, 0.0, 0.0])
    ay = np.cross(mn, ax)

    def crossing(p0, p1):  # where p0 -> p1 meets the mirror's plane, and whether inside its 40 x 28 mm
        d0, d1 = (p0 - mc) @ mn, (p1 - mc) @ mn
        x = p0 + (d0 / (d0 - d1))[:, None] * (p1 - p0)
        return x, (d0 * d1 < 0) & (np.abs((x - mc) @ ax) <= 20.0) & (np.abs((x - mc) @ ay) <= 14.0)

    def on_sensor(p):  # chief ray through the lens centre onto the 128 x 0.04 mm sensor, f 25 mm
        d = p - C
        return (np.abs(25 * d[:, 0] / d[:, 2]) < 2.56) & (np.abs(25 * d[:, 1] / d[:, 2]) < 2.56)

    def faces(p):
        return ((p - q) * nrm).sum(axis=1) > 0

    direct = faces(C) & ~crossing(q, C)[1] & on_sensor(q)
    Cv = C - 2 * ((C - mc) @ mn) * mn  # the camera's mirror image
    M, hit = crossing(q, Cv)
    via = faces(Cv) & hit & on_sensor(M)
    lit = np.zeros(n, bool)
    for s in (-1, 1):
        P = np.array([0.0, s * 160.0, 130.0])
        lit |= faces(P) & ~crossing(q, P)[1]
    d, _ = cKDTree(q[(direct | via) & lit]).query(q, distance_upper_bound=radius_mm)
    return float(np.mean(np.isfinite(d)))


def test_closed_surface_through_captured_sphere_points(sphere_scan):
    R, centre, surf, scans, *_ = sphere_scan
    P = np.concatenate([s.points_mm for s in scans])
    V = np.concatenate([s.view_dirs for s in scans])
    on = P[:, 2] > 1.0
    P, V = P[on], V[on]
    keep = remove_outliers(P, max_plane_distance_mm=0.5)
    n = estimate_normals(P[keep], V[keep])
    # normals face outward: along the radius
    radial = (P[keep] - centre) / np.linalg.norm(P[keep] - centre, axis=1, keepdims=True)
    assert np.median((n * radial).sum(1)) > 0.95
    m = closed_surface(P[keep], n, floor_z_mm=0.0, voxel_mm=0.8, centre_spacing_mm=2.0, face_size_mm=1.5,
                       element_size_mm=4.0)
    assert m.is_closed and m.boundary_edge_count() == 0
    assert m.n_elements == pytest.approx(m.face_areas_mm2.sum() / 16, rel=0.05)
    d = distances_to_surface(m.vertices_mm[m.vertices_mm[:, 2] > 6], surf)
    assert np.median(d) < 0.1


def test_closed_surface_volume_and_area_from_exact_points_on_a_sphere():
    """Points on a sphere cut by a floor (a spherical cap, closed forms for its volume and
    area), seen everywhere but within 2 mm of the floor: the RBF closure must stay within 2 %."""
    R, c, floor = 10.0, np.array([1.0, -2.0, 6.0]), 0.0
    rng = np.random.default_rng(3)
    d = rng.normal(size=(6000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    P = c + R * d
    keep = P[:, 2] > floor + 2.0
    m = closed_surface(P[keep], d[keep], floor_z_mm=floor, voxel_mm=0.5, centre_spacing_mm=1.5, face_size_mm=1.0)
    assert m.is_closed
    h = R + c[2] - floor  # height of the cap above the floor
    vol_true = np.pi * h**2 * (3 * R - h) / 3
    area_true = 2 * np.pi * R * h + np.pi * (R**2 - (R - h) ** 2)  # dome + flat disk on the floor
    t = m.vertices_mm[m.faces]
    vol = np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() / 6
    assert vol == pytest.approx(vol_true, rel=0.02)
    assert m.face_areas_mm2.sum() == pytest.approx(area_true, rel=0.02)


def test_surface_artefact_is_what_subject_surface_artefact_reads(sphere_scan, tmp_path, write_config, minimal_config):
    """The captured mesh, written as surface.h5, is accepted by `subject.surface: {artefact: ...}`
    and placed where it was measured (a mesh stays where its file puts it)."""
    from fluxcli.config import load_config
    from fluxcli.stages.plans import placer_of
    from fluxcli.artefacts.surface import write_surface_artefact
    from fluxcli.structured.scan import merge_points, surface_from_points

    R, centre, surf, scans, *_ = sphere_scan
    merged = merge_points(scans, floor_z_mm=0.0)
    mesh = surface_from_points(merged, floor_z_mm=0.0, element_size_mm=5.0, face_size_mm=1.5)
    write_surface_artefact(tmp_path / "surface.h5", mesh, points=merged)
    cfg = dict(minimal_config)
    cfg["subject"] = {"surface": {"artefact": "surface.h5"}}
    placer = placer_of(load_config(write_config(cfg)))
    s = placer.surface
    assert s.is_closed and s.n_elements == mesh.n_elements
    assert np.allclose(np.sort(s.vertices_mm, axis=0), np.sort(mesh.vertices_mm, axis=0))
    top = s.vertices_mm[np.argmax(s.vertices_mm[:, 2])]
    assert np.linalg.norm(top - (centre + [0, 0, R])) < 1.0


@pytest.mark.slow
def test_paper_like_rig_meets_issue_12_targets(tmp_path):
    """The full check (make structured-light does the same and writes figures): cylinder and mouse,
    every target of issue 12 (points within 0.1/0.2/0.4 mm, closed mesh, volume and area within 2 %)."""
    from repo_scripts import load_script

    mod = load_script("pipelines/structured_light.py")
    results = mod.run(str(tmp_path))
    assert mod.misses(results["cylinder"]) == []
    assert mod.misses(results["mouse"]) == []


def test_projector_calibration_recovers_pose_from_grid_at_heights():
    """A flat board at three heights, lit by column and row codes (EMCCD noise): local
    homographies give each grid point's projector coordinates, resection gives the projector.
    The simulated projector's pose must come back within 1 mm and 0.2 deg (issue 12)."""
    from scipy.spatial.transform import Rotation

    from fluxcli.structured.calibrate import fit_projector, projector_coordinates_at, row_patterns

    true = Projector.from_pose(center_mm=[10, -140, 170], look=[-10, 140, -165], up=[-1, 0.1, 0], width_px=400,
                               height_px=300, fx_px=1000, fy_px=1005, cx_px=205, cy_px=148, k1=0.06, k2=-0.02)
    cam = ThinLensCamera.from_pose(lens_center_mm=[0, 0, 300], look=[0, 0, -1], up=[0, 1, 0], focal_length_mm=25,
                                   aperture_radius_mm=2, focus_distance_mm=290, nx=128, ny=128, pixel_pitch_mm=0.056)
    cols = column_patterns(400, 300, period_px=16, n_steps=8)
    rows = row_patterns(400, 300, period_px=16, n_steps=8)
    sensor = N.EMCCDModel(em_gain=10, exposure_s=0.1)
    gi, gj = np.meshgrid(np.arange(11) - 5, np.arange(9) - 4, indexing="ij")
    X_all, uv_all = [], []
    for k, z in enumerate([-12.0, 0.0, 12.0]):
        board = box([-60, -60, z - 3], [60, 60, z])
        r = PatternRenderer(cam, [], [(board, 0.8)], [], true, lens_samples=2, sub=1)
        dec = []
        for j, pats in enumerate((cols, rows)):
            counts, _ = simulate_frames(r, pats, photons_white=3000, ambient_photons=20, sensor=sensor,
                                        rng=np.random.default_rng([k, j]))
            dec.append(decode(N.counts_to_photons(counts, sensor), pats, min_contrast=300).column_px)
        X = np.c_[4.0 * gi.ravel(), 4.0 * gj.ravel(), np.full(gi.size, z)]
        col, row = cam.pixel_coords(cam.focal_plane_hit(X, np.broadcast_to(cam.center_mm, X.shape)))
        uv, ok = projector_coordinates_at(np.c_[col, row], dec[0], dec[1])
        X_all.append(X[ok]); uv_all.append(uv[ok])
    X, uv = np.concatenate(X_all), np.concatenate(uv_all)
    assert len(X) > 200
    fit, res = fit_projector(X, uv, width_px=400, height_px=300)
    assert np.sqrt(np.mean(res**2)) < 0.1  # projector pixels
    assert np.linalg.norm(fit.center_mm - true.center_mm) < 1.0
    angle = np.degrees(Rotation.from_matrix(fit.rotation @ true.rotation.T).magnitude())
    assert angle < 0.2
    assert fit.fx_px == pytest.approx(1000, rel=0.01) and fit.k1 == pytest.approx(0.06, abs=0.02)


def test_distance_and_coverage_measures_on_a_box():
    """Closed forms: a point above a cube face is at its height above it; points covering the
    top face (1 of 6 equal faces) cover 1/6 of the area."""
    cube = box([0, 0, 0], [10, 10, 10])
    pts = np.array([[5.0, 5.0, 10.3], [5.0, 5.0, 9.0], [12.0, 5.0, 5.0], [13.0, 14.0, 5.0]])
    assert np.allclose(distances_to_surface(pts, cube), [0.3, 1.0, 2.0, 5.0])
    g = np.stack(np.meshgrid(np.linspace(0, 10, 41), np.linspace(0, 10, 41), [10.0], indexing="ij"), -1).reshape(-1, 3)
    assert coverage(g, cube, radius_mm=0.5, samples_per_mm2=20) == pytest.approx(1 / 6 + 4 * 10 * 0.5 / 600, abs=0.01)


def test_report_shows_the_captured_surface_over_the_truth(sphere_scan, tmp_path, write_config, minimal_config):
    """A workdir holding only a surface.h5 (what capture-surface writes): `fluxmap report` shows the
    captured surface coloured by its distance to the truth, the distance histogram, and phase and
    masks per view and projector.  The fractions it reports agree with the analytic sphere (an
    estimator that never sees the faceted truth or the mesh)."""
    import json

    import h5py
    from typer.testing import CliRunner

    from fluxcli.cli import app
    from fluxcli.artefacts.surface import write_surface_artefact
    from fluxcli.structured.scan import decode_by_view as decode_datasets
    from fluxcli.structured.mesh import capture_metrics, distances_to_surface
    from fluxcli.structured.scan import merge_points, surface_from_points

    R, centre, surf, scans, cam, mirror = sphere_scan
    merged = merge_points(scans, floor_z_mm=0.0)
    mesh = surface_from_points(merged, floor_z_mm=0.0, element_size_mm=5.0, face_size_mm=1.5)
    d = distances_to_surface(merged.points_mm, surf)
    decode = decode_datasets(scans, ["left", "right"], ["direct", "side"], cam, [mirror])
    cfg = dict(minimal_config)
    cfg["workdir"] = "run"
    (tmp_path / "run").mkdir()
    write_surface_artefact(tmp_path / "run" / "surface.h5", mesh, points=merged, distance_to_truth_mm=d, truth=surf,
                           metrics=capture_metrics(merged.points_mm, d, mesh, surf), decode=decode)
    r = CliRunner().invoke(app, ["report", str(write_config(cfg)), "-q"])
    assert r.exit_code == 0, r.output
    out = tmp_path / "run" / "report"
    html = (out / "index.html").read_text()
    assert 'id="surface3d"' in html and "plotly" in html
    assert (out / "surface_distances.png").is_file() and (out / "surface_decoding.png").is_file()
    summary = json.loads((out / "summary.json").read_text())["surface"]
    exact = np.abs(np.linalg.norm(merged.points_mm - centre, axis=1) - R)
    for t in (0.1, 0.2, 0.4):
        assert summary[f"within_{t}mm"] == pytest.approx(np.mean(exact < t), abs=0.03)
    # every decoded mask pixel of a view lies in that view's part of the image, and the views do not overlap
    with h5py.File(tmp_path / "run" / "surface.h5") as f:
        direct, side = (f[f"decode/{v}/right/mask"][()].astype(bool) for v in ("direct", "side"))
    assert direct.sum() > 100 and side.sum() > 20 and not (direct & side).any()  # the right projector lights the mirror's side
    assert summary["decoded_pixels"]["right/direct"] == int(direct.sum())
    assert f"direct: {int((merged.view == 0).sum())}, side: {int((merged.view == 1).sum())}" in html
    # the captured sphere's vertices lie on the truth (median well below a voxel)
    assert summary["vertex_distance_mm"]["median"] < 0.2
