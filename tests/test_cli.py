"""The command line: stages, exit codes and messages, the T cache."""

from __future__ import annotations

import copy
import os
import subprocess
import sys

import h5py
import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from fluxcli.cli import app
from fluxcli.config import load_config
from fluxcli.stages.build_t import plan

runner = CliRunner()


def run(*args):
    return runner.invoke(app, [str(a) for a in args])


def test_version():
    r = run("--version")
    assert r.exit_code == 0 and r.output.startswith("fluxmap ")


def test_minimal_config_builds_T_with_defaults_and_reuses_the_cache(write_config, minimal_config, tmp_path):
    cfg = write_config(minimal_config)
    r = run("build-T", cfg)
    assert r.exit_code == 0, r.output
    assert "cache hit" not in r.output
    index = tmp_path / "run" / "transfer.h5"
    with h5py.File(index) as f:
        assert f.attrs["kind"] == "transfer-index"
        path = f["paths"][0].decode() if isinstance(f["paths"][0], bytes) else f["paths"][0]
    path = index.parent / path  # relative to the index's folder (artefacts do not depend on the clone's path)
    mtime = os.stat(path).st_mtime_ns
    r = run("build-T", cfg)
    assert r.exit_code == 0 and "cache hit" in r.output
    assert os.stat(path).st_mtime_ns == mtime
    r = run("build-T", cfg, "--force", "--quiet")
    assert r.exit_code == 0 and r.output == ""
    assert os.stat(path).st_mtime_ns != mtime


def test_T_artefact_follows_the_contract(write_config, minimal_config, tmp_path):
    cfg = write_config(minimal_config)
    assert run("build-T", cfg, "--quiet").exit_code == 0
    (path,) = (tmp_path / "run" / "cache" / "T").glob("*.h5")
    assert not list((tmp_path / "run" / "cache" / "T").glob(".*tmp"))  # atomic: no leftovers
    with h5py.File(path) as f:
        for a in ("fluxmap_version", "kind", "schema_version", "created", "config_sha256", "inputs"):
            assert a in f.attrs
        assert tuple(f["T"].attrs["shape"]) == (48 * 48, 96)
        for d in ("data", "indices", "indptr"):
            assert d in f["T"]
        for d in ("vertices", "faces", "element_of_face", "areas"):
            assert d in f["surface"]
        assert path.stem == f.attrs.get("config_sha256", "") or len(path.stem) == 64
        assert f["T"]["data"][()].min() > 0


def keys(write_config, cfg, *overrides):
    p = write_config(cfg, name=f"k{abs(hash(overrides))}.yaml")
    return [pt.key for _, pt in plan(load_config(p, list(overrides)))[2]]


def test_cache_key_covers_what_T_depends_on_and_nothing_else(write_config, minimal_config):
    cfg = copy.deepcopy(minimal_config)
    cfg["system"]["mirrors"] = [{"center_mm": [0, 31.14, 14.14], "normal": [0, -1, 1], "axis": [1, 0, 0], "size_mm": [70, 40]}]
    cfg["system"]["stage"] = {"top_z_mm": -1.0}
    base = keys(write_config, cfg)
    # changes that must give a new key
    for o in ("system.mirrors.0.center_mm=[0, 32.14, 14.14]", "system.camera.lens.f_number=4.1",
              "subject.poses.heights_mm=[1.0]", "subject.poses.rotations_deg=[10]",
              "system.camera.apertures=[{distance_mm: 30, diameter_mm: 25}]",
              "system.mirrors.0.reflectance=0.9", "transfer.estimator=pairwise",
              "transfer.lens.lens_samples_min=64", "system.stage.top_z_mm=-2"):
        assert keys(write_config, cfg, o) != base, o
    # changes that must not
    for o in ("workdir=elsewhere", "reconstruct={method: paper, lambda: 10}", "system.mirrors.0.name=renamed",
              "system.camera.sensor.quantum_efficiency=0.5", "transfer.rays_per_batch=5000",
              "transfer.cache_dir=/tmp/other-cache"):
        assert keys(write_config, cfg, o) == base, o


def test_poses_give_one_T_each_and_rotation_keeps_a_phantom_on_the_stage(write_config, minimal_config):
    cfg = copy.deepcopy(minimal_config)
    cfg["subject"]["surface"] = {"phantom": "cylinder", "n_angular": 50, "n_axial": 4}
    cfg["system"]["stage"] = {}
    cfg["subject"]["poses"] = {"heights_mm": [0, 5], "rotations_deg": [0, 17]}
    views, placer, todo = plan(load_config(write_config(cfg)))
    assert len({pt.key for _, pt in todo}) == 4
    for scene, pt in todo:
        lo, hi = scene.surface.bounds_mm()
        assert lo[2] == pytest.approx(pt.pose.height_mm, abs=1e-9)  # resting on the stage top
        assert hi[2] == pytest.approx(pt.pose.height_mm + 25, abs=0.1)  # a 50-gon, turned


