"""How far the light leaving a turbid slab drifts away from a buried source, ring by ring.

Photons (fluxcli's Monte Carlo: mu_a 0.01, mu_s' 1 /mm, index n; isotropic scattering, or
Henyey-Greenstein with ``--g`` and mu_s = 1 / (1 - g) /mm, tissue's forward-peaked kind) leave the top of a wide slab
from an isotropic point ``--depth`` mm under it.  Per ring of distance rho from the source's foot
and per band of exit angle, the drift length g the photons imply: the radiance
``M p (1 + g k sin(theta) cos(phi))`` gives a mean radial component ``g k sin^2(theta) / 2``, with
``k = -d ln M / d rho`` from the photons' own exit density (a smooth fit in rho^2).  Beside it:

- the tangential-flux term's g(theta) (``emission.tangent_length``), which takes the field under
  the surface as linear in depth, ``phi = (z + z_b) m(x)``: the same in every ring;
- the term as told the medium's g (``scattering_anisotropy``: the δ-Eddington ray integral,
  ``emission.tangent_length``), "told g" (the same as planar for g 0);
- the same ray integral carried to third order (docs/design.md, "The tangential flux", a limit):
  ``phi(x, z) = phi0 (1 + z / z_b) + z^2 / 2 (c phi0 - lap_t phi0)`` and the ray's sideways walk to
  third order give the drift coefficient ``z_b + 2 mu' + 3 c mu'^2 z_b + z_b (-3 mu'^2 + 3/4
  sin^2(theta')) Q`` (lengths in l) in place of ``z_b + 2 mu'``, with ``Q = grad(lap_t M) . grad M /
  |grad M|^2`` from the photons' exitance. Near the source Q < 0 and the drift is longer.

    $ .venv/bin/python benchmarks/drift_rings.py                  # n 1.40, 6 mm deep, 4e6 photons: ~40 s
    $ .venv/bin/python benchmarks/drift_rings.py --n 1.0 --depth 4
    $ .venv/bin/python benchmarks/drift_rings.py --g 0.9           # tissue's scattering: ~10x the time
"""

from __future__ import annotations

import argparse

import numpy as np

RINGS_MM = ((0.5, 2), (2, 3.5), (3.5, 5), (5, 7), (7, 9), (9, 12), (12, 16))
BANDS_DEG = ((20, 40), (40, 65))


def run(n: float, depth_mm: float, n_photons: int, seed: int = 5, g_hg: float = 0.0) -> None:
    from fluxcli.montecarlo.transport import Medium, Shape, transport
    from fluxcli.optics import emission as E

    top_z, mua, mus = 15.0, 0.01, 1.0  # mus: the reduced scattering coefficient the model is told
    pos, dirs = [], []
    for b in range(max(1, n_photons // 1_000_000)):
        e = transport(Medium(mua, mus / (1.0 - g_hg), g_hg, n), Shape.box((120, 120, 30)), (0, 0, top_z - depth_mm),
                      min(n_photons, 1_000_000), seed=seed, batch=b)
        top = e.position_mm[:, 2] > top_z - 1e-6
        pos.append(e.position_mm[top])
        dirs.append(e.direction[top])
    p, d = np.concatenate(pos), np.concatenate(dirs)
    rho = np.hypot(p[:, 0], p[:, 1])
    d_r = np.einsum("ij,ij->i", d[:, :2], p[:, :2] / np.maximum(rho, 1e-12)[:, None])
    edges = np.arange(0.0, 25.01, 0.25)
    count, _ = np.histogram(rho, edges)
    mid, ring = 0.5 * (edges[1:] + edges[:-1]), np.pi * (edges[1:] ** 2 - edges[:-1] ** 2)
    ok = count > 50
    fit = np.polyfit(mid[ok] ** 2, np.log(count[ok] / ring[ok]), 6, w=np.sqrt(count[ok]))  # even in rho: smooth at the foot

    def M(r):
        return np.exp(np.polyval(fit, r * r))

    h = 1e-3

    def dM(r):
        return (M(r + h) - M(r - h)) / (2 * h)

    def lap(r):  # the surface Laplacian of a radial function
        return (M(r + h) - 2 * M(r) + M(r - h)) / h**2 + dM(r) / np.maximum(r, 1e-6)

    def Q(r):
        return (lap(r + 1e-2) - lap(r - 1e-2)) / 2e-2 / dM(r)

    k = -dM(rho) / M(rho)
    l = 1.0 / (mua + mus)
    zb = 2.0 * E.boundary_A(n) / 3.0
    c = E.depth_term(mus, mua)
    prof = E.diffuse(n, tangential=True, reduced_scattering_per_mm=mus, absorption_per_mm=mua)
    told = E.diffuse(n, tangential=True, reduced_scattering_per_mm=mus, absorption_per_mm=mua, scattering_anisotropy=g_hg)
    print(f"n {n}, g {g_hg}, source {depth_mm} mm deep, {len(rho)} photons leave the top ({n_photons:.3g} launched, seed {seed}); "
          f"l {l:.3f} mm, z_b {zb:.3f} l")
    print(f"{'ring':>11} {'kappa l^2':>9} {'Q l^2':>7} {'band':>6}  {'g photons (mm)':>16}  {'planar':>6}  {'3rd order':>9}"
          f"  {'told g':>6}")
    for r0, r1 in RINGS_MM:
        for lo, hi in BANDS_DEG:
            b = (rho >= r0) & (rho < r1) & (d[:, 2] <= np.cos(np.radians(lo))) & (d[:, 2] > np.cos(np.radians(hi)))
            s2 = 1 - d[b, 2] ** 2
            w = k[b] * s2
            g = 2 * d_r[b].sum() / w.sum()
            sd = 2 * d_r[b].std() * np.sqrt(b.sum()) / w.sum()
            mu = d[b, 2]
            mu_in = np.sqrt(1 - (1 - mu * mu) / n**2)
            base = zb + 2 * mu_in
            third = base + 3 * c * mu_in**2 * zb + zb * (-3 * mu_in**2 + 0.75 * (1 - mu_in**2)) * Q(rho[b]) * l * l
            gm = prof.tangent_weight(mu) / prof.weight(mu)
            gt = told.tangent_weight(mu) / told.weight(mu)
            print(f"{r0:4.1f}-{r1:4.1f} mm {np.mean(lap(rho[b]) / M(rho[b])) * l * l:+9.3f} {np.mean(Q(rho[b])) * l * l:+7.3f} "
                  f"{lo:2d}-{hi:2d}  {g:8.3f} ± {sd:.3f}  {(gm * w).sum() / w.sum():6.3f}  {(gm * third / base * w).sum() / w.sum():9.3f}"
                  f"  {(gt * w).sum() / w.sum():6.3f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=float, default=1.40)
    ap.add_argument("--depth", type=float, default=6.0, help="the source's depth (mm)")
    ap.add_argument("--photons", type=float, default=4e6)
    ap.add_argument("--g", type=float, default=0.0, help="Henyey-Greenstein anisotropy (mu_s = 1 / (1 - g) /mm)")
    a = ap.parse_args()
    with np.errstate(over="ignore", invalid="ignore"):
        run(a.n, a.depth, int(a.photons), g_hg=a.g)


if __name__ == "__main__":
    main()
