"""Make the calibration sample: a dot grid imaged at seven heights by a known thin-lens camera.

    $ .venv/bin/python data-samples/calibration/make_grid_images.py

Renders each image by ray tracing through the thin lens (fluxcli.calibration.synthetic:
sub-pixels x lens samples, traced to the grid plane, pattern evaluated exactly, cos^4
etendue), adds the full EMCCD noise chain (fluxcli.imaging.noise), and writes 16-bit TIFF
counts with the project's image writer, plus ``truth.yaml`` stating the camera.  The
config ``configs/calibrate.yaml`` calibrates from these files.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from fluxcli.calibration.synthetic import camera_looking_down, render_grid_set
from fluxcli.imaging.imagefiles import write_image
from fluxcli.imaging.noise import EMCCDModel

HERE = Path(__file__).resolve().parent

TRUTH = dict(
    lens_center_mm=(1.3, -0.8, 200.0), tilt_deg=0.6, tilt_azimuth_deg=30.0, roll_deg=3.0,
    focal_length_mm=23.9, focus_distance_mm=200.4, aperture_diameter_mm=23.9 / 2.8,
    nx=256, ny=256, pixel_pitch_mm=0.052,
)
GRID = dict(pitch_mm=4.0, shape=(25, 19), dot_radius_mm=1.0)
HEIGHTS_MM = (-39.0, -27.0, -15.0, -5.0, 6.0, 14.0, 21.0)
SENSOR = EMCCDModel(quantum_efficiency=0.9, em_gain=100.0, read_noise_e=40.0, bias_counts=500.0,
                    electrons_per_count=10.0, dark_current_e_per_s=0.001, cic_e_per_pixel=0.005, exposure_s=1.0)


def main() -> None:
    cam = camera_looking_down(**TRUTH)
    images = render_grid_set(cam, HEIGHTS_MM, pitch_mm=GRID["pitch_mm"], shape=GRID["shape"],
                             dot_radius_mm=GRID["dot_radius_mm"], peak_photons=400.0, background_fraction=0.05,
                             sub=3, lens_samples=64, seed=1, noise_model=SENSOR)
    files = []
    for z, img in zip(HEIGHTS_MM, images):
        name = f"grid_z{z:+05.1f}.tif".replace("+", "p").replace("-", "m")
        write_image(HERE / name, img, metadata={"fluxmap:units": "counts", "plane_z_mm": float(z)})
        files.append({"file": name, "plane_z_mm": z})
    up = -cam.down
    truth = {
        "about": "Camera that rendered these grid images (fluxcli.calibration.synthetic, ray traced, EMCCD noise).",
        "camera": {
            "pixels": [TRUTH["nx"], TRUTH["ny"]],
            "pixel_pitch_mm": TRUTH["pixel_pitch_mm"],
            "lens": {"focal_length_mm": TRUTH["focal_length_mm"], "focus_distance_mm": TRUTH["focus_distance_mm"],
                     "aperture_diameter_mm": round(TRUTH["aperture_diameter_mm"], 6)},
            "pose": {"lens_center_mm": list(TRUTH["lens_center_mm"]), "look": [round(float(x), 9) for x in cam.axis],
                     "up": [round(float(x), 9) for x in up]},
        },
        "image_distance_mm": round(cam.image_distance_mm, 6),
        "focal_plane_z_mm": round(float(cam.center_mm[2] + cam.focus_distance_mm * cam.axis[2]), 6),
        "grid": {"kind": "dots", "pitch_mm": GRID["pitch_mm"], "shape": list(GRID["shape"]),
                 "dot_diameter_mm": 2 * GRID["dot_radius_mm"]},
        "images": files,
        "sensor": {k: getattr(SENSOR, k) for k in ("quantum_efficiency", "em_gain", "read_noise_e", "bias_counts",
                                                   "electrons_per_count")},
    }
    (HERE / "truth.yaml").write_text(yaml.safe_dump(truth, sort_keys=False))
    print(f"wrote {len(files)} images and truth.yaml to {HERE}")


if __name__ == "__main__":
    main()
