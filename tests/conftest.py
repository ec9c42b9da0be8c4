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


# ----------------------------------------------------------------------------- the six stages chained (issue 23)
# calibrate -> capture-surface -> build-T -> simulate -> reconstruct -> report, once per session, on
# data-samples/: the camera calibrated from three of the sample grid frames (configs/calibrate.yaml) is
# the camera of a simulated rig (read out 4 x 4 binned, 64 x 64) that captures a glowing cylinder at two
# stage heights; build-T, simulate and reconstruct (from the capture) use that camera; report draws it.
# Each fixture runs one stage on the artefacts of the one before; tests/test_chain.py checks each link.
CHAIN_GRID_FRAMES = (0, 3, 6)  # z = -39, -5, 21 mm of configs/calibrate.yaml (all seven: twice the time)
CHAIN_BINNING = 4


class ChainRun:
    """The chained run so far: ``folder`` (root), ``config`` (the dict), ``path`` (its YAML),
    ``workdir`` (the artefacts), ``calibration`` (calibrate's workdir), ``outputs`` (stage -> CLI output)."""

    def __init__(self, folder: Path, calibration: Path):
        self.folder, self.calibration = folder, calibration
        self.workdir = folder / "run"
        self.path = folder / "chain.yaml"  # the rig's config, used by every stage after calibrate
        self.config: dict = {}
        self.outputs: dict[str, str] = {}

    def run(self, stage: str, path: Path | None = None) -> "ChainRun":
        from typer.testing import CliRunner

        from fluxcli.cli import app

        r = CliRunner().invoke(app, [stage, str(path or self.path)])
        assert r.exit_code == 0, f"fluxmap {stage}: exit {r.exit_code}\n{r.output}"
        self.outputs[stage] = " ".join(r.output.split())
        return self


def chain_config(run: ChainRun) -> dict:
    """The rig, the subject and the stages' settings, on the camera calibrate wrote."""
    return {
        "workdir": str(run.workdir),
        "system": {"camera": {"file": str(run.calibration / "camera.yaml"),  # lens and pose as calibrated
                              "pixels": [256 // CHAIN_BINNING] * 2, "pixel_pitch_mm": 0.052 * CHAIN_BINNING},
                   "stage": {"top_z_mm": 0.0, "size_mm": [60, 30], "thickness_mm": 5}},
        "subject": {"surface": {"phantom": "cylinder", "radius_mm": 8, "length_mm": 24, "n_angular": 16, "n_axial": 6},
                    "poses": {"heights_mm": [0, 5]}},
        "transfer": {"cache_dir": str(run.folder / "Tcache")},
        "simulate": {"flux": {"kind": "gaussian", "width_mm": 4.0, "peak_photons": 1e7},  # photons per 1 s
                     "noise": {"model": "poisson", "exposure_s": 1.0, "peaks_photons": [1e6], "repeats": 1, "seed": 5}},
        "rig": {"time_scale": 0.02,
                "filter_wheel": {"port": "pty", "positions": 6, "filters": {"open": 1}},
                "stage": {"port": "pty", "counts_per_mm": 134737.0, "travel_mm": [0.0, 50.0]},
                "camera": {"backend": "simulated", "binning": CHAIN_BINNING}},
        "capture": {"heights_mm": [0, 5], "filters": ["open"], "exposure_s": 1.0, "em_gain": 100.0, "repeats": 2,
                    "darks": 2, "seed": 3},
        "reconstruct": {"images": {"capture": "capture.h5", "filter": "open"}},
    }


@pytest.fixture(scope="session")
def chain_calibrated(tmp_path_factory) -> ChainRun:
    """1. calibrate: the sample camera from three of data-samples/calibration's grid frames."""
    folder = tmp_path_factory.mktemp("chain")
    run = ChainRun(folder, folder / "calibration")
    cal = yaml.safe_load((ROOT / "configs" / "calibrate.yaml").read_text())
    cal["workdir"] = str(run.calibration)
    frames = [cal["calibrate"]["images"][k] for k in CHAIN_GRID_FRAMES]
    cal["calibrate"]["images"] = [{**im, "file": str((ROOT / "configs" / im["file"]).resolve())} for im in frames]
    (folder / "calibrate.yaml").write_text(yaml.safe_dump(cal))
    run.run("calibrate", folder / "calibrate.yaml")
    run.config = chain_config(run)
    run.path.write_text(yaml.safe_dump(run.config))
    return run


def _chain_link(previous: str, stage: str, doc: str):
    """A session fixture running ``stage`` on the chain after fixture ``previous``."""
    @pytest.fixture(scope="session")
    def link(request) -> ChainRun:
        return request.getfixturevalue(previous).run(stage)

    link.__doc__ = doc
    return link


chain_captured = _chain_link("chain_calibrated", "capture-surface",
                             "2. capture-surface: the simulated rig's devices and camera take the plan's frames (capture.h5).")
chain_transfer = _chain_link("chain_captured", "build-T", "3. build-T with the calibrated camera.")
chain_simulated = _chain_link("chain_transfer", "simulate",
                              "4. simulate: the truth the rig's camera saw (simulation.h5) and simulated images of it.")
chain_reconstructed = _chain_link("chain_simulated", "reconstruct",
                                  "5. reconstruct from the captured frames (capture.h5, filter open).")
chain_reported = _chain_link("chain_reconstructed", "report", "6. report: figures, summary.json and the HTML page.")
