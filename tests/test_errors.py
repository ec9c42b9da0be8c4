"""Exit 2 is for the user-error type only (issue 23): bad input exits 2 with one paragraph
naming the key or file; any other exception, a plain ValueError or IndexError included, is a
bug and exits 1 with its traceback.

The hostile inputs here are the ones tests/test_user_mistakes.py does not already hold
(camera files, emission tables, calibration frames, multi-channel images, a capture that is
another artefact kind, a mesh whose triangle has three distinct but collinear corners)."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from fluxcli.cli import app
from fluxcli.errors import UserError
from fluxcli.imaging.imagefiles import read_image, write_image

from tiny_pipeline import tiny_config, tiny_run  # noqa: F401  (the session fixture)

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "data-samples" / "calibration"


def invoke(*args):
    r = CliRunner().invoke(app, [str(a) for a in args])
    return r.exit_code, " ".join(r.output.split())


def _rgb_tif(path: Path, a: np.ndarray) -> str:
    """A 3-channel float TIFF (what a colour camera or a screenshot gives)."""
    import OpenImageIO as oiio

    b = np.repeat(np.asarray(a, np.float32)[:, :, None], 3, axis=2)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), oiio.ImageSpec(b.shape[1], b.shape[0], 3, oiio.FLOAT))
    assert out.write_image(b)
    out.close()
    return str(path)


def _grid_config(d: Path) -> dict:
    cfg = yaml.safe_load((ROOT / "configs" / "calibrate.yaml").read_text())
    cfg["workdir"] = str(d / "run")
    for im in cfg["calibrate"]["images"]:
        im["file"] = str((ROOT / "configs" / im["file"]).resolve())
    return cfg


def _grid_frame(edit):
    """calibrate (configs/calibrate.yaml) with its first grid frame replaced by edit(frame, folder) -> file."""
    def make(d: Path, cache: Path):
        cfg = _grid_config(d)
        frame, _ = read_image(SAMPLES / "grid_zm39.0.tif")
        cfg["calibrate"]["images"][0]["file"] = edit(np.asarray(frame, np.float32), d)
        return "calibrate", cfg
    return make


def _nan_pixel(frame, d):
    frame[100, 100] = np.nan
    write_image(d / "g0.tif", frame, metadata={})
    return str(d / "g0.tif")


def _tiny(edit):
    """build-T / simulate / reconstruct on the tiny config with edit(cfg, folder) -> stage."""
    def make(d: Path, cache: Path):
        cfg = tiny_config(d)
        cfg["transfer"]["cache_dir"] = str(cache)
        return edit(cfg, d), cfg
    return make


def _camera_file(text):
    def edit(cfg, d):
        (d / "camera.yaml").write_text(text)
        cfg["system"]["camera"] = "camera.yaml"
        return "build-T"
    return edit


def _emission_table(text):
    def edit(cfg, d):
        (d / "table.csv").write_text(text)
        cfg["subject"]["emission"] = {"model": "table", "file": "table.csv"}
        return "simulate"
    return edit


def _emission_folder(cfg, d):
    (d / "profiles").mkdir()
    cfg["subject"]["emission"] = {"model": "table", "file": "profiles"}
    return "build-T"


def _emission(section):
    def edit(cfg, d):
        cfg["subject"]["emission"] = section
        return "build-T"
    return edit


def _flux(section):
    def edit(cfg, d):
        cfg["simulate"]["flux"] = section
        return "simulate"
    return edit


def _collinear_triangle(cfg, d):
    v = [[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10], [5, 0, 0]]
    f = [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3], [0, 4, 1]]  # the last: three distinct points on one line
    lines = ["ply", "format ascii 1.0", f"element vertex {len(v)}", *(f"property float {c}" for c in "xyz"),
             f"element face {len(f)}", "property list uchar int vertex_indices", "end_header",
             *(" ".join(map(str, p)) for p in v), *(f"3 {a} {b} {c}" for a, b, c in f)]
    (d / "m.ply").write_text("\n".join(lines) + "\n")
    cfg["subject"]["surface"] = {"mesh": "m.ply"}
    return "build-T"


def _rgb_emission_images(cfg, d):
    a = np.full((24, 24), 100.0, np.float32)
    cfg["reconstruct"]["images"] = {"files": [_rgb_tif(d / "i0.tif", a), _rgb_tif(d / "i1.tif", a)]}
    return "reconstruct"


def _capture_of_another_kind(cfg, d, tiny_dir):
    (d / "capture.h5").write_bytes((tiny_dir / "run" / "simulation.h5").read_bytes())
    cfg["reconstruct"]["images"] = {"capture": "capture.h5", "filter": "open"}
    return "reconstruct"


HOSTILE = [
    # (id, make(folder, cache) -> (stage, cfg), words the one paragraph must hold)
    ("camera-file-bad-yaml", _tiny(_camera_file("camera: [unclosed\n")), ["system.camera", "camera.yaml", "not valid YAML"]),
    ("camera-file-without-block", _tiny(_camera_file("lens: {}\n")), ["system.camera", "camera.yaml", "'camera:'"]),
    ("emission-table-nan", _tiny(_emission_table("angle_deg,radiance\n0,1\n30,nan\n60,0.5\n")),
     ["subject.emission.file", "table.csv", "finite"]),
    ("emission-table-angles-back", _tiny(_emission_table("angle_deg,radiance\n0,1\n60,0.5\n30,0.8\n")),
     ["subject.emission.file", "table.csv", "increase"]),
    ("emission-table-header-names-no-angle", _tiny(_emission_table("intensity;value\n0;1\n60;0,5\n")),
     ["subject.emission.file", "table.csv", "'intensity'", "names neither an angle"]),
    ("emission-table-a-folder", _tiny(_emission_folder), ["subject.emission.file", "is a folder"]),
    ("emission-without-model", _tiny(_emission({"refractive_index": 1.4})),
     ["subject.emission.model", "missing", "lambertian, diffuse, table"]),
    ("emission-model-misspelt", _tiny(_emission({"model": "lambertain"})),
     ["subject.emission.model", "'lambertain' is not one of lambertian, diffuse, table"]),
    ("flux-without-kind", _tiny(_flux({"width_mm": 4.0})), ["simulate.flux.kind", "missing", "montecarlo"]),
    ("mesh-collinear-triangle", _tiny(_collinear_triangle), ["subject.surface.mesh", "m.ply", "zero area"]),
    ("images-three-channels", _tiny(_rgb_emission_images), ["reconstruct.images.files[0]", "i0.tif", "channels"]),
    ("grid-frame-nan-pixel", _grid_frame(_nan_pixel), ["calibrate.images[0]", "g0.tif", "NaN"]),
    ("grid-frame-three-channels", _grid_frame(lambda a, d: _rgb_tif(d / "g0.tif", a)),
     ["calibrate.images[0].file", "g0.tif", "channels"]),
]


@pytest.mark.parametrize("make, words", [h[1:] for h in HOSTILE], ids=[h[0] for h in HOSTILE])
def test_hostile_input_exits_2_naming_the_key_and_file(make, words, tiny_run, tmp_path):
    tiny_dir = tiny_run[0]
    stage, cfg = make(tmp_path, tiny_dir / "cache")
    p = tmp_path / "cfg.yaml"
    p.write_text(yaml.safe_dump(cfg))
    code, out = invoke(stage, p)
    assert code == 2 and "Traceback" not in out, out
    for w in words:
        assert w in out, (w, out)


def test_a_capture_file_of_another_kind_exits_2_naming_it(tiny_run, tmp_path):
    cfg = tiny_config(tmp_path)
    cfg["transfer"]["cache_dir"] = str(tiny_run[0] / "cache")
    stage = _capture_of_another_kind(cfg, tmp_path, tiny_run[0])
    p = tmp_path / "cfg.yaml"
    p.write_text(yaml.safe_dump(cfg))
    code, out = invoke(stage, p)
    assert code == 2 and "capture.h5" in out and "'simulation' artefact, not 'capture'" in out, out


def test_another_tools_hdf5_in_an_artefacts_place_exits_2_naming_it(tmp_path):
    """HDF5 files that are no fluxmap artefact, read where one is expected: no 'kind', a number
    for a kind, a text schema_version (int('x') stopped the readers and the up-to-date check:
    exit 1). Each is refused naming the file; the up-to-date check says no."""
    import h5py

    from fluxcli.artefacts.store import is_up_to_date

    for name, attrs, said in (("none.h5", {}, "no fluxmap artefact (it has no 'kind' attribute)"),
                              ("five.h5", {"kind": 5}, "is a '5' artefact, not 'reconstruction'"),
                              ("text.h5", {"kind": "reconstruction", "schema_version": "x"}, "has schema version x")):
        with h5py.File(tmp_path / name, "w") as f:
            f.attrs.update(attrs)
        (tmp_path / "s.yaml").write_text(f"sessions:\n- {{artefact: {name}, subject: a, day: 1}}\n")
        r = CliRunner().invoke(app, ["study", str(tmp_path / "s.yaml"), "-q"])
        out = " ".join(r.output.split())
        assert r.exit_code == 2 and str(tmp_path / name) in out and said in out, out
        assert is_up_to_date(tmp_path / name, "reconstruction", "d") is False


# ------------------------------------------------------------------ a bug is exit 1 with its traceback
def test_user_error_is_a_value_error():
    """Code that catches ValueError (the science packages' "these numbers cannot be used")
    keeps catching the user-error type."""
    assert issubclass(UserError, ValueError)


@pytest.mark.parametrize("exc, code, traceback", [
    (ValueError("operands could not be broadcast together with shapes (3,) (4,)"), 1, True),  # a numpy shape bug
    (IndexError("index 7 is out of bounds for axis 0 with size 4"), 1, True),
    (KeyError("flux/total"), 1, True),
    (UserError("subject.poses.heights_mm: a stated problem"), 2, False),
])
def test_only_the_user_error_type_exits_2(exc, code, traceback, tiny_run, tmp_path, monkeypatch):
    import fluxcli.stages.build_t as stage

    def broken(cfg, ctx):
        raise exc

    monkeypatch.setattr(stage, "run", broken)
    r = CliRunner().invoke(app, ["build-T", str(tiny_run[2])])
    assert r.exit_code == code, r.output
    assert ("Traceback" in r.output) is traceback, r.output
    if traceback:  # the bug's own text and type, and a request to report it
        assert type(exc).__name__ in r.output and "Please report it" in r.output
    else:
        assert " ".join(r.output.split()) == "fluxmap: error: subject.poses.heights_mm: a stated problem"


@pytest.mark.parametrize("exc, code, words", [
    # numpy inside the solver: a bug, not the user's numbers (it used to be dressed up as exit 2)
    (ValueError("operands could not be broadcast together with shapes (3,) (4,)"), 1, "Traceback"),
    # the solver's own check of what it was given: exit 2, in the config's words
    (None, 2, "reconstruct.lambda must be > 0"),
])
def test_inside_the_solve_only_the_science_input_check_is_a_user_error(exc, code, words, tiny_run, tmp_path,
                                                                      monkeypatch):
    """The stage turns the science's InputError (its checks on its inputs) into the config's keys;
    any other ValueError raised inside the same call is a bug and keeps its traceback."""
    import shutil

    import fluxcli.inverse.solve as S
    from fluxcli.errors import InputError

    d = tmp_path / "tiny"
    shutil.copytree(tiny_run[0], d)
    cfg = copy.deepcopy(tiny_run[1])
    cfg["workdir"], cfg["transfer"]["cache_dir"] = str(d / "run"), str(d / "cache")
    p = d / "cfg2.yaml"
    p.write_text(yaml.safe_dump(cfg))

    def broken(*a, **k):
        raise exc if exc is not None else InputError("lam must be > 0")

    monkeypatch.setattr(S, "_reconstruct", broken)
    r = CliRunner().invoke(app, ["reconstruct", str(p), "--force"])
    assert r.exit_code == code, r.output
    assert words in r.output, r.output
    assert ("Traceback" in r.output) is (code == 1), r.output
