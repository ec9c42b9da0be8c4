"""Issue 21: what the emission model does to the totals of a turned subject (forward-model check).

Run: .venv/bin/python benchmarks/bench_emission.py   (~1-2 min on 2 busy cores)

A cylinder (r 10 mm, 32 x 6 elements) glowing from a Gaussian patch 20 deg off its top is
turned about its axis from -90 to +60 deg and seen by one camera 320 mm away.  Images are
rendered with the ``diffuse(1.40)`` profile through a finer T (4 surface samples per pixel,
64+ lens samples) than the one reconstruction uses (1.5, 32+), with Poisson noise, and each
pose is reconstructed alone (non-negative weighted least squares) with T built under
``diffuse(1.40)`` and under ``lambertian``: the totals over the observed elements against the
truth on those elements, their spread over poses, the share of the total resting on elements seen beyond 75 deg and
the residual-vs-angle test (blind here: one view per element, whose scale the fit absorbs).

This is *not* the Monte Carlo check of issue 21 (the images come from the same profile family
that reconstructs them, only sampled differently): it shows the size of the Lambertian error on
a pose sweep, and that the diagnostics flag it.  The real-transport check is the
``simulate.flux.kind: montecarlo`` battery.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
from scipy.optimize import lsq_linear

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fluxcli.inverse import diagnostics as D  # noqa: E402
from fluxcli.optics import emission as E  # noqa: E402
from fluxcli.optics.camera import ThinLensCamera  # noqa: E402
from fluxcli.optics.transfer import LensSampling, build_transfer, views_for  # noqa: E402
from fluxcli.surface import phantoms  # noqa: E402

ROTATIONS_DEG = (-90, -60, -30, 0, 30, 60)
PEAK_PHOTONS_PER_MM2 = 2e8


def rotation_x(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])


def main() -> None:
    t0 = time.perf_counter()
    rest = phantoms.cylinder(radius_mm=10, length_mm=30, n_angular=32, n_axial=6)[0]
    cam = ThinLensCamera.from_pose(lens_center_mm=[0, 0, 320], look=[0, 0, -1], up=[0, 1, 0], focal_length_mm=25,
                                   aperture_radius_mm=25 / 8, focus_distance_mm=320, nx=96, ny=96, pixel_pitch_mm=0.06)
    views = views_for(cam, [])
    c = rest.element_centroids_mm
    src = np.array([0.0, 10 * np.sin(np.radians(20)), 10 * np.cos(np.radians(20))])
    truth = rest.element_areas_mm2 * PEAK_PHOTONS_PER_MM2 * np.exp(-np.sum((c - src) ** 2, axis=1) / (2 * 6.0**2))
    profiles = {"diffuse": E.diffuse(1.40), "lambertian": E.lambertian()}
    rng = np.random.default_rng(21)
    rows = []
    for rot in ROTATIONS_DEG:
        surf = rest.transformed(rotation_x(rot), np.zeros(3))
        fine = build_transfer(surf, views, emission=profiles["diffuse"],
                              lens_sampling=LensSampling(surface_samples_per_pixel=4, lens_samples_min=64))
        a = rng.poisson(fine.T @ truth).astype(float)
        for name, prof in profiles.items():
            res = build_transfer(surf, views, emission=prof, lens_sampling=LensSampling(surface_samples_per_pixel=1.5))
            T = res.T.tocsc()
            col = np.asarray(T.sum(axis=0)).ravel()
            keep = col > 1e-3 * col.max()
            sd = np.sqrt(np.maximum(a, 1.0))
            A = (T[:, keep].toarray() / sd[:, None])
            b = np.full(len(col), np.nan)
            b[keep] = lsq_linear(A, a / sd, bounds=(0, np.inf), lsmr_tol="auto").x
            fitted = T @ np.nan_to_num(b)
            ang = D.element_angles(surf, [cam.center_mm], prof.weight)
            shares = D.total_shares(res.T_per_view, [1.0], b, ang)
            st = D.angle_structure(a, fitted, np.maximum(fitted, 1.0), D.pixel_angles(res.T_per_view, [1.0], b, ang))
            ratio = np.nansum(b) / truth[keep].sum()
            err = np.nansum(np.abs(np.nan_to_num(b)[keep] - truth[keep])) / truth[keep].sum()
            rows.append((rot, name, ratio, err, shares[1], None if st is None else st.t))
    print(f"{'rotation':>8} {'model':>10} {'total/truth':>11} {'L1 error':>8} {'total>75':>8} {'t(angle)':>8}")
    for rot, name, ratio, err, s75, t in rows:
        print(f"{rot:>8} {name:>10} {ratio:>11.4f} {err:>8.3f} {s75:>8.1%} {'-' if t is None else f'{t:.1f}':>8}")
    for name in profiles:
        r = np.array([x[2] for x in rows if x[1] == name])
        print(f"{name}: totals {r.min():.4f}-{r.max():.4f} of the truth on the observed elements, "
              f"spread (max-min)/mean {(r.max() - r.min()) / r.mean():.1%}")
    print(f"{time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
