"""What one ``fluxmap calibrate`` run does, resolved once from the config.

:func:`plan_of` is the only function below the command that reads the loaded config: it
resolves and checks every input file (grid images, a capture, radiometric and projector
frames), makes the provenance and the inputs digest; the stage's helpers take parts of the
:class:`CalibratePlan` it returns.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from .. import artefacts as A
from .. import config as C
from ..artefacts import calibration as AC
from ..errors import UserError
from ._radiometric import section_files


@dataclass(frozen=True)
class CalibratePlan:
    """One calibrate run: the section, the camera it starts from, every input file, the outputs."""

    config_path: Path  # the config file (named in messages)
    config_sha256: str  # its sha256 (recorded in the artefact)
    section: C.Calibrate  # calibrate: grid, images, capture, radiometric, projectors, refine_mirrors
    system: C.System | None  # the camera's pixels and pitch (given), the lens and pose to start from, the mirrors
    output: Path  # <workdir>/calibration.h5
    yaml_output: Path  # <workdir>/camera.yaml
    projector_frames_dir: Path  # <workdir>/projector_frames: where the simulated rig writes its frames
    capture: Path | None  # calibrate.capture, resolved and present
    image_files: tuple  # calibrate.images[].file, resolved and present
    projector_frames: dict  # config key -> [frame file], resolved, present and counted
    resolve: Callable[[Path], Path]  # a path of the config, relative to its folder, made absolute
    provenance: A.Provenance  # the config, the geometry and every input file with its sha256
    inputs_digest: str  # of the section, the camera, the mirrors and the input files: up to date when equal

    @property
    def camera(self) -> C.Camera | None:
        return self.system.camera if self.system is not None else None


def plan_of(cfg: C.LoadedConfig) -> CalibratePlan:
    """Resolve and check every input of ``calibrate:`` (UserError naming the key and the file)."""
    from .plans import provenance

    sec = cfg.model.calibrate
    if sec is None:
        raise UserError(f"config {cfg.path}: 'calibrate' is missing: what to calibrate from (images of the grid at "
                        "known heights, calibrate.images, or the frames capture-surface took, calibrate.capture).")
    system = cfg.model.system
    cam = system.camera if system is not None else None
    capture_path = cfg.resolve(sec.capture) if sec.capture is not None else None
    if capture_path is not None and not capture_path.is_file():
        raise UserError(f"calibrate.capture: {capture_path} does not exist; take the calibration frames first with "
                        "'fluxmap capture-surface CONFIG' (capture.calibration).")
    image_paths = [cfg.resolve(im.file) for im in sec.images]
    for k, p in enumerate(image_paths):
        if not p.is_file():
            raise UserError(f"calibrate.images[{k}].file: image file {p} does not exist.")
    rad_paths = [cfg.resolve(p) for p in section_files(sec.radiometric)] if sec.radiometric is not None else []
    frame_paths = _projector_frame_paths(cfg.resolve, sec)
    prov = provenance(cfg)
    for k, p in enumerate(image_paths):
        prov.add_file(f"calibrate.images[{k}]", p)
    for key, paths in frame_paths.items():
        for k, p in enumerate(paths):
            prov.add_file(f"{key}[{k}]", p)
    for k, p in enumerate(rad_paths):
        if p.is_file():
            prov.add_file(f"calibrate.radiometric[{k}]", p)
    if capture_path is not None:
        prov.add_file("calibrate.capture", capture_path)
    digest = A.inputs_digest(calibrate=sec.model_dump(mode="json"),
                             camera=cam.model_dump(mode="json") if cam is not None else None,
                             mirrors=[m.model_dump(mode="json") for m in system.mirrors] if system is not None else [],
                             files={n: d["sha256"] for n, d in prov.input_files.items()})
    return CalibratePlan(cfg.path, cfg.sha256, sec, system, cfg.workdir / AC.FILE_NAME, cfg.workdir / AC.YAML_NAME,
                         cfg.workdir / "projector_frames", capture_path, tuple(image_paths), frame_paths, cfg.resolver,
                         prov, digest)


def _expand(resolve: Callable[[Path], Path], spec, key: str) -> list[Path]:
    if isinstance(spec, str):
        import glob

        pattern = resolve(Path(spec))
        files = sorted(Path(f) for f in glob.glob(str(pattern)))
        if not files:
            raise UserError(f"{key}: the pattern {pattern} matches no file.")
        return files
    return [resolve(p) for p in spec]


def _projector_frame_paths(resolve: Callable[[Path], Path], sec: C.Calibrate) -> dict[str, list[Path]]:
    """Every projector frame file the config names (simulated frames are made later), by config key."""
    from ..structured.patterns import column_patterns

    out = {}
    for k, pc in enumerate(sec.projectors):
        for i, im in enumerate(pc.images):
            for which, cells in (("columns", pc.pixels[0]), ("rows", pc.pixels[1])):
                key = f"calibrate.projectors[{k}].images[{i}].{which}"
                paths = _expand(resolve, getattr(im, which), key)
                for p in paths:
                    if not p.is_file():
                        raise UserError(f"{key}: frame file {p} does not exist.")
                n = len(column_patterns(cells, 1, period_px=pc.patterns.period_px, n_steps=pc.patterns.n_steps).frames)
                check_count(paths, key, n)
                out[key] = paths
    return out


def check_count(paths: list[Path], key: str, n_expected: int) -> None:
    if len(paths) != n_expected:
        raise UserError(f"{key}: {len(paths)} frame file(s) given, the pattern sequence has {n_expected} "
                        "(white, black, each Gray bit and its inverse, the phase steps; check "
                        "calibrate.projectors[].pixels and .patterns).")
