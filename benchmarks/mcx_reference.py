"""Reference exit-angle radiance of a turbid box from MCX (pmcxcl, OpenCL), run here on CPU.

Issue 21's phantom: a box 30 x 40 x 20 mm, mu_a 0.01 /mm, mu_s 1 /mm, g 0, n 1.40 in air
(Fresnel at every face), an isotropic point source 6 mm under the top face and 5 mm off centre.
MCX (Fang & Boas 2009; the OpenCL port, Yu et al. 2018) transports the photons; every face of
the domain is a detector (``bc='______111111'``), so each photon packet that leaves the box is
recorded with its exit position, its direction after refraction into air, its initial weight
and its path length (``savedetflag='dpxvw'``); its weight on leaving is w0 exp(-mu_a L).

From the photons that leave the top face at least ``--edge-mm`` from its edges, the radiance
in bands of the exit angle theta (from the outward normal) is

    L_band = sum(w) / (N_launched * area * pi * (sin^2 theta_hi - sin^2 theta_lo))

(per launched photon, per mm^2, per sr: the photon count per solid-angle band divided by
cos theta, integrated exactly over the band).  The bands are 5 degrees wide and centred on
0, 5, ..., 85 degrees (the first and last are half bands), so the issue's angles are band
centres.  L(0) is the intercept of a weighted straight-line fit of the bands up to 17.5
degrees against their mean sin^2 theta (for a cos-theta-weighted band average, <sin^2> is the
band's mid value of sin^2, exactly); ``L_rel = L_band / L(0)``.  Standard errors are the Monte
Carlo ones: sqrt(sum w^2) per band, and the fit's for L(0), combined in quadrature.

The script also records the escaped fraction, its share per face and a check of the source
position against the exit points, and writes them with the table to
``data-samples/reference/mcx_box_n140.csv`` (atomically; ``--refractive-index`` makes the
same box of another index, ``mcx_box_n<100 n>.csv``).

Running MCX-CL on a CPU needs an OpenCL runtime: Debian's pocl
(``apt-get install pocl-opencl-icd ocl-icd-libopencl1``) and ``pip install pmcxcl``
(``pip install -e .[mcx]``).  The pmcxcl wheel links its own copy of libstdc++ statically and
exports its symbols; its locale ids (GNU-unique symbols) then shadow those of the system
libstdc++ that pocl's compiler uses, pocl's ``std::stringstream`` fails on the first number it
formats, and the kernel build options are cut short after ``-DPOCL_DEVICE_ADDRESS_BITS=``:
``__OPENCL_VERSION__`` is never defined, pocl_types.h takes its host branch and stops at
"'stdint.h' file not found".  Loading the system libstdc++ globally before pmcxcl (below)
avoids it; no header is missing.

MCX reads ``srcpos`` as 1-based unless ``issrcfrom0=1``: by default this source would sit at
(19, 19, 13), 7 mm deep.  The script sets ``issrcfrom0=1`` and checks that the top-face exits
centre on the source's y (the box is symmetric about it); without the flag they centre on 19.08.

    $ nice -n 5 .venv/bin/python benchmarks/mcx_reference.py                 # n 1.40, ~15 min
    $ nice -n 5 .venv/bin/python benchmarks/mcx_reference.py --refractive-index 1.33
"""

from __future__ import annotations

import argparse
import ctypes
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
REFERENCE_DIR = ROOT / "data-samples" / "reference"

# The phantom (mm; MCX grid of 1 mm voxels with its origin at a corner of the box).
SIZE_MM = (30, 40, 20)
MU_A_PER_MM = 0.01
MU_S_PER_MM = 1.0
G = 0.0
N_MEDIUM = 1.40
DEPTH_MM = 6.0
OFFSET_MM = 5.0
SOURCE_MM = (SIZE_MM[0] / 2 + OFFSET_MM, SIZE_MM[1] / 2, SIZE_MM[2] - DEPTH_MM)
TEND_S = 5e-8  # a photon still inside after 50 ns has walked 10.7 m: weight e^-107
FACES = ("x0", "x30", "y0", "y40", "z0", "z20_top")

