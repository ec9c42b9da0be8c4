"""The photon Monte Carlo (fluxcli/montecarlo) against numbers it did not produce, and
``simulate.flux.kind: montecarlo`` end to end, checked by brute-force geometry on the stored
exit photons."""

from __future__ import annotations

import json

import h5py
import numba
import numpy as np
import pytest
from typer.testing import CliRunner

from fluxcli.cli import app
from fluxcli.montecarlo import photons as PH
from fluxcli.montecarlo.transport import Medium, Shape, Tally, _next, _scatter, _splitmix64, transport

runner = CliRunner()

# Radiance leaving a box of mu_s' 1/mm, mu_a 0.01/mm, n 1.40 into air relative to the normal,
# from 2e9 MCX photons (issue 21): angle (deg) -> L/L(0)
MCX_PROFILE_N140 = {30: 0.972, 45: 0.936, 60: 0.873, 70: 0.781, 80: 0.563}


def issue_box_profile(n_photons: int, seed: int = 0) -> dict[int, float]:
    shape = Shape.box((30, 40, 20))
    hist = np.zeros(len(PH.ANGLE_EDGES_DEG) - 1)
    for b in range(0, n_photons, 1_000_000):
        e = transport(Medium(0.01, 1.0, 0.0, 1.40), shape, (5, 0, 4), min(1_000_000, n_photons - b), seed=seed, batch=b)
        hist += PH.exit_angle_histogram(shape.outward_normals(e.position_mm), e.direction, e.weight)
    mid, prof = PH.radiance_profile(hist)
    return {a: float(np.interp(a, mid, prof)) for a in MCX_PROFILE_N140}


# ------------------------------------------------------------------ transport
def test_every_photon_is_absorbed_or_escapes_and_absorption_matches_the_track_length():
    t = Tally()
    e = transport(Medium(0.05, 1.0, 0.5, 1.37), Shape.cylinder(6.0, 20.0), (1, 2, -1), 20_000, seed=3, tally=t)
    assert t.lost == 0 and t.escaped + t.absorbed == t.launched == 20_000
    assert len(e.weight) == t.escaped and np.all(e.weight == 1.0)
    # independent estimator: absorption events happen at rate mu_a per mm travelled
    expected = 0.05 * t.path_mm
    assert abs(t.absorbed - expected) < 4 * np.sqrt(expected)
    # exits lie on the cylinder and leave outwards, in unit directions
    p = e.position_mm
    on_side = np.isclose(np.hypot(p[:, 1], p[:, 2]), 6.0, atol=1e-9)
    on_cap = np.isclose(np.abs(p[:, 0]), 10.0, atol=1e-9)
    assert np.all(on_side | on_cap)
    assert np.allclose(np.linalg.norm(e.direction, axis=1), 1.0)
    assert np.all(np.einsum("ij,ij->i", Shape.cylinder(6.0, 20.0).outward_normals(p), e.direction) > 0)


def test_same_seed_same_photons_on_any_thread_count():
    args = (Medium(0.01, 1.0, 0.0, 1.4), Shape.box((10, 12, 8)), (1, 1, 1), 5000)
    old = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        a = transport(*args, seed=7)
        numba.set_num_threads(old)
        b = transport(*args, seed=7)
    finally:
        numba.set_num_threads(old)
    c = transport(*args, seed=8)
    assert np.array_equal(a.position_mm, b.position_mm) and np.array_equal(a.direction, b.direction)
    assert len(c.weight) != len(a.weight) or not np.array_equal(a.position_mm, c.position_mm)


@numba.njit
def _draw_cosines(g, n):
    st = np.empty(2, np.uint64)
    x, st[0] = _splitmix64(np.uint64(11))
    x, st[1] = _splitmix64(x)
    out = np.empty(n)
    for i in range(n):
        d = _scatter(st, g, 0.6, 0.0, 0.8)
        out[i] = 0.6 * d[0] + 0.8 * d[2]
    return out


def test_henyey_greenstein_moments_and_exact_isotropy_at_g0():
    # HG: <cos> = g, <cos^2> = (1 + 2 g^2) / 3; g = 0: cos uniform on [-1, 1]
    c = _draw_cosines(0.75, 200_000)
    assert c.mean() == pytest.approx(0.75, abs=0.005)
    assert (c**2).mean() == pytest.approx((1 + 2 * 0.75**2) / 3, abs=0.005)
    c0 = _draw_cosines(0.0, 200_000)
    h = np.histogram(c0, bins=20, range=(-1, 1))[0]
    assert np.all(np.abs(h - 10_000) < 5 * 100)  # each bin within 5 sigma of uniform
    assert c0.mean() == pytest.approx(0.0, abs=0.005)


