"""How the light leaves the top of a Monte Carlo box phantom, ring by ring around the point above
its source: the photons in each band of exit angle over what the ``diffuse`` profile (the case's
medium; with and without its depth term) puts there, each ring normalised to its own photons.

Where a row reads 1 everywhere, one profile for the whole surface holds there; a spot's elements
read high head-on and low at grazing angles when the light above a shallow source leaves more
steeply than diffusion says (docs/accuracy.md §1.4).

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
        print("from the foot " + " ".join(f"{lo:.0f}-{hi:.0f} deg".rjust(10) for lo, hi in zip(EDGES_DEG[:-1], EDGES_DEG[1:]))
              + "    photons")
        for i in range(len(RINGS_MM) - 1):
            if counts[i].sum() == 0:
                continue
            row = counts[i] / counts[i].sum() / (model / model.sum())
            print(f"{RINGS_MM[i]:>4.0f}-{RINGS_MM[i + 1]:<3.0f} mm  " + " ".join(f"{x:10.3f}" for x in row)
                  + f"   {counts[i].sum():.3g}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
