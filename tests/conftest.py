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


def cylinder_sim_config(minimal: dict, *, peaks_photons=(1e6, 1e4)) -> dict:
    """A small cylinder phantom (16 x 6 elements) on a 40 x 40 camera at two stage heights,
    with a seeded Gaussian-patch simulation: the pipeline the stage tests share."""
    import copy

    cfg = copy.deepcopy(minimal)
    cfg["system"]["camera"]["pixels"] = [40, 40]
    cfg["system"]["camera"]["pixel_pitch_mm"] = 0.3
    cfg["subject"]["surface"] = {"phantom": "cylinder", "radius_mm": 8, "length_mm": 24, "n_angular": 16, "n_axial": 6}
    cfg["subject"]["poses"] = {"heights_mm": [0, 5]}
    cfg["simulate"] = {"flux": {"kind": "gaussian", "width_mm": 4.0, "peak_photons": 1e6},
                       "noise": {"model": "poisson", "peaks_photons": list(peaks_photons), "repeats": 3, "seed": 5}}
    return cfg


# ----------------------------------------------------------------------------- real devices (opt-in)
def pytest_addoption(parser):
    group = parser.getgroup("rig", "real rig devices (tests skipped unless a port is given)")
    group.addoption("--fw102c", metavar="PORT", default=None, help="FW102C filter wheel port, e.g. /dev/ttyUSB0.")
    group.addoption("--labjack", metavar="PORT", default=None, help="L490MZ lab-jack APT controller port.")
    group.addoption("--labjack-counts-per-mm", type=float, default=134737.0,
                    help="Microsteps per mm of the lab jack's controller (default 134737).")
    group.addoption("--labjack-home", action="store_true", help="Also home the lab jack (only with nothing on it).")


def _real_port(request, option: str, what: str) -> str:
    port = request.config.getoption(option)
    if not port:
        pytest.skip(f"no real {what}: give {option} PORT")
    return port


@pytest.fixture
def fw102c_port(request):
    return _real_port(request, "--fw102c", "FW102C")


@pytest.fixture
def labjack_port(request):
    return _real_port(request, "--labjack", "lab jack")
