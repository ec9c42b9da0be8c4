import shutil
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def write_config(tmp_path):
    """Write a config dict (or YAML text) into tmp_path; sample meshes are copied beside it."""
    for name in ("mouse.vtk", "patch.ply"):
        shutil.copy(ROOT / "data-samples" / name, tmp_path / name)

    def write(cfg, name="cfg.yaml"):
        p = tmp_path / name
        p.write_text(cfg if isinstance(cfg, str) else yaml.safe_dump(cfg))
        return p

    return write


@pytest.fixture
def minimal_config():
    cfg = yaml.safe_load((ROOT / "configs" / "minimal.yaml").read_text())
    cfg["subject"]["surface"]["mesh"] = "mouse.vtk"
    cfg["workdir"] = "run"
    cfg["system"]["camera"]["pixels"] = [48, 48]
    cfg["system"]["camera"]["pixel_pitch_mm"] = 0.25
    return cfg