def test_slab_against_van_de_hulst_as_used_to_validate_mcml():
    """Wang, Jacques & Zheng 1995 (MCML), matched slab: albedo 0.9, g 0.75, n 1,
    mu_a 10/cm, mu_s 90/cm, 0.02 cm thick (optical thickness 2), normal pencil beam:
    total diffuse reflectance 0.09739 and total transmittance 0.66096 (van de Hulst)."""
    t = Tally()
    n = 60_000
    e = transport(Medium(0.1, 0.9, 0.75, 1.0), Shape.box((2e5, 2e5, 2.0)), (0, 0, 1 - 1e-9), n,
                  beam_direction=(0, 0, -1), seed=1, tally=t)
    rd = (e.position_mm[:, 2] > 0).sum() / n
    tt = (e.position_mm[:, 2] < 0).sum() / n
    assert rd == pytest.approx(0.09739, abs=4 * np.sqrt(0.09739 * 0.90261 / n))
    assert tt == pytest.approx(0.66096, abs=4 * np.sqrt(0.66096 * 0.33904 / n))


def test_spatially_resolved_reflectance_against_the_diffusion_dipole():
    """Farrell, Patterson & Wilson 1992: a pencil beam on a semi-infinite medium (matched
    boundary: A = 1, z_b = 2D), mu_a 0.01/mm, mu_s 1/mm, g 0. Each scattering depth z
    (density mu_s e^{-mu_t z}) is an isotropic source with its image at -(z + 2 z_b); the
    reflectance is the dipoles' diffusion flux, integrated over annuli 4-15 mm (4-15
    transport mean free paths, where diffusion holds to a few per cent). Also the total
    diffuse reflectance against the dipole's closed form (Farrell Eq. 12 style, one source
    at z0 = 1/mu_t')."""
    mua, musp = 0.01, 1.0
    n = 150_000
    e = transport(Medium(mua, musp, 0.0, 1.0), Shape.box((4e3, 4e3, 400.0)), (0, 0, 200 - 1e-9), n,
                  beam_direction=(0, 0, -1), seed=2)
    top = e.position_mm[:, 2] > 0
    rho = np.hypot(e.position_mm[top, 0], e.position_mm[top, 1])
    mut = mua + musp
    mueff = np.sqrt(3 * mua * mut)
    zb = 2 / (3 * mut)
    # total: a'/2 (1 + exp(-4/3 A sqrt(3(1 - a')))) exp(-sqrt(3(1 - a'))), A = 1
    ap = musp / mut
    k = np.sqrt(3 * (1 - ap))
    assert top.sum() / n == pytest.approx(ap / 2 * (1 + np.exp(-4 / 3 * k)) * np.exp(-k), rel=0.02)
    zs = np.linspace(0, 15, 3001)[1:]
    w = musp * np.exp(-mut * zs) * (zs[1] - zs[0])
    edges = np.array([4.0, 6.0, 8.0, 10.0, 15.0])
    for lo, hi in zip(edges[:-1], edges[1:]):
        r = np.linspace(lo, hi, 401)[:, None]
        r1, r2 = np.sqrt(zs**2 + r**2), np.sqrt((zs + 2 * zb) ** 2 + r**2)
        R = (w / (4 * np.pi) * (zs * (mueff + 1 / r1) * np.exp(-mueff * r1) / r1**2
                                + (zs + 2 * zb) * (mueff + 1 / r2) * np.exp(-mueff * r2) / r2**2)).sum(axis=1)
        expected = np.trapezoid(2 * np.pi * r[:, 0] * R, r[:, 0]) * n
        got = ((rho >= lo) & (rho < hi)).sum()
        assert got == pytest.approx(expected, rel=0.05 + 4 / np.sqrt(expected)), (lo, hi, got, expected)


def test_exit_angles_follow_the_mcx_profile_ci_size():
    """The issue's phantom: the radiance profile of the escaping photons against MCX's (2e9
    photons). 1.2e6 photons: about 1 % noise on each value (L(0) from a fit included)."""
    prof = issue_box_profile(1_200_000)
    for a in (30, 45, 60, 70):
        assert prof[a] == pytest.approx(MCX_PROFILE_N140[a], abs=0.03), (a, prof)


@pytest.mark.slow
def test_exit_angles_follow_the_mcx_profile_within_2_percent_of_L0():
    """4e6 photons (about 0.5 % noise): within 0.02 of L(0) up to 70 deg, 0.03 at 80 deg."""
    prof = issue_box_profile(4_000_000, seed=1)
    for a in MCX_PROFILE_N140:
        assert prof[a] == pytest.approx(MCX_PROFILE_N140[a], abs=0.02 if a <= 75 else 0.03), (a, prof)
