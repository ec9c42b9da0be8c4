"""Every key of a full config, set to each of a dozen hostile values, run through the stage
that reads it: exit 0 or exit 2 (a clear error), never 1 (a bug).  This found a length of
1e300 mm overflowing inside the ray tracer and n_angular = 10^7 filling 6 GB of memory.

~800 runs, a few minutes: `make bench` (pytest -m slow), not `make test`."""

from __future__ import annotations

import copy
import shutil
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from fluxcli.cli import app
from tiny_pipeline import tiny_config

HOSTILE = [0, -1, float("nan"), "abc", [], {}, True, None, 1e300, [1, 2, 3, 4], 1e-9, 1e5, 2**31, -0.0]
STAGE = {"system": "build-T", "subject": "build-T", "transfer": "build-T", "simulate": "simulate",
         "reconstruct": "reconstruct", "report": "report"}


def leaves(node, path=()):
    """(path, value) of every scalar and of every list of scalars (and its items)."""
    if isinstance(node, dict):
        for k, v in node.items():
            yield from leaves(v, path + (k,))
    elif isinstance(node, list) and node and not isinstance(node[0], (dict, list)):
        yield path, node
        for i, v in enumerate(node):
            yield path + (i,), v
    elif isinstance(node, list):
        for i, v in enumerate(node):
            yield from leaves(v, path + (i,))
    else:
        yield path, node


def hostile_runs(tmp_path, cfg, paths, stages, skip=("cache_dir",),
                 first=("build-T", "simulate", "reconstruct", "report"), too_long=None, options=("-q",)) -> list[str]:
    """Run a good ``cfg`` through the stages ``first`` once, then every leaf under ``paths`` (key
    prefixes, tuples) set to each hostile value through the stages after the first that reads it
    (its prefix's entry of ``stages``; leaves named in ``skip`` are left alone, and numbers above
    ``too_long[name]`` for those it names: legal, and hours to run); every exit must be 0 or 2.
    Returns the bugs found."""
    runner = CliRunner()
    p = tmp_path / "c.yaml"

    def run(stage, c):
        p.write_text(yaml.safe_dump(c))
        return runner.invoke(app, [stage, str(p), *options])

    for stage in first:  # a good run to start each from
        r = run(stage, cfg)
        assert r.exit_code == 0, r.output
    bugs = []
    for prefix, after in zip(paths, stages):
        node0 = cfg
        for k in prefix:
            node0 = node0[k]
        for path, _ in list(leaves(node0, prefix)):
            if path[-1] in skip:
                continue
            for value in HOSTILE:
                if isinstance(value, (int, float)) and value > (too_long or {}).get(path[-1], float("inf")):
                    continue  # legal and slow (2^31 photons: an hour), not hostile
                c = copy.deepcopy(cfg)
                node = c
                for k in path[:-1]:
                    node = node[k]
                node[path[-1]] = value
                work = tmp_path / "work"
                shutil.rmtree(work, ignore_errors=True)
                shutil.copytree(tmp_path / "run", work)
                c["workdir"] = str(work)
                for stage in after:
                    r = run(stage, c)
                    if r.exit_code not in (0, 2):
                        bugs.append(f"{'.'.join(map(str, path))} = {value!r} ({stage}): exit {r.exit_code}\n"
                                    f"{r.output[-800:]}")
                    if r.exit_code:
                        break
    return bugs


def full_config(tmp_path) -> dict:
    cfg = tiny_config(tmp_path)
    cfg["system"]["mirrors"] = [{"name": "right", "center_mm": [0, 31.14, 14.14], "normal": [0, -1, 1],
                                 "axis": [1, 0, 0], "size_mm": [70, 40]}]
    cfg["system"]["stage"] = {"top_z_mm": -9.0, "size_mm": [100, 34], "thickness_mm": 5}
    cfg["system"]["camera"]["apertures"] = [{"distance_mm": 30.0, "diameter_mm": 25.0}]
    cfg["report"] = {"title": "fuzz"}
    return cfg


