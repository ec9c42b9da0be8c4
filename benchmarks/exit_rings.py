"""How the light leaves the top of a Monte Carlo box phantom, ring by ring around the point above
its source: the photons in each band of exit angle over what the ``diffuse`` profile (the case's
medium; with and without its depth term) puts there, each ring normalised to its own photons.

Where a row reads 1 everywhere, one profile for the whole surface holds there; a spot's elements
read high head-on and low at grazing angles where the light above a shallow source leaves more
steeply than the profile says (docs/accuracy.md §1.1, §1.4). Beside the photons it prints what
diffusion theory's own fluence gives through the ray integral behind the profile
(:func:`diffusion_rings`): the position dependence, without the profile's assumption that the
fluence varies with depth alone.

    $ .venv/bin/python benchmarks/exit_rings.py --case box-absorbing --photons 1e8     # ~1 min
    $ .venv/bin/python benchmarks/exit_rings.py --case box-direct --photons 1e8        # ~6 min
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import accuracy_mc as AM  # noqa: E402

EDGES_DEG = np.array([0, 10, 30, 50, 60, 70, 80, 85.0])
RINGS_MM = np.array([0, 1, 2, 4, 6, 9, 15, 25.0])
BATCH = 2_000_000


def band_shares(n: float, medium: dict, depth: bool) -> np.ndarray:
    """The share of a face's photons in each band, 2 ∫ p μ dμ, under ``diffuse``(n) for ``medium``."""
    from fluxcli.optics.emission import diffuse

    mu = np.linspace(0.0, 1.0, 200_001)
    w = diffuse(n, depth=depth, reduced_scattering_per_mm=medium["mus_per_mm"] * (1 - medium["g"]),
                absorption_per_mm=medium["mua_per_mm"]).weight(mu)
    return np.array([2 * np.trapezoid(np.where((mu <= np.cos(np.radians(lo))) & (mu >= np.cos(np.radians(hi))), w * mu, 0.0), mu)
                     for lo, hi in zip(EDGES_DEG[:-1], EDGES_DEG[1:])])


def diffusion_rings(n: float, medium: dict, depth_mm: float) -> np.ndarray:
    """What diffusion theory itself says about the same rings and bands: the fluence of a point
    source ``depth_mm`` under a flat surface (the half-space dipole with the extrapolated boundary,
    z_b = 2AD), carried to the surface by the ray integral of the isotropic scattering source,
    L(x, ŝ) = ∫ μ_s/4π φ(x − s ŝ) e^{−μ_t s} ds, then through the Fresnel boundary. Photons per
    band and ring (unnormalised), as :func:`main` counts them: no emission profile enters."""
    from fluxcli.optics.emission import boundary_A, fresnel_reflectance

    mua, mus = medium["mua_per_mm"], medium["mus_per_mm"] * (1 - medium["g"])  # isotropic, the same mu_s'
    mut = mua + mus
    D = 1 / (3 * mut)
    mueff, zb = np.sqrt(mua / D), 2 * boundary_A(n) * D

    def phi(rho, z):  # z: depth under the surface
        r1, r2 = np.hypot(rho, z - depth_mm), np.hypot(rho, z + depth_mm + 2 * zb)
        return (np.exp(-mueff * r1) / r1 - np.exp(-mueff * r2) / r2) / (4 * np.pi * D)

    m = 360
    out_deg = (np.arange(m) + 0.5) * 90.0 / m  # uniform in the exit angle: the bands near 90 deg are
    thp = np.arcsin(np.sin(np.radians(out_deg)) / n)  # a sliver of inside angles below the critical one
    dthp = np.cos(np.radians(out_deg)) * np.radians(90.0 / m) / (n * np.cos(thp))
    band = np.digitize(out_deg, EDGES_DEG) - 1
    ok = band < len(EDGES_DEG) - 1
    flux = (1 - fresnel_reflectance(np.cos(thp), n)) * np.cos(thp) * np.sin(thp) * dthp
    s = (np.arange(1400) + 0.5) * 0.01 * max(1.0, 1.4 / mut)  # path back along the ray (mm), ~15 transport lengths
    ds = s[1] - s[0]
    azimuths = (np.arange(12) + 0.5) * np.pi / 12  # 0..pi: the rest by symmetry
    out = np.zeros((len(RINGS_MM) - 1, len(EDGES_DEG) - 1))
    for i, (lo, hi) in enumerate(zip(RINGS_MM[:-1], RINGS_MM[1:])):
        for rho in lo + (np.arange(8) + 0.5) * (hi - lo) / 8:
            for a in azimuths:
                x = rho - s[None, :] * (np.sin(thp)[:, None] * np.cos(a))
                y = -s[None, :] * (np.sin(thp)[:, None] * np.sin(a))
                L = mus / (4 * np.pi) * (phi(np.hypot(x, y), s[None, :] * np.cos(thp)[:, None]) * np.exp(-mut * s)).sum(axis=1) * ds
                out[i] += np.bincount(band[ok], weights=(L * flux * rho)[ok], minlength=out.shape[1])
    return out


