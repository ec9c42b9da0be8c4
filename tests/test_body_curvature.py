"""The body's own curvature in the diffuse profile (fluxcli.optics.body_curvature), checked against
a closed form in its small-curvature limit, against the exact geometry of spheres, cylinders and
boxes, and against photons leaving a sphere in fluxcli's Monte Carlo."""

import numpy as np
import pytest

from fluxcli.optics import body_curvature as bc
from fluxcli.optics import emission as E
from fluxcli.surface import phantoms
from fluxcli.surface.mesh import Surface


def _icosphere(radius_mm: float, levels: int) -> Surface:
    """An icosahedron split ``levels`` times, its vertices pushed onto the sphere (outward faces)."""
    t = (1 + 5**0.5) / 2
    v = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t],
                  [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], float)
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
                  [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5],
                  [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]])
    v = list(v / np.linalg.norm(v, axis=1)[:, None])
    for _ in range(levels):
        mid, out = {}, []

        def m(a, b):
            k = (min(a, b), max(a, b))
            if k not in mid:
                p = v[a] + v[b]
                v.append(p / np.linalg.norm(p))
                mid[k] = len(v) - 1
            return mid[k]

        for a, b, c in f:
            ab, bc_, ca = m(a, b), m(b, c), m(c, a)
            out += [[a, ab, ca], [b, bc_, ab], [c, ca, bc_], [ab, bc_, ca]]
        f = np.array(out)
    v = np.array(v) * radius_mm
    return Surface(v, f, np.arange(len(f)), len(f))


def test_the_small_curvature_limit_is_the_closed_form():
    """In a clear medium (c = 0) the ray integral under a sphere of small curvature h (1/l) gains
    h (3 mu'^2 - 1) / z_b over the flat 1 + mu' / z_b: the normal ODE's 2h phi' term (2 h mu'^2 / z_b)
    and the depth lost under a surface that falls away (-h (1 - mu'^2) / z_b), to first order."""
    zb = 2 * E.boundary_A(1.40) / 3
    mu = np.linspace(0.7, 1.0, 7)
    for h in (-0.004, 0.004):
        got = bc.ray_integrals(np.array([h]), mu, 0.0, zb)[0] / bc.ray_integrals(np.array([0.0]), mu, 0.0, zb)[0] - 1
        want = h * (3 * mu**2 - 1) / (zb + mu)
        assert np.allclose(got, want, rtol=0.05, atol=2e-5), (h, got, want)


def test_the_factor_keeps_an_elements_light_and_is_one_where_flat():
    d = E.diffuse(1.40, depth=True, body=True)
    tab = d.body
    mu = np.linspace(0.0, 1.0, bc.N_MU)
    w = E.interp_weight(d.table, mu)
    for row in tab:
        assert abs(E._moment(w * row) / E._moment(w) - 1) < 1e-12
    assert np.allclose(bc.factor(tab, mu, np.zeros_like(mu), 1.01), 1.0, atol=1e-12)
    # convex: steeper (more along the normal, less at grazing); concave: flatter
    conv = bc.factor(tab, np.array([1.0, 0.2]), np.array([1 / 12, 1 / 12]), 1.01)
    conc = bc.factor(tab, np.array([1.0, 0.2]), np.array([-1 / 12, -1 / 12]), 1.01)
    assert conv[0] > 1.03 and conv[1] < 0.975 and conc[0] < 0.985 and conc[1] > 1.01


