"""The issue-21 control's sampler (same exit points, directions redrawn from an emission
profile): the redrawn light must follow the profile's closed form and not the sampler's
own arithmetic."""

import numpy as np

from fluxcli.montecarlo.photons import ANGLE_EDGES_DEG, exit_angle_histogram, redraw_directions
from fluxcli.optics.emission import diffuse, lambertian


def test_lambertian_redraw_is_the_cosine_law():
    # cos^2 theta of a Lambertian emitter is uniform on [0, 1]: its mean is 1/2 and its
    # histogram flat (closed form, not the sampler's table)
    rng = np.random.default_rng(1)
    n = np.tile([[0.0, 0.0, 1.0]], (400_000, 1))
    d = redraw_directions(n, lambertian().table, rng)
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0)
    c2 = d[:, 2] ** 2
    assert abs(c2.mean() - 0.5) < 3e-3
    h = np.histogram(c2, bins=10, range=(0, 1))[0] / len(c2)
    assert np.all(np.abs(h - 0.1) < 0.004)
    assert abs(d[:, 0].mean()) < 3e-3 and abs(d[:, 1].mean()) < 3e-3  # azimuth uniform


def test_diffuse_redraw_follows_the_diffusion_theory_values_about_any_normal():
    # radiance relative to the normal, per d(sin^2 theta), against the diffusion-theory
    # values for n 1.37-1.40 (0.975, 0.94, 0.88, 0.79, 0.59 at 30, 45, 60, 70, 80 deg)
    rng = np.random.default_rng(2)
    m = 1_500_000
    v = rng.normal(size=(m, 3))
    normal = v / np.linalg.norm(v, axis=1)[:, None]  # every orientation, tangent frames included
    d = redraw_directions(normal, diffuse(1.40).table, rng)
    cos = np.einsum("ij,ij->i", normal, d)
    assert np.all(cos >= 0) and np.allclose(np.linalg.norm(d, axis=1), 1.0)
    hist = exit_angle_histogram(normal, d, np.ones(m))
    e = np.radians(ANGLE_EDGES_DEG)
    per = hist / np.diff(np.sin(e) ** 2)
    mid = np.degrees(np.arccos(np.sqrt(1 - (np.sin(e[1:]) ** 2 + np.sin(e[:-1]) ** 2) / 2)))
    l0 = per[mid < 15].mean()  # flat to 0.3 % below 15 deg for the diffuse profile
    deg, want = [0, 30, 45, 60, 70, 80], [1.0, 0.975, 0.94, 0.88, 0.79, 0.59]
    for k in np.flatnonzero((mid > 20) & (mid < 72)):  # the values interpolated at each 2.5-deg bin
        assert abs(per[k] / l0 - np.interp(mid[k], deg, want)) < 0.02, (mid[k], per[k] / l0)
    assert abs(np.interp(80.0, mid, per / l0) - 0.59) < 0.03  # the steep end, between the bins beside 80 deg
