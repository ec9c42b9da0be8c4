"""Glue between ``calibrate.radiometric`` (config), image files, the radiometry library
and the ``/radiometric`` group of ``calibration.h5``.

- :func:`run_radiometric` reads the frames a :class:`~fluxcli.config.Radiometric` section
  names and runs :func:`fluxcli.calibration.radiometry.calibrate_radiometric`;
- :func:`write_radiometric` (:mod:`fluxcli.artefacts.calibration`'s, re-exported) stores a result;
- :func:`read_radiometric_maps` gives ``reconstruct`` the bias, dark and flat maps back.

Bad files (missing, unreadable, of another size) raise :class:`~fluxcli.errors.UserError`
naming the config key and the file.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

from .. import config as C
from ..calibration import radiometry as R
from ..errors import InputError, UserError
from ..imaging.imagefiles import read_image
from ..artefacts.calibration import MAPS, SCALARS, write_radiometric  # noqa: F401  (re-exported)
from .context import RunContext

KEY = "calibrate.radiometric"
GROUP = "radiometric"


def section_files(section: C.Radiometric) -> list[Path]:
    """Every file the section names, relative to the config file (as ``resolve`` takes
    them), for input digests."""
    files = [*section.bias, *section.flats]
    for level in section.ptc:
        files += level.files
    for dark in section.darks:
        files += dark.files
    folder = Path(section.directory) if section.directory is not None else Path()
    return [folder / f for f in files]


def _read_frames(files, key: str, resolve: Callable[[Path], Path], shape: list,
                 max_raw_counts: float = 65535.0) -> np.ndarray:
    """Frames of ``files`` as [frame, row, col]; the first file read fixes ``shape[0]``. Each must
    hold raw counts (0 to ``max_raw_counts``) and be like the others of its list."""
    frames = []
    for i, name in enumerate(files):
        path = resolve(name)
        try:
            image, _ = read_image(path)
        except (ValueError, OSError) as e:
            raise UserError(f"{KEY}.{key}[{i}]: {e}") from None
        if not np.all(np.isfinite(image)):
            raise UserError(f"{KEY}.{key}[{i}]: {path} holds non-finite values (NaN or inf); frames must be counts.")
        if shape[0] is None:
            shape[0] = image.shape
        elif image.shape != shape[0]:
            raise UserError(f"{KEY}.{key}[{i}]: {path} is {image.shape[1]} x {image.shape[0]} pixels; "
                            f"{shape[1]} is {shape[0][1]} x {shape[0][0]}. All radiometric frames must have one size.")
        lo, hi = float(image.min()), float(image.max())
        if lo < 0 or hi > max_raw_counts:
            raise UserError(f"{KEY}.{key}[{i}]: {path} holds values from {lo:.6g} to {hi:.6g}; a radiometric frame is "
                            f"the camera's raw counts, 0 to {max_raw_counts:g} (system.camera.sensor.bit_depth), not "
                            "bias-subtracted, scaled or converted to other units.")
        frames.append(image)
    frames = np.array(frames)
    _check_stack(frames, key, [resolve(name) for name in files])
    return frames


# Frames of one list share the light, exposure and EM gain: one whose level or pixel spread is
# off by more than these is another kind of frame (a lit frame among the bias frames, a gain-on
# frame in a gain-off pair, a blank file). Bias drifts by a few counts and a lamp by a few per
# cent between frames; a wrong frame is off by tens of per cent or by the EM gain.
STACK_MEAN_REL, STACK_MEAN_COUNTS = 0.10, 5.0
STACK_SPREAD_REL, STACK_SPREAD_COUNTS = 0.5, 1.0


def _check_stack(frames: np.ndarray, key: str, paths: list[Path]) -> None:
    """A UserError naming the frame of a list that is not like the others, or two identical
    frames (the same file twice: no temporal noise between them)."""
    n = len(frames)
    flat = frames.reshape(n, -1)
    for i in range(n):
        for j in range(i + 1, n):
            if np.array_equal(flat[i], flat[j]):
                raise UserError(f"{KEY}.{key}[{i}] and [{j}]: {paths[i]} and {paths[j]} hold the same pixels (the same "
                                "file twice?); frames of a list must be separate exposures: the difference between "
                                "them is the temporal noise the calibration measures.")
    if n < 2:
        return
    # median and MAD: a cosmic ray or a hot pixel in one frame moves neither
    mean = np.median(flat, axis=1)
    spread = 1.4826 * np.median(np.abs(flat - mean[:, None]), axis=1)
    for k in range(n):
        others = np.delete(np.arange(n), k)
        m, s = float(np.median(mean[others])), float(np.median(spread[others]))
        if (abs(mean[k] - m) > STACK_MEAN_REL * abs(m) + STACK_MEAN_COUNTS
                or abs(spread[k] - s) > STACK_SPREAD_REL * s + STACK_SPREAD_COUNTS):
            which = (f"{KEY}.{key}[{k}]: {paths[k]} is not like the other frame(s) of its list" if n > 2 else
                     f"{KEY}.{key}: {paths[0]} and {paths[1]} are not alike")
            raise UserError(f"{which}: median {mean[k]:.6g} counts and pixel spread {spread[k]:.4g} against "
                            f"{m:.6g} and {s:.4g}. The frames of one list share the light, the exposure and the EM "
                            "gain; is it another kind of frame (lit, gain on, dark) or a blank file?")


def run_radiometric(section: C.Radiometric, resolve: Callable[[Path], Path], ctx: RunContext, *,
                    expected_shape: tuple[int, int] | None = None, bit_depth: int = 16) -> R.RadiometricResult:
    """Read the frames named by ``calibrate.radiometric`` and calibrate.

    Parameters
    ----------
    section : fluxcli.config.Radiometric
        The validated section.
    resolve : callable
        Turns a path from the config into an absolute path (``LoadedConfig.resolve``).
    ctx : RunContext
        Where the summary and the warnings are said.
    expected_shape : (ny, nx), optional
        Frame size the camera has (``system.camera.pixels`` reversed); other sizes are
        refused.

    Returns
    -------
    fluxcli.calibration.radiometry.RadiometricResult
    """
    if section.directory is not None:
        folder, outer = Path(section.directory), resolve
        resolve = lambda name: outer(folder / name)  # noqa: E731
    shape: list = [tuple(expected_shape) if expected_shape is not None else None,
                   "system.camera.pixels" if expected_shape is not None else f"{KEY}.bias[0]"]
    top = float(2**bit_depth - 1)
    bias = _read_frames(section.bias, "bias", resolve, shape, top)
    ptc = [R.PTCLevel(_read_frames(lv.files, f"ptc[{j}].files", resolve, shape, top), lv.exposure_s, lv.em_gain_on,
                      lv.illumination) for j, lv in enumerate(section.ptc)]
    darks = [(_read_frames(d.files, f"darks[{j}].files", resolve, shape, top), d.exposure_s, d.em_gain_on)
             for j, d in enumerate(section.darks)]
    flats = _read_frames(section.flats, "flats", resolve, shape, top) if section.flats else None
    return _calibrate(KEY, ctx, bias=bias, ptc=ptc, darks=darks or None, flats=flats,
                      max_counts=section.saturation_counts,
                      excess_noise_factor_squared=section.excess_noise_factor_squared,
                      gain_tolerance=section.gain_tolerance)


def _calibrate(key: str, ctx: RunContext, **frames) -> R.RadiometricResult:
    try:
        result = R.calibrate_radiometric(**frames)
    except InputError as e:
        raise UserError(f"{key}: {e}") from None
    ctx.table(["quantity", "value", "1 sigma"], summary_rows(result))
    for w in result.warnings:
        ctx.say(f"calibrate: warning: {w}")
    return result


EVEN_LIGHT = "capture.calibration even light"  # one source for every flat and PTC frame of a capture


def radiometric_from_capture(cal, ctx: RunContext, *, bit_depth: int = 16) -> R.RadiometricResult:
    """Calibrate from the bias, dark, flat and photon-transfer frames of a capture
    (:class:`fluxcli.acquisition.CalibrationCapture`), with the exposures and EM gains read
    back from the camera; gain-off means EM gain 1.  All PTC pairs share one light source,
    so the gain-on and gain-off signals are compared per second of exposure (the EM gain)."""
    key = f"calibrate.capture ({cal.path})"
    ptc = [R.PTCLevel(frames, exposure_s, gain > 1.0, EVEN_LIGHT) for frames, exposure_s, gain in cal.ptc]
    darks = [(frames, exposure_s, gain > 1.0) for frames, exposure_s, gain in cal.darks]
    if sum(not lv.em_gain_on for lv in ptc) < 2:
        raise UserError(f"{key}: the capture holds {sum(not lv.em_gain_on for lv in ptc)} gain-off photon-transfer "
                        "exposure(s); electrons per count need two or more (capture.calibration.ptc.exposures_off_s).")
    ctx.say(f"calibrate: radiometric frames from {cal.path}: {len(cal.bias)} bias, "
            f"{sum(len(d[0]) for d in darks)} dark, {0 if cal.flats is None else len(cal.flats)} flat, "
            f"{sum(len(lv.frames) for lv in ptc)} photon-transfer")
    return _calibrate(key, ctx, bias=cal.bias, ptc=ptc, darks=darks or None, flats=cal.flats,
                      max_counts=float(2**bit_depth - 1))


def counts_in(im, rig) -> bool | None:
    """Whether reconstruct turns counts into photons: True for a real camera's counts (a capture
    of a real camera, image files in counts), False for a simulated camera's capture (its QE is
    the simulation's own), None when its images are photons already.  ``im``: reconstruct.images
    (None: simulated images); ``rig``: the config's ``rig`` section or None."""
    if isinstance(im, C.CaptureSource):
        return not (rig is None or rig.camera is None or rig.camera.backend == "simulated")
    if isinstance(im, C.ImageFiles) and im.units == "counts":
        return True
    return None


