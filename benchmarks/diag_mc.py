"""Where the per-pose error of the Monte Carlo box comes from (issue 21 diagnosis).

One photon run (exit points and directions kept), then reconstructions of:
- ``mc``: the images of the photons as they left the box;
- ``redrawn``: the same exit points, each direction redrawn from the ``diffuse`` profile
  (the issue's own control: if the error falls to ~2-3 %, what remains is physics: the
  exit-angle distribution varies over the surface);
and variants (reconstruct overrides). Printed per pose: error, total, lambda, chi^2/px, and the
error split by viewing angle of the element (<= 60 deg / > 60 deg) and by the distance of the
element centre to the nearest box edge (< 4 mm / >= 4 mm).

    $ nice -n 5 .venv/bin/python benchmarks/diag_mc.py --photons 1e7 --rotations 0,30,60
    $ ... --skip-sim --variants drift,lamx0.1,lamx10,elements     # on the same photons
    $ ... --photons 2e7 --rotations 0,30 --camera issue-wide --element-mm 2
"""

from __future__ import annotations

import argparse
import copy
import shutil
import sys
from pathlib import Path

import h5py
import numpy as np
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
import accuracy_mc as AM  # noqa: E402

OUT = AM.ROOT / "runs" / "diag_mc"


def make_config(tag, rotations, photons, element_mm, camera, reconstruct, seed=0, case="box-direct"):
    cfg = AM.config(case, "diffuse", photons, seed)
    cfg["workdir"] = f"../{tag}"
    cfg["subject"]["poses"]["rotations_deg"] = list(rotations)
    cfg["subject"]["surface"]["element_mm"] = element_mm
    if camera is not None:
        cfg["system"]["camera"] = copy.deepcopy(camera)
    cfg["simulate"]["flux"]["keep_photons"] = True
    cfg["transfer"] = {"cache_dir": str(OUT / "T-cache")}  # one T per geometry, shared by every variant
    cfg["reconstruct"] = {"joint": False, **reconstruct}
    p = OUT / "configs" / f"{tag}.yaml"
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(yaml.safe_dump(cfg))
    return p


def mc_scenes(cfg):
    """What imaging photons needs of a loaded config: (model, body shape, placer, views, placed
    scenes, their placements, an occlusion scene per pose)."""
    from fluxcli.optics.raycast import OcclusionScene
    from fluxcli.scene import poses_from_config, views_from_config
    from fluxcli.stages.plans import placer_of
    from fluxcli.surface.mesh import merge
    from fluxcli.truth import montecarlo_shape

    m = cfg.model
    placer = placer_of(cfg)
    scenes = [placer.scene(p, m.system) for p in poses_from_config(m.subject)]
    return (m, montecarlo_shape(m.subject.surface), placer, views_from_config(m.system), scenes,
            [placer.placement(s.pose) for s in scenes], [OcclusionScene(*merge(s.surface, *s.occluders)) for s in scenes])


def reimage(cfg_path, pos, dirn, batch=1_000_000):
    """Images (P, ny, nx) of the given photons (own frame), as simulate makes them."""
    from fluxcli.config import load_config
    from fluxcli.montecarlo import camera as MC_cam

    m, shape, placer, views, scenes, placements, occl = mc_scenes(load_config(cfg_path))
    cam = views[0].camera
    images = np.zeros((len(scenes), cam.nx * cam.ny), np.int64)
    for b in range(0, len(pos), batch):
        p, d = pos[b:b + batch], dirn[b:b + batch]
        normal = shape.outward_normals(p)
        for k, (R, t) in enumerate(placements):
            img = MC_cam.image_photons(views, occl[k], (p + placer.rest_shift_mm) @ R.T + t, d @ R.T, normal @ R.T,
                                       np.random.default_rng([7, b, k]), ray_offset_mm=m.transfer.ray_offset_mm)
            images[k] += img.counts_per_pixel
    return images.reshape(len(scenes), cam.ny, cam.nx)


def element_geometry(f, half):
    """Per element: centroid and unit normal (own frame), distance of the centroid to the
    nearest box edge (mm)."""
    v, fa, eof = f["surface/vertices"][()], f["surface/faces"][()], f["surface/element_of_face"][()]
    n_el = int(f["surface"].attrs["n_elements"])
    a, b, c = v[fa[:, 0]], v[fa[:, 1]], v[fa[:, 2]]
    cr = np.cross(b - a, c - a)
    area = 0.5 * np.linalg.norm(cr, axis=1)
    cen = np.stack([np.bincount(eof, weights=area * ((a + b + c) / 3)[:, i], minlength=n_el) for i in range(3)], 1)
    cen /= np.bincount(eof, weights=area, minlength=n_el)[:, None]
    nrm = np.stack([np.bincount(eof, weights=cr[:, i], minlength=n_el) for i in range(3)], 1)
    nrm /= np.linalg.norm(nrm, axis=1)[:, None]
    h = np.asarray(half)
    axis = np.argmax(np.abs(nrm), axis=1)
    slack = h[None, :] - np.abs(cen)
    slack[np.arange(n_el), axis] = np.inf
    return cen, nrm, slack.min(axis=1)