def test_mean_curvature_of_spheres_cylinders_and_boxes():
    for R in (6.0, 12.0, 24.0):
        s = _icosphere(R, 4)
        H = bc.mean_curvature(s, bc.fit_radius_mm(s, 1.0))
        assert np.allclose(H, 1 / R, rtol=0.01), (R, H.min(), H.max())
    fine = _icosphere(12.0, 6)  # 81 920 elements: ~1300 in each fitting disc, so gathered into cells first
    H = bc.mean_curvature(fine, bc.fit_radius_mm(fine, 1.0))
    assert np.allclose(H, 1 / 12.0, rtol=0.01), (H.min(), H.max())
    for n_angular in (20, 40):  # a faceted cylinder's side: H = 1 / 2R (the axis does not curve)
        s = phantoms.cylinder(radius_mm=12.5, length_mm=50, n_angular=n_angular, n_axial=12)[0]
        H = bc.mean_curvature(s, bc.fit_radius_mm(s, 1.0))
        assert np.allclose(H, 1 / 25.0, rtol=0.03), (n_angular, H.min(), H.max())
    s = phantoms.box(size_mm=(30, 40, 20), element_mm=2.0)[0]  # flat faces up to their edges
    assert np.array_equal(bc.mean_curvature(s, bc.fit_radius_mm(s, 1.0)), np.zeros(s.n_elements))


def _sphere_bands(radius_mm: float, n_photons: int, edges_deg: np.ndarray):
    from fluxcli.montecarlo import transport as MC
    from fluxcli.montecarlo.meshbody import MeshBody

    s = _icosphere(radius_mm, 5)
    body = MeshBody.of(s.vertices_mm, s.faces)
    e = MC.transport(MC.Medium(0.01, 1.0, 0.0, 1.40), body, np.zeros(3), n_photons, seed=11)
    cos = np.clip(np.einsum("ij,ij->i", body.normals[e.face], e.direction), 0, 1)
    hist = np.histogram(np.degrees(np.arccos(cos)), bins=edges_deg, weights=e.weight)[0]
    return hist / hist.sum(), np.sqrt(hist) / hist.sum()


def _model_bands(weight, edges_deg):
    th = np.linspace(0, np.pi / 2, 20001)[1:-1]
    w = weight(np.cos(th)) * np.cos(th) * np.sin(th)
    e = np.radians(edges_deg)
    out = np.array([w[(th >= a) & (th < b)].sum() for a, b in zip(e[:-1], e[1:])])
    return out / out.sum()


@pytest.mark.parametrize("radius_mm", [12.0])
def test_photons_leaving_a_sphere_follow_the_curved_profile(radius_mm):
    """Photons from the centre of a sphere (mu_s 1, mu_a 0.01 /mm, n 1.40: the exitance is the same
    everywhere, so no other term acts) leave it more steeply than a flat surface's profile says;
    the factor of the sphere's curvature takes the bands to 80 deg to within the photons' noise."""
    edges = np.array([0, 20, 40, 55, 65, 72.5, 80])
    shares, sigma = _sphere_bands(radius_mm, 1_500_000, np.append(edges, 90.0))
    shares, sigma = shares[:-1], sigma[:-1]
    flat = E.diffuse(1.40, depth=True, body=True)
    tab = flat.body

    def curved(mu):
        return flat.weight(mu) * bc.factor(tab, mu, np.full_like(mu, 1 / radius_mm), 1.01)

    f_bands = _model_bands(flat.weight, np.append(edges, 90.0))[:-1]
    c_bands = _model_bands(curved, np.append(edges, 90.0))[:-1]
    assert np.all(sigma / shares < 0.006)
    r_flat, r_curved = shares / f_bands, shares / c_bands
    assert r_flat[0] > 1.025 and r_flat[3:].mean() < 0.98, r_flat  # the flat profile is off, in this sense
    print("photons / flat profile", np.round(r_flat, 4), "/ curved", np.round(r_curved, 4), "sigma", np.round(sigma / shares, 4))
    assert np.all(np.abs(r_curved - 1) < 0.006 + 3 * sigma / shares), r_curved
    assert np.abs(r_curved - 1).max() < 0.5 * np.abs(r_flat - 1).max()


def _camera(d_focus: float, R: float, n: int, pitch: float):
    from fluxcli.optics.camera import ThinLensCamera

    return ThinLensCamera.from_pose(lens_center_mm=[0, 0, 0], look=[0, 0, -1], up=(0, 1, 0), focal_length_mm=25.0,
                                    aperture_radius_mm=R, focus_distance_mm=d_focus, nx=n, ny=n, pixel_pitch_mm=pitch)


