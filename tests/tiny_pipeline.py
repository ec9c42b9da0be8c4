"""A tiny pipeline shared by the trust tests (user mistakes, plausible-but-wrong cases):
a 24-element cylinder on a 24 x 24 camera at two heights, run once per session."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]


def tiny_config(base: Path) -> dict:
    """A 24-element cylinder on a 24 x 24 camera at two heights, nnls (fast everywhere)."""
    cfg = yaml.safe_load((ROOT / "configs" / "minimal.yaml").read_text())
    cfg["workdir"] = str(base / "run")
    cam = cfg["system"]["camera"]
    cam["pixels"] = [24, 24]
    cam["pixel_pitch_mm"] = 0.1
    cfg["subject"] = {"surface": {"phantom": "cylinder", "radius_mm": 8, "length_mm": 24, "n_angular": 8, "n_axial": 3},
                      "poses": {"heights_mm": [0, 5]}}
    cfg["transfer"] = {"cache_dir": str(base / "cache"), "lens": {"lens_samples_min": 16}}
    cfg["simulate"] = {"flux": {"kind": "gaussian", "width_mm": 4.0, "peak_photons": 1e6},
                       "noise": {"model": "poisson", "peaks_photons": [1e6], "repeats": 1, "seed": 1}}
    cfg["reconstruct"] = {"method": "nnls", "lambda": 0.0}
    return cfg


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory):
    """The artefacts of one good run of the tiny config (build-T, simulate, reconstruct):
    (folder, config dict, config path).  Tests must not change them (copy them first)."""
    from typer.testing import CliRunner

    from fluxcli.cli import app

    d = tmp_path_factory.mktemp("tiny")
    cfg = tiny_config(d)
    p = d / "cfg.yaml"
    p.write_text(yaml.safe_dump(cfg))
    for stage in ("build-T", "simulate", "reconstruct"):
        r = CliRunner().invoke(app, [stage, str(p), "-q"])
        assert r.exit_code == 0, r.output
    return d, cfg, p
