"""End to end: reconstruct with the calibrated camera, compare with the true camera.

    $ .venv/bin/fluxmap calibrate configs/calibrate.yaml
    $ .venv/bin/python data-samples/calibration/check_end_to_end.py

Images of a cylinder phantom (Gaussian surface patch) are simulated with the TRUE camera
of the calibration sample (truth.yaml) and exported as float photon images; then the same
files are reconstructed twice, once with the true camera and once with the camera that
``fluxmap calibrate`` wrote (``system: {camera: .../camera.yaml}``, the one-line
mechanism), each with its own build-T.  Prints both totals and their ratio; exits 1 when
they differ by more than 1 %.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import h5py
import yaml

ROOT = Path(__file__).resolve().parents[2]
RUN = ROOT / "runs" / "calib-e2e"
FLUXMAP = str(Path(sys.executable).parent / "fluxmap")


def main() -> int:
    cam_yaml = ROOT / "runs" / "calibrate" / "camera.yaml"
    if not cam_yaml.is_file():
        print(f"{cam_yaml} is missing: run  fluxmap calibrate configs/calibrate.yaml  first")
        return 2
    truth = yaml.safe_load((ROOT / "data-samples" / "calibration" / "truth.yaml").read_text())
    RUN.mkdir(parents=True, exist_ok=True)
    subject = {"surface": {"phantom": "cylinder", "radius_mm": 12.5, "length_mm": 40, "n_angular": 24, "n_axial": 10},
               "poses": {"heights_mm": [-10.0], "rotations_deg": [0.0]}}
    sim = {"workdir": "sim", "system": {"camera": truth["camera"]}, "subject": subject,
           "simulate": {"flux": {"kind": "gaussian", "width_mm": 6.0, "peak_photons": 2.0e6},
                        "noise": {"model": "poisson", "seed": 3}, "export": {"format": "fits"}}}
    (RUN / "sim.yaml").write_text(yaml.safe_dump(sim))
    subprocess.run([FLUXMAP, "simulate", str(RUN / "sim.yaml"), "-q", "--jobs", "2"], check=True)
    files = sorted((RUN / "sim").rglob("*.fits"))
    assert len(files) == 1, files
    rec = {"reconstruct": {"images": {"files": [str(files[0])], "units": "photons"}, "joint": False}}
    totals = {}
    for name, camera in (("true", truth["camera"]), ("calibrated", str(cam_yaml))):
        cfg = {"workdir": name, "system": {"camera": camera}, "subject": subject, **rec}
        (RUN / f"{name}.yaml").write_text(yaml.safe_dump(cfg))
        subprocess.run([FLUXMAP, "reconstruct", str(RUN / f"{name}.yaml"), "-q", "--jobs", "2"], check=True)
        with h5py.File(RUN / name / "reconstruction.h5", "r") as f:
            totals[name] = float(f["flux/total"][()])
    with h5py.File(RUN / "sim" / "simulation.h5", "r") as f:
        truth_total = float(f["truth/power"][()].sum())
    ratio = totals["calibrated"] / totals["true"]
    print(f"total with the true camera       {totals['true']:.6g} photons")
    print(f"total with the calibrated camera {totals['calibrated']:.6g} photons")
    print(f"ratio calibrated / true          {ratio:.5f}  ({100 * (ratio - 1):+.3f} %)")
    print(f"(ground truth over the whole surface {truth_total:.6g} photons; not all of it is seen)")
    return 0 if abs(ratio - 1) < 0.01 else 1


if __name__ == "__main__":
    sys.exit(main())
