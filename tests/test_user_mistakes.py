"""User mistakes across every stage: each exits 2 with one paragraph that names the config
key or file, never a traceback.

A tiny pipeline (a 24-element cylinder on a 24 x 24 camera, two stage heights) is built
once per module; each mistake runs in process through the CLI, most against those
artefacts (a mistake never changes them: the ones that damage an artefact copy it first).
"""

from __future__ import annotations

import copy
import os
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from fluxcli.cli import app
from fluxcli.imaging.imagefiles import write_image

from tiny_pipeline import tiny_run  # noqa: F401  (the session fixture)

ROOT = Path(__file__).resolve().parents[1]
runner = CliRunner()


def invoke(*args):
    r = runner.invoke(app, [str(a) for a in args])
    return r, " ".join(r.output.split())  # messages are wrapped at 100 columns


@pytest.fixture(scope="module")
def base(tiny_run):
    return tiny_run[0], tiny_run[1]


# ------------------------------------------------------------------ helpers making bad inputs
def put(d: dict, dotted: str, value):
    keys = dotted.split(".")
    for k in keys[:-1]:
        d = d.setdefault(k, {})
    d[keys[-1]] = value


def drop(d: dict, dotted: str):
    keys = dotted.split(".")
    for k in keys[:-1]:
        d = d[k]
    del d[keys[-1]]


def ply(path: Path, vertices, faces, element=None) -> Path:
    lines = ["ply", "format ascii 1.0", f"element vertex {len(vertices)}", "property float x", "property float y",
             "property float z", f"element face {len(faces)}", "property list uchar int vertex_indices"]
    if element is not None:
        lines.append("property int element")
    lines.append("end_header")
    lines += [" ".join(str(c) for c in v) for v in vertices]
    for k, f in enumerate(faces):
        lines.append(f"{len(f)} " + " ".join(str(i) for i in f) + (f" {element[k]}" if element is not None else ""))
    path.write_text("\n".join(lines) + "\n")
    return path


TETRA = [[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10]]
TETRA_FACES = [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]


def copy_run(base_dir: Path, d: Path) -> Path:
    shutil.copytree(base_dir / "run", d / "run")
    return d / "run"


def images(d: Path, n=2, *, value=100.0, dtype=np.float32, units="photons", shape=(24, 24), heights=(0, 5), nan=False):
    files = []
    for k in range(n):
        a = np.full(shape, value, dtype)
        if nan:
            a[:] = np.nan
        f = d / f"img{k}.tif"
        write_image(f, a, metadata={"fluxmap:units": units, "fluxmap:height_mm": float(heights[k % len(heights)]),
                                    "fluxmap:rotation_deg": 0.0})
        files.append(str(f))
    return files


# ------------------------------------------------------------------ the mistakes
# (id, stage, edit(cfg, dir, base_dir) -> extra CLI args or None, words the message must hold)
def _cfg(key, value):
    def edit(cfg, d, b):
        put(cfg, key, value)
    return edit


def _del(key):
    def edit(cfg, d, b):
        drop(cfg, key)
    return edit


def _set(*items):
    def edit(cfg, d, b):
        return [x for it in items for x in ("--set", it)]
    return edit


def _mesh(vertices, faces, element=None, name="m.ply"):
    def edit(cfg, d, b):
        cfg["subject"]["surface"] = {"mesh": str(ply(d / name, vertices, faces, element))}
    return edit


def _raw_mesh(text: str, name="m.ply"):
    def edit(cfg, d, b):
        (d / name).write_text(text)
        cfg["subject"]["surface"] = {"mesh": str(d / name)}
    return edit


def _own_run(edit_run=None):
    """Work on a copy of the base run (for mistakes that damage artefacts)."""
    def edit(cfg, d, b):
        run = copy_run(b, d)
        cfg["workdir"] = str(run)
        if edit_run is not None:
            edit_run(run, cfg, d)
    return edit


def _images(**kw):
    def edit(cfg, d, b):
        cfg["reconstruct"]["images"] = {"files": images(d, **{k: v for k, v in kw.items() if k != "cfg_units"}),
                                        "units": kw.get("cfg_units", "photons")}
        cfg["workdir"] = str(d / "run")
    return edit