def test_flat_faces_keep_their_T_and_a_spheres_columns_take_the_factor():
    from fluxcli.optics.transfer import build_transfer, views_for

    on = E.diffuse(1.40, depth=True, tangential=True, body=True)
    off = E.diffuse(1.40, depth=True, tangential=True)
    assert on.key() != off.key() and on.key()["body_curvature"] == bc.LAYOUT
    cam = _camera(150.0, 6.0, 96, 0.15)
    box = phantoms.box(size_mm=(12, 10, 8), element_mm=2.0)[0].transformed(np.eye(3), np.array([0, 0, -150.0]))
    a = build_transfer(box, views_for(cam, []), emission=on)
    b = build_transfer(box, views_for(cam, []), emission=off)
    assert np.array_equal(a.T.toarray(), b.T.toarray())  # H = 0 on every face: the same T to the bit ...
    assert np.array_equal(a.T_tangent.toarray(), b.T_tangent.toarray())  # ... and the same tangential part
    ball = _icosphere(8.0, 2).transformed(np.eye(3), np.array([0, 0, -150.0]))
    ra, rb = build_transfer(ball, views_for(cam, []), emission=on), build_transfer(ball, views_for(cam, []), emission=off)
    a, b = np.asarray(ra.T.sum(axis=0)).ravel(), np.asarray(rb.T.sum(axis=0)).ravel()
    cen = ball.element_centroids_mm
    cos = np.einsum("ij,ij->i", ball.face_normals, -cen) / np.linalg.norm(cen, axis=1)
    seen = b > 0
    H = bc.mean_curvature(ball, bc.fit_radius_mm(ball, 1.01))
    assert np.allclose(H, 1 / 8.0, rtol=0.05)  # 320 facets
    want = bc.factor(on.body, cos, H, 1.01)
    assert np.allclose(a[seen] / b[seen], want[seen], rtol=1e-9)
    ta, tb = ra.T_tangent.toarray(), rb.T_tangent.toarray()  # the tangential part: its own factor
    tw = np.repeat(bc.factor(on.body_tangent, cos, H, 1.01), 2)
    cols = np.abs(tb).sum(axis=0) > 0
    assert np.allclose(ta[:, cols], tb[:, cols] * tw[cols], rtol=1e-9, atol=1e-30)
    assert tw[np.repeat(seen, 2)].min() > 1.05  # convex: it reaches further
    assert np.ptp(want[seen]) > 0.05  # the factor does move light between the ball's elements ...
    # ... but a uniformly bright ball sends as much light towards a distant lens whatever its profile
    # (by symmetry, a quarter-pi-th of its power per steradian): the factor keeps each element's power
    assert a[seen].sum() / b[seen].sum() == pytest.approx(1.0, abs=1e-3)


def test_reconstruct_says_what_curvature_it_read():
    from fluxcli.inverse.emission_checks import body_curvature_line
    from fluxcli.optics.transfer import views_for

    prof = E.profile({"model": "diffuse", "refractive_index": 1.40})  # the term is on by default
    assert prof.body_curvature
    cam = _camera(150.0, 6.0, 32, 0.5)
    ball = _icosphere(10.0, 3).transformed(np.eye(3), np.array([0, 0, -150.0]))
    line = body_curvature_line(ball, views_for(cam, []), prof)
    assert "median 0.1" in line and "radius 10 mm" in line, line
    box = phantoms.box(size_mm=(12, 10, 8), element_mm=2.0)[0].transformed(np.eye(3), np.array([0, 0, -150.0]))
    assert "flat everywhere" in body_curvature_line(box, views_for(cam, []), prof)


