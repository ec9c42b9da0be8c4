"""Issue 21's own experiment on Monte Carlo photons: the issue's camera (f 23.9 mm focused at
317 mm, Ø17 mm, 256 x 256 pixels of 52 µm), its box (30 x 40 x 20 mm, μa 0.01, μs 1 /mm, g 0,
n 1.40), its source (6 mm under the top, 5 mm off centre), its mesh (2-mm elements), nine poses
−90…+60° each alone and jointly, and two 45° mirrors at 6 rotations x 2 stage heights;
``diffuse`` (n 1.40) and ``lambertian`` reconstructed from the same photons.

The issue used 2 x 10⁹ MCX photons; this CPU Monte Carlo runs ~1–2.5 x 10⁵ photons/s on the
shared cores, so the photons are transported once into a **bank** (exit point and direction,
float32, one file per batch of 2 x 10⁶, resumable: ``--transport``) and every experiment images
the bank through its own camera, mirrors and poses (``--run``): the images are whole photons,
the truth per element is the photons that left through it, and no emission model enters.

    $ nice -n 5 .venv/bin/python benchmarks/issue21_box.py --transport 6e7 --seed 1
    $ nice -n 5 .venv/bin/python benchmarks/issue21_box.py --run direct,mirrors,direct-control
    $ nice -n 5 .venv/bin/python benchmarks/issue21_box.py --run close-direct    # the battery's lens, -90..60
    $ .venv/bin/python benchmarks/issue21_box.py --bands     # the bank's exit angles against diffuse(1.40)
    $ .venv/bin/python benchmarks/issue21_box.py --faces runs/issue21/close-m90/reconstruction-diffuse.h5
    $ .venv/bin/python benchmarks/issue21_box.py --rings runs/issue21/close-nine/reconstruction-diffuse.h5
"""

from __future__ import annotations

import argparse
import copy
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import accuracy_mc as AM  # noqa: E402

OUT = AM.ROOT / "runs" / "issue21"
BANK = OUT / "bank"
BATCH = 2_000_000
N_INDEX, SOURCE_MM = 1.40, [5.0, 0.0, 4.0]  # the issue's box: source 6 mm under the top (z 10), 5 mm off centre


def _medium_shape():
    from fluxcli.montecarlo import transport as MC
    return (MC.Medium(AM.TISSUE["mua_per_mm"], AM.TISSUE["mus_per_mm"], AM.TISSUE["g"], N_INDEX),
            MC.Shape.box(AM.BOX["size_mm"]))