def assumed_qe_warning(system: C.System | None, stage: str, *, real_counts: bool | None = True) -> str | None:
    """The one-line warning of a stage that turns counts into photons when the quantum efficiency
    is assumed: camera.yaml's ``camera.assumed`` says so, or (``real_counts``: a real camera's
    counts) the config gives no value and fluxmap's default is used.  None: nothing to warn.
    ``system``: the config's ``system`` section."""
    if system is None or real_counts is None:
        return None
    cam = system.camera
    qe = cam.sensor.quantum_efficiency
    why = cam.assumed.get("quantum_efficiency")
    if why is None and real_counts and "quantum_efficiency" not in cam.sensor.model_fields_set:
        why = f"fluxmap default {qe:g}, not measured — set system.camera.sensor.quantum_efficiency from the datasheet"
    if why is None:
        return None
    return (f"{stage}: warning: quantum_efficiency {qe:g} is assumed ({why}); every photon number scales "
            "with 1/QE")


def summary_rows(result: R.RadiometricResult) -> list[list[str]]:
    """Rows (name with unit, value, sigma) of the measured scalars, for a table."""
    rows = []
    for name, unit in SCALARS.items():
        value = getattr(result, name)
        if value is not None:
            sigma = getattr(result, f"{name}_sigma")
            rows.append([f"{name} ({unit})", f"{value:.5g}", f"{sigma:.2g}" if sigma is not None else "-"])
    return rows