def _corrupt_chunk(run: Path, cfg, d):
    p = run / "simulation.h5"
    with h5py.File(p, "r") as f:
        info = f["images/noisy"].id.get_chunk_info(0)
    with open(p, "r+b") as fh:
        fh.seek(info.byte_offset + info.size // 2)
        fh.write(b"\xff" * 8)


def _drop_dataset(name):
    def edit(run: Path, cfg, d):
        with h5py.File(run / "simulation.h5", "a") as f:
            del f[name]
    return edit


def _garbage(name):
    def edit(run: Path, cfg, d):
        (run / name).write_bytes(b"not an HDF5 file at all" * 10)
    return edit


def _h5_edit(name, statement):
    def edit(run: Path, cfg, d):
        import h5py

        with h5py.File(run / name, "r+") as f:
            exec(statement, {"f": f})
    return edit


def _swap_kind(run: Path, cfg, d):
    shutil.copy(run / "transfer.h5", run / "simulation.h5")


def _file_workdir(cfg, d, b):
    (d / "afile").write_text("x")
    cfg["workdir"] = str(d / "afile")


def _under_file_workdir(cfg, d, b):
    (d / "afile").write_text("x")
    cfg["workdir"] = str(d / "afile" / "run")


def _file_cache(cfg, d, b):
    (d / "cachefile").write_text("x")
    cfg["transfer"]["cache_dir"] = str(d / "cachefile")
    cfg["workdir"] = str(d / "run")


def _flux_file(values):
    def edit(cfg, d, b):
        np.save(d / "flux.npy", np.asarray(values, float))
        cfg["simulate"]["flux"] = {"kind": "file", "path": str(d / "flux.npy")}
        cfg["workdir"] = str(d / "run")
    return edit


def _flux_file_raw(name, write):
    def edit(cfg, d, b):
        write(d / name)
        cfg["simulate"]["flux"] = {"kind": "file", "path": str(d / name)}
        cfg["workdir"] = str(d / "run")
    return edit


def _diffusion(**over):
    def edit(cfg, d, b):
        flux = {"kind": "diffusion", "wavelength_nm": 650, "mesh_edge_mm": 3.0,
                "optical": {650: {"mua_per_mm": 0.02, "musp_per_mm": 1.7}},
                "sources": [{"depth_mm": 2.0, "power_photons": 1e8}]}
        for k, v in over.items():
            put(flux, k, v)
        cfg["simulate"]["flux"] = flux
        cfg["workdir"] = str(d / "run")
    return edit


def _patch_diffusion(cfg, d, b):
    cfg["subject"]["surface"] = {"phantom": "patch"}
    _diffusion()(cfg, d, b)


def _mesh_in_metres(cfg, d, b):
    """The tiny run's own simulated images, with the subject's size given in metres."""
    with h5py.File(b / "run" / "simulation.h5") as f:
        photons = f["images/noisy"][0, 0]  # level 0, repeat 0, every pose (photons)
    files = []
    for k, a in enumerate(photons):
        write_image(d / f"sim{k}.tif", a.astype(np.float32), metadata={"fluxmap:units": "photons"})
        files.append(str(d / f"sim{k}.tif"))
    cfg["subject"]["surface"].update(radius_mm=0.008, length_mm=0.024)
    cfg["reconstruct"]["images"] = {"files": files}
    cfg["workdir"] = str(d / "run")


def _no_sim(cfg, d, b):
    cfg["workdir"] = str(d / "run")


def _saturated(cfg, d, b):
    cfg["system"]["camera"]["sensor"] = {"bit_depth": 16}
    cfg["reconstruct"]["images"] = {"files": images(d, value=65535, dtype=np.uint16, units="counts"), "units": "counts"}
    cfg["workdir"] = str(d / "run")


def _bias_subtracted(cfg, d, b):
    cfg["system"]["camera"]["sensor"] = {"bias_counts": 500}
    cfg["reconstruct"]["images"] = {"files": images(d, value=40.0, units="counts"), "units": "counts"}
    cfg["workdir"] = str(d / "run")


def _with_images_and_sweep(cfg, d, b):
    cfg["reconstruct"]["images"] = {"files": images(d)}
    cfg["reconstruct"]["sweep"] = {"methods": [{"method": "nnls"}]}
    cfg["workdir"] = str(d / "run")


def _report_changed(cfg, d, b):
    cfg["system"]["camera"]["lens"]["f_number"] = 2.8


def _mirror(**over):
    m = {"center_mm": [0, 31.14, 14.14], "normal": [0, -1, 1], "axis": [1, 0, 0], "size_mm": [70, 40]}
    m.update(over)
    return _cfg("system.mirrors", [m])


MISTAKES = [
    # --- the config file
    ("config-missing", "build-T", lambda c, d, b: ["--set", "x=1"] and None, ["does not exist"]),
    ("yaml-invalid", "build-T", None, ["not valid YAML"]),
    ("config-is-a-folder", "build-T", None, ["is a folder"]),
    ("yaml-not-mapping", "build-T", None, ["mapping"]),
    ("yaml-duplicate-key", "build-T", None, ["duplicate key", "'workdir'"]),
    # a date YAML's pattern takes but the calendar does not: was a ValueError from inside the parser
    ("yaml-impossible-date", "build-T", None, ["not valid YAML", "'2026-02-30' is not a date", "line"]),
    ("set-impossible-date", "build-T", _set("workdir=2026-13-01"), ["--set 'workdir=2026-13-01'", "not a date"]),
    ("unknown-top-key", "build-T", _cfg("sytem", {}), ["'sytem'", "unknown key"]),
    ("unknown-nested-key", "build-T", _cfg("system.camera.pixel_pitch", 0.1), ["system.camera.pixel_pitch"]),
    # a NUL character in a path: the OS refuses it ("embedded null byte", exit 1; found by fuzzing study files)
    ("nul-in-a-path", "build-T", _cfg("subject.surface", {"mesh": "a\x00b.ply"}), ["'subject.surface.mesh'", "NUL"]),
    # a path given as empty text reads as "." (the config's folder): artefacts or a T cache would
    # land beside the configs without a word, and an empty mesh read "is a folder"
    ("empty-workdir", "build-T", _cfg("workdir", ""), ["'workdir'", "is an empty path"]),
    ("empty-cache-dir", "build-T", _cfg("transfer", {"cache_dir": "  "}), ["'transfer.cache_dir'", "is an empty path"]),
    ("empty-mesh", "build-T", _cfg("subject.surface", {"mesh": ""}), ["'subject.surface.mesh'", "is an empty path"]),
    # a key of a section with variants: was named 'subject.emission.diffuse.scattering_anisotropy' (pydantic's
    # name for the variant in the key's path); g is a mean cosine, tissue's ~0.9, not a percentage
    ("emission-g-as-percent", "build-T", _cfg("subject.emission", {"model": "diffuse", "scattering_anisotropy": 90}),
     ["'subject.emission.scattering_anisotropy'", "less than 1"]),
    ("missing-lens", "build-T", _del("system.camera.lens"), ["system.camera.lens"]),
    # a point given with two numbers: was "'system.camera.pose.lens_center_mm.2': required key is missing"
    ("vector-too-short", "build-T", _cfg("system.camera.pose.lens_center_mm", [0, 0]),
     ["'system.camera.pose.lens_center_mm': too few values: item 3"]),
    ("pixels-negative", "build-T", _cfg("system.camera.pixels", [-4, 24]), ["system.camera.pixels"]),
    ("pixel-pitch-zero", "build-T", _cfg("system.camera.pixel_pitch_mm", 0), ["system.camera.pixel_pitch_mm"]),
    ("f-number-and-diameter", "build-T", _cfg("system.camera.lens.aperture_diameter_mm", 5), ["f_number"]),
    ("f-number-impossible", "build-T", _cfg("system.camera.lens.f_number", 0.04), ["system.camera.lens", "f/0.04", "f/0.5"]),
    ("focus-inside-focal-length", "build-T", _cfg("system.camera.lens.focus_distance_mm", 10), ["focus_distance_mm"]),
    ("look-parallel-up", "build-T", _cfg("system.camera.pose.up", [0, 0, 1]), ["system.camera.pose", "up"]),
    ("look-zero", "build-T", _cfg("system.camera.pose.look", [0, 0, 0]), ["look"]),
    # a direction of length 1e300: its squares overflowed, normalising it gave (0, 0, 0) and the
    # projector calibration stopped in its solver (exit 1; found by fuzzing calibrate's keys)
    ("look-huge", "build-T", _cfg("system.camera.pose.look", [0, 0, -1e300]),
     ["system.camera.pose", "look is a direction", "1e+300"]),
    ("mirror-axis-off-plane", "build-T", _mirror(axis=[0, 1, 0]), ["system.mirrors.0", "axis"]),
    ("mirror-faces-away", "build-T", _mirror(normal=[0, 1, -1]), ["system.mirrors", "faces away"]),
    ("mirror-size-negative", "build-T", _mirror(size_mm=[-70, 40]), ["system.mirrors.0", "size_mm"]),
    ("mirror-through-subject", "build-T", _mirror(center_mm=[0, 0, 8]), ["system.mirrors", "'mirror0'", "through the subject"]),
    ("mirror-listed-twice", "build-T", _cfg("system.mirrors", [
        {"name": n, "center_mm": [0, 31.14, 14.14], "normal": [0, -1, 1], "axis": [1, 0, 0], "size_mm": [70, 40]}
        for n in ("right", "right again")]), ["system.mirrors", "'right' and 'right again'", "listed twice"]),
    ("mirror-reflectance", "build-T", _mirror(reflectance=1.5), ["system.mirrors.0.reflectance"]),
    ("sensor-bit-depth", "build-T", _cfg("system.camera.sensor", {"bit_depth": 20}), ["system.camera.sensor.bit_depth"]),
    ("phantom-unknown", "build-T", _cfg("subject.surface", {"phantom": "cube"}), ["subject.surface"]),
    ("radius-negative", "build-T", _cfg("subject.surface.radius_mm", -8), ["subject.surface.radius_mm"]),
    ("poses-empty", "simulate", _cfg("subject.poses.heights_mm", []), ["subject.poses.heights_mm"]),
    ("rotations-empty", "build-T", _cfg("subject.poses.rotations_deg", []), ["subject.poses.rotations_deg"]),
    ("estimator-unknown", "build-T", _cfg("transfer.estimator", "magic"), ["transfer.estimator"]),
    ("rays-per-batch-tiny", "build-T", _cfg("transfer.rays_per_batch", 10), ["transfer.rays_per_batch"]),
    ("lens-samples-zero", "build-T", _cfg("transfer.lens.lens_samples_min", 0), ["transfer.lens.lens_samples_min"]),
    # --- --set
    ("set-no-equals", "build-T", _set("transfer.estimator"), ["--set", "transfer.estimator"]),
    ("set-unparsable", "build-T", _set("subject.poses.heights_mm=[1,"), ["--set", "subject.poses.heights_mm", "not valid YAML"]),
    ("set-bad-index", "build-T", _set("system.mirrors.3.reflectance=0.5"), ["--set", "system.mirrors"]),
    ("set-into-value", "build-T", _set("system.camera.pixel_pitch_mm.x=1"), ["--set", "system.camera.pixel_pitch_mm"]),
    ("set-wrong-type", "build-T", _set("subject.poses.heights_mm=abc"), ["subject.poses.heights_mm"]),
    ("set-unknown-key", "build-T", _set("transfer.estimatr=lens"), ["transfer.estimatr"]),
    ("set-lambda-negative", "reconstruct", _set("reconstruct.lambda=-1"), ["reconstruct.lambda"]),
    # --- mesh files
    ("mesh-missing", "build-T", _cfg("subject.surface", {"mesh": "nowhere.ply"}), ["subject.surface.mesh", "nowhere.ply"]),
    ("mesh-nan-vertex", "build-T", _mesh([[0, 0, 0], [10, 0, 0], ["nan", 10, 0], [0, 0, 10]], TETRA_FACES),
     ["subject.surface.mesh", "m.ply", "non-finite"]),
    ("mesh-index-out-of-range", "build-T", _mesh(TETRA, [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 7]]),
     ["subject.surface.mesh", "m.ply", "vertex index 7"]),
    ("mesh-zero-area-element", "build-T", _mesh(TETRA + [[5, 5, 5]], TETRA_FACES + [[4, 4, 4]], [0, 1, 2, 3, 4]),
     ["m.ply", "element 4 has zero area"]),
    # a vertex beyond 1 km: the weld's tolerance grew with it and every element was called "zero area"
    # (1e9), or scipy's k-d tree overflowed (1e300)
    ("mesh-vertex-beyond-1-km", "build-T", _mesh(TETRA[:3] + [[0, 0, 1e9]], TETRA_FACES),
     ["subject.surface.mesh", "m.ply", "vertex 3 lies at", "more than 1 km"]),
    ("mesh-garbage", "build-T", _raw_mesh("this is not a mesh\n"), ["subject.surface.mesh", "m.ply"]),
    ("mesh-empty", "build-T", _raw_mesh(""), ["subject.surface.mesh", "m.ply"]),
    ("mesh-unknown-suffix", "build-T", _raw_mesh("x", name="m.xyz"), ["subject.surface.mesh", "m.xyz"]),
    ("surface-artefact-not-hdf5", "build-T",
     lambda c, d, b: (d.joinpath("s.h5").write_text("no"), put(c, "subject.surface", {"artefact": str(d / "s.h5")})) and None,
     ["subject.surface.artefact", "s.h5"]),
    # --- folders
    ("workdir-is-a-file", "build-T", _file_workdir, ["workdir", "afile"]),
    ("workdir-under-a-file", "simulate", _under_file_workdir, ["workdir", "afile"]),
    ("cache-dir-is-a-file", "build-T", _file_cache, ["transfer.cache_dir", "cachefile"]),
    # --- geometry that cannot give a model
    ("camera-looks-away", "build-T", _cfg("system.camera.pose.look", [0, 0, 1]),
     ["no camera view collects any light", "system.camera.pose.look"]),
    ("subject-above-lens", "build-T", _cfg("subject.poses.heights_mm", [400]),
     ["no camera view collects any light", "subject.poses.heights_mm"]),
    ("pixels-huge", "build-T", _cfg("system.camera.pixels", [100000, 100000]), ["system.camera.pixels", "GB"]),
    # --- simulate
    ("simulate-missing", "simulate", _del("simulate"), ["'simulate'"]),
    ("flux-kind-unknown", "simulate", _cfg("simulate.flux", {"kind": "laser"}), ["simulate.flux"]),
    ("flux-file-missing", "simulate", _cfg("simulate.flux", {"kind": "file", "path": "nope.npy"}),
     ["simulate.flux.path", "nope.npy"]),
    ("flux-file-wrong-count", "simulate", _flux_file(np.ones(5)), ["simulate.flux.path", "flux.npy", "5 values"]),
    ("flux-file-negative", "simulate", _flux_file(-np.ones(24)), ["simulate.flux.path", "negative"]),
    ("flux-file-of-strings", "simulate", _flux_file_raw("flux.npy", lambda p: np.save(p, np.array(["a"] * 24))),
     ["simulate.flux.path", "flux.npy", "<U1 values, not numbers"]),  # was a traceback
    ("flux-file-two-columns", "simulate", _flux_file_raw("flux.csv", lambda p: p.write_text("1,2\n" * 24)),
     ["simulate.flux.path", "flux.csv", "line 1 holds 2 values", "one value per line"]),
    ("flux-width-zero", "simulate", _cfg("simulate.flux.width_mm", 0), ["simulate.flux", "width_mm"]),
    # a gaussian that reaches no face: its truth was 0/0 and the error blamed the noise level
    ("flux-gaussian-off-the-surface", "simulate", _cfg("simulate.flux.center_mm", [1e5, 0, 0]),
     ["simulate.flux", "puts no light on the surface", "center_mm"]),
    # lengths beyond 1 km: their squares overflowed inside the ray tracer (found by fuzzing every key)
    ("flux-width-absurd", "simulate", _cfg("simulate.flux.width_mm", 1e300), ["simulate.flux.width_mm", "1 km"]),
    ("phantom-too-fine", "build-T", _set("subject.surface={phantom: cylinder, n_angular: 10000000, n_axial: 3}"),
     ["subject.surface.n_axial", "3e+07 pieces"]),  # used to fill 6 GB building the mesh
    ("aperture-absurd", "build-T", _cfg("system.camera.apertures", [{"distance_mm": 30, "diameter_mm": 1e300}]),
     ["system.camera.apertures.0.diameter_mm", "millimetres", "1 km"]),
    ("diffusion-wavelength", "simulate", _diffusion(wavelength_nm=800), ["simulate.flux", "wavelength_nm"]),
    ("diffusion-open-surface", "simulate", _patch_diffusion, ["simulate.flux", "closed"]),
    ("diffusion-too-deep", "simulate", _diffusion(**{"sources": [{"depth_mm": 50.0, "power_photons": 1e8}]}),
     ["simulate.flux.sources.0.depth_mm"]),
    ("fem-too-fine", "simulate", _diffusion(mesh_edge_mm=0.001), ["simulate.flux.mesh_edge_mm", "tetrahedra"]),
    # light that dies within 0.5 mm on a 4 mm mesh: the FEM truth swings negative (it was a
    # negative total and an error about the noise level before)
    ("fem-too-coarse", "simulate", _diffusion(mesh_edge_mm=4.0, optical={650: {"mua_per_mm": 0.5, "musp_per_mm": 1.7}},
                                              sources=[{"depth_mm": 6.0, "power_photons": 1e8}]),
     ["simulate.flux.mesh_edge_mm", "too coarse", "undershoots"]),
    ("export-folder-is-a-file", "simulate",
     lambda c, d, b: ((d / "run").mkdir(), (d / "run" / "images").write_text("x"), put(c, "workdir", str(d / "run")),
                      put(c, "simulate.export", {"format": "tiff"})) and None, ["run/images"]),
    ("noise-peaks-negative", "simulate", _cfg("simulate.noise.peaks_photons", [-1]), ["simulate.noise.peaks_photons"]),
    ("noise-repeats-zero", "simulate", _cfg("simulate.noise.repeats", 0), ["simulate.noise.repeats"]),
    ("inverse-crime", "simulate", _cfg("simulate.transfer", {"lens": {"lens_samples_min": 16}}), ["simulate.transfer"]),
    # --- reconstruct from a simulation
    ("no-simulation", "reconstruct", _no_sim, ["simulation.h5", "does not exist"]),
    # the solve only looks at pixels T reaches: light elsewhere must not vanish without a word
    ("mesh-in-metres", "reconstruct", _mesh_in_metres, ["no element of the subject can reach", "millimetres",
                                                        "subject.surface spans"]),
    ("sim-other-f-number", "reconstruct", _set("system.camera.lens.f_number=2.8"),
     ["system.camera.lens.f_number: 4 in simulation.h5, 2.8 now"]),
    ("sim-other-heights", "reconstruct", _set("subject.poses.heights_mm=[0, 10]"),
     ["subject.poses.heights_mm: [0, 5] in simulation.h5, [0, 10] now"]),
    ("sim-other-radius", "reconstruct", _set("subject.surface.radius_mm=10"),
     ["subject.surface.radius_mm: 8 in simulation.h5, 10 now"]),
    ("sim-other-mirrors", "reconstruct", _mirror(), ["system.mirrors"]),
    ("dense-normal-matrix-too-big", "reconstruct",
     _set("subject.surface={phantom: sphere, n_latitude: 250, n_longitude: 250}"),
     ["reconstruct.method", "subject.surface", "62500 elements", "GB"]),
    ("level-out-of-range", "reconstruct", _set("reconstruct.level=3"), ["reconstruct.level"]),
    ("method-unknown", "reconstruct", _set("reconstruct.method=magic"), ["reconstruct.method"]),
    ("lambda-rule-unknown", "reconstruct", _set("reconstruct.lambda_rule=guess"), ["reconstruct.lambda_rule"]),
    ("sweep-no-methods", "reconstruct", _cfg("reconstruct.sweep", {"methods": []}), ["reconstruct.sweep.methods"]),
    ("sweep-level-out-of-range", "reconstruct",
     lambda c, d, b: (put(c, "reconstruct.sweep", {"methods": [{"method": "nnls"}], "levels": [4]}), _own_run()(c, d, b)) and None,
     ["reconstruct.sweep.levels"]),
    ("sweep-repeats-out-of-range", "reconstruct",
     lambda c, d, b: (put(c, "reconstruct.sweep", {"methods": [{"method": "nnls"}], "repeats": 100}), _own_run()(c, d, b)) and None,
     ["reconstruct.sweep.repeats"]),
    ("sim-saturated-level", "reconstruct",
     lambda c, d, b: (put(c, "simulate.noise", {"model": "emccd", "peaks_photons": [1e12]}),
                      put(c, "system.camera.sensor", {"em_gain": 300}), put(c, "workdir", str(d / "run"))) and None,
     ["reconstruct.level", "saturated"]),
    ("poisson-level-too-high", "simulate", _cfg("simulate.noise.peaks_photons", [1e30]), ["simulate.noise.peaks_photons"]),
    ("rotation-axis-zero", "build-T", _cfg("subject.rotation_axis", {"direction": [0, 0, 0]}),
     ["subject.rotation_axis.direction"]),
    ("rotation-nan", "build-T", _set("subject.poses.rotations_deg=[.nan]"), ["subject.poses.rotations_deg"]),
    ("lens-samples-max-below-min", "build-T", _cfg("transfer.lens.lens_samples_max", 2), ["lens_samples_max"]),
    ("too-many-surface-samples", "build-T",
     _set("transfer.lens.surface_samples_per_pixel=1e5", "transfer.lens.max_surface_subdivisions=1000000"),
     ["transfer.lens.surface_samples_per_pixel", "GB"]),
    ("sweep-without-truth", "reconstruct", _with_images_and_sweep, ["reconstruct.sweep"]),
    ("sim-corrupt-file", "reconstruct", _own_run(_garbage("simulation.h5")), ["simulation.h5", "not a readable HDF5"]),
    ("sim-missing-dataset", "reconstruct", _own_run(_drop_dataset("truth/power")), ["simulation.h5", "truth/power"]),
    ("sim-corrupt-chunk", "reconstruct", _own_run(_corrupt_chunk), ["simulation.h5", "corrupt", "images/noisy"]),
    ("sim-wrong-kind", "reconstruct", _own_run(_swap_kind), ["simulation.h5", "transfer-index"]),
    # --- reconstruct from image files
    ("images-count", "reconstruct", _images(n=1), ["reconstruct.images.files", "1 file(s) for 2 pose(s)"]),
    ("image-missing", "reconstruct", lambda c, d, b: put(c, "reconstruct.images", {"files": ["a.tif", "b.tif"]}),
     ["reconstruct.images.files", "a.tif"]),
    ("image-wrong-size", "reconstruct", _images(shape=(20, 24)), ["reconstruct.images.files[0]", "system.camera.pixels"]),
    ("image-units-disagree", "reconstruct", _images(dtype=np.uint16, units="counts", cfg_units="photons"),
     ["img0.tif", "fluxmap:units = counts", "reconstruct.images.units"]),
    ("counts-without-sensor", "reconstruct", _images(dtype=np.uint16, units="counts", cfg_units="counts"),
     ["reconstruct.images.units", "system.camera.sensor"]),
    ("image-integers-as-photons", "reconstruct",
     lambda c, d, b: (write_image(d / "u0.tif", np.full((24, 24), 700, np.uint16)),
                      write_image(d / "u1.tif", np.full((24, 24), 700, np.uint16)),
                      put(c, "reconstruct.images", {"files": [str(d / "u0.tif"), str(d / "u1.tif")]}),
                      put(c, "workdir", str(d / "run"))) and None,
     ["u0.tif", "uint16", "reconstruct.images.units"]),
    ("image-all-nan", "reconstruct", _images(nan=True), ["img0.tif", "NaN"]),
    ("image-all-negative", "reconstruct", _images(value=-5.0), ["img0.tif", "positive"]),
    ("image-saturated", "reconstruct", _saturated, ["img0.tif", "saturated"]),
    ("image-bias-subtracted", "reconstruct", _bias_subtracted, ["img0.tif", "below the bias", "bias_counts 500"]),
    ("images-pose-order", "reconstruct", _images(heights=(5, 0)), ["reconstruct.images.files[0]", "subject.poses"]),
    ("image-suffix", "reconstruct", lambda c, d, b: (d.joinpath("a.png").write_text("x"),
                                                     put(c, "reconstruct.images", {"files": [str(d / "a.png")] * 2})) and None,
     ["reconstruct.images.files", "a.png"]),
    # a capture's keys wrong: the error named the other kind of images' keys first ("files: required
    # key is missing", "capture: unknown key", ...) under pydantic's "function-after[_check(), ImageFiles]"
    ("capture-filter-twice", "reconstruct", _cfg("reconstruct.images", {"capture": "capture.h5", "filters": ["a", "a"]}),
     ["'reconstruct.images': filters: list each filter once"]),
    ("capture-transmission-zero", "reconstruct", _cfg("reconstruct.images", {
        "capture": "capture.h5", "filters": ["a", "b"], "transmissions": {"b": 0.0}}),
     ["'reconstruct.images': transmissions must lie in (0, 1]"]),
    # filter names are HDF5 groups, where '/' nests: '580' beside '580/20' stopped writing the artefact (exit 1)
    ("capture-filters-nest", "reconstruct", _cfg("reconstruct.images", {"capture": "capture.h5", "filters": ["580/20", "580"]}),
     ["'reconstruct.images': filters: '580' and '580/20' would nest in reconstruction.h5"]),
    ("files-with-capture-keys", "reconstruct", _cfg("reconstruct.images", {"files": ["a.tif"], "filters": ["a"]}),
     ["'reconstruct.images.filters': unknown key"]),
    # --- report
    ("report-no-reconstruction", "report", _no_sim, ["reconstruction.h5"]),
    ("report-slice-outside", "report", _set("report.slice_axial_mm=1000"), ["report.slice_axial_mm", "1000"]),
    ("report-config-changed", "report", _report_changed, ["reconstruction.h5", "system.camera.lens.f_number"]),
    ("report-corrupt-reconstruction", "report", _own_run(_garbage("reconstruction.h5")), ["reconstruction.h5"]),
    # a dataset or an attribute missing inside a group (another tool's file, or one sealed by no digest):
    # the readers met h5py's KeyError (exit 1); any name at any depth is now named with the file
    ("report-reconstruction-lacks-a-dataset", "report",
     _own_run(_h5_edit("reconstruction.h5", "del f['budget/sigma']; del f.attrs['results_sha256']")),
     ["reconstruction.h5 is incomplete: it has no dataset 'budget/sigma'", "fluxmap reconstruct"]),
    ("summary-reconstruction-lacks-an-attribute", "summary",
     _own_run(_h5_edit("reconstruction.h5", "del f['budget'].attrs['labels']; del f.attrs['results_sha256']")),
     ["reconstruction.h5 is incomplete: it has no attribute 'labels' of 'budget'"]),
    # and a sealed one edited after it was written (a pose's numbers one short: the report's
    # figures met arrays of different lengths, exit 1) is refused by its seal before anything is read
    ("report-reconstruction-edited", "report",
     _own_run(_h5_edit("reconstruction.h5", "d = f['per_pose/total'][()]; del f['per_pose/total']; "
                                            "f['per_pose/total'] = d[:-1]")),
     ["reconstruction.h5 was changed after it was written", "fluxmap reconstruct"]),
]


