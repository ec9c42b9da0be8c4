"""Why the battery's ellipsoid (``accuracy_mc.py --cases ellipsoid-mesh``) misses issue 21's bars:
the geometry or the emission model?

``cone`` (the default, ~2 min on 2 cores at 1.6e7 photons): photons leave the ellipsoid (the
battery's mesh, medium and source) by fluxcli's Monte Carlo; for each pose's view direction
(rotations about the long axis) the photons leaving within a cone of ``--cone-deg`` about it are
counted per element, and set against what ``diffuse`` says each element sends into that cone,
given the element's own photons (its power) and the least-squares gradient of their exitance
(the tangential flux): by region (distance from the source's foot) and by the cosine of the angle
between the element's normal and the view.  Three variants of the model: ``flat`` (the profile
and tangential term of a flat surface), ``body`` (with the body's curvature, the default) and
``bodyprof`` (the body's curvature in the profile only).  A ratio of 1 in every row is a model
that the reconstruction can invert without bias; 1.04 against 0.91 on two sides of one cap is
light the model puts on the wrong side.

``--bands`` (~2 min at 8e6 photons): the same photons' exit angles, azimuth-averaged (the
tangential flux's odd part cancels), in bands per region, over ``diffuse``'s profile: flat, with
the body's curvature, and with the body's curvature and the curvature term (kappa = lap_t M / M
from the photons' own exitance, fitted over two element widths as reconstruct does). With
``--body cylinder`` the same on a finely faceted cylinder (r 12.5 mm) with a source 5 mm deep.

``--control N``: the issue's own control at N photons: the same exit points, every direction
redrawn from the flat ``diffuse`` profile, imaged through the battery's camera and reconstructed
with exactly that profile (no tangential, depth or curvature term): what the ellipsoid's geometry
and observation cost alone (10^8 photons: ~15 min).

    $ .venv/bin/python benchmarks/ellipsoid_photons.py
    $ .venv/bin/python benchmarks/ellipsoid_photons.py --bands
    $ .venv/bin/python benchmarks/ellipsoid_photons.py --bands --body cylinder
    $ .venv/bin/python benchmarks/ellipsoid_photons.py --control 1e8
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
import accuracy_mc as AM  # noqa: E402

CASE = "ellipsoid-mesh"
ROTATIONS = (-60, -30, 0, 30, 60)


def _surface():
    import pyvista as pv

    from fluxcli.surface.mesh import validated

    folder = AM.OUT / "configs"
    folder.mkdir(parents=True, exist_ok=True)
    AM.write_ellipsoid(folder)
    s = pv.read(str(folder / "ellipsoid.vtp"))
    f = s.faces.reshape(-1, 4)[:, 1:]
    return validated(s.points, f, np.arange(len(f)), len(f))[0]


def cone(n_photons: int, cone_deg: float, seed: int = 13) -> None:
    from fluxcli.optics import body_curvature as bc
    from fluxcli.optics import emission as E

    surf, body, n, src, batches = _photons(n_photons, seed)
    medium = AM.TISSUE
    F = len(body.faces)
    assert F == surf.n_elements  # one triangle an element
    # the camera (world +z) in the body's frame at each pose: a pose turns the body by R_x(rotation)
    views = {a: np.array([0.0, np.sin(np.radians(a)), np.cos(np.radians(a))]) for a in ROTATIONS}
    cosd = np.cos(np.radians(cone_deg))
    W = np.zeros(F)
    count = {a: np.zeros(F) for a in views}
    for e in batches:
        W += np.bincount(e.face, e.weight, F)
        for a, v in views.items():
            m = e.direction @ v >= cosd
            count[a] += np.bincount(e.face[m], e.weight[m], F)
    S, cen, nrm = E.element_geometry(surf)
    tl = E.tangent_light(surf, W).reshape(-1, 2)  # -S grad M in each face's frame
    fr = E.face_frames(surf.vertices_mm[surf.faces])
    grad_ln_M = -(tl[:, :1] * fr[:, 0] + tl[:, 1:] * fr[:, 1]) / np.maximum(W, 1e-300)[:, None]
    transport = medium["mus_per_mm"] * (1 - medium["g"]) + medium["mua_per_mm"]
    prof = E.diffuse(n, depth=True, tangential=True, body=True, reduced_scattering_per_mm=transport - medium["mua_per_mm"],
                     absorption_per_mm=medium["mua_per_mm"])
    H = bc.mean_curvature(surf, bc.fit_radius_mm(surf, transport))
    rng = np.random.default_rng(0)
    omega = 2 * np.pi * (1 - cosd)

    def predict(v, variant):
        u = 1 - rng.random(400) * (1 - cosd)
        ph = rng.random(400) * 2 * np.pi
        a = np.cross(v, [1.0, 0, 0])
        a /= np.linalg.norm(a)
        d = u[:, None] * v + np.sqrt(1 - u * u)[:, None] * (np.cos(ph)[:, None] * a + np.sin(ph)[:, None] * np.cross(v, a))
        mu = nrm @ d.T
        mup = np.clip(mu, 0, 1)
        Hm = np.repeat(H[:, None], len(d), 1)
        fb = bc.factor(prof.body, mup, Hm, transport) if variant != "flat" else 1.0
        ft = bc.factor(prof.body_tangent, mup, Hm, transport) if variant == "body" else 1.0
        dens = np.where(mu > 0, mup * (prof.weight(mup) * fb - prof.tangent_weight(mup) * ft * (grad_ln_M @ d.T)) / np.pi, 0)
        return W * dens.mean(axis=1) * omega

    r = np.hypot(cen[:, 0] - src[0], cen[:, 1] - src[1])
    print(f"{n_photons:.3g} photons (seed {seed}); photons within {cone_deg:g} deg of each view over diffuse's "
          "prediction (flat / body / bodyprof), by distance from the source's foot and cos(normal, view)")
    for a, v in views.items():
        c = nrm @ v
        pred = {k: predict(v, k) for k in ("flat", "body", "bodyprof")}
        print(f"view {a:+d} deg: {count[a].sum():.0f} photons; all " + " ".join(
            f"{k} {count[a].sum() / p.sum():.3f}" for k, p in pred.items()))
        for name, m in (("r < 6 mm", r < 6), ("r 6-12", (r >= 6) & (r < 12)), ("r 12-20", (r >= 12) & (r < 20))):
            for cn, cm in (("cos > 0.7", c > 0.7), ("cos 0.4-0.7", (c > 0.4) & (c <= 0.7)), ("cos < 0.4", (c > 0) & (c <= 0.4))):
                k = count[a][m & cm].sum()
                if k > 300:
                    print(f"   {name:9s} {cn:12s} {k:8.0f} ({k / count[a].sum():4.0%}) " + " ".join(
                        f"{key} {k / p[m & cm].sum():.3f}" for key, p in pred.items()) + f"   1 sd {1 / np.sqrt(k):.3f}")


CYLINDER_R_MM, CYLINDER_DEPTH_MM = 12.5, 5.0  # --body cylinder: the battery's radius, a source 5 mm under the top


def _cylinder():
    """A finely faceted cylinder (120 x 60 facets, each face an element), axis along x."""
    from fluxcli.surface import phantoms
    from fluxcli.surface.mesh import Surface

    s = phantoms.cylinder(radius_mm=CYLINDER_R_MM, length_mm=60, n_angular=120, n_axial=60)[0]
    return Surface(s.vertices_mm, s.faces, np.arange(len(s.faces)), len(s.faces))


def _photons(n_photons: int, seed: int, which: str = "ellipsoid"):
    """The ellipsoid (or the cylinder), its mesh body and the photons leaving it, 10^6 at a time."""
    from fluxcli.montecarlo import transport as MC
    from fluxcli.montecarlo.meshbody import MeshBody

    if which == "cylinder":
        surf, n, src = _cylinder(), 1.40, [0.0, 0.0, CYLINDER_R_MM - CYLINDER_DEPTH_MM]
    else:
        surf = _surface()
        _, n, src, _, _ = AM.CASES[CASE]
    body = MeshBody.of(surf.vertices_mm, surf.faces)
    m = AM.TISSUE
    batches = (MC.transport(MC.Medium(m["mua_per_mm"], m["mus_per_mm"], m["g"], n), body, np.array(src, float),
                            1_000_000, seed=seed, batch=b) for b in range(max(1, n_photons // 1_000_000)))
    return surf, body, n, np.array(src, float), batches


def bands(n_photons: int, seed: int = 17, which: str = "ellipsoid") -> None:
    from fluxcli.optics import body_curvature as bc
    from fluxcli.optics import emission as E

    surf, body, n, src, batches = _photons(n_photons, seed, which)
    F = len(body.faces)
    edges = np.array([0, 20, 35, 45, 55, 65, 75, 90.0])
    counts, W = np.zeros((F, len(edges) - 1)), np.zeros(F)
    for e in batches:
        cos = np.clip(np.einsum("ij,ij->i", body.normals[e.face], e.direction), 0, 1)
        band = np.clip(np.digitize(np.degrees(np.arccos(cos)), edges) - 1, 0, len(edges) - 2)
        np.add.at(counts, (e.face, band), e.weight)
        W += np.bincount(e.face, e.weight, F)
    S, cen, nrm = E.element_geometry(surf)
    transport = AM.TISSUE["mus_per_mm"] * (1 - AM.TISSUE["g"]) + AM.TISSUE["mua_per_mm"]
    K = E.curvature_operator(surf, radius_mm=2.0 * float(np.sqrt(np.median(S))))
    kappa = np.clip((K @ W) / np.maximum(W, 1e-300), -E.KAPPA_L2_MAX * transport**2, E.KAPPA_L2_MAX * transport**2)
    prof = E.diffuse(n, depth=True, body=True, curvature=True, reduced_scattering_per_mm=transport - AM.TISSUE["mua_per_mm"],
                     absorption_per_mm=AM.TISSUE["mua_per_mm"])
    H = bc.mean_curvature(surf, bc.fit_radius_mm(surf, transport))
    th = np.radians(np.linspace(0, 90, 9001)[1:-1])
    mu = np.cos(th)

    def share(w):  # photons per band under radiance weight w(mu)
        o = np.array([(w * mu * np.sin(th))[(th >= np.radians(a)) & (th < np.radians(b))].sum()
                      for a, b in zip(edges[:-1], edges[1:])])
        return o / o.sum()

    if which == "cylinder":  # along the surface from the source's foot (the top line, x = 0)
        r = np.hypot(CYLINDER_R_MM * np.arctan2(cen[:, 1], cen[:, 2]), cen[:, 0])
        side = np.abs(nrm[:, 0]) < 0.5
        regions = [(f"r {a}-{b}" if a else f"r < {b} mm", side & (r >= a) & (r < b)) for a, b in ((0, 4), (4, 8), (8, 12), (12, 20))]
        regions.append(("the whole side", side))
    else:
        r = np.hypot(cen[:, 0] - src[0], cen[:, 1] - src[1])
        regions = [("r < 4 mm, top", (r < 4) & (nrm[:, 2] > 0.5)), ("r 4-8, top", (r >= 4) & (r < 8) & (nrm[:, 2] > 0.5)),
                   ("r 8-12", (r >= 8) & (r < 12)), ("r 12-20", (r >= 12) & (r < 20)), ("sides", np.abs(nrm[:, 2]) < 0.3)]
    print(f"{which}: {n_photons:.3g} photons (seed {seed}); exit angles per band over diffuse's (depth term): flat / with the "
          "body's curvature / with it and the curvature term; bands " + " ".join(f"{a:.0f}-{b:.0f}" for a, b in
                                                                              zip(edges[:-1], edges[1:])) + " deg")
    for name, m in regions:
        ph = counts[m].sum(axis=0) / counts[m].sum()
        w = W[m] / W[m].sum()
        flat = share(prof.weight(mu))
        body_ = sum(wi * share(prof.weight(mu) * bc.factor(prof.body, mu, np.full_like(mu, h), transport))
                    for wi, h in zip(w, H[m]))
        both = sum(wi * share(prof.weight(mu) * bc.factor(prof.body, mu, np.full_like(mu, h), transport)
                              * (1 + prof.curvature_ratio(mu) * k)) for wi, h, k in zip(w, H[m], kappa[m]))
        print(f"{name:14s} {counts[m].sum():9.0f} photons, kappa {np.sum(w * kappa[m]):+.3f} /mm^2, 1 sd "
              + " ".join(f"{x:.3f}" for x in 1 / np.sqrt(counts[m].sum(axis=0))))
        for label, model in (("flat", flat), ("body", body_), ("body+kappa", both)):
            print(f"   {label:11s} " + " ".join(f"{x:.3f}" for x in ph / model))


def control(n_photons: int, seed: int = 2) -> None:
    from typer.testing import CliRunner

    from fluxcli.cli import app
    from fluxcli.montecarlo import photons as PH
    from fluxcli.montecarlo import transport as MC
    from fluxcli.optics.emission import diffuse

    folder = AM.OUT / "configs"
    folder.mkdir(parents=True, exist_ok=True)
    AM.write_ellipsoid(folder)
    cfg = AM.config(CASE, "diffuse", n_photons, seed)
    cfg["workdir"] = "../ellipsoid-control"
    cfg["subject"]["emission"] |= {"tangential_flux": False, "depth_term": False, "body_curvature": False}
    path = folder / "ellipsoid-control.yaml"
    path.write_text(yaml.safe_dump(cfg))
    table = diffuse(AM.CASES[CASE][1]).table
    rng = np.random.default_rng(7)
    transport = MC.transport

    def redrawn(medium, shape, *a, **k):  # the same exit points; directions from the profile
        e = transport(medium, shape, *a, **k)
        e.direction = PH.redraw_directions(shape.normals[e.face], table, rng)
        return e

    MC.transport = redrawn
    try:
        r = CliRunner().invoke(app, ["simulate", str(path), "--quiet", "--force"])
        assert r.exit_code == 0, r.output
    finally:
        MC.transport = transport
    AM.fluxmap("reconstruct", path, "--force", "--quiet")
    res = AM.summarise(AM.OUT / "ellipsoid-control" / "reconstruction.h5")
    print(f"control ({n_photons:.3g} photons, directions redrawn from flat diffuse, reconstructed with it): totals "
          + " ".join(f"{x:.3f}" for x in res["ratio"]) + f", spread {res['spread']:.1%}, errors "
          + " ".join(f"{x:.1%}" for x in res["error"]) + f", joint {res['joint_ratio']:.3f} / {res['joint_error']:.1%}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--photons", type=float, default=1.6e7, help="photons for the cone check")
    ap.add_argument("--cone-deg", type=float, default=10.0)
    ap.add_argument("--bands", action="store_true", help="the exit-angle bands by region instead (8e6 photons unless --photons)")
    ap.add_argument("--body", choices=("ellipsoid", "cylinder"), default="ellipsoid",
                    help="--bands on the battery's ellipsoid or on a cylinder (r 12.5 mm, source 5 mm deep)")
    ap.add_argument("--control", type=float, default=0.0, help="run the redrawn control at this many photons instead")
    a = ap.parse_args()
    if a.control:
        control(int(a.control))
    elif a.bands:
        bands(int(a.photons) if "--photons" in sys.argv else 8_000_000, which=a.body)
    else:
        cone(int(a.photons), a.cone_deg)


if __name__ == "__main__":
    main()
