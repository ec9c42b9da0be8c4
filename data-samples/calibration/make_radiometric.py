"""Regenerate the radiometric calibration sample (run: python data-samples/calibration/make_radiometric.py).

Writes ``data-samples/calibration/radiometric/``: 64 x 64 16-bit TIFF frames of a simulated
EMCCD made with fluxmap's own camera chain (:mod:`fluxcli.imaging.noise`), and
``truth.yaml`` (the camera that made them) with the true maps as float32 TIFFs:

- ``bias_*.tif``        4 bias frames, EM gain off, no light, zero exposure;
- ``dark_<t>s_*.tif``   2 dark frames at each of 30 s and 120 s, EM gain on;
- ``flat_*.tif``        4 flat frames, EM gain off, the bare sensor evenly lit;
- ``ptc_off_<i>_*.tif`` 8 gain-off photon-transfer levels (2 frames each), exposures
  0.5 ms to 256 ms of one steady source;
- ``ptc_on_<i>_*.tif``  3 gain-on levels (2 frames each) of the same source, 20-125 us.

The sensor has structure the calibration must find: a bias pattern of whole counts along
columns and rows, a pixel-response non-uniformity (a 3 % gradient and 1 % pixel to pixel),
and a few hot pixels in the dark current. The gain-off frames are read out without
multiplication (:func:`fluxcli.imaging.noise.conventional_counts`), the gain-on frames
through the gamma EM register (:func:`fluxcli.imaging.noise.emccd_counts`).
``configs/calibrate-radiometric.yaml`` lists the files for ``fluxmap calibrate``.

:func:`make_set` makes the same kind of set for any truth (tests use another camera).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from fluxcli.imaging import noise as N
from fluxcli.imaging.imagefiles import write_image

HERE = Path(__file__).resolve().parent
OUT = HERE / "radiometric"

TRUTH = {
    "pixels": [64, 64],
    "quantum_efficiency": 0.9,
    "electrons_per_count": 8.4,
    "em_gain": 250.0,
    "read_noise_e": 42.0,
    "bias_counts": 480.0,          # before the fixed pattern (whole counts, mean ~0) is added
    "dark_current_e_per_s": 0.02,  # of ordinary pixels; the map adds hot pixels
    "cic_e_per_pixel": 0.005,
    "bit_depth": 16,
    "photon_rate_per_s": 1.0e6,    # PTC source: photons per pixel per second (flat response 1)
    "seed": 20261122,
}


def truth_maps(truth: dict, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Bias (counts), dark current (e-/s) and flat (mean 1) per pixel of the simulated sensor."""
    nx, ny = truth["pixels"]
    rows, cols = np.mgrid[0:ny, 0:nx]
    pattern = np.rint(2.0 * np.sin(cols / 5.0) + 1.0 * (rows % 8 == 0))  # whole counts
    bias = truth["bias_counts"] + pattern
    dark = np.full((ny, nx), truth["dark_current_e_per_s"])
    hot = rng.choice(nx * ny, size=max(1, nx * ny // 500), replace=False)
    dark.ravel()[hot] = rng.uniform(0.3, 1.0, size=hot.size)
    gradient = 1.0 + 0.03 * (cols / (nx - 1) - 0.5) + 0.02 * ((rows - ny / 2) / ny) ** 2
    flat = gradient * (1.0 + 0.01 * rng.standard_normal((ny, nx)))
    return {"bias_counts_map": bias, "dark_e_per_s_map": dark, "flat_map": flat / flat.mean()}


def _frames(photons: np.ndarray, model: N.EMCCDModel, bias_pattern: np.ndarray, n: int, em_gain_on: bool,
            rng: np.random.Generator) -> list[np.ndarray]:
    read = N.emccd_counts if em_gain_on else N.conventional_counts
    # the model's scalar bias is the map's mean level; the fixed pattern (whole counts) is added after the ADC
    return [np.clip(read(photons, model, rng).astype(np.int64) + bias_pattern, 0, model.max_count).astype(np.uint16)
            for _ in range(n)]


def make_set(out: Path, truth: dict) -> dict:
    """Simulate the frames of a radiometric calibration into ``out``; returns the
    ``calibrate.radiometric`` section (file names relative to ``out``) and writes
    ``truth.yaml`` and the true maps there."""
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(truth["seed"])
    maps = truth_maps(truth, rng)
    pattern = (maps["bias_counts_map"] - truth["bias_counts"]).astype(np.int64)
    qe = truth["quantum_efficiency"]
    model = N.EMCCDModel(quantum_efficiency=qe, em_gain=truth["em_gain"], read_noise_e=truth["read_noise_e"],
                         bias_counts=truth["bias_counts"], electrons_per_count=truth["electrons_per_count"],
                         dark_current_e_per_s=0.0,  # the dark map enters as equivalent photons, hot pixels and all
                         cic_e_per_pixel=truth["cic_e_per_pixel"], exposure_s=0.0, bit_depth=truth["bit_depth"])
    dark_photons = maps["dark_e_per_s_map"] / qe  # photons per second that give the dark electrons

    def write(name: str, frames: list[np.ndarray]) -> list[str]:
        names = [f"{name}_{i}.tif" for i in range(len(frames))]
        for n, frame in zip(names, frames):
            write_image(out / n, frame)
        return names

    def light(rate_photons_per_s: float, exposure_s: float) -> np.ndarray:
        return (rate_photons_per_s * maps["flat_map"] + dark_photons) * exposure_s

    section: dict = {}
    section["bias"] = write("bias", _frames(np.zeros_like(dark_photons), model, pattern, 4, False, rng))
    section["darks"] = []
    for t in (30.0, 120.0):
        files = write(f"dark_{t:g}s", _frames(light(0.0, t), model, pattern, 2, True, rng))
        section["darks"].append({"files": files, "exposure_s": t, "em_gain_on": True})
    section["flats"] = write("flat", _frames(light(1.0e6, 0.18), model, pattern, 4, False, rng))
    rate = truth["photon_rate_per_s"]
    section["ptc"] = []
    for i, t in enumerate((5e-4, 1.2e-3, 3e-3, 7.5e-3, 0.018, 0.043, 0.105, 0.256)):
        files = write(f"ptc_off_{i}", _frames(light(rate, t), model, pattern, 2, False, rng))
        section["ptc"].append({"files": files, "exposure_s": float(t), "em_gain_on": False})
    for i, t in enumerate((2e-5, 5e-5, 1.25e-4)):
        files = write(f"ptc_on_{i}", _frames(light(rate, t), model, pattern, 2, True, rng))
        section["ptc"].append({"files": files, "exposure_s": float(t), "em_gain_on": True})

    for name, arr in maps.items():
        write_image(out / f"truth_{name}.tif", arr.astype(np.float32))
    mean_dark = float(maps["dark_e_per_s_map"].mean())
    stated = {k: v for k, v in truth.items()} | {
        "dark_current_e_per_s": mean_dark,
        "dark_current_e_per_s_note": f"mean of truth_dark_e_per_s_map.tif ({truth['dark_current_e_per_s']} e-/s "
                                     "in ordinary pixels plus hot pixels)",
        "bias_counts": float(maps["bias_counts_map"].mean()),
        "bias_counts_note": "mean of truth_bias_counts_map.tif",
        "maps": {name: f"truth_{name}.tif" for name in maps},
    }
    (out / "truth.yaml").write_text("# The camera that made these frames (make_radiometric.py).\n"
                                    + yaml.safe_dump(stated, sort_keys=False))
    return section


if __name__ == "__main__":
    section = make_set(OUT, TRUTH)
    total = sum(p.stat().st_size for p in OUT.iterdir())
    print(f"wrote {len(list(OUT.iterdir()))} files ({total / 1e6:.2f} MB) to {OUT}")