# Bands of the exit angle, centred on multiples of 5 degrees.
BAND_EDGES_DEG = np.concatenate([[0.0], np.arange(2.5, 90.0, 5.0), [90.0]])
FIT_MAX_DEG = 17.5


def load_pmcxcl():
    """Import pmcxcl with the system libstdc++ loaded first (see the module docstring)."""
    for name in ("libstdc++.so.6",):
        try:
            ctypes.CDLL(name, mode=ctypes.RTLD_GLOBAL)
        except OSError:
            pass
    import pmcxcl  # noqa: PLC0415

    return pmcxcl


def opencl_devices(pmcxcl) -> list[dict]:
    try:
        return list(pmcxcl.gpuinfo())
    except Exception:  # noqa: BLE001  (no platform: pmcxcl raises a bare RuntimeError)
        return []


def run_chunk(mcx, nphoton: int, seed: int, n_medium: float = N_MEDIUM,
              dtype=np.float64) -> tuple[np.ndarray, dict]:
    """One MCX run (the box of index ``n_medium`` in air) by ``mcx``: pmcxcl, or pmcx (CUDA),
    which takes the same settings.

    Returns the detected photons as rows (ppath_mm, x, y, z, vx, vy, vz, w0) x photons, and
    MCX's own statistics (``energytot``, ``energyabs``, ...)."""
    det, stat = run_chunk_raw(mcx, nphoton, seed, n_medium, dtype)
    return det[1:], stat


def run_chunk_raw(mcx, nphoton: int, seed: int, n_medium: float = N_MEDIUM,
                  dtype=np.float64) -> tuple[np.ndarray, dict]:
    """:func:`run_chunk` with MCX's detector-id row kept in front (9 rows), in the memory order
    MCX gave: its rows cut off, MCX's Fortran-ordered array is neither C nor Fortran contiguous,
    and writing such a view to a file takes several times as long as the run itself."""
    vol = np.ones(SIZE_MM, dtype="uint8")
    prop = np.array([[0.0, 0.0, 1.0, 1.0], [MU_A_PER_MM, MU_S_PER_MM, G, n_medium]])
    res = mcx.run(
        nphoton=int(nphoton), vol=vol, prop=prop, unitinmm=1.0,
        srcpos=list(SOURCE_MM), srcdir=[0, 0, 1], srctype="isotropic",
        tstart=0, tend=TEND_S, tstep=TEND_S,
        issrcfrom0=1, isreflect=1, bc="______111111", issavedet=1, savedetflag="dpxvw",
        maxdetphoton=int(nphoton), seed=int(seed), outputtype="flux",
    )
    det = res["detp"]
    if isinstance(det, dict):  # some versions give the fields by name
        det = np.vstack([np.atleast_2d(np.asarray(det[k], dtype).T if np.ndim(det[k]) > 1 else det[k])
                         for k in ("detid", "ppath", "p", "v", "w0")])
    det = np.asarray(det, dtype=dtype)
    if det.ndim != 2 or det.shape[0] != 9:
        raise RuntimeError(f"unexpected detected-photon array {det.shape} (want 9 rows: d p x3 v3 w)")
    return det, dict(res["stat"])


def classify_faces(pos: np.ndarray, tol: float = 1e-3) -> np.ndarray:
    """Index into FACES of the face each exit point lies on (-1 if none)."""
    face = np.full(pos.shape[1], -1, dtype=np.int64)
    for axis in range(3):
        lo = np.abs(pos[axis]) < tol
        hi = np.abs(pos[axis] - SIZE_MM[axis]) < tol
        face[lo & (face < 0)] = 2 * axis
        face[hi & (face < 0)] = 2 * axis + 1
    return face


