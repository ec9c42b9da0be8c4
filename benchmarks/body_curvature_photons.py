"""The body-curvature term of the diffuse profile against photons (docs/design.md, "The body's curvature").

Photons from fluxcli's Monte Carlo leave a sphere (its own mesh, an icosahedron split 5 times, from a
source at its centre: the exitance is the same everywhere) or the battery's cylinder (r 12.5 mm, 50 mm
long, 240 facets around, a source under its top; the round body's light), mu_s 1 /mm, mu_a 0.01 /mm,
g 0, n 1.40.  Their shares by band of exit angle are divided by the shares `diffuse` (its depth term)
predicts, flat and with the body's curvature (H = 1/R on the sphere, 1/2R on the cylinder).

    .venv/bin/python benchmarks/body_curvature_photons.py [--photons 3e6]   # ~2 min on 2 cores
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from fluxcli.montecarlo import transport as MC  # noqa: E402
from fluxcli.montecarlo.meshbody import MeshBody  # noqa: E402
from fluxcli.optics import body_curvature as bc  # noqa: E402
from fluxcli.optics import emission as E  # noqa: E402
from fluxcli.surface import phantoms  # noqa: E402
from test_body_curvature import _icosphere, _model_bands  # noqa: E402

EDGES = np.array([0, 20, 40, 55, 65, 72.5, 80, 90.0])


def bands(surface, source, n_photons: int, side_only: bool = False):
    body = MeshBody.of(surface.vertices_mm, surface.faces)
    hist = 0.0
    for b in range(max(1, n_photons // 1_000_000)):
        e = MC.transport(MC.Medium(0.01, 1.0, 0.0, 1.40), body, np.asarray(source, float),
                         min(n_photons, 1_000_000), seed=5, batch=b)
        nn = body.normals[e.face]
        keep = np.abs(nn[:, 0]) < 0.5 if side_only else np.ones(len(nn), bool)
        cos = np.clip(np.einsum("ij,ij->i", nn, e.direction), 0, 1)[keep]
        hist = hist + np.histogram(np.degrees(np.arccos(cos)), bins=EDGES, weights=e.weight[keep])[0]
    return hist / hist.sum(), np.sqrt(hist) / hist.sum()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--photons", type=float, default=3e6)
    a = ap.parse_args(argv)
    n = int(a.photons)
    prof = E.diffuse(1.40, depth=True, body=True)
    flat = _model_bands(prof.weight, EDGES)
    cases = [(f"sphere R {R:g} mm", _icosphere(R, 5), np.zeros(3), 1 / R, False) for R in (6.0, 12.0, 24.0)]
    cyl = phantoms.cylinder(radius_mm=12.5, length_mm=50, n_angular=240, n_axial=50)[0]
    cases += [(f"cylinder, source {d:g} mm deep", cyl, [0, 0, 12.5 - d], 1 / 25.0, True) for d in (5.0, 12.5)]
    print("bands (deg):", " ".join(f"{lo:g}-{hi:g}" for lo, hi in zip(EDGES[:-1], EDGES[1:])))
    for name, surf, src, H, side in cases:
        shares, sigma = bands(surf, src, n, side)
        curved = _model_bands(lambda m, H=H: prof.weight(m) * bc.factor(prof.body, m, np.full_like(m, H), 1.01), EDGES)
        print(f"{name} ({n:.3g} photons)")
        print("  photons / flat profile:  " + " ".join(f"{x:.3f}" for x in shares / flat))
        print("  photons / with the term: " + " ".join(f"{x:.3f}" for x in shares / curved))
        print("  1 sigma:                 " + " ".join(f"{x:.3f}" for x in sigma / shares))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