def transport(n_photons: float, seed: int) -> None:
    """Transport into the bank, batch by batch (a batch already there is skipped)."""
    from fluxcli.montecarlo import transport as MC
    medium, shape = _medium_shape()
    BANK.mkdir(parents=True, exist_ok=True)
    t0, done = time.perf_counter(), 0
    for b in range(-(-int(n_photons) // BATCH)):
        path = BANK / f"s{seed}-b{b:04d}.npz"
        if path.exists():
            continue
        esc = MC.transport(medium, shape, np.asarray(SOURCE_MM), BATCH, seed=seed, batch=b)
        assert np.all(esc.weight == 1.0)  # analogue absorption: whole photons
        tmp = path.with_suffix(".tmp.npz")
        np.savez(tmp, position_mm=esc.position_mm.astype(np.float32), direction=esc.direction.astype(np.float32),
                 launched=BATCH)
        tmp.replace(path)
        done += BATCH
        print(f"bank {path.name}: {len(esc.weight)} escaped; {done / (time.perf_counter() - t0):.3g} photons/s",
              flush=True)


def bank_from_simulation(sim_path: Path, name: str) -> None:
    """Put the photons a ``keep_photons`` simulate stored into the bank (one file)."""
    import h5py
    path = BANK / f"{name}.npz"
    if path.exists():
        return
    with h5py.File(sim_path) as f:
        launched = int(f["montecarlo"].attrs["launched"])
        pos, d = f["montecarlo/photons/position_mm"][()], f["montecarlo/photons/direction"][()]
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, position_mm=pos.astype(np.float32), direction=d.astype(np.float32), launched=launched)
    tmp.replace(path)


ISSUE_CAMERA = {"pixels": [256, 256], "pixel_pitch_mm": 0.052,
                "lens": {"focal_length_mm": 23.9, "aperture_diameter_mm": 17.0, "focus_distance_mm": 317.0},
                "pose": {"lens_center_mm": [0, 0, 10.0 + 317.0], "look": [0, 0, -1], "up": [0, 1, 0]}}
NINE = [-90, -75, -60, -45, -30, -15, 0, 30, 60]
SIX = [-90, -60, -30, 0, 30, 60]
# name -> camera, element size (mm), rotations, heights, mirrors
EXPERIMENTS = {
    "direct": (ISSUE_CAMERA, 2.0, NINE, [0.0], False),
    "mirrors": (ISSUE_CAMERA, 2.0, SIX, [0.0, 8.0], True),
    "close-direct": (AM.CAMERA, 4.0, [-90, -60, -30, 0, 30, 60], [0.0], False),  # the battery's camera (issue item 2)
    "close-mirrors": (AM.CAMERA, 4.0, [-60, 0, 60], [0.0, 8.0], True),
    "close-m90": (AM.CAMERA, 4.0, [-90], [0.0], False),  # the battery's edge-on pose alone (issue item 2)
    # the issue's 2-mm elements and nine poses through the battery's lens: a pixel covers 0.54 mm of the
    # subject (the issue's camera: 0.64 mm) and it collects ~25x the light, so a 10^8 bank stands in for
    # the issue's 2 x 10^9 photons at the issue's resolution
    "close-nine": (AM.CAMERA, 2.0, NINE, [0.0], False),
}


def configs(name: str) -> dict:
    """The experiment's configs per model (``NAME-control``: the issue's control, reconstructed
    with the profile alone, since its redrawn directions carry no tangential flux; ``mcx-NAME``:
    the same experiment on MCX photons, benchmarks/issue21_mcx.py)."""
    control = name.endswith("-control")
    camera, element_mm, rotations, heights, mirrors = EXPERIMENTS[name.removeprefix("mcx-").removesuffix("-control")]
    AM.CASES[name] = ({**AM.BOX, "element_mm": element_mm}, N_INDEX, SOURCE_MM, rotations, mirrors)
    AM.HEIGHTS[name] = heights
    folder = OUT / "configs"
    folder.mkdir(parents=True, exist_ok=True)
    paths = {}
    for model in AM.models_of(name):
        cfg = AM.config(name, model, 10_000, 0)  # the photons come from the bank, not from this
        cfg["system"]["camera"] = copy.deepcopy(camera)
        cfg["subject"]["surface"]["element_mm"] = element_mm
        cfg["subject"]["poses"]["heights_mm"] = list(heights)
        cfg["transfer"] = {"cache_dir": str(OUT / "T-cache")}
        if control and model == "diffuse":  # the redrawn directions follow P1's profile alone
            cfg["subject"]["emission"]["tangential_flux"] = False
            cfg["subject"]["emission"]["depth_term"] = False
        p = folder / f"{name}-{model}.yaml"
        import yaml
        p.write_text(yaml.safe_dump(cfg))
        paths[model] = p
    return paths


def bank_files(max_photons=None):
    files, n = [], 0
    for path in sorted(BANK.glob("s*.npz")):
        if path.name.endswith(".tmp.npz"):
            continue
        with np.load(path) as z:
            launched = int(z["launched"])
        if max_photons is not None and n + launched > max_photons:
            break
        files.append(path)
        n += launched
    return files, n


def reach_cones(views, placements, rest_shift_mm, radius_mm: float) -> list:
    """Per pose, the cones (in the body's own frame) within which a photon's direction must lie
    to reach a view's (real or virtual) lens: a photon leaving within ``radius_mm`` of the
    body's centre can reach a lens of radius R at distance D only within asin((radius + R) / D)
    of the centre-to-lens line. A cull that changes no count: image_photons tests the rest
    exactly. Returns [(axes (3, V), cos_max (V,))] per pose: a photon of own-frame direction d
    may reach pose k if any d @ axes >= cos_max."""
    out = []
    for R, t in placements:
        c = np.asarray(rest_shift_mm) @ R.T + t  # the body's placed centre
        axes, cos_max = [], []
        for v in views:
            u = v.camera.center_mm - c
            D = float(np.linalg.norm(u))
            e = 1.05 * (radius_mm + v.camera.aperture_radius_mm) + 1.0
            axes.append(R.T @ (u / D))  # a world direction R d against u/D is d against R^T u/D
            cos_max.append(np.sqrt(max(0.0, 1.0 - (e / D) ** 2)) if e < D else -1.0)
        out.append((np.stack(axes, axis=1), np.asarray(cos_max)))
    return out


def image_posed(views, occl, placements, rest_shift_mm, cones, pos, d, normal, seed, ray_offset_mm):
    """Images (P, pixels) and the photons that reached each lens (P, V), of photons given in the
    body's own frame (exit points, unit directions in air, outward normals), at every pose: each
    pose places only the photons its cones let through."""
    from fluxcli.montecarlo import camera as MC_cam
    cam = views[0].camera
    images = np.zeros((len(placements), cam.nx * cam.ny), np.int64)
    reached = np.zeros((len(placements), len(views)), np.int64)
    for k, ((R, t), (axes, cos_max)) in enumerate(zip(placements, cones)):
        sel = np.flatnonzero(np.any(d @ axes >= cos_max, axis=1))
        if sel.size:
            img = MC_cam.image_photons(views, occl[k], (pos[sel] + rest_shift_mm) @ R.T + t, d[sel] @ R.T,
                                       normal[sel] @ R.T, np.random.default_rng([*seed, k]),
                                       ray_offset_mm=ray_offset_mm)
            images[k] = img.counts_per_pixel
            reached[k] = [img.reached_lens[v.name] for v in views]
    return images, reached


def photon_truth(fine, fine_scene, shape, pos) -> np.ndarray:
    """Photons per fine element of the truth surface (own frame), from their exit points."""
    from fluxcli.montecarlo import photons as MC_ph
    face = MC_ph.faces_of_exits(shape, fine.vertices_mm, fine.faces, pos, scene=fine_scene)
    el = np.where(face >= 0, fine.element_of_face[np.maximum(face, 0)], -1)
    return np.bincount(el[el >= 0], minlength=fine.n_elements)


def image_bank(cfg_path: Path, files: list, sim_path: Path, launched: int, redraw=None) -> np.ndarray:
    """Truth and images of the banked photons (as simulate makes them) written into the
    simulation artefact that simulate made for this config (same poses, views and surface)."""
    from fluxcli.config import load_config
    from fluxcli.montecarlo import photons as MC_ph
    from fluxcli.optics.raycast import OcclusionScene
    from fluxcli.truth import truth_refinement

    from diag_mc import mc_scenes

    m, shape, placer, views, scenes, placements, occl = mc_scenes(load_config(cfg_path))
    fine, parent = placer.own_surface.refined(truth_refinement(m.simulate))
    fine_scene = OcclusionScene(fine.vertices_mm, fine.faces)
    cam = views[0].camera
    P = len(scenes)
    cones = reach_cones(views, placements, placer.rest_shift_mm, float(np.linalg.norm(shape.half_mm)))
    images = np.zeros((P, cam.nx * cam.ny), np.int64)
    reached = np.zeros((P, len(views)), np.int64)
    fine_power = np.zeros(fine.n_elements)
    escaped = 0
    for i, path in enumerate(files):
        with np.load(path) as z:
            pos = z["position_mm"].astype(np.float64)
            d = z["direction"].astype(np.float64)
        d /= np.linalg.norm(d, axis=1)[:, None]
        escaped += len(pos)
        normal = shape.outward_normals(pos)
        fine_power += photon_truth(fine, fine_scene, shape, pos)
        if redraw is not None:  # the issue's control: the same exit points, directions from a profile
            d = MC_ph.redraw_directions(normal, redraw, np.random.default_rng([11, i]))
        img, got = image_posed(views, occl, placements, placer.rest_shift_mm, cones, pos, d, normal, (7, i),
                               m.transfer.ray_offset_mm)
        images += img
        reached += got
        print(f"  imaged {path.name} ({i + 1}/{len(files)})", flush=True)
    store_photon_images(sim_path, placer.surface.element_areas_mm2, cam, images, reached, fine_power, parent,
                        launched, escaped, ", ".join(p.name for p in files))
    return images.sum(axis=1)


def store_photon_images(sim_path: Path, element_areas_mm2, cam, images, reached, fine_power, parent,
                        launched: int, escaped: int, source: str) -> None:
    """Write photon images (P, pixels), the photons that reached each lens (P, V) and the truth
    they came with (photons per fine element; ``parent``: its element) into the simulation
    artefact that simulate made for the same config."""
    import h5py
    P = len(images)
    power = np.bincount(parent, weights=fine_power, minlength=len(element_areas_mm2))
    clean = np.asarray(images).reshape(1, P, cam.ny, cam.nx).astype(np.float32)
    with h5py.File(sim_path, "r+") as f:
        f["images/noisy"][0, 0] = clean[0]
        f["images/noiseless"][...] = clean
        f["images/max_snr"][...] = np.sqrt(clean.reshape(1, P, -1).max(axis=2))
        f["truth/power"][...] = power
        f["truth/exitance"][...] = power / element_areas_mm2
        f["truth/power_fine"][...] = fine_power
        f["truth/levels_peak_photons"][...] = [power.max()]
        f["montecarlo/photons_per_element"][...] = power
        f["montecarlo/reached_lens"][...] = reached
        g = f["montecarlo"]
        g.attrs["launched"], g.attrs["escaped"] = launched, escaped
        g.attrs["bank"] = source


def run_experiment(name: str, max_photons=None) -> bool:
    paths = configs(name)
    files, launched = bank_files(max_photons)
    t0 = time.perf_counter()
    sim = simulation_frame(name, paths)
    redraw = None
    if name.endswith("-control"):
        from fluxcli.optics.emission import diffuse
        redraw = diffuse(N_INDEX).table
    imaged = image_bank(paths["diffuse"], files, sim, launched, redraw)
    header = (f"{name}: {launched:.3g} photons launched (bank: {len(files)} files), imaged in "
              f"{time.perf_counter() - t0:.0f} s; heights {AM.HEIGHTS[name]} mm"
              + ("; directions redrawn from diffuse(1.40), reconstructed with its profile alone (the control)"
                 if redraw is not None else ""))
    return reconstruct_models(name, paths, sim, imaged, header, t0)


def simulation_frame(name: str, paths: dict) -> Path:
    """The simulation artefact of the experiment's config (10^4 photons), whose images and truth
    the photons' own then replace."""
    AM.fluxmap("simulate", paths["diffuse"], "--quiet", "--force")
    return OUT / name / "simulation.h5"


def reconstruct_models(name: str, paths: dict, sim: Path, imaged, header: str, t0: float) -> bool:
    """Reconstruct the simulation with each emission model and print the issue's table."""
    results = {}
    for model in AM.models_of(name):
        text = AM.fluxmap("reconstruct", paths[model], "--force")
        kept = OUT / name / f"reconstruction-{model}.h5"
        (OUT / name / "reconstruction.h5").replace(kept)
        res = AM.summarise(kept)
        res["image_over_model"] = AM.forward_check(paths[model], sim)
        res["warnings"] = [ln for ln in text.splitlines() if "warning" in ln.lower()]
        res["photons_in_images"] = np.asarray(imaged).tolist()
        results[model] = res
    results["seconds"] = time.perf_counter() - t0
    print("\n" + header)
    return AM.report(name, results)


FOOT_BANDS_MM = ((0, 1), (1, 2), (2, 4), (4, 6), (6, 9), (9, 13), (13, 18), (18, 30))


EXIT_EDGES_DEG = np.array([0, 10, 30, 50, 60, 70, 75, 80, 85, 90.0])
FACE_NAMES = ("+x", "-x", "+y", "-y", "+z", "-z")


def band_model(edges=EXIT_EDGES_DEG, depth: bool = False) -> np.ndarray:
    """The share of a face's photons that diffuse(1.40) puts in each band of exit angle
    (2 ∫ πp μ dμ over the band): P1's profile, or with ``depth`` the default profile for the
    phantom's medium (with its depth term; the tangential term moves no light between bands
    when averaged over a face's directions)."""
    from fluxcli.optics.emission import diffuse
    mu = np.linspace(0.0, 1.0, 200_001)
    w = diffuse(N_INDEX, depth=depth, reduced_scattering_per_mm=AM.TISSUE["mus_per_mm"] * (1 - AM.TISSUE["g"]),
                absorption_per_mm=AM.TISSUE["mua_per_mm"]).weight(mu)
    return np.array([2 * np.trapezoid(np.where((mu <= np.cos(np.radians(lo))) & (mu >= np.cos(np.radians(hi))),
                                               w * mu, 0.0), mu) for lo, hi in zip(edges[:-1], edges[1:])])


def exit_angles(pos: np.ndarray, d: np.ndarray, shape=None) -> tuple[np.ndarray, np.ndarray]:
    """Each photon's face of the box (index into FACE_NAMES) and exit angle from its normal (deg);
    positions in the box's own frame (centre at 0)."""
    shape = shape if shape is not None else _medium_shape()[1]
    pos, d = np.asarray(pos, np.float64), np.asarray(d, np.float64)
    d = d / np.linalg.norm(d, axis=1)[:, None]
    n = shape.outward_normals(pos)
    theta = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", n, d), -1.0, 1.0)))
    axis = np.argmax(np.abs(n), axis=1)
    return 2 * axis + (n[np.arange(len(n)), axis] < 0), theta


def face_band_counts(pos: np.ndarray, d: np.ndarray, shape=None) -> np.ndarray:
    """Photons per face (rows, FACE_NAMES) and band of exit angle (EXIT_EDGES_DEG)."""
    face, theta = exit_angles(pos, d, shape)
    return np.stack([np.histogram(theta[face == f], bins=EXIT_EDGES_DEG)[0] for f in range(6)])


def print_face_bands(counts: np.ndarray) -> None:
    """Per face, the photons in each band over what diffuse(1.40) puts there, ± the standard
    error: over P1's profile alone, and over the default profile with the depth term."""
    print("exit angle (deg)  " + " ".join(f"{lo:g}-{hi:g}".rjust(11) for lo, hi in zip(EXIT_EDGES_DEG[:-1],
                                                                                     EXIT_EDGES_DEG[1:])))
    for depth, label in ((False, "P1 alone"), (True, "with its depth term (the default)")):
        model = band_model(depth=depth)
        print(f"diffuse(1.40), {label}: " + " ".join(f"{m:.4f}" for m in model))
        for f, name in enumerate(FACE_NAMES):
            N = counts[f].sum()
            print(f"{name} {int(N):>10d} photons, over the model: " + " ".join(
                f"{c / N / m:.3f}±{np.sqrt(c) / N / m:.3f}" for c, m in zip(counts[f], model)))


def exit_bands() -> None:
    """Per face of the box, the bank's photons in bands of exit angle over what diffuse(1.40)
    puts in each band (face-averaged: 2 ∫ πp μ dμ over the band), with the photons' standard
    error: the profile against every photon, not only those a camera catches.  Then the top
    face's photons by their distance from the point straight above the source: the profile is
    not the same everywhere (docs/accuracy.md, "The exit profile is not the same everywhere")."""
    _, shape = _medium_shape()
    counts = np.zeros((6, len(EXIT_EDGES_DEG) - 1))
    top_by_distance = np.zeros((len(FOOT_BANDS_MM), len(EXIT_EDGES_DEG) - 1))
    half, h = np.asarray(AM.BOX["size_mm"], float) / 2, 1.0
    in_plane = [[i for i in range(3) if i != f // 2] for f in range(6)]
    exitance = [np.zeros(tuple((2 * half[ax] / h).astype(int))) for ax in in_plane]
    for path in bank_files()[0]:
        with np.load(path) as z:
            pos, d = z["position_mm"].astype(np.float64), z["direction"].astype(np.float64)
        face, theta = exit_angles(pos, d, shape)
        counts += face_band_counts(pos, d, shape)
        for f, ax in enumerate(in_plane):
            q = pos[face == f][:, ax]
            idx = [np.clip(((q[:, i] + half[ax[i]]) / h).astype(int), 0, exitance[f].shape[i] - 1) for i in range(2)]
            np.add.at(exitance[f], tuple(idx), 1.0 / h**2)
        top = face == 4
        rho = np.hypot(pos[top, 0] - SOURCE_MM[0], pos[top, 1] - SOURCE_MM[1])
        for b, (lo, hi) in enumerate(FOOT_BANDS_MM):
            top_by_distance[b] += np.histogram(theta[top][(rho >= lo) & (rho < hi)], bins=EXIT_EDGES_DEG)[0]
    print_face_bands(counts)
    print_border_flux(exitance, h)
    model = band_model(depth=True)
    print("\nthe top face (+z) by distance from the point above the source, over the default model:")
    for (lo, hi), c in zip(FOOT_BANDS_MM, top_by_distance):
        N = c.sum()
        print(f"{lo:>4g}-{hi:<3g} mm {int(N):>10d} photons: " + " ".join(
            f"{x / N / m:.3f}±{np.sqrt(x) / N / m:.3f}" for x, m in zip(c, model)))


def border_flux_kappa(exitance: list[np.ndarray], h_mm: float) -> np.ndarray:
    """Per face, kappa's power-weighted mean as the exitance's flux through the face's border,
    ``oint dM/dn dl / int M dS`` (1/mm^2), from the exitance binned on an ``h_mm`` grid (one 2-D
    array per face); dM/dn outward at the border, one-sided to second order.  What a planar
    field's Laplacian integrates to over a face (docs/accuracy.md §1.4: the photons do not follow it)."""
    out = []
    for M in exitance:
        def outward(a, b, c):  # a at the border, b and c one and two bins in
            return (3 * a - 4 * b + c) / (2 * h_mm)
        flux = h_mm * (outward(M[0], M[1], M[2]).sum() + outward(M[-1], M[-2], M[-3]).sum()
                       + outward(M[:, 0], M[:, 1], M[:, 2]).sum() + outward(M[:, -1], M[:, -2], M[:, -3]).sum())
        out.append(flux / (M.sum() * h_mm**2))
    return np.array(out)


def band_curvature_ratio(edges=EXIT_EDGES_DEG) -> np.ndarray:
    """The curvature term's ratio r (mm^2) averaged over each band of exit angle with the default
    profile's weight (:func:`fluxcli.optics.emission.curvature_ratio`, the phantom's medium)."""
    from fluxcli.optics.emission import curvature_ratio, depth_term, diffuse
    mus, mua = AM.TISSUE["mus_per_mm"] * (1 - AM.TISSUE["g"]), AM.TISSUE["mua_per_mm"]
    mu = np.linspace(0.0, 1.0, 200_001)
    w = diffuse(N_INDEX, depth=True, reduced_scattering_per_mm=mus, absorption_per_mm=mua).weight(mu) * mu
    r = curvature_ratio(mu, N_INDEX, depth_term(mus, mua), mus + mua)
    out = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        band = (mu <= np.cos(np.radians(lo))) & (mu >= np.cos(np.radians(hi)))
        out.append(np.trapezoid(np.where(band, w * r, 0.0), mu) / np.trapezoid(np.where(band, w, 0.0), mu))
    return np.array(out)


def print_border_flux(exitance: list[np.ndarray], h_mm: float) -> None:
    """Per face: kappa's mean from the border flux, and the bands the curvature term would then
    give the face as a whole over the profile (normalised as the photons' are), to set beside
    the photons' own bands above."""
    kbar, r = border_flux_kappa(exitance, h_mm), band_curvature_ratio()
    model = band_model(depth=True)
    print(f"\nkappa's mean per face from the exitance's flux through its border ({h_mm:g}-mm bins), and the bands"
          " the curvature term would give the face with it:")
    for name, k in zip(FACE_NAMES, kbar):
        pred = 1 + r * k
        pred /= np.sum(pred * model) / model.sum()
        print(f"{name} kappa {k:+.4f} /mm^2: " + " ".join(f"{x:.3f}" for x in pred))


def rings_table(rec_path: Path) -> None:
    """Per pose: the top face's elements by distance from the point above the source, each ring's
    share of the pose's error (points of Eq. 15) and its estimate over its truth (observed
    elements), then the other faces together (docs/accuracy.md §1.4, "Where the −75° error sits")."""
    import h5py
    with h5py.File(rec_path) as f:
        truth, pp, obs = f["truth/power"][()], f["per_pose/power"][()], f["per_pose/observed"][()]
        rots, v, fa, eof = (f[k][()] for k in ("per_pose/rotations_deg", "surface/vertices", "surface/faces",
                                               "surface/element_of_face"))
    n = len(truth)
    cr = np.cross(v[fa[:, 1]] - v[fa[:, 0]], v[fa[:, 2]] - v[fa[:, 0]])
    count = np.bincount(eof, minlength=n)[:, None]
    cen = np.stack([np.bincount(eof, weights=v[fa].mean(axis=1)[:, i], minlength=n) for i in range(3)], 1) / count
    nz = np.bincount(eof, weights=cr[:, 2] / np.linalg.norm(cr, axis=1), minlength=n) / count[:, 0]
    top = nz > 0.9
    rho = np.hypot(cen[:, 0] - SOURCE_MM[0], cen[:, 1] - SOURCE_MM[1])
    rings = ((0, 2.1), (2.1, 4.5), (4.5, 8), (8, 14), (14, np.inf))
    print("pose   error | " + " | ".join(f"top {lo:g}-{hi:g} mm" for lo, hi in rings) + " | other faces   (points, ratio)")
    for k, rot in enumerate(rots):
        o = obs[k]
        err = np.abs(np.nan_to_num(pp[k]) - truth) * o
        tot = truth[o].sum()
        cells = []
        for sel in [top & o & (rho >= lo) & (rho < hi) for lo, hi in rings] + [~top & o]:
            cells.append(f"{100 * err[sel].sum() / tot:4.1f} {np.nansum(pp[k][sel]) / truth[sel].sum():.3f}"
                         if truth[sel].sum() > 0 else "   -      ")
        print(f"{rot:5g} {100 * err.sum() / tot:5.1f} % | " + " | ".join(cells))


def faces_table(rec_path: Path) -> None:
    """Per pose and box face: elements, observed, poorly observed, the truth (all and observed)
    and the estimate over observed elements, as shares of the whole truth; and the mean angle
    from the normal at which the camera sees the observed ones (lens centre)."""
    import h5py
    with h5py.File(rec_path) as f:
        truth = f["truth/power"][()]
        pp, obs, cls = f["per_pose/power"][()], f["per_pose/observed"][()], f["per_pose/observation"][()]
        rots, hts = f["per_pose/rotations_deg"][()], f["per_pose/heights_mm"][()]
        fa, eof = f["surface/faces"][()], f["surface/element_of_face"][()]
        verts = f["per_pose/vertices_mm"][()]
        lens = np.asarray(__import__("json").loads(f.attrs["config_json"])["system"]["camera"]["pose"]["lens_center_mm"])
    n, tot = len(truth), truth.sum()
    for k in range(len(pp)):
        v = verts[k]
        cr = np.cross(v[fa[:, 1]] - v[fa[:, 0]], v[fa[:, 2]] - v[fa[:, 0]])
        cen = np.stack([np.bincount(eof, weights=((v[fa[:, 0]] + v[fa[:, 1]] + v[fa[:, 2]]) / 3)[:, i], minlength=n)
                        for i in range(3)], 1) / np.bincount(eof, minlength=n)[:, None]
        nrm = np.stack([np.bincount(eof, weights=cr[:, i], minlength=n) for i in range(3)], 1)
        nrm /= np.linalg.norm(nrm, axis=1)[:, None]
        to = lens - cen
        ang = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", nrm, to / np.linalg.norm(to, axis=1)[:, None]), -1, 1)))
        o = obs[k]
        print(f"pose h {hts[k]:g} rot {rots[k]:g}: total over observed {np.nansum(pp[k][o]) / truth[o].sum():.3f}")
        # own-frame face of each element: the unplaced normal's largest component
        v0 = verts[k]  # faces keep their identity: group by the placed normal's direction
        key = np.round(nrm, 1)
        for u in np.unique(key, axis=0):
            sel = np.all(key == u, axis=1)
            so = sel & o
            print(f"   normal {u}: {sel.sum():4d} el, obs {so.sum():4d}, poor {(cls[k][sel] == 1).sum():3d}, "
                  f"truth {truth[sel].sum() / tot:.3f} (obs {truth[so].sum() / tot:.3f}), est(obs) "
                  f"{np.nansum(pp[k][so]) / tot:.3f}, angle {np.mean(ang[so]) if so.any() else float('nan'):5.1f} deg")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--transport", type=float, default=0, help="photons to transport into the bank")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--import-sim", default=None, help="a keep_photons simulation.h5 of the same box and source")
    ap.add_argument("--run", default="", help="comma-separated experiments: " + ", ".join(EXPERIMENTS)
                    + " (NAME-control: the issue's control on the same exit points)")
    ap.add_argument("--bands", action="store_true", help="the bank's exit angles per face against diffuse(1.40)")
    ap.add_argument("--faces", default=None, help="a reconstruction.h5: the per-face table")
    ap.add_argument("--rings", default=None, help="a reconstruction.h5: the top face's error ring by ring, per pose")
    ap.add_argument("--max-photons", type=float, default=None, help="use at most this many launched photons of the bank")
    a = ap.parse_args(argv)
    if a.bands:
        exit_bands()
    if a.faces:
        faces_table(Path(a.faces))
    if a.rings:
        rings_table(Path(a.rings))
    if a.import_sim:
        bank_from_simulation(Path(a.import_sim), f"s{a.seed}-imported")
    if a.transport:
        transport(a.transport, a.seed)
    ok = True
    for name in filter(None, a.run.split(",")):
        ok &= run_experiment(name, a.max_photons)
    return 0 if ok else 1

if __name__ == "__main__":
    sys.exit(main())
