"""Photon transport: the analytic box against the same box as a triangle mesh, and a mouse-sized
mesh body (``fluxcli.montecarlo.meshbody``).

Run: .venv/bin/python benchmarks/run.py --only bench_montecarlo   (~1 min on 2 cores)

The issue-21 box (30 x 40 x 20 mm, mu_s 1 /mm, mu_a 0.01 /mm, n 1.40, source 6 mm under the top):
photons per second through the analytic kernel and through a mesh of the box's own faces (2-mm
squares, 2600 triangles), measured in the same run, and their ratio; then an ellipsoid of
semi-axes 25 x 12 x 10 mm split into ~22 000 triangles (a mouse's size and a fine surface's
triangle count). The mesh box also checks its photons are the analytic box's, photon for photon.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fluxcli.montecarlo.meshbody import MeshBody  # noqa: E402
from fluxcli.montecarlo.transport import Medium, Shape, Tally, transport  # noqa: E402
from fluxcli.surface import phantoms  # noqa: E402

PHOTONS = 300_000
MEDIUM = Medium(0.01, 1.0, 0.0, 1.40)


def ellipsoid(a=25.0, b=12.0, c=10.0, n_lat=74, n_lon=150) -> MeshBody:
    s, *_ = phantoms.sphere(radius_mm=1.0, n_latitude=n_lat, n_longitude=n_lon)
    return MeshBody.of(s.vertices_mm * [a, b, c], s.faces)


def _rate(shape, src, seed) -> tuple[float, Tally, object]:
    t = Tally()
    t0 = time.perf_counter()
    e = transport(MEDIUM, shape, src, PHOTONS, seed=seed, tally=t)
    return PHOTONS / (time.perf_counter() - t0), t, e


def run(repeats: int = 3) -> list[dict]:
    from run import row

    box = Shape.box((30, 40, 20))
    surf, *_ = phantoms.box(size_mm=(30, 40, 20), element_mm=2.0)
    mesh_box = MeshBody.of(surf.vertices_mm, surf.faces)
    mouse = ellipsoid()
    for shape, src in ((box, (5, 0, 4)), (mesh_box, (5, 0, 4)), (mouse, (8, 2, 4))):
        transport(MEDIUM, shape, src, 1000, seed=0)  # compile outside the timing
    analytic, meshed, ratio, big, same = [], [], [], [], True
    for k in range(repeats):
        ra, ta, ea = _rate(box, (5, 0, 4), k)
        rm, tm, em = _rate(mesh_box, (5, 0, 4), k)
        rb, _, _ = _rate(mouse, (8, 2, 4), k)
        same &= (ta.escaped, ta.absorbed) == (tm.escaped, tm.absorbed) and np.allclose(ea.position_mm, em.position_mm)
        analytic.append(ra)
        meshed.append(rm)
        ratio.append(rm / ra)
        big.append(rb)
    return [
        row("21", "Monte Carlo, issue-21 box, analytic kernel", "photons/s", analytic),
        row("21", "Monte Carlo, the same box as a 2600-triangle mesh", "photons/s", meshed,
            note="photon for photon the analytic box's" if same else "PHOTONS DIFFER from the analytic box's"),
        row("21", "mesh box / analytic box, same run", "x", ratio),
        row("21", f"Monte Carlo, ellipsoid 50 x 24 x 20 mm as {len(mouse.faces)} triangles", "photons/s", big),
    ]


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    for r in run(1):
        print(f"{r['name']}: {r['median']:.4g} {r['unit']} {r['note']}")
