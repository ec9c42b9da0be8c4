"""`make accuracy`: how right is fluxmap's answer on realistic, honestly simulated cases?

A benchmark, not a unit test. Every case is simulated honestly — the truth lives on a
surface finer than the reconstruction's elements (each triangle split into 4) and the
forward T is sampled more finely in every key — and reconstructed through the CLI
(`fluxmap build-T | simulate | reconstruct`) with several methods. The `indep-*` cases are
rendered by tests/independent_renderer.py, which shares no code with fluxcli. Two cases emulate an
independent renderer with fluxmap's own forward model: a mesh file whose faces are grouped into elements of 2 x 2 quads by
an integer `element` cell array, images rendered from a 4x finer mesh (each fine quad its
own element, itself refined for the truth) with a 2x finer lens sampling, written as FITS
files and read back by `reconstruct.images`.

Printed per case x method: max SNR, error (paper Eq. 15) and total ratio over observed
elements, total ratio over well-observed elements, chi^2/pixel, lambda, warnings. The
default (smooth, unknowns auto: exitance linear within faces where the camera resolves
elements) is checked against issue 8's bars; "smooth on faces" is the default before
(exitance constant per face), for before/after in one run:
  - never > 10 % off in total over observed elements without a warning;
  - at max SNR >= 30: error < 3 % and total within 2 % over well-observed elements (the error
    is held to 3 % over the observed and over the well-observed elements).

Issue 25 adds: rows "smooth on vertices", "smooth linear elem" and "nnls" (``--methods`` picks
rows); nnls also runs on every further draw, and a draw where the default is more than 1 point
of error worse than nnls is a failure; so is a headline total more than 5 % off without its
reason; the scene25-* cases (its scene from the independent renderer, with and without
mirrors, Poisson peaks 2e3-2e5 and noiseless, 0.5-150 pixels per element) print every draw.

An error is one noise draw's. With ``--draws N`` (``make accuracy`` uses 5) the default also
runs on N - 1 further Poisson/EMCCD draws of the same scene and prints mean +- sd (worst); the
SNR >= 30 bar is then judged on the means (the estimator's expected error, not one draw's
luck), a draw that misses it is marked in the table, and every draw must warn when it is
more than 10 % off.

    $ make accuracy                    # all cases, 5 draws each (~20 min on 2 cores)
    $ .venv/bin/python benchmarks/accuracy.py --cases renderer-direct,emccd-snr30 --draws 1
"""

from __future__ import annotations

import argparse
import copy
import json
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
FLUXMAP = str(Path(sys.executable).parent / "fluxmap")
OUT = ROOT / "runs" / "accuracy"

CAMERA = {
    "pixels": [128, 128], "pixel_pitch_mm": 0.065,
    "lens": {"focal_length_mm": 23.9, "f_number": 2.8, "focus_distance_mm": 317.0},
    "pose": {"lens_center_mm": [0, 0, 338.0], "look": [0, 0, -1], "up": [0, 1, 0]},
    "apertures": [{"distance_mm": 30.0, "diameter_mm": 25.0}],
}
MIRRORS = [
    {"name": "right", "center_mm": [0, 31.14, 14.14], "normal": [0, -1, 1], "axis": [1, 0, 0], "size_mm": [70, 40]},
    {"name": "left", "center_mm": [0, -31.14, 14.14], "normal": [0, 1, 1], "axis": [1, 0, 0], "size_mm": [70, 40]},
]
STAGE = {"top_z_mm": 0.0, "size_mm": [100, 34], "thickness_mm": 5}
CYLINDER = {"phantom": "cylinder", "radius_mm": 12.5, "length_mm": 50, "n_angular": 24, "n_axial": 12}
BLOB = {"kind": "gaussian", "width_mm": 6.0, "peak_photons": 1e6}