def print_rings(counts: np.ndarray, model: np.ndarray, photons: bool = True) -> None:
    print("from the foot " + " ".join(f"{lo:.0f}-{hi:.0f} deg".rjust(10) for lo, hi in zip(EDGES_DEG[:-1], EDGES_DEG[1:]))
          + ("    photons" if photons else ""))
    for i in range(len(RINGS_MM) - 1):
        if counts[i].sum() == 0:
            continue
        row = counts[i] / counts[i].sum() / (model / model.sum())
        print(f"{RINGS_MM[i]:>4.0f}-{RINGS_MM[i + 1]:<3.0f} mm  " + " ".join(f"{x:10.3f}" for x in row)
              + (f"   {counts[i].sum():.3g}" if photons else ""))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--case", default="box-absorbing", help="a box case of benchmarks/accuracy_mc.py")
    ap.add_argument("--photons", type=float, default=1e8)
    ap.add_argument("--seed", type=int, default=11)
    a = ap.parse_args(argv)
    from fluxcli.montecarlo import transport as MC

    surface, n, src, _, _ = AM.CASES[a.case]
    if surface["phantom"] != "box":
        raise SystemExit(f"{a.case} is not a box")
    medium = AM.MEDIA.get(a.case, AM.TISSUE)
    size = np.asarray(surface["size_mm"], float)
    src = np.asarray(src, float)
    top = size[2] / 2
    counts = np.zeros((len(RINGS_MM) - 1, len(EDGES_DEG) - 1))
    t0 = time.perf_counter()
    m, shape = MC.Medium(medium["mua_per_mm"], medium["mus_per_mm"], medium["g"], n), MC.Shape.box(size)
    for b in range(-(-int(a.photons) // BATCH)):
        esc = MC.transport(m, shape, src, BATCH, seed=a.seed, batch=b)
        on_top = np.abs(esc.position_mm[:, 2] - top) < 1e-6
        angle = np.degrees(np.arccos(np.clip(esc.direction[on_top, 2], -1.0, 1.0)))
        r = np.hypot(*(esc.position_mm[on_top, :2] - src[:2]).T)
        counts += np.histogram2d(r, angle, bins=[RINGS_MM, EDGES_DEG], weights=esc.weight[on_top])[0]
    print(f"{a.case}: n {n}, mu_a {medium['mua_per_mm']} /mm, mu_s {medium['mus_per_mm']} /mm, g {medium['g']}; source "
          f"{top - src[2]:g} mm under the top; {a.photons:.3g} photons in {time.perf_counter() - t0:.0f} s")
    for label, depth in (("diffuse with its depth term", True), ("P1's profile alone", False)):
        model = band_shares(n, medium, depth)
        print(f"\nphotons in each band over {label} (each ring normalised to its photons up to {EDGES_DEG[-1]:.0f} deg)")
        print_rings(counts, model)
    theory = diffusion_rings(n, medium, top - src[2])
    print(f"\ndiffusion theory's fluence (half-space dipole) through the ray integral, over diffuse with its depth term "
          f"(no photons; the box's other faces are not modelled)")
    print_rings(theory, band_shares(n, medium, True), photons=False)
    return 0


if __name__ == "__main__":
    sys.exit(main())