def summarise(rec_path, sim_path, cfg_path, half):
    from fluxcli.config import load_config
    cfg = load_config(cfg_path)
    lens = np.asarray(cfg.model.system.camera.pose.lens_center_mm, float)
    with h5py.File(sim_path) as f:
        truth = f["truth/power"][()]
    with h5py.File(rec_path) as f:
        pp, obs = f["per_pose/power"][()], f["per_pose/observed"][()]
        lam = f["per_pose/lambda"][()]
        chi = f["per_pose/chi2_per_pixel"][()] if "per_pose/chi2_per_pixel" in f else np.full(len(pp), np.nan)
        rots = f["per_pose/rotations_deg"][()]
        verts = f["per_pose/vertices_mm"][()] if "per_pose/vertices_mm" in f else None
        cen, nrm, edge = element_geometry(f, half)
        v0, fa, eof = f["surface/vertices"][()], f["surface/faces"][()], f["surface/element_of_face"][()]
    rows = []
    for k in range(len(pp)):
        o = obs[k]
        # placed element centroids and normals from the placed vertices (same faces)
        v = verts[k]
        a, b, c = v[fa[:, 0]], v[fa[:, 1]], v[fa[:, 2]]
        cr = np.cross(b - a, c - a)
        area = 0.5 * np.linalg.norm(cr, axis=1)
        n_el = len(truth)
        wc = np.stack([np.bincount(eof, weights=area * ((a + b + c) / 3)[:, i], minlength=n_el) for i in range(3)], 1)
        wc /= np.bincount(eof, weights=area, minlength=n_el)[:, None]
        wn = np.stack([np.bincount(eof, weights=cr[:, i], minlength=n_el) for i in range(3)], 1)
        wn /= np.linalg.norm(wn, axis=1)[:, None]
        to_cam = lens - wc
        to_cam /= np.linalg.norm(to_cam, axis=1)[:, None]
        ang = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", wn, to_cam), -1, 1)))
        T = truth[o].sum()
        err = np.abs(np.nan_to_num(pp[k]) - truth)
        split = {}
        for name, sel in (("<=60", ang <= 60), (">60", ang > 60), ("edge<4", edge < 4.0), ("edge>=4", edge >= 4.0)):
            s = o & sel
            split[name] = (err[s].sum() / T, err[s].sum() / max(truth[s].sum(), 1e-300), truth[s].sum() / T)
        rows.append(dict(rot=float(rots[k]), total=float(np.nansum(pp[k][o]) / T), error=float(err[o].sum() / T),
                         lam=float(lam[k]), chi=float(chi[k]), split=split))
    return rows


def show(label, rows):
    for r in rows:
        s = r["split"]
        print(f"{label:<22} {r['rot']:>5.0f} err {r['error']:6.1%} tot {r['total']:.3f} lam {r['lam']:9.3g} chi2/px "
              f"{r['chi']:6.2f} | <=60: {s['<=60'][0]:5.1%} (rel {s['<=60'][1]:5.1%}, b {s['<=60'][2]:4.0%}) "
              f">60: {s['>60'][0]:5.1%} (rel {s['>60'][1]:5.1%}, b {s['>60'][2]:4.0%}) | "
              f"edge<4: {s['edge<4'][0]:5.1%} (rel {s['edge<4'][1]:5.1%}, b {s['edge<4'][2]:4.0%}) "
              f"edge>=4: {s['edge>=4'][0]:5.1%} (rel {s['edge>=4'][1]:5.1%})", flush=True)


def reconstruct(cfg_path, tag, label, overrides=None, images=None, emission=None):
    """Reconstruct in a copy of the run's folder (own simulation.h5 with ``images`` when given)."""
    cfg = yaml.safe_load(cfg_path.read_text())
    src = OUT / cfg["workdir"].split("/")[-1]
    dst = OUT / f"{tag}--{label}"
    dst.mkdir(exist_ok=True)
    sim = dst / "simulation.h5"
    shutil.copyfile(src / "simulation.h5", sim)
    if images is not None:
        with h5py.File(sim, "r+") as f:
            f["images/noisy"][0, 0] = images.astype(np.float32)
            f["images/noiseless"][0] = images.astype(np.float32)
    cfg["workdir"] = f"../{dst.name}"
    cfg["reconstruct"].update(overrides or {})
    em = {**cfg["subject"]["emission"], **(emission or {})}
    cfg["subject"]["emission"] = {k: v for k, v in em.items() if v is not None}
    p = OUT / "configs" / f"{dst.name}.yaml"
    p.write_text(yaml.safe_dump(cfg))
    AM.fluxmap("reconstruct", p, "--force")
    half = [x / 2 for x in cfg["subject"]["surface"]["size_mm"]]
    rows = summarise(dst / "reconstruction.h5", sim, p, half)
    show(label, rows)
    return rows


