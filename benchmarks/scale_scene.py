"""Issue 22's scene at a chosen element count: paper-3d's rig with a 1024 x 1024 sensor of 13 um
pixels (three views: direct and two mirrors), a 25 x 50 mm cylinder of N elements, one pose, a
Gaussian spot of light and Poisson noise.

Run: .venv/bin/python benchmarks/scale_scene.py 20000 [--workdir runs/scale-20000]
writes <workdir>/scale.yaml (a complete config: `fluxmap build-T|simulate|reconstruct` it) and
prints its path.  ``benchmarks/bench_scale.py`` uses :func:`write_config`.

The cylinder's elements are kept near square: n_angular / n_axial ~ circumference / length
(78.5 / 50), so 2 000 -> 56 x 36, 20 000 -> 177 x 113 (the issue's 200 x 100 is also accepted
as --grid 200 100), 50 000 -> 280 x 179.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import yaml

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
PAPER_3D = ROOT / "configs" / "paper-3d.yaml"


def grid_for(n_elements: int) -> tuple[int, int]:
    """(n_angular, n_axial) with about ``n_elements`` near-square elements on the 12.5 x 50 mm cylinder."""
    aspect = 2 * math.pi * 12.5 / 50.0
    n_axial = max(2, round(math.sqrt(n_elements / aspect)))
    return max(3, round(n_elements / n_axial)), n_axial


# the brightest element's power at 20 000 elements that gives a max SNR (sqrt of the brightest pixel) of
# about 30 (measured: 5e4 gave 1.1); other counts keep the same exitance (power per element ~ 1/N)
PEAK_AT_20000 = 3.7e7


def peak_for(n_elements: int) -> float:
    return PEAK_AT_20000 * 20000 / n_elements


def scene(n_angular: int, n_axial: int, *, workdir: Path, peak_photons: float | None = None, seed: int = 1) -> dict:
    """The config as a dict (paper-3d's system, the issue's camera and subject)."""
    if peak_photons is None:
        peak_photons = peak_for(n_angular * n_axial)
    cfg = yaml.safe_load(PAPER_3D.read_text())
    cam = cfg["system"]["camera"]
    cam["pixels"] = [1024, 1024]
    cam["pixel_pitch_mm"] = 0.013
    cfg["workdir"] = str(workdir)
    cfg["subject"] = {"surface": {"phantom": "cylinder", "radius_mm": 12.5, "length_mm": 50,
                                  "n_angular": int(n_angular), "n_axial": int(n_axial)},
                      "poses": {"heights_mm": [0], "rotations_deg": [0]}}
    # a spot on the flank that faces a mirror and the camera: all three views see part of it
    cfg["simulate"] = {"flux": {"kind": "gaussian", "center_mm": [0.0, -8.84, 8.84], "width_mm": 5.0,
                                "peak_photons": float(peak_photons)},
                       "noise": {"model": "poisson", "repeats": 1, "seed": int(seed)}}
    cfg["reconstruct"] = {"method": "smooth", "lambda": "auto", "joint": False}
    cfg.pop("report", None)
    return cfg


def write_config(n_elements: int | None = None, *, workdir: Path, grid: tuple[int, int] | None = None, **kw) -> Path:
    """Write ``<workdir>/scale.yaml`` and return its path."""
    n_ang, n_ax = grid if grid is not None else grid_for(int(n_elements))
    workdir = Path(workdir).resolve()
    workdir.mkdir(parents=True, exist_ok=True)
    path = workdir / "scale.yaml"
    cfg = scene(n_ang, n_ax, workdir=workdir, **kw)
    path.write_text(f"# issue 22's scene: {n_ang} x {n_ax} = {n_ang * n_ax} elements (benchmarks/scale_scene.py)\n"
                    + yaml.safe_dump(cfg, sort_keys=False))
    return path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("n_elements", type=int)
    ap.add_argument("--grid", type=int, nargs=2, metavar=("N_ANGULAR", "N_AXIAL"), default=None)
    ap.add_argument("--workdir", type=Path, default=None)
    ap.add_argument("--peak-photons", type=float, default=None, help="default: max SNR ~30 (peak_for)")
    a = ap.parse_args(argv)
    wd = a.workdir or ROOT / "runs" / f"scale-{a.n_elements}"
    print(write_config(a.n_elements, workdir=wd, grid=tuple(a.grid) if a.grid else None, peak_photons=a.peak_photons))
    return 0


if __name__ == "__main__":
    sys.exit(main())