def read_radiometric_maps(path: Path, key: str, shape: tuple[int, int]) -> dict[str, np.ndarray | None]:
    """The bias, dark and flat maps of ``<path>:/radiometric``, checked against ``shape``.

    Parameters
    ----------
    path : Path
        A calibration.h5 written by ``fluxmap calibrate`` with radiometric inputs.
    key : str
        The config key that named ``path`` (for messages).
    shape : (ny, nx)
        Size of the images the maps will be applied to.

    Returns
    -------
    dict
        ``bias_counts_map``, ``dark_e_per_s_map``, ``flat_map``: arrays (ny, nx) or None
        when that map was not measured.
    """
    from ..artefacts.radiometric import read_maps

    try:
        maps = read_maps(path, GROUP, tuple(MAPS))
    except UserError as e:
        raise UserError(f"{key}: {e}") from None
    except (OSError, FileNotFoundError) as e:
        reason = ("it is a folder, not a calibration.h5" if Path(path).is_dir() else "it does not exist"
                  if not Path(path).is_file() else f"it is not a readable HDF5 file ({e})")
        raise UserError(f"{key}: cannot read {path}: {reason}.") from None
    if maps is None:
        raise UserError(f"{key}: {path} holds no /{GROUP} group; run 'fluxmap calibrate' with "
                        f"{KEY} inputs to make one.")
    for name, arr in maps.items():
        if arr is not None and (arr.ndim != 2 or not np.all(np.isfinite(arr))):
            raise UserError(f"{key}: the {name} in {path} is not a 2-D map of finite numbers; calibrate again.")
        if arr is not None and arr.shape != tuple(shape):
            raise UserError(f"{key}: the {name} in {path} is {arr.shape[1]} x {arr.shape[0]} pixels; the images "
                            f"are {shape[1]} x {shape[0]}. Calibrate with frames of the same size and binning.")
    return maps