class Tally:
    """Sums of weight and weight^2 over the runs, per face and per top-face angle band."""

    def __init__(self, edge_mm: float):
        self.edge_mm = edge_mm
        self.n_launched = 0
        self.n_detected = 0
        self.n_unplaced = 0
        self.n_top_down = 0
        self.face_w = np.zeros(len(FACES))
        self.face_w2 = np.zeros(len(FACES))
        self.band_w = np.zeros(len(BAND_EDGES_DEG) - 1)
        self.band_w2 = np.zeros(len(BAND_EDGES_DEG) - 1)
        self.band_n = np.zeros(len(BAND_EDGES_DEG) - 1, dtype=np.int64)
        self.top_wy = 0.0
        self.top_wy2 = 0.0
        self.top_w_all = 0.0
        self.top_n = 0
        self.mcx_escaped = 0.0  # energytot - energyabs reported by MCX itself

    def add(self, det: np.ndarray, stat: dict | None, nphoton: int, check: bool = True) -> None:
        """Add one run's detected packets (``stat`` None: a slice of a run, whose launched
        photons and MCX statistics are added once by :meth:`add_run`)."""
        ppath, pos, v, w0 = det[0], det[1:4], det[4:7], det[7]
        w = w0 * np.exp(-MU_A_PER_MM * ppath)
        face = classify_faces(pos)
        self.n_launched += nphoton
        self.n_detected += w.size
        self.n_unplaced += int(np.sum(face < 0))
        self.face_w += np.bincount(face[face >= 0], weights=w[face >= 0], minlength=len(FACES))
        self.face_w2 += np.bincount(face[face >= 0], weights=w[face >= 0] ** 2, minlength=len(FACES))
        if stat is not None:
            self.add_run(stat, 0)

        top = face == 5
        x, y = pos[0, top], pos[1, top]
        self.top_w_all += float(np.sum(w[top]))
        self.top_n += int(np.sum(top))
        self.top_wy += float(np.sum(w[top] * y))
        self.top_wy2 += float(np.sum(w[top] * y * y))
        inner = (
            (x >= self.edge_mm) & (x <= SIZE_MM[0] - self.edge_mm)
            & (y >= self.edge_mm) & (y <= SIZE_MM[1] - self.edge_mm)
        )
        cos_t = np.clip(v[2, top][inner], -1.0, 1.0)
        # A photon on the top face must be going up; MCX (float32) lets about one in 10^7 out
        # going down.  They are counted, left out, and must stay that rare.
        down = cos_t < 0
        self.n_top_down += int(np.sum(down))
        wt, cos_t = w[top][inner][~down], cos_t[~down]
        theta_deg = np.degrees(np.arccos(cos_t))
        band = np.clip(np.searchsorted(BAND_EDGES_DEG, theta_deg, side="right") - 1, 0, len(self.band_w) - 1)
        self.band_w += np.bincount(band, weights=wt, minlength=len(self.band_w))
        self.band_w2 += np.bincount(band, weights=wt * wt, minlength=len(self.band_w))
        self.band_n += np.bincount(band, minlength=len(self.band_w))
        if check:
            self.check()

    def add_run(self, stat: dict, nphoton: int) -> None:
        """A run's launched photons and MCX's own escaped energy (its packets added in slices)."""
        self.n_launched += nphoton
        self.mcx_escaped += float(stat["energytot"]) - float(stat["energyabs"])

    def merge(self, other: Tally) -> None:
        """Add another tally's sums (a slice of the same runs, tallied elsewhere)."""
        for k, v in vars(other).items():
            if k != "edge_mm":
                setattr(self, k, getattr(self, k) + v)

    def check(self) -> None:
        if self.n_top_down > 1e-5 * max(self.band_n.sum(), 1e5):
            raise RuntimeError(f"{self.n_top_down} photons leave the top face going down")

    # ---------------------------------------------------------------- results
    def inner_area_mm2(self) -> float:
        return (SIZE_MM[0] - 2 * self.edge_mm) * (SIZE_MM[1] - 2 * self.edge_mm)

    def radiance(self) -> tuple[np.ndarray, np.ndarray]:
        s2 = np.sin(np.radians(BAND_EDGES_DEG)) ** 2
        norm = self.n_launched * self.inner_area_mm2() * np.pi * np.diff(s2)
        return self.band_w / norm, np.sqrt(self.band_w2) / norm

    def l0_fit(self) -> tuple[float, float, float]:
        """Intercept a (L at theta = 0), its SE, and slope b of L = a + b sin^2(theta)."""
        rad, se = self.radiance()
        s2 = np.sin(np.radians(BAND_EDGES_DEG)) ** 2
        u = 0.5 * (s2[:-1] + s2[1:])
        use = BAND_EDGES_DEG[1:] <= FIT_MAX_DEG + 1e-9
        a_mat = np.stack([np.ones(use.sum()), u[use]], axis=1) / se[use, None]
        cov = np.linalg.inv(a_mat.T @ a_mat)
        coef = cov @ (a_mat.T @ (rad[use] / se[use]))
        return float(coef[0]), float(np.sqrt(cov[0, 0])), float(coef[1])