def tangential_drift(sim_path, source_xy=(5.0, 0.0), top_z=10.0):
    """Over the top face: the mean tangential component of the exit directions away from the
    source's foot, and the photons leaving 25-35 deg from the normal heading away from it over
    those heading towards it (|tangential cosine| > 0.25), by distance from the foot."""
    with h5py.File(sim_path) as f:
        p, d = f["montecarlo/photons/position_mm"][()], f["montecarlo/photons/direction"][()]
    top = p[:, 2] > top_z - 1e-6
    p, d = p[top], d[top]
    r = p[:, :2] - np.asarray(source_xy)
    rho = np.linalg.norm(r, axis=1)
    dt = np.einsum("ij,ij->i", d[:, :2], r / np.maximum(rho, 1e-9)[:, None])
    band = (d[:, 2] > np.cos(np.radians(35))) & (d[:, 2] < np.cos(np.radians(25)))
    for lo, hi in ((0, 2), (2, 4), (4, 6), (6, 9), (9, 13), (13, 20)):
        s = (rho >= lo) & (rho < hi)
        away, toward = (s & band & (dt > 0.25)).sum(), (s & band & (dt < -0.25)).sum()
        print(f"top face, {lo:>2}-{hi:<2} mm from the source's foot: {s.sum():8d} photons, <d_t> {dt[s].mean():+.4f}, "
              f"25-35 deg away/towards {away / max(toward, 1):.3f}", flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--photons", type=float, default=1e7)
    ap.add_argument("--rotations", default="0,30,60")
    ap.add_argument("--element-mm", type=float, default=4.0)
    ap.add_argument("--camera", default="battery", choices=["battery", "issue", "issue-wide"])
    ap.add_argument("--variants", default="mc,redrawn")
    ap.add_argument("--tag", default=None)
    ap.add_argument("--skip-sim", action="store_true")
    ap.add_argument("--case", default="box-direct", help="an accuracy_mc case: its phantom, source and mirrors")
    a = ap.parse_args(argv)
    rot = [float(x) for x in a.rotations.split(",")]
    cam = None
    if a.camera != "battery":
        cam = {"pixels": [256, 256], "pixel_pitch_mm": 0.052,
               "lens": {"focal_length_mm": 23.9, "aperture_diameter_mm": 17.0 if a.camera == "issue" else 60.0,
                        "focus_distance_mm": 317.0},
               "pose": {"lens_center_mm": [0, 0, 10.0 + 317.0], "look": [0, 0, -1], "up": [0, 1, 0]}}
    tag = a.tag or f"{a.camera}-e{a.element_mm:g}-p{a.photons:.0e}"
    p = make_config(tag, rot, int(a.photons), a.element_mm, cam, {}, case=a.case)
    if not a.skip_sim:
        print(AM.fluxmap("simulate", p)[-1500:], flush=True)
    sim = OUT / tag / "simulation.h5"
    with h5py.File(sim) as f:
        print("photons per image:", f["images/noisy"][0, 0].reshape(len(rot), -1).sum(1))
    for v in a.variants.split(","):
        if v == "drift":
            tangential_drift(sim)
        elif v == "mc":
            reconstruct(p, tag, "mc")
        elif v == "redrawn":
            with h5py.File(sim) as f:
                pos, dirn = f["montecarlo/photons/position_mm"][()], f["montecarlo/photons/direction"][()]
            from fluxcli.truth import montecarlo_shape
            from fluxcli.config import load_config
            shape = montecarlo_shape(load_config(p).model.subject.surface)
            from fluxcli.montecarlo.photons import redraw_directions
            from fluxcli.optics.emission import diffuse
            d2 = redraw_directions(shape.outward_normals(pos), diffuse(1.40).table, np.random.default_rng(11))
            imgs = reimage(p, pos, d2)
            print("redrawn photons per image:", imgs.reshape(len(rot), -1).sum(1))
            reconstruct(p, tag, "redrawn", images=imgs, emission={"tangential_flux": False, "depth_term": False})  # P1 alone
        elif v.startswith("lam"):  # lamx0.1 / lamx10: lambda fixed at factor x the mc pick (per pose, median)
            fac = float(v[4:])
            with h5py.File(OUT / f"{tag}--mc" / "reconstruction.h5") as f:
                lam = float(np.median(f["per_pose/lambda"][()]))
            reconstruct(p, tag, v, overrides={"lambda": lam * fac})
        elif v == "elements":
            reconstruct(p, tag, v, overrides={"unknowns": "elements"})
        elif v == "notangent":  # diffuse without its tangential-flux term (the profile in theta only)
            reconstruct(p, tag, v, emission={"tangential_flux": False})
        elif v == "lambertian":
            reconstruct(p, tag, v, emission={"model": "lambertian", "refractive_index": None})
    return 0


if __name__ == "__main__":
    sys.exit(main())