@pytest.mark.slow
def test_no_hostile_value_of_any_key_is_a_bug(tmp_path):
    cfg = full_config(tmp_path)
    tops = [k for k in cfg if k in STAGE]
    bugs = hostile_runs(tmp_path, cfg, [(k,) for k in tops], [(STAGE[k],) for k in tops])
    assert not bugs, "\n\n".join(bugs)


@pytest.mark.slow
def test_no_hostile_value_of_an_emission_or_photon_transport_key_is_a_bug(tmp_path):
    """Issue 21's keys, which the config above leaves out: ``subject.emission`` as ``diffuse``
    with every term on (through build-T and reconstruct, whose curvature pass reads them) and
    ``simulate.flux`` as ``montecarlo`` (through simulate).  Measured 27 November: ~3 min, no bug."""
    cfg = full_config(tmp_path)
    cfg["subject"]["emission"] = {"model": "diffuse", "refractive_index": 1.4, "tangential_flux": True,
                                  "depth_term": True, "curvature_term": True,
                                  "reduced_scattering_per_mm": 1.0, "absorption_per_mm": 0.01}
    cfg["simulate"]["flux"] = {"kind": "montecarlo", "mua_per_mm": 0.01, "mus_per_mm": 1.0, "g": 0.0,
                               "refractive_index": 1.4, "position_mm": [0, 4, 0], "radius_mm": 0.0,
                               "n_photons": 20000, "seed": 1, "batch_photons": 10000, "keep_photons": False}
    cfg["simulate"]["noise"] = {"model": "poisson", "seed": 1}  # one level and one draw: the photons' own
    cfg["reconstruct"]["unknowns"] = "vertices"  # the tangential and curvature terms act on vertices
    bugs = hostile_runs(tmp_path, cfg, [("subject", "emission"), ("simulate", "flux")],
                        [("build-T", "reconstruct"), ("simulate",)], skip=("model", "kind"),  # fuzzed above
                        too_long={"n_photons": 1e6})
    assert not bugs, "\n\n".join(bugs)


@pytest.mark.slow
def test_no_hostile_value_of_a_calibrate_key_is_a_bug(tmp_path):
    """calibrate on the sample grid frames: the camera, the grid and the first frame's keys (the
    others are alike).  This found a plane_z_mm of 0 for the -39 mm frame stopping inside the
    initial camera fit (exit 1).  ~3 min."""
    root = Path(__file__).resolve().parents[1]
    cfg = yaml.safe_load((root / "configs" / "calibrate.yaml").read_text())
    cfg["workdir"] = str(tmp_path / "run")
    for im in cfg["calibrate"]["images"]:
        im["file"] = str((root / "configs" / im["file"]).resolve())
    bugs = hostile_runs(tmp_path, cfg, [("system",), ("calibrate", "grid"), ("calibrate", "images", 0)],
                        [("calibrate",)] * 3, first=("calibrate",))
    assert not bugs, "\n\n".join(bugs)


@pytest.mark.slow
def test_no_hostile_value_of_a_capture_or_rig_key_is_a_bug(tmp_path):
    """capture-surface on the simulated rig (filter wheel and stage on pseudo terminals, the
    simulated EMCCD): the acquisition plan's keys and the camera's and wheel's.  This found
    capture.exposure_s 1e300 overflowing the clock in the simulated camera's sleep (exit 1)."""
    cfg = full_config(tmp_path)
    cfg["simulate"]["noise"] = {"model": "poisson", "exposure_s": 1.0, "peaks_photons": [1e6], "repeats": 1, "seed": 5}
    cfg["rig"] = {"time_scale": 0.02, "filter_wheel": {"port": "pty", "positions": 6, "filters": {"open": 1, "red": 3}},
                  "stage": {"port": "pty", "counts_per_mm": 134737.0, "travel_mm": [0.0, 50.0]},
                  "camera": {"backend": "simulated", "binning": 1, "filters": {"red": {"transmission": 0.5}}}}
    cfg["capture"] = {"heights_mm": [0, 5], "filters": ["open", "red"], "exposure_s": 1.0, "em_gain": 100.0,
                      "repeats": 2, "darks": 2, "seed": 3}
    bugs = hostile_runs(tmp_path, cfg, [("capture",), ("rig", "camera"), ("rig", "filter_wheel")],
                        [("capture-surface",)] * 3, first=("capture-surface",), options=("-q", "--force"),
                        too_long={"repeats": 100, "darks": 100})  # 1e5 frames: legal, an hour
    assert not bugs, "\n\n".join(bugs)