def mcx_description(pmcxcl) -> str:
    from importlib.metadata import version  # noqa: PLC0415

    try:
        pocl = subprocess.run(
            ["dpkg-query", "-W", "-f", "${Version}", "pocl-opencl-icd"],
            capture_output=True, text=True, check=False,
        ).stdout.strip() or "unknown"
    except OSError:
        pocl = "unknown"
    devs = opencl_devices(pmcxcl)
    dev = devs[0]["name"] if devs else "none"
    return f"pmcxcl {version('pmcxcl')} (MCX-CL {pmcxcl.version()}), pocl {pocl}, device '{dev}'"


def write_csv(path: Path, tally: Tally, meta: list[str]) -> None:
    rad, rad_se = tally.radiance()
    l0, l0_se, _ = tally.l0_fit()
    rel = rad / l0
    rel_se = rel * np.sqrt((rad_se / rad) ** 2 + (l0_se / l0) ** 2)
    lo, hi = BAND_EDGES_DEG[:-1], BAND_EDGES_DEG[1:]
    mid = np.where(lo == 0, 0.0, np.where(hi == 90, 90.0, 0.5 * (lo + hi)))
    lines = ["# " + m for m in meta]
    lines.append("theta_lo_deg,theta_hi_deg,theta_centre_deg,n_photons,radiance_per_mm2_sr,"
                 "radiance_se_per_mm2_sr,L_rel,L_rel_se")
    for i in range(len(rad)):
        lines.append(f"{lo[i]:.1f},{hi[i]:.1f},{mid[i]:.1f},{tally.band_n[i]:d},"
                     f"{rad[i]:.6e},{rad_se[i]:.3e},{rel[i]:.5f},{rel_se[i]:.5f}")
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".tmp-", suffix=".csv")
    with os.fdopen(fd, "w") as fh:
        fh.write("\n".join(lines) + "\n")
    os.replace(tmp, path)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--nphoton", type=float, default=1.2e7, help="photons launched in all")
    ap.add_argument("--chunk", type=float, default=2e6, help="photons per MCX run")
    ap.add_argument("--seed", type=int, default=20261125, help="seed of the first run (+1 per run)")
    ap.add_argument("--edge-mm", type=float, default=5.0, help="margin from the top face's edges")
    ap.add_argument("--refractive-index", type=float, default=N_MEDIUM, help="of the box (in air)")
    ap.add_argument("--out", type=Path, default=None,
                    help="default data-samples/reference/mcx_box_n<100 n>.csv")
    args = ap.parse_args(argv)

    n_medium = args.refractive_index
    if args.out is None:
        args.out = REFERENCE_DIR / f"mcx_box_n{round(100 * n_medium):d}.csv"
    pmcxcl = load_pmcxcl()
    if not opencl_devices(pmcxcl):
        print("no OpenCL device: install pocl-opencl-icd (Debian) or a GPU driver", file=sys.stderr)
        return 2
    desc = mcx_description(pmcxcl)
    n_total, chunk = int(args.nphoton), int(args.chunk)
    tally = Tally(args.edge_mm)
    t0 = time.time()
    seeds = []
    while tally.n_launched < n_total:
        n = min(chunk, n_total - tally.n_launched)
        seed = args.seed + len(seeds)
        det, stat = run_chunk(pmcxcl, n, seed, n_medium)
        tally.add(det, stat, n)
        seeds.append(seed)
        print(f"[mcx_reference] {tally.n_launched:.3g} photons, {time.time() - t0:.0f} s", file=sys.stderr)
    wall = time.time() - t0

    n = tally.n_launched
    esc = tally.face_w.sum() / n
    esc_se = np.sqrt(tally.face_w2.sum()) / n
    y_mean = tally.top_wy / tally.top_w_all
    y_se = np.sqrt((tally.top_wy2 / tally.top_w_all - y_mean**2) / tally.top_n)
    if abs(y_mean - SOURCE_MM[1]) > 5 * y_se:
        # the box is symmetric in y about the source: MCX has put it elsewhere
        raise RuntimeError(f"top-face exits centre on y = {y_mean:.3f} +- {y_se:.3f} mm, not on the source's y")
    l0, l0_se, slope = tally.l0_fit()
    faces = "; ".join(
        f"{f} {tally.face_w[i] / n:.5f}+-{np.sqrt(tally.face_w2[i]) / n:.5f}" for i, f in enumerate(FACES)
    )
    meta = [
        "MCX reference: exit-angle radiance at the top face of issue 21's turbid box",
        "made by benchmarks/mcx_reference.py (do not edit by hand; run it again)",
        f"code: {desc}",
        f"box {SIZE_MM[0]}x{SIZE_MM[1]}x{SIZE_MM[2]} mm (1 mm voxels), mu_a {MU_A_PER_MM} /mm, "
        f"mu_s {MU_S_PER_MM} /mm, g {G}, n {n_medium} in air (isreflect=1, Fresnel at every face)",
        f"isotropic point source at ({SOURCE_MM[0]}, {SOURCE_MM[1]}, {SOURCE_MM[2]}) mm: "
        f"{DEPTH_MM} mm under the top face z={SIZE_MM[2]}, {OFFSET_MM} mm off centre in x",
        f"settings: issrcfrom0=1 bc='______111111' savedetflag='dpxvw' tend={TEND_S} s, one time gate, "
        f"{len(seeds)} runs of <= {chunk} photons, seeds {seeds[0]}..{seeds[-1]}",
        f"photons launched {n}, detected {tally.n_detected} (on no face: {tally.n_unplaced}; "
        f"left out, on the top face going down: {tally.n_top_down}); "
        f"wall {wall:.0f} s on 2 shared CPU cores",
        f"escaped fraction {esc:.5f} +- {esc_se:.5f} (MCX's own energy balance: "
        f"{tally.mcx_escaped / n:.5f})",
        f"escaped per face (fraction of launched): {faces}",
        f"source check: weighted mean y of top-face exits {y_mean:.3f} +- {y_se:.3f} mm "
        f"(source y {SOURCE_MM[1]})",
        f"band radiance: weight per launched photon / (area {tally.inner_area_mm2():.0f} mm^2 of the "
        f"top face >= {args.edge_mm} mm from its edges) / (pi (sin^2 hi - sin^2 lo)); exit angle "
        f"theta from the outward normal, in air",
        f"L_rel = band radiance / L(0); L(0) = {l0:.6e} +- {l0_se:.2e} /mm^2/sr from a weighted fit "
        f"L = a + b sin^2(theta) over bands up to {FIT_MAX_DEG} deg (b/a = {slope / l0:.4f}); "
        "L_rel_se combines the band's and L(0)'s MC errors",
        "a band value is the cos(theta) sin(theta)-weighted mean of L over the band, not L at its centre",
    ]
    write_csv(args.out, tally, meta)
    for m in meta[6:]:
        print(m)
    print(args.out.read_text().split("theta_lo_deg", 1)[1])
    return 0


if __name__ == "__main__":
    sys.exit(main())