@pytest.mark.parametrize("case", MISTAKES, ids=[m[0] for m in MISTAKES])
def test_user_mistake_exits_2_naming_the_key_or_file(case, base, tmp_path):
    name, stage, edit, words = case
    base_dir, cfg0 = base
    cfg = copy.deepcopy(cfg0)
    extra = (edit(cfg, tmp_path, base_dir) if edit is not None else None) or []
    p = tmp_path / "cfg.yaml"
    if name == "config-missing":
        p = tmp_path / "missing.yaml"
    elif name == "config-is-a-folder":
        p = tmp_path
    elif name == "yaml-invalid":
        p.write_text("system: [1,\n")
    elif name == "yaml-not-mapping":
        p.write_text("- 1\n- 2\n")
    elif name == "yaml-duplicate-key":
        p.write_text(yaml.safe_dump(cfg) + f"workdir: {tmp_path}\n")
    elif name == "yaml-impossible-date":
        p.write_text(yaml.safe_dump(cfg) + "note: 2026-02-30\n")
    else:
        p.write_text(yaml.safe_dump(cfg))
    if name == "sim-saturated-level":  # a saturated simulation, then its reconstruction
        r, out = invoke("simulate", p, "-q")
        assert r.exit_code == 0, out
    r, out = invoke(stage, p, *extra)
    assert r.exit_code == 2, out
    assert "Traceback" not in out, out
    assert out.count("fluxmap: error:") == 1, out  # one paragraph, at the end
    out = out[out.index("fluxmap: error:"):]
    for w in words:
        assert w in out, f"{w!r} not in: {out}"
    assert "function-after" not in out and "tagged-union" not in out, out  # pydantic's names are not keys
    if name.startswith("capture-"):  # nothing of the other kind of images
        assert "files" not in out, out
    if os.environ.get("FLUXMAP_SHOW_MISTAKES"):
        print(f"\nMISTAKE {name} | {out}")