@pytest.mark.slow
def test_no_hostile_study_file_or_damaged_reconstruction_is_a_bug(tmp_path):
    """``fluxmap study`` on a study file with every leaf set to each hostile value (and a few
    path-like ones), then on a reconstruction.h5 with each dataset, each group's attributes
    and each root attribute deleted in turn, through summary, report and study.  This found
    a subject with sessions by day and by date stopping in the page's plot, and h5py's
    KeyError from every reader on a name missing inside a group (exit 1).  ~9 min on 2 busy cores."""
    import h5py

    runner = CliRunner()
    cfg = tiny_config(tmp_path)
    cfg["workdir"] = str(tmp_path / "run")
    cfg["rois"] = [{"name": "top", "kind": "box", "min_mm": [-20, -20, 12], "max_mm": [20, 20, 40]},
                   {"name": "half", "kind": "threshold", "fraction": 0.5}]
    cfg["report"] = {"title": "fuzz"}
    p = tmp_path / "c.yaml"
    p.write_text(yaml.safe_dump(cfg))
    for stage in ("build-T", "simulate", "reconstruct"):
        r = runner.invoke(app, [stage, str(p), "-q"])
        assert r.exit_code == 0, r.output
    shutil.copytree(tmp_path / "run", tmp_path / "good")
    study = {"title": "t", "output": "out", "rois": ["top", "half"], "sessions": [
        {"artefact": "run/reconstruction.h5", "subject": "a", "day": 1, "filter": "F1", "label": "x"},
        {"artefact": "good/reconstruction.h5", "subject": "a", "day": 2.5, "filter": "F1"},
        {"artefact": "good/reconstruction.h5", "subject": "b", "date": "2026-11-20", "filter": "F2"}]}
    s = tmp_path / "study.yaml"
    bugs = []

    def check(tag, args):
        r = runner.invoke(app, args)
        if r.exit_code not in (0, 2):
            bugs.append(f"{tag}: exit {r.exit_code}\n{r.output[-800:]}")

    s.write_text(yaml.safe_dump(study))
    assert runner.invoke(app, ["study", str(s), "-q"]).exit_code == 0
    for path, _ in list(leaves(study)):
        for value in HOSTILE + ["", "/dev/null", "run", "2026-02-30", "x" * 5000]:
            c = copy.deepcopy(study)
            node = c
            for k in path[:-1]:
                node = node[k]
            node[path[-1]] = value
            s.write_text(yaml.safe_dump(c))
            check(f"{'.'.join(map(str, path))} = {value!r}"[:120], ["study", str(s), "-q"])
    s.write_text(yaml.safe_dump(study))

    names = []
    with h5py.File(tmp_path / "good" / "reconstruction.h5") as f:
        f.visit(names.append)
        root = list(f.attrs)
    edits = [(f"no {n}", lambda f, n=n: f.__delitem__(n) if n in f else None) for n in names]
    edits += [(f"no attributes of {n}", lambda f, n=n: [f[n].attrs.__delitem__(a) for a in list(f[n].attrs)] if n in f else None)
              for n in names]
    edits += [(f"no root attribute {a}", lambda f, a=a: f.attrs.__delitem__(a)) for a in root]
    for tag, edit in edits:
        shutil.rmtree(tmp_path / "run")
        shutil.copytree(tmp_path / "good", tmp_path / "run")
        with h5py.File(tmp_path / "run" / "reconstruction.h5", "r+") as f:
            edit(f)
        for args in (["summary", str(p), "-q"], ["report", str(p), "-q"], ["study", str(s), "-q"]):
            check(f"reconstruction.h5 with {tag} -> {args[0]}", args)
    assert not bugs, "\n\n".join(bugs)