# ------------------------------------------------------------------ bad input: exit 2, one paragraph
def assert_user_error(r, *words):
    assert r.exit_code == 2, r.output
    assert "Traceback" not in r.output
    assert r.output.startswith("fluxmap: error:")
    text = " ".join(r.output.split())  # the paragraph is wrapped for the terminal
    for w in words:
        assert w in text, (w, r.output)


def test_missing_config_file(tmp_path):
    assert_user_error(run("build-T", tmp_path / "nope.yaml"), "nope.yaml", "does not exist")


def test_unknown_key_is_named(write_config, minimal_config):
    cfg = copy.deepcopy(minimal_config)
    cfg["system"]["camera"]["lens"]["f_numbr"] = 4
    assert_user_error(run("build-T", write_config(cfg)), "system.camera.lens.f_numbr", "unknown key")


def test_focus_shorter_than_focal_length(write_config, minimal_config):
    r = run("build-T", write_config(minimal_config), "--set", "system.camera.lens.focus_distance_mm=20")
    assert_user_error(r, "system.camera.lens", "focus_distance_mm", "focal length")


def test_missing_and_empty_mesh_files(write_config, minimal_config, tmp_path):
    cfg = copy.deepcopy(minimal_config)
    cfg["subject"]["surface"]["mesh"] = "missing.ply"
    assert_user_error(run("build-T", write_config(cfg)), "missing.ply", "does not exist")
    (tmp_path / "empty.ply").write_text("ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\n"
                                        "property float y\nproperty float z\nelement face 0\n"
                                        "property list uchar int vertex_indices\nend_header\n")
    cfg["subject"]["surface"]["mesh"] = "empty.ply"
    assert_user_error(run("build-T", write_config(cfg)), "empty.ply")


def test_bad_override_and_bad_yaml(write_config, minimal_config):
    p = write_config(minimal_config)
    assert_user_error(run("build-T", p, "--set", "transfer.estimator"), "dotted.key=value")
    assert_user_error(run("build-T", p, "--set", "transfer.estimator=magic"), "transfer.estimator")
    assert_user_error(run("build-T", write_config("system: [unclosed", name="bad.yaml")), "bad.yaml", "YAML")


def test_mirror_facing_away_from_the_camera(write_config, minimal_config):
    cfg = copy.deepcopy(minimal_config)
    cfg["system"]["mirrors"] = [{"center_mm": [0, 30, 10], "normal": [0, 1, -1], "axis": [1, 0, 0], "size_mm": [50, 30]}]
    assert_user_error(run("build-T", write_config(cfg)), "faces away")


def test_calibrate_without_its_section_names_it(write_config, minimal_config):
    assert_user_error(run("calibrate", write_config(minimal_config)), "calibrate", "needs")


def test_capture_surface_without_a_plan_names_the_section(write_config, minimal_config):
    assert_user_error(run("capture-surface", write_config(minimal_config)), "needs 'rig'")


def test_real_process_exit_code_and_no_traceback(tmp_path):
    r = subprocess.run([sys.executable, "-m", "fluxcli.cli", "build-T", str(tmp_path / "x.yaml")],
                       capture_output=True, text=True)
    assert r.returncode == 2
    assert "Traceback" not in r.stderr and "does not exist" in " ".join(r.stderr.split())


# ------------------------------------------------------------------ optional sections, camera from a file
def test_stage_names_the_section_it_needs(write_config, minimal_config):
    cfg = {"workdir": "run", "system": {"camera": {"pixels": [8, 8], "pixel_pitch_mm": 0.1}}}
    assert_user_error(run("build-T", write_config(cfg)), "build-T", "system.camera.lens")
    cfg = dict(minimal_config)
    cfg.pop("subject")
    assert_user_error(run("reconstruct", write_config(cfg)), "reconstruct", "subject")


def test_camera_from_a_file_in_one_line(write_config, minimal_config, tmp_path):
    from fluxcli.config import load_config

    cam = minimal_config["system"]["camera"]
    (tmp_path / "calib").mkdir()
    (tmp_path / "calib" / "camera.yaml").write_text(yaml.safe_dump({"camera": cam}))
    inline = load_config(write_config(minimal_config, "inline.yaml"))
    cfg = dict(minimal_config, system=dict(minimal_config["system"], camera="calib/camera.yaml"))
    by_file = load_config(write_config(cfg, "byfile.yaml"))
    assert by_file.model.system.camera == inline.model.system.camera
    assert by_file.sha256 == load_config(write_config(cfg, "byfile2.yaml")).sha256
    # keys beside `file` override the file's, section by section
    cfg["system"]["camera"] = {"file": "calib/camera.yaml", "lens": {"f_number": 4.0}}
    over = load_config(write_config(cfg, "over.yaml")).model.system.camera
    assert over.lens.f_number == 4.0
    assert over.lens.focal_length_mm == inline.model.system.camera.lens.focal_length_mm
    cfg["system"]["camera"] = "calib/nope.yaml"
    assert_user_error(run("build-T", write_config(cfg, "missing.yaml")), "system.camera", "nope.yaml")


def test_duplicate_yaml_keys_are_refused(write_config):
    text = "workdir: a\nworkdir: b\nsystem: {}\n"
    assert_user_error(run("build-T", write_config(text)), "duplicate key", "workdir")