def test_info_names_a_missing_or_foreign_file(tmp_path):
    r, out = invoke("info", tmp_path / "nope.h5")
    assert r.exit_code == 2 and "nope.h5" in out and "Traceback" not in out
    (tmp_path / "x.h5").write_text("text")
    r, out = invoke("info", tmp_path / "x.h5")
    assert r.exit_code == 2 and "x.h5" in out and "Traceback" not in out


def test_there_are_at_least_60_mistakes():
    assert len(MISTAKES) + 2 >= 60


def test_faces_split_past_what_any_camera_resolves_are_refused_by_key(tmp_path, write_config, minimal_config):
    """subject.refine_faces: 3 on a mesh of 10^5 faces would make 6 x 10^6: exit 2 naming the key."""
    import pyvista as pv

    from fluxcli.surface import phantoms

    surf = phantoms.sphere(radius_mm=10.0, n_latitude=160, n_longitude=320)[0]

    cells = np.hstack([np.full((len(surf.faces), 1), 3), surf.faces]).ravel()
    pv.PolyData(surf.vertices_mm, cells).save(tmp_path / "dense.vtp")
    cfg = copy.deepcopy(minimal_config)
    cfg["subject"]["surface"] = {"mesh": "dense.vtp"}
    cfg["subject"]["refine_faces"] = 3
    r = runner.invoke(app, ["build-T", str(write_config(cfg))])
    assert r.exit_code == 2, r.output
    text = " ".join(r.output.split())
    assert "subject.refine_faces" in text and "Traceback" not in text


def test_a_projector_direction_of_absurd_length_is_refused():
    """calibrate's simulated projector with up = [1e300, 0, 0] stopped in the pose solver with
    non-finite residuals (exit 1): every direction is now checked as the camera's is."""
    from pydantic import ValidationError

    from fluxcli.config import ProjectorPose

    ok = ProjectorPose(center_mm=(0, -200, 150), look=(0, 200, -140), up=(-1e-9, 0, 0))  # small is fine
    assert ok.up == (-1e-9, 0, 0)
    with pytest.raises(ValidationError, match="up is a direction: give it components of ordinary size"):
        ProjectorPose(center_mm=(0, -200, 150), look=(0, 200, -140), up=(1e300, 0, 0))