DEFAULT = "smooth (default)"  # the row checked against issue 8's bars
METHODS = {
    DEFAULT: [],
    # the default before issue 8's last two cases: exitance constant per face (sub-elements)
    "smooth on faces": ["--set", "reconstruct.unknowns=sub_elements"],
    # issue 25: the default's alternatives on the same images (vertices: 4-5x the unknowns on meshes
    # of grouped quads; elements: exitance constant per element)
    "smooth on vertices": ["--set", "reconstruct.unknowns=vertices"],
    "smooth linear elem": ["--set", "reconstruct.unknowns=linear_elements"],
    "nnls": ["--set", "reconstruct.method=nnls"],
    "paper auto": ["--set", "reconstruct.method=paper", "--set", "reconstruct.lambda=auto"],
    "paper lambda=10": ["--set", "reconstruct.method=paper", "--set", "reconstruct.lambda=10"],
    "mlem 200 it": ["--set", "reconstruct.method=mlem", "--set", "reconstruct.n_iter=200"],
}


# ------------------------------------------------------------------ meshes written as files
def cylinder_mesh(path: Path, *, n_angular: int, n_axial: int, group: int, radius_mm=12.5, length_mm=50.0,
                  axial_lengths=None) -> np.ndarray:
    """A closed cylinder along x whose side quads are grouped ``group`` x ``group`` into
    elements by an integer cell array ``element`` (caps: one element each). With
    ``axial_lengths`` (n_axial,) the rows have those relative lengths (unequal areas).
    Returns the element of each side quad's group for summing a finer truth."""
    import pyvista as pv

    phi = 2 * np.pi * np.arange(n_angular) / n_angular
    w = np.ones(n_axial) if axial_lengths is None else np.asarray(axial_lengths, float)
    x = -length_mm / 2 + length_mm * np.concatenate([[0], np.cumsum(w)]) / w.sum()
    ring = np.stack([np.sin(phi), np.cos(phi)], axis=1) * radius_mm
    verts = [[xi, y, z] for xi in x for y, z in ring]
    faces, elem = [], []
    ne_a, ne_x = n_angular // group, n_axial // group
    for ix in range(n_axial):
        for ia in range(n_angular):
            a, b = ix * n_angular + ia, ix * n_angular + (ia + 1) % n_angular
            c, d = a + n_angular, b + n_angular
            e = (ia // group) * ne_x + ix // group
            faces += [[a, c, b], [b, c, d]]  # outward for a ring running +z -> +y about +x
            elem += [e, e]
    n_side = len(verts)
    verts += [[-length_mm / 2, 0, 0], [length_mm / 2, 0, 0]]
    for k, (ix, sign) in enumerate(((0, -1), (n_axial, 1))):
        for ia in range(n_angular):
            a, b = ix * n_angular + ia, ix * n_angular + (ia + 1) % n_angular
            faces.append([n_side + k, a, b] if sign > 0 else [n_side + k, b, a])
            elem.append(ne_a * ne_x + k)
    verts, faces = np.array(verts, float), np.array(faces)
    # orient every face outward: radially on the side, along -x / +x on the caps
    cen = verts[faces].mean(axis=1)
    nrm = np.cross(verts[faces[:, 1]] - verts[faces[:, 0]], verts[faces[:, 2]] - verts[faces[:, 0]])
    outward = np.c_[np.zeros(len(cen)), cen[:, 1:]]
    cap = np.arange(len(faces)) >= 2 * n_axial * n_angular
    outward[cap] = np.c_[np.sign(cen[cap, 0]), np.zeros((cap.sum(), 2))]
    flip = np.einsum("ij,ij->i", nrm, outward) < 0
    faces[flip] = faces[flip][:, ::-1]
    mesh = pv.PolyData(verts, np.c_[np.full(len(faces), 3), faces].ravel())
    mesh.cell_data["element"] = np.array(elem, np.int32)
    path.parent.mkdir(parents=True, exist_ok=True)
    mesh.save(str(path))
    return np.array(elem)


# ------------------------------------------------------------------ running the CLI
def fluxmap(*args) -> str:
    r = subprocess.run([FLUXMAP, *map(str, args)], capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"fluxmap {' '.join(map(str, args))} failed:\n{r.stdout}\n{r.stderr}")
    return r.stdout + r.stderr


def write(folder: Path, cfg: dict) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    p = folder / "case.yaml"
    cfg = copy.deepcopy(cfg)
    cfg["workdir"] = "run"
    cfg.setdefault("transfer", {})["cache_dir"] = str(OUT / "cache" / "T")
    p.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return p


def simulate_at_snr(cfg_path: Path, snr: float | None) -> float:
    """Simulate; with ``snr`` rescale the peak so the brightest pixel has that max SNR."""
    fluxmap("simulate", cfg_path, "--quiet", "--jobs", "2")
    sim = cfg_path.parent / "run" / "simulation.h5"
    with h5py.File(sim) as f:
        got = float(f["images/max_snr"][0].max())
        peak = float(f["truth/levels_peak_photons"][0])
    if snr is None:
        return got
    fluxmap("simulate", cfg_path, "--quiet", "--jobs", "2", "--set",
            f"simulate.noise.peaks_photons=[{peak * (snr / got) ** 2:.6g}]")
    with h5py.File(sim) as f:
        return float(f["images/max_snr"][0].max())


def metrics(rec: Path, truth: np.ndarray) -> dict:
    with h5py.File(rec) as f:
        p = f["flux/power"][()]
        well = f["flux/well_observed"][()]
        sigma = f["flux/sigma"][()]
        obs = f["flux/observed"][()]
        chi2 = float(np.nanmean(f["per_pose/chi2_per_pixel"][()]))
        lam = float(f.attrs["lambda_used"])
        warns = [w.decode() if isinstance(w, bytes) else str(w) for w in f["warnings"][()]]
        head = f["flux/headline_total"] if "headline_total" in f["flux"] else None
        headline = float(head[()]) if head is not None else np.nan
        head_over = str(head.attrs.get("over", "observed elements")) if head is not None else "observed elements"
        head_reason = str(head.attrs.get("reason", "")) if head is not None else ""
    err = np.abs(p[obs] - truth[obs]).sum() / truth[obs].sum()
    err_well = np.abs(p[well] - truth[well]).sum() / truth[well].sum() if well.any() else np.nan
    return {"error_obs": err, "error_well": err_well, "ratio_obs": p[obs].sum() / truth[obs].sum(),
            "ratio_well": p[well].sum() / truth[well].sum() if well.any() else np.nan,
            "observed": obs.mean(), "well": well.mean(), "chi2": chi2, "lambda": lam, "warnings": warns,
            "truth_seen": truth[obs].sum() / truth.sum(),
            # the first number a user reads, against the truth over the same elements, and why it is not the
            # total over observed elements when it is not
            "headline_ratio": headline / truth[well if head_over.startswith("well") else obs].sum(),
            "headline_reason": head_reason,
            # what the noise alone costs: E|e| = sqrt(2/pi) sigma per element, the reported sigma
            "noise_floor_well": np.sqrt(2 / np.pi) * sigma[well].sum() / truth[well].sum() if well.any() else np.nan}


def reconstruct_all(cfg_path: Path, truth_of, methods=METHODS) -> dict:
    out = {}
    for name, extra in methods.items():
        fluxmap("reconstruct", cfg_path, "--quiet", "--force", "--jobs", "2", *extra)
        rec = cfg_path.parent / "run" / "reconstruction.h5"
        out[name] = metrics(rec, truth_of(rec))
    return out


def truth_from_simulation(rec: Path) -> np.ndarray:
    with h5py.File(rec) as f:
        return f["truth/power"][()]


# ------------------------------------------------------------------ the cases
def base(**over) -> dict:
    cfg = {"system": {"camera": copy.deepcopy(CAMERA), "mirrors": [], "stage": STAGE},
           "subject": {"surface": dict(CYLINDER), "poses": {"heights_mm": [0], "rotations_deg": [0]}},
           "simulate": {"flux": dict(BLOB), "noise": {"model": "poisson", "peaks_photons": [1e6], "seed": 3}},
           "reconstruct": {"joint": False}}
    for k, v in over.items():
        node = cfg
        *head, last = k.split(".")
        for h in head:
            node = node[h]
        node[last] = v
    return cfg


def _folder(name: str, draw: int) -> Path:
    """Draw 0 is the table's; further noise draws run beside it."""
    return OUT / name if draw == 0 else OUT / name / "draws" / str(draw)


def simulated_case(name: str, cfg: dict, snr: float | None):
    def run(draw=0, methods=METHODS):
        c = copy.deepcopy(cfg)
        c["simulate"]["noise"]["seed"] += draw
        p = write(_folder(name, draw), c)
        fluxmap("build-T", p, "--quiet", "--jobs", "2")
        got = simulate_at_snr(p, snr)
        return got, reconstruct_all(p, truth_from_simulation, methods)
    return run


def renderer_case(name: str, mirrors: list, snr: float):
    """The independent-renderer emulation: images from a 4x finer mesh, as files."""
    def run(draw=0, methods=METHODS):
        folder = _folder(name, draw)
        Na, Nz = 24, 12
        coarse = cylinder_mesh(folder / "cylinder.vtk", n_angular=2 * Na, n_axial=2 * Nz, group=2)
        fine_elem = cylinder_mesh(folder / "render" / "cylinder_fine.vtk", n_angular=4 * Na, n_axial=4 * Nz, group=1)
        # fine quad (ia, ix) -> coarse element (ia // 4, ix // 4) on the (Na x Nz) grid; caps map to caps
        n_side_fine = 4 * Na * 4 * Nz
        ia, ix = np.divmod(np.arange(n_side_fine), 4 * Nz)
        fine_to_coarse = np.concatenate([(ia // 4) * Nz + ix // 4, [Na * Nz, Na * Nz + 1]])
        del coarse, fine_elem
        sys_ = {"camera": copy.deepcopy(CAMERA), "mirrors": mirrors, "stage": STAGE}
        fine_lens = {"surface_samples_per_pixel": 4.0, "max_surface_subdivisions": 96, "lens_samples_min": 128,
                     "lens_samples_max": 4096, "lens_samples_per_blur_pixel": 8.0}
        render = {"system": sys_, "subject": {"surface": {"mesh": "cylinder_fine.vtk"}},
                  "transfer": {"lens": fine_lens},
                  "simulate": {"flux": dict(BLOB), "transfer": {"lens": fine_lens}, "allow_inverse_crime": True,
                               "truth_refinement": 1,
                               "noise": {"model": "poisson", "peaks_photons": [1e6], "seed": 21 + draw},
                               "export": {"format": "fits"}}}
        rp = write(folder / "render", render)
        got = simulate_at_snr(rp, snr)
        with h5py.File(rp.parent / "run" / "simulation.h5") as f:
            truth_fine = f["truth/power"][()] * f["truth/level_scale"][0]
        truth = np.bincount(fine_to_coarse, weights=truth_fine, minlength=Na * Nz + 2)
        image = rp.parent / "run" / "images" / "level0" / "h+0_rot0_rep0.fits"
        rec_cfg = {"system": sys_, "subject": {"surface": {"mesh": "cylinder.vtk"}},
                   "reconstruct": {"images": {"files": [str(image)], "units": "photons"}}}
        p = write(folder, rec_cfg)
        fluxmap("build-T", p, "--quiet")
        return got, reconstruct_all(p, lambda rec: truth, methods)
    return run


def unequal_area_case(name: str, snr: float):
    def run(draw=0, methods=METHODS):
        folder = _folder(name, draw)
        cylinder_mesh(folder / "cylinder_unequal.vtk", n_angular=24, n_axial=12, group=1,
                      axial_lengths=np.where(np.arange(12) % 2 == 0, 1.0, 4.0))
        cfg = base()
        cfg["subject"]["surface"] = {"mesh": "cylinder_unequal.vtk"}
        cfg["simulate"]["noise"]["seed"] += draw
        p = write(folder, cfg)
        fluxmap("build-T", p, "--quiet")
        return simulate_at_snr(p, snr), reconstruct_all(p, truth_from_simulation, methods)
    return run


def independent_case(name: str, mirrors: bool, snr: float, **scene):
    """Images from tests/independent_renderer.py (no fluxcli code: numpy Monte Carlo of a
    continuous Gaussian exitance through a thin lens, mirrors by reflection, Poisson noise),
    written as a float TIFF beside a mesh with an `element` cell array, reconstructed through
    the CLI as a user would; the truth is the renderer's integral per element."""
    def run(draw=0, methods=METHODS):
        sys.path.insert(0, str(ROOT / "tests"))
        import independent_renderer as ir

        folder = _folder(name, draw)
        p, truth, clean = ir.blob_scene(folder, mirrors=mirrors, max_snr=snr, noise_draw=draw, **scene)
        write(folder, yaml.safe_load(p.read_text()))  # the shared T cache
        p = folder / "case.yaml"
        fluxmap("build-T", p, "--quiet", "--jobs", "2")
        return float(np.sqrt(clean.max())), reconstruct_all(p, lambda rec: truth, methods)
    return run


def scene25_case(name: str, mirrors: bool, peak_photons: float, camera: dict | None = None, noiseless: bool = False):
    """Issue 25's scene from tests/independent_renderer.py: a 96-gon cylinder mesh of 1168
    elements (VTP, integer `element` cell array) whose images come from the smooth cylinder
    seen by a camera displaced within calibration errors; Poisson at ``peak_photons`` in the
    brightest pixel; the noiseless rendering is shared by the draws (cached in the case's
    folder). ``camera`` overrides pixels and pitch (the pixels-per-element cases)."""
    def run(draw=0, methods=METHODS):
        sys.path.insert(0, str(ROOT / "tests"))
        import independent_renderer as ir

        cam = None
        if camera is not None:
            cam = copy.deepcopy(ir.SCENE25_CAMERA) | dict(camera)
        folder = OUT / name
        p, truth, clean = ir.scene25(folder, mirrors=mirrors, peak_photons=peak_photons,
                                     noise_draw=None if noiseless else draw, camera=cam)
        write(folder, yaml.safe_load(p.read_text()))  # the shared T cache
        p = folder / "case.yaml"
        fluxmap("build-T", p, "--quiet", "--jobs", "2")
        return float(np.sqrt(peak_photons)), reconstruct_all(p, lambda rec: truth, methods)
    return run


def ring_case(name: str, snr: float):
    cfg = {"system": {"camera": {"pixels": [512, 1], "pixel_pitch_mm": 0.013,
                                 "lens": {"focal_length_mm": 23.9, "f_number": 1.4, "focus_distance_mm": 317.0},
                                 "pose": {"lens_center_mm": [0, 0, 338.0], "look": [0, 0, -1], "up": [0, 1, 0]}},
                      "mirrors": []},
           "subject": {"surface": {"phantom": "ring", "radius_mm": 25, "thickness_mm": 1, "n_elements": 100,
                                   "strips_per_element": 5},
                       "poses": {"heights_mm": [-40], "rotations_deg": [0]}},
           "simulate": {"flux": {"kind": "gaussian", "width_mm": 5.0, "peak_photons": 1e7},
                        "noise": {"model": "poisson", "peaks_photons": [1e7], "seed": 4}},
           "reconstruct": {"joint": False, "unknowns": "sub_elements"}}
    return simulated_case(name, cfg, snr)


def cases() -> dict:
    emccd = {"model": "emccd", "peaks_photons": [1e6], "seed": 5}
    c = {
        "top-poisson-snr30": simulated_case("top-poisson-snr30", base(), 30),
        "top-poisson-snr100": simulated_case("top-poisson-snr100", base(), 100),
        "top-poisson-snr5": simulated_case("top-poisson-snr5", base(), 5),
        "emccd-snr30": simulated_case("emccd-snr30", base(**{"simulate.noise": emccd}), 30),
        "emccd-snr10": simulated_case("emccd-snr10", base(**{"simulate.noise": emccd}), 10),
        "limb-rot75": simulated_case("limb-rot75", base(**{"subject.poses": {"heights_mm": [0], "rotations_deg": [75]}}), 30),
        "behind-rot150": simulated_case("behind-rot150", base(**{"subject.poses": {"heights_mm": [0], "rotations_deg": [150]}}), 30),
        "defocus-h-25": simulated_case("defocus-h-25", base(**{"subject.poses": {"heights_mm": [-25], "rotations_deg": [0]}}), 30),
        "focus-h+0-f1.4": simulated_case("focus-h+0-f1.4", _lens(base(), 1.4), 30),
        "mirrors-rot90": simulated_case("mirrors-rot90", base(**{"system.mirrors": MIRRORS,
                                                                  "subject.poses": {"heights_mm": [0], "rotations_deg": [90]}}), 30),
        "unequal-areas": unequal_area_case("unequal-areas", 30),
        "ring-subelements": ring_case("ring-subelements", 30),
        "renderer-direct": renderer_case("renderer-direct", [], 30),
        "renderer-mirrors": renderer_case("renderer-mirrors", MIRRORS, 30),
        "indep-direct": independent_case("indep-direct", False, 30),
        "indep-mirrors": independent_case("indep-mirrors", True, 30),
        "indep-direct-snr10": independent_case("indep-direct-snr10", False, 10),
        # the blob towards the limb (20° is the top view above): what a check with its own scene may do
        "indep-direct-blob45": independent_case("indep-direct-blob45", False, 30, blob_centre_deg=45.0),
        "indep-direct-blob60": independent_case("indep-direct-blob60", False, 30, blob_centre_deg=60.0),
        # a finer mesh: 120 x 48 quads in 2 x 2 elements, 5880 vertices, 0.3 pixels per quad
        "indep-direct-fine": independent_case("indep-direct-fine", False, 30, n_angular=120, n_axial=48),
    }
    # issue 25's scene: 1168 elements, smooth truth, perturbed camera; Poisson peaks 2e3..2e5
    for mirrors in (False, True):
        for peak in (2e3, 2e4, 2e5):
            name = f"scene25-{'mirrors' if mirrors else 'direct'}-peak{peak:.0e}".replace("+0", "")
            c[name] = scene25_case(name, mirrors, peak)
        name = f"scene25-{'mirrors' if mirrors else 'direct'}-noiseless"
        c[name] = scene25_case(name, mirrors, 2e4, noiseless=True)
    # the same scene from 0.5 to ~150 pixels per element (top elements; ~4 at the camera)
    for ppe, pixels, pitch_mm in ((0.5, 90, 0.148), (16, 512, 0.026), (150, 640, 0.0085)):
        name = f"scene25-direct-{ppe:g}px-per-element"
        c[name] = scene25_case(name, False, 2e4, {"pixels": [pixels, pixels], "pixel_pitch_mm": pitch_mm})
    return c


def _lens(cfg, f_number):
    cfg["system"]["camera"]["lens"]["f_number"] = f_number
    return cfg


def _bars(name: str, snr: float, m: dict, fails: list, *, off_only=False) -> str:
    """Issue 8's bars on one default-method result (or on the means over noise draws); issue 25's:
    no headline more than 5 % off without its reason beside it."""
    flag = ""
    if abs(m.get("headline_ratio", 1.0) - 1) > 0.05 and not m.get("headline_reason"):
        flag, _ = "  << headline >5 % off without its reason", fails.append((name, "headline >5 % off, no reason"))
    if abs(m["ratio_obs"] - 1) > 0.10 and not m["warnings"]:
        flag, _ = "  << >10 % off without a warning", fails.append((name, "silent >10 %"))
    # "error < 3 % and total within 2 % over well-observed elements": the error is held
    # to 3 % over the observed and over the well-observed elements (the stricter reading)
    if not off_only and snr >= 29.5 and (max(m["error_obs"], m["error_well"]) >= 0.03
                                         or abs(m["ratio_well"] - 1) >= 0.02):
        flag += "  << misses the SNR>=30 bar"
        fails.append((name, "SNR>=30 bar"))
    return flag


def _vs_nnls(name: str, draw: int, res: dict, fails: list) -> str:
    """Issue 25: on no draw may the default be more than 1 point of error worse than nnls."""
    if "nnls" not in res or res[DEFAULT]["error_obs"] <= res["nnls"]["error_obs"] + 0.01:
        return ""
    fails.append((name, f"draw {draw}: > 1 point worse than nnls"))
    return "  << more than 1 point worse than nnls"


def _spread(name: str, snr: float, draws: list[dict], fails: list) -> str:
    """The default over noise draws: mean +- sd (worst), and the SNR>=30 bar on the means."""
    def col(key, pct):
        v = np.array([d[key] for d in draws]) * (100 if pct else 1)
        worst = v.max() if pct else v[np.argmax(np.abs(v - 1))]
        d = 2 if pct else 3
        return v.mean(), f"{v.mean():.{d}f}{'%' if pct else ''} +- {v.std(ddof=1):.{d}f} ({worst:.{d}f})"
    means = {k: col(k, k.startswith("error"))[0] / (100 if k.startswith("error") else 1)
             for k in ("error_obs", "error_well", "ratio_obs", "ratio_well")}
    over = sum(max(d["error_obs"], d["error_well"]) >= 0.03 for d in draws)
    flag = _bars(name, snr, {**means, "warnings": ["(per draw)"]}, fails)
    return (f"{'':20s} {DEFAULT} over {len(draws)} noise draws, mean +- sd (worst): err obs "
            f"{col('error_obs', True)[1]}, err well {col('error_well', True)[1]}, tot obs "
            f"{col('ratio_obs', False)[1]}, tot well {col('ratio_well', False)[1]}; noise alone over "
            f"well-observed elements (sqrt(2/pi) sum sigma / sum truth) {col('noise_floor_well', True)[1]}"
            + (f"; {over} draw(s) at or above 3 %" if snr >= 29.5 else "") + flag)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", default=None, help="comma-separated case names (default all)")
    ap.add_argument("--draws", type=int, default=1,
                    help="noise draws per case for the default method (draw 0 is the table's); with more "
                         "than one, the SNR>=30 bar is judged on their mean and every draw must warn when >10 %% off")
    ap.add_argument("--methods", default=None,
                    help="comma-separated method rows besides the default (default all): " + ", ".join(METHODS))
    args = ap.parse_args()
    todo = cases()
    names = list(todo) if args.cases is None else args.cases.split(",")
    methods = dict(METHODS) if args.methods is None else {
        k: METHODS[k] for k in [DEFAULT, *args.methods.split(",")] if k in METHODS}
    per_draw = {k: v for k, v in methods.items() if k in (DEFAULT, "nnls")}
    rows, fails = [], []
    print(f"{'case':20s} {'method':17s} {'SNR':>5s} {'err obs':>8s} {'err well':>8s} {'tot obs':>8s} {'tot well':>8s} "
          f"{'obs/well':>9s} {'chi2':>6s} {'lambda':>8s}  warnings")
    for name in names:
        t0 = time.perf_counter()
        snr, res = todo[name](0, methods)
        for method, m in res.items():
            flag = _bars(name, snr, m, fails, off_only=args.draws > 1) if method == DEFAULT else ""
            if method == DEFAULT:
                flag += _vs_nnls(name, 0, res, fails)
            if method == DEFAULT and args.draws > 1 and "SNR>=30" in _bars(name, snr, m, []):
                flag += "  (this draw misses the SNR>=30 bar; judged on the mean below)"
            w = "; ".join(x[:70] for x in m["warnings"]) if m["warnings"] else "-"
            print(f"{name:20s} {method:17s} {snr:5.1f} {100 * m['error_obs']:7.2f}% {100 * m['error_well']:7.2f}% {m['ratio_obs']:8.3f} "
                  f"{m['ratio_well']:8.3f} {m['observed']:4.0%}/{m['well']:4.0%} {m['chi2']:6.2f} "
                  f"{m['lambda']:8.2g}  {len(m['warnings'])}: {w}{flag}", flush=True)
            rows.append({"case": name, "method": method, "max_snr": snr, "draw": 0, **m})
        if args.draws > 1:
            draws = [res[DEFAULT]]
            for k in range(1, args.draws):
                _, more = todo[name](k, per_draw)
                m = more[DEFAULT]
                _bars(name, snr, m, fails, off_only=True)
                flag = _vs_nnls(name, k, more, fails)
                draws.append(m)
                for method, x in more.items():
                    rows.append({"case": name, "method": method, "max_snr": snr, "draw": k, **x})
                print(f"{'':20s} draw {k}: " + ", ".join(
                    f"{method} err obs {100 * x['error_obs']:.2f}% tot obs {x['ratio_obs']:.3f} tot well "
                    f"{x['ratio_well']:.3f}" for method, x in more.items()) + flag, flush=True)
            print(_spread(name, snr, draws, fails), flush=True)
        print(f"{'':20s} ({time.perf_counter() - t0:.0f} s)", flush=True)
    (OUT / "accuracy.json").write_text(json.dumps(rows, indent=1, default=float))
    print(f"\n{len(names)} cases; default-method failures of issue 8's bars: {len(fails)} {fails if fails else ''}")
    print(f"table as JSON: {OUT / 'accuracy.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