def _drift_on_sphere(radius_mm: float, depth_mm: float, n_photons: int):
    """Photons leaving a sphere from a point ``depth_mm`` under its top: per band of exit angle the
    drift length g that their own drift away from the source's foot implies, as on the slab of
    tests/test_emission.py (``<d . t> = g k sin^2(theta) / 2`` with k = -d ln M / d rho fitted to the
    photons' exit density over the sphere's arc rho, 3-12 mm from the foot)."""
    from fluxcli.montecarlo import transport as MC
    from fluxcli.montecarlo.meshbody import MeshBody

    s = _icosphere(radius_mm, 5)
    body = MeshBody.of(s.vertices_mm, s.faces)
    e = MC.transport(MC.Medium(0.01, 1.0, 0.0, 1.40), body, np.array([0, 0, radius_mm - depth_mm]), n_photons, seed=7)
    p, d, nrm = e.position_mm, e.direction, body.normals[e.face]
    u = p / np.linalg.norm(p, axis=1)[:, None]
    rho = radius_mm * np.arccos(np.clip(u[:, 2], -1, 1))
    t = u * u[:, 2:3] - np.array([0, 0, 1.0])  # along the surface, away from the foot
    t -= nrm * np.einsum("ij,ij->i", t, nrm)[:, None]
    t /= np.maximum(np.linalg.norm(t, axis=1), 1e-12)[:, None]
    d_t, cos = np.einsum("ij,ij->i", d, t), np.einsum("ij,ij->i", d, nrm)
    edges = np.arange(1.0, 16.01, 0.5)
    count = np.histogram(rho, edges)[0]
    a = edges / radius_mm
    ring = 2 * np.pi * radius_mm**2 * (np.cos(a[:-1]) - np.cos(a[1:]))
    fit = np.polyfit(0.5 * (edges[1:] + edges[:-1]), np.log(count / ring), 3, w=np.sqrt(count))
    k = -np.polyval(np.polyder(fit), rho)
    near = (rho > 3) & (rho < 12)
    out = []
    for lo, hi in ((20, 40), (40, 65)):
        b = near & (cos <= np.cos(np.radians(lo))) & (cos > np.cos(np.radians(hi)))
        den = (k[b] * (1 - cos[b] ** 2)).sum()
        out.append((lo, hi, 2 * d_t[b].sum() / den, 2 * d_t[b].std() * np.sqrt(b.sum()) / den))
    return out


def test_photons_leaving_a_sphere_drift_as_the_curved_tangential_term_says():
    """Over a convex body the light drifts away from a buried source more than over a flat slab:
    the ray behind an exit reaches further along the surface at depth, where the fluence is larger.
    The photons' drift length g on a sphere of 12 mm over a wide slab's (the same medium, the source
    6 mm deep, tests/test_emission.py) is the osculating sphere's sideways moment over the flat one
    (body_curvature.tangent_factor_table over the scalar factor); the flat term says 1."""
    from test_emission import _g_from_photons

    R = 12.0
    prof = E.diffuse(1.40, depth=True, tangential=True, body=True)
    slab = {(lo, hi): (g, sg) for lo, hi, g, sg, _ in _g_from_photons(1.40, 1_000_000)}
    for lo, hi, g_mc, sigma in _drift_on_sphere(R, 6.0, 1_000_000):
        mu, H = np.array([np.cos(np.radians((lo + hi) / 2))]), np.full(1, 1 / R)
        want = float(bc.factor(prof.body_tangent, mu, H, 1.01)[0] / bc.factor(prof.body, mu, H, 1.01)[0])
        g_slab, s_slab = slab[(lo, hi)]
        got = g_mc / g_slab
        err = got * np.hypot(sigma / g_mc, s_slab / g_slab)
        print(f"{lo}-{hi} deg: g on the sphere {g_mc:.3f}, on the slab {g_slab:.3f}: x{got:.3f} +- {err:.3f}; model x{want:.3f}")
        assert err < 0.06 * got
        assert got == pytest.approx(want, rel=0.1), (lo, hi, got, want)
        assert got > 1.15  # the flat term (x1) is far short of it
